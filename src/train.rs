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
use crate::model::{EncoderHead, ModelConfig, ProclModel, frames_to_tensor};
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

/// Named starting points for a configuration.
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum Preset {
    /// The paper as written: PC3-style MLP encoder head, noise as in the paper.
    Paper,
    /// procl's default: the paper plus the departures in docs/design.md.
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

fn default_orientation_tolerance() -> f64 {
    0.05
}

impl TrainConfig {
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
            orientation_margin: default_orientation_margin(),
            orientation_streak: default_orientation_streak(),
            orientation_criterion: OrientationCriterion::Risk,
            orientation_tolerance: default_orientation_tolerance(),
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
            // The shoulder is a revolute joint at the image centre: polar keypoints about it,
            // the angles between keypoints (entering from 0, faded at the angle cut) over 32x32
            // cells, a tanh layer, a latent started at unit spread and held there by a variance
            // floor, orientation by the action response, and the risk on the standardised latent
            // with gains matched to that scale (docs/design.md, "Reacher").
            config.model.encoder.head = EncoderHead::SoftArgmax {
                keypoints: 16,
                hidden: 32,
                polar: true,
                pairwise_angles: true,
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
                // The risk's velocity term charges the heavily damped wrist for its velocity
                // jumps, so `V` has none; the sign term and its singular-value floor keep the
                // latent from hooking back at the shoulder's ends. Both are PD-controllability
                // terms like the risk, so PC3 gets neither (docs/design.md, "Reacher").
                config.loss.q_v = 0.0;
                config.loss.action_response_sign_weight = 3.0;
                config.loss.action_response_horizon = 5;
                config.loss.action_response_velocity = true;
                config.loss.action_response_regions = 6;
                config.loss.action_response_singular_floor = 0.25;
            }
        }
        if env == EnvKind::Fetch {
            // The paper's dt_R for Fetch is 1 (the env's control dt for the 2-D envs).
            config.loss.lyapunov_dt_s = Some(1.0);
            if preset == Preset::Procl {
                // A signed permutation leaves Fetch's latent up to 45 degrees from the gripper
                // axes; the action response measures and removes the whole rotation, and a
                // larger Kd damps the orbits a slightly turned latent makes about its goal
                // (docs/design.md, "Fetch").
                config.orientation_criterion = OrientationCriterion::ActionResponse;
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
        if !(self.learning_rate.is_finite() && self.learning_rate > 0.0) {
            return Err(Error::config(
                "learning_rate",
                format!("{} must be > 0", self.learning_rate),
            ));
        }
        if self.checkpoint_every == 0 {
            return Err(Error::config("checkpoint_every", "must be at least 1"));
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
    let mut rng = step_rng(config.seed, step);
    let n = config.batch_size;
    let du = data.action_dim();
    // The k-step sign term needs the frame `i_{t+k}` of each sample.
    let reach = config.loss.frames_ahead();
    let batch = sample_batch_reaching(data, &mut rng, n, reach);
    let (frames, u) = batch_tensors(data, &batch, device);
    // The frames `i_{t+k}` ride in the same encoder call as the others.
    let frames = if reach > 1 {
        let ahead_frames =
            frames_to_tensor(batch.iter().map(|&(e, t)| data.frame(e, t + reach)), device);
        Tensor::cat(vec![frames, ahead_frames], 0)
    } else {
        frames
    };
    let h = model.encoder.forward(frames); // [3n or 4n, du]
    let ahead = (reach > 1).then(|| {
        let drive = TensorData::new(k_step_drive(data, &batch, reach), [n, du]);
        (
            h.clone().narrow(0, 3 * n, n),
            Tensor::from_data(drive, device),
        )
    });
    let mut permutation: Vec<usize> = (0..n).collect();
    permutation.shuffle(&mut rng);
    LossInputs {
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
}

impl Objective for ProclObjective<'_> {
    type Model = ProclModel;
    const METRICS: &'static [&'static str] = &LOSS_NAMES;

    fn prepare(&mut self, mut model: ProclModel) -> ProclModel {
        let data = self.data;
        let every_frame =
            (0..data.episodes()).flat_map(|e| (0..=data.steps()).map(move |t| data.frame(e, t)));
        model.encoder = model.encoder.place_polar_cut(every_frame);
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
        let inputs = loss_inputs(model, self.data, self.config, step, self.device);
        if let Some(search) = self.search.as_mut() {
            search.observe(&inputs, &self.config.loss, dt);
        }
        let terms = procl_loss(&self.config.loss, &model.dynamics, inputs, dt);
        (terms.total.clone(), terms.values().into())
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
    fn fetch_uses_the_papers_lyapunov_dt() {
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
                "[model.dynamics]\ninit_std = \"yes\"",
                "model.dynamics.init_std",
            ),
            (
                "[loss]\naction_response_sign_weight = \"x\"",
                "loss.action_response_sign_weight",
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
        // The response `h_{t+k} - h_t - k (h_t - h_{t-1})` is `dt^2 40 B` times the drive.
        let (prev, now, ahead) = (rows(&|h| h, -1), rows(&|h| h, 0), rows(&|h| h, k as isize));
        let response = crate::model::to_vec(ahead - now.clone() - (now - prev) * k as f32);
        let drive = crate::model::to_vec(drive);
        for (row, (r, d)) in response.chunks(2).zip(drive.chunks(2)).enumerate() {
            for i in 0..2 {
                let want = dt * dt * 40.0 * (gain[i][0] * d[0] + gain[i][1] * d[1]);
                assert!((r[i] - want).abs() < 1e-4, "row {row}, dim {i}: {} vs {want}", r[i]);
            }
        }
    }

    #[test]
    fn logged_terms_add_up_to_the_total_minimised() {
        let data = tiny_dataset(EnvKind::Reacher, 2, 200);
        let mut config = TrainConfig::preset(Preset::Procl, Method::Procl, EnvKind::Reacher);
        config.batch_size = 24;
        config.loss.action_response_horizon = 3;
        config.loss.action_response_regions = 3;
        // A floor above any fresh latent's spread, so the hinge is logged above 0.
        config.loss.variance_floor = Some(100.0);
        let device = crate::model::cpu_device();
        let model = config.model.init(7, &device).expect("model");
        let inputs = loss_inputs(&model, &data, &config, 0, &device);
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
            + loss.action_response_sign_weight * term("sign");
        assert!(
            (recombined - values.total()).abs() <= 1e-4 * values.total().abs().max(1.0),
            "{values}: recombined {recombined}"
        );
        assert!(term("var") > 1.0, "{values}");
        assert!(term("sign") >= 0.0, "{values}");

        // Switched off, a term is logged as 0 and the header keeps its column.
        config.loss.action_response_sign_weight = 0.0;
        config.loss.variance_floor = None;
        let inputs = loss_inputs(&model, &data, &config, 0, &device);
        assert!(inputs.ahead.is_none());
        let off: StepValues = procl_loss(&config.loss, &model.dynamics, inputs, dt)
            .values()
            .into();
        for name in ["var", "sign"] {
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
            "step,total,cpc,cons,curv,lyap,var,sign,seconds\n\
             1,5,1,2,0,0.5,,,1.5\n2,4,1,1.5,0,0.4,,,3\n"
        );
        // Under the current header rows are kept as they are.
        truncate_metrics(&path, 1, &header).expect("truncate again");
        let text = std::fs::read_to_string(&path).expect("read");
        assert_eq!(text, format!("{header}\n1,5,1,2,0,0.5,,,1.5\n"));
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
