//! The encoder trunk's training path on the CPU: its convolutions forward and backward as
//! packed GEMMs over fixed chunks of frames, joined to burn's autodiff at the trunk's output.
//!
//! burn's CPU backend runs a convolution's backward as transposed convolutions with layout
//! copies and elementwise passes over every activation, most of a training step. Here each
//! layer costs one GEMM forward and two backward per chunk of frames (the im2col matrices are
//! rebuilt from the kept activations rather than stored). The trunk's output enters burn's
//! graph as a leaf; after `backward` its gradient is carried back through the layers here and
//! its parameters' gradients are written into burn's [`Gradients`], where the optimiser finds
//! them as it finds any other.
//!
//! Chunks have a fixed size and their weight gradients are summed in chunk order, so a step's
//! gradients do not depend on the number of threads.

use burn::nn::conv::Conv2d;
use burn::tensor::{Device, Gradients, Tensor, TensorData};
use rayon::prelude::*;

use super::host_encoder::{HostConv, add_bias, gemm_into, gemm_strided};
use super::polar_reference::PolarReference;
use super::soft_argmax::soft_argmax;
use crate::envs::{FRAME_BYTES, FRAME_PX};

/// Frames per chunk: one task of the thread pool, and the unit of the gradient sum's order.
const CHUNK_FRAMES: usize = 8;

/// A layer of the trunk: a convolution and whether a ReLU follows it.
pub(crate) struct TrunkLayer<'a> {
    pub conv: &'a Conv2d,
    pub relu: bool,
}

/// The spatial soft-argmax after the last layer: each map's softmax attention
/// `softmax(beta_k m)` over the cells, and its expectation of each grid.
pub(crate) struct TrunkSoftArgmax {
    /// `log beta`, `[K]` (a parameter).
    pub log_sharpness: Tensor<1>,
    /// The grids `[cells]` each.
    pub grids: Vec<Vec<f32>>,
    /// Under a moving cut, what gives each frame its own first (angle) grid.
    pub reference: Option<PolarReference>,
}

/// What runs on the host: the layers, then optionally the soft-argmax.
pub(crate) struct Trunk<'a> {
    pub layers: Vec<TrunkLayer<'a>>,
    pub soft_argmax: Option<TrunkSoftArgmax>,
}

/// The trunk's forward pass over one batch of frames, kept for its backward pass.
pub struct TrunkTape {
    layers: Vec<TapeLayer>,
    soft_argmax: Option<SoftArgmaxTape>,
    chunks: Vec<ChunkTape>,
    /// The trunk's output as burn sees it, a leaf the head's graph starts from: the last
    /// layer's output `[n, C, s, s]` or the soft-argmax's expectations `[n, K, G]`.
    output: TrunkOutput,
}

/// The trunk's output (see [`TrunkTape::output`]).
#[derive(Clone)]
pub enum TrunkOutput {
    /// The last layer's output `[n, C, s, s]`.
    Maps(Tensor<4>),
    /// The soft-argmax's expectations `[n, K, G]`: keypoint by keypoint, grid by grid.
    Expectations(Tensor<3>),
}

struct SoftArgmaxTape {
    log_sharpness: Tensor<1>,
    /// `beta_k`.
    sharpness: Vec<f32>,
    grids: Vec<Vec<f32>>,
    reference: Option<PolarReference>,
}

pub(crate) struct TapeLayer {
    conv: HostConv,
    relu: bool,
    /// Side of the layer's input.
    side: usize,
    /// The parameters, to address their gradients in burn's [`Gradients`].
    weight: Tensor<4>,
    bias: Option<Tensor<1>>,
}

struct ChunkTape {
    frames: usize,
    /// The network input `[frames, 64 * 64, 3]`.
    input: Vec<f32>,
    /// Each layer's output `[frames, side^2, channels]`, after its ReLU.
    outputs: Vec<Vec<f32>>,
    /// With the soft-argmax: the attention `[frames, cells, K]` and the expectations
    /// `[frames, K, G]`.
    attention: Vec<f32>,
    expectations: Vec<f32>,
    /// Under a moving cut, each frame's angle grid `[frames, cells]`.
    angle_grids: Vec<f32>,
}

impl SoftArgmaxTape {
    /// Each frame's angle grid `[frames, cells]` from its network inputs, under a moving cut
    /// (empty without one).
    fn angle_grids(&self, input: &[f32], frames: usize) -> Vec<f32> {
        let Some(reference) = &self.reference else {
            return Vec::new();
        };
        let cells = reference.cells();
        let mut grids = vec![0.0; frames * cells];
        for (x, grid) in input
            .chunks_exact(FRAME_BYTES)
            .zip(grids.chunks_exact_mut(cells))
        {
            reference.angle_grid(reference.direction(x), grid);
        }
        grids
    }

    /// The grids of frame `frame`: the fixed ones, the first replaced by the frame's own
    /// under a moving cut (`frame_grids` holds them).
    fn frame_grids<'a>(
        &'a self,
        angle_grids: &[f32],
        frame: usize,
        frame_grids: &'a mut Vec<Vec<f32>>,
    ) -> &'a [Vec<f32>] {
        if angle_grids.is_empty() {
            return &self.grids;
        }
        if frame_grids.is_empty() {
            frame_grids.clone_from(&self.grids);
        }
        let cells = frame_grids[0].len();
        frame_grids[0].copy_from_slice(&angle_grids[frame * cells..][..cells]);
        frame_grids
    }

    /// Attention and expectations of `frames` maps `[frames, cells, K]`.
    #[inline(always)]
    fn forward(&self, maps: &[f32], angle_grids: &[f32], frames: usize) -> (Vec<f32>, Vec<f32>) {
        let k = self.sharpness.len();
        let cells = maps.len() / (frames * k).max(1);
        let g = self.grids.len();
        let mut attention = vec![0.0; frames * k * cells];
        let mut expectations = vec![0.0; frames * k * g];
        let mut frame_grids = Vec::new();
        for (frame, maps) in maps.chunks_exact(cells * k).enumerate() {
            soft_argmax(
                maps,
                &self.sharpness,
                self.frame_grids(angle_grids, frame, &mut frame_grids),
                &mut attention[frame * k * cells..][..k * cells],
                &mut expectations[frame * k * g..][..k * g],
            );
        }
        (attention, expectations)
    }

    /// From the gradient of the expectations `[frames, K, G]`: the gradient of the maps
    /// `[frames, cells, K]` and of `log beta` (summed over the frames). With
    /// `s_c = sum_g dE_g (grid_g[c] - E_g)`, `dm_c = beta a_c s_c` and
    /// `d log beta = beta sum_c m_c a_c s_c`.
    #[inline(always)]
    fn backward(&self, chunk: &ChunkTape, grad: &[f32]) -> (Vec<f32>, Vec<f64>) {
        let k = self.sharpness.len();
        let g = self.grids.len();
        let maps = chunk.outputs.last().map_or(&[][..], |v| &v[..]);
        let cells = maps.len() / (chunk.frames * k).max(1);
        let mut grad_maps = vec![0.0; maps.len()];
        let mut grad_log_sharpness = vec![0.0f64; k];
        // Cell by cell with the keys side by side, as the forward pass; each key's terms are
        // formed and summed in the same order as a key-by-key loop would.
        let (mut offset, mut s, mut grad_beta) = (vec![0.0f32; k], vec![0.0f32; k], vec![0.0; k]);
        // `dE [G, K]`: the frame's expectation gradients, grid by grid.
        let mut de_by_grid = vec![0.0f32; g * k];
        let mut frame_grids = Vec::new();
        for frame in 0..chunk.frames {
            let grids = self.frame_grids(&chunk.angle_grids, frame, &mut frame_grids);
            let per_frame = cells * k;
            let maps = &maps[frame * per_frame..][..per_frame];
            let attention = &chunk.attention[frame * per_frame..][..per_frame];
            let grad_maps = &mut grad_maps[frame * per_frame..][..per_frame];
            for key in 0..k {
                let e = &chunk.expectations[(frame * k + key) * g..][..g];
                let de = &grad[(frame * k + key) * g..][..g];
                offset[key] = de.iter().zip(e).map(|(d, e)| d * e).sum();
                for (grid, &d) in de.iter().enumerate() {
                    de_by_grid[grid * k + key] = d;
                }
            }
            grad_beta.fill(0.0f64);
            let rows = attention.chunks_exact(k).zip(maps.chunks_exact(k));
            for (cell, ((a, m), dm)) in rows.zip(grad_maps.chunks_exact_mut(k)).enumerate() {
                s.iter_mut().zip(&offset).for_each(|(s, &o)| *s = -o);
                for (grid, de) in grids.iter().zip(de_by_grid.chunks_exact(k)) {
                    let x = grid[cell];
                    s.iter_mut().zip(de).for_each(|(s, &d)| *s += d * x);
                }
                let keys = a.iter().zip(m).zip(&s).zip(&self.sharpness);
                for ((((&a, &m), &s), &beta), (dm, gb)) in
                    keys.zip(dm.iter_mut().zip(&mut grad_beta))
                {
                    let t = a * s;
                    *dm = beta * t;
                    *gb += f64::from(m * t);
                }
            }
            for ((sum, &beta), &gb) in grad_log_sharpness
                .iter_mut()
                .zip(&self.sharpness)
                .zip(&grad_beta)
            {
                *sum += f64::from(beta) * gb;
            }
        }
        (grad_maps, grad_log_sharpness)
    }
}

impl TapeLayer {
    /// `conv` (and a ReLU after it when `relu`) on inputs of side `side`.
    pub(crate) fn new(conv: &Conv2d, relu: bool, side: usize) -> Self {
        Self {
            side,
            relu,
            weight: conv.weight.val(),
            bias: conv.bias.as_ref().map(|b| b.val()),
            conv: HostConv::from_conv(conv),
        }
    }

    pub(crate) fn out_side(&self) -> usize {
        self.conv.out_side(self.side)
    }

    /// Whether a ReLU follows the convolution.
    pub(crate) fn relu(&self) -> bool {
        self.relu
    }

    /// Zero gradients in the host layout: `[out, width]` for the weight, `[out]` for the bias.
    pub(crate) fn zero_gradients(&self) -> (Vec<f32>, Vec<f32>) {
        (
            vec![0.0; self.conv.weight.len()],
            vec![0.0; self.conv.bias.len()],
        )
    }

    /// The parameters' gradients from their sums in the host layout (see [`Self::backward`]).
    pub(crate) fn gradient(&self, weight: &[f32], bias: Vec<f32>) -> ConvGradient {
        ConvGradient {
            weight: self.weight.clone(),
            bias: self.bias.clone(),
            weight_grad: self.conv.weight_to_burn_layout(weight),
            bias_grad: bias,
        }
    }

    /// The layer's output for `frames` inputs `[frames, side^2, in]`.
    #[inline(always)]
    pub(crate) fn forward(&self, input: &[f32], frames: usize, scratch: &mut Scratch) -> Vec<f32> {
        let [cin, cout] = self.conv.channels;
        let rows = frames * self.out_side().pow(2);
        let mut out = vec![0.0; rows * cout];
        if self.conv.is_pointwise() {
            gemm_into(&mut out, input, &self.conv.weight, rows, cin, cout);
        } else {
            let columns = self.columns(&mut scratch.columns, input, frames);
            gemm_into(
                &mut out,
                columns,
                &self.conv.weight,
                rows,
                self.conv.width(),
                cout,
            );
        }
        add_bias(&mut out, &self.conv.bias, self.relu);
        out
    }

    /// The im2col matrix `[frames * out_side^2, width]` of `frames` inputs, in the buffer
    /// `buffers` keeps for this layer's geometry.
    #[inline(always)]
    fn columns<'a>(
        &self,
        buffers: &'a mut Vec<([usize; 5], Vec<f32>)>,
        input: &[f32],
        frames: usize,
    ) -> &'a [f32] {
        let conv = &self.conv;
        let key = [
            self.side,
            conv.kernel,
            conv.stride,
            conv.padding,
            conv.channels[0],
        ];
        let index = match buffers.iter().position(|(k, _)| *k == key) {
            Some(index) => index,
            None => {
                buffers.push((key, Vec::new()));
                buffers.len() - 1
            }
        };
        let per_input = self.side.pow(2) * conv.channels[0];
        let per_frame = self.out_side().pow(2) * conv.width();
        let buffer = &mut buffers[index].1;
        if buffer.len() < frames * per_frame {
            buffer.resize(frames * per_frame, 0.0);
        }
        let columns = &mut buffer[..frames * per_frame];
        for (frame, block) in columns.chunks_exact_mut(per_frame).enumerate() {
            conv.im2col(&input[frame * per_input..][..per_input], self.side, block);
        }
        columns
    }

    /// From the gradient `grad_out [frames * out_side^2, out]` of the layer's output before
    /// its ReLU: the weight gradient (`[out, width]`, the host layout), the bias gradient and,
    /// when `input_grad`, the gradient of the input `[frames, side^2, in]`.
    #[inline(always)]
    pub(crate) fn backward(
        &self,
        input: &[f32],
        grad_out: &[f32],
        frames: usize,
        input_grad: bool,
        scratch: &mut Scratch,
    ) -> (Vec<f32>, Vec<f32>, Option<Vec<f32>>) {
        let [cin, cout] = self.conv.channels;
        let width = self.conv.width();
        let cells = self.out_side().pow(2);
        let rows = frames * cells;
        // Summed in f64: a bias gathers one term per output cell of every frame.
        let mut bias = vec![0.0f64; cout];
        for row in grad_out.chunks_exact(cout) {
            for (b, &g) in bias.iter_mut().zip(row) {
                *b += f64::from(g);
            }
        }
        let bias: Vec<f32> = bias.into_iter().map(|b| b as f32).collect();
        let Scratch {
            columns,
            grad_columns,
        } = scratch;
        let columns = if self.conv.is_pointwise() {
            input
        } else {
            self.columns(columns, input, frames)
        };
        // dW [out, width] = grad_out^T [out, rows] . columns [rows, width]
        let mut weight = vec![0.0; cout * width];
        gemm_strided(
            &mut weight,
            [cout, width, rows],
            (grad_out, [cout, 1]),
            (columns, [1, width]),
        );
        if !input_grad {
            return (weight, bias, None);
        }
        // d columns [rows, width] = grad_out [rows, out] . W [out, width], overwritten
        // whole.
        if grad_columns.len() < rows * width {
            grad_columns.resize(rows * width, 0.0);
        }
        let grad_columns = &mut grad_columns[..rows * width];
        gemm_strided(
            grad_columns,
            [rows, width, cout],
            (grad_out, [1, cout]),
            (&self.conv.weight, [1, width]),
        );
        if self.conv.is_pointwise() {
            return (weight, bias, Some(grad_columns.to_vec()));
        }
        // col2im: each patch entry's gradient goes back to the input entry it was copied
        // from.
        let per_input = self.side.pow(2) * cin;
        let per_frame = cells * width;
        let mut grad_input = vec![0.0; frames * per_input];
        for (frame, grad) in grad_input.chunks_exact_mut(per_input).enumerate() {
            let block = &grad_columns[frame * per_frame..][..per_frame];
            self.conv
                .for_each_patch_run(self.side, |column, from, len| {
                    for (g, c) in grad[from..][..len].iter_mut().zip(&block[column..][..len]) {
                        *g += c;
                    }
                });
        }
        (weight, bias, Some(grad_input))
    }
}

/// A convolution's parameter gradients computed on the host, to be written into burn's
/// [`Gradients`] after its `backward`.
#[derive(Debug, Clone)]
pub(crate) struct ConvGradient {
    /// The parameters, to address their gradients.
    weight: Tensor<4>,
    bias: Option<Tensor<1>>,
    /// burn's layout `[out, in, kh, kw]`.
    weight_grad: Vec<f32>,
    bias_grad: Vec<f32>,
}

impl ConvGradient {
    pub(crate) fn write(self, grads: &mut Gradients) {
        let device = self.weight.device().without_autodiff();
        let dims = self.weight.dims();
        let weight = Tensor::from_data(TensorData::new(self.weight_grad, dims), &device);
        self.weight.grad_replace(grads, weight);
        if let Some(param) = &self.bias {
            let len = self.bias_grad.len();
            let bias = Tensor::from_data(TensorData::new(self.bias_grad, [len]), &device);
            param.grad_replace(grads, bias);
        }
    }
}

/// What a training step computed outside burn's graph and still owes burn's [`Gradients`]
/// after `backward`: the encoder trunk's tape, and gradients the host already has (the
/// NewtonianVAE decoder's, whose loss is scored on the host).
pub struct HostBackward {
    pub(crate) trunk: Option<TrunkTape>,
    pub(crate) convs: Vec<ConvGradient>,
}

impl HostBackward {
    /// Completes `grads`: writes the host's gradients and carries the trunk's back.
    pub fn backward(self, grads: &mut Gradients) {
        for conv in self.convs {
            conv.write(grads);
        }
        if let Some(trunk) = self.trunk {
            trunk.backward(grads);
        }
    }
}

impl From<Option<TrunkTape>> for HostBackward {
    fn from(trunk: Option<TrunkTape>) -> Self {
        Self {
            trunk,
            convs: Vec::new(),
        }
    }
}

/// Buffers a thread keeps between chunks.
#[derive(Default)]
pub(crate) struct Scratch {
    /// im2col matrices by layer geometry: their padding entries stay 0 between uses, so they
    /// are never zeroed again.
    columns: Vec<([usize; 5], Vec<f32>)>,
    /// The gradient of an im2col matrix, overwritten whole by its GEMM.
    grad_columns: Vec<f32>,
}

thread_local! {
    static SCRATCH: std::cell::RefCell<Scratch> = std::cell::RefCell::new(Scratch::default());
}

/// Runs `f` with this thread's [`Scratch`]. Call the vector-unit dispatch inside `f`, with the
/// scratch as an argument (see [`ForwardChunk`]).
pub(crate) fn with_scratch<R>(f: impl FnOnce(&mut Scratch) -> R) -> R {
    SCRATCH.with_borrow_mut(f)
}

/// Per chunk: per layer (weight, bias) gradients, and the gradient of `log beta`.
type Partial = (Vec<(Vec<f32>, Vec<f32>)>, Vec<f64>);

/// [`forward_chunk`] compiled again for the widest vector unit the CPU has, picked at run
/// time. A struct, not a closure: a closure reaches the dispatch through `FnOnce::call_once`'s
/// shim, which is compiled once for baseline x86-64 (see `host_encoder::Encode`). For the
/// same reason the thread's scratch comes in as an argument: code inside `LocalKey::with`'s
/// closure is compiled outside the dispatch too.
struct ForwardChunk<'a> {
    layers: &'a [TapeLayer],
    soft_argmax: Option<&'a SoftArgmaxTape>,
    chunk: &'a [&'a [u8]],
    scratch: &'a mut Scratch,
}

impl pulp::WithSimd for ForwardChunk<'_> {
    type Output = ChunkTape;

    #[inline(always)]
    fn with_simd<S: pulp::Simd>(self, _simd: S) -> ChunkTape {
        forward_chunk(self.layers, self.soft_argmax, self.chunk, self.scratch)
    }
}

/// [`backward_chunk`] compiled for the widest vector unit, as [`ForwardChunk`].
struct BackwardChunk<'a> {
    layers: &'a [TapeLayer],
    soft_argmax: Option<&'a SoftArgmaxTape>,
    chunk: &'a ChunkTape,
    grad_output: &'a [f32],
    first: usize,
    scratch: &'a mut Scratch,
}

impl pulp::WithSimd for BackwardChunk<'_> {
    type Output = Partial;

    #[inline(always)]
    fn with_simd<S: pulp::Simd>(self, _simd: S) -> Partial {
        backward_chunk(
            self.layers,
            self.soft_argmax,
            self.chunk,
            self.grad_output,
            self.first,
            self.scratch,
        )
    }
}

/// One chunk's forward pass: the pixels as network input, each layer, the soft-argmax.
#[inline(always)]
fn forward_chunk(
    layers: &[TapeLayer],
    soft_argmax: Option<&SoftArgmaxTape>,
    chunk: &[&[u8]],
    scratch: &mut Scratch,
) -> ChunkTape {
    let mut input = vec![0.0; chunk.len() * FRAME_BYTES];
    for (x, frame) in input.chunks_exact_mut(FRAME_BYTES).zip(chunk) {
        super::pixel_inputs(frame, x);
    }
    let mut outputs: Vec<Vec<f32>> = Vec::with_capacity(layers.len());
    for layer in layers {
        let x = outputs.last().unwrap_or(&input);
        let y = layer.forward(x, chunk.len(), scratch);
        outputs.push(y);
    }
    let (attention, expectations, angle_grids) = match (soft_argmax, outputs.last()) {
        (Some(stage), Some(maps)) => {
            let angle_grids = stage.angle_grids(&input, chunk.len());
            let (attention, expectations) = stage.forward(maps, &angle_grids, chunk.len());
            (attention, expectations, angle_grids)
        }
        _ => (Vec::new(), Vec::new(), Vec::new()),
    };
    ChunkTape {
        frames: chunk.len(),
        input,
        outputs,
        attention,
        expectations,
        angle_grids,
    }
}

/// One chunk's backward pass from the gradient of the trunk's output (`grad_output`, the whole
/// batch's; the chunk's frames start at `first`): per layer the (weight, bias) gradients, and
/// the gradient of `log beta`.
#[inline(always)]
fn backward_chunk(
    layers: &[TapeLayer],
    soft_argmax: Option<&SoftArgmaxTape>,
    chunk: &ChunkTape,
    grad_output: &[f32],
    first: usize,
    scratch: &mut Scratch,
) -> Partial {
    let Some(last) = layers.last() else {
        return (Vec::new(), Vec::new());
    };
    let channels = last.conv.channels[1];
    let cells = last.out_side().pow(2);
    // The gradient of the last layer's output, in the host layout
    // `[frames, cells, C]`.
    let (mut grad, grad_log_sharpness) = match soft_argmax {
        Some(stage) => {
            let per_frame = stage.sharpness.len() * stage.grids.len();
            let from = &grad_output[first * per_frame..][..chunk.frames * per_frame];
            stage.backward(chunk, from)
        }
        None => {
            let mut grad = vec![0.0; chunk.frames * cells * channels];
            for (frame, rows) in grad.chunks_exact_mut(cells * channels).enumerate() {
                let from = &grad_output[(first + frame) * channels * cells..];
                for (cell, values) in rows.chunks_exact_mut(channels).enumerate() {
                    for (c, v) in values.iter_mut().enumerate() {
                        *v = from[c * cells + cell];
                    }
                }
            }
            (grad, Vec::new())
        }
    };
    let mut per_layer = Vec::with_capacity(layers.len());
    for (l, layer) in layers.iter().enumerate().rev() {
        if layer.relu {
            for (g, &y) in grad.iter_mut().zip(&chunk.outputs[l]) {
                if y <= 0.0 {
                    *g = 0.0;
                }
            }
        }
        let input = if l == 0 {
            &chunk.input
        } else {
            &chunk.outputs[l - 1]
        };
        let (weight, bias, grad_input) = layer.backward(input, &grad, chunk.frames, l > 0, scratch);
        per_layer.push((weight, bias));
        if let Some(g) = grad_input {
            grad = g;
        }
    }
    per_layer.reverse();
    (per_layer, grad_log_sharpness)
}

impl TrunkTape {
    /// Runs `trunk` over `frames` (RGB u8, 64x64) and keeps what its backward pass needs.
    pub(crate) fn forward(trunk: Trunk, frames: &[&[u8]], device: &Device) -> Self {
        let mut side = FRAME_PX;
        let layers: Vec<TapeLayer> = trunk
            .layers
            .iter()
            .map(|layer| {
                let tape = TapeLayer::new(layer.conv, layer.relu, side);
                side = tape.out_side();
                tape
            })
            .collect();
        let soft_argmax = trunk.soft_argmax.map(|stage| SoftArgmaxTape {
            sharpness: super::to_vec(stage.log_sharpness.clone().exp()),
            log_sharpness: stage.log_sharpness,
            grids: stage.grids,
            reference: stage.reference,
        });
        let chunks: Vec<ChunkTape> = frames
            .par_chunks(CHUNK_FRAMES)
            .map(|chunk| {
                SCRATCH.with_borrow_mut(|scratch| {
                    pulp::Arch::new().dispatch(ForwardChunk {
                        layers: &layers,
                        soft_argmax: soft_argmax.as_ref(),
                        chunk,
                        scratch,
                    })
                })
            })
            .collect();
        let n = frames.len();
        let output = if let Some(stage) = &soft_argmax {
            let (k, g) = (stage.sharpness.len(), stage.grids.len());
            let data: Vec<f32> = chunks
                .iter()
                .flat_map(|chunk| chunk.expectations.iter().copied())
                .collect();
            TrunkOutput::Expectations(
                Tensor::from_data(TensorData::new(data, [n, k, g]), device).require_grad(),
            )
        } else {
            let channels = layers.last().map_or(3, |layer| layer.conv.channels[1]);
            let cells = side * side;
            // burn's layout `[n, C, s, s]`: channel-major per frame.
            let mut data = vec![0.0; n * channels * cells];
            data.par_chunks_mut(CHUNK_FRAMES * channels * cells)
                .zip(&chunks)
                .for_each(|(out, chunk)| {
                    let last = chunk.outputs.last().unwrap_or(&chunk.input);
                    for (frame, out) in out.chunks_exact_mut(channels * cells).enumerate() {
                        let y = &last[frame * cells * channels..][..cells * channels];
                        for (cell, values) in y.chunks_exact(channels).enumerate() {
                            for (c, &v) in values.iter().enumerate() {
                                out[c * cells + cell] = v;
                            }
                        }
                    }
                });
            TrunkOutput::Maps(
                Tensor::from_data(TensorData::new(data, [n, channels, side, side]), device)
                    .require_grad(),
            )
        };
        Self {
            layers,
            soft_argmax,
            chunks,
            output,
        }
    }

    /// The trunk's output, a graph leaf.
    pub fn output(&self) -> TrunkOutput {
        self.output.clone()
    }

    /// Carries the gradient `backward` left at [`Self::output`] back through the trunk and
    /// writes its parameters' gradients into `grads` (nothing when the loss did not depend on
    /// the output).
    pub fn backward(self, grads: &mut Gradients) {
        let grad_output = match &self.output {
            TrunkOutput::Maps(leaf) => leaf.grad_remove(grads).map(super::to_vec),
            TrunkOutput::Expectations(leaf) => leaf.grad_remove(grads).map(super::to_vec),
        };
        let Some(grad_output) = grad_output else {
            return;
        };
        let layers = &self.layers;
        let soft_argmax = &self.soft_argmax;
        let partials: Vec<Partial> = self
            .chunks
            .par_iter()
            .enumerate()
            .map(|(index, chunk)| {
                let from = index * CHUNK_FRAMES;
                SCRATCH.with_borrow_mut(|scratch| {
                    pulp::Arch::new().dispatch(BackwardChunk {
                        layers,
                        soft_argmax: soft_argmax.as_ref(),
                        chunk,
                        grad_output: &grad_output,
                        first: from,
                        scratch,
                    })
                })
            })
            .collect();
        for (l, layer) in self.layers.iter().enumerate() {
            let (mut weight, mut bias) = layer.zero_gradients();
            for (partial, _) in &partials {
                let (w, b) = &partial[l];
                weight.iter_mut().zip(w).for_each(|(sum, v)| *sum += v);
                bias.iter_mut().zip(b).for_each(|(sum, v)| *sum += v);
            }
            layer.gradient(&weight, bias).write(grads);
        }
        if let Some(stage) = &self.soft_argmax {
            let k = stage.sharpness.len();
            let mut sum = vec![0.0f64; k];
            for (_, partial) in &partials {
                sum.iter_mut().zip(partial).for_each(|(s, v)| *s += v);
            }
            let sum: Vec<f32> = sum.into_iter().map(|v| v as f32).collect();
            let device = stage.log_sharpness.device().without_autodiff();
            stage
                .log_sharpness
                .grad_replace(grads, Tensor::from_data(TensorData::new(sum, [k]), &device));
        }
    }
}

#[cfg(test)]
mod tests {
    use std::collections::BTreeMap;

    use burn::module::{Module, ModuleVisitor, Param};
    use burn::tensor::{Gradients, Tensor, TensorData};

    use crate::model::{Encoder, cpu_device, frames_to_tensor, to_vec};
    use crate::train::{Method, TrainConfig};

    /// Every parameter's gradient by path.
    struct CollectGrads<'a> {
        grads: &'a Gradients,
        path: Vec<String>,
        out: BTreeMap<String, Vec<f32>>,
    }

    impl ModuleVisitor for CollectGrads<'_> {
        fn enter_module(&mut self, name: &str, _: &str) {
            self.path.push(name.to_string());
        }
        fn exit_module(&mut self, _: &str, _: &str) {
            self.path.pop();
        }
        fn visit_float<const D: usize>(&mut self, param: &Param<Tensor<D>>) {
            if let Some(grad) = param.val().grad(self.grads) {
                self.out.insert(self.path.join("."), to_vec(grad));
            }
        }
    }

    fn grads_of(encoder: &Encoder, grads: &Gradients) -> BTreeMap<String, Vec<f32>> {
        let mut collect = CollectGrads {
            grads,
            path: vec![],
            out: BTreeMap::new(),
        };
        encoder.visit(&mut collect);
        collect.out
    }

    /// The host trunk's forward pass and gradients are burn's, to 1e-5 of each gradient's
    /// largest entry, for every shipped head: the point mass's Cartesian keypoints, the
    /// reacher's polar keypoints with pairwise angles over 32x32 cells (also under a moving
    /// cut), and the paper's MLP head. The loss weighs each latent entry differently, and the
    /// batch (19 frames) leaves a short last chunk.
    #[test]
    fn trunk_gradients_match_burns() {
        let device = cpu_device().autodiff();
        let moving_cut = (crate::envs::EnvKind::Reacher, crate::train::Preset::Procl);
        let cases = crate::model::SHIPPED_HEADS.into_iter().map(|c| (c, false));
        for ((env, preset), moving) in cases.chain([(moving_cut, true)]) {
            let mut config = TrainConfig::preset(preset, Method::Procl, env);
            config.model.encoder.polar_moving_cut = moving;
            // The presets start the pairwise angles' weights at 0; here they reach `h`.
            config.model.encoder.pairwise_init_scale = 1.0;
            let frames = crate::model::start_frames(env, 19);
            let frames: Vec<&[u8]> = frames.iter().map(|f| &f[..]).collect();
            let encoder = config.model.init(5, &device).expect("model").encoder;
            let encoder = encoder.place_moving_cut(|| frames.iter().copied());
            let du = encoder.latent_dim();
            let weights: Vec<f32> = (0..frames.len() * du)
                .map(|i| ((i * 7919) % 13) as f32 / 6.0 - 1.0)
                .collect();
            let weights =
                Tensor::<2>::from_data(TensorData::new(weights, [frames.len(), du]), &device);
            let loss = |h: Tensor<2>| (h.powi_scalar(2) * weights.clone()).sum();

            let h_burn = encoder.forward(frames_to_tensor(frames.iter().copied(), &device));
            let want_h = to_vec(h_burn.clone());
            let want = grads_of(&encoder, &loss(h_burn).backward());

            let (h_host, tape) = encoder.forward_training(&frames, &device);
            let got_h = to_vec(h_host.clone());
            let mut grads = loss(h_host).backward();
            tape.expect("a CPU autodiff device runs the trunk on the host")
                .backward(&mut grads);
            let got = grads_of(&encoder, &grads);

            for (a, b) in got_h.iter().zip(&want_h) {
                assert!(
                    (a - b).abs() <= 1e-5 * b.abs().max(1.0),
                    "{env} {preset:?} h"
                );
            }
            assert_eq!(
                got.keys().collect::<Vec<_>>(),
                want.keys().collect::<Vec<_>>(),
                "{env} {preset:?}: the same parameters get gradients"
            );
            // Each parameter's gradient is held to the relative error 3e-5 in norm, and each
            // entry to 1e-4 of the largest: host and burn sum over the batch's cells in
            // different orders, which also change with the CPU's vector width, and f32 sums of
            // thousands of terms then differ by about 1e-5 of their norm (the keypoint maps'
            // weight: 1.02e-5 on an AVX2 machine). The bias of the keypoint maps has an exact
            // gradient of 0 (a softmax ignores a constant added to its logits), which both
            // compute as rounding noise: it is held to the norm of the encoder's whole gradient
            // instead. A gradient that is a small part of the whole (the keypoints' sharpness:
            // the attention's covariance of logits and features, whose terms nearly cancel) is
            // held to a hundredth of that norm, above its own rounding noise.
            let norm = |v: &[f32]| v.iter().map(|x| f64::from(*x).powi(2)).sum::<f64>().sqrt();
            let overall = norm(&want.values().flatten().copied().collect::<Vec<_>>());
            for (path, want) in &want {
                let got = &got[path];
                let scale = if path == "keypoints.features.bias" {
                    overall
                } else {
                    norm(want).max(1e-2 * overall)
                };
                assert!(scale > 0.0, "{env} {preset:?} {path}: no gradient");
                let diff: Vec<f32> = got.iter().zip(want).map(|(a, b)| a - b).collect();
                let relative = norm(&diff) / scale;
                let largest = want.iter().fold(0f32, |m, x| m.max(x.abs()));
                let worst = diff.iter().fold(0f32, |m, x| m.max(x.abs()));
                assert!(
                    relative <= 3e-5,
                    "{env} {preset:?} {path}: host and burn differ by {relative} in norm"
                );
                assert!(
                    worst <= 1e-4 * largest || path == "keypoints.features.bias",
                    "{env} {preset:?} {path}: an entry differs by {worst} (largest {largest})"
                );
            }
        }
    }
}
