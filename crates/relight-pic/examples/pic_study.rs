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

fn detail(context: &SceneContext, _bake: &[u8], values: &[Rgb], reference: &[Rgb]) {
    let sum = |values: &[Rgb]| values.iter().map(|v| luminance(*v) as f64).sum::<f64>();
    println!(
        "    mean luminance ratio {:.3}",
        sum(values) / sum(reference).max(1e-30)
    );
    if std::env::var_os("PIC_WORST").is_some() {
        let mut order: Vec<usize> = (0..values.len()).collect();
        let error = |i: usize| (luminance(values[i]) - luminance(reference[i])).powi(2);
        order.sort_by(|&a, &b| error(b).total_cmp(&error(a)));
        let receivers = &context.atlas.receivers;
        let dark: Vec<usize> = (0..values.len())
            .filter(|&i| {
                luminance(reference[i]) < 1e-4 * sum(reference) as f32 / values.len() as f32
            })
            .collect();
        let lit: Vec<usize> = (0..values.len()).filter(|i| !dark.contains(i)).collect();
        let pick = |list: &[usize], v: &[Rgb]| list.iter().map(|&i| v[i]).collect::<Vec<_>>();
        println!(
            "    {} receivers dark in the reference; relRMSE over the rest {:.2} %",
            dark.len(),
            relight_render::metrics::error_norms(&pick(&lit, values), &pick(&lit, reference))
                .relative_rmse
                * 100.0
        );
        for &i in order.iter().take(12) {
            println!(
                "    {:>6} at {:?} normal {:?}: {:.4} vs {:.4}",
                i,
                receivers.positions[i],
                receivers.normals[i],
                luminance(values[i]),
                luminance(reference[i])
            );
        }
    }
}

fn main() {
    run_study(&PicKind, &BAKE_PARAMETERS, &detail);
}
