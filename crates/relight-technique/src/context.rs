//! Everything built once per scene and shared by all techniques.

use glam::Vec3;
use relight_scene::atlas::{Atlas, TexelDensity};
use relight_scene::{Scene, SceneError};
use relight_trace::direct::{DirectLight, DirectSettings, Emitters};
use relight_trace::{Bvh, Ray};
use std::time::{Duration, Instant};

/// Settings that shape the shared scene data.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct ContextSettings {
    pub lightmap: TexelDensity,
    pub direct: DirectSettings,
}

/// Scene, BVH, lightmap atlas and emitter table, built once.
pub struct SceneContext {
    pub scene: Scene,
    pub bvh: Bvh,
    pub atlas: Atlas,
    pub emitters: Emitters,
    pub settings: ContextSettings,
    pub bvh_build_time: Duration,
    pub atlas_build_time: Duration,
}

impl SceneContext {
    pub fn new(scene: Scene, settings: ContextSettings) -> Result<Self, SceneError> {
        let start = Instant::now();
        let bvh = Bvh::build(&scene.mesh.positions, &scene.mesh.triangles);
        let bvh_build_time = start.elapsed();
        let start = Instant::now();
        let atlas = build_atlas(&scene, &bvh, settings.lightmap)?;
        let atlas_build_time = start.elapsed();
        let emitters = Emitters::from_scene(&scene);
        Ok(Self {
            scene,
            bvh,
            atlas,
            emitters,
            settings,
            bvh_build_time,
            atlas_build_time,
        })
    }

    /// The same context over `scene`, whose first triangles are this
    /// context's static triangles and whose rest are moving meshes placed
    /// for one frame (see [`crate::Technique::frame_geometry`]): BVH and
    /// emitters are rebuilt, the lightmap atlas of the static part is kept.
    pub fn with_frame_geometry(&self, scene: Scene) -> Self {
        let start = Instant::now();
        let bvh = Bvh::build(&scene.mesh.positions, &scene.mesh.triangles);
        let bvh_build_time = start.elapsed();
        let emitters = Emitters::from_scene(&scene);
        Self {
            scene,
            bvh,
            atlas: self.atlas.clone(),
            emitters,
            settings: self.settings,
            bvh_build_time,
            atlas_build_time: Duration::ZERO,
        }
    }

    /// What a bake made for this scene and lightmap records, and is checked
    /// against when loaded.
    pub fn fingerprint(&self) -> u64 {
        crate::scene_fingerprint(&self.scene, &self.atlas)
    }

    /// Fails unless a bake made for `bake_receivers` lightmap receivers fits
    /// this context's lightmap.
    pub fn check_bake_receivers(
        &self,
        technique: &str,
        bake_receivers: usize,
    ) -> Result<(), crate::TechniqueError> {
        let receivers = self.atlas.receivers.len();
        if bake_receivers == receivers {
            return Ok(());
        }
        Err(crate::TechniqueError::Other(format!(
            "this {} bake has {bake_receivers} receivers but the scene's lightmap has {receivers}: bake again with the same lightmap resolution",
            technique.to_uppercase()
        )))
    }

    /// The shared direct-light service over this scene.
    pub fn direct(&self) -> DirectLight<'_> {
        DirectLight::new(&self.scene, &self.bvh, &self.emitters, self.settings.direct)
    }

    /// True when `point` is inside geometry: more than a quarter of the test
    /// rays that hit something hit a back face (a point in a room sees front
    /// faces all round; a point inside a box or wall sees its back faces).
    pub fn is_inside_geometry(&self, point: Vec3) -> bool {
        inside_geometry(&self.scene, &self.bvh, point)
    }

    /// The smallest lift for testing a surface point with
    /// [`SceneContext::is_hidden_surface_point`] or
    /// [`SceneContext::is_inside_geometry`]: four ray epsilons, clear of
    /// the surface's own triangles at any distance from the origin.
    pub fn surface_lift(&self) -> f32 {
        4.0 * relight_trace::direct::ray_epsilon_for(&self.bvh)
    }

    /// True when the surface point at `position`, facing `normal`, is one
    /// nobody sees: another surface lies in front of it closer than
    /// `lift`, or the point lifted off its surface is inside geometry
    /// ([`SceneContext::is_inside_geometry`]).
    ///
    /// A model that lays a second ceiling or wall just behind the visible
    /// one (the classroom's two ceilings 2.9 cm apart) puts half of any
    /// evenly spread sample set on the hidden layer, where it gathers
    /// nothing; interpolated into the visible layer, those samples are
    /// dark blotches. A lift longer than such a gap carries the test
    /// point through the visible layer into the room, so the path the
    /// lift takes is checked as well.
    pub fn is_hidden_surface_point(&self, position: Vec3, normal: Vec3, lift: f32) -> bool {
        hidden_surface_point(&self.scene, &self.bvh, position, normal, lift)
    }
}

/// Builds a lightmap atlas whose receivers stand where their texel can be
/// seen ([`relocate_receivers`]) and whose hidden texels show the seen
/// texel beside them ([`fill_hidden_texels`]).
pub fn build_atlas(scene: &Scene, bvh: &Bvh, density: TexelDensity) -> Result<Atlas, SceneError> {
    let mut atlas = chart_atlas(scene, bvh, density)?;
    relocate_receivers(scene, bvh, &mut atlas);
    fill_hidden_texels(scene, bvh, &mut atlas);
    Ok(atlas)
}

/// The atlas [`build_atlas`] starts from: charts that stop where a surface
/// stands on their edge, receivers where the rasteriser put them.
pub fn chart_atlas(scene: &Scene, bvh: &Bvh, density: TexelDensity) -> Result<Atlas, SceneError> {
    let epsilon = relight_trace::direct::ray_epsilon_for(bvh);
    let walls = |a: Vec3, b: Vec3, normal: Vec3| stands_on_edge(scene, bvh, epsilon, a, b, normal);
    Atlas::build_between_walls(scene, density, &walls)
}

/// Points along an edge where [`stands_on_edge`] looks for a surface.
const EDGE_PROBES: usize = 5;

/// Whether a surface stands on the edge from `a` to `b` of a plane with
/// `normal`: at more than half of the [`EDGE_PROBES`] points along the
/// edge, a short ray just above the plane and across the edge (`epsilon`,
/// the BVH's ray epsilon, sets its height and length) meets a surface
/// that turns from the plane by more than 60 degrees (a wall; not the
/// plane's own bumps or a curved chart's next facet).
fn stands_on_edge(scene: &Scene, bvh: &Bvh, epsilon: f32, a: Vec3, b: Vec3, normal: Vec3) -> bool {
    let along = b - a;
    let across = normal.cross(along).normalize_or_zero();
    if across == Vec3::ZERO {
        return false;
    }
    let lift = 4.0 * epsilon;
    let reach = 16.0 * epsilon;
    let walled = (0..EDGE_PROBES).filter(|&probe| {
        let point = a + along * ((probe as f32 + 0.5) / EDGE_PROBES as f32) + normal * lift;
        bvh.intersect(&Ray {
            origin: point - across * reach,
            direction: across,
            t_max: 2.0 * reach,
        })
        .is_some_and(|hit| {
            scene
                .mesh
                .geometric_normal(hit.triangle as usize)
                .dot(normal)
                .abs()
                < 0.5
        })
    });
    walled.count() > EDGE_PROBES / 2
}

/// Makes the texel of every receiver nobody sees, beside a seen texel of
/// its chart, show that texel ([`Atlas::fill_hidden`]).
///
/// The floor under an object that stands on it or in it is inside the
/// object, and so are its receivers; their zeros, blended into every
/// bilinear lookup beside the object's foot, drew a dark halo around it
/// (a generated room with an open-bottomed box 7 mm above its floor: the
/// floor's tiles by the foot 0.90x of the path tracer's light with every
/// technique). Nor does anyone see the floor under an object's bottom
/// less than a fifth of a texel above it: the gap is too thin to see
/// into. Each such texel shows its nearest seen neighbour: an edge
/// neighbour before a corner one, the lower texel index on a tie.
///
/// A texel under a partition that stands on a floor running on into the
/// next room lies between seen texels of two rooms, and whichever it
/// showed would leak into the other room's lookups. So a hidden texel is
/// filled only when all its seen neighbours are joined: they see each
/// other just off the floor, or over whatever covers the hidden texel
/// (risen to the top of that cover plus half a texel, each end seeing its
/// risen point). A box is crossed that way; a wall up to the ceiling is
/// not, and its texels stay dark.
pub fn fill_hidden_texels(scene: &Scene, bvh: &Bvh, atlas: &mut Atlas) {
    use rayon::prelude::*;
    let texel = atlas.metres_per_texel;
    if texel.is_nan() || texel <= 0.0 {
        return;
    }
    let epsilon = relight_trace::direct::ray_epsilon_for(bvh);
    let lift = 4.0 * epsilon;
    let receivers = &atlas.receivers;
    // One ray along the normal first: a point inside something meets
    // the back of a surface that way, and most receivers are spared the
    // fourteen rays of the full test.
    let hidden: Vec<bool> = (0..receivers.len())
        .into_par_iter()
        .with_min_len(1024)
        .map(|index| {
            let (position, normal) = (receivers.positions[index], receivers.normals[index]);
            let above = bvh.intersect(&Ray {
                origin: position + normal * epsilon,
                direction: normal,
                t_max: f32::INFINITY,
            });
            let texel = atlas.texel_edge(receivers.triangles[index]);
            above.is_some_and(|hit| {
                let facing_away = scene
                    .mesh
                    .geometric_normal(hit.triangle as usize)
                    .dot(normal)
                    > 0.0;
                (hit.t >= lift && is_low_cover(hit.t, facing_away, texel))
                    || ((hit.t < lift || facing_away)
                        && hidden_surface_point(scene, bvh, position, normal, lift))
            })
        })
        .collect();
    let (width, height) = (atlas.width as i64, atlas.height as i64);
    let atlas_ref = &*atlas;
    let hidden_ref = &hidden;
    let clear = |from: Vec3, to: Vec3| {
        let offset = to - from;
        let length = offset.length();
        length <= epsilon
            || !bvh.occluded(&Ray {
                origin: from,
                direction: offset / length,
                t_max: length - epsilon,
            })
    };
    let pairs: Vec<(u32, u32)> = (0..receivers.len())
        .into_par_iter()
        .with_min_len(1024)
        .filter(|&index| hidden_ref[index])
        .filter_map(|index| {
            let receivers = &atlas_ref.receivers;
            let normal = receivers.normals[index];
            let [x, y] = receivers.texels[index];
            let centre = glam::Vec2::new(x as f32 + 0.5, y as f32 + 0.5);
            // Seen texels of the same chart around this one: (squared
            // texel distance, texel, receiver).
            let mut seen = [(0i64, 0u32, 0u32); 8];
            let mut count = 0;
            for dy in -1..=1i64 {
                for dx in -1..=1i64 {
                    let (sx, sy) = (x as i64 + dx, y as i64 + dy);
                    if (dx, dy) == (0, 0) || sx < 0 || sy < 0 || sx >= width || sy >= height {
                        continue;
                    }
                    let neighbour = (sy * width + sx) as u32;
                    let receiver = atlas_ref.receiver_of_texel[neighbour as usize];
                    if receiver == u32::MAX || hidden_ref[receiver as usize] {
                        continue;
                    }
                    let other = receiver as usize;
                    let uvs = &atlas_ref.triangle_uvs[receivers.triangles[other] as usize];
                    let same_chart = receivers.normals[other].dot(normal) > 0.999
                        && relight_scene::atlas::closest_barycentric(uvs, centre).0 <= 1.75;
                    if same_chart {
                        seen[count] = (dx * dx + dy * dy, neighbour, receiver);
                        count += 1;
                    }
                }
            }
            let seen = &mut seen[..count];
            seen.sort_unstable();
            let &(_, source, source_receiver) = seen.first()?;
            let raised =
                |receiver: u32, rise: f32| receivers.positions[receiver as usize] + normal * rise;
            let position = receivers.positions[index];
            let mut cover: Option<Option<f32>> = None;
            for &(_, _, other) in &seen[1..] {
                let (a, b) = (raised(source_receiver, lift), raised(other, lift));
                if clear(a, b) {
                    continue;
                }
                // Over the top of whatever covers this texel.
                let rise = *cover.get_or_insert_with(|| {
                    bvh.intersect(&Ray {
                        origin: position + normal * epsilon,
                        direction: normal,
                        t_max: f32::INFINITY,
                    })
                    .map(|hit| hit.t + 0.5 * texel)
                });
                let rise = rise?;
                let (high_a, high_b) = (raised(source_receiver, rise), raised(other, rise));
                if !(clear(a, high_a) && clear(b, high_b) && clear(high_a, high_b)) {
                    return None;
                }
            }
            Some((y * atlas_ref.width + x, source))
        })
        .collect();
    atlas.fill_hidden(pairs);
}

/// Moves receivers that stand behind another surface to the visible part of
/// their texel.
///
/// A texel's centre, clamped onto its triangle, can fall just outside the
/// room its texel mostly lies in: a ceiling that runs under a slightly
/// tilted wall, a floor under a skirting board. Irradiance there is zero,
/// yet bilinear lookups blend that zero into the visible corner (the dark
/// seams of lightmap bakers), and a reference computed there measures a
/// point nobody sees. Rays in the texel's plane, as long as half its
/// diagonal, find such walls by their back faces; the receiver moves just
/// past the nearest one whose far side is not another chart's surface,
/// into the middle of what is left of the texel, staying in its own plane.
/// A receiver that sits on the line where another surface meets its own
/// moves a quarter texel away from it, for the same reason. A receiver
/// under an object that stands just above its surface, with no bottom or
/// with one less than a fifth of a texel above it (rays in the plane pass
/// under the object's walls), moves to the part of its texel outside the
/// object. Receivers a surface covers entirely stay where they are:
/// nothing of them is visible. A receiver inside a slab (a wall's back on
/// both sides of it) moves only within its own texel, so a texel that a
/// partition covers is never given either room's light;
/// [`fill_hidden_texels`] decides what it
/// shows. Beyond two rooms' coincident walls (each room its own box) is the
/// other room's floor, another chart (charts stop at walls standing on
/// their edges) whose lookups never read this texel: moved there, a
/// receiver would show that room's light beside the wall. Where the two
/// walls lie in one plane, this room's wall is the one met: a receiver on
/// the line where they meet the floor moves off it as from any wall, and
/// left on it, its rays and its shadow rays set out from both walls'
/// plane and passed through them into the other room (a generated pair
/// of boxes: floor texels at the partition's foot read fifty times their
/// neighbours' light). Where the
/// receiver's own triangle ends does not tell that case apart: a fine
/// floor's diagonal ends at a wall too, and so does an object's foot.
pub fn relocate_receivers(scene: &Scene, bvh: &Bvh, atlas: &mut Atlas) {
    use rayon::prelude::*;
    if atlas.metres_per_texel.is_nan() || atlas.metres_per_texel <= 0.0 {
        return;
    }
    let epsilon = relight_trace::direct::ray_epsilon_for(bvh);
    // Out of the atlas while they move, so its per-triangle lookups stay
    // readable beside them.
    let mut receivers = std::mem::take(&mut atlas.receivers);
    let atlas_ref = &*atlas;
    let triangle_uvs = &atlas_ref.triangle_uvs;
    receivers
        .positions
        .par_iter_mut()
        .zip(&receivers.normals)
        .zip(receivers.triangles.par_iter().zip(&receivers.texels))
        .for_each(|((position, &normal), (&triangle, &[x, y]))| {
            let corners = scene.mesh.vertices(triangle as usize);
            let uvs = &triangle_uvs[triangle as usize];
            // The receiver's own texel edge: finer near a light, coarser
            // outside the detail region.
            let texel = atlas_ref.texel_edge(triangle);
            let reach = texel * std::f32::consts::FRAC_1_SQRT_2;
            let lift = (texel * 1e-3).max(epsilon);
            let margin = (texel * 0.05).max(4.0 * epsilon);
            let in_texel = |point: Vec3| {
                let uv = planar_uv(corners, uvs, point);
                let inside = |value: f32, low: u32| {
                    (low as f32 - 1e-3..=low as f32 + 1.001).contains(&value)
                };
                inside(uv.x, x) && inside(uv.y, y)
            };
            // Whether the surface at `point` belongs to another chart: its
            // UVs there are far from where this chart's planar map puts
            // the point (charts lie at least two gutters apart), so its
            // lookups never read this texel. Measured in atlas texels at
            // the point itself, not from this texel's centre, so a chart's
            // finer texels near a light and a receiver clamped away from
            // its texel's centre do not read as far. A point on no surface
            // facing this way (a ray along a triangle's edge can miss it;
            // a box's bottom lies on the floor) counts as this chart's.
            let on_another_chart = |point: Vec3| {
                bvh.intersect(&Ray {
                    origin: point + normal * lift,
                    direction: -normal,
                    t_max: 2.0 * lift,
                })
                .is_some_and(|hit| {
                    let surface = hit.triangle as usize;
                    if scene.mesh.geometric_normal(surface).dot(normal) < 0.5 {
                        return false;
                    }
                    let uv = planar_uv(scene.mesh.vertices(surface), &triangle_uvs[surface], point);
                    (uv - planar_uv(corners, uvs, point)).abs().max_element() > 2.0
                })
            };
            // Under something whose back faces this way (the inside of an
            // object standing on this surface), or under an object's
            // bottom too low for the lightmap to show the gap.
            let under_cover = |point: Vec3| {
                bvh.intersect(&Ray {
                    origin: point + normal * lift,
                    direction: normal,
                    t_max: f32::INFINITY,
                })
                .is_some_and(|hit| {
                    let facing = scene.mesh.geometric_normal(hit.triangle as usize);
                    let facing_away = facing.dot(normal) > 0.0;
                    facing_away || is_low_cover(hit.t, facing_away, texel)
                })
            };
            let (tangent, bitangent) = relight_core::sampling::orthonormal_basis(normal);
            // The eight directions in the receiver's plane, 45 degrees apart,
            // that both the wall search and the way out from under a cover
            // step along.
            let in_plane = |step: usize| {
                let angle = step as f32 * std::f32::consts::FRAC_PI_4;
                tangent * angle.cos() + bitangent * angle.sin()
            };
            // The middle of the part of the texel outside the cover,
            // along the direction in which it is nearest.
            let out_from_under = |position: Vec3| {
                const STEPS: usize = 8;
                let mut nearest: Option<(f32, Vec3)> = None;
                for step in 0..8 {
                    let direction = in_plane(step);
                    for k in 1..=STEPS {
                        let distance = reach * k as f32 / STEPS as f32;
                        let point = position + direction * distance;
                        if nearest.is_some_and(|(d, _)| d <= distance) || !in_texel(point) {
                            break;
                        }
                        if !under_cover(point) {
                            nearest = Some((distance, direction));
                            break;
                        }
                    }
                }
                let (distance, direction) = nearest?;
                let beyond = ((0.5 * texel - distance) * 0.5).max(0.0);
                // Only under a cover that leaves a gap: where the object's
                // walls reach this surface (it stands on it, or in it),
                // the receiver is inside the object, and the walls
                // decide as for any other wall.
                let start = position + normal * lift;
                let reachable = |moved: Vec3| {
                    let offset = moved + normal * lift - start;
                    let length = offset.length();
                    length <= epsilon
                        || !bvh.occluded(&Ray {
                            origin: start,
                            direction: offset / length,
                            t_max: length,
                        })
                };
                [distance + beyond, distance]
                    .into_iter()
                    .map(|along| position + direction * along)
                    .find(|&moved| {
                        in_texel(moved)
                            && !under_cover(moved)
                            && reachable(moved)
                            && !on_another_chart(moved)
                    })
            };
            // A corner can put a receiver behind two walls; each step
            // crosses one.
            for pass in 0..3 {
                let origin = *position + normal * lift;
                // Whether the receiver's triangle stops before `offset`
                // from it.
                let here = *position;
                let leaves = |offset: Vec3| {
                    planar_barycentric(corners, here + offset)
                        .is_some_and(|(b, c)| b < 0.0 || c < 0.0 || b + c > 1.0)
                };
                // From the line where a wall meets this surface, `distance`
                // along `direction` ahead, to the middle of the texel's
                // side away from it.
                let off_the_line =
                    |distance: f32, direction: Vec3| -direction * ((0.5 * texel - distance) * 0.5);
                // Walls met from behind, by step: (distance, direction).
                let mut behind = [None::<(f32, Vec3)>; 8];
                let mut touching: Option<(f32, Vec3)> = None;
                for (step, wall_behind) in behind.iter_mut().enumerate() {
                    let direction = in_plane(step);
                    // Starting a margin back catches a surface the
                    // receiver lies on, which a ray from it would graze.
                    let ray = Ray {
                        origin: origin - direction * margin,
                        direction,
                        t_max: reach + margin,
                    };
                    // Where two rooms' boxes touch, the other room's wall
                    // lies in this one's plane, back to it: this room's
                    // wall, facing the receiver, decides.
                    let Some(hit) = bvh.intersect_front_first(&ray, margin, |triangle| {
                        scene
                            .mesh
                            .geometric_normal(triangle as usize)
                            .dot(direction)
                            < 0.0
                    }) else {
                        continue;
                    };
                    let distance = (hit.t - margin).max(0.0);
                    let facing = scene.mesh.geometric_normal(hit.triangle as usize);
                    let cosine = facing.dot(direction);
                    if cosine.abs() < 0.05 {
                        // A ray that runs along a surface (the receiver on
                        // a floor's plane) hits it anywhere; that says
                        // nothing about which side the receiver is on.
                        continue;
                    }
                    if cosine > 0.0 {
                        // A wall behind the start point faces away from
                        // the receiver on this side of it.
                        if hit.t >= margin {
                            *wall_behind = Some((distance, direction));
                        }
                    } else if distance < margin
                        && !leaves(-direction * margin)
                        && touching.is_none_or(|(t, _)| distance < t)
                    {
                        touching = Some((distance, direction));
                    }
                }
                // Backs of walls on both sides: inside a slab (a
                // partition, an object's side) rather than in the open
                // behind a one-sided wall.
                let enclosed =
                    (0..4).any(|step| behind[step].is_some() && behind[step + 4].is_some());
                // The nearest wall behind the receiver whose far side is
                // not another chart's surface (see the function's doc).
                let mut walls = behind;
                let wall_distance =
                    |wall: &Option<(f32, Vec3)>| wall.map_or(f32::INFINITY, |(d, _)| d);
                walls.sort_by(|a, b| wall_distance(a).total_cmp(&wall_distance(b)));
                let (mut crossing, mut covered) = (None, false);
                // A wall the receiver stands on from behind, whose far side
                // is another chart: the loader cut this surface along the
                // wall's foot ([`relight_scene::seams`]), so the receiver
                // belongs on this side.
                let mut backed_on_seam: Option<(f32, Vec3)> = None;
                for &(distance, direction) in walls.iter().flatten() {
                    // The middle of what is left of the texel beyond the
                    // wall, so the receiver stands for its visible part.
                    // A receiver inside a solid stands for its own
                    // texel: short of that when the part of the texel
                    // left is thinner, and where nothing of the texel is
                    // left (a partition covers it) it stays, hidden, for
                    // [`fill_hidden_texels`]; moved past a partition within
                    // reach of both its faces, it showed one room's light
                    // to the other's lookups. A
                    // receiver in the open behind a one-sided wall (a
                    // floor that runs on under a wall into the sun) does
                    // move out of its texel, so the room's lookups beside
                    // the wall do not read the sunlit floor outside.
                    let beyond = ((0.5 * texel - distance) * 0.5).max(margin);
                    let first = *position + direction * (distance + beyond);
                    let Some(moved) =
                        (in_texel(first) || !enclosed).then_some(first).or_else(|| {
                            [margin, 4.0 * epsilon]
                                .into_iter()
                                .map(|beyond| *position + direction * (distance + beyond))
                                .find(|&moved| in_texel(moved))
                        })
                    else {
                        covered = true;
                        break;
                    };
                    if !on_another_chart(moved) {
                        crossing = Some(moved);
                        break;
                    }
                    if distance < margin && backed_on_seam.is_none() {
                        backed_on_seam = Some((distance, direction));
                    }
                }
                if let Some(moved) = crossing {
                    *position = moved;
                } else if covered {
                    break;
                } else if let (0, Some((distance, direction))) = (pass, backed_on_seam) {
                    // On the wall's foot line, behind it (the sunlit floor
                    // outside a one-sided wall): the middle of the texel's
                    // side away from the wall, as for a wall that faces
                    // it, if its own surface reaches there; left on the
                    // line, its shadow and gather rays set out through the
                    // wall's foot.
                    let away = off_the_line(distance, direction);
                    if !leaves(away) {
                        *position += away;
                    }
                    break;
                } else if let (0, Some((distance, direction))) = (pass, touching) {
                    // On the line where another surface meets this one (a
                    // chart edge through the texel centre): the middle of
                    // the texel's side that faces away from it.
                    *position += off_the_line(distance, direction);
                    break;
                } else if pass == 0 && walls.iter().all(Option::is_none) && under_cover(*position) {
                    // Under an object that stands a few millimetres above
                    // this surface, with no bottom or a low one: rays in
                    // the plane pass under its walls and meet no back.
                    // Left there, the receiver is hidden and its texel
                    // shows the open floor beyond ([`fill_hidden_texels`]),
                    // brighter than the strip at the object's foot that the
                    // texel also covers. It moves to the middle of that
                    // strip.
                    if let Some(moved) = out_from_under(*position) {
                        *position = moved;
                    }
                    break;
                } else {
                    break;
                }
            }
        });
    atlas.receivers = receivers;
}

/// See [`SceneContext::is_inside_geometry`].
fn inside_geometry(scene: &Scene, bvh: &Bvh, point: Vec3) -> bool {
    let mut hits = 0;
    let mut back_hits = 0;
    for direction in enclosure_directions() {
        let ray = Ray {
            origin: point,
            direction,
            t_max: f32::INFINITY,
        };
        if let Some(hit) = bvh.intersect(&ray) {
            hits += 1;
            let normal = scene.mesh.geometric_normal(hit.triangle as usize);
            if normal.dot(direction) > 0.0 {
                back_hits += 1;
            }
        }
    }
    back_hits * 4 > hits
}

/// Whether the first surface along a receiver's normal, `distance` away
/// and facing the receiver unless `facing_away`, is an object's bottom low
/// enough to count as covering it, for a texel `texel` metres wide. An
/// object that stands a few millimetres above a floor on its bottom face
/// leaves a gap that lets almost no light in; the floor texels under it
/// read nearly black, yet nothing covers them along their normal within a
/// lift and no back face encloses them, so they were neither moved out
/// from under the object nor filled, and lookups beside its foot blended
/// them in: a dark halo. Below a fifth of a texel the lightmap cannot show light entering
/// the gap anyway; a table's or a bench's height is far above it at the
/// texel sizes lightmaps use.
fn is_low_cover(distance: f32, facing_away: bool, texel: f32) -> bool {
    !facing_away && distance < 0.2 * texel
}

/// See [`SceneContext::is_hidden_surface_point`].
fn hidden_surface_point(scene: &Scene, bvh: &Bvh, position: Vec3, normal: Vec3, lift: f32) -> bool {
    let epsilon = relight_trace::direct::ray_epsilon_for(bvh);
    let covered = lift > epsilon
        && bvh.occluded(&Ray {
            origin: position + normal * epsilon,
            direction: normal,
            t_max: lift - epsilon,
        });
    covered || inside_geometry(scene, bvh, position + normal * lift)
}

/// The texel-space UV of `point`, in the plane of the triangle with
/// `corners` and `uvs`, by the triangle's affine map (extended past its
/// edges, as a chart's planar projection is).
fn planar_uv(corners: [Vec3; 3], uvs: &[glam::Vec2; 3], point: Vec3) -> glam::Vec2 {
    let Some((b, c)) = planar_barycentric(corners, point) else {
        return uvs[0];
    };
    uvs[0] + (uvs[1] - uvs[0]) * b + (uvs[2] - uvs[0]) * c
}

/// The barycentric coordinates (of the second and third corner) of `point`
/// projected onto the triangle's plane; `None` for a degenerate triangle.
fn planar_barycentric(corners: [Vec3; 3], point: Vec3) -> Option<(f32, f32)> {
    let (edge_b, edge_c, offset) = (
        corners[1] - corners[0],
        corners[2] - corners[0],
        point - corners[0],
    );
    let (bb, bc, cc) = (edge_b.dot(edge_b), edge_b.dot(edge_c), edge_c.dot(edge_c));
    let (ob, oc) = (offset.dot(edge_b), offset.dot(edge_c));
    let determinant = bb * cc - bc * bc;
    if determinant.abs() <= f32::MIN_POSITIVE {
        return None;
    }
    let b = (cc * ob - bc * oc) / determinant;
    let c = (bb * oc - bc * ob) / determinant;
    Some((b, c))
}

/// Directions that test whether a point is enclosed: the axes and the cube
/// diagonals.
fn enclosure_directions() -> [Vec3; 14] {
    let mut directions = [Vec3::ZERO; 14];
    let axes = [Vec3::X, Vec3::Y, Vec3::Z];
    for (index, axis) in axes.iter().enumerate() {
        directions[2 * index] = *axis;
        directions[2 * index + 1] = -*axis;
    }
    let mut slot = 6;
    for x in [-1.0f32, 1.0] {
        for y in [-1.0f32, 1.0] {
            for z in [-1.0f32, 1.0] {
                directions[slot] = Vec3::new(x, y, z).normalize();
                slot += 1;
            }
        }
    }
    directions
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::test_variants::{default_variant, default_variant_context};

    /// The triangles of a generated variant's floor: level at y = 0,
    /// facing up.
    fn floor_triangles(mesh: &relight_scene::Mesh) -> Vec<usize> {
        (0..mesh.triangles.len())
            .filter(|&t| {
                mesh.geometric_normal(t).y > 0.99
                    && mesh.vertices(t).iter().all(|v| v.y.abs() < 1e-4)
            })
            .collect()
    }

    /// Generated variant 97 is two rooms modelled as two boxes: each floor
    /// is its own quad, and the quads meet under the two boxes' coincident
    /// walls, with a doorway. One chart held both floors, so texels
    /// straddled the partition, and relocation moved receivers on the
    /// unlit room's side across it (one wall turns its back to them), so
    /// every few texels along the unlit room's wall the floor showed the
    /// lamp-lit room's light. Now each floor's texels lie in charts apart
    /// from the other's, and each floor receiver stands on its own
    /// floor's side of the partition (within 1 mm, rounding).
    #[test]
    fn rooms_modelled_as_two_boxes_keep_their_floors_apart() {
        let context = default_variant_context(97);
        let mesh = &context.scene.mesh;
        let floors = floor_triangles(mesh);
        let max_x = |t: usize| {
            mesh.vertices(t)
                .iter()
                .map(|v| v.x)
                .fold(f32::MIN, f32::max)
        };
        // The partition: where walls facing both ways along x stand in one
        // plane. (The floors' own pieces do not tell: the loader cuts a
        // floor along the foot of an object standing on it.)
        let wall_planes = |facing: f32| {
            (0..mesh.triangles.len())
                .filter(move |&t| mesh.geometric_normal(t).x * facing > 0.99)
                .map(|t| mesh.vertices(t)[0].x)
                .collect::<Vec<f32>>()
        };
        let facing_back = wall_planes(-1.0);
        let (floor_low, floor_high) = floors
            .iter()
            .flat_map(|&t| mesh.vertices(t))
            .fold((f32::MAX, f32::MIN), |(low, high), v| {
                (low.min(v.x), high.max(v.x))
            });
        let partition = wall_planes(1.0)
            .into_iter()
            .filter(|&x| x > floor_low + 0.1 && x < floor_high - 0.1)
            .find(|x| facing_back.iter().any(|back| (back - x).abs() < 1e-4))
            .expect("coincident walls facing both ways between the floors' ends");
        let (first, second): (Vec<usize>, Vec<usize>) =
            floors.iter().partition(|&&t| max_x(t) <= partition + 1e-4);
        assert!(
            !first.is_empty() && !second.is_empty(),
            "two floors either side of x = {partition}: {floors:?}"
        );
        let walls_there = (0..mesh.triangles.len())
            .filter(|&t| {
                mesh.vertices(t)
                    .iter()
                    .all(|v| (v.x - partition).abs() < 1e-4)
            })
            .count();
        assert!(
            walls_there >= 4,
            "coincident partition walls at x = {partition}"
        );
        let uv_bounds = |triangles: &[usize]| {
            let mut low = glam::Vec2::splat(f32::MAX);
            let mut high = glam::Vec2::splat(f32::MIN);
            for &t in triangles {
                for uv in context.atlas.triangle_uvs[t] {
                    low = low.min(uv);
                    high = high.max(uv);
                }
            }
            (low, high)
        };
        let ((low_a, high_a), (low_b, high_b)) = (uv_bounds(&first), uv_bounds(&second));
        let apart =
            high_a.x < low_b.x || high_b.x < low_a.x || high_a.y < low_b.y || high_b.y < low_a.y;
        assert!(
            apart,
            "floors share texels: {low_a}..{high_a} and {low_b}..{high_b}"
        );
        let receivers = &context.atlas.receivers;
        let strays: Vec<usize> = (0..receivers.len())
            .filter(|&index| {
                let triangle = receivers.triangles[index] as usize;
                let x = receivers.positions[index].x;
                (first.contains(&triangle) && x > partition + 1e-3)
                    || (second.contains(&triangle) && x < partition - 1e-3)
            })
            .collect();
        assert!(
            strays.is_empty(),
            "{} floor receivers off their triangle, e.g. {:?}",
            strays.len(),
            strays.first().map(|&index| receivers.positions[index])
        );
    }

    /// Variant 52 of the generated family of seed 7 is two rooms modelled
    /// as two boxes that touch: each room's partition wall lies in the
    /// other's plane, facing into its own room, with a doorway through
    /// both, and the lamp in one room. The other room's floor receivers at
    /// the partition's foot sat on the line where the walls meet the
    /// floor, since the in-plane search met the lit room's wall from
    /// behind as often as its own from the front; their shadow rays set
    /// out from the walls' plane and passed through both, and those texels
    /// read fifty times their neighbours' light. Each now stands off the
    /// wall, lit as the floor a quarter texel further into its room is
    /// (dark but where the doorway lets the lamp in). The corners, where a
    /// receiver moves off one wall only, are left out: there the one
    /// nearest the lamp's room still sits on the partition's plane.
    #[test]
    fn floor_receivers_at_two_boxes_shared_wall_stay_in_their_room() {
        let (_folder, path) = crate::test_variants::seeded_variant(7, 52);
        let scene = relight_scene::load_scene(&path).expect("variant loads");
        let context = SceneContext::new(scene, ContextSettings::default()).expect("context");
        let (mesh, receivers) = (&context.scene.mesh, &context.atlas.receivers);
        let texel = context.atlas.metres_per_texel;
        let floors = floor_triangles(mesh);
        let min_x = |t: usize| {
            mesh.vertices(t)
                .iter()
                .map(|v| v.x)
                .fold(f32::MAX, f32::min)
        };
        let partition = floors.iter().map(|&t| min_x(t)).fold(f32::MIN, f32::max);
        let unlit_floor = |t: usize| floors.contains(&t) && min_x(t) > partition - 1e-4;
        assert!(
            context.scene.lights.iter().all(|light| match light {
                relight_scene::Light::Point { position, .. } => position.x < partition,
                _ => false,
            }),
            "the lamp stands in the room below x = {partition}"
        );
        let width = floors
            .iter()
            .flat_map(|&t| mesh.vertices(t))
            .map(|v| v.z)
            .fold(f32::MIN, f32::max);
        let direct = context.direct();
        let lights = &context.scene.lights;
        let at_foot: Vec<usize> = (0..receivers.len())
            .filter(|&index| {
                let position = receivers.positions[index];
                unlit_floor(receivers.triangles[index] as usize)
                    && position.x < partition + 0.5 * texel
                    && (texel..width - texel).contains(&position.z)
            })
            .collect();
        assert!(
            at_foot.len() > 20,
            "{} receivers at the foot",
            at_foot.len()
        );
        let strays: Vec<(Vec3, relight_core::Rgb, relight_core::Rgb)> = at_foot
            .iter()
            .filter_map(|&index| {
                let (position, normal) = (receivers.positions[index], receivers.normals[index]);
                let here = direct.irradiance(lights, position, normal, 0);
                let further = position + Vec3::X * 0.25 * texel;
                let there = direct.irradiance(lights, further, normal, 0);
                (here.max_element() > 2.0 * there.max_element() + 1e-4)
                    .then_some((position, here, there))
            })
            .collect();
        assert!(
            strays.is_empty(),
            "{} of {} receivers at the foot lit past the wall, e.g. {:?}",
            strays.len(),
            at_foot.len(),
            strays.first()
        );
    }

    /// Generated variant 1 is two rooms in one shell: one floor quad runs
    /// under both and a 13 cm partition with a doorway stands on it, the
    /// lamp in one room and the camera in the other. Before the loader cut
    /// the floor along the partition's feet, its chart was one projection
    /// across the partition: floor points 2 cm either side of it lay 0.8
    /// texels apart in the lightmap, so the texels at the foot straddled
    /// the partition, each holding one side's light for both (a bright
    /// line along the unlit room's wall foot). Now the two sides are
    /// different charts, and a chart's gutter keeps every bilinear lookup
    /// from the next chart's texels: such points lie more than the gutter
    /// apart, all along the partition, doorway included.
    #[test]
    fn a_slab_under_a_partition_is_two_charts() {
        let context = default_variant_context(1);
        let (scene, atlas) = (&context.scene, &context.atlas);
        let lamp = match scene.lights.as_slice() {
            [relight_scene::Light::Point { position, .. }] => *position,
            other => panic!("variant 1 has one point light, not {other:?}"),
        };
        let eye = scene.camera.eye;
        assert!(
            lamp.x < eye.x,
            "the lamp and the camera are in different rooms"
        );
        // The partition's faces: the walls between the lamp and the camera
        // that reach over a door's height (the objects in the rooms are
        // lower), facing the camera's room and, nearest that, the lamp's.
        let tall_walls = |facing: f32| {
            (0..scene.mesh.triangles.len())
                .filter(move |&t| scene.mesh.geometric_normal(t).x * facing > 0.99)
                .filter(|&t| scene.mesh.vertices(t).iter().any(|v| v.y > 1.9))
                .map(|t| scene.mesh.vertices(t)[0].x)
                .filter(|&x| x > lamp.x && x < eye.x)
        };
        let unlit_face = tall_walls(1.0).fold(f32::MIN, f32::max);
        let lit_face = tall_walls(-1.0)
            .filter(|&x| x < unlit_face)
            .fold(f32::MIN, f32::max);
        assert!(
            unlit_face > lit_face && unlit_face - lit_face < 0.5,
            "partition faces at x = {lit_face} and {unlit_face}"
        );
        let width = scene.mesh.bounds().1.z.min(6.0);
        let uv_at = |x: f32, z: f32| {
            let hit = context.bvh.intersect(&Ray {
                origin: Vec3::new(x, 0.05, z),
                direction: -Vec3::Y,
                t_max: 0.1,
            })?;
            (scene.mesh.geometric_normal(hit.triangle as usize).y > 0.99)
                .then(|| atlas.uv_of(hit.triangle, hit.barycentric))
        };
        let mut pairs = 0;
        let mut z = 0.1;
        while z < width - 0.1 {
            if let (Some(lit), Some(unlit)) =
                (uv_at(lit_face - 0.02, z), uv_at(unlit_face + 0.02, z))
            {
                pairs += 1;
                let apart = lit.distance(unlit);
                assert!(
                    apart > relight_scene::atlas::GUTTER_TEXELS as f32,
                    "floor points 2 cm either side of the partition at z = {z} are {apart} texels apart in the lightmap"
                );
            }
            z += 0.05;
        }
        assert!(
            pairs > 80,
            "{pairs} pairs of floor points along the partition"
        );
    }

    /// Generated variant 38 is a hall whose single-plane walls, floor and
    /// ceiling run 0.5 m past each other, all cut into 0.68 m cells, with
    /// boxes standing flush on the floor and 9 mm into it. A ceiling
    /// receiver whose texel reaches past a wall into the hall moves into
    /// the hall, and an object's receiver below the floor moves above it.
    /// When receivers kept to their side of any wall that met their
    /// triangle's edge along a ray (a fine ceiling's diagonal, a box's
    /// foot), 13 ceiling receivers stayed over a fifth of a texel outside
    /// the walls and 5 of the boxes' below the floor. The floor is not
    /// counted: where a box stands against a wall, its back and the wall
    /// are coincident and a ray meets either, so a few floor receivers
    /// beside it stay outside.
    ///
    /// Measured at the lightmap's 128-texel fit (0.77 m texels), where every
    /// texel on the ceiling's 0.5 m overhang reaches into the hall. The
    /// automatic atlas now keeps texels to half a metre, and there a row of
    /// texels lies wholly on the overhang outside the walls, whose
    /// receivers stay where they are.
    #[test]
    fn receivers_beside_one_wall_move_to_its_front() {
        let context = crate::test_variants::variant_context(
            38,
            ContextSettings {
                lightmap: TexelDensity::TargetResolution(128),
                ..ContextSettings::default()
            },
        );
        assert!(context.atlas.metres_per_texel > 0.7);
        let mesh = &context.scene.mesh;
        let texel = context.atlas.metres_per_texel;
        // The hall's inside: between the walls' planes.
        let (mut low, mut high) = (Vec3::splat(f32::MAX), Vec3::splat(f32::MIN));
        for t in 0..mesh.triangles.len() {
            let normal = mesh.geometric_normal(t);
            let corner = mesh.vertices(t)[0];
            for axis in [0, 2] {
                if normal[axis].abs() > 0.99 {
                    low[axis] = low[axis].min(corner[axis]);
                    high[axis] = high[axis].max(corner[axis]);
                }
            }
        }
        let receivers = &context.atlas.receivers;
        let (mut outside, mut below) = (0, 0);
        for index in 0..receivers.len() {
            let (position, normal) = (receivers.positions[index], receivers.normals[index]);
            let beyond =
                |axis: usize| (low[axis] - position[axis]).max(position[axis] - high[axis]);
            let corners = mesh.vertices(receivers.triangles[index] as usize);
            // Off the floor, inside the walls: the boxes (and the ceiling,
            // never below the floor).
            let object = corners.iter().all(|corner| {
                [0, 2].iter().all(|&axis| {
                    corner[axis] > low[axis] + 1e-3 && corner[axis] < high[axis] - 1e-3
                })
            }) && corners.iter().any(|corner| corner.y > 1e-3);
            if normal.y < -0.99 {
                let out = beyond(0).max(beyond(2));
                outside += usize::from(out > 0.2 * texel);
            }
            below += usize::from(object && position.y < -0.01);
        }
        assert!(
            outside == 0 && below == 0,
            "{outside} ceiling receivers outside the walls, {below} objects' below the floor"
        );
    }

    /// Relocation measures in each receiver's own texels: on the walls
    /// beside variant 15's corner lamp those are about a third of the
    /// room's. A step crosses one wall within reach (half the texel's
    /// diagonal, 0.71 edges) and lands at most a quarter edge past it; a
    /// corner's second wall is crossed at a right angle, so a receiver
    /// moves at most sqrt(2) * 0.96 = 1.35 of its texel edges. Measured
    /// in the room's texels, receivers on the fine walls moved 1.7 of
    /// theirs.
    #[test]
    fn receivers_move_within_their_own_texels() {
        let (_folder, path) = default_variant(15);
        let scene = relight_scene::load_scene(&path).expect("variant loads");
        let bvh = Bvh::build(&scene.mesh.positions, &scene.mesh.triangles);
        let mut atlas = chart_atlas(&scene, &bvh, TexelDensity::default()).expect("atlas");
        assert!(atlas.near_light_charts > 0, "the lamp's walls are refined");
        let before = atlas.receivers.positions.clone();
        relocate_receivers(&scene, &bvh, &mut atlas);
        let receivers = &atlas.receivers;
        let (mut farthest, mut moved_fine) = (0.0f32, 0);
        for ((&triangle, &after), &start) in receivers
            .triangles
            .iter()
            .zip(&receivers.positions)
            .zip(&before)
        {
            let moved = after.distance(start);
            farthest = farthest.max(moved / atlas.texel_edge(triangle));
            moved_fine += usize::from(moved > 0.0 && atlas.texel_scale(triangle) < 1.0);
        }
        assert!(
            moved_fine > 0,
            "the fine walls' receivers by the corner move"
        );
        assert!(
            farthest < 1.4,
            "a receiver moved {farthest} of its texel edges"
        );
    }

    /// Generated variant 0 has an open-bottomed box 7 mm above a room's
    /// floor. Rays in the floor's plane pass under its walls, so a floor
    /// receiver whose texel centre lay under the box stayed there, hidden,
    /// even where its texel reached past the box's foot, and its texel
    /// showed the open floor beyond: the foot's tiles were brighter than
    /// the path tracer's with every technique. Such receivers now stand on
    /// the strip of their texel outside the box, within their texel.
    #[test]
    fn receivers_under_an_open_box_move_to_the_strip_at_its_foot() {
        use relight_scene::generate::variants::{variant, VARIANTS_DEFAULT_SEED};
        let generated = variant(VARIANTS_DEFAULT_SEED, 0);
        let foot = generated.feet[0];
        assert!(!foot.has_bottom, "an open-bottomed box");
        let (_folder, path) = default_variant(0);
        let scene = relight_scene::load_scene(&path).expect("variant loads");
        let bvh = Bvh::build(&scene.mesh.positions, &scene.mesh.triangles);
        let mut atlas = chart_atlas(&scene, &bvh, TexelDensity::default()).expect("atlas");
        let before = atlas.receivers.positions.clone();
        relocate_receivers(&scene, &bvh, &mut atlas);
        let receivers = &atlas.receivers;
        let under = |point: Vec3| {
            point.x > foot.low.x
                && point.x < foot.high.x
                && point.z > foot.low.y
                && point.z < foot.high.y
        };
        let mut moved_out = 0;
        for (index, &from) in before.iter().enumerate() {
            let to = receivers.positions[index];
            let on_floor = receivers.normals[index].y > 0.99 && (from.y - foot.floor).abs() < 1e-3;
            if !on_floor || !under(from) || under(to) {
                continue;
            }
            moved_out += 1;
            let edge = atlas.texel_edge(receivers.triangles[index]);
            assert!(
                (to.y - from.y).abs() < 1e-5,
                "left the floor: {from} -> {to}"
            );
            // Within the texel: at most half its diagonal from the centre.
            assert!(
                from.distance(to) < 0.71 * edge,
                "{from} -> {to}, texel {edge} m"
            );
        }
        assert!(
            moved_out > 0,
            "no floor receiver moved out from under the box"
        );
    }

    /// Generated variant 15 has a point light 11 cm from a 7 m room's
    /// corner. At the automatic lightmap the walls beside it get texels of
    /// at most 10 cm (the room's are 20 cm), as whole large charts, not
    /// as the small ones whose every triangle the final gather samples;
    /// at a requested resolution they keep the room's texels, which no
    /// other chart pays for.
    #[test]
    fn walls_beside_a_lamp_in_a_corner_get_finer_texels() {
        let (_folder, path) = default_variant(15);
        let near_texels = |lightmap: TexelDensity| {
            let scene = relight_scene::load_scene(&path).expect("variant loads");
            let light = scene.lights[0].position().expect("a point light");
            let settings = ContextSettings {
                lightmap,
                ..ContextSettings::default()
            };
            let context = SceneContext::new(scene, settings).expect("context");
            let atlas = &context.atlas;
            let receivers = &atlas.receivers;
            let near: Vec<u32> = (0..receivers.len())
                .filter(|&index| receivers.positions[index].distance(light) < 0.3)
                .map(|index| receivers.triangles[index])
                .collect();
            assert!(
                near.iter()
                    .all(|&triangle| !atlas.in_small_near_light_chart(triangle)),
                "a wall counted as a small chart"
            );
            let edges: Vec<f32> = near
                .iter()
                .map(|&triangle| atlas.texel_area(triangle).sqrt())
                .collect();
            (edges, atlas.metres_per_texel)
        };
        let (automatic, room) = near_texels(TexelDensity::default());
        assert!(room > 0.15, "the room's texels: {room} m");
        assert!(
            automatic.len() > 8,
            "{} receivers near the lamp",
            automatic.len()
        );
        let coarsest = automatic.iter().copied().fold(0.0f32, f32::max);
        assert!(coarsest <= 0.1, "{coarsest} m texels near the lamp");
        let (requested, room) = near_texels(TexelDensity::TargetResolution(128));
        assert!(
            requested.iter().all(|&edge| (edge - room).abs() < 1e-6),
            "a requested resolution refined the walls: {requested:?} against {room}"
        );
    }

    /// On the shipped Cornell box some texel centres lie behind a wall (the
    /// ceiling runs under the slightly tilted right wall) or under a box.
    /// After relocation only texels a surface covers completely may still
    /// be enclosed (measured: 294 enclosed before, 193 under the boxes
    /// after, 344 moved); every moved receiver stays in its
    /// own plane within half a texel diagonal of where it was.
    #[test]
    fn relocated_receivers_stand_where_they_can_be_seen() {
        let path = std::path::Path::new(env!("CARGO_MANIFEST_DIR"))
            .join("../../scenes/cornell-box/scene.toml");
        let scene = relight_scene::load_scene(&path).expect("shipped scene loads");
        let context = SceneContext::new(scene, ContextSettings::default()).expect("context");
        let raw =
            chart_atlas(&context.scene, &context.bvh, context.settings.lightmap).expect("atlas");
        let texel = context.atlas.metres_per_texel;
        let lift = texel * 0.01;
        let enclosed = |atlas: &Atlas| {
            (0..atlas.receivers.len())
                .filter(|&i| {
                    let receivers = &atlas.receivers;
                    context.is_inside_geometry(receivers.positions[i] + receivers.normals[i] * lift)
                })
                .count()
        };
        let (before, after) = (enclosed(&raw), enclosed(&context.atlas));
        let mut moved = 0;
        for index in 0..raw.receivers.len() {
            let (from, to) = (
                raw.receivers.positions[index],
                context.atlas.receivers.positions[index],
            );
            if from != to {
                moved += 1;
                let normal = raw.receivers.normals[index];
                assert!((to - from).dot(normal).abs() < 1e-5, "left its plane");
                assert!(from.distance(to) < 1.5 * texel, "{from} -> {to}");
            }
        }
        println!("enclosed before {before}, after {after}; moved {moved}");
        assert!(
            moved > 100 && before >= after + 80,
            "{before} -> {after}, moved {moved}"
        );
    }

    /// The hidden layer of a doubled ceiling is hidden whether the lift
    /// stays in the gap or crosses it into the room, and no surface of the
    /// room is.
    #[test]
    fn a_second_ceiling_just_above_the_visible_one_is_hidden() {
        let gap = 0.025;
        let obj = relight_scene::generate::room_with_second_ceiling_obj(Some(gap));
        let scene = relight_scene::generate::load_obj_scene(&obj, "").expect("loads");
        let context = SceneContext::new(scene, ContextSettings::default()).expect("context");
        let [_, height, _] = relight_scene::generate::TEST_ROOM;
        let down = -Vec3::Y;
        for lift in [context.surface_lift(), 0.01, 0.04, 0.1] {
            for (x, z) in [(0.0, 0.0), (1.3, -0.7), (-1.9, 1.9)] {
                let upper = Vec3::new(x, height + gap, z);
                assert!(
                    context.is_hidden_surface_point(upper, down, lift),
                    "upper layer at ({x}, {z}), lift {lift}"
                );
                let visible = [
                    (Vec3::new(x, height, z), down),
                    (Vec3::new(x, 0.0, z), Vec3::Y),
                    (Vec3::new(2.0, 1.2, z.clamp(-1.9, 1.9)), -Vec3::X),
                ];
                for (position, normal) in visible {
                    assert!(
                        !context.is_hidden_surface_point(position, normal, lift),
                        "{position} facing {normal}, lift {lift}"
                    );
                }
            }
        }
    }

    /// The floor a lookup reads at (x, z): the triangle and barycentric a
    /// ray straight down from 0.3 m meets.
    fn floor_point(context: &SceneContext, x: f32, z: f32) -> (u32, glam::Vec2) {
        let hit = context
            .bvh
            .intersect(&Ray {
                origin: Vec3::new(x, 0.3, z),
                direction: -Vec3::Y,
                t_max: 1.0,
            })
            .expect("the floor is below");
        assert!((0.3 - hit.t).abs() < 1e-4, "({x}, {z}) is not on the floor");
        (hit.triangle, hit.barycentric)
    }

    /// Lightmap lookups on the floor a quarter texel outside the feet of
    /// five boxes (open-bottomed 7 mm above the floor and 15 mm into it,
    /// with a bottom flush, 20 mm into it and 6 mm above it), in a
    /// lightmap that is 1 on the floor around them and 0 under them, read
    /// the floor around them: none under 0.9. Without
    /// [`fill_hidden_texels`] 11 of the lookups around the first four
    /// read under 0.9 (mean 0.966): the contact halo every technique
    /// showed. Without [`is_low_cover`] the floor under the raised box
    /// with a bottom was neither moved out nor filled: 52 of the 270
    /// lookups read under 0.9 (mean 0.892).
    #[test]
    fn lookups_beside_the_feet_of_objects_read_the_floor_around_them() {
        let (obj, feet) = relight_scene::generate::room_with_a_raised_bottomed_box_obj(0.006);
        let scene = relight_scene::generate::load_obj_scene(&obj, "").expect("loads");
        let settings = ContextSettings {
            lightmap: TexelDensity::MetresPerTexel(0.1),
            ..ContextSettings::default()
        };
        let context = SceneContext::new(scene, settings).expect("context");
        let atlas = &context.atlas;
        let texel = atlas.metres_per_texel;
        let under = |position: Vec3| {
            feet.iter().any(|[xs, zs]| {
                (xs[0]..xs[1]).contains(&position.x) && (zs[0]..zs[1]).contains(&position.z)
            })
        };
        let values: Vec<relight_core::Rgb> = (0..atlas.receivers.len())
            .map(|index| {
                let position = atlas.receivers.positions[index];
                let on_floor = atlas.receivers.normals[index].y > 0.99 && position.y.abs() < 1e-3;
                if on_floor && under(position) {
                    relight_core::Rgb::ZERO
                } else {
                    relight_core::Rgb::ONE
                }
            })
            .collect();
        let lightmap = atlas.to_lightmap(&values);
        let mut read = Vec::new();
        for [xs, zs] in &feet {
            let out = 0.25 * texel;
            let steps = |from: f32, to: f32| {
                let count = ((to - from + 2.0 * out) / (0.5 * texel)).round() as usize;
                (0..=count).map(move |step| {
                    from - out + (to - from + 2.0 * out) * step as f32 / count as f32
                })
            };
            for x in steps(xs[0], xs[1]) {
                for z in [zs[0] - out, zs[1] + out] {
                    read.push(floor_point(&context, x, z));
                }
            }
            for z in steps(zs[0], zs[1]) {
                for x in [xs[0] - out, xs[1] + out] {
                    read.push(floor_point(&context, x, z));
                }
            }
        }
        let reads: Vec<f32> = read
            .iter()
            .map(|&(triangle, barycentric)| atlas.sample(&lightmap, triangle, barycentric).x)
            .collect();
        let mean = reads.iter().sum::<f32>() / reads.len() as f32;
        let dark = reads.iter().filter(|&&value| value < 0.9).count();
        println!(
            "{} hidden texels filled; {} lookups, mean {mean:.3}, {dark} under 0.9",
            atlas.filled_texels(),
            reads.len()
        );
        assert!(mean > 0.99 && dark == 0, "mean {mean}, {dark} dark");
    }

    /// A partition from floor to ceiling on a floor that runs under it:
    /// light on one side must not reach the other side's lookups through
    /// the texels under the partition, whether the partition covers one
    /// texel's width, two or four; and where it is thick enough that no
    /// texel under it touches both rooms, the lit side's lookups beside
    /// it read its light. When [`relocate_receivers`] moved receivers
    /// inside a 0.12 m partition out of their texels, to one side or the
    /// other, the dark side's lookups read up to 0.15 of the lit side's
    /// light.
    #[test]
    fn a_partition_on_a_shared_floor_keeps_each_rooms_light_to_itself() {
        let texel = 0.1;
        for thickness in [0.12, 0.2, 0.4] {
            let obj = relight_scene::generate::two_rooms_on_one_floor_obj(thickness);
            let scene = relight_scene::generate::load_obj_scene(&obj, "").expect("loads");
            let settings = ContextSettings {
                lightmap: TexelDensity::MetresPerTexel(texel),
                ..ContextSettings::default()
            };
            let context = SceneContext::new(scene, settings).expect("context");
            let atlas = &context.atlas;
            let half = thickness / 2.0;
            // Lit: the room at negative x, the far side of the partition dark.
            let values: Vec<relight_core::Rgb> = atlas
                .receivers
                .positions
                .iter()
                .map(|position| {
                    if position.x < -half {
                        relight_core::Rgb::ONE
                    } else {
                        relight_core::Rgb::ZERO
                    }
                })
                .collect();
            let lightmap = atlas.to_lightmap(&values);
            let (mut darkest_lit, mut brightest_dark) = (f32::MAX, 0.0f32);
            for step in 0..36 {
                let z = -1.75 + step as f32 * 0.1;
                let out = 0.25 * texel;
                let (triangle, barycentric) = floor_point(&context, -half - out, z);
                darkest_lit = darkest_lit.min(atlas.sample(&lightmap, triangle, barycentric).x);
                let (triangle, barycentric) = floor_point(&context, half + out, z);
                brightest_dark =
                    brightest_dark.max(atlas.sample(&lightmap, triangle, barycentric).x);
            }
            println!(
                "partition {thickness} m: {} texels filled, lit side reads at least {darkest_lit:.3}, dark side at most {brightest_dark:.3}",
                atlas.filled_texels()
            );
            assert!(brightest_dark < 0.02, "{thickness} m: {brightest_dark}");
            if thickness >= 3.0 * texel {
                assert!(darkest_lit > 0.95, "{thickness} m: {darkest_lit}");
            }
        }
    }
}
