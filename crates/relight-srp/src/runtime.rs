//! The SRP run time: direct light where probes look, probe projection into
//! SH, per-cluster projection onto the principal vectors, reconstruction
//! per receiver into a cluster-order array that a texel map (the dilated
//! lightmap, made at load) lets shading sample.

use crate::bake::{ClusterSet, SrpBake, BACK_FACE};
use crate::kernels;
use crate::probes::falloff_weight;
use glam::Vec3;
use rayon::prelude::*;
use relight_core::{sh, Rgb, Rgb9e5};
use relight_scene::Light;
use relight_technique::{
    FinalGather, FinalGatherSettings, Frame, FrameReads, LastFrame, MemoryEntry, SceneContext,
    SettlingPasses, StageTimings, SurfaceGather, SurfacePoint, Technique, TechniqueError,
};
use relight_trace::direct::Footprints;
use relight_trace::Ray;
use std::f32::consts::{FRAC_1_PI, PI};
use std::sync::Arc;

/// Run-time settings (one bake serves every value of them).
#[derive(Clone, Copy, Debug)]
pub struct RuntimeSettings {
    /// 1: single bounce; more: last frame's indirect light feeds the probes
    /// (and the first update runs this many passes so it starts settled).
    pub bounces: u32,
    /// Probes refreshed per frame, round robin; 0 = all.
    pub probe_budget: u32,
    /// Specular reflectance of materials with a Phong exponent.
    pub specular: f32,
    /// Gather rays per point in space.
    pub space_rays: u32,
    /// Which receivers near other geometry trace their near field.
    pub final_gather: FinalGatherSettings,
    /// With bounces, the gathered values feed the next bounce where a
    /// texel gathers (false: the reconstruction does, as in the paper).
    pub gather_feedback: bool,
}

pub struct Srp {
    context: Arc<SceneContext>,
    /// The bake, less its U rows, which `irradiance_rows` and
    /// `radiance_rows` hold in blocks.
    bake: SrpBake,
    settings: RuntimeSettings,
    coefficients: usize,
    /// Y_j(direction_s) * 4 pi / S for every shared sample direction,
    /// coefficient-major: `basis_table[j * stride + s]`.
    basis_table: Vec<f32>,
    /// Positions, normals and albedos of the probe-visible receivers.
    visible_positions: Vec<Vec3>,
    visible_normals: Vec<Vec3>,
    visible_albedos: Vec<Rgb>,
    visible_direct: Vec<Rgb>,
    /// Outgoing radiance (albedo / pi x irradiance) at probe-visible texels.
    visible_radiance: Vec<Rgb>,
    /// Probe radiance vector: `probe_radiance[(probe * 3 + channel) * C + j]`.
    probe_radiance: Vec<f32>,
    /// Light basis vectors: `light_basis[(cluster * 3 + channel) * rank + k]`.
    light_basis: Vec<f32>,
    /// The same for the radiance transport's clusters.
    radiance_light_basis: Vec<f32>,
    /// Incident radiance SH of the glossy receivers, in radiance-cluster
    /// order: `glossy_sh[slot * outputs + m]`.
    glossy_sh: Vec<Rgb>,
    /// Per atlas texel (gutters through their source), the glossy slot of
    /// its receiver, or `u32::MAX`; empty without radiance transport.
    glossy_slot_of_texel: Vec<u32>,
    /// The irradiance clusters' U rows, one per receiver, and the
    /// radiance transport's, one per output coefficient, in blocks.
    irradiance_rows: BlockedRows,
    radiance_rows: BlockedRows,
    /// (position in cluster order, probe-visible index) of every
    /// probe-visible receiver, by position, and the first pair of each
    /// cluster: reconstruction copies these receivers' irradiance into
    /// `visible_indirect` for multi-bounce feedback, which then reads it in
    /// order instead of at scattered lightmap texels.
    visible_in_cluster_order: Vec<[u32; 2]>,
    visible_cluster_starts: Vec<u32>,
    /// Indirect irradiance at the probe-visible receivers that the next
    /// bounce reflects: the last reconstruction's, or the last gather's
    /// where the receiver gathers and `gather_feedback` is on.
    visible_indirect: Vec<Rgb>,
    /// Receiver-order copy of the lightmap, gathered within the timed
    /// update: what an engine reads each frame to fill its lightmap.
    receiver_values: Vec<Rgb>,
    /// Indirect irradiance per receiver in cluster order, packed, and one
    /// zero slot after them: reconstruction writes each cluster's values
    /// in one run instead of scattering them over lightmap texels.
    irradiance: Vec<Rgb9e5>,
    /// The lightmap as a map: per atlas texel, the `irradiance` slot it
    /// shows (gutters their source's, other texels the zero slot). This is
    /// the dilation done once at load; the lightmap it stands for is
    /// identical to a dilated one, and a frame saves both the scattered
    /// texel writes and the dilation's copies.
    slot_of_texel: Vec<u32>,
    /// Per receiver, its own `irradiance` slot. A hidden receiver's texel
    /// shows a seen neighbour's slot ([`Atlas::fill_hidden`]), so a
    /// receiver's value is never addressed through its texel.
    ///
    /// [`Atlas::fill_hidden`]: relight_scene::atlas::Atlas::fill_hidden
    slot_of_receiver: Vec<u32>,
    timings: StageTimings,
    /// What the last update read, to skip a frame that repeats it.
    last_frame: LastFrame,
    /// Round-robin position of staggered updates.
    next_probe: usize,
    /// Probes refreshed this frame, and the texels they read.
    refreshing: Vec<u32>,
    needed: Vec<u32>,
    needed_stamp: Vec<u32>,
    stamp: u32,
    gathered_positions: Vec<Vec3>,
    gathered_normals: Vec<Vec3>,
    gathered_direct: Vec<Rgb>,
    /// The static direct light (environment, emissive triangles) of every
    /// visible texel, and of this frame's needed texels.
    visible_static: relight_trace::direct::StaticDirect,
    /// Each probe-visible texel's footprint (m^2): its direct light is
    /// that patch's mean, as a probe ray landing anywhere on it reads.
    visible_areas: Vec<f32>,
    /// Scratch: the footprints of the texels a frame needs.
    gathered_areas: Vec<f32>,
    gathered_static: Vec<Rgb>,
    updates: u64,
    /// The passes since the lights last changed, each update one; the
    /// light is settled when they say another adds too little to see.
    resting: SettlingPasses,
    /// Probes relit since the lights last changed.
    relit_at_rest: usize,
    settled: bool,
    /// The last frame's lights and the fixed rays that answer points in
    /// space from the light leaving the surfaces around them.
    lights: Vec<Light>,
    space_gather: SurfaceGather,
    /// Traced near field of the receivers close to other geometry; its
    /// values overwrite their lightmap slots after reconstruction.
    final_gather: FinalGather,
    /// (gathering row, probe-visible index) of every gathering receiver
    /// that probes see: the gather's values overwrite its feedback.
    gathered_visible: Vec<[u32; 2]>,
}

/// Puts the probe-visible receivers (the texels whose direct light every
/// frame computes) in Morton order of their positions instead of the
/// bake's ascending receiver order, which is lightmap scan-line order and
/// hops between charts every few texels; the sample tables are renumbered
/// to match. Shadow rays in this order share occluders and BVH nodes.
fn order_visible_receivers_spatially(bake: &mut SrpBake, positions: &[Vec3]) {
    let visible_positions: Vec<Vec3> = bake
        .visible_receivers
        .iter()
        .map(|&receiver| positions[receiver as usize])
        .collect();
    let order = relight_trace::direct::morton_order(&visible_positions);
    let mut new_index_of = vec![0u32; order.len()];
    for (new_index, &old_index) in order.iter().enumerate() {
        new_index_of[old_index as usize] = new_index as u32;
    }
    bake.visible_receivers = order
        .iter()
        .map(|&old_index| bake.visible_receivers[old_index as usize])
        .collect();
    for target in &mut bake.sample_targets {
        if *target < BACK_FACE {
            *target = new_index_of[*target as usize];
        }
    }
}

impl Srp {
    pub fn new(context: Arc<SceneContext>, mut bake: SrpBake, settings: RuntimeSettings) -> Self {
        order_visible_receivers_spatially(&mut bake, &context.atlas.receivers.positions);
        let irradiance_rows = BlockedRows::new(&mut bake.clusters, 1);
        let outputs = bake.radiance.outputs();
        let radiance_rows = BlockedRows::new(&mut bake.radiance.clusters, outputs);
        let coefficients = bake.coefficients();
        let samples = bake.sample_directions.len();
        let weight = 4.0 * PI / samples.max(1) as f32;
        let stride = kernels::basis_stride(samples);
        let mut basis_table = vec![0.0f32; coefficients * stride];
        let mut values = vec![0.0f32; coefficients];
        for (sample, direction) in bake.sample_directions.iter().enumerate() {
            sh::evaluate(*direction, bake.bands, &mut values);
            for (j, value) in values.iter().enumerate() {
                basis_table[j * stride + sample] = value * weight;
            }
        }
        let receivers = &context.atlas.receivers;
        let visible = &bake.visible_receivers;
        let pick = |values: &[Vec3]| -> Vec<Vec3> {
            visible.iter().map(|&r| values[r as usize]).collect()
        };
        let visible_positions = pick(&receivers.positions);
        let visible_normals = pick(&receivers.normals);
        let visible_albedos = pick(&receivers.albedos);
        let visible_areas: Vec<f32> = visible
            .iter()
            .map(|&r| context.atlas.texel_area(receivers.triangles[r as usize]))
            .collect();
        let probe_count = bake.probes.len();
        // The zero slot past the receivers is where texels showing none
        // read.
        let slot_of_receiver = receiver_slots(
            &bake.clusters.receivers,
            bake.receiver_count,
            receivers.len() as u32,
        );
        let slot_of_texel = texel_slots(&context, &slot_of_receiver, receivers.len() as u32);
        let mut visible_index_of = vec![u32::MAX; receivers.len()];
        for (index, &receiver) in visible.iter().enumerate() {
            visible_index_of[receiver as usize] = index as u32;
        }
        let visible_in_cluster_order: Vec<[u32; 2]> = bake
            .clusters
            .receivers
            .iter()
            .enumerate()
            .filter_map(|(position, &receiver)| {
                let index = *visible_index_of.get(receiver as usize)?;
                (index != u32::MAX).then_some([position as u32, index])
            })
            .collect();
        let visible_cluster_starts = bake
            .clusters
            .receiver_offsets
            .iter()
            .map(|&first| {
                visible_in_cluster_order.partition_point(|&[position, _]| position < first) as u32
            })
            .collect();
        let final_gather =
            FinalGather::build(&context, settings.final_gather, bake.probes.len(), false);
        let gathered_visible = final_gather
            .receivers()
            .iter()
            .enumerate()
            .filter_map(|(row, &receiver)| {
                let index = visible_index_of[receiver as usize];
                (index != u32::MAX).then_some([row as u32, index])
            })
            .collect();
        Self {
            basis_table,
            visible_direct: vec![Rgb::ZERO; visible.len()],
            visible_radiance: vec![Rgb::ZERO; visible.len()],
            needed_stamp: vec![0; visible.len()],
            visible_positions,
            visible_normals,
            visible_albedos,
            visible_areas,
            gathered_areas: Vec::new(),
            probe_radiance: vec![0.0; probe_count * 3 * coefficients],
            light_basis: vec![0.0; bake.clusters.cluster_count() * 3 * bake.clusters.rank],
            radiance_light_basis: vec![
                0.0;
                bake.radiance.clusters.cluster_count()
                    * 3
                    * bake.radiance.clusters.rank
            ],
            glossy_sh: vec![
                Rgb::ZERO;
                bake.radiance.clusters.receivers.len() * bake.radiance.outputs()
            ],
            glossy_slot_of_texel: glossy_slots(&context, &bake),
            irradiance_rows,
            radiance_rows,
            visible_in_cluster_order,
            visible_cluster_starts,
            visible_indirect: vec![Rgb::ZERO; visible.len()],
            receiver_values: vec![Rgb::ZERO; context.atlas.receivers.len()],
            irradiance: vec![Rgb9e5::default(); receivers.len() + 1],
            slot_of_texel,
            slot_of_receiver,
            timings: StageTimings::default(),
            last_frame: LastFrame::default(),
            next_probe: 0,
            refreshing: Vec::with_capacity(probe_count),
            needed: Vec::new(),
            stamp: 0,
            gathered_positions: Vec::new(),
            gathered_normals: Vec::new(),
            gathered_direct: Vec::new(),
            visible_static: Default::default(),
            gathered_static: Vec::new(),
            updates: 0,
            resting: SettlingPasses::default(),
            relit_at_rest: 0,
            settled: false,
            lights: Vec::new(),
            space_gather: SurfaceGather::new(settings.space_rays),
            final_gather,
            gathered_visible,
            coefficients,
            settings,
            context,
            bake,
        }
    }

    fn gathers_feed_back(&self) -> bool {
        self.settings.gather_feedback
            && self.settings.bounces > 1
            && !self.gathered_visible.is_empty()
    }

    /// The lightmap slot of receiver `index`.
    fn slot_of_receiver(&self, index: u32) -> usize {
        self.slot_of_receiver[index as usize] as usize
    }

    /// Runs the final gather over the reconstructed lightmap and writes
    /// its values into the gathering receivers' slots (hits reflect
    /// direct light alone with one bounce). `hits_lit`: this frame's hit
    /// light is computed already (an earlier pass gathered), so this is
    /// one more gather on top of it.
    ///
    /// With bounces, the gathered values also replace the reconstruction
    /// in the feedback of the probe-visible receivers that gather: the
    /// next bounce (the next pass, the next frame) starts from the
    /// corrected near field, as PIC's surfels read it. Fed the
    /// reconstruction alone, each bounce carried its near-field error
    /// into the next: a spot light aimed at the floor beside a wall, whose
    /// first bounce the probes put at 2.6 times the path tracer's in the
    /// corners, lit a bright two-room suite 1.9 times too brightly.
    fn gather_near_field(&mut self, hits_lit: bool) {
        let feeds_back = self.gathers_feed_back();
        let mut final_gather = std::mem::take(&mut self.final_gather);
        let indirect_at = |receiver| self.irradiance[self.slot_of_receiver(receiver)].to_rgb();
        let feedback = self.settings.bounces > 1;
        if hits_lit {
            final_gather.gather(indirect_at, feedback);
        } else {
            final_gather.update(&self.context, &self.lights, indirect_at, feedback);
        }
        for (&receiver, &value) in final_gather.receivers().iter().zip(final_gather.values()) {
            let slot = self.slot_of_receiver(receiver);
            self.irradiance[slot] = Rgb9e5::from_rgb(value);
        }
        if feeds_back {
            let values = final_gather.values();
            for &[row, index] in &self.gathered_visible {
                self.visible_indirect[index as usize] = values[row as usize];
            }
        }
        self.final_gather = final_gather;
    }

    /// Unpacks the lightmap into [`Self::receiver_values`], in receiver
    /// order.
    fn gather_receiver_values(&mut self) {
        let (irradiance, slot_of_receiver) = (&self.irradiance, &self.slot_of_receiver);
        self.receiver_values
            .par_iter_mut()
            .with_min_len(1024)
            .zip(slot_of_receiver.par_iter())
            .for_each(|(value, &slot)| *value = irradiance[slot as usize].to_rgb());
    }

    /// The probe radiance vector (lambda) after the last update.
    pub fn probe_radiance(&self) -> &[f32] {
        &self.probe_radiance
    }

    /// Whether the light is settled after an update: the first ran its
    /// passes until it was; a later one adds one bounce, and the resting
    /// scene's updates go on adding them until the visible texels' light
    /// stops changing and, under a probe budget, every probe has been
    /// relit since the lights last changed (stale probes change the light
    /// without a bounce's steady fall, which the passes could not judge).
    fn settle_at_rest(&mut self, first: bool, repeated: bool) -> bool {
        if (self.settings.bounces <= 1 && self.settings.probe_budget == 0) || first {
            return true;
        }
        if !repeated {
            self.resting = SettlingPasses::at_rest(self.settings.bounces);
            self.relit_at_rest = 0;
        }
        self.relit_at_rest += self.refreshing.len();
        let indirect = &self.visible_indirect;
        let bounces_add = self.settings.bounces > 1
            && self.resting.another_pass(|values: &mut Vec<f32>| {
                values.extend(indirect.iter().map(|&value| relight_core::luminance(value)))
            });
        !bounces_add && self.relit_at_rest >= self.bake.probes.len()
    }

    /// Chooses this frame's probes and the probe-visible texels they read.
    fn select_probes(&mut self) {
        let probe_count = self.bake.probes.len();
        self.refreshing.clear();
        let budget = self.settings.probe_budget as usize;
        // The first update refreshes everything: there is nothing stale to
        // keep.
        if budget == 0 || budget >= probe_count || self.updates == 0 {
            self.refreshing.extend(0..probe_count as u32);
            self.needed.clear();
            self.needed
                .extend(0..self.bake.visible_receivers.len() as u32);
            return;
        }
        for offset in 0..budget {
            self.refreshing
                .push(((self.next_probe + offset) % probe_count) as u32);
        }
        self.next_probe = (self.next_probe + budget) % probe_count;
        self.stamp = self.stamp.wrapping_add(1);
        if self.stamp == 0 {
            self.needed_stamp.fill(0);
            self.stamp = 1;
        }
        self.needed.clear();
        let samples = self.bake.sample_directions.len();
        for &probe in &self.refreshing {
            let targets =
                &self.bake.sample_targets[probe as usize * samples..(probe as usize + 1) * samples];
            for &target in targets {
                if target < BACK_FACE && self.needed_stamp[target as usize] != self.stamp {
                    self.needed_stamp[target as usize] = self.stamp;
                    self.needed.push(target);
                }
            }
        }
    }

    /// Direct irradiance at the needed texels.
    fn direct_light(&mut self, frame: &Frame) {
        let direct = self.context.direct();
        if self.needed.len() == self.visible_positions.len() {
            self.visible_static.irradiance_batch_over_footprints(
                &direct,
                frame.lights,
                &self.visible_positions,
                &self.visible_normals,
                Footprints::Each(&self.visible_areas),
                &mut self.visible_direct,
            );
            return;
        }
        // The static light is traced once for every visible texel (by
        // texel index, so a texel keeps its samples whichever texels a
        // frame needs).
        let visible_static =
            self.visible_static
                .at(&direct, &self.visible_positions, &self.visible_normals);
        self.gathered_positions.clear();
        self.gathered_normals.clear();
        self.gathered_static.clear();
        self.gathered_areas.clear();
        for &texel in &self.needed {
            self.gathered_areas.push(self.visible_areas[texel as usize]);
            self.gathered_positions
                .push(self.visible_positions[texel as usize]);
            self.gathered_normals
                .push(self.visible_normals[texel as usize]);
            if let Some(fixed) = visible_static {
                self.gathered_static.push(fixed[texel as usize]);
            }
        }
        self.gathered_direct.clear();
        self.gathered_direct.resize(self.needed.len(), Rgb::ZERO);
        direct.irradiance_batch_over_footprints(
            frame.lights,
            &self.gathered_positions,
            &self.gathered_normals,
            Footprints::Each(&self.gathered_areas),
            visible_static.map(|_| self.gathered_static.as_slice()),
            &mut self.gathered_direct,
        );
        for (&texel, &value) in self.needed.iter().zip(&self.gathered_direct) {
            self.visible_direct[texel as usize] = value;
        }
    }

    /// Radiance leaving the needed texels, with last frame's indirect light
    /// when bounces feed back.
    fn texel_radiance(&mut self) {
        let feedback = self.settings.bounces > 1;
        let output = kernels::DisjointWriter::new(&mut self.visible_radiance);
        let (direct, albedos) = (&self.visible_direct, &self.visible_albedos);
        let indirect = &self.visible_indirect;
        self.needed.par_chunks(4096).for_each(|needed| {
            for &visible in needed {
                let visible = visible as usize;
                let mut irradiance = direct[visible];
                if feedback {
                    irradiance += indirect[visible];
                }
                // SAFETY: `needed` lists each texel once.
                unsafe { output.write(visible, albedos[visible] * irradiance * FRAC_1_PI) };
            }
        });
    }

    /// Equation 5.1 over the shared sample directions for this frame's
    /// probes.
    fn project_probes(&mut self) {
        let coefficients = self.coefficients;
        let samples = self.bake.sample_directions.len();
        let targets = &self.bake.sample_targets;
        let radiance = &self.visible_radiance;
        let basis = &self.basis_table;
        let refreshing = &self.refreshing;
        let all = refreshing.len() == self.bake.probes.len();
        let project = |probe: usize, gathered: &mut Vec<f32>, out: &mut [f32]| {
            kernels::project_probe(
                &targets[probe * samples..(probe + 1) * samples],
                radiance,
                basis,
                coefficients,
                gathered,
                out,
            );
        };
        if all {
            self.probe_radiance
                .par_chunks_mut(3 * coefficients)
                .enumerate()
                .for_each_init(Vec::new, |gathered, (probe, out)| {
                    project(probe, gathered, out)
                });
        } else {
            let output = kernels::DisjointWriter::new(&mut self.probe_radiance);
            refreshing
                .par_iter()
                .for_each_init(Vec::new, |gathered, &probe| {
                    let mut values = [0.0f32; 3 * sh::MAX_BANDS * sh::MAX_BANDS];
                    let values = &mut values[..3 * coefficients];
                    project(probe as usize, gathered, values);
                    let start = probe as usize * 3 * coefficients;
                    for (offset, value) in values.iter().enumerate() {
                        // SAFETY: each refreshed probe appears once in the list
                        // and owns its own 3 x C values.
                        unsafe { output.write(start + offset, *value) };
                    }
                });
        }
    }

    /// Light basis vector of every cluster: Sigma_c V^T times the probe
    /// radiance of the cluster's probes (section 4.5.2).
    fn project_clusters(&mut self) {
        project_cluster_set(
            &self.bake.clusters,
            &self.probe_radiance,
            self.coefficients,
            &mut self.light_basis,
        );
    }

    /// Incident radiance SH of every glossy receiver: the radiance
    /// clusters' light basis, then U_c times it per output coefficient.
    fn transport_radiance(&mut self) {
        let bake = &self.bake;
        let radiance = &bake.radiance;
        let clusters = &radiance.clusters;
        project_cluster_set(
            clusters,
            &self.probe_radiance,
            self.coefficients,
            &mut self.radiance_light_basis,
        );
        let glossy_sh = kernels::DisjointWriter::new(&mut self.glossy_sh);
        self.radiance_rows
            .reconstruct_each(&self.radiance_light_basis, None, |_, rows, values| {
                for (row, value) in rows.zip(values) {
                    // SAFETY: clusters own disjoint row ranges.
                    unsafe { glossy_sh.write(row, *value) };
                }
            });
    }

    /// Glossy reflection from the radiance transport: the incident radiance
    /// SH of the texels around the point, bilinearly weighted, convolved
    /// with `band_factors` and evaluated in `direction`. `None` where no
    /// surrounding texel has radiance transport.
    fn transported_glossy(
        &self,
        point: &SurfacePoint,
        direction: Vec3,
        band_factors: &[f32; sh::MAX_BANDS],
    ) -> Option<Rgb> {
        let radiance = &self.bake.radiance;
        if radiance.bands == 0 {
            return None;
        }
        let outputs = radiance.outputs();
        let mut filtered = [0.0f32; sh::MAX_BANDS * sh::MAX_BANDS];
        sh::evaluate_filtered(
            direction,
            radiance.bands,
            band_factors,
            &mut filtered[..outputs],
        );
        let (mut sum, mut total) = (Rgb::ZERO, 0.0f32);
        for (texel, weight) in self
            .context
            .atlas
            .bilinear_texels(point.triangle, point.barycentric)
        {
            let slot = self.glossy_slot_of_texel[texel];
            if slot == u32::MAX || weight <= 0.0 {
                continue;
            }
            let values = &self.glossy_sh[slot as usize * outputs..][..outputs];
            let radiance = values
                .iter()
                .zip(&filtered[..outputs])
                .fold(Rgb::ZERO, |radiance, (value, basis)| {
                    radiance + *value * *basis
                });
            sum += weight * radiance;
            total += weight;
        }
        (total > 0.0).then(|| (sum / total).max(Rgb::ZERO))
    }

    /// Irradiance per receiver: U_c times the cluster's light basis,
    /// packed in cluster order.
    fn reconstruct(&mut self) {
        let visible_indirect = kernels::DisjointWriter::new(&mut self.visible_indirect);
        let (visible_pairs, visible_starts) =
            (&self.visible_in_cluster_order, &self.visible_cluster_starts);
        let receivers = self.irradiance.len() - 1;
        self.irradiance_rows.reconstruct_each(
            &self.light_basis,
            Some(&mut self.irradiance[..receivers]),
            |cluster, rows, values| {
                let first = rows.start;
                let pairs = visible_starts[cluster] as usize..visible_starts[cluster + 1] as usize;
                for &[position, index] in &visible_pairs[pairs] {
                    let value = values[position as usize - first].max(Rgb::ZERO);
                    // SAFETY: each probe-visible receiver has one position in
                    // cluster order, so one pair writes each index.
                    unsafe { visible_indirect.write(index as usize, value) };
                }
            },
        );
    }

    /// The probes' radiance field at `position`, convolved per band with
    /// `band_factors` and evaluated in `direction`: probes weighted by
    /// equation 4.4 within the cut-off radius and by whether the point sees
    /// them, or the nearest probe when none qualifies. One pass over the
    /// probes, nothing allocated: renderers call this per pixel.
    fn blend_probes(
        &self,
        position: Vec3,
        normal: Vec3,
        direction: Vec3,
        bands: usize,
        band_factors: &[f32; sh::MAX_BANDS],
    ) -> Rgb {
        let bands = bands.min(self.bake.bands);
        let count = sh::coefficient_count(bands);
        let mut filtered = [0.0f32; sh::MAX_BANDS * sh::MAX_BANDS];
        sh::evaluate_filtered(direction, bands, band_factors, &mut filtered[..count]);
        let radiance_of = |probe: usize| {
            let mut radiance = Rgb::ZERO;
            for channel in 0..3 {
                let start = (probe * 3 + channel) * self.coefficients;
                radiance[channel] = self.probe_radiance[start..start + count]
                    .iter()
                    .zip(&filtered[..count])
                    .map(|(value, basis)| value * basis)
                    .sum();
            }
            radiance
        };
        let epsilon = relight_trace::direct::ray_epsilon_for(&self.context.bvh);
        let origin = position + normal * epsilon;
        let radius = self.bake.radius;
        let (mut sum, mut total) = (Rgb::ZERO, 0.0f32);
        let mut nearest: Option<(usize, f32)> = None;
        for (index, &probe) in self.bake.probes.iter().enumerate() {
            let distance = probe.distance(position);
            if distance < radius {
                let weight = falloff_weight(distance / radius);
                let ray = Ray {
                    origin,
                    direction: probe - origin,
                    t_max: 1.0,
                };
                if weight > 0.0 && !self.context.bvh.occluded(&ray) {
                    sum += radiance_of(index) * weight;
                    total += weight;
                }
            }
            if nearest.is_none_or(|(_, best)| distance < best) {
                nearest = Some((index, distance));
            }
        }
        if total == 0.0 {
            return nearest.map_or(Rgb::ZERO, |(index, _)| radiance_of(index).max(Rgb::ZERO));
        }
        (sum / total).max(Rgb::ZERO)
    }
}

/// A cluster set's U rows, regrouped at load into blocks of
/// [`kernels::BLOCK_ROWS`] rows of one cluster (the layout
/// `kernels::reconstruct_blocks` reads), each cluster's last block padded
/// with zero rows.
#[derive(Default)]
struct BlockedRows {
    weights: Vec<u16>,
    rank: usize,
    /// First block of each cluster, then the block count.
    block_starts: Vec<u32>,
    /// First row of each cluster, then the row count.
    row_starts: Vec<u32>,
}

impl BlockedRows {
    /// Takes `clusters`' U rows (`rows_per_receiver` a receiver, in cluster
    /// order), leaving the set's copy empty so they are not held twice.
    fn new(clusters: &mut ClusterSet, rows_per_receiver: usize) -> Self {
        let rank = clusters.rank;
        let rows = std::mem::take(&mut clusters.reconstruction);
        let row_starts: Vec<u32> = clusters
            .receiver_offsets
            .iter()
            .map(|&offset| offset * rows_per_receiver as u32)
            .collect();
        if row_starts.is_empty() {
            // No clusters (no radiance transport): nothing to hold.
            return Self {
                rank,
                ..Self::default()
            };
        }
        let mut block_starts = Vec::with_capacity(row_starts.len());
        block_starts.push(0u32);
        for pair in row_starts.windows(2) {
            let blocks = ((pair[1] - pair[0]) as usize).div_ceil(kernels::BLOCK_ROWS);
            block_starts.push(block_starts[block_starts.len() - 1] + blocks as u32);
        }
        let block_count = block_starts[block_starts.len() - 1] as usize;
        let mut weights = vec![0u16; block_count * rank * kernels::BLOCK_ROWS];
        for (pair, &first_block) in row_starts.windows(2).zip(&block_starts) {
            for row in pair[0] as usize..pair[1] as usize {
                let local = row - pair[0] as usize;
                let block = first_block as usize + local / kernels::BLOCK_ROWS;
                let lane = local % kernels::BLOCK_ROWS;
                for (k, &weight) in rows[row * rank..(row + 1) * rank].iter().enumerate() {
                    weights[(block * rank + k) * kernels::BLOCK_ROWS + lane] = weight;
                }
            }
        }
        Self {
            weights,
            rank,
            block_starts,
            row_starts,
        }
    }

    fn bytes(&self) -> usize {
        self.weights.len() * 2 + (self.block_starts.len() + self.row_starts.len()) * 4
    }

    /// U_c times each cluster's light basis (`light_basis[(cluster * 3 +
    /// channel) * rank + k]`), clusters in parallel; `deliver` gets each
    /// cluster's index, row range and values. With `packed`, every value
    /// also lands there packed, at its row.
    fn reconstruct_each(
        &self,
        light_basis: &[f32],
        packed: Option<&mut [Rgb9e5]>,
        deliver: impl Fn(usize, std::ops::Range<usize>, &[Rgb]) + Sync,
    ) {
        let rank = self.rank;
        let clusters = self.row_starts.len().saturating_sub(1);
        let rows_total = self.row_starts.last().copied().unwrap_or(0) as usize;
        let packed = packed.map(|packed| {
            assert_eq!(packed.len(), rows_total);
            kernels::DisjointWriter::new(packed)
        });
        (0..clusters)
            .into_par_iter()
            .for_each_init(Vec::new, |values, cluster| {
                let rows = self.row_starts[cluster] as usize..self.row_starts[cluster + 1] as usize;
                let blocks =
                    self.block_starts[cluster] as usize..self.block_starts[cluster + 1] as usize;
                values.clear();
                values.resize(rows.len(), Rgb::ZERO);
                let packed_rows = match &packed {
                    // SAFETY: clusters own disjoint row ranges.
                    Some(packed) => unsafe { packed.slice(rows.clone()) },
                    None => &mut [],
                };
                kernels::reconstruct_blocks(
                    &self.weights[blocks.start * rank * kernels::BLOCK_ROWS
                        ..blocks.end * rank * kernels::BLOCK_ROWS],
                    &light_basis[cluster * 3 * rank..(cluster + 1) * 3 * rank],
                    rank,
                    values,
                    packed_rows,
                );
                deliver(cluster, rows, values);
            });
    }
}

/// Sigma_c V^T times the probe radiance of each cluster's probes, for one
/// set of clusters (the irradiance's or the radiance's), into
/// `light_basis[(cluster * 3 + channel) * rank + k]`.
fn project_cluster_set(
    clusters: &ClusterSet,
    probe_radiance: &[f32],
    coefficients: usize,
    light_basis: &mut [f32],
) {
    let rank = clusters.rank;
    let (probe_offsets, projection) = (&clusters.probe_offsets, &clusters.projection);
    light_basis
        .par_chunks_mut(3 * rank)
        .enumerate()
        .for_each_init(Vec::new, |gathered, (cluster, out)| {
            let probes = &clusters.probes
                [probe_offsets[cluster] as usize..probe_offsets[cluster + 1] as usize];
            let width = probes.len() * coefficients;
            // Channel-major copy of the cluster's probe radiance, so each
            // projection row is three contiguous dot products.
            gathered.clear();
            gathered.resize(3 * width, 0.0f32);
            for (slot, &probe) in probes.iter().enumerate() {
                for channel in 0..3 {
                    let source = (probe as usize * 3 + channel) * coefficients;
                    let target = channel * width + slot * coefficients;
                    gathered[target..target + coefficients]
                        .copy_from_slice(&probe_radiance[source..source + coefficients]);
                }
            }
            let start = probe_offsets[cluster] as usize * coefficients * rank;
            let matrix = &projection[start..start + rank * width];
            kernels::project_cluster(matrix, gathered, width, rank, out);
        });
}

/// Per atlas texel, the slot of its receiver in the radiance transport
/// (gutter texels through the texel they copy), or `u32::MAX`.
fn glossy_slots(context: &SceneContext, bake: &SrpBake) -> Vec<u32> {
    let radiance = &bake.radiance;
    if radiance.bands == 0 {
        return Vec::new();
    }
    let slot_of_receiver =
        receiver_slots(&radiance.clusters.receivers, bake.receiver_count, u32::MAX);
    texel_slots(context, &slot_of_receiver, u32::MAX)
}

/// Per receiver, its position in `ordered_receivers`, or `missing`.
fn receiver_slots(ordered_receivers: &[u32], receiver_count: usize, missing: u32) -> Vec<u32> {
    let mut slot_of_receiver = vec![missing; receiver_count];
    for (slot, &receiver) in ordered_receivers.iter().enumerate() {
        slot_of_receiver[receiver as usize] = slot as u32;
    }
    slot_of_receiver
}

/// Per atlas texel, the slot of the receiver it shows (hidden and gutter
/// texels through the texel they copy), or `missing` where there is none.
fn texel_slots(context: &SceneContext, slot_of_receiver: &[u32], missing: u32) -> Vec<u32> {
    context
        .atlas
        .dilated_receiver_of_texel()
        .into_iter()
        .map(|receiver| {
            slot_of_receiver
                .get(receiver as usize)
                .copied()
                .unwrap_or(missing)
        })
        .collect()
}

impl Technique for Srp {
    fn name(&self) -> &'static str {
        "srp"
    }

    fn indirect_bounces(&self) -> Option<u32> {
        (self.settings.bounces == 1).then_some(1)
    }

    fn update(&mut self, frame: &Frame) -> Result<(), TechniqueError> {
        let start = std::time::Instant::now();
        let repeated = self.last_frame.repeats(frame, FrameReads::default());
        if repeated && self.settled() {
            self.timings.skip(start);
            return Ok(());
        }
        let first = self.updates == 0;
        let mut timings = std::mem::take(&mut self.timings);
        timings.clear();
        self.lights.clear();
        self.lights.extend_from_slice(frame.lights);
        timings.time("direct lightmap", || {
            self.select_probes();
            self.direct_light(frame);
        });
        let mut settling = SettlingPasses::for_update(self.settings.bounces, first);
        let gathers_feed_back = self.gathers_feed_back();
        let mut hits_lit = false;
        let mut gather_in_passes = std::time::Duration::ZERO;
        loop {
            timings.time("probe projection", || {
                self.texel_radiance();
                self.project_probes();
            });
            timings.time("cluster projection", || self.project_clusters());
            timings.time("reconstruction", || self.reconstruct());
            let indirect = &self.visible_indirect;
            let measure = |values: &mut Vec<f32>| {
                values.extend(indirect.iter().map(|&value| relight_core::luminance(value)))
            };
            if !settling.another_pass(measure) {
                break;
            }
            if gathers_feed_back {
                // The next pass's bounce starts from the gathered near
                // field, one gather a pass: the gather's first-frame
                // gathers, all in one pass, add bounces at once, and the
                // settling, which reads each pass's added light as a
                // geometric series, stopped a bright room (generated
                // variant 33, albedo 0.76) after 3 passes at 0.94x of its
                // light, where 15 passes settle it.
                let start = std::time::Instant::now();
                if !hits_lit {
                    self.final_gather.light_hits(&self.context, &self.lights);
                    hits_lit = true;
                }
                self.gather_near_field(hits_lit);
                gather_in_passes += start.elapsed();
            }
            self.needed.clear();
            self.needed
                .extend(0..self.bake.visible_receivers.len() as u32);
        }
        timings.feedback_passes = settling.feedback_passes();
        if self.bake.radiance.bands > 0 {
            timings.time("radiance transport", || self.transport_radiance());
        }
        if !self.final_gather.is_empty() {
            let start = std::time::Instant::now();
            self.gather_near_field(hits_lit);
            self.final_gather
                .push_stages(&mut timings, start.elapsed() + gather_in_passes);
        }
        timings.time("receiver values", || self.gather_receiver_values());
        self.timings = timings;
        self.updates += 1;
        self.settled = self.settle_at_rest(first, repeated);
        Ok(())
    }

    fn settled(&self) -> bool {
        // Under `update_budget` the gather's parts still to refresh change
        // the light too.
        self.settled && self.final_gather.refreshed()
    }

    fn forget_last_frame(&mut self) {
        self.last_frame.forget();
    }

    fn indirect_irradiance(&self, point: &SurfacePoint) -> Rgb {
        self.context.atlas.sample_packed(
            |texel| self.irradiance[self.slot_of_texel[texel] as usize],
            point.triangle,
            point.barycentric,
        )
    }

    /// The light leaving the surfaces around the point, gathered over
    /// fixed rays: each hit reflects its direct light plus the lightmap's
    /// indirect light there (none with `bounces = 1`, so the answer has the
    /// lightmap's bounce count). Blending the probes instead has neither
    /// parallax nor visibility between probe and point: 30 % relRMSE on
    /// the two-rooms grid of points in space against the gather's 6 %.
    fn indirect_irradiance_in_space(&self, position: Vec3, normal: Vec3) -> Rgb {
        let single_bounce = self.settings.bounces <= 1;
        self.space_gather
            .irradiance(&self.context, &self.lights, position, normal, |point| {
                if single_bounce {
                    Rgb::ZERO
                } else {
                    self.indirect_irradiance(point)
                }
            })
    }

    /// Glossy reflection of the probes' radiance: the interpolated probe SH
    /// convolved with the normalised Phong lobe around the mirror direction
    /// (up to 5 bands, the paper's order-4 limit), times `specular`.
    fn glossy_radiance(
        &self,
        point: &SurfacePoint,
        toward_viewer: Vec3,
        exponent: f32,
    ) -> Option<Rgb> {
        if self.settings.specular <= 0.0 || exponent <= 1.0 {
            return None;
        }
        let reflected = (-toward_viewer).reflect(point.normal).normalize_or_zero();
        let lobe = sh::phong_band_factors(exponent);
        if let Some(radiance) = self.transported_glossy(point, reflected, &lobe) {
            return Some(radiance * self.settings.specular);
        }
        Some(
            self.blend_probes(point.position, point.normal, reflected, 5, &lobe)
                * self.settings.specular,
        )
    }

    fn receiver_irradiance(&self) -> Option<&[Rgb]> {
        Some(&self.receiver_values)
    }

    fn bake_facts(&self) -> Vec<(&'static str, String)> {
        let bake = &self.bake;
        let stats = &bake.stats;
        vec![
            (
                "srp probes",
                format!(
                    "{} ({} added for coverage, {} inside geometry), order {}, {} samples each",
                    bake.probes.len(),
                    stats.added_for_coverage,
                    stats.probes_inside_geometry,
                    bake.bands - 1,
                    bake.sample_directions.len()
                ),
            ),
            (
                "srp coverage",
                format!(
                    "radius {:.3} m; {} of the {} receivers that see geometry see fewer than {} probes \
                     ({} see only the environment and need none); {:.2} probes per receiver",
                    bake.radius,
                    stats.receivers_short_of_probes,
                    bake.receiver_count - stats.open_receivers as usize,
                    stats.min_probes,
                    stats.open_receivers,
                    stats.mean_nearby
                ),
            ),
            (
                "srp transport",
                format!(
                    "{:.1} % valid samples; {} clusters, {} vectors each, {:.2} % of the energy kept",
                    stats.valid_sample_fraction * 100.0,
                    bake.clusters.cluster_count(),
                    bake.clusters.rank,
                    stats.captured_energy * 100.0
                ),
            ),
            (
                "srp radiance transport",
                if bake.radiance.bands == 0 {
                    "off (glossy reflection blends the probes)".to_string()
                } else {
                    format!(
                        "order {} for {} glossy receivers in {} clusters, {} vectors each",
                        bake.radiance.bands - 1,
                        bake.radiance.clusters.receivers.len(),
                        bake.radiance.clusters.cluster_count(),
                        bake.radiance.clusters.rank
                    )
                },
            ),
        ]
    }

    fn timings(&self) -> &StageTimings {
        &self.timings
    }

    fn memory(&self) -> Vec<MemoryEntry> {
        let bake = &self.bake;
        let mut entries = vec![
            MemoryEntry::new(
                "cluster projection matrices (f16)",
                bake.clusters.projection.len() * 2,
            ),
            MemoryEntry::new(
                "receiver reconstruction matrices (f16, blocks of 8)",
                self.irradiance_rows.bytes(),
            ),
            MemoryEntry::new(
                "cluster receiver and probe lists",
                bake.clusters.list_bytes(),
            ),
            MemoryEntry::new("probe sample tables", bake.sample_targets.len() * 4),
            MemoryEntry::new("SH basis table", self.basis_table.len() * 4),
            MemoryEntry::new(
                "probe-visible texels",
                bake.visible_receivers.len() * (4 + 12 + 12 + 12 + 12 + 12 + 4 + 4),
            ),
            MemoryEntry::new("probe radiance (lambda)", self.probe_radiance.len() * 4),
            MemoryEntry::new("light basis vectors", self.light_basis.len() * 4),
            MemoryEntry::new(
                "probe-visible feedback (cluster order)",
                self.visible_in_cluster_order.len() * 8
                    + self.visible_cluster_starts.len() * 4
                    + self.visible_indirect.len() * 12
                    + self.gathered_visible.len() * 8,
            ),
            MemoryEntry::new(
                "irradiance per receiver (RGB9E5, cluster order)",
                self.irradiance.len() * 4,
            ),
            MemoryEntry::new("lightmap slot per texel", self.slot_of_texel.len() * 4),
            MemoryEntry::new("slot per receiver", self.slot_of_receiver.len() * 4),
            MemoryEntry::new("receiver values", self.receiver_values.len() * 12),
            MemoryEntry::new(
                "radiance transport matrices and lists (f16, u32)",
                bake.radiance.clusters.matrix_bytes()
                    + self.radiance_rows.bytes()
                    + bake.radiance.clusters.list_bytes(),
            ),
            MemoryEntry::new(
                "glossy receivers' radiance SH and texel slots",
                self.glossy_sh.len() * 12
                    + self.radiance_light_basis.len() * 4
                    + self.glossy_slot_of_texel.len() * 4,
            ),
        ];
        entries.extend(self.final_gather.memory_entry());
        entries
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use half::f16;
    use relight_core::SampleStream;

    #[test]
    fn blocked_rows_reconstruct_every_row_of_its_cluster() {
        let mut rng = SampleStream::new(9, 0, 0);
        let (rank, rows_per_receiver) = (5usize, 2usize);
        // Clusters of 5, 8 and 11 receivers: partial, whole and two-block
        // (with rows_per_receiver 2: 10, 16 and 22 rows).
        let receiver_offsets = vec![0u32, 5, 13, 24];
        let rows = 24 * rows_per_receiver;
        let weights: Vec<f32> = (0..rows * rank).map(|_| rng.next_f32() - 0.5).collect();
        let mut clusters = ClusterSet {
            rank,
            receivers: (0..24).collect(),
            receiver_offsets: receiver_offsets.clone(),
            reconstruction: weights
                .iter()
                .map(|&w| f16::from_f32(w).to_bits())
                .collect(),
            ..Default::default()
        };
        let blocked = BlockedRows::new(&mut clusters, rows_per_receiver);
        assert!(
            clusters.reconstruction.is_empty(),
            "the rows are moved, not copied"
        );
        let light_basis: Vec<f32> = (0..3 * 3 * rank).map(|_| rng.next_f32() * 2.0).collect();
        let results = std::sync::Mutex::new(vec![(usize::MAX, Rgb::splat(f32::NAN)); rows]);
        let mut packed = vec![Rgb9e5(u32::MAX); rows];
        blocked.reconstruct_each(&light_basis, Some(&mut packed), |cluster, range, values| {
            assert_eq!(values.len(), range.len());
            let mut results = results.lock().unwrap();
            for (row, value) in range.zip(values) {
                results[row] = (cluster, *value);
            }
        });
        for (row, &(cluster, value)) in results.into_inner().unwrap().iter().enumerate() {
            // Every row's packed value lands at that row.
            assert_eq!(packed[row], Rgb9e5::from_rgb(value), "row {row}");
            let expected_cluster = receiver_offsets
                .partition_point(|&first| first as usize * rows_per_receiver <= row)
                - 1;
            assert_eq!(cluster, expected_cluster, "row {row}");
            for channel in 0..3 {
                let exact: f64 = (0..rank)
                    .map(|k| {
                        f16::from_f32(weights[row * rank + k]).to_f64()
                            * light_basis[(cluster * 3 + channel) * rank + k] as f64
                    })
                    .sum();
                // Five products below 1 in magnitude, summed in f32.
                assert!((value[channel] as f64 - exact).abs() < 1e-5, "row {row}");
            }
        }
    }
}
