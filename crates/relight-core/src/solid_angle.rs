//! Solid angles of small planar patches seen from a point, for light from a
//! point source averaged over a patch instead of taken at its centre.
//!
//! Why: a point light's irradiance I cos / d^2 diverges as the light nears
//! a surface, so a sample point that happens to fall a few centimetres from
//! a lamp reads hundreds of times the light of its neighbours. Where such a
//! point stands for a whole patch of surface (PRM's entry points, each
//! carrying its patch's flux into the bake's light paths), the flux the
//! patch really receives is the source's intensity times the solid angle
//! the patch subtends, which stays below 2 pi however close the light is.

use crate::sampling::orthonormal_basis;
use glam::{DVec3, Vec3};

/// Distance from the source, in sides of the square, beyond which
/// [`mean_cosine_over_square`] takes the point value instead of the solid
/// angle.
pub const POINT_VALUE_DISTANCE_PER_SIDE: f32 = 16.0;

/// Solid angle (sr) of the triangle with corners `a`, `b`, `c`, given
/// relative to the viewpoint (Van Oosterom and Strackee, 1983).
pub fn triangle_solid_angle(a: DVec3, b: DVec3, c: DVec3) -> f64 {
    let (la, lb, lc) = (a.length(), b.length(), c.length());
    let numerator = a.dot(b.cross(c)).abs();
    let denominator = la * lb * lc + a.dot(b) * lc + a.dot(c) * lb + b.dot(c) * la;
    // atan2 keeps the angle right past pi / 2, where the denominator is
    // negative (a large triangle seen from close by).
    2.0 * numerator.atan2(denominator)
}

/// The mean of cos(theta) / d^2 toward a point source over a square patch
/// of `area` (m^2) centred on a surface point and lying in its plane, where
/// `offset` runs from the point to the source and `normal` is the
/// surface's unit normal: the patch's solid angle over its area. A point
/// light of intensity I gives the patch a mean irradiance of I times this.
/// Far from the source it tends to the point value n.offset / |offset|^3;
/// a source touching the plane gives 2 pi / area instead of infinity. Zero
/// for a source behind the plane or a patch without area. In f64: far
/// from the source the corners' directions differ little, and their cross
/// products would lose the patch's size to f32 rounding. Farther than
/// [`POINT_VALUE_DISTANCE_PER_SIDE`] sides from the source it returns the
/// point value, which then differs from the mean by under 0.1 % of the
/// on-axis value 1 / d^2 (relatively more at grazing angles, where both
/// are small).
pub fn mean_cosine_over_square(offset: Vec3, normal: Vec3, area: f32) -> f32 {
    let cosine = normal.dot(offset);
    if cosine <= 0.0 || area.is_nan() || area <= 0.0 {
        return 0.0;
    }
    let distance_squared = offset.length_squared();
    if distance_squared > POINT_VALUE_DISTANCE_PER_SIDE * POINT_VALUE_DISTANCE_PER_SIDE * area {
        // The mean's second-order term is about (side / distance)^2 / 4 of
        // I / d^2 at any angle; at 16 sides that is under 0.1 %, and the
        // solid angle's f64 atan2s are most of a hit's direct-light cost.
        return cosine / (distance_squared * distance_squared.sqrt());
    }
    let (tangent, bitangent) = orthonormal_basis(normal);
    let half = 0.5 * (area as f64).sqrt();
    let tangent = tangent.as_dvec3() * half;
    let bitangent = bitangent.as_dvec3() * half;
    let source = offset.as_dvec3();
    let corner = |u: f64, v: f64| tangent * u + bitangent * v - source;
    let corners = [
        corner(-1.0, -1.0),
        corner(1.0, -1.0),
        corner(1.0, 1.0),
        corner(-1.0, 1.0),
    ];
    let solid_angle = triangle_solid_angle(corners[0], corners[1], corners[2])
        + triangle_solid_angle(corners[0], corners[2], corners[3]);
    (solid_angle / area as f64) as f32
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::f64::consts::PI;

    #[test]
    fn an_octant_triangle_subtends_an_eighth_of_the_sphere() {
        let angle = triangle_solid_angle(DVec3::X, DVec3::Y, DVec3::Z);
        assert!((angle - PI / 2.0).abs() < 1e-12, "{angle}");
    }

    /// A square of side s seen on its axis from height h subtends
    /// 4 asin(s^2 / (s^2 + 4 h^2)), a closed form independent of the
    /// triangle formula.
    #[test]
    fn the_square_matches_the_closed_form_on_its_axis() {
        for (side, height) in [(0.3f64, 0.05f64), (0.3, 0.3), (1.0, 2.0), (0.2, 3.0)] {
            let expected =
                4.0 * (side * side / (side * side + 4.0 * height * height)).asin() / (side * side);
            let mean = mean_cosine_over_square(
                Vec3::new(0.0, height as f32, 0.0),
                Vec3::Y,
                (side * side) as f32,
            ) as f64;
            // f32 inputs and output: 1e-5 relative.
            assert!(
                (mean / expected - 1.0).abs() < 1e-5,
                "side {side} height {height}: {mean} against {expected}"
            );
        }
    }

    #[test]
    fn far_away_it_is_the_point_value_and_close_by_it_stays_bounded() {
        let normal = Vec3::new(0.0, 0.0, 1.0);
        let offset = Vec3::new(3.0, -2.0, 5.0);
        let point_value = normal.dot(offset) / offset.length().powi(3);
        let mean = mean_cosine_over_square(offset, normal, 0.01);
        // The patch is 0.1 m across at 6.2 m: the two differ by a few 1e-4.
        assert!(
            (mean / point_value - 1.0).abs() < 1e-3,
            "{mean} {point_value}"
        );
        // A source just off the plane: nearly a hemisphere, never more.
        let touching = mean_cosine_over_square(Vec3::new(0.0, 0.0, 1e-6), normal, 0.04);
        let hemisphere = 2.0 * std::f32::consts::PI / 0.04;
        assert!(touching <= hemisphere * 1.0001 && touching > 0.99 * hemisphere);
        assert_eq!(mean_cosine_over_square(-offset, normal, 0.01), 0.0);
        assert_eq!(mean_cosine_over_square(offset, normal, 0.0), 0.0);
    }

    /// Just inside the switch to the point value, the solid angle and the
    /// point value agree within 0.1 % of the on-axis value I / d^2 at every
    /// angle to the normal, so the switch leaves no visible seam; just
    /// outside, the point value is returned exactly.
    #[test]
    fn the_point_value_takes_over_without_a_seam() {
        let normal = Vec3::Z;
        let area = 0.0025f32;
        let side = area.sqrt();
        let inside = POINT_VALUE_DISTANCE_PER_SIDE * side * 0.999;
        let outside = POINT_VALUE_DISTANCE_PER_SIDE * side * 1.001;
        for step in 0..32 {
            let polar = step as f32 / 32.0 * std::f32::consts::FRAC_PI_2;
            let direction = Vec3::new(polar.sin() * 0.8, polar.sin() * 0.6, polar.cos());
            let near = direction * inside;
            let point_value = normal.dot(near) / inside.powi(3);
            let mean = mean_cosine_over_square(near, normal, area);
            assert!(
                (mean - point_value).abs() * inside * inside < 1e-3,
                "polar {polar}: {mean} against {point_value}"
            );
            let far = direction * outside;
            let far_point_value = normal.dot(far) / outside.powi(3);
            let far_mean = mean_cosine_over_square(far, normal, area);
            assert!(
                (far_mean - far_point_value).abs() <= 1e-6 * far_point_value.abs(),
                "polar {polar}: {far_mean} against {far_point_value}"
            );
        }
    }
}
