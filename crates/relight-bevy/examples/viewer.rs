//! An interactive window on a relight scene: Bevy draws it with shadow
//! maps, relight adds indirect light as the lights move.
//!
//! cargo run --release -p relight-bevy --features viewer --example viewer -- SCENE.toml \
//!     [--technique T] [--bake F] [--adopt]
//!
//! With --adopt, Bevy's glTF loader loads the scene's glTF (the file, or
//! the scene file's mesh) with its own materials and textures, and the
//! plugin adopts it (`RelightScene::adopt_gltf`).
//!
//! Keys: WASD, Q/E and the mouse (left button held) fly the camera;
//! arrows move the point and spot lights around the scene's centre (left,
//! right) and up and down; the right mouse button dragged turns the sun;
//! 1-4 switch technique (PIC, SRP, PRM, LightSkin; bakes in memory unless
//! --bake fits), 0 shows direct light only; R shows relight's path-traced
//! reference of the current view instead, refined pass by pass while the
//! camera and the lights rest (a quarter of the window's resolution, all
//! bounces; both views use Reinhard tone mapping, so they compare
//! directly). The panel shows frames a second, the GI update's stages on
//! the worker, its memory, the bridge's main-thread time and the GI's age
//! in frames. The scene file's moving meshes ([[dynamic]]) go back and
//! forth along their scripted motion (M pauses them, as does the
//! reference view); LightSkin moves them through its maps.

use bevy::asset::RenderAssetUsages;
use bevy::camera_controller::free_camera::{FreeCamera, FreeCameraPlugin};
use bevy::core_pipeline::tonemapping::Tonemapping;
use bevy::diagnostic::{DiagnosticsStore, FrameTimeDiagnosticsPlugin};
use bevy::input::mouse::AccumulatedMouseMotion;
use bevy::prelude::*;
use bevy::render::render_resource::{Extent3d, TextureDimension, TextureFormat};
use clap::Parser;
use relight_bevy::{
    RelightContext, RelightLight, RelightLights, RelightMovingMeshes, RelightPlugin, RelightScene,
    RelightStats, RelightStatus,
};
use relight_scene::Light;
use relight_technique::SceneContext;
use std::path::PathBuf;
use std::sync::mpsc::{channel, Receiver};
use std::sync::{Arc, Mutex};

#[derive(Parser, Resource, Clone)]
struct Args {
    scene: PathBuf,
    #[arg(long, short, default_value = "lightskin")]
    technique: String,
    #[arg(long)]
    bake: Option<PathBuf>,
    /// Window size, WIDTHxHEIGHT.
    #[arg(long, default_value = "1280x720")]
    size: String,
    /// Save a screenshot to this PNG once the GI has run this many
    /// updates, then quit (for documentation).
    #[arg(long)]
    screenshot: Option<PathBuf>,
    #[arg(long, default_value_t = 10)]
    screenshot_after: u64,
    /// Start with the reference view on (R); a --screenshot then waits
    /// for --screenshot-after passes of it.
    #[arg(long)]
    reference: bool,
    /// Bevy loads the scene's glTF itself and relight adopts it.
    #[arg(long)]
    adopt: bool,
}

#[derive(Component)]
struct Panel;

#[derive(Component)]
struct ViewerCamera {
    placed: bool,
}

fn main() -> AppExit {
    let args = Args::parse();
    // Adoption: Bevy's asset server reads the glTF from its folder.
    let assets = match args.adopt.then(|| relight_bevy::gltf_to_adopt(&args.scene)) {
        Some(Ok(gltf)) => AssetPlugin {
            file_path: gltf.parent().unwrap_or(&gltf).display().to_string(),
            ..default()
        },
        Some(Err(message)) => {
            eprintln!("error: {message}");
            return AppExit::error();
        }
        None => AssetPlugin::default(),
    };
    let (width, height) = args
        .size
        .split_once('x')
        .and_then(|(w, h)| Some((w.parse::<u32>().ok()?, h.parse::<u32>().ok()?)))
        .unwrap_or((1280, 720));
    App::new()
        .add_plugins((
            DefaultPlugins.set(assets).set(WindowPlugin {
                primary_window: Some(Window {
                    title: "relight viewer".into(),
                    resolution: (width, height).into(),
                    ..default()
                }),
                ..default()
            }),
            RelightPlugin,
            FreeCameraPlugin,
            FrameTimeDiagnosticsPlugin::default(),
        ))
        .insert_resource(GlobalAmbientLight::NONE)
        .insert_resource(args.clone())
        .insert_resource(Reference {
            on: args.reference,
            ..default()
        })
        .add_systems(Startup, setup)
        .add_systems(
            Update,
            (
                place_camera,
                move_lights,
                switch_technique,
                update_panel,
                reference_view,
                animate_moving_meshes,
                screenshot,
            ),
        )
        .run()
}

/// Spawns the scene with `technique`, and with --adopt the glTF Bevy
/// loads for it.
fn spawn_scene(commands: &mut Commands, assets: &AssetServer, args: &Args, technique: &str) {
    let mut scene = RelightScene::new(&args.scene).technique(technique);
    if technique == args.technique {
        scene.bake = args.bake.clone();
    }
    let gltf = args
        .adopt
        .then(|| relight_bevy::gltf_to_adopt(&args.scene).ok())
        .flatten();
    match gltf.as_ref().and_then(|gltf| gltf.file_name()) {
        Some(file) => commands.spawn((
            scene.adopt_gltf(),
            WorldAssetRoot(
                assets
                    .load(GltfAssetLabel::Scene(0).from_asset(file.to_string_lossy().into_owned())),
            ),
        )),
        None => commands.spawn(scene),
    };
}

fn setup(mut commands: Commands, args: Res<Args>, assets: Res<AssetServer>) {
    spawn_scene(&mut commands, &assets, &args, &args.technique);
    commands.spawn((
        ReferenceOverlay,
        ImageNode::default(),
        // Under the panel.
        ZIndex(-1),
        Node {
            position_type: PositionType::Absolute,
            width: percent(100),
            height: percent(100),
            ..default()
        },
        Visibility::Hidden,
    ));
    commands.spawn((
        Camera3d::default(),
        bevy::camera::Hdr,
        // The reference view applies the same curve to its pixels.
        Tonemapping::Reinhard,
        relight_bevy::matching_exposure(),
        FreeCamera {
            walk_speed: 2.0,
            run_speed: 8.0,
            ..default()
        },
        ViewerCamera { placed: false },
    ));
    commands.spawn((
        Panel,
        Text::new("loading"),
        TextFont {
            font_size: FontSize::Px(14.0),
            ..default()
        },
        Node {
            position_type: PositionType::Absolute,
            top: px(8),
            left: px(8),
            ..default()
        },
        BackgroundColor(Color::srgba(0.0, 0.0, 0.0, 0.6)),
    ));
}

/// Puts the camera where the scene file's camera is, once loaded.
fn place_camera(
    scenes: Query<&RelightStats>,
    mut cameras: Query<(&mut Transform, &mut Projection, &mut ViewerCamera)>,
) {
    let Some(camera) = scenes.iter().find_map(|stats| stats.camera.clone()) else {
        return;
    };
    for (mut transform, mut projection, mut viewer) in &mut cameras {
        if viewer.placed {
            continue;
        }
        let v = |value: relight_core::Vec3| Vec3::from_array(value.to_array());
        *transform =
            Transform::from_translation(v(camera.eye)).looking_at(v(camera.target), v(camera.up));
        if let Projection::Perspective(perspective) = projection.as_mut() {
            perspective.fov = camera.fov_y_degrees.to_radians();
        }
        viewer.placed = true;
    }
}

/// Arrows orbit and lift the point and spot lights; the right mouse
/// button turns directional lights.
fn move_lights(
    keys: Res<ButtonInput<KeyCode>>,
    buttons: Res<ButtonInput<MouseButton>>,
    motion: Res<AccumulatedMouseMotion>,
    time: Res<Time>,
    mut lights: Query<(&mut Transform, Has<DirectionalLight>), With<RelightLight>>,
) {
    let step = time.delta_secs();
    let mut yaw = 0.0;
    let mut lift = 0.0;
    if keys.pressed(KeyCode::ArrowLeft) {
        yaw += step;
    }
    if keys.pressed(KeyCode::ArrowRight) {
        yaw -= step;
    }
    if keys.pressed(KeyCode::ArrowUp) {
        lift += step * 2.0;
    }
    if keys.pressed(KeyCode::ArrowDown) {
        lift -= step * 2.0;
    }
    let drag = if buttons.pressed(MouseButton::Right) {
        motion.delta * 0.005
    } else {
        Vec2::ZERO
    };
    for (mut transform, directional) in &mut lights {
        if directional {
            transform.rotate_y(-drag.x);
            transform.rotate_local_x(-drag.y);
        } else {
            transform.rotate_around(Vec3::ZERO, Quat::from_rotation_y(yaw));
            transform.translation.y += lift;
        }
    }
}

/// 1-4: PIC, SRP, PRM, LightSkin; 0: direct light only.
fn switch_technique(
    mut commands: Commands,
    keys: Res<ButtonInput<KeyCode>>,
    args: Res<Args>,
    assets: Res<AssetServer>,
    scenes: Query<(Entity, &RelightScene)>,
) {
    let choice = [
        (KeyCode::Digit1, "pic"),
        (KeyCode::Digit2, "srp"),
        (KeyCode::Digit3, "prm"),
        (KeyCode::Digit4, "lightskin"),
        (KeyCode::Digit0, "direct"),
    ]
    .into_iter()
    .find(|(key, _)| keys.just_pressed(*key));
    let Some((_, technique)) = choice else {
        return;
    };
    for (entity, scene) in &scenes {
        if scene.technique == technique {
            return;
        }
        commands.entity(entity).despawn();
    }
    spawn_scene(&mut commands, &assets, &args, technique);
}

fn update_panel(
    reference: Res<Reference>,
    scenes: Query<(&RelightScene, &RelightStatus, &RelightStats)>,
    diagnostics: Res<DiagnosticsStore>,
    mut panel: Query<&mut Text, With<Panel>>,
) {
    let fps = diagnostics
        .get(&FrameTimeDiagnosticsPlugin::FPS)
        .and_then(|fps| fps.smoothed())
        .unwrap_or(0.0);
    let mut text = format!("{fps:.0} frames/s\n");
    for (scene, status, stats) in &scenes {
        text.push_str(&format!("technique {}\n", scene.technique));
        match status {
            RelightStatus::Loading { stage, fraction } => {
                text.push_str(&format!("{stage}: {:.0} %\n", fraction * 100.0));
            }
            RelightStatus::Failed(message) => text.push_str(&format!("failed: {message}\n")),
            RelightStatus::Running => {
                let total: f64 = stats.stages.iter().map(|(_, ms)| ms).sum();
                text.push_str(&format!(
                    "GI age {} frames, {} updates\nbridge {:.3} ms (main thread)\nworker {:.1} ms:\n",
                    stats.gi_age_frames, stats.updates, stats.bridge_ms, total
                ));
                for (stage, ms) in &stats.stages {
                    text.push_str(&format!("  {stage} {ms:.2} ms\n"));
                }
                text.push_str(&format!(
                    "memory {:.1} MB\n",
                    stats.memory_bytes as f64 / 1e6
                ));
            }
        }
    }
    if reference.on {
        text.push_str(&format!(
            "reference view: {} passes of {REFERENCE_SPP} paths a pixel{}\n",
            reference.passes,
            if reference.passes == 0 {
                " (waiting for the camera and lights to rest)"
            } else {
                ""
            }
        ));
    }
    text.push_str("\nWASD/QE + left mouse: fly   arrows: lights   right drag: sun\n1 PIC  2 SRP  3 PRM  4 LightSkin  0 direct only   R reference   M moving meshes");
    for mut panel in &mut panel {
        **panel = text.clone();
    }
}

/// Script frames the moving meshes have run, unless paused.
#[derive(Default)]
struct MotionClock {
    frames: f32,
    paused: bool,
}

/// Moves the scene file's moving meshes like an app moves any entity:
/// along their scripted velocity and spin, 10 script frames a second,
/// back and forth over the first 8 (the shipped sequence's box crosses
/// the room in about that many). M pauses them, and so does the reference
/// view, which needs the scene to rest.
fn animate_moving_meshes(
    keys: Res<ButtonInput<KeyCode>>,
    time: Res<Time>,
    mut clock: Local<MotionClock>,
    scenes: Query<&RelightContext>,
    mut meshes: Query<(&relight_bevy::RelightMovingMesh, &mut Transform)>,
    mut scripts: Local<Option<Vec<relight_engine::MovingMesh>>>,
    reference: Res<Reference>,
) {
    if keys.just_pressed(KeyCode::KeyM) {
        clock.paused = !clock.paused;
    }
    if clock.paused || reference.on {
        return;
    }
    let Some(context) = scenes.iter().next() else {
        return;
    };
    let scripts = scripts
        .get_or_insert_with(|| relight_engine::moving_meshes(&context.0.scene).unwrap_or_default());
    clock.frames += time.delta_secs() * 10.0;
    let frame = 8.0 - (clock.frames.rem_euclid(16.0) - 8.0).abs();
    for (marker, mut transform) in &mut meshes {
        let Some(script) = scripts.get(marker.index) else {
            continue;
        };
        let pose = relight_core::Mat4::from(script.pose_between_frames(frame));
        *transform = Transform::from_matrix(Mat4::from_cols_array(&pose.to_cols_array()));
    }
}

/// Paths a pixel in each pass of the reference view.
const REFERENCE_SPP: u32 = 2;
/// Frames the camera and lights must rest before the reference starts.
const REFERENCE_REST_FRAMES: u32 = 5;

#[derive(Component)]
struct ReferenceOverlay;

/// A traced pass: the view generation it was traced for, its pixels, and
/// the scene it traced.
type Pass = (u64, Vec<relight_core::Rgb>, Arc<SceneContext>);

/// The progressive reference: the sum of the passes so far for the view
/// and lights they were traced with.
#[derive(Resource, Default)]
struct Reference {
    on: bool,
    /// Camera, lights and moving meshes' poses the passes were traced for.
    view: Option<(Transform, Vec<Light>, Vec<relight_core::Affine3A>)>,
    resting_frames: u32,
    sum: Vec<[f64; 3]>,
    passes: u32,
    size: (u32, u32),
    in_flight: Option<Mutex<Receiver<Pass>>>,
    /// Bumped when the view changes, so a pass traced for the old view is
    /// dropped.
    generation: u64,
    image: Option<Handle<Image>>,
    /// The scene's moving meshes, read once per loaded scene.
    moving_meshes: Option<(Arc<SceneContext>, Arc<Vec<relight_engine::MovingMesh>>)>,
    /// The scene traced for this view, with the moving meshes in place
    /// (its BVH built by the first pass, reused by the rest).
    traced: Option<Arc<SceneContext>>,
}

/// R toggles relight's path-traced reference of the current view: a pass
/// of REFERENCE_SPP paths a pixel at a time on a thread, averaged into
/// the overlay, started again whenever the camera or a light moves.
#[allow(clippy::too_many_arguments)]
fn reference_view(
    keys: Res<ButtonInput<KeyCode>>,
    mut reference: ResMut<Reference>,
    scenes: Query<(Entity, &GlobalTransform, &RelightContext)>,
    cameras: Query<(&Transform, &GlobalTransform, &Projection), With<ViewerCamera>>,
    lights: RelightLights,
    moving_meshes: RelightMovingMeshes,
    windows: Query<&Window>,
    mut overlay: Query<(&mut ImageNode, &mut Visibility), With<ReferenceOverlay>>,
    mut images: ResMut<Assets<Image>>,
) {
    if keys.just_pressed(KeyCode::KeyR) {
        reference.on = !reference.on;
        reference.view = None;
    }
    let Ok((mut node, mut visibility)) = overlay.single_mut() else {
        return;
    };
    let (Some((scene, scene_transform, context)), Ok((transform, global, projection))) =
        (scenes.iter().next(), cameras.single())
    else {
        return;
    };
    if !reference.on {
        *visibility = Visibility::Hidden;
        return;
    }
    let current = relight_bevy::relight_lights(&lights, scene_transform);
    let mut poses = vec![relight_core::Affine3A::IDENTITY; moving_meshes.iter().len()];
    relight_bevy::read_moving_mesh_poses(&moving_meshes, scene, scene_transform, &mut poses);
    let view = (*transform, current, poses);
    if reference.view.as_ref() != Some(&view) {
        let window = windows.iter().next().map_or((1280, 720), |window| {
            (window.physical_width(), window.physical_height())
        });
        let size = ((window.0 / 4).max(16), (window.1 / 4).max(16));
        reference.view = Some(view);
        reference.resting_frames = 0;
        reference.passes = 0;
        reference.size = size;
        reference.sum = vec![[0.0; 3]; (size.0 * size.1) as usize];
        reference.generation += 1;
        reference.in_flight = None;
        reference.traced = None;
        *visibility = Visibility::Hidden;
        return;
    }
    reference.resting_frames += 1;
    if let Some(receiver) = &reference.in_flight {
        let finished = receiver.lock().unwrap().try_recv();
        if let Ok((generation, pixels, traced)) = finished {
            reference.in_flight = None;
            if generation == reference.generation {
                reference.traced = Some(traced);
                for (sum, pixel) in reference.sum.iter_mut().zip(&pixels) {
                    for channel in 0..3 {
                        sum[channel] += f64::from(pixel[channel]);
                    }
                }
                reference.passes += 1;
                let image = reference_image(&reference);
                let handle = match reference.image.clone() {
                    Some(handle) => {
                        let _ = images.insert(&handle, image);
                        handle
                    }
                    None => images.add(image),
                };
                reference.image = Some(handle.clone());
                node.image = handle;
                *visibility = Visibility::Visible;
            }
        }
    }
    if reference.in_flight.is_none() && reference.resting_frames >= REFERENCE_REST_FRAMES {
        let (sender, receiver) = channel();
        let context = context.0.clone();
        let meshes = match &reference.moving_meshes {
            Some((loaded, meshes)) if Arc::ptr_eq(loaded, &context) => meshes.clone(),
            _ => {
                let meshes =
                    Arc::new(relight_engine::moving_meshes(&context.scene).unwrap_or_default());
                reference.moving_meshes = Some((context.clone(), meshes.clone()));
                meshes
            }
        };
        let traced = reference.traced.clone();
        let (_, lights, poses) = reference.view.clone().unwrap();
        let mut camera = relight_bevy::relight_camera(global, projection);
        camera.resolution = [reference.size.0, reference.size.1];
        let generation = reference.generation;
        let settings = relight_trace::path::PathSettings {
            seed: u64::from(reference.passes) + 1,
            ..Default::default()
        };
        std::thread::spawn(move || {
            // The moving meshes where they are now, in the traced scene.
            let traced = traced.unwrap_or_else(|| {
                if meshes.is_empty() || meshes.len() != poses.len() {
                    return context;
                }
                let world = relight_engine::MovingWorld::place(&meshes, &poses);
                Arc::new(context.with_frame_geometry(world.merged_into(&context.scene)))
            });
            let renders = relight_render::render::render_reference_view(
                &traced,
                &lights,
                &camera,
                settings,
                REFERENCE_SPP,
                &relight_technique::NoProgress,
            );
            let _ = sender.send((generation, renders.full.pixels, traced));
        });
        reference.in_flight = Some(Mutex::new(receiver));
    }
}

/// The passes' mean, Reinhard-mapped like the 3D view, as sRGB bytes.
fn reference_image(reference: &Reference) -> Image {
    let scale = 1.0 / f64::from(reference.passes.max(1));
    let data = reference
        .sum
        .iter()
        .flat_map(|sum| {
            let channel = |value: f64| {
                let radiance = (value * scale) as f32;
                relight_core::colour::linear_to_srgb8(radiance / (1.0 + radiance))
            };
            [channel(sum[0]), channel(sum[1]), channel(sum[2]), 255]
        })
        .collect();
    Image::new(
        Extent3d {
            width: reference.size.0,
            height: reference.size.1,
            depth_or_array_layers: 1,
        },
        TextureDimension::D2,
        data,
        TextureFormat::Rgba8UnormSrgb,
        RenderAssetUsages::RENDER_WORLD | RenderAssetUsages::MAIN_WORLD,
    )
}

/// With --screenshot: saves the window once the GI has run for a while,
/// then quits.
fn screenshot(
    mut commands: Commands,
    args: Res<Args>,
    scenes: Query<&RelightStats>,
    reference: Res<Reference>,
    mut taken: Local<u32>,
    mut exit: MessageWriter<AppExit>,
) {
    let Some(path) = &args.screenshot else {
        return;
    };
    let ready = if reference.on {
        u64::from(reference.passes) >= args.screenshot_after
    } else {
        scenes
            .iter()
            .any(|stats| stats.updates >= args.screenshot_after)
    };
    if !ready {
        return;
    }
    *taken += 1;
    if *taken == 1 {
        commands
            .spawn(bevy::render::view::screenshot::Screenshot::primary_window())
            .observe(bevy::render::view::screenshot::save_to_disk(path.clone()));
    }
    if *taken > 30 {
        exit.write(AppExit::Success);
    }
}
