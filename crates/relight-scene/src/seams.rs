//! Cuts the static surfaces along the lines where walls stand on them, so
//! that the lightmap's charts can end there.
//!
//! A model that lays one floor slab under every room (or one ceiling over
//! them) has no edge where a partition stands on it. A chart grown over the slab is one planar
//! projection, so the texels along the partition's foot straddle it: each
//! holds one receiver on one side, and a bilinear lookup in the other
//! room, within a texel of the wall, reads a share of it (a generated
//! suite with a 13 cm partition on a floor of 21 cm texels: a bright line
//! along the unlit room's wall foot, 1.17 times the path tracer's light
//! in view). No texel size fixes that for a partition thinner than two
//! texels, and no chart boundary can be drawn where the mesh has no edge.
//!
//! So at load, [`cut_under_walls`] finds the feet: the edges of triangles
//! that lie in the plane of a level triangle (a floor or a ceiling), over
//! it, turned from it by more than 60 degrees and rising on its front side
//! (a wall on a floor, a partition under a ceiling).
//! Collinear feet in one plane make a line; a line whose feet run at least
//! [`LEAST_FOOT_M`] and cover at least [`LEAST_COVER`] of its span (a
//! partition with its doorway; not a chair leg) cuts every triangle of
//! that plane that it crosses within its span, doorways included, since a
//! chart that stays whole under the doorway is still one projection across
//! the partition. Every edge on such a line, cut or already there, becomes
//! a seam ([`Scene::lightmap_seams`](crate::Scene)) where the atlas stops
//! its charts. A line that crosses a triangle past its span's ends leaves
//! that triangle whole: cutting it would draw a seam across open floor.
//! Walls are not cut ([`LEVEL_COS`]), so one outer wall quad that runs
//! past a partition's end still has texels straddling it.

use crate::detail::{push_pieces, Corner};
use crate::Mesh;
use glam::Vec3;
use rayon::prelude::*;
use std::collections::{BTreeMap, HashMap};
use std::ops::Range;

/// Feet along a line shorter than this, in metres, cut nothing: a chair's
/// or a column base's foot is an object's, which the lightmap's hidden
/// texels serve, and seams there would only add charts.
pub const LEAST_FOOT_M: f32 = 0.5;

/// The share of a line's span its feet must cover: a partition keeps most
/// of its length however wide its doorway (a 1.6 m door in a 2.5 m wall
/// leaves 36 %); a row of objects along one line keeps gaps wider than
/// themselves.
pub const LEAST_COVER: f32 = 0.25;

/// A surface stands on a plane when it turns from it by more than 60
/// degrees, as the atlas's wall probes judge walls.
const STANDING_COS: f32 = 0.5;

/// Only level surfaces are cut, floors and ceilings (normal within about
/// 25 degrees of relight's up axis, +y, as in glTF): they are what rooms
/// share in plan. Cutting walls too (at a partition's end against an outer
/// wall, but also along every window frame and moulding) made a furnished
/// room's walls worse for no gain on the generated suites.
pub const LEVEL_COS: f32 = 0.9;

/// Coplanar surfaces to cut face the same way as the surface the feet were
/// found on (about 8 degrees): a slab's underside is another surface.
const SAME_PLANE_COS: f32 = 0.99;

/// Wall edges shorter than this, in metres, are not searched for feet: a
/// dense mesh's furniture and carving has millions of them, and a wall's
/// foot is not made of millimetre steps.
const SHORTEST_FOOT_EDGE_M: f32 = 0.05;

/// Triangles whose box covers more grid cells than this are kept in one
/// list that every search scans (a ground plane's far pieces).
const MOST_CELLS: usize = 1024;

/// What [`cut_under_walls`] did: for each triangle before, the range of
/// triangles it became; how many triangles were cut along how many lines;
/// and the seams, the edges on those lines, as pairs of vertex positions,
/// bit for bit those of the mesh's vertices.
pub struct WallCut {
    pub pieces_of: Vec<Range<u32>>,
    pub cut: usize,
    pub lines: usize,
    pub seams: Vec<[Vec3; 2]>,
}

/// One line walls stand on: in the plane `normal . x = offset`, along
/// `direction` through `through`, with feet spanning `span` (in
/// `direction . x`).
#[derive(Clone, Copy, Debug)]
struct WallLine {
    normal: Vec3,
    offset: f32,
    direction: Vec3,
    through: Vec3,
    span: (f32, f32),
}

impl WallLine {
    /// Signed distance from the plane through the line across `normal`.
    fn side(&self, point: Vec3) -> f32 {
        self.normal.cross(self.direction).dot(point - self.through)
    }

    fn along(&self, point: Vec3) -> f32 {
        self.direction.dot(point)
    }

    fn within_span(&self, from: f32, to: f32, tolerance: f32) -> bool {
        from.min(to) >= self.span.0 - tolerance && from.max(to) <= self.span.1 + tolerance
    }
}

/// Triangles binned by the grid cells their boxes touch, for finding the
/// triangles near an edge.
struct TriangleGrid {
    low: Vec3,
    cell: f32,
    cells: HashMap<[i32; 3], Vec<u32>>,
    large: Vec<u32>,
}

impl TriangleGrid {
    fn new(mesh: &Mesh, low: Vec3, extent: f32) -> Self {
        let cell = (extent / 256.0).max(0.25);
        let mut grid = Self {
            low,
            cell,
            cells: HashMap::new(),
            large: Vec::new(),
        };
        for triangle in 0..mesh.triangles.len() {
            let [a, b, c] = mesh.vertices(triangle);
            let (from, to) = (grid.cell_of(a.min(b).min(c)), grid.cell_of(a.max(b).max(c)));
            let count = (0..3)
                .map(|axis| (to[axis] - from[axis] + 1) as usize)
                .product::<usize>();
            if count > MOST_CELLS {
                grid.large.push(triangle as u32);
                continue;
            }
            for x in from[0]..=to[0] {
                for y in from[1]..=to[1] {
                    for z in from[2]..=to[2] {
                        grid.cells
                            .entry([x, y, z])
                            .or_default()
                            .push(triangle as u32);
                    }
                }
            }
        }
        grid
    }

    fn cell_of(&self, point: Vec3) -> [i32; 3] {
        ((point - self.low) / self.cell)
            .floor()
            .as_ivec3()
            .to_array()
    }

    /// The triangles whose cells meet the box from `low` to `high`, each
    /// once, in index order.
    fn near(&self, low: Vec3, high: Vec3, found: &mut Vec<u32>) {
        found.clear();
        found.extend_from_slice(&self.large);
        let (from, to) = (self.cell_of(low), self.cell_of(high));
        let count = (0..3)
            .map(|axis| (to[axis] - from[axis] + 1) as usize)
            .product::<usize>();
        if count > self.cells.len() {
            found.extend(self.cells.values().flatten());
        } else {
            for x in from[0]..=to[0] {
                for y in from[1]..=to[1] {
                    for z in from[2]..=to[2] {
                        if let Some(triangles) = self.cells.get(&[x, y, z]) {
                            found.extend_from_slice(triangles);
                        }
                    }
                }
            }
        }
        found.sort_unstable();
        found.dedup();
    }
}

/// Cuts the triangles that walls stand on along the walls' feet (see the
/// module's doc). Emissive triangles stay whole (they are lights). Pieces
/// keep the triangle's winding and material; their UVs are interpolated.
pub fn cut_under_walls(mesh: &mut Mesh, emissive: impl Fn(u32) -> bool + Sync) -> WallCut {
    let triangle_count = mesh.triangles.len();
    let unchanged = || WallCut {
        pieces_of: (0..triangle_count as u32).map(|t| t..t + 1).collect(),
        cut: 0,
        lines: 0,
        seams: Vec::new(),
    };
    if triangle_count == 0 {
        return unchanged();
    }
    let (low, high) = mesh.bounds();
    let extent = (high - low).max_element();
    // Modelled contact is exact to well under a millimetre near the origin;
    // a large model's coordinates round coarser.
    let tolerance = 2e-4 + 1e-5 * extent;
    let grid = TriangleGrid::new(mesh, low, extent);
    let normals: Vec<Vec3> = (0..triangle_count)
        .map(|t| mesh.geometric_normal(t))
        .collect();
    let lines = wall_lines(mesh, &normals, &grid, tolerance);
    if lines.is_empty() {
        return unchanged();
    }
    // Each line's triangles: in its plane, facing its way, near its span.
    let mut lines_of: Vec<Vec<u32>> = vec![Vec::new(); triangle_count];
    let mut near = Vec::new();
    for (index, line) in lines.iter().enumerate() {
        let ends = [
            line.through + line.direction * (line.span.0 - line.along(line.through)),
            line.through + line.direction * (line.span.1 - line.along(line.through)),
        ];
        let margin = Vec3::splat(tolerance);
        grid.near(
            ends[0].min(ends[1]) - margin,
            ends[0].max(ends[1]) + margin,
            &mut near,
        );
        for &triangle in &near {
            let t = triangle as usize;
            let in_plane = mesh
                .vertices(t)
                .iter()
                .all(|v| (line.normal.dot(*v) - line.offset).abs() <= tolerance);
            if in_plane
                && normals[t].dot(line.normal) >= SAME_PLANE_COS
                && !emissive(mesh.material_ids[t])
            {
                lines_of[t].push(index as u32);
            }
        }
    }
    let mut triangles = Vec::with_capacity(triangle_count);
    let mut material_ids = Vec::with_capacity(triangle_count);
    let mut pieces_of = Vec::with_capacity(triangle_count);
    let mut seams = Vec::new();
    let mut cut = 0;
    for (triangle, its_lines) in lines_of.iter().enumerate() {
        let first = triangles.len() as u32;
        let mut polygons = vec![Corner::of_triangle(mesh, triangle)];
        for &line in its_lines {
            let line = &lines[line as usize];
            let mut next = Vec::with_capacity(polygons.len() + 1);
            for polygon in polygons.drain(..) {
                match split(&polygon, line, tolerance) {
                    Some((below, above)) => next.extend([below, above]),
                    None => next.push(polygon),
                }
            }
            polygons = next;
        }
        // Seams are the final pieces' edges on a line, so that a later
        // line's cut across an earlier seam leaves seams that are edges.
        for polygon in &polygons {
            for (index, from) in polygon.iter().enumerate() {
                let to = polygon[(index + 1) % polygon.len()];
                let on_a_line = its_lines.iter().any(|&line| {
                    let line = &lines[line as usize];
                    line.side(from.position).abs() <= tolerance
                        && line.side(to.position).abs() <= tolerance
                        && line.within_span(
                            line.along(from.position),
                            line.along(to.position),
                            tolerance,
                        )
                });
                if on_a_line {
                    seams.push([from.position, to.position]);
                }
            }
        }
        if polygons.len() > 1 {
            cut += 1;
            push_pieces(mesh, triangle, &polygons, &mut triangles, &mut material_ids);
        } else {
            triangles.push(mesh.triangles[triangle]);
            material_ids.push(mesh.material_ids[triangle]);
        }
        pieces_of.push(first..triangles.len() as u32);
    }
    mesh.triangles = triangles;
    mesh.material_ids = material_ids;
    for seam in &mut seams {
        let key = |p: Vec3| p.to_array().map(f32::to_bits);
        if key(seam[1]) < key(seam[0]) {
            seam.swap(0, 1);
        }
    }
    seams.sort_unstable_by_key(|seam| seam.map(|p| p.to_array().map(f32::to_bits)));
    seams.dedup();
    WallCut {
        pieces_of,
        cut,
        lines: lines.len(),
        seams,
    }
}

/// Splits a convex polygon by the plane through `line` across its surface
/// when the line crosses it within the line's span; `None` otherwise.
/// Corners within `tolerance` of the line count as on it, and a crossing
/// is interpolated from its edge's lower end (by position bits), so
/// neighbouring triangles that share the edge share the crossing exactly.
fn split(
    polygon: &[Corner],
    line: &WallLine,
    tolerance: f32,
) -> Option<(Vec<Corner>, Vec<Corner>)> {
    let sides: Vec<f32> = polygon
        .iter()
        .map(|corner| {
            let side = line.side(corner.position);
            if side.abs() <= tolerance {
                0.0
            } else {
                side
            }
        })
        .collect();
    if !(sides.iter().any(|&s| s < 0.0) && sides.iter().any(|&s| s > 0.0)) {
        return None;
    }
    let mut below = Vec::with_capacity(polygon.len() + 1);
    let mut above = Vec::with_capacity(polygon.len() + 1);
    let mut chord = Vec::with_capacity(2);
    for index in 0..polygon.len() {
        let next = (index + 1) % polygon.len();
        let (from, to) = (polygon[index], polygon[next]);
        let (from_side, to_side) = (sides[index], sides[next]);
        if from_side <= 0.0 {
            below.push(from);
        }
        if from_side >= 0.0 {
            above.push(from);
        }
        if from_side == 0.0 {
            chord.push(from.position);
        }
        if (from_side < 0.0 && to_side > 0.0) || (from_side > 0.0 && to_side < 0.0) {
            let key = |c: &Corner| c.position.to_array().map(f32::to_bits);
            let (start, end, start_side, end_side) = if key(&from) <= key(&to) {
                (from, to, from_side, to_side)
            } else {
                (to, from, to_side, from_side)
            };
            let t = start_side / (start_side - end_side);
            let crossing = Corner {
                position: start.position + (end.position - start.position) * t,
                barycentric: start.barycentric + (end.barycentric - start.barycentric) * t,
            };
            below.push(crossing);
            above.push(crossing);
            chord.push(crossing.position);
        }
    }
    let [from, to] = chord[..] else {
        return None;
    };
    line.within_span(line.along(from), line.along(to), tolerance)
        .then_some((below, above))
}

/// A line's plane (normal, offset) and its direction and point nearest the
/// origin, rounded.
type LineKey = ([i32; 3], i32, [i32; 3], [i32; 3]);

/// One wall's foot on one triangle: the plane it stands on and the part of
/// the wall's edge that lies over the triangle.
struct Foot {
    normal: Vec3,
    offset: f32,
    from: Vec3,
    to: Vec3,
}

/// Finds every foot and gathers the qualifying lines, in a fixed order.
fn wall_lines(mesh: &Mesh, normals: &[Vec3], grid: &TriangleGrid, tolerance: f32) -> Vec<WallLine> {
    let feet: Vec<Foot> = (0..mesh.triangles.len())
        .into_par_iter()
        .map_init(Vec::new, |near, wall| {
            let corners = mesh.vertices(wall);
            let mut feet = Vec::new();
            for edge in 0..3 {
                let (a, b, rising) = (
                    corners[edge],
                    corners[(edge + 1) % 3],
                    corners[(edge + 2) % 3],
                );
                if a.distance(b) < SHORTEST_FOOT_EDGE_M.max(4.0 * tolerance) {
                    continue;
                }
                let margin = Vec3::splat(tolerance);
                grid.near(a.min(b) - margin, a.max(b) + margin, near);
                for &floor in near.iter() {
                    let floor = floor as usize;
                    let normal = normals[floor];
                    if floor == wall
                        || normal.y.abs() < LEVEL_COS
                        || normal.dot(normals[wall]).abs() >= STANDING_COS
                    {
                        continue;
                    }
                    let offset = normal.dot(mesh.vertices(floor)[0]);
                    let height = |p: Vec3| normal.dot(p) - offset;
                    if height(a).abs() > tolerance
                        || height(b).abs() > tolerance
                        || height(rising) <= tolerance
                    {
                        continue;
                    }
                    if let Some((from, to)) = over_triangle(mesh, floor, normal, a, b, tolerance) {
                        feet.push(Foot {
                            normal,
                            offset,
                            from,
                            to,
                        });
                    }
                }
            }
            feet
        })
        .flatten()
        .collect();
    // Feet of one line in one plane share a key: the plane and the line,
    // rounded to a step above the contact tolerance.
    let step = (2.0 * tolerance).max(1e-3);
    let round = |v: Vec3, step: f32| (v / step).round().as_ivec3().to_array();
    let mut groups: BTreeMap<LineKey, (WallLine, Vec<(f32, f32)>)> = BTreeMap::new();
    for foot in feet {
        let mut direction = (foot.to - foot.from).normalize_or_zero();
        let largest = direction.abs().max_element();
        let leading = direction
            .to_array()
            .into_iter()
            .find(|c| c.abs() == largest)
            .unwrap_or(1.0);
        if leading < 0.0 {
            direction = -direction;
        }
        let through = foot.from - direction * direction.dot(foot.from);
        let key = (
            round(foot.normal, 1e-3),
            (foot.offset / step).round() as i32,
            round(direction, 1e-3),
            round(through, step),
        );
        let (along_from, along_to) = (direction.dot(foot.from), direction.dot(foot.to));
        let entry = groups.entry(key).or_insert_with(|| {
            (
                WallLine {
                    normal: foot.normal,
                    offset: foot.offset,
                    direction,
                    through,
                    span: (f32::INFINITY, f32::NEG_INFINITY),
                },
                Vec::new(),
            )
        });
        entry
            .1
            .push((along_from.min(along_to), along_from.max(along_to)));
    }
    groups
        .into_values()
        .filter_map(|(mut line, mut feet)| {
            feet.sort_unstable_by(|a, b| a.0.total_cmp(&b.0).then(a.1.total_cmp(&b.1)));
            let mut covered = 0.0;
            let mut run = feet[0];
            for &(from, to) in &feet[1..] {
                if from <= run.1 + tolerance {
                    run.1 = run.1.max(to);
                } else {
                    covered += run.1 - run.0;
                    run = (from, to);
                }
            }
            covered += run.1 - run.0;
            let span = (feet[0].0, feet.iter().map(|f| f.1).fold(f32::MIN, f32::max));
            line.span = span;
            (covered >= LEAST_FOOT_M && covered >= LEAST_COVER * (span.1 - span.0)).then_some(line)
        })
        .collect()
}

/// The part of the segment from `a` to `b` (in the triangle's plane) that
/// lies over `triangle`, edges included, if longer than `tolerance`.
fn over_triangle(
    mesh: &Mesh,
    triangle: usize,
    normal: Vec3,
    a: Vec3,
    b: Vec3,
    tolerance: f32,
) -> Option<(Vec3, Vec3)> {
    let corners = mesh.vertices(triangle);
    let (mut from, mut to) = (0.0f32, 1.0f32);
    for edge in 0..3 {
        let (p, q) = (corners[edge], corners[(edge + 1) % 3]);
        let inward = normal.cross(q - p).normalize_or_zero();
        // inward . (a + (b - a) s - p) >= -tolerance
        let start = inward.dot(a - p) + tolerance;
        let slope = inward.dot(b - a);
        if slope.abs() < 1e-12 {
            if start < 0.0 {
                return None;
            }
        } else if slope > 0.0 {
            from = from.max(-start / slope);
        } else {
            to = to.min(-start / slope);
        }
    }
    let length = (b - a).length();
    ((to - from) * length > tolerance).then(|| (a + (b - a) * from, a + (b - a) * to))
}

#[cfg(test)]
mod tests {
    use super::*;
    use glam::Vec2;

    fn quad(mesh: &mut Mesh, corners: [Vec3; 4], material: u32) {
        let base = mesh.positions.len() as u32;
        mesh.positions.extend(corners);
        mesh.triangles.push([base, base + 1, base + 2]);
        mesh.triangles.push([base, base + 2, base + 3]);
        mesh.material_ids.extend([material; 2]);
    }

    /// A 6 x 4 m floor of two triangles, facing up, with walls of zero
    /// thickness standing on it at x = 2.5 over the given stretches of z.
    fn floor_and_walls(walls: &[(f32, f32)]) -> Mesh {
        let mut mesh = Mesh::default();
        quad(
            &mut mesh,
            [
                Vec3::new(0.0, 0.0, 0.0),
                Vec3::new(0.0, 0.0, 4.0),
                Vec3::new(6.0, 0.0, 4.0),
                Vec3::new(6.0, 0.0, 0.0),
            ],
            0,
        );
        let x = 2.5;
        for &(z0, z1) in walls {
            quad(
                &mut mesh,
                [
                    Vec3::new(x, 0.0, z0),
                    Vec3::new(x, 2.5, z0),
                    Vec3::new(x, 2.5, z1),
                    Vec3::new(x, 0.0, z1),
                ],
                0,
            );
        }
        mesh.texcoords = vec![Vec2::ZERO; mesh.positions.len()];
        mesh
    }

    /// A partition across the floor with a doorway from `door.0` to `door.1`.
    fn slab_under_a_partition(door: (f32, f32)) -> Mesh {
        floor_and_walls(&[(0.0, door.0), (door.1, 4.0)])
    }

    fn floor_area(mesh: &Mesh, keep: impl Fn(Vec3) -> bool) -> f32 {
        (0..mesh.triangles.len())
            .filter(|&t| mesh.geometric_normal(t).y > 0.9)
            .filter(|&t| {
                let [a, b, c] = mesh.vertices(t);
                keep((a + b + c) / 3.0)
            })
            .map(|t| mesh.area(t))
            .sum()
    }

    #[test]
    fn a_slab_under_a_partition_is_cut_along_its_foot_doorway_included() {
        let mut mesh = slab_under_a_partition((1.5, 2.5));
        let cut = cut_under_walls(&mut mesh, |_| false);
        assert_eq!(
            cut.cut, 2,
            "both floor triangles cross the partition's line"
        );
        // No floor piece straddles x = 2.5, and the floor keeps its area.
        for t in 0..mesh.triangles.len() {
            if mesh.geometric_normal(t).y > 0.9 {
                let xs = mesh.vertices(t).map(|v| v.x);
                let (lo, hi) = (
                    xs.iter().copied().fold(f32::MAX, f32::min),
                    xs.iter().copied().fold(f32::MIN, f32::max),
                );
                assert!(
                    hi <= 2.5 + 1e-4 || lo >= 2.5 - 1e-4,
                    "piece {t} spans {lo}..{hi}"
                );
            }
        }
        let left = floor_area(&mesh, |c| c.x < 2.5);
        let right = floor_area(&mesh, |c| c.x > 2.5);
        assert!(
            (left - 10.0).abs() < 1e-3 && (right - 14.0).abs() < 1e-3,
            "{left} {right}"
        );
        // The seams run the floor's whole width along the foot, doorway
        // included, and are the pieces' own edges.
        let length: f32 = cut.seams.iter().map(|[a, b]| a.distance(*b)).sum();
        assert!((length - 4.0).abs() < 1e-3, "seams {:?}", cut.seams);
        for [a, b] in &cut.seams {
            assert!((a.x - 2.5).abs() < 1e-4 && (b.x - 2.5).abs() < 1e-4);
            assert!(mesh.positions.contains(a) && mesh.positions.contains(b));
        }
        assert_eq!(cut.pieces_of.len(), 6);
        assert_eq!(mesh.texcoords.len(), mesh.positions.len());
    }

    #[test]
    fn an_object_foot_and_a_wide_opening_cut_nothing() {
        // A partition of 0.4 m in a 4 m span of foot line, most of it an
        // opening: a row of posts, not a wall.
        let mut mesh = slab_under_a_partition((0.2, 3.8));
        let before = mesh.triangles.clone();
        let cut = cut_under_walls(&mut mesh, |_| false);
        assert_eq!(cut.cut, 0);
        assert!(cut.seams.is_empty());
        assert_eq!(mesh.triangles, before);
    }

    #[test]
    fn a_line_that_runs_past_its_walls_leaves_the_triangle_whole() {
        // A 1.2 m wall standing in the middle of the floor: its line crosses
        // both floor triangles well beyond its ends.
        let mut mesh = floor_and_walls(&[(1.4, 2.6)]);
        let cut = cut_under_walls(&mut mesh, |_| false);
        assert_eq!(cut.cut, 0, "seams {:?}", cut.seams);
    }
}
