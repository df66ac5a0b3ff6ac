//! Renders a relight scene's camera through Bevy without a window, with
//! relight's GI in Bevy's lightmap: EXR (linear, no tone mapping) or PNG.
//!
//! cargo run --release -p relight-bevy --example snapshot -- SCENE.toml \
//!     --technique T [--bake F] [--indirect-only] [--adopt] [--frames N] -o OUT.exr

use clap::Parser;
use relight_bevy::snapshot::{render_snapshot, SnapshotSettings};
use relight_bevy::RelightScene;
use std::path::PathBuf;
use std::process::ExitCode;
use std::time::Duration;

#[derive(Parser)]
struct Args {
    /// A scene file (TOML) or a mesh file (OBJ, glTF).
    scene: PathBuf,
    #[arg(long, short, default_value = "lightskin")]
    technique: String,
    #[arg(long)]
    bake: Option<PathBuf>,
    /// Technique parameter, repeatable: --set key=value.
    #[arg(long = "set", value_name = "KEY=VALUE")]
    set: Vec<String>,
    /// Bevy draws no direct light and the lightmap holds indirect light
    /// only: the image to compare with `relight render --indirect-only`.
    #[arg(long)]
    indirect_only: bool,
    /// Bevy loads the scene's glTF itself and relight adopts it
    /// (`RelightScene::adopt_gltf`) instead of spawning its own copy.
    #[arg(long)]
    adopt: bool,
    /// GI updates before the picture.
    #[arg(long, default_value_t = 5)]
    frames: u64,
    #[arg(short, long)]
    output: PathBuf,
}

fn main() -> ExitCode {
    let args = Args::parse();
    let mut scene = RelightScene::new(&args.scene).technique(&args.technique);
    scene.bake = args.bake.clone();
    scene.indirect_only = args.indirect_only;
    scene.adopt = args.adopt;
    for pair in &args.set {
        let Some((key, value)) = pair.split_once('=') else {
            eprintln!("error: --set {pair}: expected KEY=VALUE");
            return ExitCode::from(2);
        };
        scene = scene.set(key.trim(), value.trim());
    }
    let settings = SnapshotSettings {
        scene,
        gi_updates: args.frames.max(1),
        size: None,
        timeout: Duration::from_secs(1800),
    };
    let snapshot = match render_snapshot(&settings) {
        Ok(snapshot) => snapshot,
        Err(message) => {
            eprintln!("error: {message}");
            return ExitCode::FAILURE;
        }
    };
    let image = relight_render::Image {
        width: snapshot.width,
        height: snapshot.height,
        pixels: snapshot
            .pixels
            .iter()
            .map(|pixel| relight_core::Vec3::from_array(*pixel))
            .collect(),
    };
    if let Err(error) = image.write(&args.output, None) {
        eprintln!("error: {error}");
        return ExitCode::FAILURE;
    }
    eprintln!("wrote {}", args.output.display());
    ExitCode::SUCCESS
}
