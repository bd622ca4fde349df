//! The latent PD-control Lyapunov risk with hindsight targets (paper section III-B): PD toward a
//! target that reproduces the recorded action must not raise the Lyapunov function `V`.

use burn::tensor::activation::relu;
use burn::tensor::{Tensor, TensorData};

use super::LossConfig;
use super::regularisers::batch_std;

/// The hindsight pseudo-target (paper eq. 11): `v*` is `v` permuted across the batch, and
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

/// `V(z) = h^T Q_h h + v^T Q_v v` per row (paper eq. 2): `[n, du]` twice -> `[n]`.
fn lyapunov_value(h: Tensor<2>, v: Tensor<2>, q_h: f64, q_v: f64) -> Tensor<1> {
    let n = h.dims()[0];
    (h.powi_scalar(2).sum_dim(1) * q_h + v.powi_scalar(2).sum_dim(1) * q_v).reshape([n])
}

/// Latent PD-control Lyapunov risk (paper eqs. 9, 10, 12):
/// `mean max(0, (V(z_{t+1} - z*) - V(z_t - z*)) / dt_R)`.
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

/// The factor `c / std(h_t)` (`[1, du]`, gradient through the std) that the Lyapunov risk
/// multiplies every latent of a sample by under `loss.risk_latent_std = c`; `None` when off.
pub(crate) fn risk_scale(config: &LossConfig, h_now: Tensor<2>) -> Option<Tensor<2>> {
    config.risk_latent_std.map(|c| batch_std(h_now).recip() * c)
}

#[cfg(test)]
mod tests {
    //! Every pinned number below was computed by hand, not by running the code under test.

    use super::*;
    use crate::losses::test_support::{scalar, t2};
    use crate::model::{cpu_device, to_vec};

    #[test]
    fn hindsight_targets_reproduce_the_recorded_action_under_pd() {
        let device = cpu_device();
        let h: [f32; 6] = [0.3, -1.2, 0.0, 0.7, 2.5, -0.4];
        let v: [f32; 6] = [1.0, 2.0, -3.0, 0.5, 0.25, -1.5];
        let u: [f32; 6] = [0.9, -0.3, -1.0, 1.0, 0.1, 0.0];
        let permutation = [2usize, 0, 1];
        let (kp, kd) = (10.0, 2.0);
        let (h_star, v_star) = hindsight_targets(
            t2(&h, 3, 2, &device),
            t2(&v, 3, 2, &device),
            t2(&u, 3, 2, &device),
            &permutation,
            kp,
            kd,
        );
        let (h_star, v_star) = (to_vec(h_star), to_vec(v_star));
        // v*_i = v_{permutation[i]}: rows (0.25, -1.5), (1, 2), (-3, 0.5), exactly.
        assert_eq!(v_star, vec![0.25, -1.5, 1.0, 2.0, -3.0, 0.5]);
        // PD toward (h*, v*) gives back u: kp (h* - h) + kd (v* - v) = u.
        for k in 0..6 {
            let pd = kp * (h_star[k] as f64 - h[k] as f64) + kd * (v_star[k] as f64 - v[k] as f64);
            assert!(
                (pd - u[k] as f64).abs() < 1e-5,
                "entry {k}: PD gives {pd}, u = {}",
                u[k]
            );
        }
        // One entry by hand: h*_00 = 0.3 + (0.9 - 2 (0.25 - 1)) / 10 = 0.54.
        assert!((h_star[0] - 0.54).abs() < 1e-6);
    }

    #[test]
    fn lyapunov_risk_is_zero_when_contracting_and_pinned_when_expanding() {
        let device = cpu_device();
        let (q_h, q_v, dt_r) = (1.0, 0.1, 0.02);
        let pair = |h: &[f32], v: &[f32]| (t2(h, 2, 2, &device), t2(v, 2, 2, &device));
        // Both rows move toward the target in the V metric.
        let contracting = lyapunov_risk(
            pair(&[1.0, 0.0, 1.0, 1.0], &[0.0, 1.0, 0.0, 0.0]),
            pair(&[0.5, 0.0, 0.5, 0.5], &[0.0, 0.5, 0.0, 0.0]),
            pair(&[0.0; 4], &[0.0; 4]),
            q_h,
            q_v,
            dt_r,
        );
        assert_eq!(scalar(contracting), 0.0);
        // Row 0 expands, row 1 contracts. By hand, target h* = (0.5, 0.5), v* = 0 for row 0:
        //   V(z_now - z*) = 0.25 + 0.25 + 0.1 * 1 = 0.6
        //   V(z_next - z*) = 1.5^2 + 0.5^2 + 0.1 (1 + 1) = 2.7
        //   (2.7 - 0.6) / 0.02 = 105. Row 1 (target 0): V 2 -> 0.5, clipped to 0.
        //   Mean over the 2 rows: 52.5.
        // The expanding batch, its latent scaled by `scale`.
        let expanding = |scale: f32| {
            let s = |v: &[f32]| v.iter().map(|x| scale * x).collect::<Vec<f32>>();
            scalar(lyapunov_risk(
                pair(&s(&[1.0, 0.0, 1.0, 1.0]), &s(&[0.0, 1.0, 0.0, 0.0])),
                pair(&s(&[2.0, 0.0, 0.5, 0.5]), &s(&[1.0, 1.0, 0.0, 0.0])),
                pair(&s(&[0.5, 0.5, 0.0, 0.0]), &[0.0; 4]),
                q_h,
                q_v,
                dt_r,
            ))
        };
        let got = expanding(1.0);
        assert!((got - 52.5).abs() < 1e-3, "risk {got}");
        // V is quadratic: a latent 3 times as large raises the risk 9 times.
        let scaled = expanding(3.0);
        assert!((scaled - 9.0 * got).abs() < 1e-2, "scaled risk {scaled}");
    }

    /// The velocity term of `V` charges a joint for how far one step moves its velocity, so a
    /// joint whose velocity follows the torque within a step (the reacher's overdamped wrist)
    /// is charged ten times a double integrator's for the same step: the risk is lowered by
    /// making that joint faint in `h` (docs/design.md, reacher). Without the term
    /// (`q_v = 0`) neither is charged.
    #[test]
    fn the_velocity_term_charges_an_overdamped_joint_and_q_v_0_charges_neither() {
        let device = cpu_device();
        let (kp, kd, dt) = (1.0, 0.2, 0.02);
        let one = |x: f32| t2(&[x], 1, 1, &device);
        // Row 0 of a batch: at rest at h = 0 under u = 1; v* is row 1's velocity, -2. By hand,
        // h* = 0 + (1 - 0.2 (-2 - 0)) / 1 = 1.4.
        let (h_star, v_star) = hindsight_targets(
            t2(&[0.0, 0.0], 2, 1, &device),
            t2(&[0.0, -2.0], 2, 1, &device),
            t2(&[1.0, 0.0], 2, 1, &device),
            &[1, 0],
            kp,
            kd,
        );
        let (h_star, v_star) = (to_vec(h_star)[0], to_vec(v_star)[0]);
        assert!(
            (h_star - 1.4).abs() < 1e-6 && v_star == -2.0,
            "{h_star} {v_star}"
        );
        // V(z_now - z*) = 1.4^2 + q_v 2^2 = 1.96 + 4 q_v.
        // Overdamped: the velocity jumps to 1.5 in the step, h_next = 0.02 * 1.5 = 0.03:
        //   V(z_next - z*) = 1.37^2 + q_v 3.5^2 = 1.8769 + 12.25 q_v;
        //   at q_v = 0.1 the rise is 0.7419, over dt: 37.095.
        // Double integrator: v_next = dt a = 0.2, h_next = 0.004:
        //   V(z_next - z*) = 1.396^2 + q_v 2.2^2 = 1.948816 + 4.84 q_v;
        //   at q_v = 0.1 the rise is 0.072816, over dt: 3.6408.
        let risk = |h_next: f32, v_next: f32, q_v: f64| {
            scalar(lyapunov_risk(
                (one(0.0), one(0.0)),
                (one(h_next), one(v_next)),
                (one(h_star), one(v_star)),
                1.0,
                q_v,
                dt,
            ))
        };
        let overdamped = risk(0.03, 1.5, 0.1);
        let double_integrator = risk(0.004, 0.2, 0.1);
        assert!((overdamped - 37.095).abs() < 1e-3, "{overdamped}");
        assert!(
            (double_integrator - 3.6408).abs() < 1e-3,
            "{double_integrator}"
        );
        // Both steps move h toward h*, so without the velocity term neither is charged.
        assert_eq!(risk(0.03, 1.5, 0.0), 0.0);
        assert_eq!(risk(0.004, 0.2, 0.0), 0.0);
    }
}
