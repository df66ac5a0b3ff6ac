//! Error metrics between a technique's result and the reference.
//!
//! relight uses one definition everywhere: relative RMSE is the L2 norm of
//! the error over the L2 norm of the reference, over all pixels (or
//! receivers) and channels; mean relative error is the L1 norm of the error
//! over the L1 norm of the reference. Normalising by the whole reference
//! rather than per pixel keeps dark pixels from dominating.

use crate::image::{false_colour, Image};
use relight_core::{luminance, Rgb};

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

#[cfg(test)]
mod tests {
    use super::*;

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
