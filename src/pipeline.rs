//! Resumable stages shared by `demo` and `experiment`: a dataset collected or read back, a run
//! trained or its finished checkpoint reused, an evaluation run or its `eval.json` reused.

use std::path::Path;

use crate::data::{CollectConfig, Dataset, collect};
use crate::envs::EnvKind;
use crate::error::{Error, Result};
use crate::eval::{ReachConfig, ReachReport, evaluate_run};
use crate::model::{EncoderHead, cpu_device};
use crate::train::{RunPaths, StepValues, TrainConfig, train};

/// Whether a stage did its work now or found it done by an earlier invocation.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Outcome {
    Ran,
    Reused,
}

/// The dataset at `path`, collected with `config` (and saved) unless it is already there.
pub fn collect_or_reuse(config: &CollectConfig, path: &Path) -> Result<(Dataset, Outcome)> {
    if path.exists() {
        let data = Dataset::load(path)?;
        if data.meta.env != config.env {
            return Err(Error::dataset(
                path,
                format!(
                    "holds {} transitions, this stage collects {}; move it away or pick another --out",
                    data.meta.env, config.env
                ),
            ));
        }
        return Ok((data, Outcome::Reused));
    }
    let data = collect(config, |_| {})?;
    data.save(path, false)?;
    Ok((data, Outcome::Ran))
}

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
    };
    if let Some(nvae) = config.nvae.as_mut() {
        nvae.trunk_channels = [8, 8];
        nvae.encoder_head = EncoderHead::Mlp { hidden: 16 };
        nvae.decoder_hidden = 16;
        nvae.decoder_channels = [8, 8, 4];
    }
}

/// Whether a run's `metrics.csv` reaches `steps`.
fn is_complete(run: &RunPaths, steps: u64) -> bool {
    std::fs::read_to_string(run.metrics())
        .ok()
        .and_then(|text| {
            text.lines()
                .last()
                .and_then(|l| l.split(',').next())
                .and_then(|s| s.parse::<u64>().ok())
        })
        == Some(steps)
}

/// Trains `config` into `run`: reuses a finished run of the same configuration, resumes an
/// interrupted one, and refuses a folder holding a run of another configuration (never
/// overwriting it). Returns the training seconds when it trained.
pub fn train_or_reuse(
    config: &TrainConfig,
    data: &Dataset,
    run: &RunPaths,
    progress: impl FnMut(u64, &StepValues),
) -> Result<(Option<f64>, Outcome)> {
    let has_checkpoint = run.checkpoint().exists();
    let same_config = run.load_config().ok().as_ref() == Some(config);
    if has_checkpoint && same_config && is_complete(run, config.steps) {
        return Ok((None, Outcome::Reused));
    }
    if has_checkpoint && !same_config {
        return Err(Error::config(
            "run",
            format!(
                "{} holds a run with another configuration; move it away or pick another --out",
                run.dir.display()
            ),
        ));
    }
    let start = std::time::Instant::now();
    train(config, data, run, has_checkpoint, &cpu_device(), progress)?;
    Ok((Some(start.elapsed().as_secs_f64()), Outcome::Ran))
}

/// The run's `eval.json` if it was written for `protocol` and `retrained` is false, otherwise
/// a fresh evaluation (which rewrites it). `progress` gets finished episodes.
pub fn evaluate_or_reuse(
    run: &RunPaths,
    protocol: &ReachConfig,
    retrained: bool,
    progress: impl FnMut(usize),
) -> Result<(ReachReport, Outcome)> {
    if !retrained && let Some(report) = read_eval(run).filter(|r| &r.protocol == protocol) {
        return Ok((report, Outcome::Reused));
    }
    Ok((evaluate_run(run, protocol, progress)?, Outcome::Ran))
}

/// The run's `eval.json`, if there is a readable one.
pub fn read_eval(run: &RunPaths) -> Option<ReachReport> {
    let text = std::fs::read_to_string(run.dir.join("eval.json")).ok()?;
    serde_json::from_str(&text).ok()
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
