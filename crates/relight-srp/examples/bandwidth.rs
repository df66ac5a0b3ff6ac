//! The machine's streaming read bandwidth on all threads, the floor under
//! SRP's reconstruction (every f16 weight of every receiver read once per
//! frame): sums a 256 MiB buffer several times and prints GB/s.
//!
//! Run: `cargo run --release -p relight-srp --example bandwidth`

use rayon::prelude::*;
use std::time::Instant;

fn main() {
    let values = vec![1.0f32; 64 << 20];
    let mut best = f64::INFINITY;
    let mut total = 0.0f32;
    for _ in 0..10 {
        let start = Instant::now();
        total += values
            .par_chunks(1 << 16)
            .map(|chunk| {
                // Eight lanes so the sum is not bound by one add chain.
                let mut lanes = [0.0f32; 8];
                for block in chunk.chunks_exact(8) {
                    for (lane, value) in lanes.iter_mut().zip(block) {
                        *lane += value;
                    }
                }
                lanes.iter().sum::<f32>()
            })
            .sum::<f32>();
        best = best.min(start.elapsed().as_secs_f64());
    }
    let bytes = (values.len() * 4) as f64;
    println!(
        "read bandwidth: {:.1} GB/s on {} threads (best of 10 passes over {} MiB; checksum {total})",
        bytes / best / 1e9,
        rayon::current_num_threads(),
        bytes as usize >> 20
    );
}
