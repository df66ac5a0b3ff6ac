//! PRM against the path tracer on the shipped scenes, determinism of the
//! bake, and bake-file robustness.

use relight_prm::{PrmBake, PrmKind, PrmParams};
use relight_render::metrics::{error_norms, relative_noise};
use relight_scene::atlas::TexelDensity;
use relight_technique::{
    reference_receiver_irradiance, ContextSettings, Frame, NoProgress, SceneContext, Shard,
    TechniqueKind,
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

/// PRM at its defaults, baked for `context` and updated under its lights.
fn baked_and_updated(context: &Arc<SceneContext>) -> Box<dyn relight_technique::Technique> {
    let bake = PrmKind.bake(context, &[], &NoProgress).unwrap();
    updated_from(context, &bake, &[])
}

/// PRM with `params`, from `bake`, updated under the scene's lights.
fn updated_from(
    context: &Arc<SceneContext>,
    bake: &[u8],
    params: &[(String, String)],
) -> Box<dyn relight_technique::Technique> {
    let mut prm = PrmKind
        .create(context.clone(), Some(bake), params, &NoProgress)
        .unwrap();
    prm.update(&Frame {
        lights: &context.scene.lights,
        index: 0,
        camera: None,
        moving_mesh_poses: None,
    })
    .unwrap();
    prm
}

/// A bake and the parameters it was made with.
type CachedBake = (Vec<(String, String)>, Vec<u8>);

/// Lightmap relRMSE of PRM against a path-traced reference for each run (a
/// full parameter list; runs with the same bake parameters share a bake),
/// and the reference's own noise.
fn lightmap_errors(
    scene: &str,
    resolution: u32,
    reference_samples: u32,
    runs: &[&[(&str, &str)]],
) -> (Vec<f64>, f64) {
    let context = context(scene, resolution);
    let lights = context.scene.lights.clone();
    let reference = reference_receiver_irradiance(
        &context,
        &lights,
        PathSettings::default(),
        reference_samples,
        &NoProgress,
    );
    let noise = relative_noise(&reference.mean, &reference.standard_error);
    let mut bakes: Vec<CachedBake> = Vec::new();
    let errors = runs
        .iter()
        .map(|run| {
            let params: Vec<(String, String)> = run
                .iter()
                .map(|(key, value)| (key.to_string(), value.to_string()))
                .collect();
            let bake_params: Vec<(String, String)> = params
                .iter()
                .filter(|(key, _)| relight_prm::BAKE_PARAMETERS.contains(&key.as_str()))
                .cloned()
                .collect();
            if !bakes.iter().any(|(known, _)| *known == bake_params) {
                let bake = PrmKind.bake(&context, &bake_params, &NoProgress).unwrap();
                bakes.push((bake_params.clone(), bake));
            }
            let bake = &bakes
                .iter()
                .find(|(known, _)| *known == bake_params)
                .unwrap()
                .1;
            let prm = updated_from(&context, bake, &params);
            error_norms(prm.receiver_irradiance().unwrap(), &reference.mean).relative_rmse
        })
        .collect();
    (errors, noise)
}

#[test]
fn cornell_box_within_bound_error_grows_as_k_falls_and_compression_beats_top_k() {
    let uncompressed = ("rank", "0");
    let runs: [&[(&str, &str)]; 5] = [
        &[uncompressed, ("top_k", "0")],
        &[uncompressed, ("top_k", "32")],
        &[uncompressed, ("top_k", "8")],
        &[uncompressed, ("top_k", "32"), ("selection", "\"weight\"")],
        &[("rank", "32"), ("top_k", "0")],
    ];
    let (errors, noise) = lightmap_errors("cornell-box", 64, 2048, &runs);
    eprintln!(
        "cornell-box: all {:.4}, K=32 {:.4}, K=8 {:.4}, K=32 by weight {:.4}, rank 32 {:.4}; reference noise {noise:.4}",
        errors[0], errors[1], errors[2], errors[3], errors[4]
    );
    // The bound for all clusters is 15 %, and the reference's own
    // noise (about 3 % here) is inside the measured error: no allowance.
    assert!(errors[0] < 0.15, "all clusters: {}", errors[0]);
    assert!(errors[0] < errors[1] && errors[1] < errors[2], "{errors:?}");
    // Ranking by contribution keeps more light than ranking by weight.
    assert!(errors[1] < errors[3], "{errors:?}");
    // Same per-frame cost (32 panes summed): 32 principal components of all
    // 256 clusters lose far less than the 32 strongest clusters (about 16 %
    // against 48 % at the automatic lightmap size); a 10-point margin.
    assert!(errors[4] < errors[1] - 0.10, "{errors:?}");
}

#[test]
fn corridor_converges_with_entry_points() {
    // The paper's 256 clusters, all used, stored uncompressed. 8192 paths
    // keep the reference's noise (4.3 % at 2048) from eating the margin.
    // Virtual lights sample near-field light only as densely as the entry
    // points, and the corridor's two lights hang 10-20 cm under its
    // ceiling: with entries spaced like the rest of the surface, the
    // lightmap erred by about 17 % at 4096 entries (this test's bounds
    // were 18 % and, at 16384, 15 %). With an eighth of the entries near the lights and their paths
    // traced by flux: 5.1 % and 4.9 % against the reference's 2.0 % noise;
    // with entries clustered by their light under the scene file's lights
    // too, 3.6 % and 4.2 % (the split helps the fewer entries more).
    // Bounds: 8 %, the boxes' bound, for both, and four times the entries
    // worse by at most one point (the two bakes' own spread).
    let (errors, noise) = lightmap_errors(
        "corridor",
        64,
        8192,
        &[
            &[("rank", "0"), ("top_k", "0")],
            &[("rank", "0"), ("top_k", "0"), ("entries", "16384")],
        ],
    );
    eprintln!(
        "corridor, 256 clusters, all used: 4096 entries {:.4}, 16384 entries {:.4}; reference noise {noise:.4}",
        errors[0], errors[1]
    );
    assert!(errors[0] < 0.08, "4096 entries: {}", errors[0]);
    assert!(errors[1] < 0.08, "16384 entries: {}", errors[1]);
    assert!(errors[1] < errors[0] + 0.01, "{errors:?}");
}

#[test]
fn every_cluster_receives_entry_points() {
    // Regression: seeding k-means with every 16th Halton entry put all seeds
    // in one sixteenth of the area and left 190 of 256 clusters empty.
    for scene in ["cornell-box", "corridor", "two-rooms"] {
        let context = context(scene, 64);
        let params = PrmParams {
            paths_per_entry: 1,
            rank: 0,
            ..PrmParams::default()
        };
        let bake = PrmBake::build(&context, &params, &NoProgress).unwrap();
        let sizes = bake.cluster_sizes();
        let empty = sizes.iter().filter(|&&size| size == 0).count();
        let mut areas = vec![0.0f64; bake.cluster_count];
        for (&cluster, &area) in bake.entry_clusters.iter().zip(&bake.entry_areas) {
            areas[cluster as usize] += area as f64;
        }
        let total: f64 = areas.iter().sum();
        let largest = areas.iter().copied().fold(0.0, f64::max) / total;
        eprintln!(
            "{scene}: {empty} empty clusters, the largest {:.2} % of the surface ({} entries)",
            largest * 100.0,
            sizes.iter().max().unwrap()
        );
        assert_eq!(empty, 0, "{scene}");
        // 1/256 of the surface per cluster on average; k-means on even
        // Halton points stays within a few times that, and an entry that
        // sees none of its nearest clusters' anchors, or a merge that frees
        // a cluster for such entries, can double one. By area, not count:
        // the entries near a light are dense, and its few square metres
        // are one cluster of hundreds (two-rooms' ceiling above the lamp).
        assert!(largest <= 8.0 / 256.0, "{scene}: largest cluster {largest}");
    }
}

#[test]
fn bake_is_identical_on_one_and_two_threads() {
    let context = context("cornell-box-point", 32);
    // Pane points two texels apart: their choice and coverage rounds are
    // part of what must not depend on the thread count.
    let params = PrmParams {
        entries: 512,
        clusters: 32,
        rank: 8,
        pane_resolution: 16,
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
    let one = bake_with(1);
    assert!(!PrmBake::decode(&one)
        .unwrap()
        .pane_points
        .is_every_receiver());
    assert!(one == bake_with(2));
}

/// Four shards, baked on one and two threads, merge to the bytes of the
/// whole bake: the panes are joined before their compression.
#[test]
fn shards_merge_to_the_whole_bake() {
    let context = context("cornell-box-point", 32);
    let params: Vec<(String, String)> = [
        ("entries", "512"),
        ("clusters", "32"),
        ("rank", "8"),
        ("pane_resolution", "16"),
    ]
    .iter()
    .map(|(key, value)| (key.to_string(), value.to_string()))
    .collect();
    relight_technique::robustness::check_shards_merge_to_whole(&PrmKind, &context, &params, 4);
}

#[test]
fn corrupt_payloads_are_errors_not_panics() {
    let context = context("cornell-box-point", 32);
    let params = PrmParams {
        entries: 256,
        clusters: 16,
        rank: 4,
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
    // Version, receivers, pane points (none: every receiver), their
    // spacing, entries, then the cluster count.
    lying[20..24].copy_from_slice(&u32::MAX.to_le_bytes());
    assert!(PrmBake::decode(&lying).is_err());
}

/// A quick bake's parameters with pane points two texels apart at a
/// 32-texel lightmap.
fn small_bake_with_pane_points() -> Vec<(String, String)> {
    [
        ("entries", "256"),
        ("clusters", "16"),
        ("rank", "4"),
        ("pane_resolution", "16"),
    ]
    .iter()
    .map(|(key, value)| (key.to_string(), value.to_string()))
    .collect()
}

/// Bit flips and truncations of a bake are refused or run; none panics.
#[test]
fn damaged_bakes_never_panic() {
    let context = context("cornell-box-point", 32);
    let params = small_bake_with_pane_points();
    let bake = PrmKind.bake(&context, &params, &NoProgress).unwrap();
    let (accepted, refused) = relight_technique::robustness::check_damaged_payloads(
        &PrmKind, &context, &params, &bake, 300, 1,
    );
    assert!(
        accepted > 0 && refused > 0,
        "{accepted} accepted, {refused} refused"
    );
}

/// The estimate counts the compression's basis, where a whole bake peaks,
/// and a shard its own panes twice (held, then encoded): a quarter of the
/// clusters needs less than half the whole bake's memory.
#[test]
fn the_estimate_counts_the_compression_and_shards() {
    let receivers = 10_000u64;
    let params = PrmParams::default();
    let whole = relight_prm::estimate_peak_bytes(&params, Shard::WHOLE, receivers);
    assert_eq!(whole, (256 + 128) * receivers * 6);
    let quarter = relight_prm::estimate_peak_bytes(&params, Shard::new(1, 4).unwrap(), receivers);
    assert!(quarter < whole / 2, "{quarter} of {whole}");

    let context = context("cornell-box-point", 64);
    let receivers = context.atlas.receivers.len() as u64;
    let estimate = PrmKind
        .estimate(&context, &[], Shard::WHOLE)
        .unwrap()
        .expect("PRM bakes");
    assert_eq!(
        estimate.peak_bytes(),
        relight_prm::estimate_peak_bytes(&params, Shard::WHOLE, receivers)
    );
    assert!(
        estimate.lower_memory_with.contains("clusters")
            && estimate.lower_memory_with.contains("--shard"),
        "{}",
        estimate.lower_memory_with
    );
}

#[test]
fn one_entry_pane_matches_path_traced_unit_irradiance() {
    // A unit-irradiance patch of area A and albedo a reflects like an
    // emitter of radiance a / pi over A. Path trace that emitter in the box
    // (direct light from it plus all indirect light) at every receiver and
    // compare with the entry point's pane.
    use glam::Vec3;
    use relight_core::Rgb;
    use relight_scene::Material;
    use relight_trace::path::PathTracer;

    // The entry point is on the ceiling's centre, facing down: far from the
    // blocks, so the patch's own penumbra (a point entry has none) does not
    // enter the comparison. (On the floor beside the short block, 2 cm of
    // patch is half hidden from parts of the walls.)
    let context = context("cornell-box-point", 48);
    let (_, high) = context.scene.mesh.bounds();
    let entry = Vec3::new(0.278, high.y, 0.28);
    let side = 0.01f32;
    let area = side * side;
    let ceiling_triangle = (0..context.scene.mesh.triangles.len())
        .find(|&t| {
            let [a, b, c] = context.scene.mesh.vertices(t);
            [a, b, c].iter().all(|v| (v.y - high.y).abs() < 1e-4)
        })
        .expect("the box has a ceiling");
    let ceiling_albedo = context.scene.material_of(ceiling_triangle).albedo;
    let down = -Vec3::Y;
    let pane = PrmBake::single_entry_pane(&context, entry, down, ceiling_albedo, area, 4096, 5);
    // A second, independent pane measures the light paths' own noise.
    let pane_again =
        PrmBake::single_entry_pane(&context, entry, down, ceiling_albedo, area, 4096, 6);

    // The same box with a small emitter just below the entry point, facing down.
    let mut scene = context.scene.clone();
    let base = scene.mesh.positions.len() as u32;
    let lift = -1e-4;
    let half = side / 2.0;
    scene.mesh.positions.extend([
        entry + Vec3::new(-half, lift, -half),
        entry + Vec3::new(half, lift, -half),
        entry + Vec3::new(half, lift, half),
        entry + Vec3::new(-half, lift, half),
    ]);
    // Counter-clockwise seen from below: normal -Y.
    scene
        .mesh
        .triangles
        .extend([[base, base + 1, base + 2], [base, base + 2, base + 3]]);
    let material = scene.materials.len() as u32;
    scene.mesh.material_ids.extend([material, material]);
    scene.materials.push(Material {
        name: "unit patch".into(),
        albedo: Rgb::ZERO,
        emission: ceiling_albedo / std::f32::consts::PI,
        ..Material::default()
    });
    let lit = SceneContext::new(
        scene,
        ContextSettings {
            lightmap: TexelDensity::TargetResolution(48),
            ..ContextSettings::default()
        },
    )
    .unwrap();
    let direct = lit.direct();
    let receivers = &context.atlas.receivers;
    // Two independent path-traced halves: their mean is the answer, their
    // difference measures its noise (stratification defeats the iid formula).
    let samples = 1024u32;
    let halves: Vec<Vec<[f64; 3]>> = [11u64, 12]
        .iter()
        .map(|&seed| {
            let tracer = PathTracer::new(
                &direct,
                PathSettings {
                    seed,
                    ..PathSettings::default()
                },
            );
            let mut sums = vec![[0.0f64; 3]; receivers.len()];
            tracer.indirect_irradiance_sums(
                &[],
                &receivers.positions,
                &receivers.normals,
                0,
                samples,
                samples,
                &mut sums,
            );
            sums
        })
        .collect();
    let far: Vec<usize> = (0..receivers.len())
        .filter(|&r| receivers.positions[r].distance(entry) > 0.1)
        .collect();
    let mut expected = Vec::with_capacity(far.len());
    let mut got = Vec::with_capacity(far.len());
    let mut got_again = Vec::with_capacity(far.len());
    let mut traced_difference = Vec::with_capacity(far.len());
    for &receiver in &far {
        let mut direct_sum = Rgb::ZERO;
        for key in 0..64u64 {
            direct_sum += direct.irradiance(
                &[],
                receivers.positions[receiver],
                receivers.normals[receiver],
                (receiver as u64) << 8 | key,
            );
        }
        let half = |index: usize| {
            Rgb::from_array(halves[index][receiver].map(|value| (value / samples as f64) as f32))
        };
        expected.push(direct_sum / 64.0 + (half(0) + half(1)) * 0.5);
        traced_difference.push((half(0) - half(1)) * 0.5);
        got.push(pane[receiver]);
        got_again.push(pane_again[receiver]);
    }
    let error = error_norms(&got, &expected).relative_rmse;
    // Two independent panes differ by sqrt(2) times one pane's noise.
    let pane_noise = error_norms(&got, &got_again).relative_rmse / 2f64.sqrt();
    let traced_noise = relative_noise(
        &expected,
        &traced_difference
            .iter()
            .map(|d| d.abs())
            .collect::<Vec<_>>(),
    );
    let total = |values: &[Rgb]| {
        values
            .iter()
            .map(|v| v.x as f64 + v.y as f64 + v.z as f64)
            .sum::<f64>()
    };
    let ratio = total(&got) / total(&expected);
    eprintln!(
        "single entry pane vs path tracing over {} receivers: relRMSE {error:.4}, pane noise {pane_noise:.4}, path-traced noise {traced_noise:.4}, sum ratio {ratio:.4}",
        far.len()
    );
    // Totals average out the virtual lights' noise: they must agree within
    // 3 %, which catches a missed bounce (the first bounce alone is about 70 %
    // of the total), a wrong factor of pi or a wrong albedo.
    assert!((ratio - 1.0).abs() < 0.03, "sum ratio {ratio}");
    // Per receiver: both sides' measured noise (independent, so in
    // quadrature, with 25 % slack for the noise estimates' own spread) plus
    // 3 % systematic: the disc guard changes 1/d^2 by r^2/d^2 <= 0.3 % beyond
    // 0.1 m for the entry itself, and trims the near field of the later
    // virtual lights (the totals come out about 2 % low).
    let bound = (pane_noise.powi(2) + traced_noise.powi(2)).sqrt() * 1.25 + 0.03;
    assert!(error < bound, "relRMSE {error} above {bound}");
}

#[test]
fn unlit_room_gets_the_light_that_crosses_the_doorway() {
    // Clusters of entry points straddle the dividing wall's ends. With the
    // paper's mean weight the lit room's irradiance and the unlit room's
    // panes mix, and the view from inside room B held 0.85x the path
    // tracer's indirect light; weights averaged by each entry's share of
    // the pane give 0.97x (relight converge
    // scenes/two-rooms/scene-unlit-room.toml -t prm, 320x240). Here at
    // 160x120 with 64 paths a pixel, whose noise on the total is well under
    // 1 %; the bound is the 0.85..1.15.
    let path =
        Path::new(env!("CARGO_MANIFEST_DIR")).join("../../scenes/two-rooms/scene-unlit-room.toml");
    let mut scene = relight_scene::load_scene(&path).expect("shipped scene loads");
    scene.camera.resolution = [160, 120];
    let context = Arc::new(SceneContext::new(scene, ContextSettings::default()).unwrap());
    let lights = context.scene.lights.clone();
    let reference = relight_render::render::render_reference(
        &context,
        &lights,
        PathSettings::default(),
        64,
        &NoProgress,
    );
    let prm = baked_and_updated(&context);
    let image = relight_render::render::render_with_technique(
        &context,
        &lights,
        prm.as_ref(),
        2,
        1,
        &NoProgress,
    );
    let ratio =
        relight_render::metrics::light_ratio(&image.indirect.pixels, &reference.indirect.pixels);
    eprintln!("view of room B: PRM {ratio:.3}x the path tracer's indirect light");
    assert!((0.85..1.15).contains(&ratio), "room B light ratio {ratio}");
}

#[test]
fn points_in_space_gather_the_lightmap() {
    // Points in space gather the light leaving the surfaces around them
    // (direct plus the lightmap's indirect). The cluster-centre disc lights
    // they replace gave one bounce without visibility: 71 % relRMSE and
    // 0.34x the light on two-rooms, 64 % on the corridor (relight converge
    // SCENE -t prm); the gather gives 8 % and 16 % there, 12 % and 16 % at
    // this test's 64-texel lightmap. The bound for PRM is 30 %;
    // 256 reference paths add about 5 % of noise.
    for scene in ["two-rooms", "corridor"] {
        let context = context(scene, 64);
        let prm = baked_and_updated(&context);
        let error = relight_render::convergence::space_error(&context, prm.as_ref(), 256);
        eprintln!("{scene}: points in space relRMSE {error:.4}");
        assert!(error < 0.3, "{scene}: {error}");
    }
}

/// The bound for PRM on the closed boxes is 15 % relRMSE of the
/// indirect image over 8x8-pixel tile means. What limits PRM there is the
/// compression of the panes, not the entry points or clusters (relight
/// converge SCENE -t prm --sweep rank=32,64,128,0 at full resolution, 8x8
/// tiles: area-lit box 14.5 / 9.8 / 5.3 / 4.7 %, point-lit box 11.9 / 13.1
/// / 9.5 / 8.7 %, light by a wall 20.2 / 15.4 / 8.5 / 5.9 %, light in a
/// corner 11.1 / 9.2 / 4.7 / 3.6 %, corridor 19.8 / 15.1 / 14.1 / 11.5 %),
/// so the default keeps 128 components: every box is within the bound,
/// where 32 left the wall light and the corridor outside it. At half the
/// cameras' resolution the reference's own tile noise is about 2 %.
#[test]
fn closed_boxes_within_fifteen_percent_over_tiles() {
    for scene in relight_render::convergence::CLOSED_BOXES {
        let context = relight_render::convergence::shipped_context(scene, 2);
        let error_at = |params: Vec<(String, String)>| {
            let bake = relight_technique::robustness::shared_bake(&PrmKind, &context, &params);
            let prm = updated_from(&context, &bake, &params);
            relight_render::convergence::measure_against_path_tracer(
                &context,
                prm.as_ref(),
                256,
                256,
            )
        };
        let (rank_32, _) = error_at(vec![("rank".to_string(), "32".to_string())]);
        let (defaults, noise) = error_at(Vec::new());
        println!(
            "{scene}: image 8x8 tiles {:.1} % at rank 32, {:.1} % at the defaults (reference noise {:.1} %)",
            rank_32.image_tiles * 100.0,
            defaults.image_tiles * 100.0,
            noise.image_tiles * 100.0
        );
        assert!(noise.image_tiles < 0.03, "{scene}: {}", noise.image_tiles);
        assert!(
            defaults.image_tiles <= 0.15,
            "{scene}: {}",
            defaults.image_tiles
        );
        assert!(
            defaults.image_tiles <= rank_32.image_tiles + noise.image_tiles,
            "{scene}: {} at the defaults against {} at rank 32",
            defaults.image_tiles,
            rank_32.image_tiles
        );
    }
}

/// Panes at pane points two lightmap texels apart, upsampled each frame,
/// against panes at every texel: the error against the path tracer may
/// grow by at most 1.5 points (two-rooms: 4.5 -> 5.5 %, the corridor 14.2
/// -> 13.9 %, `relight converge scenes/S/scene.toml -t prm
/// --lightmap-resolution 128 --sweep pane_resolution=0,64
/// --reference-samples 1024`). At four texels apart two-rooms reaches
/// 5.9 %; on Sponza, whose default 256 pane resolution is four of its
/// texels, the lightmap went 20.9 -> 21.7 % and the 8x8 tiles stayed at
/// 11.1 %.
#[test]
fn coarse_panes_upsample_to_the_light_of_full_panes() {
    for scene in ["two-rooms", "corridor"] {
        let runs: [&[(&str, &str)]; 2] =
            [&[("pane_resolution", "0")], &[("pane_resolution", "64")]];
        let (errors, noise) = lightmap_errors(scene, 128, 1024, &runs);
        eprintln!(
            "{scene}: lightmap relRMSE {:.4} with panes at every texel, {:.4} at pane points 2 texels apart; reference noise {noise:.4}",
            errors[0], errors[1]
        );
        assert!(errors[1] <= errors[0] + 0.015, "{scene}: {errors:?}");
    }
}

/// Every receiver that someone sees reads at least one pane point it sees
/// and that faces its way, and the pane points are a small share of the
/// receivers. A hidden receiver (under the Cornell box's blocks) may read
/// none: it stays dark, as the path tracer has it.
#[test]
fn every_receiver_reads_a_pane_point() {
    for scene in ["two-rooms", "corridor", "cornell-box"] {
        let context = context(scene, 128);
        let spacing = context.atlas.metres_per_texel * 4.0;
        let points = relight_prm::panes::PanePoints::select(&context, spacing);
        let upsampling =
            relight_prm::panes::Upsampling::build(&context, &points.receivers, spacing);
        let receivers = &context.atlas.receivers;
        assert_eq!(upsampling.weights.len(), receivers.len());
        let lift = relight_prm::panes::visibility_lift(&context, spacing);
        let mut dark = 0;
        for (receiver, weights) in upsampling.weights.iter().enumerate() {
            let total: u32 = weights.iter().map(|&weight| weight as u32).sum();
            if total == 0 {
                dark += 1;
                assert!(
                    context.is_hidden_surface_point(
                        receivers.positions[receiver],
                        receivers.normals[receiver],
                        lift
                    ),
                    "{scene}: receiver {receiver} is seen but reads no pane point"
                );
            } else {
                assert_eq!(total, 65535, "{scene}: receiver {receiver}");
            }
        }
        let receivers = receivers.len();
        let share = points.receivers.len() as f64 / receivers as f64;
        eprintln!(
            "{scene}: {} pane points for {receivers} receivers ({:.1} %), {dark} hidden ones read none",
            points.receivers.len(),
            share * 100.0
        );
        // One per 4x4 texels of a plane is 6 %; bins cut by edges and
        // curved surfaces add some, and uncovered receivers add their own.
        assert!(share < 0.2, "{scene}: {share}");
    }
}

/// A bake whose pane points claim to be closer than a lightmap texel (only
/// a damaged file can) is refused, not left to crowd the taps' grid.
#[test]
fn pane_points_closer_than_a_texel_are_refused() {
    let context = context("cornell-box-point", 32);
    let params = small_bake_with_pane_points();
    let bytes = PrmKind.bake(&context, &params, &NoProgress).unwrap();
    let mut bake = PrmBake::decode(&bytes).unwrap();
    assert!(!bake.pane_points.is_every_receiver());
    bake.pane_points.spacing = 1e-30;
    let error = PrmKind
        .create(context.clone(), Some(&bake.encode()), &params, &NoProgress)
        .err()
        .expect("refused");
    assert!(error.to_string().contains("bake it again"), "{error}");
}

/// A second ceiling 2.5 cm above the room's own, facing down like it (as
/// real models lay panels under a slab): no pane point stands on it, and
/// the visible ceiling gets the light it gets without the hidden layer.
/// Pane points 0.4 m apart lift their visibility rays 4 cm, across the
/// gap: pane points on the hidden layer, which gather nothing, passed as
/// visible and speckled the visible ceiling black (the classroom's).
#[test]
fn a_hidden_second_ceiling_takes_no_pane_points_and_leaves_no_blotch() {
    let gap = 0.025;
    let [_, height, _] = relight_scene::generate::TEST_ROOM;
    let light =
        "[[lights]]\nkind = \"point\"\nposition = [0.8, 1.0, -0.5]\nintensity = [4, 4, 4]\n";
    let params = vec![("pane_texel_size".to_string(), "0.4".to_string())];
    let run = |second_ceiling: Option<f32>| {
        let scene = relight_scene::generate::load_obj_scene(
            &relight_scene::generate::room_with_second_ceiling_obj(second_ceiling),
            light,
        )
        .expect("loads");
        let settings = ContextSettings {
            lightmap: TexelDensity::MetresPerTexel(0.05),
            ..ContextSettings::default()
        };
        let context = Arc::new(SceneContext::new(scene, settings).unwrap());
        let bytes = PrmKind.bake(&context, &params, &NoProgress).unwrap();
        let bake = PrmBake::decode(&bytes).unwrap();
        let receivers = &context.atlas.receivers;
        let on_hidden_layer = bake
            .pane_points
            .receivers
            .iter()
            .filter(|&&receiver| receivers.positions[receiver as usize].y > height + 0.5 * gap)
            .count();
        let prm = updated_from(&context, &bytes, &params);
        let irradiance = prm.receiver_irradiance().expect("receiver values");
        let ceiling = (0..receivers.len()).filter(|&index| {
            receivers.normals[index].y < -0.9
                && (receivers.positions[index].y - height).abs() < 0.005
        });
        let cells = relight_render::metrics::cell_means(
            ceiling.map(|index| (receivers.positions[index], irradiance[index])),
            0.5,
        );
        (on_hidden_layer, cells)
    };
    let (on_hidden_layer, doubled) = run(Some(gap));
    let (_, single) = run(None);
    let worst = relight_render::metrics::cell_ratio_range(&doubled, &single);
    println!("visible ceiling's 0.5 m cells, doubled over single: {worst:?}");
    assert_eq!(on_hidden_layer, 0, "pane points on the hidden layer");
    // The same entries light both rooms; what differs is the other
    // layer's charts in the atlas: measured 0.97-1.03x; with pane points
    // on the hidden layer 0.69-1.01x.
    assert!(worst.0 > 0.85 && worst.1 < 1.15, "{worst:?}");
}

/// Two-room suites of the robustness study's default family, seen from
/// the unlit room: a lamp in a shade (variant 1), 12 cm from the corner
/// where the partition meets an outer wall (7) and 10 cm from a corner
/// (10). Measured at the study's settings (`relight robustness -t prm
/// --first N --variants 1`): before, 3.92x, 2.88x and 0.67x of the path
/// tracer's light; 0.95x, 1.03x and 1.05x once clusters hold only entries
/// that see each other from the front, the entries near a lamp are dense
/// and trace paths by their flux, and the compression weighs each pane by
/// its light. Bound: the 0.85-1.15x; the light in view is an
/// image mean, far less noisy than the references' tiles (39, 23 and
/// 31 % here).
///
/// Variant 67 (a lamp 8 cm from a corner of the lit room, albedo 0.11)
/// read 1.22x with a bright blotch over the partition and doorway seen
/// from the unlit room: clusters a metre across held entries
/// by the lamp and in the patch of light through the doorway beside much
/// dimmer ones, and spread the light of the bright few over their whole
/// pane. Clustered by their light under the scene file's lights too, it
/// reads 1.04x (tile noise 26 %).
#[test]
fn unlit_rooms_beside_a_lamp_get_its_light() {
    for index in [1, 7, 10, 67] {
        let case = relight_render::robustness::VariantCase::default_family(index)
            .expect("the variant loads");
        let prm = baked_and_updated(&case.context);
        let (measured, _) = case.measure_as_the_study_does(prm.as_ref());
        assert!(
            (0.85..=1.15).contains(&measured.light_ratio),
            "variant {index}: {}",
            measured.light_ratio
        );
    }
}

/// Generated variant 30 has a box with a bottom face 6.5 mm above the floor
/// of a 4.6 m room (10 cm texels). Nothing covered the floor texels under
/// it within a lift and no back face enclosed them, so they were neither
/// moved out nor filled; nearly black, they darkened every lookup at the
/// box's foot. Measured at the study's settings (`relight robustness -t prm
/// --first 30 --variants 1`): the foot's tiles 5.8 % against the image's
/// 2.1 % (2.8x, a halo) at 0.952x of the path tracer's light; with the
/// floor under a bottom lower than a fifth of a texel counted as covered,
/// 1.8 % against 1.3 % at 0.987x. Bounds: the contact target (the
/// foot's tiles within 1.5x the image's), and the foot's light within
/// 3 % of the reference's: the reference's noise over those tiles is
/// 0.6 %.
#[test]
fn no_dark_halo_under_a_box_just_above_the_floor() {
    let case =
        relight_render::robustness::VariantCase::default_family(30).expect("the variant loads");
    let prm = baked_and_updated(&case.context);
    let (measured, contact) = case.measure_contact_as_the_study_does(prm.as_ref());
    assert!(contact.tiles > 0, "no contact tiles in view");
    assert!(
        !contact.is_halo(measured.image_tiles),
        "contact {} against the image's {}",
        contact.relative_rmse,
        measured.image_tiles
    );
    assert!(
        contact.light_ratio > 0.97,
        "contact light {}",
        contact.light_ratio
    );
}
