//! The bake file container shared by every technique: a magic number, a
//! format version, the technique and its payload version, fingerprints of
//! the scene and the bake parameters it was baked for, which shard of a
//! sharded bake it holds (none for a whole bake), the payload, and a CRC-32
//! over all of it.
//!
//! Files are written to a temporary sibling and renamed into place, so an
//! interrupted bake never destroys a good one.

use crate::{Shard, TechniqueError};
use relight_scene::atlas::Atlas;
use relight_scene::Scene;
use std::io::Write;
use std::path::{Path, PathBuf};

pub const BAKE_MAGIC: [u8; 8] = *b"RELIGHT\x1a";
/// 2 added the parameters' fingerprint and the shard.
pub const BAKE_FORMAT_VERSION: u32 = 2;

/// What a bake file says about itself.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct BakeHeader {
    pub technique: String,
    pub payload_version: u32,
    pub scene_fingerprint: u64,
    /// [`crate::parameters_fingerprint`] of the bake parameters: shards of
    /// one bake must agree on it.
    pub parameters_fingerprint: u64,
    /// Which part of a sharded bake the payload holds; `None` for a whole
    /// bake, which is what techniques load.
    pub shard: Option<Shard>,
}

/// FNV-1a over the geometry, materials, atlas layout and receiver
/// positions: a bake is only valid for the scene (and lightmap) it was made
/// for, and bakes that store per-receiver data depend on where receivers
/// stand (relocation may move them without changing the layout).
pub fn scene_fingerprint(scene: &Scene, atlas: &Atlas) -> u64 {
    let mut hash = 0xcbf2_9ce4_8422_2325u64;
    let mut feed = |bytes: &[u8]| {
        for byte in bytes {
            hash ^= *byte as u64;
            hash = hash.wrapping_mul(0x0100_0000_01b3);
        }
    };
    for position in &scene.mesh.positions {
        for value in position.to_array() {
            feed(&value.to_le_bytes());
        }
    }
    for triangle in &scene.mesh.triangles {
        for index in triangle {
            feed(&index.to_le_bytes());
        }
    }
    for id in &scene.mesh.material_ids {
        feed(&id.to_le_bytes());
    }
    for material in &scene.materials {
        for value in material
            .albedo
            .to_array()
            .into_iter()
            .chain(material.emission.to_array())
        {
            feed(&value.to_le_bytes());
        }
    }
    feed(&atlas.width.to_le_bytes());
    feed(&atlas.height.to_le_bytes());
    feed(&(atlas.receivers.len() as u64).to_le_bytes());
    for position in &atlas.receivers.positions {
        for value in position.to_array() {
            feed(&value.to_le_bytes());
        }
    }
    hash
}

fn encode(header: &BakeHeader, payload: &[u8]) -> Vec<u8> {
    let mut bytes = Vec::with_capacity(payload.len() + 64);
    bytes.extend_from_slice(&BAKE_MAGIC);
    bytes.extend_from_slice(&BAKE_FORMAT_VERSION.to_le_bytes());
    bytes.extend_from_slice(&(header.technique.len() as u16).to_le_bytes());
    bytes.extend_from_slice(header.technique.as_bytes());
    bytes.extend_from_slice(&header.payload_version.to_le_bytes());
    bytes.extend_from_slice(&header.scene_fingerprint.to_le_bytes());
    bytes.extend_from_slice(&header.parameters_fingerprint.to_le_bytes());
    let (index, count) = header
        .shard
        .map_or((0, 0), |shard| (shard.index, shard.count));
    bytes.extend_from_slice(&index.to_le_bytes());
    bytes.extend_from_slice(&count.to_le_bytes());
    bytes.extend_from_slice(&(payload.len() as u64).to_le_bytes());
    bytes.extend_from_slice(payload);
    let checksum = crc32fast::hash(&bytes);
    bytes.extend_from_slice(&checksum.to_le_bytes());
    bytes
}

/// Writes a bake file atomically: temporary sibling, fsync, rename.
pub fn write_bake_atomic(
    path: &Path,
    header: &BakeHeader,
    payload: &[u8],
) -> Result<(), TechniqueError> {
    let io_error = |error| TechniqueError::Io {
        path: path.to_path_buf(),
        error,
    };
    let file_name = path.file_name().ok_or_else(|| TechniqueError::BakeFile {
        path: path.to_path_buf(),
        message: "the output path names no file: give a file name such as scene.bake".into(),
    })?;
    let mut temporary_name = file_name.to_os_string();
    temporary_name.push(format!(".{}.tmp", std::process::id()));
    let temporary = path.with_file_name(temporary_name);
    let result = (|| {
        let mut file = std::fs::File::create(&temporary)?;
        file.write_all(&encode(header, payload))?;
        file.sync_all()?;
        std::fs::rename(&temporary, path)
    })();
    if result.is_err() {
        let _ = std::fs::remove_file(&temporary);
    }
    result.map_err(io_error)
}

/// Reads and verifies a bake file; returns its header and payload.
pub fn read_bake(path: &Path) -> Result<(BakeHeader, Vec<u8>), TechniqueError> {
    let bytes = std::fs::read(path).map_err(|error| TechniqueError::Io {
        path: path.to_path_buf(),
        error,
    })?;
    decode(path, &bytes)
}

fn decode(path: &Path, bytes: &[u8]) -> Result<(BakeHeader, Vec<u8>), TechniqueError> {
    let invalid = |message: &str| TechniqueError::BakeFile {
        path: PathBuf::from(path),
        message: format!("{message}; bake it again with `relight bake`"),
    };
    if bytes.len() < BAKE_MAGIC.len() + 4 || bytes[..8] != BAKE_MAGIC {
        return Err(invalid("not a relight bake file (wrong magic number)"));
    }
    if bytes.len() < 8 + 4 + 2 + 4 {
        return Err(invalid("truncated bake file"));
    }
    let (body, checksum_bytes) = bytes.split_at(bytes.len() - 4);
    let stored = u32::from_le_bytes(checksum_bytes.try_into().expect("4 bytes"));
    if crc32fast::hash(body) != stored {
        return Err(invalid(
            "checksum mismatch: the file is corrupt or was cut short",
        ));
    }
    let mut cursor = 8usize;
    let mut take = |count: usize| -> Result<&[u8], TechniqueError> {
        let slice = body
            .get(cursor..cursor + count)
            .ok_or_else(|| invalid("truncated bake file"))?;
        cursor += count;
        Ok(slice)
    };
    let format = u32::from_le_bytes(take(4)?.try_into().expect("4 bytes"));
    if format != BAKE_FORMAT_VERSION {
        return Err(invalid(&format!(
            "bake format version {format}, this relight reads {BAKE_FORMAT_VERSION}"
        )));
    }
    let name_length = u16::from_le_bytes(take(2)?.try_into().expect("2 bytes")) as usize;
    let technique = String::from_utf8(take(name_length)?.to_vec())
        .map_err(|_| invalid("technique name is not UTF-8"))?;
    let payload_version = u32::from_le_bytes(take(4)?.try_into().expect("4 bytes"));
    let scene_fingerprint = u64::from_le_bytes(take(8)?.try_into().expect("8 bytes"));
    let parameters_fingerprint = u64::from_le_bytes(take(8)?.try_into().expect("8 bytes"));
    let index = u32::from_le_bytes(take(4)?.try_into().expect("4 bytes"));
    let count = u32::from_le_bytes(take(4)?.try_into().expect("4 bytes"));
    let shard = match count {
        0 if index == 0 => None,
        _ => Some(Shard::new(index, count).map_err(|message| invalid(&message))?),
    };
    let payload_length = u64::from_le_bytes(take(8)?.try_into().expect("8 bytes"));
    let payload_length =
        usize::try_from(payload_length).map_err(|_| invalid("payload length too large"))?;
    let payload = take(payload_length)?.to_vec();
    Ok((
        BakeHeader {
            technique,
            payload_version,
            scene_fingerprint,
            parameters_fingerprint,
            shard,
        },
        payload,
    ))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn header() -> BakeHeader {
        BakeHeader {
            technique: "pic".into(),
            payload_version: 3,
            scene_fingerprint: 0xDEAD_BEEF,
            parameters_fingerprint: 0x1234,
            shard: Some(Shard { index: 2, count: 4 }),
        }
    }

    #[test]
    fn round_trip_and_corruption_detected() {
        let folder = tempfile::tempdir().unwrap();
        let path = folder.path().join("scene.bake");
        let payload: Vec<u8> = (0..1000u32).map(|i| (i * 7) as u8).collect();
        write_bake_atomic(&path, &header(), &payload).unwrap();
        let (read_header, read_payload) = read_bake(&path).unwrap();
        assert_eq!(read_header, header());
        assert_eq!(read_payload, payload);
        // No temporary file is left behind.
        assert_eq!(std::fs::read_dir(folder.path()).unwrap().count(), 1);

        let mut bytes = std::fs::read(&path).unwrap();
        bytes[40] ^= 0x10;
        std::fs::write(&path, &bytes).unwrap();
        let error = read_bake(&path).unwrap_err().to_string();
        assert!(error.contains("checksum"), "{error}");

        std::fs::write(&path, &bytes[..bytes.len() / 2]).unwrap();
        assert!(read_bake(&path).is_err());
        std::fs::write(&path, b"not a bake").unwrap();
        assert!(read_bake(&path).unwrap_err().to_string().contains("magic"));
    }

    #[test]
    fn failed_write_keeps_the_old_file() {
        let folder = tempfile::tempdir().unwrap();
        let path = folder.path().join("good.bake");
        write_bake_atomic(&path, &header(), b"good").unwrap();
        // Writing into a missing folder fails before touching the good file.
        let bad = folder.path().join("missing").join("good.bake");
        assert!(write_bake_atomic(&bad, &header(), b"bad").is_err());
        assert_eq!(read_bake(&path).unwrap().1, b"good");
    }
}
