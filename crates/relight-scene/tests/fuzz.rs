//! Randomly mutated copies of valid scene files must never make a loader
//! panic: every outcome has to be `Ok` or a `SceneError`.
//!
//! Mutations are byte flips, truncation, insertion of random bytes or of
//! tokens that often break parsers (huge numbers, nan, separators), line
//! duplication and line deletion, driven by a seeded PCG so a failure is
//! reproducible from the seed printed in the message.

mod common;

use common::*;
use relight_core::Pcg32;
use relight_scene::load_scene;
use std::panic::{catch_unwind, AssertUnwindSafe};

const TOKENS: [&[u8]; 16] = [
    b"-",
    b"nan",
    b"inf",
    b"1e39",
    b"99999999999",
    b"-1",
    b"0",
    b"/",
    b"..",
    b"\"",
    b"{",
    b"]",
    b",",
    b"\n",
    b"4294967295",
    b"f 1 2 3\n",
];

fn mutate(original: &[u8], rng: &mut Pcg32) -> Vec<u8> {
    let mut bytes = original.to_vec();
    let edits = 1 + rng.next_u32() % 4;
    for _ in 0..edits {
        let position = if bytes.is_empty() {
            0
        } else {
            rng.next_u32() as usize % bytes.len()
        };
        match rng.next_u32() % 6 {
            0 if !bytes.is_empty() => bytes[position] = rng.next_u32() as u8,
            1 => bytes.truncate(position),
            2 => {
                let token = TOKENS[rng.next_u32() as usize % TOKENS.len()];
                bytes.splice(position..position, token.iter().copied());
            }
            3 => {
                let random: Vec<u8> = (0..1 + rng.next_u32() % 8)
                    .map(|_| rng.next_u32() as u8)
                    .collect();
                bytes.splice(position..position, random);
            }
            4 | 5 => {
                let lines: Vec<&[u8]> = bytes.split_inclusive(|&b| b == b'\n').collect();
                if lines.is_empty() {
                    continue;
                }
                let line = rng.next_u32() as usize % lines.len();
                let mut rebuilt: Vec<u8> = Vec::with_capacity(bytes.len() + 64);
                for (index, text) in lines.iter().enumerate() {
                    let duplicate = rng.next_u32() % 6 == 4;
                    if index == line && duplicate {
                        rebuilt.extend(*text);
                        rebuilt.extend(*text);
                    } else if index != line || !duplicate && rng.next_u32().is_multiple_of(2) {
                        rebuilt.extend(*text);
                    }
                }
                bytes = rebuilt;
            }
            _ => bytes.push(rng.next_u32() as u8),
        }
    }
    bytes
}

const OBJ: &str = "\
# fuzz fixture
mtllib mesh.mtl
o first
v 0 0 0
v 1 0 0 1
v 1 1 0 0.5 0.5 0.5
v 0 1 0
vt 0 0
vt 1 0
vt 1 1 0
vn 0 0 1
g second
usemtl white
f 1/1/1 2/2/1 3/3/1
f -4/-3 -2/-1 -1/-1
usemtl lamp
f 1//1 3//1 4//1
l 1 2
f 1 2 3 4
";

const MTL: &str = "\
newmtl white
Kd 0.8 0.7 0.6
Ns 10
map_Kd tex.png
newmtl lamp
Kd 0.5
Ke 1 2 3
illum 2
";

const TOML: &str = r#"mesh = "mesh.obj"
[camera]
eye = [0.278, 0.273, -0.8]
target = [0.278, 0.273, 0.0]
up = [0.0, 1.0, 0.0]
fov_y = 39.3077
resolution = [256, 256]
[[lights]]
kind = "point"
position = [0.4, 0.45, 0.15]
intensity = [0.3, 0.28, 0.25]
[[lights]]
kind = "directional"
direction = [0.3, -1.0, 0.2]
irradiance = [3.0, 2.9, 2.7]
[[lights]]
kind = "spot"
position = [0, 2, 0]
direction = [0, -1, 0]
intensity = [5, 5, 5]
inner_angle = 20
outer_angle = 30
[environment]
radiance = [0.0, 0.0, 0.0]
[srp]
probes = 4
"#;

/// Which file of the fixture gets mutated.
#[derive(Clone, Copy, Debug)]
enum Target {
    Obj,
    Mtl,
    Toml,
    Gltf,
    Glb,
    Png,
}

struct Fixture {
    dir: TempDir,
    png: Vec<u8>,
    gltf: Vec<u8>,
    glb: Vec<u8>,
}

impl Fixture {
    /// Writes every valid file once; each case then rewrites only the file
    /// it mutates (file creation is the slow part of this test).
    fn new() -> Self {
        let png = png_rows(2, &[[200, 100, 50], [10, 20, 30]]);
        let mut json = quad_gltf(Some("quad.bin"));
        json["images"] = serde_json::json!([{"uri": "tex.png"}]);
        json["textures"] = serde_json::json!([{"source": 0}]);
        json["materials"][0]["pbrMetallicRoughness"]["baseColorTexture"] =
            serde_json::json!({"index": 0});
        let gltf = serde_json::to_vec_pretty(&json).unwrap();
        let mut binary = quad_binary();
        let image_offset = binary.len();
        binary.extend(&png);
        let mut glb_json = quad_gltf(None);
        glb_json["buffers"][0]["byteLength"] = serde_json::json!(binary.len());
        glb_json["bufferViews"].as_array_mut().unwrap().push(
            serde_json::json!({"buffer": 0, "byteOffset": image_offset, "byteLength": png.len()}),
        );
        glb_json["images"] = serde_json::json!([{"bufferView": 4, "mimeType": "image/png"}]);
        glb_json["textures"] = serde_json::json!([{"source": 0}]);
        glb_json["materials"][0]["pbrMetallicRoughness"]["baseColorTexture"] =
            serde_json::json!({"index": 0});
        let glb = to_glb(&glb_json, &binary);
        let fixture = Self {
            dir: TempDir::new("fuzz"),
            png,
            gltf,
            glb,
        };
        for target in [
            Target::Obj,
            Target::Mtl,
            Target::Toml,
            Target::Gltf,
            Target::Glb,
            Target::Png,
        ] {
            fixture.restore(target);
        }
        fixture.dir.write("quad.bin", quad_binary());
        fixture
            .dir
            .write("scene-gltf.toml", TOML.replace("mesh.obj", "quad.gltf"));
        fixture
            .dir
            .write("scene-glb.toml", TOML.replace("mesh.obj", "quad.glb"));
        fixture
    }

    fn file(target: Target) -> &'static str {
        match target {
            Target::Obj => "mesh.obj",
            Target::Mtl => "mesh.mtl",
            Target::Toml => "scene.toml",
            Target::Gltf => "quad.gltf",
            Target::Glb => "quad.glb",
            Target::Png => "tex.png",
        }
    }

    fn original(&self, target: Target) -> &[u8] {
        match target {
            Target::Obj => OBJ.as_bytes(),
            Target::Mtl => MTL.as_bytes(),
            Target::Toml => TOML.as_bytes(),
            Target::Gltf => &self.gltf,
            Target::Glb => &self.glb,
            Target::Png => &self.png,
        }
    }

    fn restore(&self, target: Target) {
        self.dir.write(Self::file(target), self.original(target));
    }

    /// Writes `target` mutated and returns the scene file that reads it.
    fn write_mutated(&self, target: Target, rng: &mut Pcg32) -> std::path::PathBuf {
        self.dir
            .write(Self::file(target), mutate(self.original(target), rng));
        self.scene(target)
    }

    fn scene(&self, target: Target) -> std::path::PathBuf {
        self.dir.path(match target {
            Target::Gltf => "scene-gltf.toml",
            Target::Glb => "scene-glb.toml",
            _ => "scene.toml",
        })
    }
}

#[test]
fn unmutated_fixtures_load() {
    let fixture = Fixture::new();
    for (target, lights) in [(Target::Obj, 3), (Target::Gltf, 5), (Target::Glb, 5)] {
        let scene = load_scene(&fixture.scene(target))
            .unwrap_or_else(|error| panic!("{target:?}: {error}"));
        assert_eq!(scene.lights.len(), lights, "{target:?}");
        assert_eq!(scene.textures.len(), 1, "{target:?}");
    }
}

#[test]
fn mutated_files_never_panic() {
    let fixture = Fixture::new();
    let plan = [
        (Target::Obj, 900),
        (Target::Mtl, 400),
        (Target::Toml, 700),
        (Target::Gltf, 700),
        (Target::Glb, 700),
        (Target::Png, 200),
    ];
    let mut panics: Vec<(Target, u64)> = Vec::new();
    let mut outcomes = [0usize; 2];
    for (target, cases) in plan {
        for seed in 0..cases {
            let mut rng = Pcg32::new(seed, target as u64);
            let path = fixture.write_mutated(target, &mut rng);
            match catch_unwind(AssertUnwindSafe(|| load_scene(&path))) {
                Ok(result) => outcomes[result.is_ok() as usize] += 1,
                Err(_) => panics.push((target, seed)),
            }
        }
        fixture.restore(target);
    }
    assert!(
        panics.is_empty(),
        "{} mutated inputs panicked; first: {:?} seed {} (reproduce with Pcg32::new(seed, target as u64)); all: {panics:?}",
        panics.len(),
        panics[0].0,
        panics[0].1
    );
    // Both outcomes must occur, or the mutations test nothing.
    assert!(
        outcomes[0] > 100 && outcomes[1] > 30,
        "errors/successes: {outcomes:?}"
    );
}
