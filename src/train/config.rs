//! Training configurations: the method, the presets per environment (docs/design.md) and
//! TOML files over them, validated with the offending field's name.

use std::path::Path;

use crate::baselines::nvae::NvaeConfig;
use crate::data::{Hub, PixelSpread};
use crate::envs::EnvKind;
use crate::error::{Error, Result};
use crate::losses::{LossConfig, NoiseMode};
use crate::model::{EncoderHead, ModelConfig};
use crate::train::orientation::OrientationCriterion;

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

/// The NewtonianVAE's default batch, in windows of `nvae.sequence_len` frames: 16 windows of
/// 10 encode 160 frames and decode 128, a step no dearer than a ProCL step of 128 samples
/// (README, "Benchmarks").
const NVAE_BATCH_SIZE: usize = 16;

/// A bound on the NewtonianVAE's steps, not its budget: its stopping rule
/// (`nvae.plateau_patience`) ends the run when the validation ELBO stops improving, which on
/// the reacher takes about three times the 4000 steps after which the ELBO still falls
/// (docs/design.md, Baselines).
const NVAE_STEPS: u64 = 20_000;

/// Everything a training run needs; written to the run folder as `config.json`.
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(deny_unknown_fields)]
pub struct TrainConfig {
    pub preset: Preset,
    pub method: Method,
    /// Environment the model is for (checked against the dataset); `None`, written `custom`,
    /// for data from a system procl does not simulate.
    #[serde(with = "crate::envs::env_or_custom")]
    pub env: Option<EnvKind>,
    /// Custom data only: the dataset's time between frames, which the controller's latent
    /// velocity divides by (an environment's runs take their environment's).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub control_dt_s: Option<f64>,
    /// Seed of weights, batches and noise.
    pub seed: u64,
    /// Optimiser steps.
    pub steps: u64,
    /// Samples per batch (`K` of the CPC loss).
    pub batch_size: usize,
    /// Adam learning rate.
    pub learning_rate: f64,
    /// Scale each step's gradient down to this percentile of the run's gradient norms so far
    /// (AutoClip; see [`crate::train::checkpoint::Adam::step`]); absent: no clipping.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub gradient_clip_percentile: Option<f64>,
    /// Save a checkpoint every this many steps (and at the end).
    pub checkpoint_every: u64,
    /// Every this many steps, also keep the weights in `snapshots/step-NNNNNN/`, a run folder
    /// that `procl eval --run` accepts: the points of a learning curve (0: none).
    #[serde(default, skip_serializing_if = "is_zero")]
    pub snapshot_every: u64,
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

fn is_zero(value: &u64) -> bool {
    *value == 0
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

/// The recipe data from elsewhere trains with.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Recipe {
    /// The point mass's (Cartesian keypoints, a tanh layer of 32, the output layer) with the latent
    /// oriented by its response to the action: nothing else about the system is known.
    Generic,
    /// The recipe of one of procl's environments. The reacher's is the recipe for frames that
    /// turn about a hub: polar keypoints about it (docs/design.md, "Custom data").
    Env(EnvKind),
}

impl Recipe {
    /// Names `--preset-env` takes.
    pub const NAMES: [&'static str; 4] = ["generic", "point-mass", "reacher", "fetch"];

    /// The recipe frames with this spread call for: the reacher's when they turn about a hub
    /// (an arm's base), the generic one otherwise.
    pub fn for_frames(spread: &PixelSpread) -> Self {
        match spread.hub() {
            Some(_) => Self::Env(EnvKind::Reacher),
            None => Self::Generic,
        }
    }
}

impl std::str::FromStr for Recipe {
    type Err = Error;
    fn from_str(name: &str) -> Result<Self> {
        match name {
            "generic" => Ok(Self::Generic),
            name => name.parse::<EnvKind>().map(Self::Env).map_err(|_| {
                Error::config(
                    "preset-env",
                    format!(
                        "unknown recipe {name:?}; expected one of {}",
                        Self::NAMES.join(", ")
                    ),
                )
            }),
        }
    }
}

/// Where a configuration's defaults come from: one of procl's environments, or data from
/// elsewhere with `action_dim` components per action, trained with `recipe`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum ConfigBase {
    Env(EnvKind),
    Custom {
        action_dim: usize,
        control_dt_s: f64,
        recipe: Recipe,
        /// The hub the dataset's frames turn about, when the recipe was chosen from them.
        hub: Option<Hub>,
    },
}

impl ConfigBase {
    /// The base for a dataset: its environment's, or custom with `recipe` (which only custom
    /// data may choose; by default the one its frames call for, [`Recipe::for_frames`]).
    pub fn for_dataset(data: &crate::data::Dataset, recipe: Option<Recipe>) -> Result<Self> {
        match (data.meta.env, recipe) {
            (Some(env), None) => Ok(Self::Env(env)),
            (Some(env), Some(_)) => Err(Error::config(
                "preset-env",
                format!("is for custom data; the dataset is from {env}, whose own preset applies"),
            )),
            (None, recipe) => {
                let (recipe, hub) = match recipe {
                    Some(recipe) => (recipe, None),
                    None => {
                        let spread = PixelSpread::of_frames(data.every_frame());
                        (Recipe::for_frames(&spread), spread.hub())
                    }
                };
                Ok(Self::Custom {
                    action_dim: data.action_dim(),
                    control_dt_s: data.meta.control_dt_s,
                    recipe,
                    hub,
                })
            }
        }
    }

    /// One line on the recipe custom data trains with and why (`None` for an environment's
    /// data, whose preset applies).
    pub fn describe(&self) -> Option<String> {
        let Self::Custom { recipe, hub, .. } = self else {
            return None;
        };
        Some(match (recipe, hub) {
            (Recipe::Env(env), Some(hub)) => {
                let [col, row] = hub.pixels();
                format!(
                    "custom data: the frames turn about a hub at pixel (column {col:.1}, row {row:.1}), so the {env} recipe trains it (polar keypoints about the hub); --preset-env generic for the generic one"
                )
            }
            (Recipe::Generic, _) => {
                "custom data: the generic recipe (the frames turn about no hub)".into()
            }
            (Recipe::Env(env), None) => format!(
                "custom data: the {env} recipe, as named (a polar head is centred on the hub the frames turn about, or on the image centre without one)"
            ),
        })
    }

    fn preset(self, preset: Preset, method: Method) -> TrainConfig {
        match self {
            Self::Env(env) => TrainConfig::preset(preset, method, env),
            Self::Custom {
                action_dim,
                control_dt_s,
                recipe,
                ..
            } => TrainConfig::custom_preset(preset, method, action_dim, control_dt_s, recipe),
        }
    }

    fn env(self) -> Option<EnvKind> {
        match self {
            Self::Env(env) => Some(env),
            Self::Custom { .. } => None,
        }
    }
}

/// How many control periods ahead the PD law looks: `u = -Kp (e + Kd / Kp de/dt)`.
const PD_LEAD_PERIODS: f64 = 10.0;

/// The derivative gain of a procl preset: `Kd = 10 dt Kp`, so the law damps over ten control
/// periods whatever the system's rate. At 0.02 s it is the paper's `Kd = 2` for `Kp = 10`; at
/// Fetch's 0.04 s it damps the orbits a slightly turned latent makes about its goal, which the
/// paper's `Kd = 2` leaves (docs/design.md, "Fetch").
fn pd_derivative_gain(kp: f64, control_dt_s: f64) -> f64 {
    PD_LEAD_PERIODS * control_dt_s * kp
}

/// The encoder head of every procl preset: 16 soft-argmax keypoints, a tanh layer of 32 and the
/// output layer; with `polar`, the keypoints are polar about the frames' hub and the angles
/// between them join the tanh layer's inputs (the reacher's and frames with a hub).
fn procl_head(polar: bool) -> EncoderHead {
    EncoderHead::SoftArgmax {
        keypoints: 16,
        hidden: 32,
        polar,
        pairwise_angles: polar,
    }
}

/// The training steps every published result uses on `env` (and the default of `procl train`):
/// 600 on point mass and Fetch, 1200 on the reacher.
pub fn training_budget(env: EnvKind) -> u64 {
    match env {
        EnvKind::PointMass | EnvKind::Fetch => 600,
        EnvKind::Reacher => 1200,
    }
}

impl TrainConfig {
    /// The configuration of `preset` for `method` on `env`.
    pub fn preset(preset: Preset, method: Method, env: EnvKind) -> Self {
        Self::preset_at_period(preset, method, env, None)
    }

    /// [`Self::preset`] with the gain rule applied at `control_dt_s` (custom data's period)
    /// instead of the environment's when given.
    fn preset_at_period(
        preset: Preset,
        method: Method,
        env: EnvKind,
        control_dt_s: Option<f64>,
    ) -> Self {
        let sim = env.make();
        let du = sim.action_dim();
        let mut config = Self {
            preset,
            method,
            env: Some(env),
            control_dt_s: None,
            seed: 0,
            steps: training_budget(env),
            batch_size: 128,
            learning_rate: 1e-3,
            gradient_clip_percentile: None,
            checkpoint_every: 500,
            snapshot_every: 0,
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
                // PC3's losses leave the latent's orientation free, and PD needs each action
                // to push its own coordinate: every 50 steps the latent is turned so its mean
                // response to the action is most positive on the diagonal. Unlike a search
                // over signed permutations by the risk, it measures the whole rotation and
                // does not depend on the latent's scale (docs/design.md, "Departures in every
                // environment").
                config.orientation_criterion = OrientationCriterion::ActionResponse;
                config.orientation_search_every = 50;
                config.model.encoder.keypoint_sharpness = 30.0;
                // A tanh layer of 32 between the keypoints and the latent lets `h` bend where
                // the pixels move unevenly per unit of state (the reacher's wrist is 5-10x
                // fainter than its shoulder through a linear map); where they do not, it
                // learns a near-linear map and costs nothing (docs/design.md, "Which parts
                // are on where").
                config.model.encoder.head = procl_head(false);
            }
        }
        match method {
            Method::Procl => {}
            Method::Pc3 => config.loss.lambda_r = 0.0,
            Method::Nvae => {
                let mut nvae = NvaeConfig::for_action_dim(du);
                if preset == Preset::Procl {
                    // Every method compares on ProCL's encoder head.
                    nvae.encoder_head = config.model.encoder.head;
                    // Its paper's appendix fixes `A = 0, B = 0, C = 1`: every action then
                    // accelerates its own latent coordinate at the same rate everywhere, which
                    // a learned, state-dependent `C` lets the reacher's latent bend away from
                    // (docs/design.md, "Baselines").
                    nvae.fixed_transition = Some([0.0, 0.0, 1.0]);
                }
                config.nvae = Some(nvae);
                // Its PID acts on each latent coordinate with its own action, the
                // correspondence the prior's diagonal `C` stands for but the ELBO barely
                // enforces: the readout is turned by the action response, as ProCL's latent
                // is (docs/design.md, "Baselines").
                config.orientation_criterion = OrientationCriterion::ActionResponse;
                config.batch_size = NVAE_BATCH_SIZE;
                config.steps = NVAE_STEPS;
            }
        }
        if env == EnvKind::Reacher
            && preset == Preset::Procl
            && let Some(nvae) = config.nvae.as_mut()
        {
            // ProCL's reacher head (below): with Cartesian keypoints the NewtonianVAE's
            // latent is the fingertip's image position, and PID reaches 2% of goals
            // (docs/research/reacher.md, H).
            nvae.encoder_head = procl_head(true);
        }
        if env == EnvKind::Reacher && preset == Preset::Procl && method != Method::Nvae {
            // The shoulder is a revolute joint: polar keypoints about it (the hub the frames
            // turn about, placed before training by `Encoder::place_polar_frame`),
            // the angles between keypoints (entering from 0) over 32x32 cells, a
            // latent started at unit spread, orientation by the action response, and the risk
            // on the standardised latent with gains matched to that scale (docs/design.md,
            // "Reacher"). The cells' angles count less beyond the elbow, about 0.4 of the
            // frame's half-width from the shoulder: only the outer link and the fingertip sweep
            // past the angle's cut; each frame's cut moves to the side opposite its arm, so
            // none of the arm's cells crosses it.
            config.model.encoder.head = procl_head(true);
            config.model.encoder.pairwise_init_scale = 0.0;
            config.model.encoder.trunk_second_stride = 1;
            config.model.encoder.polar_angle_falloff = Some(0.4);
            config.model.encoder.polar_moving_cut = true;
            config.model.encoder.init_latent_std = Some(1.0);
            config.loss.risk_latent_std = Some(1.0);
            config.loss.kp = 1.0;
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
        if preset == Preset::Procl && method != Method::Nvae {
            // A step's gradient can spike thousands of times over the median (angles between
            // keypoints jumping by 2 pi, the sign term where a region's response nearly
            // vanishes) and derail the run; clipped to the 10th percentile of the run's gradient
            // norms, it moves the weights no further than a quiet step (docs/design.md,
            // "Departures in every environment").
            config.gradient_clip_percentile = Some(10.0);
        }
        if env == EnvKind::Fetch {
            // The paper's dt_R for Fetch is 1 (the env's control dt for the 2-D envs).
            config.loss.lyapunov_dt_s = Some(1.0);
        }
        if preset == Preset::Procl {
            let dt = control_dt_s.unwrap_or_else(|| sim.control_dt_s());
            config.loss.kd = pd_derivative_gain(config.loss.kp, dt);
        }
        config
    }

    /// The configuration of `preset` for `method` on data from a system procl does not
    /// simulate, with `action_dim` action components every `control_dt_s` seconds: `recipe`
    /// with its latent resized to `action_dim`.
    pub fn custom_preset(
        preset: Preset,
        method: Method,
        action_dim: usize,
        control_dt_s: f64,
        recipe: Recipe,
    ) -> Self {
        let env = match recipe {
            Recipe::Generic => EnvKind::PointMass,
            Recipe::Env(env) => env,
        };
        let mut config = Self::preset_at_period(preset, method, env, Some(control_dt_s));
        config.env = None;
        config.control_dt_s = Some(control_dt_s);
        config.model.encoder.latent_dim = action_dim;
        config.model.dynamics.latent_dim = action_dim;
        // On arms procl was not tuned on, each frame's own cut lifts some seeds and erases the
        // wrist on others, even with the gradient clipped (docs/research/one-recipe.md, E), so
        // custom data keeps the one cut.
        config.model.encoder.polar_moving_cut = false;
        if let Some(nvae) = &mut config.nvae {
            nvae.latent_dim = action_dim;
        }
        config
    }

    /// The environment a trained run controls, or an error naming `run_dir` for custom runs,
    /// which only a user's own loop can run.
    pub fn simulated_env(&self, run_dir: &Path) -> Result<EnvKind> {
        self.env.ok_or_else(|| {
            Error::config(
                "env",
                format!(
                    "{} was trained on custom data, and procl simulates only {}; run its controller in your own loop (Python: procl.Controller.load)",
                    run_dir.display(),
                    EnvKind::NAMES.join(", ")
                ),
            )
        })
    }

    /// Seconds between control steps: the environment's, or the custom dataset's.
    pub fn control_dt_s(&self) -> f64 {
        match (self.env, self.control_dt_s) {
            (Some(env), _) => env.make().control_dt_s(),
            (None, Some(dt)) => dt,
            // validate() refuses this combination.
            (None, None) => f64::NAN,
        }
    }

    /// Rejects invalid values with the field's name.
    pub fn validate(&self) -> Result<()> {
        match (self.env, self.control_dt_s) {
            (Some(env), Some(_)) => {
                return Err(Error::config(
                    "control_dt_s",
                    format!("is for custom data; {env} runs at its own control period"),
                ));
            }
            (None, dt) if !dt.is_some_and(|dt| dt.is_finite() && dt > 0.0) => {
                return Err(Error::config(
                    "control_dt_s",
                    "custom data needs a positive control period in seconds",
                ));
            }
            _ => {}
        }
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
        if let Some(percentile) = self.gradient_clip_percentile
            && !(percentile > 0.0 && percentile <= 100.0)
        {
            return Err(Error::config(
                "gradient_clip_percentile",
                format!("{percentile} must be in (0, 100]"),
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
        let du = self.env.map(|env| env.make().action_dim());
        let source = crate::envs::source_name(self.env);
        match (&self.nvae, self.method) {
            (Some(nvae), Method::Nvae) => {
                if let Some(du) = du
                    && nvae.latent_dim != du
                {
                    return Err(Error::config(
                        "nvae.latent_dim",
                        format!("must equal the action dimension {du} of {source}"),
                    ));
                }
                if self.orientation_search_every > 0
                    && self.orientation_criterion != OrientationCriterion::ActionResponse
                {
                    return Err(Error::config(
                        "orientation_criterion",
                        "must be `action-response` for method nvae (`risk` is ProCL's Lyapunov risk, which the NewtonianVAE has no dynamics for)",
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
        if let Some(du) = du
            && self.model.encoder.latent_dim != du
        {
            return Err(Error::config(
                "model.encoder.latent_dim",
                format!("must equal the action dimension {du} of {source}"),
            ));
        }
        self.loss.validate()?;
        self.model.validate()
    }
}

/// Reads a TOML config file over a preset: `preset`/`method` keys pick the base, every other
/// key overrides it.
pub fn config_from_toml(
    path: &Path,
    base: impl Into<ConfigBase>,
    method: Option<Method>,
) -> Result<TrainConfig> {
    config_from_table(read_config_table(path)?, base, method).map_err(|e| match e {
        Error::InvalidConfig { field, message } => {
            Error::config(format!("{}: {field}", path.display()), message)
        }
        other => other,
    })
}

/// The keys of the TOML config file at `path`, unresolved (a syntax error names the file).
pub fn read_config_table(path: &Path) -> Result<toml::Table> {
    let text = std::fs::read_to_string(path).map_err(|e| Error::io(path, e))?;
    text.parse().map_err(|e: toml::de::Error| {
        Error::config(path.display().to_string(), e.message().to_string())
    })
}

/// [`config_from_toml`] on an already parsed table.
pub fn config_from_table(
    table: toml::Table,
    base: impl Into<ConfigBase>,
    method: Option<Method>,
) -> Result<TrainConfig> {
    let base = base.into();
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
    let mut merged = toml::Table::try_from(base.preset(preset, method))
        .map_err(|e| Error::config("config", e.to_string()))?;
    merge(&mut merged, table);
    merged.insert(
        "method".into(),
        toml::Value::try_from(method).map_err(|e| Error::config("method", e.to_string()))?,
    );
    let source = crate::envs::source_name(base.env());
    if let Some(named) = merged.get("env").and_then(|v| v.as_str())
        && named != source
    {
        return Err(Error::config(
            "env",
            format!("the configuration is for {named}, the dataset is from {source}"),
        ));
    }
    merged.insert("env".into(), toml::Value::String(source.into()));
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

impl From<EnvKind> for ConfigBase {
    fn from(env: EnvKind) -> Self {
        Self::Env(env)
    }
}

/// Deep-merges `over` into `base` (tables recursively, other values replaced). A table that
/// names another `kind` (a head of another kind) replaces the base's whole: the fields of the
/// base's kind mean nothing to it.
pub(crate) fn merge(base: &mut toml::Table, over: toml::Table) {
    for (key, value) in over {
        match (base.get_mut(&key), value) {
            (Some(toml::Value::Table(b)), toml::Value::Table(o))
                if o.get("kind").is_none_or(|kind| b.get("kind") == Some(kind)) =>
            {
                merge(b, o)
            }
            (_, value) => {
                base.insert(key, value);
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::model::EncoderConfig;

    #[test]
    fn a_table_of_another_kind_replaces_the_base_and_one_of_the_same_kind_merges() {
        let table = |text: &str| text.parse::<toml::Table>().unwrap();
        let base = table("[head]\nkind = \"soft-argmax\"\nkeypoints = 8\nhidden = 32\n");
        let merged = |over: &str| {
            let mut merged = base.clone();
            merge(&mut merged, table(over));
            merged
        };
        assert_eq!(
            merged("[head]\nkind = \"mlp\"\nhidden = 8\n"),
            table("[head]\nkind = \"mlp\"\nhidden = 8\n")
        );
        let same_kind = "[head]\nkind = \"soft-argmax\"\nkeypoints = 8\nhidden = 16\n";
        assert_eq!(merged("[head]\nhidden = 16\n"), table(same_kind));
        assert_eq!(
            merged("[head]\nkind = \"soft-argmax\"\nhidden = 16\n"),
            table(same_kind)
        );
    }

    #[test]
    fn recipes_parse_by_name_and_frames_without_a_hub_get_the_generic_one() {
        assert_eq!("generic".parse::<Recipe>().unwrap(), Recipe::Generic);
        assert_eq!(
            "reacher".parse::<Recipe>().unwrap(),
            Recipe::Env(EnvKind::Reacher)
        );
        let err = "arm".parse::<Recipe>().unwrap_err().to_string();
        assert!(
            err.contains("preset-env") && err.contains("generic, point-mass"),
            "{err}"
        );
        let still = [7u8; crate::envs::FRAME_BYTES];
        let spread = PixelSpread::of_frames(std::iter::repeat_n(&still[..], 3));
        assert_eq!(Recipe::for_frames(&spread), Recipe::Generic);
        // The arm's recipe is the reacher's, resized to the data's action and period.
        let arm = TrainConfig::custom_preset(
            Preset::Procl,
            Method::Procl,
            3,
            0.05,
            Recipe::Env(EnvKind::Reacher),
        );
        let reacher = TrainConfig::preset(Preset::Procl, Method::Procl, EnvKind::Reacher);
        // Except each frame's own cut, which custom data does without.
        assert!(reacher.model.encoder.polar_moving_cut && !arm.model.encoder.polar_moving_cut);
        assert_eq!(
            EncoderConfig {
                latent_dim: reacher.model.encoder.latent_dim,
                polar_moving_cut: true,
                ..arm.model.encoder
            },
            reacher.model.encoder
        );
        assert_eq!(
            arm.gradient_clip_percentile,
            reacher.gradient_clip_percentile
        );
        assert_eq!(
            LossConfig {
                kd: reacher.loss.kd,
                ..arm.loss
            },
            reacher.loss
        );
        assert_eq!(
            (arm.model.encoder.latent_dim, arm.control_dt_s, arm.loss.kd),
            (3, Some(0.05), 0.5)
        );
        let generic =
            TrainConfig::custom_preset(Preset::Procl, Method::Procl, 2, 0.05, Recipe::Generic);
        assert_eq!(
            generic.orientation_criterion,
            OrientationCriterion::ActionResponse
        );
    }

    #[test]
    fn fetch_uses_the_papers_lyapunov_dt() {
        for preset in [Preset::Paper, Preset::Procl] {
            let fetch = TrainConfig::preset(preset, Method::Procl, EnvKind::Fetch);
            assert_eq!(fetch.loss.lyapunov_dt_s, Some(1.0));
            let reacher = TrainConfig::preset(preset, Method::Procl, EnvKind::Reacher);
            assert_eq!(reacher.loss.lyapunov_dt_s, None);
        }
    }

    #[test]
    fn procl_presets_orient_by_the_action_response_and_damp_by_one_rule() {
        // Every procl preset, for both latent methods, orients by the action response; the
        // paper preset searches nothing.
        for env in [EnvKind::PointMass, EnvKind::Fetch, EnvKind::Reacher] {
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
        let paper = TrainConfig::preset(Preset::Paper, Method::Procl, EnvKind::Fetch);
        assert_eq!(paper.orientation_search_every, 0);
        // Kd = 10 dt Kp in every procl preset, for both latent methods, and for custom data at
        // its own control period; the paper preset keeps the paper's Kd = 2.
        assert_eq!(paper.loss.kd, 2.0);
        for method in [Method::Procl, Method::Pc3] {
            let gains = |env| {
                let loss = TrainConfig::preset(Preset::Procl, method, env).loss;
                (loss.kp, loss.kd)
            };
            assert_eq!(gains(EnvKind::PointMass), (10.0, 2.0));
            assert_eq!(gains(EnvKind::Reacher), (1.0, 0.2));
            assert_eq!(gains(EnvKind::Fetch), (10.0, 4.0));
            let custom = TrainConfig::custom_preset(Preset::Procl, method, 1, 0.1, Recipe::Generic);
            assert_eq!((custom.loss.kp, custom.loss.kd), (10.0, 10.0));
        }
    }

    #[test]
    fn every_method_of_a_procl_preset_encodes_through_one_head_with_a_tanh_layer() {
        let head_of = |config: &TrainConfig| match &config.nvae {
            Some(nvae) => nvae.encoder_head,
            None => config.model.encoder.head,
        };
        // (configuration, whether its frames turn about a hub: the reacher's and a custom arm's
        // keypoints are polar, with the angles between them).
        let mut cases = vec![];
        for method in [Method::Procl, Method::Pc3, Method::Nvae] {
            for env in [EnvKind::PointMass, EnvKind::Reacher, EnvKind::Fetch] {
                let config = TrainConfig::preset(Preset::Procl, method, env);
                cases.push((config, env == EnvKind::Reacher));
            }
            for (recipe, polar) in [
                (Recipe::Generic, false),
                (Recipe::Env(EnvKind::Reacher), true),
            ] {
                let config = TrainConfig::custom_preset(Preset::Procl, method, 2, 0.05, recipe);
                cases.push((config, polar));
            }
        }
        for (config, polar) in cases {
            let expected = EncoderHead::SoftArgmax {
                keypoints: 16,
                hidden: 32,
                polar,
                pairwise_angles: polar,
            };
            let what = (config.env, config.method);
            assert_eq!(head_of(&config), expected, "{what:?}");
        }
        // The paper preset keeps PC3's MLP.
        let paper = TrainConfig::preset(Preset::Paper, Method::Procl, EnvKind::PointMass);
        assert_eq!(paper.model.encoder.head, EncoderHead::Mlp { hidden: 256 });
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

    #[test]
    fn a_clipping_percentile_outside_0_to_100_is_refused_by_name() {
        for percentile in ["0.0", "-5.0", "100.5", "nan"] {
            let table: toml::Table = format!("gradient_clip_percentile = {percentile}")
                .parse()
                .unwrap();
            let err = config_from_table(table, EnvKind::PointMass, None)
                .unwrap_err()
                .to_string();
            assert!(
                err.contains("gradient_clip_percentile"),
                "{percentile}: {err}"
            );
        }
        let table: toml::Table = "gradient_clip_percentile = 100.0".parse().unwrap();
        let config = config_from_table(table, EnvKind::PointMass, None).unwrap();
        assert_eq!(config.gradient_clip_percentile, Some(100.0));
    }
}
