//! The lightmap pipeline (atlas, conservative receivers, dilation, bilinear
//! lookup, back-face handling) must not change the answer: indirect light
//! stored per receiver by the path tracer and looked up per pixel has to
//! agree with per-pixel path tracing, within the two estimates' noise plus
//! the lightmap's interpolation error.

use relight_core::Rgb;
use relight_render::metrics::{error_norms, relative_noise};
use relight_render::render::{render_reference, render_with_technique};
use relight_scene::atlas::TexelDensity;
use relight_technique::{
    ContextSettings, Frame, NoProgress, ReferenceKind, SceneContext, TechniqueKind,
};
use relight_trace::path::PathSettings;
use std::path::Path;
use std::sync::Arc;

#[test]
fn path_traced_lightmap_matches_per_pixel_path_tracing() {
    let path =
        Path::new(env!("CARGO_MANIFEST_DIR")).join("../../scenes/cornell-box-point/scene.toml");
    let mut scene = relight_scene::load_scene(&path).expect("shipped scene loads");
    scene.camera.resolution = [96, 96];
    let settings = ContextSettings {
        lightmap: TexelDensity::TargetResolution(96),
        ..ContextSettings::default()
    };
    let context = Arc::new(SceneContext::new(scene, settings).unwrap());
    let lights = context.scene.lights.clone();

    let reference = render_reference(&context, &lights, PathSettings::default(), 256, &NoProgress);
    let pairs = [("samples".to_string(), "512".to_string())];
    let mut technique = ReferenceKind
        .create(context.clone(), None, &pairs, &NoProgress)
        .unwrap();
    technique
        .update(&Frame {
            lights: &lights,
            index: 0,
            camera: None,
            moving_mesh_poses: None,
        })
        .unwrap();
    let lightmapped =
        render_with_technique(&context, &lights, technique.as_ref(), 4, 1, &NoProgress);

    // Per-pixel noise at 256 paths is ~15 %, too much to see a real defect;
    // 8x8 block means cut it eightfold while keeping the spatial structure.
    let block = |image: &relight_render::Image, squared: bool| -> Vec<Rgb> {
        let blocks = image.width / 8;
        let mut out = vec![Rgb::ZERO; (blocks * blocks) as usize];
        for y in 0..image.height {
            for x in 0..image.width {
                let value = image.get(x, y);
                out[((y / 8) * blocks + x / 8) as usize] +=
                    if squared { value * value } else { value } / 64.0;
            }
        }
        out
    };
    let reference_blocks = block(&reference.indirect, false);
    // Standard error of a block mean: sqrt(sum of se^2) / 64 = sqrt(mean se^2 / 64).
    let block_errors: Vec<Rgb> = block(&reference.indirect_standard_error, true)
        .iter()
        .map(|mean_square| (*mean_square / 64.0).map(f32::sqrt))
        .collect();
    let image_noise = relative_noise(&reference_blocks, &block_errors);
    let error = error_norms(&block(&lightmapped.indirect, false), &reference_blocks).relative_rmse;
    eprintln!("block noise {image_noise:.4}, lightmap-vs-pixels relRMSE {error:.4}");
    // Independent noise adds in quadrature: the per-pixel reference's noise,
    // plus the lightmap's (512 paths per texel: at most the image's 256-path
    // noise per block), plus up to 5 % of genuine interpolation error at the
    // box's corners, where indirect irradiance changes within a texel.
    let bound = (2.0 * image_noise.powi(2) + 0.05f64.powi(2)).sqrt() * 1.25;
    assert!(
        error < bound,
        "lightmap disagrees with per-pixel path tracing: {error:.4} >= {bound:.4}"
    );
}
