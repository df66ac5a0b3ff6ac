//! The bridge's test: Bevy's render of the shipped Cornell boxes, lit by
//! relight's lightmap, against relight's own render of the same camera.
//! It pins the units, the UV channel and the lightmap's orientation.
//! Needs a Vulkan device; CI installs Mesa's software one (lavapipe).
//!
//! Bounds (the issue's): indirect-only images agree within 5 % in total
//! light and 10 % relative RMSE over 8x8-pixel tile means; full images
//! (Bevy's shadow-mapped direct light plus relight's indirect) within 15 %
//! over tiles. Tiles, because the two renderers sample pixels differently
//! (MSAA against jittered rays) and Bevy's lightmap is bilinear in texels
//! where relight's renderer asks the technique at every point.

use relight_bevy::snapshot::{render_snapshot, Snapshot, SnapshotSettings};
use relight_bevy::RelightScene;
use relight_core::Rgb;
use relight_render::metrics::{error_norms, light_ratio, tile_means};
use relight_render::Image;
use relight_technique::{
    parameters_fingerprint, write_bake_atomic, BakeHeader, ContextSettings, Frame, NoProgress,
    SceneContext,
};
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::time::Duration;

fn shipped(name: &str) -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("../../scenes")
        .join(name)
        .join("scene.toml")
}

fn image_of(snapshot: &Snapshot) -> Image {
    Image {
        width: snapshot.width,
        height: snapshot.height,
        pixels: snapshot
            .pixels
            .iter()
            .map(|pixel| Rgb::from_array(*pixel))
            .collect(),
    }
}

/// The technique's bake of the scene as a file in `folder`, as `relight
/// bake` writes it (`None` for techniques without one), so that relight's
/// render and Bevy's load the same bake.
fn bake_file(context: &SceneContext, technique: &str, folder: &Path) -> Option<PathBuf> {
    let kind = relight_engine::techniques::find(technique).unwrap();
    if !kind.needs_bake() {
        return None;
    }
    let payload = kind.bake(context, &[], &NoProgress).unwrap();
    let header = BakeHeader {
        technique: technique.to_string(),
        payload_version: 1,
        scene_fingerprint: context.fingerprint(),
        parameters_fingerprint: parameters_fingerprint(kind, &context.scene, &[]),
        shard: None,
    };
    let path = folder.join(format!("{technique}.bake"));
    write_bake_atomic(&path, &header, &payload).unwrap();
    Some(path)
}

/// relight's own render of the scene camera after `frames` updates:
/// (full, indirect).
fn relight_render(
    context: &Arc<SceneContext>,
    technique: &str,
    bake: Option<&Path>,
    frames: u64,
) -> (Image, Image) {
    let mut instance =
        relight_engine::open_technique(context, technique, &[], bake, &NoProgress).unwrap();
    let lights = context.scene.lights.clone();
    for index in 0..frames {
        instance
            .update(&Frame {
                lights: &lights,
                index,
                camera: None,
            })
            .unwrap();
    }
    let renders = relight_render::render::render_with_technique(
        context,
        &lights,
        instance.as_ref(),
        16,
        1,
        &NoProgress,
    );
    (renders.full, renders.indirect)
}

struct Agreement {
    total: f64,
    tiles: f64,
}

fn agreement(bevy: &Image, relight: &Image) -> Agreement {
    assert_eq!((bevy.width, bevy.height), (relight.width, relight.height));
    Agreement {
        total: light_ratio(&bevy.pixels, &relight.pixels),
        tiles: error_norms(&tile_means(bevy, 8), &tile_means(relight, 8)).relative_rmse,
    }
}

fn snapshot(
    path: &Path,
    technique: &str,
    bake: Option<&Path>,
    indirect_only: bool,
    frames: u64,
) -> Image {
    let mut scene = RelightScene::new(path).technique(technique);
    scene.bake = bake.map(Path::to_path_buf);
    scene.indirect_only = indirect_only;
    scene.volume_cells = 0;
    let settings = SnapshotSettings {
        scene,
        gi_updates: frames,
        size: None,
        timeout: Duration::from_secs(900),
    };
    image_of(&render_snapshot(&settings).expect("Bevy renders the scene"))
}

#[test]
fn bevy_shows_relights_light() {
    let mut failures = Vec::new();
    let folder = tempfile::tempdir().unwrap();
    for scene in ["cornell-box-point", "cornell-box"] {
        let path = shipped(scene);
        let context = Arc::new(
            SceneContext::new(
                relight_scene::load_scene(&path).unwrap(),
                ContextSettings::default(),
            )
            .unwrap(),
        );
        for technique in ["lightskin", "prm", "srp", "pic"] {
            // Several updates: SRP and PIC feed last frame's light back.
            let frames = 6;
            let bake = bake_file(&context, technique, folder.path());
            let (full, indirect) = relight_render(&context, technique, bake.as_deref(), frames);
            let bevy_indirect = snapshot(&path, technique, bake.as_deref(), true, frames);
            let bevy_full = snapshot(&path, technique, bake.as_deref(), false, frames);
            let indirect_agreement = agreement(&bevy_indirect, &indirect);
            let full_agreement = agreement(&bevy_full, &full);
            println!(
                "{scene} {technique}: indirect total {:.3}x, tiles {:.1} %; full total {:.3}x, tiles {:.1} %",
                indirect_agreement.total,
                100.0 * indirect_agreement.tiles,
                full_agreement.total,
                100.0 * full_agreement.tiles
            );
            if (indirect_agreement.total - 1.0).abs() > 0.05
                || indirect_agreement.tiles > 0.10
                || full_agreement.tiles > 0.15
            {
                failures.push(format!("{scene} {technique}"));
            }
            if let Ok(folder) = std::env::var("RELIGHT_SNAPSHOT_DIR") {
                let folder = PathBuf::from(folder);
                std::fs::create_dir_all(&folder).unwrap();
                for (name, image, same_as) in [
                    ("bevy-indirect", &bevy_indirect, &indirect),
                    ("relight-indirect", &indirect, &indirect),
                    ("bevy-full", &bevy_full, &full),
                    ("relight-full", &full, &full),
                ] {
                    let stem = folder.join(format!("{scene}-{technique}-{name}"));
                    image.write(&stem.with_extension("exr"), None).unwrap();
                    // PNGs of a pair share the relight image's exposure.
                    let exposure = same_as.auto_exposure();
                    image
                        .write(&stem.with_extension("png"), Some(exposure))
                        .unwrap();
                }
            }
        }
    }
    assert!(failures.is_empty(), "out of bounds: {failures:?}");
}
