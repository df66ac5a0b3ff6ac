//! The lightmap an engine uploads: every atlas texel in the engine's
//! convention, refilled each frame from a technique's receiver values.

use crate::units::lightmap_texel;
use half::f16;
use half::slice::HalfFloatSliceExt;
use rayon::prelude::*;
use relight_core::Rgb;
use relight_scene::atlas::Atlas;

/// Rows a rayon task fills: enough to amortise the task, few enough that
/// two cores share a 1024-row atlas evenly.
const ROWS_PER_TASK: usize = 16;

/// Texels converted to half floats together: a few kilobytes on the stack.
const TEXELS_PER_BLOCK: usize = 256;

/// Which texel each atlas texel copies, fixed at creation so that a frame
/// is one parallel pass with no scatter and no dilation step.
#[derive(Clone, Debug)]
pub struct LightmapLayout {
    pub width: u32,
    pub height: u32,
    /// The receiver each texel shows: its own, the covered texel a gutter
    /// texel copies (chains of the atlas's dilation resolved), or
    /// `u32::MAX` for texels that cover nothing (they stay black).
    receiver_of_texel: Vec<u32>,
}

impl LightmapLayout {
    pub fn new(atlas: &Atlas) -> Self {
        Self {
            width: atlas.width,
            height: atlas.height,
            receiver_of_texel: atlas.dilated_receiver_of_texel(),
        }
    }

    pub fn texel_count(&self) -> usize {
        self.receiver_of_texel.len()
    }

    /// Fills `bytes` (RGBA16F little-endian, 8 bytes a texel, `width *
    /// height` texels, row 0 first: glTF's and Bevy's V = 0) with
    /// `per_receiver` irradiance (W/m^2), plus `added` per receiver when
    /// given (static light an engine cannot draw), converted by
    /// [`lightmap_texel`]; alpha is 1. The same texels as the atlas's
    /// scatter and dilation, in one parallel pass over rows: these are
    /// the bytes an engine uploads every frame.
    pub fn fill_rgba16f(&self, per_receiver: &[Rgb], added: Option<&[Rgb]>, bytes: &mut [u8]) {
        assert_eq!(bytes.len(), self.texel_count() * 8);
        let width = self.width as usize;
        bytes
            .par_chunks_mut(width * 8 * ROWS_PER_TASK)
            .zip(self.receiver_of_texel.par_chunks(width * ROWS_PER_TASK))
            .for_each(|(out, receivers)| {
                // A block's channels are clamped as `f16_of` does, then
                // converted together: the slice conversion runs 8 lanes
                // of F16C where one value at a time was a third of the
                // pass.
                let mut floats = [0.0f32; TEXELS_PER_BLOCK * 4];
                let mut halves = [f16::ZERO; TEXELS_PER_BLOCK * 4];
                for (out, receivers) in out
                    .chunks_mut(TEXELS_PER_BLOCK * 8)
                    .zip(receivers.chunks(TEXELS_PER_BLOCK))
                {
                    let count = receivers.len();
                    for (rgba, &receiver) in floats.chunks_exact_mut(4).zip(receivers) {
                        let index = receiver as usize;
                        let value = match per_receiver.get(index) {
                            Some(&irradiance) => {
                                let extra = added.map_or(Rgb::ZERO, |added| added[index]);
                                lightmap_texel(irradiance + extra)
                            }
                            None => Rgb::ZERO,
                        };
                        for (channel, value) in rgba.iter_mut().zip(value.to_array()) {
                            *channel = crate::ktx2_file::f16_range(value);
                        }
                        rgba[3] = 1.0;
                    }
                    halves[..count * 4].convert_from_f32_slice(&floats[..count * 4]);
                    for (texel, half) in out.chunks_exact_mut(2).zip(&halves[..count * 4]) {
                        texel.copy_from_slice(&half.to_le_bytes());
                    }
                }
            });
    }

    /// The lightmap in engine units as linear RGB, for files.
    pub fn to_rgb(&self, per_receiver: &[Rgb]) -> Vec<Rgb> {
        self.receiver_of_texel
            .par_iter()
            .map(|&receiver| {
                per_receiver
                    .get(receiver as usize)
                    .map_or(Rgb::ZERO, |&irradiance| lightmap_texel(irradiance))
            })
            .collect()
    }
}

/// A technique's irradiance at every receiver: its stored lightmap, or one
/// lookup a receiver for techniques without one.
pub fn receiver_irradiance(
    context: &relight_technique::SceneContext,
    technique: &dyn relight_technique::Technique,
) -> Vec<Rgb> {
    if let Some(values) = technique.receiver_irradiance() {
        return values.to_vec();
    }
    let receivers = &context.atlas.receivers;
    (0..receivers.len())
        .into_par_iter()
        .map(|index| {
            technique.indirect_irradiance(&relight_technique::SurfacePoint {
                position: receivers.positions[index],
                normal: receivers.normals[index],
                triangle: receivers.triangles[index],
                barycentric: receivers.barycentrics[index],
            })
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;
    use relight_scene::atlas::TexelDensity;

    /// Out-of-range light saturates, and negative or NaN light is black,
    /// bit for bit as [`crate::f16_of`] converts one value.
    #[test]
    fn texels_clamp_as_single_conversions_do() {
        let scene = relight_scene::load_scene(&crate::tests::shipped("cornell-box")).unwrap();
        let atlas = Atlas::build(&scene, TexelDensity::TargetResolution(32)).unwrap();
        let specials = [1e9, -3.0, f32::NAN, 0.0, -0.0, f32::INFINITY, 1e-9, 200.0];
        let per_receiver: Vec<Rgb> = (0..atlas.receivers.len())
            .map(|index| {
                let pick = |offset: usize| specials[(index + offset) % specials.len()];
                Rgb::new(pick(0), pick(3), pick(5))
            })
            .collect();
        let layout = LightmapLayout::new(&atlas);
        let mut bytes = vec![0u8; layout.texel_count() * 8];
        layout.fill_rgba16f(&per_receiver, None, &mut bytes);
        let shown = atlas.dilated_receiver_of_texel();
        for (texel, &receiver) in shown.iter().enumerate() {
            let value = per_receiver
                .get(receiver as usize)
                .map_or(Rgb::ZERO, |&irradiance| lightmap_texel(irradiance));
            for channel in 0..3 {
                let at = texel * 8 + channel * 2;
                let got = f16::from_le_bytes([bytes[at], bytes[at + 1]]);
                assert_eq!(
                    got.to_bits(),
                    crate::f16_of(value[channel]).to_bits(),
                    "{value}"
                );
            }
        }
    }

    #[test]
    fn texels_equal_the_atlas_scatter_and_dilation_in_engine_units() {
        let scene = relight_scene::load_scene(&crate::tests::shipped("cornell-box")).unwrap();
        let atlas = Atlas::build(&scene, TexelDensity::TargetResolution(32)).unwrap();
        let per_receiver: Vec<Rgb> = (0..atlas.receivers.len())
            .map(|index| Rgb::new(index as f32, 1.0, 2.0 * index as f32) * 0.01)
            .collect();
        let expected = atlas.to_lightmap(&per_receiver);
        let layout = LightmapLayout::new(&atlas);
        let mut bytes = vec![0u8; layout.texel_count() * 8];
        layout.fill_rgba16f(&per_receiver, None, &mut bytes);
        let texels: Vec<f16> = bytes
            .chunks_exact(2)
            .map(|pair| f16::from_le_bytes([pair[0], pair[1]]))
            .collect();
        let mut covered = 0;
        for (index, irradiance) in expected.iter().enumerate() {
            let want = lightmap_texel(*irradiance);
            let got = Rgb::new(
                texels[4 * index].to_f32(),
                texels[4 * index + 1].to_f32(),
                texels[4 * index + 2].to_f32(),
            );
            // Half floats keep 11 significant bits: relative 2^-11.
            assert!(
                (got - want).abs().max_element() <= want.max_element() / 2048.0 + 1e-7,
                "texel {index}: {got} against {want}"
            );
            assert_eq!(texels[4 * index + 3], f16::ONE);
            // The same bits as converting one value at a time.
            for channel in 0..3 {
                assert_eq!(texels[4 * index + channel], crate::f16_of(want[channel]));
            }
            covered += usize::from(want.max_element() > 0.0);
        }
        assert!(covered > atlas.receivers.len() / 2);
    }
}
