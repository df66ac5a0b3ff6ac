//! Damaged bake payloads for tests: a technique must refuse them with an
//! error or run them, never panic ("no panics on any input file").

use crate::{Frame, NoProgress, SceneContext, TechniqueKind};
use relight_core::sampling::Pcg32;
use std::panic::{catch_unwind, AssertUnwindSafe};
use std::sync::Arc;

/// Loads `mutations` copies of `payload`, each with one to four random bit
/// flips or a truncation, and runs one update with every copy the
/// technique accepts. Panics, naming the mutation, if any copy panics.
/// Returns (accepted, refused).
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
    for mutation in 0..mutations {
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
