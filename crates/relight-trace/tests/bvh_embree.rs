//! With the `embree` feature: the BVH agrees with Embree 3 on random soups
//! and on a shared scene when present.
#![cfg(feature = "embree")]

use glam::Vec3;
use relight_core::sampling::{uniform_sphere, Pcg32};
use relight_trace::bvh::{Bvh, EmbreeScene, Ray};

#[test]
fn bvh_agrees_with_embree() {
    let mut rng = Pcg32::new(17, 3);
    let mut positions = Vec::new();
    for _ in 0..20_000 {
        let center = Vec3::new(rng.next_f32(), rng.next_f32(), rng.next_f32()) * 20.0;
        for _ in 0..3 {
            positions.push(center + uniform_sphere(rng.next_vec2()) * 0.6);
        }
    }
    let triangles: Vec<[u32; 3]> = (0..20_000u32)
        .map(|index| [3 * index, 3 * index + 1, 3 * index + 2])
        .collect();
    let bvh = Bvh::build(&positions, &triangles);
    let embree = EmbreeScene::build(&positions, &triangles);
    let mut hits = 0;
    let mut disagreements = 0;
    for index in 0..50_000 {
        let ray = Ray {
            origin: Vec3::new(rng.next_f32(), rng.next_f32(), rng.next_f32()) * 20.0,
            direction: uniform_sphere(rng.next_vec2()) * (0.5 + rng.next_f32()),
            t_max: if index % 2 == 0 { f32::INFINITY } else { 3.0 },
        };
        let ours = bvh.intersect(&ray);
        let theirs = embree.intersect(&ray);
        assert_eq!(bvh.occluded(&ray), ours.is_some());
        match (ours, theirs) {
            (Some(ours), Some(theirs)) => {
                hits += 1;
                // Absolute part: t near zero carries the rounding of the scene-scale
                // coordinates it was computed from.
                assert!(
                    (ours.t - theirs.t).abs() <= 1e-4 * theirs.t + 1e-5,
                    "ray {index}: t {} vs {}",
                    ours.t,
                    theirs.t
                );
                if ours.triangle == theirs.triangle {
                    assert!((ours.barycentric - theirs.barycentric).length() < 1e-3);
                }
            }
            (None, None) => {}
            // Embree's default test is not watertight; rays grazing an edge
            // may differ. They must stay rare.
            _ => disagreements += 1,
        }
        if embree.occluded(&ray) != bvh.occluded(&ray) {
            disagreements += 1;
        }
    }
    assert!(hits > 10_000, "{hits}");
    assert!(
        disagreements <= 5,
        "{disagreements} disagreements with Embree"
    );
}
