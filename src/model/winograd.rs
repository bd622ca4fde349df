//! A 3x3, stride-1, padding-1 convolution for the host encoder by Winograd's minimal
//! filtering F(4x4, 3x3) (Lavin and Gray, *Fast Algorithms for Convolutional Neural
//! Networks*, 2016): each 4x4 block of outputs from a 6x6 block of inputs with 36
//! multiplications per channel pair instead of 144. The reacher's second convolution keeps
//! 32x32 maps and is most of its control step's arithmetic; this form computes it with 4x
//! fewer multiplications and without an im2col matrix.
//!
//! With `d` a 6x6 input tile and `g` a 3x3 kernel, the tile's 4x4 output is
//! `A^T [(G g G^T) . (B^T d B)] A`, where `.` multiplies entry by entry and
//!
//! ```text
//! B^T = [4  0 -5  0  1  0]    G = [ 1/4    0     0  ]    A^T = [1  1  1  1  1  0]
//!       [0 -4 -4  1  1  0]        [-1/6  -1/6  -1/6 ]          [0  1 -1  2 -2  0]
//!       [0  4 -4 -1  1  0]        [-1/6   1/6  -1/6 ]          [0  1  1  4  4  0]
//!       [0 -2 -1  2  1  0]        [ 1/24  1/12  1/6 ]          [0  1 -1  8 -8  1]
//!       [0  2 -1 -2  1  0]        [ 1/24 -1/12  1/6 ]
//!       [0  4  0 -5  0  1]        [ 0     0     1   ]
//! ```
//!
//! Summed over input channels, the 36 entry-wise products become 36 small matrix products
//! (tiles x in by in x out), which run here a block of tiles at a time so that the block's
//! tiles stay in the L1 cache. The result equals im2col + GEMM's in exact arithmetic; only
//! the rounding differs (`G g G^T` rounded to f32, the transforms' sums, the order of the
//! products' sums). The transforms' entries up to 8 cost about three bits of f32's
//! precision against F(2x2, 3x3)'s; docs/research/speed.md has what each form buys.

use pulp::Simd;

use super::direct_conv::{CHANNEL_MULTIPLE, copy_inside_zero_border};

/// Side of a tile of outputs.
const OUT_TILE: usize = 4;

/// Side of a tile of inputs: the outputs' and the kernel's border.
const IN_TILE: usize = OUT_TILE + 2;

/// Points of the transformed tile: 6x6.
const POINTS: usize = IN_TILE * IN_TILE;

/// Tiles transformed and multiplied together: eight rows of accumulators in registers.
const TILE_BLOCK: usize = 8;

/// A convolution's weights transformed for F(4x4, 3x3), with the scratch of one call.
#[derive(Debug, Clone)]
pub(crate) struct Winograd3x3 {
    /// `G g G^T` of each channel pair, `[point, in, out]`.
    transformed: Vec<f32>,
    bias: Vec<f32>,
    channels: [usize; 2],
    /// The input with a zero border, `[(side + 2)^2, in]`.
    padded: Vec<f32>,
    /// `B^T d B` of a block of tiles, `[tile, point, in]`.
    tiles_in: Vec<f32>,
    /// The products of a block of tiles, `[tile, point, out]`.
    tiles_out: Vec<f32>,
}

impl Winograd3x3 {
    /// The Winograd form of a convolution with `weight` in the host layout `[out, kh, kw,
    /// in]` and `[kernel, stride, padding]` of `shape`, when it has one here: a 3x3 kernel,
    /// stride 1, padding 1, and channels in whole registers.
    pub fn new(
        weight: &[f32],
        bias: &[f32],
        [cin, cout]: [usize; 2],
        shape: [usize; 3],
    ) -> Option<Self> {
        if shape != [3, 1, 1]
            || !cin.is_multiple_of(CHANNEL_MULTIPLE)
            || !cout.is_multiple_of(CHANNEL_MULTIPLE)
        {
            return None;
        }
        // G g G^T in f64, rounded once.
        const G: [[f64; 3]; IN_TILE] = [
            [1.0 / 4.0, 0.0, 0.0],
            [-1.0 / 6.0, -1.0 / 6.0, -1.0 / 6.0],
            [-1.0 / 6.0, 1.0 / 6.0, -1.0 / 6.0],
            [1.0 / 24.0, 1.0 / 12.0, 1.0 / 6.0],
            [1.0 / 24.0, -1.0 / 12.0, 1.0 / 6.0],
            [0.0, 0.0, 1.0],
        ];
        let mut transformed = vec![0.0; POINTS * cin * cout];
        for o in 0..cout {
            for c in 0..cin {
                // Host layout `[out, kh, kw, in]`.
                let g = |ky: usize, kx: usize| f64::from(weight[((o * 3 + ky) * 3 + kx) * cin + c]);
                for (i, gi) in G.iter().enumerate() {
                    for (j, gj) in G.iter().enumerate() {
                        let mut u = 0.0;
                        for (ky, &a) in gi.iter().enumerate() {
                            for (kx, &b) in gj.iter().enumerate() {
                                u += a * g(ky, kx) * b;
                            }
                        }
                        transformed[((i * IN_TILE + j) * cin + c) * cout + o] = u as f32;
                    }
                }
            }
        }
        Some(Self {
            transformed,
            bias: bias.to_vec(),
            channels: [cin, cout],
            padded: Vec::new(),
            tiles_in: vec![0.0; TILE_BLOCK * POINTS * cin],
            tiles_out: vec![0.0; TILE_BLOCK * POINTS * cout],
        })
    }

    /// Whether an input of `side x side` pixels runs here: whole 4x4 output tiles.
    pub fn fits(&self, side: usize) -> bool {
        side.is_multiple_of(OUT_TILE) && side > 0
    }

    /// `input` is `[side * side, in]`; writes `[side * side, out]` into `out`, with a ReLU
    /// when `relu`. `side` must [`Self::fits`]. Written in `simd`'s vectors of channels (so
    /// the compiler cannot vectorise across tiles instead, with gathers and scatters), and
    /// compiled as a function of its own, as [`super::direct_conv::DirectConv::forward`] is.
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

/// `B^T` applied to six vectors (each scaled entry a multiply-add).
#[inline(always)]
fn b_transpose<S: Simd>(simd: S, [x0, x1, x2, x3, x4, x5]: [S::f32s; 6]) -> [S::f32s; 6] {
    let k = |c: f32| simd.splat_f32s(c);
    // r1, r2 = (x4 - 4 x2) +- (x3 - 4 x1); r3, r4 = (x4 - x2) +- 2 (x3 - x1).
    let a = simd.mul_add_e_f32s(k(-4.0), x2, x4);
    let b = simd.mul_add_e_f32s(k(-4.0), x1, x3);
    let c = simd.sub_f32s(x4, x2);
    let d = simd.mul_f32s(k(2.0), simd.sub_f32s(x3, x1));
    [
        simd.mul_add_e_f32s(k(4.0), x0, simd.mul_add_e_f32s(k(-5.0), x2, x4)),
        simd.add_f32s(a, b),
        simd.sub_f32s(a, b),
        simd.add_f32s(c, d),
        simd.sub_f32s(c, d),
        simd.mul_add_e_f32s(k(4.0), x1, simd.mul_add_e_f32s(k(-5.0), x3, x5)),
    ]
}

/// `B^T d B` of the 6x6 tile whose top-left pixel starts at vector `at` of `padded` (pixels
/// `[row, pixel]` vectors apart), a vector of input channels at a time, into `v [point, in]`.
#[inline(always)]
fn input_transform<S: Simd>(
    simd: S,
    padded: &[S::f32s],
    at: usize,
    [row, pixel]: [usize; 2],
    v: &mut [S::f32s],
) {
    for c in 0..pixel {
        let d = |r: usize, col: usize| padded[at + r * row + col * pixel + c];
        // B^T d, column by column: `t[col][i]` (plain loops: an array's `map` runs its
        // closure outside the vector unit's compilation).
        let mut t = [[simd.splat_f32s(0.0); IN_TILE]; IN_TILE];
        for (col, t_col) in t.iter_mut().enumerate() {
            let column = [
                d(0, col),
                d(1, col),
                d(2, col),
                d(3, col),
                d(4, col),
                d(5, col),
            ];
            *t_col = b_transpose(simd, column);
        }
        // (B^T d) B: the same combinations of each row's columns.
        for i in 0..IN_TILE {
            let row_i = b_transpose(simd, [t[0][i], t[1][i], t[2][i], t[3][i], t[4][i], t[5][i]]);
            for (j, x) in row_i.into_iter().enumerate() {
                v[(i * IN_TILE + j) * pixel + c] = x;
            }
        }
    }
}

/// For every point, `tiles_out [tile, point, :] = tiles_in [tile, point, :] . transformed
/// [point]` over a block of [`TILE_BLOCK`] tiles (stale tiles past the block's count are
/// multiplied too and ignored), a vector of output channels at a time, the block's
/// accumulators in registers.
#[inline(always)]
fn multiply<S: Simd>(
    simd: S,
    tiles_in: &[f32],
    transformed: &[S::f32s],
    [cin, cout_v]: [usize; 2],
    tiles_out: &mut [S::f32s],
) {
    for point in 0..POINTS {
        let weights = &transformed[point * cin * cout_v..][..cin * cout_v];
        // Each tile's row at this point, `cin` long, so that indexing by `c < cin` needs no
        // check.
        let mut rows: [&[f32]; TILE_BLOCK] = [&[]; TILE_BLOCK];
        for (t, row) in rows.iter_mut().enumerate() {
            *row = &tiles_in[(t * POINTS + point) * cin..][..cin];
        }
        for o in 0..cout_v {
            let mut acc = [simd.splat_f32s(0.0); TILE_BLOCK];
            for (c, u) in weights.chunks_exact(cout_v).enumerate() {
                let u = u[o];
                for (sum, row) in acc.iter_mut().zip(&rows) {
                    *sum = simd.mul_add_e_f32s(simd.splat_f32s(row[c]), u, *sum);
                }
            }
            for (t, sum) in acc.into_iter().enumerate() {
                tiles_out[(t * POINTS + point) * cout_v + o] = sum;
            }
        }
    }
}

/// `A^T` applied to six vectors.
#[inline(always)]
fn a_transpose<S: Simd>(simd: S, [x0, x1, x2, x3, x4, x5]: [S::f32s; 6]) -> [S::f32s; 4] {
    let k = |c: f32| simd.splat_f32s(c);
    let (sum12, diff12) = (simd.add_f32s(x1, x2), simd.sub_f32s(x1, x2));
    let (sum34, diff34) = (simd.add_f32s(x3, x4), simd.sub_f32s(x3, x4));
    [
        simd.add_f32s(simd.add_f32s(x0, sum12), sum34),
        simd.mul_add_e_f32s(k(2.0), diff34, diff12),
        simd.mul_add_e_f32s(k(4.0), sum34, sum12),
        simd.add_f32s(simd.mul_add_e_f32s(k(8.0), diff34, diff12), x5),
    ]
}

/// `A^T m A` of one tile's products `m [point, out]`, plus the bias (and a ReLU), into the
/// 4x4 outputs from vector `at` of `out` (pixels `[row, pixel]` vectors apart).
#[inline(always)]
fn output_transform<S: Simd>(
    simd: S,
    m: &[S::f32s],
    (bias, relu): (&[S::f32s], bool),
    out: &mut [S::f32s],
    at: usize,
    [row, pixel]: [usize; 2],
) {
    for o in 0..pixel {
        let p = |i: usize, j: usize| m[(i * IN_TILE + j) * pixel + o];
        // A^T m, column by column: `s[j][i]`.
        let mut s = [[simd.splat_f32s(0.0); OUT_TILE]; IN_TILE];
        for (j, s_col) in s.iter_mut().enumerate() {
            let column = [p(0, j), p(1, j), p(2, j), p(3, j), p(4, j), p(5, j)];
            *s_col = a_transpose(simd, column);
        }
        // (A^T m) A, row by row.
        for i in 0..OUT_TILE {
            let y = a_transpose(simd, [s[0][i], s[1][i], s[2][i], s[3][i], s[4][i], s[5][i]]);
            for (j, y) in y.into_iter().enumerate() {
                let y = simd.add_f32s(y, bias[o]);
                out[at + i * row + j * pixel + o] = if relu {
                    simd.max_f32s(y, simd.splat_f32s(0.0))
                } else {
                    y
                };
            }
        }
    }
}

/// [`Winograd3x3::forward`]'s arguments; its body is compiled as a function of its own.
pub(crate) struct Forward<'a>(
    &'a mut Winograd3x3,
    &'a [f32],
    usize,
    &'a mut Vec<f32>,
    bool,
);

impl pulp::WithSimd for Forward<'_> {
    type Output = ();

    #[inline(always)]
    fn with_simd<S: Simd>(self, simd: S) {
        let Self(conv, input, side, out, relu) = self;
        debug_assert!(
            conv.fits(side),
            "a side of {side} pixels has no whole 4x4 tiles"
        );
        let [cin, cout] = conv.channels;
        let padded_side = copy_inside_zero_border(input, [side, cin], 1, &mut conv.padded);
        out.resize(side * side * cout, 0.0);
        let lanes = std::mem::size_of::<S::f32s>() / std::mem::size_of::<f32>();
        let [cin_v, cout_v] = [cin / lanes, cout / lanes];
        let padded = S::as_simd_f32s(&conv.padded).0;
        let transformed = S::as_simd_f32s(&conv.transformed).0;
        let bias = S::as_simd_f32s(&conv.bias).0;
        let out = S::as_mut_simd_f32s(out).0;
        let per_row = side / OUT_TILE;
        let tiles = per_row * per_row;
        let mut first = 0;
        while first < tiles {
            let count = TILE_BLOCK.min(tiles - first);
            let tiles_in = S::as_mut_simd_f32s(&mut conv.tiles_in).0;
            for t in 0..count {
                let tile = first + t;
                let (ty, tx) = (tile / per_row, tile % per_row);
                input_transform(
                    simd,
                    padded,
                    (OUT_TILE * (ty * padded_side + tx)) * cin_v,
                    [padded_side * cin_v, cin_v],
                    &mut tiles_in[t * POINTS * cin_v..][..POINTS * cin_v],
                );
            }
            multiply(
                simd,
                &conv.tiles_in,
                transformed,
                [cin, cout_v],
                S::as_mut_simd_f32s(&mut conv.tiles_out).0,
            );
            let tiles_out = S::as_simd_f32s(&conv.tiles_out).0;
            for t in 0..count {
                let tile = first + t;
                let (ty, tx) = (tile / per_row, tile % per_row);
                output_transform(
                    simd,
                    &tiles_out[t * POINTS * cout_v..][..POINTS * cout_v],
                    (bias, relu),
                    out,
                    (OUT_TILE * (ty * side + tx)) * cout_v,
                    [side * cout_v, cout_v],
                );
            }
            first += count;
        }
    }
}

#[cfg(test)]
mod tests {
    use pulp::Simd;

    use super::Forward;
    use crate::model::host_encoder::{HostConv, form_checks};

    /// One convolution's Winograd form against its im2col + GEMM on inputs of the given
    /// sides, on the vector unit `run` dispatches to. The transforms' entries up to 8 cost
    /// about three bits of f32's precision, hence 5e-5.
    fn check_against_im2col(
        channels: [usize; 2],
        sides: &[usize],
        run: &mut dyn FnMut(Forward<'_>),
    ) {
        let conv = form_checks::conv(channels, [3, 1, 1]);
        let mut winograd = conv.winograd().expect("a 3x3 stride-1 conv");
        assert!(sides.iter().all(|&side| winograd.fits(side)));
        form_checks::assert_matches_im2col(&conv, sides, 5e-5, &mut |input, side, out, relu| {
            run(Forward(&mut winograd, input, side, out, relu))
        });
    }

    /// The Winograd form gives im2col + GEMM's outputs to f32 rounding: a 32x32 input (8
    /// tiles a row, whole blocks), then a 12x12 one whose 9 tiles end one into a second block,
    /// with 16 channels in and 32 out and the other way round, on the widest vector unit the
    /// CPU has, on AVX2 where there is one, and on scalar code.
    #[test]
    fn winograd_equals_im2col_convolution() {
        for channels in [[16, 32], [32, 16]] {
            check_against_im2col(channels, &[32, 12], &mut |f| pulp::Arch::new().dispatch(f));
            check_against_im2col(channels, &[32, 12], &mut |f| {
                Simd::vectorize(pulp::Scalar, f)
            });
            #[cfg(target_arch = "x86_64")]
            if let Some(avx2) = pulp::x86::V3::try_new() {
                check_against_im2col(channels, &[32, 12], &mut |f| Simd::vectorize(avx2, f));
            }
        }
    }

    #[test]
    fn only_3x3_stride_1_padding_1_convolutions_with_whole_registers_and_tiles_have_the_form() {
        let conv = |k, stride, pad, cout| {
            HostConv::new(
                &vec![0.0; cout * 16 * k * k],
                vec![0.0; cout],
                [16, cout],
                k,
                stride,
                pad,
            )
        };
        let fitting = conv(3, 1, 1, 32).winograd().expect("a 3x3 stride-1 conv");
        assert!(fitting.fits(32) && fitting.fits(4));
        assert!(!fitting.fits(30) && !fitting.fits(6) && !fitting.fits(0));
        assert!(conv(3, 2, 1, 32).winograd().is_none());
        assert!(conv(4, 1, 1, 32).winograd().is_none());
        assert!(conv(3, 1, 0, 32).winograd().is_none());
        assert!(conv(3, 1, 1, 24).winograd().is_none());
        let five_in = HostConv::new(&vec![0.0; 32 * 5 * 9], vec![0.0; 32], [5, 32], 3, 1, 1);
        assert!(five_in.winograd().is_none());
    }
}
