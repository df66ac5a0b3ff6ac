//! The PRM run time: entry irradiance, cluster weights, top-K panes summed
//! into the indirect lightmap.

use crate::panes::{upsample, Upsampling};
use crate::PrmBake;
use glam::Vec3;
use half::slice::HalfFloatSliceExt;
use rayon::prelude::*;
use relight_core::{luminance, Rgb};
use relight_technique::{
    FinalGather, FinalGatherSettings, Frame, FrameReads, LastFrame, MemoryEntry, SceneContext,
    SettlingPasses, StageTimings, SurfaceGather, SurfacePoint, Technique, TechniqueError,
};
use relight_trace::direct::{DirectLight, DirectSettings, Footprints, StaticDirect};
use std::sync::Arc;

/// Receivers per work item of the lightmap sum: its f32 accumulators and one
/// converted pane slice stay in L1.
const RECEIVER_BLOCK: usize = 512;

pub struct Prm {
    context: Arc<SceneContext>,
    bake: PrmBake,
    top_k: usize,
    entry_irradiance: Vec<Rgb>,
    /// The entries' direct light that no frame changes.
    entry_static: StaticDirect,
    cluster_weights: Vec<Rgb>,
    selected: Vec<u32>,
    /// This frame's stored panes and their weights: the selected clusters,
    /// or with compression every basis pane.
    terms: Vec<(u32, Rgb)>,
    /// The panes' sum at the pane points, when they are not every receiver.
    pane_values: Vec<Rgb>,
    /// From the pane points to every receiver (empty when they are all).
    upsampling: Upsampling,
    receiver_values: Vec<Rgb>,
    /// The receiver each lightmap texel shows: shading reads
    /// `receiver_values` through it, so no frame builds a lightmap.
    shown_receiver: Vec<u32>,
    /// Per receiver, whether the final gather writes its light: once it
    /// has gathered, nothing reads the upsampled value there.
    gathered_receivers: Vec<bool>,
    timings: StageTimings,
    /// What the last update read, to skip a frame that repeats it.
    last_frame: LastFrame,
    /// The final gather's passes since the lights last changed, one an
    /// update: its hits on gathering receivers reflect the last gather,
    /// so its near field takes a few updates to settle after a change.
    resting: SettlingPasses,
    settled: bool,
    updated: bool,
    /// The direct-light settings for entry points: fewer shadow rays toward
    /// area lights than a lightmap texel gets, since a cluster's weight
    /// averages its entries.
    entry_direct: DirectSettings,
    /// The lights of the last update, for gathers at points in space.
    lights: Vec<relight_scene::Light>,
    space_gather: SurfaceGather,
    /// Traced near field of the receivers close to other geometry.
    final_gather: FinalGather,
    /// Per cluster, the factor its weight's luminance is ranked by: 1 for
    /// the paper's ranking by weight, the pane's total luminance for ranking
    /// by contribution.
    ranking_scale: Vec<f32>,
}

/// The most updates a resting scene runs for the final gather's near
/// field to settle: each carries it one bounce further, and a bounce keeps
/// at most about half the light in a white room.
const RESTING_GATHERS: u32 = 32;

/// How the top-K clusters are chosen each frame.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Selection {
    /// By weight (the entries' irradiance, averaged by their shares), as
    /// the paper does.
    Weight,
    /// By weight times the pane's total luminance: the light the cluster
    /// would add to the lightmap.
    Contribution,
}

impl Prm {
    pub fn new(
        context: Arc<SceneContext>,
        bake: PrmBake,
        top_k: u32,
        selection: Selection,
        entry_area_samples: u32,
        space_rays: u32,
        final_gather: FinalGatherSettings,
    ) -> Self {
        let ranking_scale = match selection {
            Selection::Weight => vec![1.0; bake.cluster_count],
            Selection::Contribution => {
                let stored_totals: Vec<f32> = bake
                    .panes
                    .chunks_exact(bake.pane_length() * 3)
                    .map(|pane| {
                        pane.chunks_exact(3)
                            .map(|rgb| {
                                luminance(Rgb::new(
                                    rgb[0].to_f32(),
                                    rgb[1].to_f32(),
                                    rgb[2].to_f32(),
                                ))
                            })
                            .sum()
                    })
                    .collect();
                if bake.rank == 0 {
                    stored_totals
                } else {
                    // A pane's total is linear in the pane: the same
                    // combination of the basis panes' totals.
                    bake.coefficients
                        .chunks_exact(bake.rank)
                        .map(|coefficients| {
                            coefficients
                                .iter()
                                .zip(&stored_totals)
                                .map(|(c, total)| c * total)
                                .sum()
                        })
                        .collect()
                }
            }
        };
        let top_k = if top_k == 0 {
            bake.cluster_count
        } else {
            (top_k as usize).min(bake.cluster_count)
        };
        let receivers = bake.receiver_count;
        let upsampling = Upsampling::build(
            &context,
            &bake.pane_points.receivers,
            bake.pane_points.spacing,
        );
        let pane_values = if upsampling.points.is_empty() {
            Vec::new()
        } else {
            vec![Rgb::ZERO; bake.pane_length()]
        };
        let final_gather =
            FinalGather::build(&context, final_gather, bake.entry_positions.len(), false);
        Self {
            entry_irradiance: vec![Rgb::ZERO; bake.entry_positions.len()],
            entry_static: StaticDirect::default(),
            cluster_weights: vec![Rgb::ZERO; bake.cluster_count],
            selected: Vec::with_capacity(top_k),
            terms: Vec::with_capacity(top_k.max(bake.rank)),
            entry_direct: DirectSettings {
                area_light_samples: entry_area_samples,
                ..context.settings.direct
            },
            receiver_values: vec![Rgb::ZERO; receivers],
            pane_values,
            upsampling,
            shown_receiver: context.atlas.dilated_receiver_of_texel(),
            gathered_receivers: final_gather.replaces(receivers),
            bake,
            top_k,
            timings: StageTimings::default(),
            last_frame: LastFrame::default(),
            resting: SettlingPasses::default(),
            settled: false,
            updated: false,
            lights: Vec::new(),
            space_gather: SurfaceGather::new(space_rays),
            final_gather,
            context,
            ranking_scale,
        }
    }
}

/// out[r] = sum over (pane, weight) terms of weight * pane[r], blocked over
/// pane values so each block's accumulators stay in L1.
fn sum_panes(panes: &[half::f16], receivers: usize, terms: &[(u32, Rgb)], out: &mut [Rgb]) {
    let wide = wide_kernel_available();
    out.par_chunks_mut(RECEIVER_BLOCK)
        .enumerate()
        .for_each(|(block, values)| {
            let start = block * RECEIVER_BLOCK;
            let mut accumulator = [0.0f32; RECEIVER_BLOCK * 3];
            let length = values.len() * 3;
            for &(pane_index, weight) in terms {
                // Eight RGB triples per 24 floats: a fixed weight pattern
                // lets the multiply-add run as plain SIMD lanes, not
                // strided RGB.
                let pattern: [f32; 24] = std::array::from_fn(|lane| weight[lane % 3]);
                let offset = (pane_index as usize * receivers + start) * 3;
                let pane = &panes[offset..offset + length];
                if wide {
                    // SAFETY: the CPU has AVX2, FMA and F16C (checked above).
                    unsafe { accumulate_wide(&mut accumulator[..length], pane, &pattern) }
                } else {
                    accumulate_portable(&mut accumulator[..length], pane, &pattern);
                }
            }
            for (value, triple) in values.iter_mut().zip(accumulator.chunks_exact(3)) {
                *value = Rgb::new(triple[0], triple[1], triple[2]);
            }
        });
}

fn wide_kernel_available() -> bool {
    #[cfg(target_arch = "x86_64")]
    {
        std::arch::is_x86_feature_detected!("avx2")
            && std::arch::is_x86_feature_detected!("fma")
            && std::arch::is_x86_feature_detected!("f16c")
    }
    #[cfg(not(target_arch = "x86_64"))]
    {
        false
    }
}

fn accumulate_portable(accumulator: &mut [f32], pane: &[half::f16], pattern: &[f32; 24]) {
    let mut converted = [0.0f32; 24];
    let whole = accumulator.len() / 24 * 24;
    for (lanes, source) in accumulator[..whole]
        .chunks_exact_mut(24)
        .zip(pane[..whole].chunks_exact(24))
    {
        source.convert_to_f32_slice(&mut converted);
        for lane in 0..24 {
            lanes[lane] += pattern[lane] * converted[lane];
        }
    }
    for index in whole..accumulator.len() {
        accumulator[index] += pattern[index % 3] * pane[index].to_f32();
    }
}

/// The same sum with 8-wide f16 conversion and fused multiply-add. The
/// baseline x86-64 target has neither, and this loop is the whole per-frame
/// cost once the panes are in cache.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2,fma,f16c")]
unsafe fn accumulate_wide(accumulator: &mut [f32], pane: &[half::f16], pattern: &[f32; 24]) {
    use std::arch::x86_64::*;
    debug_assert_eq!(accumulator.len(), pane.len());
    let whole = accumulator.len() / 24 * 24;
    let weights = [
        _mm256_loadu_ps(pattern.as_ptr()),
        _mm256_loadu_ps(pattern.as_ptr().add(8)),
        _mm256_loadu_ps(pattern.as_ptr().add(16)),
    ];
    let target = accumulator.as_mut_ptr();
    let source = pane.as_ptr() as *const u16;
    let mut index = 0;
    while index < whole {
        for (part, weight) in weights.iter().enumerate() {
            let at = index + part * 8;
            let halves = _mm_loadu_si128(source.add(at) as *const __m128i);
            let sum = _mm256_fmadd_ps(
                *weight,
                _mm256_cvtph_ps(halves),
                _mm256_loadu_ps(target.add(at)),
            );
            _mm256_storeu_ps(target.add(at), sum);
        }
        index += 24;
    }
    for index in whole..accumulator.len() {
        accumulator[index] += pattern[index % 3] * pane[index].to_f32();
    }
}

#[cfg(not(target_arch = "x86_64"))]
unsafe fn accumulate_wide(accumulator: &mut [f32], pane: &[half::f16], pattern: &[f32; 24]) {
    accumulate_portable(accumulator, pane, pattern)
}

impl Technique for Prm {
    fn name(&self) -> &'static str {
        "prm"
    }

    fn update(&mut self, frame: &Frame) -> Result<(), TechniqueError> {
        let start = std::time::Instant::now();
        let repeated = self.last_frame.repeats(frame, FrameReads::default());
        if repeated && self.settled() {
            self.timings.skip(start);
            return Ok(());
        }
        self.timings.clear();
        self.lights.clear();
        self.lights.extend_from_slice(frame.lights);
        let context = &self.context;
        let bake = &self.bake;
        let entry_irradiance = &mut self.entry_irradiance;
        let entry_static = &mut self.entry_static;
        let settings = self.entry_direct;
        self.timings.time("entry irradiance", || {
            let direct =
                DirectLight::new(&context.scene, &context.bvh, &context.emitters, settings);
            entry_static.irradiance_batch_over_footprints(
                &direct,
                frame.lights,
                &bake.entry_positions,
                &bake.entry_normals,
                Footprints::Each(&bake.entry_areas),
                entry_irradiance,
            );
        });
        let weights = &mut self.cluster_weights;
        let selected = &mut self.selected;
        let top_k = self.top_k;
        let scale = &self.ranking_scale;
        self.timings.time("weights and top-K", || {
            weights.fill(Rgb::ZERO);
            // The pane holds the sum over its entries, so the common weight
            // is their irradiance averaged with each entry's share of the
            // pane: exact in total light, however unevenly they are lit.
            for ((&cluster, &share), &irradiance) in bake
                .entry_clusters
                .iter()
                .zip(&bake.entry_shares)
                .zip(entry_irradiance.iter())
            {
                weights[cluster as usize] += irradiance * share;
            }
            selected.clear();
            selected.extend(0..bake.cluster_count as u32);
            // Ranking only matters when some clusters are left out.
            if top_k < bake.cluster_count {
                let rank =
                    |cluster: u32| luminance(weights[cluster as usize]) * scale[cluster as usize];
                // Strongest first; equal ranks keep index order (deterministic).
                selected.sort_by(|&a, &b| rank(b).total_cmp(&rank(a)).then(a.cmp(&b)));
                selected.truncate(top_k);
            }
            selected.retain(|&cluster| weights[cluster as usize] != Rgb::ZERO);
        });
        let receiver_values = &mut self.receiver_values;
        let pane_values = &mut self.pane_values;
        let terms = &mut self.terms;
        self.timings.time("pane sum", || {
            terms.clear();
            if bake.rank == 0 {
                terms.extend(
                    selected
                        .iter()
                        .map(|&cluster| (cluster, weights[cluster as usize])),
                );
            } else {
                // sum_k w_k P_k ~ sum_j (sum_k w_k c_kj) B_j: the selected
                // clusters fold into one weight per basis pane, so the cost
                // is rank panes whatever K is.
                terms.extend((0..bake.rank as u32).map(|basis| (basis, Rgb::ZERO)));
                for &cluster in selected.iter() {
                    let weight = weights[cluster as usize];
                    let row = &bake.coefficients
                        [cluster as usize * bake.rank..(cluster as usize + 1) * bake.rank];
                    for ((_, basis_weight), &coefficient) in terms.iter_mut().zip(row) {
                        *basis_weight += weight * coefficient;
                    }
                }
            }
            let out = if pane_values.is_empty() {
                &mut receiver_values[..]
            } else {
                &mut pane_values[..]
            };
            sum_panes(&bake.panes, bake.pane_length(), terms, out)
        });
        if !self.pane_values.is_empty() {
            let (upsampling, pane_values) = (&self.upsampling, &self.pane_values);
            // The gather's hits on gathering receivers reflect its last
            // values, so after the first gather the upsampled values there
            // would be written over unread.
            let skipped: &[bool] = if self.final_gather.has_gathered() {
                &self.gathered_receivers
            } else {
                &[]
            };
            self.timings.time("upsampling", || {
                upsample(upsampling, pane_values, skipped, receiver_values)
            });
        }
        let final_gather = &mut self.final_gather;
        if !final_gather.is_empty() {
            let start = std::time::Instant::now();
            final_gather.update(
                context,
                frame.lights,
                |receiver| receiver_values[receiver as usize],
                true,
            );
            final_gather.apply(receiver_values);
            final_gather.push_stages(&mut self.timings, start.elapsed());
        }
        // The panes answer the lights at once; the first update gathers
        // until its near field settles, a later one once.
        let first = !std::mem::replace(&mut self.updated, true);
        self.settled = first || final_gather.is_empty() || {
            if !repeated {
                self.resting = SettlingPasses::at_rest(RESTING_GATHERS);
            }
            let values = final_gather.values();
            !self.resting.another_pass(|measured: &mut Vec<f32>| {
                measured.extend(values.iter().map(|&value| luminance(value)))
            })
        };
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
        self.context.atlas.sample_receivers(
            &self.shown_receiver,
            &self.receiver_values,
            point.triangle,
            point.barycentric,
        )
    }

    fn indirect_irradiance_in_space(&self, position: Vec3, normal: Vec3) -> Rgb {
        self.space_gather
            .irradiance(&self.context, &self.lights, position, normal, |point| {
                self.indirect_irradiance(point)
            })
    }

    fn receiver_irradiance(&self) -> Option<&[Rgb]> {
        Some(&self.receiver_values)
    }

    fn timings(&self) -> &StageTimings {
        &self.timings
    }

    fn memory(&self) -> Vec<MemoryEntry> {
        let bake = &self.bake;
        let mut entries = vec![
            MemoryEntry::new(
                if bake.rank > 0 {
                    format!(
                        "{} basis panes (f16 RGB, {:.1} % of the panes' light-weighted energy)",
                        bake.rank,
                        bake.captured_energy * 100.0
                    )
                } else {
                    "panes (f16 RGB)".to_string()
                },
                bake.panes.len() * 2,
            ),
            MemoryEntry::new("compression coefficients", bake.coefficients.len() * 4),
            MemoryEntry::new(
                format!(
                    "upsampling from {} pane points ({} taps a receiver)",
                    bake.pane_length(),
                    crate::panes::TAPS
                ),
                self.upsampling.memory_bytes() + self.pane_values.len() * 12,
            ),
            MemoryEntry::new(
                "entry points",
                bake.entry_positions.len() * (12 + 12 + 4 + 12),
            ),
            MemoryEntry::new("clusters", bake.cluster_count * (12 * 4)),
            MemoryEntry::new("receiver irradiance", self.receiver_values.len() * 12),
            MemoryEntry::new("lightmap texels' receivers", self.shown_receiver.len() * 4),
        ];
        entries.extend(self.final_gather.memory_entry());
        entries
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use relight_core::SampleStream;

    /// The AVX2 kernel and the portable one add the same numbers (up to the
    /// rounding of fused multiply-add), tails included.
    #[test]
    fn wide_and_portable_pane_sums_agree() {
        if !wide_kernel_available() {
            eprintln!("no AVX2/FMA/F16C here: only the portable kernel runs");
            return;
        }
        let mut rng = SampleStream::new(5, 0, 0);
        for length in [3usize, 24, 51, 1536] {
            let pane: Vec<half::f16> = (0..length)
                .map(|_| half::f16::from_f32(rng.next_f32()))
                .collect();
            let pattern: [f32; 24] = std::array::from_fn(|lane| [0.3, 1.7, 0.9][lane % 3]);
            let start: Vec<f32> = (0..length).map(|_| rng.next_f32()).collect();
            let mut portable = start.clone();
            let mut wide = start.clone();
            accumulate_portable(&mut portable, &pane, &pattern);
            // SAFETY: checked above.
            unsafe { accumulate_wide(&mut wide, &pane, &pattern) };
            for (index, (a, b)) in portable.iter().zip(&wide).enumerate() {
                // Sums below 3 in f32: FMA differs by at most one rounding.
                assert!(
                    (a - b).abs() <= 1e-6 * a.abs().max(1.0),
                    "{length} at {index}: {a} {b}"
                );
                let expected = start[index] + pattern[index % 3] * pane[index].to_f32();
                assert!((a - expected).abs() <= 1e-6 * expected.abs().max(1.0));
            }
        }
    }
}
