//! ProCL's objective (paper section III-B, eq. 13): the PC3 terms ([`pc3`]), the latent
//! PD-control Lyapunov risk with hindsight targets ([`lyapunov`]) and the regularisers the
//! reacher preset adds ([`regularisers`]; docs/design.md), combined by [`procl_loss`].

mod lyapunov;
mod pc3;
mod regularisers;

pub(crate) use lyapunov::risk_scale;
pub use lyapunov::{hindsight_targets, lyapunov_risk};
pub use pc3::{consistency_loss, cpc_loss, curvature_loss, pairwise_gaussian_log_density};
pub use regularisers::action_response_sign;

use burn::tensor::Tensor;

use crate::error::{Error, Result};
use crate::model::{Dynamics, Transition};

/// Where the latent noise `eps` on `E(x_{t+1})` enters (paper section III-C).
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum NoiseMode {
    /// As the paper: noise on `h_{t+1}` before CPC, consistency and the Lyapunov risk, so it
    /// reaches `v_{t+1} = (h_{t+1} - h_t)/dt` amplified by `1/dt`.
    Paper,
    /// Noise for CPC and consistency only; the Lyapunov risk sees clean encodings.
    CleanRisk,
}

/// Loss weights and hyperparameters; the defaults are the paper's.
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(deny_unknown_fields)]
pub struct LossConfig {
    pub lambda_pc3: f64,
    pub lambda_r: f64,
    pub lambda_cpc: f64,
    pub lambda_cons: f64,
    pub lambda_curv: f64,
    /// Std of the Gaussian noise added to the next-step encoding.
    pub latent_noise_std: f64,
    pub noise_mode: NoiseMode,
    /// Std of the curvature perturbations `eta_z`, `eta_u`.
    pub curvature_std: f64,
    /// PD gains `Kp = kp I`, `Kd = kd I` of the hindsight labelling.
    pub kp: f64,
    pub kd: f64,
    /// Lyapunov weights `Q_h = q_h I`, `Q_v = q_v I`.
    pub q_h: f64,
    pub q_v: f64,
    /// `dt_R` of the finite-difference Lie derivative, seconds (`None`: the env's control dt).
    pub lyapunov_dt_s: Option<f64>,
    /// Compute the Lyapunov risk on the batch-standardised latent `c h / std(h)` (per
    /// dimension, batch std of `h_t`, gradient through the std) with `c` this value (`None`: on
    /// `h` as it is, the paper). The risk then cannot be lowered by shrinking the latent, and
    /// its scale against the hindsight offset `u / Kp` is fixed at `c`. The controller runs on
    /// `h`, so `Kp` and `Kd` should match `h`'s scale over `c` (docs/design.md). In a config
    /// file `0` means off (the way to undo a preset that sets it).
    #[serde(default, deserialize_with = "zero_is_none")]
    pub risk_latent_std: Option<f64>,
    /// Steps `k` over which the sign term reads the latent's response to the action (1: the
    /// second difference of one step). One step's action moves a slow latent little against
    /// frame-to-frame jitter; over `k` steps the response
    /// `h_{t+k} - h_t - k (h_t - h_{t-1}) = dt^2 sum_j (k - j) B u_{t+j}` (Euler, `B` the input
    /// gain) grows like `k^2` for a held action while the jitter grows like `k`, and the term
    /// regresses it on the drive `sum_j (k - j) u_{t+j}`. Needs episodes longer than `k + 1`.
    #[serde(default = "default_action_response_horizon")]
    pub action_response_horizon: usize,
    /// Fit the response `h_{t+k} - h_t` on the velocity step `h_t - h_{t-1}` as well as the
    /// drive, with its own coefficients, instead of extrapolating the velocity `k` steps
    /// (false). A heavily damped joint (the reacher's wrist) loses its velocity within about
    /// a step, so the extrapolation is wrong for it.
    #[serde(default)]
    pub action_response_velocity: bool,
    /// Sign term (0: off, the paper): adds `action_response_sign_weight * mean_r sum_i
    /// relu(-D_r[i, i]) / s`, where `D_r` is the drive block of the least-squares response map
    /// fitted in each of `action_response_regions` groups of the batch (contiguous along the
    /// first principal axis of `h_t`) and `s` the root mean square entry of the whole batch's
    /// drive block (held fixed). PD on `h` with one gain per coordinate needs the action on
    /// `h_i` to move `h_i` forwards everywhere: near a goal the loop is
    /// `h'' = -B (Kp dh + Kd h')` with `B = J M(q)^-1`, unstable once a diagonal entry of `B`
    /// turns negative, which is where a latent hooks back.
    #[serde(default)]
    pub action_response_sign_weight: f64,
    /// Groups of the sign term; at least 2. A group must be narrow enough to see a hook.
    #[serde(default = "default_action_response_regions")]
    pub action_response_regions: usize,
    /// Singular-value floor of the sign term: each group's charge also gets `relu(rho -
    /// sigma_min(D_r) / s)`, `rho` this value (0: off). The sign term asks each coordinate to
    /// move forwards under its own action, not to move by much; PD on `h` moves a joint only
    /// as far as its action moves `h`, so a direction the action barely moves is one PD cannot
    /// resolve. `sigma_min` comes from the host's SVD of the group's map, its singular vectors
    /// held fixed (its exact gradient where it is simple).
    #[serde(default)]
    pub action_response_singular_floor: f64,
}

fn default_action_response_horizon() -> usize {
    1
}

fn default_action_response_regions() -> usize {
    3
}

/// Reads an optional number where `0` (like a missing value) means off.
fn zero_is_none<'de, D: serde::Deserializer<'de>>(
    deserializer: D,
) -> std::result::Result<Option<f64>, D::Error> {
    let value: Option<f64> = serde::Deserialize::deserialize(deserializer)?;
    Ok(value.filter(|&v| v != 0.0))
}

impl Default for LossConfig {
    fn default() -> Self {
        Self {
            lambda_pc3: 1.0,
            lambda_r: 10.0,
            lambda_cpc: 1.0,
            lambda_cons: 1.0,
            lambda_curv: 10.0,
            latent_noise_std: 0.01,
            noise_mode: NoiseMode::Paper,
            curvature_std: 0.1,
            kp: 10.0,
            kd: 2.0,
            q_h: 1.0,
            q_v: 0.1,
            lyapunov_dt_s: None,
            risk_latent_std: None,
            action_response_horizon: default_action_response_horizon(),
            action_response_velocity: false,
            action_response_sign_weight: 0.0,
            action_response_regions: default_action_response_regions(),
            action_response_singular_floor: 0.0,
        }
    }
}

impl LossConfig {
    /// How many steps past `t` a training sample's frames reach: the sign term's horizon `k`
    /// when the term is on (it reads `i_{t+k}`), else 1 (`i_{t+1}`).
    pub fn frames_ahead(&self) -> usize {
        if self.reads_action_response() {
            self.action_response_horizon
        } else {
            1
        }
    }

    /// Whether the sign term is on (it reads the latent's response to the action).
    pub fn reads_action_response(&self) -> bool {
        self.action_response_sign_weight > 0.0
    }

    /// Rejects values that make no sense (negative weights or noise, zero gains).
    pub fn validate(&self) -> Result<()> {
        let non_negative = [
            ("loss.lambda_pc3", self.lambda_pc3),
            ("loss.lambda_r", self.lambda_r),
            ("loss.lambda_cpc", self.lambda_cpc),
            ("loss.lambda_cons", self.lambda_cons),
            ("loss.lambda_curv", self.lambda_curv),
            ("loss.latent_noise_std", self.latent_noise_std),
            ("loss.curvature_std", self.curvature_std),
            ("loss.kd", self.kd),
            ("loss.q_h", self.q_h),
            ("loss.q_v", self.q_v),
            (
                "loss.action_response_sign_weight",
                self.action_response_sign_weight,
            ),
            (
                "loss.action_response_singular_floor",
                self.action_response_singular_floor,
            ),
        ];
        if let Some(c) = self.risk_latent_std
            && !(c.is_finite() && c > 0.0)
        {
            return Err(Error::config(
                "loss.risk_latent_std",
                format!("{c} must be finite and > 0"),
            ));
        }
        for (field, value) in non_negative {
            if !(value.is_finite() && value >= 0.0) {
                return Err(Error::config(
                    field,
                    format!("{value} must be finite and >= 0"),
                ));
            }
        }
        if self.action_response_regions < 2 {
            return Err(Error::config(
                "loss.action_response_regions",
                format!(
                    "{} must be at least 2 (one map is compared with several)",
                    self.action_response_regions
                ),
            ));
        }
        if self.action_response_horizon == 0 {
            return Err(Error::config(
                "loss.action_response_horizon",
                "0 must be at least 1 (steps)",
            ));
        }
        if !(self.kp.is_finite() && self.kp > 0.0) {
            return Err(Error::config(
                "loss.kp",
                format!("{} must be > 0 (Kp is inverted)", self.kp),
            ));
        }
        if let Some(dt) = self.lyapunov_dt_s
            && !(dt.is_finite() && dt > 0.0)
        {
            return Err(Error::config(
                "loss.lyapunov_dt_s",
                format!("{dt} must be > 0"),
            ));
        }
        Ok(())
    }
}

/// The encodings of one batch of samples `(i_{t-1}, i_t, u_t, i_{t+1})` and the random draws
/// the losses use (drawn by the caller from its seeded RNG, so tests can pin them).
#[derive(Debug, Clone)]
pub struct LossInputs {
    /// `h_{t-1}, h_t, h_{t+1}`: `[n, du]` each.
    pub h_prev: Tensor<2>,
    pub h_now: Tensor<2>,
    pub h_next: Tensor<2>,
    /// `u_t`: `[n, du]`.
    pub u: Tensor<2>,
    /// Standard normal noise for `E(x_{t+1})`: `[n, du]`.
    pub latent_noise: Tensor<2>,
    /// Standard normal curvature perturbations for `h`, `v`, `u`: `[n, du]` each.
    pub curvature_noise: (Tensor<2>, Tensor<2>, Tensor<2>),
    /// Batch permutation that draws `v*` from the batch's `v`.
    pub permutation: Vec<usize>,
    /// For the `k`-step sign term (`k > 1` and the term on): `h_{t+k}` and the drive
    /// `sum_{j<k} (k - j) u_{t+j}`, `[n, du]` each. `None`: the term reads one step.
    pub ahead: Option<(Tensor<2>, Tensor<2>)>,
}

/// The loss terms of one step (unweighted) and the weighted total. A term that is switched
/// off is 0.
#[derive(Debug, Clone)]
pub struct LossTerms {
    pub cpc: Tensor<1>,
    pub cons: Tensor<1>,
    pub curv: Tensor<1>,
    pub lyap: Tensor<1>,
    /// The sign term (`loss.action_response_sign_weight`).
    pub sign: Tensor<1>,
    pub total: Tensor<1>,
}

/// Names of the logged terms, in [`LossValues::as_array`] order (metrics.csv's columns).
pub const LOSS_NAMES: [&str; 6] = ["total", "cpc", "cons", "curv", "lyap", "sign"];

/// Loss values read back to the host, for logging.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct LossValues {
    pub total: f64,
    pub cpc: f64,
    pub cons: f64,
    pub curv: f64,
    pub lyap: f64,
    pub sign: f64,
}

impl LossValues {
    pub fn as_array(&self) -> [f64; 6] {
        [
            self.total, self.cpc, self.cons, self.curv, self.lyap, self.sign,
        ]
    }
    pub fn is_finite(&self) -> bool {
        self.as_array().iter().all(|x| x.is_finite())
    }
}

impl LossTerms {
    /// Reads every term back (one device sync).
    pub fn values(&self) -> LossValues {
        let v = crate::model::read_scalars(&[
            &self.total,
            &self.cpc,
            &self.cons,
            &self.curv,
            &self.lyap,
            &self.sign,
        ]);
        LossValues {
            total: v[0],
            cpc: v[1],
            cons: v[2],
            curv: v[3],
            lyap: v[4],
            sign: v[5],
        }
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

/// The sign term of one batch, or 0 when it is off.
fn sign_term(
    config: &LossConfig,
    h_prev: Tensor<2>,
    h_now: Tensor<2>,
    h_next: Tensor<2>,
    u: Tensor<2>,
    ahead: Option<(Tensor<2>, Tensor<2>)>,
) -> Tensor<1> {
    if !config.reads_action_response() {
        return Tensor::zeros([1], &h_now.device());
    }
    // Without `ahead` the term reads one step, whatever the configured horizon.
    let (k, (h_ahead, drive)) = match ahead {
        Some(ahead) => (config.action_response_horizon as f64, ahead),
        None => (1.0, (h_next, u)),
    };
    let step = h_now.clone() - h_prev; // dt v_t
    let moved = h_ahead - h_now.clone(); // h_{t+k} - h_t
    let (response, regressors) = if config.action_response_velocity {
        (moved, Tensor::cat(vec![step, drive], 1))
    } else {
        (moved - step * k, drive)
    };
    action_response_sign(
        response,
        regressors,
        h_now,
        config.action_response_regions,
        config.action_response_singular_floor,
    )
}

/// The ProCL objective (paper eq. 13): `lambda_pc3 (lambda_cpc L_cpc + lambda_cons L_cons +
/// lambda_curv L_curv) + lambda_R R`, plus the configured regularisers. PC3 is the same with
/// `lambda_R = 0`.
pub fn procl_loss(
    config: &LossConfig,
    dynamics: &Dynamics,
    inputs: LossInputs,
    dt: f64,
) -> LossTerms {
    let LossInputs {
        h_prev,
        h_now,
        h_next,
        u,
        latent_noise,
        curvature_noise,
        permutation,
        ahead,
    } = inputs;
    let sign = sign_term(
        config,
        h_prev.clone(),
        h_now.clone(),
        h_next.clone(),
        u.clone(),
        ahead,
    );
    let v_now = (h_now.clone() - h_prev) / dt;
    let h_next_noisy = h_next.clone() + latent_noise * config.latent_noise_std;
    let v_next_noisy = (h_next_noisy.clone() - h_now.clone()) / dt;

    // PC3 terms: score the (noisy) next latent under every transition of the batch.
    let predicted: Transition = dynamics.forward(h_now.clone(), v_now.clone(), u.clone(), dt);
    // Scored in unoriented (h', dt v') coordinates, where the std is diagonal. The density of
    // v' is that of dt v' times dt per dimension, so + du ln(dt) makes it exactly log F(z'|z,u).
    let unoriented = |h: Tensor<2>, v: Tensor<2>| {
        Tensor::cat(vec![dynamics.unoriented(h), dynamics.unoriented(v) * dt], 1)
    };
    let z_next = unoriented(h_next_noisy.clone(), v_next_noisy.clone());
    let z_predicted = unoriented(predicted.h_next, predicted.v_next);
    let du = h_now.dims()[1] as f64;
    let log_density =
        pairwise_gaussian_log_density(z_next, z_predicted, dynamics.log_std.val()) + du * dt.ln();
    let cpc = cpc_loss(log_density.clone());
    let cons = consistency_loss(log_density);
    let (eta_h, eta_v, eta_u) = curvature_noise;
    let s = config.curvature_std;
    let curv = curvature_loss(
        dynamics,
        h_now.clone(),
        v_now.clone(),
        u.clone(),
        eta_h * s,
        eta_v * s,
        eta_u * s,
        dt,
    );

    // Lyapunov risk with hindsight targets, on the standardised latent if asked (one scale
    // for every latent of the sample, so velocities stay finite differences of positions).
    let z_after = match config.noise_mode {
        NoiseMode::Paper => (h_next_noisy, v_next_noisy),
        NoiseMode::CleanRisk => (h_next.clone(), (h_next - h_now.clone()) / dt),
    };
    let (h_now, v_now, z_after) = match risk_scale(config, h_now.clone()) {
        Some(scale) => (
            h_now * scale.clone(),
            v_now * scale.clone(),
            (z_after.0 * scale.clone(), z_after.1 * scale),
        ),
        None => (h_now, v_now, z_after),
    };
    let z_target = hindsight_targets(
        h_now.clone(),
        v_now.clone(),
        u,
        &permutation,
        config.kp,
        config.kd,
    );
    let dt_r = config.lyapunov_dt_s.unwrap_or(dt);
    let lyap = lyapunov_risk(
        (h_now, v_now),
        z_after,
        z_target,
        config.q_h,
        config.q_v,
        dt_r,
    );

    let pc3 = cpc.clone() * config.lambda_cpc
        + cons.clone() * config.lambda_cons
        + curv.clone() * config.lambda_curv;
    let total = pc3 * config.lambda_pc3
        + lyap.clone() * config.lambda_r
        + sign.clone() * config.action_response_sign_weight;
    LossTerms {
        cpc,
        cons,
        curv,
        lyap,
        sign,
        total,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn loss_config_validate_rejects_bad_values() {
        assert!(LossConfig::default().validate().is_ok());
        let field_of = |config: LossConfig| match config.validate() {
            Err(Error::InvalidConfig { field, .. }) => field,
            other => panic!("expected InvalidConfig, got {other:?}"),
        };
        let bad = |edit: fn(&mut LossConfig)| {
            let mut config = LossConfig::default();
            edit(&mut config);
            field_of(config)
        };
        assert_eq!(bad(|c| c.lambda_r = -1.0), "loss.lambda_r");
        assert_eq!(bad(|c| c.lambda_cpc = -0.5), "loss.lambda_cpc");
        assert_eq!(bad(|c| c.lambda_curv = f64::NAN), "loss.lambda_curv");
        assert_eq!(bad(|c| c.latent_noise_std = -0.1), "loss.latent_noise_std");
        assert_eq!(bad(|c| c.curvature_std = -1e-3), "loss.curvature_std");
        assert_eq!(bad(|c| c.kp = 0.0), "loss.kp");
        assert_eq!(bad(|c| c.kp = -2.0), "loss.kp");
        assert_eq!(bad(|c| c.kp = f64::INFINITY), "loss.kp");
        assert_eq!(bad(|c| c.lyapunov_dt_s = Some(0.0)), "loss.lyapunov_dt_s");
        assert_eq!(
            bad(|c| c.action_response_sign_weight = f64::NAN),
            "loss.action_response_sign_weight"
        );
        assert_eq!(
            bad(|c| c.action_response_singular_floor = -0.1),
            "loss.action_response_singular_floor"
        );
        assert_eq!(
            bad(|c| c.action_response_regions = 1),
            "loss.action_response_regions"
        );
        assert_eq!(
            bad(|c| c.action_response_horizon = 0),
            "loss.action_response_horizon"
        );
        assert_eq!(
            bad(|c| c.risk_latent_std = Some(-1.0)),
            "loss.risk_latent_std"
        );
        // Zero weights and kd = 0 are allowed (PC3 is lambda_r = 0).
        let mut ok = LossConfig {
            lambda_r: 0.0,
            kd: 0.0,
            latent_noise_std: 0.0,
            ..LossConfig::default()
        };
        assert!(ok.validate().is_ok());
        ok.lyapunov_dt_s = Some(0.05);
        assert!(ok.validate().is_ok());
    }
}

/// Small tensors and comparisons the loss tests share.
#[cfg(test)]
pub(crate) mod test_support {
    use burn::tensor::{Device, Tensor, TensorData};

    use crate::model::to_vec;

    pub fn t2(values: &[f32], rows: usize, cols: usize, device: &Device) -> Tensor<2> {
        Tensor::from_data(TensorData::new(values.to_vec(), [rows, cols]), device)
    }

    pub fn t1(values: &[f32], device: &Device) -> Tensor<1> {
        Tensor::from_data(TensorData::new(values.to_vec(), [values.len()]), device)
    }

    pub fn scalar(t: Tensor<1>) -> f64 {
        let v = to_vec(t);
        assert_eq!(v.len(), 1);
        v[0] as f64
    }

    pub fn assert_close(got: &[f32], want: &[f64], tol: f64, what: &str) {
        assert_eq!(got.len(), want.len(), "{what}: length");
        for (k, (&g, &w)) in got.iter().zip(want).enumerate() {
            assert!(
                (g as f64 - w).abs() <= tol,
                "{what}[{k}]: got {g}, want {w} (tol {tol})"
            );
        }
    }
}
