//! Rays traced through [`crate::Bvh`], counted per thread without locked
//! instructions, so a bake can compare its time with the time its rays
//! alone need at the scene's measured ray rate.

use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex};

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

/// One thread's counts: only that thread writes them (plain loads and
/// stores, no locked instruction), any thread may read them.
#[derive(Default)]
struct Slot {
    closest_hit: AtomicU64,
    occlusion: AtomicU64,
}

/// Every thread's slot, kept after the thread ends so no count is lost.
static SLOTS: Mutex<Vec<Arc<Slot>>> = Mutex::new(Vec::new());

thread_local! {
    static OWN: Arc<Slot> = {
        let slot = Arc::new(Slot::default());
        SLOTS
            .lock()
            .unwrap_or_else(|poisoned| poisoned.into_inner())
            .push(slot.clone());
        slot
    };
}

#[inline]
fn bump(counter: &AtomicU64) {
    counter.store(counter.load(Ordering::Relaxed) + 1, Ordering::Relaxed);
}

#[inline]
pub(crate) fn count_closest_hit() {
    OWN.with(|slot| bump(&slot.closest_hit));
}

#[inline]
pub(crate) fn count_occlusion() {
    OWN.with(|slot| bump(&slot.occlusion));
}

/// Rays traced by every thread so far.
pub fn rays_traced() -> RayCount {
    SLOTS
        .lock()
        .unwrap_or_else(|poisoned| poisoned.into_inner())
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
