//! The contract between relight's GI techniques and everything else.
//!
//! Data flow: a [`SceneContext`] (scene, BVH, lightmap atlas, emitters) is
//! built once. A [`TechniqueKind`] bakes from it (or needs no bake) and
//! creates a [`Technique`], which each frame [`Technique::update`]s its
//! internal state from the current lights and then answers indirect
//! irradiance at surface points of the static scene and at points in space.
//! Direct light never comes from a technique: the renderer and every
//! technique take it from the shared direct-light service, so techniques
//! differ only in indirect light.
//!
//! A bake may also be made in [`Shard`]s, separately and anywhere, which
//! [`TechniqueKind::merge_shards`] joins into the bytes of a whole bake.
//! Before any bake, [`TechniqueKind::estimate`] forecasts its rays and peak
//! memory from the scene's counts and the parameters.
//!
//! The built-in kinds are `direct` (no indirect light, the lower bound) and
//! `reference` (path-traced per-receiver indirect light, the ground truth).
//! The four GI techniques live in crates of their own (`relight-prm`,
//! `relight-srp`, `relight-pic`, `relight-lightskin`);
//! `relight_engine::techniques::find` names every kind.
//!
//! # Using a technique
//!
//! Every kind is used the same way: build the context once, bake if the
//! kind needs it (or read a bake file with [`read_bake`]), create, then
//! update each frame with the lights as they are and read the light.
//!
//! ```
//! use relight_technique::{
//!     ContextSettings, Frame, NoProgress, ReferenceKind, SceneContext, TechniqueKind,
//! };
//! use std::sync::Arc;
//!
//! let file = concat!(env!("CARGO_MANIFEST_DIR"), "/../../scenes/cornell-box/scene.toml");
//! let scene = relight_scene::load_scene(std::path::Path::new(file))?;
//! // The BVH, the lightmap atlas and its receivers, built once per scene.
//! let context = Arc::new(SceneContext::new(scene, ContextSettings::default())?);
//!
//! // The path tracer at 4 paths a receiver: cheap, noisy, and used here
//! // only because it needs no other crate.
//! let kind: &dyn TechniqueKind = &ReferenceKind;
//! let params = vec![("samples".to_string(), "4".to_string())];
//! let bake = match kind.needs_bake() {
//!     true => Some(kind.bake(&context, &params, &NoProgress)?),
//!     false => None,
//! };
//! let mut technique = kind.create(context.clone(), bake.as_deref(), &params, &NoProgress)?;
//!
//! // Each frame: the lights where the application has moved them.
//! let mut lights = context.scene.lights.clone();
//! for index in 0..2 {
//!     technique.update(&Frame {
//!         lights: &lights,
//!         index,
//!         camera: None,
//!         moving_mesh_poses: None,
//!     })?;
//!     // Indirect irradiance per lightmap receiver, in the atlas's order
//!     // (`relight_engine::LightmapLayout` turns it into texels).
//!     let irradiance = technique.receiver_irradiance().expect("a lightmap");
//!     assert_eq!(irradiance.len(), context.atlas.receivers.len());
//!     // Here they turn a quarter turn about the scene's middle.
//!     let (low, high) = context.scene.content_bounds();
//!     let turn = glam::Quat::from_rotation_y(std::f32::consts::FRAC_PI_2);
//!     for light in &mut lights {
//!         *light = light.rotated_about((low + high) * 0.5, turn);
//!     }
//! }
//! # Ok::<(), Box<dyn std::error::Error>>(())
//! ```

mod bakefile;
mod builtin;
mod context;
mod estimate;
mod final_gather;
mod gather;
mod interface;
mod params;
mod payload;
mod repeat;
pub mod robustness;
mod settling;
mod shard;
#[cfg(test)]
mod test_variants;

pub use bakefile::{
    read_bake, scene_fingerprint, write_bake_atomic, BakeHeader, BAKE_FORMAT_VERSION, BAKE_MAGIC,
};
pub use builtin::{
    reference_irradiance_at, reference_receiver_irradiance, DirectKind, ReferenceKind,
    ReferenceLightmap, ReferenceParams,
};
pub use context::{
    build_atlas, chart_atlas, fill_hidden_texels, relocate_receivers, ContextSettings, SceneContext,
};
pub use estimate::{available_bytes, format_bytes, parse_size, resident_bytes, BakeEstimate};
pub use final_gather::{
    FinalGather, FinalGatherSettings, GatherReach, NearLightRows, NearLightSamples,
};
pub use gather::SurfaceGather;
pub use interface::*;
pub use params::{parse_params, with_scene_section, ParamError};
pub use payload::{PayloadReader, PayloadWriter};
pub use repeat::{FrameReads, LastFrame};
pub use settling::{SettlingPasses, SETTLED_SHARE};
pub use shard::{
    join_parts, parameters_fingerprint, read_shard_set, shards_disagree, BakePart, Shard, ShardSet,
};
