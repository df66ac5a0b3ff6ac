//! This machine's peak of 8-wide fused multiply-adds, the bound the
//! gathering kernel is compared with: twelve independent accumulators per
//! thread (enough to hide the FMA latency), one thread per core.
//!
//! `cargo run --release -p relight-lightskin --example fma_peak [THREADS]`

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2,fma")]
unsafe fn fma_loop(iterations: u64) -> f32 {
    use std::arch::x86_64::*;
    let mut accumulators = [_mm256_set1_ps(1.0); 12];
    let scale = _mm256_set1_ps(0.999_999);
    let offset = _mm256_set1_ps(1e-7);
    for _ in 0..iterations {
        for accumulator in &mut accumulators {
            *accumulator = _mm256_fmadd_ps(*accumulator, scale, offset);
        }
    }
    let mut lanes = [0f32; 8];
    let mut total = 0.0;
    for accumulator in accumulators {
        _mm256_storeu_ps(lanes.as_mut_ptr(), accumulator);
        total += lanes[0];
    }
    total
}

fn main() {
    #[cfg(target_arch = "x86_64")]
    {
        if !(std::arch::is_x86_feature_detected!("avx2")
            && std::arch::is_x86_feature_detected!("fma"))
        {
            eprintln!("this CPU has no AVX2/FMA");
            return;
        }
        let threads: usize = std::env::args()
            .nth(1)
            .and_then(|value| value.parse().ok())
            .unwrap_or_else(|| std::thread::available_parallelism().map_or(1, |n| n.get()));
        let iterations = 200_000_000u64;
        let start = std::time::Instant::now();
        let handles: Vec<_> = (0..threads)
            // SAFETY: AVX2 and FMA were detected above.
            .map(|_| std::thread::spawn(move || unsafe { fma_loop(iterations) }))
            .collect();
        let checksum: f32 = handles.into_iter().map(|h| h.join().unwrap()).sum();
        let seconds = start.elapsed().as_secs_f64();
        let instructions = iterations as f64 * 12.0 * threads as f64;
        println!(
            "{threads} threads: {:.1} GFLOP/s, {:.2} G 8-wide FMA per second per thread (checksum {checksum})",
            instructions * 16.0 / seconds / 1e9,
            instructions / threads as f64 / seconds / 1e9
        );
    }
}
