//! Probe placement: candidates in free space above the receivers, spread by
//! farthest-point sampling, then topped up where receivers see too few
//! probes within the cut-off radius.
//!
//! Receivers whose hemisphere holds nothing but the environment (the
//! outside of a closed building under an empty sky, a third of Sponza's
//! texels) need no probe and are left out. Surfaces that face out of the
//! scene but see some of it (a roof beside a higher roof) get probes from
//! just outside its bounds. A placement kept inside the bounds left 28 % of
//! Sponza's receivers short of three probes (see the test
//! `placement_covers_outward_facing_surfaces`).

use glam::Vec3;
use rayon::prelude::*;
use relight_core::sampling::{cosine_hemisphere_around, radical_inverse};
use relight_scene::atlas::Receivers;
use relight_technique::SceneContext;
use relight_trace::Ray;

/// Where the probes went and how well they cover the receivers.
#[derive(Clone, Debug, PartialEq)]
pub struct Placement {
    pub probes: Vec<Vec3>,
    pub radius: f32,
    /// Probes added by the coverage pass on top of the requested count.
    pub added_for_coverage: usize,
    /// Receivers that see geometry and fewer than `min_probes` probes
    /// within the radius.
    pub receivers_short_of_probes: usize,
    /// Receivers whose hemisphere holds nothing but the environment (see
    /// [`receivers_seeing_geometry`]): they need no probe.
    pub open_receivers: usize,
}

/// Re-exported for the probe placement tests.
pub fn is_inside_geometry(context: &SceneContext, point: Vec3) -> bool {
    context.is_inside_geometry(point)
}

/// A candidate probe position above receiver `index`: `height` along its
/// normal, at most half way to whatever the normal ray hits first or, where
/// it hits nothing, to where it leaves `room` (the scene's bounds with a
/// margin), so probes for surfaces facing the open sky or the outside of
/// the building stay near them instead of hanging far out in the void.
fn candidate_above(
    context: &SceneContext,
    receivers: &Receivers,
    index: usize,
    height: f32,
    room: (Vec3, Vec3),
) -> Vec3 {
    let position = receivers.positions[index];
    let normal = receivers.normals[index];
    let ray = Ray {
        origin: position + normal * relight_trace::direct::ray_epsilon_for(&context.bvh),
        direction: normal,
        t_max: f32::INFINITY,
    };
    let free = context
        .bvh
        .intersect(&ray)
        .map_or_else(|| exit_distance(position, normal, room), |hit| hit.t);
    position + normal * height.min(0.5 * free)
}

/// How far a ray from `origin` (inside `room`) along `direction` travels
/// before it leaves the box.
fn exit_distance(origin: Vec3, direction: Vec3, room: (Vec3, Vec3)) -> f32 {
    let (low, high) = room;
    let mut distance = f32::INFINITY;
    for axis in 0..3 {
        let step = direction[axis];
        if step > 0.0 {
            distance = distance.min((high[axis] - origin[axis]) / step);
        } else if step < 0.0 {
            distance = distance.min((low[axis] - origin[axis]) / step);
        }
    }
    distance.max(0.0)
}

/// The scene's bounds grown by `margin` on every side.
fn room_around(context: &SceneContext, margin: f32) -> (Vec3, Vec3) {
    let (low, high) = context.scene.mesh.bounds();
    (low - Vec3::splat(margin), high + Vec3::splat(margin))
}

/// Farthest-point selection of `count` of `candidates`, starting from the
/// first; returns the chosen indices and the covering distance (the largest
/// distance from a candidate to its nearest chosen one).
fn farthest_points(candidates: &[Vec3], count: usize) -> (Vec<usize>, f32) {
    let mut chosen = Vec::with_capacity(count);
    let mut nearest = vec![f32::INFINITY; candidates.len()];
    let mut next = 0usize;
    while chosen.len() < count.min(candidates.len()) {
        chosen.push(next);
        let added = candidates[next];
        for (distance, candidate) in nearest.iter_mut().zip(candidates) {
            *distance = distance.min(candidate.distance_squared(added));
        }
        // Ties go to the lower index, so the choice never depends on threads.
        next = nearest
            .iter()
            .enumerate()
            .fold((0usize, -1.0f32), |best, (index, &distance)| {
                if distance > best.1 {
                    (index, distance)
                } else {
                    best
                }
            })
            .0;
    }
    let covering = nearest.iter().copied().fold(0.0f32, f32::max).sqrt();
    (chosen, covering)
}

/// Lloyd relaxation of the farthest-point seeds over the candidates (eight
/// rounds of k-means), each probe then snapped to its nearest candidate so it
/// stays in free space. Farthest-point sampling alone picks the extremes
/// first, a shell along the walls; the relaxed set spreads through the
/// volume like a grid (Cornell box lightmap error 10.3 % for the seeds, see
/// the crate documentation for the relaxed figure).
fn relax(candidates: &[Vec3], seeds: Vec<usize>) -> Vec<Vec3> {
    let mut centres: Vec<Vec3> = seeds.iter().map(|&index| candidates[index]).collect();
    let mut nearest = vec![0usize; candidates.len()];
    let closest = |centres: &[Vec3], point: Vec3| {
        centres
            .iter()
            .enumerate()
            .fold((0usize, f32::INFINITY), |best, (index, centre)| {
                let distance = centre.distance_squared(point);
                if distance < best.1 {
                    (index, distance)
                } else {
                    best
                }
            })
            .0
    };
    for _ in 0..8 {
        for (slot, candidate) in nearest.iter_mut().zip(candidates) {
            *slot = closest(&centres, *candidate);
        }
        let mut sums = vec![(Vec3::ZERO, 0u32); centres.len()];
        for (&centre, candidate) in nearest.iter().zip(candidates) {
            sums[centre].0 += *candidate;
            sums[centre].1 += 1;
        }
        for (centre, (sum, count)) in centres.iter_mut().zip(sums) {
            if count > 0 {
                *centre = sum / count as f32;
            }
        }
    }
    centres
        .iter()
        .map(|centre| candidates[closest(candidates, *centre)])
        .collect()
}

/// The smooth falloff weight of equation 4.4 for t = distance / radius.
#[inline]
pub fn falloff_weight(t: f32) -> f32 {
    if (0.0..=1.0).contains(&t) {
        2.0 * t * t * t - 3.0 * t * t + 1.0
    } else {
        0.0
    }
}

/// True when the probe lies in front of the receiver's plane and a ray
/// between them is unoccluded.
pub fn receiver_sees_probe(
    context: &SceneContext,
    position: Vec3,
    normal: Vec3,
    probe: Vec3,
    epsilon: f32,
) -> bool {
    let offset = probe - position;
    if offset.dot(normal) <= 0.0 {
        return false;
    }
    // Nudged toward the probe as well as off the surface: a texel centre
    // clamped onto the edge of a concave corner would otherwise start its
    // ray inside the neighbouring wall.
    let origin = position + (normal + offset.normalize_or_zero()) * epsilon;
    let ray = Ray {
        origin,
        direction: probe - origin,
        t_max: 1.0 - 1e-4,
    };
    !context.bvh.occluded(&ray)
}

/// The probes within `radius` of a receiver and in front of its plane, as
/// (probe, distance, whether the receiver sees it).
fn probes_in_reach<'a>(
    context: &'a SceneContext,
    probes: &'a [Vec3],
    radius: f32,
    position: Vec3,
    normal: Vec3,
    epsilon: f32,
) -> impl Iterator<Item = (u32, f32, bool)> + 'a {
    probes.iter().enumerate().filter_map(move |(index, probe)| {
        let distance = probe.distance(position);
        (distance < radius && (*probe - position).dot(normal) > 0.0).then(|| {
            let seen = receiver_sees_probe(context, position, normal, *probe, epsilon);
            (index as u32, distance, seen)
        })
    })
}

/// Probes within `radius` of every receiver, closest first, at most
/// `max_nearby` of them, those the receiver sees before those it does not
/// (the transport's mutual-visibility rays decide per direction; this only
/// picks which probes get a slot).
pub fn nearby_probes(
    context: &SceneContext,
    probes: &[Vec3],
    radius: f32,
    max_nearby: usize,
) -> Vec<Vec<u32>> {
    let receivers = &context.atlas.receivers;
    let epsilon = relight_trace::direct::ray_epsilon_for(&context.bvh);
    (0..receivers.len())
        .into_par_iter()
        .map(|index| {
            let position = receivers.positions[index];
            let normal = receivers.normals[index];
            let mut candidates: Vec<(bool, f32, u32)> =
                probes_in_reach(context, probes, radius, position, normal, epsilon)
                    .map(|(probe, distance, seen)| (!seen, distance, probe))
                    .collect();
            candidates.sort_by(|a, b| a.0.cmp(&b.0).then(a.1.total_cmp(&b.1)).then(a.2.cmp(&b.2)));
            candidates.truncate(max_nearby);
            let mut chosen: Vec<u32> = candidates.into_iter().map(|(_, _, probe)| probe).collect();
            chosen.sort_unstable();
            chosen
        })
        .collect()
}

/// How many probes within `radius` each receiver sees.
pub fn visible_counts(context: &SceneContext, probes: &[Vec3], radius: f32) -> Vec<usize> {
    let receivers = &context.atlas.receivers;
    let epsilon = relight_trace::direct::ray_epsilon_for(&context.bvh);
    (0..receivers.len())
        .into_par_iter()
        .map(|index| {
            let position = receivers.positions[index];
            let normal = receivers.normals[index];
            probes_in_reach(context, probes, radius, position, normal, epsilon)
                .filter(|&(_, _, seen)| seen)
                .count()
        })
        .collect()
}

/// Cosine-weighted test directions per receiver for
/// [`receivers_seeing_geometry`], on a stratified grid.
const OPENNESS_RAYS_PER_SIDE: u32 = 4;

/// Which receivers see a lit side of any surface over their hemisphere:
/// of `OPENNESS_RAYS_PER_SIDE`^2 stratified cosine-weighted rays, at least
/// one hits a front face. A receiver that sees only the environment, or
/// only back faces (a face buried inside another solid), has no indirect
/// light to reconstruct: relight counts the environment's light as direct,
/// back faces hold no light, and a transport sample that escapes or hits a
/// back face carries none, so its transport is zero whichever probes it
/// sees. The outside of a closed building under an empty sky is such a
/// surface; probes placed for it would be wasted.
pub fn receivers_seeing_geometry(context: &SceneContext) -> Vec<bool> {
    let receivers = &context.atlas.receivers;
    let epsilon = relight_trace::direct::ray_epsilon_for(&context.bvh);
    (0..receivers.len())
        .into_par_iter()
        .map(|index| {
            let normal = receivers.normals[index];
            let origin = receivers.positions[index] + normal * epsilon;
            openness_directions(normal).any(|direction| {
                let ray = Ray {
                    origin,
                    direction,
                    t_max: f32::INFINITY,
                };
                context.bvh.intersect(&ray).is_some_and(|hit| {
                    context
                        .scene
                        .mesh
                        .geometric_normal(hit.triangle as usize)
                        .dot(direction)
                        < 0.0
                })
            })
        })
        .collect()
}

/// The test directions of [`receivers_seeing_geometry`] around `normal`.
pub fn openness_directions(normal: Vec3) -> impl Iterator<Item = Vec3> {
    let side = OPENNESS_RAYS_PER_SIDE;
    (0..side * side).map(move |cell| {
        let uv = glam::Vec2::new(
            ((cell % side) as f32 + 0.5) / side as f32,
            ((cell / side) as f32 + 0.5) / side as f32,
        );
        cosine_hemisphere_around(normal, uv)
    })
}

/// Settings of automatic placement.
#[derive(Clone, Copy, Debug)]
pub struct PlacementSettings {
    pub count: usize,
    /// Cut-off radius; 0 picks `radius_factor` times the covering distance.
    pub radius: f32,
    pub radius_factor: f32,
    pub min_probes: usize,
    /// Upper bound on probes the coverage pass may add.
    pub max_added: usize,
}

/// Automatic placement (see the module comment).
pub fn place_probes(context: &SceneContext, settings: PlacementSettings) -> Placement {
    let receivers = &context.atlas.receivers;
    let sees_geometry = receivers_seeing_geometry(context);
    let open_receivers = sees_geometry.iter().filter(|&&sees| !sees).count();
    // Receivers are even over area, so the ones that need probes stand for
    // their share of it; were none to, placement goes on as if all did.
    let needing = match receivers.len() - open_receivers {
        0 => receivers.len(),
        needing => needing,
    };
    let needs_probes = |index: usize| sees_geometry[index] || needing == receivers.len();
    let needy_area =
        context.scene.mesh.total_area() as f32 * needing as f32 / receivers.len().max(1) as f32;
    let spacing = (needy_area / settings.count.max(1) as f32).sqrt();
    let height = 0.5 * spacing;
    // Candidates above receivers picked by a Halton sequence (even over the
    // lightmap, which is even over area), each at a height between a fifth
    // and all of the way to the middle of the free space in front of it, so
    // the candidates fill the volume near surfaces rather than one shell at
    // a fixed distance: a shell of probes hugging the walls sees every
    // surface at grazing angles, where band-limited radiance is worst
    // (Cornell box lightmap error 12.2 % for a shell, 7.7 % for a 3 x 3 x 3
    // grid through the room).
    let room = room_around(context, 0.5 * spacing);
    // The sequence runs over all receivers and skips those that need no
    // probe, so a scene with few of them keeps the candidates it had.
    let candidate_count = (settings.count * 16).min(receivers.len());
    let mut picks: Vec<usize> = (0..candidate_count as u64)
        .map(|index| {
            ((radical_inverse(2, index + 1) * receivers.len() as f64) as usize)
                .min(receivers.len() - 1)
        })
        .filter(|&index| needs_probes(index))
        .collect();
    if picks.is_empty() {
        picks = (0..receivers.len())
            .filter(|&index| needs_probes(index))
            .take(candidate_count)
            .collect();
    }
    let candidates: Vec<Vec3> = picks
        .par_iter()
        .enumerate()
        .map(|(pick, &index)| {
            let fraction = 0.2 + 0.8 * radical_inverse(3, pick as u64 + 1) as f32;
            candidate_above(context, receivers, index, fraction * 2.0 * spacing, room)
        })
        .collect();
    let candidates: Vec<Vec3> = candidates
        .into_iter()
        .filter(|&candidate| !is_inside_geometry(context, candidate))
        .collect();
    let (chosen, _) = farthest_points(&candidates, settings.count);
    let mut probes = relax(&candidates, chosen);
    let covering = candidates
        .iter()
        .map(|candidate| {
            probes
                .iter()
                .map(|probe| probe.distance_squared(*candidate))
                .fold(f32::INFINITY, f32::min)
        })
        .fold(0.0f32, f32::max)
        .sqrt();
    let radius = if settings.radius > 0.0 {
        settings.radius
    } else {
        (settings.radius_factor * covering).max(1e-3)
    };
    let (added_for_coverage, receivers_short_of_probes) = cover_receivers(
        context,
        &sees_geometry,
        &mut probes,
        radius,
        height,
        settings,
    );
    Placement {
        probes,
        radius,
        added_for_coverage,
        receivers_short_of_probes,
        open_receivers,
    }
}

/// Receivers that see geometry and fewer than `min_probes` visible probes
/// within `radius` for the given probe set.
pub fn count_short_receivers(
    context: &SceneContext,
    probes: &[Vec3],
    radius: f32,
    min_probes: usize,
) -> usize {
    coverage_of(context, probes, radius, min_probes).0
}

/// For the given probe set: the receivers that see geometry and fewer than
/// `min_probes` visible probes within `radius`, and the receivers that see
/// no lit surface and need none.
pub fn coverage_of(
    context: &SceneContext,
    probes: &[Vec3],
    radius: f32,
    min_probes: usize,
) -> (usize, usize) {
    let sees_geometry = receivers_seeing_geometry(context);
    let counts = visible_counts(context, probes, radius);
    let short = short_receivers(&counts, &sees_geometry, min_probes).len();
    let open = sees_geometry.iter().filter(|&&sees| !sees).count();
    (short, open)
}

/// The receivers that see geometry but fewer than `min_probes` of the
/// probes `counts` counted.
fn short_receivers(counts: &[usize], sees_geometry: &[bool], min_probes: usize) -> Vec<usize> {
    (0..counts.len())
        .filter(|&index| sees_geometry[index] && counts[index] < min_probes)
        .collect()
}

/// Candidate positions and short receivers judging them, per coverage
/// round.
const COVERAGE_CANDIDATES: usize = 2048;
const COVERAGE_JUDGES: usize = 8192;
const COVERAGE_ROUNDS: usize = 12;

/// Adds probes above receivers that see too few, a spread-out batch of the
/// most useful per round, until none is short or the budget is spent. Returns (probes
/// added, receivers still short).
fn cover_receivers(
    context: &SceneContext,
    sees_geometry: &[bool],
    probes: &mut Vec<Vec3>,
    radius: f32,
    height: f32,
    settings: PlacementSettings,
) -> (usize, usize) {
    let receivers = &context.atlas.receivers;
    let mut added = 0usize;
    // Counts add up over probe sets: each round counts only its new batch.
    let mut counts = visible_counts(context, probes, radius);
    let room = room_around(context, height);
    for _round in 0..COVERAGE_ROUNDS {
        let short = short_receivers(&counts, sees_geometry, settings.min_probes);
        if short.is_empty() || added >= settings.max_added {
            return (added, short.len());
        }
        // Candidates above (a spread sample of) the short receivers, ranked
        // by how many short receivers within the radius would see them: a
        // probe in an arcade helps the receivers around it, one hung beside
        // a column helps few. Gains are counted on a strided sample of the
        // short receivers, which ranks them the same for far less work.
        let candidates: Vec<Vec3> = short
            .iter()
            .step_by(short.len().div_ceil(COVERAGE_CANDIDATES))
            .map(|&index| {
                candidate_above(context, receivers, index, height.min(0.5 * radius), room)
            })
            .filter(|&candidate| !is_inside_geometry(context, candidate))
            .collect();
        let judged: Vec<usize> = short
            .iter()
            .step_by(short.len().div_ceil(COVERAGE_JUDGES))
            .copied()
            .collect();
        let epsilon = relight_trace::direct::ray_epsilon_for(&context.bvh);
        let gains: Vec<usize> = candidates
            .par_iter()
            .map(|&candidate| {
                judged
                    .iter()
                    .filter(|&&index| {
                        let position = receivers.positions[index];
                        let normal = receivers.normals[index];
                        position.distance(candidate) < radius
                            && receiver_sees_probe(context, position, normal, candidate, epsilon)
                    })
                    .count()
            })
            .collect();
        let mut order: Vec<usize> = (0..candidates.len()).filter(|&i| gains[i] > 0).collect();
        order.sort_by_key(|&index| (std::cmp::Reverse(gains[index]), index));
        // A spread batch: one new probe serves every receiver within the
        // radius of it, so the next pick stands apart from the last.
        // Quarter batches: gains are recounted after each, so later picks
        // see what earlier ones already cover.
        let budget = (settings.max_added - added).min(settings.max_added.div_ceil(4));
        let mut batch: Vec<Vec3> = Vec::new();
        for index in order {
            let candidate = candidates[index];
            if batch.len() >= budget {
                break;
            }
            if batch
                .iter()
                .any(|other| other.distance(candidate) < 0.5 * radius)
            {
                continue;
            }
            batch.push(candidate);
        }
        if batch.is_empty() {
            return (added, short.len());
        }
        added += batch.len();
        for (count, seen) in counts
            .iter_mut()
            .zip(visible_counts(context, &batch, radius))
        {
            *count += seen;
        }
        probes.extend(batch);
    }
    let short = short_receivers(&counts, sees_geometry, settings.min_probes).len();
    (added, short)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn falloff_is_smooth_and_bounded() {
        assert_eq!(falloff_weight(0.0), 1.0);
        assert_eq!(falloff_weight(1.0), 0.0);
        assert_eq!(falloff_weight(1.5), 0.0);
        assert!((falloff_weight(0.5) - 0.5).abs() < 1e-6);
        // Zero slope at both ends (w'(t) = 6t^2 - 6t).
        let slope = |t: f32| (falloff_weight(t + 1e-3) - falloff_weight(t)) / 1e-3;
        assert!(slope(0.0).abs() < 1e-2 && slope(1.0 - 1e-3).abs() < 1e-2);
    }

    #[test]
    fn farthest_points_spread_and_cover() {
        let candidates: Vec<Vec3> = (0..100).map(|i| Vec3::new(i as f32, 0.0, 0.0)).collect();
        let (chosen, covering) = farthest_points(&candidates, 3);
        assert_eq!(chosen, vec![0, 99, 49]);
        assert!(covering <= 25.0, "{covering}");
    }
}
