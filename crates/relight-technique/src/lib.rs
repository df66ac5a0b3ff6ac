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

mod bakefile;
mod builtin;
mod context;
mod estimate;
mod final_gather;
mod gather;
mod interface;
mod params;
mod payload;
pub mod robustness;
mod shard;

pub use bakefile::{
    read_bake, scene_fingerprint, write_bake_atomic, BakeHeader, BAKE_FORMAT_VERSION, BAKE_MAGIC,
};
pub use builtin::{
    reference_irradiance_at, reference_receiver_irradiance, DirectKind, ReferenceKind,
    ReferenceLightmap, ReferenceParams,
};
pub use context::{
    build_atlas, fill_hidden_texels, relocate_receivers, ContextSettings, SceneContext,
};
pub use estimate::{available_bytes, format_bytes, parse_size, resident_bytes, BakeEstimate};
pub use final_gather::{FinalGather, FinalGatherSettings, GatherReach};
pub use gather::SurfaceGather;
pub use interface::*;
pub use params::{parse_params, with_scene_section, ParamError};
pub use payload::{PayloadReader, PayloadWriter};
pub use shard::{
    join_parts, parameters_fingerprint, read_shard_set, shards_disagree, BakePart, Shard, ShardSet,
};
