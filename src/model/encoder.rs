//! Encoder `e`: one 64x64 RGB frame -> configuration latent `h` in R^du.

use burn::module::{Module, Param};
use burn::nn::conv::{Conv2d, Conv2dConfig};
use burn::nn::{Linear, LinearConfig, PaddingConfig2d};
use burn::tensor::activation::{relu, softmax, tanh};
use burn::tensor::module::interpolate;
use burn::tensor::ops::{InterpolateMode, InterpolateOptions};
use burn::tensor::{Device, Int, Tensor, TensorData};

use crate::envs::{FRAME_BYTES, FRAME_PX};
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
    ///
    /// With `polar = true` each keypoint is the expected angle and distance about the image
    /// centre of the cells it attends to, instead of their expected `(x, y)`: the coordinates
    /// of a revolute joint anchored there. An
    /// angle must be cut somewhere on the circle; the cut is placed, once, in the direction the
    /// training frames change least (for an arm with joint limits, the sector its links never
    /// sweep), see [`Encoder::place_polar_cut`].
    SoftArgmax {
        keypoints: usize,
        #[serde(default)]
        hidden: usize,
        #[serde(default)]
        polar: bool,
        /// With `polar = true`, also feed each keypoint's expected `(x, y)` to the next layer.
        /// Polar coordinates about the centre resolve a link anchored there but not a point
        /// that comes close to the centre (the reacher's fingertip with the wrist folded back
        /// lies within a cell or two of it) or crosses the cut; `(x, y)` is smooth at both.
        #[serde(default)]
        with_cartesian: bool,
        /// With `polar = true`, also feed the angle between every pair of keypoints, seen from
        /// the centre (from their expected `(x, y)`). A keypoint's own angle jumps where it
        /// crosses the cut; the angle between two keypoints jumps only where it reaches
        /// 180 degrees. The reacher's links are equally long, so the angle between the wrist
        /// and the fingertip is exactly half the wrist angle at every shoulder angle, while
        /// the fingertip's own angle (shoulder + wrist / 2) sweeps more than a full turn.
        #[serde(default)]
        pairwise_angles: bool,
        /// With `polar`, `pairwise_angles` and a tanh layer: `h_0` is one linear map of the
        /// keypoints' angles about the centre (the base coordinate), and `h_1..` come from the
        /// tanh layer on the keypoints' radii and pairwise angles only, inputs that do not change
        /// when the whole scene turns about the centre. For a planar arm whose base joint sits
        /// at the centre that is the joint structure: the base angle turns every link, and the
        /// outer joint shows in the angles between links (the reacher's wrist is twice the
        /// angle between elbow and fingertip). With one tanh layer on every input, CPC curls
        /// the shoulder's 320 degrees into a U whose ends a fixed PD gain cannot follow
        /// (stops 17-21); a linear map of angles cannot curl.
        #[serde(default)]
        linear_base: bool,
    },
}

/// Encoder architecture. Defaults sized for 2 CPU cores (spec.md 3).
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct EncoderConfig {
    /// Dimension of `h` (= action dimension du).
    pub latent_dim: usize,
    /// Channels of the two trunk convs (64 -> 32 -> 16 pixels at the default strides).
    pub trunk_channels: [usize; 2],
    /// Stride of the trunk's second conv: 2 (16x16 keypoint cells of 4 pixels) or, with a
    /// soft-argmax head, 1 (32x32 cells of 2 pixels, four times the second conv's work). Unlike
    /// `keypoint_upsample`, which interpolates the 16x16 maps, the finer cells see the image at
    /// that resolution: at the reacher's folded wrist the fingertip lies 4-12 pixels from the
    /// centre, one to three coarse cells.
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
    /// Soft-argmax heads: upsample the keypoint feature maps bilinearly by this factor before
    /// the attention (1: the trunk's 16x16 cells). The attention then averages over finer cells,
    /// which matters for polar keypoints near the centre, where one of the 16x16 cells spans up
    /// to 90 degrees of angle.
    #[serde(default = "default_keypoint_upsample")]
    pub keypoint_upsample: usize,
    /// Polar heads with `pairwise_angles`: the fan-in initial weights from the pairwise angles
    /// into the head's first layer are multiplied by this (1: as drawn; 0: the angles start
    /// with no influence and enter only as training finds them useful). Pairwise angles of
    /// keypoints that sit off the arm wrap inside the joint ranges, and the fresh head's random
    /// mix of them already curls the shoulder round an arc at step 1, a shape training keeps.
    #[serde(default = "default_pairwise_init_scale")]
    pub pairwise_init_scale: f64,
    /// Polar heads: each cell's angle fades linearly to 0 over this many degrees before the cut
    /// (0: no fade, a jump of 2 pi at the cut). The cut sits in the shoulder's unreachable gap,
    /// but the reacher's forearm and fingertip cross it, and a keypoint attending to them jumps
    /// there; faded, its angle goes to 0 from both sides and stays continuous.
    #[serde(default)]
    pub polar_cut_fade_deg: f64,
    /// Polar heads: the direction of the angle cut in the image, degrees from +x with image
    /// rows growing downwards (`None`: the quietest direction of the training frames, see
    /// [`Encoder::place_polar_cut`]). On the reacher that estimate lands at 167.5 degrees,
    /// 7.5 degrees past the shoulder's limit at -160 (the fingertip, which overhangs the gap
    /// on one side only, shifts it); the gap's centre is 180.
    #[serde(default)]
    pub polar_cut_deg: Option<f64>,
    /// Polar heads: measure every keypoint but the first from the first one's direction (each
    /// cell's angle relative to keypoint 0's expected position, in `(-pi, pi]`), keeping only
    /// keypoint 0's angle about the fixed axis. A keypoint's own angle jumps where it crosses
    /// the cut, and the reacher's forearm and fingertip cross it near either shoulder limit;
    /// seen from a keypoint on the upper arm, the fingertip is at half the wrist angle, which
    /// never reaches 180 degrees. Only keypoint 0 can then meet the cut. Which part keypoint 0
    /// attends to is learned.
    #[serde(default)]
    pub relative_angles: bool,
    /// With `relative_angles`: keypoint 0 attends only to cells within this distance of the
    /// centre (image half-widths; 0: anywhere). On the reacher the upper arm reaches 0.39 and
    /// the fingertip 0.77, so a disc of 0.35 holds the upper arm in every configuration (and
    /// the forearm only with the wrist folded past 120 degrees): keypoint 0 then measures the
    /// shoulder, whose angle never meets the cut.
    #[serde(default)]
    pub relative_reference_radius: f64,
}

fn default_pairwise_init_scale() -> f64 {
    1.0
}

fn default_sharpness() -> f64 {
    1.0
}

fn default_keypoint_upsample() -> usize {
    1
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
                with_cartesian: false,
                pairwise_angles: false,
                linear_base: false,
            },
            keypoint_sharpness: 1.0,
            init_latent_std: None,
            keypoint_upsample: default_keypoint_upsample(),
            trunk_second_stride: default_trunk_second_stride(),
            pairwise_init_scale: default_pairwise_init_scale(),
            polar_cut_fade_deg: 0.0,
            polar_cut_deg: None,
            relative_angles: false,
            relative_reference_radius: 0.0,
        }
    }

    /// Width `F` of the keypoint head's features (the K angles and K radii, or x and y, then
    /// the Cartesian extras and the pairwise angles when on); `None` for the MLP head.
    pub fn keypoint_feature_count(&self) -> Option<usize> {
        let EncoderHead::SoftArgmax {
            keypoints,
            polar,
            with_cartesian,
            pairwise_angles,
            ..
        } = self.head
        else {
            return None;
        };
        let per_keypoint = if polar && with_cartesian { 4 } else { 2 };
        let pairs = if polar && pairwise_angles {
            keypoints * (keypoints - 1) / 2
        } else {
            0
        };
        Some(per_keypoint * keypoints + pairs)
    }

    pub(crate) fn validate(&self) -> Result<()> {
        if let Some(cut) = self.polar_cut_deg
            && !cut.is_finite()
        {
            return Err(Error::config(
                "model.encoder.polar_cut_deg",
                format!("{cut} must be a finite angle in degrees"),
            ));
        }
        if !(self.polar_cut_fade_deg.is_finite()
            && (0.0..=180.0).contains(&self.polar_cut_fade_deg))
        {
            return Err(Error::config(
                "model.encoder.polar_cut_fade_deg",
                format!("{} must be in [0, 180]", self.polar_cut_fade_deg),
            ));
        }
        if !(self.pairwise_init_scale.is_finite() && self.pairwise_init_scale >= 0.0) {
            return Err(Error::config(
                "model.encoder.pairwise_init_scale",
                format!("{} must be finite and >= 0", self.pairwise_init_scale),
            ));
        }
        if !(1..=4).contains(&self.keypoint_upsample) {
            return Err(Error::config(
                "model.encoder.keypoint_upsample",
                format!("{} must be 1, 2, 3 or 4", self.keypoint_upsample),
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
                with_cartesian: true,
                ..
            } => Err(Error::config(
                "model.encoder.head.with_cartesian",
                "adds (x, y) to polar keypoints; it needs polar = true",
            )),
            EncoderHead::SoftArgmax {
                polar: false,
                pairwise_angles: true,
                ..
            } => Err(Error::config(
                "model.encoder.head.pairwise_angles",
                "adds the angles between polar keypoints; it needs polar = true",
            )),
            EncoderHead::SoftArgmax {
                linear_base: true,
                polar,
                pairwise_angles,
                with_cartesian,
                hidden,
                ..
            } if !polar
                || !pairwise_angles
                || with_cartesian
                || hidden == 0
                || self.relative_angles
                || self.latent_dim < 2 =>
            {
                Err(Error::config(
                    "model.encoder.head.linear_base",
                    "splits h into a base angle and the rest; it needs polar = true, \
                     pairwise_angles = true, hidden > 0, latent_dim >= 2, and neither \
                     with_cartesian nor relative_angles",
                ))
            }
            EncoderHead::SoftArgmax { polar: false, .. } | EncoderHead::Mlp { .. }
                if self.relative_angles =>
            {
                Err(Error::config(
                    "model.encoder.relative_angles",
                    "measures polar keypoints from keypoint 0; it needs head.polar = true",
                ))
            }
            _ if !(self.relative_reference_radius.is_finite()
                && self.relative_reference_radius >= 0.0) =>
            {
                Err(Error::config(
                    "model.encoder.relative_reference_radius",
                    format!("{} must be finite and >= 0", self.relative_reference_radius),
                ))
            }
            _ if self.relative_reference_radius > 0.0 && !self.relative_angles => {
                Err(Error::config(
                    "model.encoder.relative_reference_radius",
                    "confines keypoint 0 of relative angles; it needs relative_angles = true",
                ))
            }
            EncoderHead::SoftArgmax { keypoints: 1, .. } if self.relative_angles => {
                Err(Error::config(
                    "model.encoder.relative_angles",
                    "needs at least 2 keypoints (keypoint 0 is the reference)",
                ))
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
            EncoderHead::SoftArgmax {
                keypoints,
                hidden,
                polar,
                with_cartesian,
                pairwise_angles,
                linear_base,
            } => {
                let with_cartesian = polar && with_cartesian;
                let pairwise_angles = polar && pairwise_angles;
                let linear_base = pairwise_angles && linear_base && hidden > 0;
                // The linear base takes the K angles; the tanh layer gets everything else.
                let features = self.keypoint_feature_count().unwrap_or(0)
                    - if linear_base { keypoints } else { 0 };
                let base = linear_base.then(|| LinearConfig::new(keypoints, 1).init(device));
                let out_dim = self.latent_dim - usize::from(linear_base);
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
                        upsample: self.keypoint_upsample,
                        cut_fade_rad: self.polar_cut_fade_deg.to_radians(),
                        relative_angles: polar && self.relative_angles,
                        reference_radius: self.relative_reference_radius,
                        with_cartesian,
                        pairwise_angles,
                        hidden: hidden_layer,
                        base,
                        out: LinearConfig::new(out_inputs, out_dim).init(device),
                        // Cut opposite +x until [`Encoder::place_polar_cut`] sees the data.
                        polar_axis: polar.then(|| {
                            Param::from_tensor(Tensor::from_data(
                                TensorData::new(vec![1f32, 0.0], [2]),
                                device,
                            ))
                            .set_require_grad(false)
                        }),
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
    /// Bilinear upsampling factor of the feature maps (1: none).
    upsample: usize,
    /// Polar keypoints followed by their `(x, y)` as well: 4 numbers per keypoint.
    with_cartesian: bool,
    /// Polar keypoints followed by the angle between each pair of them: `K (K - 1) / 2` more.
    pairwise_angles: bool,
    /// Width of the polar angle's fade before the cut, radians (0: none).
    cut_fade_rad: f64,
    /// Polar keypoints 1.. measured from keypoint 0's direction (see
    /// [`EncoderConfig::relative_angles`]).
    relative_angles: bool,
    /// Keypoint 0's attention is confined to this distance from the centre (0: anywhere).
    reference_radius: f64,
    /// Log of the per-keypoint softmax sharpness, `[K]`.
    log_sharpness: Param<Tensor<1>>,
    /// Optional tanh layer between the keypoint coordinates and `out`.
    hidden: Option<Linear>,
    /// With [`EncoderHead::SoftArgmax::linear_base`]: the keypoints' angles -> `h_0`; `out`
    /// then gives `h_1..`.
    base: Option<Linear>,
    out: Linear,
    /// Polar coordinates only: the unit direction `(cos m, sin m)` at which angles are 0; they
    /// are cut at `m + pi`. Not trained (excluded from init and the optimiser).
    polar_axis: Option<Param<Tensor<1>>>,
}

/// Name of the polar head's non-trained axis parameter.
pub(crate) const POLAR_AXIS: &str = "polar_axis";

/// Distance from the centre (image half-widths) within which a cell's angle fades to 0: the
/// angle of a point at the pivot is undefined.
const POLAR_FADE_RADIUS: f32 = 0.05;

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
        self.forward_with_features(frames).0
    }

    /// The head's output `raw [n, du]` turned by the orientation `Q`: rows are samples, so
    /// `h = raw Q^T`.
    fn orient(&self, raw: Tensor<2>) -> Tensor<2> {
        raw.matmul(self.latent_transform.val().transpose())
    }

    /// Rescales the head's output layer so the latent of `frames` has zero mean and standard
    /// deviation `target_std` in every dimension (data-dependent initialisation).
    pub fn normalise_latent_scale(mut self, frames: Tensor<4>, target_std: f64) -> Self {
        let raw = self.forward_unoriented(frames).0.detach(); // [n, du]
        let mean = raw.clone().mean_dim(0); // [1, du]
        let std = (raw - mean.clone())
            .powi_scalar(2)
            .mean_dim(0)
            .sqrt()
            .clamp_min(1e-12); // [1, du]
        let scale = std.recip() * target_std; // [1, du]
        match (&mut self.mlp, &mut self.keypoints) {
            (Some(head), _) => standardise_columns(&mut head.fc2, mean, scale),
            (None, Some(head)) => match head.base.as_mut() {
                // `h_0` is the base's one output, `h_1..` the rest's.
                Some(base) => {
                    let du = scale.dims()[1];
                    let (mean_0, mean_rest) =
                        (mean.clone().slice([0..1, 0..1]), mean.slice([0..1, 1..du]));
                    let scale_0 = scale.clone().slice([0..1, 0..1]);
                    standardise_columns(base, mean_0, scale_0);
                    standardise_columns(&mut head.out, mean_rest, scale.slice([0..1, 1..du]));
                }
                None => standardise_columns(&mut head.out, mean, scale),
            },
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
        // The linear base takes the angles away from the first layer.
        let per_keypoint = match (head.with_cartesian, head.base.is_some()) {
            (true, _) => 4,
            (false, false) => 2,
            (false, true) => 1,
        };
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

    /// Places the polar head's angle cut in the direction where `frames` (RGB u8, 64x64)
    /// change least, so no reachable configuration sits on it (no-op for the other heads).
    /// Data-dependent initialisation, run once before training on every frame of the dataset
    /// (a 256-frame sample put the reacher's cut inside the shoulder's range for 2 of 6 seeds);
    /// the axis is stored with the weights.
    pub fn place_polar_cut<'a>(self, frames: impl Iterator<Item = &'a [u8]>) -> Self {
        if self.polar_axis().is_none() {
            return self;
        }
        let cut = quietest_direction(frames);
        self.set_polar_cut(cut)
    }

    /// Puts the polar head's angle cut at `cut_deg` (degrees from +x, image rows growing
    /// downwards; no-op for the other heads).
    pub fn with_polar_cut_at(self, cut_deg: f64) -> Self {
        let (sin, cos) = cut_deg.to_radians().sin_cos();
        self.set_polar_cut([cos as f32, sin as f32])
    }

    fn set_polar_cut(mut self, [cut_x, cut_y]: [f32; 2]) -> Self {
        let Some(head) = self.keypoints.as_mut() else {
            return self;
        };
        let Some(axis) = head.polar_axis.as_mut() else {
            return self;
        };
        let device = axis.val().device();
        *axis = Param::from_tensor(Tensor::from_data(
            TensorData::new(vec![-cut_x, -cut_y], [2]),
            &device,
        ))
        .set_require_grad(false);
        self
    }

    /// The polar head's axis `(cos m, sin m)`: angles are measured from it and cut opposite.
    pub fn polar_axis(&self) -> Option<[f32; 2]> {
        let axis = self.keypoints.as_ref()?.polar_axis.as_ref()?;
        let v = crate::model::to_vec(axis.val());
        Some([v[0], v[1]])
    }

    /// `h` of `frames` (as [`Encoder::forward`]) and, for the keypoint head, the keypoint
    /// features `[n, F]` it was computed from (see [`EncoderConfig::keypoint_feature_count`]);
    /// the feature decoder reconstructs these.
    pub fn forward_with_features(&self, frames: Tensor<4>) -> (Tensor<2>, Option<Tensor<2>>) {
        let (raw, features) = self.forward_unoriented(frames);
        (self.orient(raw), features)
    }

    /// `h` from keypoint features `[n, F]` (as [`Encoder::forward_with_features`] gives them):
    /// the head's layers after the keypoints, then the orientation. `None` for the MLP head.
    pub fn latent_from_features(&self, features: Tensor<2>) -> Option<Tensor<2>> {
        let head = self.keypoints.as_ref()?;
        Some(self.orient(head.latent_from_features(features)))
    }

    /// The head's output before the orientation `Q`, and the keypoint features it read.
    fn forward_unoriented(&self, frames: Tensor<4>) -> (Tensor<2>, Option<Tensor<2>>) {
        let x = relu(self.conv1.forward(frames)); // [n, c1, 32, 32]
        let x = relu(self.conv2.forward(x)); // [n, c2, 16, 16], or 32x32 at stride 1
        if let Some(head) = &self.mlp {
            let x = relu(head.conv3.forward(x)); // [n, 32, 8, 8]
            let n = x.dims()[0];
            let x = relu(head.fc1.forward(x.reshape([n, 32 * 8 * 8]))); // [n, hidden]
            return (head.fc2.forward(x), None); // [n, du]
        }
        let head = self
            .keypoints
            .as_ref()
            .expect("encoder has one head by construction");
        let maps = head.features.forward(x); // [n, K, 16, 16] (32x32 at stride 1)
        let maps = if head.upsample > 1 {
            let [_, _, rows, cols] = maps.dims();
            let size = [rows * head.upsample, cols * head.upsample];
            let options = InterpolateOptions::new(InterpolateMode::Bilinear)
                .with_output_size(size)
                .with_align_corners(false);
            interpolate(maps, options) // [n, K, 16 u, 16 u]
        } else {
            maps
        };
        let [n, k, rows, cols] = maps.dims();
        let sharpness = head.log_sharpness.val().exp().reshape([1, k, 1]);
        let logits = maps.reshape([n, k, rows * cols]) * sharpness; // [n, K, cells]
        let logits = if head.relative_angles && head.reference_radius > 0.0 {
            let device = logits.device();
            logits + reference_mask(k, rows, cols, head.reference_radius, &device)
        } else {
            logits
        };
        let attention = softmax(logits, 2); // [n, K, cells]
        // Each keypoint is the attention's expected cell coordinate: Cartesian, or the polar
        // angle and radius of the cells about the image centre.
        let (grid_x, grid_y) = pixel_grid(rows, cols, &attention.device());
        let expected = |grid: Tensor<3>| (attention.clone() * grid).sum_dim(2); // [n, K, 1]
        let mut coordinates = match &head.polar_axis {
            Some(axis) => {
                let axis = axis.val();
                let cos_m = axis.clone().slice(0..1).reshape([1, 1, 1]);
                let sin_m = axis.slice(1..2).reshape([1, 1, 1]);
                let (x, y) = (grid_x.clone(), grid_y.clone());
                let (angle, radius) = polar_grid(x, y, cos_m, sin_m, head.cut_fade_rad);
                let angle = expected(angle);
                let angle = if head.relative_angles {
                    let (x, y) = (grid_x.clone(), grid_y.clone());
                    // Only keypoint 0 keeps its angle about the fixed axis.
                    let relative = relative_angles(attention.clone(), x, y, head.cut_fade_rad);
                    Tensor::cat(vec![angle.slice([0..n, 0..1]), relative], 1)
                } else {
                    angle
                };
                vec![angle, expected(radius)]
            }
            None => vec![expected(grid_x.clone()), expected(grid_y.clone())],
        };
        // The polar head's extras share one expected (x, y) per keypoint.
        let cartesian = (head.with_cartesian || head.pairwise_angles)
            .then(|| (expected(grid_x), expected(grid_y)));
        if head.with_cartesian
            && let Some((x, y)) = &cartesian
        {
            coordinates.extend([x.clone(), y.clone()]);
        }
        let features = coordinates.len() * k;
        let keypoints = Tensor::cat(coordinates, 1).reshape([n, features]); // [n, 2K or 4K]
        let keypoints = match cartesian.filter(|_| head.pairwise_angles) {
            // [n, features + K (K - 1) / 2]
            Some((x, y)) => Tensor::cat(vec![keypoints, pairwise_angles(x, y)], 1),
            None => keypoints,
        };
        (
            head.latent_from_features(keypoints.clone()),
            Some(keypoints),
        )
    }
}

impl KeypointHead {
    /// The keypoint features `[n, F]` (the K angles, the K radii, then any extras) -> `h`.
    fn latent_from_features(&self, features: Tensor<2>) -> Tensor<2> {
        let (base, rest) = match &self.base {
            Some(base) => {
                let [n, width] = features.dims();
                let k = base.weight.dims()[0];
                let angles = features.clone().slice([0..n, 0..k]);
                (Some(base.forward(angles)), features.slice([0..n, k..width]))
            }
            None => (None, features),
        };
        let rest = match &self.hidden {
            Some(hidden) => self.out.forward(tanh(hidden.forward(rest))), // [n, du or du - 1]
            None => self.out.forward(rest),
        };
        match base {
            Some(base) => Tensor::cat(vec![base, rest], 1), // [n, du]
            None => rest,
        }
    }
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

/// Cell coordinates `(x, y)` (`[1, 1, cells]` each, about the image centre) -> each cell's
/// angle from the axis `(cos m, sin m)` and its distance from the centre. The axis is
/// `[1, 1, 1]`, or `[n, 1, 1]` for one axis per sample (the angle is then `[n, 1, cells]`).
/// Angles are in `(-pi, pi]`, faded to 0 within [`POLAR_FADE_RADIUS`] of the centre, where the
/// angle is undefined. The expected angle under a
/// keypoint's attention then grows with the angle of what it attends to, with no jump unless
/// that crosses the cut opposite `axis`; with `cut_fade > 0` the angle also fades linearly to 0
/// over the last `cut_fade` radians before the cut, so it does not jump there either.
fn polar_grid(
    x: Tensor<3>,
    y: Tensor<3>,
    cos_m: Tensor<3>,
    sin_m: Tensor<3>,
    cut_fade: f64,
) -> (Tensor<3>, Tensor<3>) {
    // Rotate by -m so the axis lies along +x and the cut along -x, where atan2 jumps.
    let along = x.clone() * cos_m.clone() + y.clone() * sin_m.clone();
    let across = y * cos_m - x * sin_m;
    let r_squared = along.clone().powi_scalar(2) + across.clone().powi_scalar(2);
    let fade = r_squared.clone() / (r_squared.clone() + POLAR_FADE_RADIUS * POLAR_FADE_RADIUS);
    let angle = across.atan2(along);
    let angle = if cut_fade > 0.0 {
        let to_cut = angle.clone().abs().neg().add_scalar(std::f64::consts::PI);
        angle * (to_cut / cut_fade).clamp(0.0, 1.0)
    } else {
        angle
    };
    (angle * fade, r_squared.sqrt())
}

/// `[1, K, rows * cols]`: 0, except a large negative number at keypoint 0's cells further than
/// `radius` from the centre: added to the attention's logits, it confines keypoint 0 to the
/// disc (a disc with no cell in it shifts all of keypoint 0's logits alike, which changes
/// nothing).
fn reference_mask(k: usize, rows: usize, cols: usize, radius: f64, device: &Device) -> Tensor<3> {
    let (x, y) = pixel_grid(rows, cols, device);
    let r = (x.powi_scalar(2) + y.powi_scalar(2)).sqrt(); // [1, 1, cells]
    let outside = r.greater_elem(radius).float() * -1e4; // [1, 1, cells]
    let rest = Tensor::zeros([1, k - 1, rows * cols], device);
    Tensor::cat(vec![outside, rest], 1)
}

/// Keypoint attention `[n, K, cells]` over cells at `(x, y)` (`[1, 1, cells]` each) -> the
/// expected angle of keypoints `1..K` measured from keypoint 0's expected direction about the
/// centre (`[n, K - 1, 1]`; each cell's angle in `(-pi, pi]`, faded as in [`polar_grid`]), so
/// a keypoint is continuous wherever it stays within half a turn of keypoint 0.
fn relative_angles(attention: Tensor<3>, x: Tensor<3>, y: Tensor<3>, cut_fade: f64) -> Tensor<3> {
    let [n, k, _] = attention.dims();
    let reference = attention.clone().slice([0..n, 0..1]); // [n, 1, cells]
    let x0 = (reference.clone() * x.clone()).sum_dim(2); // [n, 1, 1]
    let y0 = (reference * y.clone()).sum_dim(2);
    // The offset keeps the direction's gradient finite with keypoint 0 at the centre.
    let norm = (x0.clone().powi_scalar(2) + y0.clone().powi_scalar(2))
        .add_scalar(POLAR_FADE_RADIUS * POLAR_FADE_RADIUS)
        .sqrt();
    let (angle, _) = polar_grid(x, y, x0 / norm.clone(), y0 / norm, cut_fade); // [n, 1, cells]
    (attention.slice([0..n, 1..k]) * angle).sum_dim(2)
}

/// Expected keypoint positions `x, y` (`[n, K, 1]` each, about the image centre) -> the angle
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

/// The direction (unit vector in image coordinates about the centre) in which `frames` (RGB
/// u8, 64x64) change least: each pixel's standard deviation over the frames (summed over the
/// channels), divided by its distance from the centre and binned by its angle about the centre
/// in 5-degree bins, smoothed over +-15 degrees; the cut is the emptiest bin. For an arm with
/// joint limits that is the sector its links never sweep.
fn quietest_direction<'a>(frames: impl Iterator<Item = &'a [u8]>) -> [f32; 2] {
    const BINS: usize = 72;
    const SMOOTH: isize = 3;
    let (rows, cols) = (FRAME_PX, FRAME_PX);
    let mut sum = vec![0f64; FRAME_BYTES];
    let mut sum_squares = vec![0f64; FRAME_BYTES];
    let mut count = 0usize;
    for frame in frames {
        for ((s, q), &byte) in sum.iter_mut().zip(&mut sum_squares).zip(frame) {
            let x = byte as f64;
            *s += x;
            *q += x * x;
        }
        count += 1;
    }
    let n = count.max(1) as f64;
    let std: Vec<f64> = sum
        .chunks_exact(3)
        .zip(sum_squares.chunks_exact(3))
        .map(|(s, q)| {
            (0..3)
                .map(|c| (q[c] / n - (s[c] / n).powi(2)).max(0.0).sqrt())
                .sum()
        })
        .collect();
    let mut histogram = [0f64; BINS];
    let coord = |i: usize, n: usize| (2.0 * i as f64 + 1.0) / n as f64 - 1.0;
    for (p, &w) in std.iter().enumerate() {
        let (x, y) = (coord(p % cols, cols), coord(p / cols, rows));
        let turn = y.atan2(x).rem_euclid(std::f64::consts::TAU) / std::f64::consts::TAU;
        // 1 / r: every distance from the centre counts equally per angle (there are r times
        // more pixels per degree at radius r), so an arm's inner link, whose sweep is bounded
        // by the joint limit, weighs as much as the outer one, whose sweep overhangs it.
        let r = x.hypot(y).max(POLAR_FADE_RADIUS as f64);
        histogram[((turn * BINS as f64) as usize).min(BINS - 1)] += w / r;
    }
    let smoothed = |b: usize| -> f64 {
        (-SMOOTH..=SMOOTH)
            .map(|d| histogram[(b as isize + d).rem_euclid(BINS as isize) as usize])
            .sum()
    };
    let quietest = (0..BINS)
        .min_by(|&a, &b| smoothed(a).total_cmp(&smoothed(b)))
        .unwrap_or(0);
    let angle = (quietest as f64 + 0.5) / BINS as f64 * std::f64::consts::TAU;
    [angle.cos() as f32, angle.sin() as f32]
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
    use crate::envs::EnvKind;
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
                with_cartesian: false,
                pairwise_angles: false,
                linear_base: false,
            },
            EncoderHead::SoftArgmax {
                keypoints: 4,
                hidden: 8,
                polar: true,
                with_cartesian: false,
                pairwise_angles: false,
                linear_base: false,
            },
            // Polar keypoints and their (x, y): 16 inputs to the tanh layer or the output.
            EncoderHead::SoftArgmax {
                keypoints: 4,
                hidden: 8,
                polar: true,
                with_cartesian: true,
                pairwise_angles: false,
                linear_base: false,
            },
            EncoderHead::SoftArgmax {
                keypoints: 4,
                hidden: 0,
                polar: true,
                with_cartesian: true,
                pairwise_angles: false,
                linear_base: false,
            },
            EncoderHead::Mlp { hidden: 8 },
            // h_0 from the base layer, h_1 from `out`: each is standardised.
            EncoderHead::SoftArgmax {
                keypoints: 4,
                hidden: 8,
                polar: true,
                with_cartesian: false,
                pairwise_angles: true,
                linear_base: true,
            },
        ];
        // Every head as it is, then the polar tanh head (`heads[1]`) with keypoints 1..
        // measured from keypoint 0.
        let cases = heads.map(|head| (head, false)).into_iter();
        for (head, relative_angles) in cases.chain([(heads[1], true)]) {
            let config = EncoderConfig {
                trunk_channels: [4, 4],
                head,
                keypoint_sharpness: 30.0,
                relative_angles,
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

    #[test]
    fn upsampled_keypoints_attend_over_finer_cells() {
        let device = cpu_device();
        let mut config = EncoderConfig {
            trunk_channels: [4, 4],
            head: EncoderHead::SoftArgmax {
                keypoints: 4,
                hidden: 8,
                polar: true,
                with_cartesian: false,
                pairwise_angles: false,
                linear_base: false,
            },
            keypoint_sharpness: 30.0,
            ..EncoderConfig::new(2)
        };
        config.keypoint_upsample = 0;
        let err = config.validate().unwrap_err().to_string();
        assert!(err.contains("keypoint_upsample"), "{err}");
        config.keypoint_upsample = 2;
        assert!(config.validate().is_ok());
        let fine = reinit_params(config.init(&device), 3);
        config.keypoint_upsample = 1;
        let coarse = reinit_params(config.init(&device), 3);
        // A stride-1 second conv has the same weights' shapes and attends over 32x32 cells.
        config.trunk_second_stride = 1;
        let strided = reinit_params(config.init(&device), 3);
        let h_strided = to_vec(strided.forward(frames(&device)));
        assert_eq!(h_strided.len(), 48);
        assert!(h_strided.iter().all(|x| x.is_finite()));
        assert!(
            h_strided
                .iter()
                .zip(&to_vec(coarse.forward(frames(&device))))
                .any(|(a, b)| (a - b).abs() > 1e-6)
        );
        config.trunk_second_stride = 3;
        let err = config.validate().unwrap_err().to_string();
        assert!(err.contains("model.encoder.trunk_second_stride"), "{err}");
        config.trunk_second_stride = 1;
        config.head = EncoderHead::Mlp { hidden: 8 };
        let err = config.validate().unwrap_err().to_string();
        assert!(err.contains("model.encoder.trunk_second_stride"), "{err}");
        // Same weights, different attention grids: finite encodings that differ.
        let (h_fine, h_coarse) = (
            to_vec(fine.forward(frames(&device))),
            to_vec(coarse.forward(frames(&device))),
        );
        assert_eq!(h_fine.len(), 48);
        assert!(h_fine.iter().all(|x| x.is_finite()));
        assert!(
            h_fine
                .iter()
                .zip(&h_coarse)
                .any(|(a, b)| (a - b).abs() > 1e-6)
        );
    }

    #[test]
    fn cartesian_and_relative_features_need_the_polar_head() {
        let mut config = EncoderConfig::new(2);
        config.head = EncoderHead::SoftArgmax {
            keypoints: 4,
            hidden: 8,
            polar: false,
            with_cartesian: true,
            pairwise_angles: false,
            linear_base: false,
        };
        let err = config.validate().unwrap_err().to_string();
        assert!(err.contains("with_cartesian"), "{err}");
        config.head = EncoderHead::SoftArgmax {
            keypoints: 4,
            hidden: 8,
            polar: true,
            with_cartesian: true,
            pairwise_angles: false,
            linear_base: false,
        };
        assert!(config.validate().is_ok());
        // Relative angles need polar keypoints, and a second keypoint to measure.
        config.relative_angles = true;
        assert!(config.validate().is_ok());
        for (polar, keypoints) in [(false, 4), (true, 1)] {
            config.head = EncoderHead::SoftArgmax {
                keypoints,
                hidden: 8,
                polar,
                with_cartesian: false,
                pairwise_angles: false,
                linear_base: false,
            };
            let err = config.validate().unwrap_err().to_string();
            assert!(err.contains("model.encoder.relative_angles"), "{err}");
        }
    }

    /// The polar head's cut must fall in the sector the reacher's shoulder cannot reach (q0
    /// beyond +-160 degrees, to the image's left), so the angle of the upper arm about the
    /// centre is continuous and monotone over the whole joint range.
    #[test]
    fn polar_cut_falls_in_the_reachers_unreachable_sector() {
        let device = cpu_device();
        let config = EncoderConfig {
            trunk_channels: [4, 4],
            head: EncoderHead::SoftArgmax {
                keypoints: 4,
                hidden: 0,
                polar: true,
                with_cartesian: false,
                pairwise_angles: false,
                linear_base: false,
            },
            ..EncoderConfig::new(2)
        };
        let encoder = config.init(&device);
        assert_eq!(encoder.polar_axis(), Some([1.0, 0.0]));
        let mut env = EnvKind::Reacher.make();
        let mut rendered = vec![];
        for seed in 0..96 {
            env.reset(seed).unwrap();
            let mut frame = [0u8; FRAME_BYTES];
            env.render(&mut frame);
            rendered.push(frame);
        }
        let encoder = encoder.place_polar_cut(rendered.iter().map(|f| &f[..]));
        let [ax, ay] = encoder.polar_axis().unwrap();
        // The unreachable sector is centred on world -x, image column < centre, row = centre.
        let off_axis_deg = ay.atan2(ax).to_degrees();
        assert!(
            off_axis_deg.abs() < 20.0,
            "axis {off_axis_deg} deg from image +x"
        );
        // The wrist (0.12 m from the centre) over the shoulder's range, in image coordinates.
        let reacher = crate::envs::Reacher::new(Default::default());
        let camera = reacher.config().camera;
        let angles: Vec<f32> = (0..=64)
            .map(|i| (-160.0 + 5.0 * i as f64).to_radians())
            .map(|q0| {
                let (wrist, _) = reacher.forward_kinematics([q0, 0.0]);
                let (col, row) = camera.project(wrist[0], wrist[1]);
                let (x, y) = (col as f32 / 32.0 - 1.0, row as f32 / 32.0 - 1.0);
                (y * ax - x * ay).atan2(x * ax + y * ay)
            })
            .collect();
        assert!(
            angles.windows(2).all(|w| w[1] < w[0]),
            "wrist angle not monotone in q0: {angles:?}"
        );
        let margin = std::f32::consts::PI - 0.1;
        assert!(angles.iter().all(|a| a.abs() < margin), "{angles:?}");
        // A cut put at 180 degrees (`model.encoder.polar_cut_deg`) is the gap's centre (world
        // -x): the axis points along image +x.
        let centred = encoder.with_polar_cut_at(180.0);
        let [ax, ay] = centred.polar_axis().unwrap();
        assert!(
            (ax - 1.0).abs() < 1e-6 && ay.abs() < 1e-6,
            "axis ({ax}, {ay})"
        );
        let mut bad = config.clone();
        bad.polar_cut_deg = Some(f64::NAN);
        let err = bad.validate().unwrap_err().to_string();
        assert!(err.contains("model.encoder.polar_cut_deg"), "{err}");
    }

    /// Keypoint 1 straddles the fixed cut (half its attention just above -x, half just
    /// below): its angle about the axis averages +-175 degrees to about 0, while seen from
    /// keypoint 0 (at 170 degrees) it is the 10 degrees it really is, and turning the whole
    /// scene leaves that unchanged.
    #[test]
    fn relative_angles_are_measured_from_keypoint_0_and_ignore_the_cut() {
        let device = cpu_device();
        let deg = |d: f32| d.to_radians();
        let relative_for = |turn: f32| {
            // Cells at radius 0.5: keypoint 0's one cell, then keypoint 1's two.
            let cells = [170.0, 175.0, -175.0].map(|a: f32| deg(a + turn));
            let t3 = |v: Vec<f32>| Tensor::<3>::from_data(TensorData::new(v, [1, 1, 3]), &device);
            let x = t3(cells.iter().map(|a| 0.5 * a.cos()).collect());
            let y = t3(cells.iter().map(|a| 0.5 * a.sin()).collect());
            let attention = vec![1.0, 0.0, 0.0, 0.0, 0.5, 0.5];
            let attention = Tensor::<3>::from_data(TensorData::new(attention, [1, 2, 3]), &device);
            to_vec(relative_angles(attention, x, y, 0.0))[0]
        };
        let fade = 0.25 / (0.25 + POLAR_FADE_RADIUS * POLAR_FADE_RADIUS);
        for turn in [0.0, 90.0, -135.0] {
            let got = relative_for(turn);
            assert!((got - deg(10.0) * fade).abs() < 1e-3, "turn {turn}: {got}");
        }
        let one = |v: f32| Tensor::<3>::from_data(TensorData::new(vec![v], [1, 1, 1]), &device);
        let t3 = |v: Vec<f32>| Tensor::<3>::from_data(TensorData::new(v, [1, 1, 2]), &device);
        let (x, y) = (
            t3(vec![-0.5, -0.5]),
            t3(vec![0.5 * deg(5.0).sin(), -0.5 * deg(5.0).sin()]),
        );
        let (absolute, _) = polar_grid(x, y, one(1.0), one(0.0), 0.0);
        let absolute = to_vec(absolute);
        assert!((absolute[0] + absolute[1]).abs() < 1e-3, "{absolute:?}");
    }

    /// Keypoint 0's logits are pushed down outside the disc, and nowhere else.
    #[test]
    fn the_reference_keypoint_is_confined_to_a_disc_about_the_centre() {
        let device = cpu_device();
        let mask = to_vec(reference_mask(3, 16, 16, 0.35, &device));
        let (x, y) = pixel_grid(16, 16, &device);
        let (x, y) = (to_vec(x), to_vec(y));
        let mut inside = 0;
        for cell in 0..256 {
            let r = (x[cell].powi(2) + y[cell].powi(2)).sqrt();
            let want = if r > 0.35 { -1e4 } else { 0.0 };
            assert_eq!(mask[cell], want, "cell {cell} at radius {r}");
            inside += usize::from(r <= 0.35);
            assert_eq!(mask[256 + cell], 0.0);
            assert_eq!(mask[512 + cell], 0.0);
        }
        // The central 3-cell-radius disc: cells whose centres lie within 0.35 of the centre.
        assert_eq!(inside, 24);
        let mut config = EncoderConfig::new(2);
        config.relative_reference_radius = 0.35;
        let err = config.validate().unwrap_err().to_string();
        assert!(err.contains("needs relative_angles"), "{err}");
        config.relative_reference_radius = f64::NAN;
        let err = config.validate().unwrap_err().to_string();
        assert!(
            err.contains("model.encoder.relative_reference_radius"),
            "{err}"
        );
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
        let (angle, radius) = polar_grid(x.clone(), y.clone(), c, s, 0.0);
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
        let (angle, _) = polar_grid(x.clone(), y.clone(), c, s, 0.0);
        let angle = to_vec(angle);
        assert!((angle[0] + pi / 2.0 * fade).abs() < 0.01, "{angle:?}");
        assert!((angle[2] - pi / 2.0 * fade).abs() < 0.01, "{angle:?}");
        // A fade of 1 rad before the cut: the point just past -x (0.002 rad from the cut)
        // nearly vanishes, the quarter turns (pi/2 from the cut) stay whole.
        let (c, s) = axis([1.0, 0.0]);
        let (angle, _) = polar_grid(x, y, c, s, 1.0);
        let angle = to_vec(angle);
        for (got, want) in angle
            .iter()
            .zip([0.0, pi / 2.0 * fade, -0.002 * pi * fade, 0.0])
        {
            assert!((got - want).abs() < 0.01, "{angle:?}");
        }
    }

    #[test]
    fn latent_from_held_features_reshapes_only_the_head_after_the_keypoints() {
        let device = cpu_device().autodiff();
        let mut config = EncoderConfig::new(2);
        config.head = EncoderHead::SoftArgmax {
            keypoints: 4,
            hidden: 8,
            polar: true,
            with_cartesian: false,
            pairwise_angles: true,
            linear_base: false,
        };
        let encoder = reinit_params(config.init(&device), 5);
        let frames = Tensor::<4>::random(
            [3, 3, 64, 64],
            burn::tensor::Distribution::Uniform(-0.5, 0.5),
            &device,
        );
        let (h, features) = encoder.forward_with_features(frames);
        let features = features.expect("keypoint features");
        // 4 angles, 4 radii and 6 pairwise angles.
        assert_eq!(features.dims(), [3, 14]);
        let again = encoder
            .latent_from_features(features.detach())
            .expect("keypoint head");
        assert_eq!(to_vec(again.clone()), to_vec(h));
        let grads = again.sum().backward();
        let head = encoder.keypoints.as_ref().expect("keypoint head");
        assert!(head.out.weight.grad(&grads).is_some());
        assert!(head.features.weight.grad(&grads).is_none());
        assert!(encoder.conv1.weight.grad(&grads).is_none());
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
            with_cartesian: false,
            pairwise_angles,
            linear_base: false,
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
    fn a_linear_base_takes_h0_from_the_angles_alone_and_the_rest_from_radii_and_pairs() {
        let device = cpu_device();
        let head = |pairwise_angles, hidden| EncoderHead::SoftArgmax {
            keypoints: 4,
            hidden,
            polar: true,
            with_cartesian: false,
            pairwise_angles,
            linear_base: true,
        };
        let mut config = EncoderConfig {
            trunk_channels: [4, 4],
            head: head(true, 8),
            keypoint_sharpness: 30.0,
            ..EncoderConfig::new(2)
        };
        assert!(config.validate().is_ok());
        let encoder = reinit_params(config.init(&device), 5);
        let keypoint_head = encoder.keypoints.as_ref().expect("keypoint head");
        let dims = |layer: Option<&Linear>| layer.map(|l| l.weight.dims());
        // 4 angles -> h_0; 4 radii and 6 pairs -> 8 tanh units -> h_1.
        assert_eq!(dims(keypoint_head.base.as_ref()), Some([4, 1]));
        assert_eq!(dims(keypoint_head.hidden.as_ref()), Some([10, 8]));
        assert_eq!(dims(Some(&keypoint_head.out)), Some([8, 1]));
        let h = to_vec(encoder.forward(frames(&device)));
        assert_eq!(h.len(), 48);
        assert!(h.iter().all(|x| x.is_finite()), "{h:?}");

        // Features of 3 samples: angles, radii, pairs. Turning every angle moves h_0 by the
        // base's weights times the turn and leaves h_1; changing radii and pairs leaves h_0.
        let features: Vec<f32> = (0..3 * 14)
            .map(|i| ((i * 37 % 11) as f32 - 5.0) / 7.0)
            .collect();
        let latent = |features: &[f32]| {
            let features =
                Tensor::<2>::from_data(TensorData::new(features.to_vec(), [3, 14]), &device);
            to_vec(keypoint_head.latent_from_features(features))
        };
        let perturbed = |columns: std::ops::Range<usize>, by: f32| {
            let mut f = features.clone();
            for row in 0..3 {
                for c in columns.clone() {
                    f[row * 14 + c] += by;
                }
            }
            latent(&f)
        };
        let h = latent(&features);
        let base_weights = to_vec(keypoint_head.base.as_ref().expect("base").weight.val());
        let turned = perturbed(0..4, 0.3);
        for row in 0..3 {
            let want = h[2 * row] + 0.3 * base_weights.iter().sum::<f32>();
            assert!((turned[2 * row] - want).abs() < 1e-5, "{turned:?} {want}");
            assert_eq!(turned[2 * row + 1], h[2 * row + 1]);
        }
        for changed in [perturbed(4..8, 0.3), perturbed(8..14, -0.4)] {
            for row in 0..3 {
                assert_eq!(changed[2 * row], h[2 * row]);
                assert_ne!(changed[2 * row + 1], h[2 * row + 1]);
            }
        }

        // `pairwise_init_scale` scales the 6 pair rows of the tanh layer, not the radii.
        assert_only_pair_rows_scaled(&encoder, 4, 8);

        // Refused by name without what it splits.
        let refused = |config: &EncoderConfig| {
            let err = config.validate().unwrap_err().to_string();
            assert!(err.contains("model.encoder.head.linear_base"), "{err}");
        };
        for bad_head in [head(false, 8), head(true, 0)] {
            refused(&EncoderConfig {
                head: bad_head,
                ..config.clone()
            });
        }
        config.relative_angles = true;
        refused(&config);
        config.relative_angles = false;
        config.latent_dim = 1;
        refused(&config);
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
