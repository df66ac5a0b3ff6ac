//! Principal components of a few hundred long rows stored as f16 (transport
//! panes of hundreds of thousands of values each): the best rank-R
//! approximation in the least-squares sense, `row_k ~ sum_j coefficient_kj
//! basis_j`, without centring, so a set of positive rows keeps its mean
//! direction in the first component.
//!
//! The rows are too long for an SVD of the matrix itself, but there are few
//! of them, so relight forms their Gram matrix (rows x rows, in f64), takes
//! its leading eigenvectors with faer, and projects the rows onto them. Every
//! sum runs in an order fixed by the sizes alone, never by the thread count,
//! so the result is the same bytes on any number of threads.

use half::f16;
use half::slice::HalfFloatSliceExt;
use rayon::prelude::*;

/// Columns converted to f32 at a time: rows x BLOCK f32 stay in L2 for a few
/// hundred rows.
const BLOCK: usize = 1024;

/// A rank-R approximation of `rows` rows of `row_length` values.
#[derive(Clone, Debug, PartialEq)]
pub struct PrincipalComponents {
    pub rank: usize,
    /// `basis[j * row_length + column]`: basis row j, scaled by its singular
    /// value so its values have the magnitude of the input rows, in f16 as
    /// the rows are.
    pub basis: Vec<f16>,
    /// `coefficients[row * rank + j]`: row k ~ sum_j coefficients[k, j] basis_j.
    pub coefficients: Vec<f32>,
    /// Fraction of the rows' squared Frobenius norm the basis captures.
    pub captured: f64,
}

#[derive(Debug, thiserror::Error)]
pub enum PcaError {
    #[error("the eigendecomposition of the {rows} x {rows} Gram matrix did not converge")]
    NoConvergence { rows: usize },
}

/// Dot product in eight independent lanes, so it vectorises (a single running
/// sum would have to stay in order).
fn dot(a: &[f32], b: &[f32]) -> f32 {
    let mut lanes = [0.0f32; 8];
    let whole = a.len() / 8 * 8;
    for (x, y) in a[..whole].chunks_exact(8).zip(b[..whole].chunks_exact(8)) {
        for lane in 0..8 {
            lanes[lane] += x[lane] * y[lane];
        }
    }
    let tail: f32 = a[whole..].iter().zip(&b[whole..]).map(|(x, y)| x * y).sum();
    lanes.iter().sum::<f32>() + tail
}

/// Columns `start..end` of every row, converted to f32, row-major.
fn convert_block(
    rows: &[f16],
    row_count: usize,
    row_length: usize,
    start: usize,
    end: usize,
    out: &mut Vec<f32>,
) {
    let width = end - start;
    out.resize(row_count * width, 0.0);
    for row in 0..row_count {
        rows[row * row_length + start..row * row_length + end]
            .convert_to_f32_slice(&mut out[row * width..(row + 1) * width]);
    }
}

/// Lower triangle of the Gram matrix `rows x rows`, in f64. Blocks of columns
/// are split into a number of groups fixed by the sizes; each group sums its
/// blocks in order and the groups are added in order.
fn gram(rows: &[f16], row_count: usize, row_length: usize) -> Vec<f64> {
    assert_eq!(rows.len(), row_count * row_length);
    let blocks = row_length.div_ceil(BLOCK);
    // At most 16 partial matrices, and no more than 256 MiB of them.
    let matrix_bytes = (row_count * row_count * 8).max(1);
    let groups = (256 * 1024 * 1024 / matrix_bytes)
        .clamp(1, 16)
        .min(blocks.max(1));
    let blocks_per_group = blocks.div_ceil(groups).max(1);
    let partials: Vec<Vec<f64>> = (0..groups)
        .into_par_iter()
        .map(|group| {
            let mut partial = vec![0.0f64; row_count * row_count];
            let mut converted = Vec::new();
            let first = group * blocks_per_group;
            let last = ((group + 1) * blocks_per_group).min(blocks);
            for block in first..last {
                let start = block * BLOCK;
                let end = (start + BLOCK).min(row_length);
                let width = end - start;
                convert_block(rows, row_count, row_length, start, end, &mut converted);
                for i in 0..row_count {
                    let row_i = &converted[i * width..(i + 1) * width];
                    for j in 0..=i {
                        let row_j = &converted[j * width..(j + 1) * width];
                        partial[i * row_count + j] += dot(row_i, row_j) as f64;
                    }
                }
            }
            partial
        })
        .collect();
    let mut total = vec![0.0f64; row_count * row_count];
    for partial in &partials {
        for (sum, value) in total.iter_mut().zip(partial) {
            *sum += value;
        }
    }
    total
}

/// The best rank-`rank` approximation of the rows (`rank` is capped at the
/// row count).
pub fn principal_components(
    rows: &[f16],
    row_count: usize,
    row_length: usize,
    rank: usize,
) -> Result<PrincipalComponents, PcaError> {
    principal_components_weighted(rows, row_count, row_length, rank, None)
}

/// [`principal_components`] minimising the sum over rows of the squared
/// error times the row's weight squared (`row_weights`, positive and
/// finite; `None`: all 1): for rows that will be used at scales so
/// different that an error in one matters hundreds of times more than in
/// another, the weight being that scale. The components of the weighted
/// rows are found and each row's coefficients divided by its weight;
/// `captured` is the weighted energy's share. Weights at most 1 keep the
/// basis within the magnitude of the rows, as f16 needs.
pub fn principal_components_weighted(
    rows: &[f16],
    row_count: usize,
    row_length: usize,
    rank: usize,
    row_weights: Option<&[f64]>,
) -> Result<PrincipalComponents, PcaError> {
    use faer::diag::Diag;
    use faer::linalg::evd::{
        self_adjoint_evd, self_adjoint_evd_scratch, ComputeEigenvectors, SelfAdjointEvdParams,
    };
    use faer::{dyn_stack::MemBuffer, dyn_stack::MemStack, Mat, Par, Spec};

    let rank = rank.min(row_count);
    let mut lower = gram(rows, row_count, row_length);
    let weight = |row: usize| row_weights.map_or(1.0, |weights| weights[row]);
    if let Some(weights) = row_weights {
        assert_eq!(weights.len(), row_count);
        for i in 0..row_count {
            for j in 0..=i {
                lower[i * row_count + j] *= weights[i] * weights[j];
            }
        }
    }
    let matrix = Mat::<f64>::from_fn(row_count, row_count, |i, j| {
        lower[i.max(j) * row_count + i.min(j)]
    });
    let mut eigenvalues = Diag::<f64>::zeros(row_count);
    let mut eigenvectors = Mat::<f64>::zeros(row_count, row_count);
    // Sequential: faer's parallel path may sum in another order.
    let params: Spec<SelfAdjointEvdParams, f64> = Default::default();
    let mut buffer = MemBuffer::new(self_adjoint_evd_scratch::<f64>(
        row_count,
        ComputeEigenvectors::Yes,
        Par::Seq,
        params,
    ));
    self_adjoint_evd(
        matrix.as_ref(),
        eigenvalues.as_mut(),
        Some(eigenvectors.as_mut()),
        Par::Seq,
        MemStack::new(&mut buffer),
        params,
    )
    .map_err(|_| PcaError::NoConvergence { rows: row_count })?;

    // faer orders eigenvalues ascending; the components are the last ones.
    let trace: f64 = (0..row_count).map(|i| lower[i * row_count + i]).sum();
    // basis_j = sum_k V[k, j] weight_k row_k; row_k ~ sum_j (V[k, j] /
    // weight_k) basis_j.
    let mut basis_weights = vec![0.0f32; row_count * rank];
    let mut coefficients = vec![0.0f32; row_count * rank];
    let mut captured = 0.0;
    for j in 0..rank {
        let column = row_count - 1 - j;
        captured += eigenvalues[column].max(0.0);
        // A fixed sign (largest entry positive) so the basis does not depend
        // on the solver's choice.
        let mut largest = 0.0f64;
        for k in 0..row_count {
            let value = eigenvectors[(k, column)];
            if value.abs() > largest.abs() {
                largest = value;
            }
        }
        let sign = if largest < 0.0 { -1.0 } else { 1.0 };
        for k in 0..row_count {
            let value = sign * eigenvectors[(k, column)];
            basis_weights[k * rank + j] = (value * weight(k)) as f32;
            coefficients[k * rank + j] = if weight(k) > 0.0 {
                (value / weight(k)) as f32
            } else {
                0.0
            };
        }
    }
    let captured = if trace > 0.0 { captured / trace } else { 1.0 };

    // basis_j = sum_k V[k, j] row_k: sigma_j times the left singular vector.
    // Each block of columns is summed in f32 and written as f16 straight
    // into its place in every basis row. A full f32 basis and the blocks'
    // copies of it took twice the memory of 256 f16 rows at rank 128, the
    // bake's peak (PRM on a generated atrium: 547 -> 299 MB, the same
    // bytes out).
    let mut basis = vec![f16::ZERO; rank * row_length];
    let mut blocks_of_rows: Vec<Vec<&mut [f16]>> = (0..row_length.div_ceil(BLOCK))
        .map(|_| Vec::with_capacity(rank))
        .collect();
    for row in basis.chunks_mut(row_length.max(1)) {
        for (block, part) in row.chunks_mut(BLOCK).enumerate() {
            blocks_of_rows[block].push(part);
        }
    }
    blocks_of_rows
        .into_par_iter()
        .enumerate()
        .for_each(|(block, mut parts)| {
            let start = block * BLOCK;
            let end = (start + BLOCK).min(row_length);
            let width = end - start;
            let mut converted = Vec::new();
            convert_block(rows, row_count, row_length, start, end, &mut converted);
            let mut output = vec![0.0f32; rank * width];
            for k in 0..row_count {
                let row = &converted[k * width..(k + 1) * width];
                for j in 0..rank {
                    let weight = basis_weights[k * rank + j];
                    if weight == 0.0 {
                        continue;
                    }
                    for (out, &value) in output[j * width..(j + 1) * width].iter_mut().zip(row) {
                        *out += weight * value;
                    }
                }
            }
            for (j, part) in parts.iter_mut().enumerate() {
                part.convert_from_f32_slice(&output[j * width..(j + 1) * width]);
            }
        });
    Ok(PrincipalComponents {
        rank,
        basis,
        coefficients,
        captured,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::SampleStream;

    fn to_f16(values: &[f32]) -> Vec<f16> {
        values.iter().map(|&v| f16::from_f32(v)).collect()
    }

    /// Rows built from three known patterns are reproduced exactly (up to f16
    /// rounding of the input) by rank 3, and rank 3 captures all energy.
    #[test]
    fn rank_three_rows_are_reproduced_by_three_components() {
        let (row_count, row_length) = (40, 3000);
        let mut rng = SampleStream::new(7, 0, 0);
        let patterns: Vec<Vec<f32>> = (0..3)
            .map(|_| (0..row_length).map(|_| rng.next_f32()).collect())
            .collect();
        let mut values = Vec::new();
        for _ in 0..row_count {
            let weights = [rng.next_f32(), rng.next_f32() - 0.5, rng.next_f32() * 0.1];
            for column in 0..row_length {
                let combined: f32 = weights
                    .iter()
                    .zip(&patterns)
                    .map(|(weight, pattern)| weight * pattern[column])
                    .sum();
                values.push(combined);
            }
        }
        let rows = to_f16(&values);
        let components = principal_components(&rows, row_count, row_length, 3).unwrap();
        assert!(components.captured > 0.999_999, "{}", components.captured);
        let mut worst = 0.0f32;
        for k in 0..row_count {
            for column in 0..row_length {
                let approximation: f32 = (0..3)
                    .map(|j| {
                        components.coefficients[k * 3 + j]
                            * components.basis[j * row_length + column].to_f32()
                    })
                    .sum();
                worst = worst.max((approximation - values[k * row_length + column]).abs());
            }
        }
        // Against the exact rows: values are below 2, where f16 rounds by up
        // to 4.9e-4; the fit averages that rounding, so no element may be off
        // by more than 1e-3 (a missing pattern would be off by ~0.1).
        assert!(worst < 1e-3, "worst error {worst}");
    }

    /// The Gram matrix matches a direct f64 computation, and does not depend
    /// on the thread count.
    #[test]
    fn gram_matches_direct_sums_on_any_thread_count() {
        let (row_count, row_length) = (9, 5000);
        let mut rng = SampleStream::new(3, 0, 0);
        let rows = to_f16(
            &(0..row_count * row_length)
                .map(|_| rng.next_f32() - 0.3)
                .collect::<Vec<_>>(),
        );
        let on = |threads: usize| {
            rayon::ThreadPoolBuilder::new()
                .num_threads(threads)
                .build()
                .unwrap()
                .install(|| gram(&rows, row_count, row_length))
        };
        let one = on(1);
        assert_eq!(one, on(2));
        for i in 0..row_count {
            for j in 0..=i {
                let direct: f64 = (0..row_length)
                    .map(|c| rows[i * row_length + c].to_f64() * rows[j * row_length + c].to_f64())
                    .sum();
                assert!((one[i * row_count + j] - direct).abs() < 1e-6 * direct.abs().max(1.0));
            }
        }
    }

    /// Weights trade the rows' errors: two unrelated rows and rank 1 keep
    /// the row of the larger weight, whichever has more energy, and the
    /// coefficients still reproduce it at its own scale.
    #[test]
    fn weights_choose_which_rows_the_basis_keeps() {
        let length = 64;
        let mut rows = vec![0.0f32; 2 * length];
        for column in 0..length {
            rows[column] = if column < 32 { 1.0 } else { 0.0 };
            rows[length + column] = if column < 32 { 0.0 } else { 0.25 };
        }
        let rows = to_f16(&rows);
        let unweighted = principal_components(&rows, 2, length, 1).unwrap();
        assert!(unweighted.basis[0].to_f32().abs() > 0.5);
        let weighted =
            principal_components_weighted(&rows, 2, length, 1, Some(&[0.01, 1.0])).unwrap();
        let kept = |column: usize| weighted.coefficients[1] * weighted.basis[column].to_f32();
        assert!(kept(0).abs() < 1e-3, "{}", kept(0));
        assert!((kept(40) - 0.25).abs() < 1e-3, "{}", kept(40));
    }

    /// Truncation keeps the leading energy: a strong pattern plus weak noise
    /// gives a first component capturing nearly everything.
    #[test]
    fn leading_component_carries_the_dominant_pattern() {
        let (row_count, row_length) = (16, 2048);
        let mut rng = SampleStream::new(11, 0, 0);
        let pattern: Vec<f32> = (0..row_length)
            .map(|c| 1.0 + (c as f32 * 0.01).sin())
            .collect();
        let values: Vec<f32> = (0..row_count)
            .flat_map(|k| {
                let scale = 0.5 + k as f32 * 0.1;
                pattern
                    .iter()
                    .map(|&p| scale * p + 0.001 * (rng.next_f32() - 0.5))
                    .collect::<Vec<_>>()
            })
            .collect();
        let components = principal_components(&to_f16(&values), row_count, row_length, 1).unwrap();
        assert!(components.captured > 0.9999, "{}", components.captured);
        // The first basis row is the pattern (sign fixed positive).
        let ratio = components.basis[0].to_f32() / pattern[0];
        for c in (0..row_length).step_by(97) {
            assert!((components.basis[c].to_f32() / pattern[c] - ratio).abs() < 0.01 * ratio);
        }
    }
}
