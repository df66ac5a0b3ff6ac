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

/// f16 bits to f32 for normal numbers and zero-ish values, branch free so
/// eight lanes vectorise (subnormal f16 values, below 6e-5, come out
/// within 2^-14 of their value; the bake keeps factors normal).
#[inline(always)]
fn half_to_f32(bits: u16) -> f32 {
    let bits = bits as u32;
    let sign = (bits & 0x8000) << 16;
    let magnitude = ((bits & 0x7fff) << 13) + ((127 - 15) << 23);
    let magnitude = if bits & 0x7fff == 0 { 0 } else { magnitude };
    f32::from_bits(sign | magnitude)
}

/// Sums one cache's links into SH: `luma` gets `BANDS^2` coefficients of Y,
/// `co` and `cg` `CHROMA^2` of the chroma channels. `flux` is per node in
/// YCoCg. Coefficients come out times the bake's factor scale. Every step
/// is a loop over eight lanes of plain arithmetic so it vectorises.
#[inline(always)]
pub fn light_cache<const BANDS: usize, const CHROMA: usize>(
    links: &LinkSlice,
    flux: &[Vec3],
    luma: &mut [f32],
    co: &mut [f32],
    cg: &mut [f32],
) {
    use std::f32::consts::PI;
    let luma_count = BANDS * BANDS;
    let chroma_count = CHROMA * CHROMA;
    let mut acc_y = [[0.0f32; LANES]; 16];
    let mut acc_co = [[0.0f32; LANES]; 16];
    let mut acc_cg = [[0.0f32; LANES]; 16];
    for block in 0..links.nodes.len() / LANES {
        let start = block * LANES;
        let factors: &[u16; LANES] = links.factors[start..start + LANES].try_into().unwrap();
        let cones: &[u16; LANES] = links.cones[start..start + LANES].try_into().unwrap();
        let directions: &[[u16; 2]; LANES] =
            links.directions[start..start + LANES].try_into().unwrap();
        let nodes: &[u32; LANES] = links.nodes[start..start + LANES].try_into().unwrap();
        let mut x = [0.0f32; LANES];
        let mut y = [0.0f32; LANES];
        let mut z = [0.0f32; LANES];
        let mut weight = [[0.0f32; LANES]; 4];
        for lane in 0..LANES {
            // Octahedral decode.
            let u = directions[lane][0] as f32 * (2.0 / 65535.0) - 1.0;
            let v = directions[lane][1] as f32 * (2.0 / 65535.0) - 1.0;
            let w = 1.0 - u.abs() - v.abs();
            let shift = (-w).max(0.0);
            let dx = u - shift.copysign(u);
            let dy = v - shift.copysign(v);
            let inverse = 1.0 / (dx * dx + dy * dy + w * w).sqrt();
            x[lane] = dx * inverse;
            y[lane] = dy * inverse;
            z[lane] = w * inverse;
            // Cone factors (Appendix C) times the link's factor.
            let factor = half_to_f32(factors[lane]);
            let c = 1.0 - half_to_f32(cones[lane]);
            let c2 = c * c;
            weight[0][lane] = factor * (2.0 * PI) * (1.0 - c);
            weight[1][lane] = factor * PI * (1.0 - c2);
            weight[2][lane] = factor * PI * c * (1.0 - c2);
            weight[3][lane] = factor * (0.25 * PI) * (6.0 * c2 - 5.0 * c2 * c2 - 1.0);
        }
        let mut basis = [[0.0f32; LANES]; 16];
        for lane in 0..LANES {
            let (x, y, z) = (x[lane], y[lane], z[lane]);
            let (x2, y2, z2) = (x * x, y * y, z * z);
            basis[0][lane] = 0.282_094_8;
            basis[1][lane] = 0.488_602_5 * y;
            basis[2][lane] = 0.488_602_5 * z;
            basis[3][lane] = 0.488_602_5 * x;
            if BANDS > 2 {
                basis[4][lane] = 1.092_548_4 * x * y;
                basis[5][lane] = 1.092_548_4 * y * z;
                basis[6][lane] = 0.315_391_57 * (3.0 * z2 - 1.0);
                basis[7][lane] = 1.092_548_4 * x * z;
                basis[8][lane] = 0.546_274_2 * (x2 - y2);
            }
            if BANDS > 3 {
                basis[9][lane] = 0.590_043_6 * y * (3.0 * x2 - y2);
                basis[10][lane] = 2.890_611_4 * x * y * z;
                basis[11][lane] = 0.457_045_8 * y * (5.0 * z2 - 1.0);
                basis[12][lane] = 0.373_176_34 * z * (5.0 * z2 - 3.0);
                basis[13][lane] = 0.457_045_8 * x * (5.0 * z2 - 1.0);
                basis[14][lane] = 1.445_305_7 * z * (x2 - y2);
                basis[15][lane] = 0.590_043_6 * x * (x2 - 3.0 * y2);
            }
        }
        let mut flux_y = [0.0f32; LANES];
        let mut flux_co = [0.0f32; LANES];
        let mut flux_cg = [0.0f32; LANES];
        for lane in 0..LANES {
            let node_flux = flux[nodes[lane] as usize];
            flux_y[lane] = node_flux.x;
            flux_co[lane] = node_flux.y;
            flux_cg[lane] = node_flux.z;
        }
        for band in 0..BANDS {
            let mut weighted_y = [0.0f32; LANES];
            let mut weighted_co = [0.0f32; LANES];
            let mut weighted_cg = [0.0f32; LANES];
            for lane in 0..LANES {
                weighted_y[lane] = weight[band][lane] * flux_y[lane];
                weighted_co[lane] = weight[band][lane] * flux_co[lane];
                weighted_cg[lane] = weight[band][lane] * flux_cg[lane];
            }
            for index in band * band..(band + 1) * (band + 1) {
                for lane in 0..LANES {
                    acc_y[index][lane] += basis[index][lane] * weighted_y[lane];
                }
                if band < CHROMA {
                    for lane in 0..LANES {
                        acc_co[index][lane] += basis[index][lane] * weighted_co[lane];
                        acc_cg[index][lane] += basis[index][lane] * weighted_cg[lane];
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

    /// The lane kernel (closed-form SH and cone factors, branch-free f16)
    /// against the general one-link-at-a-time path on random links.
    #[test]
    fn lane_kernel_matches_the_general_path() {
        let mut rng = Pcg32::new(9, 0);
        let count = 64;
        let nodes: Vec<u32> = (0..count).map(|_| rng.next_u32() % 16).collect();
        let factors: Vec<u16> = (0..count)
            .map(|_| half::f16::from_f32(0.1 + 10.0 * rng.next_f32()).to_bits())
            .collect();
        let cones: Vec<u16> = (0..count)
            .map(|_| half::f16::from_f32(2.0 * rng.next_f32()).to_bits())
            .collect();
        let directions: Vec<[u16; 2]> = (0..count)
            .map(|_| relight_core::colour::octahedral_encode(uniform_sphere(rng.next_vec2())))
            .collect();
        let flux: Vec<Vec3> = (0..16)
            .map(|_| Vec3::new(rng.next_f32(), rng.next_f32() - 0.5, rng.next_f32() - 0.5))
            .collect();
        let links = LinkSlice {
            nodes: &nodes,
            factors: &factors,
            cones: &cones,
            directions: &directions,
        };
        fn compare<const B: usize, const C: usize>(links: &LinkSlice, flux: &[Vec3]) {
            let (mut luma, mut co, mut cg) = ([0.0f32; 16], [0.0f32; 16], [0.0f32; 16]);
            light_cache::<B, C>(links, flux, &mut luma, &mut co, &mut cg);
            let (mut luma_ref, mut co_ref, mut cg_ref) = ([0.0f32; 16], [0.0f32; 16], [0.0f32; 16]);
            light_cache_general(links, flux, B, C, &mut luma_ref, &mut co_ref, &mut cg_ref);
            let scale = luma_ref.iter().map(|v| v.abs()).fold(0.0f32, f32::max);
            for (got, want) in luma
                .iter()
                .zip(&luma_ref)
                .chain(co.iter().zip(&co_ref))
                .chain(cg.iter().zip(&cg_ref))
            {
                // Sloan's 7-digit constants and f32 sums of 64 terms.
                assert!(
                    (got - want).abs() <= 1e-5 * scale,
                    "{B}:{C} {got} vs {want}"
                );
            }
        }
        compare::<2, 2>(&links, &flux);
        compare::<3, 3>(&links, &flux);
        compare::<3, 2>(&links, &flux);
        compare::<4, 4>(&links, &flux);
        compare::<4, 2>(&links, &flux);
    }

    #[test]
    fn branch_free_half_conversion_matches_half() {
        for bits in (0u16..0x7c00).step_by(7).chain([0x3c00, 0x0400, 0x7bff]) {
            for sign in [0u16, 0x8000] {
                let exact = half::f16::from_bits(bits | sign).to_f32();
                let fast = half_to_f32(bits | sign);
                // Normal numbers convert exactly; subnormals (below 2^-14)
                // within 2^-14.
                let tolerance = if bits < 0x0400 { 2f32.powi(-14) } else { 0.0 };
                assert!(
                    (exact - fast).abs() <= tolerance,
                    "{bits:#x}: {exact} vs {fast}"
                );
            }
        }
    }
}
