//! KTX2 files of one mip level: 2D lightmaps and 3D irradiance volumes, in
//! RGBA16F or RGB9E5, optionally Zstandard-supercompressed.
//!
//! Written by hand from the KTX 2.0 specification because the file is a
//! fixed header, a data format descriptor and the texels: no crate writes
//! uncompressed float KTX2 (the `ktx2` crate reads only; KTX-Software is a C
//! library). Tests read every file back with the `ktx2` crate, the reader
//! Bevy uses.

use half::f16;
use relight_core::{Rgb, Rgb9e5};

/// The texel formats relight writes, with their Vulkan format numbers.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum TexelFormat {
    /// `VK_FORMAT_R16G16B16A16_SFLOAT`: 8 bytes a texel, alpha 1; the
    /// format Bevy's lightmaps and irradiance volumes are usually in.
    Rgba16Float,
    /// `VK_FORMAT_E5B9G9R9_UFLOAT_PACK32`: 4 bytes a texel, three 9-bit
    /// mantissas sharing a 5-bit exponent (bias 15), at most 65408.
    Rgb9e5,
}

impl TexelFormat {
    pub fn vk_format(self) -> u32 {
        match self {
            TexelFormat::Rgba16Float => 97,
            TexelFormat::Rgb9e5 => 123,
        }
    }

    pub fn bytes_per_texel(self) -> usize {
        match self {
            TexelFormat::Rgba16Float => 8,
            TexelFormat::Rgb9e5 => 4,
        }
    }

    /// `typeSize`: the size of the format's data type (2 for half floats,
    /// 4 for the packed word).
    fn type_size(self) -> u32 {
        match self {
            TexelFormat::Rgba16Float => 2,
            TexelFormat::Rgb9e5 => 4,
        }
    }

    /// Appends `values` as texels of this format (little-endian).
    pub fn encode_into(self, values: &[Rgb], bytes: &mut Vec<u8>) {
        bytes.reserve(values.len() * self.bytes_per_texel());
        match self {
            TexelFormat::Rgba16Float => {
                for value in values {
                    for channel in [value.x, value.y, value.z, 1.0] {
                        bytes.extend_from_slice(&f16_of(channel).to_le_bytes());
                    }
                }
            }
            TexelFormat::Rgb9e5 => {
                for value in values {
                    bytes.extend_from_slice(&rgb9e5_gpu(*value).to_le_bytes());
                }
            }
        }
    }
}

/// Half float of a channel, saturating at the largest finite half (65504)
/// instead of becoming infinity, and storing 0 for negative or NaN values:
/// a lightmap texel is never negative, and an infinity would poison every
/// bilinear lookup that touches it.
#[inline]
pub fn f16_of(value: f32) -> f16 {
    f16::from_f32(f16_range(value))
}

/// What [`f16_of`] converts: `value` clamped to the largest half float,
/// and 0 for negative or NaN light. Block conversions clamp with it too.
#[inline]
pub(crate) fn f16_range(value: f32) -> f32 {
    if value > 0.0 {
        value.min(f16::MAX.to_f32())
    } else {
        0.0
    }
}

/// The GPU's shared-exponent word (`E5B9G9R9`, exponent bias 15).
/// relight's own [`Rgb9e5`] uses bias 11, four binades higher, so scaling
/// by 2^4 before packing gives exactly the GPU encoding: both store the
/// same mantissas, and the exponent field of `16 x` under bias 11 equals
/// that of `x` under bias 15. Values above 65408 saturate.
#[inline]
pub fn rgb9e5_gpu(value: Rgb) -> u32 {
    const GPU_MAX: f32 = 511.0 * 128.0;
    Rgb9e5::from_rgb(value.min(Rgb::splat(GPU_MAX)) * 16.0).0
}

/// Decodes [`rgb9e5_gpu`]'s word, as the GPU samples it.
pub fn rgb9e5_gpu_decode(word: u32) -> Rgb {
    Rgb9e5(word).to_rgb() / 16.0
}

/// One mip level of a 2D (depth 0) or 3D texture.
pub struct Ktx2Texture<'a> {
    pub format: TexelFormat,
    pub width: u32,
    pub height: u32,
    /// 0 for a 2D texture.
    pub depth: u32,
    /// Texels in the format's encoding, rows of `width`, then `height`
    /// rows a slice, then `depth` slices.
    pub texels: &'a [u8],
}

/// Why a KTX2 file could not be made.
#[derive(Debug, thiserror::Error)]
pub enum Ktx2Error {
    #[error("a {width} x {height} x {depth} texture of {format:?} needs {expected} bytes of texels, got {actual}")]
    WrongSize {
        format: TexelFormat,
        width: u32,
        height: u32,
        depth: u32,
        expected: usize,
        actual: usize,
    },
    // The cause is in the message, not a source as well (see
    // `ExportError`).
    #[error("Zstandard compression failed: {0}")]
    Compression(std::io::Error),
}

const IDENTIFIER: [u8; 12] = [
    0xAB, 0x4B, 0x54, 0x58, 0x20, 0x32, 0x30, 0xBB, 0x0D, 0x0A, 0x1A, 0x0A,
];
const SUPERCOMPRESSION_ZSTD: u32 = 2;
const WRITER: &str = concat!("relight ", env!("CARGO_PKG_VERSION"));

impl Ktx2Texture<'_> {
    /// The file's bytes; `zstd_level` supercompresses the level with
    /// Zstandard at that level (1-22; 19 and above are slow).
    pub fn to_bytes(&self, zstd_level: Option<i32>) -> Result<Vec<u8>, Ktx2Error> {
        let expected = self.width as usize
            * self.height as usize
            * self.depth.max(1) as usize
            * self.format.bytes_per_texel();
        if self.texels.len() != expected || expected == 0 {
            return Err(Ktx2Error::WrongSize {
                format: self.format,
                width: self.width,
                height: self.height,
                depth: self.depth,
                expected,
                actual: self.texels.len(),
            });
        }
        let compressed;
        let (level, scheme) = match zstd_level {
            Some(level) => {
                compressed =
                    zstd::bulk::compress(self.texels, level).map_err(Ktx2Error::Compression)?;
                (&compressed[..], SUPERCOMPRESSION_ZSTD)
            }
            None => (self.texels, 0),
        };
        let dfd = data_format_descriptor(self.format);
        let kvd = key_value_data();
        // Header (12 + 36 bytes), index (32), one level's index entry (24).
        let dfd_offset = 12 + 36 + 32 + 24;
        let kvd_offset = dfd_offset + dfd.len();
        // Uncompressed levels start on a multiple of lcm(texel size, 4);
        // supercompressed ones need no alignment.
        let align = if scheme == 0 {
            self.format.bytes_per_texel()
        } else {
            1
        };
        let level_offset = (kvd_offset + kvd.len()).div_ceil(align) * align;

        let mut bytes = Vec::with_capacity(level_offset + level.len());
        bytes.extend_from_slice(&IDENTIFIER);
        for word in [
            self.format.vk_format(),
            self.format.type_size(),
            self.width,
            self.height,
            self.depth,
            0, // layerCount: not an array
            1, // faceCount
            1, // levelCount
            scheme,
        ] {
            bytes.extend_from_slice(&word.to_le_bytes());
        }
        for word in [
            dfd_offset as u32,
            dfd.len() as u32,
            kvd_offset as u32,
            kvd.len() as u32,
        ] {
            bytes.extend_from_slice(&word.to_le_bytes());
        }
        // No supercompression global data.
        bytes.extend_from_slice(&0u64.to_le_bytes());
        bytes.extend_from_slice(&0u64.to_le_bytes());
        for word in [
            level_offset as u64,
            level.len() as u64,
            self.texels.len() as u64,
        ] {
            bytes.extend_from_slice(&word.to_le_bytes());
        }
        bytes.extend_from_slice(&dfd);
        bytes.extend_from_slice(&kvd);
        bytes.resize(level_offset, 0);
        bytes.extend_from_slice(level);
        Ok(bytes)
    }
}

/// The Khronos basic data format descriptor of the uncompressed texels
/// (Zstandard supercompression keeps it: KTX 2.0, section 3.10), linear
/// BT.709 primaries.
fn data_format_descriptor(format: TexelFormat) -> Vec<u8> {
    const RGBSDA: u32 = 1;
    const BT709: u32 = 1;
    const LINEAR: u32 = 1;
    const FLOAT: u32 = 0x80;
    const SIGNED: u32 = 0x40;
    const EXPONENT: u32 = 0x20;
    // (bit offset, bit length, channel | qualifiers, lower, upper)
    let samples: Vec<(u32, u32, u32, u32, u32)> = match format {
        TexelFormat::Rgba16Float => [0u32, 1, 2, 15]
            .iter()
            .enumerate()
            .map(|(index, &channel)| {
                (
                    16 * index as u32,
                    16,
                    channel | FLOAT | SIGNED,
                    (-1.0f32).to_bits(),
                    1.0f32.to_bits(),
                )
            })
            .collect(),
        // Each channel's 9-bit mantissa, then the shared exponent (bias
        // 15) as an exponent sample of the same channel, as KTX-Software
        // describes the format.
        TexelFormat::Rgb9e5 => (0..3u32)
            .flat_map(|channel| {
                [
                    (9 * channel, 9, channel, 0, 8448),
                    (27, 5, channel | EXPONENT, 15, 31),
                ]
            })
            .collect(),
    };
    let block_size = 24 + 16 * samples.len() as u32;
    let mut words = vec![
        block_size + 4, // dfdTotalSize
        0,              // vendor Khronos, descriptor type basic
        2 | (block_size << 16),
        RGBSDA | (BT709 << 8) | (LINEAR << 16),
        0, // 1x1x1x1 texel blocks
        format.bytes_per_texel() as u32,
        0,
    ];
    for (offset, length, channel, lower, upper) in samples {
        words.extend([
            offset | ((length - 1) << 16) | (channel << 24),
            0,
            lower,
            upper,
        ]);
    }
    bytemuck::cast_slice(&words).to_vec()
}

/// `KTXwriter`, the one key the specification asks writers to set.
fn key_value_data() -> Vec<u8> {
    let mut pair = b"KTXwriter\0".to_vec();
    pair.extend_from_slice(WRITER.as_bytes());
    pair.push(0);
    let mut bytes = (pair.len() as u32).to_le_bytes().to_vec();
    bytes.extend_from_slice(&pair);
    bytes.resize(bytes.len().div_ceil(4) * 4, 0);
    bytes
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The Vulkan specification's shared-exponent encoding (section
    /// "Shared Exponent"), written out: the independent check of the
    /// bias-shift trick.
    fn rgb9e5_by_the_spec(value: Rgb) -> u32 {
        let (n, b, e_max) = (9i32, 15i32, 31i32);
        let sharedexp_max = ((1 << n) - 1) as f32 / (1 << n) as f32 * 2f32.powi(e_max - b);
        let clamp = |x: f32| x.clamp(0.0, sharedexp_max);
        let (r, g, bl) = (clamp(value.x), clamp(value.y), clamp(value.z));
        let max = r.max(g).max(bl);
        let mut exp_p = (max.log2().floor() as i32).max(-b - 1) + 1 + b;
        let max_s = (max / 2f32.powi(exp_p - b - n) + 0.5).floor() as i32;
        if max_s == 1 << n {
            exp_p += 1;
        }
        let q = |x: f32| (x / 2f32.powi(exp_p - b - n) + 0.5).floor() as u32;
        q(r) | (q(g) << 9) | (q(bl) << 18) | ((exp_p as u32) << 27)
    }

    #[test]
    fn shared_exponent_words_match_the_vulkan_encoding() {
        for value in [
            Rgb::new(1.0, 0.5, 0.25),
            Rgb::new(0.001, 0.002, 0.0),
            Rgb::new(300.0, 7.5, 0.01),
            Rgb::new(65000.0, 1.0, 2.0),
            Rgb::new(3.0e-7, 1.0e-6, 0.0),
        ] {
            assert_eq!(rgb9e5_gpu(value), rgb9e5_by_the_spec(value), "{value}");
            // 9 mantissa bits: at most half a step of the brightest
            // channel's binade, 2^-9 of it, or half the smallest step
            // (2^-24) below 2^-15.
            let back = rgb9e5_gpu_decode(rgb9e5_gpu(value));
            let bound = (value.max_element() / 512.0).max(2f32.powi(-25));
            assert!(
                (back - value).abs().max_element() <= bound,
                "{value}: {back}"
            );
        }
        assert_eq!(
            rgb9e5_gpu_decode(rgb9e5_gpu(Rgb::splat(1.0e9))),
            Rgb::splat(65408.0)
        );
    }

    #[test]
    fn half_floats_saturate_instead_of_overflowing() {
        assert_eq!(f16_of(1.0e6), f16::MAX);
        assert_eq!(f16_of(-3.0), f16::ZERO);
        assert_eq!(f16_of(f32::NAN), f16::ZERO);
        assert_eq!(f16_of(0.5).to_f32(), 0.5);
    }

    /// The `ktx2` crate generates descriptors from its own table, checked
    /// against Khronos's validator: ours must be the same bytes.
    #[test]
    fn descriptors_match_the_ktx2_crates() {
        for (format, theirs) in [
            (TexelFormat::Rgba16Float, ktx2::Format::R16G16B16A16_SFLOAT),
            (TexelFormat::Rgb9e5, ktx2::Format::E5B9G9R9_UFLOAT_PACK32),
        ] {
            let (basic, type_size) = ktx2::dfd::Basic::from_format(theirs).unwrap();
            let expected = ktx2::dfd::Block::Basic(basic).to_vec();
            let ours = data_format_descriptor(format);
            assert_eq!(&ours[4..], &expected[..], "{format:?}");
            assert_eq!(format.type_size(), type_size);
        }
    }

    #[test]
    fn a_wrong_texel_count_is_refused() {
        let texture = Ktx2Texture {
            format: TexelFormat::Rgba16Float,
            width: 4,
            height: 4,
            depth: 0,
            texels: &[0u8; 8 * 15],
        };
        let message = texture.to_bytes(None).unwrap_err().to_string();
        assert!(message.contains("needs 128 bytes"), "{message}");
    }
}
