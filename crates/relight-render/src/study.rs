//! Helpers for parameter studies: a path-traced reference lightmap cached
//! on disk (it costs far more than the bakes being compared) and
//! `key=value,key=value` parameter lists.

use relight_core::Rgb;
use relight_scene::atlas::TexelDensity;
use relight_technique::{reference_receiver_irradiance, ContextSettings, NoProgress, SceneContext};
use relight_trace::path::PathSettings;
use std::sync::Arc;

/// The context of a study: `scene_path` with a lightmap of `resolution`
/// texels on its longer side (0 = automatic). Panics with the reason, as
/// studies are run by hand.
pub fn study_context(scene_path: &str, resolution: u32) -> Arc<SceneContext> {
    let scene = relight_scene::load_scene(std::path::Path::new(scene_path))
        .unwrap_or_else(|error| panic!("{scene_path}: {error}"));
    let settings = ContextSettings {
        lightmap: TexelDensity::from_resolution(Some(resolution).filter(|&r| r != 0)),
        ..ContextSettings::default()
    };
    Arc::new(SceneContext::new(scene, settings).expect("the scene's lightmap builds"))
}

/// The reference indirect lightmap of `context` under its scene's lights
/// with `samples` paths per receiver, and its own relative noise; cached in
/// the temporary folder under a key of everything that changes it (see
/// [`crate::convergence::ReferenceSet::key`]): two scene files over one
/// mesh with different lights never share a reference.
pub fn cached_reference_lightmap(context: &SceneContext, samples: u32) -> (Vec<Rgb>, f64) {
    let key = format!(
        "{:016x}",
        crate::convergence::ReferenceSet::key(context, PathSettings::default(), samples, 0)
    );
    let file = std::env::temp_dir().join(format!("relight-study-{key}.f32"));
    let count = context.atlas.receivers.len();
    if let Ok(bytes) = std::fs::read(&file) {
        if bytes.len() == (count * 3 + 1) * 4 {
            let values: Vec<f32> = bytes
                .chunks_exact(4)
                .map(|b| f32::from_le_bytes(b.try_into().expect("4 bytes")))
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
    let noise = crate::metrics::relative_noise(&reference.mean, &reference.standard_error);
    let mut bytes = Vec::with_capacity((count * 3 + 1) * 4);
    for value in &reference.mean {
        for component in value.to_array() {
            bytes.extend_from_slice(&component.to_le_bytes());
        }
    }
    bytes.extend_from_slice(&(noise as f32).to_le_bytes());
    // A cache that cannot be written only costs the next run its time.
    let _ = std::fs::write(&file, bytes);
    (reference.mean, noise)
}

/// `"a=1,b=[[1,2],[3,4]]"` as key-value pairs: commas inside brackets
/// belong to the value; parts without `=` are ignored.
pub fn parse_pairs(list: &str) -> Vec<(String, String)> {
    split_top_level(list)
        .into_iter()
        .filter_map(|part| part.split_once('='))
        .map(|(key, value)| (key.trim().to_string(), value.trim().to_string()))
        .collect()
}

/// `list` split at the commas outside brackets: `"1,[2,3]"` is `1` and
/// `[2,3]`.
pub fn split_top_level(list: &str) -> Vec<&str> {
    let mut parts = Vec::new();
    let (mut depth, mut start) = (0i32, 0usize);
    for (index, character) in list.char_indices() {
        match character {
            '[' => depth += 1,
            ']' => depth -= 1,
            ',' if depth == 0 => {
                parts.push(&list[start..index]);
                start = index + 1;
            }
            _ => {}
        }
    }
    parts.push(&list[start..]);
    parts
}

/// What a study reports of one parameter set beyond the shared line: the
/// context, the bake bytes and the technique's receiver irradiance.
pub type StudyDetail<'a> = &'a dyn Fn(&SceneContext, &[u8], &[Rgb], &[Rgb]);

/// The command line of a parameter study, `SCENE.toml RESOLUTION
/// REFERENCE_SAMPLES PARAMS...`: for each `key=value,...` set, bakes `kind`
/// (once per distinct set of `bake_parameters`), updates it under the
/// scene's lights and prints its lightmap relRMSE against the cached
/// reference and against the first set, then whatever `detail` adds
/// (given the context, the bake, the values and the reference).
pub fn run_study(
    kind: &dyn relight_technique::TechniqueKind,
    bake_parameters: &[&str],
    detail: StudyDetail,
) {
    use relight_technique::Frame;
    let args: Vec<String> = std::env::args().skip(1).collect();
    let [scene_path, resolution, samples, sets @ ..] = args.as_slice() else {
        eprintln!("usage: study SCENE.toml RESOLUTION REFERENCE_SAMPLES PARAMS...");
        std::process::exit(2);
    };
    let resolution: u32 = resolution.parse().expect("RESOLUTION is a number");
    let samples: u32 = samples.parse().expect("REFERENCE_SAMPLES is a number");
    let context = study_context(scene_path, resolution);
    let (reference, noise) = cached_reference_lightmap(&context, samples);
    println!(
        "{scene_path}: {} receivers, reference {samples} paths, noise {:.2} %",
        reference.len(),
        noise * 100.0
    );
    let lights = context.scene.lights.clone();
    // With RELIGHT_STUDY_WORST: the count, and where receivers stood before
    // relocation (built once for all parameter sets).
    let worst: Option<(usize, Vec<glam::Vec3>)> = std::env::var("RELIGHT_STUDY_WORST")
        .ok()
        .and_then(|count| count.parse().ok())
        .map(|count| {
            let raw = relight_technique::chart_atlas(
                &context.scene,
                &context.bvh,
                context.settings.lightmap,
            )
            .map(|atlas| atlas.receivers.positions)
            .unwrap_or_default();
            (count, raw)
        });
    let mut first: Option<Vec<Rgb>> = None;
    // (bake parameters, bake bytes, seconds it took), one per distinct set.
    type Baked = (Vec<(String, String)>, Vec<u8>, f64);
    let mut bakes: Vec<Baked> = Vec::new();
    for set in sets {
        let params = parse_pairs(set);
        let bake_params: Vec<(String, String)> = params
            .iter()
            .filter(|(key, _)| bake_parameters.contains(&key.as_str()))
            .cloned()
            .collect();
        let index = match bakes.iter().position(|(key, _, _)| *key == bake_params) {
            Some(index) => index,
            None if !kind.needs_bake() => {
                bakes.push((bake_params, Vec::new(), 0.0));
                bakes.len() - 1
            }
            None => {
                let started = std::time::Instant::now();
                let bake = kind
                    .bake(&context, &bake_params, &NoProgress)
                    .expect("bake");
                bakes.push((bake_params, bake, started.elapsed().as_secs_f64()));
                bakes.len() - 1
            }
        };
        let (_, bake, bake_seconds) = &bakes[index];
        let payload = kind.needs_bake().then_some(bake.as_slice());
        let mut technique = kind
            .create(context.clone(), payload, &params, &NoProgress)
            .expect("create");
        technique
            .update(&Frame {
                lights: &lights,
                index: 0,
                camera: None,
                moving_mesh_poses: None,
            })
            .expect("update");
        let values = technique
            .receiver_irradiance()
            .expect("the technique keeps a lightmap");
        let norms = crate::metrics::error_norms(values, &reference);
        // Against the first parameter set too: that isolates what a change
        // costs from the error both share.
        let against_first = first
            .as_ref()
            .map(|first| crate::metrics::error_norms(values, first).relative_rmse * 100.0)
            .unwrap_or(0.0);
        println!(
            "{set:40} relRMSE {:6.2} %  MRE {:6.2} %  vs first {against_first:6.2} %  (bake {bake_seconds:.1} s, {:.1} MiB)",
            norms.relative_rmse * 100.0,
            norms.mean_relative_error * 100.0,
            bake.len() as f64 / 1048576.0
        );
        if let Some((count, unmoved)) = &worst {
            report_worst(&context, unmoved, values, &reference, *count);
        }
        detail(&context, bake, values, &reference);
        if first.is_none() {
            first = Some(values.to_vec());
        }
    }
}

/// One line about receiver `index`: where it stands, its normal, and its
/// luminance against the reference's.
pub fn print_receiver(context: &SceneContext, index: usize, values: &[Rgb], reference: &[Rgb]) {
    use relight_core::luminance;
    let receivers = &context.atlas.receivers;
    println!(
        "    {:>6} at {:?} normal {:?}: {:.4} vs {:.4}",
        index,
        receivers.positions[index],
        receivers.normals[index],
        luminance(values[index]),
        luminance(reference[index])
    );
}

/// Prints the `count` receivers with the largest squared luminance error,
/// and the error without the receivers the reference sees as dark
/// (enclosed texels), which tells a technique's error from disagreement
/// over texels nobody sees, and the error at receivers that relocation
/// moved away from `unmoved` (their texel-centre positions) against the
/// rest. Studies print it when `RELIGHT_STUDY_WORST` is set to a count.
pub fn report_worst(
    context: &SceneContext,
    unmoved: &[glam::Vec3],
    values: &[Rgb],
    reference: &[Rgb],
    count: usize,
) {
    use relight_core::luminance;
    let mean =
        reference.iter().map(|v| luminance(*v) as f64).sum::<f64>() / reference.len().max(1) as f64;
    let (lit, dark): (Vec<usize>, Vec<usize>) =
        (0..values.len()).partition(|&i| luminance(reference[i]) as f64 >= 1e-4 * mean);
    let pick = |list: &[usize], from: &[Rgb]| list.iter().map(|&i| from[i]).collect::<Vec<_>>();
    println!(
        "    {} receivers dark in the reference; relRMSE over the rest {:.2} %",
        dark.len(),
        crate::metrics::error_norms(&pick(&lit, values), &pick(&lit, reference)).relative_rmse
            * 100.0
    );
    if unmoved.len() == values.len() {
        let (moved, kept): (Vec<usize>, Vec<usize>) =
            (0..values.len()).partition(|&i| unmoved[i] != context.atlas.receivers.positions[i]);
        let error_of = |list: &[usize]| {
            crate::metrics::error_norms(&pick(list, values), &pick(list, reference)).relative_rmse
                * 100.0
        };
        println!(
            "    {} receivers relocated: relRMSE {:.2} % there, {:.2} % over the rest",
            moved.len(),
            error_of(&moved),
            error_of(&kept)
        );
    }
    let error = |i: usize| (luminance(values[i]) - luminance(reference[i])).powi(2);
    let mut order: Vec<usize> = (0..values.len()).collect();
    order.sort_by(|&a, &b| error(b).total_cmp(&error(a)));
    for &i in order.iter().take(count) {
        print_receiver(context, i, values, reference);
    }
}

/// A technique's indirect light against the path tracer on one scene.
#[derive(Clone, Copy, Debug)]
pub struct IndirectErrors {
    /// relRMSE of the receivers' indirect irradiance.
    pub lightmap: f64,
    /// The reference lightmap's own relative noise.
    pub lightmap_noise: f64,
    /// relRMSE of the indirect-only image (4 primary rays per pixel).
    pub image: f64,
    /// The reference image's own relative noise.
    pub image_noise: f64,
}

/// `technique`, already updated under the scene's lights, against path
/// tracing with `settings`: `reference_samples` paths per receiver and
/// `reference_spp` per pixel of the context's camera. The references cost
/// far more than the technique, and tests measure several settings on one
/// scene, and several techniques' test binaries the same scene: each is
/// traced once per process and kept in
/// [`crate::convergence::TEST_REFERENCE_FOLDER`] where that is set.
pub fn indirect_errors(
    context: &SceneContext,
    technique: &dyn relight_technique::Technique,
    settings: PathSettings,
    reference_samples: u32,
    reference_spp: u32,
) -> IndirectErrors {
    use crate::convergence::{ReferenceSet, SpacePoints, TEST_REFERENCE_FOLDER};
    use crate::metrics::{error_norms, relative_noise};
    use crate::render::render_with_technique;
    static REFERENCES: relight_technique::robustness::OncePerProcess<u64, ReferenceSet> =
        relight_technique::robustness::OncePerProcess::new();
    let key = ReferenceSet::key(context, settings, reference_samples, reference_spp);
    let reference = REFERENCES.get_or_compute(key, || {
        let folder = std::env::var_os(TEST_REFERENCE_FOLDER).map(std::path::PathBuf::from);
        let no_points = SpacePoints::default();
        ReferenceSet::cached(
            context,
            &no_points,
            settings,
            reference_samples,
            reference_spp,
            folder.as_deref(),
            &NoProgress,
        )
    });
    let receivers = technique
        .receiver_irradiance()
        .expect("the technique keeps a lightmap");
    let lights = &context.scene.lights;
    let image = render_with_technique(context, lights, technique, 4, 1, &NoProgress);
    IndirectErrors {
        lightmap: error_norms(receivers, &reference.lightmap).relative_rmse,
        lightmap_noise: relative_noise(&reference.lightmap, &reference.lightmap_error),
        image: error_norms(&image.indirect.pixels, &reference.image.pixels).relative_rmse,
        image_noise: relative_noise(&reference.image.pixels, &reference.image_error.pixels),
    }
}
