//! ProCL's losses, one function per equation of the paper (and spec.md 3), each returning a
//! scalar tensor; [`procl_loss`] combines them and returns the per-term breakdown for logging.

use burn::tensor::activation::{log_softmax, relu};
use burn::tensor::{Tensor, TensorData};

use crate::error::{Error, Result};
use crate::model::{Dynamics, Transition};

/// Where the latent noise `eps` on `E(x_{t+1})` enters (spec.md 3.1).
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum NoiseMode {
    /// As the paper: noise on `h_{t+1}` before CPC, consistency and the Lyapunov risk, so it
    /// reaches `v_{t+1} = (h_{t+1} - h_t)/dt` amplified by `1/dt`.
    Paper,
    /// Noise for CPC and consistency only; the Lyapunov risk sees clean encodings.
    CleanRisk,
}

/// Loss weights and hyperparameters; defaults are the paper's (spec.md 3).
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
    /// Stop gradients through the hindsight targets `h*`, `v*`.
    pub detach_targets: bool,
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
            detach_targets: false,
        }
    }
}

impl LossConfig {
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
        ];
        for (field, value) in non_negative {
            if !(value.is_finite() && value >= 0.0) {
                return Err(Error::config(
                    field,
                    format!("{value} must be finite and >= 0"),
                ));
            }
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

/// `log N(x_i | mean_j, diag(exp(log_std))^2)` for every pair: `x [n, d]`, `mean [m, d]`,
/// `log_std [d]` -> `[n, m]`. Row `i` scores `x_i` under every transition `j`.
pub fn pairwise_gaussian_log_density(
    x: Tensor<2>,
    mean: Tensor<2>,
    log_std: Tensor<1>,
) -> Tensor<2> {
    let [n, d] = x.dims();
    let m = mean.dims()[0];
    let inv_std = log_std.clone().neg().exp().reshape([1, 1, d]);
    let diff = (x.reshape([n, 1, d]) - mean.reshape([1, m, d])) * inv_std; // [n, m, d]
    let quad = diff.powi_scalar(2).sum_dim(2).reshape([n, m]) * (-0.5);
    let norm = log_std.sum() + 0.5 * d as f64 * (2.0 * std::f64::consts::PI).ln();
    quad - norm.reshape([1, 1])
}

/// CPC (paper eq. 3): `-mean_i log softmax_j log F(z'_i | z_j, u_j)`, from the `[K, K]` matrix
/// of [`pairwise_gaussian_log_density`].
pub fn cpc_loss(log_density: Tensor<2>) -> Tensor<1> {
    let log_probs = log_softmax(log_density, 1);
    diagonal(log_probs).mean().neg().reshape([1])
}

/// Consistency (paper eq. 4): `-mean_i log F(z'_i | z_i, u_i)`.
pub fn consistency_loss(log_density: Tensor<2>) -> Tensor<1> {
    diagonal(log_density).mean().neg().reshape([1])
}

/// The diagonal of a square `[n, n]` matrix as `[n]`.
fn diagonal(matrix: Tensor<2>) -> Tensor<1> {
    let n = matrix.dims()[0];
    let eye: Vec<f32> = (0..n * n)
        .map(|k| if k / n == k % n { 1.0 } else { 0.0 })
        .collect();
    let eye = Tensor::from_data(TensorData::new(eye, [n, n]), &matrix.device());
    (matrix * eye).sum_dim(1).reshape([n])
}

/// Curvature (paper eq. 5, with a true Jacobian-vector product as spec.md 3 requires):
/// `mean_i || f(z+eta_z, u+eta_u) - f(z, u) - (J_z eta_z + J_u eta_u) ||^2`.
#[allow(clippy::too_many_arguments)]
pub fn curvature_loss(
    dynamics: &Dynamics,
    h: Tensor<2>,
    v: Tensor<2>,
    u: Tensor<2>,
    eta_h: Tensor<2>,
    eta_v: Tensor<2>,
    eta_u: Tensor<2>,
    dt: f64,
) -> Tensor<1> {
    let (base, jvp) = dynamics.forward_jvp(
        h.clone(),
        v.clone(),
        u.clone(),
        Some((eta_h.clone(), eta_v.clone(), eta_u.clone())),
        dt,
    );
    let jvp = jvp.expect("tangent requested");
    let perturbed = dynamics.forward(h + eta_h, v + eta_v, u + eta_u, dt);
    let residual = perturbed.z() - base.z() - jvp.z(); // [n, 2 du]
    residual.powi_scalar(2).sum_dim(1).mean().reshape([1])
}

/// The hindsight pseudo-target (paper eq. 9): `v*` is `v` permuted across the batch, and
/// `h* = h + Kp^-1 (u - Kd (v* - v))` so that PD toward `(h*, v*)` reproduces `u` exactly.
pub fn hindsight_targets(
    h: Tensor<2>,
    v: Tensor<2>,
    u: Tensor<2>,
    permutation: &[usize],
    kp: f64,
    kd: f64,
) -> (Tensor<2>, Tensor<2>) {
    let index = Tensor::<1, burn::tensor::Int>::from_data(
        TensorData::new(
            permutation.iter().map(|&i| i as i64).collect::<Vec<_>>(),
            [permutation.len()],
        ),
        &v.device(),
    );
    let v_target = v.clone().select(0, index);
    let h_target = h + (u - (v_target.clone() - v) * kd) / kp;
    (h_target, v_target)
}

/// `V(z) = h^T Q_h h + v^T Q_v v` per row: `[n, du]` twice -> `[n]`.
fn lyapunov_value(h: Tensor<2>, v: Tensor<2>, q_h: f64, q_v: f64) -> Tensor<1> {
    let n = h.dims()[0];
    (h.powi_scalar(2).sum_dim(1) * q_h + v.powi_scalar(2).sum_dim(1) * q_v).reshape([n])
}

/// Latent PD-control Lyapunov risk (paper eqs. 7, 10):
/// `mean max(0, (V(z_{t+1} - z*) - V(z_t - z*)) / dt_R)`.
#[allow(clippy::too_many_arguments)]
pub fn lyapunov_risk(
    z_now: (Tensor<2>, Tensor<2>),
    z_next: (Tensor<2>, Tensor<2>),
    z_target: (Tensor<2>, Tensor<2>),
    q_h: f64,
    q_v: f64,
    dt_r: f64,
) -> Tensor<1> {
    let (h_star, v_star) = z_target;
    let before = lyapunov_value(z_now.0 - h_star.clone(), z_now.1 - v_star.clone(), q_h, q_v);
    let after = lyapunov_value(z_next.0 - h_star, z_next.1 - v_star, q_h, q_v);
    relu((after - before) / dt_r).mean().reshape([1])
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
}

/// The loss terms of one step (unweighted) and the weighted total.
#[derive(Debug, Clone)]
pub struct LossTerms {
    pub cpc: Tensor<1>,
    pub cons: Tensor<1>,
    pub curv: Tensor<1>,
    pub lyap: Tensor<1>,
    pub total: Tensor<1>,
}

/// Names of the logged terms, in [`LossValues::as_array`] order.
pub const LOSS_NAMES: [&str; 5] = ["total", "cpc", "cons", "curv", "lyap"];

/// Loss values read back to the host, for logging.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct LossValues {
    pub total: f64,
    pub cpc: f64,
    pub cons: f64,
    pub curv: f64,
    pub lyap: f64,
}

impl LossValues {
    pub fn as_array(&self) -> [f64; 5] {
        [self.total, self.cpc, self.cons, self.curv, self.lyap]
    }
    pub fn is_finite(&self) -> bool {
        self.as_array().iter().all(|x| x.is_finite())
    }
}

impl LossTerms {
    /// Reads every term back (one device sync).
    pub fn values(&self) -> LossValues {
        let all = Tensor::cat(
            vec![
                self.total.clone(),
                self.cpc.clone(),
                self.cons.clone(),
                self.curv.clone(),
                self.lyap.clone(),
            ],
            0,
        );
        let v = crate::model::to_vec(all);
        LossValues {
            total: v[0] as f64,
            cpc: v[1] as f64,
            cons: v[2] as f64,
            curv: v[3] as f64,
            lyap: v[4] as f64,
        }
    }
}

/// The ProCL objective (paper eq. 11): `lambda_pc3 (lambda_cpc L_cpc + lambda_cons L_cons +
/// lambda_curv L_curv) + lambda_R R`. PC3 is the same with `lambda_R = 0`.
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
    } = inputs;
    let v_now = (h_now.clone() - h_prev) / dt;
    let h_next_noisy = h_next.clone() + latent_noise * config.latent_noise_std;
    let v_next_noisy = (h_next_noisy.clone() - h_now.clone()) / dt;

    // PC3 terms: score the (noisy) next latent under every transition of the batch.
    let predicted: Transition = dynamics.forward(h_now.clone(), v_now.clone(), u.clone(), dt);
    let z_next = Tensor::cat(vec![h_next_noisy.clone(), v_next_noisy.clone() * dt], 1);
    let du = h_now.dims()[1] as f64;
    // Scored in (h', dt v') coordinates; + du ln(1/dt) makes it exactly log F(z' | z, u).
    let log_density =
        pairwise_gaussian_log_density(z_next, predicted.z_scaled(dt), dynamics.log_std.val())
            + du * (1.0 / dt).ln();
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

    // Lyapunov risk with hindsight targets.
    let (h_target, v_target) = hindsight_targets(
        h_now.clone(),
        v_now.clone(),
        u,
        &permutation,
        config.kp,
        config.kd,
    );
    let (h_target, v_target) = if config.detach_targets {
        (h_target.detach(), v_target.detach())
    } else {
        (h_target, v_target)
    };
    let z_after = match config.noise_mode {
        NoiseMode::Paper => (h_next_noisy, v_next_noisy),
        NoiseMode::CleanRisk => (h_next.clone(), (h_next - h_now.clone()) / dt),
    };
    let dt_r = config.lyapunov_dt_s.unwrap_or(dt);
    let lyap = lyapunov_risk(
        (h_now, v_now),
        z_after,
        (h_target, v_target),
        config.q_h,
        config.q_v,
        dt_r,
    );

    let pc3 = cpc.clone() * config.lambda_cpc
        + cons.clone() * config.lambda_cons
        + curv.clone() * config.lambda_curv;
    let total = pc3 * config.lambda_pc3 + lyap.clone() * config.lambda_r;
    LossTerms {
        cpc,
        cons,
        curv,
        lyap,
        total,
    }
}
