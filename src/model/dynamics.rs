//! Latent dynamics `g`: `v_{t+1} = g(h_t, v_t, u_t)`, `h_{t+1} = h_t + dt v_{t+1}`, with a
//! Gaussian transition density of learned diagonal std, and its exact Jacobian-vector product.

use burn::module::{Module, Param};
use burn::nn::{Linear, LinearConfig};
use burn::tensor::activation::relu;
use burn::tensor::{Device, Tensor};

use crate::error::{Error, Result};

/// Dynamics architecture.
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(deny_unknown_fields)]
pub struct DynamicsConfig {
    /// Dimension of `h` and `v` (= du).
    pub latent_dim: usize,
    /// Hidden units of each of the MLP's two hidden layers.
    pub hidden: usize,
    /// Initial transition std (of `h'` and of the displacement `dt v'`); 0.1 lets CPC see
    /// differences between fresh, small latents from the first step (std 1 took thousands).
    pub init_std: f64,
}

impl DynamicsConfig {
    pub fn new(latent_dim: usize) -> Self {
        Self {
            latent_dim,
            hidden: 64,
            init_std: 0.1,
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
        Ok(())
    }

    pub fn init(&self, device: &Device) -> Dynamics {
        let d = self.latent_dim;
        Dynamics {
            fc1: LinearConfig::new(3 * d, self.hidden).init(device),
            fc2: LinearConfig::new(self.hidden, self.hidden).init(device),
            fc3: LinearConfig::new(self.hidden, d).init(device),
            log_std: Param::from_tensor(Tensor::full([2 * d], self.init_std.ln(), device)),
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
        let inputs = vec![
            self.unoriented(h.clone()),
            self.unoriented(v.clone()) * dt,
            u,
        ];
        let x = Tensor::cat(inputs, 1); // [n, 3 du]
        let pre1 = dense(&self.fc1, x); // [n, hidden]
        let a1 = relu(pre1.clone());
        let pre2 = dense(&self.fc2, a1); // [n, hidden]
        let a2 = relu(pre2.clone());
        let accel_unoriented = dense(&self.fc3, a2);
        let accel = self.oriented(accel_unoriented); // [n, du]
        let v_next = v + accel * dt;
        let h_next = h + v_next.clone() * dt;
        let mean = Transition { h_next, v_next };

        let tangent_out = tangent.map(|(th, tv, tu)| {
            let t_inputs = vec![
                self.unoriented(th.clone()),
                self.unoriented(tv.clone()) * dt,
                tu,
            ];
            let tx = Tensor::cat(t_inputs, 1);
            let t1 = dense_tangent(&self.fc1, tx) * pre1.greater_elem(0.0).float();
            let t2 = dense_tangent(&self.fc2, t1) * pre2.greater_elem(0.0).float();
            let t_accel_unoriented = dense_tangent(&self.fc3, t2);
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
