//! Stack-based traversal of the 4-wide BVH: one SIMD slab test per node,
//! nearest-first order for closest hit, early exit for occlusion.

use super::triangle::{intersect_packet, ShearedRay};
use super::{Hit, Ray, TrianglePacket, WideNode, EMPTY_CHILD, LEAF_FLAG};
use glam::{Vec2, Vec4};
use std::mem::MaybeUninit;

/// Enough for the deepest tree the builder can produce: it forces median
/// splits below depth `build::MAX_SAH_DEPTH`, so the binary depth is at most
/// 48 + 33, each wide level pushes at most three entries, and 3 * 81 < 256.
pub(crate) const STACK_SIZE: usize = 256;

/// Ize (2013), "Robust BVH Ray Traversal": scaling the far distance by
/// 1 + 2 gamma(3) makes the float slab test conservative.
const FAR_SCALE: f32 = 1.0 + 2.0 * (3.0 * f32::EPSILON * 0.5) / (1.0 - 3.0 * f32::EPSILON * 0.5);

/// Per-ray constants of the slab test, splatted across the four children.
struct SlabRay {
    origin: [Vec4; 3],
    inverse_direction: [Vec4; 3],
    /// Index into `WideNode::bounds` of the entry and exit plane per axis.
    near: [usize; 3],
    far: [usize; 3],
}

impl SlabRay {
    #[inline(always)]
    fn new(ray: &Ray) -> Self {
        // A zero component would make (plane - origin) * inf a NaN when the
        // origin lies on the plane; a tiny component of the same sign gives
        // a huge but finite inverse and the same answer everywhere else.
        let safe = |component: f32| {
            if component.abs() < 1e-30 {
                1e-30f32.copysign(component)
            } else {
                component
            }
        };
        let direction = [
            safe(ray.direction.x),
            safe(ray.direction.y),
            safe(ray.direction.z),
        ];
        let origin = ray.origin.to_array();
        let negative = direction.map(|component| (component < 0.0) as usize);
        Self {
            origin: origin.map(Vec4::splat),
            inverse_direction: direction.map(|component| Vec4::splat(1.0 / component)),
            near: [negative[0], 2 + negative[1], 4 + negative[2]],
            far: [1 - negative[0], 3 - negative[1], 5 - negative[2]],
        }
    }

    /// Entry distances and the mask of children the ray enters within
    /// (0, t_max).
    #[inline(always)]
    fn test(&self, node: &WideNode, t_max: f32) -> (Vec4, u32) {
        let plane = |index: usize, axis: usize| {
            (Vec4::from_array(node.bounds[index]) - self.origin[axis])
                * self.inverse_direction[axis]
        };
        let near_x = plane(self.near[0], 0);
        let near_y = plane(self.near[1], 1);
        let near_z = plane(self.near[2], 2);
        let far_x = plane(self.far[0], 0);
        let far_y = plane(self.far[1], 1);
        let far_z = plane(self.far[2], 2);
        let entry = near_x.max(near_y).max(near_z.max(Vec4::ZERO));
        let exit = far_x.min(far_y).min(far_z.min(Vec4::splat(t_max))) * FAR_SCALE;
        (entry, entry.cmple(exit).bitmask())
    }
}

#[derive(Clone, Copy)]
struct StackEntry {
    child: u32,
    entry_distance: f32,
}

/// Fixed-capacity stack on the machine stack; no per-ray allocation and no
/// initialisation cost (one uninitialised array, not an array of
/// uninitialised entries, which LLVM was zeroing with a 2 KiB memset).
struct TraversalStack {
    entries: [MaybeUninit<StackEntry>; STACK_SIZE],
    length: usize,
}

impl TraversalStack {
    #[inline(always)]
    fn new() -> Self {
        Self {
            entries: [const { MaybeUninit::uninit() }; STACK_SIZE],
            length: 0,
        }
    }

    #[inline(always)]
    fn push(&mut self, child: u32, entry_distance: f32) {
        debug_assert!(self.length < STACK_SIZE);
        // SAFETY: the builder bounds the tree depth so that at most
        // STACK_SIZE entries are ever pending (checked by `validate`).
        unsafe {
            self.entries
                .get_unchecked_mut(self.length)
                .write(StackEntry {
                    child,
                    entry_distance,
                });
        }
        self.length += 1;
    }

    #[inline(always)]
    fn pop(&mut self) -> Option<StackEntry> {
        if self.length == 0 {
            return None;
        }
        self.length -= 1;
        // SAFETY: entries below `length` were written by `push`.
        Some(unsafe { self.entries.get_unchecked(self.length).assume_init() })
    }
}

/// Returns the nearest child entered (`mask` non-zero) and stacks the
/// others farthest first, so they pop in order of entry distance.
#[inline(always)]
fn visit_nearest_first(node: &WideNode, entry: Vec4, mut mask: u32, stack: &mut TraversalStack) -> u32 {
    let first = mask.trailing_zeros() as usize;
    mask &= mask - 1;
    if mask == 0 {
        return node.children[first];
    }
    let distances = entry.to_array();
    let mut order = [(0.0f32, 0u32); 4];
    order[0] = (distances[first], node.children[first]);
    let mut count = 1;
    while mask != 0 {
        let slot = mask.trailing_zeros() as usize;
        mask &= mask - 1;
        let candidate = (distances[slot], node.children[slot]);
        let mut position = count;
        while position > 0 && order[position - 1].0 > candidate.0 {
            order[position] = order[position - 1];
            position -= 1;
        }
        order[position] = candidate;
        count += 1;
    }
    for &(distance, child) in order[1..count].iter().rev() {
        stack.push(child, distance);
    }
    order[0].1
}

/// Non-finite origins or directions would turn slab distances into NaN,
/// which the min/max chain does not reject; such rays hit nothing.
#[inline(always)]
fn is_traceable(ray: &Ray) -> bool {
    ray.t_max > 0.0 && ray.origin.is_finite() && ray.direction.is_finite()
}

#[inline(always)]
fn is_leaf(child: u32) -> bool {
    child & LEAF_FLAG != 0
}

/// Whether the AVX2/FMA builds of the traversal may run (checked once by std
/// and cached, so this is a load and a test per ray).
#[cfg(target_arch = "x86_64")]
#[inline(always)]
fn has_avx2() -> bool {
    std::arch::is_x86_feature_detected!("avx2") && std::arch::is_x86_feature_detected!("fma")
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2,fma")]
fn intersect_avx2(nodes: &[WideNode], packets: &[TrianglePacket], ray: &Ray) -> Option<Hit> {
    intersect_portable(nodes, packets, ray)
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2,fma")]
fn occluded_avx2(nodes: &[WideNode], packets: &[TrianglePacket], ray: &Ray) -> bool {
    occluded_portable(nodes, packets, ray)
}

/// The same traversal compiled for the baseline target and, on x86_64, with
/// AVX2/FMA enabled (VEX encoding, wider register file use); picked per call.
#[inline]
pub(crate) fn intersect(nodes: &[WideNode], packets: &[TrianglePacket], ray: &Ray) -> Option<Hit> {
    #[cfg(target_arch = "x86_64")]
    if has_avx2() {
        // SAFETY: the CPU supports the features the function is compiled for.
        return unsafe { intersect_avx2(nodes, packets, ray) };
    }
    intersect_portable(nodes, packets, ray)
}

#[inline]
pub(crate) fn occluded(nodes: &[WideNode], packets: &[TrianglePacket], ray: &Ray) -> bool {
    #[cfg(target_arch = "x86_64")]
    if has_avx2() {
        // SAFETY: as in `intersect`.
        return unsafe { occluded_avx2(nodes, packets, ray) };
    }
    occluded_portable(nodes, packets, ray)
}

#[inline(always)]
fn intersect_portable(nodes: &[WideNode], packets: &[TrianglePacket], ray: &Ray) -> Option<Hit> {
    let mut t_max = ray.t_max;
    if !is_traceable(ray) {
        return None;
    }
    let slab = SlabRay::new(ray);
    let sheared = ShearedRay::new(ray.origin, ray.direction);
    let mut stack = TraversalStack::new();
    let mut best: Option<(u32, f32, Vec2)> = None;
    let mut current = 0u32;
    loop {
        if is_leaf(current) {
            // SAFETY: the builder only emits packet indices below the count.
            let packet = unsafe { packets.get_unchecked((current & !LEAF_FLAG) as usize) };
            if let Some(hits) = intersect_packet(&sheared, packet, t_max) {
                let t = hits.t.to_array();
                let mut mask = hits.mask;
                let mut closest_lane = mask.trailing_zeros() as usize;
                mask &= mask - 1;
                while mask != 0 {
                    let lane = mask.trailing_zeros() as usize;
                    if t[lane] < t[closest_lane] {
                        closest_lane = lane;
                    }
                    mask &= mask - 1;
                }
                t_max = t[closest_lane];
                let inverse_determinant = 1.0 / hits.determinant.to_array()[closest_lane];
                let barycentric = Vec2::new(
                    hits.edge_v.to_array()[closest_lane] * inverse_determinant,
                    hits.edge_w.to_array()[closest_lane] * inverse_determinant,
                );
                best = Some((packet.triangles[closest_lane], t_max, barycentric));
            }
        } else {
            // SAFETY: the builder only emits node indices below the count.
            let node = unsafe { nodes.get_unchecked(current as usize) };
            let (entry, mask) = slab.test(node, t_max);
            if mask != 0 {
                current = visit_nearest_first(node, entry, mask, &mut stack);
                continue;
            }
        }
        // Pop the next child that can still hold a closer hit.
        loop {
            match stack.pop() {
                None => {
                    return best.map(|(triangle, t, barycentric)| Hit {
                        t,
                        triangle,
                        barycentric,
                    })
                }
                Some(entry) if entry.entry_distance <= t_max => {
                    current = entry.child;
                    break;
                }
                Some(_) => {}
            }
        }
    }
}

#[inline(always)]
fn occluded_portable(nodes: &[WideNode], packets: &[TrianglePacket], ray: &Ray) -> bool {
    let t_max = ray.t_max;
    if !is_traceable(ray) {
        return false;
    }
    let slab = SlabRay::new(ray);
    let sheared = ShearedRay::new(ray.origin, ray.direction);
    let mut stack = TraversalStack::new();
    let mut current = 0u32;
    loop {
        if is_leaf(current) {
            // SAFETY: the builder only emits packet indices below the count.
            let packet = unsafe { packets.get_unchecked((current & !LEAF_FLAG) as usize) };
            if intersect_packet(&sheared, packet, t_max).is_some() {
                return true;
            }
        } else {
            // SAFETY: the builder only emits node indices below the count.
            let node = unsafe { nodes.get_unchecked(current as usize) };
            let (_, mut mask) = slab.test(node, t_max);
            if mask != 0 {
                // Any order will do; sorting costs more than it saves here.
                current = node.children[mask.trailing_zeros() as usize];
                mask &= mask - 1;
                while mask != 0 {
                    stack.push(node.children[mask.trailing_zeros() as usize], 0.0);
                    mask &= mask - 1;
                }
                continue;
            }
        }
        match stack.pop() {
            None => return false,
            Some(entry) => current = entry.child,
        }
    }
}

/// Empty-slot bounds: min +inf, max -inf, so every slab test misses.
pub(crate) fn empty_node() -> WideNode {
    let mut bounds = [[0.0; 4]; 6];
    for axis in 0..3 {
        bounds[2 * axis] = [f32::INFINITY; 4];
        bounds[2 * axis + 1] = [f32::NEG_INFINITY; 4];
    }
    WideNode {
        bounds,
        children: [EMPTY_CHILD; 4],
    }
}

