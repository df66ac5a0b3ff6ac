//! The bridge's test: Bevy's render of the shipped Cornell boxes, lit by
//! relight's lightmap, against relight's own render of the same camera.
//! It pins the units, the UV channel and the lightmap's orientation.
//! Needs a Vulkan device; CI installs Mesa's software one (lavapipe).
//!
//! Bounds (the issue's): indirect-only images agree within 5 % in total
//! light and 10 % relative RMSE over 8x8-pixel tile means; full images
//! (Bevy's shadow-mapped direct light plus relight's indirect) within 15 %
//! over tiles. Tiles, because the two renderers sample pixels differently
//! (MSAA against jittered rays) and Bevy's lightmap is bilinear in texels
//! where relight's renderer asks the technique at every point.

use relight_bevy::snapshot::{render_snapshot, Snapshot, SnapshotSettings};
use relight_bevy::RelightScene;
use relight_core::Rgb;
use relight_render::metrics::{error_norms, light_ratio, tile_means};
use relight_render::Image;
use relight_technique::{
    parameters_fingerprint, write_bake_atomic, BakeHeader, ContextSettings, Frame, NoProgress,
    SceneContext,
};
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::time::Duration;

fn shipped(name: &str) -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("../../scenes")
        .join(name)
        .join("scene.toml")
}

fn image_of(snapshot: &Snapshot) -> Image {
    Image {
        width: snapshot.width,
        height: snapshot.height,
        pixels: snapshot
            .pixels
            .iter()
            .map(|pixel| Rgb::from_array(*pixel))
            .collect(),
    }
}

/// The technique's bake of the scene as a file in `folder`, as `relight
/// bake` writes it (`None` for techniques without one), so that relight's
/// render and Bevy's load the same bake.
fn bake_file(context: &SceneContext, technique: &str, folder: &Path) -> Option<PathBuf> {
    let kind = relight_engine::techniques::find(technique).unwrap();
    if !kind.needs_bake() {
        return None;
    }
    let payload = kind.bake(context, &[], &NoProgress).unwrap();
    let header = BakeHeader {
        technique: technique.to_string(),
        payload_version: 1,
        scene_fingerprint: context.fingerprint(),
        parameters_fingerprint: parameters_fingerprint(kind, &context.scene, &[]),
        shard: None,
    };
    let path = folder.join(format!("{technique}.bake"));
    write_bake_atomic(&path, &header, &payload).unwrap();
    Some(path)
}

/// relight's own render of the scene camera after `frames` updates.
struct RelightRender {
    full: Image,
    indirect: Image,
    /// Which pixels see a moving mesh at their centre.
    moving_mesh_pixels: Vec<bool>,
    /// The path tracer's indirect light, with as many bounces as the
    /// technique computes, when the scene has moving meshes (which the
    /// reference technique's receivers leave out).
    traced_indirect: Option<Image>,
}

/// Moving meshes stay at their first pose, where the plugin spawns them.
fn relight_render(
    context: &Arc<SceneContext>,
    technique: &str,
    bake: Option<&Path>,
    frames: u64,
) -> RelightRender {
    let mut instance =
        relight_engine::open_technique(context, technique, &[], bake, &NoProgress).unwrap();
    let lights = context.scene.lights.clone();
    let poses: Vec<_> = relight_engine::moving_meshes(&context.scene)
        .unwrap()
        .iter()
        .map(|mesh| mesh.pose(0))
        .collect();
    for index in 0..frames {
        instance
            .update(&Frame {
                lights: &lights,
                index,
                camera: None,
                moving_mesh_poses: Some(&poses),
            })
            .unwrap();
    }
    // The renderer traces the moving meshes where the technique put them.
    let frame_context = instance
        .frame_geometry()
        .map(|scene| context.with_frame_geometry(scene));
    let traced = frame_context.as_ref().unwrap_or(context);
    let rays = relight_trace::path::CameraRays::new(&context.scene.camera);
    let static_triangles = context.scene.mesh.triangles.len() as u32;
    let moving_mesh_pixels = (0..rays.height)
        .flat_map(|y| (0..rays.width).map(move |x| (x, y)))
        .map(|(x, y)| {
            traced
                .bvh
                .intersect(&rays.ray(x, y, relight_core::Vec2::splat(0.5)))
                .is_some_and(|hit| hit.triangle >= static_triangles)
        })
        .collect();
    let renders = relight_render::render::render_with_technique(
        traced,
        &lights,
        instance.as_ref(),
        16,
        1,
        &NoProgress,
    );
    let traced_indirect = frame_context.as_ref().map(|frame_context| {
        let settings = relight_trace::path::PathSettings {
            max_bounces: instance.reference_bounces(64),
            ..Default::default()
        };
        relight_render::render::render_reference(frame_context, &lights, settings, 256, &NoProgress)
            .indirect
    });
    RelightRender {
        full: renders.full,
        indirect: renders.indirect,
        moving_mesh_pixels,
        traced_indirect,
    }
}

struct Agreement {
    total: f64,
    tiles: f64,
}

/// Agreement over the pixels outside `left_out` (whole tiles: a tile
/// with any such pixel is left out).
fn agreement(bevy: &Image, relight: &Image, left_out: &[bool]) -> Agreement {
    assert_eq!((bevy.width, bevy.height), (relight.width, relight.height));
    let tile_columns = bevy.width.div_ceil(8) as usize;
    let tile_of = |pixel: usize| {
        (pixel / bevy.width as usize / 8) * tile_columns + (pixel % bevy.width as usize) / 8
    };
    let mut tile_left_out = vec![false; tile_columns * bevy.height.div_ceil(8) as usize];
    for (pixel, _) in left_out.iter().enumerate().filter(|(_, &out)| out) {
        tile_left_out[tile_of(pixel)] = true;
    }
    let kept = |image: &Image| -> Vec<Rgb> {
        image
            .pixels
            .iter()
            .enumerate()
            .filter(|(pixel, _)| !tile_left_out[tile_of(*pixel)])
            .map(|(_, &value)| value)
            .collect()
    };
    let kept_tiles = |image: &Image| -> Vec<Rgb> {
        tile_means(image, 8)
            .into_iter()
            .zip(&tile_left_out)
            .filter(|(_, &out)| !out)
            .map(|(value, _)| value)
            .collect()
    };
    Agreement {
        total: light_ratio(&kept(bevy), &kept(relight)),
        tiles: error_norms(&kept_tiles(bevy), &kept_tiles(relight)).relative_rmse,
    }
}

/// Mean light over the pixels marked in `mask`.
fn mean_over(image: &Image, mask: &[bool]) -> f64 {
    let (sum, count) = image
        .pixels
        .iter()
        .zip(mask)
        .filter(|(_, &inside)| inside)
        .fold((0.0, 0usize), |(sum, count), (pixel, _)| {
            (sum + f64::from(pixel.x + pixel.y + pixel.z), count + 1)
        });
    sum / count.max(1) as f64
}

/// How Bevy gets the scene: spawned by the plugin from relight's copy, or
/// loaded by Bevy's glTF loader and adopted, with the file's materials as
/// Bevy's loader makes them or with relight's shading.
#[derive(Clone, Copy, PartialEq)]
enum Spawning {
    ByRelight,
    Adopted { relight_shading: bool },
}

impl Spawning {
    /// Whether Bevy shades direct light as relight does, so the full
    /// images must agree too. Bevy's glTF materials (Burley diffuse, a 4 %
    /// specular lobe) are not relight's Lambertian ones: measured 1.098x
    /// and 18.8 % over tiles in the adopted room, 0.992x and 1.3 % with
    /// relight's shading.
    fn shades_like_relight(self) -> bool {
        !matches!(
            self,
            Spawning::Adopted {
                relight_shading: false
            }
        )
    }
}

fn snapshot(
    path: &Path,
    technique: &str,
    bake: Option<&Path>,
    indirect_only: bool,
    frames: u64,
    volume_cells: u32,
    spawning: Spawning,
) -> Image {
    let mut scene = RelightScene::new(path).technique(technique);
    scene.bake = bake.map(Path::to_path_buf);
    scene.indirect_only = indirect_only;
    scene.volume_cells = volume_cells;
    if let Spawning::Adopted { relight_shading } = spawning {
        scene.adopt = true;
        scene.relight_shading = relight_shading;
    }
    let settings = SnapshotSettings {
        scene,
        gi_updates: frames,
        size: None,
        timeout: Duration::from_secs(900),
    };
    image_of(&render_snapshot(&settings).expect("Bevy renders the scene"))
}

/// Bevy's light on moving meshes (the volume's) over relight's (the
/// technique asked at each point), in total over their pixels. Looser
/// than the lightmap's 5 %: the volume holds six directions at voxel
/// centres (3.5 cm apart in the Cornell box) and Bevy blends them by the
/// squared normal and trilinearly, where relight's render asks at every
/// point; measured 0.947x (and relight's own 1.017x the path tracer's).
/// Light read before the lights reached their places (the first update
/// used to, with every light at the origin) measured 0.171x.
const MOVING_MESH_LIGHT: (f64, f64) = (0.85, 1.15);

/// Compares Bevy's snapshots of `path` with relight's renders for each
/// technique; returns those out of bounds.
fn compare(
    path: &Path,
    techniques: &[&str],
    volume_cells: u32,
    spawning: Spawning,
    folder: &Path,
) -> Vec<String> {
    let mut failures = Vec::new();
    let folder_name = path
        .parent()
        .and_then(Path::file_name)
        .unwrap()
        .to_string_lossy();
    let scene = match spawning {
        Spawning::ByRelight => folder_name.into_owned(),
        Spawning::Adopted { relight_shading } => format!(
            "adopted glTF ({} shading)",
            if relight_shading {
                "relight's"
            } else {
                "the file's"
            }
        ),
    };
    let context = Arc::new(
        SceneContext::new(
            relight_scene::load_scene(path).unwrap(),
            ContextSettings::default(),
        )
        .unwrap(),
    );
    for &technique in techniques {
        // Several updates: SRP and PIC feed last frame's light back.
        let frames = 6;
        let bake = bake_file(&context, technique, folder);
        let RelightRender {
            full,
            indirect,
            moving_mesh_pixels: moving,
            traced_indirect,
        } = relight_render(&context, technique, bake.as_deref(), frames);
        let bevy_indirect = snapshot(
            path,
            technique,
            bake.as_deref(),
            true,
            frames,
            volume_cells,
            spawning,
        );
        let bevy_full = snapshot(
            path,
            technique,
            bake.as_deref(),
            false,
            frames,
            volume_cells,
            spawning,
        );
        // The lightmap's agreement, over the static surfaces: Bevy lights
        // moving meshes from the volume's voxels, relight's render asks the
        // technique at each of their points (LightSkin: its interpolated
        // lights at the mesh's vertices), two estimates, compared below.
        let indirect_agreement = agreement(&bevy_indirect, &indirect, &moving);
        let full_agreement = agreement(&bevy_full, &full, &moving);
        println!(
            "{scene} {technique}: indirect total {:.3}x, tiles {:.1} %; full total {:.3}x, tiles {:.1} %",
            indirect_agreement.total,
            100.0 * indirect_agreement.tiles,
            full_agreement.total,
            100.0 * full_agreement.tiles
        );
        if (indirect_agreement.total - 1.0).abs() > 0.05
            || indirect_agreement.tiles > 0.10
            || (spawning.shades_like_relight() && full_agreement.tiles > 0.15)
        {
            failures.push(format!("{scene} {technique}"));
        }
        let moving_pixels = moving.iter().filter(|&&inside| inside).count();
        if moving_pixels > 0 {
            let ratio = mean_over(&bevy_indirect, &moving) / mean_over(&indirect, &moving);
            let traced = traced_indirect
                .as_ref()
                .map_or(f64::NAN, |image| mean_over(image, &moving));
            println!(
                "{scene} {technique}: moving meshes ({moving_pixels} pixels), indirect light {ratio:.3}x relight's; against the path tracer: Bevy {:.3}x, relight {:.3}x",
                mean_over(&bevy_indirect, &moving) / traced,
                mean_over(&indirect, &moving) / traced,
            );
            if !(MOVING_MESH_LIGHT.0..=MOVING_MESH_LIGHT.1).contains(&ratio) {
                failures.push(format!("{scene} {technique}: moving meshes {ratio:.3}x"));
            }
        }
        if let Ok(folder) = std::env::var("RELIGHT_SNAPSHOT_DIR") {
            let folder = PathBuf::from(folder);
            std::fs::create_dir_all(&folder).unwrap();
            for (name, image, same_as) in [
                ("bevy-indirect", &bevy_indirect, &indirect),
                ("relight-indirect", &indirect, &indirect),
                ("bevy-full", &bevy_full, &full),
                ("relight-full", &full, &full),
            ] {
                let stem = folder.join(format!("{scene}-{technique}-{name}"));
                image.write(&stem.with_extension("exr"), None).unwrap();
                // PNGs of a pair share the relight image's exposure.
                let exposure = same_as.auto_exposure();
                image
                    .write(&stem.with_extension("png"), Some(exposure))
                    .unwrap();
            }
        }
    }
    failures
}

#[test]
fn bevy_shows_relights_light() {
    let folder = tempfile::tempdir().unwrap();
    let mut failures = Vec::new();
    for scene in ["cornell-box-point", "cornell-box"] {
        failures.extend(compare(
            &shipped(scene),
            &["lightskin", "prm", "srp", "pic"],
            0,
            Spawning::ByRelight,
            folder.path(),
        ));
    }
    assert!(failures.is_empty(), "out of bounds: {failures:?}");
}

/// The moving box: the plugin spawns it, reads its entity's transform
/// into LightSkin's frame (its shadow and bounce move the lightmap), and
/// Bevy lights it from the irradiance volume, which relight's render
/// answers at every point instead. Same bounds as the static boxes.
#[test]
fn moving_mesh_follows_its_entity_and_is_lit_by_the_volume() {
    let folder = tempfile::tempdir().unwrap();
    let path =
        Path::new(env!("CARGO_MANIFEST_DIR")).join("../../scenes/sequences/moving-box/scene.toml");
    let failures = compare(
        &path,
        &["lightskin"],
        16,
        Spawning::ByRelight,
        folder.path(),
    );
    assert!(failures.is_empty(), "out of bounds: {failures:?}");
}

/// A glTF the app loads itself, adopted: Bevy's glTF loader spawns it
/// (its own materials, its light read as sRGB), the plugin gives its mesh
/// entities relight's atlas and the lightmap and takes over its light.
/// The file has what real exports have and a lookup by mesh alone gets
/// wrong: one mesh placed by two nodes, one of them mirrored and under a
/// parent node; a mesh of three primitives; a degenerate triangle that
/// relight drops; a coloured point light. The lightmap has the bounds of
/// the boxes relight spawns, with the file's materials and with relight's
/// shading; the full image only with relight's shading (see
/// [`Spawning::shades_like_relight`]), where it checks the light the
/// plugin took over. A wrong placement or corner order shows as a
/// lightmap off by far more, the light read as sRGB as a colour shift.
#[test]
fn an_adopted_gltf_shows_relights_light() {
    let folder = tempfile::tempdir().unwrap();
    if let Ok(keep) = std::env::var("RELIGHT_ADOPT_DIR") {
        std::fs::create_dir_all(&keep).unwrap();
        write_adoptable_room(Path::new(&keep));
    }
    let path = write_adoptable_room(folder.path());
    let mut failures = Vec::new();
    for relight_shading in [false, true] {
        failures.extend(compare(
            &path,
            &["lightskin", "pic"],
            0,
            Spawning::Adopted { relight_shading },
            folder.path(),
        ));
    }
    // The same lightmap on the same surfaces: Bevy's image of the adopted
    // meshes is Bevy's image of relight's own copy but for rasterisation
    // order. Any texel looked up in the wrong place (a corner order, a
    // node) shows in the tiles it covers, which the whole-image bounds
    // above average away.
    let spawned = snapshot(&path, "lightskin", None, true, 6, 0, Spawning::ByRelight);
    let adopted = snapshot(
        &path,
        "lightskin",
        None,
        true,
        6,
        0,
        Spawning::Adopted {
            relight_shading: false,
        },
    );
    let worst = worst_tile_difference(&adopted, &spawned);
    println!(
        "adopted against spawned: worst 8x8 tile {:.2} % of the mean tile",
        100.0 * worst
    );
    assert!(worst < ADOPTED_TILE_DIFFERENCE, "worst tile {worst}");
    assert!(failures.is_empty(), "out of bounds: {failures:?}");
}

/// The worst 8x8 tile difference (sum of RGB) between two images of the
/// same scene, over the mean tile.
fn worst_tile_difference(a: &Image, b: &Image) -> f64 {
    let sum = |value: &Rgb| f64::from(value.x + value.y + value.z);
    let (a, b) = (tile_means(a, 8), tile_means(b, 8));
    let mean = b.iter().map(sum).sum::<f64>() / b.len() as f64;
    a.iter()
        .zip(&b)
        .map(|(x, y)| (sum(x) - sum(y)).abs())
        .fold(0.0, f64::max)
        / mean
}

const ADOPTED_TILE_DIFFERENCE: f64 = 0.01;

/// The room's glTF (`room.gltf`, `room.bin`) and a scene file with its
/// camera; returns the scene file.
fn write_adoptable_room(folder: &Path) -> PathBuf {
    #[derive(Default)]
    struct Primitive {
        positions: Vec<[f32; 3]>,
        normals: Vec<[f32; 3]>,
        indices: Vec<u16>,
    }
    impl Primitive {
        /// A quad with its winding set to face `normal`.
        fn quad(&mut self, mut corners: [[f32; 3]; 4], normal: [f32; 3]) {
            let v = |p: [f32; 3]| relight_core::Vec3::from_array(p);
            let facing = (v(corners[1]) - v(corners[0]))
                .cross(v(corners[2]) - v(corners[0]))
                .dot(v(normal));
            if facing < 0.0 {
                corners.swap(1, 3);
            }
            let base = self.positions.len() as u16;
            self.positions.extend(corners);
            self.normals.extend([normal; 4]);
            self.indices
                .extend([0, 1, 2, 0, 2, 3].map(|corner| base + corner));
        }
        /// An axis-aligned box from `lo` to `hi`, faces pointing out
        /// (`outward`) or in.
        fn cuboid(&mut self, lo: [f32; 3], hi: [f32; 3], outward: bool, faces: &[usize]) {
            for &face in faces {
                let axis = face / 2;
                let high = face % 2 == 1;
                let (u, w) = ((axis + 1) % 3, (axis + 2) % 3);
                let mut corners = [[0.0; 3]; 4];
                for (corner, (a, b)) in [(false, false), (true, false), (true, true), (false, true)]
                    .into_iter()
                    .enumerate()
                {
                    corners[corner][axis] = if high { hi[axis] } else { lo[axis] };
                    corners[corner][u] = if a { hi[u] } else { lo[u] };
                    corners[corner][w] = if b { hi[w] } else { lo[w] };
                }
                let mut normal = [0.0; 3];
                normal[axis] = if high == outward { 1.0 } else { -1.0 };
                self.quad(corners, normal);
            }
        }
    }
    // Faces: 0 -x, 1 +x, 2 -y, 3 +y, 4 -z, 5 +z. The room is open at +z,
    // towards the camera.
    let mut white = Primitive::default();
    white.cuboid([0.0; 3], [1.0; 3], false, &[2, 3]);
    // A zero-area triangle between the floor and the ceiling.
    white.indices.extend([0, 1, 1]);
    white.cuboid([0.0; 3], [1.0; 3], false, &[4]);
    let mut red = Primitive::default();
    red.cuboid([0.0; 3], [1.0; 3], false, &[0]);
    let mut green = Primitive::default();
    green.cuboid([0.0; 3], [1.0; 3], false, &[1]);
    let mut block = Primitive::default();
    block.cuboid([0.0; 3], [0.25, 0.5, 0.25], true, &[0, 1, 2, 3, 4, 5]);
    let primitives = [white, red, green, block];

    let mut binary = Vec::new();
    let mut views = Vec::new();
    let mut accessors = Vec::new();
    let mut view = |binary: &mut Vec<u8>, bytes: Vec<u8>| {
        let offset = binary.len();
        binary.extend(&bytes);
        while !binary.len().is_multiple_of(4) {
            binary.push(0);
        }
        views.push(
            serde_json::json!({"buffer": 0, "byteOffset": offset, "byteLength": bytes.len()}),
        );
        views.len() - 1
    };
    for primitive in &primitives {
        let floats = |values: &[[f32; 3]]| -> Vec<u8> {
            values
                .iter()
                .flatten()
                .flat_map(|value| value.to_le_bytes())
                .collect()
        };
        let (mut lo, mut hi) = ([f32::MAX; 3], [f32::MIN; 3]);
        for position in &primitive.positions {
            for axis in 0..3 {
                lo[axis] = lo[axis].min(position[axis]);
                hi[axis] = hi[axis].max(position[axis]);
            }
        }
        let count = primitive.positions.len();
        let positions = view(&mut binary, floats(&primitive.positions));
        accessors.push(
            serde_json::json!({"bufferView": positions, "componentType": 5126,
            "count": count, "type": "VEC3", "min": lo, "max": hi}),
        );
        let normals = view(&mut binary, floats(&primitive.normals));
        accessors.push(
            serde_json::json!({"bufferView": normals, "componentType": 5126,
            "count": count, "type": "VEC3"}),
        );
        let indices = view(
            &mut binary,
            primitive
                .indices
                .iter()
                .flat_map(|index| index.to_le_bytes())
                .collect(),
        );
        accessors.push(
            serde_json::json!({"bufferView": indices, "componentType": 5123,
            "count": primitive.indices.len(), "type": "SCALAR"}),
        );
    }
    let primitive_json = |index: usize, material: usize| {
        serde_json::json!({"attributes": {"POSITION": 3 * index, "NORMAL": 3 * index + 1},
            "indices": 3 * index + 2, "material": material})
    };
    let material = |rgb: [f32; 3]| {
        serde_json::json!({"pbrMetallicRoughness": {
            "baseColorFactor": [rgb[0], rgb[1], rgb[2], 1.0],
            "metallicFactor": 0.0, "roughnessFactor": 1.0}})
    };
    let turn = (0.3f32 / 2.0).sin_cos();
    let gltf = serde_json::json!({
        "asset": {"version": "2.0"},
        "extensionsUsed": ["KHR_lights_punctual"],
        "scene": 0,
        "scenes": [{"nodes": [0, 1, 2, 4]}],
        "nodes": [
            {"mesh": 0, "name": "room"},
            {"mesh": 1, "name": "tall block", "translation": [0.22, 0.0, 0.3],
             "rotation": [0.0, turn.0, 0.0, turn.1]},
            {"name": "mirror", "translation": [0.1, 0.0, 0.0], "children": [3]},
            {"mesh": 1, "name": "mirrored block", "translation": [0.65, 0.0, 0.45],
             "scale": [-1.0, 0.6, 1.0]},
            {"name": "lamp", "translation": [0.5, 0.9, 0.55],
             "extensions": {"KHR_lights_punctual": {"light": 0}}}
        ],
        "meshes": [
            {"name": "room", "primitives": [primitive_json(0, 0), primitive_json(1, 1), primitive_json(2, 2)]},
            {"name": "block", "primitives": [primitive_json(3, 0)]}
        ],
        "materials": [material([0.75, 0.75, 0.75]), material([0.7, 0.12, 0.1]), material([0.12, 0.6, 0.15])],
        "extensions": {"KHR_lights_punctual": {"lights": [
            {"type": "point", "color": [1.0, 0.85, 0.6], "intensity": 1.0}
        ]}},
        "buffers": [{"uri": "room.bin", "byteLength": binary.len()}],
        "bufferViews": views,
        "accessors": accessors
    });
    std::fs::write(folder.join("room.bin"), &binary).unwrap();
    std::fs::write(
        folder.join("room.gltf"),
        serde_json::to_vec_pretty(&gltf).unwrap(),
    )
    .unwrap();
    let scene = folder.join("scene.toml");
    std::fs::write(
        &scene,
        "mesh = \"room.gltf\"\n[camera]\neye = [0.5, 0.5, 2.0]\ntarget = [0.5, 0.45, 0.0]\nup = [0.0, 1.0, 0.0]\nfov_y = 38.0\nresolution = [160, 160]\n",
    )
    .unwrap();
    scene
}

/// Sponza as real exports are: Bevy's glTF loader spawns
/// `sponza_flat.gltf` (about 66,000 triangles in 19 primitives) and the
/// plugin adopts it; the scene file beside it gives relight the same
/// camera and sun as `scene.toml`. Same bounds as the boxes.
#[test]
fn adopted_sponza_shows_relights_light() {
    let folder = tempfile::tempdir().unwrap();
    let sponza = Path::new(env!("CARGO_MANIFEST_DIR")).join("../../../shared/scenes/sponza");
    let gltf = std::path::absolute(sponza.join("sponza_flat.gltf")).unwrap();
    let text = std::fs::read_to_string(sponza.join("scene.toml")).unwrap();
    assert!(text.contains("mesh = \"mesh.obj\""));
    let path = folder.path().join("scene.toml");
    std::fs::write(
        &path,
        text.replace(
            "mesh = \"mesh.obj\"",
            &format!("mesh = {:?}", gltf.display().to_string()),
        ),
    )
    .unwrap();
    let started = std::time::Instant::now();
    let failures = compare(
        &path,
        &["prm"],
        0,
        Spawning::Adopted {
            relight_shading: true,
        },
        folder.path(),
    );
    println!("took {:?}", started.elapsed());
    assert!(failures.is_empty(), "out of bounds: {failures:?}");
}
