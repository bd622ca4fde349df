//! Controllers as small `Copy` values with pure control laws, and the latent policy that runs
//! one on camera frames.

mod demonstrations;
mod latent;
mod pid;

pub use demonstrations::{PathShape, ReferenceConfig, generate_reference};
pub use latent::{LatentPdPolicy, LatentPolicy, OraclePdPolicy, Policy, Target};
pub use pid::{FeedbackLaw, Pid, PidController};

/// PD control `u = Kp (h* - h) + Kd (v* - v)` with diagonal gains, clipped to [-1, 1].
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(deny_unknown_fields)]
pub struct PdController {
    pub kp: f64,
    pub kd: f64,
}

impl PdController {
    /// The control for configuration `h`, velocity `v` and targets `h_target`, `v_target`
    /// (equal lengths), written into `u` and clipped to the action bounds.
    pub fn control(&self, h: &[f64], v: &[f64], h_target: &[f64], v_target: &[f64], u: &mut [f64]) {
        for i in 0..u.len() {
            let raw = self.kp * (h_target[i] - h[i]) + self.kd * (v_target[i] - v[i]);
            u[i] = if raw.is_finite() {
                raw.clamp(-1.0, 1.0)
            } else {
                0.0
            };
        }
    }
}

/// Oracle PD gains on the true state per environment, chosen so the closed loop is close to
/// critically damped (point mass: w^2 = Kp gear/m = 16.7, zeta = 0.8; reacher: w^2 about 33 on
/// the shoulder, overdamped on the light wrist; Fetch, a pure double integrator
/// `v' = v + dt a_max u` with a_max = 0.5 m/s^2: w^2 = Kp a_max = 12.5, zeta = Kd a_max / 2w =
/// 0.99, within 5 mm of any goal in the workspace after 2.2 s, and fast enough to follow a
/// 4.8 s figure-eight; Kp = Kd = 8 reached goals too but lagged that path by a third of its size).
pub fn oracle_gains(env: crate::envs::EnvKind) -> PdController {
    match env {
        crate::envs::EnvKind::PointMass => PdController { kp: 50.0, kd: 10.0 },
        crate::envs::EnvKind::Reacher => PdController { kp: 2.0, kd: 0.2 },
        crate::envs::EnvKind::Fetch => PdController { kp: 25.0, kd: 14.0 },
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn pd_law_and_clipping() {
        let pd = PdController { kp: 10.0, kd: 2.0 };
        let mut u = [0.0; 2];
        // 10 (0.05 - 0) + 2 (0 - 0.1) = 0.3 ; 10 (-0.3) + 2 (0.5) = -2 -> clipped to -1.
        pd.control(&[0.0, 0.3], &[0.1, -0.5], &[0.05, 0.0], &[0.0, 0.0], &mut u);
        assert!((u[0] - 0.3).abs() < 1e-12);
        assert_eq!(u[1], -1.0);
        pd.control(
            &[f64::NAN, 0.0],
            &[0.0, 0.0],
            &[0.0, 0.0],
            &[0.0, 0.0],
            &mut u,
        );
        assert_eq!(u, [0.0, 0.0]);
    }
}
