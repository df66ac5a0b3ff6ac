//! The `scene.toml` format and the one entry point that turns it into a
//! [`Scene`].
//!
//! Design choices:
//! - The TOML is read into private `Raw*` structs with serde
//!   `deny_unknown_fields`, so a typo such as `lihgts` is an error naming the
//!   key, the file and the line, instead of a silently ignored section.
//!   Technique sections (`[srp]`, `[[dynamic]]`, ...) are declared as raw
//!   `toml::Value`s and handed on untouched in [`SceneFile::extra`]: each
//!   technique validates its own section.
//! - Numeric fields are `toml::Spanned` so that validation, which happens
//!   right here where the values are read, can point at the offending line.
//! - Work shared by both mesh loaders (texture decoding, warnings, dropping
//!   degenerate triangles, choosing a camera) lives here so that OBJ and glTF
//!   scenes obey exactly the same rules.

use crate::detail::{split_for_detail, DetailRegion, LightmapDetail, LightmapLayout};
use crate::mesh_input::{text_from_bytes, warn, LoadedMesh, MAX_TEXTURE_SIDE};
use crate::{gltf_loader, obj_loader};
use crate::{Camera, Environment, Light, Material, Mesh, Scene, SceneError};
use glam::Vec3;
use relight_core::colour::is_valid_radiometric;
use relight_core::Rgb;
use serde::Deserialize;
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use toml::Spanned;

/// Top-level sections that belong to techniques; their content passes through
/// unparsed in [`SceneFile::extra`].
pub const TECHNIQUE_SECTIONS: [&str; 5] = ["pic", "srp", "prm", "lightskin", "dynamic"];

/// A parsed and validated `scene.toml`, before the mesh is read.
#[derive(Clone, Debug)]
pub struct SceneFile {
    /// The scene file itself.
    pub path: PathBuf,
    /// The mesh file, resolved against the scene file's folder.
    pub mesh: PathBuf,
    /// `None` when the file has no `[camera]`: the mesh's camera (glTF) or
    /// an automatic framing is used instead.
    pub camera: Option<Camera>,
    /// Lights from the TOML; they are added to the lights of the mesh file.
    pub lights: Vec<Light>,
    /// Black when the file has no `[environment]`.
    pub environment: Environment,
    /// Raw technique sections keyed by name (see [`TECHNIQUE_SECTIONS`]).
    pub extra: BTreeMap<String, toml::Value>,
    /// The `[lightmap]` section; the default without one.
    pub lightmap: LightmapLayout,
}

type Spanned3 = Spanned<[f32; 3]>;

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct RawSceneFile {
    mesh: Spanned<String>,
    camera: Option<RawCamera>,
    #[serde(default)]
    lights: Vec<RawLight>,
    environment: Option<RawEnvironment>,
    lightmap: Option<RawLightmap>,
    pic: Option<toml::Value>,
    srp: Option<toml::Value>,
    prm: Option<toml::Value>,
    lightskin: Option<toml::Value>,
    dynamic: Option<toml::Value>,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct RawCamera {
    eye: Spanned3,
    target: Spanned3,
    up: Option<Spanned3>,
    fov_y: Spanned<f32>,
    resolution: Option<Spanned<[u32; 2]>>,
}

/// One struct for every kind, rather than a serde-tagged enum, so that a
/// field that does not belong to the kind gets a message naming both.
#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct RawLight {
    kind: Spanned<String>,
    position: Option<Spanned3>,
    direction: Option<Spanned3>,
    intensity: Option<Spanned3>,
    irradiance: Option<Spanned3>,
    inner_angle: Option<Spanned<f32>>,
    outer_angle: Option<Spanned<f32>>,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct RawEnvironment {
    radiance: Spanned3,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct RawLightmap {
    detail: Option<Spanned<String>>,
    detail_min: Option<Spanned3>,
    detail_max: Option<Spanned3>,
    detail_margin: Option<Spanned<f32>>,
    refine_near_lights: Option<bool>,
    cut_under_walls: Option<bool>,
}

/// 1-based line of a byte offset, for error messages.
fn line_of(text: &str, offset: usize) -> usize {
    let end = offset.min(text.len());
    text.as_bytes()[..end]
        .iter()
        .filter(|&&b| b == b'\n')
        .count()
        + 1
}

/// Builds `SceneError::Syntax` errors that point into one text file.
struct TextSource<'a> {
    path: &'a Path,
    text: &'a str,
}

impl TextSource<'_> {
    fn error_at<T>(&self, spanned: &Spanned<T>, message: impl Into<String>) -> SceneError {
        SceneError::Syntax {
            path: self.path.to_path_buf(),
            line: line_of(self.text, spanned.span().start),
            message: message.into(),
        }
    }

    fn finite_vec3(&self, field: &Spanned3, name: &str) -> Result<Vec3, SceneError> {
        let value = Vec3::from_array(*field.get_ref());
        if value.is_finite() {
            Ok(value)
        } else {
            Err(self.error_at(field, format!("`{name}` must be three finite numbers")))
        }
    }

    fn direction(&self, field: &Spanned3, name: &str) -> Result<Vec3, SceneError> {
        let value = self.finite_vec3(field, name)?;
        let length = value.length();
        if length.is_finite() && length > 1e-12 {
            Ok(value / length)
        } else {
            Err(self.error_at(field, format!("`{name}` must be a non-zero vector")))
        }
    }

    fn radiometric(&self, field: &Spanned3, name: &str) -> Result<Rgb, SceneError> {
        let value = Vec3::from_array(*field.get_ref());
        if is_valid_radiometric(value) {
            Ok(value)
        } else {
            Err(self.error_at(
                field,
                format!(
                    "`{name}` must be three finite, non-negative numbers (one per RGB channel)"
                ),
            ))
        }
    }

    fn lightmap(&self, raw: &RawLightmap) -> Result<LightmapLayout, SceneError> {
        let kind = raw
            .detail
            .as_ref()
            .map_or("auto", |kind| kind.get_ref().as_str());
        let bounds = match (&raw.detail_min, &raw.detail_max) {
            (Some(min), Some(max)) => Some((
                min,
                self.finite_vec3(min, "lightmap.detail_min")?,
                self.finite_vec3(max, "lightmap.detail_max")?,
            )),
            (None, None) => None,
            (Some(one), None) | (None, Some(one)) => {
                return Err(self.error_at(
                    one,
                    "give both `lightmap.detail_min` and `lightmap.detail_max` (the corners of the detail box), or neither",
                ))
            }
        };
        let detail = match (kind, bounds) {
            ("auto", None) => LightmapDetail::Automatic,
            ("uniform", None) => LightmapDetail::Uniform,
            ("box", Some((at, low, high))) => {
                if !low.cmplt(high).all() {
                    return Err(self.error_at(
                        at,
                        "`lightmap.detail_min` must be below `lightmap.detail_max` on every axis",
                    ));
                }
                LightmapDetail::Bounds { low, high }
            }
            ("box", None) => {
                let at = raw.detail.as_ref().expect("\"box\" was read from `detail`");
                return Err(self.error_at(
                    at,
                    "`lightmap.detail = \"box\"` needs `detail_min` and `detail_max`, the corners of the box that gets full texel density",
                ));
            }
            ("auto" | "uniform", Some((at, _, _))) => {
                return Err(self.error_at(
                    at,
                    "`lightmap.detail_min` and `detail_max` go with `detail = \"box\"`",
                ))
            }
            (other, _) => {
                let at = raw.detail.as_ref().expect("only `detail` names a kind");
                return Err(self.error_at(
                    at,
                    format!("`lightmap.detail` is \"{other}\": use \"auto\" (full texel density where the scene's detail is, coarser far outside), \"uniform\" or \"box\""),
                ));
            }
        };
        let margin = match &raw.detail_margin {
            Some(margin) if !(margin.get_ref().is_finite() && *margin.get_ref() > 0.0) => {
                return Err(self.error_at(
                    margin,
                    "`lightmap.detail_margin` must be a positive number of metres",
                ))
            }
            Some(margin) => Some(*margin.get_ref()),
            None => None,
        };
        Ok(LightmapLayout {
            detail,
            margin,
            refine_near_lights: raw.refine_near_lights.unwrap_or(true),
            cut_under_walls: raw.cut_under_walls.unwrap_or(true),
        })
    }

    fn camera(&self, raw: &RawCamera) -> Result<Camera, SceneError> {
        let eye = self.finite_vec3(&raw.eye, "camera.eye")?;
        let target = self.finite_vec3(&raw.target, "camera.target")?;
        let up = match &raw.up {
            Some(up) => self.direction(up, "camera.up")?,
            None => Vec3::Y,
        };
        let forward = target - eye;
        if forward.length_squared() <= 1e-18 {
            return Err(self.error_at(&raw.target, "`camera.target` must differ from `camera.eye`"));
        }
        if forward.normalize().cross(up).length() < 1e-6 {
            return Err(self.error_at(
                &raw.target,
                "the camera looks along `camera.up`: choose an `up` that is not parallel to target - eye",
            ));
        }
        let fov_y = *raw.fov_y.get_ref();
        if !(fov_y > 0.0 && fov_y < 180.0) {
            return Err(self.error_at(
                &raw.fov_y,
                format!("`camera.fov_y` is {fov_y}: use a vertical field of view in degrees, between 0 and 180 (exclusive)"),
            ));
        }
        let resolution = match &raw.resolution {
            Some(resolution) => {
                let [width, height] = *resolution.get_ref();
                if !(1..=MAX_TEXTURE_SIDE).contains(&width)
                    || !(1..=MAX_TEXTURE_SIDE).contains(&height)
                {
                    return Err(self.error_at(
                        resolution,
                        format!("`camera.resolution` is {width} x {height}: width and height must be between 1 and {MAX_TEXTURE_SIDE}"),
                    ));
                }
                [width, height]
            }
            None => Camera::default().resolution,
        };
        Ok(Camera {
            eye,
            target,
            up,
            fov_y_degrees: fov_y,
            resolution,
        })
    }

    fn light(&self, raw: &RawLight) -> Result<Light, SceneError> {
        let kind = raw.kind.get_ref().as_str();
        let (required, allowed): (&[&str], &[&str]) = match kind {
            "point" => (&["position", "intensity"], &["position", "intensity"]),
            "directional" => (&["direction", "irradiance"], &["direction", "irradiance"]),
            "spot" => (
                &[
                    "position",
                    "direction",
                    "intensity",
                    "inner_angle",
                    "outer_angle",
                ],
                &[
                    "position",
                    "direction",
                    "intensity",
                    "inner_angle",
                    "outer_angle",
                ],
            ),
            other => {
                return Err(self.error_at(
                    &raw.kind,
                    format!(
                    "unknown light kind \"{other}\": use \"point\", \"directional\" or \"spot\""
                ),
                ))
            }
        };
        let present: [(&str, Option<std::ops::Range<usize>>); 6] = [
            ("position", raw.position.as_ref().map(Spanned::span)),
            ("direction", raw.direction.as_ref().map(Spanned::span)),
            ("intensity", raw.intensity.as_ref().map(Spanned::span)),
            ("irradiance", raw.irradiance.as_ref().map(Spanned::span)),
            ("inner_angle", raw.inner_angle.as_ref().map(Spanned::span)),
            ("outer_angle", raw.outer_angle.as_ref().map(Spanned::span)),
        ];
        for (name, span) in &present {
            match span {
                Some(span) if !allowed.contains(name) => {
                    return Err(SceneError::Syntax {
                        path: self.path.to_path_buf(),
                        line: line_of(self.text, span.start),
                        message: format!(
                            "a {kind} light has no `{name}`: its fields are {}",
                            allowed.join(", ")
                        ),
                    });
                }
                None if required.contains(name) => {
                    return Err(self.error_at(
                        &raw.kind,
                        format!(
                            "this {kind} light lacks `{name}`: a {kind} light needs {}",
                            required.join(", ")
                        ),
                    ));
                }
                _ => {}
            }
        }
        // The loop above guarantees every required field is present.
        let missing = || self.error_at(&raw.kind, "internal: light field vanished");
        match kind {
            "point" => Ok(Light::Point {
                position: self
                    .finite_vec3(raw.position.as_ref().ok_or_else(missing)?, "position")?,
                intensity: self
                    .radiometric(raw.intensity.as_ref().ok_or_else(missing)?, "intensity")?,
            }),
            "directional" => Ok(Light::Directional {
                direction: self
                    .direction(raw.direction.as_ref().ok_or_else(missing)?, "direction")?,
                irradiance: self
                    .radiometric(raw.irradiance.as_ref().ok_or_else(missing)?, "irradiance")?,
            }),
            _ => {
                let inner = raw.inner_angle.as_ref().ok_or_else(missing)?;
                let outer = raw.outer_angle.as_ref().ok_or_else(missing)?;
                let (inner_degrees, outer_degrees) = (*inner.get_ref(), *outer.get_ref());
                let outer_valid = outer_degrees > 0.0 && outer_degrees <= 90.0;
                if !outer_valid {
                    return Err(self.error_at(
                        outer,
                        format!("`outer_angle` is {outer_degrees}: use a half-angle in degrees, above 0 and at most 90"),
                    ));
                }
                if !(0.0..=outer_degrees).contains(&inner_degrees) {
                    return Err(self.error_at(
                        inner,
                        format!("`inner_angle` is {inner_degrees}: use a half-angle in degrees between 0 and `outer_angle` ({outer_degrees})"),
                    ));
                }
                Ok(Light::Spot {
                    position: self
                        .finite_vec3(raw.position.as_ref().ok_or_else(missing)?, "position")?,
                    direction: self
                        .direction(raw.direction.as_ref().ok_or_else(missing)?, "direction")?,
                    intensity: self
                        .radiometric(raw.intensity.as_ref().ok_or_else(missing)?, "intensity")?,
                    inner_angle: inner_degrees.to_radians(),
                    outer_angle: outer_degrees.to_radians(),
                })
            }
        }
    }
}

/// Reads and validates a scene file without touching the mesh it names.
pub fn parse_scene_file(path: &Path) -> Result<SceneFile, SceneError> {
    let bytes = std::fs::read(path).map_err(|error| SceneError::Io {
        path: path.to_path_buf(),
        error,
    })?;
    let text = text_from_bytes(path, &bytes)?;
    parse_scene_text(path, &text)
}

fn parse_scene_text(path: &Path, text: &str) -> Result<SceneFile, SceneError> {
    let raw: RawSceneFile = toml::from_str(text).map_err(|error| {
        let line = error.span().map_or(1, |span| line_of(text, span.start));
        let mut message = error.message().trim().to_string();
        if message.contains("unknown field") {
            message.push_str(&format!(
                " (technique sections allowed at the top level: {})",
                TECHNIQUE_SECTIONS.join(", ")
            ));
        }
        SceneError::Syntax {
            path: path.to_path_buf(),
            line,
            message,
        }
    })?;
    let source = TextSource { path, text };

    if raw.mesh.get_ref().trim().is_empty() {
        return Err(source.error_at(
            &raw.mesh,
            "`mesh` is empty: name an .obj, .gltf or .glb file relative to this scene file",
        ));
    }
    let folder = path.parent().unwrap_or(Path::new(""));
    let mesh = folder.join(raw.mesh.get_ref());
    let camera = raw
        .camera
        .as_ref()
        .map(|camera| source.camera(camera))
        .transpose()?;
    let lights = raw
        .lights
        .iter()
        .map(|light| source.light(light))
        .collect::<Result<Vec<_>, _>>()?;
    let environment = match &raw.environment {
        Some(environment) => Environment {
            radiance: source.radiometric(&environment.radiance, "environment.radiance")?,
        },
        None => Environment::default(),
    };
    let lightmap = raw
        .lightmap
        .as_ref()
        .map(|lightmap| source.lightmap(lightmap))
        .transpose()?
        .unwrap_or_default();
    let extra: BTreeMap<String, toml::Value> = [
        ("pic", raw.pic),
        ("srp", raw.srp),
        ("prm", raw.prm),
        ("lightskin", raw.lightskin),
        ("dynamic", raw.dynamic),
    ]
    .into_iter()
    .filter_map(|(name, value)| value.map(|value| (name.to_string(), value)))
    .collect();

    Ok(SceneFile {
        path: path.to_path_buf(),
        mesh,
        camera,
        lights,
        environment,
        extra,
        lightmap,
    })
}

/// Reads a scene file (TOML), or a mesh file (OBJ, glTF, GLB) as a scene
/// of its own, with its mesh, materials and textures.
pub fn load_scene(path: &Path) -> Result<Scene, SceneError> {
    let file = if is_mesh_file(path) {
        // A mesh file on its own is a scene with its own lights and camera
        // (glTF) or an automatic framing: what an engine hands over.
        SceneFile {
            path: path.to_path_buf(),
            mesh: path.to_path_buf(),
            camera: None,
            lights: Vec::new(),
            environment: Environment::default(),
            extra: BTreeMap::new(),
            lightmap: LightmapLayout::default(),
        }
    } else {
        parse_scene_file(path)?
    };
    let loaded = load_mesh_file(&file.mesh)?;
    finish_scene(file, loaded)
}

/// True for the mesh formats relight loads (OBJ, glTF, GLB), by extension.
pub fn is_mesh_file(path: &Path) -> bool {
    path.extension()
        .and_then(|extension| extension.to_str())
        .is_some_and(|extension| {
            ["obj", "gltf", "glb"]
                .iter()
                .any(|known| extension.eq_ignore_ascii_case(known))
        })
}

fn load_mesh_file(path: &Path) -> Result<LoadedMesh, SceneError> {
    let extension = path
        .extension()
        .and_then(|extension| extension.to_str())
        .unwrap_or("")
        .to_ascii_lowercase();
    match extension.as_str() {
        "obj" => obj_loader::load_obj(path),
        "gltf" | "glb" => gltf_loader::load_gltf(path),
        _ => Err(SceneError::UnsupportedFormat {
            path: path.to_path_buf(),
            extension,
        }),
    }
}

/// A mesh file on its own (OBJ or glTF) with its materials, textures
/// folded into each material's average colour, degenerate triangles
/// dropped: the form techniques use for extra, moving meshes.
pub fn load_mesh(path: &Path) -> Result<(Mesh, Vec<Material>), SceneError> {
    let LoadedMesh {
        mut mesh,
        mut materials,
        textures,
        ..
    } = load_mesh_file(path)?;
    if let Some(position) = mesh.positions.iter().position(|p| !p.is_finite()) {
        return Err(SceneError::Invalid {
            path: path.to_path_buf(),
            message: format!("vertex {position} has a non-finite coordinate: fix or remove it"),
        });
    }
    drop_degenerate_triangles(&mut mesh);
    if mesh.triangles.is_empty() {
        return Err(SceneError::Empty {
            path: path.to_path_buf(),
        });
    }
    for material in &mut materials {
        if let Some(texture) = material.albedo_texture.take() {
            material.albedo *= textures[texture as usize].average();
        }
    }
    Ok((mesh, materials))
}

fn finish_scene(file: SceneFile, loaded: LoadedMesh) -> Result<Scene, SceneError> {
    let LoadedMesh {
        mut mesh,
        materials,
        textures,
        mut lights,
        camera: mesh_camera,
        mut warnings,
        mut gltf_primitives,
    } = loaded;
    if let Some(position) = mesh.positions.iter().position(|p| !p.is_finite()) {
        return Err(SceneError::Invalid {
            path: file.mesh.clone(),
            message: format!("vertex {position} has a non-finite coordinate: fix or remove it"),
        });
    }
    let (dropped, kept) = drop_degenerate_triangles(&mut mesh);
    for primitive in &mut gltf_primitives {
        for triangle in primitive.triangles.iter_mut() {
            *triangle = triangle.and_then(|old| kept[old as usize]);
        }
    }
    if dropped > 0 {
        warn(
            &mut warnings,
            format!(
                "{}: dropped {dropped} degenerate triangle(s) (zero area or non-finite)",
                file.mesh.display()
            ),
        );
    }
    if mesh.triangles.is_empty() {
        return Err(SceneError::Empty { path: file.mesh });
    }
    debug_assert!(mesh
        .material_ids
        .iter()
        .all(|&id| (id as usize) < materials.len()));
    let lightmap_layout = cut_for_lightmap_detail(
        &mut mesh,
        &materials,
        file.lightmap,
        &mut gltf_primitives,
        &file.mesh,
        &mut warnings,
    );
    let lightmap_seams = if lightmap_layout.cut_under_walls && mesh.lightmap_uvs.is_empty() {
        cut_under_walls(
            &mut mesh,
            &materials,
            &mut gltf_primitives,
            &file.mesh,
            &mut warnings,
        )
    } else {
        Vec::new()
    };

    lights.extend(file.lights);
    let camera = match (file.camera, mesh_camera) {
        (Some(camera), _) | (None, Some(camera)) => camera,
        (None, None) => {
            warn(
                &mut warnings,
                format!(
                    "{}: no camera in the scene file or the mesh; framing the whole scene from +Z (add a [camera] section)",
                    file.path.display()
                ),
            );
            framing_camera(&mesh)
        }
    };
    Ok(Scene {
        mesh,
        materials,
        textures,
        lights,
        camera,
        environment: file.environment,
        source: file.path,
        warnings,
        technique_sections: file.extra,
        gltf_primitives,
        lightmap_layout,
        lightmap_seams,
    })
}

/// Cuts the surfaces walls stand on along the walls' feet
/// ([`crate::seams`]) and returns the seams. A glTF triangle that was cut
/// no longer maps to one scene triangle, as in [`cut_for_lightmap_detail`].
fn cut_under_walls(
    mesh: &mut Mesh,
    materials: &[Material],
    gltf_primitives: &mut [crate::GltfPrimitive],
    mesh_path: &Path,
    warnings: &mut Vec<String>,
) -> Vec<[Vec3; 2]> {
    let emissive = |material: u32| materials[material as usize].emission.max_element() > 0.0;
    let cut = crate::seams::cut_under_walls(mesh, emissive);
    if cut.cut == 0 {
        return cut.seams;
    }
    tracing::info!(
        "{}: cut {} triangle(s) along {} line(s) where walls stand on them, so that no lightmap texel straddles a wall (`[lightmap] cut_under_walls = false` keeps them whole)",
        mesh_path.display(),
        cut.cut,
        cut.lines,
    );
    remap_cut_primitives(gltf_primitives, &cut.pieces_of, warnings, |unmapped| {
        format!(
            "{}: {unmapped} glTF floor or ceiling triangle(s) that walls stand on were cut along the walls' feet; an engine adopting this file gets no lightmap on them: set `[lightmap] cut_under_walls = false` to keep them whole (light may then show through the walls' feet)",
            mesh_path.display()
        )
    });
    cut.seams
}

/// Points each glTF triangle at the one piece it became; a triangle cut
/// into several maps to none, and where any did, `warning` (given their
/// count) is warned.
fn remap_cut_primitives(
    gltf_primitives: &mut [crate::GltfPrimitive],
    pieces_of: &[std::ops::Range<u32>],
    warnings: &mut Vec<String>,
    warning: impl FnOnce(usize) -> String,
) {
    let mut unmapped = 0;
    for primitive in gltf_primitives.iter_mut() {
        for triangle in primitive.triangles.iter_mut() {
            *triangle = triangle.and_then(|old| {
                let pieces = &pieces_of[old as usize];
                if pieces.len() == 1 {
                    Some(pieces.start)
                } else {
                    unmapped += 1;
                    None
                }
            });
        }
    }
    if unmapped > 0 {
        warn(warnings, warning(unmapped));
    }
}

/// Cuts the triangles that reach from the detail region far out (see
/// [`crate::detail`]) unless the mesh brings its own lightmap UVs, whose
/// density is the author's. A glTF triangle that was cut no longer maps to
/// one scene triangle, so an engine adopting the file cannot give it
/// relight's lightmap: the warning says so and how to keep it whole.
///
/// Returns the layout resolved once for the loaded scene: the region fixed
/// as a box (the cut mesh has no huge triangles left, so the automatic
/// region found again from it would be the whole ground), or uniform where
/// nothing reaches past a region's margin, so that no later use searches
/// the mesh again.
fn cut_for_lightmap_detail(
    mesh: &mut Mesh,
    materials: &[Material],
    layout: LightmapLayout,
    gltf_primitives: &mut [crate::GltfPrimitive],
    mesh_path: &Path,
    warnings: &mut Vec<String>,
) -> LightmapLayout {
    let Some(region) = DetailRegion::of(mesh, layout) else {
        return LightmapLayout {
            detail: LightmapDetail::Uniform,
            ..layout
        };
    };
    let fixed = LightmapLayout {
        detail: LightmapDetail::Bounds {
            low: region.low,
            high: region.high,
        },
        margin: Some(region.margin),
        ..layout
    };
    if !mesh.lightmap_uvs.is_empty() {
        return fixed;
    }
    let emissive = |material: u32| materials[material as usize].emission.max_element() > 0.0;
    let split = split_for_detail(mesh, &region, emissive);
    if split.cut == 0 {
        return fixed;
    }
    tracing::info!(
        "{}: cut {} triangle(s) reaching more than {:.1} m outside the detail region {} so that the lightmap coarsens with distance (`[lightmap] detail = \"uniform\"` keeps them whole)",
        mesh_path.display(),
        split.cut,
        region.margin,
        region.describe_box(),
    );
    remap_cut_primitives(gltf_primitives, &split.pieces_of, warnings, |unmapped| {
        format!(
            "{}: {unmapped} glTF triangle(s) reaching far outside the detail region were cut for a coarser lightmap there; an engine adopting this file gets no lightmap on them: set `[lightmap] detail = \"uniform\"` (or a `detail = \"box\"` that holds them) to keep them whole",
            mesh_path.display()
        )
    });
    fixed
}

/// A camera on +Z that sees the whole bounding box, for meshes without one.
fn framing_camera(mesh: &Mesh) -> Camera {
    let (low, high) = mesh.bounds();
    let centre = (low + high) * 0.5;
    let radius = ((high - low).length() * 0.5).max(1e-3);
    let fov_y_degrees = 45.0_f32;
    let distance = radius / (fov_y_degrees.to_radians() * 0.5).sin();
    Camera {
        eye: centre + Vec3::Z * distance,
        target: centre,
        up: Vec3::Y,
        fov_y_degrees,
        resolution: Camera::default().resolution,
    }
}

/// Removes zero-area and non-finite triangles, then the vertices nobody uses
/// any more, so bounds and vertex counts describe real geometry. Returns
/// how many triangles were dropped and, for each old triangle, its new
/// index (`None`: dropped).
fn drop_degenerate_triangles(mesh: &mut Mesh) -> (usize, Vec<Option<u32>>) {
    let before = mesh.triangles.len();
    let mut kept_triangles = Vec::with_capacity(before);
    let mut kept_materials = Vec::with_capacity(before);
    let mut new_index = Vec::with_capacity(before);
    for (triangle, &material) in mesh.triangles.iter().zip(&mesh.material_ids) {
        let [a, b, c] = triangle.map(|index| mesh.positions[index as usize]);
        let doubled_area = (b - a).cross(c - a);
        let usable = doubled_area.is_finite()
            && doubled_area.length_squared() > 0.0
            && doubled_area.normalize_or_zero() != Vec3::ZERO;
        new_index.push(usable.then_some(kept_triangles.len() as u32));
        if usable {
            kept_triangles.push(*triangle);
            kept_materials.push(material);
        }
    }
    let dropped = before - kept_triangles.len();
    mesh.triangles = kept_triangles;
    mesh.material_ids = kept_materials;

    // New indices keep the old vertex order, so nothing moves when every
    // vertex is still used.
    let mut used = vec![false; mesh.positions.len()];
    for triangle in &mesh.triangles {
        for &index in triangle {
            used[index as usize] = true;
        }
    }
    let mut remap = vec![u32::MAX; mesh.positions.len()];
    let mut next = 0u32;
    for (old, _) in used.iter().enumerate().filter(|(_, &used)| used) {
        remap[old] = next;
        next += 1;
    }
    if (next as usize) < mesh.positions.len() {
        for triangle in &mut mesh.triangles {
            for index in triangle.iter_mut() {
                *index = remap[*index as usize];
            }
        }
        let compact = |values: &mut Vec<glam::Vec2>| {
            if values.is_empty() {
                return;
            }
            let mut out = vec![glam::Vec2::ZERO; next as usize];
            for (old, &new) in remap.iter().enumerate() {
                if new != u32::MAX {
                    out[new as usize] = values[old];
                }
            }
            *values = out;
        };
        compact(&mut mesh.texcoords);
        compact(&mut mesh.lightmap_uvs);
        let mut positions = vec![Vec3::ZERO; next as usize];
        for (old, &new) in remap.iter().enumerate() {
            if new != u32::MAX {
                positions[new as usize] = mesh.positions[old];
            }
        }
        mesh.positions = positions;
    }
    (dropped, new_index)
}
