//! Lightmap parameterisation of the static geometry, and its receivers.
//!
//! Every technique stores indirect light for static geometry in one lightmap,
//! and is measured against the path tracer on the same texels, so the atlas
//! is shared. When the mesh carries a second UV set that is a valid,
//! non-overlapping atlas it is used as is; otherwise charts are grown over
//! edge-connected triangles whose normals stay within a cone of the chart's
//! seed normal, projected onto the seed's plane (a height field, so no folds),
//! and shelf-packed with a gutter of [`GUTTER_TEXELS`]. A chart does not
//! grow across an edge that a surface stands on ([`Atlas::build_between_walls`]):
//! two rooms' floors that meet under a partition get charts of their own, so
//! no texel straddles the partition and shows one room's light in the other.
//! Nor across a seam the loader cut where a partition stands on one slab
//! under both rooms ([`Scene::lightmap_seams`], [`crate::seams`]).
//!
//! Receivers are the texels that cover geometry. Rasterisation is
//! conservative: a texel is covered when its square overlaps a triangle, so
//! thin triangles still get texels; the texel's world point is the closest
//! point of the triangle to the texel centre. Dilation copies each covered
//! texel into the empty gutter texels around it within the same chart, so a
//! bilinear lookup anywhere inside a chart never fetches an empty texel and
//! never mixes in a neighbouring chart (seam-aware). The dilation is a
//! precomputed gather list, so the per-frame cost is one copy per gutter texel.
//! Covered texels that nobody sees (the floor under an object standing on
//! it) may head that list, each showing a seen texel beside it
//! ([`Atlas::fill_hidden`], decided with ray casts by the technique crate):
//! their receivers keep their own values, only what the texel shows changes.
//!
//! Texel density is uniform inside the scene's detail region and coarsens
//! ring by ring outside it ([`crate::detail`]): charts grow within one ring
//! and each is projected at its ring's texel size. Charts near the scene
//! file's point and spot lights (a lampshade, a sconce, the walls by a lamp
//! in a corner) are projected finer, so the light they bounce is resolved
//! (`refine_near_lights`); the other charts keep their texels.

use crate::detail::DetailRegion;
use crate::{Scene, SceneError};
use glam::{Vec2, Vec3};
use rayon::prelude::*;
use relight_core::{Rgb, Rgb9e5};
use std::collections::{HashMap, HashSet};
use std::sync::atomic::{AtomicU64, Ordering};

/// Empty texels kept around every chart: one for the conservative
/// rasterisation's spill, one for the bilinear footprint.
pub const GUTTER_TEXELS: u32 = 2;

/// Charts accept triangles whose normal is within this angle of the seed's,
/// keeping the planar projection injective and texel stretch below 1/cos.
const CHART_NORMAL_COS: f32 = 0.707; // 45 degrees

/// Edges shorter than this many texels never stop a chart: a texel
/// straddles a wall along its length only where the wall runs on for
/// texels, and a short wall (a column's base, a moulding's end) is an
/// object's foot, which the technique crate's hidden-texel fill serves.
const WALL_EDGE_TEXELS: f32 = 2.0;

/// Says whether a surface stands on the edge from `a` to `b` of a plane
/// with normal `normal` (see [`Atlas::build_between_walls`]).
pub type StandsOnEdge<'a> = &'a (dyn Fn(Vec3, Vec3, Vec3) -> bool + Sync);

/// How the atlas resolution is chosen.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum TexelDensity {
    /// World-space size of one texel edge, in metres.
    MetresPerTexel(f32),
    /// Aim for an atlas of about this many texels on its longer side.
    TargetResolution(u32),
    /// At least `minimum` texels on a side, raised to the power of two that
    /// leaves every chart at least as much room as its gutter ring, so scenes
    /// with thousands of charts (Sponza) work without tuning.
    Automatic { minimum: u32 },
}

impl Default for TexelDensity {
    fn default() -> Self {
        TexelDensity::Automatic { minimum: 128 }
    }
}

impl TexelDensity {
    /// A fixed resolution when one is given, the automatic size otherwise.
    pub fn from_resolution(resolution: Option<u32>) -> Self {
        resolution.map_or_else(Self::default, Self::TargetResolution)
    }
}

/// One lightmap texel that covers geometry.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Receiver {
    pub texel: [u32; 2],
    pub position: Vec3,
    /// Geometric normal of `triangle` (front face, counter-clockwise).
    pub normal: Vec3,
    pub triangle: u32,
    /// (b1, b2) of `position` on `triangle`.
    pub barycentric: Vec2,
    pub albedo: Rgb,
}

/// Receivers in struct-of-arrays form, in texel scan order.
#[derive(Clone, Debug, Default)]
pub struct Receivers {
    pub texels: Vec<[u32; 2]>,
    pub positions: Vec<Vec3>,
    pub normals: Vec<Vec3>,
    pub triangles: Vec<u32>,
    pub barycentrics: Vec<Vec2>,
    pub albedos: Vec<Rgb>,
}

impl Receivers {
    pub fn len(&self) -> usize {
        self.positions.len()
    }

    pub fn is_empty(&self) -> bool {
        self.positions.is_empty()
    }

    pub fn get(&self, index: usize) -> Receiver {
        Receiver {
            texel: self.texels[index],
            position: self.positions[index],
            normal: self.normals[index],
            triangle: self.triangles[index],
            barycentric: self.barycentrics[index],
            albedo: self.albedos[index],
        }
    }
}

/// The lightmap layout of a scene: per-triangle texel-space UVs, the texel
/// grid, its receivers and the dilation gather list.
#[derive(Clone, Debug)]
pub struct Atlas {
    pub width: u32,
    pub height: u32,
    /// Texel-space UVs of each triangle's corners (0..width, 0..height).
    pub triangle_uvs: Vec<[Vec2; 3]>,
    /// Each triangle's texel edge over [`Self::metres_per_texel`]: 1 in the
    /// detail region, 4^k in ring k, below 1 near a light; empty for the
    /// mesh's own UVs (see [`Self::texel_area_weight`]).
    pub triangle_texel_scales: Vec<f32>,
    /// For each texel, its receiver index or `u32::MAX` when empty.
    pub receiver_of_texel: Vec<u32>,
    pub receivers: Receivers,
    /// (texel, texel whose value it shows), both as texel indices, applied
    /// in order: first the covered texels nobody sees, each showing a seen
    /// texel beside it ([`Self::fill_hidden`]), then the empty gutter
    /// texels, each copying a covered texel.
    pub dilation: Vec<(u32, u32)>,
    /// True when the mesh's own second UV set was used.
    pub from_mesh_uvs: bool,
    pub chart_count: usize,
    /// Charts given finer texels for standing near a point or spot light
    /// of the scene file (`lightmap.refine_near_lights`).
    pub near_light_charts: usize,
    /// Per triangle, whether it is in a small chart refined near a light
    /// (a shade's inside, a sconce's recess), which stands near the light
    /// as a whole; the large charts refined near a light (a wall beside a
    /// lamp in a corner) have one part near it. Empty when no chart is.
    pub triangle_in_small_near_light_chart: Vec<bool>,
    /// Metres per texel edge inside the detail region: as generated, or for
    /// the mesh's own UVs the mean over the surface (0 only for a mesh
    /// without area).
    pub metres_per_texel: f32,
    /// The region of full density when texels coarsen outside it (a
    /// generated atlas of a scene that reaches far out), else `None`.
    pub detail: Option<DetailRegion>,
}

const EMPTY: u32 = u32::MAX;

impl Atlas {
    /// The area of a texel on `triangle` over a detail-region texel's:
    /// what a sum over receivers weights each by to sum over the surface
    /// (exactly 1 where texels are uniform, and for the mesh's own UVs).
    pub fn texel_area_weight(&self, triangle: u32) -> f32 {
        self.texel_scale(triangle) * self.texel_scale(triangle)
    }

    /// The edge of a texel on `triangle` over a detail-region texel's:
    /// below 1 on charts refined near a light, above it outside the detail
    /// region, 1 for the mesh's own UVs.
    pub fn texel_scale(&self, triangle: u32) -> f32 {
        self.triangle_texel_scales
            .get(triangle as usize)
            .copied()
            .unwrap_or(1.0)
    }

    /// The edge (m) of a texel on `triangle`.
    pub fn texel_edge(&self, triangle: u32) -> f32 {
        self.metres_per_texel * self.texel_scale(triangle)
    }

    /// The surface (m^2) a receiver on `triangle` stands for: its texel's
    /// footprint on the surface.
    pub fn texel_area(&self, triangle: u32) -> f32 {
        self.metres_per_texel * self.metres_per_texel * self.texel_area_weight(triangle)
    }

    /// Whether `triangle` is in a small chart refined near a light
    /// ([`Self::triangle_in_small_near_light_chart`]).
    pub fn in_small_near_light_chart(&self, triangle: u32) -> bool {
        self.triangle_in_small_near_light_chart
            .get(triangle as usize)
            .copied()
            .unwrap_or(false)
    }

    /// Builds the atlas of `scene` at the requested density.
    pub fn build(scene: &Scene, density: TexelDensity) -> Result<Self, SceneError> {
        Self::build_refining(
            scene,
            density,
            scene.lightmap_layout.refine_near_lights,
            None,
        )
    }

    /// [`Self::build`] with charts that stop at the edges `walls` finds a
    /// surface standing on (it is given the edge's ends and the normal of
    /// the plane on both its sides, and answers with ray casts, which
    /// this crate has none of).
    ///
    /// Where two rooms' floors (or walls, or ceilings) are separate
    /// triangles of one plane that meet under a partition, a chart grown
    /// over both put texels across the partition: each such texel's one
    /// receiver stood on one side, and the other room's lookups beside
    /// the partition's foot read that side's light (a generated suite of
    /// two boxes sharing a wall: a bead of lamp-lit floor every few
    /// texels along the unlit room's wall).
    pub fn build_between_walls(
        scene: &Scene,
        density: TexelDensity,
        walls: StandsOnEdge,
    ) -> Result<Self, SceneError> {
        Self::build_refining(
            scene,
            density,
            scene.lightmap_layout.refine_near_lights,
            Some(walls),
        )
    }

    /// [`Self::build`] without finer texels near lights, for an atlas that
    /// places a technique's samples rather than holding light (PIC's
    /// caches): at its coarse texels whole walls and tables near a light
    /// count as small charts, and its receiver count would stop following
    /// its texel size.
    pub fn build_unrefined(scene: &Scene, density: TexelDensity) -> Result<Self, SceneError> {
        Self::build_refining(scene, density, false, None)
    }

    fn build_refining(
        scene: &Scene,
        density: TexelDensity,
        near_lights: bool,
        walls: Option<StandsOnEdge>,
    ) -> Result<Self, SceneError> {
        if density_is_invalid(density) {
            return Err(SceneError::Invalid {
                path: scene.source.clone(),
                message: format!(
                    "lightmap density {density:?} is not usable: metres per texel must be \
                     positive and finite, target resolution between 8 and 16384"
                ),
            });
        }
        if let Some(atlas) = Self::from_mesh_uvs(scene, density) {
            return Ok(atlas);
        }
        let detail = scene.detail_region();
        let rings: Vec<u32> = match &detail {
            Some(region) => (0..scene.mesh.triangles.len())
                .map(|triangle| region.ring_of_triangle(&scene.mesh, triangle))
                .collect(),
            None => vec![0; scene.mesh.triangles.len()],
        };
        let graph = EdgeGraph::of(scene);
        let mut charts = grow_charts(scene, &rings, &graph, &HashSet::new());
        let mut sizing = match density {
            TexelDensity::MetresPerTexel(metres) => Sizing::Given(metres),
            TexelDensity::TargetResolution(side) => Sizing::Fitted { side, kept: true },
            TexelDensity::Automatic { minimum } => {
                let crowded = (2 * minimal_resolution(charts.len())).next_power_of_two();
                Sizing::Fitted {
                    side: minimum.max(crowded).min(16384),
                    kept: false,
                }
            }
        };
        let fit = |charts: &[Chart], sizing: Sizing| match sizing {
            Sizing::Given(metres) => Ok((metres, pack_charts(scene, charts, metres, None))),
            Sizing::Fitted { side, .. } => fit_resolution(scene, charts, side),
        };
        let (mut metres_per_texel, mut packed) = fit(&charts, sizing)?;
        if matches!(density, TexelDensity::Automatic { .. })
            && metres_per_texel > LARGEST_AUTOMATIC_TEXEL
        {
            sizing = Sizing::Given(LARGEST_AUTOMATIC_TEXEL);
            metres_per_texel = LARGEST_AUTOMATIC_TEXEL;
            packed = pack_charts(scene, &charts, metres_per_texel, None);
        }
        // Split at walls once the texel size is known, and keep it: the
        // automatic size follows the chart count, and real models' small
        // parts (column bases, mouldings) stand on many short edges.
        let mut split_at_walls = false;
        if let Some(walls) = walls {
            let mut walled =
                graph.walled_edges(scene, &rings, walls, WALL_EDGE_TEXELS * metres_per_texel);
            walled.extend(graph.seam_edges(&scene.lightmap_seams));
            if !walled.is_empty() {
                let split = grow_charts(scene, &rings, &graph, &walled);
                split_at_walls = split.len() > charts.len();
                if split_at_walls {
                    charts = split;
                }
            }
        }
        // A requested resolution is kept by coarsening every other chart,
        // so only a small chart's few texels are worth it there.
        let large_too = !matches!(sizing, Sizing::Fitted { kept: true, .. });
        let near_light_charts = if near_lights {
            refine_near_lights(scene, &mut charts, metres_per_texel, large_too)
        } else {
            0
        };
        if near_light_charts > 0 || split_at_walls {
            // Every other chart keeps the texel size it had, and so its
            // texels: an automatic atlas grows a few rows for the refined
            // or split charts rather than coarsening the rest; a
            // requested resolution is kept.
            packed = match sizing {
                Sizing::Given(metres) => pack_charts(scene, &charts, metres, None),
                Sizing::Fitted { side, kept } => {
                    let grown = pack_charts(scene, &charts, metres_per_texel, Some(side));
                    if kept && grown.0.max(grown.1) > side {
                        let refitted;
                        (metres_per_texel, refitted) = fit(&charts, sizing)?;
                        refitted
                    } else {
                        grown
                    }
                }
            };
        }
        let (width, height, triangle_uvs) = packed;
        if (width as u64) * (height as u64) > 16384 * 16384 {
            return Err(SceneError::Invalid {
                path: scene.source.clone(),
                message: format!(
                    "lightmap would be {width}x{height} texels at {metres_per_texel} m per texel: \
                     raise the texel size or give a lightmap resolution"
                ),
            });
        }
        let mut atlas = Self::rasterise(scene, width, height, triangle_uvs);
        atlas.chart_count = charts.len();
        atlas.triangle_texel_scales = vec![1.0; scene.mesh.triangles.len()];
        for chart in &charts {
            for &triangle in &chart.triangles {
                atlas.triangle_texel_scales[triangle as usize] = chart.texel_scale;
            }
        }
        if charts.iter().any(|chart| chart.small_near_light) {
            atlas.triangle_in_small_near_light_chart = vec![false; scene.mesh.triangles.len()];
            for chart in charts.iter().filter(|chart| chart.small_near_light) {
                for &triangle in &chart.triangles {
                    atlas.triangle_in_small_near_light_chart[triangle as usize] = true;
                }
            }
        }
        atlas.near_light_charts = near_light_charts;
        atlas.metres_per_texel = metres_per_texel;
        atlas.detail = detail.filter(|_| rings.iter().any(|&ring| ring > 0));
        Ok(atlas)
    }

    /// Uses the mesh's second UV set when it lies in [0,1] and no two
    /// triangles share a texel at the requested resolution.
    fn from_mesh_uvs(scene: &Scene, density: TexelDensity) -> Option<Self> {
        let mesh = &scene.mesh;
        if mesh.lightmap_uvs.len() != mesh.positions.len() || mesh.triangles.is_empty() {
            return None;
        }
        let resolution = match density {
            TexelDensity::TargetResolution(resolution) => resolution,
            TexelDensity::Automatic { minimum } => minimum,
            TexelDensity::MetresPerTexel(metres) => {
                ((mesh.total_area() as f32).sqrt() / metres / 0.7)
                    .ceil()
                    .clamp(8.0, 16384.0) as u32
            }
        };
        let in_unit_square = mesh
            .lightmap_uvs
            .iter()
            .all(|uv| uv.is_finite() && uv.min_element() >= 0.0 && uv.max_element() <= 1.0);
        if !in_unit_square {
            return None;
        }
        let scale = resolution as f32;
        let triangle_uvs: Vec<[Vec2; 3]> = mesh
            .triangles
            .iter()
            .map(|corners| corners.map(|vertex| mesh.lightmap_uvs[vertex as usize] * scale))
            .collect();
        // Overlap check: count texel centres claimed by more than one triangle.
        let mut owner: HashMap<u32, u32> = HashMap::new();
        for (triangle, uvs) in triangle_uvs.iter().enumerate() {
            let mut overlapping = false;
            for_each_texel_centre_inside(uvs, resolution, resolution, |texel| {
                if let Some(previous) = owner.insert(texel, triangle as u32) {
                    overlapping |= previous != triangle as u32;
                }
            });
            if overlapping {
                tracing::info!("the mesh's second UV set overlaps; generating a lightmap atlas");
                return None;
            }
        }
        // The texel size everything downstream scales by (receiver
        // relocation, the final gather's reach, PIC's cache spacing): the
        // mean over the surface, as the mesh's own UVs need not be uniform.
        let texel_area: f64 = triangle_uvs
            .iter()
            .map(|[a, b, c]| 0.5 * (*b - *a).perp_dot(*c - *a).abs() as f64)
            .sum();
        let mut atlas = Self::rasterise(scene, resolution, resolution, triangle_uvs);
        atlas.from_mesh_uvs = true;
        if texel_area > 0.0 {
            atlas.metres_per_texel = (mesh.total_area() / texel_area).sqrt() as f32;
        }
        Some(atlas)
    }

    fn rasterise(scene: &Scene, width: u32, height: u32, triangle_uvs: Vec<[Vec2; 3]>) -> Self {
        let texel_count = width as usize * height as usize;
        // Per texel, the best (distance-to-triangle, triangle) packed so that
        // an atomic min picks the same winner whatever the thread order.
        let best: Vec<AtomicU64> = (0..texel_count).map(|_| AtomicU64::new(u64::MAX)).collect();
        triangle_uvs
            .par_iter()
            .enumerate()
            .for_each(|(triangle, uvs)| {
                if scene.mesh.area(triangle) <= 0.0 {
                    return;
                }
                let lo = uvs[0].min(uvs[1]).min(uvs[2]).floor().max(Vec2::ZERO);
                let hi = uvs[0].max(uvs[1]).max(uvs[2]).ceil();
                let x_end = (hi.x as u32).min(width);
                let y_end = (hi.y as u32).min(height);
                for y in lo.y as u32..y_end {
                    for x in lo.x as u32..x_end {
                        let texel_min = Vec2::new(x as f32, y as f32);
                        if !triangle_overlaps_box(uvs, texel_min, texel_min + Vec2::ONE) {
                            continue;
                        }
                        let centre = texel_min + Vec2::splat(0.5);
                        let (distance, _) = closest_barycentric(uvs, centre);
                        let key = ((distance.to_bits() as u64) << 32) | triangle as u64;
                        best[y as usize * width as usize + x as usize]
                            .fetch_min(key, Ordering::Relaxed);
                    }
                }
            });
        let mut receiver_of_texel = vec![EMPTY; texel_count];
        let mut receivers = Receivers::default();
        for (texel, key) in best.iter().enumerate() {
            let key = key.load(Ordering::Relaxed);
            if key == u64::MAX {
                continue;
            }
            let triangle = (key & 0xFFFF_FFFF) as usize;
            let x = texel as u32 % width;
            let y = texel as u32 / width;
            let texel_min = Vec2::new(x as f32, y as f32);
            let centre = texel_min + Vec2::splat(0.5);
            let uvs = &triangle_uvs[triangle];
            // A border texel's centre lies off its triangle: the point of
            // the triangle nearest it stands for it, so a bilinear lookup,
            // which places every texel's value at its centre, extrapolates
            // least. (The middle of the covered part, tried instead, lies
            // up to half a texel inward: living room, PIC high, 8x8 tiles
            // 17.0 % with the nearest point, 23.4 % with the middle.)
            // Where that point sits on the line another surface meets,
            // `relocate_receivers` moves it off.
            let (_, barycentric) = closest_barycentric(uvs, centre);
            let [a, b, c] = scene.mesh.vertices(triangle);
            let position =
                a * (1.0 - barycentric.x - barycentric.y) + b * barycentric.x + c * barycentric.y;
            receiver_of_texel[texel] = receivers.len() as u32;
            receivers.texels.push([x, y]);
            receivers.positions.push(position);
            receivers
                .normals
                .push(scene.mesh.geometric_normal(triangle));
            receivers.triangles.push(triangle as u32);
            receivers.barycentrics.push(barycentric);
        }
        receivers.albedos = (0..receivers.len())
            .into_par_iter()
            .map(|index| {
                let triangle = receivers.triangles[index] as usize;
                let [x, y] = receivers.texels[index];
                texel_albedo(
                    scene,
                    triangle,
                    &triangle_uvs[triangle],
                    Vec2::new(x as f32, y as f32),
                    receivers.barycentrics[index],
                )
            })
            .collect();
        let dilation = dilation_list(width, height, &receiver_of_texel, &receivers, &triangle_uvs);
        Self {
            width,
            height,
            triangle_uvs,
            receiver_of_texel,
            receivers,
            dilation,
            from_mesh_uvs: false,
            chart_count: 0,
            near_light_charts: 0,
            triangle_in_small_near_light_chart: Vec::new(),
            triangle_texel_scales: Vec::new(),
            metres_per_texel: 0.0,
            detail: None,
        }
    }

    /// Fraction of atlas texels that cover geometry.
    pub fn coverage(&self) -> f64 {
        self.receivers.len() as f64 / (self.width as f64 * self.height as f64)
    }

    /// Scatters per-receiver values into a full lightmap and dilates it.
    pub fn to_lightmap(&self, per_receiver: &[Rgb]) -> Vec<Rgb> {
        let mut lightmap = vec![Rgb::ZERO; self.width as usize * self.height as usize];
        self.scatter_into(per_receiver, &mut lightmap);
        lightmap
    }

    /// Writes per-receiver values into an existing `width * height`
    /// lightmap and dilates it: the allocation-free form for every frame.
    /// Texels that cover no geometry and lie outside every gutter keep
    /// whatever they held.
    pub fn scatter_into(&self, per_receiver: &[Rgb], lightmap: &mut [Rgb]) {
        for (value, texel) in per_receiver.iter().zip(&self.receivers.texels) {
            lightmap[(texel[1] * self.width + texel[0]) as usize] = *value;
        }
        self.dilate(lightmap);
    }

    /// Shows seen texels in the hidden texels beside them, then copies
    /// covered texels into the gutter texels around them.
    pub fn dilate(&self, lightmap: &mut [Rgb]) {
        for &(target, source) in &self.dilation {
            lightmap[target as usize] = lightmap[source as usize];
        }
    }

    /// Makes each covered texel in `pairs` (texel, seen texel beside it)
    /// show its seen texel in every dilated lightmap and in
    /// [`Self::dilated_receiver_of_texel`], ahead of the gutters. The
    /// receivers keep their texels: a technique still addresses a hidden
    /// receiver's own value through [`Self::receiver_of_texel`] and
    /// [`Receivers::texels`]; only what the texel shows changes.
    ///
    /// Under an object that stands on or in a floor, the floor's texels
    /// are inside the object and their irradiance is zero; every bilinear
    /// footprint beside the object's foot (the renderer's, the final
    /// gather's, an engine's texture filter) would blend those zeros in, a
    /// dark halo around the foot.
    pub fn fill_hidden(&mut self, mut pairs: Vec<(u32, u32)>) {
        pairs.sort_unstable();
        pairs.dedup_by_key(|pair| pair.0);
        let receiver_of_texel = &self.receiver_of_texel;
        self.dilation
            .retain(|&(target, _)| receiver_of_texel[target as usize] == EMPTY);
        self.dilation.splice(0..0, pairs);
    }

    /// How many covered texels show another texel ([`Self::fill_hidden`]):
    /// the dilation pairs whose target is covered.
    pub fn filled_texels(&self) -> usize {
        self.dilation
            .iter()
            .take_while(|&&(target, _)| self.receiver_of_texel[target as usize] != EMPTY)
            .count()
    }

    /// Texel-space UV of a point on a triangle.
    #[inline]
    pub fn uv_of(&self, triangle: u32, barycentric: Vec2) -> Vec2 {
        let [a, b, c] = self.triangle_uvs[triangle as usize];
        a * (1.0 - barycentric.x - barycentric.y) + b * barycentric.x + c * barycentric.y
    }

    /// The receiver every texel shows: its own, or for hidden and gutter
    /// texels the receiver of the texel they copy (`u32::MAX` where
    /// neither): what a lookup that lands on a texel should read.
    pub fn dilated_receiver_of_texel(&self) -> Vec<u32> {
        let mut receivers = self.receiver_of_texel.clone();
        for &(target, source) in &self.dilation {
            receivers[target as usize] = receivers[source as usize];
        }
        receivers
    }

    /// The four texels around a surface point for a bilinear lookup (texel
    /// centres at half-integer UVs, clamped at the atlas edge), as (texel
    /// index, weight) in the order (x0, y0), (x1, y0), (x0, y1), (x1, y1).
    /// For lookups that skip texels with nothing in them and renormalise;
    /// inlined so that the taps stay in registers (per-pixel shading).
    #[inline]
    pub fn bilinear_texels(&self, triangle: u32, barycentric: Vec2) -> [(usize, f32); 4] {
        let ([upper_left, upper_right, lower_left, lower_right], fx, fy) =
            self.bilinear_footprint(triangle, barycentric);
        [
            (upper_left, (1.0 - fx) * (1.0 - fy)),
            (upper_right, fx * (1.0 - fy)),
            (lower_left, (1.0 - fx) * fy),
            (lower_right, fx * fy),
        ]
    }

    /// Bilinear lookup of a dilated lightmap at a point on a triangle.
    /// Renderers call this per pixel: inlined, with the four fetches as
    /// straight-line code.
    #[inline]
    pub fn sample(&self, lightmap: &[Rgb], triangle: u32, barycentric: Vec2) -> Rgb {
        let ([upper_left, upper_right, lower_left, lower_right], fx, fy) =
            self.bilinear_footprint(triangle, barycentric);
        let top = lightmap[upper_left].lerp(lightmap[upper_right], fx);
        let bottom = lightmap[lower_left].lerp(lightmap[lower_right], fx);
        top.lerp(bottom, fy)
    }

    /// [`Atlas::sample`] of the lightmap that [`Self::scatter_into`] would
    /// make from `per_receiver`, read through `shown_receiver` (from
    /// [`Self::dilated_receiver_of_texel`]) instead: the same four texels
    /// and the same lerps, so the same bits, without scattering and
    /// dilating a full map every frame for lookups that read a few texels.
    #[inline]
    pub fn sample_receivers(
        &self,
        shown_receiver: &[u32],
        per_receiver: &[Rgb],
        triangle: u32,
        barycentric: Vec2,
    ) -> Rgb {
        let ([upper_left, upper_right, lower_left, lower_right], fx, fy) =
            self.bilinear_footprint(triangle, barycentric);
        let value = |texel: usize| match shown_receiver[texel] {
            EMPTY => Rgb::ZERO,
            receiver => per_receiver[receiver as usize],
        };
        let top = value(upper_left).lerp(value(upper_right), fx);
        let bottom = value(lower_left).lerp(value(lower_right), fx);
        top.lerp(bottom, fy)
    }

    /// [`Atlas::sample`] of a packed lightmap, the four texels decoded and
    /// weighted together (4-wide on x86-64). `texel_value` gives a texel's
    /// packed value: a plain lightmap indexes itself, a lightmap kept as
    /// values plus a texel-to-slot map goes through the map.
    #[inline]
    pub fn sample_packed(
        &self,
        texel_value: impl Fn(usize) -> Rgb9e5,
        triangle: u32,
        barycentric: Vec2,
    ) -> Rgb {
        // The footprint inlines here, so texel indices and weights stay in
        // registers; through `bilinear_texels` (a call returning them in
        // memory) the weights came back as a 16-byte load of four 4-byte
        // stores, which the store buffer cannot forward.
        let ([upper_left, upper_right, lower_left, lower_right], fx, fy) =
            self.bilinear_footprint(triangle, barycentric);
        relight_core::colour::bilinear_rgb9e5(
            [
                texel_value(upper_left),
                texel_value(upper_right),
                texel_value(lower_left),
                texel_value(lower_right),
            ],
            [
                (1.0 - fx) * (1.0 - fy),
                fx * (1.0 - fy),
                (1.0 - fx) * fy,
                fx * fy,
            ],
        )
    }

    /// The texels (x0, y0), (x1, y0), (x0, y1), (x1, y1) around a point,
    /// clamped at the atlas edge, and the fractions toward x1 and y1.
    #[inline]
    fn bilinear_footprint(&self, triangle: u32, barycentric: Vec2) -> ([usize; 4], f32, f32) {
        let uv = self.uv_of(triangle, barycentric) - Vec2::splat(0.5);
        let (x0, y0) = (floor_small(uv.x), floor_small(uv.y));
        let (fx, fy) = (uv.x - x0, uv.y - y0);
        let (max_x, max_y) = (self.width as i64 - 1, self.height as i64 - 1);
        let (x0, y0) = (x0 as i64, y0 as i64);
        let column = |x: i64| x.clamp(0, max_x) as usize;
        let row = |y: i64| y.clamp(0, max_y) as usize * self.width as usize;
        let (left, right) = (column(x0), column(x0 + 1));
        let (upper, lower) = (row(y0), row(y0 + 1));
        (
            [upper + left, upper + right, lower + left, lower + right],
            fx,
            fy,
        )
    }

    pub fn memory_bytes(&self) -> usize {
        self.triangle_uvs.len() * std::mem::size_of::<[Vec2; 3]>()
            + self.receiver_of_texel.len() * 4
            + self.receivers.len() * (8 + 12 + 12 + 4 + 8 + 12)
            + self.dilation.len() * 8
            + self.triangle_texel_scales.len() * 4
            + self.triangle_in_small_near_light_chart.len()
    }
}

/// `value.floor()` for texel coordinates (finite, well inside the i32
/// range), without the libm call that `f32::floor` compiles to on x86-64
/// without SSE4.1; per-pixel bilinear lookups use it. NaN gives 0.
#[inline]
pub(crate) fn floor_small(value: f32) -> f32 {
    let truncated = value as i32 as f32;
    if truncated > value {
        truncated - 1.0
    } else {
        truncated
    }
}

fn density_is_invalid(density: TexelDensity) -> bool {
    match density {
        TexelDensity::MetresPerTexel(metres) => !(metres.is_finite() && metres > 0.0),
        TexelDensity::TargetResolution(resolution)
        | TexelDensity::Automatic {
            minimum: resolution,
        } => !(8..=16384).contains(&resolution),
    }
}

/// Smallest square side that holds `chart_count` charts shrunk to one texel
/// each, with their gutter rings, in shelves: no texel size fits below it.
fn minimal_resolution(chart_count: usize) -> u32 {
    let smallest_chart = 2 * GUTTER_TEXELS + 2;
    let fits = |side: u32| {
        let per_row = (side / smallest_chart).max(1) as usize;
        chart_count.div_ceil(per_row) as u32 * smallest_chart <= side
    };
    (8..=16384).find(|&side| fits(side)).unwrap_or(16384)
}

/// The largest texel edge (m) an automatic atlas takes inside the detail
/// region. A fixed texel count spreads a large, plainly modelled hall over
/// texels a metre wide, wider than the windows its sun comes through: a
/// texel's light is its centre's, so a sun patch smaller than a texel
/// reads all or nothing, and the light it bounces is placed a texel off.
/// Generated halls lit by a sun through windows lost up to a fifth of
/// their indirect light that way, and got it back at half-metre texels;
/// rooms and real models already have finer texels than this. A model's
/// own lightmap UVs are used as they are.
pub const LARGEST_AUTOMATIC_TEXEL: f32 = 0.5;

/// How an atlas's texel size is found: given, or fitted to a square side
/// that a requested resolution keeps and an automatic one may outgrow by a
/// few rows for charts refined near lights.
#[derive(Clone, Copy)]
enum Sizing {
    Given(f32),
    Fitted { side: u32, kept: bool },
}

/// A chart: triangles, the plane basis they are projected onto and its
/// texel size relative to the detail region's.
struct Chart {
    triangles: Vec<u32>,
    tangent: Vec3,
    bitangent: Vec3,
    texel_scale: f32,
    /// Refined near a light as a small chart, all of it near the light.
    small_near_light: bool,
}

/// A chart near a point or spot light gets texels no longer than its
/// distance to the light over this: the light's irradiance falls as 1/d^2,
/// so a texel a quarter of d across varies about 1.5x from edge to edge.
/// The final gather samples the surfaces nearer a light than this many of
/// their texels explicitly, for the same reason.
pub const NEAR_LIGHT_DISTANCE_PER_TEXEL: f32 = 4.0;

/// Texel edges near a light are at most this many times finer than the
/// detail region's.
const NEAR_LIGHT_FINEST_SCALE: f32 = 0.125;

/// A small chart refined near a light holds at most this many texels.
const NEAR_LIGHT_CHART_TEXELS: f32 = 256.0;

/// Charts of at most this many texels at the room's texel size are small:
/// a lampshade's face (one or two texels). They are refined to
/// [`NEAR_LIGHT_CHART_TEXELS`] at most, whatever the atlas's sizing.
const NEAR_LIGHT_SMALL_CHART_TEXELS: f32 = 16.0;

/// A larger chart refined near a light (a wall or floor beside a lamp)
/// holds at most this many texels: on a 7 m room's 21 m^2 wall, 7 cm
/// texels. Its light varies fast only near the lamp, but a chart has one
/// texel size, so the budget bounds what the rest of it costs.
const NEAR_LIGHT_LARGE_CHART_TEXELS: f32 = 4096.0;

/// Gives the charts that stand near a point or spot light of the scene
/// file, and face it, finer texels; returns how many changed. Small charts
/// are refined always; larger ones only when `large_too` (an atlas whose
/// size follows its charts, not a requested resolution, where every other
/// chart's texels would pay for them: the shipped two rooms at a 64-texel
/// lightmap, 4 charts near the light made every other texel 26 % longer).
///
/// A light inside a shade, a sconce or a recess heats the few square
/// decimetres around it hundreds of times brighter than the room, and much
/// of the light that leaves it has bounced inside first (a 32 cm shade of
/// albedo 0.75, open below, lets about 14 % of the light out directly and,
/// by a cavity estimate, about twice that after bounces off its inside). At
/// a room's texel size such a shade is one or two texels a face: the light
/// at one point of each stands for a face over which it varies fivefold,
/// and the bounces inside are not resolved, so every technique lit the
/// rooms of such lamps too dark. A chart's back (the shade's outside) is
/// lit as the rest of the room is and keeps its texels: refined too, it
/// made SRP's room brighter than the path tracer's.
///
/// A lamp a few centimetres from a corner makes a hot spot a few of its
/// distances wide on each wall, and the walls light each other from
/// them: their indirect light varies over a decimetre where a room's
/// texels are 20 cm (a generated 7 m room with a lamp 11 cm from a corner:
/// 25 % over tiles with every technique, 8 % at 10 cm texels). So a larger
/// chart within four of its texels of a light is refined, within
/// [`NEAR_LIGHT_LARGE_CHART_TEXELS`], when another chart turned from it by
/// more than 60 degrees is that near the same light too.
///
/// Only the charts near the lights change, so a scene whose lights stand
/// in the open keeps its atlas. The lights are those of the scene file: a
/// light moved at run time leaves the refinement where the file put it.
fn refine_near_lights(
    scene: &Scene,
    charts: &mut [Chart],
    metres_per_texel: f32,
    large_too: bool,
) -> usize {
    let positions: Vec<Vec3> = scene
        .lights
        .iter()
        .filter_map(crate::Light::position)
        .collect();
    if positions.is_empty() || metres_per_texel.is_nan() || metres_per_texel <= 0.0 {
        return 0;
    }
    let small = NEAR_LIGHT_SMALL_CHART_TEXELS * metres_per_texel * metres_per_texel;
    let reach = NEAR_LIGHT_DISTANCE_PER_TEXEL * metres_per_texel;
    let mesh = &scene.mesh;
    // Per chart of the detail region: its area, its mean normal and its
    // distance to each light in front of it (infinite for the others).
    let measured: Vec<Option<(f32, Vec3, Vec<f32>)>> = charts
        .iter()
        .map(|chart| {
            if chart.texel_scale != 1.0 {
                return None;
            }
            let mut area = 0.0;
            let mut normal = Vec3::ZERO;
            let mut low = Vec3::splat(f32::INFINITY);
            let mut high = Vec3::splat(f32::NEG_INFINITY);
            for &triangle in &chart.triangles {
                let triangle = triangle as usize;
                let triangle_area = mesh.area(triangle);
                area += triangle_area;
                normal += mesh.geometric_normal(triangle) * triangle_area;
                for vertex in mesh.vertices(triangle) {
                    low = low.min(vertex);
                    high = high.max(vertex);
                }
            }
            // Only a light in front of the chart lights it directly; its
            // back (a shade's outside) is lit as the rest of the room is.
            let distances = positions
                .iter()
                .map(|&light| {
                    let faces = chart
                        .triangles
                        .iter()
                        .any(|&triangle| mesh.faces_point(triangle as usize, light));
                    if faces {
                        light.clamp(low, high).distance(light)
                    } else {
                        f32::INFINITY
                    }
                })
                .collect();
            Some((area, normal.normalize_or_zero(), distances))
        })
        .collect();
    // A large chart's indirect light varies fast near a light only where
    // another surface, turned from it by more than 60 degrees, is near the
    // light too (a corner, a wall's foot): each lights the other from its
    // hot spot. A ceiling above a lamp in the open has a hot spot of direct
    // light, which the indirect lightmap does not hold, and keeps its
    // texels.
    let corner_distance = |index: usize| -> f32 {
        let Some((_, normal, distances)) = &measured[index] else {
            return f32::INFINITY;
        };
        (0..positions.len())
            .filter(|&light| distances[light] < reach)
            .filter(|&light| {
                measured.iter().enumerate().any(|(other, entry)| {
                    other != index
                        && entry
                            .as_ref()
                            .is_some_and(|(_, other_normal, other_distances)| {
                                other_distances[light] < reach
                                    && normal.dot(*other_normal).abs() < 0.5
                            })
                })
            })
            .map(|light| distances[light])
            .fold(f32::INFINITY, f32::min)
    };
    let mut refined = 0;
    for index in 0..charts.len() {
        let Some((area, _, distances)) = &measured[index] else {
            continue;
        };
        let is_small = *area <= small;
        let distance = if is_small {
            distances.iter().copied().fold(f32::INFINITY, f32::min)
        } else if large_too {
            corner_distance(index)
        } else {
            continue;
        };
        let wanted = distance / NEAR_LIGHT_DISTANCE_PER_TEXEL / metres_per_texel;
        let budget = if is_small {
            NEAR_LIGHT_CHART_TEXELS
        } else {
            NEAR_LIGHT_LARGE_CHART_TEXELS
        };
        let within_budget = (area / budget).sqrt() / metres_per_texel;
        let scale = wanted.max(within_budget).max(NEAR_LIGHT_FINEST_SCALE);
        if scale < 1.0 {
            charts[index].texel_scale = scale;
            charts[index].small_near_light = is_small;
            refined += 1;
        }
    }
    refined
}

/// The mesh's triangles joined by their edges, vertices welded by position
/// so meshes with split vertices still connect: built once, grown into
/// charts with and without walls.
struct EdgeGraph {
    /// Welded vertex of each position's bits.
    welded: HashMap<[u32; 3], u32>,
    vertex_id: Vec<u32>,
    /// Per welded vertex, its position.
    welded_positions: Vec<Vec3>,
    edge_triangles: HashMap<(u32, u32), Vec<u32>>,
    normals: Vec<Vec3>,
}

impl EdgeGraph {
    fn of(scene: &Scene) -> Self {
        let mesh = &scene.mesh;
        let mut welded: HashMap<[u32; 3], u32> = HashMap::new();
        let mut welded_positions = Vec::new();
        let vertex_id: Vec<u32> = mesh
            .positions
            .iter()
            .map(|p| {
                let key = [p.x.to_bits(), p.y.to_bits(), p.z.to_bits()];
                let next = welded.len() as u32;
                *welded.entry(key).or_insert_with(|| {
                    welded_positions.push(*p);
                    next
                })
            })
            .collect();
        let mut edge_triangles: HashMap<(u32, u32), Vec<u32>> = HashMap::new();
        for (triangle, corners) in mesh.triangles.iter().enumerate() {
            for corner in 0..3 {
                let a = vertex_id[corners[corner] as usize];
                let b = vertex_id[corners[(corner + 1) % 3] as usize];
                edge_triangles
                    .entry((a.min(b), a.max(b)))
                    .or_default()
                    .push(triangle as u32);
            }
        }
        let normals = (0..mesh.triangles.len())
            .map(|t| mesh.geometric_normal(t))
            .collect();
        Self {
            welded,
            vertex_id,
            welded_positions,
            edge_triangles,
            normals,
        }
    }

    /// The mesh's edges among `seams` (pairs of vertex positions, bit for
    /// bit; [`Scene::lightmap_seams`]).
    fn seam_edges(&self, seams: &[[Vec3; 2]]) -> HashSet<(u32, u32)> {
        let id = |p: Vec3| self.welded.get(&p.to_array().map(f32::to_bits)).copied();
        seams
            .iter()
            .filter_map(|&[a, b]| {
                let (a, b) = (id(a)?, id(b)?);
                let edge = (a.min(b), a.max(b));
                self.edge_triangles.contains_key(&edge).then_some(edge)
            })
            .collect()
    }

    /// The edges of two triangles a chart could join (area, ring, normals
    /// within the chart cone) that are at least `least_length` long at
    /// their ring's texel scale and that `walls` finds a surface standing
    /// on; tested once each, in parallel, before the charts grow.
    fn walled_edges(
        &self,
        scene: &Scene,
        rings: &[u32],
        walls: StandsOnEdge,
        least_length: f32,
    ) -> HashSet<(u32, u32)> {
        let mesh = &scene.mesh;
        let normals = &self.normals;
        let mut joinable: Vec<((u32, u32), (Vec3, u32))> = self
            .edge_triangles
            .iter()
            .filter_map(|(&edge, triangles)| {
                let joined = triangles.iter().enumerate().find_map(|(i, &t)| {
                    triangles[i + 1..].iter().find_map(|&u| {
                        let (t, u) = (t as usize, u as usize);
                        (mesh.area(t) > 0.0
                            && mesh.area(u) > 0.0
                            && rings[t] == rings[u]
                            && normals[t].dot(normals[u]) >= CHART_NORMAL_COS)
                            .then(|| ((normals[t] + normals[u]).normalize_or_zero(), rings[t]))
                    })
                })?;
                Some((edge, joined))
            })
            .collect();
        joinable.sort_unstable_by_key(|&(edge, _)| edge);
        joinable
            .par_iter()
            .filter(|&&((a, b), (normal, ring))| {
                let (a, b) = (
                    self.welded_positions[a as usize],
                    self.welded_positions[b as usize],
                );
                a.distance(b) >= least_length * DetailRegion::texel_scale(ring)
                    && walls(a, b, normal)
            })
            .map(|&(edge, _)| edge)
            .collect()
    }
}

/// Grows charts by flood fill over shared edges other than the `walled`
/// ones, in triangle order, so the result is deterministic; a chart keeps
/// to its seed's ring of detail.
fn grow_charts(
    scene: &Scene,
    rings: &[u32],
    graph: &EdgeGraph,
    walled: &HashSet<(u32, u32)>,
) -> Vec<Chart> {
    let mesh = &scene.mesh;
    let triangle_count = mesh.triangles.len();
    let EdgeGraph {
        vertex_id,
        edge_triangles,
        normals,
        ..
    } = graph;
    let mut chart_of = vec![u32::MAX; triangle_count];
    let mut charts = Vec::new();
    let mut stack = Vec::new();
    for seed in 0..triangle_count {
        if chart_of[seed] != u32::MAX || mesh.area(seed) <= 0.0 {
            continue;
        }
        let chart_index = charts.len() as u32;
        let seed_normal = normals[seed];
        let mut members = vec![seed as u32];
        chart_of[seed] = chart_index;
        stack.push(seed as u32);
        while let Some(triangle) = stack.pop() {
            let corners = mesh.triangles[triangle as usize];
            for corner in 0..3 {
                let a = vertex_id[corners[corner] as usize];
                let b = vertex_id[corners[(corner + 1) % 3] as usize];
                let edge = (a.min(b), a.max(b));
                if walled.contains(&edge) {
                    continue;
                }
                for &neighbour in &edge_triangles[&edge] {
                    let n = neighbour as usize;
                    if chart_of[n] == u32::MAX
                        && mesh.area(n) > 0.0
                        && rings[n] == rings[seed]
                        && normals[n].dot(seed_normal) >= CHART_NORMAL_COS
                    {
                        chart_of[n] = chart_index;
                        members.push(neighbour);
                        stack.push(neighbour);
                    }
                }
            }
        }
        members.sort_unstable();
        let (tangent, bitangent) = chart_axes(scene, &members, seed_normal);
        charts.push(Chart {
            triangles: members,
            tangent,
            bitangent,
            texel_scale: DetailRegion::texel_scale(rings[seed]),
            small_near_light: false,
        });
    }
    charts
}

/// In-plane axes along the chart edge direction whose bounding rectangle is
/// smallest (edges of a few dozen triangles are tried), so axis-aligned walls
/// and quads pack as tight rectangles rather than diamonds.
fn chart_axes(scene: &Scene, members: &[u32], normal: Vec3) -> (Vec3, Vec3) {
    let mut points: Vec<Vec3> = Vec::with_capacity(members.len() * 3);
    for &triangle in members {
        points.extend(scene.mesh.vertices(triangle as usize));
    }
    let fallback = relight_core::sampling::orthonormal_basis(normal).0;
    let mut best = (f32::INFINITY, fallback);
    for &triangle in members.iter().take(32) {
        let [a, b, c] = scene.mesh.vertices(triangle as usize);
        for edge in [b - a, c - b, a - c] {
            let tangent = (edge - normal * edge.dot(normal)).normalize_or_zero();
            if tangent == Vec3::ZERO {
                continue;
            }
            let bitangent = normal.cross(tangent);
            let mut lo = Vec2::splat(f32::INFINITY);
            let mut hi = Vec2::splat(f32::NEG_INFINITY);
            for point in &points {
                let projected = Vec2::new(point.dot(tangent), point.dot(bitangent));
                lo = lo.min(projected);
                hi = hi.max(projected);
            }
            let extent = hi - lo;
            let area = extent.x * extent.y;
            // Strictly smaller wins, so the first of equal candidates stays.
            if area < best.0 * (1.0 - 1e-5) {
                best = (area, tangent);
            }
        }
    }
    (best.1, normal.cross(best.1))
}

/// Finds the smallest texel size whose packing fits a `resolution` square:
/// geometric growth from the perfect-packing bound, then bisection.
#[allow(clippy::type_complexity)]
fn fit_resolution(
    scene: &Scene,
    charts: &[Chart],
    resolution: u32,
) -> Result<(f32, (u32, u32, Vec<[Vec2; 3]>)), SceneError> {
    // However large the texels, every chart keeps its gutter ring and one
    // texel: below this side no texel size fits.
    let needed = minimal_resolution(charts.len());
    if needed > resolution {
        return Err(SceneError::Invalid {
            path: scene.source.clone(),
            message: format!(
                "a {resolution}x{resolution} lightmap cannot hold this scene's {} charts with their gutters: \
                 use a lightmap resolution of at least {}, or leave it automatic",
                charts.len(),
                (needed as f64 * 1.5).ceil() as u32
            ),
        });
    }
    let fits = |metres: f32| {
        let packed = pack_charts(scene, charts, metres, Some(resolution));
        (packed.0.max(packed.1) <= resolution, packed)
    };
    // Area in detail-region texels: a chart of ring k covers 4^k times less.
    // At full density everywhere it is the mesh's own sum, in its order, so
    // those atlases come out bit for bit as before rings existed.
    let uniform = charts.iter().all(|chart| chart.texel_scale == 1.0);
    let effective_area = if uniform {
        scene.mesh.total_area()
    } else {
        charts
            .iter()
            .map(|chart| {
                let area: f64 = chart
                    .triangles
                    .iter()
                    .map(|&triangle| scene.mesh.area(triangle as usize) as f64)
                    .sum();
                area / (chart.texel_scale as f64).powi(2)
            })
            .sum::<f64>()
    };
    let total_area = effective_area.max(1e-12) as f32;
    let mut too_small = (total_area / (resolution as f32).powi(2)).sqrt();
    let (first_fits, first) = fits(too_small);
    if first_fits {
        return Ok((too_small, first));
    }
    let mut large_enough = too_small;
    let mut growth_steps = 0;
    let mut packed = loop {
        large_enough *= 1.5;
        growth_steps += 1;
        let (ok, packed) = fits(large_enough);
        if ok {
            break packed;
        }
        // 1.5^40 is a 10^7-fold texel size: charts are single texels by then.
        if growth_steps > 40 {
            return Err(SceneError::Invalid {
                path: scene.source.clone(),
                message: format!("no texel size fits a {resolution}x{resolution} lightmap: raise the lightmap resolution"),
            });
        }
        too_small = large_enough;
    };
    // Bisection to within 1 % of the smallest texel size that fits.
    while large_enough / too_small > 1.01 {
        let middle = (too_small * large_enough).sqrt();
        let (ok, candidate) = fits(middle);
        if ok {
            large_enough = middle;
            packed = candidate;
        } else {
            too_small = middle;
        }
    }
    Ok((large_enough, packed))
}

/// Projects charts at `metres_per_texel` and shelf-packs them; returns the
/// atlas size and every triangle's texel-space UVs.
/// `shelf_width` fixes the atlas width (a target resolution); otherwise the
/// width is chosen for a roughly square atlas.
fn pack_charts(
    scene: &Scene,
    charts: &[Chart],
    metres_per_texel: f32,
    shelf_width: Option<u32>,
) -> (u32, u32, Vec<[Vec2; 3]>) {
    let mut triangle_uvs = vec![[Vec2::ZERO; 3]; scene.mesh.triangles.len()];
    // Project each chart into its own texel frame with origin at its minimum.
    let mut sizes = Vec::with_capacity(charts.len());
    for chart in charts {
        let mut lo = Vec2::splat(f32::INFINITY);
        let mut hi = Vec2::splat(f32::NEG_INFINITY);
        let chart_metres = metres_per_texel * chart.texel_scale;
        for &triangle in &chart.triangles {
            let vertices = scene.mesh.vertices(triangle as usize);
            let uvs = vertices
                .map(|p| Vec2::new(p.dot(chart.tangent), p.dot(chart.bitangent)) / chart_metres);
            for uv in uvs {
                lo = lo.min(uv);
                hi = hi.max(uv);
            }
            triangle_uvs[triangle as usize] = uvs;
        }
        for &triangle in &chart.triangles {
            for uv in &mut triangle_uvs[triangle as usize] {
                *uv -= lo;
            }
        }
        let extent = (hi - lo).max(Vec2::ZERO);
        // Size in whole texels including the gutter on both sides.
        let size = (extent.ceil() + Vec2::splat(2.0 * GUTTER_TEXELS as f32 + 1.0)).as_uvec2();
        sizes.push(size);
    }
    let total_area: f64 = sizes.iter().map(|s| s.x as f64 * s.y as f64).sum();
    let widest = sizes.iter().map(|s| s.x).max().unwrap_or(1);
    let width = shelf_width
        .unwrap_or((total_area.sqrt() * 1.05).ceil() as u32)
        .max(widest)
        .max(8);
    // Shelf packing, tallest first; ties broken by chart index for determinism.
    let mut order: Vec<usize> = (0..charts.len()).collect();
    order.sort_by(|&a, &b| {
        sizes[b]
            .y
            .cmp(&sizes[a].y)
            .then(sizes[b].x.cmp(&sizes[a].x))
            .then(a.cmp(&b))
    });
    let (mut cursor_x, mut shelf_y, mut shelf_height) = (0u32, 0u32, 0u32);
    for index in order {
        let size = sizes[index];
        if cursor_x + size.x > width {
            shelf_y += shelf_height;
            cursor_x = 0;
            shelf_height = 0;
        }
        let offset =
            Vec2::new(cursor_x as f32, shelf_y as f32) + Vec2::splat(GUTTER_TEXELS as f32 + 0.5);
        for &triangle in &charts[index].triangles {
            for uv in &mut triangle_uvs[triangle as usize] {
                *uv += offset;
            }
        }
        cursor_x += size.x;
        shelf_height = shelf_height.max(size.y);
    }
    let height = (shelf_y + shelf_height).max(8);
    (width, height, triangle_uvs)
}

/// For each empty texel within the gutter of a covered one, the covered
/// texel to copy: the nearest covered texel (Chebyshev rings, then squared
/// distance, then index) among those whose triangles' UV footprint reaches the
/// empty texel's bilinear neighbourhood, so values never cross charts.
fn dilation_list(
    width: u32,
    height: u32,
    receiver_of_texel: &[u32],
    receivers: &Receivers,
    triangle_uvs: &[[Vec2; 3]],
) -> Vec<(u32, u32)> {
    let radius = GUTTER_TEXELS as i64;
    let mut list = Vec::new();
    for y in 0..height as i64 {
        for x in 0..width as i64 {
            let texel = (y * width as i64 + x) as usize;
            if receiver_of_texel[texel] != EMPTY {
                continue;
            }
            let centre = Vec2::new(x as f32 + 0.5, y as f32 + 0.5);
            let mut best: Option<(f32, i64, u32)> = None;
            for dy in -radius..=radius {
                for dx in -radius..=radius {
                    let (sx, sy) = (x + dx, y + dy);
                    if sx < 0 || sy < 0 || sx >= width as i64 || sy >= height as i64 {
                        continue;
                    }
                    let source = (sy * width as i64 + sx) as usize;
                    let receiver = receiver_of_texel[source];
                    if receiver == EMPTY {
                        continue;
                    }
                    // Only texels whose triangle is close to this texel in UV
                    // belong to the same chart as any bilinear lookup here.
                    let uvs = &triangle_uvs[receivers.triangles[receiver as usize] as usize];
                    let (uv_distance, _) = closest_barycentric(uvs, centre);
                    if uv_distance > radius as f32 + 0.75 {
                        continue;
                    }
                    let distance = (dx * dx + dy * dy) as f32;
                    let candidate = (distance, source as i64, source as u32);
                    if best.is_none_or(|b| (candidate.0, candidate.1) < (b.0, b.1)) {
                        best = Some(candidate);
                    }
                }
            }
            if let Some((_, _, source)) = best {
                list.push((texel as u32, source));
            }
        }
    }
    list
}

/// Calls `visit` with the index of every texel whose centre lies inside the
/// triangle (used for the overlap test of mesh-provided UVs).
fn for_each_texel_centre_inside(
    uvs: &[Vec2; 3],
    width: u32,
    height: u32,
    mut visit: impl FnMut(u32),
) {
    let lo = uvs[0].min(uvs[1]).min(uvs[2]).floor().max(Vec2::ZERO);
    let hi = uvs[0].max(uvs[1]).max(uvs[2]).ceil();
    for y in lo.y as u32..(hi.y as u32).min(height) {
        for x in lo.x as u32..(hi.x as u32).min(width) {
            let centre = Vec2::new(x as f32 + 0.5, y as f32 + 0.5);
            if closest_barycentric(uvs, centre).0 == 0.0 {
                visit(y * width + x);
            }
        }
    }
}

/// Distance from `point` to the 2D triangle and the barycentric (b1, b2) of
/// the closest point (Ericson, Real-Time Collision Detection 5.1.5).
pub fn closest_barycentric(uvs: &[Vec2; 3], point: Vec2) -> (f32, Vec2) {
    let [a, b, c] = *uvs;
    let ab = b - a;
    let ac = c - a;
    let ap = point - a;
    let d1 = ab.dot(ap);
    let d2 = ac.dot(ap);
    if d1 <= 0.0 && d2 <= 0.0 {
        return (point.distance(a), Vec2::ZERO);
    }
    let bp = point - b;
    let d3 = ab.dot(bp);
    let d4 = ac.dot(bp);
    if d3 >= 0.0 && d4 <= d3 {
        return (point.distance(b), Vec2::new(1.0, 0.0));
    }
    let vc = d1 * d4 - d3 * d2;
    if vc <= 0.0 && d1 >= 0.0 && d3 <= 0.0 {
        let v = d1 / (d1 - d3);
        return (point.distance(a + ab * v), Vec2::new(v, 0.0));
    }
    let cp = point - c;
    let d5 = ab.dot(cp);
    let d6 = ac.dot(cp);
    if d6 >= 0.0 && d5 <= d6 {
        return (point.distance(c), Vec2::new(0.0, 1.0));
    }
    let vb = d5 * d2 - d1 * d6;
    if vb <= 0.0 && d2 >= 0.0 && d6 <= 0.0 {
        let w = d2 / (d2 - d6);
        return (point.distance(a + ac * w), Vec2::new(0.0, w));
    }
    let va = d3 * d6 - d5 * d4;
    if va <= 0.0 && (d4 - d3) >= 0.0 && (d5 - d6) >= 0.0 {
        let w = (d4 - d3) / ((d4 - d3) + (d5 - d6));
        let closest = b + (c - b) * w;
        return (point.distance(closest), Vec2::new(1.0 - w, w));
    }
    let denominator = va + vb + vc;
    if denominator.abs() < 1e-30 {
        // Degenerate in UV: fall back to the nearest corner.
        return (point.distance(a), Vec2::ZERO);
    }
    let v = vb / denominator;
    let w = vc / denominator;
    (0.0, Vec2::new(v, w))
}

/// Centroid of the part of the unit texel at `texel_min` that the 2D
/// triangle covers (Sutherland-Hodgman clipping), or None where the overlap
/// has no area.
/// Sub-samples a side of a texel for its mean albedo.
const ALBEDO_SUBSAMPLES: u32 = 8;

/// The mean albedo over the part of a texel that `triangle` covers: what
/// the texel reflects on average, which a path that lands anywhere in it
/// sees. A texture sampled at the texel's centre alone is one draw of its
/// pattern; on Sponza, whose 15 cm texels span a brick or a frieze, that
/// draw is off the mean by tens of per cent, and the light the texel
/// reflects with it. Untextured materials are uniform and take one sample.
fn texel_albedo(
    scene: &Scene,
    triangle: usize,
    uvs: &[Vec2; 3],
    texel_min: Vec2,
    centre_barycentric: Vec2,
) -> Rgb {
    let centre = scene.albedo_at(triangle, centre_barycentric);
    if scene.material_of(triangle).albedo_texture.is_none() {
        return centre;
    }
    let mut sum = Rgb::ZERO;
    let mut count = 0u32;
    let step = 1.0 / ALBEDO_SUBSAMPLES as f32;
    for j in 0..ALBEDO_SUBSAMPLES {
        for i in 0..ALBEDO_SUBSAMPLES {
            let point = texel_min + Vec2::new((i as f32 + 0.5) * step, (j as f32 + 0.5) * step);
            let (distance, barycentric) = closest_barycentric(uvs, point);
            if distance == 0.0 {
                sum += scene.albedo_at(triangle, barycentric);
                count += 1;
            }
        }
    }
    if count == 0 {
        centre
    } else {
        sum / count as f32
    }
}

/// Separating-axis test of a 2D triangle against an axis-aligned box.
fn triangle_overlaps_box(uvs: &[Vec2; 3], box_min: Vec2, box_max: Vec2) -> bool {
    let lo = uvs[0].min(uvs[1]).min(uvs[2]);
    let hi = uvs[0].max(uvs[1]).max(uvs[2]);
    if lo.x >= box_max.x || lo.y >= box_max.y || hi.x <= box_min.x || hi.y <= box_min.y {
        return false;
    }
    let corners = [
        box_min,
        Vec2::new(box_max.x, box_min.y),
        box_max,
        Vec2::new(box_min.x, box_max.y),
    ];
    for edge in 0..3 {
        let start = uvs[edge];
        let direction = uvs[(edge + 1) % 3] - start;
        let axis = Vec2::new(-direction.y, direction.x);
        let opposite = uvs[(edge + 2) % 3];
        let side = axis.dot(opposite - start);
        if side == 0.0 {
            continue;
        }
        // Separated when every box corner is strictly on the far side.
        if corners
            .iter()
            .all(|corner| axis.dot(*corner - start) * side < 0.0)
        {
            return false;
        }
    }
    true
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::{Material, Mesh};

    fn quad_scene(size: f32) -> Scene {
        // Two unit quads: one in the floor plane, one standing, sharing an edge.
        let positions = vec![
            Vec3::new(0.0, 0.0, 0.0),
            Vec3::new(size, 0.0, 0.0),
            Vec3::new(size, 0.0, size),
            Vec3::new(0.0, 0.0, size),
            Vec3::new(0.0, size, 0.0),
            Vec3::new(size, size, 0.0),
        ];
        let triangles = vec![[0, 2, 1], [0, 3, 2], [0, 1, 5], [0, 5, 4]];
        Scene {
            mesh: Mesh {
                positions,
                triangles,
                material_ids: vec![0; 4],
                ..Default::default()
            },
            materials: vec![Material::default()],
            ..Default::default()
        }
    }

    #[test]
    fn two_planes_make_two_charts_with_full_coverage() {
        let scene = quad_scene(1.0);
        let atlas = Atlas::build(&scene, TexelDensity::MetresPerTexel(0.05)).unwrap();
        assert_eq!(atlas.chart_count, 2);
        // Each 1 m quad at 5 cm per texel covers 20x20 texels; conservative
        // rasterisation may add one ring (22x22) but never less than 20x20.
        let per_chart = atlas.receivers.len() / 2;
        assert!(
            (400..=484).contains(&per_chart),
            "{per_chart} texels per chart"
        );
        for index in 0..atlas.receivers.len() {
            let receiver = atlas.receivers.get(index);
            let triangle_normal = scene.mesh.geometric_normal(receiver.triangle as usize);
            assert_eq!(receiver.normal, triangle_normal);
            // Receiver points lie on the quads (closest point clamps to them).
            assert!(
                receiver.position.min_element() >= -1e-5
                    && receiver.position.max_element() <= 1.0 + 1e-5
            );
        }
    }

    #[test]
    fn thin_triangle_still_gets_texels() {
        // A sliver 1 m long and 1 mm wide at 5 cm texels covers no texel centre.
        let mut scene = quad_scene(1.0);
        scene.mesh.positions = vec![
            Vec3::ZERO,
            Vec3::new(1.0, 0.0, 0.0),
            Vec3::new(0.5, 0.0, 0.001),
        ];
        scene.mesh.triangles = vec![[0, 2, 1]];
        scene.mesh.material_ids = vec![0];
        let atlas = Atlas::build(&scene, TexelDensity::MetresPerTexel(0.05)).unwrap();
        assert!(
            atlas.receivers.len() >= 20,
            "only {} texels",
            atlas.receivers.len()
        );
    }

    #[test]
    fn bilinear_lookups_inside_charts_never_see_empty_texels() {
        let scene = quad_scene(1.0);
        let atlas = Atlas::build(&scene, TexelDensity::MetresPerTexel(0.1)).unwrap();
        let lightmap = atlas.to_lightmap(&vec![Rgb::ONE; atlas.receivers.len()]);
        // A constant lightmap must read back as exactly one everywhere on the
        // geometry, edges and corners included: any empty (zero) texel in a
        // bilinear footprint would pull the value below one.
        let steps = 50;
        for triangle in 0..scene.mesh.triangles.len() as u32 {
            for i in 0..=steps {
                for j in 0..=(steps - i) {
                    let barycentric = Vec2::new(i as f32 / steps as f32, j as f32 / steps as f32);
                    let value = atlas.sample(&lightmap, triangle, barycentric);
                    assert!(
                        (value - Rgb::ONE).abs().max_element() < 1e-5,
                        "{value} at {triangle} {barycentric}"
                    );
                }
            }
        }
    }

    #[test]
    fn dilation_does_not_cross_charts() {
        let scene = quad_scene(1.0);
        let atlas = Atlas::build(&scene, TexelDensity::MetresPerTexel(0.1)).unwrap();
        // Chart of the floor is 1.0, chart of the wall is 2.0.
        let values: Vec<Rgb> = (0..atlas.receivers.len())
            .map(|r| {
                if atlas.receivers.normals[r].y.abs() > 0.5 {
                    Rgb::ONE
                } else {
                    Rgb::splat(2.0)
                }
            })
            .collect();
        let lightmap = atlas.to_lightmap(&values);
        for triangle in 0..4u32 {
            let expected = if scene.mesh.geometric_normal(triangle as usize).y.abs() > 0.5 {
                1.0
            } else {
                2.0
            };
            for barycentric in [
                Vec2::ZERO,
                Vec2::X,
                Vec2::Y,
                Vec2::splat(0.5),
                Vec2::splat(1.0 / 3.0),
            ] {
                let value = atlas.sample(&lightmap, triangle, barycentric);
                assert!(
                    (value.x - expected).abs() < 1e-5,
                    "triangle {triangle} at {barycentric}: {value}"
                );
            }
        }
    }

    /// Lookups through the shown receivers read the same bits as lookups
    /// of the scattered, dilated map, in gutters, at filled hidden texels
    /// and on texels that show nothing.
    #[test]
    fn receiver_lookups_equal_lookups_of_the_scattered_map() {
        let scene = quad_scene(1.0);
        let mut atlas = Atlas::build(&scene, TexelDensity::MetresPerTexel(0.1)).unwrap();
        // Make one covered texel show its neighbour, as under an object.
        let [x, y] = atlas.receivers.texels[5];
        let [sx, sy] = atlas.receivers.texels[6];
        atlas.fill_hidden(vec![(y * atlas.width + x, sy * atlas.width + sx)]);
        let values: Vec<Rgb> = (0..atlas.receivers.len())
            .map(|r| Rgb::new(r as f32 * 0.37, 1.0 / (1.0 + r as f32), (r % 7) as f32))
            .collect();
        let lightmap = atlas.to_lightmap(&values);
        let shown = atlas.dilated_receiver_of_texel();
        let steps = 40;
        for triangle in 0..scene.mesh.triangles.len() as u32 {
            // Barycentrics past the triangle reach texels beyond the gutter.
            for i in -5..=steps + 5 {
                for j in -5..=steps + 5 {
                    let barycentric = Vec2::new(i as f32, j as f32) / steps as f32;
                    let expected = atlas.sample(&lightmap, triangle, barycentric);
                    let value = atlas.sample_receivers(&shown, &values, triangle, barycentric);
                    assert_eq!(
                        value.to_array().map(f32::to_bits),
                        expected.to_array().map(f32::to_bits),
                        "{triangle} {barycentric}"
                    );
                }
            }
        }
    }

    #[test]
    fn target_resolution_is_respected() {
        let scene = quad_scene(3.0);
        for target in [32, 64, 128] {
            let atlas = Atlas::build(&scene, TexelDensity::TargetResolution(target)).unwrap();
            assert!(atlas.width.max(atlas.height) <= target);
            // Not wastefully small either. Each chart costs 2 * GUTTER + 1 texels
            // of border per axis, which dominates at 32; from 64 on at least a
            // quarter of the target's texels must be receivers.
            if target >= 64 {
                assert!(
                    atlas.receivers.len() as f64 > 0.25 * (target * target) as f64,
                    "{target}: {}",
                    atlas.receivers.len()
                );
            }
        }
    }

    #[test]
    fn invalid_density_is_an_error() {
        let scene = quad_scene(1.0);
        assert!(Atlas::build(&scene, TexelDensity::MetresPerTexel(0.0)).is_err());
        assert!(Atlas::build(&scene, TexelDensity::MetresPerTexel(f32::NAN)).is_err());
        assert!(Atlas::build(&scene, TexelDensity::TargetResolution(1 << 20)).is_err());
        // Two charts with gutters need 12 texels; 8 must fail at once with advice.
        let error = Atlas::build(&scene, TexelDensity::TargetResolution(8))
            .unwrap_err()
            .to_string();
        assert!(error.contains("at least"), "{error}");
    }

    #[test]
    fn overlapping_mesh_uvs_are_replaced() {
        let mut scene = quad_scene(1.0);
        // Every vertex at the same UV region: overlapping.
        scene.mesh.lightmap_uvs = vec![
            Vec2::new(0.1, 0.1),
            Vec2::new(0.9, 0.1),
            Vec2::new(0.9, 0.9),
            Vec2::new(0.1, 0.9),
            Vec2::new(0.1, 0.9),
            Vec2::new(0.9, 0.9),
        ];
        let atlas = Atlas::build(&scene, TexelDensity::TargetResolution(32)).unwrap();
        assert!(!atlas.from_mesh_uvs);
    }

    /// The mesh's own UVs keep a texel size: relocation, the final
    /// gather's reach and PIC's cache spacing all scale by it, and at 0
    /// the gather found no receiver near anything. Two 2 m quads each take
    /// 32 x 16 texels of a 64-texel atlas (a stretch the mean absorbs;
    /// diagonals that miss the texel centres, which the overlap check
    /// would count twice): 4 m^2 over 512 texels.
    #[test]
    fn mesh_uvs_give_their_texel_size() {
        let mut scene = quad_scene(2.0);
        scene.mesh.lightmap_uvs = vec![
            Vec2::new(0.0, 0.25),
            Vec2::new(0.5, 0.25),
            Vec2::new(0.5, 0.0),
            Vec2::new(0.0, 0.0),
            Vec2::new(0.0, 0.5),
            Vec2::new(0.5, 0.5),
        ];
        let atlas = Atlas::build(&scene, TexelDensity::TargetResolution(64)).unwrap();
        assert!(atlas.from_mesh_uvs);
        assert!(
            (atlas.metres_per_texel - (4.0f32 / 512.0).sqrt()).abs() < 1e-5,
            "{}",
            atlas.metres_per_texel
        );
    }

    #[test]
    fn floor_small_is_floor_on_texel_coordinates() {
        let mut values = vec![0.0f32, -0.0, -0.5, 0.5, -1.0, 1.0, 4095.0, -4096.5];
        for step in -40_000..40_000 {
            let value = step as f32 * 0.137;
            values.extend([value, value.next_up(), value.next_down()]);
        }
        for value in values {
            assert_eq!(floor_small(value), value.floor(), "{value}");
        }
    }

    /// The two quads of [`quad_scene`] (2 m) and a 0.3 m square facing
    /// down 1.5 m above the floor, with a point light `light_below` under
    /// the square's centre (above it when negative): a lampshade's top in
    /// miniature.
    fn shade_scene(light_below: f32) -> Scene {
        let mut scene = quad_scene(2.0);
        let base = scene.mesh.positions.len() as u32;
        scene.mesh.positions.extend([
            Vec3::new(0.85, 1.5, 0.85),
            Vec3::new(1.15, 1.5, 0.85),
            Vec3::new(1.15, 1.5, 1.15),
            Vec3::new(0.85, 1.5, 1.15),
        ]);
        scene
            .mesh
            .triangles
            .extend([[base, base + 1, base + 2], [base, base + 2, base + 3]]);
        scene.mesh.material_ids.extend([0, 0]);
        scene.lights = vec![crate::Light::Point {
            position: Vec3::new(1.0, 1.5 - light_below, 1.0),
            intensity: Rgb::ONE,
        }];
        scene
    }

    fn on_the_square(point: Vec3) -> bool {
        (point.y - 1.5).abs() < 1e-4
    }

    fn receivers_on_the_square(atlas: &Atlas) -> usize {
        (0..atlas.receivers.len())
            .filter(|&index| on_the_square(atlas.receivers.positions[index]))
            .count()
    }

    #[test]
    fn charts_near_a_light_get_finer_texels() {
        let density = TexelDensity::MetresPerTexel(0.2);
        let far = Atlas::build(&shade_scene(10.0), density).unwrap();
        let near = Atlas::build(&shade_scene(0.1), density).unwrap();
        // 0.1 m from the light the square wants 2.5 cm texels, 8x finer than
        // 20 cm, the finest allowed: 12 x 12 texels or more instead of 2 x 2
        // with the conservative ring.
        assert_eq!(far.near_light_charts, 0);
        assert_eq!(near.near_light_charts, 1);
        assert!(receivers_on_the_square(&far) <= 9);
        assert!(
            receivers_on_the_square(&near) >= 144,
            "{} receivers on the square",
            receivers_on_the_square(&near)
        );
        // The floor and the wall keep their texels: the same receivers
        // stand at the same points.
        let others = |atlas: &Atlas| -> Vec<[u32; 3]> {
            let mut points: Vec<[u32; 3]> = (0..atlas.receivers.len())
                .filter(|&index| !on_the_square(atlas.receivers.positions[index]))
                .map(|index| {
                    atlas.receivers.positions[index]
                        .to_array()
                        .map(f32::to_bits)
                })
                .collect();
            points.sort_unstable();
            points
        };
        assert_eq!(others(&far), others(&near));
        // A light standing in the open (1 m from the square, 0.5 m from the
        // floor it lights) leaves the atlas as it was.
        let mut open = shade_scene(10.0);
        open.lights = vec![crate::Light::Point {
            position: Vec3::new(1.0, 0.5, 1.0),
            intensity: Rgb::ONE,
        }];
        let open = Atlas::build(&open, density).unwrap();
        assert_eq!(open.near_light_charts, 0);
        assert_eq!(
            (open.width, open.height, &open.triangle_uvs),
            (far.width, far.height, &far.triangle_uvs)
        );
        // An atlas that places samples (PIC's caches) is built without it.
        let unrefined = Atlas::build_unrefined(&shade_scene(0.1), density).unwrap();
        assert_eq!(unrefined.near_light_charts, 0);
        assert_eq!(
            receivers_on_the_square(&unrefined),
            receivers_on_the_square(&far)
        );
        // A light behind the square (a shade's outside) does not light it.
        let behind = Atlas::build(&shade_scene(-0.1), density).unwrap();
        assert_eq!(behind.near_light_charts, 0);
        // The scene file's switch turns it off.
        let mut off = shade_scene(0.1);
        off.lightmap_layout.refine_near_lights = false;
        let off = Atlas::build(&off, density).unwrap();
        assert_eq!(off.near_light_charts, 0);
        assert_eq!(receivers_on_the_square(&off), receivers_on_the_square(&far));
    }

    /// A 40 m hall fitted to the automatic 128 texels would get texels of
    /// 0.6 m; it gets [`LARGEST_AUTOMATIC_TEXEL`], while a requested
    /// resolution is kept and a 5 m room's automatic texel is what the 128
    /// texels give it.
    #[test]
    fn an_automatic_atlas_keeps_its_texels_under_half_a_metre() {
        let room = |size: [f32; 3]| {
            crate::generate::load_obj_scene(&crate::generate::closed_room_obj(size), "")
                .expect("the room loads")
        };
        let hall = room([40.0, 8.0, 20.0]);
        let automatic = Atlas::build(&hall, TexelDensity::default()).unwrap();
        assert_eq!(automatic.metres_per_texel, LARGEST_AUTOMATIC_TEXEL);
        let requested = Atlas::build(&hall, TexelDensity::TargetResolution(128)).unwrap();
        assert!(requested.metres_per_texel > LARGEST_AUTOMATIC_TEXEL);
        assert!(automatic.receivers.len() > requested.receivers.len());
        let small = room([5.0, 2.5, 4.0]);
        let automatic = Atlas::build(&small, TexelDensity::default()).unwrap();
        let fitted = Atlas::build(&small, TexelDensity::TargetResolution(128)).unwrap();
        assert!(automatic.metres_per_texel < LARGEST_AUTOMATIC_TEXEL);
        assert_eq!(automatic.metres_per_texel, fitted.metres_per_texel);
    }

    #[test]
    fn refined_charts_keep_the_rest_of_an_automatic_atlas_and_a_requested_resolution() {
        let automatic = TexelDensity::Automatic { minimum: 32 };
        let far = Atlas::build(&shade_scene(10.0), automatic).unwrap();
        let near = Atlas::build(&shade_scene(0.1), automatic).unwrap();
        assert_eq!(near.metres_per_texel, far.metres_per_texel);
        assert!(receivers_on_the_square(&near) > receivers_on_the_square(&far));
        let requested = TexelDensity::TargetResolution(32);
        let near = Atlas::build(&shade_scene(0.1), requested).unwrap();
        assert_eq!(near.near_light_charts, 1);
        assert!(near.width.max(near.height) <= 32);
    }

    /// Every receiver stands at the point of its triangle nearest its
    /// texel's centre, so within half a texel diagonal of it in the atlas,
    /// on an atlas whose coordinates run into the hundreds (a generated
    /// atrium, 512 texels a side). Fails with the covered part's middle
    /// that this replaced, whose shoelace sums at such coordinates lost
    /// the area to rounding and put receivers up to 5 texels away.
    #[test]
    fn receivers_stand_nearest_their_texel_centres() {
        let folder = std::env::temp_dir().join(format!("relight-atlas-{}", std::process::id()));
        let path = crate::generate::write_atrium(&folder, 8_000).expect("atrium written");
        let scene = crate::load_scene(&path).expect("atrium loads");
        let _ = std::fs::remove_dir_all(&folder);
        let atlas = Atlas::build(&scene, TexelDensity::default()).expect("atlas");
        assert!(atlas.width >= 256, "{} texels", atlas.width);
        let receivers = &atlas.receivers;
        let farthest = (0..receivers.len())
            .map(|index| {
                let [x, y] = receivers.texels[index];
                let centre = Vec2::new(x as f32 + 0.5, y as f32 + 0.5);
                atlas
                    .uv_of(receivers.triangles[index], receivers.barycentrics[index])
                    .distance(centre)
            })
            .fold(0.0f32, f32::max);
        assert!(farthest <= 0.5f32.hypot(0.5) + 1e-3, "{farthest} texels");
    }

    #[test]
    fn closest_point_matches_inside_and_outside() {
        let uvs = [Vec2::ZERO, Vec2::new(2.0, 0.0), Vec2::new(0.0, 2.0)];
        let (distance, barycentric) = closest_barycentric(&uvs, Vec2::new(0.5, 0.5));
        assert_eq!(distance, 0.0);
        assert!((barycentric - Vec2::splat(0.25)).length() < 1e-6);
        let (distance, barycentric) = closest_barycentric(&uvs, Vec2::new(1.0, -1.0));
        assert!((distance - 1.0).abs() < 1e-6);
        assert!((barycentric - Vec2::new(0.5, 0.0)).length() < 1e-6);
    }
}
