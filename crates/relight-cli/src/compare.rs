//! `relight compare` and `relight demo`: every technique against the path
//! tracer on the same receivers and the same camera view.

use crate::progress::Bars;
use crate::techniques;
use anyhow::{bail, Context, Result};
use relight_core::Rgb;
use relight_render::convergence::TILE;
use relight_render::metrics::{error_image, error_norms, relative_noise, tile_means, ErrorNorms};
use relight_render::render::{render_reference, render_with_technique};
use relight_technique::{reference_receiver_irradiance, Frame, SceneContext};
use relight_trace::path::PathSettings;
use std::collections::BTreeMap;
use std::fmt::Write as _;
use std::path::{Path, PathBuf};
use std::time::Instant;

#[derive(clap::Args, Clone, Debug)]
pub struct CompareSettings {
    /// Primary rays per pixel for technique images.
    #[arg(long, default_value_t = 4, value_parser = clap::value_parser!(u32).range(1..))]
    pub spp: u32,
    /// Paths per pixel for the reference image.
    #[arg(long, default_value_t = 256, value_parser = clap::value_parser!(u32).range(1..))]
    pub reference_spp: u32,
    /// Paths per receiver for the reference lightmap.
    #[arg(long, default_value_t = 4096, value_parser = clap::value_parser!(u32).range(1..))]
    pub reference_samples: u32,
    /// Indirect bounces of the reference: 0 = direct only.
    #[arg(long, default_value_t = 64)]
    pub max_bounces: u32,
    #[arg(long, default_value_t = 1)]
    pub seed: u64,
    /// Update runs timed per technique (median reported).
    #[arg(long, default_value_t = 5, value_parser = clap::value_parser!(u32).range(1..))]
    pub timing_frames: u32,
    /// Technique parameter, repeatable: --set TECHNIQUE.key=value (e.g. prm.top_k=8).
    #[arg(long = "set", value_name = "TECHNIQUE.KEY=VALUE")]
    pub set: Vec<String>,
}

struct Reference {
    lightmap: relight_technique::ReferenceLightmap,
    renders: relight_render::render::Renders,
    lightmap_seconds: f64,
    image_seconds: f64,
}

struct Row {
    technique: String,
    /// Indirect bounces of the reference this row is measured against.
    bounces: u32,
    lightmap: ErrorNorms,
    image: ErrorNorms,
    image_tiles: f64,
    update_ms: f64,
    memory_bytes: usize,
}

/// Compares `names` against the reference on one scene; writes images and
/// `report.md` into `output`; returns the Markdown table.
pub fn run(
    context: &std::sync::Arc<SceneContext>,
    scene_path: &Path,
    names: &[String],
    settings: &CompareSettings,
    output: &Path,
    quiet: bool,
) -> Result<String> {
    std::fs::create_dir_all(output)
        .with_context(|| format!("{}: cannot create output folder", output.display()))?;
    let kinds = names
        .iter()
        .map(|name| techniques::find(name.trim()))
        .collect::<Result<Vec<_>>>()?;
    for pair in &settings.set {
        let known = pair
            .split_once('.')
            .is_some_and(|(name, _)| kinds.iter().any(|kind| kind.name() == name));
        if !known {
            bail!("--set {pair}: name a compared technique, as in --set prm.top_k=8");
        }
    }
    if kinds.iter().any(|kind| kind.name() == "reference") {
        bail!("--techniques: 'reference' is what the others are compared with; leave it out");
    }
    let bars = Bars::new(quiet);
    let lights = context.scene.lights.clone();
    let path_settings = PathSettings {
        max_bounces: settings.max_bounces,
        seed: settings.seed,
        ..PathSettings::default()
    };

    // The path tracer with all bounces, and limited to as many as a
    // technique computes (LightSkin's one) for that technique's row.
    let mut references: BTreeMap<u32, Reference> = BTreeMap::new();
    let trace = |bounces: u32| -> Reference {
        let path_settings = PathSettings {
            max_bounces: bounces,
            ..path_settings
        };
        let start = Instant::now();
        let lightmap = reference_receiver_irradiance(
            context,
            &lights,
            path_settings,
            settings.reference_samples,
            &bars,
        );
        let lightmap_seconds = start.elapsed().as_secs_f64();
        let start = Instant::now();
        let renders = render_reference(
            context,
            &lights,
            path_settings,
            settings.reference_spp,
            &bars,
        );
        Reference {
            lightmap,
            renders,
            lightmap_seconds,
            image_seconds: start.elapsed().as_secs_f64(),
        }
    };
    let all_bounces = trace(settings.max_bounces);
    let indirect_exposure = all_bounces.renders.indirect.auto_exposure();
    let full_exposure = all_bounces.renders.full.auto_exposure();
    let written = &all_bounces.renders;
    written.indirect.write(
        &output.join("reference-indirect.png"),
        Some(indirect_exposure),
    )?;
    written
        .indirect
        .write(&output.join("reference-indirect.exr"), None)?;
    written
        .full
        .write(&output.join("reference-full.png"), Some(full_exposure))?;
    written
        .full
        .write(&output.join("reference-full.exr"), None)?;
    references.insert(settings.max_bounces, all_bounces);

    let mut rows = Vec::new();
    for kind in kinds {
        let prefix = format!("{}.", kind.name());
        let options = crate::TechniqueOptions {
            technique: kind.name().to_string(),
            bake: None,
            set: settings
                .set
                .iter()
                .filter_map(|pair| pair.strip_prefix(&prefix).map(str::to_string))
                .collect(),
            preset: None,
        };
        let mut technique = crate::create_technique(context, &options, quiet)?;
        let mut update_ms = Vec::new();
        for index in 0..settings.timing_frames.max(1) {
            // The same lights every run: timed as full updates, not as
            // the skipped repeats an engine gets.
            technique.forget_last_frame();
            technique.update(&Frame {
                lights: &lights,
                index: index as u64,
                camera: None,
                moving_mesh_poses: None,
            })?;
            update_ms.push(technique.timings().total().as_secs_f64() * 1e3);
        }
        update_ms.sort_by(|a, b| a.total_cmp(b));
        let bounces = technique.reference_bounces(settings.max_bounces);
        let reference = references.entry(bounces).or_insert_with(|| trace(bounces));
        let receivers = technique.receiver_irradiance().map(<[Rgb]>::to_vec);
        let lightmap = match receivers {
            Some(values) if values.len() == reference.lightmap.mean.len() => {
                error_norms(&values, &reference.lightmap.mean)
            }
            _ => ErrorNorms {
                relative_rmse: f64::NAN,
                mean_relative_error: f64::NAN,
            },
        };
        let renders = render_with_technique(
            context,
            &lights,
            technique.as_ref(),
            settings.spp,
            settings.seed,
            &bars,
        );
        let reference_image = &reference.renders.indirect;
        let image = error_norms(&renders.indirect.pixels, &reference_image.pixels);
        let image_tiles = error_norms(
            &tile_means(&renders.indirect, TILE),
            &tile_means(reference_image, TILE),
        );
        let name = kind.name();
        renders.indirect.write(
            &output.join(format!("{name}-indirect.png")),
            Some(indirect_exposure),
        )?;
        renders
            .indirect
            .write(&output.join(format!("{name}-indirect.exr")), None)?;
        renders.full.write(
            &output.join(format!("{name}-full.png")),
            Some(full_exposure),
        )?;
        error_image(&renders.indirect, reference_image, 0.5)
            .write(&output.join(format!("{name}-error.png")), Some(1.0))?;
        rows.push(Row {
            technique: name.to_string(),
            bounces,
            lightmap,
            image,
            image_tiles: image_tiles.relative_rmse,
            update_ms: update_ms[update_ms.len() / 2],
            memory_bytes: technique.memory().iter().map(|entry| entry.bytes).sum(),
        });
    }

    let mut table = String::new();
    writeln!(table, "### {}\n", scene_path.display())?;
    for (bounces, reference) in &references {
        let lightmap_noise =
            relative_noise(&reference.lightmap.mean, &reference.lightmap.standard_error);
        let image_noise = relative_noise(
            &reference.renders.indirect.pixels,
            &reference.renders.indirect_standard_error.pixels,
        );
        writeln!(
            table,
            "Reference at {bounces} bounces: {} paths per receiver ({:.1} s, its own noise {:.1} % relRMSE), {} paths per pixel ({:.1} s, noise {:.1} %).",
            settings.reference_samples,
            reference.lightmap_seconds,
            lightmap_noise * 100.0,
            settings.reference_spp,
            reference.image_seconds,
            image_noise * 100.0,
        )?;
    }
    writeln!(
        table,
        "\n{} receivers. Each technique is measured against the path tracer with as many bounces as it computes (LightSkin: one).\n",
        context.atlas.receivers.len()
    )?;
    writeln!(table, "| technique | bounces | lightmap relRMSE | lightmap MRE | image relRMSE | image 8x8 tiles | image MRE | update ms | memory |")?;
    writeln!(table, "|---|---:|---:|---:|---:|---:|---:|---:|---:|")?;
    for row in &rows {
        writeln!(
            table,
            "| {} | {} | {:.1} % | {:.1} % | {:.1} % | {:.1} % | {:.1} % | {:.2} | {} |",
            row.technique,
            row.bounces,
            row.lightmap.relative_rmse * 100.0,
            row.lightmap.mean_relative_error * 100.0,
            row.image.relative_rmse * 100.0,
            row.image_tiles * 100.0,
            row.image.mean_relative_error * 100.0,
            row.update_ms,
            human_bytes(row.memory_bytes)
        )?;
    }
    let mut report = table.clone();
    writeln!(report, "\n| reference indirect | reference full |\n|---|---|\n| ![](reference-indirect.png) | ![](reference-full.png) |\n")?;
    for row in &rows {
        let name = &row.technique;
        writeln!(report, "| {name} indirect | {name} error (full scale 50 % of mean) | {name} full |\n|---|---|---|\n| ![]({name}-indirect.png) | ![]({name}-error.png) | ![]({name}-full.png) |\n")?;
    }
    std::fs::write(output.join("report.md"), report)
        .with_context(|| format!("{}: cannot write report.md", output.display()))?;
    Ok(table)
}

fn human_bytes(bytes: usize) -> String {
    if bytes >= 1 << 20 {
        format!("{:.1} MiB", bytes as f64 / (1u64 << 20) as f64)
    } else {
        format!("{:.1} KiB", bytes as f64 / 1024.0)
    }
}

/// Finds the shipped scenes: `--scenes`, else ./scenes, else the repository's
/// scenes folder next to the executable's build tree.
fn scenes_folder(explicit: Option<PathBuf>) -> Result<PathBuf> {
    if let Some(folder) = explicit {
        return Ok(folder);
    }
    let local = PathBuf::from("scenes");
    if local.join("cornell-box").is_dir() {
        return Ok(local);
    }
    if let Ok(executable) = std::env::current_exe() {
        for ancestor in executable.ancestors() {
            let candidate = ancestor.join("scenes");
            if candidate.join("cornell-box").is_dir() {
                return Ok(candidate);
            }
        }
    }
    bail!("no shipped scenes found: run from the repository root or pass --scenes DIR")
}

pub fn demo(
    scenes: Option<PathBuf>,
    settings: &CompareSettings,
    output: &Path,
    quiet: bool,
) -> Result<()> {
    let folder = scenes_folder(scenes)?;
    let mut scene_files: Vec<PathBuf> = std::fs::read_dir(&folder)
        .with_context(|| format!("{}: cannot list scenes", folder.display()))?
        .filter_map(|entry| entry.ok().map(|entry| entry.path().join("scene.toml")))
        .filter(|path| path.is_file())
        .collect();
    scene_files.sort();
    if scene_files.is_empty() {
        bail!("{}: no scene folders with scene.toml", folder.display());
    }
    let names: Vec<String> = techniques::kinds()
        .iter()
        .map(|kind| kind.name().to_string())
        .filter(|name| name != "reference")
        .collect();
    let options = crate::SceneOptions {
        lightmap_resolution: None,
        texel_size: None,
        area_samples: 16,
    };
    let start = Instant::now();
    let mut summary = String::from("# relight demo\n\nEvery technique against the path-traced reference; see each scene's report.md for images.\n\n");
    for scene in &scene_files {
        let name = scene
            .parent()
            .and_then(Path::file_name)
            .map(|n| n.to_string_lossy().into_owned())
            .unwrap_or_default();
        if !quiet {
            eprintln!("== {name}");
        }
        let context = crate::load_context(scene, &options, quiet)?;
        let table = run(
            &context,
            scene,
            &names,
            settings,
            &output.join(&name),
            quiet,
        )?;
        say!("{table}");
        summary.push_str(&table);
        summary.push('\n');
    }
    writeln!(
        summary,
        "Total demo time: {:.1} s",
        start.elapsed().as_secs_f64()
    )?;
    std::fs::write(output.join("README.md"), &summary)
        .with_context(|| format!("{}: cannot write", output.display()))?;
    say!(
        "demo finished in {:.1} s; reports in {}",
        start.elapsed().as_secs_f64(),
        output.display()
    );
    Ok(())
}
