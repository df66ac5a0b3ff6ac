//! An interactive window on a relight scene: Bevy draws it with shadow
//! maps, relight adds indirect light as the lights move.
//!
//! cargo run --release -p relight-bevy --example viewer -- SCENE.toml \
//!     [--technique T] [--bake F]
//!
//! Keys: WASD, Q/E and the mouse (left button held) fly the camera;
//! arrows move the point and spot lights around the scene's centre (left,
//! right) and up and down; the right mouse button dragged turns the sun;
//! 1-4 switch technique (PIC, SRP, PRM, LightSkin; bakes in memory unless
//! --bake fits), 0 shows direct light only. The panel shows frames a
//! second, the GI update's stages on the worker, its memory, the bridge's
//! main-thread time and the GI's age in frames.

use bevy::camera_controller::free_camera::{FreeCamera, FreeCameraPlugin};
use bevy::diagnostic::{DiagnosticsStore, FrameTimeDiagnosticsPlugin};
use bevy::input::mouse::AccumulatedMouseMotion;
use bevy::prelude::*;
use clap::Parser;
use relight_bevy::{RelightLight, RelightPlugin, RelightScene, RelightStats, RelightStatus};
use std::path::PathBuf;

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
}

#[derive(Component)]
struct Panel;

#[derive(Component)]
struct ViewerCamera {
    placed: bool,
}

fn main() -> AppExit {
    let args = Args::parse();
    let (width, height) = args
        .size
        .split_once('x')
        .and_then(|(w, h)| Some((w.parse::<u32>().ok()?, h.parse::<u32>().ok()?)))
        .unwrap_or((1280, 720));
    App::new()
        .add_plugins((
            DefaultPlugins.set(WindowPlugin {
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
        .insert_resource(args)
        .add_systems(Startup, setup)
        .add_systems(
            Update,
            (
                place_camera,
                move_lights,
                switch_technique,
                update_panel,
                screenshot,
            ),
        )
        .run()
}

fn scene_of(args: &Args, technique: &str) -> RelightScene {
    let mut scene = RelightScene::new(&args.scene).technique(technique);
    if technique == args.technique {
        scene.bake = args.bake.clone();
    }
    scene
}

fn setup(mut commands: Commands, args: Res<Args>) {
    commands.spawn(scene_of(&args, &args.technique));
    commands.spawn((
        Camera3d::default(),
        bevy::camera::Hdr,
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
    commands.spawn(scene_of(&args, technique));
}

fn update_panel(
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
    text.push_str("\nWASD/QE + left mouse: fly   arrows: lights   right drag: sun\n1 PIC  2 SRP  3 PRM  4 LightSkin  0 direct only");
    for mut panel in &mut panel {
        **panel = text.clone();
    }
}

/// With --screenshot: saves the window once the GI has run for a while,
/// then quits.
fn screenshot(
    mut commands: Commands,
    args: Res<Args>,
    scenes: Query<&RelightStats>,
    mut taken: Local<u32>,
    mut exit: MessageWriter<AppExit>,
) {
    let Some(path) = &args.screenshot else {
        return;
    };
    let ready = scenes
        .iter()
        .any(|stats| stats.updates >= args.screenshot_after);
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
