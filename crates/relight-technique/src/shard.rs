//! Sharded bakes: one bake's work split into `count` parts that separate
//! processes or machines bake alone and `relight merge` joins.
//!
//! A technique that shards divides the work whose cost grows with the scene
//! (PRM's panes, SRP's receiver clusters, PIC's caches) into contiguous
//! index ranges ([`Shard::range`]) and recomputes the cheap set-up every
//! shard needs (entry points, probes, the surfel hierarchy) in each. Each
//! work item draws its random numbers from its own index, never from the
//! range it was baked in, and the whole bake is the merge of the single
//! shard `0/1`, so a merge of any number of shards gives the same bytes as
//! a bake in one piece.

use crate::{read_bake, BakeHeader, TechniqueError, TechniqueKind};
use std::fmt;
use std::ops::Range;
use std::path::{Path, PathBuf};

/// Part `index` (from 0) of `count` equal parts of a bake's work.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub struct Shard {
    pub index: u32,
    pub count: u32,
}

impl Shard {
    /// The whole bake as one part.
    pub const WHOLE: Shard = Shard { index: 0, count: 1 };

    pub fn new(index: u32, count: u32) -> Result<Self, String> {
        if count == 0 {
            return Err("a bake has at least one shard: give --shard I/N with N >= 1".into());
        }
        if index >= count {
            return Err(format!(
                "shard {index}/{count} does not exist: shards count from 0, so {count} shards are 0/{count} to {}/{count} \
                 (Slurm's SLURM_ARRAY_TASK_ID with --array=0-{}, Kubernetes' JOB_COMPLETION_INDEX)",
                count - 1,
                count - 1
            ));
        }
        Ok(Self { index, count })
    }

    /// This shard's part of `total` work items: contiguous, the parts of
    /// all shards in index order covering `0..total` exactly once, their
    /// sizes differing by at most one.
    pub fn range(self, total: usize) -> Range<usize> {
        let part = |index: u32| (total as u128 * index as u128 / self.count as u128) as usize;
        part(self.index)..part(self.index + 1)
    }

    /// This shard's part of work items of the given costs: contiguous, in
    /// index order over all shards, each part ending at the first item
    /// whose running cost reaches its share of the total.
    pub fn weighted_range(self, costs: &[u64]) -> Range<usize> {
        let total: u128 = costs.iter().map(|&cost| cost as u128).sum();
        if total == 0 {
            return self.range(costs.len());
        }
        let boundary = |index: u32| -> usize {
            if index == 0 {
                return 0;
            }
            if index == self.count {
                return costs.len();
            }
            let share = total * index as u128 / self.count as u128;
            let mut running = 0u128;
            costs
                .iter()
                .position(|&cost| {
                    running += cost as u128;
                    running >= share
                })
                .map_or(costs.len(), |last| last + 1)
        };
        boundary(self.index)..boundary(self.index + 1)
    }
}

impl fmt::Display for Shard {
    fn fmt(&self, formatter: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(formatter, "{}/{}", self.index, self.count)
    }
}

impl std::str::FromStr for Shard {
    type Err = String;

    fn from_str(text: &str) -> Result<Self, String> {
        let malformed = || {
            format!(
                "shard '{text}' is not INDEX/COUNT: give e.g. --shard 0/4 for the first of four"
            )
        };
        let (index, count) = text.split_once('/').ok_or_else(malformed)?;
        let index = index.trim().parse().map_err(|_| malformed())?;
        let count = count.trim().parse().map_err(|_| malformed())?;
        Shard::new(index, count)
    }
}

/// One shard's part of a technique's bake, which the merge joins to the
/// parts of the shards after it.
pub trait BakePart: Sized {
    /// The technique's name, for errors.
    const TECHNIQUE: &'static str;
    /// Whether the part holds the first work items (shard 0's).
    fn is_first(&self) -> bool;
    /// Whether `other` was baked from the same set-up (the work every
    /// shard repeats), so that their parts belong to one bake.
    fn same_setup(&self, other: &Self) -> bool;
    /// Appends `next`, which must hold the work items right after this
    /// part's; says what is wrong otherwise.
    fn append(&mut self, next: Self) -> Result<(), &'static str>;
}

/// The error for shards that do not form one bake.
pub fn shards_disagree(technique: &str, message: &str) -> TechniqueError {
    TechniqueError::Other(format!(
        "{} shards {message}: bake every shard with the same relight, scene and parameters",
        technique.to_uppercase()
    ))
}

/// Joins parts given in shard order into one, which holds every work item
/// when no shard is missing.
pub fn join_parts<P: BakePart>(
    parts: impl IntoIterator<Item = Result<P, TechniqueError>>,
) -> Result<P, TechniqueError> {
    let disagree = |message: &str| shards_disagree(P::TECHNIQUE, message);
    let mut parts = parts.into_iter();
    let mut joined = parts.next().ok_or_else(|| disagree("are missing"))??;
    if !joined.is_first() {
        return Err(disagree("do not start with the first shard"));
    }
    for part in parts {
        let part = part?;
        if !part.same_setup(&joined) {
            return Err(disagree("disagree on the set-up every shard repeats"));
        }
        joined.append(part).map_err(disagree)?;
    }
    Ok(joined)
}

/// FNV-1a over the bake parameters in effect (the scene file's technique
/// section, then `params`, the later of a repeated key winning), restricted
/// to the kind's [`TechniqueKind::bake_parameters`] and sorted by key: two
/// bakes with the same fingerprint were asked for the same bake. Values
/// are compared as written (`1024` and `1024.0` differ), which can only
/// make a merge refuse shards, never join different ones.
pub fn parameters_fingerprint(
    kind: &dyn TechniqueKind,
    scene: &relight_scene::Scene,
    params: &[(String, String)],
) -> u64 {
    let baked = kind.bake_parameters();
    let mut in_effect: Vec<(String, String)> = Vec::new();
    for (key, value) in crate::with_scene_section(scene, kind.name(), params) {
        if !baked.is_empty() && !baked.contains(&key.as_str()) {
            continue;
        }
        in_effect.retain(|(existing, _)| *existing != key);
        in_effect.push((key, value));
    }
    in_effect.sort();
    let mut hash = 0xcbf2_9ce4_8422_2325u64;
    for (key, value) in &in_effect {
        for byte in key
            .bytes()
            .chain([b'='])
            .chain(value.bytes())
            .chain([b'\n'])
        {
            hash ^= byte as u64;
            hash = hash.wrapping_mul(0x0100_0000_01b3);
        }
    }
    hash
}

/// A complete set of shards read from files, in shard order.
pub struct ShardSet {
    /// The header the merged bake carries (the shards' less the shard).
    pub header: BakeHeader,
    /// Each shard's payload, shard 0 first.
    pub payloads: Vec<Vec<u8>>,
}

/// Reads the shard files `paths` (any order) and checks that they are all
/// the shards of one bake: the same technique, payload version, scene,
/// bake parameters and shard count, each index once, none missing.
pub fn read_shard_set(paths: &[PathBuf]) -> Result<ShardSet, TechniqueError> {
    let refuse = |path: &Path, message: String| TechniqueError::BakeFile {
        path: path.to_path_buf(),
        message,
    };
    let first_path = paths.first().ok_or_else(|| {
        TechniqueError::Other(
            "relight merge needs the shard files to join: relight merge part-*.bake -o scene.bake"
                .into(),
        )
    })?;
    let mut slots: Vec<Option<(PathBuf, Vec<u8>)>> = Vec::new();
    let mut expected: Option<BakeHeader> = None;
    for path in paths {
        let (header, payload) = read_bake(path)?;
        let shard = header.shard.ok_or_else(|| {
            refuse(
                path,
                "is a whole bake, not a shard: merge only files written by `relight bake --shard I/N`"
                    .into(),
            )
        })?;
        let expected = expected.get_or_insert_with(|| header.clone());
        let first = expected.shard.expect("the first file is a shard");
        let differs = if header.technique != expected.technique {
            Some(format!(
                "is a shard of a {} bake, {} of {}",
                header.technique,
                first_path.display(),
                expected.technique
            ))
        } else if header.payload_version != expected.payload_version {
            Some(format!(
                "was baked by another relight version than {} (payload version {} against {})",
                first_path.display(),
                header.payload_version,
                expected.payload_version
            ))
        } else if header.scene_fingerprint != expected.scene_fingerprint {
            Some(format!(
                "was baked for another scene or lightmap than {}",
                first_path.display()
            ))
        } else if header.parameters_fingerprint != expected.parameters_fingerprint {
            Some(format!(
                "was baked with other bake parameters (--set, --preset or the scene's [{}] section) than {}",
                header.technique,
                first_path.display()
            ))
        } else if shard.count != first.count {
            Some(format!(
                "is shard {shard} of {} shards, {} one of {}",
                shard.count,
                first_path.display(),
                first.count
            ))
        } else {
            None
        };
        if let Some(message) = differs {
            return Err(refuse(
                path,
                format!("{message}: bake all shards with the same command"),
            ));
        }
        slots.resize_with(first.count as usize, || None);
        let slot = &mut slots[shard.index as usize];
        if let Some((other, _)) = slot {
            return Err(refuse(
                path,
                format!(
                    "holds shard {shard}, as {} does: give each shard once",
                    other.display()
                ),
            ));
        }
        *slot = Some((path.clone(), payload));
    }
    let missing: Vec<String> = slots
        .iter()
        .enumerate()
        .filter(|(_, slot)| slot.is_none())
        .map(|(index, _)| index.to_string())
        .collect();
    let mut header = expected.expect("at least one file was read");
    let count = header.shard.expect("shard").count;
    if !missing.is_empty() {
        return Err(TechniqueError::Other(format!(
            "shards {} of {count} are missing: bake each with `relight bake SCENE --technique {} --shard I/{count} -o FILE` and merge again",
            missing.join(", "),
            header.technique
        )));
    }
    header.shard = None;
    Ok(ShardSet {
        header,
        payloads: slots
            .into_iter()
            .map(|slot| slot.expect("no shard is missing").1)
            .collect(),
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn ranges_cover_the_work_once_in_order() {
        for total in [0usize, 1, 3, 7, 256, 1001] {
            for count in 1..=9u32 {
                let mut next = 0;
                for index in 0..count {
                    let range = Shard { index, count }.range(total);
                    assert_eq!(range.start, next, "{index}/{count} of {total}");
                    let size = range.len();
                    assert!(
                        size == total / count as usize || size == total.div_ceil(count as usize)
                    );
                    next = range.end;
                }
                assert_eq!(next, total);
            }
        }
    }

    fn write_shard(folder: &Path, name: &str, shard: Option<Shard>, parameters: u64) -> PathBuf {
        let path = folder.join(name);
        let header = BakeHeader {
            technique: "prm".into(),
            payload_version: 1,
            scene_fingerprint: 7,
            parameters_fingerprint: parameters,
            shard,
        };
        let payload = name.as_bytes().to_vec();
        crate::write_bake_atomic(&path, &header, &payload).unwrap();
        path
    }

    #[test]
    fn a_shard_set_is_complete_and_of_one_bake() {
        let folder = tempfile::tempdir().unwrap();
        let folder = folder.path();
        let shard = |index| Some(Shard { index, count: 3 });
        let parts: Vec<PathBuf> = (0..3)
            .map(|index| write_shard(folder, &format!("part-{index}"), shard(index), 1))
            .collect();
        // Any order; payloads come back in shard order, the header whole.
        let set = read_shard_set(&[parts[2].clone(), parts[0].clone(), parts[1].clone()]).unwrap();
        assert_eq!(set.header.shard, None);
        assert_eq!(
            set.payloads,
            vec![b"part-0".to_vec(), b"part-1".to_vec(), b"part-2".to_vec()]
        );

        let error = |paths: &[PathBuf]| read_shard_set(paths).err().unwrap().to_string();
        let missing = error(&[parts[1].clone()]);
        assert!(
            missing.contains("shards 0, 2 of 3 are missing"),
            "{missing}"
        );
        let twice = error(&[parts[0].clone(), parts[0].clone()]);
        assert!(twice.contains("give each shard once"), "{twice}");
        let other = write_shard(folder, "other", shard(1), 2);
        let mixed = error(&[parts[0].clone(), other]);
        assert!(
            mixed.contains("other: was baked with other bake parameters"),
            "{mixed}"
        );
        let whole = write_shard(folder, "whole", None, 1);
        assert!(error(&[whole]).contains("is a whole bake"));
        let fewer = write_shard(folder, "fewer", Some(Shard { index: 1, count: 2 }), 1);
        assert!(error(&[parts[0].clone(), fewer]).contains("of 2 shards"));
        assert!(read_shard_set(&[]).is_err());
    }

    #[test]
    fn weighted_ranges_cover_the_work_once_and_balance_its_cost() {
        let costs: Vec<u64> = (0..100u64)
            .map(|item| 1 + (item % 7) * (item % 3) * 10)
            .collect();
        let total: u64 = costs.iter().sum();
        for count in 1..=6u32 {
            let mut next = 0;
            for index in 0..count {
                let range = Shard { index, count }.weighted_range(&costs);
                assert_eq!(range.start, next, "{index}/{count}");
                let cost: u64 = costs[range.clone()].iter().sum();
                // A part overshoots its share by at most one item.
                let largest = *costs.iter().max().unwrap();
                assert!(
                    cost <= total.div_ceil(count as u64) + largest,
                    "{index}/{count}: {cost} of {total}"
                );
                next = range.end;
            }
            assert_eq!(next, costs.len());
        }
        assert_eq!(
            Shard { index: 1, count: 2 }.weighted_range(&[0, 0, 0, 0]),
            2..4
        );
        assert_eq!(Shard::WHOLE.weighted_range(&[]), 0..0);
    }

    #[test]
    fn parses_index_over_count() {
        assert_eq!("2/4".parse::<Shard>(), Ok(Shard { index: 2, count: 4 }));
        assert!("4/4".parse::<Shard>().unwrap_err().contains("0/4 to 3/4"));
        assert!("1/0".parse::<Shard>().is_err());
        assert!("two/4"
            .parse::<Shard>()
            .unwrap_err()
            .contains("INDEX/COUNT"));
        assert!("3".parse::<Shard>().is_err());
    }
}
