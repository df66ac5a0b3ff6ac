//! Deterministic random numbers and the warps every Monte Carlo estimator in
//! relight uses.
//!
//! Determinism across thread counts comes from seeding one stream per work
//! item (pixel, receiver, sample index) with [`SampleStream::new`], never from
//! a shared generator, so the order in which rayon runs items cannot change a
//! single bit of the result.

use glam::{Vec2, Vec3};
use std::f32::consts::PI;

/// PCG32 (O'Neill 2014): small state, good statistics, cheap to seed per item.
#[derive(Clone, Debug)]
pub struct Pcg32 {
    state: u64,
    increment: u64,
}

const PCG_MULTIPLIER: u64 = 6_364_136_223_846_793_005;

impl Pcg32 {
    pub fn new(seed: u64, stream: u64) -> Self {
        let mut rng = Self {
            state: 0,
            increment: (stream << 1) | 1,
        };
        rng.next_u32();
        rng.state = rng.state.wrapping_add(seed);
        rng.next_u32();
        rng
    }

    #[inline]
    pub fn next_u32(&mut self) -> u32 {
        let old = self.state;
        self.state = old
            .wrapping_mul(PCG_MULTIPLIER)
            .wrapping_add(self.increment);
        let xorshifted = (((old >> 18) ^ old) >> 27) as u32;
        let rotation = (old >> 59) as u32;
        xorshifted.rotate_right(rotation)
    }

    /// Uniform float in [0, 1), never 1.0.
    #[inline]
    pub fn next_f32(&mut self) -> f32 {
        (self.next_u32() >> 8) as f32 * (1.0 / 16_777_216.0)
    }

    #[inline]
    pub fn next_vec2(&mut self) -> Vec2 {
        Vec2::new(self.next_f32(), self.next_f32())
    }
}

/// SplitMix64 finaliser: decorrelates structured keys (pixel, sample) into seeds.
#[inline]
pub fn mix64(mut value: u64) -> u64 {
    value = value.wrapping_add(0x9E37_79B9_7F4A_7C15);
    value = (value ^ (value >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
    value = (value ^ (value >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
    value ^ (value >> 31)
}

/// Builds the per-work-item generator from a user seed and up to two keys.
pub struct SampleStream;

impl SampleStream {
    #[inline]
    #[allow(clippy::new_ret_no_self)]
    pub fn new(seed: u64, item: u64, pass: u64) -> Pcg32 {
        Pcg32::new(
            mix64(seed ^ mix64(item)),
            mix64(pass.wrapping_add(0x5851_F42D)),
        )
    }
}

/// The Cranley-Patterson shift of `stratified_square` for one work item:
/// drawn once per item from a stream no sample index uses.
pub fn stratification_offset(seed: u64, item: u64) -> Vec2 {
    SampleStream::new(seed, item, u64::MAX).next_vec2()
}

/// Sample `index` of `total` stratified over a square grid of
/// floor(sqrt(total))^2 cells (jittered inside its cell; indices past the grid
/// are uniform), then toroidally shifted by `offset` (Cranley-Patterson) so
/// that different work items use decorrelated patterns. Estimates that sum
/// all `total` samples keep their expectation and lose most of the variance
/// of smooth integrands.
pub fn stratified_square(index: u32, total: u32, offset: Vec2, rng: &mut Pcg32) -> Vec2 {
    let side = (total as f64).sqrt().floor().max(1.0) as u32;
    let jitter = rng.next_vec2();
    let point = if index < side * side {
        (Vec2::new((index % side) as f32, (index / side) as f32) + jitter) / side as f32
    } else {
        jitter
    };
    let shifted = point + offset;
    // fract keeps [0,1); the min guards the rounding of values just below 1.
    Vec2::new(shifted.x.fract(), shifted.y.fract()).min(Vec2::splat(1.0 - f32::EPSILON / 2.0))
}

/// Van der Corput radical inverse in `base`, for Halton sequences.
pub fn radical_inverse(base: u32, mut index: u64) -> f64 {
    let inverse_base = 1.0 / base as f64;
    let mut fraction = inverse_base;
    let mut result = 0.0;
    while index > 0 {
        result += (index % base as u64) as f64 * fraction;
        index /= base as u64;
        fraction *= inverse_base;
    }
    result
}

/// Point `index` of the 2D Halton sequence (bases 2 and 3).
pub fn halton2(index: u64) -> Vec2 {
    Vec2::new(
        radical_inverse(2, index) as f32,
        radical_inverse(3, index) as f32,
    )
}

/// Orthonormal basis around a unit normal (Duff et al. 2017, branchless).
#[inline]
pub fn orthonormal_basis(normal: Vec3) -> (Vec3, Vec3) {
    let sign = 1.0f32.copysign(normal.z);
    let a = -1.0 / (sign + normal.z);
    let b = normal.x * normal.y * a;
    let tangent = Vec3::new(
        1.0 + sign * normal.x * normal.x * a,
        sign * b,
        -sign * normal.x,
    );
    let bitangent = Vec3::new(b, sign + normal.y * normal.y * a, -normal.y);
    (tangent, bitangent)
}

/// Cosine-weighted direction about +Z from a uniform square sample; pdf = cos / pi.
#[inline]
pub fn cosine_hemisphere(sample: Vec2) -> Vec3 {
    let disc = concentric_disc(sample);
    let z = (1.0 - disc.length_squared()).max(0.0).sqrt();
    Vec3::new(disc.x, disc.y, z)
}

/// Cosine-weighted direction about `normal`.
#[inline]
pub fn cosine_hemisphere_around(normal: Vec3, sample: Vec2) -> Vec3 {
    let local = cosine_hemisphere(sample);
    let (tangent, bitangent) = orthonormal_basis(normal);
    tangent * local.x + bitangent * local.y + normal * local.z
}

/// Uniform direction on the hemisphere about `normal`; pdf = 1 / (2 pi).
#[inline]
pub fn uniform_hemisphere_around(normal: Vec3, sample: Vec2) -> Vec3 {
    let z = sample.x;
    let radius = (1.0 - z * z).max(0.0).sqrt();
    let phi = 2.0 * PI * sample.y;
    let (tangent, bitangent) = orthonormal_basis(normal);
    tangent * (radius * phi.cos()) + bitangent * (radius * phi.sin()) + normal * z
}

/// Uniform direction on the unit sphere; pdf = 1 / (4 pi).
#[inline]
pub fn uniform_sphere(sample: Vec2) -> Vec3 {
    let z = 1.0 - 2.0 * sample.x;
    let radius = (1.0 - z * z).max(0.0).sqrt();
    let phi = 2.0 * PI * sample.y;
    Vec3::new(radius * phi.cos(), radius * phi.sin(), z)
}

/// Shirley-Chiu concentric map from the square to the unit disc (area preserving).
#[inline]
pub fn concentric_disc(sample: Vec2) -> Vec2 {
    let offset = sample * 2.0 - Vec2::ONE;
    if offset.x == 0.0 && offset.y == 0.0 {
        return Vec2::ZERO;
    }
    let (radius, theta) = if offset.x.abs() > offset.y.abs() {
        (offset.x, (PI / 4.0) * (offset.y / offset.x))
    } else {
        (offset.y, PI / 2.0 - (PI / 4.0) * (offset.x / offset.y))
    };
    Vec2::new(radius * theta.cos(), radius * theta.sin())
}

/// Uniform barycentric coordinates (b1, b2) on a triangle; b0 = 1 - b1 - b2.
/// Uses the square-root-free fold so stratification of `sample` is kept.
#[inline]
pub fn uniform_triangle(sample: Vec2) -> Vec2 {
    if sample.x + sample.y > 1.0 {
        Vec2::new(1.0 - sample.x, 1.0 - sample.y)
    } else {
        sample
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn pcg_is_deterministic_and_uniform() {
        let mut first = SampleStream::new(7, 3, 1);
        let mut second = SampleStream::new(7, 3, 1);
        let mut sum = 0.0f64;
        let count = 100_000;
        for _ in 0..count {
            let value = first.next_f32();
            assert_eq!(value.to_bits(), second.next_f32().to_bits());
            assert!((0.0..1.0).contains(&value));
            sum += value as f64;
        }
        // Mean of U(0,1) has standard deviation 1/sqrt(12 n) ~ 0.0009; allow 5 sigma.
        assert!((sum / count as f64 - 0.5).abs() < 0.0046);
    }

    #[test]
    fn cosine_hemisphere_integrates_cosine_to_pi() {
        // E[cos / pdf] = E[pi] = pi exactly; instead check E[cos] = 2/3 for pdf cos/pi.
        let mut rng = Pcg32::new(1, 1);
        let count = 200_000;
        let mean: f64 = (0..count)
            .map(|_| cosine_hemisphere(rng.next_vec2()).z as f64)
            .sum::<f64>()
            / count as f64;
        // Var(cos) = 1/2 - 4/9 = 1/18; sigma of mean = 0.00053; 5 sigma bound.
        assert!((mean - 2.0 / 3.0).abs() < 0.0027, "{mean}");
    }

    #[test]
    fn uniform_hemisphere_has_the_moments_of_its_pdf() {
        // For pdf 1 / (2 pi): E[cos] = 1/2 and E[cos^2] = 1/3; every sample
        // lies on the normal's side.
        let normal = Vec3::new(0.3, -0.5, 0.8).normalize();
        let mut rng = Pcg32::new(3, 3);
        let count = 200_000;
        let (mut first, mut second) = (0.0f64, 0.0f64);
        for _ in 0..count {
            let direction = uniform_hemisphere_around(normal, rng.next_vec2());
            let cosine = direction.dot(normal) as f64;
            assert!(cosine >= -1e-6 && (direction.length() - 1.0).abs() < 1e-5);
            first += cosine;
            second += cosine * cosine;
        }
        // Standard errors are about 0.0007: bounds of 5 of them.
        assert!((first / count as f64 - 0.5).abs() < 0.003);
        assert!((second / count as f64 - 1.0 / 3.0).abs() < 0.003);
    }

    #[test]
    fn basis_is_orthonormal() {
        let mut rng = Pcg32::new(2, 2);
        for _ in 0..1000 {
            let normal = uniform_sphere(rng.next_vec2());
            let (tangent, bitangent) = orthonormal_basis(normal);
            assert!(tangent.dot(normal).abs() < 1e-5);
            assert!(bitangent.dot(normal).abs() < 1e-5);
            assert!(tangent.dot(bitangent).abs() < 1e-5);
            assert!((tangent.length() - 1.0).abs() < 1e-5);
        }
    }

    #[test]
    fn stratified_square_covers_every_cell_once() {
        let mut rng = Pcg32::new(4, 4);
        let total = 64;
        let mut cells = [0u32; 64];
        for index in 0..total {
            let point = stratified_square(index, total, Vec2::ZERO, &mut rng);
            assert!(point.min_element() >= 0.0 && point.max_element() < 1.0);
            cells[(point.y * 8.0) as usize * 8 + (point.x * 8.0) as usize] += 1;
        }
        assert!(cells.iter().all(|&count| count == 1));
        // Shifted patterns stay in the unit square.
        let shifted = stratified_square(63, total, Vec2::new(0.99, 0.5), &mut rng);
        assert!(shifted.min_element() >= 0.0 && shifted.max_element() < 1.0);
    }

    #[test]
    fn halton_is_in_unit_square() {
        for index in 0..1000 {
            let point = halton2(index);
            assert!(point.x >= 0.0 && point.x < 1.0 && point.y >= 0.0 && point.y < 1.0);
        }
        assert_eq!(radical_inverse(2, 1), 0.5);
        assert_eq!(radical_inverse(3, 2), 2.0 / 3.0);
    }
}
