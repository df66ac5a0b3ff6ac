//! SRP: Sparse Radiance Probes (Silvennoinen and Lehtinen, "Real-time
//! Global Illumination by Precomputed Local Reconstruction from Sparse
//! Radiance Probes", 2017, as detailed in Bennett's 2019 thesis, chapters
//! 4 and 5): indirect light at every lightmap texel reconstructed from a
//! few SH radiance probes through precomputed, compressed transport.
//!
//! Data flow. Bake: probes are placed in free space in front of the
//! surfaces that see any geometry, outward-facing ones included (candidates
//! at varied heights above those receivers, no farther out than half a
//! probe spacing beyond the scene's bounds, farthest-point seeds relaxed by
//! Lloyd iterations so they spread through the volume, then topped up where
//! receivers see fewer than `min_probes` within the cut-off radius r;
//! receivers that see only the environment have no indirect light to
//! reconstruct and need none) or read from the scene file's
//! `[srp] probes = [[x, y, z], ...]`. Every receiver (lightmap texel) gets
//! its nearby probes and, by progressive Monte Carlo over cosine-weighted
//! rays from its texel, the transport coefficients alpha_ij of equation
//! 4.12: per sample one primary ray, then per nearby probe a
//! mutual-visibility ray to the hit point with the two validity checks of
//! section 5.6.4 (an escaping ray is a valid sample without light), the
//! weights w(t) = 2t^3 - 3t^2 + 1, the parallax-corrected direction
//! phi(omega) in the SH basis, Welford means, and invalid samples left out
//! of the normalisation (section 5.6.5). Receivers are clustered by halving
//! bounding boxes (at most `cluster_size` each); one cluster's transport
//! matrix at a time is compressed to `pca_vectors` principal vectors by
//! faer's partial SVD, halved again while those keep less than
//! `cluster_energy` of its squared transport, and stored as f16, only the
//! columns of the cluster's probes. Each probe also keeps a sample table: for each of the shared
//! stratified sphere directions, the texel its ray hits.
//!
//! Every frame: direct irradiance at the texels the probes see (a point
//! light's averaged over each texel's footprint, as a probe ray lands
//! anywhere on it; plus last frame's indirect irradiance, the final
//! gather's where a texel gathers, times albedo / pi, for further
//! bounces);
//! probe projection into SH through the sample tables; per cluster the
//! light basis vector Sigma_c V^T lambda; per receiver U_c times it,
//! stored packed (RGB9E5) in cluster order. The lightmap is that array seen
//! through a map from atlas texel to receiver made at load, with the
//! gutters pointing at the texels they copy: dilation done once, so a frame
//! neither scatters texel writes nor copies gutters. Shading samples it
//! bilinearly through the map.
//!
//! | parameter | default | meaning |
//! |---|---|---|
//! | `order` | 7 | SH order of the probes, 0 to 7 ((order + 1)^2 coefficients) |
//! | `probe_count` | 32 | probes placed automatically (the thesis: 27 for the Cornell box, 160 for Sponza) |
//! | `probes` | `[]` | explicit probe positions `[[x, y, z], ...]`; replaces automatic placement |
//! | `radius` | 0 | cut-off radius r in metres; 0 = `radius_factor` x the probes' covering distance |
//! | `radius_factor` | 2 | see `radius` |
//! | `min_probes` | 3 | receivers that see geometry should see at least this many probes within r; placement adds probes where they do not |
//! | `max_added_probes` | 32 | probes the coverage pass may add |
//! | `max_nearby` | 8 | probes per receiver (closest visible first) |
//! | `samples` | 1024 | transport samples per receiver (the thesis: 4096) |
//! | `probe_samples` | 1024 | sample directions per probe (the thesis: 1024) |
//! | `cluster_size` | 1024 | receivers per CPCA cluster at most |
//! | `cluster_energy` | 0.99 | fraction of a cluster's squared transport its `pca_vectors` must keep; a cluster that keeps less is halved (down to 2 x `pca_vectors` receivers) and compressed again (0 = never) |
//! | `pca_vectors` | 32 | principal vectors per cluster, n_c |
//! | `radiance_order` | 0 | SH order (1 to 4) of the radiance transport to receivers on materials with a Phong exponent, for glossy reflection with parallax and visibility (the original paper's extension); 0 = off, glossy reflection then blends the probes |
//! | `radiance_samples` | 1024 | uniform hemisphere samples per glossy receiver for the radiance transport |
//! | `radiance_pca_vectors` | 64 | principal vectors per cluster of the radiance transport; its clusters hold `cluster_size` / (radiance_order + 1)^2 receivers, as each brings that many rows (Cornell box, glossy walls: 32 / 64 / 128 vectors gave 9.3 / 8.0 / 7.9 %) |
//! | `texel_jitter` | false | transport rays start anywhere in the texel (the thesis) rather than at its centre, where relight's receivers and references are evaluated |
//! | `bounces` | 128 | 1 = single bounce; more = last frame's indirect light feeds the probes, and the first update runs passes until they settle, at most this many |
//! | `probe_budget` | 0 | probes refreshed per frame, round robin (staggered updates); 0 = all |
//! | `specular` | 0 | specular reflectance of materials with a Phong exponent (glossy reflection of the probes) |
//! | `space_rays` | 64 | gather rays per point in space (run time) |
//! | `final_gather` | `auto` | receivers nearer other geometry than this many lightmap texels gather their near field by tracing (see below): `auto` = the spacing of the probes over the lightmap, 0 = off (the paper's method), `inf` = every receiver that sees geometry (run time) |
//! | `final_gather_rays` | 0 | rays per gathering receiver; 0 = automatic: 2^23 rays a frame shared by the gathering receivers, `final_gather_min_rays` to 1024 each (run time) |
//! | `final_gather_min_rays` | 128 | the automatic ray count's floor, which large scenes get: Sponza's 260k gathering receivers get it (see below) (run time) |
//! | `update_budget` | 1 | the share of the final gather's work an update after the first does: the direct light of that share of its hit points (Morton order) and the sums of that share of its receivers, the rest keeping the last update's; 1 = all of it every update. Once the lights rest the light equals the unbudgeted within 2 / `update_budget` - 1 updates (run time) |
//! | `gather_feedback` | true | with bounces, the final gather's values, where a texel gathers, feed the next bounce instead of the probes' reconstruction there; false: the reconstruction alone (the paper) (run time) |
//! | `seed` | 1 | |
//!
//! Known limits and choices:
//! - The bake's estimate (`relight bake --estimate`, printed before every
//!   bake) counts every receiver's samples times its nearby probes, and for
//!   memory the compressed clusters three times over (held, assembled,
//!   encoded) and each worker a whole cluster's matrix twelve times over
//!   (its f64 copy, the SVD, the halves, the allocator's arenas). Peaks of
//!   identical bakes differ by up to a fifth as those arenas fill (the 300k
//!   atrium: 286 and 357 MiB), and small scenes, whose clusters see fewer
//!   probes, peak below the estimate (two-rooms: 115 of 205 MiB).
//! - A fixed count of principal vectors per cluster is too few where a
//!   cluster's receivers see many probes at order 7 (the corridor's
//!   clusters kept 89.6 % of their squared transport, the box's 8x8-tile
//!   image error 13.0 %) and plenty on Sponza at order 2 (99.5 %). Clusters
//!   that keep less than `cluster_energy` are halved instead (8x8-tile
//!   error at 0 / 0.95 / 0.98 / 0.99: corridor 13.0 / 8.1 / 6.0 / 6.0 %,
//!   Cornell box 8.0 / 7.0 / 6.5 / 6.4 %); on Sponza at order 2 with 160
//!   probes 0.99 makes 678 clusters of 565 and the projection matrices
//!   7.3 MB of 5.9 MB.
//! - 32 probes are a box's count: with the point light 0.1 m from a
//!   corner (`cornell-box-point/scene-corner-light.toml`) 8x8-tile error is
//!   8.5 % at 32 probes and 6.8 % at 64, whatever the transport samples.
//! - The thesis places probes by hand. Probes hugging the surfaces see them
//!   at grazing angles where band-limited radiance rings, so placement
//!   spreads them through the volume (Cornell box lightmap error, measured
//!   while building it: 12.2 % for a shell of probes at a fixed height,
//!   10.3 % for candidates at varied heights, 8.8 % once relaxed, 7.7 % for
//!   a hand-made 3 x 3 x 3 grid; 7.9 % with the final placement).
//! - An escaping primary ray is a valid sample with no indirect light (the
//!   environment's light is direct light here), not a question for the
//!   probes: at openings, probes deeper inside see walls in that direction,
//!   and dropping the sample would hand the room's light to dark directions.
//! - Transport rays start at the texel centre by default: relight's
//!   receivers, references and bilinear lookups treat a texel's value as the
//!   value at its centre, and averaging over the texel instead (the thesis,
//!   `texel_jitter = true`) measured 15.7 % against 11.3 % on the Cornell box
//!   while building (before the placement above).
//! - The thesis counts light arriving from the environment at the probes as
//!   indirect. relight's direct-light service already gives receivers the
//!   environment's light, so escaping probe samples carry no radiance here,
//!   and escaping receiver samples count as directions without indirect
//!   light (the thesis's Figure 5.5 effect, obtained without asking the
//!   probes).
//! - Every probe shares one set of sample directions, so one SH basis table
//!   serves all probes and the projection is a small matrix product.
//! - Direct light is evaluated only at the texels some probe sample hits,
//!   not at the whole lightmap: nothing else reads it.
//! - Bounces beyond the first come from last frame's indirect light. With
//!   fixed lights repeated updates converge to all bounces; with moving
//!   lights higher bounces lag by a frame each. `bounces` cannot stop the
//!   feedback at an exact count without a lightmap per bounce, so it caps
//!   the passes of the first update and switches feedback off at 1. The
//!   first update stops once the rest of each probe-visible texel's
//!   bounce series, estimated from its last two passes' added light, is
//!   under 0.5 % of its light in root mean square
//!   ([`relight_technique::SettlingPasses`]): a fixed 16 passes cut it
//!   short in bright closed rooms (a grey room of albedo 0.9: 0.895x the
//!   path tracer's indirect light, 10.4 % over 8x8 tiles; settled, 1.002x
//!   and 0.7 %, in about 50 passes), while rooms of albedo 0.3 settle in
//!   fewer than 16.
//! - Points in space (dynamic objects, back faces) gather the light
//!   leaving the surfaces around them over `space_rays` fixed rays (direct
//!   light at each hit plus the lightmap's indirect light there), so walls
//!   stop light and the answer has the lightmap's bounces; it costs
//!   `space_rays` rays and direct-light evaluations a query. Blending the
//!   probes, which have neither parallax nor visibility to the point,
//!   measured 30 % relRMSE on the two-rooms grid. Glossy reflection still
//!   blends the probes, distance-weighted with visibility to each probe,
//!   unless `radiance_order` > 0, which precomputes the
//!   receivers' incident radiance from the probes with the same parallax
//!   and visibility as the irradiance transport (one CPCA row per receiver
//!   and output coefficient) and convolves it with the Phong lobe.
//! - A receiver whose primary ray hits the back of a surface has no valid
//!   probe for that direction (check 2 of section 5.6.4), and a probe sample
//!   that hits a back face reads black: the lightmap holds front sides only.
//! - A probe sees a surface near a receiver from far away: the hit's
//!   radiance comes from the probes' SH, which carry none of the light a
//!   corner's surfaces exchange at short range (Sponza: texels within two
//!   texels of other geometry at 0.81x, 90 % of the lightmap's squared
//!   error; the living room 0.84x). The final gather (`final_gather`, on
//!   by default) traces the near field of texels closer to other geometry
//!   than the probes' spacing, each hit reflecting its direct light plus
//!   the reconstructed lightmap's indirect light, and writes the result
//!   into their lightmap slots: living room 8x8-tile relRMSE 22.3 ->
//!   10.3 %, camera-visible lightmap 35.9 -> 18.2 %, light 0.863 ->
//!   0.930x (`relight converge SCENE -t srp --sweep final_gather=0,auto`);
//!   at order 7 the corridor 6.0 -> 2.5 % and the point-lit box 5.9 ->
//!   2.3 % over tiles. A gather hit on a texel that gathers too reflects
//!   what that texel gathered, so light passed from corner to corner
//!   keeps its near field: living room tiles 9.6 -> 6.8 %,
//!   camera-visible lightmap 16.3 -> 14.3 %, light 0.932 -> 0.971x. With
//!   `gather_feedback` (the default) the multi-bounce feedback reads the
//!   gathered values too where a texel gathers, and the first update
//!   gathers once a settling pass: fed the reconstruction, each bounce
//!   carried the probes' near-field error into the next (a bright suite
//!   lit by a spot beside a wall got 1.9 times the path tracer's light;
//!   `relight robustness -t srp --first 88 --variants 1 --set
//!   gather_feedback=false`). It doubles the first update on Sponza.
//! - On Sponza the gather's own noise decides the camera-visible
//!   lightmap's error: its 260k gathering texels get the automatic count's
//!   floor (`final_gather_min_rays`). At 64 / 128 / 256 rays each the
//!   visible lightmap measures 15.9 / 11.6 / 9.7 %, all receivers 17.4 /
//!   13.6 / 11.8 %, 8x8 tiles 8.0 / 7.4 / 7.1 % (`relight converge
//!   ../shared/scenes/sponza/scene.toml -t srp --reference-samples 1024
//!   --sweep final_gather_rays=64,128,256`, the counts set explicitly).
//!   The floor is 128, the least that keeps Sponza within 15 %: against
//!   64 it costs the frame 59 / 61 -> 83 / 80 ms (gather 50 / 51 -> 74 /
//!   71 ms) and the gather 98 -> 167 MB, where 256 rays cost 128 / 79 ms
//!   and 302 MB (`relight bench ../shared/scenes/sponza/scene.toml -t srp
//!   --bake B --set final_gather_rays=64|128|256 --frames 20
//!   --shading-resolution 0x0`, two interleaved rounds each, two cores).
//!   On the living room (267k of 278k texels gather) the floor of 128
//!   takes the visible lightmap from 14.3 to 12.3 % (tiles 6.8 % both;
//!   `relight converge ../shared/scenes/living-room/scene.toml -t srp
//!   --sweep final_gather_min_rays=64,128`) for a frame of 118 / 108 ->
//!   120 / 125 ms and the gather 112 -> 184 MB. Scenes with fewer than
//!   65k gathering texels already get more than the floor.

mod bake;
mod kernels;
pub mod probes;
mod runtime;
pub mod transport;

pub use bake::{
    cluster_transport, sample_directions, BakeStats, ClusterSet, PartClusters, RadianceTransport,
    SrpBake, SrpPart, BACK_FACE, ESCAPED,
};
pub use runtime::{RuntimeSettings, Srp};

use relight_technique::{
    parse_params, with_scene_section, FinalGatherSettings, GatherReach, Progress, SceneContext,
    Shard, Technique, TechniqueError, TechniqueKind,
};
use serde::{Deserialize, Serialize};
use std::sync::Arc;

/// The parameters only the bake reads; the others act at run time, so one
/// bake serves every value of them.
pub const BAKE_PARAMETERS: [&str; 18] = [
    "order",
    "probe_count",
    "probes",
    "radius",
    "radius_factor",
    "min_probes",
    "max_added_probes",
    "max_nearby",
    "samples",
    "probe_samples",
    "cluster_size",
    "cluster_energy",
    "pca_vectors",
    "texel_jitter",
    "radiance_order",
    "radiance_samples",
    "radiance_pca_vectors",
    "seed",
];

/// Parameters of SRP, bake and run time together.
#[derive(Clone, Debug, Serialize, Deserialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct SrpParams {
    pub order: u32,
    pub probe_count: u32,
    pub probes: Vec<[f32; 3]>,
    pub radius: f32,
    pub radius_factor: f32,
    pub min_probes: u32,
    pub max_added_probes: u32,
    pub max_nearby: u32,
    pub samples: u32,
    pub probe_samples: u32,
    pub cluster_size: u32,
    pub cluster_energy: f32,
    pub pca_vectors: u32,
    pub texel_jitter: bool,
    pub radiance_order: u32,
    pub radiance_samples: u32,
    pub radiance_pca_vectors: u32,
    pub bounces: u32,
    pub probe_budget: u32,
    pub specular: f32,
    pub space_rays: u32,
    pub final_gather: GatherReach,
    pub final_gather_rays: u32,
    pub final_gather_min_rays: u32,
    pub update_budget: f32,
    pub gather_feedback: bool,
    pub seed: u64,
}

impl Default for SrpParams {
    fn default() -> Self {
        Self {
            order: 7,
            probe_count: 32,
            probes: Vec::new(),
            radius: 0.0,
            radius_factor: 2.0,
            min_probes: 3,
            max_added_probes: 32,
            max_nearby: 8,
            samples: 1024,
            probe_samples: 1024,
            cluster_size: 1024,
            cluster_energy: 0.99,
            pca_vectors: 32,
            texel_jitter: false,
            radiance_order: 0,
            radiance_samples: 1024,
            radiance_pca_vectors: 64,
            bounces: 128,
            probe_budget: 0,
            specular: 0.0,
            space_rays: 64,
            final_gather: GatherReach::default(),
            final_gather_rays: 0,
            final_gather_min_rays: 128,
            update_budget: 1.0,
            gather_feedback: true,
            seed: 1,
        }
    }
}

impl SrpParams {
    /// Parameters from the scene file's `[srp]` table and `pairs` on top.
    pub fn from_scene(
        context: &SceneContext,
        pairs: &[(String, String)],
    ) -> Result<Self, TechniqueError> {
        let merged = with_scene_section(&context.scene, "srp", pairs);
        let params = parse_params("srp", &Self::default(), &merged)?;
        params.validate()?;
        Ok(params)
    }

    fn validate(&self) -> Result<(), TechniqueError> {
        let problem = if self.order > 7 {
            Some("order must be 0 to 7 (1 to 64 SH coefficients)".to_string())
        } else if self.probes.is_empty() && self.probe_count == 0 {
            Some("probe_count must be at least 1 (or give probes = [[x, y, z], ...])".into())
        } else if let Some(bad) = self
            .probes
            .iter()
            .position(|p| p.iter().any(|v| !v.is_finite()))
        {
            Some(format!("probes[{bad}] is not a finite position"))
        } else if !(self.radius.is_finite() && self.radius >= 0.0) {
            Some("radius must be a finite number >= 0 (0 = automatic)".into())
        } else if !(self.radius_factor.is_finite() && self.radius_factor > 0.0) {
            Some("radius_factor must be a finite number > 0".into())
        } else if self.max_nearby == 0 {
            Some("max_nearby must be at least 1".into())
        } else if self.samples == 0 || self.probe_samples == 0 || self.radiance_samples == 0 {
            Some("samples, probe_samples and radiance_samples must be at least 1".into())
        } else if self.radiance_order as usize >= bake::MAX_RADIANCE_BANDS {
            Some(format!(
                "radiance_order must be 0 (off) to {} (the original paper's limit)",
                bake::MAX_RADIANCE_BANDS - 1
            ))
        } else if !(self.cluster_energy.is_finite() && (0.0..=1.0).contains(&self.cluster_energy)) {
            Some("cluster_energy must be between 0 and 1".into())
        } else if self.cluster_size == 0 {
            Some("cluster_size must be at least 1".into())
        } else if self.pca_vectors == 0 || self.radiance_pca_vectors == 0 {
            Some("pca_vectors and radiance_pca_vectors must be at least 1".into())
        } else if self.bounces == 0 {
            Some("bounces must be at least 1".into())
        } else if self.space_rays == 0 {
            Some("space_rays must be at least 1".into())
        } else if let Err(problem) = self.final_gather_settings() {
            Some(problem)
        } else if !(self.specular.is_finite() && (0.0..=1.0).contains(&self.specular)) {
            Some("specular must be between 0 and 1".into())
        } else {
            None
        };
        match problem {
            Some(message) => Err(relight_technique::ParamError {
                technique: "srp",
                message,
            }
            .into()),
            None => Ok(()),
        }
    }

    pub fn runtime(&self) -> RuntimeSettings {
        RuntimeSettings {
            bounces: self.bounces,
            probe_budget: self.probe_budget,
            specular: self.specular,
            space_rays: self.space_rays,
            gather_feedback: self.gather_feedback,
            // validate() has checked it.
            final_gather: self
                .final_gather_settings()
                .unwrap_or(FinalGatherSettings::OFF),
        }
    }

    fn final_gather_settings(&self) -> Result<FinalGatherSettings, String> {
        FinalGatherSettings::from_params(&self.final_gather, self.final_gather_rays)?
            .with_least_rays(self.final_gather_min_rays)?
            .with_update_budget(self.update_budget)
    }
}

/// The SRP technique kind for the CLI's table.
pub struct SrpKind;

impl TechniqueKind for SrpKind {
    fn name(&self) -> &'static str {
        "srp"
    }
    fn summary(&self) -> &'static str {
        "Sparse Radiance Probes: SH probes, precomputed parallax- and visibility-aware transport to texels, clustered PCA"
    }
    fn needs_bake(&self) -> bool {
        true
    }
    fn bake_parameters(&self) -> &'static [&'static str] {
        &BAKE_PARAMETERS
    }
    fn estimate(
        &self,
        context: &SceneContext,
        params: &[(String, String)],
        shard: Shard,
    ) -> Result<Option<relight_technique::BakeEstimate>, TechniqueError> {
        let params = SrpParams::from_scene(context, params)?;
        Ok(Some(bake::estimate(context, &params, shard)))
    }
    fn bake(
        &self,
        context: &SceneContext,
        params: &[(String, String)],
        progress: &dyn Progress,
    ) -> Result<Vec<u8>, TechniqueError> {
        let params = SrpParams::from_scene(context, params)?;
        let bake = SrpBake::build(context, &params, progress)?;
        tracing::info!(
            "srp bake: {} probes ({} added for coverage), radius {:.3} m, {} receivers short of {} probes ({} see only the environment), {} clusters, {:.1} % of the transport's energy kept",
            bake.probes.len(),
            bake.stats.added_for_coverage,
            bake.radius,
            bake.stats.receivers_short_of_probes,
            bake.stats.min_probes,
            bake.stats.open_receivers,
            bake.clusters.cluster_count(),
            bake.stats.captured_energy * 100.0
        );
        Ok(bake.encode())
    }
    fn bake_shard(
        &self,
        context: &SceneContext,
        params: &[(String, String)],
        shard: Shard,
        progress: &dyn Progress,
    ) -> Result<Vec<u8>, TechniqueError> {
        let params = SrpParams::from_scene(context, params)?;
        Ok(SrpPart::build(context, &params, shard, progress)?.encode())
    }
    fn merge_shards(
        &self,
        parts: Vec<Vec<u8>>,
        _progress: &dyn Progress,
    ) -> Result<Vec<u8>, TechniqueError> {
        let decoded = parts.into_iter().map(|bytes| SrpPart::decode(&bytes));
        Ok(SrpBake::from_parts(decoded)?.encode())
    }
    fn create(
        &self,
        context: Arc<SceneContext>,
        bake: Option<&[u8]>,
        params: &[(String, String)],
        _progress: &dyn Progress,
    ) -> Result<Box<dyn Technique>, TechniqueError> {
        let params = SrpParams::from_scene(&context, params)?;
        let bake = bake.ok_or(TechniqueError::BakeRequired { technique: "srp" })?;
        let bake = SrpBake::decode(bake)?;
        context.check_bake_receivers("srp", bake.receiver_count)?;
        Ok(Box::new(Srp::new(context, bake, params.runtime())))
    }
}
