//! Minimal hand-written FFI to Embree 3 (Debian `libembree-dev`), used only
//! as a test oracle and a speed reference for [`super::Bvh`]; behind the
//! `embree` feature so normal builds need no C library.
//!
//! Only the handful of calls needed for one static triangle mesh are bound;
//! struct layouts follow `embree3/rtcore_ray.h` and `rtcore_common.h` of
//! Embree 3.13 with `RTC_MAX_INSTANCE_LEVEL_COUNT == 1` and
//! `RTC_MIN_WIDTH == 0`, as the Debian package is configured.

use super::{Hit, Ray};
use glam::{Vec2, Vec3};
use rayon::prelude::*;
use std::ffi::c_void;
use std::os::raw::{c_char, c_uint};

type RtcDevice = *mut c_void;
type RtcScene = *mut c_void;
type RtcGeometry = *mut c_void;

const RTC_GEOMETRY_TYPE_TRIANGLE: c_uint = 0;
const RTC_BUFFER_TYPE_INDEX: c_uint = 0;
const RTC_BUFFER_TYPE_VERTEX: c_uint = 1;
const RTC_FORMAT_UINT3: c_uint = 0x5003;
const RTC_FORMAT_FLOAT3: c_uint = 0x9003;
const RTC_BUILD_QUALITY_MEDIUM: c_uint = 1;
const RTC_INVALID_GEOMETRY_ID: c_uint = u32::MAX;

#[repr(C, align(16))]
#[derive(Clone, Copy)]
struct RtcRay {
    org_x: f32,
    org_y: f32,
    org_z: f32,
    tnear: f32,
    dir_x: f32,
    dir_y: f32,
    dir_z: f32,
    time: f32,
    tfar: f32,
    mask: c_uint,
    id: c_uint,
    flags: c_uint,
}

#[repr(C, align(16))]
#[derive(Clone, Copy)]
struct RtcHit {
    ng_x: f32,
    ng_y: f32,
    ng_z: f32,
    u: f32,
    v: f32,
    prim_id: c_uint,
    geom_id: c_uint,
    inst_id: [c_uint; 1],
}

#[repr(C)]
#[derive(Clone, Copy)]
struct RtcRayHit {
    ray: RtcRay,
    hit: RtcHit,
}

#[repr(C)]
struct RtcIntersectContext {
    flags: c_uint,
    filter: *const c_void,
    inst_id: [c_uint; 1],
}

#[link(name = "embree3")]
extern "C" {
    fn rtcNewDevice(config: *const c_char) -> RtcDevice;
    fn rtcReleaseDevice(device: RtcDevice);
    fn rtcGetDeviceError(device: RtcDevice) -> c_uint;
    fn rtcNewScene(device: RtcDevice) -> RtcScene;
    fn rtcSetSceneBuildQuality(scene: RtcScene, quality: c_uint);
    fn rtcReleaseScene(scene: RtcScene);
    fn rtcNewGeometry(device: RtcDevice, kind: c_uint) -> RtcGeometry;
    fn rtcSetNewGeometryBuffer(
        geometry: RtcGeometry,
        kind: c_uint,
        slot: c_uint,
        format: c_uint,
        byte_stride: usize,
        item_count: usize,
    ) -> *mut c_void;
    fn rtcCommitGeometry(geometry: RtcGeometry);
    fn rtcAttachGeometry(scene: RtcScene, geometry: RtcGeometry) -> c_uint;
    fn rtcReleaseGeometry(geometry: RtcGeometry);
    fn rtcCommitScene(scene: RtcScene);
    fn rtcIntersect1(scene: RtcScene, context: *mut RtcIntersectContext, ray_hit: *mut RtcRayHit);
    fn rtcOccluded1(scene: RtcScene, context: *mut RtcIntersectContext, ray: *mut RtcRay);
}

/// One Embree scene holding one triangle mesh.
pub struct EmbreeScene {
    device: RtcDevice,
    scene: RtcScene,
}

// SAFETY: Embree scenes are immutable after commit and documented as safe
// to query from any number of threads at once.
unsafe impl Send for EmbreeScene {}
unsafe impl Sync for EmbreeScene {}

impl Drop for EmbreeScene {
    fn drop(&mut self) {
        // SAFETY: both handles were created by `build` and are released once.
        unsafe {
            rtcReleaseScene(self.scene);
            rtcReleaseDevice(self.device);
        }
    }
}

fn context() -> RtcIntersectContext {
    // What the header's inline rtcInitIntersectContext does.
    RtcIntersectContext {
        flags: 0,
        filter: std::ptr::null(),
        inst_id: [RTC_INVALID_GEOMETRY_ID],
    }
}

fn to_embree_ray(ray: &Ray) -> RtcRay {
    RtcRay {
        org_x: ray.origin.x,
        org_y: ray.origin.y,
        org_z: ray.origin.z,
        tnear: 0.0,
        dir_x: ray.direction.x,
        dir_y: ray.direction.y,
        dir_z: ray.direction.z,
        time: 0.0,
        tfar: ray.t_max,
        mask: u32::MAX,
        id: 0,
        flags: 0,
    }
}

impl EmbreeScene {
    /// Builds with Embree's high-quality (SAH) builder on its own threads.
    ///
    /// # Panics
    /// If Embree reports an error (e.g. the device cannot be created).
    pub fn build(positions: &[Vec3], triangles: &[[u32; 3]]) -> EmbreeScene {
        // SAFETY: plain C API use; buffers are sized by Embree to the counts
        // passed and filled within those bounds.
        unsafe {
            let device = rtcNewDevice(std::ptr::null());
            assert!(!device.is_null(), "rtcNewDevice failed");
            let scene = rtcNewScene(device);
            rtcSetSceneBuildQuality(scene, RTC_BUILD_QUALITY_MEDIUM);
            if !triangles.is_empty() {
                let geometry = rtcNewGeometry(device, RTC_GEOMETRY_TYPE_TRIANGLE);
                // Buffers from rtcSetNewGeometryBuffer carry the tail padding
                // Embree's 16-byte vertex loads need.
                let vertices = rtcSetNewGeometryBuffer(
                    geometry,
                    RTC_BUFFER_TYPE_VERTEX,
                    0,
                    RTC_FORMAT_FLOAT3,
                    12,
                    positions.len().max(1),
                ) as *mut f32;
                for (index, position) in positions.iter().enumerate() {
                    std::ptr::copy_nonoverlapping(
                        position.to_array().as_ptr(),
                        vertices.add(3 * index),
                        3,
                    );
                }
                let indices = rtcSetNewGeometryBuffer(
                    geometry,
                    RTC_BUFFER_TYPE_INDEX,
                    0,
                    RTC_FORMAT_UINT3,
                    12,
                    triangles.len(),
                ) as *mut u32;
                std::ptr::copy_nonoverlapping(
                    triangles.as_ptr() as *const u32,
                    indices,
                    3 * triangles.len(),
                );
                rtcCommitGeometry(geometry);
                rtcAttachGeometry(scene, geometry);
                rtcReleaseGeometry(geometry);
            }
            rtcCommitScene(scene);
            let error = rtcGetDeviceError(device);
            assert_eq!(error, 0, "Embree error {error}");
            EmbreeScene { device, scene }
        }
    }

    pub fn intersect(&self, ray: &Ray) -> Option<Hit> {
        let mut ray_hit = RtcRayHit {
            ray: to_embree_ray(ray),
            hit: RtcHit {
                ng_x: 0.0,
                ng_y: 0.0,
                ng_z: 0.0,
                u: 0.0,
                v: 0.0,
                prim_id: RTC_INVALID_GEOMETRY_ID,
                geom_id: RTC_INVALID_GEOMETRY_ID,
                inst_id: [RTC_INVALID_GEOMETRY_ID],
            },
        };
        let mut context = context();
        // SAFETY: the scene is committed; both structs live for the call.
        unsafe { rtcIntersect1(self.scene, &mut context, &mut ray_hit) };
        (ray_hit.hit.geom_id != RTC_INVALID_GEOMETRY_ID).then(|| Hit {
            t: ray_hit.ray.tfar,
            triangle: ray_hit.hit.prim_id,
            barycentric: Vec2::new(ray_hit.hit.u, ray_hit.hit.v),
        })
    }

    pub fn occluded(&self, ray: &Ray) -> bool {
        let mut embree_ray = to_embree_ray(ray);
        let mut context = context();
        // SAFETY: as in `intersect`.
        unsafe { rtcOccluded1(self.scene, &mut context, &mut embree_ray) };
        // Embree marks an occluded ray by setting tfar to -inf.
        embree_ray.tfar < 0.0
    }

    pub fn intersect_batch(&self, rays: &[Ray], hits: &mut [Option<Hit>]) {
        assert_eq!(rays.len(), hits.len(), "one hit slot per ray");
        rays.par_chunks(256)
            .zip(hits.par_chunks_mut(256))
            .for_each(|(ray_chunk, hit_chunk)| {
                for (ray, hit) in ray_chunk.iter().zip(hit_chunk) {
                    *hit = self.intersect(ray);
                }
            });
    }

    pub fn occluded_batch(&self, rays: &[Ray], occluded: &mut [bool]) {
        assert_eq!(rays.len(), occluded.len(), "one result slot per ray");
        rays.par_chunks(256)
            .zip(occluded.par_chunks_mut(256))
            .for_each(|(ray_chunk, result_chunk)| {
                for (ray, result) in ray_chunk.iter().zip(result_chunk) {
                    *result = self.occluded(ray);
                }
            });
    }
}
