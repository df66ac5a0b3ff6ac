//! Indirect light at points in space from the light leaving the static
//! surfaces around them: a final gather over a fixed set of
//! cosine-distributed rays. A technique whose own data lives only on the
//! lightmap (PRM's panes) answers `indirect_irradiance_in_space` this way:
//! each ray's hit reflects the direct light there plus the technique's
//! indirect light there, so the answer has every bounce the lightmap has,
//! and a wall between a light and the point stops that light.

use crate::{SceneContext, SurfacePoint};
use glam::Vec3;
use relight_core::sampling::orthonormal_basis;
use relight_core::Rgb;
use relight_scene::Light;
use relight_trace::Ray;

/// A fixed set of gather directions about +Z, cosine-distributed and
/// stratified (a Hammersley set), shared by every query: neighbouring
/// points see the same pattern, so the answer varies smoothly in space
/// and is the same on every run.
#[derive(Clone, Debug, PartialEq)]
pub struct SurfaceGather {
    local_directions: Vec<Vec3>,
}

impl SurfaceGather {
    pub fn new(rays: u32) -> Self {
        Self {
            local_directions: crate::final_gather::gather_directions(rays),
        }
    }

    pub fn rays(&self) -> usize {
        self.local_directions.len()
    }

    /// Indirect irradiance at `position` on the side `normal` faces under
    /// `lights`: the mean over the rays of the hit's albedo times its
    /// direct irradiance plus `indirect_at` the hit (front faces; the
    /// lightmap holds no back sides, so a back-face hit reflects its direct
    /// light alone). Emission seen along a ray is direct light, not counted.
    pub fn irradiance(
        &self,
        context: &SceneContext,
        lights: &[Light],
        position: Vec3,
        normal: Vec3,
        indirect_at: impl Fn(&SurfacePoint) -> Rgb,
    ) -> Rgb {
        let scene = &context.scene;
        let mut direct = context.direct();
        // The rays average the area lights' and the sky's noise: one sample
        // per hit is as good as many per hit for the same cost.
        direct.settings.area_light_samples = 1;
        direct.settings.environment_samples = 1;
        let (tangent, bitangent) = orthonormal_basis(normal);
        let origin = position + normal * direct.ray_epsilon;
        // The key decorrelates area-light samples between points.
        let point_key = position.to_array().iter().fold(0u64, |key, value| {
            key.rotate_left(21) ^ value.to_bits() as u64
        });
        let mut sum = Rgb::ZERO;
        for (index, local) in self.local_directions.iter().enumerate() {
            let direction = tangent * local.x + bitangent * local.y + normal * local.z;
            let ray = Ray {
                origin,
                direction,
                t_max: f32::INFINITY,
            };
            let Some(hit) = context.bvh.intersect(&ray) else {
                continue;
            };
            let triangle = hit.triangle as usize;
            let front = scene.mesh.geometric_normal(triangle);
            let seen_from_front = front.dot(direction) < 0.0;
            let hit_normal = if seen_from_front { front } else { -front };
            let hit_position = scene.mesh.point_at(triangle, hit.barycentric);
            let mut irradiance = direct.irradiance(
                lights,
                hit_position,
                hit_normal,
                point_key ^ ((index as u64) << 48),
            );
            if seen_from_front {
                irradiance += indirect_at(&SurfacePoint {
                    position: hit_position,
                    normal: front,
                    triangle: hit.triangle,
                    barycentric: hit.barycentric,
                });
            }
            sum += scene.albedo_at(triangle, hit.barycentric) * irradiance;
        }
        // pdf cos / pi against the integrand L cos with L = albedo E / pi.
        sum / self.local_directions.len() as f32
    }
}
