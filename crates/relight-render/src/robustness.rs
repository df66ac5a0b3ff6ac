//! Robustness over generated variants: a technique measured on scenes
//! modelled the many ways real buildings are (see
//! [`relight_scene::generate::variants`]), not only on the scenes it was
//! tuned on, and the image tiles around objects' feet, where contact halos
//! show.
//!
//! Data flow: [`VariantCase::load`] writes a variant's files, loads them
//! like any scene and finds the tiles around its objects' feet
//! ([`contact_tiles`]); the caller bakes and updates a technique on its
//! context and measures it with [`crate::convergence::Measurement::of`];
//! [`ContactError::of`] adds the feet's tiles, and [`bound`] says what a
//! variant of each kind is held to.

use crate::convergence::{shrink_camera, Measurement, Noise, TILE};
use crate::image::Image;
use crate::metrics::{kept, relative_noise, subset_error, tile_means};
use glam::Vec3;
use relight_core::Rgb;
use relight_scene::generate::variants::{Foot, Variant, VariantKind};
use relight_scene::SceneError;
use relight_technique::{ContextSettings, SceneContext, Technique};
use relight_trace::bvh::Ray;
use relight_trace::path::CameraRays;
use std::path::Path;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::Arc;

/// How `relight robustness` measures a variant by default (its
/// `--shrink`): the camera halved on each side.
pub const STUDY_SHRINK: u32 = 2;

/// The reference's paths per pixel, receiver and point in space that
/// `relight robustness` and `relight converge` default to.
pub const STUDY_PATHS: u32 = 256;

/// One generated variant, loaded.
pub struct VariantCase {
    pub variant: Variant,
    pub context: Arc<SceneContext>,
    /// Per 8x8 tile of the camera image (row-major): whether it shows floor
    /// within 15 cm of an object's foot.
    pub contact_tiles: Vec<bool>,
}

impl VariantCase {
    /// Writes `variant` into `folder` (`mesh.obj`, `mesh.mtl`,
    /// `scene.toml`), loads it with `settings` and its camera image shrunk
    /// by `shrink` on each side.
    pub fn load(
        variant: Variant,
        folder: &Path,
        shrink: u32,
        settings: ContextSettings,
    ) -> Result<Self, SceneError> {
        let scene_file = variant.write(folder)?;
        let mut scene = relight_scene::load_scene(&scene_file)?;
        shrink_camera(&mut scene, shrink);
        let context = Arc::new(SceneContext::new(scene, settings)?);
        let contact_tiles = contact_tiles(&context, &variant.feet, TILE);
        Ok(Self {
            variant,
            context,
            contact_tiles,
        })
    }

    /// [`Self::load`] through a folder of its own in the system's temporary
    /// folder, removed once the variant is loaded: the loader reads files,
    /// and a caller that keeps none needs no folder.
    pub fn load_temporary(
        variant: Variant,
        shrink: u32,
        settings: ContextSettings,
    ) -> Result<Self, SceneError> {
        // Tests load variants on several threads of one process.
        static NEXT: AtomicU64 = AtomicU64::new(0);
        let folder = std::env::temp_dir().join(format!(
            "relight-variant-{}-{}-{}",
            std::process::id(),
            NEXT.fetch_add(1, Ordering::Relaxed),
            variant.name()
        ));
        let loaded = Self::load(variant, &folder, shrink, settings);
        // Left behind, it costs only disk space.
        let _ = std::fs::remove_dir_all(&folder);
        loaded
    }

    /// Variant `index` of the generator's default family, loaded as the
    /// study loads it ([`STUDY_SHRINK`], default context settings): where a
    /// test that holds a technique to the study's figures starts.
    pub fn default_family(index: usize) -> Result<Self, SceneError> {
        let variant = relight_scene::generate::variants::variant(
            relight_scene::generate::variants::VARIANTS_DEFAULT_SEED,
            index,
        );
        Self::load_temporary(variant, STUDY_SHRINK, ContextSettings::default())
    }

    /// `technique`, already updated under the variant's lights, against
    /// the path tracer at [`STUDY_PATHS`], as the study measures it; prints
    /// the figures a test's bounds read.
    pub fn measure_as_the_study_does(&self, technique: &dyn Technique) -> (Measurement, Noise) {
        let (measured, noise) = crate::convergence::measure_against_path_tracer(
            &self.context,
            technique,
            STUDY_PATHS,
            STUDY_PATHS,
        );
        println!(
            "{}: 8x8 tiles {:.1} % (reference noise {:.1} %), light in view {:.3}x",
            self.variant.name(),
            measured.image_tiles * 100.0,
            noise.image_tiles * 100.0,
            measured.light_ratio
        );
        (measured, noise)
    }

    /// [`Self::measure_as_the_study_does`] and the technique's error on the
    /// tiles around the variant's objects' feet ([`ContactError`]).
    pub fn measure_contact_as_the_study_does(
        &self,
        technique: &dyn Technique,
    ) -> (Measurement, ContactError) {
        let (measured, _, image, reference) =
            crate::convergence::measure_and_render_against_path_tracer(
                &self.context,
                technique,
                STUDY_PATHS,
                STUDY_PATHS,
            );
        let contact = ContactError::of(
            &image,
            &reference.image,
            &reference.tile_standard_errors(),
            &self.contact_tiles,
        );
        println!(
            "{}: 8x8 tiles {:.1} %, contact tiles {:.1} % ({} tiles, reference noise {:.1} %), contact light {:.3}x",
            self.variant.name(),
            measured.image_tiles * 100.0,
            contact.relative_rmse * 100.0,
            contact.tiles,
            contact.reference_noise * 100.0,
            contact.light_ratio
        );
        (measured, contact)
    }
}

/// How far from a foot's edge the floor counts as its surroundings: a
/// halo larger than a texel (5-13 cm at the variants' default lightmaps)
/// shows within it.
pub const CONTACT_REACH: f32 = 0.15;

/// The tiles of the camera image (row-major, `tile` pixels a side) that see
/// floor within [`CONTACT_REACH`] of one of `feet`: points on rings around
/// each footprint, projected into the image, kept where the camera's ray
/// reaches them unblocked and lands on an upward floor.
pub fn contact_tiles(context: &SceneContext, feet: &[Foot], tile: u32) -> Vec<bool> {
    let camera = CameraRays::new(&context.scene.camera);
    let columns = camera.width.div_ceil(tile);
    let rows = camera.height.div_ceil(tile);
    let mut mask = vec![false; (columns * rows) as usize];
    const STEPS: usize = 24;
    for foot in feet {
        for reach in [0.01, 0.03, 0.06, 0.1, CONTACT_REACH] {
            let low = foot.low - reach;
            let high = foot.high + reach;
            for step in 0..STEPS {
                let t = (step as f32 + 0.5) / STEPS as f32;
                let along = low + (high - low) * t;
                for (x, z) in [
                    (along.x, low.y),
                    (along.x, high.y),
                    (low.x, along.y),
                    (high.x, along.y),
                ] {
                    let point = Vec3::new(x, foot.floor, z);
                    if !sees_floor_at(context, &camera, point) {
                        continue;
                    }
                    if let Some([px, py]) = camera.pixel_of(point) {
                        mask[((py / tile) * columns + px / tile) as usize] = true;
                    }
                }
            }
        }
    }
    mask
}

fn sees_floor_at(context: &SceneContext, camera: &CameraRays, point: Vec3) -> bool {
    let offset = point - camera.eye;
    let distance = offset.length();
    let ray = Ray {
        origin: camera.eye,
        direction: offset / distance,
        t_max: f32::INFINITY,
    };
    let Some(hit) = context.bvh.intersect(&ray) else {
        return false;
    };
    let normal = context.scene.mesh.geometric_normal(hit.triangle as usize);
    (hit.t - distance).abs() < 0.01 + 0.002 * distance && normal.y > 0.9
}

/// A technique's error on the tiles around objects' feet.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct ContactError {
    pub tiles: usize,
    /// relRMSE of those tiles' means against the reference's.
    pub relative_rmse: f64,
    /// Their light against the reference's: a dark halo is under 1.
    pub light_ratio: f64,
    /// The reference's own relative noise over those tile means: a perfect
    /// technique would still show about this much contact error. Feet are
    /// often small, far or in the dark, where a few tiles of a 256-path
    /// reference are mostly noise.
    pub reference_noise: f64,
}

/// The contact target: the tiles at objects' feet within this
/// factor of the whole image's tile error; over it is a halo.
pub const CONTACT_HALO: f64 = 1.5;

impl ContactError {
    /// `reference_tile_errors` are the standard errors of `reference`'s
    /// tile means ([`crate::convergence::ReferenceSet::tile_standard_errors`]).
    pub fn of(
        image: &Image,
        reference: &Image,
        reference_tile_errors: &[Rgb],
        contact_tiles: &[bool],
    ) -> Self {
        let values = tile_means(image, TILE);
        let truth = tile_means(reference, TILE);
        if values.len() != contact_tiles.len()
            || reference_tile_errors.len() != contact_tiles.len()
            || !contact_tiles.iter().any(|&near| near)
        {
            return Self {
                tiles: 0,
                relative_rmse: f64::NAN,
                light_ratio: f64::NAN,
                reference_noise: f64::NAN,
            };
        }
        let part = subset_error(&values, &truth, |i| contact_tiles[i]);
        Self {
            tiles: part.count,
            relative_rmse: part.relative_rmse,
            light_ratio: part.light_ratio,
            reference_noise: relative_noise(
                &kept(&truth, contact_tiles),
                &kept(reference_tile_errors, contact_tiles),
            ),
        }
    }

    /// Whether the reference is precise enough at the feet to tell a halo
    /// from its own noise: noise at most `resolving_share` of the halo
    /// threshold (`CONTACT_HALO` times `image_tiles`), as the study asks of
    /// a whole image against its bound.
    pub fn resolved(&self, image_tiles: f64, resolving_share: f64) -> bool {
        self.tiles > 0 && self.reference_noise <= CONTACT_HALO * image_tiles * resolving_share
    }

    /// Over the halo threshold.
    pub fn is_halo(&self, image_tiles: f64) -> bool {
        self.relative_rmse > CONTACT_HALO * image_tiles
    }
}

/// The 8x8-tile relRMSE a technique is held to on a kind of variant: the
/// closed boxes' bounds for rooms and two-room suites (PIC at `high` and
/// SRP 8 %, PRM and LightSkin 15 %), the real interiors' for halls (15, 15,
/// 20 and 25 %). `None` for a technique without a bound.
pub fn bound(technique: &str, kind: VariantKind) -> Option<f64> {
    let (closed, large) = match technique {
        "pic" | "srp" => (0.08, 0.15),
        "prm" => (0.15, 0.20),
        "lightskin" => (0.15, 0.25),
        _ => return None,
    };
    Some(if kind.is_large() { large } else { closed })
}

/// Light in view an unlit room is held to, against the path tracer's.
pub const UNLIT_LIGHT_RATIO: (f64, f64) = (0.85, 1.15);

/// Median, 90th percentile (nearest rank) and largest of `values`, NaNs
/// left out; `None` when none is left.
pub fn distribution(values: &[f64]) -> Option<(f64, f64, f64)> {
    let mut sorted: Vec<f64> = values.iter().copied().filter(|v| !v.is_nan()).collect();
    if sorted.is_empty() {
        return None;
    }
    sorted.sort_by(f64::total_cmp);
    let rank = |share: f64| {
        let index = ((share * sorted.len() as f64).ceil() as usize).clamp(1, sorted.len()) - 1;
        sorted[index]
    };
    Some((rank(0.5), rank(0.9), sorted[sorted.len() - 1]))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn distribution_uses_nearest_ranks_and_skips_nan() {
        let values: Vec<f64> = (1..=10).map(f64::from).chain([f64::NAN]).collect();
        assert_eq!(distribution(&values), Some((5.0, 9.0, 10.0)));
        assert_eq!(distribution(&[3.0]), Some((3.0, 3.0, 3.0)));
        assert_eq!(distribution(&[f64::NAN]), None);
    }

    #[test]
    fn contact_error_reads_the_reference_noise_of_its_tiles() {
        let flat = |value: f32| Image {
            width: 16,
            height: 8,
            pixels: vec![Rgb::splat(value); 128],
        };
        let mut image = flat(1.0);
        for y in 0..8 {
            for x in 0..8 {
                image.pixels[y * 16 + x] = Rgb::splat(1.2);
            }
        }
        // Each pixel's standard error 0.8 gives each 64-pixel tile mean
        // 0.8 / 8 = 0.1, a tenth of the reference's light.
        let reference = flat(1.0);
        let errors = vec![Rgb::splat(0.1); 2];
        let contact = ContactError::of(&image, &reference, &errors, &[true, false]);
        assert_eq!(contact.tiles, 1);
        assert!((contact.relative_rmse - 0.2).abs() < 1e-6);
        assert!((contact.light_ratio - 1.2).abs() < 1e-6);
        assert!((contact.reference_noise - 0.1).abs() < 1e-6);
        // Threshold 1.5 x 0.1 = 0.15: 0.2 is a halo; noise 0.1 resolves it
        // at half the threshold only when the image error is at least 0.134.
        assert!(contact.is_halo(0.1));
        assert!(!contact.resolved(0.1, 0.5));
        assert!(contact.resolved(0.14, 0.5));
        let none = ContactError::of(&image, &reference, &errors, &[false, false]);
        assert!(!none.resolved(0.1, 0.5) && none.relative_rmse.is_nan());
    }

    #[test]
    fn bounds_follow_the_kind() {
        assert_eq!(bound("pic", VariantKind::Room), Some(0.08));
        assert_eq!(bound("lightskin", VariantKind::Hall), Some(0.25));
        assert_eq!(bound("direct", VariantKind::Room), None);
    }
}
