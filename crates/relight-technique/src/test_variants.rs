//! Generated variants for this crate's unit tests.

use crate::{ContextSettings, SceneContext};

/// Variant `index` of the generated default family, written to a
/// temporary folder that lives as long as the returned guard.
pub(crate) fn default_variant(index: usize) -> (tempfile::TempDir, std::path::PathBuf) {
    seeded_variant(
        relight_scene::generate::variants::VARIANTS_DEFAULT_SEED,
        index,
    )
}

/// Variant `index` of the generated family of `seed`, as [`default_variant`].
pub(crate) fn seeded_variant(seed: u64, index: usize) -> (tempfile::TempDir, std::path::PathBuf) {
    let folder = tempfile::tempdir().expect("temporary folder");
    let path = relight_scene::generate::variants::variant(seed, index)
        .write(folder.path())
        .expect("variant written");
    (folder, path)
}

/// The context of [`default_variant`] `index` at the default settings.
pub(crate) fn default_variant_context(index: usize) -> SceneContext {
    variant_context(index, ContextSettings::default())
}

/// The context of [`default_variant`] `index` at `settings`.
pub(crate) fn variant_context(index: usize, settings: ContextSettings) -> SceneContext {
    let (_folder, path) = default_variant(index);
    let scene = relight_scene::load_scene(&path).expect("variant loads");
    SceneContext::new(scene, settings).expect("context")
}
