//! Restarts: candidates trained from different seeds, and the one whose Lyapunov risk is lowest
//! kept as the run.

use std::io::Write;
use std::ops::ControlFlow;
use std::path::Path;

use burn::tensor::Device;

use super::config::{RESTART_SCORE_STEPS, candidate_seed};
use super::{DataRecord, RunPaths, TrainConfig, TrainSummary, train_interruptible};
use crate::data::Dataset;
use crate::error::{Error, Result};
use crate::losses::StepValues;

/// One candidate of a run with restarts, as `restarts.csv` records it.
struct Candidate {
    seed: u64,
    /// Mean Lyapunov risk over the candidate's last [`RESTART_SCORE_STEPS`] steps.
    risk: f64,
}

/// Trains `config.restarts` candidates in `run`'s `candidates/<i>/` folders (continuing any an
/// interrupted invocation left, as `--resume` would), then fills `run` with the one whose risk
/// is lowest: its weights, logs and snapshots, `restarts.csv` naming every candidate, and a
/// `metrics.csv` whose clock counts the other candidates' training first, so that a learning
/// curve of the run charges it for all of them. `progress` counts steps over all candidates.
pub(super) fn train_restarts(
    config: &TrainConfig,
    data: &Dataset,
    run: &RunPaths,
    resume: bool,
    device: &Device,
    progress: &mut dyn FnMut(u64, &StepValues) -> ControlFlow<()>,
) -> Result<TrainSummary> {
    let _writer = crate::fsutil::FolderLock::acquire(&run.dir)?;
    // A larger budget trains every candidate on, as `--resume` does a single run.
    if resume {
        super::saved_config_for_resume(run, config)?;
    } else {
        super::refuse_trained_folder(run)?;
    }
    crate::fsutil::write_json(&run.config(), config)?;
    crate::fsutil::write_json(&run.data_record(), &DataRecord::of(data))?;
    let mut candidates = Vec::new();
    let mut last = Vec::new();
    for i in 0..config.restarts {
        let candidate = TrainConfig {
            seed: candidate_seed(config.seed, i),
            restarts: 1,
            ..config.clone()
        };
        let paths = candidate_paths(run, i);
        let offset = i * config.steps;
        let summary = train_interruptible(
            &candidate,
            data,
            &paths,
            paths.checkpoint().exists(),
            device,
            |step, values| progress(offset + step, values),
        )?;
        candidates.push(Candidate {
            seed: candidate.seed,
            risk: final_risk(&paths)?,
        });
        last.push(summary.last);
    }
    let kept = (0..candidates.len())
        .min_by(|&a, &b| candidates[a].risk.total_cmp(&candidates[b].risk))
        .unwrap_or(0);
    let others: f64 = (0..config.restarts)
        .filter(|&i| i as usize != kept)
        .filter_map(|i| super::training_seconds(&candidate_paths(run, i)))
        .sum();
    keep_candidate(run, &candidate_paths(run, kept as u64), others)?;
    write_restarts_csv(run, &candidates, kept)?;
    Ok(TrainSummary {
        steps_done: config.steps,
        last: last.swap_remove(kept),
        seconds: super::training_seconds(run).unwrap_or(others),
        kept_candidate: Some((kept as u64, candidates[kept].seed)),
    })
}

/// The run folder of candidate `i` of a run with restarts.
pub fn candidate_paths(run: &RunPaths, i: u64) -> RunPaths {
    RunPaths::new(run.dir.join("candidates").join(i.to_string()))
}

/// The mean of the `lyap` column over the last [`RESTART_SCORE_STEPS`] rows of a run's
/// `metrics.csv`.
fn final_risk(run: &RunPaths) -> Result<f64> {
    let path = run.metrics();
    let text = std::fs::read_to_string(&path).map_err(|e| Error::io(&path, e))?;
    let bad = |message: &str| Error::config(path.display().to_string(), message.to_string());
    let mut lines = text.lines();
    let column = lines
        .next()
        .and_then(|header| header.split(',').position(|name| name == "lyap"))
        .ok_or_else(|| bad("no lyap column to rank the candidate by"))?;
    let rows: Vec<f64> = lines
        .filter_map(|line| line.split(',').nth(column)?.parse().ok())
        .collect();
    let tail = &rows[rows.len().saturating_sub(RESTART_SCORE_STEPS)..];
    if tail.is_empty() {
        return Err(bad("no rows to rank the candidate by"));
    }
    Ok(tail.iter().sum::<f64>() / tail.len() as f64)
}

/// Copies the kept candidate's files into `run` (its weights last, which mark the run finished)
/// and writes `run`'s `metrics.csv` with `others` seconds added to each row's clock.
fn keep_candidate(run: &RunPaths, kept: &RunPaths, others: f64) -> Result<()> {
    let clock = super::training_clock(kept).unwrap_or_default();
    let metrics =
        std::fs::read_to_string(kept.metrics()).map_err(|e| Error::io(kept.metrics(), e))?;
    let mut lines = metrics.lines();
    let mut body = lines.next().unwrap_or_default().to_string() + "\n";
    for (line, (_, seconds)) in lines.zip(&clock) {
        let row = line.rsplit_once(',').map_or(line, |(row, _)| row);
        body += &format!("{row},{:.3}\n", others + seconds);
    }
    crate::fsutil::write_atomically(&run.metrics(), true, |w| {
        w.write_all(body.as_bytes())
            .map_err(|e| Error::io(run.metrics(), e))
    })?;
    let skip = [
        run.config(),
        run.metrics(),
        run.checkpoint(),
        run.data_record(),
    ]
    .map(|p| p.file_name().map(|n| n.to_os_string()));
    copy_files(&kept.dir, &run.dir, &|name| {
        name.to_string_lossy().starts_with('.') || skip.contains(&Some(name.to_os_string()))
    })?;
    let snapshots = kept.dir.join("snapshots");
    if snapshots.is_dir() {
        for entry in std::fs::read_dir(&snapshots).map_err(|e| Error::io(&snapshots, e))? {
            let entry = entry.map_err(|e| Error::io(&snapshots, e))?;
            let to = run.dir.join("snapshots").join(entry.file_name());
            copy_files(&entry.path(), &to, &|name| {
                name.to_string_lossy().starts_with('.')
            })?;
        }
    }
    copy_file(&kept.checkpoint(), &run.checkpoint())
}

/// Copies the regular files of `from` into `to` (created if needed), except those `skip` names.
fn copy_files(from: &Path, to: &Path, skip: &dyn Fn(&std::ffi::OsStr) -> bool) -> Result<()> {
    std::fs::create_dir_all(to).map_err(|e| Error::io(to, e))?;
    for entry in std::fs::read_dir(from).map_err(|e| Error::io(from, e))? {
        let entry = entry.map_err(|e| Error::io(from, e))?;
        let is_file = entry
            .file_type()
            .map_err(|e| Error::io(entry.path(), e))?
            .is_file();
        if is_file && !skip(&entry.file_name()) {
            copy_file(&entry.path(), &to.join(entry.file_name()))?;
        }
    }
    Ok(())
}

/// Copies `from` over `to` atomically.
fn copy_file(from: &Path, to: &Path) -> Result<()> {
    let mut source = std::fs::File::open(from).map_err(|e| Error::io(from, e))?;
    crate::fsutil::write_atomically(to, true, |w| {
        std::io::copy(&mut source, w)
            .map(|_| ())
            .map_err(|e| Error::io(from, e))
    })
}

/// `restarts.csv`: each candidate's seed and final risk, and which one the run kept.
fn write_restarts_csv(run: &RunPaths, candidates: &[Candidate], kept: usize) -> Result<()> {
    let path = run.dir.join("restarts.csv");
    let mut body = String::from("candidate,seed,risk,kept\n");
    for (i, c) in candidates.iter().enumerate() {
        body += &format!("{i},{},{:.6},{}\n", c.seed, c.risk, i == kept);
    }
    crate::fsutil::write_atomically(&path, true, |w| {
        w.write_all(body.as_bytes())
            .map_err(|e| Error::io(&path, e))
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn final_risk_is_the_mean_of_the_last_logged_steps() {
        let dir = tempfile::tempdir().unwrap();
        let run = RunPaths::new(dir.path());
        let mut text = String::from("step,total,lyap,seconds\n");
        for step in 1..=60 {
            text += &format!("{step},9,{step},0.1\n");
        }
        std::fs::write(run.metrics(), text).unwrap();
        // Steps 11..=60: their mean is 35.5.
        assert_eq!(RESTART_SCORE_STEPS, 50);
        assert_eq!(final_risk(&run).unwrap(), 35.5);
        std::fs::write(run.metrics(), "step,total,elbo,seconds\n1,2,3,0.1\n").unwrap();
        let err = final_risk(&run).unwrap_err().to_string();
        assert!(err.contains("metrics.csv") && err.contains("lyap"), "{err}");
    }
}
