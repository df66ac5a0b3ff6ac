//! The SRP bake: probes, per-receiver transport compressed per cluster, and
//! the probes' sample tables.

use crate::probes::{self, PlacementSettings};
use crate::transport::{self, TransportScratch, TransportSettings};
use crate::SrpParams;
use glam::{Vec2, Vec3};
use half::f16;
use rayon::prelude::*;
use relight_core::sampling::{stratified_square, uniform_sphere, SampleStream};
use relight_core::sh;
use relight_technique::{
    join_parts, shards_disagree, BakeEstimate, BakePart, PayloadReader, PayloadWriter, Progress,
    SceneContext, Shard, TechniqueError,
};
use relight_trace::Ray;
use std::collections::HashMap;

/// Payload layout version; bump when the encoding changes.
const PAYLOAD_VERSION: u32 = 4;

/// A probe sample that escapes the scene.
pub const ESCAPED: u32 = u32::MAX;
/// A probe sample that hits the back of a surface, whose light the
/// lightmap (front sides only) does not hold: it counts as black.
pub const BACK_FACE: u32 = u32::MAX - 1;

/// Figures about a bake for `relight info` and the closing report.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct BakeStats {
    pub placed_probes: u32,
    pub added_for_coverage: u32,
    pub min_probes: u32,
    /// Receivers that see geometry but fewer than `min_probes` probes.
    pub receivers_short_of_probes: u32,
    pub probes_inside_geometry: u32,
    /// Receivers that see only the environment and need no probe.
    pub open_receivers: u32,
    /// Mean number of nearby probes per receiver.
    pub mean_nearby: f32,
    /// Fraction of primary samples some probe could stand in for.
    pub valid_sample_fraction: f32,
    /// Fraction of the transport matrices' squared norm the kept principal
    /// vectors capture.
    pub captured_energy: f32,
}

impl BakeStats {
    /// The placement's counts, in the order bake payloads store them.
    fn placement_counts(&self) -> [u32; 6] {
        [
            self.placed_probes,
            self.added_for_coverage,
            self.min_probes,
            self.receivers_short_of_probes,
            self.probes_inside_geometry,
            self.open_receivers,
        ]
    }

    fn from_placement_counts(counts: [u32; 6]) -> Self {
        let [placed_probes, added_for_coverage, min_probes, receivers_short_of_probes, probes_inside_geometry, open_receivers] =
            counts;
        Self {
            placed_probes,
            added_for_coverage,
            min_probes,
            receivers_short_of_probes,
            probes_inside_geometry,
            open_receivers,
            ..Default::default()
        }
    }
}

/// Everything the run time needs.
#[derive(Clone, Debug, PartialEq)]
pub struct SrpBake {
    pub receiver_count: usize,
    pub bands: usize,
    pub radius: f32,
    pub probes: Vec<Vec3>,
    /// The sample directions every probe shares (stratified over the sphere).
    pub sample_directions: Vec<Vec3>,
    /// `sample_targets[probe * S + sample]`: index into `visible_receivers`
    /// of the texel the sample's ray hits, or [`ESCAPED`] / [`BACK_FACE`].
    pub sample_targets: Vec<u32>,
    /// The receivers (lightmap texels) any probe sample hits, ascending.
    pub visible_receivers: Vec<u32>,
    /// The irradiance transport: one row per receiver, every receiver in
    /// one cluster.
    pub clusters: ClusterSet,
    pub stats: BakeStats,
    /// Radiance transport of the glossy receivers (empty when off).
    pub radiance: RadianceTransport,
}

/// The original paper's glossy extension: for receivers on materials with
/// a Phong exponent, transport from the probes to the receiver's incident
/// radiance in world-space SH of `bands` bands, compressed like the
/// irradiance transport with one row per receiver and output coefficient.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct RadianceTransport {
    /// Output SH bands; 0 = no radiance transport.
    pub bands: usize,
    /// The glossy receivers' transport: `bands^2` rows per receiver. Its
    /// rank is its own: each receiver brings `bands^2` rows of differing
    /// shape, so it is larger than the irradiance's.
    pub clusters: ClusterSet,
}

impl RadianceTransport {
    pub fn outputs(&self) -> usize {
        self.bands * self.bands
    }
}

/// Transport compressed by clustered PCA (section 4.5.2): receivers grouped
/// by [`transport::aabb_clusters`], each cluster keeping only its
/// receivers' nearby probes as columns, with Sigma_c V^T and U_c in f16.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct ClusterSet {
    /// Principal vectors per cluster (clusters with fewer keep zero rows).
    pub rank: usize,
    /// Receivers in cluster order; cluster c owns
    /// `receivers[receiver_offsets[c]..receiver_offsets[c + 1]]`.
    pub receivers: Vec<u32>,
    pub receiver_offsets: Vec<u32>,
    /// Probes whose columns a cluster stores (its receivers' nearby
    /// probes), with offsets like the receivers'.
    pub probes: Vec<u32>,
    pub probe_offsets: Vec<u32>,
    /// Sigma_c V^T per cluster, row-major rank x (probes x C), f16 bits;
    /// cluster c starts at `rank * C * probe_offsets[c]`.
    pub projection: Vec<u16>,
    /// U_c rows in cluster-receiver order, `rank` f16 values each, one or
    /// more rows per receiver.
    pub reconstruction: Vec<u16>,
}

/// Sums over a cluster set's compression, for the bake's figures.
#[derive(Clone, Copy, Debug, Default)]
struct CompressionTotals {
    energy: f64,
    captured: f64,
    valid_samples: u64,
}

impl ClusterSet {
    /// The set of `clusters` (members in cluster order) and their
    /// compressed outputs, in the same order.
    fn assemble(
        rank: usize,
        clusters: &[Vec<u32>],
        compressed: Vec<ClusterOutput>,
    ) -> (Self, CompressionTotals) {
        let mut set = Self {
            rank,
            receiver_offsets: vec![0],
            probe_offsets: vec![0],
            ..Default::default()
        };
        let mut totals = CompressionTotals::default();
        for (members, output) in clusters.iter().zip(compressed) {
            set.receivers.extend_from_slice(members);
            set.receiver_offsets.push(set.receivers.len() as u32);
            set.probes.extend_from_slice(&output.probes);
            set.probe_offsets.push(set.probes.len() as u32);
            set.projection.extend(output.projection);
            set.reconstruction.extend(output.reconstruction);
            totals.energy += output.energy;
            totals.captured += output.captured;
            totals.valid_samples += output.valid_samples;
        }
        (set, totals)
    }

    pub fn cluster_count(&self) -> usize {
        self.receiver_offsets.len().saturating_sub(1)
    }

    /// Bytes of the receiver and probe lists with their offsets.
    pub fn list_bytes(&self) -> usize {
        (self.receivers.len()
            + self.receiver_offsets.len()
            + self.probes.len()
            + self.probe_offsets.len())
            * 4
    }

    /// Bytes of the two f16 matrices.
    pub fn matrix_bytes(&self) -> usize {
        (self.projection.len() + self.reconstruction.len()) * 2
    }

    /// Everything but the rank, which the payload keeps beside the set's
    /// other sizes.
    fn write(&self, writer: &mut PayloadWriter) {
        writer.u32s(&self.receivers);
        writer.u32s(&self.receiver_offsets);
        writer.u32s(&self.probes);
        writer.u32s(&self.probe_offsets);
        writer.halves(&self.projection);
        writer.halves(&self.reconstruction);
    }

    fn read(reader: &mut PayloadReader, rank: usize) -> Result<Self, TechniqueError> {
        Ok(Self {
            rank,
            receivers: reader.u32s()?,
            receiver_offsets: reader.u32s()?,
            probes: reader.u32s()?,
            probe_offsets: reader.u32s()?,
            projection: reader.halves()?,
            reconstruction: reader.halves()?,
        })
    }

    /// Every index the run time follows stays in bounds: receivers below
    /// `receiver_count` and listed once, probes below `probe_count`, and
    /// matrices of `coefficients` per probe and `rows_per_receiver` rows.
    fn validate(
        &self,
        receiver_count: usize,
        probe_count: usize,
        coefficients: usize,
        rows_per_receiver: usize,
    ) -> Result<(), &'static str> {
        if self.rank == 0 {
            return Err("no principal vectors per cluster");
        }
        if self.receiver_offsets.len() != self.probe_offsets.len()
            || !offsets_are_monotonic(&self.receiver_offsets, self.receivers.len())
            || !offsets_are_monotonic(&self.probe_offsets, self.probes.len())
        {
            return Err("cluster offsets are inconsistent");
        }
        let mut seen = vec![false; receiver_count];
        for &receiver in &self.receivers {
            match seen.get_mut(receiver as usize) {
                Some(slot) if !*slot => *slot = true,
                _ => return Err("a cluster's receiver does not exist or is in two clusters"),
            }
        }
        if self
            .probes
            .iter()
            .any(|&probe| probe as usize >= probe_count)
        {
            return Err("a cluster names a probe that does not exist");
        }
        if self.projection.len() != self.rank * coefficients * self.probes.len()
            || self.reconstruction.len() != self.rank * rows_per_receiver * self.receivers.len()
        {
            return Err("compressed matrices do not match their sizes");
        }
        Ok(())
    }
}

/// The shared sample directions: `count` stratified directions over the
/// sphere, the same for every probe so one basis table serves all.
pub fn sample_directions(count: u32, seed: u64) -> Vec<Vec3> {
    (0..count)
        .map(|index| {
            let mut rng = SampleStream::new(seed ^ 0x5a5a, index as u64, 0);
            uniform_sphere(stratified_square(index, count, Vec2::ZERO, &mut rng))
        })
        .collect()
}

/// The clusters of one kind of transport that a shard compressed.
#[derive(Default)]
pub struct PartClusters {
    /// Clusters of the whole bake, before any is halved.
    pub total: usize,
    /// This shard's clusters are `first..first + own` of them.
    pub first: usize,
    pub own: usize,
    pub rank: usize,
    /// Members and compressed output of each, halves in spatial order.
    compressed: Vec<(Vec<u32>, ClusterOutput)>,
}

impl PartClusters {
    fn write(&self, writer: &mut PayloadWriter) {
        for value in [self.total, self.first, self.own, self.rank] {
            writer.u32(value as u32);
        }
        writer.u32(self.compressed.len() as u32);
        for (members, output) in &self.compressed {
            writer.u32s(members);
            writer.u32s(&output.probes);
            writer.halves(&output.projection);
            writer.halves(&output.reconstruction);
            writer.f64(output.energy);
            writer.f64(output.captured);
            writer.u64(output.valid_samples);
        }
    }

    fn read(reader: &mut PayloadReader) -> Result<Self, TechniqueError> {
        let mut sizes = [0usize; 4];
        for size in &mut sizes {
            *size = reader.u32()? as usize;
        }
        let [total, first, own, rank] = sizes;
        // Each cluster takes at least 36 bytes.
        let count = reader.u32()? as usize;
        let compressed = (0..count)
            .map(|_| {
                let members = reader.u32s()?;
                let output = ClusterOutput {
                    probes: reader.u32s()?,
                    projection: reader.halves()?,
                    reconstruction: reader.halves()?,
                    energy: reader.f64()?,
                    captured: reader.f64()?,
                    valid_samples: reader.u64()?,
                };
                Ok((members, output))
            })
            .collect::<Result<Vec<_>, TechniqueError>>()?;
        if first + own > total {
            return Err(reader.corrupt("a shard's clusters lie beyond the bake's"));
        }
        Ok(Self {
            total,
            first,
            own,
            rank,
            compressed,
        })
    }

    /// Appends `next`, the following shard's clusters.
    fn join(&mut self, next: PartClusters) -> Result<(), &'static str> {
        if next.total != self.total || next.rank != self.rank {
            return Err("disagree on their clusters");
        }
        if next.first != self.first + self.own {
            return Err("do not follow each other");
        }
        self.own += next.own;
        self.compressed.extend(next.compressed);
        Ok(())
    }

    fn assemble(self) -> Result<(ClusterSet, CompressionTotals), &'static str> {
        if self.first != 0 || self.own != self.total {
            return Err("leave clusters unbaked");
        }
        let (members, outputs): (Vec<Vec<u32>>, Vec<ClusterOutput>) =
            self.compressed.into_iter().unzip();
        Ok(ClusterSet::assemble(self.rank, &members, outputs))
    }
}

/// One shard of an SRP bake: the probes, which every shard places alike,
/// and the shard's part of the three kinds of work: receiver clusters'
/// irradiance transport, glossy clusters' radiance transport, and probes'
/// sample tables. Each receiver's and probe's rays draw on its own index,
/// so the work is the same in any shard.
pub struct SrpPart {
    pub receiver_count: usize,
    pub bands: usize,
    pub radius: f32,
    pub probes: Vec<Vec3>,
    /// The placement's figures; the transport's are summed at the merge.
    pub stats: BakeStats,
    /// Transport samples per receiver.
    pub samples: u32,
    pub sample_directions: Vec<Vec3>,
    pub irradiance: PartClusters,
    /// Radiance transport bands; 0 = none.
    pub radiance_bands: usize,
    pub radiance: PartClusters,
    pub first_probe: usize,
    /// Sample tables of probes `first_probe..`, before compaction.
    pub sample_targets: Vec<u32>,
}

/// Shard payloads carry their own version beside the bake's.
const PART_VERSION: u32 = 1;

impl SrpPart {
    pub fn build(
        context: &SceneContext,
        params: &SrpParams,
        shard: Shard,
        progress: &dyn Progress,
    ) -> Result<Self, TechniqueError> {
        let receivers = &context.atlas.receivers;
        if receivers.is_empty() {
            return Err(TechniqueError::Other(
                "the scene's lightmap has no receivers: SRP needs lit surfaces to bake for".into(),
            ));
        }
        let bands = params.order as usize + 1;
        let coefficients = sh::coefficient_count(bands);
        progress.start("srp probe placement", 1);
        let mut stats = BakeStats {
            min_probes: params.min_probes,
            ..Default::default()
        };
        let (probes, radius) = if params.probes.is_empty() {
            let placement = probes::place_probes(
                context,
                PlacementSettings {
                    count: params.probe_count as usize,
                    radius: params.radius,
                    radius_factor: params.radius_factor,
                    min_probes: params.min_probes as usize,
                    max_added: params.max_added_probes as usize,
                },
            );
            stats.added_for_coverage = placement.added_for_coverage as u32;
            stats.receivers_short_of_probes = placement.receivers_short_of_probes as u32;
            stats.open_receivers = placement.open_receivers as u32;
            (placement.probes, placement.radius)
        } else {
            let probes: Vec<Vec3> = params.probes.iter().map(|p| Vec3::from_array(*p)).collect();
            let radius = if params.radius > 0.0 {
                params.radius
            } else {
                // The covering distance of the given probes over the
                // receivers, times the same factor as automatic placement.
                let covering = receivers
                    .positions
                    .par_iter()
                    .map(|position| {
                        probes
                            .iter()
                            .map(|probe| probe.distance(*position))
                            .fold(f32::INFINITY, f32::min)
                    })
                    .reduce(|| 0.0, f32::max);
                (params.radius_factor * covering).max(1e-3)
            };
            let (short, open) =
                probes::coverage_of(context, &probes, radius, params.min_probes as usize);
            stats.receivers_short_of_probes = short as u32;
            stats.open_receivers = open as u32;
            (probes, radius)
        };
        stats.placed_probes = probes.len() as u32;
        stats.probes_inside_geometry = probes
            .iter()
            .filter(|probe| probes::is_inside_geometry(context, **probe))
            .count() as u32;
        progress.finish();

        progress.start("srp nearby probes", 1);
        let nearby = probes::nearby_probes(context, &probes, radius, params.max_nearby as usize);
        stats.mean_nearby =
            nearby.iter().map(Vec::len).sum::<usize>() as f32 / receivers.len() as f32;
        let mut clusters =
            transport::aabb_clusters(&receivers.positions, params.cluster_size as usize);
        progress.finish();
        let total = clusters.len();
        // A receiver's rays: its samples, each tested against the nearby
        // probes it uses; clusters differ in them, so shards split by cost.
        let costs: Vec<u64> = clusters
            .iter()
            .map(|members| {
                members
                    .iter()
                    .map(|&receiver| 1 + nearby[receiver as usize].len() as u64)
                    .sum()
            })
            .collect();
        let own = shard.weighted_range(&costs);
        clusters.truncate(own.end);
        let clusters = clusters.split_off(own.start);
        let settings = TransportSettings {
            bands,
            samples: params.samples,
            radius,
            texel_jitter: params.texel_jitter,
            seed: params.seed,
        };
        let rank = params.pca_vectors as usize;
        progress.start(
            "srp transport",
            clusters.iter().map(Vec::len).sum::<usize>() as u64,
        );
        // One cluster per work item: its transport matrix exists only while
        // it is compressed, so memory grows with the threads, not the scene.
        let split = ClusterSplit {
            positions: &receivers.positions,
            nearby: &nearby,
            coefficients,
            rank,
            min_energy: params.cluster_energy as f64,
        };
        let compressed: Vec<(Vec<u32>, ClusterOutput)> = clusters
            .into_par_iter()
            .map_init(
                || TransportScratch::new(bands),
                |scratch, members| {
                    let count = members.len() as u64;
                    let (matrix, columns, valid_samples) =
                        cluster_transport(context, &probes, &nearby, &members, &settings, scratch);
                    let mut parts = Vec::new();
                    split.compress(members, matrix, columns, valid_samples, &mut parts);
                    progress.advance(count);
                    parts
                },
            )
            .flatten_iter()
            .collect();
        progress.finish();
        let irradiance = PartClusters {
            total,
            first: own.start,
            own: own.len(),
            rank,
            compressed,
        };
        let radiance = if params.radiance_order > 0 {
            radiance_transport(
                context, &probes, &nearby, &settings, params, shard, progress,
            )
        } else {
            PartClusters::default()
        };

        let own_probes = shard.range(probes.len());
        progress.start("srp probe sample tables", own_probes.len() as u64);
        let sample_directions = sample_directions(params.probe_samples, params.seed);
        let sample_targets = sample_tables(
            context,
            &probes[own_probes.clone()],
            &sample_directions,
            progress,
        );
        progress.finish();
        Ok(Self {
            receiver_count: receivers.len(),
            bands,
            radius,
            probes,
            stats,
            samples: params.samples,
            sample_directions,
            irradiance,
            radiance_bands: if params.radiance_order > 0 {
                params.radiance_order as usize + 1
            } else {
                0
            },
            radiance,
            first_probe: own_probes.start,
            sample_targets,
        })
    }

    pub fn encode(&self) -> Vec<u8> {
        let mut writer = PayloadWriter::default();
        writer.u32(PART_VERSION);
        writer.u32(self.receiver_count as u32);
        writer.u32(self.bands as u32);
        writer.f32(self.radius);
        writer.vectors(&self.probes);
        let stats = &self.stats;
        for value in stats.placement_counts() {
            writer.u32(value);
        }
        writer.f32(stats.mean_nearby);
        writer.u32(self.samples);
        writer.vectors(&self.sample_directions);
        self.irradiance.write(&mut writer);
        writer.u32(self.radiance_bands as u32);
        self.radiance.write(&mut writer);
        writer.u32(self.first_probe as u32);
        writer.u32s(&self.sample_targets);
        writer.finish()
    }

    pub fn decode(bytes: &[u8]) -> Result<Self, TechniqueError> {
        let mut reader = PayloadReader::new(bytes, "srp");
        reader.version(
            PART_VERSION,
            "SRP shard",
            "bake the shards with this relight",
        )?;
        let receiver_count = reader.u32()? as usize;
        let bands = reader.u32()? as usize;
        let radius = reader.finite()?;
        let probes = reader.vectors()?;
        let mut counts = [0u32; 6];
        for count in &mut counts {
            *count = reader.u32()?;
        }
        let stats = BakeStats {
            mean_nearby: reader.finite()?,
            ..BakeStats::from_placement_counts(counts)
        };
        let part = Self {
            receiver_count,
            bands,
            radius,
            probes,
            stats,
            samples: reader.u32()?,
            sample_directions: reader.vectors()?,
            irradiance: PartClusters::read(&mut reader)?,
            radiance_bands: reader.u32()? as usize,
            radiance: PartClusters::read(&mut reader)?,
            first_probe: reader.u32()? as usize,
            sample_targets: reader.u32s()?,
        };
        reader.end()?;
        Ok(part)
    }
}

impl BakePart for SrpPart {
    const TECHNIQUE: &'static str = "srp";

    fn is_first(&self) -> bool {
        self.first_probe == 0 && self.irradiance.first == 0 && self.radiance.first == 0
    }

    /// The same probes for the same lightmap.
    fn same_setup(&self, other: &Self) -> bool {
        self.receiver_count == other.receiver_count
            && self.bands == other.bands
            && self.radius.to_bits() == other.radius.to_bits()
            && self.probes == other.probes
            && self.stats == other.stats
            && self.samples == other.samples
            && self.sample_directions == other.sample_directions
            && self.radiance_bands == other.radiance_bands
    }

    fn append(&mut self, next: Self) -> Result<(), &'static str> {
        if next.first_probe * self.sample_directions.len() != self.sample_targets.len() {
            return Err("do not follow each other");
        }
        self.sample_targets.extend(next.sample_targets);
        self.irradiance.join(next.irradiance)?;
        self.radiance.join(next.radiance)
    }
}

impl SrpBake {
    /// Bakes in one piece: the merge of the single shard 0/1.
    pub fn build(
        context: &SceneContext,
        params: &SrpParams,
        progress: &dyn Progress,
    ) -> Result<Self, TechniqueError> {
        let part = SrpPart::build(context, params, Shard::WHOLE, progress)?;
        Self::from_parts(std::iter::once(Ok(part)))
    }

    /// Joins parts given in shard order.
    pub fn from_parts(
        parts: impl IntoIterator<Item = Result<SrpPart, TechniqueError>>,
    ) -> Result<Self, TechniqueError> {
        let disagree = |message: &str| shards_disagree("srp", message);
        let SrpPart {
            receiver_count,
            bands,
            radius,
            probes,
            mut stats,
            samples,
            sample_directions,
            irradiance,
            radiance_bands,
            radiance,
            sample_targets: targets,
            ..
        } = join_parts(parts)?;
        if targets.len() != probes.len() * sample_directions.len() {
            return Err(disagree("leave probes without sample tables"));
        }
        let (cluster_set, totals) = irradiance.assemble().map_err(disagree)?;
        stats.captured_energy = if totals.energy > 0.0 {
            (totals.captured / totals.energy) as f32
        } else {
            1.0
        };
        stats.valid_sample_fraction =
            totals.valid_samples as f32 / (receiver_count as f32 * samples as f32);
        let radiance = RadianceTransport {
            bands: radiance_bands,
            clusters: if radiance_bands > 0 {
                radiance.assemble().map_err(disagree)?.0
            } else {
                ClusterSet::default()
            },
        };
        // Compact the hit receivers so the direct light is evaluated only
        // where probes look.
        let mut compact = HashMap::new();
        let mut hit: Vec<u32> = targets.iter().copied().filter(|&t| t < BACK_FACE).collect();
        hit.sort_unstable();
        hit.dedup();
        for (index, receiver) in hit.iter().enumerate() {
            compact.insert(*receiver, index as u32);
        }
        let sample_targets = targets
            .into_iter()
            .map(|target| {
                if target < BACK_FACE {
                    compact[&target]
                } else {
                    target
                }
            })
            .collect();
        let bake = Self {
            receiver_count,
            bands,
            radius,
            probes,
            sample_directions,
            sample_targets,
            visible_receivers: hit,
            clusters: cluster_set,
            stats,
            radiance,
        };
        bake.validate().map_err(|message| disagree(&message))?;
        Ok(bake)
    }

    pub fn coefficients(&self) -> usize {
        sh::coefficient_count(self.bands)
    }

    /// Little-endian payload for the bake file.
    pub fn encode(&self) -> Vec<u8> {
        let mut writer = PayloadWriter::with_capacity(
            self.clusters.matrix_bytes() + self.sample_targets.len() * 4,
        );
        writer.u32(PAYLOAD_VERSION);
        writer.u32(self.receiver_count as u32);
        writer.u32(self.bands as u32);
        writer.f32(self.radius);
        writer.u32(self.clusters.rank as u32);
        writer.vectors(&self.probes);
        writer.vectors(&self.sample_directions);
        writer.u32s(&self.sample_targets);
        writer.u32s(&self.visible_receivers);
        self.clusters.write(&mut writer);
        let stats = &self.stats;
        for value in stats.placement_counts() {
            writer.u32(value);
        }
        writer.f32s(&[
            stats.mean_nearby,
            stats.valid_sample_fraction,
            stats.captured_energy,
        ]);
        let radiance = &self.radiance;
        writer.u32(radiance.bands as u32);
        writer.u32(radiance.clusters.rank as u32);
        radiance.clusters.write(&mut writer);
        writer.finish()
    }

    pub fn decode(bytes: &[u8]) -> Result<Self, TechniqueError> {
        let mut reader = PayloadReader::new(bytes, "srp");
        reader.version(PAYLOAD_VERSION, "SRP payload", "bake again")?;
        let receiver_count = reader.u32()? as usize;
        let bands = reader.u32()? as usize;
        let radius = reader.finite()?;
        let rank = reader.u32()? as usize;
        let probes = reader.vectors()?;
        let sample_directions = reader.vectors()?;
        let sample_targets = reader.u32s()?;
        let visible_receivers = reader.u32s()?;
        let clusters = ClusterSet::read(&mut reader, rank)?;
        let mut counts = [0u32; 6];
        for count in &mut counts {
            *count = reader.u32()?;
        }
        let floats = reader.f32s()?;
        let radiance_bands = reader.u32()? as usize;
        let radiance_rank = reader.u32()? as usize;
        let radiance = RadianceTransport {
            bands: radiance_bands,
            clusters: ClusterSet::read(&mut reader, radiance_rank)?,
        };
        reader.end()?;
        let bake = Self {
            receiver_count,
            bands,
            radius,
            probes,
            sample_directions,
            sample_targets,
            visible_receivers,
            clusters,
            stats: BakeStats {
                mean_nearby: floats.first().copied().unwrap_or(0.0),
                valid_sample_fraction: floats.get(1).copied().unwrap_or(0.0),
                captured_energy: floats.get(2).copied().unwrap_or(0.0),
                ..BakeStats::from_placement_counts(counts)
            },
            radiance,
        };
        bake.validate()
            .map_err(|message| reader.corrupt(&message))?;
        Ok(bake)
    }

    /// Every index the run time follows stays in bounds.
    fn validate(&self) -> Result<(), String> {
        if !(1..=sh::MAX_BANDS).contains(&self.bands) {
            return Err("SH bands outside 1..=8".into());
        }
        if self.radius.is_nan() || self.radius <= 0.0 {
            return Err("the cut-off radius is not positive".into());
        }
        let samples = self.sample_directions.len();
        if self.sample_targets.len() != samples * self.probes.len() {
            return Err("sample tables do not match probes x samples".into());
        }
        if self
            .sample_targets
            .iter()
            .any(|&target| target < BACK_FACE && target as usize >= self.visible_receivers.len())
            || self
                .visible_receivers
                .iter()
                .any(|&receiver| receiver as usize >= self.receiver_count)
        {
            return Err("a probe sample names a texel that does not exist".into());
        }
        if self.clusters.receivers.len() != self.receiver_count {
            return Err("clusters do not cover the receivers".into());
        }
        let coefficients = self.coefficients();
        self.clusters
            .validate(self.receiver_count, self.probes.len(), coefficients, 1)?;
        let radiance = &self.radiance;
        if radiance.bands == 0 {
            return if radiance.clusters.receivers.is_empty()
                && radiance.clusters.projection.is_empty()
            {
                Ok(())
            } else {
                Err("radiance transport without bands".into())
            };
        }
        if radiance.bands > MAX_RADIANCE_BANDS {
            return Err("radiance transport bands outside 1..=5".into());
        }
        radiance
            .clusters
            .validate(
                self.receiver_count,
                self.probes.len(),
                coefficients,
                radiance.outputs(),
            )
            .map_err(|message| format!("radiance transport: {message}"))
    }
}

/// Cluster offsets start at 0, never fall and end at `total`.
fn offsets_are_monotonic(offsets: &[u32], total: usize) -> bool {
    offsets.first() == Some(&0)
        && offsets.windows(2).all(|pair| pair[0] <= pair[1])
        && offsets.last().map(|&last| last as usize) == Some(total)
}

/// The original paper kept radiance transport at order 4 (25
/// coefficients) for speed; so does relight.
pub const MAX_RADIANCE_BANDS: usize = 5;

/// Radiance transport for every receiver on a material with a Phong
/// exponent, clustered and compressed cluster by cluster like the
/// irradiance transport.
/// The receivers on materials with a Phong exponent, which the radiance
/// transport serves, in receiver order.
fn glossy_receivers(context: &SceneContext) -> Vec<u32> {
    let receivers = &context.atlas.receivers;
    (0..receivers.len() as u32)
        .filter(|&receiver| {
            let triangle = receivers.triangles[receiver as usize];
            context.scene.material_of(triangle as usize).phong_exponent > 1.0
        })
        .collect()
}

fn radiance_transport(
    context: &SceneContext,
    probes: &[Vec3],
    nearby: &[Vec<u32>],
    settings: &TransportSettings,
    params: &SrpParams,
    shard: Shard,
    progress: &dyn Progress,
) -> PartClusters {
    let receivers = &context.atlas.receivers;
    let glossy = glossy_receivers(context);
    let bands = params.radiance_order as usize + 1;
    let outputs = bands * bands;
    let coefficients = sh::coefficient_count(settings.bands);
    let rank = params.radiance_pca_vectors as usize;
    let settings = TransportSettings {
        samples: params.radiance_samples,
        ..*settings
    };
    let positions: Vec<Vec3> = glossy
        .iter()
        .map(|&receiver| receivers.positions[receiver as usize])
        .collect();
    // Each receiver brings `outputs` rows: clusters of cluster_size /
    // outputs receivers keep the matrices (and the bake's memory and SVD
    // time) the size of the irradiance's.
    let cluster_receivers = (params.cluster_size as usize / outputs).max(1);
    let all_clusters = transport::aabb_clusters(&positions, cluster_receivers);
    let costs: Vec<u64> = all_clusters
        .iter()
        .map(|members| {
            members
                .iter()
                .map(|&local| 1 + nearby[glossy[local as usize] as usize].len() as u64)
                .sum()
        })
        .collect();
    let own = shard.weighted_range(&costs);
    let clusters: Vec<Vec<u32>> = all_clusters[own.clone()]
        .iter()
        .map(|members| {
            members
                .iter()
                .map(|&local| glossy[local as usize])
                .collect()
        })
        .collect();
    progress.start(
        "srp radiance transport",
        clusters.iter().map(Vec::len).sum::<usize>() as u64,
    );
    let compressed: Vec<ClusterOutput> = clusters
        .par_iter()
        .map_init(
            || TransportScratch::new(settings.bands),
            |scratch, members| {
                let (matrix, columns, valid_samples) = cluster_matrix(
                    nearby,
                    members,
                    coefficients,
                    outputs,
                    |receiver, own, rows| {
                        transport::radiance_rows(
                            context,
                            probes,
                            receiver as usize,
                            own,
                            &settings,
                            bands,
                            scratch,
                            rows,
                        )
                    },
                );
                let output = compress_cluster(
                    &matrix,
                    members.len() * outputs,
                    columns,
                    coefficients,
                    rank,
                    valid_samples,
                );
                progress.advance(members.len() as u64);
                output
            },
        )
        .collect();
    progress.finish();
    PartClusters {
        total: all_clusters.len(),
        first: own.start,
        own: own.len(),
        rank,
        compressed: clusters.into_iter().zip(compressed).collect(),
    }
}

/// One compressed cluster.
struct ClusterOutput {
    probes: Vec<u32>,
    projection: Vec<u16>,
    reconstruction: Vec<u16>,
    energy: f64,
    captured: f64,
    valid_samples: u64,
}

/// The transport matrix of one cluster, row per receiver, columns the
/// union of its receivers' nearby probes times C (zero where a receiver does
/// not use a probe); returns (matrix, column probes, valid samples).
pub fn cluster_transport(
    context: &SceneContext,
    probes: &[Vec3],
    nearby: &[Vec<u32>],
    members: &[u32],
    settings: &TransportSettings,
    scratch: &mut TransportScratch,
) -> (Vec<f32>, Vec<u32>, u64) {
    let coefficients = sh::coefficient_count(settings.bands);
    cluster_matrix(nearby, members, coefficients, 1, |receiver, own, row| {
        transport::transport_row(
            context,
            probes,
            receiver as usize,
            own,
            settings,
            scratch,
            row,
        )
    })
}

/// A cluster's matrix with `outputs` rows per member (member `local` owns
/// rows from `local * outputs` on) and the members' nearby probes times C
/// as columns. `rows_of(receiver, nearby probes, rows)` fills one member's
/// rows, each its probes times C long, and returns its valid samples; the
/// rows are scattered into the probes' columns. Returns (matrix, column
/// probes, valid samples).
fn cluster_matrix(
    nearby: &[Vec<u32>],
    members: &[u32],
    coefficients: usize,
    outputs: usize,
    mut rows_of: impl FnMut(u32, &[u32], &mut [f32]) -> u32,
) -> (Vec<f32>, Vec<u32>, u64) {
    let mut columns: Vec<u32> = members
        .iter()
        .flat_map(|&receiver| nearby[receiver as usize].iter().copied())
        .collect();
    columns.sort_unstable();
    columns.dedup();
    let width = columns.len() * coefficients;
    let mut matrix = vec![0.0f32; members.len() * outputs * width];
    let mut rows = Vec::new();
    let mut valid_samples = 0u64;
    for (local, &receiver) in members.iter().enumerate() {
        let own = &nearby[receiver as usize];
        let own_width = own.len() * coefficients;
        rows.clear();
        rows.resize(outputs * own_width, 0.0);
        valid_samples += rows_of(receiver, own, &mut rows) as u64;
        for (slot, probe) in own.iter().enumerate() {
            let column = columns
                .binary_search(probe)
                .expect("nearby probe is a column");
            for output in 0..outputs {
                let target = (local * outputs + output) * width + column * coefficients;
                matrix[target..target + coefficients].copy_from_slice(
                    &rows[output * own_width + slot * coefficients..][..coefficients],
                );
            }
        }
    }
    (matrix, columns, valid_samples)
}

/// How clusters whose principal vectors keep too little of their
/// transport's energy are halved and compressed again.
struct ClusterSplit<'a> {
    positions: &'a [Vec3],
    nearby: &'a [Vec<u32>],
    coefficients: usize,
    rank: usize,
    /// Fraction of the squared transport a cluster's `rank` vectors must
    /// keep; below it a cluster of at least `2 rank` members is halved.
    min_energy: f64,
}

impl ClusterSplit<'_> {
    /// Compresses the cluster `members` (the rows of `matrix`, whose
    /// columns are `columns` probes times C), halving it spatially while
    /// its vectors keep less than `min_energy`; pushes the parts in
    /// spatial order. A cluster's vectors must serve every probe its
    /// members see (more in a long corridor than in a box) and every
    /// direction its members face, so one count of vectors per 1024
    /// receivers is too few in some scenes and wasted in others.
    fn compress(
        &self,
        members: Vec<u32>,
        matrix: Vec<f32>,
        columns: Vec<u32>,
        valid_samples: u64,
        parts: &mut Vec<(Vec<u32>, ClusterOutput)>,
    ) {
        let rows = members.len();
        let output = compress_cluster(
            &matrix,
            rows,
            columns.clone(),
            self.coefficients,
            self.rank,
            valid_samples,
        );
        let kept = if output.energy > 0.0 {
            output.captured / output.energy
        } else {
            1.0
        };
        if kept >= self.min_energy || rows < 2 * self.rank.max(1) {
            parts.push((members, output));
            return;
        }
        let (low, high) = transport::halve((0..rows as u32).collect(), |local| {
            self.positions[members[local as usize] as usize]
        });
        // The valid-sample count only feeds the bake's statistics, which
        // sum it over clusters: the first part carries the whole count.
        for (part, valid) in [(low, valid_samples), (high, 0)] {
            let part_members: Vec<u32> =
                part.iter().map(|&local| members[local as usize]).collect();
            let (part_matrix, part_columns) = self.rows_of(&matrix, &columns, &members, &part);
            self.compress(part_members, part_matrix, part_columns, valid, parts);
        }
    }

    /// The rows `locals` of a cluster's matrix, keeping only the columns of
    /// the probes those rows' receivers see.
    fn rows_of(
        &self,
        matrix: &[f32],
        columns: &[u32],
        members: &[u32],
        locals: &[u32],
    ) -> (Vec<f32>, Vec<u32>) {
        let c = self.coefficients;
        let width = columns.len() * c;
        let mut part_columns: Vec<u32> = locals
            .iter()
            .flat_map(|&local| {
                self.nearby[members[local as usize] as usize]
                    .iter()
                    .copied()
            })
            .collect();
        part_columns.sort_unstable();
        part_columns.dedup();
        let part_width = part_columns.len() * c;
        let mut part = vec![0.0f32; locals.len() * part_width];
        for (row, &local) in locals.iter().enumerate() {
            let source = &matrix[local as usize * width..][..width];
            for (slot, probe) in part_columns.iter().enumerate() {
                let column = columns
                    .binary_search(probe)
                    .expect("a part's probe is a column of its cluster");
                part[row * part_width + slot * c..][..c]
                    .copy_from_slice(&source[column * c..][..c]);
            }
        }
        (part, part_columns)
    }
}

/// Compresses one cluster's `rows` x (columns x C) transport matrix to
/// `rank` principal vectors in f16.
fn compress_cluster(
    matrix: &[f32],
    rows: usize,
    columns: Vec<u32>,
    coefficients: usize,
    rank: usize,
    valid_samples: u64,
) -> ClusterOutput {
    let width = columns.len() * coefficients;
    let compressed = transport::compress(matrix, rows, width, rank);
    let energy: f64 = matrix.iter().map(|&v| (v as f64) * (v as f64)).sum();
    // ||T_k||^2 = sum of the kept sigma^2 = squared norm of the projection.
    let captured: f64 = compressed
        .projection
        .iter()
        .map(|&v| (v as f64) * (v as f64))
        .sum();
    // Clusters with fewer than `rank` vectors pad with zeros so every
    // cluster has the same shape at run time.
    let mut projection = vec![0u16; rank * width];
    for k in 0..compressed.rank {
        for column in 0..width {
            projection[k * width + column] =
                f16::from_f32(compressed.projection[k * width + column]).to_bits();
        }
    }
    let mut reconstruction = vec![0u16; rows * rank];
    for row in 0..rows {
        for k in 0..compressed.rank {
            reconstruction[row * rank + k] =
                f16::from_f32(compressed.reconstruction[row * compressed.rank + k]).to_bits();
        }
    }
    ClusterOutput {
        probes: columns,
        projection,
        reconstruction,
        energy,
        captured: captured.min(energy),
        valid_samples,
    }
}

/// For every probe and shared direction, the receiver whose texel the ray
/// hits (or [`ESCAPED`] / [`BACK_FACE`]).
fn sample_tables(
    context: &SceneContext,
    probes: &[Vec3],
    directions: &[Vec3],
    progress: &dyn Progress,
) -> Vec<u32> {
    let atlas = &context.atlas;
    // Gutter texels point at the covered texel they copy.
    let receiver_of_texel = atlas.dilated_receiver_of_texel();
    let receiver_at = |triangle: u32, barycentric: Vec2| -> u32 {
        let uv = atlas.uv_of(triangle, barycentric);
        let x = (uv.x.floor() as i64).clamp(0, atlas.width as i64 - 1) as u32;
        let y = (uv.y.floor() as i64).clamp(0, atlas.height as i64 - 1) as u32;
        let receiver = receiver_of_texel[(y * atlas.width + x) as usize];
        // A hit on a texel nothing covers (thin slivers) counts as black.
        if receiver == u32::MAX {
            BACK_FACE
        } else {
            receiver
        }
    };
    probes
        .par_iter()
        .flat_map_iter(|&probe| {
            let targets: Vec<u32> = directions
                .iter()
                .map(|&direction| {
                    let ray = Ray {
                        origin: probe,
                        direction,
                        t_max: f32::INFINITY,
                    };
                    match context.bvh.intersect(&ray) {
                        None => ESCAPED,
                        Some(hit) => {
                            let normal = context.scene.mesh.geometric_normal(hit.triangle as usize);
                            if normal.dot(direction) >= 0.0 {
                                BACK_FACE
                            } else {
                                receiver_at(hit.triangle, hit.barycentric)
                            }
                        }
                    }
                })
                .collect();
            progress.advance(1);
            targets
        })
        .collect()
}

/// Occlusion rays per transport sample over the nearby probes a receiver
/// uses: a sample tests every nearby probe in front of the surface it hit,
/// and misses (sky) and back faces test none. Sponza, order 7 with 160
/// probes: 4.55 per sample of 8 nearby.
const OCCLUSION_PER_NEARBY: f64 = 0.57;

/// Forecasts the bake of `shard` from the parameters. Rays: every
/// receiver's samples (and every glossy receiver's radiance samples), each
/// testing its nearby probes, and the placement's rays from every receiver
/// to the probes in reach. Time per ray time grows with the coefficients
/// each valid sample projects onto (SH evaluation is a quarter of an
/// order-7 bake). Peak: the compressed clusters held as parts, assembled
/// and encoded, the nearby lists, and each thread's cluster matrix with
/// its SVD.
pub fn estimate(context: &SceneContext, params: &SrpParams, shard: Shard) -> BakeEstimate {
    let receivers = context.atlas.receivers.len() as f64;
    let share = 1.0 / shard.count as f64;
    let coefficients = sh::coefficient_count(params.order as usize + 1) as f64;
    let probes = if params.probes.is_empty() {
        params.probe_count + params.max_added_probes / 2
    } else {
        params.probes.len() as u32
    };
    let nearby = params.max_nearby.min(probes).max(1) as f64;
    let glossy = if params.radiance_order > 0 {
        glossy_receivers(context).len() as f64
    } else {
        0.0
    };
    let samples =
        share * (receivers * params.samples as f64 + glossy * params.radiance_samples as f64);
    let placement = receivers * (16.0 + (3.0 * nearby).min(probes as f64));
    let threads = rayon::current_num_threads() as f64;
    let width = (2.0 * nearby).min(probes as f64) * coefficients;
    let rank = params.pca_vectors as f64;
    // Clusters end up about a third of `cluster_size` after the energy
    // test halves them (Sponza: about 1100 clusters for 378k receivers).
    let clusters = receivers * share / (params.cluster_size as f64 / 3.0).max(2.0 * rank);
    let compressed = receivers * share * rank * 2.0 + clusters * rank * width * 2.0;
    let held_clusters = 3.0 * compressed;
    let nearby_lists = receivers * (24.0 + 4.0 * nearby);
    // A whole cluster's columns: the nearby probes of receivers spread over
    // it, up to four receivers' worth of different ones.
    let cluster_width = (4.0 * nearby).min(probes as f64) * coefficients;
    let matrices = threads * params.cluster_size as f64 * cluster_width * 4.0 * MATRIX_RETENTION;
    BakeEstimate {
        rays: relight_trace::counters::RayCount {
            closest_hit: samples as u64,
            occlusion: (samples * nearby * OCCLUSION_PER_NEARBY + placement) as u64,
        },
        time_per_ray_time: 1.1 + 0.008 * coefficients,
        occlusion_rate: None,
        fixed_seconds: 0.0,
        peak: vec![
            ("compressed clusters".into(), held_clusters as u64),
            ("cluster matrices".into(), matrices as u64),
            ("nearby probes".into(), nearby_lists as u64),
        ],
        lower_memory_with: "--set order=N, --set pca_vectors=N, --set max_nearby=N, --set cluster_size=N, a lower --lightmap-resolution, or --shard I/N on several machines".into(),
    }
}

/// Bytes a worker holds per byte of its cluster's f32 matrix: the matrix,
/// its f64 copy for the SVD and the SVD's workspace, the halves it splits
/// into while the whole is still held, and the allocator's per-thread
/// arenas, which stay at their largest. Measured: the 100k atrium's SRP
/// bake peaks 103 MiB higher on 2 threads than on 1, for 8 MiB matrices.
const MATRIX_RETENTION: f64 = 12.0;
