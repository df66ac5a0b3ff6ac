//! Where the lightmap spends its texels: full density over the region that
//! holds the scene's detail, coarser with distance outside it.
//!
//! Real models often carry one huge triangle pair for the ground (the
//! classroom's floor is a 222 m plane of which a 10 x 40 m patch is inside the
//! building). At one texel size everywhere such a plane takes nearly all
//! receivers, so every bake and frame pays for texels no one looks at.
//!
//! The detail region is a box: given in `scene.toml` (`[lightmap]
//! detail = "box"`), or found automatically as the bounds of every triangle
//! smaller than an eighth of the surface, so that a ground plane of a few
//! huge triangles does not stretch it while the walls and floor of any room
//! (whose triangles are each a small share of the surface) keep it. Around
//! the box lie nested rings: ring 0 reaches `margin` beyond it at full
//! density; ring k reaches `margin * (2^(k+1) - 1)` with texels 4^k times
//! larger. Ring widths double while texels quadruple, so each ring holds
//! about a quarter of the texels of the one inside it even as its
//! perimeter grows: with texels only doubling, every ring of a ground plane
//! held as many as the one before and the classroom kept 38 % of its
//! receivers outside (62 % within 4.8 m of the building, 1.87 M in all).
//!
//! A texel size can only change between triangles (UVs are linear across
//! one), so at load a large triangle that spans rings is cut along the
//! rings' planes into pieces that each lie in one ring ([`split_for_detail`]).
//! The atlas then grows its charts within one ring and scales each chart's
//! texels by its ring. When no triangle reaches past ring 0 nothing is cut
//! and the atlas is the uniform one.

use crate::{Mesh, Scene};
use glam::{Vec2, Vec3};

/// How the lightmap's texel density is laid out, from `scene.toml`'s
/// `[lightmap]` section.
#[derive(Clone, Copy, Debug, PartialEq, Default)]
pub enum LightmapDetail {
    /// The detail region is found from the geometry (the module comment).
    #[default]
    Automatic,
    /// One texel size everywhere.
    Uniform,
    /// The detail region is the given box.
    Bounds { low: Vec3, high: Vec3 },
}

/// Settings of the `[lightmap]` section: the layout and, when given, the
/// width of full-density margin around the detail region in metres.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct LightmapLayout {
    pub detail: LightmapDetail,
    pub margin: Option<f32>,
    /// Charts near the scene file's point and spot lights get finer texels
    /// (`refine_near_lights`, on unless set to false).
    pub refine_near_lights: bool,
    /// Surfaces are cut along the feet of walls that stand on them, so
    /// the atlas's charts end there (`cut_under_walls`, on unless set to
    /// false; see [`crate::seams`]).
    pub cut_under_walls: bool,
}

impl Default for LightmapLayout {
    fn default() -> Self {
        Self {
            detail: LightmapDetail::default(),
            margin: None,
            refine_near_lights: true,
            cut_under_walls: true,
        }
    }
}

/// Rings beyond the last one all take its texel size (4^4 = 256 times the
/// detail region's); it starts 31 margins out.
pub const MAX_RING: u32 = 4;

/// A triangle larger than this share of the surface does not define the
/// automatic detail region (a ground plane of a few triangles); every
/// triangle of a room's walls, floor and ceiling is below it.
const OUTLIER_AREA_SHARE: f64 = 1.0 / 8.0;

/// The full-density box and the rings around it.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct DetailRegion {
    pub low: Vec3,
    pub high: Vec3,
    /// Width of ring 0 in metres.
    pub margin: f32,
}

impl DetailRegion {
    /// The region `layout` asks for, or `None` when the lightmap is uniform:
    /// by request, or because no geometry reaches past ring 0.
    pub fn of(mesh: &Mesh, layout: LightmapLayout) -> Option<Self> {
        let (low, high) = match layout.detail {
            LightmapDetail::Uniform => return None,
            LightmapDetail::Bounds { low, high } => (low, high),
            LightmapDetail::Automatic => automatic_bounds(mesh)?,
        };
        let margin = layout
            .margin
            .unwrap_or_else(|| (0.1 * (high - low).length()).max(1.0));
        let region = Self { low, high, margin };
        let (mesh_low, mesh_high) = mesh.bounds();
        let reaches_out = region.gap(mesh_low, mesh_high) > 0.0
            || (0..3).any(|axis| {
                mesh_low[axis] < low[axis] - margin || mesh_high[axis] > high[axis] + margin
            });
        reaches_out.then_some(region)
    }

    /// The box as `[x, y, z] .. [x, y, z]` to a tenth of a metre, for
    /// messages.
    pub fn describe_box(&self) -> String {
        let [a, b, c] = self.low.to_array();
        let [d, e, f] = self.high.to_array();
        format!("[{a:.1}, {b:.1}, {c:.1}] .. [{d:.1}, {e:.1}, {f:.1}]")
    }

    /// Outer edge of ring `ring`, in metres beyond the box.
    pub fn ring_edge(&self, ring: u32) -> f32 {
        self.margin * ((1u32 << (ring + 1)) - 1) as f32
    }

    /// Largest per-axis distance from the box to the box `low..high` (0
    /// when they overlap on every axis): the rings are boxes, so this
    /// Chebyshev distance says which ring the nearest point is in.
    pub fn gap(&self, low: Vec3, high: Vec3) -> f32 {
        let below = self.low - high;
        let above = low - self.high;
        below.max(above).max(Vec3::ZERO).max_element()
    }

    /// Ring of the box `low..high` (a triangle's bounds, or a point): the
    /// number of ring boxes it lies wholly outside. Compared against the
    /// very plane coordinates the cuts use, so a piece cut exactly on a
    /// ring's outer plane starts the next ring (a distance computed by
    /// subtraction can round below the ring's width and put it back).
    pub fn ring_of_bounds(&self, low: Vec3, high: Vec3) -> u32 {
        (0..MAX_RING)
            .take_while(|&ring| {
                let edge = self.ring_edge(ring);
                (0..3).any(|axis| {
                    high[axis] <= self.low[axis] - edge || low[axis] >= self.high[axis] + edge
                })
            })
            .count() as u32
    }

    /// Ring of a triangle: that of its nearest point to the box, so a small
    /// triangle across a ring's edge takes the finer texels.
    pub fn ring_of_triangle(&self, mesh: &Mesh, triangle: usize) -> u32 {
        let [a, b, c] = mesh.vertices(triangle);
        self.ring_of_bounds(a.min(b).min(c), a.max(b).max(c))
    }

    /// Texel size of `ring` relative to the detail region's.
    pub fn texel_scale(ring: u32) -> f32 {
        (1u32 << (2 * ring.min(MAX_RING))) as f32
    }

    /// Planes between rings along `axis`, below and above the box.
    fn planes(&self, axis: usize) -> impl Iterator<Item = f32> + '_ {
        (0..MAX_RING).flat_map(move |ring| {
            let edge = self.ring_edge(ring);
            [self.low[axis] - edge, self.high[axis] + edge]
        })
    }
}

impl Scene {
    /// This scene's detail region (see [`crate::detail`]).
    pub fn detail_region(&self) -> Option<DetailRegion> {
        DetailRegion::of(&self.mesh, self.lightmap_layout)
    }

    /// Each triangle's density relative to the detail region's, the
    /// lightmap's: 1 within ring 0, 1/16^k in ring k (texel edges 4^k
    /// longer). `None` when the lightmap is uniform. Techniques that spread
    /// points by area weight it by this, so that a ground plane far
    /// outside does not take them from the building.
    pub fn detail_weights(&self) -> Option<Vec<f32>> {
        let region = self.detail_region()?;
        Some(
            (0..self.mesh.triangles.len())
                .map(|triangle| {
                    let scale =
                        DetailRegion::texel_scale(region.ring_of_triangle(&self.mesh, triangle));
                    1.0 / (scale * scale)
                })
                .collect(),
        )
    }

    /// The detail region and its full-density margin, clipped to the
    /// mesh's bounds, when the lightmap coarsens outside them; else `None`.
    pub fn detail_bounds(&self) -> Option<(Vec3, Vec3)> {
        let region = self.detail_region()?;
        let (low, high) = self.mesh.bounds();
        Some((
            (region.low - Vec3::splat(region.margin)).max(low),
            (region.high + Vec3::splat(region.margin)).min(high),
        ))
    }

    /// Where the scene's content is: [`Self::detail_bounds`], else the
    /// mesh's bounds. An irradiance volume covers this, not a ground plane
    /// 200 m across (the classroom's volume was 16 x 1 x 16 voxels of 14 m).
    pub fn content_bounds(&self) -> (Vec3, Vec3) {
        self.detail_bounds().unwrap_or_else(|| self.mesh.bounds())
    }
}

/// Bounds of the triangles that each hold less than [`OUTLIER_AREA_SHARE`]
/// of the surface; `None` when there are none.
fn automatic_bounds(mesh: &Mesh) -> Option<(Vec3, Vec3)> {
    let limit = (mesh.total_area() * OUTLIER_AREA_SHARE) as f32;
    let mut low = Vec3::splat(f32::INFINITY);
    let mut high = Vec3::splat(f32::NEG_INFINITY);
    for triangle in 0..mesh.triangles.len() {
        if mesh.area(triangle) < limit {
            for vertex in mesh.vertices(triangle) {
                low = low.min(vertex);
                high = high.max(vertex);
            }
        }
    }
    (low.cmple(high).all()).then_some((low, high))
}

/// What [`split_for_detail`] did: for each triangle before, the range of
/// triangles it became, and how many triangles were cut.
pub struct DetailSplit {
    pub pieces_of: Vec<std::ops::Range<u32>>,
    pub cut: usize,
}

/// Cuts every triangle that spans rings and is longer than a margin along
/// the planes between rings, so each piece lies in one ring. Emissive
/// triangles stay whole (they are lights). Pieces keep the triangle's
/// winding and material; their texture and lightmap UVs are interpolated.
/// Cuts are exact: a vertex on a plane gets the plane's coordinate, and an
/// edge is always interpolated from its lower end, so the two pieces on
/// either side of a cut share their vertices bit for bit.
pub fn split_for_detail(
    mesh: &mut Mesh,
    region: &DetailRegion,
    emissive: impl Fn(u32) -> bool,
) -> DetailSplit {
    let triangle_count = mesh.triangles.len();
    let mut triangles = Vec::with_capacity(triangle_count);
    let mut material_ids = Vec::with_capacity(triangle_count);
    let mut pieces_of = Vec::with_capacity(triangle_count);
    let mut cut = 0;
    let mut polygons: Vec<Vec<Corner>> = Vec::new();
    for triangle in 0..triangle_count {
        let material = mesh.material_ids[triangle];
        let first = triangles.len() as u32;
        let pieces = if emissive(material) {
            None
        } else {
            cut_triangle(mesh, triangle, region, &mut polygons)
        };
        match pieces {
            None => {
                triangles.push(mesh.triangles[triangle]);
                material_ids.push(material);
            }
            Some(()) => {
                cut += 1;
                push_pieces(mesh, triangle, &polygons, &mut triangles, &mut material_ids);
            }
        }
        pieces_of.push(first..triangles.len() as u32);
    }
    mesh.triangles = triangles;
    mesh.material_ids = material_ids;
    DetailSplit { pieces_of, cut }
}

/// A polygon corner: its position and its barycentric (b1, b2) on the
/// triangle being cut.
#[derive(Clone, Copy, Debug)]
pub(crate) struct Corner {
    pub position: Vec3,
    pub barycentric: Vec2,
}

impl Corner {
    /// The corners of `triangle` as the polygon a cut starts from.
    pub(crate) fn of_triangle(mesh: &Mesh, triangle: usize) -> Vec<Corner> {
        let [a, b, c] = mesh.vertices(triangle);
        vec![
            Corner {
                position: a,
                barycentric: Vec2::ZERO,
            },
            Corner {
                position: b,
                barycentric: Vec2::X,
            },
            Corner {
                position: c,
                barycentric: Vec2::Y,
            },
        ]
    }
}

/// Appends the pieces `polygons` (convex, in the plane of `triangle`) as
/// fans of triangles with `triangle`'s material, their vertices added to
/// the mesh.
pub(crate) fn push_pieces(
    mesh: &mut Mesh,
    triangle: usize,
    polygons: &[Vec<Corner>],
    triangles: &mut Vec<[u32; 3]>,
    material_ids: &mut Vec<u32>,
) {
    let material = mesh.material_ids[triangle];
    let corners = mesh.triangles[triangle];
    let normal = mesh.geometric_normal(triangle);
    let smallest = mesh.area(triangle) * 1e-7;
    for polygon in polygons {
        for fan in 1..polygon.len().saturating_sub(1) {
            let piece = [polygon[0], polygon[fan], polygon[fan + 1]];
            let doubled = (piece[1].position - piece[0].position)
                .cross(piece[2].position - piece[0].position);
            // Cuts through a vertex leave slivers of no area, and
            // rounding can flip one: neither covers anything.
            if 0.5 * doubled.length() <= smallest || doubled.dot(normal) <= 0.0 {
                continue;
            }
            let indices = piece.map(|corner| push_vertex(mesh, corners, corner) as u32);
            triangles.push(indices);
            material_ids.push(material);
        }
    }
}

/// Cuts `triangle` into `polygons` when it spans rings and is long enough
/// to matter; `None` leaves it whole.
fn cut_triangle(
    mesh: &Mesh,
    triangle: usize,
    region: &DetailRegion,
    polygons: &mut Vec<Vec<Corner>>,
) -> Option<()> {
    let [a, b, c] = mesh.vertices(triangle);
    let longest = (b - a).length().max((c - b).length()).max((a - c).length());
    if longest <= region.margin {
        return None;
    }
    let nearest = region.ring_of_triangle(mesh, triangle);
    let farthest = [a, b, c]
        .iter()
        .map(|&vertex| region.ring_of_bounds(vertex, vertex))
        .max()
        .unwrap_or(0);
    if nearest == farthest {
        return None;
    }
    polygons.clear();
    polygons.push(Corner::of_triangle(mesh, triangle));
    let (low, high) = (a.min(b).min(c), a.max(b).max(c));
    for axis in 0..3 {
        for plane in region.planes(axis) {
            if plane <= low[axis] || plane >= high[axis] {
                continue;
            }
            let mut next = Vec::with_capacity(polygons.len() * 2);
            for polygon in polygons.drain(..) {
                let (below, above) = clip(&polygon, axis, plane);
                next.extend([below, above].into_iter().filter(|side| side.len() >= 3));
            }
            *polygons = next;
        }
    }
    Some(())
}

/// Splits a convex polygon by the plane `position[axis] = plane`
/// (Sutherland-Hodgman, both sides at once; order and winding kept).
fn clip(polygon: &[Corner], axis: usize, plane: f32) -> (Vec<Corner>, Vec<Corner>) {
    let mut below = Vec::with_capacity(polygon.len() + 1);
    let mut above = Vec::with_capacity(polygon.len() + 1);
    for (index, &from) in polygon.iter().enumerate() {
        let to = polygon[(index + 1) % polygon.len()];
        let from_side = from.position[axis] - plane;
        let to_side = to.position[axis] - plane;
        if from_side <= 0.0 {
            below.push(from);
        }
        if from_side >= 0.0 {
            above.push(from);
        }
        if (from_side < 0.0 && to_side > 0.0) || (from_side > 0.0 && to_side < 0.0) {
            let crossing = crossing(from, to, axis, plane);
            below.push(crossing);
            above.push(crossing);
        }
    }
    (below, above)
}

/// Where the edge between `p` and `q` crosses the plane, computed from its
/// lower end so both pieces that share the edge get the same bits.
fn crossing(p: Corner, q: Corner, axis: usize, plane: f32) -> Corner {
    let (start, end) = if p.position[axis] <= q.position[axis] {
        (p, q)
    } else {
        (q, p)
    };
    let t = (plane - start.position[axis]) / (end.position[axis] - start.position[axis]);
    // start + (end - start) t, not glam's lerp (start (1 - t) + end t),
    // which moves a coordinate the two ends share: a piece on a plane of
    // one axis must stay exactly on it when cut along another.
    let mut position = start.position + (end.position - start.position) * t;
    position[axis] = plane;
    Corner {
        position,
        barycentric: start.barycentric + (end.barycentric - start.barycentric) * t,
    }
}

/// Appends a vertex at `corner` of the triangle with vertex indices
/// `corners`, its UV sets interpolated; returns its index.
pub(crate) fn push_vertex(mesh: &mut Mesh, corners: [u32; 3], corner: Corner) -> usize {
    let [b1, b2] = corner.barycentric.to_array();
    let weights = [1.0 - b1 - b2, b1, b2];
    let interpolate = |values: &[Vec2]| {
        corners
            .iter()
            .zip(weights)
            .map(|(&vertex, weight)| values[vertex as usize] * weight)
            .sum::<Vec2>()
    };
    if !mesh.texcoords.is_empty() {
        let uv = interpolate(&mesh.texcoords);
        mesh.texcoords.push(uv);
    }
    if !mesh.lightmap_uvs.is_empty() {
        let uv = interpolate(&mesh.lightmap_uvs);
        mesh.lightmap_uvs.push(uv);
    }
    mesh.positions.push(corner.position);
    mesh.positions.len() - 1
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A 100 m ground of two triangles and a 4 m room-sized cluster of small
    /// triangles at its centre.
    fn ground_and_room() -> Mesh {
        let mut mesh = Mesh::default();
        let ground = [
            Vec3::new(-50.0, 0.0, -50.0),
            Vec3::new(-50.0, 0.0, 50.0),
            Vec3::new(50.0, 0.0, 50.0),
            Vec3::new(50.0, 0.0, -50.0),
        ];
        mesh.positions.extend(ground);
        mesh.triangles.extend([[0, 1, 2], [0, 2, 3]]);
        // Walls of a 4 m room, each a quad of two triangles.
        for (x, z) in [(-2.0, -2.0), (2.0, -2.0), (2.0, 2.0), (-2.0, 2.0)] {
            let base = mesh.positions.len() as u32;
            mesh.positions.extend([
                Vec3::new(x, 0.0, z),
                Vec3::new(-z, 0.0, x),
                Vec3::new(-z, 3.0, x),
                Vec3::new(x, 3.0, z),
            ]);
            mesh.triangles
                .extend([[base, base + 1, base + 2], [base, base + 2, base + 3]]);
        }
        mesh.material_ids = vec![0; mesh.triangles.len()];
        mesh
    }

    #[test]
    fn a_ground_plane_does_not_stretch_the_automatic_region() {
        let mesh = ground_and_room();
        let region = DetailRegion::of(&mesh, LightmapLayout::default()).unwrap();
        assert_eq!(region.low, Vec3::new(-2.0, 0.0, -2.0));
        assert_eq!(region.high, Vec3::new(2.0, 3.0, 2.0));
        // 10 % of the box's 6.4 m diagonal is below the 1 m floor.
        assert_eq!(region.margin, 1.0);
        let uniform = LightmapLayout {
            detail: LightmapDetail::Uniform,
            ..LightmapLayout::default()
        };
        assert_eq!(DetailRegion::of(&mesh, uniform), None);
    }

    #[test]
    fn a_room_without_outliers_keeps_a_uniform_lightmap() {
        let mut mesh = ground_and_room();
        // Without the ground the walls are all there is: nothing reaches out.
        mesh.triangles.drain(..2);
        mesh.material_ids.drain(..2);
        mesh.positions.drain(..4);
        for triangle in &mut mesh.triangles {
            for vertex in triangle.iter_mut() {
                *vertex -= 4;
            }
        }
        assert_eq!(DetailRegion::of(&mesh, LightmapLayout::default()), None);
    }

    #[test]
    fn rings_double_their_width_and_texel_size() {
        let region = DetailRegion {
            low: Vec3::ZERO,
            high: Vec3::ONE,
            margin: 2.0,
        };
        assert_eq!(region.ring_edge(0), 2.0);
        assert_eq!(region.ring_edge(1), 6.0);
        assert_eq!(region.ring_edge(2), 14.0);
        let ring_at =
            |x: f32| region.ring_of_bounds(Vec3::new(x, 0.5, 0.5), Vec3::new(x, 0.5, 0.5));
        assert_eq!(ring_at(0.5), 0);
        assert_eq!(ring_at(2.99), 0);
        assert_eq!(ring_at(3.0), 1, "on ring 0's outer plane is ring 1");
        assert_eq!(ring_at(-13.5), 2);
        assert_eq!(ring_at(1e9), MAX_RING);
        assert_eq!(DetailRegion::texel_scale(0), 1.0);
        assert_eq!(DetailRegion::texel_scale(3), 64.0);
        assert_eq!(DetailRegion::texel_scale(MAX_RING + 1), 256.0);
        // Chebyshev: 3 m out on x and 1 m out on y is 3 m out.
        assert_eq!(
            region.gap(Vec3::new(4.0, 2.0, 0.5), Vec3::new(5.0, 2.0, 0.5)),
            3.0
        );
    }

    #[test]
    fn cut_pieces_cover_the_ground_once_each_in_one_ring() {
        let mut mesh = ground_and_room();
        let area_before = mesh.total_area();
        let region = DetailRegion::of(&mesh, LightmapLayout::default()).unwrap();
        let split = split_for_detail(&mut mesh, &region, |_| false);
        assert_eq!(split.cut, 2, "both ground triangles span rings");
        assert_eq!(split.pieces_of[2].len(), 1, "walls stay whole");
        assert!((mesh.total_area() - area_before).abs() < 1e-6 * area_before);
        for triangle in 0..mesh.triangles.len() {
            let [a, b, c] = mesh.vertices(triangle);
            let rings = [a, b, c].map(|vertex| region.ring_of_bounds(vertex, vertex));
            let nearest = region.ring_of_triangle(&mesh, triangle);
            // A piece's far corners lie at most on its ring's outer plane.
            assert!(
                rings.iter().all(|&ring| ring <= nearest + 1),
                "triangle {triangle} spans rings {rings:?} from {nearest}: {:?}",
                [a, b, c]
            );
            assert!(mesh.geometric_normal(triangle).y > 0.99 || triangle >= 2);
        }
        // The ground's centre is in the box: pieces of ring 0 exist.
        assert!((0..mesh.triangles.len()).any(|t| {
            mesh.vertices(t).iter().all(|v| v.y == 0.0) && region.ring_of_triangle(&mesh, t) == 0
        }));
    }

    #[test]
    fn pieces_share_their_cut_vertices_exactly() {
        let mut mesh = ground_and_room();
        let region = DetailRegion::of(&mesh, LightmapLayout::default()).unwrap();
        split_for_detail(&mut mesh, &region, |_| false);
        // Every edge of a ground piece inside the ground is shared by
        // another piece with the same two end points (no T-junctions, no
        // cracks); edges on the ground's border are not.
        let mut edges = std::collections::HashMap::new();
        for triangle in 0..mesh.triangles.len() {
            let vertices = mesh.vertices(triangle);
            if vertices.iter().any(|v| v.y != 0.0) {
                continue;
            }
            for corner in 0..3 {
                let key = |p: Vec3| [p.x.to_bits(), p.z.to_bits()];
                let (p, q) = (key(vertices[corner]), key(vertices[(corner + 1) % 3]));
                *edges.entry((p.min(q), p.max(q))).or_insert(0) += 1;
            }
        }
        let on_border =
            |[x, z]: [u32; 2]| f32::from_bits(x).abs() == 50.0 || f32::from_bits(z).abs() == 50.0;
        for ((p, q), count) in edges {
            if on_border(p) && on_border(q) {
                continue;
            }
            assert_eq!(count, 2, "edge {p:?}-{q:?} is used {count} times");
        }
    }
}
