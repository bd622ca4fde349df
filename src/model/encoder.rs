//! Encoder `e`: one 64x64 RGB frame -> configuration latent `h` in R^du.

use burn::module::{Module, Param};
use burn::nn::conv::{Conv2d, Conv2dConfig};
use burn::nn::{Linear, LinearConfig, PaddingConfig2d};
use burn::tensor::activation::{relu, softmax, tanh};
use burn::tensor::{Device, Tensor, TensorData};

use crate::error::{Error, Result};

/// How the conv features become `h`.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "kebab-case", tag = "kind")]
pub enum EncoderHead {
    /// The PC3-style head: one more stride-2 conv, flatten, an MLP with `hidden` units.
    Mlp { hidden: usize },
    /// Spatial soft-argmax (Levine et al. 2016, "deep spatial autoencoders"): `keypoints`
    /// feature maps, each reduced to its expected image coordinate, then one linear map
    /// (`hidden = 0`) or a one-hidden-layer tanh MLP (`hidden > 0`). With the linear map `h` is
    /// linear in the image positions the keypoints track, right for a point mass; joint angles
    /// (reacher) are not linear in any image position, so an arm needs the hidden layer.
    SoftArgmax {
        keypoints: usize,
        #[serde(default)]
        hidden: usize,
    },
}

/// Encoder architecture. Defaults sized for 2 CPU cores (spec.md 3).
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct EncoderConfig {
    /// Dimension of `h` (= action dimension du).
    pub latent_dim: usize,
    /// Channels of the two stride-2 trunk convs (64 -> 32 -> 16 pixels).
    pub trunk_channels: [usize; 2],
    /// The head.
    pub head: EncoderHead,
    /// Initial sharpness `beta` of the soft-argmax (`softmax(beta * maps)`), learned from there.
    /// With beta = 1 the fresh attention is nearly uniform, keypoints barely move with the
    /// scene, and CPC can lose the race against consistency's contraction (latent collapse).
    #[serde(default = "default_sharpness")]
    pub keypoint_sharpness: f64,
    /// Data-dependent initialisation of the latent's scale: before training, the head's output
    /// layer is rescaled so `h` has zero mean and this standard deviation per dimension over a
    /// batch of training frames (`None`: keep the fan-in initialisation). How large the fresh
    /// latent is against the transition std decides whether CPC can start; on the reacher
    /// the fan-in initialisation leaves `h` spread ~30x narrower than on the point mass.
    /// `Some(0.0)` also keeps the fan-in initialisation (a config file's way to undo a preset
    /// that sets it).
    #[serde(default)]
    pub init_latent_std: Option<f64>,
}

fn default_sharpness() -> f64 {
    1.0
}

impl EncoderConfig {
    /// Default encoder for `h` in R^du: soft-argmax head with 16 keypoints.
    pub fn new(latent_dim: usize) -> Self {
        Self {
            latent_dim,
            trunk_channels: [16, 32],
            head: EncoderHead::SoftArgmax {
                keypoints: 16,
                hidden: 0,
            },
            keypoint_sharpness: 1.0,
            init_latent_std: None,
        }
    }

    pub(crate) fn validate(&self) -> Result<()> {
        if self.latent_dim == 0 || self.trunk_channels.contains(&0) {
            return Err(Error::config(
                "model.encoder",
                "latent_dim and trunk_channels must be positive",
            ));
        }
        if let Some(std) = self.init_latent_std
            && !(std.is_finite() && std >= 0.0)
        {
            return Err(Error::config(
                "model.encoder.init_latent_std",
                format!("{std} is not a number >= 0"),
            ));
        }
        match self.head {
            EncoderHead::Mlp { hidden: 0 } | EncoderHead::SoftArgmax { keypoints: 0, .. } => {
                Err(Error::config("model.encoder.head", "size must be positive"))
            }
            _ => Ok(()),
        }
    }

    /// Builds the encoder (weights are redrawn by [`super::reinit_params`]).
    pub fn init(&self, device: &Device) -> Encoder {
        let [c1, c2] = self.trunk_channels;
        let conv = |cin, cout, k, stride, pad| {
            Conv2dConfig::new([cin, cout], [k, k])
                .with_stride([stride, stride])
                .with_padding(PaddingConfig2d::Explicit(pad, pad, pad, pad))
                .init(device)
        };
        let (mlp, keypoints) = match self.head {
            EncoderHead::Mlp { hidden } => (
                Some(MlpHead {
                    conv3: conv(c2, 32, 4, 2, 1),
                    fc1: LinearConfig::new(32 * 8 * 8, hidden).init(device),
                    fc2: LinearConfig::new(hidden, self.latent_dim).init(device),
                }),
                None,
            ),
            EncoderHead::SoftArgmax { keypoints, hidden } => {
                let (hidden_layer, out_inputs) = if hidden == 0 {
                    (None, 2 * keypoints)
                } else {
                    (
                        Some(LinearConfig::new(2 * keypoints, hidden).init(device)),
                        hidden,
                    )
                };
                (
                    None,
                    Some(KeypointHead {
                        log_sharpness: Param::from_tensor(Tensor::full(
                            [keypoints],
                            self.keypoint_sharpness.ln(),
                            device,
                        )),
                        features: conv(c2, keypoints, 1, 1, 0),
                        hidden: hidden_layer,
                        out: LinearConfig::new(out_inputs, self.latent_dim).init(device),
                    }),
                )
            }
        };
        Encoder {
            conv1: conv(3, c1, 4, 2, 1),
            conv2: conv(c1, c2, 3, 2, 1),
            mlp,
            keypoints,
            latent_transform: super::transform_param(self.latent_dim, device),
        }
    }
}

/// PC3-style flatten + MLP head.
#[derive(Module, Debug)]
pub struct MlpHead {
    conv3: Conv2d,
    fc1: Linear,
    fc2: Linear,
}

/// Spatial soft-argmax head.
#[derive(Module, Debug)]
pub struct KeypointHead {
    features: Conv2d,
    /// Log of the per-keypoint softmax sharpness, `[K]`.
    log_sharpness: Param<Tensor<1>>,
    /// Optional tanh layer between the keypoint coordinates and `out`.
    hidden: Option<Linear>,
    out: Linear,
}

/// The encoder `e`. Exactly one of the heads is present.
#[derive(Module, Debug)]
pub struct Encoder {
    conv1: Conv2d,
    conv2: Conv2d,
    mlp: Option<MlpHead>,
    keypoints: Option<KeypointHead>,
    /// Orientation `Q`, a signed permutation, not trained: `h = Q head(frame)` (see
    /// [`super::ProclModel::reorient_latent`]).
    pub latent_transform: Param<Tensor<2>>,
}

impl Encoder {
    /// Dimension of `h`.
    pub fn latent_dim(&self) -> usize {
        self.latent_transform.val().dims()[0]
    }

    /// `frames [n, 3, 64, 64]` (from [`super::frames_to_tensor`]) -> `h [n, du]`.
    pub fn forward(&self, frames: Tensor<4>) -> Tensor<2> {
        // Rows are samples: h = raw Q^T.
        self.forward_unoriented(frames)
            .matmul(self.latent_transform.val().transpose())
    }

    /// Rescales the head's output layer so the latent of `frames` has zero mean and standard
    /// deviation `target_std` in every dimension (data-dependent initialisation).
    pub fn normalise_latent_scale(mut self, frames: Tensor<4>, target_std: f64) -> Self {
        let raw = self.forward_unoriented(frames).detach(); // [n, du]
        let mean = raw.clone().mean_dim(0); // [1, du]
        let std = (raw - mean.clone())
            .powi_scalar(2)
            .mean_dim(0)
            .sqrt()
            .clamp_min(1e-12); // [1, du]
        let scale = std.recip() * target_std; // [1, du]
        let out = match (&mut self.mlp, &mut self.keypoints) {
            (Some(head), _) => &mut head.fc2,
            (None, Some(head)) => &mut head.out,
            (None, None) => return self,
        };
        // Weights are [in, out]: scaling column j scales h_j. New parameters must be graph
        // leaves, so they are rebuilt from their values.
        let weight = out.weight.val().detach() * scale.clone();
        let device = weight.device();
        out.weight = Param::from_tensor(super::trainable(Tensor::from_data(
            weight.into_data(),
            &device,
        )));
        if let Some(bias) = &out.bias {
            let du = scale.dims()[1];
            let bias = (bias.val().detach().reshape([1, du]) - mean) * scale;
            let device = bias.device();
            let values = Tensor::<1>::from_data(bias.reshape([du]).into_data(), &device);
            out.bias = Some(Param::from_tensor(super::trainable(values)));
        }
        self
    }

    /// The head's output before the orientation `Q`.
    fn forward_unoriented(&self, frames: Tensor<4>) -> Tensor<2> {
        let x = relu(self.conv1.forward(frames)); // [n, c1, 32, 32]
        let x = relu(self.conv2.forward(x)); // [n, c2, 16, 16]
        if let Some(head) = &self.mlp {
            let x = relu(head.conv3.forward(x)); // [n, 32, 8, 8]
            let n = x.dims()[0];
            let x = relu(head.fc1.forward(x.reshape([n, 32 * 8 * 8]))); // [n, hidden]
            return head.fc2.forward(x); // [n, du]
        }
        let head = self
            .keypoints
            .as_ref()
            .expect("encoder has one head by construction");
        let maps = head.features.forward(x); // [n, K, 16, 16]
        let [n, k, rows, cols] = maps.dims();
        let sharpness = head.log_sharpness.val().exp().reshape([1, k, 1]);
        let attention = softmax(maps.reshape([n, k, rows * cols]) * sharpness, 2); // [n, K, 256]
        let (grid_x, grid_y) = pixel_grid(rows, cols, &attention.device());
        let expected_x = (attention.clone() * grid_x).sum_dim(2); // [n, K, 1]
        let expected_y = (attention * grid_y).sum_dim(2); // [n, K, 1]
        let keypoints = Tensor::cat(vec![expected_x, expected_y], 1).reshape([n, 2 * k]); // [n, 2K]
        match &head.hidden {
            Some(hidden) => head.out.forward(tanh(hidden.forward(keypoints))), // [n, du]
            None => head.out.forward(keypoints),                               // [n, du]
        }
    }
}

/// Column and row coordinates of each cell, in [-1, 1], shaped `[1, 1, rows * cols]`.
fn pixel_grid(rows: usize, cols: usize, device: &Device) -> (Tensor<3>, Tensor<3>) {
    let coord = |i: usize, n: usize| (2.0 * i as f32 + 1.0) / n as f32 - 1.0;
    let xs: Vec<f32> = (0..rows * cols).map(|p| coord(p % cols, cols)).collect();
    let ys: Vec<f32> = (0..rows * cols).map(|p| coord(p / cols, rows)).collect();
    let make = |v| Tensor::from_data(TensorData::new(v, [1, 1, rows * cols]), device);
    (make(xs), make(ys))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::envs::{EnvKind, FRAME_BYTES};
    use crate::model::{cpu_device, frames_to_tensor, reinit_params, to_vec};

    /// 24 reacher frames at random configurations.
    fn frames(device: &Device) -> Tensor<4> {
        let mut env = EnvKind::Reacher.make();
        let mut rendered = vec![];
        for seed in 0..24 {
            env.reset(seed).unwrap();
            let mut frame = [0u8; FRAME_BYTES];
            env.render(&mut frame);
            rendered.push(frame);
        }
        frames_to_tensor(rendered.iter().map(|f| &f[..]), device)
    }

    #[test]
    fn latent_scale_initialisation_standardises_every_head() {
        let device = cpu_device();
        for head in [
            EncoderHead::SoftArgmax {
                keypoints: 4,
                hidden: 0,
            },
            EncoderHead::SoftArgmax {
                keypoints: 4,
                hidden: 8,
            },
            EncoderHead::Mlp { hidden: 8 },
        ] {
            let config = EncoderConfig {
                trunk_channels: [4, 4],
                head,
                keypoint_sharpness: 30.0,
                ..EncoderConfig::new(2)
            };
            let encoder = reinit_params(config.init(&device), 3);
            let encoder = encoder.normalise_latent_scale(frames(&device), 2.5);
            let h = to_vec(encoder.forward(frames(&device)));
            for dim in 0..2 {
                let column: Vec<f64> = h.iter().skip(dim).step_by(2).map(|&x| x as f64).collect();
                let mean = column.iter().sum::<f64>() / 24.0;
                let std = (column.iter().map(|x| (x - mean).powi(2)).sum::<f64>() / 24.0).sqrt();
                assert!(mean.abs() < 1e-4, "{head:?} dim {dim}: mean {mean}");
                assert!((std - 2.5).abs() < 1e-3, "{head:?} dim {dim}: std {std}");
            }
        }
    }

    #[test]
    fn bad_latent_scale_is_refused_by_name() {
        let config = EncoderConfig {
            init_latent_std: Some(-1.0),
            ..EncoderConfig::new(2)
        };
        let err = config.validate().unwrap_err().to_string();
        assert!(err.contains("init_latent_std"), "{err}");
    }
}
