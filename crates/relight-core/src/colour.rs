//! Linear RGB colour helpers and the sRGB transfer function.

use glam::Vec3;

/// Linear RGB radiometric quantity (radiance, irradiance, albedo, flux).
pub type Rgb = Vec3;

/// Rec. 709 luminance of a linear RGB colour.
#[inline]
pub fn luminance(colour: Rgb) -> f32 {
    0.2126 * colour.x + 0.7152 * colour.y + 0.0722 * colour.z
}

/// sRGB-encoded channel value (0..1) to linear.
#[inline]
pub fn srgb_to_linear(encoded: f32) -> f32 {
    if encoded <= 0.04045 {
        encoded / 12.92
    } else {
        ((encoded + 0.055) / 1.055).powf(2.4)
    }
}

/// Linear channel value to sRGB encoding (clamped to 0..1).
#[inline]
pub fn linear_to_srgb(linear: f32) -> f32 {
    let linear = linear.clamp(0.0, 1.0);
    if linear <= 0.003_130_8 {
        linear * 12.92
    } else {
        1.055 * linear.powf(1.0 / 2.4) - 0.055
    }
}

/// Linear channel value to an 8-bit sRGB code (clamped, rounded): PNG
/// pixels and 8-bit textures.
#[inline]
pub fn linear_to_srgb8(linear: f32) -> u8 {
    (linear_to_srgb(linear) * 255.0 + 0.5) as u8
}

/// True when every channel is finite and non-negative: the contract for
/// light values read from user files.
#[inline]
pub fn is_valid_radiometric(colour: Rgb) -> bool {
    colour.is_finite() && colour.min_element() >= 0.0
}

/// RGB to YCoCg (Malvar and Sullivan; equation 7 of the PIC paper): luma
/// and two chroma channels that decorrelate colour, so chroma can keep fewer
/// SH bands than luma. Linear and exactly invertible by [`ycocg_to_rgb`].
#[inline]
pub fn rgb_to_ycocg(colour: Rgb) -> Vec3 {
    let co = (colour.x - colour.z) * 0.5;
    let t = colour.z + co;
    let cg = (colour.y - t) * 0.5;
    Vec3::new(t + cg, co, cg)
}

/// Inverse of [`rgb_to_ycocg`].
#[inline]
pub fn ycocg_to_rgb(ycocg: Vec3) -> Rgb {
    let t = ycocg.x - ycocg.z;
    let green = ycocg.x + ycocg.z;
    let blue = t - ycocg.y;
    Rgb::new(t + ycocg.y, green, blue)
}

/// A unit direction as two 16-bit octahedral coordinates (Cigolle et al.
/// 2014): about 3e-5 rad of error, 4 bytes instead of 12.
pub fn octahedral_encode(direction: Vec3) -> [u16; 2] {
    let sum = direction.x.abs() + direction.y.abs() + direction.z.abs();
    let (mut u, mut v) = if sum > 0.0 {
        (direction.x / sum, direction.y / sum)
    } else {
        (0.0, 0.0)
    };
    if direction.z < 0.0 {
        let (fu, fv) = (u, v);
        u = (1.0 - fv.abs()) * fu.signum();
        v = (1.0 - fu.abs()) * fv.signum();
    }
    let quantise = |value: f32| (((value.clamp(-1.0, 1.0) + 1.0) * 0.5) * 65535.0).round() as u16;
    [quantise(u), quantise(v)]
}

/// Inverse of [`octahedral_encode`].
#[inline]
pub fn octahedral_decode(encoded: [u16; 2]) -> Vec3 {
    let u = encoded[0] as f32 * (2.0 / 65535.0) - 1.0;
    let v = encoded[1] as f32 * (2.0 / 65535.0) - 1.0;
    let z = 1.0 - u.abs() - v.abs();
    let shift = (-z).max(0.0);
    let x = u - shift.copysign(u);
    let y = v - shift.copysign(v);
    Vec3::new(x, y, z).normalize()
}

/// Packed HDR colour for lightmaps: three 9-bit mantissas sharing one 5-bit
/// exponent, the bit layout of the GPU texture format RGB9_E5, in a third
/// of an [`Rgb`]'s bytes, so a lightmap rewritten every frame moves a third
/// of the memory. The exponent bias is 11 instead of the GPU's 15, which
/// moves the range up four binades to [2^-20, 1 046 528]: photometric
/// scenes (a 100 000 lux sun) fit as well as unit-scaled ones. Every channel
/// keeps 9 bits relative to the brightest one, so the error of a channel is
/// at most 2^-9 of the brightest channel (or 2^-21 below 2^-11); negative
/// and NaN channels store 0 and brighter values saturate at
/// [`Rgb9e5::MAX`].
#[repr(transparent)]
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, bytemuck::Pod, bytemuck::Zeroable)]
pub struct Rgb9e5(pub u32);

impl Rgb9e5 {
    const MANTISSA_BITS: i32 = 9;
    const EXPONENT_BIAS: i32 = 11;
    /// The brightest storable channel value, 511 x 2^(31 - 11 - 9).
    pub const MAX: f32 = 511.0 * 2048.0;

    /// Rounds each channel to the nearest step of the shared exponent that
    /// the brightest channel needs (floor(x + 0.5), the same arithmetic as
    /// [`pack_rgb9e5_x8`], so both give the same bits).
    #[inline]
    pub fn from_rgb(colour: Rgb) -> Self {
        // `v > 0` is false for NaN, which thus stores 0.
        let clamp = |value: f32| {
            if value > 0.0 {
                value.min(Self::MAX)
            } else {
                0.0
            }
        };
        let (red, green, blue) = (clamp(colour.x), clamp(colour.y), clamp(colour.z));
        let brightest = red.max(green).max(blue);
        // 2^e <= brightest < 2^(e + 1), from the float's exponent field.
        let e = ((brightest.to_bits() >> 23) as i32 - 127).max(-Self::EXPONENT_BIAS - 1);
        let mut shared = e + 1 + Self::EXPONENT_BIAS;
        let mut scale = f32::from_bits(((127 + Self::MANTISSA_BITS - 1 - e) as u32) << 23);
        if (brightest * scale + 0.5) as u32 > 511 {
            // Rounding carried into a tenth bit: one binade up.
            shared += 1;
            scale *= 0.5;
        }
        let quantise = |value: f32| (value * scale + 0.5) as u32;
        Self(
            quantise(red)
                | (quantise(green) << 9)
                | (quantise(blue) << 18)
                | ((shared as u32) << 27),
        )
    }

    /// Each mantissa m becomes m x 2^(shared - 20) without an int-to-float
    /// conversion: with the mantissa in the low bits of a float whose
    /// exponent makes its unit in the last place equal that step, the float
    /// is 2^E + m x step, and subtracting 2^E leaves m x step exactly.
    /// Bilinear lookups decode four texels a pixel, so this is on the
    /// shading path.
    #[inline]
    pub fn to_rgb(self) -> Rgb {
        let shared = self.0 >> 27;
        // Exponent field of 2^E, E = shared - 20 + 23 (127-biased).
        let base_bits =
            (shared + (127 + 23 - Self::EXPONENT_BIAS as u32 - Self::MANTISSA_BITS as u32)) << 23;
        let base = f32::from_bits(base_bits);
        let channel = |shift: u32| f32::from_bits(base_bits | ((self.0 >> shift) & 511)) - base;
        Rgb::new(channel(0), channel(9), channel(18))
    }
}

impl From<Rgb9e5> for Rgb {
    #[inline]
    fn from(packed: Rgb9e5) -> Rgb {
        packed.to_rgb()
    }
}

/// The sum of `weights[i] * texels[i]`, decoded: the bilinear blend of four
/// lightmap texels. On x86-64 the four texels decode side by side in SSE2
/// (part of every x86-64 CPU), so a per-pixel lookup costs a handful of
/// vector operations instead of twelve scalar decodes.
#[inline]
pub fn bilinear_rgb9e5(texels: [Rgb9e5; 4], weights: [f32; 4]) -> Rgb {
    #[cfg(target_arch = "x86_64")]
    {
        use std::arch::x86_64::*;
        // SAFETY: SSE2 is part of x86-64.
        unsafe {
            let packed = _mm_loadu_si128(texels.as_ptr() as *const __m128i);
            let bias = 127 + 23 - Rgb9e5::EXPONENT_BIAS - Rgb9e5::MANTISSA_BITS;
            let base_bits = _mm_slli_epi32(
                _mm_add_epi32(_mm_srli_epi32(packed, 27), _mm_set1_epi32(bias)),
                23,
            );
            let base = _mm_castsi128_ps(base_bits);
            let mantissa = _mm_set1_epi32(511);
            let weights = _mm_loadu_ps(weights.as_ptr());
            let channel = |bits: __m128i| {
                let value =
                    _mm_castsi128_ps(_mm_or_si128(base_bits, _mm_and_si128(bits, mantissa)));
                let weighted = _mm_mul_ps(_mm_sub_ps(value, base), weights);
                // (w0 t0 + w1 t1) + (w2 t2 + w3 t3), as the portable sum.
                let pairs = _mm_add_ps(weighted, _mm_shuffle_ps(weighted, weighted, 0b10_11_00_01));
                _mm_cvtss_f32(_mm_add_ss(pairs, _mm_movehl_ps(pairs, pairs)))
            };
            Rgb::new(
                channel(packed),
                channel(_mm_srli_epi32(packed, 9)),
                channel(_mm_srli_epi32(packed, 18)),
            )
        }
    }
    #[cfg(not(target_arch = "x86_64"))]
    {
        let decoded = texels.map(Rgb9e5::to_rgb);
        (decoded[0] * weights[0] + decoded[1] * weights[1])
            + (decoded[2] * weights[2] + decoded[3] * weights[3])
    }
}

/// [`Rgb9e5::from_rgb`] for eight colours given channel by channel, with
/// the same arithmetic, so the bits are the same.
///
/// # Safety
/// The CPU must support AVX2.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
#[inline]
pub unsafe fn pack_rgb9e5_x8(
    red: std::arch::x86_64::__m256,
    green: std::arch::x86_64::__m256,
    blue: std::arch::x86_64::__m256,
) -> std::arch::x86_64::__m256i {
    use std::arch::x86_64::*;
    let zero = _mm256_setzero_ps();
    let ceiling = _mm256_set1_ps(Rgb9e5::MAX);
    let half = _mm256_set1_ps(0.5);
    // max_ps returns its second operand when the first is NaN.
    let clamp = |value: __m256| _mm256_min_ps(_mm256_max_ps(value, zero), ceiling);
    let (red, green, blue) = (clamp(red), clamp(green), clamp(blue));
    let brightest = _mm256_max_ps(_mm256_max_ps(red, green), blue);
    let e = _mm256_max_epi32(
        _mm256_sub_epi32(
            _mm256_srli_epi32(_mm256_castps_si256(brightest), 23),
            _mm256_set1_epi32(127),
        ),
        _mm256_set1_epi32(-Rgb9e5::EXPONENT_BIAS - 1),
    );
    let shared = _mm256_add_epi32(e, _mm256_set1_epi32(1 + Rgb9e5::EXPONENT_BIAS));
    let scale = _mm256_castsi256_ps(_mm256_slli_epi32(
        _mm256_sub_epi32(_mm256_set1_epi32(127 + Rgb9e5::MANTISSA_BITS - 1), e),
        23,
    ));
    let top = _mm256_cvttps_epi32(_mm256_add_ps(_mm256_mul_ps(brightest, scale), half));
    let carried = _mm256_cmpgt_epi32(top, _mm256_set1_epi32(511));
    let shared = _mm256_sub_epi32(shared, carried);
    let scale = _mm256_blendv_ps(
        scale,
        _mm256_mul_ps(scale, half),
        _mm256_castsi256_ps(carried),
    );
    let quantise =
        |value: __m256| _mm256_cvttps_epi32(_mm256_add_ps(_mm256_mul_ps(value, scale), half));
    _mm256_or_si256(
        _mm256_or_si256(quantise(red), _mm256_slli_epi32(quantise(green), 9)),
        _mm256_or_si256(
            _mm256_slli_epi32(quantise(blue), 18),
            _mm256_slli_epi32(shared, 27),
        ),
    )
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn srgb_round_trip() {
        for step in 0..=100 {
            let value = step as f32 / 100.0;
            let back = srgb_to_linear(linear_to_srgb(value));
            // f32 pow round trip keeps about 6 significant digits.
            assert!((back - value).abs() < 1e-5, "{value} -> {back}");
        }
    }

    #[test]
    fn luminance_of_white_is_one() {
        assert!((luminance(Rgb::ONE) - 1.0).abs() < 1e-6);
    }
}

#[cfg(test)]
mod encoding_tests {
    use super::*;
    use crate::sampling::{uniform_sphere, Pcg32};

    #[test]
    fn ycocg_round_trips() {
        let mut rng = Pcg32::new(3, 0);
        for _ in 0..1000 {
            let colour = Rgb::new(rng.next_f32(), rng.next_f32(), rng.next_f32()) * 10.0;
            let back = ycocg_to_rgb(rgb_to_ycocg(colour));
            // Two adds and a halving per channel: a few ulps of 10.
            assert!(
                (back - colour).abs().max_element() < 1e-5,
                "{colour} {back}"
            );
        }
        // Grey has no chroma.
        let grey = rgb_to_ycocg(Rgb::splat(0.7));
        assert!((grey.x - 0.7).abs() < 1e-7 && grey.y == 0.0 && grey.z == 0.0);
    }

    #[test]
    fn octahedral_round_trips_every_octant() {
        let mut rng = Pcg32::new(5, 0);
        let mut worst = 0.0f32;
        for _ in 0..20_000 {
            let direction = uniform_sphere(rng.next_vec2());
            let back = octahedral_decode(octahedral_encode(direction));
            worst = worst.max(back.cross(direction).length().atan2(back.dot(direction)));
        }
        for axis in [Vec3::X, -Vec3::X, Vec3::Y, -Vec3::Y, Vec3::Z, -Vec3::Z] {
            let back = octahedral_decode(octahedral_encode(axis));
            worst = worst.max(back.cross(axis).length().atan2(back.dot(axis)));
        }
        // 16-bit coordinates over [-1, 1]: a step of 3e-5, about 1e-4 rad
        // at the octahedron's edges where the map stretches most.
        assert!(worst < 2e-4, "worst angle {worst}");
    }
    #[test]
    fn rgb9e5_keeps_nine_bits_of_the_brightest_channel() {
        let mut rng = crate::SampleStream::new(11, 0, 0);
        for _ in 0..20_000 {
            // Magnitudes from 1e-7 to 1e6, channels up to 1e4 apart.
            let magnitude = 10f32.powf(rng.next_f32() * 13.0 - 7.0);
            let colour = Rgb::new(
                magnitude,
                magnitude * 10f32.powf(-4.0 * rng.next_f32()),
                magnitude * rng.next_f32(),
            );
            let decoded = Rgb9e5::from_rgb(colour).to_rgb();
            // Half a step of the shared exponent: at most 2^-9 of the
            // brightest channel, and 2^-21 where the exponent bottoms out.
            let bound = (colour.max_element() * 2f32.powi(-9)).max(2f32.powi(-21));
            assert!(
                (decoded - colour).abs().max_element() <= bound,
                "{colour} came back as {decoded}"
            );
        }
    }

    #[test]
    fn rgb9e5_edge_cases() {
        let round_trip = |colour: Rgb| Rgb9e5::from_rgb(colour).to_rgb();
        assert_eq!(Rgb9e5::from_rgb(Rgb::ZERO), Rgb9e5(0));
        assert_eq!(round_trip(Rgb::ZERO), Rgb::ZERO);
        // Powers of two and small integers are exact.
        for value in [1.0f32, 0.5, 2.0f32.powi(-20), 256.0, 511.0, Rgb9e5::MAX] {
            assert_eq!(round_trip(Rgb::splat(value)), Rgb::splat(value), "{value}");
        }
        // Negative and NaN store 0; too bright and infinite saturate.
        assert_eq!(
            round_trip(Rgb::new(-1.0, f32::NAN, 3.0)),
            Rgb::new(0.0, 0.0, 3.0)
        );
        assert_eq!(round_trip(Rgb::new(1e9, f32::INFINITY, 0.0)).x, Rgb9e5::MAX);
        assert_eq!(round_trip(Rgb::new(1e9, f32::INFINITY, 0.0)).y, Rgb9e5::MAX);
        // Rounding that carries into a tenth mantissa bit moves one binade up.
        assert_eq!(round_trip(Rgb::splat(511.9)), Rgb::splat(512.0));
        // Below the smallest step, values round to 0 or to the step.
        assert_eq!(round_trip(Rgb::splat(2.0f32.powi(-22))), Rgb::ZERO);
    }

    #[cfg(target_arch = "x86_64")]
    #[test]
    fn rgb9e5_eight_wide_packing_gives_the_same_bits() {
        if !std::arch::is_x86_feature_detected!("avx2") {
            return;
        }
        let mut rng = crate::SampleStream::new(12, 0, 0);
        let special = [
            0.0f32,
            -0.0,
            -2.0,
            f32::NAN,
            f32::INFINITY,
            1e-30,
            2.0f32.powi(-21),
            511.9,
            Rgb9e5::MAX,
            2e6,
        ];
        let mut channels: Vec<f32> = special.to_vec();
        channels.extend((0..3000).map(|_| 10f32.powf(rng.next_f32() * 14.0 - 8.0)));
        for start in (0..channels.len() - 24).step_by(7) {
            let lanes: Vec<Rgb> = (0..8)
                .map(|lane| {
                    let at = start + 3 * lane;
                    Rgb::new(channels[at], channels[at + 1], channels[at + 2])
                })
                .collect();
            let mut packed = [0u32; 8];
            // SAFETY: AVX2 was detected above.
            unsafe {
                use std::arch::x86_64::*;
                let gather = |channel: usize| {
                    _mm256_loadu_ps(
                        lanes
                            .iter()
                            .map(|c| c[channel])
                            .collect::<Vec<_>>()
                            .as_ptr(),
                    )
                };
                let bits = pack_rgb9e5_x8(gather(0), gather(1), gather(2));
                _mm256_storeu_si256(packed.as_mut_ptr() as *mut __m256i, bits);
            }
            for (lane, colour) in lanes.iter().enumerate() {
                assert_eq!(packed[lane], Rgb9e5::from_rgb(*colour).0, "{colour}");
            }
        }
    }

    #[test]
    fn rgb9e5_bilinear_blend_matches_the_decoded_sum() {
        let mut rng = crate::SampleStream::new(13, 0, 0);
        for _ in 0..2000 {
            let texels: [Rgb9e5; 4] = std::array::from_fn(|_| {
                let magnitude = 10f32.powf(rng.next_f32() * 8.0 - 4.0);
                Rgb9e5::from_rgb(
                    Rgb::new(rng.next_f32(), rng.next_f32(), rng.next_f32()) * magnitude,
                )
            });
            let (fx, fy) = (rng.next_f32(), rng.next_f32());
            let weights = [
                (1.0 - fx) * (1.0 - fy),
                fx * (1.0 - fy),
                (1.0 - fx) * fy,
                fx * fy,
            ];
            let blended = bilinear_rgb9e5(texels, weights);
            let decoded = texels.map(Rgb9e5::to_rgb);
            let expected = (decoded[0] * weights[0] + decoded[1] * weights[1])
                + (decoded[2] * weights[2] + decoded[3] * weights[3]);
            // The same products in the same order: equal up to the last
            // bit of the two sums.
            assert!(
                (blended - expected).abs().max_element() <= expected.max_element() * 1e-6,
                "{blended} against {expected}"
            );
        }
    }
}
