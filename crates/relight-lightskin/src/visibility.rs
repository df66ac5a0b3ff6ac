//! Which static sparse points see each other, traced once when the scene
//! is loaded, and the VAL anchors that use it every frame.
//!
//! The disc occlusion of section 3.3 dims a point's light by the sparse
//! points between it and the averaged light, so a wall dims light through
//! it only as far as its few points cover the projected light sphere: on
//! the living room, sunlit outer walls lit the rooms behind them (the
//! thin-geometry receivers got 1.12x the path tracer's one bounce). Static
//! points and static walls stay where they are, so their mutual visibility
//! is fixed: one shadow ray per pair of static points (n^2 / 2 rays, 8.4M
//! for the default 4096 points), which is a load-time cost, not a bake.
//!
//! Every lightmap receiver gets, at load, the nearest static point on each
//! side of its surface (its anchors). Each frame, every VAL takes the
//! anchor of the receiver it lands on, for its side, and a sparse point
//! gathers a VAL only if it sees the VAL's anchor. A VAL with no static
//! point near it on its side (the back of a one-sided wall), or off the
//! static mesh (a moving mesh, a captured point cloud), is unanchored and
//! seen by every point. An anchor must be seen from the receiver, and
//! each frame from the VAL: where points face a receiver's side nearby but
//! it sees none of them (a wall plane running on past a corner, outside
//! the building), or a VAL sees neither its receiver's anchor nor any
//! other point near it, the VAL is hidden and seen by no point.

use crate::points::{Nearest, PointGrid};
use crate::vals::{Vals, NO_SITE, WORD_BITS};
use glam::Vec3;
use rayon::prelude::*;
use relight_scene::atlas::Atlas;
use relight_trace::{Bvh, Ray};

/// How far anchor visibility rays start off their surfaces, over the
/// anchors' reach (two points' spacings): a tenth of a spacing, as PRM's
/// pane points lift theirs. With the ray epsilon alone, VALs on Sponza's
/// columns and drapes lost sight of anchors a chord away, and the point
/// light's indirect light fell to 0.92x.
const ANCHOR_LIFT: f32 = 0.05;

/// How much farther than its usual reach a receiver looks for an anchor it
/// sees before its VALs count as hidden or unanchored: the inside of a
/// lamp's shade, smaller than the points' spacing, has none of its own,
/// and unanchored its VALs would light the room through the shade.
const WIDER_REACH: f32 = 4.0;

/// A VAL's anchor while it is being replaced: it does not see the anchor
/// its receiver gave it.
const BLOCKED: u32 = u32::MAX;

/// A VAL's anchor must face its side of the surface this closely (cosine
/// between the point's and the VAL's normals): the nearest point of a
/// corner's other wall sees a different part of the room.
const ANCHOR_MIN_COS: f32 = 0.5;

/// Mutual visibility of the static sparse points as one bit row per
/// point, plus an all-visible row for points that move (the moving meshes'
/// sparse points): they are not where any shadow ray was traced.
/// Column `points` is the unanchored VAL's and is set in every row;
/// column `points + 1` is the hidden VAL's and is set in none.
#[derive(Clone, Debug, Default)]
pub struct PointVisibility {
    points: usize,
    words_per_row: usize,
    bits: Vec<u32>,
    /// Per receiver: its anchor for VALs on its front and on its back.
    receiver_anchors: Vec<[u32; 2]>,
    /// The static points in a grid of `reach` cells, and their normals,
    /// kept from [`Self::anchor_receivers`]: each frame a VAL's anchor is
    /// checked against them (both ends lifted `anchor_lift`), and a VAL
    /// that does not see its anchor looks for another.
    grid: Option<PointGrid<'static>>,
    normals: Vec<Vec3>,
    anchor_lift: f32,
    /// How far from a receiver its anchors may stand.
    reach: f32,
}

impl PointVisibility {
    /// Traces every pair of `positions` (static points, with their surface
    /// `normals`), each end lifted off its surface by `epsilon`.
    pub fn trace(bvh: &Bvh, positions: &[Vec3], normals: &[Vec3], epsilon: f32) -> Self {
        let points = positions.len();
        let words_per_row = (points + 2).div_ceil(WORD_BITS);
        let lifted: Vec<Vec3> = positions
            .iter()
            .zip(normals)
            .map(|(&position, &normal)| position + normal * epsilon)
            .collect();
        let lifted = &lifted;
        // Each row traces the pairs after its point; the lower triangle is
        // mirrored below. Rows are uneven, so small tasks balance them.
        let mut bits = vec![0u32; (points + 1) * words_per_row];
        bits.par_chunks_mut(words_per_row)
            .take(points)
            .enumerate()
            .with_max_len(16)
            .for_each(|(from, row)| {
                for to in from + 1..points {
                    let ray = Ray {
                        origin: lifted[from],
                        direction: lifted[to] - lifted[from],
                        // Stops short of the far end so that the surface it
                        // stands on does not count as in the way.
                        t_max: 1.0 - 1e-3,
                    };
                    if !bvh.occluded(&ray) {
                        row[to / WORD_BITS] |= 1 << (to % WORD_BITS);
                    }
                }
            });
        for from in 0..points {
            for to in from + 1..points {
                if bits[from * words_per_row + to / WORD_BITS] & (1 << (to % WORD_BITS)) != 0 {
                    bits[to * words_per_row + from / WORD_BITS] |= 1 << (from % WORD_BITS);
                }
            }
        }
        for from in 0..points {
            bits[from * words_per_row + points / WORD_BITS] |= 1 << (points % WORD_BITS);
            bits[from * words_per_row + from / WORD_BITS] |= 1 << (from % WORD_BITS);
        }
        bits[points * words_per_row..].fill(u32::MAX);
        let hidden = points + 1;
        bits[points * words_per_row + hidden / WORD_BITS] &= !(1 << (hidden % WORD_BITS));
        Self {
            points,
            words_per_row,
            bits,
            receiver_anchors: Vec::new(),
            grid: None,
            normals: Vec::new(),
            anchor_lift: epsilon,
            reach: 0.0,
        }
    }

    /// Whether there is anything to look up (no static points: nothing).
    pub fn is_empty(&self) -> bool {
        self.bits.is_empty()
    }

    /// The anchor index of a VAL that no static point stands for.
    pub fn unanchored(&self) -> u32 {
        self.points as u32
    }

    /// The anchor index of a VAL on a surface that no point near it sees
    /// (a wall plane running on past the corner outside a building): its
    /// light reaches nobody.
    pub fn hidden(&self) -> u32 {
        self.points as u32 + 1
    }

    /// The row of sparse point `point` (static points first; any later
    /// index is a moving point and sees everything).
    #[inline]
    pub fn row(&self, point: usize) -> &[u32] {
        let row = point.min(self.points);
        &self.bits[row * self.words_per_row..(row + 1) * self.words_per_row]
    }

    /// Pairs of static points that see each other, over all pairs.
    pub fn visible_fraction(&self) -> f64 {
        if self.points < 2 {
            return 1.0;
        }
        let mut visible = 0u64;
        for point in 0..self.points {
            // Less the point itself and the unanchored column.
            visible += self
                .row(point)
                .iter()
                .map(|word| word.count_ones() as u64)
                .sum::<u64>()
                - 2;
        }
        visible as f64 / (self.points * (self.points - 1)) as f64
    }

    pub fn memory_bytes(&self) -> usize {
        self.bits.len() * 4
            + self.receiver_anchors.len() * 8
            + (self.grid.as_ref().map_or(0, |grid| grid.positions().len()) + self.normals.len())
                * 12
    }

    /// Finds each receiver's anchors, front and back: the nearest static
    /// point (`positions`, `normals`) within `reach` facing that side, and
    /// not behind the receiver's surface on it
    /// ([`PointGrid::nearest_in_front_within`]), that the receiver sees (a ray between them, both ends lifted off their
    /// surfaces by a twentieth of `reach` and at least `epsilon`, so that
    /// a chord across a column or a tessellated floor is not taken for a
    /// wall). A VAL later takes the anchor of the receiver whose texel it
    /// lands on, for its side: one lookup per VAL and frame.
    ///
    /// A receiver side with no such point looks `WIDER_REACH` (4) times
    /// as far. One with points facing it, none of which it sees, is hidden
    /// ([`Self::hidden`]): a wall plane that runs on past the corner
    /// outside a building finds the points of its own plane inside, behind
    /// the other wall, and its sunlit VALs would light the room through
    /// it. One with no such points at all (the back of a one-sided wall)
    /// stays unanchored.
    pub fn anchor_receivers(
        &mut self,
        bvh: &Bvh,
        atlas: &Atlas,
        (positions, normals): (&[Vec3], &[Vec3]),
        (reach, epsilon): (f32, f32),
    ) {
        self.reach = reach;
        self.anchor_lift = (ANCHOR_LIFT * reach).max(epsilon);
        let lift = self.anchor_lift;
        let unanchored = self.unanchored();
        let hidden = self.hidden();
        let grid = PointGrid::owned(positions.to_vec(), reach);
        let receivers = &atlas.receivers;
        self.receiver_anchors = (0..receivers.len())
            .into_par_iter()
            .map_init(Nearest::default, |found, receiver| {
                let position = receivers.positions[receiver];
                [1.0, -1.0].map(|side| {
                    let normal = receivers.normals[receiver] * side;
                    let sees = |point: u32| {
                        let point = point as usize;
                        sees_lifted(
                            bvh,
                            lift,
                            (position, normal),
                            (positions[point], normals[point]),
                        )
                    };
                    let mut any_facing = false;
                    for search in [reach, WIDER_REACH * reach] {
                        grid.nearest_in_front_within(position, normal, normals, search, found);
                        let mut facing = found
                            .as_slice()
                            .iter()
                            .filter(|&&(point, distance)| {
                                distance <= search
                                    && normals[point as usize].dot(normal) >= ANCHOR_MIN_COS
                            })
                            .map(|&(point, _)| point)
                            .peekable();
                        any_facing |= facing.peek().is_some();
                        if let Some(point) = facing.find(|&point| sees(point)) {
                            return point;
                        }
                    }
                    if any_facing {
                        hidden
                    } else {
                        unanchored
                    }
                })
            })
            .collect();
        self.grid = Some(grid);
        self.normals = normals.to_vec();
    }

    /// Gives every VAL of `vals` its anchor: the anchor of the receiver
    /// whose texel it lies in, on the VAL's side; [`Self::unanchored`] for
    /// VALs off the static mesh and for padding (which carries no power).
    ///
    /// A VAL must see its anchor (one ray each, `bvh`): a texel can
    /// straddle a wall, its receiver moved to the part inside the room,
    /// while the VAL lies on the part outside (a floor plane that runs on
    /// under the wall into the sun), and the receiver's anchor would let
    /// the room gather it. Such a VAL takes the nearest point facing its
    /// side that it sees, or is hidden.
    ///
    /// Hidden rather than unanchored: a VAL that sees no point near it is
    /// on a surface the room's points do not see either (a wall plane
    /// running on past a corner, outside the building); seen by every
    /// point, the VALs inside a lamp's shade lit the points on the shade's
    /// outside, a centimetre away (a generated suite of two rooms: 24x the
    /// path tracer's light). The shade's inside is now the near-light
    /// samples' (below).
    ///
    /// VALs on surfaces that `near_light(triangle, position)` takes are
    /// hidden too: the points gather those surfaces' light from explicit
    /// samples instead (`relight_technique::NearLightSamples`).
    ///
    /// `shown_receiver` is the atlas's receiver of each texel, gutters
    /// included ([`Atlas::dilated_receiver_of_texel`]).
    pub fn anchor_vals(
        &self,
        vals: &mut Vals,
        atlas: &Atlas,
        shown_receiver: &[u32],
        bvh: &Bvh,
        near_light: impl Fn(u32, Vec3) -> bool + Sync,
    ) {
        let hidden = self.hidden();
        let unanchored = self.unanchored();
        let width = atlas.width as i64;
        let height = atlas.height as i64;
        let mut anchors = std::mem::take(&mut vals.anchor);
        anchors.clear();
        anchors.resize(vals.padded_len(), unanchored);
        let vals_ref = &*vals;
        anchors[..vals.count]
            .par_iter_mut()
            .with_min_len(1024)
            .enumerate()
            .for_each(|(index, anchor)| {
                let triangle = vals_ref.site_triangle[index];
                if triangle == NO_SITE || triangle as usize >= atlas.triangle_uvs.len() {
                    return;
                }
                let position =
                    Vec3::new(vals_ref.px[index], vals_ref.py[index], vals_ref.pz[index]);
                if near_light(triangle, position) {
                    *anchor = hidden;
                    return;
                }
                let uv = atlas.uv_of(triangle, vals_ref.site_barycentric[index]);
                let x = (uv.x.floor() as i64).clamp(0, width - 1);
                let y = (uv.y.floor() as i64).clamp(0, height - 1);
                let receiver = shown_receiver[(y * width + x) as usize];
                if receiver == u32::MAX {
                    return;
                }
                let normal = Vec3::new(vals_ref.nx[index], vals_ref.ny[index], vals_ref.nz[index]);
                let front = atlas.receivers.normals[receiver as usize].dot(normal) >= 0.0;
                *anchor = self.receiver_anchors[receiver as usize][usize::from(!front)];
                if (*anchor as usize) < self.points && !self.sees(bvh, vals_ref, index, *anchor) {
                    *anchor = BLOCKED;
                }
            });
        if anchors.contains(&BLOCKED) {
            self.reanchor_blocked(vals, &mut anchors, bvh);
        }
        vals.group_by_anchor(anchors);
    }

    /// The static points' grid; VALs have anchors only once
    /// [`Self::anchor_receivers`] has built it.
    fn anchor_grid(&self) -> &PointGrid<'static> {
        self.grid
            .as_ref()
            .expect("VAL anchors come from anchor_receivers, which builds the grid")
    }

    /// Whether VAL `index` of `vals` sees static point `point`.
    fn sees(&self, bvh: &Bvh, vals: &Vals, index: usize, point: u32) -> bool {
        let normal = Vec3::new(vals.nx[index], vals.ny[index], vals.nz[index]);
        let position = Vec3::new(vals.px[index], vals.py[index], vals.pz[index]);
        let point = point as usize;
        let grid = self.anchor_grid();
        sees_lifted(
            bvh,
            self.anchor_lift,
            (position, normal),
            (grid.positions()[point], self.normals[point]),
        )
    }

    /// Anchors each VAL marked [`BLOCKED`] to the nearest static point
    /// within the wider reach, facing its side and in front of it, that it
    /// sees; hidden if none.
    fn reanchor_blocked(&self, vals: &Vals, anchors: &mut [u32], bvh: &Bvh) {
        let hidden = self.hidden();
        let grid = self.anchor_grid();
        anchors[..vals.count]
            .par_iter_mut()
            .enumerate()
            .filter(|(_, anchor)| **anchor == BLOCKED)
            .for_each_init(Nearest::default, |found, (index, anchor)| {
                let normal = Vec3::new(vals.nx[index], vals.ny[index], vals.nz[index]);
                let position = Vec3::new(vals.px[index], vals.py[index], vals.pz[index]);
                let reach = WIDER_REACH * self.reach;
                grid.nearest_in_front_within(position, normal, &self.normals, reach, found);
                *anchor = found
                    .as_slice()
                    .iter()
                    .filter(|&&(point, distance)| {
                        distance <= reach
                            && self.normals[point as usize].dot(normal) >= ANCHOR_MIN_COS
                    })
                    .map(|&(point, _)| point)
                    .find(|&point| self.sees(bvh, vals, index, point))
                    .unwrap_or(hidden);
            });
    }
}

/// Whether nothing lies between two surface points (position, normal),
/// each lifted `lift` off its surface.
fn sees_lifted(bvh: &Bvh, lift: f32, from: (Vec3, Vec3), to: (Vec3, Vec3)) -> bool {
    let origin = from.0 + from.1 * lift;
    let target = to.0 + to.1 * lift;
    !bvh.occluded(&Ray {
        origin,
        direction: target - origin,
        t_max: 1.0 - 1e-3,
    })
}
