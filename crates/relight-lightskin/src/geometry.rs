//! What the light sees: the static scene's BVH and, when the scene has
//! moving meshes, this frame's BVH over them; the nearer hit wins.

use crate::dynamic::DynamicWorld;
use glam::Vec3;
use relight_core::Rgb;
use relight_scene::Scene;
use relight_trace::direct::Emitters;
use relight_trace::{Bvh, Ray};

/// The first surface a ray meets.
#[derive(Clone, Copy, Debug)]
pub struct SurfaceHit {
    pub position: Vec3,
    /// Geometric normal of the hit triangle's front face.
    pub normal: Vec3,
    pub albedo: Rgb,
    pub distance: f32,
    /// Triangle and barycentric coordinates of a hit on the static mesh
    /// (`None` on a moving mesh).
    pub site: Option<(u32, glam::Vec2)>,
}

pub struct Geometry<'a> {
    pub scene: &'a Scene,
    pub bvh: &'a Bvh,
    /// The scene's emissive triangles (built once with the scene).
    pub emitters: &'a Emitters,
    pub ray_epsilon: f32,
    pub dynamic: Option<&'a DynamicWorld>,
    /// The scene's detail region and margin when its lightmap coarsens
    /// outside them ([`Scene::detail_bounds`]), else `None`.
    pub content: Option<(Vec3, Vec3)>,
}

impl Geometry<'_> {
    /// First hit along a unit `direction`.
    pub fn first_hit(&self, origin: Vec3, direction: Vec3) -> Option<SurfaceHit> {
        let mut ray = Ray {
            origin,
            direction,
            t_max: f32::INFINITY,
        };
        let mut nearest = self.bvh.intersect(&ray).map(|hit| {
            let triangle = hit.triangle as usize;
            SurfaceHit {
                position: origin + direction * hit.t,
                normal: self.scene.mesh.geometric_normal(triangle),
                albedo: self.scene.albedo_at(triangle, hit.barycentric),
                distance: hit.t,
                site: Some((hit.triangle, hit.barycentric)),
            }
        });
        if let Some(world) = self.dynamic {
            if let Some(hit) = nearest {
                ray.t_max = hit.distance;
            }
            if let Some(hit) = world.bvh.intersect(&ray) {
                nearest = Some(SurfaceHit {
                    position: origin + direction * hit.t,
                    normal: world.triangle_normals[hit.triangle as usize],
                    albedo: world.materials[world.material_ids[hit.triangle as usize] as usize]
                        .albedo,
                    distance: hit.t,
                    site: None,
                });
            }
        }
        nearest
    }

    /// Centre and radius of a sphere around everything that can be lit.
    pub fn bounding_sphere(&self) -> (Vec3, f32) {
        self.sphere_with_moving_meshes(self.bvh.bounds())
    }

    /// What a directional light's map covers: the centre and radius of a
    /// sphere around the scene's content and moving meshes, and how far
    /// back along the light its rays start, past everything that can cast
    /// a shadow on it. Without content bounds the sphere is the whole
    /// scene's; with them, a ground plane 200 m across no longer spreads
    /// the map's texels (and VALs) over land outside the building.
    pub fn directional_extent(&self) -> (Vec3, f32, f32) {
        let (centre, radius) = self.bounding_sphere();
        match self.content {
            None => (centre, radius, 2.0 * radius),
            Some(content) => {
                let (content_centre, content_radius) = self.sphere_with_moving_meshes(content);
                let back = content_centre.distance(centre) + 2.0 * radius;
                (content_centre, content_radius, back)
            }
        }
    }

    fn sphere_with_moving_meshes(&self, (mut low, mut high): (Vec3, Vec3)) -> (Vec3, f32) {
        if let Some(world) = self.dynamic {
            if !world.triangle_normals.is_empty() {
                let (dynamic_low, dynamic_high) = world.bvh.bounds();
                low = low.min(dynamic_low);
                high = high.max(dynamic_high);
            }
        }
        ((low + high) * 0.5, ((high - low) * 0.5).length().max(1e-3))
    }
}
