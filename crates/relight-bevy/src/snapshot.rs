//! A headless render of a relight scene through Bevy: the bridge's test.
//!
//! No window: Bevy renders the scene camera into an RGBA16F image (HDR, no
//! tone mapping, the exposure at which Bevy's output equals relight's
//! radiance), driven frame by frame on this thread, and reads it back with
//! Bevy's screenshot. On a machine without a GPU it runs on Mesa's software
//! Vulkan (lavapipe).

use crate::runtime::{RelightContext, RelightLight, RelightScene, RelightStats, RelightStatus};
use crate::{convert, RelightPlugin};
use bevy::camera::RenderTarget;
use bevy::core_pipeline::tonemapping::Tonemapping;
use bevy::prelude::*;
use bevy::render::render_resource::{PollType, TextureFormat, TextureUsages};
use bevy::render::renderer::RenderDevice;
use bevy::render::view::screenshot::{Screenshot, ScreenshotCaptured};
use bevy::render::RenderPlugin;
use bevy::window::ExitCondition;
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

/// What to render.
#[derive(Clone, Debug)]
pub struct SnapshotSettings {
    pub scene: RelightScene,
    /// GI updates shown before the picture is taken, at most: it is taken
    /// as soon as the light has settled ([`RelightStats::settled`]), since
    /// a resting scene's updates stop there.
    pub gi_updates: u64,
    /// Image size; `None`: the scene camera's resolution.
    pub size: Option<[u32; 2]>,
    /// Loading and rendering together may take at most this long.
    pub timeout: Duration,
}

/// Linear RGB pixels, rows from the top.
#[derive(Clone, Debug)]
pub struct Snapshot {
    pub width: u32,
    pub height: u32,
    pub pixels: Vec<[f32; 3]>,
    /// The last GI update's stages on the worker (ms).
    pub stages: Vec<(String, f64)>,
}

#[derive(Resource, Default, Clone)]
struct Captured(Arc<Mutex<Option<Image>>>);

/// Renders `settings.scene` through Bevy with relight's GI. With
/// `indirect_only` the scene's Bevy lights are hidden (Bevy draws no
/// direct light; relight still reads them) and the lightmap holds indirect
/// light only.
///
/// With [`RelightScene::adopt`] Bevy loads the scene's glTF itself (the
/// file, or the scene file's mesh) and the plugin adopts it.
pub fn render_snapshot(settings: &SnapshotSettings) -> Result<Snapshot, String> {
    let gltf = settings
        .scene
        .adopt
        .then(|| crate::gltf_to_adopt(&settings.scene.path))
        .transpose()?;
    let mut app = headless_app(gltf.as_ref().and_then(|path| path.parent()));
    let scene_entity = app.world_mut().spawn(settings.scene.clone()).id();
    if let Some(path) = &gltf {
        let file = path
            .file_name()
            .ok_or_else(|| format!("{}: not a file", path.display()))?
            .to_string_lossy()
            .into_owned();
        let world = app.world_mut();
        let handle = world
            .resource::<AssetServer>()
            .load(GltfAssetLabel::Scene(0).from_asset(file));
        world
            .entity_mut(scene_entity)
            .insert(WorldAssetRoot(handle));
    }
    let captured = app.world().resource::<Captured>().clone();
    let started = Instant::now();
    let mut camera_spawned = false;
    let mut screenshot_at: Option<u64> = None;
    let mut frames_after_screenshot = 0;
    loop {
        if started.elapsed() > settings.timeout {
            return Err(format!(
                "no snapshot after {} s",
                settings.timeout.as_secs()
            ));
        }
        update_and_wait(&mut app)?;
        if let Some(image) = captured.0.lock().unwrap().take() {
            let stats = app.world().get::<RelightStats>(scene_entity).cloned();
            return to_snapshot(image, stats.map(|stats| stats.stages).unwrap_or_default());
        }
        let world = app.world_mut();
        let status = world.get::<RelightStatus>(scene_entity).cloned();
        match status {
            Some(RelightStatus::Failed(message)) => return Err(message),
            Some(RelightStatus::Running) => {}
            _ => {
                std::thread::sleep(Duration::from_millis(20));
                continue;
            }
        }
        if settings.scene.indirect_only {
            let mut lights = world.query_filtered::<&mut Visibility, With<RelightLight>>();
            for mut visibility in lights.iter_mut(world) {
                *visibility = Visibility::Hidden;
            }
        }
        let stats = world
            .get::<RelightStats>(scene_entity)
            .cloned()
            .unwrap_or_default();
        if !camera_spawned {
            let camera = stats.camera.clone().unwrap_or_default();
            let [width, height] = settings.size.unwrap_or(camera.resolution);
            let mut target =
                Image::new_target_texture(width, height, TextureFormat::Rgba16Float, None);
            target.texture_descriptor.usage |= TextureUsages::COPY_SRC;
            let handle = world.resource_mut::<Assets<Image>>().add(target);
            let (transform, mut projection) = convert::camera(&camera);
            if let Projection::Perspective(perspective) = &mut projection {
                perspective.aspect_ratio = width as f32 / height as f32;
            }
            world.spawn((
                Camera3d::default(),
                RenderTarget::Image(handle.clone().into()),
                bevy::camera::Hdr,
                Tonemapping::None,
                crate::matching_exposure(),
                transform,
                projection,
                SnapshotTarget(handle),
            ));
            camera_spawned = true;
            continue;
        }
        // Two frames after the update arrives: the image upload and a
        // render with it.
        let ready = stats.updates >= settings.gi_updates || (stats.updates > 0 && stats.settled);
        if ready && screenshot_at.is_none() {
            screenshot_at = Some(stats.updates);
            frames_after_screenshot = 0;
        }
        if screenshot_at.is_some() {
            frames_after_screenshot += 1;
            if frames_after_screenshot == 3 {
                let handle = world
                    .query::<&SnapshotTarget>()
                    .iter(world)
                    .next()
                    .map(|target| target.0.clone())
                    .ok_or("the snapshot camera disappeared")?;
                let slot = captured.0.clone();
                world.spawn(Screenshot::image(handle)).observe(
                    move |event: On<ScreenshotCaptured>| {
                        *slot.lock().unwrap() = Some(event.image.clone());
                    },
                );
            }
        }
    }
}

#[derive(Component)]
struct SnapshotTarget(Handle<Image>);

fn to_snapshot(image: Image, stages: Vec<(String, f64)>) -> Result<Snapshot, String> {
    let (width, height) = (image.width(), image.height());
    let data = image.data.as_ref().ok_or("the screenshot has no pixels")?;
    let pixels = match image.texture_descriptor.format {
        TextureFormat::Rgba16Float => data
            .chunks_exact(8)
            .map(|texel| {
                let channel =
                    |i: usize| half::f16::from_le_bytes([texel[2 * i], texel[2 * i + 1]]).to_f32();
                [channel(0), channel(1), channel(2)]
            })
            .collect(),
        TextureFormat::Rgba32Float => data
            .chunks_exact(16)
            .map(|texel| {
                let channel =
                    |i: usize| f32::from_le_bytes(texel[4 * i..4 * i + 4].try_into().unwrap());
                [channel(0), channel(1), channel(2)]
            })
            .collect(),
        other => {
            return Err(format!(
                "the screenshot came back as {other:?}, not a float format"
            ))
        }
    };
    Ok(Snapshot {
        width,
        height,
        pixels,
        stages,
    })
}

/// A windowless Bevy app with relight's plugin, rendering on this thread
/// (no pipelined rendering), no ambient light and a black background;
/// assets come from `asset_folder` (default: Bevy's).
fn headless_app(asset_folder: Option<&std::path::Path>) -> App {
    let mut app = App::new();
    let assets = match asset_folder {
        Some(folder) => AssetPlugin {
            file_path: folder.display().to_string(),
            ..default()
        },
        None => AssetPlugin::default(),
    };
    app.add_plugins(
        DefaultPlugins
            .set(assets)
            .set(WindowPlugin {
                primary_window: None,
                exit_condition: ExitCondition::DontExit,
                ..default()
            })
            .set(RenderPlugin {
                // Every pipeline ready in the frame that first needs it.
                synchronous_pipeline_compilation: true,
                ..default()
            })
            .disable::<bevy::winit::WinitPlugin>()
            .disable::<bevy::render::pipelined_rendering::PipelinedRenderingPlugin>()
            .disable::<bevy::log::LogPlugin>(),
    )
    .add_plugins(RelightPlugin)
    .insert_resource(GlobalAmbientLight::NONE)
    .insert_resource(ClearColor(Color::BLACK))
    .init_resource::<Captured>();
    app.finish();
    app.cleanup();
    app
}

/// One frame, main and render world, and the GPU's work finished.
fn update_and_wait(app: &mut App) -> Result<(), String> {
    app.update();
    app.world()
        .resource::<RenderDevice>()
        .wgpu_device()
        .poll(PollType::Wait {
            submission_index: None,
            timeout: None,
        })
        .map(|_| ())
        .map_err(|error| format!("the GPU device failed: {error}"))
}

/// What the plugin cost over a run of frames: the main thread's exchange
/// every frame, and each GI update's stages on the worker.
#[derive(Clone, Debug, Default)]
pub struct BridgeRun {
    /// Main-thread milliseconds of the exchange, one a frame.
    pub bridge_ms: Vec<f64>,
    /// The stages of each GI update shown (ms on the worker).
    pub updates: Vec<Vec<(String, f64)>>,
    /// Frames between reading the lights and showing their light, one a
    /// frame.
    pub gi_age_frames: Vec<u64>,
    /// Wall time of each frame's main and render world (Bevy's own work
    /// plus the bridge), ms: on a machine without a GPU the render world
    /// rasterises on the CPU (lavapipe), on the cores the worker uses.
    pub frame_ms: Vec<f64>,
}

/// How [`run_bridge`] runs the app.
#[derive(Clone, Debug)]
pub struct BridgeSettings {
    /// GI updates shown before measuring.
    pub warm_up: u64,
    /// GI updates measured.
    pub gi_updates: u64,
    /// Frames start this far apart (an app synchronised to its display,
    /// whose main thread waits between frames); `Duration::ZERO` runs them
    /// back to back.
    pub frame_interval: Duration,
    pub timeout: Duration,
    /// Run every Bevy schedule, main and render world, on the main thread
    /// (Bevy's `SingleThreadedExecutor`) instead of dispatching systems to
    /// the task pools: an app's choice that leaves the worker's threads
    /// fewer wake-ups to be preempted by on few cores.
    pub single_threaded_schedules: bool,
}

/// Runs `scene` headless (no camera: what the bridge costs does not
/// depend on what is drawn) until `gi_updates` updates are shown after
/// `warm_up` of them, moving its lights every frame along `relight
/// bench`'s orbit (a turn every `2 gi_updates` frames) so that each update
/// has new lights in the places `relight bench` puts them.
pub fn run_bridge(scene: &RelightScene, settings: &BridgeSettings) -> Result<BridgeRun, String> {
    let BridgeSettings {
        warm_up,
        gi_updates,
        frame_interval,
        timeout,
        single_threaded_schedules,
    } = settings.clone();
    let mut app = headless_app(None);
    if single_threaded_schedules {
        use bevy::ecs::schedule::{Schedules, SingleThreadedExecutor};
        let single_threaded = |world: &mut World| {
            for (_, schedule) in world.resource_mut::<Schedules>().iter_mut() {
                schedule.set_executor(SingleThreadedExecutor::new());
            }
        };
        single_threaded(app.world_mut());
        single_threaded(app.sub_app_mut(bevy::render::RenderApp).world_mut());
    }
    let scene_entity = app.world_mut().spawn(scene.clone()).id();
    let started = Instant::now();
    let mut run = BridgeRun::default();
    let mut last_updates = 0;
    let mut next_frame = Instant::now();
    let mut orbit_centre = None;
    let mut frames_moved = 0u32;
    loop {
        if started.elapsed() > timeout {
            return Err(format!(
                "{} GI updates took over {} s",
                gi_updates,
                timeout.as_secs()
            ));
        }
        let now = Instant::now();
        if next_frame > now {
            std::thread::sleep(next_frame - now);
        }
        next_frame = Instant::now() + frame_interval;
        let frame_start = Instant::now();
        // No wait for the GPU, as in an app: the frame's time is Bevy's
        // own work and submission, not the software rasteriser's.
        app.update();
        let frame_ms = frame_start.elapsed().as_secs_f64() * 1e3;
        let world = app.world_mut();
        match world.get::<RelightStatus>(scene_entity).cloned() {
            Some(RelightStatus::Failed(message)) => return Err(message),
            Some(RelightStatus::Running) => {}
            _ => {
                std::thread::sleep(Duration::from_millis(20));
                continue;
            }
        }
        let stats = world
            .get::<RelightStats>(scene_entity)
            .cloned()
            .unwrap_or_default();
        // The lights move every frame, as an app moves them, along
        // `relight bench`'s orbit: a turn over about as many updates as
        // are measured (an update takes about two frames), so both time
        // lights in the same places.
        if let Some(context) = world.get::<RelightContext>(scene_entity).cloned() {
            let scene = &context.0.scene;
            let centre = *orbit_centre.get_or_insert_with(|| {
                let (lo, hi) = scene.mesh.bounds();
                (lo + hi) * 0.5
            });
            let period = u32::try_from(gi_updates.saturating_mul(2)).unwrap_or(u32::MAX);
            frames_moved += 1;
            let step = frames_moved;
            let orbiting = relight_engine::orbit(&scene.lights, centre, step, period);
            let mut lights = world.query::<(&RelightLight, &mut Transform)>();
            for (marker, mut transform) in lights.iter_mut(world) {
                if let Some(light) = orbiting.get(marker.0) {
                    *transform = crate::convert::light_transform(light);
                }
            }
        }
        if stats.updates <= warm_up {
            last_updates = stats.updates;
            continue;
        }
        run.bridge_ms.push(stats.bridge_ms);
        run.frame_ms.push(frame_ms);
        run.gi_age_frames.push(stats.gi_age_frames);
        if stats.updates != last_updates {
            last_updates = stats.updates;
            run.updates.push(stats.stages.clone());
        }
        if run.updates.len() as u64 >= gi_updates {
            return Ok(run);
        }
    }
}
