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

/// Blocks of `LANES` links prepared at a time: their weighted bases and
/// fluxes (19 KiB) stay in L1 while the accumulation reads them.
const CHUNK_BLOCKS: usize = 32;

/// The SH band of each of the first 16 coefficients.
const BAND_OF_COEFFICIENT: [usize; 16] = [0, 1, 1, 1, 2, 2, 2, 2, 2, 3, 3, 3, 3, 3, 3, 3];

/// One block's per-lane inputs to the accumulation: the SH basis already
/// times the link's band weight, and the linked node's YCoCg flux.
#[derive(Clone, Copy)]
struct PreparedBlock {
    weighted_basis: [[f32; LANES]; 16],
    flux: [[f32; LANES]; 3],
}

/// A thread's working space for `light_cache`, reused across caches so
/// that no cache clears 19 KiB it is about to overwrite.
pub struct LinkScratch {
    blocks: Box<[PreparedBlock; CHUNK_BLOCKS]>,
}

impl Default for LinkScratch {
    fn default() -> Self {
        LinkScratch {
            blocks: Box::new(
                [PreparedBlock {
                    weighted_basis: [[0.0; LANES]; 16],
                    flux: [[0.0; LANES]; 3],
                }; CHUNK_BLOCKS],
            ),
        }
    }
}

/// Sums one cache's links into SH: `luma` gets `BANDS^2` coefficients of Y,
/// `co` and `cg` `CHROMA^2` of the chroma channels. `flux` is per node in
/// YCoCg. Coefficients come out times the bake's factor scale.
///
/// Two passes per chunk of links, each a loop over eight lanes of plain
/// arithmetic so it vectorises: the first decodes links into weighted SH
/// bases, the second sums basis times flux into at most eight accumulators
/// at a time. Accumulating all 48 coefficients in one pass needs more
/// vector registers than x86 has, and every spilled accumulator costs a
/// load and a store per link block.
///
/// # Safety
/// Every node in `links.nodes` must index `flux`: the gathers skip their
/// bounds checks. `Pic::new` checks this once for the whole bake.
#[inline(always)]
pub unsafe fn light_cache<const BANDS: usize, const CHROMA: usize>(
    links: &LinkSlice,
    flux: &[Vec3],
    scratch: &mut LinkScratch,
    luma: &mut [f32],
    co: &mut [f32],
    cg: &mut [f32],
) {
    let luma_count = BANDS * BANDS;
    let chroma_count = CHROMA * CHROMA;
    debug_assert!(links.nodes.iter().all(|&node| (node as usize) < flux.len()));
    let mut acc_y = [[0.0f32; LANES]; 16];
    let mut acc_co = [[0.0f32; LANES]; 16];
    let mut acc_cg = [[0.0f32; LANES]; 16];
    let block_count = links.nodes.len() / LANES;
    for chunk_start in (0..block_count).step_by(CHUNK_BLOCKS) {
        let chunk = &mut scratch.blocks[..CHUNK_BLOCKS.min(block_count - chunk_start)];
        for (offset, block) in chunk.iter_mut().enumerate() {
            let start = (chunk_start + offset) * LANES;
            prefetch_flux(links, flux, start + PREFETCH_LINKS_AHEAD);
            prepare_block::<BANDS>(links, flux, start, block);
        }
        accumulate_channel(chunk, 0, luma_count, &mut acc_y);
        accumulate_channel(chunk, 1, chroma_count, &mut acc_co);
        accumulate_channel(chunk, 2, chroma_count, &mut acc_cg);
    }
    for index in 0..luma_count {
        luma[index] = acc_y[index].iter().sum();
    }
    for index in 0..chroma_count {
        co[index] = acc_co[index].iter().sum();
        cg[index] = acc_cg[index].iter().sum();
    }
}

/// How far ahead the flux of linked nodes is fetched. The flux array of a
/// large hierarchy (3 MB at 256k nodes) outgrows L2, and each link reads a
/// scattered node, so without this the lanes wait on memory.
const PREFETCH_LINKS_AHEAD: usize = 4 * LANES;

/// Asks for the flux of the `LANES` links from `start` (if there are any)
/// to be brought into L1.
#[inline(always)]
fn prefetch_flux(links: &LinkSlice, flux: &[Vec3], start: usize) {
    #[cfg(target_arch = "x86_64")]
    if let Some(nodes) = links.nodes.get(start..start + LANES) {
        for &node in nodes {
            // A prefetch never faults, and the caller vouches for the node.
            let address = flux.as_ptr().wrapping_add(node as usize) as *const i8;
            // SAFETY: SSE is part of x86_64; prefetching reads nothing.
            unsafe { std::arch::x86_64::_mm_prefetch(address, std::arch::x86_64::_MM_HINT_T0) };
        }
    }
    #[cfg(not(target_arch = "x86_64"))]
    let _ = (links, flux, start);
}

/// Decodes the `LANES` links from `start`: direction, cone factors of
/// Appendix C times the link factor, closed-form SH and the node's flux.
#[inline(always)]
fn prepare_block<const BANDS: usize>(
    links: &LinkSlice,
    flux: &[Vec3],
    start: usize,
    block: &mut PreparedBlock,
) {
    use std::f32::consts::PI;
    let factors: &[u16; LANES] = links.factors[start..start + LANES].try_into().unwrap();
    let cones: &[u16; LANES] = links.cones[start..start + LANES].try_into().unwrap();
    let directions: &[[u16; 2]; LANES] = links.directions[start..start + LANES].try_into().unwrap();
    let nodes: &[u32; LANES] = links.nodes[start..start + LANES].try_into().unwrap();
    let basis = &mut block.weighted_basis;
    for lane in 0..LANES {
        // Octahedral decode.
        let u = directions[lane][0] as f32 * (2.0 / 65535.0) - 1.0;
        let v = directions[lane][1] as f32 * (2.0 / 65535.0) - 1.0;
        let w = 1.0 - u.abs() - v.abs();
        let shift = (-w).max(0.0);
        let dx = u - shift.copysign(u);
        let dy = v - shift.copysign(v);
        let inverse = 1.0 / (dx * dx + dy * dy + w * w).sqrt();
        let (x, y, z) = (dx * inverse, dy * inverse, w * inverse);
        // Cone factors (Appendix C) times the link's factor.
        let factor = half_to_f32(factors[lane]);
        let c = 1.0 - half_to_f32(cones[lane]);
        let c2 = c * c;
        let weight = [
            factor * (2.0 * PI) * (1.0 - c),
            factor * PI * (1.0 - c2),
            factor * PI * c * (1.0 - c2),
            factor * (0.25 * PI) * (6.0 * c2 - 5.0 * c2 * c2 - 1.0),
        ];
        let values = sh::evaluate_four_bands(Vec3::new(x, y, z));
        for (index, value) in values.iter().enumerate().take(BANDS * BANDS) {
            basis[index][lane] = weight[BAND_OF_COEFFICIENT[index]] * value;
        }
        // SAFETY: the caller of `light_cache` vouches for every node.
        let node_flux = unsafe { *flux.get_unchecked(nodes[lane] as usize) };
        block.flux[0][lane] = node_flux.x;
        block.flux[1][lane] = node_flux.y;
        block.flux[2][lane] = node_flux.z;
    }
}

/// Adds the first `count` (1, 4, 9 or 16) coefficients of `channel`, in groups
/// of at most eight accumulators so they stay in registers.
#[inline(always)]
fn accumulate_channel(
    blocks: &[PreparedBlock],
    channel: usize,
    count: usize,
    acc: &mut [[f32; LANES]; 16],
) {
    match count {
        1 => accumulate::<1>(blocks, 0, channel, &mut acc[..1]),
        4 => accumulate::<4>(blocks, 0, channel, &mut acc[..4]),
        9 => {
            accumulate::<5>(blocks, 0, channel, &mut acc[..5]);
            accumulate::<4>(blocks, 5, channel, &mut acc[5..9]);
        }
        _ => {
            accumulate::<8>(blocks, 0, channel, &mut acc[..8]);
            accumulate::<8>(blocks, 8, channel, &mut acc[8..]);
        }
    }
}

/// Adds `COUNT` coefficients from `first` of every block's weighted basis
/// times its flux in `channel` to `acc`, kept in registers for the chunk.
#[inline(always)]
fn accumulate<const COUNT: usize>(
    blocks: &[PreparedBlock],
    first: usize,
    channel: usize,
    acc: &mut [[f32; LANES]],
) {
    let mut local: [[f32; LANES]; COUNT] = acc[..COUNT].try_into().unwrap();
    for block in blocks {
        let flux = &block.flux[channel];
        for (index, sum) in local.iter_mut().enumerate() {
            let basis = &block.weighted_basis[first + index];
            for lane in 0..LANES {
                sum[lane] = basis[lane].mul_add(flux[lane], sum[lane]);
            }
        }
    }
    acc[..COUNT].copy_from_slice(&local);
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
            // SAFETY: the test's nodes index its flux.
            unsafe {
                light_cache::<B, C>(
                    links,
                    flux,
                    &mut LinkScratch::default(),
                    &mut luma,
                    &mut co,
                    &mut cg,
                )
            };
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
