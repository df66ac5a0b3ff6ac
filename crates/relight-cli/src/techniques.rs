//! The CLI's view of the technique table, which lives in
//! `relight_engine::techniques` so that the CLI and the Bevy plugin share
//! it: adding a technique is one line there.

pub use relight_engine::techniques::kinds;
use relight_technique::TechniqueKind;

pub fn find(name: &str) -> anyhow::Result<&'static dyn TechniqueKind> {
    Ok(relight_engine::techniques::find(name)?)
}
