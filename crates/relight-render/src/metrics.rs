//! Error metrics between a technique's result and the reference.
//!
//! relight uses one definition everywhere: relative RMSE is the L2 norm of
//! the error over the L2 norm of the reference, over all pixels (or
//! receivers) and channels; mean relative error is the L1 norm of the error
//! over the L1 norm of the reference. Normalising by the whole reference
//! rather than per pixel keeps dark pixels from dominating.

use crate::image::{false_colour, Image};
use glam::Vec3;
use relight_core::{luminance, Rgb};
use std::collections::BTreeMap;

/// Both error norms of `values` against `reference`.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct ErrorNorms {
    pub relative_rmse: f64,
    pub mean_relative_error: f64,
}

pub fn error_norms(values: &[Rgb], reference: &[Rgb]) -> ErrorNorms {
    assert_eq!(
        values.len(),
        reference.len(),
        "compared buffers differ in size"
    );
    let (mut error_squared, mut reference_squared, mut error_absolute, mut reference_absolute) =
        (0.0f64, 0.0f64, 0.0f64, 0.0f64);
    for (value, truth) in values.iter().zip(reference) {
        for channel in 0..3 {
            let difference = (value[channel] - truth[channel]) as f64;
            error_squared += difference * difference;
            reference_squared += (truth[channel] as f64).powi(2);
            error_absolute += difference.abs();
            reference_absolute += (truth[channel] as f64).abs();
        }
    }
    ErrorNorms {
        relative_rmse: if reference_squared > 0.0 {
            (error_squared / reference_squared).sqrt()
        } else {
            0.0
        },
        mean_relative_error: if reference_absolute > 0.0 {
            error_absolute / reference_absolute
        } else {
            0.0
        },
    }
}

/// Means of `tile` x `tile` pixel blocks (partial blocks at the right and
/// bottom edges average the pixels they hold), row-major. Comparing tile
/// means averages a Monte Carlo reference's per-pixel noise away, so the
/// error left is the technique's bias at the scale a viewer judges light.
pub fn tile_means(image: &Image, tile: u32) -> Vec<Rgb> {
    let tile = tile.max(1);
    let columns = image.width.div_ceil(tile);
    let rows = image.height.div_ceil(tile);
    let mut means = Vec::with_capacity((columns * rows) as usize);
    for row in 0..rows {
        for column in 0..columns {
            let (x0, y0) = (column * tile, row * tile);
            let (x1, y1) = ((x0 + tile).min(image.width), (y0 + tile).min(image.height));
            let mut sum = [0.0f64; 3];
            for y in y0..y1 {
                for x in x0..x1 {
                    let pixel = image.get(x, y);
                    for (channel, total) in sum.iter_mut().enumerate() {
                        *total += pixel[channel] as f64;
                    }
                }
            }
            let count = ((x1 - x0) * (y1 - y0)) as f64;
            means.push(Rgb::new(
                (sum[0] / count) as f32,
                (sum[1] / count) as f32,
                (sum[2] / count) as f32,
            ));
        }
    }
    means
}

/// Mean luminance of the (position, value) `samples` in each cube `cell`
/// metres wide, keyed by the cell's integer coordinates: the lightmap's
/// counterpart of [`tile_means`], which compares runs whose atlases differ
/// (a blotch is a cell far from its counterpart).
pub fn cell_means(
    samples: impl IntoIterator<Item = (Vec3, Rgb)>,
    cell: f32,
) -> BTreeMap<[i32; 3], f64> {
    let mut sums: BTreeMap<[i32; 3], (f64, usize)> = BTreeMap::new();
    for (position, value) in samples {
        let key = (position / cell).floor().as_ivec3().to_array();
        let entry = sums.entry(key).or_default();
        entry.0 += luminance(value) as f64;
        entry.1 += 1;
    }
    sums.into_iter()
        .map(|(key, (sum, count))| (key, sum / count as f64))
        .collect()
}

/// The lowest and highest ratio of a cell of `values` to the same cell of
/// `reference` ([`cell_means`]), over the cells both have: (inf, 0) when
/// they share none.
pub fn cell_ratio_range(
    values: &BTreeMap<[i32; 3], f64>,
    reference: &BTreeMap<[i32; 3], f64>,
) -> (f64, f64) {
    values
        .iter()
        .filter_map(|(cell, value)| Some(value / reference.get(cell)?))
        .fold((f64::INFINITY, 0.0), |(low, high), ratio| {
            (low.min(ratio), high.max(ratio))
        })
}

/// Total luminance of `values` over that of `reference`: 1 when a
/// technique brings as much light as the reference, whatever its
/// distribution (NaN when the reference is black).
pub fn light_ratio(values: &[Rgb], reference: &[Rgb]) -> f64 {
    let total = |list: &[Rgb]| list.iter().map(|v| luminance(*v) as f64).sum::<f64>();
    total(values) / total(reference)
}

/// One subset's part of an error: how many elements `keep` selects, their
/// share of the whole's squared error, and relRMSE and light ratio within
/// them.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct SubsetError {
    pub count: usize,
    pub share: f64,
    pub relative_rmse: f64,
    pub light_ratio: f64,
}

pub fn subset_error(
    values: &[Rgb],
    reference: &[Rgb],
    keep: impl Fn(usize) -> bool,
) -> SubsetError {
    let squared = |(value, truth): (&Rgb, &Rgb)| (*value - *truth).length_squared() as f64;
    let total: f64 = values.iter().zip(reference).map(squared).sum();
    let (picked, truth): (Vec<Rgb>, Vec<Rgb>) = (0..values.len())
        .filter(|&index| keep(index))
        .map(|index| (values[index], reference[index]))
        .unzip();
    let part: f64 = picked.iter().zip(&truth).map(squared).sum();
    SubsetError {
        count: picked.len(),
        share: if total > 0.0 { part / total } else { 0.0 },
        relative_rmse: error_norms(&picked, &truth).relative_rmse,
        light_ratio: light_ratio(&picked, &truth),
    }
}

/// The values whose flag in `keep` is set, in order.
pub fn kept(values: &[Rgb], keep: &[bool]) -> Vec<Rgb> {
    values
        .iter()
        .zip(keep)
        .filter(|(_, &kept)| kept)
        .map(|(value, _)| *value)
        .collect()
}

/// Relative noise of a Monte Carlo estimate: the L2 norm of its per-element
/// standard errors over the L2 norm of the estimate. A perfect technique
/// compared against this reference would still show about this relRMSE.
pub fn relative_noise(estimate: &[Rgb], standard_error: &[Rgb]) -> f64 {
    let noise: f64 = standard_error
        .iter()
        .map(|e| e.length_squared() as f64)
        .sum();
    let signal: f64 = estimate.iter().map(|m| m.length_squared() as f64).sum();
    if signal > 0.0 {
        (noise / signal).sqrt()
    } else {
        0.0
    }
}

/// False-colour image of |value - reference| luminance relative to the
/// reference's mean luminance; full scale (red) at `full_scale` (e.g. 0.5 = 50%).
pub fn error_image(values: &Image, reference: &Image, full_scale: f32) -> Image {
    let mean = reference
        .pixels
        .iter()
        .map(|p| luminance(*p) as f64)
        .sum::<f64>()
        / reference.pixels.len().max(1) as f64;
    let scale = if mean > 0.0 {
        1.0 / (mean as f32 * full_scale)
    } else {
        0.0
    };
    Image {
        width: values.width,
        height: values.height,
        pixels: values
            .pixels
            .iter()
            .zip(&reference.pixels)
            .map(|(value, truth)| {
                false_colour((luminance(*value) - luminance(*truth)).abs() * scale)
            })
            .collect(),
    }
}

/// Where a technique is too bright or too dark, at the scale of `tile`
/// pixel blocks: each tile's log2 ratio of luminance to the reference's,
/// red where brighter, blue where darker, full colour at `stops` stops
/// (1 = twice or half the light), black where the reference is black.
/// Written as PNG with exposure 1 (the colours are already display values).
pub fn tile_ratio_image(values: &Image, reference: &Image, tile: u32, stops: f32) -> Image {
    let tile = tile.max(1);
    let columns = values.width.div_ceil(tile) as usize;
    let technique = tile_means(values, tile);
    let truth = tile_means(reference, tile);
    let mut image = Image::new(values.width, values.height);
    for y in 0..values.height {
        for x in 0..values.width {
            let index = (y / tile) as usize * columns + (x / tile) as usize;
            let (value, truth) = (luminance(technique[index]), luminance(truth[index]));
            let colour = if truth <= 0.0 {
                Rgb::ZERO
            } else {
                let ratio = (value.max(truth * 1e-3) / truth).log2() / stops.max(1e-3);
                let strength = ratio.abs().min(1.0);
                let hue = if ratio > 0.0 {
                    Rgb::new(1.0, 0.1, 0.05)
                } else {
                    Rgb::new(0.05, 0.2, 1.0)
                };
                Rgb::splat(0.9).lerp(hue, strength)
            };
            image.pixels[(y * values.width + x) as usize] = colour;
        }
    }
    image
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn tile_means_average_blocks_and_edges() {
        // 10 x 9 image whose pixel value is its x: 8x8 tiles give the mean
        // x of columns 0..8 (3.5) and of the partial columns 8..10 (8.5).
        let mut image = Image::new(10, 9);
        for y in 0..9 {
            for x in 0..10 {
                image.pixels[(y * 10 + x) as usize] = Rgb::splat(x as f32);
            }
        }
        let means = tile_means(&image, 8);
        assert_eq!(means.len(), 4);
        assert_eq!(means[0], Rgb::splat(3.5));
        assert_eq!(means[1], Rgb::splat(8.5));
        assert_eq!(means[2], Rgb::splat(3.5));
        assert_eq!(means[3], Rgb::splat(8.5));
    }

    #[test]
    fn tile_means_cancel_zero_mean_noise() {
        // A checkerboard of +-1 around 2 has per-pixel relRMSE 1/2 but
        // exact 2x2 tile means.
        let mut noisy = Image::new(4, 4);
        let mut flat = Image::new(4, 4);
        for y in 0..4 {
            for x in 0..4 {
                let sign = if (x + y) % 2 == 0 { 1.0 } else { -1.0 };
                noisy.pixels[(y * 4 + x) as usize] = Rgb::splat(2.0 + sign);
                flat.pixels[(y * 4 + x) as usize] = Rgb::splat(2.0);
            }
        }
        let per_pixel = error_norms(&noisy.pixels, &flat.pixels).relative_rmse;
        assert!((per_pixel - 0.5).abs() < 1e-6);
        let tiled = error_norms(&tile_means(&noisy, 2), &tile_means(&flat, 2)).relative_rmse;
        assert_eq!(tiled, 0.0);
        assert!((light_ratio(&noisy.pixels, &flat.pixels) - 1.0).abs() < 1e-9);
    }

    #[test]
    fn norms_of_known_errors() {
        let reference = vec![Rgb::splat(1.0); 4];
        assert_eq!(error_norms(&reference, &reference), ErrorNorms::default());
        let scaled: Vec<Rgb> = reference.iter().map(|p| *p * 1.1).collect();
        let norms = error_norms(&scaled, &reference);
        assert!((norms.relative_rmse - 0.1).abs() < 1e-6);
        assert!((norms.mean_relative_error - 0.1).abs() < 1e-6);
        // One pixel off by 2 in one channel of 12 values of 1: sqrt(4/12).
        let mut one_off = reference.clone();
        one_off[0].x = 3.0;
        let norms = error_norms(&one_off, &reference);
        assert!((norms.relative_rmse - (4.0f64 / 12.0).sqrt()).abs() < 1e-6);
        assert!((norms.mean_relative_error - 2.0 / 12.0).abs() < 1e-6);
    }
}
