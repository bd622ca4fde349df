//! Training: the loop every method shares (ProCL, PC3, NewtonianVAE) with seeded batches,
//! per-term metrics, atomic checkpoints, `--resume`, and a clean stop on a non-finite loss.

mod batches;
pub mod checkpoint;
mod config;
mod nvae;
pub mod orientation;
mod run_folder;

pub use batches::loss_inputs;
pub(crate) use batches::{normal_tensor, step_rng};
pub(crate) use config::merge;
pub use config::{
    ConfigBase, Method, Preset, Recipe, TrainConfig, config_from_table, config_from_toml,
    read_config_table, training_budget,
};
pub use nvae::{EpisodeSplit, PlateauRule, WindowFrames, window_frames};
pub use run_folder::{DataRecord, RunPaths, TrainedModel};

use std::io::Write;
use std::ops::ControlFlow;
use std::path::Path;
use std::time::Instant;

use burn::module::Module;
use burn::tensor::{Device, Tensor};

use crate::data::{Dataset, PixelSpread};
use crate::error::{Error, Result};
use crate::losses::{LOSS_NAMES, StepValues, procl_loss};
use crate::model::{HostBackward, ProclModel};
use crate::train::checkpoint::{Adam, CheckpointMeta, load_checkpoint, save_checkpoint};
use crate::train::orientation::{LatentOrienter, WindowRule};
use batches::scale_frames;
use nvae::NvaeObjective;

/// How a run ended.
#[derive(Debug, Clone)]
pub struct TrainSummary {
    pub steps_done: u64,
    pub last: Option<StepValues>,
    pub seconds: f64,
}

/// What one method brings to the shared training loop ([`run_training`]): its model, its loss
/// and what happens around the optimiser step.
pub(crate) trait Objective {
    type Model: Module;
    /// metrics.csv's columns between `step` and `seconds`; the first is the total.
    const METRICS: &'static [&'static str];
    /// Prepares a freshly initialised (not resumed) model.
    fn prepare(&mut self, model: Self::Model) -> Self::Model {
        model
    }
    /// The loss to minimise at step `step` (0-based), its logged values and what the host
    /// computed outside burn's graph (the encoder trunk's tape, host gradients).
    fn loss(&mut self, model: &Self::Model, step: u64) -> (Tensor<1>, StepValues, HostBackward);
    /// Runs after the optimiser update of step `step` (0-based).
    fn after_update(&mut self, model: Self::Model, _step: u64) -> Result<Self::Model> {
        Ok(model)
    }
    /// Runs once before the first step: `resumed_at` is the checkpoint's step when resuming.
    fn begin(&mut self, _resumed_at: Option<u64>) -> Result<()> {
        Ok(())
    }
    /// After step `step` (0-based) and its update: true when the method's stopping rule ends
    /// the run there.
    fn stop_after(&mut self, _model: &Self::Model, _step: u64) -> Result<bool> {
        Ok(false)
    }
}

/// ProCL and PC3: the losses of [`procl_loss`], the latent-scale initialisation and the
/// orientation search.
struct ProclObjective<'a> {
    config: &'a TrainConfig,
    data: &'a Dataset,
    run: &'a RunPaths,
    device: &'a Device,
    search: Option<LatentOrienter>,
}

impl Objective for ProclObjective<'_> {
    type Model = ProclModel;
    const METRICS: &'static [&'static str] = &LOSS_NAMES;

    fn prepare(&mut self, mut model: ProclModel) -> ProclModel {
        model.encoder = model
            .encoder
            .place_polar_frame(|| PixelSpread::of_frames(self.data.every_frame()))
            .place_moving_cut(|| self.data.every_frame());
        if let Some(target_std) = self.config.model.encoder.init_latent_std
            && target_std > 0.0
        {
            let frames = scale_frames(self.data, self.config.seed, self.device);
            model.encoder = model.encoder.normalise_latent_scale(frames, target_std);
        }
        model
    }

    fn loss(&mut self, model: &ProclModel, step: u64) -> (Tensor<1>, StepValues, HostBackward) {
        let dt = self.data.meta.control_dt_s;
        let (inputs, trunk) = loss_inputs(model, self.data, self.config, step, self.device);
        if let Some(search) = self.search.as_mut() {
            search.observe(&inputs, &self.config.loss, dt);
        }
        let terms = procl_loss(&self.config.loss, &model.dynamics, inputs, dt);
        (terms.total.clone(), terms.values().into(), trunk.into())
    }

    fn after_update(&mut self, model: ProclModel, step: u64) -> Result<ProclModel> {
        let turn = orientation_window_end(self.search.as_mut(), self.config, self.run, step)?;
        Ok(match turn {
            Some(flip) => model.reorient_latent(&flip),
            None => model,
        })
    }
}

/// After step `step` (0-based): where an orientation window ends there, the reorientation
/// `h -> p h` its evidence asks for (logged in the run folder), if any.
fn orientation_window_end(
    search: Option<&mut LatentOrienter>,
    config: &TrainConfig,
    run: &RunPaths,
    step: u64,
) -> Result<Option<Vec<f32>>> {
    let Some(search) = search else {
        return Ok(None);
    };
    if !(step + 1).is_multiple_of(config.orientation_search_every) {
        return Ok(None);
    }
    let rule = WindowRule {
        margin: config.orientation_margin,
        streak: config.orientation_streak,
        tolerance: config.orientation_tolerance,
    };
    search.end_window(&run.dir, step + 1, rule)
}

/// Trains `config` on `data` into the run folder `run`. With `resume`, continues from the
/// folder's checkpoint (same config required). `progress(step, values)` is called every step.
pub fn train(
    config: &TrainConfig,
    data: &Dataset,
    run: &RunPaths,
    resume: bool,
    device: &Device,
    mut progress: impl FnMut(u64, &StepValues),
) -> Result<TrainSummary> {
    train_interruptible(config, data, run, resume, device, |step, values| {
        progress(step, values);
        ControlFlow::Continue(())
    })
}

/// As [`train`], stopping when `progress` breaks: after that step (and its checkpoint, if one
/// falls on it) with [`Error::Interrupted`], which names the checkpoint `--resume` continues
/// from. A resumed run gives the same weights as one never stopped.
pub fn train_interruptible(
    config: &TrainConfig,
    data: &Dataset,
    run: &RunPaths,
    resume: bool,
    device: &Device,
    mut progress: impl FnMut(u64, &StepValues) -> ControlFlow<()>,
) -> Result<TrainSummary> {
    config.validate()?;
    if data.meta.env != config.env {
        return Err(Error::config(
            "env",
            format!(
                "the dataset is from {}, the config is for {}",
                data.meta.source_name(),
                crate::envs::source_name(config.env)
            ),
        ));
    }
    let (latent_field, latent_dim) = match &config.nvae {
        Some(nvae) => ("nvae.latent_dim", nvae.latent_dim),
        None => ("model.encoder.latent_dim", config.model.encoder.latent_dim),
    };
    if latent_dim != data.action_dim() {
        return Err(Error::config(
            latent_field,
            format!(
                "{latent_dim} must equal the dataset's action dimension {} (PD control drives one latent coordinate per action)",
                data.action_dim()
            ),
        ));
    }
    if (config.control_dt_s() - data.meta.control_dt_s).abs() > 1e-12 * data.meta.control_dt_s {
        return Err(Error::config(
            "control_dt_s",
            format!(
                "{} s differs from the dataset's {} s",
                config.control_dt_s(),
                data.meta.control_dt_s
            ),
        ));
    }
    let horizon = config.loss.frames_ahead();
    if config.loss.reads_action_response() && horizon + 1 > data.steps() {
        return Err(Error::config(
            "loss.action_response_horizon",
            format!(
                "{horizon} steps do not fit after a step t >= 1 in the dataset's episodes of {} steps",
                data.steps()
            ),
        ));
    }
    let record = DataRecord::of(data);
    let device = &device.clone().autodiff();
    match &config.nvae {
        Some(nvae) => {
            let model = nvae.init(config.seed, device)?;
            let search = (config.orientation_search_every > 0)
                .then(|| LatentOrienter::new(config.orientation_criterion, data.action_dim()));
            let objective = NvaeObjective::new(config, nvae, data, run, device, search)?;
            run_training(
                objective,
                model,
                config,
                run,
                &record,
                resume,
                device,
                &mut progress,
            )
        }
        None => {
            let model = config.model.init(config.seed, device)?;
            let objective = ProclObjective {
                config,
                data,
                run,
                device,
                search: (config.orientation_search_every > 0)
                    .then(|| LatentOrienter::new(config.orientation_criterion, data.action_dim())),
            };
            run_training(
                objective,
                model,
                config,
                run,
                &record,
                resume,
                device,
                &mut progress,
            )
        }
    }
}

/// The loop every method shares: run folder and `--resume`, Adam, one metrics.csv row per
/// step, a checkpoint every `checkpoint_every` steps and at the end, and a clean stop on a
/// non-finite loss that keeps the last good checkpoint.
#[allow(clippy::too_many_arguments)]
fn run_training<O: Objective>(
    mut objective: O,
    mut model: O::Model,
    config: &TrainConfig,
    run: &RunPaths,
    record: &DataRecord,
    resume: bool,
    device: &Device,
    progress: &mut dyn FnMut(u64, &StepValues) -> ControlFlow<()>,
) -> Result<TrainSummary> {
    let mut adam = Adam::default();
    let mut start = 0;
    let _writer = crate::fsutil::FolderLock::acquire(&run.dir)?;
    if resume {
        let saved = run.load_config()?;
        // A larger budget trains the run on (nothing in training depends on the total); any
        // other change would train another model from this one's weights.
        let budget_aside = TrainConfig {
            steps: config.steps,
            ..saved.clone()
        };
        if &budget_aside != config {
            return Err(Error::config(
                "resume",
                format!(
                    "{} differs from this run's configuration",
                    run.config().display()
                ),
            ));
        }
        run.check_same_data(record)?;
        let (m, a, meta) = load_checkpoint(&run.checkpoint(), model, device)?;
        if meta.stopped_early {
            return Err(Error::config(
                "resume",
                format!(
                    "{} is finished: its stopping rule ended it after step {}",
                    run.dir.display(),
                    meta.step
                ),
            ));
        }
        if config.steps < meta.step {
            return Err(Error::config(
                "steps",
                format!(
                    "{} is below the step {} the run in {} has reached",
                    config.steps,
                    meta.step,
                    run.dir.display()
                ),
            ));
        }
        (model, adam, start) = (m, a, meta.step);
        truncate_metrics(&run.metrics(), start, &metrics_header(O::METRICS))?;
        if saved.steps != config.steps {
            crate::fsutil::write_json(&run.config(), config)?;
        }
    } else {
        if run.checkpoint().exists() {
            return Err(Error::config(
                "out",
                format!(
                    "{} already holds a trained model; pass --resume to continue it, or choose another --out",
                    run.dir.display()
                ),
            ));
        }
        model = objective.prepare(model);
        crate::fsutil::write_json(&run.config(), config)?;
        crate::fsutil::write_json(&run.data_record(), record)?;
        let header = metrics_header(O::METRICS) + "\n";
        std::fs::write(run.metrics(), header).map_err(|e| Error::io(run.metrics(), e))?;
    }
    objective.begin(resume.then_some(start))?;
    let mut metrics = std::fs::OpenOptions::new()
        .append(true)
        .open(run.metrics())
        .map_err(|e| Error::io(run.metrics(), e))?;
    let clock = Instant::now();
    let mut last = None;
    for step in start..config.steps {
        let (total, values, host) = objective.loss(&model, step);
        if !values.is_finite() {
            return Err(Error::Diverged(format!(
                "non-finite loss at step {} ({values}); {}",
                step + 1,
                kept_checkpoint(run, config, step, resume)
            )));
        }
        let mut grads = total.backward();
        host.backward(&mut grads);
        model = adam.step(
            config.learning_rate,
            config.gradient_clip_percentile,
            model,
            &grads,
        );
        model = objective.after_update(model, step)?;
        let row: Vec<String> = values.values.iter().map(|x| format!("{x:.6}")).collect();
        writeln!(
            metrics,
            "{},{},{:.3}",
            step + 1,
            row.join(","),
            clock.elapsed().as_secs_f64()
        )
        .map_err(|e| Error::io(run.metrics(), e))?;
        let flow = progress(step + 1, &values);
        last = Some(values);
        let plateaued = objective.stop_after(&model, step)?;
        // Before the checkpoint: a run killed between the two resumes from the previous
        // checkpoint and writes this snapshot again.
        if config.snapshot_every > 0 && (step + 1).is_multiple_of(config.snapshot_every) {
            save_snapshot(run, step + 1, &model)?;
        }
        if (step + 1) % config.checkpoint_every == 0 || step + 1 == config.steps || plateaued {
            let meta = CheckpointMeta {
                stopped_early: plateaued && step + 1 < config.steps,
                ..CheckpointMeta::at(step + 1)
            };
            save_checkpoint(&run.checkpoint(), &model, Some(&adam), &meta)?;
        }
        if plateaued {
            return Ok(TrainSummary {
                steps_done: step + 1,
                last,
                seconds: clock.elapsed().as_secs_f64(),
            });
        }
        if flow.is_break() && step + 1 < config.steps {
            let has_checkpoint = resume || step + 1 >= config.checkpoint_every;
            return Err(Error::Interrupted(format!(
                "training stopped after step {}; {}{}",
                step + 1,
                kept_checkpoint(run, config, step + 1, resume),
                if has_checkpoint {
                    "; --resume continues from it"
                } else {
                    ""
                }
            )));
        }
    }
    Ok(TrainSummary {
        steps_done: config.steps,
        last,
        seconds: clock.elapsed().as_secs_f64(),
    })
}

/// Keeps the weights after `step` steps in the run's snapshot folder for that step, with the
/// run's `config.json` and `data.json` beside them so that the folder evaluates as a run.
fn save_snapshot<M: Module>(run: &RunPaths, step: u64, model: &M) -> Result<()> {
    let snapshot = run.snapshot(step);
    std::fs::create_dir_all(&snapshot.dir).map_err(|e| Error::io(&snapshot.dir, e))?;
    for (from, to) in [
        (run.config(), snapshot.config()),
        (run.data_record(), snapshot.data_record()),
    ] {
        std::fs::copy(&from, &to).map_err(|e| Error::io(&to, e))?;
    }
    save_checkpoint(
        &snapshot.checkpoint(),
        model,
        None,
        &CheckpointMeta::at(step),
    )
}

/// What a run stopped after `steps_done` steps keeps: its last periodic checkpoint, the one it
/// resumed from, or nothing yet.
fn kept_checkpoint(run: &RunPaths, config: &TrainConfig, steps_done: u64, resume: bool) -> String {
    match (steps_done / config.checkpoint_every) * config.checkpoint_every {
        0 if !resume => "no checkpoint was written yet".to_string(),
        0 => format!("the checkpoint in {} is kept", run.checkpoint().display()),
        good => format!(
            "the last good checkpoint (step {good}) is kept in {}",
            run.checkpoint().display()
        ),
    }
}

/// metrics.csv's first line for a method logging `terms`.
fn metrics_header(terms: &[&str]) -> String {
    format!("step,{},seconds", terms.join(","))
}

/// Drops the metric rows after `step` (written after the last checkpoint by a run that then
/// stopped), so a resumed run's `metrics.csv` has each step once, and brings the header up to
/// `header`.
fn truncate_metrics(path: &Path, step: u64, header: &str) -> Result<()> {
    let text = std::fs::read_to_string(path).map_err(|e| Error::io(path, e))?;
    let mut lines = text.lines();
    let old_header = lines.next().unwrap_or(header);
    // A run started by an older procl has fewer columns: its rows are carried over by column
    // name, with the columns it did not log left empty, so every row matches the header.
    // `sources[j]`: the old column of the header's column `j`; `None` when the headers agree.
    let sources: Option<Vec<Option<usize>>> = (old_header != header).then(|| {
        let old_columns: Vec<&str> = old_header.split(',').collect();
        header
            .split(',')
            .map(|name| old_columns.iter().position(|c| *c == name))
            .collect()
    });
    let carry = |line: &str| -> String {
        let Some(sources) = &sources else {
            return line.to_string();
        };
        let fields: Vec<&str> = line.split(',').collect();
        sources
            .iter()
            .map(|k| k.and_then(|k| fields.get(k)).copied().unwrap_or(""))
            .collect::<Vec<_>>()
            .join(",")
    };
    let kept: Vec<String> = std::iter::once(header.to_string())
        .chain(
            lines
                .filter(|line| {
                    line.split(',')
                        .next()
                        .and_then(|s| s.parse::<u64>().ok())
                        .is_some_and(|s| s <= step)
                })
                .map(carry),
        )
        .collect();
    let body = kept.join("\n") + "\n";
    crate::write_atomically(path, true, |w| {
        w.write_all(body.as_bytes()).map_err(|e| Error::io(path, e))
    })
}

/// `transitions` random-control transitions of `env` in episodes of 20 steps (unit tests).
#[cfg(test)]
pub(crate) fn tiny_dataset(env: crate::envs::EnvKind, seed: u64, transitions: usize) -> Dataset {
    let config = crate::data::CollectConfig {
        transitions,
        episode_len: 20,
        ..crate::data::CollectConfig::new(env, seed)
    };
    crate::data::collect(&config, |_| {}).expect("collect")
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::envs::EnvKind;

    #[test]
    fn resumed_metrics_keep_steps_up_to_the_checkpoint_under_the_current_header() {
        let dir = tempfile::tempdir().expect("tempdir");
        let path = dir.path().join("metrics.csv");
        let header = metrics_header(&LOSS_NAMES);
        // Written by a procl that logged five terms; step 3 came after the last checkpoint.
        let old = "step,total,cpc,cons,curv,lyap,seconds\n\
                   1,5,1,2,0,0.5,1.5\n2,4,1,1.5,0,0.4,3\n3,3,1,1,0,0.3,4.5\n";
        std::fs::write(&path, old).expect("write");
        truncate_metrics(&path, 2, &header).expect("truncate");
        let text = std::fs::read_to_string(&path).expect("read");
        assert_eq!(
            text,
            "step,total,cpc,cons,curv,lyap,sign,seconds\n\
             1,5,1,2,0,0.5,,1.5\n2,4,1,1.5,0,0.4,,3\n"
        );
        // Under the current header rows are kept as they are.
        truncate_metrics(&path, 1, &header).expect("truncate again");
        let text = std::fs::read_to_string(&path).expect("read");
        assert_eq!(text, format!("{header}\n1,5,1,2,0,0.5,,1.5\n"));
    }

    #[test]
    fn action_response_horizon_is_checked_by_name() {
        let mut config = TrainConfig::preset(Preset::Procl, Method::Procl, EnvKind::Reacher);
        config.loss.action_response_horizon = 0;
        let err = config.validate().unwrap_err().to_string();
        assert!(err.contains("loss.action_response_horizon"), "{err}");
        // A horizon longer than the dataset's episodes is refused before training starts.
        let data = tiny_dataset(EnvKind::Reacher, 1, 40);
        config.loss.action_response_horizon = 20;
        let dir = std::env::temp_dir().join(format!("procl-horizon-{}", std::process::id()));
        let device = crate::model::cpu_device();
        let err = train(
            &config,
            &data,
            &RunPaths::new(&dir),
            false,
            &device,
            |_, _| {},
        )
        .unwrap_err()
        .to_string();
        assert!(err.contains("loss.action_response_horizon"), "{err}");
        assert!(!dir.exists(), "nothing is written for a refused config");
    }
}
