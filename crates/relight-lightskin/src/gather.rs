//! Applying every VAL to a receiving point (equations 3, 4 and 7).
//!
//! For a VAL j at l_j with normal n_j, power over pi P_j and disc radius r_j,
//! and a receiver at x with normal n, v = x - l_j, d^2 = |v|^2:
//!
//!   irradiance_j = P_j * max(0, n_j.v) * max(0, -n.v) / (d^2 (r_j^2 + d^2))
//!
//! which is the disc form factor of equation 3 (w_j cos(theta_i)) times the
//! disc's radiant exitance P_j pi / (pi r_j^2). The kernel also sums the
//! weights of the averaged light position l'_d and, when occlusion needs
//! the light's spread, the weighted squares.
//!
//! Weights: the paper averages positions with w_j cos(theta_i) alone, so a
//! dark VAL pulls the averaged light as hard as a bright one. relight
//! weights by the luminance of each VAL's irradiance at x instead, which
//! puts l'_d at the centre of the light that actually arrives (a test shows
//! the difference); the epsilon term of equation 7 is kept.
//!
//! Blocking: VALs are read in blocks of `block` (the paper's K_cache) for a
//! group of receivers at a time, so a block stays in L1/L2 while every
//! receiver of the group uses it. The inner loop runs eight VALs per step
//! in AVX2/FMA when the CPU has them (detected at run time), otherwise in
//! portable code; both give the same sums up to rounding (tested).

use crate::vals::{Vals, LANES};
use glam::Vec3;
use relight_core::Rgb;

/// Sums of one receiver over some VALs.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct Sums {
    pub irradiance: [f32; 3],
    /// Sum of position weights.
    pub weight: f32,
    /// Sum of weight times position.
    pub weighted_position: [f32; 3],
    /// Sum of weight times position squared (only when spread is wanted).
    pub weighted_square: [f32; 3],
}

impl Sums {
    pub fn irradiance(&self) -> Rgb {
        Rgb::from_array(self.irradiance)
    }
}

/// Smallest squared distance the kernel divides by: keeps a VAL that sits
/// exactly on a receiver (both cosines zero) from producing 0/0.
const MIN_DISTANCE_SQ: f32 = 1e-12;

/// Adds VALs `start..end` (multiples of [`LANES`]) to `sums` for the
/// receiver at `position` with `normal`; `SPREAD` also sums the squares.
pub fn accumulate<const SPREAD: bool>(
    vals: &Vals,
    start: usize,
    end: usize,
    position: Vec3,
    normal: Vec3,
    sums: &mut Sums,
) {
    debug_assert!(
        start.is_multiple_of(LANES) && end.is_multiple_of(LANES) && end <= vals.padded_len()
    );
    #[cfg(target_arch = "x86_64")]
    {
        if std::arch::is_x86_feature_detected!("avx2") && std::arch::is_x86_feature_detected!("fma")
        {
            // SAFETY: the CPU supports AVX2 and FMA (checked just above),
            // and the range lies inside every column (asserted by callers
            // and by the padding to LANES).
            unsafe { accumulate_avx2::<SPREAD>(vals, start, end, position, normal, sums) };
            return;
        }
    }
    accumulate_portable::<SPREAD>(vals, start, end, position, normal, sums);
}

/// The portable form of [`accumulate`]; also the reference for its test.
pub fn accumulate_portable<const SPREAD: bool>(
    vals: &Vals,
    start: usize,
    end: usize,
    position: Vec3,
    normal: Vec3,
    sums: &mut Sums,
) {
    for j in start..end {
        let vx = position.x - vals.px[j];
        let vy = position.y - vals.py[j];
        let vz = position.z - vals.pz[j];
        let distance_sq = (vx * vx + vy * vy + vz * vz).max(MIN_DISTANCE_SQ);
        let cos_val = (vals.nx[j] * vx + vals.ny[j] * vy + vals.nz[j] * vz).max(0.0);
        let cos_receiver = -(normal.x * vx + normal.y * vy + normal.z * vz);
        let geometry =
            cos_val * cos_receiver.max(0.0) / (distance_sq * (vals.radius_sq[j] + distance_sq));
        sums.irradiance[0] += vals.power_r[j] * geometry;
        sums.irradiance[1] += vals.power_g[j] * geometry;
        sums.irradiance[2] += vals.power_b[j] * geometry;
        let weight = vals.power_luminance[j] * geometry;
        sums.weight += weight;
        let p = [vals.px[j], vals.py[j], vals.pz[j]];
        for (axis, coordinate) in p.into_iter().enumerate() {
            let weighted = weight * coordinate;
            sums.weighted_position[axis] += weighted;
            if SPREAD {
                sums.weighted_square[axis] += weighted * coordinate;
            }
        }
    }
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2,fma")]
unsafe fn accumulate_avx2<const SPREAD: bool>(
    vals: &Vals,
    start: usize,
    end: usize,
    position: Vec3,
    normal: Vec3,
    sums: &mut Sums,
) {
    use std::arch::x86_64::*;
    let x = _mm256_set1_ps(position.x);
    let y = _mm256_set1_ps(position.y);
    let z = _mm256_set1_ps(position.z);
    // -n, so that cos_receiver is a plain dot product with v.
    let mx = _mm256_set1_ps(-normal.x);
    let my = _mm256_set1_ps(-normal.y);
    let mz = _mm256_set1_ps(-normal.z);
    let zero = _mm256_setzero_ps();
    let min_distance_sq = _mm256_set1_ps(MIN_DISTANCE_SQ);
    let mut irradiance_r = zero;
    let mut irradiance_g = zero;
    let mut irradiance_b = zero;
    let mut weight_sum = zero;
    let mut sum_x = zero;
    let mut sum_y = zero;
    let mut sum_z = zero;
    let mut square_x = zero;
    let mut square_y = zero;
    let mut square_z = zero;
    let column = |values: &Vec<f32>, j: usize| _mm256_loadu_ps(values.as_ptr().add(j));
    let mut j = start;
    while j < end {
        let px = column(&vals.px, j);
        let py = column(&vals.py, j);
        let pz = column(&vals.pz, j);
        let vx = _mm256_sub_ps(x, px);
        let vy = _mm256_sub_ps(y, py);
        let vz = _mm256_sub_ps(z, pz);
        let distance_sq = _mm256_max_ps(
            _mm256_fmadd_ps(vz, vz, _mm256_fmadd_ps(vy, vy, _mm256_mul_ps(vx, vx))),
            min_distance_sq,
        );
        let cos_val = _mm256_fmadd_ps(
            column(&vals.nz, j),
            vz,
            _mm256_fmadd_ps(
                column(&vals.ny, j),
                vy,
                _mm256_mul_ps(column(&vals.nx, j), vx),
            ),
        );
        let cos_receiver = _mm256_fmadd_ps(mz, vz, _mm256_fmadd_ps(my, vy, _mm256_mul_ps(mx, vx)));
        let numerator = _mm256_mul_ps(
            _mm256_max_ps(cos_val, zero),
            _mm256_max_ps(cos_receiver, zero),
        );
        let denominator = _mm256_mul_ps(
            distance_sq,
            _mm256_add_ps(column(&vals.radius_sq, j), distance_sq),
        );
        let geometry = _mm256_div_ps(numerator, denominator);
        irradiance_r = _mm256_fmadd_ps(column(&vals.power_r, j), geometry, irradiance_r);
        irradiance_g = _mm256_fmadd_ps(column(&vals.power_g, j), geometry, irradiance_g);
        irradiance_b = _mm256_fmadd_ps(column(&vals.power_b, j), geometry, irradiance_b);
        let weight = _mm256_mul_ps(column(&vals.power_luminance, j), geometry);
        weight_sum = _mm256_add_ps(weight_sum, weight);
        let weighted_x = _mm256_mul_ps(weight, px);
        let weighted_y = _mm256_mul_ps(weight, py);
        let weighted_z = _mm256_mul_ps(weight, pz);
        sum_x = _mm256_add_ps(sum_x, weighted_x);
        sum_y = _mm256_add_ps(sum_y, weighted_y);
        sum_z = _mm256_add_ps(sum_z, weighted_z);
        if SPREAD {
            square_x = _mm256_fmadd_ps(weighted_x, px, square_x);
            square_y = _mm256_fmadd_ps(weighted_y, py, square_y);
            square_z = _mm256_fmadd_ps(weighted_z, pz, square_z);
        }
        j += LANES;
    }
    let total = |v: __m256| {
        let mut lanes = [0f32; LANES];
        _mm256_storeu_ps(lanes.as_mut_ptr(), v);
        lanes.iter().sum::<f32>()
    };
    sums.irradiance[0] += total(irradiance_r);
    sums.irradiance[1] += total(irradiance_g);
    sums.irradiance[2] += total(irradiance_b);
    sums.weight += total(weight_sum);
    sums.weighted_position[0] += total(sum_x);
    sums.weighted_position[1] += total(sum_y);
    sums.weighted_position[2] += total(sum_z);
    if SPREAD {
        sums.weighted_square[0] += total(square_x);
        sums.weighted_square[1] += total(square_y);
        sums.weighted_square[2] += total(square_z);
    }
}

/// Glossy sums of equation 7 (L'_s and l'_s) for a receiver whose ideal
/// reflection of the view direction is `reflected` and whose Phong exponent
/// is `exponent`: irradiance-like P_j cos_j cos^k(gamma) / (r_j^2 + d^2),
/// with cos(gamma) the angle between `reflected` and the direction to the
/// VAL. Scalar: only glossy receivers pay for it.
pub fn accumulate_glossy(
    vals: &Vals,
    position: Vec3,
    normal: Vec3,
    reflected: Vec3,
    exponent: f32,
    sums: &mut Sums,
) {
    for j in 0..vals.count {
        let to_val = Vec3::new(vals.px[j], vals.py[j], vals.pz[j]) - position;
        let distance_sq = to_val.length_squared().max(MIN_DISTANCE_SQ);
        let distance = distance_sq.sqrt();
        let direction = to_val / distance;
        if direction.dot(normal) <= 0.0 {
            continue;
        }
        let cos_val =
            -(vals.nx[j] * direction.x + vals.ny[j] * direction.y + vals.nz[j] * direction.z);
        let cos_gamma = reflected.dot(direction);
        if cos_val <= 0.0 || cos_gamma <= 0.0 {
            continue;
        }
        let geometry = cos_val * cos_gamma.powf(exponent) / (vals.radius_sq[j] + distance_sq);
        sums.irradiance[0] += vals.power_r[j] * geometry;
        sums.irradiance[1] += vals.power_g[j] * geometry;
        sums.irradiance[2] += vals.power_b[j] * geometry;
        let weight = vals.power_luminance[j] * geometry;
        sums.weight += weight;
        for axis in 0..3 {
            sums.weighted_position[axis] += weight * to_val[axis] + weight * position[axis];
        }
    }
}
