//! Shared math for every relight crate: colour, random numbers and sampling,
//! real spherical harmonics, and principal components of long f16 vectors
//! (the techniques' transport compression).
//!
//! Nothing here knows about scenes or rays. Data flows one way through relight
//! (scene, then bake, then per-frame update, then shading), and this crate sits
//! under all of it, so it holds only pure functions and small value types.
//! Colours are linear RGB in `glam::Vec3` (`Rgb`), so SIMD-friendly arithmetic
//! is shared between positions and radiometric quantities.

pub mod colour;
pub mod pca;
pub mod sampling;
pub mod sh;

pub use colour::{luminance, Rgb, Rgb9e5};
pub use glam::{Mat3, Mat4, UVec2, Vec2, Vec3, Vec3A, Vec4};
pub use sampling::{Pcg32, SampleStream};
