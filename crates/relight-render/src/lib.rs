//! Images for relight: rendering the camera view with a technique or the
//! path tracer, writing EXR (linear) and PNG (tone-mapped sRGB), and the
//! error metrics every comparison reports.
//!
//! Data flow: [`render::render_with_technique`] traces primary rays, takes
//! direct light from the shared service and indirect light from the
//! technique; [`render::render_reference`] path traces the same split. Both
//! return [`image::Image`]s that [`metrics`] compares and [`image`] writes.
//! [`convergence`] and [`robustness`] measure a technique against the path
//! tracer on one scene's settings and over generated scene variants.

pub mod convergence;
pub mod image;
pub mod metrics;
pub mod render;
pub mod robustness;
pub mod study;

pub use image::{Image, ImageError};
