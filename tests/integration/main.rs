//! procl's integration tests, one binary: environments (Fetch-3D in its own file), datasets,
//! the command line.

mod cli;
mod control;
mod custom;
mod data;
mod envs;
mod experiment;
mod faults;
mod fetch;
mod fuzz;
mod nvae;
mod presets;
mod shipped;
mod support;
mod track;
mod train;
