//! `relight compare` and `relight demo`: every technique against the path
//! tracer on the same receivers and the same camera view.

use crate::progress::Bars;
use crate::techniques;
use anyhow::{bail, Context, Result};
use relight_core::Rgb;
use relight_render::metrics::{error_image, error_norms, relative_noise, ErrorNorms};
use relight_render::render::{render_reference, render_with_technique};
use relight_technique::{reference_receiver_irradiance, Frame, SceneContext};
use relight_trace::path::PathSettings;
use std::fmt::Write as _;
use std::path::{Path, PathBuf};
use std::time::Instant;

#[derive(clap::Args, Clone, Debug)]
pub struct CompareSettings {
    /// Primary rays per pixel for technique images.
    #[arg(long, default_value_t = 4)]
    pub spp: u32,
    /// Paths per pixel for the reference image.
    #[arg(long, default_value_t = 256)]
    pub reference_spp: u32,
    /// Paths per receiver for the reference lightmap.
    #[arg(long, default_value_t = 4096)]
    pub reference_samples: u32,
    /// Indirect bounces of the reference: 0 = direct only.
    #[arg(long, default_value_t = 64)]
    pub max_bounces: u32,
    #[arg(long, default_value_t = 1)]
    pub seed: u64,
    /// Update runs timed per technique (median reported).
    #[arg(long, default_value_t = 5)]
    pub timing_frames: u32,
    /// Technique parameter, repeatable: --set TECHNIQUE.key=value (e.g. prm.top_k=8).
    #[arg(long = "set", value_name = "TECHNIQUE.KEY=VALUE")]
    pub set: Vec<String>,
}

struct Row {
    technique: String,
    lightmap: ErrorNorms,
    image: ErrorNorms,
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

    let start = Instant::now();
    let reference_lightmap = reference_receiver_irradiance(
        context,
        &lights,
        path_settings,
        settings.reference_samples,
        &bars,
    );
    let reference_lightmap_seconds = start.elapsed().as_secs_f64();
    let start = Instant::now();
    let reference = render_reference(
        context,
        &lights,
        path_settings,
        settings.reference_spp,
        &bars,
    );
    let reference_image_seconds = start.elapsed().as_secs_f64();
    let indirect_exposure = reference.indirect.auto_exposure();
    let full_exposure = reference.full.auto_exposure();
    reference.indirect.write(
        &output.join("reference-indirect.png"),
        Some(indirect_exposure),
    )?;
    reference
        .indirect
        .write(&output.join("reference-indirect.exr"), None)?;
    reference
        .full
        .write(&output.join("reference-full.png"), Some(full_exposure))?;
    reference
        .full
        .write(&output.join("reference-full.exr"), None)?;
    let lightmap_noise =
        relative_noise(&reference_lightmap.mean, &reference_lightmap.standard_error);
    let image_noise = relative_noise(
        &reference.indirect.pixels,
        &reference.indirect_standard_error.pixels,
    );

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
            technique.update(&Frame {
                lights: &lights,
                index: index as u64,
            })?;
            update_ms.push(technique.timings().total().as_secs_f64() * 1e3);
        }
        update_ms.sort_by(|a, b| a.total_cmp(b));
        let receivers = technique.receiver_irradiance().map(<[Rgb]>::to_vec);
        let lightmap = match receivers {
            Some(values) if values.len() == reference_lightmap.mean.len() => {
                error_norms(&values, &reference_lightmap.mean)
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
        let image = error_norms(&renders.indirect.pixels, &reference.indirect.pixels);
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
        error_image(&renders.indirect, &reference.indirect, 0.5)
            .write(&output.join(format!("{name}-error.png")), Some(1.0))?;
        rows.push(Row {
            technique: name.to_string(),
            lightmap,
            image,
            update_ms: update_ms[update_ms.len() / 2],
            memory_bytes: technique.memory().iter().map(|entry| entry.bytes).sum(),
        });
    }

    let mut table = String::new();
    writeln!(table, "### {}\n", scene_path.display())?;
    writeln!(
        table,
        "{} receivers; reference: {} paths per receiver ({:.1} s, its own noise {:.1} % relRMSE), {} paths per pixel ({:.1} s, noise {:.1} %), max bounces {}.\n",
        context.atlas.receivers.len(),
        settings.reference_samples,
        reference_lightmap_seconds,
        lightmap_noise * 100.0,
        settings.reference_spp,
        reference_image_seconds,
        image_noise * 100.0,
        settings.max_bounces
    )?;
    writeln!(table, "| technique | lightmap relRMSE | lightmap MRE | image relRMSE | image MRE | update ms | memory |")?;
    writeln!(table, "|---|---:|---:|---:|---:|---:|---:|")?;
    for row in &rows {
        writeln!(
            table,
            "| {} | {:.1} % | {:.1} % | {:.1} % | {:.1} % | {:.2} | {} |",
            row.technique,
            row.lightmap.relative_rmse * 100.0,
            row.lightmap.mean_relative_error * 100.0,
            row.image.relative_rmse * 100.0,
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
