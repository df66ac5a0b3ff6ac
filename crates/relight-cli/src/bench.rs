//! `relight bench`: per-stage update timings over a fixed light orbit, and
//! `relight bench-rays`: BVH throughput.

use anyhow::Result;
use glam::{Vec2, Vec3};
use rayon::prelude::*;
use relight_core::Rgb;
use relight_scene::Light;
use relight_technique::{Frame, Progress, SceneContext, SurfacePoint, Technique};
use relight_trace::path::CameraRays;
use serde::Serialize;
use std::fmt;
use std::path::Path;

/// Frames run before timing so caches and thread pools are warm.
const WARM_UP_FRAMES: u32 = 3;

#[derive(Serialize)]
pub struct StageReport {
    pub stage: String,
    pub median_ms: f64,
    pub p95_ms: f64,
}

#[derive(Serialize)]
pub struct BenchReport {
    pub technique: String,
    pub scene: String,
    pub frames: u32,
    pub threads: usize,
    pub receivers: usize,
    /// The first update, which settles every bounce of feedback techniques
    /// (PIC, SRP) at once; not in the medians.
    pub first_update_ms: f64,
    /// Feedback passes the first update ran (0: the technique has none).
    pub first_update_passes: u32,
    pub stages: Vec<StageReport>,
    pub total: StageReport,
    /// Indirect light (diffuse, plus glossy where the material and the
    /// technique have it) at every pixel of the camera's view that sees the
    /// static scene; apart from `total`, which is the GI update alone.
    pub shading: Option<StageReport>,
    pub shaded_points: usize,
    /// The lightmap texels an engine uploads (RGBA16F, every atlas texel,
    /// gutters included) made from the update's receiver values; `None`
    /// for techniques without a lightmap.
    pub lightmap_image: Option<StageReport>,
    /// The update plus the lightmap image: an engine's GI cost a frame.
    pub engine_frame: Option<StageReport>,
    /// One refresh of the irradiance volume for dynamic objects (six
    /// lookups of light in space a voxel), which engines run at their own
    /// rate; `None` with `--volume-cells 0`.
    pub irradiance_volume: Option<StageReport>,
    pub memory: Vec<(String, usize)>,
    pub memory_total_bytes: usize,
}

fn percentile(sorted: &[f64], fraction: f64) -> f64 {
    if sorted.is_empty() {
        return 0.0;
    }
    let position = ((sorted.len() - 1) as f64 * fraction).round() as usize;
    sorted[position]
}

fn stage_report(stage: &str, mut samples: Vec<f64>) -> StageReport {
    samples.sort_by(|a, b| a.total_cmp(b));
    StageReport {
        stage: stage.to_string(),
        median_ms: percentile(&samples, 0.5),
        p95_ms: percentile(&samples, 0.95),
    }
}

/// A static-scene point the camera sees: the surface, the direction back to
/// the camera, and the material's Phong exponent.
struct ShadedPoint {
    surface: SurfacePoint,
    toward_viewer: Vec3,
    exponent: f32,
}

/// One point per pixel centre of the scene's camera at `resolution`, where
/// the pixel sees the front of a surface (the lightmap holds front sides).
fn camera_points(context: &SceneContext, resolution: [u32; 2]) -> Vec<ShadedPoint> {
    let mut camera = context.scene.camera.clone();
    camera.resolution = resolution;
    let rays = CameraRays::new(&camera);
    let scene = &context.scene;
    (0..resolution[0] * resolution[1])
        .into_par_iter()
        .filter_map(|pixel| {
            let ray = rays.ray(
                pixel % resolution[0],
                pixel / resolution[0],
                Vec2::splat(0.5),
            );
            let hit = context.bvh.intersect(&ray)?;
            let triangle = hit.triangle as usize;
            let normal = scene.mesh.geometric_normal(triangle);
            if normal.dot(ray.direction) >= 0.0 {
                return None;
            }
            Some(ShadedPoint {
                surface: SurfacePoint {
                    position: scene.mesh.point_at(triangle, hit.barycentric),
                    normal,
                    triangle: hit.triangle,
                    barycentric: hit.barycentric,
                },
                toward_viewer: -ray.direction,
                exponent: scene.material_of(triangle).phong_exponent,
            })
        })
        .collect()
}

/// Shades every point from the technique's current state, in parallel.
fn shade(technique: &dyn Technique, points: &[ShadedPoint], out: &mut [Rgb]) {
    out.par_iter_mut().zip(points).for_each(|(value, point)| {
        let mut indirect = technique.indirect_irradiance(&point.surface);
        if point.exponent > 1.0 {
            if let Some(glossy) =
                technique.glossy_radiance(&point.surface, point.toward_viewer, point.exponent)
            {
                indirect += glossy;
            }
        }
        *value = indirect;
    });
}

/// What `relight bench` runs.
#[derive(Clone, Copy, Debug)]
pub struct BenchSettings {
    pub frames: u32,
    /// The shading stage's image size (`None`: the scene camera's; a zero
    /// side: no shading stage).
    pub shading_resolution: Option<[u32; 2]>,
    /// The irradiance volume's voxels along the scene's longest side (0:
    /// none).
    pub volume_cells: u32,
    /// Idle time before each frame (an engine's worker waiting for the
    /// next frame's lights).
    pub pause: std::time::Duration,
}

pub fn run(
    context: &SceneContext,
    technique: &mut dyn Technique,
    settings: BenchSettings,
    progress: &dyn Progress,
) -> Result<BenchReport> {
    let BenchSettings {
        frames,
        shading_resolution,
        volume_cells,
        pause,
    } = settings;
    let frames = frames.max(1);
    let resolution = shading_resolution.unwrap_or(context.scene.camera.resolution);
    let points = if resolution.contains(&0) {
        Vec::new()
    } else {
        camera_points(context, resolution)
    };
    let mut shaded = vec![Rgb::ZERO; points.len()];
    let mut shading_samples = Vec::with_capacity(frames as usize);
    let (lo, hi) = context.scene.mesh.bounds();
    let centre = (lo + hi) * 0.5;
    let base = &context.scene.lights;
    let mut stage_names: Vec<&'static str> = Vec::new();
    let mut stage_samples: Vec<Vec<f64>> = Vec::new();
    let mut totals = Vec::with_capacity(frames as usize);
    let layout = relight_engine::LightmapLayout::new(&context.atlas);
    let mut lightmap_bytes = vec![0u8; layout.texel_count() * 8];
    let (mut lightmap_samples, mut engine_frames) = (Vec::new(), Vec::new());
    let (lo, hi) = context.scene.content_bounds();
    let grid =
        (volume_cells > 0).then(|| relight_engine::VolumeGrid::covering(lo, hi, volume_cells));
    let mut volume_texels = vec![Rgb::ZERO; grid.map_or(0, |grid| grid.voxel_count() * 6)];
    let mut volume_samples = Vec::new();
    let mut first_update = (0.0, 0);
    progress.start("bench", (frames + WARM_UP_FRAMES) as u64);
    for index in 0..frames + WARM_UP_FRAMES {
        let lights = relight_engine::orbit(base, centre, index, frames);
        if !pause.is_zero() {
            std::thread::sleep(pause);
        }
        technique.update(&Frame {
            lights: &lights,
            index: index as u64,
            camera: None,
            moving_mesh_poses: None,
        })?;
        progress.advance(1);
        let timings = technique.timings();
        if index == 0 {
            first_update = (timings.total().as_secs_f64() * 1e3, timings.feedback_passes);
        }
        if index < WARM_UP_FRAMES {
            continue;
        }
        for (stage, duration) in &timings.stages {
            let slot = match stage_names.iter().position(|name| name == stage) {
                Some(slot) => slot,
                None => {
                    stage_names.push(stage);
                    stage_samples.push(Vec::new());
                    stage_names.len() - 1
                }
            };
            stage_samples[slot].push(duration.as_secs_f64() * 1e3);
        }
        let update_ms = timings.total().as_secs_f64() * 1e3;
        totals.push(update_ms);
        if let Some(values) = technique.receiver_irradiance() {
            let start = std::time::Instant::now();
            layout.fill_rgba16f(values, None, &mut lightmap_bytes);
            let lightmap_ms = start.elapsed().as_secs_f64() * 1e3;
            lightmap_samples.push(lightmap_ms);
            engine_frames.push(update_ms + lightmap_ms);
        }
        if let Some(grid) = &grid {
            let start = std::time::Instant::now();
            relight_engine::fill_volume(grid, &*technique, &mut volume_texels);
            volume_samples.push(start.elapsed().as_secs_f64() * 1e3);
        }
        if !points.is_empty() {
            let start = std::time::Instant::now();
            shade(&*technique, &points, &mut shaded);
            shading_samples.push(start.elapsed().as_secs_f64() * 1e3);
        }
    }
    progress.finish();
    let memory: Vec<(String, usize)> = technique
        .memory()
        .into_iter()
        .map(|entry| (entry.buffer, entry.bytes))
        .collect();
    Ok(BenchReport {
        technique: technique.name().to_string(),
        scene: context.scene.source.display().to_string(),
        frames,
        threads: rayon::current_num_threads(),
        receivers: context.atlas.receivers.len(),
        first_update_ms: first_update.0,
        first_update_passes: first_update.1,
        stages: stage_names
            .iter()
            .zip(stage_samples)
            .map(|(name, samples)| stage_report(name, samples))
            .collect(),
        total: stage_report("total", totals),
        shading: (!points.is_empty()).then(|| {
            stage_report(
                &format!("shading {}x{}", resolution[0], resolution[1]),
                shading_samples,
            )
        }),
        shaded_points: points.len(),
        lightmap_image: (!lightmap_samples.is_empty()).then(|| {
            stage_report(
                &format!("lightmap RGBA16F {}x{}", layout.width, layout.height),
                lightmap_samples,
            )
        }),
        engine_frame: (!engine_frames.is_empty())
            .then(|| stage_report("update + lightmap", engine_frames)),
        irradiance_volume: grid.map(|grid| {
            let [x, y, z] = grid.resolution.to_array();
            stage_report(&format!("irradiance volume {x}x{y}x{z}"), volume_samples)
        }),
        memory_total_bytes: memory.iter().map(|(_, bytes)| bytes).sum(),
        memory,
    })
}

impl fmt::Display for BenchReport {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        writeln!(
            f,
            "{} on {}: {} frames, {} threads, {} receivers",
            self.technique, self.scene, self.frames, self.threads, self.receivers
        )?;
        let passes = match self.first_update_passes {
            0 => String::new(),
            passes => format!(", {passes} feedback passes (it settles the bounces)"),
        };
        writeln!(
            f,
            "first update {:.1} ms{passes}; not in the medians",
            self.first_update_ms
        )?;
        writeln!(f, "{:<28} {:>12} {:>12}", "stage", "median ms", "p95 ms")?;
        for stage in self.stages.iter().chain(std::iter::once(&self.total)) {
            writeln!(
                f,
                "{:<28} {:>12.3} {:>12.3}",
                stage.stage, stage.median_ms, stage.p95_ms
            )?;
        }
        if let Some(shading) = &self.shading {
            writeln!(
                f,
                "{:<28} {:>12.3} {:>12.3}   (not in total; {} pixels see the static scene)",
                shading.stage, shading.median_ms, shading.p95_ms, self.shaded_points
            )?;
        }
        for (stage, note) in [
            (&self.lightmap_image, "(the texels an engine uploads)"),
            (&self.engine_frame, "(an engine's GI cost a frame)"),
            (
                &self.irradiance_volume,
                "(one refresh, at the engine's rate)",
            ),
        ] {
            if let Some(stage) = stage {
                writeln!(
                    f,
                    "{:<28} {:>12.3} {:>12.3}   {note}",
                    stage.stage, stage.median_ms, stage.p95_ms
                )?;
            }
        }
        writeln!(f, "{:<28} {:>12}", "buffer", "bytes")?;
        for (buffer, bytes) in &self.memory {
            writeln!(f, "{buffer:<28} {bytes:>12}")?;
        }
        write!(f, "{:<28} {:>12}", "memory total", self.memory_total_bytes)
    }
}

pub fn rays(scene_path: &Path, rays: usize, repeats: usize, quiet: bool) -> Result<()> {
    if !quiet {
        eprintln!("loading {}", scene_path.display());
    }
    let scene = relight_scene::load_scene(scene_path)?;
    let light_position = shadow_ray_target(&scene);
    let report = relight_trace::raybench::run(
        &scene.mesh.positions,
        &scene.mesh.triangles,
        light_position,
        rays,
        repeats,
        1,
    );
    say!(
        "{} triangles, {} threads",
        scene.mesh.triangles.len(),
        rayon::current_num_threads()
    );
    say!("{report}");
    Ok(())
}

/// Where `relight bench-rays`' shadow rays go: the first point or spot
/// light, or above the scene's centre.
pub fn shadow_ray_target(scene: &relight_scene::Scene) -> Vec3 {
    let (lo, hi) = scene.mesh.bounds();
    scene
        .lights
        .iter()
        .find_map(Light::position)
        .unwrap_or(Vec3::new(
            (lo.x + hi.x) * 0.5,
            lo.y + (hi.y - lo.y) * 0.9,
            (lo.z + hi.z) * 0.5,
        ))
}

/// The scene's own diffuse ray rates (rays per second, closest-hit and
/// occlusion), as `relight bench-rays` measures them, on `rays` rays.
pub fn scene_ray_rates(context: &relight_technique::SceneContext, rays: usize) -> (f64, f64) {
    let mesh = &context.scene.mesh;
    let rates = relight_trace::raybench::rates_on(
        &context.bvh,
        &mesh.positions,
        &mesh.triangles,
        shadow_ray_target(&context.scene),
        rays,
        3,
        1,
    );
    (
        rates.diffuse_closest_hit * 1e6,
        rates.diffuse_occlusion * 1e6,
    )
}

/// The time `rays` alone take at the scene's `rates` (from
/// [`scene_ray_rates`]), with a report line.
pub fn ray_bound(rates: (f64, f64), rays: relight_trace::counters::RayCount) -> (f64, String) {
    let seconds =
        rays.closest_hit as f64 / rates.0.max(1.0) + rays.occlusion as f64 / rates.1.max(1.0);
    let line = format!(
        "rays            {:.1} M closest-hit + {:.1} M occlusion: {:.1} s at this scene's {:.2} / {:.2} Mrays/s (relight bench-rays' diffuse rays, {} threads)",
        rays.closest_hit as f64 / 1e6,
        rays.occlusion as f64 / 1e6,
        seconds,
        rates.0 / 1e6,
        rates.1 / 1e6,
        rayon::current_num_threads()
    );
    (seconds, line)
}
