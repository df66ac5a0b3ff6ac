//! Scene-file, OBJ/MTL and glTF loading: the happy paths and every documented
//! failure (each bad input must be an error naming the file, and the line for
//! text formats, or a warning with a documented fallback, never a panic).

mod common;

use common::*;
use glam::{Vec2, Vec3};
use relight_scene::{load_scene, parse_scene_file, Light, SceneError};
use serde_json::json;
use std::path::Path;

fn syntax_line(error: &SceneError) -> Option<(String, usize)> {
    match error {
        SceneError::Syntax { path, line, .. } => Some((path.display().to_string(), *line)),
        _ => None,
    }
}

/// Writes `scene.toml` + a valid quad OBJ/MTL, with `toml_tail` appended.
fn obj_scene(dir: &TempDir, toml_tail: &str) -> std::path::PathBuf {
    dir.write("mesh.obj", CORNER_OBJ);
    dir.write("mesh.mtl", WHITE_MTL);
    dir.write(
        "scene.toml",
        format!("{}{toml_tail}", mesh_only_toml("mesh.obj")),
    )
}

// ---------------------------------------------------------------- scene.toml

#[test]
fn full_scene_file_is_parsed() {
    let dir = TempDir::new("full");
    let path = obj_scene(
        &dir,
        r#"
[camera]
eye = [0.278, 0.273, -0.8]
target = [0.278, 0.273, 0.0]
up = [0.0, 1.0, 0.0]
fov_y = 39.3077
resolution = [320, 200]
[[lights]]
kind = "point"
position = [0.4, 0.45, 0.15]
intensity = [0.3, 0.28, 0.25]
[[lights]]
kind = "directional"
direction = [0.0, -2.0, 0.0]
irradiance = [3.0, 2.9, 2.7]
[[lights]]
kind = "spot"
position = [0, 2, 0]
direction = [0, -1, 0]
intensity = [5, 5, 5]
inner_angle = 20
outer_angle = 30
[environment]
radiance = [0.1, 0.2, 0.3]
[srp]
probes = 64
[[dynamic]]
name = "door"
"#,
    );
    let file = parse_scene_file(&path).unwrap();
    assert_eq!(file.mesh, dir.path("mesh.obj"));
    let camera = file.camera.clone().unwrap();
    assert_eq!(camera.resolution, [320, 200]);
    assert_close(camera.fov_y_degrees, 39.3077, "fov");
    assert_eq!(file.lights.len(), 3);
    assert_eq!(
        file.lights[1],
        Light::Directional {
            direction: Vec3::new(0.0, -1.0, 0.0),
            irradiance: Vec3::new(3.0, 2.9, 2.7)
        }
    );
    match &file.lights[2] {
        Light::Spot {
            inner_angle,
            outer_angle,
            ..
        } => {
            assert_close(*inner_angle, 20f32.to_radians(), "inner");
            assert_close(*outer_angle, 30f32.to_radians(), "outer");
        }
        other => panic!("expected a spot light, got {other:?}"),
    }
    assert_eq!(file.environment.radiance, Vec3::new(0.1, 0.2, 0.3));
    assert_eq!(file.extra.keys().collect::<Vec<_>>(), ["dynamic", "srp"]);
    assert_eq!(file.extra["srp"]["probes"].as_integer(), Some(64));

    let scene = load_scene(&path).unwrap();
    assert_eq!(scene.source, path);
    assert_eq!(scene.lights.len(), 3);
    assert_eq!(scene.camera, camera);
    assert_eq!(scene.mesh.triangles.len(), 2);
    assert!(scene.warnings.is_empty(), "{:?}", scene.warnings);
    // Technique sections reach the scene for the techniques to parse.
    assert_eq!(
        scene.technique_sections["srp"]["probes"].as_integer(),
        Some(64)
    );
}

#[test]
fn misspelt_top_level_key_names_key_file_and_line() {
    let dir = TempDir::new("typo");
    let path = obj_scene(&dir, "\n[[lihgts]]\nkind = \"point\"\n");
    let error = parse_scene_file(&path).unwrap_err();
    let text = error.to_string();
    assert!(
        text.contains("lihgts") && text.contains("scene.toml"),
        "{text}"
    );
    assert_eq!(syntax_line(&error).unwrap().1, 3, "{text}");
}

#[test]
fn unknown_light_field_is_an_error() {
    let dir = TempDir::new("light-field");
    let path = obj_scene(
        &dir,
        "[[lights]]\nkind = \"point\"\nposition = [0,0,0]\nintensity = [1,1,1]\nradius = 2\n",
    );
    let text = message(parse_scene_file(&path));
    assert!(text.contains("radius"), "{text}");
}

#[test]
fn toml_syntax_error_has_line() {
    let dir = TempDir::new("toml-syntax");
    let path = obj_scene(&dir, "[camera\neye = 1\n");
    let error = parse_scene_file(&path).unwrap_err();
    assert_eq!(syntax_line(&error).unwrap().1, 2, "{error}");
}

#[test]
fn negative_or_non_finite_light_values_are_errors() {
    let cases = [
        (
            "[[lights]]\nkind = \"point\"\nposition = [0,0,0]\nintensity = [1,-1,1]\n",
            5,
            "intensity",
        ),
        (
            "[[lights]]\nkind = \"point\"\nposition = [0,0,0]\nintensity = [inf,1,1]\n",
            5,
            "intensity",
        ),
        (
            "[[lights]]\nkind = \"point\"\nposition = [nan,0,0]\nintensity = [1,1,1]\n",
            4,
            "position",
        ),
        (
            "[[lights]]\nkind = \"directional\"\ndirection = [0,-1,0]\nirradiance = [nan,1,1]\n",
            5,
            "irradiance",
        ),
        ("[environment]\nradiance = [0,0,-0.5]\n", 3, "radiance"),
        (
            "[[lights]]\nkind = \"directional\"\ndirection = [0,0,0]\nirradiance = [1,1,1]\n",
            4,
            "direction",
        ),
    ];
    for (tail, line, field) in cases {
        let dir = TempDir::new("light-values");
        let path = obj_scene(&dir, tail);
        let error = parse_scene_file(&path).unwrap_err();
        let text = error.to_string();
        assert!(text.contains(field), "{tail}: {text}");
        assert_eq!(
            syntax_line(&error).map(|(_, line)| line),
            Some(line),
            "{tail}: {text}"
        );
    }
}

#[test]
fn spot_angles_are_validated() {
    let spot = |inner: &str, outer: &str| {
        format!("[[lights]]\nkind = \"spot\"\nposition = [0,2,0]\ndirection = [0,-1,0]\nintensity = [1,1,1]\ninner_angle = {inner}\nouter_angle = {outer}\n")
    };
    for (inner, outer, word) in [
        ("40", "30", "inner_angle"),
        ("10", "95", "outer_angle"),
        ("-1", "30", "inner_angle"),
        ("0", "0", "outer_angle"),
    ] {
        let dir = TempDir::new("spot");
        let text = message(parse_scene_file(&obj_scene(&dir, &spot(inner, outer))));
        assert!(text.contains(word), "{inner}/{outer}: {text}");
    }
    let dir = TempDir::new("spot-ok");
    assert!(parse_scene_file(&obj_scene(&dir, &spot("30", "30"))).is_ok());
}

#[test]
fn light_kind_and_fields_must_match() {
    let cases = [
        ("[[lights]]\nkind = \"area\"\n", "unknown light kind"),
        ("[[lights]]\nkind = \"point\"\nposition = [0,0,0]\n", "lacks `intensity`"),
        ("[[lights]]\nkind = \"point\"\nposition = [0,0,0]\nintensity = [1,1,1]\nirradiance = [1,1,1]\n", "has no `irradiance`"),
    ];
    for (tail, expected) in cases {
        let dir = TempDir::new("kind");
        let text = message(parse_scene_file(&obj_scene(&dir, tail)));
        assert!(text.contains(expected), "{tail}: {text}");
    }
}

#[test]
fn bad_cameras_are_errors() {
    let camera = |eye: &str, fov: &str, extra: &str| {
        format!("[camera]\neye = {eye}\ntarget = [0,0,0]\nfov_y = {fov}\n{extra}")
    };
    for (tail, word) in [
        (camera("[0,0,0]", "45", ""), "differ"),
        (camera("[0,0,1]", "180", ""), "fov_y"),
        (camera("[0,0,1]", "nan", ""), "fov_y"),
        (camera("[0,1,0]", "45", ""), "parallel"),
        (
            camera("[0,0,1]", "45", "resolution = [0, 10]\n"),
            "resolution",
        ),
    ] {
        let dir = TempDir::new("camera");
        let text = message(parse_scene_file(&obj_scene(&dir, &tail)));
        assert!(text.contains(word), "{tail}: {text}");
    }
}

#[test]
fn missing_files_and_formats() {
    let dir = TempDir::new("missing");
    let text = message(parse_scene_file(&dir.path("nope.toml")));
    assert!(text.contains("nope.toml"), "{text}");

    let path = dir.write("scene.toml", mesh_only_toml("absent.obj"));
    let text = message(load_scene(&path));
    assert!(text.contains("absent.obj"), "{text}");

    let path = dir.write("scene.toml", mesh_only_toml("mesh.ply"));
    dir.write("mesh.ply", "ply\n");
    assert!(matches!(
        load_scene(&path),
        Err(SceneError::UnsupportedFormat { .. })
    ));
}

#[test]
fn scene_without_camera_gets_a_framing_camera_and_a_warning() {
    let dir = TempDir::new("no-camera");
    let scene = load_scene(&obj_scene(&dir, "")).unwrap();
    assert!(
        scene
            .warnings
            .iter()
            .any(|warning| warning.contains("no camera")),
        "{:?}",
        scene.warnings
    );
    assert!(scene.camera.eye.z > 1.0);
}

#[test]
fn a_mesh_file_is_a_scene_of_its_own() {
    let folder = Path::new(env!("CARGO_MANIFEST_DIR")).join("../../scenes/cornell-box");
    let from_toml = load_scene(&folder.join("scene.toml")).unwrap();
    let from_obj = load_scene(&folder.join("mesh.obj")).unwrap();
    assert_eq!(from_obj.mesh.triangles, from_toml.mesh.triangles);
    assert_eq!(from_obj.mesh.positions, from_toml.mesh.positions);
    // The OBJ has no camera and its light is emissive geometry.
    assert!(from_obj.warnings.iter().any(|w| w.contains("no camera")));
    assert_eq!(
        from_obj.emissive_triangles(),
        from_toml.emissive_triangles()
    );
}

// ---------------------------------------------------------------- OBJ / MTL

fn obj_error(obj: impl AsRef<[u8]>) -> SceneError {
    let dir = TempDir::new("obj-error");
    dir.write("mesh.obj", obj);
    dir.write("mesh.mtl", WHITE_MTL);
    let path = dir.write("scene.toml", mesh_only_toml("mesh.obj"));
    load_scene(&path).unwrap_err()
}

#[test]
fn obj_errors_name_file_and_line() {
    let cases = [
        ("v 0 0 0\nv 1 0 0\nv nan 1 0\nf 1 2 3\n", 3, "not finite"),
        ("v 0 0 0\nv 1 0 0\nv 1e39 1 0\nf 1 2 3\n", 3, "not finite"),
        ("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 4\n", 4, "out of range"),
        ("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 -4\n", 4, "out of range"),
        (
            "v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1/1 2 3\n",
            4,
            "texture coordinate index",
        ),
        ("v 0 0 0\nv 1 0 x\n", 2, "not a number"),
        ("v 0 0\n", 1, "three coordinates"),
        ("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2\n", 4, "at least 3"),
        ("v 0 0 0\nusemtl\n", 2, "usemtl"),
        ("v 0 0 0 0\n", 1, "w = 0"),
    ];
    for (obj, line, expected) in cases {
        let error = obj_error(obj);
        let text = error.to_string();
        let (path, actual_line) = syntax_line(&error).unwrap_or_else(|| panic!("{obj:?}: {text}"));
        assert!(path.ends_with("mesh.obj"), "{text}");
        assert_eq!(actual_line, line, "{obj:?}: {text}");
        assert!(text.contains(expected), "{obj:?}: {text}");
    }
    let error = obj_error(b"v 0 0 0\n\xff\n");
    assert_eq!(
        syntax_line(&error).map(|(_, line)| line),
        Some(2),
        "{error}"
    );
    assert!(error.to_string().contains("UTF-8"), "{error}");
}

#[test]
fn mtl_errors_name_file_and_line() {
    for (mtl, line, expected) in [
        ("newmtl white\nKe -1 0 0\n", 2, "non-negative"),
        ("newmtl white\nKe inf 0 0\n", 2, "finite"),
        ("Kd 0.5 0.5 0.5\n", 1, "before any `newmtl`"),
        ("newmtl white\nKd 0.5 0.5\n", 2, "one or three"),
        ("newmtl white\nNs -3\n", 2, "Ns"),
    ] {
        let dir = TempDir::new("mtl-error");
        dir.write("mesh.obj", CORNER_OBJ);
        dir.write("mesh.mtl", mtl);
        let path = dir.write("scene.toml", mesh_only_toml("mesh.obj"));
        let error = load_scene(&path).unwrap_err();
        let text = error.to_string();
        let (path, actual_line) = syntax_line(&error).unwrap_or_else(|| panic!("{mtl:?}: {text}"));
        assert!(path.ends_with("mesh.mtl"), "{text}");
        assert_eq!(actual_line, line, "{mtl:?}: {text}");
        assert!(text.contains(expected), "{mtl:?}: {text}");
    }
}

#[test]
fn degenerate_triangles_are_dropped_with_one_warning() {
    let dir = TempDir::new("degenerate");
    dir.write(
        "mesh.obj",
        "v 0 0 0\nv 1 0 0\nv 0 1 0\nv 2 0 0\nv 9 9 9\nf 1 2 3\nf 1 2 4\nf 1 1 3\nf 2 2 2\n",
    );
    let path = dir.write("scene.toml", mesh_only_toml("mesh.obj"));
    let scene = load_scene(&path).unwrap();
    assert_eq!(scene.mesh.triangles.len(), 1);
    // Unused vertices are compacted away, so bounds describe the geometry.
    assert_eq!(scene.mesh.positions.len(), 3);
    let dropped: Vec<_> = scene
        .warnings
        .iter()
        .filter(|warning| warning.contains("degenerate triangle"))
        .collect();
    assert_eq!(dropped.len(), 1, "{:?}", scene.warnings);
    assert!(dropped[0].contains("dropped 3"), "{}", dropped[0]);
}

#[test]
fn all_degenerate_is_empty() {
    let dir = TempDir::new("empty");
    dir.write("mesh.obj", "v 0 0 0\nv 1 0 0\nv 2 0 0\nf 1 2 3\n");
    let path = dir.write("scene.toml", mesh_only_toml("mesh.obj"));
    assert!(matches!(load_scene(&path), Err(SceneError::Empty { .. })));
}

#[test]
fn missing_mtl_falls_back_to_grey_with_warning() {
    let dir = TempDir::new("no-mtl");
    dir.write("mesh.obj", CORNER_OBJ);
    let path = dir.write("scene.toml", mesh_only_toml("mesh.obj"));
    let scene = load_scene(&path).unwrap();
    assert!(
        scene
            .warnings
            .iter()
            .any(|warning| warning.contains("mesh.mtl")),
        "{:?}",
        scene.warnings
    );
    assert_eq!(scene.materials.len(), 1);
    assert_eq!(scene.material_of(0).albedo, Vec3::splat(0.5));
}

#[test]
fn missing_texture_falls_back_to_grey_with_warning() {
    let dir = TempDir::new("no-texture");
    dir.write("mesh.obj", CORNER_OBJ);
    dir.write(
        "mesh.mtl",
        "newmtl white\nKd 0.8 0.8 0.8\nmap_Kd absent.png\n",
    );
    let scene = load_scene(&dir.write("scene.toml", mesh_only_toml("mesh.obj"))).unwrap();
    assert!(
        scene
            .warnings
            .iter()
            .any(|warning| warning.contains("absent.png")),
        "{:?}",
        scene.warnings
    );
    assert_eq!(scene.material_of(0).albedo, Vec3::splat(0.5));
    assert_eq!(scene.material_of(0).albedo_texture, None);
}

#[test]
fn obj_materials_textures_and_flipped_v() {
    let dir = TempDir::new("texture");
    // Two rows red on top, two rows 50% grey below (sRGB 188 ~ linear 0.5).
    dir.write(
        "albedo.png",
        png_rows(
            1,
            &[[255, 0, 0], [255, 0, 0], [188, 188, 188], [188, 188, 188]],
        ),
    );
    dir.write(
        "mesh.obj",
        "mtllib mesh.mtl\nv 0 0 0\nv 1 0 0\nv 0 1 0\nv 0 0 1\nvt 0.5 0.75\nvt 0.5 0.25\nusemtl cloth\nf 1/1 2/1 3/1\nusemtl lamp\nf 1/2 3/2 4/2\nusemtl nowhere\nf 1 2 4\n",
    );
    dir.write(
        "mesh.mtl",
        "# comment\nnewmtl cloth\nKd 1 1 1\nNs 20\nmap_Kd -s 1 1 1 albedo.png\n\nnewmtl lamp\nKd 0.5\nKe 2 3 4\n",
    );
    let scene = load_scene(&dir.write("scene.toml", mesh_only_toml("mesh.obj"))).unwrap();
    assert_eq!(scene.materials.len(), 3, "cloth, lamp, default");
    assert_eq!(scene.materials[0].phong_exponent, 20.0);
    assert_eq!(scene.materials[1].emission, Vec3::new(2.0, 3.0, 4.0));
    assert_eq!(scene.materials[1].albedo, Vec3::splat(0.5));
    assert_eq!(scene.materials[2].albedo, Vec3::splat(0.5));
    assert_eq!(scene.emissive_triangles(), vec![1]);
    assert!(
        scene
            .warnings
            .iter()
            .any(|warning| warning.contains("usemtl nowhere")),
        "{:?}",
        scene.warnings
    );
    // OBJ v = 0.75 is near the top of the image once flipped.
    let top = scene.albedo_at(0, Vec2::new(0.3, 0.3));
    assert_close(top.x, 1.0, "red");
    assert_close(top.y, 0.0, "green");
    // v = 0.25 lands in the grey rows, linearised from sRGB.
    let texture = &scene.textures[0];
    let grey = texture.sample(Vec2::new(0.5, 0.75));
    assert!((grey.x - 0.5).abs() < 0.01, "{grey}");
    assert_eq!(scene.mesh.texcoords.len(), scene.mesh.positions.len());
    assert_close(
        scene.mesh.texcoords[scene.mesh.triangles[0][0] as usize].y,
        0.25,
        "flipped v",
    );
}

#[test]
fn oversized_texture_is_refused_before_decoding() {
    let dir = TempDir::new("huge-texture");
    dir.write("huge.png", png_header_only(20_000, 20_000));
    dir.write("mesh.obj", CORNER_OBJ);
    dir.write("mesh.mtl", "newmtl white\nmap_Kd huge.png\n");
    let text = message(load_scene(
        &dir.write("scene.toml", mesh_only_toml("mesh.obj")),
    ));
    assert!(
        text.contains("20000 x 20000") && text.contains("huge.png"),
        "{text}"
    );
}

#[test]
fn corrupt_texture_is_an_error() {
    let dir = TempDir::new("corrupt-texture");
    let mut png = png_rows(4, &[[1, 2, 3]; 4]);
    png.truncate(png.len() / 2);
    dir.write("bad.png", png);
    dir.write("mesh.obj", CORNER_OBJ);
    dir.write("mesh.mtl", "newmtl white\nmap_Kd bad.png\n");
    let text = message(load_scene(
        &dir.write("scene.toml", mesh_only_toml("mesh.obj")),
    ));
    assert!(text.contains("bad.png"), "{text}");
}

// ---------------------------------------------------------------- glTF

/// One corruption of the fixture glTF JSON.
type JsonEdit = Box<dyn Fn(&mut serde_json::Value)>;

fn write_gltf(dir: &TempDir, json: &serde_json::Value) -> std::path::PathBuf {
    dir.write("quad.bin", quad_binary());
    dir.write("quad.gltf", serde_json::to_vec_pretty(json).unwrap());
    dir.write("scene.toml", mesh_only_toml("quad.gltf"))
}

fn check_quad_scene(scene: &relight_scene::Scene) {
    assert_eq!(scene.mesh.triangles.len(), 2);
    // The node translation is applied.
    assert!(scene
        .mesh
        .positions
        .iter()
        .all(|position| position.y == 2.0));
    assert_eq!(scene.mesh.texcoords.len(), 4);
    assert_eq!(scene.mesh.lightmap_uvs.len(), 4);
    assert_eq!(scene.mesh.lightmap_uvs[0], Vec2::new(0.1, 0.1));
    let material = &scene.materials[0];
    assert_eq!(material.albedo, Vec3::new(0.8, 0.6, 0.4));
    assert_eq!(material.emission, Vec3::new(4.0, 2.0, 1.0));
    assert_close(
        material.phong_exponent,
        2.0 / 0.0625 - 2.0,
        "phong exponent",
    );
    assert_eq!(scene.emissive_triangles().len(), 2);
    assert!(scene
        .mesh
        .geometric_normal(0)
        .abs_diff_eq(Vec3::NEG_Y, 1e-6));
    assert_eq!(
        scene.lights[0],
        Light::Point {
            position: Vec3::ONE,
            intensity: Vec3::new(2.0, 1.0, 0.5)
        }
    );
    match &scene.lights[1] {
        Light::Spot {
            position,
            direction,
            intensity,
            inner_angle,
            outer_angle,
        } => {
            assert!(position.abs_diff_eq(Vec3::new(0.0, 3.0, 0.0), 1e-6));
            assert!(direction.abs_diff_eq(Vec3::NEG_Y, 1e-5), "{direction}");
            assert_eq!(*intensity, Vec3::splat(4.0));
            assert_eq!((*inner_angle, *outer_angle), (0.3, 0.6));
        }
        other => panic!("expected a spot light, got {other:?}"),
    }
    let camera = &scene.camera;
    assert!(camera.eye.abs_diff_eq(Vec3::new(0.0, 1.0, 5.0), 1e-6));
    assert!((camera.target - camera.eye)
        .normalize()
        .abs_diff_eq(Vec3::NEG_Z, 1e-6));
    assert_close(camera.fov_y_degrees, 0.8f32.to_degrees(), "fov");
    assert_eq!(camera.resolution, [384, 256]);
}

#[test]
fn gltf_with_external_buffer() {
    let dir = TempDir::new("gltf");
    let scene = load_scene(&write_gltf(&dir, &quad_gltf(Some("quad.bin")))).unwrap();
    check_quad_scene(&scene);
    assert!(scene.warnings.is_empty(), "{:?}", scene.warnings);
}

#[test]
fn gltf_with_data_uri_and_toml_overrides() {
    let dir = TempDir::new("gltf-data");
    let uri = format!(
        "data:application/octet-stream;base64,{}",
        base64(&quad_binary())
    );
    dir.write(
        "quad.gltf",
        serde_json::to_vec(&quad_gltf(Some(&uri))).unwrap(),
    );
    let path = dir.write(
        "scene.toml",
        "mesh = \"quad.gltf\"\n[camera]\neye = [0,0,9]\ntarget = [0,0,0]\nfov_y = 30\n[[lights]]\nkind = \"directional\"\ndirection = [0,-1,0]\nirradiance = [1,1,1]\n",
    );
    let scene = load_scene(&path).unwrap();
    assert_eq!(
        scene.lights.len(),
        3,
        "two from glTF plus one from the TOML"
    );
    assert!(matches!(scene.lights[2], Light::Directional { .. }));
    assert_eq!(scene.camera.eye, Vec3::new(0.0, 0.0, 9.0));
}

#[test]
fn glb_with_embedded_texture() {
    let dir = TempDir::new("glb");
    let png = png_rows(2, &[[255, 255, 255], [0, 0, 0]]);
    let mut binary = quad_binary();
    let image_offset = binary.len();
    binary.extend(&png);
    let mut json = quad_gltf(None);
    json["buffers"][0]["byteLength"] = json!(binary.len());
    json["bufferViews"]
        .as_array_mut()
        .unwrap()
        .push(json!({"buffer": 0, "byteOffset": image_offset, "byteLength": png.len()}));
    json["images"] = json!([{"bufferView": 4, "mimeType": "image/png"}]);
    json["textures"] = json!([{"source": 0}]);
    json["materials"][0]["pbrMetallicRoughness"]["baseColorTexture"] = json!({"index": 0});
    dir.write("quad.glb", to_glb(&json, &binary));
    let scene = load_scene(&dir.write("scene.toml", mesh_only_toml("quad.glb"))).unwrap();
    check_quad_scene(&scene);
    assert_eq!(scene.textures.len(), 1);
    assert_eq!(scene.materials[0].albedo_texture, Some(0));
    // glTF uv is top-down already: v = 0.25 is the white top row.
    assert_close(
        scene.textures[0].sample(Vec2::new(0.5, 0.25)).x,
        1.0,
        "top row",
    );
}

/// An engine loading the same glTF finds each of its mesh entities'
/// triangles in relight's scene through `Scene::gltf_primitives`: node,
/// mesh and primitive, the node's world transform, and each file
/// triangle's scene triangle in index order (corners swapped under a
/// mirroring node).
#[test]
fn gltf_primitives_record_where_each_instance_went() {
    let dir = TempDir::new("gltf-instances");
    let mut json = quad_gltf(Some("quad.bin"));
    // Node 4, a child of node 0, places the same mesh mirrored in x.
    json["nodes"][0]["children"] = json!([4]);
    json["nodes"]
        .as_array_mut()
        .unwrap()
        .push(json!({"mesh": 0, "translation": [5.0, 0.0, 0.0], "scale": [-1.0, 1.0, 1.0]}));
    let scene = load_scene(&write_gltf(&dir, &json)).unwrap();
    let records = &scene.gltf_primitives;
    assert_eq!(records.len(), 2, "{records:?}");
    assert_eq!(
        (records[0].node, records[0].mesh, records[0].primitive),
        (0, 0, 0)
    );
    assert_eq!(
        (records[1].node, records[1].mesh, records[1].primitive),
        (4, 0, 0)
    );
    assert!(!records[0].mirrored && records[1].mirrored);
    assert!(records[1]
        .world
        .transform_point3(Vec3::ZERO)
        .abs_diff_eq(Vec3::new(5.0, 2.0, 0.0), 1e-6));
    assert_eq!(records[0].triangles, vec![Some(0), Some(1)]);
    assert_eq!(records[1].triangles, vec![Some(2), Some(3)]);
    // The file's triangle 1 (indices 0, 2, 3) under the mirror: corners
    // 1 and 2 swapped, positions through the node's world transform.
    let file_corners = [[0.0, 0.0, 0.0], [1.0, 0.0, 1.0], [0.0, 0.0, 1.0]].map(Vec3::from_array);
    let placed = scene.mesh.vertices(3);
    let world = records[1].world;
    for (corner, file_corner) in [(0, 0), (1, 2), (2, 1)] {
        assert!(placed[corner].abs_diff_eq(world.transform_point3(file_corners[file_corner]), 1e-6));
    }
}

/// A degenerate triangle that loading drops has no scene triangle, and
/// the triangles after it keep pointing at theirs.
#[test]
fn gltf_primitives_follow_dropped_triangles() {
    let dir = TempDir::new("gltf-degenerate");
    let mut binary = quad_binary();
    // Indices 0 1 1 (zero area), then 0 2 3.
    binary.truncate(112);
    for index in [0u16, 1, 1, 0, 2, 3] {
        binary.extend(index.to_le_bytes());
    }
    dir.write("quad.bin", binary);
    let json = quad_gltf(Some("quad.bin"));
    dir.write("quad.gltf", serde_json::to_vec_pretty(&json).unwrap());
    let scene = load_scene(&dir.write("scene.toml", mesh_only_toml("quad.gltf"))).unwrap();
    assert_eq!(scene.mesh.triangles.len(), 1);
    assert_eq!(scene.gltf_primitives[0].triangles, vec![None, Some(0)]);
}

#[test]
fn gltf_uris_outside_the_folder_are_refused() {
    let outer = TempDir::new("gltf-escape");
    std::fs::write(outer.path("outside.bin"), quad_binary()).unwrap();
    let absolute = outer.path("outside.bin").display().to_string();
    for uri in [
        absolute.as_str(),
        "../outside.bin",
        "sub/../../outside.bin",
        "%2e%2e/outside.bin",
        "http://example.com/quad.bin",
        "file:///etc/passwd",
        "C:\\Windows\\quad.bin",
    ] {
        let dir = TempDir::new("gltf-escape-inner");
        let text = message(load_scene(&write_gltf(&dir, &quad_gltf(Some(uri)))));
        assert!(text.contains("refused"), "{uri}: {text}");
    }
}

#[test]
fn gltf_absurd_sizes_are_refused() {
    let mutations: Vec<(&str, JsonEdit)> = vec![
        (
            "more bytes than",
            Box::new(|json| json["accessors"][0]["count"] = json!(1_000_000_000_000u64)),
        ),
        (
            "more bytes than",
            Box::new(|json| json["accessors"][3]["byteOffset"] = json!(4)),
        ),
        (
            "outside its buffer",
            Box::new(|json| json["bufferViews"][3]["byteLength"] = json!(4000)),
        ),
        (
            "declares",
            Box::new(|json| json["buffers"][0]["byteLength"] = json!(999_999_999_999u64)),
        ),
        // Only 2 positions, but the indices reach vertex 3.
        (
            "references vertex",
            Box::new(|json| {
                json["accessors"][0]["count"] = json!(2);
                json["meshes"][0]["primitives"][0]["attributes"] = json!({"POSITION": 0});
            }),
        ),
    ];
    for (expected, mutate) in mutations {
        let dir = TempDir::new("gltf-size");
        let mut json = quad_gltf(Some("quad.bin"));
        mutate(&mut json);
        let path = write_gltf(&dir, &json);
        let text = message(load_scene(&path));
        assert!(text.contains(expected), "{expected}: {text}");
    }
}

#[test]
fn gltf_oversized_image_is_refused() {
    let dir = TempDir::new("gltf-huge-image");
    dir.write("huge.png", png_header_only(16_385, 8));
    let mut json = quad_gltf(Some("quad.bin"));
    json["images"] = json!([{"uri": "huge.png"}]);
    json["textures"] = json!([{"source": 0}]);
    json["materials"][0]["pbrMetallicRoughness"]["baseColorTexture"] = json!({"index": 0});
    let text = message(load_scene(&write_gltf(&dir, &json)));
    assert!(text.contains("16385 x 8"), "{text}");
}

#[test]
fn gltf_missing_image_falls_back_to_grey() {
    let dir = TempDir::new("gltf-missing-image");
    let mut json = quad_gltf(Some("quad.bin"));
    json["images"] = json!([{"uri": "absent.png"}]);
    json["textures"] = json!([{"source": 0}]);
    json["materials"][0]["pbrMetallicRoughness"]["baseColorTexture"] = json!({"index": 0});
    let scene = load_scene(&write_gltf(&dir, &json)).unwrap();
    assert_eq!(scene.materials[0].albedo, Vec3::splat(0.5));
    assert!(
        scene
            .warnings
            .iter()
            .any(|warning| warning.contains("absent.png")),
        "{:?}",
        scene.warnings
    );
}

#[test]
fn gltf_node_cycles_are_errors() {
    let dir = TempDir::new("gltf-cycle");
    let mut json = quad_gltf(Some("quad.bin"));
    json["nodes"][0]["children"] = json!([1]);
    json["nodes"][1]["children"] = json!([0]);
    let text = message(load_scene(&write_gltf(&dir, &json)));
    assert!(text.contains("quad.gltf"), "{text}");
}

#[test]
fn gltf_light_values_are_validated() {
    let mutations: Vec<JsonEdit> = vec![
        Box::new(|json| {
            json["extensions"]["KHR_lights_punctual"]["lights"][0]["intensity"] = json!(-1.0)
        }),
        Box::new(|json| {
            json["extensions"]["KHR_lights_punctual"]["lights"][1]["spot"]["outerConeAngle"] =
                json!(2.0)
        }),
        Box::new(|json| {
            json["extensions"]["KHR_lights_punctual"]["lights"][1]["spot"]["innerConeAngle"] =
                json!(0.7)
        }),
        Box::new(|json| json["materials"][0]["emissiveFactor"] = json!([-1.0, 0.0, 0.0])),
        Box::new(|json| {
            json["materials"][0]["extensions"]["KHR_materials_emissive_strength"]
                ["emissiveStrength"] = json!(-2.0)
        }),
    ];
    for (index, mutate) in mutations.iter().enumerate() {
        let dir = TempDir::new("gltf-light");
        let mut json = quad_gltf(Some("quad.bin"));
        mutate(&mut json);
        let text = message(load_scene(&write_gltf(&dir, &json)));
        assert!(text.contains("quad.gltf"), "case {index}: {text}");
    }
}

#[test]
fn gltf_json_syntax_error_has_line() {
    let dir = TempDir::new("gltf-syntax");
    dir.write(
        "quad.gltf",
        "{\n  \"asset\": {\"version\": \"2.0\"},\n  \"nodes\": [,]\n}\n",
    );
    let error = load_scene(&dir.write("scene.toml", mesh_only_toml("quad.gltf"))).unwrap_err();
    assert_eq!(
        syntax_line(&error).map(|(_, line)| line),
        Some(3),
        "{error}"
    );
}

#[test]
fn gltf_without_material_and_partial_uv1_and_mirroring() {
    let dir = TempDir::new("gltf-partial");
    let mut json = quad_gltf(Some("quad.bin"));
    // A second primitive without TEXCOORD_1 and without material, on a
    // mirrored node.
    json["meshes"]
        .as_array_mut()
        .unwrap()
        .push(json!({"primitives": [{"attributes": {"POSITION": 0}, "indices": 3}]}));
    json["nodes"]
        .as_array_mut()
        .unwrap()
        .push(json!({"mesh": 1, "scale": [1.0, -1.0, 1.0]}));
    json["scenes"][0]["nodes"]
        .as_array_mut()
        .unwrap()
        .push(json!(4));
    let scene = load_scene(&write_gltf(&dir, &json)).unwrap();
    assert_eq!(scene.mesh.triangles.len(), 4);
    assert!(
        scene.mesh.lightmap_uvs.is_empty(),
        "TEXCOORD_1 only where every primitive has it"
    );
    assert_eq!(scene.mesh.texcoords.len(), scene.mesh.positions.len());
    assert_eq!(scene.materials.len(), 2);
    assert_eq!(scene.materials[1].albedo, Vec3::splat(0.5));
    assert_eq!(scene.mesh.material_ids[2], 1);
    // A mirror flips the winding back so the front face is the mirrored one.
    assert!(
        scene.mesh.geometric_normal(2).abs_diff_eq(Vec3::Y, 1e-6),
        "{:?} {:?}",
        scene.mesh.vertices(2),
        scene.mesh.positions
    );
}

#[test]
fn glb_truncated_or_lying_header_is_an_error() {
    let full = to_glb(&quad_gltf(None), &quad_binary());
    for cut in [4, 11, 20, full.len() - 10] {
        let dir = TempDir::new("glb-cut");
        dir.write("quad.glb", &full[..cut]);
        let text = message(load_scene(
            &dir.write("scene.toml", mesh_only_toml("quad.glb")),
        ));
        assert!(text.contains("quad.glb"), "{cut}: {text}");
    }
    let dir = TempDir::new("glb-magic");
    dir.write("quad.glb", b"{\"asset\": {}}");
    let text = message(load_scene(
        &dir.write("scene.toml", mesh_only_toml("quad.glb")),
    ));
    assert!(text.contains("glTF"), "{text}");
}

// ---------------------------------------------------------------- shipped scenes

#[test]
fn shipped_scenes_load() {
    let scenes = Path::new(env!("CARGO_MANIFEST_DIR")).join("../../scenes");
    // (folder, triangles, emissive triangles, lights)
    for (folder, triangles, emissive, lights) in [
        ("cornell-box", 32, 2, 0),
        ("cornell-box-point", 30, 0, 1),
        ("corridor", 52, 0, 2),
        ("two-rooms", 108, 0, 1),
    ] {
        let scene = load_scene(&scenes.join(folder).join("scene.toml")).unwrap();
        assert!(scene.warnings.is_empty(), "{folder}: {:?}", scene.warnings);
        assert_eq!(scene.mesh.triangles.len(), triangles, "{folder}");
        assert_eq!(scene.emissive_triangles().len(), emissive, "{folder}");
        assert_eq!(scene.lights.len(), lights, "{folder}");
        for triangle in scene.emissive_triangles() {
            let normal = scene.mesh.geometric_normal(triangle as usize);
            assert!(
                normal.abs_diff_eq(Vec3::NEG_Y, 1e-3),
                "{folder}: the light must face down, {normal}"
            );
        }
    }
}

#[test]
fn cornell_box_walls_face_into_the_box() {
    let scenes = Path::new(env!("CARGO_MANIFEST_DIR")).join("../../scenes");
    let scene = load_scene(&scenes.join("cornell-box/scene.toml")).unwrap();
    let centre = Vec3::new(0.278, 0.274, 0.28);
    let (low, high) = scene.mesh.bounds();
    assert!(
        low.abs_diff_eq(Vec3::ZERO, 1e-6)
            && high.abs_diff_eq(Vec3::new(0.556, 0.5488, 0.5592), 1e-6)
    );
    for triangle in 0..scene.mesh.triangles.len() {
        let [a, b, c] = scene.mesh.vertices(triangle);
        let on_box_boundary = [a, b, c]
            .iter()
            .all(|p| p.y == 0.0 || p.y == 0.5488 || p.z == 0.5592 || p.x < 1e-9 || p.x > 0.549);
        if on_box_boundary {
            let towards_centre = centre - (a + b + c) / 3.0;
            assert!(
                scene.mesh.geometric_normal(triangle).dot(towards_centre) > 0.0,
                "triangle {triangle}"
            );
        }
    }
    let red = scene
        .materials
        .iter()
        .find(|material| material.name == "red")
        .unwrap();
    assert_eq!(red.albedo, Vec3::new(0.63, 0.065, 0.05));
}
