//! Adopting a glTF scene the app has Bevy load itself: its mesh entities
//! keep their materials, names and components and get relight's atlas as
//! UV 1 and the lightmap; its lights become the lights relight reads.
//!
//! relight loads the same file and records, for each triangle-list
//! primitive each node places (`Scene::gltf_primitives`), the node's
//! world transform and the scene triangle each file triangle became. A
//! Bevy mesh entity names its primitive in its mesh handle's label
//! (`Mesh{m}/Primitive{p}`, as Bevy's glTF loader writes it); among the
//! nodes that place that primitive, its transform relative to the scene
//! entity picks the node. Each entity's mesh is then copied with one
//! vertex per triangle corner (atlas charts have seams the file's vertices
//! do not) and relight's atlas UVs, after its corners are checked against
//! relight's copy, so a different file or a changed mesh is an error
//! instead of a scrambled lightmap.

use crate::convert;
use bevy::mesh::{Indices, PrimitiveTopology, VertexAttributeValues};
use bevy::prelude::*;
use relight_scene::{GltfPrimitive, Light, Scene};
use std::collections::HashMap;

/// A mesh entity of the adopted scene, as the plugin found it.
pub(crate) struct MeshEntity<'a> {
    pub entity: Entity,
    pub name: Option<&'a str>,
    /// Its mesh handle's label (`Mesh0/Primitive1`), if it has one.
    pub label: Option<&'a str>,
    /// Mesh space to the scene entity's space.
    pub to_scene: Mat4,
    pub mesh: &'a Mesh,
    pub material: Option<Handle<StandardMaterial>>,
}

/// A mesh entity's replacement mesh, with relight's atlas as UV 1.
pub(crate) struct AdoptedMesh {
    pub entity: Entity,
    pub mesh: Mesh,
    pub material: Option<Handle<StandardMaterial>>,
    /// relight's material of its triangles (`None`: all degenerate).
    pub relight_material: Option<u32>,
}

/// What adoption found: meshes to replace, and the entities not adopted
/// (for a warning: they get no lightmap).
pub(crate) struct MeshAdoption {
    pub meshes: Vec<AdoptedMesh>,
    pub skipped: Vec<String>,
}

/// Matches the scene's mesh entities with relight's glTF primitives and
/// builds their lightmapped meshes. An entity that names a primitive
/// relight has but matches none of its placements, or whose triangles are
/// not relight's, is an error naming it.
pub(crate) fn adopt_meshes(
    scene: &Scene,
    atlas: &relight_scene::atlas::Atlas,
    entities: &[MeshEntity],
) -> Result<MeshAdoption, String> {
    if scene.gltf_primitives.is_empty() {
        return Err(format!(
            "{}: relight's scene has no glTF mesh primitives to adopt; adoption needs the glTF file (or a scene file whose mesh is it) that Bevy loads",
            scene.source.display()
        ));
    }
    let mut placements: HashMap<(u32, u32), Vec<usize>> = HashMap::new();
    for (index, record) in scene.gltf_primitives.iter().enumerate() {
        placements
            .entry((record.mesh, record.primitive))
            .or_default()
            .push(index);
    }
    let tolerance = place_tolerance(scene);
    let size = Vec2::new(atlas.width as f32, atlas.height as f32);
    let mut used = vec![false; scene.gltf_primitives.len()];
    let mut adoption = MeshAdoption {
        meshes: Vec::new(),
        skipped: Vec::new(),
    };
    for found in entities {
        let what = || {
            format!(
                "mesh entity {}{}",
                found.name.unwrap_or("(unnamed)"),
                found
                    .label
                    .map(|label| format!(" ({label})"))
                    .unwrap_or_default()
            )
        };
        let Some((mesh_index, primitive_index)) = found.label.and_then(primitive_of_label) else {
            adoption.skipped.push(what());
            continue;
        };
        let Some(candidates) = placements.get(&(mesh_index, primitive_index)) else {
            // Strips and fans, and primitives outside the file's scene.
            adoption.skipped.push(what());
            continue;
        };
        let best = candidates
            .iter()
            .copied()
            .filter(|&index| !used[index])
            .map(|index| {
                let world = to_bevy(scene.gltf_primitives[index].world);
                (index, max_difference(world, found.to_scene))
            })
            .min_by(|a, b| a.1.total_cmp(&b.1));
        let scale = found
            .to_scene
            .to_cols_array()
            .iter()
            .fold(1.0f32, |m, v| m.max(v.abs()));
        let Some((index, _)) = best.filter(|(_, difference)| *difference <= 1e-4 * scale) else {
            return Err(format!(
                "{}: no node of {} places glTF mesh {mesh_index} primitive {primitive_index} where Bevy has it; adopt a scene whose root is the entity with the RelightScene, loaded without coordinate conversion",
                what(),
                scene.source.display()
            ));
        };
        used[index] = true;
        let record = &scene.gltf_primitives[index];
        let uv1 = corner_lightmap_uvs(scene, atlas, record, found, tolerance, size)
            .map_err(|message| format!("{}: {message}", what()))?;
        let mut mesh = found.mesh.clone();
        // Bevy 0.19.1's StandardMaterial shader samples its textures at
        // UV 0 whenever a mesh has any UVs, so a mesh with UV 1 alone fails
        // to compile its pipeline and is not drawn: untextured glTF
        // meshes (no TEXCOORD_0) get zeros.
        if !mesh.contains_attribute(Mesh::ATTRIBUTE_UV_0) {
            let vertices = mesh.count_vertices();
            mesh.try_insert_attribute(Mesh::ATTRIBUTE_UV_0, vec![[0.0f32, 0.0]; vertices])
                .map_err(|error| format!("{}: {error}", what()))?;
        }
        mesh.try_duplicate_vertices()
            .and_then(|()| mesh.try_insert_attribute(Mesh::ATTRIBUTE_UV_1, uv1))
            .map_err(|error| format!("{}: {error}", what()))?;
        adoption.meshes.push(AdoptedMesh {
            entity: found.entity,
            mesh,
            material: found.material.clone(),
            relight_material: record
                .triangles
                .iter()
                .flatten()
                .next()
                .map(|&triangle| scene.mesh.material_ids[triangle as usize]),
        });
    }
    Ok(adoption)
}

/// How far apart Bevy's and relight's copies of one point may be: the
/// float error of composing node transforms in the two glams, relative to
/// the scene's size; a different mesh or light is off by far more.
fn place_tolerance(scene: &Scene) -> f32 {
    let (lo, hi) = scene.mesh.bounds();
    1e-4 * (hi - lo).length().max(1e-3)
}

/// `Mesh{m}/Primitive{p}` as (m, p).
fn primitive_of_label(label: &str) -> Option<(u32, u32)> {
    let (mesh, primitive) = label.strip_prefix("Mesh")?.split_once("/Primitive")?;
    Some((mesh.parse().ok()?, primitive.parse().ok()?))
}

/// relight's glam and Bevy's are different versions.
fn to_bevy(matrix: relight_core::Mat4) -> Mat4 {
    Mat4::from_cols_array(&matrix.to_cols_array())
}

fn max_difference(a: Mat4, b: Mat4) -> f32 {
    a.to_cols_array()
        .iter()
        .zip(b.to_cols_array())
        .fold(0.0f32, |m, (x, y)| m.max((x - y).abs()))
}

/// Relight's atlas UV (0..1) of each corner of the entity's mesh, in the
/// order `Mesh::duplicate_vertices` lays them out, after checking each
/// corner against relight's copy of the triangle.
fn corner_lightmap_uvs(
    scene: &Scene,
    atlas: &relight_scene::atlas::Atlas,
    record: &GltfPrimitive,
    found: &MeshEntity,
    tolerance: f32,
    size: Vec2,
) -> Result<Vec<[f32; 2]>, String> {
    let mesh = found.mesh;
    if mesh.primitive_topology() != PrimitiveTopology::TriangleList {
        return Err(format!(
            "its mesh is a {:?}, relight's copy a triangle list",
            mesh.primitive_topology()
        ));
    }
    let positions = match mesh.try_attribute(Mesh::ATTRIBUTE_POSITION) {
        Ok(VertexAttributeValues::Float32x3(positions)) => positions,
        Ok(_) => return Err("its positions are not three floats a vertex".into()),
        Err(error) => {
            return Err(format!(
                "{error}: keep the glTF's meshes in the main world (GltfLoaderSettings::load_meshes with MAIN_WORLD) until relight has adopted them"
            ))
        }
    };
    let corners: Vec<usize> = match mesh.try_indices_option().map_err(|e| e.to_string())? {
        Some(Indices::U16(indices)) => indices.iter().map(|&i| i as usize).collect(),
        Some(Indices::U32(indices)) => indices.iter().map(|&i| i as usize).collect(),
        None => (0..positions.len()).collect(),
    };
    let triangle_count = corners.len() / 3;
    if triangle_count != record.triangles.len() || !corners.len().is_multiple_of(3) {
        return Err(format!(
            "it has {} corners, relight's copy of node {} {} triangles: is it the same file?",
            corners.len(),
            record.node,
            record.triangles.len()
        ));
    }
    // relight swapped corners 1 and 2 under a mirroring node.
    let relight_corner = if record.mirrored {
        [0, 2, 1]
    } else {
        [0, 1, 2]
    };
    let mut uvs = Vec::with_capacity(corners.len());
    for (triangle, file_corners) in record.triangles.iter().zip(corners.chunks_exact(3)) {
        let Some(scene_triangle) = triangle.map(|t| t as usize) else {
            // Dropped as degenerate (no area to light), or cut into pieces
            // for the lightmap's coarser rings far out, which one triangle's
            // UVs cannot follow (the scene's warnings say so).
            uvs.extend([[0.0, 0.0]; 3]);
            continue;
        };
        let placed = scene.mesh.vertices(scene_triangle);
        let chart = atlas.triangle_uvs[scene_triangle];
        for (corner, &vertex) in file_corners.iter().enumerate() {
            let position = positions.get(vertex).ok_or_else(|| {
                format!("index {vertex} is past its {} vertices", positions.len())
            })?;
            let in_scene = found.to_scene.transform_point3(Vec3::from_array(*position));
            let relight = convert::vec3(placed[relight_corner[corner]]);
            if in_scene.distance(relight) > tolerance {
                return Err(format!(
                    "its triangle {} is at {in_scene}, relight's copy at {relight}: is it the same file?",
                    uvs.len() / 3
                ));
            }
            uvs.push(
                (Vec2::from_array(chart[relight_corner[corner]].to_array()) / size).to_array(),
            );
        }
    }
    Ok(uvs)
}

/// For each Bevy light of the adopted scene (kind, position and direction
/// in the scene entity's space, as `bevy_light_to_relight` reads them),
/// the scene light it is, matched by kind, place and direction; each scene
/// light at most once.
pub(crate) fn match_lights(scene: &Scene, found: &[Light]) -> Vec<Option<usize>> {
    let tolerance = place_tolerance(scene);
    let mut taken = vec![false; scene.lights.len()];
    found
        .iter()
        .map(|light| {
            let index = scene
                .lights
                .iter()
                .enumerate()
                .position(|(index, candidate)| {
                    !taken[index] && same_place(light, candidate, tolerance)
                })?;
            taken[index] = true;
            Some(index)
        })
        .collect()
}

fn same_place(a: &Light, b: &Light, tolerance: f32) -> bool {
    let aligned = |d: relight_core::Vec3, e: relight_core::Vec3| d.dot(e) > 1.0 - 1e-4;
    match (a, b) {
        (Light::Point { position: p, .. }, Light::Point { position: q, .. }) => {
            p.distance(*q) <= tolerance
        }
        (
            Light::Spot {
                position: p,
                direction: d,
                ..
            },
            Light::Spot {
                position: q,
                direction: e,
                ..
            },
        ) => p.distance(*q) <= tolerance && aligned(*d, *e),
        (Light::Directional { direction: d, .. }, Light::Directional { direction: e, .. }) => {
            aligned(*d, *e)
        }
        _ => false,
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use bevy::asset::RenderAssetUsages;
    use relight_scene::atlas::{Atlas, TexelDensity};

    /// A unit quad (two triangles) as glTF mesh 0 primitive 0, placed by
    /// node 3 at x + 2 and, mirrored in x, by node 5 at x + 6; file
    /// triangle 0 of node 5 was dropped as degenerate.
    fn two_placements() -> (Scene, Atlas) {
        let corners = [
            [0.0, 0.0, 0.0],
            [1.0, 0.0, 0.0],
            [1.0, 1.0, 0.0],
            [0.0, 1.0, 0.0],
        ];
        let file_triangles = [[0u32, 1, 2], [0, 2, 3]];
        let place = relight_core::Mat4::from_translation(relight_core::Vec3::new(2.0, 0.0, 0.0));
        let mirror = relight_core::Mat4::from_translation(relight_core::Vec3::new(6.0, 0.0, 0.0))
            * relight_core::Mat4::from_scale(relight_core::Vec3::new(-1.0, 1.0, 1.0));
        let mut mesh = relight_scene::Mesh::default();
        for world in [place, mirror] {
            let base = mesh.positions.len() as u32;
            mesh.positions
                .extend(corners.map(|c| world.transform_point3(relight_core::Vec3::from_array(c))));
            let mirrored = world.determinant() < 0.0;
            for (index, triangle) in file_triangles.iter().enumerate() {
                if mirrored && index == 0 {
                    continue;
                }
                let [a, b, c] = triangle.map(|corner| corner + base);
                mesh.triangles
                    .push(if mirrored { [a, c, b] } else { [a, b, c] });
                mesh.material_ids.push(0);
            }
        }
        let record = |node, world, mirrored, triangles| GltfPrimitive {
            node,
            mesh: 0,
            primitive: 0,
            world,
            mirrored,
            triangles,
        };
        let scene = Scene {
            mesh,
            materials: vec![relight_scene::Material::default()],
            gltf_primitives: vec![
                record(3, place, false, vec![Some(0), Some(1)]),
                record(5, mirror, true, vec![None, Some(2)]),
            ],
            ..Scene::default()
        };
        let atlas = Atlas::build(&scene, TexelDensity::TargetResolution(64)).unwrap();
        (scene, atlas)
    }

    fn bevy_quad() -> Mesh {
        Mesh::new(
            PrimitiveTopology::TriangleList,
            RenderAssetUsages::default(),
        )
        .with_inserted_attribute(
            Mesh::ATTRIBUTE_POSITION,
            vec![
                [0.0f32, 0.0, 0.0],
                [1.0, 0.0, 0.0],
                [1.0, 1.0, 0.0],
                [0.0, 1.0, 0.0],
            ],
        )
        .with_inserted_indices(Indices::U16(vec![0, 1, 2, 0, 2, 3]))
    }

    fn entity<'a>(index: u32, mesh: &'a Mesh, to_scene: Mat4) -> MeshEntity<'a> {
        MeshEntity {
            entity: Entity::from_raw_u32(index).unwrap(),
            name: None,
            label: Some("Mesh0/Primitive0"),
            to_scene,
            mesh,
            material: None,
        }
    }

    fn uvs(mesh: &Mesh) -> Vec<[f32; 2]> {
        match mesh.attribute(Mesh::ATTRIBUTE_UV_1) {
            Some(VertexAttributeValues::Float32x2(uvs)) => uvs.clone(),
            other => panic!("no UV 1: {other:?}"),
        }
    }

    /// Each entity finds its own placement whatever the order; UV 1 holds
    /// relight's atlas corners, the mirrored node's in swapped order.
    #[test]
    fn entities_find_their_placements_and_corners() {
        let (scene, atlas) = two_placements();
        let quad = bevy_quad();
        let mirror = Mat4::from_translation(Vec3::new(6.0, 0.0, 0.0))
            * Mat4::from_scale(Vec3::new(-1.0, 1.0, 1.0));
        let place = Mat4::from_translation(Vec3::new(2.0, 0.0, 0.0));
        let found = [entity(1, &quad, mirror), entity(2, &quad, place)];
        let adoption = adopt_meshes(&scene, &atlas, &found).unwrap();
        assert_eq!(adoption.meshes.len(), 2);
        let size = Vec2::new(atlas.width as f32, atlas.height as f32);
        let atlas_uv = |triangle: usize, corner: usize| {
            (Vec2::from_array(atlas.triangle_uvs[triangle][corner].to_array()) / size).to_array()
        };
        let mirrored = uvs(&adoption.meshes[0].mesh);
        assert_eq!(mirrored.len(), 6);
        // The dropped triangle gets zeros; the next is scene triangle 2
        // with corners 1 and 2 swapped.
        assert_eq!(&mirrored[..3], &[[0.0, 0.0]; 3]);
        assert_eq!(
            mirrored[3..],
            [atlas_uv(2, 0), atlas_uv(2, 2), atlas_uv(2, 1)]
        );
        let placed = uvs(&adoption.meshes[1].mesh);
        let expected: Vec<[f32; 2]> = (0..2)
            .flat_map(|triangle| (0..3).map(move |corner| (triangle, corner)))
            .map(|(triangle, corner)| atlas_uv(triangle, corner))
            .collect();
        assert_eq!(placed, expected);
        // Bevy's shader needs UV 0 where UV 1 is.
        assert!(adoption.meshes[1]
            .mesh
            .contains_attribute(Mesh::ATTRIBUTE_UV_0));
    }

    #[test]
    fn a_different_mesh_or_place_is_an_error_and_other_primitives_are_skipped() {
        let (scene, atlas) = two_placements();
        let place = Mat4::from_translation(Vec3::new(2.0, 0.0, 0.0));
        let mut moved = bevy_quad();
        if let Some(VertexAttributeValues::Float32x3(positions)) =
            moved.attribute_mut(Mesh::ATTRIBUTE_POSITION)
        {
            positions[2][2] = 0.1;
        }
        let message = adopt_meshes(&scene, &atlas, &[entity(1, &moved, place)])
            .err()
            .unwrap();
        assert!(message.contains("same file"), "{message}");
        let quad = bevy_quad();
        let nowhere = Mat4::from_translation(Vec3::new(9.0, 0.0, 0.0));
        let message = adopt_meshes(&scene, &atlas, &[entity(1, &quad, nowhere)])
            .err()
            .unwrap();
        assert!(message.contains("no node"), "{message}");
        let mut other = entity(1, &quad, place);
        other.label = Some("Mesh1/Primitive0");
        let adoption = adopt_meshes(&scene, &atlas, &[other]).unwrap();
        assert!(adoption.meshes.is_empty() && adoption.skipped.len() == 1);
    }

    #[test]
    fn lights_match_by_kind_and_place() {
        let (mut scene, _) = two_placements();
        let point = |x: f32| Light::Point {
            position: relight_core::Vec3::new(x, 0.5, 0.5),
            intensity: relight_core::Vec3::ONE,
        };
        scene.lights = vec![point(1.0), point(3.0)];
        let found = [point(3.0), point(1.0), point(7.0)];
        assert_eq!(match_lights(&scene, &found), vec![Some(1), Some(0), None]);
    }

    #[test]
    fn primitive_labels_parse() {
        assert_eq!(primitive_of_label("Mesh3/Primitive12"), Some((3, 12)));
        assert_eq!(primitive_of_label("Mesh3"), None);
        assert_eq!(primitive_of_label("Material0"), None);
        assert_eq!(primitive_of_label("Mesh/Primitive1"), None);
    }
}
