//! Lightmap detail: a ground plane reaching far outside a building takes
//! few texels by default, the building keeps its density, and the
//! `[lightmap]` section's control and errors.

mod common;

use common::*;
use glam::Vec3;
use relight_scene::atlas::{Atlas, TexelDensity};
use relight_scene::detail::{LightmapDetail, MAX_RING};
use relight_scene::{load_scene, parse_scene_file, Scene, SceneError};

/// A 120 m ground quad (two triangles, as real models have it) under a
/// 6 x 3 x 8 m room of wall quads: the classroom's shape in small.
fn ground_and_room_obj() -> String {
    let faces = relight_scene::generate::ground_and_room_obj(120.0, [6.0, 3.0, 8.0]);
    format!("mtllib mesh.mtl\nusemtl white\n{faces}")
}

fn load(dir: &TempDir, lightmap_section: &str) -> Scene {
    dir.write("mesh.obj", ground_and_room_obj());
    dir.write("mesh.mtl", WHITE_MTL);
    let path = dir.write(
        "scene.toml",
        format!("{}{lightmap_section}", mesh_only_toml("mesh.obj")),
    );
    load_scene(&path).expect("the scene loads")
}

/// Receivers within `metres` of the room's 6 x 3 x 8 m box.
fn near_room(atlas: &Atlas, metres: f32) -> usize {
    let (low, high) = (Vec3::new(-3.0, 0.0, -4.0), Vec3::new(3.0, 3.0, 4.0));
    atlas
        .receivers
        .positions
        .iter()
        .filter(|p| (low - **p).max(**p - high).max_element() < metres)
        .count()
}

#[test]
fn a_ground_plane_gives_its_texels_to_the_building() {
    let dir = TempDir::new("detail-ground");
    let texel = TexelDensity::MetresPerTexel(0.1);
    let scene = load(&dir, "");
    let region = scene.detail_region().expect("the ground reaches far out");
    // 10 % of the room box's 10.4 m diagonal.
    assert!((region.margin - 1.04).abs() < 0.01, "{region:?}");
    let atlas = Atlas::build(&scene, texel).unwrap();
    let uniform_scene = load(&dir, "[lightmap]\ndetail = \"uniform\"\n");
    assert_eq!(
        uniform_scene.mesh.triangles.len(),
        10,
        "uniform keeps the file's triangles"
    );
    let uniform = Atlas::build(&uniform_scene, texel).unwrap();
    // The building's share: at one texel size the 14,400 m^2 ground holds
    // 99 % of the texels; coarsening outside leaves most to the room.
    let share = near_room(&atlas, region.margin) as f64 / atlas.receivers.len() as f64;
    let uniform_share = near_room(&uniform, region.margin) as f64 / uniform.receivers.len() as f64;
    assert!(share > 0.8, "{share} of receivers near the room");
    assert!(uniform_share < 0.05, "{uniform_share}");
    // ... at the same density there: the count within the margin is the
    // uniform atlas's, to within the texels on cut edges (2 %).
    let (near, near_uniform) = (
        near_room(&atlas, region.margin * 0.9),
        near_room(&uniform, region.margin * 0.9),
    );
    assert!(
        (near as f64 - near_uniform as f64).abs() < 0.02 * near_uniform as f64,
        "{near} against {near_uniform}"
    );
    // The cut ground still covers the same surface.
    let (area, uniform_area) = (scene.mesh.total_area(), uniform_scene.mesh.total_area());
    assert!((area - uniform_area).abs() < 1e-6 * uniform_area);
    // The farthest ground takes the coarsest texels: one receiver per
    // (0.1 m * 4^MAX_RING)^2 there, where the uniform atlas has 65,536.
    let far = |atlas: &Atlas| {
        atlas
            .receivers
            .positions
            .iter()
            .filter(|p| p.x.abs() > 55.0 && p.z.abs() > 55.0)
            .count()
    };
    let coarsest = 0.1 * 4f32.powi(MAX_RING as i32);
    assert!(region.ring_edge(MAX_RING - 1) < 52.0);
    let expected = 4.0 * 5.0 * 5.0 / (coarsest * coarsest);
    assert!(
        (far(&atlas) as f32) < 4.0 * expected.max(4.0),
        "{} receivers in the far corners, against {expected} at the coarsest texels",
        far(&atlas)
    );
    assert!(far(&uniform) > 9000);
}

#[test]
fn content_bounds_hold_the_building_not_the_ground() {
    let dir = TempDir::new("detail-content");
    let scene = load(&dir, "");
    let margin = scene.detail_region().unwrap().margin;
    let (low, high) = scene.content_bounds();
    assert_eq!(low, Vec3::new(-3.0 - margin, 0.0, -4.0 - margin));
    assert_eq!(high, Vec3::new(3.0 + margin, 3.0, 4.0 + margin));
    let uniform = load(&dir, "[lightmap]\ndetail = \"uniform\"\n");
    assert_eq!(uniform.content_bounds(), uniform.mesh.bounds());
}

#[test]
fn the_same_file_gives_the_same_atlas() {
    let dir = TempDir::new("detail-determinism");
    let first = Atlas::build(&load(&dir, ""), TexelDensity::Automatic { minimum: 128 }).unwrap();
    let second = Atlas::build(&load(&dir, ""), TexelDensity::Automatic { minimum: 128 }).unwrap();
    assert_eq!(first.receiver_of_texel, second.receiver_of_texel);
    assert_eq!(first.receivers.positions, second.receivers.positions);
}

#[test]
fn a_detail_box_from_the_file_is_used() {
    let dir = TempDir::new("detail-box");
    let scene = load(
        &dir,
        "[lightmap]\ndetail = \"box\"\ndetail_min = [-10, 0, -10]\ndetail_max = [10, 3, 10]\ndetail_margin = 2\n",
    );
    let region = scene.detail_region().unwrap();
    assert_eq!(region.low, Vec3::new(-10.0, 0.0, -10.0));
    assert_eq!(region.high, Vec3::new(10.0, 3.0, 10.0));
    assert_eq!(region.margin, 2.0);
    assert_eq!(
        scene.lightmap_layout.detail,
        LightmapDetail::Bounds {
            low: region.low,
            high: region.high
        }
    );
}

#[test]
fn bad_lightmap_sections_are_errors_with_their_line() {
    let cases = [
        ("detail = \"fine\"\n", "auto"),
        ("detail = \"box\"\n", "detail_min"),
        ("detail = \"box\"\ndetail_min = [0, 0, 0]\n", "neither"),
        (
            "detail = \"box\"\ndetail_min = [0, 0, 0]\ndetail_max = [1, 0, 1]\n",
            "every axis",
        ),
        ("detail_min = [0, 0, 0]\ndetail_max = [1, 1, 1]\n", "box"),
        ("detail_margin = -1\n", "positive"),
        ("detail_margin = nan\n", "positive"),
        ("margin = 1\n", "margin"),
        ("refine_near_lights = \"yes\"\n", "expected a boolean"),
    ];
    for (section, expected) in cases {
        let dir = TempDir::new("detail-errors");
        dir.write("mesh.obj", CORNER_OBJ);
        dir.write("mesh.mtl", WHITE_MTL);
        let path = dir.write(
            "scene.toml",
            format!("{}[lightmap]\n{section}", mesh_only_toml("mesh.obj")),
        );
        let error = parse_scene_file(&path).expect_err(section);
        let text = error.to_string();
        assert!(text.contains(expected), "{section:?}: {text}");
        match error {
            SceneError::Syntax { line, .. } => assert!(line >= 3, "{section:?}: line {line}"),
            other => panic!("{section:?}: {other}"),
        }
    }
}

/// `refine_near_lights` reads as a switch, on unless the file turns it off.
#[test]
fn refining_near_lights_is_on_unless_turned_off() {
    let dir = TempDir::new("detail-near-lights");
    assert!(load(&dir, "").lightmap_layout.refine_near_lights);
    assert!(
        !load(&dir, "[lightmap]\nrefine_near_lights = false\n")
            .lightmap_layout
            .refine_near_lights
    );
}
