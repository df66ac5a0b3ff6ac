//! PRM parameter study: one path-traced reference lightmap (cached on disk,
//! since it costs far more than the bakes), then the lightmap relRMSE of
//! PRM for each parameter set given on the command line.
//!
//! Run: `cargo run --release -p relight-prm --example study -- SCENE.toml
//! RESOLUTION REFERENCE_SAMPLES "clusters=256,top_k=0" "top_k=32" ...`
//! (RESOLUTION 0 = the automatic lightmap size).

use relight_core::Rgb;
use relight_prm::PrmKind;
use relight_render::metrics::{error_norms, relative_noise};
use relight_scene::atlas::TexelDensity;
use relight_technique::{
    reference_receiver_irradiance, ContextSettings, Frame, NoProgress, SceneContext, TechniqueKind,
};
use relight_trace::path::PathSettings;
use std::collections::HashMap;
use std::sync::Arc;
use std::time::Instant;

fn cached_reference(context: &SceneContext, key: &str, samples: u32) -> (Vec<Rgb>, f64) {
    let file = std::env::temp_dir().join(format!("relight-study-{key}.f32"));
    let count = context.atlas.receivers.len();
    if let Ok(bytes) = std::fs::read(&file) {
        if bytes.len() == (count * 3 + 1) * 4 {
            let values: Vec<f32> = bytes
                .chunks_exact(4)
                .map(|b| f32::from_le_bytes(b.try_into().unwrap()))
                .collect();
            let noise = values[count * 3] as f64;
            let mean = values[..count * 3]
                .chunks_exact(3)
                .map(|v| Rgb::new(v[0], v[1], v[2]))
                .collect();
            return (mean, noise);
        }
    }
    let lights = context.scene.lights.clone();
    let reference = reference_receiver_irradiance(
        context,
        &lights,
        PathSettings::default(),
        samples,
        &NoProgress,
    );
    let noise = relative_noise(&reference.mean, &reference.standard_error);
    let mut bytes = Vec::with_capacity((count * 3 + 1) * 4);
    for value in &reference.mean {
        for component in value.to_array() {
            bytes.extend_from_slice(&component.to_le_bytes());
        }
    }
    bytes.extend_from_slice(&(noise as f32).to_le_bytes());
    std::fs::write(&file, bytes).expect("write the reference cache");
    (reference.mean, noise)
}

fn parse(set: &str) -> Vec<(String, String)> {
    set.split(',')
        .filter(|part| !part.is_empty())
        .map(|part| {
            let (key, value) = part.split_once('=').expect("key=value");
            (key.to_string(), value.to_string())
        })
        .collect()
}

fn main() {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let [scene_path, resolution, samples, sets @ ..] = args.as_slice() else {
        eprintln!("usage: study SCENE.toml RESOLUTION REFERENCE_SAMPLES PARAMS...");
        std::process::exit(2);
    };
    let resolution: u32 = resolution.parse().expect("resolution");
    let samples: u32 = samples.parse().expect("reference samples");
    let scene = relight_scene::load_scene(std::path::Path::new(scene_path)).expect("scene loads");
    let settings = ContextSettings {
        lightmap: TexelDensity::from_resolution(Some(resolution).filter(|&r| r != 0)),
        ..ContextSettings::default()
    };
    let context = Arc::new(SceneContext::new(scene, settings).expect("context"));
    let key = format!(
        "{}-{}-{}-{}",
        context.fingerprint(),
        context.atlas.width,
        context.atlas.receivers.len(),
        samples
    );
    let (reference, noise) = cached_reference(&context, &key, samples);
    println!(
        "{scene_path}: {} receivers, reference {samples} paths, noise {:.2} %",
        reference.len(),
        noise * 100.0
    );
    let lights = context.scene.lights.clone();
    let mut first: Option<Vec<Rgb>> = None;
    let mut bakes: HashMap<Vec<(String, String)>, Vec<u8>> = HashMap::new();
    for set in sets {
        let params = parse(set);
        let bake_params: Vec<(String, String)> = params
            .iter()
            .filter(|(key, _)| relight_prm::BAKE_PARAMETERS.contains(&key.as_str()))
            .cloned()
            .collect();
        let started = Instant::now();
        let bake = bakes.entry(bake_params.clone()).or_insert_with(|| {
            PrmKind
                .bake(&context, &bake_params, &NoProgress)
                .expect("bake")
        });
        let bake_seconds = started.elapsed().as_secs_f64();
        let mut prm = PrmKind
            .create(context.clone(), Some(bake), &params, &NoProgress)
            .expect("create");
        prm.update(&Frame {
            lights: &lights,
            index: 0,
        })
        .expect("update");
        let values = prm.receiver_irradiance().unwrap();
        let norms = error_norms(values, &reference);
        // Against the first parameter set too: that isolates what a change
        // (clustering, compression) costs from the error both share.
        let against_first = first
            .as_ref()
            .map(|first| error_norms(values, first).relative_rmse * 100.0)
            .unwrap_or(0.0);
        println!(
            "{set:40} relRMSE {:6.2} %  MRE {:6.2} %  vs first {against_first:6.2} %  (bake {bake_seconds:.1} s, {:.1} MiB)",
            norms.relative_rmse * 100.0,
            norms.mean_relative_error * 100.0,
            bake.len() as f64 / 1048576.0
        );
        let decoded = relight_prm::PrmBake::decode(bake).expect("decode");
        let sizes = decoded.cluster_sizes();
        println!(
            "    captured energy {:.6}, empty clusters {}, largest cluster {}",
            decoded.captured_energy,
            sizes.iter().filter(|&&size| size == 0).count(),
            sizes.iter().max().unwrap()
        );
        if first.is_none() {
            first = Some(values.to_vec());
        }
    }
}
