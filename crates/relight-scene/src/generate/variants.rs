//! Generated scene variants that differ in how a building is modelled, so
//! that a technique's robustness is measured over many models rather than
//! tuned on one.
//!
//! Every variant is a room, two rooms joined by a doorway, or a large hall,
//! and draws independently, from its seed and index alone:
//! - the shell: one closed shell around all rooms, or a closed box per room
//!   (two coplanar walls back to back, or with a gap and a door frame);
//! - the walls: single inward-facing planes, thick solids with reveals at
//!   every opening, or planes that run past each other at the corners (an
//!   open, non-manifold mesh, as modelling tools leave them);
//! - the tessellation: one quad per wall piece, or fine triangles;
//! - objects standing on floors: with or without a bottom face, flush with
//!   the floor, slightly above it or slightly into it, free, against a wall
//!   or in a corner;
//! - the lights: point or spot lights anywhere, 0.05-0.3 m from a wall, in a
//!   corner, or inside a shade open on one or two sides; a low sun through
//!   small windows into a hall;
//! - albedos from 0.1 to 0.9 and rooms from 2 m to 50 m.
//!
//! Each variant is valid for the path tracer by construction: every light
//! lies in open space (in a room, outside every object, inside its shade's
//! opening), which the tests check against the loaded geometry. Output is OBJ
//! and MTL text, so variants go through the same loader as users' files. The
//! [`Variant::feet`] record where objects meet floors, so that a study can
//! look at the image tiles around them, where contact halos show.

use crate::SceneError;
use glam::{Vec2, Vec3};
use relight_core::Pcg32;
use std::fmt::Write as _;
use std::path::{Path, PathBuf};

/// Seed used when none is given.
pub const VARIANTS_DEFAULT_SEED: u64 = 0x5EED_0039;

/// Largest number of variants one call writes.
pub const VARIANTS_MAX_COUNT: usize = 10_000;

/// What kind of building a variant is: what its error is judged against.
#[derive(Clone, Copy, Debug, PartialEq, Eq, PartialOrd, Ord, Hash)]
pub enum VariantKind {
    /// One room lit from inside, 2-8 m.
    Room,
    /// Two rooms joined by a doorway; only one has a light and the camera
    /// stands in the other, so most of what it sees has bounced twice.
    TwoRooms,
    /// A hall of 10-50 m lit by a low sun through small windows.
    Hall,
}

impl VariantKind {
    pub const ALL: [VariantKind; 3] = [VariantKind::Room, VariantKind::TwoRooms, VariantKind::Hall];

    pub fn name(self) -> &'static str {
        match self {
            VariantKind::Room => "room",
            VariantKind::TwoRooms => "two-rooms",
            VariantKind::Hall => "hall",
        }
    }

    /// Closed rooms are held to the boxes' bounds, halls to the large
    /// interiors' (issue tables: rooms as boxes, halls as real interiors).
    pub fn is_large(self) -> bool {
        self == VariantKind::Hall
    }
}

/// How the rooms' enclosure is built.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Shell {
    /// One closed shell around every room, partition walls inside it.
    OneShell,
    /// A closed box per room; neighbouring boxes touch or leave a gap.
    BoxPerRoom,
}

/// How one wall is modelled.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Walls {
    /// Single planes facing into the room.
    Planes,
    /// Thick solids: inner and outer faces, reveals around openings.
    Solids,
    /// Single planes that run past each other at the corners.
    Overlapping,
}

/// How surfaces are cut into triangles.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Tessellation {
    /// As few quads as the openings allow.
    Quads,
    /// Cells of about `cell` metres, each two triangles, diagonals alternating.
    Fine { cell: f32 },
}

/// Where an object stands relative to the floor.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Contact {
    Flush,
    /// Its bottom this many metres above the floor.
    Above(f32),
    /// Its bottom this many metres below the floor.
    Into(f32),
}

/// Where a light is put.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum LightPlace {
    Free,
    /// This many metres from one wall.
    NearWall(f32),
    /// This many metres from two walls.
    Corner(f32),
    /// Inside a shade open on this many sides (1: below; 2: below and above).
    Shaded(u32),
    /// A sun through windows.
    Sun,
}

/// Where one object meets a floor: its footprint in x and z and the floor's
/// height, for measuring the image around it.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Foot {
    pub low: Vec2,
    pub high: Vec2,
    pub floor: f32,
    pub has_bottom: bool,
    pub contact: Contact,
}

/// One generated variant: files as text, and what it is made of.
#[derive(Clone, Debug)]
pub struct Variant {
    pub index: usize,
    pub kind: VariantKind,
    pub shell: Shell,
    pub walls: Walls,
    pub tessellation: Tessellation,
    pub lights: Vec<LightPlace>,
    /// Albedo of the walls, 0.1-0.9.
    pub albedo: f32,
    /// Longest side of the building in metres.
    pub size: f32,
    pub feet: Vec<Foot>,
    /// The camera stands in a room with no light of its own.
    pub unlit_view: bool,
    pub obj: String,
    pub mtl: String,
    pub scene_toml: String,
    pub triangle_count: usize,
}

impl Variant {
    /// Writes `mesh.obj`, `mesh.mtl` and `scene.toml` into `folder`
    /// (created if needed) and returns the path of `scene.toml`.
    pub fn write(&self, folder: &Path) -> Result<PathBuf, SceneError> {
        super::write_scene_files(
            folder,
            &[
                ("mesh.obj", &self.obj),
                ("mesh.mtl", &self.mtl),
                ("scene.toml", &self.scene_toml),
            ],
        )
    }

    /// Folder name: index and kind, sortable.
    pub fn name(&self) -> String {
        format!("{:03}-{}", self.index, self.kind.name())
    }

    /// One line naming every modelling choice.
    pub fn description(&self) -> String {
        let tessellation = match self.tessellation {
            Tessellation::Quads => "quads".to_string(),
            Tessellation::Fine { cell } => format!("fine {cell:.2} m"),
        };
        let lights: Vec<String> = self.lights.iter().map(|light| light.describe()).collect();
        let feet: Vec<String> = self.feet.iter().map(|foot| foot.describe()).collect();
        format!(
            "{} {:.1} m, {:?}, {:?} walls, {tessellation}, albedo {:.2}; lights: {}; objects: {}",
            self.kind.name(),
            self.size,
            self.shell,
            self.walls,
            self.albedo,
            lights.join(", "),
            if feet.is_empty() {
                "none".to_string()
            } else {
                feet.join(", ")
            }
        )
    }
}

impl LightPlace {
    fn describe(&self) -> String {
        match self {
            LightPlace::Free => "free".into(),
            LightPlace::NearWall(distance) => format!("{distance:.2} m from a wall"),
            LightPlace::Corner(distance) => format!("{distance:.2} m from a corner"),
            LightPlace::Shaded(open) => format!("in a shade open on {open} side(s)"),
            LightPlace::Sun => "sun through windows".into(),
        }
    }
}

impl Foot {
    fn describe(&self) -> String {
        let contact = match self.contact {
            Contact::Flush => "flush".to_string(),
            Contact::Above(gap) => format!("{:.0} mm above", gap * 1000.0),
            Contact::Into(depth) => format!("{:.0} mm into", depth * 1000.0),
        };
        format!(
            "{} {contact}",
            if self.has_bottom {
                "box"
            } else {
                "open-bottomed box"
            }
        )
    }
}

/// Generates variant `index` of the family `seed`; the same pair always
/// gives the same bytes.
pub fn variant(seed: u64, index: usize) -> Variant {
    let mut rng = Random(Pcg32::new(seed, 0x0039_0000 + index as u64));
    let kind = VariantKind::ALL[index % VariantKind::ALL.len()];
    let shell = if rng.chance(0.5) {
        Shell::OneShell
    } else {
        Shell::BoxPerRoom
    };
    let walls = *rng.pick(&[Walls::Planes, Walls::Solids, Walls::Overlapping]);
    let albedo = rng.range(0.1, 0.9);
    let mut builder = Builder::default();
    let plan = match kind {
        VariantKind::Room => room(&mut rng, &mut builder, walls, albedo),
        VariantKind::TwoRooms => two_rooms(&mut rng, &mut builder, shell, walls, albedo),
        VariantKind::Hall => hall(&mut rng, &mut builder, walls, albedo),
    };
    let tessellation = if rng.chance(0.5) {
        Tessellation::Quads
    } else {
        // Fine enough to be "many triangles", coarse enough that a 50 m hall
        // stays under a few hundred thousand.
        Tessellation::Fine {
            cell: (plan.size / 60.0).max(rng.range(0.15, 0.4)),
        }
    };
    let (obj, triangle_count) = builder.obj(tessellation);
    Variant {
        index,
        kind,
        shell: if kind == VariantKind::TwoRooms {
            shell
        } else {
            Shell::OneShell
        },
        walls,
        tessellation,
        lights: plan.lights.iter().map(|light| light.place).collect(),
        albedo,
        size: plan.size,
        feet: plan.feet.clone(),
        unlit_view: kind == VariantKind::TwoRooms,
        scene_toml: plan.scene_toml(index, seed),
        mtl: builder.mtl(),
        obj,
        triangle_count,
    }
}

/// Writes variants `0..count` of family `seed` into `folder`, one
/// sub-folder each (`mesh.obj`, `mesh.mtl`, `scene.toml`), and an index
/// `variants.txt` with one line per variant; returns each scene file with
/// its variant.
pub fn write_variants(
    folder: &Path,
    seed: u64,
    count: usize,
) -> Result<Vec<(PathBuf, Variant)>, SceneError> {
    if !(1..=VARIANTS_MAX_COUNT).contains(&count) {
        return Err(SceneError::InvalidArgument {
            message: format!(
                "variants: {count} requested; choose between 1 and {VARIANTS_MAX_COUNT}"
            ),
        });
    }
    let mut written = Vec::with_capacity(count);
    let mut index_text = format!("# relight gen variants --seed {seed} --count {count}\n");
    for index in 0..count {
        let variant = variant(seed, index);
        let scene = variant.write(&folder.join(variant.name()))?;
        let _ = writeln!(
            index_text,
            "{}  {} triangles  {}",
            variant.name(),
            variant.triangle_count,
            variant.description()
        );
        written.push((scene, variant));
    }
    let index_path = folder.join("variants.txt");
    std::fs::write(&index_path, index_text).map_err(|error| SceneError::Write {
        path: index_path.clone(),
        error,
    })?;
    Ok(written)
}

struct Random(Pcg32);

impl Random {
    fn unit(&mut self) -> f32 {
        self.0.next_f32()
    }
    fn range(&mut self, low: f32, high: f32) -> f32 {
        low + (high - low) * self.unit()
    }
    fn chance(&mut self, probability: f32) -> bool {
        self.unit() < probability
    }
    fn below(&mut self, count: usize) -> usize {
        ((self.unit() * count as f32) as usize).min(count - 1)
    }
    fn pick<'a, T>(&mut self, items: &'a [T]) -> &'a T {
        &items[self.below(items.len())]
    }
}

/// An axis-aligned rectangle in a plane's two in-plane coordinates.
#[derive(Clone, Copy, Debug, PartialEq)]
struct Rect {
    low: Vec2,
    high: Vec2,
}

impl Rect {
    fn new(low: Vec2, high: Vec2) -> Self {
        Self { low, high }
    }
    fn contains(&self, point: Vec2) -> bool {
        point.cmpgt(self.low).all() && point.cmplt(self.high).all()
    }
}

/// A point from plane coordinates: `axis` is the plane's normal axis, `a`
/// runs along axis+1 and `b` along axis+2 (cyclic), so that a along x b
/// points along +axis.
fn on_plane(axis: usize, level: f32, a: f32, b: f32) -> Vec3 {
    let mut point = [0.0; 3];
    point[axis] = level;
    point[(axis + 1) % 3] = a;
    point[(axis + 2) % 3] = b;
    Vec3::from_array(point)
}

/// A planar quad before tessellation: corners in counter-clockwise order
/// seen from its front.
#[derive(Clone, Copy, Debug)]
struct Quad {
    corners: [Vec3; 4],
    material: usize,
}

#[derive(Default)]
struct Builder {
    quads: Vec<Quad>,
    materials: Vec<(String, [f32; 3])>,
}

impl Builder {
    /// A new material; its name gets the material's number, since MTL
    /// names must be unique (objects and shades recur).
    fn material(&mut self, name: &str, albedo: [f32; 3]) -> usize {
        let index = self.materials.len();
        self.materials.push((format!("{name}{index}"), albedo));
        index
    }

    /// A rectangle in the plane `axis = level`, facing +axis when
    /// `positive`, with `holes` (rectangles inside it) left open. The rest
    /// is cut into the fewest axis-aligned pieces the holes' edges allow.
    fn wall(
        &mut self,
        material: usize,
        axis: usize,
        level: f32,
        rect: Rect,
        holes: &[Rect],
        positive: bool,
    ) {
        let mut cuts_a = vec![rect.low.x, rect.high.x];
        let mut cuts_b = vec![rect.low.y, rect.high.y];
        for hole in holes {
            cuts_a.extend([hole.low.x, hole.high.x]);
            cuts_b.extend([hole.low.y, hole.high.y]);
        }
        for cuts in [&mut cuts_a, &mut cuts_b] {
            cuts.sort_by(f32::total_cmp);
            cuts.dedup_by(|a, b| (*a - *b).abs() < 1e-6);
        }
        cuts_a.retain(|a| (rect.low.x..=rect.high.x).contains(a));
        cuts_b.retain(|b| (rect.low.y..=rect.high.y).contains(b));
        for a in cuts_a.windows(2) {
            // Merge runs of solid cells along b into one piece.
            let mut start: Option<f32> = None;
            for b in cuts_b.windows(2) {
                let centre = Vec2::new((a[0] + a[1]) * 0.5, (b[0] + b[1]) * 0.5);
                let solid = !holes.iter().any(|hole| hole.contains(centre));
                match (solid, start) {
                    (true, None) => start = Some(b[0]),
                    (false, Some(from)) => {
                        self.piece(material, axis, level, [a[0], a[1]], [from, b[0]], positive);
                        start = None;
                    }
                    _ => {}
                }
            }
            if let Some(from) = start {
                self.piece(
                    material,
                    axis,
                    level,
                    [a[0], a[1]],
                    [from, rect.high.y],
                    positive,
                );
            }
        }
    }

    fn piece(
        &mut self,
        material: usize,
        axis: usize,
        level: f32,
        a: [f32; 2],
        b: [f32; 2],
        positive: bool,
    ) {
        let mut corners = [
            on_plane(axis, level, a[0], b[0]),
            on_plane(axis, level, a[1], b[0]),
            on_plane(axis, level, a[1], b[1]),
            on_plane(axis, level, a[0], b[1]),
        ];
        if !positive {
            corners.reverse();
        }
        self.quads.push(Quad { corners, material });
    }

    /// The four faces lining a rectangular opening through the planes
    /// `axis = from .. to`, facing into the opening.
    fn reveal(&mut self, material: usize, axis: usize, from: f32, to: f32, hole: Rect) {
        let (a_axis, b_axis) = ((axis + 1) % 3, (axis + 2) % 3);
        // Faces at a = low (facing +a), a = high (facing -a), b likewise.
        // In the plane a_axis = level, in-plane coordinates run along
        // a_axis+1 and a_axis+2, which are b_axis and axis.
        let span = |first_axis: usize, along: [f32; 2], across: [f32; 2]| {
            // Returns (a, b) ranges in the plane of `first_axis` ordering.
            if (first_axis + 1) % 3 == axis {
                (across, along)
            } else {
                (along, across)
            }
        };
        let depth = [from.min(to), from.max(to)];
        let (a, b) = span(a_axis, [hole.low.y, hole.high.y], depth);
        self.piece(material, a_axis, hole.low.x, a, b, true);
        self.piece(material, a_axis, hole.high.x, a, b, false);
        let (a, b) = span(b_axis, [hole.low.x, hole.high.x], depth);
        self.piece(material, b_axis, hole.low.y, a, b, true);
        self.piece(material, b_axis, hole.high.y, a, b, false);
    }

    /// An axis-aligned box of outward faces, optionally without its bottom
    /// (-y) face.
    fn cuboid(&mut self, material: usize, low: Vec3, high: Vec3, bottom: bool) {
        for axis in 0..3 {
            let rect = Rect::new(
                Vec2::new(low[(axis + 1) % 3], low[(axis + 2) % 3]),
                Vec2::new(high[(axis + 1) % 3], high[(axis + 2) % 3]),
            );
            if axis != 1 || bottom {
                self.wall(material, axis, low[axis], rect, &[], false);
            }
            self.wall(material, axis, high[axis], rect, &[], true);
        }
    }

    /// The inside of an axis-aligned box, `openings[face]` cut into each
    /// face (face = 2 * axis + side, side 1 the high one), modelled in
    /// `style`.
    fn enclosure(&mut self, style: &Style, low: Vec3, high: Vec3, openings: &[Vec<Rect>; 6]) {
        let Style {
            materials,
            walls,
            thickness,
            overhang,
        } = *style;
        for (face, holes) in openings.iter().enumerate() {
            let (axis, side) = (face / 2, face % 2);
            let material = match axis {
                1 if side == 0 => materials[1],
                1 => materials[2],
                _ => materials[0],
            };
            let (a, b) = ((axis + 1) % 3, (axis + 2) % 3);
            let grow = if walls == Walls::Overlapping {
                overhang
            } else {
                0.0
            };
            let rect = Rect::new(
                Vec2::new(low[a] - grow, low[b] - grow),
                Vec2::new(high[a] + grow, high[b] + grow),
            );
            let level = if side == 0 { low[axis] } else { high[axis] };
            // Inner faces face into the box: +axis on the low side.
            self.wall(material, axis, level, rect, holes, side == 0);
            if walls == Walls::Solids {
                let outer_level = if side == 0 {
                    level - thickness
                } else {
                    level + thickness
                };
                let outer = Rect::new(
                    Vec2::new(low[a] - thickness, low[b] - thickness),
                    Vec2::new(high[a] + thickness, high[b] + thickness),
                );
                self.wall(material, axis, outer_level, outer, holes, side == 1);
                for &hole in holes {
                    self.reveal(material, axis, level, outer_level, hole);
                }
            }
        }
    }

    /// A shade around a light at `centre`: four thin walls (1 cm solids)
    /// of half-size `half`, open below, and above too when `open_sides` is
    /// 2, a top otherwise; rims close the walls' thickness at each opening.
    fn shade(&mut self, material: usize, centre: Vec3, half: Vec3, open_sides: u32) {
        let thickness = 0.01;
        let low = centre - half;
        let high = centre + half;
        for face in 0..6 {
            let (axis, side) = (face / 2, face % 2);
            if axis == 1 && (side == 0 || open_sides >= 2) {
                continue;
            }
            let (a, b) = ((axis + 1) % 3, (axis + 2) % 3);
            let level = if side == 0 { low[axis] } else { high[axis] };
            let outer_level = if side == 0 {
                level - thickness
            } else {
                level + thickness
            };
            let inner = Rect::new(Vec2::new(low[a], low[b]), Vec2::new(high[a], high[b]));
            let outer = Rect::new(
                Vec2::new(low[a] - thickness, low[b] - thickness),
                Vec2::new(high[a] + thickness, high[b] + thickness),
            );
            self.wall(material, axis, level, inner, &[], side == 0);
            self.wall(material, axis, outer_level, outer, &[], side == 1);
        }
        // In the plane y = const, a runs along z and b along x.
        let ring_inner = Rect::new(Vec2::new(low.z, low.x), Vec2::new(high.z, high.x));
        let ring_outer = Rect::new(
            Vec2::new(low.z - thickness, low.x - thickness),
            Vec2::new(high.z + thickness, high.x + thickness),
        );
        self.wall(material, 1, low.y, ring_outer, &[ring_inner], false);
        if open_sides >= 2 {
            self.wall(material, 1, high.y, ring_outer, &[ring_inner], true);
        }
    }

    fn mtl(&self) -> String {
        let mut text = String::from("# Materials of a generated relight variant.\n");
        for (name, [red, green, blue]) in &self.materials {
            let _ = writeln!(text, "\nnewmtl {name}\nKd {red:.4} {green:.4} {blue:.4}");
        }
        text
    }

    /// OBJ text of every quad, in material order, and its triangle count.
    fn obj(&self, tessellation: Tessellation) -> (String, usize) {
        let mut text = String::from("# Generated relight variant.\nmtllib mesh.mtl\n");
        let mut vertices = 0usize;
        let mut triangles = 0usize;
        for (material, (name, _)) in self.materials.iter().enumerate() {
            let quads: Vec<&Quad> = self
                .quads
                .iter()
                .filter(|quad| quad.material == material)
                .collect();
            if quads.is_empty() {
                continue;
            }
            let _ = writeln!(text, "usemtl {name}");
            for quad in quads {
                let [p0, p1, p2, p3] = quad.corners;
                let (columns, rows) = match tessellation {
                    Tessellation::Quads => (1, 1),
                    Tessellation::Fine { cell } => (
                        (((p1 - p0).length() / cell).ceil() as usize).clamp(1, 400),
                        (((p3 - p0).length() / cell).ceil() as usize).clamp(1, 400),
                    ),
                };
                let first = vertices + 1;
                for row in 0..=rows {
                    let v = row as f32 / rows as f32;
                    for column in 0..=columns {
                        let u = column as f32 / columns as f32;
                        let p = p0.lerp(p1, u).lerp(p3.lerp(p2, u), v);
                        let _ = writeln!(text, "v {:.5} {:.5} {:.5}", p.x, p.y, p.z);
                    }
                }
                vertices += (columns + 1) * (rows + 1);
                let stride = columns + 1;
                for row in 0..rows {
                    for column in 0..columns {
                        let a = first + row * stride + column;
                        let (b, c, d) = (a + 1, a + 1 + stride, a + stride);
                        if columns == 1 && rows == 1 {
                            let _ = writeln!(text, "f {a} {b} {c} {d}");
                        } else if (row + column) % 2 == 0 {
                            let _ = writeln!(text, "f {a} {b} {c}\nf {a} {c} {d}");
                        } else {
                            let _ = writeln!(text, "f {a} {b} {d}\nf {b} {c} {d}");
                        }
                        triangles += 2;
                    }
                }
            }
        }
        (text, triangles)
    }
}

struct PlacedLight {
    place: LightPlace,
    toml: String,
}

struct Plan {
    size: f32,
    feet: Vec<Foot>,
    lights: Vec<PlacedLight>,
    eye: Vec3,
    target: Vec3,
    environment: f32,
}

impl Plan {
    fn scene_toml(&self, index: usize, seed: u64) -> String {
        let mut text = format!(
            "# relight gen variants --seed {seed}: variant {index}.\nmesh = \"mesh.obj\"\n\n[camera]\neye = {}\ntarget = {}\nup = [0.0, 1.0, 0.0]\nfov_y = 65.0\nresolution = [320, 240]\n",
            array(self.eye),
            array(self.target)
        );
        for light in &self.lights {
            text.push('\n');
            text.push_str(&light.toml);
        }
        let sky = self.environment;
        let _ = write!(
            text,
            "\n[environment]\nradiance = [{:.3}, {:.3}, {:.3}]\n",
            sky * 0.8,
            sky * 0.9,
            sky
        );
        text
    }
}

fn array(value: Vec3) -> String {
    format!("[{:.4}, {:.4}, {:.4}]", value.x, value.y, value.z)
}

/// Wall, floor and ceiling materials of albedo about `albedo`, each with a
/// slight tint, and now and then one coloured wall.
fn room_materials(rng: &mut Random, builder: &mut Builder, albedo: f32) -> [usize; 3] {
    let tint = |rng: &mut Random, level: f32| {
        let warm = rng.range(-0.08, 0.08);
        [
            (level * (1.0 + warm)).clamp(0.02, 0.92),
            level.clamp(0.02, 0.92),
            (level * (1.0 - warm)).clamp(0.02, 0.92),
        ]
    };
    let wall = if rng.chance(0.25) {
        // A saturated wall: colour bleeding is what GI is for.
        let strong = albedo.max(0.3);
        *rng.pick(&[
            [strong, strong * 0.15, strong * 0.12],
            [strong * 0.2, strong, strong * 0.25],
            [strong * 0.2, strong * 0.3, strong],
        ])
    } else {
        tint(rng, albedo)
    };
    let floor_level = (albedo * rng.range(0.5, 1.0)).max(0.08);
    let floor = tint(rng, floor_level);
    let ceiling = tint(rng, albedo.max(0.3));
    [
        builder.material("wall", wall),
        builder.material("floor", floor),
        builder.material("ceiling", ceiling),
    ]
}

/// A room's interior: its bounds and the boxes already standing in it.
struct Room {
    low: Vec3,
    high: Vec3,
    taken: Vec<(Vec3, Vec3)>,
}

impl Room {
    fn overlaps(&self, low: Vec3, high: Vec3, margin: f32) -> bool {
        self.taken
            .iter()
            .any(|(l, h)| (low - margin).cmplt(*h).all() && (high + margin).cmpgt(*l).all())
    }
}

/// Puts up to `count` boxes on `room`'s floor, each with a random contact,
/// bottom and place (free, against a wall, in a corner); returns their feet.
fn place_objects(
    rng: &mut Random,
    builder: &mut Builder,
    room: &mut Room,
    count: usize,
    largest: f32,
) -> Vec<Foot> {
    let mut feet = Vec::new();
    for _ in 0..count {
        let colour = {
            let level = rng.range(0.1, 0.9);
            let hue = rng.below(4);
            match hue {
                0 => [level, level, level],
                1 => [level, level * 0.55, level * 0.3],
                2 => [level * 0.35, level * 0.6, level],
                _ => [level * 0.5, level, level * 0.45],
            }
        };
        let material = builder.material("object", colour);
        let extent = room.high - room.low;
        for _attempt in 0..24 {
            let size = Vec3::new(
                rng.range(0.25, largest).min(extent.x * 0.4),
                rng.range(0.3, largest * 1.2).min(extent.y * 0.6),
                rng.range(0.25, largest).min(extent.z * 0.4),
            );
            let place = rng.below(3);
            let mut x = rng.range(room.low.x + 0.3, room.high.x - 0.3 - size.x);
            let mut z = rng.range(room.low.z + 0.3, room.high.z - 0.3 - size.z);
            if place >= 1 {
                x = if rng.chance(0.5) {
                    room.low.x
                } else {
                    room.high.x - size.x
                };
            }
            if place == 2 {
                z = if rng.chance(0.5) {
                    room.low.z
                } else {
                    room.high.z - size.z
                };
            }
            let contact = match rng.below(3) {
                0 => Contact::Flush,
                1 => Contact::Above(rng.range(0.002, 0.02)),
                _ => Contact::Into(rng.range(0.005, 0.03)),
            };
            let bottom_y = room.low.y
                + match contact {
                    Contact::Flush => 0.0,
                    Contact::Above(gap) => gap,
                    Contact::Into(depth) => -depth,
                };
            let low = Vec3::new(x, bottom_y, z);
            let high = low + size;
            if room.overlaps(low, high, 0.2) {
                continue;
            }
            let has_bottom = rng.chance(0.5);
            builder.cuboid(material, low, high, has_bottom);
            room.taken.push((low, high));
            feet.push(Foot {
                low: Vec2::new(low.x, low.z),
                high: Vec2::new(high.x, high.z),
                floor: room.low.y,
                has_bottom,
                contact,
            });
            break;
        }
    }
    feet
}

/// A point or spot light somewhere in `room`, clear of its objects: free,
/// near a wall, in a corner or in a shade (which it builds). `power` scales
/// the intensity with the room.
fn place_light(
    rng: &mut Random,
    builder: &mut Builder,
    room: &mut Room,
    power: f32,
) -> PlacedLight {
    let extent = room.high - room.low;
    let colour = if rng.chance(0.3) {
        *rng.pick(&[[1.0, 0.55, 0.3], [0.45, 0.7, 1.0], [1.0, 0.9, 0.5]])
    } else {
        [1.0, 0.92, 0.8]
    };
    let strength = power * rng.range(0.3, 1.5);
    for _attempt in 0..64 {
        let kind = rng.below(4);
        let mut position = Vec3::new(
            rng.range(room.low.x + 0.35, room.high.x - 0.35),
            rng.range(room.low.y + 0.5, room.high.y - 0.35),
            rng.range(room.low.z + 0.35, room.high.z - 0.35),
        );
        let place = match kind {
            0 => LightPlace::Free,
            1 => {
                let distance = rng.range(0.05, 0.3);
                if rng.chance(0.5) {
                    position.x = if rng.chance(0.5) {
                        room.low.x + distance
                    } else {
                        room.high.x - distance
                    };
                } else {
                    position.z = if rng.chance(0.5) {
                        room.low.z + distance
                    } else {
                        room.high.z - distance
                    };
                }
                LightPlace::NearWall(distance)
            }
            2 => {
                let distance = rng.range(0.05, 0.3);
                position.x = if rng.chance(0.5) {
                    room.low.x + distance
                } else {
                    room.high.x - distance
                };
                position.z = if rng.chance(0.5) {
                    room.low.z + distance
                } else {
                    room.high.z - distance
                };
                LightPlace::Corner(distance)
            }
            _ => LightPlace::Shaded(1 + rng.below(2) as u32),
        };
        let shade_half = Vec3::new(0.16, 0.14, 0.16);
        if let LightPlace::Shaded(_) = place {
            // Hangs 0.3-0.6 m from a wall or free, at least 1.2 m up.
            position.y = rng.range((room.low.y + 1.2).min(room.high.y - 0.4), room.high.y - 0.4);
            if extent.x < 1.2 || extent.z < 1.2 {
                continue;
            }
        }
        let clearance = match place {
            LightPlace::Shaded(_) => shade_half + 0.05,
            _ => Vec3::splat(0.05),
        };
        if room.overlaps(position - clearance, position + clearance, 0.0) {
            continue;
        }
        if let LightPlace::Shaded(open) = place {
            let material = builder.material("shade", [0.8, 0.75, 0.6]);
            builder.shade(material, position + Vec3::Y * 0.05, shade_half, open);
            room.taken
                .push((position - shade_half - 0.02, position + shade_half + 0.07));
        }
        let intensity = Vec3::from_array(colour) * strength;
        let spot = !matches!(place, LightPlace::Shaded(_)) && rng.chance(0.3);
        let toml = if spot {
            let target = Vec3::new(
                rng.range(room.low.x, room.high.x),
                room.low.y,
                rng.range(room.low.z, room.high.z),
            );
            let inner = rng.range(15.0_f32, 40.0);
            format!(
                "[[lights]]\nkind = \"spot\"\nposition = {}\ndirection = {}\nintensity = {}\ninner_angle = {:.1}\nouter_angle = {:.1}\n",
                array(position),
                array((target - position).normalize_or(Vec3::NEG_Y)),
                array(intensity * 2.0),
                inner,
                inner + rng.range(5.0, 20.0)
            )
        } else {
            format!(
                "[[lights]]\nkind = \"point\"\nposition = {}\nintensity = {}\n",
                array(position),
                array(intensity)
            )
        };
        return PlacedLight { place, toml };
    }
    // A room too full for any of the above still gets a light at its centre
    // under the ceiling, which the objects (at most 60 % of its height)
    // never reach.
    let position = Vec3::new(
        (room.low.x + room.high.x) * 0.5,
        room.high.y - 0.2,
        (room.low.z + room.high.z) * 0.5,
    );
    PlacedLight {
        place: LightPlace::Free,
        toml: format!(
            "[[lights]]\nkind = \"point\"\nposition = {}\nintensity = {}\n",
            array(position),
            array(Vec3::from_array(colour) * strength)
        ),
    }
}

/// An eye in a corner of `room` at eye height, its place reserved so that
/// no object is put around it.
fn corner_eye(rng: &mut Random, room: &mut Room) -> Vec3 {
    let extent = room.high - room.low;
    let inset = (extent * 0.12).min(Vec3::splat(0.6));
    let eye = Vec3::new(
        if rng.chance(0.5) {
            room.low.x + inset.x
        } else {
            room.high.x - inset.x
        },
        room.low.y + (extent.y * 0.55).clamp(0.8, 1.8),
        if rng.chance(0.5) {
            room.low.z + inset.z
        } else {
            room.high.z - inset.z
        },
    );
    reserve_eye(room, eye);
    eye
}

fn reserve_eye(room: &mut Room, eye: Vec3) {
    let around = Vec3::new(0.5, 0.0, 0.5);
    room.taken.push((
        Vec3::new(eye.x, room.low.y - 1.0, eye.z) - around,
        Vec3::new(eye.x, eye.y + 0.3, eye.z) + around,
    ));
}

/// Where the camera looks: the first object's foot when it stands more
/// than a metre away, else across the room.
fn aim(room: &Room, feet: &[Foot], eye: Vec3) -> Vec3 {
    let across = Vec3::new(
        (room.low.x + room.high.x) * 0.5,
        room.low.y + (room.high.y - room.low.y) * 0.3,
        (room.low.z + room.high.z) * 0.5,
    );
    match feet.first() {
        Some(foot) => {
            let centre = (foot.low + foot.high) * 0.5;
            let target = Vec3::new(centre.x, foot.floor + 0.2, centre.y);
            if (target - eye).length() > 1.0 {
                target
            } else {
                across
            }
        }
        None => across,
    }
}

/// How one building's enclosure is modelled: its wall, floor and ceiling
/// materials, wall kind, solid walls' thickness and overlapping walls'
/// overhang past the corners.
#[derive(Clone, Copy)]
struct Style {
    materials: [usize; 3],
    walls: Walls,
    thickness: f32,
    overhang: f32,
}

impl Style {
    /// Draws materials, thickness (0.1-0.35 m for solids) and an overhang
    /// in `overhang` metres, in that order.
    fn draw(
        rng: &mut Random,
        builder: &mut Builder,
        walls: Walls,
        albedo: f32,
        overhang: (f32, f32),
    ) -> Self {
        let materials = room_materials(rng, builder, albedo);
        let thickness = match walls {
            Walls::Solids => rng.range(0.1, 0.35),
            _ => 0.0,
        };
        Self {
            materials,
            walls,
            thickness,
            overhang: rng.range(overhang.0, overhang.1),
        }
    }
}

fn room(rng: &mut Random, builder: &mut Builder, walls: Walls, albedo: f32) -> Plan {
    let size = Vec3::new(
        rng.range(2.0, 8.0),
        rng.range(2.2, 3.6),
        rng.range(2.0, 8.0),
    );
    let style = Style::draw(rng, builder, walls, albedo, (0.05, 0.3));
    builder.enclosure(&style, Vec3::ZERO, size, &Default::default());
    let mut room = Room {
        low: Vec3::ZERO,
        high: size,
        taken: Vec::new(),
    };
    let eye = corner_eye(rng, &mut room);
    let count = 1 + rng.below(3);
    let feet = place_objects(rng, builder, &mut room, count, 1.0);
    let power = (size.x * size.z).max(4.0) * 0.5;
    let mut lights = vec![place_light(rng, builder, &mut room, power)];
    if rng.chance(0.3) {
        lights.push(place_light(rng, builder, &mut room, power * 0.5));
    }
    let target = aim(&room, &feet, eye);
    Plan {
        size: size.max_element(),
        feet,
        lights,
        eye,
        target,
        environment: 0.0,
    }
}

fn two_rooms(
    rng: &mut Random,
    builder: &mut Builder,
    shell: Shell,
    walls: Walls,
    albedo: f32,
) -> Plan {
    let height = rng.range(2.3, 3.4);
    let width = rng.range(2.5, 6.0);
    let (length_a, length_b) = (rng.range(2.5, 6.0), rng.range(2.5, 6.0));
    let style = Style::draw(rng, builder, walls, albedo, (0.05, 0.3));
    let (materials, thickness) = (style.materials, style.thickness);
    // The partition (or the gap between two boxes) between x = length_a and
    // x = start_b.
    let partition = match (shell, walls) {
        (Shell::BoxPerRoom, Walls::Solids) => 2.0 * thickness + rng.range(0.0, 0.1),
        (Shell::BoxPerRoom, _) => {
            if rng.chance(0.5) {
                0.0
            } else {
                rng.range(0.05, 0.25)
            }
        }
        (Shell::OneShell, _) => rng.range(0.1, 0.3),
    };
    let start_b = length_a + partition;
    let door_width = rng.range(0.7, 1.6).min(width - 0.6);
    let door_height = rng.range(1.9, 2.2).min(height - 0.1);
    let door_z = rng.range(0.3, width - 0.3 - door_width);
    // In the plane x = const, a runs along y and b along z.
    let door = Rect::new(
        Vec2::new(0.0, door_z),
        Vec2::new(door_height, door_z + door_width),
    );
    let size = Vec3::new(start_b + length_b, height, width);
    match shell {
        Shell::OneShell => {
            builder.enclosure(&style, Vec3::ZERO, size, &Default::default());
            let whole = Rect::new(Vec2::ZERO, Vec2::new(height, width));
            builder.wall(materials[0], 0, length_a, whole, &[door], false);
            builder.wall(materials[0], 0, start_b, whole, &[door], true);
            if walls == Walls::Solids {
                builder.reveal(materials[0], 0, length_a, start_b, door);
            }
        }
        Shell::BoxPerRoom => {
            let box_thickness = if walls == Walls::Solids {
                thickness
            } else {
                0.0
            };
            let mut openings_a: [Vec<Rect>; 6] = Default::default();
            openings_a[1] = vec![door];
            let mut openings_b: [Vec<Rect>; 6] = Default::default();
            openings_b[0] = vec![door];
            // Overlapping walls stop halfway across the gap between boxes.
            let boxes = Style {
                overhang: style.overhang.min(partition * 0.5).max(0.0),
                ..style
            };
            let a_high = Vec3::new(length_a, height, width);
            builder.enclosure(&boxes, Vec3::ZERO, a_high, &openings_a);
            builder.enclosure(&boxes, Vec3::new(start_b, 0.0, 0.0), size, &openings_b);
            // A door frame across the gap between the boxes' outer faces.
            let gap_from = length_a + box_thickness;
            let gap_to = start_b - box_thickness;
            if gap_to - gap_from > 1e-3 {
                builder.reveal(materials[0], 0, gap_from, gap_to, door);
            }
        }
    }
    let mut lit = Room {
        low: Vec3::ZERO,
        high: Vec3::new(length_a, height, width),
        taken: Vec::new(),
    };
    // Keep the doorway clear so the unlit room's light is not a box's shadow.
    lit.taken.push((
        Vec3::new(length_a - 0.8, 0.0, door_z),
        Vec3::new(length_a, door_height, door_z + door_width),
    ));
    let mut unlit = Room {
        low: Vec3::new(start_b, 0.0, 0.0),
        high: size,
        taken: vec![(
            Vec3::new(start_b, 0.0, door_z),
            Vec3::new(start_b + 0.8, door_height, door_z + door_width),
        )],
    };
    // Eye near the unlit room's far wall, on the side away from the door,
    // looking back toward the objects or the doorway.
    let eye = Vec3::new(
        size.x - (length_b * 0.12).min(0.5),
        (height * 0.55).clamp(0.9, 1.7),
        if door_z + door_width * 0.5 > width * 0.5 {
            0.4_f32.min(width * 0.2)
        } else {
            width - 0.4_f32.min(width * 0.2)
        },
    );
    reserve_eye(&mut unlit, eye);
    let count = 1 + rng.below(2);
    let feet = place_objects(rng, builder, &mut unlit, count, 1.0);
    let lit_count = rng.below(2);
    place_objects(rng, builder, &mut lit, lit_count, 1.0);
    let power = (length_a * width).max(4.0) * 0.6;
    let lights = vec![place_light(rng, builder, &mut lit, power)];
    let target = if feet.is_empty() {
        Vec3::new(start_b, 0.8, door_z + door_width * 0.5)
    } else {
        aim(&unlit, &feet, eye)
    };
    Plan {
        size: size.max_element(),
        feet,
        lights,
        eye,
        target,
        environment: 0.0,
    }
}

fn hall(rng: &mut Random, builder: &mut Builder, walls: Walls, albedo: f32) -> Plan {
    let length = rng.range(10.0, 50.0);
    let size = Vec3::new(
        length,
        rng.range(5.0, 15.0).min(length * 0.6),
        rng.range(0.35, 0.8) * length,
    );
    let mut style = Style::draw(rng, builder, walls, albedo, (0.1, 0.5));
    if walls == Walls::Solids {
        // A hall's walls are at least 0.3 m thick.
        style.thickness = style.thickness.max(0.3);
    }
    // Small windows along the x = 0 wall; in that plane a runs along y and
    // b along z.
    let mut windows = Vec::new();
    let count = 2 + rng.below(5);
    let spacing = size.z / count as f32;
    // Small beside the hall, but growing with it, so that a 50 m hall gets
    // enough sun for its reference to converge in a study's time.
    let window_scale = (length / 10.0).sqrt();
    for window in 0..count {
        let width = (rng.range(0.6, 2.0) * window_scale).min(spacing * 0.7);
        let height = (rng.range(1.0, 2.5) * window_scale).min(size.y * 0.4);
        let sill = rng.range(1.0, 3.0).min(size.y - height - 0.5);
        let centre = spacing * (window as f32 + 0.5);
        windows.push(Rect::new(
            Vec2::new(sill, centre - width * 0.5),
            Vec2::new(sill + height, centre + width * 0.5),
        ));
    }
    let mut openings: [Vec<Rect>; 6] = Default::default();
    openings[0] = windows;
    builder.enclosure(&style, Vec3::ZERO, size, &openings);
    let mut room = Room {
        low: Vec3::ZERO,
        high: size,
        taken: Vec::new(),
    };
    let eye = Vec3::new(
        size.x - (size.x * 0.08).min(2.0),
        1.7,
        if rng.chance(0.5) {
            size.z * 0.15
        } else {
            size.z * 0.85
        },
    );
    reserve_eye(&mut room, eye);
    let scale = (length / 10.0).sqrt();
    let count = 2 + rng.below(4);
    let feet = place_objects(rng, builder, &mut room, count, 1.5 * scale);
    // A low sun through the windows: travels into the hall (+x), 15-45
    // degrees above the horizon, up to 35 degrees off the wall's normal.
    let elevation = rng.range(15.0_f32, 45.0).to_radians();
    let azimuth = rng.range(-35.0_f32, 35.0).to_radians();
    let direction = Vec3::new(
        elevation.cos() * azimuth.cos(),
        -elevation.sin(),
        elevation.cos() * azimuth.sin(),
    );
    let irradiance = rng.range(4.0, 10.0);
    let sun = PlacedLight {
        place: LightPlace::Sun,
        toml: format!(
            "[[lights]]\nkind = \"directional\"\ndirection = {}\nirradiance = [{:.3}, {:.3}, {:.3}]\n",
            array(direction),
            irradiance,
            irradiance * 0.93,
            irradiance * 0.8
        ),
    };
    let target = Vec3::new(size.x * 0.3, size.y * 0.2, size.z * 0.5);
    Plan {
        size: size.max_element(),
        feet,
        lights: vec![sun],
        eye,
        target,
        environment: if rng.chance(0.5) {
            rng.range(0.05, 0.3)
        } else {
            0.0
        },
    }
}
