//! relight's scene as Bevy assets and components, and Bevy lights back as
//! relight lights, through relight_engine's one unit factor.

use bevy::asset::RenderAssetUsages;
use bevy::image::{ImageAddressMode, ImageFilterMode, ImageSampler, ImageSamplerDescriptor};
use bevy::mesh::{Indices, PrimitiveTopology};
use bevy::prelude::*;
use bevy::render::render_resource::{Extent3d, TextureDimension, TextureFormat};
use relight_core::Rgb;
use relight_engine::{
    directional_light_from_lux, directional_light_lux, ev100_matching_relight, look_rotation,
    point_light_from_lumens, point_light_lumens, roughness_of, LUMENS_PER_WATT,
};
use relight_scene::{Light, Scene};

/// relight's glam and Bevy's are different versions: values cross as
/// arrays.
pub(crate) fn vec3(value: relight_core::Vec3) -> Vec3 {
    Vec3::from_array(value.to_array())
}

fn rgb(value: Vec3) -> Rgb {
    Rgb::from_array(value.to_array())
}

fn linear(colour: Rgb) -> Color {
    Color::linear_rgb(colour.x, colour.y, colour.z)
}

/// The camera exposure at which Bevy's linear output equals relight's
/// radiance (W/(m^2 sr)) for the same scene.
pub fn matching_exposure() -> bevy::camera::Exposure {
    bevy::camera::Exposure {
        ev100: ev100_matching_relight(),
    }
}

/// The scene's primitives (`relight_engine::static_primitives`) as Bevy
/// meshes, with relight's atlas as UV 1.
pub(crate) fn static_meshes(
    scene: &Scene,
    atlas: &relight_scene::atlas::Atlas,
) -> Vec<(u32, Mesh)> {
    relight_engine::static_primitives(scene, atlas)
        .into_iter()
        .map(bevy_mesh)
        .collect()
}

/// A moving mesh's primitives (`relight_engine::moving_primitives`) as
/// Bevy meshes in the mesh's own space, without UV 1: Bevy lights them
/// from the irradiance volume.
pub(crate) fn moving_meshes(mesh: &relight_engine::MovingMesh) -> Vec<(u32, Mesh)> {
    relight_engine::moving_primitives(mesh)
        .into_iter()
        .map(bevy_mesh)
        .collect()
}

fn bevy_mesh(primitive: relight_engine::Primitive) -> (u32, Mesh) {
    let corners = primitive.positions.len() as u32;
    let mut mesh = Mesh::new(
        PrimitiveTopology::TriangleList,
        RenderAssetUsages::RENDER_WORLD,
    )
    .with_inserted_attribute(Mesh::ATTRIBUTE_POSITION, primitive.positions)
    .with_inserted_attribute(Mesh::ATTRIBUTE_NORMAL, primitive.normals)
    .with_inserted_attribute(Mesh::ATTRIBUTE_UV_0, primitive.uv0)
    .with_inserted_indices(Indices::U32((0..corners).collect()));
    if !primitive.uv1.is_empty() {
        mesh.insert_attribute(Mesh::ATTRIBUTE_UV_1, primitive.uv1);
    }
    (primitive.material, mesh)
}

/// A relight pose (mesh space to world) as a Bevy transform.
pub(crate) fn transform_of(pose: relight_core::Affine3A) -> Transform {
    Transform::from_matrix(Mat4::from_cols_array(
        &relight_core::Mat4::from(pose).to_cols_array(),
    ))
}

/// A Bevy affine transform as a relight pose.
pub(crate) fn pose_of(affine: bevy::math::Affine3A) -> relight_core::Affine3A {
    relight_core::Affine3A::from_cols_array(&affine.to_cols_array())
}

/// relight's Lambertian (or Blinn-Phong) material as a `StandardMaterial`:
/// metallic 0, emission in cd/m^2, the lightmap at exposure 1 (its texels
/// are already in cd/m^2). Lambertian materials get no specular
/// reflectance (relight has none) and perceptual roughness 0.5: Bevy's
/// diffuse is Burley's, whose grazing-angle factor f90 = 0.5 + 2 r
/// (L.H)^2 is at most 1 at roughness r = 0.25, the closest Burley comes to
/// Lambert (at the fully rough 1 it brightened the point-lit Cornell box's
/// direct light 9 % over relight's); with no specular lobe the roughness
/// changes nothing else. Glossy materials take the roughness relight's
/// glTF loader maps to their Phong exponent.
pub(crate) fn material(
    material: &relight_scene::Material,
    texture: Option<Handle<Image>>,
) -> StandardMaterial {
    let mut bevy_material = StandardMaterial {
        base_color: linear(material.albedo),
        base_color_texture: texture,
        emissive: LinearRgba::from(linear(material.emission * LUMENS_PER_WATT)),
        lightmap_exposure: 1.0,
        ..default()
    };
    relight_shading(&mut bevy_material, material);
    bevy_material
}

/// The `StandardMaterial` parameters of relight's lobe (see [`material`]);
/// colours, textures and emission stay.
pub(crate) fn relight_shading(
    bevy_material: &mut StandardMaterial,
    material: &relight_scene::Material,
) {
    let lambertian = material.phong_exponent <= 1.0;
    bevy_material.metallic = 0.0;
    bevy_material.perceptual_roughness = if lambertian {
        0.5
    } else {
        roughness_of(material.phong_exponent)
    };
    bevy_material.reflectance = if lambertian { 0.0 } else { 0.5 };
}

/// An albedo texture as sRGB bytes with repeat addressing.
pub(crate) fn albedo_image(texture: &relight_scene::Texture) -> Image {
    use relight_core::colour::linear_to_srgb8 as encode;
    let data = texture
        .texels
        .iter()
        .flat_map(|texel| [encode(texel.x), encode(texel.y), encode(texel.z), 255])
        .collect();
    let mut image = Image::new(
        Extent3d {
            width: texture.width,
            height: texture.height,
            depth_or_array_layers: 1,
        },
        TextureDimension::D2,
        data,
        TextureFormat::Rgba8UnormSrgb,
        RenderAssetUsages::RENDER_WORLD,
    );
    image.sampler = ImageSampler::Descriptor(ImageSamplerDescriptor {
        address_mode_u: ImageAddressMode::Repeat,
        address_mode_v: ImageAddressMode::Repeat,
        mag_filter: ImageFilterMode::Linear,
        min_filter: ImageFilterMode::Linear,
        ..default()
    });
    image
}

/// An RGBA16F texture (2D, or 3D with `depth` > 1) the worker refills:
/// bilinear and clamped (the lightmap's gutters hold its charts' edges;
/// Bevy's volume lookup clamps itself). Render-world only, so each upload
/// moves the bytes instead of copying them.
pub(crate) fn float_image(width: u32, height: u32, depth: u32, data: Vec<u8>) -> Image {
    let mut image = Image::new(
        Extent3d {
            width,
            height,
            depth_or_array_layers: depth,
        },
        if depth > 1 {
            TextureDimension::D3
        } else {
            TextureDimension::D2
        },
        data,
        TextureFormat::Rgba16Float,
        RenderAssetUsages::RENDER_WORLD,
    );
    image.sampler = ImageSampler::Descriptor(ImageSamplerDescriptor {
        address_mode_u: ImageAddressMode::ClampToEdge,
        address_mode_v: ImageAddressMode::ClampToEdge,
        address_mode_w: ImageAddressMode::ClampToEdge,
        mag_filter: ImageFilterMode::Linear,
        min_filter: ImageFilterMode::Linear,
        ..default()
    });
    image
}

/// A relight light as a Bevy light bundle with shadow maps, placed by
/// [`light_transform`]; `range` is where Bevy may cut point and spot
/// lights off (relight's fall off with the inverse square only, so give
/// the scene's size).
pub(crate) fn bevy_light(light: &Light, range: f32, commands: &mut EntityCommands) {
    commands.insert(light_transform(light));
    insert_light_values(light, range, commands);
}

/// A relight light's Bevy light component (colour, intensity, cone,
/// shadow maps), for an entity already in its place.
pub(crate) fn insert_light_values(light: &Light, range: f32, commands: &mut EntityCommands) {
    match *light {
        Light::Point { intensity, .. } => {
            let (colour, lumens) = point_light_lumens(intensity);
            commands.insert(PointLight {
                color: linear(colour),
                intensity: lumens,
                range,
                shadow_maps_enabled: true,
                ..default()
            });
        }
        Light::Spot {
            intensity,
            inner_angle,
            outer_angle,
            ..
        } => {
            let (colour, lumens) = point_light_lumens(intensity);
            commands.insert(SpotLight {
                color: linear(colour),
                intensity: lumens,
                range,
                inner_angle,
                outer_angle,
                shadow_maps_enabled: true,
                ..default()
            });
        }
        Light::Directional { irradiance, .. } => {
            let (colour, lux) = directional_light_lux(irradiance);
            commands.insert(DirectionalLight {
                color: linear(colour),
                illuminance: lux,
                shadow_maps_enabled: true,
                ..default()
            });
        }
    }
}

/// Where a relight light sits in Bevy: point lights at their position,
/// spot and directional lights looking along their direction.
pub fn light_transform(light: &Light) -> Transform {
    let looking_along = |direction: relight_core::Vec3| {
        Quat::from_array(look_rotation(direction, relight_core::Vec3::Y).to_array())
    };
    match *light {
        Light::Point { position, .. } => Transform::from_translation(vec3(position)),
        Light::Spot {
            position,
            direction,
            ..
        } => Transform::from_translation(vec3(position)).with_rotation(looking_along(direction)),
        Light::Directional { direction, .. } => Transform::from_rotation(looking_along(direction)),
    }
}

/// A Bevy light as the app has it now (its global transform, colour and
/// intensity) in relight's units; `None` for entities without one.
pub fn bevy_light_to_relight(
    transform: &GlobalTransform,
    point: Option<&PointLight>,
    spot: Option<&SpotLight>,
    directional: Option<&DirectionalLight>,
) -> Option<Light> {
    let colour = |color: Color| {
        let linear = color.to_linear();
        rgb(Vec3::new(linear.red, linear.green, linear.blue))
    };
    let position = relight_core::Vec3::from_array(transform.translation().to_array());
    let forward = relight_core::Vec3::from_array(transform.forward().as_vec3().to_array());
    if let Some(light) = point {
        return Some(Light::Point {
            position,
            intensity: point_light_from_lumens(colour(light.color), light.intensity),
        });
    }
    if let Some(light) = spot {
        return Some(Light::Spot {
            position,
            direction: forward,
            intensity: point_light_from_lumens(colour(light.color), light.intensity),
            inner_angle: light.inner_angle,
            outer_angle: light.outer_angle,
        });
    }
    directional.map(|light| Light::Directional {
        direction: forward,
        irradiance: directional_light_from_lux(colour(light.color), light.illuminance),
    })
}

/// A Bevy camera as relight's: eye, a point ahead, up and field of view
/// (what view-dependent light needs; the resolution is not used).
pub fn relight_camera(
    transform: &GlobalTransform,
    projection: &Projection,
) -> relight_scene::Camera {
    let v = |value: Vec3| relight_core::Vec3::from_array(value.to_array());
    let eye = transform.translation();
    let fov_y_degrees = match projection {
        Projection::Perspective(perspective) => perspective.fov.to_degrees(),
        _ => relight_scene::Camera::default().fov_y_degrees,
    };
    relight_scene::Camera {
        eye: v(eye),
        target: v(eye + transform.forward().as_vec3()),
        up: v(transform.up().as_vec3()),
        fov_y_degrees,
        ..relight_scene::Camera::default()
    }
}

/// The scene camera's Bevy transform and projection.
pub(crate) fn camera(camera: &relight_scene::Camera) -> (Transform, Projection) {
    let transform = Transform::from_translation(vec3(camera.eye))
        .looking_at(vec3(camera.target), vec3(camera.up));
    let projection = Projection::Perspective(PerspectiveProjection {
        fov: camera.fov_y_degrees.to_radians(),
        aspect_ratio: camera.resolution[0] as f32 / camera.resolution[1].max(1) as f32,
        near: 0.01,
        ..default()
    });
    (transform, projection)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn cameras_come_back_as_they_went() {
        let scene_camera = relight_scene::Camera {
            eye: relight_core::Vec3::new(1.0, 2.0, 3.0),
            target: relight_core::Vec3::new(0.0, 1.0, 0.0),
            up: relight_core::Vec3::Y,
            fov_y_degrees: 50.0,
            resolution: [64, 32],
        };
        let (transform, projection) = camera(&scene_camera);
        let back = relight_camera(&GlobalTransform::from(transform), &projection);
        let forward = |c: &relight_scene::Camera| (c.target - c.eye).normalize();
        assert!((back.eye - scene_camera.eye).length() < 1e-5);
        assert!((forward(&back) - forward(&scene_camera)).length() < 1e-5);
        assert!((back.fov_y_degrees - 50.0).abs() < 1e-3);
    }

    #[test]
    fn lights_come_back_as_they_went() {
        let lights = [
            Light::Point {
                position: relight_core::Vec3::new(1.0, 2.0, 3.0),
                intensity: Rgb::new(4.0, 2.0, 1.0),
            },
            Light::Spot {
                position: relight_core::Vec3::new(0.0, 3.0, 0.0),
                direction: relight_core::Vec3::new(0.2, -1.0, 0.1).normalize(),
                intensity: Rgb::splat(7.0),
                inner_angle: 0.3,
                outer_angle: 0.5,
            },
            Light::Directional {
                direction: relight_core::Vec3::new(0.3, -0.9, 0.2).normalize(),
                irradiance: Rgb::new(3.0, 3.0, 2.0),
            },
        ];
        let mut world = World::new();
        for light in &lights {
            let entity = world.spawn_empty();
            let id = entity.id();
            let mut queue = bevy::ecs::world::CommandQueue::default();
            let mut commands = Commands::new(&mut queue, &world);
            bevy_light(light, 100.0, &mut commands.entity(id));
            queue.apply(&mut world);
            let entity = world.entity(id);
            let transform = GlobalTransform::from(*entity.get::<Transform>().unwrap());
            let back = bevy_light_to_relight(
                &transform,
                entity.get::<PointLight>(),
                entity.get::<SpotLight>(),
                entity.get::<DirectionalLight>(),
            )
            .unwrap();
            let close = |a: relight_core::Vec3, b: relight_core::Vec3| (a - b).length() < 1e-4;
            match (light, &back) {
                (
                    Light::Point {
                        position: p,
                        intensity: i,
                    },
                    Light::Point {
                        position: q,
                        intensity: j,
                    },
                ) => assert!(close(*p, *q) && close(*i, *j)),
                (
                    Light::Spot {
                        position: p,
                        direction: d,
                        intensity: i,
                        ..
                    },
                    Light::Spot {
                        position: q,
                        direction: e,
                        intensity: j,
                        ..
                    },
                ) => assert!(close(*p, *q) && close(*d, *e) && close(*i, *j), "{back:?}"),
                (
                    Light::Directional {
                        direction: d,
                        irradiance: i,
                    },
                    Light::Directional {
                        direction: e,
                        irradiance: j,
                    },
                ) => assert!(close(*d, *e) && close(*i, *j), "{back:?}"),
                other => panic!("light changed kind: {other:?}"),
            }
        }
    }
}
