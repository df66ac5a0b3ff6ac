//! `export_scene` on the point-lit Cornell box with LightSkin: every file
//! read back by an independent reader (the `ktx2` crate, the `gltf`
//! crate, relight's own scene loader) and compared with what the
//! technique computed.

use glam::UVec3;
use relight_core::Rgb;
use relight_engine::{
    export_scene, lightmap_texel, rgb9e5_gpu_decode, ExportSettings, LightmapLayout, TexelFormat,
    VolumeGrid,
};
use relight_technique::{
    ContextSettings, Frame, NoProgress, SceneContext, Technique, TechniqueKind,
};
use std::path::Path;
use std::sync::Arc;

fn lit_box() -> (Arc<SceneContext>, Box<dyn Technique>) {
    let path =
        Path::new(env!("CARGO_MANIFEST_DIR")).join("../../scenes/cornell-box-point/scene.toml");
    let scene = relight_scene::load_scene(&path).expect("shipped scene loads");
    let context = Arc::new(SceneContext::new(scene, ContextSettings::default()).unwrap());
    let mut technique = relight_lightskin::LightSkinKind
        .create(context.clone(), None, &[], &NoProgress)
        .unwrap();
    technique
        .update(&Frame {
            lights: &context.scene.lights,
            index: 0,
            camera: None,
            moving_mesh_poses: None,
        })
        .unwrap();
    (context, technique)
}

/// The texels of a KTX2 file's one level, checked against the header the
/// export promises.
fn read_ktx2(path: &Path, format: TexelFormat, size: [u32; 3], zstd: bool) -> Vec<Rgb> {
    let bytes = std::fs::read(path).unwrap();
    let reader = ktx2::Reader::new(&bytes[..]).expect("the ktx2 crate parses the file");
    let header = reader.header();
    let expected_format = match format {
        TexelFormat::Rgba16Float => ktx2::Format::R16G16B16A16_SFLOAT,
        TexelFormat::Rgb9e5 => ktx2::Format::E5B9G9R9_UFLOAT_PACK32,
    };
    assert_eq!(header.format, Some(expected_format));
    assert_eq!(
        [header.pixel_width, header.pixel_height, header.pixel_depth],
        size
    );
    assert_eq!((header.face_count, header.level_count), (1, 1));
    assert_eq!(
        header.supercompression_scheme,
        zstd.then_some(ktx2::SupercompressionScheme::Zstandard)
    );
    let basic = reader.basic_dfd().expect("a basic descriptor");
    assert_eq!(
        basic.transfer_function,
        Some(ktx2::TransferFunction::Linear)
    );
    let level = reader.levels().next().unwrap();
    let data = if zstd {
        zstd::bulk::decompress(level.data, level.uncompressed_byte_length as usize).unwrap()
    } else {
        level.data.to_vec()
    };
    let texels = (size[0] * size[1] * size[2].max(1)) as usize;
    assert_eq!(data.len(), texels * format.bytes_per_texel());
    match format {
        TexelFormat::Rgba16Float => data
            .chunks_exact(8)
            .map(|texel| {
                let half =
                    |i: usize| half::f16::from_le_bytes([texel[2 * i], texel[2 * i + 1]]).to_f32();
                assert_eq!(half(3), 1.0);
                Rgb::new(half(0), half(1), half(2))
            })
            .collect(),
        TexelFormat::Rgb9e5 => data
            .chunks_exact(4)
            .map(|word| rgb9e5_gpu_decode(u32::from_le_bytes(word.try_into().unwrap())))
            .collect(),
    }
}

fn assert_close(got: &[Rgb], want: &[Rgb], relative: f32, what: &str) {
    assert_eq!(got.len(), want.len(), "{what}");
    for (index, (got, want)) in got.iter().zip(want).enumerate() {
        let bound = want.max_element() * relative + 1e-6;
        assert!(
            (*got - *want).abs().max_element() <= bound,
            "{what} texel {index}: {got} against {want}"
        );
    }
}

#[test]
fn exported_files_read_back_as_the_technique_computed() {
    let (context, technique) = lit_box();
    let (lo, hi) = context.scene.mesh.bounds();
    let grid = VolumeGrid::covering(lo, hi, 4);
    let lights = context.scene.lights.clone();
    let folder = tempfile::tempdir().unwrap();
    for (format, zstd_level, tolerance) in [
        // Half floats: 11 significant bits. RGB9E5: 9 bits of the
        // brightest channel, so a dim channel beside a bright one may be
        // off by 2^-9 of the bright one (bounded per texel by its max).
        (TexelFormat::Rgba16Float, Some(3), 1.0 / 2048.0),
        (TexelFormat::Rgb9e5, None, 1.0 / 512.0),
    ] {
        let out = folder.path().join(format!("{format:?}"));
        let settings = ExportSettings {
            format,
            zstd_level,
            with_direct: true,
            volume: Some(grid),
        };
        let summary = export_scene(&context, technique.as_ref(), &lights, &settings, &out).unwrap();
        assert!(summary.files.iter().all(|file| file.exists()));
        assert!(!std::fs::read_dir(&out)
            .unwrap()
            .any(|entry| entry.unwrap().path().extension() == Some("tmp".as_ref())));

        let layout = LightmapLayout::new(&context.atlas);
        let size = [context.atlas.width, context.atlas.height, 0];
        let indirect = technique.receiver_irradiance().unwrap();
        let want = layout.to_rgb(indirect);
        assert!(want.iter().any(|texel| texel.max_element() > 0.0));
        let got = read_ktx2(
            &out.join("lightmap-indirect.ktx2"),
            format,
            size,
            zstd_level.is_some(),
        );
        assert_close(&got, &want, tolerance, "indirect lightmap");

        // The full lightmap adds the direct light the renderer computes.
        let receivers = &context.atlas.receivers;
        let mut direct = vec![Rgb::ZERO; receivers.len()];
        context.direct().irradiance_batch(
            &lights,
            &receivers.positions,
            &receivers.normals,
            &mut direct,
        );
        let full: Vec<Rgb> = direct.iter().zip(indirect).map(|(d, i)| *d + *i).collect();
        let got = read_ktx2(
            &out.join("lightmap-full.ktx2"),
            format,
            size,
            zstd_level.is_some(),
        );
        assert_close(&got, &layout.to_rgb(&full), tolerance, "full lightmap");

        // The volume: each voxel face is the technique's light in space.
        let volume = read_ktx2(
            &out.join("irradiance-volume.ktx2"),
            format,
            grid.texture_size().to_array(),
            zstd_level.is_some(),
        );
        let voxel = UVec3::new(1, 2, 1);
        for (face, normal) in relight_engine::volume::FACES.into_iter().enumerate() {
            let want = lightmap_texel(
                technique.indirect_irradiance_in_space(grid.voxel_centre(voxel), normal),
            );
            let got = volume[grid.texel_index(voxel, face)];
            assert_close(&[got], &[want], tolerance, "volume");
        }
    }
}

#[test]
fn the_gltf_loads_back_into_the_same_scene() {
    let (context, technique) = lit_box();
    let folder = tempfile::tempdir().unwrap();
    let settings = ExportSettings {
        format: TexelFormat::Rgba16Float,
        zstd_level: None,
        with_direct: false,
        volume: None,
    };
    let lights = context.scene.lights.clone();
    export_scene(
        &context,
        technique.as_ref(),
        &lights,
        &settings,
        folder.path(),
    )
    .unwrap();
    let gltf_path = folder.path().join("scene.gltf");

    // The gltf crate's validation accepts the document and finds the
    // lightmap through MOZ_lightmap on every material.
    let document = gltf::Gltf::open(&gltf_path).expect("gltf validates the export");
    for material in document.materials() {
        let lightmap = material
            .extension_value("MOZ_lightmap")
            .expect("every material names the lightmap");
        assert_eq!(lightmap["texCoord"], 1);
        let image = document
            .textures()
            .nth(lightmap["index"].as_u64().unwrap() as usize)
            .unwrap()
            .source();
        match image.source() {
            gltf::image::Source::Uri { uri, .. } => assert_eq!(uri, "lightmap-indirect.ktx2"),
            other => panic!("lightmap image is not a file: {other:?}"),
        }
    }

    // relight reads it back: same triangles, materials, lights, camera;
    // and its atlas comes from TEXCOORD_1, the exported atlas.
    let loaded = relight_scene::load_scene(&gltf_path).expect("relight loads its export");
    let (original, mesh) = (&context.scene, &loaded.mesh);
    assert_eq!(mesh.triangles.len(), original.mesh.triangles.len());
    assert_eq!(loaded.lights.len(), original.lights.len());
    for (a, b) in loaded.lights.iter().zip(&original.lights) {
        match (a, b) {
            (
                relight_scene::Light::Point {
                    position: pa,
                    intensity: ia,
                },
                relight_scene::Light::Point {
                    position: pb,
                    intensity: ib,
                },
            ) => {
                assert!((*pa - *pb).length() < 1e-5 && (*ia - *ib).abs().max_element() < 1e-4);
            }
            other => panic!("lights differ: {other:?}"),
        }
    }
    assert!((loaded.camera.eye - original.camera.eye).length() < 1e-4);
    let forward = |camera: &relight_scene::Camera| (camera.target - camera.eye).normalize();
    assert!((forward(&loaded.camera) - forward(&original.camera)).length() < 1e-4);
    let total_albedo = |scene: &relight_scene::Scene| -> Rgb {
        (0..scene.mesh.triangles.len())
            .map(|t| scene.material_of(t).albedo * scene.mesh.area(t))
            .sum()
    };
    assert!(
        (total_albedo(&loaded) - total_albedo(original))
            .abs()
            .max_element()
            < 1e-3
    );
    // TEXCOORD_1 is the atlas: every corner inside the unit square and
    // the same texel area in all (triangles come back grouped by material,
    // so the comparison is of sums).
    assert_eq!(mesh.lightmap_uvs.len(), mesh.positions.len());
    assert!(mesh
        .lightmap_uvs
        .iter()
        .all(|uv| uv.cmpge(glam::Vec2::ZERO).all() && uv.cmple(glam::Vec2::ONE).all()));
    let size = glam::Vec2::new(context.atlas.width as f32, context.atlas.height as f32);
    let area = |[a, b, c]: [glam::Vec2; 3]| 0.5 * (b - a).perp_dot(c - a).abs();
    let exported: f32 = mesh
        .triangles
        .iter()
        .map(|corners| area(corners.map(|v| mesh.lightmap_uvs[v as usize] * size)))
        .sum();
    let atlas: f32 = context
        .atlas
        .triangle_uvs
        .iter()
        .map(|uvs| area(*uvs))
        .sum();
    assert!(
        (exported - atlas).abs() < 1e-3 * atlas,
        "{exported} against {atlas}"
    );
}
