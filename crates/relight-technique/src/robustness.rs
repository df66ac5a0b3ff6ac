//! Checks that techniques' tests share: damaged bake payloads (a technique
//! must refuse them with an error or run them, never panic: "no panics on
//! any input file"), sharded bakes that must merge to the whole, and bakes
//! made once per test process.

use crate::{Frame, NoProgress, SceneContext, Technique, TechniqueKind};
use relight_core::sampling::Pcg32;
use relight_scene::Light;
use std::collections::HashMap;
use std::panic::{catch_unwind, AssertUnwindSafe};
use std::sync::{Arc, Mutex, OnceLock};

/// Values computed once per process for each key and shared, for tests
/// that need the same costly result (a bake, a reference) several times.
/// Callers asking for one key at once wait for one of them to compute it;
/// different keys compute in parallel.
pub struct OncePerProcess<K, V> {
    slots: Mutex<Option<HashMap<K, Slot<V>>>>,
}

/// One key's value, filled by the first caller.
type Slot<V> = Arc<OnceLock<Arc<V>>>;

impl<K: std::hash::Hash + Eq, V> OncePerProcess<K, V> {
    pub const fn new() -> Self {
        Self {
            slots: Mutex::new(None),
        }
    }

    /// The value for `key`, computed by `compute` if no caller has yet.
    pub fn get_or_compute(&self, key: K, compute: impl FnOnce() -> V) -> Arc<V> {
        let slot = self
            .slots
            .lock()
            // A test that panicked while holding the lock left the map whole.
            .unwrap_or_else(|poisoned| poisoned.into_inner())
            .get_or_insert_with(HashMap::new)
            .entry(key)
            .or_default()
            .clone();
        slot.get_or_init(|| Arc::new(compute())).clone()
    }
}

impl<K: std::hash::Hash + Eq, V> Default for OncePerProcess<K, V> {
    fn default() -> Self {
        Self::new()
    }
}

/// `kind`'s bake of `context` with `params`, made once per process for each
/// technique, scene fingerprint ([`SceneContext::fingerprint`]) and
/// parameter list, and shared: a bake does not depend on the lights or the
/// camera, so tests that measure one bake under several lights or at
/// several image sizes need not bake it again. Panics if the bake fails.
pub fn shared_bake(
    kind: &dyn TechniqueKind,
    context: &SceneContext,
    params: &[(String, String)],
) -> Arc<Vec<u8>> {
    /// Technique, scene fingerprint, parameters.
    type BakeKey = (String, u64, Vec<(String, String)>);
    static BAKES: OncePerProcess<BakeKey, Vec<u8>> = OncePerProcess::new();
    let key = (
        kind.name().to_string(),
        context.fingerprint(),
        params.to_vec(),
    );
    BAKES.get_or_compute(key, || {
        kind.bake(context, params, &NoProgress)
            .unwrap_or_else(|error| panic!("{} bakes: {error}", kind.name()))
    })
}

/// A closed room whose every surface reflects `albedo` (grey), with four
/// boxes on its floor
/// ([`relight_scene::generate::room_with_objects_on_its_floor_obj`]) and a
/// point light under its ceiling: nearly all light stays in, so at albedo
/// 0.9 most of it arrives after many bounces.
pub fn closed_grey_room(albedo: f32) -> Arc<SceneContext> {
    let (obj, _) = relight_scene::generate::room_with_objects_on_its_floor_obj();
    let tail =
        "[[lights]]\nkind = \"point\"\nposition = [0.3, 2.2, -0.4]\nintensity = [2.0, 2.0, 2.0]\n";
    let mut scene = relight_scene::generate::load_obj_scene(&obj, tail)
        .unwrap_or_else(|error| panic!("the generated room loads: {error}"));
    for material in &mut scene.materials {
        material.albedo = relight_core::Rgb::splat(albedo);
    }
    Arc::new(
        SceneContext::new(scene, crate::ContextSettings::default())
            .unwrap_or_else(|error| panic!("the generated room's context: {error}")),
    )
}

/// Checks a feedback technique's first update in [`closed_grey_room`]
/// (`context`) at albedo 0.9, where most light arrives after many bounces:
/// its feedback passes must stop on their own, after more than the old
/// fixed 16 and before `cap`, and its lightmap must be within 1 % of what
/// 300 more updates under the same lights reach (the rest of the series
/// after 300 more passes is below 1e-6 at this albedo). Panics otherwise;
/// returns the passes and that share.
pub fn check_first_update_settles(
    technique: &mut dyn Technique,
    context: &SceneContext,
    cap: u32,
) -> (u32, f64) {
    let passes = technique.timings().feedback_passes;
    assert!((17..cap).contains(&passes), "{passes} passes");
    let share = settled_share(technique, &context.scene.lights, 300);
    assert!(
        (0.99..=1.01).contains(&share),
        "{share} after {passes} passes"
    );
    (passes, share)
}

/// The summed luminance of `technique`'s lightmap after the update it has
/// had, over the same after `more` further updates under `lights`: 1 when
/// that update had already settled every bounce, less when feedback
/// passes were still adding light. Panics if the technique keeps no
/// lightmap or an update fails.
pub fn settled_share(technique: &mut dyn Technique, lights: &[Light], more: u32) -> f64 {
    let total = |technique: &dyn Technique| -> f64 {
        technique
            .receiver_irradiance()
            .expect("the technique keeps a lightmap")
            .iter()
            .map(|&value| f64::from(relight_core::luminance(value)))
            .sum()
    };
    let first = total(technique);
    for index in 1..=more {
        // Each a bounce more, as before the light counted as settled.
        technique.forget_last_frame();
        technique
            .update(&Frame {
                lights,
                index: u64::from(index),
                camera: None,
                moving_mesh_poses: None,
            })
            .unwrap_or_else(|error| panic!("update {index}: {error}"));
    }
    first / total(technique)
}

/// Loads `mutations` copies of `payload`, each with one to four random bit
/// flips or a truncation, and runs one update with every copy the
/// technique accepts. Panics, naming the mutation, if any copy panics.
/// Returns (accepted, refused).
///
/// The first tenth of the copies load with `params` as given; the rest
/// with the final gather off (`final_gather=0`). The gather's set-up reads
/// the scene, never the payload, and repeated at every load it was most of
/// the check's time, while a copy's bytes are read the same either way.
pub fn check_damaged_payloads(
    kind: &dyn TechniqueKind,
    context: &Arc<SceneContext>,
    params: &[(String, String)],
    payload: &[u8],
    mutations: usize,
    seed: u64,
) -> (usize, usize) {
    let mut rng = Pcg32::new(seed, 0xBAD);
    let (mut accepted, mut refused) = (0, 0);
    let lights = context.scene.lights.clone();
    let without_gather: Vec<(String, String)> = params
        .iter()
        .filter(|(key, _)| key != "final_gather")
        .cloned()
        .chain([("final_gather".to_string(), "0".to_string())])
        .collect();
    let with_gather = mutations.div_ceil(10);
    for mutation in 0..mutations {
        let params = if mutation < with_gather {
            params
        } else {
            &without_gather
        };
        let mut bytes = payload.to_vec();
        if rng.next_u32().is_multiple_of(8) {
            bytes.truncate(rng.next_u32() as usize % bytes.len().max(1));
        } else {
            for _ in 0..1 + rng.next_u32() % 4 {
                let at = rng.next_u32() as usize % bytes.len();
                bytes[at] ^= 1 << (rng.next_u32() % 8);
            }
        }
        let outcome = catch_unwind(AssertUnwindSafe(|| {
            match kind.create(context.clone(), Some(&bytes), params, &NoProgress) {
                Ok(mut technique) => technique
                    .update(&Frame {
                        lights: &lights,
                        index: 0,
                        camera: None,
                        moving_mesh_poses: None,
                    })
                    .is_ok(),
                Err(_) => false,
            }
        }));
        match outcome {
            Ok(true) => accepted += 1,
            Ok(false) => refused += 1,
            Err(_) => panic!(
                "{}: damaged payload {mutation} (seed {seed}) panicked instead of being refused",
                kind.name()
            ),
        }
    }
    (accepted, refused)
}

/// Bakes `params` whole on every thread, then in `count` shards, shard `i`
/// on `1 + i % 2` threads, and merges them: panics unless the merge gives
/// the whole bake's bytes, and unless merging the shards out of order or
/// with one missing is an error, and unless damaged shards (bit flips,
/// truncations) merge or are refused without a panic. Returns the whole
/// bake.
pub fn check_shards_merge_to_whole(
    kind: &dyn TechniqueKind,
    context: &SceneContext,
    params: &[(String, String)],
    count: u32,
) -> Vec<u8> {
    let on_threads = |threads: usize, work: &(dyn Fn() -> Vec<u8> + Sync)| {
        rayon::ThreadPoolBuilder::new()
            .num_threads(threads)
            .build()
            .expect("a thread pool")
            .install(work)
    };
    let whole = kind
        .bake(context, params, &NoProgress)
        .expect("the whole bake succeeds");
    let shards: Vec<Vec<u8>> = (0..count)
        .map(|index| {
            let shard = crate::Shard::new(index, count).expect("a valid shard");
            on_threads(1 + index as usize % 2, &|| {
                kind.bake_shard(context, params, shard, &NoProgress)
                    .expect("the shard bakes")
            })
        })
        .collect();
    let merged = kind
        .merge_shards(shards.clone(), &NoProgress)
        .expect("the shards merge");
    assert!(
        merged == whole,
        "{}: {count} shards merged ({} bytes) differ from the whole bake ({} bytes)",
        kind.name(),
        merged.len(),
        whole.len()
    );
    if count > 1 {
        let mut reversed = shards.clone();
        reversed.reverse();
        assert!(kind.merge_shards(reversed, &NoProgress).is_err());
        assert!(kind
            .merge_shards(shards[..shards.len() - 1].to_vec(), &NoProgress)
            .is_err());
    }
    let mut rng = Pcg32::new(count as u64, 0x5AAD);
    for mutation in 0..60 {
        let mut damaged = shards.clone();
        let victim = &mut damaged[rng.next_u32() as usize % count as usize];
        if mutation % 6 == 0 {
            victim.truncate(rng.next_u32() as usize % victim.len().max(1));
        } else {
            let at = rng.next_u32() as usize % victim.len();
            victim[at] ^= 1 << (rng.next_u32() % 8);
        }
        let outcome = catch_unwind(AssertUnwindSafe(|| {
            let _ = kind.merge_shards(damaged, &NoProgress);
        }));
        assert!(
            outcome.is_ok(),
            "{}: damaged shard {mutation} panicked the merge",
            kind.name()
        );
    }
    whole
}
