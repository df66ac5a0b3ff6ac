//! `relight robustness`: a technique over generated variants against the
//! path tracer, so that the next scene it fails on is found by a command
//! rather than by a user.
//!
//! Data flow: for each variant of the family (`--seed`), the variant is
//! written and loaded ([`VariantCase::load`]), the technique baked in memory
//! and updated under its lights, and measured like one setting of `relight
//! converge` (8x8 tiles, visible lightmap, light in view, points in space)
//! plus the tiles around objects' feet; references are cached like
//! converge's. The report gives every variant's row and, per kind of
//! variant, the median, 90th percentile and worst against the kind's bound,
//! and writes the worst variants' images.

use crate::converge::{json_number, percent, studied_kind, updated_technique, MeasureSettings};
use crate::progress::Bars;
use anyhow::{bail, Context, Result};
use relight_render::convergence::{Measurement, Split, TILE};
use relight_render::metrics::tile_ratio_image;
use relight_render::robustness::{
    bound, distribution, ContactError, VariantCase, CONTACT_HALO, UNLIT_LIGHT_RATIO,
};
use relight_scene::generate::variants::{variant, VariantKind, VARIANTS_DEFAULT_SEED};
use relight_technique::ContextSettings;
use relight_trace::path::PathSettings;
use std::fmt::Write as _;
use std::path::PathBuf;
use std::time::Instant;

#[derive(clap::Args, Clone, Debug)]
pub struct RobustnessSettings {
    /// How many variants to measure.
    #[arg(long, default_value_t = 12)]
    pub variants: usize,
    /// The variant family (`relight gen variants --seed`).
    #[arg(long, default_value_t = VARIANTS_DEFAULT_SEED)]
    pub seed: u64,
    /// Index of the first variant (to continue or split a study).
    #[arg(long, default_value_t = 0)]
    pub first: usize,
    /// Camera images at 1/N of the variants' 320x240 on each side.
    #[arg(long, default_value_t = relight_render::robustness::STUDY_SHRINK)]
    pub shrink: u32,
    #[command(flatten)]
    pub measure: MeasureSettings,
    /// Keep the variants' files here (default: each is written to the
    /// temporary folder and removed once loaded).
    #[arg(long)]
    pub keep: Option<PathBuf>,
    /// Write the worst variants' images (reference, technique, 8x8-tile
    /// light ratio) here.
    #[arg(long)]
    pub images: Option<PathBuf>,
    /// How many of the worst variants' images to write.
    #[arg(long, default_value_t = 4)]
    pub worst: usize,
    /// Also write the results as JSON.
    #[arg(long)]
    pub json: Option<PathBuf>,
}

struct Row {
    name: String,
    kind: VariantKind,
    description: String,
    unlit_view: bool,
    triangles: usize,
    receivers: usize,
    bake_seconds: f64,
    update_ms: f64,
    measurement: Measurement,
    contact: ContactError,
    reference_tile_noise: f64,
    bound: Option<f64>,
}

/// A variant's reference resolves its bound when its own 8x8-tile noise
/// is at most this share of the bound: noisier, an error near the bound is
/// as much the reference's as the technique's (shaded lamps and unlit
/// rooms lit through a doorway need many more paths).
const RESOLVING_NOISE: f64 = 0.5;

impl Row {
    /// Whether the reference is precise enough to judge this variant
    /// against its bound.
    fn resolved(&self) -> bool {
        self.bound
            .is_none_or(|bound| self.reference_tile_noise <= bound * RESOLVING_NOISE)
    }

    /// Whether the reference's tiles at objects' feet are precise enough
    /// to tell a halo there from the reference's own noise. The halo
    /// threshold follows the image's error, so the image must be resolved
    /// too: against a noisy reference that error is mostly noise.
    fn contact_resolved(&self) -> bool {
        self.resolved()
            && self
                .contact
                .resolved(self.measurement.image_tiles, RESOLVING_NOISE)
    }

    /// Tile error over the bound: over 1 fails.
    fn severity(&self) -> f64 {
        self.bound.map_or(self.measurement.image_tiles, |bound| {
            self.measurement.image_tiles / bound
        })
    }
}

pub fn run(
    technique: &crate::TechniqueOptions,
    context_settings: ContextSettings,
    settings: &RobustnessSettings,
    quiet: bool,
) -> Result<String> {
    let kind = studied_kind(technique, "robustness", "variant")?;
    if settings.variants == 0 {
        bail!("--variants must be at least 1");
    }
    let pairs = technique.pairs()?;
    let bars = Bars::new(quiet);
    let cache = settings.measure.cache_folder()?;
    if let Some(folder) = &settings.images {
        std::fs::create_dir_all(folder)
            .with_context(|| format!("{}: cannot create the images folder", folder.display()))?;
    }
    let mut rows = Vec::new();
    let mut images = Vec::new();
    for index in settings.first..settings.first + settings.variants {
        let generated = variant(settings.seed, index);
        let name = generated.name();
        if !quiet {
            eprintln!("== {name}: {}", generated.description());
        }
        let loaded = match &settings.keep {
            Some(keep) => VariantCase::load(
                generated,
                &keep.join(&name),
                settings.shrink,
                context_settings,
            ),
            None => VariantCase::load_temporary(generated, settings.shrink, context_settings),
        };
        let case = loaded.with_context(|| format!("variant {name} (seed {})", settings.seed))?;
        let context = &case.context;
        let start = Instant::now();
        let payload = if kind.needs_bake() {
            Some(
                kind.bake(context, &pairs, &bars)
                    .with_context(|| format!("baking {} on variant {name}", kind.name()))?,
            )
        } else {
            None
        };
        let bake_seconds = start.elapsed().as_secs_f64();
        let (instance, update_ms) = updated_technique(
            kind,
            context,
            payload.as_deref(),
            &pairs,
            &bars,
            &format!("on variant {name}"),
        )?;
        let split = Split::of(context);
        let bounces = instance.reference_bounces(settings.measure.max_bounces);
        let reference = settings.measure.reference(
            context,
            &split,
            bounces,
            PathSettings::default().seed,
            &cache,
            &bars,
        );
        let (measurement, image) = Measurement::of(
            context,
            instance.as_ref(),
            &reference,
            &split,
            settings.measure.spp,
            &bars,
        );
        let contact = ContactError::of(
            &image,
            &reference.image,
            &reference.tile_standard_errors(),
            &case.contact_tiles,
        );
        let row = Row {
            name: name.clone(),
            kind: case.variant.kind,
            description: case.variant.description(),
            unlit_view: case.variant.unlit_view,
            triangles: context.scene.mesh.triangles.len(),
            receivers: context.atlas.receivers.len(),
            bake_seconds,
            update_ms,
            contact,
            reference_tile_noise: reference.noise(&split.visible).image_tiles,
            bound: bound(kind.name(), case.variant.kind),
            measurement,
        };
        if !quiet {
            eprintln!(
                "   tiles {:.1} %, light {:.3}x, contact tiles {:.1} % ({:.3}x)",
                row.measurement.image_tiles * 100.0,
                row.measurement.light_ratio,
                row.contact.relative_rmse * 100.0,
                row.contact.light_ratio
            );
        }
        if settings.images.is_some() {
            images.push((row.severity(), name, image, reference.image));
            images.sort_by(|a, b| b.0.total_cmp(&a.0));
            images.truncate(settings.worst);
        }
        rows.push(row);
    }
    if let Some(folder) = &settings.images {
        for (_, name, image, reference) in &images {
            let exposure = reference.auto_exposure();
            reference.write(
                &folder.join(format!("{name}-reference.png")),
                Some(exposure),
            )?;
            image.write(
                &folder.join(format!("{name}-{}.png", kind.name())),
                Some(exposure),
            )?;
            tile_ratio_image(image, reference, TILE, 1.0).write(
                &folder.join(format!("{name}-{}-tile-ratio.png", kind.name())),
                Some(1.0),
            )?;
        }
    }
    if let Some(path) = &settings.json {
        std::fs::write(
            path,
            serde_json::to_string_pretty(&json(kind.name(), settings, &rows))?,
        )
        .with_context(|| format!("{}: cannot write the JSON report", path.display()))?;
    }
    report(kind.name(), &pairs, settings, &rows)
}

fn report(
    technique: &str,
    pairs: &[(String, String)],
    settings: &RobustnessSettings,
    rows: &[Row],
) -> Result<String> {
    let mut out = String::new();
    let setting = if pairs.is_empty() {
        "defaults".to_string()
    } else {
        pairs
            .iter()
            .map(|(key, value)| format!("{key}={value}"))
            .collect::<Vec<_>>()
            .join(" ")
    };
    writeln!(
        out,
        "### {technique} ({setting}) on variants {}..{} of seed {}\n",
        settings.first,
        settings.first + settings.variants,
        settings.seed
    )?;
    writeln!(
        out,
        "Reference: {} paths per pixel, {} per receiver and point in space; images 1/{} of 320x240.\n",
        settings.measure.reference_spp, settings.measure.reference_samples, settings.shrink
    )?;
    writeln!(out, "| variant | triangles | receivers | image 8x8 tiles | bound | reference tile noise | visible lightmap | light in view | contact tiles | contact light | contact reference noise | points in space | bake s | update ms |")?;
    writeln!(
        out,
        "|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|"
    )?;
    for row in rows {
        let m = &row.measurement;
        writeln!(
            out,
            "| {} | {} | {} | {} | {} | {} | {} | {:.3}x | {} | {:.3}x | {} | {} | {:.1} | {:.1} |",
            row.name,
            row.triangles,
            row.receivers,
            percent(m.image_tiles),
            row.bound.map_or("-".to_string(), percent),
            percent(row.reference_tile_noise),
            percent(m.visible_lightmap),
            m.light_ratio,
            percent(row.contact.relative_rmse),
            row.contact.light_ratio,
            percent(row.contact.reference_noise),
            percent(m.space),
            row.bake_seconds,
            row.update_ms
        )?;
    }
    writeln!(
        out,
        "\nPer kind, over the variants whose reference resolves the bound (its 8x8-tile noise at most {:.0} % of it; raise --reference-spp for the rest):",
        RESOLVING_NOISE * 100.0
    )?;
    writeln!(out, "\n| kind | variants resolved | tiles: median | 90th percentile | worst | bound | over bound | worst over 1.5x bound | contact / image tiles: median, worst; halos over {CONTACT_HALO}x where the reference resolves them | unlit rooms' light in view |")?;
    writeln!(out, "|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|")?;
    for kind in VariantKind::ALL {
        let all_of_kind = rows.iter().filter(|row| row.kind == kind).count();
        let of_kind: Vec<&Row> = rows
            .iter()
            .filter(|row| row.kind == kind && row.resolved())
            .collect();
        if of_kind.is_empty() {
            if all_of_kind > 0 {
                writeln!(
                    out,
                    "| {} | 0 of {all_of_kind} resolved | | | | | | | | |",
                    kind.name()
                )?;
            }
            continue;
        }
        let tiles: Vec<f64> = of_kind
            .iter()
            .map(|row| row.measurement.image_tiles)
            .collect();
        let contact_over_image: Vec<f64> = of_kind
            .iter()
            .map(|row| row.contact.relative_rmse / row.measurement.image_tiles)
            .collect();
        let contact_resolved: Vec<&&Row> = of_kind
            .iter()
            .filter(|row| row.contact_resolved())
            .collect();
        let halos = contact_resolved
            .iter()
            .filter(|row| row.contact.is_halo(row.measurement.image_tiles))
            .count();
        let bound = of_kind[0].bound;
        let over = |factor: f64| {
            bound.map_or("-".to_string(), |bound| {
                tiles
                    .iter()
                    .filter(|&&tile| tile > bound * factor)
                    .count()
                    .to_string()
            })
        };
        let unlit: Vec<f64> = of_kind
            .iter()
            .filter(|row| row.unlit_view)
            .map(|row| row.measurement.light_ratio)
            .collect();
        let unlit_text = if unlit.is_empty() {
            "-".to_string()
        } else {
            let low = unlit.iter().copied().fold(f64::INFINITY, f64::min);
            let high = unlit.iter().copied().fold(f64::NEG_INFINITY, f64::max);
            let outside = unlit
                .iter()
                .filter(|&&ratio| !(UNLIT_LIGHT_RATIO.0..=UNLIT_LIGHT_RATIO.1).contains(&ratio))
                .count();
            format!("{low:.2}-{high:.2}x, {outside} outside 0.85-1.15x")
        };
        let (median, p90, worst) = distribution(&tiles).unwrap_or((f64::NAN, f64::NAN, f64::NAN));
        let contact =
            distribution(&contact_over_image).map_or("-".to_string(), |(median, _, worst)| {
                format!(
                    "{median:.2}x, {worst:.2}x; {halos} of {} resolved",
                    contact_resolved.len()
                )
            });
        writeln!(
            out,
            "| {} | {} of {all_of_kind} | {} | {} | {} | {} | {} | {} | {} | {} |",
            kind.name(),
            of_kind.len(),
            percent(median),
            percent(p90),
            percent(worst),
            bound.map_or("-".to_string(), percent),
            over(1.0),
            over(1.5),
            contact,
            unlit_text
        )?;
    }
    writeln!(out, "\nVariants:\n")?;
    for row in rows {
        writeln!(out, "- {}: {}", row.name, row.description)?;
    }
    Ok(out)
}

fn json(technique: &str, settings: &RobustnessSettings, rows: &[Row]) -> serde_json::Value {
    serde_json::json!({
        "technique": technique,
        "seed": settings.seed,
        "first": settings.first,
        "variants": settings.variants,
        "reference_spp": settings.measure.reference_spp,
        "reference_samples": settings.measure.reference_samples,
        "rows": rows.iter().map(|row| {
            let m = &row.measurement;
            serde_json::json!({
                "variant": row.name,
                "kind": row.kind.name(),
                "description": row.description,
                "unlit_view": row.unlit_view,
                "triangles": row.triangles,
                "receivers": row.receivers,
                "bake_seconds": row.bake_seconds,
                "update_ms": row.update_ms,
                "image_tiles": json_number(m.image_tiles),
                "bound": row.bound.map(json_number),
                "reference_tile_noise": json_number(row.reference_tile_noise),
                "reference_resolves_bound": row.resolved(),
                "lightmap": json_number(m.lightmap),
                "visible_lightmap": json_number(m.visible_lightmap),
                "image": json_number(m.image),
                "light_ratio": json_number(m.light_ratio),
                "space": json_number(m.space),
                "space_light_ratio": json_number(m.space_light_ratio),
                "contact_tiles": row.contact.tiles,
                "contact_relative_rmse": json_number(row.contact.relative_rmse),
                "contact_light_ratio": json_number(row.contact.light_ratio),
                "contact_reference_noise": json_number(row.contact.reference_noise),
                "contact_resolved": row.contact_resolved(),
            })
        }).collect::<Vec<_>>(),
    })
}
