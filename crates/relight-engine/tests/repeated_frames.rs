//! An engine may update a technique every frame: a frame that repeats the
//! last one is skipped once the light has settled, and feedback techniques
//! (PIC, SRP, and PRM through its final gather) keep updating a resting
//! scene only while their bounces still add light. The four GI techniques on the point-lit Cornell box, with
//! its light moved across the box.

use relight_core::Rgb;
use relight_scene::{Camera, Light};
use relight_technique::{
    ContextSettings, Frame, NoProgress, SceneContext, Technique, TechniqueKind, SETTLED_SHARE,
};
use std::path::Path;
use std::sync::Arc;

fn frame<'a>(lights: &'a [Light], index: u64, camera: Option<&'a Camera>) -> Frame<'a> {
    Frame {
        lights,
        index,
        camera,
        moving_mesh_poses: None,
    }
}

/// relRMSE of `values` against `truth` over the receivers' colours.
fn relative_rms(values: &[Rgb], truth: &[Rgb]) -> f64 {
    let (mut error, mut norm) = (0.0f64, 0.0f64);
    for (value, truth) in values.iter().zip(truth) {
        for channel in 0..3 {
            error += f64::from(value[channel] - truth[channel]).powi(2);
            norm += f64::from(truth[channel]).powi(2);
        }
    }
    (error / norm.max(f64::MIN_POSITIVE)).sqrt()
}

fn created(kind: &dyn TechniqueKind, context: &Arc<SceneContext>) -> Box<dyn Technique> {
    let bake = kind
        .needs_bake()
        .then(|| kind.bake(context, &[], &NoProgress).unwrap());
    kind.create(context.clone(), bake.as_deref(), &[], &NoProgress)
        .unwrap()
}

#[test]
fn repeated_frames_are_skipped_once_the_light_settles() {
    let path =
        Path::new(env!("CARGO_MANIFEST_DIR")).join("../../scenes/cornell-box-point/scene.toml");
    let scene = relight_scene::load_scene(&path).expect("shipped scene loads");
    let context = Arc::new(SceneContext::new(scene, ContextSettings::default()).unwrap());
    let start_lights = context.scene.lights.clone();
    // From the ceiling's middle to near the green wall's front corner: the
    // bounce light changes everywhere.
    let moved_lights: Vec<Light> = start_lights
        .iter()
        .map(|light| match *light {
            Light::Point {
                position,
                intensity,
            } => Light::Point {
                position: position + glam::Vec3::new(0.17, -0.15, -0.12),
                intensity,
            },
            _ => panic!("the point-lit box has one point light"),
        })
        .collect();
    let mut turned = context.scene.camera.clone();
    turned.eye += glam::Vec3::new(0.1, 0.05, 0.0);
    for &kind in relight_engine::techniques::kinds() {
        let name = kind.name();
        // The reference path traces every update; `direct` has no
        // indirect light to compare.
        if matches!(name, "reference" | "direct") {
            continue;
        }
        let mut technique = created(kind, &context);
        technique.update(&frame(&start_lights, 0, None)).unwrap();
        assert!(!technique.timings().skipped, "{name}: the first update ran");
        assert!(technique.settled(), "{name}: the first update settles");
        let before = technique.receiver_irradiance().unwrap().to_vec();
        // The same lights seen from elsewhere: no technique here has
        // view-dependent light in its update (the box has no glossy
        // surface).
        technique
            .update(&frame(&start_lights, 1, Some(&turned)))
            .unwrap();
        assert!(
            technique.timings().skipped,
            "{name}: a camera move is skipped"
        );
        assert_eq!(
            technique.receiver_irradiance().unwrap(),
            &before[..],
            "{name}"
        );

        technique.update(&frame(&moved_lights, 2, None)).unwrap();
        assert!(!technique.timings().skipped, "{name}: moved lights update");
        let after_move = technique.receiver_irradiance().unwrap().to_vec();
        assert!(
            relative_rms(&after_move, &before) > 0.05,
            "{name}: the light changed"
        );
        let mut settling_updates = 0;
        for index in 3..200 {
            technique
                .update(&frame(&moved_lights, index, None))
                .unwrap();
            if technique.timings().skipped {
                break;
            }
            settling_updates += 1;
        }
        assert!(technique.settled() && technique.timings().skipped, "{name}");
        let settled = technique.receiver_irradiance().unwrap().to_vec();
        technique.update(&frame(&moved_lights, 300, None)).unwrap();
        assert!(technique.timings().skipped, "{name}: settled stays skipped");

        // A fresh technique's first update settles in one call: the
        // resting updates must reach the same light. Each side leaves at
        // most SETTLED_SHARE of its light unadded by its own estimate, so
        // they may differ by twice that, and by as much again where the
        // estimate of a geometric series' tail falls short.
        let mut fresh = created(kind, &context);
        fresh.update(&frame(&moved_lights, 0, None)).unwrap();
        let truth = fresh.receiver_irradiance().unwrap();
        let settled_error = relative_rms(&settled, truth);
        // PIC and SRP feed their light back; PRM's final gather reflects
        // its last gathered near field. LightSkin is one bounce.
        let feedback = matches!(name, "pic" | "srp" | "prm");
        if feedback {
            let lagging_error = relative_rms(&after_move, truth);
            assert!(
                settling_updates >= 1 && lagging_error > 4.0 * f64::from(SETTLED_SHARE),
                "{name}: one update after the move ({settling_updates} more, {lagging_error:.4} off) left bounces to add"
            );
            assert!(
                settled_error < 4.0 * f64::from(SETTLED_SHARE),
                "{name}: settled at rest {settled_error:.4} off a fresh settled update after {settling_updates} updates (one after the move {lagging_error:.4})"
            );
        } else {
            assert_eq!(settling_updates, 0, "{name}: one bounce settles at once");
            assert_eq!(settled, after_move, "{name}");
            assert!(
                settled_error < 1e-6,
                "{name}: {settled_error} off a fresh update"
            );
        }
        println!(
            "{name}: {settling_updates} settling updates, {settled_error:.5} off a fresh update, {:.5} one update after the move",
            relative_rms(&after_move, truth)
        );
    }
}
