//! Surfels: equal-area discs over every triangle (section 4.2). Triangles
//! are sampled in proportion to area along one Halton sequence; the area of
//! triangles too small for a surfel is carried on until it spawns one; then
//! surfels repel their nearest neighbours in their tangent planes.

use glam::{Vec2, Vec3};
use relight_core::sampling::{halton2, uniform_triangle};
use relight_core::Rgb;
use relight_scene::atlas::closest_barycentric;
use relight_scene::Scene;

/// Surfels as struct of arrays; every surfel has area `area`.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Surfels {
    pub positions: Vec<Vec3>,
    pub normals: Vec<Vec3>,
    pub triangles: Vec<u32>,
    pub barycentrics: Vec<Vec2>,
    pub albedos: Vec<Rgb>,
    /// Emitted radiance of the surface under the surfel.
    pub emission: Vec<Rgb>,
    /// The area of one surfel: the scene's area over the surfel count.
    pub area: f32,
}

impl Surfels {
    pub fn len(&self) -> usize {
        self.positions.len()
    }

    pub fn is_empty(&self) -> bool {
        self.positions.is_empty()
    }

    /// Keeps the surfels for which `keep` is true.
    pub fn retain(&mut self, keep: &[bool]) {
        let order: Vec<u32> = (0..self.len() as u32)
            .filter(|&i| keep[i as usize])
            .collect();
        self.permute(&order);
    }

    /// Reorders every array by `order` (new index -> old index).
    pub fn permute(&mut self, order: &[u32]) {
        fn apply<T: Copy>(values: &mut Vec<T>, order: &[u32]) {
            *values = order.iter().map(|&old| values[old as usize]).collect();
        }
        apply(&mut self.positions, order);
        apply(&mut self.normals, order);
        apply(&mut self.triangles, order);
        apply(&mut self.barycentrics, order);
        apply(&mut self.albedos, order);
        apply(&mut self.emission, order);
    }
}

/// Places about `count` surfels over `scene` and relaxes them
/// `relaxation_steps` times.
pub fn place_surfels(scene: &Scene, count: usize, relaxation_steps: u32) -> Surfels {
    let mesh = &scene.mesh;
    let total_area: f64 = mesh.total_area();
    let mut surfels = Surfels {
        area: (total_area / count.max(1) as f64) as f32,
        ..Default::default()
    };
    if count == 0 || total_area <= 0.0 {
        return surfels;
    }
    let surfel_area = total_area / count as f64;
    let mut carried = 0.0f64;
    let mut halton_index = 1u64;
    for triangle in 0..mesh.triangles.len() {
        let area = mesh.area(triangle) as f64;
        if area.is_nan() || area <= 0.0 {
            continue;
        }
        carried += area;
        // A small epsilon so a surfel whose area is exactly reached spawns.
        let spawn = ((carried / surfel_area) + 1e-9).floor() as usize;
        if spawn == 0 {
            continue;
        }
        carried -= spawn as f64 * surfel_area;
        let normal = mesh.geometric_normal(triangle);
        let corners = mesh.vertices(triangle);
        for _ in 0..spawn {
            let barycentric = uniform_triangle(halton2(halton_index));
            halton_index += 1;
            push_surfel(scene, &mut surfels, triangle, corners, normal, barycentric);
        }
    }
    for _ in 0..relaxation_steps {
        relax(scene, &mut surfels);
    }
    surfels
}

fn push_surfel(
    scene: &Scene,
    surfels: &mut Surfels,
    triangle: usize,
    corners: [Vec3; 3],
    normal: Vec3,
    barycentric: Vec2,
) {
    let position = corners[0] * (1.0 - barycentric.x - barycentric.y)
        + corners[1] * barycentric.x
        + corners[2] * barycentric.y;
    surfels.positions.push(position);
    surfels.normals.push(normal);
    surfels.triangles.push(triangle as u32);
    surfels.barycentrics.push(barycentric);
    surfels.albedos.push(scene.albedo_at(triangle, barycentric));
    surfels.emission.push(scene.material_of(triangle).emission);
}

/// One relaxation step: every surfel moves away from neighbours closer than
/// twice its radius (with normals within 60 degrees, so walls meeting at a
/// corner do not push each other), in its tangent plane, and stays on its
/// own triangle.
fn relax(scene: &Scene, surfels: &mut Surfels) {
    use rayon::prelude::*;
    let radius = (surfels.area / std::f32::consts::PI).sqrt();
    let reach = 2.0 * radius;
    let grid = PointGrid::new(&surfels.positions, reach);
    let moved: Vec<(Vec3, Vec2)> = (0..surfels.len())
        .into_par_iter()
        .map(|index| {
            let position = surfels.positions[index];
            let normal = surfels.normals[index];
            let mut push = Vec3::ZERO;
            grid.for_each_near(position, |other| {
                if other as usize == index {
                    return;
                }
                let offset = position - surfels.positions[other as usize];
                let distance = offset.length();
                if distance >= reach || normal.dot(surfels.normals[other as usize]) < 0.5 {
                    return;
                }
                let away = if distance > 1e-9 {
                    offset / distance
                } else {
                    // Coincident surfels: a fixed tangent per pair order.
                    let (tangent, _) = relight_core::sampling::orthonormal_basis(normal);
                    if (other as usize) < index {
                        tangent
                    } else {
                        -tangent
                    }
                };
                // Half the overlap: the neighbour moves the other half.
                push += away * (0.5 * (reach - distance));
            });
            let tangential = push - normal * normal.dot(push);
            let triangle = surfels.triangles[index] as usize;
            let corners = scene.mesh.vertices(triangle);
            let target = position + tangential;
            let barycentric = barycentric_on_triangle(corners, target);
            (
                corners[0] * (1.0 - barycentric.x - barycentric.y)
                    + corners[1] * barycentric.x
                    + corners[2] * barycentric.y,
                barycentric,
            )
        })
        .collect();
    for (index, (position, barycentric)) in moved.into_iter().enumerate() {
        surfels.positions[index] = position;
        surfels.barycentrics[index] = barycentric;
        let triangle = surfels.triangles[index] as usize;
        surfels.albedos[index] = scene.albedo_at(triangle, barycentric);
    }
}

/// The barycentric coordinates (b1, b2) of the point of the triangle closest
/// to `point` projected into the triangle's plane.
fn barycentric_on_triangle(corners: [Vec3; 3], point: Vec3) -> Vec2 {
    let edge1 = corners[1] - corners[0];
    let edge2 = corners[2] - corners[0];
    // 2D frame of the triangle's plane.
    let axis_u = edge1.normalize_or_zero();
    let normal = edge1.cross(edge2);
    let axis_v = normal.cross(edge1).normalize_or_zero();
    let flat = |p: Vec3| Vec2::new((p - corners[0]).dot(axis_u), (p - corners[0]).dot(axis_v));
    let uvs = [Vec2::ZERO, flat(corners[1]), flat(corners[2])];
    closest_barycentric(&uvs, flat(point)).1
}

/// Points bucketed in a uniform grid of cells `cell` wide.
pub struct PointGrid {
    origin: Vec3,
    cell: f32,
    dims: [usize; 3],
    starts: Vec<u32>,
    items: Vec<u32>,
}

impl PointGrid {
    pub fn new(points: &[Vec3], cell: f32) -> Self {
        let (mut lo, mut hi) = (Vec3::splat(f32::MAX), Vec3::splat(f32::MIN));
        for point in points {
            lo = lo.min(*point);
            hi = hi.max(*point);
        }
        if points.is_empty() {
            lo = Vec3::ZERO;
            hi = Vec3::ZERO;
        }
        // Cap the cell count: a coarser grid only costs more comparisons.
        let mut cell = cell.max(1e-6);
        let extent = hi - lo;
        while ((extent / cell).floor() + 1.0).element_product() > (4 * points.len() + 64) as f32 {
            cell *= 1.5;
        }
        let dims = [
            (extent.x / cell) as usize + 1,
            (extent.y / cell) as usize + 1,
            (extent.z / cell) as usize + 1,
        ];
        let mut grid = PointGrid {
            origin: lo,
            cell,
            dims,
            starts: vec![0; dims[0] * dims[1] * dims[2] + 1],
            items: vec![0; points.len()],
        };
        let cells: Vec<usize> = points.iter().map(|p| grid.cell_index(*p)).collect();
        for &cell in &cells {
            grid.starts[cell + 1] += 1;
        }
        for index in 1..grid.starts.len() {
            grid.starts[index] += grid.starts[index - 1];
        }
        let mut fill = grid.starts.clone();
        for (point, &cell) in cells.iter().enumerate() {
            grid.items[fill[cell] as usize] = point as u32;
            fill[cell] += 1;
        }
        grid
    }

    fn coordinates(&self, point: Vec3) -> [usize; 3] {
        let local = ((point - self.origin) / self.cell).max(Vec3::ZERO);
        [
            (local.x as usize).min(self.dims[0] - 1),
            (local.y as usize).min(self.dims[1] - 1),
            (local.z as usize).min(self.dims[2] - 1),
        ]
    }

    fn cell_index(&self, point: Vec3) -> usize {
        let [x, y, z] = self.coordinates(point);
        (z * self.dims[1] + y) * self.dims[0] + x
    }

    /// Calls `visit` with every point in the 27 cells around `point`, which
    /// holds every point within one cell width of it.
    pub fn for_each_near(&self, point: Vec3, mut visit: impl FnMut(u32)) {
        let [cx, cy, cz] = self.coordinates(point);
        for z in cz.saturating_sub(1)..(cz + 2).min(self.dims[2]) {
            for y in cy.saturating_sub(1)..(cy + 2).min(self.dims[1]) {
                for x in cx.saturating_sub(1)..(cx + 2).min(self.dims[0]) {
                    let cell = (z * self.dims[1] + y) * self.dims[0] + x;
                    for &item in
                        &self.items[self.starts[cell] as usize..self.starts[cell + 1] as usize]
                    {
                        visit(item);
                    }
                }
            }
        }
    }
}
