//! Seeded parameter initialisation: every weight redrawn from one ChaCha stream in module order,
//! so the same seed gives the same weights on any backend (burn's own initialisers draw from a
//! backend RNG that is neither scoped nor guaranteed identical across backends).

use burn::module::{Module, ModuleMapper, Param};
use burn::tensor::{Tensor, TensorData};
use rand::{RngExt, SeedableRng};
use rand_chacha::ChaCha8Rng;

/// Redraws all float parameters of `module`: weights and their biases uniform in
/// `+-1/sqrt(fan_in)` (PyTorch's default for Linear and Conv2d); parameters named `log_std`
/// `log_sharpness`, `log_input_gain` and `precision_lower` and the orientation keep their
/// configured initial values.
pub fn reinit_params<M: Module>(module: M, seed: u64) -> M {
    let mut mapper = SeededInit {
        rng: ChaCha8Rng::seed_from_u64(seed),
        path: vec![],
        fan_in: 1,
    };
    module.map(&mut mapper)
}

struct SeededInit {
    rng: ChaCha8Rng,
    path: Vec<String>,
    /// Fan-in of the last weight seen, used by the bias that follows it.
    fan_in: usize,
}

impl ModuleMapper for SeededInit {
    fn enter_module(&mut self, name: &str, _container_type: &str) {
        self.path.push(name.to_string());
    }
    fn exit_module(&mut self, _name: &str, _container_type: &str) {
        self.path.pop();
    }
    fn map_float<const D: usize>(&mut self, param: Param<Tensor<D>>) -> Param<Tensor<D>> {
        let name = self.path.last().map(String::as_str).unwrap_or("");
        let dims = param.val().dims();
        let count: usize = dims.iter().product();
        if name == "log_std"
            || name == "log_sharpness"
            || name == "log_input_gain"
            || name == "precision_lower"
            || name == super::LATENT_TRANSFORM
            || name == super::encoder::POLAR_AXIS
            || name == super::encoder::POLAR_CENTRE
            || name == super::encoder::POLAR_BACKGROUND
            || name == super::encoder::POLAR_REFERENCE_AXIS
        {
            return param;
        }
        let values: Vec<f32> = {
            if D >= 2 {
                // Conv weight [out, in, k, k]: fan_in = in k k. Linear weight [in, out]: in.
                self.fan_in = if D == 4 {
                    dims[1] * dims[2] * dims[3]
                } else {
                    dims[0]
                };
            }
            let bound = 1.0 / (self.fan_in.max(1) as f32).sqrt();
            (0..count)
                .map(|_| self.rng.random_range(-bound..bound))
                .collect()
        };
        param.map(|tensor| {
            let device = tensor.device();
            crate::model::trainable(Tensor::from_data(TensorData::new(values, dims), &device))
        })
    }
}
