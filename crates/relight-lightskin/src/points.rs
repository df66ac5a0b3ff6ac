//! Sparse scene points in model space and the neighbour lists that
//! interpolate from them (section 3.2, step 3).
//!
//! Points are anchored to a triangle and barycentric coordinates, so they
//! stay fixed to their mesh whatever it does. They are spread Poisson-like:
//! area-proportional Halton candidates, accepted by dart throwing with a
//! minimum distance that shrinks until the requested count is reached.
//! Neighbour lists (eight nearest points with a facing normal, weights of
//! equation 12) are built once, when a mesh is loaded.

use glam::{Vec2, Vec3};
use rayon::prelude::*;
use relight_core::sampling::{radical_inverse, uniform_triangle};
use relight_core::Rgb;
use relight_scene::{AreaTable, Mesh};
use std::borrow::Cow;
use std::collections::HashMap;

/// Neighbours per interpolated target (the paper's eight).
pub const NEIGHBOURS: usize = 8;

/// How far a target's neighbours may be, in point spacings (or in
/// distances to its nearest point where that is farther). Interpolation
/// blends the neighbours' averaged lights and evaluates them at the
/// target, so a point a metre and a half away, lit by a lamp that the
/// target stands beside, gave the target that lamp's light at a tenth of
/// the distance: on a small lampshade with one point of its own, the
/// other seven neighbours were on a box's face far below.
const NEIGHBOUR_REACH: f32 = 2.0;

/// How far, in point spacings, a target looks for a point in front of it
/// before it takes the nearest facing points wherever they lie (see
/// [`interpolation_neighbours`]).
const FARTHEST_FRONT: f32 = 8.0;

/// A point fixed to a mesh.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Anchor {
    pub triangle: u32,
    pub barycentric: Vec2,
}

/// Where an anchor lies on `mesh` (in the mesh's own space).
pub fn anchor_position(mesh: &Mesh, anchor: Anchor) -> Vec3 {
    let [a, b, c] = mesh.vertices(anchor.triangle as usize);
    a + (b - a) * anchor.barycentric.x + (c - a) * anchor.barycentric.y
}

/// Candidates per requested point for dart throwing.
const CANDIDATES_PER_POINT: usize = 8;

/// About `count` points spread evenly over `set` (fewer only when `set`
/// has no area). `seed` rotates the Halton candidates (Cranley-Patterson),
/// so different seeds give different, equally even, distributions.
///
/// With `weights` (one per triangle, [`relight_scene::Scene::detail_weights`])
/// a triangle's share of the points follows its area times its weight, so
/// points thin out with the lightmap where it coarsens.
///
/// With `hidden` (a test of a candidate's triangle and position), candidates
/// on surfaces nobody sees are dropped before any is accepted, so the
/// points go to the visible surfaces: see
/// `relight_technique::SceneContext::is_hidden_surface_point`.
///
/// Returns the anchors and the area they were spread over (weighted by
/// `weights`; without the hidden share when `hidden` is given, estimated
/// from the share of candidates it dropped).
pub fn spread_points(
    mesh: &Mesh,
    count: usize,
    seed: u64,
    weights: Option<&[f32]>,
    hidden: Option<&(dyn Fn(u32, Vec3) -> bool + Sync)>,
) -> (Vec<Anchor>, f64) {
    let areas = AreaTable::weighted(mesh, weights);
    let total_area = areas.total();
    if count == 0 || total_area <= 0.0 {
        return (Vec::new(), total_area);
    }
    let rotation = [
        radical_inverse(7, seed),
        radical_inverse(11, seed),
        radical_inverse(13, seed),
    ];
    // A candidate's distance to its neighbours scales with its triangle's
    // density, 1/sqrt(weight): points on a ring of 4x coarser texels stand
    // 4x apart, and each ring is thinned against itself (its own grid), or
    // the first pass would accept every candidate where they are sparse.
    let candidates: Vec<(Anchor, Vec3, f32)> = (0..(count * CANDIDATES_PER_POINT) as u64)
        .map(|index| {
            let rotate =
                |base: u32, offset: f64| (radical_inverse(base, index + 1) + offset).fract();
            let triangle = areas.triangle_at(rotate(2, rotation[0]) * total_area) as u32;
            let barycentric = uniform_triangle(Vec2::new(
                rotate(3, rotation[1]) as f32,
                rotate(5, rotation[2]) as f32,
            ));
            let anchor = Anchor {
                triangle,
                barycentric,
            };
            let scale = weights.map_or(1.0, |weights| 1.0 / weights[triangle as usize].sqrt());
            (anchor, anchor_position(mesh, anchor), scale)
        })
        .collect();
    let (candidates, total_area) = match hidden {
        Some(hidden) => {
            let drawn = candidates.len();
            let visible: Vec<(Anchor, Vec3, f32)> = candidates
                .into_par_iter()
                .filter(|(anchor, position, _)| !hidden(anchor.triangle, *position))
                .collect();
            let share = visible.len() as f64 / drawn as f64;
            (visible, total_area * share)
        }
        None => (candidates, total_area),
    };
    if candidates.is_empty() {
        return (Vec::new(), total_area);
    }
    // Hexagonal packing of `count` discs of diameter d covers
    // count * sqrt(3)/2 * d^2; dart throwing stalls well below that.
    let hexagonal = (2.0 * total_area / (3f64.sqrt() * count as f64)).sqrt() as f32;
    let mut spacing = 0.8 * hexagonal;
    let mut accepted: Vec<(Anchor, Vec3, f32)> = Vec::with_capacity(count);
    let mut taken = vec![false; candidates.len()];
    while accepted.len() < count && spacing > hexagonal * 1e-4 {
        let mut grid: HashMap<(u32, [i32; 3]), Vec<Vec3>> = HashMap::new();
        let cell_of = |p: Vec3, scale: f32| {
            let cell = (p / (spacing * scale)).floor().as_ivec3().to_array();
            (scale.to_bits(), cell)
        };
        for &(_, position, scale) in &accepted {
            grid.entry(cell_of(position, scale))
                .or_default()
                .push(position);
        }
        for (index, &(anchor, position, scale)) in candidates.iter().enumerate() {
            if accepted.len() >= count {
                break;
            }
            if taken[index] {
                continue;
            }
            let (ring, cell) = cell_of(position, scale);
            let distance = spacing * scale;
            let mut free = true;
            'search: for dx in -1..=1 {
                for dy in -1..=1 {
                    for dz in -1..=1 {
                        let key = (ring, [cell[0] + dx, cell[1] + dy, cell[2] + dz]);
                        if let Some(points) = grid.get(&key) {
                            if points
                                .iter()
                                .any(|p| p.distance_squared(position) < distance * distance)
                            {
                                free = false;
                                break 'search;
                            }
                        }
                    }
                }
            }
            if free {
                taken[index] = true;
                accepted.push((anchor, position, scale));
                grid.entry((ring, cell)).or_default().push(position);
            }
        }
        spacing *= 0.85;
    }
    let anchors = accepted.into_iter().map(|(anchor, _, _)| anchor).collect();
    (anchors, total_area)
}

/// How far below a query's tangent plane a neighbour may lie, as the sine
/// of its angle: a curved surface's own points lie behind the plane by
/// about distance^2 / (2 radius), under half the distance wherever the
/// points are spaced closer than the radius; a point across a thin wall
/// or a shade lies nearly straight behind.
const MAX_BEHIND_SLOPE: f32 = 0.5;

/// Uniform hash grid over points for nearest-neighbour queries; it
/// borrows the points ([`PointGrid::new`]) or owns them
/// ([`PointGrid::owned`], to be kept across frames).
#[derive(Clone, Debug)]
pub struct PointGrid<'a> {
    positions: Cow<'a, [Vec3]>,
    cell: f32,
    cells: HashMap<[i32; 3], Vec<u32>>,
    low: Vec3,
    high: Vec3,
}

impl PointGrid<'static> {
    pub fn owned(positions: Vec<Vec3>, cell: f32) -> Self {
        PointGrid::over(Cow::Owned(positions), cell)
    }
}

impl<'a> PointGrid<'a> {
    pub fn new(positions: &'a [Vec3], cell: f32) -> Self {
        Self::over(Cow::Borrowed(positions), cell)
    }

    fn over(positions: Cow<'a, [Vec3]>, cell: f32) -> Self {
        let cell = cell.max(1e-6);
        let mut cells: HashMap<[i32; 3], Vec<u32>> = HashMap::new();
        let mut low = Vec3::splat(f32::INFINITY);
        let mut high = Vec3::splat(f32::NEG_INFINITY);
        for (index, &position) in positions.iter().enumerate() {
            cells
                .entry((position / cell).floor().as_ivec3().to_array())
                .or_default()
                .push(index as u32);
            low = low.min(position);
            high = high.max(position);
        }
        Self {
            positions,
            cell,
            cells,
            low,
            high,
        }
    }

    /// The points, in the order they were given.
    pub fn positions(&self) -> &[Vec3] {
        &self.positions
    }

    /// The `NEIGHBOURS` nearest points whose normal faces the same side as
    /// `normal` (positive dot product), nearest first, as (index, distance).
    /// Points facing away would get weight zero in equation 12 anyway;
    /// skipping them keeps a texel in a corner from ending up with only
    /// the other wall's points and no light. The search has no bound: it
    /// ends once it holds `NEIGHBOURS` points.
    pub fn nearest_facing(
        &self,
        position: Vec3,
        normal: Vec3,
        normals: &[Vec3],
        found: &mut Nearest,
    ) {
        self.search(position, normal, normals, f32::INFINITY, false, found);
    }

    /// [`Self::nearest_facing`] among the points within `max_distance`
    /// (a few cells, so a query with nothing facing it near is cheap; the
    /// result may hold farther points too) that do not lie behind the
    /// query's surface. Points behind are across the surface: the outside
    /// of a thick lampshade has the far inside wall's points, lit by the
    /// lamp, facing its own way a hand's width behind it, and where no
    /// point of its own was near it took their light.
    pub fn nearest_in_front_within(
        &self,
        position: Vec3,
        normal: Vec3,
        normals: &[Vec3],
        max_distance: f32,
        found: &mut Nearest,
    ) {
        self.search(position, normal, normals, max_distance, true, found);
    }

    fn search(
        &self,
        position: Vec3,
        normal: Vec3,
        normals: &[Vec3],
        max_distance: f32,
        in_front_only: bool,
        found: &mut Nearest,
    ) {
        found.clear();
        if self.positions.is_empty() {
            return;
        }
        let centre = (position / self.cell).floor().as_ivec3();
        let whole = ((self.high - self.low).max_element() / self.cell).ceil() + 2.0;
        let reach = whole.min((max_distance / self.cell).ceil() + 1.0) as i32;
        let consider = |index: u32, found: &mut Nearest| {
            if normals[index as usize].dot(normal) <= 0.0 {
                return;
            }
            let offset = self.positions[index as usize] - position;
            let distance = offset.length();
            if in_front_only && offset.dot(normal) < -MAX_BEHIND_SLOPE * distance {
                return;
            }
            found.offer(index, distance);
        };
        for ring in 0..=reach {
            for dx in -ring..=ring {
                for dy in -ring..=ring {
                    for dz in -ring..=ring {
                        if dx.abs().max(dy.abs()).max(dz.abs()) != ring {
                            continue;
                        }
                        let key = [centre.x + dx, centre.y + dy, centre.z + dz];
                        if let Some(indices) = self.cells.get(&key) {
                            for &index in indices {
                                consider(index, found);
                            }
                        }
                    }
                }
            }
            // Every point outside the searched rings is at least `ring`
            // cells away.
            if found.is_full() && found.farthest() <= ring as f32 * self.cell {
                return;
            }
        }
    }
}

/// The [`NEIGHBOURS`] nearest points offered so far, as (index, distance),
/// nearest first, ties by index so that results do not depend on the order
/// of offers. Fixed size: no allocation per query.
#[derive(Clone, Copy, Debug)]
pub struct Nearest {
    entries: [(u32, f32); NEIGHBOURS],
    len: usize,
}

impl Default for Nearest {
    fn default() -> Self {
        Self {
            entries: [(0, 0.0); NEIGHBOURS],
            len: 0,
        }
    }
}

impl Nearest {
    pub fn clear(&mut self) {
        self.len = 0;
    }

    pub fn offer(&mut self, index: u32, distance: f32) {
        if self.len == NEIGHBOURS && distance >= self.entries[NEIGHBOURS - 1].1 {
            return;
        }
        let at = self.entries[..self.len].partition_point(|&(i, d)| (d, i) < (distance, index));
        let end = (self.len + 1).min(NEIGHBOURS);
        self.entries.copy_within(at..end - 1, at + 1);
        self.entries[at] = (index, distance);
        self.len = end;
    }

    pub fn as_slice(&self) -> &[(u32, f32)] {
        &self.entries[..self.len]
    }

    /// Equation 12 weights of these neighbours for a target with `normal`
    /// (see [`interpolation_weights`]).
    pub fn weights(
        &self,
        normal: Vec3,
        point_normals: &[Vec3],
    ) -> ([u32; NEIGHBOURS], [f32; NEIGHBOURS]) {
        let mut entries = [(0u32, 0f32, Vec3::ZERO); NEIGHBOURS];
        for (entry, &(index, distance)) in entries.iter_mut().zip(self.as_slice()) {
            *entry = (index, distance, point_normals[index as usize]);
        }
        interpolation_weights(normal, &entries[..self.len])
    }

    /// Drops the neighbours farther than `distance`, keeping the nearest.
    pub fn keep_within(&mut self, distance: f32) {
        let within = self.entries[..self.len].partition_point(|&(_, d)| d <= distance);
        self.len = within.max(self.len.min(1));
    }

    fn is_full(&self) -> bool {
        self.len == NEIGHBOURS
    }

    fn farthest(&self) -> f32 {
        self.entries[self.len - 1].1
    }
}

/// Fixed neighbours and normalised weights of interpolated targets
/// (texels or vertices), struct of arrays, compact because the texels'
/// lists are read whole every frame: 16-bit point indices while there are
/// at most 65536 points, and weights in 16-bit fixed point (1/65535ths,
/// summing to exactly 65535), 32 bytes a target instead of 64. On Sponza
/// (378k texels) that is 12 MiB a frame instead of 24 MiB.
#[derive(Clone, Debug)]
pub struct Interpolation {
    neighbours: Neighbours,
    weights: Vec<[u16; NEIGHBOURS]>,
}

#[derive(Clone, Debug)]
enum Neighbours {
    Narrow(Vec<[u16; NEIGHBOURS]>),
    Wide(Vec<[u32; NEIGHBOURS]>),
}

impl Default for Interpolation {
    fn default() -> Self {
        Self {
            neighbours: Neighbours::Narrow(Vec::new()),
            weights: Vec::new(),
        }
    }
}

/// Weights scaled to 16-bit fixed point summing to 65535 (the remainder
/// goes to the heaviest), or all zero when they are.
fn quantise_weights(weights: &[f32; NEIGHBOURS]) -> [u16; NEIGHBOURS] {
    let mut fixed = [0u16; NEIGHBOURS];
    let total: f32 = weights.iter().sum();
    if total <= 0.0 {
        return fixed;
    }
    let heaviest = (0..NEIGHBOURS)
        .max_by(|&a, &b| weights[a].total_cmp(&weights[b]).then(b.cmp(&a)))
        .unwrap_or(0);
    let mut assigned = 0u32;
    for slot in 0..NEIGHBOURS {
        if slot != heaviest {
            fixed[slot] = (weights[slot] / total * 65535.0).round() as u16;
            assigned += fixed[slot] as u32;
        }
    }
    fixed[heaviest] = 65535u32.saturating_sub(assigned) as u16;
    fixed
}

/// The neighbours a target interpolates: its nearest facing points in
/// front of it within `NEIGHBOUR_REACH` spacings, or within
/// `NEIGHBOUR_REACH` times its nearest such point's distance where none is
/// within a spacing. Every search is bounded: a target that no point
/// fronts within `FARTHEST_FRONT` spacings (the outside of a closed
/// building, whose hidden faces have no points, all of them behind it)
/// would otherwise search the whole grid, for minutes on a scene with
/// many such receivers and a large ground. Such a target takes its
/// nearest facing points wherever they lie, as every target did before
/// the in-front rule.
fn interpolation_neighbours(
    grid: &PointGrid,
    (position, normal): (Vec3, Vec3),
    point_normals: &[Vec3],
    spacing: f32,
    found: &mut Nearest,
) {
    let near = NEIGHBOUR_REACH * spacing;
    grid.nearest_in_front_within(position, normal, point_normals, near, found);
    if let Some(&(_, nearest)) = found.as_slice().first() {
        if nearest <= spacing {
            found.keep_within(near);
            return;
        }
    }
    // This rescans the near cells, which is cheaper than letting every
    // target search eight spacings: most fill their eight within two, but
    // those on an edge or in a corner hold fewer and would search all
    // eight.
    let far = FARTHEST_FRONT * spacing;
    grid.nearest_in_front_within(position, normal, point_normals, far, found);
    match found.as_slice().first() {
        Some(&(_, nearest)) if nearest <= far => {
            found.keep_within(NEIGHBOUR_REACH * nearest);
        }
        _ => grid.nearest_facing(position, normal, point_normals, found),
    }
}

impl Interpolation {
    pub fn len(&self) -> usize {
        self.weights.len()
    }

    pub fn is_empty(&self) -> bool {
        self.weights.is_empty()
    }

    pub fn memory_bytes(&self) -> usize {
        let index_bytes = match &self.neighbours {
            Neighbours::Narrow(_) => 2,
            Neighbours::Wide(_) => 4,
        };
        self.len() * NEIGHBOURS * (index_bytes + 2)
    }

    /// Builds the lists for `targets` against `points` (same space).
    pub fn build(
        target_positions: &[Vec3],
        target_normals: &[Vec3],
        point_positions: &[Vec3],
        point_normals: &[Vec3],
        spacing: f32,
    ) -> Self {
        use rayon::prelude::*;
        let grid = PointGrid::new(point_positions, spacing.max(1e-6) * 2.0);
        let (neighbours, weights): (Vec<[u32; NEIGHBOURS]>, Vec<[u16; NEIGHBOURS]>) =
            target_positions
                .par_iter()
                .zip(target_normals)
                .map_init(Nearest::default, |found, (&position, &normal)| {
                    interpolation_neighbours(
                        &grid,
                        (position, normal),
                        point_normals,
                        spacing,
                        found,
                    );
                    let (indices, weights) = found.weights(normal, point_normals);
                    (indices, quantise_weights(&weights))
                })
                .unzip();
        let neighbours = if point_positions.len() <= 1 << 16 {
            Neighbours::Narrow(
                neighbours
                    .into_iter()
                    .map(|list| list.map(|index| index as u16))
                    .collect(),
            )
        } else {
            Neighbours::Wide(neighbours)
        };
        Self {
            neighbours,
            weights,
        }
    }

    /// The targets of every part in order, each part's point indices
    /// counting from its offset.
    pub fn concat(parts: Vec<(Interpolation, u32)>) -> Self {
        let mut wide = Vec::new();
        let mut weights = Vec::new();
        for (part, first) in parts {
            wide.extend(
                part.wide_lists()
                    .into_iter()
                    .map(|list| list.map(|index| index + first)),
            );
            weights.extend(part.weights);
        }
        let fits = wide.iter().flatten().all(|&index| index < 1 << 16);
        let neighbours = if fits {
            Neighbours::Narrow(wide.into_iter().map(|l| l.map(|i| i as u16)).collect())
        } else {
            Neighbours::Wide(wide)
        };
        Self {
            neighbours,
            weights,
        }
    }

    fn wide_lists(&self) -> Vec<[u32; NEIGHBOURS]> {
        match &self.neighbours {
            Neighbours::Narrow(lists) => lists.iter().map(|l| l.map(u32::from)).collect(),
            Neighbours::Wide(lists) => lists.clone(),
        }
    }

    /// Equation 13 at one target: its neighbours' powers and light
    /// positions, blended by its weights.
    #[inline]
    pub fn blend(&self, target: usize, powers: &[Rgb], positions: &[Vec3]) -> (Rgb, Vec3) {
        const SCALE: f32 = 1.0 / 65535.0;
        let weights = &self.weights[target];
        let mut power = Rgb::ZERO;
        let mut position = Vec3::ZERO;
        let mut add = |slot: usize, source: usize| {
            let weight = weights[slot] as f32 * SCALE;
            power += powers[source] * weight;
            position += positions[source] * weight;
        };
        match &self.neighbours {
            Neighbours::Narrow(lists) => {
                for (slot, &source) in lists[target].iter().enumerate() {
                    add(slot, source as usize);
                }
            }
            Neighbours::Wide(lists) => {
                for (slot, &source) in lists[target].iter().enumerate() {
                    add(slot, source as usize);
                }
            }
        }
        (power, position)
    }
}

/// Equation 12: w_j = (1 - d_j / d_max) * clamp(n_v . n_j, 0, 1) over the
/// given (index, distance, normal) neighbours, normalised to sum to one.
/// When every weight vanishes (one neighbour, or all at the same distance)
/// the neighbours share equally by normal agreement instead, and with no
/// neighbour at all the weights are zero.
pub fn interpolation_weights(
    normal: Vec3,
    neighbours: &[(u32, f32, Vec3)],
) -> ([u32; NEIGHBOURS], [f32; NEIGHBOURS]) {
    let mut indices = [0u32; NEIGHBOURS];
    let mut weights = [0f32; NEIGHBOURS];
    let farthest = neighbours
        .iter()
        .map(|&(_, distance, _)| distance)
        .fold(0.0f32, f32::max);
    let mut total = 0.0;
    for (slot, &(index, distance, point_normal)) in neighbours.iter().take(NEIGHBOURS).enumerate() {
        indices[slot] = index;
        let closeness = if farthest > 0.0 {
            1.0 - distance / farthest
        } else {
            1.0
        };
        weights[slot] = closeness * normal.dot(point_normal).clamp(0.0, 1.0);
        total += weights[slot];
    }
    if total <= 0.0 {
        for (slot, &(_, _, point_normal)) in neighbours.iter().take(NEIGHBOURS).enumerate() {
            weights[slot] = normal.dot(point_normal).clamp(0.0, 1.0);
            total += weights[slot];
        }
    }
    if total > 0.0 {
        for weight in &mut weights {
            *weight /= total;
        }
    }
    (indices, weights)
}
