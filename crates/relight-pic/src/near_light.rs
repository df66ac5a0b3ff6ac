//! The surfaces beside the scene file's lights (a shade's inside, the
//! patch of wall a few texels from a lamp), which the lightmap caches see
//! through explicit samples rather than through the links.
//!
//! A cache's links go to the nodes of largest visible solid angle, chosen
//! at bake without the lights, and each link's factor averages the
//! visibility of a few of its node's surfels. A shade's inside is a few
//! surfels of a node that also holds the wall or ceiling around it, so
//! whether the next room's caches see the shade's light depended on which
//! surfels the factor sampled (generated suites with a shaded lamp: PIC
//! `high` 0.78x of the path tracer's light in the unlit room). Here each
//! lightmap cache traces, once at load, the final gather's explicit samples
//! of those surfaces ([`relight_technique::NearLightSamples`]), and every
//! frame adds their light to its SH; the surfels there leave their direct
//! light out of the flux the links carry, so it is not counted twice.
//!
//! A cache's entries are grouped by the scene-file light nearest each
//! texel side, and each group is projected along one direction (the
//! entries' weighted mean): the caches' four or fewer SH bands resolve
//! about 45 degrees, wider than a shade or a hot patch seen from a cache
//! that does not gather it by the final gather. The group's SH is scaled
//! so that the cache's own lookup (its normal, the cosine lobe) returns
//! the form factors' irradiance exactly: the band-limited lobe is 0.09
//! where the true one is 0 at the horizon, so light projected as radiance
//! from a hot patch seen at a grazing angle (the next wall of a lamp's
//! corner) would come back too bright.
//!
//! Grid caches (points in space with `space = grid`) get none of this.

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
pub struct NearLightLinks {
    samples: NearLightSamples,
    bands: usize,
    /// Per lightmap cache: its groups, `cache_groups[c]..cache_groups[c + 1]`.
    cache_groups: Vec<u32>,
    /// Per group: Y_lm of its direction (`bands^2` values) and its entries,
    /// `group_entries[g]..group_entries[g + 1]`.
    group_basis: Vec<f32>,
    group_entries: Vec<u32>,
    /// (texel side, form factor): the irradiance its radiosity gives the
    /// cache.
    entries: Vec<(u32, f32)>,
    /// Per surfel: whether its direct light reaches the caches through the
    /// samples instead of the links.
    hot_surfels: Vec<bool>,
}

impl NearLightLinks {
    /// `caches`: the lightmap caches' positions and normals; `surfels`:
    /// the surfels' triangles and positions.
    pub fn build(
        context: &SceneContext,
        caches: (&[Vec3], &[Vec3]),
        surfels: (&[u32], &[Vec3]),
        bands: usize,
    ) -> Self {
        let samples = NearLightSamples::of(context);
        if samples.is_empty() {
            return Self::default();
        }
        let lights: Vec<Vec3> = context
            .scene
            .lights
            .iter()
            .filter_map(Light::position)
            .collect();
        let light_of_texel: Vec<u32> = samples
            .texel_positions()
            .iter()
            .map(|&position| {
                (0..lights.len())
                    .min_by(|&a, &b| {
                        position
                            .distance_squared(lights[a])
                            .total_cmp(&position.distance_squared(lights[b]))
                    })
                    .unwrap_or(0) as u32
            })
            .collect();
        let (positions, normals) = caches;
        let rows = samples.rows(context, positions, normals);
        let coefficients = bands * bands;
        let texel_positions = samples.texel_positions();
        let cosine_factors: [f32; sh::MAX_BANDS] = std::array::from_fn(sh::cosine_lobe_factor);
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
                        (
                            light_of_texel[texel as usize],
                            texel,
                            form_factor,
                            direction,
                        )
                    })
                    .collect();
                row.sort_unstable_by_key(|&(light, texel, ..)| (light, texel));
                let mut lobe = vec![0.0f32; coefficients];
                sh::evaluate_filtered(normals[cache], bands, &cosine_factors, &mut lobe);
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
                    let mut values = vec![0.0f32; coefficients];
                    sh::evaluate(direction, bands, &mut values);
                    // Unit irradiance at the cache's own normal.
                    let lookup: f32 = values.iter().zip(&lobe).map(|(y, l)| y * l).sum();
                    let scale = if lookup > 1e-3 { 1.0 / lookup } else { 0.0 };
                    basis.extend(values.iter().map(|y| y * scale));
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
        let mut links = Self {
            bands,
            cache_groups: Vec::with_capacity(positions.len() + 1),
            group_entries: vec![0],
            ..Self::default()
        };
        links.cache_groups.push(0);
        for CacheGroups {
            basis,
            ends,
            entries,
        } in per_cache
        {
            let base = links.entries.len() as u32;
            links.group_basis.extend(basis);
            links
                .group_entries
                .extend(ends.iter().map(|&end| base + end));
            links.entries.extend(entries);
            links
                .cache_groups
                .push(links.group_entries.len() as u32 - 1);
        }
        let (triangles, surfel_positions) = surfels;
        links.hot_surfels = triangles
            .par_iter()
            .zip(surfel_positions.par_iter())
            .map(|(&triangle, &position)| samples.covers(triangle, position))
            .collect();
        links.samples = samples;
        links
    }

    pub fn is_empty(&self) -> bool {
        self.samples.is_empty()
    }

    /// Lights the samples for this frame.
    pub fn light(&mut self, context: &SceneContext, lights: &[Light]) {
        self.samples.light(context, lights);
    }

    /// Whether surfel `index`'s direct light is the samples' to carry.
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
        let coefficients = self.bands * self.bands;
        for group in range[0] as usize..range[1] as usize {
            let entries =
                self.group_entries[group] as usize..self.group_entries[group + 1] as usize;
            let light: Rgb = self.entries[entries]
                .iter()
                .map(|&(texel, factor)| radiosity[texel as usize] * factor)
                .sum();
            let light = rgb_to_ycocg(light);
            let basis = &self.group_basis[group * coefficients..(group + 1) * coefficients];
            for (value, &y) in luma.iter_mut().zip(basis) {
                *value += light.x * y;
            }
            for ((co, cg), &y) in co.iter_mut().zip(cg.iter_mut()).zip(basis) {
                *co += light.y * y;
                *cg += light.z * y;
            }
        }
    }

    /// How many samples, texel sides and caches that see some.
    pub fn counts(&self) -> (usize, usize, usize) {
        let (samples, texels) = self.samples.len();
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
