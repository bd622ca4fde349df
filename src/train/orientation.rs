//! The latent's orientation during training: which rotation or mirror image of `h` a PD law
//! with diagonal gains acts on, chosen by the windowed Lyapunov risk of the signed permutations
//! or by the latent's measured response to the action (docs/design.md).

use std::path::Path;

use burn::tensor::{Tensor, TensorData};
use nalgebra::DMatrix;

use crate::error::Result;
use crate::fsutil::append_line;
use crate::losses::{LossConfig, LossInputs};

/// How the training loop chooses the orientation of the latent (every
/// `orientation_search_every` steps, from the window's training batches).
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum OrientationCriterion {
    /// The signed permutation with the lowest Lyapunov risk over the window
    /// ([`OrientationSearch`]).
    #[default]
    Risk,
    /// The rotation or reflection that makes the latent's mean response to the action most
    /// positive on its diagonal ([`ActionResponse`]). It does not depend on the latent's scale,
    /// which the risk does.
    ActionResponse,
}

/// The orientation chooser of one training run, by criterion.
pub enum LatentOrienter {
    Risk(OrientationSearch),
    ActionResponse(ActionResponse),
}

impl LatentOrienter {
    pub fn new(criterion: OrientationCriterion, du: usize) -> Self {
        match criterion {
            OrientationCriterion::Risk => Self::Risk(OrientationSearch::new(du)),
            OrientationCriterion::ActionResponse => Self::ActionResponse(ActionResponse::new(du)),
        }
    }

    /// Adds one training batch (clean encodings, read detached: choosing trains nothing).
    pub fn observe(&mut self, inputs: &LossInputs, loss: &LossConfig, dt: f64) {
        match self {
            Self::Risk(search) => search.observe(inputs, loss, dt),
            Self::ActionResponse(response) => response.observe(inputs),
        }
    }

    /// Ends the window that closes at step `step` (1-based): logs its evidence in `dir`
    /// (`orientation_windows.csv` or `action_response.csv`) and returns the reorientation `p`
    /// (row-major `du x du`, `h -> p h`) to apply, if any, after logging it to
    /// `orientation.csv` as `step, p, criterion before, criterion after` (risk: lower is
    /// better; action response: `trace B`, higher is better).
    pub fn end_window(
        &mut self,
        dir: &Path,
        step: u64,
        rule: WindowRule,
    ) -> Result<Option<Vec<f32>>> {
        let decision = match self {
            Self::Risk(search) => {
                search.log_window(&dir.join("orientation_windows.csv"), step)?;
                search.decide(rule.margin, rule.streak)
            }
            Self::ActionResponse(response) => {
                let window = response.end_window();
                if let Some(w) = &window {
                    let b: Vec<String> = w.response.iter().map(|x| format!("{x:.6e}")).collect();
                    let header = (0..b.len())
                        .map(|k| format!("b{}{}", k / w.du, k % w.du))
                        .collect::<Vec<_>>()
                        .join(",");
                    append_line(
                        &dir.join("action_response.csv"),
                        &format!("step,samples,{header},distance_to_identity"),
                        &format!(
                            "{step},{},{},{:.6}",
                            w.samples,
                            b.join(","),
                            w.distance_to_identity
                        ),
                    )?;
                }
                window
                    .filter(|w| w.distance_to_identity > rule.tolerance)
                    .map(|w| (w.alignment, w.trace_before, w.trace_after))
            }
        };
        let Some((p, before, after)) = decision else {
            return Ok(None);
        };
        append_line(
            &dir.join("orientation.csv"),
            "",
            &format!("{step},{p:?},{before:.6},{after:.6}"),
        )?;
        Ok(Some(p))
    }
}

/// When a window's evidence changes the orientation.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct WindowRule {
    /// Risk: the best candidate must beat the current orientation by this fraction ...
    pub margin: f64,
    /// ... and have been the best for this many consecutive windows.
    pub streak: u64,
    /// Action response: rotate only when the aligning map is further than this from the
    /// identity (Frobenius norm), so estimation noise does not turn the latent every window.
    pub tolerance: f64,
}

/// The latent's mean response to the action, `B` in `h_{t+1} - 2 h_t + h_{t-1} ~ B u_t + c`,
/// fitted by least squares over a window of training samples.
///
/// A PD law with diagonal gains, `u = Kp (h* - h) - Kd v`, drives the latent to its target
/// when `B` has a positive-definite symmetric part (locally `B = J M^-1`, the image Jacobian
/// times the inverse inertia, has the eigenvalues of `M^-1 J`). The orthogonal map `p` that
/// maximises `trace(p B)` is `U^T` from the polar decomposition `B = U P` (orthogonal
/// Procrustes); after it the response is `P`, symmetric positive semi-definite. Unlike the
/// windowed Lyapunov risk, this does not depend on the latent's scale: on the reacher the risk
/// told the 8 signed permutations apart by less than 0.5% and left runs mis-oriented.
/// Random-control data has actions independent of the state, so regressing on `u` alone
/// averages the state-dependent terms into `c`.
pub struct ActionResponse {
    du: usize,
    samples: u64,
    sum_u: Vec<f64>,
    sum_a: Vec<f64>,
    /// Row-major `du x du`: `sum a_i u_j`.
    sum_au: Vec<f64>,
    /// Row-major `du x du`: `sum u_i u_j`.
    sum_uu: Vec<f64>,
}

/// One window's fit and the alignment it implies.
#[derive(Debug, Clone, PartialEq)]
pub struct ResponseWindow {
    pub du: usize,
    pub samples: u64,
    /// `B`, row-major.
    pub response: Vec<f64>,
    /// `p = U^T`, row-major: `h -> p h` makes the response symmetric positive semi-definite.
    pub alignment: Vec<f32>,
    /// `|| p - I ||_F`.
    pub distance_to_identity: f64,
    /// `trace B` and `trace (p B)`.
    pub trace_before: f64,
    pub trace_after: f64,
}

impl ActionResponse {
    pub fn new(du: usize) -> Self {
        Self {
            du,
            samples: 0,
            sum_u: vec![0.0; du],
            sum_a: vec![0.0; du],
            sum_au: vec![0.0; du * du],
            sum_uu: vec![0.0; du * du],
        }
    }

    /// Adds a training batch's `(h_{t-1}, h_t, h_{t+1}, u_t)`.
    pub fn observe(&mut self, inputs: &LossInputs) {
        let second_difference = inputs.h_next.clone().detach()
            - inputs.h_now.clone().detach() * 2.0
            + inputs.h_prev.clone().detach();
        let a = crate::model::to_vec(second_difference);
        let u = crate::model::to_vec(inputs.u.clone());
        self.observe_rows(&a, &u);
    }

    /// Adds samples given as row-major `[n, du]` second differences `a` and actions `u`.
    pub fn observe_rows(&mut self, a: &[f32], u: &[f32]) {
        let du = self.du;
        for (a, u) in a.chunks_exact(du).zip(u.chunks_exact(du)) {
            self.samples += 1;
            for i in 0..du {
                self.sum_u[i] += u[i] as f64;
                self.sum_a[i] += a[i] as f64;
                for j in 0..du {
                    self.sum_au[i * du + j] += a[i] as f64 * u[j] as f64;
                    self.sum_uu[i * du + j] += u[i] as f64 * u[j] as f64;
                }
            }
        }
    }

    /// The window's fit (`None` when the actions do not span every direction) and a fresh
    /// window.
    pub fn end_window(&mut self) -> Option<ResponseWindow> {
        let (du, samples) = (self.du, self.samples);
        let fit = self.fit();
        *self = Self::new(du);
        let b = fit?;
        let u = polar_orthogonal(&b)?;
        let p = u.transpose();
        let aligned = &p * &b;
        Some(ResponseWindow {
            du,
            samples,
            response: b.transpose().as_slice().to_vec(),
            alignment: p.transpose().as_slice().iter().map(|&x| x as f32).collect(),
            distance_to_identity: (&p - DMatrix::identity(du, du)).norm(),
            trace_before: b.trace(),
            trace_after: aligned.trace(),
        })
    }

    /// `B = C_au C_uu^-1` from the centred sums.
    fn fit(&self) -> Option<DMatrix<f64>> {
        let (du, n) = (self.du, self.samples as f64);
        if self.samples <= du as u64 {
            return None;
        }
        let centred = |sum: &[f64], x: &[f64], y: &[f64]| {
            DMatrix::from_fn(du, du, |i, j| (sum[i * du + j] - x[i] * y[j] / n) / n)
        };
        let c_au = centred(&self.sum_au, &self.sum_a, &self.sum_u);
        let c_uu = centred(&self.sum_uu, &self.sum_u, &self.sum_u);
        let c_uu_inv = c_uu.try_inverse()?;
        Some(c_au * c_uu_inv).filter(|b| b.iter().all(|x| x.is_finite()))
    }
}

/// The orthogonal factor `U` of the polar decomposition `B = U P` (`P` symmetric positive
/// semi-definite), from the SVD `B = W S V^T`: `U = W V^T`. `None` when `B` is numerically
/// singular (then `U` is not unique and the fit says nothing about some direction).
pub fn polar_orthogonal(b: &DMatrix<f64>) -> Option<DMatrix<f64>> {
    let svd = b.clone().svd(true, true);
    let (w, v_t) = (svd.u?, svd.v_t?);
    let largest = svd.singular_values.max();
    let smallest = svd.singular_values.min();
    (largest > 0.0 && smallest > 1e-6 * largest).then(|| w * v_t)
}

/// The Lyapunov risk of each signed permutation of the latent (2^du du! of them), summed over
/// a window of steps on the training batches (clean encodings, detached: it only chooses, it
/// does not train).
pub struct OrientationSearch {
    /// Row-major `du x du` signed permutation matrices, identity first.
    candidates: Vec<Vec<f32>>,
    sums: Vec<f64>,
    /// The candidate that was best in the last windows, and for how many in a row.
    run: (usize, u64),
}

/// All signed permutation matrices of size `du` (row-major), identity first.
pub fn signed_permutations(du: usize) -> Vec<Vec<f32>> {
    fn permutations(items: Vec<usize>) -> Vec<Vec<usize>> {
        if items.len() <= 1 {
            return vec![items];
        }
        let mut out = vec![];
        for (i, &first) in items.iter().enumerate() {
            let mut rest = items.clone();
            rest.remove(i);
            for mut tail in permutations(rest) {
                tail.insert(0, first);
                out.push(tail);
            }
        }
        out
    }
    let mut all = vec![];
    for perm in permutations((0..du).collect()) {
        for bits in 0..1usize << du {
            let mut m = vec![0.0f32; du * du];
            for (row, &col) in perm.iter().enumerate() {
                m[row * du + col] = if bits & (1 << row) != 0 { -1.0 } else { 1.0 };
            }
            all.push(m);
        }
    }
    all
}

impl OrientationSearch {
    pub fn new(du: usize) -> Self {
        let candidates = signed_permutations(du);
        let sums = vec![0.0; candidates.len()];
        Self {
            candidates,
            sums,
            run: (0, 0),
        }
    }

    /// Adds this batch's risk under every candidate `p` (latent `h -> p h`).
    pub fn observe(&mut self, inputs: &LossInputs, loss: &LossConfig, dt: f64) {
        let du = inputs.h_now.dims()[1];
        let device = inputs.h_now.device();
        for (k, candidate) in self.candidates.iter().enumerate() {
            // Rows are samples: h p^T.
            let p_t = Tensor::<2>::from_data(TensorData::new(candidate.clone(), [du, du]), &device)
                .transpose();
            let h_prev = inputs.h_prev.clone().detach().matmul(p_t.clone());
            let h_now = inputs.h_now.clone().detach().matmul(p_t.clone());
            let h_next = inputs.h_next.clone().detach().matmul(p_t);
            // The risk the trainer optimises: standardised if `loss.risk_latent_std` says so.
            let (h_prev, h_now, h_next) = match crate::losses::risk_scale(loss, h_now.clone()) {
                Some(scale) => (
                    h_prev * scale.clone(),
                    h_now * scale.clone(),
                    h_next * scale,
                ),
                None => (h_prev, h_now, h_next),
            };
            let v_now = (h_now.clone() - h_prev) / dt;
            let v_next = (h_next.clone() - h_now.clone()) / dt;
            let target = crate::losses::hindsight_targets(
                h_now.clone(),
                v_now.clone(),
                inputs.u.clone(),
                &inputs.permutation,
                loss.kp,
                loss.kd,
            );
            let risk = crate::losses::lyapunov_risk(
                (h_now, v_now),
                (h_next, v_next),
                target,
                loss.q_h,
                loss.q_v,
                loss.lyapunov_dt_s.unwrap_or(dt),
            );
            self.sums[k] += crate::model::to_vec(risk)
                .first()
                .copied()
                .unwrap_or(f32::NAN) as f64;
        }
    }

    /// Appends this window's summed risk of every candidate (in [`signed_permutations`]
    /// order, candidate 0 the current orientation) to `path`, with a header on creation: the
    /// evidence behind each decision, including the windows that changed nothing.
    pub fn log_window(&self, path: &Path, step: u64) -> Result<()> {
        let names: Vec<String> = (0..self.sums.len()).map(|k| format!("c{k}")).collect();
        let sums: Vec<String> = self.sums.iter().map(|x| format!("{x:.6}")).collect();
        append_line(
            path,
            &format!("step,{}", names.join(",")),
            &format!("{step},{}", sums.join(",")),
        )
    }

    /// Ends the window: the best candidate if it has been the best for `streak` consecutive
    /// windows and beats the current orientation by the fraction `margin` in this one, with the
    /// window's summed risks of the current orientation and the best.
    pub fn decide(&mut self, margin: f64, streak: u64) -> Option<(Vec<f32>, f64, f64)> {
        let best = (0..self.sums.len())
            .min_by(|&a, &b| self.sums[a].total_cmp(&self.sums[b]))
            .unwrap_or(0);
        let (identity, best_sum) = (self.sums[0], self.sums[best]);
        self.sums.iter_mut().for_each(|s| *s = 0.0);
        self.run = match self.run {
            (k, n) if k == best && best != 0 => (best, n + 1),
            _ => (best, u64::from(best != 0)),
        };
        let switch =
            best != 0 && self.run.1 >= streak.max(1) && best_sum < (1.0 - margin) * identity;
        if switch {
            self.run = (0, 0);
        }
        switch.then(|| (self.candidates[best].clone(), identity, best_sum))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::envs::EnvKind;
    use rand::{RngExt, SeedableRng};
    use rand_chacha::ChaCha8Rng;

    fn rotation(angle: f64) -> DMatrix<f64> {
        let (s, c) = angle.sin_cos();
        DMatrix::from_row_slice(2, 2, &[c, -s, s, c])
    }

    #[test]
    fn polar_factor_is_the_rotation_in_front_of_a_positive_definite_matrix() {
        let spd = DMatrix::from_row_slice(2, 2, &[2.0, 0.5, 0.5, 1.0]);
        let mirror = DMatrix::from_row_slice(2, 2, &[-1.0, 0.0, 0.0, 1.0]);
        for u in [rotation(0.7), rotation(-2.9), rotation(1.2) * &mirror] {
            let found = polar_orthogonal(&(&u * &spd)).unwrap();
            assert!((found - &u).norm() < 1e-12);
        }
        // A singular response leaves the orientation undetermined.
        let singular = DMatrix::from_row_slice(2, 2, &[1.0, 2.0, 2.0, 4.0]);
        assert!(polar_orthogonal(&singular).is_none());
    }

    /// Random-control rollouts of `env` (actions held 1-5 steps, as the datasets), observed
    /// through the synthetic latent `h = s R q` of the true configuration; returns the window.
    fn window_of_synthetic_latent(env: EnvKind, r: &DMatrix<f64>, s: f64) -> ResponseWindow {
        let mut env = env.make();
        let du = env.action_dim();
        let mut rng = ChaCha8Rng::seed_from_u64(3);
        let mut response = ActionResponse::new(du);
        let latent = |q: &[f64]| -> Vec<f64> {
            (r * DMatrix::from_column_slice(du, 1, q) * s)
                .as_slice()
                .to_vec()
        };
        for episode in 0..40 {
            env.reset(episode).unwrap();
            let mut h = vec![latent(&env.state().q)];
            let mut action = vec![0.0; du];
            let mut actions = vec![];
            for t in 0..50 {
                if t % rng.random_range(1..=5) == 0 {
                    action = (0..du).map(|_| rng.random_range(-1.0..=1.0)).collect();
                }
                env.step(&action);
                actions.push(action.clone());
                h.push(latent(&env.state().q));
            }
            for t in 1..50 {
                let a: Vec<f32> = (0..du)
                    .map(|i| (h[t + 1][i] - 2.0 * h[t][i] + h[t - 1][i]) as f32)
                    .collect();
                let u: Vec<f32> = actions[t].iter().map(|&x| x as f32).collect();
                response.observe_rows(&a, &u);
            }
        }
        response.end_window().unwrap()
    }

    #[test]
    fn action_response_undoes_a_rotated_mirror_image_of_the_true_configuration() {
        // The point mass (B = I / m) and the reacher (B = M(q)^-1 averaged, coupled, with joint
        // limits and damping): whatever orthogonal map R the latent is seen through, the
        // alignment p brings h = s R q back to s q, so PD with diagonal gains pushes each
        // coordinate the right way. The scale s does not matter (the risk's blind spot).
        let mirror = DMatrix::from_row_slice(2, 2, &[1.0, 0.0, 0.0, -1.0]);
        for env in [EnvKind::PointMass, EnvKind::Reacher] {
            for (r, s) in [
                (rotation(2.5) * &mirror, 0.1),
                (rotation(-1.0), 3.0),
                (rotation(std::f64::consts::FRAC_PI_2), 0.01),
            ] {
                let window = window_of_synthetic_latent(env, &r, s);
                let p = DMatrix::from_row_slice(
                    2,
                    2,
                    &window
                        .alignment
                        .iter()
                        .map(|&x| x as f64)
                        .collect::<Vec<_>>(),
                );
                let error = (&p * &r - DMatrix::identity(2, 2)).norm();
                assert!(error < 0.15, "{env}: p R = {}", &p * &r);
                assert!(window.trace_after > 0.0 && window.trace_after >= window.trace_before);
                assert!(window.distance_to_identity > 0.5);
            }
            // Already aligned: the map stays within the tolerance of the identity.
            let window = window_of_synthetic_latent(env, &DMatrix::identity(2, 2), 1.0);
            assert!(window.distance_to_identity < 0.15, "{env}: {window:?}");
        }
    }

    #[test]
    fn action_response_needs_actions_in_every_direction() {
        let mut response = ActionResponse::new(2);
        // u only ever along the first axis: C_uu is singular.
        response.observe_rows(
            &[1.0, 0.0, 2.0, 0.0, -1.0, 0.0],
            &[1.0, 0.0, 2.0, 0.0, -1.0, 0.0],
        );
        assert!(response.end_window().is_none());
    }

    #[test]
    fn orientation_search_needs_the_margin_and_the_streak() {
        let mut search = OrientationSearch::new(2);
        let window = |search: &mut OrientationSearch, best: usize, ratio: f64| {
            search.sums.iter_mut().for_each(|s| *s = 1.0);
            search.sums[best] = ratio;
            search.decide(0.0, 3).map(|(p, _, _)| p)
        };
        // Candidate 5 wins by 3% twice, candidate 2 interrupts, then 5 wins three in a row.
        assert_eq!(window(&mut search, 5, 0.97), None);
        assert_eq!(window(&mut search, 5, 0.97), None);
        assert_eq!(window(&mut search, 2, 0.97), None);
        assert_eq!(window(&mut search, 5, 0.97), None);
        assert_eq!(window(&mut search, 5, 0.97), None);
        let expected = signed_permutations(2)[5].clone();
        assert_eq!(window(&mut search, 5, 0.97), Some(expected));
        // The default rule (margin 10%, streak 1): a 3% win is not enough, a 20% win is.
        search.sums.iter_mut().for_each(|s| *s = 1.0);
        search.sums[4] = 0.97;
        assert!(search.decide(0.1, 1).is_none());
        search.sums.iter_mut().for_each(|s| *s = 1.0);
        search.sums[4] = 0.8;
        assert!(search.decide(0.1, 1).is_some());
    }
}
