//! Progress bars on stderr (indicatif) behind the library's Progress trait,
//! and the time each stage took, for the reports of long work.

use indicatif::{ProgressBar, ProgressDrawTarget, ProgressStyle};
use relight_technique::Progress;
use std::sync::Mutex;
use std::time::{Duration, Instant};

pub struct Bars {
    quiet: bool,
    bar: Mutex<Option<ProgressBar>>,
    /// The stage under way and when it started; stages finished, in order.
    current: Mutex<Option<(String, Instant)>>,
    finished: Mutex<Vec<(String, Duration)>>,
}

impl Bars {
    pub fn new(quiet: bool) -> Self {
        Self {
            quiet,
            bar: Mutex::new(None),
            current: Mutex::new(None),
            finished: Mutex::new(Vec::new()),
        }
    }

    /// Each finished stage and its wall-clock time, in order; a stage that
    /// ran more than once is summed in the place of its first run.
    pub fn stage_times(&self) -> Vec<(String, Duration)> {
        let mut stages: Vec<(String, Duration)> = Vec::new();
        for (name, time) in self.finished.lock().expect("progress lock").iter() {
            match stages.iter_mut().find(|(seen, _)| seen == name) {
                Some((_, total)) => *total += *time,
                None => stages.push((name.clone(), *time)),
            }
        }
        stages
    }

    /// Lines for a report: each stage's time and share of `total`, then
    /// the time outside every stage.
    pub fn stage_report(&self, total: Duration) -> Vec<String> {
        let stages = self.stage_times();
        let staged: Duration = stages.iter().map(|(_, time)| *time).sum();
        let share = |time: Duration| 100.0 * time.as_secs_f64() / total.as_secs_f64().max(1e-9);
        stages
            .iter()
            .map(|(name, time)| (name.as_str(), *time))
            .chain(std::iter::once((
                "outside the stages",
                total.saturating_sub(staged),
            )))
            .map(|(name, time)| {
                format!(
                    "  {name:<28} {:>9.2} s {:>5.1} %",
                    time.as_secs_f64(),
                    share(time)
                )
            })
            .collect()
    }
}

impl Progress for Bars {
    fn start(&self, stage: &str, total: u64) {
        self.end_stage();
        *self.current.lock().expect("progress lock") = Some((stage.to_string(), Instant::now()));
        if self.quiet {
            return;
        }
        let bar = ProgressBar::with_draw_target(Some(total), ProgressDrawTarget::stderr());
        bar.set_style(
            ProgressStyle::with_template(
                "{msg:>20} [{bar:40}] {pos}/{len} {elapsed_precise} (eta {eta})",
            )
            .expect("valid template")
            .progress_chars("=> "),
        );
        bar.set_message(stage.to_string());
        *self.bar.lock().expect("progress lock") = Some(bar);
    }
    fn advance(&self, amount: u64) {
        if let Some(bar) = self.bar.lock().expect("progress lock").as_ref() {
            bar.inc(amount);
        }
    }
    fn finish(&self) {
        self.end_stage();
        if let Some(bar) = self.bar.lock().expect("progress lock").take() {
            bar.finish_and_clear();
        }
    }
}

impl Bars {
    fn end_stage(&self) {
        if let Some((stage, started)) = self.current.lock().expect("progress lock").take() {
            self.finished
                .lock()
                .expect("progress lock")
                .push((stage, started.elapsed()));
        }
    }
}
