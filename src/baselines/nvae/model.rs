//! The NewtonianVAE networks: Gaussian encoder `q(x | frame)`, decoder `p(frame | x)`, and the
//! Newtonian transition prior `p(x_{t+1} | x_t, v_t, u_t)`.

use burn::module::{Module, Param};
use burn::nn::conv::{Conv2d, Conv2dConfig};
use burn::nn::{Linear, LinearConfig, PaddingConfig2d};
use burn::tensor::activation::relu;
use burn::tensor::module::interpolate;
use burn::tensor::ops::{InterpolateMode, InterpolateOptions};
use burn::tensor::{Device, Tensor};

use super::NvaeConfig;
use crate::model::{
    Encoder, EncoderConfig, HostEncoder, LatentEncoder, TrunkTape, reinit_params, to_vec,
    turn_transform,
};

/// The encoder `q(x | frame) = N(mean, diag(exp(log_std))^2)`: ProCL's conv trunk and head
/// with `2 du` outputs, split into the mean and the log std. As a [`LatentEncoder`] it gives
/// the posterior mean turned by the readout orientation `Q`, the latent the controller acts on.
#[derive(Module, Debug)]
pub struct GaussianEncoder {
    net: Encoder,
    /// The readout orientation `Q` (`du x du`, not trained): the controller's latent is
    /// `h = Q mean`. The ELBO works on the unturned mean, so choosing `Q` (by the action
    /// response, [`crate::train::orientation`]) leaves training's losses as they are.
    pub latent_transform: Param<Tensor<2>>,
}

impl GaussianEncoder {
    /// Places a polar head's centre and cut from the data, as [`Encoder::place_polar_frame`].
    pub fn place_polar_frame(self, spread: impl FnOnce() -> crate::data::PixelSpread) -> Self {
        Self {
            net: self.net.place_polar_frame(spread),
            ..self
        }
    }

    /// The polar head's centre, as [`Encoder::polar_centre`].
    pub fn polar_centre(&self) -> Option<[f32; 2]> {
        self.net.polar_centre()
    }

    /// The readout orientation `Q`, row-major `du x du`.
    pub fn readout(&self) -> Vec<f32> {
        to_vec(self.latent_transform.val())
    }

    /// Turns the controller's latent by `p` (row-major `du x du`): `Q -> p Q`.
    pub fn reorient_readout(self, p: &[f32]) -> Self {
        Self {
            latent_transform: turn_transform(self.latent_transform, p),
            ..self
        }
    }

    /// `frames [n, 3, 64, 64]` -> `(mean, log_std)`, `[n, du]` each.
    pub fn posterior(&self, frames: Tensor<4>) -> (Tensor<2>, Tensor<2>) {
        let out = self.net.forward(frames); // [n, 2 du]
        let du = out.dims()[1] / 2;
        (out.clone().narrow(1, 0, du), out.narrow(1, du, du))
    }

    /// As [`Self::posterior`] for training on raw frames: on the CPU the conv trunk runs
    /// outside burn's graph, and its tape carries the gradient back
    /// ([`crate::model::TrunkTape::backward`]).
    pub fn posterior_training(
        &self,
        frames: &[&[u8]],
        device: &Device,
    ) -> (Tensor<2>, Tensor<2>, Option<TrunkTape>) {
        let (out, tape) = self.net.forward_training(frames, device); // [n, 2 du]
        let du = out.dims()[1] / 2;
        (out.clone().narrow(1, 0, du), out.narrow(1, du, du), tape)
    }
}

impl LatentEncoder for GaussianEncoder {
    fn encode(&self, frames: Tensor<4>) -> Tensor<2> {
        // Rows are samples: h = mean Q^T.
        let mean = self.posterior(frames).0;
        mean.matmul(self.latent_transform.val().transpose())
    }
    fn latent_dim(&self) -> usize {
        self.net.latent_dim() / 2
    }
    fn host_encoder(&self) -> Option<HostEncoder> {
        let host = self.net.host_encoder().leading(self.latent_dim());
        Some(host.turned(&self.readout()))
    }
}

/// The decoder: `x [n, du]` -> the mean frame `[n, 3, 64, 64]` (pixels in [-0.5, 0.5]). Two
/// dense layers to an 8x8 feature map, then three nearest-neighbour 2x upsamplings, each
/// followed by a 3x3 conv (no transposed convs: upsample + conv has no checkerboard artefacts).
#[derive(Module, Debug)]
pub struct Decoder {
    fc1: Linear,
    fc2: Linear,
    pub(super) conv1: Conv2d,
    pub(super) conv2: Conv2d,
    pub(super) conv3: Conv2d,
}

/// Side of the decoder's first feature map.
pub(super) const DECODER_BASE_PX: usize = 8;

impl Decoder {
    /// `x [n, du]` -> `[n, 3, 64, 64]`.
    pub fn forward(&self, x: Tensor<2>) -> Tensor<4> {
        let n = x.dims()[0];
        let c0 = self.conv1.weight.val().dims()[1];
        let x = self
            .base_maps(x)
            .reshape([n, c0, DECODER_BASE_PX, DECODER_BASE_PX]); // [n, c0, 8, 8]
        let x = relu(self.conv1.forward(upsample2(x))); // [n, c1, 16, 16]
        let x = relu(self.conv2.forward(upsample2(x))); // [n, c2, 32, 32]
        self.conv3.forward(upsample2(x)) // [n, 3, 64, 64]
    }

    /// The dense layers: `x [n, du]` -> the 8x8 feature maps, flattened `[n, c0 * 8 * 8]`.
    pub(super) fn base_maps(&self, x: Tensor<2>) -> Tensor<2> {
        let x = relu(self.fc1.forward(x)); // [n, hidden]
        relu(self.fc2.forward(x))
    }
}

/// Nearest-neighbour 2x upsampling, `[n, c, h, w]` -> `[n, c, 2h, 2w]`.
fn upsample2(x: Tensor<4>) -> Tensor<4> {
    let [_, _, h, w] = x.dims();
    interpolate(
        x,
        InterpolateOptions::new(InterpolateMode::Nearest).with_output_size([2 * h, 2 * w]),
    )
}

/// The Newtonian transition prior: `[A, log(-B), log C] = MLP(x)` (diagonal matrices, two ReLU
/// hidden layers), `v' = v + dt (A x + B v + C u)`, `x' ~ N(x + dt v', diag(exp(log_std))^2)`.
/// `B < 0` makes the latent velocity damped, `C > 0` makes each action push its own latent
/// coordinate forward: the structure that is meant to make the latent P(I)D-controllable.
#[derive(Module, Debug)]
pub struct NvaeTransition {
    fc1: Linear,
    fc2: Linear,
    fc3: Linear,
    /// Log of the prior's std `sigma_p` per latent dimension, `[du]` (learned).
    pub log_std: Param<Tensor<1>>,
}

/// The diagonals of `A`, `B`, `C` at each sample, `[n, du]` each.
#[derive(Debug, Clone)]
pub struct TransitionMatrices {
    pub a: Tensor<2>,
    pub b: Tensor<2>,
    pub c: Tensor<2>,
}

impl NvaeTransition {
    /// `[A, B, C]` at `x [n, du]`.
    pub fn matrices(&self, x: Tensor<2>) -> TransitionMatrices {
        let du = x.dims()[1];
        let out = self
            .fc3
            .forward(relu(self.fc2.forward(relu(self.fc1.forward(x))))); // [n, 3 du]
        TransitionMatrices {
            a: out.clone().narrow(1, 0, du),
            b: out.clone().narrow(1, du, du).exp().neg(),
            c: out.narrow(1, 2 * du, du).exp(),
        }
    }
}

impl TransitionMatrices {
    /// The same diagonals `[A, B, C]` at each of `n` samples of `du` dimensions.
    pub fn constant([a, b, c]: [f64; 3], n: usize, du: usize, device: &Device) -> Self {
        let full = |value: f64| Tensor::full([n, du], value, device);
        Self {
            a: full(a),
            b: full(b),
            c: full(c),
        }
    }

    /// One Newtonian step from `x_t`, `v_t`, `u_t` (`[n, du]` each) over `dt` seconds:
    /// `v' = v + dt (A x + B v + C u)`, `x' = x + dt v'`; returns the prior's mean `x'` and the
    /// predicted velocity `v'`.
    pub fn step(self, x: Tensor<2>, v: Tensor<2>, u: Tensor<2>, dt: f64) -> (Tensor<2>, Tensor<2>) {
        let accel = self.a * x.clone() + self.b * v.clone() + self.c * u; // [n, du]
        let v_next = v + accel * dt;
        let x_next = x + v_next.clone() * dt;
        (x_next, v_next)
    }
}

/// The whole NewtonianVAE, trained jointly by the ELBO ([`super::elbo_loss`]).
#[derive(Module, Debug)]
pub struct NvaeModel {
    pub encoder: GaussianEncoder,
    pub decoder: Decoder,
    pub transition: NvaeTransition,
}

impl NvaeConfig {
    /// Builds the model with weights drawn from `seed` (same seed, same weights).
    pub fn init(&self, seed: u64, device: &Device) -> crate::Result<NvaeModel> {
        self.validate()?;
        let du = self.latent_dim;
        let [c0, c1, c2] = self.decoder_channels;
        let conv3x3 = |cin, cout| {
            Conv2dConfig::new([cin, cout], [3, 3])
                .with_padding(PaddingConfig2d::Explicit(1, 1, 1, 1))
                .init(device)
        };
        let h = self.transition_hidden;
        let model = NvaeModel {
            encoder: GaussianEncoder {
                net: self.encoder_config().init(device),
                latent_transform: crate::model::transform_param(du, device),
            },
            decoder: Decoder {
                fc1: LinearConfig::new(du, self.decoder_hidden).init(device),
                fc2: LinearConfig::new(self.decoder_hidden, c0 * DECODER_BASE_PX * DECODER_BASE_PX)
                    .init(device),
                conv1: conv3x3(c0, c1),
                conv2: conv3x3(c1, c2),
                conv3: conv3x3(c2, 3),
            },
            transition: NvaeTransition {
                fc1: LinearConfig::new(du, h).init(device),
                fc2: LinearConfig::new(h, h).init(device),
                fc3: LinearConfig::new(h, 3 * du).init(device),
                log_std: Param::from_tensor(Tensor::full([du], self.init_prior_std.ln(), device)),
            },
        };
        Ok(reinit_params(model, seed))
    }

    /// The encoder network: ProCL's trunk and head with `2 du` outputs (mean, log std).
    pub(crate) fn encoder_config(&self) -> EncoderConfig {
        EncoderConfig {
            trunk_channels: self.trunk_channels,
            head: self.encoder_head,
            keypoint_sharpness: self.keypoint_sharpness,
            ..EncoderConfig::new(2 * self.latent_dim)
        }
    }
}

#[cfg(test)]
pub(crate) mod tests {
    use burn::tensor::TensorData;

    use super::*;
    use crate::model::{cpu_device, to_vec};

    pub(crate) fn tiny() -> NvaeConfig {
        NvaeConfig {
            trunk_channels: [4, 4],
            encoder_head: crate::model::EncoderHead::Mlp { hidden: 8 },
            decoder_hidden: 8,
            decoder_channels: [4, 4, 4],
            ..NvaeConfig::for_action_dim(2)
        }
    }

    #[test]
    fn decoder_renders_full_frames_and_encoder_splits_mean_and_std() {
        let device = cpu_device();
        let model = tiny().init(0, &device).unwrap();
        let x = Tensor::<2>::from_data(
            TensorData::new(vec![0.1f32, -0.2, 0.3, 0.0, 1.0, 2.0], [3, 2]),
            &device,
        );
        let frames = model.decoder.forward(x);
        assert_eq!(frames.dims(), [3, 3, 64, 64]);
        let (mean, log_std) = model.encoder.posterior(frames.clone());
        assert_eq!((mean.dims(), log_std.dims()), ([3, 2], [3, 2]));
        // The control-time latent is the posterior mean.
        assert_eq!(to_vec(model.encoder.encode(frames)), to_vec(mean));
        assert_eq!(LatentEncoder::latent_dim(&model.encoder), 2);
    }

    #[test]
    fn host_encoder_gives_the_posterior_mean_turned_by_the_readout() {
        let device = cpu_device();
        let frames = crate::model::start_frames(crate::envs::EnvKind::PointMass, 3);
        for head in [
            crate::model::EncoderHead::Mlp { hidden: 8 },
            crate::model::EncoderHead::SoftArgmax {
                keypoints: 4,
                hidden: 0,
                polar: false,
                pairwise_angles: false,
            },
        ] {
            let config = NvaeConfig {
                encoder_head: head,
                ..tiny()
            };
            let encoder = config.init(2, &device).unwrap().encoder;
            let input = crate::model::frames_to_tensor(frames.iter().map(|f| &f[..]), &device);
            let (mean, _) = encoder.posterior(input.clone());
            let mean = to_vec(mean);
            // The readout turned by 30 degrees, then mirrored: h = p mean.
            let (c, s) = (30f32.to_radians().cos(), 30f32.to_radians().sin());
            let p = [c, -s, -s, -c];
            let encoder = encoder.reorient_readout(&p);
            let turned: Vec<f32> = mean
                .chunks_exact(2)
                .flat_map(|m| [p[0] * m[0] + p[1] * m[1], p[2] * m[0] + p[3] * m[1]])
                .collect();
            let encoded = to_vec(encoder.encode(input));
            let mut host = encoder.host_encoder().expect("a host copy");
            assert_eq!(host.latent_dim(), 2);
            for (k, frame) in frames.iter().enumerate() {
                let mut h = [0.0; 2];
                host.encode(frame, &mut h);
                for j in 0..2 {
                    let want = turned[2 * k + j];
                    let (got_host, got) = (h[j], encoded[2 * k + j]);
                    assert!(
                        (got_host - f64::from(want)).abs() < 1e-4 && (got - want).abs() < 1e-5,
                        "{head:?}: host {got_host}, encode {got}, want {want}"
                    );
                }
            }
        }
    }

    #[test]
    fn same_seed_same_weights() {
        let device = cpu_device();
        let x = Tensor::<2>::from_data(TensorData::new(vec![0.5f32, -0.5], [1, 2]), &device);
        let render = |seed| {
            to_vec(
                tiny()
                    .init(seed, &device)
                    .unwrap()
                    .decoder
                    .forward(x.clone()),
            )
        };
        assert_eq!(render(3), render(3));
        assert_ne!(render(3), render(4));
        // The prior std keeps its configured initial value (reinit skips `log_std`).
        let model = tiny().init(3, &device).unwrap();
        let sigma = to_vec(model.transition.log_std.val().exp());
        assert!(sigma.iter().all(|s| (s - 0.1).abs() < 1e-6), "{sigma:?}");
    }

    /// A transition whose MLP outputs the constants `[a, log(-b), log c]` for every `x`: zero
    /// last-layer weights, the constants as its bias.
    fn constant_transition(
        a: [f32; 2],
        b: [f32; 2],
        c: [f32; 2],
        device: &Device,
    ) -> NvaeTransition {
        let mut transition = tiny().init(1, device).unwrap().transition;
        let weight = transition.fc3.weight.val();
        transition.fc3.weight = Param::from_tensor(weight.zeros_like());
        let bias = vec![a[0], a[1], (-b[0]).ln(), (-b[1]).ln(), c[0].ln(), c[1].ln()];
        transition.fc3.bias = Some(Param::from_tensor(Tensor::from_data(
            TensorData::new(bias, [6]),
            device,
        )));
        transition
    }

    #[test]
    fn transition_prior_follows_the_newtonian_update() {
        let device = cpu_device();
        let row =
            |v: [f32; 2]| Tensor::<2>::from_data(TensorData::new(v.to_vec(), [1, 2]), &device);
        let transition = constant_transition([-2.0, 0.5], [-1.0, -4.0], [3.0, 0.25], &device);
        let m = transition.matrices(row([0.0, 0.0]));
        assert_eq!(to_vec(m.a), vec![-2.0, 0.5]);
        let (b, c) = (to_vec(m.b), to_vec(m.c));
        assert!(
            (b[0] + 1.0).abs() < 1e-6 && (b[1] + 4.0).abs() < 1e-6,
            "{b:?}"
        );
        assert!(
            (c[0] - 3.0).abs() < 1e-6 && (c[1] - 0.25).abs() < 1e-6,
            "{c:?}"
        );
        // By hand, dt = 0.1, x = (1, -2), v = (0.5, 2), u = (1, -1):
        //   accel_0 = -2 (1) + -1 (0.5) + 3 (1) = 0.5;   v'_0 = 0.5 + 0.1 (0.5) = 0.55;
        //   x'_0 = 1 + 0.1 (0.55) = 1.055.
        //   accel_1 = 0.5 (-2) + -4 (2) + 0.25 (-1) = -9.25;   v'_1 = 2 - 0.925 = 1.075;
        //   x'_1 = -2 + 0.1075 = -1.8925.
        let x = row([1.0, -2.0]);
        let (x_next, v_next) =
            transition
                .matrices(x.clone())
                .step(x, row([0.5, 2.0]), row([1.0, -1.0]), 0.1);
        let (x_next, v_next) = (to_vec(x_next), to_vec(v_next));
        for (got, want) in [
            (v_next[0], 0.55),
            (v_next[1], 1.075),
            (x_next[0], 1.055),
            (x_next[1], -1.8925),
        ] {
            assert!((got as f64 - want).abs() < 1e-5, "got {got}, want {want}");
        }
    }
}
