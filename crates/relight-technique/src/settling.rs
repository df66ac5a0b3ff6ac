//! How many feedback passes an update that settles the light runs.

/// The share of the total light the passes not run may leave out.
pub const SETTLED_SHARE: f64 = 0.005;

/// Decides when the feedback passes of a settling update (the first one,
/// or one whose lights just changed) may stop.
///
/// A technique that feeds its last pass's indirect light back (PIC, SRP)
/// adds one bounce a pass, and the light each pass adds falls
/// geometrically by a ratio set by the scene: how much of the light a
/// surface reflects reaches other surfaces rather than leaving. A fixed
/// count of passes cuts that series where a bright closed interior still
/// has much to add: 16 passes in a closed grey room of albedo 0.9 gave SRP
/// 0.895x and PIC `high` 0.818x of the path tracer's indirect light. Here
/// the ratio is estimated from the last two passes' added light, and the
/// passes stop once the rest of the series, `added * ratio / (1 - ratio)`,
/// is under [`SETTLED_SHARE`] of the total, or at `most` passes.
#[derive(Clone, Debug)]
pub struct SettlingPasses {
    most: u32,
    passes: u32,
    total: Option<f64>,
    added: Option<f64>,
}

impl SettlingPasses {
    /// At most `most` passes (at least one runs).
    pub fn new(most: u32) -> Self {
        Self {
            most: most.max(1),
            passes: 0,
            total: None,
            added: None,
        }
    }

    /// Records a finished pass and says whether another is worth running.
    /// `total` measures the light after it (anything linear in the light:
    /// a luminance sum, a total flux); it is not called when the passes are
    /// at their limit anyway.
    pub fn another_pass(&mut self, total: impl FnOnce() -> f64) -> bool {
        self.passes += 1;
        if self.passes >= self.most {
            return false;
        }
        let total = total();
        if !total.is_finite() {
            return false;
        }
        let Some(last_total) = self.total.replace(total) else {
            return true;
        };
        let added = total - last_total;
        let last_added = self.added.replace(added);
        if added.abs() <= SETTLED_SHARE * 1e-3 * total.abs() {
            return false;
        }
        let Some(last_added) = last_added else {
            return true;
        };
        if last_added <= 0.0 || added < 0.0 {
            // Not yet a falling series (a near field that changes the
            // first passes); keep going until it is.
            return true;
        }
        let ratio = added / last_added;
        if ratio >= 1.0 {
            return true;
        }
        added * ratio / (1.0 - ratio) > SETTLED_SHARE * total
    }

    /// Passes recorded so far.
    pub fn passes(&self) -> u32 {
        self.passes
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A geometric series of ratio r: the passes stop when the tail
    /// r^n / (1 - r) * (1 - r) = r^n of the sum is under the share, that
    /// is after ceil(ln(share) / ln(r)) passes (plus one for the first
    /// pass, whose added light is not known until the second).
    #[test]
    fn passes_stop_where_the_rest_of_a_geometric_series_is_small() {
        for ratio in [0.3f64, 0.6, 0.9, 0.97] {
            let mut settling = SettlingPasses::new(10_000);
            let (mut total, mut bounce) = (0.0, 1.0);
            loop {
                total += bounce;
                bounce *= ratio;
                if !settling.another_pass(|| total) {
                    break;
                }
            }
            let limit = 1.0 / (1.0 - ratio);
            let left = (limit - total) / limit;
            assert!(left <= SETTLED_SHARE * 1.0001, "ratio {ratio}: {left} left");
            // No more than one pass past the point where the rest is under
            // the share.
            let needed = (SETTLED_SHARE.ln() / ratio.ln()).ceil() as u32;
            assert!(
                settling.passes() <= needed + 1,
                "ratio {ratio}: {} passes",
                settling.passes()
            );
        }
    }

    #[test]
    fn the_most_passes_and_a_dark_scene_stop_it() {
        let mut settling = SettlingPasses::new(3);
        assert!(settling.another_pass(|| 1.0));
        assert!(settling.another_pass(|| 1.99));
        assert!(!settling.another_pass(|| 2.97));
        // No light at all: nothing to add after the second pass.
        let mut settling = SettlingPasses::new(100);
        assert!(settling.another_pass(|| 0.0));
        assert!(!settling.another_pass(|| 0.0));
        // A growing series runs to the limit.
        let mut settling = SettlingPasses::new(20);
        let mut runs = 1;
        let mut total = 1.0;
        while settling.another_pass(|| total) {
            total *= 2.0;
            runs += 1;
        }
        assert_eq!(runs, 20);
    }
}
