//! Clustering against flicker: moves the corridor's lights along a slow
//! orbit and reports, per cluster count, the lightmap error against the
//! path tracer and the frame-to-frame change of the indirect lightmap next
//! to the reference's own frame-to-frame change.
//!
//! Run: `cargo run --release -p relight-prm --example flicker [SCENE.toml [RESOLUTION]]`

use glam::{Quat, Vec3};
use relight_prm::PrmKind;
use relight_render::metrics::error_norms;
use relight_scene::atlas::TexelDensity;
use relight_scene::Light;
use relight_technique::{
    reference_receiver_irradiance, ContextSettings, Frame, NoProgress, SceneContext, TechniqueKind,
};
use relight_trace::path::PathSettings;
use std::sync::Arc;

const FRAMES: u32 = 12;
/// One degree per frame: the light moves a few centimetres each frame.
const DEGREES_PER_FRAME: f32 = 1.0;

fn orbit(lights: &[Light], centre: Vec3, frame: u32) -> Vec<Light> {
    let rotation = Quat::from_rotation_y((frame as f32 * DEGREES_PER_FRAME).to_radians());
    lights
        .iter()
        .map(|light| light.rotated_about(centre, rotation))
        .collect()
}

/// Mean over consecutive frames of ||L_t - L_(t-1)|| / ||L_t||.
fn mean_change(frames: &[Vec<relight_core::Rgb>]) -> f64 {
    let changes: Vec<f64> = frames
        .windows(2)
        .map(|pair| error_norms(&pair[0], &pair[1]).relative_rmse)
        .collect();
    changes.iter().sum::<f64>() / changes.len().max(1) as f64
}

fn main() {
    let path = std::env::args().nth(1).unwrap_or_else(|| {
        concat!(
            env!("CARGO_MANIFEST_DIR"),
            "/../../scenes/corridor/scene.toml"
        )
        .to_string()
    });
    let scene = relight_scene::load_scene(std::path::Path::new(&path)).expect("scene loads");
    // Second argument: lightmap resolution (0 or absent: automatic).
    let resolution = std::env::args()
        .nth(2)
        .map(|value| value.parse::<u32>().expect("resolution"))
        .filter(|&resolution| resolution != 0);
    let settings = ContextSettings {
        lightmap: TexelDensity::from_resolution(resolution),
        ..ContextSettings::default()
    };
    let context = Arc::new(SceneContext::new(scene, settings).expect("context"));
    let (lo, hi) = context.scene.mesh.bounds();
    let centre = (lo + hi) * 0.5;
    let lights: Vec<Vec<Light>> = (0..FRAMES)
        .map(|frame| orbit(&context.scene.lights, centre, frame))
        .collect();

    // Same seed every frame: the reference's frame-to-frame change is then
    // mostly the real change of the light, not independent noise.
    let reference: Vec<Vec<relight_core::Rgb>> = lights
        .iter()
        .map(|frame_lights| {
            reference_receiver_irradiance(
                &context,
                frame_lights,
                PathSettings::default(),
                1024,
                &NoProgress,
            )
            .mean
        })
        .collect();
    println!(
        "{path}: {} receivers, {FRAMES} frames, light orbit {DEGREES_PER_FRAME} degree per frame",
        context.atlas.receivers.len()
    );
    println!(
        "reference frame-to-frame change: {:.2} %",
        mean_change(&reference) * 100.0
    );
    println!("| clusters | rank | top_k | mean lightmap relRMSE | frame-to-frame change |");
    println!("|---:|---:|---:|---:|---:|");
    let runs: [(u32, u32, u32); 8] = [
        (64, 0, 0),
        (256, 0, 0),
        (256, 0, 32),
        (256, 32, 0),
        (256, 16, 0),
        (1024, 0, 0),
        (1024, 32, 0),
        (4096, 0, 0),
    ];
    for (clusters, rank, top_k) in runs {
        let bake = PrmKind
            .bake(
                &context,
                &[
                    ("clusters".into(), clusters.to_string()),
                    ("rank".into(), rank.to_string()),
                ],
                &NoProgress,
            )
            .expect("bake");
        {
            let mut prm = PrmKind
                .create(
                    context.clone(),
                    Some(&bake),
                    &[("top_k".into(), top_k.to_string())],
                    &NoProgress,
                )
                .expect("create");
            let mut frames = Vec::new();
            let mut error = 0.0;
            for (index, frame_lights) in lights.iter().enumerate() {
                prm.update(&Frame {
                    lights: frame_lights,
                    index: index as u64,
                    camera: None,
                    moving_mesh_poses: None,
                })
                .expect("update");
                let values = prm.receiver_irradiance().expect("lightmap").to_vec();
                error += error_norms(&values, &reference[index]).relative_rmse;
                frames.push(values);
            }
            println!(
                "| {clusters} | {rank} | {} | {:.1} % | {:.2} % |",
                if top_k == 0 {
                    "all".to_string()
                } else {
                    top_k.to_string()
                },
                error / FRAMES as f64 * 100.0,
                mean_change(&frames) * 100.0
            );
        }
    }
}
