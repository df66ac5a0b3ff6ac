//! PRM parameter study: one path-traced reference lightmap (cached on disk,
//! since it costs far more than the bakes), then the lightmap relRMSE of
//! PRM for each parameter set given on the command line.
//!
//! Run: `cargo run --release -p relight-prm --example prm_study -- SCENE.toml
//! RESOLUTION REFERENCE_SAMPLES "clusters=256,top_k=0" "top_k=32" ...`
//! (RESOLUTION 0 = the automatic lightmap size).

use relight_prm::{PrmBake, PrmKind, BAKE_PARAMETERS};
use relight_render::study::run_study;

fn main() {
    run_study(&PrmKind, &BAKE_PARAMETERS, &|_, bake, _, _| {
        let decoded = PrmBake::decode(bake).expect("decode");
        let sizes = decoded.cluster_sizes();
        println!(
            "    captured energy {:.6}, empty clusters {}, largest cluster {}",
            decoded.captured_energy,
            sizes.iter().filter(|&&size| size == 0).count(),
            sizes.iter().max().unwrap()
        );
    });
}
