//! The NewtonianVAE objective, one function per term, and the ELBO on a batch of windows of
//! consecutive frames with its per-term breakdown for logging.

use burn::tensor::Tensor;

use super::{NvaeConfig, NvaeModel, TransitionMatrices};
use crate::losses::StepValues;
use crate::model::{ConvGradient, HostBackward, TrunkTape};

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

/// The frames the prior's predictions are scored on.
// One is built a step and moved once: boxing the tensor would only add an allocation.
#[allow(clippy::large_enum_variant)]
#[derive(Debug, Clone)]
pub enum Targets<'a> {
    /// As the network sees them, `[m, 3, 64, 64]` ([`crate::model::frames_to_tensor`]): the
    /// decoder runs in burn's graph.
    Pixels(Tensor<4>),
    /// RGB u8 frames: the decoder's convolutions and their score run on the host (training on
    /// the CPU), their parameter gradients returned in [`ElboTerms::decoder_gradients`].
    Frames(&'a [&'a [u8]]),
}

/// One batch of training windows as the ELBO sees them: `w` windows of `len` consecutive
/// frames of one episode each, window-major.
#[derive(Debug, Clone)]
pub struct ElboInputs<'a> {
    /// The posterior `q(x | i)` of every frame: mean and log std, `[w len, du]` each.
    pub mean: Tensor<2>,
    pub log_std: Tensor<2>,
    /// The frames the prior's predictions are scored on, frames `2..len` of every window:
    /// `w (len - 2)` of them.
    pub targets: Targets<'a>,
    /// `u_t` for `t = 1..len - 1` of every window (`u_t` moves frame `t` to `t + 1`):
    /// `[w (len - 2), du]`.
    pub u: Tensor<2>,
    /// Standard normal draws for the posterior samples of `x`, `[w len, du]`, and for the
    /// prior's samples of `x_{t+1}`, `[w (len - 2), du]`.
    pub posterior_noise: Tensor<2>,
    pub prior_noise: Tensor<2>,
    /// Number of windows `w`.
    pub windows: usize,
}

/// The ELBO's terms on one batch (each a mean per ELBO term, i.e. per predicted frame) and
/// the weighted total to minimise.
#[derive(Debug, Clone)]
pub struct ElboTerms {
    /// Reconstruction NLL of frame `t + 1` decoded from the prior's sample of `x_{t+1}`.
    pub recon: Tensor<1>,
    /// `KL(q(x_{t+1} | i_{t+1}) || p(x_{t+1} | x_t, v_t, u_t))`, unweighted.
    pub kl: Tensor<1>,
    /// `KL(q(x | i) || N(0, I))` over every frame, unweighted.
    pub kl_standard: Tensor<1>,
    /// `recon + beta kl + kl_standard_weight kl_standard` (the negative ELBO per term, up to
    /// the decoder's constant, when both weights are 1).
    pub total: Tensor<1>,
    /// The transition KL's weight this step.
    pub beta: f64,
    /// The decoder's convolution gradients when it ran on the host ([`Targets::Frames`]):
    /// burn's `backward` of `total` leaves them out.
    pub(crate) decoder_gradients: Vec<ConvGradient>,
}

/// Names of the logged NVAE terms (metrics.csv columns), in [`ElboTerms::values`] order.
pub const ELBO_NAMES: [&str; 5] = ["total", "recon", "kl", "kl_std", "beta"];

/// Names of validation.csv's terms: the ELBO's at `beta = 1`.
pub const VALIDATION_NAMES: [&str; 4] = ["total", "recon", "kl", "kl_std"];

impl ElboTerms {
    /// What the host owes burn's gradients after `total.backward()`: the decoder's
    /// convolution gradients, and the encoder trunk's tape `trunk` if it ran on the host.
    pub fn host_backward(self, trunk: Option<TrunkTape>) -> HostBackward {
        HostBackward {
            trunk,
            convs: self.decoder_gradients,
        }
    }

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

/// The NewtonianVAE's ELBO (its paper's Eq. 11) on a batch of windows: draw every
/// `x ~ q(x | i)` by reparameterisation, take `v_t = (x_t - x_{t-1}) / dt`, predict
/// `p(x_{t+1} | x_t, v_t, u_t)` with the learned `sigma_p`, and score frame `t + 1` decoded
/// from a sample of that prediction, plus `q(x_{t+1} | i_{t+1})` against it (`beta` weights
/// that KL). Decoding the prediction, not the posterior, is what ties the latent to the
/// action through `C`.
pub fn elbo_loss(
    model: &NvaeModel,
    config: &NvaeConfig,
    inputs: ElboInputs,
    beta: f64,
    dt: f64,
) -> ElboTerms {
    let ElboInputs {
        mean,
        log_std,
        targets,
        u,
        posterior_noise,
        prior_noise,
        windows,
    } = inputs;
    let [rows, du] = mean.dims();
    let len = rows / windows;
    let terms = len - 2;
    let x = (mean.clone() + log_std.clone().exp() * posterior_noise).reshape([windows, len, du]);
    // Frames `start..start + terms` of every window, flattened to `[w terms, du]`.
    let frames_from =
        |t: Tensor<3>, start: usize| t.narrow(1, start, terms).reshape([windows * terms, du]);
    let x_prev = frames_from(x.clone(), 0);
    let x_now = frames_from(x, 1);
    let v_now = (x_now.clone() - x_prev) / dt;
    let matrices = match config.fixed_transition {
        Some(abc) => TransitionMatrices::constant(abc, windows * terms, du, &x_now.device()),
        None => model.transition.matrices(x_now.clone()),
    };
    let (prior_mean, _) = matrices.step(x_now, v_now, u, dt);
    let prior_log_std = model.transition.log_std.val().reshape([1, du]);
    let x_next = prior_mean.clone() + prior_log_std.clone().exp() * prior_noise;
    let (recon, decoder_gradients) = match targets {
        Targets::Pixels(targets) => {
            let decoded = model.decoder.forward(x_next);
            (
                reconstruction_nll(decoded, targets, config.recon_std),
                Vec::new(),
            )
        }
        Targets::Frames(frames) => {
            model
                .decoder
                .reconstruction_on_host(x_next, frames, config.recon_std)
        }
    };
    let kl = gaussian_kl(
        frames_from(mean.clone().reshape([windows, len, du]), 2),
        frames_from(log_std.clone().reshape([windows, len, du]), 2),
        prior_mean,
        prior_log_std,
    );
    let kl_standard = gaussian_kl(
        mean.clone(),
        log_std.clone(),
        mean.zeros_like(),
        log_std.zeros_like(),
    );
    let total = recon.clone() + kl.clone() * beta + kl_standard.clone() * config.kl_standard_weight;
    ElboTerms {
        recon,
        kl,
        kl_standard,
        total,
        beta,
        decoder_gradients,
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

    #[test]
    fn sequence_elbo_predicts_each_frame_from_the_two_before_it_and_the_action() {
        let device = cpu_device();
        let config = super::super::model::tests::tiny();
        let model = config.init(1, &device).unwrap();
        let dt = 0.1;
        // One window of 4 frames with distinct posterior means; zero noise makes every sample
        // its mean, so the terms can be rebuilt from the transition by hand.
        let mean = t2(&[0.0, 0.1, 0.2, 0.4, 0.5, 0.3, 0.9, -0.2], 4, 2, &device);
        let log_std = t2(&[0.5f32.ln(); 8], 4, 2, &device);
        let targets = Tensor::<4>::ones([2, 3, 64, 64], &device) * 0.25;
        let u = t2(&[1.0, -1.0, 0.5, 0.0], 2, 2, &device);
        let inputs = ElboInputs {
            mean: mean.clone(),
            log_std: log_std.clone(),
            targets: Targets::Pixels(targets.clone()),
            u: u.clone(),
            posterior_noise: mean.zeros_like(),
            prior_noise: u.zeros_like(),
            windows: 1,
        };
        let terms = elbo_loss(&model, &config, inputs.clone(), 0.3, dt);
        // Term t = 1 predicts frame 2 from frames 0, 1 and u_1; t = 2 frame 3 from 1, 2, u_2.
        let rows = |k: usize| mean.clone().narrow(0, k, 2);
        let v = (rows(1) - rows(0)) / dt;
        let (prior_mean, _) = model
            .transition
            .matrices(rows(1))
            .step(rows(1), v, u.clone(), dt);
        let prior_log_std = model.transition.log_std.val().reshape([1, 2]);
        let kl = scalar(gaussian_kl(
            rows(2),
            log_std.clone().narrow(0, 2, 2),
            prior_mean.clone(),
            prior_log_std,
        ));
        let recon = scalar(reconstruction_nll(
            model.decoder.forward(prior_mean),
            targets,
            config.recon_std,
        ));
        let kl_std = scalar(gaussian_kl(
            mean.clone(),
            log_std.clone(),
            mean.zeros_like(),
            log_std.zeros_like(),
        ));
        // Each of 4 posteriors N(m, 0.5^2) against N(0, 1): ln 2 + (0.25 + |m|^2) / 2 - 1/2 per
        // dimension; the means' squares sum to 1.4, so the mean over frames is
        // 2 (ln 2 - 0.375) + 1.4 / 8 = 0.811294.
        assert!((kl_std - 0.811_294).abs() < 1e-5, "{kl_std}");
        for (got, want) in [
            (scalar(terms.kl.clone()), kl),
            (scalar(terms.recon.clone()), recon),
            (scalar(terms.kl_standard.clone()), kl_std),
            (scalar(terms.total.clone()), recon + 0.3 * kl + kl_std),
        ] {
            assert!(
                (got - want).abs() < 1e-4 * want.abs().max(1.0),
                "{got} vs {want}"
            );
        }
        // The prediction, and with it the reconstruction, depends on the action.
        let pushed = ElboInputs {
            u: u * -1.0,
            ..inputs
        };
        let other = scalar(elbo_loss(&model, &config, pushed, 0.3, dt).kl);
        assert!((other - kl).abs() > 1e-6, "{other} vs {kl}");
    }

    #[test]
    fn a_fixed_transition_predicts_x_plus_dt_v_plus_dt_squared_u() {
        let device = cpu_device();
        let mut config = super::super::model::tests::tiny();
        config.fixed_transition = Some([0.0, 0.0, 1.0]);
        let dt = 0.1;
        let mean = t2(&[0.0, 0.1, 0.2, 0.4, 0.5, 0.3], 3, 2, &device);
        let log_std = t2(&[0.5f32.ln(); 6], 3, 2, &device);
        let u = t2(&[1.0, -2.0], 1, 2, &device);
        let model = config.init(1, &device).unwrap();
        let batch = ElboInputs {
            mean: mean.clone(),
            log_std: log_std.clone(),
            targets: Targets::Pixels(Tensor::<4>::zeros([1, 3, 64, 64], &device)),
            u: u.clone(),
            posterior_noise: mean.zeros_like(),
            prior_noise: u.zeros_like(),
            windows: 1,
        };
        let terms = elbo_loss(&model, &config, batch, 1.0, dt);
        // x_1 = (0.2, 0.4), v_1 = (0.2, 0.3) / 0.1 = (2, 3): the prediction is
        // x_1 + dt v_1 + dt^2 u = (0.2 + 0.2 + 0.01, 0.4 + 0.3 - 0.02) = (0.41, 0.68).
        let prior_log_std = model.transition.log_std.val().reshape([1, 2]);
        let want = scalar(gaussian_kl(
            mean.clone().narrow(0, 2, 1),
            log_std.clone().narrow(0, 2, 1),
            t2(&[0.41, 0.68], 1, 2, &device),
            prior_log_std,
        ));
        let got = scalar(terms.kl.clone());
        assert!(
            (got - want).abs() < 1e-4 * want.abs().max(1.0),
            "{got} vs {want}"
        );
    }
}
