//! The methods ProCL is measured against: the NewtonianVAE (its own networks, ELBO and PID on
//! its posterior mean) and model-predictive control through a learned latent dynamics: CEM
//! (`mpc`) and PC3's own controller, iLQR (`ilqr`).

pub mod ilqr;
pub mod mpc;
pub mod nvae;
