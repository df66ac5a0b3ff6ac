//! The in-memory scene: triangles, Lambertian materials, textures, lights.

use glam::{Quat, Vec2, Vec3};
use relight_core::Rgb;
use std::path::PathBuf;

/// Static triangle geometry. Per-vertex arrays are indexed by `triangles`;
/// every triangle has one material. Struct-of-arrays so the BVH build and the
/// samplers touch only what they need.
#[derive(Clone, Debug, Default)]
pub struct Mesh {
    pub positions: Vec<Vec3>,
    /// Texture coordinates for albedo textures; empty when the file has none.
    pub texcoords: Vec<Vec2>,
    /// A second UV set from the file (lightmap candidate); empty when absent.
    pub lightmap_uvs: Vec<Vec2>,
    pub triangles: Vec<[u32; 3]>,
    pub material_ids: Vec<u32>,
}

impl Mesh {
    #[inline]
    pub fn vertices(&self, triangle: usize) -> [Vec3; 3] {
        let [a, b, c] = self.triangles[triangle];
        [
            self.positions[a as usize],
            self.positions[b as usize],
            self.positions[c as usize],
        ]
    }

    /// The point of `triangle` at `barycentric` (the weights of its second
    /// and third vertices), as ray hits and samples report it.
    #[inline]
    pub fn point_at(&self, triangle: usize, barycentric: Vec2) -> Vec3 {
        let [a, b, c] = self.vertices(triangle);
        a + (b - a) * barycentric.x + (c - a) * barycentric.y
    }

    /// Geometric normal from the counter-clockwise winding (front face).
    #[inline]
    pub fn geometric_normal(&self, triangle: usize) -> Vec3 {
        let [a, b, c] = self.vertices(triangle);
        (b - a).cross(c - a).normalize_or_zero()
    }

    /// Whether `point` lies in front of `triangle` (on its normal's side
    /// of its plane): a light there can light its front.
    #[inline]
    pub fn faces_point(&self, triangle: usize, point: Vec3) -> bool {
        let [corner, ..] = self.vertices(triangle);
        self.geometric_normal(triangle).dot(point - corner) > 0.0
    }

    #[inline]
    pub fn area(&self, triangle: usize) -> f32 {
        let [a, b, c] = self.vertices(triangle);
        0.5 * (b - a).cross(c - a).length()
    }

    pub fn bounds(&self) -> (Vec3, Vec3) {
        self.positions.iter().fold(
            (Vec3::splat(f32::INFINITY), Vec3::splat(f32::NEG_INFINITY)),
            |(lo, hi), p| (lo.min(*p), hi.max(*p)),
        )
    }

    pub fn total_area(&self) -> f64 {
        (0..self.triangles.len()).map(|t| self.area(t) as f64).sum()
    }
}

/// Running sums of triangle areas, for picking triangles in proportion to
/// their area (entry points, sparse points).
#[derive(Clone, Debug, Default)]
pub struct AreaTable {
    cumulative: Vec<f64>,
}

impl AreaTable {
    pub fn new(mesh: &Mesh) -> Self {
        let mut running = 0.0f64;
        let cumulative = (0..mesh.triangles.len())
            .map(|triangle| {
                running += mesh.area(triangle) as f64;
                running
            })
            .collect();
        Self { cumulative }
    }

    /// Running sums of each triangle's area times its weight: with
    /// [`Scene::detail_weights`], picks follow the lightmap's density.
    /// Without weights, [`Self::new`].
    pub fn weighted(mesh: &Mesh, weights: Option<&[f32]>) -> Self {
        let Some(weights) = weights else {
            return Self::new(mesh);
        };
        let mut running = 0.0f64;
        let cumulative = (0..mesh.triangles.len())
            .map(|triangle| {
                running += mesh.area(triangle) as f64 * weights[triangle] as f64;
                running
            })
            .collect();
        Self { cumulative }
    }

    /// Total area (m^2; weighted area for [`Self::weighted`]).
    pub fn total(&self) -> f64 {
        self.cumulative.last().copied().unwrap_or(0.0)
    }

    /// The triangle whose share of the running area holds `target` (in
    /// 0..total); targets at or past the total give the last triangle.
    /// The table must not be empty.
    pub fn triangle_at(&self, target: f64) -> usize {
        self.cumulative
            .partition_point(|&c| c <= target)
            .min(self.cumulative.len() - 1)
    }
}

/// Lambertian material with an optional albedo texture, optional emission and
/// a Blinn-Phong exponent kept for glossy techniques.
#[derive(Clone, Debug)]
pub struct Material {
    pub name: String,
    pub albedo: Rgb,
    /// Index into [`Scene::textures`]; its texels multiply `albedo`.
    pub albedo_texture: Option<u32>,
    /// Emitted radiance in W/(m^2 sr) from the front face.
    pub emission: Rgb,
    pub phong_exponent: f32,
}

impl Default for Material {
    fn default() -> Self {
        Self {
            name: "default".into(),
            albedo: Rgb::splat(0.5),
            albedo_texture: None,
            emission: Rgb::ZERO,
            phong_exponent: 1.0,
        }
    }
}

/// Linear-RGB texture, decoded from sRGB at load time, sampled with wrap.
#[derive(Clone, Debug)]
pub struct Texture {
    pub name: String,
    pub width: u32,
    pub height: u32,
    pub texels: Vec<Rgb>,
}

impl Texture {
    /// Bilinear lookup with repeat wrapping; v = 0 is the top row (glTF/OBJ
    /// loaders flip OBJ's bottom-up v so that both agree).
    pub fn sample(&self, uv: Vec2) -> Rgb {
        let x = uv.x.rem_euclid(1.0) * self.width as f32 - 0.5;
        let y = uv.y.rem_euclid(1.0) * self.height as f32 - 0.5;
        let x0 = crate::atlas::floor_small(x);
        let y0 = crate::atlas::floor_small(y);
        let fx = x - x0;
        let fy = y - y0;
        let texel = |ix: i64, iy: i64| {
            let ix = ix.rem_euclid(self.width as i64) as usize;
            let iy = iy.rem_euclid(self.height as i64) as usize;
            self.texels[iy * self.width as usize + ix]
        };
        let (x0, y0) = (x0 as i64, y0 as i64);
        let top = texel(x0, y0).lerp(texel(x0 + 1, y0), fx);
        let bottom = texel(x0, y0 + 1).lerp(texel(x0 + 1, y0 + 1), fx);
        top.lerp(bottom, fy)
    }

    pub fn average(&self) -> Rgb {
        let sum: Vec3 = self.texels.iter().copied().sum();
        sum / self.texels.len().max(1) as f32
    }
}

/// A light that may move from frame to frame. Emissive triangles are not
/// here: they are static geometry (see [`Scene::emissive_triangles`]).
#[derive(Clone, Debug, PartialEq)]
pub enum Light {
    /// Radiant intensity in W/sr per channel.
    Point { position: Vec3, intensity: Rgb },
    /// `direction` is where the light travels; `irradiance` on a surface facing it.
    Directional { direction: Vec3, irradiance: Rgb },
    /// Point light restricted to a cone: full inside `inner_angle`, smoothstep
    /// to zero at `outer_angle` (half-angles in radians).
    Spot {
        position: Vec3,
        direction: Vec3,
        intensity: Rgb,
        inner_angle: f32,
        outer_angle: f32,
    },
}

impl Light {
    /// Where a point or spot light stands; `None` for a sun.
    pub fn position(&self) -> Option<Vec3> {
        match *self {
            Light::Point { position, .. } | Light::Spot { position, .. } => Some(position),
            Light::Directional { .. } => None,
        }
    }

    /// The light turned by `rotation` about `centre`: positions move,
    /// directions turn, intensities stay (benchmark and study orbits).
    pub fn rotated_about(&self, centre: Vec3, rotation: Quat) -> Light {
        let around = |position: Vec3| centre + rotation * (position - centre);
        match *self {
            Light::Point {
                position,
                intensity,
            } => Light::Point {
                position: around(position),
                intensity,
            },
            Light::Spot {
                position,
                direction,
                intensity,
                inner_angle,
                outer_angle,
            } => Light::Spot {
                position: around(position),
                direction: rotation * direction,
                intensity,
                inner_angle,
                outer_angle,
            },
            Light::Directional {
                direction,
                irradiance,
            } => Light::Directional {
                direction: rotation * direction,
                irradiance,
            },
        }
    }
}

/// Pinhole camera, gluLookAt convention: right = normalize(forward x up).
#[derive(Clone, Debug, PartialEq)]
pub struct Camera {
    pub eye: Vec3,
    pub target: Vec3,
    pub up: Vec3,
    pub fov_y_degrees: f32,
    pub resolution: [u32; 2],
}

impl Default for Camera {
    fn default() -> Self {
        Self {
            eye: Vec3::new(0.0, 0.0, 5.0),
            target: Vec3::ZERO,
            up: Vec3::Y,
            fov_y_degrees: 45.0,
            resolution: [256, 256],
        }
    }
}

/// Constant radiance seen by rays that leave the scene.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Environment {
    pub radiance: Rgb,
}

/// Everything a technique needs: static geometry with materials, the current
/// lights, camera and environment.
#[derive(Clone, Debug, Default)]
pub struct Scene {
    pub mesh: Mesh,
    pub materials: Vec<Material>,
    pub textures: Vec<Texture>,
    pub lights: Vec<Light>,
    pub camera: Camera,
    pub environment: Environment,
    /// Scene file this came from, for messages.
    pub source: PathBuf,
    /// Non-fatal problems met while loading (missing MTL, dropped triangles).
    pub warnings: Vec<String>,
    /// Raw per-technique tables of the scene file (`[srp]`, `[[dynamic]]`,
    /// ...), parsed by the technique that owns them.
    pub technique_sections: std::collections::BTreeMap<String, toml::Value>,
    /// Where each glTF mesh primitive went (glTF mesh files only): lets an
    /// engine that loads the same file itself find relight's triangles, and
    /// so its lightmap atlas, for each of its meshes.
    pub gltf_primitives: Vec<GltfPrimitive>,
    /// Where the lightmap spends its texels (`[lightmap]` of the scene
    /// file; see [`crate::detail`]). The loader resolves it to a box or to
    /// uniform; a scene built in code may keep `Automatic`, which each use
    /// finds from the mesh.
    pub lightmap_layout: crate::detail::LightmapLayout,
    /// Edges where the lightmap's charts end, as pairs of vertex positions
    /// (bit for bit the mesh's): the lines walls stand on, where the
    /// loader cut the surfaces under them ([`crate::seams`]). Empty for a
    /// scene built in code.
    pub lightmap_seams: Vec<[Vec3; 2]>,
}

/// One triangle-list primitive of a glTF mesh as one node places it.
#[derive(Clone, Debug, PartialEq)]
pub struct GltfPrimitive {
    /// The glTF node, mesh and primitive indices, as in the file.
    pub node: u32,
    pub mesh: u32,
    pub primitive: u32,
    /// The node's world transform: the file's scene space, which is
    /// relight's.
    pub world: glam::Mat4,
    /// The world transform mirrors (negative determinant): relight swapped
    /// the second and third corners of each triangle to keep the front face
    /// counter-clockwise.
    pub mirrored: bool,
    /// For each triangle of the primitive, in the file's index order, the
    /// scene triangle it became, or `None` where it was dropped as
    /// degenerate.
    pub triangles: Vec<Option<u32>>,
}

impl Scene {
    #[inline]
    pub fn material_of(&self, triangle: usize) -> &Material {
        &self.materials[self.mesh.material_ids[triangle] as usize]
    }

    /// Albedo at barycentric (b1, b2) on `triangle`, texture included.
    pub fn albedo_at(&self, triangle: usize, barycentric: Vec2) -> Rgb {
        let material = self.material_of(triangle);
        match material.albedo_texture {
            Some(texture) if !self.mesh.texcoords.is_empty() => {
                let [a, b, c] = self.mesh.triangles[triangle];
                let uv = self.mesh.texcoords[a as usize] * (1.0 - barycentric.x - barycentric.y)
                    + self.mesh.texcoords[b as usize] * barycentric.x
                    + self.mesh.texcoords[c as usize] * barycentric.y;
                material.albedo * self.textures[texture as usize].sample(uv)
            }
            _ => material.albedo,
        }
    }

    /// Triangles whose material emits, in index order.
    pub fn emissive_triangles(&self) -> Vec<u32> {
        (0..self.mesh.triangles.len() as u32)
            .filter(|&t| self.material_of(t as usize).emission.max_element() > 0.0)
            .collect()
    }
}
