//! Latent dynamics `g`: `v_{t+1} = g(h_t, v_t, u_t)`, `h_{t+1} = h_t + dt v_{t+1}`, with a
//! Gaussian transition density of learned diagonal std, and its exact Jacobian-vector product.

use burn::module::{Module, Param};
use burn::nn::{Linear, LinearConfig};
use burn::tensor::activation::relu;
use burn::tensor::{Device, Tensor};

use crate::error::{Error, Result};

/// Dynamics architecture.
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct DynamicsConfig {
    /// Dimension of `h` and `v` (= du).
    pub latent_dim: usize,
    /// Hidden units of each of the MLP's two hidden layers.
    pub hidden: usize,
    /// Initial transition std (of `h'` and of the displacement `dt v'`); 0.1 lets CPC see
    /// differences between fresh, small latents from the first step (std 1 took thousands).
    pub init_std: f64,
    /// How the action enters the latent acceleration.
    #[serde(default)]
    pub input: DynamicsInput,
    /// A full covariance for the transition density (`false`: diagonal, the paper's). Its
    /// precision is `W^T W` with `W` lower triangular: the diagonal `exp(-log_std)` and a
    /// learned strict lower part, started at 0. A diagonal std is fixed to the latent's axes,
    /// so when the prediction error of one joint runs diagonally it sets the std of both axes,
    /// and CPC cannot resolve a thin direction across it.
    #[serde(default)]
    pub full_covariance: bool,
}

/// How `u` enters `a`, the latent acceleration of [`Dynamics`].
#[derive(Debug, Clone, Copy, Default, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(tag = "kind", rename_all = "kebab-case")]
pub enum DynamicsInput {
    /// `a(h, dt v, u)`: the action is an input of the MLP (PC3's and the paper's `g`).
    #[default]
    Mlp,
    /// Control-affine with a constant, positive diagonal input matrix:
    /// `Q (a(Q^T h, Q^T dt v) + diag(b) u)`, in unoriented coordinates, `b = exp(log_b)` learned from
    /// `initial_gain`. The encoder must then find coordinates in which each action component
    /// accelerates its own latent axis, positively and by the same amount everywhere, which is
    /// what a PD law with diagonal gains needs: the mirror images and rotations the
    /// orientation search chooses between no longer fit the model equally well.
    ConstantDiagonal {
        /// `b` at initialisation (latent units per s^2 per unit action).
        initial_gain: f64,
    },
}

impl DynamicsConfig {
    pub fn new(latent_dim: usize) -> Self {
        Self {
            latent_dim,
            hidden: 64,
            init_std: 0.1,
            input: DynamicsInput::Mlp,
            full_covariance: false,
        }
    }

    pub(crate) fn validate(&self) -> Result<()> {
        if self.latent_dim == 0 || self.hidden == 0 {
            return Err(Error::config(
                "model.dynamics",
                "latent_dim and hidden must be positive",
            ));
        }
        if !(self.init_std.is_finite() && self.init_std > 0.0) {
            return Err(Error::config(
                "model.dynamics.init_std",
                format!("{} must be > 0", self.init_std),
            ));
        }
        if let DynamicsInput::ConstantDiagonal { initial_gain } = self.input
            && !(initial_gain.is_finite() && initial_gain > 0.0)
        {
            return Err(Error::config(
                "model.dynamics.input.initial_gain",
                format!("{initial_gain} must be > 0"),
            ));
        }
        Ok(())
    }

    pub fn init(&self, device: &Device) -> Dynamics {
        let d = self.latent_dim;
        let (mlp_inputs, log_input_gain) = match self.input {
            DynamicsInput::Mlp => (3 * d, None),
            DynamicsInput::ConstantDiagonal { initial_gain } => (
                2 * d,
                Some(Param::from_tensor(Tensor::full(
                    [d],
                    initial_gain.ln(),
                    device,
                ))),
            ),
        };
        Dynamics {
            fc1: LinearConfig::new(mlp_inputs, self.hidden).init(device),
            fc2: LinearConfig::new(self.hidden, self.hidden).init(device),
            fc3: LinearConfig::new(self.hidden, d).init(device),
            log_std: Param::from_tensor(Tensor::full([2 * d], self.init_std.ln(), device)),
            precision_lower: self
                .full_covariance
                .then(|| Param::from_tensor(Tensor::zeros([2 * d, 2 * d], device))),
            log_input_gain,
            latent_transform: super::transform_param(d, device),
        }
    }
}

/// The dynamics network. `g` is parametrised as a velocity increment,
/// `g(h, v, u) = v + dt a(h, dt v, u)` with `a` a 2-hidden-layer ReLU MLP: the MLP sees the
/// per-step displacement `dt v` (same scale as `h`) rather than `v` (1/dt = 50 times larger).
#[derive(Module, Debug)]
pub struct Dynamics {
    fc1: Linear,
    fc2: Linear,
    fc3: Linear,
    /// Log std of the transition density over unoriented `(h', dt v')`, `[2 du]`: velocities are
    /// scored as per-step displacements so both halves share one scale (see `losses::procl_loss`).
    pub log_std: Param<Tensor<1>>,
    /// The strict lower part of the precision factor `W` (`[2 du, 2 du]`, only the entries
    /// below the diagonal are used) when `full_covariance` is on.
    pub precision_lower: Option<Param<Tensor<2>>>,
    /// `log b` of [`DynamicsInput::ConstantDiagonal`], `[du]` (absent for [`DynamicsInput::Mlp`]).
    pub log_input_gain: Option<Param<Tensor<1>>>,
    /// The encoder's orientation `Q` (kept equal to it): the MLP works in unoriented
    /// coordinates, `a_Q(h, v, u) = Q a(Q^T h, Q^T v, u)`, so reorienting both networks leaves
    /// every PC3 loss exactly unchanged.
    pub latent_transform: Param<Tensor<2>>,
}

/// The transition density's mean `f(z, u) = (h', v')` and log std.
#[derive(Debug, Clone)]
pub struct Transition {
    /// `[n, du]`
    pub h_next: Tensor<2>,
    /// `[n, du]`
    pub v_next: Tensor<2>,
}

impl Transition {
    /// `[n, 2 du]`: `(h', v')`.
    pub fn z(&self) -> Tensor<2> {
        Tensor::cat(vec![self.h_next.clone(), self.v_next.clone()], 1)
    }
}

fn dense(layer: &Linear, x: Tensor<2>) -> Tensor<2> {
    layer.forward(x)
}

/// The tangent through a linear layer: `W t` (no bias).
fn dense_tangent(layer: &Linear, t: Tensor<2>) -> Tensor<2> {
    t.matmul(layer.weight.val())
}

impl Dynamics {
    /// Latent rows `[n, du]` in the unoriented coordinates: `x Q` (= `(Q^T x^T)^T`).
    pub fn unoriented(&self, x: Tensor<2>) -> Tensor<2> {
        x.matmul(self.latent_transform.val())
    }

    /// Unoriented rows back to latent coordinates: `x Q^T`.
    fn oriented(&self, x: Tensor<2>) -> Tensor<2> {
        x.matmul(self.latent_transform.val().transpose())
    }

    /// The strictly lower triangular part of the precision factor, `[2 du, 2 du]`, if any.
    pub fn precision_off_diagonal(&self) -> Option<Tensor<2>> {
        self.precision_lower
            .as_ref()
            .map(|lower| lower.val().tril(-1))
    }

    /// `b` of [`DynamicsInput::ConstantDiagonal`] as a row `[1, du]`.
    pub fn input_gain(&self) -> Option<Tensor<2>> {
        self.log_input_gain
            .as_ref()
            .map(|log_b| log_b.val().exp().unsqueeze_dim(0))
    }

    /// Mean of the transition: `h, v, u [n, du]` -> `(h', v')`.
    pub fn forward(&self, h: Tensor<2>, v: Tensor<2>, u: Tensor<2>, dt: f64) -> Transition {
        self.forward_jvp(h, v, u, None, dt).0
    }

    /// Mean of the transition and, if `tangent = (t_h, t_v, t_u)` is given, its directional
    /// derivative `J_z (t_h, t_v) + J_u t_u` at `(z, u)`, both as `(h', v')` pairs. The tangent is
    /// propagated forward by hand (exact for the ReLU MLP: `W t`, then the ReLU mask).
    pub fn forward_jvp(
        &self,
        h: Tensor<2>,
        v: Tensor<2>,
        u: Tensor<2>,
        tangent: Option<(Tensor<2>, Tensor<2>, Tensor<2>)>,
        dt: f64,
    ) -> (Transition, Option<Transition>) {
        let gain = self.input_gain(); // [1, du] when control-affine
        let mut inputs = vec![self.unoriented(h.clone()), self.unoriented(v.clone()) * dt];
        if gain.is_none() {
            inputs.push(u.clone());
        }
        let x = Tensor::cat(inputs, 1); // [n, 3 du] or [n, 2 du]
        let pre1 = dense(&self.fc1, x); // [n, hidden]
        let a1 = relu(pre1.clone());
        let pre2 = dense(&self.fc2, a1); // [n, hidden]
        let a2 = relu(pre2.clone());
        let mut accel_unoriented = dense(&self.fc3, a2);
        if let Some(gain) = &gain {
            accel_unoriented = accel_unoriented + u * gain.clone();
        }
        let accel = self.oriented(accel_unoriented); // [n, du]
        let v_next = v + accel * dt;
        let h_next = h + v_next.clone() * dt;
        let mean = Transition { h_next, v_next };

        let tangent_out = tangent.map(|(th, tv, tu)| {
            let mut t_inputs = vec![
                self.unoriented(th.clone()),
                self.unoriented(tv.clone()) * dt,
            ];
            if gain.is_none() {
                t_inputs.push(tu.clone());
            }
            let tx = Tensor::cat(t_inputs, 1);
            let t1 = dense_tangent(&self.fc1, tx) * pre1.greater_elem(0.0).float();
            let t2 = dense_tangent(&self.fc2, t1) * pre2.greater_elem(0.0).float();
            let mut t_accel_unoriented = dense_tangent(&self.fc3, t2);
            if let Some(gain) = &gain {
                t_accel_unoriented = t_accel_unoriented + tu * gain.clone();
            }
            let t_accel = self.oriented(t_accel_unoriented);
            let t_v_next = tv + t_accel * dt;
            let t_h_next = th + t_v_next.clone() * dt;
            Transition {
                h_next: t_h_next,
                v_next: t_v_next,
            }
        });
        (mean, tangent_out)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use burn::tensor::TensorData;

    fn rows(values: &[f32], device: &Device) -> Tensor<2> {
        Tensor::from_data(
            TensorData::new(values.to_vec(), [values.len() / 2, 2]),
            device,
        )
    }

    #[test]
    fn precision_factor_uses_only_the_strict_lower_part() {
        let device = crate::model::cpu_device();
        let config = DynamicsConfig {
            full_covariance: true,
            ..DynamicsConfig::new(1)
        };
        let mut dynamics = config.init(&device);
        assert_eq!(
            crate::model::to_vec(dynamics.precision_off_diagonal().expect("full covariance")),
            [0.0; 4]
        );
        dynamics.precision_lower = Some(Param::from_tensor(Tensor::ones([2, 2], &device)));
        let lower = dynamics.precision_off_diagonal().expect("full covariance");
        assert_eq!(crate::model::to_vec(lower), [0.0, 0.0, 1.0, 0.0]);
        assert!(
            DynamicsConfig::new(1)
                .init(&device)
                .precision_off_diagonal()
                .is_none()
        );
    }

    #[test]
    fn constant_diagonal_input_accelerates_each_axis_by_its_gain() {
        let device = crate::model::cpu_device();
        let mut config = DynamicsConfig::new(2);
        config.input = DynamicsInput::ConstantDiagonal { initial_gain: 4.0 };
        // Seeded initialisation keeps the configured gain (it is not redrawn like a weight).
        let dynamics = crate::model::reinit_params(config.init(&device), 5);
        let gain = crate::model::to_vec(dynamics.input_gain().expect("control-affine"));
        assert!(gain.iter().all(|b| (b - 4.0).abs() < 1e-5), "{gain:?}");
        // A mirror-and-swap orientation Q: the action still drives the unoriented axes, so in
        // latent coordinates u_0 moves -h_1 and u_1 moves +h_0.
        let q = [0.0f32, 1.0, -1.0, 0.0];
        let q = Tensor::<2>::from_data(TensorData::new(q.to_vec(), [2, 2]), &device);
        let mut dynamics = dynamics;
        dynamics.latent_transform = dynamics.latent_transform.map(|_| q);
        let (h, v) = (rows(&[0.3, -0.2], &device), rows(&[0.1, 0.4], &device));
        let dt = 0.02;
        let v_next = |u: [f32; 2]| {
            let out = dynamics.forward(h.clone(), v.clone(), rows(&u, &device), dt);
            crate::model::to_vec(out.v_next)
        };
        let (free, pushed) = (v_next([0.0, 0.0]), v_next([0.5, -1.0]));
        // Q diag(b) u = Q (2, -4) = (-4, -2); times dt.
        let expected = [-4.0 * dt, -2.0 * dt];
        for k in 0..2 {
            assert!(
                ((pushed[k] - free[k]) as f64 - expected[k]).abs() < 1e-6,
                "{pushed:?} - {free:?}"
            );
        }
        // The tangent along u alone is the same linear response.
        let zero = rows(&[0.0, 0.0], &device);
        let (_, tangent) = dynamics.forward_jvp(
            h.clone(),
            v.clone(),
            rows(&[0.2, 0.2], &device),
            Some((zero.clone(), zero, rows(&[0.5, -1.0], &device))),
            dt,
        );
        let t_v = crate::model::to_vec(tangent.expect("tangent given").v_next);
        for k in 0..2 {
            assert!(((t_v[k] as f64) - expected[k]).abs() < 1e-6, "{t_v:?}");
        }
    }

    #[test]
    fn input_gain_must_be_positive() {
        let mut config = DynamicsConfig::new(2);
        config.input = DynamicsInput::ConstantDiagonal { initial_gain: 0.0 };
        let err = config.validate().unwrap_err().to_string();
        assert!(err.contains("model.dynamics.input.initial_gain"), "{err}");
    }
}
