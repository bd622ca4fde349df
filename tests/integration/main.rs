//! procl's integration tests, one binary: environments, datasets, the command line.

mod cli;
mod control;
mod data;
mod envs;
mod nvae;
mod research;
mod track;
mod train;
