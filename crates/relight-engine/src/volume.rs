//! Irradiance volumes for dynamic objects: a box of voxels, each holding
//! the indirect light arriving from six axis directions (an ambient cube),
//! laid out as Bevy's `IrradianceVolume` texture.
//!
//! Bevy's layout, from its shader `irradiance_volume.wgsl` (Bevy 0.19; the
//! doc comment of `IrradianceVolume` describes the halves the other way
//! round): a grid of Rx x Ry x Rz voxels is a 3D texture of Rx x 2Ry x 3Rz
//! texels. Voxel (x, y, z)'s value for the face whose world normal points
//! along axis a (0 X, 1 Y, 2 Z) is at texel (x, y + Ry if the normal is
//! negative, z + a Rz). The volume is the unit cube [-0.5, 0.5]^3 under the
//! light probe's transform, and voxel i's centre is at (i + 0.5) / R - 0.5
//! along each axis. The shader blends the three faces the normal leans to
//! by the squared normal components.

use crate::units::lightmap_texel;
use glam::{UVec3, Vec3};
use rayon::prelude::*;
use relight_core::Rgb;
use relight_technique::Technique;

/// The six face normals in the order the texture's thirds and halves take
/// them (the `face` of [`VolumeGrid::texel_index`]): +X, -X, +Y, -Y, +Z, -Z.
pub const FACES: [Vec3; 6] = [
    Vec3::X,
    Vec3::NEG_X,
    Vec3::Y,
    Vec3::NEG_Y,
    Vec3::Z,
    Vec3::NEG_Z,
];

/// An axis-aligned box of voxels.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct VolumeGrid {
    pub min: Vec3,
    pub max: Vec3,
    pub resolution: UVec3,
}

impl VolumeGrid {
    /// A grid over `min..max` with `cells_on_longest` voxels along the
    /// box's longest side and cubic voxels (at least one a side).
    pub fn covering(min: Vec3, max: Vec3, cells_on_longest: u32) -> Self {
        let size = (max - min).max(Vec3::splat(1e-6));
        let voxel = size.max_element() / cells_on_longest.max(1) as f32;
        let resolution = (size / voxel).round().max(Vec3::ONE).as_uvec3();
        Self {
            min,
            max,
            resolution,
        }
    }

    pub fn voxel_count(&self) -> usize {
        (self.resolution.x * self.resolution.y * self.resolution.z) as usize
    }

    /// The texture's size: Rx x 2Ry x 3Rz.
    pub fn texture_size(&self) -> UVec3 {
        self.resolution * UVec3::new(1, 2, 3)
    }

    pub fn voxel_centre(&self, voxel: UVec3) -> Vec3 {
        let fraction = (voxel.as_vec3() + 0.5) / self.resolution.as_vec3();
        self.min + (self.max - self.min) * fraction
    }

    /// The light probe's transform: the unit cube centred at the box's
    /// centre, scaled to its size.
    pub fn centre_and_scale(&self) -> (Vec3, Vec3) {
        ((self.min + self.max) * 0.5, self.max - self.min)
    }

    /// Index in the texture (rows of `texture_size().x`, then slices) of
    /// `voxel`'s face `face` (an index into +X, -X, +Y, -Y, +Z, -Z).
    pub fn texel_index(&self, voxel: UVec3, face: usize) -> usize {
        let size = self.texture_size();
        let axis = face as u32 / 2;
        let negative = face as u32 % 2;
        let t = voxel.y + negative * self.resolution.y;
        let p = voxel.z + axis * self.resolution.z;
        ((p * size.y + t) * size.x + voxel.x) as usize
    }

    fn voxel_of(&self, index: usize) -> UVec3 {
        let [x, y, _] = self.resolution.to_array();
        let index = index as u32;
        UVec3::new(index % x, index / x % y, index / (x * y))
    }
}

/// Fills `texels` (the grid's texture, `texture_size` texels) with the
/// technique's indirect irradiance in space at every voxel centre for each
/// of the six face normals, as [`lightmap_texel`]s; voxels in parallel.
pub fn fill_volume(grid: &VolumeGrid, technique: &dyn Technique, texels: &mut [Rgb]) {
    assert_eq!(texels.len(), grid.voxel_count() * 6);
    let faces: Vec<[Rgb; 6]> = (0..grid.voxel_count())
        .into_par_iter()
        .map(|index| {
            let centre = grid.voxel_centre(grid.voxel_of(index));
            FACES.map(|normal| {
                lightmap_texel(technique.indirect_irradiance_in_space(centre, normal))
            })
        })
        .collect();
    for (index, values) in faces.iter().enumerate() {
        let voxel = grid.voxel_of(index);
        for (face, value) in values.iter().enumerate() {
            texels[grid.texel_index(voxel, face)] = *value;
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use relight_technique::{Frame, MemoryEntry, StageTimings, SurfacePoint, TechniqueError};

    /// Light that tells where and which way it was asked.
    struct Probe(StageTimings);

    fn answer(position: Vec3, normal: Vec3) -> Rgb {
        position * 10.0 + Vec3::splat(100.0) + normal
    }

    impl Technique for Probe {
        fn name(&self) -> &'static str {
            "probe"
        }
        fn update(&mut self, _frame: &Frame) -> Result<(), TechniqueError> {
            Ok(())
        }
        fn indirect_irradiance(&self, _point: &SurfacePoint) -> Rgb {
            Rgb::ZERO
        }
        fn indirect_irradiance_in_space(&self, position: Vec3, normal: Vec3) -> Rgb {
            answer(position, normal)
        }
        fn receiver_irradiance(&self) -> Option<&[Rgb]> {
            None
        }
        fn timings(&self) -> &StageTimings {
            &self.0
        }
        fn memory(&self) -> Vec<MemoryEntry> {
            Vec::new()
        }
    }

    /// Bevy's shader (`irradiance_volume_light`) for a point at a voxel
    /// centre, with the texture read at the nearest texel: the texture
    /// coordinates and the halves and thirds it picks, written out.
    fn bevy_shader_lookup(
        grid: &VolumeGrid,
        texels: &[Rgb],
        world_position: Vec3,
        normal: Vec3,
    ) -> Rgb {
        let (centre, scale) = grid.centre_and_scale();
        let unit_pos = (world_position - centre) / scale;
        let atlas_resolution = grid.texture_size().as_vec3();
        let resolution = grid.resolution.as_vec3();
        let stp = ((unit_pos + 0.5) * resolution).clamp(Vec3::splat(0.5), resolution - 0.5);
        let uvw = stp / atlas_resolution;
        let neg = Vec3::select(normal.cmplt(Vec3::ZERO), Vec3::splat(0.5), Vec3::ZERO);
        let fetch = |uvw: Vec3| {
            let texel = (uvw * atlas_resolution).floor().as_uvec3();
            let size = grid.texture_size();
            texels[((texel.z * size.y + texel.y) * size.x + texel.x) as usize]
        };
        let x = fetch(uvw + Vec3::new(0.0, neg.x, 0.0));
        let y = fetch(uvw + Vec3::new(0.0, neg.y, 1.0 / 3.0));
        let z = fetch(uvw + Vec3::new(0.0, neg.z, 2.0 / 3.0));
        let nn = normal * normal;
        x * nn.x + y * nn.y + z * nn.z
    }

    #[test]
    fn bevys_shader_reads_each_voxel_face_where_it_was_written() {
        let grid = VolumeGrid::covering(Vec3::new(-1.0, 0.0, 2.0), Vec3::new(3.0, 2.0, 3.0), 4);
        assert_eq!(grid.resolution, UVec3::new(4, 2, 1));
        let mut texels = vec![Rgb::ZERO; grid.voxel_count() * 6];
        fill_volume(&grid, &Probe(StageTimings::default()), &mut texels);
        for index in 0..grid.voxel_count() {
            let centre = grid.voxel_centre(grid.voxel_of(index));
            for normal in FACES {
                let read = bevy_shader_lookup(&grid, &texels, centre, normal);
                let want = lightmap_texel(answer(centre, normal));
                assert!(
                    (read - want).abs().max_element() < 1e-4,
                    "voxel {index} normal {normal}: {read} against {want}"
                );
            }
        }
    }
}
