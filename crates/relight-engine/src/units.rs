//! relight's radiometric values in an engine's photometric units, through
//! the one factor [`LUMENS_PER_WATT`].

use glam::Vec3;
use relight_core::Rgb;
pub use relight_core::LUMENS_PER_WATT;
use std::f32::consts::PI;

/// A lightmap or irradiance-volume texel from irradiance `E` (W/m^2): the
/// radiance a white Lambertian surface reflects, E/pi, in cd/m^2. Engines
/// multiply it by the surface's base colour (Bevy: times the camera's
/// exposure, with no further 1/pi).
#[inline]
pub fn lightmap_texel(irradiance: Rgb) -> Rgb {
    irradiance * (LUMENS_PER_WATT / PI)
}

/// The irradiance (W/m^2) a texel of [`lightmap_texel`] holds.
#[inline]
pub fn irradiance_of_texel(texel: Rgb) -> Rgb {
    texel * (PI / LUMENS_PER_WATT)
}

/// A colour split into a unit colour (brightest channel 1) and the scale
/// it was divided by, for engines whose lights take a colour and one
/// intensity. Black gives white at scale 0.
pub fn colour_and_scale(value: Rgb) -> (Rgb, f32) {
    let scale = value.max_element();
    if scale > 0.0 && scale.is_finite() {
        (value / scale, scale)
    } else {
        (Rgb::ONE, 0.0)
    }
}

/// A point or spot light of radiant intensity `intensity` (W/sr) as an
/// engine light: unit colour and luminous power in lumens, the 4 pi
/// steradians of an isotropic emitter (Bevy's `PointLight::intensity` and,
/// for the cone, `SpotLight::intensity`, which Bevy also divides by 4 pi).
pub fn point_light_lumens(intensity: Rgb) -> (Rgb, f32) {
    let (colour, scale) = colour_and_scale(intensity);
    (colour, scale * 4.0 * PI * LUMENS_PER_WATT)
}

/// A directional light of irradiance `irradiance` (W/m^2) as unit colour
/// and illuminance in lux.
pub fn directional_light_lux(irradiance: Rgb) -> (Rgb, f32) {
    let (colour, scale) = colour_and_scale(irradiance);
    (colour, scale * LUMENS_PER_WATT)
}

/// A point or spot light's radiant intensity (W/sr) from an engine's
/// linear colour and lumens: the inverse of [`point_light_lumens`].
pub fn point_light_from_lumens(colour: Rgb, lumens: f32) -> Rgb {
    colour * (lumens / (4.0 * PI * LUMENS_PER_WATT))
}

/// A directional light's irradiance (W/m^2) from an engine's linear
/// colour and lux: the inverse of [`directional_light_lux`].
pub fn directional_light_from_lux(colour: Rgb, lux: f32) -> Rgb {
    colour * (lux / LUMENS_PER_WATT)
}

/// The metallic-roughness roughness that relight's glTF loader turns back
/// into Phong `exponent` (exponent = 2 / roughness^4 - 2); Lambertian
/// materials (exponent at most 1) are fully rough.
pub fn roughness_of(exponent: f32) -> f32 {
    if exponent > 1.0 {
        (2.0 / (exponent + 2.0)).powf(0.25)
    } else {
        1.0
    }
}

/// The camera exposure (Bevy's `Exposure::ev100`) at which the engine's
/// linear output equals relight's linear render: exposure =
/// 1 / (1.2 x 2^ev100) = 1 / [`LUMENS_PER_WATT`].
pub fn ev100_matching_relight() -> f32 {
    (LUMENS_PER_WATT / 1.2).log2()
}

/// The rotation that turns an engine's forward axis (-Z for glTF's and
/// Bevy's lights and cameras) to `forward`, with +Y turned toward `up`
/// (any perpendicular when `up` is parallel to `forward`).
pub fn look_rotation(forward: Vec3, up: Vec3) -> glam::Quat {
    let forward = forward.normalize_or_zero();
    if forward == Vec3::ZERO {
        return glam::Quat::IDENTITY;
    }
    let mut right = forward.cross(up).normalize_or_zero();
    if right == Vec3::ZERO {
        right = forward.any_orthonormal_vector();
    }
    let true_up = right.cross(forward);
    glam::Quat::from_mat3(&glam::Mat3::from_cols(right, true_up, -forward))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn texels_hold_e_over_pi_and_come_back() {
        let irradiance = Rgb::new(PI, 2.0 * PI, 0.0);
        assert!(
            (lightmap_texel(irradiance) - Rgb::new(1.0, 2.0, 0.0))
                .abs()
                .max_element()
                < 1e-6
        );
        let back = irradiance_of_texel(lightmap_texel(irradiance));
        assert!((back - irradiance).abs().max_element() < 1e-5);
    }

    #[test]
    fn lights_keep_colour_and_power() {
        let (colour, lumens) = point_light_lumens(Rgb::new(2.0, 1.0, 0.5));
        assert_eq!(colour, Rgb::new(1.0, 0.5, 0.25));
        assert!((lumens - 8.0 * PI * LUMENS_PER_WATT).abs() < 1e-4);
        assert_eq!(directional_light_lux(Rgb::ZERO), (Rgb::ONE, 0.0));
        let back = point_light_from_lumens(colour, lumens);
        assert!((back - Rgb::new(2.0, 1.0, 0.5)).abs().max_element() < 1e-5);
        let (colour, lux) = directional_light_lux(Rgb::new(3.0, 6.0, 0.0));
        assert!(
            (directional_light_from_lux(colour, lux) - Rgb::new(3.0, 6.0, 0.0)).length() < 1e-5
        );
        for exponent in [2.0f32, 40.0, 1000.0] {
            let roughness = roughness_of(exponent);
            assert!((2.0 / roughness.powi(4) - 2.0 - exponent).abs() < 1e-3 * exponent);
        }
    }

    #[test]
    fn exposure_undoes_the_factor() {
        let exposure = 1.0 / (1.2 * 2f32.powf(ev100_matching_relight()));
        assert!((exposure * LUMENS_PER_WATT - 1.0).abs() < 1e-5);
    }

    #[test]
    fn forward_turns_to_the_direction() {
        for direction in [Vec3::X, -Vec3::Y, Vec3::new(0.3, -0.8, 0.5), Vec3::Y] {
            let rotation = look_rotation(direction, Vec3::Y);
            let forward = rotation * -Vec3::Z;
            assert!(
                (forward - direction.normalize()).length() < 1e-5,
                "{direction}"
            );
            let up = rotation * Vec3::Y;
            assert!(
                up.dot(direction).abs() < 1e-5 && up.y >= -1e-6,
                "{direction}: up {up}"
            );
        }
    }
}
