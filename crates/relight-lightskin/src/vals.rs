//! Virtual area lights (VALs) from reflective shadow maps, rendered by ray
//! casting from each light (section 4.1): every texel's first hit becomes a
//! Lambertian disc that re-emits the flux the texel received times the
//! albedo there.

use crate::geometry::{Geometry, SurfaceHit};
use glam::{Vec2, Vec3};
use rayon::prelude::*;
use relight_core::colour::luminance;
use relight_core::Rgb;
use relight_scene::Light;
use relight_trace::direct::spot_falloff;
use std::f32::consts::{FRAC_1_PI, PI};

/// Kernels read VALs eight at a time; padding VALs carry no power.
pub const LANES: usize = 8;

/// A texel seen at a grazing angle covers a long sliver of surface; its disc
/// is capped at this many times the texel's perpendicular footprint so that
/// one grazing texel does not become a huge soft light.
const MAX_GRAZING_STRETCH: f32 = 5.0;

/// The site of a VAL that is not on the static mesh.
pub const NO_SITE: u32 = u32::MAX;

/// Bits per word of a sparse point's visibility row (see
/// [`crate::visibility`]): the rows are the VALs' anchors' bits, so the
/// VALs, which group their blocks by word, and the rows share the layout.
pub const WORD_BITS: usize = 32;

/// [`Vals::block_word`] of a block whose anchors fall in several words.
pub const MIXED_WORDS: u32 = u32::MAX;

/// Whether a visibility row has `anchor`'s bit.
#[inline]
pub fn row_sees(row: &[u32], anchor: u32) -> bool {
    let anchor = anchor as usize;
    row[anchor / WORD_BITS] >> (anchor % WORD_BITS) & 1 != 0
}

/// Columns of [`Vals`].
const COLUMNS: usize = 14;

/// One virtual area light before it is stored in [`Vals`].
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Val {
    pub position: Vec3,
    /// Unit normal of the side that emits.
    pub normal: Vec3,
    /// Re-emitted flux over pi (W/pi): a Lambertian disc of this flux gives
    /// irradiance `power_over_pi * cos_j * cos_i / (r^2 + d^2)` (equation 3
    /// with the disc's radiance folded in).
    pub power_over_pi: Rgb,
    /// Disc area (m^2).
    pub area: f32,
}

/// VALs in struct-of-arrays form, padded to a multiple of [`LANES`].
#[derive(Clone, Debug, Default)]
pub struct Vals {
    pub px: Vec<f32>,
    pub py: Vec<f32>,
    pub pz: Vec<f32>,
    pub nx: Vec<f32>,
    pub ny: Vec<f32>,
    pub nz: Vec<f32>,
    pub power_r: Vec<f32>,
    pub power_g: Vec<f32>,
    pub power_b: Vec<f32>,
    /// Luminance of the power: the weight of a VAL's position in the
    /// averaged light (see `gather`).
    pub power_luminance: Vec<f32>,
    /// Disc radius squared, r^2 = area / pi.
    pub radius_sq: Vec<f32>,
    /// Squared coordinates, so that the spread sums cost one FMA per axis.
    pub px_sq: Vec<f32>,
    pub py_sq: Vec<f32>,
    pub pz_sq: Vec<f32>,
    /// Per VAL: the static sparse point that stands for it in visibility
    /// lookups (see [`crate::visibility`]); empty when visibility is off.
    pub anchor: Vec<u32>,
    /// Per real VAL: the static triangle it lies on ([`NO_SITE`] for
    /// moving meshes and point clouds) and where on it.
    pub site_triangle: Vec<u32>,
    pub site_barycentric: Vec<Vec2>,
    /// Per block of [`LANES`] VALs, when anchored: the one word of a
    /// visibility row that holds all their anchors
    /// ([`MIXED_WORDS`] where they span several), and
    /// those anchors' bits in it.
    pub block_word: Vec<u32>,
    pub block_bits: Vec<u32>,
    /// VALs that are real (the rest is padding).
    pub count: usize,
    /// Sums over the real VALs of position and position squared, for the
    /// epsilon term of equation 7, which adds the same amount for every VAL
    /// at every sparse point and so needs no per-pair work.
    pub position_sum: [f64; 3],
    pub position_square_sum: [f64; 3],
}

impl Vals {
    pub fn clear(&mut self) {
        for column in self.columns_mut() {
            column.clear();
        }
        self.anchor.clear();
        self.site_triangle.clear();
        self.site_barycentric.clear();
        self.block_word.clear();
        self.block_bits.clear();
        self.count = 0;
        self.position_sum = [0.0; 3];
        self.position_square_sum = [0.0; 3];
    }

    fn columns_mut(&mut self) -> [&mut Vec<f32>; COLUMNS] {
        [
            &mut self.px,
            &mut self.py,
            &mut self.pz,
            &mut self.nx,
            &mut self.ny,
            &mut self.nz,
            &mut self.power_r,
            &mut self.power_g,
            &mut self.power_b,
            &mut self.power_luminance,
            &mut self.radius_sq,
            &mut self.px_sq,
            &mut self.py_sq,
            &mut self.pz_sq,
        ]
    }

    /// Appends real VALs that lie on no static triangle; call [`Vals::pad`]
    /// after the last.
    pub fn extend(&mut self, vals: &[Val]) {
        self.site_triangle
            .extend(std::iter::repeat_n(NO_SITE, vals.len()));
        self.site_barycentric
            .extend(std::iter::repeat_n(Vec2::ZERO, vals.len()));
        self.extend_columns(vals.iter());
    }

    /// Appends real VALs with their sites (triangle, barycentric).
    pub fn extend_sited(&mut self, vals: &[(Val, Option<(u32, Vec2)>)]) {
        for (_, site) in vals {
            let (triangle, barycentric) = site.unwrap_or((NO_SITE, Vec2::ZERO));
            self.site_triangle.push(triangle);
            self.site_barycentric.push(barycentric);
        }
        self.extend_columns(vals.iter().map(|(val, _)| val));
    }

    fn extend_columns<'a>(&mut self, vals: impl Iterator<Item = &'a Val>) {
        for val in vals {
            self.px.push(val.position.x);
            self.py.push(val.position.y);
            self.pz.push(val.position.z);
            self.nx.push(val.normal.x);
            self.ny.push(val.normal.y);
            self.nz.push(val.normal.z);
            self.power_r.push(val.power_over_pi.x);
            self.power_g.push(val.power_over_pi.y);
            self.power_b.push(val.power_over_pi.z);
            self.power_luminance.push(luminance(val.power_over_pi));
            self.radius_sq.push(val.area * FRAC_1_PI);
            self.px_sq.push(val.position.x * val.position.x);
            self.py_sq.push(val.position.y * val.position.y);
            self.pz_sq.push(val.position.z * val.position.z);
            for axis in 0..3 {
                let coordinate = val.position[axis] as f64;
                self.position_sum[axis] += coordinate;
                self.position_square_sum[axis] += coordinate * coordinate;
            }
            self.count += 1;
        }
    }

    /// Pads to a multiple of [`LANES`] with VALs that have no power and no
    /// normal, far away, so that kernels need no tail loop and never divide
    /// zero by zero.
    pub fn pad(&mut self) {
        while !self.px.len().is_multiple_of(LANES) {
            self.px.push(1e6);
            self.py.push(1e6);
            self.pz.push(1e6);
            for column in [
                &mut self.nx,
                &mut self.ny,
                &mut self.nz,
                &mut self.power_r,
                &mut self.power_g,
                &mut self.power_b,
                &mut self.power_luminance,
            ] {
                column.push(0.0);
            }
            self.radius_sq.push(1.0);
            self.px_sq.push(1e12);
            self.py_sq.push(1e12);
            self.pz_sq.push(1e12);
        }
    }

    /// Keeps exactly `budget` of the real VALs (when there are more), every
    /// (count / budget)-th, their power scaled by count / budget so that the
    /// total flux is unchanged: a fixed per-frame cost whatever the lights.
    /// Call before [`Vals::pad`].
    pub fn limit_to(&mut self, budget: usize) {
        if budget == 0 || self.count <= budget {
            return;
        }
        let count = self.count;
        let scale = count as f32 / budget as f32;
        // Source index * count / budget never falls behind its destination,
        // so a forward copy in place is safe.
        for column in self.columns_mut() {
            for index in 0..budget {
                column[index] = column[index * count / budget];
            }
            column.truncate(budget);
        }
        for index in 0..budget {
            self.site_triangle[index] = self.site_triangle[index * count / budget];
            self.site_barycentric[index] = self.site_barycentric[index * count / budget];
        }
        self.site_triangle.truncate(budget);
        self.site_barycentric.truncate(budget);
        self.count = budget;
        for column in [
            &mut self.power_r,
            &mut self.power_g,
            &mut self.power_b,
            &mut self.power_luminance,
        ] {
            for power in column.iter_mut() {
                *power *= scale;
            }
        }
        self.position_sum = [0.0; 3];
        self.position_square_sum = [0.0; 3];
        for index in 0..budget {
            for (axis, column) in [&self.px, &self.py, &self.pz].into_iter().enumerate() {
                let coordinate = column[index] as f64;
                self.position_sum[axis] += coordinate;
                self.position_square_sum[axis] += coordinate * coordinate;
            }
        }
    }

    /// Takes `anchors` (one per VAL, padding included) and sorts the real
    /// VALs by anchor. VALs of one anchor then sit side by side, so most
    /// blocks of eight read one word of a receiver's visibility row, which
    /// the kernel loads once instead of gathering eight.
    pub fn group_by_anchor(&mut self, anchors: Vec<u32>) {
        assert_eq!(anchors.len(), self.padded_len());
        self.anchor = anchors;
        let mut order: Vec<u32> = (0..self.count as u32).collect();
        order.par_sort_unstable_by_key(|&index| (self.anchor[index as usize], index));
        self.permute(&order);
        self.block_word.clear();
        self.block_bits.clear();
        for block in self.anchor.chunks_exact(LANES) {
            let word = block[0] as usize / WORD_BITS;
            let shared = block
                .iter()
                .all(|&anchor| anchor as usize / WORD_BITS == word);
            self.block_word
                .push(if shared { word as u32 } else { MIXED_WORDS });
            self.block_bits.push(
                block
                    .iter()
                    .fold(0, |bits, &anchor| bits | 1 << (anchor as usize % WORD_BITS)),
            );
        }
    }

    /// Reorders the real VALs: the `index`-th becomes `order[index]`'s.
    fn permute(&mut self, order: &[u32]) {
        debug_assert_eq!(order.len(), self.count);
        // One scratch column per element type, reused across columns.
        fn reorder<T: Copy>(column: &mut [T], order: &[u32], scratch: &mut Vec<T>) {
            scratch.clear();
            scratch.extend(order.iter().map(|&from| column[from as usize]));
            column[..scratch.len()].copy_from_slice(scratch);
        }
        let mut floats = Vec::with_capacity(order.len());
        for column in self.columns_mut() {
            reorder(column, order, &mut floats);
        }
        let mut indices = Vec::with_capacity(order.len());
        reorder(&mut self.anchor, order, &mut indices);
        reorder(&mut self.site_triangle, order, &mut indices);
        reorder(&mut self.site_barycentric, order, &mut Vec::new());
    }

    pub fn padded_len(&self) -> usize {
        self.px.len()
    }

    pub fn get(&self, index: usize) -> Val {
        Val {
            position: Vec3::new(self.px[index], self.py[index], self.pz[index]),
            normal: Vec3::new(self.nx[index], self.ny[index], self.nz[index]),
            power_over_pi: Rgb::new(
                self.power_r[index],
                self.power_g[index],
                self.power_b[index],
            ),
            area: self.radius_sq[index] * PI,
        }
    }

    pub fn memory_bytes(&self) -> usize {
        self.px.capacity() * 4 * COLUMNS
            + (self.anchor.capacity() + self.site_triangle.capacity()) * 4
            + self.site_barycentric.capacity() * 8
    }

    /// Total re-emitted flux (W), for conservation checks.
    pub fn total_power(&self) -> Rgb {
        let mut total = Rgb::ZERO;
        for index in 0..self.count {
            total += self.get(index).power_over_pi * PI;
        }
        total
    }
}

/// Where primary light comes from, as the RSM sees it.
#[derive(Clone, Copy, Debug)]
enum Source {
    /// Radiant intensity from a point, with an angular profile.
    Point {
        position: Vec3,
        intensity: Rgb,
        profile: Profile,
    },
    Directional {
        direction: Vec3,
        irradiance: Rgb,
    },
}

#[derive(Clone, Copy, Debug)]
enum Profile {
    Isotropic,
    Spot {
        axis: Vec3,
        inner: f32,
        outer: f32,
    },
    /// A small Lambertian emitter: intensity falls with the cosine to `normal`.
    Lambertian {
        normal: Vec3,
    },
}

impl Profile {
    fn factor(&self, direction: Vec3) -> f32 {
        match *self {
            Profile::Isotropic => 1.0,
            Profile::Spot { axis, inner, outer } => spot_falloff(direction.dot(axis), inner, outer),
            Profile::Lambertian { normal } => direction.dot(normal).max(0.0),
        }
    }
}

/// Settings of the reflective shadow maps.
#[derive(Clone, Copy, Debug)]
pub struct RsmSettings {
    /// Texels per side of each map (a point light has six maps).
    pub resolution: u32,
    /// Texels per side of the maps of all emissive triangles together:
    /// each emitter gets `resolution / sqrt(emitters)`, at least 2.
    pub emissive_resolution: u32,
}

/// The six cube faces: (forward, right, up).
const CUBE_FACES: [(Vec3, Vec3, Vec3); 6] = [
    (Vec3::X, Vec3::NEG_Z, Vec3::Y),
    (Vec3::NEG_X, Vec3::Z, Vec3::Y),
    (Vec3::Y, Vec3::X, Vec3::NEG_Z),
    (Vec3::NEG_Y, Vec3::X, Vec3::Z),
    (Vec3::Z, Vec3::X, Vec3::Y),
    (Vec3::NEG_Z, Vec3::NEG_X, Vec3::Y),
];

/// Renders every light's reflective shadow maps into `out` (cleared first):
/// perspective maps for spot lights, six cube faces for point lights and
/// for each emissive triangle (treated as a small Lambertian emitter at its
/// centroid), an orthographic map over the scene's bounding sphere for
/// directional lights. Call [`Vals::pad`] after adding any other VALs.
pub fn render_rsms(geometry: &Geometry, lights: &[Light], settings: RsmSettings, out: &mut Vals) {
    out.clear();
    let resolution = settings.resolution.max(1);
    let mut sources = Vec::new();
    for light in lights {
        match *light {
            Light::Point {
                position,
                intensity,
            } => sources.push((
                Source::Point {
                    position,
                    intensity,
                    profile: Profile::Isotropic,
                },
                resolution,
            )),
            Light::Spot {
                position,
                direction,
                intensity,
                inner_angle,
                outer_angle,
            } => sources.push((
                Source::Point {
                    position,
                    intensity,
                    profile: Profile::Spot {
                        axis: direction,
                        inner: inner_angle,
                        outer: outer_angle,
                    },
                },
                resolution,
            )),
            Light::Directional {
                direction,
                irradiance,
            } => sources.push((
                Source::Directional {
                    direction,
                    irradiance,
                },
                resolution,
            )),
        }
    }
    let emitters = geometry.emitters;
    if !emitters.is_empty() && settings.emissive_resolution > 0 {
        let count = emitters.triangles.len();
        let per_emitter =
            ((settings.emissive_resolution as f32 / (count as f32).sqrt()).round() as u32).max(2);
        for emitter in 0..count {
            let [a, b, c] = emitters.vertices[emitter];
            let normal = emitters.normals[emitter];
            sources.push((
                Source::Point {
                    position: (a + b + c) / 3.0 + normal * geometry.ray_epsilon,
                    // A small Lambertian emitter of radiance L and area A has
                    // intensity L A cos(theta) (W/sr).
                    intensity: emitters.radiance[emitter] * emitters.areas[emitter],
                    profile: Profile::Lambertian { normal },
                },
                per_emitter,
            ));
        }
    }
    for (source, resolution) in sources {
        match source {
            Source::Point {
                position,
                intensity,
                profile,
            } => match profile {
                Profile::Spot { axis, outer, .. } => {
                    let (right, up) = relight_core::sampling::orthonormal_basis(axis);
                    // Cover the cone; beyond 80 degrees a single map wastes
                    // most texels, so wide spots are clipped there.
                    let half_extent = outer.min(80f32.to_radians()).tan();
                    perspective_map(
                        geometry,
                        position,
                        (axis, right, up),
                        half_extent,
                        resolution,
                        intensity,
                        profile,
                        out,
                    )
                }
                _ => {
                    for face in CUBE_FACES {
                        perspective_map(
                            geometry, position, face, 1.0, resolution, intensity, profile, out,
                        );
                    }
                }
            },
            Source::Directional {
                direction,
                irradiance,
            } => orthographic_map(geometry, direction, irradiance, resolution, out),
        }
    }
}

/// Sub-texels per side of a map's texel where the light passes an edge:
/// a low sun reaches a hall only through windows about a texel across, and
/// one ray per texel lets all of a window's light in or none of it (a 38 m
/// hall: 0.73x of one bounce at 48 texels a side, 0.83x at 128).
const EDGE_REFINEMENT: u32 = 3;

/// How a map's texels meet the scene.
trait MapRays: Sync {
    /// The first surface along the ray through map point (`u`, `v`).
    fn cast(&self, u: f32, v: f32) -> Option<SurfaceHit>;
    /// The VAL of a `side`-wide square of the map around (`u`, `v`) whose
    /// ray met `hit`.
    fn val(&self, u: f32, v: f32, side: f32, hit: &SurfaceHit) -> Option<SitedVal>;
}

/// Casts every texel of a `resolution`^2 map spanning
/// (-half_extent, half_extent)^2 through its centre and appends the VALs
/// to `out` in row order (deterministic). With `refine_along` (the
/// direction a parallel map's light travels, its texels as wide on every
/// surface as on the map), a texel is cast again at [`EDGE_REFINEMENT`]^2
/// points where the light passes an edge between it and a neighbour
/// ([`passes_an_edge`]), and its rays leave one VAL per surface they meet,
/// of their summed flux, so edges cost rays but few VALs.
fn map_texels(
    resolution: u32,
    half_extent: f32,
    refine_along: Option<Vec3>,
    out: &mut Vals,
    rays: &impl MapRays,
) {
    let columns = resolution as usize;
    let side = 2.0 * half_extent / resolution as f32;
    // Map coordinates of the point `fraction` of the way across texel
    // `index` in each direction.
    let at = |index: usize, fraction: (f32, f32)| {
        let (row, column) = (index / columns, index % columns);
        (
            (column as f32 + fraction.0) * side - half_extent,
            (row as f32 + fraction.1) * side - half_extent,
        )
    };
    let coarse: Vec<Option<SurfaceHit>> = (0..columns * columns)
        .into_par_iter()
        .with_min_len(64)
        .map(|index| {
            let (u, v) = at(index, (0.5, 0.5));
            rays.cast(u, v)
        })
        .collect();
    let sub_side = side / EDGE_REFINEMENT as f32;
    let sub_fraction = |sub: u32| (sub as f32 + 0.5) / EDGE_REFINEMENT as f32;
    // The middle sub-ray of an odd refinement is the coarse ray again.
    let middle = (EDGE_REFINEMENT % 2 == 1).then_some(EDGE_REFINEMENT / 2);
    // Surfaces within a quarter texel of each other's plane are one.
    let tolerance = 0.25 * side;
    let rows: Vec<Vec<SitedVal>> = (0..columns)
        .into_par_iter()
        .map(|row| {
            let mut vals = Vec::new();
            let mut surfaces: Vec<Surface> = Vec::new();
            for column in 0..columns {
                let index = row * columns + column;
                let Some(hit) = &coarse[index] else {
                    continue;
                };
                let refine = refine_along.is_some_and(|travel| {
                    passes_an_edge(&coarse, columns, row, column, travel, tolerance)
                });
                if !refine {
                    let (u, v) = at(index, (0.5, 0.5));
                    vals.extend(rays.val(u, v, side, hit));
                    continue;
                }
                surfaces.clear();
                for sub_row in 0..EDGE_REFINEMENT {
                    for sub_column in 0..EDGE_REFINEMENT {
                        let (u, v) = at(index, (sub_fraction(sub_column), sub_fraction(sub_row)));
                        let sub_hit = if middle == Some(sub_row) && middle == Some(sub_column) {
                            Some(*hit)
                        } else {
                            rays.cast(u, v)
                        };
                        let Some(val) =
                            sub_hit.and_then(|sub_hit| rays.val(u, v, sub_side, &sub_hit))
                        else {
                            continue;
                        };
                        match surfaces
                            .iter_mut()
                            .find(|surface| surface.holds(&val.0, tolerance))
                        {
                            Some(surface) => surface.add(val),
                            None => surfaces.push(Surface::new(val)),
                        }
                    }
                }
                vals.extend(surfaces.iter().map(Surface::val));
            }
            vals
        })
        .collect();
    for row in rows {
        out.extend_sited(&row);
    }
}

/// Whether the light passes an edge between coarse texel (`row`, `column`)
/// and one of the four beside it: the nearer surface shadows the farther
/// one, which lies behind its plane while it lies in front of the farther
/// one's. Creases (a roof meeting a wall, a floor meeting a wall) put the
/// two surfaces side by side and move no light far, and a texel beside one
/// that meets nothing lies on the scene's outline against the sky, whose
/// outer faces nobody inside sees; neither is refined. The light travels
/// along `travel`; `tolerance` (a quarter texel) is how far behind a plane
/// counts.
fn passes_an_edge(
    coarse: &[Option<SurfaceHit>],
    columns: usize,
    row: usize,
    column: usize,
    travel: Vec3,
    tolerance: f32,
) -> bool {
    let Some(here) = &coarse[row * columns + column] else {
        return false;
    };
    let last = columns - 1;
    let behind = |a: &SurfaceHit, b: &SurfaceHit| {
        lit_side(a, travel).dot(b.position - a.position) < -tolerance
    };
    [
        (row > 0).then(|| (row - 1) * columns + column),
        (row < last).then(|| (row + 1) * columns + column),
        (column > 0).then(|| row * columns + column - 1),
        (column < last).then(|| row * columns + column + 1),
    ]
    .into_iter()
    .flatten()
    .any(|index| {
        coarse[index]
            .as_ref()
            .is_some_and(|there| behind(here, there) != behind(there, here))
    })
}

/// The rays of one perspective map: texel (i, j) looks along forward +
/// u right + v up with u, v in (-half_extent, half_extent); its solid angle
/// is s^2 / (1 + u^2 + v^2)^(3/2) for texel side s on the unit-distance
/// plane.
struct PerspectiveRays<'a> {
    geometry: &'a Geometry<'a>,
    origin: Vec3,
    forward: Vec3,
    right: Vec3,
    up: Vec3,
    intensity: Rgb,
    profile: Profile,
}

impl PerspectiveRays<'_> {
    fn direction(&self, u: f32, v: f32) -> Vec3 {
        self.forward + self.right * u + self.up * v
    }
}

impl MapRays for PerspectiveRays<'_> {
    fn cast(&self, u: f32, v: f32) -> Option<SurfaceHit> {
        let direction = self.direction(u, v);
        let unit = direction / direction.length_squared().sqrt();
        if self.profile.factor(unit) <= 0.0 {
            return None;
        }
        self.geometry.first_hit(self.origin, unit)
    }

    fn val(&self, u: f32, v: f32, side: f32, hit: &SurfaceHit) -> Option<SitedVal> {
        let direction = self.direction(u, v);
        let length_sq = direction.length_squared();
        let unit = direction / length_sq.sqrt();
        let solid_angle = side * side / (length_sq * length_sq.sqrt());
        let incident_power = self.intensity * (self.profile.factor(unit) * solid_angle);
        let cos_hit = hit.normal.dot(unit).abs();
        let footprint = solid_angle * hit.distance * hit.distance;
        reflect(hit, unit, incident_power, footprint, cos_hit)
    }
}

#[allow(clippy::too_many_arguments)]
fn perspective_map(
    geometry: &Geometry,
    origin: Vec3,
    (forward, right, up): (Vec3, Vec3, Vec3),
    half_extent: f32,
    resolution: u32,
    intensity: Rgb,
    profile: Profile,
    out: &mut Vals,
) {
    let rays = PerspectiveRays {
        geometry,
        origin,
        forward,
        right,
        up,
        intensity,
        profile,
    };
    // A point light's six maps meet many more edges than a sun's one, and
    // refining them cost far more than it gained (docs/techniques.md), so
    // they keep one ray a texel.
    map_texels(resolution, half_extent, None, out, &rays);
}

/// The rays of an orthographic map over the bounding sphere of everything
/// that can be lit (of the scene's content, where it has content bounds),
/// perpendicular to `direction`.
struct OrthographicRays<'a> {
    geometry: &'a Geometry<'a>,
    start: Vec3,
    direction: Vec3,
    right: Vec3,
    up: Vec3,
    irradiance: Rgb,
}

impl MapRays for OrthographicRays<'_> {
    fn cast(&self, u: f32, v: f32) -> Option<SurfaceHit> {
        self.geometry
            .first_hit(self.start + self.right * u + self.up * v, self.direction)
    }

    fn val(&self, _u: f32, _v: f32, side: f32, hit: &SurfaceHit) -> Option<SitedVal> {
        let area = side * side;
        let cos_hit = hit.normal.dot(self.direction).abs();
        reflect(hit, self.direction, self.irradiance * area, area, cos_hit)
    }
}

fn orthographic_map(
    geometry: &Geometry,
    direction: Vec3,
    irradiance: Rgb,
    resolution: u32,
    out: &mut Vals,
) {
    let (centre, radius, back) = geometry.directional_extent();
    let (right, up) = relight_core::sampling::orthonormal_basis(direction);
    let rays = OrthographicRays {
        geometry,
        start: centre - direction * back,
        direction,
        right,
        up,
        irradiance,
    };
    map_texels(resolution, radius, Some(direction), out, &rays);
}

/// The VALs a refined texel's rays left on one surface, merged into one.
struct Surface {
    first: SitedVal,
    position_sum: Vec3,
    power_over_pi: Rgb,
    area: f32,
    count: u32,
}

impl Surface {
    fn new(val: SitedVal) -> Self {
        Self {
            first: val,
            position_sum: val.0.position,
            power_over_pi: val.0.power_over_pi,
            area: val.0.area,
            count: 1,
        }
    }

    /// Whether `val` lies on this surface: the same emitting side within
    /// about 25 degrees (the two faces of a thin wall light opposite rooms)
    /// and each within `tolerance` of the other's plane.
    fn holds(&self, val: &Val, tolerance: f32) -> bool {
        let first = &self.first.0;
        let offset = val.position - first.position;
        first.normal.dot(val.normal) > 0.9
            && first.normal.dot(offset).abs() <= tolerance
            && val.normal.dot(offset).abs() <= tolerance
    }

    fn add(&mut self, val: SitedVal) {
        self.position_sum += val.0.position;
        self.power_over_pi += val.0.power_over_pi;
        self.area += val.0.area;
        self.count += 1;
    }

    /// One VAL at the rays' mean position, on the first ray's triangle (the
    /// site only picks the VAL's anchor, which the plane shares).
    fn val(&self) -> SitedVal {
        let (first, site) = self.first;
        (
            Val {
                position: self.position_sum / self.count as f32,
                normal: first.normal,
                power_over_pi: self.power_over_pi,
                area: self.area,
            },
            site,
        )
    }
}

/// The VAL a texel leaves: the flux it received times the albedo, on the
/// side the light came from, over the surface area the texel covers
/// (perpendicular footprint / cos, capped for grazing texels).
fn reflect(
    hit: &SurfaceHit,
    travel: Vec3,
    incident_power: Rgb,
    perpendicular_footprint: f32,
    cos_hit: f32,
) -> Option<SitedVal> {
    let power = incident_power * hit.albedo;
    if power.max_element() <= 0.0 {
        return None;
    }
    let normal = lit_side(hit, travel);
    let area = perpendicular_footprint / cos_hit.max(1.0 / MAX_GRAZING_STRETCH);
    Some((
        Val {
            position: hit.position,
            normal,
            power_over_pi: power * FRAC_1_PI,
            area,
        },
        hit.site,
    ))
}

/// The normal of `hit`'s side that light travelling along `travel` reaches.
fn lit_side(hit: &SurfaceHit, travel: Vec3) -> Vec3 {
    if hit.normal.dot(travel) > 0.0 {
        -hit.normal
    } else {
        hit.normal
    }
}

/// A VAL and the static triangle and barycentric coordinates it lies at.
type SitedVal = (Val, Option<(u32, Vec2)>);
