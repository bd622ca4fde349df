//! The PC3 terms (paper section II-C, eqs. 4-7): CPC, consistency and curvature of the latent
//! dynamics' Gaussian transition density.

use burn::tensor::Tensor;
use burn::tensor::activation::log_softmax;

use crate::model::Dynamics;

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
    let raw = x.reshape([n, 1, d]) - mean.reshape([1, m, d]); // [n, m, d]
    let diff = raw * inv_std;
    let quad = diff.powi_scalar(2).sum_dim(2).reshape([n, m]) * (-0.5);
    let norm = log_std.sum() + 0.5 * d as f64 * (2.0 * std::f64::consts::PI).ln();
    quad - norm.reshape([1, 1])
}

/// CPC (paper eq. 4): `-mean_i log softmax_j log F(z'_i | z_j, u_j)`, from the `[K, K]` matrix
/// of [`pairwise_gaussian_log_density`].
pub fn cpc_loss(log_density: Tensor<2>) -> Tensor<1> {
    let log_probs = log_softmax(log_density, 1);
    diagonal(log_probs).mean().neg().reshape([1])
}

/// Consistency (paper eq. 5): `-mean_i log F(z'_i | z_i, u_i)`.
pub fn consistency_loss(log_density: Tensor<2>) -> Tensor<1> {
    diagonal(log_density).mean().neg().reshape([1])
}

/// The diagonal of a square `[n, n]` matrix as `[n]`.
fn diagonal(matrix: Tensor<2>) -> Tensor<1> {
    let n = matrix.dims()[0];
    let eye = Tensor::eye(n, &matrix.device());
    (matrix * eye).sum_dim(1).reshape([n])
}

/// Curvature (paper eq. 6), with a true Jacobian-vector product rather than finite differences:
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

#[cfg(test)]
mod tests {
    //! Every pinned number below was computed independently of this crate (by hand or with the
    //! numpy one-liners quoted next to it), not by running the code under test.

    use burn::tensor::{Device, Tensor};

    use super::*;
    use crate::losses::test_support::{assert_close, scalar, t1, t2};
    use crate::model::{DynamicsConfig, cpu_device, reinit_params, to_vec};

    #[test]
    fn pairwise_gaussian_log_density_matches_full_covariance_formula() {
        let device = cpu_device();
        let x = t2(&[0.0, 0.0, 1.0, 2.0], 2, 2, &device);
        let mean = t2(&[0.0, 1.0, 1.0, -1.0, -2.0, 0.5], 3, 2, &device);
        let log_std = t1(&[0.5f32.ln(), 2.0f32.ln()], &device);
        let out = pairwise_gaussian_log_density(x, mean, log_std);
        assert_eq!(out.dims(), [2, 3]);
        // numpy, through the full covariance (not the per-dimension formula used here):
        //   cov = diag(exp(2 log_std)); out[i, j] = -0.5 d^T cov^-1 d - 0.5 log((2 pi)^2 det cov)
        //   with d = x[i] - mean[j]. Row i scores x_i under every mean j.
        let want = [
            -1.962877066,
            -3.962877066,
            -9.869127066,
            -3.962877066,
            -2.962877066,
            -20.119127066,
        ];
        assert_close(&to_vec(out), &want, 1e-5, "log density");
    }

    /// An asymmetric matrix, so row-wise and column-wise softmax give different losses.
    fn log_density_3x3(device: &Device) -> Tensor<2> {
        t2(
            &[-1.0, -2.0, -3.0, 0.5, 1.5, -0.5, 2.0, 0.0, 1.0],
            3,
            3,
            device,
        )
    }

    #[test]
    fn cpc_loss_is_row_softmax_cross_entropy_on_the_diagonal() {
        let device = cpu_device();
        // numpy: L = [[-1,-2,-3],[.5,1.5,-.5],[2,0,1]];
        //   -mean(diag(L) - log(exp(L).sum(axis=1))) = 0.7409392977777136
        //   (softmax over columns instead, axis=0, would give 1.2277966710865273).
        let got = scalar(cpc_loss(log_density_3x3(&device)));
        assert!((got - 0.740_939_297_8).abs() < 1e-5, "cpc {got}");
        // Adding a constant to every row leaves CPC unchanged (by hand).
        let shifted = scalar(cpc_loss(log_density_3x3(&device) + 7.0));
        assert!((shifted - got).abs() < 1e-5, "shifted cpc {shifted}");
        // A strongly dominant diagonal gives CPC ~ 0; a uniform matrix gives ln 3 (by hand).
        let eye = t2(
            &[50.0, 0.0, 0.0, 0.0, 50.0, 0.0, 0.0, 0.0, 50.0],
            3,
            3,
            &device,
        );
        assert!(scalar(cpc_loss(eye)).abs() < 1e-5);
        let flat = t2(&[0.3; 9], 3, 3, &device);
        assert!((scalar(cpc_loss(flat)) - 3f64.ln()).abs() < 1e-5);
    }

    #[test]
    fn consistency_loss_is_minus_mean_diagonal() {
        let device = cpu_device();
        // By hand: -(-1 + 1.5 + 1) / 3 = -0.5.
        let got = scalar(consistency_loss(log_density_3x3(&device)));
        assert!((got + 0.5).abs() < 1e-6, "cons {got}");
    }

    /// The dynamics' parameters read out to f64 by path (`fc1.weight` is `[in, out]`).
    struct Params(std::collections::BTreeMap<String, (Vec<usize>, Vec<f64>)>);

    struct CollectParams {
        path: Vec<String>,
        out: std::collections::BTreeMap<String, (Vec<usize>, Vec<f64>)>,
    }

    impl burn::module::ModuleVisitor for CollectParams {
        fn enter_module(&mut self, name: &str, _: &str) {
            self.path.push(name.to_string());
        }
        fn exit_module(&mut self, _: &str, _: &str) {
            self.path.pop();
        }
        fn visit_float<const D: usize>(&mut self, param: &burn::module::Param<Tensor<D>>) {
            let value = param.val();
            let dims = value.dims().to_vec();
            let values = to_vec(value).into_iter().map(f64::from).collect();
            self.out.insert(self.path.join("."), (dims, values));
        }
    }

    impl Params {
        fn of(dynamics: &Dynamics) -> Self {
            use burn::module::Module;
            let mut collect = CollectParams {
                path: vec![],
                out: Default::default(),
            };
            dynamics.visit(&mut collect);
            Params(collect.out)
        }

        /// `x W + b` for one row.
        fn dense(&self, layer: &str, x: &[f64]) -> Vec<f64> {
            let (dims, w) = &self.0[&format!("{layer}.weight")];
            let (_, b) = &self.0[&format!("{layer}.bias")];
            let (inputs, outputs) = (dims[0], dims[1]);
            assert_eq!(x.len(), inputs);
            (0..outputs)
                .map(|o| b[o] + (0..inputs).map(|i| x[i] * w[i * outputs + o]).sum::<f64>())
                .collect()
        }

        /// f64 re-implementation of the documented dynamics for one row:
        /// `a = MLP(h, dt v, u)`, `v' = v + dt a`, `h' = h + dt v'`; returns `(h', v')` and the
        /// pre-activations of both hidden layers.
        fn forward(&self, h: &[f64], v: &[f64], u: &[f64], dt: f64) -> (Vec<f64>, [Vec<f64>; 2]) {
            let x: Vec<f64> = h
                .iter()
                .copied()
                .chain(v.iter().map(|x| x * dt))
                .chain(u.iter().copied())
                .collect();
            let pre1 = self.dense("fc1", &x);
            let pre2 = self.dense("fc2", &pre1.iter().map(|p| p.max(0.0)).collect::<Vec<_>>());
            let a = self.dense("fc3", &pre2.iter().map(|p| p.max(0.0)).collect::<Vec<_>>());
            let v_next: Vec<f64> = v.iter().zip(&a).map(|(v, a)| v + dt * a).collect();
            let h_next = h.iter().zip(&v_next).map(|(h, v)| h + dt * v);
            (h_next.chain(v_next.iter().copied()).collect(), [pre1, pre2])
        }
    }

    fn random_dynamics(seed: u64, device: &Device) -> Dynamics {
        reinit_params(DynamicsConfig::new(2).init(device), seed)
    }

    /// `n x 2` values from a fixed LCG, uniform in [-1, 1) (test inputs, no crate RNG).
    fn lcg(state: &mut u64, n: usize) -> Vec<f32> {
        (0..2 * n)
            .map(|_| {
                *state = state
                    .wrapping_mul(6364136223846793005)
                    .wrapping_add(1442695040888963407);
                ((*state >> 40) as f32 / (1u64 << 24) as f32) * 2.0 - 1.0
            })
            .collect()
    }

    #[test]
    fn curvature_loss_vanishes_without_perturbation() {
        let device = cpu_device();
        let dynamics = random_dynamics(7, &device);
        let mut state = 1;
        let n = 5;
        let [h, v, u] = [0; 3].map(|_| t2(&lcg(&mut state, n), n, 2, &device));
        let zero = || t2(&vec![0.0; 2 * n], n, 2, &device);
        let loss = scalar(curvature_loss(
            &dynamics,
            h,
            v,
            u,
            zero(),
            zero(),
            zero(),
            0.02,
        ));
        assert!(loss.abs() < 1e-10, "curvature {loss}");
    }

    /// Checks `Dynamics::forward_jvp`'s tangent twice:
    /// 1. against the central finite difference `(f(z + s t) - f(z - s t)) / (2 s)` of the
    ///    crate's own f32 `forward`, s = 1e-3, on the whole output (relative 1e-3);
    /// 2. its network part (the tangent minus the identity part `(t_h + dt t_v, t_v)`, which
    ///    dominates for small dt and would hide an error in the MLP tangent) against an f64
    ///    finite difference, s = 1e-6, of an f64 re-implementation of the dynamics that is first
    ///    checked to match the crate's `forward` (relative 1e-4), with no ReLU kink crossed.
    fn check_jvp(dt: f64) {
        let device = cpu_device();
        let dynamics = random_dynamics(11, &device);
        let n = 6;
        let mut state = 42;
        let [h, v, u, th, tv, tu] = [0; 6].map(|_| lcg(&mut state, n));
        let t = |x: &[f32]| t2(x, n, 2, &device);
        let shifted = |x: &[f32], dx: &[f32], s: f32| {
            t2(
                &x.iter().zip(dx).map(|(a, b)| a + s * b).collect::<Vec<_>>(),
                n,
                2,
                &device,
            )
        };
        let (base, jvp) =
            dynamics.forward_jvp(t(&h), t(&v), t(&u), Some((t(&th), t(&tv), t(&tu))), dt);
        let (base, jvp) = (to_vec(base.z()), to_vec(jvp.expect("tangent given").z()));

        // 1. f32 finite difference of the crate's forward.
        let s = 1e-3f32;
        let at = |sign: f32| {
            let z = dynamics.forward(
                shifted(&h, &th, sign * s),
                shifted(&v, &tv, sign * s),
                shifted(&u, &tu, sign * s),
                dt,
            );
            to_vec(z.z())
        };
        let (plus, minus) = (at(1.0), at(-1.0));
        let (mut err2, mut norm2) = (0.0, 0.0);
        for i in 0..4 * n {
            let fd = (plus[i] as f64 - minus[i] as f64) / (2.0 * s as f64);
            err2 += (fd - jvp[i] as f64).powi(2);
            norm2 += (jvp[i] as f64).powi(2);
        }
        let rel = (err2 / norm2).sqrt();
        assert!(rel < 1e-3, "dt {dt}: JVP vs f32 finite difference: {rel}");

        // 2. The network part against the f64 reference.
        let params = Params::of(&dynamics);
        let row = |x: &[f32], r: usize| [x[2 * r] as f64, x[2 * r + 1] as f64];
        let (mut err2, mut norm2) = (0.0, 0.0);
        let s = 1e-6;
        for r in 0..n {
            let (hr, vr, ur) = (row(&h, r), row(&v, r), row(&u, r));
            let (thr, tvr, tur) = (row(&th, r), row(&tv, r), row(&tu, r));
            let (reference, pre) = params.forward(&hr, &vr, &ur, dt);
            for k in 0..4 {
                let got = base[4 * r + k] as f64;
                let want = reference[k];
                assert!(
                    (got - want).abs() <= 1e-4 * (1.0 + want.abs()),
                    "dt {dt}: forward row {r}[{k}]: crate {got}, reference {want}"
                );
            }
            let step = |sign: f64| {
                let add =
                    |x: &[f64; 2], d: &[f64; 2]| [x[0] + sign * s * d[0], x[1] + sign * s * d[1]];
                params.forward(&add(&hr, &thr), &add(&vr, &tvr), &add(&ur, &tur), dt)
            };
            let ((plus, pre_plus), (minus, pre_minus)) = (step(1.0), step(-1.0));
            // Piecewise-linear network: no pre-activation changes sign along the segment, so the
            // finite difference is exact up to rounding (layer 2 is linear once layer 1 is).
            for layer in 0..2 {
                for (j, p) in pre[layer].iter().enumerate() {
                    assert!(
                        p.signum() == pre_plus[layer][j].signum()
                            && p.signum() == pre_minus[layer][j].signum(),
                        "dt {dt}: row {r} crosses a ReLU kink (layer {layer} unit {j}); move the inputs"
                    );
                }
            }
            for k in 0..4 {
                let c = k % 2;
                let identity = if k < 2 { thr[c] + dt * tvr[c] } else { tvr[c] };
                let fd_net = (plus[k] - minus[k]) / (2.0 * s) - identity;
                let jvp_net = jvp[4 * r + k] as f64 - identity;
                err2 += (fd_net - jvp_net).powi(2);
                norm2 += fd_net.powi(2);
            }
        }
        let rel = (err2 / norm2).sqrt();
        assert!(norm2 > 0.0);
        assert!(
            rel < 1e-4,
            "dt {dt}: network part of the JVP vs f64 finite difference: {rel}"
        );
    }

    #[test]
    fn dynamics_jvp_matches_finite_difference() {
        for dt in [1.0, 0.5, 0.1, 0.02] {
            check_jvp(dt);
        }
    }
}
