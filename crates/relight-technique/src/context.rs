//! Everything built once per scene and shared by all techniques.

use glam::Vec3;
use relight_scene::atlas::{Atlas, TexelDensity};
use relight_scene::{Scene, SceneError};
use relight_trace::direct::{DirectLight, DirectSettings, Emitters};
use relight_trace::{Bvh, Ray};
use std::time::{Duration, Instant};

/// Settings that shape the shared scene data.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct ContextSettings {
    pub lightmap: TexelDensity,
    pub direct: DirectSettings,
}

/// Scene, BVH, lightmap atlas and emitter table, built once.
pub struct SceneContext {
    pub scene: Scene,
    pub bvh: Bvh,
    pub atlas: Atlas,
    pub emitters: Emitters,
    pub settings: ContextSettings,
    pub bvh_build_time: Duration,
    pub atlas_build_time: Duration,
}

impl SceneContext {
    pub fn new(scene: Scene, settings: ContextSettings) -> Result<Self, SceneError> {
        let start = Instant::now();
        let bvh = Bvh::build(&scene.mesh.positions, &scene.mesh.triangles);
        let bvh_build_time = start.elapsed();
        let start = Instant::now();
        let atlas = Atlas::build(&scene, settings.lightmap)?;
        let atlas_build_time = start.elapsed();
        let emitters = Emitters::from_scene(&scene);
        Ok(Self {
            scene,
            bvh,
            atlas,
            emitters,
            settings,
            bvh_build_time,
            atlas_build_time,
        })
    }

    /// The same context over `scene`, whose first triangles are this
    /// context's static triangles and whose rest are moving meshes placed
    /// for one frame (see [`crate::Technique::frame_geometry`]): BVH and
    /// emitters are rebuilt, the lightmap atlas of the static part is kept.
    pub fn with_frame_geometry(&self, scene: Scene) -> Self {
        let start = Instant::now();
        let bvh = Bvh::build(&scene.mesh.positions, &scene.mesh.triangles);
        let bvh_build_time = start.elapsed();
        let emitters = Emitters::from_scene(&scene);
        Self {
            scene,
            bvh,
            atlas: self.atlas.clone(),
            emitters,
            settings: self.settings,
            bvh_build_time,
            atlas_build_time: Duration::ZERO,
        }
    }

    /// What a bake made for this scene and lightmap records, and is checked
    /// against when loaded.
    pub fn fingerprint(&self) -> u64 {
        crate::scene_fingerprint(&self.scene, &self.atlas)
    }

    /// Fails unless a bake made for `bake_receivers` lightmap receivers fits
    /// this context's lightmap.
    pub fn check_bake_receivers(
        &self,
        technique: &str,
        bake_receivers: usize,
    ) -> Result<(), crate::TechniqueError> {
        let receivers = self.atlas.receivers.len();
        if bake_receivers == receivers {
            return Ok(());
        }
        Err(crate::TechniqueError::Other(format!(
            "this {} bake has {bake_receivers} receivers but the scene's lightmap has {receivers}: bake again with the same lightmap resolution",
            technique.to_uppercase()
        )))
    }

    /// The shared direct-light service over this scene.
    pub fn direct(&self) -> DirectLight<'_> {
        DirectLight::new(&self.scene, &self.bvh, &self.emitters, self.settings.direct)
    }

    /// True when `point` is inside geometry: more than a quarter of the test
    /// rays that hit something hit a back face (a point in a room sees front
    /// faces all round; a point inside a box or wall sees its back faces).
    pub fn is_inside_geometry(&self, point: Vec3) -> bool {
        let mut hits = 0;
        let mut back_hits = 0;
        for direction in enclosure_directions() {
            let ray = Ray {
                origin: point,
                direction,
                t_max: f32::INFINITY,
            };
            if let Some(hit) = self.bvh.intersect(&ray) {
                hits += 1;
                let normal = self.scene.mesh.geometric_normal(hit.triangle as usize);
                if normal.dot(direction) > 0.0 {
                    back_hits += 1;
                }
            }
        }
        back_hits * 4 > hits
    }
}

/// Directions that test whether a point is enclosed: the axes and the cube
/// diagonals.
fn enclosure_directions() -> [Vec3; 14] {
    let mut directions = [Vec3::ZERO; 14];
    let axes = [Vec3::X, Vec3::Y, Vec3::Z];
    for (index, axis) in axes.iter().enumerate() {
        directions[2 * index] = *axis;
        directions[2 * index + 1] = -*axis;
    }
    let mut slot = 6;
    for x in [-1.0f32, 1.0] {
        for y in [-1.0f32, 1.0] {
            for z in [-1.0f32, 1.0] {
                directions[slot] = Vec3::new(x, y, z).normalize();
                slot += 1;
            }
        }
    }
    directions
}
