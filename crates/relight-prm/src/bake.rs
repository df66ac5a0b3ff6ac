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
use relight_scene::atlas::Atlas;
use relight_scene::Scene;
use relight_technique::{
    join_parts, shards_disagree, BakeEstimate, BakePart, PayloadReader, PayloadWriter, Progress,
    SceneContext, Shard, TechniqueError,
};
use relight_trace::direct::{DirectLight, Footprints};
use relight_trace::Ray;

/// Payload layout version; bump when the encoding changes.
const PAYLOAD_VERSION: u32 = 6;

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
    let entries = sample_entries(context, params.entries as usize)?;
    let epsilon = relight_trace::direct::ray_epsilon_for(&context.bvh);
    // Entries are a Halton sequence whose base-2 digits pick the triangle:
    // every 64th entry would all lie in the first 64th of the area, so the
    // pilot takes the entries an odd multiplier spreads over every residue.
    let entry_count = entries.positions.len();
    let pilot_count = PILOT_ENTRIES.min(entry_count);
    let receiver_stride = (receiver_count / PILOT_RECEIVERS).max(1);
    let (mut pilots, mut lights, mut path_rays, mut pairs, mut facing) =
        (0u64, 0u64, 0u64, 0u64, 0u64);
    let mut sample_rays = Vec::new();
    for pilot in 0..pilot_count {
        let entry = (pilot as u64 * PILOT_SPREAD % entry_count as u64) as usize;
        let vertices = light_path_vertices(context, &entries, entry, params, epsilon);
        pilots += 1;
        lights += vertices.len() as u64;
        // One closest-hit ray leaves every vertex but the last of a path.
        path_rays += (vertices.len() as u64).max(1) - 1
            + params.paths_per_entry as u64 * entries.path_factors[entry] as u64;
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
    let own_entries = entry_count as f64 * own_share;
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
    /// The surface each entry point stands for (m^2): a frame averages a
    /// point light's irradiance over a patch this large around the entry.
    pub entry_areas: Vec<f32>,
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
    /// Fraction of the panes' energy (squared norm, each pane's weighted by
    /// its light under the scene file's lights, see `compression_weights`)
    /// the basis keeps; 1 without compression.
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
    pub entry_areas: Vec<f32>,
    /// Luminance of each entry's irradiance under the scene file's lights,
    /// averaged over its patch: what the merge weights each cluster's pane
    /// by in compression.
    pub entry_irradiance: Vec<f32>,
    pub entry_clusters: Vec<u32>,
    pub first_cluster: usize,
    /// Shares of each cluster's entries, cluster by cluster, entries in
    /// ascending order within each.
    pub shares: Vec<f32>,
    /// This part's clusters' panes, pane-major like [`PrmBake::panes`].
    pub panes: Vec<f16>,
}

/// Shard payloads carry their own version beside the bake's.
const PART_VERSION: u32 = 3;

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
        let entries = sample_entries(context, params.entries as usize)?;
        // The content's diagonal: a ground plane far outside would shrink
        // every distance between entries in the clustering's metric.
        let (lo, hi) = scene.content_bounds();
        let diagonal = (hi - lo).length().max(1e-6);
        // Segments between entries start and end this far off their
        // surfaces, so that two entries on one wall see each other past
        // the wall's own rounding, while a partition 1 cm thick or more
        // between them still blocks.
        let lift =
            (diagonal * 1e-3).max(relight_trace::direct::ray_epsilon_for(&context.bvh) * 4.0);
        // How far one entry may lie behind the other's plane: entries of
        // one flat wall lie in it, a column's within a few centimetres.
        let behind = 4.0 * lift;
        let alike = |a: usize, b: usize| {
            let (position_a, normal_a) = (entries.positions[a], entries.normals[a]);
            let (position_b, normal_b) = (entries.positions[b], entries.normals[b]);
            let offset = position_b - position_a;
            if normal_a.dot(offset) < -behind || normal_b.dot(-offset) < -behind {
                return false;
            }
            let from = position_a + normal_a * lift;
            let to = position_b + normal_b * lift;
            !context.bvh.occluded(&Ray {
                origin: from,
                direction: to - from,
                t_max: 1.0,
            })
        };
        let entry_flux = entries.flux();
        let levels = light_levels(
            &entries,
            params.clusters as usize,
            diagonal,
            params.irradiance_weight,
        );
        let entry_clusters = cluster_entries(
            &entries.positions,
            &entries.normals,
            params.clusters as usize,
            Metric {
                normal_weight: params.normal_weight,
                diagonal,
                light_levels: &levels,
            },
            params.seed,
            &entry_flux,
            alike,
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
            entry_areas: entries.areas,
            entry_irradiance: entries.irradiance,
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
        writer.f32s(&self.entry_areas);
        writer.f32s(&self.entry_irradiance);
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
        let entry_areas = reader.f32s()?;
        let entry_irradiance = reader.f32s()?;
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
            entry_areas,
            entry_irradiance,
            entry_clusters,
            first_cluster,
            shares,
            panes,
        };
        let entries = part.entry_positions.len();
        if part.entry_normals.len() != entries
            || part.entry_areas.len() != entries
            || !part
                .entry_areas
                .iter()
                .all(|area| area.is_finite() && *area >= 0.0)
            || part.entry_irradiance.len() != entries
            || !part
                .entry_irradiance
                .iter()
                .all(|value| value.is_finite() && *value >= 0.0)
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
            && self.entry_areas == other.entry_areas
            && self.entry_irradiance == other.entry_irradiance
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
            entry_areas,
            entry_irradiance,
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
                let weights = compression_weights(
                    cluster_count,
                    &entry_clusters,
                    &entry_shares,
                    &entry_irradiance,
                );
                let components = relight_core::pca::principal_components_weighted(
                    &panes,
                    cluster_count,
                    pane_length * 3,
                    requested_rank,
                    Some(&weights),
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
            entry_areas,
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
            path_factors: vec![1],
            irradiance: vec![0.0],
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
            Vec::with_capacity(self.panes.len() * 2 + self.entry_positions.len() * 36 + 64);
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
        for area in &self.entry_areas {
            bytes.extend_from_slice(&area.to_le_bytes());
        }
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
        let needed = entry_count as u128 * (12 * 2 + 4 + 4 + 4)
            + cluster_count as u128 * rank as u128 * 4
            + pane_values as u128 * 2;
        if needed > (bytes.len() - reader.cursor) as u128 {
            return Err(corrupt("payload shorter than its sizes say"));
        }
        let entry_positions = reader.vectors(entry_count)?;
        let entry_normals = reader.vectors(entry_count)?;
        let entry_areas = (0..entry_count)
            .map(|_| reader.f32())
            .collect::<Result<Vec<_>, _>>()?;
        if entry_areas
            .iter()
            .any(|area| !(area.is_finite() && *area >= 0.0))
        {
            return Err(corrupt("an entry point's area is not a finite size"));
        }
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
            entry_areas,
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

/// How much each cluster pane's errors count in compression: its weight
/// under the scene file's lights (its entries' irradiance averaged by
/// their shares, as a frame weighs it), raised to the clusters' mean where
/// it is lower, over the largest. Plain components spend themselves on
/// the panes of most energy, which are those of large dim clusters; a
/// cluster of a few entries beside a lamp holds a small pane that a frame
/// multiplies by hundreds, so its compression error became blotches over
/// the whole room, some negative (a generated suite with a lamp 10 cm from
/// a corner: 8x8 tiles 33 % with every pane kept, 83 % with 128 plain
/// components). The floor keeps the rest as they were: a light that moves
/// away from where the file put it still finds every cluster's pane.
fn compression_weights(
    cluster_count: usize,
    entry_clusters: &[u32],
    entry_shares: &[f32],
    entry_irradiance: &[f32],
) -> Vec<f64> {
    let mut weights = vec![0.0f64; cluster_count];
    for ((&cluster, &share), &irradiance) in entry_clusters
        .iter()
        .zip(entry_shares)
        .zip(entry_irradiance)
    {
        weights[cluster as usize] += share as f64 * irradiance as f64;
    }
    let mean = weights.iter().sum::<f64>() / cluster_count.max(1) as f64;
    if !(mean > 0.0 && mean.is_finite()) {
        return vec![1.0; cluster_count];
    }
    let raised: Vec<f64> = weights.iter().map(|&weight| weight.max(mean)).collect();
    let largest = raised.iter().copied().fold(0.0, f64::max);
    raised.iter().map(|&weight| weight / largest).collect()
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
#[derive(Default)]
pub(crate) struct Entries {
    pub positions: Vec<Vec3>,
    pub normals: Vec<Vec3>,
    pub albedos: Vec<Rgb>,
    /// The surface each entry stands for (m^2): its virtual light's flux
    /// per unit irradiance over its albedo, and its disc.
    pub areas: Vec<f32>,
    /// Each entry traces `paths_per_entry` times this many light paths:
    /// its flux under the scene file's lights over the mean entry's,
    /// rounded down, from 1 to [`MAX_PATH_FACTOR`].
    pub path_factors: Vec<u32>,
    /// Luminance of the irradiance under the scene file's lights, averaged
    /// over the entry's patch.
    pub irradiance: Vec<f32>,
}

/// The Halton point `index` (from 1) of an area table: base 2 picks the
/// triangle, bases 3 and 5 the point within it.
fn halton_point(table: &relight_scene::AreaTable, total: f64, index: u64) -> (usize, Vec2) {
    let triangle = table.triangle_at(radical_inverse(2, index) * total);
    let barycentric = uniform_triangle(Vec2::new(
        radical_inverse(3, index) as f32,
        radical_inverse(5, index) as f32,
    ));
    (triangle, barycentric)
}

impl Entries {
    /// Appends the entry at `barycentric` on `triangle`, standing for
    /// `area`.
    fn push(&mut self, scene: &Scene, triangle: usize, barycentric: Vec2, area: f32) {
        let mesh = &scene.mesh;
        self.positions.push(mesh.point_at(triangle, barycentric));
        self.normals.push(mesh.geometric_normal(triangle));
        self.albedos.push(scene.albedo_at(triangle, barycentric));
        self.areas.push(area);
    }

    /// The light falling on the surface the entries stand for, under the
    /// scene file's lights: irradiance times area, summed (luminance).
    fn irradiance_times_area(&self) -> f64 {
        self.irradiance
            .iter()
            .zip(&self.areas)
            .map(|(&irradiance, &area)| irradiance as f64 * area as f64)
            .sum()
    }

    /// Each entry's flux under the scene file's lights: irradiance times
    /// albedo and area (luminance).
    fn flux(&self) -> Vec<f32> {
        self.irradiance
            .iter()
            .zip(&self.albedos)
            .zip(&self.areas)
            .map(|((&irradiance, &albedo), &area)| irradiance * luminance(albedo) * area)
            .collect()
    }
}

/// The most paths an entry traces, in `paths_per_entry`s. Where a lamp
/// stands in a shade or beside a wall, a few entries beside it carry much
/// of the scene's light, and their few paths decide where it goes: on a
/// generated suite lit by a lamp in a shade, the unlit room's light over
/// four seeds was 0.70-1.53x of the path tracer's with 4 paths from every
/// entry, and 0.91-1.15x with 64 from those on the shade. Entries traced
/// in proportion to their flux under the scene file's lights spend the
/// paths where the light is; lights moved at run time keep the bake's
/// allocation, which is still unbiased, only noisier.
const MAX_PATH_FACTOR: u32 = 16;

/// Entry points distributed by area with the Halton sequence (bases 2 for
/// the triangle, 3 and 5 within it), so they cover surfaces evenly. Where
/// the lightmap's texels are larger or smaller than the detail region's
/// (coarser far outside it, finer on small charts near a light) the area
/// is weighted by its texel density and each entry there stands for as
/// much less or more surface: a ground plane far outside would otherwise
/// take nearly every entry (the classroom's took 98 %).
///
/// Up to [`NEAR_LIGHT_ENTRY_SHARE`] of the entries go to the surfaces that
/// face a point or spot light of the scene file within
/// [`NEAR_LIGHT_RADIUS_SPACINGS`] entry spacings of it (see
/// [`NearLights`]), the rest elsewhere.
pub(crate) fn sample_entries(
    context: &SceneContext,
    count: usize,
) -> Result<Entries, TechniqueError> {
    let scene = &context.scene;
    let mesh = &scene.mesh;
    let weights = entry_weights(scene, &context.atlas);
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
        path_factors: Vec::new(),
        irradiance: Vec::new(),
    };
    let spacing = (running as f32 / count as f32).sqrt();
    let mut near_lights = NearLights::new(scene, spacing);
    let near_budget = (count as f32 * NEAR_LIGHT_ENTRY_SHARE) as usize;
    let mut near = Entries::default();
    near_lights.sample(scene, near_budget, spacing, &mut near);
    // The rest of the surface takes the other entries: Halton draws over
    // all of it, skipping those the near-light entries cover, until there
    // are enough; each draw stands for an equal share of the weighted area.
    let base_count = count.saturating_sub(near.positions.len());
    let mut kept: Vec<(usize, Vec2)> = Vec::with_capacity(base_count);
    let mut draws = 0u64;
    while kept.len() < base_count && draws < MAX_DRAWS_PER_ENTRY * count as u64 {
        // Index 0 of Halton is the origin; start at 1.
        draws += 1;
        let (triangle, barycentric) = halton_point(&areas, running, draws);
        if near_lights
            .owner(triangle, mesh.point_at(triangle, barycentric))
            .is_none()
        {
            kept.push((triangle, barycentric));
        }
    }
    let area_per_entry = running as f32 / draws.max(1) as f32;
    for (triangle, barycentric) in kept {
        let area = match &weights {
            Some(weights) => area_per_entry / weights[triangle],
            None => area_per_entry,
        };
        entries.push(scene, triangle, barycentric, area);
    }
    entries.positions.append(&mut near.positions);
    entries.normals.append(&mut near.normals);
    entries.albedos.append(&mut near.albedos);
    entries.areas.append(&mut near.areas);
    entries.irradiance = irradiance_under_scene_lights(context, &entries);
    entries.path_factors = path_factors(&entries);
    Ok(entries)
}

/// Share of the entry points kept for the surfaces near the scene file's
/// point and spot lights. A light 10 cm from a corner puts most of the
/// walls' light within 30 cm of it, where entries spaced like the room's
/// (20-30 cm on generated rooms) fall few and by chance: over 4096
/// entries, the light they counted on such rooms was 0.85-1.05 of the
/// light's whole flux (4 pi I, every ray ending on a wall), and the unlit
/// room next door came out up to 0.7x as bright as the path tracer's.
const NEAR_LIGHT_ENTRY_SHARE: f32 = 1.0 / 8.0;

/// Halton draws per entry before the rest of the surface gives up: only a
/// scene lying almost wholly near its lights leaves fewer entries.
const MAX_DRAWS_PER_ENTRY: u64 = 64;

/// Radius of the region around a light whose facing surfaces get the
/// near-light entries, in the room's entry spacings: a light at a quarter
/// of it from a wall puts 84 % of that wall's light inside.
const NEAR_LIGHT_RADIUS_SPACINGS: f32 = 2.5;

/// Near-light entries are at most this many times as dense as the room's:
/// a light whose region holds only its shade does not spend the budget on
/// a few square decimetres.
const NEAR_LIGHT_MAX_DENSITY: f32 = 64.0;

/// Halton draws that estimate how much of a region's candidate triangles
/// lies inside it.
const NEAR_LIGHT_PILOT_DRAWS: u64 = 1024;

/// The regions near the scene file's point and spot lights: the points of
/// triangles that face the light within the radius. A point belongs to
/// the first light's region that holds it, so regions do not overlap.
struct NearLights {
    centres: Vec<Vec3>,
    radius: f32,
    /// Per region, the triangles facing its light whose bounds reach
    /// within the radius, ascending.
    candidates: Vec<Vec<u32>>,
}

impl NearLights {
    fn new(scene: &Scene, spacing: f32) -> Self {
        let centres: Vec<Vec3> = scene
            .lights
            .iter()
            .filter_map(relight_scene::Light::position)
            .collect();
        let radius = NEAR_LIGHT_RADIUS_SPACINGS * spacing;
        let mesh = &scene.mesh;
        let candidates = centres
            .iter()
            .map(|&centre| {
                (0..mesh.triangles.len() as u32)
                    .filter(|&triangle| {
                        let corners = mesh.vertices(triangle as usize);
                        let low = corners[0].min(corners[1]).min(corners[2]);
                        let high = corners[0].max(corners[1]).max(corners[2]);
                        centre.clamp(low, high).distance_squared(centre) < radius * radius
                            && mesh.faces_point(triangle as usize, centre)
                            && mesh.area(triangle as usize) > 0.0
                    })
                    .collect()
            })
            .collect();
        Self {
            centres,
            radius,
            candidates,
        }
    }

    /// The region `point` on `triangle` belongs to, if any.
    fn owner(&self, triangle: usize, point: Vec3) -> Option<usize> {
        (0..self.centres.len()).find(|&region| {
            point.distance_squared(self.centres[region]) < self.radius * self.radius
                && self.candidates[region]
                    .binary_search(&(triangle as u32))
                    .is_ok()
        })
    }

    /// Appends each region's entries to `near`: an equal share of `budget`
    /// per light, at most [`NEAR_LIGHT_MAX_DENSITY`] times the room's
    /// density, drawn by area over the region's triangles and kept where
    /// the region owns them, each standing for an equal part of the area.
    /// A region that gets no entries (more lights than the budget has
    /// entries for, or too little surface) is dropped, so that the rest of
    /// the surface's entries cover it and later regions may own what it
    /// overlapped.
    fn sample(&mut self, scene: &Scene, budget: usize, spacing: f32, near: &mut Entries) {
        let per_light = budget / self.centres.len().max(1);
        for region in 0..self.candidates.len() {
            let before = near.positions.len();
            self.sample_region(scene, region, per_light, spacing, near);
            if near.positions.len() == before {
                self.candidates[region].clear();
            }
        }
    }

    fn sample_region(
        &self,
        scene: &Scene,
        region: usize,
        per_light: usize,
        spacing: f32,
        near: &mut Entries,
    ) {
        let mesh = &scene.mesh;
        let candidates = &self.candidates[region];
        if candidates.is_empty() || per_light == 0 {
            return;
        }
        let mut weights = vec![0.0f32; mesh.triangles.len()];
        for &triangle in candidates {
            weights[triangle as usize] = 1.0;
        }
        let table = relight_scene::AreaTable::weighted(mesh, Some(&weights));
        let total = table.total();
        let draw = |index: u64| {
            let (triangle, barycentric) = halton_point(&table, total, index + 1);
            let inside = self.owner(triangle, mesh.point_at(triangle, barycentric)) == Some(region);
            (triangle, barycentric, inside)
        };
        let accepted = (0..NEAR_LIGHT_PILOT_DRAWS)
            .filter(|&index| draw(index).2)
            .count();
        if accepted == 0 {
            return;
        }
        let fraction = accepted as f64 / NEAR_LIGHT_PILOT_DRAWS as f64;
        let inside_area = total * fraction;
        let densest = NEAR_LIGHT_MAX_DENSITY as f64 * inside_area / (spacing * spacing) as f64;
        let wanted = (per_light as f64).min(densest);
        let draws = (wanted / fraction).round() as u64;
        if draws == 0 {
            return;
        }
        let area = (total / draws as f64) as f32;
        for index in 0..draws {
            let (triangle, barycentric, inside) = draw(index);
            if inside {
                near.push(scene, triangle, barycentric, area);
            }
        }
    }
}

/// [`Entries::irradiance`].
fn irradiance_under_scene_lights(context: &SceneContext, entries: &Entries) -> Vec<f32> {
    let direct = DirectLight::new(
        &context.scene,
        &context.bvh,
        &context.emitters,
        context.settings.direct,
    );
    let mut irradiance = vec![Rgb::ZERO; entries.positions.len()];
    direct.irradiance_batch_over_footprints(
        &context.scene.lights,
        &entries.positions,
        &entries.normals,
        Footprints::Each(&entries.areas),
        None,
        &mut irradiance,
    );
    // A non-finite value (a degenerate triangle's normal) counts as dark:
    // the bake file refuses non-finite irradiance.
    irradiance
        .into_iter()
        .map(|value| {
            Some(luminance(value))
                .filter(|value| value.is_finite() && *value >= 0.0)
                .unwrap_or(0.0)
        })
        .collect()
}

/// [`Entries::path_factors`]: each entry's flux (irradiance times albedo
/// and area) under the scene file's lights, over the mean entry's.
fn path_factors(entries: &Entries) -> Vec<u32> {
    let flux = entries.flux();
    let mean = flux.iter().map(|&flux| flux as f64).sum::<f64>() / flux.len().max(1) as f64;
    flux.iter()
        .map(|&flux| {
            if mean > 0.0 && flux.is_finite() {
                (flux as f64 / mean).clamp(1.0, MAX_PATH_FACTOR as f64) as u32
            } else {
                1
            }
        })
        .collect()
}

/// Entries per unit area on each triangle, relative to the detail
/// region's: the lightmap's own texel density, which coarsens outside the
/// detail region and refines on small charts near the scene's lights;
/// `None` where it is uniform. A large chart refined near a light (the
/// walls by a lamp in a corner) keeps the room's density: its light varies
/// fast only near the lamp, where the near-light entries are, and at its
/// texels' density the walls drew most of a room's entries (in a first
/// version, variant 85's entries, a lamp 10 cm from a corner, counted
/// 0.93 of its flux).
fn entry_weights(scene: &Scene, atlas: &Atlas) -> Option<Vec<f32>> {
    if atlas.triangle_texel_scales.is_empty() {
        return scene.detail_weights();
    }
    let weights: Vec<f32> = atlas
        .triangle_texel_scales
        .iter()
        .enumerate()
        .map(|(triangle, &scale)| {
            if scale < 1.0 && !atlas.in_small_near_light_chart(triangle as u32) {
                1.0
            } else {
                1.0 / (scale * scale)
            }
        })
        .collect();
    weights
        .iter()
        .any(|&weight| weight != 1.0)
        .then_some(weights)
}

/// Each entry's light level for the clustering, `log2(1 + E / mean E)`
/// with E its irradiance under the scene file's lights and the mean over
/// the surface, in units of `weight` typical cluster spacings (the
/// metric's: positions over the diagonal); empty where `weight` is 0 or
/// the scene file lights nothing.
///
/// Why: a frame scales a cluster's pane, the sum of its entries' panes
/// at unit irradiance, by their mean irradiance, which is right only where
/// that irradiance is even over the cluster. Beside a lamp near a wall or
/// along the edge of a patch of light through a doorway, a cluster of a
/// room's size holds entries 10 to 100 times brighter than others, and
/// spreads the light that the bright few send to their own neighbourhood
/// over the whole cluster's: a glow on a wall that the reference lights
/// only near the lamp or the doorway. With the level among the
/// coordinates, clusters split along the steep gradients of the scene
/// file's light and stay whole where it is dim or even. Lights moved at
/// run time keep the bake's clusters, which are still compact in space.
fn light_levels(entries: &Entries, clusters: usize, diagonal: f32, weight: f32) -> Vec<f32> {
    let area: f64 = entries.areas.iter().map(|&area| area as f64).sum();
    let lit = entries.irradiance_times_area();
    if weight <= 0.0 || area <= 0.0 || lit <= 0.0 || clusters == 0 {
        return Vec::new();
    }
    let mean = (lit / area) as f32;
    let spacing = (area as f32 / clusters as f32).sqrt() / diagonal;
    entries
        .irradiance
        .iter()
        .map(|&irradiance| (1.0 + irradiance / mean).log2() * weight * spacing)
        .collect()
}

/// A cluster's centre in the clustering's space: position over the
/// diagonal, normal times its weight, light level (see [`light_levels`]).
type Centre = (Vec3, Vec3, f32);

fn squared_distance(a: &Centre, b: &Centre) -> f32 {
    a.0.distance_squared(b.0) + a.1.distance_squared(b.1) + (a.2 - b.2) * (a.2 - b.2)
}

/// Clusters an entry may join, nearest first, before it gives up on
/// finding one whose anchor is alike: a room's entries find a cluster of
/// their own room among the first few.
const ALIKE_CANDIDATES: usize = 16;

/// The clustering's distance: positions in scene diagonals, normals
/// times `normal_weight`, and each entry's light level (see
/// [`light_levels`]; empty: none).
#[derive(Clone, Copy)]
pub(crate) struct Metric<'a> {
    pub normal_weight: f32,
    pub diagonal: f32,
    pub light_levels: &'a [f32],
}

/// k-means over (position / diagonal, normal * weight, light level; levels
/// empty: none), seeded by k-means++
/// (each seed drawn with probability proportional to its squared distance
/// from the seeds so far) and a fixed number of Lloyd iterations; a cluster
/// left empty restarts at the entry farthest from its centre. Ties go to the
/// lower index and the draws come from `seed`: deterministic.
///
/// An entry joins the nearest cluster whose anchor (the member nearest its
/// centre, at first its seed) is `alike` (the bake: they see each other
/// and neither lies behind the other's plane), among the
/// [`ALIKE_CANDIDATES`] nearest; only when none is does it take the
/// nearest. A cluster's pane is the sum of its entries' panes, and a frame
/// scales it by their mean irradiance, so entries whose light goes to
/// different places must not share one: entries on the two sides of a
/// partition (a wall that runs on into the next room) light different
/// rooms, and the inside of a lamp's shade lights the lamp's room while a
/// doorway's jamb with the same normal lights both. One lit entry beside
/// the lamp then spread its light over the other room's pane: on generated
/// two-room suites such clusters carried most of the unlit room's light,
/// 2 to 4 times too much.
///
/// Entries that find no alike anchor among those clusters get clusters of
/// their own, as far as [`give_orphans_clusters`] allows.
///
/// Evenly spaced entries of the Halton order are not a usable seeding: every
/// 16th index shares its low bits, so its base-2 radical inverse (which picks
/// the triangle) falls in one sixteenth of the area, and most clusters came
/// out empty.
pub(crate) fn cluster_entries(
    positions: &[Vec3],
    normals: &[Vec3],
    clusters: usize,
    metric: Metric,
    seed: u64,
    priority: &[f32],
    alike: impl Fn(usize, usize) -> bool + Sync,
) -> Vec<u32> {
    let level = |index: usize| metric.light_levels.get(index).copied().unwrap_or(0.0);
    let feature = |index: usize| {
        (
            positions[index] / metric.diagonal,
            normals[index] * metric.normal_weight,
            level(index),
        )
    };
    let distance = |index: usize, centre: &Centre| squared_distance(&feature(index), centre);
    let count = positions.len();
    let mut rng = SampleStream::new(seed, u64::MAX, 0);
    let mut centres: Vec<Centre> = Vec::with_capacity(clusters);
    let mut anchors: Vec<usize> = Vec::with_capacity(clusters);
    let first = (rng.next_f32() as f64 * count as f64) as usize % count;
    centres.push(feature(first));
    anchors.push(first);
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
        anchors.push(chosen);
    }
    let mut assignment = vec![0u32; count];
    let mut distances = vec![0.0f32; count];
    let mut unplaced = vec![false; count];
    // Each entry to the nearest cluster whose anchor is alike among the
    // nearest few, else to the nearest (and marked unplaced); returns how
    // many changed cluster.
    let assign = |assignment: &mut [u32],
                  distances: &mut [f32],
                  unplaced: &mut [bool],
                  centres: &[Centre],
                  anchors: &[usize]| {
        assignment
            .par_iter_mut()
            .zip(distances.par_iter_mut())
            .zip(unplaced.par_iter_mut())
            .enumerate()
            .map(|(index, ((slot, slot_distance), slot_unplaced))| {
                // The nearest candidates, ascending by (distance, cluster).
                let mut nearest = [(f32::INFINITY, 0u32); ALIKE_CANDIDATES];
                for (cluster, centre) in centres.iter().enumerate() {
                    let d = distance(index, centre);
                    if d < nearest[ALIKE_CANDIDATES - 1].0 {
                        let mut at = ALIKE_CANDIDATES - 1;
                        while at > 0 && nearest[at - 1].0 > d {
                            nearest[at] = nearest[at - 1];
                            at -= 1;
                        }
                        nearest[at] = (d, cluster as u32);
                    }
                }
                let placed = nearest
                    .iter()
                    .take_while(|candidate| candidate.0.is_finite())
                    .find(|candidate| {
                        let anchor = anchors[candidate.1 as usize];
                        anchor == index || alike(index, anchor)
                    })
                    .copied();
                *slot_unplaced = placed.is_none();
                let best = placed.unwrap_or(nearest[0]);
                let changed = (*slot != best.1) as usize;
                *slot = best.1;
                *slot_distance = best.0;
                changed
            })
            .sum::<usize>()
    };
    for _ in 0..16 {
        let changed = assign(
            &mut assignment,
            &mut distances,
            &mut unplaced,
            &centres,
            &anchors,
        );
        let mut sums = vec![(Vec3::ZERO, Vec3::ZERO, 0.0f32, 0u32); clusters];
        for (index, &cluster) in assignment.iter().enumerate() {
            let (position, normal, level) = feature(index);
            let sum = &mut sums[cluster as usize];
            sum.0 += position;
            sum.1 += normal;
            sum.2 += level;
            sum.3 += 1;
        }
        let mut restarted = false;
        for ((centre, anchor), sum) in centres.iter_mut().zip(&mut anchors).zip(&sums) {
            if sum.3 > 0 {
                let count = sum.3 as f32;
                *centre = (sum.0 / count, sum.1 / count, sum.2 / count);
                *anchor = usize::MAX;
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
                    *anchor = farthest;
                    distances[farthest] = 0.0;
                    restarted = true;
                }
            }
        }
        // Each populated cluster's anchor: its member nearest the new
        // centre (ties to the lower index).
        let mut anchor_distances = vec![f32::INFINITY; clusters];
        for (index, &cluster) in assignment.iter().enumerate() {
            let cluster = cluster as usize;
            if sums[cluster].3 == 0 {
                continue;
            }
            let d = distance(index, &centres[cluster]);
            if d < anchor_distances[cluster] {
                anchor_distances[cluster] = d;
                anchors[cluster] = index;
            }
        }
        if changed == 0 && !restarted {
            break;
        }
    }
    // Once more against the final anchors, which orphans are judged by.
    assign(
        &mut assignment,
        &mut distances,
        &mut unplaced,
        &centres,
        &anchors,
    );
    give_orphans_clusters(
        &mut assignment,
        &mut anchors,
        &centres,
        &unplaced,
        priority,
        &alike,
    );
    assignment
}

/// At most one cluster in this many is given to orphans. Among columns and
/// arcades many entries see none of their nearest clusters' anchors (an
/// atrium: 470 of 4096), and a cluster for each group of them took 110 of
/// 256 clusters by merging the others, which cost more than it gained
/// (8x8 tiles 10.0 -> 13-14 %).
const ORPHAN_CLUSTER_SHARE: usize = 16;

/// Entries `unplaced` found no cluster with an alike anchor among those
/// nearest them: the inside of a lamp's shade, whose faces no other surface
/// resembles, falls into the nearest cluster of a doorway's jamb and
/// spreads the lamp's light into the next room. The orphan of the most
/// light (`priority`: flux under the scene file's lights) first, each gets
/// a cluster of its own, with every other orphan alike to it, up to one
/// cluster in [`ORPHAN_CLUSTER_SHARE`], in a slot freed by merging
/// the two populated clusters with the nearest centres whose anchors are
/// alike (or an empty one). Merged clusters and new ones are not merged
/// again; orphans left when no pair remains stay where they are.
fn give_orphans_clusters(
    assignment: &mut [u32],
    anchors: &mut [usize],
    centres: &[Centre],
    unplaced: &[bool],
    priority: &[f32],
    alike: &(impl Fn(usize, usize) -> bool + Sync),
) {
    let clusters = centres.len();
    let mut orphans: Vec<usize> = (0..assignment.len())
        .filter(|&index| unplaced[index])
        .collect();
    orphans.sort_by(|&a, &b| priority[b].total_cmp(&priority[a]).then(a.cmp(&b)));
    let mut new_clusters = 0;
    if orphans.is_empty() {
        return;
    }
    let mut sizes = vec![0u32; clusters];
    for &cluster in assignment.iter() {
        sizes[cluster as usize] += 1;
    }
    let mut empty: Vec<u32> = (0..clusters as u32)
        .filter(|&cluster| sizes[cluster as usize] == 0)
        .rev()
        .collect();
    let mut pairs: Vec<(f32, u32, u32)> = Vec::new();
    for first in 0..clusters {
        for second in first + 1..clusters {
            if sizes[first] > 0 && sizes[second] > 0 {
                let (a, b) = (centres[first], centres[second]);
                let distance = squared_distance(&a, &b);
                pairs.push((distance, first as u32, second as u32));
            }
        }
    }
    pairs.sort_by(|a, b| a.0.total_cmp(&b.0).then((a.1, a.2).cmp(&(b.1, b.2))));
    let mut pairs = pairs.into_iter();
    let mut settled = vec![false; clusters];
    while let Some(&first_orphan) = orphans.first() {
        if new_clusters >= clusters / ORPHAN_CLUSTER_SHARE {
            return;
        }
        new_clusters += 1;
        let freed = empty.pop().or_else(|| {
            pairs.by_ref().find_map(|(_, keep, merge)| {
                let (keep_index, merge_index) = (keep as usize, merge as usize);
                if settled[keep_index]
                    || settled[merge_index]
                    || !alike(anchors[keep_index], anchors[merge_index])
                {
                    return None;
                }
                settled[keep_index] = true;
                for slot in assignment.iter_mut() {
                    if *slot == merge {
                        *slot = keep;
                    }
                }
                Some(merge)
            })
        });
        let Some(freed) = freed else {
            return;
        };
        settled[freed as usize] = true;
        anchors[freed as usize] = first_orphan;
        assignment[first_orphan] = freed;
        orphans.retain(|&index| {
            if index == first_orphan {
                return false;
            }
            if alike(index, first_orphan) {
                assignment[index] = freed;
                return false;
            }
            true
        });
    }
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
    let paths = params
        .paths_per_entry
        .saturating_mul(entries.path_factors[entry]);
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

    /// Entries on a line, alike only on the same side of x = 0 (a
    /// partition), and three at x = 0.3-0.32 alike only to each other (the
    /// inside of a lamp's shade): no cluster holds both sides, and the
    /// three share a cluster with nothing else, though their nearest
    /// clusters are those of the right-hand side.
    #[test]
    fn clusters_hold_only_alike_entries() {
        let mut positions: Vec<Vec3> = (0..200)
            .map(|index| Vec3::new(-1.0 + 2.0 * (index as f32 + 0.5) / 200.0, 0.0, 0.0))
            .collect();
        let shade = positions.len();
        positions.extend((0..3).map(|index| Vec3::new(0.3 + 0.01 * index as f32, 0.0, 0.0)));
        let normals = vec![Vec3::Y; positions.len()];
        let in_shade = |index: usize| index >= shade;
        let alike = |a: usize, b: usize| {
            in_shade(a) == in_shade(b) && (positions[a].x > 0.0) == (positions[b].x > 0.0)
        };
        // From 16 clusters one may go to orphans (ORPHAN_CLUSTER_SHARE).
        for clusters in [16, 32] {
            let priority = vec![1.0; positions.len()];
            let metric = Metric {
                normal_weight: 0.5,
                diagonal: 2.0,
                light_levels: &[],
            };
            let assignment =
                cluster_entries(&positions, &normals, clusters, metric, 7, &priority, alike);
            for cluster in 0..clusters as u32 {
                let members: Vec<usize> = (0..positions.len())
                    .filter(|&index| assignment[index] == cluster)
                    .collect();
                for pair in members.windows(2) {
                    assert!(
                        alike(pair[0], pair[1]),
                        "{clusters} clusters: cluster {cluster} holds {members:?}"
                    );
                }
            }
            assert!(assignment[shade..].iter().all(|&c| c == assignment[shade]));
        }
    }

    /// Every ray of a point light in a closed room ends on a wall, so the
    /// entries' irradiance times their areas must add up to the light's
    /// flux, 4 pi I. Generated rooms of the robustness study's default
    /// family: a light 10 cm from a corner (variants 10 and 85; the room's
    /// entries alone counted 0.86x and 0.85x), one in a shade (1) and one
    /// standing free (0); measured 0.98-1.02. Bound: 5 %, the Halton
    /// entries' spread over these rooms at 4096 entries.
    #[test]
    fn entries_count_a_lamps_whole_flux() {
        for index in [10, 85, 1, 0] {
            let variant = relight_scene::generate::variants::variant(
                relight_scene::generate::variants::VARIANTS_DEFAULT_SEED,
                index,
            );
            let case = relight_render::robustness::VariantCase::load_temporary(
                variant,
                2,
                relight_technique::ContextSettings::default(),
            )
            .unwrap();
            let entries = sample_entries(&case.context, 4096).unwrap();
            let counted = entries.irradiance_times_area();
            let flux: f64 = case
                .context
                .scene
                .lights
                .iter()
                .map(|light| match *light {
                    relight_scene::Light::Point { intensity, .. } => {
                        luminance(intensity) as f64 * 4.0 * std::f64::consts::PI
                    }
                    _ => panic!("variant {index}: the family's rooms have point lights"),
                })
                .sum();
            let ratio = counted / flux;
            println!("variant {index}: entries count {ratio:.3} of the light's flux");
            assert!((ratio - 1.0).abs() < 0.05, "variant {index}: {ratio}");
        }
    }

    /// A 120 m two-triangle ground under an open 6 x 3 x 8 m room, loaded
    /// from a file so that the ground is cut into rings of coarser texels.
    fn ground_and_room() -> Scene {
        relight_scene::generate::load_ground_and_room("").unwrap()
    }

    #[test]
    fn entries_follow_the_lightmaps_detail_and_stand_for_their_area() {
        let scene = ground_and_room();
        let region = scene.detail_region().expect("the ground reaches far out");
        assert!(
            scene
                .lights
                .iter()
                .all(|light| matches!(light, relight_scene::Light::Directional { .. })),
            "no near-light entries: every entry is the room's or the ground's"
        );
        let context = |scene: &Scene| {
            SceneContext::new(scene.clone(), relight_technique::ContextSettings::default()).unwrap()
        };
        let entries = sample_entries(&context(&scene), 4096).unwrap();
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
        let entries = sample_entries(&context(&uniform), 4096).unwrap();
        let each = uniform.mesh.total_area() as f32 / 4096.0;
        assert!(entries.areas.iter().all(|&area| area == each));
    }
}
