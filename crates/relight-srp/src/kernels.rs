//! The per-frame inner loops, kept small and branch-free so they vectorise:
//! probe projection (samples x SH basis), cluster projection (f16 rows dot
//! channel-major radiance) and reconstruction (blocks of eight receivers'
//! f16 weights times the light basis).

use crate::bake::BACK_FACE;
use half::f16;
#[cfg(target_arch = "x86_64")]
use relight_core::colour::pack_rgb9e5_x8;
use relight_core::{Rgb, Rgb9e5};

/// Samples per row of the probe-projection basis table: the sample count
/// rounded up to whole 8-lane vectors (the padding samples have zero basis).
pub fn basis_stride(samples: usize) -> usize {
    samples.div_ceil(8) * 8
}

/// lambda[channel][j] = sum over samples of radiance(sample) * basis[j][sample]
/// (the 4 pi / S weight is folded into the basis table, which is
/// coefficient-major with [`basis_stride`] samples a row). The probe's
/// sample radiance is first gathered into one contiguous row per channel,
/// so each coefficient is three 8-wide dot products over the samples
/// instead of a loop over `coefficients` per sample, which the compiler
/// could not vectorise for a run-time coefficient count.
pub fn project_probe(
    targets: &[u32],
    radiance: &[Rgb],
    basis: &[f32],
    coefficients: usize,
    gathered: &mut Vec<f32>,
    out: &mut [f32],
) {
    #[cfg(target_arch = "x86_64")]
    if wide_kernels_available() {
        // SAFETY: AVX2 and FMA were detected.
        return unsafe {
            project_probe_wide(targets, radiance, basis, coefficients, gathered, out)
        };
    }
    project_probe_body(targets, radiance, basis, coefficients, gathered, out)
}

/// The same with 8-wide AVX2 multiply-adds, one accumulator per channel
/// and one horizontal sum per coefficient and channel (left to itself, the
/// compiler interleaved the sums of eight coefficients with shuffles).
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2,fma")]
unsafe fn project_probe_wide(
    targets: &[u32],
    radiance: &[Rgb],
    basis: &[f32],
    coefficients: usize,
    gathered: &mut Vec<f32>,
    out: &mut [f32],
) {
    use std::arch::x86_64::*;
    let stride = gather_probe_radiance(targets, radiance, gathered);
    assert!(basis.len() >= coefficients * stride && out.len() >= 3 * coefficients);
    let light = gathered.as_ptr();
    for j in 0..coefficients {
        let row = basis.as_ptr().add(j * stride);
        let mut sums = [_mm256_setzero_ps(); 3];
        for start in (0..stride).step_by(8) {
            let basis_values = _mm256_loadu_ps(row.add(start));
            for (channel, sum) in sums.iter_mut().enumerate() {
                let values = _mm256_loadu_ps(light.add(channel * stride + start));
                *sum = _mm256_fmadd_ps(basis_values, values, *sum);
            }
        }
        for (channel, sum) in sums.into_iter().enumerate() {
            out[channel * coefficients + j] = sum8(sum);
        }
    }
}

/// Copies the probe's sample radiance into one row per channel of
/// `gathered` (zero where a sample hit nothing that shines), [`basis_stride`]
/// long each; returns the stride.
#[inline(always)]
fn gather_probe_radiance(targets: &[u32], radiance: &[Rgb], gathered: &mut Vec<f32>) -> usize {
    let stride = basis_stride(targets.len());
    gathered.clear();
    gathered.resize(3 * stride, 0.0);
    let (red, rest) = gathered.split_at_mut(stride);
    let (green, blue) = rest.split_at_mut(stride);
    for (sample, &target) in targets.iter().enumerate() {
        if target < BACK_FACE {
            let value = radiance[target as usize];
            red[sample] = value.x;
            green[sample] = value.y;
            blue[sample] = value.z;
        }
    }
    stride
}

fn project_probe_body(
    targets: &[u32],
    radiance: &[Rgb],
    basis: &[f32],
    coefficients: usize,
    gathered: &mut Vec<f32>,
    out: &mut [f32],
) {
    let stride = gather_probe_radiance(targets, radiance, gathered);
    let (red, rest) = gathered.split_at(stride);
    let (green, blue) = rest.split_at(stride);
    for (j, row) in basis.chunks_exact(stride).take(coefficients).enumerate() {
        let mut sums = [[0.0f32; 8]; 3];
        for (((row, red), green), blue) in row
            .chunks_exact(8)
            .zip(red.chunks_exact(8))
            .zip(green.chunks_exact(8))
            .zip(blue.chunks_exact(8))
        {
            for lane in 0..8 {
                sums[0][lane] += row[lane] * red[lane];
                sums[1][lane] += row[lane] * green[lane];
                sums[2][lane] += row[lane] * blue[lane];
            }
        }
        for (channel, lanes) in sums.iter().enumerate() {
            out[channel * coefficients + j] = lanes.iter().sum();
        }
    }
}

/// out[channel * rank + k] = row k of `matrix` (f16 bits, `width` long)
/// dot `gathered[channel * width ..]`.
pub fn project_cluster(
    matrix: &[u16],
    gathered: &[f32],
    width: usize,
    rank: usize,
    out: &mut [f32],
) {
    #[cfg(target_arch = "x86_64")]
    if wide_kernels_available() {
        for k in 0..rank {
            let row = &matrix[k * width..(k + 1) * width];
            // SAFETY: AVX2, FMA and F16C were detected above.
            let sums = unsafe { dot3_wide(row, gathered, width) };
            for channel in 0..3 {
                out[channel * rank + k] = sums[channel];
            }
        }
        return;
    }
    for k in 0..rank {
        let row = &matrix[k * width..(k + 1) * width];
        let sums = dot3_portable(row, gathered, width);
        for channel in 0..3 {
            out[channel * rank + k] = sums[channel];
        }
    }
}

/// Rows per reconstruction block. A block holds eight rows of one cluster
/// k-major (`weights[(block * rank + k) * BLOCK_ROWS + lane]`), so one
/// 8-wide multiply-add advances eight rows at once and no horizontal sums
/// are needed; rows past a cluster's end are zero.
pub const BLOCK_ROWS: usize = 8;

/// Irradiance of `out.len()` consecutive rows of one cluster, stored in
/// blocks of [`BLOCK_ROWS`] from the first block of `weights` on: row `i`'s
/// `rank` f16 weights dot the cluster's channel-major light basis
/// (`basis[channel * rank + k]`). Unless `packed` is empty, it also gets
/// every value as [`Rgb9e5`] (what a lightmap stores), packed eight at a
/// time while the block is still in registers.
pub fn reconstruct_blocks(
    weights: &[u16],
    basis: &[f32],
    rank: usize,
    out: &mut [Rgb],
    packed: &mut [Rgb9e5],
) {
    let blocks = out.len().div_ceil(BLOCK_ROWS);
    assert!(weights.len() >= blocks * rank * BLOCK_ROWS && basis.len() >= 3 * rank);
    assert!(packed.is_empty() || packed.len() == out.len());
    #[cfg(target_arch = "x86_64")]
    if wide_kernels_available() {
        // SAFETY: AVX2, FMA and F16C were detected; the lengths are checked
        // above.
        return unsafe { reconstruct_blocks_wide(weights, basis, rank, out, packed) };
    }
    reconstruct_blocks_portable(weights, basis, rank, out);
    for (packed, value) in packed.iter_mut().zip(out.iter()) {
        *packed = Rgb9e5::from_rgb(*value);
    }
}

pub fn reconstruct_blocks_portable(weights: &[u16], basis: &[f32], rank: usize, out: &mut [Rgb]) {
    for (block, rows) in out.chunks_mut(BLOCK_ROWS).enumerate() {
        let block_weights = &weights[block * rank * BLOCK_ROWS..(block + 1) * rank * BLOCK_ROWS];
        for (lane, value) in rows.iter_mut().enumerate() {
            let mut sums = [0.0f32; 3];
            for k in 0..rank {
                let weight = f16::from_bits(block_weights[k * BLOCK_ROWS + lane]).to_f32();
                for (channel, sum) in sums.iter_mut().enumerate() {
                    *sum += weight * basis[channel * rank + k];
                }
            }
            *value = Rgb::new(sums[0], sums[1], sums[2]);
        }
    }
}

/// Four partial sums per channel (twelve accumulators, k split four ways)
/// hide the multiply-add latency; the basis values are broadcast from
/// memory, so the accumulators and one converted weight vector are all the
/// registers the loop holds. A receiver is twelve multiply-adds and four
/// f16 conversions, with no shuffles: the compiler's version of the
/// four-receivers-by-three-channels kernel this replaces spilled an
/// accumulator through the stack every iteration.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2,fma,f16c")]
unsafe fn reconstruct_blocks_wide(
    weights: &[u16],
    basis: &[f32],
    rank: usize,
    out: &mut [Rgb],
    packed: &mut [Rgb9e5],
) {
    use std::arch::x86_64::*;
    let light = basis.as_ptr();
    let whole_k = rank / 4 * 4;
    for (block, rows) in out.chunks_mut(BLOCK_ROWS).enumerate() {
        let source = weights.as_ptr().add(block * rank * BLOCK_ROWS);
        let load = |k: usize| {
            _mm256_cvtph_ps(_mm_loadu_si128(source.add(k * BLOCK_ROWS) as *const __m128i))
        };
        let mut sums = [[_mm256_setzero_ps(); 3]; 4];
        let mut k = 0;
        while k < whole_k {
            for (part, partial) in sums.iter_mut().enumerate() {
                let values = load(k + part);
                for (channel, sum) in partial.iter_mut().enumerate() {
                    let factor = _mm256_broadcast_ss(&*light.add(channel * rank + k + part));
                    *sum = _mm256_fmadd_ps(values, factor, *sum);
                }
            }
            k += 4;
        }
        while k < rank {
            let values = load(k);
            for (channel, sum) in sums[0].iter_mut().enumerate() {
                let factor = _mm256_broadcast_ss(&*light.add(channel * rank + k));
                *sum = _mm256_fmadd_ps(values, factor, *sum);
            }
            k += 1;
        }
        let totals: [__m256; 3] = std::array::from_fn(|channel| {
            _mm256_add_ps(
                _mm256_add_ps(sums[0][channel], sums[1][channel]),
                _mm256_add_ps(sums[2][channel], sums[3][channel]),
            )
        });
        let mut channels = [[0.0f32; BLOCK_ROWS]; 3];
        for (lanes, total) in channels.iter_mut().zip(totals) {
            _mm256_storeu_ps(lanes.as_mut_ptr(), total);
        }
        for (lane, value) in rows.iter_mut().enumerate() {
            *value = Rgb::new(channels[0][lane], channels[1][lane], channels[2][lane]);
        }
        if !packed.is_empty() {
            let mut lanes = [Rgb9e5::default(); BLOCK_ROWS];
            let bits = pack_rgb9e5_x8(totals[0], totals[1], totals[2]);
            _mm256_storeu_si256(lanes.as_mut_ptr() as *mut __m256i, bits);
            let first = block * BLOCK_ROWS;
            packed[first..first + rows.len()].copy_from_slice(&lanes[..rows.len()]);
        }
    }
}

/// Horizontal sum of eight lanes.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
#[inline]
unsafe fn sum8(vector: std::arch::x86_64::__m256) -> f32 {
    use std::arch::x86_64::*;
    let quad = _mm_add_ps(
        _mm256_castps256_ps128(vector),
        _mm256_extractf128_ps(vector, 1),
    );
    let pair = _mm_add_ps(quad, _mm_movehl_ps(quad, quad));
    _mm_cvtss_f32(_mm_add_ss(pair, _mm_shuffle_ps(pair, pair, 1)))
}

pub fn dot3_portable(row: &[u16], gathered: &[f32], width: usize) -> [f32; 3] {
    // Eight partial sums per channel break the dependency chain.
    let mut partial = [[0.0f32; 8]; 3];
    let whole = width / 8 * 8;
    for start in (0..whole).step_by(8) {
        for lane in 0..8 {
            let value = f16::from_bits(row[start + lane]).to_f32();
            for (channel, sums) in partial.iter_mut().enumerate() {
                sums[lane] += value * gathered[channel * width + start + lane];
            }
        }
    }
    let mut sums = [0.0f32; 3];
    for (channel, sums_of_channel) in partial.iter().enumerate() {
        sums[channel] = sums_of_channel.iter().sum();
        for index in whole..width {
            sums[channel] +=
                f16::from_bits(row[index]).to_f32() * gathered[channel * width + index];
        }
    }
    sums
}

pub fn wide_kernels_available() -> bool {
    #[cfg(target_arch = "x86_64")]
    {
        static AVAILABLE: std::sync::OnceLock<bool> = std::sync::OnceLock::new();
        *AVAILABLE.get_or_init(|| {
            std::arch::is_x86_feature_detected!("avx2")
                && std::arch::is_x86_feature_detected!("fma")
                && std::arch::is_x86_feature_detected!("f16c")
        })
    }
    #[cfg(not(target_arch = "x86_64"))]
    {
        false
    }
}

/// The same three dot products with 8-wide f16 conversion and FMA: the
/// cluster projection streams every f16 of the projection matrices once per
/// frame, so this loop is the stage.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2,fma,f16c")]
pub unsafe fn dot3_wide(row: &[u16], gathered: &[f32], width: usize) -> [f32; 3] {
    use std::arch::x86_64::*;
    debug_assert!(row.len() >= width && gathered.len() >= 3 * width);
    let whole = width / 8 * 8;
    let mut red = _mm256_setzero_ps();
    let mut green = _mm256_setzero_ps();
    let mut blue = _mm256_setzero_ps();
    let source = row.as_ptr();
    let light = gathered.as_ptr();
    let mut index = 0;
    while index < whole {
        let values = _mm256_cvtph_ps(_mm_loadu_si128(source.add(index) as *const __m128i));
        red = _mm256_fmadd_ps(values, _mm256_loadu_ps(light.add(index)), red);
        green = _mm256_fmadd_ps(values, _mm256_loadu_ps(light.add(width + index)), green);
        blue = _mm256_fmadd_ps(values, _mm256_loadu_ps(light.add(2 * width + index)), blue);
        index += 8;
    }
    let mut sums = [sum8(red), sum8(green), sum8(blue)];
    for index in whole..width {
        let value = f16::from_bits(row[index]).to_f32();
        for (channel, sum) in sums.iter_mut().enumerate() {
            *sum += value * gathered[channel * width + index];
        }
    }
    sums
}

/// Lets parallel tasks write distinct elements of one slice.
pub struct DisjointWriter<T> {
    pointer: *mut T,
    length: usize,
}

// SAFETY: callers promise that no element is written by two tasks.
unsafe impl<T: Send> Send for DisjointWriter<T> {}
unsafe impl<T: Send> Sync for DisjointWriter<T> {}

impl<T> DisjointWriter<T> {
    pub fn new(slice: &mut [T]) -> Self {
        Self {
            pointer: slice.as_mut_ptr(),
            length: slice.len(),
        }
    }

    /// # Safety
    /// No other task may write or read `index` while the writer lives.
    #[inline]
    pub unsafe fn write(&self, index: usize, value: T) {
        assert!(index < self.length);
        self.pointer.add(index).write(value);
    }

    /// The elements `range` as a slice of their own.
    ///
    /// # Safety
    /// No other task may touch `range` while the slice lives.
    #[inline]
    #[allow(clippy::mut_from_ref)]
    pub unsafe fn slice(&self, range: std::ops::Range<usize>) -> &mut [T] {
        assert!(range.start <= range.end && range.end <= self.length);
        std::slice::from_raw_parts_mut(self.pointer.add(range.start), range.len())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use relight_core::SampleStream;

    #[test]
    fn blocked_reconstruction_matches_the_sum_per_row() {
        let mut rng = SampleStream::new(5, 0, 0);
        // Ranks below, at and past the four-way split, odd ones included;
        // row counts that leave partial blocks.
        for (rank, rows) in [
            (1usize, 1usize),
            (3, 7),
            (8, 8),
            (32, 9),
            (37, 64),
            (40, 13),
        ] {
            let blocks = rows.div_ceil(BLOCK_ROWS);
            let per_row: Vec<Vec<f32>> = (0..rows)
                .map(|_| (0..rank).map(|_| rng.next_f32() - 0.5).collect())
                .collect();
            // Padding rows hold NaN-free garbage that must not leak into
            // real rows.
            let mut weights = vec![f16::from_f32(0.25).to_bits(); blocks * rank * BLOCK_ROWS];
            for (row, values) in per_row.iter().enumerate() {
                let (block, lane) = (row / BLOCK_ROWS, row % BLOCK_ROWS);
                for (k, value) in values.iter().enumerate() {
                    weights[(block * rank + k) * BLOCK_ROWS + lane] =
                        f16::from_f32(*value).to_bits();
                }
            }
            let basis: Vec<f32> = (0..3 * rank).map(|_| rng.next_f32() * 4.0).collect();
            let mut dispatched = vec![Rgb::splat(f32::NAN); rows];
            let mut packed = vec![Rgb9e5(u32::MAX); rows];
            let mut portable = vec![Rgb::splat(f32::NAN); rows];
            reconstruct_blocks(&weights, &basis, rank, &mut dispatched, &mut packed);
            reconstruct_blocks_portable(&weights, &basis, rank, &mut portable);
            for (value, packed) in dispatched.iter().zip(&packed) {
                assert_eq!(*packed, Rgb9e5::from_rgb(*value));
            }
            for row in 0..rows {
                for channel in 0..3 {
                    let exact: f64 = (0..rank)
                        .map(|k| {
                            f16::from_f32(per_row[row][k]).to_f64()
                                * basis[channel * rank + k] as f64
                        })
                        .sum();
                    // At most 40 products below 2 in magnitude, summed in
                    // f32 in two different orders.
                    for value in [dispatched[row][channel], portable[row][channel]] {
                        assert!(
                            (value as f64 - exact).abs() < 1e-4,
                            "rank {rank}, row {row}, channel {channel}: {value} against {exact}"
                        );
                    }
                }
            }
        }
    }

    #[test]
    fn probe_projection_matches_the_sum_over_samples() {
        let mut rng = SampleStream::new(6, 0, 0);
        let radiance: Vec<Rgb> = (0..50)
            .map(|_| Rgb::new(rng.next_f32(), rng.next_f32(), rng.next_f32()))
            .collect();
        for (samples, coefficients) in [(5usize, 1usize), (64, 9), (77, 16), (256, 64)] {
            // A few samples see nothing that shines (back faces, escapes).
            let targets: Vec<u32> = (0..samples)
                .map(|sample| match sample % 11 {
                    3 => BACK_FACE,
                    7 => u32::MAX,
                    _ => (rng.next_f32() * radiance.len() as f32) as u32 % radiance.len() as u32,
                })
                .collect();
            let stride = basis_stride(samples);
            let mut basis = vec![0.0f32; coefficients * stride];
            for j in 0..coefficients {
                for sample in 0..samples {
                    basis[j * stride + sample] = rng.next_f32() - 0.5;
                }
            }
            let mut out = vec![f32::NAN; 3 * coefficients];
            let mut gathered = vec![f32::NAN; 3];
            project_probe(
                &targets,
                &radiance,
                &basis,
                coefficients,
                &mut gathered,
                &mut out,
            );
            let mut portable = vec![f32::NAN; 3 * coefficients];
            project_probe_body(
                &targets,
                &radiance,
                &basis,
                coefficients,
                &mut gathered,
                &mut portable,
            );
            for j in 0..coefficients {
                for channel in 0..3 {
                    let exact: f64 = targets
                        .iter()
                        .enumerate()
                        .filter(|(_, &target)| target < BACK_FACE)
                        .map(|(sample, &target)| {
                            basis[j * stride + sample] as f64
                                * radiance[target as usize][channel] as f64
                        })
                        .sum();
                    // Up to 256 terms below 0.5 in magnitude: a few f32
                    // roundings of the running sums.
                    for value in [
                        out[channel * coefficients + j],
                        portable[channel * coefficients + j],
                    ] {
                        assert!(
                            (value as f64 - exact).abs() < 1e-4,
                            "{samples} samples, coefficient {j}, channel {channel}: {value} against {exact}"
                        );
                    }
                }
            }
        }
    }

    #[test]
    fn wide_and_portable_cluster_dots_agree() {
        if !wide_kernels_available() {
            eprintln!("no AVX2/FMA/F16C here: only the portable kernel runs");
            return;
        }
        let mut rng = SampleStream::new(3, 0, 0);
        for width in [5usize, 64, 83, 1920] {
            let row: Vec<u16> = (0..width)
                .map(|_| f16::from_f32(rng.next_f32() - 0.5).to_bits())
                .collect();
            let gathered: Vec<f32> = (0..3 * width).map(|_| rng.next_f32()).collect();
            let portable = dot3_portable(&row, &gathered, width);
            #[cfg(target_arch = "x86_64")]
            {
                // SAFETY: checked above.
                let wide = unsafe { dot3_wide(&row, &gathered, width) };
                for channel in 0..3 {
                    let exact: f64 = (0..width)
                        .map(|i| {
                            f16::from_bits(row[i]).to_f64() * gathered[channel * width + i] as f64
                        })
                        .sum();
                    // Sums of up to 1920 terms below 0.5 in magnitude: a few
                    // f32 roundings of the running sums.
                    assert!((portable[channel] as f64 - exact).abs() < 1e-3, "{width}");
                    assert!((wide[channel] as f64 - exact).abs() < 1e-3, "{width}");
                }
            }
        }
    }
}
