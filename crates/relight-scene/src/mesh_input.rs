//! What the scene file and the mesh loaders (OBJ, glTF) share: the mesh a
//! loader hands back, texture and text decoding, and warnings. It depends
//! on neither side, so the scene file calls the loaders and the loaders
//! call this, with no loop between them.

use crate::{Camera, Light, Material, Mesh, SceneError, Texture};
use glam::Vec3;
use relight_core::colour::srgb_to_linear;
use relight_core::Rgb;
use std::path::Path;

/// Largest texture side accepted; larger images are refused before decoding
/// so that a hostile header cannot make us allocate gigabytes.
pub(crate) const MAX_TEXTURE_SIDE: u32 = 16_384;

/// UTF-8 decoding with the line of the first bad byte in the error.
pub(crate) fn text_from_bytes(path: &Path, bytes: &[u8]) -> Result<String, SceneError> {
    String::from_utf8(bytes.to_vec()).map_err(|error| {
        let valid = error.utf8_error().valid_up_to();
        SceneError::Syntax {
            path: path.to_path_buf(),
            line: bytes[..valid].iter().filter(|&&b| b == b'\n').count() + 1,
            message: "the file is not valid UTF-8 text: save it as UTF-8".into(),
        }
    })
}

/// What a mesh loader hands back before the shared clean-up.
#[derive(Default)]
pub(crate) struct LoadedMesh {
    pub mesh: Mesh,
    pub materials: Vec<Material>,
    pub textures: Vec<Texture>,
    pub lights: Vec<Light>,
    pub camera: Option<Camera>,
    pub warnings: Vec<String>,
    pub gltf_primitives: Vec<crate::GltfPrimitive>,
}

/// Records a non-fatal problem both for the caller ([`Scene::warnings`]) and
/// for whoever watches the log.
pub(crate) fn warn(warnings: &mut Vec<String>, message: String) {
    tracing::warn!("{message}");
    warnings.push(message);
}

/// Decodes a PNG or JPEG into linear RGB. The header is checked before any
/// pixel buffer exists, so oversized images cost nothing. Alpha is ignored:
/// relight materials are opaque.
pub(crate) fn decode_texture(
    bytes: &[u8],
    name: String,
    source: &Path,
) -> Result<Texture, SceneError> {
    use image::ImageReader;
    use std::io::Cursor;
    let invalid = |message: String| SceneError::Invalid {
        path: source.to_path_buf(),
        message,
    };
    let reader = || {
        ImageReader::new(Cursor::new(bytes))
            .with_guessed_format()
            .map_err(|error| invalid(format!("texture {name}: {error}")))
    };
    let probe = reader()?;
    if probe.format().is_none() {
        return Err(invalid(format!(
            "texture {name} is neither PNG nor JPEG: convert it to one of those"
        )));
    }
    let (width, height) = probe
        .into_dimensions()
        .map_err(|error| invalid(format!("texture {name} has an unreadable header: {error}")))?;
    if width == 0 || height == 0 || width > MAX_TEXTURE_SIDE || height > MAX_TEXTURE_SIDE {
        return Err(invalid(format!(
            "texture {name} is {width} x {height}: sides must be between 1 and {MAX_TEXTURE_SIDE} pixels; downscale it"
        )));
    }
    let mut decoder = reader()?;
    let mut limits = image::Limits::default();
    limits.max_image_width = Some(MAX_TEXTURE_SIDE);
    limits.max_image_height = Some(MAX_TEXTURE_SIDE);
    // 16 bytes per pixel covers RGBA32F, the widest layout the decoders use.
    limits.max_alloc = Some(width as u64 * height as u64 * 16 + (1 << 20));
    decoder.limits(limits);
    let decoded = decoder
        .decode()
        .map_err(|error| invalid(format!("texture {name} cannot be decoded: {error}")))?;
    let texels: Vec<Rgb> =
        if decoded.color().bytes_per_pixel() / decoded.color().channel_count() == 1 {
            let table: Vec<f32> = (0..256)
                .map(|value| srgb_to_linear(value as f32 / 255.0))
                .collect();
            decoded
                .to_rgb8()
                .pixels()
                .map(|pixel| {
                    Vec3::new(
                        table[pixel[0] as usize],
                        table[pixel[1] as usize],
                        table[pixel[2] as usize],
                    )
                })
                .collect()
        } else {
            decoded
                .to_rgb32f()
                .pixels()
                .map(|pixel| {
                    Vec3::from_array(
                        pixel
                            .0
                            .map(|channel| srgb_to_linear(channel.clamp(0.0, 1.0))),
                    )
                })
                .collect()
        };
    Ok(Texture {
        name,
        width: decoded.width(),
        height: decoded.height(),
        texels,
    })
}
