//! Link generation (sections 4.5 and 4.6, Appendix A): for every cache the
//! `n_L` most important sender nodes, found top down by refining the node
//! with the largest visible solid angle, and their transport factors.
//!
//! Every surfel sample stands for its disc: solid angle
//! Omega = a cos(theta_s) / (d^2 + a / (2 pi)) (a / d^2 far away, the
//! disc's full 2 pi when the cache touches it) with a visibility ray. Flux
//! flows through the tree in units of one surfel's area (Phi' = sum of the
//! leaves' radiosities), so a node's radiance is Phi' / (pi * leaves) and
//! the factor folds in 1 / (pi * leaves) (section 4.1).

use crate::hierarchy::Hierarchy;
use crate::surfels::Surfels;
use glam::Vec3;
use relight_core::sampling::SampleStream;
use relight_core::sh;
use relight_trace::{Bvh, Ray};
use std::cmp::Reverse;
use std::collections::BinaryHeap;
use std::f32::consts::PI;

/// How a link carries its transport.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum LinkForm {
    /// Scalar factor, cone and direction, projected into SH every frame
    /// (section 4.6): 12 bytes, any band count at run time.
    Runtime,
    /// The factor projected into SH at bake time (section 3.1, Appendix A):
    /// `bands^2` f16 coefficients per link.
    Projected { bands: usize },
}

/// What link generation needs to know.
#[derive(Clone, Copy, Debug)]
pub struct LinkSettings {
    pub links: usize,
    /// Surfel samples that estimate a node's importance while refining.
    pub node_samples: u32,
    /// Surfel samples for the final factor of each link.
    pub link_samples: u32,
    /// Extra refinement priority for nodes whose samples are partly hidden
    /// or face away: such a node's flux is averaged over surfels the cache
    /// cannot see, which leaks light.
    pub leak_refinement: f32,
    pub form: LinkForm,
    pub seed: u64,
}

/// One cache's links before encoding.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct RuntimeLink {
    pub node: u32,
    /// Omega_visible / (Omega_cone * pi * leaves).
    pub factor: f32,
    /// 1 - cos(alpha) of the cone.
    pub one_minus_cos: f32,
    pub direction: Vec3,
    /// The node's visible solid angle, which the factor folds in: what
    /// [`hemisphere_scale`] sums over a cache's links.
    pub solid_angle: f32,
}

/// How far a cache's links may sum past what it can see before they are
/// scaled back. The sampled solid angles of the Cornell box's caches at
/// `high` sum to 1.00 of what they see at the 99th percentile and 1.01 at
/// the 99.9th: the link samples' noise, which scaling back would turn
/// into a darkening of every cache whose noise went up (at 1.0 the
/// two-rooms view from its unlit room lost 0.6 % of its light). Overlap
/// at contact gives far more: two-rooms' 99.9th percentile is 1.3-1.4,
/// its worst 8.7 (`high`) and 19 (the defaults). A bake logs these
/// figures at `RELIGHT_LOG=info`.
pub const OVERLAP_ALLOWANCE: f32 = 1.1;

/// The most solid angle a cache can see: the hemisphere around `normal`,
/// the whole sphere for a grid cache (whose normal is zero).
pub fn visible_solid_angle(normal: Vec3) -> f32 {
    if normal == Vec3::ZERO {
        4.0 * PI
    } else {
        2.0 * PI
    }
}

/// The factor that brings a cache's links, whose solid angles sum to
/// `linked`, within what it can see ([`visible_solid_angle`]). Each surfel
/// sample counts as a disc of up to 2 pi at contact, so the discs around a
/// cache standing where two surfaces meet overlap and can claim many
/// hemispheres together; scaling a sum beyond [`OVERLAP_ALLOWANCE`] back
/// to the most the cache can see keeps it from shining many times brighter
/// than anything it links to.
pub fn hemisphere_scale(normal: Vec3, linked: f32) -> f32 {
    let visible = visible_solid_angle(normal);
    if linked > visible * OVERLAP_ALLOWANCE {
        visible / linked
    } else {
        1.0
    }
}

/// The scene as link generation samples it.
pub struct Senders<'a> {
    pub surfels: &'a Surfels,
    pub hierarchy: &'a Hierarchy,
    pub bvh: &'a Bvh,
    pub epsilon: f32,
}

/// Sums over one node's samples.
#[derive(Clone, Copy, Default)]
struct NodeEstimate {
    /// Visible solid angle, and direction-weighted sum.
    solid_angle: f32,
    direction_sum: Vec3,
    visible_samples: u32,
    samples: u32,
}

impl Senders<'_> {
    /// Solid angle and direction of leaf `surfel` seen from the cache, with
    /// its visibility; zero when it faces away, is below the cache's horizon
    /// or hidden.
    fn sample(&self, origin: Vec3, normal: Vec3, surfel: usize) -> Option<(f32, Vec3)> {
        let target = self.surfels.positions[surfel];
        let surfel_normal = self.surfels.normals[surfel];
        let offset = target - origin;
        let distance_squared = offset.length_squared();
        if distance_squared <= 0.0 {
            return None;
        }
        let direction = offset / distance_squared.sqrt();
        let cos_sender = -surfel_normal.dot(direction);
        if cos_sender <= 0.0 || (normal != Vec3::ZERO && normal.dot(direction) <= 0.0) {
            return None;
        }
        let lifted = target + surfel_normal * self.epsilon;
        let ray = Ray {
            origin,
            direction: lifted - origin,
            t_max: 1.0,
        };
        if self.bvh.occluded(&ray) {
            return None;
        }
        let area = self.surfels.area;
        Some((
            area * cos_sender / (distance_squared + area / (2.0 * PI)),
            direction,
        ))
    }

    /// Stratified samples over a node's leaves (every leaf when it has at
    /// most `samples`), scaled to the whole node.
    fn estimate(
        &self,
        origin: Vec3,
        normal: Vec3,
        node: u32,
        samples: u32,
        rng: &mut relight_core::Pcg32,
        mut each: impl FnMut(f32, f32, Vec3),
    ) -> NodeEstimate {
        let first = self.hierarchy.first_leaf[node as usize];
        let leaves = self.hierarchy.leaves[node as usize];
        let taken = leaves.min(samples.max(1));
        let scale = leaves as f32 / taken as f32;
        let mut estimate = NodeEstimate {
            samples: taken,
            ..Default::default()
        };
        for index in 0..taken {
            let leaf = if taken == leaves {
                first + index
            } else {
                let position = (index as f32 + rng.next_f32()) * leaves as f32 / taken as f32;
                first + (position as u32).min(leaves - 1)
            };
            if let Some((solid_angle, direction)) = self.sample(origin, normal, leaf as usize) {
                let weighted = solid_angle * scale;
                estimate.solid_angle += weighted;
                estimate.direction_sum += direction * weighted;
                estimate.visible_samples += 1;
                each(weighted, solid_angle, direction);
            }
        }
        estimate
    }

    /// Priority of refining a node: its visible solid angle, raised when
    /// part of it is hidden (a leak risk).
    fn priority(estimate: &NodeEstimate, leak_refinement: f32) -> f32 {
        let hidden = 1.0 - estimate.visible_samples as f32 / estimate.samples.max(1) as f32;
        estimate.solid_angle * (1.0 + leak_refinement * hidden)
    }

    /// A node's estimate from `samples` leaves, retried with four times as
    /// many while nothing is seen, the node has more leaves than were
    /// tried, and fewer than `most` were.
    fn estimate_until_seen(
        &self,
        origin: Vec3,
        normal: Vec3,
        node: u32,
        mut samples: u32,
        most: u32,
        rng: &mut relight_core::Pcg32,
    ) -> NodeEstimate {
        let leaves = self.hierarchy.leaves[node as usize];
        loop {
            let estimate = self.estimate(origin, normal, node, samples, rng, |_, _, _| {});
            if estimate.solid_angle > 0.0 || samples >= leaves || samples >= most {
                return estimate;
            }
            samples *= 4;
        }
    }

    /// The cut of at most `settings.links` visible nodes for the cache at
    /// `position` (hemispherical around `normal`, spherical when zero), in
    /// node order.
    pub fn cut(
        &self,
        cache: u64,
        position: Vec3,
        normal: Vec3,
        settings: &LinkSettings,
    ) -> Vec<u32> {
        let origin = position + normal * self.epsilon;
        let mut rng = SampleStream::new(settings.seed, cache, 0xC07);
        let mut finished = Vec::new();
        let mut open: BinaryHeap<(u32, Reverse<u32>)> = BinaryHeap::new();
        if self.hierarchy.node_count() == 0 {
            return finished;
        }
        let root = self.hierarchy.root();
        // A cache that sees little of the scene (a box's side facing a
        // corner) can miss every visible leaf among a few samples; dropping
        // the root then leaves it with no light at all, so it is sampled
        // more densely until something is seen or every leaf was tried.
        let estimate =
            self.estimate_until_seen(origin, normal, root, settings.node_samples, 4096, &mut rng);
        if estimate.solid_angle > 0.0 {
            open.push((
                Self::priority(&estimate, settings.leak_refinement).to_bits(),
                Reverse(root),
            ));
        }
        while finished.len() + open.len() < settings.links {
            let Some((_, Reverse(node))) = open.pop() else {
                break;
            };
            if self.hierarchy.is_leaf(node) {
                finished.push(node);
                continue;
            }
            for child in self.hierarchy.children_of(node) {
                // One denser look before a large child is dropped as
                // unseen: its parent was seen, so some of it may be.
                let estimate = self.estimate_until_seen(
                    origin,
                    normal,
                    child,
                    settings.node_samples,
                    settings.node_samples * 4,
                    &mut rng,
                );
                if estimate.solid_angle > 0.0 {
                    let priority = Self::priority(&estimate, settings.leak_refinement);
                    open.push((priority.to_bits(), Reverse(child)));
                }
            }
        }
        finished.extend(open.into_iter().map(|(_, Reverse(node))| node));
        finished.sort_unstable();
        finished
    }

    /// Runtime-projection link to `node`: factor, cone and mean direction.
    /// The cone's spread matches the samples' mean resultant length
    /// (R = (1 + cos alpha) / 2 for a uniform cone), but is never narrower
    /// than the visible solid angle, so bands 0 and 1 are those of the
    /// samples.
    pub fn runtime_link(
        &self,
        cache: u64,
        position: Vec3,
        normal: Vec3,
        node: u32,
        settings: &LinkSettings,
    ) -> RuntimeLink {
        let origin = position + normal * self.epsilon;
        let mut rng = SampleStream::new(settings.seed, cache, 0x1000_0000 + node as u64);
        let estimate = self.estimate(
            origin,
            normal,
            node,
            settings.link_samples,
            &mut rng,
            |_, _, _| {},
        );
        if estimate.solid_angle <= 0.0 {
            return RuntimeLink {
                node,
                ..Default::default()
            };
        }
        let resultant = (estimate.direction_sum.length() / estimate.solid_angle).min(1.0);
        let one_minus_cos = (2.0 * (1.0 - resultant))
            .max(estimate.solid_angle / (2.0 * PI))
            .min(2.0);
        let cone = 2.0 * PI * one_minus_cos;
        let leaves = self.hierarchy.leaves[node as usize] as f32;
        RuntimeLink {
            node,
            factor: estimate.solid_angle / (cone * PI * leaves),
            one_minus_cos,
            direction: estimate.direction_sum.normalize_or_zero(),
            solid_angle: estimate.solid_angle,
        }
    }

    /// SH-projected link to `node` (Appendix A), each sample projected as
    /// the small cone of its disc rather than a single direction; returns
    /// the node's visible solid angle.
    #[allow(clippy::too_many_arguments)]
    pub fn projected_link(
        &self,
        cache: u64,
        position: Vec3,
        normal: Vec3,
        node: u32,
        bands: usize,
        settings: &LinkSettings,
        coefficients: &mut [f32],
    ) -> f32 {
        let origin = position + normal * self.epsilon;
        let mut rng = SampleStream::new(settings.seed, cache, 0x1000_0000 + node as u64);
        coefficients.fill(0.0);
        let mut basis = [0.0f32; 64];
        let leaves = self.hierarchy.leaves[node as usize] as f32;
        let folded = 1.0 / (PI * leaves);
        let estimate = self.estimate(
            origin,
            normal,
            node,
            settings.link_samples,
            &mut rng,
            |weighted, solid_angle, direction| {
                // The disc's own cone, carrying the weight of the leaves this
                // sample stands for (cone[0] is the cone's solid angle).
                let cone = sh::cone_band_factors(1.0 - (solid_angle / (2.0 * PI)).min(2.0));
                let scale = if cone[0] > 0.0 {
                    weighted / cone[0]
                } else {
                    0.0
                };
                sh::evaluate(direction, bands, &mut basis);
                for band in 0..bands {
                    for index in band * band..(band + 1) * (band + 1) {
                        coefficients[index] += folded * scale * cone[band] * basis[index];
                    }
                }
            },
        );
        estimate.solid_angle
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn links_are_scaled_back_to_what_the_cache_sees() {
        let up = Vec3::Y;
        assert_eq!(hemisphere_scale(up, PI + 0.5 * PI), 1.0);
        // Within the sampling noise's allowance: left alone.
        assert_eq!(hemisphere_scale(up, PI + 1.05 * PI), 1.0);
        assert!((hemisphere_scale(up, 3.0 * PI) - 2.0 / 3.0).abs() < 1e-6);
        // A grid cache sees the whole sphere.
        assert_eq!(hemisphere_scale(Vec3::ZERO, 3.0 * PI), 1.0);
        assert!((hemisphere_scale(Vec3::ZERO, 8.0 * PI) - 0.5).abs() < 1e-6);
        assert_eq!(hemisphere_scale(up, 0.0), 1.0);
    }
}
