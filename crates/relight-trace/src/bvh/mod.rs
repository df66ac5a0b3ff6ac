//! The ray-tracing acceleration structure: every bake and every frame's
//! direct light traces against this, so it is the hot path of relight.
//!
//! Design:
//! - **Build** (`build.rs`): a binary binned-SAH tree (32 bins on all three
//!   axes, cost counted in packets of four triangles because a leaf packet
//!   costs the same for one to four triangles). Large nodes bin in parallel
//!   and the two halves of a split are built with `rayon::join`. Every
//!   decision is a pure function of the input (bins merge with min/max and
//!   integer sums, which are order independent), so the tree is bit-identical
//!   for any thread count. A child's bounds come from the bins of its side
//!   of the split and its centroid bounds from the partition pass, so no
//!   node pays a separate bounds pass. Deep, badly split chains fall back
//!   to median splits, which bounds the depth and hence the traversal stack.
//! - **Layout**: the binary tree is collapsed into an 8-wide BVH stored as two
//!   flat arrays: [`WideNode`] (struct-of-arrays child bounds, so one ray
//!   tests all eight children with one SIMD slab test) and [`TrianglePacket`]
//!   (four triangles' vertices copied in leaf order, struct-of-arrays,
//!   tested together; a leaf is one or two consecutive packets, chosen by
//!   SAH with a traversal cost so the bottom of the tree is not all
//!   half-empty nodes). Children are plain `u32` indices, so a GPU path can
//!   upload both arrays as they are.
//! - **Traversal** (`traverse.rs`): ordered by entry distance for closest hit
//!   (nearest child first, farther ones stacked with their distance so they
//!   are skipped once a closer hit is known); for occlusion, in slot order
//!   with early exit, where the builder sorts slots by decreasing
//!   min(triangle area inside, box area): big boxes full of surface are the
//!   likeliest to block a ray. The stack is a fixed array on the machine
//!   stack; nothing is allocated per ray. The slab test picks near/far
//!   planes by the sign of the ray direction and widens the far distance by
//!   a few ulps (Ize 2013), so boxes are never missed by rounding.
//! - **Triangles** (`triangle.rs`): the watertight test of Woop, Benthin and
//!   Wald (2013), four triangles per SIMD packet, with a double-precision
//!   re-evaluation of edge functions that round to exactly zero. A ray
//!   through a shared edge or vertex of a closed mesh hits at least one of
//!   the triangles sharing it; degenerate triangles never hit.
//! - **SIMD**: node tests run on eight lanes: AVX (`std::arch`) in copies of
//!   the traversal compiled with AVX2/FMA, chosen at run time on x86_64 CPUs
//!   that have them, otherwise two `glam::Vec4` (SSE2 on x86_64, NEON on
//!   aarch64, scalar elsewhere). Triangle packets always use `glam::Vec4`.
//!   Measured on the shared scenes (single thread, CPU time per ray): the
//!   8-wide AVX traversal is about 1.4x faster than the same code 4-wide
//!   with SSE2; slot-order occlusion beats nearest-first occlusion by about
//!   1.4x (ordering only pays for closest hit), and biggest-box-first slot
//!   order gains another 15% on Sponza, and weighing box area by the
//!   triangle area inside (leaves first among equals) cuts node and packet
//!   tests per occlusion ray by another 1-4%. Things measured that did not help: 64 instead of 32 bins,
//!   software prefetch of stacked children or of leaf packets, one FMA per
//!   plane instead of subtract-multiply, sorting only the nearest child,
//!   branch-free (rank-counting) child ordering, testing both packets of a
//!   two-packet leaf in one 8-wide AVX test, 8-bit quantised child bounds
//!   (128-byte nodes; 25-40% slower: looser boxes and decoding cost more
//!   than the smaller nodes save), pre-splitting large triangles (Karras
//!   and Aila 2013; fewer packet tests but more node visits, 10-30% slower
//!   occlusion), and other SAH traversal costs or leaf sizes (within noise).
//!
//! Triangles with zero area or non-finite vertices are dropped at build time
//! (they can never be hit); [`Bvh::triangle_count`] still reports the input
//! count and hits always name indices into the input list.

mod build;
#[cfg(feature = "embree")]
pub mod embree;
mod traverse;
mod triangle;

use glam::{Vec2, Vec3};
use rayon::prelude::*;

#[cfg(feature = "embree")]
pub use embree::EmbreeScene;

/// An empty shadow cache for [`Bvh::occluded_cached`].
pub const NO_OCCLUDER: u32 = u32::MAX;

#[derive(Clone, Copy, Debug)]
pub struct Ray {
    pub origin: Vec3,
    /// Need not be unit length; `t` is measured in multiples of it.
    pub direction: Vec3,
    pub t_max: f32,
}

#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Hit {
    pub t: f32,
    /// Index into the triangle list given to [`Bvh::build`].
    pub triangle: u32,
    /// Weights (b1, b2) of vertices 1 and 2: p = (1-b1-b2) v0 + b1 v1 + b2 v2.
    pub barycentric: Vec2,
}

/// A child slot that holds nothing; its bounds are empty (min +inf, max -inf).
pub const EMPTY_CHILD: u32 = u32::MAX;
/// Set on a child reference that names a leaf instead of a node. A leaf is
/// `LEAF_FLAG | (packet count - 1) << LEAF_COUNT_SHIFT | first packet`: its
/// packets are consecutive in [`Bvh::packets`].
pub const LEAF_FLAG: u32 = 1 << 31;
pub const LEAF_COUNT_SHIFT: u32 = 28;
pub const LEAF_INDEX_MASK: u32 = (1 << LEAF_COUNT_SHIFT) - 1;

/// (first packet, packet count) of a leaf child reference.
#[inline(always)]
pub fn leaf_packets(child: u32) -> (usize, usize) {
    (
        (child & LEAF_INDEX_MASK) as usize,
        (((child & !LEAF_FLAG) >> LEAF_COUNT_SHIFT) + 1) as usize,
    )
}

/// Children per node.
pub const WIDTH: usize = 8;

/// One node of the 8-wide BVH (256 bytes, four cache lines).
/// `bounds[2 * axis]` holds the minima and `bounds[2 * axis + 1]` the maxima
/// of the children along `axis`, so the near plane of an axis is
/// `bounds[2 * axis + (direction < 0)]`.
#[repr(C, align(64))]
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct WideNode {
    pub bounds: [[f32; WIDTH]; 6],
    /// Node index, leaf reference (see [`LEAF_FLAG`]), or [`EMPTY_CHILD`].
    pub children: [u32; WIDTH],
}

/// Up to four triangles, vertices gathered in leaf order.
/// `vertices[corner][axis][lane]`; unused lanes repeat the last used lane, so
/// they can only ever report a hit the packet already reports.
#[repr(C, align(16))]
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct TrianglePacket {
    pub vertices: [[[f32; 4]; 3]; 3],
    /// Indices into the input triangle list.
    pub triangles: [u32; 4],
}

pub struct Bvh {
    nodes: Vec<WideNode>,
    packets: Vec<TrianglePacket>,
    input_triangle_count: usize,
    stored_triangle_count: usize,
    bounds: (Vec3, Vec3),
}

/// Rays per rayon task in the batch methods: large enough to amortise task
/// overhead, small enough to balance incoherent batches across threads.
const BATCH_CHUNK: usize = 256;

impl Bvh {
    /// Builds the tree in parallel on the current rayon pool. Deterministic:
    /// the same input gives the same node and packet arrays on any number of
    /// threads.
    ///
    /// # Panics
    /// If a triangle names a vertex index outside `positions`.
    pub fn build(positions: &[Vec3], triangles: &[[u32; 3]]) -> Bvh {
        build::build(positions, triangles)
    }

    /// Closest hit with 0 < t < `ray.t_max`; front and back faces both hit.
    #[inline]
    pub fn intersect(&self, ray: &Ray) -> Option<Hit> {
        crate::counters::count_closest_hit();
        traverse::intersect(&self.nodes, &self.packets, ray, |_| true)
    }

    /// [`Bvh::intersect`] among the triangles `accept` takes (by their index
    /// in the list given to [`Bvh::build`]); the others are transparent.
    #[inline]
    pub fn intersect_where(&self, ray: &Ray, accept: impl Fn(u32) -> bool) -> Option<Hit> {
        crate::counters::count_closest_hit();
        traverse::intersect(&self.nodes, &self.packets, ray, accept)
    }

    /// [`Bvh::intersect`], except that a back face yields to a front face
    /// at most `tolerance` (in units of t) beyond it. `faces_the_ray` says
    /// which triangles face the ray (the tree keeps no normals).
    ///
    /// Two surfaces in one plane facing away from each other (rooms
    /// modelled as separate boxes that touch: each room's wall in the
    /// plane of the next room's) tie along any ray, and the tree returns
    /// whichever it meets first: from one side, now one room's wall, now
    /// the back of the other's. A rasteriser that culls back faces shows
    /// the front one, and a point on or just off that plane belongs to the
    /// room the front face looks into.
    pub fn intersect_front_first(
        &self,
        ray: &Ray,
        tolerance: f32,
        faces_the_ray: impl Fn(u32) -> bool,
    ) -> Option<Hit> {
        let hit = self.intersect(ray)?;
        if faces_the_ray(hit.triangle) {
            return Some(hit);
        }
        let within_tolerance = Ray {
            t_max: (hit.t + tolerance).min(ray.t_max),
            ..*ray
        };
        Some(
            self.intersect_where(&within_tolerance, faces_the_ray)
                .unwrap_or(hit),
        )
    }

    /// Whether anything is hit with 0 < t < `ray.t_max`.
    #[inline]
    pub fn occluded(&self, ray: &Ray) -> bool {
        crate::counters::count_occlusion();
        traverse::occluded(&self.nodes, &self.packets, ray, &mut { NO_OCCLUDER })
    }

    /// [`Bvh::occluded`] that first tries the geometry which blocked an
    /// earlier, similar ray: `cache` starts as [`NO_OCCLUDER`] and is
    /// updated whenever this ray is blocked. Rays toward one light from
    /// neighbouring points, taken in order, mostly skip their traversal.
    /// The answer is the same for any `cache` value.
    #[inline]
    pub fn occluded_cached(&self, ray: &Ray, cache: &mut u32) -> bool {
        crate::counters::count_occlusion();
        traverse::occluded(&self.nodes, &self.packets, ray, cache)
    }

    /// [`Bvh::intersect`] for every ray, in parallel.
    ///
    /// # Panics
    /// If `hits` and `rays` differ in length.
    pub fn intersect_batch(&self, rays: &[Ray], hits: &mut [Option<Hit>]) {
        assert_eq!(rays.len(), hits.len(), "one hit slot per ray");
        rays.par_chunks(BATCH_CHUNK)
            .zip(hits.par_chunks_mut(BATCH_CHUNK))
            .for_each(|(ray_chunk, hit_chunk)| {
                for (ray, hit) in ray_chunk.iter().zip(hit_chunk) {
                    *hit = self.intersect(ray);
                }
            });
    }

    /// [`Bvh::occluded`] for every ray, in parallel.
    ///
    /// # Panics
    /// If `occluded` and `rays` differ in length.
    pub fn occluded_batch(&self, rays: &[Ray], occluded: &mut [bool]) {
        assert_eq!(rays.len(), occluded.len(), "one result slot per ray");
        rays.par_chunks(BATCH_CHUNK)
            .zip(occluded.par_chunks_mut(BATCH_CHUNK))
            .for_each(|(ray_chunk, result_chunk)| {
                for (ray, result) in ray_chunk.iter().zip(result_chunk) {
                    *result = self.occluded(ray);
                }
            });
    }

    /// Number of triangles given to [`Bvh::build`], degenerate ones included.
    pub fn triangle_count(&self) -> usize {
        self.input_triangle_count
    }

    /// Number of triangles stored in leaves (the input minus degenerate ones).
    pub fn stored_triangle_count(&self) -> usize {
        self.stored_triangle_count
    }

    pub fn node_count(&self) -> usize {
        self.nodes.len()
    }

    pub fn packet_count(&self) -> usize {
        self.packets.len()
    }

    pub fn memory_bytes(&self) -> usize {
        std::mem::size_of::<Self>()
            + self.nodes.len() * std::mem::size_of::<WideNode>()
            + self.packets.len() * std::mem::size_of::<TrianglePacket>()
    }

    /// Bounding box (min, max) of all stored triangles; both zero when none.
    pub fn bounds(&self) -> (Vec3, Vec3) {
        self.bounds
    }

    /// The flat node array; node 0 is the root (always present).
    pub fn nodes(&self) -> &[WideNode] {
        &self.nodes
    }

    /// The flat leaf array that `LEAF_FLAG` children index.
    pub fn packets(&self) -> &[TrianglePacket] {
        &self.packets
    }

    /// Checks the tree invariants: every node is reached exactly once from
    /// the root, every child's contents lie inside its slot bounds, every
    /// stored triangle appears in exactly one leaf, empty slots have empty
    /// bounds, and the depth fits the traversal stack.
    pub fn validate(&self) -> Result<(), String> {
        build::validate(self)
    }
}
