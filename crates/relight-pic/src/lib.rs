//! PIC: Precomputed Illuminance Composition (Jendersie, Kuri and Grosch,
//! "Real-Time Global Illumination Using Precomputed Illuminance Composition
//! with Chrominance Compression", JCGT 2016): surfels sample the scene's
//! light, a cluster hierarchy carries their flux, and precomputed links from
//! a cut of that hierarchy light SH caches in a lightmap and a grid.
//!
//! Data flow. Bake: equal-area surfels over every triangle (Halton samples
//! in proportion to area, tangential relaxation); a binary hierarchy over
//! them (agglomerative clustering with the paper's metric plus a visibility
//! term, or a kd-tree); caches at the texels of a lightmap atlas (the
//! scene's own or a coarser one with about `lightmap_caches` texels) and on
//! a grid, moved out of geometry; per cache the `links` nodes of largest
//! visible solid angle, refined top down, each with a scalar factor, cone
//! and direction (runtime projection, 12 bytes) or SH coefficients.
//!
//! Load (besides the rays of the final gather, the near-light samples and
//! the cache visibility below): each lightmap cache's links get one
//! scale, so that a uniform radiosity gives the cache the share of its
//! view that meets geometry ([`normalisation`]).
//!
//! Every frame: surfel lighting (the direct-light service at each surfel,
//! a point light's averaged over a square of the surfel's area, the light
//! of emissive surfaces through the links, and last frame's caches for
//! further bounces) into flux per leaf in YCoCg; the pull sums
//! flux up the tree; cache lighting sums linked flux times transport into
//! SH (`bands` for luma, `chroma_bands` for chroma); shading reads the
//! caches bilinearly in the lightmap (static surfaces) or trilinearly in
//! the grid (points in space with `space = grid`) and convolves them with
//! the cosine lobe, or with a Phong lobe for glossy reflection. By default
//! points in space gather the light leaving the surfaces around them over
//! `space_rays` fixed rays (each hit's direct light plus the lightmap
//! caches' indirect light there): the grid's trilinear blend crosses walls
//! and measured 70.6 % relRMSE on Sponza's grid of points in space (points
//! between the grid's caches, 1.5 m apart there), the gather 18.3 %, at
//! `space_rays` rays and direct-light evaluations a query.
//!
//! | parameter | default | meaning |
//! |---|---|---|
//! | `preset` | `""` | `moderate` (32k surfels, 128 links, 3 bands) or `high` (128k, 254, 4): the paper's Sponza settings, both with `projected` links (faster on a CPU); other keys override it |
//! | `surfels` | 32768 | n_s |
//! | `links` | 128 | n_L, links per cache (stored padded to a multiple of 8) |
//! | `bands` | 3 | SH bands of the caches (2 to 8); with `projected` also of the links |
//! | `chroma_bands` | 0 | bands of the chroma channels Co, Cg (section 4.8); 0 = `bands` |
//! | `projected` | false | links hold SH coefficients (Appendix A) instead of runtime projection |
//! | `hierarchy` | `hac` | `hac` (agglomerative) or `kd` (kd-tree) |
//! | `normal_weight` | 0.1 | C_n of the clustering metric |
//! | `balance_weight` | 0.02 | C_b |
//! | `visibility_weight` | 1 | added for clusters whose surfels cannot see each other (0 = the paper's metric) |
//! | `relaxation` | 4 | surfel relaxation steps |
//! | `lightmap_caches` | 8192 | lightmap caches wanted; a coarser atlas than the scene's is built for them when the scene's has more texels (0 = always the scene's) |
//! | `grid_cells` | 2304 | grid caches over the scene's bounds (the paper: 24 x 8 x 12) |
//! | `grid` | `[0, 0, 0]` | explicit grid dimensions |
//! | `node_samples` | 16 | surfel samples per node while choosing links |
//! | `link_samples` | 32 | surfel samples per link factor |
//! | `leak_refinement` | 16 | how much sooner partly hidden nodes are refined: a node's priority is its visible solid angle times 1 + this times the share of its samples the cache cannot see (hidden, facing away or below its horizon; 0 = the paper's solid angle alone) |
//! | `bounces` | 128 | 1 = single bounce; more = last frame's caches light the surfels, and the first update runs passes until they settle (the rest of each cache's bounce series under 0.5 % of its light in root mean square, [`relight_technique::SettlingPasses`]), at most this many |
//! | `area_lights` | `links` | `links`: emissive surfels send their light through the links (the paper); `direct`: the direct-light service lights surfels from emissive triangles too |
//! | `specular` | 0 | specular reflectance of materials with a Phong exponent |
//! | `space` | `gather` | points in space: `gather` the light leaving the surfaces around them over `space_rays` fixed rays, or read the `grid` caches (the paper; cheaper, but it leaks through walls) |
//! | `space_rays` | 64 | gather rays per point in space |
//! | `cache_visibility` | true | receivers and surfels drop the bilinear lightmap caches they cannot see (one ray each at load; see the limits below); false: the paper's plain bilinear lookup (run time) |
//! | `link_normalisation` | true | each lightmap cache's links are scaled at load so that a uniform radiosity gives the cache the share of its view that meets geometry ([`normalisation`]; 256 rays a cache); false: the links as baked (the paper) (run time) |
//! | `final_gather` | `auto` | receivers nearer other geometry than this many lightmap texels gather their near field by tracing (see below): `auto` = the spacing of the lightmap caches over the lightmap, 0 = off (the paper's method), `inf` = every receiver that sees geometry (run time) |
//! | `final_gather_rays` | 0 | rays per gathering receiver; 0 = automatic: 2^23 rays a frame shared by the gathering receivers, `final_gather_min_rays` to 1024 each (run time) |
//! | `final_gather_min_rays` | 64 (`high`: 256) | the automatic ray count's floor, which large scenes get: Sponza's 180k gathering receivers get it (see below) (run time) |
//! | `update_budget` | 1 | the share of the final gather's work an update after the first does: the direct light of that share of its hit points (Morton order) and the sums of that share of its receivers, the rest keeping the last update's; 1 = all of it every update. Once the lights rest the light equals the unbudgeted within 2 / `update_budget` - 1 updates (run time) |
//! | `seed` | 1 | |
//!
//! Known limits and choices:
//! - The bake's estimate (`relight bake --estimate`, printed before every
//!   bake) takes every cache's links at 0.95 of their link and node
//!   samples in rays, as measured on Sponza, the living room and the
//!   atrium; a small closed box, whose caches see every node, traces more
//!   (the Cornell box: 76 M rays for 61 M estimated).
//! - Flux is carried in units of one surfel's area (the sum of the leaves'
//!   radiosities), so factors stay in f16 range whatever the scene's scale;
//!   one power-of-two scale per bake keeps them normal f16 numbers.
//! - A surfel sample is a disc: solid angle a cos / (d^2 + a / (2 pi)),
//!   which is a / d^2 far away and the disc's 2 pi at contact, instead of
//!   the paper's unbounded a cos / d^2. The discs around a cache where
//!   two surfaces meet still overlap: such caches linked up to 19
//!   hemispheres (two-rooms at the defaults) and 13 (the classroom at
//!   `high`), where one lit its texels 300 times brighter than the path
//!   tracer. A cache whose links' solid angles sum to more than 1.1
//!   hemispheres (a grid cache: spheres), beyond what the link samples'
//!   noise gives, has them scaled back to one. Link normalisation (below)
//!   then brings every lightmap cache to what it sees; the scale-back
//!   still holds the grid caches.
//! - Runtime-projection cones match the samples' mean resultant length, so
//!   bands 0 and 1 of each link are those of its samples.
//! - Clusters whose representative surfels cannot see each other pay
//!   `visibility_weight` in the metric, and links refine partly hidden
//!   nodes first: both fight the leak of the paper's Figure 9c.
//! - A link spreads its whole node's flux over the part the cache sees, so
//!   a node seen only in part is right only while its hidden surfels are
//!   as bright as its visible ones. Through a doorway they are not: an
//!   unlit room's caches see the lit room as slivers of large nodes whose
//!   flux comes mostly from the lamp's hot spot out of sight, and the cut
//!   by solid angle alone (`leak_refinement` 1) spent its links on the
//!   unlit room's own walls. Generated two-room suites then showed bright
//!   blotches on the unlit room's walls (variant 64 of `relight gen
//!   variants`: 19.8 % over 8x8 tiles) or too little light (variant 55:
//!   0.821x). Refining the partly hidden nodes first cures both (6.1 %,
//!   0.924x at 16) and also helps where nothing is that visibly wrong:
//!   Sponza (sun) tiles 11.5 -> 10.0 %, its point light 16.0 -> 15.4 %
//!   (`relight converge SCENE -t pic --preset high --sweep
//!   leak_refinement=1,16,64`). 64 was better still on the two-room suites
//!   and the living room, worse on Sponza and on rooms and halls at the
//!   90th percentile of `relight robustness`. It costs elsewhere: the
//!   classroom's tiles went 29.5 -> 31.9 % (a blotch on the ceiling by
//!   its windows grew; why is not known) and the atrium's light 0.945 ->
//!   0.928x. The link count, and so the frame's cost, does not change.
//! - Sponza's 4666 lightmap charts do not fit a 128 x 128 atlas, so its
//!   cache atlas is as coarse as gives about `lightmap_caches` texels.
//! - A lightmap cache whose texel point is buried (a column shaft running
//!   into its capital) slides within half a texel toward its triangle's
//!   middle to where it can gather; one covered entirely stays dark, as
//!   the path tracer has it.
//! - Near-field light is sampled only as densely as the surfels: on Sponza
//!   receivers within two texels of other geometry got 0.87x the path
//!   tracer's light, and finer caches, which stand nearer the corners, got
//!   less (`lightmap_caches=32768`: 0.68x; with 131072 surfels 0.75x).
//!   The final gather (`final_gather`, on by default) traces the near
//!   field of the texels closer to other geometry than the lightmap
//!   caches' spacing, each hit reflecting its direct light plus the
//!   caches' indirect light: Sponza (sun) 8x8-tile relRMSE 35.2 -> 16.2 %,
//!   camera-visible lightmap 48.8 -> 21.7 %, light 0.745 -> 0.879x; the
//!   living room 33.2 -> 20.4 % and 47.6 -> 24.3 % (`relight converge
//!   SCENE -t pic --sweep final_gather=0,auto`). `final_gather=inf`
//!   (every texel) gives 13.0 % on Sponza.
//! - The interior excess on Sponza (1.28x over all receivers, 62 % of
//!   PIC high's squared lightmap error) was not the cut: `links` 254 /
//!   512 / 1024 left it at 1.28 / 1.26 / 1.26x. It was the walls of the
//!   closed attics under the aisle roofs (2.9x; the path tracer has them
//!   nearly black), whose texels blend metre-wide cache texels standing in
//!   the sunlit court above the roof line. A receiver or surfel now drops
//!   the bilinear taps whose caches it cannot see (one ray each, at load;
//!   both ends a tenth of a cache texel off their surfaces), and shading
//!   reads the receivers' lightmap wherever its bilinear footprint touches
//!   such a receiver (a correction lightmap added to the per-point cache
//!   lookup there, as first built, shaded black strips where the lookup
//!   changes sharply within a texel: beside a wall corner whose cache
//!   texel straddles the corner). Sponza (sun), PIC high:
//!   lightmap 45.7 -> 23.7 %, interior 1.28 -> 0.99x, points in space
//!   15.3 -> 13.5 % (1.04 -> 0.99x); camera-visible lightmap 19.9 ->
//!   20.0 % and tiles 14.7 -> 14.8 % (the camera sees no attic). Two-rooms
//!   seen from the unlit room (defaults): tiles 11.1 -> 10.2 %, light
//!   0.890 -> 0.903x. Living room, high: tiles 18.1 -> 17.4 %. Where the
//!   cache atlas is too coarse to hold a cache on the near side of a wall
//!   nothing is left to keep: two-rooms' floor by the dividing wall gets
//!   1.00x the path tracer's light with 1024 caches (1.69x with
//!   `cache_visibility=false`) but 2.7x with 256.
//! - The top-down cut keeps a child only if one of its samples (16, then
//!   64) sees it, so children seen through a small part are dropped and
//!   their light lost: on the living room, PIC high's light ratio is
//!   0.848 / 0.863 / 0.873x and its tiles 17.4 / 15.4 / 14.1 % at
//!   `node_samples` 16 / 64 / 256 (bake 47 / 93 / 196 s). Keeping unseen
//!   children as links instead leaks on Sponza (tiles 14.8 -> 18.1 %).
//! - Later bounces read the near field too: surfels take the caches'
//!   light plus the final gather's correction at their point, and a
//!   gather hit on a gathering receiver reflects what that receiver
//!   gathered. With the caches alone each bounce lost the near field
//!   again: the living room (PIC high) held 0.967x the path tracer's
//!   first bounce and 0.986x of two, but 0.851x of all. Now 0.915x, 8x8
//!   tiles 17.1 -> 11.0 %, camera-visible lightmap 19.9 -> 16.1 %;
//!   two-rooms from the unlit room 0.925 -> 0.952x, tiles 6.1 -> 3.9 %
//!   (`relight converge SCENE -t pic --preset high`). Of the 16.1 %, the
//!   256-path reference's own noise is 7.2 %: against 1024 paths (noise
//!   3.4 %, `--reference-samples 1024`) the same lightmap measures
//!   14.8 %, tiles 11.0 %. The first update
//!   gathers after each of its passes (living room: 0.29 ->
//!   1.9 s once); later frames gather once, as before.
//! - The first update runs passes until the bounces settle, not a fixed
//!   count: 16 passes left a bright closed room (grey, albedo 0.9) at
//!   0.818x the path tracer's indirect light with PIC high, 18.1 % over
//!   8x8 tiles; settled, 0.939x and 6.1 % (before the links were
//!   normalised, below). The 6 % still missing there was PIC's loss per
//!   bounce (0.97x at albedo 0.3, where one bounce is most of the light).
//! - A link spreads its node's flux by the node's mean factor, so where
//!   the brightest surfels of a coarse node are also the nearest (a point
//!   light by the floor), the first bounce comes out dark: Sponza with its
//!   point light, PIC high against the one-bounce path tracer, gives 0.890
//!   / 0.913 / 0.925x the light in view and 8x8 tiles 17.1 / 15.1 / 14.5 %
//!   at `links` 254 / 512 / 1024 (bake 31 / 71 / 117 s), while 32768
//!   lightmap caches (0.888x, 16.0 %) and 128 link samples (0.888x) do
//!   not move it (`relight converge ../shared/scenes/sponza/scene-point.toml
//!   -t pic --preset high --max-bounces 1 --set bounces=1 --sweep
//!   links=512,1024`). All bounces (the same command with
//!   `--reference-samples 1024` instead of the one-bounce options): tiles
//!   17.6 / 15.3 / 14.4 %, visible lightmap 13.4 / 11.2 / 10.1 %, 0.868 /
//!   0.895 / 0.909x. So `--set links=1024` meets
//!   the 15 % bound there; it costs the cache lighting 5-6 -> 19-21 ms a
//!   frame and 307 MB more (`relight bench ... --frames 20`, two
//!   interleaved pairs), and the bake 33 -> 109 s and 113 -> 420 MB on
//!   disk. `high` keeps the paper's 254.
//! - The final gather's own noise: large scenes get the automatic count's
//!   floor, 64 rays a receiver, and the camera-visible lightmap of
//!   Sponza (sun, PIC high, 1024-path reference) measured 18.5 / 15.1 %
//!   at 64 / 256 rays, tiles 14.6 / 14.2 %. The `high`
//!   preset raises the floor to 256 (`final_gather_min_rays`), which
//!   costs Sponza about 60 ms a frame more on two cores (gather 57-87 ->
//!   117-119 ms) and 148 MB; small scenes already get up to 1024.
//! - The surfaces beside the scene file's lights (a shade's inside, the
//!   patch of wall a few texels from a lamp) reach the lightmap caches
//!   through the final gather's explicit samples, not through the links
//!   (see [`near_light`]): a link's factor samples a few of its node's
//!   surfels, and whether they were the shade's decided how much of its
//!   light the next room got (a generated suite with a lamp in a shade
//!   open on two sides: 1.14x of the path tracer's light, 1.04x with the
//!   samples). Each lightmap cache traces the samples once at load; the
//!   grid caches lose those surfaces' first bounce, which the links no
//!   longer carry. Two limits remain. A room lit through a doorway by a
//!   shaded lamp (variant 1 of `relight gen variants`) gets 0.82x of the
//!   path tracer's light, while one bounce is 0.90x (2048 paths). And a
//!   lamp 14 cm from a corner by a doorway gives the next room 0.95x of
//!   one bounce with the samples, 1.02x with the links.
//! - Every bounce passes through the links, and the links as baked gather
//!   less than their cache sees: under a uniform radiosity of one, the
//!   caches of a closed room should gather one, and a generated two-room
//!   suite's (variant 88 of `relight gen variants`, `high`) gathered
//!   0.986 at the median, 0.916 at the 10th percentile and 0.90 within
//!   5 cm of other geometry (discs for surfels, children the cut dropped).
//!   The loss compounds over bounces: that suite's unlit room got 0.92x
//!   the path tracer's first bounce, 1.02x of three, 0.81x of all, and
//!   tracing every texel's near field (`final_gather=inf`) gave 0.86x.
//!   Each lightmap cache's links are therefore scaled at load to what it
//!   sees ([`normalisation`]), which also scales down links that claim
//!   more than the cache sees. Grid caches are not scaled. The missing
//!   light is taken to be as bright as the rest of the cache's view, so
//!   where it is mostly a bright near field the scale overshoots: a suite
//!   lit by a lamp 16 cm from a corner (variant 40) went from 0.96x to
//!   1.08x.

// SH loops index several per-band arrays by band number on purpose.
#![allow(clippy::needless_range_loop)]

mod bake;
pub mod caches;
pub mod hierarchy;
mod kernels;
pub mod links;
pub mod near_light;
pub mod normalisation;
mod runtime;
pub mod surfels;

pub use bake::{PicBake, PicPart};
pub use runtime::{Pic, RuntimeSettings};

use relight_technique::{
    parse_params, with_scene_section, FinalGatherSettings, GatherReach, Progress, SceneContext,
    Shard, SurfaceGather, Technique, TechniqueError, TechniqueKind,
};
use serde::{Deserialize, Serialize};
use std::sync::Arc;

/// The parameters only the bake reads.
pub const BAKE_PARAMETERS: [&str; 17] = [
    "preset",
    "surfels",
    "links",
    "projected",
    "hierarchy",
    "normal_weight",
    "balance_weight",
    "visibility_weight",
    "relaxation",
    "lightmap_caches",
    "grid_cells",
    "grid",
    "node_samples",
    "link_samples",
    "leak_refinement",
    "seed",
    "bands",
];

/// Parameters of PIC, bake and run time together.
#[derive(Clone, Debug, Serialize, Deserialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct PicParams {
    pub preset: String,
    pub surfels: u32,
    pub links: u32,
    pub bands: u32,
    pub chroma_bands: u32,
    pub projected: bool,
    pub hierarchy: String,
    pub normal_weight: f32,
    pub balance_weight: f32,
    pub visibility_weight: f32,
    pub relaxation: u32,
    pub lightmap_caches: u32,
    pub grid_cells: u32,
    pub grid: [u32; 3],
    pub node_samples: u32,
    pub link_samples: u32,
    pub leak_refinement: f32,
    pub bounces: u32,
    pub area_lights: String,
    pub specular: f32,
    pub space: String,
    pub space_rays: u32,
    pub cache_visibility: bool,
    pub link_normalisation: bool,
    pub final_gather: GatherReach,
    pub final_gather_rays: u32,
    pub final_gather_min_rays: u32,
    pub update_budget: f32,
    pub seed: u64,
}

impl Default for PicParams {
    fn default() -> Self {
        Self {
            preset: String::new(),
            surfels: 32768,
            links: 128,
            bands: 3,
            chroma_bands: 0,
            projected: false,
            hierarchy: "hac".into(),
            normal_weight: 0.1,
            balance_weight: 0.02,
            visibility_weight: 1.0,
            relaxation: 4,
            lightmap_caches: 8192,
            grid_cells: 2304,
            grid: [0, 0, 0],
            node_samples: 16,
            link_samples: 32,
            leak_refinement: 16.0,
            bounces: 128,
            area_lights: "links".into(),
            specular: 0.0,
            space: "gather".into(),
            space_rays: 64,
            cache_visibility: true,
            link_normalisation: true,
            final_gather: GatherReach::default(),
            final_gather_rays: 0,
            final_gather_min_rays: 64,
            update_budget: 1.0,
            seed: 1,
        }
    }
}

impl PicParams {
    /// The defaults of a preset (`""`, `moderate` or `high`).
    pub fn preset(name: &str) -> Result<Self, TechniqueError> {
        let mut params = Self::default();
        match name {
            "" => {}
            // The paper's Sponza settings, with SH-projected links: on a
            // CPU the cache lighting then streams f16 rows at memory speed
            // instead of evaluating SH and cone factors per link, 2.5x
            // faster at 22 (moderate) or 36 (high) bytes a link instead of
            // 12, and as accurate (Cornell box, all bounces: 7.6 % against
            // 7.1 % at moderate, 6.2 % against 6.0 % at high).
            "moderate" => params.projected = true,
            "high" => {
                params.surfels = 131072;
                params.links = 254;
                params.bands = 4;
                params.projected = true;
                params.final_gather_min_rays = 256;
            }
            other => {
                return Err(relight_technique::ParamError {
                    technique: "pic",
                    message: format!("unknown preset '{other}': use moderate or high"),
                }
                .into())
            }
        }
        params.preset = name.to_string();
        Ok(params)
    }

    /// Parameters from the scene file's `[pic]` table and `pairs` on top; a
    /// `preset` among them sets the defaults the others override.
    pub fn from_scene(
        context: &SceneContext,
        pairs: &[(String, String)],
    ) -> Result<Self, TechniqueError> {
        let merged = with_scene_section(&context.scene, "pic", pairs);
        let preset = merged
            .iter()
            .rev()
            .find(|(key, _)| key == "preset")
            .map(|(_, value)| value.trim_matches('"').to_string())
            .unwrap_or_default();
        let rest: Vec<(String, String)> = merged
            .into_iter()
            .filter(|(key, _)| key != "preset")
            .collect();
        let params = parse_params("pic", &Self::preset(&preset)?, &rest)?;
        params.validate()?;
        Ok(params)
    }

    fn validate(&self) -> Result<(), TechniqueError> {
        let problem = if self.surfels == 0 {
            Some("surfels must be at least 1".to_string())
        } else if self.links == 0 {
            Some("links must be at least 1".into())
        } else if !(2..=8).contains(&self.bands) {
            Some("bands must be 2 to 8".into())
        } else if self.chroma_bands > self.bands {
            Some("chroma_bands must be at most bands (0 = bands)".into())
        } else if self.chroma_bands == 1 {
            Some("chroma_bands must be 0 or 2 to bands".into())
        } else if self.hierarchy != "hac" && self.hierarchy != "kd" {
            Some(format!(
                "hierarchy '{}' is unknown: use hac or kd",
                self.hierarchy
            ))
        } else if [
            self.normal_weight,
            self.balance_weight,
            self.visibility_weight,
            self.leak_refinement,
        ]
        .iter()
        .any(|w| !(w.is_finite() && *w >= 0.0))
        {
            Some("normal_weight, balance_weight, visibility_weight and leak_refinement must be finite and >= 0".into())
        } else if self.node_samples == 0 || self.link_samples == 0 {
            Some("node_samples and link_samples must be at least 1".into())
        } else if self.grid_cells == 0 && self.grid.contains(&0) {
            Some("grid_cells must be at least 1 (or give grid = [x, y, z])".into())
        } else if self.bounces == 0 {
            Some("bounces must be at least 1".into())
        } else if let Err(problem) = self.final_gather_settings() {
            Some(problem)
        } else if self.area_lights != "links" && self.area_lights != "direct" {
            Some(format!(
                "area_lights '{}' is unknown: use links or direct",
                self.area_lights
            ))
        } else if !(self.specular.is_finite() && (0.0..=1.0).contains(&self.specular)) {
            Some("specular must be between 0 and 1".into())
        } else if self.space != "gather" && self.space != "grid" {
            Some(format!(
                "space '{}' is unknown: use gather or grid",
                self.space
            ))
        } else if self.space_rays == 0 {
            Some("space_rays must be at least 1".into())
        } else {
            None
        };
        match problem {
            Some(message) => Err(relight_technique::ParamError {
                technique: "pic",
                message,
            }
            .into()),
            None => Ok(()),
        }
    }

    fn final_gather_settings(&self) -> Result<FinalGatherSettings, String> {
        FinalGatherSettings::from_params(&self.final_gather, self.final_gather_rays)?
            .with_least_rays(self.final_gather_min_rays)?
            .with_update_budget(self.update_budget)
    }

    pub fn runtime(&self) -> RuntimeSettings {
        RuntimeSettings {
            bands: self.bands as usize,
            chroma_bands: if self.chroma_bands == 0 {
                self.bands as usize
            } else {
                self.chroma_bands as usize
            },
            bounces: self.bounces,
            area_lights_through_links: self.area_lights == "links",
            specular: self.specular,
            space_gather: (self.space == "gather").then(|| SurfaceGather::new(self.space_rays)),
            cache_visibility: self.cache_visibility,
            link_normalisation: self.link_normalisation,
            // validate() has checked it.
            final_gather: self
                .final_gather_settings()
                .unwrap_or(FinalGatherSettings::OFF),
        }
    }
}

/// The PIC technique kind for the CLI's table.
pub struct PicKind;

impl TechniqueKind for PicKind {
    fn name(&self) -> &'static str {
        "pic"
    }
    fn summary(&self) -> &'static str {
        "Precomputed Illuminance Composition: surfels, cluster hierarchy, precomputed links into SH caches in a lightmap and a grid"
    }
    fn needs_bake(&self) -> bool {
        true
    }
    fn bake_parameters(&self) -> &'static [&'static str] {
        &BAKE_PARAMETERS
    }
    fn bake(
        &self,
        context: &SceneContext,
        params: &[(String, String)],
        progress: &dyn Progress,
    ) -> Result<Vec<u8>, TechniqueError> {
        let params = PicParams::from_scene(context, params)?;
        let bake = PicBake::build(context, &params, progress)?;
        tracing::info!(
            "pic bake: {} surfels, {} nodes (depth {}), {} caches ({} lightmap, {} grid), {} links each",
            bake.surfels.len(),
            bake.hierarchy.node_count(),
            bake.hierarchy.depth(),
            bake.cache_count(),
            bake.caches.lightmap_count,
            bake.cache_count() - bake.caches.lightmap_count,
            bake.links_per_cache
        );
        Ok(bake.encode())
    }
    fn estimate(
        &self,
        context: &SceneContext,
        params: &[(String, String)],
        shard: Shard,
    ) -> Result<Option<relight_technique::BakeEstimate>, TechniqueError> {
        let params = PicParams::from_scene(context, params)?;
        Ok(Some(bake::estimate(context, &params, shard)))
    }
    fn bake_shard(
        &self,
        context: &SceneContext,
        params: &[(String, String)],
        shard: Shard,
        progress: &dyn Progress,
    ) -> Result<Vec<u8>, TechniqueError> {
        let params = PicParams::from_scene(context, params)?;
        Ok(PicPart::build(context, &params, shard, progress)?.encode())
    }
    fn merge_shards(
        &self,
        parts: Vec<Vec<u8>>,
        _progress: &dyn Progress,
    ) -> Result<Vec<u8>, TechniqueError> {
        let decoded = parts.into_iter().map(|bytes| PicPart::decode(&bytes));
        Ok(PicBake::from_parts(decoded)?.encode())
    }
    fn create(
        &self,
        context: Arc<SceneContext>,
        bake: Option<&[u8]>,
        params: &[(String, String)],
        _progress: &dyn Progress,
    ) -> Result<Box<dyn Technique>, TechniqueError> {
        let given = with_scene_section(&context.scene, "pic", params);
        let params = PicParams::from_scene(&context, params)?;
        let bake = bake.ok_or(TechniqueError::BakeRequired { technique: "pic" })?;
        let bake = PicBake::decode(bake)?;
        let mut runtime = params.runtime();
        // A bake made at `--preset high` runs with its four bands unless the
        // run names its bands itself.
        let named = |key: &str| given.iter().any(|(given_key, _)| given_key == key);
        if !named("bands") && !named("chroma_bands") && !named("preset") {
            runtime.bands = bake.cache_bands[0] as usize;
            runtime.chroma_bands = bake.cache_bands[1] as usize;
        }
        Ok(Box::new(Pic::new(context, bake, runtime)?))
    }
}
