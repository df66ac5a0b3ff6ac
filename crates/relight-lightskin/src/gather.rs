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
//!
//! Visibility: given the receiver's row of [`crate::visibility`], a VAL
//! counts only where the receiver sees the VAL's anchor (the AVX2 kernel
//! gathers the eight anchors' bits from the row and masks the geometry
//! term).

use crate::vals::{row_sees, MIXED_WORDS};
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

    /// Adds one light's `irradiance` arriving from `position` (with its
    /// squares `position_sq`), weighted `weight` in the averaged light;
    /// `SPREAD` also sums the weighted squares.
    #[inline]
    pub fn add<const SPREAD: bool>(
        &mut self,
        irradiance: [f32; 3],
        weight: f32,
        position: [f32; 3],
        position_sq: [f32; 3],
    ) {
        for (sum, value) in self.irradiance.iter_mut().zip(irradiance) {
            *sum += value;
        }
        self.weight += weight;
        for axis in 0..3 {
            self.weighted_position[axis] += weight * position[axis];
            if SPREAD {
                self.weighted_square[axis] += weight * position_sq[axis];
            }
        }
    }
}

/// Smallest squared distance the kernel divides by: keeps a VAL that sits
/// exactly on a receiver (both cosines zero) from producing 0/0.
const MIN_DISTANCE_SQ: f32 = 1e-12;

/// Adds VALs `start..end` (multiples of [`LANES`]) to `sums` for the
/// receiver at `position` with `normal`; `SPREAD` also sums the squares.
/// With `visible`, the receiver's visibility row, only the VALs whose
/// anchor it sees count (`vals.anchor` must then be filled).
pub fn accumulate<const SPREAD: bool>(
    vals: &Vals,
    start: usize,
    end: usize,
    position: Vec3,
    normal: Vec3,
    visible: Option<&[u32]>,
    sums: &mut Sums,
) {
    accumulate_many::<SPREAD>(
        vals,
        start,
        end,
        &[position],
        &[normal],
        visible.as_ref().map(std::slice::from_ref),
        std::slice::from_mut(sums),
    );
}

/// The portable form of [`accumulate`]; also the reference for its test.
pub fn accumulate_portable<const SPREAD: bool>(
    vals: &Vals,
    start: usize,
    end: usize,
    position: Vec3,
    normal: Vec3,
    visible: Option<&[u32]>,
    sums: &mut Sums,
) {
    for j in start..end {
        if visible.is_some_and(|row| !row_sees(row, vals.anchor[j])) {
            continue;
        }
        let vx = position.x - vals.px[j];
        let vy = position.y - vals.py[j];
        let vz = position.z - vals.pz[j];
        let distance_sq = (vx * vx + vy * vy + vz * vz).max(MIN_DISTANCE_SQ);
        let cos_val = (vals.nx[j] * vx + vals.ny[j] * vy + vals.nz[j] * vz).max(0.0);
        let cos_receiver = -(normal.x * vx + normal.y * vy + normal.z * vz);
        let geometry =
            cos_val * cos_receiver.max(0.0) / (distance_sq * (vals.radius_sq[j] + distance_sq));
        sums.add::<SPREAD>(
            [
                vals.power_r[j] * geometry,
                vals.power_g[j] * geometry,
                vals.power_b[j] * geometry,
            ],
            vals.power_luminance[j] * geometry,
            [vals.px[j], vals.py[j], vals.pz[j]],
            [vals.px_sq[j], vals.py_sq[j], vals.pz_sq[j]],
        );
    }
}

/// Receivers per pass of the AVX2 kernel: each VAL load serves both, and
/// the two independent dependency chains keep the FP units busy (the
/// single-receiver loop is bound by its chain's latency, not by issue).
pub const RECEIVERS_PER_PASS: usize = 4;

/// [`accumulate`] for several receivers: the AVX2 kernel takes them
/// [`RECEIVERS_PER_PASS`] at a time, the rest one by one.
/// `visible`: each receiver's visibility row, as in [`accumulate`].
pub fn accumulate_many<const SPREAD: bool>(
    vals: &Vals,
    start: usize,
    end: usize,
    positions: &[Vec3],
    normals: &[Vec3],
    visible: Option<&[&[u32]]>,
    sums: &mut [Sums],
) {
    debug_assert!(
        start.is_multiple_of(LANES) && end.is_multiple_of(LANES) && end <= vals.padded_len()
    );
    debug_assert!(visible.is_none_or(|rows| rows.len() == sums.len() && vals.anchor.len() >= end));
    #[cfg(target_arch = "x86_64")]
    {
        if std::arch::is_x86_feature_detected!("avx2") && std::arch::is_x86_feature_detected!("fma")
        {
            let rows_from = |index: usize| visible.map(|rows| &rows[index..]);
            let mut index = 0;
            while index + RECEIVERS_PER_PASS <= sums.len() {
                // SAFETY: AVX2 and FMA are present (checked above); the
                // range lies inside every column (padding to LANES).
                unsafe {
                    accumulate_avx2_receivers::<SPREAD, RECEIVERS_PER_PASS>(
                        vals,
                        start,
                        end,
                        &positions[index..],
                        &normals[index..],
                        rows_from(index),
                        &mut sums[index..],
                    )
                };
                index += RECEIVERS_PER_PASS;
            }
            for rest in index..sums.len() {
                // SAFETY: as above.
                unsafe {
                    accumulate_avx2_receivers::<SPREAD, 1>(
                        vals,
                        start,
                        end,
                        &positions[rest..],
                        &normals[rest..],
                        rows_from(rest),
                        &mut sums[rest..],
                    )
                };
            }
            return;
        }
    }
    for index in 0..sums.len() {
        accumulate_portable::<SPREAD>(
            vals,
            start,
            end,
            positions[index],
            normals[index],
            visible.map(|rows| rows[index]),
            &mut sums[index],
        );
    }
}

/// The first `R` receivers of the slices through the AVX2 kernel, with the
/// visibility mask when `visible` is given.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2,fma")]
#[inline]
unsafe fn accumulate_avx2_receivers<const SPREAD: bool, const R: usize>(
    vals: &Vals,
    start: usize,
    end: usize,
    positions: &[Vec3],
    normals: &[Vec3],
    visible: Option<&[&[u32]]>,
    sums: &mut [Sums],
) {
    // A row nobody reads stands in when there is no visibility.
    let everything = [u32::MAX];
    let mut group: [Sums; R] = std::array::from_fn(|offset| sums[offset]);
    let positions = std::array::from_fn(|offset| positions[offset]);
    let normals = std::array::from_fn(|offset| normals[offset]);
    let rows = std::array::from_fn(|offset| visible.map_or(&everything[..], |rows| rows[offset]));
    if visible.is_some() {
        accumulate_avx2_group::<SPREAD, true, R>(
            vals, start, end, positions, normals, rows, &mut group,
        )
    } else {
        accumulate_avx2_group::<SPREAD, false, R>(
            vals, start, end, positions, normals, rows, &mut group,
        )
    }
    sums[..R].copy_from_slice(&group);
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2,fma")]
#[inline]
/// `VISIBLE`: mask each VAL by its anchor's bit in the receiver's `rows`
/// (which must then hold every anchor's word).
unsafe fn accumulate_avx2_group<const SPREAD: bool, const VISIBLE: bool, const R: usize>(
    vals: &Vals,
    start: usize,
    end: usize,
    positions: [Vec3; R],
    normals: [Vec3; R],
    rows: [&[u32]; R],
    sums: &mut [Sums; R],
) {
    use std::arch::x86_64::*;
    let zero = _mm256_setzero_ps();
    let min_distance_sq = _mm256_set1_ps(MIN_DISTANCE_SQ);
    let x = positions.map(|p| _mm256_set1_ps(p.x));
    let y = positions.map(|p| _mm256_set1_ps(p.y));
    let z = positions.map(|p| _mm256_set1_ps(p.z));
    // -n, so that cos_receiver is a plain dot product with v.
    let mx = normals.map(|n| _mm256_set1_ps(-n.x));
    let my = normals.map(|n| _mm256_set1_ps(-n.y));
    let mz = normals.map(|n| _mm256_set1_ps(-n.z));
    let mut irradiance_r = [zero; R];
    let mut irradiance_g = [zero; R];
    let mut irradiance_b = [zero; R];
    let mut weight_sum = [zero; R];
    let mut sum_x = [zero; R];
    let mut sum_y = [zero; R];
    let mut sum_z = [zero; R];
    let mut square_x = [zero; R];
    let mut square_y = [zero; R];
    let mut square_z = [zero; R];
    let column = |values: &Vec<f32>, j: usize| _mm256_loadu_ps(values.as_ptr().add(j));
    let one = _mm256_set1_epi32(1);
    let low_bits = _mm256_set1_epi32(31);
    let all_lanes = _mm256_castsi256_ps(_mm256_set1_epi32(-1));
    let mut j = start;
    while j < end {
        let mut masks = [all_lanes; R];
        if VISIBLE {
            let anchors = _mm256_loadu_si256(vals.anchor.as_ptr().add(j) as *const __m256i);
            let anchor_bit = _mm256_and_si256(anchors, low_bits);
            let block = j / LANES;
            let word = *vals.block_word.get_unchecked(block);
            if word != MIXED_WORDS {
                // Sorted by anchor, most blocks' anchors share one word of
                // each row: one load per receiver, and no work at all for
                // a block that none of the receivers sees.
                let words: [u32; R] =
                    std::array::from_fn(|r| *rows[r].get_unchecked(word as usize));
                let bits = *vals.block_bits.get_unchecked(block);
                if words.iter().all(|&word| word & bits == 0) {
                    j += LANES;
                    continue;
                }
                for r in 0..R {
                    let seen = _mm256_and_si256(
                        _mm256_srlv_epi32(_mm256_set1_epi32(words[r] as i32), anchor_bit),
                        one,
                    );
                    masks[r] = _mm256_castsi256_ps(_mm256_cmpeq_epi32(seen, one));
                }
            } else {
                let anchor_word = _mm256_srli_epi32::<5>(anchors);
                for r in 0..R {
                    let words =
                        _mm256_i32gather_epi32::<4>(rows[r].as_ptr() as *const i32, anchor_word);
                    let seen = _mm256_and_si256(_mm256_srlv_epi32(words, anchor_bit), one);
                    masks[r] = _mm256_castsi256_ps(_mm256_cmpeq_epi32(seen, one));
                }
            }
        }
        let px = column(&vals.px, j);
        let py = column(&vals.py, j);
        let pz = column(&vals.pz, j);
        let nx = column(&vals.nx, j);
        let ny = column(&vals.ny, j);
        let nz = column(&vals.nz, j);
        let radius_sq = column(&vals.radius_sq, j);
        let power_r = column(&vals.power_r, j);
        let power_g = column(&vals.power_g, j);
        let power_b = column(&vals.power_b, j);
        let luminance = column(&vals.power_luminance, j);
        for r in 0..R {
            let vx = _mm256_sub_ps(x[r], px);
            let vy = _mm256_sub_ps(y[r], py);
            let vz = _mm256_sub_ps(z[r], pz);
            let distance_sq = _mm256_max_ps(
                _mm256_fmadd_ps(vz, vz, _mm256_fmadd_ps(vy, vy, _mm256_mul_ps(vx, vx))),
                min_distance_sq,
            );
            let cos_val = _mm256_fmadd_ps(nz, vz, _mm256_fmadd_ps(ny, vy, _mm256_mul_ps(nx, vx)));
            let cos_receiver = _mm256_fmadd_ps(
                mz[r],
                vz,
                _mm256_fmadd_ps(my[r], vy, _mm256_mul_ps(mx[r], vx)),
            );
            let numerator = _mm256_mul_ps(
                _mm256_max_ps(cos_val, zero),
                _mm256_max_ps(cos_receiver, zero),
            );
            let denominator = _mm256_mul_ps(distance_sq, _mm256_add_ps(radius_sq, distance_sq));
            // The reciprocal estimate alone (relative error below 1.5 *
            // 2^-12, 0.04 %, far under the method's own error): a Newton
            // step or a division would lengthen the dependency chain that
            // limits this loop.
            let mut geometry = _mm256_mul_ps(numerator, _mm256_rcp_ps(denominator));
            if VISIBLE {
                geometry = _mm256_and_ps(geometry, masks[r]);
            }
            irradiance_r[r] = _mm256_fmadd_ps(power_r, geometry, irradiance_r[r]);
            irradiance_g[r] = _mm256_fmadd_ps(power_g, geometry, irradiance_g[r]);
            irradiance_b[r] = _mm256_fmadd_ps(power_b, geometry, irradiance_b[r]);
            let weight = _mm256_mul_ps(luminance, geometry);
            weight_sum[r] = _mm256_add_ps(weight_sum[r], weight);
            sum_x[r] = _mm256_fmadd_ps(weight, px, sum_x[r]);
            sum_y[r] = _mm256_fmadd_ps(weight, py, sum_y[r]);
            sum_z[r] = _mm256_fmadd_ps(weight, pz, sum_z[r]);
            if SPREAD {
                square_x[r] = _mm256_fmadd_ps(weight, column(&vals.px_sq, j), square_x[r]);
                square_y[r] = _mm256_fmadd_ps(weight, column(&vals.py_sq, j), square_y[r]);
                square_z[r] = _mm256_fmadd_ps(weight, column(&vals.pz_sq, j), square_z[r]);
            }
        }
        j += LANES;
    }
    let total = |v: __m256| {
        let mut lanes = [0f32; LANES];
        _mm256_storeu_ps(lanes.as_mut_ptr(), v);
        lanes.iter().sum::<f32>()
    };
    for r in 0..R {
        let sums = &mut sums[r];
        sums.irradiance[0] += total(irradiance_r[r]);
        sums.irradiance[1] += total(irradiance_g[r]);
        sums.irradiance[2] += total(irradiance_b[r]);
        sums.weight += total(weight_sum[r]);
        sums.weighted_position[0] += total(sum_x[r]);
        sums.weighted_position[1] += total(sum_y[r]);
        sums.weighted_position[2] += total(sum_z[r]);
        if SPREAD {
            sums.weighted_square[0] += total(square_x[r]);
            sums.weighted_square[1] += total(square_y[r]);
            sums.weighted_square[2] += total(square_z[r]);
        }
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
    visible: Option<&[u32]>,
    sums: &mut Sums,
) {
    for j in 0..vals.count {
        if visible.is_some_and(|row| !row_sees(row, vals.anchor[j])) {
            continue;
        }
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
