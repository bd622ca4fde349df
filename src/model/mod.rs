//! The ProCL networks: encoder `e` (one frame -> `h`), latent `z = (h, v)`, dynamics `g`.
//!
//! Tensors live on a runtime-selected burn [`Device`]: [`cpu_device`] (burn-flex, pure Rust)
//! for tests and CI, `Device::cuda(0)` with the `cuda` feature. The code never names a backend.

mod direct_conv;
mod dynamics;
mod encoder;
mod host_encoder;
mod init;
mod polar_reference;
mod soft_argmax;
mod trunk;
mod winograd;

pub use dynamics::{Dynamics, DynamicsConfig, Transition};
pub(crate) use encoder::POLAR_CENTRE;
pub use encoder::{Encoder, EncoderConfig, EncoderHead};
pub use host_encoder::HostEncoder;
pub use init::reinit_params;
pub(crate) use trunk::{ConvGradient, Scratch, TapeLayer, with_scratch};
pub use trunk::{HostBackward, TrunkTape};

use burn::module::Module;
use burn::tensor::{Device, Tensor, TensorData};

use crate::envs::{FRAME_BYTES, FRAME_PX};

/// The CPU device every test and CI run uses (burn-flex, deterministic, no native libraries).
pub fn cpu_device() -> Device {
    Device::flex()
}

/// Whether training on `device` runs the convolutions on the host, outside burn's graph
/// ([`TrunkTape`]): on the CPU with autodiff.
pub(crate) fn trains_on_host(device: &Device) -> bool {
    *device == cpu_device() && device.is_autodiff()
}

/// Picks a device by name: `cpu`, or `cuda` when built with the `cuda` feature.
pub fn device_by_name(name: &str) -> crate::Result<Device> {
    match name {
        "cpu" => Ok(cpu_device()),
        #[cfg(feature = "cuda")]
        "cuda" => Ok(Device::cuda(0)),
        other => Err(crate::Error::config(
            "device",
            format!(
                "unknown device `{other}` (available: cpu{})",
                if cfg!(feature = "cuda") {
                    ", cuda"
                } else {
                    "; build with --features cuda for cuda"
                }
            ),
        )),
    }
}

/// Distance from the polar centre (image half-widths) within which a polar keypoint's angle
/// fades to 0: the angle of a point at the pivot is undefined.
pub(crate) const POLAR_FADE_RADIUS: f32 = 0.05;

/// A pixel byte as the network sees it: [0, 255] -> [-0.5, 0.5].
#[inline(always)]
pub(crate) fn pixel_input(byte: u8) -> f32 {
    byte as f32 / 255.0 - 0.5
}

/// [`pixel_input`] of each byte of `frame` into `input`: computed, not looked up, so that it
/// vectorises (a table lookup per byte is a scalar load each).
#[inline(always)]
pub(crate) fn pixel_inputs(frame: &[u8], input: &mut [f32]) {
    for (x, &b) in input.iter_mut().zip(frame) {
        *x = pixel_input(b);
    }
}

/// Converts RGB u8 frames to the network input `[n, 3, 64, 64]`, scaled to [-0.5, 0.5].
/// This is the only place pixels are normalised.
pub fn frames_to_tensor<'a>(
    frames: impl ExactSizeIterator<Item = &'a [u8]>,
    device: &Device,
) -> Tensor<4> {
    let n = frames.len();
    let plane = FRAME_PX * FRAME_PX;
    let mut data = vec![0f32; n * FRAME_BYTES];
    for (k, frame) in frames.enumerate() {
        let out = &mut data[k * FRAME_BYTES..(k + 1) * FRAME_BYTES];
        for (p, rgb) in frame.chunks_exact(3).enumerate() {
            for c in 0..3 {
                out[c * plane + p] = pixel_input(rgb[c]);
            }
        }
    }
    Tensor::from_data(TensorData::new(data, [n, 3, FRAME_PX, FRAME_PX]), device)
}

/// Frames to the latent configuration a controller acts on: ProCL's encoder `e`, or the
/// NewtonianVAE's posterior mean. Closed-loop control, tracking and the latent diagnostics see
/// a model only through this.
pub trait LatentEncoder {
    /// `frames [n, 3, 64, 64]` (from [`frames_to_tensor`]) -> `[n, du]`.
    fn encode(&self, frames: Tensor<4>) -> Tensor<2>;
    /// Dimension of the latent configuration.
    fn latent_dim(&self) -> usize;
    /// A host copy for encoding one frame at a time, where the model has one.
    fn host_encoder(&self) -> Option<HostEncoder> {
        None
    }
}

impl LatentEncoder for Encoder {
    fn encode(&self, frames: Tensor<4>) -> Tensor<2> {
        self.forward(frames)
    }
    fn latent_dim(&self) -> usize {
        Encoder::latent_dim(self)
    }
    fn host_encoder(&self) -> Option<HostEncoder> {
        Some(Encoder::host_encoder(self))
    }
}

/// The whole ProCL model: encoder and latent dynamics, trained jointly.
#[derive(Module, Debug)]
pub struct ProclModel {
    pub encoder: Encoder,
    pub dynamics: Dynamics,
}

/// Architecture of a [`ProclModel`]; stored in the run's `config.json`.
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ModelConfig {
    pub encoder: EncoderConfig,
    pub dynamics: DynamicsConfig,
}

impl ModelConfig {
    /// Defaults for an environment with `du` action dimensions (`h` has `du` dimensions too).
    pub fn for_action_dim(du: usize) -> Self {
        Self {
            encoder: EncoderConfig::new(du),
            dynamics: DynamicsConfig::new(du),
        }
    }

    /// Builds the model with weights drawn from `seed` (same seed, same weights).
    pub fn init(&self, seed: u64, device: &Device) -> crate::Result<ProclModel> {
        self.validate()?;
        let model = ProclModel {
            encoder: self.encoder.init(device),
            dynamics: self.dynamics.init(device),
        };
        let mut model = reinit_params(model, seed);
        if self.encoder.pairwise_init_scale != 1.0 {
            model.encoder = model
                .encoder
                .scale_pairwise_inputs(self.encoder.pairwise_init_scale);
        }
        Ok(model)
    }

    /// Checks sizes before anything is built.
    pub fn validate(&self) -> crate::Result<()> {
        self.encoder.validate()?;
        self.dynamics.validate()?;
        if self.encoder.latent_dim != self.dynamics.latent_dim {
            return Err(crate::Error::config(
                "model.dynamics.latent_dim",
                "must equal model.encoder.latent_dim",
            ));
        }
        Ok(())
    }
}

/// Name of the non-trained orientation parameter (skipped by init and the optimiser).
pub(crate) const LATENT_TRANSFORM: &str = "latent_transform";

/// A fresh orientation `Q = I` (du x du), excluded from training.
pub(crate) fn transform_param(du: usize, device: &Device) -> burn::module::Param<Tensor<2>> {
    burn::module::Param::from_tensor(Tensor::eye(du, device)).set_require_grad(false)
}

impl ProclModel {
    /// The orientation `Q` of the latent (an orthogonal map, row-major `du x du`):
    /// `h = Q head(frame)`.
    pub fn latent_transform(&self) -> Vec<f32> {
        to_vec(self.encoder.latent_transform.val())
    }

    /// Applies the orthogonal map `p` (row-major `du x du`) to the latent in the encoder and
    /// the dynamics together: `h -> p h`. CPC, consistency and curvature are exactly invariant
    /// to this (the dynamics MLP and the diagonal transition density work in the unturned
    /// coordinates); the Lyapunov risk is not, which is what lets the orientation search pick
    /// the PD-controllable one of the mirror images and axis orders that gradient descent
    /// cannot move between (it would have to collapse a latent axis on the way).
    pub fn reorient_latent(self, p: &[f32]) -> Self {
        let mut model = self;
        model.encoder.latent_transform = turn_transform(model.encoder.latent_transform, p);
        model.dynamics.latent_transform = turn_transform(model.dynamics.latent_transform, p);
        model
    }
}

/// The orientation `Q` turned by `p` (row-major, the same size): `Q -> p Q`, so `h -> p h`.
pub(crate) fn turn_transform(
    q: burn::module::Param<Tensor<2>>,
    p: &[f32],
) -> burn::module::Param<Tensor<2>> {
    q.map(|q| {
        let du = q.dims()[0];
        Tensor::<2>::from_data(TensorData::new(p.to_vec(), [du, du]), &q.device()).matmul(q)
    })
}

/// Marks a freshly built parameter tensor as trainable when it lives on an autodiff device
/// (inference devices have no autodiff and need no gradients).
pub(crate) fn trainable<const D: usize>(tensor: Tensor<D>) -> Tensor<D> {
    if tensor.is_autodiff() {
        tensor.require_grad()
    } else {
        tensor
    }
}

/// Reads scalar `[1]` tensors back to the host in one device sync (loss terms for logging).
pub fn read_scalars(scalars: &[&Tensor<1>]) -> Vec<f64> {
    let all = Tensor::cat(scalars.iter().map(|&t| t.clone()).collect(), 0);
    to_vec(all).into_iter().map(f64::from).collect()
}

/// Reads a float tensor back as a flat `Vec<f32>`, row-major.
pub fn to_vec<const D: usize>(tensor: Tensor<D>) -> Vec<f32> {
    tensor.into_data().iter::<f32>().collect()
}

/// One preset for each shipped encoder head: the point mass's Cartesian keypoints, the
/// reacher's polar keypoints with pairwise angles over 32x32 cells and a tanh layer, and the
/// paper's MLP head.
#[cfg(test)]
pub(crate) const SHIPPED_HEADS: [(crate::envs::EnvKind, crate::train::Preset); 3] = [
    (crate::envs::EnvKind::PointMass, crate::train::Preset::Procl),
    (crate::envs::EnvKind::Reacher, crate::train::Preset::Procl),
    (crate::envs::EnvKind::Reacher, crate::train::Preset::Paper),
];

/// The first frame of `n` episodes of `env` (seeds 0 to n - 1): test inputs for the encoders.
#[cfg(test)]
pub(crate) fn start_frames(env: crate::envs::EnvKind, n: u64) -> Vec<[u8; FRAME_BYTES]> {
    let mut environment = env.make();
    (0..n)
        .map(|seed| {
            environment.reset(seed).expect("reset");
            let mut frame = [0u8; FRAME_BYTES];
            environment.render(&mut frame);
            frame
        })
        .collect()
}
