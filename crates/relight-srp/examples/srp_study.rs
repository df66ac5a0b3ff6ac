//! SRP parameter study: one path-traced reference lightmap (cached on disk),
//! then for each parameter set the lightmap relRMSE of SRP, its bake time
//! and the bake's own figures (probes, coverage, energy kept by CPCA); with
//! `SRP_WORST=1` also the worst receivers next to one exact gather step
//! from the reference's light (what unlimited probes would give).
//!
//! Run: `cargo run --release -p relight-srp --example srp_study -- SCENE.toml
//! RESOLUTION REFERENCE_SAMPLES "order=7" "order=2" "probe_count=64" ...`
//! (RESOLUTION 0 = the automatic lightmap size).

use glam::Vec3;
use relight_core::{luminance, Rgb};
use relight_render::metrics::error_norms;
use relight_render::study::run_study;
use relight_srp::probes::{openness_directions, receivers_seeing_geometry, visible_counts};
use relight_srp::{SrpBake, SrpKind, BAKE_PARAMETERS};
use relight_technique::SceneContext;

fn detail(context: &SceneContext, bake: &[u8], values: &[Rgb], reference: &[Rgb]) {
    let lights = context.scene.lights.clone();
    // Where the error sits: per dominant normal axis, and the ratio of
    // mean luminance (bias) to the reference's.
    let normals = &context.atlas.receivers.normals;
    let mut by_axis = String::new();
    for (name, axis) in [
        ("+x", Vec3::X),
        ("-x", -Vec3::X),
        ("+y", Vec3::Y),
        ("-y", -Vec3::Y),
        ("+z", Vec3::Z),
        ("-z", -Vec3::Z),
    ] {
        let members: Vec<usize> = (0..normals.len())
            .filter(|&i| normals[i].dot(axis) > 0.7)
            .collect();
        if members.is_empty() {
            continue;
        }
        let pick = |values: &[Rgb]| members.iter().map(|&i| values[i]).collect::<Vec<_>>();
        let norms = error_norms(&pick(values), &pick(reference));
        let ratio = pick(values)
            .iter()
            .map(|v| luminance(*v) as f64)
            .sum::<f64>()
            / pick(reference)
                .iter()
                .map(|v| luminance(*v) as f64)
                .sum::<f64>();
        by_axis += &format!(" {name}: {:.1} % x{ratio:.3};", norms.relative_rmse * 100.0);
    }
    println!("   {by_axis}");
    if std::env::var_os("SRP_WORST").is_some() {
        let mut order: Vec<usize> = (0..values.len()).collect();
        let ratio = |i: usize| luminance(values[i]) / luminance(reference[i]).max(1e-6);
        let difference = |i: usize| (luminance(values[i]) - luminance(reference[i])).abs();
        order.sort_by(|&a, &b| difference(a).total_cmp(&difference(b)).reverse());
        let reference_map = context.atlas.to_lightmap(reference);
        let direct = context.direct();
        for &i in order.iter().take(6) {
            // One gather step of the rendering equation from the
            // reference's own light: what exact probes would give.
            let position = context.atlas.receivers.positions[i] + normals[i] * 1e-4;
            let mut sum = Rgb::ZERO;
            let count = 4096;
            for sample in 0..count {
                let mut rng = relight_core::SampleStream::new(9, i as u64, sample);
                let direction =
                    relight_core::sampling::cosine_hemisphere_around(normals[i], rng.next_vec2());
                let ray = relight_trace::Ray {
                    origin: position,
                    direction,
                    t_max: f32::INFINITY,
                };
                if let Some(hit) = context.bvh.intersect(&ray) {
                    let triangle = hit.triangle as usize;
                    let front = context.scene.mesh.geometric_normal(triangle);
                    if front.dot(direction) >= 0.0 {
                        continue;
                    }
                    let point = context.scene.mesh.point_at(triangle, hit.barycentric);
                    let irradiance = direct.irradiance(&lights, point, front, sample)
                        + context
                            .atlas
                            .sample(&reference_map, hit.triangle, hit.barycentric);
                    sum += context.scene.albedo_at(triangle, hit.barycentric) * irradiance;
                }
            }
            let gathered = luminance(sum / count as f32);
            println!(
                    "    receiver {i} at {:.3} n {:.2}: srp/reference {:.3} (reference {:.4}, one gather {:.4})",
                    context.atlas.receivers.positions[i],
                    normals[i],
                    ratio(i),
                    luminance(reference[i]),
                    gathered
                );
        }
    }
    let decoded = SrpBake::decode(bake).expect("decode");
    if std::env::var_os("SRP_SPLIT").is_some() {
        split_by_visible_probes(context, &decoded, values, reference);
    }
    let stats = &decoded.stats;
    println!(
            "    {} probes ({} added), radius {:.3}, {} receivers short of {}, {:.2} nearby, {:.1} % valid samples, {:.4} energy kept, {} clusters, {} probe-visible texels",
            decoded.probes.len(),
            stats.added_for_coverage,
            decoded.radius,
            stats.receivers_short_of_probes,
            stats.min_probes,
            stats.mean_nearby,
            stats.valid_sample_fraction * 100.0,
            stats.captured_energy,
            decoded.clusters.cluster_count(),
            decoded.visible_receivers.len()
        );
}

fn main() {
    run_study(&SrpKind, &BAKE_PARAMETERS, &detail);
}

/// With `SRP_SPLIT=1`: the squared error split by how many probes within
/// the radius each receiver sees (0, 1 to 2, 3 or more), as each group's
/// share of the total and its own relRMSE, and the receivers placement
/// leaves out (seeing only sky, or only back faces) with their share and
/// mean reference light, which should be nil.
fn split_by_visible_probes(
    context: &SceneContext,
    bake: &SrpBake,
    values: &[Rgb],
    reference: &[Rgb],
) {
    let receivers = &context.atlas.receivers;
    let epsilon = relight_trace::direct::ray_epsilon_for(&context.bvh);
    let groups: Vec<usize> = visible_counts(context, &bake.probes, bake.radius)
        .into_iter()
        .map(|seen| seen.min(3).div_ceil(2))
        .collect();
    let mut squared_error = [0.0f64; 3];
    let mut squared_reference = [0.0f64; 3];
    let mut counts = [0usize; 3];
    for ((group, value), truth) in groups.iter().zip(values).zip(reference) {
        squared_error[*group] += (*value - *truth).length_squared() as f64;
        squared_reference[*group] += truth.length_squared() as f64;
        counts[*group] += 1;
    }
    let total: f64 = squared_error.iter().sum();
    // Receivers that need no probe, by why: every test ray escapes, or some
    // hit only back faces.
    let sees_geometry = receivers_seeing_geometry(context);
    let mut open = [(0usize, 0.0f64, 0.0f64); 2];
    for index in 0..receivers.len() {
        if sees_geometry[index] {
            continue;
        }
        let normal = receivers.normals[index];
        let origin = receivers.positions[index] + normal * epsilon;
        let hits_back = openness_directions(normal).any(|direction| {
            let ray = relight_trace::Ray {
                origin,
                direction,
                t_max: f32::INFINITY,
            };
            context.bvh.occluded(&ray)
        });
        let slot = &mut open[usize::from(hits_back)];
        slot.0 += 1;
        slot.1 += (values[index] - reference[index]).length_squared() as f64;
        slot.2 += luminance(reference[index]) as f64;
    }
    for (name, (count, error, light)) in ["sky only", "back faces"].iter().zip(open) {
        println!(
            "    open ({name}): {count} receivers, {:.1} % of the squared error, mean reference luminance {:.4}",
            100.0 * error / total,
            light / count.max(1) as f64
        );
    }
    for (group, name) in ["0 probes", "1-2 probes", "3+ probes"].iter().enumerate() {
        println!(
            "    {name}: {} receivers, {:.1} % of the squared error, relRMSE {:.1} %",
            counts[group],
            100.0 * squared_error[group] / total,
            100.0 * (squared_error[group] / squared_reference[group].max(1e-30)).sqrt()
        );
    }
}
