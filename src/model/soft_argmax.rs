//! The spatial soft-argmax (Levine et al. 2016) of one frame's keypoint maps on the host,
//! shared by training's forward pass and the control encoder: each map's attention and its
//! expectation of each grid, with every sum in an order fixed by the code, not the CPU, so a
//! seed gives the same weights on any x86-64 vector unit.

/// The spatial soft-argmax of one frame's keypoint maps `[cells, K]` (a convolution's
/// output): each map's attention `softmax(beta_k m)` into `attention [cells, K]` (the maps'
/// layout) and its expectation of each grid (`[cells]` each) into `expectations [K, G]`.
/// Keys go side by side in blocks of [`KEY_BLOCK`], so each pass reads whole rows of the
/// maps and vectorises over the keys. Sums are taken in f64, each key's over [`SUM_LANES`]
/// running sums (lane `c mod SUM_LANES`) added in lane order: over 1024 cells the f32
/// rounding of an expectation reaches the pairwise angles' gradients in training.
///
/// On a CPU with AVX-512 the key blocks run in [`avx512`]'s explicit 512-bit form, which
/// gives the same bits as the portable form: the auto-vectoriser keeps the portable loops on
/// 256-bit registers.
#[inline(always)]
pub(crate) fn soft_argmax(
    maps: &[f32],
    sharpness: &[f32],
    grids: &[Vec<f32>],
    attention: &mut [f32],
    expectations: &mut [f32],
) {
    #[cfg(target_arch = "x86_64")]
    if let Some(v4) = pulp::x86::V4::try_new() {
        let key_blocks = avx512::KeyBlocks {
            v4,
            maps,
            sharpness,
            grids,
            attention,
            expectations,
        };
        return pulp::Simd::vectorize(v4, key_blocks);
    }
    soft_argmax_portable(maps, sharpness, grids, attention, expectations)
}

/// [`soft_argmax`] in loops the compiler vectorises for whatever CPU it targets.
#[inline(always)]
fn soft_argmax_portable(
    maps: &[f32],
    sharpness: &[f32],
    grids: &[Vec<f32>],
    attention: &mut [f32],
    expectations: &mut [f32],
) {
    by_key_blocks(
        maps,
        sharpness,
        grids,
        (attention, expectations),
        |first, a, e| soft_argmax_keys::<KEY_BLOCK>(maps, sharpness, grids, first, a, e),
    )
}

/// [`soft_argmax`] with `block(first, attention, expectations)` computing each whole block
/// of [`KEY_BLOCK`] keys from `first`, and the keys past the last whole block one by one.
#[inline(always)]
fn by_key_blocks(
    maps: &[f32],
    sharpness: &[f32],
    grids: &[Vec<f32>],
    (attention, expectations): (&mut [f32], &mut [f32]),
    mut block: impl FnMut(usize, &mut [f32], &mut [f32]),
) {
    let k = sharpness.len();
    let whole = k - k % KEY_BLOCK;
    for first in (0..whole).step_by(KEY_BLOCK) {
        block(first, attention, expectations);
    }
    for key in whole..k {
        soft_argmax_keys::<1>(maps, sharpness, grids, key, attention, expectations);
    }
}

/// Keys side by side in [`soft_argmax`]: 16 f32 are one AVX-512 register, and the 16 running
/// f64 sums of one lane in one pass stay in registers.
const KEY_BLOCK: usize = 16;

/// [`soft_argmax`] of the `B` keys from `first`. Each lane's cells are summed in cell order,
/// one lane after the other, so a lane's sums live in registers.
#[inline(always)]
fn soft_argmax_keys<const B: usize>(
    maps: &[f32],
    sharpness: &[f32],
    grids: &[Vec<f32>],
    first: usize,
    attention: &mut [f32],
    expectations: &mut [f32],
) {
    let (k, g) = (sharpness.len(), grids.len());
    let cells = maps.len() / k;
    let at = |cell: usize| cell * k + first;
    let beta = &sharpness[first..][..B];
    let mut max = [f32::NEG_INFINITY; B];
    for cell in 0..cells {
        let m = &maps[at(cell)..][..B];
        for i in 0..B {
            max[i] = max[i].max(beta[i] * m[i]);
        }
    }
    let total = lane_sums::<B>(cells, |cell, sum| {
        let m = &maps[at(cell)..][..B];
        let a = &mut attention[at(cell)..][..B];
        for i in 0..B {
            a[i] = exp_non_positive(beta[i] * m[i] - max[i]);
            sum[i] += f64::from(a[i]);
        }
    });
    let scale: [f32; B] = std::array::from_fn(|i| (1.0 / total[i]) as f32);
    for cell in 0..cells {
        let a = &mut attention[at(cell)..][..B];
        for i in 0..B {
            a[i] *= scale[i];
        }
    }
    for (index, grid) in grids.iter().enumerate() {
        let total = lane_sums::<B>(cells, |cell, dot| {
            let (a, x) = (&attention[at(cell)..][..B], grid[cell]);
            for i in 0..B {
                dot[i] += f64::from(a[i] * x);
            }
        });
        for (i, &e) in total.iter().enumerate() {
            expectations[(first + i) * g + index] = e as f32;
        }
    }
}

/// `B` sums over `cells` in f64: `add(cell, lane)` adds cell `cell`'s terms to its lane's
/// running sums (lane `cell mod SUM_LANES`), each lane's cells in order, one lane after the
/// other so that a lane's sums live in registers; the lanes are then added in order from
/// -0.0, as `Iterator::sum` adds them.
#[inline(always)]
fn lane_sums<const B: usize>(cells: usize, mut add: impl FnMut(usize, &mut [f64; B])) -> [f64; B] {
    let mut total = [-0.0f64; B];
    for lane in 0..SUM_LANES {
        let mut sum = [0.0f64; B];
        for cell in (lane..cells).step_by(SUM_LANES) {
            add(cell, &mut sum);
        }
        for i in 0..B {
            total[i] += sum[i];
        }
    }
    total
}

/// Lanes of each f64 sum in [`soft_argmax`]: one AVX-512 register of f64. A single running
/// sum is a chain of dependent additions the compiler may not reorder, which costs more than
/// the exponentials.
const SUM_LANES: usize = 8;

/// `exp(x)` for `x <= 0` (the softmax's `beta m - max`), within 2 ulp of libm's, in a form
/// the compiler vectorises (a call to libm's `expf` keeps the softmax loop scalar):
/// `exp(x) = 2^n exp(r)`, `n = round(x / ln 2)`, `r = x - n ln 2` in `[-ln 2 / 2, ln 2 / 2]`,
/// with Cephes' degree-6 polynomial for `exp(r)` and `2^n` built in the exponent bits.
/// Below `-87.3` (where `exp` leaves f32's normal range) it returns 0.
#[inline(always)]
pub(crate) fn exp_non_positive(x: f32) -> f32 {
    let clamped = x.max(EXP_FLOOR);
    let n = (clamped * std::f32::consts::LOG2_E + ROUND) - ROUND;
    let r = clamped - n * LN2_HI - n * LN2_LO;
    let poly = EXP_POLY.iter().fold(0.0f32, |acc, &c| acc * r + c);
    let exp_r = poly * r * r + r + 1.0;
    let two_n = f32::from_bits(((n as i32 + 127) as u32) << 23);
    if x < EXP_FLOOR { 0.0 } else { exp_r * two_n }
}

/// Where [`exp_non_positive`] returns 0: `exp` leaves f32's normal range below it.
const EXP_FLOOR: f32 = -87.3;
/// `ln 2` split in two, so that `n ln 2` is exact in the high part for the `n` that occur.
const LN2_HI: f32 = 0.693_359_4;
const LN2_LO: f32 = -2.121_944_4e-4;
/// Cephes' polynomial for `(exp(r) - 1 - r) / r^2`, highest degree first.
const EXP_POLY: [f32; 6] = [
    1.987_569_1e-4,
    1.398_199_9e-3,
    8.333_452e-3,
    4.166_579_6e-2,
    1.666_666_5e-1,
    0.5,
];
/// Rounds to the nearest integer by adding and removing 1.5 * 2^23, where f32 has no
/// fraction bits left: plain additions, which vectorise on any x86-64, where
/// `round_ties_even` becomes a call to libm's `rintf` without SSE4.1.
const ROUND: f32 = 12_582_912.0;

/// [`soft_argmax`]'s key blocks on AVX-512 registers: 16 keys' f32 values are one register and
/// their f64 sums two. Every operation is the portable form's, in its order and without fused
/// multiply-adds, so the two give the same bits (a test holds them to it).
#[cfg(target_arch = "x86_64")]
mod avx512 {
    use pulp::x86::V4;
    use pulp::{Simd, f32x8, f32x16, f64x8};

    use super::{EXP_FLOOR, EXP_POLY, KEY_BLOCK, LN2_HI, LN2_LO, ROUND, SUM_LANES, by_key_blocks};

    /// The arguments of [`super::soft_argmax`], with the vector unit that runs them.
    pub(super) struct KeyBlocks<'a> {
        pub v4: V4,
        pub maps: &'a [f32],
        pub sharpness: &'a [f32],
        pub grids: &'a [Vec<f32>],
        pub attention: &'a mut [f32],
        pub expectations: &'a mut [f32],
    }

    impl pulp::WithSimd for KeyBlocks<'_> {
        type Output = ();

        #[inline(always)]
        fn with_simd<S: Simd>(self, _simd: S) {
            let Self {
                v4,
                maps,
                sharpness,
                grids,
                attention,
                expectations,
            } = self;
            let k = sharpness.len();
            let cells = maps.len() / k.max(1);
            by_key_blocks(
                maps,
                sharpness,
                grids,
                (attention, expectations),
                |first, a, e| {
                    let block = Block {
                        v4,
                        first,
                        k,
                        cells,
                    };
                    block.soft_argmax(maps, sharpness, grids, a, e)
                },
            )
        }
    }

    /// The [`KEY_BLOCK`] keys from `first` of `k`, over `cells` cells.
    #[derive(Clone, Copy)]
    struct Block {
        v4: V4,
        first: usize,
        k: usize,
        cells: usize,
    }

    /// Grids whose expectations one pass over the attention sums: 4 grids' running sums take
    /// 8 of the 32 registers.
    const GRIDS_PER_PASS: usize = 4;

    impl Block {
        /// Where cell `cell`'s 16 values start in a `[cells, K]` array.
        #[inline(always)]
        fn at(self, cell: usize) -> usize {
            cell * self.k + self.first
        }

        /// The portable `soft_argmax_keys::<16>`.
        #[inline(always)]
        fn soft_argmax(
            self,
            maps: &[f32],
            sharpness: &[f32],
            grids: &[Vec<f32>],
            attention: &mut [f32],
            expectations: &mut [f32],
        ) {
            let v4 = self.v4;
            let beta = load(&sharpness[self.first..]);
            // `max(beta m, max)` keeps `max` where `beta m` is NaN, as `f32::max` does.
            let mut max = v4.splat_f32s(f32::NEG_INFINITY);
            for cell in 0..self.cells {
                max = v4.max_f32s(v4.mul_f32s(beta, load(&maps[self.at(cell)..])), max);
            }
            let [total] = self.lane_sums::<1>(|cell, [sum]| {
                let x = v4.sub_f32s(v4.mul_f32s(beta, load(&maps[self.at(cell)..])), max);
                let a = exp_non_positive(v4, x);
                store(&mut attention[self.at(cell)..], a);
                add_widened(v4, sum, a);
            });
            let one = v4.splat_f64s(1.0);
            let scale: f32x16 =
                pulp::cast(total.map(|t| v4.convert_f64x8_to_f32x8(v4.div_f64s(one, t))));
            if grids.is_empty() {
                for cell in 0..self.cells {
                    let a = &mut attention[self.at(cell)..];
                    store(a, v4.mul_f32s(load(a), scale));
                }
            }
            // The first pass also normalises the attention, which the later ones read.
            let mut scale = Some(scale);
            let mut index = 0;
            while index < grids.len() {
                let pass = (grids.len() - index).min(GRIDS_PER_PASS);
                let args = (grids, index, scale);
                match pass {
                    1 => self.expectations::<1>(args, attention, expectations),
                    2 => self.expectations::<2>(args, attention, expectations),
                    3 => self.expectations::<3>(args, attention, expectations),
                    _ => self.expectations::<4>(args, attention, expectations),
                }
                index += pass;
                scale = None;
            }
        }

        /// The expectations of grids `index..index + N` into `expectations [K, G]`, scaling
        /// the attention by `scale` first where it is given.
        #[inline(always)]
        fn expectations<const N: usize>(
            self,
            (grids, index, scale): (&[Vec<f32>], usize, Option<f32x16>),
            attention: &mut [f32],
            expectations: &mut [f32],
        ) {
            let v4 = self.v4;
            let pass: [&[f32]; N] = std::array::from_fn(|n| &grids[index + n][..self.cells]);
            let sums = self.lane_sums::<N>(|cell, dots| {
                let mut a = load(&attention[self.at(cell)..]);
                if let Some(scale) = scale {
                    a = v4.mul_f32s(a, scale);
                    store(&mut attention[self.at(cell)..], a);
                }
                for (dot, grid) in dots.iter_mut().zip(&pass) {
                    add_widened(v4, dot, v4.mul_f32s(a, v4.splat_f32s(grid[cell])));
                }
            });
            for (n, halves) in sums.iter().enumerate() {
                let sums: [f64; KEY_BLOCK] = pulp::cast(*halves);
                for (i, &e) in sums.iter().enumerate() {
                    expectations[(self.first + i) * grids.len() + index + n] = e as f32;
                }
            }
        }

        /// `N` sums of the 16 keys over the cells in f64, as the portable `lane_sums`:
        /// `add(cell, sums)` adds cell `cell`'s terms to its lane's running sums, each lane's
        /// cells in order, one lane after the other; the lanes are then added in order from
        /// -0.0.
        #[inline(always)]
        fn lane_sums<const N: usize>(
            self,
            mut add: impl FnMut(usize, &mut [[f64x8; 2]; N]),
        ) -> [[f64x8; 2]; N] {
            let v4 = self.v4;
            let mut total = [[v4.splat_f64s(-0.0); 2]; N];
            for lane in 0..SUM_LANES {
                let mut sums = [[v4.splat_f64s(0.0); 2]; N];
                for cell in (lane..self.cells).step_by(SUM_LANES) {
                    add(cell, &mut sums);
                }
                for (total, sums) in total.iter_mut().zip(&sums) {
                    for (t, &s) in total.iter_mut().zip(sums) {
                        *t = v4.add_f64s(*t, s);
                    }
                }
            }
            total
        }
    }

    /// 16 keys' values from the front of `values`.
    #[inline(always)]
    fn load(values: &[f32]) -> f32x16 {
        let mut block = [0.0f32; KEY_BLOCK];
        block.copy_from_slice(&values[..KEY_BLOCK]);
        pulp::cast(block)
    }

    #[inline(always)]
    fn store(values: &mut [f32], block: f32x16) {
        values[..KEY_BLOCK].copy_from_slice(&pulp::cast::<f32x16, [f32; KEY_BLOCK]>(block));
    }

    /// Adds each of 16 f32 values, widened to f64, to its key's running sum.
    #[inline(always)]
    fn add_widened(v4: V4, sums: &mut [f64x8; 2], values: f32x16) {
        let halves: [f32x8; 2] = pulp::cast(values);
        for (sum, half) in sums.iter_mut().zip(halves) {
            *sum = v4.add_f64s(*sum, v4.convert_f32x8_to_f64x8(half));
        }
    }

    /// The portable `exp_non_positive`, lane by lane.
    #[inline(always)]
    fn exp_non_positive(v4: V4, x: f32x16) -> f32x16 {
        let splat = |c: f32| v4.splat_f32s(c);
        // `max(x, floor)` gives the floor where `x` is NaN, as `f32::max` does.
        let clamped = v4.max_f32s(x, splat(EXP_FLOOR));
        let scaled = v4.mul_f32s(clamped, splat(std::f32::consts::LOG2_E));
        let n = v4.sub_f32s(v4.add_f32s(scaled, splat(ROUND)), splat(ROUND));
        let r = v4.sub_f32s(clamped, v4.mul_f32s(n, splat(LN2_HI)));
        let r = v4.sub_f32s(r, v4.mul_f32s(n, splat(LN2_LO)));
        let poly = EXP_POLY.iter().fold(splat(0.0), |acc, &c| {
            v4.add_f32s(v4.mul_f32s(acc, r), splat(c))
        });
        let exp_r = v4.mul_f32s(v4.mul_f32s(poly, r), r);
        let exp_r = v4.add_f32s(v4.add_f32s(exp_r, r), splat(1.0));
        let biased = v4.wrapping_add_i32x16(v4.convert_f32x16_to_i32x16(n), v4.splat_i32x16(127));
        let two_n: f32x16 = pulp::cast(v4.shl_const_i32x16::<23>(biased));
        let value = v4.mul_f32s(exp_r, two_n);
        v4.select_f32s(v4.less_than_f32s(x, splat(EXP_FLOOR)), splat(0.0), value)
    }
}

#[cfg(test)]
mod tests {
    use super::SUM_LANES;

    #[test]
    fn exp_non_positive_is_within_two_ulp_of_libm() {
        // Every 1e-4 from -87 to 0, and the edges: 1 at 0, 0 past f32's normal range.
        let mut worst = 0.0f64;
        for k in 0..=870_000 {
            let x = -(k as f32) * 1e-4;
            let (got, want) = (super::exp_non_positive(x), x.exp());
            worst = worst.max(f64::from((got - want).abs() / want));
        }
        assert!(
            worst < 2.0 * f64::from(f32::EPSILON),
            "relative error {worst:e}"
        );
        assert_eq!(super::exp_non_positive(0.0), 1.0);
        assert_eq!(super::exp_non_positive(-100.0), 0.0);
        assert_eq!(super::exp_non_positive(f32::NEG_INFINITY), 0.0);
    }

    /// `sum_i a_i b_i` in f64 over [`SUM_LANES`] running sums (lane `i mod SUM_LANES`) added
    /// in lane order: one key's row of [`super::soft_argmax`]'s sums.
    fn lane_dot(a: &[f32], b: &[f32]) -> f64 {
        let mut lanes = [0.0f64; SUM_LANES];
        for (i, (&a, &b)) in a.iter().zip(b).enumerate() {
            lanes[i % SUM_LANES] += f64::from(a * b);
        }
        lanes.iter().sum()
    }

    #[test]
    fn lane_sums_equal_the_plain_sums() {
        // 21 values: lanes 0-4 take three each, lanes 5-7 two; quarters sum exactly.
        let values: Vec<f32> = (0..21).map(|i| i as f32 * 0.25).collect();
        let index: Vec<f32> = (0..21).map(|i| i as f32).collect();
        assert_eq!(lane_dot(&values, &[1.0; 21]), 52.5);
        let weighted = lane_dot(&values, &index);
        assert_eq!(
            weighted,
            (0..21).map(|i| (i * i) as f64 * 0.25).sum::<f64>()
        );
    }

    /// The soft-argmax over `[cells, K]` maps gives, bit for bit, each key's softmax and
    /// expectations computed row by row (so training from a seed keeps its weights whichever
    /// way the passes run), in its portable form and on the widest vector unit the CPU has
    /// (the explicit AVX-512 form where there is one; elsewhere both are the portable form);
    /// on 1027 cells (a tail past the lanes), 37 keys of different sharpness (two blocks of
    /// 16 and 5 one by one) and 0 to 5 grids (5: two passes).
    #[test]
    fn soft_argmax_equals_the_row_by_row_softmax() {
        let (cells, k) = (1027, 37);
        let maps: Vec<f32> = (0..cells * k)
            .map(|i| ((i * 7919) % 1000) as f32 / 250.0 - 2.0)
            .collect();
        let sharpness: Vec<f32> = (0..k).map(|key| 0.5 + key as f32 * 1.5).collect();
        type SoftArgmax = fn(&[f32], &[f32], &[Vec<f32>], &mut [f32], &mut [f32]);
        let forms: [(&str, SoftArgmax); 2] = [
            ("portable", super::soft_argmax_portable),
            ("widest", super::soft_argmax),
        ];
        for (form, soft_argmax) in forms {
            for grid_count in 0..=5 {
                let grids: Vec<Vec<f32>> = (0..grid_count)
                    .map(|g| {
                        (0..cells)
                            .map(|c| ((c * (g + 3)) % 64) as f32 / 32.0 - 1.0)
                            .collect()
                    })
                    .collect();
                let mut attention = vec![0.0; cells * k];
                let mut expectations = vec![0.0; k * grids.len()];
                soft_argmax(&maps, &sharpness, &grids, &mut attention, &mut expectations);
                let got = (form, &attention[..], &expectations[..]);
                check_row_by_row(&maps, &sharpness, &grids, got);
            }
        }
    }

    /// `attention` and `expectations` of one soft-argmax form against the row-by-row softmax.
    fn check_row_by_row(
        maps: &[f32],
        sharpness: &[f32],
        grids: &[Vec<f32>],
        (form, attention, expectations): (&str, &[f32], &[f32]),
    ) {
        let k = sharpness.len();
        let cells = maps.len() / k;
        for (key, &beta) in sharpness.iter().enumerate() {
            let row: Vec<f32> = (0..cells).map(|c| maps[c * k + key]).collect();
            let max = row.iter().fold(f32::NEG_INFINITY, |m, &v| m.max(beta * v));
            let e: Vec<f32> = row
                .iter()
                .map(|&v| super::exp_non_positive(beta * v - max))
                .collect();
            let scale = (1.0 / lane_dot(&e, &vec![1.0; cells])) as f32;
            let a: Vec<f32> = e.iter().map(|&e| e * scale).collect();
            for c in 0..cells {
                assert_eq!(
                    attention[c * k + key].to_bits(),
                    a[c].to_bits(),
                    "{form}: key {key} cell {c}"
                );
            }
            for (g, grid) in grids.iter().enumerate() {
                let want = lane_dot(&a, grid) as f32;
                assert_eq!(
                    expectations[key * grids.len() + g].to_bits(),
                    want.to_bits(),
                    "{form}: key {key} grid {g}"
                );
            }
        }
    }
}
