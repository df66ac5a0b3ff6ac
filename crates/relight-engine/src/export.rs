//! `relight export`: the static scene as glTF 2.0 with its lightmap and
//! irradiance volume baked from a technique, for any engine.
//!
//! What a folder holds:
//! - `scene.gltf` and `scene.bin`: the static triangles, one primitive a
//!   material, with flat normals, `TEXCOORD_0` (albedo textures) and
//!   relight's atlas as `TEXCOORD_1`; materials as metallic-roughness
//!   (metallic 0, roughness from the Phong exponent as relight's glTF
//!   loader reads it back); lights (`KHR_lights_punctual`) and the camera.
//! - `textures/albedo-N.png`: albedo textures, sRGB.
//! - `lightmap-indirect.ktx2` (and `lightmap-full.ktx2` with direct light
//!   added): texels of [`crate::lightmap_texel`] (E/pi, Bevy's
//!   convention), referenced by every material's `MOZ_lightmap` extension
//!   (`texCoord` 1, `intensity` pi, since three.js and Hubs read texel
//!   times intensity as irradiance) and described in the mesh node's
//!   `extras.relight`.
//! - `irradiance-volume.ktx2`: a 3D texture in Bevy's
//!   `IrradianceVolume` layout (see [`crate::volume`]), its box in the
//!   scene's `extras.relight.irradianceVolume`.
//!
//! Units are relight's at [`crate::LUMENS_PER_WATT`]: glTF candela and lux
//! are relight's W/sr and W/m^2, so relight loads the export back to the
//! same scene. `MOZ_lightmap` is listed in `extensionsUsed` only: readers
//! that do not know it still load the scene.
//!
//! Every file is written to a temporary name and renamed, so a failed
//! export never leaves a half-written file under a final name.

use crate::ktx2_file::{Ktx2Error, Ktx2Texture, TexelFormat};
use crate::lightmap::{receiver_irradiance, LightmapLayout};
use crate::primitives::static_primitives;
use crate::units::{colour_and_scale, look_rotation, roughness_of, LUMENS_PER_WATT};
use crate::volume::{fill_volume, VolumeGrid};
use glam::Vec3;
use relight_core::Rgb;
use relight_scene::{Light, Scene};
use relight_technique::{SceneContext, Technique};
use serde_json::{json, Value};
use std::path::{Path, PathBuf};

/// What to export besides the scene.
#[derive(Clone, Debug)]
pub struct ExportSettings {
    pub format: TexelFormat,
    /// Zstandard level for the KTX2 files; `None` writes them plain.
    pub zstd_level: Option<i32>,
    /// Also write the lightmap with direct light added.
    pub with_direct: bool,
    /// The irradiance volume's grid; `None` writes none.
    pub volume: Option<VolumeGrid>,
}

/// Why an export failed; each names the file.
#[derive(Debug, thiserror::Error)]
pub enum ExportError {
    // The cause's message is part of this one, not a source as well: a
    // caller printing the chain would show it twice.
    #[error("cannot write {path}: {error}")]
    Io {
        path: PathBuf,
        error: std::io::Error,
    },
    #[error("cannot encode {path}: {error}")]
    Ktx2 { path: PathBuf, error: Ktx2Error },
    #[error("cannot encode {path}: {message}")]
    Image { path: PathBuf, message: String },
}

/// The files an export wrote, in the order written.
#[derive(Clone, Debug, Default)]
pub struct ExportSummary {
    pub files: Vec<PathBuf>,
    pub lightmap_size: [u32; 2],
    pub volume_resolution: Option<[u32; 3]>,
}

/// Writes the export of `context`'s scene lit by `lights` with
/// `technique`'s current indirect light (update it first) into `folder`,
/// which is created if missing.
pub fn export_scene(
    context: &SceneContext,
    technique: &dyn Technique,
    lights: &[Light],
    settings: &ExportSettings,
    folder: &Path,
) -> Result<ExportSummary, ExportError> {
    let io = |path: &Path| {
        let path = path.to_path_buf();
        move |error| ExportError::Io { path, error }
    };
    std::fs::create_dir_all(folder).map_err(io(folder))?;
    let mut summary = ExportSummary {
        lightmap_size: [context.atlas.width, context.atlas.height],
        ..ExportSummary::default()
    };
    let mut write = |name: &str, bytes: &[u8]| -> Result<(), ExportError> {
        let path = folder.join(name);
        write_atomic(&path, bytes).map_err(io(&path))?;
        summary.files.push(path);
        Ok(())
    };
    let ktx2 = |name: &str, size: [u32; 3], values: &[Rgb]| {
        let mut texels = Vec::new();
        settings.format.encode_into(values, &mut texels);
        Ktx2Texture {
            format: settings.format,
            width: size[0],
            height: size[1],
            depth: size[2],
            texels: &texels,
        }
        .to_bytes(settings.zstd_level)
        .map_err(|error| ExportError::Ktx2 {
            path: folder.join(name),
            error,
        })
    };

    let layout = LightmapLayout::new(&context.atlas);
    let indirect = receiver_irradiance(context, technique);
    let lightmap_size = [context.atlas.width, context.atlas.height, 0];
    let mut lightmaps = json!({ "indirect": "lightmap-indirect.ktx2" });
    write(
        "lightmap-indirect.ktx2",
        &ktx2(
            "lightmap-indirect.ktx2",
            lightmap_size,
            &layout.to_rgb(&indirect),
        )?,
    )?;
    if settings.with_direct {
        let receivers = &context.atlas.receivers;
        let mut full = vec![Rgb::ZERO; receivers.len()];
        context.direct().irradiance_batch(
            lights,
            &receivers.positions,
            &receivers.normals,
            &mut full,
        );
        for (value, indirect) in full.iter_mut().zip(&indirect) {
            *value += *indirect;
        }
        write(
            "lightmap-full.ktx2",
            &ktx2("lightmap-full.ktx2", lightmap_size, &layout.to_rgb(&full))?,
        )?;
        lightmaps["full"] = json!("lightmap-full.ktx2");
    }

    let mut scene_extras = json!({
        "technique": technique.name(),
        "lumensPerWatt": LUMENS_PER_WATT,
        "texel": "irradiance / pi x lumensPerWatt (cd/m^2): the radiance of a white Lambertian surface",
    });
    if let Some(grid) = &settings.volume {
        let mut values = vec![Rgb::ZERO; grid.voxel_count() * 6];
        fill_volume(grid, technique, &mut values);
        let size = grid.texture_size().to_array();
        write(
            "irradiance-volume.ktx2",
            &ktx2("irradiance-volume.ktx2", size, &values)?,
        )?;
        let (centre, scale) = grid.centre_and_scale();
        scene_extras["irradianceVolume"] = json!({
            "uri": "irradiance-volume.ktx2",
            "resolution": grid.resolution.to_array(),
            "min": grid.min.to_array(),
            "max": grid.max.to_array(),
            "translation": centre.to_array(),
            "scale": scale.to_array(),
            "layout": "Bevy IrradianceVolume: Rx x 2Ry x 3Rz; face +-X, +-Y, +-Z of voxel (x, y, z) at (x, y + Ry if negative, z + axis Rz)",
        });
        summary.volume_resolution = Some(grid.resolution.to_array());
    }

    let mut textures = Vec::new();
    for (index, texture) in context.scene.textures.iter().enumerate() {
        let name = format!("textures/albedo-{index}.png");
        let path = folder.join(&name);
        std::fs::create_dir_all(folder.join("textures")).map_err(io(&path))?;
        let png = encode_srgb_png(texture).map_err(|message| ExportError::Image {
            path: path.clone(),
            message,
        })?;
        write(&name, &png)?;
        textures.push(name);
    }

    let (document, buffer) = gltf_document(
        &context.scene,
        &context.atlas,
        lights,
        &textures,
        lightmaps,
        scene_extras,
    );
    write("scene.bin", &buffer)?;
    let text = serde_json::to_vec_pretty(&document).expect("a JSON value serialises");
    write("scene.gltf", &text)?;
    Ok(summary)
}

fn write_atomic(path: &Path, bytes: &[u8]) -> std::io::Result<()> {
    let mut temporary = path.as_os_str().to_owned();
    temporary.push(".tmp");
    let temporary = PathBuf::from(temporary);
    std::fs::write(&temporary, bytes)?;
    std::fs::rename(&temporary, path).inspect_err(|_| {
        let _ = std::fs::remove_file(&temporary);
    })
}

fn encode_srgb_png(texture: &relight_scene::Texture) -> Result<Vec<u8>, String> {
    use relight_core::colour::linear_to_srgb8 as encode;
    let pixels: Vec<u8> = texture
        .texels
        .iter()
        .flat_map(|texel| [encode(texel.x), encode(texel.y), encode(texel.z)])
        .collect();
    let image = image::RgbImage::from_raw(texture.width, texture.height, pixels)
        .ok_or("texture size does not match its texels")?;
    let mut bytes = Vec::new();
    image
        .write_to(
            &mut std::io::Cursor::new(&mut bytes),
            image::ImageFormat::Png,
        )
        .map_err(|error| error.to_string())?;
    Ok(bytes)
}

/// The binary buffer and its views and accessors as they are appended.
#[derive(Default)]
struct BufferBuilder {
    bytes: Vec<u8>,
    views: Vec<Value>,
    accessors: Vec<Value>,
}

impl BufferBuilder {
    /// Appends `data` (floats, `components` a vertex) as a view and an
    /// accessor; returns the accessor's index.
    fn push_floats(&mut self, data: &[f32], components: usize, bounds: bool) -> usize {
        let offset = self.bytes.len();
        self.bytes.extend_from_slice(bytemuck::cast_slice(data));
        self.views.push(json!({
            "buffer": 0,
            "byteOffset": offset,
            "byteLength": data.len() * 4,
            "target": 34962,
        }));
        let kind = ["", "SCALAR", "VEC2", "VEC3", "VEC4"][components];
        let mut accessor = json!({
            "bufferView": self.views.len() - 1,
            "componentType": 5126,
            "count": data.len() / components,
            "type": kind,
        });
        if bounds {
            let mut lo = vec![f32::INFINITY; components];
            let mut hi = vec![f32::NEG_INFINITY; components];
            for vertex in data.chunks_exact(components) {
                for (axis, &value) in vertex.iter().enumerate() {
                    lo[axis] = lo[axis].min(value);
                    hi[axis] = hi[axis].max(value);
                }
            }
            accessor["min"] = json!(lo);
            accessor["max"] = json!(hi);
        }
        self.accessors.push(accessor);
        self.accessors.len() - 1
    }
}

fn gltf_document(
    scene: &Scene,
    atlas: &relight_scene::atlas::Atlas,
    lights: &[Light],
    albedo_textures: &[String],
    lightmaps: Value,
    scene_extras: Value,
) -> (Value, Vec<u8>) {
    let mut buffer = BufferBuilder::default();
    let primitives: Vec<Value> = static_primitives(scene, atlas)
        .iter()
        .map(|primitive| {
            let attributes = json!({
                "POSITION": buffer.push_floats(primitive.positions.as_flattened(), 3, true),
                "NORMAL": buffer.push_floats(primitive.normals.as_flattened(), 3, false),
                "TEXCOORD_0": buffer.push_floats(primitive.uv0.as_flattened(), 2, false),
                "TEXCOORD_1": buffer.push_floats(primitive.uv1.as_flattened(), 2, false),
            });
            json!({ "attributes": attributes, "material": primitive.material, "mode": 4 })
        })
        .collect();

    // Texture 0 is the lightmap; albedo textures follow.
    let lightmap_texture = 0;
    // No mimeType: core glTF names only PNG and JPEG, and readers (Bevy's
    // among them) pick the KTX2 loader by the file's extension.
    let mut images = vec![json!({ "uri": "lightmap-indirect.ktx2" })];
    let mut textures = vec![json!({ "source": 0, "sampler": 0 })];
    for (index, uri) in albedo_textures.iter().enumerate() {
        images.push(json!({ "uri": uri, "mimeType": "image/png" }));
        textures.push(json!({ "source": index + 1, "sampler": 1 }));
    }
    let materials: Vec<Value> = scene
        .materials
        .iter()
        .map(|material| {
            let mut pbr = json!({
                "baseColorFactor": [material.albedo.x, material.albedo.y, material.albedo.z, 1.0],
                "metallicFactor": 0.0,
                "roughnessFactor": roughness_of(material.phong_exponent),
            });
            if let Some(texture) = material.albedo_texture {
                pbr["baseColorTexture"] = json!({ "index": texture as usize + 1, "texCoord": 0 });
            }
            let mut value = json!({
                "name": material.name,
                "pbrMetallicRoughness": pbr,
                "extensions": {
                    // three.js and Hubs read texel x intensity as
                    // irradiance; the texels hold E / pi.
                    "MOZ_lightmap": { "index": lightmap_texture, "texCoord": 1, "intensity": std::f32::consts::PI },
                },
            });
            if material.phong_exponent <= 1.0 {
                // relight's Lambertian surfaces have no specular lobe;
                // without this, glTF's default F0 of 0.04 adds one.
                value["extensions"]["KHR_materials_specular"] = json!({ "specularFactor": 0.0 });
            }
            let (colour, strength) = colour_and_scale(material.emission);
            if strength > 0.0 {
                value["emissiveFactor"] = json!(colour.to_array());
                value["extensions"]["KHR_materials_emissive_strength"] =
                    json!({ "emissiveStrength": strength * LUMENS_PER_WATT });
            }
            value
        })
        .collect();

    let mut nodes = vec![json!({
        "name": "relight static scene",
        "mesh": 0,
        "extras": { "relight": { "lightmap": lightmaps, "texCoord": 1 } },
    })];
    let mut punctual = Vec::new();
    for light in lights {
        let (definition, translation, direction) = light_definition(light);
        punctual.push(definition);
        let mut node = json!({
            "name": format!("light {}", punctual.len() - 1),
            "extensions": { "KHR_lights_punctual": { "light": punctual.len() - 1 } },
        });
        if let Some(translation) = translation {
            node["translation"] = json!(translation.to_array());
        }
        if let Some(direction) = direction {
            node["rotation"] = json!(look_rotation(direction, Vec3::Y).to_array());
        }
        nodes.push(node);
    }
    let camera = &scene.camera;
    nodes.push(json!({
        "name": "camera",
        "camera": 0,
        "translation": camera.eye.to_array(),
        "rotation": look_rotation(camera.target - camera.eye, camera.up).to_array(),
    }));
    let aspect = camera.resolution[0] as f32 / camera.resolution[1].max(1) as f32;

    let document = json!({
        "asset": { "version": "2.0", "generator": concat!("relight ", env!("CARGO_PKG_VERSION")) },
        "extensionsUsed": [
            "MOZ_lightmap",
            "KHR_lights_punctual",
            "KHR_materials_emissive_strength",
            "KHR_materials_specular",
        ],
        "extensions": { "KHR_lights_punctual": { "lights": punctual } },
        "scene": 0,
        "scenes": [{
            "nodes": (0..nodes.len()).collect::<Vec<_>>(),
            "extras": { "relight": scene_extras },
        }],
        "nodes": nodes,
        "meshes": [{ "name": "static", "primitives": primitives }],
        "materials": materials,
        "cameras": [{
            "type": "perspective",
            "perspective": {
                "yfov": camera.fov_y_degrees.to_radians(),
                "aspectRatio": aspect,
                "znear": 0.01,
            },
        }],
        "images": images,
        "textures": textures,
        "samplers": [
            // The lightmap: bilinear, clamped (its gutters hold the edge).
            { "magFilter": 9729, "minFilter": 9729, "wrapS": 33071, "wrapT": 33071 },
            { "magFilter": 9729, "minFilter": 9987, "wrapS": 10497, "wrapT": 10497 },
        ],
        "accessors": buffer.accessors,
        "bufferViews": buffer.views,
        "buffers": [{ "uri": "scene.bin", "byteLength": buffer.bytes.len() }],
    });
    (document, buffer.bytes)
}

/// A light's `KHR_lights_punctual` entry, node position and direction.
fn light_definition(light: &Light) -> (Value, Option<Vec3>, Option<Vec3>) {
    match *light {
        Light::Point {
            position,
            intensity,
        } => {
            let (colour, scale) = colour_and_scale(intensity);
            (
                json!({ "type": "point", "color": colour.to_array(), "intensity": scale * LUMENS_PER_WATT }),
                Some(position),
                None,
            )
        }
        Light::Spot {
            position,
            direction,
            intensity,
            inner_angle,
            outer_angle,
        } => {
            let (colour, scale) = colour_and_scale(intensity);
            (
                json!({
                    "type": "spot",
                    "color": colour.to_array(),
                    "intensity": scale * LUMENS_PER_WATT,
                    "spot": { "innerConeAngle": inner_angle, "outerConeAngle": outer_angle },
                }),
                Some(position),
                Some(direction),
            )
        }
        Light::Directional {
            direction,
            irradiance,
        } => {
            let (colour, scale) = colour_and_scale(irradiance);
            (
                json!({ "type": "directional", "color": colour.to_array(), "intensity": scale * LUMENS_PER_WATT }),
                None,
                Some(direction),
            )
        }
    }
}
