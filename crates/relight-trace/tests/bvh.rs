//! BVH correctness: brute force as the oracle, tree invariants, build
//! determinism across thread counts, watertightness on closed meshes, and
//! degenerate input.

use glam::{Vec2, Vec3};
use relight_core::sampling::{uniform_sphere, Pcg32};
use relight_trace::bvh::{Bvh, Hit, Ray};

/// Relative tolerance on t between the BVH (f32 watertight test) and the f64
/// brute force.
const T_TOLERANCE: f64 = 1e-4;

struct BruteHit {
    t: f64,
    triangle: u32,
    barycentric: [f64; 2],
}

/// Double-precision Möller-Trumbore over every triangle; independent of the
/// code under test.
fn brute_force(positions: &[Vec3], triangles: &[[u32; 3]], ray: &Ray) -> Option<BruteHit> {
    let to_f64 = |vector: Vec3| [vector.x as f64, vector.y as f64, vector.z as f64];
    let sub = |a: [f64; 3], b: [f64; 3]| [a[0] - b[0], a[1] - b[1], a[2] - b[2]];
    let dot = |a: [f64; 3], b: [f64; 3]| a[0] * b[0] + a[1] * b[1] + a[2] * b[2];
    let cross = |a: [f64; 3], b: [f64; 3]| {
        [
            a[1] * b[2] - a[2] * b[1],
            a[2] * b[0] - a[0] * b[2],
            a[0] * b[1] - a[1] * b[0],
        ]
    };
    let origin = to_f64(ray.origin);
    let direction = to_f64(ray.direction);
    let mut best: Option<BruteHit> = None;
    let mut t_max = ray.t_max as f64;
    for (index, triangle) in triangles.iter().enumerate() {
        let [v0, v1, v2] = triangle.map(|vertex| to_f64(positions[vertex as usize]));
        let edge1 = sub(v1, v0);
        let edge2 = sub(v2, v0);
        let p = cross(direction, edge2);
        let determinant = dot(edge1, p);
        if determinant == 0.0 || !determinant.is_finite() {
            continue;
        }
        let s = sub(origin, v0);
        let b1 = dot(s, p) / determinant;
        let q = cross(s, edge1);
        let b2 = dot(direction, q) / determinant;
        if b1 < 0.0 || b2 < 0.0 || b1 + b2 > 1.0 {
            continue;
        }
        let t = dot(edge2, q) / determinant;
        if t > 0.0 && t < t_max {
            t_max = t;
            best = Some(BruteHit {
                t,
                triangle: index as u32,
                barycentric: [b1, b2],
            });
        }
    }
    best
}

fn random_soup(seed: u64, count: usize, size: f32) -> (Vec<Vec3>, Vec<[u32; 3]>) {
    let mut rng = Pcg32::new(seed, 7);
    let mut positions = Vec::new();
    let mut triangles = Vec::new();
    for index in 0..count {
        let center = Vec3::new(rng.next_f32(), rng.next_f32(), rng.next_f32()) * 10.0;
        for _ in 0..3 {
            positions.push(center + uniform_sphere(rng.next_vec2()) * size * rng.next_f32());
        }
        let base = 3 * index as u32;
        triangles.push([base, base + 1, base + 2]);
    }
    (positions, triangles)
}

/// Closed axis-aligned box [-1, 1]^3 with each face split into a grid of
/// `cells` x `cells` quads, vertices shared between faces.
fn tessellated_box(cells: u32) -> (Vec<Vec3>, Vec<[u32; 3]>) {
    let mut positions: Vec<Vec3> = Vec::new();
    let mut triangles = Vec::new();
    let mut index_of = std::collections::HashMap::new();
    let mut vertex = |point: [i32; 3], positions: &mut Vec<Vec3>| -> u32 {
        *index_of.entry(point).or_insert_with(|| {
            positions.push(
                Vec3::new(point[0] as f32, point[1] as f32, point[2] as f32) * (2.0 / cells as f32)
                    - Vec3::ONE,
            );
            (positions.len() - 1) as u32
        })
    };
    let cells = cells as i32;
    for axis in 0..3 {
        for side in [0, cells] {
            for row in 0..cells {
                for column in 0..cells {
                    let corner = |du: i32, dv: i32| {
                        let mut point = [0; 3];
                        point[axis] = side;
                        point[(axis + 1) % 3] = row + du;
                        point[(axis + 2) % 3] = column + dv;
                        point
                    };
                    let a = vertex(corner(0, 0), &mut positions);
                    let b = vertex(corner(1, 0), &mut positions);
                    let c = vertex(corner(1, 1), &mut positions);
                    let d = vertex(corner(0, 1), &mut positions);
                    triangles.push([a, b, c]);
                    triangles.push([a, c, d]);
                }
            }
        }
    }
    (positions, triangles)
}

/// Closed UV sphere of radius 1 around `center`, poles shared.
fn tessellated_sphere(center: Vec3, rings: u32, segments: u32) -> (Vec<Vec3>, Vec<[u32; 3]>) {
    let mut positions = vec![center + Vec3::Z, center - Vec3::Z];
    for ring in 1..rings {
        let polar = std::f32::consts::PI * ring as f32 / rings as f32;
        for segment in 0..segments {
            let azimuth = std::f32::consts::TAU * segment as f32 / segments as f32;
            positions.push(
                center
                    + Vec3::new(
                        polar.sin() * azimuth.cos(),
                        polar.sin() * azimuth.sin(),
                        polar.cos(),
                    ),
            );
        }
    }
    let ring_vertex = |ring: u32, segment: u32| 2 + (ring - 1) * segments + segment % segments;
    let mut triangles = Vec::new();
    for segment in 0..segments {
        triangles.push([0, ring_vertex(1, segment), ring_vertex(1, segment + 1)]);
        triangles.push([
            1,
            ring_vertex(rings - 1, segment + 1),
            ring_vertex(rings - 1, segment),
        ]);
        for ring in 1..rings - 1 {
            let a = ring_vertex(ring, segment);
            let b = ring_vertex(ring, segment + 1);
            let c = ring_vertex(ring + 1, segment + 1);
            let d = ring_vertex(ring + 1, segment);
            triangles.push([a, d, c]);
            triangles.push([a, c, b]);
        }
    }
    (positions, triangles)
}

fn random_rays(seed: u64, count: usize, center: Vec3, spread: f32) -> Vec<Ray> {
    let mut rng = Pcg32::new(seed, 11);
    (0..count)
        .map(|index| {
            let origin =
                center + (Vec3::new(rng.next_f32(), rng.next_f32(), rng.next_f32()) - 0.5) * spread;
            // Non-unit directions and finite t_max on some rays exercise both.
            let length = 0.5 + 2.0 * rng.next_f32();
            let t_max = if index % 3 == 0 {
                2.0 + 10.0 * rng.next_f32()
            } else {
                f32::INFINITY
            };
            Ray {
                origin,
                direction: uniform_sphere(rng.next_vec2()) * length,
                t_max,
            }
        })
        .collect()
}

/// Checks the BVH against brute force on `rays`. A disagreement is accepted
/// only where brute force puts the hit within a hair of a triangle edge
/// (float and double may round differently there) or two triangles tie.
fn check_against_brute_force(
    positions: &[Vec3],
    triangles: &[[u32; 3]],
    rays: &[Ray],
    minimum_hit_fraction: f32,
) {
    let bvh = Bvh::build(positions, triangles);
    bvh.validate().unwrap();
    let near_edge = |hit: &BruteHit| {
        let [b1, b2] = hit.barycentric;
        b1.min(b2).min(1.0 - b1 - b2) < 1e-5
    };
    let mut hits = vec![None; rays.len()];
    let mut occluded = vec![false; rays.len()];
    bvh.intersect_batch(rays, &mut hits);
    bvh.occluded_batch(rays, &mut occluded);
    let mut hit_count = 0;
    for (index, ray) in rays.iter().enumerate() {
        let expected = brute_force(positions, triangles, ray);
        let actual = bvh.intersect(ray);
        assert_eq!(
            actual, hits[index],
            "batch and single differ on ray {index}"
        );
        assert_eq!(bvh.occluded(ray), occluded[index]);
        assert_eq!(
            actual.is_some(),
            occluded[index],
            "occlusion disagrees with closest hit on ray {index}"
        );
        match (&expected, &actual) {
            (None, None) => {}
            (Some(expected), Some(actual)) => {
                hit_count += 1;
                let relative = (actual.t as f64 - expected.t).abs() / expected.t.max(1e-6);
                if actual.triangle != expected.triangle {
                    // A tie: the BVH's triangle is hit at the same distance.
                    let alternative =
                        brute_force(positions, &[triangles[actual.triangle as usize]], ray);
                    let tie = alternative.is_some_and(|other| {
                        (other.t - expected.t).abs() <= T_TOLERANCE * expected.t
                    });
                    assert!(
                        tie || near_edge(expected),
                        "ray {index}: triangle {} vs brute force {} (t {} vs {})",
                        actual.triangle,
                        expected.triangle,
                        actual.t,
                        expected.t
                    );
                } else {
                    assert!(
                        relative < T_TOLERANCE,
                        "ray {index}: t {} vs {}",
                        actual.t,
                        expected.t
                    );
                    let point = ray.origin.as_dvec3() + ray.direction.as_dvec3() * actual.t as f64;
                    let [v0, v1, v2] = triangles[actual.triangle as usize]
                        .map(|vertex| positions[vertex as usize].as_dvec3());
                    let [b1, b2] = [actual.barycentric.x as f64, actual.barycentric.y as f64];
                    let reconstructed = v0 * (1.0 - b1 - b2) + v1 * b1 + v2 * b2;
                    let scale = (v1 - v0).length().max((v2 - v0).length());
                    assert!(
                        (point - reconstructed).length() < 1e-3 * scale.max(1.0),
                        "ray {index}: barycentric off"
                    );
                }
            }
            (Some(expected), None) => assert!(
                near_edge(expected),
                "ray {index}: BVH misses triangle {} at t {}",
                expected.triangle,
                expected.t
            ),
            (None, Some(actual)) => {
                let alternative = brute_force(
                    positions,
                    &[triangles[actual.triangle as usize]],
                    &Ray {
                        t_max: f32::INFINITY,
                        ..*ray
                    },
                );
                panic!("ray {index}: BVH hits triangle {} at t {} where brute force misses (alone: {:?})", actual.triangle, actual.t, alternative.map(|hit| hit.barycentric));
            }
        }
    }
    assert!(
        hit_count as f32 >= minimum_hit_fraction * rays.len() as f32,
        "too few test rays hit something ({hit_count})"
    );
}

#[test]
fn bvh_matches_brute_force_on_random_soups() {
    for (seed, count, size, minimum_hit_fraction) in [
        (1, 1, 3.0, 0.0),
        (2, 7, 3.0, 0.001),
        (3, 300, 2.0, 0.05),
        (4, 3000, 1.0, 0.2),
        (5, 5000, 0.3, 0.05),
    ] {
        let (positions, triangles) = random_soup(seed, count, size);
        let rays = random_rays(seed + 100, 3000, Vec3::splat(5.0), 14.0);
        check_against_brute_force(&positions, &triangles, &rays, minimum_hit_fraction);
    }
}

#[test]
fn bvh_matches_brute_force_in_closed_box() {
    let (positions, triangles) = tessellated_box(12);
    let rays = random_rays(42, 5000, Vec3::ZERO, 1.8);
    check_against_brute_force(&positions, &triangles, &rays, 0.99);
    // Every ray from inside a closed box hits it.
    let bvh = Bvh::build(&positions, &triangles);
    for ray in rays.iter().filter(|ray| ray.t_max == f32::INFINITY) {
        assert!(bvh.intersect(ray).is_some());
    }
}

#[test]
fn bvh_build_is_deterministic_across_thread_counts() {
    // Large enough for parallel binning and parallel subtrees.
    let (positions, triangles) = random_soup(9, 60_000, 0.2);
    let build_with = |threads: usize| {
        rayon::ThreadPoolBuilder::new()
            .num_threads(threads)
            .build()
            .unwrap()
            .install(|| Bvh::build(&positions, &triangles))
    };
    let single = build_with(1);
    let double = build_with(2);
    let quadruple = build_with(4);
    single.validate().unwrap();
    assert_eq!(single.nodes(), double.nodes());
    assert_eq!(single.packets(), double.packets());
    assert_eq!(single.nodes(), quadruple.nodes());
    assert_eq!(single.packets(), quadruple.packets());
    assert_eq!(single.stored_triangle_count(), triangles.len());
}

/// Rays from inside aimed exactly at vertices and at points on shared edges
/// must never escape a closed mesh.
fn assert_watertight(positions: &[Vec3], triangles: &[[u32; 3]], origins: &[Vec3]) {
    let bvh = Bvh::build(positions, triangles);
    bvh.validate().unwrap();
    let mut targets: Vec<Vec3> = positions.to_vec();
    for triangle in triangles {
        for corner in 0..3 {
            let a = positions[triangle[corner] as usize];
            let b = positions[triangle[(corner + 1) % 3] as usize];
            for fraction in [0.5f32, 0.25, 1.0 / 3.0, 0.1] {
                targets.push(a + (b - a) * fraction);
            }
        }
    }
    let mut escaped = 0;
    let mut tested = 0;
    for &origin in origins {
        for &target in &targets {
            for scale in [1.0f32, 0.37, 5.0] {
                let ray = Ray {
                    origin,
                    direction: (target - origin) * scale,
                    t_max: f32::INFINITY,
                };
                tested += 1;
                if bvh.intersect(&ray).is_none() || !bvh.occluded(&ray) {
                    escaped += 1;
                }
            }
        }
    }
    assert_eq!(escaped, 0, "{escaped} of {tested} rays escaped");
}

#[test]
fn bvh_is_watertight_on_closed_sphere() {
    let center = Vec3::new(0.3, -2.0, 7.0);
    let (positions, triangles) = tessellated_sphere(center, 24, 48);
    let origins = [
        center,
        center + Vec3::new(0.1, 0.2, -0.3),
        center + Vec3::new(-0.5, 0.1, 0.6),
        center + Vec3::new(0.0, 0.0, 0.9),
    ];
    assert_watertight(&positions, &triangles, &origins);
}

#[test]
fn bvh_is_watertight_on_closed_box() {
    let (positions, triangles) = tessellated_box(8);
    // The center lies in the plane of many diagonals: rays graze them exactly.
    let origins = [
        Vec3::ZERO,
        Vec3::new(0.25, 0.5, -0.75),
        Vec3::new(-0.9, 0.9, 0.0),
        Vec3::new(0.5, 0.5, 0.5),
    ];
    assert_watertight(&positions, &triangles, &origins);
}

#[test]
fn bvh_handles_empty_and_degenerate_input() {
    let ray = Ray {
        origin: Vec3::ZERO,
        direction: Vec3::X,
        t_max: f32::INFINITY,
    };
    let empty = Bvh::build(&[], &[]);
    empty.validate().unwrap();
    assert_eq!(empty.intersect(&ray), None);
    assert!(!empty.occluded(&ray));
    assert_eq!(empty.triangle_count(), 0);
    assert_eq!(empty.bounds(), (Vec3::ZERO, Vec3::ZERO));
    let mut hits = vec![];
    empty.intersect_batch(&[], &mut hits);

    let positions = vec![
        Vec3::new(1.0, -1.0, -1.0),
        Vec3::new(1.0, 1.0, -1.0),
        Vec3::new(1.0, 0.0, 1.0),
        Vec3::new(2.0, 0.0, 0.0),
        Vec3::new(3.0, 0.0, 0.0),
        Vec3::new(f32::NAN, 0.0, 0.0),
        Vec3::new(f32::INFINITY, 0.0, 0.0),
        Vec3::new(4.0, 0.0, 0.0),
    ];
    let degenerate = vec![
        [0, 0, 1],
        [3, 4, 3],
        [0, 1, 0],
        [3, 3, 3],
        [0, 1, 5],
        [0, 6, 2],
        [3, 4, 7],
    ];
    let bvh = Bvh::build(&positions, &degenerate);
    bvh.validate().unwrap();
    assert_eq!(bvh.triangle_count(), degenerate.len());
    assert_eq!(bvh.stored_triangle_count(), 0);
    assert_eq!(bvh.intersect(&ray), None);
    assert!(!bvh.occluded(&ray));

    let mut mixed = degenerate.clone();
    mixed.push([0, 1, 2]);
    let bvh = Bvh::build(&positions, &mixed);
    bvh.validate().unwrap();
    let hit = bvh.intersect(&ray).expect("the one valid triangle is hit");
    assert_eq!(hit.triangle, 7);
    assert!((hit.t - 1.0).abs() < 1e-6);
    let expected = Vec2::new(0.25, 0.5);
    assert!(
        (hit.barycentric - expected).length() < 1e-6,
        "{:?}",
        hit.barycentric
    );
    // Zero and NaN directions, NaN origins, zero t_max: no panic, no hit.
    for bad in [
        Ray {
            direction: Vec3::ZERO,
            ..ray
        },
        Ray {
            origin: Vec3::NAN,
            ..ray
        },
        Ray {
            direction: Vec3::NAN,
            ..ray
        },
        Ray { t_max: 0.0, ..ray },
        Ray {
            t_max: f32::NAN,
            ..ray
        },
    ] {
        assert_eq!(bvh.intersect(&bad), None::<Hit>);
        assert!(!bvh.occluded(&bad));
    }
    // Axis-aligned rays with zero direction components hit as usual.
    let (positions, triangles) = tessellated_box(4);
    let bvh = Bvh::build(&positions, &triangles);
    for direction in [Vec3::X, -Vec3::X, Vec3::Y, -Vec3::Y, Vec3::Z, -Vec3::Z] {
        let hit = bvh
            .intersect(&Ray {
                origin: Vec3::splat(0.1),
                direction,
                t_max: f32::INFINITY,
            })
            .unwrap();
        assert!((hit.t - 0.9).abs() < 1e-5 || (hit.t - 1.1).abs() < 1e-5);
    }
}

#[test]
fn bvh_reports_sizes() {
    let (positions, triangles) = random_soup(3, 1000, 0.5);
    let bvh = Bvh::build(&positions, &triangles);
    assert_eq!(bvh.triangle_count(), 1000);
    assert!(bvh.node_count() > 1);
    assert!(
        bvh.memory_bytes()
            >= bvh.node_count() * std::mem::size_of::<relight_trace::bvh::WideNode>()
    );
    let (low, high) = bvh.bounds();
    for position in &positions {
        assert!(position.cmpge(low).all() && position.cmple(high).all());
    }
}
