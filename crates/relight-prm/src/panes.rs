//! PRM's own pane resolution: panes hold light at pane points, a subset of
//! the lightmap's receivers about one pane texel apart, and every frame the
//! pane points' light is upsampled to all receivers.
//!
//! Why: the per-frame cost is the panes streamed from memory, basis panes
//! times pane points, and a bake's shadow rays are virtual lights times
//! pane points. The light a pane carries varies over the entry points'
//! spacing (metres), not the lightmap's (centimetres); the near field,
//! which does vary at texel scale, is the final gather's, which runs at
//! every receiver after the upsampling.
//!
//! Pane points: receivers are binned by a cubic cell one pane texel wide
//! and by the direction of their normal (64 octahedral buckets), and each
//! bin's receiver nearest the bin's mean stands for it. A receiver reads
//! the [`TAPS`] nearest pane points that face its way (normals within 45
//! degrees) and that it sees, weighted by (1 - d / d_next)^2 with d_next
//! the distance of the next candidate, so a point's weight falls to zero
//! before the set of taps changes (no seams). A receiver with no such
//! point (behind a moulding, on a thin step) becomes a pane point itself,
//! so every receiver keeps light of its own side of every wall.
//!
//! Pane points stand only where someone sees
//! ([`SceneContext::is_hidden_surface_point`], lifted as far as the
//! visibility rays): a second ceiling a few centimetres above the visible
//! one shares its bins, and a pane point there gathers nothing while its
//! lifted end, past the gap, passes as visible from the room below (the
//! classroom's ceiling, speckled black). A hidden receiver reads the
//! visible points it sees, or none and stays dark, as the path tracer has
//! it.

use glam::{IVec3, Vec3};
use rayon::prelude::*;
use relight_core::colour::octahedral_encode;
use relight_scene::atlas::Receivers;
use relight_technique::SceneContext;
use relight_trace::Ray;
use std::collections::HashMap;

/// Pane points each receiver blends.
pub const TAPS: usize = 4;

/// Candidates tested for visibility per receiver, nearest first.
const CANDIDATES: usize = 12;

/// Pane points read by a receiver face within 45 degrees of its normal.
const FACING_COS: f32 = 0.707;

/// Candidates lie within this many pane texels.
const REACH_TEXELS: f32 = 2.0;

/// Visibility rays start and end this fraction of a pane texel off the
/// surface along each end's normal, so that a chord across a convex
/// column (sagitta 2 cm for a 0.3 m column over 40 degrees) or over a
/// tessellated floor is not taken for a wall.
const LIFT_TEXELS: f32 = 0.1;

/// How far visibility rays between receivers and pane points start off
/// the surface.
pub fn visibility_lift(context: &SceneContext, spacing: f32) -> f32 {
    (spacing * LIFT_TEXELS).max(relight_trace::direct::ray_epsilon_for(&context.bvh))
}

/// Rounds in which receivers without a visible pane point add points.
const COVERAGE_ROUNDS: usize = 3;

/// The pane points and each receiver's taps.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct PanePoints {
    /// Receiver index of each pane point, ascending; empty: every receiver
    /// is a pane point and there is nothing to upsample.
    pub receivers: Vec<u32>,
    /// Metres between them, which sets how far a receiver's taps reach.
    pub spacing: f32,
}

impl PanePoints {
    /// Every receiver is a pane point.
    pub fn every_receiver() -> Self {
        Self::default()
    }

    pub fn is_every_receiver(&self) -> bool {
        self.receivers.is_empty()
    }

    /// Pane values per pane: the pane points, or every receiver.
    pub fn count(&self, receiver_count: usize) -> usize {
        if self.is_every_receiver() {
            receiver_count
        } else {
            self.receivers.len()
        }
    }

    /// Distinct receivers below `receiver_count`, ascending (what a bake
    /// file must hold).
    pub fn is_valid(&self, receiver_count: usize) -> bool {
        self.receivers.windows(2).all(|pair| pair[0] < pair[1])
            && self
                .receivers
                .last()
                .is_none_or(|&last| (last as usize) < receiver_count)
    }

    /// Chooses pane points `spacing` metres apart; a spacing at or below
    /// the lightmap's texel keeps every receiver.
    pub fn select(context: &SceneContext, spacing: f32) -> Self {
        let receivers = &context.atlas.receivers;
        if spacing.is_nan() || spacing <= context.atlas.metres_per_texel || receivers.is_empty() {
            return Self::every_receiver();
        }
        // A bin's representative is a receiver someone sees: a second
        // ceiling just above the visible one shares its bins, and half of
        // them would otherwise stand on the hidden layer.
        let lift = visibility_lift(context, spacing);
        let seen: Vec<u32> = (0..receivers.len() as u32)
            .into_par_iter()
            .filter(|&receiver| {
                let index = receiver as usize;
                !context.is_hidden_surface_point(
                    receivers.positions[index],
                    receivers.normals[index],
                    lift,
                )
            })
            .collect();
        // Hidden receivers need no pane point of their own: they read the
        // visible points they see, and one enclosed by geometry reads
        // none, dark as the path tracer has it (each would otherwise
        // become a pane point: 2.5x the classroom's panes).
        let mut points = bin_representatives(receivers, &seen, spacing);
        let mut uncovered = seen;
        for round in 0..=COVERAGE_ROUNDS {
            // Points only ever add candidates, so a covered receiver stays
            // covered: each round tests the ones the last left uncovered.
            let taps = Upsampling::build_for(context, &points, spacing, &uncovered, false);
            uncovered = uncovered
                .iter()
                .zip(&taps.weights)
                .filter(|(_, weights)| weights[0] == 0)
                .map(|(&receiver, _)| receiver)
                .collect();
            if uncovered.is_empty() {
                break;
            }
            // The last round takes every receiver still without light.
            let added = if round == COVERAGE_ROUNDS {
                std::mem::take(&mut uncovered)
            } else {
                bin_representatives(receivers, &uncovered, spacing)
            };
            points.extend(added);
            points.sort_unstable();
            points.dedup();
        }
        Self {
            receivers: points,
            spacing,
        }
    }
}

/// The cell and normal bucket of a receiver.
fn bin_key(position: Vec3, normal: Vec3, spacing: f32) -> (IVec3, u16) {
    let cell = (position / spacing).floor().as_ivec3();
    let [u, v] = octahedral_encode(normal);
    (cell, (u >> 13) << 3 | (v >> 13))
}

/// For each bin of `members`, the member nearest the bin's mean position
/// (ties to the lower index); ascending.
fn bin_representatives(receivers: &Receivers, members: &[u32], spacing: f32) -> Vec<u32> {
    let mut keyed: Vec<((IVec3, u16), u32)> = members
        .iter()
        .map(|&receiver| {
            let index = receiver as usize;
            (
                bin_key(
                    receivers.positions[index],
                    receivers.normals[index],
                    spacing,
                ),
                receiver,
            )
        })
        .collect();
    keyed.sort_unstable_by_key(|&((cell, bucket), receiver)| {
        (cell.x, cell.y, cell.z, bucket, receiver)
    });
    let mut chosen: Vec<u32> = keyed
        .chunk_by(|a, b| a.0 == b.0)
        .map(|bin| {
            let mean = bin
                .iter()
                .map(|&(_, receiver)| receivers.positions[receiver as usize])
                .sum::<Vec3>()
                / bin.len() as f32;
            bin.iter()
                .map(|&(_, receiver)| receiver)
                .min_by(|&a, &b| {
                    let da = receivers.positions[a as usize].distance_squared(mean);
                    let db = receivers.positions[b as usize].distance_squared(mean);
                    da.total_cmp(&db).then(a.cmp(&b))
                })
                .expect("bins are not empty")
        })
        .collect();
    chosen.sort_unstable();
    chosen
}

/// Each receiver's pane points and weights (unit-sum, 16-bit fixed point):
/// 24 bytes a receiver, read once a frame.
#[derive(Clone, Debug, Default)]
pub struct Upsampling {
    pub points: Vec<[u32; TAPS]>,
    /// Weights in 1/65535ths; a receiver without taps has all zeros.
    pub weights: Vec<[u16; TAPS]>,
}

impl Upsampling {
    /// Taps of every receiver from `points` (receiver indices) spaced about
    /// `spacing` apart.
    pub fn build(context: &SceneContext, points: &[u32], spacing: f32) -> Self {
        if points.is_empty() {
            return Self::default();
        }
        let every: Vec<u32> = (0..context.atlas.receivers.len() as u32).collect();
        Self::build_for(context, points, spacing, &every, true)
    }

    /// Taps of the receivers `targets`, in their order.
    ///
    /// With `check_hidden`, a hidden pane point lights only itself: its
    /// lift can cross a thin gap to the visible layer, where the visibility
    /// ray below would let it through. [`PanePoints::select`] never
    /// chooses one, so only a bake made before it kept pane points off
    /// hidden surfaces holds any, and only loading a bake checks.
    fn build_for(
        context: &SceneContext,
        points: &[u32],
        spacing: f32,
        targets: &[u32],
        check_hidden: bool,
    ) -> Self {
        let receivers = &context.atlas.receivers;
        let reach = spacing * REACH_TEXELS;
        let grid = PointGrid::new(points, &receivers.positions, reach);
        let lift = visibility_lift(context, spacing);
        let hidden: Option<Vec<bool>> = check_hidden.then(|| {
            grid.points
                .par_iter()
                .map(|&point| {
                    let index = point as usize;
                    context.is_hidden_surface_point(
                        receivers.positions[index],
                        receivers.normals[index],
                        lift,
                    )
                })
                .collect()
        });
        let (points, weights) = targets
            .par_iter()
            .map_init(Vec::new, |candidates, &receiver| {
                let receiver = receiver as usize;
                let position = receivers.positions[receiver];
                let normal = receivers.normals[receiver];
                candidates.clear();
                grid.for_each_near(position, |slot, point| {
                    let point_normal = receivers.normals[point as usize];
                    if point_normal.dot(normal) < FACING_COS {
                        return;
                    }
                    let distance = receivers.positions[point as usize].distance(position);
                    if distance <= reach {
                        candidates.push((distance, slot));
                    }
                });
                candidates.sort_unstable_by(|a, b| a.0.total_cmp(&b.0).then(a.1.cmp(&b.1)));
                let mut taps = [(0u32, 0.0f32); TAPS + 1];
                let mut found = 0;
                for &(distance, slot) in candidates.iter().take(CANDIDATES) {
                    let point = grid.points[slot as usize] as usize;
                    let visible = point == receiver
                        || !hidden.as_ref().is_some_and(|hidden| hidden[slot as usize]) && {
                            let from = position + normal * lift;
                            let to = receivers.positions[point] + receivers.normals[point] * lift;
                            !context.bvh.occluded(&Ray {
                                origin: from,
                                direction: to - from,
                                t_max: 1.0 - 1e-4,
                            })
                        };
                    if visible {
                        taps[found] = (slot, distance);
                        found += 1;
                        if found == TAPS + 1 {
                            break;
                        }
                    }
                }
                tap_weights(&taps[..found], reach)
            })
            .unzip();
        Self { points, weights }
    }

    pub fn memory_bytes(&self) -> usize {
        self.points.len() * TAPS * (4 + 2)
    }
}

/// Weights of up to `TAPS` taps, the extra candidate (if found) marking
/// where the last tap's weight must have fallen to zero.
fn tap_weights(found: &[(u32, f32)], reach: f32) -> ([u32; TAPS], [u16; TAPS]) {
    let mut slots = [0u32; TAPS];
    let mut weights = [0u16; TAPS];
    let used = found.len().min(TAPS);
    if used == 0 {
        return (slots, weights);
    }
    let limit = if found.len() > TAPS {
        found[TAPS].1
    } else {
        reach
    };
    let mut raw = [0.0f32; TAPS];
    for (tap, &(slot, distance)) in found.iter().take(used).enumerate() {
        slots[tap] = slot;
        raw[tap] = if limit > 0.0 {
            (1.0 - distance / limit).max(0.0).powi(2)
        } else {
            0.0
        };
    }
    let total: f32 = raw.iter().sum();
    if total <= 0.0 {
        // Every tap as far as the next candidate: the nearest alone.
        raw = [0.0; TAPS];
        raw[0] = 1.0;
    }
    let total: f32 = raw.iter().sum();
    // Fixed point that sums to exactly 65535: the remainder goes to the
    // nearest tap, so a uniform pane upsamples to itself.
    let mut assigned = 0u32;
    for tap in 1..used {
        weights[tap] = (raw[tap] / total * 65535.0).round() as u16;
        assigned += weights[tap] as u32;
    }
    weights[0] = (65535 - assigned.min(65535)) as u16;
    (slots, weights)
}

/// Pane points bucketed by a cubic grid of cells `cell` wide.
struct PointGrid {
    cell: f32,
    /// Pane point receivers, cell by cell.
    points: Vec<u32>,
    /// Receiver index of each pane-point slot in the caller's order.
    cells: HashMap<IVec3, std::ops::Range<u32>>,
    /// Slot of each sorted entry in the caller's point list.
    slots: Vec<u32>,
}

impl PointGrid {
    fn new(points: &[u32], positions: &[Vec3], cell: f32) -> Self {
        let key = |point: u32| (positions[point as usize] / cell).floor().as_ivec3();
        let mut order: Vec<u32> = (0..points.len() as u32).collect();
        order.sort_unstable_by_key(|&slot| {
            let at = key(points[slot as usize]);
            (at.x, at.y, at.z, slot)
        });
        let mut cells = HashMap::new();
        let mut start = 0usize;
        while start < order.len() {
            let at = key(points[order[start] as usize]);
            let mut end = start + 1;
            while end < order.len() && key(points[order[end] as usize]) == at {
                end += 1;
            }
            cells.insert(at, start as u32..end as u32);
            start = end;
        }
        Self {
            cell,
            points: points.to_vec(),
            cells,
            slots: order,
        }
    }

    /// Calls `visit(slot, receiver)` for the pane points in the 27 cells
    /// around `position`.
    fn for_each_near(&self, position: Vec3, mut visit: impl FnMut(u32, u32)) {
        let centre = (position / self.cell).floor().as_ivec3();
        for dz in -1..=1 {
            for dy in -1..=1 {
                for dx in -1..=1 {
                    if let Some(range) = self.cells.get(&(centre + IVec3::new(dx, dy, dz))) {
                        for &slot in &self.slots[range.start as usize..range.end as usize] {
                            visit(slot, self.points[slot as usize]);
                        }
                    }
                }
            }
        }
    }
}

/// Every receiver's light from the pane points' (`out[r] = sum of weight x
/// value` over its taps).
///
/// Receivers marked in `skipped` (empty: none) keep what they hold.
pub fn upsample(
    upsampling: &Upsampling,
    values: &[relight_core::Rgb],
    skipped: &[bool],
    out: &mut [relight_core::Rgb],
) {
    const SCALE: f32 = 1.0 / 65535.0;
    out.par_chunks_mut(4096)
        .enumerate()
        .zip(upsampling.points.par_chunks(4096))
        .zip(upsampling.weights.par_chunks(4096))
        .for_each(|(((chunk, out), points), weights)| {
            let skipped = skipped.get(chunk * 4096..).unwrap_or(&[]);
            for (index, ((value, taps), tap_weights)) in
                out.iter_mut().zip(points).zip(weights).enumerate()
            {
                if skipped.get(index) == Some(&true) {
                    continue;
                }
                let mut sum = relight_core::Rgb::ZERO;
                for tap in 0..TAPS {
                    sum += values[taps[tap] as usize] * (tap_weights[tap] as f32 * SCALE);
                }
                *value = sum;
            }
        });
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn weights_sum_to_one_and_fall_with_distance() {
        let (slots, weights) =
            tap_weights(&[(3, 0.1), (1, 0.2), (7, 0.3), (2, 0.35), (9, 0.4)], 1.0);
        assert_eq!(slots, [3, 1, 7, 2]);
        assert_eq!(weights.iter().map(|&w| w as u32).sum::<u32>(), 65535);
        assert!(weights.windows(2).all(|pair| pair[0] >= pair[1]));
        // One tap takes everything; none gives nothing.
        assert_eq!(tap_weights(&[(5, 0.3)], 1.0).1, [65535, 0, 0, 0]);
        assert_eq!(tap_weights(&[], 1.0).1, [0; TAPS]);
        // Taps as far as the next candidate: the nearest alone.
        assert_eq!(
            tap_weights(&[(1, 0.5), (2, 0.5), (3, 0.5), (4, 0.5), (5, 0.5)], 1.0).1,
            [65535, 0, 0, 0]
        );
    }
}
