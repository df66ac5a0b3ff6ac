//! Real spherical harmonics, orthonormal over the sphere, for up to 8 bands.
//!
//! Index convention: coefficient `l * (l + 1) + m` for band `l` and order
//! `-l <= m <= l` (the layout of Sloan's "Stupid SH Tricks"). Evaluation uses
//! the associated Legendre recurrence in Cartesian form, so there is no
//! trigonometry per call and the cost is a few FMAs per coefficient.

use glam::Vec3;
use std::f64::consts::PI;

/// Largest number of bands relight stores (l = 0..=7, 64 coefficients).
pub const MAX_BANDS: usize = 8;

/// Number of coefficients for `bands` bands.
#[inline]
pub const fn coefficient_count(bands: usize) -> usize {
    bands * bands
}

#[inline]
pub const fn index(band: usize, order: isize) -> usize {
    (band * (band + 1)) as isize as usize + order as usize
}

/// Normalisation constant K_l^m = sqrt((2l+1)/(4 pi) (l-|m|)!/(l+|m|)!).
fn normalisation(band: usize, order_abs: usize) -> f64 {
    let mut ratio = 1.0f64;
    for k in (band - order_abs + 1)..=(band + order_abs) {
        ratio /= k as f64;
    }
    ((2 * band + 1) as f64 / (4.0 * PI) * ratio).sqrt()
}

/// Precomputed constants so evaluation does no divisions or factorials.
struct Tables {
    normalisation: [[f32; MAX_BANDS]; MAX_BANDS],
}

fn tables() -> &'static Tables {
    static TABLES: std::sync::OnceLock<Tables> = std::sync::OnceLock::new();
    TABLES.get_or_init(|| {
        let mut normalisation_table = [[0.0f32; MAX_BANDS]; MAX_BANDS];
        for (band, row) in normalisation_table.iter_mut().enumerate() {
            for (order, value) in row.iter_mut().enumerate().take(band + 1) {
                let factor = if order == 0 { 1.0 } else { 2.0f64.sqrt() };
                *value = (factor * normalisation(band, order)) as f32;
            }
        }
        Tables {
            normalisation: normalisation_table,
        }
    })
}

/// Evaluates all basis functions of `bands` bands at the unit `direction`
/// into `out[..bands*bands]`.
pub fn evaluate(direction: Vec3, bands: usize, out: &mut [f32]) {
    assert!(
        (1..=MAX_BANDS).contains(&bands),
        "SH bands must be 1..=8, got {bands}"
    );
    assert!(out.len() >= coefficient_count(bands));
    if bands <= 4 {
        // Irradiance and the presets use at most four bands, evaluated per
        // pixel and per sample: the recurrence unrolled, with no table.
        let values = evaluate_four_bands(direction);
        out[..bands * bands].copy_from_slice(&values[..bands * bands]);
        return;
    }
    evaluate_by_recurrence(direction, bands, out);
}

/// `factors[l] * Y_lm(direction)` for `bands` bands into
/// `out[..bands*bands]`: the basis convolved with a zonal kernel given by
/// its per-band factors (the cosine lobe's for irradiance, a Phong lobe's
/// for glossy reflection), ready to dot with radiance SH.
pub fn evaluate_filtered(
    direction: Vec3,
    bands: usize,
    factors: &[f32; MAX_BANDS],
    out: &mut [f32],
) {
    evaluate(direction, bands, out);
    for (band, factor) in factors.iter().enumerate().take(bands) {
        for value in &mut out[band * band..(band + 1) * (band + 1)] {
            *value *= factor;
        }
    }
}

/// [`evaluate_filtered`] for all of the first four bands at once, in
/// closed form and inlined: per-pixel lookups with at most four bands use
/// it without the call, the length checks and the copy of the general form
/// (a lookup that needs fewer bands ignores the rest).
#[inline(always)]
pub fn evaluate_four_bands_filtered(direction: Vec3, factors: &[f32; MAX_BANDS]) -> [f32; 16] {
    const BAND_OF_COEFFICIENT: [usize; 16] = [0, 1, 1, 1, 2, 2, 2, 2, 2, 3, 3, 3, 3, 3, 3, 3];
    let mut values = evaluate_four_bands(direction);
    for (value, band) in values.iter_mut().zip(BAND_OF_COEFFICIENT) {
        *value *= factors[band];
    }
    values
}

/// The first four bands (16 coefficients) in closed form: the
/// recurrence's Legendre polynomials in z times Re and Im of (x + i y)^m,
/// with the normalisation folded into each constant (same convention, no
/// Condon-Shortley phase). Inlined so that lane loops vectorise it and drop
/// the bands they do not use.
#[inline(always)]
pub fn evaluate_four_bands(direction: Vec3) -> [f32; 16] {
    let (x, y, z) = (direction.x, direction.y, direction.z);
    let (z2, xx_minus_yy, two_xy) = (z * z, x * x - y * y, 2.0 * x * y);
    // Re and Im of (x + i y)^3.
    let cos_3 = x * xx_minus_yy - y * two_xy;
    let sin_3 = x * two_xy + y * xx_minus_yy;
    let band_3_order_1 = 2.285_229 * z2 - 0.457_045_8;
    [
        0.282_094_8,
        0.488_602_5 * y,
        0.488_602_5 * z,
        0.488_602_5 * x,
        0.546_274_2 * two_xy,
        1.092_548_4 * z * y,
        0.946_174_7 * z2 - 0.315_391_57,
        1.092_548_4 * z * x,
        0.546_274_2 * xx_minus_yy,
        0.590_043_6 * sin_3,
        1.445_305_7 * z * two_xy,
        band_3_order_1 * y,
        z * (1.865_881_7 * z2 - 1.119_529),
        band_3_order_1 * x,
        1.445_305_7 * z * xx_minus_yy,
        0.590_043_6 * cos_3,
    ]
}

/// Any band count, by the associated Legendre recurrence.
fn evaluate_by_recurrence(direction: Vec3, bands: usize, out: &mut [f32]) {
    let tables = tables();
    let (x, y, z) = (direction.x, direction.y, direction.z);
    // Associated Legendre P_l^m(z) without the (1-z^2)^(m/2) factor; that factor
    // is folded into cos(m phi) sin^m(theta) = Re((x + i y)^m), computed below.
    let mut legendre = [[0.0f32; MAX_BANDS]; MAX_BANDS];
    for m in 0..bands {
        // P_m^m = (2m-1)!!, without the Condon-Shortley phase, so that the
        // real basis matches the common graphics convention (Y_1^-1 = +c y).
        let mut pmm = 1.0f32;
        for k in 0..m {
            pmm *= (2 * k + 1) as f32;
        }
        legendre[m][m] = pmm;
        if m + 1 < bands {
            legendre[m + 1][m] = z * (2 * m + 1) as f32 * pmm;
        }
        for l in (m + 2)..bands {
            legendre[l][m] = ((2 * l - 1) as f32 * z * legendre[l - 1][m]
                - (l + m - 1) as f32 * legendre[l - 2][m])
                / (l - m) as f32;
        }
    }
    let mut cos_m = [0.0f32; MAX_BANDS];
    let mut sin_m = [0.0f32; MAX_BANDS];
    cos_m[0] = 1.0;
    for m in 1..bands {
        cos_m[m] = x * cos_m[m - 1] - y * sin_m[m - 1];
        sin_m[m] = x * sin_m[m - 1] + y * cos_m[m - 1];
    }
    for (l, (legendre_row, normalisation_row)) in legendre
        .iter()
        .zip(&tables.normalisation)
        .take(bands)
        .enumerate()
    {
        let centre = l * (l + 1);
        out[centre] = normalisation_row[0] * legendre_row[0];
        for m in 1..=l {
            let scaled = normalisation_row[m] * legendre_row[m];
            out[centre + m] = scaled * cos_m[m];
            out[centre - m] = scaled * sin_m[m];
        }
    }
}

/// Zonal coefficient A_l of the clamped cosine lobe max(cos theta, 0), scaled
/// so that convolving radiance SH with it yields irradiance:
/// E_lm = A_l * L_lm with A_l = sqrt(4 pi / (2l+1)) * (cosine lobe zonal coefficient).
/// Closed form of Ramamoorthi and Hanrahan 2001: A_0 = pi, A_1 = 2pi/3, odd l>1 vanish.
pub fn cosine_lobe_factor(band: usize) -> f32 {
    match band {
        0 => std::f32::consts::PI,
        1 => 2.0 * std::f32::consts::PI / 3.0,
        l if !l.is_multiple_of(2) => 0.0,
        l => {
            let l = l as f64;
            // 2 pi (-1)^(l/2 - 1) / ((l+2)(l-1)) * l! / (2^l ((l/2)!)^2)
            let sign = if (l as usize / 2 - 1).is_multiple_of(2) {
                1.0
            } else {
                -1.0
            };
            let factorial = |n: usize| (1..=n).fold(1.0f64, |acc, k| acc * k as f64);
            let value = 2.0 * PI * sign / ((l + 2.0) * (l - 1.0)) * factorial(l as usize)
                / (2f64.powi(l as i32) * factorial(l as usize / 2).powi(2));
            value as f32
        }
    }
}

/// Zonal factors, per band, of the normalised Phong lobe
/// (k + 1) / (2 pi) cos^k around the reflection direction: sqrt(4 pi /
/// (2l + 1)) times its zonal coefficient, which is (k + 1) I_l with
/// I_l = integral over [0, 1] of mu^k P_l(mu), from I_0 = 1 / (k + 1),
/// I_1 = 1 / (k + 2) and I_l = (k - l + 2) / (k + l + 1) I_(l-2).
pub fn phong_band_factors(exponent: f32) -> [f32; MAX_BANDS] {
    let k = exponent as f64;
    let mut integrals = [0.0f64; MAX_BANDS];
    integrals[0] = 1.0 / (k + 1.0);
    integrals[1] = 1.0 / (k + 2.0);
    for band in 2..MAX_BANDS {
        let l = band as f64;
        integrals[band] = (k - l + 2.0) / (k + l + 1.0) * integrals[band - 2];
    }
    integrals.map(|integral| ((k + 1.0) * integral) as f32)
}

/// Band factors of a cone of half-angle alpha (Appendix C of the PIC
/// paper, by Funk-Hecke): the SH coefficients of the cone's indicator
/// function around the unit `d` are `factors[l] * Y_lm(d)`, where
/// `factors[l] = 2 pi * integral over [cos alpha, 1] of P_l(x) dx`, that is
/// 2 pi (1 - cos alpha) for l = 0 and 2 pi (P_(l-1) - P_(l+1)) / (2l + 1)
/// at cos alpha otherwise. Band 0 is the cone's solid angle times Y_00.
pub fn cone_band_factors(cos_alpha: f32) -> [f32; MAX_BANDS] {
    let x = cos_alpha.clamp(-1.0, 1.0);
    // Legendre polynomials P_0..P_MAX_BANDS at x.
    let mut legendre = [0.0f32; MAX_BANDS + 1];
    legendre[0] = 1.0;
    legendre[1] = x;
    for l in 1..MAX_BANDS {
        legendre[l + 1] =
            ((2 * l + 1) as f32 * x * legendre[l] - l as f32 * legendre[l - 1]) / (l + 1) as f32;
    }
    let tau = 2.0 * std::f32::consts::PI;
    std::array::from_fn(|band| {
        if band == 0 {
            tau * (1.0 - x)
        } else {
            tau * (legendre[band - 1] - legendre[band + 1]) / (2 * band + 1) as f32
        }
    })
}

/// Projects a function on the sphere into SH by deterministic quadrature over
/// a latitude-longitude grid (reference for tests and bakes that need exact
/// projections of analytic functions).
pub fn project_by_quadrature(
    bands: usize,
    resolution: usize,
    function: impl Fn(Vec3) -> f32,
) -> Vec<f32> {
    let mut coefficients = vec![0.0f64; coefficient_count(bands)];
    let mut basis = vec![0.0f32; coefficient_count(bands)];
    let theta_steps = resolution;
    let phi_steps = 2 * resolution;
    let d_theta = PI / theta_steps as f64;
    let d_phi = 2.0 * PI / phi_steps as f64;
    for i in 0..theta_steps {
        let theta = (i as f64 + 0.5) * d_theta;
        let weight = theta.sin() * d_theta * d_phi;
        for j in 0..phi_steps {
            let phi = (j as f64 + 0.5) * d_phi;
            let direction = Vec3::new(
                (theta.sin() * phi.cos()) as f32,
                (theta.sin() * phi.sin()) as f32,
                theta.cos() as f32,
            );
            let value = function(direction) as f64;
            evaluate(direction, bands, &mut basis);
            for (coefficient, b) in coefficients.iter_mut().zip(&basis) {
                *coefficient += value * *b as f64 * weight;
            }
        }
    }
    coefficients.into_iter().map(|c| c as f32).collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn closed_form_bands_match_the_recurrence() {
        let mut rng = crate::sampling::Pcg32::new(17, 4);
        let mut directions = vec![Vec3::X, Vec3::Y, Vec3::Z, -Vec3::Z];
        directions.extend((0..500).map(|_| crate::sampling::uniform_sphere(rng.next_vec2())));
        for direction in directions {
            let mut closed = [0.0f32; 16];
            let mut recurrence = [0.0f32; 16];
            for bands in 1..=4 {
                closed.fill(f32::NAN);
                evaluate(direction, bands, &mut closed);
                evaluate_by_recurrence(direction, bands, &mut recurrence);
                for index in 0..bands * bands {
                    // The basis is below 0.75 in magnitude; f32 constants
                    // and a different operation order differ by a few ulps.
                    assert!(
                        (closed[index] - recurrence[index]).abs() < 2e-6,
                        "{direction} bands {bands} index {index}: {} against {}",
                        closed[index],
                        recurrence[index]
                    );
                }
                assert!(closed[bands * bands..].iter().all(|value| value.is_nan()));
            }
        }
    }

    /// The inlined four-band form gives the general form's bits: same
    /// closed-form basis, same single multiply by the band's factor.
    #[test]
    fn four_band_filtered_basis_is_the_general_one() {
        let factors = [0.9, -0.7, 0.45, 0.3, 0.2, 0.1, 0.05, 0.01];
        let mut rng = crate::sampling::Pcg32::new(3, 8);
        for _ in 0..200 {
            let direction = crate::sampling::uniform_sphere(rng.next_vec2());
            let mut general = [0.0f32; 16];
            evaluate_filtered(direction, 4, &factors, &mut general);
            assert_eq!(evaluate_four_bands_filtered(direction, &factors), general);
        }
    }

    #[test]
    fn basis_is_orthonormal_by_quadrature() {
        let bands = MAX_BANDS;
        let count = coefficient_count(bands);
        let mut gram = vec![0.0f64; count * count];
        let resolution = 256;
        let d_theta = PI / resolution as f64;
        let d_phi = PI / resolution as f64;
        let mut basis = vec![0.0f32; count];
        for i in 0..resolution {
            let theta = (i as f64 + 0.5) * d_theta;
            for j in 0..2 * resolution {
                let phi = (j as f64 + 0.5) * d_phi;
                let direction = Vec3::new(
                    (theta.sin() * phi.cos()) as f32,
                    (theta.sin() * phi.sin()) as f32,
                    theta.cos() as f32,
                );
                evaluate(direction, bands, &mut basis);
                let weight = theta.sin() * d_theta * d_phi;
                for a in 0..count {
                    for b in 0..count {
                        gram[a * count + b] += basis[a] as f64 * basis[b] as f64 * weight;
                    }
                }
            }
        }
        for a in 0..count {
            for b in 0..count {
                let expected = if a == b { 1.0 } else { 0.0 };
                // Midpoint quadrature on a 256x512 grid integrates degree-14
                // polynomials to ~1e-4; f32 basis values add ~1e-6.
                assert!(
                    (gram[a * count + b] - expected).abs() < 2e-3,
                    "<Y{a}, Y{b}> = {}",
                    gram[a * count + b]
                );
            }
        }
    }

    #[test]
    fn low_bands_match_closed_forms() {
        let direction = Vec3::new(0.48, -0.6, 0.64);
        let mut out = [0.0f32; 9];
        evaluate(direction, 3, &mut out);
        let (x, y, z) = (direction.x, direction.y, direction.z);
        let expected = [
            0.282_095,
            0.488_603 * y,
            0.488_603 * z,
            0.488_603 * x,
            1.092_548 * x * y,
            1.092_548 * y * z,
            0.315_392 * (3.0 * z * z - 1.0),
            1.092_548 * x * z,
            0.546_274 * (x * x - y * y),
        ];
        for (index, (got, want)) in out.iter().zip(expected).enumerate() {
            // Sloan's constants are printed to 6 digits.
            assert!(
                (got - want).abs() < 1e-5,
                "coefficient {index}: {got} vs {want}"
            );
        }
    }

    #[test]
    fn cosine_lobe_factors_match_numerical_convolution() {
        // Projecting max(z, 0) gives zonal coefficients c_l; the convolution
        // factor is A_l = sqrt(4 pi / (2l+1)) c_l (Funk-Hecke).
        let bands = MAX_BANDS;
        let coefficients = project_by_quadrature(bands, 512, |direction| direction.z.max(0.0));
        for band in 0..bands {
            let zonal = coefficients[index(band, 0)] as f64;
            let numerical = (4.0 * PI / (2 * band + 1) as f64).sqrt() * zonal;
            let analytic = cosine_lobe_factor(band) as f64;
            // The kink of max(z,0) limits midpoint quadrature to ~1e-4 here.
            assert!(
                (numerical - analytic).abs() < 5e-4,
                "band {band}: numerical {numerical} analytic {analytic}"
            );
        }
    }

    /// The recurrence against midpoint quadrature of (k + 1) times the
    /// integral of mu^k P_l(mu) over [0, 1]; band 0 is 1 (the lobe is
    /// normalised).
    #[test]
    fn phong_band_factors_match_quadrature() {
        for exponent in [1.5f32, 2.0, 7.3, 40.0, 200.0] {
            let factors = phong_band_factors(exponent);
            assert!((factors[0] - 1.0).abs() < 1e-6);
            for (band, factor) in factors.iter().enumerate() {
                const STEPS: usize = 20_000;
                let mut sum = 0.0f64;
                for step in 0..STEPS {
                    let mu = (step as f64 + 0.5) / STEPS as f64;
                    let (mut previous, mut current) = (1.0f64, mu);
                    let legendre = if band == 0 {
                        1.0
                    } else {
                        for l in 1..band {
                            let next = ((2 * l + 1) as f64 * mu * current - l as f64 * previous)
                                / (l + 1) as f64;
                            previous = current;
                            current = next;
                        }
                        current
                    };
                    sum += mu.powf(exponent as f64) * legendre;
                }
                let expected = (exponent as f64 + 1.0) * sum / STEPS as f64;
                // Midpoint error of a smooth integrand at 20k steps.
                assert!(
                    (*factor as f64 - expected).abs() < 1e-4,
                    "k {exponent} band {band}"
                );
            }
        }
    }

    /// A cone's band factors against quadrature of its indicator function
    /// projected into SH around an arbitrary axis, for 1 to 8 bands.
    #[test]
    fn cone_band_factors_match_projected_indicator() {
        let axis = Vec3::new(0.3, -0.5, 0.81).normalize();
        for cos_alpha in [0.99f32, 0.9, 0.5, 0.0, -0.4] {
            let factors = cone_band_factors(cos_alpha);
            let projected = project_by_quadrature(MAX_BANDS, 1024, |direction| {
                if direction.dot(axis) >= cos_alpha {
                    1.0
                } else {
                    0.0
                }
            });
            let mut basis = [0.0f32; 64];
            evaluate(axis, MAX_BANDS, &mut basis);
            #[allow(clippy::needless_range_loop)]
            for band in 0..MAX_BANDS {
                for order in -(band as isize)..=band as isize {
                    let i = index(band, order);
                    let expected = projected[i];
                    let got = factors[band] * basis[i];
                    // A 1024 x 2048 grid resolves the cone's edge to about
                    // 3e-3 sr of its area.
                    assert!(
                        (got - expected).abs() < 6e-3,
                        "cos {cos_alpha} band {band} order {order}: {got} vs {expected}"
                    );
                }
            }
        }
    }
}
