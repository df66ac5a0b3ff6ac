//! Indirect occlusion by sparse-point discs (section 3.3).
//!
//! Each sparse point's averaged light becomes a sphere S_o centred at l'_d
//! whose radius is the largest side of the box l'_d +- sigma (sigma: the
//! weighted standard deviation of the light positions per axis). Every
//! other sparse point is a disc occluder of the area that point stands for.
//! Both are projected onto the receiver's tangent plane (Nusselt's analogue:
//! pi * F_disk of equation 3 is the projected area) as squares of that area
//! centred on the projected centres (equation 14); the occluded fraction is
//! the summed overlap over the sphere's projected area, each occluder scaled
//! linearly from one in front of S_o to zero at its centre, so that the
//! light's own surfaces behind and inside S_o do not occlude it.

use glam::Vec3;
use relight_core::sampling::orthonormal_basis;

/// Sparse points as occluders, struct of arrays.
pub struct Occluders<'a> {
    pub positions: &'a [Vec3],
    pub normals: &'a [Vec3],
    /// Disc radius squared of each point.
    pub radius_sq: &'a [f32],
}

/// Fraction (0..1) of the light sphere (`light_centre`, `light_radius`)
/// hidden from the sparse point `receiver` by the other points' discs.
pub fn occluded_fraction(
    occluders: &Occluders,
    receiver: usize,
    light_centre: Vec3,
    light_radius: f32,
) -> f32 {
    let position = occluders.positions[receiver];
    let normal = occluders.normals[receiver];
    let to_light = light_centre - position;
    let light_distance = to_light.length();
    if light_distance <= 1e-6 {
        return 0.0;
    }
    let light_direction = to_light / light_distance;
    let cos_light = light_direction.dot(normal);
    if cos_light <= 0.0 {
        return 0.0;
    }
    let light_radius = light_radius.max(1e-6);
    let light_radius_sq = light_radius * light_radius;
    // pi F_disk of a sphere (cos theta_j = 1), in the unit circle's area.
    let light_area = std::f32::consts::PI * light_radius_sq
        / (light_radius_sq + light_distance * light_distance)
        * cos_light;
    let (tangent, bitangent) = orthonormal_basis(normal);
    let light_half_side = 0.5 * light_area.sqrt();
    let light_u = light_direction.dot(tangent);
    let light_v = light_direction.dot(bitangent);
    let mut overlap_sum = 0.0f32;
    for k in 0..occluders.positions.len() {
        let to_occluder = occluders.positions[k] - position;
        let distance_sq = to_occluder.length_squared();
        if k == receiver || distance_sq <= 1e-12 {
            continue;
        }
        let distance = distance_sq.sqrt();
        // Linear fade: 1 in front of the sphere, 0 from its centre on.
        let fade = ((light_distance - distance) / light_radius).clamp(0.0, 1.0);
        if fade <= 0.0 {
            continue;
        }
        let direction = to_occluder / distance;
        let cos_receiver = direction.dot(normal);
        if cos_receiver <= 1e-4 {
            continue;
        }
        // A disc hides light from either side.
        let cos_disc = direction.dot(occluders.normals[k]).abs();
        let radius_sq = occluders.radius_sq[k];
        let area =
            std::f32::consts::PI * radius_sq * cos_disc / (radius_sq + distance_sq) * cos_receiver;
        let half_side = 0.5 * area.sqrt();
        let u = direction.dot(tangent);
        let v = direction.dot(bitangent);
        let overlap_u = ((u + half_side).min(light_u + light_half_side)
            - (u - half_side).max(light_u - light_half_side))
        .max(0.0);
        let overlap_v = ((v + half_side).min(light_v + light_half_side)
            - (v - half_side).max(light_v - light_half_side))
        .max(0.0);
        overlap_sum += fade * overlap_u * overlap_v;
    }
    (overlap_sum / light_area).min(1.0)
}
