//! The NewtonianVAE baseline (Jaques, Burke, Hospedales 2021): a VAE whose latent
//! position `x` follows a Newtonian transition prior with diagonal `A`, `B <= 0`, `C > 0`
//! (state-dependent, or fixed as in its paper's appendix), trained by the ELBO over windows of
//! the dataset's episodes, with each frame after the second reconstructed from the prior's
//! prediction, and controlled by PID on the posterior mean.

mod host_decoder;
mod loss;
mod model;

pub use loss::{
    ELBO_NAMES, ElboInputs, ElboTerms, Targets, VALIDATION_NAMES, elbo_loss, gaussian_kl,
    reconstruction_nll,
};
pub use model::{Decoder, GaussianEncoder, NvaeModel, NvaeTransition, TransitionMatrices};

use crate::control::{LatentPolicy, Pid};

/// PID on the NewtonianVAE's posterior mean.
pub type LatentPidPolicy = LatentPolicy<Pid, GaussianEncoder>;

use crate::control::PidController;
use crate::error::{Error, Result};
use crate::model::EncoderHead;

/// NewtonianVAE architecture, objective and controller; the `nvae` table of a run's
/// `config.json` (present for `method = "nvae"` only).
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(deny_unknown_fields)]
pub struct NvaeConfig {
    /// Dimension of the latent position `x` (= action dimension du).
    pub latent_dim: usize,
    /// Encoder: channels of the two stride-2 trunk convs (64 -> 32 -> 16 pixels), as ProCL's.
    pub trunk_channels: [usize; 2],
    /// Encoder head, with `2 du` outputs (mean and log std of `q(x | frame)`). Default:
    /// ProCL's soft-argmax keypoints, so that every method compares on the same encoder; with
    /// the PC3-style MLP head the latent was still folded after 1000 steps
    /// (docs/research/point-mass.md).
    pub encoder_head: EncoderHead,
    /// Initial soft-argmax sharpness (soft-argmax heads only; learned from there), as ProCL's
    /// `model.encoder.keypoint_sharpness`.
    #[serde(default = "default_sharpness")]
    pub keypoint_sharpness: f64,
    /// Decoder: units of the dense layer before the 8x8 feature map.
    pub decoder_hidden: usize,
    /// Decoder: channels of the 8x8, 16x16 and 32x32 feature maps (the 64x64 output has 3).
    /// Sized so that decoding costs about what encoding does on 2 CPU cores.
    pub decoder_channels: [usize; 3],
    /// Units of each of the transition MLP's two ReLU hidden layers (the paper: 16).
    pub transition_hidden: usize,
    /// `dt` of the latent dynamics and of `v = (x_t - x_{t-1}) / dt`, seconds (`None`: the
    /// environment's control period).
    pub dt_s: Option<f64>,
    /// The transition's diagonal matrices: `None` learns `[A, log(-B), log C]` as the MLP's
    /// outputs (the paper's model); `[a, b, c]` fixes `A = a I`, `B = b I`, `C = c I`. The
    /// NewtonianVAE paper's appendix fixes `A = 0, B = 0, C = 1`, which makes each action
    /// accelerate its own latent coordinate at a known rate, whatever the ELBO prefers.
    #[serde(default)]
    pub fixed_transition: Option<[f64; 3]>,
    /// Initial transition-prior std `sigma_p` (learned per dimension from there).
    pub init_prior_std: f64,
    /// Std `sigma_x` of the Gaussian decoder, fixed, in pixel units ([-0.5, 0.5] per channel):
    /// the reconstruction NLL is the squared error summed over pixels / (2 sigma_x^2).
    pub recon_std: f64,
    /// Weight of `KL(q(x_t | i_t) || N(0, I))`: fixes the latent's scale (everything else in
    /// the ELBO is unchanged when the latent, `sigma_p` and `C` are scaled together), and with
    /// it the meaning of the PID gains.
    pub kl_standard_weight: f64,
    /// KL annealing: the transition KL's weight `beta` is `kl_start` for the first
    /// `kl_anneal_begin` steps, then rises linearly to 1 over `kl_anneal_steps` steps
    /// (`kl_anneal_steps = 0`: `beta = 1` throughout). The NewtonianVAE paper anneals from
    /// 0.001 between epochs 30 and 60 of 300.
    pub kl_start: f64,
    #[serde(default)]
    pub kl_anneal_begin: u64,
    pub kl_anneal_steps: u64,
    /// Frames per training window: a window of `L` consecutive frames of one episode gives
    /// `L - 2` terms of the sequence ELBO (each predicts frame `t + 1` from frames `t - 1`, `t`
    /// and `u_t`). The batch is `batch_size` windows.
    #[serde(default = "default_sequence_len")]
    pub sequence_len: usize,
    /// Share of the dataset's episodes (the last ones) held out for the validation ELBO; 0
    /// trains on every episode and validates nothing.
    #[serde(default)]
    pub validation_share: f64,
    /// Steps between validation ELBOs (written to `validation.csv`).
    #[serde(default = "default_validate_every")]
    pub validate_every: u64,
    /// Stopping rule: training ends once the validation ELBO at `beta = 1` has not improved on
    /// its best by more than `plateau_tolerance` (relative) for `plateau_patience`
    /// validations in a row (0: train for `steps`).
    #[serde(default)]
    pub plateau_patience: u64,
    #[serde(default = "default_plateau_tolerance")]
    pub plateau_tolerance: f64,
    /// The controller on the posterior mean.
    pub pid: PidController,
}

/// ProCL's preset sharpness: at 1 the fresh soft-argmax barely moves with the scene.
fn default_sharpness() -> f64 {
    30.0
}

/// Ten frames: eight ELBO terms per window, and the reacher's episodes of 10 steps hold one.
fn default_sequence_len() -> usize {
    10
}

fn default_validate_every() -> u64 {
    100
}

fn default_plateau_tolerance() -> f64 {
    1e-3
}

impl NvaeConfig {
    /// Defaults for an environment with `du` action dimensions.
    pub fn for_action_dim(du: usize) -> Self {
        Self {
            latent_dim: du,
            trunk_channels: [16, 32],
            encoder_head: EncoderHead::SoftArgmax {
                keypoints: 16,
                hidden: 0,
                polar: false,
                pairwise_angles: false,
            },
            keypoint_sharpness: default_sharpness(),
            decoder_hidden: 128,
            decoder_channels: [32, 16, 8],
            transition_hidden: 16,
            dt_s: None,
            fixed_transition: None,
            init_prior_std: 0.1,
            recon_std: 0.1,
            kl_standard_weight: 1.0,
            kl_start: 0.001,
            kl_anneal_begin: 500,
            kl_anneal_steps: 500,
            sequence_len: default_sequence_len(),
            validation_share: 0.1,
            validate_every: 200,
            plateau_patience: 5,
            plateau_tolerance: default_plateau_tolerance(),
            pid: PidController::default(),
        }
    }

    /// The `dt` of the latent dynamics for an environment with control period `env_dt_s`.
    pub fn dt(&self, env_dt_s: f64) -> f64 {
        self.dt_s.unwrap_or(env_dt_s)
    }

    /// The transition KL's weight `beta` at training step `step` (0-based).
    pub fn kl_weight(&self, step: u64) -> f64 {
        if step >= self.kl_anneal_end() {
            return 1.0;
        }
        let into = step.saturating_sub(self.kl_anneal_begin) as f64;
        self.kl_start + (1.0 - self.kl_start) * into / self.kl_anneal_steps as f64
    }

    /// The first step at which `beta = 1`.
    pub fn kl_anneal_end(&self) -> u64 {
        if self.kl_anneal_steps == 0 {
            return 0;
        }
        self.kl_anneal_begin + self.kl_anneal_steps
    }

    /// Rejects invalid values with the field's name.
    pub fn validate(&self) -> Result<()> {
        let sizes = [
            ("nvae.latent_dim", self.latent_dim),
            ("nvae.decoder_hidden", self.decoder_hidden),
            ("nvae.transition_hidden", self.transition_hidden),
            ("nvae.validate_every", self.validate_every as usize),
        ];
        for (field, value) in sizes {
            if value == 0 {
                return Err(Error::config(field, "must be at least 1"));
            }
        }
        if self.decoder_channels.contains(&0) {
            return Err(Error::config(
                "nvae.decoder_channels",
                "channels must be positive",
            ));
        }
        let positive = [
            ("nvae.init_prior_std", Some(self.init_prior_std)),
            ("nvae.keypoint_sharpness", Some(self.keypoint_sharpness)),
            ("nvae.recon_std", Some(self.recon_std)),
            ("nvae.dt_s", self.dt_s),
            ("nvae.pid.kp", Some(self.pid.kp)),
            ("nvae.plateau_tolerance", Some(self.plateau_tolerance)),
        ];
        for (field, value) in positive {
            if let Some(value) = value
                && !(value.is_finite() && value > 0.0)
            {
                return Err(Error::config(field, format!("{value} must be > 0")));
            }
        }
        let non_negative = [
            ("nvae.kl_standard_weight", self.kl_standard_weight),
            ("nvae.pid.ki", self.pid.ki),
            ("nvae.pid.kd", self.pid.kd),
        ];
        for (field, value) in non_negative {
            if !(value.is_finite() && value >= 0.0) {
                return Err(Error::config(
                    field,
                    format!("{value} must be finite and >= 0"),
                ));
            }
        }
        if let Some([a, b, c]) = self.fixed_transition
            && !([a, b, c].iter().all(|x| x.is_finite()) && b <= 0.0 && c > 0.0)
        {
            return Err(Error::config(
                "nvae.fixed_transition",
                format!("[{a}, {b}, {c}] must be finite with B <= 0 (damping) and C > 0"),
            ));
        }
        if self.sequence_len < 3 {
            return Err(Error::config(
                "nvae.sequence_len",
                format!(
                    "{} frames hold no ELBO term (a term needs frames t - 1, t and t + 1)",
                    self.sequence_len
                ),
            ));
        }
        if !(0.0..0.5).contains(&self.validation_share) {
            return Err(Error::config(
                "nvae.validation_share",
                format!("{} must be in [0, 0.5)", self.validation_share),
            ));
        }
        if self.plateau_patience > 0 && self.validation_share == 0.0 {
            return Err(Error::config(
                "nvae.plateau_patience",
                "the stopping rule reads the validation ELBO: set nvae.validation_share > 0",
            ));
        }
        if !(0.0..=1.0).contains(&self.kl_start) {
            return Err(Error::config(
                "nvae.kl_start",
                format!("{} must be in [0, 1]", self.kl_start),
            ));
        }
        self.encoder_config().validate().map_err(|e| match e {
            Error::InvalidConfig { message, .. } => Error::config("nvae.encoder_head", message),
            other => other,
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn kl_weight_anneals_linearly_to_one() {
        let mut config = NvaeConfig {
            kl_start: 0.2,
            kl_anneal_begin: 0,
            kl_anneal_steps: 4,
            ..NvaeConfig::for_action_dim(2)
        };
        for (step, want) in [0.2, 0.4, 0.6, 0.8, 1.0, 1.0].into_iter().enumerate() {
            let got = config.kl_weight(step as u64);
            assert!((got - want).abs() < 1e-12, "step {step}: {got}");
        }
        // A delayed start holds kl_start first.
        config.kl_anneal_begin = 3;
        for (step, want) in [0.2, 0.2, 0.2, 0.2, 0.4, 0.6, 0.8, 1.0]
            .into_iter()
            .enumerate()
        {
            let got = config.kl_weight(step as u64);
            assert!((got - want).abs() < 1e-12, "step {step}: {got}");
        }
        assert_eq!(config.kl_anneal_end(), 7);
        config.kl_anneal_steps = 0;
        assert_eq!(config.kl_weight(0), 1.0);
        assert_eq!(config.kl_anneal_end(), 0);
    }

    #[test]
    fn bad_values_are_refused_by_name() {
        let base = NvaeConfig::for_action_dim(2);
        let cases = [
            (
                "nvae.recon_std",
                NvaeConfig {
                    recon_std: 0.0,
                    ..base.clone()
                },
            ),
            (
                "nvae.dt_s",
                NvaeConfig {
                    dt_s: Some(-0.1),
                    ..base.clone()
                },
            ),
            (
                "nvae.kl_start",
                NvaeConfig {
                    kl_start: 1.5,
                    ..base.clone()
                },
            ),
            (
                "nvae.sequence_len",
                NvaeConfig {
                    sequence_len: 2,
                    ..base.clone()
                },
            ),
            (
                "nvae.plateau_patience",
                NvaeConfig {
                    plateau_patience: 3,
                    validation_share: 0.0,
                    ..base.clone()
                },
            ),
            (
                "nvae.decoder_channels",
                NvaeConfig {
                    decoder_channels: [8, 0, 8],
                    ..base.clone()
                },
            ),
            (
                "nvae.pid.ki",
                NvaeConfig {
                    pid: PidController {
                        ki: f64::NAN,
                        ..base.pid
                    },
                    ..base.clone()
                },
            ),
            (
                "nvae.encoder_head",
                NvaeConfig {
                    encoder_head: EncoderHead::Mlp { hidden: 0 },
                    ..base.clone()
                },
            ),
        ];
        for (field, config) in cases {
            let err = config.validate().unwrap_err().to_string();
            assert!(err.contains(field), "{field}: {err}");
        }
        assert!(base.validate().is_ok());
    }
}
