//! The direct-light service: incident irradiance from every light at batches
//! of surface points, with exact shadows by shadow rays.
//!
//! Every technique calls this for its own sample points each frame and the
//! renderer calls it for visible pixels, so direct light is computed one way
//! everywhere and techniques differ only in indirect light. Area lights
//! (emissive triangles) use a fixed number of stratified samples chosen in
//! proportion to emitted power; the samples of a point depend only on the
//! seed and the point's index, so a static point sees the same pattern every
//! frame (no temporal flicker) and results do not depend on thread count.

use crate::bvh::{Bvh, Ray, NO_OCCLUDER};
use glam::{Vec2, Vec3};
use rayon::prelude::*;
use relight_core::sampling::{cosine_hemisphere_around, SampleStream};
use relight_core::solid_angle::mean_cosine_over_square;
use relight_core::{luminance, Rgb};
use relight_scene::{Light, Scene};

/// Points per rayon task: enough shadow rays to amortise scheduling.
const POINTS_PER_TASK: usize = 256;

/// The indices of `points` sorted along a Morton curve over their bounds
/// (ties by index, so the order is deterministic). Batches of shadow rays
/// from points in this order run much faster than from points in, say,
/// lightmap scan-line order: neighbouring points share their occluders
/// (the shadow cache's first guess) and their BVH nodes stay in cache.
pub fn morton_order(points: &[Vec3]) -> Vec<u32> {
    let (low, high) = points.iter().fold(
        (Vec3::splat(f32::INFINITY), Vec3::splat(f32::NEG_INFINITY)),
        |(low, high), point| (low.min(*point), high.max(*point)),
    );
    let cell_scale = Vec3::splat(1023.0) / (high - low).max(Vec3::splat(1e-20));
    let mut order: Vec<u32> = (0..points.len() as u32).collect();
    order.sort_by_cached_key(|&index| {
        let cell = ((points[index as usize] - low) * cell_scale)
            .clamp(Vec3::ZERO, Vec3::splat(1023.0))
            .as_uvec3()
            .to_array();
        (morton_code(cell), index)
    });
    order
}

/// Interleaves the bits of a 10-bit-per-axis grid position.
pub fn morton_code(cell: [u32; 3]) -> u32 {
    let spread = |mut value: u32| {
        value &= 0x3ff;
        value = (value | (value << 16)) & 0x0300_00ff;
        value = (value | (value << 8)) & 0x0300_f00f;
        value = (value | (value << 4)) & 0x030c_30c3;
        (value | (value << 2)) & 0x0924_9249
    };
    spread(cell[0]) | (spread(cell[1]) << 1) | (spread(cell[2]) << 2)
}

/// Settings of the direct-light service.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct DirectSettings {
    /// Shadow rays per point toward emissive triangles (stratified over power).
    pub area_light_samples: u32,
    /// Cosine-distributed rays per point toward the constant environment.
    pub environment_samples: u32,
    pub seed: u64,
}

impl Default for DirectSettings {
    fn default() -> Self {
        Self {
            area_light_samples: 16,
            environment_samples: 16,
            seed: 0x5EED,
        }
    }
}

/// The patch (m^2) each point of a batch stands for, over which its
/// punctual light is averaged (see
/// [`DirectLight::irradiance_batch_over_footprints`]).
#[derive(Clone, Copy, Debug)]
pub enum Footprints<'a> {
    /// Point i's patch is `areas[i]`.
    Each(&'a [f32]),
    /// Every point's patch has this area (equal-area samples).
    All(f32),
}

impl Footprints<'_> {
    #[inline]
    fn area(&self, index: usize) -> f32 {
        match self {
            Footprints::Each(areas) => areas[index],
            Footprints::All(area) => *area,
        }
    }
}

/// The direct light at a fixed set of points that no frame changes
/// (emissive triangles, the environment), traced the first time it is
/// asked for. A technique that lights the same points every frame keeps
/// one, so that a frame traces only its punctual lights.
#[derive(Clone, Debug, Default)]
pub struct StaticDirect {
    irradiance: Vec<Rgb>,
}

impl StaticDirect {
    /// The static irradiance at `points` (the same points at every call),
    /// or `None` when the scene has no static light.
    pub fn at(
        &mut self,
        direct: &DirectLight,
        points: &[Vec3],
        normals: &[Vec3],
    ) -> Option<&[Rgb]> {
        if !direct.has_static_light() {
            return None;
        }
        if self.irradiance.len() != points.len() {
            self.irradiance = vec![Rgb::ZERO; points.len()];
            direct.static_irradiance_batch(points, normals, &mut self.irradiance);
        }
        Some(&self.irradiance)
    }

    /// [`DirectLight::irradiance_batch`] at `points` (the same points at
    /// every call), tracing the static light only the first time.
    pub fn irradiance_batch(
        &mut self,
        direct: &DirectLight,
        lights: &[Light],
        points: &[Vec3],
        normals: &[Vec3],
        irradiance: &mut [Rgb],
    ) {
        let fixed = self.at(direct, points, normals);
        direct.irradiance_batch_over_static(lights, points, normals, fixed, irradiance);
    }

    /// [`DirectLight::irradiance_batch_over_footprints`] at `points` (the
    /// same points at every call), tracing the static light only the first
    /// time.
    pub fn irradiance_batch_over_footprints(
        &mut self,
        direct: &DirectLight,
        lights: &[Light],
        points: &[Vec3],
        normals: &[Vec3],
        footprints: Footprints,
        irradiance: &mut [Rgb],
    ) {
        let fixed = self.at(direct, points, normals);
        direct.irradiance_batch_over_footprints(
            lights, points, normals, footprints, fixed, irradiance,
        );
    }

    pub fn memory_bytes(&self) -> usize {
        self.irradiance.len() * 12
    }
}

/// Emissive triangles with a power-proportional sampling table.
#[derive(Clone, Debug, Default)]
pub struct Emitters {
    pub triangles: Vec<u32>,
    pub vertices: Vec<[Vec3; 3]>,
    pub normals: Vec<Vec3>,
    pub areas: Vec<f32>,
    pub radiance: Vec<Rgb>,
    /// Cumulative distribution over triangles, by area times luminance.
    cdf: Vec<f32>,
    pub total_power: f32,
}

impl Emitters {
    pub fn from_scene(scene: &Scene) -> Self {
        let mut emitters = Emitters::default();
        let mut running = 0.0f64;
        for triangle in scene.emissive_triangles() {
            let area = scene.mesh.area(triangle as usize);
            let radiance = scene.material_of(triangle as usize).emission;
            let power = area as f64 * luminance(radiance).max(1e-12) as f64;
            if area <= 0.0 {
                continue;
            }
            running += power;
            emitters.triangles.push(triangle);
            emitters
                .vertices
                .push(scene.mesh.vertices(triangle as usize));
            emitters
                .normals
                .push(scene.mesh.geometric_normal(triangle as usize));
            emitters.areas.push(area);
            emitters.radiance.push(radiance);
            emitters.cdf.push(running as f32);
        }
        emitters.total_power = running as f32;
        if running > 0.0 {
            for value in &mut emitters.cdf {
                *value /= running as f32;
            }
        }
        emitters
    }

    pub fn is_empty(&self) -> bool {
        self.triangles.is_empty()
    }

    /// Picks a triangle for `u` in [0,1) and returns (index, probability).
    #[inline]
    fn pick(&self, u: f32) -> (usize, f32) {
        let index = self
            .cdf
            .partition_point(|&c| c <= u)
            .min(self.cdf.len() - 1);
        let previous = if index == 0 { 0.0 } else { self.cdf[index - 1] };
        (index, self.cdf[index] - previous)
    }
}

/// Lights whose shadow rays keep a cache of their last occluder in a batch;
/// further lights trace without one.
const CACHED_LIGHTS: usize = 8;

/// The occluder that last blocked a shadow ray, per punctual light and for
/// the area lights, carried from point to point through a batch (see
/// [`Bvh::occluded_cached`]). Results never depend on it.
#[derive(Clone, Copy, Debug)]
pub struct ShadowCache {
    lights: [u32; CACHED_LIGHTS],
    area_lights: u32,
}

impl Default for ShadowCache {
    fn default() -> Self {
        Self {
            lights: [NO_OCCLUDER; CACHED_LIGHTS],
            area_lights: NO_OCCLUDER,
        }
    }
}

/// The shared direct-light service over one scene's BVH.
#[derive(Clone, Copy)]
pub struct DirectLight<'a> {
    pub scene: &'a Scene,
    pub bvh: &'a Bvh,
    pub emitters: &'a Emitters,
    pub settings: DirectSettings,
    /// Offset of shadow-ray origins along the normal, scaled to the scene.
    pub ray_epsilon: f32,
}

/// Shadow-ray origin offset for a scene of this size: large enough to clear
/// f32 rounding of hit points far from the origin, small against geometry.
pub fn ray_epsilon_for(bvh: &Bvh) -> f32 {
    let (lo, hi) = bvh.bounds();
    let extent = (hi - lo).max_element().max(1e-3);
    let magnitude = lo.abs().max(hi.abs()).max_element();
    (extent * 2e-5).max(magnitude * 4e-6)
}

impl<'a> DirectLight<'a> {
    /// `emitters` must come from [`Emitters::from_scene`] of the same scene;
    /// it is built once per scene, while a service is cheap to create.
    pub fn new(
        scene: &'a Scene,
        bvh: &'a Bvh,
        emitters: &'a Emitters,
        settings: DirectSettings,
    ) -> Self {
        Self {
            scene,
            bvh,
            emitters,
            settings,
            ray_epsilon: ray_epsilon_for(bvh),
        }
    }

    /// Irradiance at `point` on the side `normal` faces, from `lights`, the
    /// emissive triangles and the environment. `point_key` selects the sample
    /// pattern (use a stable index such as the receiver or pixel number).
    pub fn irradiance(&self, lights: &[Light], point: Vec3, normal: Vec3, point_key: u64) -> Rgb {
        self.irradiance_cached(
            lights,
            point,
            normal,
            point_key,
            &mut ShadowCache::default(),
        )
    }

    /// [`DirectLight::irradiance`] with a shadow cache carried over from the
    /// previous point: the same result, faster when points come in spatial
    /// order.
    pub fn irradiance_cached(
        &self,
        lights: &[Light],
        point: Vec3,
        normal: Vec3,
        point_key: u64,
        cache: &mut ShadowCache,
    ) -> Rgb {
        let origin = point + normal * self.ray_epsilon;
        let irradiance = self.punctual_part(lights, origin, normal, 0.0, cache);
        self.static_part(irradiance, origin, normal, point_key, cache)
    }

    /// `footprint`: see [`Self::irradiance_batch_over_footprints`]; 0 for
    /// the light at the point itself.
    fn punctual_part(
        &self,
        lights: &[Light],
        origin: Vec3,
        normal: Vec3,
        footprint: f32,
        cache: &mut ShadowCache,
    ) -> Rgb {
        let mut irradiance = Rgb::ZERO;
        let mut uncached = NO_OCCLUDER;
        for (index, light) in lights.iter().enumerate() {
            let occluder = cache.lights.get_mut(index).unwrap_or(&mut uncached);
            irradiance += self.punctual(light, origin, normal, footprint, occluder);
        }
        irradiance
    }

    /// `irradiance` plus the light of the emissive triangles and the
    /// environment.
    fn static_part(
        &self,
        mut irradiance: Rgb,
        origin: Vec3,
        normal: Vec3,
        point_key: u64,
        cache: &mut ShadowCache,
    ) -> Rgb {
        if !self.emitters.is_empty() && self.settings.area_light_samples > 0 {
            irradiance += self.area_lights(origin, normal, point_key, &mut cache.area_lights);
        }
        let environment = self.scene.environment.radiance;
        if environment.max_element() > 0.0 && self.settings.environment_samples > 0 {
            irradiance += self.environment(origin, normal, point_key, environment);
        }
        irradiance
    }

    /// True when the scene has light that no frame moves: emissive
    /// triangles or an environment.
    pub fn has_static_light(&self) -> bool {
        (!self.emitters.is_empty() && self.settings.area_light_samples > 0)
            || (self.scene.environment.radiance.max_element() > 0.0
                && self.settings.environment_samples > 0)
    }

    /// The irradiance of [`Self::irradiance_batch`] that never changes for a
    /// static point: emissive triangles (static geometry) and the constant
    /// environment, with the same samples. Points whose direct light is
    /// needed every frame compute it once and add it to
    /// [`Self::irradiance_batch_over_static`]'s punctual lights: on a scene
    /// lit by a sky, 16 of a point's 18 shadow rays.
    pub fn static_irradiance_batch(
        &self,
        points: &[Vec3],
        normals: &[Vec3],
        irradiance: &mut [Rgb],
    ) {
        self.batch(points, normals, irradiance, |index, cache| {
            let origin = points[index] + normals[index] * self.ray_epsilon;
            self.static_part(Rgb::ZERO, origin, normals[index], index as u64, cache)
        });
    }

    /// [`Self::irradiance_batch`] given its static part from
    /// [`Self::static_irradiance_batch`] over the same points: only the
    /// punctual lights are traced. `None` (a scene without static light,
    /// see [`StaticDirect::at`]) is [`Self::irradiance_batch`] itself.
    pub fn irradiance_batch_over_static(
        &self,
        lights: &[Light],
        points: &[Vec3],
        normals: &[Vec3],
        static_irradiance: Option<&[Rgb]>,
        irradiance: &mut [Rgb],
    ) {
        self.batch_over_static(
            lights,
            points,
            normals,
            |_| 0.0,
            static_irradiance,
            irradiance,
        );
    }

    /// [`Self::irradiance_batch_over_static`] with each point's punctual
    /// light averaged over a square of its footprint (m^2) around it
    /// in its plane ([`mean_cosine_over_square`]), for points that each
    /// stand for a patch of surface: a point light a few centimetres from
    /// such a point gives it the patch's mean irradiance, bounded, not the
    /// 1/d^2 value at its centre. Visibility is still the centre's shadow
    /// ray; suns are unchanged.
    pub fn irradiance_batch_over_footprints(
        &self,
        lights: &[Light],
        points: &[Vec3],
        normals: &[Vec3],
        footprints: Footprints,
        static_irradiance: Option<&[Rgb]>,
        irradiance: &mut [Rgb],
    ) {
        if let Footprints::Each(areas) = footprints {
            assert_eq!(points.len(), areas.len());
        }
        self.batch_over_static(
            lights,
            points,
            normals,
            |index| footprints.area(index),
            static_irradiance,
            irradiance,
        );
    }

    /// Both of the above: `footprint(i)` is point i's patch area, 0 for
    /// the light at the point itself. Without `static_irradiance` the
    /// static light is traced here, with the point's index as its key, as
    /// [`Self::irradiance_batch`] does.
    fn batch_over_static(
        &self,
        lights: &[Light],
        points: &[Vec3],
        normals: &[Vec3],
        footprint: impl Fn(usize) -> f32 + Sync,
        static_irradiance: Option<&[Rgb]>,
        irradiance: &mut [Rgb],
    ) {
        if let Some(static_irradiance) = static_irradiance {
            assert_eq!(points.len(), static_irradiance.len());
        }
        self.batch(points, normals, irradiance, |index, cache| {
            let origin = points[index] + normals[index] * self.ray_epsilon;
            let punctual =
                self.punctual_part(lights, origin, normals[index], footprint(index), cache);
            match static_irradiance {
                Some(static_irradiance) => punctual + static_irradiance[index],
                None => self.static_part(punctual, origin, normals[index], index as u64, cache),
            }
        });
    }

    /// Batch form over struct-of-arrays inputs; `keys` default to indices.
    pub fn irradiance_batch(
        &self,
        lights: &[Light],
        points: &[Vec3],
        normals: &[Vec3],
        irradiance: &mut [Rgb],
    ) {
        self.batch(points, normals, irradiance, |index, cache| {
            self.irradiance_cached(lights, points[index], normals[index], index as u64, cache)
        });
    }

    /// `out[i] = point(i, cache)` in parallel blocks of points, each block
    /// carrying one shadow cache from point to point.
    fn batch(
        &self,
        points: &[Vec3],
        normals: &[Vec3],
        out: &mut [Rgb],
        point: impl Fn(usize, &mut ShadowCache) -> Rgb + Sync,
    ) {
        assert_eq!(points.len(), normals.len());
        assert_eq!(points.len(), out.len());
        out.par_chunks_mut(POINTS_PER_TASK)
            .enumerate()
            .for_each(|(chunk, values)| {
                let start = chunk * POINTS_PER_TASK;
                let mut cache = ShadowCache::default();
                for (offset, value) in values.iter_mut().enumerate() {
                    *value = point(start + offset, &mut cache);
                }
            });
    }

    fn punctual(
        &self,
        light: &Light,
        origin: Vec3,
        normal: Vec3,
        footprint: f32,
        occluder: &mut u32,
    ) -> Rgb {
        match *light {
            Light::Point {
                position,
                intensity,
            } => self.point_light(origin, normal, position, intensity, footprint, occluder),
            Light::Spot {
                position,
                direction,
                intensity,
                inner_angle,
                outer_angle,
            } => {
                let to_point = (origin - position).normalize_or_zero();
                let falloff = spot_falloff(
                    to_point.dot(direction.normalize_or_zero()),
                    inner_angle,
                    outer_angle,
                );
                if falloff <= 0.0 {
                    return Rgb::ZERO;
                }
                self.point_light(
                    origin,
                    normal,
                    position,
                    intensity * falloff,
                    footprint,
                    occluder,
                )
            }
            Light::Directional {
                direction,
                irradiance,
            } => {
                let toward_light = -direction.normalize_or_zero();
                let cosine = normal.dot(toward_light);
                if cosine <= 0.0 {
                    return Rgb::ZERO;
                }
                let ray = Ray {
                    origin,
                    direction: toward_light,
                    t_max: f32::INFINITY,
                };
                if self.bvh.occluded_cached(&ray, occluder) {
                    Rgb::ZERO
                } else {
                    irradiance * cosine
                }
            }
        }
    }

    #[inline]
    fn point_light(
        &self,
        origin: Vec3,
        normal: Vec3,
        position: Vec3,
        intensity: Rgb,
        footprint: f32,
        occluder: &mut u32,
    ) -> Rgb {
        let offset = position - origin;
        let distance_squared = offset.length_squared();
        let cosine = normal.dot(offset);
        if cosine <= 0.0 || distance_squared <= 0.0 {
            return Rgb::ZERO;
        }
        if !self.visible(origin, offset, occluder) {
            return Rgb::ZERO;
        }
        let geometry = if footprint > 0.0 {
            mean_cosine_over_square(offset, normal, footprint)
        } else {
            // E = I cos(theta) / d^2, with cos = n.offset / d.
            cosine / (distance_squared * distance_squared.sqrt())
        };
        intensity * geometry
    }

    /// Shadow ray from `origin` to `origin + offset`, stopping just short of
    /// the target so the light's own surface does not occlude it.
    #[inline]
    fn visible(&self, origin: Vec3, offset: Vec3, occluder: &mut u32) -> bool {
        let ray = Ray {
            origin,
            direction: offset,
            t_max: 1.0 - 1e-4,
        };
        !self.bvh.occluded_cached(&ray, occluder)
    }

    fn area_lights(&self, origin: Vec3, normal: Vec3, point_key: u64, occluder: &mut u32) -> Rgb {
        let samples = self.settings.area_light_samples;
        let mut rng = SampleStream::new(self.settings.seed, point_key, 0xA4EA);
        let mut sum = Rgb::ZERO;
        for sample in 0..samples {
            // Stratified in the power CDF: one sample per 1/samples interval.
            let u = (sample as f32 + rng.next_f32()) / samples as f32;
            let (index, probability) = self.emitters.pick(u.min(0.999_999_94));
            let barycentric = relight_core::sampling::uniform_triangle(rng.next_vec2());
            sum += self.emitter_sample(origin, normal, index, barycentric, occluder) / probability;
        }
        sum / samples as f32
    }

    /// Irradiance estimate of one point sample on emitter `index`, divided by
    /// nothing but the area pdf (1 / area).
    #[inline]
    pub fn emitter_sample(
        &self,
        origin: Vec3,
        normal: Vec3,
        index: usize,
        barycentric: Vec2,
        occluder: &mut u32,
    ) -> Rgb {
        let [a, b, c] = self.emitters.vertices[index];
        let light_point = a + (b - a) * barycentric.x + (c - a) * barycentric.y;
        let offset = light_point - origin;
        let distance_squared = offset.length_squared();
        let distance = distance_squared.sqrt();
        if distance <= 0.0 {
            return Rgb::ZERO;
        }
        let direction = offset / distance;
        let cosine_receiver = normal.dot(direction);
        // Emission only from the front face.
        let cosine_emitter = -self.emitters.normals[index].dot(direction);
        if cosine_receiver <= 0.0 || cosine_emitter <= 0.0 {
            return Rgb::ZERO;
        }
        if !self.visible(origin, offset, occluder) {
            return Rgb::ZERO;
        }
        self.emitters.radiance[index]
            * (cosine_receiver * cosine_emitter * self.emitters.areas[index] / distance_squared)
    }

    fn environment(&self, origin: Vec3, normal: Vec3, point_key: u64, radiance: Rgb) -> Rgb {
        let samples = self.settings.environment_samples;
        let mut rng = SampleStream::new(self.settings.seed, point_key, 0xE417);
        let mut visible = 0u32;
        for _ in 0..samples {
            let direction = cosine_hemisphere_around(normal, rng.next_vec2());
            let ray = Ray {
                origin,
                direction,
                t_max: f32::INFINITY,
            };
            if !self.bvh.occluded(&ray) {
                visible += 1;
            }
        }
        // E = pi L V with V the cosine-weighted visible fraction.
        radiance * (std::f32::consts::PI * visible as f32 / samples as f32)
    }
}

/// Spot cone falloff: one inside `inner`, smoothstep to zero at `outer`
/// (half-angles in radians), evaluated on the cosine of the angle.
#[inline]
pub fn spot_falloff(cosine: f32, inner: f32, outer: f32) -> f32 {
    let cos_inner = inner.cos();
    let cos_outer = outer.cos();
    if cosine >= cos_inner {
        return 1.0;
    }
    if cosine <= cos_outer || cos_inner <= cos_outer {
        return 0.0;
    }
    let t = (cosine - cos_outer) / (cos_inner - cos_outer);
    t * t * (3.0 - 2.0 * t)
}

#[cfg(test)]
mod tests {
    use super::*;
    use relight_scene::{Environment, Material, Mesh};

    /// The eight corners of a box come out in Morton order (x the lowest
    /// bit, then y, then z), ties keep index order, and the result is a
    /// permutation.
    #[test]
    fn morton_order_walks_the_z_curve() {
        let corner = |code: u32| {
            Vec3::new(
                (code & 1) as f32,
                ((code >> 1) & 1) as f32 * 2.0,
                ((code >> 2) & 1) as f32 * 3.0,
            )
        };
        // Corners listed in a scrambled order, plus a duplicate of corner 5.
        let codes = [6u32, 1, 5, 0, 7, 3, 2, 4, 5];
        let points: Vec<Vec3> = codes.iter().map(|&code| corner(code)).collect();
        let order = morton_order(&points);
        let walked: Vec<u32> = order.iter().map(|&index| codes[index as usize]).collect();
        assert_eq!(walked, [0, 1, 2, 3, 4, 5, 5, 6, 7]);
        // The two copies of corner 5 (indices 2 and 8) keep index order.
        assert_eq!(order[5..7], [2, 8]);
        assert_eq!(morton_code([1, 0, 0]), 1);
        assert_eq!(morton_code([0, 1, 0]), 2);
        assert_eq!(morton_code([0, 0, 1]), 4);
        assert_eq!(morton_code([1023, 1023, 1023]), (1 << 30) - 1);
        assert!(morton_order(&[]).is_empty());
    }

    /// A 2x2 m floor at y = 0 facing up, and optionally an emissive square
    /// facing down at height `light_height`.
    fn floor_scene(light: Option<(f32, f32, Rgb)>) -> Scene {
        let mut positions = vec![
            Vec3::new(-1.0, 0.0, -1.0),
            Vec3::new(1.0, 0.0, -1.0),
            Vec3::new(1.0, 0.0, 1.0),
            Vec3::new(-1.0, 0.0, 1.0),
        ];
        let mut triangles = vec![[0, 2, 1], [0, 3, 2]];
        let mut material_ids = vec![0, 0];
        let mut materials = vec![Material::default()];
        if let Some((height, half_size, radiance)) = light {
            let base = positions.len() as u32;
            positions.extend([
                Vec3::new(-half_size, height, -half_size),
                Vec3::new(half_size, height, -half_size),
                Vec3::new(half_size, height, half_size),
                Vec3::new(-half_size, height, half_size),
            ]);
            // Counter-clockwise seen from below: normal -Y.
            triangles.push([base, base + 1, base + 2]);
            triangles.push([base, base + 2, base + 3]);
            material_ids.extend([1, 1]);
            materials.push(Material {
                emission: radiance,
                ..Material::default()
            });
        }
        Scene {
            mesh: Mesh {
                positions,
                triangles,
                material_ids,
                ..Default::default()
            },
            materials,
            ..Default::default()
        }
    }

    fn bvh_of(scene: &Scene) -> Bvh {
        Bvh::build(&scene.mesh.positions, &scene.mesh.triangles)
    }

    #[test]
    fn point_light_follows_inverse_square_cosine_law() {
        let scene = floor_scene(None);
        let bvh = bvh_of(&scene);
        let emitters = Emitters::from_scene(&scene);
        let service = DirectLight::new(&scene, &bvh, &emitters, DirectSettings::default());
        let light = Light::Point {
            position: Vec3::new(0.0, 2.0, 0.0),
            intensity: Rgb::new(4.0, 2.0, 1.0),
        };
        for x in [0.0f32, 0.3, 0.7] {
            let point = Vec3::new(x, 0.0, 0.0);
            let distance_squared = 4.0 + x * x;
            let cosine = 2.0 / distance_squared.sqrt();
            let expected = Rgb::new(4.0, 2.0, 1.0) * cosine / distance_squared;
            let got = service.irradiance(std::slice::from_ref(&light), point, Vec3::Y, 0);
            assert!(
                (got - expected).abs().max_element() < 1e-4 * expected.max_element(),
                "{got} vs {expected}"
            );
            // Below the floor the light is behind the surface.
            let below = service.irradiance(std::slice::from_ref(&light), point, -Vec3::Y, 0);
            assert_eq!(below, Rgb::ZERO);
        }
    }

    /// A point light 2 cm above the floor: a point reads I / d^2 = 2500 I,
    /// a point standing for a 20 x 20 cm patch reads the patch's mean, the
    /// square's solid angle over its area (4 asin(s^2 / (s^2 + 4 h^2)) /
    /// s^2 on its axis, about 121 I). Far from the light both agree, and a
    /// shadowed point reads nothing either way.
    #[test]
    fn footprints_average_a_point_light_over_their_patch() {
        let scene = floor_scene(Some((1.0, 0.1, Rgb::ZERO)));
        let bvh = bvh_of(&scene);
        let emitters = Emitters::from_scene(&scene);
        let service = DirectLight::new(&scene, &bvh, &emitters, DirectSettings::default());
        let intensity = Rgb::new(4.0, 2.0, 1.0);
        let lights = [Light::Point {
            position: Vec3::new(0.0, 0.02, 0.0),
            intensity,
        }];
        let points = [
            Vec3::ZERO,
            Vec3::new(0.9, 0.0, 0.0),
            Vec3::new(0.0, 1.5, 0.0),
        ];
        let normals = [Vec3::Y, Vec3::Y, -Vec3::Y];
        let mut patch = [Rgb::ZERO; 3];
        let mut point = [Rgb::ZERO; 3];
        service.irradiance_batch_over_footprints(
            &lights,
            &points,
            &normals,
            Footprints::All(0.04),
            None,
            &mut patch,
        );
        service.irradiance_batch(&lights, &points, &normals, &mut point);
        let side = 0.2f32;
        let height = 0.02f32;
        let mean =
            4.0 * (side * side / (side * side + 4.0 * height * height)).asin() / (side * side);
        assert!(
            (patch[0].x / (4.0 * mean) - 1.0).abs() < 1e-3,
            "{}",
            patch[0]
        );
        // The shadow ray's origin sits 4e-5 m off the floor: 0.4 % nearer.
        assert!((point[0].x / (4.0 / (height * height)) - 1.0).abs() < 1e-2);
        // 0.9 m out the patch is 0.2 m across: the two differ by about 2 %.
        assert!(
            (patch[1].x / point[1].x - 1.0).abs() < 0.05,
            "{} {}",
            patch[1],
            point[1]
        );
        // The (dark) emissive square at 1 m hides the light from above.
        assert_eq!(patch[2], Rgb::ZERO);
        assert_eq!(point[2], Rgb::ZERO);
    }

    #[test]
    fn directional_light_is_shadowed_by_geometry() {
        let scene = floor_scene(Some((1.0, 0.5, Rgb::ZERO)));
        let bvh = bvh_of(&scene);
        let emitters = Emitters::from_scene(&scene);
        let service = DirectLight::new(&scene, &bvh, &emitters, DirectSettings::default());
        let light = Light::Directional {
            direction: Vec3::new(0.0, -1.0, 0.0),
            irradiance: Rgb::splat(3.0),
        };
        // Under the (non-emissive) square: shadowed; outside it: lit.
        let shadowed = service.irradiance(
            std::slice::from_ref(&light),
            Vec3::new(0.0, 0.0, 0.0),
            Vec3::Y,
            0,
        );
        let lit = service.irradiance(
            std::slice::from_ref(&light),
            Vec3::new(0.9, 0.0, 0.9),
            Vec3::Y,
            0,
        );
        assert_eq!(shadowed, Rgb::ZERO);
        assert!((lit - Rgb::splat(3.0)).abs().max_element() < 1e-6);
    }

    #[test]
    fn area_light_matches_analytic_square_form_factor() {
        // Irradiance under the centre of a square emitter of half-size a at
        // height h: E = L * 4 * [ a / sqrt(a^2 + h^2) * atan(a / sqrt(a^2 + h^2)) ]
        // (the point-to-parallel-rectangle form factor, times pi L).
        let (height, half_size, radiance) = (1.0f32, 0.5f32, Rgb::splat(2.0));
        let scene = floor_scene(Some((height, half_size, radiance)));
        let bvh = bvh_of(&scene);
        let emitters = Emitters::from_scene(&scene);
        let service = DirectLight::new(
            &scene,
            &bvh,
            &emitters,
            DirectSettings {
                area_light_samples: 4096,
                ..DirectSettings::default()
            },
        );
        let mut sum = Rgb::ZERO;
        let points = 32;
        for key in 0..points {
            sum += service.irradiance(&[], Vec3::new(0.0, 0.0, 0.0), Vec3::Y, key);
        }
        let estimate = sum / points as f32;
        let s = (half_size * half_size + height * height).sqrt();
        let expected = radiance.x * 4.0 * (half_size / s) * (half_size / s).atan();
        // 131k stratified samples of a smooth integrand: well under 0.5% error.
        assert!(
            (estimate.x - expected).abs() < 5e-3 * expected,
            "{} vs {expected}",
            estimate.x
        );
    }

    #[test]
    fn environment_irradiance_is_pi_radiance_when_unoccluded() {
        let mut scene = floor_scene(None);
        scene.environment = Environment {
            radiance: Rgb::splat(0.5),
        };
        let bvh = bvh_of(&scene);
        let emitters = Emitters::from_scene(&scene);
        let service = DirectLight::new(&scene, &bvh, &emitters, DirectSettings::default());
        let got = service.irradiance(&[], Vec3::new(0.0, 0.0, 0.0), Vec3::Y, 3);
        assert!((got.x - std::f32::consts::PI * 0.5).abs() < 1e-5);
    }

    /// Tracing the static light once and the punctual lights each frame
    /// gives the irradiance of tracing them together (the same samples; the
    /// sums differ only in the order of two additions).
    #[test]
    fn static_light_traced_once_adds_to_the_punctual_lights() {
        let mut scene = floor_scene(Some((1.0, 0.25, Rgb::splat(4.0))));
        scene.environment = Environment {
            radiance: Rgb::new(0.2, 0.3, 0.5),
        };
        let bvh = bvh_of(&scene);
        let emitters = Emitters::from_scene(&scene);
        let service = DirectLight::new(&scene, &bvh, &emitters, DirectSettings::default());
        assert!(service.has_static_light());
        let lights = [Light::Point {
            position: Vec3::new(0.3, 0.6, -0.2),
            intensity: Rgb::splat(2.0),
        }];
        let points: Vec<Vec3> = (0..600)
            .map(|index| {
                Vec3::new(
                    (index % 30) as f32 / 15.0 - 1.0,
                    0.0,
                    (index / 30) as f32 / 10.0 - 1.0,
                )
            })
            .collect();
        let normals = vec![Vec3::Y; points.len()];
        let mut together = vec![Rgb::ZERO; points.len()];
        service.irradiance_batch(&lights, &points, &normals, &mut together);
        let mut fixed = vec![Rgb::ZERO; points.len()];
        service.static_irradiance_batch(&points, &normals, &mut fixed);
        let mut split = vec![Rgb::ZERO; points.len()];
        service.irradiance_batch_over_static(&lights, &points, &normals, Some(&fixed), &mut split);
        for (index, (a, b)) in together.iter().zip(&split).enumerate() {
            assert!(
                (*a - *b).abs().max_element() <= 1e-5 * a.max_element().max(1.0),
                "{index}: {a:?} {b:?}"
            );
        }
        // The static part alone is the light with no punctual light.
        let mut unlit = vec![Rgb::ZERO; points.len()];
        service.irradiance_batch(&[], &points, &normals, &mut unlit);
        assert_eq!(unlit, fixed);
        // Without emitters or environment there is nothing to keep.
        let bare = floor_scene(None);
        let bare_bvh = bvh_of(&bare);
        let bare_emitters = Emitters::from_scene(&bare);
        assert!(
            !DirectLight::new(&bare, &bare_bvh, &bare_emitters, DirectSettings::default())
                .has_static_light()
        );
    }

    #[test]
    fn spot_falloff_is_smooth_and_bounded() {
        let inner = 20f32.to_radians();
        let outer = 30f32.to_radians();
        assert_eq!(spot_falloff(1.0, inner, outer), 1.0);
        assert_eq!(spot_falloff(19f32.to_radians().cos(), inner, outer), 1.0);
        assert_eq!(spot_falloff(31f32.to_radians().cos(), inner, outer), 0.0);
        let middle = spot_falloff(25f32.to_radians().cos(), inner, outer);
        assert!(middle > 0.3 && middle < 0.7, "{middle}");
    }
}
