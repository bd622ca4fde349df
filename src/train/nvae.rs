//! The NewtonianVAE's part of the shared training loop: seeded windows of consecutive frames,
//! the sequence ELBO, the validation ELBO on held-out episodes and the plateau stopping rule.

use std::io::Write;
use std::ops::Range;

use burn::tensor::{Device, Tensor, TensorData};
use rand::RngExt;
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;

use super::orientation::LatentOrienter;
use super::{
    Objective, RunPaths, TrainConfig, normal_tensor, orientation_window_end, step_rng,
    truncate_metrics,
};
use crate::baselines::nvae::{
    ELBO_NAMES, ElboInputs, NvaeConfig, NvaeModel, Targets, VALIDATION_NAMES, elbo_loss,
};
use crate::data::{Dataset, PixelSpread};
use crate::error::{Error, Result};
use crate::losses::StepValues;
use crate::model::{HostBackward, TrunkTape, frames_to_tensor, to_vec, trains_on_host};

/// Validation windows at most: enough for a stable mean, few enough to cost a few steps.
const VALIDATION_WINDOWS: usize = 64;

/// The dataset's episodes split into those trained on and those held out for validation
/// (the last `validation_share` of them, at least one when the share is positive).
#[derive(Debug, Clone, PartialEq)]
pub struct EpisodeSplit {
    pub train: Range<usize>,
    pub validation: Range<usize>,
}

impl EpisodeSplit {
    pub fn of(data: &Dataset, nvae: &NvaeConfig) -> Result<Self> {
        let episodes = data.episodes();
        if nvae.sequence_len > data.steps() + 1 {
            return Err(Error::config(
                "nvae.sequence_len",
                format!(
                    "{} frames do not fit in the dataset's episodes of {} frames",
                    nvae.sequence_len,
                    data.steps() + 1
                ),
            ));
        }
        let held = if nvae.validation_share > 0.0 {
            ((nvae.validation_share * episodes as f64).round() as usize).max(1)
        } else {
            0
        };
        if held >= episodes {
            return Err(Error::config(
                "nvae.validation_share",
                format!(
                    "holding out {held} of the dataset's {episodes} episodes leaves none to train on; set it and nvae.plateau_patience to 0"
                ),
            ));
        }
        Ok(Self {
            train: 0..episodes - held,
            validation: episodes - held..episodes,
        })
    }
}

/// `n` windows `(episode, first frame)` of `len` frames, from `episodes`.
fn sample_windows(
    data: &Dataset,
    rng: &mut ChaCha8Rng,
    episodes: &Range<usize>,
    len: usize,
    n: usize,
) -> Vec<(usize, usize)> {
    (0..n)
        .map(|_| {
            (
                rng.random_range(episodes.clone()),
                rng.random_range(0..data.steps() + 2 - len),
            )
        })
        .collect()
}

/// What the ELBO reads of a batch of windows of consecutive frames.
pub struct WindowFrames<'a> {
    /// Every frame of every window, window-major.
    pub frames: Vec<&'a [u8]>,
    /// Frames `2..len` of every window: those the ELBO scores.
    pub targets: Vec<&'a [u8]>,
    /// `u_t` for `t = 1..len - 1` of every window, row-major `[windows (len - 2), du]`.
    pub u: Vec<f32>,
}

/// The frames and actions of `windows` `(episode, first frame)` of `len` frames each.
pub fn window_frames<'a>(
    data: &'a Dataset,
    windows: &[(usize, usize)],
    len: usize,
) -> WindowFrames<'a> {
    let du = data.action_dim();
    let frames: Vec<&[u8]> = windows
        .iter()
        .flat_map(|&(e, s)| (s..s + len).map(move |t| data.frame(e, t)))
        .collect();
    let targets: Vec<&[u8]> = frames
        .chunks_exact(len)
        .flat_map(|window| &window[2..])
        .copied()
        .collect();
    let u: Vec<f32> = windows
        .iter()
        .flat_map(|&(e, s)| (s + 1..s + len - 1).flat_map(move |t| (0..du).map(move |i| (e, t, i))))
        .map(|(e, t, i)| data.actions[[e, t, i]])
        .collect();
    WindowFrames { frames, targets, u }
}

/// The raw frames and tensors of a batch of windows; the posterior is the model's part.
struct WindowBatch<'a> {
    /// Every frame of every window, window-major.
    frames: Vec<&'a [u8]>,
    /// Frames `2..len` of every window: those the ELBO scores.
    targets: Vec<&'a [u8]>,
    u: Tensor<2>,
    posterior_noise: Tensor<2>,
    prior_noise: Tensor<2>,
    windows: usize,
}

impl<'a> WindowBatch<'a> {
    fn new(
        data: &'a Dataset,
        windows: &[(usize, usize)],
        len: usize,
        rng: &mut ChaCha8Rng,
        device: &Device,
    ) -> Self {
        let (w, du, terms) = (windows.len(), data.action_dim(), len - 2);
        let WindowFrames { frames, targets, u } = window_frames(data, windows, len);
        Self {
            frames,
            targets,
            u: Tensor::from_data(TensorData::new(u, [w * terms, du]), device),
            posterior_noise: normal_tensor(rng, w * len, du, device),
            prior_noise: normal_tensor(rng, w * terms, du, device),
            windows: w,
        }
    }

    /// Encodes the frames and returns the ELBO's inputs with the trunk's tape (the batch's
    /// tensors are shared, not copied). With `decode_on_host` the decoder's convolutions run
    /// on the host ([`Targets::Frames`]).
    fn inputs(
        &self,
        model: &NvaeModel,
        device: &Device,
        decode_on_host: bool,
    ) -> (ElboInputs<'_>, Option<TrunkTape>) {
        let (mean, log_std, tape) = model.encoder.posterior_training(&self.frames, device);
        let targets = if decode_on_host {
            Targets::Frames(&self.targets)
        } else {
            Targets::Pixels(frames_to_tensor(self.targets.iter().copied(), device))
        };
        let inputs = ElboInputs {
            mean,
            log_std,
            targets,
            u: self.u.clone(),
            posterior_noise: self.posterior_noise.clone(),
            prior_noise: self.prior_noise.clone(),
            windows: self.windows,
        };
        (inputs, tape)
    }
}

/// The controller's latent's second differences `h_{t+1} - 2 h_t + h_{t-1}`, `h = Q mean`,
/// for `t = 1..len - 1` of every window: row-major `[windows (len - 2), du]`, the rows of the
/// batch's actions `u_t` (what the action response regresses). `mean` is window-major
/// `[windows len, du]`, `q` row-major `du x du`.
fn readout_second_differences(mean: &[f32], q: &[f32], du: usize, len: usize) -> Vec<f32> {
    let mut a = Vec::with_capacity(mean.len());
    for window in mean.chunks_exact(len * du) {
        let row = |k: usize| &window[k * du..(k + 1) * du];
        for t in 1..len - 1 {
            let (prev, now, next) = (row(t - 1), row(t), row(t + 1));
            let raw: Vec<f32> = (0..du).map(|j| next[j] - 2.0 * now[j] + prev[j]).collect();
            a.extend((0..du).map(|i| (0..du).map(|j| q[i * du + j] * raw[j]).sum::<f32>()));
        }
    }
    a
}

/// The stopping rule: a run has plateaued once its validation ELBO has not improved on the
/// best so far by more than `tolerance` (relative) for `patience` validations in a row.
#[derive(Debug, Clone)]
pub struct PlateauRule {
    patience: u64,
    tolerance: f64,
    best: Option<f64>,
    stale: u64,
}

impl PlateauRule {
    pub fn new(patience: u64, tolerance: f64) -> Self {
        Self {
            patience,
            tolerance,
            best: None,
            stale: 0,
        }
    }

    /// Records one validation loss (lower is better); true once the run has plateaued.
    pub fn observe(&mut self, loss: f64) -> bool {
        match self.best {
            Some(best) if loss >= best - self.tolerance * best.abs() => self.stale += 1,
            _ => {
                self.best = Some(loss);
                self.stale = 0;
            }
        }
        self.patience > 0 && self.stale >= self.patience
    }
}

/// Trains a [`NvaeModel`] by the annealed sequence ELBO.
pub(crate) struct NvaeObjective<'a> {
    config: &'a TrainConfig,
    nvae: &'a NvaeConfig,
    data: &'a Dataset,
    run: &'a RunPaths,
    device: &'a Device,
    split: EpisodeSplit,
    plateau: PlateauRule,
    /// The validation windows and noise, drawn once (`None` without validation episodes).
    validation: Option<WindowBatch<'a>>,
    /// The readout orientation's chooser (action response only; `None`: the readout stays
    /// the identity).
    search: Option<LatentOrienter>,
}

impl<'a> NvaeObjective<'a> {
    pub(crate) fn new(
        config: &'a TrainConfig,
        nvae: &'a NvaeConfig,
        data: &'a Dataset,
        run: &'a RunPaths,
        device: &'a Device,
        search: Option<LatentOrienter>,
    ) -> Result<Self> {
        let split = EpisodeSplit::of(data, nvae)?;
        let validation = (!split.validation.is_empty())
            .then(|| validation_batch(data, config.seed, nvae.sequence_len, &split, device));
        Ok(Self {
            config,
            nvae,
            data,
            run,
            device,
            split,
            plateau: PlateauRule::new(nvae.plateau_patience, nvae.plateau_tolerance),
            validation,
            search,
        })
    }

    fn dt(&self) -> f64 {
        self.nvae.dt(self.data.meta.control_dt_s)
    }

    fn validation_header() -> String {
        format!("step,{}", VALIDATION_NAMES.join(","))
    }
}

/// Up to [`VALIDATION_WINDOWS`] windows of the validation episodes and their noise, from a
/// stream of the seed that training never draws from: the same at every validation.
fn validation_batch<'a>(
    data: &'a Dataset,
    seed: u64,
    len: usize,
    split: &EpisodeSplit,
    device: &Device,
) -> WindowBatch<'a> {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    rng.set_stream(u64::MAX - 1);
    let episodes = &split.validation;
    let available = episodes.len() * (data.steps() + 2 - len);
    let windows = sample_windows(
        data,
        &mut rng,
        episodes,
        len,
        available.min(VALIDATION_WINDOWS),
    );
    WindowBatch::new(data, &windows, len, &mut rng, device)
}

impl Objective for NvaeObjective<'_> {
    type Model = NvaeModel;
    const METRICS: &'static [&'static str] = &ELBO_NAMES;

    fn prepare(&mut self, mut model: NvaeModel) -> NvaeModel {
        // The same polar frame as ProCL's, so that both methods see the arm from its shoulder.
        model.encoder = model
            .encoder
            .place_polar_frame(|| PixelSpread::of_frames(self.data.every_frame()));
        model
    }

    fn begin(&mut self, resumed_at: Option<u64>) -> Result<()> {
        if self.validation.is_none() {
            return Ok(());
        }
        let path = self.run.validation();
        let header = Self::validation_header();
        let Some(start) = resumed_at else {
            return std::fs::write(&path, header + "\n").map_err(|e| Error::io(&path, e));
        };
        if !path.exists() {
            std::fs::write(&path, format!("{header}\n")).map_err(|e| Error::io(&path, e))?;
        }
        truncate_metrics(&path, start, &header)?;
        // The stopping rule picks up where the interrupted run left it.
        let text = std::fs::read_to_string(&path).map_err(|e| Error::io(&path, e))?;
        for line in text.lines().skip(1) {
            let mut fields = line.split(',').map(|f| f.parse::<f64>());
            if let (Some(Ok(step)), Some(Ok(total))) = (fields.next(), fields.next())
                && step as u64 > self.nvae.kl_anneal_end()
            {
                self.plateau.observe(total);
            }
        }
        Ok(())
    }

    fn loss(&mut self, model: &NvaeModel, step: u64) -> (Tensor<1>, StepValues, HostBackward) {
        let mut rng = step_rng(self.config.seed, step);
        let len = self.nvae.sequence_len;
        let windows = sample_windows(
            self.data,
            &mut rng,
            &self.split.train,
            len,
            self.config.batch_size,
        );
        let batch = WindowBatch::new(self.data, &windows, len, &mut rng, self.device);
        let (inputs, tape) = batch.inputs(model, self.device, trains_on_host(self.device));
        if let Some(LatentOrienter::ActionResponse(response)) = self.search.as_mut() {
            let mean = to_vec(inputs.mean.clone().detach());
            let du = inputs.u.dims()[1];
            let a = readout_second_differences(&mean, &model.encoder.readout(), du, len);
            response.observe_rows(&a, &to_vec(inputs.u.clone()));
        }
        let terms = elbo_loss(
            model,
            self.nvae,
            inputs,
            self.nvae.kl_weight(step),
            self.dt(),
        );
        (
            terms.total.clone(),
            terms.values(),
            terms.host_backward(tape),
        )
    }

    fn after_update(&mut self, mut model: NvaeModel, step: u64) -> Result<NvaeModel> {
        if let Some(turn) =
            orientation_window_end(self.search.as_mut(), self.config, self.run, step)?
        {
            model.encoder = model.encoder.reorient_readout(&turn);
        }
        Ok(model)
    }

    fn stop_after(&mut self, model: &NvaeModel, step: u64) -> Result<bool> {
        let done = step + 1;
        let Some(batch) = self.validation.as_ref() else {
            return Ok(false);
        };
        if !done.is_multiple_of(self.nvae.validate_every) {
            return Ok(false);
        }
        // Scored in burn's graph: validation needs no gradients.
        let (inputs, _) = batch.inputs(model, self.device, false);
        let values = elbo_loss(model, self.nvae, inputs, 1.0, self.dt()).values();
        let path = self.run.validation();
        let row: Vec<String> = values.values[..VALIDATION_NAMES.len()]
            .iter()
            .map(|x| format!("{x:.6}"))
            .collect();
        let mut file = std::fs::OpenOptions::new()
            .append(true)
            .open(&path)
            .map_err(|e| Error::io(&path, e))?;
        writeln!(file, "{done},{}", row.join(",")).map_err(|e| Error::io(&path, e))?;
        // The objective changes while beta anneals: only validations at beta = 1 count.
        Ok(done > self.nvae.kl_anneal_end() && self.plateau.observe(values.total()))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn plateau_rule_stops_after_patience_validations_without_improvement() {
        let mut rule = PlateauRule::new(2, 0.01);
        // 100 -> 90 improves; 89.5 is within 1% of 90 (stale 1); 95 is worse (stale 2): stop.
        assert!(!rule.observe(100.0));
        assert!(!rule.observe(90.0));
        assert!(!rule.observe(89.5));
        assert!(rule.observe(95.0));
        // An improvement past the tolerance resets the count.
        let mut rule = PlateauRule::new(2, 0.01);
        for loss in [100.0, 99.5, 98.0, 97.5] {
            assert!(!rule.observe(loss), "{loss}");
        }
        assert!(rule.observe(97.2));
        // Patience 0 never stops.
        let mut rule = PlateauRule::new(0, 0.01);
        assert!((0..10).all(|_| !rule.observe(1.0)));
    }

    #[test]
    fn second_differences_are_taken_within_windows_and_turned_by_the_readout() {
        // Two windows of 4 frames, du = 2. Window 0: x = t^2 (second difference 2), y = 0;
        // window 1: x = 0, y = -t^3 (second differences -6 at t = 1, -12 at t = 2).
        let mean = [
            0.0, 0.0, 1.0, 0.0, 4.0, 0.0, 9.0, 0.0, //
            0.0, 0.0, 0.0, -1.0, 0.0, -8.0, 0.0, -27.0,
        ];
        let identity = [1.0, 0.0, 0.0, 1.0];
        let a = readout_second_differences(&mean, &identity, 2, 4);
        assert_eq!(a, vec![2.0, 0.0, 2.0, 0.0, 0.0, -6.0, 0.0, -12.0]);
        // A quarter turn h = (-y, x).
        let turn = [0.0, -1.0, 1.0, 0.0];
        let a = readout_second_differences(&mean, &turn, 2, 4);
        assert_eq!(a, vec![0.0, 2.0, 0.0, 2.0, 6.0, 0.0, 12.0, 0.0]);
    }

    #[test]
    fn episodes_split_into_training_and_held_out_validation() {
        let data = super::super::tiny_dataset(crate::envs::EnvKind::PointMass, 1, 200);
        assert_eq!(data.episodes(), 10);
        let mut nvae = NvaeConfig::for_action_dim(2);
        nvae.validation_share = 0.1;
        let split = EpisodeSplit::of(&data, &nvae).unwrap();
        assert_eq!((split.train, split.validation), (0..9, 9..10));
        // A small positive share still holds out one episode; 0 holds out none.
        nvae.validation_share = 0.01;
        assert_eq!(EpisodeSplit::of(&data, &nvae).unwrap().validation, 9..10);
        nvae.validation_share = 0.0;
        assert_eq!(EpisodeSplit::of(&data, &nvae).unwrap().train, 0..10);
        // Windows longer than an episode (21 frames) are refused by name.
        nvae.sequence_len = 22;
        let err = EpisodeSplit::of(&data, &nvae).unwrap_err().to_string();
        assert!(err.contains("nvae.sequence_len"), "{err}");
        // Every window lies inside one training episode.
        let mut rng = ChaCha8Rng::seed_from_u64(3);
        for (e, s) in sample_windows(&data, &mut rng, &(0..9), 21, 50) {
            assert!(e < 9 && s == 0);
        }
        for (e, s) in sample_windows(&data, &mut rng, &(0..9), 5, 200) {
            assert!(e < 9 && s + 5 <= 21, "{e} {s}");
        }
    }
}
