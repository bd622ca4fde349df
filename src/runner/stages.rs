//! Resumable stages shared by `demo` and `experiment`: a dataset collected or read back, a run
//! trained or its finished checkpoint reused, an evaluation run or its `eval.json` reused.

use std::path::Path;

use crate::data::{CollectConfig, Dataset, collect};
use crate::envs::EnvKind;
use crate::error::{Error, Result};
use crate::eval::{Controller, EvalOutputs, ReachConfig, ReachReport, evaluate_run_with};
use crate::losses::StepValues;
use crate::model::{EncoderHead, cpu_device};
use crate::train::{RunPaths, TrainConfig, train};

/// Whether a stage did its work now or found it done by an earlier invocation.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Outcome {
    Ran,
    Reused,
}

/// The dataset at `path`, collected with `config` (and saved) unless it is already there; a file
/// there that `config` would not have produced (another env, seed, size or source) is refused.
/// `progress` gets finished episodes when collecting.
pub fn collect_or_reuse(
    config: &CollectConfig,
    path: &Path,
    progress: impl FnMut(usize),
) -> Result<(Dataset, Outcome)> {
    let episodes = config.episodes()?;
    let steps = config.episode_len.min(config.transitions);
    if path.exists() {
        let data = Dataset::load(path)?;
        let found = (
            (data.meta.env, data.meta.env_config.clone()),
            data.meta.seed,
            data.episodes(),
            data.steps(),
            data.meta.source.as_str(),
        );
        let wanted = (
            config.recorded_env(),
            config.seed,
            episodes,
            steps,
            RANDOM_CONTROL,
        );
        if found.0 != wanted.0
            && (found.1, found.2, found.3, found.4) == (wanted.1, wanted.2, wanted.3, wanted.4)
        {
            return Err(Error::dataset(
                path,
                "was recorded from another environment configuration than this stage's (another variant, or --as-custom differs); move it away or pick another --out",
            ));
        }
        if found != wanted {
            return Err(Error::dataset(
                path,
                format!(
                    "holds {} {} episodes x {} steps of {} (seed {}), this stage needs {} {} x {} of {} (seed {}); move it away or pick another --out",
                    found.2,
                    found.4,
                    found.3,
                    data.meta.source_name(),
                    found.1,
                    wanted.2,
                    wanted.4,
                    wanted.3,
                    crate::envs::source_name(wanted.0.0),
                    wanted.1
                ),
            ));
        }
        return Ok((data, Outcome::Reused));
    }
    let data = collect(config, progress)?;
    data.save(path, false)?;
    Ok((data, Outcome::Ran))
}

/// The `source` of a random-control dataset.
const RANDOM_CONTROL: &str = "random-control";

/// Sets the training budget (`steps`, and `batch_size` if given) and keeps the checkpoint and
/// orientation-search cadences consistent with it: a checkpoint every 500 steps (or at the end
/// of a shorter run), on a multiple of the search period so that a resumed run searches where an
/// uninterrupted one would.
pub fn set_budget(config: &mut TrainConfig, steps: u64, batch_size: Option<usize>) {
    config.steps = steps;
    if let Some(batch) = batch_size {
        config.batch_size = batch;
    }
    config.checkpoint_every = if steps >= 500 { 500 } else { steps };
    let search = config.orientation_search_every;
    if search > 0 && !config.checkpoint_every.is_multiple_of(search) {
        config.orientation_search_every = config.checkpoint_every.min(search);
        config.checkpoint_every = config.orientation_search_every;
    }
}

/// Shrinks the networks of `config` to a few channels (smoke runs on a tiny budget).
pub fn shrink_networks(config: &mut TrainConfig) {
    config.model.encoder.trunk_channels = [8, 8];
    config.model.encoder.head = EncoderHead::SoftArgmax {
        keypoints: 4,
        hidden: 0,
        polar: false,
        pairwise_angles: false,
    };
    if let Some(nvae) = config.nvae.as_mut() {
        nvae.trunk_channels = [8, 8];
        nvae.encoder_head = EncoderHead::Mlp { hidden: 16 };
        nvae.decoder_hidden = 16;
        nvae.decoder_channels = [8, 8, 4];
    }
}

/// Whether the run's checkpoint holds `steps` training steps, or its stopping rule ended it
/// sooner (`metrics.csv` can run ahead of the checkpoint: its row for a step is written before
/// that step's checkpoint).
pub(crate) fn is_complete(run: &RunPaths, steps: u64) -> bool {
    crate::read_checkpoint_meta(&run.checkpoint())
        .is_ok_and(|meta| meta.step == steps || meta.stopped_early)
}

/// Trains `config` into `run`: reuses a finished run of the same configuration, resumes an
/// interrupted one, and refuses a folder holding a run of another configuration (never
/// overwriting it).
pub fn train_or_reuse(
    config: &TrainConfig,
    data: &Dataset,
    run: &RunPaths,
    progress: impl FnMut(u64, &StepValues),
) -> Result<Outcome> {
    let has_checkpoint = run.checkpoint().exists();
    if has_checkpoint {
        // An unreadable config.json is reported as it is, not as "another configuration".
        let saved = run.load_config()?;
        if &saved != config {
            return Err(Error::config(
                "run",
                format!(
                    "{} holds a run with another configuration ({}); move it away or pick another --out",
                    run.dir.display(),
                    run.config().display()
                ),
            ));
        }
        if is_complete(run, config.steps) {
            return Ok(Outcome::Reused);
        }
    }
    train(config, data, run, has_checkpoint, &cpu_device(), progress)?;
    Ok(Outcome::Ran)
}

/// Wall-clock training seconds of a run over every invocation that trained it, or `None`
/// without metrics.
pub fn training_seconds(run: &RunPaths) -> Option<f64> {
    let clock = training_clock(run)?;
    Some(clock.last().map_or(0.0, |(_, seconds)| *seconds))
}

/// `(step, wall-clock training seconds up to and including it)` for every step in the run's
/// `metrics.csv`, over every invocation that trained it (the file's `seconds` column restarts
/// from 0 on each resume), or `None` without metrics.
pub fn training_clock(run: &RunPaths) -> Option<Vec<(u64, f64)>> {
    let text = std::fs::read_to_string(run.metrics()).ok()?;
    let (mut before, mut last) = (0.0, 0.0);
    let mut clock = vec![];
    for (step, seconds) in text.lines().skip(1).filter_map(|line| {
        let step = line.split(',').next()?.parse::<u64>().ok()?;
        let seconds = line.rsplit(',').next()?.parse::<f64>().ok()?;
        Some((step, seconds))
    }) {
        if seconds < last {
            before += last;
        }
        last = seconds;
        clock.push((step, before + seconds));
    }
    Some(clock)
}

/// Whether `output` (an evaluation, tracking or diagnostics file of `run`) was written after
/// the run's checkpoint, so it describes these weights and not earlier ones.
pub fn is_current(run: &RunPaths, output: &Path) -> bool {
    let modified = |p: &Path| std::fs::metadata(p).and_then(|m| m.modified()).ok();
    match (modified(output), modified(&run.checkpoint())) {
        (Some(written), Some(weights)) => written >= weights,
        _ => false,
    }
}

/// The run's `eval.json` if it is current and was written for `protocol`, otherwise a fresh
/// evaluation (which rewrites it). `progress` gets finished episodes.
pub fn evaluate_or_reuse(
    run: &RunPaths,
    protocol: &ReachConfig,
    progress: impl FnMut(usize),
) -> Result<(ReachReport, Outcome)> {
    evaluate_or_reuse_with(run, protocol, &Controller::Feedback, progress)
}

/// As [`evaluate_or_reuse`] for `controller` on the run's latent (its own file,
/// `eval-mpc.json`, `eval-ilqr.json`, ...).
pub fn evaluate_or_reuse_with(
    run: &RunPaths,
    protocol: &ReachConfig,
    controller: &Controller,
    progress: impl FnMut(usize),
) -> Result<(ReachReport, Outcome)> {
    if let Some(report) = read_eval_with(run, controller).filter(|r| &r.protocol == protocol) {
        return Ok((report, Outcome::Reused));
    }
    Ok((
        evaluate_run_with(run, protocol, controller, progress)?,
        Outcome::Ran,
    ))
}

/// The run's JSON output `path` (in its folder), if readable and written after the run's
/// checkpoint.
pub fn read_current<T: serde::de::DeserializeOwned>(run: &RunPaths, path: &Path) -> Option<T> {
    if !is_current(run, path) {
        return None;
    }
    serde_json::from_str(&std::fs::read_to_string(path).ok()?).ok()
}

/// The run's `eval.json`, if there is a readable one written after its checkpoint.
pub fn read_eval(run: &RunPaths) -> Option<ReachReport> {
    read_eval_with(run, &Controller::Feedback)
}

/// The evaluation of `controller` on the run's latent, if current (as [`read_eval`]).
pub fn read_eval_with(run: &RunPaths, controller: &Controller) -> Option<ReachReport> {
    read_current(run, &EvalOutputs::for_controller(run, controller).json)
}

/// The goal-reaching protocol of `env` with the evaluation seed 1000 (disjoint from the data
/// seeds), `episodes` episodes and, if given, a shorter horizon.
pub fn reach_protocol(env: EnvKind, episodes: usize, horizon: Option<usize>) -> ReachConfig {
    let mut protocol = ReachConfig::for_env(env, 1000);
    protocol.episodes = episodes;
    if let Some(h) = horizon {
        protocol.horizon = h;
    }
    protocol
}

/// Decides when a long stage prints its next progress line: at the first step and then at
/// most once per `every`, so a log file or a cluster job sees a stage is alive without a line
/// per step.
pub struct ThrottledLine {
    every: std::time::Duration,
    last: Option<std::time::Instant>,
    /// When the first count was seen, and that count: the rate is measured from there, so a
    /// resumed run (whose count starts at its checkpoint) estimates from its own pace.
    origin: Option<(std::time::Instant, u64)>,
}

impl ThrottledLine {
    pub fn new(every: std::time::Duration) -> Self {
        Self {
            every,
            last: None,
            origin: None,
        }
    }

    /// As [`ThrottledLine::new`], but the first line is due only after `every` (a command that
    /// finishes sooner prints none).
    pub fn first_after(every: std::time::Duration) -> Self {
        Self {
            last: Some(std::time::Instant::now()),
            ..Self::new(every)
        }
    }

    /// `Some(eta)` (the estimated time left, as `1h02m03s`) when a line is due after `done` of
    /// `total` units of work, `None` otherwise.
    pub fn due(&mut self, done: u64, total: u64) -> Option<String> {
        self.due_at(std::time::Instant::now(), done, total)
    }

    fn due_at(&mut self, now: std::time::Instant, done: u64, total: u64) -> Option<String> {
        let (since, from) = *self.origin.get_or_insert((now, done));
        if self.last.is_some_and(|last| now - last < self.every) {
            return None;
        }
        self.last = Some(now);
        let left = if done <= from {
            f64::NAN
        } else {
            (now - since).as_secs_f64() / (done - from) as f64 * total.saturating_sub(done) as f64
        };
        Some(duration_text(left))
    }
}

/// Seconds as `1h02m03s`, `4m05s` or `6s`; `?` when unknown.
pub fn duration_text(seconds: f64) -> String {
    if !seconds.is_finite() || seconds < 0.0 {
        return "?".into();
    }
    let s = seconds.round() as u64;
    match (s / 3600, s / 60 % 60, s % 60) {
        (0, 0, sec) => format!("{sec}s"),
        (0, min, sec) => format!("{min}m{sec:02}s"),
        (h, min, sec) => format!("{h}h{min:02}m{sec:02}s"),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_progress_line_is_due_at_the_start_and_then_once_per_period() {
        let mut line = ThrottledLine::new(std::time::Duration::from_secs(3600));
        assert!(line.due(1, 10).is_some());
        assert_eq!(line.due(2, 10), None);
        let mut every_time = ThrottledLine::new(std::time::Duration::ZERO);
        assert_eq!(every_time.due(0, 10).as_deref(), Some("?"));
        assert!(every_time.due(5, 10).is_some());
        let mut later = ThrottledLine::first_after(std::time::Duration::from_secs(3600));
        assert_eq!(later.due(1, 10), None);
    }

    #[test]
    fn the_time_left_is_estimated_from_the_pace_since_the_first_count() {
        // A run resumed at step 4000 of 8000 that takes 10 s for its next 10 steps has 3990
        // steps, 3990 s, left: the 4000 steps before it ran in another process.
        let mut line = ThrottledLine::new(std::time::Duration::ZERO);
        let t0 = std::time::Instant::now();
        assert_eq!(line.due_at(t0, 4000, 8000).as_deref(), Some("?"));
        let t1 = t0 + std::time::Duration::from_secs(10);
        assert_eq!(line.due_at(t1, 4010, 8000).as_deref(), Some("1h06m30s"));
    }

    #[test]
    fn durations_read_as_hours_minutes_seconds() {
        assert_eq!(duration_text(6.4), "6s");
        assert_eq!(duration_text(245.0), "4m05s");
        assert_eq!(duration_text(3723.0), "1h02m03s");
        assert_eq!(duration_text(f64::NAN), "?");
    }
}
