//! Evaluating a trained run folder: latent PD and the oracle on the same tasks, written as
//! `eval.json`, `reach.png`, `latent_traj.png` and `episode.gif` beside the weights.

use std::path::PathBuf;

use super::plots::{save_episode_gif, save_latent_plot, save_reach_plot};
use super::reach::{MethodSummary, ReachConfig, ReachReport, evaluate_reach, summarise};
use crate::control::{
    LatentPdPolicy, MpcConfig, MpcPolicy, OraclePdPolicy, PdController, oracle_gains,
};
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
    /// The files of latent PD's evaluation (the run's own controller).
    pub fn in_run(run: &RunPaths) -> Self {
        Self::for_controller(run, &Controller::Pd)
    }

    /// The files of `controller`'s evaluation: PD writes `eval.json`, ..., MPC `eval-mpc.json`,
    /// ..., so evaluating one never overwrites the other.
    pub fn for_controller(run: &RunPaths, controller: &Controller) -> Self {
        let suffix = match controller {
            Controller::Pd => "",
            Controller::Mpc(_) => "-mpc",
        };
        Self {
            json: run.dir.join(format!("eval{suffix}.json")),
            reach_png: run.dir.join(format!("reach{suffix}.png")),
            latent_png: run.dir.join(format!("latent_traj{suffix}.png")),
            gif: run.dir.join(format!("episode{suffix}.gif")),
        }
    }
}

/// Which controller acts on the learned latent.
#[derive(Debug, Clone, PartialEq)]
pub enum Controller {
    /// PD with the training config's gains (ProCL's controller).
    Pd,
    /// CEM-MPC through the learned dynamics `g` (the run-time cost reference).
    Mpc(MpcConfig),
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
    progress: impl FnMut(usize),
) -> Result<ReachReport> {
    evaluate_run_with(run, protocol, &Controller::Pd, progress)
}

/// As [`evaluate_run`] with the given controller on the latent.
pub fn evaluate_run_with(
    run: &RunPaths,
    protocol: &ReachConfig,
    controller: &Controller,
    mut progress: impl FnMut(usize),
) -> Result<ReachReport> {
    let device = cpu_device();
    let (config, model) = run.load_model(&device)?;
    let env = config.env;
    let dt = env.make().control_dt_s();
    let method = match config.method {
        Method::Procl => "ProCL",
        Method::Pc3 => "PC3",
    };
    let (label, records, times) = match controller {
        Controller::Pd => {
            let pd = PdController {
                kp: config.loss.kp,
                kd: config.loss.kd,
            };
            let mut policy = LatentPdPolicy::new(model.encoder, device, pd, dt);
            let records = evaluate_reach(env, protocol, &mut policy, true, &mut progress)?;
            (format!("{method} + PD"), records, policy.control_times_s)
        }
        Controller::Mpc(mpc) => {
            let mut policy =
                MpcPolicy::new(model.encoder, model.dynamics, device, mpc.clone(), dt)?;
            let records = evaluate_reach(env, protocol, &mut policy, true, &mut progress)?;
            (format!("{method} + MPC"), records, policy.control_times_s)
        }
    };
    let label = label.as_str();
    let latent = summarise(label, &records, protocol, &times);
    let oracle = evaluate_oracle(env, protocol)?;
    let report = ReachReport {
        env,
        protocol: protocol.clone(),
        methods: vec![latent, oracle],
    };
    let out = EvalOutputs::for_controller(run, controller);
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
