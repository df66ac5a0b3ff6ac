//! The one table of techniques, shared by the CLI and the Bevy plugin:
//! adding a technique is one line here (and a dependency on its crate).
//! [`open_technique`] creates one from a bake file or bakes in memory.

use relight_technique::{
    parameters_fingerprint, read_bake, DirectKind, Progress, ReferenceKind, SceneContext,
    Technique, TechniqueError, TechniqueKind,
};
use std::path::{Path, PathBuf};
use std::sync::Arc;

pub fn kinds() -> &'static [&'static dyn TechniqueKind] {
    &[
        &DirectKind,
        &ReferenceKind,
        &relight_prm::PrmKind,
        &relight_lightskin::LightSkinKind,
        &relight_srp::SrpKind,
        &relight_pic::PicKind,
    ]
}

/// Why a technique could not be opened; each names what to change.
#[derive(Debug, thiserror::Error)]
pub enum OpenError {
    #[error("unknown technique '{name}'; available: {known}")]
    UnknownTechnique { name: String, known: String },
    #[error("{}: holds shard {shard} of a sharded bake: join all {count} shards with `relight merge PART... -o FILE` and pass that file", path.display())]
    Shard {
        path: PathBuf,
        shard: String,
        count: u32,
    },
    #[error("{}: this bake is for technique '{baked}', not '{wanted}'", path.display())]
    OtherTechnique {
        path: PathBuf,
        baked: String,
        wanted: String,
    },
    #[error("{}: this bake was made for another scene or lightmap resolution; bake again", path.display())]
    OtherScene { path: PathBuf },
    #[error("{}: technique '{technique}' needs no bake; drop the bake file", path.display())]
    NeedsNoBake {
        path: PathBuf,
        technique: &'static str,
    },
    #[error(transparent)]
    Technique(#[from] TechniqueError),
}

pub fn find(name: &str) -> Result<&'static dyn TechniqueKind, OpenError> {
    kinds()
        .iter()
        .copied()
        .find(|kind| kind.name() == name)
        .ok_or_else(|| OpenError::UnknownTechnique {
            name: name.to_string(),
            known: kinds()
                .iter()
                .map(|kind| kind.name())
                .collect::<Vec<_>>()
                .join(", "),
        })
}

/// Creates technique `name` for `context` with `params`, from the bake
/// file `bake` when given (checked to be this technique's, for this
/// scene), else baking in memory when the technique needs a bake.
/// A bake made with other bake parameters is used with a warning, since
/// run-time parameters may differ freely.
pub fn open_technique(
    context: &Arc<SceneContext>,
    name: &str,
    params: &[(String, String)],
    bake: Option<&Path>,
    progress: &dyn Progress,
) -> Result<Box<dyn Technique>, OpenError> {
    let kind = find(name)?;
    let payload = match (bake, kind.needs_bake()) {
        (Some(path), true) => {
            let (header, payload) = read_bake(path)?;
            if let Some(shard) = header.shard {
                return Err(OpenError::Shard {
                    path: path.to_path_buf(),
                    shard: shard.to_string(),
                    count: shard.count,
                });
            }
            if header.technique != kind.name() {
                return Err(OpenError::OtherTechnique {
                    path: path.to_path_buf(),
                    baked: header.technique,
                    wanted: kind.name().to_string(),
                });
            }
            if header.scene_fingerprint != context.fingerprint() {
                return Err(OpenError::OtherScene {
                    path: path.to_path_buf(),
                });
            }
            if header.parameters_fingerprint != parameters_fingerprint(kind, &context.scene, params)
            {
                tracing::warn!(
                    "{}: baked with other bake parameters ({}) than given; the bake's are used",
                    path.display(),
                    kind.bake_parameters().join(", ")
                );
            }
            Some(payload)
        }
        (None, true) => {
            tracing::info!("no bake given: baking {} in memory", kind.name());
            Some(kind.bake(context, params, progress)?)
        }
        (Some(path), false) => {
            return Err(OpenError::NeedsNoBake {
                path: path.to_path_buf(),
                technique: kind.name(),
            })
        }
        (None, false) => None,
    };
    Ok(kind.create(context.clone(), payload.as_deref(), params, progress)?)
}
