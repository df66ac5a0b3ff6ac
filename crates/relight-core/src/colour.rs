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

/// True when every channel is finite and non-negative: the contract for
/// light values read from user files.
#[inline]
pub fn is_valid_radiometric(colour: Rgb) -> bool {
    colour.is_finite() && colour.min_element() >= 0.0
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
