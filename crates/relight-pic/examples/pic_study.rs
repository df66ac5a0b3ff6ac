//! PIC parameter study: one path-traced reference lightmap (cached on disk),
//! then for each parameter set the lightmap relRMSE of PIC, its bake time
//! and the ratio of its mean luminance to the reference's (bias).
//!
//! Run: `cargo run --release -p relight-pic --example pic_study -- SCENE.toml
//! RESOLUTION REFERENCE_SAMPLES "preset=moderate" "preset=high" ...`
//! (RESOLUTION 0 = the automatic lightmap size). `RELIGHT_STUDY_WORST=N`
//! adds the N worst receivers and the error at relocated receivers.

use relight_core::{luminance, Rgb};
use relight_pic::{PicKind, BAKE_PARAMETERS};
use relight_render::study::{print_receiver, run_study};
use relight_technique::SceneContext;

fn detail(context: &SceneContext, _bake: &[u8], values: &[Rgb], reference: &[Rgb]) {
    let sum = |values: &[Rgb]| values.iter().map(|v| luminance(*v) as f64).sum::<f64>();
    println!(
        "    mean luminance ratio {:.3}",
        sum(values) / sum(reference).max(1e-30)
    );
    // PIC_NEAR="x,y,z,radius" lists the receivers within radius of a point.
    if let Ok(near) = std::env::var("PIC_NEAR") {
        let numbers: Vec<f32> = near.split(',').filter_map(|v| v.parse().ok()).collect();
        if let [x, y, z, radius] = numbers[..] {
            let centre = glam::Vec3::new(x, y, z);
            let receivers = &context.atlas.receivers;
            let mut list: Vec<usize> = (0..values.len())
                .filter(|&i| receivers.positions[i].distance(centre) < radius)
                .collect();
            list.sort_by(|&a, &b| {
                let (pa, pb) = (receivers.positions[a], receivers.positions[b]);
                (pa.y, pa.x, pa.z).partial_cmp(&(pb.y, pb.x, pb.z)).unwrap()
            });
            for i in list {
                print_receiver(context, i, values, reference);
            }
        }
    }
}

fn main() {
    run_study(&PicKind, &BAKE_PARAMETERS, &detail);
}
