//! LightSkin: the disc form factor against numerical integration, the
//! kernels against their portable forms, renormalisation, interpolation
//! weights, flux conservation of the reflective shadow maps, moving meshes,
//! point clouds, determinism, and accuracy against the path tracer limited
//! to one indirect bounce.

use glam::Vec3;
use relight_core::Rgb;
use relight_lightskin::gather::{accumulate, accumulate_portable, Sums};
use relight_lightskin::occlusion::{occluded_fraction, occluded_fraction_portable, Occluders};
use relight_lightskin::points::interpolation_weights;
use relight_lightskin::vals::{Val, Vals};
use relight_lightskin::{phong_diffuse, LightSkin, LightSkinKind, LightSkinParams};
use relight_render::study::indirect_errors;
use relight_scene::atlas::TexelDensity;
use relight_scene::{Light, Scene};
use relight_technique::{
    ContextSettings, Frame, NoProgress, SceneContext, Technique, TechniqueKind,
};
use relight_trace::path::PathSettings;
use std::path::{Path, PathBuf};
use std::sync::Arc;

fn scene_path(name: &str) -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("../../scenes")
        .join(name)
        .join("scene.toml")
}

fn context_of(scene: Scene, lightmap: TexelDensity) -> Arc<SceneContext> {
    let settings = ContextSettings {
        lightmap,
        ..ContextSettings::default()
    };
    Arc::new(SceneContext::new(scene, settings).unwrap())
}

fn shipped(name: &str) -> Arc<SceneContext> {
    context_of(
        relight_scene::load_scene(&scene_path(name)).expect("shipped scene loads"),
        TexelDensity::default(),
    )
}

fn updated(context: &Arc<SceneContext>, params: LightSkinParams) -> LightSkin {
    let mut technique = LightSkin::new(context.clone(), params).unwrap();
    let lights = context.scene.lights.clone();
    technique
        .update(&Frame {
            lights: &lights,
            index: 0,
            camera: None,
            moving_mesh_poses: None,
        })
        .unwrap();
    technique
}

fn single_val(position: Vec3, normal: Vec3, power_over_pi: Rgb, area: f32) -> Vals {
    let mut vals = Vals::default();
    vals.extend(&[Val {
        position,
        normal,
        power_over_pi,
        area,
    }]);
    vals.pad();
    vals
}

/// Irradiance at `receiver` (normal `normal`) from a Lambertian disc of
/// radiance `radiance`, centre `centre`, normal `disc_normal`, radius
/// `radius`, by the midpoint rule on a fine polar grid.
fn disc_irradiance_numerically(
    receiver: Vec3,
    normal: Vec3,
    centre: Vec3,
    disc_normal: Vec3,
    radius: f32,
    radiance: f64,
) -> f64 {
    let (tangent, bitangent) = relight_core::sampling::orthonormal_basis(disc_normal);
    let rings = 400;
    let sectors = 800;
    let mut irradiance = 0.0f64;
    for ring in 0..rings {
        let r0 = radius as f64 * ring as f64 / rings as f64;
        let r1 = radius as f64 * (ring + 1) as f64 / rings as f64;
        let r = 0.5 * (r0 + r1);
        let ring_area = std::f64::consts::PI * (r1 * r1 - r0 * r0) / sectors as f64;
        for sector in 0..sectors {
            let angle = std::f64::consts::TAU * (sector as f64 + 0.5) / sectors as f64;
            let point =
                centre + tangent * (r * angle.cos()) as f32 + bitangent * (r * angle.sin()) as f32;
            let to_receiver = (receiver - point).as_dvec3();
            let distance_sq = to_receiver.length_squared();
            let direction = to_receiver / distance_sq.sqrt();
            let cos_disc = direction.dot(disc_normal.as_dvec3()).max(0.0);
            let cos_receiver = (-direction).dot(normal.as_dvec3()).max(0.0);
            irradiance += radiance * cos_disc * cos_receiver / distance_sq * ring_area;
        }
    }
    irradiance
}

#[test]
fn disc_form_factor_is_exact_on_axis_and_close_off_axis() {
    let radius = 0.1f32;
    let area = std::f32::consts::PI * radius * radius;
    let radiance = 2.0f32;
    // A Lambertian disc of radiance L emits pi L A; the kernel's power over
    // pi is therefore L A.
    let power = Rgb::splat(radiance * area);
    let centre = Vec3::ZERO;
    let disc_normal = Vec3::Y;
    let vals = single_val(centre, disc_normal, power, area);
    let kernel = |receiver: Vec3, normal: Vec3| {
        let mut sums = Sums::default();
        accumulate_portable::<false>(
            &vals,
            0,
            vals.padded_len(),
            receiver,
            normal,
            None,
            &mut sums,
        );
        sums.irradiance[0] as f64
    };
    // On the axis, facing the disc: r^2 / (r^2 + d^2) is the exact form
    // factor, so only the quadrature's error (well below 1e-3) remains.
    for distance in [0.05f32, 0.1, 0.3, 1.0] {
        let receiver = Vec3::new(0.0, distance, 0.0);
        let exact = disc_irradiance_numerically(
            receiver,
            -Vec3::Y,
            centre,
            disc_normal,
            radius,
            radiance as f64,
        );
        let formula = kernel(receiver, -Vec3::Y);
        assert!(
            (formula - exact).abs() / exact < 1e-3,
            "on axis at {distance}: formula {formula}, integral {exact}"
        );
    }
    // Off the axis the formula treats the disc as seen from its centre:
    // its relative error is second order in r/d (measured: 0.8 to 1.8
    // times (r/d)^2 at 3 to 15 radii, tilted receivers included), so the
    // bound is 2 (r/d)^2; this is why VALs are small (one RSM texel).
    for (offset, tilt) in [(0.3f32, 0.0f32), (0.5, 0.4), (0.8, -0.3), (1.5, 0.2)] {
        let receiver = Vec3::new(offset, 0.3 + 0.2 * offset, 0.1);
        let normal = (centre - receiver)
            .normalize()
            .lerp(Vec3::X * tilt.signum(), tilt.abs())
            .normalize();
        let exact = disc_irradiance_numerically(
            receiver,
            normal,
            centre,
            disc_normal,
            radius,
            radiance as f64,
        );
        let formula = kernel(receiver, normal);
        let bound = 2.0 * (radius / receiver.length()).powi(2) as f64;
        assert!(
            (formula - exact).abs() / exact < bound,
            "off axis at {receiver}: formula {formula}, integral {exact}, bound {bound}"
        );
    }
}

fn random_vals(count: usize) -> Vals {
    let mut rng = relight_core::sampling::Pcg32::new(7, 1);
    let vals: Vec<Val> = (0..count)
        .map(|_| {
            let position = Vec3::new(rng.next_f32(), rng.next_f32(), rng.next_f32()) * 2.0;
            let normal = relight_core::sampling::uniform_sphere(rng.next_vec2());
            Val {
                position,
                normal,
                power_over_pi: Rgb::new(rng.next_f32(), rng.next_f32(), rng.next_f32()),
                area: 1e-3 * (1.0 + rng.next_f32()),
            }
        })
        .collect();
    let mut packed = Vals::default();
    packed.extend(&vals);
    packed.pad();
    packed
}

#[test]
fn simd_gathering_matches_portable_gathering() {
    let vals = random_vals(1003);
    let mut rng = relight_core::sampling::Pcg32::new(9, 2);
    for _ in 0..50 {
        let position = Vec3::new(rng.next_f32(), rng.next_f32(), rng.next_f32()) * 2.0;
        let normal = relight_core::sampling::uniform_sphere(rng.next_vec2());
        let mut fast = Sums::default();
        let mut portable = Sums::default();
        accumulate::<true>(
            &vals,
            0,
            vals.padded_len(),
            position,
            normal,
            None,
            &mut fast,
        );
        accumulate_portable::<true>(
            &vals,
            0,
            vals.padded_len(),
            position,
            normal,
            None,
            &mut portable,
        );
        // The SIMD kernel uses the hardware reciprocal estimate (relative
        // error below 1.5 * 2^-12 = 3.7e-4 per term) and sums in another
        // order; 1e-3 of the total bounds both.
        let close = |a: f32, b: f32, scale: f32| (a - b).abs() <= 1e-3 * scale.abs().max(1e-12);
        for channel in 0..3 {
            assert!(close(
                fast.irradiance[channel],
                portable.irradiance[channel],
                portable.irradiance[channel]
            ));
            let scale = portable.weighted_position[channel]
                .abs()
                .max(portable.weight);
            assert!(close(
                fast.weighted_position[channel],
                portable.weighted_position[channel],
                scale
            ));
            let scale = portable.weighted_square[channel].abs().max(portable.weight);
            assert!(close(
                fast.weighted_square[channel],
                portable.weighted_square[channel],
                scale
            ));
        }
        assert!(close(fast.weight, portable.weight, portable.weight));
    }
}

#[test]
fn simd_gathering_with_visibility_matches_portable_gathering() {
    // Random anchors over 200 points (seven words of a row), grouped as
    // each frame groups them: blocks whose anchors share a word take the
    // kernel's one-load path, the others its gather; a random row hides
    // about half of them. Same tolerance as above.
    let mut vals = random_vals(1003);
    let mut rng = relight_core::sampling::Pcg32::new(11, 3);
    let anchors: Vec<u32> = (0..vals.padded_len())
        .map(|_| (rng.next_f32() * 200.0) as u32)
        .collect();
    vals.group_by_anchor(anchors);
    assert!(vals
        .block_word
        .contains(&relight_lightskin::vals::MIXED_WORDS));
    assert!(vals
        .block_word
        .iter()
        .any(|&word| word != relight_lightskin::vals::MIXED_WORDS));
    for _ in 0..50 {
        let row: Vec<u32> = (0..7)
            .map(|_| (rng.next_f32() * u32::MAX as f32) as u32)
            .collect();
        let position = Vec3::new(rng.next_f32(), rng.next_f32(), rng.next_f32()) * 2.0;
        let normal = relight_core::sampling::uniform_sphere(rng.next_vec2());
        let mut fast = Sums::default();
        let mut portable = Sums::default();
        let mut everything = Sums::default();
        let end = vals.padded_len();
        accumulate::<false>(&vals, 0, end, position, normal, Some(&row), &mut fast);
        accumulate_portable::<false>(&vals, 0, end, position, normal, Some(&row), &mut portable);
        accumulate_portable::<false>(&vals, 0, end, position, normal, None, &mut everything);
        for channel in 0..3 {
            let exact = portable.irradiance[channel];
            assert!((fast.irradiance[channel] - exact).abs() <= 1e-3 * exact.abs().max(1e-12));
        }
        // The row hides some of the light, so the test would see a mask
        // that does nothing.
        assert!(portable.irradiance[0] < 0.9 * everything.irradiance[0]);
    }
}

#[test]
fn simd_occlusion_matches_portable_occlusion() {
    let context = shipped("cornell-box-point");
    let technique = updated(&context, LightSkinParams::default());
    let points = technique.sparse_points();
    let normals: Vec<Vec3> = (0..points.len())
        .map(|i| technique.sparse_point_normal(i))
        .collect();
    let mut occluders = Occluders::default();
    occluders.fill(points, &normals, &vec![2e-5; points.len()]);
    let mut compared = 0;
    for index in (0..points.len()).step_by(37) {
        let (_, light, _) = technique.sparse_point_light(index);
        let fast = occluded_fraction(&occluders, points[index], normals[index], light, 0.1);
        let portable =
            occluded_fraction_portable(&occluders, points[index], normals[index], light, 0.1);
        // rsqrt and rcp estimates (12 bits) in distances, cosines and
        // square sides: 1 % of the fraction, or 1e-3 absolute.
        assert!(
            (fast - portable).abs() <= 1e-3 + 0.01 * portable,
            "point {index}: simd {fast}, portable {portable}"
        );
        compared += usize::from(portable > 0.0);
    }
    assert!(
        compared > 10,
        "too few occluded points to compare ({compared})"
    );
}

#[test]
fn averaged_light_follows_the_bright_val() {
    // Two VALs at equal distance on either side of the receiver's normal;
    // the paper's geometric weights would put the light halfway. Weighted
    // by delivered luminance it sits next to the bright one.
    let mut vals = Vals::default();
    let bright = Val {
        position: Vec3::new(-0.5, 1.0, 0.0),
        normal: -Vec3::Y,
        power_over_pi: Rgb::splat(1.0),
        area: 1e-3,
    };
    let dark = Val {
        position: Vec3::new(0.5, 1.0, 0.0),
        power_over_pi: Rgb::splat(0.01),
        ..bright
    };
    vals.extend(&[bright, dark]);
    vals.pad();
    let mut sums = Sums::default();
    accumulate_portable::<false>(
        &vals,
        0,
        vals.padded_len(),
        Vec3::ZERO,
        Vec3::Y,
        None,
        &mut sums,
    );
    let averaged_x = sums.weighted_position[0] / sums.weight;
    assert!(
        (averaged_x - (-0.5 + 1.0 / 101.0)).abs() < 1e-4,
        "averaged x {averaged_x}"
    );
}

#[test]
fn renormalised_lights_reproduce_the_gathered_irradiance_at_sparse_points() {
    let context = shipped("cornell-box-point");
    let technique = updated(&context, LightSkinParams::default());
    let points = technique.sparse_points();
    let mut checked = 0;
    for (index, &point) in points.iter().enumerate() {
        let (irradiance, light, power) = technique.sparse_point_light(index);
        let normal = technique.sparse_point_normal(index);
        let to_light = light - point;
        // Equation 11 clamps the cosine at 0.02; the identity holds above it.
        if irradiance.max_element() <= 0.0 || normal.dot(to_light.normalize()) <= 0.02 {
            continue;
        }
        let shaded = phong_diffuse(power, light, point, normal);
        for channel in 0..3 {
            assert!(
                (shaded[channel] - irradiance[channel]).abs() <= 1e-4 * irradiance[channel],
                "point {index}: L_phong(L'', l') = {shaded}, L' = {irradiance}"
            );
        }
        checked += 1;
    }
    assert!(checked > points.len() / 2, "only {checked} points checked");
}

#[test]
fn interpolation_weights_follow_equation_12() {
    let normal = Vec3::Y;
    let tilted = Vec3::new(0.6, 0.8, 0.0);
    let neighbours = [
        (4, 0.1, Vec3::Y),
        (7, 0.2, tilted),
        (9, 0.4, Vec3::Y),
        (2, 0.3, -Vec3::Y),
    ];
    let (indices, weights) = interpolation_weights(normal, &neighbours);
    // (1 - d/d_max) * clamp(n.n): 0.75, 0.5 * 0.8, 0 (farthest), 0 (facing away).
    let raw = [0.75f32, 0.4, 0.0, 0.0];
    let total: f32 = raw.iter().sum();
    assert_eq!(&indices[..4], &[4, 7, 9, 2]);
    for slot in 0..4 {
        assert!(
            (weights[slot] - raw[slot] / total).abs() < 1e-6,
            "slot {slot}: {}",
            weights[slot]
        );
    }
    assert!(weights[4..].iter().all(|&w| w == 0.0));
    // All at one distance: equation 12 gives zero everywhere; the fallback
    // shares by normal agreement.
    let (_, weights) = interpolation_weights(normal, &[(0, 0.2, Vec3::Y), (1, 0.2, tilted)]);
    assert!((weights[0] - 1.0 / 1.8).abs() < 1e-6 && (weights[1] - 0.8 / 1.8).abs() < 1e-6);
    // No neighbour: nothing.
    let (_, weights) = interpolation_weights(normal, &[]);
    assert!(weights.iter().all(|&w| w == 0.0));
}

/// The outside of a thick lampshade, with one sparse point of its own: the
/// far inside wall 30 cm behind faces the same way, and so does a box's
/// face a metre and a half below; both gathered the lamp's light. Neither
/// may lend it to the outside, where it would be evaluated a tenth as far
/// from the lamp (variant 27 of the default family: tiles 8 % at 4096
/// points, 660 % at 2048).
#[test]
fn interpolation_takes_no_light_from_behind_the_surface_or_from_afar() {
    let own = (Vec3::new(0.1, 0.0, 0.0), 1.0);
    let mut points = vec![own];
    // The far inside wall, straight behind and beside.
    for offset in [
        Vec3::ZERO,
        Vec3::new(0.05, 0.05, 0.0),
        Vec3::new(-0.1, 0.1, 0.0),
    ] {
        points.push((Vec3::new(0.0, 0.0, -0.3) + offset, 1000.0));
    }
    // A box's face well below, seen from the shade's outside.
    for x in 0..6 {
        points.push((Vec3::new(-0.3 + 0.12 * x as f32, -1.5, 0.4), 1000.0));
    }
    let positions: Vec<Vec3> = points.iter().map(|&(position, _)| position).collect();
    let normals = vec![Vec3::Z; points.len()];
    let powers: Vec<Rgb> = points.iter().map(|&(_, power)| Rgb::splat(power)).collect();
    let spacing = 0.25;
    let interpolation = relight_lightskin::points::Interpolation::build(
        &[Vec3::ZERO, Vec3::new(0.05, 0.1, 0.0)],
        &[Vec3::Z, Vec3::Z],
        &positions,
        &normals,
        spacing,
    );
    for target in 0..2 {
        let (power, position) = interpolation.blend(target, &powers, &positions);
        // Weights are 16-bit fixed point.
        assert!(
            (power - Rgb::ONE).abs().max_element() < 1e-3,
            "target {target}: {power:?}"
        );
        assert!(
            position.distance(own.0) < 1e-3,
            "target {target}: {position:?}"
        );
    }
    // Points a little below the plane of a curved surface still count:
    // the same points, all in front or level, spread the light as before.
    let level: Vec<Vec3> = positions
        .iter()
        .map(|p| Vec3::new(p.x, p.y * 0.05, 0.0))
        .collect();
    let interpolation = relight_lightskin::points::Interpolation::build(
        &[Vec3::ZERO],
        &[Vec3::Z],
        &level,
        &normals,
        1.0,
    );
    let (power, _) = interpolation.blend(0, &powers, &level);
    assert!(power.x > 100.0, "level neighbours were dropped: {power:?}");
}

/// A texel with no point in front of it near by looks farther before it
/// takes points behind its surface, and one with none in front at all (a
/// hidden outer face) still interpolates, from the nearest facing points
/// wherever they lie.
#[test]
fn interpolation_looks_farther_in_front_before_it_takes_points_behind() {
    let spacing = 0.1;
    let behind = Vec3::new(0.0, 0.0, -0.1);
    let in_front_far = Vec3::new(0.5, 0.0, 0.05);
    let normals = [Vec3::Z; 2];
    let powers = [Rgb::splat(1000.0), Rgb::ONE];
    let build = |positions: &[Vec3]| {
        relight_lightskin::points::Interpolation::build(
            &[Vec3::ZERO],
            &[Vec3::Z],
            positions,
            &normals[..positions.len()],
            spacing,
        )
    };
    // Five spacings away in front, one behind: the one in front, alone.
    let positions = [behind, in_front_far];
    let (power, position) = build(&positions).blend(0, &powers, &positions);
    assert!(
        (power - Rgb::ONE).abs().max_element() < 1e-3,
        "took light from behind: {power:?}"
    );
    assert!(position.distance(in_front_far) < 1e-3, "{position:?}");
    // Nothing in front at all: the point behind rather than no light.
    let positions = [behind];
    let (power, position) = build(&positions).blend(0, &powers, &positions);
    assert!(
        (power - Rgb::splat(1000.0)).abs().max_element() < 1.0,
        "{power:?}"
    );
    assert!(position.distance(behind) < 1e-3, "{position:?}");
}

/// A closed cube of side 2 around the origin, all faces inward, one albedo.
fn closed_cube(albedo: f32, light: Light) -> Scene {
    let mut scene = Scene::default();
    let corners = |axis: usize, side: f32| {
        let (u, v) = ((axis + 1) % 3, (axis + 2) % 3);
        let mut quad = [Vec3::ZERO; 4];
        for (k, (a, b)) in [(-1.0, -1.0), (1.0, -1.0), (1.0, 1.0), (-1.0, 1.0)]
            .into_iter()
            .enumerate()
        {
            quad[k][axis] = side;
            quad[k][u] = a;
            quad[k][v] = b;
        }
        quad
    };
    for axis in 0..3 {
        for side in [-1.0f32, 1.0] {
            let quad = corners(axis, side);
            let first = scene.mesh.positions.len() as u32;
            scene.mesh.positions.extend_from_slice(&quad);
            let inward = -Vec3::from_array({
                let mut n = [0.0; 3];
                n[axis] = side;
                n
            });
            let mut triangles = [[first, first + 1, first + 2], [first, first + 2, first + 3]];
            let normal = (quad[1] - quad[0]).cross(quad[2] - quad[0]);
            if normal.dot(inward) < 0.0 {
                triangles = [[first, first + 2, first + 1], [first, first + 3, first + 2]];
            }
            scene.mesh.triangles.extend_from_slice(&triangles);
            scene.mesh.material_ids.extend_from_slice(&[0, 0]);
        }
    }
    scene.materials.push(relight_scene::Material {
        albedo: Rgb::splat(albedo),
        ..Default::default()
    });
    scene.lights.push(light);
    scene
}

/// Two closed cubes side by side, 0.1 m apart, a point light in the
/// left one: no light can reach the right one.
fn two_closed_cubes() -> Scene {
    let mut scene = closed_cube(
        0.7,
        Light::Point {
            position: Vec3::new(-1.05, 0.3, 0.2),
            intensity: Rgb::splat(5.0),
        },
    );
    let count = scene.mesh.positions.len();
    let triangles = scene.mesh.triangles.len();
    for index in 0..count {
        let position = scene.mesh.positions[index];
        scene.mesh.positions[index] = position - Vec3::X * 1.05;
        scene.mesh.positions.push(position + Vec3::X * 1.05);
    }
    for index in 0..triangles {
        let [a, b, c] = scene.mesh.triangles[index];
        let shift = |vertex: u32| vertex + count as u32;
        scene.mesh.triangles.push([shift(a), shift(b), shift(c)]);
        scene.mesh.material_ids.push(0);
    }
    scene
}

#[test]
fn light_does_not_pass_through_walls() {
    // The right cube's sparse points face the left cube's lit walls
    // through two walls; the disc occlusion of section 3.3 stops only
    // part of that light, while the traced visibility between sparse
    // points stops it all. (Texels by the gap also interpolate from the
    // other cube's points; the final gather, on by default, traces those.)
    let context = context_of(two_closed_cubes(), TexelDensity::TargetResolution(64));
    let receivers = &context.atlas.receivers;
    let light_on = |right: bool, params: LightSkinParams| {
        let technique = updated(&context, params);
        let irradiance = technique.receiver_irradiance().unwrap();
        (0..receivers.len())
            .filter(|&index| (receivers.positions[index].x > 0.0) == right)
            .map(|index| irradiance[index].x as f64)
            .sum::<f64>()
    };
    let params = |visibility: bool| LightSkinParams {
        visibility,
        occlusion: !visibility,
        ..LightSkinParams::default()
    };
    let lit = light_on(false, params(true));
    let leaked = light_on(true, params(true));
    let leaked_without = light_on(true, params(false));
    println!("lit cube {lit}, dark cube {leaked} ({leaked_without} without visibility)");
    assert!(lit > 0.0);
    // Measured: 8e-5 of the lit cube's light without visibility (the
    // discs stop most of it in a box this simple), none with it.
    assert!(leaked_without > 1e-5 * lit, "{leaked_without} of {lit}");
    assert!(leaked < 1e-7 * lit, "{leaked} of {lit}");
}

#[test]
fn reflective_shadow_maps_conserve_flux() {
    // Every ray from a point light inside a closed cube hits a wall, so the
    // VALs re-emit albedo * 4 pi I; the texel solid angles are a midpoint
    // rule of the exact cube-face integral (error far below 0.1 %).
    let intensity = 3.0f32;
    let albedo = 0.6f32;
    let scene = closed_cube(
        albedo,
        Light::Point {
            position: Vec3::new(0.1, -0.2, 0.3),
            intensity: Rgb::splat(intensity),
        },
    );
    let context = context_of(scene, TexelDensity::TargetResolution(32));
    let technique = updated(&context, LightSkinParams::default());
    let expected = albedo * 4.0 * std::f32::consts::PI * intensity;
    let total = technique.vals().total_power();
    assert_eq!(technique.vals().count, 6 * 48 * 48);
    assert!(
        (total.x - expected).abs() / expected < 1e-3,
        "VAL power {total}, expected {expected}"
    );
    // A directional light from above hits the cube's top from outside:
    // the VALs re-emit albedo times the irradiance times the top's area (4).
    let scene = closed_cube(
        albedo,
        Light::Directional {
            direction: -Vec3::Y,
            irradiance: Rgb::splat(2.0),
        },
    );
    let context = context_of(scene, TexelDensity::TargetResolution(32));
    let technique = updated(&context, LightSkinParams::default());
    let total = technique.vals().total_power();
    let expected = albedo * 2.0 * 4.0;
    // Texel centres decide coverage: 28 texels of 7.2 cm cover 2.02 m of
    // the 2 m face per side, about 2 % more area.
    assert!(
        (total.x - expected).abs() / expected < 0.04,
        "VAL power {total}, expected {expected}"
    );
}

/// `closed_cube` with a square opening of side `size` in its top face
/// (y = 1) centred at (`centre.x`, `centre.y`) in x and z.
fn cube_with_a_roof_opening(light: Light, centre: glam::Vec2, size: f32) -> Scene {
    let mut scene = closed_cube(0.6, light);
    // The top face is the fourth quad (axis 1, side +1): triangles 6 and 7.
    scene.mesh.triangles.drain(6..8);
    scene.mesh.material_ids.drain(6..8);
    let (low, high) = (centre - size / 2.0, centre + size / 2.0);
    let frame = [
        (glam::Vec2::new(-1.0, -1.0), glam::Vec2::new(low.x, 1.0)),
        (glam::Vec2::new(high.x, -1.0), glam::Vec2::new(1.0, 1.0)),
        (glam::Vec2::new(low.x, -1.0), glam::Vec2::new(high.x, low.y)),
        (glam::Vec2::new(low.x, high.y), glam::Vec2::new(high.x, 1.0)),
    ];
    for (a, b) in frame {
        let first = scene.mesh.positions.len() as u32;
        scene.mesh.positions.extend_from_slice(&[
            Vec3::new(a.x, 1.0, a.y),
            Vec3::new(b.x, 1.0, a.y),
            Vec3::new(b.x, 1.0, b.y),
            Vec3::new(a.x, 1.0, b.y),
        ]);
        // Wound to face down, into the cube, as closed_cube's faces do.
        scene
            .mesh
            .triangles
            .extend_from_slice(&[[first, first + 2, first + 1], [first, first + 3, first + 2]]);
        scene.mesh.material_ids.extend_from_slice(&[0, 0]);
    }
    scene
}

#[test]
fn a_sun_through_an_opening_about_a_map_texel_wide_lets_in_its_flux() {
    // The sun's map spans the cube's bounding sphere (texels of 7.2 cm);
    // the opening is 11 cm, a texel and a half. One ray a texel lets in a
    // whole number of texels' flux by where the opening falls on the grid
    // (measured over these seven places: 0.46-1.37x, 34 % off on average);
    // rays refined where they pass its edges find them to a third of a
    // texel, 4.5 such steps across the opening, so each side is off by at
    // most (5 / 4.5)^2 - 1 = 23 % (measured: 0.92-1.07x, 4 % on average).
    let direction = Vec3::new(0.3, -1.0, 0.2).normalize();
    let irradiance = 2.0f32;
    let size = 0.11f32;
    let mut ratios = Vec::new();
    for step in 0..7 {
        let centre = glam::Vec2::new(0.031, 0.023) * step as f32 - 0.1;
        let scene = cube_with_a_roof_opening(
            Light::Directional {
                direction,
                irradiance: Rgb::splat(irradiance),
            },
            centre,
            size,
        );
        let context = context_of(scene, TexelDensity::TargetResolution(32));
        let params = LightSkinParams {
            points: 256,
            ..LightSkinParams::default()
        };
        let technique = updated(&context, params);
        let vals = technique.vals();
        let inside: f32 = (0..vals.count)
            .filter(|&index| {
                // The sun also lights the outside of the top and two sides,
                // whose VALs face away from the centre.
                let position = Vec3::new(vals.px[index], vals.py[index], vals.pz[index]);
                let normal = Vec3::new(vals.nx[index], vals.ny[index], vals.nz[index]);
                normal.dot(position) < 0.0
            })
            .map(|index| vals.power_r[index])
            .sum::<f32>()
            * std::f32::consts::PI;
        let expected = 0.6 * irradiance * size * size * -direction.y;
        ratios.push(inside / expected);
    }
    println!("flux let in over the opening's: {ratios:?}");
    let mean_error = ratios.iter().map(|r| (r - 1.0).abs()).sum::<f32>() / ratios.len() as f32;
    let worst = ratios.iter().map(|r| (r - 1.0).abs()).fold(0.0, f32::max);
    assert!(mean_error < 0.1, "mean error {mean_error}: {ratios:?}");
    assert!(worst < 0.25, "worst error {worst}: {ratios:?}");
}

#[test]
fn gathering_is_deterministic_across_thread_counts() {
    let context = shipped("corridor");
    let run = |threads: usize| {
        let pool = rayon::ThreadPoolBuilder::new()
            .num_threads(threads)
            .build()
            .unwrap();
        pool.install(|| {
            let technique = updated(&context, LightSkinParams::default());
            technique.receiver_irradiance().unwrap().to_vec()
        })
    };
    let one = run(1);
    let two = run(2);
    assert!(one
        .iter()
        .zip(&two)
        .all(|(a, b)| a.to_array().map(f32::to_bits) == b.to_array().map(f32::to_bits)));
}

#[test]
fn moving_box_changes_the_indirect_light_on_the_floor() {
    let scene = relight_scene::load_scene(
        &Path::new(env!("CARGO_MANIFEST_DIR")).join("../../scenes/sequences/moving-box/scene.toml"),
    )
    .unwrap();
    let context = context_of(scene, TexelDensity::default());
    let mut technique = LightSkinKind
        .create(context.clone(), None, &[], &NoProgress)
        .unwrap();
    let lights = context.scene.lights.clone();
    let receivers = &context.atlas.receivers;
    let floor: Vec<usize> = (0..receivers.len())
        .filter(|&i| receivers.normals[i].y > 0.99 && receivers.positions[i].y < 0.01)
        .collect();
    assert!(floor.len() > 100);
    let mut floor_light = Vec::new();
    for index in [0u64, 3, 7] {
        technique
            .update(&Frame {
                lights: &lights,
                index,
                camera: None,
                moving_mesh_poses: None,
            })
            .unwrap();
        let irradiance = technique.receiver_irradiance().unwrap();
        floor_light.push(floor.iter().map(|&i| irradiance[i]).collect::<Vec<Rgb>>());
        // The box is traced by the renderer and receives indirect light
        // on its underside, which no direct light reaches.
        let merged = technique.frame_geometry().expect("moving meshes placed");
        assert_eq!(
            merged.mesh.triangles.len(),
            context.scene.mesh.triangles.len() + 12
        );
        let first_box_triangle = context.scene.mesh.triangles.len();
        let underside = (first_box_triangle..merged.mesh.triangles.len())
            .find(|&t| merged.mesh.geometric_normal(t).y < -0.99)
            .unwrap();
        let [a, b, c] = merged.mesh.vertices(underside);
        let point = relight_technique::SurfacePoint {
            position: (a + b + c) / 3.0,
            normal: -Vec3::Y,
            triangle: underside as u32,
            barycentric: glam::Vec2::splat(1.0 / 3.0),
        };
        assert!(technique.indirect_irradiance(&point).max_element() > 0.0);
    }
    // The floor's indirect light changes where the box's shadow moves (the
    // lit area that re-emits moves with it): some texels by over 5 %.
    let changed = |a: &[Rgb], b: &[Rgb]| {
        a.iter()
            .zip(b)
            .filter(|(x, y)| (x.x - y.x).abs() > 0.05 * x.x.max(y.x))
            .count()
    };
    assert!(changed(&floor_light[0], &floor_light[1]) > floor.len() / 50);
    assert!(changed(&floor_light[1], &floor_light[2]) > floor.len() / 50);
}

/// An application that moves the meshes itself (a game engine's
/// entities) gets the same light as the scene file's script when it puts
/// them where the script would; a wrong count or a broken pose is an error
/// naming what to pass, not a panic.
#[test]
fn moving_meshes_follow_the_poses_the_frame_gives() {
    let scene = relight_scene::load_scene(
        &Path::new(env!("CARGO_MANIFEST_DIR")).join("../../scenes/sequences/moving-box/scene.toml"),
    )
    .unwrap();
    let context = context_of(scene, TexelDensity::default());
    let meshes = relight_lightskin::dynamic::load_dynamic_meshes(&context.scene).unwrap();
    let lights = context.scene.lights.clone();
    let light_after = |index: u64, poses: Option<&[glam::Affine3A]>| {
        let mut technique = LightSkinKind
            .create(context.clone(), None, &[], &NoProgress)
            .unwrap();
        technique
            .update(&Frame {
                lights: &lights,
                index,
                camera: None,
                moving_mesh_poses: poses,
            })
            .map(|()| technique.receiver_irradiance().unwrap().to_vec())
    };
    let scripted = light_after(5, None).unwrap();
    let poses: Vec<glam::Affine3A> = meshes.iter().map(|mesh| mesh.pose(5)).collect();
    // Frame index 0: the poses, not the index, place the box.
    assert_eq!(light_after(0, Some(&poses)).unwrap(), scripted);
    assert_ne!(light_after(0, None).unwrap(), scripted);
    let wrong_count = light_after(0, Some(&[])).unwrap_err().to_string();
    assert!(wrong_count.contains("[[dynamic]]"), "{wrong_count}");
    let broken = [glam::Affine3A::from_translation(Vec3::new(
        f32::NAN,
        0.0,
        0.0,
    ))];
    let not_finite = light_after(0, Some(&broken)).unwrap_err().to_string();
    assert!(not_finite.contains("box.obj"), "{not_finite}");
}

const PLY_ASCII: &str = "ply
format ascii 1.0
comment two points of a captured wall
element vertex 2
property float x
property float y
property float z
property float nx
property float ny
property float nz
property uchar red
property uchar green
property uchar blue
property float radius
end_header
0.1 0.2 0.3 0 0 1 255 128 0 0.01
0.4 0.5 0.6 0 1 0 10 20 30 0.02
";

#[test]
fn point_clouds_read_in_ascii_and_binary_and_refuse_bad_files() {
    let path = Path::new("capture.ply");
    let ascii = relight_lightskin::ply::parse_point_cloud(path, PLY_ASCII.as_bytes()).unwrap();
    assert_eq!(ascii.len(), 2);
    assert_eq!(ascii[1].position, Vec3::new(0.4, 0.5, 0.6));
    assert_eq!(ascii[0].colour.x, 1.0);
    assert_eq!(ascii[1].radius, Some(0.02));
    // The same points, binary little-endian.
    let header = PLY_ASCII
        .split("end_header\n")
        .next()
        .unwrap()
        .replace("ascii", "binary_little_endian");
    let mut binary = format!("{header}end_header\n").into_bytes();
    for point in [
        (
            0.1f32,
            0.2f32,
            0.3f32,
            [0f32, 0., 1.],
            [255u8, 128, 0],
            0.01f32,
        ),
        (0.4, 0.5, 0.6, [0., 1., 0.], [10, 20, 30], 0.02),
    ] {
        for value in [
            point.0, point.1, point.2, point.3[0], point.3[1], point.3[2],
        ] {
            binary.extend_from_slice(&value.to_le_bytes());
        }
        binary.extend_from_slice(&point.4);
        binary.extend_from_slice(&point.5.to_le_bytes());
    }
    let parsed = relight_lightskin::ply::parse_point_cloud(path, &binary).unwrap();
    assert_eq!(parsed, ascii);
    // Truncated binary data, a missing property and a non-PLY file are
    // errors that say what is wrong.
    let truncated = relight_lightskin::ply::parse_point_cloud(path, &binary[..binary.len() - 5]);
    assert!(truncated.unwrap_err().to_string().contains("truncated"));
    let missing = PLY_ASCII.replace("property float nz\n", "");
    let missing = relight_lightskin::ply::parse_point_cloud(path, missing.as_bytes());
    assert!(missing.unwrap_err().to_string().contains("`nz`"));
    let not_ply = relight_lightskin::ply::parse_point_cloud(path, b"solid cube\nend_header\n");
    assert!(not_ply.unwrap_err().to_string().contains("line 1"));
    // Each point is a disc of radiance colour * scale: power over pi = L A.
    let vals = relight_lightskin::ply::point_cloud_vals(&ascii, 2.0);
    let area = std::f32::consts::PI * 0.01 * 0.01;
    assert!((vals[0].power_over_pi.x - 2.0 * area).abs() < 1e-9);
}

#[test]
fn a_point_cloud_lights_the_scene() {
    // A bright captured patch facing down into the unlit Cornell box (its
    // light switched off) is the only source of indirect light.
    let mut scene = relight_scene::load_scene(&scene_path("cornell-box-point")).unwrap();
    scene.lights.clear();
    let folder = std::env::temp_dir().join(format!("relight-lightskin-ply-{}", std::process::id()));
    std::fs::create_dir_all(&folder).unwrap();
    let mut text = String::from("ply\nformat ascii 1.0\nelement vertex 100\nproperty float x\nproperty float y\nproperty float z\nproperty float nx\nproperty float ny\nproperty float nz\nproperty uchar red\nproperty uchar green\nproperty uchar blue\nend_header\n");
    for i in 0..10 {
        for j in 0..10 {
            text += &format!(
                "{} 0.5 {} 0 -1 0 255 255 255\n",
                0.23 + 0.01 * i as f32,
                0.23 + 0.01 * j as f32
            );
        }
    }
    std::fs::write(folder.join("patch.ply"), text).unwrap();
    scene.source = folder.join("scene.toml");
    let context = context_of(scene, TexelDensity::default());
    let params = [("point_cloud".to_string(), "\"patch.ply\"".to_string())];
    let mut technique = LightSkinKind
        .create(context.clone(), None, &params, &NoProgress)
        .unwrap();
    technique
        .update(&Frame {
            lights: &[],
            index: 0,
            camera: None,
            moving_mesh_poses: None,
        })
        .unwrap();
    let total: f32 = technique
        .receiver_irradiance()
        .unwrap()
        .iter()
        .map(|e| e.x)
        .sum();
    assert!(total > 0.0);
    std::fs::remove_dir_all(&folder).ok();
}

/// Lightmap and indirect-image relRMSE of LightSkin against the path
/// tracer limited to one indirect bounce (what LightSkin computes), and
/// the references' own noise.
fn accuracy(scene_name: &str, params: &[(&str, &str)]) -> (f64, f64, f64, f64) {
    let mut scene = relight_scene::load_scene(&scene_path(scene_name)).unwrap();
    // A small image keeps the reference's noise low at a test's cost.
    let [width, height] = scene.camera.resolution;
    scene.camera.resolution = [width / 4, height / 4];
    let context = context_of(scene, TexelDensity::default());
    let lights = context.scene.lights.clone();
    let settings = PathSettings {
        max_bounces: 1,
        ..PathSettings::default()
    };
    let pairs: Vec<(String, String)> = params
        .iter()
        .map(|(k, v)| (k.to_string(), v.to_string()))
        .collect();
    let mut technique = LightSkinKind
        .create(context.clone(), None, &pairs, &NoProgress)
        .unwrap();
    technique
        .update(&Frame {
            lights: &lights,
            index: 0,
            camera: None,
            moving_mesh_poses: None,
        })
        .unwrap();
    let errors = indirect_errors(&context, technique.as_ref(), settings, 1024, 4096);
    (
        errors.lightmap,
        errors.lightmap_noise,
        errors.image,
        errors.image_noise,
    )
}

#[test]
fn accuracy_within_twenty_percent_of_one_bounce_path_tracing() {
    // The bound: 20 % relRMSE of the indirect-only image at the
    // defaults, on the point-lit Cornell box and the corridor. The
    // references' own noise (printed) is a few percent and adds to the
    // measured error in quadrature, so the bound is met with that noise in.
    for scene in ["cornell-box-point", "corridor"] {
        let (lightmap, lightmap_noise, image, image_noise) = accuracy(scene, &[]);
        println!(
            "{scene}: lightmap {:.1} % (reference noise {:.1} %), image {:.1} % (reference noise {:.1} %)",
            lightmap * 100.0,
            lightmap_noise * 100.0,
            image * 100.0,
            image_noise * 100.0
        );
        assert!(lightmap_noise < 0.1 && image_noise < 0.1);
        assert!(lightmap <= 0.20, "{scene}: lightmap relRMSE {lightmap}");
        assert!(image <= 0.20, "{scene}: image relRMSE {image}");
    }
}

#[test]
fn occlusion_lowers_the_error_of_the_papers_method() {
    // Section 3.3 exists to darken what indirect light cannot reach; on the
    // Cornell box (two blocks shadowing walls and floor) it must help the
    // paper's method, which has no other visibility.
    let paper = [("visibility", "false")];
    let (with_occlusion, ..) = accuracy("cornell-box-point", &[paper[0], ("occlusion", "true")]);
    let (without, ..) = accuracy("cornell-box-point", &[paper[0], ("occlusion", "false")]);
    assert!(
        with_occlusion < without * 0.8,
        "with {with_occlusion}, without {without}"
    );
}

#[test]
fn traced_visibility_lowers_the_error_below_the_disc_occlusion() {
    // The defaults (visibility traced between sparse points, no disc
    // occlusion) against the paper's occlusion: at full resolution the
    // point-lit box's lightmap measured 13.5 % against 18.3 %, its image
    // tiles 2.5 % against 14.1 % (relight converge
    // scenes/cornell-box-point/scene.toml -t lightskin --sweep
    // visibility=false,true --sweep occlusion=true,false). A fifth better
    // leaves room for the reference's noise.
    let (traced, ..) = accuracy("cornell-box-point", &[]);
    let (discs, ..) = accuracy(
        "cornell-box-point",
        &[("visibility", "false"), ("occlusion", "true")],
    );
    assert!(traced < discs * 0.8, "traced {traced}, discs {discs}");
}

#[test]
fn points_in_space_gather_one_bounce_from_the_surfaces_around_them() {
    // A point in space gathers the direct light leaving the surfaces
    // around it over fixed rays. Blending its nearest visible sparse
    // points' light instead measured 75 % relRMSE against one bounce on
    // the point-lit box's grid and 78 % on the corridor's (relight converge
    // SCENE -t lightskin), since a point in the middle of a room is nearer
    // the lit surfaces than the points on the walls; the gather measures
    // 12 % and 16 %. The bound is the 30 % for LightSkin; 256
    // reference paths add about 5 % of noise.
    for scene in ["cornell-box-point", "corridor"] {
        let context = shipped(scene);
        let technique = updated(&context, LightSkinParams::default());
        let error = relight_render::convergence::space_error(&context, &technique, 256);
        eprintln!("{scene}: points in space relRMSE {error:.3} against one bounce");
        assert!(error < 0.3, "{scene}: {error}");
    }
}

/// The bound for LightSkin on the closed boxes: the indirect image
/// within 15 % relRMSE of the one-bounce path tracer over 8x8-pixel tile
/// means. With the disc occlusion the point-lit box missed it (14.1 to
/// 16.4 %, 0.92x the light: the discs approximate visibility); with the
/// visibility traced between sparse points every box measures 1 to 6 %
/// at full resolution (relight converge SCENE -t lightskin). At half the
/// cameras' resolution the reference's own tile noise is about 2 %.
#[test]
fn closed_boxes_within_fifteen_percent_over_tiles_of_one_bounce() {
    let measured = relight_render::convergence::closed_box_measurements(|context, _| {
        Box::new(updated(context, LightSkinParams::default()))
    });
    for (scene, measured) in measured {
        assert!(
            measured.image_tiles <= 0.15,
            "{scene}: {}",
            measured.image_tiles
        );
    }
}

/// The 0.85-1.15x of the path tracer's light (one bounce, as
/// LightSkin computes) in the view from inside the unlit room, which sees
/// the lit room only through the doorway, and no seams or dark corners
/// there: over 8x8 tiles under 5 %, about twice what the defaults measure.
/// Full size (`relight converge scenes/two-rooms/scene-unlit-room.toml -t
/// lightskin`) measured 0.990x and 2.4 %; without the final gather
/// (`--sweep final_gather=0`), 0.967x and 11.9 %. The light ratio's own
/// noise over a whole image at 256 paths is well under 1 %, so its bound
/// is the issue's.
#[test]
fn unlit_room_gets_the_light_that_crosses_the_doorway() {
    let measured = relight_render::convergence::unlit_room_measurement(|context| {
        Box::new(updated(context, LightSkinParams::default()))
    });
    assert!(
        (0.85..1.15).contains(&measured.light_ratio),
        "{}",
        measured.light_ratio
    );
    assert!(measured.image_tiles < 0.05, "{}", measured.image_tiles);
}

/// Glossy light is gathered for the frame's camera: the same point and
/// view direction read other glossy light once the camera has moved (so a
/// frame that moves only the camera is not skipped), and a frame without a
/// camera uses the scene's.
#[test]
fn glossy_light_follows_the_frames_camera() {
    let mut scene = closed_cube(
        0.6,
        Light::Point {
            position: Vec3::new(0.5, 0.6, -0.4),
            intensity: Rgb::splat(5.0),
        },
    );
    scene.materials[0].phong_exponent = 40.0;
    scene.camera.eye = Vec3::new(-0.6, 0.2, 0.7);
    scene.camera.target = Vec3::new(0.0, -1.0, 0.0);
    let context = context_of(scene, TexelDensity::TargetResolution(32));
    let params = LightSkinParams {
        specular: 0.5,
        ..LightSkinParams::default()
    };
    let floor = relight_technique::SurfacePoint {
        position: Vec3::new(0.1, -1.0, 0.1),
        normal: Vec3::Y,
        triangle: (0..context.scene.mesh.triangles.len() as u32)
            .find(|&t| context.scene.mesh.geometric_normal(t as usize).y > 0.9)
            .unwrap(),
        barycentric: glam::Vec2::new(0.3, 0.3),
    };
    let floor = relight_technique::SurfacePoint {
        position: context
            .scene
            .mesh
            .point_at(floor.triangle as usize, floor.barycentric),
        ..floor
    };
    let toward_viewer = (context.scene.camera.eye - floor.position).normalize();
    let glossy_seen_from = |camera: Option<&relight_scene::Camera>| {
        let mut technique = LightSkin::new(context.clone(), params.clone()).unwrap();
        let lights = context.scene.lights.clone();
        technique
            .update(&Frame {
                lights: &lights,
                index: 0,
                camera,
                moving_mesh_poses: None,
            })
            .unwrap();
        technique
            .glossy_radiance(&floor, toward_viewer, 40.0)
            .expect("a glossy floor has glossy light")
    };
    let scene_camera = glossy_seen_from(None);
    let same = glossy_seen_from(Some(&context.scene.camera));
    let mut moved = context.scene.camera.clone();
    moved.eye = Vec3::new(0.7, 0.3, -0.6);
    let elsewhere = glossy_seen_from(Some(&moved));
    assert_eq!(scene_camera, same);
    assert!(scene_camera.max_element() > 0.0);
    assert!(
        (elsewhere - scene_camera).abs().max_element() > 0.01 * scene_camera.max_element(),
        "{elsewhere} against {scene_camera}"
    );
    // Glossy light is gathered in the update: a camera move alone is not
    // a repeated frame to skip, as it is without glossy surfaces.
    let mut technique = LightSkin::new(context.clone(), params.clone()).unwrap();
    let lights = context.scene.lights.clone();
    for (index, camera) in [None, Some(&moved)].into_iter().enumerate() {
        technique
            .update(&Frame {
                lights: &lights,
                index: index as u64,
                camera,
                moving_mesh_poses: None,
            })
            .unwrap();
        assert!(!technique.timings().skipped, "update {index}");
    }
    assert_eq!(
        technique.glossy_radiance(&floor, toward_viewer, 40.0),
        Some(elsewhere)
    );
}

/// A 120 m ground of two triangles under an open-topped 6 x 3 x 8 m room of
/// wall quads, lit by a low sun, loaded from a file as a user's would be (so
/// the ground is cut into rings of coarser lightmap texels).
fn ground_and_room_scene() -> Scene {
    let sun = "[[lights]]\nkind = \"directional\"\ndirection = [0.5, -0.6, 0.3]\nirradiance = [3, 3, 3]\n";
    relight_scene::generate::load_ground_and_room(sun).unwrap()
}

/// Sparse points and a sun's VALs follow the lightmap's detail: a ground
/// plane 100 times the room's area no longer takes nearly all of them.
#[test]
fn points_and_sun_vals_stay_where_the_detail_is() {
    let context = context_of(ground_and_room_scene(), TexelDensity::MetresPerTexel(0.25));
    let margin = context
        .scene
        .detail_region()
        .expect("the ground reaches out")
        .margin;
    let near_room =
        |p: Vec3| p.x.abs() < 3.0 + margin && p.z.abs() < 4.0 + margin && p.y < 3.0 + margin;
    let technique = updated(&context, LightSkinParams::default());
    let points = technique.sparse_points();
    let near = points.iter().filter(|&&p| near_room(p)).count();
    // By area the room and its margin hold 1.1 % of the surface; weighted by
    // the lightmap's density about 96 %.
    assert!(
        near as f64 > 0.8 * points.len() as f64,
        "{near} of {} sparse points near the room",
        points.len()
    );
    // The sun's map covers the room's surroundings, not the whole ground:
    // its 48 x 48 texels over the 170 m ground put about 4 VALs in the room.
    let vals = technique.vals();
    let in_room = (0..vals.count)
        .filter(|&index| vals.px[index].abs() < 3.0 && vals.pz[index].abs() < 4.0)
        .count();
    assert!(
        in_room > 100,
        "{in_room} of {} VALs in the room",
        vals.count
    );
}

/// The point light of the doubled-ceiling tests: off centre, so the
/// ceiling's light varies across it.
const SECOND_CEILING_LIGHT: &str =
    "[[lights]]\nkind = \"point\"\nposition = [0.8, 1.0, -0.5]\nintensity = [4, 4, 4]\n";

/// Mean irradiance of the visible ceiling's receivers in 0.5 m cells.
fn visible_ceiling_cells(
    context: &SceneContext,
    technique: &dyn Technique,
) -> std::collections::BTreeMap<[i32; 3], f64> {
    let [_, height, _] = relight_scene::generate::TEST_ROOM;
    let receivers = &context.atlas.receivers;
    let irradiance = technique.receiver_irradiance().expect("receiver values");
    let ceiling = (0..receivers.len()).filter(|&index| {
        receivers.normals[index].y < -0.9 && (receivers.positions[index].y - height).abs() < 0.005
    });
    relight_render::metrics::cell_means(
        ceiling.map(|index| (receivers.positions[index], irradiance[index])),
        0.5,
    )
}

/// A second ceiling 2.5 cm above the room's own, facing down like it (as
/// real models lay panels under a slab): no sparse point stands on it, and
/// the visible ceiling gets the light it gets without the hidden layer.
/// Points on the hidden layer gather nothing and, blended into the visible
/// ceiling, made dark blotches (the classroom's ceiling).
#[test]
fn a_hidden_second_ceiling_takes_no_points_and_leaves_no_blotch() {
    let gap = 0.025;
    let [_, height, _] = relight_scene::generate::TEST_ROOM;
    let run = |second_ceiling: Option<f32>| {
        let scene = relight_scene::generate::load_obj_scene(
            &relight_scene::generate::room_with_second_ceiling_obj(second_ceiling),
            SECOND_CEILING_LIGHT,
        )
        .expect("loads");
        let context = context_of(scene, TexelDensity::MetresPerTexel(0.05));
        let technique = updated(&context, LightSkinParams::default());
        let on_hidden_layer = technique
            .sparse_points()
            .iter()
            .filter(|point| point.y > height + 0.5 * gap)
            .count();
        (on_hidden_layer, visible_ceiling_cells(&context, &technique))
    };
    let (on_hidden_layer, doubled) = run(Some(gap));
    let (_, single) = run(None);
    let worst = relight_render::metrics::cell_ratio_range(&doubled, &single);
    println!("visible ceiling's 0.5 m cells, doubled over single: {worst:?}");
    assert_eq!(on_hidden_layer, 0, "sparse points on the hidden layer");
    // Both runs spread their own 4096 points, so cells differ by the
    // interpolation's noise alone: measured 0.995-1.003x; with points on
    // the hidden layer 0.23-0.79x.
    assert!(worst.0 > 0.85 && worst.1 < 1.15, "{worst:?}");
}

/// A closed room whose floor runs on under its +x wall into a low sun:
/// nothing lights the room. Floor texels 0.3 m wide straddle the wall,
/// their receivers inside and part of their area in the sun outside; the
/// VALs there took the inside receiver's anchor, and the room gathered
/// them through the wall (the generated halls: 3.3x the path tracer's
/// light).
#[test]
fn vals_outside_a_wall_do_not_light_the_room_through_a_shared_texel() {
    let [width, height, _] = relight_scene::generate::TEST_ROOM;
    let sun = "[[lights]]\nkind = \"directional\"\ndirection = [-0.8, -0.5, 0.1]\nirradiance = [3, 3, 3]\n";
    let scene = relight_scene::generate::load_obj_scene(
        &relight_scene::generate::room_on_a_longer_floor_obj(3.0),
        sun,
    )
    .expect("loads");
    let context = context_of(scene, TexelDensity::MetresPerTexel(0.3));
    let technique = updated(&context, LightSkinParams::default());
    let irradiance = technique.receiver_irradiance().expect("receiver values");
    let receivers = &context.atlas.receivers;
    let (mut inside, mut outside) = (0.0f32, 0.0f32);
    for (index, position) in receivers.positions.iter().enumerate() {
        let light = relight_core::luminance(irradiance[index]);
        if position.x < 0.5 * width - 0.01 && position.y < height {
            inside = inside.max(light);
        } else if position.y < 0.01 {
            outside = outside.max(light);
        }
    }
    println!("brightest receiver inside {inside}, on the floor outside {outside}");
    assert!(outside > 0.05, "the sunlit floor outside reflects light");
    // The path tracer gives the room nothing. Measured: 0.69 % of the
    // floor outside (the side walls by the +x wall; 0.36 % before the
    // loader cut the floor along the wall's foot), 26 % when VALs keep the
    // anchor of their texel's receiver.
    assert!(inside < 0.01 * outside, "{inside} inside against {outside}");
}

/// A generated hall lit by a low sun through small windows, whose wall
/// planes run past each other at the corners out into the sun (variant 8
/// of the default family): the light in view within 0.85-1.15x of the path
/// tracer's one bounce. Its sunlit floor and wall ends outside shared
/// texels with the floor and walls inside, and gave 3.3x before VALs had
/// to see their anchors.
#[test]
fn a_hall_whose_walls_run_out_into_the_sun_gets_the_light_of_one_bounce() {
    use relight_scene::generate::variants::{variant, VariantKind, VARIANTS_DEFAULT_SEED};
    let hall = variant(VARIANTS_DEFAULT_SEED, 8);
    assert_eq!(hall.kind, VariantKind::Hall, "{}", hall.name());
    let case = relight_render::robustness::VariantCase::load_temporary(
        hall,
        4,
        ContextSettings::default(),
    )
    .expect("the variant loads");
    let context = case.context;
    let lights = context.scene.lights.clone();
    let technique = updated(&context, LightSkinParams::default());
    let settings = PathSettings {
        max_bounces: 1,
        ..PathSettings::default()
    };
    let reference =
        relight_render::render::render_reference(&context, &lights, settings, 64, &NoProgress);
    let image = relight_render::render::render_with_technique(
        &context,
        &lights,
        &technique,
        4,
        1,
        &NoProgress,
    );
    let ratio =
        relight_render::metrics::light_ratio(&image.indirect.pixels, &reference.indirect.pixels);
    println!("light in view {ratio:.3}x of one bounce");
    // The bound on an unlit room's light. Measured 0.912x here (a
    // quarter of the camera's resolution, 64 paths a pixel; fixed seeds),
    // 0.994x in the robustness study (half, 256 paths); 3.28x before VALs
    // had to see their anchors.
    assert!((0.85..=1.15).contains(&ratio), "{ratio}");
}

/// Two rooms lit by a point light inside a lampshade, seen from the unlit
/// room (variants 52 and 61 of the default family: two boxes of large
/// quads, a shade open on one side). The shade's inside is smaller than
/// the sparse points' spacing, so its VALs had to borrow an anchor outside
/// it, and the unlit room's points saw that anchor or not depending on
/// where the points fell: on 61, light in view against one bounce 0.61x,
/// 0.99x, 0.98x and 0.36x with point seeds 1 to 4 (a 2048-path reference,
/// `relight robustness -t lightskin --first 61 --variants 1
/// --reference-spp 2048 --set seed=S`); 052 read 0.75x at the study's 256
/// paths. The static points now gather the surfaces beside the lamp from
/// the final gather's explicit samples, traced to them at load: 61 0.91x
/// with seeds 1 and 4 against 2048 paths, and at 256 paths 052 0.995x and
/// 061 0.931x with seed 1. Bound: the 0.85-1.15x in an unlit room,
/// for two point seeds, since a bound met by one placement of points is
/// met by chance.
#[test]
fn a_shaded_lamps_light_reaches_the_next_room_wherever_the_points_fall() {
    for index in [52, 61] {
        let case = relight_render::robustness::VariantCase::default_family(index)
            .expect("the variant loads");
        for seed in [1, 4] {
            let params = LightSkinParams {
                seed,
                ..LightSkinParams::default()
            };
            let technique = updated(&case.context, params);
            let (measured, _) = case.measure_as_the_study_does(&technique);
            assert!(
                (0.85..=1.15).contains(&measured.light_ratio),
                "variant {index}, point seed {seed}: {}",
                measured.light_ratio
            );
        }
    }
}

/// A point light 11 cm from a room's corner (variant 15 of the default
/// family: a 7 m room, walls as solids, 20 cm texels at the automatic
/// lightmap) makes a hot spot a few of its distances wide on each wall,
/// and each wall's indirect light there comes from the other's hot spot:
/// it varies over a decimetre. At the room's texels every technique read
/// 19-25 % over 8x8 tiles (LightSkin 21.4 % against one bounce; PRM 24.8 %,
/// and 8.3 % with the whole lightmap at 10 cm texels). The atlas now gives
/// the walls beside such a lamp finer texels: LightSkin 2.7 %. Bound: the
/// issue's 15 % for rooms (the reference's own tile noise is 2.4 %).
#[test]
fn walls_beside_a_lamp_in_a_corner_are_resolved() {
    let case =
        relight_render::robustness::VariantCase::default_family(15).expect("the variant loads");
    assert!(case.context.atlas.near_light_charts > 0);
    let technique = updated(&case.context, LightSkinParams::default());
    let (measured, _) = case.measure_as_the_study_does(&technique);
    assert!(measured.image_tiles < 0.15, "{}", measured.image_tiles);
}
