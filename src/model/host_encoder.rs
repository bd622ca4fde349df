//! The encoder's inference path for control: a copy of a trained encoder's weights that maps
//! one u8 frame to `h` on the host, with packed GEMMs (the `gemm` crate) over buffers kept
//! between calls, no autodiff graph and no tensor allocation. It computes what
//! [`super::Encoder::forward`] computes, in another summation order.

use burn::nn::PaddingConfig2d;
use burn::nn::conv::Conv2d;
use gemm::Parallelism;

use super::POLAR_FADE_RADIUS;
use super::direct_conv::{self, DirectConv};
use super::polar_reference::PolarReference;
use super::soft_argmax::soft_argmax;
use super::winograd::Winograd3x3;
use crate::envs::FRAME_PX;

/// A convolution as im2col + GEMM with zero padding on the input. The weight is held
/// `[out, kh, kw, in]` row-major, so each kernel row of a patch is one contiguous copy from
/// the `[pixel, channel]` input.
#[derive(Debug, Clone)]
pub(crate) struct HostConv {
    /// `[out, kh, kw, in]` row-major: `[out, width]` with `width = kh kw in`.
    pub weight: Vec<f32>,
    pub bias: Vec<f32>,
    pub channels: [usize; 2],
    pub kernel: usize,
    pub stride: usize,
    pub padding: usize,
}

impl HostConv {
    /// A copy of a trained convolution's weights.
    pub fn from_conv(conv: &Conv2d) -> Self {
        let [cout, cin, kernel, _] = conv.weight.dims();
        let padding = match conv.padding {
            PaddingConfig2d::Explicit(top, ..) => top,
            _ => 0,
        };
        Self::new(
            &super::to_vec(conv.weight.val()),
            conv.bias
                .as_ref()
                .map_or_else(|| vec![0.0; cout], |b| super::to_vec(b.val())),
            [cin, cout],
            kernel,
            conv.stride[0],
            padding,
        )
    }

    /// From burn's weight layout `[out, in, kh, kw]` (row-major) and the bias.
    pub fn new(
        weight: &[f32],
        bias: Vec<f32>,
        channels: [usize; 2],
        kernel: usize,
        stride: usize,
        padding: usize,
    ) -> Self {
        let reordered = reorder_weight(weight, channels, kernel, true);
        Self {
            weight: reordered,
            bias,
            channels,
            kernel,
            stride,
            padding,
        }
    }

    /// This convolution in the direct form, where it has one (see [`DirectConv::new`]).
    pub fn direct(&self) -> Option<DirectConv> {
        DirectConv::new(
            &self.weight,
            &self.bias,
            self.channels,
            [self.kernel, self.stride, self.padding],
        )
    }

    /// This convolution in Winograd's form, where it has one (see [`Winograd3x3::new`]).
    pub fn winograd(&self) -> Option<Winograd3x3> {
        Winograd3x3::new(
            &self.weight,
            &self.bias,
            self.channels,
            [self.kernel, self.stride, self.padding],
        )
    }

    /// A weight (or its gradient) in the host layout `[out, kh, kw, in]` back in burn's
    /// `[out, in, kh, kw]`.
    pub fn weight_to_burn_layout(&self, weight: &[f32]) -> Vec<f32> {
        reorder_weight(weight, self.channels, self.kernel, false)
    }

    pub fn out_side(&self, side: usize) -> usize {
        direct_conv::out_side(side, [self.kernel, self.stride, self.padding])
    }

    /// Width of a patch row of the im2col matrix: `kh kw in`.
    pub fn width(&self) -> usize {
        self.kernel * self.kernel * self.channels[0]
    }

    /// Whether the convolution is a pointwise one, whose im2col matrix is its input.
    pub fn is_pointwise(&self) -> bool {
        (self.kernel, self.stride, self.padding) == (1, 1, 0)
    }

    /// Calls `visit(column, input, len)` for every run of `len` floats that im2col copies from
    /// `input [side * side, in]` at `input` to the columns `[out_side^2, width]` at `column`;
    /// entries no run covers (the padding) are 0 in the columns.
    #[inline(always)]
    pub fn for_each_patch_run(&self, side: usize, mut visit: impl FnMut(usize, usize, usize)) {
        let cin = self.channels[0];
        let (k, s, p) = (self.kernel, self.stride, self.padding);
        let o = self.out_side(side);
        let width = self.width();
        for oy in 0..o {
            for ox in 0..o {
                // The patch's columns inside the image: [x0, x1) of kx.
                let left = (ox * s) as isize - p as isize;
                let x0 = (-left).max(0) as usize;
                let x1 = k.min((side as isize - left).max(0) as usize);
                if x0 >= x1 {
                    continue;
                }
                for ky in 0..k {
                    let iy = (oy * s + ky) as isize - p as isize;
                    if iy < 0 || iy >= side as isize {
                        continue;
                    }
                    let from = (iy as usize * side) as isize + left + x0 as isize;
                    visit(
                        (oy * o + ox) * width + (ky * k + x0) * cin,
                        from as usize * cin,
                        (x1 - x0) * cin,
                    );
                }
            }
        }
    }

    /// Writes the im2col matrix `[out_side^2, width]` of one input `[side * side, in]` into
    /// `columns`, whose padding entries must already be 0.
    #[inline(always)]
    pub fn im2col(&self, input: &[f32], side: usize, columns: &mut [f32]) {
        // A kernel row's length known at compile time makes each interior copy a few moves.
        match self.kernel * self.channels[0] {
            12 => self.im2col_runs::<12>(input, side, columns),
            48 => self.im2col_runs::<48>(input, side, columns),
            128 => self.im2col_runs::<128>(input, side, columns),
            _ => self.im2col_runs::<0>(input, side, columns),
        }
    }

    /// [`Self::im2col`] with interior kernel rows `RUN` floats long (0: any length).
    #[inline(always)]
    fn im2col_runs<const RUN: usize>(&self, input: &[f32], side: usize, columns: &mut [f32]) {
        let cin = self.channels[0];
        let (k, s, p) = (self.kernel, self.stride, self.padding);
        let o = self.out_side(side);
        let width = self.width();
        let run = k * cin;
        // Output columns whose kernel row lies inside the image: the run is copied whole.
        let inside = |ox: usize| ox * s >= p && ox * s + k <= side + p;
        for oy in 0..o {
            for ky in 0..k {
                let iy = (oy * s + ky) as isize - p as isize;
                if iy < 0 || iy >= side as isize {
                    continue;
                }
                let row = &input[iy as usize * side * cin..][..side * cin];
                for ox in 0..o {
                    let column = (oy * o + ox) * width + ky * run;
                    if inside(ox) {
                        let from = (ox * s - p) * cin;
                        let (dst, src) = (&mut columns[column..][..run], &row[from..][..run]);
                        if RUN > 0 {
                            copy_exact::<RUN>(dst, src);
                        } else {
                            copy_short(dst, src);
                        }
                        continue;
                    }
                    let left = (ox * s) as isize - p as isize;
                    let x0 = (-left).max(0) as usize;
                    let x1 = k.min((side as isize - left).max(0) as usize);
                    if x0 < x1 {
                        let from = (left + x0 as isize) as usize * cin;
                        let len = (x1 - x0) * cin;
                        copy_short(
                            &mut columns[column + x0 * cin..][..len],
                            &row[from..][..len],
                        );
                    }
                }
            }
        }
    }

    /// `input` is `[side * side, in]` (pixels row-major, channels innermost); writes
    /// `[out_side^2, out]` into `out`, with a ReLU when `relu`.
    #[inline(always)]
    pub(crate) fn forward(
        &self,
        input: &[f32],
        side: usize,
        columns: &mut Vec<f32>,
        out: &mut Vec<f32>,
        relu: bool,
    ) {
        let [cin, cout] = self.channels;
        let o = self.out_side(side);
        // The GEMM overwrites every entry.
        out.resize(o * o * cout, 0.0);
        if self.is_pointwise() {
            // A pointwise convolution is the GEMM itself.
            gemm_into(out, input, &self.weight, o * o, cin, cout);
            add_bias(out, &self.bias, relu);
            return;
        }
        let width = self.width();
        // Each call writes the same interior entries; the padding's stay 0 from the first.
        if columns.len() != o * o * width {
            columns.clear();
            columns.resize(o * o * width, 0.0);
        }
        self.im2col(input, side, columns);
        gemm_into(out, columns, &self.weight, o * o, width, cout);
        add_bias(out, &self.bias, relu);
    }
}

/// A convolution weight from burn's layout `[out, in, kh, kw]` to the host's `[out, kh, kw,
/// in]` (`to_host`), or back.
fn reorder_weight(weight: &[f32], [cin, cout]: [usize; 2], k: usize, to_host: bool) -> Vec<f32> {
    let mut reordered = vec![0.0; weight.len()];
    for o in 0..cout {
        for c in 0..cin {
            for ky in 0..k {
                for kx in 0..k {
                    let burn = ((o * cin + c) * k + ky) * k + kx;
                    let host = ((o * k + ky) * k + kx) * cin + c;
                    if to_host {
                        reordered[host] = weight[burn];
                    } else {
                        reordered[burn] = weight[host];
                    }
                }
            }
        }
    }
    reordered
}

/// Copies `N` floats: with `N` known at compile time, in blocks of 32 (128 bytes), each a few
/// register moves. memcpy's call and size dispatch cost more than the copy at these lengths,
/// and the compiler calls memcpy for a single copy over 128 bytes.
#[inline(always)]
fn copy_exact<const N: usize>(dst: &mut [f32], src: &[f32]) {
    #[inline(always)]
    fn block<const M: usize>(dst: &mut [f32], src: &[f32], at: usize) {
        if let (Ok(d), Ok(s)) = (
            <&mut [f32; M]>::try_from(&mut dst[at..at + M]),
            <&[f32; M]>::try_from(&src[at..at + M]),
        ) {
            *d = *s;
        }
    }
    let (dst, src) = (&mut dst[..N], &src[..N]);
    let mut at = 0;
    while at + 32 <= N {
        block::<32>(dst, src, at);
        at += 32;
    }
    if at + 16 <= N {
        block::<16>(dst, src, at);
        at += 16;
    }
    dst[at..].copy_from_slice(&src[at..]);
}

/// Copies a patch row of any length (the image's border rows, other layers' kernels).
#[inline]
pub(crate) fn copy_short(dst: &mut [f32], src: &[f32]) {
    match src.len() {
        9 => copy_exact::<9>(dst, src),
        12 => copy_exact::<12>(dst, src),
        32 => copy_exact::<32>(dst, src),
        48 => copy_exact::<48>(dst, src),
        96 => copy_exact::<96>(dst, src),
        128 => copy_exact::<128>(dst, src),
        _ => dst.copy_from_slice(src),
    }
}

/// A dense layer `y = x W + b` with burn's `[in, out]` weight.
#[derive(Debug, Clone)]
pub(crate) struct HostLinear {
    pub weight: Vec<f32>,
    pub bias: Vec<f32>,
    pub outputs: usize,
}

impl HostLinear {
    #[inline(always)]
    fn forward(&self, x: &[f32], out: &mut Vec<f32>) {
        out.clear();
        out.extend_from_slice(&self.bias);
        for (i, &xi) in x.iter().enumerate() {
            let row = &self.weight[i * self.outputs..(i + 1) * self.outputs];
            for (o, &w) in out.iter_mut().zip(row) {
                *o += xi * w;
            }
        }
    }
}

/// `out [m, n] = lhs [m, k] * rhs^T`, `rhs` row-major `[n, k]` (a weight `[out, in]`), on the
/// calling thread.
pub(crate) fn gemm_into(out: &mut [f32], lhs: &[f32], rhs: &[f32], m: usize, k: usize, n: usize) {
    gemm_strided(out, [m, n, k], (lhs, [1, k]), (rhs, [k, 1]));
}

/// `dst [m, n] = lhs [m, k] . rhs [k, n]`, each operand given with its (column, row) strides,
/// on the calling thread.
pub(crate) fn gemm_strided(
    dst: &mut [f32],
    [m, n, k]: [usize; 3],
    (lhs, [lhs_cs, lhs_rs]): (&[f32], [usize; 2]),
    (rhs, [rhs_cs, rhs_rs]): (&[f32], [usize; 2]),
) {
    let last =
        |[rows, cols]: [usize; 2], cs: usize, rs: usize| (rows - 1) * rs + (cols - 1) * cs + 1;
    assert!(m > 0 && n > 0 && k > 0);
    assert!(dst.len() >= m * n);
    assert!(lhs.len() >= last([m, k], lhs_cs, lhs_rs));
    assert!(rhs.len() >= last([k, n], rhs_cs, rhs_rs));
    // SAFETY: the asserts bound the last entry each operand's strides reach.
    unsafe {
        gemm::gemm(
            m,
            n,
            k,
            dst.as_mut_ptr(),
            1,
            n as isize,
            false,
            lhs.as_ptr(),
            lhs_cs as isize,
            lhs_rs as isize,
            rhs.as_ptr(),
            rhs_cs as isize,
            rhs_rs as isize,
            0.0,
            1.0,
            false,
            false,
            false,
            Parallelism::None,
        );
    }
}

#[inline(always)]
pub(crate) fn add_bias(out: &mut [f32], bias: &[f32], relu: bool) {
    for row in out.chunks_exact_mut(bias.len()) {
        for (v, b) in row.iter_mut().zip(bias) {
            *v += b;
            if relu && *v < 0.0 {
                *v = 0.0;
            }
        }
    }
}

/// The head after the trunk.
#[derive(Debug, Clone)]
pub(crate) enum HostHead {
    /// PC3's: one more conv, flatten (channel-major), an MLP.
    Mlp {
        conv3: HostConv,
        fc1: HostLinear,
        fc2: HostLinear,
    },
    /// Spatial soft-argmax keypoints, each the attention's expectations of `grids` (see
    /// [`soft_argmax`]), then the angles between keypoints (from the last two grids, the
    /// cells' `(x, y)`) when `pairwise`, then an optional tanh layer and the output layer.
    Keypoints {
        features: HostConv,
        sharpness: Vec<f32>,
        /// The per-cell values whose expectations are the keypoint features, `[cells]` each:
        /// `(x, y)` or the polar `(angle, radius)`, then with `pairwise` the `(x, y)`.
        grids: Vec<Vec<f32>>,
        /// Under a moving cut, what gives each frame its own first (angle) grid.
        reference: Option<PolarReference>,
        pairwise: bool,
        hidden: Option<HostLinear>,
        out: HostLinear,
    },
}

/// How one of the control encoder's convolutions runs, for its fixed input side.
#[derive(Debug, Clone)]
enum ConvForm {
    /// Winograd's F(4x4, 3x3): 3x3, stride 1, padding 1, whole registers of channels, a side
    /// in multiples of 4 (the reacher's `conv2`, which keeps 32x32 maps).
    Winograd(Winograd3x3),
    /// Straight from the padded input: any other convolution with whole registers of
    /// outputs and a kernel wider than one pixel.
    Direct(DirectConv),
    /// im2col + GEMM: a pointwise convolution (the GEMM itself), or channels that do not
    /// fill registers.
    Im2col,
}

impl ConvForm {
    /// The fastest form of `conv` for inputs of `side x side` pixels.
    fn fastest(conv: &HostConv, side: usize) -> Self {
        if let Some(winograd) = conv.winograd().filter(|w| w.fits(side)) {
            return Self::Winograd(winograd);
        }
        if conv.is_pointwise() {
            return Self::Im2col;
        }
        conv.direct().map_or(Self::Im2col, Self::Direct)
    }

    /// `conv` (this form's convolution) of `input` (`[side * side, in]`) into `out`, with a
    /// ReLU when `relu`; `columns` is the im2col scratch.
    #[inline(always)]
    fn forward<S: pulp::Simd>(
        &mut self,
        simd: S,
        conv: &HostConv,
        (input, side): (&[f32], usize),
        (columns, out): (&mut Vec<f32>, &mut Vec<f32>),
        relu: bool,
    ) {
        match self {
            Self::Winograd(winograd) => winograd.forward(simd, input, side, out, relu),
            Self::Direct(direct) => direct.forward(simd, input, side, out, relu),
            Self::Im2col => conv.forward(input, side, columns, out, relu),
        }
    }
}

/// A trained encoder's weights on the host (see the module's doc).
#[derive(Debug, Clone)]
pub struct HostEncoder {
    pub(crate) conv1: HostConv,
    pub(crate) conv2: HostConv,
    pub(crate) head: HostHead,
    /// How `conv1`, `conv2` and the head's convolution run. Frames are always `FRAME_PX`
    /// square, so each one's input side, and the form that fits it, is fixed at construction.
    forms: [ConvForm; 3],
    /// The orientation `Q`, row-major `du x du`: `h = Q raw`.
    pub(crate) transform: Vec<f32>,
    /// How many leading components of `Q raw` are `h`: all of them, or the mean's half of a
    /// NewtonianVAE's `(mean, log std)`.
    outputs: usize,
    buffers: Buffers,
}

#[derive(Debug, Clone, Default)]
struct Buffers {
    input: Vec<f32>,
    /// im2col of each convolution that runs as im2col + GEMM, kept between calls (see
    /// [`HostConv::forward`]).
    columns: [Vec<f32>; 3],
    /// `[cells, K]`: each keypoint's attention.
    attention: Vec<f32>,
    /// `[K, G]`: each keypoint's expectations of the grids.
    expectations: Vec<f32>,
    /// Under a moving cut, the frame's grids: the fixed ones with the frame's angle grid.
    frame_grids: Vec<Vec<f32>>,
    a: Vec<f32>,
    b: Vec<f32>,
    features: Vec<f32>,
    hidden: Vec<f32>,
    raw: Vec<f32>,
}

impl HostEncoder {
    pub(crate) fn new(
        conv1: HostConv,
        conv2: HostConv,
        head: HostHead,
        transform: Vec<f32>,
    ) -> Self {
        let side1 = conv1.out_side(FRAME_PX);
        let head_conv = match &head {
            HostHead::Mlp { conv3, .. } => conv3,
            HostHead::Keypoints { features, .. } => features,
        };
        Self {
            forms: [
                ConvForm::fastest(&conv1, FRAME_PX),
                ConvForm::fastest(&conv2, side1),
                ConvForm::fastest(head_conv, conv2.out_side(side1)),
            ],
            conv1,
            conv2,
            head,
            outputs: (transform.len() as f64).sqrt() as usize,
            transform,
            buffers: Buffers::default(),
        }
    }

    /// Dimension of `h`.
    pub fn latent_dim(&self) -> usize {
        self.outputs
    }

    /// The same encoder giving only the first `n` components of `h`.
    pub(crate) fn leading(self, n: usize) -> Self {
        Self {
            outputs: n.min(self.outputs),
            ..self
        }
    }

    /// The same encoder with `h` turned by `p` (row-major `du x du`, `du` = [`Self::latent_dim`]):
    /// `h -> p h`, folded into the orientation's leading rows.
    pub(crate) fn turned(self, p: &[f32]) -> Self {
        let (du, full) = (self.outputs, (self.transform.len() as f64).sqrt() as usize);
        assert_eq!(p.len(), du * du, "a {du} x {du} turn");
        let mut transform = self.transform.clone();
        for i in 0..du {
            for j in 0..full {
                transform[i * full + j] = (0..du)
                    .map(|k| p[i * du + k] * self.transform[k * full + j])
                    .sum();
            }
        }
        Self { transform, ..self }
    }

    /// `h` of one RGB u8 frame (64x64, row-major, channels innermost), written into `h`.
    pub fn encode(&mut self, frame: &[u8], h: &mut [f64]) {
        pulp::Arch::new().dispatch(Encode {
            encoder: self,
            frame,
            h,
        })
    }

    /// The body of [`Self::encode`]; inlined into each of [`Encode`]'s compilations.
    #[inline(always)]
    fn encode_here<S: pulp::Simd>(&mut self, simd: S, frame: &[u8], h: &mut [f64]) {
        let buffers = &mut self.buffers;
        buffers.input.resize(frame.len(), 0.0);
        super::pixel_inputs(frame, &mut buffers.input);
        let [form1, form2, form3] = &mut self.forms;
        let side0 = FRAME_PX;
        let input = (&buffers.input[..], side0);
        let scratch = (&mut buffers.columns[0], &mut buffers.a);
        form1.forward(simd, &self.conv1, input, scratch, true);
        let side1 = self.conv1.out_side(side0);
        let input = (&buffers.a[..], side1);
        let scratch = (&mut buffers.columns[1], &mut buffers.b);
        form2.forward(simd, &self.conv2, input, scratch, true);
        let side2 = self.conv2.out_side(side1);
        match &self.head {
            HostHead::Mlp { conv3, fc1, fc2 } => {
                let input = (&buffers.b[..], side2);
                let scratch = (&mut buffers.columns[2], &mut buffers.a);
                form3.forward(simd, conv3, input, scratch, true);
                // Flattened channel-major, as the tensor `[n, c, y, x]` is.
                let cells = conv3.out_side(side2).pow(2);
                let channels = conv3.channels[1];
                buffers.features.clear();
                buffers.features.extend(
                    (0..channels * cells).map(|i| buffers.a[(i % cells) * channels + i / cells]),
                );
                fc1.forward(&buffers.features, &mut buffers.hidden);
                for v in buffers.hidden.iter_mut() {
                    *v = v.max(0.0);
                }
                fc2.forward(&buffers.hidden, &mut buffers.raw);
            }
            HostHead::Keypoints {
                features,
                sharpness,
                grids,
                reference,
                pairwise,
                hidden,
                out,
            } => {
                let input = (&buffers.b[..], side2);
                // The keypoint maps take no ReLU.
                let scratch = (&mut buffers.columns[2], &mut buffers.a);
                form3.forward(simd, features, input, scratch, false);
                let k = features.channels[1];
                let (cells, g) = (side2 * side2, grids.len());
                buffers.attention.resize(k * cells, 0.0);
                buffers.expectations.resize(k * g, 0.0);
                let grids = match reference {
                    Some(reference) => {
                        if buffers.frame_grids.is_empty() {
                            buffers.frame_grids.clone_from(grids);
                        }
                        let psi = reference.direction(&buffers.input);
                        reference.angle_grid(psi, &mut buffers.frame_grids[0]);
                        &buffers.frame_grids
                    }
                    None => grids,
                };
                soft_argmax(
                    &buffers.a,
                    sharpness,
                    grids,
                    &mut buffers.attention,
                    &mut buffers.expectations,
                );
                let e = |key: usize, grid: usize| buffers.expectations[key * g + grid];
                let feats = &mut buffers.features;
                feats.clear();
                feats.extend((0..k).map(|key| e(key, 0)));
                feats.extend((0..k).map(|key| e(key, 1)));
                if *pairwise {
                    let fade = |key: usize| {
                        let r2 = e(key, 2).powi(2) + e(key, 3).powi(2);
                        r2 / (r2 + POLAR_FADE_RADIUS * POLAR_FADE_RADIUS)
                    };
                    for i in 0..k {
                        for j in i + 1..k {
                            let cross = e(i, 2) * e(j, 3) - e(i, 3) * e(j, 2);
                            let dot = e(i, 2) * e(j, 2) + e(i, 3) * e(j, 3);
                            feats.push(cross.atan2(dot + 1e-12) * fade(i) * fade(j));
                        }
                    }
                }
                match hidden {
                    Some(layer) => {
                        layer.forward(feats, &mut buffers.hidden);
                        for v in buffers.hidden.iter_mut() {
                            *v = v.tanh();
                        }
                        out.forward(&buffers.hidden, &mut buffers.raw);
                    }
                    None => out.forward(feats, &mut buffers.raw),
                }
            }
        }
        let du = buffers.raw.len();
        for (i, hi) in h.iter_mut().enumerate().take(self.outputs) {
            *hi = (0..du)
                .map(|j| self.transform[i * du + j] * buffers.raw[j])
                .sum::<f32>() as f64;
        }
    }
}

/// [`HostEncoder::encode`] compiled again for the widest vector unit the CPU has, picked at
/// run time. A struct, not a closure: a closure that borrows mutably reaches the dispatch
/// through `FnOnce::call_once`'s shim, which is compiled once for baseline x86-64 and keeps
/// the whole encoder on 128-bit registers.
struct Encode<'a> {
    encoder: &'a mut HostEncoder,
    frame: &'a [u8],
    h: &'a mut [f64],
}

impl pulp::WithSimd for Encode<'_> {
    type Output = ();

    #[inline(always)]
    fn with_simd<S: pulp::Simd>(self, simd: S) {
        self.encoder.encode_here(simd, self.frame, self.h)
    }
}

/// What the tests of each convolution form share: a convolution with fixed weights and the
/// check of a form against im2col + GEMM.
#[cfg(test)]
pub(crate) mod form_checks {
    use super::HostConv;

    /// A form of a convolution run as `(input, side, out, relu)`.
    pub type RunForm<'a> = dyn FnMut(&[f32], usize, &mut Vec<f32>, bool) + 'a;

    /// A convolution with weights in [-0.5, 0.5) and a small bias, fixed by its shape.
    pub fn conv([cin, cout]: [usize; 2], [kernel, stride, padding]: [usize; 3]) -> HostConv {
        let weight: Vec<f32> = (0..cout * cin * kernel * kernel)
            .map(|i| ((i * 7919) % 1000) as f32 / 1000.0 - 0.5)
            .collect();
        let bias: Vec<f32> = (0..cout).map(|o| o as f32 * 0.01 - 0.1).collect();
        HostConv::new(&weight, bias, [cin, cout], kernel, stride, padding)
    }

    /// `run(input, side, out, relu)`, a form of `conv` run on one instance, against `conv`'s
    /// im2col + GEMM on an input of each of `sides` in turn (so the form's scratch is resized
    /// between them), with and without the ReLU: every entry within `tolerance`, relative
    /// above 1 and absolute below.
    pub fn assert_matches_im2col(
        conv: &HostConv,
        sides: &[usize],
        tolerance: f32,
        run: &mut RunForm<'_>,
    ) {
        for &side in sides {
            let input: Vec<f32> = (0..side * side * conv.channels[0])
                .map(|i| ((i * 104_729) % 997) as f32 / 997.0 - 0.5)
                .collect();
            for relu in [false, true] {
                let (mut columns, mut want, mut got) = (Vec::new(), Vec::new(), Vec::new());
                conv.forward(&input, side, &mut columns, &mut want, relu);
                run(&input, side, &mut got, relu);
                assert_eq!(got.len(), want.len());
                for (i, (g, w)) in got.iter().zip(&want).enumerate() {
                    assert!(
                        (g - w).abs() <= tolerance * w.abs().max(1.0),
                        "side {side}, relu {relu}, entry {i}: {g} vs {w}"
                    );
                }
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use crate::model::{cpu_device, frames_to_tensor, to_vec};
    use crate::train::{Method, TrainConfig};

    /// Each shipped encoder runs its convolutions in the forms the design gives them: the
    /// first convolution and a strided second one direct, the reacher's stride-1 second by
    /// Winograd, the keypoint maps' 1x1 as one GEMM and the MLP head's convolution direct.
    #[test]
    fn each_convolution_runs_in_its_fastest_form() {
        use super::ConvForm;
        use crate::envs::EnvKind;
        use crate::train::Preset;
        let names = |forms: &[ConvForm; 3]| {
            forms.clone().map(|form| match form {
                ConvForm::Winograd(_) => "winograd",
                ConvForm::Direct(_) => "direct",
                ConvForm::Im2col => "im2col",
            })
        };
        for (preset, env, want) in [
            (
                Preset::Procl,
                EnvKind::PointMass,
                ["direct", "direct", "im2col"],
            ),
            (
                Preset::Procl,
                EnvKind::Reacher,
                ["direct", "winograd", "im2col"],
            ),
            (
                Preset::Paper,
                EnvKind::PointMass,
                ["direct", "direct", "direct"],
            ),
        ] {
            let config = TrainConfig::preset(preset, Method::Procl, env).model;
            let encoder = config.init(0, &cpu_device()).expect("model").encoder;
            assert_eq!(
                names(&encoder.host_encoder().forms),
                want,
                "{preset:?} {env:?}"
            );
        }
    }

    /// The host encoder gives the tensor encoder's `h` for every shipped head: the point mass's
    /// Cartesian keypoints, the reacher's polar keypoints with their pairwise angles over 32x32
    /// cells and a tanh layer (also under a moving cut), and the paper's MLP head.
    #[test]
    fn host_encoding_matches_the_tensor_encoder() {
        let device = cpu_device();
        let moving_cut = (crate::envs::EnvKind::Reacher, crate::train::Preset::Procl);
        let cases = crate::model::SHIPPED_HEADS.into_iter().map(|c| (c, false));
        for ((env, preset), moving) in cases.chain([(moving_cut, true)]) {
            let mut config = TrainConfig::preset(preset, Method::Procl, env);
            config.model.encoder.polar_moving_cut = moving;
            // The presets start the pairwise angles' weights at 0; here they reach `h`.
            config.model.encoder.pairwise_init_scale = 1.0;
            let frames = crate::model::start_frames(env, 6);
            let encoder = config.model.init(3, &device).expect("model").encoder;
            // A centre and a cut away from the defaults and a signed permutation, as a trained
            // encoder has.
            let encoder = encoder
                .set_polar_frame([0.1, -0.05], [-0.6, 0.8])
                .place_moving_cut(|| frames.iter().map(|f| &f[..]));
            let mut model = crate::model::ProclModel {
                encoder,
                dynamics: config.model.dynamics.init(&device),
            };
            model = model.reorient_latent(&[0.0, -1.0, 1.0, 0.0]);
            let encoder = model.encoder;
            let want =
                to_vec(encoder.forward(frames_to_tensor(frames.iter().map(|f| &f[..]), &device)));
            let mut host = encoder.host_encoder();
            for (k, frame) in frames.iter().enumerate() {
                let mut h = [0.0; 2];
                host.encode(frame, &mut h);
                for i in 0..2 {
                    let w = f64::from(want[2 * k + i]);
                    assert!(
                        (h[i] - w).abs() <= 1e-4 * w.abs().max(1.0),
                        "{env} {preset:?} frame {k} dim {i}: host {} vs {w}",
                        h[i]
                    );
                }
            }
        }
    }
}
