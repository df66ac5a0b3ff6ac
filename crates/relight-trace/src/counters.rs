//! Rays traced through [`crate::Bvh`], counted without contention (one
//! cache line per rayon worker), so a bake can compare its time with the
//! time its rays alone need at the scene's measured ray rate.

use std::sync::atomic::{AtomicU64, Ordering};

const SLOTS: usize = 64;

/// Rays traced since the process started, by kind.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct RayCount {
    pub closest_hit: u64,
    pub occlusion: u64,
}

impl RayCount {
    /// Rays traced since `earlier`.
    pub fn since(self, earlier: RayCount) -> RayCount {
        RayCount {
            closest_hit: self.closest_hit.wrapping_sub(earlier.closest_hit),
            occlusion: self.occlusion.wrapping_sub(earlier.occlusion),
        }
    }

    pub fn total(self) -> u64 {
        self.closest_hit + self.occlusion
    }
}

#[repr(align(64))]
struct Slot {
    closest_hit: AtomicU64,
    occlusion: AtomicU64,
}

static COUNTS: [Slot; SLOTS] = [const {
    Slot {
        closest_hit: AtomicU64::new(0),
        occlusion: AtomicU64::new(0),
    }
}; SLOTS];

/// The calling thread's slot: rayon workers have their own (threads of
/// different pools may share one, which costs only contention); other
/// threads share the last.
#[inline]
fn slot() -> &'static Slot {
    let index = rayon::current_thread_index().map_or(SLOTS - 1, |index| index % (SLOTS - 1));
    &COUNTS[index]
}

#[inline]
pub(crate) fn count_closest_hit() {
    slot().closest_hit.fetch_add(1, Ordering::Relaxed);
}

#[inline]
pub(crate) fn count_occlusion() {
    slot().occlusion.fetch_add(1, Ordering::Relaxed);
}

/// Rays traced by every thread so far.
pub fn rays_traced() -> RayCount {
    COUNTS
        .iter()
        .fold(RayCount::default(), |sum, slot| RayCount {
            closest_hit: sum.closest_hit + slot.closest_hit.load(Ordering::Relaxed),
            occlusion: sum.occlusion + slot.occlusion.load(Ordering::Relaxed),
        })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::{Bvh, Ray};
    use glam::Vec3;

    #[test]
    fn every_query_is_counted() {
        let bvh = Bvh::build(&[Vec3::ZERO, Vec3::X, Vec3::Y], &[[0, 1, 2]]);
        let ray = Ray {
            origin: Vec3::new(0.2, 0.2, 1.0),
            direction: -Vec3::Z,
            t_max: f32::INFINITY,
        };
        let before = rays_traced();
        let mut cache = crate::NO_OCCLUDER;
        for _ in 0..1000 {
            assert!(bvh.intersect(&ray).is_some());
            assert!(bvh.occluded(&ray));
            assert!(bvh.occluded_cached(&ray, &mut cache));
        }
        // Other tests may trace at the same time: at least these were seen.
        let seen = rays_traced().since(before);
        assert!(seen.closest_hit >= 1000, "{seen:?}");
        assert!(seen.occlusion >= 2000, "{seen:?}");
    }
}
