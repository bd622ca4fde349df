//! Whole experiments from the command line: resumable stages, the end-to-end demo, the paper's
//! experiment and ablation grids, with their reports.

pub mod ablate;
pub mod demo;
pub mod experiment;
pub mod stages;
