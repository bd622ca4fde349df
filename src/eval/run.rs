//! Evaluating a trained run folder: latent PD and the oracle on the same tasks, written as
//! `eval.json`, `reach.png`, `latent_traj.png` and `episode.gif` beside the weights.

use std::path::PathBuf;

use burn::tensor::Device;

use super::plots::{save_episode_gif, save_latent_plot, save_reach_plot};
use super::reach::{
    EpisodeRecord, MethodSummary, ReachConfig, ReachReport, evaluate_reach, summarise,
};
use crate::baselines::ilqr::{IlqrMpc, IlqrPolicy};
use crate::baselines::mpc::{CemMpc, MpcConfig, MpcPolicy};
use crate::baselines::nvae::LatentPidPolicy;
use crate::control::{
    FeedbackLaw, LatentPdPolicy, LatentPolicy, OraclePdPolicy, PdController, Pid, PidController,
    Policy, oracle_gains,
};
use crate::envs::EnvConfig;
use crate::error::{Error, Result};
use crate::model::{LatentEncoder, cpu_device};
use crate::train::{RunPaths, TrainConfig, TrainedModel};

/// The latent map [`write_diagnostics`] draws into a run folder.
pub const LATENT_MAP: &str = "latent_map.png";

/// Output files of an evaluation.
pub struct EvalOutputs {
    pub json: PathBuf,
    pub reach_png: PathBuf,
    pub latent_png: PathBuf,
    pub gif: PathBuf,
}

impl EvalOutputs {
    /// The files of the run's own controller's evaluation (latent PD, or PID for nvae).
    pub fn in_run(run: &RunPaths) -> Self {
        Self::for_controller(run, &Controller::Feedback)
    }

    /// The files of `controller`'s evaluation: the run's feedback law writes `eval.json`, ...,
    /// MPC `eval-mpc.json`, ..., so evaluating one never overwrites the other.
    pub fn for_controller(run: &RunPaths, controller: &Controller) -> Self {
        let suffix = match controller {
            Controller::Feedback => "",
            Controller::Mpc(_) => "-mpc",
            Controller::Ilqr(_) => "-ilqr",
            Controller::Proportional => "-p",
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
    /// The run's own feedback law (see [`run_policy`]): PD with the training config's gains
    /// (ProCL, PC3), PID on the posterior mean (NewtonianVAE).
    Feedback,
    /// CEM-MPC through the learned dynamics `g` (the run-time cost reference; ProCL and PC3).
    Mpc(MpcConfig),
    /// iLQR-MPC through `g`, PC3's own controller (ProCL and PC3).
    Ilqr(crate::baselines::ilqr::IlqrConfig),
    /// P control on the NewtonianVAE's posterior mean, its paper's controller: the run's PID
    /// with `Ki = Kd = 0`.
    Proportional,
}

/// A latent policy of any feedback law and encoder, as the evaluations drive it.
pub trait RunPolicy: Policy {
    /// The encoder the policy sees frames through (tracking encodes its references with it).
    fn encoder(&self) -> &dyn LatentEncoder;
    /// The wall time of every `act` so far, seconds, handed over.
    fn take_control_times(&mut self) -> Vec<f64>;
}

impl<L: FeedbackLaw, E: LatentEncoder> RunPolicy for LatentPolicy<L, E> {
    fn encoder(&self) -> &dyn LatentEncoder {
        LatentPolicy::<L, E>::encoder(self)
    }
    fn take_control_times(&mut self) -> Vec<f64> {
        std::mem::take(&mut self.control_times_s)
    }
}

/// The run's own controller on its latent, its label (`ProCL + PD`, `PC3 + PD`,
/// `NewtonianVAE + PID`) and the `dt` of its latent velocity `v = (h_t - h_{t-1}) / dt`.
pub fn run_policy(
    config: &TrainConfig,
    model: TrainedModel,
    device: Device,
) -> Result<(String, f64, Box<dyn RunPolicy>)> {
    let env_dt = config.control_dt_s();
    let label = config.method.label();
    match (model, &config.nvae) {
        (TrainedModel::Procl(model), _) => {
            let pd = PdController {
                kp: config.loss.kp,
                kd: config.loss.kd,
            };
            let policy = LatentPdPolicy::new(model.encoder, device, pd, env_dt);
            Ok((format!("{label} + PD"), env_dt, Box::new(policy)))
        }
        (TrainedModel::Nvae(model), _) => {
            let (gains, dt) = nvae_control(config)?;
            let policy = LatentPidPolicy::new(model.encoder, device, Pid::new(gains, dt), dt);
            Ok((format!("{label} + PID"), dt, Box::new(policy)))
        }
    }
}

/// A NewtonianVAE run's PID gains and the `dt` of its latent velocity.
fn nvae_control(config: &TrainConfig) -> Result<(PidController, f64)> {
    let nvae = config.nvae.as_ref().ok_or_else(|| {
        Error::config(
            "nvae",
            "a NewtonianVAE model needs its [nvae] configuration",
        )
    })?;
    Ok((nvae.pid, nvae.dt(config.control_dt_s())))
}

/// Computes the latent diagnostics of a trained run and writes `latent_map.png` and
/// `diagnostics.json` into its folder; `None` for a run on custom data, whose true states
/// procl cannot sweep.
pub fn write_diagnostics(run: &RunPaths) -> Result<Option<super::latent_map::LatentDiagnostics>> {
    let device = cpu_device();
    let (config, model) = run.load_trained(&device)?;
    let Some(env) = run.recorded_simulator(&config)? else {
        return Ok(None);
    };
    let png = run.dir.join(LATENT_MAP);
    let encoder: &dyn LatentEncoder = match &model {
        TrainedModel::Procl(model) => &model.encoder,
        TrainedModel::Nvae(model) => &model.encoder,
    };
    let diagnostics = super::latent_map::latent_diagnostics(&env, encoder, &device, Some(&png))?;
    let path = run.dir.join("diagnostics.json");
    crate::fsutil::write_json(&path, &diagnostics)?;
    Ok(Some(diagnostics))
}

/// [`write_diagnostics`] for a run of one of procl's environments (an error for custom data).
pub fn write_env_diagnostics(run: &RunPaths) -> Result<super::latent_map::LatentDiagnostics> {
    write_diagnostics(run)?.ok_or_else(|| {
        Error::config(
            "env",
            format!(
                "{} holds a run on custom data, which has no latent diagnostics",
                run.dir.display()
            ),
        )
    })
}

/// Evaluates the oracle PD on the true state for `protocol`.
pub fn evaluate_oracle(env: &EnvConfig, protocol: &ReachConfig) -> Result<MethodSummary> {
    let gains = oracle_gains(env.kind());
    let records = evaluate_reach(
        env,
        protocol,
        &mut OraclePdPolicy::new(gains),
        false,
        |_| {},
    )?;
    Ok(summarise("oracle PD (true state)", &records, protocol, &[]))
}

/// Runs the run's own controller (latent PD with the gains of its `config.json`, or PID for a
/// NewtonianVAE) and the oracle on the same tasks, and writes the outputs into the run folder.
pub fn evaluate_run(
    run: &RunPaths,
    protocol: &ReachConfig,
    progress: impl FnMut(usize),
) -> Result<ReachReport> {
    evaluate_run_with(run, protocol, &Controller::Feedback, progress)
}

/// The reach episodes of a planner's policy, and its control times.
fn reach_with<L: FeedbackLaw, E: LatentEncoder>(
    env: &EnvConfig,
    protocol: &ReachConfig,
    mut policy: LatentPolicy<L, E>,
    progress: &mut impl FnMut(usize),
) -> Result<(Vec<EpisodeRecord>, Vec<f64>)> {
    let records = evaluate_reach(env, protocol, &mut policy, true, progress)?;
    Ok((records, policy.control_times_s))
}

/// As [`evaluate_run`] with the given controller on the latent.
pub fn evaluate_run_with(
    run: &RunPaths,
    protocol: &ReachConfig,
    controller: &Controller,
    mut progress: impl FnMut(usize),
) -> Result<ReachReport> {
    let device = cpu_device();
    let (config, model) = run.load_trained(&device)?;
    let sim = run.simulator(&config)?;
    let env = sim.kind();
    let (label, records, times) = match (controller, model) {
        (Controller::Feedback, model) => {
            let (label, _, mut policy) = run_policy(&config, model, device)?;
            let records = evaluate_reach(&sim, protocol, policy.as_mut(), true, &mut progress)?;
            (label, records, policy.take_control_times())
        }
        (Controller::Mpc(mpc), TrainedModel::Procl(model)) => {
            let dt = sim.make().control_dt_s();
            let law = CemMpc::new(model.dynamics, device.clone(), mpc.clone(), dt)?;
            let policy = MpcPolicy::new(model.encoder, device, law, dt);
            let (records, times) = reach_with(&sim, protocol, policy, &mut progress)?;
            (format!("{} + MPC", config.method.label()), records, times)
        }
        (Controller::Ilqr(ilqr), TrainedModel::Procl(model)) => {
            let dt = sim.make().control_dt_s();
            let law = IlqrMpc::new(model.dynamics, device.clone(), ilqr.clone(), dt)?;
            let policy = IlqrPolicy::new(model.encoder, device, law, dt);
            let (records, times) = reach_with(&sim, protocol, policy, &mut progress)?;
            (format!("{} + iLQR", config.method.label()), records, times)
        }
        (Controller::Proportional, TrainedModel::Nvae(model)) => {
            let (pid, dt) = nvae_control(&config)?;
            let gains = PidController {
                ki: 0.0,
                kd: 0.0,
                ..pid
            };
            let policy = LatentPidPolicy::new(model.encoder, device, Pid::new(gains, dt), dt);
            let (records, times) = reach_with(&sim, protocol, policy, &mut progress)?;
            (format!("{} + P", config.method.label()), records, times)
        }
        (Controller::Proportional, TrainedModel::Procl(_)) => {
            return Err(Error::config(
                "controller",
                format!(
                    "P control is the NewtonianVAE's; {} is a {} run, evaluated with its PD (leave out --controller)",
                    run.dir.display(),
                    config.method.label()
                ),
            ));
        }
        (Controller::Mpc(_) | Controller::Ilqr(_), TrainedModel::Nvae(_)) => {
            return Err(Error::config(
                "controller",
                format!(
                    "MPC plans through ProCL's and PC3's learned dynamics; {} is a NewtonianVAE run, evaluated with its PID (leave out --controller)",
                    run.dir.display()
                ),
            ));
        }
    };
    let label = label.as_str();
    let latent = summarise(label, &records, protocol, &times);
    let oracle = evaluate_oracle(&sim, protocol)?;
    let report = ReachReport {
        env,
        env_config: (!sim.is_default()).then_some(sim),
        protocol: protocol.clone(),
        methods: vec![latent, oracle],
    };
    let out = EvalOutputs::for_controller(run, controller);
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
    // Last, so that an evaluation interrupted while plotting is not taken for a finished one.
    crate::fsutil::write_json(&out.json, &report)?;
    Ok(report)
}
