//! procl: PD-controllable latent spaces learned from pixels (ProCL, Wang, Kobilarov, Hager).
//!
//! Data flows through the modules in order: [`envs`] simulate and render systems, [`data`]
//! collects random-control datasets to NPZ.

mod error;
mod fsutil;
mod image_io;

pub mod ablate;
pub mod allocator;
mod checkpoint;
pub mod control;
pub mod data;
pub mod demo;
pub mod envs;
pub mod eval;
pub mod experiment;
pub mod losses;
pub mod model;
pub mod nvae;
pub mod orientation;
pub mod pipeline;
pub mod train;

pub use checkpoint::{
    Adam, CheckpointMeta, load_checkpoint, read_checkpoint_meta, save_checkpoint,
};
pub use error::{Error, Result};
pub use fsutil::{check_writable, write_atomically};
pub use image_io::RgbImage;
