//! PRM: Precomputed Radiance Maps (Szécsi and Szirmay-Kalos, "On Making
//! Light Maps Dynamic"), a lightmap made dynamic by precomputed light paths.
//!
//! Data flow. Bake: entry points are sampled on all surfaces in proportion
//! to area (Halton, low discrepancy; weighted by the lightmap's texel
//! density, which coarsens outside the scene's detail region and refines
//! on small charts near lights, each entry then standing for its own area;
//! an eighth of them kept for the surfaces that face a light of the scene
//! file within a few entry spacings of it) and clustered by position,
//! normal and their light under the scene file's lights (k-means++
//! seeding, Lloyd iterations, an entry joining only a cluster whose anchor
//! it sees from the front); from each entry point
//! quasi-random light paths (cosine directions, Russian roulette by albedo
//! luminance, equations 1 to 3; more of them from entries that the scene
//! file's lights make bright) leave virtual point lights, and every
//! lightmap receiver (the paper's exit points) gathers from them by shadow
//! rays, assuming unit irradiance at the entry point. The result, summed
//! per cluster, is one pane per cluster; by default the panes are then
//! compressed to their leading principal components (`rank` basis panes
//! and a coefficient per cluster and component, each pane's errors
//! weighted by its light under the scene file's lights), stored as f16
//! RGB. Every frame: the shared direct-light service gives each entry
//! point's irradiance (a point light's averaged over the patch the entry
//! stands for), a cluster's weight is their average weighted by each
//! entry's share of the cluster pane's light (fixed by the bake), the
//! top-K clusters (or all) are selected, and their panes times their
//! weights sum into the indirect lightmap (with compression, the selected
//! weights fold into one weight per basis pane first), which is dilated
//! and sampled bilinearly.
//!
//! | parameter | default | meaning |
//! |---|---|---|
//! | `entries` | 4096 | entry points (the paper: 4096) |
//! | `clusters` | 256 | clusters of entry points (the paper: 256) |
//! | `rank` | 128 | basis panes kept by compression; 0, or at least `clusters`, = store every cluster's pane |
//! | `top_k` | 0 | clusters summed per frame (the paper: 32); 0 = all |
//! | `selection` | `"contribution"` | how the top K are ranked: `"contribution"` (weight times the pane's total luminance) or `"weight"` (mean entry irradiance alone, as the paper does) |
//! | `pane_resolution` | 256 | pane points as far apart as the texels of a lightmap this many texels on its longer side (the paper's panes: 256 x 256); the light is upsampled to the scene's lightmap each frame; 0 = a pane value at every lightmap texel |
//! | `pane_texel_size` | 0 | pane point spacing in metres; overrides `pane_resolution` when above 0 |
//! | `entry_area_samples` | 2 | shadow rays per entry point toward area lights each frame |
//! | `paths_per_entry` | 4 | light paths from each entry point, times 1 to 16 by its flux under the scene file's lights |
//! | `normal_weight` | 0.5 | weight of the normal against position (in scene diagonals) in clustering |
//! | `irradiance_weight` | 0.5 | weight of each entry's irradiance under the scene file's lights in clustering: a doubling above the surface's mean counts as this many cluster spacings; 0 = position and normal alone (the paper) |
//! | `space_rays` | 64 | gather rays per point in space (run time) |
//! | `final_gather` | `auto` | receivers nearer other geometry than this many lightmap texels gather their near field by tracing (see below): `auto` = the spacing of the entry points over the lightmap, 0 = off (the paper's method), `inf` = every receiver that sees geometry (run time) |
//! | `final_gather_rays` | 0 | rays per gathering receiver; 0 = automatic: 2^23 rays a frame shared by the gathering receivers, 64 to 1024 each (run time) |
//! | `update_budget` | 1 | the share of the final gather's work an update after the first does: the direct light of that share of its hit points (Morton order) and the sums of that share of its receivers, the rest keeping the last update's; 1 = all of it every update. Once the lights rest the light equals the unbudgeted within 2 / `update_budget` - 1 updates (run time) |
//! | `seed` | 1 | |
//!
//! Why compression and all clusters by default: the per-frame cost is the
//! number of panes summed, and principal components of all 256 clusters
//! lose far less light than the paper's strongest clusters at the same
//! cost (Cornell box lightmap error 16 % at 32 components against 48 % for
//! the 32 strongest clusters: in a room lit everywhere, the 224 weaker
//! clusters carry half the indirect light). `rank = 0, top_k = 32` is the
//! paper's configuration.
//!
//! Why 128 components: the components are what limits PRM's accuracy on
//! every scene measured, not the entry points or clusters. A pane is
//! bright near its own entry points, so the panes overlap little and their
//! energy spreads over many components: 32 keep only 72-77 % of it on the
//! Cornell box, the corridor and a generated atrium, 128 keep 95-98 %
//! (plain components; `relight bench`'s memory report gives the share,
//! now of the energy weighted by each pane's light). A light that
//! reaches one part of a building is then smeared over the others.
//! Camera-visible lightmap / 8x8-tile relRMSE at rank 32 -> 128
//! (`relight converge SCENE -t prm --sweep rank=32,128`, Sponza with
//! `--reference-samples 1024`): Sponza's point light 22.0 / 18.2 -> 15.2 /
//! 13.4 %, Sponza's sun 19.3 / 12.1 -> 18.6 / 11.1 %, the living room
//! 15.2 / 9.7 -> 14.4 / 8.5 %, the atrium (`relight gen atrium`) 20.6 /
//! 19.4 -> 14.4 / 12.4 % (64: 17.6 / 16.1 %, every pane: 14.0 / 10.9 %);
//! over tiles the corridor goes 19.8 -> 14.1 % and the Cornell box with a
//! light by a wall 20.2 -> 8.5 %. It costs four times the pane sum and the
//! panes' memory of rank 32, half of storing every pane. Sponza (378k
//! receivers): frame 44.3 / 37.7 -> 59.9 / 57.3 ms, pane sum 5.1 / 4.6 ->
//! 17.6 / 20.0 ms, memory 171 -> 389 MB, bake file 73 -> 291 MB; the
//! atrium (113k): pane sum 1.6 / 1.7 -> 5.8 / 6.0 ms of a 260-270 ms frame
//! (`relight bench SCENE -t prm --bake B --set rank=R --frames 20
//! --shading-resolution 0x0`, two interleaved rounds). The bake's peak
//! stays where it was (Sponza 939 -> 949 MB, atrium 292 -> 299 MB) since
//! the components are written as f16 in place.
//!
//! Why pane points (`pane_resolution`): the per-frame pane sum streams
//! every basis pane from memory, and the bake traces a shadow ray from
//! every pane value to every virtual light it faces, so both grow with the
//! values a pane holds. The paper's panes were 256 x 256; relight's
//! default spaces pane points like the texels of a lightmap 256 texels on
//! its longer side and upsamples to the scene's lightmap (see [`panes`]).
//! The figures above were measured with a pane value at every texel
//! (`pane_resolution = 0`). Sponza (378k receivers, 39.8k pane points), 2
//! threads: bake 71.9 -> 10.6 s and 920 -> 188 MiB at its peak, pane sum
//! 17.9 -> 1.1-2.1 ms plus 0.5-0.7 ms of upsampling (`relight bench
//! ../shared/scenes/sponza/scene.toml -t prm --frames 20
//! --shading-resolution 0x0`, three rounds); lightmap / camera-visible
//! lightmap / 8x8 tiles at every texel, 256 and 128: 20.9 / 18.6 / 11.1 %,
//! 21.7 / 19.0 / 11.1 %, 22.2 / 19.0 / 11.0 % (`relight converge ... -t
//! prm --sweep pane_resolution=0,256,128 --reference-samples 1024`);
//! Sponza's point light 15.2 / 13.4 -> 16.1 / 13.7 %, the atrium 14.4 /
//! 12.4 -> 14.5 / 12.2 %. The living room loses more (visible lightmap /
//! tiles at 0, 512, 256, 128 with 256 reference paths: 14.4 / 8.5, 14.9 /
//! 8.9, 15.4 / 9.4, 16.7 / 11.7 %; bakes 146.9, 49.9, 21.9, 10.8 s): its
//! panes carry indirect shadows of furniture finer than a pane texel, and
//! a sharper blend (modified Shepard weights, exact at the pane points)
//! measured the same. `--set pane_resolution=512` or `0` buys that back at
//! the cost above. Lightmaps at most 256 texels wide (the shipped boxes)
//! keep a value at every texel.
//!
//! Per frame on Sponza the pane sum is no longer what costs: the update
//! takes 2.8-3.1 ms without the final gather (pane sum, upsampling, and
//! 0.8-0.9 ms writing the 1024 x 1024 f32 lightmap) and 23.4-24.4 ms with
//! it, whose 391k hit texels each trace a shadow ray toward the sun
//! (`--set final_gather=0|auto`, three interleaved rounds).
//!
//! Choose PRM for small and medium static scenes with few, moving lights
//! where a lightmap is wanted anyway: its per-frame cost is K pane-sized
//! multiply-adds and one upsampling, independent of how many bounces the
//! panes contain. Memory grows as clusters times pane points, which rules
//! out fine panes with many clusters: [`estimate`] forecasts it (and the shadow rays, from the light
//! paths of 256 pilot entries) before a bake, and `relight bake` refuses a
//! bake whose peak would pass `--max-memory` (default: the memory
//! available), naming the parameters that lower it, or sharding it.
//!
//! Known limits and choices:
//! - The paper sums path vertices from z1 on (equation 3), which would drop
//!   light that bounced once, at the entry point itself; relight includes
//!   the entry point as the first virtual light, so a pane holds every bounce.
//! - Virtual lights are singular (1/d^2). relight treats each as a disc of
//!   the area its entry point stands for (r^2 = A / (N pi)) and uses the
//!   on-axis disc formula, replacing d^2 by d^2 + r^2: bounded, biased only
//!   within about r of a virtual light, and never a "spike".
//! - The paper ranks clusters by weight alone, so a brightly lit cluster
//!   whose light goes nowhere can displace a dimmer one that lights half the
//!   room. relight ranks by weight times the pane's total luminance, the
//!   light a cluster adds (`selection = "weight"` restores the paper's
//!   ranking). At K = 32 (uncompressed) this lowers the Cornell box's
//!   lightmap error from 54.0 % to 47.8 % and the point-lit Cornell box's
//!   from 31.3 % to 29.2 %.
//! - The paper weights a cluster by its entries' mean irradiance. A cluster
//!   that straddles a wall (two rooms: entries on both sides of the
//!   dividing wall's ends) then lends the lit side's irradiance to the
//!   panes of the dark side, whose light is what the pane carries, or the
//!   other way round. relight weights each entry by its share of the pane's
//!   total luminance, which makes every cluster's total light exact: the
//!   unlit room of `two-rooms` (camera in room B) goes from 0.85x to 0.97x
//!   the path tracer's light and from 22.6 % to 12.0 % 8x8-tile error.
//!   The share is of light over the surface: each pane point's light is
//!   weighted by the area its texel stands for, since texels near a light
//!   are finer (`lightmap.refine_near_lights`).
//! - A lamp beside a wall, in a corner or in a shade heats a few square
//!   decimetres around it hundreds of times brighter than the room, and
//!   four things about those few entries decided the light of whole rooms
//!   (`relight robustness -t prm`: unlit rooms of two-room suites 0.67x
//!   to 3.9x of the path tracer's). A cluster joined them to entries whose
//!   light goes elsewhere (the same wall past a partition, a doorway's
//!   jamb with the shade's normal), and the pane spread their light into
//!   the next room: an entry now joins only a cluster whose anchor it sees
//!   from the front, and entries alike to no cluster near them get one of
//!   their own (`cluster_entries`). Entries spaced like the room's fell near the
//!   lamp by chance and counted 0.85-1.05 of its flux: an eighth of the
//!   entries now cover the surfaces near each light of the scene file, and
//!   a point light's irradiance is averaged over each entry's patch, so an
//!   entry 2 cm from a lamp does not read 1/d^2. Their four paths each
//!   decided where most of the light went: entries trace paths in
//!   proportion to their flux under the scene file's lights, up to 16
//!   times as many. And the compression spent its components on large dim
//!   panes, so the small hot panes came back as blotches over the room,
//!   some negative: each pane's errors now count by its light. The lights
//!   are those of the scene file: one moved far from where the file put
//!   it is still unbiased but noisier near its new place.
//! - A cluster's pane assumes its entries' irradiance is even, so a
//!   cluster that holds the entries beside a lamp or in a patch of light
//!   through a doorway together with ten to a hundred times dimmer ones
//!   spreads the bright few's light over its whole pane: a glow on the
//!   walls near them. Entries are clustered by their light under the
//!   scene file's lights too (`irradiance_weight`), so clusters split
//!   where that light changes steeply; a light moved at run time keeps
//!   clusters shaped for the file's lights, compact in space still. The
//!   weight stays at half a cluster spacing a doubling: at a whole one, a
//!   lamp 12 cm from a corner got clusters so small and hot that the
//!   compression's error on their panes, times their weight, came back
//!   as a bright blob ringed by negative light on the floor.
//! - Near-field light is sampled only as densely as the entry points
//!   (about 1.4 m apart on Sponza at 4096): receivers within a few tenths
//!   of a metre of a lit surface (corners, column bases) got too little
//!   (Sponza: texels within two texels of other geometry at 0.51x, 80 % of
//!   the lightmap's squared error). The final gather (`final_gather`, on
//!   by default) traces the near field of texels closer to other geometry
//!   than the entry points' spacing, each hit reflecting its direct light
//!   plus the panes' indirect light: Sponza (sun) 8x8-tile relRMSE
//!   51.3 -> 15.6 %, camera-visible lightmap 59.0 -> 23.6 %, light 0.681
//!   -> 0.896x (`relight converge SCENE -t prm --sweep
//!   final_gather=0,auto`). It costs more than the pane sum: the corridor
//!   updates in 2.6 ms instead of 0.3 ms (`relight bench
//!   scenes/corridor/scene.toml -t prm --set final_gather=0|auto`,
//!   medians of 20 frames, interleaved), most of it the direct light at
//!   the texels the rays hit. A hit on a texel that gathers too reflects
//!   what that texel gathered, so light passed from corner to corner keeps
//!   its near field (the first frame gathers four times): living room
//!   8x8 tiles 13.9 -> 9.7 %, camera-visible lightmap 18.3 -> 15.2 %,
//!   light 0.883 -> 0.931x (`relight converge
//!   ../shared/scenes/living-room/scene.toml -t prm`).
//! - Entry points face their triangle's front side; light reaching only the
//!   back of thin two-sided geometry does not enter the panes.
//! - Points in space (dynamic objects, back faces) gather the light leaving
//!   the surfaces around them over `space_rays` fixed rays: each hit
//!   reflects its direct light and the lightmap's indirect light, so the
//!   answer has every bounce and walls stop light. It costs `space_rays`
//!   closest-hit rays and as many direct-light evaluations a query; the
//!   paper has no answer off the lightmap. Back-face hits reflect their
//!   direct light alone (the lightmap holds front sides).

mod bake;
pub mod panes;
mod runtime;

pub use bake::{estimate, estimate_pane_bytes, estimate_peak_bytes, PrmBake, PrmPart};
pub use runtime::{Prm, Selection};

use relight_technique::{
    parse_params, FinalGatherSettings, GatherReach, Progress, SceneContext, Shard, Technique,
    TechniqueError, TechniqueKind,
};
use serde::{Deserialize, Serialize};
use std::sync::Arc;

/// The parameters only the bake reads; the others act at run time, so one
/// bake serves every value of them.
pub const BAKE_PARAMETERS: [&str; 9] = [
    "entries",
    "clusters",
    "paths_per_entry",
    "normal_weight",
    "irradiance_weight",
    "seed",
    "rank",
    "pane_resolution",
    "pane_texel_size",
];

/// Parameters of PRM, bake and run time together.
#[derive(Clone, Debug, Serialize, Deserialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct PrmParams {
    pub entries: u32,
    pub clusters: u32,
    pub top_k: u32,
    pub selection: String,
    pub paths_per_entry: u32,
    pub entry_area_samples: u32,
    pub rank: u32,
    pub pane_resolution: u32,
    pub pane_texel_size: f32,
    pub normal_weight: f32,
    pub irradiance_weight: f32,
    pub space_rays: u32,
    pub final_gather: GatherReach,
    pub final_gather_rays: u32,
    pub update_budget: f32,
    pub seed: u64,
}

impl Default for PrmParams {
    fn default() -> Self {
        Self {
            entries: 4096,
            clusters: 256,
            top_k: 0,
            selection: "contribution".into(),
            paths_per_entry: 4,
            entry_area_samples: 2,
            rank: 128,
            pane_resolution: 256,
            pane_texel_size: 0.0,
            normal_weight: 0.5,
            irradiance_weight: 0.5,
            space_rays: 64,
            final_gather: GatherReach::default(),
            final_gather_rays: 0,
            update_budget: 1.0,
            seed: 1,
        }
    }
}

impl PrmParams {
    fn final_gather_settings(&self) -> Result<FinalGatherSettings, String> {
        FinalGatherSettings::from_params(&self.final_gather, self.final_gather_rays)?
            .with_update_budget(self.update_budget)
    }

    /// Metres between pane points; at or below the lightmap's texel every
    /// receiver is one.
    pub fn pane_spacing(&self, atlas: &relight_scene::atlas::Atlas) -> f32 {
        if self.pane_texel_size > 0.0 {
            self.pane_texel_size
        } else if self.pane_resolution == 0 {
            0.0
        } else {
            let longer = atlas.width.max(atlas.height) as f32;
            atlas.metres_per_texel * longer / self.pane_resolution as f32
        }
    }

    fn validate(&self) -> Result<(), TechniqueError> {
        let problem = if self.entries == 0 {
            Some("entries must be at least 1")
        } else if self.clusters == 0 || self.clusters > self.entries {
            Some("clusters must be between 1 and entries")
        } else if self.selection != "weight" && self.selection != "contribution" {
            Some("selection must be \"weight\" or \"contribution\"")
        } else if self.entry_area_samples == 0 {
            Some("entry_area_samples must be at least 1")
        } else if self.space_rays == 0 {
            Some("space_rays must be at least 1")
        } else if self.paths_per_entry == 0 {
            Some("paths_per_entry must be at least 1")
        } else if !(self.pane_texel_size.is_finite() && self.pane_texel_size >= 0.0) {
            Some("pane_texel_size must be a finite number of metres >= 0 (0: use pane_resolution)")
        } else if self.pane_resolution != 0 && self.pane_resolution < 8 {
            Some("pane_resolution must be 0 (every lightmap texel) or at least 8")
        } else if !(self.normal_weight.is_finite() && self.normal_weight >= 0.0) {
            Some("normal_weight must be a finite number >= 0")
        } else if !(self.irradiance_weight.is_finite() && self.irradiance_weight >= 0.0) {
            Some("irradiance_weight must be a finite number >= 0 (0: cluster by position and normal alone)")
        } else {
            None
        };
        let problem = problem
            .map(str::to_string)
            .or_else(|| self.final_gather_settings().err());
        match problem {
            Some(message) => Err(relight_technique::ParamError {
                technique: "prm",
                message,
            }
            .into()),
            None => Ok(()),
        }
    }
}

/// The PRM technique kind for the CLI's table.
pub struct PrmKind;

impl TechniqueKind for PrmKind {
    fn name(&self) -> &'static str {
        "prm"
    }
    fn summary(&self) -> &'static str {
        "Precomputed Radiance Maps: light paths from clustered entry points, panes compressed by PCA, weighted per frame"
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
        let params = parse_params("prm", &PrmParams::default(), params)?;
        params.validate()?;
        Ok(Some(bake::estimate(context, &params, shard)?))
    }
    fn bake(
        &self,
        context: &SceneContext,
        params: &[(String, String)],
        progress: &dyn Progress,
    ) -> Result<Vec<u8>, TechniqueError> {
        let params = parse_params("prm", &PrmParams::default(), params)?;
        params.validate()?;
        Ok(PrmBake::build(context, &params, progress)?.encode())
    }
    fn bake_shard(
        &self,
        context: &SceneContext,
        params: &[(String, String)],
        shard: Shard,
        progress: &dyn Progress,
    ) -> Result<Vec<u8>, TechniqueError> {
        let params = parse_params("prm", &PrmParams::default(), params)?;
        params.validate()?;
        Ok(PrmPart::build(context, &params, shard, progress)?.encode())
    }
    fn merge_shards(
        &self,
        parts: Vec<Vec<u8>>,
        progress: &dyn Progress,
    ) -> Result<Vec<u8>, TechniqueError> {
        // Each shard's bytes are freed once its panes are copied.
        let decoded = parts.into_iter().map(|bytes| PrmPart::decode(&bytes));
        Ok(PrmBake::from_parts(decoded, progress)?.encode())
    }
    fn create(
        &self,
        context: Arc<SceneContext>,
        bake: Option<&[u8]>,
        params: &[(String, String)],
        _progress: &dyn Progress,
    ) -> Result<Box<dyn Technique>, TechniqueError> {
        let params = parse_params("prm", &PrmParams::default(), params)?;
        params.validate()?;
        let bake = bake.ok_or(TechniqueError::BakeRequired { technique: "prm" })?;
        let bake = PrmBake::decode(bake)?;
        context.check_bake_receivers("prm", bake.receiver_count)?;
        // The bake only chooses pane points wider apart than a texel; a
        // spacing below that comes from a damaged file and would pile every
        // point into one cell of the taps' grid.
        let spacing = bake.pane_points.spacing;
        if !bake.pane_points.is_every_receiver() && spacing <= context.atlas.metres_per_texel {
            return Err(TechniqueError::Other(format!(
                "PRM bake is corrupt: its pane points are {spacing} m apart, not wider than the lightmap's {} m texels; bake it again",
                context.atlas.metres_per_texel
            )));
        }
        let selection = if params.selection == "contribution" {
            Selection::Contribution
        } else {
            Selection::Weight
        };
        Ok(Box::new(Prm::new(
            context,
            bake,
            params.top_k,
            selection,
            params.entry_area_samples,
            params.space_rays,
            params
                .final_gather_settings()
                .map_err(|message| relight_technique::ParamError {
                    technique: "prm",
                    message,
                })?,
        )))
    }
}
