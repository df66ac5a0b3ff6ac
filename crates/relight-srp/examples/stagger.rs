//! What staggered probe updates cost: the lights orbit the scene (as in
//! `relight bench`) and, frame by frame, the lightmap of SRP refreshing
//! `budget` probes per frame is compared with SRP refreshing every probe.
//!
//! Run: `cargo run --release -p relight-srp --example stagger -- SCENE.toml
//! FRAMES BUDGET [BUDGET ...]`

use glam::Quat;
use relight_render::metrics::error_norms;
use relight_scene::atlas::TexelDensity;
use relight_srp::SrpKind;
use relight_technique::{ContextSettings, Frame, NoProgress, SceneContext, TechniqueKind};
use std::sync::Arc;

fn main() {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let [scene_path, frames, budgets @ ..] = args.as_slice() else {
        eprintln!("usage: stagger SCENE.toml FRAMES BUDGET...");
        std::process::exit(2);
    };
    let frames: u32 = frames.parse().expect("frames");
    let scene = relight_scene::load_scene(std::path::Path::new(scene_path)).expect("scene loads");
    let settings = ContextSettings {
        lightmap: TexelDensity::from_resolution(None),
        ..ContextSettings::default()
    };
    let context = Arc::new(SceneContext::new(scene, settings).expect("context"));
    let bake = SrpKind.bake(&context, &[], &NoProgress).expect("bake");
    let (lo, hi) = context.scene.mesh.bounds();
    let centre = (lo + hi) * 0.5;
    let lights_of = |index: u32| {
        let rotation = Quat::from_rotation_y(std::f32::consts::TAU * index as f32 / frames as f32);
        context
            .scene
            .lights
            .iter()
            .map(|light| light.rotated_about(centre, rotation))
            .collect::<Vec<_>>()
    };
    for budget in budgets {
        let create = |pairs: &[(String, String)]| {
            SrpKind
                .create(context.clone(), Some(&bake), pairs, &NoProgress)
                .expect("create")
        };
        let mut full = create(&[]);
        let mut staggered = create(&[("probe_budget".to_string(), budget.clone())]);
        let mut errors = Vec::new();
        // Squared differences and squared full values summed over the
        // orbit: frames where the lights leave the scene have almost no
        // indirect light, and a per-frame relative error would be all noise.
        let (mut difference, mut magnitude) = (0.0f64, 0.0f64);
        // The same measure between consecutive full frames: how much the
        // light itself changes per frame, the scale stale probes lag by.
        let mut change = 0.0f64;
        let mut previous: Option<Vec<relight_core::Rgb>> = None;
        for index in 0..frames {
            let lights = lights_of(index);
            let frame = Frame {
                lights: &lights,
                index: index as u64,
                camera: None,
                moving_mesh_poses: None,
            };
            full.update(&frame).expect("update");
            staggered.update(&frame).expect("update");
            let (ours, truth) = (
                staggered.receiver_irradiance().unwrap(),
                full.receiver_irradiance().unwrap(),
            );
            for (a, b) in ours.iter().zip(truth) {
                difference += (*a - *b).length_squared() as f64;
                magnitude += b.length_squared() as f64;
            }
            errors.push(error_norms(ours, truth).relative_rmse);
            if let Some(previous) = &previous {
                for (a, b) in previous.iter().zip(truth) {
                    change += (*a - *b).length_squared() as f64;
                }
            }
            previous = Some(truth.to_vec());
        }
        errors.sort_by(|a, b| a.total_cmp(b));
        println!(
            "budget {budget:>4} probes/frame: relRMSE against refreshing all over the orbit {:.2} %; per frame median {:.2} % ({frames} frames, a full orbit; consecutive full frames differ by {:.2} %)",
            (difference / magnitude).sqrt() * 100.0,
            errors[errors.len() / 2] * 100.0,
            (change / magnitude).sqrt() * 100.0
        );
    }
}
