//! Seeded training batches: the samples `(i_{t-1}, i_t, u_t, i_{t+1})` of a step, drawn from
//! the step's own RNG stream so a resumed run draws what the uninterrupted one would have.

use burn::tensor::{Device, Tensor, TensorData};
use rand::seq::SliceRandom;
use rand::{RngExt, SeedableRng};
use rand_chacha::ChaCha8Rng;

use super::TrainConfig;
use crate::data::Dataset;
use crate::losses::LossInputs;
use crate::model::{ProclModel, TrunkTape, frames_to_tensor};

/// Frames for the data-dependent latent-scale initialisation: 256 drawn from a stream of
/// `seed` that training batches never use.
pub(super) fn scale_frames(data: &Dataset, seed: u64, device: &Device) -> Tensor<4> {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    rng.set_stream(u64::MAX);
    let picks = sample_batch(data, &mut rng, 256);
    frames_to_tensor(picks.iter().map(|&(e, t)| data.frame(e, t)), device)
}

/// A training sample `(i_{t-1}, i_t, u_t, i_{t+1})` is addressed by (episode, t), 1 <= t < T.
pub(crate) fn sample_batch(data: &Dataset, rng: &mut ChaCha8Rng, n: usize) -> Vec<(usize, usize)> {
    sample_batch_reaching(data, rng, n, 1)
}

/// Samples whose frame `t + reach` is in the episode too: 1 <= t <= T - reach (`reach = 1`
/// draws exactly what [`sample_batch`] draws).
fn sample_batch_reaching(
    data: &Dataset,
    rng: &mut ChaCha8Rng,
    n: usize,
    reach: usize,
) -> Vec<(usize, usize)> {
    (0..n)
        .map(|_| {
            (
                rng.random_range(0..data.episodes()),
                rng.random_range(1..data.steps() + 1 - reach),
            )
        })
        .collect()
}

/// The drive of the `k`-step action response: `sum_{j<k} (k - j) u_{t+j}` for every sample,
/// `[n * du]` row-major. Under Euler steps `v' = v + dt B u`, `h' = h + dt v'` it is what
/// `(h_{t+k} - h_t - k (h_t - h_{t-1})) / dt^2` equals through `B`.
fn k_step_drive(data: &Dataset, batch: &[(usize, usize)], k: usize) -> Vec<f32> {
    let du = data.action_dim();
    batch
        .iter()
        .flat_map(|&(e, t)| {
            (0..du).map(move |i| {
                (0..k)
                    .map(|j| (k - j) as f32 * data.actions[[e, t + j, i]])
                    .sum::<f32>()
            })
        })
        .collect()
}

/// `[n, d]` standard normal draws from `rng` (Box-Muller; deterministic for a seed).
pub(crate) fn normal_tensor(
    rng: &mut ChaCha8Rng,
    n: usize,
    d: usize,
    device: &Device,
) -> Tensor<2> {
    let values: Vec<f32> = (0..n * d)
        .map(|_| {
            let u1: f64 = rng.random_range(f64::EPSILON..1.0);
            let u2: f64 = rng.random_range(0.0..1.0);
            ((-2.0 * u1.ln()).sqrt() * (2.0 * std::f64::consts::PI * u2).cos()) as f32
        })
        .collect();
    Tensor::from_data(TensorData::new(values, [n, d]), device)
}

/// The RNG of training step `step`: stream `step + 1` of the seed, so a resumed run draws
/// exactly what the uninterrupted run would have.
pub(crate) fn step_rng(seed: u64, step: u64) -> ChaCha8Rng {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    rng.set_stream(step + 1);
    rng
}

/// The frames of the samples `batch`: every `i_{t-1}`, then every `i_t`, then every `i_{t+1}`.
pub(crate) fn batch_frames<'a>(data: &'a Dataset, batch: &[(usize, usize)]) -> Vec<&'a [u8]> {
    batch
        .iter()
        .map(|&(e, t)| data.frame(e, t - 1))
        .chain(batch.iter().map(|&(e, t)| data.frame(e, t)))
        .chain(batch.iter().map(|&(e, t)| data.frame(e, t + 1)))
        .collect()
}

/// The actions `u_t` of the samples `batch`, `[n, du]`.
pub(crate) fn batch_actions(
    data: &Dataset,
    batch: &[(usize, usize)],
    device: &Device,
) -> Tensor<2> {
    let du = data.action_dim();
    let actions: Vec<f32> = batch
        .iter()
        .flat_map(|&(e, t)| (0..du).map(move |i| (e, t, i)))
        .map(|(e, t, i)| data.actions[[e, t, i]])
        .collect();
    Tensor::from_data(TensorData::new(actions, [batch.len(), du]), device)
}

/// The encodings and random draws of training step `step` (see [`step_rng`]), and the
/// encoder trunk's tape where it ran on the host: pass it the loss's gradients
/// ([`TrunkTape::backward`]) before the optimiser step.
pub fn loss_inputs(
    model: &ProclModel,
    data: &Dataset,
    config: &TrainConfig,
    step: u64,
    device: &Device,
) -> (LossInputs, Option<TrunkTape>) {
    let mut rng = step_rng(config.seed, step);
    let n = config.batch_size;
    let du = data.action_dim();
    // The k-step sign term needs the frame `i_{t+k}` of each sample.
    let reach = config.loss.frames_ahead();
    let batch = sample_batch_reaching(data, &mut rng, n, reach);
    let u = batch_actions(data, &batch, device);
    // Every `i_{t-1}`, every `i_t`, every `i_{t+1}`, then every `i_{t+k}`, in one encoder call.
    let mut frames = batch_frames(data, &batch);
    if reach > 1 {
        frames.extend(batch.iter().map(|&(e, t)| data.frame(e, t + reach)));
    }
    let (h, trunk) = model.encoder.forward_training(&frames, device); // [3n or 4n, du]
    let ahead = (reach > 1).then(|| {
        let drive = TensorData::new(k_step_drive(data, &batch, reach), [n, du]);
        (
            h.clone().narrow(0, 3 * n, n),
            Tensor::from_data(drive, device),
        )
    });
    let mut permutation: Vec<usize> = (0..n).collect();
    permutation.shuffle(&mut rng);
    let inputs = LossInputs {
        h_prev: h.clone().narrow(0, 0, n),
        h_now: h.clone().narrow(0, n, n),
        h_next: h.narrow(0, 2 * n, n),
        u,
        latent_noise: normal_tensor(&mut rng, n, du, device),
        curvature_noise: (
            normal_tensor(&mut rng, n, du, device),
            normal_tensor(&mut rng, n, du, device),
            normal_tensor(&mut rng, n, du, device),
        ),
        permutation,
        ahead,
    };
    (inputs, trunk)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::envs::EnvKind;
    use crate::losses::{LOSS_NAMES, StepValues, procl_loss};
    use crate::train::{Method, Preset, tiny_dataset};

    #[test]
    fn k_step_drive_is_what_an_euler_latent_responds_to() {
        let data = tiny_dataset(EnvKind::PointMass, 5, 400);
        let (dt, k) = (0.02f32, 6);
        // A latent that moves by Euler steps with one input gain `B` (turned and sheared), from
        // a random start at rest in every episode.
        let gain = [[0.8f32, -0.6], [0.3, 1.1]];
        let mut rng = step_rng(3, 0);
        let latent: Vec<Vec<[f32; 2]>> = (0..data.episodes())
            .map(|e| {
                let mut h = [rng.random_range(-1.0..1.0), rng.random_range(-1.0..1.0)];
                let mut v = [0.0f32; 2];
                let mut path = vec![h];
                for t in 0..data.steps() {
                    let u = [data.actions[[e, t, 0]], data.actions[[e, t, 1]]];
                    for i in 0..2 {
                        v[i] += dt * 40.0 * (gain[i][0] * u[0] + gain[i][1] * u[1]);
                        h[i] += dt * v[i];
                    }
                    path.push(h);
                }
                path
            })
            .collect();
        let batch = sample_batch_reaching(&data, &mut rng, 64, k);
        assert!(batch.iter().all(|&(_, t)| t >= 1 && t + k <= data.steps()));
        let device = crate::model::cpu_device();
        let rows = |map: &dyn Fn([f32; 2]) -> [f32; 2], offset: isize| {
            let values: Vec<f32> = batch
                .iter()
                .flat_map(|&(e, t)| map(latent[e][(t as isize + offset) as usize]))
                .collect();
            Tensor::<2>::from_data(TensorData::new(values, [batch.len(), 2]), &device)
        };
        let drive = Tensor::<2>::from_data(
            TensorData::new(k_step_drive(&data, &batch, k), [batch.len(), 2]),
            &device,
        );
        // The response `h_{t+k} - h_t - k (h_t - h_{t-1})` is `dt^2 40 B` times the drive.
        let (prev, now, ahead) = (rows(&|h| h, -1), rows(&|h| h, 0), rows(&|h| h, k as isize));
        let response = crate::model::to_vec(ahead - now.clone() - (now - prev) * k as f32);
        let drive = crate::model::to_vec(drive);
        for (row, (r, d)) in response.chunks(2).zip(drive.chunks(2)).enumerate() {
            for i in 0..2 {
                let want = dt * dt * 40.0 * (gain[i][0] * d[0] + gain[i][1] * d[1]);
                assert!(
                    (r[i] - want).abs() < 1e-4,
                    "row {row}, dim {i}: {} vs {want}",
                    r[i]
                );
            }
        }
    }

    #[test]
    fn logged_terms_add_up_to_the_total_minimised() {
        let data = tiny_dataset(EnvKind::Reacher, 2, 200);
        let mut config = TrainConfig::preset(Preset::Procl, Method::Procl, EnvKind::Reacher);
        config.batch_size = 24;
        config.loss.action_response_horizon = 3;
        config.loss.action_response_regions = 3;
        let device = crate::model::cpu_device();
        let model = config.model.init(7, &device).expect("model");
        let (inputs, _) = loss_inputs(&model, &data, &config, 0, &device);
        let dt = data.meta.control_dt_s;
        let values: StepValues = procl_loss(&config.loss, &model.dynamics, inputs, dt)
            .values()
            .into();
        let term = |name: &str| values.get(name).expect(name);
        let loss = &config.loss;
        let pc3 = loss.lambda_cpc * term("cpc")
            + loss.lambda_cons * term("cons")
            + loss.lambda_curv * term("curv");
        let recombined = loss.lambda_pc3 * pc3
            + loss.lambda_r * term("lyap")
            + loss.action_response_sign_weight * term("sign");
        assert!(
            (recombined - values.total()).abs() <= 1e-4 * values.total().abs().max(1.0),
            "{values}: recombined {recombined}"
        );
        assert!(term("sign") >= 0.0, "{values}");

        // Switched off, a term is logged as 0 and the header keeps its column.
        config.loss.action_response_sign_weight = 0.0;
        let (inputs, _) = loss_inputs(&model, &data, &config, 0, &device);
        assert!(inputs.ahead.is_none());
        let off: StepValues = procl_loss(&config.loss, &model.dynamics, inputs, dt)
            .values()
            .into();
        assert_eq!(off.get("sign"), Some(0.0), "{off}");
        assert_eq!(off.names, &LOSS_NAMES);
    }
}
