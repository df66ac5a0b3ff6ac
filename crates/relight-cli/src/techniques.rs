//! The one table of techniques the CLI knows. Adding a technique is one
//! line here (and a dependency on its crate).

use relight_technique::{DirectKind, ReferenceKind, TechniqueKind};

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

pub fn find(name: &str) -> anyhow::Result<&'static dyn TechniqueKind> {
    kinds()
        .iter()
        .copied()
        .find(|kind| kind.name() == name)
        .ok_or_else(|| {
            let known: Vec<&str> = kinds().iter().map(|kind| kind.name()).collect();
            anyhow::anyhow!(
                "unknown technique '{name}'; available: {}",
                known.join(", ")
            )
        })
}
