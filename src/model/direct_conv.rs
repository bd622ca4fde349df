//! A convolution for the host encoder computed straight from a zero-bordered copy of its
//! input, a row of output pixels at a time: each output pixel's channels are a few vector
//! registers, and every kernel tap adds `input x weight row` to them. It does the arithmetic
//! of im2col + GEMM without writing the im2col matrix (48 floats a pixel for the trunk's
//! first convolution, whose copy takes two-thirds as long as its products).

use pulp::Simd;

/// Output pixels computed together: 8 pixels of 2 registers are 16 running sums, half of
/// AVX-512's 32 registers, with the rest free for the weights and the broadcast inputs; each
/// broadcast input feeds 2 multiply-adds. (AVX2 has 16 registers, so there the block spills a
/// few sums; AVX-512 is the unit this is tuned for.)
const PIXEL_BLOCK: usize = 8;

/// Output channels must come in multiples of one AVX-512 register of f32, so that every
/// narrower vector unit's registers (8, 4 or 1 lanes) divide them too.
pub(crate) const CHANNEL_MULTIPLE: usize = 16;

/// Side of a convolution's output for an input of `side x side` pixels, with `[kernel, stride,
/// padding]` of `shape`.
pub(crate) fn out_side(side: usize, [kernel, stride, padding]: [usize; 3]) -> usize {
    (side + 2 * padding - kernel) / stride + 1
}

/// Copies `input` (`[side * side, channels]`) inside a zero border `padding` pixels wide,
/// into `padded` (`[(side + 2 padding)^2, channels]`), and returns the padded side. The
/// border stays 0 from the first call; only the interior is rewritten.
#[inline(always)]
pub(crate) fn copy_inside_zero_border(
    input: &[f32],
    [side, channels]: [usize; 2],
    padding: usize,
    padded: &mut Vec<f32>,
) -> usize {
    let padded_side = side + 2 * padding;
    if padded.len() != padded_side * padded_side * channels {
        padded.clear();
        padded.resize(padded_side * padded_side * channels, 0.0);
    }
    let row = side * channels;
    for y in 0..side {
        let to = ((y + padding) * padded_side + padding) * channels;
        padded[to..][..row].copy_from_slice(&input[y * row..][..row]);
    }
    padded_side
}

/// A convolution's weights laid out for the direct form, with the scratch of one call.
#[derive(Debug, Clone)]
pub(crate) struct DirectConv {
    /// `[kh, kw, in, out]`: each tap's weights for all outputs are one run of registers.
    weight: Vec<f32>,
    bias: Vec<f32>,
    channels: [usize; 2],
    /// `[kernel, stride, padding]`.
    shape: [usize; 3],
    /// The input with a zero border of `padding`, `[(side + 2 padding)^2, in]`.
    padded: Vec<f32>,
}

impl DirectConv {
    /// The direct form of a convolution with `weight` in the host layout `[out, kh, kw, in]`
    /// and `[kernel, stride, padding]` of `shape`, when its outputs fill whole registers.
    pub fn new(
        weight: &[f32],
        bias: &[f32],
        [cin, cout]: [usize; 2],
        shape: [usize; 3],
    ) -> Option<Self> {
        if !cout.is_multiple_of(CHANNEL_MULTIPLE) || cin == 0 {
            return None;
        }
        let taps = shape[0] * shape[0] * cin;
        let mut reordered = vec![0.0; taps * cout];
        for o in 0..cout {
            for tap in 0..taps {
                reordered[tap * cout + o] = weight[o * taps + tap];
            }
        }
        Some(Self {
            weight: reordered,
            bias: bias.to_vec(),
            channels: [cin, cout],
            shape,
            padded: Vec::new(),
        })
    }

    /// `input` is `[side * side, in]`; writes `[out_side^2, out]` into `out`, with a ReLU when
    /// `relu`. Written in `simd`'s vectors of output channels, and compiled as a function of
    /// its own: inlined into the whole encoder, its running sums spill out of the registers
    /// and it runs at less than half the speed.
    #[inline(always)]
    pub fn forward<S: Simd>(
        &mut self,
        simd: S,
        input: &[f32],
        side: usize,
        out: &mut Vec<f32>,
        relu: bool,
    ) {
        simd.vectorize(Forward(self, input, side, out, relu))
    }
}

/// What one output row needs: the reordered weights and bias in registers, the padded input.
struct Rows<'a, S: Simd> {
    weight: &'a [S::f32s],
    bias: &'a [S::f32s],
    padded: &'a [f32],
    padded_side: usize,
    cin: usize,
    cout_v: usize,
    shape: [usize; 3],
    relu: bool,
}

impl<S: Simd> Rows<'_, S> {
    /// Output row `y`'s registers `v..v + V` of each pixel into `out_row` (`[pixels, out]`).
    #[inline(always)]
    fn row<const V: usize>(&self, simd: S, y: usize, v: usize, out_row: &mut [S::f32s]) {
        let pixels = out_row.len() / self.cout_v;
        let mut x = 0;
        while x + PIXEL_BLOCK <= pixels {
            self.pixels::<PIXEL_BLOCK, V>(simd, [y, x], v, out_row);
            x += PIXEL_BLOCK;
        }
        while x < pixels {
            self.pixels::<1, V>(simd, [y, x], v, out_row);
            x += 1;
        }
    }

    /// Registers `v..v + V` of the `P` output pixels from `(y, x)` along the row.
    #[inline(always)]
    fn pixels<const P: usize, const V: usize>(
        &self,
        simd: S,
        [y, x]: [usize; 2],
        v: usize,
        out_row: &mut [S::f32s],
    ) {
        let [kernel, stride, _] = self.shape;
        let cin = self.cin;
        let mut acc = [[simd.splat_f32s(0.0); V]; P];
        // A kernel row's taps `(kx, c)` are one run in the padded input and in the weights.
        let run = kernel * cin;
        for ky in 0..kernel {
            let row = (y * stride + ky) * self.padded_side;
            let inputs: [&[f32]; P] =
                std::array::from_fn(|p| &self.padded[(row + (x + p) * stride) * cin..][..run]);
            let taps = &self.weight[ky * run * self.cout_v..][..run * self.cout_v];
            for (tap, weights) in taps.chunks_exact(self.cout_v).enumerate() {
                let w: [S::f32s; V] = std::array::from_fn(|i| weights[v + i]);
                for (sums, inputs) in acc.iter_mut().zip(&inputs) {
                    let input = simd.splat_f32s(inputs[tap]);
                    for (sum, &w) in sums.iter_mut().zip(&w) {
                        *sum = simd.mul_add_e_f32s(input, w, *sum);
                    }
                }
            }
        }
        let zero = simd.splat_f32s(0.0);
        for (p, sums) in acc.into_iter().enumerate() {
            for (i, sum) in sums.into_iter().enumerate() {
                let value = simd.add_f32s(sum, self.bias[v + i]);
                out_row[(x + p) * self.cout_v + v + i] = if self.relu {
                    simd.max_f32s(value, zero)
                } else {
                    value
                };
            }
        }
    }
}

/// [`DirectConv::forward`]'s arguments; its body is compiled as a function of its own.
pub(crate) struct Forward<'a>(&'a mut DirectConv, &'a [f32], usize, &'a mut Vec<f32>, bool);

impl pulp::WithSimd for Forward<'_> {
    type Output = ();

    #[inline(always)]
    fn with_simd<S: Simd>(self, simd: S) {
        let Self(conv, input, side, out, relu) = self;
        let [cin, cout] = conv.channels;
        let padding = conv.shape[2];
        let padded_side = copy_inside_zero_border(input, [side, cin], padding, &mut conv.padded);
        let o = out_side(side, conv.shape);
        out.resize(o * o * cout, 0.0);
        let lanes = std::mem::size_of::<S::f32s>() / std::mem::size_of::<f32>();
        let cout_v = cout / lanes;
        let rows = Rows {
            weight: S::as_simd_f32s(&conv.weight).0,
            bias: S::as_simd_f32s(&conv.bias).0,
            padded: &conv.padded,
            padded_side,
            cin,
            cout_v,
            shape: conv.shape,
            relu,
        };
        let out = S::as_mut_simd_f32s(out).0;
        for y in 0..o {
            let out_row = &mut out[y * o * cout_v..][..o * cout_v];
            let mut v = 0;
            while v + 2 <= cout_v {
                rows.row::<2>(simd, y, v, out_row);
                v += 2;
            }
            if v < cout_v {
                rows.row::<1>(simd, y, v, out_row);
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use pulp::Simd;

    use super::Forward;
    use crate::model::host_encoder::{HostConv, form_checks};

    /// One convolution's direct form against its im2col + GEMM on inputs of the given sides,
    /// on the vector unit `run` dispatches to.
    fn check_against_im2col(
        channels: [usize; 2],
        shape: [usize; 3],
        sides: &[usize],
        run: &mut dyn FnMut(Forward<'_>),
    ) {
        let conv = form_checks::conv(channels, shape);
        let mut direct = conv.direct().expect("whole registers of outputs");
        form_checks::assert_matches_im2col(&conv, sides, 1e-5, &mut |input, side, out, relu| {
            run(Forward(&mut direct, input, side, out, relu))
        });
    }

    /// The direct form gives im2col + GEMM's outputs to f32 rounding, for the trunk's first
    /// convolution (3 channels in, 16 out: one register) on 64x64 frames and on 10x10 inputs
    /// (5 outputs a row: no whole block of pixels), the point mass's second (16 in, 32 out:
    /// two registers a pixel) on 32x32 and 9x9, and an unpadded one with 48 outputs (a pair
    /// of registers, then one), on the widest vector unit the CPU has, on AVX2 where there is
    /// one, and on scalar code.
    #[test]
    fn direct_equals_im2col_convolution() {
        let cases: [([usize; 2], [usize; 3], &[usize]); 3] = [
            ([3, 16], [4, 2, 1], &[64, 10]),
            ([16, 32], [3, 2, 1], &[32, 9]),
            ([8, 48], [3, 1, 0], &[12]),
        ];
        for (channels, shape, sides) in cases {
            check_against_im2col(channels, shape, sides, &mut |f| {
                pulp::Arch::new().dispatch(f)
            });
            check_against_im2col(channels, shape, sides, &mut |f| {
                Simd::vectorize(pulp::Scalar, f)
            });
            #[cfg(target_arch = "x86_64")]
            if let Some(avx2) = pulp::x86::V3::try_new() {
                check_against_im2col(channels, shape, sides, &mut |f| Simd::vectorize(avx2, f));
            }
        }
    }

    #[test]
    fn only_convolutions_with_whole_registers_of_outputs_have_the_form() {
        let conv = |cin, cout| {
            HostConv::new(
                &vec![0.0; cout * cin * 9],
                vec![0.0; cout],
                [cin, cout],
                3,
                2,
                1,
            )
        };
        assert!(conv(3, 16).direct().is_some());
        assert!(conv(5, 32).direct().is_some());
        assert!(conv(16, 24).direct().is_none());
        assert!(conv(16, 8).direct().is_none());
    }
}
