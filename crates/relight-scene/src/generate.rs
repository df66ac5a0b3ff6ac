//! Procedural test scenes of any size: a Sponza-like atrium, and in
//! [`variants`] rooms and buildings modelled the many ways real models are.
//!
//! The atrium is a walled courtyard (30 m x 14 m) with two storeys of arcades
//! along its long sides (columns, elliptical arches, gallery slabs), coloured
//! cloth banners hanging in front of the arcades, and an open roof over the
//! courtyard. A directional sun shines in through the roof, a weak point light
//! fills the ground floor, and the camera looks along the courtyard, so most
//! of what it sees is lit indirectly.
//!
//! Design choices:
//! - Every surface is a parametric grid, so one tessellation level `n`
//!   scales columns (sides and rings), arches (segments) and banners (cloth
//!   cells) together, roughly as `n^2`.
//! - The triangle budget is met in two steps: the largest `n` whose triangle
//!   count stays under three quarters of the target, then the floor tiling
//!   (repeated detail) takes the rest. The count is obtained by running the
//!   same builder in counting mode, so it can never drift from the geometry.
//! - Output is OBJ + MTL text (quads, which tobj triangulates), so generated
//!   scenes go through the same loader as hand-made ones. Everything depends
//!   only on the arguments: `seed` picks banner colours and cloth ripples.

use crate::SceneError;
use glam::Vec3;
use relight_core::Pcg32;
use std::f32::consts::{PI, TAU};
use std::fmt::Write as _;
use std::path::{Path, PathBuf};

pub mod variants;

/// Smallest and largest budgets the generator accepts.
pub const ATRIUM_MIN_TRIANGLES: usize = 5_000;
pub const ATRIUM_MAX_TRIANGLES: usize = 20_000_000;

/// Seed used by [`write_atrium`].
pub const ATRIUM_DEFAULT_SEED: u64 = 0x5EED_A791;

/// The generated files, as text.
#[derive(Clone, Debug)]
pub struct Atrium {
    /// Wavefront OBJ; names `atrium.mtl`.
    pub obj: String,
    pub mtl: String,
    /// Scene file; names `atrium.obj`.
    pub scene_toml: String,
    /// Triangles after tobj triangulates the quads.
    pub triangle_count: usize,
}

/// Generates an atrium with about `target_triangles` triangles (within a few
/// percent for budgets from 10k up).
pub fn atrium(target_triangles: usize, seed: u64) -> Result<Atrium, SceneError> {
    if !(ATRIUM_MIN_TRIANGLES..=ATRIUM_MAX_TRIANGLES).contains(&target_triangles) {
        return Err(SceneError::InvalidArgument {
            message: format!(
                "atrium: {target_triangles} triangles requested; choose between {ATRIUM_MIN_TRIANGLES} and {ATRIUM_MAX_TRIANGLES}"
            ),
        });
    }
    let detail = choose_detail(target_triangles, seed);
    let mut builder = ObjBuilder::new(false);
    build_atrium(&mut builder, &detail, seed);
    Ok(Atrium {
        obj: builder.text,
        mtl: atrium_mtl(),
        scene_toml: ATRIUM_SCENE.to_string(),
        triangle_count: builder.triangles,
    })
}

/// OBJ faces (no materials) of a square ground of two triangles,
/// `ground_side` metres across, under an open-topped room of four wall
/// quads facing in, `room` = [width, height, depth] centred on the origin:
/// a building whose ground plane reaches far out, in small.
pub fn ground_and_room_obj(ground_side: f32, [width, height, depth]: [f32; 3]) -> String {
    let half = ground_side / 2.0;
    let mut obj = String::new();
    for (x, z) in [(-half, -half), (-half, half), (half, half), (half, -half)] {
        obj.push_str(&format!("v {x} 0 {z}\n"));
    }
    obj.push_str("f 1 2 3 4\n");
    let (x, z) = (width / 2.0, depth / 2.0);
    let corners = [(-x, -z), (x, -z), (x, z), (-x, z)];
    for side in 0..4 {
        let ((x0, z0), (x1, z1)) = (corners[side], corners[(side + 1) % 4]);
        let base = 5 + side * 4;
        obj.push_str(&format!(
            "v {x0} 0 {z0}\nv {x1} 0 {z1}\nv {x1} {height} {z1}\nv {x0} {height} {z0}\nf {} {} {} {}\n",
            base,
            base + 3,
            base + 2,
            base + 1
        ));
    }
    obj
}

/// Loads [`ground_and_room_obj`] (120 m of ground, a 6 x 3 x 8 m room)
/// with `scene_tail` in its scene file ([`load_obj_scene`]): the ground is
/// cut into rings of coarser lightmap texels, as a user's file would be.
pub fn load_ground_and_room(scene_tail: &str) -> Result<crate::Scene, SceneError> {
    load_obj_scene(&ground_and_room_obj(120.0, [6.0, 3.0, 8.0]), scene_tail)
}

/// OBJ text of quads, each wound to face the way it is asked to.
#[derive(Default)]
struct QuadObj {
    text: String,
    vertices: usize,
}

impl QuadObj {
    fn quad(&mut self, corners: [Vec3; 4], facing: Vec3) {
        let winding = (corners[1] - corners[0]).cross(corners[2] - corners[0]);
        let order: [usize; 4] = if winding.dot(facing) > 0.0 {
            [0, 1, 2, 3]
        } else {
            [0, 3, 2, 1]
        };
        for corner in corners {
            let _ = writeln!(self.text, "v {} {} {}", corner.x, corner.y, corner.z);
        }
        let index = |slot: usize| self.vertices + order[slot] + 1;
        let face = format!("f {} {} {} {}", index(0), index(1), index(2), index(3));
        let _ = writeln!(self.text, "{face}");
        self.vertices += 4;
    }

    /// A horizontal quad over x in `xs`, z in `zs` at height `y`.
    fn level(&mut self, xs: [f32; 2], y: f32, zs: [f32; 2], facing: Vec3) {
        self.quad(
            [
                Vec3::new(xs[0], y, zs[0]),
                Vec3::new(xs[0], y, zs[1]),
                Vec3::new(xs[1], y, zs[1]),
                Vec3::new(xs[1], y, zs[0]),
            ],
            facing,
        );
    }

    /// An axis-aligned box of outward faces from `low` to `high`, with or
    /// without its bottom face.
    fn cuboid(&mut self, low: Vec3, high: Vec3, bottom: bool) {
        let centre = (low + high) / 2.0;
        for axis in 0..3 {
            for (side, at) in [(-1.0f32, low[axis]), (1.0, high[axis])] {
                if axis == 1 && side < 0.0 && !bottom {
                    continue;
                }
                let (a, b) = ((axis + 1) % 3, (axis + 2) % 3);
                let corner = |u: f32, v: f32| {
                    let mut point = centre;
                    point[axis] = at;
                    point[a] = u;
                    point[b] = v;
                    point
                };
                let mut facing = Vec3::ZERO;
                facing[axis] = side;
                self.quad(
                    [
                        corner(low[a], low[b]),
                        corner(high[a], low[b]),
                        corner(high[a], high[b]),
                        corner(low[a], high[b]),
                    ],
                    facing,
                );
            }
        }
    }

    /// A closed room, `[width, height, depth]` with its floor at y = 0 and
    /// centred on x and z, of single planes facing in: the floor, then
    /// [`Self::walls_and_ceiling`].
    fn closed_room(size: [f32; 3]) -> Self {
        let (x, z) = (size[0] / 2.0, size[2] / 2.0);
        let mut obj = Self::default();
        obj.level([-x, x], 0.0, [-z, z], Vec3::Y);
        obj.walls_and_ceiling(size);
        obj
    }

    /// The four walls and the ceiling of a room, `[width, height, depth]`
    /// with its floor at y = 0 and centred on x and z, facing in.
    fn walls_and_ceiling(&mut self, [width, height, depth]: [f32; 3]) {
        let (x, z) = (width / 2.0, depth / 2.0);
        self.level([-x, x], height, [-z, z], -Vec3::Y);
        let corners = [(-x, -z), (x, -z), (x, z), (-x, z)];
        for side in 0..4 {
            let ((x0, z0), (x1, z1)) = (corners[side], corners[(side + 1) % 4]);
            let inward = -Vec3::new(x0 + x1, 0.0, z0 + z1).normalize();
            self.quad(
                [
                    Vec3::new(x0, 0.0, z0),
                    Vec3::new(x1, 0.0, z1),
                    Vec3::new(x1, height, z1),
                    Vec3::new(x0, height, z0),
                ],
                inward,
            );
        }
    }
}

/// The room of the generated test rooms below: [width, height, depth].
pub const TEST_ROOM: [f32; 3] = [4.0, 2.5, 4.0];

/// OBJ faces (no materials) of a closed [`TEST_ROOM`] of single planes
/// facing in, its floor at y = 0 and centred on x and z; with
/// `second_ceiling` = Some(gap), a second ceiling `gap` metres above the
/// room's own and facing down like it.
///
/// Real models lay such hidden layers behind visible surfaces (the
/// classroom's ceiling panels 2.9 cm under its ceiling), and nobody sees
/// the upper one: it faces the back of the lower.
pub fn room_with_second_ceiling_obj(second_ceiling: Option<f32>) -> String {
    let [width, height, depth] = TEST_ROOM;
    let (x, z) = (width / 2.0, depth / 2.0);
    let mut obj = QuadObj::closed_room(TEST_ROOM);
    if let Some(gap) = second_ceiling {
        obj.level([-x, x], height + gap, [-z, z], -Vec3::Y);
    }
    obj.text
}

/// OBJ faces (no materials) of a closed room `size` metres (width, height,
/// depth) of single planes facing in, its floor at y = 0 and centred on x
/// and z: forty metres long, a plainly modelled hall.
pub fn closed_room_obj(size: [f32; 3]) -> String {
    QuadObj::closed_room(size).text
}

/// OBJ faces (no materials) of a closed [`TEST_ROOM`] of single planes
/// facing in whose floor runs on `beyond` metres past its +x wall, under
/// it, into the open: as modelling tools leave a floor drawn before the
/// walls. A lightmap texel on the floor can straddle that wall.
pub fn room_on_a_longer_floor_obj(beyond: f32) -> String {
    let [width, _, depth] = TEST_ROOM;
    let (x, z) = (width / 2.0, depth / 2.0);
    let mut obj = QuadObj::default();
    obj.level([-x, x + beyond], 0.0, [-z, z], Vec3::Y);
    obj.walls_and_ceiling(TEST_ROOM);
    obj.text
}

/// An object of [`room_with_objects_on_its_floor_obj`]: its footprint on
/// the floor, `[x0, x1]` by `[z0, z1]`.
pub type Footprint = [[f32; 2]; 2];

/// A box standing in a [`TEST_ROOM`]: its footprint, its bottom's height,
/// whether it has a bottom face, and its top's height.
type StandingBox = (Footprint, f32, bool, f32);

/// The four boxes of [`room_with_objects_on_its_floor_obj`].
const FOUR_STANDING_BOXES: [StandingBox; 4] = [
    ([[-1.47, -0.88], [-1.37, -0.83]], 0.007, false, 0.7),
    ([[0.61, 1.34], [-1.29, -0.87]], 0.0, true, 0.5),
    ([[-1.27, -0.74], [0.72, 1.38]], -0.015, false, 0.9),
    ([[0.83, 1.22], [0.79, 1.46]], -0.02, true, 0.4),
];

/// OBJ faces (no materials) of a closed [`TEST_ROOM`] of single planes
/// facing in, with four boxes of outward faces on its floor as real models
/// stand them: an open-bottomed box 7 mm above the floor, a box with a
/// bottom flush with it, an open-bottomed box 15 mm into it and a box with
/// a bottom 20 mm into it, one in each quarter of the room. Returns the
/// boxes' footprints with the text.
pub fn room_with_objects_on_its_floor_obj() -> (String, Vec<Footprint>) {
    room_with_standing_boxes_obj(&FOUR_STANDING_BOXES)
}

/// [`room_with_objects_on_its_floor_obj`] with a fifth box in the middle
/// of the room: one with a bottom face `gap` above the floor, as a model's
/// furniture often floats a few millimetres over it.
pub fn room_with_a_raised_bottomed_box_obj(gap: f32) -> (String, Vec<Footprint>) {
    let mut boxes = FOUR_STANDING_BOXES.to_vec();
    boxes.push(([[-0.3, 0.3], [-0.3, 0.3]], gap, true, 0.45));
    room_with_standing_boxes_obj(&boxes)
}

fn room_with_standing_boxes_obj(boxes: &[StandingBox]) -> (String, Vec<Footprint>) {
    let mut obj = QuadObj::closed_room(TEST_ROOM);
    for &([xs, zs], bottom, has_bottom, top) in boxes {
        obj.cuboid(
            Vec3::new(xs[0], bottom, zs[0]),
            Vec3::new(xs[1], top, zs[1]),
            has_bottom,
        );
    }
    (obj.text, boxes.iter().map(|entry| entry.0).collect())
}

/// OBJ faces (no materials) of a closed room of single planes facing in,
/// 6 x 2.5 x 4 m with its floor at y = 0 and centred on x and z, split
/// at x = 0 into two rooms by a partition `thickness` thick from floor to
/// ceiling: a box of outward faces standing on the one floor that runs
/// under it from room to room.
pub fn two_rooms_on_one_floor_obj(thickness: f32) -> String {
    let room = [6.0, 2.5, 4.0];
    let z = room[2] / 2.0;
    let mut obj = QuadObj::closed_room(room);
    let half = thickness / 2.0;
    obj.cuboid(
        Vec3::new(-half, 0.0, -z),
        Vec3::new(half, room[1], z),
        false,
    );
    obj.text
}

/// Writes `obj` as `mesh.obj` and a `scene.toml` naming it, followed by
/// `scene_tail`, into a temporary folder of its own, loads the scene and
/// removes the folder again (tests of several crates load such scenes,
/// and may run at once).
pub fn load_obj_scene(obj: &str, scene_tail: &str) -> Result<crate::Scene, SceneError> {
    static NEXT: std::sync::atomic::AtomicUsize = std::sync::atomic::AtomicUsize::new(0);
    let folder = std::env::temp_dir().join(format!(
        "relight-generated-{}-{}",
        std::process::id(),
        NEXT.fetch_add(1, std::sync::atomic::Ordering::Relaxed)
    ));
    let toml = format!("mesh = \"mesh.obj\"\n{scene_tail}");
    let scene = write_scene_files(
        &folder,
        &[("mesh.obj", &obj.to_string()), ("scene.toml", &toml)],
    )
    .and_then(|path| crate::load_scene(&path));
    let _ = std::fs::remove_dir_all(&folder);
    scene
}

/// Writes `atrium.obj`, `atrium.mtl` and `scene.toml` into `folder`
/// (created if needed) and returns the path of `scene.toml`.
pub fn write_atrium(folder: &Path, target_triangles: usize) -> Result<PathBuf, SceneError> {
    let atrium = atrium(target_triangles, ATRIUM_DEFAULT_SEED)?;
    write_scene_files(
        folder,
        &[
            ("atrium.obj", &atrium.obj),
            ("atrium.mtl", &atrium.mtl),
            ("scene.toml", &atrium.scene_toml),
        ],
    )
}

/// Writes each (file name, text) into `folder` (created if needed) and
/// returns the path of its `scene.toml`.
fn write_scene_files(folder: &Path, files: &[(&str, &String)]) -> Result<PathBuf, SceneError> {
    let io_error = |path: &Path| {
        let path = path.to_path_buf();
        move |error| SceneError::Write { path, error }
    };
    std::fs::create_dir_all(folder).map_err(io_error(folder))?;
    for (name, text) in files {
        let path = folder.join(name);
        std::fs::write(&path, text).map_err(io_error(&path))?;
    }
    Ok(folder.join("scene.toml"))
}

const ATRIUM_SCENE: &str = r#"# Procedural atrium generated by relight_scene::generate::atrium.
mesh = "atrium.obj"

[camera]
eye = [-13.5, 1.7, -1.5]
target = [10.0, 5.0, 1.0]
up = [0.0, 1.0, 0.0]
fov_y = 60.0
resolution = [640, 360]

# Sun through the open roof.
[[lights]]
kind = "directional"
direction = [0.35, -1.0, 0.25]
irradiance = [8.0, 7.4, 6.4]

# Weak fill light on the ground floor.
[[lights]]
kind = "point"
position = [0.0, 3.0, 0.0]
intensity = [1.5, 1.3, 1.0]

[environment]
radiance = [0.25, 0.32, 0.45]
"#;

/// Material names and their albedos (linear RGB) and Blinn-Phong exponents.
const MATERIALS: [(&str, [f32; 3], f32); 8] = [
    ("floor", [0.45, 0.42, 0.38], 10.0),
    ("wall", [0.62, 0.57, 0.50], 1.0),
    ("stone", [0.70, 0.67, 0.60], 4.0),
    ("column", [0.74, 0.71, 0.64], 8.0),
    ("slab", [0.58, 0.55, 0.50], 1.0),
    ("banner_red", [0.62, 0.07, 0.05], 1.0),
    ("banner_green", [0.10, 0.42, 0.12], 1.0),
    ("banner_blue", [0.07, 0.14, 0.52], 1.0),
];

fn atrium_mtl() -> String {
    let mut text = String::from("# Materials of the procedural atrium.\n");
    for (name, [red, green, blue], exponent) in MATERIALS {
        let _ = writeln!(
            text,
            "\nnewmtl {name}\nKd {red} {green} {blue}\nNs {exponent}"
        );
    }
    text
}

/// Tessellation of one atrium.
struct Detail {
    /// Common level `n` of columns, arches and banners.
    level: usize,
    floor_columns: usize,
    floor_rows: usize,
}

impl Detail {
    fn column_sides(&self) -> usize {
        6 + 3 * self.level
    }
    fn column_rings(&self) -> usize {
        self.level
    }
    fn arch_segments(&self) -> usize {
        4 + 2 * self.level
    }
    fn banner_cells(&self) -> (usize, usize) {
        (1 + self.level, 2 + 2 * self.level)
    }
}

fn count_triangles(detail: &Detail, seed: u64) -> usize {
    let mut counter = ObjBuilder::new(true);
    build_atrium(&mut counter, detail, seed);
    counter.triangles
}

fn choose_detail(target: usize, seed: u64) -> Detail {
    let without_floor = |level| Detail {
        level,
        floor_columns: 0,
        floor_rows: 0,
    };
    let budget = target * 3 / 4;
    let mut level = 1;
    while count_triangles(&without_floor(level + 1), seed) <= budget {
        level += 1;
    }
    let rest = target.saturating_sub(count_triangles(&without_floor(level), seed));
    let cells = (rest / 2).max(1) as f64;
    // Square-ish tiles over the 30 m x 14 m floor.
    let floor_columns = ((cells * COURT_HALF_LENGTH as f64 / COURT_HALF_WIDTH as f64)
        .sqrt()
        .round() as usize)
        .max(1);
    let floor_rows = ((cells / floor_columns as f64).round() as usize).max(1);
    Detail {
        level,
        floor_columns,
        floor_rows,
    }
}

/// Writes OBJ text, or only counts triangles (`counting`), for grids.
struct ObjBuilder {
    counting: bool,
    text: String,
    vertices: usize,
    triangles: usize,
}

impl ObjBuilder {
    fn new(counting: bool) -> Self {
        let mut text = String::new();
        if !counting {
            text.push_str("# Procedural atrium generated by relight_scene::generate::atrium.\nmtllib atrium.mtl\n");
        }
        Self {
            counting,
            text,
            vertices: 0,
            triangles: 0,
        }
    }

    fn material(&mut self, name: &str) {
        if !self.counting {
            let _ = writeln!(self.text, "usemtl {name}");
        }
    }

    /// A `columns` x `rows` grid of quads over `point(u, v)`, u and v in
    /// [0, 1]; the front face is the side of du x dv.
    fn grid(&mut self, columns: usize, rows: usize, point: impl Fn(f32, f32) -> Vec3) {
        self.triangles += 2 * columns * rows;
        if self.counting {
            return;
        }
        let first = self.vertices + 1;
        for row in 0..=rows {
            let v = row as f32 / rows as f32;
            for column in 0..=columns {
                let p = point(column as f32 / columns as f32, v);
                let _ = writeln!(self.text, "v {:.4} {:.4} {:.4}", p.x, p.y, p.z);
            }
        }
        self.vertices += (columns + 1) * (rows + 1);
        let stride = columns + 1;
        for row in 0..rows {
            for column in 0..columns {
                let a = first + row * stride + column;
                let _ = writeln!(
                    self.text,
                    "f {} {} {} {}",
                    a,
                    a + 1,
                    a + 1 + stride,
                    a + stride
                );
            }
        }
    }

    /// Axis-aligned box with outward-facing quads.
    fn cuboid(&mut self, low: Vec3, high: Vec3) {
        let size = high - low;
        let corner = |x: f32, y: f32, z: f32| low + size * Vec3::new(x, y, z);
        self.grid(1, 1, |u, v| corner(u, 0.0, v)); // bottom, -Y
        self.grid(1, 1, |u, v| corner(v, 1.0, u)); // top, +Y
        self.grid(1, 1, |u, v| corner(v, u, 0.0)); // -Z
        self.grid(1, 1, |u, v| corner(u, v, 1.0)); // +Z
        self.grid(1, 1, |u, v| corner(0.0, v, u)); // -X
        self.grid(1, 1, |u, v| corner(1.0, u, v)); // +X
    }
}

const COURT_HALF_LENGTH: f32 = 15.0;
const COURT_HALF_WIDTH: f32 = 7.0;
const WALL_HEIGHT: f32 = 16.0;
const WALL_THICKNESS: f32 = 0.5;
/// |z| of the arcade's column line.
const COLUMN_LINE: f32 = 4.5;
const COLUMN_SPACING: f32 = 3.0;
const COLUMNS_PER_ROW: usize = 9;
const COLUMN_RADIUS: f32 = 0.3;
const STOREY_HEIGHT: f32 = 6.0;
const SLAB_THICKNESS: f32 = 0.4;
const ARCH_DEPTH: f32 = 0.6;
const ARCH_RISE: f32 = 1.0;
/// Height of the arch springing above the storey floor.
const SPRINGING: f32 = 4.5;

fn build_atrium(builder: &mut ObjBuilder, detail: &Detail, seed: u64) {
    let (length, width) = (COURT_HALF_LENGTH, COURT_HALF_WIDTH);

    if detail.floor_columns > 0 {
        builder.material("floor");
        builder.grid(detail.floor_columns, detail.floor_rows, |u, v| {
            // du x dv must point up: u along z, v along x.
            Vec3::new(-length + 2.0 * length * v, 0.0, -width + 2.0 * width * u)
        });
    }

    builder.material("wall");
    let (outer_length, outer_width) = (length + WALL_THICKNESS, width + WALL_THICKNESS);
    builder.cuboid(
        Vec3::new(-outer_length, 0.0, width),
        Vec3::new(outer_length, WALL_HEIGHT, outer_width),
    );
    builder.cuboid(
        Vec3::new(-outer_length, 0.0, -outer_width),
        Vec3::new(outer_length, WALL_HEIGHT, -width),
    );
    builder.cuboid(
        Vec3::new(-outer_length, 0.0, -width),
        Vec3::new(-length, WALL_HEIGHT, width),
    );
    builder.cuboid(
        Vec3::new(length, 0.0, -width),
        Vec3::new(outer_length, WALL_HEIGHT, width),
    );

    let mut rng = Pcg32::new(seed, 0xA791);
    for storey in 0..2 {
        let floor_y = storey as f32 * (STOREY_HEIGHT + SLAB_THICKNESS);
        let top_y = floor_y + STOREY_HEIGHT;
        for side in [-1.0f32, 1.0] {
            let line_z = side * COLUMN_LINE;
            builder.material("slab");
            let slab_inner = side * (COLUMN_LINE - ARCH_DEPTH * 0.5);
            let (z_low, z_high) = if side > 0.0 {
                (slab_inner, width)
            } else {
                (-width, slab_inner)
            };
            builder.cuboid(
                Vec3::new(-length, top_y, z_low),
                Vec3::new(length, top_y + SLAB_THICKNESS, z_high),
            );
            let first_x = -COLUMN_SPACING * (COLUMNS_PER_ROW - 1) as f32 * 0.5;
            for column in 0..COLUMNS_PER_ROW {
                let x = first_x + column as f32 * COLUMN_SPACING;
                build_column(builder, detail, Vec3::new(x, floor_y, line_z));
            }
            builder.material("stone");
            for bay in 0..COLUMNS_PER_ROW - 1 {
                let centre_x = first_x + (bay as f32 + 0.5) * COLUMN_SPACING;
                build_arch(builder, detail, Vec3::new(centre_x, floor_y, line_z), top_y);
            }
            for bay in (1..COLUMNS_PER_ROW - 1).step_by(2) {
                let centre_x = first_x + (bay as f32 + 0.5) * COLUMN_SPACING;
                let colour =
                    ["banner_red", "banner_green", "banner_blue"][(rng.next_u32() % 3) as usize];
                let phase = rng.next_f32() * TAU;
                builder.material(colour);
                let hang_z = side * (COLUMN_LINE - ARCH_DEPTH * 0.5 - 0.35);
                build_banner(
                    builder,
                    detail,
                    Vec3::new(centre_x, top_y + 0.3, hang_z),
                    side,
                    phase,
                );
            }
        }
    }
}

/// Base, shaft, capital and the pier that carries the arches, standing at
/// `foot` (centre of the column's base at floor level).
fn build_column(builder: &mut ObjBuilder, detail: &Detail, foot: Vec3) {
    builder.material("stone");
    let plinth = Vec3::new(COLUMN_RADIUS + 0.1, 0.0, COLUMN_RADIUS + 0.1);
    builder.cuboid(foot - plinth, foot + plinth + Vec3::Y * 0.3);
    let capital_low = foot + Vec3::Y * (SPRINGING - 0.3);
    builder.cuboid(capital_low - plinth, capital_low + plinth + Vec3::Y * 0.3);
    let pier = Vec3::new(COLUMN_RADIUS, 0.0, ARCH_DEPTH * 0.5);
    builder.cuboid(
        foot + Vec3::Y * SPRINGING - pier,
        foot + pier + Vec3::Y * STOREY_HEIGHT,
    );
    builder.material("column");
    let (bottom, top) = (0.3, SPRINGING - 0.3);
    builder.grid(detail.column_sides(), detail.column_rings(), |u, v| {
        let angle = -TAU * u;
        // A slight entasis (swelling) makes the rings visible in renders.
        let radius = COLUMN_RADIUS * (1.0 + 0.04 * (PI * v).sin());
        foot + Vec3::new(
            radius * angle.cos(),
            bottom + (top - bottom) * v,
            radius * angle.sin(),
        )
    });
}

/// One elliptical arch between two piers: the curved underside (intrados)
/// and the two spandrel faces up to the slab at `top_y`.
fn build_arch(builder: &mut ObjBuilder, detail: &Detail, centre: Vec3, top_y: f32) {
    let half_span = COLUMN_SPACING * 0.5 - COLUMN_RADIUS;
    let spring_y = centre.y + SPRINGING;
    let arc = move |t: f32| {
        let angle = PI * (1.0 - t);
        Vec3::new(
            centre.x + half_span * angle.cos(),
            spring_y + ARCH_RISE * angle.sin(),
            centre.z,
        )
    };
    let segments = detail.arch_segments();
    let half_depth = ARCH_DEPTH * 0.5;
    // The intrados faces down into the opening: du runs along the arc
    // from the left springing, dv along +Z.
    builder.grid(segments, 1, |u, v| {
        arc(u) + Vec3::Z * (2.0 * half_depth * v - half_depth)
    });
    for face_z in [-half_depth, half_depth] {
        builder.grid(segments, 1, |u, v| {
            let low = arc(u);
            let point = low.lerp(Vec3::new(low.x, top_y, low.z), v);
            // Along the arc du x dv (up) points +Z: the -Z face mirrors
            // the grid so that it points away from the arch too.
            let point = if face_z > 0.0 {
                point
            } else {
                arc_mirror(point, centre.x)
            };
            point + Vec3::Z * face_z
        });
    }
}

/// Mirrors a point of an arch about its vertical axis, which reverses the
/// grid's winding for the back spandrel.
fn arc_mirror(point: Vec3, axis_x: f32) -> Vec3 {
    Vec3::new(2.0 * axis_x - point.x, point.y, point.z)
}

/// A rippled cloth banner hanging from `top` (its top centre).
fn build_banner(builder: &mut ObjBuilder, detail: &Detail, top: Vec3, side: f32, phase: f32) {
    let (columns, rows) = detail.banner_cells();
    let (half_width, length) = (0.7, 3.0);
    builder.grid(columns, rows, |u, v| {
        let ripple = 0.06 * (TAU * (1.5 * v + 0.5 * u) + phase).sin() * v;
        Vec3::new(
            top.x + half_width * (2.0 * u - 1.0) * side,
            top.y - length * v,
            top.z - side * ripple,
        )
    });
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn counting_matches_writing() {
        let detail = choose_detail(12_000, 7);
        let mut writer = ObjBuilder::new(false);
        build_atrium(&mut writer, &detail, 7);
        assert_eq!(count_triangles(&detail, 7), writer.triangles);
        let faces = writer
            .text
            .lines()
            .filter(|line| line.starts_with("f "))
            .count();
        assert_eq!(faces * 2, writer.triangles);
    }

    /// Every face of the atrium points out of its solid, so that from the
    /// open court and the arcades a ray meets only front faces. The scene
    /// contract lets back faces reflect too, but the atrium is the stand-in
    /// for a well-made model: with the cuboids' +-X faces and the arches
    /// wound inward, PIC put no surfels on the court's end walls (27 % of
    /// them dropped as enclosed) and measured 0.57x of the path tracer's
    /// light. Banners are single-sided cloth and may be seen from behind.
    #[test]
    fn faces_point_out_of_their_solids() {
        let detail = choose_detail(12_000, 7);
        let mut writer = ObjBuilder::new(false);
        build_atrium(&mut writer, &detail, 7);
        let mut vertices = Vec::new();
        let mut triangles = Vec::new();
        let mut banner = false;
        for line in writer.text.lines() {
            let mut words = line.split_whitespace();
            match words.next() {
                Some("v") => {
                    let xyz: Vec<f32> = words.map(|word| word.parse().unwrap()).collect();
                    vertices.push(Vec3::new(xyz[0], xyz[1], xyz[2]));
                }
                Some("usemtl") => banner = words.next().unwrap().starts_with("banner"),
                Some("f") if !banner => {
                    let corners: Vec<Vec3> = words
                        .map(|word| vertices[word.parse::<usize>().unwrap() - 1])
                        .collect();
                    triangles.push([corners[0], corners[1], corners[2]]);
                    triangles.push([corners[0], corners[2], corners[3]]);
                }
                _ => {}
            }
        }
        // Nearest hit along the ray: its triangle's normal against the ray.
        let nearest_is_back = |origin: Vec3, direction: Vec3| -> Option<bool> {
            let mut best: Option<(f32, bool)> = None;
            for [a, b, c] in &triangles {
                let (edge1, edge2) = (*b - *a, *c - *a);
                let p = direction.cross(edge2);
                let determinant = edge1.dot(p);
                if determinant.abs() < 1e-9 {
                    continue;
                }
                let t_vector = origin - *a;
                let u = t_vector.dot(p) / determinant;
                let q = t_vector.cross(edge1);
                let v = direction.dot(q) / determinant;
                let t = edge2.dot(q) / determinant;
                if u < 0.0 || v < 0.0 || u + v > 1.0 || t <= 1e-4 {
                    continue;
                }
                if best.is_none_or(|(nearest, _)| t < nearest) {
                    best = Some((t, edge1.cross(edge2).dot(direction) > 0.0));
                }
            }
            best.map(|(_, back)| back)
        };
        let origins = [
            Vec3::new(0.0, 3.0, 0.0),
            Vec3::new(-9.0, 10.0, 1.0),
            Vec3::new(1.5, 2.0, 5.8),
            Vec3::new(-4.5, 8.5, -5.8),
        ];
        let directions = 400;
        let (mut hits, mut back_hits) = (0, 0);
        for origin in origins {
            for index in 0..directions {
                // A Fibonacci sphere.
                let z = 1.0 - 2.0 * (index as f32 + 0.5) / directions as f32;
                let radius = (1.0 - z * z).sqrt();
                let angle = index as f32 * PI * (3.0 - 5f32.sqrt());
                let direction = Vec3::new(radius * angle.cos(), z, radius * angle.sin());
                if let Some(back) = nearest_is_back(origin, direction) {
                    hits += 1;
                    back_hits += back as usize;
                }
            }
        }
        assert!(hits > 1000, "{hits}");
        assert_eq!(back_hits, 0, "{back_hits} of {hits} rays met a back face");
    }
}
