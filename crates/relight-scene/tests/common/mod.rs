//! Fixtures shared by the loader tests: temporary folders, a small glTF
//! (JSON + binary buffer, or GLB) and tiny PNG files, all built in code so
//! that each test can corrupt exactly the part it is about.

#![allow(dead_code)]

use serde_json::{json, Value};
use std::f64::consts::FRAC_1_SQRT_2;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicUsize, Ordering};

/// A fresh folder under the system temp dir, removed on drop.
pub struct TempDir {
    pub path: PathBuf,
}

impl TempDir {
    pub fn new(label: &str) -> Self {
        static COUNTER: AtomicUsize = AtomicUsize::new(0);
        let path = std::env::temp_dir().join(format!(
            "relight-scene-{label}-{}-{}",
            std::process::id(),
            COUNTER.fetch_add(1, Ordering::Relaxed)
        ));
        let _ = std::fs::remove_dir_all(&path);
        std::fs::create_dir_all(&path).expect("create temp dir");
        Self { path }
    }

    pub fn write(&self, name: &str, contents: impl AsRef<[u8]>) -> PathBuf {
        let path = self.path.join(name);
        if let Some(parent) = path.parent() {
            std::fs::create_dir_all(parent).expect("create folder");
        }
        std::fs::write(&path, contents).expect("write fixture");
        path
    }

    pub fn path(&self, name: &str) -> PathBuf {
        self.path.join(name)
    }
}

impl Drop for TempDir {
    fn drop(&mut self) {
        let _ = std::fs::remove_dir_all(&self.path);
    }
}

/// A scene file that only names a mesh.
pub fn mesh_only_toml(mesh: &str) -> String {
    format!("mesh = \"{mesh}\"\n")
}

pub const CORNER_OBJ: &str = "\
mtllib mesh.mtl
v 0 0 0
v 1 0 0
v 1 1 0
v 0 1 0
vt 0 0
vt 1 0
vt 1 1
vt 0 1
usemtl white
f 1/1 2/2 3/3 4/4
";

pub const WHITE_MTL: &str = "newmtl white\nKd 0.8 0.8 0.8\n";

/// A quad on y = 0 (front face -Y), with two UV sets and 16-bit indices.
pub fn quad_binary() -> Vec<u8> {
    let mut bytes = Vec::new();
    for position in [
        [0.0f32, 0.0, 0.0],
        [1.0, 0.0, 0.0],
        [1.0, 0.0, 1.0],
        [0.0, 0.0, 1.0],
    ] {
        position
            .iter()
            .for_each(|value| bytes.extend(value.to_le_bytes()));
    }
    for uv in [[0.0f32, 0.0], [1.0, 0.0], [1.0, 1.0], [0.0, 1.0]] {
        uv.iter()
            .for_each(|value| bytes.extend(value.to_le_bytes()));
    }
    for uv in [[0.1f32, 0.1], [0.9, 0.1], [0.9, 0.9], [0.1, 0.9]] {
        uv.iter()
            .for_each(|value| bytes.extend(value.to_le_bytes()));
    }
    for index in [0u16, 1, 2, 0, 2, 3] {
        bytes.extend(index.to_le_bytes());
    }
    assert_eq!(bytes.len(), 124);
    bytes
}

/// glTF JSON for [`quad_binary`]: one emissive material, a camera, a point
/// light and a spot light pointing down.
pub fn quad_gltf(buffer_uri: Option<&str>) -> Value {
    let mut buffer = json!({"byteLength": 124});
    if let Some(uri) = buffer_uri {
        buffer["uri"] = json!(uri);
    }
    json!({
        "asset": {"version": "2.0"},
        "extensionsUsed": ["KHR_lights_punctual", "KHR_materials_emissive_strength"],
        "scene": 0,
        "scenes": [{"nodes": [0, 1, 2, 3]}],
        "nodes": [
            {"mesh": 0, "translation": [0.0, 2.0, 0.0]},
            {"camera": 0, "translation": [0.0, 1.0, 5.0]},
            {"extensions": {"KHR_lights_punctual": {"light": 0}}, "translation": [1.0, 1.0, 1.0]},
            {"extensions": {"KHR_lights_punctual": {"light": 1}},
             "rotation": [-FRAC_1_SQRT_2, 0.0, 0.0, FRAC_1_SQRT_2], "translation": [0.0, 3.0, 0.0]}
        ],
        "cameras": [{"type": "perspective", "perspective": {"yfov": 0.8, "znear": 0.1, "aspectRatio": 1.5}}],
        "extensions": {"KHR_lights_punctual": {"lights": [
            {"type": "point", "color": [1.0, 0.5, 0.25], "intensity": 2.0},
            {"type": "spot", "color": [1.0, 1.0, 1.0], "intensity": 4.0,
             "spot": {"innerConeAngle": 0.3, "outerConeAngle": 0.6}}
        ]}},
        "meshes": [{"primitives": [{
            "attributes": {"POSITION": 0, "TEXCOORD_0": 1, "TEXCOORD_1": 2},
            "indices": 3, "material": 0
        }]}],
        "materials": [{
            "name": "glow",
            "pbrMetallicRoughness": {"baseColorFactor": [0.8, 0.6, 0.4, 1.0], "roughnessFactor": 0.5},
            "emissiveFactor": [1.0, 0.5, 0.25],
            "extensions": {"KHR_materials_emissive_strength": {"emissiveStrength": 4.0}}
        }],
        "buffers": [buffer],
        "bufferViews": [
            {"buffer": 0, "byteOffset": 0, "byteLength": 48},
            {"buffer": 0, "byteOffset": 48, "byteLength": 32},
            {"buffer": 0, "byteOffset": 80, "byteLength": 32},
            {"buffer": 0, "byteOffset": 112, "byteLength": 12}
        ],
        "accessors": [
            {"bufferView": 0, "componentType": 5126, "count": 4, "type": "VEC3",
             "min": [0.0, 0.0, 0.0], "max": [1.0, 0.0, 1.0]},
            {"bufferView": 1, "componentType": 5126, "count": 4, "type": "VEC2"},
            {"bufferView": 2, "componentType": 5126, "count": 4, "type": "VEC2"},
            {"bufferView": 3, "componentType": 5123, "count": 6, "type": "SCALAR"}
        ]
    })
}

/// Packs JSON and a binary chunk into a GLB container.
pub fn to_glb(json: &Value, binary: &[u8]) -> Vec<u8> {
    let mut json_bytes = serde_json::to_vec(json).unwrap();
    while !json_bytes.len().is_multiple_of(4) {
        json_bytes.push(b' ');
    }
    let mut binary = binary.to_vec();
    while !binary.len().is_multiple_of(4) {
        binary.push(0);
    }
    let total = 12 + 8 + json_bytes.len() + 8 + binary.len();
    let mut out = Vec::with_capacity(total);
    out.extend(b"glTF");
    out.extend(2u32.to_le_bytes());
    out.extend((total as u32).to_le_bytes());
    out.extend((json_bytes.len() as u32).to_le_bytes());
    out.extend(b"JSON");
    out.extend(json_bytes);
    out.extend((binary.len() as u32).to_le_bytes());
    out.extend(b"BIN\0");
    out.extend(binary);
    out
}

pub fn base64(bytes: &[u8]) -> String {
    const ALPHABET: &[u8; 64] = b"ABCDEFGHIJKLMNOPQRSTUVWXYZabcdefghijklmnopqrstuvwxyz0123456789+/";
    let mut out = String::new();
    for chunk in bytes.chunks(3) {
        let word = (chunk[0] as u32) << 16
            | (*chunk.get(1).unwrap_or(&0) as u32) << 8
            | *chunk.get(2).unwrap_or(&0) as u32;
        for index in 0..4 {
            if index <= chunk.len() {
                out.push(ALPHABET[(word >> (18 - 6 * index) & 63) as usize] as char);
            } else {
                out.push('=');
            }
        }
    }
    out
}

/// A PNG whose rows are given top to bottom, one sRGB colour per row.
pub fn png_rows(width: u32, rows: &[[u8; 3]]) -> Vec<u8> {
    let image = image::RgbImage::from_fn(width, rows.len() as u32, |_, y| {
        image::Rgb(rows[y as usize])
    });
    let mut bytes = std::io::Cursor::new(Vec::new());
    image.write_to(&mut bytes, image::ImageFormat::Png).unwrap();
    bytes.into_inner()
}

fn crc32(bytes: &[u8]) -> u32 {
    let mut crc = !0u32;
    for &byte in bytes {
        crc ^= byte as u32;
        for _ in 0..8 {
            crc = if crc & 1 != 0 {
                (crc >> 1) ^ 0xEDB8_8320
            } else {
                crc >> 1
            };
        }
    }
    !crc
}

/// Only a PNG signature and header claiming `width` x `height`: enough for
/// the size check, which must refuse it without decoding anything.
pub fn png_header_only(width: u32, height: u32) -> Vec<u8> {
    let mut out = vec![0x89, b'P', b'N', b'G', 0x0D, 0x0A, 0x1A, 0x0A];
    let mut chunk = b"IHDR".to_vec();
    chunk.extend(width.to_be_bytes());
    chunk.extend(height.to_be_bytes());
    chunk.extend([8, 2, 0, 0, 0]);
    out.extend(13u32.to_be_bytes());
    out.extend(&chunk);
    out.extend(crc32(&chunk).to_be_bytes());
    // Decoders read up to the first IDAT before reporting dimensions.
    for kind in [b"IDAT", b"IEND"] {
        out.extend(0u32.to_be_bytes());
        out.extend(kind);
        out.extend(crc32(kind).to_be_bytes());
    }
    out
}

pub fn assert_close(actual: f32, expected: f32, what: &str) {
    assert!(
        (actual - expected).abs() < 1e-4,
        "{what}: {actual} != {expected}"
    );
}

/// The error's text, for `contains` checks.
pub fn message<T: std::fmt::Debug>(result: Result<T, relight_scene::SceneError>) -> String {
    match result {
        Ok(value) => panic!("expected an error, got {value:?}"),
        Err(error) => error.to_string(),
    }
}

pub fn exists(path: &Path) -> bool {
    path.exists()
}
