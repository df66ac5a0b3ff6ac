//! What a convergence study measures of a technique against the path
//! tracer, beyond one relRMSE: the reference (lightmap and camera image,
//! cached on disk under a key of everything that changes it), which
//! receivers the camera sees, what kind of place each receiver stands in,
//! and the error norms over each of those.
//!
//! Data flow: [`Split::of`] finds once per scene which receivers the camera
//! sees, each receiver's class, the pixels that see back faces and the
//! points in space; [`ReferenceSet::cached`] path traces (or reads) the
//! reference at all of them once per bounce count; [`Measurement::of`]
//! compares one updated technique with it.

use crate::image::Image;
use crate::metrics::{
    error_norms, kept, light_ratio, relative_noise, subset_error, tile_means, SubsetError,
};
use crate::render::{render_reference, render_with_technique, visible_hit};
use rayon::prelude::*;
use relight_core::sampling::{cosine_hemisphere_around, stratified_square};
use relight_core::Rgb;
use relight_technique::{
    reference_irradiance_at, reference_receiver_irradiance, Progress, SceneContext, Technique,
};
use relight_trace::bvh::Ray;
use relight_trace::path::{CameraRays, PathSettings};
use std::path::Path;

/// Pixel tiles whose means the tile error compares: 8x8 averages the
/// reference's per-pixel noise down by 8 while keeping the scale at which
/// blotches, seams and leaks show.
pub const TILE: u32 = 8;

/// The path-traced reference of one scene, light set and path setting.
#[derive(Clone, Debug)]
pub struct ReferenceSet {
    pub lightmap: Vec<Rgb>,
    pub lightmap_error: Vec<Rgb>,
    /// Indirect-only camera image and its per-pixel standard error.
    pub image: Image,
    pub image_error: Image,
    /// Indirect irradiance at [`SpacePoints`] and its standard error.
    pub space: Vec<Rgb>,
    pub space_error: Vec<Rgb>,
}

/// Points in space where dynamic objects could stand: a grid over the
/// scene's bounds (inset by half a cell), those inside geometry left out,
/// each with the six axis normals.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct SpacePoints {
    pub positions: Vec<glam::Vec3>,
    pub normals: Vec<glam::Vec3>,
}

/// Grid cells of [`SpacePoints`]: about 8 x 8 x 8 over the scene's content
/// bounds (not a ground plane far outside; `Scene::content_bounds`).
const SPACE_CELLS: f32 = 512.0;

impl SpacePoints {
    pub fn of(context: &SceneContext) -> Self {
        let (lo, hi) = context.scene.content_bounds();
        let extent = (hi - lo).max(glam::Vec3::splat(1e-3));
        let cell = (extent.x * extent.y * extent.z / SPACE_CELLS).cbrt();
        let dims = (extent / cell).ceil().max(glam::Vec3::ONE).as_uvec3();
        let step = extent / dims.as_vec3();
        let mut points = Self {
            positions: Vec::new(),
            normals: Vec::new(),
        };
        let axes = [
            glam::Vec3::X,
            glam::Vec3::NEG_X,
            glam::Vec3::Y,
            glam::Vec3::NEG_Y,
            glam::Vec3::Z,
            glam::Vec3::NEG_Z,
        ];
        for z in 0..dims.z {
            for y in 0..dims.y {
                for x in 0..dims.x {
                    let position = lo + (glam::UVec3::new(x, y, z).as_vec3() + 0.5) * step;
                    if context.is_inside_geometry(position) {
                        continue;
                    }
                    for normal in axes {
                        points.positions.push(position);
                        points.normals.push(normal);
                    }
                }
            }
        }
        points
    }
}

/// A 64-bit FNV-1a over bytes: cache keys, not security.
fn fnv(hash: &mut u64, bytes: &[u8]) {
    for byte in bytes {
        *hash ^= *byte as u64;
        *hash = hash.wrapping_mul(0x0100_0000_01b3);
    }
}

impl ReferenceSet {
    /// Everything the reference depends on: geometry, materials and
    /// receivers (the bake fingerprint), texture texels, lights,
    /// environment, camera, direct-light and path settings, sample counts.
    /// Two scene files over one mesh with different lights get different
    /// keys.
    pub fn key(context: &SceneContext, settings: PathSettings, samples: u32, spp: u32) -> u64 {
        let mut hash = 0xcbf2_9ce4_8422_2325u64;
        fnv(&mut hash, &context.fingerprint().to_le_bytes());
        let scene = &context.scene;
        for texture in &scene.textures {
            fnv(&mut hash, &texture.width.to_le_bytes());
            fnv(&mut hash, &texture.height.to_le_bytes());
            fnv(&mut hash, bytemuck::cast_slice(&texture.texels));
        }
        let described = format!(
            "{:?}|{:?}|{:?}|{:?}|{:?}|{samples}|{spp}",
            scene.lights, scene.environment, scene.camera, context.settings.direct, settings
        );
        fnv(&mut hash, described.as_bytes());
        hash
    }

    /// The reference with `samples` paths per receiver and per point of
    /// `space_points` (those of [`SpacePoints::of`] this context, which the
    /// cache file's layout assumes) and `spp` per pixel, read from `cache`
    /// when a file of the same key is there, else traced and written there
    /// (a cache that cannot be written only costs the next run its time).
    pub fn cached(
        context: &SceneContext,
        space_points: &SpacePoints,
        settings: PathSettings,
        samples: u32,
        spp: u32,
        cache: Option<&Path>,
        progress: &dyn Progress,
    ) -> Self {
        let key = Self::key(context, settings, samples, spp);
        // A set without points in space is another file, so a study's set
        // and a test's never overwrite each other under one key.
        let name = match space_points.positions.len() {
            0 => format!("relight-reference-{key:016x}-no-space.f32"),
            _ => format!("relight-reference-{key:016x}.f32"),
        };
        let file = cache.map(|folder| folder.join(name));
        let receivers = context.atlas.receivers.len();
        let [width, height] = context.scene.camera.resolution;
        let pixels = (width * height) as usize;
        let points = space_points.positions.len();
        if let Some(values) = file.as_ref().and_then(|file| std::fs::read(file).ok()) {
            if values.len() == (receivers + pixels + points) * 2 * 12 {
                let mut floats = values
                    .chunks_exact(4)
                    .map(|b| f32::from_le_bytes([b[0], b[1], b[2], b[3]]));
                let mut take = |count: usize| -> Vec<Rgb> {
                    (0..count)
                        .map(|_| {
                            let mut next = || floats.next().unwrap_or(0.0);
                            Rgb::new(next(), next(), next())
                        })
                        .collect()
                };
                let lightmap = take(receivers);
                let lightmap_error = take(receivers);
                let image = take(pixels);
                let image_error = take(pixels);
                let space = take(points);
                let space_error = take(points);
                let as_image = |pixels| Image {
                    width,
                    height,
                    pixels,
                };
                return Self {
                    lightmap,
                    lightmap_error,
                    image: as_image(image),
                    image_error: as_image(image_error),
                    space,
                    space_error,
                };
            }
        }
        let lights = &context.scene.lights;
        let traced = reference_receiver_irradiance(context, lights, settings, samples, progress);
        let renders = render_reference(context, lights, settings, spp, progress);
        let space = reference_irradiance_at(
            context,
            lights,
            settings,
            samples,
            &space_points.positions,
            &space_points.normals,
            progress,
        );
        let set = Self {
            lightmap: traced.mean,
            lightmap_error: traced.standard_error,
            image: renders.indirect,
            image_error: renders.indirect_standard_error,
            space: space.mean,
            space_error: space.standard_error,
        };
        if let Some(file) = file {
            let mut bytes = Vec::with_capacity((receivers + pixels + points) * 24);
            for list in [
                &set.lightmap,
                &set.lightmap_error,
                &set.image.pixels,
                &set.image_error.pixels,
                &set.space,
                &set.space_error,
            ] {
                for value in list.iter() {
                    for component in value.to_array() {
                        bytes.extend_from_slice(&component.to_le_bytes());
                    }
                }
            }
            // Written aside and renamed, so a process reading the folder
            // meanwhile never takes a part-written file for a reference.
            let aside = file.with_extension(format!("{}.part", std::process::id()));
            if std::fs::write(&aside, bytes).is_ok() && std::fs::rename(&aside, &file).is_err() {
                let _ = std::fs::remove_file(&aside);
            }
        }
        set
    }

    /// The standard error of each 8x8 tile mean of the reference image
    /// (row-major, as [`tile_means`] orders them): the root sum of its
    /// pixels' squared errors over the pixel count, the pixels being
    /// independent estimates.
    pub fn tile_standard_errors(&self) -> Vec<Rgb> {
        let squared = Image {
            width: self.image_error.width,
            height: self.image_error.height,
            pixels: self.image_error.pixels.iter().map(|e| *e * *e).collect(),
        };
        let pixels_per_tile = (TILE * TILE) as f32;
        tile_means(&squared, TILE)
            .into_iter()
            .map(|mean| {
                Rgb::new(mean.x.sqrt(), mean.y.sqrt(), mean.z.sqrt()) / pixels_per_tile.sqrt()
            })
            .collect()
    }

    /// The reference's own relative noise: over all receivers, over those
    /// `visible` selects, per pixel and over tile means.
    pub fn noise(&self, visible: &[bool]) -> Noise {
        let pick = |list: &[Rgb]| kept(list, visible);
        let tile_error = self.tile_standard_errors();
        Noise {
            lightmap: relative_noise(&self.lightmap, &self.lightmap_error),
            visible_lightmap: relative_noise(&pick(&self.lightmap), &pick(&self.lightmap_error)),
            image: relative_noise(&self.image.pixels, &self.image_error.pixels),
            image_tiles: relative_noise(&tile_means(&self.image, TILE), &tile_error),
            space: relative_noise(&self.space, &self.space_error),
        }
    }
}

/// The reference's own relative noise in each norm a study reports: a
/// perfect technique would still show about this much error.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct Noise {
    pub lightmap: f64,
    pub visible_lightmap: f64,
    pub image: f64,
    pub image_tiles: f64,
    pub space: f64,
}

/// Receivers whose texels a camera pixel reads from the front (2x2 primary
/// rays per pixel, each marking the texels of its bilinear footprint):
/// the part of the lightmap a viewer of the scene's camera judges.
pub fn visible_receivers(context: &SceneContext) -> Vec<bool> {
    let camera = CameraRays::new(&context.scene.camera);
    let atlas = &context.atlas;
    let receiver_of_texel = atlas.dilated_receiver_of_texel();
    let mesh = &context.scene.mesh;
    let seen: Vec<Vec<u32>> = (0..camera.height)
        .into_par_iter()
        .map(|y| {
            let mut row = Vec::new();
            for x in 0..camera.width {
                for sub in 0..4u32 {
                    let offset = glam::Vec2::new(
                        0.25 + 0.5 * (sub % 2) as f32,
                        0.25 + 0.5 * (sub / 2) as f32,
                    );
                    let ray = camera.ray(x, y, offset);
                    let Some(hit) = visible_hit(context, &ray) else {
                        continue;
                    };
                    let front = mesh.geometric_normal(hit.triangle as usize);
                    if front.dot(ray.direction) >= 0.0 {
                        continue;
                    }
                    for (texel, weight) in atlas.bilinear_texels(hit.triangle, hit.barycentric) {
                        let receiver = receiver_of_texel[texel];
                        if weight > 0.0 && receiver != u32::MAX {
                            row.push(receiver);
                        }
                    }
                }
            }
            row
        })
        .collect();
    let mut visible = vec![false; atlas.receivers.len()];
    for receiver in seen.into_iter().flatten() {
        visible[receiver as usize] = true;
    }
    visible
}

/// Pixels whose centre ray meets the back of a triangle: the lightmap
/// holds front sides, so techniques answer these through
/// `indirect_irradiance_in_space`, a path of its own worth measuring apart.
pub fn back_facing_pixels(context: &SceneContext) -> Vec<bool> {
    let camera = CameraRays::new(&context.scene.camera);
    let mesh = &context.scene.mesh;
    (0..camera.height * camera.width)
        .into_par_iter()
        .map(|pixel| {
            let ray = camera.ray(
                pixel % camera.width,
                pixel / camera.width,
                glam::Vec2::splat(0.5),
            );
            visible_hit(context, &ray).is_some_and(|hit| {
                mesh.geometric_normal(hit.triangle as usize)
                    .dot(ray.direction)
                    >= 0.0
            })
        })
        .collect()
}

/// What kind of place a receiver stands in, for splitting a technique's
/// error by cause.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub enum ReceiverClass {
    /// More than a quarter of its hemisphere's hits are back faces: its
    /// texel centre lies inside or under other geometry.
    Enclosed,
    /// Some hemisphere ray hits geometry within two texels: a concave
    /// corner or a contact, where interpolation across texels is hardest.
    Corner,
    /// Single-sided geometry: the ray straight behind it meets no back
    /// face, so its other side is open space that the lightmap does not
    /// hold (banners, thin walls, open meshes).
    Thin,
    /// Most of its hemisphere escapes the scene: roofs, outer walls.
    Exterior,
    /// Everything else: the inside of rooms.
    Interior,
}

impl ReceiverClass {
    pub const ALL: [ReceiverClass; 5] = [
        ReceiverClass::Enclosed,
        ReceiverClass::Corner,
        ReceiverClass::Thin,
        ReceiverClass::Exterior,
        ReceiverClass::Interior,
    ];

    pub fn name(self) -> &'static str {
        match self {
            ReceiverClass::Enclosed => "enclosed",
            ReceiverClass::Corner => "corner",
            ReceiverClass::Thin => "thin",
            ReceiverClass::Exterior => "exterior",
            ReceiverClass::Interior => "interior",
        }
    }
}

/// Hemisphere rays per receiver for [`classify_receivers`]: stratified
/// 4x4, enough to tell a closed gap from open space.
const CLASSIFY_RAYS: u32 = 16;

/// The class of every receiver, from 16 stratified cosine-weighted rays
/// over its front hemisphere and one ray straight behind it.
pub fn classify_receivers(context: &SceneContext) -> Vec<ReceiverClass> {
    let receivers = &context.atlas.receivers;
    let mesh = &context.scene.mesh;
    let bvh = &context.bvh;
    let epsilon = 1e-4 * mesh.bounds().1.distance(mesh.bounds().0).max(1e-3);
    let corner_distance = 2.0 * context.atlas.metres_per_texel;
    (0..receivers.len())
        .into_par_iter()
        .map(|index| {
            let position = receivers.positions[index];
            let normal = receivers.normals[index];
            let mut rng = relight_core::sampling::SampleStream::new(0x5eed, index as u64, 0);
            let (mut hits, mut back_hits, mut escapes, mut nearest) = (0, 0, 0, f32::INFINITY);
            for sample in 0..CLASSIFY_RAYS {
                let square = stratified_square(sample, CLASSIFY_RAYS, glam::Vec2::ZERO, &mut rng);
                let direction = cosine_hemisphere_around(normal, square);
                let ray = Ray {
                    origin: position + normal * epsilon,
                    direction,
                    t_max: f32::INFINITY,
                };
                match bvh.intersect(&ray) {
                    Some(hit) => {
                        hits += 1;
                        nearest = nearest.min(hit.t);
                        if mesh.geometric_normal(hit.triangle as usize).dot(direction) > 0.0 {
                            back_hits += 1;
                        }
                    }
                    None => escapes += 1,
                }
            }
            let behind = Ray {
                origin: position - normal * epsilon,
                direction: -normal,
                t_max: f32::INFINITY,
            };
            let closed_behind = bvh
                .intersect(&behind)
                .is_some_and(|hit| mesh.geometric_normal(hit.triangle as usize).dot(-normal) > 0.0);
            if back_hits * 4 > hits {
                ReceiverClass::Enclosed
            } else if nearest < corner_distance {
                ReceiverClass::Corner
            } else if !closed_behind {
                ReceiverClass::Thin
            } else if escapes * 2 > CLASSIFY_RAYS {
                ReceiverClass::Exterior
            } else {
                ReceiverClass::Interior
            }
        })
        .collect()
}

/// How a scene's receivers and pixels divide for a study, computed once:
/// which receivers the camera sees, each receiver's class, and which
/// pixels see back faces.
#[derive(Clone, Debug, PartialEq)]
pub struct Split {
    pub visible: Vec<bool>,
    pub classes: Vec<ReceiverClass>,
    pub back_facing: Vec<bool>,
    pub space: SpacePoints,
}

impl Split {
    pub fn of(context: &SceneContext) -> Self {
        Self {
            visible: visible_receivers(context),
            classes: classify_receivers(context),
            back_facing: back_facing_pixels(context),
            space: SpacePoints::of(context),
        }
    }
}

/// One class's part of a lightmap error.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ClassError {
    pub class: ReceiverClass,
    pub receivers: usize,
    /// Of those, how many the camera sees.
    pub visible: usize,
    /// This class's share of the whole lightmap's squared error.
    pub share: f64,
    /// relRMSE within the class.
    pub relative_rmse: f64,
    /// Total light against the reference's within the class.
    pub light_ratio: f64,
}

/// A technique's indirect light against a [`ReferenceSet`].
#[derive(Clone, Debug, PartialEq)]
pub struct Measurement {
    pub lightmap: f64,
    pub visible_lightmap: f64,
    pub image: f64,
    pub image_tiles: f64,
    /// Total indirect light in the camera image against the reference's.
    pub light_ratio: f64,
    pub classes: Vec<ClassError>,
    /// Pixels that see back faces: how many, their share of the image's
    /// squared error, their relRMSE and light ratio.
    pub back_facing: SubsetError,
    /// `indirect_irradiance_in_space` at the [`SpacePoints`]: relRMSE and
    /// total light against the path tracer's.
    pub space: f64,
    pub space_light_ratio: f64,
}

impl Measurement {
    /// Renders `technique` (already updated under the scene's lights) with
    /// `spp` primary rays per pixel and measures it.
    pub fn of(
        context: &SceneContext,
        technique: &dyn Technique,
        reference: &ReferenceSet,
        split: &Split,
        spp: u32,
        progress: &dyn Progress,
    ) -> (Self, Image) {
        let (visible, classes, back_facing) = (&split.visible, &split.classes, &split.back_facing);
        let renders =
            render_with_technique(context, &context.scene.lights, technique, spp, 1, progress);
        let image = renders.indirect;
        let space: Vec<Rgb> = split
            .space
            .positions
            .par_iter()
            .zip(&split.space.normals)
            .map(|(&position, &normal)| technique.indirect_irradiance_in_space(position, normal))
            .collect();
        let receivers = technique
            .receiver_irradiance()
            .filter(|values| values.len() == reference.lightmap.len());
        let (lightmap, visible_lightmap, classes) = match receivers {
            Some(values) => {
                let truth = &reference.lightmap;
                let split = ReceiverClass::ALL
                    .iter()
                    .map(|&class| {
                        let part = subset_error(values, truth, |i| classes[i] == class);
                        ClassError {
                            class,
                            receivers: part.count,
                            visible: (0..values.len())
                                .filter(|&i| classes[i] == class && visible[i])
                                .count(),
                            share: part.share,
                            relative_rmse: part.relative_rmse,
                            light_ratio: part.light_ratio,
                        }
                    })
                    .collect();
                (
                    error_norms(values, truth).relative_rmse,
                    subset_error(values, truth, |i| visible[i]).relative_rmse,
                    split,
                )
            }
            None => (f64::NAN, f64::NAN, Vec::new()),
        };
        let measurement = Self {
            lightmap,
            visible_lightmap,
            image: error_norms(&image.pixels, &reference.image.pixels).relative_rmse,
            image_tiles: error_norms(
                &tile_means(&image, TILE),
                &tile_means(&reference.image, TILE),
            )
            .relative_rmse,
            light_ratio: light_ratio(&image.pixels, &reference.image.pixels),
            classes,
            space: error_norms(&space, &reference.space).relative_rmse,
            space_light_ratio: light_ratio(&space, &reference.space),
            back_facing: subset_error(&image.pixels, &reference.image.pixels, |i| back_facing[i]),
        };
        (measurement, image)
    }
}

/// The environment variable naming a folder where
/// [`measure_against_path_tracer`] keeps its references for later
/// processes. CI points it at a folder made for its one run, so the test
/// binaries of several techniques that measure the same shipped scenes
/// trace each reference once. Unset, nothing outlives the process: a
/// folder kept longer would outlive the path tracer code that filled it.
pub const TEST_REFERENCE_FOLDER: &str = "RELIGHT_TEST_REFERENCES";

/// `technique`, already updated under the scene's lights, against the path
/// tracer with as many bounces as it computes (`samples` paths per receiver
/// and point in space, `spp` per pixel): the measurement a convergence study
/// makes of one setting, and the reference's own noise. Each reference is
/// traced once per process (and kept in [`TEST_REFERENCE_FOLDER`] where
/// that is set): tests measure several techniques or settings against it.
pub fn measure_against_path_tracer(
    context: &SceneContext,
    technique: &dyn Technique,
    samples: u32,
    spp: u32,
) -> (Measurement, Noise) {
    let (measurement, noise, _, _) =
        measure_and_render_against_path_tracer(context, technique, samples, spp);
    (measurement, noise)
}

/// [`measure_against_path_tracer`], with the technique's camera image and
/// the reference it was measured against, for figures of parts of the
/// image (the tiles around objects' feet).
pub fn measure_and_render_against_path_tracer(
    context: &SceneContext,
    technique: &dyn Technique,
    samples: u32,
    spp: u32,
) -> (Measurement, Noise, Image, std::sync::Arc<ReferenceSet>) {
    static REFERENCES: relight_technique::robustness::OncePerProcess<u64, ReferenceSet> =
        relight_technique::robustness::OncePerProcess::new();
    let split = Split::of(context);
    let settings = PathSettings {
        max_bounces: technique.reference_bounces(PathSettings::default().max_bounces),
        ..PathSettings::default()
    };
    let progress = relight_technique::NoProgress;
    let key = ReferenceSet::key(context, settings, samples, spp);
    let reference = REFERENCES.get_or_compute(key, || {
        let folder = std::env::var_os(TEST_REFERENCE_FOLDER).map(std::path::PathBuf::from);
        ReferenceSet::cached(
            context,
            &split.space,
            settings,
            samples,
            spp,
            folder.as_deref(),
            &progress,
        )
    });
    let (measurement, image) =
        Measurement::of(context, technique, &reference, &split, 4, &progress);
    let noise = reference.noise(&split.visible);
    (measurement, noise, image, reference)
}

/// The shipped closed scenes the tightest bounds apply to, relative
/// to the repository's `scenes/` folder: the Cornell box with its area
/// light, with a point light under the ceiling, 0.1 m from a wall and 0.1 m
/// from a corner, and the corridor.
pub const CLOSED_BOXES: [&str; 5] = [
    "cornell-box/scene.toml",
    "cornell-box-point/scene.toml",
    "cornell-box-point/scene-wall-light.toml",
    "cornell-box-point/scene-corner-light.toml",
    "corridor/scene.toml",
];

/// The context of a shipped scene (`scenes/` + `relative`) at its own
/// lightmap density, its camera's image shrunk by `shrink` on each side:
/// for tests, which need the references' noise low at a test's cost.
pub fn shipped_context(relative: &str, shrink: u32) -> std::sync::Arc<SceneContext> {
    let path = Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("../../scenes")
        .join(relative);
    let mut scene = relight_scene::load_scene(&path)
        .unwrap_or_else(|error| panic!("{}: {error}", path.display()));
    shrink_camera(&mut scene, shrink);
    let settings = relight_technique::ContextSettings {
        lightmap: relight_scene::atlas::TexelDensity::from_resolution(None),
        ..relight_technique::ContextSettings::default()
    };
    std::sync::Arc::new(SceneContext::new(scene, settings).expect("the scene's lightmap builds"))
}

/// Divides the camera image's sides by `shrink` (at least 1 pixel, a
/// `shrink` of 0 taken as 1): cheaper references for tests and studies.
pub fn shrink_camera(scene: &mut relight_scene::Scene, shrink: u32) {
    let [width, height] = scene.camera.resolution;
    let shrink = shrink.max(1);
    scene.camera.resolution = [(width / shrink).max(1), (height / shrink).max(1)];
}

/// relRMSE of `technique.indirect_irradiance_in_space` at the
/// [`SpacePoints`] of `context`, against the path tracer with as many
/// bounces as the technique computes and `samples` paths a point.
pub fn space_error(context: &SceneContext, technique: &dyn Technique, samples: u32) -> f64 {
    let points = SpacePoints::of(context);
    let settings = PathSettings {
        max_bounces: technique.reference_bounces(PathSettings::default().max_bounces),
        ..PathSettings::default()
    };
    let reference = reference_irradiance_at(
        context,
        &context.scene.lights,
        settings,
        samples,
        &points.positions,
        &points.normals,
        &relight_technique::NoProgress,
    );
    let values: Vec<Rgb> = points
        .positions
        .iter()
        .zip(&points.normals)
        .map(|(&position, &normal)| technique.indirect_irradiance_in_space(position, normal))
        .collect();
    error_norms(&values, &reference.mean).relative_rmse
}

/// The shipped scene `relative` at half its camera's resolution, with the
/// technique `make` returns for it (updated under the scene's lights),
/// measured by [`measure_against_path_tracer`] at 256 paths: what the
/// techniques' tests hold to the bounds. Prints the 8x8-tile error
/// and the light ratio, and fails when the reference's own tile noise
/// exceeds 3 %, where it would blur the bound.
pub fn half_size_measurement(
    relative: &str,
    make: impl FnOnce(&std::sync::Arc<SceneContext>) -> Box<dyn Technique>,
) -> Measurement {
    let context = shipped_context(relative, 2);
    let technique = make(&context);
    let (measured, noise) = measure_against_path_tracer(&context, technique.as_ref(), 256, 256);
    println!(
        "{relative}: image 8x8 tiles {:.1} % (reference noise {:.1} %), light ratio {:.3}",
        measured.image_tiles * 100.0,
        noise.image_tiles * 100.0,
        measured.light_ratio
    );
    assert!(
        noise.image_tiles < 0.03,
        "{relative}: {}",
        noise.image_tiles
    );
    measured
}

/// Each of [`CLOSED_BOXES`] measured by [`half_size_measurement`], with the
/// technique `make` returns for it.
pub fn closed_box_measurements(
    make: impl Fn(&std::sync::Arc<SceneContext>, &str) -> Box<dyn Technique>,
) -> Vec<(&'static str, Measurement)> {
    CLOSED_BOXES
        .iter()
        .map(|&scene| {
            let measured = half_size_measurement(scene, |context| make(context, scene));
            (scene, measured)
        })
        .collect()
}

/// The shipped view from inside two-rooms' unlit room, which sees the lit
/// room only through the doorway: nearly all its light has bounced at
/// least twice, so it is where a technique's lost or leaked multi-bounce
/// light shows.
pub const UNLIT_ROOM_VIEW: &str = "two-rooms/scene-unlit-room.toml";

/// [`UNLIT_ROOM_VIEW`] measured by [`half_size_measurement`]: what the
/// techniques' tests hold to the 0.85-1.15x of the path tracer's
/// light in view.
pub fn unlit_room_measurement(
    make: impl FnOnce(&std::sync::Arc<SceneContext>) -> Box<dyn Technique>,
) -> Measurement {
    half_size_measurement(UNLIT_ROOM_VIEW, make)
}
