//! PID control on a latent configuration (the NewtonianVAE baseline's controller): the PD law
//! plus an integral of the configuration error, with conditional-integration anti-windup.

use super::PdController;

/// PID gains, diagonal: `u = Kp e + Ki I + Kd (v* - v)` with `e = h* - h` and `I` the time
/// integral of `e`, clipped to [-1, 1]. Defaults are NewtonianVAE's (Jaques et al. 2021):
/// Kp = 8, Ki = 2, Kd = 0.5.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(deny_unknown_fields)]
pub struct PidController {
    pub kp: f64,
    pub ki: f64,
    pub kd: f64,
}

impl Default for PidController {
    fn default() -> Self {
        Self {
            kp: 8.0,
            ki: 2.0,
            kd: 0.5,
        }
    }
}

impl PidController {
    /// The control for configuration `h`, velocity `v` and targets `h_target`, `v_target`
    /// (equal lengths), written into `u` and clipped to the action bounds; `integral` (one
    /// entry per dimension, seconds x latent units) is advanced by `e dt`.
    ///
    /// Anti-windup by conditional integration: the error is integrated only when that leaves
    /// the output unsaturated or moves it back toward [-1, 1]. While the actuator is pinned at
    /// a bound the integral is frozen, so a long approach from far away does not wind it up
    /// into an overshoot once the target is near.
    #[allow(clippy::too_many_arguments)]
    pub fn control(
        &self,
        integral: &mut [f64],
        h: &[f64],
        v: &[f64],
        h_target: &[f64],
        v_target: &[f64],
        dt: f64,
        u: &mut [f64],
    ) {
        for i in 0..u.len() {
            let error = h_target[i] - h[i];
            let pd = self.kp * error + self.kd * (v_target[i] - v[i]);
            let candidate = integral[i] + error * dt;
            let raw = pd + self.ki * candidate;
            // Saturated and the integration pushes further out: keep the integral as it is.
            let winds_up = raw.abs() > 1.0 && raw.signum() == (self.ki * error).signum();
            if candidate.is_finite() && !winds_up {
                integral[i] = candidate;
            }
            let raw = pd + self.ki * integral[i];
            u[i] = if raw.is_finite() {
                raw.clamp(-1.0, 1.0)
            } else {
                0.0
            };
        }
    }
}

/// A feedback law on the latent, `(h, v)` and the target `(h*, v*)` -> `u`, with whatever it
/// remembers within an episode (PID's integral).
pub trait FeedbackLaw {
    /// Starts an episode: forgets the memory of the last one.
    fn reset(&mut self) {}
    /// The action, written into `u` (clipped to [-1, 1]).
    fn feedback(&mut self, h: &[f64], v: &[f64], h_target: &[f64], v_target: &[f64], u: &mut [f64]);
}

impl FeedbackLaw for PdController {
    fn feedback(
        &mut self,
        h: &[f64],
        v: &[f64],
        h_target: &[f64],
        v_target: &[f64],
        u: &mut [f64],
    ) {
        self.control(h, v, h_target, v_target, u);
    }
}

/// A [`PidController`] running in closed loop: its control period and integral.
#[derive(Debug, Clone, PartialEq)]
pub struct Pid {
    pub gains: PidController,
    /// Control period, seconds.
    pub dt: f64,
    /// The integral of the error per dimension (empty until the first step).
    pub integral: Vec<f64>,
}

impl Pid {
    pub fn new(gains: PidController, dt: f64) -> Self {
        Self {
            gains,
            dt,
            integral: vec![],
        }
    }
}

impl FeedbackLaw for Pid {
    fn reset(&mut self) {
        self.integral.clear();
    }

    fn feedback(
        &mut self,
        h: &[f64],
        v: &[f64],
        h_target: &[f64],
        v_target: &[f64],
        u: &mut [f64],
    ) {
        self.integral.resize(u.len(), 0.0);
        self.gains
            .control(&mut self.integral, h, v, h_target, v_target, self.dt, u);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn pid_law_integrates_the_error() {
        let pid = PidController {
            kp: 8.0,
            ki: 2.0,
            kd: 0.5,
        };
        let mut integral = [0.0, 0.3];
        let mut u = [0.0; 2];
        // Dim 0: e = 0.05, I = 0 + 0.05 * 0.1 = 0.005, u = 8 (0.05) + 2 (0.005) + 0.5 (0 - 0.2)
        //   = 0.4 + 0.01 - 0.1 = 0.31.
        // Dim 1: e = -0.02, I = 0.3 - 0.002 = 0.298, u = -0.16 + 0.596 + 0.5 (0.1) = 0.486.
        pid.control(
            &mut integral,
            &[0.0, 0.02],
            &[0.2, 0.0],
            &[0.05, 0.0],
            &[0.0, 0.1],
            0.1,
            &mut u,
        );
        assert!((integral[0] - 0.005).abs() < 1e-12, "{integral:?}");
        assert!((integral[1] - 0.298).abs() < 1e-12, "{integral:?}");
        assert!((u[0] - 0.31).abs() < 1e-12, "{u:?}");
        assert!((u[1] - 0.486).abs() < 1e-12, "{u:?}");
        // A constant error keeps adding e dt: after 10 more steps, I_0 = 0.005 + 10 (0.005).
        for _ in 0..10 {
            pid.control(
                &mut integral,
                &[0.0, 0.02],
                &[0.0, 0.0],
                &[0.05, 0.0],
                &[0.0, 0.0],
                0.1,
                &mut u,
            );
        }
        assert!((integral[0] - 0.055).abs() < 1e-12, "{integral:?}");
        // Ki = 0 is PD: the same output as the PD law.
        let pd_only = PidController { ki: 0.0, ..pid };
        let (mut u_pid, mut u_pd) = ([0.0; 2], [0.0; 2]);
        pd_only.control(
            &mut [5.0, -5.0],
            &[0.0, 0.3],
            &[0.1, -0.5],
            &[0.05, 0.0],
            &[0.0, 0.0],
            0.02,
            &mut u_pid,
        );
        PdController { kp: 8.0, kd: 0.5 }.control(
            &[0.0, 0.3],
            &[0.1, -0.5],
            &[0.05, 0.0],
            &[0.0, 0.0],
            &mut u_pd,
        );
        assert_eq!(u_pid, u_pd);
    }

    #[test]
    fn integral_is_frozen_while_the_output_saturates() {
        let pid = PidController::default();
        let dt = 0.02;
        // Far from the target (e = 1): Kp e = 8 saturates, so the integral must not grow.
        let mut integral = [0.0];
        let mut u = [0.0];
        for _ in 0..500 {
            pid.control(&mut integral, &[0.0], &[0.0], &[1.0], &[0.0], dt, &mut u);
        }
        assert_eq!(u, [1.0]);
        assert_eq!(integral, [0.0], "wound up while saturated");
        // Without anti-windup it would be 500 * 0.02 = 10, and at the target (e = 0) the
        // output would stay pinned at Ki I = 20 -> 1 instead of 0.
        pid.control(&mut integral, &[1.0], &[0.0], &[1.0], &[0.0], dt, &mut u);
        assert_eq!(u, [0.0]);

        // Saturated with a wound-up integral, an error of the other sign is integrated: it
        // moves the output back toward the bounds. I = 1, e = -0.05: raw = -0.4 + 2 (0.999)
        // = 1.598 > 1 but the integration lowers it, so I becomes 0.999.
        let mut integral = [1.0];
        pid.control(&mut integral, &[0.05], &[0.0], &[0.0], &[0.0], dt, &mut u);
        assert!((integral[0] - 0.999).abs() < 1e-12, "{integral:?}");
        assert_eq!(u, [1.0]);

        // Non-finite input: no action and the integral is left alone.
        let mut integral = [0.25];
        pid.control(
            &mut integral,
            &[f64::NAN],
            &[0.0],
            &[0.0],
            &[0.0],
            dt,
            &mut u,
        );
        assert_eq!((integral, u), ([0.25], [0.0]));
    }

    #[test]
    fn pid_in_closed_loop_resets_its_integral() {
        let mut pid = Pid::new(PidController::default(), 0.1);
        let mut u = [0.0; 2];
        pid.feedback(&[0.0, 0.0], &[0.0, 0.0], &[0.1, -0.1], &[0.0, 0.0], &mut u);
        // I = e dt = +-0.01; u = 8 (0.1) + 2 (0.01) = 0.82.
        assert_eq!(pid.integral.len(), 2);
        assert!((pid.integral[0] - 0.01).abs() < 1e-12);
        assert!(
            (u[0] - 0.82).abs() < 1e-12 && (u[1] + 0.82).abs() < 1e-12,
            "{u:?}"
        );
        pid.reset();
        assert!(pid.integral.is_empty());
    }
}
