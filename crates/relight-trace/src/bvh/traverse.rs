//! Stack-based traversal of the 8-wide BVH: one SIMD slab test of all
//! eight children per node, nearest-first order for closest hit, early exit
//! for occlusion.
//!
//! The traversal is written once, generic over an eight-lane float type:
//! AVX (`__m256`) inside functions compiled with AVX2/FMA on x86_64 CPUs
//! that have them, and two `glam::Vec4` (SSE2/NEON/scalar) everywhere else.

use super::triangle::{intersect_packet, ShearedRay};
use super::{leaf_packets, Hit, Ray, TrianglePacket, WideNode, EMPTY_CHILD, LEAF_FLAG, WIDTH};
use glam::{Vec2, Vec4};
use std::mem::MaybeUninit;

/// Enough for the deepest tree the builder can produce: it forces median
/// splits below depth `build::MAX_SAH_DEPTH` (48), so the binary depth is at
/// most 48 + 33; a wide level is at least one binary level and pushes at
/// most WIDTH - 1 = 7 entries, and 7 * 81 + 1 <= 576.
pub(crate) const STACK_SIZE: usize = 576;

/// Ize (2013), "Robust BVH Ray Traversal": scaling the far distance by
/// 1 + 2 gamma(3) makes the float slab test conservative.
const FAR_SCALE: f32 = 1.0 + 2.0 * (3.0 * f32::EPSILON * 0.5) / (1.0 - 3.0 * f32::EPSILON * 0.5);

/// Eight f32 lanes: what the slab test needs and nothing more.
///
/// # Safety
/// Implementations may use instructions the caller must know are available
/// (see `AvxLanes`); every method is therefore `unsafe`.
trait Lanes: Copy {
    unsafe fn load(values: &[f32; WIDTH]) -> Self;
    unsafe fn splat(value: f32) -> Self;
    unsafe fn sub(self, other: Self) -> Self;
    unsafe fn mul(self, other: Self) -> Self;
    unsafe fn min(self, other: Self) -> Self;
    unsafe fn max(self, other: Self) -> Self;
    /// Bit i set where lane i of self <= other.
    unsafe fn less_equal_mask(self, other: Self) -> u32;
    unsafe fn to_array(self) -> [f32; WIDTH];
}

#[derive(Clone, Copy)]
struct PortableLanes([Vec4; 2]);

impl Lanes for PortableLanes {
    #[inline(always)]
    unsafe fn load(values: &[f32; WIDTH]) -> Self {
        Self([
            Vec4::from_slice(&values[..4]),
            Vec4::from_slice(&values[4..]),
        ])
    }
    #[inline(always)]
    unsafe fn splat(value: f32) -> Self {
        Self([Vec4::splat(value); 2])
    }
    #[inline(always)]
    unsafe fn sub(self, other: Self) -> Self {
        Self([self.0[0] - other.0[0], self.0[1] - other.0[1]])
    }
    #[inline(always)]
    unsafe fn mul(self, other: Self) -> Self {
        Self([self.0[0] * other.0[0], self.0[1] * other.0[1]])
    }
    #[inline(always)]
    unsafe fn min(self, other: Self) -> Self {
        Self([self.0[0].min(other.0[0]), self.0[1].min(other.0[1])])
    }
    #[inline(always)]
    unsafe fn max(self, other: Self) -> Self {
        Self([self.0[0].max(other.0[0]), self.0[1].max(other.0[1])])
    }
    #[inline(always)]
    unsafe fn less_equal_mask(self, other: Self) -> u32 {
        self.0[0].cmple(other.0[0]).bitmask() | (self.0[1].cmple(other.0[1]).bitmask() << 4)
    }
    #[inline(always)]
    unsafe fn to_array(self) -> [f32; WIDTH] {
        let (low, high) = (self.0[0].to_array(), self.0[1].to_array());
        [
            low[0], low[1], low[2], low[3], high[0], high[1], high[2], high[3],
        ]
    }
}

/// Only constructed inside `#[target_feature(enable = "avx2,fma")]`
/// functions, which run only after the CPU was checked for AVX2.
#[cfg(target_arch = "x86_64")]
#[derive(Clone, Copy)]
struct AvxLanes(std::arch::x86_64::__m256);

#[cfg(target_arch = "x86_64")]
impl Lanes for AvxLanes {
    #[inline(always)]
    unsafe fn load(values: &[f32; WIDTH]) -> Self {
        Self(std::arch::x86_64::_mm256_loadu_ps(values.as_ptr()))
    }
    #[inline(always)]
    unsafe fn splat(value: f32) -> Self {
        Self(std::arch::x86_64::_mm256_set1_ps(value))
    }
    #[inline(always)]
    unsafe fn sub(self, other: Self) -> Self {
        Self(std::arch::x86_64::_mm256_sub_ps(self.0, other.0))
    }
    #[inline(always)]
    unsafe fn mul(self, other: Self) -> Self {
        Self(std::arch::x86_64::_mm256_mul_ps(self.0, other.0))
    }
    #[inline(always)]
    unsafe fn min(self, other: Self) -> Self {
        Self(std::arch::x86_64::_mm256_min_ps(self.0, other.0))
    }
    #[inline(always)]
    unsafe fn max(self, other: Self) -> Self {
        Self(std::arch::x86_64::_mm256_max_ps(self.0, other.0))
    }
    #[inline(always)]
    unsafe fn less_equal_mask(self, other: Self) -> u32 {
        use std::arch::x86_64::{_mm256_cmp_ps, _mm256_movemask_ps, _CMP_LE_OQ};
        _mm256_movemask_ps(_mm256_cmp_ps::<_CMP_LE_OQ>(self.0, other.0)) as u32
    }
    #[inline(always)]
    unsafe fn to_array(self) -> [f32; WIDTH] {
        std::mem::transmute::<std::arch::x86_64::__m256, [f32; WIDTH]>(self.0)
    }
}

/// Per-ray constants of the slab test, splatted across the children.
struct SlabRay<L: Lanes> {
    origin: [L; 3],
    inverse_direction: [L; 3],
    zero: L,
    /// Index into `WideNode::bounds` of the entry and exit plane per axis.
    near: [usize; 3],
    far: [usize; 3],
}

impl<L: Lanes> SlabRay<L> {
    #[inline(always)]
    unsafe fn new(ray: &Ray) -> Self {
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
            origin: origin.map(|value| L::splat(value)),
            inverse_direction: direction.map(|component| L::splat(1.0 / component)),
            zero: L::splat(0.0),
            near: [negative[0], 2 + negative[1], 4 + negative[2]],
            far: [1 - negative[0], 3 - negative[1], 5 - negative[2]],
        }
    }

    /// Entry distances and the mask of children the ray enters within
    /// (0, t_max). Empty slots (min +inf, max -inf) always fail.
    #[inline(always)]
    unsafe fn test(&self, node: &WideNode, t_max: f32) -> (L, u32) {
        let plane = |index: usize, axis: usize| {
            L::load(&node.bounds[index])
                .sub(self.origin[axis])
                .mul(self.inverse_direction[axis])
        };
        let near_x = plane(self.near[0], 0);
        let near_y = plane(self.near[1], 1);
        let near_z = plane(self.near[2], 2);
        let far_x = plane(self.far[0], 0);
        let far_y = plane(self.far[1], 1);
        let far_z = plane(self.far[2], 2);
        let entry = near_x.max(near_y).max(near_z.max(self.zero));
        let exit = far_x
            .min(far_y)
            .min(far_z.min(L::splat(t_max)))
            .mul(L::splat(FAR_SCALE));
        (entry, entry.less_equal_mask(exit))
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
unsafe fn visit_nearest_first<L: Lanes>(
    node: &WideNode,
    entry: L,
    mut mask: u32,
    stack: &mut TraversalStack,
) -> u32 {
    let first = mask.trailing_zeros() as usize;
    mask &= mask - 1;
    if mask == 0 {
        return node.children[first];
    }
    let distances = entry.to_array();
    let mut order = [(0.0f32, 0u32); WIDTH];
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

/// The lanes of `mask` whose triangle `accept` takes.
#[inline(always)]
fn accepted_lanes(mask: u32, triangles: &[u32; 4], accept: &impl Fn(u32) -> bool) -> u32 {
    let mut kept = 0;
    let mut remaining = mask;
    while remaining != 0 {
        let lane = remaining.trailing_zeros();
        remaining &= remaining - 1;
        if accept(triangles[lane as usize]) {
            kept |= 1 << lane;
        }
    }
    kept
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
fn intersect_avx2(
    nodes: &[WideNode],
    packets: &[TrianglePacket],
    ray: &Ray,
    accept: impl Fn(u32) -> bool,
) -> Option<Hit> {
    // SAFETY: AVX2 is enabled for this function.
    unsafe { intersect_generic::<AvxLanes>(nodes, packets, ray, accept) }
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2,fma")]
fn occluded_avx2(
    nodes: &[WideNode],
    packets: &[TrianglePacket],
    ray: &Ray,
    occluder: &mut u32,
) -> bool {
    // SAFETY: AVX2 is enabled for this function.
    unsafe { occluded_generic::<AvxLanes>(nodes, packets, ray, occluder) }
}

/// The same traversal compiled for the baseline target and, on x86_64, with
/// AVX2/FMA enabled (VEX encoding, wider register file use); picked per call.
/// Only triangles `accept` takes count as hits; the unfiltered caller passes
/// a closure that is constant true, which compiles the test away.
#[inline]
pub(crate) fn intersect(
    nodes: &[WideNode],
    packets: &[TrianglePacket],
    ray: &Ray,
    accept: impl Fn(u32) -> bool,
) -> Option<Hit> {
    #[cfg(target_arch = "x86_64")]
    if has_avx2() {
        // SAFETY: the CPU supports the features the function is compiled for.
        return unsafe { intersect_avx2(nodes, packets, ray, accept) };
    }
    // SAFETY: PortableLanes needs no CPU features beyond the target's.
    unsafe { intersect_generic::<PortableLanes>(nodes, packets, ray, accept) }
}

/// `occluder` is a triangle packet index tested before the traversal, and
/// set to the packet that blocks this ray when one does (a shadow cache:
/// neighbouring shadow rays toward one light are mostly blocked by the same
/// geometry). Any value is safe: one past the packets skips the test, and a
/// packet that misses only costs its test, so the answer never depends on
/// it.
#[inline]
pub(crate) fn occluded(
    nodes: &[WideNode],
    packets: &[TrianglePacket],
    ray: &Ray,
    occluder: &mut u32,
) -> bool {
    #[cfg(target_arch = "x86_64")]
    if has_avx2() {
        // SAFETY: as in `intersect`.
        return unsafe { occluded_avx2(nodes, packets, ray, occluder) };
    }
    // SAFETY: as in `intersect`.
    unsafe { occluded_generic::<PortableLanes>(nodes, packets, ray, occluder) }
}

/// # Safety
/// `L`'s instructions must be available (see [`Lanes`]).
#[inline(always)]
unsafe fn intersect_generic<L: Lanes>(
    nodes: &[WideNode],
    packets: &[TrianglePacket],
    ray: &Ray,
    accept: impl Fn(u32) -> bool,
) -> Option<Hit> {
    let mut t_max = ray.t_max;
    if !is_traceable(ray) {
        return None;
    }
    let slab = SlabRay::<L>::new(ray);
    let sheared = ShearedRay::new(ray.origin, ray.direction);
    let mut stack = TraversalStack::new();
    let mut best: Option<(u32, f32, Vec2)> = None;
    let mut current = 0u32;
    loop {
        if is_leaf(current) {
            let (first_packet, packet_count) = leaf_packets(current);
            for packet_index in first_packet..first_packet + packet_count {
                // SAFETY: the builder only emits packet ranges inside the array.
                let packet = unsafe { packets.get_unchecked(packet_index) };
                if let Some(hits) = intersect_packet(&sheared, packet, t_max) {
                    let t = hits.t.to_array();
                    let mut mask = accepted_lanes(hits.mask, &packet.triangles, &accept);
                    if mask == 0 {
                        continue;
                    }
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

/// # Safety
/// As for [`intersect_generic`].
#[inline(always)]
unsafe fn occluded_generic<L: Lanes>(
    nodes: &[WideNode],
    packets: &[TrianglePacket],
    ray: &Ray,
    occluder: &mut u32,
) -> bool {
    let t_max = ray.t_max;
    if !is_traceable(ray) {
        return false;
    }
    let sheared = ShearedRay::new(ray.origin, ray.direction);
    if let Some(packet) = packets.get(*occluder as usize) {
        if intersect_packet(&sheared, packet, t_max).is_some() {
            return true;
        }
    }
    let slab = SlabRay::<L>::new(ray);
    let mut stack = TraversalStack::new();
    let mut current = 0u32;
    loop {
        if is_leaf(current) {
            let (first_packet, packet_count) = leaf_packets(current);
            for packet_index in first_packet..first_packet + packet_count {
                // SAFETY: the builder only emits packet ranges inside the array.
                let packet = unsafe { packets.get_unchecked(packet_index) };
                if intersect_packet(&sheared, packet, t_max).is_some() {
                    *occluder = packet_index as u32;
                    return true;
                }
            }
        } else {
            // SAFETY: the builder only emits node indices below the count.
            let node = unsafe { nodes.get_unchecked(current as usize) };
            let (_, mut mask) = slab.test(node, t_max);
            if mask != 0 {
                // Slot order, not distance order: the builder puts big boxes
                // first, and sorting by distance costs more than it saves
                // here. Stacked from the last slot so slots pop in order.
                current = node.children[mask.trailing_zeros() as usize];
                mask &= mask - 1;
                while mask != 0 {
                    let slot = 31 - mask.leading_zeros() as usize;
                    stack.push(node.children[slot], 0.0);
                    mask &= !(1 << slot);
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
    let mut bounds = [[0.0; WIDTH]; 6];
    for axis in 0..3 {
        bounds[2 * axis] = [f32::INFINITY; WIDTH];
        bounds[2 * axis + 1] = [f32::NEG_INFINITY; WIDTH];
    }
    WideNode {
        bounds,
        children: [EMPTY_CHILD; WIDTH],
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::bvh::Bvh;
    use glam::Vec3;
    use relight_core::sampling::{uniform_sphere, Pcg32};

    /// A thousand random triangles overlapping in a 10 m cube.
    fn scattered_triangles(rng: &mut Pcg32) -> (Vec<Vec3>, Vec<[u32; 3]>) {
        let positions = (0..3000)
            .map(|_| Vec3::new(rng.next_f32(), rng.next_f32(), rng.next_f32()) * 10.0)
            .collect();
        let triangles = (0..1000u32)
            .map(|index| [3 * index, 3 * index + 1, 3 * index + 2])
            .collect();
        (positions, triangles)
    }

    /// A random ray from inside [`scattered_triangles`]' cube.
    fn scattered_ray(rng: &mut Pcg32) -> Ray {
        Ray {
            origin: Vec3::new(rng.next_f32(), rng.next_f32(), rng.next_f32()) * 10.0,
            direction: uniform_sphere(rng.next_vec2()),
            t_max: 1.0 + 20.0 * rng.next_f32(),
        }
    }

    /// The AVX and the portable lane types must give identical answers; the
    /// integration tests only reach the one the CPU selects.
    #[test]
    fn bvh_portable_and_dispatched_traversal_agree() {
        let mut rng = Pcg32::new(5, 1);
        let (positions, triangles) = scattered_triangles(&mut rng);
        let bvh = Bvh::build(&positions, &triangles);
        for _ in 0..2000 {
            let ray = scattered_ray(&mut rng);
            // SAFETY: PortableLanes needs no CPU features.
            let portable = unsafe {
                intersect_generic::<PortableLanes>(&bvh.nodes, &bvh.packets, &ray, |_| true)
            };
            let portable_occluded = unsafe {
                occluded_generic::<PortableLanes>(&bvh.nodes, &bvh.packets, &ray, &mut {
                    crate::bvh::NO_OCCLUDER
                })
            };
            assert_eq!(portable, bvh.intersect(&ray));
            assert_eq!(portable_occluded, bvh.occluded(&ray));
        }
    }

    /// A filtered traversal answers as a tree built from the accepted
    /// triangles alone would: the rejected ones neither hit nor shorten the
    /// search of the others.
    #[test]
    fn a_filtered_traversal_equals_a_tree_of_the_accepted_triangles() {
        let mut rng = Pcg32::new(11, 4);
        let (positions, triangles) = scattered_triangles(&mut rng);
        let bvh = Bvh::build(&positions, &triangles);
        let accepted: Vec<u32> = (0..1000u32).filter(|index| index % 3 != 1).collect();
        let accepted_triangles: Vec<[u32; 3]> = accepted
            .iter()
            .map(|&index| triangles[index as usize])
            .collect();
        let accepted_bvh = Bvh::build(&positions, &accepted_triangles);
        let mut filtered_hits = 0;
        for _ in 0..2000 {
            let ray = scattered_ray(&mut rng);
            let filtered = bvh.intersect_where(&ray, |triangle| triangle % 3 != 1);
            let expected = accepted_bvh.intersect(&ray).map(|hit| Hit {
                triangle: accepted[hit.triangle as usize],
                ..hit
            });
            assert_eq!(filtered, expected);
            let unfiltered = bvh.intersect(&ray);
            if unfiltered.is_some_and(|hit| hit.triangle % 3 == 1) {
                filtered_hits += 1;
            }
        }
        // The rays must reach rejected triangles first often enough for the
        // comparison to test the filter at all.
        assert!(
            filtered_hits > 100,
            "{filtered_hits} rays met a rejected triangle first"
        );
    }

    /// Two triangles in one plane facing away from each other: from either
    /// side the one facing the ray is returned, whichever the traversal
    /// meets first, and a back face with no front face near it stays.
    #[test]
    fn a_back_face_yields_to_a_coincident_front_face() {
        let positions = vec![
            Vec3::new(0.0, -1.0, -1.0),
            Vec3::new(0.0, 1.0, -1.0),
            Vec3::new(0.0, 0.0, 1.0),
            Vec3::new(5.0, -1.0, -1.0),
            Vec3::new(5.0, 1.0, -1.0),
            Vec3::new(5.0, 0.0, 1.0),
        ];
        // 0 faces -x, 1 (the same corners, wound the other way) faces +x;
        // 2 lies 5 m further along +x and faces -x.
        let triangles = vec![[0, 2, 1], [0, 1, 2], [3, 5, 4]];
        let normal = |triangle: u32| {
            let [a, b, c] = triangles[triangle as usize].map(|index| positions[index as usize]);
            (b - a).cross(c - a)
        };
        assert!(normal(0).x < 0.0 && normal(1).x > 0.0);
        let bvh = Bvh::build(&positions, &triangles);
        for (origin, direction, facing) in [(-1.0, 1.0, 0), (1.0, -1.0, 1)] {
            let ray = Ray {
                origin: Vec3::new(origin, 0.0, 0.0),
                direction: Vec3::new(direction, 0.0, 0.0),
                t_max: f32::INFINITY,
            };
            let faces = |triangle: u32| normal(triangle).dot(ray.direction) < 0.0;
            let hit = bvh.intersect_front_first(&ray, 1e-3, faces).expect("hit");
            assert_eq!(hit.triangle, facing, "from x = {origin}");
            assert!((hit.t - 1.0).abs() < 1e-5);
        }
        // From x = 6 toward -x the first hit is the back of 2, and the
        // front face behind it is 5 m away, not coincident.
        let away = Ray {
            origin: Vec3::new(6.0, 0.0, 0.0),
            direction: Vec3::new(-1.0, 0.0, 0.0),
            t_max: f32::INFINITY,
        };
        let faces = |triangle: u32| normal(triangle).dot(away.direction) < 0.0;
        let hit = bvh.intersect_front_first(&away, 1e-3, faces).expect("hit");
        assert_eq!(hit.triangle, 2, "a lone back face stays the hit");
    }

    /// The shadow cache may only save work: with the cache carried along a
    /// row of points (as the direct-light service does), reset, or set to an
    /// unrelated or out-of-range packet, every answer equals the plain
    /// traversal's, and rows under the slabs do hit the cache.
    #[test]
    fn shadow_cache_never_changes_the_answer() {
        let mut rng = Pcg32::new(9, 3);
        // Random slabs of triangles between y = 1 and y = 3, over a floor.
        let mut positions = Vec::new();
        for _ in 0..400 {
            let corner = Vec3::new(
                rng.next_f32() * 10.0,
                1.0 + 2.0 * rng.next_f32(),
                rng.next_f32() * 10.0,
            );
            let size = 0.2 + rng.next_f32();
            positions.extend([
                corner,
                corner + Vec3::new(size, 0.0, 0.0),
                corner + Vec3::new(0.0, 0.1 * rng.next_f32(), size),
            ]);
        }
        let triangles: Vec<[u32; 3]> = (0..400u32)
            .map(|index| [3 * index, 3 * index + 1, 3 * index + 2])
            .collect();
        let bvh = Bvh::build(&positions, &triangles);
        let toward_light = Vec3::new(0.3, 1.0, 0.2).normalize();
        let mut carried = crate::bvh::NO_OCCLUDER;
        let (mut blocked, mut cache_hits) = (0, 0);
        for step in 0..4000 {
            let origin = Vec3::new((step % 200) as f32 * 0.05, 0.0, (step / 200) as f32 * 0.5);
            let ray = Ray {
                origin,
                direction: toward_light,
                t_max: f32::INFINITY,
            };
            let expected = bvh.occluded(&ray);
            let before = carried;
            let with_carried = bvh.occluded_cached(&ray, &mut carried);
            assert_eq!(with_carried, expected, "step {step}");
            if expected {
                blocked += 1;
                cache_hits += usize::from(carried == before);
            }
            let unrelated = rng.next_u32() % (bvh.packet_count() as u32 + 3);
            assert_eq!(bvh.occluded_cached(&ray, &mut { unrelated }), expected);
            assert_eq!(
                bvh.occluded_cached(&Ray { t_max: 0.5, ..ray }, &mut { before }),
                bvh.occluded(&Ray { t_max: 0.5, ..ray })
            );
        }
        assert!(blocked > 500, "the slabs must block many rays: {blocked}");
        assert!(
            cache_hits > blocked / 2,
            "{cache_hits} of {blocked} blocked rays reused the occluder"
        );
    }
}
