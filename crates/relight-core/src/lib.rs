//! Shared math for every relight crate: colour, random numbers and sampling,
//! real spherical harmonics, solid angles of small patches, and principal
//! components of long f16 vectors (the techniques' transport compression).
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
pub mod solid_angle;

pub use colour::{luminance, Rgb, Rgb9e5};
pub use glam::{Affine3A, Mat3, Mat4, UVec2, Vec2, Vec3, Vec3A, Vec4};
pub use sampling::{Pcg32, SampleStream};

/// Lumens per watt between relight's radiometric values and an engine's
/// photometric ones, the one factor every bridge and export uses.
///
/// relight computes in watts (irradiance in W/m^2, radiance in
/// W/(m^2 sr), point lights in W/sr). Engines such as Bevy are photometric
/// (lux, candela, cd/m^2). relight maps them one to one: a W/sr point light
/// is a candela, a W/m^2 sun is a lux, a lightmap texel E/pi in W/(m^2 sr)
/// is a cd/m^2. The scene loaders read glTF's `KHR_lights_punctual`
/// candela and lux the same way, so a scene exported by relight and loaded
/// back by relight or by an engine shows the same light. The physical
/// 683 lm/W would hold only at 555 nm and would make every exported light
/// 683 times brighter than the scene file said.
pub const LUMENS_PER_WATT: f32 = 1.0;
