//! The per-frame inner loops, kept small and branch-free so they vectorise:
//! probe projection (samples x SH basis), cluster projection (f16 rows dot
//! channel-major radiance) and reconstruction (f16 weights dot light basis).

use crate::bake::BACK_FACE;
use half::f16;
use relight_core::Rgb;

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

/// Irradiance of one receiver: its `rank` f16 weights dot the cluster's
/// channel-major light basis.
pub fn reconstruct_portable(weights: &[u16], basis: &[f32], rank: usize) -> Rgb {
    let mut sums = [0.0f32; 3];
    for (k, &bits) in weights[..rank].iter().enumerate() {
        let weight = f16::from_bits(bits).to_f32();
        sums[0] += weight * basis[k];
        sums[1] += weight * basis[rank + k];
        sums[2] += weight * basis[2 * rank + k];
    }
    Rgb::new(sums[0], sums[1], sums[2])
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2,fma,f16c")]
unsafe fn reconstruct_wide(weights: &[u16], basis: &[f32], rank: usize) -> Rgb {
    use std::arch::x86_64::*;
    debug_assert!(weights.len() >= rank && basis.len() >= 3 * rank && rank.is_multiple_of(8));
    let mut red = _mm256_setzero_ps();
    let mut green = _mm256_setzero_ps();
    let mut blue = _mm256_setzero_ps();
    let light = basis.as_ptr();
    let mut k = 0;
    while k < rank {
        let values = _mm256_cvtph_ps(_mm_loadu_si128(weights.as_ptr().add(k) as *const __m128i));
        red = _mm256_fmadd_ps(values, _mm256_loadu_ps(light.add(k)), red);
        green = _mm256_fmadd_ps(values, _mm256_loadu_ps(light.add(rank + k)), green);
        blue = _mm256_fmadd_ps(values, _mm256_loadu_ps(light.add(2 * rank + k)), blue);
        k += 8;
    }
    Rgb::new(sum8(red), sum8(green), sum8(blue))
}

/// Irradiance of consecutive receivers sharing one light basis: receiver
/// `i`'s `rank` weights are `weights[i * rank..]`, its value goes to
/// `out[i]`.
pub fn reconstruct_many(weights: &[u16], basis: &[f32], rank: usize, out: &mut [Rgb]) {
    assert!(weights.len() >= out.len() * rank && basis.len() >= 3 * rank);
    #[cfg(target_arch = "x86_64")]
    if rank.is_multiple_of(8) && wide_kernels_available() {
        // SAFETY: AVX2, FMA and F16C were detected; the lengths are checked
        // above and rank is a multiple of 8.
        return unsafe { reconstruct_many_wide(weights, basis, rank, out) };
    }
    for (index, value) in out.iter_mut().enumerate() {
        *value = reconstruct_portable(&weights[index * rank..], basis, rank);
    }
}

/// Four receivers at a time: twelve independent accumulator chains hide the
/// multiply-add latency that one receiver's three chains expose, and the
/// twelve horizontal sums share one transposing reduction whose three
/// vectors are the four receivers' RGB in memory order.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2,fma,f16c")]
unsafe fn reconstruct_many_wide(weights: &[u16], basis: &[f32], rank: usize, out: &mut [Rgb]) {
    use std::arch::x86_64::*;
    let light = basis.as_ptr();
    let whole = out.len() / 4 * 4;
    let mut receiver = 0;
    while receiver < whole {
        let row = weights.as_ptr().add(receiver * rank);
        let mut sums = [_mm256_setzero_ps(); 12];
        let mut k = 0;
        while k < rank {
            let red = _mm256_loadu_ps(light.add(k));
            let green = _mm256_loadu_ps(light.add(rank + k));
            let blue = _mm256_loadu_ps(light.add(2 * rank + k));
            for lane in 0..4 {
                let values =
                    _mm256_cvtph_ps(_mm_loadu_si128(row.add(lane * rank + k) as *const __m128i));
                sums[3 * lane] = _mm256_fmadd_ps(values, red, sums[3 * lane]);
                sums[3 * lane + 1] = _mm256_fmadd_ps(values, green, sums[3 * lane + 1]);
                sums[3 * lane + 2] = _mm256_fmadd_ps(values, blue, sums[3 * lane + 2]);
            }
            k += 8;
        }
        // Pairwise sums leave [s0 s1 s2 s3] of four accumulators in each
        // 128-bit half; adding the halves finishes them.
        let pairs = [
            _mm256_hadd_ps(sums[0], sums[1]),
            _mm256_hadd_ps(sums[2], sums[3]),
            _mm256_hadd_ps(sums[4], sums[5]),
            _mm256_hadd_ps(sums[6], sums[7]),
            _mm256_hadd_ps(sums[8], sums[9]),
            _mm256_hadd_ps(sums[10], sums[11]),
        ];
        let target = out.as_mut_ptr().add(receiver) as *mut f32;
        for quad in 0..3 {
            let partial = _mm256_hadd_ps(pairs[2 * quad], pairs[2 * quad + 1]);
            let total = _mm_add_ps(
                _mm256_castps256_ps128(partial),
                _mm256_extractf128_ps(partial, 1),
            );
            _mm_storeu_ps(target.add(4 * quad), total);
        }
        receiver += 4;
    }
    for index in whole..out.len() {
        out[index] = reconstruct_wide(&weights[index * rank..], basis, rank);
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

    /// # Safety
    /// No task may write `index` while the writer lives.
    #[inline]
    pub unsafe fn read(&self, index: usize) -> T
    where
        T: Copy,
    {
        assert!(index < self.length);
        self.pointer.add(index).read()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use relight_core::SampleStream;

    #[test]
    fn reconstruction_kernels_agree() {
        let mut rng = SampleStream::new(4, 0, 0);
        for rank in [8usize, 32, 40] {
            let weights: Vec<u16> = (0..rank)
                .map(|_| f16::from_f32(rng.next_f32() - 0.5).to_bits())
                .collect();
            let basis: Vec<f32> = (0..3 * rank).map(|_| rng.next_f32() * 4.0).collect();
            let portable = reconstruct_portable(&weights, &basis, rank);
            let mut dispatched = [Rgb::ZERO];
            reconstruct_many(&weights, &basis, rank, &mut dispatched);
            let dispatched = dispatched[0];
            for channel in 0..3 {
                let exact: f64 = (0..rank)
                    .map(|k| f16::from_bits(weights[k]).to_f64() * basis[channel * rank + k] as f64)
                    .sum();
                // At most 40 terms of magnitude below 2.
                assert!((portable[channel] as f64 - exact).abs() < 1e-4);
                assert!((dispatched[channel] as f64 - exact).abs() < 1e-4);
            }
        }
    }

    #[test]
    fn batched_reconstruction_matches_one_receiver_at_a_time() {
        let mut rng = SampleStream::new(5, 0, 0);
        for (rank, receivers) in [(8usize, 1usize), (32, 7), (40, 9), (32, 64)] {
            let weights: Vec<u16> = (0..rank * receivers)
                .map(|_| f16::from_f32(rng.next_f32() - 0.5).to_bits())
                .collect();
            let basis: Vec<f32> = (0..3 * rank).map(|_| rng.next_f32() * 4.0).collect();
            let mut batched = vec![Rgb::splat(f32::NAN); receivers];
            reconstruct_many(&weights, &basis, rank, &mut batched);
            for (index, value) in batched.iter().enumerate() {
                let single = reconstruct_portable(&weights[index * rank..], &basis, rank);
                // Same products summed in another order: at most 40 terms
                // below 2 in magnitude.
                assert!(
                    (*value - single).abs().max_element() < 1e-4,
                    "rank {rank}, receiver {index}: {value} against {single}"
                );
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
