//! LightSkin (Lensing and Broll, "LightSkin: Real-Time Global Illumination
//! for Virtual and Mixed Reality"): one-bounce diffuse and glossy indirect
//! light from virtual area lights, gathered at sparse model-space points
//! and interpolated, with no precomputation.
//!
//! Data flow, every frame:
//! 1. Reflective shadow maps, by ray casting from each light (and from each
//!    emissive triangle): every texel's first hit is a virtual area light
//!    (VAL), a Lambertian disc re-emitting the flux it received times the
//!    albedo. Points of a captured point cloud (PLY) are added as VALs.
//! 2. Gathering (equations 3 to 7) at the sparse points, which are spread
//!    over every mesh when it is loaded and fixed to it (over the static
//!    scene by area times the lightmap's density, which falls off outside
//!    the scene's detail region, `relight_scene::detail`; a directional
//!    light's map likewise covers the scene's content bounds): irradiance
//!    and the averaged light position, diffuse and (for glossy materials)
//!    glossy. With `visibility` (the default), a point gathers a VAL only if it
//!    sees the VAL's anchor, the static point nearest the VAL on its side
//!    of the surface; which static points see each other is traced once,
//!    when the scene is loaded (see [`visibility`]).
//! 3. Occlusion (section 3.3, off by default): the other sparse points as
//!    discs dim each point's light.
//! 4. Renormalisation (equations 8 to 11): each point's averaged virtual
//!    point light gets the power that reproduces its gathered irradiance.
//! 5. Interpolation (equations 12 and 13) to the lightmap texels of the
//!    static scene and the vertices of moving meshes, from the eight
//!    nearest sparse points fixed when the mesh was loaded; each texel's
//!    light evaluated at its receiver (equation 10), the final gather's
//!    near field over it, is the irradiance lightmap.
//! 6. Shading: static surfaces sample the irradiance lightmap bilinearly;
//!    moving meshes evaluate their vertices' interpolated lights at each
//!    pixel (equation 10), and glossy light is evaluated per pixel from
//!    the texels' or vertices' interpolated glossy lights.
//!
//! Moving meshes come from the scene file's `[[dynamic]]` tables (see
//! [`dynamic`]); they block and reflect light in the maps and receive
//! indirect light through their own sparse points.
//!
//! | parameter | default | meaning |
//! |---|---|---|
//! | `rsm_resolution` | 48 | texels per side of each reflective shadow map (8 to 512; a point light has six) |
//! | `vals` | 0 | keep at most this many VALs per frame, evenly subsampled with their power scaled (0: all) |
//! | `emissive_resolution` | 64 | texels per side shared by all emissive triangles' maps |
//! | `points` | 4096 | sparse points on the static scene |
//! | `dynamic_points` | 256 | sparse points on each moving mesh (the paper's Figure 5) |
//! | `visibility` | true | a sparse point gathers only the VALs whose anchor it sees, traced between every pair of static points at load (at most 16384 points) |
//! | `occlusion` | false | section 3.3's disc occlusion (the paper's method: `visibility=false occlusion=true`) |
//! | `interpolation` | true | false: every VAL applied to every receiver and pixel (the paper's brute-force comparison) |
//! | `epsilon` | 1e-3 | equation 7's epsilon, relative to an average VAL seen across the scene's diagonal |
//! | `specular` | 0 | specular reflectance of materials with a Phong exponent above 1 (0: diffuse only) |
//! | `block` | 512 | VALs per cache block (the paper's K_cache) |
//! | `point_cloud` | "" | PLY file of captured points added as VALs (section 5) |
//! | `point_cloud_scale` | 1 | radiance (W/m^2/sr) of a point whose colour is 1 |
//! | `space_rays` | 64 | gather rays per point in space |
//! | `final_gather` | `auto` | receivers nearer other geometry than this many lightmap texels gather their near field by tracing (see below): `auto` = the spacing of the sparse points over the lightmap, 0 = off (the paper's method), `inf` = every receiver that sees geometry (run time) |
//! | `final_gather_rays` | 0 | rays per gathering receiver; 0 = automatic: 2^23 rays a frame shared by the gathering receivers, 64 to 1024 each (run time) |
//! | `update_budget` | 1 | the share of the final gather's work an update after the first does: the direct light of that share of its hit points (Morton order) and the sums of that share of its receivers, the rest keeping the last update's; 1 = all of it every update. Once the lights rest the light equals the unbudgeted within 2 / `update_budget` - 1 updates (run time) |
//! | `seed` | 1 | rotation of the sparse points' Halton candidates |
//!
//! The scene file may set any of these under `[lightskin]`; `--set` wins.
//!
//! Choices and limits:
//! - One bounce: VALs are where direct light lands; their light reaching a
//!   receiver is the first indirect bounce, and nothing bounces further.
//! - The disc form factor of equation 3 is exact on the disc's axis and an
//!   approximation elsewhere (tested against numerical integration).
//! - A sun's map spans the whole scene, so a hall's windows are a texel or
//!   two across and one ray per texel let all of a window's light in or
//!   none of it. Where the light passes an edge between two texels (the
//!   nearer surface shadows the farther one) the texels are cast again at
//!   3 x 3 points, and each surface those rays meet becomes one VAL of
//!   their flux. Creases and the scene's outline against the sky are not
//!   refined, and neither are point and spot lights' maps, whose many
//!   edges cost far more rays than the rooms gained (docs/techniques.md
//!   has the figures).
//! - A VAL's disc has the surface area its texel covers (perpendicular
//!   footprint over the cosine, at most five times the footprint), not the
//!   paper's area facing the light, which overstates exitance on tilted
//!   surfaces.
//! - Averaged light positions are weighted by each VAL's luminance at the
//!   point (see [`gather`]), not by geometry alone.
//! - Texels, not mesh vertices, are the interpolation targets of static
//!   geometry: the paper notes its interpolation fails when the mesh is
//!   coarser than the points (a wall of two triangles), and lightmap texels
//!   are a tessellation finer than the points everywhere. Moving meshes
//!   interpolate at their vertices, as in the paper.
//! - A texel's neighbours are the eight nearest points that face its way,
//!   lie in front of its surface and within two point spacings (or twice
//!   its nearest point's distance where no point is that near): a thick
//!   lampshade's outside otherwise took the light of the inside wall
//!   behind it and of a box far below, evaluated beside the lamp
//!   ([`points::Interpolation`]). A texel with no point in front of it
//!   within eight spacings (the outside of a closed building, whose hidden
//!   faces hold no points) takes its nearest facing points wherever they
//!   lie, so that no search runs over the whole scene.
//! - Points in space (back faces, points off the meshes) gather one
//!   bounce from the static surfaces around them over `space_rays` fixed
//!   rays (direct light at each hit), plus the point cloud's VALs without
//!   occlusion; moving meshes neither block nor reflect light to them.
//!   Blending the nearest visible sparse points' light measured 75 to 80 %
//!   relRMSE against one bounce on the shipped scenes' grids of points
//!   (`relight converge`), since a point in the middle of a room is nearer
//!   the lit surfaces than the points on them; `interpolation = false`
//!   gathers every VAL at the query (9 to 12 % on the boxes, but with no
//!   occlusion: 1.23x on Sponza).
//! - Sparse points see their surroundings only as finely as they are
//!   spaced: on Sponza texels within two texels of other geometry got
//!   0.83x of one bounce. The final gather (`final_gather`, on by
//!   default) replaces the interpolated light of texels nearer other
//!   geometry than the sparse points' spacing by one traced bounce (each
//!   hit's direct light), and shading adds the change as a lightmap:
//!   Sponza 8x8-tile relRMSE against one bounce 51.3 -> 17.2 %,
//!   camera-visible lightmap 63.0 -> 24.0 %; the living room 54.7 ->
//!   22.1 % and 74.1 -> 31.9 %, its light 1.32 -> 1.10x (`relight
//!   converge SCENE -t lightskin --sweep final_gather=0,auto`, measured
//!   with the disc occlusion). With `final_gather=inf` every texel that
//!   sees geometry is traced and LightSkin's own interpolation serves only
//!   moving meshes and glossy light.
//! - Visibility between sparse points: the disc occlusion dims light
//!   through a wall only as far as the wall's few points cover the light,
//!   so sunlit outer walls lit the rooms behind them (living room, against
//!   one bounce: thin geometry 1.12x, camera-visible lightmap 31.0 %).
//!   Static points and walls stay put, so each pair of static points is
//!   traced once at load (n^2 / 2 shadow rays: 8.4M for 4096 points;
//!   loading took 1.6 s longer on the living room and 2.8 s on Sponza on
//!   two cores; n^2 bits, 2 MiB), and a VAL counts at a
//!   point that sees its anchor. A VAL stands for the area around its
//!   anchor, so light that a point sees only part of counts whole or not
//!   at all. Measured by `relight converge SCENE -t lightskin --sweep
//!   visibility=false,true --sweep occlusion=true,false` (camera-visible
//!   lightmap / 8x8 image tiles against one bounce, the paper's method ->
//!   the defaults): living room 31.0 / 21.9 % -> 23.9 / 18.4 % (light
//!   1.10 -> 0.98x), Sponza (sun) 21.9 / 10.9 % -> 21.3 / 10.6 %, Sponza
//!   (point) 15.9 / 13.7 % -> 13.1 / 11.7 %, the atrium 44.6 / 17.1 % ->
//!   23.5 / 14.6 %, the point-lit Cornell box 19.7 / 14.1 % -> 14.6 /
//!   2.5 %. With visibility the disc occlusion only darkens further
//!   (living room 0.960x against 0.983x of the light, atrium 0.88x
//!   against 0.94x) and costs a stage, so it is off. The gather masks
//!   VALs by their anchors' bits; VALs are sorted by anchor and points
//!   stored in Morton order, so most blocks of eight VALs read one word
//!   of a row and blocks no receiver of a group sees are skipped.
//! - Sparse points go only where someone sees
//!   ([`relight_technique::SceneContext::is_hidden_surface_point`]): a
//!   second ceiling a few centimetres above the visible one took half the
//!   points there, which gathered nothing, and the visible ceiling
//!   blended them in as dark blotches (the classroom). Each point then
//!   stands for its share of the visible area. The test counts back
//!   faces, so ground just outside a building of one-sided walls counts
//!   as hidden and gets no points of its own.
//! - A VAL must see its anchor (one ray per VAL and frame): a lightmap
//!   texel can straddle a wall, its receiver moved to the part inside the
//!   room while a VAL lands on the part outside (a floor or wall plane
//!   running on past the building into the sun), and the room gathered
//!   such VALs through the wall (generated halls: up to 3.3x the path
//!   tracer's light). Such a VAL takes the nearest point facing it that
//!   it sees, or lights no one. A receiver looks four times its usual
//!   reach for an anchor it sees before its VALs count as hidden (points
//!   face it, none seen) or unanchored (seen by every point; the back of a
//!   one-sided wall).
//! - The surfaces beside the scene file's lights (a shade's inside, the
//!   patch of wall a few texels from a lamp: the final gather's hot
//!   surfaces, [`relight_technique::NearLightSamples`]) are not gathered
//!   through anchors. A shade's inside is smaller than the points'
//!   spacing, so its VALs borrowed an anchor outside it, and a room seen
//!   through a doorway got the shade's light whole or not at all with the
//!   points' placement (generated suites of two rooms with a shaded lamp:
//!   the unlit room's light swung from 0.36x to 0.99x of one bounce with
//!   the points' seed). Their VALs are hidden, and each static point adds
//!   the samples it sees, traced once at load (one shadow ray per static
//!   point and sample in front of it; the final gather caps the samples a
//!   scene has), weighted by their form factors. Moving meshes' points and
//!   glossy light do not see those surfaces, and with `occlusion` on the
//!   disc occlusion dims the samples' light too, though it was traced.
//! - Static surfaces shade from the irradiance lightmap: evaluating the
//!   bilinear blend of neighbouring texels' averaged lights per pixel
//!   (the paper's equation 10) gave blotches where those lights sit near
//!   the surface (atrium, visibility on: image 77 % per pixel, 22.4 % over
//!   tiles; from the lightmap 23.5 % and 14.6 %; Sponza 32.9 / 12.2 %
//!   against 24.7 / 10.6 %), and it lost to the lightmap on every scene
//!   measured. The lightmap is also what an engine uploads.
//! - Glossy reflection is evaluated for the eye of the frame's camera
//!   (`Frame::camera`; the scene camera's when none is given), so it
//!   follows a moving viewer from the next update; the glossy lobe uses
//!   c = specular / (2 pi), so c_k =
//!   specular (k + 1) / (2 pi) is the normalised Phong lobe.

pub mod dynamic;
pub mod gather;
mod geometry;
pub mod occlusion;
pub mod ply;
pub mod points;
pub mod vals;
pub mod visibility;

use dynamic::{DynamicMesh, DynamicWorld};
use gather::Sums;
use geometry::Geometry;
use glam::{Affine3A, Vec3};
use points::{Anchor, Interpolation};
use rayon::prelude::*;
use relight_core::colour::luminance;
use relight_core::Rgb;
use relight_scene::{Light, Mesh, Scene};
use relight_technique::{
    parse_params, with_scene_section, FinalGather, FinalGatherSettings, Frame, FrameReads,
    GatherReach, LastFrame, MemoryEntry, NearLightRows, NearLightSamples, Progress, SceneContext,
    StageTimings, SurfaceGather, SurfacePoint, Technique, TechniqueError, TechniqueKind,
};
use serde::{Deserialize, Serialize};
use std::f32::consts::PI;
use std::path::PathBuf;
use std::sync::Arc;
use vals::{RsmSettings, Val, Vals};
use visibility::PointVisibility;

/// What can go wrong setting LightSkin up, each saying where and what to do.
#[derive(Debug, thiserror::Error)]
pub enum LightSkinError {
    #[error("{path}: {message}")]
    Scene { path: PathBuf, message: String },
    #[error("{path}: {message}")]
    PointCloud { path: PathBuf, message: String },
}

impl From<LightSkinError> for TechniqueError {
    fn from(error: LightSkinError) -> Self {
        TechniqueError::Other(error.to_string())
    }
}

#[derive(Clone, Debug, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct LightSkinParams {
    pub rsm_resolution: u32,
    pub vals: u32,
    pub emissive_resolution: u32,
    pub points: u32,
    pub dynamic_points: u32,
    pub occlusion: bool,
    pub visibility: bool,
    pub interpolation: bool,
    pub epsilon: f32,
    pub specular: f32,
    pub block: u32,
    pub point_cloud: String,
    pub point_cloud_scale: f32,
    pub space_rays: u32,
    pub final_gather: GatherReach,
    pub final_gather_rays: u32,
    pub update_budget: f32,
    pub seed: u64,
}

impl Default for LightSkinParams {
    fn default() -> Self {
        Self {
            rsm_resolution: 48,
            vals: 0,
            emissive_resolution: 64,
            points: 4096,
            dynamic_points: 256,
            occlusion: false,
            visibility: true,
            interpolation: true,
            epsilon: 1e-3,
            specular: 0.0,
            block: 512,
            point_cloud: String::new(),
            point_cloud_scale: 1.0,
            space_rays: 64,
            final_gather: GatherReach::default(),
            final_gather_rays: 0,
            update_budget: 1.0,
            seed: 1,
        }
    }
}

impl LightSkinParams {
    fn final_gather_settings(&self) -> Result<FinalGatherSettings, String> {
        FinalGatherSettings::from_params(&self.final_gather, self.final_gather_rays)?
            .with_update_budget(self.update_budget)
    }

    fn validate(&self) -> Result<(), TechniqueError> {
        let fail = |message: String| {
            Err(TechniqueError::Params(relight_technique::ParamError {
                technique: "lightskin",
                message,
            }))
        };
        if !(8..=512).contains(&self.rsm_resolution) {
            return fail(format!(
                "rsm_resolution must be between 8 and 512, got {}",
                self.rsm_resolution
            ));
        }
        if self.emissive_resolution > 2048 {
            return fail(format!(
                "emissive_resolution must be at most 2048, got {}",
                self.emissive_resolution
            ));
        }
        if !(1..=1_000_000).contains(&self.points) {
            return fail(format!(
                "points must be between 1 and 1000000, got {}",
                self.points
            ));
        }
        if self.visibility && self.points > MAX_VISIBILITY_POINTS {
            return fail(format!(
                "visibility traces a shadow ray between every pair of sparse points, so it allows \
                 at most {MAX_VISIBILITY_POINTS} points (got {}): lower points or set visibility=false",
                self.points
            ));
        }
        if self.dynamic_points > 1_000_000 {
            return fail(format!(
                "dynamic_points must be at most 1000000, got {}",
                self.dynamic_points
            ));
        }
        if self.space_rays == 0 {
            return fail("space_rays must be at least 1".to_string());
        }
        if let Err(problem) = self.final_gather_settings() {
            return fail(problem);
        }
        if !(self.epsilon.is_finite() && self.epsilon > 0.0) {
            return fail(format!("epsilon must be positive, got {}", self.epsilon));
        }
        if !(self.specular.is_finite() && (0.0..=1.0).contains(&self.specular)) {
            return fail(format!(
                "specular must be between 0 and 1, got {}",
                self.specular
            ));
        }
        if self.block < 8 || !self.block.is_multiple_of(8) {
            return fail(format!(
                "block must be a positive multiple of 8, got {}",
                self.block
            ));
        }
        if !(self.point_cloud_scale.is_finite() && self.point_cloud_scale >= 0.0) {
            return fail(format!(
                "point_cloud_scale must be a non-negative number, got {}",
                self.point_cloud_scale
            ));
        }
        Ok(())
    }
}

pub struct LightSkinKind;

impl TechniqueKind for LightSkinKind {
    fn name(&self) -> &'static str {
        "lightskin"
    }
    fn summary(&self) -> &'static str {
        "LightSkin: RSM virtual area lights gathered at sparse model-space points, interpolated; no bake, moving meshes"
    }
    fn needs_bake(&self) -> bool {
        false
    }
    fn create(
        &self,
        context: Arc<SceneContext>,
        _bake: Option<&[u8]>,
        params: &[(String, String)],
        _progress: &dyn Progress,
    ) -> Result<Box<dyn Technique>, TechniqueError> {
        let pairs = with_scene_section(&context.scene, "lightskin", params);
        let params = parse_params("lightskin", &LightSkinParams::default(), &pairs)?;
        params.validate()?;
        Ok(Box::new(LightSkin::new(context, params)?))
    }
}

/// Averaged virtual point lights of a set of receivers: power (W/pi-like,
/// the L'' of equation 11) and position, struct of arrays.
#[derive(Clone, Debug, Default)]
struct Vpls {
    power: Vec<Rgb>,
    position: Vec<Vec3>,
}

impl Vpls {
    fn zeroed(count: usize) -> Self {
        Self {
            power: vec![Rgb::ZERO; count],
            position: vec![Vec3::ZERO; count],
        }
    }

    fn memory_bytes(&self) -> usize {
        (self.power.len() + self.position.len()) * 12
    }

    /// Equation 13 for every target of `interpolation`.
    fn interpolate_from(&mut self, sources: &Vpls, interpolation: &Interpolation) {
        self.power
            .par_iter_mut()
            .zip(self.position.par_iter_mut())
            .enumerate()
            .for_each(|(target, (power, position))| {
                (*power, *position) =
                    interpolation.blend(target, &sources.power, &sources.position);
            });
    }
}

/// Equation 10, diffuse term: irradiance at `position` with `normal` from a
/// point light of power `power` (L''_d) at `light`: L cos(theta) / d^2.
#[inline]
pub fn phong_diffuse(power: Rgb, light: Vec3, position: Vec3, normal: Vec3) -> Rgb {
    let to_light = light - position;
    let distance_sq = to_light.length_squared().max(1e-12);
    let cos = normal.dot(to_light);
    if cos <= 0.0 {
        return Rgb::ZERO;
    }
    power * (cos / (distance_sq * distance_sq.sqrt()))
}

/// Equation 10, glossy term without the BRDF factor: L cos^k(gamma) / d^2
/// with gamma between `reflected` and the direction to the light.
#[inline]
pub fn phong_glossy(
    power: Rgb,
    light: Vec3,
    position: Vec3,
    normal: Vec3,
    reflected: Vec3,
    exponent: f32,
) -> Rgb {
    let to_light = light - position;
    let distance_sq = to_light.length_squared().max(1e-12);
    let direction = to_light / distance_sq.sqrt();
    let cos_gamma = reflected.dot(direction);
    if cos_gamma <= 0.0 || normal.dot(direction) <= 0.0 {
        return Rgb::ZERO;
    }
    power * (cos_gamma.powf(exponent) / distance_sq)
}

/// Smallest cosine equation 11 divides by: an averaged light almost in the
/// receiver's plane would otherwise get an unbounded power that
/// interpolation spreads to neighbours.
const MIN_RENORMALISATION_COSINE: f32 = 0.02;

/// Equation 11: the power that makes [`phong_diffuse`] of the averaged light
/// at `light` reproduce `irradiance` at the point.
#[inline]
pub fn renormalise_diffuse(irradiance: Rgb, light: Vec3, position: Vec3, normal: Vec3) -> Rgb {
    let to_light = light - position;
    let distance_sq = to_light.length_squared().max(1e-12);
    let distance = distance_sq.sqrt();
    let cos = (normal.dot(to_light) / distance).max(MIN_RENORMALISATION_COSINE);
    irradiance * (distance_sq / cos)
}

/// Sparse points of the static scene and of the moving meshes, in world
/// space for the current frame, struct of arrays. Static points come first.
#[derive(Clone, Debug, Default)]
struct SparsePoints {
    positions: Vec<Vec3>,
    normals: Vec<Vec3>,
    /// Disc radius squared (occluders): r^2 = (area per point) / pi.
    radius_sq: Vec<f32>,
    /// Phong exponent; 0 where the point has no glossy lobe.
    glossy_exponent: Vec<f32>,
    /// Per moving mesh: its anchors (mesh space) and first point index.
    dynamic_anchors: Vec<(usize, Vec<Anchor>)>,
}

impl SparsePoints {
    /// Spreads `count` points over `mesh` (in the mesh's own space, by
    /// area times `weights`, see [`points::spread_points`]) and appends
    /// them as discs; returns their anchors and the area each stands for
    /// where the weight is 1. A point's disc covers that area over its
    /// triangle's weight.
    fn add_mesh(
        &mut self,
        mesh: &Mesh,
        count: usize,
        seed: u64,
        weights: Option<&[f32]>,
        hidden: Option<&(dyn Fn(u32, Vec3) -> bool + Sync)>,
        glossy_exponent: impl Fn(usize) -> f32,
    ) -> (Vec<Anchor>, f32) {
        let (anchors, spread_area) = points::spread_points(mesh, count, seed, weights, hidden);
        let area_per_point = spread_area as f32 / anchors.len().max(1) as f32;
        for anchor in &anchors {
            let triangle = anchor.triangle as usize;
            self.positions.push(points::anchor_position(mesh, *anchor));
            self.normals.push(mesh.geometric_normal(triangle));
            let weight = weights.map_or(1.0, |weights| weights[triangle]);
            self.radius_sq.push(area_per_point / weight / PI);
            self.glossy_exponent
                .push(glossy_exponent(anchor.triangle as usize));
        }
        (anchors, area_per_point)
    }

    /// Puts the points in Morton order. Points next to each other then
    /// see much the same VALs: the gather's groups of receivers share
    /// visibility words and skip the same blocks of VALs.
    fn sort_spatially(&mut self) {
        let order = relight_trace::direct::morton_order(&self.positions);
        fn apply<T: Copy>(values: &mut Vec<T>, order: &[u32]) {
            *values = order.iter().map(|&index| values[index as usize]).collect();
        }
        apply(&mut self.positions, &order);
        apply(&mut self.normals, &order);
        apply(&mut self.radius_sq, &order);
        apply(&mut self.glossy_exponent, &order);
    }
}

/// The most static sparse points whose mutual visibility is traced: n^2 / 2
/// shadow rays at load (134M here) and n^2 bits (32 MiB).
const MAX_VISIBILITY_POINTS: u32 = 16384;

/// A running LightSkin for one scene.
pub struct LightSkin {
    context: Arc<SceneContext>,
    params: LightSkinParams,
    dynamic_meshes: Vec<DynamicMesh>,
    dynamic_world: Option<DynamicWorld>,
    point_cloud: Vec<Val>,
    /// The point cloud's VALs alone, padded, for points in space.
    point_cloud_vals: Vals,
    points: SparsePoints,
    vals: Vals,
    sums: Vec<Sums>,
    glossy_sums: Vec<Sums>,
    /// Light sphere radius per point, for occlusion.
    light_radius: Vec<f32>,
    occlusion: Vec<f32>,
    occluders: occlusion::Occluders,
    /// Which static points see each other and the VAL anchors (empty with
    /// `visibility` off), and how many static points there are.
    visibility: PointVisibility,
    static_points: usize,
    /// [`Scene::detail_bounds`]: what directional lights' maps cover
    /// when the lightmap coarsens outside them.
    content_bounds: Option<(Vec3, Vec3)>,
    point_diffuse: Vpls,
    point_glossy: Vpls,
    texel_interpolation: Interpolation,
    /// The texels' interpolated glossy lights (empty without glossy
    /// materials); their diffuse lights are evaluated as they are blended.
    texel_glossy: Vpls,
    /// The receiver each lightmap texel shows: shading samples the
    /// receivers' irradiance (final gather included) and the texels'
    /// interpolated glossy lights through it, so no frame builds a map;
    /// the VALs find their anchors' receivers through it too.
    shown_receiver: Vec<u32>,
    /// Per receiver, whether the final gather writes its light. One
    /// bounce: the gather's hits reflect direct light alone and never read
    /// the interpolated value there, so it is not computed.
    gathered_receivers: Vec<bool>,
    /// Per moving-mesh vertex (all meshes in order): neighbours among the
    /// mesh's own points (global indices), mesh-space normals, and lights.
    vertex_interpolation: Interpolation,
    vertex_normals_local: Vec<Vec3>,
    vertex_diffuse: Vpls,
    vertex_glossy: Vpls,
    receiver_irradiance: Vec<Rgb>,
    eye: Vec3,
    /// The last frame's lights and the fixed rays that answer points in
    /// space from the direct light leaving the surfaces around them.
    lights: Vec<Light>,
    space_gather: SurfaceGather,
    final_gather: FinalGather,
    /// The surfaces beside the scene file's lights, gathered by the static
    /// points from explicit samples they were traced to at load rather
    /// than from VALs through anchors (empty without `visibility`).
    near_light: NearLightSamples,
    near_light_rows: NearLightRows,
    timings: StageTimings,
    /// What the last update read, to skip a frame that repeats it.
    last_frame: LastFrame,
}

impl LightSkin {
    pub fn new(
        context: Arc<SceneContext>,
        params: LightSkinParams,
    ) -> Result<Self, TechniqueError> {
        let scene = &context.scene;
        let dynamic_meshes = dynamic::load_dynamic_meshes(scene)?;
        let point_cloud = if params.point_cloud.is_empty() {
            Vec::new()
        } else {
            let folder = scene.source.parent().unwrap_or(std::path::Path::new("."));
            let path = folder.join(&params.point_cloud);
            ply::read_point_cloud_vals(&path, params.point_cloud_scale)?
        };

        // Static sparse points, fixed to the static mesh.
        let mut sparse = SparsePoints::default();
        let glossy_exponent = |triangle: usize| {
            let material = scene.material_of(triangle);
            if params.specular > 0.0 && material.phong_exponent > 1.0 {
                material.phong_exponent
            } else {
                0.0
            }
        };
        // Points follow the lightmap's density: a ground plane far outside
        // the building gets few (the classroom's took 98 % of them).
        let detail_weights = scene.detail_weights();
        // No points on surfaces nobody sees (a second ceiling just above
        // the visible one): blended into the visible surface they would
        // be dark blotches.
        let lift = context.surface_lift();
        let hidden = |triangle: u32, position: Vec3| {
            context.is_hidden_surface_point(
                position,
                scene.mesh.geometric_normal(triangle as usize),
                lift,
            )
        };
        let (_, area_per_point) = sparse.add_mesh(
            &scene.mesh,
            params.points as usize,
            params.seed,
            detail_weights.as_deref(),
            Some(&hidden),
            glossy_exponent,
        );
        sparse.sort_spatially();
        let static_points = sparse.positions.len();
        let point_spacing = area_per_point.sqrt();
        let visibility = if params.visibility && params.interpolation {
            let mut visibility = PointVisibility::trace(
                &context.bvh,
                &sparse.positions,
                &sparse.normals,
                relight_trace::direct::ray_epsilon_for(&context.bvh),
            );
            // Two spacings: where a surface has points at all, the nearest
            // on a side is within about one.
            visibility.anchor_receivers(
                &context.bvh,
                &context.atlas,
                (&sparse.positions, &sparse.normals),
                (
                    2.0 * point_spacing,
                    relight_trace::direct::ray_epsilon_for(&context.bvh),
                ),
            );
            visibility
        } else {
            PointVisibility::default()
        };
        let near_light = if visibility.is_empty() {
            NearLightSamples::default()
        } else {
            NearLightSamples::of(&context)
        };
        let near_light_rows = near_light.rows(
            &context,
            &sparse.positions[..static_points],
            &sparse.normals[..static_points],
        );
        let texel_interpolation = Interpolation::build(
            &context.atlas.receivers.positions,
            &context.atlas.receivers.normals,
            &sparse.positions,
            &sparse.normals,
            area_per_point.sqrt(),
        );

        // Moving meshes: points and vertex neighbour lists in mesh space.
        let mut vertex_lists = Vec::with_capacity(dynamic_meshes.len());
        let mut vertex_normals_local = Vec::new();
        for mesh in &dynamic_meshes {
            let first = sparse.positions.len();
            let (anchors, area_per_point) = sparse.add_mesh(
                &mesh.mesh,
                params.dynamic_points as usize,
                params.seed,
                None,
                None,
                |_| 0.0,
            );
            let normals = vertex_normals(&mesh.mesh);
            let lists = Interpolation::build(
                &mesh.mesh.positions,
                &normals,
                &sparse.positions[first..],
                &sparse.normals[first..],
                area_per_point.sqrt(),
            );
            vertex_lists.push((lists, first as u32));
            vertex_normals_local.extend(normals);
            sparse.dynamic_anchors.push((first, anchors));
        }
        let vertex_interpolation = Interpolation::concat(vertex_lists);

        let point_count = sparse.positions.len();
        let receiver_count = context.atlas.receivers.len();
        let final_gather = match params.final_gather_settings() {
            Ok(settings) => FinalGather::build(&context, settings, params.points as usize, false),
            Err(message) => {
                return Err(relight_technique::ParamError {
                    technique: "lightskin",
                    message,
                }
                .into())
            }
        };
        let vertex_count = vertex_normals_local.len();
        let glossy = params.specular > 0.0;
        let eye = scene.camera.eye;
        Ok(Self {
            dynamic_world: None,
            point_cloud_vals: {
                let mut vals = Vals::default();
                vals.extend(&point_cloud);
                vals.pad();
                vals
            },
            point_cloud,
            sums: vec![Sums::default(); point_count],
            glossy_sums: vec![Sums::default(); if glossy { point_count } else { 0 }],
            light_radius: vec![0.0; point_count],
            occlusion: vec![0.0; point_count],
            occluders: occlusion::Occluders::default(),
            visibility,
            static_points,
            content_bounds: scene.detail_bounds(),
            point_diffuse: Vpls::zeroed(point_count),
            point_glossy: Vpls::zeroed(if glossy { point_count } else { 0 }),
            texel_interpolation,
            texel_glossy: Vpls::zeroed(if glossy { receiver_count } else { 0 }),
            shown_receiver: context.atlas.dilated_receiver_of_texel(),
            gathered_receivers: final_gather.replaces(receiver_count),
            vertex_interpolation,
            vertex_normals_local,
            vertex_diffuse: Vpls::zeroed(vertex_count),
            vertex_glossy: Vpls::zeroed(if glossy { vertex_count } else { 0 }),
            receiver_irradiance: vec![Rgb::ZERO; receiver_count],
            points: sparse,
            vals: Vals::default(),
            dynamic_meshes,
            eye,
            lights: Vec::new(),
            space_gather: SurfaceGather::new(params.space_rays),
            final_gather,
            near_light,
            near_light_rows,
            params,
            context,
            timings: StageTimings::default(),
            last_frame: LastFrame::default(),
        })
    }

    /// The VALs of the last update.
    pub fn vals(&self) -> &Vals {
        &self.vals
    }

    /// Sparse point positions of the last update (static ones first).
    pub fn sparse_points(&self) -> &[Vec3] {
        &self.points.positions
    }

    /// Irradiance each sparse point gathered in the last update (after
    /// occlusion), and its averaged diffuse light (l'_d, L''_d).
    pub fn sparse_point_light(&self, index: usize) -> (Rgb, Vec3, Rgb) {
        (
            self.sums[index].irradiance() * (1.0 - self.occlusion[index]),
            self.point_diffuse.position[index],
            self.point_diffuse.power[index],
        )
    }

    pub fn sparse_point_normal(&self, index: usize) -> Vec3 {
        self.points.normals[index]
    }

    /// The moving meshes placed for the last update, if the scene has any.
    pub fn dynamic_world(&self) -> Option<&DynamicWorld> {
        self.dynamic_world.as_ref()
    }

    fn geometry(&self) -> Geometry<'_> {
        Geometry {
            scene: &self.context.scene,
            bvh: &self.context.bvh,
            emitters: &self.context.emitters,
            ray_epsilon: relight_trace::direct::ray_epsilon_for(&self.context.bvh),
            dynamic: self.dynamic_world.as_ref(),
            content: self.content_bounds,
        }
    }

    /// Equation 6 summed over every VAL at one point: the brute-force answer.
    pub fn brute_force_irradiance(&self, position: Vec3, normal: Vec3) -> Rgb {
        irradiance_from_every_val(&self.vals, position, normal)
    }

    /// Each moving mesh's pose this frame: the application's, or the
    /// scene file's script at the frame's index.
    fn moving_mesh_poses(&self, frame: &Frame) -> Result<Vec<Affine3A>, TechniqueError> {
        let Some(poses) = frame.moving_mesh_poses else {
            return Ok(self
                .dynamic_meshes
                .iter()
                .map(|mesh| mesh.pose(frame.index))
                .collect());
        };
        if poses.len() != self.dynamic_meshes.len() {
            return Err(TechniqueError::Other(format!(
                "the frame places {} moving meshes but the scene has {} ([[dynamic]] entries): pass one pose for each, in the scene file's order",
                poses.len(),
                self.dynamic_meshes.len()
            )));
        }
        if let Some(index) = poses.iter().position(|pose| !pose.is_finite()) {
            return Err(TechniqueError::Other(format!(
                "moving mesh {} ({}): its pose is not finite",
                index + 1,
                self.dynamic_meshes[index].path.display()
            )));
        }
        Ok(poses.to_vec())
    }

    fn place_dynamic_points(&mut self, world: &DynamicWorld) {
        for (mesh_index, (first, anchors)) in self.points.dynamic_anchors.iter().enumerate() {
            let pose = world.poses[mesh_index];
            let mesh = &self.dynamic_meshes[mesh_index].mesh;
            for (offset, anchor) in anchors.iter().enumerate() {
                self.points.positions[first + offset] =
                    pose.transform_point3(points::anchor_position(mesh, *anchor));
                self.points.normals[first + offset] = pose
                    .transform_vector3(mesh.geometric_normal(anchor.triangle as usize))
                    .normalize_or_zero();
            }
        }
    }

    /// The epsilon weight of equation 7 per VAL: `epsilon` times the weight
    /// of an average VAL facing a receiver across the scene's diagonal.
    fn epsilon_weight(&self) -> f64 {
        if self.vals.count == 0 {
            return 0.0;
        }
        let (low, high) = self
            .content_bounds
            .unwrap_or_else(|| self.context.bvh.bounds());
        let diagonal_sq = (high - low).length_squared().max(1e-12) as f64;
        let mean_luminance: f64 = self.vals.power_luminance[..self.vals.count]
            .iter()
            .map(|&l| l as f64)
            .sum::<f64>()
            / self.vals.count as f64;
        self.params.epsilon as f64 * mean_luminance / diagonal_sq
    }

    /// Anchors this frame's VALs to the static points that stand for them
    /// in visibility lookups.
    fn anchor_vals(&mut self) {
        let near_light = &self.near_light;
        self.visibility.anchor_vals(
            &mut self.vals,
            &self.context.atlas,
            &self.shown_receiver,
            &self.context.bvh,
            |triangle, position| near_light.covers(triangle, position),
        );
    }

    /// Adds the near-light samples each static point sees to its sums, as
    /// VALs at the samples would add them.
    fn gather_near_light(&mut self) {
        let near_light = &self.near_light;
        let rows = &self.near_light_rows;
        let spread = self.params.occlusion;
        self.sums[..self.static_points]
            .par_iter_mut()
            .enumerate()
            .for_each(|(index, sums)| {
                near_light.for_each_in_row(rows, index, |position, irradiance| {
                    let add = if spread {
                        Sums::add::<true>
                    } else {
                        Sums::add::<false>
                    };
                    add(
                        sums,
                        irradiance.to_array(),
                        luminance(irradiance),
                        position.to_array(),
                        (position * position).to_array(),
                    );
                });
            });
    }

    fn gather_points(&mut self) {
        let vals = &self.vals;
        let block = self.params.block as usize;
        let spread = self.params.occlusion;
        let positions = &self.points.positions;
        let normals = &self.points.normals;
        let visibility = (!self.visibility.is_empty()).then_some(&self.visibility);
        const GROUP: usize = 16;
        self.sums
            .par_chunks_mut(GROUP)
            .enumerate()
            .for_each(|(group, sums)| {
                let first = group * GROUP;
                let count = sums.len();
                sums.fill(Sums::default());
                let rows: [&[u32]; GROUP] = std::array::from_fn(|offset| {
                    visibility.map_or(&[][..], |visibility| visibility.row(first + offset))
                });
                let rows = visibility.is_some().then_some(&rows[..count]);
                let mut start = 0;
                while start < vals.padded_len() {
                    let end = (start + block).min(vals.padded_len());
                    let positions = &positions[first..first + count];
                    let normals = &normals[first..first + count];
                    if spread {
                        gather::accumulate_many::<true>(
                            vals, start, end, positions, normals, rows, sums,
                        );
                    } else {
                        gather::accumulate_many::<false>(
                            vals, start, end, positions, normals, rows, sums,
                        );
                    }
                    start = end;
                }
            });
        if !self.near_light.is_empty() {
            self.gather_near_light();
        }
        let vals = &self.vals;
        let positions = &self.points.positions;
        let normals = &self.points.normals;
        // Finish equation 7: the averaged light position l'_d (and the light
        // sphere radius occlusion uses) once per point, for both later stages.
        let epsilon_weight = self.epsilon_weight();
        let sums = &self.sums;
        self.point_diffuse
            .position
            .par_iter_mut()
            .zip(self.light_radius.par_iter_mut())
            .enumerate()
            .for_each(|(index, (centre, radius))| {
                (*centre, *radius) = Self::averaged_light(&sums[index], epsilon_weight, vals);
            });
        if !self.glossy_sums.is_empty() {
            let eye = self.eye;
            let exponents = &self.points.glossy_exponent;
            let visibility = (!self.visibility.is_empty()).then_some(&self.visibility);
            self.glossy_sums
                .par_iter_mut()
                .enumerate()
                .for_each(|(index, sums)| {
                    *sums = Sums::default();
                    if exponents[index] > 0.0 {
                        let position = positions[index];
                        let normal = normals[index];
                        let reflected = reflect_view(eye, position, normal);
                        gather::accumulate_glossy(
                            vals,
                            position,
                            normal,
                            reflected,
                            exponents[index],
                            visibility.map(|visibility| visibility.row(index)),
                            sums,
                        );
                    }
                });
        }
    }

    /// Averaged light position and the light sphere radius (largest side of
    /// the box l'_d +- sigma; meaningful when the spread was summed).
    fn averaged_light(sums: &Sums, epsilon_weight: f64, vals: &Vals) -> (Vec3, f32) {
        let count = vals.count as f64;
        let weight = sums.weight as f64 + epsilon_weight * count;
        if weight <= 0.0 {
            return (Vec3::ZERO, 0.0);
        }
        let mut centre = [0.0f64; 3];
        let mut largest_sigma = 0.0f64;
        for (axis, coordinate) in centre.iter_mut().enumerate() {
            let mean = (sums.weighted_position[axis] as f64
                + epsilon_weight * vals.position_sum[axis])
                / weight;
            let square = (sums.weighted_square[axis] as f64
                + epsilon_weight * vals.position_square_sum[axis])
                / weight;
            *coordinate = mean;
            largest_sigma = largest_sigma.max((square - mean * mean).max(0.0).sqrt());
        }
        (
            Vec3::new(centre[0] as f32, centre[1] as f32, centre[2] as f32),
            (2.0 * largest_sigma) as f32,
        )
    }

    fn renormalise_points(&mut self) {
        let positions = &self.points.positions;
        let normals = &self.points.normals;
        let sums = &self.sums;
        let occlusion = &self.occlusion;
        let lights = &self.point_diffuse.position;
        self.point_diffuse
            .power
            .par_iter_mut()
            .enumerate()
            .for_each(|(index, power)| {
                let irradiance = sums[index].irradiance() * (1.0 - occlusion[index]);
                *power = renormalise_diffuse(
                    irradiance,
                    lights[index],
                    positions[index],
                    normals[index],
                );
            });
        if !self.glossy_sums.is_empty() {
            let eye = self.eye;
            let exponents = &self.points.glossy_exponent;
            let glossy_sums = &self.glossy_sums;
            self.point_glossy
                .power
                .par_iter_mut()
                .zip(self.point_glossy.position.par_iter_mut())
                .enumerate()
                .for_each(|(index, (power, light))| {
                    let sums = &glossy_sums[index];
                    let exponent = exponents[index];
                    if exponent <= 0.0 || sums.weight <= 0.0 {
                        *power = Rgb::ZERO;
                        *light = positions[index] + normals[index];
                        return;
                    }
                    let centre = Vec3::from_array(sums.weighted_position) / sums.weight;
                    let position = positions[index];
                    let reflected = reflect_view(eye, position, normals[index]);
                    // Equation 11, glossy: L'' = L' d^2 / cos^k(gamma).
                    let to_light = centre - position;
                    let distance_sq = to_light.length_squared().max(1e-12);
                    let cos_gamma = (reflected.dot(to_light) / distance_sq.sqrt())
                        .max(MIN_RENORMALISATION_COSINE);
                    *light = centre;
                    *power = sums.irradiance()
                        * (1.0 - occlusion[index])
                        * (distance_sq / cos_gamma.powf(exponent));
                });
        }
    }

    fn compute_occlusion(&mut self) {
        let sums = &self.sums;
        let mut occluders = std::mem::take(&mut self.occluders);
        occluders.fill(
            &self.points.positions,
            &self.points.normals,
            &self.points.radius_sq,
        );
        let positions = &self.points.positions;
        let normals = &self.points.normals;
        let lights = &self.point_diffuse.position;
        let light_radius = &self.light_radius;
        self.occlusion
            .par_iter_mut()
            .enumerate()
            .for_each(|(index, occluded)| {
                *occluded = if sums[index].weight <= 0.0 {
                    0.0
                } else {
                    occlusion::occluded_fraction(
                        &occluders,
                        positions[index],
                        normals[index],
                        lights[index],
                        light_radius[index],
                    )
                };
            });
        self.occluders = occluders;
    }

    fn interpolate(&mut self) {
        let atlas = &self.context.atlas;
        if !self.glossy_sums.is_empty() {
            self.texel_glossy
                .interpolate_from(&self.point_glossy, &self.texel_interpolation);
        }
        // Each texel's light is blended and evaluated in one pass: the
        // blended lights are not stored, since nothing else reads them.
        let receivers = &atlas.receivers;
        let (interpolation, sources) = (&self.texel_interpolation, &self.point_diffuse);
        let gathered = &self.gathered_receivers;
        self.receiver_irradiance
            .par_iter_mut()
            .enumerate()
            .for_each(|(index, irradiance)| {
                if gathered.get(index) == Some(&true) {
                    return;
                }
                let (power, light) = interpolation.blend(index, &sources.power, &sources.position);
                *irradiance = phong_diffuse(
                    power,
                    light,
                    receivers.positions[index],
                    receivers.normals[index],
                );
            });
        if !self.vertex_interpolation.is_empty() {
            self.vertex_diffuse
                .interpolate_from(&self.point_diffuse, &self.vertex_interpolation);
            if !self.glossy_sums.is_empty() {
                self.vertex_glossy
                    .interpolate_from(&self.point_glossy, &self.vertex_interpolation);
            }
        }
    }

    /// Replaces the interpolated light of the receivers near other geometry
    /// by the final gather's, and records the change for shading.
    fn apply_final_gather(&mut self, lights: &[Light]) {
        // One bounce: the hits reflect their direct light alone.
        let interpolated = &self.receiver_irradiance;
        self.final_gather.update(
            &self.context,
            lights,
            |receiver| interpolated[receiver as usize],
            false,
        );
        self.final_gather.apply(&mut self.receiver_irradiance);
    }

    fn brute_force_receivers(&mut self) {
        let receivers = &self.context.atlas.receivers;
        let vals = &self.vals;
        self.receiver_irradiance
            .par_iter_mut()
            .enumerate()
            .for_each(|(index, irradiance)| {
                let mut sums = Sums::default();
                gather::accumulate::<false>(
                    vals,
                    0,
                    vals.padded_len(),
                    receivers.positions[index],
                    receivers.normals[index],
                    None,
                    &mut sums,
                );
                *irradiance = sums.irradiance();
            });
    }

    /// The interpolated lights at a point of a moving mesh's triangle
    /// (index into the merged scene, see [`DynamicWorld::merged_into`]).
    fn dynamic_surface_light(
        &self,
        triangle: u32,
        barycentric: glam::Vec2,
        position: Vec3,
        normal: Vec3,
    ) -> Option<Rgb> {
        let world = self.dynamic_world.as_ref()?;
        let static_count = self.context.scene.mesh.triangles.len() as u32;
        let local = triangle.checked_sub(static_count)?;
        let [a, b, c] = *world.triangles.get(local as usize)?;
        let weights = [
            1.0 - barycentric.x - barycentric.y,
            barycentric.x,
            barycentric.y,
        ];
        let mut power = Rgb::ZERO;
        let mut light = Vec3::ZERO;
        for (vertex, weight) in [a, b, c].into_iter().zip(weights) {
            power += self.vertex_diffuse.power[vertex as usize] * weight;
            light += self.vertex_diffuse.position[vertex as usize] * weight;
        }
        Some(phong_diffuse(power, light, position, normal))
    }
}

/// Ideal reflection of the direction from `eye` to `position` about `normal`.
/// Equation 6 summed over every VAL of `vals` at one point, without
/// occlusion.
fn irradiance_from_every_val(vals: &Vals, position: Vec3, normal: Vec3) -> Rgb {
    let mut sums = Sums::default();
    gather::accumulate::<false>(
        vals,
        0,
        vals.padded_len(),
        position,
        normal,
        None,
        &mut sums,
    );
    sums.irradiance()
}

fn reflect_view(eye: Vec3, position: Vec3, normal: Vec3) -> Vec3 {
    let incoming = (position - eye).normalize_or_zero();
    (incoming - 2.0 * incoming.dot(normal) * normal).normalize_or_zero()
}

/// Area-weighted vertex normals of a mesh.
fn vertex_normals(mesh: &Mesh) -> Vec<Vec3> {
    let mut normals = vec![Vec3::ZERO; mesh.positions.len()];
    for triangle in &mesh.triangles {
        let [a, b, c] = triangle.map(|v| mesh.positions[v as usize]);
        let weighted = (b - a).cross(c - a);
        for &vertex in triangle {
            normals[vertex as usize] += weighted;
        }
    }
    normals.into_iter().map(|n| n.normalize_or_zero()).collect()
}

impl Technique for LightSkin {
    fn name(&self) -> &'static str {
        "lightskin"
    }

    /// The paper's single bounce: virtual area lights are directly lit
    /// surfaces, and nothing they light bounces further.
    fn indirect_bounces(&self) -> Option<u32> {
        Some(1)
    }

    fn forget_last_frame(&mut self) {
        self.last_frame.forget();
    }

    /// One bounce settles in one update, but under `update_budget` the
    /// final gather's parts still to refresh change the light.
    fn settled(&self) -> bool {
        self.final_gather.refreshed()
    }

    fn update(&mut self, frame: &Frame) -> Result<(), TechniqueError> {
        let start = std::time::Instant::now();
        let poses = self.moving_mesh_poses(frame)?;
        // A single bounce: the same lights, moving meshes and (for glossy
        // light, which the update gathers toward the eye) camera give the
        // same light.
        let reads = FrameReads {
            camera: !self.glossy_sums.is_empty(),
            moving_meshes: !self.dynamic_meshes.is_empty(),
        };
        let repeated = self.last_frame.repeats(frame, reads);
        if repeated && self.final_gather.refreshed() {
            self.timings.skip(start);
            return Ok(());
        }
        let mut timings = std::mem::take(&mut self.timings);
        timings.clear();
        self.lights.clear();
        self.lights.extend_from_slice(frame.lights);
        if let Some(camera) = frame.camera {
            self.eye = camera.eye;
        }
        if !self.dynamic_meshes.is_empty() {
            let world = timings.time("dynamic meshes", || {
                DynamicWorld::place(&self.dynamic_meshes, &poses)
            });
            self.place_dynamic_points(&world);
            self.dynamic_world = Some(world);
        }
        timings.time("rsm", || {
            let mut vals = std::mem::take(&mut self.vals);
            vals::render_rsms(
                &self.geometry(),
                frame.lights,
                RsmSettings {
                    resolution: self.params.rsm_resolution,
                    emissive_resolution: self.params.emissive_resolution,
                },
                &mut vals,
            );
            vals.extend(&self.point_cloud);
            vals.limit_to(self.params.vals as usize);
            vals.pad();
            self.vals = vals;
        });
        if !self.visibility.is_empty() {
            timings.time("anchors", || self.anchor_vals());
        }
        if !self.near_light.is_empty() {
            timings.time("near-light samples", || {
                self.near_light.light(&self.context, frame.lights)
            });
        }
        if !self.params.interpolation {
            timings.time("brute force", || self.brute_force_receivers());
            self.timings = timings;
            return Ok(());
        }
        timings.time("gather", || self.gather_points());
        if self.params.occlusion {
            timings.time("occlusion", || self.compute_occlusion());
        } else {
            self.occlusion.fill(0.0);
        }
        timings.time("renormalise", || self.renormalise_points());
        timings.time("interpolate", || self.interpolate());
        if !self.final_gather.is_empty() {
            let start = std::time::Instant::now();
            self.apply_final_gather(frame.lights);
            self.final_gather.push_stages(&mut timings, start.elapsed());
        }
        self.timings = timings;
        Ok(())
    }

    fn indirect_irradiance(&self, point: &SurfacePoint) -> Rgb {
        if !self.params.interpolation {
            return self.brute_force_irradiance(point.position, point.normal);
        }
        if point.triangle as usize >= self.context.scene.mesh.triangles.len() {
            return self
                .dynamic_surface_light(
                    point.triangle,
                    point.barycentric,
                    point.position,
                    point.normal,
                )
                .unwrap_or_else(|| {
                    self.indirect_irradiance_in_space(point.position, point.normal)
                });
        }
        // The lightmap, not equation 10 per pixel (see the crate doc).
        self.context
            .atlas
            .sample_receivers(
                &self.shown_receiver,
                &self.receiver_irradiance,
                point.triangle,
                point.barycentric,
            )
            .max(Rgb::ZERO)
    }

    /// One bounce gathered from the static surfaces around the point over
    /// `space_rays` fixed rays (each hit reflects its direct light), so a
    /// wall between a lit surface and the point stops its light; plus the
    /// point cloud's VALs, which no surface carries, without occlusion.
    /// Blending the nearest visible sparse points' light instead measured
    /// 75 to 80 % relRMSE on the shipped scenes' grids of points in space:
    /// a point in the middle of a room is nearer the lit surfaces than the
    /// points on the walls are.
    fn indirect_irradiance_in_space(&self, position: Vec3, normal: Vec3) -> Rgb {
        if !self.params.interpolation {
            return self.brute_force_irradiance(position, normal);
        }
        let surfaces =
            self.space_gather
                .irradiance(&self.context, &self.lights, position, normal, |_| Rgb::ZERO);
        if self.point_cloud.is_empty() {
            return surfaces;
        }
        surfaces + irradiance_from_every_val(&self.point_cloud_vals, position, normal)
    }

    fn glossy_radiance(
        &self,
        point: &SurfacePoint,
        toward_viewer: Vec3,
        exponent: f32,
    ) -> Option<Rgb> {
        if self.glossy_sums.is_empty()
            || !self.params.interpolation
            || exponent <= 1.0
            || point.triangle as usize >= self.context.scene.mesh.triangles.len()
        {
            return None;
        }
        let atlas = &self.context.atlas;
        let shown = &self.shown_receiver;
        let (triangle, barycentric) = (point.triangle, point.barycentric);
        let power = atlas.sample_receivers(shown, &self.texel_glossy.power, triangle, barycentric);
        let light =
            atlas.sample_receivers(shown, &self.texel_glossy.position, triangle, barycentric);
        let reflected = (-toward_viewer).reflect(point.normal).normalize_or_zero();
        let lobe = self.params.specular * (exponent + 1.0) / (2.0 * PI);
        Some(
            phong_glossy(
                power,
                light,
                point.position,
                point.normal,
                reflected,
                exponent,
            ) * lobe,
        )
    }

    fn frame_geometry(&self) -> Option<Scene> {
        self.dynamic_world
            .as_ref()
            .map(|world| world.merged_into(&self.context.scene))
    }

    fn receiver_irradiance(&self) -> Option<&[Rgb]> {
        Some(&self.receiver_irradiance)
    }

    fn timings(&self) -> &StageTimings {
        &self.timings
    }

    fn memory(&self) -> Vec<MemoryEntry> {
        let sums = std::mem::size_of::<Sums>();
        let mut entries = vec![
            MemoryEntry::new(
                format!("VALs ({})", self.vals.count),
                self.vals.memory_bytes(),
            ),
            MemoryEntry::new(
                "sparse points",
                self.points.positions.len() * (12 + 12 + 4 + 4),
            ),
            MemoryEntry::new(
                "gathered sums",
                (self.sums.len() + self.glossy_sums.len()) * sums
                    + (self.light_radius.len() + self.occlusion.len()) * 4
                    + self.occluders.memory_bytes(),
            ),
            MemoryEntry::new(
                "sparse point lights",
                self.point_diffuse.memory_bytes() + self.point_glossy.memory_bytes(),
            ),
            MemoryEntry::new(
                "neighbour lists",
                self.texel_interpolation.memory_bytes() + self.vertex_interpolation.memory_bytes(),
            ),
            MemoryEntry::new("texel glossy lights", self.texel_glossy.memory_bytes()),
            MemoryEntry::new(
                "lightmap texels' receivers",
                self.shown_receiver.len() * 4 + self.gathered_receivers.len(),
            ),
            MemoryEntry::new("receiver irradiance", self.receiver_irradiance.len() * 12),
        ];
        if !self.visibility.is_empty() {
            entries.push(MemoryEntry::new(
                format!(
                    "sparse point visibility ({} points, {:.1} % of pairs see each other)",
                    self.static_points,
                    100.0 * self.visibility.visible_fraction()
                ),
                self.visibility.memory_bytes(),
            ));
        }
        if !self.vertex_normals_local.is_empty() {
            entries.push(MemoryEntry::new(
                "moving-mesh vertex lights",
                self.vertex_normals_local.len() * 12
                    + self.vertex_diffuse.memory_bytes()
                    + self.vertex_glossy.memory_bytes(),
            ));
        }
        if !self.near_light.is_empty() {
            entries.push(MemoryEntry::new(
                format!(
                    "near-light samples ({} on {} texel sides, seen by {} points)",
                    self.near_light.counts().0,
                    self.near_light.counts().1,
                    self.near_light_rows.points_seeing()
                ),
                self.near_light.memory_bytes() + self.near_light_rows.memory_bytes(),
            ));
        }
        entries.extend(self.final_gather.memory_entry());
        entries
    }
}
