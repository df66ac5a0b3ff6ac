//! The PIC bake: surfels, hierarchy, caches and links, and their encoding.

use crate::caches::{cache_atlas, place_caches, CachePlacement, GridLayout};
use crate::hierarchy::{self, ClusterMetric, Hierarchy};
use crate::links::{
    hemisphere_scale, visible_solid_angle, LinkForm, LinkSettings, Senders, OVERLAP_ALLOWANCE,
};
use crate::surfels::{place_surfels, Surfels};
use crate::PicParams;
use glam::{Vec2, Vec3};
use rayon::prelude::*;
use relight_core::colour::octahedral_encode;
use relight_technique::{
    join_parts, shards_disagree, BakeEstimate, BakePart, PayloadReader, PayloadWriter, Progress,
    SceneContext, Shard, TechniqueError,
};

// 3: links cut with partly hidden nodes first and scaled back to the
// cache's hemisphere; a version-2 bake holds other links for the same
// parameters.
const PAYLOAD_VERSION: u32 = 3;

/// Links are padded to a multiple of this per cache (the kernel's lanes).
pub const LINK_ALIGNMENT: usize = crate::kernels::LANES;

/// Everything precomputed. Links are struct of arrays, `links_per_cache`
/// per cache, caches in placement order.
#[derive(Clone, Debug, PartialEq)]
pub struct PicBake {
    pub surfels: Surfels,
    pub hierarchy: Hierarchy,
    /// Metres per texel of the cache atlas; 0 = the scene's own atlas.
    pub cache_atlas_metres: f32,
    pub caches: CachePlacement,
    pub links_per_cache: usize,
    /// 0 for runtime projection, else the bands of the projected links.
    pub projected_bands: usize,
    pub link_nodes: Vec<u32>,
    /// f16 of factor x `factor_scale` (runtime projection).
    pub link_factors: Vec<u16>,
    /// f16 of 1 - cos(alpha).
    pub link_cones: Vec<u16>,
    pub link_directions: Vec<[u16; 2]>,
    /// f16 of coefficient x `factor_scale`, `projected_bands^2` per link.
    pub link_coefficients: Vec<u16>,
    pub factor_scale: f32,
    pub hierarchy_builder: u32,
    /// Surfels dropped because geometry encloses them.
    pub enclosed_surfels: u32,
    /// The cache bands (luma, chroma) the bake was made for: the run-time
    /// default unless `bands`, `chroma_bands` or `preset` are given again.
    pub cache_bands: [u32; 2],
}

/// The power of two that brings `largest` into [8192, 16384), the top
/// octave of f16 below 32768, so that scaled values stay normal f16 numbers
/// with room to spare; 0 for nothing to scale.
fn scale_exponent(largest: f32) -> i32 {
    if largest > 0.0 {
        (16384.0 / largest).log2().floor() as i32
    } else {
        0
    }
}

/// One shard of a PIC bake: the surfels, their hierarchy and the caches,
/// which every shard computes alike, and the links of the caches
/// `first_cache..`, before the bake-wide scale that only the merge knows.
/// Each cache's links draw on its own index, so they are the same in any
/// shard.
pub struct PicPart {
    pub surfels: Surfels,
    pub hierarchy: Hierarchy,
    pub cache_atlas_metres: f32,
    pub caches: CachePlacement,
    pub links_per_cache: usize,
    /// SH coefficients per projected link; 0 for run-time projection.
    pub coefficient_count: usize,
    pub hierarchy_builder: u32,
    pub enclosed_surfels: u32,
    pub cache_bands: [u32; 2],
    pub first_cache: usize,
    /// Per own cache: its linked nodes, and with run-time projection the
    /// unscaled (factor, 1 - cos, direction) of each.
    pub nodes: Vec<Vec<u32>>,
    pub runtime: Vec<Vec<(f32, f32, Vec3)>>,
    /// Per own cache: the power of two its projected coefficients are
    /// stored at, and their largest magnitude.
    pub exponents: Vec<i32>,
    pub largest: Vec<f32>,
    /// Projected coefficients of the own caches, f16 at each cache's scale,
    /// `links_per_cache * coefficient_count` per cache.
    pub coefficients: Vec<u16>,
}

/// Shard payloads carry their own version beside the bake's.
const PART_VERSION: u32 = 2;

/// Link slots per cache: `links` rounded up to the kernel's lanes, and no
/// more than a cut of the hierarchy can hold (one node per surfel).
fn links_per_cache(links: usize, surfels: usize) -> usize {
    links.min(surfels).div_ceil(LINK_ALIGNMENT) * LINK_ALIGNMENT
}

impl PicPart {
    pub fn build(
        context: &SceneContext,
        params: &PicParams,
        shard: Shard,
        progress: &dyn Progress,
    ) -> Result<Self, TechniqueError> {
        progress.start("pic surfels", 1);
        let mut surfels = place_surfels(&context.scene, params.surfels as usize, params.relaxation);
        // Surfels enclosed by geometry (floor under a box, faces pressed
        // together) neither see nor are seen: in a cluster they would only
        // dilute its radiosity, so they go.
        let lift = context.surface_lift();
        let keep: Vec<bool> = (0..surfels.len())
            .into_par_iter()
            .map(|i| !context.is_inside_geometry(surfels.positions[i] + surfels.normals[i] * lift))
            .collect();
        let enclosed = keep.iter().filter(|k| !**k).count();
        surfels.retain(&keep);
        progress.finish();
        if surfels.is_empty() {
            return Err(TechniqueError::Other(
                "the scene has no surface area for surfels: PIC needs triangles".into(),
            ));
        }
        let merges = if params.hierarchy == "kd" {
            hierarchy::build_kd_tree(&surfels.positions)
        } else {
            hierarchy::build_agglomerative(
                &surfels.positions,
                &surfels.normals,
                &context.bvh,
                ClusterMetric {
                    normal: params.normal_weight,
                    balance: params.balance_weight,
                    visibility: params.visibility_weight,
                },
                progress,
            )
        };
        let (hierarchy, order) = hierarchy::finalise(surfels.len(), &merges);
        surfels.permute(&order);
        progress.start("pic cache placement", 1);
        let (own_atlas, cache_atlas_metres) =
            cache_atlas(context, params.lightmap_caches as usize)?;
        let atlas = own_atlas.as_ref().unwrap_or(&context.atlas);
        let grid_dims = (params.grid.iter().all(|&d| d > 0)).then_some(params.grid);
        let caches = place_caches(context, atlas, params.grid_cells as usize, grid_dims);
        progress.finish();
        let form = if params.projected {
            LinkForm::Projected {
                bands: params.bands as usize,
            }
        } else {
            LinkForm::Runtime
        };
        let settings = LinkSettings {
            links: params.links as usize,
            node_samples: params.node_samples,
            link_samples: params.link_samples,
            leak_refinement: params.leak_refinement,
            form,
            seed: params.seed,
        };
        let senders = Senders {
            surfels: &surfels,
            hierarchy: &hierarchy,
            bvh: &context.bvh,
            epsilon: 4.0 * relight_trace::direct::ray_epsilon_for(&context.bvh),
        };
        let links_per_cache = links_per_cache(params.links as usize, surfels.len());
        let own_caches = shard.range(caches.positions.len());
        let coefficient_count = match form {
            LinkForm::Projected { bands } => bands * bands,
            LinkForm::Runtime => 0,
        };
        progress.start("linking caches", own_caches.len() as u64);
        // SH-projected coefficients go straight into their place as f16 at
        // a power-of-two scale of each cache's own; the merge rescales them
        // in place to the common scale once the largest value of all is
        // known. Holding them all in f32 first doubled the high preset's
        // bake memory.
        let chunk = links_per_cache * coefficient_count;
        let mut coefficients = vec![0u16; own_caches.len() * chunk];
        let coefficient_chunks: Vec<&mut [u16]> = if chunk > 0 {
            coefficients.chunks_mut(chunk).collect()
        } else {
            (0..own_caches.len()).map(|_| Default::default()).collect()
        };
        // Per cache: nodes, (factor, 1 - cos, direction), the scale
        // exponent and largest magnitude of its coefficients, and its links'
        // solid angle over what it can see before any scaling back.
        type CacheLinks = (Vec<u32>, Vec<(f32, f32, Vec3)>, i32, f32, f32);
        let per_cache: Vec<CacheLinks> = coefficient_chunks
            .into_par_iter()
            .zip(own_caches.clone())
            .map(|(stored, cache)| {
                let position = caches.positions[cache];
                let normal = caches.normals[cache];
                let nodes = senders.cut(cache as u64, position, normal, &settings);
                let mut runtime = Vec::new();
                let mut projected = vec![0.0f32; nodes.len() * coefficient_count];
                let mut linked = 0.0f32;
                for (slot, &node) in nodes.iter().enumerate() {
                    linked += match form {
                        LinkForm::Runtime => {
                            let link = senders.runtime_link(
                                cache as u64,
                                position,
                                normal,
                                node,
                                &settings,
                            );
                            runtime.push((link.factor, link.one_minus_cos, link.direction));
                            link.solid_angle
                        }
                        LinkForm::Projected { bands } => senders.projected_link(
                            cache as u64,
                            position,
                            normal,
                            node,
                            bands,
                            &settings,
                            &mut projected
                                [slot * coefficient_count..(slot + 1) * coefficient_count],
                        ),
                    };
                }
                let scale = hemisphere_scale(normal, linked);
                if scale < 1.0 {
                    runtime
                        .iter_mut()
                        .for_each(|(factor, _, _)| *factor *= scale);
                    projected.iter_mut().for_each(|value| *value *= scale);
                }
                let largest = projected.iter().fold(0.0f32, |m, c| m.max(c.abs()));
                let exponent = scale_exponent(largest);
                for (slot, value) in projected.iter().enumerate() {
                    stored[slot] = half::f16::from_f32(value * 2f32.powi(exponent)).to_bits();
                }
                progress.advance(1);
                (
                    nodes,
                    runtime,
                    exponent,
                    largest,
                    linked / visible_solid_angle(normal),
                )
            })
            .collect();
        progress.finish();
        let mut part = PicPart {
            surfels,
            hierarchy,
            cache_atlas_metres,
            caches,
            links_per_cache,
            coefficient_count,
            hierarchy_builder: (params.hierarchy == "kd") as u32,
            enclosed_surfels: enclosed as u32,
            cache_bands: {
                let runtime = params.runtime();
                [runtime.bands as u32, runtime.chroma_bands as u32]
            },
            first_cache: own_caches.start,
            nodes: Vec::with_capacity(per_cache.len()),
            runtime: Vec::with_capacity(per_cache.len()),
            exponents: Vec::with_capacity(per_cache.len()),
            largest: Vec::with_capacity(per_cache.len()),
            coefficients,
        };
        log_overlap(per_cache.iter().map(|cache| cache.4));
        for (nodes, runtime, exponent, largest, _) in per_cache {
            part.nodes.push(nodes);
            part.runtime.push(runtime);
            part.exponents.push(exponent);
            part.largest.push(largest);
        }
        Ok(part)
    }

    pub fn encode(&self) -> Vec<u8> {
        let mut writer = PayloadWriter::with_capacity(self.coefficients.len() * 2 + 1024);
        writer.u32(PART_VERSION);
        write_setup(
            &mut writer,
            &self.surfels,
            &self.hierarchy,
            self.cache_atlas_metres,
            &self.caches,
        );
        for value in [
            self.links_per_cache as u32,
            self.coefficient_count as u32,
            self.hierarchy_builder,
            self.enclosed_surfels,
            self.cache_bands[0],
            self.cache_bands[1],
            self.first_cache as u32,
        ] {
            writer.u32(value);
        }
        let counts: Vec<u32> = self.nodes.iter().map(|nodes| nodes.len() as u32).collect();
        writer.u32s(&counts);
        writer.u32s(&self.nodes.concat());
        let runtime: Vec<&(f32, f32, Vec3)> = self.runtime.iter().flatten().collect();
        writer.f32s(&runtime.iter().map(|link| link.0).collect::<Vec<_>>());
        writer.f32s(&runtime.iter().map(|link| link.1).collect::<Vec<_>>());
        writer.vectors(&runtime.iter().map(|link| link.2).collect::<Vec<_>>());
        let exponents: Vec<u32> = self.exponents.iter().map(|&e| e as u32).collect();
        writer.u32s(&exponents);
        writer.f32s(&self.largest);
        writer.halves(&self.coefficients);
        writer.finish()
    }

    pub fn decode(bytes: &[u8]) -> Result<Self, TechniqueError> {
        let mut reader = PayloadReader::new(bytes, "pic");
        reader.version(
            PART_VERSION,
            "PIC shard",
            "bake the shards with this relight",
        )?;
        let (surfels, hierarchy, cache_atlas_metres, caches) = read_setup(&mut reader)?;
        let mut sizes = [0u32; 7];
        for size in &mut sizes {
            *size = reader.u32()?;
        }
        let [links_per_cache, coefficient_count, hierarchy_builder, enclosed_surfels, luma, chroma, first_cache] =
            sizes;
        let counts = reader.u32s()?;
        let flat_nodes = reader.u32s()?;
        let factors = reader.f32s()?;
        let cones = reader.f32s()?;
        let directions = reader.vectors()?;
        let exponents: Vec<i32> = reader.u32s()?.into_iter().map(|e| e as i32).collect();
        let largest = reader.f32s()?;
        let coefficients = reader.halves()?;
        reader.end()?;
        let own = counts.len();
        if links_per_cache as usize > self::links_per_cache(usize::MAX, surfels.len()) {
            return Err(reader.corrupt("more links per cache than surfels"));
        }
        let links: usize = counts.iter().map(|&count| count as usize).sum();
        let runtime_form = coefficient_count == 0;
        let consistent = flat_nodes.len() == links
            && counts
                .iter()
                .all(|&count| count as usize <= links_per_cache as usize)
            && exponents.len() == own
            && largest.len() == own
            && first_cache as usize + own <= caches.positions.len()
            && coefficients.len() == own * links_per_cache as usize * coefficient_count as usize
            && if runtime_form {
                factors.len() == links && cones.len() == links && directions.len() == links
            } else {
                factors.is_empty() && cones.is_empty() && directions.is_empty()
            };
        if !consistent {
            return Err(reader.corrupt("a shard's links disagree with its sizes"));
        }
        let mut nodes = Vec::with_capacity(own);
        let mut runtime = Vec::with_capacity(own);
        let mut at = 0;
        for &count in &counts {
            let range = at..at + count as usize;
            nodes.push(flat_nodes[range.clone()].to_vec());
            runtime.push(if runtime_form {
                range
                    .clone()
                    .map(|link| (factors[link], cones[link], directions[link]))
                    .collect()
            } else {
                Vec::new()
            });
            at = range.end;
        }
        Ok(Self {
            surfels,
            hierarchy,
            cache_atlas_metres,
            caches,
            links_per_cache: links_per_cache as usize,
            coefficient_count: coefficient_count as usize,
            hierarchy_builder,
            enclosed_surfels,
            cache_bands: [luma, chroma],
            first_cache: first_cache as usize,
            nodes,
            runtime,
            exponents,
            largest,
            coefficients,
        })
    }
}

impl BakePart for PicPart {
    const TECHNIQUE: &'static str = "pic";

    fn is_first(&self) -> bool {
        self.first_cache == 0
    }

    /// The same surfels, hierarchy and caches.
    fn same_setup(&self, other: &Self) -> bool {
        self.surfels == other.surfels
            && self.hierarchy == other.hierarchy
            && self.cache_atlas_metres.to_bits() == other.cache_atlas_metres.to_bits()
            && self.caches == other.caches
            && self.links_per_cache == other.links_per_cache
            && self.coefficient_count == other.coefficient_count
            && self.hierarchy_builder == other.hierarchy_builder
            && self.enclosed_surfels == other.enclosed_surfels
            && self.cache_bands == other.cache_bands
    }

    fn append(&mut self, next: Self) -> Result<(), &'static str> {
        if next.first_cache != self.first_cache + self.nodes.len() {
            return Err("do not follow each other");
        }
        self.nodes.extend(next.nodes);
        self.runtime.extend(next.runtime);
        self.exponents.extend(next.exponents);
        self.largest.extend(next.largest);
        self.coefficients.extend_from_slice(&next.coefficients);
        Ok(())
    }
}

impl PicBake {
    /// Bakes in one piece: the merge of the single shard 0/1.
    pub fn build(
        context: &SceneContext,
        params: &PicParams,
        progress: &dyn Progress,
    ) -> Result<Self, TechniqueError> {
        let part = PicPart::build(context, params, Shard::WHOLE, progress)?;
        Self::from_parts(std::iter::once(Ok(part)))
    }

    /// Joins parts given in shard order and brings every link to one scale.
    pub fn from_parts(
        parts: impl IntoIterator<Item = Result<PicPart, TechniqueError>>,
    ) -> Result<Self, TechniqueError> {
        let PicPart {
            surfels,
            hierarchy,
            cache_atlas_metres,
            caches,
            links_per_cache,
            coefficient_count,
            hierarchy_builder,
            enclosed_surfels,
            cache_bands,
            nodes: per_cache_nodes,
            runtime: per_cache_runtime,
            exponents,
            largest: per_cache_largest,
            coefficients: mut link_coefficients,
            ..
        } = join_parts(parts)?;
        let cache_count = caches.positions.len();
        if per_cache_nodes.len() != cache_count {
            return Err(shards_disagree("pic", "leave caches unlinked"));
        }
        // One power-of-two scale keeps every factor a normal f16.
        let largest = per_cache_runtime
            .iter()
            .zip(&per_cache_largest)
            .flat_map(|(runtime, largest)| {
                runtime
                    .iter()
                    .map(|(factor, _, _)| factor.abs())
                    .chain(std::iter::once(*largest))
            })
            .fold(0.0f32, f32::max);
        let common_exponent = scale_exponent(largest);
        let factor_scale = 2f32.powi(common_exponent);
        let chunk = links_per_cache * coefficient_count;
        if chunk > 0 {
            link_coefficients
                .par_chunks_mut(chunk)
                .zip(&exponents)
                .for_each(|(stored, exponent)| {
                    // The common scale is at most the cache's own.
                    let rescale = 2f32.powi(common_exponent - exponent);
                    for bits in stored {
                        let value = half::f16::from_bits(*bits).to_f32() * rescale;
                        *bits = half::f16::from_f32(value).to_bits();
                    }
                });
        }
        let total = cache_count * links_per_cache;
        let runtime_form = coefficient_count == 0;
        let mut bake = PicBake {
            surfels,
            hierarchy,
            cache_atlas_metres,
            caches,
            links_per_cache,
            projected_bands: coefficient_count.isqrt(),
            link_nodes: vec![0; total],
            link_factors: Vec::new(),
            link_cones: Vec::new(),
            link_directions: Vec::new(),
            link_coefficients,
            factor_scale,
            hierarchy_builder,
            enclosed_surfels,
            cache_bands,
        };
        let half = |value: f32| half::f16::from_f32(value).to_bits();
        if runtime_form {
            bake.link_factors = vec![0; total];
            bake.link_cones = vec![0; total];
            bake.link_directions = vec![[0; 2]; total];
        }
        for (cache, (nodes, runtime)) in per_cache_nodes
            .into_iter()
            .zip(per_cache_runtime)
            .enumerate()
        {
            let base = cache * links_per_cache;
            bake.link_nodes[base..base + nodes.len()].copy_from_slice(&nodes);
            for (slot, (factor, cone, direction)) in runtime.into_iter().enumerate() {
                bake.link_factors[base + slot] = half(factor * factor_scale);
                bake.link_cones[base + slot] = half(cone);
                bake.link_directions[base + slot] = octahedral_encode(direction);
            }
        }
        Ok(bake)
    }

    pub fn cache_count(&self) -> usize {
        self.caches.positions.len()
    }

    /// Run-time projection links: node, factor, cone, direction.
    pub fn link_bytes(&self) -> usize {
        self.link_nodes.len() * 4
            + self.link_factors.len() * 2
            + self.link_cones.len() * 2
            + self.link_directions.len() * 4
            + self.link_coefficients.len() * 2
    }

    pub fn encode(&self) -> Vec<u8> {
        let mut writer = PayloadWriter::with_capacity(self.link_bytes() + self.surfels.len() * 64);
        writer.u32(PAYLOAD_VERSION);
        write_setup(
            &mut writer,
            &self.surfels,
            &self.hierarchy,
            self.cache_atlas_metres,
            &self.caches,
        );
        writer.u32(self.links_per_cache as u32);
        writer.u32(self.projected_bands as u32);
        writer.u32s(&self.link_nodes);
        writer.halves(&self.link_factors);
        writer.halves(&self.link_cones);
        let directions: Vec<u16> = self.link_directions.iter().flatten().copied().collect();
        writer.halves(&directions);
        writer.halves(&self.link_coefficients);
        writer.f32(self.factor_scale);
        writer.u32(self.hierarchy_builder);
        writer.u32(self.enclosed_surfels);
        writer.u32(self.cache_bands[0]);
        writer.u32(self.cache_bands[1]);
        writer.finish()
    }

    pub fn decode(bytes: &[u8]) -> Result<Self, TechniqueError> {
        let mut reader = PayloadReader::new(bytes, "pic");
        reader.version(PAYLOAD_VERSION, "PIC payload", "bake again")?;
        let (surfels, hierarchy, cache_atlas_metres, caches) = read_setup(&mut reader)?;
        let node_count = hierarchy.first_leaf.len();
        let cache_count = caches.positions.len();
        let links_per_cache = reader.u32()? as usize;
        let projected_bands = reader.u32()? as usize;
        let link_nodes = reader.u32s()?;
        let link_factors = reader.halves()?;
        let link_cones = reader.halves()?;
        let link_directions: Vec<[u16; 2]> = reader
            .halves()?
            .chunks_exact(2)
            .map(|pair| [pair[0], pair[1]])
            .collect();
        let link_coefficients = reader.halves()?;
        let factor_scale = reader.finite()?;
        let hierarchy_builder = reader.u32()?;
        let enclosed_surfels = reader.u32()?;
        let cache_bands = [reader.u32()?, reader.u32()?];
        reader.end()?;
        let bands_ok = (2..=relight_core::sh::MAX_BANDS as u32).contains(&cache_bands[0])
            && (2..=cache_bands[0]).contains(&cache_bands[1]);
        if !bands_ok {
            return Err(reader.corrupt("the cache bands are out of range"));
        }
        let total = cache_count * links_per_cache;
        let runtime = projected_bands == 0;
        let links_ok = links_per_cache.is_multiple_of(LINK_ALIGNMENT)
            && projected_bands <= relight_core::sh::MAX_BANDS
            && link_nodes.len() == total
            && link_nodes.iter().all(|&node| (node as usize) < node_count)
            && if runtime {
                link_factors.len() == total
                    && link_cones.len() == total
                    && link_directions.len() == total
            } else {
                link_coefficients.len() == total * projected_bands * projected_bands
            };
        if !links_ok || factor_scale <= 0.0 {
            return Err(reader.corrupt("the links are inconsistent"));
        }
        Ok(PicBake {
            surfels,
            hierarchy,
            cache_atlas_metres,
            caches,
            links_per_cache,
            projected_bands,
            link_nodes,
            link_factors,
            link_cones,
            link_directions,
            link_coefficients,
            factor_scale,
            hierarchy_builder,
            enclosed_surfels,
            cache_bands,
        })
    }
}

/// The surfels, their hierarchy and the caches: what every shard of a bake
/// computes alike, written as the bake's payload begins.
fn write_setup(
    writer: &mut PayloadWriter,
    surfels: &Surfels,
    hierarchy: &Hierarchy,
    cache_atlas_metres: f32,
    caches: &CachePlacement,
) {
    writer.f32(surfels.area);
    writer.vectors(&surfels.positions);
    writer.vectors(&surfels.normals);
    writer.u32s(&surfels.triangles);
    let barycentrics: Vec<f32> = surfels
        .barycentrics
        .iter()
        .flat_map(|b| b.to_array())
        .collect();
    writer.f32s(&barycentrics);
    writer.vectors(&surfels.albedos);
    writer.vectors(&surfels.emission);
    writer.u32(hierarchy.leaf_count);
    let children: Vec<u32> = hierarchy.children.iter().flatten().copied().collect();
    writer.u32s(&children);
    writer.u32s(&hierarchy.first_leaf);
    writer.u32s(&hierarchy.leaves);
    writer.f32(cache_atlas_metres);
    writer.vectors(&caches.positions);
    writer.vectors(&caches.normals);
    writer.u32(caches.lightmap_count as u32);
    for dim in caches.grid.dims {
        writer.u32(dim);
    }
    writer.vectors(&[caches.grid.origin, caches.grid.step]);
    writer.u32s(&caches.grid_cache);
    for count in [
        caches.moved,
        caches.stuck,
        caches.grid_moved,
        caches.grid_culled,
    ] {
        writer.u32(count as u32);
    }
}

/// Reads what [`write_setup`] wrote.
fn read_setup(
    reader: &mut PayloadReader,
) -> Result<(Surfels, Hierarchy, f32, CachePlacement), TechniqueError> {
    let area = reader.finite()?;
    let positions = reader.vectors()?;
    let normals = reader.vectors()?;
    let triangles = reader.u32s()?;
    let barycentrics: Vec<Vec2> = reader
        .f32s()?
        .chunks_exact(2)
        .map(|pair| Vec2::new(pair[0], pair[1]))
        .collect();
    let albedos = reader.vectors()?;
    let emission = reader.vectors()?;
    let n = positions.len();
    if [
        normals.len(),
        triangles.len(),
        barycentrics.len(),
        albedos.len(),
        emission.len(),
    ]
    .iter()
    .any(|&len| len != n)
    {
        return Err(reader.corrupt("surfel arrays differ in length"));
    }
    let surfels = Surfels {
        positions,
        normals,
        triangles,
        barycentrics,
        albedos,
        emission,
        area,
    };
    let leaf_count = reader.u32()?;
    let children: Vec<[u32; 2]> = reader
        .u32s()?
        .chunks_exact(2)
        .map(|pair| [pair[0], pair[1]])
        .collect();
    let first_leaf = reader.u32s()?;
    let leaves = reader.u32s()?;
    let node_count = first_leaf.len();
    let hierarchy_ok = leaf_count as usize == n
        && leaves.len() == node_count
        && node_count == (2 * n).saturating_sub(1)
        && children.len() + n == node_count
        && children
            .iter()
            .enumerate()
            .all(|(k, pair)| pair.iter().all(|&child| (child as usize) < n + k))
        && first_leaf
            .iter()
            .zip(&leaves)
            .all(|(&first, &count)| count >= 1 && first as usize + count as usize <= n);
    if !hierarchy_ok {
        return Err(reader.corrupt("the surfel hierarchy is inconsistent"));
    }
    let hierarchy = Hierarchy {
        leaf_count,
        children,
        first_leaf,
        leaves,
    };
    let cache_atlas_metres = reader.finite()?;
    let cache_positions = reader.vectors()?;
    let cache_normals = reader.vectors()?;
    let lightmap_count = reader.u32()? as usize;
    let dims = [reader.u32()?, reader.u32()?, reader.u32()?];
    let grid_vectors = reader.vectors()?;
    let grid_cache = reader.u32s()?;
    let counts = [reader.u32()?, reader.u32()?, reader.u32()?, reader.u32()?];
    let cache_count = cache_positions.len();
    let grid_points = dims.iter().map(|&d| d as u64).product::<u64>();
    if cache_normals.len() != cache_count
        || lightmap_count > cache_count
        || grid_vectors.len() != 2
        || grid_points != grid_cache.len() as u64
        || grid_cache
            .iter()
            .any(|&cache| cache != u32::MAX && cache as usize >= cache_count)
    {
        return Err(reader.corrupt("the cache placement is inconsistent"));
    }
    let caches = CachePlacement {
        positions: cache_positions,
        normals: cache_normals,
        lightmap_count,
        grid: GridLayout {
            dims,
            origin: grid_vectors[0],
            step: grid_vectors[1],
        },
        grid_cache,
        moved: counts[0] as usize,
        stuck: counts[1] as usize,
        grid_moved: counts[2] as usize,
        grid_culled: counts[3] as usize,
    };
    Ok((surfels, hierarchy, cache_atlas_metres, caches))
}

/// Says (at `RELIGHT_LOG=info`) how far the caches' links sum past what
/// each can see, before scaling back: what [`OVERLAP_ALLOWANCE`] is set
/// against, and how many caches it catches.
fn log_overlap(ratios: impl Iterator<Item = f32>) {
    let mut ratios: Vec<f32> = ratios.collect();
    if ratios.is_empty() {
        return;
    }
    ratios.sort_unstable_by(f32::total_cmp);
    let at = |share: f64| ratios[((ratios.len() - 1) as f64 * share) as usize];
    let scaled = ratios.iter().filter(|&&r| r > OVERLAP_ALLOWANCE).count();
    tracing::info!(
        "pic links: {} caches' solid angle over what each sees: {:.2} at the 99th percentile, {:.2} at the 99.9th, {:.2} at most; {scaled} over {OVERLAP_ALLOWANCE} scaled back to 1",
        ratios.len(),
        at(0.99),
        at(0.999),
        ratios[ratios.len() - 1],
    );
}

/// Occlusion rays per link, over `link_samples + node_samples`: a link's
/// own samples, and the node estimates of the cut that chose it (a cut
/// looks at two children per link, most with `node_samples` rays, some
/// with up to four times as many) less the links a cache that sees little
/// never fills. Measured on Sponza, the living room and the atrium at the
/// defaults: 0.87-0.97 of the sum, more than the 0.76-0.82 of a cut by
/// solid angle alone, since partly hidden nodes, refined first, take more
/// looks before they are seen (the Cornell box, whose caches see nearly
/// every node: 1.17).
const RAYS_PER_LINK_SAMPLE: f64 = 0.95;

/// Bytes per scene triangle the cache atlas's trial builds hold, from the
/// peaks above.
const CACHE_ATLAS_BYTES_PER_TRIANGLE: u64 = 120;

/// Forecasts the bake of `shard` from the parameters: its rays are the
/// caches' links (the lightmap caches wanted plus the grid cells), its
/// fixed time the surfels' clustering, and its peak the links held while
/// they are made and then encoded.
pub fn estimate(context: &SceneContext, params: &PicParams, shard: Shard) -> BakeEstimate {
    let receivers = context.atlas.receivers.len() as u64;
    let lightmap_caches = if params.lightmap_caches == 0 {
        receivers
    } else {
        (params.lightmap_caches as u64).min(receivers)
    };
    let grid_cells = if params.grid.iter().all(|&d| d > 0) {
        params.grid.iter().map(|&d| d as u64).product()
    } else {
        params.grid_cells as u64
    };
    let caches = lightmap_caches + grid_cells;
    let own_caches = shard.range(caches as usize).len() as u64;
    let links = links_per_cache(params.links as usize, params.surfels as usize) as u64;
    let occlusion = own_caches as f64
        * params.links.min(params.surfels) as f64
        * (params.link_samples + params.node_samples) as f64
        * RAYS_PER_LINK_SAMPLE;
    let coefficients = if params.projected {
        (params.bands * params.bands) as u64
    } else {
        0
    };
    // Per link: its node (4 bytes), its runtime factor, cone and direction
    // (20) or its f16 coefficients, held while baking and again encoded.
    let link_bytes = if params.projected {
        4 + 2 * coefficients
    } else {
        4 + 20
    };
    let links_held = 2 * own_caches * links * link_bytes;
    // Surfels (position, normal, albedo, area, ...) and two hierarchy nodes
    // each, with the clustering's neighbour lists.
    let surfels_held = params.surfels as u64 * 400;
    // A scene lightmap finer than the caches wanted gets a coarser atlas of
    // its own, found by trial builds over every triangle, two alive at a
    // time: the 1M-triangle atrium's bake peaks 161 MiB above its links and
    // surfels, the 300k one's 18 MiB, Sponza's (66k) 5 MiB.
    let cache_atlas = if params.lightmap_caches > 0 && receivers > lightmap_caches {
        context.scene.mesh.triangles.len() as u64 * CACHE_ATLAS_BYTES_PER_TRIANGLE
    } else {
        0
    };
    // The agglomerative clustering's time grows as n^1.5 on these scenes
    // (Sponza, 2 threads: 0.4 s at 32k surfels, 3.1 s at 128k), placement
    // and surfels about as much again at 32k.
    let surfels_over_default = params.surfels as f64 / 32768.0;
    let threads = rayon::current_num_threads() as f64;
    let fixed_seconds = 2.0 * 0.8 * surfels_over_default.powf(1.5) / threads;
    BakeEstimate {
        rays: relight_trace::counters::RayCount {
            closest_hit: 0,
            occlusion: occlusion as u64,
        },
        time_per_ray_time: 1.6,
        occlusion_rate: None,
        fixed_seconds,
        peak: vec![
            (format!("links ({own_caches} caches x {links})"), links_held),
            (format!("surfels ({})", params.surfels), surfels_held),
            ("cache atlas".into(), cache_atlas),
        ],
        lower_memory_with: "--set links=N, --set lightmap_caches=N, --set grid_cells=N, or --shard I/N on several machines".into(),
    }
}
