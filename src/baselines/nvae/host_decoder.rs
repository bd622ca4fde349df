//! The decoder's convolutions and the reconstruction term on the CPU for training. Each chunk
//! of frames runs the three upsample-and-convolve layers forward, scores its frames and runs
//! the layers backward in one pass, as packed GEMMs ([`TapeLayer`]). burn's graph keeps the
//! dense layers up to the 8x8 feature maps; their gradient enters it through a term whose
//! value is 0 and whose gradient is the host's, and the convolutions' parameter gradients are
//! written into burn's gradients after its `backward` ([`crate::model::HostBackward`]).
//!
//! burn's CPU backend runs these convolutions' backward passes as transposed convolutions with
//! layout copies and zero-filled buffers: most of a NewtonianVAE step. Chunks have a fixed size
//! and their sums are taken in chunk order, so a step's gradients do not depend on the number
//! of threads.

use burn::tensor::{Tensor, TensorData};
use rayon::prelude::*;

use super::model::{DECODER_BASE_PX, Decoder};
use crate::envs::{FRAME_BYTES, FRAME_PX};
use crate::model::{ConvGradient, Scratch, TapeLayer, pixel_inputs, to_vec, with_scratch};

/// Frames per chunk: one task of the thread pool, and the unit of the sums' order.
const CHUNK_FRAMES: usize = 8;

/// One chunk's share: its frames' summed squared error, the gradient of its feature maps in
/// burn's layout `[frames, c0, 8, 8]`, and each layer's (weight, bias) gradient in the host
/// layout.
struct ChunkResult {
    squared_error: f64,
    grad_maps: Vec<f32>,
    layers: Vec<(Vec<f32>, Vec<f32>)>,
}

impl Decoder {
    /// The reconstruction NLL of `targets` (RGB u8 frames) decoded from `x [n, du]`, as
    /// [`super::reconstruction_nll`] of [`Decoder::forward`] computes it, with the
    /// convolutions' parameter gradients, which burn's `backward` does not see.
    pub(crate) fn reconstruction_on_host(
        &self,
        x: Tensor<2>,
        targets: &[&[u8]],
        recon_std: f64,
    ) -> (Tensor<1>, Vec<ConvGradient>) {
        let maps = self.base_maps(x); // [n, c0 * 8 * 8]
        let [n, width] = maps.dims();
        let mut side = DECODER_BASE_PX;
        let layers: Vec<TapeLayer> = [
            (&self.conv1, true),
            (&self.conv2, true),
            (&self.conv3, false),
        ]
        .into_iter()
        .map(|(conv, relu)| {
            side *= 2;
            TapeLayer::new(conv, relu, side)
        })
        .collect();
        // d/dy of sum (t - y)^2 / (2 sigma^2 n).
        let scale = (1.0 / (recon_std * recon_std * n as f64)) as f32;
        let values = to_vec(maps.clone().detach());
        let chunks: Vec<ChunkResult> = values
            .par_chunks(CHUNK_FRAMES * width)
            .zip(targets.par_chunks(CHUNK_FRAMES))
            .map(|(maps, targets)| {
                with_scratch(|scratch| {
                    pulp::Arch::new().dispatch(DecodeChunk {
                        layers: &layers,
                        maps,
                        targets,
                        scale,
                        scratch,
                    })
                })
            })
            .collect();
        let mut squared_error = 0.0f64;
        let mut grad_maps = Vec::with_capacity(n * width);
        let mut sums: Vec<(Vec<f32>, Vec<f32>)> =
            layers.iter().map(TapeLayer::zero_gradients).collect();
        for chunk in chunks {
            squared_error += chunk.squared_error;
            grad_maps.extend_from_slice(&chunk.grad_maps);
            for ((weight, bias), (w, b)) in sums.iter_mut().zip(&chunk.layers) {
                weight.iter_mut().zip(w).for_each(|(sum, v)| *sum += v);
                bias.iter_mut().zip(b).for_each(|(sum, v)| *sum += v);
            }
        }
        let nll = squared_error / (2.0 * recon_std * recon_std * n as f64);
        let device = maps.device();
        let grad_maps = Tensor::<2>::from_data(TensorData::new(grad_maps, [n, width]), &device);
        // Zero in value, `grad_maps` in gradient.
        let carrier = ((maps.clone() - maps.detach()) * grad_maps).sum();
        let gradients = layers
            .iter()
            .zip(sums)
            .map(|(layer, (weight, bias))| layer.gradient(&weight, bias))
            .collect();
        (carrier + nll, gradients)
    }
}

/// [`decode_chunk`] compiled for the widest vector unit the CPU has, as the trunk's chunks are
/// ([`crate::model::TrunkTape`]).
struct DecodeChunk<'a> {
    layers: &'a [TapeLayer],
    maps: &'a [f32],
    targets: &'a [&'a [u8]],
    scale: f32,
    scratch: &'a mut Scratch,
}

impl pulp::WithSimd for DecodeChunk<'_> {
    type Output = ChunkResult;

    #[inline(always)]
    fn with_simd<S: pulp::Simd>(self, _simd: S) -> ChunkResult {
        decode_chunk(
            self.layers,
            self.maps,
            self.targets,
            self.scale,
            self.scratch,
        )
    }
}

/// One chunk forward, scored and backward. `maps` are the chunk's 8x8 feature maps in burn's
/// layout `[frames, c0, 8, 8]`; `scale` is the gradient of the loss per squared-error unit
/// halved (`1 / (sigma^2 n)`).
#[inline(always)]
fn decode_chunk(
    layers: &[TapeLayer],
    maps: &[f32],
    targets: &[&[u8]],
    scale: f32,
    scratch: &mut Scratch,
) -> ChunkResult {
    let frames = targets.len();
    let cells = DECODER_BASE_PX * DECODER_BASE_PX;
    let c0 = maps.len() / (frames * cells).max(1);
    // The host layout `[frames, cells, channels]`.
    let mut x = vec![0.0; maps.len()];
    for (out, from) in x
        .chunks_exact_mut(cells * c0)
        .zip(maps.chunks_exact(cells * c0))
    {
        for (cell, values) in out.chunks_exact_mut(c0).enumerate() {
            for (c, v) in values.iter_mut().enumerate() {
                *v = from[c * cells + cell];
            }
        }
    }
    // Each layer's upsampled input and its output (after its ReLU).
    let mut inputs = Vec::with_capacity(layers.len());
    let mut outputs: Vec<Vec<f32>> = Vec::with_capacity(layers.len());
    let mut side = DECODER_BASE_PX;
    for layer in layers {
        let from = outputs.last().unwrap_or(&x);
        let up = upsample2(from, frames, side);
        outputs.push(layer.forward(&up, frames, scratch));
        inputs.push(up);
        side *= 2;
    }
    // The frames' squared error and its gradient at the decoded means `[frames, 64^2, 3]`.
    let decoded = outputs.last().map_or(&[][..], |y| &y[..]);
    let mut grad = vec![0.0f32; decoded.len()];
    let mut target = vec![0.0f32; FRAME_BYTES];
    let mut squared_error = 0.0f64;
    for ((frame, y), g) in targets
        .iter()
        .zip(decoded.chunks_exact(FRAME_BYTES))
        .zip(grad.chunks_exact_mut(FRAME_BYTES))
    {
        pixel_inputs(frame, &mut target);
        let mut sum = 0.0f32;
        for ((&t, &y), g) in target.iter().zip(y).zip(g) {
            let d = y - t;
            sum += d * d;
            *g = d * scale;
        }
        squared_error += f64::from(sum);
    }
    let mut per_layer = Vec::with_capacity(layers.len());
    for (l, layer) in layers.iter().enumerate().rev() {
        if layer.relu() {
            for (g, &y) in grad.iter_mut().zip(&outputs[l]) {
                if y <= 0.0 {
                    *g = 0.0;
                }
            }
        }
        let (weight, bias, grad_input) = layer.backward(&inputs[l], &grad, frames, true, scratch);
        per_layer.push((weight, bias));
        side /= 2;
        let grad_up = grad_input.unwrap_or_default();
        grad = downsample2_sum(&grad_up, frames, side);
    }
    per_layer.reverse();
    // Back to burn's layout `[frames, c0, 8, 8]`.
    let mut grad_maps = vec![0.0; grad.len()];
    for (out, from) in grad_maps
        .chunks_exact_mut(cells * c0)
        .zip(grad.chunks_exact(cells * c0))
    {
        for (cell, values) in from.chunks_exact(c0).enumerate() {
            for (c, &v) in values.iter().enumerate() {
                out[c * cells + cell] = v;
            }
        }
    }
    debug_assert_eq!(side, DECODER_BASE_PX);
    debug_assert_eq!(FRAME_PX, DECODER_BASE_PX << layers.len());
    ChunkResult {
        squared_error,
        grad_maps,
        layers: per_layer,
    }
}

/// Nearest-neighbour 2x upsampling of `frames` maps `[side^2, channels]` (row-major cells).
#[inline(always)]
fn upsample2(x: &[f32], frames: usize, side: usize) -> Vec<f32> {
    let per_frame = x.len() / frames.max(1);
    let channels = per_frame / (side * side).max(1);
    let mut out = vec![0.0; 4 * x.len()];
    for (out, x) in out
        .chunks_exact_mut(4 * per_frame)
        .zip(x.chunks_exact(per_frame))
    {
        for (row, out_rows) in out.chunks_exact_mut(4 * side * channels).enumerate() {
            let (top, bottom) = out_rows.split_at_mut(2 * side * channels);
            let from = &x[row * side * channels..][..side * channels];
            for (pair, cell) in top
                .chunks_exact_mut(2 * channels)
                .zip(from.chunks_exact(channels))
            {
                pair[..channels].copy_from_slice(cell);
                pair[channels..].copy_from_slice(cell);
            }
            bottom.copy_from_slice(top);
        }
    }
    out
}

/// The gradient of [`upsample2`]'s input from its output's: each cell sums its 2x2 block.
/// `side` is the input's.
#[inline(always)]
fn downsample2_sum(grad: &[f32], frames: usize, side: usize) -> Vec<f32> {
    let per_frame = grad.len() / frames.max(1);
    let channels = per_frame / (4 * side * side).max(1);
    let mut out = vec![0.0; grad.len() / 4];
    let row = 2 * side * channels;
    for (out, grad) in out
        .chunks_exact_mut(per_frame / 4)
        .zip(grad.chunks_exact(per_frame))
    {
        for (y, out_row) in out.chunks_exact_mut(side * channels).enumerate() {
            let top = &grad[2 * y * row..][..row];
            let bottom = &grad[(2 * y + 1) * row..][..row];
            for (x, cell) in out_row.chunks_exact_mut(channels).enumerate() {
                let at = 2 * x * channels;
                for (c, v) in cell.iter_mut().enumerate() {
                    *v = top[at + c]
                        + top[at + channels + c]
                        + bottom[at + c]
                        + bottom[at + channels + c];
                }
            }
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use burn::module::{Module, ModuleVisitor, Param};
    use burn::tensor::Gradients;

    use super::*;
    use crate::baselines::nvae::model::tests::tiny;
    use crate::baselines::nvae::reconstruction_nll;
    use crate::model::{HostBackward, cpu_device, frames_to_tensor};

    #[test]
    fn upsampling_repeats_cells_and_its_gradient_sums_blocks() {
        // One frame, 2x2 cells, 2 channels: cell k holds (k, 10 k).
        let x = [0.0, 0.0, 1.0, 10.0, 2.0, 20.0, 3.0, 30.0];
        let up = upsample2(&x, 1, 2);
        // Row 0 of the 4x4 output: cells 0, 0, 1, 1; row 2: cells 2, 2, 3, 3.
        assert_eq!(&up[..8], &[0.0, 0.0, 0.0, 0.0, 1.0, 10.0, 1.0, 10.0]);
        assert_eq!(&up[8..16], &up[..8]);
        assert_eq!(&up[16..24], &[2.0, 20.0, 2.0, 20.0, 3.0, 30.0, 3.0, 30.0]);
        // Summing the blocks of the upsampled map gives 4 x.
        let sums = downsample2_sum(&up, 1, 2);
        let four: Vec<f32> = x.iter().map(|v| 4.0 * v).collect();
        assert_eq!(sums, four);
    }

    /// Every float parameter's gradient (flattened), in visiting order.
    struct CollectGrads<'a> {
        grads: &'a Gradients,
        out: Vec<Vec<f32>>,
    }

    impl ModuleVisitor for CollectGrads<'_> {
        fn visit_float<const D: usize>(&mut self, param: &Param<Tensor<D>>) {
            self.out
                .push(param.val().grad(self.grads).map(to_vec).unwrap_or_default());
        }
    }

    #[test]
    fn host_reconstruction_matches_burns_value_and_gradients() {
        let device = cpu_device().autodiff();
        let model = tiny().init(3, &device).unwrap();
        let decoder = model.decoder;
        // 11 frames: one full chunk and a partial one.
        let n = 11;
        let x_values: Vec<f32> = (0..n * 2)
            .map(|k| ((k * 37 % 23) as f32 - 11.0) / 7.0)
            .collect();
        let x = Tensor::<2>::from_data(TensorData::new(x_values, [n, 2]), &device).require_grad();
        let frames: Vec<Vec<u8>> = (0..n)
            .map(|f| {
                (0..FRAME_BYTES)
                    .map(|i| ((i * 7 + f * 31) % 256) as u8)
                    .collect()
            })
            .collect();
        let frames: Vec<&[u8]> = frames.iter().map(|f| &f[..]).collect();
        let recon_std = 0.2;

        let targets = frames_to_tensor(frames.iter().copied(), &device);
        let burn_nll = reconstruction_nll(decoder.forward(x.clone()), targets, recon_std);
        let burn_grads = burn_nll.backward();
        let mut burn = CollectGrads {
            grads: &burn_grads,
            out: vec![],
        };
        decoder.visit(&mut burn);
        let burn_x = to_vec(x.grad(&burn_grads).unwrap());

        let (host_nll, convs) = decoder.reconstruction_on_host(x.clone(), &frames, recon_std);
        let mut host_grads = host_nll.backward();
        let host_x = to_vec(x.grad(&host_grads).unwrap());
        HostBackward { trunk: None, convs }.backward(&mut host_grads);
        let mut host = CollectGrads {
            grads: &host_grads,
            out: vec![],
        };
        decoder.visit(&mut host);

        let (a, b) = (to_vec(burn_nll)[0], to_vec(host_nll)[0]);
        assert!((a - b).abs() <= 1e-5 * a.abs(), "nll {a} vs {b}");
        let close = |name: &str, want: &[f32], got: &[f32]| {
            assert_eq!(want.len(), got.len(), "{name}");
            let scale = want.iter().fold(0.0f32, |m, v| m.max(v.abs()));
            assert!(scale > 0.0, "{name}: no gradient");
            for (w, g) in want.iter().zip(got) {
                assert!((w - g).abs() <= 1e-4 * scale, "{name}: {w} vs {g}");
            }
        };
        close("x", &burn_x, &host_x);
        assert_eq!(burn.out.len(), host.out.len());
        for (k, (want, got)) in burn.out.iter().zip(&host.out).enumerate() {
            close(&format!("parameter {k}"), want, got);
        }
    }
}
