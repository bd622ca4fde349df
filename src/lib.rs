//! procl: PD-controllable latent spaces learned from pixels (ProCL, Wang, Kobilarov, Hager).
//!
//! The modules follow the data flow, each using only those above it:
//! - [`envs`]: the simulated systems and their 64x64 cameras (know nothing of datasets);
//! - [`data`]: random-control datasets, collected and stored as NPZ;
//! - [`model`]: the encoder `e`, the latent `z = (h, v)` and the latent dynamics `g`;
//! - [`losses`]: the PC3 terms, the Lyapunov risk with hindsight targets, the regularisers;
//! - [`control`]: PD and PID laws, the policies that run them on camera frames, and the
//!   demonstrations the oracle PD records for tracking;
//! - [`baselines`]: the NewtonianVAE and model-predictive control on a learned latent;
//! - [`train`]: configurations and presets, batches, the loop, checkpoints, run folders;
//! - [`eval`]: goal reaching, tracking, latent diagnostics and plots of a trained run;
//! - [`runner`]: resumable stages, the demo, the paper's experiment and ablation grids;
//! - [`fuzz`]: every file parser above as a fuzz target.

mod error;
mod fsutil;
mod image_io;

pub mod allocator;
pub mod baselines;
pub mod control;
pub mod data;
pub mod envs;
pub mod eval;
pub mod fuzz;
pub mod losses;
pub mod model;
pub mod runner;
pub mod train;

pub use error::{Error, Result};
pub use fsutil::{FolderLock, check_writable, write_atomically};
pub use image_io::RgbImage;
pub use train::checkpoint::{
    Adam, CheckpointMeta, load_checkpoint, read_checkpoint_meta, save_checkpoint,
};
