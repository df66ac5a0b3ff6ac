//! The surfaces beside the scene file's lights (a shade's inside, the
//! patch of wall a few texels from a lamp), which the lightmap caches see
//! through explicit samples rather than through the links.
//!
//! A cache's links go to the nodes of largest visible solid angle, chosen
//! at bake without the lights, and each link's factor averages the
//! visibility of a few of its node's surfels. A shade's inside is a few
//! surfels of a node that also holds the wall or ceiling around it, so
//! whether the next room's caches see the shade's light depended on which
//! surfels the factor sampled. Here each
//! lightmap cache traces, once at load, the final gather's explicit samples
//! of those surfaces ([`relight_technique::NearLightSamples`]), and every
//! frame adds their light to its SH; the surfels there leave their direct
//! light out of the flux the links carry, so it is not counted twice.
//!
//! A cache's entries are grouped by the scene-file light nearest each
//! texel side, and each group is projected along one direction (the
//! entries' weighted mean): the presets' three or four SH bands resolve
//! about 45 degrees, wider than a shade or a hot patch seen from a cache
//! that does not gather it by the final gather. The group's SH is scaled
//! so that the cache's own lookup (its normal, the cosine lobe) returns
//! the form factors' irradiance exactly, luma and chroma each at its own
//! bands: the band-limited lobe is 0.09 where the true one is 0 at the
//! horizon, so light projected as radiance from a hot patch seen at a
//! grazing angle (the next wall of a lamp's corner) came back too bright.
//! Other lookups of the same cache (a neighbouring texel's normal across a
//! curved surface, glossy reflection) read that scaled SH as it is.
//!
//! Grid caches (points in space with `space = grid`) lose those surfaces'
//! first bounce: they read the links, which no longer carry it.

use glam::Vec3;
use rayon::prelude::*;
use relight_core::colour::rgb_to_ycocg;
use relight_core::{sh, Rgb};
use relight_scene::Light;
use relight_technique::{NearLightSamples, SceneContext};

/// One cache's groups while they are built: their bases, where each
/// group's entries end, and the entries.
struct CacheGroups {
    basis: Vec<f32>,
    ends: Vec<u32>,
    entries: Vec<(u32, f32)>,
}

#[derive(Default)]
pub struct NearLightCaches {
    samples: NearLightSamples,
    /// Luma and chroma SH coefficients per cache (`bands^2`, `chroma^2`).
    luma_count: usize,
    chroma_count: usize,
    /// Per lightmap cache: its groups, `cache_groups[c]..cache_groups[c + 1]`.
    cache_groups: Vec<u32>,
    /// Per group: Y_lm of its direction, scaled for luma (`luma_count`
    /// values) and for chroma (`chroma_count`), and its entries,
    /// `group_entries[g]..group_entries[g + 1]`.
    group_basis: Vec<f32>,
    group_entries: Vec<u32>,
    /// (texel side, form factor): the irradiance its radiosity gives the
    /// cache.
    entries: Vec<(u32, f32)>,
    /// Per surfel: whether its direct and emissive light reach the caches
    /// through the samples instead of the caches.
    hot_surfels: Vec<bool>,
}

impl NearLightCaches {
    /// `caches`: the lightmap caches' positions and normals; `surfels`:
    /// the surfels' triangles and positions; `bands` for luma and
    /// chroma, and the cosine lobe's factors that the caches' lookups use.
    pub fn build(
        context: &SceneContext,
        caches: (&[Vec3], &[Vec3]),
        surfels: (&[u32], &[Vec3]),
        (bands, chroma_bands): (usize, usize),
        cosine_factors: &[f32; sh::MAX_BANDS],
    ) -> Self {
        let samples = NearLightSamples::of(context);
        if samples.is_empty() {
            return Self::default();
        }
        let light_of_side = samples.light_of_side();
        let (positions, normals) = caches;
        let rows = samples.rows(context, positions, normals);
        let luma_count = bands * bands;
        let chroma_count = chroma_bands * chroma_bands;
        let texel_positions = samples.texel_positions();
        // Per cache: its groups' bases and entries, built in parallel.
        let per_cache: Vec<CacheGroups> = (0..positions.len())
            .into_par_iter()
            .map(|cache| {
                let mut row: Vec<(u32, u32, f32, Vec3)> = rows
                    .row(cache)
                    .iter()
                    .map(|&(texel, form_factor)| {
                        let direction = (texel_positions[texel as usize] - positions[cache])
                            .normalize_or_zero();
                        (light_of_side[texel as usize], texel, form_factor, direction)
                    })
                    .collect();
                row.sort_unstable_by_key(|&(light, texel, ..)| (light, texel));
                let mut lobe = vec![0.0f32; luma_count];
                sh::evaluate_filtered(normals[cache], bands, cosine_factors, &mut lobe);
                // What a unit of radiance along `values`' direction gives
                // the cache's own cosine lookup over its first `count`
                // coefficients, inverted.
                let unit_scale = |values: &[f32], count: usize| {
                    let lookup: f32 = values[..count]
                        .iter()
                        .zip(&lobe[..count])
                        .map(|(y, l)| y * l)
                        .sum();
                    if lookup > 0.0 {
                        1.0 / lookup
                    } else {
                        0.0
                    }
                };
                let mut basis = Vec::new();
                let mut ends = Vec::new();
                let mut entries = Vec::with_capacity(row.len());
                let mut start = 0;
                while start < row.len() {
                    let light = row[start].0;
                    let end = start + row[start..].partition_point(|entry| entry.0 == light);
                    let direction = row[start..end]
                        .iter()
                        .map(|&(_, _, factor, direction)| direction * factor)
                        .sum::<Vec3>()
                        .normalize_or_zero();
                    let mut values = vec![0.0f32; luma_count];
                    sh::evaluate(direction, bands, &mut values);
                    let luma_scale = unit_scale(&values, luma_count);
                    let chroma_scale = unit_scale(&values, chroma_count);
                    basis.extend(values.iter().map(|y| y * luma_scale));
                    basis.extend(values[..chroma_count].iter().map(|y| y * chroma_scale));
                    entries.extend(
                        row[start..end]
                            .iter()
                            .map(|&(_, texel, factor, _)| (texel, factor)),
                    );
                    ends.push(entries.len() as u32);
                    start = end;
                }
                CacheGroups {
                    basis,
                    ends,
                    entries,
                }
            })
            .collect();
        let mut caches = Self {
            luma_count,
            chroma_count,
            cache_groups: Vec::with_capacity(positions.len() + 1),
            group_entries: vec![0],
            ..Self::default()
        };
        caches.cache_groups.push(0);
        for CacheGroups {
            basis,
            ends,
            entries,
        } in per_cache
        {
            let base = caches.entries.len() as u32;
            caches.group_basis.extend(basis);
            caches
                .group_entries
                .extend(ends.iter().map(|&end| base + end));
            caches.entries.extend(entries);
            caches
                .cache_groups
                .push(caches.group_entries.len() as u32 - 1);
        }
        let (triangles, surfel_positions) = surfels;
        caches.hot_surfels = triangles
            .par_iter()
            .zip(surfel_positions.par_iter())
            .map(|(&triangle, &position)| samples.covers(triangle, position))
            .collect();
        caches.samples = samples;
        caches
    }

    pub fn is_empty(&self) -> bool {
        self.samples.is_empty()
    }

    /// Lights the samples for this frame.
    pub fn light(&mut self, context: &SceneContext, lights: &[Light]) {
        self.samples.light(context, lights);
    }

    /// Whether surfel `index`'s direct and emissive light are the samples'
    /// to carry.
    pub fn is_hot(&self, surfel: usize) -> bool {
        self.hot_surfels.get(surfel).copied().unwrap_or(false)
    }

    /// Adds the samples' light to lightmap cache `cache`'s SH (radiance,
    /// YCoCg: `luma` of `bands^2` values, `co` and `cg` of the chroma
    /// bands' count).
    pub fn add_to_cache(&self, cache: usize, luma: &mut [f32], co: &mut [f32], cg: &mut [f32]) {
        let Some(range) = self.cache_groups.get(cache..cache + 2) else {
            return;
        };
        let radiosity = self.samples.radiosity();
        let stride = self.luma_count + self.chroma_count;
        for group in range[0] as usize..range[1] as usize {
            let entries =
                self.group_entries[group] as usize..self.group_entries[group + 1] as usize;
            let light: Rgb = self.entries[entries]
                .iter()
                .map(|&(texel, factor)| radiosity[texel as usize] * factor)
                .sum();
            let light = rgb_to_ycocg(light);
            let basis = &self.group_basis[group * stride..(group + 1) * stride];
            let (luma_basis, chroma_basis) = basis.split_at(self.luma_count);
            for (value, &y) in luma.iter_mut().zip(luma_basis) {
                *value += light.x * y;
            }
            for ((co, cg), &y) in co.iter_mut().zip(cg.iter_mut()).zip(chroma_basis) {
                *co += light.y * y;
                *cg += light.z * y;
            }
        }
    }

    /// How many samples, texel sides and caches that see some.
    pub fn counts(&self) -> (usize, usize, usize) {
        let (samples, texels) = self.samples.counts();
        let caches = self
            .cache_groups
            .windows(2)
            .filter(|pair| pair[1] > pair[0])
            .count();
        (samples, texels, caches)
    }

    pub fn memory_bytes(&self) -> usize {
        self.samples.memory_bytes()
            + self.cache_groups.len() * 4
            + self.group_basis.len() * 4
            + self.group_entries.len() * 4
            + self.entries.len() * 8
            + self.hot_surfels.len()
    }
}
