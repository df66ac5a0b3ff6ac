//! Transport coefficients (equation 4.12) per receiver, the AABB clusters
//! they are compressed in, and the compression itself (equations 4.14 and
//! 4.15).

use crate::probes::falloff_weight;
use glam::{Vec2, Vec3};
use relight_core::sampling::{
    cosine_hemisphere_around, stratification_offset, stratified_square, uniform_hemisphere_around,
    SampleStream,
};
use relight_core::sh;
use relight_technique::SceneContext;
use relight_trace::Ray;

/// What the transport of one receiver needs to know.
#[derive(Clone, Copy, Debug)]
pub struct TransportSettings {
    pub bands: usize,
    pub samples: u32,
    pub radius: f32,
    /// Ray origins jittered over the texel's footprint (the thesis) rather
    /// than its centre.
    pub texel_jitter: bool,
    pub seed: u64,
}

/// Work buffers reused across the receivers one thread handles, so the
/// per-sample loop allocates nothing.
pub struct TransportScratch {
    basis: Vec<f32>,
    weights: Vec<f32>,
    visible: Vec<bool>,
    directions: Vec<Vec3>,
    /// Samples folded into each probe's running means so far.
    folded: Vec<u32>,
}

impl TransportScratch {
    pub fn new(bands: usize) -> Self {
        Self {
            basis: vec![0.0; sh::coefficient_count(bands)],
            weights: Vec::new(),
            visible: Vec::new(),
            directions: Vec::new(),
            folded: Vec::new(),
        }
    }
}

/// A point on the receiver's texel: the receiver's position, or a
/// uniformly jittered point of its footprint clamped onto the receiver's
/// triangle (so that origins never leave the surface the texel stands for)
/// and seen from the receiver's position along the surface (so that they
/// stay on the visible part of the texel, which the receiver stands for:
/// a point behind a wall that cuts the texel would average darkness into
/// it).
fn texel_point(
    context: &SceneContext,
    receiver: usize,
    jitter: Option<Vec2>,
    epsilon: f32,
) -> Vec3 {
    let receivers = &context.atlas.receivers;
    let centre = receivers.positions[receiver];
    let Some(jitter) = jitter else {
        return centre;
    };
    let texel = receivers.texels[receiver];
    let triangle = receivers.triangles[receiver];
    let uv = Vec2::new(texel[0] as f32, texel[1] as f32) + jitter;
    let uvs = &context.atlas.triangle_uvs[triangle as usize];
    let (_, barycentric) = relight_scene::atlas::closest_barycentric(uvs, uv);
    let point = context.scene.mesh.point_at(triangle as usize, barycentric);
    let lift = receivers.normals[receiver] * epsilon;
    let along = Ray {
        origin: centre + lift,
        direction: point - centre,
        t_max: 1.0,
    };
    if context.bvh.occluded(&along) {
        centre
    } else {
        point
    }
}

/// What one primary sample of a receiver gives the probes.
enum SampleKernel {
    /// The ray leaves the scene. Light arriving from the environment is
    /// direct light in relight (the direct-light service gives it to every
    /// receiver), so this direction carries no indirect light at all: a
    /// valid sample whose kernel is zero for every probe. The thesis instead
    /// asks probes whether they too see the environment, and drops the
    /// sample when none does; at openings, where probes deeper inside see
    /// walls in that direction, that hands the room's light to directions
    /// that are dark.
    Escaped,
    /// No probe can stand in for the surface the ray hits.
    Invalid,
    /// `scratch.visible` and `scratch.directions` name the probes that see
    /// the hit point; the value is the sum of their weights.
    Valid(f32),
}

/// Traces `primary` and asks each nearby probe whether it can stand in for
/// the point hit, with the two validity checks of section 5.6.4 and the
/// parallax-corrected direction of equation 4.5.
fn probe_kernels(
    context: &SceneContext,
    probes: &[Vec3],
    nearby: &[u32],
    primary: &Ray,
    epsilon: f32,
    scratch: &mut TransportScratch,
) -> SampleKernel {
    let Some(hit) = context.bvh.intersect(primary) else {
        return SampleKernel::Escaped;
    };
    let triangle = hit.triangle as usize;
    let surface_normal = context.scene.mesh.geometric_normal(triangle);
    // Check 2 of section 5.6.4: the receiver must see the front of the
    // surface it hits; otherwise no probe can stand in.
    if surface_normal.dot(primary.direction) >= 0.0 {
        return SampleKernel::Invalid;
    }
    let hit_point = context.scene.mesh.point_at(triangle, hit.barycentric);
    let lifted = hit_point + surface_normal * epsilon;
    let mut denominator = 0.0f32;
    for (slot, &probe) in nearby.iter().enumerate() {
        let probe = probes[probe as usize];
        // Check 1: the probe must be in front of the surface.
        let seen = (probe - hit_point).dot(surface_normal) > 0.0 && {
            let ray = Ray {
                origin: probe,
                direction: lifted - probe,
                t_max: 1.0,
            };
            !context.bvh.occluded(&ray)
        };
        scratch.visible[slot] = seen;
        if seen {
            scratch.directions[slot] = (hit_point - probe).normalize_or_zero();
            denominator += scratch.weights[slot];
        }
    }
    if denominator > 0.0 {
        SampleKernel::Valid(denominator)
    } else {
        SampleKernel::Invalid
    }
}

/// The probe weights of equation 4.4 for `receiver` and the per-probe
/// scratch sized for `nearby`.
fn prepare_scratch(
    probes: &[Vec3],
    centre: Vec3,
    nearby: &[u32],
    radius: f32,
    scratch: &mut TransportScratch,
) {
    scratch.weights.clear();
    scratch.weights.extend(
        nearby
            .iter()
            .map(|&probe| falloff_weight(probes[probe as usize].distance(centre) / radius)),
    );
    scratch.visible.clear();
    scratch.visible.resize(nearby.len(), false);
    scratch.directions.clear();
    scratch.directions.resize(nearby.len(), Vec3::ZERO);
    scratch.folded.clear();
    scratch.folded.resize(nearby.len(), 0);
}

/// The transport row of one receiver: `row[k * C + j]` = alpha for the k-th
/// of `nearby` probes and SH coefficient j (equation 4.12), estimated from
/// cosine-weighted samples (equation 5.6, with the factor pi kept so the
/// row maps probe radiance to irradiance). Returns the row and the number
/// of valid samples.
pub fn transport_row(
    context: &SceneContext,
    probes: &[Vec3],
    receiver: usize,
    nearby: &[u32],
    settings: &TransportSettings,
    scratch: &mut TransportScratch,
    row: &mut [f32],
) -> u32 {
    let receivers = &context.atlas.receivers;
    let coefficients = sh::coefficient_count(settings.bands);
    debug_assert_eq!(row.len(), nearby.len() * coefficients);
    row.fill(0.0);
    let normal = receivers.normals[receiver];
    let centre = receivers.positions[receiver];
    let epsilon = relight_trace::direct::ray_epsilon_for(&context.bvh);
    prepare_scratch(probes, centre, nearby, settings.radius, scratch);
    let offset = stratification_offset(settings.seed, receiver as u64);
    let mut valid = 0u32;
    for sample in 0..settings.samples {
        let mut rng = SampleStream::new(settings.seed, receiver as u64, sample as u64);
        let direction = cosine_hemisphere_around(
            normal,
            stratified_square(sample, settings.samples, offset, &mut rng),
        );
        let jitter = settings.texel_jitter.then(|| rng.next_vec2());
        let origin = texel_point(context, receiver, jitter, epsilon) + normal * epsilon;
        let primary = Ray {
            origin,
            direction,
            t_max: f32::INFINITY,
        };
        let denominator = match probe_kernels(context, probes, nearby, &primary, epsilon, scratch) {
            SampleKernel::Escaped => {
                valid += 1;
                continue;
            }
            // No probe sees what the receiver sees: excluded from the
            // normalisation (section 5.6.5).
            SampleKernel::Invalid => continue,
            SampleKernel::Valid(denominator) => denominator,
        };
        valid += 1;
        let inverse_count = 1.0 / valid as f32;
        for slot in 0..nearby.len() {
            if !scratch.visible[slot] {
                continue;
            }
            let kernel = scratch.weights[slot] / denominator;
            sh::evaluate(scratch.directions[slot], settings.bands, &mut scratch.basis);
            // Welford's running mean, with the zero samples this probe
            // missed since its last update folded in lazily: the mean over
            // `folded` samples becomes the mean over valid - 1 by scaling.
            let previous = scratch.folded[slot];
            let rescale = if valid > 1 {
                previous as f32 / (valid - 1) as f32
            } else {
                0.0
            };
            let means = &mut row[slot * coefficients..(slot + 1) * coefficients];
            for (mean, basis) in means.iter_mut().zip(&scratch.basis) {
                let scaled = *mean * rescale;
                *mean = scaled + (kernel * basis - scaled) * inverse_count;
            }
            scratch.folded[slot] = valid;
        }
    }
    if valid > 0 {
        for slot in 0..nearby.len() {
            let scale = std::f32::consts::PI * scratch.folded[slot] as f32 / valid as f32;
            for mean in &mut row[slot * coefficients..(slot + 1) * coefficients] {
                *mean *= scale;
            }
        }
    }
    valid
}

/// The radiance transport of one receiver (the original paper's glossy
/// extension): `rows[m * W + k * C + j]`, W = `nearby.len()` x C, maps
/// coefficient j of the k-th nearby probe to coefficient m (of
/// `output_bands`) of the incident radiance at the receiver, in world
/// space: the integral of Y_m(omega) times the probe-interpolated radiance
/// arriving from omega, with the same probe kernels as `transport_row`.
/// Uniform hemisphere samples (pdf 1 / 2 pi), because the cosine-weighted
/// ones of the irradiance would divide by the cosine here, an estimator of
/// unbounded variance at grazing directions. Returns the valid samples.
#[allow(clippy::too_many_arguments)]
pub fn radiance_rows(
    context: &SceneContext,
    probes: &[Vec3],
    receiver: usize,
    nearby: &[u32],
    settings: &TransportSettings,
    output_bands: usize,
    scratch: &mut TransportScratch,
    rows: &mut [f32],
) -> u32 {
    let receivers = &context.atlas.receivers;
    let coefficients = sh::coefficient_count(settings.bands);
    let outputs = sh::coefficient_count(output_bands);
    let width = nearby.len() * coefficients;
    debug_assert_eq!(rows.len(), outputs * width);
    rows.fill(0.0);
    let normal = receivers.normals[receiver];
    let centre = receivers.positions[receiver];
    let epsilon = relight_trace::direct::ray_epsilon_for(&context.bvh);
    prepare_scratch(probes, centre, nearby, settings.radius, scratch);
    // A stream apart from the irradiance rows' so the two estimates are
    // independent.
    let stream = receiver as u64 | (1 << 40);
    let offset = stratification_offset(settings.seed, stream);
    let mut output_basis = [0.0f32; sh::MAX_BANDS * sh::MAX_BANDS];
    let mut valid = 0u32;
    for sample in 0..settings.samples {
        let mut rng = SampleStream::new(settings.seed, stream, sample as u64);
        let direction = uniform_hemisphere_around(
            normal,
            stratified_square(sample, settings.samples, offset, &mut rng),
        );
        let primary = Ray {
            origin: centre + normal * epsilon,
            direction,
            t_max: f32::INFINITY,
        };
        let denominator = match probe_kernels(context, probes, nearby, &primary, epsilon, scratch) {
            SampleKernel::Escaped => {
                valid += 1;
                continue;
            }
            SampleKernel::Invalid => continue,
            SampleKernel::Valid(denominator) => denominator,
        };
        valid += 1;
        sh::evaluate(direction, output_bands, &mut output_basis[..outputs]);
        for slot in 0..nearby.len() {
            if !scratch.visible[slot] {
                continue;
            }
            let kernel = scratch.weights[slot] / denominator;
            sh::evaluate(scratch.directions[slot], settings.bands, &mut scratch.basis);
            for (m, &outgoing) in output_basis[..outputs].iter().enumerate() {
                let scale = kernel * outgoing;
                let target = &mut rows[m * width + slot * coefficients..][..coefficients];
                for (value, basis) in target.iter_mut().zip(&scratch.basis) {
                    *value += scale * basis;
                }
            }
        }
    }
    if valid > 0 {
        let scale = 2.0 * std::f32::consts::PI / valid as f32;
        for value in rows.iter_mut() {
            *value *= scale;
        }
    }
    valid
}

/// Splits receiver indices into clusters of at most `max_size` by halving
/// the bounding box across its longest axis (section 5.6.6). When the
/// midpoint leaves one side empty (coincident points) the split falls back
/// to the median.
pub fn aabb_clusters(positions: &[Vec3], max_size: usize) -> Vec<Vec<u32>> {
    let mut done = Vec::new();
    let mut pending = vec![(0..positions.len() as u32).collect::<Vec<u32>>()];
    while let Some(members) = pending.pop() {
        if members.len() <= max_size.max(1) {
            if !members.is_empty() {
                done.push(members);
            }
            continue;
        }
        let (low, high) = halve(members, |index| positions[index as usize]);
        // Pushed high first so clusters come out in ascending spatial order.
        pending.push(high);
        pending.push(low);
    }
    done
}

/// Splits two or more `members` in two across the longest axis of their
/// bounding box, at its middle, or at the median when the middle leaves
/// one side empty (coincident points); the low side first.
pub fn halve(members: Vec<u32>, position_of: impl Fn(u32) -> Vec3) -> (Vec<u32>, Vec<u32>) {
    let (lo, hi) = members.iter().fold(
        (Vec3::splat(f32::INFINITY), Vec3::splat(f32::NEG_INFINITY)),
        |(lo, hi), &index| {
            let position = position_of(index);
            (lo.min(position), hi.max(position))
        },
    );
    let extent = hi - lo;
    let axis = if extent.x >= extent.y && extent.x >= extent.z {
        0
    } else if extent.y >= extent.z {
        1
    } else {
        2
    };
    let middle = 0.5 * (lo[axis] + hi[axis]);
    let (low, high): (Vec<u32>, Vec<u32>) = members
        .iter()
        .partition(|&&index| position_of(index)[axis] < middle);
    if !low.is_empty() && !high.is_empty() {
        return (low, high);
    }
    let mut sorted = members;
    sorted.sort_by(|&a, &b| {
        position_of(a)[axis]
            .total_cmp(&position_of(b)[axis])
            .then(a.cmp(&b))
    });
    let high = sorted.split_off(sorted.len() / 2);
    (sorted, high)
}

/// A cluster's transport matrix compressed to `rank` principal vectors:
/// T (receivers x columns) ~ reconstruction (receivers x rank) x projection
/// (rank x columns).
pub struct Compressed {
    pub rank: usize,
    pub reconstruction: Vec<f32>,
    pub projection: Vec<f32>,
}

/// The best rank-`rank` approximation of the row-major `rows x columns`
/// matrix (equation 4.15): U_c is kept as the reconstruction matrix, Sigma_c
/// V^T as the projection matrix, from a randomised SVD (faer's products and
/// thin SVD). Sequential, so the result does not depend on the thread count.
pub fn compress(matrix: &[f32], rows: usize, columns: usize, rank: usize) -> Compressed {
    use faer::Mat;
    let rank = rank.min(rows).min(columns);
    let mut reconstruction = vec![0.0f32; rows * rank];
    let mut projection = vec![0.0f32; rank * columns];
    if rank == 0 {
        return Compressed {
            rank,
            reconstruction,
            projection,
        };
    }
    let dense = Mat::<f64>::from_fn(rows, columns, |row, column| {
        matrix[row * columns + column] as f64
    });
    // Small matrices take the full thin SVD; large ones the randomised one.
    let small = rows.min(columns) <= 2 * rank + 16;
    let partial = (!small).then(|| randomized_svd(&dense, rank)).flatten();
    let (left, values, right) = match partial {
        Some(triplets) => triplets,
        None => match thin_svd(&dense, rank) {
            Some(triplets) => triplets,
            // A matrix faer cannot decompose is all but impossible for
            // finite input; an empty basis keeps the bake going.
            None => {
                return Compressed {
                    rank,
                    reconstruction,
                    projection,
                }
            }
        },
    };
    for row in 0..rows {
        for k in 0..rank {
            reconstruction[row * rank + k] = left[(row, k)] as f32;
        }
    }
    for k in 0..rank {
        for column in 0..columns {
            projection[k * columns + column] = (values[k] * right[(column, k)]) as f32;
        }
    }
    Compressed {
        rank,
        reconstruction,
        projection,
    }
}

type Triplets = (faer::Mat<f64>, Vec<f64>, faer::Mat<f64>);

/// The leading `rank` triplets from the full thin SVD, run sequentially.
fn thin_svd(dense: &faer::Mat<f64>, rank: usize) -> Option<Triplets> {
    use faer::diag::Diag;
    use faer::dyn_stack::{MemBuffer, MemStack};
    use faer::linalg::svd::{svd, svd_scratch, ComputeSvdVectors};
    use faer::{Mat, Par};
    let (rows, columns) = (dense.nrows(), dense.ncols());
    let size = rows.min(columns);
    let mut values = Diag::<f64>::zeros(size);
    let mut left = Mat::<f64>::zeros(rows, size);
    let mut right = Mat::<f64>::zeros(columns, size);
    let mut buffer = MemBuffer::new(svd_scratch::<f64>(
        rows,
        columns,
        ComputeSvdVectors::Thin,
        ComputeSvdVectors::Thin,
        Par::Seq,
        Default::default(),
    ));
    svd(
        dense.as_ref(),
        values.as_mut(),
        Some(left.as_mut()),
        Some(right.as_mut()),
        Par::Seq,
        MemStack::new(&mut buffer),
        Default::default(),
    )
    .ok()?;
    let left = Mat::<f64>::from_fn(rows, rank, |row, k| left[(row, k)]);
    let right = Mat::<f64>::from_fn(columns, rank, |column, k| right[(column, k)]);
    let values = (0..rank).map(|k| values[k]).collect();
    Some((left, values, right))
}

/// Randomised SVD (Halko, Martinsson and Tropp 2011): the range of the
/// matrix is found from its product with `rank + 8` fixed pseudo-random
/// vectors, sharpened by two power iterations, and the small projected
/// matrix is decomposed exactly. Cost is a few matrix products, predictable
/// and sequential (deterministic), where Krylov methods can stall on the
/// rank-deficient transport matrices of clusters whose receivers see the
/// same probes.
fn randomized_svd(dense: &faer::Mat<f64>, rank: usize) -> Option<Triplets> {
    use faer::linalg::matmul::matmul;
    use faer::{Accum, Mat, Par};
    use relight_core::sampling::Pcg32;
    let (rows, columns) = (dense.nrows(), dense.ncols());
    let width = (rank + 8).min(rows).min(columns);
    let mut rng = Pcg32::new(0x5e_ed, rows as u64 * 65_537 + columns as u64);
    let test = Mat::<f64>::from_fn(columns, width, |_, _| rng.next_f32() as f64 - 0.5);
    let mut range = Mat::<f64>::zeros(rows, width);
    matmul(
        range.as_mut(),
        Accum::Replace,
        dense.as_ref(),
        test.as_ref(),
        1.0,
        Par::Seq,
    );
    orthonormalise(&mut range);
    let mut back = Mat::<f64>::zeros(columns, width);
    for _ in 0..2 {
        matmul(
            back.as_mut(),
            Accum::Replace,
            dense.transpose(),
            range.as_ref(),
            1.0,
            Par::Seq,
        );
        orthonormalise(&mut back);
        matmul(
            range.as_mut(),
            Accum::Replace,
            dense.as_ref(),
            back.as_ref(),
            1.0,
            Par::Seq,
        );
        orthonormalise(&mut range);
    }
    // B = Q^T A (width x columns), decomposed exactly.
    let mut small = Mat::<f64>::zeros(width, columns);
    matmul(
        small.as_mut(),
        Accum::Replace,
        range.transpose(),
        dense.as_ref(),
        1.0,
        Par::Seq,
    );
    let (small_left, values, right) = thin_svd(&small, rank.min(width))?;
    let mut left = Mat::<f64>::zeros(rows, small_left.ncols());
    matmul(
        left.as_mut(),
        Accum::Replace,
        range.as_ref(),
        small_left.as_ref(),
        1.0,
        Par::Seq,
    );
    Some((left, values, right))
}

/// Modified Gram-Schmidt, twice ("twice is enough"), on the columns; a
/// column that vanishes (rank deficiency) becomes zero rather than noise.
fn orthonormalise(matrix: &mut faer::Mat<f64>) {
    let (rows, columns) = (matrix.nrows(), matrix.ncols());
    for column in 0..columns {
        let original: f64 = (0..rows)
            .map(|row| matrix[(row, column)].powi(2))
            .sum::<f64>()
            .sqrt();
        for _ in 0..2 {
            for previous in 0..column {
                let dot: f64 = (0..rows)
                    .map(|row| matrix[(row, column)] * matrix[(row, previous)])
                    .sum();
                for row in 0..rows {
                    let value = matrix[(row, previous)];
                    matrix[(row, column)] -= dot * value;
                }
            }
        }
        let norm: f64 = (0..rows)
            .map(|row| matrix[(row, column)].powi(2))
            .sum::<f64>()
            .sqrt();
        let scale = if norm > 1e-12 * original.max(f64::MIN_POSITIVE) && norm > 0.0 {
            1.0 / norm
        } else {
            0.0
        };
        for row in 0..rows {
            matrix[(row, column)] *= scale;
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn clusters_respect_the_size_and_cover_everything() {
        let positions: Vec<Vec3> = (0..5000)
            .map(|i| Vec3::new((i % 100) as f32, (i / 100) as f32 * 0.3, 0.0))
            .collect();
        let clusters = aabb_clusters(&positions, 1024);
        assert!(clusters.iter().all(|cluster| cluster.len() <= 1024));
        let mut all: Vec<u32> = clusters.concat();
        all.sort_unstable();
        assert_eq!(all, (0..5000).collect::<Vec<u32>>());
        // Coincident points still split.
        let same = vec![Vec3::ONE; 3000];
        let clusters = aabb_clusters(&same, 1024);
        assert!(clusters.iter().all(|cluster| cluster.len() <= 1024));
        assert_eq!(clusters.concat().len(), 3000);
    }

    #[test]
    fn compression_of_a_low_rank_matrix_is_exact() {
        // A rank-3 matrix 200 x 90: three principal vectors reproduce it.
        let (rows, columns) = (200, 90);
        let matrix: Vec<f32> = (0..rows * columns)
            .map(|index| {
                let (row, column) = ((index / columns) as f32, (index % columns) as f32);
                (row * 0.01).sin() * (column * 0.1).cos()
                    + (row * 0.02 + 1.0) * 0.1 * column.sqrt()
                    + 0.3 * (row * 0.05).cos() * (column * 0.07).sin()
            })
            .collect();
        for rank in [3usize, 8, 40] {
            let compressed = compress(&matrix, rows, columns, rank);
            let mut error = 0.0f64;
            let mut norm = 0.0f64;
            for row in 0..rows {
                for column in 0..columns {
                    let rebuilt: f32 = (0..compressed.rank)
                        .map(|k| {
                            compressed.reconstruction[row * compressed.rank + k]
                                * compressed.projection[k * columns + column]
                        })
                        .sum();
                    let value = matrix[row * columns + column];
                    error += ((rebuilt - value) as f64).powi(2);
                    norm += (value as f64).powi(2);
                }
            }
            assert!(
                (error / norm).sqrt() < 1e-4,
                "rank {rank}: {}",
                (error / norm).sqrt()
            );
        }
    }
}
