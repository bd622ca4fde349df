//! The NewtonianVAE's part of the shared training loop: seeded batches and the ELBO.

use burn::tensor::{Device, Tensor};

use super::{Objective, TrainConfig, batch_tensors, normal_tensor, sample_batch, step_rng};
use crate::baselines::nvae::{ELBO_NAMES, ElboInputs, NvaeConfig, NvaeModel, elbo_loss};
use crate::data::Dataset;
use crate::losses::StepValues;
use crate::model::TrunkTape;

/// The frames, actions and reparameterisation noise of training step `step`, drawn from the
/// step's own RNG stream (so `--resume` is exact), as ProCL's batches are.
pub fn elbo_inputs(data: &Dataset, config: &TrainConfig, step: u64, device: &Device) -> ElboInputs {
    let mut rng = step_rng(config.seed, step);
    let n = config.batch_size;
    let batch = sample_batch(data, &mut rng, n);
    let (frames, u) = batch_tensors(data, &batch, device);
    ElboInputs {
        frames,
        u,
        noise: normal_tensor(&mut rng, 3 * n, data.action_dim(), device),
    }
}

/// Trains a [`NvaeModel`] by the annealed ELBO.
pub(crate) struct NvaeObjective<'a> {
    config: &'a TrainConfig,
    nvae: &'a NvaeConfig,
    data: &'a Dataset,
    device: &'a Device,
}

impl<'a> NvaeObjective<'a> {
    pub(crate) fn new(
        config: &'a TrainConfig,
        nvae: &'a NvaeConfig,
        data: &'a Dataset,
        device: &'a Device,
    ) -> Self {
        Self {
            config,
            nvae,
            data,
            device,
        }
    }
}

impl Objective for NvaeObjective<'_> {
    type Model = NvaeModel;
    const METRICS: &'static [&'static str] = &ELBO_NAMES;

    fn loss(&mut self, model: &NvaeModel, step: u64) -> (Tensor<1>, StepValues, Option<TrunkTape>) {
        let inputs = elbo_inputs(self.data, self.config, step, self.device);
        let dt = self.nvae.dt(self.data.meta.control_dt_s);
        let terms = elbo_loss(model, self.nvae, inputs, self.nvae.kl_weight(step), dt);
        (terms.total.clone(), terms.values(), None)
    }
}
