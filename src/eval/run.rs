//! Evaluating a trained run folder: latent PD and the oracle on the same tasks, written as
//! `eval.json`, `reach.png`, `latent_traj.png` and `episode.gif` beside the weights.

use std::path::PathBuf;

use super::plots::{save_episode_gif, save_latent_plot, save_reach_plot};
use super::reach::{MethodSummary, ReachConfig, ReachReport, evaluate_reach, summarise};
use crate::control::{LatentPdPolicy, OraclePdPolicy, PdController, oracle_gains};
use crate::error::Result;
use crate::model::cpu_device;
use crate::train::{Method, RunPaths};

/// Output files of an evaluation.
pub struct EvalOutputs {
    pub json: PathBuf,
    pub reach_png: PathBuf,
    pub latent_png: PathBuf,
    pub gif: PathBuf,
}

impl EvalOutputs {
    pub fn in_run(run: &RunPaths) -> Self {
        Self {
            json: run.dir.join("eval.json"),
            reach_png: run.dir.join("reach.png"),
            latent_png: run.dir.join("latent_traj.png"),
            gif: run.dir.join("episode.gif"),
        }
    }
}

/// Computes the latent diagnostics of a trained run and writes `latent_map.png` and
/// `diagnostics.json` into its folder.
pub fn write_diagnostics(run: &RunPaths) -> Result<super::LatentDiagnostics> {
    let device = cpu_device();
    let (config, model) = run.load_model(&device)?;
    let png = run.dir.join("latent_map.png");
    let diagnostics = super::latent_diagnostics(config.env, &model.encoder, &device, Some(&png))?;
    let path = run.dir.join("diagnostics.json");
    crate::fsutil::write_json(&path, &diagnostics)?;
    Ok(diagnostics)
}

/// Evaluates the oracle PD on the true state for `protocol`.
pub fn evaluate_oracle(env: crate::envs::EnvKind, protocol: &ReachConfig) -> Result<MethodSummary> {
    let gains = oracle_gains(env);
    let records = evaluate_reach(
        env,
        protocol,
        &mut OraclePdPolicy::new(gains),
        false,
        |_| {},
    )?;
    Ok(summarise("oracle PD (true state)", &records, protocol, &[]))
}

/// Runs latent PD with the run's gains (its `config.json`) and the oracle on the same tasks,
/// and writes the outputs into the run folder.
pub fn evaluate_run(
    run: &RunPaths,
    protocol: &ReachConfig,
    mut progress: impl FnMut(usize),
) -> Result<ReachReport> {
    let device = cpu_device();
    let (config, model) = run.load_model(&device)?;
    let env = config.env;
    let pd = PdController {
        kp: config.loss.kp,
        kd: config.loss.kd,
    };
    let dt = env.make().control_dt_s();
    let mut policy = LatentPdPolicy::new(model.encoder, device, pd, dt);
    let records = evaluate_reach(env, protocol, &mut policy, true, &mut progress)?;
    let times = std::mem::take(&mut policy.control_times_s);
    let label = match config.method {
        Method::Procl => "ProCL + PD",
        Method::Pc3 => "PC3 + PD",
    };
    let latent = summarise(label, &records, protocol, &times);
    let oracle = evaluate_oracle(env, protocol)?;
    let report = ReachReport {
        env,
        protocol: protocol.clone(),
        methods: vec![latent, oracle],
    };
    let out = EvalOutputs::in_run(run);
    crate::fsutil::write_json(&out.json, &report)?;
    let title = format!("{env}: goal reaching over {} episodes", protocol.episodes);
    save_reach_plot(
        &out.reach_png,
        &title,
        &report.methods,
        protocol.success_threshold,
        &protocol.distance_unit,
    )?;
    save_latent_plot(
        &out.latent_png,
        &format!("{label}: latent trajectories ({env})"),
        &records,
        8,
    )?;
    if let Some(first) = records.first() {
        save_episode_gif(&out.gif, first, 5, 3)?;
    }
    Ok(report)
}
