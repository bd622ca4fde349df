//! Ablation grids: every cell of a TOML grid trained on several seeds and evaluated with the
//! goal-reaching protocol; resumable (finished tasks are read back, not redone), one
//! `result.json` per (cell, seed) and one line each in `ablation.jsonl`, and `ablation.md` +
//! `ablation.json` at the end. A job array runs one (cell, seed) per index (`GridWork::Task`).
//!
//! Grid file:
//!
//! ```toml
//! [base]            # fields over the preset, for every cell
//! steps = 1000
//! [[cell]]
//! name = "default"
//! [[cell]]
//! name = "paper"
//! preset = "paper"
//! [[cell]]
//! name = "eps=0.1"
//! loss = { latent_noise_std = 0.1 }
//! ```

use std::io::Write;
use std::path::{Path, PathBuf};

use crate::data::Dataset;
use crate::error::{Error, Result};
use crate::eval::{ReachConfig, evaluate_run, write_env_diagnostics};
use crate::losses::StepValues;
use crate::model::cpu_device;
use crate::train::{ConfigBase, RunPaths, TrainConfig, config_from_table, train};

use super::stages::is_complete;

/// A parsed grid.
#[derive(Debug, Clone)]
pub struct Grid {
    pub base: toml::Table,
    pub cells: Vec<(String, toml::Table)>,
}

impl Grid {
    pub fn from_toml(path: &Path) -> Result<Self> {
        let text = std::fs::read_to_string(path).map_err(|e| Error::io(path, e))?;
        let bad = |m: String| Error::config(format!("grid {}", path.display()), m);
        let mut table: toml::Table = text
            .parse()
            .map_err(|e: toml::de::Error| bad(e.message().to_string()))?;
        let base = match table.remove("base") {
            Some(toml::Value::Table(t)) => t,
            None => toml::Table::new(),
            Some(_) => return Err(bad("`base` must be a table".into())),
        };
        let cells = match table.remove("cell") {
            Some(toml::Value::Array(cells)) => cells,
            _ => return Err(bad("needs at least one [[cell]]".into())),
        };
        if let Some(key) = table.keys().next() {
            return Err(bad(format!(
                "unknown top-level key `{key}` (expected base, cell)"
            )));
        }
        let mut parsed = vec![];
        for (k, cell) in cells.into_iter().enumerate() {
            let toml::Value::Table(mut cell) = cell else {
                return Err(bad(format!("cell {k} is not a table")));
            };
            let name = match cell.remove("name") {
                Some(toml::Value::String(s))
                    if !s.is_empty()
                        && s.chars()
                            .all(|c| c.is_ascii_alphanumeric() || "-_=.".contains(c)) =>
                {
                    s
                }
                _ => {
                    return Err(bad(format!(
                        "cell {k} needs a `name` of letters, digits and - _ = ."
                    )));
                }
            };
            if parsed.iter().any(|(n, _)| n == &name) {
                return Err(bad(format!("duplicate cell name `{name}`")));
            }
            parsed.push((name, cell));
        }
        Ok(Self {
            base,
            cells: parsed,
        })
    }

    /// Every (cell, seed) of the grid over `seeds`, cell by cell: the tasks a job array's
    /// indices name (`--task-index`, `--list-tasks`).
    pub fn tasks(&self, seeds: std::ops::Range<u64>) -> Vec<(String, u64)> {
        self.cells
            .iter()
            .flat_map(|(name, _)| seeds.clone().map(move |seed| (name.clone(), seed)))
            .collect()
    }

    /// The resolved training configuration of every cell from `base` (the cell's keys
    /// deep-merged over `[base]`, over the preset), or the first cell that does not resolve,
    /// by name.
    pub fn cell_configs(&self, base: ConfigBase) -> Result<Vec<(String, TrainConfig)>> {
        self.cells
            .iter()
            .map(|(name, cell)| {
                let mut table = self.base.clone();
                crate::train::merge(&mut table, cell.clone());
                config_from_table(table, base, None)
                    .map(|config| (name.clone(), config))
                    .map_err(|e| Error::config(format!("cell `{name}`"), e.to_string()))
            })
            .collect()
    }
}

/// One trained and evaluated (cell, seed).
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct CellResult {
    pub cell: String,
    pub seed: u64,
    /// Mean over the task sets (each holds the same number of episodes).
    pub success_rate: f64,
    /// Success on each task set, in the order of [`run_grid`]'s protocols.
    #[serde(default)]
    pub success_per_task_set: Vec<f64>,
    /// Mean over the task sets.
    pub final_mean: f64,
    pub linear_r2: f64,
    pub det: Option<f64>,
    pub oracle_success_rate: f64,
    pub train_seconds: f64,
    /// The evaluation protocol of each task set (empty in results that lack the field): a
    /// result is reused only for the protocols it was evaluated on.
    #[serde(default)]
    pub task_sets: Vec<ReachConfig>,
}

/// What [`run_grid`] does with the grid's (cell, seed) tasks.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum GridWork {
    /// Train and evaluate every task without a result, then write the summary. Holds the
    /// grid folder's lock.
    TrainMissing,
    /// Train and evaluate task `i` of [`Grid::tasks`] only (a job-array element), unless it has
    /// a result; other tasks run beside it, so only its run folder is locked and no summary
    /// is written.
    Task(usize),
    /// Train nothing: summarise the results there are.
    ReportOnly,
}

/// The name of a task's result file in its run folder.
pub const TASK_RESULT: &str = "result.json";

/// Runs (or resumes) the grid on `data`, training seeds `seeds` per cell and evaluating each
/// trained run on every protocol of `task_sets` (one set of tasks each), into `out`: cell
/// `c`, seed `s` trains in `out/c/seed-s/` and leaves its [`CellResult`] there in
/// `result.json` (and, without `Task`, as a line of `out/ablation.jsonl`), its `eval.json` the
/// first task set's report. Tasks with a result
/// in either place are read back instead of trained, so grids split across processes or
/// machines merge by copying their folders (or concatenating `ablation.jsonl`).
/// `progress(cell, seed, step, steps, values)` is called after every training step.
#[allow(clippy::too_many_arguments)]
pub fn run_grid(
    grid: &Grid,
    data: &Dataset,
    seeds: std::ops::Range<u64>,
    task_sets: &[ReachConfig],
    out: &Path,
    work: GridWork,
    mut log: impl FnMut(&CellResult),
    mut progress: impl FnMut(&str, u64, u64, u64, &StepValues),
) -> Result<Vec<CellResult>> {
    let Some(protocol) = task_sets.first() else {
        return Err(Error::config("task-sets", "must be at least 1"));
    };
    std::fs::create_dir_all(out).map_err(|e| Error::io(out, e))?;
    // Training every task writes the grid's folder; one task writes its run folder only, and a
    // report from what is there only reads.
    let _writer = (work == GridWork::TrainMissing)
        .then(|| crate::fsutil::FolderLock::acquire(out))
        .transpose()?;
    // Custom data (an environment recorded with --as-custom) starts from the recipe its frames
    // call for, as `procl train` does.
    let base = ConfigBase::for_dataset(data, None)?;
    // Validate every cell before spending hours on the first one.
    let configs = grid.cell_configs(base)?;
    let tasks = grid.tasks(seeds);
    if let GridWork::Task(index) = work
        && index >= tasks.len()
    {
        return Err(Error::config(
            "task-index",
            format!(
                "{index} is out of range: the grid has {} tasks, 0 to {} (--list-tasks)",
                tasks.len(),
                tasks.len().saturating_sub(1)
            ),
        ));
    }
    let jsonl = out.join("ablation.jsonl");
    let mut done = read_results(out, &jsonl, &tasks)?;
    for (index, (name, seed)) in tasks.iter().enumerate() {
        let wanted = match work {
            GridWork::TrainMissing => true,
            GridWork::Task(i) => i == index,
            GridWork::ReportOnly => false,
        };
        let Some((_, base_config)) = configs.iter().find(|(n, _)| n == name) else {
            continue;
        };
        let mut config = base_config.clone();
        config.seed = *seed;
        let run = RunPaths::new(task_dir(out, name, *seed));
        // A run folder trained with another configuration (a cell or a preset edited after
        // training) must not pass for this cell's result. A job-array task checks its own.
        let checked = wanted || work == GridWork::ReportOnly;
        if checked && run.config().exists() && run.load_config()? != config {
            return Err(Error::config(
                format!("cell `{name}`"),
                format!(
                    "{} holds a run of another configuration than the grid's cell gives; move it away or pick another --out",
                    run.dir.display()
                ),
            ));
        }
        // A result evaluated on other task sets (another --episodes, --task-sets or
        // --horizon) is evaluated again on these, from the trained run, whose training time
        // and latent diagnostics stay as they were. Where that cannot happen it is refused:
        // reported as it is, it would pass for a result of the protocol the report states.
        let previous = done.iter().position(|r| &r.cell == name && r.seed == *seed);
        let other_protocol = previous.filter(|&i| done[i].task_sets != task_sets);
        if let Some(i) = other_protocol
            && (work == GridWork::ReportOnly || wanted)
            && !(wanted && is_complete(&run, config.steps))
        {
            let remedy = if wanted {
                format!(
                    "{} holds no complete run to evaluate it again on these; pass the protocol it \
                     was evaluated on, or remove the result from its result.json and {} to train \
                     it again",
                    run.dir.display(),
                    jsonl.display()
                )
            } else {
                "run without --report-only to evaluate it again on these".to_string()
            };
            return Err(Error::config(
                format!("cell `{name}` seed {seed}"),
                format!(
                    "its result was evaluated on {}, not on these task sets; {remedy}",
                    describe_task_sets(&done[i].task_sets)
                ),
            ));
        }
        if !wanted {
            continue;
        }
        let trained = match (previous, other_protocol) {
            (Some(_), None) => continue,
            (_, Some(i)) => Trained::from(done.remove(i)),
            (None, None) => {
                let resume = run.checkpoint().exists();
                let start = std::time::Instant::now();
                train(
                    &config,
                    data,
                    &run,
                    resume,
                    &cpu_device(),
                    |step, values| progress(name, *seed, step, config.steps, values),
                )?;
                let train_seconds = start.elapsed().as_secs_f64();
                let diagnostics = write_env_diagnostics(&run)?;
                Trained {
                    train_seconds,
                    linear_r2: diagnostics.linear_r2,
                    det: diagnostics.config_to_latent_det,
                }
            }
        };
        let result = evaluate_task(&run, name, *seed, task_sets, trained)?;
        crate::fsutil::write_json(&run.dir.join(TASK_RESULT), &result)?;
        if work == GridWork::TrainMissing {
            let line = serde_json::to_string(&result)
                .map_err(|e| Error::config("ablation", e.to_string()))?;
            crate::fsutil::append_line(&jsonl, "", &line)?;
        }
        log(&result);
        done.push(result);
    }
    let order: Vec<&String> = configs.iter().map(|(n, _)| n).collect();
    done.retain(|r| order.contains(&&r.cell));
    done.sort_by_key(|r| (order.iter().position(|n| *n == &r.cell), r.seed));
    if !matches!(work, GridWork::Task(_)) {
        write_summary(out, &done, &order, protocol)?;
    }
    Ok(done)
}

/// What a trained run's result keeps whatever it is evaluated on.
struct Trained {
    train_seconds: f64,
    linear_r2: f64,
    det: Option<f64>,
}

impl From<CellResult> for Trained {
    fn from(result: CellResult) -> Self {
        Self {
            train_seconds: result.train_seconds,
            linear_r2: result.linear_r2,
            det: result.det,
        }
    }
}

/// The result of the `trained` run evaluated on every protocol of `task_sets`.
fn evaluate_task(
    run: &RunPaths,
    name: &str,
    seed: u64,
    task_sets: &[ReachConfig],
    trained: Trained,
) -> Result<CellResult> {
    // The first set last, so that the run's eval.json is its report.
    let mut reports = task_sets
        .iter()
        .rev()
        .map(|set| evaluate_run(run, set, |_| {}))
        .collect::<Result<Vec<_>>>()?;
    reports.reverse();
    let mean = |value: &dyn Fn(&crate::eval::ReachReport) -> f64| {
        reports.iter().map(value).sum::<f64>() / reports.len() as f64
    };
    Ok(CellResult {
        cell: name.to_string(),
        seed,
        success_rate: mean(&|r| r.methods[0].success_rate),
        success_per_task_set: reports.iter().map(|r| r.methods[0].success_rate).collect(),
        final_mean: mean(&|r| r.methods[0].final_mean),
        linear_r2: trained.linear_r2,
        det: trained.det,
        oracle_success_rate: mean(&|r| r.methods.get(1).map_or(f64::NAN, |m| m.success_rate)),
        train_seconds: trained.train_seconds,
        task_sets: task_sets.to_vec(),
    })
}

/// How a result's task sets read in a message: "2 sets of 200 episodes of 500 steps".
fn describe_task_sets(sets: &[ReachConfig]) -> String {
    match sets.first() {
        None => "task sets it does not record".to_string(),
        Some(first) => format!(
            "{} set{} of {} episodes of {} steps",
            sets.len(),
            if sets.len() == 1 { "" } else { "s" },
            first.episodes,
            first.horizon
        ),
    }
}

/// The run folder of cell `name`, seed `seed`.
fn task_dir(out: &Path, name: &str, seed: u64) -> PathBuf {
    out.join(name).join(format!("seed-{seed}"))
}

/// The results already in `out`: each task's `result.json`, which holds its latest
/// evaluation, and the lines of `jsonl` for tasks without one (results merged from elsewhere;
/// a later line for the same task replaces an earlier one). A line cut short by a crash is
/// skipped (its task's `result.json`, written atomically, still counts); a malformed
/// `result.json` is refused by name.
pub(crate) fn read_results(
    out: &Path,
    jsonl: &Path,
    tasks: &[(String, u64)],
) -> Result<Vec<CellResult>> {
    let mut done: Vec<CellResult> = vec![];
    for result in std::fs::read_to_string(jsonl)
        .unwrap_or_default()
        .lines()
        .filter_map(|l| serde_json::from_str::<CellResult>(l).ok())
    {
        done.retain(|r| !(r.cell == result.cell && r.seed == result.seed));
        done.push(result);
    }
    for (name, seed) in tasks {
        let path = task_dir(out, name, *seed).join(TASK_RESULT);
        if !path.exists() {
            continue;
        }
        let text = std::fs::read_to_string(&path).map_err(|e| Error::io(&path, e))?;
        let result: CellResult = serde_json::from_str(&text)
            .map_err(|e| Error::config(path.display().to_string(), e.to_string()))?;
        done.retain(|r| !(&r.cell == name && r.seed == *seed));
        done.push(result);
    }
    Ok(done)
}

fn write_summary(
    out: &Path,
    results: &[CellResult],
    order: &[&String],
    protocol: &ReachConfig,
) -> Result<PathBuf> {
    let json_path = out.join("ablation.json");
    crate::fsutil::write_json(&json_path, results)?;
    // Read from the results, not the command line: the seeds asked for were evaluated on the
    // requested task sets (or refused), but results of other seeds in the folder are reported
    // as they were evaluated.
    let set_counts = results.iter().map(|r| r.success_per_task_set.len().max(1));
    let (fewest, most) = set_counts.fold((usize::MAX, 0), |(lo, hi), n| (lo.min(n), hi.max(n)));
    let sets = match (fewest, most) {
        (_, 0 | 1) => String::new(),
        (lo, hi) if lo == hi => format!(" on each of {hi} task sets; min-max over seeds and sets"),
        (lo, hi) => format!(" on {lo} to {hi} task sets; min-max over seeds and sets"),
    };
    let mut md = format!(
        "# Ablation\n\n{} episodes per seed{sets}, {} steps, success = final distance < {} {}.\n\n\
         | cell | seeds | success mean | success min-max | final distance | R^2 | det(q->h) > 0 | train s |\n|---|---|---|---|---|---|---|---|\n",
        protocol.episodes, protocol.horizon, protocol.success_threshold, protocol.distance_unit
    );
    for name in order {
        let rows: Vec<&CellResult> = results.iter().filter(|r| &&r.cell == name).collect();
        if rows.is_empty() {
            continue;
        }
        let n = rows.len() as f64;
        let mean = |f: &dyn Fn(&CellResult) -> f64| rows.iter().map(|r| f(r)).sum::<f64>() / n;
        // Each seed's success on every task set (a result without per-set figures carries
        // only its mean).
        let each = || {
            rows.iter()
                .flat_map(|r| match r.success_per_task_set.as_slice() {
                    [] => vec![r.success_rate],
                    sets => sets.to_vec(),
                })
        };
        let min = each().fold(f64::MAX, f64::min);
        let max = each().fold(f64::MIN, f64::max);
        let positive = rows
            .iter()
            .filter(|r| r.det.is_some_and(|d| d > 0.0))
            .count();
        md.push_str(&format!(
            "| {name} | {} | {:.1}% | {:.1}-{:.1}% | {:.4} | {:.3} | {positive}/{} | {:.0} |\n",
            rows.len(),
            100.0 * mean(&|r| r.success_rate),
            100.0 * min,
            100.0 * max,
            mean(&|r| r.final_mean),
            mean(&|r| r.linear_r2),
            rows.len(),
            mean(&|r| r.train_seconds),
        ));
    }
    let md_path = out.join("ablation.md");
    crate::write_atomically(&md_path, true, |w| {
        w.write_all(md.as_bytes())
            .map_err(|e| Error::io(&md_path, e))
    })?;
    Ok(md_path)
}
