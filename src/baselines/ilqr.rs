//! Receding-horizon iLQR in the learned latent, as PC3's own controller runs it: several
//! candidate action sequences (the previous plan shifted by one, and random ones), each
//! improved by a few iLQR iterations with a backtracking line search through the latent
//! dynamics `g`; the cheapest plan's first action is applied. The cost is CEM's (the Lyapunov
//! function's quadratic form to the goal latent plus a small action cost), so the two MPC
//! controllers and PD are compared on the same latent and the same objective.

use burn::tensor::{Device, Tensor, TensorData};
use nalgebra::{DMatrix, DVector};
use rand::{RngExt, SeedableRng};
use rand_chacha::ChaCha8Rng;

use super::mpc::{
    LatentStep, apply_first_action, dynamics_step, require_non_negative, require_positive,
    shifted_plan,
};
use crate::control::{FeedbackLaw, LatentPolicy};
use crate::model::{Dynamics, to_vec};

/// iLQR-MPC settings (defaults: PC3's planar settings, horizon 10, 6 candidates, 4 iterations).
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(deny_unknown_fields)]
pub struct IlqrConfig {
    /// Planning horizon in control steps.
    pub horizon: usize,
    /// Action sequences optimised per control step: the warm start and random ones.
    pub candidates: usize,
    /// iLQR iterations per candidate and control step.
    pub iterations: usize,
    /// Step sizes the line search tries, largest first.
    pub line_search: Vec<f64>,
    /// Cost `sum_k |h_k - h*|^2 q_h + |v_k - v*|^2 q_v + |u_k|^2 r` over the horizon.
    pub q_h: f64,
    pub q_v: f64,
    pub r: f64,
    /// Added to the diagonal of the action Hessian (keeps the backward pass invertible).
    pub regularisation: f64,
    /// Central-difference step of the dynamics' Jacobians (the network computes in f32).
    pub jacobian_step: f64,
    /// Seed of the random candidates.
    pub seed: u64,
}

impl Default for IlqrConfig {
    fn default() -> Self {
        Self {
            horizon: 10,
            candidates: 6,
            iterations: 4,
            line_search: vec![1.0, 0.5, 0.25, 0.1],
            q_h: 1.0,
            q_v: 0.1,
            r: 0.001,
            regularisation: 1e-6,
            jacobian_step: 1e-2,
            seed: 0,
        }
    }
}

impl IlqrConfig {
    pub fn validate(&self) -> crate::Result<()> {
        require_positive(
            "ilqr",
            &[
                ("horizon", self.horizon),
                ("candidates", self.candidates),
                ("iterations", self.iterations),
                ("line_search", self.line_search.len()),
            ],
        )?;
        require_non_negative(
            "ilqr",
            &[
                ("q_h", self.q_h),
                ("q_v", self.q_v),
                ("r", self.r),
                ("regularisation", self.regularisation),
            ],
        )?;
        if !(self.jacobian_step.is_finite() && self.jacobian_step > 0.0) {
            return Err(crate::Error::config("ilqr.jacobian_step", "must be > 0"));
        }
        if self
            .line_search
            .iter()
            .any(|a| !(a.is_finite() && *a > 0.0))
        {
            return Err(crate::Error::config(
                "ilqr.line_search",
                "step sizes must be > 0",
            ));
        }
        Ok(())
    }
}

/// The latent dynamics on the host: batches of states `x = (h, v)` and actions, one call.
struct Model<'a> {
    step: &'a LatentStep<'a>,
    device: &'a Device,
    du: usize,
}

impl Model<'_> {
    /// `x'` of every `(x, u)` row (`x` of length `2 du`, `u` of `du`).
    fn step_all(&self, xs: &[Vec<f64>], us: &[Vec<f64>]) -> Vec<Vec<f64>> {
        let (n, du) = (xs.len(), self.du);
        let tensor = |rows: &mut dyn Iterator<Item = f32>| {
            let values: Vec<f32> = rows.collect();
            Tensor::<2>::from_data(TensorData::new(values, [n, du]), self.device)
        };
        let h = tensor(&mut xs.iter().flat_map(|x| x[..du].iter().map(|&a| a as f32)));
        let v = tensor(&mut xs.iter().flat_map(|x| x[du..].iter().map(|&a| a as f32)));
        let u = tensor(&mut us.iter().flat_map(|u| u.iter().map(|&a| a as f32)));
        let (h, v) = (self.step)(h, v, u);
        let (h, v) = (to_vec(h), to_vec(v));
        (0..n)
            .map(|i| {
                let mut x: Vec<f64> = h[i * du..(i + 1) * du].iter().map(|&a| a as f64).collect();
                x.extend(v[i * du..(i + 1) * du].iter().map(|&a| a as f64));
                x
            })
            .collect()
    }
}

/// One candidate's plan and its states `x_0..x_H` under it.
#[derive(Clone)]
struct Trajectory {
    u: Vec<Vec<f64>>,
    x: Vec<Vec<f64>>,
    cost: f64,
}

/// The horizon cost of states `x_1..x_H` and actions `u_0..u_{H-1}`.
fn cost(config: &IlqrConfig, target: &[f64], x: &[Vec<f64>], u: &[Vec<f64>]) -> f64 {
    let du = target.len() / 2;
    let state: f64 = x[1..]
        .iter()
        .map(|xk| {
            xk.iter()
                .zip(target)
                .enumerate()
                .map(|(i, (a, b))| (a - b).powi(2) * if i < du { config.q_h } else { config.q_v })
                .sum::<f64>()
        })
        .sum();
    let effort: f64 = u.iter().flatten().map(|a| a * a * config.r).sum();
    state + effort
}

/// Rolls `plans` plans out from `x0` and costs them; each step's action may depend on the
/// state reached (`policy(plan, k, x_k)`), so the steps run one batched call at a time.
fn rollout(
    model: &Model<'_>,
    (config, target): (&IlqrConfig, &[f64]),
    x0: &[f64],
    plans: usize,
    mut policy: impl FnMut(usize, usize, &[f64]) -> Vec<f64>,
) -> Vec<Trajectory> {
    let horizon = config.horizon;
    let mut xs: Vec<Vec<Vec<f64>>> = vec![vec![x0.to_vec()]; plans];
    let mut us: Vec<Vec<Vec<f64>>> = vec![vec![]; plans];
    for k in 0..horizon {
        let current: Vec<Vec<f64>> = xs.iter().map(|x| x[k].clone()).collect();
        let actions: Vec<Vec<f64>> = (0..plans).map(|p| policy(p, k, &current[p])).collect();
        let next = model.step_all(&current, &actions);
        for p in 0..plans {
            xs[p].push(next[p].clone());
            us[p].push(actions[p].clone());
        }
    }
    us.into_iter()
        .zip(xs)
        .map(|(u, x)| Trajectory {
            cost: cost(config, target, &x, &u),
            u,
            x,
        })
        .collect()
}

/// The Jacobians `(A_k, B_k)` of `x_{k+1} = f(x_k, u_k)` along every step of every
/// trajectory, by central differences in one batched call.
fn linearise(
    model: &Model<'_>,
    config: &IlqrConfig,
    trajectories: &[Trajectory],
) -> Vec<Vec<(DMatrix<f64>, DMatrix<f64>)>> {
    let du = model.du;
    let (dx, eps) = (2 * du, config.jacobian_step);
    let (mut xs, mut us) = (vec![], vec![]);
    for t in trajectories {
        for k in 0..t.u.len() {
            for j in 0..dx + du {
                for sign in [1.0, -1.0] {
                    let (mut x, mut u) = (t.x[k].clone(), t.u[k].clone());
                    if j < dx {
                        x[j] += sign * eps;
                    } else {
                        u[j - dx] += sign * eps;
                    }
                    xs.push(x);
                    us.push(u);
                }
            }
        }
    }
    let next = model.step_all(&xs, &us);
    let mut rows = next.chunks(2 * (dx + du));
    trajectories
        .iter()
        .map(|t| {
            (0..t.u.len())
                .map(|_| {
                    let block = rows.next().unwrap_or(&[]);
                    let mut a = DMatrix::zeros(dx, dx);
                    let mut b = DMatrix::zeros(dx, du);
                    for j in 0..dx + du {
                        let (plus, minus) = (&block[2 * j], &block[2 * j + 1]);
                        for i in 0..dx {
                            let d = (plus[i] - minus[i]) / (2.0 * eps);
                            if j < dx {
                                a[(i, j)] = d;
                            } else {
                                b[(i, j - dx)] = d;
                            }
                        }
                    }
                    (a, b)
                })
                .collect()
        })
        .collect()
}

/// The backward pass: feedforward `k_k` and feedback gains `K_k` of every step, or `None`
/// when the action Hessian is not invertible.
#[allow(clippy::type_complexity)]
fn backward_pass(
    config: &IlqrConfig,
    target: &[f64],
    t: &Trajectory,
    jacobians: &[(DMatrix<f64>, DMatrix<f64>)],
) -> Option<Vec<(DVector<f64>, DMatrix<f64>)>> {
    let dx = target.len();
    let du = dx / 2;
    let weights = DVector::from_fn(dx, |i, _| if i < du { config.q_h } else { config.q_v });
    let l_xx = DMatrix::from_diagonal(&(&weights * 2.0));
    let l_uu = DMatrix::identity(du, du) * (2.0 * config.r);
    let state_gradient =
        |x: &[f64]| DVector::from_fn(dx, |i, _| 2.0 * weights[i] * (x[i] - target[i]));
    let horizon = t.u.len();
    let mut v_x = state_gradient(&t.x[horizon]);
    let mut v_xx = l_xx.clone();
    let mut gains = vec![(DVector::zeros(du), DMatrix::zeros(du, dx)); horizon];
    for k in (0..horizon).rev() {
        let (a, b) = &jacobians[k];
        let u = DVector::from_column_slice(&t.u[k]);
        let q_x = a.transpose() * &v_x;
        let q_u = &u * (2.0 * config.r) + b.transpose() * &v_x;
        let q_xx = a.transpose() * &v_xx * a;
        let q_uu =
            &l_uu + b.transpose() * &v_xx * b + DMatrix::identity(du, du) * config.regularisation;
        let q_ux = b.transpose() * &v_xx * a;
        let q_uu_inv = q_uu.clone().try_inverse()?;
        let feedforward = -&q_uu_inv * &q_u;
        let feedback = -&q_uu_inv * &q_ux;
        // The state cost of x_k (x_0 is given, so it carries none).
        let (l_x, l_xx_k) = if k > 0 {
            (state_gradient(&t.x[k]), l_xx.clone())
        } else {
            (DVector::zeros(dx), DMatrix::zeros(dx, dx))
        };
        v_x = l_x
            + q_x
            + feedback.transpose() * &q_uu * &feedforward
            + feedback.transpose() * &q_u
            + q_ux.transpose() * &feedforward;
        v_xx = l_xx_k
            + q_xx
            + feedback.transpose() * &q_uu * &feedback
            + feedback.transpose() * &q_ux
            + q_ux.transpose() * &feedback;
        v_xx = (&v_xx + v_xx.transpose()) * 0.5;
        gains[k] = (feedforward, feedback);
    }
    Some(gains)
}

/// Plans `u_0..u_{H-1}` from `x0 = (h, v)` to `target = (h*, v*)` through `step`: iLQR on
/// each initial plan in `starts` (`[H][du]` each), the cheapest result returned.
pub fn ilqr_plan(
    step: &LatentStep<'_>,
    config: &IlqrConfig,
    x0: &[f64],
    target: &[f64],
    starts: Vec<Vec<Vec<f64>>>,
    device: &Device,
) -> Vec<Vec<f64>> {
    let du = x0.len() / 2;
    let model = Model { step, device, du };
    let mut trajectories = rollout(&model, (config, target), x0, starts.len(), |p, k, _| {
        starts[p][k].clone()
    });
    let alphas = &config.line_search;
    for _ in 0..config.iterations {
        let jacobians = linearise(&model, config, &trajectories);
        let gains: Vec<_> = trajectories
            .iter()
            .zip(&jacobians)
            .map(|(t, j)| backward_pass(config, target, t, j))
            .collect();
        // Every candidate with every step size, one rollout.
        let tried = rollout(
            &model,
            (config, target),
            x0,
            trajectories.len() * alphas.len(),
            |row, k, x| {
                let (c, alpha) = (row / alphas.len(), alphas[row % alphas.len()]);
                let t = &trajectories[c];
                let Some(gains) = &gains[c] else {
                    return t.u[k].clone();
                };
                let (feedforward, feedback) = &gains[k];
                let dx = DVector::from_iterator(x.len(), x.iter().zip(&t.x[k]).map(|(a, b)| a - b));
                let du = feedforward * alpha + feedback * dx;
                t.u[k]
                    .iter()
                    .zip(du.iter())
                    .map(|(u, d)| (u + d).clamp(-1.0, 1.0))
                    .collect()
            },
        );
        for (row, candidate) in tried.into_iter().enumerate() {
            let c = row / alphas.len();
            if candidate.cost.is_finite() && candidate.cost < trajectories[c].cost {
                trajectories[c] = candidate;
            }
        }
    }
    trajectories
        .into_iter()
        .min_by(|a, b| a.cost.total_cmp(&b.cost))
        .map(|t| t.u)
        .unwrap_or_default()
}

/// iLQR-MPC as a feedback law on the latent: plans to `(h*, v*)` through the learned dynamics
/// `g` and applies the plan's first action; the next plan starts from this one shifted.
pub struct IlqrMpc {
    dynamics: Dynamics,
    device: Device,
    config: IlqrConfig,
    dt: f64,
    /// Draws the random candidates; seeded once, so an evaluation is deterministic.
    rng: ChaCha8Rng,
    plan: Vec<Vec<f64>>,
}

impl IlqrMpc {
    pub fn new(
        dynamics: Dynamics,
        device: Device,
        config: IlqrConfig,
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

impl FeedbackLaw for IlqrMpc {
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
        let (horizon, du) = (self.config.horizon, h.len());
        let mut starts = vec![shifted_plan(std::mem::take(&mut self.plan), horizon, du)];
        for _ in 1..self.config.candidates {
            starts.push(
                (0..horizon)
                    .map(|_| (0..du).map(|_| self.rng.random_range(-1.0..1.0)).collect())
                    .collect(),
            );
        }
        let x0: Vec<f64> = h.iter().chain(v).copied().collect();
        let target: Vec<f64> = h_target.iter().chain(v_target).copied().collect();
        let step = dynamics_step(&self.dynamics, self.dt);
        self.plan = ilqr_plan(&step, &self.config, &x0, &target, starts, &self.device);
        apply_first_action(&self.plan, u);
    }
}

/// iLQR-MPC on encoded frames: `h = e(frame)`, `v = (h - h_prev)/dt` and the targets exactly
/// as latent PD, then [`IlqrMpc`].
pub type IlqrPolicy = LatentPolicy<IlqrMpc>;

#[cfg(test)]
mod tests {
    use super::*;
    use crate::model::cpu_device;

    /// A double integrator per dimension with dt = 0.1 (`v' = v + dt u`, `h' = h + dt v'`).
    fn double_integrator(h: Tensor<2>, v: Tensor<2>, u: Tensor<2>) -> (Tensor<2>, Tensor<2>) {
        let v_next = v + u * 0.1;
        (h + v_next.clone() * 0.1, v_next)
    }

    fn plan_cost(config: &IlqrConfig, x0: &[f64], target: &[f64], plan: &[Vec<f64>]) -> f64 {
        let mut x = vec![x0.to_vec()];
        for u in plan {
            let last = x.last().cloned().unwrap_or_default();
            let v: Vec<f64> = (0..2).map(|i| last[2 + i] + 0.1 * u[i]).collect();
            let h: Vec<f64> = (0..2).map(|i| last[i] + 0.1 * v[i]).collect();
            x.push(h.into_iter().chain(v).collect());
        }
        cost(config, target, &x, plan)
    }

    #[test]
    fn the_linearisation_of_a_linear_model_is_exact() {
        let device = cpu_device();
        let config = IlqrConfig::default();
        let model = Model {
            step: &double_integrator,
            device: &device,
            du: 2,
        };
        let t = Trajectory {
            u: vec![vec![0.3, -0.2]],
            x: vec![vec![0.1, 0.2, 0.0, 0.5]],
            cost: 0.0,
        };
        let (a, b) = &linearise(&model, &config, &[t])[0][0];
        // x' = A x + B u with A = [[I, dt I], [0, I]], B = [[dt^2 I], [dt I]].
        let a_true = DMatrix::from_row_slice(
            4,
            4,
            &[
                1., 0., 0.1, 0., 0., 1., 0., 0.1, 0., 0., 1., 0., 0., 0., 0., 1.,
            ],
        );
        let b_true = DMatrix::from_row_slice(4, 2, &[0.01, 0., 0., 0.01, 0.1, 0., 0., 0.1]);
        assert!((a - a_true).abs().max() < 1e-4, "{a}");
        assert!((b - b_true).abs().max() < 1e-4, "{b}");
    }

    #[test]
    fn ilqr_lowers_the_cost_and_drives_a_double_integrator_to_the_goal() {
        let device = cpu_device();
        let config = IlqrConfig::default();
        let x0 = [0.0, 0.0, 0.0, 0.0];
        let target = [0.2, -0.1, 0.0, 0.0];
        let idle = vec![vec![0.0; 2]; config.horizon];
        let plan = ilqr_plan(
            &double_integrator,
            &config,
            &x0,
            &target,
            vec![idle.clone()],
            &device,
        );
        let (before, after) = (
            plan_cost(&config, &x0, &target, &idle),
            plan_cost(&config, &x0, &target, &plan),
        );
        assert!(after < 0.5 * before, "cost {before} -> {after}");
        // In closed loop (re-planning every step from the shifted plan) it reaches the goal
        // and stops there.
        let mut x = x0.to_vec();
        let mut plan = idle;
        for _ in 0..100 {
            plan = ilqr_plan(
                &double_integrator,
                &config,
                &x,
                &target,
                vec![plan],
                &device,
            );
            let u = &plan[0];
            let v: Vec<f64> = (0..2).map(|i| x[2 + i] + 0.1 * u[i]).collect();
            let h: Vec<f64> = (0..2).map(|i| x[i] + 0.1 * v[i]).collect();
            x = h.into_iter().chain(v).collect();
            plan.rotate_left(1);
        }
        let distance = ((x[0] - 0.2).powi(2) + (x[1] + 0.1).powi(2)).sqrt();
        assert!(distance < 0.01, "final state {x:?}");
    }

    #[test]
    fn bad_settings_are_refused_by_name() {
        for (config, field) in [
            (
                IlqrConfig {
                    horizon: 0,
                    ..Default::default()
                },
                "ilqr.horizon",
            ),
            (
                IlqrConfig {
                    line_search: vec![],
                    ..Default::default()
                },
                "ilqr.line_search",
            ),
            (
                IlqrConfig {
                    q_h: f64::NAN,
                    ..Default::default()
                },
                "ilqr.q_h",
            ),
        ] {
            let err = config.validate().unwrap_err().to_string();
            assert!(err.contains(field), "{err}");
        }
    }
}
