//! The plugin's systems: loading off the main thread, spawning the scene,
//! and the per-frame exchange with the worker that owns the technique.

use crate::convert;
use bevy::diagnostic::FrameCount;
use bevy::light::{IrradianceVolume, LightProbe};
use bevy::pbr::Lightmap;
use bevy::prelude::*;
use relight_core::Rgb;
use relight_engine::{fill_volume, LightmapLayout, VolumeGrid};
use relight_scene::Light;
use relight_technique::{ContextSettings, Frame, Progress, SceneContext, Technique};
use std::path::PathBuf;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::mpsc::{channel, Receiver, Sender, TryRecvError};
use std::sync::{Arc, Condvar, Mutex};
use std::time::Instant;

/// Adds the systems that load, spawn and keep [`RelightScene`]s lit.
pub struct RelightPlugin;

impl Plugin for RelightPlugin {
    fn build(&self, app: &mut App) {
        // The exchange reads the lights' and moving meshes' global
        // transforms, so it runs after this frame's propagation: before
        // it, what the app moved in Update (and what loading just
        // spawned, still at the origin) has not reached them.
        app.add_systems(
            Update,
            (start_loading, finish_loading, adopt_gltf_scenes).chain(),
        )
        .add_systems(
            PostUpdate,
            exchange_with_worker.after(bevy::transform::TransformSystems::Propagate),
        );
    }

    /// On a software rasteriser (Mesa's lavapipe: CI, machines without a
    /// GPU) Bevy 0.19.1's GPU clustering leaves the irradiance volume out
    /// of every cluster, and moving meshes lit only by it render black;
    /// clustering on the CPU lights them. Runs after Bevy's PBR plugin
    /// has chosen (`finish` follows plugin order).
    fn finish(&self, app: &mut App) {
        let software = app
            .get_sub_app(bevy::render::RenderApp)
            .and_then(|render| {
                render
                    .world()
                    .get_resource::<bevy::render::renderer::RenderAdapterInfo>()
            })
            .is_some_and(|info| format!("{:?}", info.device_type) == "Cpu");
        if software {
            if let Some(mut settings) = app
                .world_mut()
                .get_resource_mut::<bevy::light::cluster::GlobalClusterSettings>()
            {
                settings.gpu_clustering = None;
            }
        }
    }
}

/// A relight scene in a Bevy app: which file, technique and bake.
#[derive(Component, Clone, Debug)]
pub struct RelightScene {
    /// A scene file (TOML) or a mesh file (OBJ, glTF, GLB).
    pub path: PathBuf,
    pub technique: String,
    /// Technique parameters, as `relight --set key=value` takes them.
    pub params: Vec<(String, String)>,
    /// A bake file from `relight bake`; without one, techniques that need a
    /// bake bake in memory while [`RelightStatus::Loading`].
    pub bake: Option<PathBuf>,
    /// Irradiance-volume voxels along the scene's longest side; 0: none.
    pub volume_cells: u32,
    /// Refresh the volume every this many GI updates (a refresh costs
    /// about 100 ms on Sponza's 16 x 8 x 7 voxels, on the worker).
    pub volume_every: u32,
    /// Threads of the GI update; 0: rayon's global pool (every core).
    /// Fewer leave the app's own threads cores of their own: on two
    /// cores, one worker thread runs its update as fast as `relight bench
    /// --threads 1` does while Bevy renders, where two share the cores
    /// with Bevy's task pools and slow down (see the guide's Bevy page,
    /// docs/bevy.md).
    pub worker_threads: usize,
    /// Spawn the scene's lights as Bevy lights (with [`RelightLight`]).
    pub spawn_lights: bool,
    /// The lightmap holds indirect light only, without the static
    /// emitters' direct light (for comparisons with relight's
    /// indirect-only renders).
    pub indirect_only: bool,
    /// Light the glTF scene Bevy spawns under this entity's
    /// `WorldAssetRoot` instead of spawning relight's copy: see
    /// [`RelightScene::adopt_gltf`].
    pub adopt: bool,
    /// Give the adopted glTF's materials relight's shading (its Lambertian
    /// or Blinn-Phong lobe as `StandardMaterial` parameters, as for the
    /// meshes relight spawns), keeping their colours and textures: for
    /// comparisons with relight's renders. Off, an adopted scene keeps
    /// the app's look: Bevy's glTF materials have a specular lobe and
    /// Burley diffuse, which relight's lightmap does not model (its
    /// indirect light is the same either way; see the snapshot test).
    pub relight_shading: bool,
}

impl RelightScene {
    pub fn new(path: impl Into<PathBuf>) -> Self {
        Self {
            path: path.into(),
            technique: "lightskin".into(),
            params: Vec::new(),
            bake: None,
            volume_cells: 16,
            volume_every: 10,
            worker_threads: 0,
            spawn_lights: true,
            indirect_only: false,
            adopt: false,
            relight_shading: false,
        }
    }

    /// Adopt the glTF scene the app has Bevy load on this same entity
    /// (`WorldAssetRoot(assets.load(GltfAssetLabel::Scene(0).from_asset(..)))`)
    /// instead of spawning relight's copy of `path`, which must be that
    /// glTF file or a scene file whose mesh it is. Once Bevy has spawned
    /// it, each of its mesh entities keeps its material and components and
    /// gets relight's atlas as UV 1 (a copy of its mesh with one vertex a
    /// triangle corner) and the [`Lightmap`]; each of its lights that is
    /// one of relight's becomes a [`RelightLight`] with relight's colour
    /// (linear, as glTF defines it; Bevy's loader reads it as sRGB) and
    /// shadow maps. Lights only the scene file has are spawned. A mesh that
    /// is not relight's copy of the file is a [`RelightStatus::Failed`]
    /// naming it. The glTF must be loaded without coordinate conversion
    /// and with its meshes kept in the main world (Bevy's defaults).
    pub fn adopt_gltf(mut self) -> Self {
        self.adopt = true;
        self
    }

    pub fn technique(mut self, name: impl Into<String>) -> Self {
        self.technique = name.into();
        self
    }

    pub fn set(mut self, key: impl Into<String>, value: impl Into<String>) -> Self {
        self.params.push((key.into(), value.into()));
        self
    }

    pub fn bake(mut self, path: impl Into<PathBuf>) -> Self {
        self.bake = Some(path.into());
        self
    }
}

/// The glTF file an app loads for [`RelightScene::adopt_gltf`] with the
/// scene at `path` (the file itself, or a scene file's mesh), as an
/// absolute path: its folder is where Bevy's `AssetPlugin` must look.
pub fn gltf_to_adopt(path: &std::path::Path) -> Result<std::path::PathBuf, String> {
    let mesh = if relight_scene::is_mesh_file(path) {
        path.to_path_buf()
    } else {
        relight_scene::parse_scene_file(path)
            .map_err(|error| error.to_string())?
            .mesh
    };
    let is_gltf = mesh.extension().is_some_and(|extension| {
        extension.eq_ignore_ascii_case("gltf") || extension.eq_ignore_ascii_case("glb")
    });
    if !is_gltf {
        return Err(format!(
            "{}: adoption needs a glTF scene, and its mesh is {}",
            path.display(),
            mesh.display()
        ));
    }
    std::path::absolute(&mesh).map_err(|error| format!("{}: {error}", mesh.display()))
}

/// Where a [`RelightScene`] is: loading (with the stage and its fraction
/// done), running, or failed with relight's message.
#[derive(Component, Clone, Debug, PartialEq)]
pub enum RelightStatus {
    Loading { stage: String, fraction: f32 },
    Running,
    Failed(String),
}

/// Marks a Bevy light that relight reads each frame; the number orders
/// the lights as the technique sees them.
#[derive(Component, Clone, Copy, Debug, PartialEq, Eq)]
pub struct RelightLight(pub usize);

/// One of a scene's moving meshes (its `[[dynamic]]` entry `index`, from
/// 0), spawned by the plugin at the scene file's first pose. The app moves
/// it like any entity; each GI update reads its transform relative to its
/// `scene` entity, and LightSkin moves the mesh through its maps to match
/// (the other techniques light it without it blocking or reflecting).
/// Bevy lights it from the irradiance volume. A despawned one stays where
/// it was last seen.
#[derive(Component, Clone, Copy, Debug, PartialEq, Eq)]
pub struct RelightMovingMesh {
    pub scene: Entity,
    pub index: usize,
}

/// The loaded scene (geometry, BVH, atlas, emitters) of a running
/// [`RelightScene`], for apps that trace it themselves (the viewer's
/// reference view).
#[derive(Component, Clone)]
pub struct RelightContext(pub Arc<SceneContext>);

/// What the last GI update cost and how old the light on screen is.
#[derive(Component, Clone, Debug, Default)]
pub struct RelightStats {
    /// Frames between reading the lights and showing the light computed
    /// from them.
    pub gi_age_frames: u64,
    /// GI updates shown so far (updates that ran).
    pub updates: u64,
    /// Updates the technique skipped: the scene's state repeated the
    /// last one's as far as the technique reads it (a camera move, for a
    /// technique without view-dependent light) and its light had settled.
    pub skipped_updates: u64,
    /// Whether the light on screen is where the technique's light settles
    /// for the scene's newest state: false while that state waits for the
    /// worker, and while feedback techniques (PIC, SRP, PRM's final
    /// gather) still add bounces after a change, which the worker does by
    /// itself while no newer state waits.
    pub settled: bool,
    /// The technique's stages, then the lightmap bytes and (when it was
    /// refreshed) the volume, in milliseconds, on the worker.
    pub stages: Vec<(String, f64)>,
    /// The technique's run-time buffers.
    pub memory_bytes: usize,
    /// Main-thread time of the last frame's exchange (light sync, moving
    /// the finished bytes into the images), in milliseconds.
    pub bridge_ms: f64,
    /// The scene as loaded, for apps that need its camera or bounds.
    pub camera: Option<relight_scene::Camera>,
}

/// Progress of the loading thread, shared with the main thread.
#[derive(Default)]
struct SharedProgress {
    stage: Mutex<String>,
    total: AtomicU64,
    done: AtomicU64,
}

impl Progress for SharedProgress {
    fn start(&self, stage: &str, total: u64) {
        *self.stage.lock().unwrap() = stage.to_string();
        self.total.store(total.max(1), Ordering::Relaxed);
        self.done.store(0, Ordering::Relaxed);
    }
    fn advance(&self, amount: u64) {
        self.done.fetch_add(amount, Ordering::Relaxed);
    }
    fn finish(&self) {
        self.done
            .store(self.total.load(Ordering::Relaxed), Ordering::Relaxed);
    }
}

struct Loaded {
    context: Arc<SceneContext>,
    technique: Box<dyn Technique>,
    moving_meshes: Vec<relight_engine::MovingMesh>,
}

#[derive(Component)]
struct Loading {
    progress: Arc<SharedProgress>,
    result: Mutex<Receiver<Result<Loaded, String>>>,
}

fn start_loading(
    mut commands: Commands,
    added: Query<(Entity, &RelightScene), Added<RelightScene>>,
) {
    for (entity, scene) in &added {
        let progress = Arc::new(SharedProgress::default());
        let (send, receive) = channel();
        let (settings, shared) = (scene.clone(), progress.clone());
        std::thread::spawn(move || {
            let _ = send.send(load(&settings, shared.as_ref()));
        });
        commands.entity(entity).insert((
            Loading {
                progress,
                result: Mutex::new(receive),
            },
            RelightStatus::Loading {
                stage: "loading".into(),
                fraction: 0.0,
            },
            RelightStats::default(),
        ));
        // An adopted scene's root has the app's transform already.
        commands
            .entity(entity)
            .insert_if_new((Transform::default(), Visibility::default()));
    }
}

fn load(settings: &RelightScene, progress: &SharedProgress) -> Result<Loaded, String> {
    progress.start(&format!("loading {}", settings.path.display()), 1);
    let scene = relight_scene::load_scene(&settings.path).map_err(|error| error.to_string())?;
    let moving_meshes = relight_engine::moving_meshes(&scene).map_err(|error| error.to_string())?;
    let context = Arc::new(
        SceneContext::new(scene, ContextSettings::default()).map_err(|error| error.to_string())?,
    );
    let technique = relight_engine::open_technique(
        &context,
        &settings.technique,
        &settings.params,
        settings.bake.as_deref(),
        progress,
    )
    .map_err(|error| error.to_string())?;
    Ok(Loaded {
        context,
        technique,
        moving_meshes,
    })
}

/// What the GI depends on in one frame: lights, camera, moving meshes.
#[derive(Clone, Debug, PartialEq)]
struct SceneState {
    lights: Vec<Light>,
    /// The active 3D camera, for view-dependent (glossy) light.
    camera: Option<relight_scene::Camera>,
    /// Where the moving meshes are (none in the scene: `None`).
    moving_mesh_poses: Option<Vec<relight_core::Affine3A>>,
}

/// A frame's state for the worker.
struct Job {
    state: SceneState,
    /// Bevy's frame when it was read.
    frame: u64,
}

/// The newest job, which the worker takes as soon as it is free: a job
/// the worker has not taken yet is replaced, never queued, so the worker
/// never computes stale light and never idles while the scene moves (an
/// idle gap before each update made it 15-30 % slower: `relight bench
/// --pause-ms`).
#[derive(Default)]
struct Mailbox {
    slot: Mutex<MailboxSlot>,
    wake: Condvar,
}

#[derive(Default)]
struct MailboxSlot {
    job: Option<Job>,
    closed: bool,
}

impl Mailbox {
    fn post(&self, job: Job) {
        self.slot.lock().unwrap().job = Some(job);
        self.wake.notify_one();
    }

    /// The waiting job, if any, without waiting; `None` once closed too.
    fn try_take(&self) -> Option<Job> {
        self.slot.lock().unwrap().job.take()
    }

    fn is_closed(&self) -> bool {
        self.slot.lock().unwrap().closed
    }

    /// The next job, waiting for one; `None` once closed.
    fn take(&self) -> Option<Job> {
        let mut slot = self.slot.lock().unwrap();
        loop {
            if let Some(job) = slot.job.take() {
                return Some(job);
            }
            if slot.closed {
                return None;
            }
            slot = self.wake.wait(slot).unwrap();
        }
    }

    fn close(&self) {
        self.slot.lock().unwrap().closed = true;
        self.wake.notify_one();
    }
}

struct Done {
    frame: u64,
    /// `None`: the update was skipped, the images hold its light already.
    lightmap: Option<Vec<u8>>,
    volume: Option<Vec<u8>>,
    settled: bool,
    stages: Vec<(String, f64)>,
    memory_bytes: usize,
}

#[derive(Component)]
struct Worker {
    mailbox: Arc<Mailbox>,
    done: Mutex<Receiver<Result<Done, String>>>,
    /// What was last posted, and Bevy's frame when it was.
    posted: Option<SceneState>,
    posted_frame: Option<u64>,
    /// Bevy's frame whose state the light on screen was computed from.
    shown_frame: Option<u64>,
    lightmap: Handle<Image>,
    volume: Option<Handle<Image>>,
    /// Each moving mesh's last seen pose relative to the scene entity.
    moving_mesh_poses: Vec<relight_core::Affine3A>,
}

impl Drop for Worker {
    /// The worker thread ends with its scene.
    fn drop(&mut self) {
        self.mailbox.close();
    }
}

fn finish_loading(
    mut commands: Commands,
    mut loading: Query<(
        Entity,
        &RelightScene,
        &Loading,
        &mut RelightStatus,
        &mut RelightStats,
    )>,
    mut assets: SceneAssets,
) {
    for (entity, settings, state, mut status, mut stats) in &mut loading {
        let message = state.result.lock().unwrap().try_recv();
        let loaded = match message {
            Err(TryRecvError::Empty) => {
                let total = state.progress.total.load(Ordering::Relaxed).max(1);
                let done = state.progress.done.load(Ordering::Relaxed);
                *status = RelightStatus::Loading {
                    stage: state.progress.stage.lock().unwrap().clone(),
                    fraction: (done as f32 / total as f32).min(1.0),
                };
                continue;
            }
            Err(TryRecvError::Disconnected) => Err("the loading thread stopped".to_string()),
            Ok(result) => result,
        };
        commands.entity(entity).remove::<Loading>();
        let loaded = match loaded {
            Ok(loaded) => loaded,
            Err(message) => {
                fail(&mut status, message);
                continue;
            }
        };
        if settings.adopt {
            *status = RelightStatus::Loading {
                stage: "waiting for Bevy to spawn the glTF scene".into(),
                fraction: 1.0,
            };
            commands
                .entity(entity)
                .insert(AwaitingGltf(Mutex::new(Some(loaded))));
            continue;
        }
        let lightmap = assets.images.add(empty_lightmap(&loaded.context));
        start_running(
            &mut commands,
            entity,
            settings,
            loaded,
            Adopted::Nothing,
            lightmap,
            &mut assets,
            &mut stats,
        );
        *status = RelightStatus::Running;
    }
}

/// A loaded scene waiting for Bevy to spawn the glTF it adopts.
#[derive(Component)]
struct AwaitingGltf(Mutex<Option<Loaded>>);

/// The assets the plugin adds while starting a scene.
#[derive(bevy::ecs::system::SystemParam)]
struct SceneAssets<'w> {
    meshes: ResMut<'w, Assets<Mesh>>,
    materials: ResMut<'w, Assets<StandardMaterial>>,
    images: ResMut<'w, Assets<Image>>,
}

/// What the app's own entities already stand for.
enum Adopted {
    Nothing,
    /// A glTF scene's meshes, and which of relight's lights its lights
    /// are.
    Gltf {
        lights: Vec<bool>,
    },
}

/// The lightmap image before the first update: black, the atlas's size.
fn empty_lightmap(context: &SceneContext) -> Image {
    let atlas = &context.atlas;
    convert::float_image(
        atlas.width,
        atlas.height,
        1,
        vec![0; atlas.width as usize * atlas.height as usize * 8],
    )
}

/// Once Bevy has spawned an adopted glTF scene (its `WorldInstance` is
/// ready, and its transforms were propagated in that frame's PostUpdate):
/// gives its meshes relight's atlas and the lightmap, claims its lights,
/// and starts the scene.
#[allow(clippy::too_many_arguments)]
fn adopt_gltf_scenes(
    mut commands: Commands,
    mut waiting: AwaitingScenes,
    spawner: Option<Res<bevy::world_serialization::WorldInstanceSpawner>>,
    asset_server: Res<AssetServer>,
    children: Query<&Children>,
    mesh_entities: AdoptableMeshes,
    light_entities: RelightLightCandidates,
    mut assets: SceneAssets,
) {
    for (entity, settings, awaiting, root, mut status, mut stats, (asset, instance)) in &mut waiting
    {
        let problem = match (asset, instance) {
            (None, _) => Some(
                "RelightScene::adopt_gltf needs a WorldAssetRoot (the glTF scene Bevy loads) on the same entity"
                    .to_string(),
            ),
            (Some(asset), None) => match asset_server.load_state(&asset.0) {
                bevy::asset::LoadState::Failed(error) => {
                    Some(format!("Bevy could not load the glTF to adopt: {error}"))
                }
                // Still loading: the instance comes once it is loaded.
                _ => None,
            },
            (Some(_), Some(_)) => None,
        };
        if let Some(message) = problem {
            commands.entity(entity).remove::<AwaitingGltf>();
            fail(&mut status, message);
            continue;
        }
        let Some(instance) = instance else {
            continue;
        };
        if !spawner
            .as_ref()
            .is_some_and(|spawner| spawner.instance_is_ready(**instance))
        {
            continue;
        }
        commands.entity(entity).remove::<AwaitingGltf>();
        let Some(loaded) = awaiting.0.lock().unwrap().take() else {
            continue;
        };
        let to_scene = root.affine().inverse();
        let descendants: Vec<Entity> = children.iter_descendants(entity).collect();
        let found: Vec<crate::adopt::MeshEntity> = descendants
            .iter()
            .filter_map(|&descendant| {
                let (mesh, transform, name, material) = mesh_entities.get(descendant).ok()?;
                Some(crate::adopt::MeshEntity {
                    entity: descendant,
                    name: name.map(|name| name.as_str()),
                    label: mesh.0.path().and_then(|path| path.label()),
                    to_scene: Mat4::from(to_scene * transform.affine()),
                    mesh: assets.meshes.get(&mesh.0)?,
                    material: material.map(|material| material.0.clone()),
                })
            })
            .collect();
        let adoption = match crate::adopt::adopt_meshes(
            &loaded.context.scene,
            &loaded.context.atlas,
            &found,
        ) {
            Ok(adoption) => adoption,
            Err(message) => {
                fail(&mut status, message);
                continue;
            }
        };
        if !adoption.skipped.is_empty() {
            warn!(
                "relight: {} mesh entities of the adopted scene are not relight's glTF triangle lists and get no lightmap: {}",
                adoption.skipped.len(),
                adoption.skipped.join(", ")
            );
        }
        if settings.relight_shading {
            let mut shaded = std::collections::HashSet::new();
            for adopted in &adoption.meshes {
                let (Some(handle), Some(material)) = (&adopted.material, adopted.relight_material)
                else {
                    continue;
                };
                if shaded.insert(handle.id()) {
                    if let Some(mut bevy_material) = assets.materials.get_mut(handle) {
                        convert::relight_shading(
                            &mut bevy_material,
                            &loaded.context.scene.materials[material as usize],
                        );
                    }
                }
            }
        }
        let lightmap = assets.images.add(empty_lightmap(&loaded.context));
        for adopted in adoption.meshes {
            commands.entity(adopted.entity).insert((
                Mesh3d(assets.meshes.add(adopted.mesh)),
                Lightmap {
                    image: lightmap.clone(),
                    ..default()
                },
            ));
        }
        let scene = &loaded.context.scene;
        let mut claimed = vec![false; scene.lights.len()];
        if settings.spawn_lights {
            let lights: Vec<(Entity, Light)> = descendants
                .iter()
                .filter_map(|&descendant| {
                    let (transform, point, spot, directional) =
                        light_entities.get(descendant).ok()?;
                    let in_scene = GlobalTransform::from(to_scene * transform.affine());
                    convert::bevy_light_to_relight(&in_scene, point, spot, directional)
                        .map(|light| (descendant, light))
                })
                .collect();
            let found: Vec<Light> = lights.iter().map(|(_, light)| light.clone()).collect();
            let range = scene_range(scene);
            for ((light_entity, _), matched) in
                lights.iter().zip(crate::adopt::match_lights(scene, &found))
            {
                match matched {
                    Some(index) => {
                        claimed[index] = true;
                        let mut commands = commands.entity(*light_entity);
                        commands.insert(RelightLight(index));
                        convert::insert_light_values(&scene.lights[index], range, &mut commands);
                    }
                    None => warn!(
                        "relight: a light of the adopted scene is none of {}'s lights, so relight does not see it",
                        scene.source.display()
                    ),
                }
            }
        }
        start_running(
            &mut commands,
            entity,
            settings,
            loaded,
            Adopted::Gltf { lights: claimed },
            lightmap,
            &mut assets,
            &mut stats,
        );
        *status = RelightStatus::Running;
    }
}

/// Scenes whose glTF Bevy may have spawned by now.
type AwaitingScenes<'w, 's> = Query<
    'w,
    's,
    (
        Entity,
        &'static RelightScene,
        &'static AwaitingGltf,
        &'static GlobalTransform,
        &'static mut RelightStatus,
        &'static mut RelightStats,
        (
            Option<&'static WorldAssetRoot>,
            Option<&'static bevy::world_serialization::WorldInstance>,
        ),
    ),
>;

/// The mesh entities an adopted scene may hold.
type AdoptableMeshes<'w, 's> = Query<
    'w,
    's,
    (
        &'static Mesh3d,
        &'static GlobalTransform,
        Option<&'static Name>,
        Option<&'static MeshMaterial3d<StandardMaterial>>,
    ),
>;

/// The lights an adopted scene may hold.
type RelightLightCandidates<'w, 's> = Query<
    'w,
    's,
    (
        &'static GlobalTransform,
        Option<&'static PointLight>,
        Option<&'static SpotLight>,
        Option<&'static DirectionalLight>,
    ),
>;

/// Where Bevy may cut the scene's point and spot lights off: well past
/// the scene (relight's fall off with the inverse square only).
fn scene_range(scene: &relight_scene::Scene) -> f32 {
    let (lo, hi) = scene.mesh.bounds();
    (hi - lo).length() * 4.0
}

/// Spawns what the app does not have already (the static meshes, the
/// lights, the moving meshes, the irradiance volume) and starts the worker.
#[allow(clippy::too_many_arguments)]
fn start_running(
    commands: &mut Commands,
    entity: Entity,
    settings: &RelightScene,
    loaded: Loaded,
    adopted: Adopted,
    lightmap: Handle<Image>,
    assets: &mut SceneAssets,
    stats: &mut RelightStats,
) {
    let Loaded {
        context,
        technique,
        moving_meshes: moving,
    } = loaded;
    let scene = &context.scene;
    let atlas = &context.atlas;
    let layout = LightmapLayout::new(atlas);
    let (spawn_static_meshes, lights_present) = match adopted {
        Adopted::Nothing => (true, vec![false; scene.lights.len()]),
        Adopted::Gltf { lights } => (false, lights),
    };
    let material_handles: Vec<Handle<StandardMaterial>> = if spawn_static_meshes {
        let textures: Vec<Handle<Image>> = scene
            .textures
            .iter()
            .map(|texture| assets.images.add(convert::albedo_image(texture)))
            .collect();
        scene
            .materials
            .iter()
            .map(|material| {
                let texture = material
                    .albedo_texture
                    .and_then(|index| textures.get(index as usize).cloned());
                let mut material = convert::material(material, texture);
                if settings.indirect_only {
                    // Emitters show as light seen directly, not bounced.
                    material.emissive = LinearRgba::BLACK;
                }
                assets.materials.add(material)
            })
            .collect()
    } else {
        Vec::new()
    };
    let (lo, hi) = scene.content_bounds();
    let range = scene_range(scene);
    commands.entity(entity).with_children(|children| {
        if spawn_static_meshes {
            for (material, mesh) in convert::static_meshes(scene, atlas) {
                children.spawn((
                    Mesh3d(assets.meshes.add(mesh)),
                    MeshMaterial3d(material_handles[material as usize].clone()),
                    Lightmap {
                        image: lightmap.clone(),
                        ..default()
                    },
                ));
            }
        }
        for (index, mesh) in moving.iter().enumerate() {
            let mesh_materials: Vec<Handle<StandardMaterial>> = mesh
                .materials
                .iter()
                .map(|material| assets.materials.add(convert::material(material, None)))
                .collect();
            children
                .spawn((
                    RelightMovingMesh {
                        scene: entity,
                        index,
                    },
                    convert::transform_of(mesh.pose(0)),
                    Visibility::default(),
                ))
                .with_children(|parts| {
                    for (material, part) in convert::moving_meshes(mesh) {
                        parts.spawn((
                            Mesh3d(assets.meshes.add(part)),
                            MeshMaterial3d(mesh_materials[material as usize].clone()),
                        ));
                    }
                });
        }
        if settings.spawn_lights {
            for (index, light) in scene.lights.iter().enumerate() {
                if !lights_present[index] {
                    let mut light_entity = children.spawn(RelightLight(index));
                    convert::bevy_light(light, range, &mut light_entity);
                }
            }
        }
    });
    let grid =
        (settings.volume_cells > 0).then(|| VolumeGrid::covering(lo, hi, settings.volume_cells));
    let volume = grid.map(|grid| {
        let size = grid.texture_size();
        let handle = assets.images.add(convert::float_image(
            size.x,
            size.y,
            size.z,
            vec![0; grid.voxel_count() * 6 * 8],
        ));
        let (centre, scale) = grid.centre_and_scale();
        commands.spawn((
            IrradianceVolume {
                voxels: handle.clone(),
                intensity: 1.0,
                // The lightmap is these meshes' indirect light.
                affects_lightmapped_meshes: false,
            },
            LightProbe::default(),
            Transform::from_translation(convert::vec3(centre)).with_scale(convert::vec3(scale)),
            ChildOf(entity),
        ));
        handle
    });
    let static_direct = (!settings.indirect_only && context.direct().has_static_light())
        .then(|| static_direct_light(&context));
    stats.camera = Some(scene.camera.clone());
    commands
        .entity(entity)
        .insert(RelightContext(context.clone()));
    let mailbox = Arc::new(Mailbox::default());
    let (done_sender, done) = channel();
    let moving_mesh_poses = moving.iter().map(|mesh| mesh.pose(0)).collect();
    let worker = Work {
        context,
        layout,
        grid,
        volume_every: settings.volume_every.max(1),
        static_direct,
    };
    let jobs = mailbox.clone();
    let threads = settings.worker_threads;
    let pool = (threads > 0).then(|| {
        rayon::ThreadPoolBuilder::new()
            .num_threads(threads)
            .thread_name(|index| format!("relight GI {index}"))
            .build()
    });
    std::thread::spawn(move || match pool {
        // The worker loop runs on one of the pool's threads, so the
        // technique's parallel loops use that pool.
        Some(Ok(pool)) => pool.install(|| worker.run(technique, &jobs, done_sender)),
        Some(Err(error)) => {
            let _ = done_sender.send(Err(format!(
                "could not start {} GI worker threads: {error}",
                threads
            )));
        }
        None => worker.run(technique, &jobs, done_sender),
    });
    commands.entity(entity).insert(Worker {
        mailbox,
        done: Mutex::new(done),
        posted: None,
        posted_frame: None,
        shown_frame: None,
        lightmap,
        volume,
        moving_mesh_poses,
    });
}

/// Direct light from what Bevy cannot draw as lights: emissive
/// triangles and the environment, static, so computed once.
fn static_direct_light(context: &SceneContext) -> Vec<Rgb> {
    let receivers = &context.atlas.receivers;
    let mut light = vec![Rgb::ZERO; receivers.len()];
    context
        .direct()
        .irradiance_batch(&[], &receivers.positions, &receivers.normals, &mut light);
    light
}

/// What the worker thread needs besides the technique.
struct Work {
    context: Arc<SceneContext>,
    layout: LightmapLayout,
    grid: Option<VolumeGrid>,
    /// Refresh the volume every this many updates.
    volume_every: u32,
    static_direct: Option<Vec<Rgb>>,
}

impl Work {
    /// Owns the technique, turns each job into lightmap (and volume)
    /// bytes. Ends when the mailbox closes or the main side is gone.
    fn run(
        self,
        mut technique: Box<dyn Technique>,
        jobs: &Mailbox,
        done: Sender<Result<Done, String>>,
    ) {
        let Work {
            context,
            layout,
            grid,
            volume_every,
            static_direct,
        } = self;
        let mut volume_values = vec![Rgb::ZERO; grid.map_or(0, |grid| grid.voxel_count() * 6)];
        let mut updates = 0u64;
        let mut settled = true;
        let mut last: Option<Job> = None;
        loop {
            // While the light is still settling after a change, the last
            // job runs again until a new one arrives.
            let waiting = match settled {
                true => jobs.take(),
                false => jobs.try_take(),
            };
            let job = match (waiting, last.take()) {
                (Some(job), _) => job,
                (None, Some(job)) if !jobs.is_closed() => job,
                _ => return,
            };
            let refresh_volume = updates.is_multiple_of(u64::from(volume_every));
            let index = updates;
            let result = technique
                .update(&Frame {
                    lights: &job.state.lights,
                    index,
                    camera: job.state.camera.as_ref(),
                    moving_mesh_poses: job.state.moving_mesh_poses.as_deref(),
                })
                .map_err(|error| error.to_string())
                .map(|()| {
                    settled = technique.settled();
                    if technique.timings().skipped {
                        return Done {
                            frame: job.frame,
                            lightmap: None,
                            volume: None,
                            settled,
                            stages: Vec::new(),
                            memory_bytes: 0,
                        };
                    }
                    updates += 1;
                    let mut stages: Vec<(String, f64)> = technique
                        .timings()
                        .stages
                        .iter()
                        .map(|(name, duration)| (name.to_string(), duration.as_secs_f64() * 1e3))
                        .collect();
                    let start = Instant::now();
                    let computed;
                    let values = match technique.receiver_irradiance() {
                        Some(values) => values,
                        None => {
                            computed =
                                relight_engine::receiver_irradiance(&context, technique.as_ref());
                            &computed
                        }
                    };
                    let mut lightmap = vec![0u8; layout.texel_count() * 8];
                    layout.fill_rgba16f(values, static_direct.as_deref(), &mut lightmap);
                    stages.push((
                        "lightmap RGBA16F".into(),
                        start.elapsed().as_secs_f64() * 1e3,
                    ));
                    let volume = match (&grid, refresh_volume) {
                        (Some(grid), true) => {
                            let start = Instant::now();
                            fill_volume(grid, technique.as_ref(), &mut volume_values);
                            let mut bytes = Vec::with_capacity(volume_values.len() * 8);
                            relight_engine::TexelFormat::Rgba16Float
                                .encode_into(&volume_values, &mut bytes);
                            stages.push((
                                "irradiance volume".into(),
                                start.elapsed().as_secs_f64() * 1e3,
                            ));
                            Some(bytes)
                        }
                        _ => None,
                    };
                    Done {
                        frame: job.frame,
                        lightmap: Some(lightmap),
                        volume,
                        settled,
                        stages,
                        memory_bytes: technique.memory().iter().map(|entry| entry.bytes).sum(),
                    }
                });
            // A failed update is not run again.
            settled |= result.is_err();
            last = Some(job);
            if done.send(result).is_err() {
                return;
            }
        }
    }
}

/// The Bevy lights relight reads each frame.
pub type RelightLights<'w, 's> = Query<
    'w,
    's,
    (
        &'static RelightLight,
        &'static GlobalTransform,
        Option<&'static PointLight>,
        Option<&'static SpotLight>,
        Option<&'static DirectionalLight>,
    ),
>;

/// The scene's moving meshes as the app has placed them.
pub type RelightMovingMeshes<'w, 's> =
    Query<'w, 's, (&'static RelightMovingMesh, &'static GlobalTransform)>;

/// The lights as relight sees them, in [`RelightLight`] order, in the
/// space of the scene entity whose global transform is `scene` (relight's
/// scene lives there).
pub fn relight_lights(lights: &RelightLights, scene: &GlobalTransform) -> Vec<Light> {
    let to_scene = scene.affine().inverse();
    let mut ordered: Vec<(usize, Light)> = lights
        .iter()
        .filter_map(|(marker, transform, point, spot, directional)| {
            let in_scene = GlobalTransform::from(to_scene * transform.affine());
            crate::convert::bevy_light_to_relight(&in_scene, point, spot, directional)
                .map(|light| (marker.0, light))
        })
        .collect();
    ordered.sort_by_key(|(index, _)| *index);
    ordered.into_iter().map(|(_, light)| light).collect()
}

/// Writes the poses (mesh space to the scene entity's space) of `scene`'s
/// moving meshes into `poses`, indexed by [`RelightMovingMesh::index`];
/// meshes that are gone keep what `poses` held.
pub fn read_moving_mesh_poses(
    meshes: &RelightMovingMeshes,
    scene: Entity,
    scene_transform: &GlobalTransform,
    poses: &mut [relight_core::Affine3A],
) {
    let to_scene = scene_transform.affine().inverse();
    for (mesh, transform) in meshes {
        if mesh.scene == scene {
            if let Some(pose) = poses.get_mut(mesh.index) {
                *pose = crate::convert::pose_of(to_scene * transform.affine());
            }
        }
    }
}

fn fail(status: &mut RelightStatus, message: String) {
    error!("relight: {message}");
    *status = RelightStatus::Failed(message);
}

/// Each frame: take a finished update (moving its bytes into the images),
/// then hand the worker this frame's lights if it is free.
fn exchange_with_worker(
    mut scenes: Query<(
        Entity,
        &GlobalTransform,
        &mut Worker,
        &mut RelightStats,
        &mut RelightStatus,
    )>,
    lights: RelightLights,
    moving_meshes: RelightMovingMeshes,
    cameras: Query<(&Camera, &GlobalTransform, &Projection), With<Camera3d>>,
    mut images: ResMut<Assets<Image>>,
    frame_count: Res<FrameCount>,
) {
    for (entity, root, mut worker, mut stats, mut status) in &mut scenes {
        let start = Instant::now();
        let now = u64::from(frame_count.0);
        let finished = worker.done.lock().unwrap().try_recv();
        match finished {
            Ok(Ok(done)) => {
                match done.lightmap {
                    Some(lightmap) => {
                        if let Some(mut image) = images.get_mut(&worker.lightmap) {
                            image.data = Some(lightmap);
                        }
                        stats.updates += 1;
                        stats.stages = done.stages;
                        stats.memory_bytes = done.memory_bytes;
                    }
                    None => stats.skipped_updates += 1,
                }
                if let (Some(bytes), Some(handle)) = (done.volume, worker.volume.clone()) {
                    if let Some(mut image) = images.get_mut(&handle) {
                        image.data = Some(bytes);
                    }
                }
                stats.settled = done.settled && worker.posted_frame == Some(done.frame);
                worker.shown_frame = Some(done.frame);
            }
            Ok(Err(message)) => {
                fail(&mut status, message);
                continue;
            }
            Err(TryRecvError::Disconnected) => {
                fail(&mut status, "the relight worker stopped".into());
                continue;
            }
            Err(TryRecvError::Empty) => {}
        }
        if let Some(shown) = worker.shown_frame {
            stats.gi_age_frames = now.saturating_sub(shown);
        }
        if *status == RelightStatus::Running {
            // relight's scene lives in the scene entity's space.
            read_moving_mesh_poses(&moving_meshes, entity, root, &mut worker.moving_mesh_poses);
            let state = SceneState {
                lights: relight_lights(&lights, root),
                camera: cameras
                    .iter()
                    .filter(|(camera, _, _)| camera.is_active)
                    .max_by_key(|(camera, _, _)| camera.order)
                    .map(|(_, transform, projection)| {
                        crate::convert::relight_camera(transform, projection)
                    }),
                moving_mesh_poses: (!worker.moving_mesh_poses.is_empty())
                    .then(|| worker.moving_mesh_poses.clone()),
            };
            // A changed scene replaces whatever job is waiting; the
            // technique skips a state that changes nothing it reads (the
            // camera, mostly), and the worker settles a resting scene by
            // itself.
            if worker.posted.as_ref() != Some(&state) {
                worker.posted = Some(state.clone());
                worker.posted_frame = Some(now);
                stats.settled = false;
                worker.mailbox.post(Job { state, frame: now });
            }
        }
        stats.bridge_ms = start.elapsed().as_secs_f64() * 1e3;
    }
}
