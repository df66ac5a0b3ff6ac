//! Cache placement (section 4.4): one cache per covered texel of a lightmap
//! atlas for the static geometry (its gutters filled by dilation through an
//! index, not by extra caches) and a uniform grid for dynamic objects and
//! points in space. Caches that sit behind or inside geometry (the paper's
//! Figure 9a) move to a nearby free spot or, in the grid, drop out.

use glam::Vec3;
use rayon::prelude::*;
use relight_scene::atlas::{Atlas, TexelDensity};
use relight_technique::{SceneContext, TechniqueError};

/// The atlas PIC's lightmap caches use: the scene's own when it has at most
/// `target` receivers (or `target` is 0), otherwise one built at the texel
/// size that gives about `target` receivers.
pub fn cache_atlas(
    context: &SceneContext,
    target: usize,
) -> Result<(Option<Atlas>, f32), TechniqueError> {
    let own = context.atlas.receivers.len();
    if target == 0 || own <= target {
        return Ok((None, 0.0));
    }
    // Receivers scale roughly with 1 / texel^2; chart overhead makes it
    // sub-quadratic, so iterate on the measured count.
    let mut metres = context.atlas.metres_per_texel.max(1e-4) * (own as f32 / target as f32).sqrt();
    let mut best: Option<(Atlas, f32)> = None;
    // Trial atlases are only counted; relocation (rays per receiver, and it
    // never changes the count) runs once, on the chosen one.
    for _ in 0..6 {
        let atlas = Atlas::build_unrefined(&context.scene, TexelDensity::MetresPerTexel(metres))
            .map_err(|error| TechniqueError::Other(error.to_string()))?;
        let count = atlas.receivers.len();
        let ratio = count as f32 / target as f32;
        let better = best.as_ref().is_none_or(|(previous, _)| {
            (previous.receivers.len() as f32 / target as f32).ln().abs() > ratio.ln().abs()
        });
        if better {
            best = Some((atlas, metres));
        }
        if (0.9..=1.1).contains(&ratio) {
            break;
        }
        metres *= ratio.sqrt().clamp(0.5, 2.0);
    }
    let (mut atlas, metres) = best.expect("at least one atlas was built");
    relight_technique::relocate_receivers(&context.scene, &context.bvh, &mut atlas);
    Ok((Some(atlas), metres))
}

/// Where the caches are: the lightmap caches first (one per receiver of the
/// cache atlas, hemispherical around its normal), then the grid caches
/// (spherical, normal zero).
#[derive(Clone, Debug, Default, PartialEq)]
pub struct CachePlacement {
    pub positions: Vec<Vec3>,
    pub normals: Vec<Vec3>,
    pub lightmap_count: usize,
    pub grid: GridLayout,
    /// Grid point -> cache index, or `u32::MAX` where the point was inside
    /// geometry with no free spot nearby.
    pub grid_cache: Vec<u32>,
    /// Lightmap caches moved out from behind geometry, and those that found
    /// no free spot on their triangle and stayed.
    pub moved: usize,
    pub stuck: usize,
    pub grid_moved: usize,
    pub grid_culled: usize,
}

/// Grid points at the centres of `dims` cells over the scene's bounds.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct GridLayout {
    pub dims: [u32; 3],
    pub origin: Vec3,
    pub step: Vec3,
}

impl GridLayout {
    /// About `cells` points over the box `lo..hi`, cells as cubic as fits.
    pub fn new(lo: Vec3, hi: Vec3, cells: usize, dims: Option<[u32; 3]>) -> Self {
        let extent = (hi - lo).max(Vec3::splat(1e-4));
        let dims = dims.unwrap_or_else(|| {
            let side = (extent.element_product() / cells.max(1) as f32).cbrt();
            [
                ((extent.x / side).round() as u32).max(1),
                ((extent.y / side).round() as u32).max(1),
                ((extent.z / side).round() as u32).max(1),
            ]
        });
        GridLayout {
            dims,
            origin: lo,
            step: extent / Vec3::new(dims[0] as f32, dims[1] as f32, dims[2] as f32),
        }
    }

    pub fn point_count(&self) -> usize {
        self.dims.iter().map(|&d| d as usize).product()
    }

    pub fn position(&self, x: u32, y: u32, z: u32) -> Vec3 {
        self.origin + (Vec3::new(x as f32, y as f32, z as f32) + 0.5) * self.step
    }

    pub fn index(&self, x: u32, y: u32, z: u32) -> usize {
        ((z * self.dims[1] + y) * self.dims[0] + x) as usize
    }

    /// The 8 grid points around `position` and their trilinear weights.
    pub fn corners(&self, position: Vec3) -> [(usize, f32); 8] {
        let local = (position - self.origin) / self.step - 0.5;
        let mut base = [0u32; 3];
        let mut fraction = [0.0f32; 3];
        for axis in 0..3 {
            let max = self.dims[axis] as f32 - 1.0;
            let clamped = local[axis].clamp(0.0, max);
            let floor = clamped.floor().min((max - 1.0).max(0.0));
            base[axis] = floor as u32;
            fraction[axis] = if max > 0.0 { clamped - floor } else { 0.0 };
        }
        std::array::from_fn(|corner| {
            let offset = [corner & 1, (corner >> 1) & 1, (corner >> 2) & 1];
            let mut weight = 1.0;
            let mut coordinate = [0u32; 3];
            for axis in 0..3 {
                let step = offset[axis] as u32;
                coordinate[axis] = (base[axis] + step).min(self.dims[axis] - 1);
                weight *= if step == 1 {
                    fraction[axis]
                } else {
                    1.0 - fraction[axis]
                };
            }
            (
                self.index(coordinate[0], coordinate[1], coordinate[2]),
                weight,
            )
        })
    }
}

/// Places the caches: `atlas` receivers and a grid of about `grid_cells`
/// points (or `grid_dims`) over the scene's bounds.
pub fn place_caches(
    context: &SceneContext,
    atlas: &Atlas,
    grid_cells: usize,
    grid_dims: Option<[u32; 3]>,
) -> CachePlacement {
    let receivers = &atlas.receivers;
    // Where the links' rays start (the bake's link epsilon).
    let surface_offset = 4.0 * relight_trace::direct::ray_epsilon_for(&context.bvh);
    let placed: Vec<(Vec3, u8)> = (0..receivers.len())
        .into_par_iter()
        .map(|index| {
            // A cache gathers from where it stands (the link epsilon off
            // its surface), so that is the point tested. A texel point in a
            // crack between two meshes (a column shaft entering its
            // capital) is buried there although most of its texel is in
            // view: it slides within half a texel toward the middle of its
            // triangle to the first free spot, or every link would be
            // hidden and the cache black. A texel that something covers
            // entirely (the ceiling behind the Cornell box's light) finds
            // none and stays buried, dark as the path tracer finds it. A
            // lift off the surface is no way out: it can cross a thin
            // occluder into the room beyond.
            let position = receivers.positions[index];
            let normal = receivers.normals[index];
            let gather_point = |point: Vec3| point + normal * surface_offset;
            if !context.is_inside_geometry(gather_point(position)) {
                return (position, 0);
            }
            let triangle = receivers.triangles[index] as usize;
            let corners = context.scene.mesh.vertices(triangle);
            let centroid = (corners[0] + corners[1] + corners[2]) / 3.0;
            let slide = (centroid - position).clamp_length_max(0.5 * atlas.metres_per_texel);
            for step in 1..=4 {
                let candidate = position + slide * (step as f32 / 4.0);
                if !context.is_inside_geometry(gather_point(candidate)) {
                    return (candidate, 1);
                }
            }
            // No free spot: the cache stays on the surface, buried, and
            // reads the darkness the path tracer finds there.
            (position, 2)
        })
        .collect();
    let mut placement = CachePlacement {
        lightmap_count: receivers.len(),
        ..Default::default()
    };
    for (index, (position, outcome)) in placed.into_iter().enumerate() {
        placement.positions.push(position);
        placement.normals.push(receivers.normals[index]);
        match outcome {
            1 => placement.moved += 1,
            2 => placement.stuck += 1,
            _ => {}
        }
    }
    let (lo, hi) = context.scene.mesh.bounds();
    let grid = GridLayout::new(lo, hi, grid_cells, grid_dims);
    placement.grid = grid;
    let points: Vec<(u32, u32, u32)> = (0..grid.dims[2])
        .flat_map(|z| {
            (0..grid.dims[1]).flat_map(move |y| (0..grid.dims[0]).map(move |x| (x, y, z)))
        })
        .collect();
    let free: Vec<(Option<Vec3>, bool)> = points
        .par_iter()
        .map(|&(x, y, z)| {
            let position = grid.position(x, y, z);
            if !context.is_inside_geometry(position) {
                return (Some(position), false);
            }
            for dz in -1..=1 {
                for dy in -1..=1 {
                    for dx in -1..=1 {
                        if (dx, dy, dz) == (0, 0, 0) {
                            continue;
                        }
                        let candidate = position
                            + Vec3::new(dx as f32, dy as f32, dz as f32) * grid.step * 0.45;
                        if !context.is_inside_geometry(candidate) {
                            return (Some(candidate), true);
                        }
                    }
                }
            }
            (None, false)
        })
        .collect();
    for (position, moved) in free {
        match position {
            Some(position) => {
                placement.grid_cache.push(placement.positions.len() as u32);
                placement.positions.push(position);
                placement.normals.push(Vec3::ZERO);
                placement.grid_moved += moved as usize;
            }
            None => {
                placement.grid_cache.push(u32::MAX);
                placement.grid_culled += 1;
            }
        }
    }
    placement
}
