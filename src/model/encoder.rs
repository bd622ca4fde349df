//! Encoder `e`: one 64x64 RGB frame -> configuration latent `h` in R^du.

use burn::module::{Module, Param};
use burn::nn::conv::{Conv2d, Conv2dConfig};
use burn::nn::{Linear, LinearConfig, PaddingConfig2d};
use burn::tensor::activation::{relu, softmax, tanh};
use burn::tensor::{Device, Int, Tensor, TensorData};

use super::POLAR_FADE_RADIUS;
use super::host_encoder::{HostConv, HostEncoder, HostHead, HostLinear};
use super::polar_reference::PolarReference;
use super::trunk::{Trunk, TrunkLayer, TrunkOutput, TrunkSoftArgmax, TrunkTape};
use crate::data::PixelSpread;
use crate::envs::{FRAME_BYTES, FRAME_PX};
use crate::error::{Error, Result};

/// How the conv features become `h`.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "kebab-case", tag = "kind", deny_unknown_fields)]
pub enum EncoderHead {
    /// The PC3-style head: one more stride-2 conv, flatten, an MLP with `hidden` units.
    Mlp { hidden: usize },
    /// Spatial soft-argmax (Levine et al. 2016, "deep spatial autoencoders"): `keypoints`
    /// feature maps, each reduced to its expected image coordinate, then one linear map
    /// (`hidden = 0`) or a one-hidden-layer tanh MLP (`hidden > 0`). With the linear map `h` is
    /// linear in the image positions the keypoints track, right for a point mass; joint angles
    /// (reacher) are not linear in any image position, so an arm needs the hidden layer.
    ///
    /// With `polar = true` each keypoint is the expected angle and distance of the cells it
    /// attends to about a centre, instead of their expected `(x, y)`: the coordinates of a
    /// revolute joint anchored there. The centre is the hub the training frames turn about
    /// (the image centre if they have none). An angle must be cut somewhere on the circle; the
    /// cut is placed, once, in the direction the training frames change least (for an arm with
    /// joint limits, the sector its links never sweep), see [`Encoder::place_polar_frame`].
    SoftArgmax {
        keypoints: usize,
        #[serde(default)]
        hidden: usize,
        #[serde(default)]
        polar: bool,
        /// With `polar = true`, also feed the angle between every pair of keypoints, seen from
        /// the centre (from their expected `(x, y)`). A keypoint's own angle jumps where it
        /// crosses the cut; the angle between two keypoints jumps only where it reaches
        /// 180 degrees. The reacher's links are equally long, so the angle between the wrist
        /// and the fingertip is exactly half the wrist angle at every shoulder angle, while
        /// the fingertip's own angle (shoulder + wrist / 2) sweeps more than a full turn.
        #[serde(default)]
        pairwise_angles: bool,
    },
}

/// Encoder architecture. Defaults sized for 2 CPU cores.
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(deny_unknown_fields)]
pub struct EncoderConfig {
    /// Dimension of `h` (= action dimension du).
    pub latent_dim: usize,
    /// Channels of the two trunk convs (64 -> 32 -> 16 pixels at the default strides).
    pub trunk_channels: [usize; 2],
    /// Stride of the trunk's second conv: 2 (16x16 keypoint cells of 4 pixels) or, with a
    /// soft-argmax head, 1 (32x32 cells of 2 pixels, four times the second conv's work). At the
    /// reacher's folded wrist the fingertip lies 4-12 pixels from the centre, one to three
    /// coarse cells.
    #[serde(default = "default_trunk_second_stride")]
    pub trunk_second_stride: usize,
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
    /// Polar heads with `pairwise_angles`: the fan-in initial weights from the pairwise angles
    /// into the head's first layer are multiplied by this (1: as drawn; 0: the angles start
    /// with no influence and enter only as training finds them useful). Pairwise angles of
    /// keypoints that sit off the arm wrap inside the joint ranges, and the fresh head's random
    /// mix of them already curls the shoulder round an arc at step 1, a shape training keeps.
    #[serde(default = "default_pairwise_init_scale")]
    pub pairwise_init_scale: f64,
    /// Polar heads: the distance `R` from the centre (image units; the frame's half-width is 1)
    /// at which a cell's angle enters its keypoint's angle at half weight, each cell's angle
    /// multiplied by `1 / (1 + (r / R)^2)`. An arm's inner link sweeps only its joint's range,
    /// so its cells never reach the cut; the outer link and the tip can sweep past it, and
    /// their cells' angles jump there. `None` or 0: every cell's angle at full weight.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub polar_angle_falloff: Option<f64>,
    /// Polar heads: each frame's cut moves to the side opposite the direction in which the
    /// frame differs most from the still background, so no part of the arm crosses it (see
    /// `polar_reference.rs`). Off: one cut for every frame, where the frames change least.
    #[serde(default, skip_serializing_if = "std::ops::Not::not")]
    pub polar_moving_cut: bool,
}

fn default_pairwise_init_scale() -> f64 {
    1.0
}

fn default_sharpness() -> f64 {
    1.0
}

fn default_trunk_second_stride() -> usize {
    2
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
                polar: false,
                pairwise_angles: false,
            },
            keypoint_sharpness: 1.0,
            init_latent_std: None,
            trunk_second_stride: default_trunk_second_stride(),
            pairwise_init_scale: default_pairwise_init_scale(),
            polar_angle_falloff: None,
            polar_moving_cut: false,
        }
    }

    /// Width `F` of the keypoint head's features (the K angles and K radii, or x and y, then
    /// the Cartesian extras and the pairwise angles when on); `None` for the MLP head.
    pub fn keypoint_feature_count(&self) -> Option<usize> {
        let EncoderHead::SoftArgmax {
            keypoints,
            polar,
            pairwise_angles,
            ..
        } = self.head
        else {
            return None;
        };
        let pairs = if polar && pairwise_angles {
            keypoints * (keypoints - 1) / 2
        } else {
            0
        };
        Some(2 * keypoints + pairs)
    }

    pub(crate) fn validate(&self) -> Result<()> {
        if !(self.pairwise_init_scale.is_finite() && self.pairwise_init_scale >= 0.0) {
            return Err(Error::config(
                "model.encoder.pairwise_init_scale",
                format!("{} must be finite and >= 0", self.pairwise_init_scale),
            ));
        }
        match (self.trunk_second_stride, self.head) {
            (2, _) | (1, EncoderHead::SoftArgmax { .. }) => {}
            (1, EncoderHead::Mlp { .. }) => {
                return Err(Error::config(
                    "model.encoder.trunk_second_stride",
                    "1 needs the soft-argmax head (the MLP head's layers expect 16x16 maps)",
                ));
            }
            (stride, _) => {
                return Err(Error::config(
                    "model.encoder.trunk_second_stride",
                    format!("{stride} must be 1 or 2"),
                ));
            }
        }
        if self.latent_dim == 0 || self.trunk_channels.contains(&0) {
            return Err(Error::config(
                "model.encoder",
                "latent_dim and trunk_channels must be positive",
            ));
        }
        if let Some(radius) = self.polar_angle_falloff
            && !(radius.is_finite() && radius >= 0.0)
        {
            return Err(Error::config(
                "model.encoder.polar_angle_falloff",
                format!("{radius} is not a distance >= 0 (0: off)"),
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
            EncoderHead::SoftArgmax {
                polar: false,
                pairwise_angles: true,
                ..
            } => Err(Error::config(
                "model.encoder.head.pairwise_angles",
                "adds the angles between polar keypoints; it needs polar = true",
            )),
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
            EncoderHead::SoftArgmax {
                keypoints,
                hidden,
                polar,
                pairwise_angles,
            } => {
                let pairwise_angles = polar && pairwise_angles;
                let features = self.keypoint_feature_count().unwrap_or(0);
                let (hidden_layer, out_inputs) = if hidden == 0 {
                    (None, features)
                } else {
                    (
                        Some(LinearConfig::new(features, hidden).init(device)),
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
                        pairwise_angles,
                        angle_falloff: self.polar_angle_falloff.unwrap_or(0.0),
                        hidden: hidden_layer,
                        out: LinearConfig::new(out_inputs, self.latent_dim).init(device),
                        // About the image centre, cut opposite +x, until
                        // [`Encoder::place_polar_frame`] sees the data.
                        polar_centre: polar.then(|| fixed_vector([0.0, 0.0], device)),
                        polar_axis: polar.then(|| fixed_vector([1.0, 0.0], device)),
                        // Placed by [`Encoder::place_moving_cut`] from the data.
                        polar_background: (polar && self.polar_moving_cut)
                            .then(|| fixed_values(vec![0.0; FRAME_BYTES], device)),
                        polar_reference_axis: (polar && self.polar_moving_cut)
                            .then(|| fixed_vector([1.0, 0.0], device)),
                    }),
                )
            }
        };
        Encoder {
            conv1: conv(3, c1, 4, 2, 1),
            conv2: conv(c1, c2, 3, self.trunk_second_stride, 1),
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
    /// Polar keypoints followed by the angle between each pair of them: `K (K - 1) / 2` more.
    pairwise_angles: bool,
    /// [`EncoderConfig::polar_angle_falloff`], 0 when off.
    angle_falloff: f64,
    /// Log of the per-keypoint softmax sharpness, `[K]`.
    log_sharpness: Param<Tensor<1>>,
    /// Optional tanh layer between the keypoint coordinates and `out`.
    hidden: Option<Linear>,
    out: Linear,
    /// Polar coordinates only: the point `(x, y)` (image coordinates) angles and distances
    /// are measured about. Not trained (excluded from init and the optimiser).
    polar_centre: Option<Param<Tensor<1>>>,
    /// Polar coordinates only: the unit direction `(cos m, sin m)` at which angles are 0; they
    /// are cut at `m + pi`. Not trained (excluded from init and the optimiser).
    polar_axis: Option<Param<Tensor<1>>>,
    /// With [`EncoderConfig::polar_moving_cut`]: the still background (`FRAME_BYTES` network
    /// inputs) and the axis `(cos m, sin m)` of the frames' own directions. Not trained.
    polar_background: Option<Param<Tensor<1>>>,
    polar_reference_axis: Option<Param<Tensor<1>>>,
}

/// Name of the polar head's non-trained axis parameter.
pub(crate) const POLAR_AXIS: &str = "polar_axis";
/// Name of the polar head's non-trained centre parameter. Checkpoints without it (the shipped
/// reacher run) load with the image centre `(0, 0)`, the centre they were trained with.
pub(crate) const POLAR_CENTRE: &str = "polar_centre";

/// Name of the moving cut's non-trained background parameter.
pub(crate) const POLAR_BACKGROUND: &str = "polar_background";
/// Name of the moving cut's non-trained axis parameter.
pub(crate) const POLAR_REFERENCE_AXIS: &str = "polar_reference_axis";

/// A parameter that training leaves alone.
fn fixed_vector(values: [f32; 2], device: &Device) -> Param<Tensor<1>> {
    fixed_values(values.to_vec(), device)
}

fn fixed_values(values: Vec<f32>, device: &Device) -> Param<Tensor<1>> {
    let n = values.len();
    Param::from_tensor(Tensor::from_data(TensorData::new(values, [n]), device))
        .set_require_grad(false)
}

/// The encoder `e`. Exactly one of the heads is present.
#[derive(Module, Debug)]
pub struct Encoder {
    conv1: Conv2d,
    conv2: Conv2d,
    mlp: Option<MlpHead>,
    keypoints: Option<KeypointHead>,
    /// Orientation `Q`, an orthogonal map (a signed permutation under the risk search), not
    /// trained: `h = Q head(frame)` (see [`super::ProclModel::reorient_latent`]).
    pub latent_transform: Param<Tensor<2>>,
}

impl Encoder {
    /// Dimension of `h`.
    pub fn latent_dim(&self) -> usize {
        self.latent_transform.val().dims()[0]
    }

    /// `frames [n, 3, 64, 64]` (from [`super::frames_to_tensor`]) -> `h [n, du]`.
    pub fn forward(&self, frames: Tensor<4>) -> Tensor<2> {
        self.orient(self.forward_unoriented(frames))
    }

    /// The head's output `raw [n, du]` turned by the orientation `Q`: rows are samples, so
    /// `h = raw Q^T`.
    fn orient(&self, raw: Tensor<2>) -> Tensor<2> {
        raw.matmul(self.latent_transform.val().transpose())
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
        match (&mut self.mlp, &mut self.keypoints) {
            (Some(head), _) => standardise_columns(&mut head.fc2, mean, scale),
            (None, Some(head)) => standardise_columns(&mut head.out, mean, scale),
            (None, None) => {}
        }
        self
    }

    /// Multiplies the weights from the pairwise-angle inputs into the keypoint head's first
    /// layer by `scale` (no-op without pairwise angles); see
    /// [`EncoderConfig::pairwise_init_scale`].
    pub fn scale_pairwise_inputs(mut self, scale: f64) -> Self {
        let Some(head) = self.keypoints.as_mut() else {
            return self;
        };
        if !head.pairwise_angles {
            return self;
        }
        let keypoints = head.log_sharpness.val().dims()[0];
        // Each keypoint's angle and radius come first.
        let per_keypoint = 2;
        let first = head.hidden.as_mut().unwrap_or(&mut head.out);
        // Weights are [in, out]: the pairwise angles are the inputs after the per-keypoint ones.
        let weight = first.weight.val().detach();
        let [inputs, _] = weight.dims();
        let device = weight.device();
        let row_scale: Vec<f32> = (0..inputs)
            .map(|i| {
                if i < per_keypoint * keypoints {
                    1.0
                } else {
                    scale as f32
                }
            })
            .collect();
        let row_scale = Tensor::<2>::from_data(TensorData::new(row_scale, [inputs, 1]), &device);
        let scaled = (weight * row_scale).into_data();
        first.weight = Param::from_tensor(super::trainable(Tensor::from_data(scaled, &device)));
        self
    }

    /// Places the polar head's centre on the hub the training frames turn about (the image
    /// centre if they have none) and its angle cut in the direction about it where the frames
    /// change least, so no reachable configuration sits on it (no-op for the other heads).
    /// Data-dependent initialisation, run once before training on the spread of every frame of
    /// the dataset (a 256-frame sample put the reacher's cut inside the shoulder's range for 2
    /// of 6 seeds); centre and axis are stored with the weights. `spread` is called only for a
    /// polar head: a pass over every frame that the other heads do not need.
    pub fn place_polar_frame(self, spread: impl FnOnce() -> PixelSpread) -> Self {
        if self.polar_axis().is_none() {
            return self;
        }
        let spread = spread();
        let centre = spread.hub().map_or([0.0, 0.0], |hub| hub.centre);
        let cut = spread.quietest_direction(centre);
        self.set_polar_frame(centre, cut)
    }

    /// Sets the polar head's centre and the direction of its cut (image coordinates; no-op for
    /// the other heads).
    pub(crate) fn set_polar_frame(mut self, centre: [f64; 2], [cut_x, cut_y]: [f64; 2]) -> Self {
        let Some(head) = self.keypoints.as_mut() else {
            return self;
        };
        let (Some(centre_param), Some(axis)) =
            (head.polar_centre.as_mut(), head.polar_axis.as_mut())
        else {
            return self;
        };
        let device = axis.val().device();
        *centre_param = fixed_vector(centre.map(|c| c as f32), &device);
        *axis = fixed_vector([-cut_x as f32, -cut_y as f32], &device);
        self
    }

    /// With [`EncoderConfig::polar_moving_cut`]: the still background of `frames` and the axis
    /// of their directions about the polar centre, so each frame's cut falls opposite its arm
    /// and the directions' own cut where none of the frames points (no-op otherwise). Run once
    /// before training, after [`Self::place_polar_frame`]; `frames` is called twice.
    pub fn place_moving_cut<'a, I: Iterator<Item = &'a [u8]>>(
        mut self,
        frames: impl Fn() -> I,
    ) -> Self {
        let Some(centre) = self.polar_centre() else {
            return self;
        };
        let Some(head) = self.keypoints.as_mut() else {
            return self;
        };
        let (Some(background_param), Some(axis_param)) = (
            head.polar_background.as_mut(),
            head.polar_reference_axis.as_mut(),
        ) else {
            return self;
        };
        let device = axis_param.val().device();
        let background = PolarReference::background_of(frames());
        let reference = PolarReference::new(centre, background.clone(), [1.0, 0.0], 1, 0.0);
        let mut input = vec![0.0; FRAME_BYTES];
        let directions = frames().map(|frame| {
            super::pixel_inputs(frame, &mut input);
            reference.direction(&input)
        });
        let axis = PolarReference::axis_for(directions);
        *background_param = fixed_values(background, &device);
        *axis_param = fixed_vector(axis, &device);
        self
    }

    /// The polar head's centre `(x, y)` in image coordinates (`[-1, 1]`, `(0, 0)` the image
    /// centre): angles and distances are measured about it.
    pub fn polar_centre(&self) -> Option<[f32; 2]> {
        let centre = self.keypoints.as_ref()?.polar_centre.as_ref()?;
        let v = crate::model::to_vec(centre.val());
        Some([v[0], v[1]])
    }

    /// The polar head's axis `(cos m, sin m)`: angles are measured from it and cut opposite.
    pub fn polar_axis(&self) -> Option<[f32; 2]> {
        let axis = self.keypoints.as_ref()?.polar_axis.as_ref()?;
        let v = crate::model::to_vec(axis.val());
        Some([v[0], v[1]])
    }

    /// The head's output before the orientation `Q`.
    fn forward_unoriented(&self, frames: Tensor<4>) -> Tensor<2> {
        let reference = self
            .keypoints
            .as_ref()
            .and_then(|head| head.polar_reference(self.keypoint_side()));
        let angle_grids = reference.map(|reference| reference_grids(&reference, &frames));
        let x = relu(self.conv1.forward(frames)); // [n, c1, 32, 32]
        let x = relu(self.conv2.forward(x)); // [n, c2, 16, 16], or 32x32 at stride 1
        let x = match &self.keypoints {
            Some(head) => head.features.forward(x), // [n, K, 16, 16] (32x32 at stride 1)
            None => x,
        };
        self.head_from_trunk(x, angle_grids)
    }

    /// Side of the keypoint maps: 64 pixels through conv1 and conv2.
    fn keypoint_side(&self) -> usize {
        host_conv(&self.conv2).out_side(host_conv(&self.conv1).out_side(FRAME_PX))
    }

    /// The trunk run on the host in training: conv1 and conv2 (each with its ReLU) and, with
    /// the keypoint head, its feature maps and their spatial soft-argmax.
    fn trunk(&self) -> Trunk<'_> {
        let mut layers = vec![
            TrunkLayer {
                conv: &self.conv1,
                relu: true,
            },
            TrunkLayer {
                conv: &self.conv2,
                relu: true,
            },
        ];
        let Some(head) = &self.keypoints else {
            return Trunk {
                layers,
                soft_argmax: None,
            };
        };
        layers.push(TrunkLayer {
            conv: &head.features,
            relu: false,
        });
        let side = layers
            .iter()
            .fold(FRAME_PX, |side, layer| host_conv(layer.conv).out_side(side));
        let device = head.log_sharpness.val().device();
        let grids = head
            .expectation_grids(side, side, &device)
            .into_iter()
            .map(super::to_vec)
            .collect();
        Trunk {
            layers,
            soft_argmax: Some(TrunkSoftArgmax {
                log_sharpness: head.log_sharpness.val(),
                grids,
                reference: head.polar_reference(side),
            }),
        }
    }

    /// `h` of `frames` (RGB u8, 64x64) for a training step. On the CPU with autodiff the
    /// trunk runs on the host (see [`TrunkTape`]): call [`TrunkTape::backward`] on the returned
    /// tape after the loss's `backward` to complete the gradients. Elsewhere the whole encoder
    /// runs in burn and there is no tape.
    pub fn forward_training(
        &self,
        frames: &[&[u8]],
        device: &Device,
    ) -> (Tensor<2>, Option<TrunkTape>) {
        if !super::trains_on_host(device) {
            let input = super::frames_to_tensor(frames.iter().copied(), device);
            return (self.forward(input), None);
        }
        let tape = TrunkTape::forward(self.trunk(), frames, device);
        let raw = match tape.output() {
            TrunkOutput::Maps(x) => self.head_from_trunk(x, None),
            // A trunk ends in the soft-argmax exactly when the head has keypoints.
            TrunkOutput::Expectations(e) => self
                .keypoints
                .as_ref()
                .expect("a soft-argmax trunk belongs to a keypoint head")
                .latent_from_expectations(e),
        };
        (self.orient(raw), Some(tape))
    }

    /// The head's output before `Q`, from the trunk's output: conv2's (MLP head) or the
    /// keypoint feature maps; `angle_grids` (`[n, 1, cells]`) replace the fixed angle grid
    /// with each frame's own under a moving cut.
    fn head_from_trunk(&self, x: Tensor<4>, angle_grids: Option<Tensor<3>>) -> Tensor<2> {
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
        let [n, k, rows, cols] = x.dims();
        let sharpness = head.log_sharpness.val().exp().reshape([1, k, 1]);
        let logits = x.reshape([n, k, rows * cols]) * sharpness; // [n, K, cells]
        let attention = softmax(logits, 2); // [n, K, cells]
        let mut grids = head.expectation_grids(rows, cols, &attention.device());
        if let Some(angle_grids) = angle_grids {
            grids[0] = angle_grids;
        }
        let expectations = grids
            .into_iter()
            .map(|grid| (attention.clone() * grid).sum_dim(2)) // [n, K, 1]
            .collect();
        head.latent_from_expectations(Tensor::cat(expectations, 2))
    }
}

impl Encoder {
    /// A host copy of this encoder's weights for control (see [`HostEncoder`]).
    pub fn host_encoder(&self) -> HostEncoder {
        let device = self.latent_transform.val().device();
        let (conv1, conv2) = (host_conv(&self.conv1), host_conv(&self.conv2));
        let head = match (&self.mlp, &self.keypoints) {
            (Some(mlp), _) => HostHead::Mlp {
                conv3: host_conv(&mlp.conv3),
                fc1: host_linear(&mlp.fc1),
                fc2: host_linear(&mlp.fc2),
            },
            (None, Some(head)) => {
                let features = host_conv(&head.features);
                // The trunk's output side: 64 pixels through conv1 and conv2.
                let side = conv2.out_side(conv1.out_side(FRAME_PX));
                let grids = head.expectation_grids(side, side, &device);
                HostHead::Keypoints {
                    features,
                    sharpness: super::to_vec(head.log_sharpness.val().exp()),
                    grids: grids.into_iter().map(super::to_vec).collect(),
                    reference: head.polar_reference(side),
                    pairwise: head.pairwise_angles,
                    hidden: head.hidden.as_ref().map(host_linear),
                    out: host_linear(&head.out),
                }
            }
            (None, None) => unreachable!("an encoder has one head by construction"),
        };
        HostEncoder::new(
            conv1,
            conv2,
            head,
            super::to_vec(self.latent_transform.val()),
        )
    }
}

fn host_conv(conv: &Conv2d) -> HostConv {
    HostConv::from_conv(conv)
}

fn host_linear(layer: &Linear) -> HostLinear {
    let [_, outputs] = layer.weight.dims();
    HostLinear {
        weight: super::to_vec(layer.weight.val()),
        bias: layer
            .bias
            .as_ref()
            .map_or_else(|| vec![0.0; outputs], |b| super::to_vec(b.val())),
        outputs,
    }
}

impl KeypointHead {
    /// The moving cut's reference for maps of `side x side` cells, when the head has one.
    pub(crate) fn polar_reference(&self, side: usize) -> Option<PolarReference> {
        let background = super::to_vec(self.polar_background.as_ref()?.val());
        let axis = super::to_vec(self.polar_reference_axis.as_ref()?.val());
        let centre = super::to_vec(self.polar_centre.as_ref()?.val());
        Some(PolarReference::new(
            [centre[0], centre[1]],
            background,
            [axis[0], axis[1]],
            side,
            self.angle_falloff,
        ))
    }

    /// The per-cell values whose expectations under a keypoint's attention are its features
    /// (the polar angle and radius about the polar centre, or the cell's `(x, y)`), and the
    /// cells' `(x, y)` (about the polar centre for a polar head): `[1, 1, rows * cols]` each.
    fn coordinate_grids(
        &self,
        rows: usize,
        cols: usize,
        device: &Device,
    ) -> ([Tensor<3>; 2], [Tensor<3>; 2]) {
        let (grid_x, grid_y) = pixel_grid(rows, cols, device);
        let (grid_x, grid_y) = match &self.polar_centre {
            Some(centre) => {
                let centre = centre.val();
                let x = centre.clone().slice(0..1).reshape([1, 1, 1]);
                let y = centre.slice(1..2).reshape([1, 1, 1]);
                (grid_x - x, grid_y - y)
            }
            None => (grid_x, grid_y),
        };
        let features = match &self.polar_axis {
            Some(axis) => {
                let axis = axis.val();
                let cos_m = axis.clone().slice(0..1).reshape([1, 1, 1]);
                let sin_m = axis.slice(1..2).reshape([1, 1, 1]);
                let (x, y) = (grid_x.clone(), grid_y.clone());
                let (angle, radius) = polar_grid(x, y, cos_m, sin_m);
                let angle = if self.angle_falloff > 0.0 {
                    let scaled = radius.clone() / self.angle_falloff;
                    angle / (scaled.powi_scalar(2) + 1.0)
                } else {
                    angle
                };
                [angle, radius]
            }
            None => [grid_x.clone(), grid_y.clone()],
        };
        (features, [grid_x, grid_y])
    }

    /// The grids `[1, 1, rows * cols]` whose expectations under each keypoint's attention
    /// the head reads: the two coordinates of [`Self::coordinate_grids`], then, with pairwise
    /// angles, the cells' `(x, y)`.
    fn expectation_grids(&self, rows: usize, cols: usize, device: &Device) -> Vec<Tensor<3>> {
        let ([first, second], [grid_x, grid_y]) = self.coordinate_grids(rows, cols, device);
        let mut grids = vec![first, second];
        if self.pairwise_angles {
            grids.extend([grid_x, grid_y]);
        }
        grids
    }

    /// The expectations `[n, K, G]` of [`Self::expectation_grids`] -> `h`.
    fn latent_from_expectations(&self, expectations: Tensor<3>) -> Tensor<2> {
        let [n, k, _] = expectations.dims();
        let grid = |g: usize| expectations.clone().narrow(2, g, 1); // [n, K, 1]
        // Each keypoint is the attention's expected cell coordinate: Cartesian, or the polar
        // angle and radius of the cells about the polar centre; all first coordinates, then
        // all second ones.
        let keypoints = Tensor::cat(vec![grid(0), grid(1)], 1).reshape([n, 2 * k]);
        let features = if self.pairwise_angles {
            // The angles between polar keypoints come from their expected (x, y).
            // [n, 2K + K (K - 1) / 2]
            Tensor::cat(vec![keypoints, pairwise_angles(grid(2), grid(3))], 1)
        } else {
            keypoints
        };
        self.latent_from_features(features)
    }

    /// The keypoint features `[n, F]` (the K angles, the K radii, then any extras) -> `h`.
    fn latent_from_features(&self, features: Tensor<2>) -> Tensor<2> {
        match &self.hidden {
            Some(hidden) => self.out.forward(tanh(hidden.forward(features))), // [n, du]
            None => self.out.forward(features),
        }
    }
}

/// Each frame's angle grid under `reference`: frames `[n, 3, 64, 64]` -> `[n, 1, cells]`.
fn reference_grids(reference: &PolarReference, frames: &Tensor<4>) -> Tensor<3> {
    let n = frames.dims()[0];
    let planar = super::to_vec(frames.clone());
    let plane = FRAME_PX * FRAME_PX;
    let cells = reference.cells();
    let mut input = vec![0.0; FRAME_BYTES];
    let mut grids = vec![0.0; n * cells];
    for (frame, grid) in planar
        .chunks_exact(FRAME_BYTES)
        .zip(grids.chunks_exact_mut(cells))
    {
        for (p, rgb) in input.chunks_exact_mut(3).enumerate() {
            for (c, v) in rgb.iter_mut().enumerate() {
                *v = frame[c * plane + p];
            }
        }
        reference.angle_grid(reference.direction(&input), grid);
    }
    Tensor::from_data(TensorData::new(grids, [n, 1, cells]), &frames.device())
}

/// Rewrites `layer` so each output `y_j` becomes `(y_j - mean_j) scale_j` (`mean`, `scale`:
/// `[1, out]`; data-dependent initialisation). Weights are `[in, out]`:
/// scaling column j scales output j. New parameters must be graph leaves, so they are rebuilt
/// from their values.
fn standardise_columns(layer: &mut Linear, mean: Tensor<2>, scale: Tensor<2>) {
    let weight = layer.weight.val().detach() * scale.clone();
    let device = weight.device();
    layer.weight = Param::from_tensor(super::trainable(Tensor::from_data(
        weight.into_data(),
        &device,
    )));
    if let Some(bias) = &layer.bias {
        let out = scale.dims()[1];
        let bias = (bias.val().detach().reshape([1, out]) - mean) * scale;
        let values = Tensor::<1>::from_data(bias.reshape([out]).into_data(), &device);
        layer.bias = Some(Param::from_tensor(super::trainable(values)));
    }
}

/// Cell coordinates `(x, y)` (`[1, 1, cells]` each, about the polar centre) -> each cell's
/// angle from the axis `(cos m, sin m)` and its distance from the centre. The axis is
/// `[1, 1, 1]`, or `[n, 1, 1]` for one axis per sample (the angle is then `[n, 1, cells]`).
/// Angles are in `(-pi, pi]`, faded to 0 within [`POLAR_FADE_RADIUS`] of the centre, where the
/// angle is undefined. The expected angle under a keypoint's attention then grows with the
/// angle of what it attends to, with no jump unless that crosses the cut opposite `axis`.
fn polar_grid(
    x: Tensor<3>,
    y: Tensor<3>,
    cos_m: Tensor<3>,
    sin_m: Tensor<3>,
) -> (Tensor<3>, Tensor<3>) {
    // Rotate by -m so the axis lies along +x and the cut along -x, where atan2 jumps.
    let along = x.clone() * cos_m.clone() + y.clone() * sin_m.clone();
    let across = y * cos_m - x * sin_m;
    let r_squared = along.clone().powi_scalar(2) + across.clone().powi_scalar(2);
    let fade = r_squared.clone() / (r_squared.clone() + POLAR_FADE_RADIUS * POLAR_FADE_RADIUS);
    (across.atan2(along) * fade, r_squared.sqrt())
}

/// Expected keypoint positions `x, y` (`[n, K, 1]` each, about the polar centre) -> the angle
/// from keypoint `i` to keypoint `j` about the centre for every pair `i < j` (`[n, K (K - 1) / 2]`,
/// in `(-pi, pi]`), faded to 0 as either keypoint nears the centre (see [`polar_grid`]).
fn pairwise_angles(x: Tensor<3>, y: Tensor<3>) -> Tensor<2> {
    let [n, k, _] = x.dims();
    let (x_j, y_j) = (x.clone().reshape([n, 1, k]), y.clone().reshape([n, 1, k]));
    let cross = x.clone() * y_j.clone() - y.clone() * x_j.clone(); // [n, K, K]
    let dot = x.clone() * x_j.clone() + y.clone() * y_j.clone();
    let r_squared = x.powi_scalar(2) + y.powi_scalar(2); // [n, K, 1]
    let fade = r_squared.clone() / (r_squared + POLAR_FADE_RADIUS * POLAR_FADE_RADIUS);
    let fade_pair = fade.clone() * fade.reshape([n, 1, k]);
    // atan2's gradient is 0/0 at the origin; the offset keeps it finite there, where the fade
    // is 0 anyway.
    let angle = cross.atan2(dot + 1e-12) * fade_pair; // [n, K, K]
    let upper: Vec<i64> = (0..k)
        .flat_map(|i| (i + 1..k).map(move |j| (i * k + j) as i64))
        .collect();
    let pairs = upper.len();
    let index = Tensor::<1, Int>::from_data(TensorData::new(upper, [pairs]), &angle.device());
    angle.reshape([n, k * k]).select(1, index)
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

    /// Halves the pair inputs' rows (`scale_pairwise_inputs(0.5)`) of the tanh layer with
    /// `outputs` units and checks that exactly the rows after the first `unscaled` inputs
    /// changed, by half; returns the drawn weights.
    fn assert_only_pair_rows_scaled(
        encoder: &Encoder,
        unscaled: usize,
        outputs: usize,
    ) -> Vec<f32> {
        let weights = |encoder: &Encoder| {
            let head = encoder.keypoints.as_ref().expect("keypoint head");
            to_vec(head.hidden.as_ref().expect("tanh layer").weight.val())
        };
        let drawn = weights(encoder);
        let scaled = weights(&encoder.clone().scale_pairwise_inputs(0.5));
        for (i, (d, s)) in drawn.iter().zip(&scaled).enumerate() {
            let (input, output) = (i / outputs, i % outputs);
            let want = if input < unscaled { *d } else { 0.5 * d };
            assert_eq!(*s, want, "weight {i} (input {input}, output {output})");
        }
        drawn
    }

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
        let heads = [
            EncoderHead::SoftArgmax {
                keypoints: 4,
                hidden: 0,
                polar: false,
                pairwise_angles: false,
            },
            EncoderHead::SoftArgmax {
                keypoints: 4,
                hidden: 8,
                polar: true,
                pairwise_angles: false,
            },
            EncoderHead::SoftArgmax {
                keypoints: 4,
                hidden: 0,
                polar: true,
                pairwise_angles: false,
            },
            EncoderHead::Mlp { hidden: 8 },
            EncoderHead::SoftArgmax {
                keypoints: 4,
                hidden: 8,
                polar: true,
                pairwise_angles: true,
            },
        ];
        for head in heads {
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
                // Standardising subtracts a mean much larger than the spread in f32, so the
                // rescaled output keeps a rounding that depends on the CPU's SIMD kernels (1.3e-4
                // for the polar tanh head on an AMD EPYC, under 1e-4 on earlier CI machines):
                // 1e-3 is 0.04% of the std, far below the O(1) mean of an unstandardised head.
                assert!(mean.abs() < 1e-3, "{head:?} dim {dim}: mean {mean}");
                assert!((std - 2.5).abs() < 1e-3, "{head:?} dim {dim}: std {std}");
            }
        }
    }

    /// The polar head's centre must fall on the reacher's shoulder, at the image centre or
    /// moved off it, and its cut in the sector the shoulder cannot reach (q0 beyond +-160
    /// degrees, to the image's left), so the angle of the upper arm about the centre is
    /// continuous and monotone over the whole joint range.
    #[test]
    fn polar_frame_sits_on_the_reachers_shoulder_and_cuts_its_unreachable_sector() {
        let device = cpu_device();
        let config = EncoderConfig {
            trunk_channels: [4, 4],
            head: EncoderHead::SoftArgmax {
                keypoints: 4,
                hidden: 0,
                polar: true,
                pairwise_angles: false,
            },
            ..EncoderConfig::new(2)
        };
        for base_m in [[0.0, 0.0], [0.035, -0.025]] {
            let reacher_config = crate::envs::ReacherConfig {
                base_m,
                ..Default::default()
            };
            let encoder = config.init(&device);
            assert_eq!(encoder.polar_centre(), Some([0.0, 0.0]));
            assert_eq!(encoder.polar_axis(), Some([1.0, 0.0]));
            // Random-torque episodes, as `procl collect` records them.
            let data = crate::data::collect(
                &crate::data::CollectConfig {
                    env: crate::envs::EnvConfig::Reacher(reacher_config.clone()),
                    transitions: 3000,
                    ..crate::data::CollectConfig::new(EnvKind::Reacher, 0)
                },
                |_| {},
            )
            .unwrap();
            let spread = PixelSpread::of_frames(data.every_frame());
            let encoder = encoder.place_polar_frame(|| spread);
            let camera = reacher_config.camera;
            let to_image = |[x_m, y_m]: [f64; 2]| {
                let (col, row) = camera.project(x_m, y_m);
                [col as f32 / 32.0 - 1.0, row as f32 / 32.0 - 1.0]
            };
            let [cx, cy] = encoder.polar_centre().unwrap();
            let [bx, by] = to_image(base_m);
            // Within one pixel (1/32 of the half-width) of the shoulder.
            assert!(
                (cx - bx).abs() <= 1.0 / 32.0 && (cy - by).abs() <= 1.0 / 32.0,
                "centre ({cx}, {cy}), shoulder ({bx}, {by})"
            );
            let [ax, ay] = encoder.polar_axis().unwrap();
            // The unreachable sector is centred on world -x: image column < the shoulder's.
            let off_axis_deg = ay.atan2(ax).to_degrees();
            assert!(
                off_axis_deg.abs() < 20.0,
                "axis {off_axis_deg} deg from image +x"
            );
            // The wrist (0.12 m from the shoulder) over the shoulder's range, about the centre.
            let reacher = crate::envs::Reacher::new(reacher_config.clone());
            let angles: Vec<f32> = (0..=64)
                .map(|i| (-160.0 + 5.0 * i as f64).to_radians())
                .map(|q0| {
                    let (wrist, _) = reacher.forward_kinematics([q0, 0.0]);
                    let [x, y] = to_image([base_m[0] + wrist[0], base_m[1] + wrist[1]]);
                    let (x, y) = (x - cx, y - cy);
                    (y * ax - x * ay).atan2(x * ax + y * ay)
                })
                .collect();
            assert!(
                angles.windows(2).all(|w| w[1] < w[0]),
                "wrist angle not monotone in q0: {angles:?}"
            );
            let margin = std::f32::consts::PI - 0.1;
            assert!(angles.iter().all(|a| a.abs() < margin), "{angles:?}");
        }
    }

    #[test]
    fn polar_grid_measures_angles_from_the_axis_and_cuts_opposite() {
        let device = cpu_device();
        let t3 = |v: Vec<f32>| Tensor::<3>::from_data(TensorData::new(v, [1, 1, 4]), &device);
        // Points at radius 0.5: along +x, along +y (image rows grow downwards), just either side
        // of -x, and one at the centre.
        let x = t3(vec![0.5, 0.0, -0.5, 0.0]);
        let y = t3(vec![0.0, 0.5, -0.001, 0.0]);
        let fade = 0.25 / (0.25 + POLAR_FADE_RADIUS * POLAR_FADE_RADIUS);
        let one = |v: f32| Tensor::<3>::from_data(TensorData::new(vec![v], [1, 1, 1]), &device);
        let axis = |[c, s]: [f32; 2]| (one(c), one(s));
        let (c, s) = axis([1.0, 0.0]);
        let (angle, radius) = polar_grid(x.clone(), y.clone(), c, s);
        let (angle, radius) = (to_vec(angle), to_vec(radius));
        let pi = std::f32::consts::PI;
        for (got, want) in angle.iter().zip([0.0, pi / 2.0 * fade, -pi * fade, 0.0]) {
            assert!((got - want).abs() < 0.01, "{angle:?}");
        }
        for (got, want) in radius.iter().zip([0.5, 0.5, 0.5, 0.0]) {
            assert!((got - want).abs() < 1e-3, "{radius:?}");
        }
        // With the axis along +y the cut moves to -y: the point along +x is now at -pi/2 and
        // the one near -x at +pi/2, continuous across the old cut.
        let (c, s) = axis([0.0, 1.0]);
        let (angle, _) = polar_grid(x, y, c, s);
        let angle = to_vec(angle);
        assert!((angle[0] + pi / 2.0 * fade).abs() < 0.01, "{angle:?}");
        assert!((angle[2] - pi / 2.0 * fade).abs() < 0.01, "{angle:?}");
    }

    #[test]
    fn pairwise_angles_are_the_angles_between_keypoints_about_the_centre() {
        let device = cpu_device().autodiff();
        let t3 = |v: Vec<f32>| Tensor::<3>::from_data(TensorData::new(v, [1, 4, 1]), &device);
        // Keypoints at radius 1 along +x, +y and -x, and one at the centre.
        let x = t3(vec![1.0, 0.0, -1.0, 0.0]).require_grad();
        let y = t3(vec![0.0, 1.0, 0.0, 0.0]).require_grad();
        let angles = pairwise_angles(x.clone(), y.clone());
        assert_eq!(angles.dims(), [1, 6]);
        let fade = 1.0 / (1.0 + POLAR_FADE_RADIUS * POLAR_FADE_RADIUS);
        let pi = std::f32::consts::PI;
        // Pairs (0,1) (0,2) (0,3) (1,2) (1,3) (2,3): a quarter turn, a half turn (on the jump,
        // atan2 gives +pi), a quarter turn; any pair with the centre is 0.
        let want = [pi / 2.0, pi, 0.0, pi / 2.0, 0.0, 0.0].map(|a| a * fade * fade);
        let got = to_vec(angles.clone());
        for (g, w) in got.iter().zip(want) {
            assert!((g - w).abs() < 1e-5, "{got:?}");
        }
        // Turning the scene turns no angle between keypoints.
        let turn = 0.7f32;
        let (c, s) = (turn.cos(), turn.sin());
        let (xs, ys) = ([1.0f32, 0.0, -1.0, 0.0], [0.0f32, 1.0, 0.0, 0.0]);
        let xr = t3(xs.iter().zip(ys).map(|(x, y)| c * x - s * y).collect());
        let yr = t3(xs.iter().zip(ys).map(|(x, y)| s * x + c * y).collect());
        let turned = to_vec(pairwise_angles(xr, yr));
        // Pair (0,2) sits on the jump, where rounding picks either side.
        for (i, (g, w)) in turned.iter().zip(&got).enumerate().filter(|(i, _)| *i != 1) {
            assert!((g - w).abs() < 1e-4, "pair {i}: {turned:?}");
        }
        // The keypoint at the centre gets a finite (zero) gradient.
        let grads = angles.sum().backward();
        let (gx, gy) = (
            to_vec(x.grad(&grads).unwrap()),
            to_vec(y.grad(&grads).unwrap()),
        );
        assert!(gx.iter().chain(&gy).all(|g| g.is_finite()), "{gx:?} {gy:?}");
        assert_eq!((gx[3], gy[3]), (0.0, 0.0));
    }

    #[test]
    fn pairwise_angles_need_the_polar_head_and_widen_its_input() {
        let device = cpu_device();
        let head = |polar, pairwise_angles| EncoderHead::SoftArgmax {
            keypoints: 4,
            hidden: 8,
            polar,
            pairwise_angles,
        };
        let mut config = EncoderConfig {
            trunk_channels: [4, 4],
            head: head(false, true),
            ..EncoderConfig::new(2)
        };
        let err = config.validate().unwrap_err().to_string();
        assert!(err.contains("pairwise_angles"), "{err}");
        config.head = head(true, true);
        assert!(config.validate().is_ok());
        let encoder = reinit_params(config.init(&device), 5);
        // 4 angles, 4 radii and 6 pairs feed the tanh layer.
        let hidden = encoder.keypoints.as_ref().and_then(|k| k.hidden.as_ref());
        assert_eq!(hidden.map(|l| l.weight.dims()), Some([14, 8]));
        let h = to_vec(encoder.forward(frames(&device)));
        assert_eq!(h.len(), 48);
        assert!(h.iter().all(|x| x.is_finite()), "{h:?}");

        // `pairwise_init_scale` scales the 6 pair rows of the first layer and no other.
        let drawn = assert_only_pair_rows_scaled(&encoder, 8, 8);
        assert!(drawn[8 * 8..].iter().any(|&w| w != 0.0));
        // At 0 (through the model config) the fresh latent does not see the pairs at all.
        config.pairwise_init_scale = 0.0;
        let model = crate::model::ModelConfig {
            encoder: config.clone(),
            ..crate::model::ModelConfig::for_action_dim(2)
        };
        let zeroed = model.init(5, &device).expect("init").encoder;
        let pairs = to_vec(
            zeroed
                .keypoints
                .as_ref()
                .unwrap()
                .hidden
                .as_ref()
                .unwrap()
                .weight
                .val(),
        );
        assert!(pairs[8 * 8..].iter().all(|&w| w == 0.0));
        config.pairwise_init_scale = -1.0;
        let err = config.validate().unwrap_err().to_string();
        assert!(err.contains("model.encoder.pairwise_init_scale"), "{err}");
    }

    #[test]
    fn angle_falloff_weighs_each_cells_angle_by_its_distance() {
        let device = cpu_device();
        let polar = |falloff| EncoderConfig {
            trunk_channels: [4, 4],
            head: EncoderHead::SoftArgmax {
                keypoints: 2,
                hidden: 0,
                polar: true,
                pairwise_angles: false,
            },
            polar_angle_falloff: falloff,
            ..EncoderConfig::new(2)
        };
        let grids = |config: EncoderConfig| {
            let encoder = config.init(&device);
            let head = encoder.keypoints.expect("a keypoint head");
            let ([angle, radius], _) = head.coordinate_grids(6, 6, &device);
            (to_vec(angle), to_vec(radius))
        };
        let (full, radius) = grids(polar(None));
        assert_eq!(grids(polar(Some(0.0))), (full.clone(), radius.clone()));
        let (weighed, weighed_radius) = grids(polar(Some(0.5)));
        assert_eq!(radius, weighed_radius);
        // Cells at 0.5 from the centre keep half their angle; nearer ones more, farther less.
        for ((&a, &w), &r) in full.iter().zip(&weighed).zip(&radius) {
            let want = a / (1.0 + (r / 0.5).powi(2));
            assert!((w - want).abs() < 1e-6, "r {r}: {w} against {want}");
        }
        assert!(full.iter().any(|a| a.abs() > 1.0));
        for bad in [-0.5, f64::NAN, f64::INFINITY] {
            let err = polar(Some(bad)).validate().unwrap_err().to_string();
            assert!(err.contains("model.encoder.polar_angle_falloff"), "{err}");
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
