//! Ray-throughput benchmark of [`Bvh`] (and of Embree beside it with the
//! `embree` feature), for `relight bench-rays` and for tuning the BVH.
//!
//! Three ray sets, generated deterministically from `seed` and shared by
//! both tracers so the numbers compare like with like:
//! 1. incoherent diffuse rays: origins area-weighted on random triangles,
//!    offset along the geometric normal, cosine-distributed about it, traced
//!    for the closest hit;
//! 2. the same rays as occlusion queries with t_max = infinity;
//! 3. coherent shadow rays from random surface points sorted along a Morton
//!    curve (neighbouring rays start close together) to `light_position`,
//!    stopping just short of the light.
//!
//! Each set is traced through the batch methods (all rayon threads) once to
//! warm caches, then `repeats` times, BVH and Embree alternating so both see
//! the same machine load; the median rate is reported. Build time
//! is the median of [`BUILD_REPEATS`] builds.

use crate::bvh::{Bvh, Hit, Ray};
use crate::direct::morton_code;
use glam::Vec3;
use rayon::prelude::*;
use relight_core::sampling::{cosine_hemisphere_around, uniform_triangle, SampleStream};
use std::fmt;
use std::time::Instant;

pub const BUILD_REPEATS: usize = 3;

/// Millions of rays per second, median over the repeats.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct RayRates {
    pub diffuse_closest_hit: f64,
    pub diffuse_occlusion: f64,
    pub coherent_shadow: f64,
}

#[derive(Clone, Debug, Default, PartialEq)]
pub struct RayBenchReport {
    pub triangle_count: usize,
    pub ray_count: usize,
    pub repeats: usize,
    pub threads: usize,
    pub build_ms: f64,
    pub node_count: usize,
    pub memory_bytes: usize,
    pub rates: RayRates,
    /// Sanity figures: fraction of diffuse rays that hit something and of
    /// shadow rays that are blocked.
    pub diffuse_hit_fraction: f64,
    pub shadow_occluded_fraction: f64,
    /// Embree on the same rays (feature `embree`); `None` without it.
    pub embree_build_ms: Option<f64>,
    pub embree_rates: Option<RayRates>,
    /// Diffuse rays whose closest hit differs from Embree's beyond float
    /// rounding (different hit/miss, or different triangle at a clearly
    /// different distance), and shadow rays whose occlusion differs.
    pub embree_closest_hit_disagreements: Option<usize>,
    pub embree_occlusion_disagreements: Option<usize>,
}

/// The three ray sets of the benchmark.
pub struct RaySets {
    pub diffuse: Vec<Ray>,
    pub shadow: Vec<Ray>,
}

fn median(mut values: Vec<f64>) -> f64 {
    values.sort_by(f64::total_cmp);
    values[values.len() / 2]
}

/// Samples surface points area-weighted: (point, geometric unit normal).
fn surface_points(
    positions: &[Vec3],
    triangles: &[[u32; 3]],
    count: usize,
    seed: u64,
    pass: u64,
) -> Vec<(Vec3, Vec3)> {
    let corners = |triangle: &[u32; 3]| triangle.map(|index| positions[index as usize]);
    let mut cumulative_area = Vec::with_capacity(triangles.len());
    let mut total = 0.0f64;
    for triangle in triangles {
        let [v0, v1, v2] = corners(triangle);
        let area = 0.5 * (v1 - v0).cross(v2 - v0).length() as f64;
        if area.is_finite() {
            total += area;
        }
        cumulative_area.push(total);
    }
    if total <= 0.0 {
        return Vec::new();
    }
    (0..count)
        .into_par_iter()
        .map(|index| {
            let mut rng = SampleStream::new(seed, index as u64, pass);
            let target = (rng.next_f32() as f64) * total;
            let chosen = cumulative_area
                .partition_point(|&area| area <= target)
                .min(triangles.len() - 1);
            let [v0, v1, v2] = corners(&triangles[chosen]);
            let barycentric = uniform_triangle(rng.next_vec2());
            let point = v0 + (v1 - v0) * barycentric.x + (v2 - v0) * barycentric.y;
            let normal = (v1 - v0).cross(v2 - v0).normalize_or_zero();
            (point, normal)
        })
        .collect()
}

impl RaySets {
    /// The diffuse rays as occlusion queries to infinity.
    pub fn diffuse_occlusion(&self) -> Vec<Ray> {
        self.diffuse
            .iter()
            .map(|ray| Ray {
                t_max: f32::INFINITY,
                ..*ray
            })
            .collect()
    }

    pub fn generate(
        positions: &[Vec3],
        triangles: &[[u32; 3]],
        light_position: Vec3,
        ray_count: usize,
        seed: u64,
    ) -> RaySets {
        let (low, high) = positions.iter().fold(
            (Vec3::splat(f32::INFINITY), Vec3::splat(f32::NEG_INFINITY)),
            |(low, high), &position| (low.min(position), high.max(position)),
        );
        let extent = (high - low).max(Vec3::splat(1e-6));
        // Large enough to clear float error at scene scale, small enough not
        // to skip thin geometry.
        let offset = 1e-4 * extent.length();

        let diffuse = surface_points(positions, triangles, ray_count, seed, 0)
            .into_par_iter()
            .enumerate()
            .map(|(index, (point, normal))| {
                let mut rng = SampleStream::new(seed, index as u64, 1);
                Ray {
                    origin: point + normal * offset,
                    direction: cosine_hemisphere_around(normal, rng.next_vec2()),
                    t_max: f32::INFINITY,
                }
            })
            .collect();

        let mut shadow_points = surface_points(positions, triangles, ray_count, seed, 2);
        let cell_scale = Vec3::splat(1023.0) / extent;
        shadow_points.par_sort_by_cached_key(|(point, _)| {
            morton_code(((*point - low) * cell_scale).as_uvec3().to_array())
        });
        let shadow = shadow_points
            .into_iter()
            .map(|(point, normal)| {
                // Offset toward the light's side so the ray leaves its surface.
                let facing = if normal.dot(light_position - point) >= 0.0 {
                    normal
                } else {
                    -normal
                };
                let origin = point + facing * offset;
                Ray {
                    origin,
                    direction: light_position - origin,
                    t_max: 1.0 - 1e-4,
                }
            })
            .collect();
        RaySets { diffuse, shadow }
    }
}

fn time_builds<T>(mut build: impl FnMut() -> T) -> (f64, T) {
    let mut durations = Vec::new();
    let mut built = None;
    for _ in 0..BUILD_REPEATS {
        let start = Instant::now();
        let result = build();
        durations.push(start.elapsed().as_secs_f64() * 1e3);
        built = Some(result);
    }
    (median(durations), built.expect("at least one build"))
}

/// Anything that traces batches; lets the BVH and Embree share the timing code.
trait BatchTracer: Sync {
    fn intersect_batch(&self, rays: &[Ray], hits: &mut [Option<Hit>]);
    fn occluded_batch(&self, rays: &[Ray], occluded: &mut [bool]);
}

impl BatchTracer for Bvh {
    fn intersect_batch(&self, rays: &[Ray], hits: &mut [Option<Hit>]) {
        Bvh::intersect_batch(self, rays, hits)
    }
    fn occluded_batch(&self, rays: &[Ray], occluded: &mut [bool]) {
        Bvh::occluded_batch(self, rays, occluded)
    }
}

#[cfg(feature = "embree")]
impl BatchTracer for crate::bvh::EmbreeScene {
    fn intersect_batch(&self, rays: &[Ray], hits: &mut [Option<Hit>]) {
        crate::bvh::EmbreeScene::intersect_batch(self, rays, hits)
    }
    fn occluded_batch(&self, rays: &[Ray], occluded: &mut [bool]) {
        crate::bvh::EmbreeScene::occluded_batch(self, rays, occluded)
    }
}

struct Traced {
    rates: RayRates,
    diffuse_hits: Vec<Option<Hit>>,
    shadow_occluded: Vec<bool>,
}

fn seconds(work: impl FnOnce()) -> f64 {
    let start = Instant::now();
    work();
    start.elapsed().as_secs_f64()
}

/// Traces every ray set with every tracer: one warm-up pass, then
/// `repeats` passes, the tracers interleaved within each pass so that load
/// from other processes affects them alike. Rates are medians in Mrays/s.
fn measure(tracers: &[&dyn BatchTracer], rays: &RaySets, repeats: usize) -> Vec<Traced> {
    let diffuse_occlusion_rays = rays.diffuse_occlusion();
    let mut traced: Vec<Traced> = tracers
        .iter()
        .map(|_| Traced {
            rates: RayRates::default(),
            diffuse_hits: vec![None; rays.diffuse.len()],
            shadow_occluded: vec![false; rays.shadow.len()],
        })
        .collect();
    let mut diffuse_occluded = vec![false; rays.diffuse.len()];
    let mut rates: Vec<[Vec<f64>; 3]> = vec![Default::default(); tracers.len()];
    let ray_counts = [rays.diffuse.len(), rays.diffuse.len(), rays.shadow.len()];
    for pass in 0..=repeats.max(1) {
        for ((tracer, traced), rates) in tracers.iter().zip(&mut traced).zip(&mut rates) {
            let durations = [
                seconds(|| tracer.intersect_batch(&rays.diffuse, &mut traced.diffuse_hits)),
                seconds(|| tracer.occluded_batch(&diffuse_occlusion_rays, &mut diffuse_occluded)),
                seconds(|| tracer.occluded_batch(&rays.shadow, &mut traced.shadow_occluded)),
            ];
            if pass > 0 {
                for case in 0..3 {
                    rates[case].push(ray_counts[case] as f64 / durations[case] / 1e6);
                }
            }
        }
    }
    for (traced, rates) in traced.iter_mut().zip(rates) {
        let [closest, occlusion, shadow] = rates.map(median);
        traced.rates = RayRates {
            diffuse_closest_hit: closest,
            diffuse_occlusion: occlusion,
            coherent_shadow: shadow,
        };
    }
    traced
}

fn fraction(count: usize, total: usize) -> f64 {
    count as f64 / total.max(1) as f64
}

/// The rates of `bvh` on `ray_count` rays of each set (median of
/// `repeats` passes after a warm-up): what `relight bench-rays` reports,
/// without its builds.
pub fn rates_on(
    bvh: &Bvh,
    positions: &[Vec3],
    triangles: &[[u32; 3]],
    light_position: Vec3,
    ray_count: usize,
    repeats: usize,
    seed: u64,
) -> RayRates {
    let rays = RaySets::generate(positions, triangles, light_position, ray_count, seed);
    let tracers: [&dyn BatchTracer; 1] = [bvh];
    measure(&tracers, &rays, repeats)
        .into_iter()
        .next()
        .expect("the BVH was traced")
        .rates
}

/// Builds and traces; see the module documentation for the ray sets.
pub fn run(
    positions: &[Vec3],
    triangles: &[[u32; 3]],
    light_position: Vec3,
    ray_count: usize,
    repeats: usize,
    seed: u64,
) -> RayBenchReport {
    let (build_ms, bvh) = time_builds(|| Bvh::build(positions, triangles));
    let rays = RaySets::generate(positions, triangles, light_position, ray_count, seed);
    #[cfg(feature = "embree")]
    let (embree_build_ms, embree) =
        time_builds(|| crate::bvh::EmbreeScene::build(positions, triangles));
    #[cfg(feature = "embree")]
    let tracers: [&dyn BatchTracer; 2] = [&bvh, &embree];
    #[cfg(not(feature = "embree"))]
    let tracers: [&dyn BatchTracer; 1] = [&bvh];
    let mut all_traced = measure(&tracers, &rays, repeats).into_iter();
    let traced = all_traced.next().expect("the BVH was traced");
    #[allow(unused_mut)]
    let mut report = RayBenchReport {
        triangle_count: triangles.len(),
        ray_count: rays.diffuse.len(),
        repeats,
        threads: rayon::current_num_threads(),
        build_ms,
        node_count: bvh.node_count(),
        memory_bytes: bvh.memory_bytes(),
        rates: traced.rates,
        diffuse_hit_fraction: fraction(
            traced
                .diffuse_hits
                .iter()
                .filter(|hit| hit.is_some())
                .count(),
            rays.diffuse.len(),
        ),
        shadow_occluded_fraction: fraction(
            traced
                .shadow_occluded
                .iter()
                .filter(|&&blocked| blocked)
                .count(),
            rays.shadow.len(),
        ),
        ..RayBenchReport::default()
    };
    #[cfg(feature = "embree")]
    {
        let embree_traced = all_traced.next().expect("Embree was traced");
        let closest_hit_disagreements = traced
            .diffuse_hits
            .iter()
            .zip(&embree_traced.diffuse_hits)
            .filter(|(ours, theirs)| match (ours, theirs) {
                (None, None) => false,
                (Some(ours), Some(theirs)) => {
                    ours.triangle != theirs.triangle
                        && (ours.t - theirs.t).abs() > 1e-4 * theirs.t.abs()
                }
                _ => true,
            })
            .count();
        let occlusion_disagreements = traced
            .shadow_occluded
            .iter()
            .zip(&embree_traced.shadow_occluded)
            .filter(|(ours, theirs)| ours != theirs)
            .count();
        report.embree_build_ms = Some(embree_build_ms);
        report.embree_rates = Some(embree_traced.rates);
        report.embree_closest_hit_disagreements = Some(closest_hit_disagreements);
        report.embree_occlusion_disagreements = Some(occlusion_disagreements);
    }
    report
}

impl fmt::Display for RayBenchReport {
    fn fmt(&self, formatter: &mut fmt::Formatter<'_>) -> fmt::Result {
        writeln!(
            formatter,
            "{} triangles, {} rays per set, {} threads, median of {} runs",
            self.triangle_count, self.ray_count, self.threads, self.repeats
        )?;
        writeln!(
            formatter,
            "BVH: {} nodes, {:.1} MiB; diffuse rays hitting {:.1}%, shadow rays blocked {:.1}%",
            self.node_count,
            self.memory_bytes as f64 / (1024.0 * 1024.0),
            100.0 * self.diffuse_hit_fraction,
            100.0 * self.shadow_occluded_fraction
        )?;
        writeln!(formatter, "{:<34}{:>12}{:>12}", "", "relight", "Embree 3")?;
        let embree = |value: Option<f64>| match value {
            Some(value) => format!("{value:>12.2}"),
            None => format!("{:>12}", "-"),
        };
        let rows = [
            ("build (ms)", self.build_ms, self.embree_build_ms),
            (
                "diffuse closest hit (Mrays/s)",
                self.rates.diffuse_closest_hit,
                self.embree_rates.map(|rates| rates.diffuse_closest_hit),
            ),
            (
                "diffuse occlusion (Mrays/s)",
                self.rates.diffuse_occlusion,
                self.embree_rates.map(|rates| rates.diffuse_occlusion),
            ),
            (
                "coherent shadow (Mrays/s)",
                self.rates.coherent_shadow,
                self.embree_rates.map(|rates| rates.coherent_shadow),
            ),
        ];
        for (label, ours, theirs) in rows {
            writeln!(formatter, "{label:<34}{ours:>12.2}{}", embree(theirs))?;
        }
        if let (Some(closest), Some(occlusion)) = (
            self.embree_closest_hit_disagreements,
            self.embree_occlusion_disagreements,
        ) {
            writeln!(
                formatter,
                "disagreements with Embree: {closest} closest hits, {occlusion} shadow rays"
            )?;
        }
        Ok(())
    }
}
