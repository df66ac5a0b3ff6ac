//! SRP against analytic answers and the path tracer.

use glam::Vec3;
use relight_core::Rgb;
use relight_render::metrics::error_norms;
use relight_render::study::indirect_errors;
use relight_scene::atlas::TexelDensity;
use relight_srp::probes::{
    count_short_receivers, is_inside_geometry, place_probes, receivers_seeing_geometry,
    PlacementSettings,
};
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
    context_of(relight_scene::load_scene(&scene_path(name)).expect("shipped scene loads"))
}

fn context_of(scene: relight_scene::Scene) -> Arc<SceneContext> {
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
    let bake = relight_technique::robustness::shared_bake(&SrpKind, context, &params);
    let mut technique = SrpKind
        .create(context.clone(), Some(&bake), &params, &NoProgress)
        .expect("SRP loads its bake");
    let lights = context.scene.lights.clone();
    technique
        .update(&Frame {
            lights: &lights,
            index: 0,
            camera: None,
            moving_mesh_poses: None,
        })
        .expect("update");
    technique
}

/// Automatic placement puts no probe inside geometry or far outside the
/// scene, and (with the coverage pass) leaves few receivers short of
/// `min_probes` visible probes; the count the bake reports is the count a
/// fresh check finds.
#[test]
fn probe_placement_guarantees() {
    let context = context("cornell-box");
    let params = SrpParams::from_scene(&context, &[]).unwrap();
    let bake = SrpBake::build(&context, &params, &NoProgress).unwrap();
    assert!(bake.probes.len() >= params.probe_count as usize);
    let short = count_short_receivers(
        &context,
        &bake.probes,
        bake.radius,
        params.min_probes as usize,
    );
    assert_eq!(short, bake.stats.receivers_short_of_probes as usize);
    // Texel centres clamped onto edges where two surfaces meet see only the
    // neighbouring surface's back and need no probe; every other receiver
    // of this box sees 3 probes (0 short when measured), bounded at 5 %.
    assert_placement_covers(
        &context,
        &bake.probes,
        params.probe_count as usize,
        short,
        0.05,
    );
}

/// `probes` avoid geometry and stay within half a probe spacing of the
/// scene's bounds, and at most `bound` of the receivers that see geometry
/// (the ones that need probes) are `short`.
fn assert_placement_covers(
    context: &SceneContext,
    probes: &[Vec3],
    count: usize,
    short: usize,
    bound: f64,
) {
    let spacing = (context.scene.mesh.total_area() as f32 / count as f32).sqrt();
    let (lo, hi) = context.scene.mesh.bounds();
    let margin = Vec3::splat(0.5 * spacing + 1e-4);
    for probe in probes {
        assert!(
            !is_inside_geometry(context, *probe),
            "probe {probe} is inside geometry"
        );
        assert!(
            probe.cmpge(lo - margin).all() && probe.cmple(hi + margin).all(),
            "probe {probe} is far outside the scene"
        );
    }
    let needing = receivers_seeing_geometry(context)
        .into_iter()
        .filter(|&sees| sees)
        .count();
    let fraction = short as f64 / needing as f64;
    assert!(
        fraction <= bound,
        "{short} of {needing} receivers ({:.1} %) see too few probes",
        fraction * 100.0
    );
}

/// The two rooms are a closed building of solid walls under an empty sky:
/// every texel on its outer shell (away from the shell's edges, where a
/// face's hemisphere grazes the neighbouring box) sees only the
/// environment, and every texel inside a room sees a lit surface.
#[test]
fn only_the_outside_of_a_closed_building_sees_nothing_but_sky() {
    let context = context("two-rooms");
    let sees_geometry = receivers_seeing_geometry(&context);
    let (lo, hi) = context.scene.mesh.bounds();
    let receivers = &context.atlas.receivers;
    let (mut shell, mut inside) = (0, 0);
    for (index, &sees) in sees_geometry.iter().enumerate() {
        let position = receivers.positions[index];
        let normal = receivers.normals[index];
        let on_shell = (0..3).any(|axis| {
            let away_from_edges = (0..3).filter(|&other| other != axis).all(|other| {
                position[other] > lo[other] + 0.3 && position[other] < hi[other] - 0.3
            });
            away_from_edges
                && ((position[axis] - lo[axis]).abs() < 1e-3 && normal[axis] < -0.99
                    || (position[axis] - hi[axis]).abs() < 1e-3 && normal[axis] > 0.99)
        });
        // The rooms' own surfaces included: receivers lie on them.
        let within = |value: f32, low: f32, high: f32| value > low - 1e-3 && value < high + 1e-3;
        let in_a_room = within(position.y, 0.0, 2.5)
            && within(position.z, 0.0, 4.0)
            && (within(position.x, 0.0, 4.0) || within(position.x, 4.2, 8.2));
        if on_shell {
            shell += 1;
            assert!(
                !sees,
                "outer-shell receiver {index} at {position} sees geometry"
            );
        }
        if in_a_room {
            inside += 1;
            assert!(
                sees,
                "room receiver {index} at {position} sees only the sky"
            );
        }
    }
    assert!(
        shell > 1000 && inside > 1000,
        "{shell} shell and {inside} room receivers"
    );
}

/// Placement on scenes whose surfaces face outward as well as in: the two
/// rooms' outer walls, and Sponza's roof, outer walls, floor underside and
/// open courtyard. Receivers that see only the sky need no probe; the rest
/// get probes from wherever they face, just outside the scene's bounds if
/// need be. A placement kept inside the bounds, and counting every
/// receiver, left 26 % of the two rooms' receivers and 28 % of Sponza's
/// (at 160 probes plus 32 for coverage) short of 3 probes. Measured now, of
/// the receivers that see a lit surface: 234 of 3,855 (6.1 %; texels at the
/// corners of the overlapping wall boxes, more of them since charts stop
/// at the walls standing on the floors' edges, 162 of 4,050 before) and
/// 5,793 of 254,507 (2.3 %, at 128 plus 32, the benchmark's 160), bounded
/// at 7 % and 5 %. Sponza runs where ../shared/scenes is beside the
/// repository.
#[test]
fn placement_covers_outward_facing_surfaces() {
    let sponza =
        Path::new(env!("CARGO_MANIFEST_DIR")).join("../../../shared/scenes/sponza/scene.toml");
    let mut scenes = vec![(context("two-rooms"), 32usize, 0.07)];
    if sponza.exists() {
        scenes.push((
            context_of(relight_scene::load_scene(&sponza).expect("Sponza loads")),
            128,
            0.05,
        ));
    }
    for (context, count, bound) in scenes {
        let min_probes = 3;
        let placement = place_probes(
            &context,
            PlacementSettings {
                count,
                radius: 0.0,
                radius_factor: 2.0,
                min_probes,
                max_added: 32,
            },
        );
        let short =
            count_short_receivers(&context, &placement.probes, placement.radius, min_probes);
        assert_eq!(short, placement.receivers_short_of_probes);
        println!(
            "{} probes ({} added), radius {:.2}: {short} of {} receivers short of {min_probes}",
            placement.probes.len(),
            placement.added_for_coverage,
            placement.radius,
            context.atlas.receivers.len()
        );
        assert_placement_covers(&context, &placement.probes, count, short, bound);
    }
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
    // Glossy walls, so the radiance transport is baked and compared too.
    let context = glossy_cornell();
    let params = pairs(&[
        ("samples", "32"),
        ("order", "3"),
        ("probe_samples", "256"),
        ("radiance_order", "2"),
        ("radiance_samples", "32"),
    ]);
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

/// Four shards, baked on one and two threads, merge to the bytes of the
/// whole bake, radiance transport and sample tables included.
#[test]
fn shards_merge_to_the_whole_bake() {
    let context = glossy_cornell();
    let params = pairs(&[
        ("samples", "32"),
        ("order", "3"),
        ("probe_samples", "256"),
        ("radiance_order", "2"),
        ("radiance_samples", "32"),
    ]);
    relight_technique::robustness::check_shards_merge_to_whole(&SrpKind, &context, &params, 4);
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
    let decoded = SrpBake::decode(&bake).unwrap();
    // Consistent in every size yet without principal vectors: the run
    // time would split its buffers into chunks of zero.
    let mut rankless = decoded.clone();
    rankless.clusters.rank = 0;
    rankless.clusters.projection.clear();
    rankless.clusters.reconstruction.clear();
    assert!(SrpBake::decode(&rankless.encode()).is_err());
    let mut rankless_radiance = decoded.clone();
    rankless_radiance.radiance = relight_srp::RadianceTransport {
        bands: 2,
        clusters: relight_srp::ClusterSet {
            rank: 0,
            receiver_offsets: vec![0],
            probe_offsets: vec![0],
            ..Default::default()
        },
    };
    assert!(SrpBake::decode(&rankless_radiance.encode()).is_err());
    assert!(SrpBake::decode(&decoded.encode()).is_ok());
}

/// Lightmap relRMSE of SRP on the point-lit Cornell box for the given
/// parameters, against a 1024-path reference (its noise is about 2.3 %).
fn lightmap_error(reference: &[Rgb], context: &Arc<SceneContext>, params: &[(&str, &str)]) -> f64 {
    let technique = srp(context, params);
    error_norms(technique.receiver_irradiance().unwrap(), reference).relative_rmse
}

/// The thesis's Figure 6.7 trend, and the same for probe count: error falls
/// as SH order and probes grow, for the paper's method alone (the final
/// gather off: on this box it answers for nearly every receiver, and since
/// its values feed the bounces the error is 5.2 % whatever the order).
/// Measured 21.7, 11.0, 8.1 % for orders 1, 3, 7 and 21.3, 11.2, 8.5 % for
/// 4, 8, 16 probes at 256 samples. The probe steps asserted stop at 16:
/// with the gather on, before it fed the bounces, 32 and 64 probes gave
/// 9.3 and 10.3 %, a plateau set by the transport's own noise at 256
/// samples per receiver.
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
                &[("order", order), ("samples", "256"), ("final_gather", "0")],
            )
        })
        .collect();
    let by_probes: Vec<f64> = ["4", "8", "16"]
        .iter()
        .map(|count| {
            lightmap_error(
                &reference,
                &context,
                &[
                    ("probe_count", count),
                    ("max_added_probes", "0"),
                    ("samples", "256"),
                    ("final_gather", "0"),
                ],
            )
        })
        .collect();
    println!("by order 1, 3, 7: {by_order:?}; by probes 4, 8, 16: {by_probes:?}");
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
    let technique = srp(&context, params);
    let errors = indirect_errors(
        &context,
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

/// The point-lit Cornell box with its white walls, floor and boxes glossy.
fn glossy_cornell() -> Arc<SceneContext> {
    let mut scene =
        relight_scene::load_scene(&scene_path("cornell-box-point")).expect("shipped scene loads");
    for material in &mut scene.materials {
        if material.name == "white" {
            material.phong_exponent = 8.0;
        }
    }
    context_of(scene)
}

/// Path-traced incident radiance at a receiver, projected on SH of
/// `bands` bands: uniform hemisphere rays, each reading the radiance that
/// leaves the surface it hits (albedo / pi x its direct irradiance plus
/// the path-traced indirect irradiance of the reference lightmap there).
fn reference_incident_sh(
    context: &SceneContext,
    reference_lightmap: &[Rgb],
    receiver: usize,
    bands: usize,
    samples: u32,
    seed: u64,
) -> Vec<[f32; 3]> {
    use relight_core::sampling::{
        stratification_offset, stratified_square, uniform_hemisphere_around, SampleStream,
    };
    let receivers = &context.atlas.receivers;
    let (position, normal) = (receivers.positions[receiver], receivers.normals[receiver]);
    let direct = context.direct();
    let lights = context.scene.lights.clone();
    let epsilon = relight_trace::direct::ray_epsilon_for(&context.bvh);
    let count = bands * bands;
    let mut sums = vec![[0.0f32; 3]; count];
    let mut basis = vec![0.0f32; count];
    let offset = stratification_offset(seed, receiver as u64);
    for sample in 0..samples {
        let mut rng = SampleStream::new(seed, receiver as u64, sample as u64);
        let direction =
            uniform_hemisphere_around(normal, stratified_square(sample, samples, offset, &mut rng));
        let ray = relight_trace::Ray {
            origin: position + normal * epsilon,
            direction,
            t_max: f32::INFINITY,
        };
        let Some(hit) = context.bvh.intersect(&ray) else {
            continue;
        };
        let triangle = hit.triangle as usize;
        let surface_normal = context.scene.mesh.geometric_normal(triangle);
        if surface_normal.dot(direction) >= 0.0 {
            continue;
        }
        let point = context.scene.mesh.point_at(triangle, hit.barycentric);
        let irradiance = direct.irradiance(&lights, point, surface_normal, sample as u64)
            + context
                .atlas
                .sample(reference_lightmap, hit.triangle, hit.barycentric);
        let radiance = context.scene.albedo_at(triangle, hit.barycentric)
            * irradiance
            * std::f32::consts::FRAC_1_PI;
        relight_core::sh::evaluate(direction, bands, &mut basis);
        for (sum, value) in sums.iter_mut().zip(&basis) {
            for channel in 0..3 {
                sum[channel] += radiance[channel] * value;
            }
        }
    }
    let scale = 2.0 * std::f32::consts::PI / samples as f32;
    sums.iter()
        .map(|sum| sum.map(|value| value * scale))
        .collect()
}

/// Radiance transport (the original paper's glossy extension) against
/// path-traced incident radiance: glossy reflection at receivers of the
/// glossy white surfaces, seen from three directions, with the Phong lobe
/// cut to the same three bands in both, at order 7 with 64 probes. It must beat the probe blend that
/// glossy reflection falls back to without it (no parallax, no visibility
/// from the hit points), and stay within a bound.
#[test]
fn radiance_transport_follows_path_traced_incident_radiance() {
    let context = glossy_cornell();
    let receivers = &context.atlas.receivers;
    let atlas = &context.atlas;
    let reference_values = reference(&context, 512);
    let reference_lightmap = atlas.to_lightmap(&reference_values);
    let common = [
        ("order", "7"),
        ("probe_count", "64"),
        ("samples", "256"),
        ("specular", "1"),
    ];
    let with_order = |radiance_order: &str| {
        let mut params = common.to_vec();
        params.push(("radiance_order", radiance_order));
        params.push(("radiance_samples", "2048"));
        srp(&context, &params)
    };
    let transported = with_order("2");
    let blended = with_order("0");
    let facts = transported.bake_facts();
    let glossy_count = facts
        .iter()
        .find(|(name, _)| *name == "srp radiance transport")
        .map(|(_, text)| text.clone())
        .unwrap();
    println!("{glossy_count}");
    let lobe = relight_core::sh::phong_band_factors(8.0);
    let glossy: Vec<usize> = (0..receivers.len())
        .filter(|&r| {
            context
                .scene
                .material_of(receivers.triangles[r] as usize)
                .phong_exponent
                > 1.0
        })
        .collect();
    assert!(glossy.len() > 1000, "{} glossy receivers", glossy.len());
    let (mut reference_glossy, mut transported_glossy, mut blended_glossy) =
        (Vec::new(), Vec::new(), Vec::new());
    let mut half_difference = Vec::new();
    for &receiver in glossy.iter().step_by(glossy.len() / 120) {
        let normal = receivers.normals[receiver];
        // Two independent halves: their mean is the reference, their
        // difference measures its noise.
        let halves = [1u64, 2].map(|seed| {
            reference_incident_sh(&context, &reference_lightmap, receiver, 3, 1024, seed)
        });
        let (tangent, _) = relight_core::sampling::orthonormal_basis(normal);
        let point = relight_technique::SurfacePoint {
            position: receivers.positions[receiver],
            normal,
            triangle: receivers.triangles[receiver],
            barycentric: receivers.barycentrics[receiver],
        };
        for toward_viewer in [
            normal,
            (normal + tangent).normalize(),
            (normal - tangent).normalize(),
        ] {
            let reflected = (-toward_viewer).reflect(normal);
            let mut basis = [0.0f32; 9];
            relight_core::sh::evaluate(reflected, 3, &mut basis);
            let glossy_of = |sh: &[[f32; 3]]| {
                let mut value = Rgb::ZERO;
                for (index, coefficient) in sh.iter().enumerate() {
                    let band = (index as f32).sqrt() as usize;
                    for channel in 0..3 {
                        value[channel] += lobe[band] * basis[index] * coefficient[channel];
                    }
                }
                value
            };
            let [first, second] = [glossy_of(&halves[0]), glossy_of(&halves[1])];
            reference_glossy.push(((first + second) * 0.5).max(Rgb::ZERO));
            half_difference.push((first - second) * 0.5);
            transported_glossy.push(
                transported
                    .glossy_radiance(&point, toward_viewer, 8.0)
                    .unwrap(),
            );
            blended_glossy.push(blended.glossy_radiance(&point, toward_viewer, 8.0).unwrap());
        }
    }
    let transport_error = error_norms(&transported_glossy, &reference_glossy).relative_rmse;
    let blend_error = error_norms(&blended_glossy, &reference_glossy).relative_rmse;
    // The reference's own noise: half the halves' difference is the
    // standard error of their mean.
    let shifted: Vec<Rgb> = reference_glossy
        .iter()
        .zip(&half_difference)
        .map(|(value, difference)| *value + *difference)
        .collect();
    let noise = error_norms(&shifted, &reference_glossy).relative_rmse;
    println!(
        "glossy reflection against path-traced incident radiance (3 bands, {} lookups): radiance transport {:.1} %, probe blend {:.1} %, reference noise {:.1} %",
        reference_glossy.len(),
        transport_error * 100.0,
        blend_error * 100.0,
        noise * 100.0
    );
    // Measured 8.2 % against 36.5 %, with the reference 2.3 % noisy
    // (and its indirect lightmap, 512 paths, noisier still). What remains
    // is the method's own error (probe interpolation, 2048 transport
    // samples, f16 compression to 64 vectors per cluster of 113 receivers).
    // The bounds leave room for that, not for losing the parallax and
    // visibility that the probe blend lacks.
    assert!(transport_error < 0.12, "{transport_error}");
    assert!(
        transport_error < 0.5 * blend_error,
        "{transport_error} vs {blend_error}"
    );
}

/// Damaged bakes (bit flips, truncations), radiance transport included,
/// are refused or run; none panics.
#[test]
fn damaged_bakes_never_panic() {
    let context = glossy_cornell();
    let params = pairs(&[
        ("samples", "8"),
        ("order", "1"),
        ("probe_samples", "64"),
        ("radiance_order", "1"),
        ("radiance_samples", "8"),
        // The gather's rays come from the scene, not the bake; its
        // automatic count (up to 1024 rays a gathering receiver on a
        // small scene, at every create) would be most of the
        // test's time.
        ("final_gather_rays", "8"),
    ]);
    let bake = SrpKind.bake(&context, &params, &NoProgress).unwrap();
    let (accepted, refused) = relight_technique::robustness::check_damaged_payloads(
        &SrpKind, &context, &params, &bake, 300, 1,
    );
    assert!(
        accepted > 0 && refused > 0,
        "{accepted} accepted, {refused} refused"
    );
}

/// The run time keeps irradiance per receiver and reads the lightmap
/// through a texel map made at load (gutters pointing at the texels they
/// copy) instead of dilating a lightmap every frame. Lookups anywhere on
/// the surface, edges included, must give what a per-frame dilated
/// lightmap of the same values gives.
#[test]
fn lookups_match_a_dilated_lightmap() {
    let context = context("cornell-box");
    let technique = srp(&context, &[("samples", "16"), ("probe_samples", "64")]);
    let receivers = technique
        .receiver_irradiance()
        .expect("SRP has receiver values");
    let lightmap = context.atlas.to_lightmap(receivers);
    let mesh = &context.scene.mesh;
    let mut rng = relight_core::sampling::Pcg32::new(11, 2);
    let mut brightest = 0.0f32;
    let corners = [
        glam::Vec2::ZERO,
        glam::Vec2::X,
        glam::Vec2::Y,
        glam::Vec2::splat(0.5),
    ];
    for triangle in 0..mesh.triangles.len() {
        let random = (0..8).map(|_| relight_core::sampling::uniform_triangle(rng.next_vec2()));
        for barycentric in corners.into_iter().chain(random) {
            let point = relight_technique::SurfacePoint {
                position: mesh.point_at(triangle, barycentric),
                normal: mesh.geometric_normal(triangle),
                triangle: triangle as u32,
                barycentric,
            };
            let looked_up = technique.indirect_irradiance(&point);
            let dilated = context
                .atlas
                .sample(&lightmap, triangle as u32, barycentric);
            brightest = brightest.max(dilated.max_element());
            // Same four values and weights, blended in a different order
            // (weighted sum against nested lerps): f32 rounding only.
            assert!(
                (looked_up - dilated).abs().max_element() <= 1e-5 * dilated.max_element().max(1.0),
                "triangle {triangle} at {barycentric}: {looked_up} against {dilated}"
            );
        }
    }
    assert!(brightest > 0.0, "the lookups saw light");
}

#[test]
fn points_in_space_gather_the_lightmap() {
    // Points in space gather the light leaving the surfaces around them
    // (direct plus the lightmap's indirect) instead of blending the probes,
    // which have neither parallax nor visibility to the point: the blend
    // measured 30.2 % relRMSE on the two-rooms grid (relight converge
    // scenes/two-rooms/scene-unlit-room.toml -t srp), the gather 6.3 %
    // there and 14.7 % on the corridor at the defaults. The gathered
    // lightmap's own error enters only after one more bounce, so order 2
    // and 256 transport samples keep the test quick. The bound is the
    // issue's 20 % for SRP; 256 reference paths add about 5 % of noise.
    for scene in ["two-rooms", "corridor"] {
        let context = context(scene);
        let technique = srp(&context, &[("order", "2"), ("samples", "256")]);
        let error = relight_render::convergence::space_error(&context, technique.as_ref(), 256);
        eprintln!("{scene}: points in space relRMSE {error:.4}");
        assert!(error < 0.2, "{scene}: {error}");
    }
}

/// The bound at order 7 on the closed boxes: the indirect image
/// within 8 % relRMSE of the path tracer over 8x8-pixel tile means, all
/// bounces. The light 0.1 m from a corner needs more than a box's 32
/// probes (relight converge at full resolution: 8.5 % at 32, 6.8 % at 64
/// whatever the transport samples), so it runs at 64. At half the
/// cameras' resolution the reference's own tile noise is about 2 %.
/// Before clusters were halved to keep `cluster_energy` of their transport
/// the corridor measured 13.0 % and the area-lit box 8.0 %.
#[test]
fn closed_boxes_within_eight_percent_over_tiles_at_order_seven() {
    let measured = relight_render::convergence::closed_box_measurements(|context, scene| {
        if scene.contains("corner-light") {
            srp(context, &[("probe_count", "64")])
        } else {
            srp(context, &[])
        }
    });
    for (scene, measured) in measured {
        assert!(
            measured.image_tiles <= 0.08,
            "{scene}: {}",
            measured.image_tiles
        );
    }
}

/// The 0.85-1.15x of the path tracer's light in the view from
/// inside the unlit room, which gets its light through the doorway after
/// two bounces or more, and no corner seams there: over 8x8 tiles under
/// 5 %, about twice what the defaults measure. Full size (`relight converge
/// scenes/two-rooms/scene-unlit-room.toml -t srp --sweep
/// gather_feedback=false,true`) measured 1.013x and 1.5 %, then 0.995x and
/// 1.4 %; without the final gather (`--sweep final_gather=0`), 1.120x and
/// 7.2 % before that change. The light ratio's own noise over a whole image at 256 paths is
/// well under 1 %, so its bound is the issue's.
#[test]
fn unlit_room_gets_the_light_that_crosses_the_doorway() {
    let measured = relight_render::convergence::unlit_room_measurement(|context| srp(context, &[]));
    assert!(
        (0.85..1.15).contains(&measured.light_ratio),
        "{}",
        measured.light_ratio
    );
    assert!(measured.image_tiles < 0.05, "{}", measured.image_tiles);
}

/// The first update settles every bounce of a bright closed room
/// ([`relight_technique::robustness::check_first_update_settles`]: passes
/// stop once the light they would still add is under
/// [`relight_technique::SETTLED_SHARE`]). Measured: 49 passes, 0.995 of
/// what 300 more updates reach (1.004 before the gathered near field fed
/// the bounces, when the one-pass updates that follow settled 0.4 % lower
/// than the first update's passes; I have not found why). A
/// fixed 16 passes gave 0.883 here, and 0.895x of the path tracer's light
/// in a 4 x 2.6 x 5 m grey room of albedo 0.9 (`relight converge`).
#[test]
fn the_first_update_settles_the_bounces_of_a_bright_closed_room() {
    let context = relight_technique::robustness::closed_grey_room(0.9);
    let mut technique = srp(&context, &[]);
    let (passes, share) = relight_technique::robustness::check_first_update_settles(
        technique.as_mut(),
        &context,
        128,
    );
    println!("{passes} passes, {share:.3} of what 300 more updates reach");
}

/// Variant `index` of the generator's default family and SRP's figures on
/// it with `params`, as `relight robustness` measures them.
fn srp_on_variant(
    index: usize,
    params: &[(&str, &str)],
) -> (
    relight_render::robustness::VariantCase,
    relight_render::convergence::Measurement,
) {
    let case =
        relight_render::robustness::VariantCase::default_family(index).expect("the variant loads");
    let technique = srp(&case.context, params);
    let (measured, _) = case.measure_as_the_study_does(technique.as_ref());
    (case, measured)
}

/// The bound on an unlit room's light in view: 0.85-1.15x.
fn assert_unlit_light_in_bounds(index: usize, light_ratio: f64) {
    assert!(
        (0.85..=1.15).contains(&light_ratio),
        "variant {index}: {light_ratio}"
    );
}

/// Two rooms lit by a point light inside a lampshade (1 cm solid walls,
/// 32 x 28 x 32 cm, open below), seen from the unlit room: variants 1 and
/// 28 of the generator's default family. Most of the light that leaves a
/// shade has bounced inside it first, which a 21 cm lightmap texel cannot
/// resolve on a 32 cm face; the atlas now gives the shade's inside finer
/// texels (`lightmap.refine_near_lights`). Measured at the study's settings
/// (half the variants' camera, 256 paths, as `relight robustness -t srp
/// --first 1 --variants 1`): light in view 0.704x and 0.778x before, 0.906x
/// and 0.987x after; 8x8 tiles on 28 23.5 % before, 8.1 % after. A
/// 4096-path reference of variant 1 gives the same light (0.710x before),
/// so the light is a measure here even where the 256-path tiles are noise
/// (variant 1's reference: 39 % over tiles, variant 28's 7.5 %). Once
/// the gathered near field fed the bounces (the test below), 0.940x and
/// 0.939x, 28's tiles 9.2 %. Bounds: the 0.85-1.15x in an unlit
/// room, and for 28 one and a half times its 8 % over tiles, as the
/// reference's own noise is nearly that.
#[test]
fn rooms_lit_by_a_shaded_lamp_get_its_light() {
    for index in [1, 28] {
        let (case, measured) = srp_on_variant(index, &[]);
        assert!(
            case.context.atlas.near_light_charts > 0,
            "variant {index}: the shade is refined"
        );
        assert_unlit_light_in_bounds(index, measured.light_ratio);
        if index == 28 {
            assert!(measured.image_tiles < 0.12, "{}", measured.image_tiles);
        }
    }
}

/// Bright two-room suites whose bounces the probes' near field overshot:
/// variants 49 (albedo 0.69, a shaded lamp) and 88 (albedo 0.86, a spot
/// light pointing at the floor 0.44 m from a wall) of the default family.
/// In 88 the probes put the first bounce in the lit room's corners at 2.6
/// times the path tracer's (`relight converge` with `bounces=1
/// final_gather=0`); the final gather corrects those receivers for the
/// image, but with `gather_feedback=false` the bounces read the
/// reconstruction, each carried the error into the next, and the unlit
/// rooms got 1.193x (49) and 1.904x (88) the path tracer's light. Fed the
/// gathered values: 0.979x and 0.854x at the study's settings (`relight
/// robustness -t srp --first 88 --variants 1`), 0.862x since the final
/// gather samples the floor under the spot explicitly. Bound: the
/// issue's 0.85-1.15x in an unlit room; 88 clears it by 0.012, so a
/// change that moves it deserves a look rather than a wider bound. Much
/// of the overshoot was light read across the partition: since charts
/// stop at walls standing on their edges and receivers no longer cross
/// coincident walls, 88 without the feedback gives 0.905x instead of
/// 1.904x, and is held to the same bound.
#[test]
fn bright_suites_keep_their_bounces_in_bounds() {
    for index in [49, 88] {
        let (case, measured) = srp_on_variant(index, &[]);
        assert_unlit_light_in_bounds(index, measured.light_ratio);
        if index == 88 {
            let technique = srp(&case.context, &[("gather_feedback", "false")]);
            let (measured, _) = case.measure_as_the_study_does(technique.as_ref());
            assert_unlit_light_in_bounds(index, measured.light_ratio);
        }
    }
}

/// A point light 6 cm from a wall of one room of two (variant 25 of the
/// default family: 11 m suite, walls of single planes in 0.29 m
/// triangles), seen from the unlit room. The wall is one large chart, so
/// the atlas does not refine it, and two things put the lamp's light into
/// the next room: the final gather's hits read their texel's direct light
/// at its centre (beside the lamp the 1/d^2 of the nearest point, 2.4
/// times the texel's mean for a 15 cm texel at 6 cm), and rays from the
/// unlit room found the hot patch by chance (bright spots on its far
/// wall). Hits now read their texel's footprint mean and the gather
/// samples the wall within four texels of the lamp. At the study's
/// settings (`relight robustness -t srp --first 25 --variants 1`) the
/// unlit room's light went from 1.476x to 0.977x (against a 2048-path
/// reference 1.480x to 0.980x, 8x8 tiles 191 % to 8.4 %, that
/// reference's own noise 8.3 %). Bound: the
/// issue's 0.85-1.15x; the tiles are not asserted, as the 256-path
/// reference's own tile noise is 22.6 %.
#[test]
fn a_lamp_beside_a_large_wall_keeps_its_light_in_its_room() {
    let (_, measured) = srp_on_variant(25, &[]);
    assert_unlit_light_in_bounds(25, measured.light_ratio);
}

/// A 47 m hall of albedo 0.68 lit by a low sun through small windows
/// (variant 56 of the default family). Fitted to 128 texels its lightmap
/// had 1.05 m texels, wider than the sun's patches: a texel's light is its
/// centre's, so the probes and the final gather read those patches all or
/// nothing and a texel off, and SRP gave 0.79x of the path tracer's light
/// over the whole view (8x8 tiles 23.8 %, the family's worst hall, at the
/// study's settings: `relight robustness -t srp --first 56 --variants 1`).
/// At the automatic atlas's half-metre texels, 1.00x and 5.5 %. Bounds:
/// the 15 % over tiles for a hall, and light within a tenth, as
/// the reference's own tile noise is 3.3 %.
#[test]
fn a_hall_lit_through_small_windows_keeps_its_light() {
    let (case, measured) = srp_on_variant(56, &[]);
    assert!(case.context.atlas.metres_per_texel <= relight_scene::atlas::LARGEST_AUTOMATIC_TEXEL);
    assert!(
        (0.9..=1.1).contains(&measured.light_ratio),
        "{}",
        measured.light_ratio
    );
    assert!(measured.image_tiles < 0.15, "{}", measured.image_tiles);
}
