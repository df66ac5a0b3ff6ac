//! Ray-throughput benchmark on the shared test scenes:
//! `cargo bench -p relight-trace --bench raybench [--features embree]`.
//! `RAYBENCH_RAYS` (default 1,000,000) and `RAYBENCH_REPEATS` (default 5)
//! override the sizes; scenes that are missing are skipped.
//! `RAYBENCH_CPU_TIME=1` instead traces single-threaded and reports thread
//! CPU time per ray, which stays comparable while other processes load the
//! machine (used for A/B tuning of the traversal), and the process CPU time
//! of a build (all threads together).

use glam::Vec3;
use relight_trace::bvh::{Bvh, Ray};
use relight_trace::raybench::{self, RaySets};

#[cfg(all(target_os = "linux", target_pointer_width = "64"))]
#[repr(C)]
struct Timespec {
    seconds: i64,
    nanoseconds: i64,
}

#[cfg(all(target_os = "linux", target_pointer_width = "64"))]
extern "C" {
    fn clock_gettime(clock: i32, time: *mut Timespec) -> i32;
}

/// Seconds on a Linux CPU-time clock.
#[cfg(all(target_os = "linux", target_pointer_width = "64"))]
fn clock_seconds(clock: i32) -> f64 {
    let mut time = Timespec {
        seconds: 0,
        nanoseconds: 0,
    };
    // SAFETY: clock_gettime only writes the struct it is given.
    unsafe { clock_gettime(clock, &mut time) };
    time.seconds as f64 + time.nanoseconds as f64 * 1e-9
}

/// CPU time of the calling thread (Linux CLOCK_THREAD_CPUTIME_ID) in seconds.
#[cfg(all(target_os = "linux", target_pointer_width = "64"))]
fn thread_cpu_seconds() -> f64 {
    clock_seconds(3)
}

/// CPU time of the whole process (all threads, CLOCK_PROCESS_CPUTIME_ID) in
/// seconds: the work a parallel build does, comparable under load.
#[cfg(all(target_os = "linux", target_pointer_width = "64"))]
fn process_cpu_seconds() -> f64 {
    clock_seconds(2)
}

#[cfg(not(all(target_os = "linux", target_pointer_width = "64")))]
fn process_cpu_seconds() -> f64 {
    thread_cpu_seconds()
}

/// Elsewhere wall time stands in for CPU time.
#[cfg(not(all(target_os = "linux", target_pointer_width = "64")))]
fn thread_cpu_seconds() -> f64 {
    use std::sync::OnceLock;
    static START: OnceLock<std::time::Instant> = OnceLock::new();
    START
        .get_or_init(std::time::Instant::now)
        .elapsed()
        .as_secs_f64()
}

/// Minimum over `repeats` of thread CPU nanoseconds per ray.
fn cpu_nanoseconds_per_ray(
    rays: &[Ray],
    repeats: usize,
    mut trace: impl FnMut(&Ray) -> bool,
) -> f64 {
    (0..repeats.max(1))
        .map(|_| {
            let start = thread_cpu_seconds();
            let hits = rays.iter().filter(|ray| trace(ray)).count();
            std::hint::black_box(hits);
            (thread_cpu_seconds() - start) * 1e9 / rays.len() as f64
        })
        .fold(f64::INFINITY, f64::min)
}

fn cpu_time_report(
    positions: &[Vec3],
    triangles: &[[u32; 3]],
    light: Vec3,
    ray_count: usize,
    repeats: usize,
) {
    let build_cpu_ms = (0..repeats.max(1))
        .map(|_| {
            let start = process_cpu_seconds();
            std::hint::black_box(Bvh::build(positions, triangles));
            (process_cpu_seconds() - start) * 1e3
        })
        .fold(f64::INFINITY, f64::min);
    println!("build CPU ms (all threads): {build_cpu_ms:.1}");
    let bvh = Bvh::build(positions, triangles);
    let rays = RaySets::generate(positions, triangles, light, ray_count, 1);
    let occlusion = rays.diffuse_occlusion();
    let closest =
        cpu_nanoseconds_per_ray(&rays.diffuse, repeats, |ray| bvh.intersect(ray).is_some());
    let occluded = cpu_nanoseconds_per_ray(&occlusion, repeats, |ray| bvh.occluded(ray));
    let shadow = cpu_nanoseconds_per_ray(&rays.shadow, repeats, |ray| bvh.occluded(ray));
    println!("single thread CPU ns/ray: closest {closest:.0}, occlusion {occluded:.0}, shadow {shadow:.0}");
    #[cfg(feature = "embree")]
    {
        let embree = relight_trace::bvh::EmbreeScene::build(positions, triangles);
        let closest = cpu_nanoseconds_per_ray(&rays.diffuse, repeats, |ray| {
            embree.intersect(ray).is_some()
        });
        let occluded = cpu_nanoseconds_per_ray(&occlusion, repeats, |ray| embree.occluded(ray));
        let shadow = cpu_nanoseconds_per_ray(&rays.shadow, repeats, |ray| embree.occluded(ray));
        println!("Embree single thread CPU ns/ray: closest {closest:.0}, occlusion {occluded:.0}, shadow {shadow:.0}");
    }
}

/// (OBJ path, point light position from the scene's scene.toml)
const SCENES: [(&str, [f32; 3]); 2] = [
    ("/work/shared/scenes/sponza/mesh.obj", [0.0, 5.3, 0.0]),
    ("/work/shared/scenes/living-room/mesh.obj", [1.5, 2.1, -1.8]),
];

fn load_obj(path: &str) -> Result<(Vec<Vec3>, Vec<[u32; 3]>), tobj::LoadError> {
    let (models, _) = tobj::load_obj(
        path,
        &tobj::LoadOptions {
            triangulate: true,
            single_index: true,
            ..Default::default()
        },
    )?;
    let mut positions = Vec::new();
    let mut triangles = Vec::new();
    for model in models {
        let base = positions.len() as u32;
        positions.extend(
            model
                .mesh
                .positions
                .chunks_exact(3)
                .map(|xyz| Vec3::new(xyz[0], xyz[1], xyz[2])),
        );
        triangles.extend(
            model
                .mesh
                .indices
                .chunks_exact(3)
                .map(|corners| [base + corners[0], base + corners[1], base + corners[2]]),
        );
    }
    Ok((positions, triangles))
}

fn environment_number(name: &str, default: usize) -> usize {
    std::env::var(name)
        .ok()
        .and_then(|value| value.replace('_', "").parse().ok())
        .unwrap_or(default)
}

fn main() {
    let ray_count = environment_number("RAYBENCH_RAYS", 1_000_000);
    let repeats = environment_number("RAYBENCH_REPEATS", 5);
    for (path, light) in SCENES {
        let (positions, triangles) = match load_obj(path) {
            Ok(mesh) => mesh,
            Err(error) => {
                eprintln!("skipping {path}: {error}");
                continue;
            }
        };
        println!("== {path}");
        if std::env::var_os("RAYBENCH_CPU_TIME").is_some() {
            cpu_time_report(
                &positions,
                &triangles,
                Vec3::from_array(light),
                ray_count,
                repeats,
            );
            continue;
        }
        let report = raybench::run(
            &positions,
            &triangles,
            Vec3::from_array(light),
            ray_count,
            repeats,
            1,
        );
        println!("{report}");
    }
}
