//! relight in Bevy: a plugin that keeps Bevy's lightmaps and irradiance
//! volumes lit by a relight technique while the app moves its lights.
//!
//! ```no_run
//! use bevy::prelude::*;
//! use relight_bevy::{RelightPlugin, RelightScene};
//!
//! fn main() {
//!     App::new()
//!         .add_plugins((DefaultPlugins, RelightPlugin))
//!         // relight's lightmap replaces ambient light on the scene.
//!         .insert_resource(GlobalAmbientLight::NONE)
//!         .add_systems(Startup, |mut commands: Commands| {
//!             commands.spawn(RelightScene::new("scenes/cornell-box/scene.toml").technique("lightskin"));
//!             commands.spawn((Camera3d::default(), relight_bevy::matching_exposure()));
//!         })
//!         .run();
//! }
//! ```
//!
//! Data flow: spawning a [`RelightScene`] starts a loading thread (scene
//! file, BVH and atlas, then the bake file or a bake in memory; progress
//! in [`RelightStatus::Loading`]). When it is done the plugin spawns the
//! static meshes as children (relight's atlas as `ATTRIBUTE_UV_1`, a
//! `Lightmap` on each), the scene's lights as Bevy lights with shadow
//! maps and [`RelightLight`] (Bevy draws direct light), the scene file's
//! moving meshes with [`RelightMovingMesh`], and an `IrradianceVolume`
//! over the scene for them and the app's own dynamic objects. A worker thread
//! then owns the technique: each frame, after Bevy has propagated
//! transforms, the main thread reads the Bevy lights' transforms, colours
//! and intensities, the moving meshes' transforms and the active camera,
//! and posts them to a one-slot mailbox when they changed (a state the
//! worker has not taken is replaced, never queued). The worker takes the
//! newest state as soon as it is free, updates the technique and fills
//! the lightmap's RGBA16F bytes (and, every `volume_every` updates, the
//! volume's), which the main thread moves into the images: a frame never
//! waits for GI, and [`RelightStats::gi_age_frames`] says how old the
//! light on screen is. On a software rasteriser the plugin clusters
//! lights on the CPU (Bevy's GPU clustering there leaves the irradiance
//! volume out).
//!
//! Adoption: an app that loads its glTF itself puts the `RelightScene`
//! (with [`RelightScene::adopt_gltf`]) on the entity with the
//! `WorldAssetRoot`. The loading thread loads relight's copy of the same
//! file; once Bevy has spawned the scene, the plugin gives each mesh
//! entity a copy of its mesh with relight's atlas as UV 1 and the
//! `Lightmap` (finding relight's triangles by the mesh handle's
//! `Mesh{m}/Primitive{p}` label and the entity's transform, and checking
//! every corner), turns the glTF's lights into [`RelightLight`]s, and
//! starts as above without spawning static meshes.
//!
//! Units: texels are E/pi in cd/m^2 at [`relight_engine::LUMENS_PER_WATT`];
//! Bevy lights are read back through the same factor. Static emitters
//! (emissive triangles, the environment) are not Bevy lights, so their
//! direct light goes into the lightmap with the indirect light (unless
//! [`RelightScene::indirect_only`]).

mod adopt;
mod convert;
mod runtime;
pub mod snapshot;

pub use convert::{bevy_light_to_relight, light_transform, matching_exposure, relight_camera};
pub use runtime::{
    gltf_to_adopt, read_moving_mesh_poses, relight_lights, RelightContext, RelightLight,
    RelightLights, RelightMovingMesh, RelightMovingMeshes, RelightPlugin, RelightScene,
    RelightStats, RelightStatus,
};
