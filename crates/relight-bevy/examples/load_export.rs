//! Loads a folder written by `relight export` into plain Bevy, without
//! relight's plugin: the glTF scene (meshes with TEXCOORD_1, lights,
//! camera), the KTX2 lightmap on every mesh and the KTX2 irradiance volume
//! from the scene's extras. What any Bevy app needs to show relight's baked
//! light, in one file.
//!
//! relight export scenes/cornell-box-point/scene.toml -t prm -o out/box
//! cargo run --release -p relight-bevy --example load_export -- out/box [--screenshot OUT.png]

use bevy::gltf::GltfSceneExtras;
use bevy::light::{IrradianceVolume, LightProbe};
use bevy::pbr::Lightmap;
use bevy::prelude::*;
use bevy::render::view::screenshot::{save_to_disk, Screenshot};
use std::path::PathBuf;

#[derive(Resource)]
struct Options {
    screenshot: Option<PathBuf>,
}

fn main() -> AppExit {
    let mut arguments = std::env::args().skip(1);
    let Some(folder) = arguments.next() else {
        eprintln!("usage: load_export DIR [--screenshot OUT.png]");
        return AppExit::error();
    };
    let screenshot = match (arguments.next().as_deref(), arguments.next()) {
        (Some("--screenshot"), Some(path)) => Some(PathBuf::from(path)),
        _ => None,
    };
    let folder = std::fs::canonicalize(&folder).unwrap_or(PathBuf::from(folder));
    App::new()
        .add_plugins(DefaultPlugins.set(AssetPlugin {
            file_path: folder.display().to_string(),
            ..default()
        }))
        // The lightmap holds the ambient (indirect) light.
        .insert_resource(GlobalAmbientLight::NONE)
        .insert_resource(Options { screenshot })
        .add_systems(
            Startup,
            |mut commands: Commands, assets: Res<AssetServer>| {
                commands.spawn(WorldAssetRoot(
                    assets.load(GltfAssetLabel::Scene(0).from_asset("scene.gltf")),
                ));
            },
        )
        .add_systems(
            Update,
            (
                add_lightmaps,
                add_volume,
                set_up_camera_and_lights,
                take_screenshot,
            ),
        )
        .run()
}

/// Every mesh the glTF spawned gets the lightmap (its UVs are
/// TEXCOORD_1, which Bevy loads as ATTRIBUTE_UV_1).
fn add_lightmaps(
    mut commands: Commands,
    assets: Res<AssetServer>,
    meshes: Query<Entity, (Added<Mesh3d>, Without<Lightmap>)>,
) {
    for entity in &meshes {
        commands.entity(entity).insert(Lightmap {
            image: assets.load("lightmap-indirect.ktx2"),
            ..default()
        });
    }
}

/// The irradiance volume's box, from `extras.relight.irradianceVolume`.
fn add_volume(
    mut commands: Commands,
    assets: Res<AssetServer>,
    scenes: Query<&GltfSceneExtras, Added<GltfSceneExtras>>,
) {
    for extras in &scenes {
        let Ok(value) = serde_json::from_str::<serde_json::Value>(&extras.value) else {
            continue;
        };
        let volume = &value["relight"]["irradianceVolume"];
        let vector = |key: &str| {
            let array = volume[key].as_array()?;
            let component = |i: usize| array.get(i)?.as_f64().map(|v| v as f32);
            Some(Vec3::new(component(0)?, component(1)?, component(2)?))
        };
        let (Some(uri), Some(translation), Some(scale)) = (
            volume["uri"].as_str(),
            vector("translation"),
            vector("scale"),
        ) else {
            continue;
        };
        commands.spawn((
            IrradianceVolume {
                voxels: assets.load(uri.to_string()),
                // Texels are already in cd/m^2.
                intensity: 1.0,
                affects_lightmapped_meshes: false,
            },
            LightProbe::default(),
            Transform::from_translation(translation).with_scale(scale),
        ));
    }
}

/// relight's units are one lumen a watt: exposure 1 shows its radiance as
/// is. glTF lights come without shadows; relight's cast them.
fn set_up_camera_and_lights(
    mut commands: Commands,
    cameras: Query<Entity, Added<Camera3d>>,
    mut points: Query<&mut PointLight, Added<PointLight>>,
    mut spots: Query<&mut SpotLight, Added<SpotLight>>,
    mut suns: Query<&mut DirectionalLight, Added<DirectionalLight>>,
) {
    for camera in &cameras {
        commands.entity(camera).insert((
            bevy::camera::Hdr,
            bevy::camera::Exposure {
                ev100: (1.0f32 / 1.2).log2(),
            },
        ));
    }
    for mut light in &mut points {
        light.shadow_maps_enabled = true;
        light.range = 1000.0;
    }
    for mut light in &mut spots {
        light.shadow_maps_enabled = true;
        light.range = 1000.0;
    }
    for mut light in &mut suns {
        light.shadow_maps_enabled = true;
    }
}

fn take_screenshot(
    mut commands: Commands,
    options: Res<Options>,
    mut frames: Local<u32>,
    mut exit: MessageWriter<AppExit>,
) {
    let Some(path) = &options.screenshot else {
        return;
    };
    *frames += 1;
    if *frames == 60 {
        commands
            .spawn(Screenshot::primary_window())
            .observe(save_to_disk(path.clone()));
    }
    if *frames > 90 {
        exit.write(AppExit::Success);
    }
}
