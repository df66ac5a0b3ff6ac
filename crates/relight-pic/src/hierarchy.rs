//! The sender hierarchy over the surfels (section 4.3): a binary tree built
//! by hierarchical agglomerative clustering with the paper's metric, made
//! visibility-aware, or by a kd-tree as the fast alternative.
//!
//! Whatever built it, the tree is stored in one layout: surfels reordered so
//! every node covers a contiguous range of leaves, leaves are nodes
//! `0..n`, internal nodes `n..2n-1` in post order (children before parents,
//! a subtree's internal nodes contiguous, the root last), so the pull is one
//! forward pass and subtrees can be pulled in parallel.

use glam::Vec3;
use rayon::prelude::*;
use relight_trace::{Bvh, Ray};
use std::cmp::Reverse;
use std::collections::BinaryHeap;

/// The tree over `n` leaves (surfels in leaf order).
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Hierarchy {
    pub leaf_count: u32,
    /// Children (node ids) of internal node `n + k`.
    pub children: Vec<[u32; 2]>,
    /// First leaf and leaf count of every node (leaves included).
    pub first_leaf: Vec<u32>,
    pub leaves: Vec<u32>,
}

impl Hierarchy {
    pub fn node_count(&self) -> usize {
        self.first_leaf.len()
    }

    pub fn root(&self) -> u32 {
        self.node_count().saturating_sub(1) as u32
    }

    pub fn is_leaf(&self, node: u32) -> bool {
        node < self.leaf_count
    }

    pub fn children_of(&self, node: u32) -> [u32; 2] {
        self.children[(node - self.leaf_count) as usize]
    }

    /// Depth of the deepest leaf (balance, for reports).
    pub fn depth(&self) -> u32 {
        let mut depth = vec![0u32; self.node_count()];
        let mut deepest = 0;
        for node in (self.leaf_count..self.node_count() as u32).rev() {
            for child in self.children_of(node) {
                depth[child as usize] = depth[node as usize] + 1;
                deepest = deepest.max(depth[child as usize]);
            }
        }
        deepest
    }

    /// Internal nodes whose subtrees the pull can run in parallel: disjoint
    /// subtrees of at most `n / parts` leaves covering all leaves, and the
    /// internal nodes above them, in post order.
    pub fn pull_schedule(&self, parts: usize) -> (Vec<u32>, Vec<u32>) {
        let limit = (self.leaf_count as usize / parts.max(1)).max(1) as u32;
        let mut subtrees = Vec::new();
        let mut top = Vec::new();
        if self.node_count() == 0 {
            return (subtrees, top);
        }
        let mut stack = vec![self.root()];
        while let Some(node) = stack.pop() {
            if self.leaves[node as usize] <= limit || self.is_leaf(node) {
                subtrees.push(node);
            } else {
                top.push(node);
                stack.extend(self.children_of(node));
            }
        }
        // Post order is increasing id order.
        top.sort_unstable();
        subtrees.sort_unstable();
        (subtrees, top)
    }
}

/// Turns a list of merges over original surfel ids (merge k creates node
/// `n + k`) into the stored layout; returns it with the leaf order (new leaf
/// index -> original surfel).
pub fn finalise(leaf_count: usize, merges: &[[u32; 2]]) -> (Hierarchy, Vec<u32>) {
    let n = leaf_count;
    let total = n + merges.len();
    let mut hierarchy = Hierarchy {
        leaf_count: n as u32,
        children: Vec::with_capacity(merges.len()),
        first_leaf: vec![0; total],
        leaves: vec![0; total],
    };
    let mut order = Vec::with_capacity(n);
    if n == 0 {
        hierarchy.first_leaf.clear();
        hierarchy.leaves.clear();
        return (hierarchy, order);
    }
    let mut new_id = vec![u32::MAX; total];
    let mut next_internal = n as u32;
    // Iterative post-order walk from the root.
    let mut stack = vec![(total as u32 - 1, false)];
    while let Some((node, expanded)) = stack.pop() {
        if (node as usize) < n {
            let leaf = order.len() as u32;
            order.push(node);
            new_id[node as usize] = leaf;
            hierarchy.first_leaf[leaf as usize] = leaf;
            hierarchy.leaves[leaf as usize] = 1;
            continue;
        }
        let [left, right] = merges[node as usize - n];
        if !expanded {
            stack.push((node, true));
            stack.push((right, false));
            stack.push((left, false));
            continue;
        }
        let id = next_internal;
        next_internal += 1;
        new_id[node as usize] = id;
        let (left, right) = (new_id[left as usize], new_id[right as usize]);
        hierarchy.children.push([left, right]);
        hierarchy.first_leaf[id as usize] = hierarchy.first_leaf[left as usize];
        hierarchy.leaves[id as usize] =
            hierarchy.leaves[left as usize] + hierarchy.leaves[right as usize];
    }
    (hierarchy, order)
}

/// kd-tree: median splits along the longest axis of each node's bounds.
pub fn build_kd_tree(positions: &[Vec3]) -> Vec<[u32; 2]> {
    fn build(positions: &[Vec3], indices: &mut [u32], merges: &mut Vec<[u32; 2]>, n: u32) -> u32 {
        if indices.len() == 1 {
            return indices[0];
        }
        let (mut lo, mut hi) = (Vec3::splat(f32::MAX), Vec3::splat(f32::MIN));
        for &index in indices.iter() {
            lo = lo.min(positions[index as usize]);
            hi = hi.max(positions[index as usize]);
        }
        let axis = (hi - lo).max_position();
        let middle = indices.len() / 2;
        indices.select_nth_unstable_by(middle, |&a, &b| {
            positions[a as usize][axis]
                .total_cmp(&positions[b as usize][axis])
                .then(a.cmp(&b))
        });
        let (left_half, right_half) = indices.split_at_mut(middle);
        let left = build(positions, left_half, merges, n);
        let right = build(positions, right_half, merges, n);
        merges.push([left, right]);
        n + merges.len() as u32 - 1
    }
    let mut merges = Vec::with_capacity(positions.len().saturating_sub(1));
    if positions.len() > 1 {
        let mut indices: Vec<u32> = (0..positions.len() as u32).collect();
        build(positions, &mut indices, &mut merges, positions.len() as u32);
    }
    merges
}

/// Weights of the clustering metric.
#[derive(Clone, Copy, Debug)]
pub struct ClusterMetric {
    /// C_n: penalty on diverging normals (0.1 in the paper).
    pub normal: f32,
    /// C_b: penalty on unequal sizes, for a balanced tree (0.02).
    pub balance: f32,
    /// Added times the fraction of representative surfel pairs of the two
    /// clusters that cannot see each other; 0 gives the paper's metric.
    pub visibility: f32,
}

#[derive(Clone, Copy)]
struct Cluster {
    centre: Vec3,
    normal_sum: Vec3,
    count: u32,
    reps: [u32; 4],
    rep_count: u32,
    alive: bool,
}

/// Candidates kept per nearest-neighbour search before visibility decides.
const CANDIDATES: usize = 4;

struct Clustering<'a> {
    clusters: Vec<Cluster>,
    grid: DynamicGrid,
    metric: ClusterMetric,
    inverse_extent_squared: f32,
    positions: &'a [Vec3],
    normals: &'a [Vec3],
    bvh: &'a Bvh,
    epsilon: f32,
}

impl Clustering<'_> {
    /// d(a, b) of section 4.3 without the visibility term.
    fn base_metric(&self, a: &Cluster, b: &Cluster) -> f32 {
        let distance = (a.centre - b.centre).length_squared() * self.inverse_extent_squared;
        let normal_a = a.normal_sum.normalize_or_zero();
        let normal_b = b.normal_sum.normalize_or_zero();
        let normal = self.metric.normal * (1.0 - normal_a.dot(normal_b));
        let (size_a, size_b) = (a.count as f32, b.count as f32);
        let balance = self.metric.balance * (size_a - size_b).abs() / size_a.max(size_b);
        distance + normal + balance
    }

    /// Fraction of representative pairs with something between them.
    fn invisible_fraction(&self, a: &Cluster, b: &Cluster) -> f32 {
        let pairs = a.rep_count.max(b.rep_count);
        let mut blocked = 0;
        for pair in 0..pairs {
            let from = a.reps[(pair % a.rep_count) as usize] as usize;
            let to = b.reps[(pair % b.rep_count) as usize] as usize;
            let origin = self.positions[from] + self.normals[from] * self.epsilon;
            let target = self.positions[to] + self.normals[to] * self.epsilon;
            let ray = Ray {
                origin,
                direction: target - origin,
                t_max: 1.0,
            };
            if self.bvh.occluded(&ray) {
                blocked += 1;
            }
        }
        blocked as f32 / pairs as f32
    }

    /// The best partner of `id` under the full metric, among the closest
    /// `CANDIDATES` under the metric without visibility.
    fn nearest(&self, id: u32) -> Option<(f32, u32)> {
        let cluster = &self.clusters[id as usize];
        let mut best: [(f32, u32); CANDIDATES] = [(f32::INFINITY, u32::MAX); CANDIDATES];
        self.grid
            .search(cluster.centre, |candidate, lower_bound_distance| {
                let worst = best[CANDIDATES - 1].0;
                if lower_bound_distance * self.inverse_extent_squared >= worst {
                    return false;
                }
                if candidate != id && candidate != u32::MAX {
                    let other = &self.clusters[candidate as usize];
                    let metric = self.base_metric(cluster, other);
                    if metric < worst || (metric == worst && candidate < best[CANDIDATES - 1].1) {
                        let mut slot = CANDIDATES - 1;
                        best[slot] = (metric, candidate);
                        while slot > 0
                            && (best[slot].0, best[slot].1) < (best[slot - 1].0, best[slot - 1].1)
                        {
                            best.swap(slot, slot - 1);
                            slot -= 1;
                        }
                    }
                }
                true
            });
        let mut chosen: Option<(f32, u32)> = None;
        for (metric, candidate) in best {
            if candidate == u32::MAX {
                break;
            }
            if let Some((value, _)) = chosen {
                if metric >= value {
                    break;
                }
            }
            let penalty = if self.metric.visibility > 0.0 {
                self.metric.visibility
                    * self.invisible_fraction(cluster, &self.clusters[candidate as usize])
            } else {
                0.0
            };
            let value = metric + penalty;
            if chosen.is_none_or(|(best_value, _)| value < best_value) {
                chosen = Some((value, candidate));
            }
        }
        chosen
    }
}

/// Hierarchical agglomerative clustering: repeatedly merges the pair with
/// the smallest metric (nearest neighbours kept in a heap and recomputed
/// when a partner is gone, as in Walter et al.'s locally-ordered
/// clustering), searching neighbours in a grid that coarsens as clusters
/// merge. Sequential and tie-broken by id, so the tree is deterministic.
pub fn build_agglomerative(
    positions: &[Vec3],
    normals: &[Vec3],
    bvh: &Bvh,
    metric: ClusterMetric,
    progress: &dyn relight_technique::Progress,
) -> Vec<[u32; 2]> {
    let n = positions.len();
    let mut merges = Vec::with_capacity(n.saturating_sub(1));
    if n < 2 {
        return merges;
    }
    let (mut lo, mut hi) = (Vec3::splat(f32::MAX), Vec3::splat(f32::MIN));
    for position in positions {
        lo = lo.min(*position);
        hi = hi.max(*position);
    }
    let extent = (hi - lo).max_element().max(1e-6);
    let mut clusters: Vec<Cluster> = (0..n)
        .map(|index| Cluster {
            centre: positions[index],
            normal_sum: normals[index],
            count: 1,
            reps: [index as u32; 4],
            rep_count: 1,
            alive: true,
        })
        .collect();
    clusters.reserve(n);
    let cell_for = |active: usize| (extent / (active as f32).cbrt()).max(1e-6);
    let mut grid = DynamicGrid::new(lo, hi, cell_for(n));
    for (index, cluster) in clusters.iter().enumerate() {
        grid.insert(index as u32, cluster.centre);
    }
    let mut state = Clustering {
        clusters,
        grid,
        metric,
        inverse_extent_squared: 1.0 / (extent * extent),
        positions,
        normals,
        bvh,
        epsilon: 4.0 * relight_trace::direct::ray_epsilon_for(bvh),
    };
    let initial: Vec<Option<(f32, u32)>> = (0..n as u32)
        .into_par_iter()
        .map(|id| state.nearest(id))
        .collect();
    let mut heap: BinaryHeap<Reverse<(u32, u32, u32)>> = initial
        .into_iter()
        .enumerate()
        .filter_map(|(id, best)| {
            best.map(|(value, other)| Reverse((value.to_bits(), id as u32, other)))
        })
        .collect();
    let mut active = n;
    let mut active_at_rebuild = n;
    progress.start("clustering surfels", n as u64 - 1);
    while active > 1 {
        let Some(Reverse((_, a, b))) = heap.pop() else {
            break;
        };
        if !state.clusters[a as usize].alive {
            continue;
        }
        if !state.clusters[b as usize].alive {
            if let Some((value, other)) = state.nearest(a) {
                heap.push(Reverse((value.to_bits(), a, other)));
            }
            continue;
        }
        let (first, second) = (state.clusters[a as usize], state.clusters[b as usize]);
        let count = first.count + second.count;
        let mut reps = [0u32; 4];
        let mut rep_count = 0;
        for slot in 0..4 {
            let source = if slot % 2 == 0 { &first } else { &second };
            let index = slot / 2;
            if index < source.rep_count as usize && rep_count < 4 {
                reps[rep_count] = source.reps[index];
                rep_count += 1;
            }
        }
        for slot in rep_count..4 {
            reps[slot] = reps[slot % rep_count.max(1)];
        }
        let merged = Cluster {
            centre: (first.centre * first.count as f32 + second.centre * second.count as f32)
                / count as f32,
            normal_sum: first.normal_sum + second.normal_sum,
            count,
            reps,
            rep_count: rep_count as u32,
            alive: true,
        };
        state.clusters[a as usize].alive = false;
        state.clusters[b as usize].alive = false;
        state.grid.remove(a, first.centre);
        state.grid.remove(b, second.centre);
        let id = state.clusters.len() as u32;
        state.clusters.push(merged);
        state.grid.insert(id, merged.centre);
        merges.push([a, b]);
        active -= 1;
        progress.advance(1);
        if active * 2 < active_at_rebuild && active > 1 {
            let mut grid = DynamicGrid::new(lo, hi, cell_for(active));
            for (index, cluster) in state.clusters.iter().enumerate() {
                if cluster.alive {
                    grid.insert(index as u32, cluster.centre);
                }
            }
            state.grid = grid;
            active_at_rebuild = active;
        }
        if active > 1 {
            if let Some((value, other)) = state.nearest(id) {
                heap.push(Reverse((value.to_bits(), id, other)));
            }
        }
    }
    progress.finish();
    merges
}

/// A grid of cluster ids that supports removal, searched ring by ring.
struct DynamicGrid {
    origin: Vec3,
    cell: f32,
    dims: [i32; 3],
    cells: Vec<Vec<u32>>,
}

impl DynamicGrid {
    fn new(lo: Vec3, hi: Vec3, cell: f32) -> Self {
        let mut cell = cell;
        let extent = hi - lo;
        // At most about 2^21 cells.
        while ((extent / cell).floor() + 1.0).element_product() > 2_097_152.0 {
            cell *= 1.25;
        }
        let dims = [
            (extent.x / cell) as i32 + 1,
            (extent.y / cell) as i32 + 1,
            (extent.z / cell) as i32 + 1,
        ];
        DynamicGrid {
            origin: lo,
            cell,
            dims,
            cells: vec![Vec::new(); (dims[0] * dims[1] * dims[2]) as usize],
        }
    }

    fn coordinates(&self, point: Vec3) -> [i32; 3] {
        let local = (point - self.origin) / self.cell;
        [
            (local.x as i32).clamp(0, self.dims[0] - 1),
            (local.y as i32).clamp(0, self.dims[1] - 1),
            (local.z as i32).clamp(0, self.dims[2] - 1),
        ]
    }

    fn index(&self, [x, y, z]: [i32; 3]) -> usize {
        ((z * self.dims[1] + y) * self.dims[0] + x) as usize
    }

    fn insert(&mut self, id: u32, point: Vec3) {
        let cell = self.index(self.coordinates(point));
        self.cells[cell].push(id);
    }

    fn remove(&mut self, id: u32, point: Vec3) {
        let cell = self.index(self.coordinates(point));
        if let Some(slot) = self.cells[cell].iter().position(|&other| other == id) {
            self.cells[cell].swap_remove(slot);
        }
    }

    /// Visits clusters ring by ring around `point`; `visit(id, bound)` gets
    /// a lower bound on the squared distance of the ring's clusters and
    /// returns false to stop the search.
    fn search(&self, point: Vec3, mut visit: impl FnMut(u32, f32) -> bool) {
        let centre = self.coordinates(point);
        let max_ring = self.dims.iter().copied().max().unwrap_or(1);
        for ring in 0..max_ring {
            // Clusters in ring r are at least (r - 1) cells away.
            let bound = ((ring - 1).max(0) as f32 * self.cell).powi(2);
            if !visit(u32::MAX, bound) {
                return;
            }
            for z in (centre[2] - ring).max(0)..=(centre[2] + ring).min(self.dims[2] - 1) {
                for y in (centre[1] - ring).max(0)..=(centre[1] + ring).min(self.dims[1] - 1) {
                    let on_face = (z - centre[2]).abs() == ring || (y - centre[1]).abs() == ring;
                    let step = if on_face { 1 } else { (2 * ring).max(1) };
                    let mut x = centre[0] - ring;
                    while x <= centre[0] + ring {
                        if x >= 0 && x < self.dims[0] {
                            for &id in &self.cells[self.index([x, y, z])] {
                                if !visit(id, bound) {
                                    return;
                                }
                            }
                        }
                        x += step;
                    }
                }
            }
        }
    }
}
