//! The PRM run time: entry irradiance, cluster weights, top-K panes summed
//! into the indirect lightmap.

use crate::PrmBake;
use glam::Vec3;
use half::slice::HalfFloatSliceExt;
use rayon::prelude::*;
use relight_core::{luminance, Rgb};
use relight_technique::{
    Frame, MemoryEntry, SceneContext, StageTimings, SurfacePoint, Technique, TechniqueError,
};
use std::sync::Arc;

/// Receivers per work item of the lightmap sum: its f32 accumulators and one
/// converted pane slice stay in L1.
const RECEIVER_BLOCK: usize = 512;

pub struct Prm {
    context: Arc<SceneContext>,
    bake: PrmBake,
    top_k: usize,
    entry_irradiance: Vec<Rgb>,
    cluster_weights: Vec<Rgb>,
    selected: Vec<u32>,
    receiver_values: Vec<Rgb>,
    lightmap: Vec<Rgb>,
    timings: StageTimings,
    /// Entry points per cluster (fixed by the bake).
    cluster_sizes: Vec<u32>,
    /// Per cluster, the factor its weight's luminance is ranked by: 1 for
    /// the paper's ranking by weight, the pane's total luminance for ranking
    /// by contribution.
    ranking_scale: Vec<f32>,
}

/// How the top-K clusters are chosen each frame.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Selection {
    /// By weight (mean entry irradiance), as the paper does.
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
    ) -> Self {
        let mut cluster_sizes = vec![0u32; bake.cluster_count];
        for &cluster in &bake.entry_clusters {
            cluster_sizes[cluster as usize] += 1;
        }
        let ranking_scale = match selection {
            Selection::Weight => vec![1.0; bake.cluster_count],
            Selection::Contribution => bake
                .panes
                .chunks_exact(bake.receiver_count * 3)
                .map(|pane| {
                    pane.chunks_exact(3)
                        .map(|rgb| {
                            luminance(Rgb::new(rgb[0].to_f32(), rgb[1].to_f32(), rgb[2].to_f32()))
                        })
                        .sum()
                })
                .collect(),
        };
        let top_k = if top_k == 0 {
            bake.cluster_count
        } else {
            (top_k as usize).min(bake.cluster_count)
        };
        let receivers = bake.receiver_count;
        Self {
            entry_irradiance: vec![Rgb::ZERO; bake.entry_positions.len()],
            cluster_weights: vec![Rgb::ZERO; bake.cluster_count],
            selected: Vec::with_capacity(top_k),
            receiver_values: vec![Rgb::ZERO; receivers],
            lightmap: vec![Rgb::ZERO; (context.atlas.width * context.atlas.height) as usize],
            context,
            bake,
            top_k,
            timings: StageTimings::default(),
            cluster_sizes,
            ranking_scale,
        }
    }

    /// Clusters selected in the last update, strongest first.
    pub fn selected_clusters(&self) -> &[u32] {
        &self.selected
    }
}

/// out[r] = sum over selected clusters of weight * pane[r], blocked over
/// receivers so each block's accumulators stay in cache.
fn sum_panes(
    panes: &[half::f16],
    receivers: usize,
    selected: &[u32],
    weights: &[Rgb],
    out: &mut [Rgb],
) {
    out.par_chunks_mut(RECEIVER_BLOCK)
        .enumerate()
        .for_each(|(block, values)| {
            let start = block * RECEIVER_BLOCK;
            let mut accumulator = [0.0f32; RECEIVER_BLOCK * 3];
            let mut converted = [0.0f32; RECEIVER_BLOCK * 3];
            let length = values.len() * 3;
            for &cluster in selected {
                let weight = weights[cluster as usize];
                // Four RGB triples per 12 floats: a fixed weight pattern lets
                // the multiply-add run as plain SIMD lanes, not strided RGB.
                let pattern: [f32; 12] = std::array::from_fn(|lane| weight[lane % 3]);
                let offset = (cluster as usize * receivers + start) * 3;
                panes[offset..offset + length].convert_to_f32_slice(&mut converted[..length]);
                let whole = length / 12 * 12;
                for (lanes, source) in accumulator[..whole]
                    .chunks_exact_mut(12)
                    .zip(converted[..whole].chunks_exact(12))
                {
                    for lane in 0..12 {
                        lanes[lane] += pattern[lane] * source[lane];
                    }
                }
                for index in whole..length {
                    accumulator[index] += pattern[index % 3] * converted[index];
                }
            }
            for (value, triple) in values.iter_mut().zip(accumulator.chunks_exact(3)) {
                *value = Rgb::new(triple[0], triple[1], triple[2]);
            }
        });
}

impl Technique for Prm {
    fn name(&self) -> &'static str {
        "prm"
    }

    fn update(&mut self, frame: &Frame) -> Result<(), TechniqueError> {
        self.timings.clear();
        let context = &self.context;
        let bake = &self.bake;
        let entry_irradiance = &mut self.entry_irradiance;
        self.timings.time("entry irradiance", || {
            context.direct().irradiance_batch(
                frame.lights,
                &bake.entry_positions,
                &bake.entry_normals,
                entry_irradiance,
            );
        });
        let weights = &mut self.cluster_weights;
        let selected = &mut self.selected;
        let top_k = self.top_k;
        let (sizes, scale) = (&self.cluster_sizes, &self.ranking_scale);
        self.timings.time("weights and top-K", || {
            weights.fill(Rgb::ZERO);
            for (entry, &cluster) in bake.entry_clusters.iter().enumerate() {
                weights[cluster as usize] += entry_irradiance[entry];
            }
            // The pane holds the sum over its entries, so the common weight
            // is their mean irradiance.
            for (weight, &size) in weights.iter_mut().zip(sizes) {
                *weight /= size.max(1) as f32;
            }
            selected.clear();
            selected.extend(0..bake.cluster_count as u32);
            let rank =
                |cluster: u32| luminance(weights[cluster as usize]) * scale[cluster as usize];
            // Strongest first; equal ranks keep index order (deterministic).
            selected.sort_by(|&a, &b| rank(b).total_cmp(&rank(a)).then(a.cmp(&b)));
            selected.truncate(top_k);
            selected.retain(|&cluster| weights[cluster as usize] != Rgb::ZERO);
        });
        let receiver_values = &mut self.receiver_values;
        self.timings.time("pane sum", || {
            sum_panes(
                &bake.panes,
                bake.receiver_count,
                selected,
                weights,
                receiver_values,
            )
        });
        let lightmap = &mut self.lightmap;
        self.timings.time("dilation", || {
            context.atlas.scatter_into(receiver_values, lightmap);
        });
        Ok(())
    }

    fn indirect_irradiance(&self, point: &SurfacePoint) -> Rgb {
        self.context
            .atlas
            .sample(&self.lightmap, point.triangle, point.barycentric)
    }

    fn indirect_irradiance_in_space(&self, position: Vec3, normal: Vec3) -> Rgb {
        // One bounce from each cluster as a disc light of its entries' area,
        // without visibility: an approximation for dynamic objects.
        let mut irradiance = Rgb::ZERO;
        for cluster in 0..self.bake.cluster_count {
            let offset = self.bake.cluster_centres[cluster] - position;
            let distance_squared = offset.length_squared();
            let cosine_receiver = normal.dot(offset);
            let cosine_light = -self.bake.cluster_normals[cluster].dot(offset);
            if cosine_receiver <= 0.0 || cosine_light <= 0.0 {
                continue;
            }
            let flux = self.cluster_weights[cluster] * self.bake.cluster_reflectance_area[cluster];
            irradiance += flux
                * (cosine_receiver * cosine_light
                    / (distance_squared * (distance_squared + self.bake.disc_radius_squared))
                    * std::f32::consts::FRAC_1_PI);
        }
        irradiance
    }

    fn receiver_irradiance(&self) -> Option<&[Rgb]> {
        Some(&self.receiver_values)
    }

    fn timings(&self) -> &StageTimings {
        &self.timings
    }

    fn memory(&self) -> Vec<MemoryEntry> {
        let bake = &self.bake;
        vec![
            MemoryEntry::new("panes (f16 RGB)", bake.panes.len() * 2),
            MemoryEntry::new(
                "entry points",
                bake.entry_positions.len() * (12 + 12 + 4 + 12),
            ),
            MemoryEntry::new("clusters", bake.cluster_count * (12 * 4)),
            MemoryEntry::new("receiver irradiance", self.receiver_values.len() * 12),
            MemoryEntry::new("lightmap", self.lightmap.len() * 12),
        ]
    }
}
