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

/// Sparse points as occluders, struct of arrays padded to a multiple of
/// eight (padding: far away, zero radius).
#[derive(Clone, Debug, Default)]
pub struct Occluders {
    pub x: Vec<f32>,
    pub y: Vec<f32>,
    pub z: Vec<f32>,
    pub nx: Vec<f32>,
    pub ny: Vec<f32>,
    pub nz: Vec<f32>,
    /// Disc radius squared of each point.
    pub radius_sq: Vec<f32>,
}

const LANES: usize = 8;

impl Occluders {
    /// Refills from the sparse points of this frame.
    pub fn fill(&mut self, positions: &[Vec3], normals: &[Vec3], radius_sq: &[f32]) {
        let padded = positions.len().div_ceil(LANES) * LANES;
        let columns = [
            &mut self.x,
            &mut self.y,
            &mut self.z,
            &mut self.nx,
            &mut self.ny,
            &mut self.nz,
            &mut self.radius_sq,
        ];
        for column in columns {
            column.clear();
            column.resize(padded, 0.0);
        }
        for (index, ((position, normal), &r_sq)) in
            positions.iter().zip(normals).zip(radius_sq).enumerate()
        {
            self.x[index] = position.x;
            self.y[index] = position.y;
            self.z[index] = position.z;
            self.nx[index] = normal.x;
            self.ny[index] = normal.y;
            self.nz[index] = normal.z;
            self.radius_sq[index] = r_sq;
        }
        for index in positions.len()..padded {
            self.x[index] = 1e6;
            self.y[index] = 1e6;
            self.z[index] = 1e6;
        }
    }

    pub fn memory_bytes(&self) -> usize {
        self.x.capacity() * 4 * 7
    }
}

/// What one receiver needs to know about its light sphere.
#[derive(Clone, Copy, Debug)]
struct LightQuad {
    position: Vec3,
    normal: Vec3,
    tangent: Vec3,
    bitangent: Vec3,
    distance: f32,
    inverse_radius: f32,
    half_side: f32,
    u: f32,
    v: f32,
}

/// Fraction (0..1) of the light sphere (`light_centre`, `light_radius`)
/// hidden from the point at `position` with `normal` by the discs of
/// `occluders` (a disc at distance zero, the point itself, is skipped).
pub fn occluded_fraction(
    occluders: &Occluders,
    position: Vec3,
    normal: Vec3,
    light_centre: Vec3,
    light_radius: f32,
) -> f32 {
    let Some((light, area)) = light_quad(position, normal, light_centre, light_radius) else {
        return 0.0;
    };
    #[cfg(target_arch = "x86_64")]
    {
        if std::arch::is_x86_feature_detected!("avx2") && std::arch::is_x86_feature_detected!("fma")
        {
            // SAFETY: AVX2 and FMA are present (checked above) and every
            // column has the same, padded length.
            let overlap = unsafe { overlap_avx2(occluders, &light) };
            return (overlap / area).min(1.0);
        }
    }
    (overlap_portable(occluders, &light) / area).min(1.0)
}

/// The light sphere as seen from the receiver, and its projected area;
/// `None` when the light is at the receiver or behind its surface.
fn light_quad(
    position: Vec3,
    normal: Vec3,
    light_centre: Vec3,
    light_radius: f32,
) -> Option<(LightQuad, f32)> {
    let to_light = light_centre - position;
    let distance = to_light.length();
    if distance <= 1e-6 {
        return None;
    }
    let direction = to_light / distance;
    let cos_light = direction.dot(normal);
    if cos_light <= 0.0 {
        return None;
    }
    let radius = light_radius.max(1e-6);
    let radius_sq = radius * radius;
    // pi F_disk of a sphere (cos theta_j = 1): its area on the unit circle.
    let area = std::f32::consts::PI * radius_sq / (radius_sq + distance * distance) * cos_light;
    let (tangent, bitangent) = orthonormal_basis(normal);
    let light = LightQuad {
        position,
        normal,
        tangent,
        bitangent,
        distance,
        inverse_radius: 1.0 / radius,
        half_side: 0.5 * area.sqrt(),
        u: direction.dot(tangent),
        v: direction.dot(bitangent),
    };
    Some((light, area))
}

/// Summed, faded overlap of the occluders' squares with the light's square.
fn overlap_portable(occluders: &Occluders, light: &LightQuad) -> f32 {
    let mut overlap_sum = 0.0f32;
    for k in 0..occluders.x.len() {
        let to_occluder =
            Vec3::new(occluders.x[k], occluders.y[k], occluders.z[k]) - light.position;
        let distance_sq = to_occluder.length_squared();
        if distance_sq <= 1e-12 {
            continue;
        }
        let distance = distance_sq.sqrt();
        // Linear fade: 1 in front of the sphere, 0 from its centre on.
        let fade = ((light.distance - distance) * light.inverse_radius).clamp(0.0, 1.0);
        let direction = to_occluder / distance;
        let cos_receiver = direction.dot(light.normal);
        if cos_receiver <= 1e-4 || fade <= 0.0 {
            continue;
        }
        // A disc hides light from either side.
        let disc_normal = Vec3::new(occluders.nx[k], occluders.ny[k], occluders.nz[k]);
        let cos_disc = direction.dot(disc_normal).abs();
        let radius_sq = occluders.radius_sq[k];
        let area =
            std::f32::consts::PI * radius_sq * cos_disc / (radius_sq + distance_sq) * cos_receiver;
        let half_side = 0.5 * area.sqrt();
        let u = direction.dot(light.tangent);
        let v = direction.dot(light.bitangent);
        let overlap = |centre: f32, light_centre: f32| {
            ((centre + half_side).min(light_centre + light.half_side)
                - (centre - half_side).max(light_centre - light.half_side))
            .max(0.0)
        };
        let overlap_u = overlap(u, light.u);
        let overlap_v = overlap(v, light.v);
        overlap_sum += fade * overlap_u * overlap_v;
    }
    overlap_sum
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2,fma")]
unsafe fn overlap_avx2(occluders: &Occluders, light: &LightQuad) -> f32 {
    use std::arch::x86_64::*;
    let splat = _mm256_set1_ps;
    let (x, y, z) = (
        splat(light.position.x),
        splat(light.position.y),
        splat(light.position.z),
    );
    let (nx, ny, nz) = (
        splat(light.normal.x),
        splat(light.normal.y),
        splat(light.normal.z),
    );
    let (tx, ty, tz) = (
        splat(light.tangent.x),
        splat(light.tangent.y),
        splat(light.tangent.z),
    );
    let (bx, by, bz) = (
        splat(light.bitangent.x),
        splat(light.bitangent.y),
        splat(light.bitangent.z),
    );
    let light_distance = splat(light.distance);
    let inverse_radius = splat(light.inverse_radius);
    let light_u_high = splat(light.u + light.half_side);
    let light_u_low = splat(light.u - light.half_side);
    let light_v_high = splat(light.v + light.half_side);
    let light_v_low = splat(light.v - light.half_side);
    let zero = _mm256_setzero_ps();
    let one = splat(1.0);
    let pi_quarter = splat(0.25 * std::f32::consts::PI);
    let min_distance_sq = splat(1e-12);
    let min_cos = splat(1e-4);
    let tiny = splat(1e-30);
    let sign_mask = splat(-0.0);
    let column = |values: &Vec<f32>, k: usize| _mm256_loadu_ps(values.as_ptr().add(k));
    let mut total = zero;
    let mut k = 0;
    while k < occluders.x.len() {
        let dx = _mm256_sub_ps(column(&occluders.x, k), x);
        let dy = _mm256_sub_ps(column(&occluders.y, k), y);
        let dz = _mm256_sub_ps(column(&occluders.z, k), z);
        let distance_sq = _mm256_fmadd_ps(dz, dz, _mm256_fmadd_ps(dy, dy, _mm256_mul_ps(dx, dx)));
        // Approximate 1/d (12 bits): the projection is itself approximate.
        let inverse = _mm256_rsqrt_ps(_mm256_max_ps(distance_sq, min_distance_sq));
        let distance = _mm256_mul_ps(distance_sq, inverse);
        let fade = _mm256_min_ps(
            _mm256_max_ps(
                _mm256_mul_ps(_mm256_sub_ps(light_distance, distance), inverse_radius),
                zero,
            ),
            one,
        );
        let cos_receiver = _mm256_mul_ps(
            _mm256_fmadd_ps(dz, nz, _mm256_fmadd_ps(dy, ny, _mm256_mul_ps(dx, nx))),
            inverse,
        );
        let disc_dot = _mm256_fmadd_ps(
            dz,
            column(&occluders.nz, k),
            _mm256_fmadd_ps(
                dy,
                column(&occluders.ny, k),
                _mm256_mul_ps(dx, column(&occluders.nx, k)),
            ),
        );
        let cos_disc = _mm256_mul_ps(_mm256_andnot_ps(sign_mask, disc_dot), inverse);
        let radius_sq = column(&occluders.radius_sq, k);
        // (half side)^2 = area / 4 with area = pi r^2 cos_disc cos_rec / (r^2 + d^2).
        let half_side_sq = _mm256_mul_ps(
            _mm256_mul_ps(
                _mm256_mul_ps(pi_quarter, radius_sq),
                _mm256_mul_ps(cos_disc, cos_receiver),
            ),
            _mm256_rcp_ps(_mm256_add_ps(radius_sq, distance_sq)),
        );
        let half_side_sq = _mm256_max_ps(half_side_sq, tiny);
        let half_side = _mm256_mul_ps(half_side_sq, _mm256_rsqrt_ps(half_side_sq));
        let u = _mm256_mul_ps(
            _mm256_fmadd_ps(dz, tz, _mm256_fmadd_ps(dy, ty, _mm256_mul_ps(dx, tx))),
            inverse,
        );
        let v = _mm256_mul_ps(
            _mm256_fmadd_ps(dz, bz, _mm256_fmadd_ps(dy, by, _mm256_mul_ps(dx, bx))),
            inverse,
        );
        // Overlap of [centre - half, centre + half] with [low, high].
        let overlap = |centre: __m256, low: __m256, high: __m256| {
            _mm256_max_ps(
                _mm256_sub_ps(
                    _mm256_min_ps(_mm256_add_ps(centre, half_side), high),
                    _mm256_max_ps(_mm256_sub_ps(centre, half_side), low),
                ),
                zero,
            )
        };
        let overlap_u = overlap(u, light_u_low, light_u_high);
        let overlap_v = overlap(v, light_v_low, light_v_high);
        let valid = _mm256_and_ps(
            _mm256_cmp_ps::<_CMP_GT_OQ>(cos_receiver, min_cos),
            _mm256_cmp_ps::<_CMP_GT_OQ>(distance_sq, min_distance_sq),
        );
        let contribution = _mm256_mul_ps(fade, _mm256_mul_ps(overlap_u, overlap_v));
        total = _mm256_add_ps(total, _mm256_and_ps(valid, contribution));
        k += LANES;
    }
    let mut lanes = [0f32; LANES];
    _mm256_storeu_ps(lanes.as_mut_ptr(), total);
    lanes.iter().sum()
}

/// [`occluded_fraction`] without SIMD, for tests of the AVX2 form.
pub fn occluded_fraction_portable(
    occluders: &Occluders,
    position: Vec3,
    normal: Vec3,
    light_centre: Vec3,
    light_radius: f32,
) -> f32 {
    match light_quad(position, normal, light_centre, light_radius) {
        Some((light, area)) => (overlap_portable(occluders, &light) / area).min(1.0),
        None => 0.0,
    }
}
