//! Ray tracing for relight: the BVH every bake and every frame traces
//! against, the shared direct-light service, and the path tracer that is the
//! ground truth for all techniques.
//!
//! Data flow: [`bvh::Bvh`] is built once from the scene's triangles.
//! [`direct::DirectLight`] answers irradiance from the current lights for
//! batches of surface points, with exact shadows by shadow rays; every
//! technique and the renderer use it, so direct light is identical
//! everywhere and techniques differ only in indirect light.
//! [`path::PathTracer`] uses both to produce reference images and
//! per-receiver indirect irradiance.

pub mod bvh;
pub mod counters;
pub mod direct;
pub mod path;
pub mod raybench;

pub use bvh::{Bvh, Hit, Ray, NO_OCCLUDER};
