//! The PRM bake: entry points, their clustering, light paths and panes.

use crate::panes::PanePoints;
use crate::PrmParams;
use glam::{Vec2, Vec3};
use half::f16;
use rayon::prelude::*;
use relight_core::sampling::{
    cosine_hemisphere_around, radical_inverse, uniform_triangle, SampleStream,
};
use relight_core::{luminance, Rgb};
use relight_scene::Scene;
use relight_technique::{
    join_parts, shards_disagree, BakeEstimate, BakePart, PayloadReader, PayloadWriter, Progress,
    SceneContext, Shard, TechniqueError,
};
use relight_trace::Ray;

/// Payload layout version; bump when the encoding changes.
const PAYLOAD_VERSION: u32 = 5;

/// Bytes of f16 RGB panes for `clusters` panes of `pane_points` values
/// (every receiver at `pane_resolution = 0`).
pub fn estimate_pane_bytes(clusters: u64, pane_points: u64) -> u64 {
    clusters * pane_points * 3 * 2
}

/// Basis panes the compression keeps; 0 = none.
fn compressed_rank(params: &PrmParams) -> u64 {
    if params.rank > 0 && params.rank < params.clusters {
        params.rank as u64
    } else {
        0
    }
}

/// The most the panes take during `shard`'s bake over `pane_points`
/// values: its f16 panes with one f32 pane per worker thread while they
/// are gathered, for a shard then its panes again as the encoded payload,
/// and for a whole bake every pane with the compression's f16 basis (with
/// a pane value at every texel, Sponza's 256 + 128 panes were 831 of the
/// 924 MiB the bake's process peaked at; at the default pane resolution
/// this counts 87 MiB against a measured peak of 188 MiB). A merge peaks
/// like a whole bake.
pub fn estimate_peak_bytes(params: &PrmParams, shard: Shard, pane_points: u64) -> u64 {
    let own = estimate_pane_bytes(
        shard.range(params.clusters as usize).len() as u64,
        pane_points,
    );
    let scratch = rayon::current_num_threads() as u64 * pane_points * 12;
    if shard == Shard::WHOLE {
        (own + scratch).max(estimate_pane_bytes(
            params.clusters as u64 + compressed_rank(params),
            pane_points,
        ))
    } else {
        (own + scratch).max(2 * own)
    }
}

/// Entry points whose light paths forecast a bake's rays: 256 of the
/// default 4096, a few milliseconds.
const PILOT_ENTRIES: usize = 256;

/// An odd multiplier near 2^32 / golden ratio: `k * PILOT_SPREAD mod n`
/// visits every low-bit pattern for a power-of-two `n`.
const PILOT_SPREAD: u64 = 2_654_435_761;

/// Every this-many-th facing pair of the pilot becomes a shadow ray that is
/// timed, up to `TIMED_RAYS` of them (a few tens of milliseconds).
const TIMED_EVERY: u64 = 4;
const TIMED_RAYS: usize = 1 << 18;

/// Pane points each pilot light is tested against for facing.
const PILOT_RECEIVERS: usize = 4096;

/// Forecasts `shard`'s bake without baking: the same entry points and light
/// paths as the bake for a sample of the entries give the lights per entry,
/// and a sample of receivers the share of them each light faces (only
/// those get a shadow ray); a sample of those shadow rays, traced and
/// timed, gives their rate.
pub fn estimate(
    context: &SceneContext,
    params: &PrmParams,
    shard: Shard,
) -> Result<BakeEstimate, TechniqueError> {
    // The bake chooses the same pane points first: the estimate times
    // that choice and counts it as the bake's fixed seconds.
    let selection_start = std::time::Instant::now();
    let pane_points = PanePoints::select(context, params.pane_spacing(&context.atlas));
    let selection_seconds = selection_start.elapsed().as_secs_f64();
    let targets = PaneTargets::new(context, &pane_points);
    let receiver_count = targets.positions.len();
    let entries = sample_entries(&context.scene, params.entries as usize)?;
    let epsilon = relight_trace::direct::ray_epsilon_for(&context.bvh);
    // Entries are a Halton sequence whose base-2 digits pick the triangle:
    // every 64th entry would all lie in the first 64th of the area, so the
    // pilot takes the entries an odd multiplier spreads over every residue.
    let pilot_count = PILOT_ENTRIES.min(params.entries as usize);
    let receiver_stride = (receiver_count / PILOT_RECEIVERS).max(1);
    let (mut pilots, mut lights, mut path_rays, mut pairs, mut facing) =
        (0u64, 0u64, 0u64, 0u64, 0u64);
    let mut sample_rays = Vec::new();
    for pilot in 0..pilot_count {
        let entry = (pilot as u64 * PILOT_SPREAD % params.entries as u64) as usize;
        let vertices = light_path_vertices(context, &entries, entry, params, epsilon);
        pilots += 1;
        lights += vertices.len() as u64;
        // One closest-hit ray leaves every vertex but the last of a path.
        path_rays += (vertices.len() as u64).max(1) - 1 + params.paths_per_entry as u64;
        for light in &vertices {
            for index in (0..receiver_count).step_by(receiver_stride) {
                let offset = light.position - targets.positions[index];
                pairs += 1;
                if targets.normals[index].dot(offset) > 0.0 && light.normal.dot(offset) < 0.0 {
                    facing += 1;
                    if facing % TIMED_EVERY == 0 && sample_rays.len() < TIMED_RAYS {
                        let origin = targets.positions[index] + targets.normals[index] * epsilon;
                        sample_rays.push(Ray {
                            origin,
                            direction: light.position + light.normal * epsilon - origin,
                            t_max: 1.0 - 1e-4,
                        });
                    }
                }
            }
        }
    }
    let own_share = shard.range(params.clusters as usize).len() as f64 / params.clusters as f64;
    let own_entries = params.entries as f64 * own_share;
    let lights_per_entry = lights as f64 / pilots.max(1) as f64;
    let facing_share = facing as f64 / pairs.max(1) as f64;
    let occlusion = own_entries * lights_per_entry * receiver_count as f64 * facing_share;
    let closest_hit = own_entries * path_rays as f64 / pilots.max(1) as f64;
    let panes = estimate_peak_bytes(params, shard, receiver_count as u64);
    // The bake's own shadow rays, receiver to light, cost what no generic
    // ray set does: short in a living room, long through Sponza's arcades.
    // The fastest of three passes: a pass takes a few tens of milliseconds,
    // which another process on a shared machine can double.
    let seconds = (0..3)
        .map(|_| {
            let start = std::time::Instant::now();
            let blocked = sample_rays
                .par_iter()
                .filter(|ray| context.bvh.occluded(ray))
                .count();
            std::hint::black_box(blocked);
            start.elapsed().as_secs_f64()
        })
        .fold(f64::INFINITY, f64::min);
    let occlusion_rate =
        (sample_rays.len() >= 1024 && seconds > 0.0).then(|| sample_rays.len() as f64 / seconds);
    Ok(BakeEstimate {
        occlusion_rate,
        rays: relight_trace::counters::RayCount {
            closest_hit: closest_hit as u64,
            occlusion: occlusion as u64,
        },
        // The bake's time over its rays' time at the sample's rate, with
        // pane points in Morton order: 0.81 on Sponza (0.69-0.86 for its
        // quarters), 0.74 on the living room, 0.99-1.17 on the atriums; the
        // middle of that range keeps every one within a quarter.
        time_per_ray_time: 0.92,
        fixed_seconds: selection_seconds,
        peak: vec![(
            format!(
                "panes ({} x {} pane points)",
                if shard == Shard::WHOLE {
                    params.clusters as u64 + compressed_rank(params)
                } else {
                    shard.range(params.clusters as usize).len() as u64
                },
                receiver_count
            ),
            panes,
        )],
        lower_memory_with: "--set clusters=N, --set rank=N, fewer pane points (--set pane_resolution=N, N under the lightmap's size), or --shard I/N on several machines".into(),
    })
}

/// Everything the run time needs.
#[derive(Clone, Debug, PartialEq)]
pub struct PrmBake {
    pub receiver_count: usize,
    /// Where the panes hold light (see [`crate::panes`]).
    pub pane_points: PanePoints,
    pub entry_positions: Vec<Vec3>,
    pub entry_normals: Vec<Vec3>,
    /// Cluster of each entry point.
    pub entry_clusters: Vec<u32>,
    /// Each entry point's share of its cluster's weight: its own pane's
    /// total luminance over the cluster pane's (equal shares where the pane
    /// is black); they sum to 1. The cluster's weight is its entries'
    /// irradiance averaged with these shares, which gives the cluster's
    /// total light exactly however unevenly its entries are lit. The plain
    /// mean (the paper's) gives every entry the same say, so a sunlit entry
    /// outside a wall, whose light escapes, lends its irradiance to the dim
    /// entries inside whose light the pane carries.
    pub entry_shares: Vec<f32>,
    pub cluster_count: usize,
    /// Principal components kept (0: the panes are stored as they are).
    pub rank: usize,
    /// With compression, `coefficients[cluster * rank + j]`: cluster pane ~
    /// sum_j coefficient x basis pane j.
    pub coefficients: Vec<f32>,
    /// Fraction of the panes' energy (squared norm) the basis keeps; 1
    /// without compression.
    pub captured_energy: f32,
    /// Pane-major: `panes[(pane * pane points + point) * 3 + channel]`.
    /// Without compression one pane per cluster, the indirect irradiance per
    /// unit irradiance at its entries; with compression the `rank` basis
    /// panes.
    pub panes: Vec<f16>,
}

/// A virtual point light on a light path.
#[derive(Clone, Copy)]
struct VirtualLight {
    position: Vec3,
    /// Normal on the side the light leaves from.
    normal: Vec3,
    /// Flux per unit entry irradiance.
    flux: Rgb,
}

/// One shard of a PRM bake: the entry points and their clusters, which
/// every shard computes alike, and the panes of the clusters
/// `first_cluster..first_cluster + cluster_panes` with their entries'
/// shares. Panes are the work that divides: each cluster's light paths
/// draw on its entries' own indices, so a pane is the same in any shard.
#[derive(Clone, Debug, PartialEq)]
pub struct PrmPart {
    pub receiver_count: usize,
    pub pane_points: PanePoints,
    pub cluster_count: usize,
    /// The `rank` parameter the merge compresses to.
    pub requested_rank: usize,
    pub entry_positions: Vec<Vec3>,
    pub entry_normals: Vec<Vec3>,
    pub entry_clusters: Vec<u32>,
    pub first_cluster: usize,
    /// Shares of each cluster's entries, cluster by cluster, entries in
    /// ascending order within each.
    pub shares: Vec<f32>,
    /// This part's clusters' panes, pane-major like [`PrmBake::panes`].
    pub panes: Vec<f16>,
}

/// Shard payloads carry their own version beside the bake's.
const PART_VERSION: u32 = 2;

impl PrmPart {
    /// Bakes the panes of `shard`'s clusters.
    pub fn build(
        context: &SceneContext,
        params: &PrmParams,
        shard: Shard,
        progress: &dyn Progress,
    ) -> Result<Self, TechniqueError> {
        let receiver_count = context.atlas.receivers.len();
        let own_clusters = shard.range(params.clusters as usize);
        let scene = &context.scene;
        progress.start("prm pane points", 1);
        let pane_points = PanePoints::select(context, params.pane_spacing(&context.atlas));
        let targets = PaneTargets::new(context, &pane_points);
        progress.finish();
        progress.start("prm entry points", 1);
        let entries = sample_entries(scene, params.entries as usize)?;
        // The content's diagonal: a ground plane far outside would shrink
        // every distance between entries in the clustering's metric.
        let (lo, hi) = scene.content_bounds();
        let diagonal = (hi - lo).length().max(1e-6);
        let entry_clusters = cluster_entries(
            &entries.positions,
            &entries.normals,
            params.clusters as usize,
            params.normal_weight,
            diagonal,
            params.seed,
        );
        progress.finish();

        // Members of each cluster, in entry order, for deterministic sums.
        let mut members: Vec<Vec<u32>> = vec![Vec::new(); params.clusters as usize];
        for (entry, &cluster) in entry_clusters.iter().enumerate() {
            members[cluster as usize].push(entry as u32);
        }
        let epsilon = relight_trace::direct::ray_epsilon_for(&context.bvh);
        progress.start("prm panes", own_clusters.len() as u64);
        let pane_length = targets.positions.len();
        let mut panes = vec![f16::ZERO; own_clusters.len() * pane_length * 3];
        // Each entry's share of its cluster's weight: the total luminance
        // of its own pane over the cluster pane's.
        let shares_per_cluster: Vec<Vec<f32>> = panes
            .par_chunks_mut(pane_length * 3)
            .zip(members[own_clusters.clone()].par_iter())
            .map(|(pane_out, cluster_members)| {
                let mut pane = vec![Rgb::ZERO; pane_length];
                let mut own_totals: Vec<f64> = Vec::with_capacity(cluster_members.len());
                for &entry in cluster_members {
                    let lights =
                        light_path_vertices(context, &entries, entry as usize, params, epsilon);
                    let disc_radius_squared = entries.areas[entry as usize] / std::f32::consts::PI;
                    own_totals.push(
                        lights
                            .iter()
                            .map(|light| {
                                gather(
                                    context,
                                    &targets,
                                    light,
                                    disc_radius_squared,
                                    epsilon,
                                    &mut pane,
                                )
                            })
                            .sum(),
                    );
                }
                for (out, value) in pane_out.chunks_exact_mut(3).zip(&pane) {
                    out[0] = f16::from_f32(value.x);
                    out[1] = f16::from_f32(value.y);
                    out[2] = f16::from_f32(value.z);
                }
                progress.advance(1);
                let total: f64 = own_totals.iter().sum();
                own_totals
                    .iter()
                    .map(|own| {
                        if total > 0.0 {
                            (own / total) as f32
                        } else {
                            1.0 / cluster_members.len() as f32
                        }
                    })
                    .collect()
            })
            .collect();
        progress.finish();
        drop(targets);
        Ok(Self {
            receiver_count,
            pane_points,
            cluster_count: params.clusters as usize,
            requested_rank: params.rank as usize,
            entry_positions: entries.positions,
            entry_normals: entries.normals,
            entry_clusters,
            first_cluster: own_clusters.start,
            shares: shares_per_cluster.into_iter().flatten().collect(),
            panes,
        })
    }

    /// Clusters whose panes this part holds.
    pub fn cluster_panes(&self) -> usize {
        self.panes.len() / (self.pane_length() * 3).max(1)
    }

    /// Values per pane.
    pub fn pane_length(&self) -> usize {
        self.pane_points.count(self.receiver_count)
    }

    pub fn encode(&self) -> Vec<u8> {
        let mut writer = PayloadWriter::with_capacity(self.panes.len() * 2 + 64);
        writer.u32(PART_VERSION);
        writer.u32(self.receiver_count as u32);
        writer.u32s(&self.pane_points.receivers);
        writer.f32(self.pane_points.spacing);
        writer.u32(self.cluster_count as u32);
        writer.u32(self.requested_rank as u32);
        writer.vectors(&self.entry_positions);
        writer.vectors(&self.entry_normals);
        writer.u32s(&self.entry_clusters);
        writer.u32(self.first_cluster as u32);
        writer.f32s(&self.shares);
        let bits: &[u16] = bytemuck::cast_slice(&self.panes);
        writer.halves(bits);
        writer.finish()
    }

    pub fn decode(bytes: &[u8]) -> Result<Self, TechniqueError> {
        let mut reader = PayloadReader::new(bytes, "prm");
        reader.version(
            PART_VERSION,
            "PRM shard",
            "bake the shards with this relight",
        )?;
        let receiver_count = reader.u32()? as usize;
        let pane_points = PanePoints {
            receivers: reader.u32s()?,
            spacing: reader.f32()?,
        };
        let cluster_count = reader.u32()? as usize;
        let requested_rank = reader.u32()? as usize;
        let entry_positions = reader.vectors()?;
        let entry_normals = reader.vectors()?;
        let entry_clusters = reader.u32s()?;
        let first_cluster = reader.u32()? as usize;
        let shares = reader.f32s()?;
        let panes: Vec<f16> = reader.halves()?.into_iter().map(f16::from_bits).collect();
        reader.end()?;
        let part = Self {
            receiver_count,
            pane_points,
            cluster_count,
            requested_rank,
            entry_positions,
            entry_normals,
            entry_clusters,
            first_cluster,
            shares,
            panes,
        };
        let entries = part.entry_positions.len();
        if part.entry_normals.len() != entries
            || part.entry_clusters.len() != entries
            || part
                .entry_clusters
                .iter()
                .any(|&cluster| cluster as usize >= cluster_count)
            || part.receiver_count == 0
            || !part.pane_points.is_valid(receiver_count)
            || !part.panes.len().is_multiple_of(part.pane_length() * 3)
            || part.first_cluster + part.cluster_panes() > cluster_count
        {
            return Err(reader.corrupt("a shard's sizes disagree"));
        }
        Ok(part)
    }
}

impl BakePart for PrmPart {
    const TECHNIQUE: &'static str = "prm";

    fn is_first(&self) -> bool {
        self.first_cluster == 0
    }

    /// The same entry points for the same lightmap and compression.
    fn same_setup(&self, other: &Self) -> bool {
        self.receiver_count == other.receiver_count
            && self.pane_points == other.pane_points
            && self.cluster_count == other.cluster_count
            && self.requested_rank == other.requested_rank
            && self.entry_positions == other.entry_positions
            && self.entry_normals == other.entry_normals
            && self.entry_clusters == other.entry_clusters
    }

    fn append(&mut self, next: Self) -> Result<(), &'static str> {
        if next.first_cluster != self.first_cluster + self.cluster_panes() {
            return Err("do not follow each other");
        }
        self.panes.extend_from_slice(&next.panes);
        self.shares.extend_from_slice(&next.shares);
        Ok(())
    }
}

impl PrmBake {
    /// Bakes in one piece: the merge of the single shard 0/1.
    pub fn build(
        context: &SceneContext,
        params: &PrmParams,
        progress: &dyn Progress,
    ) -> Result<Self, TechniqueError> {
        let part = PrmPart::build(context, params, Shard::WHOLE, progress)?;
        Self::from_parts(std::iter::once(Ok(part)), progress)
    }

    /// Joins parts given in shard order, then compresses the panes.
    pub fn from_parts(
        parts: impl IntoIterator<Item = Result<PrmPart, TechniqueError>>,
        progress: &dyn Progress,
    ) -> Result<Self, TechniqueError> {
        let disagree = |message: &str| shards_disagree("prm", message);
        let PrmPart {
            receiver_count,
            pane_points,
            cluster_count,
            requested_rank,
            entry_positions,
            entry_normals,
            entry_clusters,
            shares,
            mut panes,
            ..
        } = join_parts(parts)?;
        let pane_length = pane_points.count(receiver_count);
        let expected = cluster_count
            .checked_mul(pane_length)
            .and_then(|values| values.checked_mul(3));
        if expected != Some(panes.len()) || shares.len() != entry_clusters.len() {
            return Err(disagree("leave clusters without panes"));
        }
        // Shares come cluster by cluster, each cluster's entries ascending.
        let mut entry_shares = vec![0.0f32; entry_clusters.len()];
        let mut order: Vec<u32> = (0..entry_clusters.len() as u32).collect();
        order.sort_by_key(|&entry| entry_clusters[entry as usize]);
        for (&entry, &share) in order.iter().zip(&shares) {
            entry_shares[entry as usize] = share;
        }

        let (rank, coefficients, captured_energy) =
            if requested_rank > 0 && requested_rank < cluster_count {
                progress.start("prm compression", 1);
                let components = relight_core::pca::principal_components(
                    &panes,
                    cluster_count,
                    pane_length * 3,
                    requested_rank,
                )
                .map_err(|error| TechniqueError::Other(format!("PRM pane compression: {error}")))?;
                progress.finish();
                panes = components.basis;
                (
                    components.rank,
                    components.coefficients,
                    components.captured as f32,
                )
            } else {
                (0, Vec::new(), 1.0)
            };
        Ok(Self {
            receiver_count,
            pane_points,
            entry_positions,
            entry_normals,
            entry_clusters,
            entry_shares,
            cluster_count,
            rank,
            coefficients,
            captured_energy,
            panes,
        })
    }

    /// Values per pane.
    pub fn pane_length(&self) -> usize {
        self.pane_points.count(self.receiver_count)
    }

    /// Entry points in each cluster.
    pub fn cluster_sizes(&self) -> Vec<u32> {
        let mut sizes = vec![0u32; self.cluster_count];
        for &cluster in &self.entry_clusters {
            sizes[cluster as usize] += 1;
        }
        sizes
    }

    /// The pane of one entry point at `position` with `normal`, `albedo`
    /// and represented `area`, with unit irradiance, from `paths` light
    /// paths: the indirect irradiance it causes at every receiver. The bake
    /// sums exactly these per cluster; exposed to test it against the path
    /// tracer.
    pub fn single_entry_pane(
        context: &SceneContext,
        position: Vec3,
        normal: Vec3,
        albedo: Rgb,
        area: f32,
        paths: u32,
        seed: u64,
    ) -> Vec<Rgb> {
        let entries = Entries {
            positions: vec![position],
            normals: vec![normal],
            albedos: vec![albedo],
            areas: vec![area],
        };
        let params = PrmParams {
            entries: 1,
            clusters: 1,
            paths_per_entry: paths,
            seed,
            ..PrmParams::default()
        };
        let epsilon = relight_trace::direct::ray_epsilon_for(&context.bvh);
        let lights = light_path_vertices(context, &entries, 0, &params, epsilon);
        let disc_radius_squared = area / std::f32::consts::PI;
        let receivers = context.atlas.receivers.len();
        let targets = PaneTargets::new(context, &PanePoints::every_receiver());
        // Gather per virtual light in parallel, then add in light order.
        let partial: Vec<Vec<Rgb>> = lights
            .par_iter()
            .map(|light| {
                let mut pane = vec![Rgb::ZERO; receivers];
                let _ = gather(
                    context,
                    &targets,
                    light,
                    disc_radius_squared,
                    epsilon,
                    &mut pane,
                );
                pane
            })
            .collect();
        let mut pane = vec![Rgb::ZERO; receivers];
        for contribution in partial {
            for (total, value) in pane.iter_mut().zip(contribution) {
                *total += value;
            }
        }
        pane
    }

    /// Little-endian payload for the bake file.
    pub fn encode(&self) -> Vec<u8> {
        let mut bytes =
            Vec::with_capacity(self.panes.len() * 2 + self.entry_positions.len() * 28 + 64);
        let put_u32 =
            |bytes: &mut Vec<u8>, value: u32| bytes.extend_from_slice(&value.to_le_bytes());
        put_u32(&mut bytes, PAYLOAD_VERSION);
        put_u32(&mut bytes, self.receiver_count as u32);
        put_u32(&mut bytes, self.pane_points.receivers.len() as u32);
        for &receiver in &self.pane_points.receivers {
            put_u32(&mut bytes, receiver);
        }
        bytes.extend_from_slice(&self.pane_points.spacing.to_le_bytes());
        put_u32(&mut bytes, self.entry_positions.len() as u32);
        put_u32(&mut bytes, self.cluster_count as u32);
        put_u32(&mut bytes, self.rank as u32);
        bytes.extend_from_slice(&self.captured_energy.to_le_bytes());
        let put_vectors = |bytes: &mut Vec<u8>, values: &[Vec3]| {
            for value in values {
                for component in value.to_array() {
                    bytes.extend_from_slice(&component.to_le_bytes());
                }
            }
        };
        put_vectors(&mut bytes, &self.entry_positions);
        put_vectors(&mut bytes, &self.entry_normals);
        for cluster in &self.entry_clusters {
            bytes.extend_from_slice(&cluster.to_le_bytes());
        }
        for share in &self.entry_shares {
            bytes.extend_from_slice(&share.to_le_bytes());
        }
        for value in &self.coefficients {
            bytes.extend_from_slice(&value.to_le_bytes());
        }
        for value in &self.panes {
            bytes.extend_from_slice(&value.to_bits().to_le_bytes());
        }
        bytes
    }

    pub fn decode(bytes: &[u8]) -> Result<Self, TechniqueError> {
        let mut reader = Reader { bytes, cursor: 0 };
        let version = reader.u32()?;
        if version != PAYLOAD_VERSION {
            return Err(corrupt(&format!(
                "PRM payload version {version}, this relight reads {PAYLOAD_VERSION}"
            )));
        }
        let receiver_count = reader.u32()? as usize;
        let point_count = reader.u32()? as usize;
        if point_count as u128 * 4 > (bytes.len() - reader.cursor) as u128 {
            return Err(corrupt("payload shorter than its pane points say"));
        }
        let pane_points = PanePoints {
            receivers: (0..point_count)
                .map(|_| reader.u32())
                .collect::<Result<Vec<_>, _>>()?,
            spacing: reader.f32()?,
        };
        if !pane_points.is_valid(receiver_count) {
            return Err(corrupt("pane points are not distinct receivers in order"));
        }
        let pane_length = pane_points.count(receiver_count);
        let entry_count = reader.u32()? as usize;
        let cluster_count = reader.u32()? as usize;
        let rank = reader.u32()? as usize;
        let captured_energy = reader.f32()?;
        if rank >= cluster_count && rank != 0 {
            return Err(corrupt("more basis panes than clusters"));
        }
        let stored_panes = if rank > 0 { rank } else { cluster_count };
        // Every size is checked against the bytes left before allocating.
        let pane_values = stored_panes
            .checked_mul(pane_length)
            .and_then(|count| count.checked_mul(3))
            .ok_or_else(|| corrupt("pane size overflows"))?;
        let needed = entry_count as u128 * (12 * 2 + 4 + 4)
            + cluster_count as u128 * rank as u128 * 4
            + pane_values as u128 * 2;
        if needed > (bytes.len() - reader.cursor) as u128 {
            return Err(corrupt("payload shorter than its sizes say"));
        }
        let entry_positions = reader.vectors(entry_count)?;
        let entry_normals = reader.vectors(entry_count)?;
        let entry_clusters = (0..entry_count)
            .map(|_| reader.u32())
            .collect::<Result<Vec<_>, _>>()?;
        if entry_clusters
            .iter()
            .any(|&cluster| cluster as usize >= cluster_count)
        {
            return Err(corrupt(
                "an entry point names a cluster that does not exist",
            ));
        }
        let entry_shares = (0..entry_count)
            .map(|_| reader.f32())
            .collect::<Result<Vec<_>, _>>()?;
        if entry_shares
            .iter()
            .any(|share| !(share.is_finite() && *share >= 0.0))
        {
            return Err(corrupt("an entry point's share is not a finite fraction"));
        }
        let coefficients = (0..cluster_count * rank)
            .map(|_| reader.f32())
            .collect::<Result<Vec<_>, _>>()?;
        if coefficients.iter().any(|value| !value.is_finite()) {
            return Err(corrupt("a compression coefficient is not finite"));
        }
        let panes = (0..pane_values)
            .map(|_| {
                reader
                    .take(2)
                    .map(|b| f16::from_bits(u16::from_le_bytes([b[0], b[1]])))
            })
            .collect::<Result<Vec<_>, _>>()?;
        if reader.cursor != bytes.len() {
            return Err(corrupt("trailing bytes after the panes"));
        }
        Ok(Self {
            receiver_count,
            pane_points,
            entry_positions,
            entry_normals,
            entry_clusters,
            entry_shares,
            cluster_count,
            rank,
            coefficients,
            captured_energy,
            panes,
        })
    }
}

fn corrupt(message: &str) -> TechniqueError {
    TechniqueError::Other(format!("PRM bake is corrupt: {message}; bake it again"))
}

struct Reader<'a> {
    bytes: &'a [u8],
    cursor: usize,
}

impl Reader<'_> {
    fn take(&mut self, count: usize) -> Result<&[u8], TechniqueError> {
        let slice = self
            .bytes
            .get(self.cursor..self.cursor + count)
            .ok_or_else(|| corrupt("truncated"))?;
        self.cursor += count;
        Ok(slice)
    }
    fn u32(&mut self) -> Result<u32, TechniqueError> {
        Ok(u32::from_le_bytes(
            self.take(4)?.try_into().expect("4 bytes"),
        ))
    }
    fn f32(&mut self) -> Result<f32, TechniqueError> {
        Ok(f32::from_le_bytes(
            self.take(4)?.try_into().expect("4 bytes"),
        ))
    }
    fn vectors(&mut self, count: usize) -> Result<Vec<Vec3>, TechniqueError> {
        (0..count)
            .map(|_| Ok(Vec3::new(self.f32()?, self.f32()?, self.f32()?)))
            .collect()
    }
}

/// Entry points in struct-of-arrays form.
pub(crate) struct Entries {
    pub positions: Vec<Vec3>,
    pub normals: Vec<Vec3>,
    pub albedos: Vec<Rgb>,
    /// The surface each entry stands for (m^2): its virtual light's flux
    /// per unit irradiance over its albedo, and its disc.
    pub areas: Vec<f32>,
}

/// Entry points distributed by area with the Halton sequence (bases 2 for
/// the triangle, 3 and 5 within it), so they cover surfaces evenly. Where
/// the lightmap coarsens outside the scene's detail region the area is
/// weighted by its density (`Scene::detail_weights`) and each entry there
/// stands for as much more surface: a ground plane far outside would
/// otherwise take nearly every entry (the classroom's took 98 %).
pub(crate) fn sample_entries(scene: &Scene, count: usize) -> Result<Entries, TechniqueError> {
    let mesh = &scene.mesh;
    let weights = scene.detail_weights();
    let areas = relight_scene::AreaTable::weighted(mesh, weights.as_deref());
    let running = areas.total();
    if running <= 0.0 {
        return Err(TechniqueError::Other(
            "the scene has no surface area to place PRM entry points on".into(),
        ));
    }
    let mut entries = Entries {
        positions: Vec::with_capacity(count),
        normals: Vec::with_capacity(count),
        albedos: Vec::with_capacity(count),
        areas: Vec::with_capacity(count),
    };
    let area_per_entry = running as f32 / count as f32;
    for index in 0..count as u64 {
        // Index 0 of Halton is the origin; start at 1.
        let triangle = areas.triangle_at(radical_inverse(2, index + 1) * running);
        let sample = Vec2::new(
            radical_inverse(3, index + 1) as f32,
            radical_inverse(5, index + 1) as f32,
        );
        let barycentric = uniform_triangle(sample);
        entries.positions.push(mesh.point_at(triangle, barycentric));
        entries.normals.push(mesh.geometric_normal(triangle));
        entries.albedos.push(scene.albedo_at(triangle, barycentric));
        entries.areas.push(match &weights {
            Some(weights) => area_per_entry / weights[triangle],
            None => area_per_entry,
        });
    }
    Ok(entries)
}

/// k-means over (position / diagonal, normal * weight), seeded by k-means++
/// (each seed drawn with probability proportional to its squared distance
/// from the seeds so far) and a fixed number of Lloyd iterations; a cluster
/// left empty restarts at the entry farthest from its centre. Ties go to the
/// lower index and the draws come from `seed`: deterministic.
///
/// Evenly spaced entries of the Halton order are not a usable seeding: every
/// 16th index shares its low bits, so its base-2 radical inverse (which picks
/// the triangle) falls in one sixteenth of the area, and most clusters came
/// out empty.
pub(crate) fn cluster_entries(
    positions: &[Vec3],
    normals: &[Vec3],
    clusters: usize,
    normal_weight: f32,
    diagonal: f32,
    seed: u64,
) -> Vec<u32> {
    let feature = |index: usize| (positions[index] / diagonal, normals[index] * normal_weight);
    let distance = |index: usize, centre: &(Vec3, Vec3)| {
        let (position, normal) = feature(index);
        position.distance_squared(centre.0) + normal.distance_squared(centre.1)
    };
    let count = positions.len();
    let mut rng = SampleStream::new(seed, u64::MAX, 0);
    let mut centres: Vec<(Vec3, Vec3)> = Vec::with_capacity(clusters);
    centres.push(feature(
        (rng.next_f32() as f64 * count as f64) as usize % count,
    ));
    let mut nearest: Vec<f32> = (0..count)
        .map(|index| distance(index, &centres[0]))
        .collect();
    while centres.len() < clusters {
        let total: f64 = nearest.iter().map(|&d| d as f64).sum();
        let chosen = if total > 0.0 {
            let target = rng.next_f32() as f64 * total;
            let mut running = 0.0f64;
            let mut chosen = count - 1;
            for (index, &d) in nearest.iter().enumerate() {
                running += d as f64;
                if running > target && d > 0.0 {
                    chosen = index;
                    break;
                }
            }
            chosen
        } else {
            // Fewer distinct entries than clusters: duplicates stay empty.
            centres.len() % count
        };
        let centre = feature(chosen);
        for (index, slot) in nearest.iter_mut().enumerate() {
            *slot = slot.min(distance(index, &centre));
        }
        centres.push(centre);
    }
    let mut assignment = vec![0u32; count];
    let mut distances = vec![0.0f32; count];
    for _ in 0..16 {
        let changed: usize = assignment
            .par_iter_mut()
            .zip(distances.par_iter_mut())
            .enumerate()
            .map(|(index, (slot, slot_distance))| {
                let mut best = (f32::INFINITY, 0u32);
                for (cluster, centre) in centres.iter().enumerate() {
                    let d = distance(index, centre);
                    if d < best.0 {
                        best = (d, cluster as u32);
                    }
                }
                let changed = (*slot != best.1) as usize;
                *slot = best.1;
                *slot_distance = best.0;
                changed
            })
            .sum();
        let mut sums = vec![(Vec3::ZERO, Vec3::ZERO, 0u32); clusters];
        for (index, &cluster) in assignment.iter().enumerate() {
            let (position, normal) = feature(index);
            let sum = &mut sums[cluster as usize];
            sum.0 += position;
            sum.1 += normal;
            sum.2 += 1;
        }
        let mut restarted = false;
        for (centre, sum) in centres.iter_mut().zip(&sums) {
            if sum.2 > 0 {
                *centre = (sum.0 / sum.2 as f32, sum.1 / sum.2 as f32);
            } else {
                // The worst-served entry becomes the empty cluster's centre.
                let (farthest, &worst) =
                    distances
                        .iter()
                        .enumerate()
                        .fold(
                            (0, &-1.0f32),
                            |best, item| if item.1 > best.1 { item } else { best },
                        );
                if worst > 0.0 {
                    *centre = feature(farthest);
                    distances[farthest] = 0.0;
                    restarted = true;
                }
            }
        }
        if changed == 0 && !restarted {
            break;
        }
    }
    assignment
}

/// Virtual lights of the light paths leaving one entry point with unit
/// irradiance (equations 1 to 3): the entry point itself reflects
/// albedo x area; each further vertex carries the flux on, with cosine
/// directions and Russian roulette by albedo luminance. Every path starts
/// at the entry point, so the entry's light is one virtual light with the
/// whole flux rather than one per path: each virtual light costs a shadow
/// ray to every receiver, and the copies would only repeat them.
fn light_path_vertices(
    context: &SceneContext,
    entries: &Entries,
    entry: usize,
    params: &PrmParams,
    epsilon: f32,
) -> Vec<VirtualLight> {
    let scene = &context.scene;
    let paths = params.paths_per_entry;
    let start = VirtualLight {
        position: entries.positions[entry],
        normal: entries.normals[entry],
        flux: entries.albedos[entry] * entries.areas[entry],
    };
    let mut lights = vec![start];
    for path in 0..paths {
        let mut rng = SampleStream::new(params.seed, entry as u64, path as u64);
        let mut current = VirtualLight {
            flux: start.flux / paths as f32,
            ..start
        };
        for bounce in 0..64 {
            let direction = cosine_hemisphere_around(current.normal, rng.next_vec2());
            let ray = Ray {
                origin: current.position + current.normal * epsilon,
                direction,
                t_max: f32::INFINITY,
            };
            let previous = std::mem::replace(
                &mut current,
                VirtualLight {
                    position: Vec3::ZERO,
                    normal: Vec3::ZERO,
                    flux: Rgb::ZERO,
                },
            );
            // The entry point's light is already in, once for all paths.
            if bounce > 0 {
                lights.push(previous);
            }
            let Some(hit) = context.bvh.intersect(&ray) else {
                break;
            };
            let triangle = hit.triangle as usize;
            let front = scene.mesh.geometric_normal(triangle);
            let albedo = scene.albedo_at(triangle, hit.barycentric);
            let survival = luminance(albedo).clamp(0.0, 1.0);
            let flux = previous.flux;
            if survival <= 0.0 || rng.next_f32() >= survival {
                break;
            }
            current = VirtualLight {
                position: scene.mesh.point_at(triangle, hit.barycentric),
                normal: if front.dot(direction) < 0.0 {
                    front
                } else {
                    -front
                },
                // All of the flux arrives (cosine sampling of a Lambertian
                // emitter), a fraction albedo / survival is reflected on.
                flux: flux * albedo / survival,
            };
        }
        if current.flux != Rgb::ZERO {
            lights.push(current);
        }
    }
    lights
}

/// Positions and normals of the pane points, contiguous for the gather,
/// and the order it visits them in.
struct PaneTargets<'a> {
    positions: std::borrow::Cow<'a, [Vec3]>,
    normals: std::borrow::Cow<'a, [Vec3]>,
    /// Morton order: consecutive shadow rays toward one light leave nearby
    /// points and share BVH nodes. Sparse pane points in atlas order jump
    /// between charts (Sponza: the panes' rays ran at half the scene's
    /// diffuse occlusion rate).
    order: Vec<u32>,
    /// Per pane point, the surface it stands for against a detail-region
    /// texel's, so that an entry's share of its cluster's light is a share
    /// of light over the surface: with every receiver a pane point, the
    /// finer texels of a lampshade would otherwise count its light up to
    /// 64 times over, and its entries' irradiance, hundreds of times the
    /// room's, would weight their whole cluster. Binned pane points stand
    /// for a bin each: 1.
    areas: Vec<f32>,
}

impl<'a> PaneTargets<'a> {
    fn new(context: &'a SceneContext, points: &PanePoints) -> Self {
        let receivers = &context.atlas.receivers;
        if points.is_every_receiver() {
            return Self {
                positions: (&receivers.positions[..]).into(),
                normals: (&receivers.normals[..]).into(),
                order: (0..receivers.len() as u32).collect(),
                areas: receivers
                    .triangles
                    .iter()
                    .map(|&triangle| context.atlas.texel_area_weight(triangle))
                    .collect(),
            };
        }
        let pick = |values: &[Vec3]| -> Vec<Vec3> {
            points
                .receivers
                .iter()
                .map(|&receiver| values[receiver as usize])
                .collect()
        };
        let positions = pick(&receivers.positions);
        Self {
            order: relight_trace::direct::morton_order(&positions),
            areas: vec![1.0; positions.len()],
            positions: positions.into(),
            normals: pick(&receivers.normals).into(),
        }
    }
}

/// Adds one virtual light's irradiance at every pane point (shadow rays),
/// with the disc guard: E = flux / pi * cos_l cos_x / (d^2 + r^2), and
/// returns the luminance it added over the surface (each pane point's
/// weighted by the area it stands for).
fn gather(
    context: &SceneContext,
    targets: &PaneTargets,
    light: &VirtualLight,
    disc_radius_squared: f32,
    epsilon: f32,
    pane: &mut [Rgb],
) -> f64 {
    let origin = light.position + light.normal * epsilon;
    let mut added = 0.0f64;
    for &index in &targets.order {
        let index = index as usize;
        let value = &mut pane[index];
        let position = targets.positions[index];
        let normal = targets.normals[index];
        let offset = origin - position;
        let distance_squared = offset.length_squared();
        let cosine_receiver = normal.dot(offset);
        let cosine_light = -light.normal.dot(offset);
        if cosine_receiver <= 0.0 || cosine_light <= 0.0 {
            continue;
        }
        let shadow = Ray {
            origin: position + normal * epsilon,
            direction: origin - (position + normal * epsilon),
            t_max: 1.0 - 1e-4,
        };
        if context.bvh.occluded(&shadow) {
            continue;
        }
        // cosines were not normalised: divide by d^2 once more.
        let geometry = cosine_receiver * cosine_light
            / (distance_squared * (distance_squared + disc_radius_squared));
        let contribution = light.flux * (geometry * std::f32::consts::FRAC_1_PI);
        *value += contribution;
        added += (luminance(contribution) * targets.areas[index]) as f64;
    }
    added
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A 120 m two-triangle ground under an open 6 x 3 x 8 m room, loaded
    /// from a file so that the ground is cut into rings of coarser texels.
    fn ground_and_room() -> Scene {
        relight_scene::generate::load_ground_and_room("").unwrap()
    }

    #[test]
    fn entries_follow_the_lightmaps_detail_and_stand_for_their_area() {
        let scene = ground_and_room();
        let region = scene.detail_region().expect("the ground reaches far out");
        let entries = sample_entries(&scene, 4096).unwrap();
        let near = entries
            .positions
            .iter()
            .filter(|p| region.gap(**p, **p) < region.margin)
            .count();
        // By area alone the room and its margin hold 1.1 % of the surface.
        assert!(near > 3600, "{near} of 4096 entries near the room");
        // Far entries stand for 16^k times the surface of near ones.
        let near_area = entries.areas[entries
            .positions
            .iter()
            .position(|p| region.gap(*p, *p) == 0.0)
            .unwrap()];
        let weights = scene.detail_weights().unwrap();
        let weighted_total =
            relight_scene::AreaTable::weighted(&scene.mesh, Some(&weights)).total();
        assert!((near_area - weighted_total as f32 / 4096.0).abs() < 1e-3 * near_area);
        let farthest = entries.areas.iter().copied().fold(0.0, f32::max);
        assert!(
            farthest >= 16.0 * near_area,
            "{farthest} against {near_area}"
        );

        // Without a detail region every entry stands for the same area.
        let mut uniform = scene.clone();
        uniform.lightmap_layout.detail = relight_scene::detail::LightmapDetail::Uniform;
        let entries = sample_entries(&uniform, 4096).unwrap();
        let each = uniform.mesh.total_area() as f32 / 4096.0;
        assert!(entries.areas.iter().all(|&area| area == each));
    }
}
