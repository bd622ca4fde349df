//! The readout check: how far the latent `h` a controller acts on is turned from the action
//! axes, measured from fresh random-control episodes by the latent's k-step response to the
//! action (docs/design.md, "Diagnostics").

use burn::tensor::Device;
use ndarray::Array3;
use rand::{RngExt, SeedableRng};
use rand_chacha::ChaCha8Rng;

use crate::data::{CollectConfig, Dataset, collect};
use crate::envs::EnvConfig;
use crate::error::Result;
use crate::model::{LatentEncoder, frames_to_tensor, to_vec};
use crate::train::orientation::ActionResponse;

/// Steps `k` of the response. The k-step residual `h_{t+k} - h_t - k (h_t - h_{t-1})` carries
/// the drive `sum_j (k - j) u_{t+j}`, whose variance grows as `k^3` against the frame noise's
/// `k^2`, so each sample says about `k` times more than a second difference; past half of a
/// 10-step episode few samples remain and the damped response bends.
pub const READOUT_CHECK_HORIZON: usize = 4;

/// Transitions simulated for the check: about 2,400 k-step samples in the reacher's 10-step
/// episodes, 3,800 in 100-step ones.
const CHECK_TRANSITIONS: usize = 4000;

/// Bootstrap refits behind [`ReadoutCheck::spread_deg`].
const BOOTSTRAP_REFITS: usize = 50;

/// Seed of the check's episodes, apart from the datasets' (`procl collect` defaults to 0) and
/// the evaluation tasks' (1000).
const CHECK_SEED: u64 = 7919;

/// What the check found.
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct ReadoutCheck {
    /// `k`.
    pub horizon: usize,
    /// k-step samples fitted.
    pub samples: u64,
    /// `B` in `h_{t+k} - h_t - k (h_t - h_{t-1}) ~ B sum_j (k - j) u_{t+j} + c`, row-major.
    pub response: Vec<f64>,
    /// True when no rotation makes `B`'s symmetric part positive semi-definite: the latent
    /// is a mirror image of the action axes, and PD with diagonal gains pushes some
    /// direction away from its goal.
    pub mirrored: bool,
    /// The angle of the rotation that would align `h` with the action axes (the polar factor
    /// of `B`, as a turn in one plane of the same size); `None` when mirrored. PD on a latent
    /// turned by `theta` acts through a stiffness `k e^{i theta}` and oscillates about its goal.
    pub turn_deg: Option<f64>,
    /// How far the estimate itself is to be trusted: the 90th percentile of the angle between
    /// the fit and its refits on the episodes resampled with replacement. Where the latent
    /// answers the action alike everywhere this is a few degrees; where its response turns
    /// from region to region (a bent latent), which episodes were drawn moves the fit, and
    /// no single readout aligns it everywhere.
    pub spread_deg: Option<f64>,
}

/// The check for `encoder` on `env`: `None` where the actions do not span every direction or
/// the response is singular.
pub fn readout_check(
    env: &EnvConfig,
    encoder: &dyn LatentEncoder,
    device: &Device,
) -> Result<Option<ReadoutCheck>> {
    let mut config = CollectConfig::new(env.kind(), CHECK_SEED);
    config.env = env.clone();
    config.transitions = CHECK_TRANSITIONS - CHECK_TRANSITIONS % config.episode_len;
    let data = collect(&config, |_| {})?;
    let latents = encode_episodes(&data, encoder, device);
    Ok(fit_readout(&data.actions, &latents, READOUT_CHECK_HORIZON))
}

/// `h` of every frame, episode-major `[episodes (steps + 1), du]`.
fn encode_episodes(data: &Dataset, encoder: &dyn LatentEncoder, device: &Device) -> Vec<f32> {
    let frames: Vec<&[u8]> = data.every_frame().collect();
    frames
        .chunks(256)
        .flat_map(|chunk| to_vec(encoder.encode(frames_to_tensor(chunk.iter().copied(), device))))
        .collect()
}

/// Fits the k-step response of `latents` (as [`encode_episodes`] lays them out) to the
/// `actions` (`[episodes, steps, du]`), and refits it on resampled episodes.
fn fit_readout(actions: &Array3<f32>, latents: &[f32], k: usize) -> Option<ReadoutCheck> {
    let &[episodes, steps, du] = actions.shape() else {
        return None;
    };
    let frames = steps + 1;
    if latents.len() != episodes * frames * du || k + 1 >= frames {
        return None;
    }
    let samples: Vec<(Vec<f32>, Vec<f32>)> = (0..episodes)
        .map(|e| {
            let h = &latents[e * frames * du..(e + 1) * frames * du];
            k_step_samples(h, |t, i| actions[[e, t, i]], du, k)
        })
        .collect();
    let fit_of = |chosen: &mut dyn Iterator<Item = usize>| {
        let mut response = ActionResponse::new(du);
        for e in chosen {
            response.observe_rows(&samples[e].0, &samples[e].1);
        }
        response.end_window()
    };
    let fit = fit_of(&mut (0..episodes))?;
    let mut rng = ChaCha8Rng::seed_from_u64(CHECK_SEED);
    let mut refits: Vec<f64> = (0..BOOTSTRAP_REFITS)
        .filter_map(|_| fit_of(&mut (0..episodes).map(|_| rng.random_range(0..episodes))))
        .map(|refit| {
            let apart = refit
                .alignment
                .iter()
                .zip(&fit.alignment)
                .map(|(x, y)| f64::from(x - y).powi(2))
                .sum::<f64>()
                .sqrt();
            turn_angle_deg(apart)
        })
        .collect();
    refits.sort_by(f64::total_cmp);
    let mirrored = determinant_sign(&fit.alignment, du) < 0.0;
    Some(ReadoutCheck {
        horizon: k,
        samples: fit.samples,
        response: fit.response,
        mirrored,
        turn_deg: (!mirrored).then(|| turn_angle_deg(fit.distance_to_identity)),
        spread_deg: refits.get(refits.len() * 9 / 10).copied(),
    })
}

/// The residuals `h_{t+k} - h_t - k (h_t - h_{t-1})` and drives `sum_{j<k} (k - j) u_{t+j}`
/// of one episode's latents `h` (`[frames, du]`, row-major), for every `t` with
/// `1 <= t <= frames - 1 - k`; `u(t, i)` is action `i` at step `t` (from frame `t` to `t + 1`).
fn k_step_samples(
    h: &[f32],
    u: impl Fn(usize, usize) -> f32,
    du: usize,
    k: usize,
) -> (Vec<f32>, Vec<f32>) {
    let frames = h.len() / du;
    let (mut residual, mut drive) = (vec![], vec![]);
    for t in 1..frames.saturating_sub(k) {
        let at = |s: usize, i: usize| h[s * du + i];
        for i in 0..du {
            residual.push(at(t + k, i) - at(t, i) - k as f32 * (at(t, i) - at(t - 1, i)));
            drive.push((0..k).map(|j| (k - j) as f32 * u(t + j, i)).sum());
        }
    }
    (residual, drive)
}

/// The angle of a turn in one plane whose matrix is `distance` (Frobenius) from the
/// identity: `|| R - I ||_F^2 = 4 (1 - cos theta)`.
fn turn_angle_deg(distance: f64) -> f64 {
    (1.0 - distance * distance / 4.0)
        .clamp(-1.0, 1.0)
        .acos()
        .to_degrees()
}

/// The sign of the determinant of a row-major `du x du` orthogonal matrix.
fn determinant_sign(p: &[f32], du: usize) -> f64 {
    let m = nalgebra::DMatrix::from_row_slice(du, du, p).map(f64::from);
    m.determinant().signum()
}

#[cfg(test)]
mod tests {
    use super::*;

    /// One episode of a double integrator `x'' = M u` (`M = diag(2, 1)`), read as `h = R x`
    /// with `R` a turn by `theta`, optionally mirrored.
    fn turned_integrator(
        theta_deg: f64,
        mirror: bool,
        steps: usize,
        seed: u64,
    ) -> (Vec<f32>, Vec<f32>) {
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        let (c, s) = (theta_deg.to_radians().cos(), theta_deg.to_radians().sin());
        let flip = if mirror { -1.0 } else { 1.0 };
        let (mut x, mut v) = ([0.0f64; 2], [0.0f64; 2]);
        let (mut h, mut u) = (vec![], vec![]);
        for t in 0..=steps {
            h.push((c * x[0] - s * flip * x[1]) as f32);
            h.push((s * x[0] + c * flip * x[1]) as f32);
            if t == steps {
                break;
            }
            let a = [rng.random_range(-1.0..=1.0), rng.random_range(-1.0..=1.0)];
            u.extend(a.iter().map(|&a| a as f32));
            v = [v[0] + 2.0 * a[0], v[1] + a[1]];
            x = [x[0] + v[0], x[1] + v[1]];
        }
        (h, u)
    }

    fn arrays_of(episodes: &[(Vec<f32>, Vec<f32>)], steps: usize) -> (Array3<f32>, Vec<f32>) {
        let actions: Vec<f32> = episodes.iter().flat_map(|(_, u)| u.clone()).collect();
        let actions = Array3::from_shape_vec((episodes.len(), steps, 2), actions).unwrap();
        let latents = episodes.iter().flat_map(|(h, _)| h.clone()).collect();
        (actions, latents)
    }

    /// The check at `k = 4` on 40 episodes of 10 steps of [`turned_integrator`].
    fn check_of(theta_deg: f64, mirror: bool) -> ReadoutCheck {
        let episodes: Vec<_> = (0..40)
            .map(|e| turned_integrator(theta_deg, mirror, 10, e))
            .collect();
        let (actions, latents) = arrays_of(&episodes, 10);
        fit_readout(&actions, &latents, 4).unwrap()
    }

    #[test]
    fn a_latent_turned_by_30_degrees_reads_a_30_degree_turn() {
        let check = check_of(30.0, false);
        assert!(!check.mirrored);
        assert_eq!(check.samples, 40 * 6);
        let turn = check.turn_deg.unwrap();
        assert!((turn - 30.0).abs() < 1e-2, "{turn}");
        assert!(check.spread_deg.unwrap() < 1e-2);
        // B = R M: the first column is (2 cos 30, 2 sin 30) degrees.
        let (b, angle) = (&check.response, 30f64.to_radians());
        assert!((b[0] - 2.0 * angle.cos()).abs() < 1e-3, "{b:?}");
        assert!((b[2] - 2.0 * angle.sin()).abs() < 1e-3, "{b:?}");
    }

    #[test]
    fn a_mirrored_latent_is_named_as_such_and_an_aligned_one_reads_no_turn() {
        let check = check_of(0.0, true);
        assert!(check.mirrored);
        assert_eq!(check.turn_deg, None);
        assert!(check_of(0.0, false).turn_deg.unwrap() < 1e-2);
    }

    #[test]
    fn the_k_step_residual_of_a_double_integrator_is_its_drive() {
        // x'' = u from rest at x_0 = 0: x_{t+k} - x_t - k (x_t - x_{t-1}) = sum_j (k - j) u_{t+j}.
        let u = [0.5f32, -1.0, 0.25, 1.0, 0.0];
        let mut x = vec![0.0f32];
        let mut v = 0.0f32;
        for &a in &u {
            v += a;
            x.push(x.last().copied().unwrap_or(0.0) + v);
        }
        let (residual, drive) = k_step_samples(&x, |t, _| u[t], 1, 2);
        assert_eq!(residual.len(), 3);
        for (r, d) in residual.iter().zip(&drive) {
            assert!((r - d).abs() < 1e-6, "{residual:?} {drive:?}");
        }
        assert_eq!(drive[0], 2.0 * u[1] + u[2]);
    }

    #[test]
    fn episodes_too_short_for_the_horizon_give_no_check() {
        let episodes: Vec<_> = (0..4)
            .map(|e| turned_integrator(0.0, false, 4, e))
            .collect();
        let (actions, latents) = arrays_of(&episodes, 4);
        assert_eq!(fit_readout(&actions, &latents, 4), None);
    }
}
