//! The technique interface: what every GI technique offers the renderer,
//! the benchmark and the comparison.

use crate::SceneContext;
use glam::{Vec2, Vec3};
use relight_core::Rgb;
use relight_scene::Light;
use std::path::PathBuf;
use std::sync::Arc;
use std::time::Duration;

/// A point on the static geometry, as the renderer finds it.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct SurfacePoint {
    pub position: Vec3,
    /// Geometric normal of the front face of `triangle`.
    pub normal: Vec3,
    pub triangle: u32,
    /// (b1, b2) of `position` on `triangle`.
    pub barycentric: Vec2,
}

/// The lights of one frame, and the viewer.
#[derive(Clone, Copy, Debug)]
pub struct Frame<'a> {
    pub lights: &'a [Light],
    pub index: u64,
    /// The camera this frame is seen from, for view-dependent (glossy)
    /// indirect light; `None`: the scene file's camera.
    pub camera: Option<&'a relight_scene::Camera>,
    /// Where the scene's moving meshes are this frame (mesh space to world,
    /// in the scene file's `[[dynamic]]` order) when the application moves
    /// them; `None`: each follows the motion its scene file scripts for
    /// frame `index`. Techniques of static scenes ignore it.
    pub moving_mesh_poses: Option<&'a [glam::Affine3A]>,
}

/// Wall-clock time of each stage of the last update, in pipeline order.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct StageTimings {
    pub stages: Vec<(&'static str, Duration)>,
    /// Feedback passes the update ran (each adds a bounce); 0 for a
    /// technique without feedback.
    pub feedback_passes: u32,
    /// The update found its frame repeating the last one and its light
    /// settled, so it did nothing (its one stage times the check).
    pub skipped: bool,
}

impl StageTimings {
    pub fn clear(&mut self) {
        self.stages.clear();
        self.feedback_passes = 0;
        self.skipped = false;
    }

    /// Records an update skipped after checking its frame since `start`.
    pub fn skip(&mut self, start: std::time::Instant) {
        self.clear();
        self.skipped = true;
        self.stages.push(("unchanged frame", start.elapsed()));
    }

    /// Runs `work`, records its duration under `stage`, returns its result.
    pub fn time<T>(&mut self, stage: &'static str, work: impl FnOnce() -> T) -> T {
        let start = std::time::Instant::now();
        let result = work();
        self.stages.push((stage, start.elapsed()));
        result
    }

    pub fn total(&self) -> Duration {
        self.stages.iter().map(|(_, duration)| *duration).sum()
    }
}

/// One named buffer a technique keeps at run time.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct MemoryEntry {
    pub buffer: String,
    pub bytes: usize,
}

impl MemoryEntry {
    pub fn new(buffer: impl Into<String>, bytes: usize) -> Self {
        Self {
            buffer: buffer.into(),
            bytes,
        }
    }
}

/// Receives progress of long work; the CLI draws bars, libraries stay silent.
pub trait Progress: Sync {
    fn start(&self, stage: &str, total: u64);
    fn advance(&self, amount: u64);
    fn finish(&self);
}

/// Progress that goes nowhere.
pub struct NoProgress;

impl Progress for NoProgress {
    fn start(&self, _stage: &str, _total: u64) {}
    fn advance(&self, _amount: u64) {}
    fn finish(&self) {}
}

/// A running GI technique for one scene.
pub trait Technique: Send + Sync {
    fn name(&self) -> &'static str;

    /// Brings internal state up to date with `frame`'s lights. A frame
    /// that gives the update what the last one gave it (the lights, and
    /// the camera and moving meshes where the technique reads them) is
    /// skipped once the light is [`Technique::settled`], and the timings
    /// say so: an engine may call this every frame.
    fn update(&mut self, frame: &Frame) -> Result<(), TechniqueError>;

    /// Whether another update with the last frame would leave the light
    /// where it is. A technique that feeds last frame's light back (PIC,
    /// SRP) adds a bounce an update after its lights change, and is
    /// unsettled until the bounces it still adds are too small to see
    /// ([`crate::SettlingPasses`]); an engine keeps updating a resting
    /// scene while this is false.
    fn settled(&self) -> bool {
        true
    }

    /// Makes the next update run whatever its frame, as after a change of
    /// lights: for measurements that repeat updates under the same lights
    /// (their time, how far a first update settled).
    fn forget_last_frame(&mut self) {}

    /// Indirect irradiance (W/m^2) arriving at a point of the static scene on
    /// the side its `normal` faces.
    fn indirect_irradiance(&self, point: &SurfacePoint) -> Rgb;

    /// Indirect irradiance at an arbitrary point in space for a surface with
    /// `normal` there (dynamic objects, back faces of thin geometry).
    fn indirect_irradiance_in_space(&self, position: Vec3, normal: Vec3) -> Rgb;

    /// Indirect radiance leaving a glossy (Blinn-Phong) surface toward the
    /// viewer, when the technique models glossy transport.
    fn glossy_radiance(
        &self,
        _point: &SurfacePoint,
        _toward_viewer: Vec3,
        _exponent: f32,
    ) -> Option<Rgb> {
        None
    }

    /// The scene as the last update saw it when the technique moves meshes
    /// (the static triangles first, in their order, then the moving ones):
    /// renderers trace this instead of the static scene. `None` for
    /// techniques of static scenes.
    fn frame_geometry(&self) -> Option<relight_scene::Scene> {
        None
    }

    /// How many indirect bounces the technique computes, when it stops
    /// short of all of them: comparisons measure it against the path tracer
    /// limited to as many. `None`: all bounces (techniques that feed last
    /// frame's light back converge to all).
    fn indirect_bounces(&self) -> Option<u32> {
        None
    }

    /// The bounces a reference must have to measure this technique, when
    /// the comparison allows at most `most`.
    fn reference_bounces(&self, most: u32) -> u32 {
        self.indirect_bounces().map_or(most, |own| own.min(most))
    }

    /// Indirect irradiance per lightmap receiver after the last update, in
    /// the atlas's receiver order, when the technique stores a lightmap.
    fn receiver_irradiance(&self) -> Option<&[Rgb]>;

    /// Stage timings of the last update.
    fn timings(&self) -> &StageTimings;

    /// Run-time buffers and their sizes.
    fn memory(&self) -> Vec<MemoryEntry>;

    /// What the bake found, as (short label, value) lines for `relight
    /// info --bake` (probe counts, coverage, bake time...).
    fn bake_facts(&self) -> Vec<(&'static str, String)> {
        Vec::new()
    }
}

/// A technique's factory: name, bake and creation. The CLI lists kinds in
/// one table, so a new technique is one line there.
pub trait TechniqueKind: Sync {
    fn name(&self) -> &'static str;
    fn summary(&self) -> &'static str;
    fn needs_bake(&self) -> bool;

    /// The parameters the bake reads; the rest act at run time, so one bake
    /// serves every value of them. Empty: every parameter may change the
    /// bake.
    fn bake_parameters(&self) -> &'static [&'static str] {
        &[]
    }

    /// What the bake of `shard` (all of it: [`crate::Shard::WHOLE`]) will
    /// cost, from the scene's counts and the parameters, cheaply enough to
    /// tell before every bake; `None` for kinds without a bake.
    fn estimate(
        &self,
        _context: &SceneContext,
        _params: &[(String, String)],
        _shard: crate::Shard,
    ) -> Result<Option<crate::BakeEstimate>, TechniqueError> {
        Ok(None)
    }

    /// Precomputes the bake payload (technique-specific bytes).
    fn bake(
        &self,
        _context: &SceneContext,
        _params: &[(String, String)],
        _progress: &dyn Progress,
    ) -> Result<Vec<u8>, TechniqueError> {
        Err(TechniqueError::NoBake {
            technique: self.name(),
        })
    }

    /// Bakes one shard of the work (see [`crate::Shard`]): a payload only
    /// [`TechniqueKind::merge_shards`] reads. Techniques whose bake does
    /// not divide refuse.
    fn bake_shard(
        &self,
        _context: &SceneContext,
        _params: &[(String, String)],
        _shard: crate::Shard,
        _progress: &dyn Progress,
    ) -> Result<Vec<u8>, TechniqueError> {
        Err(TechniqueError::NotShardable {
            technique: self.name(),
        })
    }

    /// Joins every shard's payload, shard 0 first, into the bake payload
    /// [`TechniqueKind::bake`] would have made. Takes the payloads by value
    /// so each can be freed once read.
    fn merge_shards(
        &self,
        _parts: Vec<Vec<u8>>,
        _progress: &dyn Progress,
    ) -> Result<Vec<u8>, TechniqueError> {
        Err(TechniqueError::NotShardable {
            technique: self.name(),
        })
    }

    /// Creates the technique, from a bake payload when it needs one.
    fn create(
        &self,
        context: Arc<SceneContext>,
        bake: Option<&[u8]>,
        params: &[(String, String)],
        progress: &dyn Progress,
    ) -> Result<Box<dyn Technique>, TechniqueError>;
}

/// What can go wrong in a technique, each with what to do about it.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum TechniqueError {
    #[error("technique '{technique}' needs no bake: render or bench it directly")]
    NoBake { technique: &'static str },
    #[error("technique '{technique}' needs a bake: run `relight bake SCENE --technique {technique} -o FILE` and pass --bake FILE")]
    BakeRequired { technique: &'static str },
    #[error("technique '{technique}' bakes in one piece: drop --shard")]
    NotShardable { technique: &'static str },
    #[error(transparent)]
    Params(#[from] crate::ParamError),
    #[error("{path}: {message}")]
    BakeFile { path: PathBuf, message: String },
    // The operating system's message is part of this one, not a source
    // as well: a caller printing the chain would show it twice.
    #[error("{path}: {error}")]
    Io {
        path: PathBuf,
        error: std::io::Error,
    },
    #[error("{0}")]
    Other(String),
}
