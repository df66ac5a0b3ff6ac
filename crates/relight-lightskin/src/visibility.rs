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
//! seen by every point.

use crate::points::{Nearest, PointGrid};
use crate::vals::{Vals, NO_SITE};
use glam::Vec3;
use rayon::prelude::*;
use relight_scene::atlas::Atlas;
use relight_trace::{Bvh, Ray};

/// Bits per visibility word.
pub const WORD_BITS: usize = 32;

/// [`Vals::block_word`] of a block whose anchors fall in several words.
pub const MIXED_WORDS: u32 = u32::MAX;

/// A VAL's anchor must face its side of the surface this closely (cosine
/// between the point's and the VAL's normals): the nearest point of a
/// corner's other wall sees a different part of the room.
const ANCHOR_MIN_COS: f32 = 0.5;

/// Mutual visibility of the static sparse points as one bit row per
/// point, plus an all-visible row for points that move (the moving meshes'
/// sparse points): they are not where any shadow ray was traced.
/// Column `points` is the unanchored VAL's and is set in every row.
#[derive(Clone, Debug, Default)]
pub struct PointVisibility {
    points: usize,
    words_per_row: usize,
    bits: Vec<u32>,
    /// Per receiver: its anchor for VALs on its front and on its back.
    receiver_anchors: Vec<[u32; 2]>,
    /// The atlas's receiver of each texel, gutters included.
    receiver_of_texel: Vec<u32>,
}

impl PointVisibility {
    /// Traces every pair of `positions` (static points, with their surface
    /// `normals`), each end lifted off its surface by `epsilon`.
    pub fn trace(bvh: &Bvh, positions: &[Vec3], normals: &[Vec3], epsilon: f32) -> Self {
        let points = positions.len();
        let words_per_row = (points + 1).div_ceil(WORD_BITS);
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
        Self {
            points,
            words_per_row,
            bits,
            receiver_anchors: Vec::new(),
            receiver_of_texel: Vec::new(),
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
        self.bits.len() * 4 + self.receiver_anchors.len() * 8 + self.receiver_of_texel.len() * 4
    }

    /// Finds each receiver's anchors, front and back: the nearest static
    /// point (`positions`, `normals`) within `reach` facing that side.
    /// A VAL later takes the anchor of the receiver whose texel it lands
    /// on, for its side: one lookup per VAL and frame.
    pub fn anchor_receivers(
        &mut self,
        atlas: &Atlas,
        positions: &[Vec3],
        normals: &[Vec3],
        reach: f32,
    ) {
        let unanchored = self.unanchored();
        let grid = PointGrid::new(positions, reach);
        let receivers = &atlas.receivers;
        self.receiver_anchors = (0..receivers.len())
            .into_par_iter()
            .map_init(Nearest::default, |found, receiver| {
                let position = receivers.positions[receiver];
                [1.0, -1.0].map(|side| {
                    let normal = receivers.normals[receiver] * side;
                    grid.nearest_facing_within(position, normal, normals, reach, found);
                    found
                        .as_slice()
                        .iter()
                        .find(|&&(point, distance)| {
                            distance <= reach
                                && normals[point as usize].dot(normal) >= ANCHOR_MIN_COS
                        })
                        .map_or(unanchored, |&(point, _)| point)
                })
            })
            .collect();
        self.receiver_of_texel = atlas.dilated_receiver_of_texel();
    }

    /// Gives every VAL of `vals` its anchor: the anchor of the receiver
    /// whose texel it lies in, on the VAL's side; [`Self::unanchored`] for
    /// VALs off the static mesh and for padding (which carries no power).
    pub fn anchor_vals(&self, vals: &mut Vals, atlas: &Atlas) {
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
                let uv = atlas.uv_of(triangle, vals_ref.site_barycentric[index]);
                let x = (uv.x.floor() as i64).clamp(0, width - 1);
                let y = (uv.y.floor() as i64).clamp(0, height - 1);
                let receiver = self.receiver_of_texel[(y * width + x) as usize];
                if receiver == u32::MAX {
                    return;
                }
                let normal = Vec3::new(vals_ref.nx[index], vals_ref.ny[index], vals_ref.nz[index]);
                let front = atlas.receivers.normals[receiver as usize].dot(normal) >= 0.0;
                *anchor = self.receiver_anchors[receiver as usize][usize::from(!front)];
            });
        vals.group_by_anchor(anchors);
    }
}

/// Whether a visibility row has `anchor`'s bit.
#[inline]
pub fn row_sees(row: &[u32], anchor: u32) -> bool {
    let anchor = anchor as usize;
    row[anchor / WORD_BITS] >> (anchor % WORD_BITS) & 1 != 0
}
