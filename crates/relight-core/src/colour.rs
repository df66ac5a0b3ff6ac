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
}
