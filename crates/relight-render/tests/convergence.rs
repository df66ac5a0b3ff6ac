//! The convergence study's parts: a cached reference is keyed on what
//! changes it, the camera's receivers are the ones it sees, and receiver
//! classes name the places they were made for.

use relight_render::convergence::{
    classify_receivers, visible_receivers, ReceiverClass, ReferenceSet,
};
use relight_scene::atlas::TexelDensity;
use relight_technique::{ContextSettings, SceneContext};
use relight_trace::path::PathSettings;
use std::path::Path;

fn context(name: &str, edit: impl FnOnce(&mut relight_scene::Scene)) -> SceneContext {
    let path = Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("../../scenes")
        .join(name);
    let mut scene = relight_scene::load_scene(&path).expect("shipped scene loads");
    edit(&mut scene);
    let settings = ContextSettings {
        lightmap: TexelDensity::TargetResolution(64),
        ..ContextSettings::default()
    };
    SceneContext::new(scene, settings).unwrap()
}

#[test]
fn reference_key_changes_with_lights_camera_and_path_settings() {
    let settings = PathSettings::default();
    let key = |context: &SceneContext| ReferenceSet::key(context, settings, 64, 16);
    let base = key(&context("cornell-box-point/scene.toml", |_| {}));
    assert_eq!(base, key(&context("cornell-box-point/scene.toml", |_| {})));
    let turned = context("cornell-box-point/scene.toml", |scene| {
        let turn = glam::Quat::from_rotation_y(0.1);
        scene.lights = scene
            .lights
            .iter()
            .map(|light| light.rotated_about(glam::Vec3::new(0.28, 0.0, 0.28), turn))
            .collect();
    });
    assert_ne!(base, key(&turned), "same geometry, other lights");
    let moved = context("cornell-box-point/scene.toml", |scene| {
        scene.camera.eye.x += 0.01;
    });
    assert_ne!(base, key(&moved), "same geometry, other camera");
    let point = context("cornell-box-point/scene.toml", |_| {});
    let one_bounce = PathSettings {
        max_bounces: 1,
        ..settings
    };
    assert_ne!(base, ReferenceSet::key(&point, one_bounce, 64, 16));
    assert_ne!(base, ReferenceSet::key(&point, settings, 128, 16));
}

#[test]
fn receiver_classes_and_visibility_in_two_rooms() {
    // Two closed rooms of 0.2 m walls seen from inside room B: the outside
    // of the building is exterior and unseen, the rooms' floor is interior
    // or corner, and the camera sees receivers of room B only.
    let context = context("two-rooms/scene-unlit-room.toml", |_| {});
    let classes = classify_receivers(&context);
    let visible = visible_receivers(&context);
    let receivers = &context.atlas.receivers;
    let mut outside_roof = 0;
    for index in 0..receivers.len() {
        let (position, normal) = (receivers.positions[index], receivers.normals[index]);
        if normal.y > 0.9
            && position.y > 2.6
            && (0.5..7.7).contains(&position.x)
            && (0.5..3.5).contains(&position.z)
        {
            outside_roof += 1;
            assert_eq!(
                classes[index],
                ReceiverClass::Exterior,
                "roof at {position}"
            );
            assert!(!visible[index], "the roof is not in view");
        }
        let mid_floor = normal.y > 0.9
            && position.y.abs() < 1e-3
            && (1.0..3.0).contains(&position.z)
            && ((1.0..3.0).contains(&position.x) || (5.2..7.2).contains(&position.x));
        if mid_floor {
            assert_eq!(
                classes[index],
                ReceiverClass::Interior,
                "floor at {position}"
            );
        }
        // Room A's north wall faces away from a camera that looks toward
        // -z through the doorway, and room B's east wall is behind it.
        let north_wall_a = normal.z < -0.9 && position.x < 3.5 && position.z > 3.9;
        let east_wall_b = normal.x < -0.9 && position.x > 8.1;
        if north_wall_a || east_wall_b {
            assert!(!visible[index], "{position} is out of view");
        }
    }
    assert!(outside_roof > 10);
    assert!(visible.iter().filter(|&&seen| seen).count() > 200);
}
