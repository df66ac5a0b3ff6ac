//! SRP parameter study: one path-traced reference lightmap (cached on disk),
//! then for each parameter set the lightmap relRMSE of SRP, its bake time
//! and the bake's own figures (probes, coverage, energy kept by CPCA).
//!
//! Run: `cargo run --release -p relight-srp --example study -- SCENE.toml
//! RESOLUTION REFERENCE_SAMPLES "order=7" "order=2" "probe_count=64" ...`
//! (RESOLUTION 0 = the automatic lightmap size).

use glam::Vec3;
use relight_core::{luminance, Rgb};
use relight_render::metrics::error_norms;
use relight_render::study::{cached_reference_lightmap, parse_pairs, study_context};
use relight_srp::{SrpBake, SrpKind, BAKE_PARAMETERS};
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
    // Bakes by their bake parameters, with the seconds each took.
    type Bakes = HashMap<Vec<(String, String)>, (Vec<u8>, f64)>;
    let mut bakes: Bakes = HashMap::new();
    for set in sets {
        let params = parse_pairs(set);
        let bake_params: Vec<(String, String)> = params
            .iter()
            .filter(|(key, _)| BAKE_PARAMETERS.contains(&key.as_str()))
            .cloned()
            .collect();
        let (bake, bake_seconds) = bakes.entry(bake_params.clone()).or_insert_with(|| {
            let started = Instant::now();
            let bake = SrpKind
                .bake(&context, &bake_params, &NoProgress)
                .expect("bake");
            (bake, started.elapsed().as_secs_f64())
        });
        let mut srp = SrpKind
            .create(context.clone(), Some(bake), &params, &NoProgress)
            .expect("create");
        srp.update(&Frame {
            lights: &lights,
            index: 0,
        })
        .expect("update");
        let values = srp.receiver_irradiance().expect("SRP keeps a lightmap");
        let norms = error_norms(values, &reference);
        // Against the first parameter set too: that isolates what a change
        // costs from the error both share.
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
        // Where the error sits: per dominant normal axis, and the ratio of
        // mean luminance (bias) to the reference's.
        let normals = &context.atlas.receivers.normals;
        let mut by_axis = String::new();
        for (name, axis) in [
            ("+x", Vec3::X),
            ("-x", -Vec3::X),
            ("+y", Vec3::Y),
            ("-y", -Vec3::Y),
            ("+z", Vec3::Z),
            ("-z", -Vec3::Z),
        ] {
            let members: Vec<usize> = (0..normals.len())
                .filter(|&i| normals[i].dot(axis) > 0.7)
                .collect();
            if members.is_empty() {
                continue;
            }
            let pick = |values: &[Rgb]| members.iter().map(|&i| values[i]).collect::<Vec<_>>();
            let norms = error_norms(&pick(values), &pick(&reference));
            let ratio = pick(values)
                .iter()
                .map(|v| luminance(*v) as f64)
                .sum::<f64>()
                / pick(&reference)
                    .iter()
                    .map(|v| luminance(*v) as f64)
                    .sum::<f64>();
            by_axis += &format!(" {name}: {:.1} % x{ratio:.3};", norms.relative_rmse * 100.0);
        }
        println!("   {by_axis}");
        if std::env::var_os("SRP_WORST").is_some() {
            let mut order: Vec<usize> = (0..values.len()).collect();
            let ratio = |i: usize| luminance(values[i]) / luminance(reference[i]).max(1e-6);
            let difference = |i: usize| (luminance(values[i]) - luminance(reference[i])).abs();
            order.sort_by(|&a, &b| difference(a).total_cmp(&difference(b)).reverse());
            let reference_map = context.atlas.to_lightmap(&reference);
            let direct = context.direct();
            for &i in order.iter().take(6) {
                // One gather step of the rendering equation from the
                // reference's own light: what exact probes would give.
                let position = context.atlas.receivers.positions[i] + normals[i] * 1e-4;
                let mut sum = Rgb::ZERO;
                let count = 4096;
                for sample in 0..count {
                    let mut rng = relight_core::SampleStream::new(9, i as u64, sample);
                    let direction = relight_core::sampling::cosine_hemisphere_around(
                        normals[i],
                        rng.next_vec2(),
                    );
                    let ray = relight_trace::Ray {
                        origin: position,
                        direction,
                        t_max: f32::INFINITY,
                    };
                    if let Some(hit) = context.bvh.intersect(&ray) {
                        let triangle = hit.triangle as usize;
                        let front = context.scene.mesh.geometric_normal(triangle);
                        if front.dot(direction) >= 0.0 {
                            continue;
                        }
                        let [a, b, c] = context.scene.mesh.vertices(triangle);
                        let point = a + (b - a) * hit.barycentric.x + (c - a) * hit.barycentric.y;
                        let irradiance = direct.irradiance(&lights, point, front, sample)
                            + context
                                .atlas
                                .sample(&reference_map, hit.triangle, hit.barycentric);
                        sum += context.scene.albedo_at(triangle, hit.barycentric) * irradiance;
                    }
                }
                let gathered = luminance(sum / count as f32);
                println!(
                    "    receiver {i} at {:.3} n {:.2}: srp/reference {:.3} (reference {:.4}, one gather {:.4})",
                    context.atlas.receivers.positions[i],
                    normals[i],
                    ratio(i),
                    luminance(reference[i]),
                    gathered
                );
            }
        }
        let decoded = SrpBake::decode(bake).expect("decode");
        let stats = &decoded.stats;
        println!(
            "    {} probes ({} added), radius {:.3}, {} receivers short of {}, {:.2} nearby, {:.1} % valid samples, {:.4} energy kept, {} clusters, {} probe-visible texels",
            decoded.probes.len(),
            stats.added_for_coverage,
            decoded.radius,
            stats.receivers_short_of_probes,
            stats.min_probes,
            stats.mean_nearby,
            stats.valid_sample_fraction * 100.0,
            stats.captured_energy,
            decoded.cluster_count(),
            decoded.visible_receivers.len()
        );
        if first.is_none() {
            first = Some(values.to_vec());
        }
    }
}
