//! The `relight` command-line tool: inspect scenes, render them with a GI
//! technique or the path tracer, bake (whole, or in shards that `merge`
//! joins), benchmark and compare techniques.
//!
//! Data flow per command: scene file -> [`SceneContext`] (BVH, atlas) ->
//! technique (bake, create, update from the lights) -> images and numbers.
//! Errors are reported through `anyhow` with the file or parameter at fault.

/// `println!` that returns write errors instead of panicking, so a closed
/// pipe (`relight info scene.toml | head`) ends the program quietly.
macro_rules! say {
    ($($arg:tt)*) => {{
        use std::io::Write as _;
        writeln!(std::io::stdout(), $($arg)*)?;
    }};
}

mod bench;
mod compare;
mod converge;
mod progress;
mod robustness;
mod techniques;

use anyhow::{bail, Context, Result};
use clap::{Parser, Subcommand};
use progress::Bars;
use relight_scene::atlas::TexelDensity;
use relight_technique::Progress as _;
use relight_technique::{ContextSettings, Frame, SceneContext};
use relight_trace::direct::DirectSettings;
use relight_trace::path::PathSettings;
use std::path::{Path, PathBuf};
use std::sync::Arc;

#[derive(Parser)]
#[command(
    name = "relight",
    version,
    about = "Real-time global illumination of static scenes under dynamic lights"
)]
struct Cli {
    /// No progress bars.
    #[arg(long, short, global = true)]
    quiet: bool,
    /// Worker threads (default: all cores).
    #[arg(long, global = true)]
    threads: Option<usize>,
    #[command(subcommand)]
    command: Command,
}

/// Options that shape the shared scene data.
#[derive(clap::Args, Clone)]
struct SceneOptions {
    /// Lightmap atlas size (texels on the longer side); default: automatic
    /// (128, or the power of two the scene's charts need, grown where that
    /// would make texels wider than half a metre).
    #[arg(long)]
    lightmap_resolution: Option<u32>,
    /// Lightmap texel size in metres (overrides --lightmap-resolution).
    #[arg(long)]
    texel_size: Option<f32>,
    /// Shadow rays per point toward emissive triangles.
    #[arg(long, default_value_t = 16)]
    area_samples: u32,
}

/// Options that pick and configure a technique.
#[derive(clap::Args, Clone)]
struct TechniqueOptions {
    /// Technique name (see `relight techniques`).
    #[arg(long, short)]
    technique: String,
    /// Bake file from `relight bake` (for techniques that need one).
    #[arg(long)]
    bake: Option<PathBuf>,
    /// Technique parameter, repeatable: --set key=value.
    #[arg(long = "set", value_name = "KEY=VALUE")]
    set: Vec<String>,
    /// A technique's named parameter set (pic: moderate or high); the same
    /// as --set preset=NAME, and --set values override it.
    #[arg(long)]
    preset: Option<String>,
}

#[derive(Subcommand)]
enum Command {
    /// Print scene statistics: triangles, materials, lights, bounds, atlas.
    Info {
        scene: PathBuf,
        #[command(flatten)]
        options: SceneOptions,
        /// Also describe this bake file and check it belongs to the scene.
        #[arg(long)]
        bake: Option<PathBuf>,
    },
    /// List the available techniques.
    Techniques,
    /// Render the camera view to EXR (linear) or PNG (tone-mapped sRGB).
    Render {
        scene: PathBuf,
        #[command(flatten)]
        technique: TechniqueOptions,
        #[command(flatten)]
        options: SceneOptions,
        /// Samples per pixel (path tracer) or primary rays per pixel (techniques).
        #[arg(long, default_value_t = 64, value_parser = clap::value_parser!(u32).range(1..))]
        spp: u32,
        /// Indirect bounces for the path tracer: 0 = direct light only.
        #[arg(long, default_value_t = 64)]
        max_bounces: u32,
        /// Write only light that bounced at least once.
        #[arg(long)]
        indirect_only: bool,
        /// PNG exposure multiplier (default: automatic).
        #[arg(long)]
        exposure: Option<f32>,
        #[arg(long, default_value_t = 1)]
        seed: u64,
        /// Render a sequence of this many frames (moving meshes move; files
        /// get the frame number before the extension: out-0003.png).
        #[arg(long, default_value_t = 1)]
        frames: u32,
        #[arg(short, long)]
        output: PathBuf,
    },
    /// Write the scene as glTF 2.0 with a technique's lightmap (KTX2,
    /// through MOZ_lightmap and TEXCOORD_1) and irradiance volume (KTX2 3D
    /// texture in Bevy's layout), for any engine.
    Export {
        scene: PathBuf,
        #[command(flatten)]
        technique: TechniqueOptions,
        #[command(flatten)]
        options: SceneOptions,
        /// Texel format of the KTX2 files: rgba16f or rgb9e5.
        #[arg(long, default_value = "rgba16f", value_parser = parse_texel_format)]
        format: relight_engine::TexelFormat,
        /// Zstandard supercompression level of the KTX2 files (1-22; 0:
        /// none).
        #[arg(long, default_value_t = 10)]
        zstd: i32,
        /// Also write the lightmap with direct light added
        /// (lightmap-full.ktx2), for engines that draw no lights.
        #[arg(long)]
        with_direct: bool,
        /// Irradiance-volume voxels along the scene's longest side (cubic
        /// voxels over its bounds); 0: no volume.
        #[arg(long, default_value_t = 16)]
        volume_cells: u32,
        /// Updates before the export, so that techniques that feed last
        /// frame's light back reach all bounces.
        #[arg(long, default_value_t = 5)]
        frames: u32,
        #[arg(short, long)]
        output: PathBuf,
    },
    /// Precompute a technique's bake file.
    Bake {
        scene: PathBuf,
        #[command(flatten)]
        technique: TechniqueOptions,
        #[command(flatten)]
        options: SceneOptions,
        /// Bake only part INDEX (from 0) of COUNT parts of the work, for
        /// `relight merge`; an output that already holds that shard of the
        /// same scene and parameters is kept, so a rerun bakes only the
        /// missing shards.
        #[arg(long, value_name = "INDEX/COUNT")]
        shard: Option<relight_technique::Shard>,
        /// Refuse at once a bake whose estimated peak memory is over SIZE
        /// (4G, 512M; binary units). Default: the memory available now
        /// (the system's, or what is left under a container's limit).
        #[arg(long, value_name = "SIZE", value_parser = relight_technique::parse_size)]
        max_memory: Option<u64>,
        /// Print the bake's estimated time and peak memory and stop.
        #[arg(long)]
        estimate: bool,
        #[arg(short, long, required_unless_present = "estimate")]
        output: Option<PathBuf>,
    },
    /// Join the shards of a sharded bake (`relight bake --shard I/N`) into
    /// the bake file an unsharded bake writes, byte for byte.
    Merge {
        /// Every shard's file, in any order.
        #[arg(required = true)]
        shards: Vec<PathBuf>,
        #[arg(short, long)]
        output: PathBuf,
    },
    /// Move the lights along a fixed orbit and time each update stage.
    Bench {
        scene: PathBuf,
        #[command(flatten)]
        technique: TechniqueOptions,
        #[command(flatten)]
        options: SceneOptions,
        #[arg(long, default_value_t = 100)]
        frames: u32,
        /// Image size of the shading stage, WIDTHxHEIGHT (the paper's Table
        /// 2 used 1920x1080); default: the scene camera's; 0x0: no shading
        /// stage.
        #[arg(long, value_parser = parse_resolution)]
        shading_resolution: Option<[u32; 2]>,
        /// Irradiance-volume voxels along the scene's longest side, timed
        /// as one refresh a frame; 0: no volume stage.
        #[arg(long, default_value_t = 16)]
        volume_cells: u32,
        /// Wait this long between frames, as an engine's GI worker waits
        /// for the next frame's lights (0: frames back to back). Shows
        /// what an idle gap costs the next update (caches, clock speed).
        #[arg(long, default_value_t = 0.0)]
        pause_ms: f64,
        /// After the orbit, this many frames with the lights at rest, then
        /// as many with only the camera moving: what an engine pays while
        /// nothing it lights changes (updates are skipped once settled).
        #[arg(long, default_value_t = 20)]
        rest_frames: u32,
        /// Also write the report as JSON.
        #[arg(long)]
        json: Option<PathBuf>,
    },
    /// Measure ray throughput of the BVH on a scene.
    BenchRays {
        scene: PathBuf,
        #[arg(long, default_value_t = 1_000_000)]
        rays: usize,
        #[arg(long, default_value_t = 5)]
        repeats: usize,
    },
    /// Render techniques and the reference; write images, errors and a table.
    Compare {
        scene: PathBuf,
        /// Comma-separated technique names.
        #[arg(long, value_delimiter = ',', default_value = "direct")]
        techniques: Vec<String>,
        #[command(flatten)]
        options: SceneOptions,
        #[command(flatten)]
        settings: compare::CompareSettings,
        #[arg(short, long)]
        output: PathBuf,
    },
    /// Sweep a technique's parameters and measure each setting against the
    /// path tracer: lightmap (all and camera-visible receivers), image per
    /// pixel and over 8x8 tiles, total light, and the error by receiver class.
    Converge {
        scene: PathBuf,
        #[command(flatten)]
        technique: TechniqueOptions,
        #[command(flatten)]
        options: SceneOptions,
        #[command(flatten)]
        settings: converge::ConvergeSettings,
    },
    /// Measure a technique over generated variants (`relight gen variants`)
    /// against the path tracer: each variant's 8x8-tile error, light in view
    /// and the tiles around objects' feet, and per kind of variant the
    /// median, 90th percentile and worst against the kind's bound.
    Robustness {
        #[command(flatten)]
        technique: TechniqueOptions,
        #[command(flatten)]
        options: SceneOptions,
        #[command(flatten)]
        settings: robustness::RobustnessSettings,
    },
    /// Compare every technique on every shipped scene into out/.
    Demo {
        /// Folder holding the shipped scenes (default: ./scenes).
        #[arg(long)]
        scenes: Option<PathBuf>,
        #[command(flatten)]
        settings: compare::CompareSettings,
        #[arg(short, long, default_value = "out")]
        output: PathBuf,
    },
    /// Generate procedural scenes.
    Gen {
        #[command(subcommand)]
        kind: GenKind,
    },
}

#[derive(Subcommand)]
enum GenKind {
    /// A Sponza-like atrium of about N triangles.
    Atrium {
        #[arg(long, default_value_t = 100_000)]
        triangles: usize,
        #[arg(short, long)]
        output: PathBuf,
    },
    /// Rooms, two-room suites and halls modelled the many ways real models
    /// are (one shell or a box per room; planes, solids or overlapping
    /// walls; quads or fine triangles; objects on floors; lights near walls,
    /// in corners and in shades): one folder per variant and variants.txt.
    Variants {
        #[arg(long, default_value_t = relight_scene::generate::variants::VARIANTS_DEFAULT_SEED)]
        seed: u64,
        #[arg(long, default_value_t = 12)]
        count: usize,
        #[arg(short, long)]
        output: PathBuf,
    },
}

impl SceneOptions {
    fn context_settings(&self) -> Result<ContextSettings> {
        let lightmap = match self.texel_size {
            Some(size) if !(size.is_finite() && size > 0.0) => {
                bail!("--texel-size must be a positive number of metres, got {size}")
            }
            Some(size) => TexelDensity::MetresPerTexel(size),
            None => match self.lightmap_resolution {
                Some(resolution) if !(8..=16384).contains(&resolution) => {
                    bail!("--lightmap-resolution must be between 8 and 16384, got {resolution}")
                }
                resolution => TexelDensity::from_resolution(resolution),
            },
        };
        Ok(ContextSettings {
            lightmap,
            direct: DirectSettings {
                area_light_samples: self.area_samples,
                ..DirectSettings::default()
            },
        })
    }
}

impl TechniqueOptions {
    fn pairs(&self) -> Result<Vec<(String, String)>> {
        let preset = self
            .preset
            .iter()
            .map(|name| Ok(("preset".to_string(), name.clone())));
        preset
            .chain(self.set.iter().map(|pair| {
                let (key, value) = pair
                    .split_once('=')
                    .with_context(|| format!("--set {pair}: expected KEY=VALUE"))?;
                Ok((key.trim().to_string(), value.trim().to_string()))
            }))
            .collect()
    }
}

fn load_context(path: &Path, options: &SceneOptions, quiet: bool) -> Result<Arc<SceneContext>> {
    let spinner = (!quiet).then(|| {
        let bar = indicatif::ProgressBar::new_spinner();
        bar.set_message(format!("loading {}", path.display()));
        bar.enable_steady_tick(std::time::Duration::from_millis(120));
        bar
    });
    let scene = relight_scene::load_scene(path)?;
    for warning in &scene.warnings {
        tracing::warn!("{warning}");
    }
    if let Some(bar) = &spinner {
        bar.set_message("building BVH and lightmap atlas");
    }
    let context = SceneContext::new(scene, options.context_settings()?)?;
    if let Some(bar) = spinner {
        bar.finish_and_clear();
    }
    Ok(Arc::new(context))
}

/// Creates a technique, baking in memory or reading `--bake` as needed.
/// `out.png` with frame 3 -> `out-0003.png`.
fn numbered_path(path: &std::path::Path, index: u32) -> PathBuf {
    let stem = path
        .file_stem()
        .map(|stem| stem.to_string_lossy().into_owned())
        .unwrap_or_default();
    let name = match path.extension() {
        Some(extension) => format!("{stem}-{index:04}.{}", extension.to_string_lossy()),
        None => format!("{stem}-{index:04}"),
    };
    path.with_file_name(name)
}

/// Writes a bake file as the stage `write`, then says `what` was written,
/// in how long since `start`, and each stage's share of that time.
fn write_and_report(
    bars: &Bars,
    output: &Path,
    header: &relight_technique::BakeHeader,
    payload: &[u8],
    start: std::time::Instant,
    what: &str,
) -> Result<std::time::Duration> {
    bars.start("write", 1);
    relight_technique::write_bake_atomic(output, header, payload)?;
    bars.finish();
    let elapsed = start.elapsed();
    say!(
        "{what} in {:.2} s: {} ({} bytes)",
        elapsed.as_secs_f64(),
        output.display(),
        payload.len()
    );
    for line in bars.stage_report(elapsed) {
        say!("{line}");
    }
    Ok(elapsed)
}

/// Returns memory the loaders freed to the system. glibc keeps freed
/// small blocks in its arenas, where the resident set still counts them:
/// after loading a 1M-triangle scene that is a third of it, which a bake's
/// own small allocations then reuse without raising the peak, so an
/// estimate that added the bake to the resident set would count it twice.
fn release_freed_memory() {
    #[cfg(all(target_os = "linux", target_env = "gnu"))]
    // SAFETY: malloc_trim only returns free pages to the system; it has no
    // preconditions and touches no live allocation.
    unsafe {
        libc::malloc_trim(0);
    }
}

/// Seconds to a precision a forecast has: tenths under ten seconds, then
/// whole seconds, then minutes.
fn format_seconds(seconds: f64) -> String {
    if seconds < 10.0 {
        format!("{seconds:.1} s")
    } else if seconds < 600.0 {
        format!("{seconds:.0} s")
    } else {
        format!("{:.0} min", seconds / 60.0)
    }
}

/// Prints a bake's forecast (time at the scene's ray `rates`, peak memory:
/// the process now, with the scene loaded, plus what the bake will hold)
/// and refuses the bake when that peak is over `max_memory` (default: the
/// memory available now).
fn check_estimate(
    forecast: &relight_technique::BakeEstimate,
    rates: (f64, f64),
    max_memory: Option<u64>,
    technique: &str,
) -> Result<()> {
    use relight_technique::format_bytes;
    release_freed_memory();
    let scene_bytes = relight_technique::resident_bytes().unwrap_or(0);
    let peak = scene_bytes + forecast.peak_bytes();
    let held: Vec<String> = forecast
        .peak
        .iter()
        .map(|(what, bytes)| format!("{what} {}", format_bytes(*bytes)))
        .collect();
    say!(
        "estimate        {} and {} at peak: the loaded scene {} + {}; {:.1} M closest-hit + {:.1} M occlusion rays",
        format_seconds(forecast.seconds(rates.0, rates.1)),
        format_bytes(peak),
        format_bytes(scene_bytes),
        held.join(" + "),
        forecast.rays.closest_hit as f64 / 1e6,
        forecast.rays.occlusion as f64 / 1e6,
    );
    if let Some(rate) = forecast.occlusion_rate {
        say!(
            "                its occlusion rays at {:.2} Mrays/s, timed on a sample of them",
            rate / 1e6
        );
    }
    let (limit, source) = match max_memory {
        Some(limit) => (Some(limit), "--max-memory"),
        None => (
            relight_technique::available_bytes(),
            "the memory available now; set another with --max-memory SIZE",
        ),
    };
    if let Some(limit) = limit {
        if peak > limit {
            anyhow::bail!(
                "the {technique} bake would need about {} at its peak, over the limit of {} ({source}): lower it with {}",
                format_bytes(peak),
                format_bytes(limit),
                forecast.lower_memory_with
            );
        }
    }
    Ok(())
}

fn parse_texel_format(text: &str) -> Result<relight_engine::TexelFormat, String> {
    match text.to_ascii_lowercase().as_str() {
        "rgba16f" => Ok(relight_engine::TexelFormat::Rgba16Float),
        "rgb9e5" => Ok(relight_engine::TexelFormat::Rgb9e5),
        _ => Err(format!(
            "'{text}' is not a texel format: use rgba16f or rgb9e5"
        )),
    }
}

fn create_technique(
    context: &Arc<SceneContext>,
    options: &TechniqueOptions,
    quiet: bool,
) -> Result<Box<dyn relight_technique::Technique>> {
    let pairs = options.pairs()?;
    Ok(relight_engine::open_technique(
        context,
        &options.technique,
        &pairs,
        options.bake.as_deref(),
        &Bars::new(quiet),
    )?)
}

fn main() {
    let cli = Cli::parse();
    tracing_subscriber::fmt()
        .with_env_filter(
            tracing_subscriber::EnvFilter::try_from_env("RELIGHT_LOG")
                .unwrap_or_else(|_| "warn".into()),
        )
        .with_writer(std::io::stderr)
        .without_time()
        .init();
    if let Some(threads) = cli.threads {
        if let Err(error) = rayon::ThreadPoolBuilder::new()
            .num_threads(threads)
            .build_global()
        {
            eprintln!("error: --threads {threads}: {error}");
            std::process::exit(2);
        }
    }
    if let Err(error) = run(cli) {
        // A closed pipe (`relight info x | head`) is not an error.
        if error.chain().any(|cause| {
            cause
                .downcast_ref::<std::io::Error>()
                .is_some_and(|io| io.kind() == std::io::ErrorKind::BrokenPipe)
        }) {
            std::process::exit(0);
        }
        eprintln!("error: {error:#}");
        std::process::exit(1);
    }
}

fn run(cli: Cli) -> Result<()> {
    let quiet = cli.quiet;
    match cli.command {
        Command::Info {
            scene,
            options,
            bake,
        } => info(&scene, &options, bake.as_deref(), quiet),
        Command::Techniques => {
            for kind in techniques::kinds() {
                let bake = if kind.needs_bake() { "bake" } else { "no bake" };
                say!("{:<12} {:<8} {}", kind.name(), bake, kind.summary());
            }
            Ok(())
        }
        Command::Render {
            scene,
            technique,
            options,
            spp,
            max_bounces,
            indirect_only,
            exposure,
            seed,
            frames,
            output,
        } => {
            let context = load_context(&scene, &options, quiet)?;
            let lights = context.scene.lights.clone();
            let bars = Bars::new(quiet);
            let image_of = |renders: relight_render::render::Renders| {
                if indirect_only {
                    renders.indirect
                } else {
                    renders.full
                }
            };
            let write = |image: &relight_render::image::Image,
                         path: &std::path::Path,
                         exposure: Option<f32>|
             -> Result<()> {
                image.write(path, exposure)?;
                if !quiet {
                    eprintln!("wrote {}", path.display());
                }
                Ok(())
            };
            if technique.technique == "reference" {
                if technique.bake.is_some() || !technique.set.is_empty() {
                    bail!("--technique reference takes no --bake or --set; use --spp, --max-bounces and --seed");
                }
                if frames > 1 {
                    bail!("--frames renders a technique's sequence; the reference renders one frame of the static scene");
                }
                let settings = PathSettings {
                    max_bounces,
                    seed,
                    ..PathSettings::default()
                };
                let renders = relight_render::render::render_reference(
                    &context, &lights, settings, spp, &bars,
                );
                return write(&image_of(renders), &output, exposure);
            }
            let mut instance = create_technique(&context, &technique, quiet)?;
            // A sequence shares one exposure so that its frames compare.
            let mut sequence_exposure = exposure;
            for index in 0..frames.max(1) {
                instance.update(&Frame {
                    lights: &lights,
                    index: index as u64,
                    camera: None,
                    moving_mesh_poses: None,
                })?;
                // Techniques that move meshes hand the renderer this frame's
                // geometry; the others render the static scene.
                let frame_context = instance
                    .frame_geometry()
                    .map(|scene| context.with_frame_geometry(scene));
                let renders = relight_render::render::render_with_technique(
                    frame_context.as_ref().unwrap_or(&context),
                    &lights,
                    instance.as_ref(),
                    spp,
                    seed,
                    &bars,
                );
                let image = image_of(renders);
                if frames <= 1 {
                    write(&image, &output, exposure)?;
                } else {
                    let frame_exposure =
                        *sequence_exposure.get_or_insert_with(|| image.auto_exposure());
                    write(&image, &numbered_path(&output, index), Some(frame_exposure))?;
                }
            }
            Ok(())
        }
        Command::Bake {
            scene,
            technique,
            options,
            shard,
            max_memory,
            estimate,
            output,
        } => {
            let context = load_context(&scene, &options, quiet)?;
            let kind = techniques::find(&technique.technique)?;
            let pairs = technique.pairs()?;
            let header = relight_technique::BakeHeader {
                technique: kind.name().to_string(),
                payload_version: 1,
                scene_fingerprint: context.fingerprint(),
                parameters_fingerprint: relight_technique::parameters_fingerprint(
                    kind,
                    &context.scene,
                    &pairs,
                ),
                shard,
            };
            if let (Some(shard), Some(output)) = (shard, &output) {
                // A whole, checksummed file: a shard cut short is baked again.
                if let Ok((existing, _)) = relight_technique::read_bake(output) {
                    if existing == header {
                        say!(
                            "{}: shard {shard} of this scene and parameters is already baked; kept (delete it to bake it again)",
                            output.display(),
                        );
                        return Ok(());
                    }
                }
            }
            let rates = bench::scene_ray_rates(&context, 1 << 18);
            let forecast = kind.estimate(
                &context,
                &pairs,
                shard.unwrap_or(relight_technique::Shard::WHOLE),
            )?;
            if let Some(forecast) = &forecast {
                check_estimate(forecast, rates, max_memory, kind.name())?;
            } else if estimate {
                say!("{} has no bake to estimate", kind.name());
            }
            let Some(output) = output.filter(|_| !estimate) else {
                return Ok(());
            };
            let start = std::time::Instant::now();
            let rays_before = relight_trace::counters::rays_traced();
            let bars = Bars::new(quiet);
            let payload = match shard {
                Some(shard) => kind.bake_shard(&context, &pairs, shard, &bars)?,
                None => kind.bake(&context, &pairs, &bars)?,
            };
            let what = format!(
                "baked {}{}",
                kind.name(),
                shard
                    .map(|shard| format!(" shard {shard}"))
                    .unwrap_or_default()
            );
            let elapsed = write_and_report(&bars, &output, &header, &payload, start, &what)?;
            let rays = relight_trace::counters::rays_traced().since(rays_before);
            if rays.total() > 0 {
                let (bound, line) = bench::ray_bound(rates, rays);
                say!("{line}");
                say!(
                    "ray bound       the bake took {:.2}x the time its rays alone need",
                    elapsed.as_secs_f64() / bound.max(1e-9)
                );
            }
            Ok(())
        }
        Command::Merge { shards, output } => {
            let start = std::time::Instant::now();
            let set = relight_technique::read_shard_set(&shards)?;
            let kind = techniques::find(&set.header.technique)?;
            let bars = Bars::new(quiet);
            let payload = kind.merge_shards(set.payloads, &bars)?;
            let what = format!("merged {} shards of {}", shards.len(), kind.name());
            write_and_report(&bars, &output, &set.header, &payload, start, &what)?;
            Ok(())
        }
        Command::Bench {
            scene,
            technique,
            options,
            frames,
            shading_resolution,
            volume_cells,
            pause_ms,
            rest_frames,
            json,
        } => {
            if !pause_ms.is_finite() || !(0.0..=60_000.0).contains(&pause_ms) {
                anyhow::bail!("--pause-ms must be between 0 and 60000, got {pause_ms}");
            }
            let context = load_context(&scene, &options, quiet)?;
            let mut instance = create_technique(&context, &technique, quiet)?;
            // A budget's error is measured against the same technique
            // without one, fed the same frames.
            let pairs = technique.pairs()?;
            let budget = pairs
                .iter()
                .rev()
                .find(|(key, _)| key == "update_budget")
                .map(|(_, value)| value.clone())
                .filter(|value| value.trim().parse::<f32>() != Ok(1.0));
            let unbudgeted = match budget {
                Some(update_budget) => {
                    let pairs: Vec<(String, String)> = pairs
                        .into_iter()
                        .filter(|(key, _)| key != "update_budget")
                        .collect();
                    Some(bench::Unbudgeted {
                        technique: relight_engine::open_technique(
                            &context,
                            &technique.technique,
                            &pairs,
                            technique.bake.as_deref(),
                            &Bars::new(quiet),
                        )?,
                        update_budget,
                    })
                }
                None => None,
            };
            let report = bench::run(
                &context,
                instance.as_mut(),
                unbudgeted,
                bench::BenchSettings {
                    frames,
                    shading_resolution,
                    volume_cells,
                    pause: std::time::Duration::from_secs_f64(pause_ms / 1e3),
                    rest_frames,
                },
                &Bars::new(quiet),
            )?;
            say!("{report}");
            if let Some(path) = json {
                std::fs::write(&path, serde_json::to_string_pretty(&report)?)
                    .with_context(|| format!("{}: cannot write", path.display()))?;
            }
            Ok(())
        }
        Command::Export {
            scene,
            technique,
            options,
            format,
            zstd,
            with_direct,
            volume_cells,
            frames,
            output,
        } => {
            if !(0..=22).contains(&zstd) {
                bail!("--zstd {zstd}: give a level from 1 to 22, or 0 for none");
            }
            let context = load_context(&scene, &options, quiet)?;
            let mut instance = create_technique(&context, &technique, quiet)?;
            let lights = context.scene.lights.clone();
            for index in 0..frames.max(1) {
                instance.update(&Frame {
                    lights: &lights,
                    index: index as u64,
                    camera: None,
                    moving_mesh_poses: None,
                })?;
            }
            let (lo, hi) = context.scene.content_bounds();
            let settings = relight_engine::ExportSettings {
                format,
                zstd_level: (zstd > 0).then_some(zstd),
                with_direct,
                volume: (volume_cells > 0)
                    .then(|| relight_engine::VolumeGrid::covering(lo, hi, volume_cells)),
            };
            let summary = relight_engine::export_scene(
                &context,
                instance.as_ref(),
                &lights,
                &settings,
                &output,
            )?;
            if !quiet {
                for file in &summary.files {
                    eprintln!("wrote {}", file.display());
                }
            }
            Ok(())
        }
        Command::BenchRays {
            scene,
            rays,
            repeats,
        } => bench::rays(&scene, rays, repeats, quiet),
        Command::Compare {
            scene,
            techniques,
            options,
            settings,
            output,
        } => {
            let context = load_context(&scene, &options, quiet)?;
            let table = compare::run(&context, &scene, &techniques, &settings, &output, quiet)?;
            say!("{table}");
            Ok(())
        }
        Command::Converge {
            scene,
            technique,
            options,
            settings,
        } => {
            let context = load_context(&scene, &options, quiet)?;
            let report = converge::run(&context, &scene, &technique, &settings, quiet)?;
            say!("{report}");
            Ok(())
        }
        Command::Robustness {
            technique,
            options,
            settings,
        } => {
            let report =
                robustness::run(&technique, options.context_settings()?, &settings, quiet)?;
            say!("{report}");
            Ok(())
        }
        Command::Demo {
            scenes,
            settings,
            output,
        } => compare::demo(scenes, &settings, &output, quiet),
        Command::Gen {
            kind: GenKind::Atrium { triangles, output },
        } => {
            let scene = relight_scene::generate::write_atrium(&output, triangles)?;
            say!("wrote {}", scene.display());
            Ok(())
        }
        Command::Gen {
            kind:
                GenKind::Variants {
                    seed,
                    count,
                    output,
                },
        } => {
            let written = relight_scene::generate::variants::write_variants(&output, seed, count)?;
            for (scene, variant) in &written {
                say!("{}  {}", scene.display(), variant.description());
            }
            say!(
                "wrote {} variants and {}",
                written.len(),
                output.join("variants.txt").display()
            );
            Ok(())
        }
    }
}

fn info(path: &Path, options: &SceneOptions, bake: Option<&Path>, quiet: bool) -> Result<()> {
    let context = load_context(path, options, quiet)?;
    let scene = &context.scene;
    let (lo, hi) = scene.mesh.bounds();
    let atlas = &context.atlas;
    say!("scene           {}", path.display());
    say!("triangles       {}", scene.mesh.triangles.len());
    say!("vertices        {}", scene.mesh.positions.len());
    say!("materials       {}", scene.materials.len());
    say!("textures        {}", scene.textures.len());
    say!(
        "lights          {} (+ {} emissive triangles)",
        scene.lights.len(),
        context.emitters.triangles.len()
    );
    say!(
        "bounds          [{:.3}, {:.3}, {:.3}] .. [{:.3}, {:.3}, {:.3}]",
        lo.x,
        lo.y,
        lo.z,
        hi.x,
        hi.y,
        hi.z
    );
    say!("surface area    {:.3} m^2", scene.mesh.total_area());
    say!(
        "atlas           {} x {} texels, {} charts{}",
        atlas.width,
        atlas.height,
        atlas.chart_count,
        if atlas.from_mesh_uvs {
            " (mesh UV set 2)"
        } else {
            ""
        }
    );
    say!("texel size      {:.4} m", atlas.metres_per_texel);
    if atlas.near_light_charts > 0 {
        say!(
            "near lights     {} charts get finer texels (lightmap.refine_near_lights)",
            atlas.near_light_charts
        );
    }
    say!("receivers       {}", atlas.receivers.len());
    say!("coverage        {:.1} %", atlas.coverage() * 100.0);
    if atlas.filled_texels() > 0 {
        say!(
            "hidden texels   {} covered texels nobody sees show a seen neighbour (objects' feet)",
            atlas.filled_texels()
        );
    }
    if let Some(region) = &atlas.detail {
        let near = atlas
            .receivers
            .positions
            .iter()
            .filter(|&&position| region.gap(position, position) < region.margin)
            .count();
        say!(
            "detail region   {} and {:.1} m around it at full density ({near} receivers, {:.1} %); texel edges 4x longer ring by ring outside",
            region.describe_box(),
            region.margin,
            100.0 * near as f64 / atlas.receivers.len().max(1) as f64
        );
    }
    say!(
        "BVH             {} nodes, {:.1} MiB, built in {:.1} ms",
        context.bvh.node_count(),
        context.bvh.memory_bytes() as f64 / 1048576.0,
        context.bvh_build_time.as_secs_f64() * 1e3
    );
    say!(
        "atlas build     {:.1} ms",
        context.atlas_build_time.as_secs_f64() * 1e3
    );
    for warning in &scene.warnings {
        say!("warning         {warning}");
    }
    if let Some(bake) = bake {
        let (header, payload) = relight_technique::read_bake(bake)?;
        if let Some(shard) = header.shard {
            say!(
                "bake            {} (shard {shard} of a {} bake, {} bytes): join the shards with `relight merge`",
                bake.display(),
                header.technique,
                payload.len()
            );
            return Ok(());
        }
        let matches = header.scene_fingerprint == context.fingerprint();
        say!(
            "bake            {} ({} payload version {}, {} bytes)",
            bake.display(),
            header.technique,
            header.payload_version,
            payload.len()
        );
        say!(
            "bake scene      {}",
            if matches {
                "matches this scene and lightmap"
            } else {
                "made for another scene or lightmap resolution: bake again"
            }
        );
        if matches {
            let kind = techniques::find(&header.technique)?;
            let technique = kind.create(
                context.clone(),
                Some(&payload),
                &[],
                &relight_technique::NoProgress,
            )?;
            for (fact, value) in technique.bake_facts() {
                say!("{:<15} {}", fact, value);
            }
            for entry in technique.memory() {
                say!(
                    "memory          {:<28} {:>12} bytes",
                    entry.buffer,
                    entry.bytes
                );
            }
        }
    }
    Ok(())
}

/// `WIDTHxHEIGHT`, for `--shading-resolution`.
fn parse_resolution(text: &str) -> Result<[u32; 2], String> {
    let parse = |side: &str| side.trim().parse::<u32>().ok();
    match text.split_once(['x', 'X']) {
        Some((width, height)) => match (parse(width), parse(height)) {
            (Some(width), Some(height)) if (width == 0) == (height == 0) => Ok([width, height]),
            _ => Err(format!(
                "'{text}': expected WIDTHxHEIGHT, both positive (or 0x0 for no shading stage)"
            )),
        },
        None => Err(format!(
            "'{text}': expected WIDTHxHEIGHT, for example 1920x1080"
        )),
    }
}
