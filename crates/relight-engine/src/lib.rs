//! What a game engine takes from relight: the lightmap it uploads and the
//! irradiance volume it samples for dynamic objects, in the engine's units
//! and layouts; KTX2 textures; and the glTF export (`relight export`).
//!
//! Data flow: [`techniques`] names every technique and opens one from a
//! bake file; the technique updates (relight-technique); [`LightmapLayout`]
//! turns its receiver values into lightmap texels each frame, one parallel
//! pass that applies the atlas's dilation as it goes; [`fill_volume`]
//! evaluates its light in space at the voxels of a [`VolumeGrid`] in
//! Bevy's `IrradianceVolume` layout; [`Ktx2Texture`] writes either as a
//! KTX2 file, and [`export_scene`] writes the scene with them as glTF.
//!
//! Units: a texel is E/pi in cd/m^2 at [`LUMENS_PER_WATT`] (one lumen a
//! watt: see its doc), the radiance of a white Lambertian surface under
//! irradiance E, which engines multiply by the base colour. This crate
//! has no engine dependency, so the CLI's export and benchmark use it
//! without building one; the Bevy bridge builds on it.

mod export;
mod ktx2_file;
mod lightmap;
mod primitives;
pub mod techniques;
mod units;

use glam::{Quat, Vec3};
use relight_scene::Light;

/// The lights of frame `index` of `frames` in `relight bench` (and the
/// Bevy bridge's measurement, so both time the same work): point and spot
/// lights circle the vertical axis through `centre` once over the run,
/// directional lights turn their azimuth likewise.
pub fn orbit(lights: &[Light], centre: Vec3, index: u32, frames: u32) -> Vec<Light> {
    let angle = std::f32::consts::TAU * index as f32 / frames.max(1) as f32;
    let rotation = Quat::from_rotation_y(angle);
    lights
        .iter()
        .map(|light| light.rotated_about(centre, rotation))
        .collect()
}
pub mod volume;

pub use export::{export_scene, ExportError, ExportSettings, ExportSummary};
pub use ktx2_file::{f16_of, rgb9e5_gpu, rgb9e5_gpu_decode, Ktx2Error, Ktx2Texture, TexelFormat};
pub use lightmap::{receiver_irradiance, LightmapLayout};
pub use primitives::{moving_primitives, static_primitives, Primitive};
/// The scene file's moving meshes (`[[dynamic]]`): LightSkin moves them
/// through its maps; an engine draws them and tells the technique where
/// they are (`Frame::moving_mesh_poses`).
pub use relight_lightskin::dynamic::{
    load_dynamic_meshes as moving_meshes, DynamicMesh as MovingMesh, DynamicWorld as MovingWorld,
};
pub use techniques::{open_technique, OpenError};
pub use units::{
    colour_and_scale, directional_light_from_lux, directional_light_lux, ev100_matching_relight,
    irradiance_of_texel, lightmap_texel, look_rotation, point_light_from_lumens,
    point_light_lumens, roughness_of, LUMENS_PER_WATT,
};
pub use volume::{fill_volume, VolumeGrid};

#[cfg(test)]
pub(crate) mod tests {
    /// A scene shipped with relight, by folder name.
    pub fn shipped(name: &str) -> std::path::PathBuf {
        std::path::Path::new(env!("CARGO_MANIFEST_DIR"))
            .join("../../scenes")
            .join(name)
            .join("scene.toml")
    }
}
