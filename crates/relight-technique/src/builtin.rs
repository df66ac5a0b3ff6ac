//! The two techniques every scene has: `direct` (no indirect light) and
//! `reference` (path-traced indirect light per lightmap receiver).

use crate::params::parse_params;
use crate::{
    Frame, FrameReads, LastFrame, MemoryEntry, Progress, SceneContext, StageTimings, SurfacePoint,
    Technique, TechniqueError, TechniqueKind,
};
use glam::{Vec2, Vec3};
use relight_core::sampling::{stratified_square, SampleStream};
use relight_core::Rgb;
use relight_scene::Light;
use relight_trace::path::{halves_estimate, PathSettings, PathTracer};
use serde::{Deserialize, Serialize};
use std::sync::Arc;

/// `direct`: indirect light is zero. Its update computes the direct
/// lightmap at every receiver, which makes it the cost floor every
/// technique pays and a benchmark of the direct-light service.
pub struct DirectKind;

struct DirectOnly {
    context: Arc<SceneContext>,
    direct_lightmap: Vec<Rgb>,
    zero: Vec<Rgb>,
    timings: StageTimings,
    last_frame: LastFrame,
}

impl TechniqueKind for DirectKind {
    fn name(&self) -> &'static str {
        "direct"
    }
    fn summary(&self) -> &'static str {
        "direct light only: no indirect light (the lower bound)"
    }
    fn needs_bake(&self) -> bool {
        false
    }
    fn create(
        &self,
        context: Arc<SceneContext>,
        _bake: Option<&[u8]>,
        params: &[(String, String)],
        _progress: &dyn Progress,
    ) -> Result<Box<dyn Technique>, TechniqueError> {
        if let Some((key, _)) = params.first() {
            return Err(crate::ParamError {
                technique: "direct",
                message: format!("unknown key '{key}': this technique has no parameters"),
            }
            .into());
        }
        let receivers = context.atlas.receivers.len();
        Ok(Box::new(DirectOnly {
            context,
            direct_lightmap: vec![Rgb::ZERO; receivers],
            zero: vec![Rgb::ZERO; receivers],
            timings: StageTimings::default(),
            last_frame: LastFrame::default(),
        }))
    }
}

impl Technique for DirectOnly {
    fn name(&self) -> &'static str {
        "direct"
    }
    fn forget_last_frame(&mut self) {
        self.last_frame.forget();
    }
    fn update(&mut self, frame: &Frame) -> Result<(), TechniqueError> {
        let start = std::time::Instant::now();
        if self.last_frame.repeats(frame, FrameReads::default()) {
            self.timings.skip(start);
            return Ok(());
        }
        self.timings.clear();
        let context = &self.context;
        let lightmap = &mut self.direct_lightmap;
        self.timings.time("direct lightmap", || {
            let receivers = &context.atlas.receivers;
            context.direct().irradiance_batch(
                frame.lights,
                &receivers.positions,
                &receivers.normals,
                lightmap,
            );
        });
        Ok(())
    }
    fn indirect_irradiance(&self, _point: &SurfacePoint) -> Rgb {
        Rgb::ZERO
    }
    fn indirect_irradiance_in_space(&self, _position: Vec3, _normal: Vec3) -> Rgb {
        Rgb::ZERO
    }
    fn receiver_irradiance(&self) -> Option<&[Rgb]> {
        Some(&self.zero)
    }
    fn timings(&self) -> &StageTimings {
        &self.timings
    }
    fn memory(&self) -> Vec<MemoryEntry> {
        vec![MemoryEntry::new(
            "direct lightmap",
            self.direct_lightmap.len() * 12,
        )]
    }
}

/// Parameters of the `reference` technique.
#[derive(Clone, Debug, Serialize, Deserialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct ReferenceParams {
    /// Paths per receiver per update.
    pub samples: u32,
    /// Indirect bounces (all bounces in practice: Russian roulette ends paths).
    pub max_bounces: u32,
    /// Paths per query for points in space.
    pub space_samples: u32,
    pub seed: u64,
}

impl Default for ReferenceParams {
    fn default() -> Self {
        Self {
            samples: 256,
            max_bounces: 64,
            space_samples: 64,
            seed: 1,
        }
    }
}

/// Per-receiver path-traced indirect irradiance with its standard error.
#[derive(Clone, Debug, Default)]
pub struct ReferenceLightmap {
    pub mean: Vec<Rgb>,
    pub standard_error: Vec<Rgb>,
}

/// Path traces indirect irradiance at every receiver of `context`.
///
/// The estimate is the mean of two independent halves (different seeds),
/// each with first-bounce directions stratified over its own samples.
/// Stratification makes the usual iid variance formula wrong, so the
/// standard error comes from the halves instead: |A - B| / 2 has the
/// expected square of the mean's variance. Per receiver that is a one-sample
/// estimate; summed over many receivers it measures the noise well.
pub fn reference_receiver_irradiance(
    context: &SceneContext,
    lights: &[Light],
    settings: PathSettings,
    samples: u32,
    progress: &dyn Progress,
) -> ReferenceLightmap {
    let receivers = &context.atlas.receivers;
    reference_irradiance_at(
        context,
        lights,
        settings,
        samples,
        &receivers.positions,
        &receivers.normals,
        progress,
    )
}

/// The same estimate at any surface points: `positions` with the side
/// `normals` faces (points in space for dynamic objects, too).
pub fn reference_irradiance_at(
    context: &SceneContext,
    lights: &[Light],
    settings: PathSettings,
    samples: u32,
    positions: &[glam::Vec3],
    normals: &[glam::Vec3],
    progress: &dyn Progress,
) -> ReferenceLightmap {
    let direct = context.direct();
    let count = positions.len();
    let half = (samples / 2).max(1);
    // Passes of 16 samples keep the progress bar moving; the sum is the
    // same as one pass because every sample has its own stream.
    let pass = 16u32.min(half);
    progress.start("reference lightmap", 2 * half as u64);
    let mut halves = [vec![[0.0f64; 3]; count], vec![[0.0f64; 3]; count]];
    for (index, sums) in halves.iter_mut().enumerate() {
        let tracer = PathTracer::new(&direct, settings.half(index));
        let mut done = 0u32;
        while done < half {
            let this_pass = pass.min(half - done);
            tracer
                .indirect_irradiance_sums(lights, positions, normals, done, this_pass, half, sums);
            done += this_pass;
            progress.advance(this_pass as u64);
        }
    }
    progress.finish();
    let [first, second] = &halves;
    let (mean, standard_error) = first
        .iter()
        .zip(second)
        .map(|(&a, &b)| halves_estimate(a, b, half))
        .unzip();
    ReferenceLightmap {
        mean,
        standard_error,
    }
}

/// `reference`: path-traced indirect light, the ground truth.
pub struct ReferenceKind;

struct Reference {
    context: Arc<SceneContext>,
    params: ReferenceParams,
    receiver_values: Vec<Rgb>,
    lightmap: Vec<Rgb>,
    lights: Vec<Light>,
    timings: StageTimings,
    last_frame: LastFrame,
}

impl TechniqueKind for ReferenceKind {
    fn name(&self) -> &'static str {
        "reference"
    }
    fn summary(&self) -> &'static str {
        "path-traced indirect light per receiver (ground truth; slow)"
    }
    fn needs_bake(&self) -> bool {
        false
    }
    fn create(
        &self,
        context: Arc<SceneContext>,
        _bake: Option<&[u8]>,
        params: &[(String, String)],
        _progress: &dyn Progress,
    ) -> Result<Box<dyn Technique>, TechniqueError> {
        let params = parse_params("reference", &ReferenceParams::default(), params)?;
        Ok(Box::new(Reference {
            context,
            params,
            receiver_values: Vec::new(),
            lightmap: Vec::new(),
            lights: Vec::new(),
            timings: StageTimings::default(),
            last_frame: LastFrame::default(),
        }))
    }
}

impl Reference {
    fn path_settings(&self) -> PathSettings {
        PathSettings {
            max_bounces: self.params.max_bounces,
            seed: self.params.seed,
            ..PathSettings::default()
        }
    }
}

impl Technique for Reference {
    fn name(&self) -> &'static str {
        "reference"
    }
    fn forget_last_frame(&mut self) {
        self.last_frame.forget();
    }
    fn update(&mut self, frame: &Frame) -> Result<(), TechniqueError> {
        let start = std::time::Instant::now();
        if self.last_frame.repeats(frame, FrameReads::default()) {
            self.timings.skip(start);
            return Ok(());
        }
        self.timings.clear();
        self.lights = frame.lights.to_vec();
        let settings = self.path_settings();
        let samples = self.params.samples;
        let context = &self.context;
        let values = self.timings.time("path tracing", || {
            reference_receiver_irradiance(
                context,
                frame.lights,
                settings,
                samples,
                &crate::NoProgress,
            )
            .mean
        });
        self.lightmap = self
            .timings
            .time("dilation", || context.atlas.to_lightmap(&values));
        self.receiver_values = values;
        Ok(())
    }
    fn indirect_irradiance(&self, point: &SurfacePoint) -> Rgb {
        self.context
            .atlas
            .sample(&self.lightmap, point.triangle, point.barycentric)
    }
    fn indirect_irradiance_in_space(&self, position: Vec3, normal: Vec3) -> Rgb {
        let direct = self.context.direct();
        let tracer = PathTracer::new(&direct, self.path_settings());
        let key = relight_core::sampling::mix64(
            position.x.to_bits() as u64
                ^ ((position.y.to_bits() as u64) << 21)
                ^ ((position.z.to_bits() as u64) << 42),
        );
        let mut sum = Rgb::ZERO;
        let samples = self.params.space_samples;
        for sample in 0..samples {
            let mut rng = SampleStream::new(self.params.seed, key, sample as u64);
            let first_bounce = stratified_square(sample, samples, Vec2::ZERO, &mut rng);
            sum += tracer.indirect_irradiance_sample(
                &self.lights,
                position,
                normal,
                first_bounce,
                &mut rng,
                key ^ sample as u64,
            );
        }
        sum / self.params.space_samples.max(1) as f32
    }
    fn receiver_irradiance(&self) -> Option<&[Rgb]> {
        Some(&self.receiver_values)
    }
    fn timings(&self) -> &StageTimings {
        &self.timings
    }
    fn memory(&self) -> Vec<MemoryEntry> {
        vec![
            MemoryEntry::new("receiver irradiance", self.receiver_values.len() * 12),
            MemoryEntry::new("lightmap", self.lightmap.len() * 12),
        ]
    }
}
