//! The generated variants are valid scenes for the path tracer and cover
//! the ways of modelling a building they promise.

use relight_render::robustness::VariantCase;
use relight_scene::generate::variants::{
    variant, Contact, LightPlace, Shell, Tessellation, VariantKind, Walls,
};
use relight_technique::ContextSettings;

/// Enough variants for every choice to appear (each is drawn with
/// probability 1/4 or more per variant, so 36 miss one with odds under
/// 0.75^12 per kind-restricted choice).
const COUNT: usize = 36;
const SEED: u64 = 39;

#[test]
fn variants_are_deterministic() {
    for index in [0, 1, 2, 17] {
        let (one, two) = (variant(SEED, index), variant(SEED, index));
        assert_eq!(one.obj, two.obj);
        assert_eq!(one.scene_toml, two.scene_toml);
        assert_eq!(one.mtl, two.mtl);
    }
    assert_ne!(variant(SEED, 0).obj, variant(SEED + 1, 0).obj);
}

#[test]
fn material_names_are_unique() {
    for index in 0..COUNT {
        let generated = variant(SEED, index);
        let mut names: Vec<&str> = generated
            .mtl
            .lines()
            .filter_map(|line| line.strip_prefix("newmtl "))
            .collect();
        let count = names.len();
        names.sort_unstable();
        names.dedup();
        assert_eq!(names.len(), count, "{}", generated.name());
    }
}

#[test]
fn variants_cover_every_modelling_choice() {
    let all: Vec<_> = (0..COUNT).map(|index| variant(SEED, index)).collect();
    for kind in VariantKind::ALL {
        assert!(all.iter().any(|v| v.kind == kind), "{kind:?}");
    }
    for walls in [Walls::Planes, Walls::Solids, Walls::Overlapping] {
        assert!(all.iter().any(|v| v.walls == walls), "{walls:?}");
    }
    for shell in [Shell::OneShell, Shell::BoxPerRoom] {
        assert!(
            all.iter()
                .any(|v| v.kind == VariantKind::TwoRooms && v.shell == shell),
            "{shell:?}"
        );
    }
    assert!(all.iter().any(|v| v.tessellation == Tessellation::Quads));
    assert!(all
        .iter()
        .any(|v| matches!(v.tessellation, Tessellation::Fine { .. })));
    let feet: Vec<_> = all.iter().flat_map(|v| v.feet.iter()).collect();
    assert!(feet.iter().any(|f| f.has_bottom) && feet.iter().any(|f| !f.has_bottom));
    assert!(feet.iter().any(|f| f.contact == Contact::Flush));
    assert!(feet.iter().any(|f| matches!(f.contact, Contact::Above(_))));
    assert!(feet.iter().any(|f| matches!(f.contact, Contact::Into(_))));
    let places: Vec<_> = all.iter().flat_map(|v| v.lights.iter()).collect();
    assert!(places.iter().any(|p| matches!(p, LightPlace::NearWall(_))));
    assert!(places.iter().any(|p| matches!(p, LightPlace::Corner(_))));
    assert!(places.iter().any(|p| matches!(p, LightPlace::Shaded(1))));
    assert!(places.iter().any(|p| matches!(p, LightPlace::Shaded(2))));
    assert!(places.iter().any(|p| matches!(p, LightPlace::Sun)));
    let albedos: Vec<f32> = all.iter().map(|v| v.albedo).collect();
    assert!(albedos.iter().any(|&a| a < 0.25) && albedos.iter().any(|&a| a > 0.75));
    let sizes: Vec<f32> = all.iter().map(|v| v.size).collect();
    assert!(sizes.iter().any(|&s| s < 4.0) && sizes.iter().any(|&s| s > 30.0));
}

/// Every light and the camera stand in open space (a point inside a solid
/// sees back faces), and the camera sees the floor around most feet.
#[test]
fn variants_load_with_lights_and_camera_in_open_space() {
    let folder = tempfile::tempdir().unwrap();
    let mut feet_seen = 0;
    let mut feet_total = 0;
    for index in 0..COUNT {
        let generated = variant(SEED, index);
        let name = generated.name();
        let case = VariantCase::load(
            generated,
            &folder.path().join(&name),
            4,
            ContextSettings::default(),
        )
        .unwrap_or_else(|error| panic!("{name}: {error}"));
        let context = &case.context;
        assert!(
            context.scene.warnings.is_empty(),
            "{name}: {:?}",
            context.scene.warnings
        );
        assert!(
            !context.is_inside_geometry(context.scene.camera.eye),
            "{name}: camera inside geometry"
        );
        for light in &context.scene.lights {
            if let Some(position) = light.position() {
                assert!(
                    !context.is_inside_geometry(position),
                    "{name}: light at {position} inside geometry"
                );
            }
        }
        if !case.variant.feet.is_empty() {
            feet_total += 1;
            feet_seen += usize::from(case.contact_tiles.iter().any(|&near| near));
        }
    }
    // Cameras aim at the first object; a few others hide behind it.
    assert!(
        feet_seen * 10 >= feet_total * 8,
        "{feet_seen} of {feet_total} variants show an object's foot"
    );
}
