//! glTF 2.0 loading: `.gltf` with external `.bin` files or `data:` URIs, and
//! binary `.glb`.
//!
//! Design choices:
//! - Only the JSON parsing and validation of the `gltf` crate are used
//!   (`gltf::json::Root::from_slice`, `gltf::Document::from_json`). Its
//!   `import` resolves URIs without any safety check, and its accessor
//!   readers trust counts and offsets from the file (and index with them), so
//!   URIs, the GLB container and accessors are all handled here with checked
//!   arithmetic. Everything is read from the raw JSON structs, whose optional
//!   fields we match instead of unwrapping.
//! - URIs may only be `data:` or relative paths that stay inside the folder
//!   of the glTF file (no absolute paths, no `..` escaping, no other schemes,
//!   no symbolic links leading out): a scene file must not be able to read
//!   arbitrary files.
//! - The node graph is walked iteratively and each node may be visited once,
//!   so a cyclic or shared hierarchy is an error instead of a stack overflow.
//! - Units: relight is radiometric and takes glTF light values as radiometric
//!   as is. `KHR_lights_punctual` point and spot intensities (candela) times
//!   colour become radiant intensity in W/sr per channel; directional
//!   intensities (lux) times colour become irradiance in W/m^2: relight's
//!   one lumen per watt ([`relight_core::LUMENS_PER_WATT`]), not the
//!   physical 683 lm/W, on purpose: exporters' values are rarely
//!   calibrated, a 1:1 mapping keeps scenes predictable, and relight's own
//!   export and engine bridge use the same factor. `range`
//!   is ignored (physical inverse-square falloff).
//! - Node transforms are applied to positions only; relight uses geometric
//!   normals. A transform with negative determinant mirrors the geometry, so
//!   the winding is swapped to keep the front face counter-clockwise.

use crate::mesh_input::{decode_texture, warn, LoadedMesh};
use crate::{Camera, Light, Material, Mesh, SceneError};
use glam::{Mat4, Quat, Vec2, Vec3};
use gltf::json;
use json::validation::Checked;
use relight_core::colour::is_valid_radiometric;
use std::collections::HashMap;
use std::path::{Component, Path, PathBuf};

/// Roughness below this would give an unbounded Blinn-Phong exponent.
const MIN_ROUGHNESS: f32 = 0.01;

/// Reads a `.gltf` or `.glb` file with its buffers and images.
pub(crate) fn load_gltf(path: &Path) -> Result<LoadedMesh, SceneError> {
    let bytes = std::fs::read(path).map_err(|error| SceneError::Io {
        path: path.to_path_buf(),
        error,
    })?;
    let invalid = |message: String| SceneError::Invalid {
        path: path.to_path_buf(),
        message,
    };
    let is_glb = bytes.starts_with(b"glTF");
    let (json_bytes, binary_chunk) = if is_glb {
        split_glb(&bytes).map_err(invalid)?
    } else if path
        .extension()
        .is_some_and(|extension| extension.eq_ignore_ascii_case("glb"))
    {
        return Err(invalid(
            "not a binary glTF (it does not start with 'glTF'): re-export it as .glb, or rename it to .gltf if it is JSON".into(),
        ));
    } else {
        (&bytes[..], None)
    };
    let root = json::Root::from_slice(json_bytes).map_err(|error| {
        let message = format!("invalid glTF JSON: {error}");
        if is_glb {
            invalid(format!("{message} (in the JSON chunk)"))
        } else {
            SceneError::Syntax {
                path: path.to_path_buf(),
                line: error.line().max(1),
                message,
            }
        }
    })?;
    let document = gltf::Document::from_json(root).map_err(|error| {
        invalid(format!(
            "the glTF does not validate: {error}; check it with the Khronos glTF validator"
        ))
    })?;
    let folder = path.parent().unwrap_or(Path::new(""));
    let mut loader = Loader {
        path,
        folder,
        root: document.as_json(),
        buffers: Vec::new(),
        output: LoadedMesh::default(),
        image_cache: HashMap::new(),
        primitives: Vec::new(),
        skipped_primitives: 0,
    };
    loader.load_buffers(binary_chunk)?;
    loader.load_materials()?;
    loader.walk_nodes()?;
    loader.finish()
}

/// Splits a GLB container into its JSON chunk and optional BIN chunk,
/// checking every length against the real data before slicing.
fn split_glb(bytes: &[u8]) -> Result<(&[u8], Option<&[u8]>), String> {
    let read_u32 = |offset: usize| -> Option<u32> {
        bytes
            .get(offset..offset.checked_add(4)?)
            .map(|word| u32::from_le_bytes([word[0], word[1], word[2], word[3]]))
    };
    let truncated = || "the GLB file is truncated: re-export it".to_string();
    let version = read_u32(4).ok_or_else(truncated)?;
    if version != 2 {
        return Err(format!(
            "GLB version {version} is not supported: use glTF 2.0"
        ));
    }
    let declared = read_u32(8).ok_or_else(truncated)? as usize;
    if declared < 12 || declared > bytes.len() {
        return Err(format!(
            "the GLB header declares {declared} bytes but the file has {}: the file is truncated or corrupt",
            bytes.len()
        ));
    }
    let bytes = &bytes[..declared];
    let mut offset = 12usize;
    let mut json_chunk = None;
    let mut binary_chunk = None;
    while offset < bytes.len() {
        let length = read_u32(offset).ok_or_else(truncated)? as usize;
        let kind = read_u32(offset + 4).ok_or_else(truncated)?;
        let start = offset + 8;
        let end = start
            .checked_add(length)
            .filter(|&end| end <= bytes.len())
            .ok_or_else(|| {
                format!("a GLB chunk declares {length} bytes beyond the end of the file")
            })?;
        match kind {
            0x4E4F_534A if json_chunk.is_none() => json_chunk = Some(&bytes[start..end]),
            0x004E_4942 if binary_chunk.is_none() && json_chunk.is_some() => {
                binary_chunk = Some(&bytes[start..end])
            }
            // Unknown chunks are to be skipped, per the specification.
            _ => {}
        }
        // Chunks are 4-byte aligned; a missing pad at the very end is harmless.
        offset = end.saturating_add(3) & !3;
    }
    let json_chunk = json_chunk.ok_or("the GLB has no JSON chunk: re-export it")?;
    Ok((json_chunk, binary_chunk))
}

/// Where a URI points, after the safety checks.
enum UriTarget {
    Data(Vec<u8>),
    File(PathBuf),
}

/// One primitive's contribution, kept apart until we know whether every
/// primitive has a second UV set.
struct Primitive {
    positions: Vec<Vec3>,
    texcoords: Option<Vec<Vec2>>,
    lightmap_uvs: Option<Vec<Vec2>>,
    triangles: Vec<[u32; 3]>,
    material: Option<u32>,
    /// Where it came from; `None` for strips and fans, whose triangles
    /// relight makes itself (an engine keeps them as strips and fans).
    source: Option<crate::GltfPrimitive>,
}

struct Loader<'a> {
    path: &'a Path,
    folder: &'a Path,
    root: &'a json::Root,
    /// Each buffer cut to its declared `byteLength`.
    buffers: Vec<Vec<u8>>,
    output: LoadedMesh,
    /// Image index to texture index; `None` when the image file is missing.
    image_cache: HashMap<usize, Option<u32>>,
    primitives: Vec<Primitive>,
    skipped_primitives: usize,
}

impl Loader<'_> {
    fn invalid(&self, message: impl Into<String>) -> SceneError {
        SceneError::Invalid {
            path: self.path.to_path_buf(),
            message: message.into(),
        }
    }

    fn resolve_uri(&self, uri: &str, what: &str) -> Result<UriTarget, SceneError> {
        if let Some(rest) = uri.strip_prefix("data:") {
            let Some((_, payload)) = rest.split_once(";base64,") else {
                return Err(self.invalid(format!("{what}: only base64 data: URIs are supported")));
            };
            return decode_base64(payload)
                .map(UriTarget::Data)
                .ok_or_else(|| self.invalid(format!("{what}: the data: URI is not valid base64")));
        }
        let refuse = |reason: &str| {
            self.invalid(format!(
                "{what}: URI '{uri}' is refused ({reason}); glTF files may only reference data: URIs and files inside their own folder"
            ))
        };
        let has_scheme = uri.split_once(':').is_some_and(|(scheme, _)| {
            scheme
                .chars()
                .next()
                .is_some_and(|first| first.is_ascii_alphabetic())
                && scheme
                    .chars()
                    .all(|c| c.is_ascii_alphanumeric() || matches!(c, '+' | '-' | '.'))
        });
        if has_scheme {
            return Err(refuse("a URI scheme other than data:"));
        }
        let decoded = percent_decode(uri);
        if decoded.starts_with('/') || decoded.starts_with('\\') || decoded.contains(':') {
            return Err(refuse("an absolute path"));
        }
        let mut relative = PathBuf::new();
        let mut depth = 0usize;
        for part in decoded.split(['/', '\\']) {
            match part {
                "" | "." => {}
                ".." => {
                    if depth == 0 {
                        return Err(refuse("it leaves the glTF file's folder"));
                    }
                    depth -= 1;
                    relative.pop();
                }
                name => {
                    depth += 1;
                    relative.push(name);
                }
            }
        }
        if depth == 0 {
            return Err(refuse("it names no file"));
        }
        // Path::push of an absolute or prefixed component would replace the
        // whole path; the checks above rule that out, this double-checks.
        if relative
            .components()
            .any(|c| !matches!(c, Component::Normal(_)))
        {
            return Err(refuse("an absolute path"));
        }
        let file = self.folder.join(&relative);
        // Symbolic links could still lead out of the folder.
        if let (Ok(real_file), Ok(real_folder)) = (
            std::fs::canonicalize(&file),
            std::fs::canonicalize(if self.folder.as_os_str().is_empty() {
                Path::new(".")
            } else {
                self.folder
            }),
        ) {
            if !real_file.starts_with(&real_folder) {
                return Err(refuse(
                    "it resolves to a file outside the glTF file's folder",
                ));
            }
        }
        Ok(UriTarget::File(file))
    }

    fn load_buffers(&mut self, binary_chunk: Option<&[u8]>) -> Result<(), SceneError> {
        for (index, buffer) in self.root.buffers.iter().enumerate() {
            let declared = usize::try_from(buffer.byte_length.0).unwrap_or(usize::MAX);
            let what = format!("buffer {index}");
            let mut data = match &buffer.uri {
                None => match binary_chunk {
                    Some(chunk) if index == 0 => chunk.to_vec(),
                    _ => {
                        return Err(self.invalid(format!(
                            "{what} has no uri and there is no GLB binary chunk for it"
                        )))
                    }
                },
                Some(uri) => match self.resolve_uri(uri, &what)? {
                    UriTarget::Data(data) => data,
                    UriTarget::File(file) => std::fs::read(&file)
                        .map_err(|error| SceneError::Io { path: file, error })?,
                },
            };
            if data.len() < declared {
                return Err(self.invalid(format!(
                    "{what} declares {declared} bytes but only {} exist: the file is truncated or the byteLength is wrong",
                    data.len()
                )));
            }
            data.truncate(declared);
            self.buffers.push(data);
        }
        Ok(())
    }

    /// The bytes of a buffer view, bounds-checked against its buffer.
    fn view_bytes(&self, view_index: usize) -> Result<(&[u8], Option<usize>), SceneError> {
        let view = self
            .root
            .buffer_views
            .get(view_index)
            .ok_or_else(|| self.invalid(format!("bufferView {view_index} does not exist")))?;
        let buffer = self.buffers.get(view.buffer.value()).ok_or_else(|| {
            self.invalid(format!("bufferView {view_index} names a missing buffer"))
        })?;
        let offset =
            usize::try_from(view.byte_offset.map_or(0, |offset| offset.0)).unwrap_or(usize::MAX);
        let length = usize::try_from(view.byte_length.0).unwrap_or(usize::MAX);
        let bytes = offset
            .checked_add(length)
            .and_then(|end| buffer.get(offset..end))
            .ok_or_else(|| {
                self.invalid(format!(
                    "bufferView {view_index} (offset {offset}, length {length}) lies outside its buffer of {} bytes",
                    buffer.len()
                ))
            })?;
        Ok((bytes, view.byte_stride.map(|stride| stride.0)))
    }

    /// Reads an accessor as `f32`s, `dimensions` per element. Integer
    /// components are converted, honouring `normalized`.
    fn read_accessor(
        &self,
        accessor_index: usize,
        expected: json::accessor::Type,
        what: &str,
    ) -> Result<Vec<f32>, SceneError> {
        use json::accessor::ComponentType;
        let name = format!("accessor {accessor_index} ({what})");
        let accessor = self
            .root
            .accessors
            .get(accessor_index)
            .ok_or_else(|| self.invalid(format!("{name} does not exist")))?;
        if accessor.sparse.is_some() {
            return Err(self.invalid(format!(
                "{name} is sparse, which relight does not support: export without sparse accessors"
            )));
        }
        let (Checked::Valid(component), Checked::Valid(kind)) =
            (accessor.component_type, accessor.type_)
        else {
            return Err(self.invalid(format!("{name} has an invalid componentType or type")));
        };
        let component = component.0;
        if kind != expected {
            return Err(self.invalid(format!("{name} has type {kind:?}, expected {expected:?}")));
        }
        let dimensions = kind.multiplicity();
        let count = usize::try_from(accessor.count.0).unwrap_or(usize::MAX);
        if count == 0 {
            return Ok(Vec::new());
        }
        let Some(view_index) = accessor.buffer_view else {
            return Err(self.invalid(format!(
                "{name} has no bufferView: relight needs explicit data"
            )));
        };
        let (view, stride) = self.view_bytes(view_index.value())?;
        let component_size = component.size();
        let element_size = component_size * dimensions;
        let stride = stride.unwrap_or(element_size);
        if stride < element_size {
            return Err(self.invalid(format!(
                "{name}: byteStride {stride} is smaller than one element ({element_size} bytes)"
            )));
        }
        let offset = usize::try_from(accessor.byte_offset.map_or(0, |offset| offset.0))
            .unwrap_or(usize::MAX);
        let needed = stride
            .checked_mul(count - 1)
            .and_then(|bytes| bytes.checked_add(element_size))
            .and_then(|bytes| bytes.checked_add(offset));
        if needed.is_none_or(|needed| needed > view.len()) {
            return Err(self.invalid(format!(
                "{name}: {count} elements need more bytes than its bufferView holds ({}): the count or offset is wrong",
                view.len()
            )));
        }
        let normalized = accessor.normalized;
        let read = |bytes: &[u8]| -> f32 {
            match component {
                ComponentType::F32 => f32::from_le_bytes([bytes[0], bytes[1], bytes[2], bytes[3]]),
                ComponentType::U32 => {
                    u32::from_le_bytes([bytes[0], bytes[1], bytes[2], bytes[3]]) as f32
                }
                ComponentType::U16 => {
                    let value = u16::from_le_bytes([bytes[0], bytes[1]]) as f32;
                    if normalized {
                        value / 65_535.0
                    } else {
                        value
                    }
                }
                ComponentType::I16 => {
                    let value = i16::from_le_bytes([bytes[0], bytes[1]]) as f32;
                    if normalized {
                        (value / 32_767.0).max(-1.0)
                    } else {
                        value
                    }
                }
                ComponentType::U8 => {
                    let value = bytes[0] as f32;
                    if normalized {
                        value / 255.0
                    } else {
                        value
                    }
                }
                ComponentType::I8 => {
                    let value = bytes[0] as i8 as f32;
                    if normalized {
                        (value / 127.0).max(-1.0)
                    } else {
                        value
                    }
                }
            }
        };
        // The size check above bounds this allocation by the buffer's size.
        let mut values = Vec::with_capacity(count * dimensions);
        for element in 0..count {
            let start = offset + element * stride;
            for component_index in 0..dimensions {
                let at = start + component_index * component_size;
                values.push(read(&view[at..at + component_size]));
            }
        }
        Ok(values)
    }

    fn read_indices(
        &self,
        accessor_index: usize,
        vertex_count: usize,
    ) -> Result<Vec<u32>, SceneError> {
        use json::accessor::ComponentType;
        let accessor = self.root.accessors.get(accessor_index).ok_or_else(|| {
            self.invalid(format!("index accessor {accessor_index} does not exist"))
        })?;
        let component = match accessor.component_type {
            Checked::Valid(component) => component.0,
            Checked::Invalid => {
                return Err(self.invalid(format!(
                    "accessor {accessor_index} has an invalid componentType"
                )))
            }
        };
        if !matches!(
            component,
            ComponentType::U8 | ComponentType::U16 | ComponentType::U32
        ) || accessor.normalized
        {
            return Err(self.invalid(format!(
                "index accessor {accessor_index} must hold unsigned bytes, shorts or ints"
            )));
        }
        let values = self.read_accessor(accessor_index, json::accessor::Type::Scalar, "indices")?;
        // u32 indices above 2^24 lose precision in f32, so re-read exact values.
        let indices: Vec<u32> = if component == ComponentType::U32 {
            self.read_u32_exact(accessor_index, values.len())?
        } else {
            values.into_iter().map(|value| value as u32).collect()
        };
        if let Some(bad) = indices
            .iter()
            .find(|&&index| index as usize >= vertex_count)
        {
            return Err(self.invalid(format!(
                "index accessor {accessor_index} references vertex {bad}, but the primitive has {vertex_count} vertices"
            )));
        }
        Ok(indices)
    }

    /// Exact `u32` scalars of an accessor already checked by `read_accessor`.
    fn read_u32_exact(&self, accessor_index: usize, count: usize) -> Result<Vec<u32>, SceneError> {
        let accessor = &self.root.accessors[accessor_index];
        let Some(view_index) = accessor.buffer_view else {
            return Ok(Vec::new());
        };
        let (view, stride) = self.view_bytes(view_index.value())?;
        let stride = stride.unwrap_or(4);
        let offset = usize::try_from(accessor.byte_offset.map_or(0, |offset| offset.0))
            .unwrap_or(usize::MAX);
        Ok((0..count)
            .map(|element| {
                let at = offset + element * stride;
                u32::from_le_bytes([view[at], view[at + 1], view[at + 2], view[at + 3]])
            })
            .collect())
    }

    fn load_materials(&mut self) -> Result<(), SceneError> {
        let root = self.root;
        for (index, material) in root.materials.iter().enumerate() {
            let name = material
                .name
                .clone()
                .unwrap_or_else(|| format!("material {index}"));
            let pbr = &material.pbr_metallic_roughness;
            let [red, green, blue, _alpha] = pbr.base_color_factor.0;
            let mut albedo = Vec3::new(red, green, blue);
            if !is_valid_radiometric(albedo) {
                return Err(self.invalid(format!(
                    "material '{name}': baseColorFactor must be finite and non-negative"
                )));
            }
            if albedo.max_element() > 1.0 {
                warn(
                    &mut self.output.warnings,
                    format!(
                        "{}: material '{name}' has baseColorFactor above 1; clamped",
                        self.path.display()
                    ),
                );
                albedo = albedo.min(Vec3::ONE);
            }
            let roughness = pbr.roughness_factor.0;
            if !roughness.is_finite() {
                return Err(
                    self.invalid(format!("material '{name}': roughnessFactor must be finite"))
                );
            }
            let roughness = roughness.clamp(MIN_ROUGHNESS, 1.0);
            let phong_exponent = 2.0 / roughness.powi(4) - 2.0;
            let strength = material
                .extensions
                .as_ref()
                .and_then(|extensions| extensions.emissive_strength.as_ref())
                .map_or(1.0, |strength| strength.emissive_strength.0);
            let emission = Vec3::from_array(material.emissive_factor.0) * strength;
            if !is_valid_radiometric(emission) {
                return Err(self.invalid(format!(
                    "material '{name}': emissiveFactor times KHR_materials_emissive_strength must be finite and non-negative"
                )));
            }
            if material.emissive_texture.is_some() {
                warn(
                    &mut self.output.warnings,
                    format!(
                        "{}: material '{name}' has an emissive texture, which relight ignores (emissiveFactor is used)",
                        self.path.display()
                    ),
                );
            }
            let mut albedo_texture = None;
            if let Some(info) = &pbr.base_color_texture {
                if info.tex_coord != 0 {
                    warn(
                        &mut self.output.warnings,
                        format!(
                            "{}: material '{name}' samples its base colour with TEXCOORD_{}; relight uses TEXCOORD_0",
                            self.path.display(),
                            info.tex_coord
                        ),
                    );
                }
                let texture = root.textures.get(info.index.value()).ok_or_else(|| {
                    self.invalid(format!("material '{name}' names a missing texture"))
                })?;
                match self.load_image(texture.source.value())? {
                    Some(texture) => albedo_texture = Some(texture),
                    None => albedo = Vec3::splat(0.5),
                }
            }
            self.output.materials.push(Material {
                name,
                albedo,
                albedo_texture,
                emission,
                phong_exponent,
            });
        }
        Ok(())
    }

    /// Decodes an image once; `None` when its file is missing (the material
    /// falls back to grey with a warning).
    fn load_image(&mut self, image_index: usize) -> Result<Option<u32>, SceneError> {
        if let Some(cached) = self.image_cache.get(&image_index) {
            return Ok(*cached);
        }
        let image = self
            .root
            .images
            .get(image_index)
            .ok_or_else(|| self.invalid(format!("image {image_index} does not exist")))?;
        let name = image
            .name
            .clone()
            .unwrap_or_else(|| format!("image {image_index}"));
        let what = format!("image {image_index}");
        let (bytes, source) = match (&image.uri, image.buffer_view) {
            (Some(uri), _) => match self.resolve_uri(uri, &what)? {
                UriTarget::Data(bytes) => (bytes, self.path.to_path_buf()),
                UriTarget::File(file) => match std::fs::read(&file) {
                    Ok(bytes) => (bytes, file),
                    Err(error) => {
                        warn(
                            &mut self.output.warnings,
                            format!(
                                "{}: cannot read texture {} ({error}); the material gets grey albedo 0.5",
                                self.path.display(),
                                file.display()
                            ),
                        );
                        self.image_cache.insert(image_index, None);
                        return Ok(None);
                    }
                },
            },
            (None, Some(view)) => (
                self.view_bytes(view.value())?.0.to_vec(),
                self.path.to_path_buf(),
            ),
            (None, None) => {
                return Err(self.invalid(format!("{what} has neither a uri nor a bufferView")));
            }
        };
        let texture = decode_texture(&bytes, name, &source)?;
        self.output.textures.push(texture);
        let index = Some(self.output.textures.len() as u32 - 1);
        self.image_cache.insert(image_index, index);
        Ok(index)
    }

    fn walk_nodes(&mut self) -> Result<(), SceneError> {
        let root = self.root;
        let scene_index = root
            .scene
            .map(|scene| scene.value())
            .or(if root.scenes.is_empty() {
                None
            } else {
                Some(0)
            });
        let roots: Vec<usize> = match scene_index {
            Some(scene) => root
                .scenes
                .get(scene)
                .ok_or_else(|| self.invalid(format!("scene {scene} does not exist")))?
                .nodes
                .iter()
                .map(|node| node.value())
                .collect(),
            None => {
                // No scene: every node that is nobody's child is a root.
                let mut is_child = vec![false; root.nodes.len()];
                for node in &root.nodes {
                    for child in node.children.iter().flatten() {
                        if let Some(flag) = is_child.get_mut(child.value()) {
                            *flag = true;
                        }
                    }
                }
                (0..root.nodes.len())
                    .filter(|&node| !is_child[node])
                    .collect()
            }
        };
        let mut visited = vec![false; root.nodes.len()];
        let mut stack: Vec<(usize, Mat4)> = roots
            .into_iter()
            .rev()
            .map(|node| (node, Mat4::IDENTITY))
            .collect();
        while let Some((node_index, parent)) = stack.pop() {
            let node = root
                .nodes
                .get(node_index)
                .ok_or_else(|| self.invalid(format!("node {node_index} does not exist")))?;
            if std::mem::replace(&mut visited[node_index], true) {
                return Err(self.invalid(format!(
                    "node {node_index} is reached twice (a cycle or a node with two parents): glTF nodes must form a tree"
                )));
            }
            let world = parent * self.local_transform(node_index, node)?;
            if !world.is_finite() {
                return Err(self.invalid(format!(
                    "node {node_index}: its world transform is not finite"
                )));
            }
            if let Some(mesh) = node.mesh {
                self.add_mesh(node_index, mesh.value(), world)?;
            }
            if let Some(camera) = node.camera {
                self.add_camera(camera.value(), world)?;
            }
            let light = node
                .extensions
                .as_ref()
                .and_then(|extensions| extensions.khr_lights_punctual.as_ref())
                .map(|light| light.light.value());
            if let Some(light) = light {
                self.add_light(light, world)?;
            }
            for child in node.children.iter().flatten().rev() {
                stack.push((child.value(), world));
            }
        }
        Ok(())
    }

    fn local_transform(&self, index: usize, node: &json::Node) -> Result<Mat4, SceneError> {
        if let Some(matrix) = node.matrix {
            return Ok(Mat4::from_cols_array(&matrix));
        }
        let translation = Vec3::from_array(node.translation.unwrap_or([0.0; 3]));
        let scale = Vec3::from_array(node.scale.unwrap_or([1.0; 3]));
        let [x, y, z, w] = node
            .rotation
            .as_ref()
            .map_or([0.0, 0.0, 0.0, 1.0], |rotation| rotation.0);
        let rotation = Quat::from_xyzw(x, y, z, w);
        let length = rotation.length();
        if !(length.is_finite() && length > 1e-6) {
            return Err(self.invalid(format!("node {index}: rotation is not a unit quaternion")));
        }
        Ok(Mat4::from_scale_rotation_translation(
            scale,
            rotation / length,
            translation,
        ))
    }

    fn add_mesh(
        &mut self,
        node_index: usize,
        mesh_index: usize,
        world: Mat4,
    ) -> Result<(), SceneError> {
        use json::mesh::{Mode, Semantic};
        let root = self.root;
        let mesh = root
            .meshes
            .get(mesh_index)
            .ok_or_else(|| self.invalid(format!("mesh {mesh_index} does not exist")))?;
        let mirrored = world.determinant() < 0.0;
        for (primitive_index, primitive) in mesh.primitives.iter().enumerate() {
            let what = format!("mesh {mesh_index} primitive {primitive_index}");
            let mode = match primitive.mode {
                Checked::Valid(mode) => mode,
                Checked::Invalid => return Err(self.invalid(format!("{what} has an invalid mode"))),
            };
            if !matches!(
                mode,
                Mode::Triangles | Mode::TriangleStrip | Mode::TriangleFan
            ) {
                self.skipped_primitives += 1;
                continue;
            }
            let attribute = |semantic: Semantic| {
                primitive
                    .attributes
                    .get(&Checked::Valid(semantic))
                    .map(|index| index.value())
            };
            let Some(position_accessor) = attribute(Semantic::Positions) else {
                return Err(self.invalid(format!("{what} has no POSITION attribute")));
            };
            let positions: Vec<Vec3> = self
                .read_accessor(position_accessor, json::accessor::Type::Vec3, "POSITION")?
                .chunks_exact(3)
                .map(|xyz| world.transform_point3(Vec3::new(xyz[0], xyz[1], xyz[2])))
                .collect();
            if positions.iter().any(|position| !position.is_finite()) {
                return Err(self.invalid(format!(
                    "{what}: a vertex position is not finite (in the file or after the node transform)"
                )));
            }
            let read_uvs =
                |semantic: Semantic, name: &str| -> Result<Option<Vec<Vec2>>, SceneError> {
                    let Some(accessor) = attribute(semantic) else {
                        return Ok(None);
                    };
                    let uvs: Vec<Vec2> = self
                        .read_accessor(accessor, json::accessor::Type::Vec2, name)?
                        .chunks_exact(2)
                        .map(|uv| Vec2::new(uv[0], uv[1]))
                        .collect();
                    if uvs.len() != positions.len() {
                        return Err(self.invalid(format!(
                            "{what}: {name} has {} elements but POSITION has {}",
                            uvs.len(),
                            positions.len()
                        )));
                    }
                    if uvs.iter().any(|uv| !uv.is_finite()) {
                        return Err(self.invalid(format!("{what}: {name} has non-finite values")));
                    }
                    Ok(Some(uvs))
                };
            let texcoords = read_uvs(Semantic::TexCoords(0), "TEXCOORD_0")?;
            let lightmap_uvs = read_uvs(Semantic::TexCoords(1), "TEXCOORD_1")?;
            let corners: Vec<u32> = match primitive.indices {
                Some(indices) => self.read_indices(indices.value(), positions.len())?,
                None => (0..positions.len() as u32).collect(),
            };
            let mut triangles: Vec<[u32; 3]> = match mode {
                Mode::TriangleStrip => (0..corners.len().saturating_sub(2))
                    .map(|i| {
                        // Every other strip triangle is flipped to keep one winding.
                        if i % 2 == 0 {
                            [corners[i], corners[i + 1], corners[i + 2]]
                        } else {
                            [corners[i + 1], corners[i], corners[i + 2]]
                        }
                    })
                    .collect(),
                Mode::TriangleFan => (1..corners.len().saturating_sub(1))
                    .map(|i| [corners[i], corners[i + 1], corners[0]])
                    .collect(),
                _ => corners
                    .chunks_exact(3)
                    .map(|corner| [corner[0], corner[1], corner[2]])
                    .collect(),
            };
            if mirrored {
                for triangle in &mut triangles {
                    triangle.swap(1, 2);
                }
            }
            let material = match primitive.material {
                Some(material) if material.value() < self.output.materials.len() => {
                    Some(material.value() as u32)
                }
                Some(material) => {
                    return Err(self.invalid(format!(
                        "{what} names missing material {}",
                        material.value()
                    )))
                }
                None => None,
            };
            let source = matches!(mode, Mode::Triangles).then(|| crate::GltfPrimitive {
                node: node_index as u32,
                mesh: mesh_index as u32,
                primitive: primitive_index as u32,
                world,
                mirrored,
                triangles: Vec::new(),
            });
            self.primitives.push(Primitive {
                positions,
                texcoords,
                lightmap_uvs,
                triangles,
                material,
                source,
            });
        }
        Ok(())
    }

    fn add_camera(&mut self, camera_index: usize, world: Mat4) -> Result<(), SceneError> {
        // The first camera in scene order wins, as viewers do.
        if self.output.camera.is_some() {
            return Ok(());
        }
        let camera = self
            .root
            .cameras
            .get(camera_index)
            .ok_or_else(|| self.invalid(format!("camera {camera_index} does not exist")))?;
        let Some(perspective) = camera.perspective.as_ref().filter(|_| {
            matches!(
                camera.type_,
                Checked::Valid(json::camera::Type::Perspective)
            )
        }) else {
            warn(
                &mut self.output.warnings,
                format!(
                    "{}: camera {camera_index} is not a perspective camera; relight renders pinhole cameras only, so it is ignored",
                    self.path.display()
                ),
            );
            return Ok(());
        };
        let fov_y_degrees = perspective.yfov.to_degrees();
        if !(fov_y_degrees > 0.0 && fov_y_degrees < 180.0) {
            return Err(self.invalid(format!(
                "camera {camera_index}: yfov must be between 0 and pi radians"
            )));
        }
        let height = 256u32;
        let width = match perspective.aspect_ratio {
            Some(aspect) if aspect.is_finite() && aspect > 0.0 => (aspect * height as f32)
                .round()
                .clamp(1.0, crate::mesh_input::MAX_TEXTURE_SIDE as f32)
                as u32,
            _ => height,
        };
        let eye = world.transform_point3(Vec3::ZERO);
        let forward = world.transform_vector3(-Vec3::Z).normalize_or_zero();
        let up = world.transform_vector3(Vec3::Y).normalize_or_zero();
        if forward == Vec3::ZERO || up == Vec3::ZERO || forward.cross(up).length() < 1e-6 {
            return Err(self.invalid(format!(
                "camera {camera_index}: its node transform collapses the view direction"
            )));
        }
        self.output.camera = Some(Camera {
            eye,
            target: eye + forward,
            up,
            fov_y_degrees,
            resolution: [width, height],
        });
        Ok(())
    }

    fn add_light(&mut self, light_index: usize, world: Mat4) -> Result<(), SceneError> {
        use json::extensions::scene::khr_lights_punctual::Type;
        let light = self
            .root
            .extensions
            .as_ref()
            .and_then(|extensions| extensions.khr_lights_punctual.as_ref())
            .and_then(|lights| lights.lights.get(light_index))
            .ok_or_else(|| {
                self.invalid(format!(
                    "KHR_lights_punctual light {light_index} does not exist"
                ))
            })?;
        let what = format!("KHR_lights_punctual light {light_index}");
        let value = Vec3::from_array(light.color) * light.intensity;
        if !is_valid_radiometric(value) {
            return Err(self.invalid(format!(
                "{what}: color times intensity must be finite and non-negative"
            )));
        }
        let position = world.transform_point3(Vec3::ZERO);
        let direction = world.transform_vector3(-Vec3::Z).normalize_or_zero();
        let needs_direction = !matches!(light.type_, Checked::Valid(Type::Point));
        if needs_direction && direction == Vec3::ZERO {
            return Err(self.invalid(format!(
                "{what}: its node transform collapses the light direction"
            )));
        }
        let light = match light.type_ {
            Checked::Valid(Type::Point) => Light::Point {
                position,
                intensity: value,
            },
            Checked::Valid(Type::Directional) => Light::Directional {
                direction,
                irradiance: value,
            },
            Checked::Valid(Type::Spot) => {
                let (inner, outer) = light
                    .spot
                    .as_ref()
                    .map_or((0.0, std::f32::consts::FRAC_PI_4), |spot| {
                        (spot.inner_cone_angle, spot.outer_cone_angle)
                    });
                let valid = inner >= 0.0
                    && inner <= outer
                    && outer > 0.0
                    && outer <= std::f32::consts::FRAC_PI_2;
                if !valid {
                    return Err(self.invalid(format!(
                        "{what}: cone angles must satisfy 0 <= innerConeAngle <= outerConeAngle <= pi/2 (radians), found {inner} and {outer}"
                    )));
                }
                Light::Spot {
                    position,
                    direction,
                    intensity: value,
                    inner_angle: inner,
                    outer_angle: outer,
                }
            }
            Checked::Invalid => return Err(self.invalid(format!("{what} has an invalid type"))),
        };
        self.output.lights.push(light);
        Ok(())
    }

    fn finish(mut self) -> Result<LoadedMesh, SceneError> {
        if self.skipped_primitives > 0 {
            warn(
                &mut self.output.warnings,
                format!(
                    "{}: skipped {} point or line primitive(s); relight renders triangles only",
                    self.path.display(),
                    self.skipped_primitives
                ),
            );
        }
        let any_texcoords = self
            .primitives
            .iter()
            .any(|primitive| primitive.texcoords.is_some());
        let all_lightmap_uvs = !self.primitives.is_empty()
            && self
                .primitives
                .iter()
                .all(|primitive| primitive.lightmap_uvs.is_some());
        let default_material = self.output.materials.len() as u32;
        let mut needs_default = false;
        let mut mesh = Mesh::default();
        for primitive in self.primitives {
            let base = u32::try_from(mesh.positions.len())
                .ok()
                .filter(|base| base.checked_add(primitive.positions.len() as u32).is_some())
                .ok_or_else(|| SceneError::Invalid {
                    path: self.path.to_path_buf(),
                    message: "more than 4 billion vertices: split the scene".into(),
                })?;
            let vertex_count = primitive.positions.len();
            mesh.positions.extend(primitive.positions);
            if any_texcoords {
                match primitive.texcoords {
                    Some(texcoords) => mesh.texcoords.extend(texcoords),
                    None => mesh
                        .texcoords
                        .extend(std::iter::repeat_n(Vec2::ZERO, vertex_count)),
                }
            }
            if all_lightmap_uvs {
                mesh.lightmap_uvs
                    .extend(primitive.lightmap_uvs.into_iter().flatten());
            }
            let material = primitive.material.unwrap_or_else(|| {
                needs_default = true;
                default_material
            });
            if let Some(mut source) = primitive.source {
                let first = mesh.triangles.len() as u32;
                source.triangles = (first..first + primitive.triangles.len() as u32)
                    .map(Some)
                    .collect();
                self.output.gltf_primitives.push(source);
            }
            for triangle in primitive.triangles {
                mesh.triangles.push(triangle.map(|index| index + base));
                mesh.material_ids.push(material);
            }
        }
        if needs_default {
            self.output.materials.push(Material::default());
        }
        self.output.mesh = mesh;
        Ok(self.output)
    }
}

/// Standard or URL-safe base64, padding optional; `None` on any other byte.
fn decode_base64(text: &str) -> Option<Vec<u8>> {
    let value_of = |byte: u8| -> Option<u32> {
        Some(match byte {
            b'A'..=b'Z' => byte - b'A',
            b'a'..=b'z' => byte - b'a' + 26,
            b'0'..=b'9' => byte - b'0' + 52,
            b'+' | b'-' => 62,
            b'/' | b'_' => 63,
            _ => return None,
        } as u32)
    };
    let trimmed = text.trim_end_matches('=');
    let mut output = Vec::with_capacity(trimmed.len() / 4 * 3 + 3);
    let mut accumulator = 0u32;
    let mut bits = 0u32;
    for byte in trimmed.bytes() {
        accumulator = (accumulator << 6) | value_of(byte)?;
        bits += 6;
        if bits >= 8 {
            bits -= 8;
            output.push((accumulator >> bits) as u8);
            accumulator &= (1 << bits) - 1;
        }
    }
    Some(output)
}

/// Decodes `%XX` escapes of a relative URI; malformed escapes stay literal.
fn percent_decode(uri: &str) -> String {
    let bytes = uri.as_bytes();
    let mut output = Vec::with_capacity(bytes.len());
    let mut index = 0;
    while index < bytes.len() {
        let hex = |offset: usize| {
            bytes
                .get(index + offset)
                .and_then(|&byte| (byte as char).to_digit(16))
        };
        match (bytes[index], hex(1), hex(2)) {
            (b'%', Some(high), Some(low)) => {
                output.push((high * 16 + low) as u8);
                index += 3;
            }
            (byte, _, _) => {
                output.push(byte);
                index += 1;
            }
        }
    }
    String::from_utf8_lossy(&output).into_owned()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn base64_round_trip_of_known_strings() {
        assert_eq!(decode_base64("TWFu").unwrap(), b"Man");
        assert_eq!(decode_base64("TWE=").unwrap(), b"Ma");
        assert_eq!(decode_base64("TQ==").unwrap(), b"M");
        assert!(decode_base64("T*==").is_none());
    }

    #[test]
    fn percent_escapes_are_decoded() {
        assert_eq!(percent_decode("a%20b%2e%2E"), "a b..");
        assert_eq!(percent_decode("100%"), "100%");
    }
}
