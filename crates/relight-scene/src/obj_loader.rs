//! Wavefront OBJ + MTL loading.
//!
//! Design choices:
//! - `tobj` assembles the mesh (`single_index`, `triangulate`), but it reports
//!   errors without line numbers and indexes arrays with values straight from
//!   the file. So a validation pass over the OBJ text runs first: it checks
//!   every `v`, `vt`, `f`, `l` and `usemtl` line the way tobj will read it
//!   and reports the first problem with its line. After it, tobj only ever
//!   sees well-formed input.
//! - MTL files are parsed here, not by tobj: the format is tiny, and our own
//!   parser gives line numbers and validates emission (an error when negative
//!   or non-finite). tobj gets name-only placeholder materials so that it
//!   still resolves `usemtl` to indices.
//! - OBJ `vt` v runs bottom-up; [`Texture::sample`](crate::Texture::sample)
//!   treats v = 0 as the top row, so v is flipped here (1 - v).
//! - `map_Kd` texels multiply `Kd`, as glTF's base colour texture multiplies
//!   its factor, so both formats mean the same thing.

use crate::mesh_input::{decode_texture, text_from_bytes, warn, LoadedMesh};
use crate::{Material, Mesh, SceneError, Texture};
use glam::{Vec2, Vec3};
use relight_core::colour::is_valid_radiometric;
use std::cell::RefCell;
use std::collections::HashMap;
use std::path::{Path, PathBuf};

/// Reads an OBJ file with the MTL files and textures it names.
pub(crate) fn load_obj(path: &Path) -> Result<LoadedMesh, SceneError> {
    let bytes = std::fs::read(path).map_err(|error| SceneError::Io {
        path: path.to_path_buf(),
        error,
    })?;
    let text = text_from_bytes(path, &bytes)?;
    let scan = validate_obj_text(path, &text)?;
    // tobj fails on faces that mix vertices with and without colours; relight
    // does not use vertex colours, so they are dropped before tobj sees them.
    let text = if scan.has_vertex_colours {
        strip_vertex_colours(&text)
    } else {
        text
    };

    let folder = path.parent().unwrap_or(Path::new("")).to_path_buf();
    let libraries = RefCell::new(MaterialLibraries::default());
    // Field by field, so that tobj features enabled elsewhere in the
    // workspace (which add fields) cannot break this.
    #[allow(clippy::field_reassign_with_default)]
    let options = {
        let mut options = tobj::LoadOptions::default();
        options.single_index = true;
        options.triangulate = true;
        options.ignore_points = true;
        options.ignore_lines = true;
        options
    };
    let loaded = tobj::load_obj_buf(&mut text.as_bytes(), &options, |library: &Path| {
        libraries.borrow_mut().load(path, &folder, library)
    });
    let mut libraries = libraries.into_inner();
    if let Some(error) = libraries.fatal.take() {
        return Err(error);
    }
    let (models, _placeholders) = loaded.map_err(|error| SceneError::Invalid {
        path: path.to_path_buf(),
        message: format!("cannot read the OBJ: {error}"),
    })?;

    let mut warnings = std::mem::take(&mut libraries.warnings);
    if !libraries.failed {
        for (name, line) in scan.material_uses {
            if !libraries
                .materials
                .iter()
                .any(|material| material.name == name)
            {
                warn(
                    &mut warnings,
                    format!(
                        "{}:{line}: `usemtl {name}`: no such material in the MTL files; its triangles get grey albedo 0.5",
                        path.display()
                    ),
                );
            }
        }
    }
    let mut materials: Vec<Material> = Vec::with_capacity(libraries.materials.len() + 1);
    let mut textures: Vec<Texture> = Vec::new();
    let mut texture_cache: HashMap<PathBuf, Option<u32>> = HashMap::new();
    for parsed in &libraries.materials {
        let mut material = Material {
            name: parsed.name.clone(),
            albedo: parsed.albedo,
            albedo_texture: None,
            emission: parsed.emission,
            phong_exponent: parsed.phong_exponent,
        };
        if let Some(texture_path) = &parsed.albedo_map {
            let texture = match texture_cache.get(texture_path) {
                Some(cached) => *cached,
                None => {
                    let loaded = load_texture_file(texture_path, &mut textures, &mut warnings)?;
                    texture_cache.insert(texture_path.clone(), loaded);
                    loaded
                }
            };
            match texture {
                Some(index) => material.albedo_texture = Some(index),
                None => material.albedo = Vec3::splat(0.5),
            }
        }
        materials.push(material);
    }

    let mut mesh = Mesh::default();
    let any_texcoords = models.iter().any(|model| !model.mesh.texcoords.is_empty());
    let mut default_material: Option<u32> = None;
    for model in &models {
        let source = &model.mesh;
        let base = mesh.positions.len() as u32;
        let vertex_count = source.positions.len() / 3;
        mesh.positions.extend(
            source
                .positions
                .chunks_exact(3)
                .map(|xyz| Vec3::new(xyz[0], xyz[1], xyz[2])),
        );
        if any_texcoords {
            if source.texcoords.len() == vertex_count * 2 {
                mesh.texcoords.extend(
                    source
                        .texcoords
                        .chunks_exact(2)
                        .map(|uv| Vec2::new(uv[0], 1.0 - uv[1])),
                );
            } else {
                if !source.texcoords.is_empty() {
                    warn(
                        &mut warnings,
                        format!(
                            "{}: object '{}' gives texture coordinates for only some face corners; its texture coordinates are ignored",
                            path.display(),
                            model.name
                        ),
                    );
                }
                mesh.texcoords
                    .extend(std::iter::repeat_n(Vec2::ZERO, vertex_count));
            }
        }
        let material_id = match source.material_id {
            Some(id) if id < libraries.materials.len() => id as u32,
            _ => *default_material.get_or_insert_with(|| {
                materials.push(Material::default());
                materials.len() as u32 - 1
            }),
        };
        for corner in source.indices.chunks_exact(3) {
            mesh.triangles
                .push([corner[0] + base, corner[1] + base, corner[2] + base]);
            mesh.material_ids.push(material_id);
        }
    }
    Ok(LoadedMesh {
        mesh,
        materials,
        textures,
        lights: Vec::new(),
        camera: None,
        warnings,
        gltf_primitives: Vec::new(),
    })
}

/// Loads a texture file; a missing file is a warning (the material falls
/// back to grey), a corrupt or oversized one an error.
fn load_texture_file(
    path: &Path,
    textures: &mut Vec<Texture>,
    warnings: &mut Vec<String>,
) -> Result<Option<u32>, SceneError> {
    match std::fs::read(path) {
        Ok(bytes) => {
            let name = path
                .file_name()
                .map_or_else(String::new, |name| name.to_string_lossy().into_owned());
            textures.push(decode_texture(&bytes, name, path)?);
            Ok(Some(textures.len() as u32 - 1))
        }
        Err(error) => {
            warn(
                warnings,
                format!(
                    "{}: cannot read texture ({error}); the material gets grey albedo 0.5",
                    path.display()
                ),
            );
            Ok(None)
        }
    }
}

/// One `newmtl` block, as far as relight uses it.
struct ParsedMaterial {
    name: String,
    albedo: Vec3,
    emission: Vec3,
    phong_exponent: f32,
    albedo_map: Option<PathBuf>,
}

/// State of the `mtllib` callback tobj calls while it parses the OBJ.
#[derive(Default)]
struct MaterialLibraries {
    materials: Vec<ParsedMaterial>,
    warnings: Vec<String>,
    /// A library could not be read (already warned about).
    failed: bool,
    /// The first hard error; tobj's callback can only signal failure, so the
    /// detailed error waits here.
    fatal: Option<SceneError>,
}

impl MaterialLibraries {
    fn load(&mut self, obj_path: &Path, folder: &Path, library: &Path) -> tobj::MTLLoadResult {
        if self.fatal.is_some() {
            return Err(tobj::LoadError::OpenFileFailed);
        }
        let library_path = folder.join(library);
        let bytes = match std::fs::read(&library_path) {
            Ok(bytes) => bytes,
            Err(error) => {
                warn(
                    &mut self.warnings,
                    format!(
                        "{}: cannot read material library {} ({error}); its materials get grey albedo 0.5",
                        obj_path.display(),
                        library_path.display()
                    ),
                );
                self.failed = true;
                return Err(tobj::LoadError::OpenFileFailed);
            }
        };
        match parse_mtl(&library_path, &bytes, &mut self.warnings) {
            Ok(parsed) => {
                // tobj's map type is private; `collect` infers it from the
                // callback's return type.
                let names = parsed
                    .iter()
                    .enumerate()
                    .map(|(index, material)| (material.name.clone(), index))
                    .collect();
                let placeholders = parsed
                    .iter()
                    .map(|material| tobj::Material {
                        name: material.name.clone(),
                        ..Default::default()
                    })
                    .collect();
                self.materials.extend(parsed);
                Ok((placeholders, names))
            }
            Err(error) => {
                self.fatal = Some(error);
                Err(tobj::LoadError::MaterialParseError)
            }
        }
    }
}

fn parse_floats<'a>(
    path: &Path,
    line: usize,
    keyword: &str,
    words: impl Iterator<Item = &'a str>,
) -> Result<Vec<f32>, SceneError> {
    words
        .map(|word| {
            word.parse::<f32>().map_err(|_| SceneError::Syntax {
                path: path.to_path_buf(),
                line,
                message: format!("`{keyword}`: '{word}' is not a number"),
            })
        })
        .collect()
}

/// Parses the MTL statements relight uses (`newmtl`, `Kd`, `Ke`, `Ns`,
/// `map_Kd`) and ignores the rest, as renderers do.
fn parse_mtl(
    path: &Path,
    bytes: &[u8],
    warnings: &mut Vec<String>,
) -> Result<Vec<ParsedMaterial>, SceneError> {
    let text = text_from_bytes(path, bytes)?;
    let folder = path.parent().unwrap_or(Path::new(""));
    let mut materials: Vec<ParsedMaterial> = Vec::new();
    for (index, raw_line) in text.lines().enumerate() {
        let line = index + 1;
        let syntax = |message: String| SceneError::Syntax {
            path: path.to_path_buf(),
            line,
            message,
        };
        let content = raw_line.trim();
        let mut words = content.split_whitespace();
        let Some(keyword) = words.next() else {
            continue;
        };
        if keyword.starts_with('#') {
            continue;
        }
        if keyword == "newmtl" {
            let name = content[keyword.len()..].trim();
            if name.is_empty() {
                return Err(syntax("`newmtl` needs a material name".into()));
            }
            materials.push(ParsedMaterial {
                name: name.to_string(),
                albedo: Vec3::splat(0.5),
                emission: Vec3::ZERO,
                phong_exponent: 1.0,
                albedo_map: None,
            });
            continue;
        }
        let relevant = matches!(keyword, "Kd" | "Ke" | "Ns" | "map_Kd");
        if !relevant {
            continue;
        }
        let Some(material) = materials.last_mut() else {
            return Err(syntax(format!(
                "`{keyword}` before any `newmtl`: start the material with `newmtl NAME`"
            )));
        };
        match keyword {
            "Kd" | "Ke" => {
                let values = parse_floats(path, line, keyword, words)?;
                let colour = match values.as_slice() {
                    [grey] => Vec3::splat(*grey),
                    [r, g, b] => Vec3::new(*r, *g, *b),
                    _ => {
                        return Err(syntax(format!(
                            "`{keyword}` needs one or three numbers (RGB), found {}",
                            values.len()
                        )))
                    }
                };
                if !is_valid_radiometric(colour) {
                    return Err(syntax(format!(
                        "`{keyword}` must be finite and non-negative, found {colour}"
                    )));
                }
                if keyword == "Ke" {
                    material.emission = colour;
                } else {
                    if colour.max_element() > 1.0 {
                        warn(
                            warnings,
                            format!(
                                "{}:{line}: `Kd` {colour} reflects more light than it receives; clamped to 1",
                                path.display()
                            ),
                        );
                    }
                    material.albedo = colour.min(Vec3::ONE);
                }
            }
            "Ns" => {
                let values = parse_floats(path, line, keyword, words)?;
                match values.as_slice() {
                    [exponent] if exponent.is_finite() && *exponent >= 0.0 => {
                        material.phong_exponent = *exponent
                    }
                    _ => {
                        return Err(syntax(
                            "`Ns` needs one finite, non-negative number (the Blinn-Phong exponent)"
                                .into(),
                        ))
                    }
                }
            }
            _ => {
                // Options such as `-s 1 1 1` come first; the file name is last.
                let Some(file) = words.last() else {
                    return Err(syntax("`map_Kd` needs a texture file name".into()));
                };
                material.albedo_map = Some(folder.join(file.replace('\\', "/")));
            }
        }
    }
    Ok(materials)
}

/// Checks every statement tobj interprets, so that tobj never sees input it
/// would reject without a line number (or index out of bounds with).
fn validate_obj_text(path: &Path, text: &str) -> Result<ObjScan, SceneError> {
    let mut scan = ObjScan::default();
    let mut position_count: usize = 0;
    let mut texcoord_count: usize = 0;
    let mut normal_count: usize = 0;
    // tobj splits lines as `BufRead::lines` does: on '\n', dropping "\r\n".
    for (index, raw_line) in text.split('\n').enumerate() {
        let line = index + 1;
        let syntax = |message: String| SceneError::Syntax {
            path: path.to_path_buf(),
            line,
            message,
        };
        let mut words = raw_line.split_whitespace();
        let Some(keyword) = words.next() else {
            continue;
        };
        match keyword {
            "v" => {
                let values = parse_floats(path, line, "v", words.clone().take(3))?;
                if values.len() < 3 {
                    return Err(syntax("`v` needs three coordinates: v X Y Z".into()));
                }
                let extra: Vec<&str> = words.skip(3).collect();
                let mut position = Vec3::from_slice(&values);
                match extra.len() {
                    0 => {}
                    1 => {
                        let weight = parse_floats(path, line, "v", extra.iter().copied())?[0];
                        if weight == 0.0 {
                            return Err(syntax("`v` has weight w = 0: remove the fourth number or make it non-zero".into()));
                        }
                        position /= weight;
                    }
                    3 => {
                        parse_floats(path, line, "v", extra.iter().copied())?;
                        scan.has_vertex_colours = true;
                    }
                    count => {
                        return Err(syntax(format!(
                            "`v` has {} numbers: use X Y Z, X Y Z W, or X Y Z R G B",
                            count + 3
                        )))
                    }
                }
                if !position.is_finite() {
                    return Err(syntax(format!(
                        "vertex position {position} is not finite: fix the coordinates"
                    )));
                }
                position_count += 1;
            }
            "vt" => {
                let values = parse_floats(path, line, "vt", words.take(2))?;
                if values.len() < 2 {
                    return Err(syntax("`vt` needs two texture coordinates: vt U V".into()));
                }
                if !values.iter().all(|value| value.is_finite()) {
                    return Err(syntax("texture coordinates must be finite".into()));
                }
                texcoord_count += 1;
            }
            "vn" => {
                let values = parse_floats(path, line, "vn", words.take(3))?;
                if values.len() < 3 {
                    return Err(syntax("`vn` needs three components: vn X Y Z".into()));
                }
                normal_count += 1;
            }
            "f" | "l" => {
                let corners: Vec<&str> = words.collect();
                let needed = if keyword == "f" { 3 } else { 2 };
                if corners.len() < needed {
                    return Err(syntax(format!(
                        "`{keyword}` needs at least {needed} vertices, found {}",
                        corners.len()
                    )));
                }
                for corner in corners {
                    validate_corner(corner, [position_count, texcoord_count, normal_count])
                        .map_err(syntax)?;
                }
            }
            "usemtl" => {
                let name = raw_line.split_once(' ').unwrap_or_default().1.trim();
                if name.is_empty() {
                    return Err(syntax(
                        "`usemtl` needs a material name, separated by a space".into(),
                    ));
                }
                if !scan.material_uses.iter().any(|(used, _)| used == name) {
                    scan.material_uses.push((name.to_string(), line));
                }
            }
            _ => {}
        }
    }
    Ok(scan)
}

/// What the validation pass learnt about an OBJ.
#[derive(Default)]
struct ObjScan {
    /// Each material name used, with the line of its first `usemtl`.
    material_uses: Vec<(String, usize)>,
    /// Some `v` line has R G B after its coordinates.
    has_vertex_colours: bool,
}

/// Rewrites `v X Y Z R G B` as `v X Y Z`, keeping every line in place so
/// line numbers stay valid.
fn strip_vertex_colours(text: &str) -> String {
    let mut out = String::with_capacity(text.len());
    for (index, line) in text.split('\n').enumerate() {
        if index > 0 {
            out.push('\n');
        }
        let words: Vec<&str> = line.split_whitespace().collect();
        if words.len() == 7 && words[0] == "v" {
            out.push_str(&words[..4].join(" "));
        } else {
            out.push_str(line);
        }
    }
    out
}

/// Validates one `v/vt/vn` face corner against the counts defined so far
/// (OBJ indices are 1-based; negative ones count back from the last).
fn validate_corner(corner: &str, counts: [usize; 3]) -> Result<(), String> {
    const KINDS: [&str; 3] = ["vertex", "texture coordinate", "normal"];
    let parts: Vec<&str> = corner.split('/').collect();
    if parts.len() > 3 {
        return Err(format!("face corner '{corner}' has more than v/vt/vn"));
    }
    if parts[0].is_empty() {
        return Err(format!("face corner '{corner}' lacks a vertex index"));
    }
    for (slot, part) in parts.iter().enumerate() {
        if part.is_empty() {
            continue;
        }
        let index: i64 = part
            .parse()
            .map_err(|_| format!("face corner '{corner}': '{part}' is not an index"))?;
        let count = counts[slot] as i64;
        let valid = (1..=count).contains(&index) || (-count..=-1).contains(&index);
        if !valid {
            return Err(format!(
                "face corner '{corner}': {} index {index} is out of range; {count} {}(s) are defined above this line (indices start at 1, negative ones count back)",
                KINDS[slot], KINDS[slot]
            ));
        }
    }
    Ok(())
}
