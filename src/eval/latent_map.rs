//! Latent diagnostics: encode a grid of true configurations, plot `h` coloured by the true
//! configuration, and measure how linear the map is (R^2 of q from h, determinant of the fitted
//! q -> h map: its sign says whether PD on h pushes the right way).

use std::path::Path;

use burn::tensor::Device;
use plotters::prelude::*;

use crate::envs::{EnvConfig, FRAME_BYTES, State};
use crate::error::Result;
use crate::model::{LatentEncoder, frames_to_tensor, to_vec};

/// How usable a latent is, at a glance.
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct LatentDiagnostics {
    /// R^2 of the least-squares linear fit q ~ A h + b, averaged over configuration dims.
    pub linear_r2: f64,
    /// R^2 per configuration dimension.
    pub linear_r2_per_dim: Vec<f64>,
    /// The fitted map h ~ M q + c (rows: h dims), and det(M) for 2x2 and 3x3 maps.
    pub config_to_latent: Vec<Vec<f64>>,
    pub config_to_latent_det: Option<f64>,
    /// R^2 of q from a leave-one-out 5-nearest-neighbour regression on h (averaged over
    /// configuration dims): near 1 when h determines q, even through a curved map that the
    /// linear R^2 scores low (the reacher's ring-shaped latents), near 0 when h forgets q.
    #[serde(default)]
    pub knn_r2: f64,
    /// Share of the grid's far-apart pairs that the latent folds together (see
    /// [`folded_share`]): 0 for an injective map whatever its shape. The 5-NN R^2 averages
    /// folds away when they are small; PD stops on them (docs/design.md, "Diagnostics").
    #[serde(default)]
    pub folded_share: f64,
    /// Share of the grid's pairs of configurations whose latent PD torque at rest pushes away
    /// from the goal (see [`pushes_away_share`]); `None` when `h` and `q` differ in dimension.
    #[serde(default)]
    pub pushes_away_share: Option<f64>,
    /// Share of the grid's interior cells whose local map `dh/dq` (central differences) PD
    /// cannot hold a goal with: an eigenvalue with no positive real part (see
    /// [`local_map_shares`]); `None` unless `q` and `h` are both 2-D.
    #[serde(default)]
    pub locally_unstable_share: Option<f64>,
    /// Share of the grid's interior cells whose local map is nearly singular: its smaller
    /// singular value under [`NEAR_SINGULAR`] of its larger, so a valley of configurations
    /// shares one latent and PD stops anywhere along it (the reacher's near misses with the
    /// wrist straight; docs/design.md, "Diagnostics"). `None` unless `q` and `h` are 2-D.
    #[serde(default)]
    pub near_singular_share: Option<f64>,
    /// Grid points encoded.
    pub points: usize,
    /// How far `h` is turned from the action axes, from fresh random-control episodes
    /// ([`super::readout::readout_check`]); `None` where the fit is singular.
    #[serde(default)]
    pub readout: Option<super::readout::ReadoutCheck>,
}

/// The determinant of a square 2x2 or 3x3 matrix (rows), `None` for other shapes.
pub fn determinant(m: &[Vec<f64>]) -> Option<f64> {
    if m.iter().any(|row| row.len() != m.len()) {
        return None;
    }
    match m.len() {
        2 => Some(m[0][0] * m[1][1] - m[0][1] * m[1][0]),
        3 => Some(
            m[0][0] * (m[1][1] * m[2][2] - m[1][2] * m[2][1])
                - m[0][1] * (m[1][0] * m[2][2] - m[1][2] * m[2][0])
                + m[0][2] * (m[1][0] * m[2][1] - m[1][1] * m[2][0]),
        ),
        _ => None,
    }
}

/// A pair counts as far apart when its configuration distance exceeds this share of the mean
/// over all pairs: on the reacher's grid about 0.5 rad, five times the success threshold.
const FOLD_FAR: f64 = 0.25;
/// ... and as folded together when its latent distance is under this share of the mean.
const FOLD_CLOSE: f64 = 0.02;

/// The share of pairs of `configs` further apart than [`FOLD_FAR`] times their mean distance
/// whose `latents` lie closer than [`FOLD_CLOSE`] times theirs: the pairs PD on the latent
/// cannot tell apart. 0 with fewer than 2 points or no far pair.
pub fn folded_share(latents: &[Vec<f64>], configs: &[Vec<f64>]) -> f64 {
    let distance = |a: &[f64], b: &[f64]| {
        a.iter()
            .zip(b)
            .map(|(x, y)| (x - y).powi(2))
            .sum::<f64>()
            .sqrt()
    };
    let n = configs.len().min(latents.len());
    let pairs: Vec<(f64, f64)> = (0..n)
        .flat_map(|i| (i + 1..n).map(move |j| (i, j)))
        .map(|(i, j)| {
            (
                distance(&configs[i], &configs[j]),
                distance(&latents[i], &latents[j]),
            )
        })
        .collect();
    if pairs.is_empty() {
        return 0.0;
    }
    let mean =
        |pick: fn(&(f64, f64)) -> f64| pairs.iter().map(pick).sum::<f64>() / pairs.len() as f64;
    let (far, close) = (FOLD_FAR * mean(|p| p.0), FOLD_CLOSE * mean(|p| p.1));
    let far_pairs = pairs.iter().filter(|p| p.0 > far);
    let (count, folded) = far_pairs.fold((0usize, 0usize), |(count, folded), p| {
        (count + 1, folded + usize::from(p.1 < close))
    });
    if count == 0 {
        0.0
    } else {
        folded as f64 / count as f64
    }
}

/// The share of unordered pairs `(q_i, q_j)` of `configs` for which PD on the latent, started
/// at rest at either one with the other as goal, applies an action with no positive component
/// towards the goal: `(q_j - q_i) . (h_j - h_i) <= 0`. The action at rest is `Kp (h* - h)` with
/// one scalar gain, and the env's actuators apply it with one gear for every joint, so this is
/// the sign of the work the first torque does along the straight path to the goal: a latent
/// with `h` the gradient of a strictly convex function of `q` (for instance `q` itself, up to
/// a positive scale) has none, a mirrored or crossed-over axis has many. `None` when the
/// dimensions differ or there are fewer than 2 points.
pub fn pushes_away_share(latents: &[Vec<f64>], configs: &[Vec<f64>]) -> Option<f64> {
    let n = configs.len().min(latents.len());
    let same_dims = configs.iter().zip(latents).all(|(q, h)| q.len() == h.len());
    if n < 2 || !same_dims {
        return None;
    }
    let work = |i: usize, j: usize| -> f64 {
        configs[j]
            .iter()
            .zip(&configs[i])
            .zip(latents[j].iter().zip(&latents[i]))
            .map(|((qj, qi), (hj, hi))| (qj - qi) * (hj - hi))
            .sum()
    };
    let pairs = n * (n - 1) / 2;
    let away = (0..n)
        .flat_map(|i| (i + 1..n).map(move |j| (i, j)))
        .filter(|&(i, j)| work(i, j) <= 0.0)
        .count();
    Some(away as f64 / pairs as f64)
}

/// A local map counts as nearly singular when its smaller singular value is under this share of
/// its larger.
pub const NEAR_SINGULAR: f64 = 0.1;

/// The local maps `J = dh/dq` at the interior points of a `side x side` grid of 2-D
/// configurations in [`config_grid`]'s order (`k = i + side j`, `i` along `q_0`), by central
/// differences, summarised as the shares of them that are locally unstable under PD and nearly
/// singular: `(unstable, near_singular)`.
///
/// PD on the latent applies `u = Kp (h* - h) - Kd dh/dt` through one gear per joint, so near a
/// goal `M q'' = -J (Kp dq + Kd q')`: with `M` near a multiple of the identity it holds the goal
/// only where both eigenvalues of `J` have positive real parts, for a 2x2 map `tr J > 0` and
/// `det J > 0` (a map turned past 90 degrees or mirrored fails). A nearly singular `J` holds
/// the goal only up to a valley. `None` unless every configuration and latent is 2-D and
/// there are `side^2 >= 9` of each.
pub fn local_map_shares(
    latents: &[Vec<f64>],
    configs: &[Vec<f64>],
    side: usize,
) -> Option<(f64, f64)> {
    let n = side * side;
    let two_d = |v: &[Vec<f64>]| v.len() == n && v.iter().all(|x| x.len() == 2);
    if side < 3 || !two_d(latents) || !two_d(configs) {
        return None;
    }
    let (mut unstable, mut singular, mut cells) = (0usize, 0usize, 0usize);
    for j in 1..side - 1 {
        for i in 1..side - 1 {
            let k = i + side * j;
            // Column c of J: the latent's change over the configuration's along q_c.
            let column = |before: usize, after: usize, c: usize| -> [f64; 2] {
                let dq = configs[after][c] - configs[before][c];
                [0, 1].map(|r| (latents[after][r] - latents[before][r]) / dq)
            };
            let (a, b) = (column(k - 1, k + 1, 0), column(k - side, k + side, 1));
            let (trace, det) = (a[0] + b[1], a[0] * b[1] - b[0] * a[1]);
            // Singular values: s^2 = (F +- sqrt(F^2 - 4 det^2)) / 2, F the squared norm.
            let frobenius = a[0] * a[0] + a[1] * a[1] + b[0] * b[0] + b[1] * b[1];
            let spread = (frobenius * frobenius - 4.0 * det * det).max(0.0).sqrt();
            let (large, small) = (
                (frobenius + spread) / 2.0,
                (frobenius - spread).max(0.0) / 2.0,
            );
            cells += 1;
            unstable += usize::from(!(trace > 0.0 && det > 0.0));
            singular += usize::from(small.sqrt() < NEAR_SINGULAR * large.sqrt());
        }
    }
    Some((
        unstable as f64 / cells as f64,
        singular as f64 / cells as f64,
    ))
}

/// Leave-one-out `k`-nearest-neighbour regression of `targets` from `inputs` (Euclidean in
/// the inputs, ties broken by index), scored as R^2 per target dimension.
pub fn knn_r2(inputs: &[Vec<f64>], targets: &[Vec<f64>], k: usize) -> Vec<f64> {
    let n = inputs.len();
    let dims = targets.first().map_or(0, Vec::len);
    let mut predictions = vec![vec![0.0; dims]; n];
    for (i, x) in inputs.iter().enumerate() {
        let mut by_distance: Vec<(f64, usize)> = (0..n)
            .filter(|&j| j != i)
            .map(|j| {
                let d: f64 = x.iter().zip(&inputs[j]).map(|(a, b)| (a - b).powi(2)).sum();
                (d, j)
            })
            .collect();
        by_distance.sort_by(|a, b| a.0.total_cmp(&b.0).then(a.1.cmp(&b.1)));
        let neighbours = &by_distance[..k.min(by_distance.len())];
        for (d, p) in predictions[i].iter_mut().enumerate() {
            *p = neighbours.iter().map(|&(_, j)| targets[j][d]).sum::<f64>()
                / neighbours.len().max(1) as f64;
        }
    }
    (0..dims)
        .map(|d| {
            let mean = targets.iter().map(|t| t[d]).sum::<f64>() / n.max(1) as f64;
            let total: f64 = targets.iter().map(|t| (t[d] - mean).powi(2)).sum();
            let residual: f64 = targets
                .iter()
                .zip(&predictions)
                .map(|(t, p)| (t[d] - p[d]).powi(2))
                .sum();
            if total > 0.0 {
                1.0 - residual / total
            } else {
                0.0
            }
        })
        .collect()
}

/// Configurations on a `side x side` grid over the first two dimensions of the env's
/// configuration box (at rest). A third dimension (Fetch's height) steps through `side` levels
/// along the grid's diagonals, so the linear fit sees it vary apart from the first two.
pub fn config_grid(env: &EnvConfig, side: usize) -> Vec<Vec<f64>> {
    let ranges = env.make().config_ranges();
    let lerp = |r: [f64; 2], k: usize| r[0] + (r[1] - r[0]) * (k as f64 + 0.5) / side as f64;
    (0..side * side)
        .map(|k| {
            let (i, j) = (k % side, k / side);
            let level = |d: usize| match d {
                0 => i,
                1 => j,
                _ => (i + j) % side,
            };
            ranges
                .iter()
                .enumerate()
                .map(|(d, &r)| lerp(r, level(d)))
                .collect()
        })
        .collect()
}

/// Encodes the configurations `configs` (rendered at rest) in batches.
pub fn encode_configs(
    env: &EnvConfig,
    encoder: &dyn LatentEncoder,
    configs: &[Vec<f64>],
    device: &Device,
) -> Result<Vec<Vec<f64>>> {
    let mut sim = env.make();
    let mut frames = vec![[0u8; FRAME_BYTES]; configs.len()];
    for (q, frame) in configs.iter().zip(frames.iter_mut()) {
        sim.set_state(&State {
            q: q.clone(),
            qd: vec![0.0; q.len()],
        })?;
        sim.render(frame);
    }
    let mut latents = vec![];
    for chunk in frames.chunks(256) {
        let h = encoder.encode(frames_to_tensor(chunk.iter().map(|f| f.as_slice()), device));
        let du = h.dims()[1];
        let values = to_vec(h);
        latents.extend(
            values
                .chunks(du)
                .map(|row| row.iter().map(|&x| x as f64).collect::<Vec<f64>>()),
        );
    }
    Ok(latents)
}

/// Least squares `y ~ W [x, 1]`: returns W as rows (one per y dim) and the R^2 of each y dim.
pub fn linear_fit(x: &[Vec<f64>], y: &[Vec<f64>]) -> (Vec<Vec<f64>>, Vec<f64>) {
    let (dx, dy) = (
        x.first().map_or(0, Vec::len) + 1,
        y.first().map_or(0, Vec::len),
    );
    // Normal equations (X^T X) W^T = X^T Y, with a tiny ridge for degenerate (collapsed) inputs.
    let mut xtx = vec![vec![0.0; dx]; dx];
    let mut xty = vec![vec![0.0; dy]; dx];
    for (xi, yi) in x.iter().zip(y) {
        let row: Vec<f64> = xi.iter().copied().chain(std::iter::once(1.0)).collect();
        for a in 0..dx {
            for b in 0..dx {
                xtx[a][b] += row[a] * row[b];
            }
            for b in 0..dy {
                xty[a][b] += row[a] * yi[b];
            }
        }
    }
    for (a, row) in xtx.iter_mut().enumerate() {
        row[a] += 1e-12;
    }
    let solution = solve(xtx, xty); // [dx][dy]
    let weights: Vec<Vec<f64>> = (0..dy)
        .map(|b| (0..dx).map(|a| solution[a][b]).collect())
        .collect();
    let r2 = (0..dy)
        .map(|b| {
            let mean = y.iter().map(|yi| yi[b]).sum::<f64>() / y.len().max(1) as f64;
            let (mut ss_res, mut ss_tot) = (0.0, 0.0);
            for (xi, yi) in x.iter().zip(y) {
                let pred: f64 = xi.iter().zip(&weights[b]).map(|(a, w)| a * w).sum::<f64>()
                    + weights[b][dx - 1];
                ss_res += (yi[b] - pred).powi(2);
                ss_tot += (yi[b] - mean).powi(2);
            }
            if ss_tot > 0.0 {
                1.0 - ss_res / ss_tot
            } else {
                0.0
            }
        })
        .collect();
    (weights, r2)
}

/// Solves `A X = B` by Gaussian elimination with partial pivoting (A square, small).
fn solve(mut a: Vec<Vec<f64>>, mut b: Vec<Vec<f64>>) -> Vec<Vec<f64>> {
    let n = a.len();
    for col in 0..n {
        let pivot = (col..n)
            .max_by(|&i, &j| a[i][col].abs().total_cmp(&a[j][col].abs()))
            .unwrap_or(col);
        a.swap(col, pivot);
        b.swap(col, pivot);
        let p = a[col][col];
        if p.abs() < 1e-300 {
            continue;
        }
        for row in 0..n {
            if row != col {
                let f = a[row][col] / p;
                if f != 0.0 {
                    let (pivot_a, pivot_b) = (a[col].clone(), b[col].clone());
                    a[row]
                        .iter_mut()
                        .zip(&pivot_a)
                        .for_each(|(x, p)| *x -= f * p);
                    b[row]
                        .iter_mut()
                        .zip(&pivot_b)
                        .for_each(|(x, p)| *x -= f * p);
                }
            }
        }
    }
    (0..n)
        .map(|i| {
            b[i].iter()
                .map(|v| {
                    if a[i][i].abs() > 1e-300 {
                        v / a[i][i]
                    } else {
                        0.0
                    }
                })
                .collect()
        })
        .collect()
}

/// Computes the diagnostics of `encoder` on a grid and, if `png` is given, plots the latent map.
pub fn latent_diagnostics(
    env: &EnvConfig,
    encoder: &dyn LatentEncoder,
    device: &Device,
    png: Option<&Path>,
) -> Result<LatentDiagnostics> {
    let side = 24;
    let configs = config_grid(env, side);
    let latents = encode_configs(env, encoder, &configs, device)?;
    let local = local_map_shares(&latents, &configs, side);
    let (_, r2) = linear_fit(&latents, &configs);
    let (to_latent, _) = linear_fit(&configs, &latents);
    let square: Vec<Vec<f64>> = to_latent
        .iter()
        .map(|row| row[..row.len() - 1].to_vec())
        .collect();
    let det = determinant(&square);
    if let Some(path) = png {
        save_latent_map(path, env, &configs, &latents)?;
    }
    Ok(LatentDiagnostics {
        linear_r2: r2.iter().sum::<f64>() / r2.len().max(1) as f64,
        linear_r2_per_dim: r2,
        config_to_latent: square,
        config_to_latent_det: det,
        knn_r2: {
            let r2 = knn_r2(&latents, &configs, 5);
            r2.iter().sum::<f64>() / r2.len().max(1) as f64
        },
        folded_share: folded_share(&latents, &configs),
        pushes_away_share: pushes_away_share(&latents, &configs),
        locally_unstable_share: local.map(|(unstable, _)| unstable),
        near_singular_share: local.map(|(_, singular)| singular),
        points: configs.len(),
        readout: super::readout::readout_check(env, encoder, device)?,
    })
}

/// Scatter of `h` (first two dims), each point coloured by its true configuration (red: q0,
/// blue: q1), grid neighbours joined so folds and twists are visible.
fn save_latent_map(
    path: &Path,
    env: &EnvConfig,
    configs: &[Vec<f64>],
    latents: &[Vec<f64>],
) -> Result<()> {
    let ranges = env.make().config_ranges();
    let side = (configs.len() as f64).sqrt().round() as usize;
    super::plots::render_png(path, (640, 640), |root| {
        let title = format!(
            "latent map of {}: h coloured by true configuration",
            env.kind()
        );
        let point = |k: usize| (latents[k][0], latents[k].get(1).copied().unwrap_or(0.0));
        let mut chart =
            super::plots::latent_plane_chart(root, &title, (0..latents.len()).map(point))?;
        for k in 0..configs.len() {
            for next in [k + 1, k + side] {
                let same_row = next != k + 1 || (k + 1) % side != 0;
                if next < configs.len() && same_row {
                    chart
                        .draw_series(std::iter::once(PathElement::new(
                            vec![point(k), point(next)],
                            RGBColor(200, 200, 200),
                        )))
                        .map_err(|e| e.to_string())?;
                }
            }
        }
        chart
            .draw_series(configs.iter().enumerate().map(|(k, q)| {
                let unit = |i: usize| {
                    ((q[i] - ranges[i][0]) / (ranges[i][1] - ranges[i][0])).clamp(0.0, 1.0)
                };
                let color = RGBColor((255.0 * unit(0)) as u8, 60, (255.0 * unit(1)) as u8);
                Circle::new(point(k), 3, color.filled())
            }))
            .map_err(|e| e.to_string())?;
        Ok(())
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Points of a 20x20 grid over [0, 1]^2.
    fn grid() -> Vec<Vec<f64>> {
        (0..400)
            .map(|k| vec![(k % 20) as f64 / 19.0, (k / 20) as f64 / 19.0])
            .collect()
    }

    #[test]
    fn determinants_of_2x2_and_3x3_maps() {
        assert_eq!(determinant(&[vec![2.0, 1.0], vec![1.0, 3.0]]), Some(5.0));
        // A 3x3 signed permutation (h -> (-h2, h1, h0)) has det +1; numpy: 1.0.
        let p = [
            vec![0.0, 0.0, -1.0],
            vec![0.0, 1.0, 0.0],
            vec![1.0, 0.0, 0.0],
        ];
        assert_eq!(determinant(&p), Some(1.0));
        // numpy.linalg.det([[1,2,3],[0,1,4],[5,6,0]]) = 1.0
        let m = [
            vec![1.0, 2.0, 3.0],
            vec![0.0, 1.0, 4.0],
            vec![5.0, 6.0, 0.0],
        ];
        assert!((determinant(&m).unwrap() - 1.0).abs() < 1e-12);
        assert_eq!(determinant(&[vec![1.0, 2.0]]), None);
    }

    #[test]
    fn folded_share_counts_far_pairs_the_latent_puts_together() {
        let configs = grid();
        // Any injective map, however curved, folds nothing.
        let curled: Vec<Vec<f64>> = configs
            .iter()
            .map(|q| {
                let (r, a) = (1.0 + q[1], 4.0 * q[0]);
                vec![r * a.cos(), r * a.sin()]
            })
            .collect();
        assert_eq!(folded_share(&curled, &configs), 0.0);
        // Folding x about 0.5 puts (x, y) and (1 - x, y) on one point. The mean distance over
        // the 400 * 399 / 2 pairs is 0.5495, so pairs more than 0.1374 apart are far: 76230 of
        // them (numpy). The folded ones are the mirror pairs k / 19 and 1 - k / 19 of a row
        // with |19 - 2k| / 19 > 0.1374, k = 0..=8: 9 per row, 180 in all (every other pair's
        // latents differ by at least the grid step 1/19, far above 0.02 of their mean).
        let folded: Vec<Vec<f64>> = configs
            .iter()
            .map(|q| vec![(q[0] - 0.5).abs(), q[1]])
            .collect();
        let got = folded_share(&folded, &configs);
        assert!((got - 180.0 / 76230.0).abs() < 1e-9, "{got}");
        assert_eq!(folded_share(&[], &[]), 0.0);
    }

    #[test]
    fn pushes_away_share_counts_pairs_whose_first_torque_opposes_the_goal() {
        let configs = grid();
        let map = |m: [[f64; 2]; 2]| -> Vec<Vec<f64>> {
            configs
                .iter()
                .map(|q| (0..2).map(|r| m[r][0] * q[0] + m[r][1] * q[1]).collect())
                .collect()
        };
        // The gradient of a convex quadratic (a symmetric positive-definite map), and a
        // rotation by 30 degrees (its symmetric part cos 30 I is positive definite), push every
        // pair towards the goal.
        assert_eq!(
            pushes_away_share(&map([[2.0, 1.0], [1.0, 1.0]]), &configs),
            Some(0.0)
        );
        let (c, s) = (30f64.to_radians().cos(), 30f64.to_radians().sin());
        assert_eq!(
            pushes_away_share(&map([[c, -s], [s, c]]), &configs),
            Some(0.0)
        );
        // A map crossed over by 120 degrees pushes every pair away.
        let (c, s) = (120f64.to_radians().cos(), 120f64.to_radians().sin());
        assert_eq!(
            pushes_away_share(&map([[c, -s], [s, c]]), &configs),
            Some(1.0)
        );
        // Three points, q0 mirrored: the pair along q0 has work -1 and the diagonal pair
        // (-1, 1) . (1, 1) = 0; only the pair along q1 (work +1) is pushed towards: 2 of 3.
        let q = [vec![0.0, 0.0], vec![1.0, 0.0], vec![0.0, 1.0]];
        let h = [vec![0.0, 0.0], vec![-1.0, 0.0], vec![0.0, 1.0]];
        assert_eq!(pushes_away_share(&h, &q), Some(2.0 / 3.0));
        // Undefined across dimensions, or without a pair.
        assert_eq!(pushes_away_share(&[vec![0.0], vec![1.0]], &q[..2]), None);
        assert_eq!(pushes_away_share(&h[..1], &q[..1]), None);
    }

    #[test]
    fn local_map_shares_find_unstable_and_nearly_singular_cells() {
        // A 5x5 grid (`config_grid`'s order) has 9 interior cells.
        let configs: Vec<Vec<f64>> = (0..25)
            .map(|k| vec![(k % 5) as f64, (k / 5) as f64])
            .collect();
        let map = |f: &dyn Fn(f64, f64) -> [f64; 2]| -> Vec<Vec<f64>> {
            configs.iter().map(|q| f(q[0], q[1]).to_vec()).collect()
        };
        // Linear maps: diag(2, 1) is fine everywhere; diag(1, 0.05) is nearly singular (0.05
        // < 0.1) but stable; a 120-degree turn (trace 2 cos 120 < 0) and a mirror (det < 0)
        // are unstable and not singular.
        assert_eq!(
            local_map_shares(&map(&|a, b| [2.0 * a, b]), &configs, 5),
            Some((0.0, 0.0))
        );
        assert_eq!(
            local_map_shares(&map(&|a, b| [a, 0.05 * b]), &configs, 5),
            Some((0.0, 1.0))
        );
        let (c, s) = (120f64.to_radians().cos(), 120f64.to_radians().sin());
        assert_eq!(
            local_map_shares(&map(&|a, b| [c * a - s * b, s * a + c * b]), &configs, 5),
            Some((1.0, 0.0))
        );
        assert_eq!(
            local_map_shares(&map(&|a, b| [-a, b]), &configs, 5),
            Some((1.0, 0.0))
        );
        // h_1 = (q_1 - 2)^2 / 2: dh_1/dq_1 by central differences is q_1 - 2, so the interior
        // row q_1 = 1 has det < 0 and the row q_1 = 2 det 0 (unstable and singular): 6 of 9
        // cells unstable, 3 singular.
        let got = local_map_shares(&map(&|a, b| [a, (b - 2.0).powi(2) / 2.0]), &configs, 5);
        assert_eq!(got, Some((6.0 / 9.0, 3.0 / 9.0)));
        // Not 2-D, or too few points.
        let three: Vec<Vec<f64>> = configs.iter().map(|q| vec![q[0], q[1], 0.0]).collect();
        assert_eq!(local_map_shares(&three, &configs, 5), None);
        assert_eq!(local_map_shares(&configs[..4], &configs[..4], 2), None);
    }

    #[test]
    fn knn_r2_sees_through_curved_maps_and_catches_forgotten_dims() {
        let q = grid();
        // A ring: angle from q0, radius from q1. Injective, far from linear.
        let ring: Vec<Vec<f64>> = q
            .iter()
            .map(|c| {
                let (angle, radius) = (4.0 * c[0], 1.0 + c[1]);
                vec![radius * angle.cos(), radius * angle.sin()]
            })
            .collect();
        let r2 = knn_r2(&ring, &q, 5);
        assert!(r2.iter().all(|&x| x > 0.95), "{r2:?}");
        let (_, linear) = linear_fit(&ring, &q);
        assert!(
            linear[1] < 0.5,
            "the linear fit should miss the radius: {linear:?}"
        );
        // A latent that ignores q1 cannot predict it.
        let forgetful: Vec<Vec<f64>> = q.iter().map(|c| vec![c[0], 0.0]).collect();
        let r2 = knn_r2(&forgetful, &q, 5);
        assert!(r2[0] > 0.95 && r2[1] < 0.05, "{r2:?}");
    }
}
