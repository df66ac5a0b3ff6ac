//! `relight converge`: a technique's error against the path tracer as its
//! parameters grow. A technique whose error does not fall toward the
//! reference's own noise as its quality settings rise has a bias; this is
//! the command that shows it.
//!
//! Data flow: the reference (per bounce count the swept settings need) is
//! traced once and cached under a key of everything that changes it; each
//! setting of the sweep's Cartesian product is baked (once for settings
//! that differ only in run-time parameters), updated under the
//! scene's lights, rendered and measured (see
//! [`relight_render::convergence`]).

use crate::progress::Bars;
use crate::techniques;
use anyhow::{bail, Context, Result};
use relight_render::convergence::{Measurement, ReceiverClass, ReferenceSet, Split, TILE};
use relight_render::metrics::tile_ratio_image;
use relight_render::study::split_top_level;
use relight_technique::{Frame, Progress, SceneContext, Technique, TechniqueKind};
use relight_trace::path::PathSettings;
use std::collections::BTreeMap;
use std::fmt::Write as _;
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::time::Instant;

/// The technique's image and the path-traced reference it is measured
/// against: what `relight converge` and `relight robustness` share.
#[derive(clap::Args, Clone, Debug)]
pub struct MeasureSettings {
    /// Primary rays per pixel for the technique's image.
    #[arg(long, default_value_t = 4, value_parser = clap::value_parser!(u32).range(1..))]
    pub spp: u32,
    /// Paths per pixel for the reference image.
    #[arg(long, default_value_t = relight_render::robustness::STUDY_PATHS, value_parser = clap::value_parser!(u32).range(1..))]
    pub reference_spp: u32,
    /// Paths per receiver (and point in space) for the reference.
    #[arg(long, default_value_t = relight_render::robustness::STUDY_PATHS, value_parser = clap::value_parser!(u32).range(1..))]
    pub reference_samples: u32,
    /// Indirect bounces of the reference (a technique that computes fewer
    /// is measured against a reference limited to as many).
    #[arg(long, default_value_t = 64)]
    pub max_bounces: u32,
    /// Folder for cached references (default: the system's temporary folder).
    #[arg(long)]
    pub cache: Option<PathBuf>,
}

impl MeasureSettings {
    /// The reference cache's folder, created if it is not there yet.
    pub fn cache_folder(&self) -> Result<PathBuf> {
        let cache = self.cache.clone().unwrap_or_else(std::env::temp_dir);
        std::fs::create_dir_all(&cache)
            .with_context(|| format!("{}: cannot create the reference cache", cache.display()))?;
        Ok(cache)
    }

    /// The path-traced reference of `context` at `bounces` indirect bounces
    /// with path seed `seed`, read from `cache` or traced and written there.
    pub fn reference(
        &self,
        context: &SceneContext,
        split: &Split,
        bounces: u32,
        seed: u64,
        cache: &Path,
        progress: &dyn Progress,
    ) -> ReferenceSet {
        ReferenceSet::cached(
            context,
            &split.space,
            PathSettings {
                max_bounces: bounces,
                seed,
                ..PathSettings::default()
            },
            self.reference_samples,
            self.reference_spp,
            Some(cache),
            progress,
        )
    }
}

/// The technique a study (`command`) measures: any but the reference,
/// baked by the study itself for every `unit`.
pub(crate) fn studied_kind(
    technique: &crate::TechniqueOptions,
    command: &str,
    unit: &str,
) -> Result<&'static dyn TechniqueKind> {
    let kind = techniques::find(&technique.technique)?;
    if kind.name() == "reference" {
        bail!("--technique reference is what {command} compares with; name another technique");
    }
    if technique.bake.is_some() {
        bail!("{command} bakes every {unit} itself; drop --bake");
    }
    Ok(kind)
}

/// `kind` created on `context` from `payload` and updated once under the
/// scene's lights, with that update's time in milliseconds; `what` names
/// the setting or variant in errors.
pub(crate) fn updated_technique(
    kind: &dyn TechniqueKind,
    context: &Arc<SceneContext>,
    payload: Option<&[u8]>,
    pairs: &[(String, String)],
    progress: &dyn Progress,
    what: &str,
) -> Result<(Box<dyn Technique>, f64)> {
    let mut instance = kind
        .create(context.clone(), payload, pairs, progress)
        .with_context(|| format!("creating {} {what}", kind.name()))?;
    instance.update(&Frame {
        lights: &context.scene.lights,
        index: 0,
        camera: None,
        moving_mesh_poses: None,
    })?;
    let update_ms = instance.timings().total().as_secs_f64() * 1e3;
    Ok((instance, update_ms))
}

#[derive(clap::Args, Clone, Debug)]
pub struct ConvergeSettings {
    /// Parameter to sweep, repeatable: --sweep key=v1,v2,... (every
    /// combination of the sweeps is measured).
    #[arg(long = "sweep", value_name = "KEY=V1,V2,...")]
    pub sweeps: Vec<String>,
    #[command(flatten)]
    pub measure: MeasureSettings,
    #[arg(long, default_value_t = 1)]
    pub seed: u64,
    /// Write the indirect-only images of the reference and of every setting
    /// here, with a map of each setting's 8x8-tile light ratio (red: too
    /// bright, blue: too dark, full colour at twice or half).
    #[arg(long)]
    pub images: Option<PathBuf>,
    /// Also write the results as JSON.
    #[arg(long)]
    pub json: Option<PathBuf>,
    /// Also write the Markdown report to this file.
    #[arg(long)]
    pub markdown: Option<PathBuf>,
}

/// `key=v1,v2` as the key and its values; brackets keep their commas
/// (`probes=[[0,1,0],[1,1,1]],[[0,0,0]]`).
fn parse_sweep(text: &str) -> Result<(String, Vec<String>)> {
    let (key, values) = text
        .split_once('=')
        .with_context(|| format!("--sweep {text}: expected KEY=V1,V2,..."))?;
    let values: Vec<String> = split_top_level(values)
        .into_iter()
        .map(|value| value.trim().to_string())
        .filter(|value| !value.is_empty())
        .collect();
    if key.trim().is_empty() || values.is_empty() {
        bail!("--sweep {text}: expected KEY=V1,V2,... with at least one value");
    }
    Ok((key.trim().to_string(), values))
}

/// Every combination of the sweeps' values, the last sweep varying fastest.
fn combinations(sweeps: &[(String, Vec<String>)]) -> Vec<Vec<(String, String)>> {
    let mut settings = vec![Vec::new()];
    for (key, values) in sweeps {
        settings = settings
            .into_iter()
            .flat_map(|setting: Vec<(String, String)>| {
                values.iter().map(move |value| {
                    let mut next = setting.clone();
                    next.push((key.clone(), value.clone()));
                    next
                })
            })
            .collect();
    }
    settings
}

/// A row's name: every parameter that is not a default, `--preset` and
/// `--set` included, so that a table read on its own says what ran.
fn setting_label(pairs: &[(String, String)]) -> String {
    if pairs.is_empty() {
        return "defaults".to_string();
    }
    pairs
        .iter()
        .map(|(key, value)| format!("{key}={value}"))
        .collect::<Vec<_>>()
        .join(" ")
}

struct Row {
    setting: String,
    bounces: u32,
    bake_seconds: f64,
    update_ms: f64,
    measurement: Measurement,
}

/// The parameter pairs that decide a bake.
type BakeKey = Vec<(String, String)>;

/// The pairs that decide a bake: the bake parameters' final values, or
/// every pair when the technique names none.
fn bake_key(bake_parameters: &[&str], pairs: &[(String, String)]) -> BakeKey {
    let mut last: BTreeMap<&str, &str> = BTreeMap::new();
    for (key, value) in pairs {
        if bake_parameters.is_empty() || bake_parameters.contains(&key.as_str()) {
            last.insert(key, value);
        }
    }
    last.into_iter()
        .map(|(key, value)| (key.to_string(), value.to_string()))
        .collect()
}

pub fn run(
    context: &Arc<SceneContext>,
    scene_path: &Path,
    technique: &crate::TechniqueOptions,
    settings: &ConvergeSettings,
    quiet: bool,
) -> Result<String> {
    let kind = studied_kind(technique, "converge", "setting")?;
    let sweeps = settings
        .sweeps
        .iter()
        .map(|sweep| parse_sweep(sweep))
        .collect::<Result<Vec<_>>>()?;
    let fixed = technique.pairs()?;
    let bars = Bars::new(quiet);
    let cache = settings.measure.cache_folder()?;
    if let Some(folder) = &settings.images {
        std::fs::create_dir_all(folder)
            .with_context(|| format!("{}: cannot create the images folder", folder.display()))?;
    }
    let split = Split::of(context);
    let visible = &split.visible;
    let mut references: BTreeMap<u32, ReferenceSet> = BTreeMap::new();
    let mut rows = Vec::new();
    // Settings that differ only in run-time parameters share one bake.
    let mut last_bake: Option<(BakeKey, Vec<u8>)> = None;
    for (index, swept) in combinations(&sweeps).into_iter().enumerate() {
        let mut pairs = fixed.clone();
        pairs.extend(swept.iter().cloned());
        let setting = setting_label(&pairs);
        if !quiet {
            eprintln!("== {setting}");
        }
        let start = Instant::now();
        let bake_key = bake_key(kind.bake_parameters(), &pairs);
        let payload = match &last_bake {
            _ if !kind.needs_bake() => None,
            Some((key, payload)) if *key == bake_key => Some(payload.clone()),
            _ => {
                let payload = kind
                    .bake(context, &pairs, &bars)
                    .with_context(|| format!("baking {} with {setting}", kind.name()))?;
                last_bake = Some((bake_key, payload.clone()));
                Some(payload)
            }
        };
        let bake_seconds = start.elapsed().as_secs_f64();
        let (instance, update_ms) = updated_technique(
            kind,
            context,
            payload.as_deref(),
            &pairs,
            &bars,
            &format!("with {setting}"),
        )?;
        let bounces = instance.reference_bounces(settings.measure.max_bounces);
        let reference = references.entry(bounces).or_insert_with(|| {
            settings
                .measure
                .reference(context, &split, bounces, settings.seed, &cache, &bars)
        });
        let (measurement, image) = Measurement::of(
            context,
            instance.as_ref(),
            reference,
            &split,
            settings.measure.spp,
            &bars,
        );
        if let Some(folder) = &settings.images {
            let exposure = reference.image.auto_exposure();
            let reference_file = folder.join(format!("reference-{bounces}-bounces.png"));
            if !reference_file.exists() {
                reference.image.write(&reference_file, Some(exposure))?;
            }
            image.write(
                &folder.join(format!("{index:02}-indirect.png")),
                Some(exposure),
            )?;
            image.write(&folder.join(format!("{index:02}-indirect.exr")), None)?;
            tile_ratio_image(&image, &reference.image, TILE, 1.0).write(
                &folder.join(format!("{index:02}-tile-ratio.png")),
                Some(1.0),
            )?;
        }
        rows.push(Row {
            setting,
            bounces,
            bake_seconds,
            update_ms,
            measurement,
        });
    }
    let study = Study {
        scene_path,
        technique: kind.name(),
        settings,
        references: &references,
        visible,
        space_points: split.space.positions.len(),
        rows: &rows,
    };
    let report = study.markdown()?;
    if let Some(path) = &settings.markdown {
        std::fs::write(path, &report)
            .with_context(|| format!("{}: cannot write the report", path.display()))?;
    }
    if let Some(path) = &settings.json {
        std::fs::write(path, serde_json::to_string_pretty(&study.json())?)
            .with_context(|| format!("{}: cannot write the JSON report", path.display()))?;
    }
    Ok(report)
}

/// A finite number as JSON, anything else as null (JSON has no NaN).
pub(crate) fn json_number(value: f64) -> serde_json::Value {
    if value.is_finite() {
        serde_json::json!(value)
    } else {
        serde_json::Value::Null
    }
}

pub(crate) fn percent(value: f64) -> String {
    if value.is_nan() {
        "-".to_string()
    } else {
        format!("{:.1} %", value * 100.0)
    }
}

/// What a study found, for its reports.
struct Study<'a> {
    scene_path: &'a Path,
    technique: &'a str,
    settings: &'a ConvergeSettings,
    /// Per bounce count the swept settings needed.
    references: &'a BTreeMap<u32, ReferenceSet>,
    visible: &'a [bool],
    space_points: usize,
    rows: &'a [Row],
}

impl Study<'_> {
    fn markdown(&self) -> Result<String> {
        let Study {
            scene_path,
            technique,
            settings,
            references,
            visible,
            space_points,
            rows,
        } = *self;
        let mut out = String::new();
        writeln!(out, "### {technique} on {}\n", scene_path.display())?;
        writeln!(
        out,
        "{} receivers, {} seen by the camera, {} points in space (a grid over the scene's content bounds, six normals each); reference: {} paths per receiver and point, {} per pixel, seed {}.\n",
        visible.len(),
        visible.iter().filter(|&&seen| seen).count(),
        space_points,
        settings.measure.reference_samples,
        settings.measure.reference_spp,
        settings.seed
    )?;
        for (bounces, reference) in references {
            let noise = reference.noise(visible);
            writeln!(
            out,
            "Reference noise at {bounces} bounces: lightmap {}, visible lightmap {}, image {}, image 8x8 tiles {}, points in space {}.",
            percent(noise.lightmap),
            percent(noise.visible_lightmap),
            percent(noise.image),
            percent(noise.image_tiles),
            percent(noise.space)
        )?;
        }
        writeln!(out)?;
        writeln!(out, "| setting | bounces | lightmap relRMSE | visible lightmap | image relRMSE | image 8x8 tiles | light ratio | points in space | their light | bake s | update ms |")?;
        writeln!(
            out,
            "|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|"
        )?;
        for row in rows {
            let m = &row.measurement;
            writeln!(
                out,
                "| {} | {} | {} | {} | {} | {} | {:.3}x | {} | {:.3}x | {:.1} | {:.2} |",
                row.setting,
                row.bounces,
                percent(m.lightmap),
                percent(m.visible_lightmap),
                percent(m.image),
                percent(m.image_tiles),
                m.light_ratio,
                percent(m.space),
                m.space_light_ratio,
                row.bake_seconds,
                row.update_ms
            )?;
        }
        if let Some(first) = rows
            .first()
            .filter(|row| row.measurement.back_facing.count > 0)
        {
            writeln!(
                out,
                "\nPixels that see back faces (answered as points in space): {}.\n",
                first.measurement.back_facing.count
            )?;
            writeln!(
            out,
            "| setting | share of the image's squared error | relRMSE there | light ratio there |"
        )?;
            writeln!(out, "|---|---:|---:|---:|")?;
            for row in rows {
                let m = &row.measurement;
                writeln!(
                    out,
                    "| {} | {} | {} | {:.3}x |",
                    row.setting,
                    percent(m.back_facing.share),
                    percent(m.back_facing.relative_rmse),
                    m.back_facing.light_ratio
                )?;
            }
        }
        if rows.iter().any(|row| !row.measurement.classes.is_empty()) {
            writeln!(out, "\nLightmap error by receiver class (share of the squared error, relRMSE within the class, light against the reference's):\n")?;
            write!(out, "| setting |")?;
            for class in ReceiverClass::ALL {
                write!(out, " {} |", class.name())?;
            }
            writeln!(out)?;
            writeln!(out, "|---|{}", "---:|".repeat(ReceiverClass::ALL.len()))?;
            if let Some(first) = rows.iter().find(|row| !row.measurement.classes.is_empty()) {
                write!(out, "| receivers (seen) |")?;
                for class in &first.measurement.classes {
                    write!(out, " {} ({}) |", class.receivers, class.visible)?;
                }
                writeln!(out)?;
            }
            for row in rows {
                write!(out, "| {} |", row.setting)?;
                for class in &row.measurement.classes {
                    write!(
                        out,
                        " {} / {} / {:.2}x |",
                        percent(class.share),
                        percent(class.relative_rmse),
                        class.light_ratio
                    )?;
                }
                writeln!(out)?;
            }
        }
        Ok(out)
    }

    fn json(&self) -> serde_json::Value {
        let Study {
            scene_path,
            technique,
            settings,
            references,
            visible,
            rows,
            ..
        } = *self;
        serde_json::json!({
            "scene": scene_path.display().to_string(),
            "technique": technique,
            "receivers": visible.len(),
            "visible_receivers": visible.iter().filter(|&&seen| seen).count(),
            "reference_samples": settings.measure.reference_samples,
            "reference_spp": settings.measure.reference_spp,
            "seed": settings.seed,
            "reference_noise": references.iter().map(|(bounces, reference)| {
                let noise = reference.noise(visible);
                serde_json::json!({
                    "bounces": bounces,
                    "lightmap": json_number(noise.lightmap),
                    "visible_lightmap": json_number(noise.visible_lightmap),
                    "image": json_number(noise.image),
                    "image_tiles": json_number(noise.image_tiles),
                    "space": json_number(noise.space),
                })
            }).collect::<Vec<_>>(),
            "settings": rows.iter().map(|row| {
                let m = &row.measurement;
                serde_json::json!({
                    "setting": row.setting,
                    "bounces": row.bounces,
                    "bake_seconds": row.bake_seconds,
                    "update_ms": row.update_ms,
                    "lightmap": json_number(m.lightmap),
                    "visible_lightmap": json_number(m.visible_lightmap),
                    "image": json_number(m.image),
                    "image_tiles": json_number(m.image_tiles),
                    "light_ratio": json_number(m.light_ratio),
                    "space": json_number(m.space),
                    "space_light_ratio": json_number(m.space_light_ratio),
                    "back_facing_pixels": m.back_facing.count,
                    "back_facing_share": json_number(m.back_facing.share),
                    "back_facing_relative_rmse": json_number(m.back_facing.relative_rmse),
                    "back_facing_light_ratio": json_number(m.back_facing.light_ratio),
                    "classes": m.classes.iter().map(|class| serde_json::json!({
                        "class": class.class.name(),
                        "receivers": class.receivers,
                        "visible": class.visible,
                        "share": json_number(class.share),
                        "relative_rmse": json_number(class.relative_rmse),
                        "light_ratio": json_number(class.light_ratio),
                    })).collect::<Vec<_>>(),
                })
            }).collect::<Vec<_>>(),
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn sweeps_combine_with_the_last_varying_fastest() {
        let sweeps = vec![
            parse_sweep("order=2,7").unwrap(),
            parse_sweep("probes=[[0,1,0],[1,1,1]],[[0,0,0]]").unwrap(),
        ];
        assert_eq!(sweeps[1].1, vec!["[[0,1,0],[1,1,1]]", "[[0,0,0]]"]);
        let all = combinations(&sweeps);
        assert_eq!(all.len(), 4);
        assert_eq!(all[1][0], ("order".to_string(), "2".to_string()));
        assert_eq!(all[1][1].1, "[[0,0,0]]");
        assert_eq!(combinations(&[]), vec![Vec::new()]);
        assert!(parse_sweep("order").is_err());
        assert!(parse_sweep("order=").is_err());
    }

    #[test]
    fn rows_name_fixed_settings_as_well_as_swept_ones() {
        let pair = |key: &str, value: &str| (key.to_string(), value.to_string());
        assert_eq!(setting_label(&[]), "defaults");
        assert_eq!(
            setting_label(&[
                pair("preset", "high"),
                pair("order", "2"),
                pair("rank", "64")
            ]),
            "preset=high order=2 rank=64"
        );
    }
}
