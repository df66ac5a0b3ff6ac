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
use crate::metrics::{subset_error, tile_means};
use glam::Vec3;
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
}

impl ContactError {
    pub fn of(image: &Image, reference: &Image, contact_tiles: &[bool]) -> Self {
        let values = tile_means(image, TILE);
        let truth = tile_means(reference, TILE);
        if values.len() != contact_tiles.len() || !contact_tiles.iter().any(|&near| near) {
            return Self {
                tiles: 0,
                relative_rmse: f64::NAN,
                light_ratio: f64::NAN,
            };
        }
        let part = subset_error(&values, &truth, |i| contact_tiles[i]);
        Self {
            tiles: part.count,
            relative_rmse: part.relative_rmse,
            light_ratio: part.light_ratio,
        }
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
    fn bounds_follow_the_kind() {
        assert_eq!(bound("pic", VariantKind::Room), Some(0.08));
        assert_eq!(bound("lightskin", VariantKind::Hall), Some(0.25));
        assert_eq!(bound("direct", VariantKind::Room), None);
    }
}
