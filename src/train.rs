//! The training loop every method shares (ProCL, PC3, NewtonianVAE): seeded batches, per-term
//! metrics, atomic checkpoints, `--resume`, and a clean stop on a non-finite loss.

use std::io::Write;
use std::path::{Path, PathBuf};
use std::time::Instant;

use burn::module::Module;
use burn::tensor::{Device, Tensor, TensorData};
use rand::seq::SliceRandom;
use rand::{RngExt, SeedableRng};
use rand_chacha::ChaCha8Rng;

use crate::checkpoint::{Adam, CheckpointMeta, load_checkpoint, save_checkpoint};
use crate::data::Dataset;
use crate::envs::EnvKind;
use crate::error::{Error, Result};
use crate::losses::{LOSS_NAMES, LossConfig, LossInputs, LossValues, NoiseMode, procl_loss};
use crate::model::{DynamicsInput, EncoderHead, ModelConfig, ProclModel, frames_to_tensor};
use crate::nvae::{NvaeConfig, NvaeModel, NvaeObjective};
use crate::orientation::{LatentOrienter, OrientationCriterion, WindowRule};

/// Which objective to train.
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum Method {
    /// PC3 losses plus the latent PD-control Lyapunov risk.
    Procl,
    /// PC3 alone: the same networks with `lambda_R = 0`.
    Pc3,
    /// The NewtonianVAE baseline (its own networks, the `nvae` config table), PID-controlled.
    Nvae,
}

impl Method {
    /// The method's name in reports: ProCL, PC3, NewtonianVAE.
    pub fn label(self) -> &'static str {
        match self {
            Method::Procl => "ProCL",
            Method::Pc3 => "PC3",
            Method::Nvae => "NewtonianVAE",
        }
    }

    /// The method's name on the command line and as a run folder: procl, pc3, nvae.
    pub fn dir_name(self) -> &'static str {
        match self {
            Method::Procl => "procl",
            Method::Pc3 => "pc3",
            Method::Nvae => "nvae",
        }
    }
}

impl std::str::FromStr for Method {
    type Err = Error;
    fn from_str(s: &str) -> Result<Self> {
        match [Method::Procl, Method::Pc3, Method::Nvae]
            .into_iter()
            .find(|m| m.dir_name() == s)
        {
            Some(method) => Ok(method),
            None => Err(Error::config(
                "method",
                format!("unknown method `{s}` (expected procl, pc3 or nvae)"),
            )),
        }
    }
}

/// Named starting points for a configuration (issue 9).
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum Preset {
    /// spec.md sections 3-4 literally: PC3-style MLP encoder head, noise as in the paper.
    Paper,
    /// procl's default: the best design found (docs/method.md).
    Procl,
}

/// The NewtonianVAE's default batch: each sample also decodes its three frames; at 64 a step
/// took 0.6-1.0 s on the shared 2-core machine, about a ProCL step at 128.
const NVAE_BATCH_SIZE: usize = 64;

/// Everything a training run needs; written to the run folder as `config.json`.
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(deny_unknown_fields)]
pub struct TrainConfig {
    pub preset: Preset,
    pub method: Method,
    /// Environment the model is for (checked against the dataset).
    pub env: EnvKind,
    /// Seed of weights, batches and noise.
    pub seed: u64,
    /// Optimiser steps.
    pub steps: u64,
    /// Samples per batch (`K` of the CPC loss).
    pub batch_size: usize,
    /// Adam learning rate.
    pub learning_rate: f64,
    /// Save a checkpoint every this many steps (and at the end).
    pub checkpoint_every: u64,
    /// Every this many steps, choose the latent's orientation from the window's training
    /// batches by `orientation_criterion` (0: off, the paper's training). See
    /// [`crate::model::ProclModel::reorient_latent`]; must divide `checkpoint_every`.
    #[serde(default)]
    pub orientation_search_every: u64,
    /// What the orientation search compares: the Lyapunov risk of the signed permutations
    /// (`risk`, margin and streak below) or the latent's response to the action
    /// (`action-response`, tolerance below).
    #[serde(default)]
    pub orientation_criterion: OrientationCriterion,
    /// `action-response`: rotate when the aligning map is further than this from the identity
    /// (Frobenius norm; a rotation by `a` radians in a plane is at `2 sqrt(2) sin(a/2)`).
    #[serde(default = "default_orientation_tolerance")]
    pub orientation_tolerance: f64,
    /// Ramp `lambda_R` linearly from 0 over this many steps (0: the full weight from step 1,
    /// as the paper). The risk is lowest for a collapsed latent, so while CPC has not yet
    /// spread the latent out, the risk can win the race and collapse it.
    #[serde(default)]
    pub risk_warmup_steps: u64,
    /// The orientation search switches when a candidate's windowed risk is below
    /// `(1 - orientation_margin)` times the current one's ...
    #[serde(default = "default_orientation_margin")]
    pub orientation_margin: f64,
    /// ... and it has been the best candidate for this many consecutive windows (1: decide on
    /// each window alone). For Fetch the candidates' risks differ by only 2-3% per window,
    /// but the same one wins window after window. A streak > 1 is not carried across
    /// `--resume` (the count restarts).
    #[serde(default = "default_orientation_streak")]
    pub orientation_streak: u64,
    /// Draw the batch in groups of this many samples from one stretch of one episode (1: every
    /// sample independent, the paper's). Frames a few steps apart differ a little in every
    /// joint, so as CPC negatives they ask the latent to resolve small moves of each joint,
    /// where independent samples are told apart by the joint that moves the image most.
    #[serde(default = "default_batch_group_size")]
    pub batch_group_size: usize,
    /// The length in steps of that stretch (at least `batch_group_size`; unused at 1).
    #[serde(default)]
    pub batch_group_window: usize,
    /// ProCL's and PC3's losses and networks (unused by `nvae`).
    pub loss: LossConfig,
    pub model: ModelConfig,
    /// The NewtonianVAE's networks, ELBO and PID (method `nvae` only; absent otherwise, so
    /// the config.json of earlier runs still loads and compares equal).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub nvae: Option<NvaeConfig>,
}

fn default_orientation_margin() -> f64 {
    0.1
}

fn default_orientation_streak() -> u64 {
    1
}

fn default_batch_group_size() -> usize {
    1
}

fn default_orientation_tolerance() -> f64 {
    0.05
}

impl TrainConfig {
    /// The loss settings of step `step` (0-based): `lambda_R` ramped over the warm-up.
    pub fn loss_at(&self, step: u64) -> LossConfig {
        let mut loss = self.loss.clone();
        if step < self.risk_warmup_steps {
            loss.lambda_r *= (step + 1) as f64 / self.risk_warmup_steps as f64;
        }
        loss
    }

    /// The configuration of `preset` for `method` on `env`.
    pub fn preset(preset: Preset, method: Method, env: EnvKind) -> Self {
        let du = env.make().action_dim();
        let mut config = Self {
            preset,
            method,
            env,
            seed: 0,
            steps: 3000,
            batch_size: 128,
            learning_rate: 1e-3,
            checkpoint_every: 500,
            orientation_search_every: 0,
            risk_warmup_steps: 0,
            orientation_margin: default_orientation_margin(),
            orientation_streak: default_orientation_streak(),
            orientation_criterion: OrientationCriterion::Risk,
            orientation_tolerance: default_orientation_tolerance(),
            batch_group_size: default_batch_group_size(),
            batch_group_window: 0,
            loss: LossConfig::default(),
            model: ModelConfig::for_action_dim(du),
            nvae: None,
        };
        match preset {
            Preset::Paper => {
                config.model.encoder.head = EncoderHead::Mlp { hidden: 256 };
            }
            Preset::Procl => {
                config.loss.noise_mode = NoiseMode::CleanRisk;
                config.orientation_search_every = 50;
                config.model.encoder.keypoint_sharpness = 30.0;
            }
        }
        match method {
            Method::Procl => {}
            Method::Pc3 => config.loss.lambda_r = 0.0,
            Method::Nvae => {
                config.nvae = Some(NvaeConfig::for_action_dim(du));
                // The search reorients ProCL's latent by its Lyapunov risk; the NewtonianVAE's
                // orientation is the transition prior's business.
                config.orientation_search_every = 0;
                config.batch_size = NVAE_BATCH_SIZE;
            }
        }
        if env == EnvKind::Reacher && preset == Preset::Procl && method != Method::Nvae {
            // The shoulder is a revolute joint at the image centre: keypoints in polar
            // coordinates about it make its angle a latent coordinate (Cartesian keypoints give
            // a ring), a tanh layer after them brings in the wrist, a latent started at unit
            // spread and a variance floor keep it from collapsing, and the action response
            // orients it (the risk search cannot tell the candidates apart here). The risk is
            // computed on the standardised latent (`risk_latent_std = 1`) so it cannot shrink
            // it, with gains that match that scale: the risk is homogeneous of degree 2 in the
            // latent, so `Kp = 1, Kd = 0.2` train the paper's `Kp = 10, Kd = 2` on a latent of
            // std 0.1, while the controller on `h` gets the gains the risk trained for
            // (docs/method.md, Reacher-2D stop 15). `V` has no velocity term (`Q_v = 0`): the
            // wrist's velocity follows the torque within a step, so that term charged the true
            // joint angles ten times a latent with a faint wrist. Without it the risk can weigh
            // ten times more than stop 15's 0.1 (`lambda_R = 1`): 69.5/66.5/74.5% on 3 seeds
            // against 61.5/60/65% (stop 20). The angles between keypoints resolve the folded
            // wrist (the angle from elbow to fingertip is half the wrist angle at any
            // shoulder), entering from 0 so the fresh latent is not curled by a random mix of
            // them, with the angle faded to 0 at the cut so the forearm crossing it does not
            // jump; the keypoints attend over 32x32 cells of the image, which the folded
            // wrist's few pixels need: 74/72/82.5% against 69.5/66.5/74.5% (stop 22), at
            // about twice the training time.
            config.model.encoder.head = EncoderHead::SoftArgmax {
                keypoints: 16,
                hidden: 32,
                polar: true,
                with_cartesian: false,
                pairwise_angles: true,
                linear_base: false,
            };
            config.model.encoder.pairwise_init_scale = 0.0;
            config.model.encoder.polar_cut_fade_deg = 15.0;
            config.model.encoder.trunk_second_stride = 1;
            config.model.encoder.init_latent_std = Some(1.0);
            config.loss.variance_floor = Some(1.0);
            config.loss.variance_weight = 10.0;
            config.orientation_criterion = OrientationCriterion::ActionResponse;
            config.loss.risk_latent_std = Some(1.0);
            config.loss.kp = 1.0;
            config.loss.kd = 0.2;
            config.loss.lambda_r /= 10.0;
            if method == Method::Procl {
                // PC3 has no risk; its config stays the one stop 15 measured.
                config.loss.q_v = 0.0;
                // The latent hooks back at the shoulder's ends, where the action on a latent
                // coordinate moves it backwards and PD pushes away from the goal. The sign term
                // charges negative diagonals of the 5-step response map in six groups along the
                // latent's long axis: 85.5/86/78.5% on 3 seeds against 84.5/81/75% without it
                // (docs/method.md, reacher stop 29). It is a PD-controllability term like the
                // risk, so PC3 does not get it either.
                config.loss.action_response_sign_weight = 3.0;
                config.loss.action_response_horizon = 5;
                config.loss.action_response_velocity = true;
                config.loss.action_response_regions = 6;
                // A group's map may not squash a direction either: its smaller singular value
                // is held above a quarter of the batch's rms drive entry (standardised joint
                // angles sit at 0.33-0.47). Seed 2's near misses ended in a valley where the
                // wrist's response was squashed: 89.5/85/83.5% on seeds 0-2 against 85.5/86/78.5%
                // (docs/method.md, reacher stop 32).
                config.loss.action_response_singular_floor = 0.25;
            }
        }
        if env == EnvKind::Fetch {
            // spec.md 3: dt_R = 1 for Fetch (the env's control dt for the 2D envs).
            config.loss.lyapunov_dt_s = Some(1.0);
            if preset == Preset::Procl {
                // A signed permutation leaves Fetch's latent up to 45 degrees from the gripper
                // axes; the action response measures and removes the whole rotation
                // (docs/method.md, Fetch-3D: 64-84% with the risk search, 94-100% with this).
                config.orientation_criterion = OrientationCriterion::ActionResponse;
                // PD on a latent `h = J p` is stable only where every eigenvalue `r e^{i theta}`
                // of `a_max J` has `r > (Kp / Kd^2) sin^2 theta / cos theta`: a latent turned
                // against the gripper axes, or short along one, orbits its goal. At Kd = 2 (Kp
                // = 10) 40 of seed 1's 45 failures still moved after 250 steps; at Kd = 4 the
                // bound is 4 times lower (docs/method.md, Fetch stop 25: 95.5% -> 99.5%).
                config.loss.kd = 4.0;
            }
        }
        config
    }

    /// Rejects invalid values with the field's name.
    pub fn validate(&self) -> Result<()> {
        if self.steps == 0 {
            return Err(Error::config("steps", "must be at least 1"));
        }
        let du = self.env.make().action_dim();
        if self.loss.action_response_sign_form == crate::losses::SignForm::Eigenvalues && du != 2 {
            return Err(Error::config(
                "loss.action_response_sign_form",
                format!("eigenvalues needs 2-D actions; {} has {du}", self.env),
            ));
        }
        if !(0.0..1.0).contains(&self.orientation_margin) {
            return Err(Error::config(
                "orientation_margin",
                format!("{} must be in [0, 1)", self.orientation_margin),
            ));
        }
        if !(self.orientation_tolerance.is_finite() && self.orientation_tolerance >= 0.0) {
            return Err(Error::config(
                "orientation_tolerance",
                format!("{} must be >= 0", self.orientation_tolerance),
            ));
        }
        if self.batch_size < 2 && self.method != Method::Nvae {
            return Err(Error::config(
                "batch_size",
                format!(
                    "{} must be at least 2 (CPC needs negatives)",
                    self.batch_size
                ),
            ));
        }
        if self.batch_group_size == 0 || !self.batch_size.is_multiple_of(self.batch_group_size) {
            return Err(Error::config(
                "batch_group_size",
                format!(
                    "{} must be at least 1 and divide batch_size = {}",
                    self.batch_group_size, self.batch_size
                ),
            ));
        }
        if self.batch_group_size > 1 && self.batch_group_window < self.batch_group_size {
            return Err(Error::config(
                "batch_group_window",
                format!(
                    "{} must be at least batch_group_size = {} (distinct steps in a group)",
                    self.batch_group_window, self.batch_group_size
                ),
            ));
        }
        if self.batch_group_size > 1 && self.loss.frames_ahead() > 1 {
            return Err(Error::config(
                "loss.action_response_horizon",
                format!(
                    "{} steps cannot be read from grouped batches (batch_group_size = {}); use 1",
                    self.loss.action_response_horizon, self.batch_group_size
                ),
            ));
        }
        if !(self.learning_rate.is_finite() && self.learning_rate > 0.0) {
            return Err(Error::config(
                "learning_rate",
                format!("{} must be > 0", self.learning_rate),
            ));
        }
        if self.checkpoint_every == 0 {
            return Err(Error::config("checkpoint_every", "must be at least 1"));
        }
        if self.loss.decoder_weight > 0.0 && self.model.feature_decoder_width == 0 {
            return Err(Error::config(
                "loss.decoder_weight",
                format!(
                    "{} needs a feature decoder: set model.feature_decoder_width > 0",
                    self.loss.decoder_weight
                ),
            ));
        }
        if self.loss.stretch_weight > 0.0 && self.model.encoder.keypoint_feature_count().is_none() {
            return Err(Error::config(
                "loss.stretch_weight",
                format!(
                    "{} needs the keypoint head's features: set model.encoder.head.kind = \"soft-argmax\"",
                    self.loss.stretch_weight
                ),
            ));
        }
        if self.orientation_search_every > 0
            && !self
                .checkpoint_every
                .is_multiple_of(self.orientation_search_every)
        {
            return Err(Error::config(
                "orientation_search_every",
                format!(
                    "{} must divide checkpoint_every = {} (so a resumed run searches the same windows)",
                    self.orientation_search_every, self.checkpoint_every
                ),
            ));
        }
        // The action-response search measures the turn the gains have not (yet) fixed and
        // turns the dynamics' input matrix with the latent; the risk search cannot see it.
        if self.orientation_search_every != 0
            && self.orientation_criterion == OrientationCriterion::Risk
            && matches!(
                self.model.dynamics.input,
                DynamicsInput::ConstantDiagonal { .. }
            )
        {
            return Err(Error::config(
                "orientation_search_every",
                "must be 0 with model.dynamics.input constant-diagonal and the risk criterion \
                 (its positive input gains fix the orientation; a risk search could only turn \
                 the latent against them)",
            ));
        }
        if self.method == Method::Pc3 && self.loss.lambda_r != 0.0 {
            return Err(Error::config("loss.lambda_r", "must be 0 for method pc3"));
        }
        let du = self.env.make().action_dim();
        match (&self.nvae, self.method) {
            (Some(nvae), Method::Nvae) => {
                if nvae.latent_dim != du {
                    return Err(Error::config(
                        "nvae.latent_dim",
                        format!("must equal the action dimension {du} of {}", self.env),
                    ));
                }
                if self.orientation_search_every != 0 {
                    return Err(Error::config(
                        "orientation_search_every",
                        "must be 0 for method nvae (the search is ProCL's)",
                    ));
                }
                nvae.validate()?;
            }
            (None, Method::Nvae) => {
                return Err(Error::config("nvae", "method nvae needs its [nvae] table"));
            }
            (Some(_), _) => {
                return Err(Error::config(
                    "nvae",
                    format!("is for method nvae only, not {}", self.method.label()),
                ));
            }
            (None, _) => {}
        }
        if self.model.encoder.latent_dim != du {
            return Err(Error::config(
                "model.encoder.latent_dim",
                format!("must equal the action dimension {du} of {}", self.env),
            ));
        }
        self.loss.validate()?;
        self.model.validate()
    }
}

/// Files of a run folder.
pub struct RunPaths {
    pub dir: PathBuf,
}

impl RunPaths {
    pub fn new(dir: impl Into<PathBuf>) -> Self {
        Self { dir: dir.into() }
    }
    pub fn config(&self) -> PathBuf {
        self.dir.join("config.json")
    }
    pub fn checkpoint(&self) -> PathBuf {
        self.dir.join("model.safetensors")
    }
    pub fn metrics(&self) -> PathBuf {
        self.dir.join("metrics.csv")
    }

    /// Reads the resolved config of a finished or running run.
    pub fn load_config(&self) -> Result<TrainConfig> {
        let path = self.config();
        let text = std::fs::read_to_string(&path).map_err(|e| match e.kind() {
            std::io::ErrorKind::NotFound => Error::config(
                "run",
                format!(
                    "{} not found: is {} a training run?",
                    path.display(),
                    self.dir.display()
                ),
            ),
            _ => Error::io(&path, e),
        })?;
        serde_json::from_str(&text)
            .map_err(|e| Error::config("run", format!("{}: {e}", path.display())))
    }

    /// Rebuilds the trained model, of whichever method, from `config.json` and the checkpoint.
    pub fn load_trained(&self, device: &Device) -> Result<(TrainConfig, TrainedModel)> {
        let config = self.load_config()?;
        let model = match (config.method, &config.nvae) {
            (Method::Nvae, Some(nvae)) => {
                let model = nvae.init(config.seed, device)?;
                TrainedModel::Nvae(load_checkpoint(&self.checkpoint(), model, device)?.0)
            }
            (Method::Nvae, None) => {
                return Err(Error::config(
                    "nvae",
                    format!(
                        "{} has method nvae but no nvae table",
                        self.config().display()
                    ),
                ));
            }
            _ => {
                let model = config.model.init(config.seed, device)?;
                TrainedModel::Procl(load_checkpoint(&self.checkpoint(), model, device)?.0)
            }
        };
        Ok((config, model))
    }

    /// Rebuilds a trained ProCL or PC3 model (the latent with learned dynamics `g`).
    pub fn load_model(&self, device: &Device) -> Result<(TrainConfig, ProclModel)> {
        match self.load_trained(device)? {
            (config, TrainedModel::Procl(model)) => Ok((config, model)),
            (_, TrainedModel::Nvae(_)) => Err(Error::config(
                "run",
                format!(
                    "{} is a NewtonianVAE run; this needs a ProCL or PC3 run",
                    self.dir.display()
                ),
            )),
        }
    }
}

/// A trained model as [`RunPaths::load_trained`] rebuilds it.
// Both variants are a few kB of tensor handles, built once per command: no reason to box.
#[allow(clippy::large_enum_variant)]
pub enum TrainedModel {
    /// ProCL or PC3: encoder and latent dynamics.
    Procl(ProclModel),
    /// The NewtonianVAE.
    Nvae(NvaeModel),
}

/// Frames for the data-dependent latent-scale initialisation: 256 drawn from a stream of
/// `seed` that training batches never use.
fn scale_frames(data: &Dataset, seed: u64, device: &Device) -> Tensor<4> {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    rng.set_stream(u64::MAX);
    let picks = sample_batch(data, &mut rng, 256);
    frames_to_tensor(picks.iter().map(|&(e, t)| data.frame(e, t)), device)
}

/// A training sample `(i_{t-1}, i_t, u_t, i_{t+1})` is addressed by (episode, t), 1 <= t < T.
pub(crate) fn sample_batch(data: &Dataset, rng: &mut ChaCha8Rng, n: usize) -> Vec<(usize, usize)> {
    sample_batch_reaching(data, rng, n, 1)
}

/// Samples whose frame `t + reach` is in the episode too: 1 <= t <= T - reach (`reach = 1`
/// draws exactly what [`sample_batch`] draws).
fn sample_batch_reaching(
    data: &Dataset,
    rng: &mut ChaCha8Rng,
    n: usize,
    reach: usize,
) -> Vec<(usize, usize)> {
    (0..n)
        .map(|_| {
            (
                rng.random_range(0..data.episodes()),
                rng.random_range(1..data.steps() + 1 - reach),
            )
        })
        .collect()
}

/// The drive of the `k`-step action response: `sum_{j<k} (k - j) u_{t+j}` for every sample,
/// `[n * du]` row-major. Under Euler steps `v' = v + dt B u`, `h' = h + dt v'` it is what
/// `(h_{t+k} - h_t - k (h_t - h_{t-1})) / dt^2` equals through `B`.
fn k_step_drive(data: &Dataset, batch: &[(usize, usize)], k: usize) -> Vec<f32> {
    let du = data.action_dim();
    batch
        .iter()
        .flat_map(|&(e, t)| {
            (0..du).map(move |i| {
                (0..k)
                    .map(|j| (k - j) as f32 * data.actions[[e, t + j, i]])
                    .sum::<f32>()
            })
        })
        .collect()
}

/// `n` samples in groups of `group` distinct steps of one episode, inside a stretch of
/// `window` consecutive steps (shortened to the episode's if longer).
pub(crate) fn sample_grouped_batch(
    data: &Dataset,
    rng: &mut ChaCha8Rng,
    n: usize,
    group: usize,
    window: usize,
) -> Vec<(usize, usize)> {
    // Valid steps are 1..steps: each sample needs the frames t - 1, t and t + 1.
    let window = window.min(data.steps() - 1);
    let mut batch = Vec::with_capacity(n);
    while batch.len() < n {
        let episode = rng.random_range(0..data.episodes());
        let start = rng.random_range(1..=data.steps() - window);
        let take = group.min(window).min(n - batch.len());
        batch.extend(
            rand::seq::index::sample(rng, window, take)
                .into_iter()
                .map(|offset| (episode, start + offset)),
        );
    }
    batch
}

/// `[n, d]` standard normal draws from `rng` (Box-Muller; deterministic for a seed).
pub(crate) fn normal_tensor(
    rng: &mut ChaCha8Rng,
    n: usize,
    d: usize,
    device: &Device,
) -> Tensor<2> {
    let values: Vec<f32> = (0..n * d)
        .map(|_| {
            let u1: f64 = rng.random_range(f64::EPSILON..1.0);
            let u2: f64 = rng.random_range(0.0..1.0);
            ((-2.0 * u1.ln()).sqrt() * (2.0 * std::f64::consts::PI * u2).cos()) as f32
        })
        .collect();
    Tensor::from_data(TensorData::new(values, [n, d]), device)
}

/// The RNG of training step `step`: stream `step + 1` of the seed, so a resumed run draws
/// exactly what the uninterrupted run would have.
pub(crate) fn step_rng(seed: u64, step: u64) -> ChaCha8Rng {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    rng.set_stream(step + 1);
    rng
}

/// The frames of the samples `batch` as one network input `[3n, 3, 64, 64]` (every `i_{t-1}`,
/// then every `i_t`, then every `i_{t+1}`) and their actions `u_t` `[n, du]`.
pub(crate) fn batch_tensors(
    data: &Dataset,
    batch: &[(usize, usize)],
    device: &Device,
) -> (Tensor<4>, Tensor<2>) {
    let frames = batch
        .iter()
        .map(|&(e, t)| data.frame(e, t - 1))
        .chain(batch.iter().map(|&(e, t)| data.frame(e, t)))
        .chain(batch.iter().map(|&(e, t)| data.frame(e, t + 1)));
    let frames: Vec<&[u8]> = frames.collect();
    let du = data.action_dim();
    let actions: Vec<f32> = batch
        .iter()
        .flat_map(|&(e, t)| (0..du).map(move |i| (e, t, i)))
        .map(|(e, t, i)| data.actions[[e, t, i]])
        .collect();
    (
        frames_to_tensor(frames.into_iter(), device),
        Tensor::from_data(TensorData::new(actions, [batch.len(), du]), device),
    )
}

/// The encodings and random draws of training step `step` (see [`step_rng`]).
pub fn loss_inputs(
    model: &ProclModel,
    data: &Dataset,
    config: &TrainConfig,
    step: u64,
    device: &Device,
) -> LossInputs {
    loss_inputs_and_batch(model, data, config, step, device).0
}

/// [`loss_inputs`] and the batch's `(episode, t)` of each `h_t`.
fn loss_inputs_and_batch(
    model: &ProclModel,
    data: &Dataset,
    config: &TrainConfig,
    step: u64,
    device: &Device,
) -> (LossInputs, Vec<(usize, usize)>) {
    let mut rng = step_rng(config.seed, step);
    let n = config.batch_size;
    let du = data.action_dim();
    // The k-step action-response term needs the frame `i_{t+k}` of each sample.
    let reach = config.loss.frames_ahead();
    let batch = if config.batch_group_size > 1 {
        sample_grouped_batch(
            data,
            &mut rng,
            n,
            config.batch_group_size,
            config.batch_group_window,
        )
    } else {
        sample_batch_reaching(data, &mut rng, n, reach)
    };
    let (frames, u) = batch_tensors(data, &batch, device);
    let frame_distances = (config.loss.separation_weight > 0.0)
        .then(|| crate::losses::frame_block_distances(frames.clone().narrow(0, n, n)));
    // The frames `i_{t+k}` ride in the same encoder call as the others.
    let frames = if reach > 1 {
        let ahead_frames =
            frames_to_tensor(batch.iter().map(|&(e, t)| data.frame(e, t + reach)), device);
        Tensor::cat(vec![frames, ahead_frames], 0)
    } else {
        frames
    };
    let decoder = model
        .feature_decoder
        .as_ref()
        .filter(|_| config.loss.decoder_weight > 0.0);
    // [3n or 4n, du]; the keypoint head computes its features either way.
    let (h, features) = model.encoder.forward_with_features(frames);
    let ahead = (reach > 1).then(|| {
        let drive = TensorData::new(k_step_drive(data, &batch, reach), [n, du]);
        (
            h.clone().narrow(0, 3 * n, n),
            Tensor::from_data(drive, device),
        )
    });
    let mut permutation: Vec<usize> = (0..n).collect();
    permutation.shuffle(&mut rng);
    let inputs = LossInputs {
        h_prev: h.clone().narrow(0, 0, n),
        h_now: h.clone().narrow(0, n, n),
        h_next: h.narrow(0, 2 * n, n),
        u,
        latent_noise: normal_tensor(&mut rng, n, du, device),
        curvature_noise: (
            normal_tensor(&mut rng, n, du, device),
            normal_tensor(&mut rng, n, du, device),
            normal_tensor(&mut rng, n, du, device),
        ),
        permutation,
        ahead,
        frame_distances,
        decoded_features: None,
        stretch_features: features
            .as_ref()
            .filter(|_| config.loss.stretch_weight > 0.0)
            .map(|features| features.clone().narrow(0, 0, 3 * n).detach()),
    };
    // Drawn last, so switching the term on leaves every other draw of the step as it was.
    let decoded_features = decoder.zip(features).map(|(decoder, features)| {
        let features = features.narrow(0, n, n);
        let held = config
            .loss
            .decoder_head_only
            .then(|| features.clone().detach());
        let h_now = held
            .and_then(|features| model.encoder.latent_from_features(features))
            .unwrap_or_else(|| inputs.h_now.clone());
        let standardised = crate::losses::decoder_input(h_now);
        let noise = normal_tensor(&mut rng, n, du, device) * config.loss.decoder_noise;
        (decoder.forward(standardised + noise), features)
    });
    let inputs = LossInputs {
        decoded_features,
        ..inputs
    };
    (inputs, batch)
}

/// The standardised true configuration `s(q) = (q - mean) / std` per coordinate, over every
/// state of a dataset: the target of the diagnostic [`LossConfig::state_supervision_weight`].
struct StateStandardiser {
    mean: Vec<f64>,
    std: Vec<f64>,
}

impl StateStandardiser {
    fn new(data: &Dataset) -> Self {
        let dq = data.config_dim();
        let count = (data.episodes() * (data.steps() + 1)).max(1) as f64;
        let column = |i: usize| data.states.index_axis(ndarray::Axis(2), i);
        let mean: Vec<f64> = (0..dq)
            .map(|i| column(i).iter().map(|&x| x as f64).sum::<f64>() / count)
            .collect();
        let std = (0..dq)
            .map(|i| {
                let var = column(i)
                    .iter()
                    .map(|&x| (x as f64 - mean[i]).powi(2))
                    .sum::<f64>()
                    / count;
                // A joint that never moves is held at 0 rather than divided by 0.
                var.sqrt().max(1e-6)
            })
            .collect();
        Self { mean, std }
    }

    /// `s(q_t)` of each sample, `[n, dq]`.
    fn targets(&self, data: &Dataset, batch: &[(usize, usize)], device: &Device) -> Tensor<2> {
        let dq = self.mean.len();
        let values: Vec<f32> = batch
            .iter()
            .flat_map(|&(e, t)| data.config(e, t))
            .enumerate()
            .map(|(k, q)| ((q - self.mean[k % dq]) / self.std[k % dq]) as f32)
            .collect();
        Tensor::from_data(TensorData::new(values, [batch.len(), dq]), device)
    }
}

/// One training step's logged values, named as metrics.csv's columns; the first is the total
/// loss.
#[derive(Debug, Clone, PartialEq)]
pub struct StepValues {
    pub names: &'static [&'static str],
    pub values: Vec<f64>,
}

impl StepValues {
    /// The total loss minimised.
    pub fn total(&self) -> f64 {
        self.values.first().copied().unwrap_or(f64::NAN)
    }

    /// The value of the column `name`.
    pub fn get(&self, name: &str) -> Option<f64> {
        let k = self.names.iter().position(|n| *n == name)?;
        self.values.get(k).copied()
    }

    pub fn is_finite(&self) -> bool {
        self.values.iter().all(|x| x.is_finite())
    }
}

impl std::fmt::Display for StepValues {
    /// `total 1.2345 cpc 0.6789 ...`
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        let pairs: Vec<String> = self
            .names
            .iter()
            .zip(&self.values)
            .map(|(name, value)| format!("{name} {value:.4}"))
            .collect();
        f.write_str(&pairs.join(" "))
    }
}

impl From<LossValues> for StepValues {
    fn from(values: LossValues) -> Self {
        Self {
            names: &LOSS_NAMES,
            values: values.as_array().to_vec(),
        }
    }
}

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
    /// The loss to minimise at step `step` (0-based) and its logged values.
    fn loss(&mut self, model: &Self::Model, step: u64) -> (Tensor<1>, StepValues);
    /// Runs after the optimiser update of step `step` (0-based).
    fn after_update(&mut self, model: Self::Model, _step: u64) -> Result<Self::Model> {
        Ok(model)
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
    /// The diagnostic state supervision's target, when its weight is above 0.
    state_target: Option<StateStandardiser>,
}

impl Objective for ProclObjective<'_> {
    type Model = ProclModel;
    const METRICS: &'static [&'static str] = &LOSS_NAMES;

    fn prepare(&mut self, mut model: ProclModel) -> ProclModel {
        let data = self.data;
        let every_frame =
            (0..data.episodes()).flat_map(|e| (0..=data.steps()).map(move |t| data.frame(e, t)));
        model.encoder = match self.config.model.encoder.polar_cut_deg {
            Some(cut_deg) => model.encoder.with_polar_cut_at(cut_deg),
            None => model.encoder.place_polar_cut(every_frame),
        };
        if let Some(target_std) = self.config.model.encoder.init_latent_std
            && target_std > 0.0
        {
            let frames = scale_frames(self.data, self.config.seed, self.device);
            model.encoder = model.encoder.normalise_latent_scale(frames, target_std);
        }
        model
    }

    fn loss(&mut self, model: &ProclModel, step: u64) -> (Tensor<1>, StepValues) {
        let dt = self.data.meta.control_dt_s;
        let (inputs, batch) =
            loss_inputs_and_batch(model, self.data, self.config, step, self.device);
        if let Some(search) = self.search.as_mut() {
            search.observe(&inputs, &self.config.loss, dt);
        }
        let supervision = self.state_target.as_ref().map(|target| {
            let error = inputs.h_now.clone() - target.targets(self.data, &batch, self.device);
            error.powf_scalar(2.0).mean() * self.config.loss.state_supervision_weight
        });
        let terms = procl_loss(&self.config.loss_at(step), &model.dynamics, inputs, dt);
        let mut values: StepValues = terms.values().into();
        let total = match supervision {
            Some(term) => {
                let total = terms.total + term;
                // The logged total is the loss minimised, the diagnostic term included.
                values.values[0] = crate::model::read_scalars(&[&total])[0];
                total
            }
            None => terms.total,
        };
        (total, values)
    }

    fn after_update(&mut self, model: ProclModel, step: u64) -> Result<ProclModel> {
        let every = self.config.orientation_search_every;
        let Some(search) = self.search.as_mut() else {
            return Ok(model);
        };
        if !(step + 1).is_multiple_of(every) {
            return Ok(model);
        }
        let rule = WindowRule {
            margin: self.config.orientation_margin,
            streak: self.config.orientation_streak,
            tolerance: self.config.orientation_tolerance,
        };
        let Some(flip) = search.end_window(&self.run.dir, step + 1, rule)? else {
            return Ok(model);
        };
        Ok(model.reorient_latent(&flip))
    }
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
    config.validate()?;
    if data.meta.env != config.env {
        return Err(Error::config(
            "env",
            format!(
                "the dataset is from {}, the config is for {}",
                data.meta.env, config.env
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
    if config.loss.state_supervision_weight > 0.0 && data.config_dim() != data.action_dim() {
        return Err(Error::config(
            "loss.state_supervision_weight",
            format!(
                "needs dim q = dim u; the dataset has {} and {}",
                data.config_dim(),
                data.action_dim()
            ),
        ));
    }
    let device = &device.clone().autodiff();
    match &config.nvae {
        Some(nvae) => {
            let model = nvae.init(config.seed, device)?;
            let objective = NvaeObjective::new(config, nvae, data, device);
            run_training(objective, model, config, run, resume, device, &mut progress)
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
                state_target: (config.loss.state_supervision_weight > 0.0)
                    .then(|| StateStandardiser::new(data)),
            };
            run_training(objective, model, config, run, resume, device, &mut progress)
        }
    }
}

/// The loop every method shares: run folder and `--resume`, Adam, one metrics.csv row per
/// step, a checkpoint every `checkpoint_every` steps and at the end, and a clean stop on a
/// non-finite loss that keeps the last good checkpoint.
fn run_training<O: Objective>(
    mut objective: O,
    mut model: O::Model,
    config: &TrainConfig,
    run: &RunPaths,
    resume: bool,
    device: &Device,
    progress: &mut dyn FnMut(u64, &StepValues),
) -> Result<TrainSummary> {
    let mut adam = Adam::default();
    let mut start = 0;
    std::fs::create_dir_all(&run.dir).map_err(|e| Error::io(&run.dir, e))?;
    if resume {
        let saved = run.load_config()?;
        if &saved != config {
            return Err(Error::config(
                "resume",
                format!(
                    "{} differs from this run's configuration",
                    run.config().display()
                ),
            ));
        }
        let (m, a, meta) = load_checkpoint(&run.checkpoint(), model, device)?;
        (model, adam, start) = (m, a, meta.step);
        truncate_metrics(&run.metrics(), start, &metrics_header(O::METRICS))?;
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
        let header = metrics_header(O::METRICS) + "\n";
        std::fs::write(run.metrics(), header).map_err(|e| Error::io(run.metrics(), e))?;
    }
    let mut metrics = std::fs::OpenOptions::new()
        .append(true)
        .open(run.metrics())
        .map_err(|e| Error::io(run.metrics(), e))?;
    let clock = Instant::now();
    let mut last = None;
    for step in start..config.steps {
        let (total, values) = objective.loss(&model, step);
        if !values.is_finite() {
            let kept = match (step / config.checkpoint_every) * config.checkpoint_every {
                0 if !resume => "no checkpoint was written yet".to_string(),
                0 => format!("the checkpoint in {} is kept", run.checkpoint().display()),
                good => format!(
                    "the last good checkpoint (step {good}) is kept in {}",
                    run.checkpoint().display()
                ),
            };
            return Err(Error::Diverged(format!(
                "non-finite loss at step {} ({values}); {kept}",
                step + 1
            )));
        }
        let grads = total.backward();
        model = adam.step(config.learning_rate, model, &grads);
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
        progress(step + 1, &values);
        last = Some(values);
        if (step + 1) % config.checkpoint_every == 0 || step + 1 == config.steps {
            save_checkpoint(
                &run.checkpoint(),
                &model,
                Some(&adam),
                &CheckpointMeta { step: step + 1 },
            )?;
        }
    }
    Ok(TrainSummary {
        steps_done: config.steps,
        last,
        seconds: clock.elapsed().as_secs_f64(),
    })
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

/// Reads a TOML config file over a preset: `preset`/`method` keys pick the base, every other
/// key overrides it.
pub fn config_from_toml(path: &Path, env: EnvKind, method: Option<Method>) -> Result<TrainConfig> {
    let text = std::fs::read_to_string(path).map_err(|e| Error::io(path, e))?;
    let table: toml::Table = text.parse().map_err(|e: toml::de::Error| {
        Error::config(path.display().to_string(), e.message().to_string())
    })?;
    config_from_table(table, env, method).map_err(|e| match e {
        Error::InvalidConfig { field, message } => {
            Error::config(format!("{}: {field}", path.display()), message)
        }
        other => other,
    })
}

/// [`config_from_toml`] on an already parsed table.
pub fn config_from_table(
    table: toml::Table,
    env: EnvKind,
    method: Option<Method>,
) -> Result<TrainConfig> {
    let preset: Preset = match table.get("preset") {
        Some(v) => v.clone().try_into().map_err(|_| {
            Error::config(
                "preset",
                format!("unknown preset {v} (expected paper or procl)"),
            )
        })?,
        None => Preset::Procl,
    };
    let method = match (method, table.get("method")) {
        (Some(m), _) => m,
        (None, Some(v)) => v.as_str().unwrap_or("").parse()?,
        (None, None) => Method::Procl,
    };
    if method != Method::Nvae && table.contains_key("nvae") {
        return Err(Error::config(
            "nvae",
            format!(
                "is for method nvae only, not {} (set method = \"nvae\" or pass --method nvae)",
                method.label()
            ),
        ));
    }
    let base = TrainConfig::preset(preset, method, env);
    let mut merged =
        toml::Table::try_from(&base).map_err(|e| Error::config("config", e.to_string()))?;
    merge(&mut merged, table);
    merged.insert(
        "method".into(),
        toml::Value::try_from(method).map_err(|e| Error::config("method", e.to_string()))?,
    );
    merged.insert("env".into(), toml::Value::String(env.name().into()));
    // The path to the offending value names the field (`model.dynamics.full_covariance`), not
    // just the whole config.
    let config: TrainConfig = serde_path_to_error::deserialize(toml::Value::Table(merged))
        .map_err(|e| {
            let field = e.path().to_string();
            let field = if field == "." { "config".into() } else { field };
            Error::config(field, e.into_inner().message().to_string())
        })?;
    config.validate()?;
    Ok(config)
}

/// Deep-merges `over` into `base` (tables recursively, other values replaced).
pub(crate) fn merge(base: &mut toml::Table, over: toml::Table) {
    for (key, value) in over {
        match (base.get_mut(&key), value) {
            (Some(toml::Value::Table(b)), toml::Value::Table(o)) => merge(b, o),
            (_, value) => {
                base.insert(key, value);
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn fetch_uses_the_specs_lyapunov_dt() {
        for preset in [Preset::Paper, Preset::Procl] {
            let fetch = TrainConfig::preset(preset, Method::Procl, EnvKind::Fetch);
            assert_eq!(fetch.loss.lyapunov_dt_s, Some(1.0));
            let reacher = TrainConfig::preset(preset, Method::Procl, EnvKind::Reacher);
            assert_eq!(reacher.loss.lyapunov_dt_s, None);
        }
        // Fetch and the reacher (both latent methods) orient by the action response; the point
        // mass keeps the risk search its results were measured with, and the paper preset
        // searches nothing.
        for env in [EnvKind::Fetch, EnvKind::Reacher] {
            for method in [Method::Procl, Method::Pc3] {
                let config = TrainConfig::preset(Preset::Procl, method, env);
                assert_eq!(
                    config.orientation_criterion,
                    OrientationCriterion::ActionResponse
                );
                assert_eq!(config.orientation_search_every, 50);
            }
        }
        // The reacher's gain-matched risk keeps PC3 at lambda_R = 0.
        let reacher_pc3 = TrainConfig::preset(Preset::Procl, Method::Pc3, EnvKind::Reacher);
        assert_eq!(reacher_pc3.loss.lambda_r, 0.0);
        assert_eq!(reacher_pc3.loss.kp, 1.0);
        let point_mass = TrainConfig::preset(Preset::Procl, Method::Procl, EnvKind::PointMass);
        assert_eq!(
            (
                point_mass.orientation_criterion,
                point_mass.orientation_margin
            ),
            (OrientationCriterion::Risk, 0.1)
        );
        let paper = TrainConfig::preset(Preset::Paper, Method::Procl, EnvKind::Fetch);
        assert_eq!(paper.orientation_search_every, 0);
        // Fetch's latent PD is damped harder than the paper's Kd = 2, for both latent methods.
        assert_eq!(paper.loss.kd, 2.0);
        for method in [Method::Procl, Method::Pc3] {
            let fetch = TrainConfig::preset(Preset::Procl, method, EnvKind::Fetch);
            assert_eq!((fetch.loss.kp, fetch.loss.kd), (10.0, 4.0));
        }
    }

    #[test]
    fn a_value_of_the_wrong_type_is_refused_by_its_path() {
        for (text, field) in [
            (
                "[model.dynamics]\nfull_covariance = \"yes\"",
                "model.dynamics.full_covariance",
            ),
            (
                "[loss]\naction_response_weight = \"x\"",
                "loss.action_response_weight",
            ),
            ("steps = -3", "steps"),
        ] {
            let table: toml::Table = text.parse().unwrap();
            let err = config_from_table(table, EnvKind::Reacher, None)
                .unwrap_err()
                .to_string();
            assert!(err.contains(&format!("`{field}`")), "{text}: {err}");
        }
    }

    #[test]
    fn orientation_rules_are_checked_by_name() {
        let mut config = TrainConfig::preset(Preset::Procl, Method::Procl, EnvKind::Fetch);
        config.orientation_margin = 1.0;
        let err = config.validate().unwrap_err().to_string();
        assert!(err.contains("orientation_margin"), "{err}");
        let mut config = TrainConfig::preset(Preset::Procl, Method::Procl, EnvKind::Reacher);
        config.orientation_tolerance = f64::NAN;
        let err = config.validate().unwrap_err().to_string();
        assert!(err.contains("orientation_tolerance"), "{err}");
        let mut config = TrainConfig::preset(Preset::Procl, Method::Procl, EnvKind::Reacher);
        config.model.dynamics.input = DynamicsInput::ConstantDiagonal { initial_gain: 1.0 };
        // The preset's action-response search may turn the gains with the latent...
        assert!(config.validate().is_ok());
        // ...the risk search may not.
        config.orientation_criterion = OrientationCriterion::Risk;
        let err = config.validate().unwrap_err().to_string();
        assert!(err.contains("orientation_search_every"), "{err}");
        config.orientation_search_every = 0;
        assert!(config.validate().is_ok());
    }

    /// `transitions` random-control transitions of `env` in episodes of 20 steps.
    fn tiny_dataset(env: EnvKind, seed: u64, transitions: usize) -> Dataset {
        let config = crate::data::CollectConfig {
            transitions,
            episode_len: 20,
            ..crate::data::CollectConfig::new(env, seed)
        };
        crate::data::collect(&config, |_| {}).expect("collect")
    }

    #[test]
    fn k_step_drive_is_what_an_euler_latent_responds_to() {
        use crate::losses::action_response_unexplained;
        let data = tiny_dataset(EnvKind::PointMass, 5, 400);
        let (dt, k) = (0.02f32, 6);
        // A latent that moves by Euler steps with one input gain `B` (turned and sheared), from
        // a random start at rest in every episode.
        let gain = [[0.8f32, -0.6], [0.3, 1.1]];
        let mut rng = step_rng(3, 0);
        let latent: Vec<Vec<[f32; 2]>> = (0..data.episodes())
            .map(|e| {
                let mut h = [rng.random_range(-1.0..1.0), rng.random_range(-1.0..1.0)];
                let mut v = [0.0f32; 2];
                let mut path = vec![h];
                for t in 0..data.steps() {
                    let u = [data.actions[[e, t, 0]], data.actions[[e, t, 1]]];
                    for i in 0..2 {
                        v[i] += dt * 40.0 * (gain[i][0] * u[0] + gain[i][1] * u[1]);
                        h[i] += dt * v[i];
                    }
                    path.push(h);
                }
                path
            })
            .collect();
        let batch = sample_batch_reaching(&data, &mut rng, 64, k);
        assert!(batch.iter().all(|&(_, t)| t >= 1 && t + k <= data.steps()));
        let device = crate::model::cpu_device();
        let rows = |map: &dyn Fn([f32; 2]) -> [f32; 2], offset: isize| {
            let values: Vec<f32> = batch
                .iter()
                .flat_map(|&(e, t)| map(latent[e][(t as isize + offset) as usize]))
                .collect();
            Tensor::<2>::from_data(TensorData::new(values, [batch.len(), 2]), &device)
        };
        let drive = Tensor::<2>::from_data(
            TensorData::new(k_step_drive(&data, &batch, k), [batch.len(), 2]),
            &device,
        );
        let unexplained = |map: &dyn Fn([f32; 2]) -> [f32; 2]| {
            let (prev, now, ahead) = (rows(map, -1), rows(map, 0), rows(map, k as isize));
            let response = ahead - now.clone() - (now - prev) * k as f32;
            crate::model::to_vec(action_response_unexplained(response, drive.clone()))[0]
        };
        // Flat: one linear map of the drive explains the whole k-step response.
        let flat = unexplained(&|h| h);
        assert!(flat < 1e-3, "flat latent: {flat}");
        // The same latent curled round the origin: its response turns with the arc.
        let curled = unexplained(&|h| {
            let (r, angle) = (2.0 + h[1], 1.5 * h[0]);
            [r * angle.cos(), r * angle.sin()]
        });
        assert!(
            curled > 0.05 && curled > 50.0 * flat,
            "curled {curled}, flat {flat}"
        );
    }

    #[test]
    fn logged_terms_add_up_to_the_total_minimised() {
        let data = tiny_dataset(EnvKind::Reacher, 2, 200);
        let mut config = TrainConfig::preset(Preset::Procl, Method::Procl, EnvKind::Reacher);
        config.batch_size = 24;
        config.loss.action_response_horizon = 3;
        config.loss.action_response_weight = 2.0;
        config.loss.action_response_turn_weight = 5.0;
        config.loss.action_response_sign_weight = 6.0;
        config.loss.separation_weight = 3.0;
        // A ratio far above any fresh latent's, so every pair is charged.
        config.loss.separation_ratio = 10.0;
        config.loss.decoder_weight = 2.0;
        config.model.feature_decoder_width = 8;
        config.loss.stretch_weight = 4.0;
        // A ratio far above any fresh latent's, so most steps are charged.
        config.loss.stretch_ratio = 10.0;
        // A floor above any fresh latent's spread, so the hinge is logged above 0.
        config.loss.variance_floor = Some(100.0);
        let device = crate::model::cpu_device();
        let model = config.model.init(7, &device).expect("model");
        let (inputs, _) = loss_inputs_and_batch(&model, &data, &config, 0, &device);
        let dt = data.meta.control_dt_s;
        let values: StepValues = procl_loss(&config.loss, &model.dynamics, inputs, dt)
            .values()
            .into();
        let term = |name: &str| values.get(name).expect(name);
        let loss = &config.loss;
        let pc3 = loss.lambda_cpc * term("cpc")
            + loss.lambda_cons * term("cons")
            + loss.lambda_curv * term("curv");
        let recombined = loss.lambda_pc3 * pc3
            + loss.lambda_r * term("lyap")
            + loss.variance_weight * term("var")
            + loss.action_response_weight * term("flat")
            + loss.action_response_turn_weight * term("turn")
            + loss.action_response_sign_weight * term("sign")
            + loss.separation_weight * term("sep")
            + loss.decoder_weight * term("dec")
            + loss.stretch_weight * term("stretch");
        assert!(
            (recombined - values.total()).abs() <= 1e-4 * values.total().abs().max(1.0),
            "{values}: recombined {recombined}"
        );
        assert!(term("var") > 1.0 && term("flat") > 0.0, "{values}");
        assert!((0.0..=1.0).contains(&term("turn")), "{values}");
        assert!(term("sign") >= 0.0, "{values}");
        assert!(term("sep") > 0.0 && term("stretch") > 0.0, "{values}");
        // The decoder starts constant: it leaves all of the features' variance.
        assert!((term("dec") - 1.0).abs() < 1e-5, "{values}");
        // Decoding an h recomputed from the held features changes where the gradient goes,
        // not what is decoded (the head's own test checks the gradient). A drawn output layer,
        // so the decoder is not constant.
        let mut drawn = model.clone();
        let width = config
            .model
            .encoder
            .keypoint_feature_count()
            .expect("keypoints");
        drawn.feature_decoder = Some(crate::model::FeatureDecoder::new(2, 8, width, &device));
        let decoded = |config: &TrainConfig| {
            let (inputs, _) = loss_inputs_and_batch(&drawn, &data, config, 0, &device);
            let (decoded, features) = inputs.decoded_features.expect("decoder on");
            (
                crate::model::to_vec(decoded),
                crate::model::to_vec(features),
            )
        };
        let whole = decoded(&config);
        assert!(whole.0.iter().any(|&x| x != 0.0));
        config.loss.decoder_head_only = true;
        let (head_only, features) = decoded(&config);
        assert_eq!(features, whole.1);
        for (a, b) in head_only.iter().zip(&whole.0) {
            assert!((a - b).abs() <= 1e-5 * b.abs().max(1.0), "{a} vs {b}");
        }

        // Switched off, a term is logged as 0 and the header keeps its column.
        config.loss.action_response_weight = 0.0;
        config.loss.action_response_turn_weight = 0.0;
        config.loss.action_response_sign_weight = 0.0;
        config.loss.variance_floor = None;
        config.loss.separation_weight = 0.0;
        config.loss.decoder_weight = 0.0;
        config.loss.stretch_weight = 0.0;
        let (inputs, _) = loss_inputs_and_batch(&model, &data, &config, 0, &device);
        assert!(inputs.frame_distances.is_none() && inputs.decoded_features.is_none());
        assert!(inputs.stretch_features.is_none());
        let off: StepValues = procl_loss(&config.loss, &model.dynamics, inputs, dt)
            .values()
            .into();
        for name in ["var", "flat", "turn", "sign", "sep", "dec", "stretch"] {
            assert_eq!(off.get(name), Some(0.0), "{off}");
        }
        assert_eq!(off.names, &LOSS_NAMES);
    }

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
            "step,total,cpc,cons,curv,lyap,var,flat,turn,sep,dec,stretch,sign,seconds\n\
             1,5,1,2,0,0.5,,,,,,,,1.5\n2,4,1,1.5,0,0.4,,,,,,,,3\n"
        );
        // Under the current header rows are kept as they are.
        truncate_metrics(&path, 1, &header).expect("truncate again");
        let text = std::fs::read_to_string(&path).expect("read");
        assert_eq!(text, format!("{header}\n1,5,1,2,0,0.5,,,,,,,,1.5\n"));
    }

    #[test]
    fn grouped_batches_take_distinct_nearby_steps_of_one_episode() {
        let data = tiny_dataset(EnvKind::PointMass, 3, 120);
        let mut rng = step_rng(7, 0);
        let batch = sample_grouped_batch(&data, &mut rng, 24, 4, 6);
        assert_eq!(batch.len(), 24);
        for group in batch.chunks(4) {
            let mut steps: Vec<usize> = group.iter().map(|&(_, t)| t).collect();
            assert!(group.iter().all(|&(e, _)| e == group[0].0 && e < 6));
            steps.sort_unstable();
            steps.dedup();
            assert_eq!(steps.len(), 4, "distinct steps {group:?}");
            // Inside one stretch of 6 steps, and a whole sample (t - 1, t + 1) in the episode.
            assert!(steps[3] - steps[0] < 6, "{group:?}");
            assert!(steps[0] >= 1 && steps[3] < 20, "{group:?}");
        }
        // Seeded: the same stream gives the same batch.
        assert_eq!(
            batch,
            sample_grouped_batch(&data, &mut step_rng(7, 0), 24, 4, 6)
        );
        // A window longer than the episode is cut to it.
        let long = sample_grouped_batch(&data, &mut rng, 8, 4, 500);
        assert!(long.iter().all(|&(_, t)| (1..20).contains(&t)));
    }

    #[test]
    fn state_supervision_targets_are_the_standardised_configuration() {
        let data = tiny_dataset(EnvKind::Reacher, 3, 200);
        let device = Device::default();
        let target = StateStandardiser::new(&data);
        let every: Vec<(usize, usize)> = (0..data.episodes())
            .flat_map(|e| (0..=data.steps()).map(move |t| (e, t)))
            .collect();
        let s = crate::model::to_vec(target.targets(&data, &every, &device));
        let dq = data.config_dim();
        assert_eq!(s.len(), every.len() * dq);
        for i in 0..dq {
            let column: Vec<f64> = s.iter().skip(i).step_by(dq).map(|&x| x as f64).collect();
            let mean = column.iter().sum::<f64>() / column.len() as f64;
            let var = column.iter().map(|x| (x - mean).powi(2)).sum::<f64>() / column.len() as f64;
            assert!(mean.abs() < 1e-4, "coordinate {i}: mean {mean}");
            assert!((var - 1.0).abs() < 1e-3, "coordinate {i}: variance {var}");
        }
        // One sample by hand: the wrist of episode 2, step 7.
        let q = data.config(2, 7)[1];
        let wrist: Vec<f64> = every.iter().map(|&(e, t)| data.config(e, t)[1]).collect();
        let mean = wrist.iter().sum::<f64>() / wrist.len() as f64;
        let std =
            (wrist.iter().map(|x| (x - mean).powi(2)).sum::<f64>() / wrist.len() as f64).sqrt();
        let got = crate::model::to_vec(target.targets(&data, &[(2, 7)], &device))[1] as f64;
        assert!(
            (got - (q - mean) / std).abs() < 1e-4,
            "{got} vs {}",
            (q - mean) / std
        );
        let mut config = TrainConfig::preset(Preset::Procl, Method::Procl, EnvKind::Reacher);
        config.loss.state_supervision_weight = -1.0;
        let err = config.validate().unwrap_err().to_string();
        assert!(err.contains("loss.state_supervision_weight"), "{err}");
    }

    #[test]
    fn batch_groups_are_checked_by_name() {
        // The point mass: the reacher's preset reads 5 steps ahead, which grouped batches
        // cannot serve (`action_response_horizon_is_checked_by_name`).
        let mut config = TrainConfig::preset(Preset::Procl, Method::Procl, EnvKind::PointMass);
        config.batch_group_size = 3;
        config.batch_group_window = 8;
        let err = config.validate().unwrap_err().to_string();
        assert!(err.contains("batch_group_size"), "{err}");
        config.batch_group_size = 4;
        config.batch_group_window = 2;
        let err = config.validate().unwrap_err().to_string();
        assert!(err.contains("batch_group_window"), "{err}");
        config.batch_group_window = 8;
        assert!(config.validate().is_ok());
    }

    #[test]
    fn action_response_horizon_is_checked_by_name() {
        let mut config = TrainConfig::preset(Preset::Procl, Method::Procl, EnvKind::Reacher);
        config.loss.action_response_weight = 3.0;
        config.loss.action_response_horizon = 0;
        let err = config.validate().unwrap_err().to_string();
        assert!(err.contains("loss.action_response_horizon"), "{err}");
        // k steps ahead cannot be read from grouped batches; one step can.
        config.loss.action_response_horizon = 5;
        config.batch_group_size = 4;
        config.batch_group_window = 8;
        let err = config.validate().unwrap_err().to_string();
        assert!(err.contains("loss.action_response_horizon"), "{err}");
        config.loss.action_response_horizon = 1;
        assert!(config.validate().is_ok());
        // A horizon longer than the dataset's episodes is refused before training starts.
        let data = tiny_dataset(EnvKind::Reacher, 1, 40);
        config.batch_group_size = 1;
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

    #[test]
    fn risk_weight_ramps_over_the_warm_up() {
        let mut config = TrainConfig::preset(Preset::Procl, Method::Procl, EnvKind::PointMass);
        config.loss.lambda_r = 10.0;
        assert_eq!(config.loss_at(0).lambda_r, 10.0);
        config.risk_warmup_steps = 4;
        let weights: Vec<f64> = (0..6).map(|s| config.loss_at(s).lambda_r).collect();
        assert_eq!(weights, [2.5, 5.0, 7.5, 10.0, 10.0, 10.0]);
        // Nothing else changes.
        assert_eq!(config.loss_at(0).kp, config.loss.kp);
    }
}
