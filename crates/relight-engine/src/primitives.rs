//! The static scene as engines draw it: one primitive a material, three
//! vertices a triangle (relight's atlas gives every triangle corner its own
//! lightmap UV, so vertices cannot be shared), with flat normals (relight
//! shades with geometric normals).

use crate::MovingMesh;
use glam::Vec2;
use relight_scene::atlas::Atlas;
use relight_scene::{Mesh, Scene};

/// One material's triangles, unshared, as vertex arrays.
#[derive(Clone, Debug, Default)]
pub struct Primitive {
    pub material: u32,
    pub positions: Vec<[f32; 3]>,
    pub normals: Vec<[f32; 3]>,
    /// Albedo texture coordinates; zero where the mesh has none (Bevy
    /// 0.19's shader for a lightmapped mesh without them does not compile:
    /// "no definition in scope for identifier: uv").
    pub uv0: Vec<[f32; 2]>,
    /// The atlas's lightmap UVs, in 0..1 with row 0 at V = 0; empty for
    /// moving meshes.
    pub uv1: Vec<[f32; 2]>,
}

/// The scene's primitives, materials in order, those without triangles
/// left out.
pub fn static_primitives(scene: &Scene, atlas: &Atlas) -> Vec<Primitive> {
    let size = Vec2::new(atlas.width as f32, atlas.height as f32);
    primitives_of(&scene.mesh, scene.materials.len(), |triangle, corner| {
        Some((atlas.triangle_uvs[triangle][corner] / size).to_array())
    })
}

/// A moving mesh's primitives in its own space (`MovingMesh::mesh`, its
/// `materials`), without lightmap UVs: engines light moving meshes from
/// the irradiance volume.
pub fn moving_primitives(mesh: &MovingMesh) -> Vec<Primitive> {
    primitives_of(&mesh.mesh, mesh.materials.len(), |_, _| None)
}

fn primitives_of(
    mesh: &Mesh,
    material_count: usize,
    lightmap_uv: impl Fn(usize, usize) -> Option<[f32; 2]>,
) -> Vec<Primitive> {
    let mut primitives: Vec<Primitive> = (0..material_count as u32)
        .map(|material| Primitive {
            material,
            ..Primitive::default()
        })
        .collect();
    for (triangle, &material) in mesh.material_ids.iter().enumerate() {
        let Some(primitive) = primitives.get_mut(material as usize) else {
            continue;
        };
        let normal = mesh.geometric_normal(triangle).to_array();
        for (corner, &vertex) in mesh.triangles[triangle].iter().enumerate() {
            primitive
                .positions
                .push(mesh.positions[vertex as usize].to_array());
            primitive.normals.push(normal);
            let uv = mesh.texcoords.get(vertex as usize).copied();
            primitive.uv0.push(uv.unwrap_or(Vec2::ZERO).to_array());
            if let Some(uv1) = lightmap_uv(triangle, corner) {
                primitive.uv1.push(uv1);
            }
        }
    }
    primitives.retain(|primitive| !primitive.positions.is_empty());
    primitives
}
