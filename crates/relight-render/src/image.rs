//! Linear RGB images, EXR and PNG output, exposure and tone mapping.

use relight_core::colour::linear_to_srgb8;
use relight_core::{luminance, Rgb};
use std::path::{Path, PathBuf};

#[derive(Debug, thiserror::Error)]
pub enum ImageError {
    #[error("{path}: cannot write image: {message}")]
    Write { path: PathBuf, message: String },
    #[error("{path}: unsupported image extension: use .exr (linear) or .png (tone-mapped sRGB)")]
    Extension { path: PathBuf },
}

/// A linear RGB image, row-major, row 0 at the top.
#[derive(Clone, Debug, PartialEq)]
pub struct Image {
    pub width: u32,
    pub height: u32,
    pub pixels: Vec<Rgb>,
}

impl Image {
    pub fn new(width: u32, height: u32) -> Self {
        Self {
            width,
            height,
            pixels: vec![Rgb::ZERO; width as usize * height as usize],
        }
    }

    #[inline]
    pub fn get(&self, x: u32, y: u32) -> Rgb {
        self.pixels[(y * self.width + x) as usize]
    }

    /// Exposure that maps the log-average luminance to middle grey
    /// (Reinhard et al. 2002's key value 0.18); 1 for a black image.
    pub fn auto_exposure(&self) -> f32 {
        let (sum, count) = self
            .pixels
            .iter()
            .fold((0.0f64, 0usize), |(sum, count), pixel| {
                let value = luminance(*pixel);
                if value > 0.0 && value.is_finite() {
                    (sum + (value as f64 + 1e-6).ln(), count + 1)
                } else {
                    (sum, count)
                }
            });
        if count == 0 {
            return 1.0;
        }
        (0.18 / (sum / count as f64).exp()) as f32
    }

    /// Writes EXR (linear, 32-bit float) or PNG (exposure-scaled, ACES-fitted
    /// tone curve, sRGB), chosen by the extension. `exposure` None = auto.
    pub fn write(&self, path: &Path, exposure: Option<f32>) -> Result<(), ImageError> {
        let extension = path
            .extension()
            .and_then(|e| e.to_str())
            .map(str::to_ascii_lowercase);
        match extension.as_deref() {
            Some("exr") => self.write_exr(path),
            Some("png") => self.write_png(path, exposure.unwrap_or_else(|| self.auto_exposure())),
            _ => Err(ImageError::Extension {
                path: path.to_path_buf(),
            }),
        }
    }

    /// Writes linear 32-bit float RGB. Compression runs on one thread:
    /// parallel writers store chunks in completion order, and relight's
    /// outputs must be the same bytes on any thread count.
    pub fn write_exr(&self, path: &Path) -> Result<(), ImageError> {
        use exr::prelude::WritableImage;
        let width = self.width as usize;
        let channels =
            exr::prelude::SpecificChannels::rgb(|position: exr::prelude::Vec2<usize>| {
                let pixel = self.pixels[position.y() * width + position.x()];
                (pixel.x, pixel.y, pixel.z)
            });
        exr::prelude::Image::from_channels((width, self.height as usize), channels)
            .write()
            .non_parallel()
            .to_file(path)
            .map_err(|error| ImageError::Write {
                path: path.to_path_buf(),
                message: error.to_string(),
            })
    }

    pub fn write_png(&self, path: &Path, exposure: f32) -> Result<(), ImageError> {
        let bytes = self.to_srgb8(exposure);
        image::save_buffer(
            path,
            &bytes,
            self.width,
            self.height,
            image::ColorType::Rgb8,
        )
        .map_err(|error| ImageError::Write {
            path: path.to_path_buf(),
            message: error.to_string(),
        })
    }

    /// Display-ready 8-bit sRGB bytes.
    pub fn to_srgb8(&self, exposure: f32) -> Vec<u8> {
        self.pixels
            .iter()
            .flat_map(|pixel| {
                let mapped = aces_fitted(*pixel * exposure);
                [mapped.x, mapped.y, mapped.z].map(linear_to_srgb8)
            })
            .collect()
    }

    /// Reads an EXR's RGB channels (for tests and tools).
    pub fn read_exr(path: &Path) -> Result<Self, ImageError> {
        let image = exr::prelude::read_first_rgba_layer_from_file(
            path,
            |resolution, _| Self::new(resolution.width() as u32, resolution.height() as u32),
            |image: &mut Self, position, (r, g, b, _a): (f32, f32, f32, f32)| {
                let index = position.y() * image.width as usize + position.x();
                image.pixels[index] = Rgb::new(r, g, b);
            },
        )
        .map_err(|error| ImageError::Write {
            path: path.to_path_buf(),
            message: error.to_string(),
        })?;
        Ok(image.layer_data.channel_data.pixels)
    }
}

/// Narkowicz's fit of the ACES filmic curve: a soft shoulder so bright
/// light sources do not clip harshly.
#[inline]
pub fn aces_fitted(colour: Rgb) -> Rgb {
    let (a, b, c, d, e) = (2.51f32, 0.03f32, 2.43f32, 0.59f32, 0.14f32);
    let mapped = (colour * (colour * a + Rgb::splat(b)))
        / (colour * (colour * c + Rgb::splat(d)) + Rgb::splat(e));
    mapped.clamp(Rgb::ZERO, Rgb::ONE)
}

/// A false-colour map from 0 (black) through blue, green, yellow to red at 1.
pub fn false_colour(value: f32) -> Rgb {
    let stops = [
        (0.0f32, Rgb::new(0.0, 0.0, 0.0)),
        (0.25, Rgb::new(0.0, 0.2, 1.0)),
        (0.5, Rgb::new(0.0, 0.9, 0.3)),
        (0.75, Rgb::new(1.0, 0.9, 0.0)),
        (1.0, Rgb::new(1.0, 0.0, 0.0)),
    ];
    let value = if value.is_finite() {
        value.clamp(0.0, 1.0)
    } else {
        1.0
    };
    for pair in stops.windows(2) {
        let ((start, low), (end, high)) = (pair[0], pair[1]);
        if value <= end {
            return low.lerp(high, (value - start) / (end - start));
        }
    }
    stops[stops.len() - 1].1
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn exr_round_trip_is_exact() {
        let folder = tempfile::tempdir().unwrap();
        let path = folder.path().join("image.exr");
        let mut image = Image::new(5, 3);
        for (index, pixel) in image.pixels.iter_mut().enumerate() {
            *pixel = Rgb::new(index as f32 * 0.5, 100.0 - index as f32, 1e-3);
        }
        image.write(&path, None).unwrap();
        let back = Image::read_exr(&path).unwrap();
        assert_eq!(back, image);
    }

    #[test]
    fn png_is_written_and_bad_extension_refused() {
        let folder = tempfile::tempdir().unwrap();
        let image = Image {
            width: 2,
            height: 1,
            pixels: vec![Rgb::splat(0.18), Rgb::splat(100.0)],
        };
        image
            .write(&folder.path().join("a.png"), Some(1.0))
            .unwrap();
        let bytes = image.to_srgb8(1.0);
        // The fitted curve maps 0.18 to 0.2669 linear, sRGB 141.1; 100 saturates.
        assert!((140..=142).contains(&bytes[0]), "{}", bytes[0]);
        assert_eq!(bytes[3], 255);
        assert!(image.write(&folder.path().join("a.jpg"), None).is_err());
    }

    #[test]
    fn auto_exposure_maps_uniform_image_to_middle_grey() {
        let image = Image {
            width: 2,
            height: 2,
            pixels: vec![Rgb::splat(2.0); 4],
        };
        assert!((image.auto_exposure() * 2.0 - 0.18).abs() < 1e-4);
    }
}
