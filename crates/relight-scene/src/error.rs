//! The one error type of relight-scene. Every variant carries the file it is
//! about (and, for text formats, the line), because the reader of the message
//! is a person fixing a scene, not code.

use std::path::PathBuf;

/// Everything a user's files can get wrong. Each variant names the file and,
/// for text formats, the line, and says what to do.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum SceneError {
    // The operating system's message is part of this one, not a source
    // as well: a caller printing the chain would show it twice.
    #[error("{path}: cannot read: {error}")]
    Io {
        path: PathBuf,
        error: std::io::Error,
    },
    #[error("{path}: cannot write: {error}")]
    Write {
        path: PathBuf,
        error: std::io::Error,
    },
    #[error("{path}:{line}: {message}")]
    Syntax {
        path: PathBuf,
        line: usize,
        message: String,
    },
    #[error("{path}: {message}")]
    Invalid { path: PathBuf, message: String },
    #[error("{path}: unsupported mesh format '{extension}': use .obj, .gltf or .glb")]
    UnsupportedFormat { path: PathBuf, extension: String },
    #[error("{path}: the scene has no triangles after dropping degenerate ones")]
    Empty { path: PathBuf },
    /// A caller-supplied parameter (not a file) is out of range, e.g. a
    /// triangle budget for the procedural generators.
    #[error("{message}")]
    InvalidArgument { message: String },
}
