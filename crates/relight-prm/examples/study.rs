//! PRM parameter study: one path-traced reference lightmap (cached on disk,
//! since it costs far more than the bakes), then the lightmap relRMSE of
//! PRM for each parameter set given on the command line.
//!
//! Run: `cargo run --release -p relight-prm --example study -- SCENE.toml
//! RESOLUTION REFERENCE_SAMPLES "clusters=256,top_k=0" "top_k=32" ...`
//! (RESOLUTION 0 = the automatic lightmap size).

use relight_core::Rgb;
use relight_prm::PrmKind;
use relight_render::metrics::error_norms;
use relight_render::study::{cached_reference_lightmap, parse_pairs, study_context};
use relight_technique::{Frame, NoProgress, TechniqueKind};
use std::collections::HashMap;
use std::time::Instant;

fn main() {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let [scene_path, resolution, samples, sets @ ..] = args.as_slice() else {
        eprintln!("usage: study SCENE.toml RESOLUTION REFERENCE_SAMPLES PARAMS...");
        std::process::exit(2);
    };
    let resolution: u32 = resolution.parse().expect("resolution");
    let samples: u32 = samples.parse().expect("reference samples");
    let context = study_context(scene_path, resolution);
    let (reference, noise) = cached_reference_lightmap(&context, samples);
    println!(
        "{scene_path}: {} receivers, reference {samples} paths, noise {:.2} %",
        reference.len(),
        noise * 100.0
    );
    let lights = context.scene.lights.clone();
    let mut first: Option<Vec<Rgb>> = None;
    let mut bakes: HashMap<Vec<(String, String)>, Vec<u8>> = HashMap::new();
    for set in sets {
        let params = parse_pairs(set);
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
