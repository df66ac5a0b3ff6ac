//! SRP against analytic answers and the path tracer.

use glam::Vec3;
use relight_core::Rgb;
use relight_render::metrics::error_norms;
use relight_render::study::indirect_errors;
use relight_scene::atlas::TexelDensity;
use relight_srp::probes::{count_short_receivers, is_inside_geometry};
use relight_srp::transport::{aabb_clusters, compress, TransportScratch, TransportSettings};
use relight_srp::{cluster_transport, SrpBake, SrpKind, SrpParams};
use relight_technique::{
    reference_receiver_irradiance, ContextSettings, Frame, NoProgress, SceneContext, Technique,
    TechniqueKind,
};
use relight_trace::path::PathSettings;
use std::path::Path;
use std::sync::Arc;

fn scene_path(name: &str) -> std::path::PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("../../scenes")
        .join(name)
        .join("scene.toml")
}

fn context(name: &str) -> Arc<SceneContext> {
    let scene = relight_scene::load_scene(&scene_path(name)).expect("shipped scene loads");
    Arc::new(
        SceneContext::new(
            scene,
            ContextSettings {
                lightmap: TexelDensity::from_resolution(None),
                ..ContextSettings::default()
            },
        )
        .expect("context"),
    )
}

fn pairs(list: &[(&str, &str)]) -> Vec<(String, String)> {
    list.iter()
        .map(|(key, value)| (key.to_string(), value.to_string()))
        .collect()
}

fn srp(context: &Arc<SceneContext>, params: &[(&str, &str)]) -> Box<dyn Technique> {
    let params = pairs(params);
    let bake = SrpKind
        .bake(context, &params, &NoProgress)
        .expect("SRP bakes");
    let mut technique = SrpKind
        .create(context.clone(), Some(&bake), &params, &NoProgress)
        .expect("SRP loads its bake");
    let lights = context.scene.lights.clone();
    technique
        .update(&Frame {
            lights: &lights,
            index: 0,
        })
        .expect("update");
    technique
}

/// Automatic placement puts no probe inside geometry, and (with the
/// coverage pass) leaves few receivers short of `min_probes` visible probes;
/// the count the bake reports is the count a fresh check finds.
#[test]
fn probe_placement_guarantees() {
    let context = context("cornell-box");
    let params = SrpParams::from_scene(&context, &[]).unwrap();
    let bake = SrpBake::build(&context, &params, &NoProgress).unwrap();
    assert!(bake.probes.len() >= params.probe_count as usize);
    for probe in &bake.probes {
        assert!(
            !is_inside_geometry(&context, *probe),
            "probe {probe} is inside geometry"
        );
        let (lo, hi) = context.scene.mesh.bounds();
        assert!(
            probe.cmpge(lo).all() && probe.cmple(hi).all(),
            "probe {probe} is outside the room"
        );
    }
    let short = count_short_receivers(
        &context,
        &bake.probes,
        bake.radius,
        params.min_probes as usize,
    );
    assert_eq!(short, bake.stats.receivers_short_of_probes as usize);
    // The receivers left short are texel centres clamped onto edges where
    // two surfaces meet, whose rays graze the neighbouring surface; 2.7 %
    // on this scene when measured, bounded here at 5 %.
    let fraction = short as f64 / context.atlas.receivers.len() as f64;
    assert!(
        fraction <= 0.05,
        "{short} receivers see fewer than {} probes",
        params.min_probes
    );
}

/// Probes from the scene file replace automatic placement.
#[test]
fn explicit_probes_are_used() {
    let context = context("cornell-box");
    let list = "[[0.0, 0.5, 0.0], [0.3, 0.5, 0.2], [-0.3, 0.5, -0.2]]";
    let params =
        SrpParams::from_scene(&context, &pairs(&[("probes", list), ("samples", "16")])).unwrap();
    let bake = SrpBake::build(&context, &params, &NoProgress).unwrap();
    assert_eq!(
        bake.probes,
        vec![
            Vec3::new(0.0, 0.5, 0.0),
            Vec3::new(0.3, 0.5, 0.2),
            Vec3::new(-0.3, 0.5, -0.2)
        ]
    );
}

/// CPCA against the uncompressed transport of one cluster of the Cornell
/// box: the relative Frobenius error falls as vectors are added (printed;
/// measured 65, 35, 25, 12 % at 4, 16, 32, 128 vectors).
#[test]
fn cpca_error_against_uncompressed_transport() {
    let context = context("cornell-box");
    let params = SrpParams::from_scene(&context, &pairs(&[("samples", "64")])).unwrap();
    let bake = SrpBake::build(
        &context,
        &SrpParams {
            samples: 1,
            ..params.clone()
        },
        &NoProgress,
    )
    .unwrap();
    let nearby = relight_srp::probes::nearby_probes(
        &context,
        &bake.probes,
        bake.radius,
        params.max_nearby as usize,
    );
    let clusters = aabb_clusters(&context.atlas.receivers.positions, 1024);
    let members = &clusters[clusters.len() / 2];
    let settings = TransportSettings {
        bands: 8,
        samples: 64,
        radius: bake.radius,
        texel_jitter: false,
        seed: 1,
    };
    let mut scratch = TransportScratch::new(8);
    let (matrix, columns, _) = cluster_transport(
        &context,
        &bake.probes,
        &nearby,
        members,
        &settings,
        &mut scratch,
    );
    let width = columns.len() * 64;
    let norm: f64 = matrix.iter().map(|&v| (v as f64).powi(2)).sum();
    let mut errors = Vec::new();
    for rank in [4usize, 16, 32, 128] {
        let compressed = compress(&matrix, members.len(), width, rank);
        let mut error = 0.0f64;
        for row in 0..members.len() {
            for column in 0..width {
                let rebuilt: f32 = (0..compressed.rank)
                    .map(|k| {
                        compressed.reconstruction[row * compressed.rank + k]
                            * compressed.projection[k * width + column]
                    })
                    .sum();
                error += ((rebuilt - matrix[row * width + column]) as f64).powi(2);
            }
        }
        errors.push((error / norm).sqrt());
    }
    println!("CPCA relative Frobenius error at 4, 16, 32, 128 vectors: {errors:?}");
    assert!(
        errors.windows(2).all(|pair| pair[1] < pair[0]),
        "{errors:?}"
    );
}

fn reference(context: &SceneContext, samples: u32) -> Vec<Rgb> {
    let lights = context.scene.lights.clone();
    reference_receiver_irradiance(
        context,
        &lights,
        PathSettings::default(),
        samples,
        &NoProgress,
    )
    .mean
}

/// The same bake and parameters give the same bytes on one thread and on
/// all of them.
#[test]
fn bake_is_deterministic_across_thread_counts() {
    let context = context("cornell-box-point");
    let params = pairs(&[("samples", "32"), ("order", "3"), ("probe_samples", "256")]);
    let bake_on = |threads: usize| {
        rayon::ThreadPoolBuilder::new()
            .num_threads(threads)
            .build()
            .unwrap()
            .install(|| SrpKind.bake(&context, &params, &NoProgress).unwrap())
    };
    let one = bake_on(1);
    let several = bake_on(3);
    assert_eq!(one, several);
}

/// Corrupt payloads fail with a message, never a panic.
#[test]
fn corrupt_bakes_are_refused() {
    let context = context("cornell-box-point");
    let params = pairs(&[("samples", "8"), ("order", "1"), ("probe_samples", "64")]);
    let bake = SrpKind.bake(&context, &params, &NoProgress).unwrap();
    for cut in [0usize, 4, 17, bake.len() / 2, bake.len() - 1] {
        assert!(SrpBake::decode(&bake[..cut]).is_err());
    }
    let mut flipped = bake.clone();
    // Receiver count field.
    flipped[4] ^= 0x40;
    assert!(SrpBake::decode(&flipped).is_err());
    assert!(SrpBake::decode(&bake).is_ok());
}

/// Lightmap relRMSE of SRP on the point-lit Cornell box for the given
/// parameters, against a 1024-path reference (its noise is about 2.3 %).
fn lightmap_error(reference: &[Rgb], context: &Arc<SceneContext>, params: &[(&str, &str)]) -> f64 {
    let technique = srp(context, params);
    error_norms(technique.receiver_irradiance().unwrap(), reference).relative_rmse
}

/// The thesis's Figure 6.7 trend, and the same for probe count: error falls
/// as SH order and probes grow (measured 23.7, 11.0, 9.1 % for orders 1, 3,
/// 7 and 20.7, 9.6, 9.2 % for 4, 16, 32 probes at 256 samples).
#[test]
fn error_falls_with_order_and_probe_count() {
    let context = context("cornell-box-point");
    let reference = reference(&context, 1024);
    let by_order: Vec<f64> = ["1", "3", "7"]
        .iter()
        .map(|order| {
            lightmap_error(
                &reference,
                &context,
                &[("order", order), ("samples", "256")],
            )
        })
        .collect();
    let by_probes: Vec<f64> = ["4", "16", "32"]
        .iter()
        .map(|count| {
            lightmap_error(
                &reference,
                &context,
                &[
                    ("probe_count", count),
                    ("max_added_probes", "0"),
                    ("samples", "256"),
                ],
            )
        })
        .collect();
    println!("by order 1, 3, 7: {by_order:?}; by probes 4, 16, 32: {by_probes:?}");
    assert!(
        by_order.windows(2).all(|pair| pair[1] < pair[0]),
        "{by_order:?}"
    );
    assert!(
        by_probes.windows(2).all(|pair| pair[1] < pair[0]),
        "{by_probes:?}"
    );
}

/// All-bounce lightmap and indirect-image relRMSE against the path tracer,
/// and the references' own noise.
fn accuracy(scene_name: &str, params: &[(&str, &str)]) -> (f64, f64, f64, f64) {
    let mut scene = relight_scene::load_scene(&scene_path(scene_name)).unwrap();
    // A small image keeps the reference's noise low at a test's cost.
    let [width, height] = scene.camera.resolution;
    scene.camera.resolution = [width / 4, height / 4];
    let context = Arc::new(
        SceneContext::new(
            scene,
            ContextSettings {
                lightmap: TexelDensity::from_resolution(None),
                ..ContextSettings::default()
            },
        )
        .unwrap(),
    );
    let lights = context.scene.lights.clone();
    let technique = srp(&context, params);
    let errors = indirect_errors(
        &context,
        &lights,
        technique.as_ref(),
        PathSettings::default(),
        2048,
        4096,
    );
    (
        errors.lightmap,
        errors.lightmap_noise,
        errors.image,
        errors.image_noise,
    )
}

/// The bounds at order 7 with all bounces: lightmap at most 10 %,
/// image at most 15 %. The corridor needs less compression than the
/// default 32 vectors over 1024 receivers (its transport spreads over more
/// probes per cluster; at the default it measured 14.5 %) and more probes:
/// since receivers stand on the visible part of their texels, the 487
/// texels at its wall junctions count (19 % error there with 48 probes),
/// and 48, 64, 96 probes measured 10.9, 10.6, 9.7 % against 2048 paths.
#[test]
fn accuracy_within_the_bounds_at_order_seven() {
    let corridor = [
        ("probe_count", "96"),
        ("cluster_size", "256"),
        ("pca_vectors", "64"),
    ];
    for (scene, params) in [
        ("cornell-box", &[][..]),
        ("cornell-box-point", &[][..]),
        ("corridor", &corridor[..]),
    ] {
        let (lightmap, lightmap_noise, image, image_noise) = accuracy(scene, params);
        println!(
            "{scene}: lightmap {:.1} % (reference noise {:.1} %), image {:.1} % (reference noise {:.1} %)",
            lightmap * 100.0,
            lightmap_noise * 100.0,
            image * 100.0,
            image_noise * 100.0
        );
        assert!(lightmap_noise < 0.05 && image_noise < 0.1);
        assert!(lightmap <= 0.10, "{scene}: lightmap relRMSE {lightmap}");
        assert!(image <= 0.15, "{scene}: image relRMSE {image}");
    }
}
