//! The regularisers the reacher preset adds to the paper's objective (docs/design.md): a
//! variance floor against latent collapse and the sign term on the latent's regional response
//! to the action, with its singular-value floor.

use burn::tensor::activation::relu;
use burn::tensor::{Tensor, TensorData};

/// Per-dimension population std over the batch, `[n, du] -> [1, du]` (a tiny floor under the
/// variance keeps the gradient of a collapsed dimension finite).
pub(super) fn batch_std(h: Tensor<2>) -> Tensor<2> {
    let mean = h.clone().mean_dim(0);
    (h - mean)
        .powi_scalar(2)
        .mean_dim(0)
        .add_scalar(1e-12)
        .sqrt()
}

/// `a` and `x` centred over their rows, and the inverse of the centred `x^T x` solved on the
/// host in f64 (nalgebra): the start of every least-squares fit `a ~ x B + c` here. `None` when
/// `x` is degenerate (no fit to judge).
fn centred_gram_inverse(
    a: Tensor<2>,
    x: Tensor<2>,
) -> Option<(Tensor<2>, Tensor<2>, nalgebra::DMatrix<f64>)> {
    let centre = |t: Tensor<2>| t.clone() - t.mean_dim(0);
    let (a, x) = (centre(a), centre(x));
    let inverse = host_matrix(x.clone().transpose().matmul(x.clone()))
        .try_inverse()
        .filter(|m| m.iter().all(|v| v.is_finite()))?;
    Some((a, x, inverse))
}

/// A tensor's values (row-major `[rows, cols]`, detached) as a column-major nalgebra matrix.
fn host_matrix(t: Tensor<2>) -> nalgebra::DMatrix<f64> {
    let [rows, cols] = t.dims();
    let values = crate::model::to_vec(t.detach());
    nalgebra::DMatrix::from_row_iterator(rows, cols, values.into_iter().map(f64::from))
}

/// A host matrix as a constant tensor on `device` (f32, no gradient).
fn device_matrix(m: &nalgebra::DMatrix<f64>, device: &burn::tensor::Device) -> Tensor<2> {
    let values: Vec<f32> = m.transpose().iter().map(|&v| v as f32).collect();
    Tensor::<2>::from_data(TensorData::new(values, [m.nrows(), m.ncols()]), device)
}

/// The least-squares coefficients `B [p, d]` of `a ~ x B + c` with the gradient through `x^T a`
/// only: `(x^T x)^-1` is solved on the host and held fixed. `None` when `x` is degenerate.
fn least_squares_coefficients(a: Tensor<2>, x: Tensor<2>) -> Option<Tensor<2>> {
    let (a, x, inverse) = centred_gram_inverse(a, x)?;
    Some(device_matrix(&inverse, &x.device()).matmul(x.transpose().matmul(a)))
}

/// The sign term (see [`super::LossConfig::action_response_sign_weight`]) of the response
/// `a [n, d]` on the regressors `x [n, p]`, whose last `d` columns are the drive: the mean over
/// `regions` groups of `h [n, d]` (contiguous along its first principal axis) of
/// `sum_i relu(-D_r[i, i]) / s`, plus `relu(singular_floor - sigma_min(D_r) / s)` where
/// `singular_floor > 0` (see [`super::LossConfig::action_response_singular_floor`]). 0 when `x`
/// has fewer than `d` columns, the batch has too few rows per group to fit (`p + 2`), or a fit
/// is degenerate.
pub fn action_response_sign(
    a: Tensor<2>,
    x: Tensor<2>,
    h: Tensor<2>,
    regions: usize,
    singular_floor: f64,
) -> Tensor<1> {
    let device = x.device();
    let zero = || Tensor::zeros([1], &device);
    let [n, p] = x.dims();
    let [_, d] = a.dims();
    if p < d || regions == 0 || n / regions < p + 2 {
        return zero();
    }
    // The drive block's diagonal: rows p - d + i, column i of B.
    let diagonal_mask = {
        let mut mask = vec![0f32; p * d];
        for i in 0..d {
            mask[(p - d + i) * d + i] = 1.0;
        }
        Tensor::<2>::from_data(TensorData::new(mask, [p, d]), &device)
    };
    let drive_rows = Tensor::<1, burn::tensor::Int>::arange((p - d) as i64..p as i64, &device);
    let Some(whole) = least_squares_coefficients(a.clone(), x.clone()) else {
        return zero();
    };
    let scale = crate::model::to_vec(
        whole
            .select(0, drive_rows.clone())
            .detach()
            .powi_scalar(2)
            .mean(),
    )[0]
    .sqrt() as f64;
    if !(scale.is_finite() && scale > 0.0) {
        return zero();
    }
    let mut total = zero();
    let groups = principal_axis_groups(h, regions);
    let count = groups.len();
    for index in groups {
        let Some(local) = least_squares_coefficients(
            a.clone().select(0, index.clone()),
            x.clone().select(0, index),
        ) else {
            return zero();
        };
        total = total
            + relu((local.clone() * diagonal_mask.clone()).neg())
                .sum()
                .reshape([1]);
        if singular_floor > 0.0 {
            // In the scale's units, like the diagonal: `relu(rho s - sigma_min)`.
            let drive = local.select(0, drive_rows.clone());
            total = total
                + relu(
                    smallest_singular_value(drive)
                        .neg()
                        .add_scalar(singular_floor * scale),
                );
        }
    }
    total / (count as f64 * scale)
}

/// The smallest singular value of the square map `m [d, d]`, `[1]`, as `u^T m v` with the
/// singular vectors `u`, `v` of the host's SVD (f64, nalgebra) held fixed: its value, and its
/// exact gradient `u v^T` wherever the smallest singular value is simple. 0 (no gradient) when
/// the SVD fails.
fn smallest_singular_value(m: Tensor<2>) -> Tensor<1> {
    let device = m.device();
    let host = host_matrix(m.clone());
    let svd = nalgebra::linalg::SVD::new(host, true, true);
    let smallest = svd
        .singular_values
        .iter()
        .enumerate()
        .min_by(|(_, x), (_, y)| x.total_cmp(y))
        .map(|(i, _)| i);
    let (Some(i), Some(u), Some(v_t)) = (smallest, svd.u, svd.v_t) else {
        return Tensor::zeros([1], &device);
    };
    let outer = u.column(i) * v_t.row(i);
    (m * device_matrix(&outer, &device)).sum().reshape([1])
}

/// Row indices of `h [n, du]` sorted by their projection on its first principal axis (the
/// eigenvector of the centred covariance with the largest eigenvalue; ties keep row order).
fn principal_axis_order(h: Tensor<2>) -> Vec<usize> {
    let [n, du] = h.dims();
    let values = crate::model::to_vec(h.detach());
    let rows = nalgebra::DMatrix::from_row_iterator(n, du, values.into_iter().map(f64::from));
    let mean = rows.row_mean();
    let centred = nalgebra::DMatrix::from_fn(n, du, |i, j| rows[(i, j)] - mean[j]);
    let eigen = (centred.transpose() * &centred).symmetric_eigen();
    let axis = eigen.eigenvalues.imax();
    let projection = centred * eigen.eigenvectors.column(axis);
    let mut order: Vec<usize> = (0..n).collect();
    order.sort_by(|&i, &j| projection[i].total_cmp(&projection[j]));
    order
}

/// The row indices of the sign term's groups of `h [n, du]`: `regions` near-equal contiguous
/// slices along its first principal axis (rows `[r n / R, (r + 1) n / R)` of
/// [`principal_axis_order`] for group `r`).
fn principal_axis_groups(h: Tensor<2>, regions: usize) -> Vec<Tensor<1, burn::tensor::Int>> {
    let [n, _] = h.dims();
    let device = h.device();
    let order = principal_axis_order(h);
    (0..regions)
        .map(|r| {
            let rows: Vec<i64> = order[r * n / regions..(r + 1) * n / regions]
                .iter()
                .map(|&i| i as i64)
                .collect();
            let len = rows.len();
            Tensor::<1, burn::tensor::Int>::from_data(TensorData::new(rows, [len]), &device)
        })
        .collect()
}

#[cfg(test)]
mod tests {
    //! Every pinned number below was computed by hand, not by running the code under test.

    use burn::tensor::{Device, Tensor};

    use super::*;
    use crate::losses::test_support::{scalar, t2};
    use crate::model::{cpu_device, to_vec};

    /// Three groups of 4 samples along a line in `h` (turned by `(c, s)`), each with the
    /// actions (1,0), (0,1), (-1,0), (0,-1) (so `x^T x = 2 I` per group), responding by
    /// `a = u B_g`, the response turned with the latent; rows shuffled, so the groups come
    /// from `h`'s principal axis and not from the row order. Returns `(h, u, a)`.
    fn regional_responses(
        maps: [[[f32; 2]; 2]; 3],
        (c, s): (f32, f32),
        device: &Device,
    ) -> (Tensor<2>, Tensor<2>, Tensor<2>) {
        let actions = [[1.0f32, 0.0], [0.0, 1.0], [-1.0, 0.0], [0.0, -1.0]];
        let shuffle = [5usize, 0, 11, 3, 8, 1, 10, 6, 2, 9, 4, 7];
        let (mut h, mut u, mut a) = (vec![], vec![], vec![]);
        for &row in &shuffle {
            let (group, k) = (row / 4, row % 4);
            let position = row as f32;
            h.extend([position * c, position * s]);
            let [u0, u1] = actions[k];
            u.extend([u0, u1]);
            let b = maps[group];
            let (a0, a1) = (u0 * b[0][0] + u1 * b[1][0], u0 * b[0][1] + u1 * b[1][1]);
            a.extend([a0 * c - a1 * s, a0 * s + a1 * c]);
        }
        (
            t2(&h, 12, 2, device),
            t2(&u, 12, 2, device),
            t2(&a, 12, 2, device),
        )
    }

    const IDENTITY: [[f32; 2]; 2] = [[1.0, 0.0], [0.0, 1.0]];
    const MINUS: [[f32; 2]; 2] = [[-1.0, 0.0], [0.0, -1.0]];

    #[test]
    fn sign_term_charges_regions_whose_response_runs_backwards() {
        // B_g = I, I, -I: the whole batch fits I / 3, whose entries' root mean square is
        // sqrt(2 / 9 / 4) = 1 / (3 sqrt 2). The third group's diagonal is (-1, -1): relu sum 2,
        // mean over the 3 groups 2/3, over the scale: 2 sqrt 2.
        let device = cpu_device().autodiff();
        let sign = |maps, regions| {
            let (h, u, a) = regional_responses(maps, (1.0, 0.0), &device);
            scalar(action_response_sign(a, u, h, regions, 0.0))
        };
        let want = 2.0 * 2f64.sqrt();
        assert!((sign([IDENTITY, IDENTITY, MINUS], 3) - want).abs() < 1e-4);
        // Responses that move each coordinate forwards cost nothing, turned or not (a 60
        // degree turn keeps the diagonal at cos 60 > 0).
        let turned = [[0.5f32, 0.866], [-0.866, 0.5]];
        assert_eq!(sign([IDENTITY, turned, IDENTITY], 3), 0.0);
        // Overall scale does not matter: the same batch at a tenth of the response.
        let tenth = |m: [[f32; 2]; 2]| m.map(|row| row.map(|v| v / 10.0));
        assert!((sign([tenth(IDENTITY), tenth(IDENTITY), tenth(MINUS)], 3) - want).abs() < 1e-3);
        // Too few rows per group: no judgement.
        assert_eq!(sign([IDENTITY, IDENTITY, MINUS], 4), 0.0);
        // The gradient reaches only the backwards group's responses (rows 8-11 before the
        // shuffle), pushing each along its own action: d/da of -B_ii with B = (x^T x)^-1 x^T a
        // is -u_i / 2 per row, times 1 / (3 groups x the scale 1 / (3 sqrt 2)) = sqrt 2.
        for (row, u, grad) in sign_gradient([IDENTITY, IDENTITY, MINUS], 0.0) {
            for i in 0..2 {
                let want = if row >= 8 {
                    -f64::from(u[i]) / 2.0 * 2f64.sqrt()
                } else {
                    0.0
                };
                assert!((grad[i] - want).abs() < 1e-4, "row {row}, dim {i}");
            }
        }
    }

    /// The sign term's gradient with respect to the response `a` of [`regional_responses`]
    /// (unturned, three groups along the principal axis, the diagonal form plus
    /// `singular_floor`): for each row, its index before the shuffle, its action and its
    /// gradient.
    fn sign_gradient(
        maps: [[[f32; 2]; 2]; 3],
        singular_floor: f64,
    ) -> Vec<(usize, [f32; 2], [f64; 2])> {
        let device = cpu_device().autodiff();
        let (h, u, a) = regional_responses(maps, (1.0, 0.0), &device);
        let a = a.require_grad();
        let loss = action_response_sign(a.clone(), u.clone(), h, 3, singular_floor);
        let grads = loss.backward();
        let got = to_vec(a.grad(&grads).expect("gradient of a"));
        let u = to_vec(u);
        let shuffle = [5usize, 0, 11, 3, 8, 1, 10, 6, 2, 9, 4, 7];
        shuffle
            .iter()
            .enumerate()
            .map(|(k, &row)| {
                let grad = [f64::from(got[2 * k]), f64::from(got[2 * k + 1])];
                (row, [u[2 * k], u[2 * k + 1]], grad)
            })
            .collect()
    }

    #[test]
    fn singular_floor_charges_a_group_whose_map_squashes_a_direction() {
        // B_g = I, I and W = diag(1, 0.1) (a faint wrist; the diagonal is positive, so the sign
        // term alone charges nothing). The whole batch fits diag(1, 0.7), rms entry s =
        // sqrt(1.49) / 2. With rho = 0.5 only W is under the floor: (rho s - 0.1) over 3 groups
        // and the scale, (0.5 - 0.1 / s) / 3.
        let device = cpu_device().autodiff();
        let faint = [[1.0f32, 0.0], [0.0, 0.1]];
        let sign = |maps, turn, floor| {
            let (h, u, a) = regional_responses(maps, turn, &device);
            scalar(action_response_sign(a, u, h, 3, floor))
        };
        let scale = 1.49f64.sqrt() / 2.0;
        let want = (0.5 - 0.1 / scale) / 3.0;
        assert_eq!(sign([IDENTITY, IDENTITY, faint], (1.0, 0.0), 0.0), 0.0);
        let got = sign([IDENTITY, IDENTITY, faint], (1.0, 0.0), 0.5);
        assert!((got - want).abs() < 1e-4, "{got} vs {want}");
        // Singular values do not see the latent's rotation (here by (0.6, 0.8)), which the
        // diagonal does.
        let got = sign([IDENTITY, IDENTITY, faint], (0.6, 0.8), 0.5);
        assert!((got - want).abs() < 1e-4, "{got} vs {want}");
        // A map turned by 60 degrees keeps both singular values at 1: nothing to charge.
        let (c, s) = (60f32.to_radians().cos(), 60f32.to_radians().sin());
        let turned = [[c, s], [-s, c]];
        assert!(sign([IDENTITY, turned, IDENTITY], (1.0, 0.0), 0.5).abs() < 1e-6);
        // The gradient reaches only the faint group's rows (8-11 before the shuffle), and only
        // along the wrist: d sigma_min / dB = e_1 e_1^T, so d/da_1 is -u_1 / 2 per row over 3
        // groups and the scale, and the shoulder's response a_0 gets nothing.
        for (row, u, grad) in sign_gradient([IDENTITY, IDENTITY, faint], 0.5) {
            let want_wrist = if row >= 8 {
                -f64::from(u[1]) / 2.0 / (3.0 * scale)
            } else {
                0.0
            };
            assert!(grad[0].abs() < 1e-5, "row {row}: {}", grad[0]);
            assert!(
                (grad[1] - want_wrist).abs() < 1e-4,
                "row {row}: {} vs {want_wrist}",
                grad[1]
            );
        }
    }
}
