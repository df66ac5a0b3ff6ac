//! PRM against the path tracer on the shipped scenes, determinism of the
//! bake, and bake-file robustness.

use relight_prm::{PrmBake, PrmKind, PrmParams};
use relight_render::metrics::{error_norms, relative_noise};
use relight_scene::atlas::TexelDensity;
use relight_technique::{
    reference_receiver_irradiance, ContextSettings, Frame, NoProgress, SceneContext, TechniqueKind,
};
use relight_trace::path::PathSettings;
use std::path::Path;
use std::sync::Arc;

fn context(scene: &str, resolution: u32) -> Arc<SceneContext> {
    let path = Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("../../scenes")
        .join(scene)
        .join("scene.toml");
    let scene = relight_scene::load_scene(&path).expect("shipped scene loads");
    let settings = ContextSettings {
        lightmap: TexelDensity::TargetResolution(resolution),
        ..ContextSettings::default()
    };
    Arc::new(SceneContext::new(scene, settings).unwrap())
}

/// Lightmap relRMSE of PRM against a path-traced reference, for each top_k,
/// and the reference's own noise.
fn lightmap_errors(
    scene: &str,
    bake_params: &[(String, String)],
    top_ks: &[u32],
) -> (Vec<f64>, f64) {
    let context = context(scene, 64);
    let lights = context.scene.lights.clone();
    let reference = reference_receiver_irradiance(
        &context,
        &lights,
        PathSettings::default(),
        2048,
        &NoProgress,
    );
    let noise = relative_noise(&reference.mean, &reference.standard_error);
    let bake = PrmKind.bake(&context, bake_params, &NoProgress).unwrap();
    let errors = top_ks
        .iter()
        .map(|top_k| {
            let params = [("top_k".to_string(), top_k.to_string())];
            let mut prm = PrmKind
                .create(context.clone(), Some(&bake), &params, &NoProgress)
                .unwrap();
            prm.update(&Frame {
                lights: &lights,
                index: 0,
            })
            .unwrap();
            error_norms(prm.receiver_irradiance().unwrap(), &reference.mean).relative_rmse
        })
        .collect();
    (errors, noise)
}

#[test]
fn cornell_box_area_light_within_bound_and_error_grows_as_k_falls() {
    let (errors, noise) = lightmap_errors("cornell-box", &[], &[0, 32, 8]);
    eprintln!(
        "cornell-box: all {:.4}, K=32 {:.4}, K=8 {:.4}; reference noise {noise:.4}",
        errors[0], errors[1], errors[2]
    );
    // The bound for all clusters is 15 %; the reference's own noise
    // (about 3 % here) is part of the measured error, so the test allows the
    // bound plus nothing: the measured value must already be under 15 %.
    assert!(errors[0] < 0.15, "all clusters: {}", errors[0]);
    assert!(errors[0] < errors[1] && errors[1] < errors[2], "{errors:?}");
}

#[test]
fn corridor_light_paths_within_bound_without_clustering() {
    // One pane per entry point isolates the light-path estimator from the
    // clustering approximation. (With the default 256 clusters the corridor
    // measures about 21 %: its point light sits close to the ceiling, so
    // irradiance varies strongly inside a cluster; that gap is open work.)
    let params = [("clusters".to_string(), "4096".to_string())];
    let (errors, noise) = lightmap_errors("corridor", &params, &[0]);
    eprintln!(
        "corridor, no clustering: {:.4}; reference noise {noise:.4}",
        errors[0]
    );
    assert!(errors[0] < 0.15, "no clustering: {}", errors[0]);
}

#[test]
fn bake_is_identical_on_one_and_two_threads() {
    let context = context("cornell-box-point", 32);
    let params = PrmParams {
        entries: 512,
        clusters: 32,
        ..PrmParams::default()
    };
    let bake_with = |threads: usize| {
        let pool = rayon::ThreadPoolBuilder::new()
            .num_threads(threads)
            .build()
            .unwrap();
        pool.install(|| {
            PrmBake::build(&context, &params, &NoProgress)
                .unwrap()
                .encode()
        })
    };
    assert!(bake_with(1) == bake_with(2));
}

#[test]
fn corrupt_payloads_are_errors_not_panics() {
    let context = context("cornell-box-point", 32);
    let params = PrmParams {
        entries: 256,
        clusters: 16,
        ..PrmParams::default()
    };
    let bytes = PrmBake::build(&context, &params, &NoProgress)
        .unwrap()
        .encode();
    assert_eq!(PrmBake::decode(&bytes).unwrap().encode(), bytes);
    for cut in [0, 3, 17, bytes.len() / 2, bytes.len() - 1] {
        assert!(PrmBake::decode(&bytes[..cut]).is_err(), "cut at {cut}");
    }
    let mut lying = bytes.clone();
    lying[12..16].copy_from_slice(&u32::MAX.to_le_bytes()); // cluster count
    assert!(PrmBake::decode(&lying).is_err());
}

#[test]
fn oversized_bakes_are_refused_with_advice() {
    let context = context("cornell-box-point", 64);
    let params = [("max_memory_mib".to_string(), "1".to_string())];
    let error = PrmKind
        .bake(&context, &params, &NoProgress)
        .unwrap_err()
        .to_string();
    assert!(
        error.contains("clusters") && error.contains("max_memory_mib"),
        "{error}"
    );
}
