//! Watertight ray/triangle test (Woop, Benthin, Wald 2013, "Watertight
//! Ray/Triangle Intersection"), four triangles of a [`TrianglePacket`] at once.
//!
//! The ray is transformed so it runs along +z from the origin; the three edge
//! functions are then 2D cross products of the sheared vertices. Two
//! triangles sharing an edge evaluate that edge's function from the same two
//! transformed vertices, so the results have opposite sign and a ray cannot
//! slip between them. Edge functions that round to exactly zero are
//! recomputed in double precision, as the paper does, so the sign decision
//! is exact for them too.

use super::TrianglePacket;
use glam::{Vec3, Vec4};

/// Per-ray constants of the watertight test.
#[derive(Clone, Copy)]
pub(crate) struct ShearedRay {
    /// Axis permutation: `axes[2]` is the dominant direction axis.
    pub axes: [usize; 3],
    /// Shear that maps the direction onto +z with unit length along it.
    pub shear_x: f32,
    pub shear_y: f32,
    pub shear_z: f32,
    pub origin: [f32; 3],
}

impl ShearedRay {
    pub fn new(origin: Vec3, direction: Vec3) -> Self {
        let magnitude = direction.abs();
        let axis_z = if magnitude.x > magnitude.y {
            if magnitude.x > magnitude.z {
                0
            } else {
                2
            }
        } else if magnitude.y > magnitude.z {
            1
        } else {
            2
        };
        let mut axis_x = (axis_z + 1) % 3;
        let mut axis_y = (axis_x + 1) % 3;
        // Keep the winding of the sheared triangle: swap x and y when the
        // dominant component is negative.
        if direction[axis_z] < 0.0 {
            std::mem::swap(&mut axis_x, &mut axis_y);
        }
        let shear_z = 1.0 / direction[axis_z];
        Self {
            axes: [axis_x, axis_y, axis_z],
            shear_x: direction[axis_x] * shear_z,
            shear_y: direction[axis_y] * shear_z,
            shear_z,
            origin: origin.to_array(),
        }
    }
}

/// Hit candidates of one packet: lane mask of hits with 0 < t < t_max and
/// what is needed to finish the closest lane.
pub(crate) struct PacketHits {
    pub mask: u32,
    pub t: Vec4,
    pub edge_v: Vec4,
    pub edge_w: Vec4,
    pub determinant: Vec4,
}

/// Tests the four lanes of `packet`. Returns `None` when no lane hits.
#[inline(always)]
pub(crate) fn intersect_packet(
    ray: &ShearedRay,
    packet: &TrianglePacket,
    t_max: f32,
) -> Option<PacketHits> {
    let [axis_x, axis_y, axis_z] = ray.axes;
    let origin_x = Vec4::splat(ray.origin[axis_x]);
    let origin_y = Vec4::splat(ray.origin[axis_y]);
    let origin_z = Vec4::splat(ray.origin[axis_z]);
    let shear_x = Vec4::splat(ray.shear_x);
    let shear_y = Vec4::splat(ray.shear_y);

    // Vertices relative to the origin, then sheared in x/y; z is scaled later.
    let corner = |index: usize| {
        let vertex = &packet.vertices[index];
        let z = Vec4::from_array(vertex[axis_z]) - origin_z;
        let x = Vec4::from_array(vertex[axis_x]) - origin_x - shear_x * z;
        let y = Vec4::from_array(vertex[axis_y]) - origin_y - shear_y * z;
        (x, y, z)
    };
    let (a_x, a_y, a_z) = corner(0);
    let (b_x, b_y, b_z) = corner(1);
    let (c_x, c_y, c_z) = corner(2);

    let mut edge_u = c_x * b_y - c_y * b_x;
    let mut edge_v = a_x * c_y - a_y * c_x;
    let mut edge_w = b_x * a_y - b_y * a_x;

    let zero = Vec4::ZERO;
    let any_exact_zero = edge_u.cmpeq(zero) | edge_v.cmpeq(zero) | edge_w.cmpeq(zero);
    if any_exact_zero.any() {
        // Rare (rays through edges/vertices, or degenerate projections): the
        // single-precision products may have cancelled, so redo all lanes
        // in double precision where the products are exact.
        let recompute = |p_x: Vec4, p_y: Vec4, q_x: Vec4, q_y: Vec4| {
            let (p_x, p_y, q_x, q_y) = (
                p_x.to_array(),
                p_y.to_array(),
                q_x.to_array(),
                q_y.to_array(),
            );
            Vec4::from_array(std::array::from_fn(|lane| {
                (p_x[lane] as f64 * q_y[lane] as f64 - p_y[lane] as f64 * q_x[lane] as f64) as f32
            }))
        };
        edge_u = recompute(c_x, c_y, b_x, b_y);
        edge_v = recompute(a_x, a_y, c_x, c_y);
        edge_w = recompute(b_x, b_y, a_x, a_y);
    }

    let any_negative = edge_u.cmplt(zero) | edge_v.cmplt(zero) | edge_w.cmplt(zero);
    let any_positive = edge_u.cmpgt(zero) | edge_v.cmpgt(zero) | edge_w.cmpgt(zero);
    let determinant = edge_u + edge_v + edge_w;
    let candidate = !(any_negative & any_positive) & determinant.cmpne(zero);
    if !candidate.any() {
        return None;
    }
    let shear_z = Vec4::splat(ray.shear_z);
    let scaled_t = shear_z * (edge_u * a_z + edge_v * b_z + edge_w * c_z);
    let t = scaled_t / determinant;
    // NaN t (from non-finite inputs) fails both comparisons.
    let in_range = t.cmpgt(zero) & t.cmplt(Vec4::splat(t_max));
    let mask = (candidate & in_range).bitmask();
    if mask == 0 {
        return None;
    }
    Some(PacketHits {
        mask,
        t,
        edge_v,
        edge_w,
        determinant,
    })
}
