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
    /// Frames of the timed orbit whose update was skipped (none while the
    /// lights move).
    pub skipped_frames: u32,
    /// The frames after the orbit, with the lights at rest.
    pub rest: Option<RestReport>,
    /// Under `--set update_budget=S` (S below 1): how far each budgeted
    /// frame's receiver light is from an unbudgeted twin's at the same
    /// lights.
    pub budget: Option<BudgetReport>,
    pub memory: Vec<(String, usize)>,
    pub memory_total_bytes: usize,
}

/// What the frames after the orbit cost, with the lights where the orbit
/// left them: first the camera still too, then the camera moving.
#[derive(Serialize)]
pub struct RestReport {
    /// Frames with the lights and the camera still, then as many with
    /// only the camera moving.
    pub frames_each: u32,
    /// Updates that ran once the lights stopped, before the technique
    /// settled (feedback techniques add a bounce an update): their cost
    /// is an engine's until the light stops changing.
    pub settling_updates: u32,
    pub settling_ms: f64,
    /// Whether the technique had settled by the last still frame.
    pub settled: bool,
    /// Frames of each half whose update was skipped.
    pub skipped_still: u32,
    pub skipped_camera_moving: u32,
    /// The update's time on the frames it skipped (median and 95th
    /// percentile over both halves).
    pub skipped: Option<StageReport>,
    /// The update's time on camera-moving frames it ran (view-dependent
    /// light), if any.
    pub camera_moving: Option<StageReport>,
}

/// The error an update budget costs, against the same technique without
/// one updated with the same frames (relative RMSE over every receiver's
/// indirect light, in per cent).
#[derive(Serialize)]
pub struct BudgetReport {
    /// The parameter as given.
    pub update_budget: String,
    /// Over the orbit's timed frames, lights moving every frame.
    pub moving_median_percent: f64,
    pub moving_p95_percent: f64,
    pub moving_worst_percent: f64,
    /// For scale: the unbudgeted light one frame late (the last frame's
    /// against this one's), median over the same frames. A budget whose
    /// error is below this costs less than one frame of latency.
    pub one_frame_late_median_percent: f64,
    /// After the orbit, per still frame (the first is the first update
    /// with the lights at rest).
    pub at_rest_percent: Vec<f64>,
    /// Still frames until the error is under 1 % and stays there (1: from
    /// the first), if it gets there.
    pub frames_to_one_percent: Option<u32>,
}

/// The twin a budget is measured against.
pub struct Unbudgeted {
    pub technique: Box<dyn Technique>,
    pub update_budget: String,
}

/// Per cent relative RMSE of the two techniques' receiver light.
fn budget_error(budgeted: &dyn Technique, unbudgeted: &dyn Technique) -> f64 {
    match (
        budgeted.receiver_irradiance(),
        unbudgeted.receiver_irradiance(),
    ) {
        (Some(values), Some(truth)) => {
            100.0 * relight_render::metrics::error_norms(values, truth).relative_rmse
        }
        _ => 0.0,
    }
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
            let hit = relight_render::render::visible_hit(context, &ray)?;
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
    /// Frames after the orbit with the lights at rest, then as many with
    /// only the camera moving (0: none).
    pub rest_frames: u32,
}

pub fn run(
    context: &SceneContext,
    technique: &mut dyn Technique,
    mut unbudgeted: Option<Unbudgeted>,
    settings: BenchSettings,
    progress: &dyn Progress,
) -> Result<BenchReport> {
    let BenchSettings {
        frames,
        shading_resolution,
        volume_cells,
        pause,
        rest_frames,
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
    let mut skipped_frames = 0;
    let mut moving_errors = Vec::new();
    let (mut late_errors, mut last_unbudgeted) = (Vec::new(), Vec::<Rgb>::new());
    progress.start("bench", (frames + WARM_UP_FRAMES + 2 * rest_frames) as u64);
    for index in 0..frames + WARM_UP_FRAMES {
        let lights = relight_engine::orbit(base, centre, index, frames);
        if !pause.is_zero() {
            std::thread::sleep(pause);
        }
        let frame = Frame {
            lights: &lights,
            index: index as u64,
            camera: None,
            moving_mesh_poses: None,
        };
        technique.update(&frame)?;
        progress.advance(1);
        let timings = technique.timings();
        if index == 0 {
            first_update = (timings.total().as_secs_f64() * 1e3, timings.feedback_passes);
        }
        // Untimed: the twin updates after the timings are read.
        if let Some(twin) = &mut unbudgeted {
            twin.technique.update(&frame)?;
            if index >= WARM_UP_FRAMES {
                moving_errors.push(budget_error(&*technique, &*twin.technique));
            }
            if let Some(values) = twin.technique.receiver_irradiance() {
                if index >= WARM_UP_FRAMES {
                    let late = relight_render::metrics::error_norms(&last_unbudgeted, values);
                    late_errors.push(100.0 * late.relative_rmse);
                }
                last_unbudgeted.clear();
                last_unbudgeted.extend_from_slice(values);
            }
        }
        let timings = technique.timings();
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
        skipped_frames += u32::from(timings.skipped);
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
    let last_lights = relight_engine::orbit(base, centre, frames + WARM_UP_FRAMES - 1, frames);
    let mut at_rest_errors = Vec::new();
    let rest = (rest_frames > 0)
        .then(|| {
            rest_frames_report(
                context,
                technique,
                match unbudgeted.as_mut() {
                    Some(twin) => Some(twin.technique.as_mut() as &mut dyn Technique),
                    None => None,
                },
                &mut at_rest_errors,
                &last_lights,
                frames,
                rest_frames,
                progress,
            )
        })
        .transpose()?;
    let budget = unbudgeted.map(|twin| {
        let mut sorted = moving_errors.clone();
        sorted.sort_by(f64::total_cmp);
        late_errors.sort_by(f64::total_cmp);
        let frames_to_one_percent = match at_rest_errors.iter().rposition(|&error| error >= 1.0) {
            None if at_rest_errors.is_empty() => None,
            None => Some(1),
            Some(last) if last + 1 < at_rest_errors.len() => Some(last as u32 + 2),
            Some(_) => None,
        };
        BudgetReport {
            update_budget: twin.update_budget,
            moving_median_percent: percentile(&sorted, 0.5),
            moving_p95_percent: percentile(&sorted, 0.95),
            moving_worst_percent: sorted.last().copied().unwrap_or(0.0),
            one_frame_late_median_percent: percentile(&late_errors, 0.5),
            at_rest_percent: at_rest_errors,
            frames_to_one_percent,
        }
    });
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
        skipped_frames,
        rest,
        budget,
        memory_total_bytes: memory.iter().map(|(_, bytes)| bytes).sum(),
        memory,
    })
}

/// Runs `rest_frames` frames with `lights` still and the scene's camera,
/// then as many turning the camera about its target, numbered on from the
/// orbit's last frame.
#[allow(clippy::too_many_arguments)]
fn rest_frames_report(
    context: &SceneContext,
    technique: &mut dyn Technique,
    mut unbudgeted: Option<&mut dyn Technique>,
    still_errors: &mut Vec<f64>,
    lights: &[Light],
    orbit_frames: u32,
    rest_frames: u32,
    progress: &dyn Progress,
) -> Result<RestReport> {
    let mut report = RestReport {
        frames_each: rest_frames,
        settling_updates: 0,
        settling_ms: 0.0,
        settled: false,
        skipped_still: 0,
        skipped_camera_moving: 0,
        skipped: None,
        camera_moving: None,
    };
    let (mut skipped, mut camera_moving) = (Vec::new(), Vec::new());
    let scene_camera = &context.scene.camera;
    let mut camera = scene_camera.clone();
    let mut settling = true;
    for rest_index in 0..2 * rest_frames {
        let moving_camera = rest_index >= rest_frames;
        if moving_camera {
            // A tenth of a turn about the target over the half.
            let angle = 0.1 * std::f32::consts::TAU * (rest_index - rest_frames + 1) as f32
                / rest_frames as f32;
            let turn = glam::Quat::from_rotation_y(angle);
            camera.eye = scene_camera.target + turn * (scene_camera.eye - scene_camera.target);
        }
        let frame = Frame {
            lights,
            index: u64::from(orbit_frames + WARM_UP_FRAMES + rest_index),
            // The orbit's frames give no camera (the scene's): so do the
            // still ones.
            camera: moving_camera.then_some(&camera),
            moving_mesh_poses: None,
        };
        let start = std::time::Instant::now();
        technique.update(&frame)?;
        let elapsed_ms = start.elapsed().as_secs_f64() * 1e3;
        progress.advance(1);
        if let Some(twin) = unbudgeted.as_deref_mut() {
            twin.update(&frame)?;
            if !moving_camera {
                still_errors.push(budget_error(&*technique, &*twin));
            }
        }
        let timings = technique.timings();
        if timings.skipped {
            settling = false;
            skipped.push(elapsed_ms);
            match moving_camera {
                true => report.skipped_camera_moving += 1,
                false => report.skipped_still += 1,
            }
        } else if moving_camera {
            camera_moving.push(elapsed_ms);
        } else if settling {
            report.settling_updates += 1;
            report.settling_ms += elapsed_ms;
        }
        if rest_index + 1 == rest_frames {
            report.settled = technique.settled();
        }
    }
    report.skipped = (!skipped.is_empty()).then(|| stage_report("skipped update", skipped));
    report.camera_moving =
        (!camera_moving.is_empty()).then(|| stage_report("camera-moving update", camera_moving));
    Ok(report)
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
        if self.skipped_frames > 0 {
            writeln!(f, "{} of the timed frames skipped", self.skipped_frames)?;
        }
        if let Some(rest) = &self.rest {
            writeln!(f, "{rest}")?;
        }
        if let Some(budget) = &self.budget {
            writeln!(f, "{budget}")?;
        }
        writeln!(f, "{:<28} {:>12}", "buffer", "bytes")?;
        for (buffer, bytes) in &self.memory {
            writeln!(f, "{buffer:<28} {bytes:>12}")?;
        }
        write!(f, "{:<28} {:>12}", "memory total", self.memory_total_bytes)
    }
}

impl fmt::Display for RestReport {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        writeln!(
            f,
            "lights at rest, {} frames still then {} with the camera moving:",
            self.frames_each, self.frames_each
        )?;
        writeln!(
            f,
            "  {} updates ran before the light settled ({:.1} ms in all){}",
            self.settling_updates,
            self.settling_ms,
            if self.settled {
                ""
            } else {
                "; still unsettled at the last still frame"
            }
        )?;
        write!(
            f,
            "  skipped: {} of the still frames, {} of the camera-moving ones",
            self.skipped_still, self.skipped_camera_moving
        )?;
        for stage in [&self.skipped, &self.camera_moving].into_iter().flatten() {
            write!(
                f,
                "\n  {:<26} {:>12.4} {:>12.4}   (median, p95 ms)",
                stage.stage, stage.median_ms, stage.p95_ms
            )?;
        }
        Ok(())
    }
}

impl fmt::Display for BudgetReport {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        writeln!(
            f,
            "update_budget={} against an unbudgeted twin (relative RMSE of the receivers' light):",
            self.update_budget
        )?;
        writeln!(
            f,
            "  lights moving: median {:.2} %, p95 {:.2} %, worst {:.2} % (unbudgeted one frame late: median {:.2} %)",
            self.moving_median_percent,
            self.moving_p95_percent,
            self.moving_worst_percent,
            self.one_frame_late_median_percent
        )?;
        let curve: Vec<String> = self
            .at_rest_percent
            .iter()
            .map(|error| format!("{error:.2}"))
            .collect();
        write!(
            f,
            "  lights at rest, per still frame: {} %",
            curve.join(" ")
        )?;
        match self.frames_to_one_percent {
            Some(frames) => write!(f, "\n  under 1 % from still frame {frames} on"),
            None if self.at_rest_percent.is_empty() => Ok(()),
            None => write!(f, "\n  not under 1 % by the last still frame"),
        }
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
