//! Moving meshes: the scene file's `[[dynamic]]` tables. Each names a mesh
//! file and a pose (translation, rotation in degrees about x, y, z) and may
//! move linearly (`velocity`, metres per frame) and turn (`spin`, degrees
//! per frame about x, y, z). Their geometry lives in mesh space; every
//! frame it is placed in the world, a small BVH is built over it, and the
//! sparse points fixed to it move with it.

use crate::LightSkinError;
use glam::{Affine3A, EulerRot, Quat, Vec3};
use relight_core::Rgb;
use relight_scene::{Material, Mesh, Scene};
use relight_trace::Bvh;
use serde::Deserialize;
use std::path::{Path, PathBuf};

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct RawDynamic {
    mesh: String,
    #[serde(default)]
    translation: [f32; 3],
    #[serde(default)]
    rotation: [f32; 3],
    #[serde(default)]
    velocity: [f32; 3],
    #[serde(default)]
    spin: [f32; 3],
}

/// One moving mesh in its own space.
#[derive(Clone, Debug)]
pub struct DynamicMesh {
    pub path: PathBuf,
    pub mesh: Mesh,
    /// Materials of `mesh.material_ids`, textures folded into their albedo
    /// (moving meshes have no lightmap).
    pub materials: Vec<Material>,
    pub translation: Vec3,
    pub rotation: Vec3,
    pub velocity: Vec3,
    pub spin: Vec3,
}

impl DynamicMesh {
    /// Mesh space to world space at `frame`.
    pub fn pose(&self, frame: u64) -> Affine3A {
        self.pose_between_frames(frame as f32)
    }

    /// [`Self::pose`] at a fractional frame (an app animating the script
    /// smoothly between frames).
    pub fn pose_between_frames(&self, frame: f32) -> Affine3A {
        let angles = (self.rotation + self.spin * frame) * (std::f32::consts::PI / 180.0);
        let rotation = Quat::from_euler(EulerRot::XYZ, angles.x, angles.y, angles.z);
        Affine3A::from_rotation_translation(rotation, self.translation + self.velocity * frame)
    }
}

/// Reads the `[[dynamic]]` tables of `scene` (none: empty list).
pub fn load_dynamic_meshes(scene: &Scene) -> Result<Vec<DynamicMesh>, LightSkinError> {
    let Some(value) = scene.technique_sections.get("dynamic") else {
        return Ok(Vec::new());
    };
    let scene_file = scene.source.display().to_string();
    let entries: Vec<RawDynamic> =
        value
            .clone()
            .try_into()
            .map_err(|error: toml::de::Error| LightSkinError::Scene {
                path: scene.source.clone(),
                message: format!(
                    "[[dynamic]]: {error}; each entry needs `mesh = \"file.obj\"` and may set translation, rotation, velocity and spin as [x, y, z]"
                ),
            })?;
    let folder = scene.source.parent().unwrap_or(Path::new("."));
    let mut meshes = Vec::with_capacity(entries.len());
    for (index, entry) in entries.into_iter().enumerate() {
        let vectors = [
            ("translation", entry.translation),
            ("rotation", entry.rotation),
            ("velocity", entry.velocity),
            ("spin", entry.spin),
        ];
        for (name, vector) in vectors {
            if !vector.iter().all(|v| v.is_finite()) {
                return Err(LightSkinError::Scene {
                    path: scene.source.clone(),
                    message: format!(
                        "[[dynamic]] entry {}: `{name}` must be three finite numbers",
                        index + 1
                    ),
                });
            }
        }
        let path = folder.join(&entry.mesh);
        let (mesh, mut materials) =
            relight_scene::load_mesh(&path).map_err(|error| LightSkinError::Scene {
                path: scene.source.clone(),
                message: format!("[[dynamic]] entry {} ({scene_file}): {error}", index + 1),
            })?;
        // Moving meshes reflect; light sources stay static (the emitter
        // table is built once per scene).
        for material in &mut materials {
            material.emission = Rgb::ZERO;
        }
        meshes.push(DynamicMesh {
            path,
            mesh,
            materials,
            translation: Vec3::from_array(entry.translation),
            rotation: Vec3::from_array(entry.rotation),
            velocity: Vec3::from_array(entry.velocity),
            spin: Vec3::from_array(entry.spin),
        });
    }
    Ok(meshes)
}

/// All moving meshes placed in the world for one frame.
pub struct DynamicWorld {
    pub positions: Vec<Vec3>,
    pub triangles: Vec<[u32; 3]>,
    pub triangle_normals: Vec<Vec3>,
    /// Every mesh's materials, concatenated, and each triangle's index
    /// into them.
    pub materials: Vec<Material>,
    pub material_ids: Vec<u32>,
    /// First triangle and first vertex of each mesh.
    pub triangle_offsets: Vec<u32>,
    pub vertex_offsets: Vec<u32>,
    pub poses: Vec<Affine3A>,
    pub bvh: Bvh,
}

impl DynamicWorld {
    /// `meshes` at `poses` (one each, mesh space to world).
    pub fn place(meshes: &[DynamicMesh], poses: &[Affine3A]) -> Self {
        let mut positions = Vec::new();
        let mut triangles = Vec::new();
        let mut materials = Vec::new();
        let mut material_ids = Vec::new();
        let mut triangle_offsets = Vec::with_capacity(meshes.len());
        let mut vertex_offsets = Vec::with_capacity(meshes.len());
        for (mesh, &pose) in meshes.iter().zip(poses) {
            let first_vertex = positions.len() as u32;
            triangle_offsets.push(triangles.len() as u32);
            vertex_offsets.push(first_vertex);
            positions.extend(
                mesh.mesh
                    .positions
                    .iter()
                    .map(|&p| pose.transform_point3(p)),
            );
            triangles.extend(
                mesh.mesh
                    .triangles
                    .iter()
                    .map(|t| t.map(|v| v + first_vertex)),
            );
            let first_material = materials.len() as u32;
            material_ids.extend(mesh.mesh.material_ids.iter().map(|&id| id + first_material));
            materials.extend_from_slice(&mesh.materials);
        }
        let triangle_normals = triangles
            .iter()
            .map(|&[a, b, c]| {
                let [a, b, c] = [a, b, c].map(|v| positions[v as usize]);
                (b - a).cross(c - a).normalize_or_zero()
            })
            .collect();
        let bvh = Bvh::build(&positions, &triangles);
        Self {
            positions,
            triangles,
            triangle_normals,
            materials,
            material_ids,
            triangle_offsets,
            vertex_offsets,
            poses: poses.to_vec(),
            bvh,
        }
    }

    /// The static scene with this frame's moving meshes appended (static
    /// triangles keep their indices): what a renderer traces for a frame.
    pub fn merged_into(&self, scene: &Scene) -> Scene {
        let mut merged = scene.clone();
        let first_vertex = merged.mesh.positions.len() as u32;
        let first_material = merged.materials.len() as u32;
        merged.mesh.positions.extend_from_slice(&self.positions);
        merged
            .mesh
            .triangles
            .extend(self.triangles.iter().map(|t| t.map(|v| v + first_vertex)));
        if !merged.mesh.lightmap_uvs.is_empty() {
            merged
                .mesh
                .lightmap_uvs
                .resize(merged.mesh.positions.len(), glam::Vec2::ZERO);
        }
        if !merged.mesh.texcoords.is_empty() {
            merged
                .mesh
                .texcoords
                .resize(merged.mesh.positions.len(), glam::Vec2::ZERO);
        }
        merged.materials.extend_from_slice(&self.materials);
        merged
            .mesh
            .material_ids
            .extend(self.material_ids.iter().map(|&id| id + first_material));
        merged
    }
}
