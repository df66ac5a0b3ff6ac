//! How many feedback passes an update that settles the light runs.

/// The relative error the passes not run may leave, as the root mean
/// square over the elements a technique measures (caches, texels) of each
/// one's estimated remaining light over its light.
pub const SETTLED_SHARE: f32 = 0.005;

/// Elements darker than this share of the mean take no part: their
/// relative change says nothing anyone sees.
const DARK_SHARE: f32 = 1e-3;

/// The highest ratio of one pass's added light to the last's that is taken
/// as falling; an element whose light is not falling yet (a room lit only
/// through a doorway, whose bounces arrive a pass late) counts as if its
/// series fell this slowly. A series that truly falls slower has its rest
/// underestimated, but would need more than 500 passes to settle, past
/// any sensible `most`.
const SLOWEST_RATIO: f32 = 0.99;

/// Decides when the feedback passes of a settling update (the first one)
/// may stop.
///
/// A technique that feeds its last pass's indirect light back (PIC, SRP)
/// adds one bounce a pass, and the light each pass adds falls
/// geometrically by a ratio set by the scene: how much of the light a
/// surface reflects reaches other surfaces rather than leaving. A fixed
/// count of passes cuts that series where a bright closed interior still
/// has much to add: 16 passes in a closed grey room of albedo 0.9 gave SRP
/// 0.895x and PIC `high` 0.818x of the path tracer's indirect light.
///
/// Each element's ratio is estimated from its last two passes' added
/// light, and its remaining light as `added * ratio / (1 - ratio)`; the
/// passes stop once the root mean square of remaining over present light
/// is under [`SETTLED_SHARE`], or at `most` passes. Per element, not over
/// the total: a room lit through a doorway holds a small part of the light
/// and gets its bounces late, so a criterion on the total stopped PIC
/// while that room was still 1 % darker than where it was going.
#[derive(Clone, Debug, Default)]
pub struct SettlingPasses {
    most: u32,
    passes: u32,
    feedback: bool,
    last: Vec<f32>,
    last_added: Vec<f32>,
    current: Vec<f32>,
}

impl SettlingPasses {
    /// The passes of one update of a technique whose `bounces` parameter
    /// caps them: the first update (`first`) runs until the bounces settle,
    /// a later one adds one bounce on top of the last, and `bounces = 1`
    /// turns feedback off.
    pub fn for_update(bounces: u32, first: bool) -> Self {
        Self {
            feedback: bounces > 1,
            ..Self::new(if first { bounces } else { 1 })
        }
    }

    /// The updates of a resting scene after its lights last changed, of a
    /// technique whose `bounces` parameter caps them: each update is one
    /// pass, recorded here until the bounces settle (the update that
    /// changed the lights is the first).
    pub fn at_rest(bounces: u32) -> Self {
        Self {
            feedback: true,
            ..Self::new(bounces)
        }
    }

    /// At most `most` passes (at least one runs).
    fn new(most: u32) -> Self {
        Self {
            most: most.max(1),
            ..Self::default()
        }
    }

    /// Records a finished pass and says whether another is worth running.
    /// `measure` fills the light of each element after it (a luminance:
    /// anything linear in the light), in the same order every pass; it is
    /// not called when the passes are at their limit anyway.
    pub fn another_pass(&mut self, measure: impl FnOnce(&mut Vec<f32>)) -> bool {
        self.passes += 1;
        if self.passes >= self.most {
            return false;
        }
        self.current.clear();
        measure(&mut self.current);
        let current = &self.current;
        if self.last.len() != current.len() {
            // The first pass (or a measure that changed its length).
            self.last.clone_from(current);
            self.last_added.clear();
            return true;
        }
        // After the second pass no ratio is known yet: every element
        // counts as falling at the slowest ratio, which stops the passes
        // only where the light added is nearly nothing.
        self.last_added.resize(current.len(), 0.0);
        // Non-finite values (a technique's fault, never expected) take no
        // part, so they neither stop the passes nor hold them to `most`.
        let (sum, finite) = current
            .iter()
            .filter(|value| value.is_finite())
            .fold((0.0f64, 0usize), |(sum, count), &value| {
                (sum + f64::from(value), count + 1)
            });
        let floor = (DARK_SHARE as f64 * sum / finite.max(1) as f64) as f32;
        let (mut squares, mut counted) = (0.0f64, 0usize);
        for ((&value, last), last_added) in current
            .iter()
            .zip(self.last.iter_mut())
            .zip(self.last_added.iter_mut())
        {
            let added = value - *last;
            let counts = value.is_finite() && added.is_finite() && value > floor;
            if counts && added > 0.0 {
                let ratio = if *last_added > 0.0 {
                    (added / *last_added).min(SLOWEST_RATIO)
                } else {
                    SLOWEST_RATIO
                };
                let remaining = added * ratio / (1.0 - ratio);
                squares += f64::from(remaining / value).powi(2);
            }
            counted += usize::from(counts);
            *last = value;
            *last_added = added;
        }
        counted > 0 && (squares / counted as f64).sqrt() > f64::from(SETTLED_SHARE)
    }

    /// Passes recorded so far.
    pub fn passes(&self) -> u32 {
        self.passes
    }

    /// What [`crate::StageTimings::feedback_passes`] reports: the passes,
    /// or 0 without feedback.
    pub fn feedback_passes(&self) -> u32 {
        if self.feedback {
            self.passes
        } else {
            0
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn run(
        settling: &mut SettlingPasses,
        mut light_after: impl FnMut(u32) -> Vec<f32>,
    ) -> Vec<f32> {
        let mut pass = 0;
        loop {
            let light = light_after(pass);
            pass += 1;
            if !settling.another_pass(|values| values.extend_from_slice(&light)) {
                return light;
            }
        }
    }

    /// Geometric series of ratio r: the passes stop when every element's
    /// tail is under the share, so each is within it of its limit 1/(1-r),
    /// and no more than one pass after that point (plus one: the first
    /// pass's added light is not known until the second).
    #[test]
    fn passes_stop_where_the_rest_of_a_geometric_series_is_small() {
        for ratio in [0.3f32, 0.6, 0.9, 0.97] {
            let mut settling = SettlingPasses::new(10_000);
            let series = |pass: u32| {
                let sum = (1.0 - ratio.powi(pass as i32 + 1)) / (1.0 - ratio);
                vec![sum, 2.0 * sum, 0.5 * sum]
            };
            let light = run(&mut settling, series);
            let limit = 1.0 / (1.0 - ratio);
            let left = (limit - light[0]) / limit;
            assert!(left <= SETTLED_SHARE * 1.01, "ratio {ratio}: {left} left");
            let needed = (SETTLED_SHARE.ln() / ratio.ln()).ceil() as u32;
            assert!(
                settling.passes() <= needed + 2,
                "ratio {ratio}: {} passes, {needed} needed",
                settling.passes()
            );
        }
    }

    /// A bright element that settles at once beside a dim one whose light
    /// arrives a pass later and falls slowly (a room lit through a
    /// doorway): the dim one decides.
    #[test]
    fn a_dim_element_whose_light_comes_late_keeps_the_passes_going() {
        let mut settling = SettlingPasses::new(10_000);
        let (fast, slow) = (0.2f32, 0.8f32);
        let light = run(&mut settling, |pass| {
            let bright = (1.0 - fast.powi(pass as i32 + 1)) / (1.0 - fast);
            let dim = if pass == 0 {
                0.0
            } else {
                0.01 * (1.0 - slow.powi(pass as i32)) / (1.0 - slow)
            };
            vec![bright, dim]
        });
        let dim_limit = 0.01 / (1.0 - slow);
        assert!(
            (dim_limit - light[1]) / dim_limit < 2.0 * SETTLED_SHARE,
            "dim element at {} of {dim_limit}",
            light[1]
        );
    }

    /// A non-finite element (a technique's fault) neither stops the passes
    /// nor holds them to the limit: the others decide alone.
    #[test]
    fn non_finite_elements_take_no_part() {
        let series = |pass: u32| (1.0 - 0.6f32.powi(pass as i32 + 1)) / 0.4;
        let mut clean = SettlingPasses::new(1000);
        run(&mut clean, |pass| vec![series(pass)]);
        for odd in [f32::NAN, f32::INFINITY] {
            let mut spoilt = SettlingPasses::new(1000);
            run(&mut spoilt, |pass| vec![odd, series(pass)]);
            assert_eq!(spoilt.passes(), clean.passes(), "{odd}");
        }
    }

    #[test]
    fn the_most_passes_and_a_dark_scene_stop_it() {
        let mut settling = SettlingPasses::new(3);
        assert!(settling.another_pass(|values| values.push(1.0)));
        assert!(settling.another_pass(|values| values.push(1.99)));
        assert!(!settling.another_pass(|values| values.push(2.97)));
        // No light at all: nothing to wait for after the second pass.
        let mut settling = SettlingPasses::new(100);
        assert!(settling.another_pass(|values| values.push(0.0)));
        assert!(!settling.another_pass(|values| values.push(0.0)));
        // A growing series runs to the limit.
        let mut settling = SettlingPasses::new(20);
        let mut total = 1.0;
        let mut runs = 1;
        while settling.another_pass(|values| values.push(total)) {
            total *= 2.0;
            runs += 1;
        }
        assert_eq!(runs, 20);
    }
}
