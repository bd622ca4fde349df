//! The `procl` command line: collect | info | render (more subcommands follow the data flow).

use std::path::PathBuf;
use std::process::ExitCode;

use anyhow::Context;
use clap::{Parser, Subcommand};
use indicatif::{ProgressBar, ProgressStyle};

use procl::data::{CollectConfig, collect};
use procl::envs::EnvKind;

#[derive(Parser)]
#[command(
    name = "procl",
    version,
    about = "Learn a PD-controllable latent space from pixels, then control with PD"
)]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand)]
enum Command {
    /// Collect a random-control dataset to an .npz file.
    Collect {
        /// Environment: point-mass | reacher.
        #[arg(long)]
        env: String,
        /// Number of transitions (default: spec.md 2's size for the env).
        #[arg(long, default_value_t = 10_000)]
        transitions: usize,
        /// Steps per episode.
        #[arg(long, default_value_t = 100)]
        episode_len: usize,
        /// Seed of the random policy and the start states.
        #[arg(long, default_value_t = 0)]
        seed: u64,
        /// Output .npz file.
        #[arg(long)]
        out: PathBuf,
        /// Replace an existing output file.
        #[arg(long)]
        force: bool,
    },
    /// Validate a dataset and print what it holds.
    Info {
        /// The .npz dataset.
        #[arg(long)]
        data: PathBuf,
    },
    /// Render a strip of frames from a random episode to a PNG.
    Render {
        /// Environment: point-mass | reacher.
        #[arg(long)]
        env: String,
        #[arg(long, default_value_t = 0)]
        seed: u64,
        /// Number of frames in the strip.
        #[arg(long, default_value_t = 8)]
        frames: usize,
        /// Upscaling factor of each 64x64 frame.
        #[arg(long, default_value_t = 4)]
        scale: usize,
        /// Output .png file.
        #[arg(long)]
        out: PathBuf,
        #[arg(long)]
        force: bool,
    },
}

fn progress_bar(len: u64, what: &str) -> ProgressBar {
    let bar = ProgressBar::new(len);
    bar.set_style(
        ProgressStyle::with_template("{msg} [{bar:30}] {pos}/{len} ({per_sec}, eta {eta})")
            .unwrap_or_else(|_| ProgressStyle::default_bar()),
    );
    bar.set_message(what.to_string());
    bar
}

fn run(cli: Cli) -> anyhow::Result<()> {
    match cli.command {
        Command::Collect {
            env,
            transitions,
            episode_len,
            seed,
            out,
            force,
        } => {
            let env: EnvKind = env.parse()?;
            procl::check_writable(&out, force)?;
            let config = CollectConfig {
                transitions,
                episode_len,
                ..CollectConfig::new(env, seed)
            };
            let bar = progress_bar(transitions as u64, "collect");
            let data = collect(&config, |done| bar.set_position(done as u64))?;
            bar.finish_and_clear();
            data.save(&out, force)?;
            println!(
                "wrote {} ({} episodes x {} steps of {env}, seed {seed})",
                out.display(),
                data.episodes(),
                data.steps()
            );
        }
        Command::Info { data } => {
            let dataset = procl::data::Dataset::load(&data)?;
            let m = &dataset.meta;
            println!(
                "{}: {} ({}), {} episodes x {} steps = {} transitions, dt {} s, seed {}, du {}, dq {}",
                data.display(),
                m.env,
                m.source,
                dataset.episodes(),
                dataset.steps(),
                dataset.transitions(),
                m.control_dt_s,
                m.seed,
                dataset.action_dim(),
                dataset.config_dim()
            );
        }
        Command::Render {
            env,
            seed,
            frames,
            scale,
            out,
            force,
        } => {
            let env: EnvKind = env.parse()?;
            procl::check_writable(&out, force)?;
            let image = procl::envs::render_strip(env, seed, frames, scale)
                .with_context(|| format!("rendering {env}"))?;
            image.save_png(&out, force)?;
            println!(
                "wrote {} ({frames} frames of {env}, seed {seed})",
                out.display()
            );
        }
    }
    Ok(())
}

fn main() -> ExitCode {
    match run(Cli::parse()) {
        Ok(()) => ExitCode::SUCCESS,
        Err(error) => {
            eprintln!("error: {}", format!("{error:#}").replace('\n', " "));
            ExitCode::FAILURE
        }
    }
}
