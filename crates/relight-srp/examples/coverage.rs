//! Where automatic probe placement leaves receivers short of probes: runs
//! the placement and sorts the short receivers by what is around them
//! (normal ray escaping the scene, narrow free space, probes near but
//! hidden, the radius that would give them `min_probes`), with maps of the
//! short fraction over four height slices.
//!
//! Run: `cargo run --release -p relight-srp --example coverage -- SCENE.toml
//! PROBE_COUNT MIN_PROBES MAX_ADDED`

use glam::Vec3;
use relight_scene::atlas::TexelDensity;
use relight_srp::probes::{
    place_probes, receiver_sees_probe, receivers_seeing_geometry, PlacementSettings,
};
use relight_technique::{ContextSettings, SceneContext};
use relight_trace::Ray;

fn main() {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let [scene_path, count, min_probes, max_added] = args.as_slice() else {
        eprintln!("usage: coverage SCENE.toml PROBE_COUNT MIN_PROBES MAX_ADDED");
        std::process::exit(2);
    };
    let scene = relight_scene::load_scene(std::path::Path::new(scene_path)).expect("scene loads");
    let settings = ContextSettings {
        lightmap: TexelDensity::from_resolution(None),
        ..ContextSettings::default()
    };
    let context = SceneContext::new(scene, settings).expect("context");
    let min_probes: usize = min_probes.parse().unwrap();
    let start = std::time::Instant::now();
    let placement = place_probes(
        &context,
        PlacementSettings {
            count: count.parse().unwrap(),
            radius: 0.0,
            radius_factor: 2.0,
            min_probes,
            max_added: max_added.parse().unwrap(),
        },
    );
    println!(
        "{} probes ({} added), radius {:.3}, {} of {} receivers short of {min_probes} ({} see only the environment), placement {:.1} s",
        placement.probes.len(),
        placement.added_for_coverage,
        placement.radius,
        placement.receivers_short_of_probes,
        context.atlas.receivers.len(),
        placement.open_receivers,
        start.elapsed().as_secs_f32()
    );
    let (low, high) = context.scene.mesh.bounds();
    println!(
        "bounds {low} .. {high}, area {:.0}; {} probes outside the bounds",
        context.scene.mesh.total_area(),
        placement
            .probes
            .iter()
            .filter(|probe| !(probe.cmpge(low).all() && probe.cmple(high).all()))
            .count()
    );
    let receivers = &context.atlas.receivers;
    let epsilon = relight_trace::direct::ray_epsilon_for(&context.bvh);
    let radius = placement.radius;
    let mut escaped = 0;
    let mut crevice = 0;
    let mut none_in_reach = 0;
    let mut occluded_only = 0;
    let mut short_total = 0;
    let mut by_height = [0usize; 8];
    let mut by_axis = [0usize; 6];
    let mut growth = [0usize; 5];
    const COLUMNS: usize = 72;
    const ROWS: usize = 18;
    let cell = |position: Vec3| {
        let u = ((position.x - low.x) / (high.x - low.x) * COLUMNS as f32) as usize;
        let v = ((position.z - low.z) / (high.z - low.z) * ROWS as f32) as usize;
        (u.min(COLUMNS - 1), v.min(ROWS - 1))
    };
    let mut maps = vec![[[0usize; 2]; COLUMNS * ROWS]; 4];
    let level = |y: f32| ((((y - low.y) / (high.y - low.y)) * 4.0) as usize).min(3);
    let sees_geometry = receivers_seeing_geometry(&context);
    for (index, &sees) in sees_geometry.iter().enumerate() {
        if !sees {
            continue;
        }
        let position = receivers.positions[index];
        let normal = receivers.normals[index];
        let mut in_reach = 0;
        let mut seen = 0;
        let mut visible_distances = Vec::new();
        for probe in &placement.probes {
            let offset = *probe - position;
            if offset.dot(normal) <= 0.0 {
                continue;
            }
            let within = offset.length() < radius;
            in_reach += usize::from(within);
            if receiver_sees_probe(&context, position, normal, *probe, epsilon) {
                seen += usize::from(within);
                visible_distances.push(offset.length());
            }
        }
        let (u, v) = cell(position);
        maps[level(position.y)][v * COLUMNS + u][0] += 1;
        if seen >= min_probes {
            continue;
        }
        maps[level(position.y)][v * COLUMNS + u][1] += 1;
        short_total += 1;
        visible_distances.sort_by(f32::total_cmp);
        let needed = visible_distances
            .get(min_probes - 1)
            .map_or(f32::INFINITY, |d| d / radius);
        let bucket = [1.25f32, 1.5, 2.0, 3.0]
            .iter()
            .position(|&limit| needed <= limit)
            .unwrap_or(4);
        growth[bucket] += 1;
        let ray = Ray {
            origin: position + normal * epsilon,
            direction: normal,
            t_max: f32::INFINITY,
        };
        match context.bvh.intersect(&ray) {
            None => escaped += 1,
            Some(hit) if hit.t < 0.1 * radius => crevice += 1,
            _ => {}
        }
        if in_reach == 0 {
            none_in_reach += 1;
        } else if seen == 0 {
            occluded_only += 1;
        }
        let band = (((position.y - low.y) / (high.y - low.y)) * 8.0) as usize;
        by_height[band.min(7)] += 1;
        let axis = [Vec3::X, -Vec3::X, Vec3::Y, -Vec3::Y, Vec3::Z, -Vec3::Z]
            .iter()
            .enumerate()
            .max_by(|a, b| normal.dot(*a.1).total_cmp(&normal.dot(*b.1)))
            .unwrap()
            .0;
        by_axis[axis] += 1;
    }
    println!(
        "short {short_total}: normal ray escapes {escaped}, free space along normal < 0.1 r {crevice}, \
         no probe in reach {none_in_reach}, probes in reach but all occluded {occluded_only}"
    );
    for (index, map) in maps.iter().enumerate() {
        println!("level {index} (x across, z down): short fraction 0-9, '.' none short, ' ' no receivers, P probe");
        let mut probe_cells = vec![false; COLUMNS * ROWS];
        for probe in &placement.probes {
            if level(probe.y) == index {
                let (u, v) = cell(*probe);
                probe_cells[v * COLUMNS + u] = true;
            }
        }
        for v in 0..ROWS {
            let line: String = (0..COLUMNS)
                .map(|u| {
                    let [all, short] = map[v * COLUMNS + u];
                    if probe_cells[v * COLUMNS + u] {
                        'P'
                    } else if all == 0 {
                        ' '
                    } else if short == 0 {
                        '.'
                    } else {
                        char::from_digit(((short * 10 - 1) / all) as u32, 10).unwrap()
                    }
                })
                .collect();
            println!("|{line}|");
        }
    }
    println!("radius needed for min_probes (<=1.25r, 1.5r, 2r, 3r, more): {growth:?}");
    println!("by height (8 bands, low to high): {by_height:?}");
    println!("by normal (+x -x +y -y +z -z): {by_axis:?}");
}
