//! The procedural atrium: triangle budgets are met, output is deterministic,
//! and the files load like any hand-made scene.

mod common;

use common::TempDir;
use relight_scene::generate::{atrium, write_atrium};
use relight_scene::{load_scene, Light, SceneError};

fn assert_within_budget(target: usize) -> relight_scene::generate::Atrium {
    let generated = atrium(target, 3).unwrap();
    let faces = generated
        .obj
        .lines()
        .filter(|line| line.starts_with("f "))
        .count();
    assert_eq!(faces * 2, generated.triangle_count, "every face is a quad");
    let ratio = generated.triangle_count as f64 / target as f64;
    assert!(
        (0.8..=1.2).contains(&ratio),
        "{target}: got {} triangles",
        generated.triangle_count
    );
    generated
}

#[test]
fn atrium_10k_loads_with_the_promised_count() {
    let dir = TempDir::new("atrium");
    let path = write_atrium(&dir.path, 10_000).unwrap();
    let scene = load_scene(&path).unwrap();
    assert!(scene.warnings.is_empty(), "{:?}", scene.warnings);
    let ratio = scene.mesh.triangles.len() as f64 / 10_000.0;
    assert!(
        (0.8..=1.2).contains(&ratio),
        "{} triangles",
        scene.mesh.triangles.len()
    );
    assert!(scene
        .lights
        .iter()
        .any(|light| matches!(light, Light::Directional { .. })));
    assert!(scene
        .lights
        .iter()
        .any(|light| matches!(light, Light::Point { .. })));
    assert!(scene.emissive_triangles().is_empty());
    let banners = scene
        .materials
        .iter()
        .filter(|material| material.name.starts_with("banner"))
        .count();
    assert_eq!(banners, 3);
    // Open roof: nothing above the courtyard centre.
    let (low, high) = scene.mesh.bounds();
    assert!(low.y >= -1e-3 && high.y <= 16.5, "{low} {high}");
    assert!(scene.environment.radiance.max_element() > 0.0);
}

#[test]
fn atrium_budgets_from_10k_to_1m() {
    for target in [10_000, 35_000, 100_000, 400_000] {
        assert_within_budget(target);
    }
}

#[test]
fn atrium_1m() {
    assert_within_budget(1_000_000);
}

#[test]
fn atrium_2m() {
    // About 100 MB of OBJ text; still about a second at opt-level 3.
    assert_within_budget(2_000_000);
}

#[test]
fn atrium_is_deterministic() {
    let first = atrium(20_000, 11).unwrap();
    let second = atrium(20_000, 11).unwrap();
    assert_eq!(first.obj, second.obj);
    assert_eq!(first.mtl, second.mtl);
    assert_eq!(first.scene_toml, second.scene_toml);
    let other = atrium(20_000, 12).unwrap();
    assert_ne!(
        first.obj, other.obj,
        "the seed changes banner colours and ripples"
    );
}

#[test]
fn atrium_rejects_absurd_budgets() {
    assert!(matches!(
        atrium(10, 0),
        Err(SceneError::InvalidArgument { .. })
    ));
    assert!(matches!(
        atrium(usize::MAX, 0),
        Err(SceneError::InvalidArgument { .. })
    ));
}
