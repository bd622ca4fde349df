//! Model-predictive control on a learned latent (the run-time reference ProCL is measured
//! against): the cross-entropy method over action sequences, rolled out through the latent
//! dynamics `g`, with the Lyapunov function's quadratic cost to the goal latent.

use burn::tensor::{Device, Tensor, TensorData};
use rand::{RngExt, SeedableRng};
use rand_chacha::ChaCha8Rng;

use crate::control::{FeedbackLaw, LatentPolicy};
use crate::model::{Dynamics, to_vec};

/// CEM-MPC settings.
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(deny_unknown_fields)]
pub struct MpcConfig {
    /// Planning horizon in control steps.
    pub horizon: usize,
    /// Action sequences sampled per CEM iteration.
    pub samples: usize,
    /// Best sequences the next sampling distribution is fitted to.
    pub elites: usize,
    /// CEM iterations per control step.
    pub iterations: usize,
    /// Std of the first iteration's sampling distribution (actions live in [-1, 1]).
    pub initial_std: f64,
    /// Cost `sum_k |h_k - h*|^2 q_h + |v_k - v*|^2 q_v + |u_k|^2 r` over the horizon.
    pub q_h: f64,
    pub q_v: f64,
    pub r: f64,
    /// Seed of the sampling noise (the controller is deterministic for a seed).
    pub seed: u64,
}

impl Default for MpcConfig {
    /// Horizon 10; the cost weights are the Lyapunov function's `Q_h = I`, `Q_v = 0.1 I`.
    fn default() -> Self {
        Self {
            horizon: 10,
            samples: 100,
            elites: 10,
            iterations: 4,
            initial_std: 0.5,
            q_h: 1.0,
            q_v: 0.1,
            r: 0.001,
            seed: 0,
        }
    }
}

impl MpcConfig {
    pub fn validate(&self) -> crate::Result<()> {
        require_positive(
            "mpc",
            &[
                ("horizon", self.horizon),
                ("samples", self.samples),
                ("elites", self.elites),
                ("iterations", self.iterations),
            ],
        )?;
        if self.elites > self.samples {
            return Err(crate::Error::config(
                "mpc.elites",
                "cannot exceed mpc.samples",
            ));
        }
        require_non_negative(
            "mpc",
            &[
                ("initial_std", self.initial_std),
                ("q_h", self.q_h),
                ("q_v", self.q_v),
                ("r", self.r),
            ],
        )
    }
}

/// Refuses, by `section.field`, a count below 1.
pub(crate) fn require_positive(section: &str, counts: &[(&str, usize)]) -> crate::Result<()> {
    match counts.iter().find(|(_, value)| *value == 0) {
        Some((field, _)) => Err(crate::Error::config(
            format!("{section}.{field}"),
            "must be at least 1",
        )),
        None => Ok(()),
    }
}

/// Refuses, by `section.field`, a weight that is negative or not finite.
pub(crate) fn require_non_negative(section: &str, weights: &[(&str, f64)]) -> crate::Result<()> {
    match weights
        .iter()
        .find(|(_, value)| !(value.is_finite() && *value >= 0.0))
    {
        Some((field, value)) => Err(crate::Error::config(
            format!("{section}.{field}"),
            format!("{value} is not a non-negative number"),
        )),
        None => Ok(()),
    }
}

/// The warm start of a receding-horizon plan: the previous plan shifted by one step with its
/// last step repeated, or doing nothing at the start of an episode (no previous plan).
pub(crate) fn shifted_plan(previous: Vec<Vec<f64>>, horizon: usize, du: usize) -> Vec<Vec<f64>> {
    let mut plan = previous;
    if plan.len() != horizon {
        return vec![vec![0.0; du]; horizon];
    }
    if horizon > 1 {
        plan.rotate_left(1);
        plan[horizon - 1] = plan[horizon - 2].clone();
    }
    plan
}

/// Writes a plan's first action into `u`, within the bounds (a non-finite component is 0).
pub(crate) fn apply_first_action(plan: &[Vec<f64>], u: &mut [f64]) {
    let first = plan.first().map(Vec::as_slice).unwrap_or(&[]);
    u.fill(0.0);
    for (ui, &pi) in u.iter_mut().zip(first) {
        if pi.is_finite() {
            *ui = pi.clamp(-1.0, 1.0);
        }
    }
}

/// One batched step of the learned dynamics `g` as a [`LatentStep`].
pub(crate) fn dynamics_step(
    dynamics: &Dynamics,
    dt: f64,
) -> impl Fn(Tensor<2>, Tensor<2>, Tensor<2>) -> (Tensor<2>, Tensor<2>) + '_ {
    move |h, v, u| {
        let next = dynamics.forward(h, v, u, dt);
        (next.h_next, next.v_next)
    }
}

/// One batched latent step `(h, v, u) -> (h', v')`, `[n, du]` each.
pub type LatentStep<'a> = dyn Fn(Tensor<2>, Tensor<2>, Tensor<2>) -> (Tensor<2>, Tensor<2>) + 'a;

/// Plans `u_0..u_{H-1}` minimising the horizon cost from `(h, v)` through `step`: CEM with a
/// diagonal Gaussian per step, warm-started from `mean` (the previous plan shifted by one).
/// Returns the final mean plan, `[H][du]`.
#[allow(clippy::too_many_arguments)]
pub fn cem_plan(
    step: &LatentStep<'_>,
    config: &MpcConfig,
    h: &[f64],
    v: &[f64],
    target: (&[f64], &[f64]),
    mut mean: Vec<Vec<f64>>,
    rng: &mut ChaCha8Rng,
    device: &Device,
) -> Vec<Vec<f64>> {
    let (n, horizon, du) = (config.samples, config.horizon, h.len());
    let mut std = vec![vec![config.initial_std; du]; horizon];
    let row = |x: &[f64]| {
        let values: Vec<f32> = (0..n).flat_map(|_| x.iter().map(|&a| a as f32)).collect();
        Tensor::<2>::from_data(TensorData::new(values, [n, du]), device)
    };
    let (h_target, v_target) = (row(target.0), row(target.1));
    for _ in 0..config.iterations {
        // plans[s][k][i]: sample s, step k, action component i (clipped to the bounds).
        let plans: Vec<Vec<Vec<f64>>> = (0..n)
            .map(|_| {
                (0..horizon)
                    .map(|k| {
                        (0..du)
                            .map(|i| {
                                (mean[k][i] + std[k][i] * standard_normal(rng)).clamp(-1.0, 1.0)
                            })
                            .collect()
                    })
                    .collect()
            })
            .collect();
        let (mut hk, mut vk) = (row(h), row(v));
        let mut cost = Tensor::<1>::zeros([n], device);
        for k in 0..horizon {
            let u: Vec<f32> = plans
                .iter()
                .flat_map(|p| p[k].iter().map(|&a| a as f32))
                .collect();
            let u = Tensor::<2>::from_data(TensorData::new(u, [n, du]), device);
            let effort = u.clone().powi_scalar(2).sum_dim(1).reshape([n]) * config.r;
            (hk, vk) = step(hk, vk, u);
            let dh = (hk.clone() - h_target.clone()).powi_scalar(2).sum_dim(1);
            let dv = (vk.clone() - v_target.clone()).powi_scalar(2).sum_dim(1);
            cost = cost + (dh * config.q_h + dv * config.q_v).reshape([n]) + effort;
        }
        let cost = to_vec(cost);
        let mut order: Vec<usize> = (0..n).collect();
        order.sort_by(|&a, &b| cost[a].total_cmp(&cost[b]));
        let elites = &order[..config.elites];
        for k in 0..horizon {
            for i in 0..du {
                let values = elites.iter().map(|&s| plans[s][k][i]);
                let m = values.clone().sum::<f64>() / elites.len() as f64;
                let var = values.map(|x| (x - m).powi(2)).sum::<f64>() / elites.len() as f64;
                mean[k][i] = m;
                std[k][i] = var.sqrt();
            }
        }
    }
    mean
}

/// One standard normal draw (Box-Muller), from the seeded stream.
fn standard_normal(rng: &mut ChaCha8Rng) -> f64 {
    let u1: f64 = rng.random_range(f64::EPSILON..1.0);
    let u2: f64 = rng.random_range(0.0..1.0);
    (-2.0 * u1.ln()).sqrt() * (std::f64::consts::TAU * u2).cos()
}

/// CEM-MPC as a feedback law on the latent: plans to the target `(h*, v*)` through the learned
/// dynamics `g` and applies the plan's first action, warm-starting each plan from the last one.
pub struct CemMpc {
    dynamics: Dynamics,
    device: Device,
    config: MpcConfig,
    dt: f64,
    /// Seeded once, so a whole evaluation is deterministic.
    rng: ChaCha8Rng,
    /// The last plan, `[H][du]` (empty at the start of an episode).
    plan: Vec<Vec<f64>>,
}

impl CemMpc {
    pub fn new(
        dynamics: Dynamics,
        device: Device,
        config: MpcConfig,
        dt: f64,
    ) -> crate::Result<Self> {
        config.validate()?;
        Ok(Self {
            rng: ChaCha8Rng::seed_from_u64(config.seed),
            dynamics,
            device,
            config,
            dt,
            plan: vec![],
        })
    }
}

impl FeedbackLaw for CemMpc {
    fn reset(&mut self) {
        self.plan.clear();
    }

    fn feedback(
        &mut self,
        h: &[f64],
        v: &[f64],
        h_target: &[f64],
        v_target: &[f64],
        u: &mut [f64],
    ) {
        let warm = shifted_plan(std::mem::take(&mut self.plan), self.config.horizon, h.len());
        let step = dynamics_step(&self.dynamics, self.dt);
        self.plan = cem_plan(
            &step,
            &self.config,
            h,
            v,
            (h_target, v_target),
            warm,
            &mut self.rng,
            &self.device,
        );
        apply_first_action(&self.plan, u);
    }
}

/// CEM-MPC on encoded frames: `h = e(frame)`, `v = (h - h_prev)/dt` and the targets exactly as
/// latent PD, then [`CemMpc`].
pub type MpcPolicy = LatentPolicy<CemMpc>;

#[cfg(test)]
mod tests {
    use super::*;
    use crate::model::cpu_device;

    /// A known linear latent model: a double integrator per dimension, `v' = v + dt u`,
    /// `h' = h + dt v'`, with dt = 0.1.
    fn double_integrator(h: Tensor<2>, v: Tensor<2>, u: Tensor<2>) -> (Tensor<2>, Tensor<2>) {
        let v_next = v + u * 0.1;
        (h + v_next.clone() * 0.1, v_next)
    }

    /// The horizon cost of `plan` from `(h, v)` to the origin, computed on the host.
    fn plan_cost(config: &MpcConfig, h: &[f64], v: &[f64], plan: &[Vec<f64>]) -> f64 {
        let (mut h, mut v) = (h.to_vec(), v.to_vec());
        let mut cost = 0.0;
        for u in plan {
            for i in 0..h.len() {
                v[i] += 0.1 * u[i];
                h[i] += 0.1 * v[i];
                cost +=
                    config.q_h * h[i] * h[i] + config.q_v * v[i] * v[i] + config.r * u[i] * u[i];
            }
        }
        cost
    }

    #[test]
    fn cem_lowers_the_cost_and_drives_a_double_integrator_to_the_goal() {
        let device = cpu_device();
        let config = MpcConfig::default();
        let mut rng = ChaCha8Rng::seed_from_u64(1);
        let (mut h, mut v) = (vec![1.0, -0.5], vec![0.0, 0.0]);
        let zeros = vec![0.0; 2];
        let idle = vec![vec![0.0; 2]; config.horizon];
        let plan = cem_plan(
            &double_integrator,
            &config,
            &h,
            &v,
            (&zeros, &zeros),
            idle.clone(),
            &mut rng,
            &device,
        );
        // Pushes toward the goal, and costs less than doing nothing.
        assert!(plan[0][0] < -0.5 && plan[0][1] > 0.25, "{plan:?}");
        assert!(plan_cost(&config, &h, &v, &plan) < 0.9 * plan_cost(&config, &h, &v, &idle));
        // Closed loop, re-planning every step: the state settles at the goal.
        let mut warm = idle;
        for _ in 0..150 {
            warm = cem_plan(
                &double_integrator,
                &config,
                &h,
                &v,
                (&zeros, &zeros),
                warm,
                &mut rng,
                &device,
            );
            for i in 0..2 {
                v[i] += 0.1 * warm[0][i];
                h[i] += 0.1 * v[i];
            }
        }
        let distance = h.iter().map(|x| x * x).sum::<f64>().sqrt();
        assert!(distance < 0.05, "h = {h:?}, v = {v:?}");
    }

    #[test]
    fn bad_settings_are_refused_by_name() {
        for (config, field) in [
            (
                MpcConfig {
                    horizon: 0,
                    ..MpcConfig::default()
                },
                "mpc.horizon",
            ),
            (
                MpcConfig {
                    elites: 500,
                    ..MpcConfig::default()
                },
                "mpc.elites",
            ),
            (
                MpcConfig {
                    r: f64::NAN,
                    ..MpcConfig::default()
                },
                "mpc.r",
            ),
        ] {
            let err = config.validate().unwrap_err().to_string();
            assert!(err.contains(field), "{err}");
        }
    }
}
