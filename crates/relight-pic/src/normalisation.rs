//! Link normalisation: each lightmap cache's links are scaled, once at
//! load, so that a uniform radiosity around the cache gives it the share
//! of its hemisphere that meets geometry (a white-furnace test).
//!
//! Why: a cache's links estimate the light of the nodes it sees from a
//! few surfel samples each, with discs for surfels and a cut that drops
//! children none of its samples saw. Under a uniform radiosity of one,
//! which should light every cache of a closed room with exactly one,
//! the caches of a generated two-room suite (variant 88 of `relight gen
//! variants`, PIC `high`) gathered 0.986 at the median but 0.916 at the
//! 10th percentile, and 0.90 within 5 cm of other geometry. Light loses
//! that share again at every bounce, so rooms whose light arrives after
//! many bounces (pale walls, a room lit through a doorway) came out
//! 0.81-0.90x of the path tracer's, while their first bounce was right.
//! The same test also catches the opposite: links that sum more than the
//! cache sees (overlapping discs where surfaces meet) are scaled down.
//!
//! A cache's scale is `seen / linked`, held to [`SCALE_RANGE`]: `linked`
//! is what its links gather when every surfel's radiosity is one (one pass
//! of the run-time cache lighting, so it is exactly what a frame
//! computes), `seen` the share of cosine-weighted rays from the cache that
//! meet any surface. The path tracer shades both sides of a triangle, so a
//! back face counts as seen: where two rooms' boxes share a wall plane,
//! the back-to-back faces at one distance would otherwise turn half the
//! wall's rays into misses (counting front faces only took variant 97's
//! tiles from 15.9 to 21.7 % instead of to 10.1 %). A cache on a surface
//! nobody sees, or with too little of either share ([`LEAST_SHARE`]),
//! keeps its links as baked. The scale multiplies the whole cache (every
//! SH band): the missing light is assumed to have the mean radiance of
//! what the cache does see, which overshoots where it is mostly a bright
//! near field (a suite lit by a lamp 16 cm from a corner went from 0.96x
//! to 1.08x of the path tracer's light in view).

use glam::{Vec2, Vec3};
use rayon::prelude::*;
use relight_core::sampling::{cosine_hemisphere_around, stratified_square, SampleStream};
use relight_technique::SceneContext;
use relight_trace::Ray;

/// Stratified cosine rays per cache are this squared. A cache that sees
/// all around (any closed room) measures exactly one whatever the count;
/// one that sees out of a window is off by about a percent at 256.
pub const RAYS_PER_SIDE: u32 = 16;

/// Below this, under uniform radiosity one, a cache's links or its view
/// are too little to scale by (a cache inside a solid, or one that sees
/// only sky): it keeps its links as baked.
pub const LEAST_SHARE: f32 = 0.05;

/// The scale stays within these bounds: a cache off by more is broken in
/// some other way that a scale would only hide.
pub const SCALE_RANGE: (f32, f32) = (0.5, 2.0);

/// Each lightmap cache's scale, given what its links gather under a
/// uniform radiosity of one (`linked`, one per cache of `positions` and
/// `normals`). A cache on a surface nobody sees (a second ceiling laid
/// just above the visible one, a face inside a solid) keeps its links:
/// from there every ray meets a back face, which no light reaches.
pub fn scales(
    context: &SceneContext,
    positions: &[Vec3],
    normals: &[Vec3],
    linked: &[f32],
) -> Vec<f32> {
    debug_assert!(positions.len() == normals.len() && normals.len() == linked.len());
    let lift = context.surface_lift();
    positions
        .par_iter()
        .zip(normals)
        .zip(linked)
        .enumerate()
        .map(|(cache, ((&position, &normal), &linked))| {
            if context.is_hidden_surface_point(position, normal, lift) {
                1.0
            } else {
                scale(
                    linked,
                    seen_share(context, position + normal * lift, normal, cache as u64),
                )
            }
        })
        .collect()
}

/// The share of the cosine-weighted hemisphere around `normal` at `origin`
/// whose rays meet a surface, either side of it.
pub fn seen_share(context: &SceneContext, origin: Vec3, normal: Vec3, seed: u64) -> f32 {
    let rays = RAYS_PER_SIDE * RAYS_PER_SIDE;
    let mut rng = SampleStream::new(0x5eed, seed, 0);
    let hits: u32 = (0..rays)
        .map(|index| {
            let square = stratified_square(index, rays, Vec2::ZERO, &mut rng);
            let ray = Ray {
                origin,
                direction: cosine_hemisphere_around(normal, square),
                t_max: f32::INFINITY,
            };
            u32::from(context.bvh.occluded(&ray))
        })
        .sum();
    hits as f32 / rays as f32
}

/// The scale of a cache whose links gather `linked` under a uniform
/// radiosity of one and whose view meets geometry over `seen` of its
/// cosine-weighted hemisphere.
fn scale(linked: f32, seen: f32) -> f32 {
    if linked > LEAST_SHARE && seen > LEAST_SHARE {
        (seen / linked).clamp(SCALE_RANGE.0, SCALE_RANGE.1)
    } else {
        1.0
    }
}

/// Says (at `RELIGHT_LOG=info`) how far the scales spread.
pub fn log_scales(scales: &[f32], took: std::time::Duration) {
    if scales.is_empty() {
        return;
    }
    let mut sorted = scales.to_vec();
    sorted.sort_unstable_by(f32::total_cmp);
    let at = |share: f64| sorted[((sorted.len() - 1) as f64 * share) as usize];
    tracing::info!(
        "pic link normalisation: {} caches scaled by {:.3} / {:.3} / {:.3} / {:.3} / {:.3} (1st / 10th / 50th / 90th / 99th percentile) in {:.2} s",
        sorted.len(),
        at(0.01),
        at(0.1),
        at(0.5),
        at(0.9),
        at(0.99),
        took.as_secs_f64(),
    );
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn scales_bring_the_links_to_what_the_cache_sees() {
        assert!((scale(0.9, 0.99) - 1.1).abs() < 1e-6);
        assert!((scale(1.2, 1.0) - 1.0 / 1.2).abs() < 1e-6);
        // Too little to scale by, or too far off to trust a scale.
        assert_eq!(scale(0.01, 1.0), 1.0);
        assert_eq!(scale(0.8, 0.0), 1.0);
        assert_eq!(scale(0.2, 1.0), SCALE_RANGE.1);
        assert_eq!(scale(3.0, 1.0), SCALE_RANGE.0);
    }

    /// Inside a closed room every ray meets a surface; just above its roof,
    /// looking down, the rays meet the ceiling's back face, which counts
    /// (the path tracer shades both sides), and looking up they meet
    /// nothing. Tolerance: 1 cm above the middle of a 4 x 5 m roof, the
    /// share of a cosine lobe that passes its edges is 3e-5, so 0.99
    /// (two of 256 rays) is never reached by chance.
    #[test]
    fn seen_share_counts_either_side_and_not_the_sky() {
        let context = relight_technique::robustness::closed_grey_room(0.5);
        let (low, high) = context.scene.mesh.bounds();
        let centre = (low + high) / 2.0;
        assert_eq!(seen_share(&context, centre, Vec3::Y, 1), 1.0);
        assert_eq!(seen_share(&context, centre, -Vec3::Z, 2), 1.0);
        let above_roof = Vec3::new(centre.x, high.y + 0.01, centre.z);
        assert!(seen_share(&context, above_roof, -Vec3::Y, 3) > 0.99);
        assert_eq!(seen_share(&context, above_roof, Vec3::Y, 4), 0.0);
    }
}
