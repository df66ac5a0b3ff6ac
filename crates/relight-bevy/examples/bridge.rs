//! What the Bevy plugin costs on a scene: the main thread's exchange each
//! frame (light sync, moving the finished lightmap and volume bytes into
//! Bevy's images) and the GI update's stages on the worker, as medians.
//!
//! cargo run --release -p relight-bevy --example bridge -- SCENE.toml \
//!     --technique T [--bake F] [--frames N] [--fps F] [--worker-threads N]
//!     [--single-threaded-schedules]

use clap::Parser;
use relight_bevy::snapshot::{run_bridge, BridgeSettings};
use relight_bevy::RelightScene;
use std::path::PathBuf;
use std::process::ExitCode;
use std::time::Duration;

#[derive(Parser)]
struct Args {
    scene: PathBuf,
    #[arg(long, short, default_value = "lightskin")]
    technique: String,
    #[arg(long)]
    bake: Option<PathBuf>,
    /// GI updates measured (after three to warm up).
    #[arg(long, default_value_t = 20)]
    frames: u64,
    /// Frames a second the app is paced at (a display's refresh; 0: back
    /// to back).
    #[arg(long, default_value_t = 60.0)]
    fps: f64,
    /// Irradiance-volume voxels along the longest side (0: none).
    #[arg(long, default_value_t = 16)]
    volume_cells: u32,
    /// Threads of the GI update (0: every core).
    #[arg(long, default_value_t = 0)]
    worker_threads: usize,
    /// Run Bevy's schedules on the main thread instead of its task pools.
    #[arg(long)]
    single_threaded_schedules: bool,
}

fn median(mut values: Vec<f64>) -> f64 {
    values.sort_by(f64::total_cmp);
    values.get(values.len() / 2).copied().unwrap_or(0.0)
}

fn main() -> ExitCode {
    let args = Args::parse();
    let mut scene = RelightScene::new(&args.scene).technique(&args.technique);
    scene.bake = args.bake.clone();
    scene.volume_cells = args.volume_cells;
    scene.worker_threads = args.worker_threads;
    let interval = if args.fps > 0.0 {
        Duration::from_secs_f64(1.0 / args.fps)
    } else {
        Duration::ZERO
    };
    let settings = BridgeSettings {
        warm_up: 3,
        gi_updates: args.frames,
        frame_interval: interval,
        timeout: Duration::from_secs(3600),
        single_threaded_schedules: args.single_threaded_schedules,
    };
    let run = match run_bridge(&scene, &settings) {
        Ok(run) => run,
        Err(message) => {
            eprintln!("error: {message}");
            return ExitCode::FAILURE;
        }
    };
    println!(
        "{} on {}: {} GI updates over {} frames",
        args.technique,
        args.scene.display(),
        run.updates.len(),
        run.bridge_ms.len()
    );
    println!("{:<32} {:>10}", "worker stage", "median ms");
    let mut names: Vec<String> = Vec::new();
    for update in &run.updates {
        for (name, _) in update {
            if !names.contains(name) {
                names.push(name.clone());
            }
        }
    }
    for name in &names {
        let samples: Vec<f64> = run
            .updates
            .iter()
            .filter_map(|update| update.iter().find(|(stage, _)| stage == name))
            .map(|(_, ms)| *ms)
            .collect();
        println!("{name:<32} {:>10.3}", median(samples));
    }
    let technique_total: Vec<f64> = run
        .updates
        .iter()
        .map(|update| {
            update
                .iter()
                .filter(|(name, _)| name != "lightmap RGBA16F" && name != "irradiance volume")
                .map(|(_, ms)| ms)
                .sum()
        })
        .collect();
    println!(
        "{:<32} {:>10.3}",
        "technique total",
        median(technique_total)
    );
    println!(
        "{:<32} {:>10.3}",
        "bridge (main thread, a frame)",
        median(run.bridge_ms.clone())
    );
    let mut sorted = run.bridge_ms.clone();
    sorted.sort_by(f64::total_cmp);
    println!(
        "{:<32} {:>10.3}",
        "bridge max",
        sorted.last().copied().unwrap_or(0.0)
    );
    println!(
        "{:<32} {:>10.3}",
        "Bevy frame (main + render, ms)",
        median(run.frame_ms.clone())
    );
    println!(
        "{:<32} {:>10.1}",
        "GI age (frames, median)",
        median(run.gi_age_frames.iter().map(|&age| age as f64).collect())
    );
    ExitCode::SUCCESS
}
