//! PIC parameter study: one path-traced reference lightmap (cached on disk),
//! then for each parameter set the lightmap relRMSE of PIC, its bake time
//! and the ratio of its mean luminance to the reference's (bias).
//!
//! Run: `cargo run --release -p relight-pic --example pic_study -- SCENE.toml
//! RESOLUTION REFERENCE_SAMPLES "preset=moderate" "preset=high" ...`
//! (RESOLUTION 0 = the automatic lightmap size).

use relight_core::{luminance, Rgb};
use relight_pic::{PicKind, BAKE_PARAMETERS};
use relight_render::study::run_study;
use relight_technique::SceneContext;

fn detail(_context: &SceneContext, _bake: &[u8], values: &[Rgb], reference: &[Rgb]) {
    let sum = |values: &[Rgb]| values.iter().map(|v| luminance(*v) as f64).sum::<f64>();
    println!(
        "    mean luminance ratio {:.3}",
        sum(values) / sum(reference).max(1e-30)
    );
}

fn main() {
    run_study(&PicKind, &BAKE_PARAMETERS, &detail);
}
