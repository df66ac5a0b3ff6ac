//! Rendering the camera view: primary rays through the BVH, exact direct
//! light from the shared service, indirect light from a technique or from
//! the path tracer. Both produce the same three images (full, direct,
//! indirect) so that comparisons are like for like.

use crate::image::Image;
use rayon::prelude::*;
use relight_core::sampling::{stratification_offset, stratified_square, SampleStream};
use relight_core::Rgb;
use relight_scene::Light;
use relight_technique::{Progress, SceneContext, SurfacePoint, Technique};
use relight_trace::bvh::{Hit, Ray};
use relight_trace::path::{halves_estimate, CameraRays, PathSettings, PathTracer};

/// The three images every render produces.
#[derive(Clone, Debug)]
pub struct Renders {
    /// Emission seen directly + direct + indirect.
    pub full: Image,
    /// Emission seen directly + light reflected once at the visible surface.
    pub direct: Image,
    /// Light that bounced at least once before the visible surface.
    pub indirect: Image,
    /// Standard error of `indirect` per pixel (Monte Carlo renders only;
    /// zero for deterministic technique renders).
    pub indirect_standard_error: Image,
}

/// Shared pixel loop: `shade(x, y, pixel_index)` returns the direct and
/// indirect means of one pixel and the indirect standard error; rows run in
/// parallel, reported to `progress`.
fn render_pixels(
    width: u32,
    height: u32,
    progress: &dyn Progress,
    stage: &str,
    shade: impl Fn(u32, u32, u64) -> (Rgb, Rgb, Rgb) + Sync,
) -> Renders {
    progress.start(stage, height as u64);
    let rows: Vec<Vec<(Rgb, Rgb, Rgb)>> = (0..height)
        .into_par_iter()
        .map(|y| {
            let row = (0..width)
                .map(|x| shade(x, y, (y as u64) * width as u64 + x as u64))
                .collect();
            progress.advance(1);
            row
        })
        .collect();
    progress.finish();
    let mut renders = Renders {
        full: Image::new(width, height),
        direct: Image::new(width, height),
        indirect: Image::new(width, height),
        indirect_standard_error: Image::new(width, height),
    };
    for (index, (direct, indirect, standard_error)) in rows.into_iter().flatten().enumerate() {
        renders.direct.pixels[index] = direct;
        renders.indirect.pixels[index] = indirect;
        renders.indirect_standard_error.pixels[index] = standard_error;
        renders.full.pixels[index] = direct + indirect;
    }
    renders
}

/// Path-traced reference images of the scene camera with `spp` jittered
/// samples per pixel (box filter).
pub fn render_reference(
    context: &SceneContext,
    lights: &[Light],
    settings: PathSettings,
    spp: u32,
    progress: &dyn Progress,
) -> Renders {
    render_reference_view(
        context,
        lights,
        &context.scene.camera,
        settings,
        spp,
        progress,
    )
}

/// [`render_reference`] from any `camera` (an interactive viewer's):
/// passes with different `settings.seed` are independent, so a viewer
/// averages them into a progressive reference.
pub fn render_reference_view(
    context: &SceneContext,
    lights: &[Light],
    camera: &relight_scene::Camera,
    settings: PathSettings,
    spp: u32,
    progress: &dyn Progress,
) -> Renders {
    let direct = context.direct();
    let tracer = PathTracer::new(&direct, settings);
    let camera = CameraRays::new(camera);
    let spp = spp.max(1);
    render_pixels(
        camera.width,
        camera.height,
        progress,
        "path tracing",
        |x, y, pixel| {
            // Two independent halves, each with its first bounce stratified
            // over its own samples: most of the indirect image's variance
            // comes from that one direction. Stratification breaks the iid
            // variance formula, so the standard error is |A - B| / 2.
            let half = (spp / 2).max(1);
            let mut direct_sum = [0.0f64; 3];
            let mut indirect_halves = [[0.0f64; 3]; 2];
            for (part, indirect_sum) in indirect_halves.iter_mut().enumerate() {
                let seed = settings.half(part).seed;
                let offset = stratification_offset(seed, pixel);
                for sample in 0..half {
                    let mut rng = SampleStream::new(seed, pixel, sample as u64);
                    let ray = camera.ray(x, y, rng.next_vec2());
                    let first_bounce = stratified_square(sample, half, offset, &mut rng);
                    let key = (pixel << 24) ^ ((part as u64) << 22) ^ sample as u64;
                    let split = tracer.camera_sample(lights, &ray, first_bounce, &mut rng, key);
                    for channel in 0..3 {
                        direct_sum[channel] += split.direct[channel] as f64;
                        indirect_sum[channel] += split.indirect[channel] as f64;
                    }
                }
            }
            let [first, second] = indirect_halves;
            let (indirect, indirect_error) = halves_estimate(first, second, half);
            (
                to_rgb(direct_sum, 0.5 / half as f64),
                indirect,
                indirect_error,
            )
        },
    )
}

fn to_rgb(sum: [f64; 3], scale: f64) -> Rgb {
    Rgb::new(
        (sum[0] * scale) as f32,
        (sum[1] * scale) as f32,
        (sum[2] * scale) as f32,
    )
}

/// Two surfaces closer than this along a camera ray are one surface seen
/// twice: rooms modelled as separate boxes that touch, or overlap by a
/// modelling slip, put one room's wall in or just before the plane of the
/// next room's, facing away from it.
const COINCIDENT_SURFACES_M: f32 = 0.01;

/// The camera ray's closest hit, except that a back face within
/// 1 cm (`COINCIDENT_SURFACES_M`) of a front face yields to it, as it does in an
/// engine that culls back faces ([`relight_trace::bvh::Bvh::intersect_front_first`]).
/// Where the tie fell to the back face, the pixel asked the technique for
/// a point in space instead of reading the wall's lightmap, and the wall
/// showed wedges of another shade that followed the BVH's ties. The path
/// tracer needs no such rule: it lights both faces alike from the
/// camera's side.
pub fn visible_hit(context: &SceneContext, ray: &Ray) -> Option<Hit> {
    let mesh = &context.scene.mesh;
    let tolerance = COINCIDENT_SURFACES_M / ray.direction.length();
    context
        .bvh
        .intersect_front_first(ray, tolerance, |triangle| {
            mesh.geometric_normal(triangle as usize).dot(ray.direction) < 0.0
        })
}

/// Images lit by `technique`'s indirect light and the shared direct light,
/// `spp` jittered primary rays per pixel (for antialiasing and area-light
/// sampling; the technique's answer itself is noise-free).
pub fn render_with_technique(
    context: &SceneContext,
    lights: &[Light],
    technique: &dyn Technique,
    spp: u32,
    seed: u64,
    progress: &dyn Progress,
) -> Renders {
    let direct = context.direct();
    let camera = CameraRays::new(&context.scene.camera);
    let scene = &context.scene;
    let spp = spp.max(1);
    render_pixels(
        camera.width,
        camera.height,
        progress,
        technique.name(),
        |x, y, pixel| {
            let mut direct_sum = Rgb::ZERO;
            let mut indirect_sum = Rgb::ZERO;
            for sample in 0..spp {
                let mut rng = SampleStream::new(seed, pixel, sample as u64);
                let ray = camera.ray(x, y, rng.next_vec2());
                let Some(hit) = visible_hit(context, &ray) else {
                    direct_sum += scene.environment.radiance;
                    continue;
                };
                let triangle = hit.triangle as usize;
                let position = scene.mesh.point_at(triangle, hit.barycentric);
                let front = scene.mesh.geometric_normal(triangle);
                let seen_from_front = front.dot(ray.direction) < 0.0;
                let normal = if seen_from_front { front } else { -front };
                let albedo = scene.albedo_at(triangle, hit.barycentric);
                let irradiance =
                    direct.irradiance(lights, position, normal, (pixel << 24) ^ sample as u64);
                if seen_from_front {
                    direct_sum += scene.material_of(triangle).emission;
                }
                direct_sum += albedo * irradiance * std::f32::consts::FRAC_1_PI;
                // The lightmap holds the front side; the back of thin geometry
                // asks the technique as a point in space.
                let indirect = if seen_from_front {
                    let point = SurfacePoint {
                        position,
                        normal,
                        triangle: hit.triangle,
                        barycentric: hit.barycentric,
                    };
                    // Glossy materials add the technique's view-dependent
                    // indirect reflection when it models one.
                    let exponent = scene.material_of(triangle).phong_exponent;
                    if exponent > 1.0 {
                        if let Some(glossy) =
                            technique.glossy_radiance(&point, -ray.direction.normalize(), exponent)
                        {
                            indirect_sum += glossy;
                        }
                    }
                    technique.indirect_irradiance(&point)
                } else {
                    technique.indirect_irradiance_in_space(position, normal)
                };
                indirect_sum += albedo * indirect * std::f32::consts::FRAC_1_PI;
            }
            let scale = 1.0 / spp as f32;
            (direct_sum * scale, indirect_sum * scale, Rgb::ZERO)
        },
    )
}
