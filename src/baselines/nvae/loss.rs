//! The NewtonianVAE objective, one function per term, and the ELBO on one training sample
//! `(i_{t-1}, i_t, u_t, i_{t+1})` with its per-term breakdown for logging.

use burn::tensor::Tensor;

use super::{NvaeConfig, NvaeModel};
use crate::losses::StepValues;

/// `KL(N(mean_q, diag(exp(log_std_q))^2) || N(mean_p, diag(exp(log_std_p))^2))` in closed
/// form, summed over dimensions and averaged over rows: `[n, d]` each (the prior's may be
/// `[1, d]`, broadcast) -> `[1]`.
pub fn gaussian_kl(
    mean_q: Tensor<2>,
    log_std_q: Tensor<2>,
    mean_p: Tensor<2>,
    log_std_p: Tensor<2>,
) -> Tensor<1> {
    // log(sigma_p / sigma_q) + (sigma_q^2 + (mu_q - mu_p)^2) / (2 sigma_p^2) - 1/2
    let var_q = (log_std_q.clone() * 2.0).exp();
    let inv_var_p = (log_std_p.clone() * -2.0).exp();
    let per_dim =
        log_std_p - log_std_q + (var_q + (mean_q - mean_p).powi_scalar(2)) * inv_var_p * 0.5 - 0.5; // [n, d]
    per_dim.sum_dim(1).mean().reshape([1])
}

/// Reconstruction NLL of a Gaussian decoder with fixed std `recon_std`, per frame:
/// `sum_pixels (frame - mean)^2 / (2 recon_std^2)` averaged over the `[n, 3, 64, 64]` frames.
/// The normalising constant `D ln(recon_std sqrt(2 pi))` (D = 12288) is left out: it moves
/// no parameter, and without it the logged value reads as a scaled squared error.
pub fn reconstruction_nll(mean: Tensor<4>, frames: Tensor<4>, recon_std: f64) -> Tensor<1> {
    let n = frames.dims()[0];
    let squared = (frames - mean).powi_scalar(2).reshape([n as i32, -1]); // [n, D]
    (squared.sum_dim(1).mean() / (2.0 * recon_std * recon_std)).reshape([1])
}

/// One batch of training samples as the ELBO sees them.
#[derive(Debug, Clone)]
pub struct ElboInputs {
    /// `[3n, 3, 64, 64]`: the frames `i_{t-1}` of every sample, then every `i_t`, then every
    /// `i_{t+1}`.
    pub frames: Tensor<4>,
    /// `u_t`: `[n, du]`.
    pub u: Tensor<2>,
    /// Standard normal draws for the reparameterised samples of `x`, in the frames' order:
    /// `[3n, du]`.
    pub noise: Tensor<2>,
}

/// The ELBO's terms on one batch (each a per-sample mean) and the weighted total to minimise.
#[derive(Debug, Clone)]
pub struct ElboTerms {
    /// Reconstruction NLL of the three frames, summed.
    pub recon: Tensor<1>,
    /// `KL(q(x_{t+1} | i_{t+1}) || p(x_{t+1} | x_t, v_t, u_t))`, unweighted.
    pub kl: Tensor<1>,
    /// `KL(q(x_t | i_t) || N(0, I))`, unweighted.
    pub kl_standard: Tensor<1>,
    /// `recon + beta kl + kl_standard_weight kl_standard` (the negative ELBO, up to the
    /// decoder's constant, when both weights are 1).
    pub total: Tensor<1>,
    /// The transition KL's weight this step.
    pub beta: f64,
}

/// Names of the logged NVAE terms (metrics.csv columns), in [`ElboTerms::values`] order.
pub const ELBO_NAMES: [&str; 5] = ["total", "recon", "kl", "kl_std", "beta"];

impl ElboTerms {
    /// Reads every term back (one device sync).
    pub fn values(&self) -> StepValues {
        let mut values =
            crate::model::read_scalars(&[&self.total, &self.recon, &self.kl, &self.kl_standard]);
        values.push(self.beta);
        StepValues {
            names: &ELBO_NAMES,
            values,
        }
    }
}

/// The NewtonianVAE's training objective on one batch: encode the three frames, draw
/// `x ~ q(x | i)` by reparameterisation, `v_t = (x_t - x_{t-1}) / dt`, decode every `x`, and
/// score `q(x_{t+1} | i_{t+1})` against the transition prior from `(x_t, v_t, u_t)` with the
/// learned `sigma_p`; `beta` weights that KL (annealing).
pub fn elbo_loss(
    model: &NvaeModel,
    config: &NvaeConfig,
    inputs: ElboInputs,
    beta: f64,
    dt: f64,
) -> ElboTerms {
    let ElboInputs { frames, u, noise } = inputs;
    let n = u.dims()[0];
    let (mean, log_std) = model.encoder.posterior(frames.clone()); // [3n, du] each
    let x = mean.clone() + log_std.clone().exp() * noise; // [3n, du]
    // Sum over the three frames of each sample = 3 x the mean over all 3n frames.
    let recon =
        reconstruction_nll(model.decoder.forward(x.clone()), frames, config.recon_std) * 3.0;

    let part = |t: Tensor<2>, k: usize| t.narrow(0, k * n, n);
    let (x_prev, x_now) = (part(x.clone(), 0), part(x, 1));
    let v_now = (x_now.clone() - x_prev) / dt;
    let (prior_mean, _) = model.transition.forward(x_now, v_now, u, dt);
    let du = prior_mean.dims()[1];
    let prior_log_std = model.transition.log_std.val().reshape([1, du]);
    let kl = gaussian_kl(
        part(mean.clone(), 2),
        part(log_std.clone(), 2),
        prior_mean,
        prior_log_std,
    );

    let (mean_now, log_std_now) = (part(mean, 1), part(log_std, 1));
    let kl_standard = gaussian_kl(
        mean_now.clone(),
        log_std_now.clone(),
        mean_now.zeros_like(),
        log_std_now.zeros_like(),
    );
    let total = recon.clone() + kl.clone() * beta + kl_standard.clone() * config.kl_standard_weight;
    ElboTerms {
        recon,
        kl,
        kl_standard,
        total,
        beta,
    }
}

#[cfg(test)]
mod tests {
    //! Pinned numbers are computed by hand from the closed forms quoted beside them.

    use burn::tensor::{Device, TensorData};

    use super::*;
    use crate::model::{cpu_device, to_vec};

    fn t2(values: &[f32], rows: usize, cols: usize, device: &Device) -> Tensor<2> {
        Tensor::from_data(TensorData::new(values.to_vec(), [rows, cols]), device)
    }

    fn scalar(t: Tensor<1>) -> f64 {
        let v = to_vec(t);
        assert_eq!(v.len(), 1);
        v[0] as f64
    }

    #[test]
    fn gaussian_kl_matches_the_closed_form_by_hand() {
        let device = cpu_device();
        // Row 0: q = N(1, 0.5^2) || p = N(0, 1) in dim 0, q = N(0, 1) || p = N(0, 1) in dim 1.
        //   dim 0: ln(1/0.5) + (0.25 + 1)/2 - 1/2 = 0.693147 + 0.625 - 0.5 = 0.818147.
        //   dim 1: 0.
        // Row 1: q = N(-1, 2^2) || p = N(0.5, 0.5^2) in dim 0, q = N(2, 1) || p = N(2, 0.5^2):
        //   dim 0: ln(0.5/2) + (4 + 2.25)/(2 (0.25)) - 1/2 = -1.386294 + 12.5 - 0.5 = 10.613706.
        //   dim 1: ln(0.5) + 1/(0.5) - 1/2 = -0.693147 + 2 - 0.5 = 0.806853.
        // Mean over rows of the per-row sums: (0.818147 + 11.420559) / 2 = 6.119353.
        let mean_q = t2(&[1.0, 0.0, -1.0, 2.0], 2, 2, &device);
        let log_std_q = t2(&[0.5f32.ln(), 0.0, 2.0f32.ln(), 0.0], 2, 2, &device);
        let mean_p = t2(&[0.0, 0.0, 0.5, 2.0], 2, 2, &device);
        let log_std_p = t2(&[0.0, 0.0, 0.5f32.ln(), 0.5f32.ln()], 2, 2, &device);
        let got = scalar(gaussian_kl(
            mean_q.clone(),
            log_std_q.clone(),
            mean_p,
            log_std_p,
        ));
        assert!((got - 6.119_353).abs() < 1e-4, "kl {got}");
        // KL of a distribution to itself is 0; a broadcast [1, d] prior works.
        let same = scalar(gaussian_kl(
            mean_q.clone(),
            log_std_q.clone(),
            mean_q,
            log_std_q,
        ));
        assert!(same.abs() < 1e-6, "{same}");
        let row = scalar(gaussian_kl(
            t2(&[1.0, 0.0], 1, 2, &device),
            t2(&[0.5f32.ln(), 0.0], 1, 2, &device),
            t2(&[0.0, 0.0], 1, 2, &device),
            t2(&[0.0, 0.0], 1, 2, &device),
        ));
        assert!((row - 0.818_147).abs() < 1e-5, "{row}");
    }

    #[test]
    fn reconstruction_nll_is_scaled_squared_error_per_frame() {
        let device = cpu_device();
        // Two frames; frame 0 is off by 0.1 in 10 values, frame 1 by 0.2 in 5 values.
        // sigma = 0.1: per frame SSE / (2 * 0.01) = (10 * 0.01) / 0.02 = 5 and
        // (5 * 0.04) / 0.02 = 10; mean 7.5.
        let target = Tensor::<4>::zeros([2, 3, 64, 64], &device);
        let mut values = vec![0f32; 2 * 3 * 64 * 64];
        values[..10].iter_mut().for_each(|v| *v = 0.1);
        let second = 3 * 64 * 64;
        values[second + 100..second + 105]
            .iter_mut()
            .for_each(|v| *v = -0.2);
        let mean = Tensor::<4>::from_data(TensorData::new(values, [2, 3, 64, 64]), &device);
        let got = scalar(reconstruction_nll(mean.clone(), target.clone(), 0.1));
        assert!((got - 7.5).abs() < 1e-4, "{got}");
        // sigma = 1 scales it by 0.01; a perfect reconstruction costs 0.
        let got = scalar(reconstruction_nll(mean, target.clone(), 1.0));
        assert!((got - 0.075).abs() < 1e-6, "{got}");
        assert_eq!(scalar(reconstruction_nll(target.clone(), target, 0.1)), 0.0);
    }
}
