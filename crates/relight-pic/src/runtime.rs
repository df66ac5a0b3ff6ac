//! The PIC run time: surfel lighting, pull, cache lighting, shading.

use crate::bake::PicBake;
use crate::kernels::{self, LinkScratch, LinkSlice};
use crate::near_light::NearLightCaches;
use crate::normalisation;
use glam::{Vec2, Vec3};
use rayon::prelude::*;
use relight_core::colour::{rgb_to_ycocg, ycocg_to_rgb};
use relight_core::{sh, Rgb};
use relight_scene::atlas::{Atlas, TexelDensity};
use relight_scene::Light;
use relight_technique::{
    FinalGather, FinalGatherSettings, Frame, FrameReads, LastFrame, MemoryEntry, SceneContext,
    SettlingPasses, StageTimings, SurfaceGather, SurfacePoint, Technique, TechniqueError,
};
use relight_trace::direct::Footprints;
use std::f32::consts::PI;
use std::sync::Arc;
use std::time::{Duration, Instant};

const NO_CACHE: u32 = u32::MAX;

/// Run-time settings (one bake serves every value of them).
#[derive(Clone, Debug)]
pub struct RuntimeSettings {
    /// Luma bands of the caches (fixed by the bake for projected links).
    pub bands: usize,
    pub chroma_bands: usize,
    pub bounces: u32,
    /// Emissive surfels light the caches through the links; the surfels'
    /// direct light then leaves emissive triangles out.
    pub area_lights_through_links: bool,
    pub specular: f32,
    /// Points in space gather the light leaving the surfaces around them;
    /// `None`: they read the grid caches.
    pub space_gather: Option<SurfaceGather>,
    /// Receivers and surfels drop the lightmap caches they cannot see.
    pub cache_visibility: bool,
    /// Which receivers near other geometry trace their near field.
    pub final_gather: FinalGatherSettings,
    /// Scale each lightmap cache's links to what it sees (see
    /// [`crate::normalisation`]).
    pub link_normalisation: bool,
}

pub struct Pic {
    context: Arc<SceneContext>,
    bake: PicBake,
    /// Link nodes of SH-projected links as u16 where the hierarchy has at
    /// most 65,536 nodes (the moderate preset's 32k surfels make 63.5k):
    /// the bake's u32 nodes are then moved out, and a link streams 20
    /// bytes a frame instead of 22.
    narrow_link_nodes: Vec<u16>,
    /// Links in the bake, whichever array holds their nodes.
    link_count: usize,
    settings: RuntimeSettings,
    /// The cache atlas when it is not the scene's.
    own_atlas: Option<Atlas>,
    /// Texel -> lightmap cache, gutters pointing at the cache they copy.
    cache_of_texel: Vec<u32>,
    /// Traced near field of the receivers close to other geometry, added
    /// to the caches' light as a correction lightmap.
    final_gather: FinalGather,
    /// Per surfel: its lightmap taps (cache, weight) that it can see.
    surfel_taps: Vec<[(u32, f32); 4]>,
    /// Receivers that cannot see some of their four bilinear lightmap
    /// caches (see [`visible_taps`]), ascending, with the taps they keep;
    /// per receiver its index here or `NO_CACHE`.
    hidden_tap_receivers: Vec<u32>,
    hidden_tap_taps: Vec<[(u32, f32); 4]>,
    hidden_tap_index: Vec<u32>,
    /// The receiver each scene-atlas texel shows
    /// ([`Atlas::dilated_receiver_of_texel`]), and per texel whether that
    /// receiver is one of [`Self::hidden_tap_receivers`]; both empty when
    /// there are none. Shading reads the receivers' values wherever its
    /// bilinear footprint touches such a texel ([`Self::indirect_irradiance`]).
    shown_receiver: Vec<u32>,
    shows_hidden_taps: Vec<bool>,
    /// Per surfel: A_l Y_lm(normal), `bands^2` values.
    surfel_basis: Vec<f32>,
    /// Irradiance at each surfel from emissive surfaces through the links
    /// (YCoCg), fixed because emission is.
    surfel_area_light: Vec<Vec3>,
    surfel_direct: Vec<Rgb>,
    /// The surfels' direct light that no frame changes (the environment,
    /// and emissive triangles unless they light through the links).
    surfel_static: relight_trace::direct::StaticDirect,
    /// Last frame's indirect irradiance at each surfel (YCoCg), reused.
    surfel_indirect: Vec<Vec3>,
    /// A_l of the clamped cosine lobe, per band.
    cosine_factors: [f32; sh::MAX_BANDS],
    /// Flux per node, YCoCg, in units of one surfel's area.
    flux: Vec<Vec3>,
    /// Per cache: Y (bands^2), Co, Cg (chroma^2 each).
    cache_sh: Vec<f32>,
    stride: usize,
    pull_subtrees: Vec<u32>,
    pull_top: Vec<u32>,
    /// Per receiver, this frame's light from the caches, and after the
    /// final gather its near field: the lightmap's values, produced within
    /// the timed update because an engine uploads them every frame. The
    /// gather reads the caches' light at its hit points from here too
    /// instead of looking each up again.
    receiver_values: Vec<Rgb>,
    timings: StageTimings,
    /// What the last update read, to skip a frame that repeats it.
    last_frame: LastFrame,
    updates: u64,
    /// The passes since the lights last changed, each update one; the
    /// light is settled when they say another adds too little to see.
    resting: SettlingPasses,
    settled: bool,
    /// The last frame's lights, for gathers at points in space.
    lights: Vec<Light>,
    /// The surfaces beside the scene file's lights, which the lightmap
    /// caches see through explicit samples (see [`crate::near_light`]).
    near_light: NearLightCaches,
    /// Each lightmap cache's link scale (see [`crate::normalisation`]);
    /// empty when the links run as baked.
    cache_scales: Vec<f32>,
}

impl Pic {
    pub fn new(
        context: Arc<SceneContext>,
        mut bake: PicBake,
        mut settings: RuntimeSettings,
    ) -> Result<Self, TechniqueError> {
        if bake.projected_bands > 0 {
            settings.bands = bake.projected_bands;
        }
        settings.chroma_bands = settings.chroma_bands.clamp(1, settings.bands);
        let own_atlas = if bake.cache_atlas_metres > 0.0 {
            Some(
                Atlas::build_unrefined(
                    &context.scene,
                    TexelDensity::MetresPerTexel(bake.cache_atlas_metres),
                )
                .map_err(|error| TechniqueError::Other(error.to_string()))?,
            )
        } else {
            None
        };
        let atlas = own_atlas.as_ref().unwrap_or(&context.atlas);
        if atlas.receivers.len() != bake.caches.lightmap_count {
            return Err(TechniqueError::Other(format!(
                "this PIC bake has {} lightmap caches but the scene's cache atlas has {} texels: bake again for this scene and lightmap resolution",
                bake.caches.lightmap_count,
                atlas.receivers.len()
            )));
        }
        let triangle_count = context.scene.mesh.triangles.len();
        if let Some(&triangle) = bake
            .surfels
            .triangles
            .iter()
            .find(|&&t| t as usize >= triangle_count)
        {
            return Err(TechniqueError::Other(format!(
                "this PIC bake puts a surfel on triangle {triangle}, but the scene has {triangle_count} triangles: bake again for this scene"
            )));
        }
        let cache_of_texel = atlas.dilated_receiver_of_texel();
        let coefficients = settings.bands * settings.bands;
        let stride = coefficients + 2 * settings.chroma_bands * settings.chroma_bands;
        let surfels = &bake.surfels;
        let cosine_factors = std::array::from_fn(sh::cosine_lobe_factor);
        let mut surfel_basis = vec![0.0f32; surfels.len() * coefficients];
        for (normal, row) in surfels
            .normals
            .iter()
            .zip(surfel_basis.chunks_exact_mut(coefficients))
        {
            sh::evaluate_filtered(*normal, settings.bands, &cosine_factors, row);
        }
        // The cache-lighting kernels gather flux without bounds checks: every
        // link node must name a hierarchy node (checked here once, not per
        // cache per frame).
        let flux = vec![Vec3::ZERO; bake.hierarchy.node_count()];
        assert!(
            bake.link_nodes
                .iter()
                .all(|&node| (node as usize) < flux.len()),
            "a PIC link names a missing hierarchy node"
        );
        let link_count = bake.link_nodes.len();
        let narrow_link_nodes = if bake.projected_bands > 0 && flux.len() <= 1 << 16 {
            std::mem::take(&mut bake.link_nodes)
                .into_iter()
                .map(|node| node as u16)
                .collect()
        } else {
            Vec::new()
        };
        let mut technique = Pic {
            narrow_link_nodes,
            link_count,
            surfel_taps: Vec::new(),
            hidden_tap_receivers: Vec::new(),
            hidden_tap_taps: Vec::new(),
            hidden_tap_index: Vec::new(),
            shown_receiver: Vec::new(),
            shows_hidden_taps: Vec::new(),
            surfel_basis,
            surfel_area_light: vec![Vec3::ZERO; surfels.len()],
            surfel_direct: vec![Rgb::ZERO; surfels.len()],
            surfel_static: Default::default(),
            surfel_indirect: vec![Vec3::ZERO; surfels.len()],
            cosine_factors,
            flux,
            cache_sh: vec![0.0; bake.cache_count() * stride],
            stride,
            pull_subtrees: Vec::new(),
            pull_top: Vec::new(),
            receiver_values: vec![Rgb::ZERO; context.atlas.receivers.len()],
            timings: StageTimings::default(),
            last_frame: LastFrame::default(),
            updates: 0,
            resting: SettlingPasses::default(),
            settled: false,
            lights: Vec::new(),
            near_light: NearLightCaches::default(),
            cache_scales: Vec::new(),
            cache_of_texel,
            own_atlas,
            final_gather: FinalGather::build(
                &context,
                settings.final_gather,
                bake.caches.lightmap_count,
                true,
            ),
            context,
            settings,
            bake,
        };
        technique.surfel_taps = (0..technique.bake.surfels.len())
            .into_par_iter()
            .map(|index| {
                let surfels = &technique.bake.surfels;
                let taps =
                    technique.lightmap_taps(surfels.triangles[index], surfels.barycentrics[index]);
                technique
                    .visible_taps(taps, surfels.positions[index], surfels.normals[index])
                    .unwrap_or(taps)
            })
            .collect();
        technique.find_hidden_taps();
        // The link scales' uniform pass pulls flux up the tree, and must
        // see the links alone: the pull schedule first, the near-light
        // samples after, and the area lights' settling on scaled links.
        let (subtrees, top) = technique
            .bake
            .hierarchy
            .pull_schedule(4 * rayon::current_num_threads());
        technique.pull_subtrees = subtrees;
        technique.pull_top = top;
        if technique.settings.link_normalisation {
            technique.cache_scales = technique.link_scales();
        }
        let lightmap_caches = technique.bake.caches.lightmap_count;
        technique.near_light = NearLightCaches::build(
            &technique.context,
            (
                &technique.bake.caches.positions[..lightmap_caches],
                &technique.bake.caches.normals[..lightmap_caches],
            ),
            (
                &technique.bake.surfels.triangles,
                &technique.bake.surfels.positions,
            ),
            (technique.settings.bands, technique.settings.chroma_bands),
            &technique.cosine_factors,
        );
        technique.settle_area_lights();
        Ok(technique)
    }

    /// Each lightmap cache's scale from its links' light under a uniform
    /// radiosity of one and the share of its view that meets geometry.
    /// Runs before the near-light samples, which are not links.
    fn link_scales(&mut self) -> Vec<f32> {
        let start = Instant::now();
        let linked = self.light_under_uniform_radiosity();
        let caches = &self.bake.caches;
        let count = caches.lightmap_count;
        let scales = normalisation::scales(
            &self.context,
            &caches.positions[..count],
            &caches.normals[..count],
            &linked,
        );
        normalisation::log_scales(&scales, start.elapsed());
        scales
    }

    /// What each lightmap cache's links gather, facing its own normal, when
    /// every surfel's radiosity is one: a cache-lighting pass, so the same
    /// kernels and scales as a frame. Leaves the caches dark.
    fn light_under_uniform_radiosity(&mut self) -> Vec<f32> {
        // YCoCg: luma one, no chroma.
        let uniform = vec![Vec3::X; self.bake.surfels.len()];
        self.light_caches_from_leaves(&uniform);
        let caches = &self.bake.caches;
        // Luma (YCoCg's first channel): the flux has no chroma.
        let linked = (0..caches.lightmap_count)
            .into_par_iter()
            .map(|cache| {
                let taps = [(cache as u32, 1.0)];
                self.lookup(&taps, caches.normals[cache], &self.cosine_factors)
                    .x
            })
            .collect();
        self.cache_sh.fill(0.0);
        linked
    }

    /// A pass at load: every surfel's flux from `leaf_flux` (YCoCg, in
    /// surfel-area units), pulled up the tree into the caches. The first
    /// update sets every leaf again and pulls, so the flux left behind is
    /// never read.
    fn light_caches_from_leaves(&mut self, leaf_flux: &[Vec3]) {
        self.flux[..leaf_flux.len()].copy_from_slice(leaf_flux);
        self.pull();
        self.light_caches();
    }

    fn atlas(&self) -> &Atlas {
        self.own_atlas.as_ref().unwrap_or(&self.context.atlas)
    }

    /// The four lightmap caches around a point and their bilinear weights
    /// (empty texels dropped, the rest renormalised).
    fn lightmap_taps(&self, triangle: u32, barycentric: Vec2) -> [(u32, f32); 4] {
        let mut taps = [(NO_CACHE, 0.0f32); 4];
        let mut total = 0.0;
        for (slot, (texel, weight)) in self
            .atlas()
            .bilinear_texels(triangle, barycentric)
            .into_iter()
            .enumerate()
        {
            let cache = self.cache_of_texel[texel];
            if cache != NO_CACHE && weight > 0.0 {
                taps[slot] = (cache, weight);
                total += weight;
            }
        }
        if total > 0.0 {
            for tap in &mut taps {
                tap.1 /= total;
            }
        }
        taps
    }

    /// The taps of `taps` whose caches a point sees, renormalised; `None`
    /// when it sees all of them or none (then the bilinear blend is all
    /// there is). The cache atlas's texels are about a metre wide on a
    /// large scene, and a texel's cache can stand on the other side of
    /// whatever meets its surface: a wall triangle that runs up past a
    /// roof into a closed attic, a floor that runs on under a wall into
    /// the next room. Without this test the attic's walls blend in the
    /// sunlit court's caches (Sponza: attic walls 2.9x the path tracer's
    /// light, 62 % of PIC high's squared lightmap error).
    fn visible_taps(
        &self,
        taps: [(u32, f32); 4],
        position: Vec3,
        normal: Vec3,
    ) -> Option<[(u32, f32); 4]> {
        if !self.settings.cache_visibility {
            return None;
        }
        // Both ends stand a tenth of a cache texel off their surfaces:
        // a ray that grazes its own surface is stopped by any moulding or
        // bump along it and would drop a cache that the point sees (on
        // Sponza's pillars that cost 0.4 points of visible-lightmap error
        // with the links' 4-epsilon lift, nothing with a tenth of a texel),
        // while a roof or a wall between them still stops it.
        let lift = (0.1 * self.atlas().metres_per_texel)
            .max(4.0 * relight_trace::direct::ray_epsilon_for(&self.context.bvh));
        let origin = position + normal * lift;
        let caches = &self.bake.caches;
        let mut kept = [(NO_CACHE, 0.0f32); 4];
        let (mut total, mut hidden) = (0.0, false);
        for (slot, &(cache, weight)) in taps.iter().enumerate() {
            if cache == NO_CACHE || weight <= 0.0 {
                continue;
            }
            let cache = cache as usize;
            let target = caches.positions[cache] + caches.normals[cache] * lift;
            let ray = relight_trace::Ray {
                origin,
                direction: target - origin,
                t_max: 1.0,
            };
            if self.context.bvh.occluded(&ray) {
                hidden = true;
            } else {
                kept[slot] = (cache as u32, weight);
                total += weight;
            }
        }
        if !hidden || total <= 0.0 {
            return None;
        }
        for tap in &mut kept {
            tap.1 /= total;
        }
        Some(kept)
    }

    /// Tests every receiver's taps once, at load.
    fn find_hidden_taps(&mut self) {
        let receivers = &self.context.atlas.receivers;
        let found: Vec<Option<[(u32, f32); 4]>> = (0..receivers.len())
            .into_par_iter()
            .map(|index| {
                let taps =
                    self.lightmap_taps(receivers.triangles[index], receivers.barycentrics[index]);
                self.visible_taps(taps, receivers.positions[index], receivers.normals[index])
            })
            .collect();
        let mut index_of = vec![NO_CACHE; receivers.len()];
        for (receiver, taps) in found.into_iter().enumerate() {
            if let Some(taps) = taps {
                index_of[receiver] = self.hidden_tap_receivers.len() as u32;
                self.hidden_tap_receivers.push(receiver as u32);
                self.hidden_tap_taps.push(taps);
            }
        }
        if !self.hidden_tap_receivers.is_empty() {
            self.shown_receiver = self.context.atlas.dilated_receiver_of_texel();
            self.shows_hidden_taps = self
                .shown_receiver
                .iter()
                .map(|&receiver| {
                    index_of
                        .get(receiver as usize)
                        .is_some_and(|&hidden| hidden != NO_CACHE)
                })
                .collect();
            self.hidden_tap_index = index_of;
        }
    }

    /// The bilinear blend of the receivers' values at a point, when the
    /// scene atlas's footprint there touches a texel whose receiver drops
    /// hidden caches; `None` elsewhere. One footprint serves the test and
    /// the blend: this runs per shaded pixel.
    fn receivers_where_taps_hide(&self, triangle: u32, barycentric: Vec2) -> Option<Rgb> {
        if self.shows_hidden_taps.is_empty() {
            return None;
        }
        let footprint = self.context.atlas.bilinear_texels(triangle, barycentric);
        if !footprint
            .iter()
            .any(|&(texel, weight)| weight > 0.0 && self.shows_hidden_taps[texel])
        {
            return None;
        }
        let value = |texel: usize| match self.shown_receiver[texel] {
            u32::MAX => Rgb::ZERO,
            receiver => self.receiver_values[receiver as usize],
        };
        Some(
            footprint
                .iter()
                .map(|&(texel, weight)| value(texel) * weight)
                .sum(),
        )
    }

    /// Irradiance (YCoCg) of `taps` for a surface whose A_l Y_lm(normal)
    /// is `basis`.
    fn irradiance_from_taps(&self, taps: &[(u32, f32)], basis: &[f32]) -> Vec3 {
        // Four taps (the lightmap's) and a common row length take the
        // branch-free path that the surfel feedback uses too.
        if let Ok(four) = <&[(u32, f32); 4]>::try_from(taps) {
            match self.stride {
                12 => return self.irradiance_from_four::<12>(four, basis),
                17 => return self.irradiance_from_four::<17>(four, basis),
                24 => return self.irradiance_from_four::<24>(four, basis),
                27 => return self.irradiance_from_four::<27>(four, basis),
                34 => return self.irradiance_from_four::<34>(four, basis),
                48 => return self.irradiance_from_four::<48>(four, basis),
                _ => {}
            }
        }
        let luma = self.settings.bands * self.settings.bands;
        let chroma = self.settings.chroma_bands * self.settings.chroma_bands;
        // Blend the taps' rows first, then one dot product per channel:
        // the blend has no chain between coefficients (it vectorises and
        // its loads overlap), where a dot product per tap chained every
        // add through one accumulator.
        let mut blended = [0.0f32; 3 * sh::MAX_BANDS * sh::MAX_BANDS];
        let blended = &mut blended[..self.stride];
        for &(cache, weight) in taps {
            if cache == NO_CACHE {
                continue;
            }
            let start = cache as usize * self.stride;
            let row = &self.cache_sh[start..start + self.stride];
            for (sum, value) in blended.iter_mut().zip(row) {
                *sum += weight * value;
            }
        }
        let (luma_row, chroma_rows) = blended.split_at(luma);
        Vec3::new(
            dot(luma_row, &basis[..luma]),
            dot(&chroma_rows[..chroma], &basis[..chroma]),
            dot(&chroma_rows[chroma..2 * chroma], &basis[..chroma]),
        )
    }

    /// Irradiance-style lookup of `taps` (YCoCg) with the band-weighted
    /// basis `factors[l] * Y_lm(direction)`. Shading calls this per pixel,
    /// hence the inlined closed form kept in registers for the presets'
    /// bands (the general form's call, copy and 256-byte return took a
    /// fifth of the shading time).
    #[inline]
    fn lookup(&self, taps: &[(u32, f32)], direction: Vec3, factors: &[f32; sh::MAX_BANDS]) -> Vec3 {
        if self.settings.bands <= 4 {
            let basis = sh::evaluate_four_bands_filtered(direction, factors);
            self.irradiance_from_taps(taps, &basis)
        } else {
            let mut basis = [0.0f32; 64];
            sh::evaluate_filtered(direction, self.settings.bands, factors, &mut basis);
            self.irradiance_from_taps(taps, &basis)
        }
    }

    /// The light of emissive surfels, through the links, at every surfel:
    /// computed once, as emission does not change.
    fn settle_area_lights(&mut self) {
        let surfels = &self.bake.surfels;
        if !self.settings.area_lights_through_links
            || surfels.emission.iter().all(|e| *e == Rgb::ZERO)
        {
            return;
        }
        // Radiant exitance pi L_e per unit area: flux in surfel-area units.
        let exitance: Vec<Vec3> = surfels
            .emission
            .iter()
            .map(|&emission| rgb_to_ycocg(emission * PI))
            .collect();
        self.light_caches_from_leaves(&exitance);
        let mut area_light = std::mem::take(&mut self.surfel_area_light);
        self.feedback_irradiance(&mut area_light);
        self.surfel_area_light = area_light;
        self.cache_sh.fill(0.0);
    }

    /// Irradiance (YCoCg) at every surfel from the current caches, into
    /// `out` (one per surfel).
    fn feedback_irradiance(&self, out: &mut [Vec3]) {
        // The strides of 2, 3 and 4 bands, in RGB mode and with chroma one
        // or two bands below luma.
        match self.stride {
            12 => return self.feedback_irradiance_fixed::<12>(out),
            17 => return self.feedback_irradiance_fixed::<17>(out),
            24 => return self.feedback_irradiance_fixed::<24>(out),
            27 => return self.feedback_irradiance_fixed::<27>(out),
            34 => return self.feedback_irradiance_fixed::<34>(out),
            48 => return self.feedback_irradiance_fixed::<48>(out),
            _ => {}
        }
        let coefficients = self.settings.bands * self.settings.bands;
        out.par_iter_mut().enumerate().for_each(|(index, value)| {
            *value = self.irradiance_from_taps(
                &self.surfel_taps[index],
                &self.surfel_basis[index * coefficients..(index + 1) * coefficients],
            );
        });
    }

    /// `feedback_irradiance` for a cache row of `STRIDE` floats, once per
    /// surfel per frame, in AVX2 where the CPU has it.
    fn feedback_irradiance_fixed<const STRIDE: usize>(&self, out: &mut [Vec3]) {
        const SURFELS_PER_TASK: usize = 1024;
        let wide = kernels_available();
        out.par_chunks_mut(SURFELS_PER_TASK)
            .enumerate()
            .for_each(|(chunk, values)| {
                let first = chunk * SURFELS_PER_TASK;
                if wide {
                    // SAFETY: `kernels_available` checked the CPU.
                    unsafe { self.feedback_chunk_avx2::<STRIDE>(first, values) };
                } else {
                    self.feedback_chunk::<STRIDE>(first, values);
                }
            });
    }

    #[cfg_attr(target_arch = "x86_64", target_feature(enable = "avx2,fma"))]
    unsafe fn feedback_chunk_avx2<const STRIDE: usize>(&self, first: usize, out: &mut [Vec3]) {
        self.feedback_chunk::<STRIDE>(first, out)
    }

    /// Feedback irradiance of the surfels from `first` on, one per `out`.
    #[inline(always)]
    fn feedback_chunk<const STRIDE: usize>(&self, first: usize, out: &mut [Vec3]) {
        let luma = self.settings.bands * self.settings.bands;
        for (offset, value) in out.iter_mut().enumerate() {
            let index = first + offset;
            *value = self.irradiance_from_four::<STRIDE>(
                &self.surfel_taps[index],
                &self.surfel_basis[index * luma..(index + 1) * luma],
            );
        }
    }

    /// Irradiance (YCoCg) of four taps on cache rows of `STRIDE` floats for
    /// a surface whose band-weighted basis is `basis`: the taps blend in
    /// one pass with no branch and no cleared scratch (a missing tap reads
    /// a zero row with weight 0), then one dot product per channel.
    #[inline(always)]
    fn irradiance_from_four<const STRIDE: usize>(
        &self,
        taps: &[(u32, f32); 4],
        basis: &[f32],
    ) -> Vec3 {
        let luma = self.settings.bands * self.settings.bands;
        let chroma = self.settings.chroma_bands * self.settings.chroma_bands;
        let zero = [0.0f32; STRIDE];
        let row = |(cache, weight): (u32, f32)| -> (&[f32; STRIDE], f32) {
            if cache == NO_CACHE {
                return (&zero, 0.0);
            }
            let start = cache as usize * STRIDE;
            (
                self.cache_sh[start..start + STRIDE].try_into().unwrap(),
                weight,
            )
        };
        let [(r0, w0), (r1, w1), (r2, w2), (r3, w3)] = taps.map(row);
        // A plain loop, not `array::from_fn`, whose closure is not inlined
        // into the AVX2 instance of the feedback.
        let mut blended = [0.0f32; STRIDE];
        for (k, sum) in blended.iter_mut().enumerate() {
            *sum = w0 * r0[k] + w1 * r1[k] + w2 * r2[k] + w3 * r3[k];
        }
        let (luma_row, chroma_rows) = blended.split_at(luma);
        Vec3::new(
            dot(luma_row, &basis[..luma]),
            dot(&chroma_rows[..chroma], &basis[..chroma]),
            dot(&chroma_rows[chroma..2 * chroma], &basis[..chroma]),
        )
    }

    fn direct_light(&mut self, frame: &Frame) {
        let mut direct = self.context.direct();
        if self.settings.area_lights_through_links {
            direct.settings.area_light_samples = 0;
        }
        let surfels = &self.bake.surfels;
        self.surfel_static.irradiance_batch_over_footprints(
            &direct,
            frame.lights,
            &surfels.positions,
            &surfels.normals,
            // A surfel beside a lamp stands for its patch, not the 1/d^2
            // at its centre: its direct light is the patch's mean.
            Footprints::All(surfels.area),
            &mut self.surfel_direct,
        );
    }

    /// Leaf flux: albedo x (direct + area lights + last indirect).
    fn light_surfels(&mut self, feedback: bool) {
        let mut indirect_buffer = std::mem::take(&mut self.surfel_indirect);
        if feedback {
            self.feedback_irradiance(&mut indirect_buffer);
        }
        let indirect = feedback.then_some(&indirect_buffer);
        let surfels = &self.bake.surfels;
        let direct = &self.surfel_direct;
        let area = &self.surfel_area_light;
        let (context, final_gather) = (&self.context, &self.final_gather);
        let near_light = &self.near_light;
        self.flux[..surfels.len()]
            .par_iter_mut()
            .enumerate()
            .for_each(|(index, flux)| {
                // The caches see a hot surfel's direct light, emissive
                // surfaces' included, through the near-light samples.
                let mut irradiance = if near_light.is_hot(index) {
                    Rgb::ZERO
                } else {
                    direct[index] + ycocg_to_rgb(area[index])
                };
                if let Some(indirect) = &indirect {
                    // The near field the caches miss reaches the receivers
                    // through the final gather; without it here the surfels
                    // by a wall or in a corner reflect too little, and each
                    // bounce loses more (living room, PIC high: 0.97x of
                    // the path tracer's first bounce, 0.85x of all).
                    let near_field = final_gather.correction(
                        context,
                        surfels.triangles[index],
                        surfels.barycentrics[index],
                    );
                    irradiance += (ycocg_to_rgb(indirect[index]) + near_field).max(Rgb::ZERO);
                }
                *flux = rgb_to_ycocg(surfels.albedos[index] * irradiance);
            });
        self.surfel_indirect = indirect_buffer;
    }

    /// Flux up the tree: disjoint subtrees in parallel, then the nodes
    /// above them.
    fn pull(&mut self) {
        let hierarchy = &self.bake.hierarchy;
        let leaf_count = hierarchy.leaf_count as usize;
        let flux = SharedFlux(self.flux.as_mut_ptr());
        self.pull_subtrees.par_iter().for_each(|&root| {
            if hierarchy.is_leaf(root) {
                return;
            }
            // A subtree's internal nodes are contiguous in post order.
            let internal = hierarchy.leaves[root as usize] as usize - 1;
            let start = root as usize + 1 - internal;
            for node in start..=root as usize {
                let [left, right] = hierarchy.children[node - leaf_count];
                // SAFETY: subtrees are disjoint, so each thread writes only
                // its own subtree's nodes and reads only its own children.
                unsafe {
                    let base = flux.pointer();
                    let value = *base.add(left as usize) + *base.add(right as usize);
                    *base.add(node) = value;
                }
            }
        });
        for &node in &self.pull_top {
            let [left, right] = hierarchy.children[node as usize - leaf_count];
            self.flux[node as usize] = self.flux[left as usize] + self.flux[right as usize];
        }
    }

    fn light_caches(&mut self) {
        let bake = &self.bake;
        let flux = &self.flux;
        let links = bake.links_per_cache;
        let bands = self.settings.bands;
        let chroma = self.settings.chroma_bands;
        let luma_count = bands * bands;
        let chroma_count = chroma * chroma;
        let inverse_scale = 1.0 / bake.factor_scale;
        let stride = self.stride;
        let fast = bands <= 4 && bake.projected_bands == 0 && kernels_available();
        let wide_kernel = projected_kernel::<u32>(bands);
        let narrow_kernel = projected_kernel::<u16>(bands);
        let narrow_nodes = &self.narrow_link_nodes;
        let near_light = &self.near_light;
        let cache_scales = &self.cache_scales;
        self.cache_sh
            .par_chunks_mut(stride * 64)
            .enumerate()
            // Only the runtime-projection kernel uses a scratch: made once
            // per rayon job, and only when needed.
            .for_each_init(
                || None::<LinkScratch>,
                |scratch, (chunk, rows)| {
                    for (offset, row) in rows.chunks_exact_mut(stride).enumerate() {
                        let cache = chunk * 64 + offset;
                        let range = cache * links..(cache + 1) * links;
                        let (luma, rest) = row.split_at_mut(luma_count);
                        let (co, cg) = rest.split_at_mut(chroma_count);
                        if bake.projected_bands > 0 {
                            let count = bands * bands;
                            let coefficients =
                                &bake.link_coefficients[range.start * count..range.end * count];
                            // SAFETY: `projected_kernel` picks the vector kernel
                            // only where the CPU has it; `Pic::new` checked that
                            // every link node indexes `flux`.
                            unsafe {
                                if narrow_nodes.is_empty() {
                                    wide_kernel(
                                        coefficients,
                                        &bake.link_nodes[range],
                                        flux,
                                        count,
                                        chroma_count,
                                        luma,
                                        co,
                                        cg,
                                    )
                                } else {
                                    narrow_kernel(
                                        coefficients,
                                        &narrow_nodes[range],
                                        flux,
                                        count,
                                        chroma_count,
                                        luma,
                                        co,
                                        cg,
                                    )
                                }
                            };
                        } else {
                            let slice = LinkSlice {
                                nodes: &bake.link_nodes[range.clone()],
                                factors: &bake.link_factors[range.clone()],
                                cones: &bake.link_cones[range.clone()],
                                directions: &bake.link_directions[range],
                            };
                            if fast {
                                let scratch = scratch.get_or_insert_with(LinkScratch::default);
                                // SAFETY: `kernels_available` checked the CPU and
                                // `Pic::new` the link nodes.
                                unsafe {
                                    light_cache_avx2(
                                        &slice, flux, scratch, bands, chroma, luma, co, cg,
                                    )
                                };
                            } else {
                                kernels::light_cache_general(
                                    &slice, flux, bands, chroma, luma, co, cg,
                                );
                            }
                        }
                        let scale = inverse_scale * cache_scales.get(cache).copied().unwrap_or(1.0);
                        for value in row.iter_mut() {
                            *value *= scale;
                        }
                        if !near_light.is_empty() {
                            let (luma, rest) = row.split_at_mut(luma_count);
                            let (co, cg) = rest.split_at_mut(chroma_count);
                            near_light.add_to_cache(cache, luma, co, cg);
                        }
                    }
                },
            );
    }

    /// The links' bytes as held at run time (nodes possibly narrowed).
    fn link_bytes(&self) -> usize {
        self.bake.link_bytes() + self.narrow_link_nodes.len() * 2
    }

    /// Diffuse irradiance (RGB) at a point of the static scene.
    /// The caches' light at lightmap receiver `index`.
    fn receiver_cached_irradiance(&self, index: u32) -> Rgb {
        let receivers = &self.context.atlas.receivers;
        let index = index as usize;
        match self.hidden_tap_index.get(index) {
            Some(&hidden) if hidden != NO_CACHE => self.irradiance_of(
                &self.hidden_tap_taps[hidden as usize],
                receivers.normals[index],
            ),
            _ => self.surface_irradiance(
                receivers.triangles[index],
                receivers.barycentrics[index],
                receivers.normals[index],
            ),
        }
    }

    /// Runs the final gather over the caches' light (hits reflect direct
    /// light alone with one bounce), on hits lit by this frame's
    /// `FinalGather::light_hits`.
    fn gather_near_field(&mut self) {
        if self.final_gather.is_empty() {
            return;
        }
        let mut final_gather = std::mem::take(&mut self.final_gather);
        let values = &self.receiver_values;
        final_gather.gather(
            |receiver| values[receiver as usize],
            self.settings.bounces > 1,
        );
        self.final_gather = final_gather;
    }

    /// Sets [`Self::receiver_values`] to every receiver's light from this
    /// pass's caches.
    fn look_up_receivers(&mut self) {
        let mut values = std::mem::take(&mut self.receiver_values);
        values
            .par_iter_mut()
            .with_min_len(256)
            .enumerate()
            .for_each(|(index, value)| *value = self.receiver_cached_irradiance(index as u32));
        self.receiver_values = values;
    }

    fn surface_irradiance(&self, triangle: u32, barycentric: Vec2, normal: Vec3) -> Rgb {
        self.irradiance_of(&self.lightmap_taps(triangle, barycentric), normal)
    }

    /// RGB irradiance of the caches `taps` blend for a surface facing
    /// `normal`.
    fn irradiance_of(&self, taps: &[(u32, f32)], normal: Vec3) -> Rgb {
        ycocg_to_rgb(self.lookup(taps, normal, &self.cosine_factors)).max(Rgb::ZERO)
    }

    /// The eight grid caches around `position` (culled ones dropped).
    fn grid_taps(&self, position: Vec3) -> [(u32, f32); 8] {
        let caches = &self.bake.caches;
        let mut taps = [(NO_CACHE, 0.0f32); 8];
        if caches.grid_cache.is_empty() {
            return taps;
        }
        let mut total = 0.0;
        for (slot, (point, weight)) in caches.grid.corners(position).into_iter().enumerate() {
            let cache = caches.grid_cache[point];
            if cache != NO_CACHE && weight > 0.0 {
                taps[slot] = (cache, weight);
                total += weight;
            }
        }
        if total > 0.0 {
            for tap in &mut taps {
                tap.1 /= total;
            }
        }
        taps
    }
}

/// The flux buffer shared by the pull's threads.
#[derive(Clone, Copy)]
struct SharedFlux(*mut Vec3);

impl SharedFlux {
    fn pointer(&self) -> *mut Vec3 {
        self.0
    }
}
// SAFETY: the pull hands each thread a disjoint subtree.
unsafe impl Send for SharedFlux {}
unsafe impl Sync for SharedFlux {}

fn kernels_available() -> bool {
    #[cfg(target_arch = "x86_64")]
    {
        std::arch::is_x86_feature_detected!("avx2") && std::arch::is_x86_feature_detected!("fma")
    }
    #[cfg(not(target_arch = "x86_64"))]
    {
        false
    }
}

/// Dot product with four partial sums, so the adds do not wait on each
/// other.
#[inline(always)]
fn dot(a: &[f32], b: &[f32]) -> f32 {
    let mut partial = [0.0f32; 4];
    let chunks = a.len() / 4 * 4;
    for (a, b) in a[..chunks].chunks_exact(4).zip(b[..chunks].chunks_exact(4)) {
        for lane in 0..4 {
            partial[lane] += a[lane] * b[lane];
        }
    }
    let mut total = (partial[0] + partial[1]) + (partial[2] + partial[3]);
    for (a, b) in a[chunks..].iter().zip(&b[chunks..]) {
        total += a * b;
    }
    total
}

/// The lane kernel compiled for AVX2 and FMA, one instance per band pair.
///
/// # Safety
/// AVX2 and FMA must be available, and every node in `links.nodes` must
/// index `flux` (see [`kernels::light_cache`]).
#[cfg_attr(target_arch = "x86_64", target_feature(enable = "avx2,fma"))]
#[allow(clippy::too_many_arguments)]
unsafe fn light_cache_avx2(
    links: &LinkSlice,
    flux: &[Vec3],
    scratch: &mut LinkScratch,
    bands: usize,
    chroma: usize,
    luma: &mut [f32],
    co: &mut [f32],
    cg: &mut [f32],
) {
    match (bands, chroma) {
        (2, 2) => kernels::light_cache::<2, 2>(links, flux, scratch, luma, co, cg),
        (2, _) => kernels::light_cache::<2, 1>(links, flux, scratch, luma, co, cg),
        (3, 3) => kernels::light_cache::<3, 3>(links, flux, scratch, luma, co, cg),
        (3, 2) => kernels::light_cache::<3, 2>(links, flux, scratch, luma, co, cg),
        (3, _) => kernels::light_cache::<3, 1>(links, flux, scratch, luma, co, cg),
        (4, 4) => kernels::light_cache::<4, 4>(links, flux, scratch, luma, co, cg),
        (4, 3) => kernels::light_cache::<4, 3>(links, flux, scratch, luma, co, cg),
        (4, 2) => kernels::light_cache::<4, 2>(links, flux, scratch, luma, co, cg),
        (4, _) => kernels::light_cache::<4, 1>(links, flux, scratch, luma, co, cg),
        _ => kernels::light_cache_general(links, flux, bands, chroma, luma, co, cg),
    }
}

/// The signature both projected-link kernels share.
type ProjectedKernel<Node> =
    unsafe fn(&[u16], &[Node], &[Vec3], usize, usize, &mut [f32], &mut [f32], &mut [f32]);

/// Projected links: coefficients times flux, `count` coefficients per link.
#[allow(clippy::too_many_arguments)]
fn light_cache_projected<Node: Copy + Into<u32>>(
    coefficients: &[u16],
    nodes: &[Node],
    flux: &[Vec3],
    count: usize,
    chroma_count: usize,
    luma: &mut [f32],
    co: &mut [f32],
    cg: &mut [f32],
) {
    luma.fill(0.0);
    co.fill(0.0);
    cg.fill(0.0);
    for (link, &node) in nodes.iter().enumerate() {
        let node_flux = flux[node.into() as usize];
        for (index, &bits) in coefficients[link * count..(link + 1) * count]
            .iter()
            .enumerate()
        {
            let value = half::f16::from_bits(bits).to_f32();
            luma[index] += value * node_flux.x;
            if index < chroma_count {
                co[index] += value * node_flux.y;
                cg[index] += value * node_flux.z;
            }
        }
    }
}

/// The projected-link kernel for `bands`: F16C and AVX2 where the CPU has
/// them (up to 16 coefficients), the scalar loop elsewhere.
fn projected_kernel<Node: Copy + Into<u32>>(bands: usize) -> ProjectedKernel<Node> {
    #[cfg(target_arch = "x86_64")]
    if bands <= 4 && projected_kernel_available() {
        return light_cache_projected_avx2;
    }
    let _ = bands;
    light_cache_projected
}

#[cfg(target_arch = "x86_64")]
fn projected_kernel_available() -> bool {
    kernels_available() && std::arch::is_x86_feature_detected!("f16c")
}

/// `light_cache_projected` for up to 16 coefficients: each link's f16 row
/// converts in one or two F16C instructions and meets its flux in two
/// fused multiply-adds per channel, so the loop runs at the speed the
/// links stream in (22 bytes a link at 3 bands). A row is read as 16
/// halves whatever `count` is: lanes past `count` hold the next link's
/// coefficients and are never stored; the last rows, where 16 halves
/// would run past the slice, are copied into a zero-padded row first
/// (converting them one half at a time in software took a tenth of the
/// kernel's time at 128 links a cache).
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2,fma,f16c")]
#[allow(clippy::too_many_arguments)]
unsafe fn light_cache_projected_avx2<Node: Copy + Into<u32>>(
    coefficients: &[u16],
    nodes: &[Node],
    flux: &[Vec3],
    count: usize,
    chroma_count: usize,
    luma: &mut [f32],
    co: &mut [f32],
    cg: &mut [f32],
) {
    use std::arch::x86_64::*;
    debug_assert!(count <= 16 && chroma_count <= count);
    debug_assert!(nodes
        .iter()
        .all(|&node| (node.into() as usize) < flux.len()));
    assert_eq!(coefficients.len(), nodes.len() * count);
    const PREFETCH_AHEAD: usize = 16;
    let vector_links = if coefficients.len() >= 16 {
        nodes.len().min((coefficients.len() - 16) / count + 1)
    } else {
        0
    };
    let mut sums = [_mm256_setzero_ps(); 6];
    let mut padded = [0u16; 16];
    for link in 0..nodes.len() {
        if let Some(&ahead) = nodes.get(link + PREFETCH_AHEAD) {
            _mm_prefetch(
                flux.as_ptr().wrapping_add(ahead.into() as usize) as *const i8,
                _MM_HINT_T0,
            );
        }
        let row = if link < vector_links {
            coefficients.as_ptr().add(link * count)
        } else {
            padded[..count].copy_from_slice(&coefficients[link * count..(link + 1) * count]);
            padded.as_ptr()
        };
        let low = _mm256_cvtph_ps(_mm_loadu_si128(row as *const __m128i));
        let high = _mm256_cvtph_ps(_mm_loadu_si128(row.add(8) as *const __m128i));
        let node_flux = flux.get_unchecked((*nodes.get_unchecked(link)).into() as usize);
        let y = _mm256_set1_ps(node_flux.x);
        let co_flux = _mm256_set1_ps(node_flux.y);
        let cg_flux = _mm256_set1_ps(node_flux.z);
        sums[0] = _mm256_fmadd_ps(low, y, sums[0]);
        sums[1] = _mm256_fmadd_ps(high, y, sums[1]);
        sums[2] = _mm256_fmadd_ps(low, co_flux, sums[2]);
        sums[3] = _mm256_fmadd_ps(high, co_flux, sums[3]);
        sums[4] = _mm256_fmadd_ps(low, cg_flux, sums[4]);
        sums[5] = _mm256_fmadd_ps(high, cg_flux, sums[5]);
    }
    let mut lanes = [[0.0f32; 16]; 3];
    for (channel, out) in lanes.iter_mut().enumerate() {
        _mm256_storeu_ps(out.as_mut_ptr(), sums[2 * channel]);
        _mm256_storeu_ps(out.as_mut_ptr().add(8), sums[2 * channel + 1]);
    }
    luma[..count].copy_from_slice(&lanes[0][..count]);
    co[..chroma_count].copy_from_slice(&lanes[1][..chroma_count]);
    cg[..chroma_count].copy_from_slice(&lanes[2][..chroma_count]);
}

impl Technique for Pic {
    fn name(&self) -> &'static str {
        "pic"
    }

    fn indirect_bounces(&self) -> Option<u32> {
        (self.settings.bounces == 1).then_some(1)
    }

    fn update(&mut self, frame: &Frame) -> Result<(), TechniqueError> {
        let start = Instant::now();
        let repeated = self.last_frame.repeats(frame, FrameReads::default());
        if repeated && self.settled() {
            self.timings.skip(start);
            return Ok(());
        }
        let first = self.updates == 0;
        let mut settling = SettlingPasses::for_update(self.settings.bounces, first);
        let feedback = self.settings.bounces > 1;
        self.lights.clear();
        self.lights.extend_from_slice(frame.lights);
        let mut surfel_time = Duration::ZERO;
        let mut pull_time = Duration::ZERO;
        let mut cache_time = Duration::ZERO;
        let mut receiver_time = Duration::ZERO;
        let start = Instant::now();
        self.direct_light(frame);
        self.near_light.light(&self.context, frame.lights);
        surfel_time += start.elapsed();
        let start = Instant::now();
        self.final_gather.light_hits(&self.context, &self.lights);
        let mut gather_time = start.elapsed();
        for pass in 0.. {
            let start = Instant::now();
            self.light_surfels(feedback && (pass > 0 || self.updates > 0));
            surfel_time += start.elapsed();
            let start = Instant::now();
            self.pull();
            pull_time += start.elapsed();
            let start = Instant::now();
            self.light_caches();
            cache_time += start.elapsed();
            // Each cache's luma (its constant SH term) grows by the bounce
            // each pass adds.
            let (cache_sh, stride) = (&self.cache_sh, self.stride);
            let measure =
                |values: &mut Vec<f32>| values.extend(cache_sh.iter().step_by(stride).copied());
            if !settling.another_pass(measure) {
                break;
            }
            if feedback && !self.final_gather.is_empty() {
                // The next pass's surfels read this pass's near field.
                let start = Instant::now();
                self.look_up_receivers();
                receiver_time += start.elapsed();
                let start = Instant::now();
                self.gather_near_field();
                gather_time += start.elapsed();
            }
        }
        let start = Instant::now();
        self.look_up_receivers();
        receiver_time += start.elapsed();
        let start = Instant::now();
        self.gather_near_field();
        gather_time += start.elapsed();
        let start = Instant::now();
        self.final_gather.apply(&mut self.receiver_values);
        receiver_time += start.elapsed();
        self.timings.clear();
        self.timings.feedback_passes = settling.feedback_passes();
        self.timings.stages.push(("surfel lighting", surfel_time));
        self.timings.stages.push(("pull", pull_time));
        self.timings.stages.push(("cache lighting", cache_time));
        self.timings.stages.push(("receiver values", receiver_time));
        if !self.final_gather.is_empty() {
            self.final_gather
                .push_stages(&mut self.timings, gather_time);
        }
        self.updates += 1;
        // The first update ran its passes until they settled; a later one
        // adds one bounce, and the resting scene's updates go on adding
        // them until the caches' light stops changing.
        self.settled = !feedback || first || {
            if !repeated {
                self.resting = SettlingPasses::at_rest(self.settings.bounces);
            }
            let (cache_sh, stride) = (&self.cache_sh, self.stride);
            !self.resting.another_pass(|values: &mut Vec<f32>| {
                values.extend(cache_sh.iter().step_by(stride).copied())
            })
        };
        Ok(())
    }

    fn settled(&self) -> bool {
        // Under `update_budget` the gather's parts still to refresh change
        // the light too.
        self.settled && self.final_gather.refreshed()
    }

    fn forget_last_frame(&mut self) {
        self.last_frame.forget();
    }

    /// The caches' bilinear light at the point plus the final gather's
    /// correction; where the scene atlas's footprint touches a receiver
    /// that drops hidden caches, the receivers' own values (the lightmap
    /// an engine reads) instead. A correction map added to the per-point
    /// lookup there was wrong within the texel: a cache texel straddling
    /// the corner of two rooms' walls lit the lookup 0.43 beside the
    /// corner and 0.09 a texel on, and the corner receiver's correction
    /// (-0.34), blended onto the dim side, shaded a black strip along it.
    fn indirect_irradiance(&self, point: &SurfacePoint) -> Rgb {
        if let Some(blend) = self.receivers_where_taps_hide(point.triangle, point.barycentric) {
            return blend.max(Rgb::ZERO);
        }
        let cached = self.surface_irradiance(point.triangle, point.barycentric, point.normal);
        let correction =
            self.final_gather
                .correction(&self.context, point.triangle, point.barycentric);
        (cached + correction).max(Rgb::ZERO)
    }

    /// Gathered from the surfaces around the point (each hit's direct
    /// light plus the lightmap caches' indirect light there, none with
    /// `bounces = 1`), or the grid caches' trilinear blend, which crosses
    /// walls: on Sponza's grid of points in space the grid measured 70.6 %
    /// relRMSE.
    fn indirect_irradiance_in_space(&self, position: Vec3, normal: Vec3) -> Rgb {
        if let Some(gather) = &self.settings.space_gather {
            let single_bounce = self.settings.bounces <= 1;
            return gather.irradiance(&self.context, &self.lights, position, normal, |point| {
                if single_bounce {
                    Rgb::ZERO
                } else {
                    self.indirect_irradiance(point)
                }
            });
        }
        self.irradiance_of(&self.grid_taps(position), normal)
    }

    fn glossy_radiance(
        &self,
        point: &SurfacePoint,
        toward_viewer: Vec3,
        exponent: f32,
    ) -> Option<Rgb> {
        if self.settings.specular <= 0.0 || exponent <= 1.0 {
            return None;
        }
        let reflected = (-toward_viewer).reflect(point.normal).normalize_or_zero();
        let taps = self.lightmap_taps(point.triangle, point.barycentric);
        let phong = sh::phong_band_factors(exponent);
        Some(
            ycocg_to_rgb(self.lookup(&taps, reflected, &phong)).max(Rgb::ZERO)
                * self.settings.specular,
        )
    }

    fn receiver_irradiance(&self) -> Option<&[Rgb]> {
        Some(&self.receiver_values)
    }

    fn timings(&self) -> &StageTimings {
        &self.timings
    }

    fn memory(&self) -> Vec<MemoryEntry> {
        let bake = &self.bake;
        let surfels = bake.surfels.len();
        let mut entries = vec![
            MemoryEntry::new(
                "surfels (position, normal, albedo, direct, area light)",
                surfels * (12 * 5),
            ),
            MemoryEntry::new(
                "hierarchy (children, leaf ranges)",
                bake.hierarchy.children.len() * 8 + bake.hierarchy.node_count() * 8,
            ),
            MemoryEntry::new("flux per node", self.flux.len() * 12),
            MemoryEntry::new("receiver values", self.receiver_values.len() * 12),
            MemoryEntry::new(
                if bake.projected_bands > 0 {
                    "links (node + f16 SH)"
                } else {
                    "links (node, f16 factor, f16 cone, octahedral direction: 12 B)"
                },
                self.link_bytes(),
            ),
            MemoryEntry::new(
                "caches (SH, f32; link scales)",
                self.cache_sh.len() * 4 + self.cache_scales.len() * 4,
            ),
            MemoryEntry::new("lightmap cache index", self.cache_of_texel.len() * 4),
            MemoryEntry::new(
                "surfel lightmap taps and basis",
                self.surfel_taps.len() * 32 + self.surfel_basis.len() * 4,
            ),
        ];
        if !self.hidden_tap_receivers.is_empty() {
            entries.push(MemoryEntry::new(
                format!(
                    "receivers with hidden lightmap caches ({}: taps, index, texels showing them)",
                    self.hidden_tap_receivers.len()
                ),
                self.hidden_tap_receivers.len() * (4 + 32)
                    + self.hidden_tap_index.len() * 4
                    + self.shown_receiver.len() * 4
                    + self.shows_hidden_taps.len(),
            ));
        }
        if !self.near_light.is_empty() {
            let (samples, texels, caches) = self.near_light.counts();
            entries.push(MemoryEntry::new(
                format!(
                    "near-light samples ({samples} on {texels} texel sides, seen by {caches} caches)"
                ),
                self.near_light.memory_bytes(),
            ));
        }
        entries.extend(self.final_gather.memory_entry());
        entries
    }

    fn bake_facts(&self) -> Vec<(&'static str, String)> {
        let bake = &self.bake;
        let caches = &bake.caches;
        vec![
            (
                "pic surfels",
                format!(
                    "{} of {:.3e} m^2 each ({} enclosed by geometry dropped)",
                    bake.surfels.len(),
                    bake.surfels.area,
                    bake.enclosed_surfels
                ),
            ),
            (
                "pic hierarchy",
                format!(
                    "{} ({} nodes, depth {})",
                    if bake.hierarchy_builder == 1 { "kd-tree" } else { "agglomerative" },
                    bake.hierarchy.node_count(),
                    bake.hierarchy.depth()
                ),
            ),
            (
                "pic caches",
                format!(
                    "{} lightmap ({} moved out of geometry, {} stuck) + {} grid of {}x{}x{} ({} moved, {} culled)",
                    caches.lightmap_count,
                    caches.moved,
                    caches.stuck,
                    bake.cache_count() - caches.lightmap_count,
                    caches.grid.dims[0],
                    caches.grid.dims[1],
                    caches.grid.dims[2],
                    caches.grid_moved,
                    caches.grid_culled
                ),
            ),
            (
                "pic links",
                format!(
                    "{} per cache, {}, {:.1} bytes each",
                    bake.links_per_cache,
                    if bake.projected_bands > 0 {
                        format!("SH-projected with {} bands", bake.projected_bands)
                    } else {
                        "runtime projection".into()
                    },
                    self.link_bytes() as f64 / self.link_count.max(1) as f64
                ),
            ),
            (
                "pic cache bands",
                format!(
                    "{} luma, {} chroma (baked for; running with {} and {})",
                    bake.cache_bands[0],
                    bake.cache_bands[1],
                    self.settings.bands,
                    self.settings.chroma_bands
                ),
            ),
        ]
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use relight_core::sampling::Pcg32;

    /// One projected-kernel call into fresh luma, Co and Cg rows of 16.
    fn run_projected_kernel<Node: Copy + Into<u32>>(
        kernel: ProjectedKernel<Node>,
        coefficients: &[u16],
        nodes: &[Node],
        flux: &[Vec3],
        count: usize,
        chroma_count: usize,
    ) -> [[f32; 16]; 3] {
        let mut rows = [[0.0f32; 16]; 3];
        let [luma, co, cg] = &mut rows;
        // SAFETY: callers check `projected_kernel_available`; the test's
        // nodes all index `flux`.
        unsafe {
            kernel(
                coefficients,
                nodes,
                flux,
                count,
                chroma_count,
                &mut luma[..count],
                &mut co[..chroma_count],
                &mut cg[..chroma_count],
            )
        };
        rows
    }

    /// Under a uniform radiosity of one, every cache of a closed room
    /// should gather one. The links as baked fall short by the share of
    /// each cache's view their samples miss; normalised, each cache gets
    /// its own view's share, which in a closed room is all of it.
    /// Tolerance: the scales come from the same pass, so only the f32
    /// sums and a cache whose scale was clamped can differ.
    #[test]
    fn normalised_links_gather_a_uniform_radiosity_whole() {
        let context = relight_technique::robustness::closed_grey_room(0.5);
        // The defaults (links projected at run time) and `moderate` (SH
        // links with u16 nodes): the scale follows every kernel.
        for preset in ["", "moderate"] {
            let params = [("preset".to_string(), preset.to_string())];
            let payload =
                relight_technique::robustness::shared_bake(&crate::PicKind, &context, &params);
            let percentiles = |normalised: bool| {
                let mut settings = crate::PicParams::preset(preset)
                    .expect("a preset")
                    .runtime();
                settings.link_normalisation = normalised;
                let bake = PicBake::decode(&payload).expect("the bake decodes");
                let mut pic = Pic::new(context.clone(), bake, settings).expect("PIC loads");
                let lift = context.surface_lift();
                let caches = &pic.bake.caches;
                let visible: Vec<bool> = (0..caches.lightmap_count)
                    .map(|cache| {
                        !context.is_hidden_surface_point(
                            caches.positions[cache],
                            caches.normals[cache],
                            lift,
                        )
                    })
                    .collect();
                let mut light: Vec<f32> = pic
                    .light_under_uniform_radiosity()
                    .into_iter()
                    .zip(&visible)
                    .filter_map(|(light, &visible)| visible.then_some(light))
                    .collect();
                light.sort_unstable_by(f32::total_cmp);
                let at = |share: f64| light[((light.len() - 1) as f64 * share) as usize];
                (at(0.1), at(0.5))
            };
            let (baked_tenth, baked_median) = percentiles(false);
            let (tenth, median) = percentiles(true);
            println!("{preset:?}: 10th percentile and median: baked {baked_tenth:.3}, {baked_median:.3}; normalised {tenth:.3}, {median:.3}");
            assert!(baked_tenth < 0.97, "{preset:?}: {baked_tenth}");
            assert!((tenth - 1.0).abs() < 0.01, "{preset:?}: {tenth}");
            assert!((median - 1.0).abs() < 0.01, "{preset:?}: {median}");
        }
    }

    /// The F16C kernel against the scalar loop, for every row length it
    /// serves, with chroma shorter than luma, and link counts whose last
    /// rows take the scalar tail (fewer than 16 halves left) or where no
    /// row fits 16 halves at all.
    #[test]
    fn projected_kernel_matches_the_scalar_loop() {
        if !projected_kernel_available() {
            return;
        }
        let mut rng = Pcg32::new(5, 0);
        let flux: Vec<Vec3> = (0..40)
            .map(|_| Vec3::new(rng.next_f32(), rng.next_f32() - 0.5, rng.next_f32() - 0.5))
            .collect();
        for (count, chroma_count) in [(4, 4), (9, 9), (9, 4), (16, 16), (16, 9)] {
            for link_count in [1, 2, 3, 17, 64] {
                let nodes: Vec<u32> = (0..link_count).map(|_| rng.next_u32() % 40).collect();
                let coefficients: Vec<u16> = (0..link_count * count)
                    .map(|_| half::f16::from_f32(4.0 * rng.next_f32() - 2.0).to_bits())
                    .collect();
                let fast = run_projected_kernel(
                    light_cache_projected_avx2,
                    &coefficients,
                    &nodes,
                    &flux,
                    count,
                    chroma_count,
                );
                let slow = run_projected_kernel(
                    light_cache_projected,
                    &coefficients,
                    &nodes,
                    &flux,
                    count,
                    chroma_count,
                );
                for (got, want) in fast.iter().flatten().zip(slow.iter().flatten()) {
                    // Same products, summed in another order: f32 rounding of
                    // at most 64 terms of size 2.
                    assert!(
                        (got - want).abs() <= 1e-4,
                        "{count}/{chroma_count}, {link_count} links: {got} vs {want}"
                    );
                }
                // The same links with u16 nodes (small hierarchies) give
                // the same bits as with u32 nodes.
                let narrow: Vec<u16> = nodes.iter().map(|&node| node as u16).collect();
                let narrowed = run_projected_kernel(
                    light_cache_projected_avx2,
                    &coefficients,
                    &narrow,
                    &flux,
                    count,
                    chroma_count,
                );
                assert_eq!(narrowed, fast);
            }
        }
    }
}
