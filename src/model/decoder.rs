//! The feature decoder: `h` -> the keypoint head's own features, a training-only regulariser.
//!
//! The reacher's failed episodes mostly end with PD at its latent goal and the arm far from the
//! true one (docs/method.md, stop 25): the encoder folds two configurations onto one `h`. The
//! keypoint features the head reads (angles, radii, pairwise angles) still tell them apart, so
//! asking a smooth decoder to recover the features from a slightly noisy `h` charges exactly
//! those folds: at a fold one `h` would have to decode to two feature vectors. Control never
//! reads the decoder.

use burn::module::{Module, Param};
use burn::nn::{Linear, LinearConfig};
use burn::tensor::activation::tanh;
use burn::tensor::{Device, Tensor};

/// Two tanh layers of width `w`, then a linear map to the `F` features.
#[derive(Module, Debug)]
pub struct FeatureDecoder {
    hidden1: Linear,
    hidden2: Linear,
    out: Linear,
}

impl FeatureDecoder {
    /// A decoder from `h in R^du` to `features` numbers through two tanh layers of `width`
    /// (weights are redrawn by [`super::reinit_params`]).
    pub fn new(du: usize, width: usize, features: usize, device: &Device) -> Self {
        Self {
            hidden1: LinearConfig::new(du, width).init(device),
            hidden2: LinearConfig::new(width, width).init(device),
            out: LinearConfig::new(width, features).init(device),
        }
    }

    /// Zeroes the output layer, so the decoder starts constant: its term starts at exactly 1
    /// and sends no gradient into `h` until the decoder has learnt something to ask for (a
    /// random decoder's gradient would push `h` in random directions).
    /// New parameters are built as trainable graph leaves.
    pub fn zero_output(mut self) -> Self {
        let weight = self.out.weight.val();
        let device = weight.device();
        let zeros = Tensor::zeros(weight.dims(), &device);
        self.out.weight = Param::from_tensor(super::trainable(zeros));
        if let Some(bias) = &self.out.bias {
            let zeros = Tensor::zeros(bias.val().dims(), &device);
            self.out.bias = Some(Param::from_tensor(super::trainable(zeros)));
        }
        self
    }

    /// `h [n, du]` -> reconstructed features `[n, F]`.
    pub fn forward(&self, h: Tensor<2>) -> Tensor<2> {
        let x = tanh(self.hidden1.forward(h));
        let x = tanh(self.hidden2.forward(x));
        self.out.forward(x)
    }

    /// Re-expresses the decoder for the latent `p h` (`p` a signed permutation, `[du, du]`), so
    /// it decodes the reoriented latent to the same features. Weights are `[in, out]` and `h` a
    /// row: `(h p^T) W' = h W` with `W' = p W`.
    /// The new weight is rebuilt from its values so it stays a trainable graph leaf (the
    /// orientation search reorients mid-training). Its Adam moments, keyed by path, stay as
    /// they were: a small lag for a regulariser that control never reads.
    pub fn reorient_input(mut self, p: Tensor<2>) -> Self {
        let weight = p.matmul(self.hidden1.weight.val().detach());
        let device = weight.device();
        let weight = Tensor::from_data(weight.into_data(), &device);
        self.hidden1.weight = Param::from_tensor(super::trainable(weight));
        self
    }
}

#[cfg(test)]
mod tests {
    use burn::tensor::Tensor;

    use crate::model::{EncoderHead, ModelConfig, cpu_device, to_vec};

    fn decoder_config() -> ModelConfig {
        let mut config = ModelConfig::for_action_dim(2);
        config.feature_decoder_width = 8;
        config
    }

    #[test]
    fn the_decoder_starts_constant_and_follows_the_latent_through_a_reorientation() {
        let device = cpu_device();
        let config = decoder_config();
        // 16 keypoints' x and y.
        assert_eq!(config.encoder.keypoint_feature_count(), Some(32));
        let model = config.init(3, &device).expect("model");
        let frames = Tensor::<4>::random(
            [3, 3, 64, 64],
            burn::tensor::Distribution::Uniform(-0.5, 0.5),
            &device,
        );
        let (h, features) = model.encoder.forward_with_features(frames.clone());
        assert_eq!(
            to_vec(h.clone()),
            to_vec(model.encoder.forward(frames.clone()))
        );
        assert_eq!(features.expect("keypoint features").dims(), [3, 32]);
        let decoder = model.feature_decoder.as_ref().expect("decoder");
        assert!(to_vec(decoder.forward(h.clone())).iter().all(|&x| x == 0.0));

        // With a non-zero output layer, reorienting the latent (swap the axes, flip one) leaves
        // what the decoder makes of each frame unchanged.
        let mut model = config.init(3, &device).expect("model");
        model.feature_decoder = Some(super::FeatureDecoder::new(2, 8, 32, &device));
        let decode = |m: &crate::model::ProclModel| {
            let decoder = m.feature_decoder.as_ref().expect("decoder");
            to_vec(decoder.forward(m.encoder.forward(frames.clone())))
        };
        let before = decode(&model);
        assert!(before.iter().any(|&x| x != 0.0));
        let turned = model.reorient_latent(&[0.0, -1.0, 1.0, 0.0]);
        let h_turned = to_vec(turned.encoder.forward(frames.clone()));
        assert_ne!(h_turned, to_vec(h));
        for (a, b) in decode(&turned).iter().zip(&before) {
            assert!((a - b).abs() < 1e-5, "{a} vs {b}");
        }
    }

    #[test]
    fn the_decoder_needs_the_keypoint_head_and_is_absent_from_earlier_configs() {
        let mut config = decoder_config();
        config.encoder.head = EncoderHead::Mlp { hidden: 16 };
        let err = config.validate().unwrap_err().to_string();
        assert!(err.contains("model.feature_decoder_width"), "{err}");
        // Without it the config serialises as before, so earlier runs' config.json compare equal.
        let plain = serde_json::to_string(&ModelConfig::for_action_dim(2)).expect("json");
        assert!(!plain.contains("feature_decoder_width"), "{plain}");
        let read: ModelConfig = serde_json::from_str(&plain).expect("read back");
        assert_eq!(read.feature_decoder_width, 0);
        let model = read.init(0, &cpu_device()).expect("model");
        assert!(model.feature_decoder.is_none());
    }
}
