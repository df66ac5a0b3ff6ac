//! PIC against analytic answers and the path tracer.

use glam::Vec3;
use relight_core::{luminance, Rgb};
use relight_pic::hierarchy::{build_kd_tree, finalise, Hierarchy};
use relight_pic::surfels::place_surfels;
use relight_pic::{PicBake, PicKind};
use relight_render::metrics::error_norms;
use relight_render::study::indirect_errors;
use relight_scene::atlas::TexelDensity;
use relight_technique::{
    reference_receiver_irradiance, ContextSettings, Frame, NoProgress, SceneContext, SurfacePoint,
    Technique, TechniqueKind,
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

fn context_with(name: &str, shrink_image: bool) -> Arc<SceneContext> {
    let mut scene = relight_scene::load_scene(&scene_path(name)).expect("shipped scene loads");
    if shrink_image {
        // A small image keeps the reference's noise low at a test's cost.
        let [width, height] = scene.camera.resolution;
        scene.camera.resolution = [width / 4, height / 4];
    }
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

fn context(name: &str) -> Arc<SceneContext> {
    context_with(name, false)
}

fn pairs(list: &[(&str, &str)]) -> Vec<(String, String)> {
    list.iter()
        .map(|(key, value)| (key.to_string(), value.to_string()))
        .collect()
}

fn pic(context: &Arc<SceneContext>, params: &[(&str, &str)]) -> Box<dyn Technique> {
    let bake = relight_technique::robustness::shared_bake(&PicKind, context, &pairs(params));
    load_and_update(context, &bake, params)
}

/// PIC from `bake` with run-time `params`, after one update.
fn load_and_update(
    context: &Arc<SceneContext>,
    bake: &[u8],
    params: &[(&str, &str)],
) -> Box<dyn Technique> {
    let mut technique = PicKind
        .create(context.clone(), Some(bake), &pairs(params), &NoProgress)
        .expect("PIC loads its bake");
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

/// Surfels cover the scene's area exactly, lie on their triangles, and
/// relaxation spreads them (fewer surfels crowd a neighbour closer than
/// half the disc radius).
#[test]
fn surfels_cover_the_area_and_relax() {
    let context = context("corridor");
    let scene = &context.scene;
    let crowded = |positions: &[Vec3], radius: f32| {
        (0..positions.len())
            .filter(|&i| {
                (0..positions.len())
                    .any(|j| j != i && positions[i].distance(positions[j]) < 0.5 * radius)
            })
            .count()
    };
    let raw = place_surfels(scene, 2000, 0);
    let relaxed = place_surfels(scene, 2000, 4);
    let total = scene.mesh.total_area();
    for surfels in [&raw, &relaxed] {
        // Carried area rounds down once at the end: at most one short.
        assert!((1999..=2000).contains(&surfels.len()), "{}", surfels.len());
        assert!((surfels.area as f64 * 2000.0 - total).abs() < 1e-3 * total);
        for index in 0..surfels.len() {
            let [a, b, c] = scene.mesh.vertices(surfels.triangles[index] as usize);
            let bary = surfels.barycentrics[index];
            let on_triangle = a * (1.0 - bary.x - bary.y) + b * bary.x + c * bary.y;
            assert!(on_triangle.distance(surfels.positions[index]) < 1e-4);
            assert!(bary.x >= -1e-6 && bary.y >= -1e-6 && bary.x + bary.y <= 1.0 + 1e-6);
        }
    }
    let radius = (raw.area / std::f32::consts::PI).sqrt();
    let (before, after) = (
        crowded(&raw.positions, radius),
        crowded(&relaxed.positions, radius),
    );
    println!("surfels closer than half a radius to another: {before} -> {after}");
    assert!(after * 2 < before, "{before} -> {after}");
}

/// Every node covers the contiguous leaf range of its two children and
/// children come before parents, for both builders.
#[test]
fn hierarchies_are_consistent() {
    fn check(hierarchy: &Hierarchy) {
        let n = hierarchy.leaf_count;
        assert_eq!(hierarchy.node_count(), 2 * n as usize - 1);
        assert_eq!(hierarchy.leaves[hierarchy.root() as usize], n);
        for node in n..hierarchy.node_count() as u32 {
            let [left, right] = hierarchy.children_of(node);
            assert!(left < node && right < node);
            let first = hierarchy.first_leaf[node as usize];
            assert_eq!(hierarchy.first_leaf[left as usize], first);
            assert_eq!(
                hierarchy.first_leaf[right as usize],
                first + hierarchy.leaves[left as usize]
            );
            assert_eq!(
                hierarchy.leaves[node as usize],
                hierarchy.leaves[left as usize] + hierarchy.leaves[right as usize]
            );
        }
        let (subtrees, top) = hierarchy.pull_schedule(8);
        let covered: u32 = subtrees.iter().map(|&s| hierarchy.leaves[s as usize]).sum();
        assert_eq!(covered, n);
        assert!(top.windows(2).all(|pair| pair[0] < pair[1]));
    }
    let context = context("cornell-box");
    let surfels = place_surfels(&context.scene, 3000, 2);
    let (kd, _) = finalise(surfels.len(), &build_kd_tree(&surfels.positions));
    check(&kd);
    let merges = relight_pic::hierarchy::build_agglomerative(
        &surfels.positions,
        &surfels.normals,
        &context.bvh,
        relight_pic::hierarchy::ClusterMetric {
            normal: 0.1,
            balance: 0.02,
            visibility: 1.0,
        },
        &NoProgress,
    );
    let (hac, order) = finalise(surfels.len(), &merges);
    check(&hac);
    let mut sorted = order.clone();
    sorted.sort_unstable();
    assert!(sorted.iter().enumerate().all(|(i, &s)| i as u32 == s));
    // Clustering keeps the tree reasonably balanced (C_b); a chain would be
    // 2999 deep.
    assert!(hac.depth() < 60, "depth {}", hac.depth());
}

/// The same bake and parameters give the same bytes on one thread and on
/// several.
#[test]
fn bake_is_deterministic_across_thread_counts() {
    let context = context("cornell-box-point");
    // Both link forms: projected coefficients are scaled per cache and
    // rescaled in place once every cache is done.
    for projected in ["false", "true"] {
        let params = pairs(&[
            ("surfels", "4000"),
            ("links", "32"),
            ("lightmap_caches", "2000"),
            ("projected", projected),
        ]);
        let bake_on = |threads: usize| {
            rayon::ThreadPoolBuilder::new()
                .num_threads(threads)
                .build()
                .unwrap()
                .install(|| PicKind.bake(&context, &params, &NoProgress).unwrap())
        };
        assert_eq!(bake_on(1), bake_on(3), "projected = {projected}");
    }
}

/// Four shards, baked on one and two threads, merge to the bytes of the
/// whole bake, in both link forms (projected links are rescaled to one
/// scale only the merge knows).
#[test]
fn shards_merge_to_the_whole_bake() {
    let context = context("cornell-box-point");
    for projected in ["false", "true"] {
        let params = pairs(&[
            ("surfels", "4000"),
            ("links", "32"),
            ("lightmap_caches", "2000"),
            ("projected", projected),
        ]);
        relight_technique::robustness::check_shards_merge_to_whole(&PicKind, &context, &params, 4);
    }
}

/// Corrupt payloads fail with a message, never a panic.
#[test]
fn corrupt_bakes_are_refused() {
    let context = context("cornell-box-point");
    let params = pairs(&[
        ("surfels", "1000"),
        ("links", "8"),
        ("lightmap_caches", "500"),
    ]);
    let bake = PicKind.bake(&context, &params, &NoProgress).unwrap();
    for cut in [0usize, 4, 17, bake.len() / 2, bake.len() - 1] {
        assert!(PicBake::decode(&bake[..cut]).is_err());
    }
    let mut flipped = bake.clone();
    // The version.
    flipped[0] ^= 0x40;
    assert!(PicBake::decode(&flipped).is_err());
    assert!(PicBake::decode(&bake).is_ok());
    // A bake for a different lightmap is refused when created.
    let other = context_with("cornell-box-point", false);
    let mut scene = other.scene.clone();
    scene.mesh.positions[0].x += 0.0;
    let coarse = Arc::new(
        SceneContext::new(
            scene,
            ContextSettings {
                lightmap: TexelDensity::TargetResolution(64),
                ..ContextSettings::default()
            },
        )
        .unwrap(),
    );
    let scene_atlas = pairs(&[
        ("surfels", "1000"),
        ("links", "8"),
        ("lightmap_caches", "0"),
    ]);
    let bake = PicKind.bake(&context, &scene_atlas, &NoProgress).unwrap();
    assert!(PicKind
        .create(coarse, Some(&bake), &scene_atlas, &NoProgress)
        .is_err());
}

/// Error falls as links, surfels and bands grow (measured on this scene
/// while building, lightmap relRMSE against 2048 paths: links 16, 48, 128:
/// 21.2, 15.8, 14.0 %; surfels 2048, 8192, 32768: 17.3, 14.4, 14.0 %;
/// bands 2, 3: 19.7, 14.0 %).
#[test]
fn error_falls_with_links_surfels_and_bands() {
    let context = context("cornell-box-point");
    let reference = reference(&context, 1024);
    let error = |params: &[(&str, &str)]| {
        let mut all = vec![("lightmap_caches", "0")];
        all.extend_from_slice(params);
        let technique = pic(&context, &all);
        error_norms(technique.receiver_irradiance().unwrap(), &reference).relative_rmse
    };
    let by_links: Vec<f64> = ["16", "48", "128"]
        .iter()
        .map(|links| error(&[("links", links), ("surfels", "16384")]))
        .collect();
    let by_surfels: Vec<f64> = ["2048", "16384"]
        .iter()
        .map(|surfels| error(&[("surfels", surfels)]))
        .collect();
    let by_bands: Vec<f64> = ["2", "3"]
        .iter()
        .map(|bands| error(&[("bands", bands), ("surfels", "16384")]))
        .collect();
    println!("links 16, 48, 128: {by_links:?}; surfels 2k, 16k: {by_surfels:?}; bands 2, 3: {by_bands:?}");
    for series in [&by_links, &by_surfels, &by_bands] {
        assert!(
            series.windows(2).all(|pair| pair[1] < pair[0]),
            "{series:?}"
        );
    }
}

/// Figure 9c of the paper: clusters that merge surfels which cannot see
/// each other carry the lit room's flux into the unlit one. The two-rooms
/// floor and ceiling run on under the dividing wall, so the paper's metric
/// merges floor surfels from both sides of it (0.3 m apart, same normal)
/// and room B's caches near the wall link clusters holding room A's lit
/// floor. Measured here:
/// - near the wall in room B (floor and ceiling within 0.8 m of it and the
///   wall's room-B face, away from the doorway), the paper's metric leaks:
///   1.80 times the path tracer's light at 32 links, 1.27 times at 128,
///   against 0.74 and 0.76 for visibility-aware clustering, which stays
///   below the reference like PIC everywhere;
/// - on room B's far wall (x = 8.2, the measure) visibility-aware
///   clustering is within 25 % of the path tracer at the default 128 links
///   (0.75; 0.58 at 32 links), and neither is several times it. The
///   paper's metric reads 0.90 there: its leak happens to offset PIC's
///   general shortfall that far from the wall.
#[test]
fn visibility_aware_clustering_stops_leaks_between_rooms() {
    let context = context("two-rooms");
    let receivers = &context.atlas.receivers;
    let select = |keep: &dyn Fn(glam::Vec3, glam::Vec3) -> bool| -> Vec<usize> {
        (0..receivers.len())
            .filter(|&i| keep(receivers.positions[i], receivers.normals[i]))
            .collect()
    };
    let far_wall = select(&|position, normal| position.x > 8.1 && normal.x < -0.9);
    // Room B is x > 4.2; the doorway spans z = 1.5 .. 2.5.
    let away_from_door = |position: glam::Vec3| position.z < 1.2 || position.z > 2.8;
    let near_wall = select(&|position, normal| {
        away_from_door(position)
            && ((position.x > 4.2 && position.x < 5.0 && normal.y.abs() > 0.9)
                || (position.x > 4.15 && position.x < 4.3 && normal.x > 0.9))
    });
    assert!(far_wall.len() > 50 && near_wall.len() > 200);
    let mean = |set: &[usize], values: &[Rgb]| {
        set.iter()
            .map(|&i| luminance(values[i]) as f64)
            .sum::<f64>()
            / set.len() as f64
    };
    let truth = reference(&context, 1024);
    // (far wall, near wall), each over the path tracer's.
    let ratios = |params: &[(&str, &str)]| {
        let mut all = vec![("lightmap_caches", "0"), ("surfels", "16384")];
        all.extend_from_slice(params);
        let technique = pic(&context, &all);
        let values = technique.receiver_irradiance().unwrap();
        (
            mean(&far_wall, values) / mean(&far_wall, &truth),
            mean(&near_wall, values) / mean(&near_wall, &truth),
        )
    };
    let paper_metric = [("visibility_weight", "0"), ("leak_refinement", "0")];
    for links in ["32", "128"] {
        let (aware_far, aware_near) = ratios(&[("links", links)]);
        let mut paper_params = vec![("links", links)];
        paper_params.extend_from_slice(&paper_metric);
        let (paper_far, paper_near) = ratios(&paper_params);
        println!(
            "{links} links, over the reference: far wall visibility-aware {aware_far:.3}, paper's metric {paper_far:.3}; near the wall {aware_near:.3} and {paper_near:.3}"
        );
        // No leak: below the reference plus the path tracer's noise
        // (PIC's clusters average radiosity low, so it sits under 1).
        assert!(aware_near < 1.05, "{links} links: {aware_near}");
        // The leak the fix removes: well above the reference.
        assert!(paper_near > 1.15, "{links} links: {paper_near}");
        assert!(paper_far < 2.0 && aware_far < 2.0);
        if links == "128" {
            assert!((aware_far - 1.0).abs() <= 0.25, "{aware_far}");
        }
    }
}

/// Chroma with fewer bands than luma stays close to full colour (section
/// 4.8), points in space read the grid close to the lightmap, and glossy
/// reflection follows the viewer.
#[test]
fn chroma_grid_and_glossy_lookups() {
    let context = context("corridor");
    let full = pic(
        &context,
        &[
            ("bands", "4"),
            ("surfels", "8192"),
            ("links", "64"),
            ("space", "grid"),
        ],
    );
    let compressed = pic(
        &context,
        &[
            ("bands", "4"),
            ("chroma_bands", "2"),
            ("surfels", "8192"),
            ("links", "64"),
            ("specular", "0.5"),
        ],
    );
    let full_values = full.receiver_irradiance().unwrap();
    let chroma_error =
        error_norms(compressed.receiver_irradiance().unwrap(), full_values).relative_rmse;
    println!("chroma 2 of 4 bands vs full: {:.2} %", chroma_error * 100.0);
    // Chroma carries a small share of the energy; losing its high bands
    // moves colour, not brightness.
    assert!(chroma_error < 0.05, "{chroma_error}");
    let receivers = &context.atlas.receivers;
    let grid: Vec<Rgb> = (0..receivers.len())
        .map(|i| {
            full.indirect_irradiance_in_space(
                receivers.positions[i] + receivers.normals[i] * 0.3,
                receivers.normals[i],
            )
        })
        .collect();
    let grid_error = error_norms(&grid, full_values).relative_rmse;
    println!(
        "grid 0.3 m off the surfaces vs lightmap: {:.1} %",
        grid_error * 100.0
    );
    // The grid's cells are about 0.6 m: trilinear interpolation over them
    // blurs the lightmap, but stays on its scale.
    assert!(grid_error < 0.5, "{grid_error}");
    let index = receivers.len() / 2;
    let point = SurfacePoint {
        position: receivers.positions[index],
        normal: receivers.normals[index],
        triangle: receivers.triangles[index],
        barycentric: receivers.barycentrics[index],
    };
    let tangent = relight_core::sampling::orthonormal_basis(point.normal).0;
    let looks: Vec<Rgb> = [0.2f32, 0.6, 0.95]
        .iter()
        .map(|&c| {
            let view = (point.normal * c + tangent * (1.0 - c * c).sqrt()).normalize();
            compressed
                .glossy_radiance(&point, view, 40.0)
                .expect("glossy with specular > 0")
        })
        .collect();
    assert!(full.glossy_radiance(&point, point.normal, 40.0).is_none());
    assert!(looks
        .iter()
        .all(|l| l.is_finite() && l.min_element() >= 0.0));
    assert!(looks.windows(2).any(
        |pair| (pair[0] - pair[1]).abs().max_element() > 1e-4 * pair[0].max_element().max(1e-6)
    ));
}

/// All-bounce accuracy against the path tracer on the shipped scenes at
/// the high preset, the bounds: lightmap relRMSE at most 10 %,
/// indirect-only image at most 15 %. The errors include the reference's own
/// noise (printed), which only makes the check stricter. Measured with
/// this test (2048 paths a receiver, 4096 a pixel): cornell-box 7.5 / 6.4 %,
/// cornell-box-point 6.1 / 6.6 %, corridor 7.7 / 7.6 % (lightmap / image).
#[test]
fn accuracy_against_the_path_tracer() {
    for scene in ["cornell-box", "cornell-box-point", "corridor"] {
        let context = context_with(scene, true);
        let technique = pic(&context, &[("preset", "high")]);
        let errors = indirect_errors(
            &context,
            technique.as_ref(),
            PathSettings::default(),
            2048,
            4096,
        );
        println!(
            "{scene}: lightmap {:.1} % (reference noise {:.1} %), image {:.1} % (reference noise {:.1} %)",
            errors.lightmap * 100.0,
            errors.lightmap_noise * 100.0,
            errors.image * 100.0,
            errors.image_noise * 100.0
        );
        assert!(errors.lightmap_noise < 0.05 && errors.image_noise < 0.1);
        assert!(
            errors.lightmap <= 0.10,
            "{scene} lightmap {}",
            errors.lightmap
        );
        assert!(errors.image <= 0.15, "{scene} image {}", errors.image);
    }
}

/// A bake made for four bands runs with four unless the run names its
/// bands: `relight bench --bake high.bake` must time the preset it baked.
#[test]
fn runs_with_the_bands_it_was_baked_for() {
    let context = context("cornell-box-point");
    let baked = pairs(&[("bands", "4"), ("surfels", "2048"), ("links", "32")]);
    let bake = PicKind
        .bake(&context, &baked, &NoProgress)
        .expect("PIC bakes");
    let run = |params: &[(&str, &str)]| {
        let technique = load_and_update(&context, &bake, params);
        let facts = technique.bake_facts();
        let bands = facts
            .iter()
            .find(|(name, _)| *name == "pic cache bands")
            .map(|(_, text)| text.clone())
            .expect("bake facts name the bands");
        (technique.receiver_irradiance().unwrap().to_vec(), bands)
    };
    let (default_values, default_bands) = run(&[]);
    let (four_values, _) = run(&[("bands", "4")]);
    let (three_values, three_bands) = run(&[("bands", "3")]);
    assert!(
        default_bands.contains("running with 4 and 4"),
        "{default_bands}"
    );
    assert!(
        three_bands.contains("running with 3 and 3"),
        "{three_bands}"
    );
    assert_eq!(default_values, four_values);
    assert_ne!(default_values, three_values);
}

/// Damaged bakes (bit flips, truncations) of both link forms are refused
/// or run; none panics.
#[test]
fn damaged_bakes_never_panic() {
    let context = context("cornell-box-point");
    for projected in ["false", "true"] {
        let params = pairs(&[
            ("surfels", "1024"),
            ("links", "16"),
            ("projected", projected),
            ("grid_cells", "64"),
            ("lightmap_caches", "256"),
            // The gather's rays come from the scene, not the bake; its
            // automatic count (up to 1024 rays a gathering receiver on a
            // small scene, at every create) would be most of the
            // test's time.
            ("final_gather_rays", "8"),
        ]);
        let bake = PicKind
            .bake(&context, &params, &NoProgress)
            .expect("PIC bakes");
        let (accepted, refused) = relight_technique::robustness::check_damaged_payloads(
            &PicKind, &context, &params, &bake, 300, 1,
        );
        // Most flips land in float data, which decodes; the counts show
        // that both paths were exercised.
        assert!(
            accepted > 0 && refused > 0,
            "{accepted} accepted, {refused} refused"
        );
    }
}

/// The bound for the high preset on the closed boxes: the indirect
/// image within 8 % relRMSE of the path tracer over 8x8-pixel tile means
/// (which average the reference's per-pixel noise away), all bounces. At
/// half the cameras' resolution (256 tiles, 256 reference paths a pixel
/// and receiver) the reference's own tile noise is about 2 %. relight
/// converge at full resolution measured 4.7 / 4.6 / 3.4 / 5.2 / 5.7 %
/// (area light, point light, light by a wall, light in a corner,
/// corridor).
#[test]
fn closed_boxes_within_eight_percent_over_tiles_at_the_high_preset() {
    let measured = relight_render::convergence::closed_box_measurements(|context, _| {
        pic(context, &[("preset", "high")])
    });
    for (scene, measured) in measured {
        assert!(
            measured.image_tiles <= 0.08,
            "{scene}: {}",
            measured.image_tiles
        );
    }
}

/// Points in space gather the light leaving the surfaces around them (each
/// hit's direct light plus the lightmap caches' indirect light there). The
/// grid's trilinear blend of caches crosses walls: relight converge SCENE
/// -t pic --sweep space=grid,gather measured 13.7 -> 9.8 % on two-rooms,
/// 16.8 -> 14.9 % on the corridor and 70.6 -> 18.3 % on Sponza. The bound
/// is the 20 % for PIC; 256 reference paths add about 5 % noise.
#[test]
fn points_in_space_gather_the_lightmap() {
    for scene in ["two-rooms", "corridor"] {
        let context = context(scene);
        let technique = pic(&context, &[]);
        let error = relight_render::convergence::space_error(&context, technique.as_ref(), 256);
        eprintln!("{scene}: points in space relRMSE {error:.4}");
        assert!(error < 0.2, "{scene}: {error}");
    }
}

/// The floor of two-rooms is one quad under the dividing wall, so a cache
/// atlas coarser than the wall is thick puts lit room A's caches and room
/// B's in the same bilinear footprint. Room B's floor next to the wall
/// (x = 4.2 .. 4.9, away from the doorway) must not take room A's light:
/// with `cache_visibility` its receivers drop the caches beyond the wall.
/// The gather is off so that the lookup alone is measured. Measured with
/// 1024 caches (texels of about 0.4 m): 0.996x the path tracer's light
/// with the visibility test, 1.688x without; the bounds leave room for
/// PIC's usual shortfall (0.77x with a cache per texel) and the
/// reference's noise (1024 paths over 50+ receivers: well under 1 %).
/// With 256 caches (0.8 m) the floor strip gets 2.4-2.7x either way: a
/// cache atlas that coarse has no cache of room B near the wall to keep.
#[test]
fn receivers_do_not_blend_caches_beyond_a_wall() {
    let context = context("two-rooms");
    let receivers = &context.atlas.receivers;
    let near_wall: Vec<usize> = (0..receivers.len())
        .filter(|&i| {
            let (position, normal) = (receivers.positions[i], receivers.normals[i]);
            position.x > 4.2
                && position.x < 4.9
                && (position.z < 1.2 || position.z > 2.8)
                && normal.y > 0.9
                && position.y < 0.1
        })
        .collect();
    assert!(near_wall.len() > 50, "{}", near_wall.len());
    let mean = |values: &[Rgb]| {
        near_wall
            .iter()
            .map(|&i| luminance(values[i]) as f64)
            .sum::<f64>()
            / near_wall.len() as f64
    };
    let truth = mean(&reference(&context, 1024));
    let ratio = |visibility: &str| {
        let technique = pic(
            &context,
            &[
                ("lightmap_caches", "1024"),
                ("surfels", "16384"),
                ("final_gather", "0"),
                ("cache_visibility", visibility),
            ],
        );
        mean(technique.receiver_irradiance().unwrap()) / truth
    };
    let (seen, blended) = (ratio("true"), ratio("false"));
    println!(
        "room B's floor by the wall over the path tracer: caches it sees {seen:.3}, all four {blended:.3}"
    );
    assert!((0.7..1.15).contains(&seen), "{seen}");
    assert!(
        blended > 1.4,
        "the leak this test is about is gone: {blended}"
    );
}

/// Two-rooms seen from inside the unlit room: nearly all its light has
/// bounced at least twice, and much of it off the near field of its
/// corners and the doorway's reveals. The final gather traces that near
/// field for the receivers; the surfels, which carry every further bounce,
/// must read it too (the gather's correction at each surfel), and a gather
/// hit on a gathering receiver must reflect what that receiver gathered.
/// Without both, each bounce lost the near field again: this view held
/// 0.925x the path tracer's light and 6.1 % over 8x8 tiles at full size
/// (`relight converge scenes/two-rooms/scene-unlit-room.toml -t pic
/// --preset high`), 0.952x and 3.9 % with them. Here, at half size:
/// 0.923x and 6.19 % without, 0.950x and 4.01 % with (reference noise
/// over tiles 0.86 %), and 0.948x and 4.1 % once partly hidden nodes were
/// refined first (`leak_refinement` 16); the bounds sit between the two,
/// the light ratio's noise over a whole image at 256 paths being well
/// under 1 %.
#[test]
fn later_bounces_keep_the_near_field() {
    let measured = relight_render::convergence::unlit_room_measurement(|context| {
        pic(context, &[("preset", "high")])
    });
    assert!(
        (0.94..1.1).contains(&measured.light_ratio),
        "{}",
        measured.light_ratio
    );
    assert!(measured.image_tiles < 0.05, "{}", measured.image_tiles);
}

/// The first update settles every bounce of a bright closed room
/// ([`relight_technique::robustness::check_first_update_settles`]: passes
/// stop once the light they would still add is under
/// [`relight_technique::SETTLED_SHARE`]). Measured: 47 passes, 0.996 of
/// what 300 more updates reach (44 before the links were normalised: PIC
/// lost more light a bounce, so its series fell faster). A fixed 16 passes gave 0.863 here, and
/// PIC `high` 0.818x of the path tracer's light in a 4 x 2.6 x 5 m grey
/// room of albedo 0.9 (`relight converge`).
#[test]
fn the_first_update_settles_the_bounces_of_a_bright_closed_room() {
    let context = relight_technique::robustness::closed_grey_room(0.9);
    let mut technique = pic(&context, &[]);
    let (passes, share) = relight_technique::robustness::check_first_update_settles(
        technique.as_mut(),
        &context,
        128,
    );
    println!("{passes} passes, {share:.3} of what 300 more updates reach");
}

/// Two rooms joined by a doorway, seen from the unlit room, as the
/// generator models them (variants 55 and 64 of the default family: a box
/// per room with a doorway, and one shell; a point light 0.27 m from a
/// corner and 0.11 m from a wall of the lit room). The unlit room's
/// caches see the lit room only through the doorway, as small parts of
/// large nodes whose flux comes mostly from surfels they cannot see; links
/// to such nodes spread that flux by the node's mean factor, and came out
/// as bright blotches on the unlit room's walls (64) or too little light
/// (55). Refining partly hidden nodes first (`leak_refinement`) puts the
/// links where the doorway is. Measured at the study's settings (half the
/// variants' camera, 256 paths, as `relight robustness -t pic --preset
/// high --first 55 --variants 1`): 55 gave 9.3 % over 8x8 tiles and
/// 0.821x the light in view, 64 19.8 % and 0.878x with `leak_refinement`
/// 1, and 7.0 %, 0.924x and 6.1 %, 0.959x at 16. The bounds are the
/// issue's (8 % on rooms, 0.85-1.15x in an unlit room); the references'
/// own tile noise is 1.9 and 3.3 %.
#[test]
fn generated_suites_light_their_unlit_room_through_the_doorway() {
    use relight_scene::generate::variants::VariantKind;
    for index in [55, 64] {
        let case = relight_render::robustness::VariantCase::default_family(index)
            .expect("the variant loads");
        assert_eq!(
            case.variant.kind,
            VariantKind::TwoRooms,
            "{}",
            case.variant.name()
        );
        let technique = pic(&case.context, &[("preset", "high")]);
        let (measured, noise) = case.measure_as_the_study_does(technique.as_ref());
        assert!(noise.image_tiles < 0.04, "{}", noise.image_tiles);
        assert!(
            (0.85..=1.15).contains(&measured.light_ratio),
            "variant {index}: {}",
            measured.light_ratio
        );
        assert!(
            measured.image_tiles < 0.08,
            "variant {index}: {}",
            measured.image_tiles
        );
    }
}

/// Bright two-room suites, whose unlit room gets most of its light after
/// many bounces (variant 28: albedo 0.9, a lamp in a shade open on one
/// side; variant 97: albedo 0.54, each room its own box, so the dividing
/// wall is two faces back to back). Each bounce passes through the
/// caches' links, which under a uniform radiosity gathered 0.90 of it at
/// the 10th percentile of a closed room's caches, so the loss compounded:
/// 028 gave 0.837x the path tracer's light in view, 097 8x8 tiles of
/// 15.9 %, while the first bounce was right. With the links normalised
/// (`link_normalisation`), 0.925x and 10.1 %. Bounds: the issue's
/// 0.85-1.15x in an unlit room, and 1.5 times the 8 % room bound, which
/// the issue allows its worst variant (the references' own tile noise is
/// 7.5 and 1.2 %, so 028's tiles are not held to a bound).
#[test]
fn later_bounces_keep_their_light_through_the_links() {
    for (index, most_tiles) in [(28, f64::INFINITY), (97, 0.12)] {
        let (_, measured) = measure_unlit_room(index);
        assert!(
            measured.image_tiles < most_tiles,
            "variant {index}: {}",
            measured.image_tiles
        );
    }
}

/// PIC `high` on variant `index` of the default family (two rooms), at the
/// study's settings, with the unlit room's light in view held to the
/// issue's 0.85-1.15x.
fn measure_unlit_room(
    index: usize,
) -> (
    relight_render::robustness::VariantCase,
    relight_render::convergence::Measurement,
) {
    let case =
        relight_render::robustness::VariantCase::default_family(index).expect("the variant loads");
    let technique = pic(&case.context, &[("preset", "high")]);
    let (measured, _) = case.measure_as_the_study_does(technique.as_ref());
    assert!(
        (0.85..=1.15).contains(&measured.light_ratio),
        "variant {index}: {}",
        measured.light_ratio
    );
    (case, measured)
}

/// Two rooms lit by a point light inside a lampshade open below, seen from
/// the unlit room (variant 79 of the default family). The shade bounces
/// much of its light inside before letting it out, which a room's texel
/// size cannot resolve on a 32 cm face; the atlas now gives the shade's
/// inside finer texels (`lightmap.refine_near_lights`). Measured at the
/// study's settings (`relight robustness -t pic --preset high --first 79
/// --variants 1`): light in view 0.807x before, 0.899x after, 8x8 tiles
/// 25.7 -> 16.8 % (the reference's own tile noise is 9.4 %, so the tiles
/// are not held to the 8 %); with the near-light samples and the
/// links normalised since, 1.002x and 12.3 %. Bound: the issue's
/// 0.85-1.15x in an unlit room.
#[test]
fn a_room_lit_by_a_shaded_lamp_gets_its_light() {
    assert_shaded_lamp_lights_the_unlit_room(79);
}

/// PIC `high` on variant `index` of the default family, whose lamp stands
/// in a shade the atlas refined: the unlit room's light in view within the
/// issue's 0.85-1.15x, at the study's settings.
fn assert_shaded_lamp_lights_the_unlit_room(index: usize) {
    let (case, _) = measure_unlit_room(index);
    assert!(case.context.atlas.near_light_charts > 0);
}

/// No cache links more solid angle than it can see. Each surfel sample is
/// a disc of up to 2 pi at contact, so the discs around a cache where two
/// surfaces meet overlap: on two-rooms a cache at the foot of the dividing
/// wall linked 19.3 hemispheres at the defaults and 8.7 with PIC high, and
/// one on a narrow face of the classroom 13.4 (PIC high), which lit its
/// texels 300 times brighter than the path tracer. The bake scales such a
/// cache's links back to its hemisphere once they sum past
/// [`relight_pic::links::OVERLAP_ALLOWANCE`] of it, which the bound
/// allows, with a little for the f16 values. Both link forms: factors
/// (the defaults) and SH coefficients (`high`), whose constant term is the
/// solid angle times Y00 / (pi * leaves).
#[test]
fn no_cache_links_more_than_its_hemisphere() {
    use std::f32::consts::PI;
    let context = context("two-rooms");
    let unhalf = |bits: u16| half::f16::from_bits(bits).to_f32();
    for params in [vec![], vec![("preset", "high")]] {
        let payload =
            relight_technique::robustness::shared_bake(&PicKind, &context, &pairs(&params));
        let bake = PicBake::decode(&payload).expect("the bake decodes");
        let coefficients = bake.projected_bands * bake.projected_bands;
        let mut widest = 0.0f32;
        for cache in 0..bake.caches.positions.len() {
            let links = cache * bake.links_per_cache..(cache + 1) * bake.links_per_cache;
            let solid_angle: f32 = links
                .map(|link| {
                    let leaves = bake.hierarchy.leaves[bake.link_nodes[link] as usize] as f32;
                    if coefficients == 0 {
                        let factor = unhalf(bake.link_factors[link]) / bake.factor_scale;
                        let cone = 2.0 * PI * unhalf(bake.link_cones[link]);
                        factor * cone * PI * leaves
                    } else {
                        let constant =
                            unhalf(bake.link_coefficients[link * coefficients]) / bake.factor_scale;
                        // Y00 = 1 / (2 sqrt(pi)).
                        constant * PI * leaves * 2.0 * PI.sqrt()
                    }
                })
                .sum();
            let visible = relight_pic::links::visible_solid_angle(bake.caches.normals[cache]);
            widest = widest.max(solid_angle / visible);
        }
        println!("{params:?}: widest cache {widest:.3} of what it can see");
        // Some cache sees nearly all of its hemisphere: the sums are real.
        assert!(widest > 0.9, "{params:?}: {widest}");
        assert!(
            widest < relight_pic::links::OVERLAP_ALLOWANCE + 0.01,
            "{params:?}: {widest}"
        );
    }
}

/// Two boxes for rooms, lit by a point light inside a shade open on two
/// sides, seen from the unlit room (variant 13 of the default family).
/// The shade's inside is a few surfels of nodes that also hold the walls
/// around it, and each link's factor samples a few of a node's surfels, so
/// the unlit room's caches got the shade's light by where those samples
/// fell: 1.139x against a 2048-path reference (`relight robustness -t pic
/// --preset high --first 13 --variants 1 --reference-spp 2048`), 8x8
/// tiles 21.6 %. The lightmap caches now see the surfaces beside the lamp
/// through the final gather's explicit samples, traced at load, and those
/// surfels leave their direct light out of the links: 1.039x, 9.6 %
/// (1.063x at the study's 256 paths; 1.066x with the links normalised).
/// Bound: the 0.85-1.15x in an unlit room, at the study's 256
/// paths.
///
/// A lamp 11 cm from a room's corner (variant 72, albedo 0.81) heats a
/// disc of each of the three surfaces there, and the caches on one see
/// the others' at grazing angles. Projected as radiance into four SH
/// bands, whose cosine lobe is 0.09 at the horizon where the true one is
/// 0, that light came back too bright: 8x8 tiles 6.9 % with the links,
/// 12.0 % with the samples so projected, 4.1 % with each group's SH
/// scaled to the cache's exact irradiance (5.0 % once the links were
/// normalised as well, 1.029x). Bound: the 8 % for rooms (the
/// reference's own tile noise is 3.6 %).
#[test]
fn caches_see_a_shaded_lamp_through_explicit_samples() {
    assert_shaded_lamp_lights_the_unlit_room(13);
    let corner =
        relight_render::robustness::VariantCase::default_family(72).expect("the variant loads");
    let technique = pic(&corner.context, &[("preset", "high")]);
    let (measured, _) = corner.measure_as_the_study_does(technique.as_ref());
    assert!(measured.image_tiles < 0.08, "{}", measured.image_tiles);
}

/// Shading between the lightmap's receivers follows their light: no point
/// the camera sees falls under half the dimmest receiver around it. Where
/// a receiver drops a cache it cannot see, shading used to add that
/// receiver's change to the per-point cache lookup; beside the corner of
/// two walls in generated variant 37 (default family; a wall plane that
/// runs on through the room's side wall into the lamp-lit room, under
/// texels of about 0.22 m) the cache texel across the corner lit the
/// lookup 0.43 at the corner and 0.09 a texel on, the corner's change of
/// -0.34 was blended onto the dim side, and a strip of wall shaded black.
/// Half is far under what bilinear blending of lookups can take away
/// between receivers, and far over the black strip's zero.
#[test]
fn shading_between_receivers_follows_their_light() {
    let case =
        relight_render::robustness::VariantCase::default_family(37).expect("the variant loads");
    let context = &case.context;
    let technique = pic(context, &[("preset", "high")]);
    let values = technique.receiver_irradiance().expect("PIC has receivers");
    let shown = context.atlas.dilated_receiver_of_texel();
    let camera = relight_trace::path::CameraRays::new(&context.scene.camera);
    let mesh = &context.scene.mesh;
    let (mut seen, mut dark) = (0usize, Vec::new());
    for y in 0..camera.height {
        for x in 0..camera.width {
            let ray = camera.ray(x, y, glam::Vec2::splat(0.5));
            let Some(hit) = relight_render::render::visible_hit(context, &ray) else {
                continue;
            };
            let normal = mesh.geometric_normal(hit.triangle as usize);
            if normal.dot(ray.direction) >= 0.0 {
                continue;
            }
            let around = context
                .atlas
                .bilinear_texels(hit.triangle, hit.barycentric)
                .into_iter()
                .filter(|&(texel, weight)| weight > 0.0 && shown[texel] != u32::MAX)
                .map(|(texel, _)| luminance(values[shown[texel] as usize]))
                .fold(f32::INFINITY, f32::min);
            if !around.is_finite() {
                continue;
            }
            seen += 1;
            let point = SurfacePoint {
                position: ray.origin + ray.direction * hit.t,
                normal,
                triangle: hit.triangle,
                barycentric: hit.barycentric,
            };
            let shaded = luminance(technique.indirect_irradiance(&point));
            if shaded < 0.5 * around {
                dark.push(([x, y], shaded, around));
            }
        }
    }
    let examples = &dark[..dark.len().min(8)];
    println!(
        "{} of {seen} points under half the dimmest receiver around them: {examples:?}",
        dark.len()
    );
    let pixels = camera.width as usize * camera.height as usize;
    assert!(seen > pixels / 2, "{seen} of {pixels}");
    assert!(dark.is_empty(), "{} points, e.g. {examples:?}", dark.len());
}
