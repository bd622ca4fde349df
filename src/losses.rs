//! ProCL's losses, one function per equation of the paper (and spec.md 3), each returning a
//! scalar tensor; [`procl_loss`] combines them and returns the per-term breakdown for logging.

use burn::tensor::activation::{log_softmax, relu};
use burn::tensor::{Tensor, TensorData};

use crate::error::{Error, Result};
use crate::model::{Dynamics, Transition};

/// Where the latent noise `eps` on `E(x_{t+1})` enters (spec.md 3.1).
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum NoiseMode {
    /// As the paper: noise on `h_{t+1}` before CPC, consistency and the Lyapunov risk, so it
    /// reaches `v_{t+1} = (h_{t+1} - h_t)/dt` amplified by `1/dt`.
    Paper,
    /// Noise for CPC and consistency only; the Lyapunov risk sees clean encodings.
    CleanRisk,
}

/// Loss weights and hyperparameters; defaults are the paper's (spec.md 3).
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(deny_unknown_fields)]
pub struct LossConfig {
    pub lambda_pc3: f64,
    pub lambda_r: f64,
    pub lambda_cpc: f64,
    pub lambda_cons: f64,
    pub lambda_curv: f64,
    /// Std of the Gaussian noise added to the next-step encoding.
    pub latent_noise_std: f64,
    pub noise_mode: NoiseMode,
    /// Std of the curvature perturbations `eta_z`, `eta_u`.
    pub curvature_std: f64,
    /// PD gains `Kp = kp I`, `Kd = kd I` of the hindsight labelling.
    pub kp: f64,
    pub kd: f64,
    /// Lyapunov weights `Q_h = q_h I`, `Q_v = q_v I`.
    pub q_h: f64,
    pub q_v: f64,
    /// `dt_R` of the finite-difference Lie derivative, seconds (`None`: the env's control dt).
    pub lyapunov_dt_s: Option<f64>,
    /// Stop gradients through the hindsight targets `h*`, `v*`.
    pub detach_targets: bool,
    /// Divide the risk by the batch mean of `V(z_t - z*)` (held constant in the gradient), so
    /// it no longer falls with the latent's scale. Unnormalised (the paper), the risk grows as
    /// the square of the latent's scale and is lowered most cheaply by shrinking the latent,
    /// which works against CPC; on the fast reacher that ends in collapse.
    #[serde(default)]
    pub normalise_risk: bool,
    /// Variance floor against collapse (VICReg-style): adds
    /// `variance_weight * mean_j max(0, floor - std_j(h))` over the batch's `h_t`, folded into
    /// `total` (`None`: off, the paper). The Lyapunov risk is smallest for a collapsed latent;
    /// where no PD-consistent latent is close (the reacher), it shrinks `h` instead of reshaping it.
    #[serde(default)]
    pub variance_floor: Option<f64>,
    /// Compute the Lyapunov risk on the batch-standardised latent `c h / std(h)` (per
    /// dimension, batch std of `h_t`, gradient through the std) with `c` this value (`None`: on
    /// `h` as it is, the paper). The risk then cannot be lowered by shrinking the latent, and
    /// its scale against the hindsight offset `u / Kp` is fixed at `c`. The controller runs
    /// on `h`, so `Kp` and `Kd` should match `h`'s scale over `c` (the reacher preset: `c = 1`
    /// and gains scaled down; docs/method.md, Reacher-2D stop 15). In a config file `0` means
    /// off (the way to undo a preset that sets it).
    #[serde(default, deserialize_with = "zero_is_none")]
    pub risk_latent_std: Option<f64>,
    #[serde(default = "default_variance_weight")]
    pub variance_weight: f64,
    /// Which axes the variance floor holds: the latent's coordinates (`coordinates`, VICReg's)
    /// or the principal axes of the batch's covariance (`principal`). A floor per coordinate
    /// is met by a thin band turned diagonally, which keeps a joint that moves the image little
    /// squeezed across the band, and it turns the latent against the orientation search; the
    /// principal floor holds the thinnest direction of the cloud whatever its orientation.
    #[serde(default)]
    pub variance_axes: VarianceAxes,
    /// Decorrelation (VICReg's covariance term, on correlations so it is scale-free): adds
    /// `decorrelation_weight * mean_{i != j} corr(h_i, h_j)^2` over the batch's `h_t` (0: off,
    /// the paper). The variance floor holds each dimension's spread but not its content; on the
    /// reacher both dimensions came to follow the shoulder and squeezed the wrist into a thin
    /// band. Independent random joints in the data make uncorrelated latent axes joint-like.
    #[serde(default)]
    pub decorrelation_weight: f64,
    /// Flat-chart term: adds `action_response_weight * (1 - R^2)`, where `R^2` is the fraction
    /// of the batch's latent acceleration `h_{t+1} - 2 h_t + h_{t-1}` that one linear map of
    /// `u_t` explains (least squares with an intercept; 0: off, the paper). Random control draws
    /// `u_t` independently of the state, so the map is the batch's mean action response. In
    /// joint-like coordinates the response `J M(q)^-1` barely turns from state to state; on a
    /// latent curled round an arc it turns with the arc and one map explains little. Invariant
    /// to the latent's rotation and overall scale.
    #[serde(default)]
    pub action_response_weight: f64,
    /// Steps `k` over which the action-response term reads the latent's response (1: the
    /// second difference of one step). One step's action moves the reacher's latent about 0.01
    /// against frame-to-frame jitter near 0.02, so a single step's `R^2` is mostly jitter. Over
    /// `k` steps the response `h_{t+k} - h_t - k (h_t - h_{t-1}) = dt^2 sum_j (k - j) B u_{t+j}`
    /// (Euler, `B` the input gain) grows like `k^2` for a held action while the jitter grows
    /// like `k`; the term regresses it on `sum_j (k - j) u_{t+j}`. Needs episodes longer than
    /// `k + 1` steps.
    #[serde(default = "default_action_response_horizon")]
    pub action_response_horizon: usize,
    /// Fit the response `h_{t+k} - h_t` on the velocity step `h_t - h_{t-1}` as well as the
    /// drive, with its own coefficients, instead of extrapolating the velocity `k` steps
    /// (false). The reacher's wrist loses its velocity within about a step (damping 0.01 on an
    /// inertia near 2e-4), so the extrapolation is wrong for its true angles: on the dataset's
    /// states the fit without the velocity leaves 70-90% of the joint angles' response
    /// unexplained at `k` = 1-10, with it 5-21% (and 18-77% for the same angles curled into a
    /// ring; `tools/k_step_response.py`).
    #[serde(default)]
    pub action_response_velocity: bool,
    /// Turn term: adds `action_response_turn_weight * (RSS_1 - sum_r RSS_r) / TSS`, the share
    /// of the latent's response (as the flat-chart term reads it: same horizon, same
    /// regressors) that separate linear maps in `action_response_regions` groups of the batch
    /// explain and one map for the whole batch does not (0: off, the paper). The groups are
    /// contiguous along the batch's first principal axis of `h_t`, so on a latent curled into a
    /// U they are its two arms and its middle, whose action responses are turned against each
    /// other; on a flat chart one map explains what the regional maps do. The flat-chart term
    /// charges the unexplained share, which frame-to-frame jitter dominates; this one charges
    /// only the part that depends on where in the latent the sample lies.
    #[serde(default)]
    pub action_response_turn_weight: f64,
    /// Sign term: adds `action_response_sign_weight * mean_r sum_i relu(-D_r[i, i]) / s`, where
    /// `D_r` is the drive block of the least-squares response map (as the flat-chart term reads
    /// it: same horizon, same regressors) fitted in each of the `action_response_regions`
    /// groups of the turn term, and `s` the root mean square entry of the whole batch's drive
    /// block (held fixed). PD on `h` with one gain per coordinate needs the action on `h_i` to
    /// move `h_i` forwards everywhere: near a goal the loop is `h'' = -B (Kp dh + Kd h')` with
    /// `B = J M(q)^-1`, which is unstable once a diagonal entry of `B` turns negative. The
    /// orientation makes the batch's mean response diagonal positive; the reacher's latents
    /// hook at the shoulder's ends: past 110 degrees the shoulder's column of the local `dh/dq`
    /// is turned by 140-170 degrees against the middle's (`dh_0/dq_0` negative), below -110 it
    /// flattens, and that is where the failures are (docs/method.md, stop 29). A group must be
    /// narrow enough to see a hook: a third of the batch averages it away. 0: off (the paper).
    #[serde(default)]
    pub action_response_sign_weight: f64,
    /// Groups of the turn and sign terms (see [`LossConfig::action_response_turn_weight`]); at
    /// least 2.
    #[serde(default = "default_action_response_regions")]
    pub action_response_regions: usize,
    /// How the turn and sign terms split the batch into their groups: contiguous slices along
    /// the first principal axis of `h_t` (`principal-axis`), or k-means clusters of `h_t`
    /// (`clusters`). A latent that hooks back at one end projects its hook onto the principal
    /// axis among the samples it turned back past, so a slice mixes both and averages the
    /// hook's backwards response away (docs/method.md, reacher stop 29); a cluster follows the
    /// curve in the plane, so the hook's tip gets a group of its own.
    #[serde(default)]
    pub action_response_grouping: ResponseGrouping,
    /// What the sign term charges in each group's drive map `D_r`: the negative part of its
    /// diagonal (`diagonal`), or the negative part of the smallest real part of its eigenvalues
    /// (`eigenvalues`, 2-D actions only). Near a goal the loop `h'' = -B (Kp dh + Kd h')` holds
    /// only where every eigenvalue of `B` has a positive real part; a positive diagonal does
    /// not ensure it (a shear `[[1, 2], [2, 1]]` has the eigenvalue -1). Over 27 reacher runs
    /// the share of grid cells whose local `dh/dq` fails it ranks their success with Spearman
    /// -0.96 (`locally_unstable_share` in `diagnostics.json`; docs/method.md, reacher stop 30).
    #[serde(default)]
    pub action_response_sign_form: SignForm,
    /// Singular-value floor of the sign term: each group's charge also gets `relu(rho -
    /// sigma_min(D_r) / s)`, `rho` this value (0: off, the paper and the preset). The sign term
    /// asks each coordinate to move forwards under its own action, not to move by much: on the
    /// reacher's seed 2 its failures end in a valley where the latent reached the goal's and the
    /// wrist is 0.1-0.6 rad off, with the wrist's column of `dh/dq` a third of the shoulder's or
    /// less, and twelve groups left 93% of the grid's local maps near-singular (docs/method.md,
    /// reacher stop 31). PD on `h` moves a joint only as far as its action moves `h`, so a
    /// direction the action barely moves is one PD cannot resolve. The global floor on the
    /// principal axes asked for the same spread over the whole batch and bent the band
    /// (stops 24, 30); this asks for it in each group. `sigma_min` comes from the host's SVD of
    /// the group's map, its singular vectors held fixed (its exact gradient where it is simple).
    #[serde(default)]
    pub action_response_singular_floor: f64,
    /// Separation term: adds `separation_weight * mean_{i != j} relu(rho D_ij - d_ij)^2 /
    /// rho^2` over the batch's frames `i_t` (0: off, the paper), where `D_ij` is the squared
    /// distance between frames `i` and `j` (each averaged over 4x4 pixel blocks) over its batch
    /// mean, `d_ij = ||h_i - h_j||` over its batch mean, and `rho = separation_ratio`. It
    /// charges pairs of frames that look different but share a latent. On the reacher most
    /// failed episodes stop with `h` within 1% of its start distance to the goal's `h` while
    /// the arm is 0.1-1.5 rad from the goal (docs/method.md, stop 25): PD did its job on a latent that folds two
    /// configurations onto one point, which CPC misses when the fold is small, because a batch
    /// rarely holds both sides of it close together. A squared frame distance grows in
    /// proportion to a small motion and saturates once the moved links no longer overlap, so
    /// far-apart configurations ask for at least `rho` times the mean latent distance, and close
    /// ones for a share that grows with how much of the image moved.
    #[serde(default)]
    pub separation_weight: f64,
    /// `rho` of the separation term (see [`LossConfig::separation_weight`]); > 0.
    #[serde(default = "default_separation_ratio")]
    pub separation_ratio: f64,
    /// Feature-decoder term: adds `decoder_weight * sum_f mean_i (D(h_i + s eta_i)_f -
    /// phi_if)^2 / sum_f var_i(phi_if)` (0: off, the paper). `phi [n, F]` are the keypoint head's
    /// features of the frames `i_t` (held fixed: the term moves `h` and the decoder `D`, not
    /// the features), `D` reads `h` centred on its batch mean and over its batch RMS spread,
    /// `eta` is standard normal, and `s = decoder_noise`. It is the share of the features'
    /// variance that `h` cannot give back, so a latent that folds two configurations with
    /// different features onto one point pays for it wherever the fold lies, from every sample
    /// near it; the noise keeps `D` from resolving a fold by growing steep. Needs
    /// `model.feature_decoder_width > 0`.
    #[serde(default)]
    pub decoder_weight: f64,
    /// Noise of the feature-decoder term, as a share of `h`'s batch RMS spread (see
    /// [`LossConfig::decoder_weight`]); >= 0.
    #[serde(default = "default_decoder_noise")]
    pub decoder_noise: f64,
    /// Weigh each feature by its own batch variance (floored at a tenth of the features' mean
    /// variance) instead of pooling the variances (false). The shoulder moves every keypoint
    /// and the wrist only the forearm's, so pooled, a latent without the wrist still explains
    /// most of the features' variance (stop 26: 80% on a latent with the wrist's linear R^2 at
    /// 0.09).
    #[serde(default)]
    pub decoder_standardise: bool,
    /// Decode an `h` recomputed from the features held fixed, so the term reshapes only the
    /// head's layers after the keypoints (false: the whole encoder). Those layers are where the
    /// folds are: the keypoint features of folded pairs are still 15-22% of the mean feature
    /// distance apart where their latents are under 2% apart (stop 26).
    #[serde(default)]
    pub decoder_head_only: bool,
    /// Local-stretch term: adds `stretch_weight * mean_s relu(rho a_s - b_s)^2 / rho^2` over
    /// the batch's frame-to-frame steps `s` (`i_{t-1} -> i_t` and `i_t -> i_{t+1}`; 0: off, the
    /// paper), where `b_s = ||h' - h||` over its batch mean and `a_s` is the step of the
    /// keypoint head's features (held fixed), each feature over its batch std of the frames
    /// `i_t` (floored at a third of the mean std), over its batch mean and capped at 4. It
    /// charges steps along which the features move and the latent barely does: on the
    /// reacher the turn term's failures end where a 0.1 rad move of the wrist changes `h` 47
    /// times less than the fitted linear map says (a fold; docs/method.md, stop 25), and the
    /// decoder's latents lost the wrist altogether (stop 26). A step is compared only with its
    /// own features' step, so a chart may bend (the turn term's business) but not squash a
    /// direction the features see. Needs the keypoint head.
    #[serde(default)]
    pub stretch_weight: f64,
    /// `rho` of the local-stretch term (see [`LossConfig::stretch_weight`]); > 0.
    #[serde(default = "default_stretch_ratio")]
    pub stretch_ratio: f64,
    /// Diagnostic, not a method: adds `state_supervision_weight * mean ||h_t - s(q_t)||^2`,
    /// where `s` standardises the dataset's true configuration `q` per coordinate (0: off, the
    /// paper and every preset). The method itself never sees states. With it on, PD on the
    /// trained latent measures what the encoder architecture can represent at all: an upper
    /// bound that separates a head that cannot see a joint from losses that do not ask for it.
    /// Needs `dim q = dim u`.
    #[serde(default)]
    pub state_supervision_weight: f64,
}

fn default_action_response_horizon() -> usize {
    1
}

/// The ratio below which about 0.5% of a trained reacher latent's pairs fall (stop 25), so a
/// sound chart is charged little.
fn default_separation_ratio() -> f64 {
    0.1
}

/// A step a quarter as long in the latent as the features' step says (both over their batch
/// means) is charged; the turn term's flat bands squash the folded wrist's steps 3-47 times.
fn default_stretch_ratio() -> f64 {
    0.25
}

/// About a tenth of a 0.1 rad reacher motion's share of the latent's spread.
fn default_decoder_noise() -> f64 {
    0.05
}

fn default_action_response_regions() -> usize {
    3
}

/// How the turn and sign terms group the batch (see [`LossConfig::action_response_grouping`]).
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum ResponseGrouping {
    /// Near-equal contiguous slices along the batch's first principal axis of `h_t`.
    #[default]
    PrincipalAxis,
    /// k-means clusters of `h_t` (farthest-point start, Lloyd's iterations), each of at least
    /// the rows a fit needs.
    Clusters,
}

/// What the sign term charges (see [`LossConfig::action_response_sign_form`]).
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum SignForm {
    /// `sum_i relu(-D[i, i])`: each latent coordinate moved backwards by its own action.
    #[default]
    Diagonal,
    /// `relu(-min Re lambda(D))` of the 2x2 drive map: PD's loop unstable near a goal.
    Eigenvalues,
}

/// The axes the variance floor holds (see [`LossConfig::variance_axes`]).
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum VarianceAxes {
    /// Each latent coordinate's std (VICReg's).
    #[default]
    Coordinates,
    /// The std along each eigenvector of the batch covariance: its square roots of eigenvalues.
    Principal,
}

/// Reads an optional number where `0` (like a missing value) means off.
fn zero_is_none<'de, D: serde::Deserializer<'de>>(
    deserializer: D,
) -> std::result::Result<Option<f64>, D::Error> {
    let value: Option<f64> = serde::Deserialize::deserialize(deserializer)?;
    Ok(value.filter(|&v| v != 0.0))
}

fn default_variance_weight() -> f64 {
    10.0
}

/// `mean_j max(0, floor - std_j(h))` over the columns of `h [n, du]`.
pub fn variance_hinge(h: Tensor<2>, floor: f64) -> Tensor<1> {
    relu(batch_std(h).neg().add_scalar(floor))
        .mean()
        .reshape([1])
}

/// `mean_k max(0, floor - sqrt(lambda_k))` over the eigenvalues `lambda_k` of the batch
/// covariance of `h [n, du]`: the variance hinge on the principal axes. The eigenvectors are
/// computed outside the graph (nalgebra) and held constant; the variance along a fixed unit vector `w`
/// is `w^T C w`, whose gradient at an eigenvector is `w w^T`, the eigenvalue's own gradient, so
/// this is the exact gradient of the hinge on the eigenvalues.
pub fn principal_variance_hinge(h: Tensor<2>, floor: f64) -> Tensor<1> {
    let [n, du] = h.dims();
    let centred = h.clone() - h.mean_dim(0);
    let covariance = centred.clone().transpose().matmul(centred.clone()) / n as f64;
    let values: Vec<f64> = covariance.into_data().iter::<f64>().collect();
    let axes = symmetric_eigenvectors(&values, du);
    let axes: Vec<f32> = axes.iter().map(|&x| x as f32).collect();
    let axes = Tensor::<2>::from_data(TensorData::new(axes, [du, du]), &centred.device());
    variance_hinge(centred.matmul(axes), floor)
}

/// The unit eigenvectors of the symmetric `du x du` matrix `a` (row-major), as the columns of
/// a row-major matrix. A matrix with a non-finite entry (a diverged batch, whose loss is then
/// non-finite and stops training) or one the iteration cannot diagonalise gets the identity.
fn symmetric_eigenvectors(a: &[f64], du: usize) -> Vec<f64> {
    let vectors = a
        .iter()
        .all(|x| x.is_finite())
        .then(|| {
            nalgebra::DMatrix::from_row_slice(du, du, a).try_symmetric_eigen(f64::EPSILON, 1000)
        })
        .flatten()
        .map_or_else(|| nalgebra::DMatrix::identity(du, du), |e| e.eigenvectors);
    (0..du * du).map(|k| vectors[(k / du, k % du)]).collect()
}

/// `mean_{i != j} corr(h_i, h_j)^2` over the columns of `h [n, du]` (0 for du = 1).
pub fn correlation_penalty(h: Tensor<2>) -> Tensor<1> {
    let [n, du] = h.dims();
    let h_device = h.device();
    if du < 2 {
        return Tensor::zeros([1], &h_device);
    }
    let mean = h.clone().mean_dim(0);
    let std = batch_std(h.clone());
    let standardised = (h - mean) / std; // [n, du]
    let correlation = standardised.clone().transpose().matmul(standardised) / n as f64; // [du, du]
    let off_diagonal = Tensor::<2>::ones([du, du], &h_device) - Tensor::eye(du, &h_device);
    (correlation.powi_scalar(2) * off_diagonal).sum() / (du * (du - 1)) as f64
}

/// `1 - R^2` of the least-squares fit `a ~ x B + c` over the batch: the share of the latent's
/// response `a [n, d]` that no single linear map of the regressors `x [n, p]` explains (see
/// [`LossConfig::action_response_weight`]). The coefficients `B = (x^T x)^-1 x^T a` (centred)
/// are solved on the host (nalgebra) and held fixed: at the least-squares optimum the residual's
/// gradient with respect to `B` is zero, so the gradient through `a` and `x` at fixed `B` is the
/// gradient of the fitted residual itself (envelope theorem). 0 when `x` is degenerate (no fit
/// to judge).
pub fn action_response_unexplained(a: Tensor<2>, x: Tensor<2>) -> Tensor<1> {
    let device = x.device();
    match least_squares_sums(a, x) {
        Some((residual, total)) => residual / total.add_scalar(1e-12),
        None => Tensor::zeros([1], &device),
    }
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

/// The least-squares fit `a ~ x B + c` over the given rows: its residual sum of squares (with
/// the gradient of [`action_response_unexplained`]: `B` fixed at the optimum) and the centred
/// total sum of squares of `a`, `[1]` each. `None` when `x` is degenerate (no fit to judge).
fn least_squares_sums(a: Tensor<2>, x: Tensor<2>) -> Option<(Tensor<1>, Tensor<1>)> {
    let (a, x, inverse) = centred_gram_inverse(a, x)?;
    let coefficients = Some(inverse * host_matrix(x.clone().transpose().matmul(a.clone())))
        .filter(|m| m.iter().all(|v| v.is_finite()))?;
    let coefficients = device_matrix(&coefficients, &x.device());
    let residual = (a.clone() - x.matmul(coefficients)).powi_scalar(2).sum();
    Some((residual.reshape([1]), a.powi_scalar(2).sum().reshape([1])))
}

/// The turn term (see [`LossConfig::action_response_turn_weight`]): `(RSS_1 - sum_r RSS_r) /
/// TSS` for the response `a [n, d]` on the regressors `x [n, p]`, one least-squares map for the
/// whole batch against one per group of `regions` groups of `h [n, du]` made by `grouping`
/// (held fixed, like the maps). 0 when the batch has too few rows per group to fit (`p + 2`)
/// or a fit is degenerate.
pub fn action_response_turn(
    a: Tensor<2>,
    x: Tensor<2>,
    h: Tensor<2>,
    regions: usize,
    grouping: ResponseGrouping,
) -> Tensor<1> {
    let device = x.device();
    let zero = || Tensor::zeros([1], &device);
    let [n, p] = x.dims();
    if regions == 0 || n / regions < p + 2 {
        return zero();
    }
    let Some((residual_one, total)) = least_squares_sums(a.clone(), x.clone()) else {
        return zero();
    };
    let mut residual_regions = zero();
    for index in response_groups(h, regions, grouping, p + 2) {
        let Some((residual, _)) = least_squares_sums(
            a.clone().select(0, index.clone()),
            x.clone().select(0, index),
        ) else {
            return zero();
        };
        residual_regions = residual_regions + residual;
    }
    (residual_one - residual_regions) / total.add_scalar(1e-12)
}

/// The least-squares coefficients `B [p, d]` of `a ~ x B + c` with the gradient through `x^T a`
/// only: `(x^T x)^-1` is solved on the host and held fixed. `None` when `x` is degenerate.
fn least_squares_coefficients(a: Tensor<2>, x: Tensor<2>) -> Option<Tensor<2>> {
    let (a, x, inverse) = centred_gram_inverse(a, x)?;
    Some(device_matrix(&inverse, &x.device()).matmul(x.transpose().matmul(a)))
}

/// The sign term (see [`LossConfig::action_response_sign_weight`]) of the response `a [n, d]`
/// on the regressors `x [n, p]`, whose last `d` columns are the drive: the mean over the groups
/// of `h [n, d]` that `grouping` makes (`regions` of them, fewer where clusters were too small to
/// fit) of the charge `form` names, `sum_i relu(-D_r[i, i]) / s` or `relu(-min Re lambda(D_r /
/// s))`, plus `relu(singular_floor - sigma_min(D_r) / s)` where `singular_floor > 0` (see
/// [`LossConfig::action_response_singular_floor`]). 0 when `x` has fewer than `d` columns, the
/// batch has too few rows per group to fit (`p + 2`), a fit is degenerate, or `form` is the
/// eigenvalues' and `d != 2`.
pub fn action_response_sign(
    a: Tensor<2>,
    x: Tensor<2>,
    h: Tensor<2>,
    regions: usize,
    grouping: ResponseGrouping,
    form: SignForm,
    singular_floor: f64,
) -> Tensor<1> {
    let device = x.device();
    let zero = || Tensor::zeros([1], &device);
    let [n, p] = x.dims();
    let [_, d] = a.dims();
    if p < d || regions == 0 || n / regions < p + 2 || (form == SignForm::Eigenvalues && d != 2) {
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
    let groups = response_groups(h, regions, grouping, p + 2);
    let count = groups.len();
    for index in groups {
        let Some(local) = least_squares_coefficients(
            a.clone().select(0, index.clone()),
            x.clone().select(0, index),
        ) else {
            return zero();
        };
        // The drive block, selected only where a charge reads it.
        let drive = || local.clone().select(0, drive_rows.clone());
        total = total
            + match form {
                SignForm::Diagonal => relu((local.clone() * diagonal_mask.clone()).neg())
                    .sum()
                    .reshape([1]),
                // On the map over the scale, so the square root's floor is scale-free.
                SignForm::Eigenvalues => {
                    relu(min_eigenvalue_real_part(drive() / scale).neg()) * scale
                }
            };
        if singular_floor > 0.0 {
            // In the scale's units, like the diagonal: `relu(rho s - sigma_min)`.
            total = total
                + relu(
                    smallest_singular_value(drive())
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

/// The smallest real part of the eigenvalues of the 2x2 map `m`, `[1]`: `tr/2 - sqrt(tr^2/4 -
/// det)` where the eigenvalues are real, `tr/2` where they are a complex pair (the root's
/// argument floored at 0, plus 1e-6 so its gradient stays finite at a double eigenvalue).
fn min_eigenvalue_real_part(m: Tensor<2>) -> Tensor<1> {
    let at = |i: usize, j: usize| m.clone().slice([i..i + 1, j..j + 1]).reshape([1]);
    let half_trace = (at(0, 0) + at(1, 1)) / 2.0;
    let det = at(0, 0) * at(1, 1) - at(0, 1) * at(1, 0);
    let discriminant = half_trace.clone().powi_scalar(2) - det;
    half_trace - relu(discriminant).add_scalar(1e-6).sqrt()
}

/// The separation term (see [`LossConfig::separation_weight`]) of the latents `h [n, du]`
/// against their frames' squared distances `frame_distances [n, n]` (any scale; the diagonal
/// is ignored). Both distances are taken over their mean across the batch's pairs; the
/// latent's mean is held fixed, so the gradient moves the charged pairs apart rather than
/// the others together. 0 for fewer than 2 rows or frames that are all equal.
pub fn separation_loss(h: Tensor<2>, frame_distances: Tensor<2>, ratio: f64) -> Tensor<1> {
    let [n, du] = h.dims();
    let device = h.device();
    if n < 2 {
        return Tensor::zeros([1], &device);
    }
    let off_diagonal = Tensor::<2>::ones([n, n], &device) - Tensor::eye(n, &device);
    let pairs = (n * (n - 1)) as f64;
    let mean_over_pairs = |d: Tensor<2>| (d.sum() / pairs).reshape([1, 1]).add_scalar(1e-12);
    // `||h_i - h_j||`, with a floor under the square so coincident rows keep a finite gradient.
    let difference = h.clone().reshape([n, 1, du]) - h.reshape([1, n, du]); // [n, n, du]
    let latent = difference
        .powi_scalar(2)
        .sum_dim(2)
        .reshape([n, n])
        .add_scalar(1e-12)
        .sqrt()
        * off_diagonal.clone();
    let latent = latent.clone() / mean_over_pairs(latent.detach());
    let frames = frame_distances.detach() * off_diagonal.clone();
    let frames = frames.clone() / mean_over_pairs(frames);
    let shortfall = relu(frames * ratio - latent) * off_diagonal;
    shortfall.powi_scalar(2).sum().reshape([1]) / (pairs * ratio * ratio)
}

/// The feature-decoder term (see [`LossConfig::decoder_weight`]): the squared reconstruction
/// error of `decoded [n, F]` against `features [n, F]` (held fixed), both centred on their batch
/// means, summed over features, over the features' total batch variance. 1 for a decoder
/// that outputs a constant, 0 for an exact one. Only the spread is compared: the features'
/// mean says nothing about folds, and it drifts while the keypoints train. Pooling the
/// variance (rather than standardising each feature) keeps a feature that barely varies from
/// dominating: at initialisation some keypoints sit still. With `standardise`, each feature's
/// error is over its own variance floored at a tenth of the mean variance, and the sum over
/// that of the variances (1 again for a constant decoder).
pub fn feature_reconstruction_loss(
    decoded: Tensor<2>,
    features: Tensor<2>,
    standardise: bool,
) -> Tensor<1> {
    let features = features.detach();
    let [n, width] = features.dims();
    let device = features.device();
    if n < 2 || width == 0 {
        return Tensor::zeros([1], &device);
    }
    let centred = |x: Tensor<2>| x.clone() - x.mean_dim(0);
    let features = centred(features);
    let variance = features.clone().powi_scalar(2).mean_dim(0); // [1, F]
    let error = (centred(decoded) - features).powi_scalar(2).mean_dim(0); // [1, F]
    let (error, variance) = if standardise {
        let floor = variance.clone().mean().reshape([1, 1]) * 0.1 + 1e-12;
        let scale = variance.clone().max_pair(floor.expand([1, width]));
        (error / scale.clone(), variance / scale)
    } else {
        (error, variance)
    };
    error.sum().reshape([1]) / variance.sum().reshape([1]).add_scalar(1e-12)
}

/// The local-stretch term (see [`LossConfig::stretch_weight`]) of the latents `h [3n, du]` and
/// the keypoint features `features [3n, F]` of the frames `i_{t-1}, i_t, i_{t+1}` (in that
/// order, `n` rows each). The features are held fixed and so is the latent steps' batch mean,
/// so the gradient lengthens the charged steps rather than shortening the others. 0 for fewer
/// than 2 samples or features that do not move.
pub fn local_stretch_loss(h: Tensor<2>, features: Tensor<2>, ratio: f64) -> Tensor<1> {
    let rows = h.dims()[0];
    let width = features.dims()[1];
    let device = h.device();
    let n = rows / 3;
    if n < 2 || width == 0 {
        return Tensor::zeros([1], &device);
    }
    let steps = |x: Tensor<2>| {
        // `x_t - x_{t-1}` and `x_{t+1} - x_t`, `[2n, columns of x]`.
        x.clone().narrow(0, n, 2 * n) - x.narrow(0, 0, 2 * n)
    };
    let features = features.detach();
    // Each feature over its std across the frames `i_t`, floored so a keypoint that sits
    // still does not make its jitter count.
    let current = features.clone().narrow(0, n, n);
    let std = (current.clone() - current.mean_dim(0))
        .powi_scalar(2)
        .mean_dim(0)
        .sqrt(); // [1, F]
    let floor = std.clone().mean().reshape([1, 1]) / 3.0 + 1e-12;
    let scale = std.max_pair(floor.expand([1, width]));
    let norm = |d: Tensor<2>| d.powi_scalar(2).sum_dim(1).add_scalar(1e-12).sqrt(); // [2n, 1]
    let feature_step = norm(steps(features) / scale);
    let feature_step = (feature_step.clone()
        / feature_step.mean().reshape([1, 1]).add_scalar(1e-12))
    .clamp_max(4.0);
    let latent_step = norm(steps(h));
    let latent_step = latent_step.clone()
        / latent_step
            .detach()
            .mean()
            .reshape([1, 1])
            .add_scalar(1e-12);
    let shortfall = relu(feature_step * ratio - latent_step);
    shortfall.powi_scalar(2).mean().reshape([1]) / (ratio * ratio)
}

/// What the feature decoder reads of `h [n, du]`: `h` centred on its batch mean and over its
/// batch RMS spread (statistics held fixed). CPC leaves the latent's offset free, and on the
/// reacher it drifts to |h| ~ 100-200, where raw inputs saturate the decoder's tanh layers and
/// it goes flat (stop 26). One spread for all coordinates, so a rotation of the latent (the
/// orientation search) is a rotation of the decoder's input.
pub fn decoder_input(h: Tensor<2>) -> Tensor<2> {
    let held = h.clone().detach();
    let centre = held.clone().mean_dim(0); // [1, du]
    let spread = (held - centre.clone()).powi_scalar(2).mean();
    let spread = spread.sqrt().add_scalar(1e-6).reshape([1, 1]);
    (h - centre) / spread
}

/// Squared distances `[n, n]` between frames `[n, c, rows, cols]` (rows and cols multiples of
/// 4), each averaged over 4x4 pixel blocks first: the separation term's `D`. The averaging
/// widens the range over which the distance grows with a small motion from a link's width
/// (2-3 pixels) to about 4 more.
pub fn frame_block_distances(frames: Tensor<4>) -> Tensor<2> {
    let [n, c, rows, cols] = frames.dims();
    let blocks = frames
        .detach()
        .reshape([n, c, rows / 4, 4, cols / 4, 4])
        .mean_dim(5)
        .mean_dim(3)
        .reshape([n, c * (rows / 4) * (cols / 4)]);
    let squares = blocks.clone().powi_scalar(2).sum_dim(1); // [n, 1]
    let gram = blocks.clone().matmul(blocks.transpose());
    (squares.clone() + squares.transpose() - gram * 2.0).clamp_min(0.0)
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

/// The row indices of the turn and sign terms' groups of `h [n, du]`: `regions` near-equal
/// contiguous slices along its first principal axis (rows `[r n / R, (r + 1) n / R)` of
/// [`principal_axis_order`] for group `r`), or its k-means clusters of at least `min_rows` rows
/// ([`cluster_rows`]).
fn response_groups(
    h: Tensor<2>,
    regions: usize,
    grouping: ResponseGrouping,
    min_rows: usize,
) -> Vec<Tensor<1, burn::tensor::Int>> {
    let [n, _] = h.dims();
    let device = h.device();
    let groups: Vec<Vec<usize>> = match grouping {
        ResponseGrouping::PrincipalAxis => {
            let order = principal_axis_order(h);
            (0..regions)
                .map(|r| order[r * n / regions..(r + 1) * n / regions].to_vec())
                .collect()
        }
        ResponseGrouping::Clusters => {
            let [_, du] = h.dims();
            let values: Vec<f64> = crate::model::to_vec(h.detach())
                .into_iter()
                .map(f64::from)
                .collect();
            let points: Vec<&[f64]> = values.chunks(du).collect();
            cluster_rows(&points, regions, min_rows)
        }
    };
    groups
        .into_iter()
        .map(|rows| {
            let len = rows.len();
            let rows: Vec<i64> = rows.into_iter().map(|i| i as i64).collect();
            Tensor::<1, burn::tensor::Int>::from_data(TensorData::new(rows, [len]), &device)
        })
        .collect()
}

/// k-means clusters of `points` as lists of row indices, deterministic: the centres start at
/// the point farthest from the mean and then, one by one, at the point farthest from every
/// centre so far (so a curve's ends get centres first), and Lloyd's iterations run until no
/// point changes cluster (at most 100). A cluster with fewer than `min_rows` points is then
/// dissolved into the nearest remaining ones, smallest first, so every group can be fitted;
/// fewer than `regions` groups come back where that happens or the points are fewer distinct.
fn cluster_rows(points: &[&[f64]], regions: usize, min_rows: usize) -> Vec<Vec<usize>> {
    let n = points.len();
    if n == 0 || regions == 0 {
        return Vec::new();
    }
    let squared =
        |a: &[f64], b: &[f64]| -> f64 { a.iter().zip(b).map(|(x, y)| (x - y).powi(2)).sum() };
    let dims = points[0].len();
    let mean: Vec<f64> = (0..dims)
        .map(|j| points.iter().map(|p| p[j]).sum::<f64>() / n as f64)
        .collect();
    // The index of the largest value (the first among equals).
    let farthest = |score: &dyn Fn(usize) -> f64| {
        (0..n).fold((0, f64::NEG_INFINITY), |best, i| {
            let s = score(i);
            if s > best.1 { (i, s) } else { best }
        })
    };
    let mut centres: Vec<Vec<f64>> =
        vec![points[farthest(&|i| squared(points[i], &mean)).0].to_vec()];
    while centres.len() < regions {
        let (next, distance) = farthest(&|i| {
            centres
                .iter()
                .map(|c| squared(points[i], c))
                .fold(f64::INFINITY, f64::min)
        });
        if distance <= 0.0 {
            break;
        }
        centres.push(points[next].to_vec());
    }
    let nearest = |p: &[f64], centres: &[Vec<f64>]| {
        (0..centres.len())
            .fold((0, f64::INFINITY), |best, c| {
                let d = squared(p, &centres[c]);
                if d < best.1 { (c, d) } else { best }
            })
            .0
    };
    let mut assignment = vec![usize::MAX; n];
    for _ in 0..100 {
        let next: Vec<usize> = points.iter().map(|p| nearest(p, &centres)).collect();
        if next == assignment {
            break;
        }
        assignment = next;
        for (c, centre) in centres.iter_mut().enumerate() {
            let members: Vec<&[f64]> = (0..n)
                .filter(|&i| assignment[i] == c)
                .map(|i| points[i])
                .collect();
            if !members.is_empty() {
                for (j, value) in centre.iter_mut().enumerate() {
                    *value = members.iter().map(|p| p[j]).sum::<f64>() / members.len() as f64;
                }
            }
        }
    }
    loop {
        let sizes: Vec<usize> = (0..centres.len())
            .map(|c| assignment.iter().filter(|&&a| a == c).count())
            .collect();
        let smallest = (0..centres.len()).min_by_key(|&c| (sizes[c], c));
        match smallest {
            Some(c) if sizes[c] < min_rows && centres.len() > 1 => {
                centres.remove(c);
                for i in 0..n {
                    if assignment[i] == c {
                        assignment[i] = nearest(points[i], &centres);
                    } else if assignment[i] > c {
                        assignment[i] -= 1;
                    }
                }
            }
            _ => break,
        }
    }
    (0..centres.len())
        .map(|c| (0..n).filter(|&i| assignment[i] == c).collect())
        .collect()
}

/// The factor `c / std(h_t)` (`[1, du]`, gradient through the std) that the Lyapunov risk
/// multiplies every latent of a sample by under `loss.risk_latent_std = c`; `None` when off.
pub(crate) fn risk_scale(config: &LossConfig, h_now: Tensor<2>) -> Option<Tensor<2>> {
    config.risk_latent_std.map(|c| batch_std(h_now).recip() * c)
}

/// Per-dimension population std over the batch, `[n, du] -> [1, du]` (a tiny floor under the
/// variance keeps the gradient of a collapsed dimension finite).
fn batch_std(h: Tensor<2>) -> Tensor<2> {
    let mean = h.clone().mean_dim(0);
    (h - mean)
        .powi_scalar(2)
        .mean_dim(0)
        .add_scalar(1e-12)
        .sqrt()
}

impl Default for LossConfig {
    fn default() -> Self {
        Self {
            lambda_pc3: 1.0,
            lambda_r: 10.0,
            lambda_cpc: 1.0,
            lambda_cons: 1.0,
            lambda_curv: 10.0,
            latent_noise_std: 0.01,
            noise_mode: NoiseMode::Paper,
            curvature_std: 0.1,
            kp: 10.0,
            kd: 2.0,
            q_h: 1.0,
            q_v: 0.1,
            lyapunov_dt_s: None,
            detach_targets: false,
            normalise_risk: false,
            variance_floor: None,
            variance_weight: default_variance_weight(),
            variance_axes: VarianceAxes::Coordinates,
            risk_latent_std: None,
            decorrelation_weight: 0.0,
            action_response_weight: 0.0,
            action_response_horizon: default_action_response_horizon(),
            action_response_velocity: false,
            action_response_turn_weight: 0.0,
            action_response_sign_weight: 0.0,
            action_response_regions: default_action_response_regions(),
            action_response_grouping: ResponseGrouping::PrincipalAxis,
            action_response_sign_form: SignForm::Diagonal,
            action_response_singular_floor: 0.0,
            separation_weight: 0.0,
            separation_ratio: default_separation_ratio(),
            decoder_weight: 0.0,
            decoder_noise: default_decoder_noise(),
            decoder_standardise: false,
            decoder_head_only: false,
            stretch_weight: 0.0,
            stretch_ratio: default_stretch_ratio(),
            state_supervision_weight: 0.0,
        }
    }
}

impl LossConfig {
    /// How many steps past `t` a training sample's frames reach: the action-response term's
    /// horizon `k` when the term is on (it reads `i_{t+k}`), else 1 (`i_{t+1}`).
    pub fn frames_ahead(&self) -> usize {
        if self.reads_action_response() {
            self.action_response_horizon
        } else {
            1
        }
    }

    /// Whether the flat-chart, turn or sign term is on (all read the latent's response).
    pub fn reads_action_response(&self) -> bool {
        self.action_response_weight > 0.0
            || self.action_response_turn_weight > 0.0
            || self.action_response_sign_weight > 0.0
    }

    /// Rejects values that make no sense (negative weights or noise, zero gains).
    pub fn validate(&self) -> Result<()> {
        let non_negative = [
            ("loss.lambda_pc3", self.lambda_pc3),
            ("loss.lambda_r", self.lambda_r),
            ("loss.lambda_cpc", self.lambda_cpc),
            ("loss.lambda_cons", self.lambda_cons),
            ("loss.lambda_curv", self.lambda_curv),
            ("loss.latent_noise_std", self.latent_noise_std),
            ("loss.curvature_std", self.curvature_std),
            ("loss.kd", self.kd),
            ("loss.q_h", self.q_h),
            ("loss.q_v", self.q_v),
            ("loss.variance_weight", self.variance_weight),
            ("loss.variance_floor", self.variance_floor.unwrap_or(0.0)),
            ("loss.decorrelation_weight", self.decorrelation_weight),
            ("loss.action_response_weight", self.action_response_weight),
            (
                "loss.action_response_turn_weight",
                self.action_response_turn_weight,
            ),
            (
                "loss.action_response_sign_weight",
                self.action_response_sign_weight,
            ),
            (
                "loss.action_response_singular_floor",
                self.action_response_singular_floor,
            ),
            ("loss.separation_weight", self.separation_weight),
            ("loss.decoder_weight", self.decoder_weight),
            ("loss.decoder_noise", self.decoder_noise),
            ("loss.stretch_weight", self.stretch_weight),
            (
                "loss.state_supervision_weight",
                self.state_supervision_weight,
            ),
        ];
        if !(self.separation_ratio.is_finite() && self.separation_ratio > 0.0) {
            return Err(Error::config(
                "loss.separation_ratio",
                format!("{} must be finite and > 0", self.separation_ratio),
            ));
        }
        if !(self.stretch_ratio.is_finite() && self.stretch_ratio > 0.0) {
            return Err(Error::config(
                "loss.stretch_ratio",
                format!("{} must be finite and > 0", self.stretch_ratio),
            ));
        }
        if let Some(c) = self.risk_latent_std
            && !(c.is_finite() && c > 0.0)
        {
            return Err(Error::config(
                "loss.risk_latent_std",
                format!("{c} must be finite and > 0"),
            ));
        }
        for (field, value) in non_negative {
            if !(value.is_finite() && value >= 0.0) {
                return Err(Error::config(
                    field,
                    format!("{value} must be finite and >= 0"),
                ));
            }
        }
        if self.action_response_regions < 2 {
            return Err(Error::config(
                "loss.action_response_regions",
                format!(
                    "{} must be at least 2 (one map is compared with several)",
                    self.action_response_regions
                ),
            ));
        }
        if self.action_response_horizon == 0 {
            return Err(Error::config(
                "loss.action_response_horizon",
                "0 must be at least 1 (steps)",
            ));
        }
        if !(self.kp.is_finite() && self.kp > 0.0) {
            return Err(Error::config(
                "loss.kp",
                format!("{} must be > 0 (Kp is inverted)", self.kp),
            ));
        }
        if let Some(dt) = self.lyapunov_dt_s
            && !(dt.is_finite() && dt > 0.0)
        {
            return Err(Error::config(
                "loss.lyapunov_dt_s",
                format!("{dt} must be > 0"),
            ));
        }
        Ok(())
    }
}

/// `log N(x_i | mean_j, diag(exp(log_std))^2)` for every pair: `x [n, d]`, `mean [m, d]`,
/// `log_std [d]` -> `[n, m]`. Row `i` scores `x_i` under every transition `j`.
pub fn pairwise_gaussian_log_density(
    x: Tensor<2>,
    mean: Tensor<2>,
    log_std: Tensor<1>,
    precision_lower: Option<Tensor<2>>,
) -> Tensor<2> {
    let [n, d] = x.dims();
    let m = mean.dims()[0];
    let inv_std = log_std.clone().neg().exp().reshape([1, 1, d]);
    let raw = x.reshape([n, 1, d]) - mean.reshape([1, m, d]); // [n, m, d]
    let diff = raw.clone() * inv_std;
    // With a full covariance, `W d` where `W = diag(exp(-log_std)) + L` (`L` strictly lower):
    // the rows here are `d^T`, so add `d^T L^T`. Its determinant is still the diagonal's.
    let diff = match precision_lower {
        Some(lower) => {
            diff + raw
                .reshape([n * m, d])
                .matmul(lower.transpose())
                .reshape([n, m, d])
        }
        None => diff,
    };
    let quad = diff.powi_scalar(2).sum_dim(2).reshape([n, m]) * (-0.5);
    let norm = log_std.sum() + 0.5 * d as f64 * (2.0 * std::f64::consts::PI).ln();
    quad - norm.reshape([1, 1])
}

/// CPC (paper eq. 3): `-mean_i log softmax_j log F(z'_i | z_j, u_j)`, from the `[K, K]` matrix
/// of [`pairwise_gaussian_log_density`].
pub fn cpc_loss(log_density: Tensor<2>) -> Tensor<1> {
    let log_probs = log_softmax(log_density, 1);
    diagonal(log_probs).mean().neg().reshape([1])
}

/// Consistency (paper eq. 4): `-mean_i log F(z'_i | z_i, u_i)`.
pub fn consistency_loss(log_density: Tensor<2>) -> Tensor<1> {
    diagonal(log_density).mean().neg().reshape([1])
}

/// The diagonal of a square `[n, n]` matrix as `[n]`.
fn diagonal(matrix: Tensor<2>) -> Tensor<1> {
    let n = matrix.dims()[0];
    let eye = Tensor::eye(n, &matrix.device());
    (matrix * eye).sum_dim(1).reshape([n])
}

/// Curvature (paper eq. 5, with a true Jacobian-vector product as spec.md 3 requires):
/// `mean_i || f(z+eta_z, u+eta_u) - f(z, u) - (J_z eta_z + J_u eta_u) ||^2`.
#[allow(clippy::too_many_arguments)]
pub fn curvature_loss(
    dynamics: &Dynamics,
    h: Tensor<2>,
    v: Tensor<2>,
    u: Tensor<2>,
    eta_h: Tensor<2>,
    eta_v: Tensor<2>,
    eta_u: Tensor<2>,
    dt: f64,
) -> Tensor<1> {
    let (base, jvp) = dynamics.forward_jvp(
        h.clone(),
        v.clone(),
        u.clone(),
        Some((eta_h.clone(), eta_v.clone(), eta_u.clone())),
        dt,
    );
    let jvp = jvp.expect("tangent requested");
    let perturbed = dynamics.forward(h + eta_h, v + eta_v, u + eta_u, dt);
    let residual = perturbed.z() - base.z() - jvp.z(); // [n, 2 du]
    residual.powi_scalar(2).sum_dim(1).mean().reshape([1])
}

/// The hindsight pseudo-target (paper eq. 9): `v*` is `v` permuted across the batch, and
/// `h* = h + Kp^-1 (u - Kd (v* - v))` so that PD toward `(h*, v*)` reproduces `u` exactly.
pub fn hindsight_targets(
    h: Tensor<2>,
    v: Tensor<2>,
    u: Tensor<2>,
    permutation: &[usize],
    kp: f64,
    kd: f64,
) -> (Tensor<2>, Tensor<2>) {
    let index = Tensor::<1, burn::tensor::Int>::from_data(
        TensorData::new(
            permutation.iter().map(|&i| i as i64).collect::<Vec<_>>(),
            [permutation.len()],
        ),
        &v.device(),
    );
    let v_target = v.clone().select(0, index);
    let h_target = h + (u - (v_target.clone() - v) * kd) / kp;
    (h_target, v_target)
}

/// `V(z) = h^T Q_h h + v^T Q_v v` per row: `[n, du]` twice -> `[n]`.
fn lyapunov_value(h: Tensor<2>, v: Tensor<2>, q_h: f64, q_v: f64) -> Tensor<1> {
    let n = h.dims()[0];
    (h.powi_scalar(2).sum_dim(1) * q_h + v.powi_scalar(2).sum_dim(1) * q_v).reshape([n])
}

/// Latent PD-control Lyapunov risk (paper eqs. 7, 10):
/// `mean max(0, (V(z_{t+1} - z*) - V(z_t - z*)) / dt_R)`, divided by the constant
/// `mean V(z_t - z*)` when `normalise` (see [`LossConfig::normalise_risk`]).
#[allow(clippy::too_many_arguments)]
pub fn lyapunov_risk(
    z_now: (Tensor<2>, Tensor<2>),
    z_next: (Tensor<2>, Tensor<2>),
    z_target: (Tensor<2>, Tensor<2>),
    q_h: f64,
    q_v: f64,
    dt_r: f64,
    normalise: bool,
) -> Tensor<1> {
    let (h_star, v_star) = z_target;
    let before = lyapunov_value(z_now.0 - h_star.clone(), z_now.1 - v_star.clone(), q_h, q_v);
    let after = lyapunov_value(z_next.0 - h_star, z_next.1 - v_star, q_h, q_v);
    let risk = relu((after - before.clone()) / dt_r).mean().reshape([1]);
    if normalise {
        // A tiny floor keeps a collapsed batch finite.
        risk / before.detach().mean().clamp_min(1e-12).reshape([1])
    } else {
        risk
    }
}

/// The encodings of one batch of samples `(i_{t-1}, i_t, u_t, i_{t+1})` and the random draws
/// the losses use (drawn by the caller from its seeded RNG, so tests can pin them).
#[derive(Debug, Clone)]
pub struct LossInputs {
    /// `h_{t-1}, h_t, h_{t+1}`: `[n, du]` each.
    pub h_prev: Tensor<2>,
    pub h_now: Tensor<2>,
    pub h_next: Tensor<2>,
    /// `u_t`: `[n, du]`.
    pub u: Tensor<2>,
    /// Standard normal noise for `E(x_{t+1})`: `[n, du]`.
    pub latent_noise: Tensor<2>,
    /// Standard normal curvature perturbations for `h`, `v`, `u`: `[n, du]` each.
    pub curvature_noise: (Tensor<2>, Tensor<2>, Tensor<2>),
    /// Batch permutation that draws `v*` from the batch's `v`.
    pub permutation: Vec<usize>,
    /// For the `k`-step action-response term (`k > 1` and the term on): `h_{t+k}` and the drive
    /// `sum_{j<k} (k - j) u_{t+j}`, `[n, du]` each. `None`: the term reads one step.
    pub ahead: Option<(Tensor<2>, Tensor<2>)>,
    /// For the separation term (on): squared distances between the frames `i_t`, `[n, n]`.
    pub frame_distances: Option<Tensor<2>>,
    /// For the feature-decoder term (on): the decoder's output from the noisy `h_t` and the
    /// keypoint features of `i_t`, `[n, F]` each.
    pub decoded_features: Option<(Tensor<2>, Tensor<2>)>,
    /// For the local-stretch term (on): the keypoint features of `i_{t-1}, i_t, i_{t+1}`,
    /// `[3n, F]`.
    pub stretch_features: Option<Tensor<2>>,
}

/// The loss terms of one step (unweighted) and the weighted total. A term that is switched
/// off is 0.
#[derive(Debug, Clone)]
pub struct LossTerms {
    pub cpc: Tensor<1>,
    pub cons: Tensor<1>,
    pub curv: Tensor<1>,
    pub lyap: Tensor<1>,
    /// The latent's variance hinge (`loss.variance_floor`).
    pub var: Tensor<1>,
    /// The flat-chart term: the share of the k-step action response one map leaves unexplained.
    pub flat: Tensor<1>,
    /// The turn term: the share regional maps explain and one map does not.
    pub turn: Tensor<1>,
    /// The sign term: negative diagonal entries of the regional drive responses.
    pub sign: Tensor<1>,
    /// The separation term: pairs of different-looking frames with too close latents.
    pub sep: Tensor<1>,
    /// The feature-decoder term: the share of the keypoint features `h` cannot give back.
    pub dec: Tensor<1>,
    /// The local-stretch term: frame steps the features see and the latent squashes.
    pub stretch: Tensor<1>,
    pub total: Tensor<1>,
}

/// Names of the logged terms, in [`LossValues::as_array`] order.
pub const LOSS_NAMES: [&str; 12] = [
    "total", "cpc", "cons", "curv", "lyap", "var", "flat", "turn", "sep", "dec", "stretch", "sign",
];

/// Loss values read back to the host, for logging.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct LossValues {
    pub total: f64,
    pub cpc: f64,
    pub cons: f64,
    pub curv: f64,
    pub lyap: f64,
    pub var: f64,
    pub flat: f64,
    pub turn: f64,
    pub sep: f64,
    pub dec: f64,
    pub stretch: f64,
    /// Absent from runs logged before the sign term.
    #[serde(default)]
    pub sign: f64,
}

impl LossValues {
    pub fn as_array(&self) -> [f64; 12] {
        [
            self.total,
            self.cpc,
            self.cons,
            self.curv,
            self.lyap,
            self.var,
            self.flat,
            self.turn,
            self.sep,
            self.dec,
            self.stretch,
            self.sign,
        ]
    }
    pub fn is_finite(&self) -> bool {
        self.as_array().iter().all(|x| x.is_finite())
    }
}

impl LossTerms {
    /// Reads every term back (one device sync).
    pub fn values(&self) -> LossValues {
        let v = crate::model::read_scalars(&[
            &self.total,
            &self.cpc,
            &self.cons,
            &self.curv,
            &self.lyap,
            &self.var,
            &self.flat,
            &self.turn,
            &self.sep,
            &self.dec,
            &self.stretch,
            &self.sign,
        ]);
        LossValues {
            total: v[0],
            cpc: v[1],
            cons: v[2],
            curv: v[3],
            lyap: v[4],
            var: v[5],
            flat: v[6],
            turn: v[7],
            sep: v[8],
            dec: v[9],
            stretch: v[10],
            sign: v[11],
        }
    }
}

/// The ProCL objective (paper eq. 11): `lambda_pc3 (lambda_cpc L_cpc + lambda_cons L_cons +
/// lambda_curv L_curv) + lambda_R R`. PC3 is the same with `lambda_R = 0`.
pub fn procl_loss(
    config: &LossConfig,
    dynamics: &Dynamics,
    inputs: LossInputs,
    dt: f64,
) -> LossTerms {
    let LossInputs {
        h_prev,
        h_now,
        h_next,
        u,
        latent_noise,
        curvature_noise,
        permutation,
        ahead,
        frame_distances,
        decoded_features,
        stretch_features,
    } = inputs;
    let h_now_for_variance = h_now.clone();
    let device = h_now.device();
    let zero = || Tensor::<1>::zeros([1], &device);
    let sep = match frame_distances.filter(|_| config.separation_weight > 0.0) {
        Some(frames) => separation_loss(h_now.clone(), frames, config.separation_ratio),
        None => zero(),
    };
    let dec = match decoded_features.filter(|_| config.decoder_weight > 0.0) {
        Some((decoded, features)) => {
            feature_reconstruction_loss(decoded, features, config.decoder_standardise)
        }
        None => zero(),
    };
    let stretch = match stretch_features.filter(|_| config.stretch_weight > 0.0) {
        Some(features) => local_stretch_loss(
            Tensor::cat(vec![h_prev.clone(), h_now.clone(), h_next.clone()], 0),
            features,
            config.stretch_ratio,
        ),
        None => zero(),
    };
    let (flat, turn, sign) = if config.reads_action_response() {
        // Without `ahead` the terms read one step, whatever the configured horizon.
        let (k, (h_ahead, drive)) = match ahead {
            Some(ahead) => (config.action_response_horizon as f64, ahead),
            None => (1.0, (h_next.clone(), u.clone())),
        };
        let step = h_now.clone() - h_prev.clone(); // dt v_t
        let moved = h_ahead - h_now.clone(); // h_{t+k} - h_t
        let (response, regressors) = if config.action_response_velocity {
            (moved, Tensor::cat(vec![step, drive], 1))
        } else {
            (moved - step * k, drive)
        };
        let flat = if config.action_response_weight > 0.0 {
            action_response_unexplained(response.clone(), regressors.clone())
        } else {
            zero()
        };
        let turn = if config.action_response_turn_weight > 0.0 {
            action_response_turn(
                response.clone(),
                regressors.clone(),
                h_now.clone(),
                config.action_response_regions,
                config.action_response_grouping,
            )
        } else {
            zero()
        };
        let sign = if config.action_response_sign_weight > 0.0 {
            action_response_sign(
                response,
                regressors,
                h_now.clone(),
                config.action_response_regions,
                config.action_response_grouping,
                config.action_response_sign_form,
                config.action_response_singular_floor,
            )
        } else {
            zero()
        };
        (flat, turn, sign)
    } else {
        (zero(), zero(), zero())
    };
    let v_now = (h_now.clone() - h_prev) / dt;
    let h_next_noisy = h_next.clone() + latent_noise * config.latent_noise_std;
    let v_next_noisy = (h_next_noisy.clone() - h_now.clone()) / dt;

    // PC3 terms: score the (noisy) next latent under every transition of the batch.
    let predicted: Transition = dynamics.forward(h_now.clone(), v_now.clone(), u.clone(), dt);
    // Scored in unoriented (h', dt v') coordinates, where the std is diagonal. The density of
    // v' is that of dt v' times dt per dimension, so + du ln(dt) makes it exactly log F(z'|z,u).
    let unoriented = |h: Tensor<2>, v: Tensor<2>| {
        Tensor::cat(vec![dynamics.unoriented(h), dynamics.unoriented(v) * dt], 1)
    };
    let z_next = unoriented(h_next_noisy.clone(), v_next_noisy.clone());
    let z_predicted = unoriented(predicted.h_next, predicted.v_next);
    let du = h_now.dims()[1] as f64;
    let log_density = pairwise_gaussian_log_density(
        z_next,
        z_predicted,
        dynamics.log_std.val(),
        dynamics.precision_off_diagonal(),
    ) + du * dt.ln();
    let cpc = cpc_loss(log_density.clone());
    let cons = consistency_loss(log_density);
    let (eta_h, eta_v, eta_u) = curvature_noise;
    let s = config.curvature_std;
    let curv = curvature_loss(
        dynamics,
        h_now.clone(),
        v_now.clone(),
        u.clone(),
        eta_h * s,
        eta_v * s,
        eta_u * s,
        dt,
    );

    // Lyapunov risk with hindsight targets, on the standardised latent if asked (one scale
    // for every latent of the sample, so velocities stay finite differences of positions).
    let z_after = match config.noise_mode {
        NoiseMode::Paper => (h_next_noisy, v_next_noisy),
        NoiseMode::CleanRisk => (h_next.clone(), (h_next - h_now.clone()) / dt),
    };
    let (h_now, v_now, z_after) = match risk_scale(config, h_now.clone()) {
        Some(scale) => (
            h_now * scale.clone(),
            v_now * scale.clone(),
            (z_after.0 * scale.clone(), z_after.1 * scale),
        ),
        None => (h_now, v_now, z_after),
    };
    let (h_target, v_target) = hindsight_targets(
        h_now.clone(),
        v_now.clone(),
        u,
        &permutation,
        config.kp,
        config.kd,
    );
    let (h_target, v_target) = if config.detach_targets {
        (h_target.detach(), v_target.detach())
    } else {
        (h_target, v_target)
    };
    let dt_r = config.lyapunov_dt_s.unwrap_or(dt);
    let lyap = lyapunov_risk(
        (h_now, v_now),
        z_after,
        (h_target, v_target),
        config.q_h,
        config.q_v,
        dt_r,
        config.normalise_risk,
    );

    let pc3 = cpc.clone() * config.lambda_cpc
        + cons.clone() * config.lambda_cons
        + curv.clone() * config.lambda_curv;
    let mut total = pc3 * config.lambda_pc3 + lyap.clone() * config.lambda_r;
    let var = match config.variance_floor {
        Some(floor) => match config.variance_axes {
            VarianceAxes::Coordinates => variance_hinge(h_now_for_variance.clone(), floor),
            VarianceAxes::Principal => principal_variance_hinge(h_now_for_variance.clone(), floor),
        },
        None => zero(),
    };
    total = total
        + var.clone() * config.variance_weight
        + flat.clone() * config.action_response_weight
        + turn.clone() * config.action_response_turn_weight
        + sign.clone() * config.action_response_sign_weight
        + sep.clone() * config.separation_weight
        + dec.clone() * config.decoder_weight
        + stretch.clone() * config.stretch_weight;
    if config.decorrelation_weight > 0.0 {
        total = total + correlation_penalty(h_now_for_variance) * config.decorrelation_weight;
    }
    LossTerms {
        cpc,
        cons,
        curv,
        lyap,
        var,
        flat,
        turn,
        sign,
        sep,
        dec,
        stretch,
        total,
    }
}

#[cfg(test)]
mod tests {
    //! Every pinned number below was computed independently of this crate (by hand or with the
    //! numpy one-liners quoted next to it), not by running the code under test.

    use burn::tensor::{Device, Tensor, TensorData};

    use super::*;
    use crate::model::{DynamicsConfig, cpu_device, reinit_params, to_vec};

    fn t2(values: &[f32], rows: usize, cols: usize, device: &Device) -> Tensor<2> {
        Tensor::from_data(TensorData::new(values.to_vec(), [rows, cols]), device)
    }

    fn t1(values: &[f32], device: &Device) -> Tensor<1> {
        Tensor::from_data(TensorData::new(values.to_vec(), [values.len()]), device)
    }

    fn scalar(t: Tensor<1>) -> f64 {
        let v = to_vec(t);
        assert_eq!(v.len(), 1);
        v[0] as f64
    }

    fn assert_close(got: &[f32], want: &[f64], tol: f64, what: &str) {
        assert_eq!(got.len(), want.len(), "{what}: length");
        for (k, (&g, &w)) in got.iter().zip(want).enumerate() {
            assert!(
                (g as f64 - w).abs() <= tol,
                "{what}[{k}]: got {g}, want {w} (tol {tol})"
            );
        }
    }

    #[test]
    fn pairwise_gaussian_log_density_matches_full_covariance_formula() {
        let device = cpu_device();
        let x = t2(&[0.0, 0.0, 1.0, 2.0], 2, 2, &device);
        let mean = t2(&[0.0, 1.0, 1.0, -1.0, -2.0, 0.5], 3, 2, &device);
        let log_std = t1(&[0.5f32.ln(), 2.0f32.ln()], &device);
        let out = pairwise_gaussian_log_density(x.clone(), mean.clone(), log_std.clone(), None);
        assert_eq!(out.dims(), [2, 3]);
        // numpy, through the full covariance (not the per-dimension formula used here):
        //   cov = diag(exp(2 log_std)); out[i, j] = -0.5 d^T cov^-1 d - 0.5 log((2 pi)^2 det cov)
        //   with d = x[i] - mean[j]. Row i scores x_i under every mean j.
        let want = [
            -1.962877066,
            -3.962877066,
            -9.869127066,
            -3.962877066,
            -2.962877066,
            -20.119127066,
        ];
        assert_close(&to_vec(out), &want, 1e-5, "log density");

        // Full covariance: W = [[2, 0], [0.7, 0.5]], so the precision W^T W is
        // [[4.49, 0.35], [0.35, 0.25]] and log det W = ln 1 = 0 (by hand).
        let lower = t2(&[0.0, 0.0, 0.7, 0.0], 2, 2, &device);
        let out = pairwise_gaussian_log_density(x, mean, log_std, Some(lower));
        let (xs, means) = (
            [[0.0, 0.0], [1.0, 2.0]],
            [[0.0, 1.0], [1.0, -1.0], [-2.0, 0.5]],
        );
        let want: Vec<f64> = xs
            .iter()
            .flat_map(|x| {
                means.iter().map(move |m| {
                    let (d0, d1) = (x[0] - m[0], x[1] - m[1]);
                    let quad = 4.49 * d0 * d0 + 2.0 * 0.35 * d0 * d1 + 0.25 * d1 * d1;
                    -0.5 * quad - (2.0 * std::f64::consts::PI).ln()
                })
            })
            .collect();
        assert_close(&to_vec(out), &want, 1e-5, "full-covariance log density");
    }

    /// An asymmetric matrix, so row-wise and column-wise softmax give different losses.
    fn log_density_3x3(device: &Device) -> Tensor<2> {
        t2(
            &[-1.0, -2.0, -3.0, 0.5, 1.5, -0.5, 2.0, 0.0, 1.0],
            3,
            3,
            device,
        )
    }

    #[test]
    fn cpc_loss_is_row_softmax_cross_entropy_on_the_diagonal() {
        let device = cpu_device();
        // numpy: L = [[-1,-2,-3],[.5,1.5,-.5],[2,0,1]];
        //   -mean(diag(L) - log(exp(L).sum(axis=1))) = 0.7409392977777136
        //   (softmax over columns instead, axis=0, would give 1.2277966710865273).
        let got = scalar(cpc_loss(log_density_3x3(&device)));
        assert!((got - 0.740_939_297_8).abs() < 1e-5, "cpc {got}");
        // Adding a constant to every row leaves CPC unchanged (by hand).
        let shifted = scalar(cpc_loss(log_density_3x3(&device) + 7.0));
        assert!((shifted - got).abs() < 1e-5, "shifted cpc {shifted}");
        // A strongly dominant diagonal gives CPC ~ 0; a uniform matrix gives ln 3 (by hand).
        let eye = t2(
            &[50.0, 0.0, 0.0, 0.0, 50.0, 0.0, 0.0, 0.0, 50.0],
            3,
            3,
            &device,
        );
        assert!(scalar(cpc_loss(eye)).abs() < 1e-5);
        let flat = t2(&[0.3; 9], 3, 3, &device);
        assert!((scalar(cpc_loss(flat)) - 3f64.ln()).abs() < 1e-5);
    }

    #[test]
    fn consistency_loss_is_minus_mean_diagonal() {
        let device = cpu_device();
        // By hand: -(-1 + 1.5 + 1) / 3 = -0.5.
        let got = scalar(consistency_loss(log_density_3x3(&device)));
        assert!((got + 0.5).abs() < 1e-6, "cons {got}");
    }

    #[test]
    fn hindsight_targets_reproduce_the_recorded_action_under_pd() {
        let device = cpu_device();
        let h: [f32; 6] = [0.3, -1.2, 0.0, 0.7, 2.5, -0.4];
        let v: [f32; 6] = [1.0, 2.0, -3.0, 0.5, 0.25, -1.5];
        let u: [f32; 6] = [0.9, -0.3, -1.0, 1.0, 0.1, 0.0];
        let permutation = [2usize, 0, 1];
        let (kp, kd) = (10.0, 2.0);
        let (h_star, v_star) = hindsight_targets(
            t2(&h, 3, 2, &device),
            t2(&v, 3, 2, &device),
            t2(&u, 3, 2, &device),
            &permutation,
            kp,
            kd,
        );
        let (h_star, v_star) = (to_vec(h_star), to_vec(v_star));
        // v*_i = v_{permutation[i]}: rows (0.25, -1.5), (1, 2), (-3, 0.5), exactly.
        assert_eq!(v_star, vec![0.25, -1.5, 1.0, 2.0, -3.0, 0.5]);
        // PD toward (h*, v*) gives back u: kp (h* - h) + kd (v* - v) = u.
        for k in 0..6 {
            let pd = kp * (h_star[k] as f64 - h[k] as f64) + kd * (v_star[k] as f64 - v[k] as f64);
            assert!(
                (pd - u[k] as f64).abs() < 1e-5,
                "entry {k}: PD gives {pd}, u = {}",
                u[k]
            );
        }
        // One entry by hand: h*_00 = 0.3 + (0.9 - 2 (0.25 - 1)) / 10 = 0.54.
        assert!((h_star[0] - 0.54).abs() < 1e-6);
    }

    #[test]
    fn lyapunov_risk_is_zero_when_contracting_and_pinned_when_expanding() {
        let device = cpu_device();
        let (q_h, q_v, dt_r) = (1.0, 0.1, 0.02);
        let pair = |h: &[f32], v: &[f32]| (t2(h, 2, 2, &device), t2(v, 2, 2, &device));
        // Both rows move toward the target in the V metric.
        let contracting = lyapunov_risk(
            pair(&[1.0, 0.0, 1.0, 1.0], &[0.0, 1.0, 0.0, 0.0]),
            pair(&[0.5, 0.0, 0.5, 0.5], &[0.0, 0.5, 0.0, 0.0]),
            pair(&[0.0; 4], &[0.0; 4]),
            q_h,
            q_v,
            dt_r,
            false,
        );
        assert_eq!(scalar(contracting), 0.0);
        // Row 0 expands, row 1 contracts. By hand, target h* = (0.5, 0.5), v* = 0 for row 0:
        //   V(z_now - z*) = 0.25 + 0.25 + 0.1 * 1 = 0.6
        //   V(z_next - z*) = 1.5^2 + 0.5^2 + 0.1 (1 + 1) = 2.7
        //   (2.7 - 0.6) / 0.02 = 105. Row 1 (target 0): V 2 -> 0.5, clipped to 0.
        //   Mean over the 2 rows: 52.5.
        // The expanding batch, its latent scaled by `scale`, under either risk.
        let expanding = |scale: f32, normalise: bool| {
            let s = |v: &[f32]| v.iter().map(|x| scale * x).collect::<Vec<f32>>();
            scalar(lyapunov_risk(
                pair(&s(&[1.0, 0.0, 1.0, 1.0]), &s(&[0.0, 1.0, 0.0, 0.0])),
                pair(&s(&[2.0, 0.0, 0.5, 0.5]), &s(&[1.0, 1.0, 0.0, 0.0])),
                pair(&s(&[0.5, 0.5, 0.0, 0.0]), &[0.0; 4]),
                q_h,
                q_v,
                dt_r,
                normalise,
            ))
        };
        let got = expanding(1.0, false);
        assert!((got - 52.5).abs() < 1e-3, "risk {got}");
        // Normalised: divided by the mean V(z_now - z*) = (0.6 + 2) / 2 = 1.3 -> 40.3846.
        let got = expanding(1.0, true);
        assert!((got - 52.5 / 1.3).abs() < 1e-3, "normalised risk {got}");
        // ... and does not change when the whole latent is scaled by 3 (V scales by 9 in both).
        let scaled = expanding(3.0, true);
        assert!((scaled - got).abs() < 1e-3);
    }

    /// The velocity term of `V` charges a joint for how far one step moves its velocity, so a
    /// joint whose velocity follows the torque within a step (the reacher's overdamped wrist)
    /// is charged ten times a double integrator's for the same step: the risk is lowered by
    /// making that joint faint in `h` (docs/method.md, reacher, stop 20). Without the term
    /// (`q_v = 0`) neither is charged.
    #[test]
    fn the_velocity_term_charges_an_overdamped_joint_and_q_v_0_charges_neither() {
        let device = cpu_device();
        let (kp, kd, dt) = (1.0, 0.2, 0.02);
        let one = |x: f32| t2(&[x], 1, 1, &device);
        // Row 0 of a batch: at rest at h = 0 under u = 1; v* is row 1's velocity, -2. By hand,
        // h* = 0 + (1 - 0.2 (-2 - 0)) / 1 = 1.4.
        let (h_star, v_star) = hindsight_targets(
            t2(&[0.0, 0.0], 2, 1, &device),
            t2(&[0.0, -2.0], 2, 1, &device),
            t2(&[1.0, 0.0], 2, 1, &device),
            &[1, 0],
            kp,
            kd,
        );
        let (h_star, v_star) = (to_vec(h_star)[0], to_vec(v_star)[0]);
        assert!(
            (h_star - 1.4).abs() < 1e-6 && v_star == -2.0,
            "{h_star} {v_star}"
        );
        // V(z_now - z*) = 1.4^2 + q_v 2^2 = 1.96 + 4 q_v.
        // Overdamped: the velocity jumps to 1.5 in the step, h_next = 0.02 * 1.5 = 0.03:
        //   V(z_next - z*) = 1.37^2 + q_v 3.5^2 = 1.8769 + 12.25 q_v;
        //   at q_v = 0.1 the rise is 0.7419, over dt: 37.095.
        // Double integrator: v_next = dt a = 0.2, h_next = 0.004:
        //   V(z_next - z*) = 1.396^2 + q_v 2.2^2 = 1.948816 + 4.84 q_v;
        //   at q_v = 0.1 the rise is 0.072816, over dt: 3.6408.
        let risk = |h_next: f32, v_next: f32, q_v: f64| {
            scalar(lyapunov_risk(
                (one(0.0), one(0.0)),
                (one(h_next), one(v_next)),
                (one(h_star), one(v_star)),
                1.0,
                q_v,
                dt,
                false,
            ))
        };
        let overdamped = risk(0.03, 1.5, 0.1);
        let double_integrator = risk(0.004, 0.2, 0.1);
        assert!((overdamped - 37.095).abs() < 1e-3, "{overdamped}");
        assert!(
            (double_integrator - 3.6408).abs() < 1e-3,
            "{double_integrator}"
        );
        // Both steps move h toward h*, so without the velocity term neither is charged.
        assert_eq!(risk(0.03, 1.5, 0.0), 0.0);
        assert_eq!(risk(0.004, 0.2, 0.0), 0.0);
    }

    #[test]
    fn variance_hinge_is_zero_above_the_floor_and_linear_below() {
        let device = cpu_device();
        // Columns: [0, 2] has std 1 (population), [0, 0.5] has std 0.25.
        let h = t2(&[0.0, 0.0, 2.0, 0.5], 2, 2, &device);
        // floor 1: max(0, 1 - 1) = 0 and 1 - 0.25 = 0.75 -> mean 0.375.
        assert!((scalar(variance_hinge(h.clone(), 1.0)) - 0.375).abs() < 1e-5);
        // floor 0.2: both columns above.
        assert!(scalar(variance_hinge(h, 0.2)).abs() < 1e-6);
    }

    #[test]
    fn symmetric_eigenvectors_are_unit_eigenvector_columns() {
        // [[2, 1, 0], [1, 2, 0], [0, 0, 5]]: eigenvalues 1, 3, 5 with (1, -1, 0) / sqrt 2 ...
        let a = [2.0, 1.0, 0.0, 1.0, 2.0, 0.0, 0.0, 0.0, 5.0];
        let v = symmetric_eigenvectors(&a, 3);
        let mut lambdas = Vec::new();
        for k in 0..3 {
            let w: Vec<f64> = (0..3).map(|i| v[i * 3 + k]).collect();
            let aw: Vec<f64> = (0..3)
                .map(|i| (0..3).map(|j| a[i * 3 + j] * w[j]).sum())
                .collect();
            let lambda: f64 = (0..3).map(|i| w[i] * aw[i]).sum();
            // A unit eigenvector: A w = lambda w.
            assert!((w.iter().map(|x| x * x).sum::<f64>() - 1.0).abs() < 1e-12);
            for i in 0..3 {
                assert!((aw[i] - lambda * w[i]).abs() < 1e-10, "{aw:?} {w:?}");
            }
            lambdas.push(lambda);
        }
        // A diverged batch gets the identity rather than an endless iteration.
        let nan = symmetric_eigenvectors(&[f64::NAN, 0.0, 0.0, 1.0], 2);
        assert_eq!(nan, [1.0, 0.0, 0.0, 1.0]);
        lambdas.sort_by(f64::total_cmp);
        for (got, want) in lambdas.iter().zip([1.0, 3.0, 5.0]) {
            assert!((got - want).abs() < 1e-10, "{lambdas:?}");
        }
    }

    #[test]
    fn principal_hinge_sees_a_thin_band_turned_diagonally() {
        let device = cpu_device();
        // Points (t, t) + s (1, -1) for t in {-2, 2}, s in {-0.1, 0.1}: along the diagonal the
        // std is 2 sqrt 2, across it 0.1 sqrt 2 (population), while each coordinate's std is
        // sqrt(4 + 0.01) > 1.
        let mut points = Vec::new();
        for t in [-2.0f32, 2.0] {
            for s in [-0.1f32, 0.1] {
                points.extend([t + s, t - s]);
            }
        }
        let h = t2(&points, 4, 2, &device);
        assert!(scalar(variance_hinge(h.clone(), 1.0)).abs() < 1e-6);
        // Principal: max(0, 1 - 2.83) = 0 and 1 - 0.1414 -> mean 0.4293 (by hand).
        let want = (1.0 - 0.1 * 2f64.sqrt()) / 2.0;
        let got = scalar(principal_variance_hinge(h.clone(), 1.0));
        assert!((got - want).abs() < 1e-5, "{got} vs {want}");
        // Uncorrelated columns of std 1 and 0.25: the principal axes are the coordinates and
        // both hinges give (0 + 0.75) / 2.
        let h = t2(
            &[1.0, 0.25, 1.0, -0.25, -1.0, 0.25, -1.0, -0.25],
            4,
            2,
            &device,
        );
        assert!((scalar(variance_hinge(h.clone(), 1.0)) - 0.375).abs() < 1e-5);
        assert!((scalar(principal_variance_hinge(h, 1.0)) - 0.375).abs() < 1e-5);
    }

    #[test]
    fn principal_hinge_gradient_is_the_eigenvalue_gradient() {
        // The hinge on a 2x2 covariance's eigenvalues in closed form, in f64.
        fn hinge(points: &[f64]) -> f64 {
            let n = points.len() / 2;
            let mean = |c: usize| (0..n).map(|i| points[2 * i + c]).sum::<f64>() / n as f64;
            let (m0, m1) = (mean(0), mean(1));
            let cov = |a: usize, ma: f64, b: usize, mb: f64| {
                (0..n)
                    .map(|i| (points[2 * i + a] - ma) * (points[2 * i + b] - mb))
                    .sum::<f64>()
                    / n as f64
            };
            let (c00, c01, c11) = (cov(0, m0, 0, m0), cov(0, m0, 1, m1), cov(1, m1, 1, m1));
            let half_trace = (c00 + c11) / 2.0;
            let gap = (((c00 - c11) / 2.0).powi(2) + c01 * c01).sqrt();
            [half_trace + gap, half_trace - gap]
                .iter()
                .map(|l| (1.0 - l.sqrt()).max(0.0))
                .sum::<f64>()
                / 2.0
        }
        let points = [0.3, 0.1, -0.5, 0.4, 0.9, -0.2, -0.1, -0.6, 0.2, 0.5];
        let device = cpu_device().autodiff();
        let as_f32: Vec<f32> = points.iter().map(|&x| x as f32).collect();
        let h = Tensor::<2>::from_data(TensorData::new(as_f32, [5, 2]), &device).require_grad();
        let loss = principal_variance_hinge(h.clone(), 1.0);
        assert!((scalar(loss.clone()) - hinge(&points)).abs() < 1e-5);
        let grads = loss.backward();
        let got = to_vec(h.grad(&grads).expect("gradient of h"));
        for k in 0..points.len() {
            let (mut up, mut down) = (points, points);
            up[k] += 1e-6;
            down[k] -= 1e-6;
            let want = (hinge(&up) - hinge(&down)) / 2e-6;
            let got = f64::from(got[k]);
            assert!((got - want).abs() < 1e-3, "d/dh[{k}]: {got} vs {want}");
        }
    }

    #[test]
    fn action_response_term_is_the_share_no_linear_map_of_u_explains() {
        let device = cpu_device();
        let u = t2(&[1.0, -1.0, 1.0, -1.0], 4, 1, &device);
        let unexplained = |a: Tensor<2>, u: Tensor<2>| scalar(action_response_unexplained(a, u));
        // Column 0 is 2 u + w, column 1 is w, with w = (1, 1, -1, -1) orthogonal
        // to u: the fit explains (u.a0)^2 / (u.u) = 64 / 4 = 16 of |a|^2 = 20 + 4 = 24.
        let a = t2(&[3.0, 1.0, -1.0, 1.0, 1.0, -1.0, -3.0, -1.0], 4, 2, &device);
        assert!((unexplained(a.clone(), u.clone()) - 1.0 / 3.0).abs() < 1e-5);
        // Rotation and scale of the latent change nothing.
        let (c, s) = (0.6f32, 0.8f32);
        let turn = t2(&[3.0 * c, 3.0 * s, -3.0 * s, 3.0 * c], 2, 2, &device);
        let turned = a.clone().matmul(turn);
        assert!((unexplained(turned, u.clone()) - 1.0 / 3.0).abs() < 1e-5);
        // A response linear in u (plus a constant) is all explained; one orthogonal to it not at all.
        let linear = t2(&[2.5, -1.0, -1.5, 1.0, 2.5, -1.0, -1.5, 1.0], 4, 2, &device);
        assert!(unexplained(linear, u.clone()).abs() < 1e-5);
        let orthogonal = t2(&[1.0, 1.0, 1.0, 1.0, -1.0, -1.0, -1.0, -1.0], 4, 2, &device);
        assert!((unexplained(orthogonal, u) - 1.0).abs() < 1e-5);
        // A constant action has no fit to judge.
        let constant = t2(&[0.3; 4], 4, 1, &device);
        assert_eq!(unexplained(a, constant), 0.0);
    }

    #[test]
    fn separation_charges_latents_closer_than_rho_times_their_frames_distance() {
        // h = 0, 1, 3 with equal frame distances (every D over its mean is 1). The latent
        // distances 1, 3, 2 over their mean 2 are 0.5, 1.5, 1; at rho = 0.8 only the pair
        // (0, 1) falls short, by 0.3, in both orders: 2 * 0.09 / (6 pairs * 0.64) = 0.046875.
        let device = cpu_device();
        let frames = t2(
            &[0.0, 5.0, 5.0, 5.0, 0.0, 5.0, 5.0, 5.0, 0.0],
            3,
            3,
            &device,
        );
        let h = t2(&[0.0, 1.0, 3.0], 3, 1, &device);
        let got = scalar(separation_loss(h.clone(), frames.clone(), 0.8));
        assert!((got - 0.046875).abs() < 1e-6, "{got}");
        // The latent's scale does not matter, and at rho = 0.5 no pair is short.
        let scaled = scalar(separation_loss(h.clone() * 7.0, frames.clone(), 0.8));
        assert!((scaled - got).abs() < 1e-6, "{scaled}");
        assert_eq!(scalar(separation_loss(h, frames.clone(), 0.5)), 0.0);
        // Two different-looking frames on nearly one latent point are charged, and the
        // gradient moves them apart.
        let device = device.autodiff();
        let collided = t2(&[0.0, 0.0, 2.0, 0.0, 2.1, 0.0], 3, 2, &device).require_grad();
        let frames = Tensor::<2>::from_data(frames.into_data(), &device);
        let loss = separation_loss(collided.clone(), frames, 0.5);
        assert!(scalar(loss.clone()) > 0.0);
        let g = to_vec(collided.grad(&loss.backward()).expect("gradient of h"));
        // Rows 1 and 2 are 0.1 apart in x: descent (-g) moves row 1 left and row 2 right.
        assert!(-g[2] < 0.0 && -g[4] > 0.0, "{g:?}");
    }

    #[test]
    fn local_stretch_charges_steps_the_latent_squashes_against_the_features() {
        // Two samples; rows are i_{t-1} (2), i_t (2), i_{t+1} (2). Features 0, 0 | 1, 3 | 2, 4:
        // std over i_t is 1 (floor 1/3), steps 1, 3, 1, 1 over their mean 1.5 are a = 2/3, 2,
        // 2/3, 2/3. Latents 0, 0 | 1, 0.5 | 2, 1.5: steps 1, 0.5, 1, 1 over their mean 0.875
        // are b = 8/7, 4/7, 8/7, 8/7. At rho = 0.5 only the second step falls short, by
        // 1 - 4/7 = 3/7: (9/49) / 4 steps / 0.25 = 9/49.
        let device = cpu_device();
        let features = t2(&[0.0, 0.0, 1.0, 3.0, 2.0, 4.0], 6, 1, &device);
        let h = t2(&[0.0, 0.0, 1.0, 0.5, 2.0, 1.5], 6, 1, &device);
        let stretch = |h: Tensor<2>, features: Tensor<2>, ratio| {
            scalar(local_stretch_loss(h, features, ratio))
        };
        let got = stretch(h.clone(), features.clone(), 0.5);
        assert!((got - 9.0 / 49.0).abs() < 1e-6, "{got}");
        // Neither the latent's scale nor the features' matters; at rho = 0.25 no step is short.
        let scaled = stretch(h.clone() * 7.0, features.clone() * 5.0, 0.5);
        assert!((scaled - got).abs() < 1e-6, "{scaled}");
        assert_eq!(stretch(h.clone(), features.clone(), 0.25), 0.0);
        // Features that do not move ask for nothing.
        assert_eq!(stretch(h, features.clone() * 0.0, 0.5), 0.0);
        // The gradient lengthens the squashed step and leaves the others.
        let device = device.autodiff();
        let h = t2(&[0.0, 0.0, 1.0, 0.5, 2.0, 1.5], 6, 1, &device).require_grad();
        let features = Tensor::<2>::from_data(features.into_data(), &device);
        let loss = local_stretch_loss(h.clone(), features, 0.5);
        let g = to_vec(h.grad(&loss.backward()).expect("gradient of h"));
        assert!(-g[3] > 0.0 && -g[1] < 0.0, "{g:?}");
        for i in [0, 2, 4, 5] {
            assert_eq!(g[i], 0.0, "{g:?}");
        }
    }

    #[test]
    fn feature_reconstruction_is_the_share_of_the_centred_features_variance_left() {
        // Features (0, 0) and (2, 4): centred (-1, -2) and (1, 2), total variance 1 + 4 = 5.
        let device = cpu_device();
        let features = t2(&[0.0, 0.0, 2.0, 4.0], 2, 2, &device);
        let loss = |decoded: &[f32]| {
            scalar(feature_reconstruction_loss(
                t2(decoded, 2, 2, &device),
                features.clone(),
                false,
            ))
        };
        // A constant decoder leaves all of it; an offset does not count.
        assert!((loss(&[3.0, -1.0, 3.0, -1.0]) - 1.0).abs() < 1e-6);
        assert!(loss(&[7.0, 7.0, 9.0, 11.0]).abs() < 1e-6);
        // (1, 1) and (3, 3), centred (-1, -1) and (1, 1): feature 0 exact, feature 1 off by 1
        // in both rows, so 1 / 5.
        let got = loss(&[1.0, 1.0, 3.0, 3.0]);
        assert!((got - 0.2).abs() < 1e-6, "{got}");
        // Standardised: variances 1 and 4 (both above the floor 0.25), so the errors 0 and 1
        // count as 0 and 1/4, over 1 + 1 = 2.
        let standardised = |decoded: &[f32]| {
            scalar(feature_reconstruction_loss(
                t2(decoded, 2, 2, &device),
                features.clone(),
                true,
            ))
        };
        let got = standardised(&[1.0, 1.0, 3.0, 3.0]);
        assert!((got - 0.125).abs() < 1e-6, "{got}");
        assert!((standardised(&[3.0, -1.0, 3.0, -1.0]) - 1.0).abs() < 1e-6);
        // A feature far below the floor (variance 1e-4 against a floor of about 0.2) counts as
        // if it had the floor's variance: its error 1e-4 adds 1e-4 / 0.200005.
        let faint = t2(&[0.0, 0.0, 0.02, 4.0], 2, 2, &device);
        let got = scalar(feature_reconstruction_loss(
            t2(&[0.0, 0.0, 0.0, 4.0], 2, 2, &device),
            faint,
            true,
        ));
        let floor = 0.1 * (1e-4 + 4.0) / 2.0;
        let want = (1e-4 / floor) / (1e-4 / floor + 1.0);
        assert!((got - want).abs() < 1e-5, "{got} vs {want}");
        // The features are targets: the gradient reaches the decoded values only.
        let device = device.autodiff();
        let features = t2(&[0.0, 0.0, 2.0, 4.0], 2, 2, &device).require_grad();
        let decoded = t2(&[1.0, 1.0, 3.0, 3.0], 2, 2, &device).require_grad();
        let grads =
            feature_reconstruction_loss(decoded.clone(), features.clone(), false).backward();
        assert!(features.grad(&grads).is_none());
        // d/d decoded of sum_f mean_i (c_if - phi_if)^2 / 5 with centring: feature 1's rows
        // are 1 above and 1 below their targets, so 2 * (1, -1) / (2 * 5) = (0.2, -0.2).
        let g = to_vec(
            decoded
                .grad(&grads)
                .expect("gradient of the decoded features"),
        );
        assert_close(&g, &[0.0, 0.2, 0.0, -0.2], 1e-6, "gradient");
    }

    #[test]
    fn the_decoder_reads_the_latent_whatever_its_offset_and_scale() {
        // h = (0, 0), (2, 0), (0, 4), (2, 4): mean (1, 2), squared deviations 1 and 4 per
        // coordinate, RMS spread sqrt(2.5).
        let device = cpu_device();
        let h = t2(&[0.0, 0.0, 2.0, 0.0, 0.0, 4.0, 2.0, 4.0], 4, 2, &device);
        let s = 2.5f64.sqrt();
        let want: Vec<f64> = [-1.0, -2.0, 1.0, -2.0, -1.0, 2.0, 1.0, 2.0]
            .iter()
            .map(|x| x / s)
            .collect();
        assert_close(
            &to_vec(decoder_input(h.clone())),
            &want,
            1e-5,
            "standardised",
        );
        // Drifted and stretched alike: the same input.
        let drifted = decoder_input(h.clone() * 3.0 + 150.0);
        assert_close(&to_vec(drifted), &want, 1e-4, "drifted");
        // A quarter turn of the latent turns the input by a quarter turn.
        let turn = t2(&[0.0, -1.0, 1.0, 0.0], 2, 2, &device);
        let turned = decoder_input(h.clone().matmul(turn.clone()));
        let want_turned = to_vec(decoder_input(h).matmul(turn));
        let want_turned: Vec<f64> = want_turned.iter().map(|&x| x as f64).collect();
        assert_close(&to_vec(turned), &want_turned, 1e-5, "turned");
    }

    #[test]
    fn frame_block_distances_average_4x4_blocks_before_squaring() {
        // Frame 0 is black; frame 1 has one pixel at 1.0 (its block's mean 1/16); frame 2 that
        // pixel's whole block at 1.0. Squared distances of the block means: 1/256, 1, and
        // between frames 1 and 2 (15/16)^2.
        let device = cpu_device();
        let mut values = vec![0.0f32; 3 * 8 * 8];
        values[64 + 5 * 8 + 1] = 1.0;
        for r in 4..8 {
            for c in 0..4 {
                values[128 + r * 8 + c] = 1.0;
            }
        }
        let frames = Tensor::<4>::from_data(TensorData::new(values, [3, 1, 8, 8]), &device);
        let d = to_vec(frame_block_distances(frames));
        let w = (15.0f64 / 16.0).powi(2);
        let want = [0.0, 1.0 / 256.0, 1.0, 1.0 / 256.0, 0.0, w, 1.0, w, 0.0];
        assert_close(&d, &want, 1e-6, "block distances");
    }

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
    fn turn_term_charges_a_response_that_turns_along_the_latent_and_not_a_flat_one() {
        // B_g is I, a quarter turn R and -I: one map fits (I + R - I) / 3 = R / 3, leaving
        // 2 (20/9 + 8/9 + 20/9) = 96/9 of the total 3 * 4 = 12, i.e. 8/9; each group's own map
        // leaves nothing. Flat (B_g = I everywhere) one map explains it all: 0. The latent is
        // turned by (0.6, 0.8), which changes nothing.
        let device = cpu_device();
        let quarter = [[0.0f32, 1.0], [-1.0, 0.0]];
        let turn = |maps, regions| {
            let (h, u, a) = regional_responses(maps, (0.6, 0.8), &device);
            scalar(action_response_turn(
                a,
                u,
                h,
                regions,
                ResponseGrouping::PrincipalAxis,
            ))
        };
        assert!((turn([IDENTITY, quarter, MINUS], 3) - 8.0 / 9.0).abs() < 1e-5);
        assert!(turn([IDENTITY, IDENTITY, IDENTITY], 3).abs() < 1e-5);
        // The flat-chart term sees the turned batch only as a share no map explains.
        let (_, u, a) = regional_responses([IDENTITY, quarter, MINUS], (0.6, 0.8), &device);
        assert!((scalar(action_response_unexplained(a, u)) - 8.0 / 9.0).abs() < 1e-5);
        // Groups of 3 rows cannot fit 2 regressors and an intercept: no judgement.
        assert_eq!(turn([IDENTITY, quarter, MINUS], 4), 0.0);
    }

    #[test]
    fn sign_term_charges_regions_whose_response_runs_backwards() {
        // B_g = I, I, -I: the whole batch fits I / 3, whose entries' root mean square is
        // sqrt(2 / 9 / 4) = 1 / (3 sqrt 2). The third group's diagonal is (-1, -1): relu sum 2,
        // mean over the 3 groups 2/3, over the scale: 2 sqrt 2.
        let device = cpu_device().autodiff();
        let sign = |maps, regions| {
            let (h, u, a) = regional_responses(maps, (1.0, 0.0), &device);
            scalar(action_response_sign(
                a,
                u,
                h,
                regions,
                ResponseGrouping::PrincipalAxis,
                SignForm::Diagonal,
                0.0,
            ))
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
        let loss = action_response_sign(
            a.clone(),
            u.clone(),
            h,
            3,
            ResponseGrouping::PrincipalAxis,
            SignForm::Diagonal,
            singular_floor,
        );
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

    /// A latent that hooks back (24 rows): an arm `A` of 8 points along `y = 0` near the
    /// origin with response `I`, and at `x` 10 to 10.75 two runs side by side, `B` at `y =
    /// -0.5` (response `I`) and the hook `C` at `y = 0.5` (response `-I`), interleaved along
    /// `x` in steps of 0.05. Each run holds each of the four unit actions twice.
    fn hooked_responses(device: &Device) -> (Tensor<2>, Tensor<2>, Tensor<2>) {
        let actions = [[1.0f32, 0.0], [0.0, 1.0], [-1.0, 0.0], [0.0, -1.0]];
        let (mut h, mut u, mut a) = (vec![], vec![], vec![]);
        for j in 0..8 {
            let [u0, u1] = actions[j % 4];
            let x = 0.1 * j as f32;
            for (point, sign) in [
                ([x, 0.0], 1.0),
                ([10.0 + x, -0.5], 1.0),
                ([10.05 + x, 0.5], -1.0),
            ] {
                h.extend(point);
                u.extend([u0, u1]);
                a.extend([sign * u0, sign * u1]);
            }
        }
        (
            t2(&h, 24, 2, device),
            t2(&u, 24, 2, device),
            t2(&a, 24, 2, device),
        )
    }

    #[test]
    fn clusters_follow_a_hook_that_principal_axis_slices_mix() {
        let device = cpu_device();
        let (h, _, _) = hooked_responses(&device);
        let values: Vec<f64> = to_vec(h.clone()).into_iter().map(f64::from).collect();
        let points: Vec<&[f64]> = values.chunks(2).collect();
        // Rows 3j, 3j + 1, 3j + 2 are A_j, B_j, C_j. The centres start at A_0 (farthest from
        // the mean), C_7 (farthest from A_0) and B_0 (1.5625 from C_7; every A is within 0.49
        // of A_0, every C within 0.49 of C_7), and Lloyd's iterations keep the three runs.
        let run = |offset: usize| (0..8).map(|j| 3 * j + offset).collect::<Vec<_>>();
        assert_eq!(cluster_rows(&points, 3, 4), vec![run(0), run(2), run(1)]);
        // The principal axis is x (the runs' y offsets cancel), so the slices past A hold B and
        // C alike.
        let order = principal_axis_order(h);
        assert_eq!(order[..8], run(0)[..]);
        let mut second: Vec<usize> = order[8..16].to_vec();
        second.sort();
        assert_eq!(second, vec![1, 2, 4, 5, 7, 8, 10, 11]);
        // A cluster under `min_rows` is dissolved into the nearest other: the outlier at (4, 20)
        // starts the first centre, (10, 0) and (0, 0.4) the others; it is left alone and joins
        // the run at x = 0 (centre (0, 0.2)), the nearer.
        let mut values = vec![];
        for j in 0..5 {
            values.extend([0.0, 0.1 * j as f64, 10.0, 0.1 * j as f64]);
        }
        values.extend([4.0, 20.0]);
        let points: Vec<&[f64]> = values.chunks(2).collect();
        assert_eq!(
            cluster_rows(&points, 3, 2),
            vec![vec![1, 3, 5, 7, 9], vec![0, 2, 4, 6, 8, 10]]
        );
        // Identical points make one group, whatever the regions asked for.
        let same = [1.0, 2.0];
        assert_eq!(
            cluster_rows(&[&same, &same, &same], 3, 1),
            vec![vec![0, 1, 2]]
        );
    }

    #[test]
    fn eigenvalue_sign_term_charges_a_shear_the_diagonal_form_misses() {
        // B_g = I, I and the shear S = [[1, 2], [2, 1]] (eigenvalues 3 and -1, diagonal
        // positive). The whole batch fits (2 I + S) / 3 = [[1, 2/3], [2/3, 1]], rms entry
        // sqrt(26) / 6. The diagonal form charges nothing; the eigenvalue form charges the
        // shear's -1, over 3 groups and the scale: 6 / (3 sqrt 26) = 2 / sqrt 26.
        let device = cpu_device();
        let shear = [[1.0f32, 2.0], [2.0, 1.0]];
        let sign = |maps, form| {
            let (h, u, a) = regional_responses(maps, (1.0, 0.0), &device);
            scalar(action_response_sign(
                a,
                u,
                h,
                3,
                ResponseGrouping::PrincipalAxis,
                form,
                0.0,
            ))
        };
        assert!(sign([IDENTITY, IDENTITY, shear], SignForm::Diagonal).abs() < 1e-6);
        let got = sign([IDENTITY, IDENTITY, shear], SignForm::Eigenvalues);
        assert!((got - 2.0 / 26f64.sqrt()).abs() < 1e-4, "{got}");
        // A turn by 60 degrees keeps both real parts at cos 60 > 0; one by 120 does not (cos
        // 120 = -1/2 each): the diagonal form charges 2 x 1/2, the eigenvalue form 1/2 (and the
        // root's floor, 1e-3 of the scale, over the 3 groups and the scale: 1/3000).
        let turn = |deg: f32| {
            let (c, s) = (deg.to_radians().cos(), deg.to_radians().sin());
            [[c, s], [-s, c]]
        };
        assert!(sign([IDENTITY, turn(60.0), IDENTITY], SignForm::Eigenvalues).abs() < 1e-6);
        let diagonal = sign([IDENTITY, turn(120.0), IDENTITY], SignForm::Diagonal);
        let eigen = sign([IDENTITY, turn(120.0), IDENTITY], SignForm::Eigenvalues);
        assert!(
            (diagonal - 2.0 * (eigen - 1.0 / 3000.0)).abs() < 1e-4,
            "{diagonal} vs {eigen}"
        );
        // The smallest real part itself: real eigenvalues 3 and -1; a complex pair 1 +- 2i.
        let m = |v: [f32; 4]| t2(&v, 2, 2, &device);
        let got = scalar(min_eigenvalue_real_part(m([1.0, 2.0, 2.0, 1.0])));
        assert!((got + 1.0).abs() < 1e-5, "{got}");
        let got = scalar(min_eigenvalue_real_part(m([1.0, -2.0, 2.0, 1.0])));
        assert!((got - (1.0 - 1e-3)).abs() < 1e-5, "{got}");
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
            scalar(action_response_sign(
                a,
                u,
                h,
                3,
                ResponseGrouping::PrincipalAxis,
                SignForm::Diagonal,
                floor,
            ))
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

    #[test]
    fn sign_term_on_clusters_sees_the_hook_that_slices_average_away() {
        // The whole batch fits I / 3 (A and B give 4 I each to x^T a, C gives -4 I, over x^T x
        // = 12 I): its drive block's rms entry is 1 / (3 sqrt 2). Slices along the principal
        // axis hold four rows of B and four of C with the same actions: their maps are 0, and
        // A's is I, so nothing is charged. Clusters are A, C and B: C's diagonal (-1, -1) gives
        // 2, over 3 groups and the scale: 2 sqrt 2.
        let device = cpu_device();
        let sign = |grouping| {
            let (h, u, a) = hooked_responses(&device);
            scalar(action_response_sign(
                a,
                u,
                h,
                3,
                grouping,
                SignForm::Diagonal,
                0.0,
            ))
        };
        assert!(sign(ResponseGrouping::PrincipalAxis).abs() < 1e-5);
        let got = sign(ResponseGrouping::Clusters);
        assert!((got - 2.0 * 2f64.sqrt()).abs() < 1e-4, "{got}");
    }

    #[test]
    fn action_response_gradient_flows_through_the_regressors_as_well() {
        // The reference: 1 - R^2 of a centred least-squares fit in f64 (nalgebra's SVD solve,
        // not the Gram inverse the code uses).
        fn unexplained(a: &[f64], x: &[f64]) -> f64 {
            let centre = |v: &[f64]| {
                let m = nalgebra::DMatrix::from_row_slice(6, 2, v);
                let mean = m.row_mean();
                nalgebra::DMatrix::from_fn(6, 2, |i, j| m[(i, j)] - mean[j])
            };
            let (a, x) = (centre(a), centre(x));
            let b = x.clone().svd(true, true).solve(&a, 1e-12).expect("solve");
            (&a - &x * b).norm_squared() / a.norm_squared()
        }
        let a = [
            0.3, 0.1, -0.5, 0.4, 0.9, -0.2, -0.1, -0.6, 0.2, 0.5, 0.7, -0.3,
        ];
        let x = [
            1.0, 0.2, -0.4, 0.8, 0.3, -0.9, -1.1, 0.1, 0.6, 0.4, -0.2, -0.7,
        ];
        let device = cpu_device().autodiff();
        let tensor = |v: &[f64]| {
            let v: Vec<f32> = v.iter().map(|&e| e as f32).collect();
            Tensor::<2>::from_data(TensorData::new(v, [6, 2]), &device).require_grad()
        };
        let (a_t, x_t) = (tensor(&a), tensor(&x));
        let loss = action_response_unexplained(a_t.clone(), x_t.clone());
        assert!((scalar(loss.clone()) - unexplained(&a, &x)).abs() < 1e-5);
        let grads = loss.backward();
        let got_a = to_vec(a_t.grad(&grads).expect("gradient of a"));
        let got_x = to_vec(x_t.grad(&grads).expect("gradient of x"));
        for k in 0..12 {
            let nudged = |v: [f64; 12], by: f64| {
                let mut v = v;
                v[k] += by;
                v
            };
            let want_a =
                (unexplained(&nudged(a, 1e-6), &x) - unexplained(&nudged(a, -1e-6), &x)) / 2e-6;
            let want_x =
                (unexplained(&a, &nudged(x, 1e-6)) - unexplained(&a, &nudged(x, -1e-6))) / 2e-6;
            assert!((f64::from(got_a[k]) - want_a).abs() < 1e-3, "d/da[{k}]");
            assert!((f64::from(got_x[k]) - want_x).abs() < 1e-3, "d/dx[{k}]");
        }
    }

    #[test]
    fn correlation_penalty_is_the_squared_off_diagonal_correlation() {
        let device = cpu_device();
        // Columns (1, 2, 3) and (1, 3, 2): deviations (-1, 0, 1), (-1, 1, 0), covariance 1/3,
        // variances 2/3 each, so corr = 0.5 and the penalty 0.25.
        let h = t2(&[1.0, 1.0, 2.0, 3.0, 3.0, 2.0], 3, 2, &device);
        assert!((scalar(correlation_penalty(h.clone())) - 0.25).abs() < 1e-5);
        // Scale-free: the same for a 100x smaller latent.
        assert!((scalar(correlation_penalty(h * 0.01)) - 0.25).abs() < 1e-4);
        // Uncorrelated columns (1, -1, 1, -1) and (1, 1, -1, -1): 0.
        let h = t2(&[1.0, 1.0, -1.0, 1.0, 1.0, -1.0, -1.0, -1.0], 4, 2, &device);
        assert!(scalar(correlation_penalty(h)).abs() < 1e-6);
    }

    /// The dynamics' parameters read out to f64 by path (`fc1.weight` is `[in, out]`).
    struct Params(std::collections::BTreeMap<String, (Vec<usize>, Vec<f64>)>);

    struct CollectParams {
        path: Vec<String>,
        out: std::collections::BTreeMap<String, (Vec<usize>, Vec<f64>)>,
    }

    impl burn::module::ModuleVisitor for CollectParams {
        fn enter_module(&mut self, name: &str, _: &str) {
            self.path.push(name.to_string());
        }
        fn exit_module(&mut self, _: &str, _: &str) {
            self.path.pop();
        }
        fn visit_float<const D: usize>(&mut self, param: &burn::module::Param<Tensor<D>>) {
            let value = param.val();
            let dims = value.dims().to_vec();
            let values = to_vec(value).into_iter().map(f64::from).collect();
            self.out.insert(self.path.join("."), (dims, values));
        }
    }

    impl Params {
        fn of(dynamics: &Dynamics) -> Self {
            use burn::module::Module;
            let mut collect = CollectParams {
                path: vec![],
                out: Default::default(),
            };
            dynamics.visit(&mut collect);
            Params(collect.out)
        }

        /// `x W + b` for one row.
        fn dense(&self, layer: &str, x: &[f64]) -> Vec<f64> {
            let (dims, w) = &self.0[&format!("{layer}.weight")];
            let (_, b) = &self.0[&format!("{layer}.bias")];
            let (inputs, outputs) = (dims[0], dims[1]);
            assert_eq!(x.len(), inputs);
            (0..outputs)
                .map(|o| b[o] + (0..inputs).map(|i| x[i] * w[i * outputs + o]).sum::<f64>())
                .collect()
        }

        /// f64 re-implementation of the documented dynamics for one row:
        /// `a = MLP(h, dt v, u)`, `v' = v + dt a`, `h' = h + dt v'`; returns `(h', v')` and the
        /// pre-activations of both hidden layers.
        fn forward(&self, h: &[f64], v: &[f64], u: &[f64], dt: f64) -> (Vec<f64>, [Vec<f64>; 2]) {
            let x: Vec<f64> = h
                .iter()
                .copied()
                .chain(v.iter().map(|x| x * dt))
                .chain(u.iter().copied())
                .collect();
            let pre1 = self.dense("fc1", &x);
            let pre2 = self.dense("fc2", &pre1.iter().map(|p| p.max(0.0)).collect::<Vec<_>>());
            let a = self.dense("fc3", &pre2.iter().map(|p| p.max(0.0)).collect::<Vec<_>>());
            let v_next: Vec<f64> = v.iter().zip(&a).map(|(v, a)| v + dt * a).collect();
            let h_next = h.iter().zip(&v_next).map(|(h, v)| h + dt * v);
            (h_next.chain(v_next.iter().copied()).collect(), [pre1, pre2])
        }
    }

    fn random_dynamics(seed: u64, device: &Device) -> Dynamics {
        reinit_params(DynamicsConfig::new(2).init(device), seed)
    }

    /// `n x 2` values from a fixed LCG, uniform in [-1, 1) (test inputs, no crate RNG).
    fn lcg(state: &mut u64, n: usize) -> Vec<f32> {
        (0..2 * n)
            .map(|_| {
                *state = state
                    .wrapping_mul(6364136223846793005)
                    .wrapping_add(1442695040888963407);
                ((*state >> 40) as f32 / (1u64 << 24) as f32) * 2.0 - 1.0
            })
            .collect()
    }

    #[test]
    fn curvature_loss_vanishes_without_perturbation() {
        let device = cpu_device();
        let dynamics = random_dynamics(7, &device);
        let mut state = 1;
        let n = 5;
        let [h, v, u] = [0; 3].map(|_| t2(&lcg(&mut state, n), n, 2, &device));
        let zero = || t2(&vec![0.0; 2 * n], n, 2, &device);
        let loss = scalar(curvature_loss(
            &dynamics,
            h,
            v,
            u,
            zero(),
            zero(),
            zero(),
            0.02,
        ));
        assert!(loss.abs() < 1e-10, "curvature {loss}");
    }

    /// Checks `Dynamics::forward_jvp`'s tangent twice:
    /// 1. against the central finite difference `(f(z + s t) - f(z - s t)) / (2 s)` of the
    ///    crate's own f32 `forward`, s = 1e-3, on the whole output (relative 1e-3);
    /// 2. its network part (the tangent minus the identity part `(t_h + dt t_v, t_v)`, which
    ///    dominates for small dt and would hide an error in the MLP tangent) against an f64
    ///    finite difference, s = 1e-6, of an f64 re-implementation of the dynamics that is first
    ///    checked to match the crate's `forward` (relative 1e-4), with no ReLU kink crossed.
    fn check_jvp(dt: f64) {
        let device = cpu_device();
        let dynamics = random_dynamics(11, &device);
        let n = 6;
        let mut state = 42;
        let [h, v, u, th, tv, tu] = [0; 6].map(|_| lcg(&mut state, n));
        let t = |x: &[f32]| t2(x, n, 2, &device);
        let shifted = |x: &[f32], dx: &[f32], s: f32| {
            t2(
                &x.iter().zip(dx).map(|(a, b)| a + s * b).collect::<Vec<_>>(),
                n,
                2,
                &device,
            )
        };
        let (base, jvp) =
            dynamics.forward_jvp(t(&h), t(&v), t(&u), Some((t(&th), t(&tv), t(&tu))), dt);
        let (base, jvp) = (to_vec(base.z()), to_vec(jvp.expect("tangent given").z()));

        // 1. f32 finite difference of the crate's forward.
        let s = 1e-3f32;
        let at = |sign: f32| {
            let z = dynamics.forward(
                shifted(&h, &th, sign * s),
                shifted(&v, &tv, sign * s),
                shifted(&u, &tu, sign * s),
                dt,
            );
            to_vec(z.z())
        };
        let (plus, minus) = (at(1.0), at(-1.0));
        let (mut err2, mut norm2) = (0.0, 0.0);
        for i in 0..4 * n {
            let fd = (plus[i] as f64 - minus[i] as f64) / (2.0 * s as f64);
            err2 += (fd - jvp[i] as f64).powi(2);
            norm2 += (jvp[i] as f64).powi(2);
        }
        let rel = (err2 / norm2).sqrt();
        assert!(rel < 1e-3, "dt {dt}: JVP vs f32 finite difference: {rel}");

        // 2. The network part against the f64 reference.
        let params = Params::of(&dynamics);
        let row = |x: &[f32], r: usize| [x[2 * r] as f64, x[2 * r + 1] as f64];
        let (mut err2, mut norm2) = (0.0, 0.0);
        let s = 1e-6;
        for r in 0..n {
            let (hr, vr, ur) = (row(&h, r), row(&v, r), row(&u, r));
            let (thr, tvr, tur) = (row(&th, r), row(&tv, r), row(&tu, r));
            let (reference, pre) = params.forward(&hr, &vr, &ur, dt);
            for k in 0..4 {
                let got = base[4 * r + k] as f64;
                let want = reference[k];
                assert!(
                    (got - want).abs() <= 1e-4 * (1.0 + want.abs()),
                    "dt {dt}: forward row {r}[{k}]: crate {got}, reference {want}"
                );
            }
            let step = |sign: f64| {
                let add =
                    |x: &[f64; 2], d: &[f64; 2]| [x[0] + sign * s * d[0], x[1] + sign * s * d[1]];
                params.forward(&add(&hr, &thr), &add(&vr, &tvr), &add(&ur, &tur), dt)
            };
            let ((plus, pre_plus), (minus, pre_minus)) = (step(1.0), step(-1.0));
            // Piecewise-linear network: no pre-activation changes sign along the segment, so the
            // finite difference is exact up to rounding (layer 2 is linear once layer 1 is).
            for layer in 0..2 {
                for (j, p) in pre[layer].iter().enumerate() {
                    assert!(
                        p.signum() == pre_plus[layer][j].signum()
                            && p.signum() == pre_minus[layer][j].signum(),
                        "dt {dt}: row {r} crosses a ReLU kink (layer {layer} unit {j}); move the inputs"
                    );
                }
            }
            for k in 0..4 {
                let c = k % 2;
                let identity = if k < 2 { thr[c] + dt * tvr[c] } else { tvr[c] };
                let fd_net = (plus[k] - minus[k]) / (2.0 * s) - identity;
                let jvp_net = jvp[4 * r + k] as f64 - identity;
                err2 += (fd_net - jvp_net).powi(2);
                norm2 += fd_net.powi(2);
            }
        }
        let rel = (err2 / norm2).sqrt();
        assert!(norm2 > 0.0);
        assert!(
            rel < 1e-4,
            "dt {dt}: network part of the JVP vs f64 finite difference: {rel}"
        );
    }

    #[test]
    fn dynamics_jvp_matches_finite_difference() {
        for dt in [1.0, 0.5, 0.1, 0.02] {
            check_jvp(dt);
        }
    }

    #[test]
    fn loss_config_validate_rejects_bad_values() {
        assert!(LossConfig::default().validate().is_ok());
        let field_of = |config: LossConfig| match config.validate() {
            Err(Error::InvalidConfig { field, .. }) => field,
            other => panic!("expected InvalidConfig, got {other:?}"),
        };
        let bad = |edit: fn(&mut LossConfig)| {
            let mut config = LossConfig::default();
            edit(&mut config);
            field_of(config)
        };
        assert_eq!(bad(|c| c.lambda_r = -1.0), "loss.lambda_r");
        assert_eq!(bad(|c| c.lambda_cpc = -0.5), "loss.lambda_cpc");
        assert_eq!(bad(|c| c.lambda_curv = f64::NAN), "loss.lambda_curv");
        assert_eq!(bad(|c| c.latent_noise_std = -0.1), "loss.latent_noise_std");
        assert_eq!(bad(|c| c.curvature_std = -1e-3), "loss.curvature_std");
        assert_eq!(bad(|c| c.kp = 0.0), "loss.kp");
        assert_eq!(bad(|c| c.kp = -2.0), "loss.kp");
        assert_eq!(bad(|c| c.kp = f64::INFINITY), "loss.kp");
        assert_eq!(bad(|c| c.lyapunov_dt_s = Some(0.0)), "loss.lyapunov_dt_s");
        assert_eq!(
            bad(|c| c.action_response_turn_weight = -1.0),
            "loss.action_response_turn_weight"
        );
        assert_eq!(
            bad(|c| c.action_response_sign_weight = f64::NAN),
            "loss.action_response_sign_weight"
        );
        assert_eq!(
            bad(|c| c.action_response_regions = 1),
            "loss.action_response_regions"
        );
        // Zero weights and kd = 0 are allowed (PC3 is lambda_r = 0).
        let mut ok = LossConfig {
            lambda_r: 0.0,
            kd: 0.0,
            latent_noise_std: 0.0,
            ..LossConfig::default()
        };
        assert!(ok.validate().is_ok());
        ok.lyapunov_dt_s = Some(0.05);
        assert!(ok.validate().is_ok());
    }
}
