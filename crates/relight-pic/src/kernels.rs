//! The cache-lighting kernel of runtime projection, eight links at a time:
//! struct-of-arrays links, lanes of `[f32; 8]` that compile to AVX2 where
//! the CPU has it, and closed-form SH up to four bands.

use glam::Vec3;
use relight_core::colour::octahedral_decode;
use relight_core::sh;

pub const LANES: usize = 8;

/// One cache's links, struct of arrays (a multiple of `LANES` long).
pub struct LinkSlice<'a> {
    pub nodes: &'a [u32],
    pub factors: &'a [u16],
    pub cones: &'a [u16],
    pub directions: &'a [[u16; 2]],
}

/// Closed-form real SH for up to 4 bands (Sloan's constants, relight's
/// sign and index convention).
#[inline(always)]
pub fn sh4(direction: Vec3, out: &mut [f32; 16]) {
    let (x, y, z) = (direction.x, direction.y, direction.z);
    let (x2, y2, z2) = (x * x, y * y, z * z);
    out[0] = 0.282_094_8;
    out[1] = 0.488_602_5 * y;
    out[2] = 0.488_602_5 * z;
    out[3] = 0.488_602_5 * x;
    out[4] = 1.092_548_4 * x * y;
    out[5] = 1.092_548_4 * y * z;
    out[6] = 0.315_391_57 * (3.0 * z2 - 1.0);
    out[7] = 1.092_548_4 * x * z;
    out[8] = 0.546_274_2 * (x2 - y2);
    out[9] = 0.590_043_6 * y * (3.0 * x2 - y2);
    out[10] = 2.890_611_4 * x * y * z;
    out[11] = 0.457_045_8 * y * (5.0 * z2 - 1.0);
    out[12] = 0.373_176_34 * z * (5.0 * z2 - 3.0);
    out[13] = 0.457_045_8 * x * (5.0 * z2 - 1.0);
    out[14] = 1.445_305_7 * z * (x2 - y2);
    out[15] = 0.590_043_6 * x * (x2 - 3.0 * y2);
}

/// Cone band factors for 4 bands in x = cos(alpha) (Appendix C).
#[inline(always)]
pub fn cone4(x: f32) -> [f32; 4] {
    use std::f32::consts::PI;
    let x2 = x * x;
    [
        2.0 * PI * (1.0 - x),
        PI * (1.0 - x2),
        PI * x * (1.0 - x2),
        0.25 * PI * (-5.0 * x2 * x2 + 6.0 * x2 - 1.0),
    ]
}

/// Sums one cache's links into SH: `luma` gets `BANDS^2` coefficients of Y,
/// `co` and `cg` `CHROMA^2` of the chroma channels. `flux` is per node in
/// YCoCg. Coefficients come out times the bake's factor scale.
#[inline(always)]
pub fn light_cache<const BANDS: usize, const CHROMA: usize>(
    links: &LinkSlice,
    flux: &[Vec3],
    luma: &mut [f32],
    co: &mut [f32],
    cg: &mut [f32],
) {
    let luma_count = BANDS * BANDS;
    let chroma_count = CHROMA * CHROMA;
    let mut acc_y = [[0.0f32; LANES]; 16];
    let mut acc_co = [[0.0f32; LANES]; 16];
    let mut acc_cg = [[0.0f32; LANES]; 16];
    for block in 0..links.nodes.len() / LANES {
        let range = block * LANES..(block + 1) * LANES;
        let mut weight = [[0.0f32; LANES]; 4];
        let mut basis = [[0.0f32; LANES]; 16];
        let mut flux_y = [0.0f32; LANES];
        let mut flux_co = [0.0f32; LANES];
        let mut flux_cg = [0.0f32; LANES];
        for lane in 0..LANES {
            let link = range.start + lane;
            let factor = half::f16::from_bits(links.factors[link]).to_f32();
            let cos_alpha = 1.0 - half::f16::from_bits(links.cones[link]).to_f32();
            let cone = cone4(cos_alpha);
            for band in 0..BANDS {
                weight[band][lane] = factor * cone[band];
            }
            let mut values = [0.0f32; 16];
            sh4(octahedral_decode(links.directions[link]), &mut values);
            for index in 0..luma_count {
                basis[index][lane] = values[index];
            }
            let node_flux = flux[links.nodes[link] as usize];
            flux_y[lane] = node_flux.x;
            flux_co[lane] = node_flux.y;
            flux_cg[lane] = node_flux.z;
        }
        for band in 0..BANDS {
            for index in band * band..(band + 1) * (band + 1) {
                for lane in 0..LANES {
                    let projected = weight[band][lane] * basis[index][lane];
                    acc_y[index][lane] += projected * flux_y[lane];
                    if band < CHROMA {
                        acc_co[index][lane] += projected * flux_co[lane];
                        acc_cg[index][lane] += projected * flux_cg[lane];
                    }
                }
            }
        }
    }
    for index in 0..luma_count {
        luma[index] = acc_y[index].iter().sum();
    }
    for index in 0..chroma_count {
        co[index] = acc_co[index].iter().sum();
        cg[index] = acc_cg[index].iter().sum();
    }
}

/// The same sum for any band count up to 8, one link at a time (the slow
/// path for more than four bands).
pub fn light_cache_general(
    links: &LinkSlice,
    flux: &[Vec3],
    bands: usize,
    chroma: usize,
    luma: &mut [f32],
    co: &mut [f32],
    cg: &mut [f32],
) {
    luma.fill(0.0);
    co.fill(0.0);
    cg.fill(0.0);
    let mut basis = [0.0f32; 64];
    for link in 0..links.nodes.len() {
        let factor = half::f16::from_bits(links.factors[link]).to_f32();
        if factor == 0.0 {
            continue;
        }
        let cone = sh::cone_band_factors(1.0 - half::f16::from_bits(links.cones[link]).to_f32());
        sh::evaluate(octahedral_decode(links.directions[link]), bands, &mut basis);
        let node_flux = flux[links.nodes[link] as usize];
        for band in 0..bands {
            let weight = factor * cone[band];
            for index in band * band..(band + 1) * (band + 1) {
                let projected = weight * basis[index];
                luma[index] += projected * node_flux.x;
                if band < chroma {
                    co[index] += projected * node_flux.y;
                    cg[index] += projected * node_flux.z;
                }
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use relight_core::sampling::{uniform_sphere, Pcg32};

    #[test]
    fn closed_form_sh_matches_the_recurrence() {
        let mut rng = Pcg32::new(9, 0);
        for _ in 0..200 {
            let direction = uniform_sphere(rng.next_vec2());
            let mut closed = [0.0f32; 16];
            let mut general = [0.0f32; 16];
            sh4(direction, &mut closed);
            sh::evaluate(direction, 4, &mut general);
            for index in 0..16 {
                // Sloan's constants are printed to 7 digits.
                assert!((closed[index] - general[index]).abs() < 2e-6, "{index}");
            }
        }
    }

    #[test]
    fn closed_form_cone_matches_the_recurrence() {
        for step in 0..=40 {
            let x = -1.0 + step as f32 / 20.0;
            let closed = cone4(x);
            let general = sh::cone_band_factors(x);
            for band in 0..4 {
                assert!(
                    (closed[band] - general[band]).abs() < 1e-5,
                    "x {x} band {band}"
                );
            }
        }
    }
}
