//! The `procl` command line: collect | info | render (more subcommands follow the data flow).

use std::path::{Path, PathBuf};
use std::process::ExitCode;

use anyhow::Context;
use clap::{Parser, Subcommand};
use indicatif::{ProgressBar, ProgressStyle};

use procl::data::{CollectConfig, collect};
use procl::envs::{EnvConfig, EnvKind};
use procl::eval::ReachConfig;
use procl::runner::ablate::GridWork;
use procl::runner::demo::DemoConfig;
use procl::runner::experiment::{Event, ExperimentConfig};
use procl::runner::stages::{Outcome, ThrottledLine};
use procl::train::{Method, RunPaths};

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
        /// Environment: point-mass | reacher | fetch (or the one --env-config configures).
        #[arg(long, required_unless_present = "env_config")]
        env: Option<String>,
        /// A TOML file configuring a variant of the environment: one table, [point-mass],
        /// [reacher] or [fetch], with the fields that differ from its defaults (for the
        /// reacher, e.g. base_m, link1_length_m, fingertip_m, arm_rgb). The dataset records it.
        #[arg(long)]
        env_config: Option<PathBuf>,
        /// Record the data as custom: `procl train` then uses the recipe for data from
        /// elsewhere, and `procl eval` still runs in the recorded simulator.
        #[arg(long)]
        as_custom: bool,
        /// Number of transitions (default: the paper's dataset size for the env, 10,000; fetch 50,000).
        #[arg(long)]
        transitions: Option<usize>,
        /// Steps per episode (default: the env's, 100; reacher 10).
        #[arg(long)]
        episode_len: Option<usize>,
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
    /// Print the resolved configuration of a preset as TOML (a file `train --config` accepts).
    Config {
        /// Environment: point-mass | reacher | fetch.
        #[arg(long)]
        env: String,
        /// procl | pc3 | nvae.
        #[arg(long, default_value = "procl")]
        method: String,
        /// procl (the shipped design, docs/design.md) | paper (the paper as written).
        #[arg(long, default_value = "procl")]
        preset: String,
    },
    /// Validate a dataset and print what it holds.
    Info {
        /// The .npz dataset.
        #[arg(long)]
        data: PathBuf,
    },
    /// Train ProCL (or the PC3 or NewtonianVAE baseline) on a dataset into a run folder.
    Train {
        /// The .npz dataset.
        #[arg(long)]
        data: PathBuf,
        /// procl | pc3 | nvae (pc3 = lambda_R 0, same networks; nvae = NewtonianVAE).
        #[arg(long)]
        method: Option<String>,
        /// Run folder (config.json, model.safetensors, metrics.csv, diagnostics).
        #[arg(long)]
        out: PathBuf,
        /// TOML file over the preset (`preset = "paper"|"procl"`, any config field).
        #[arg(long)]
        config: Option<PathBuf>,
        /// Custom data only: the recipe to train with (generic | point-mass | reacher |
        /// fetch). Default: the reacher's when the frames turn about a hub (an arm's base),
        /// else the generic one.
        #[arg(long)]
        preset_env: Option<String>,
        /// Override the config's seed.
        #[arg(long)]
        seed: Option<u64>,
        /// Training steps (default: the environment's budget, which every published result
        /// uses: 600 point-mass, 1200 reacher, 600 fetch).
        #[arg(long)]
        steps: Option<u64>,
        /// Continue the run in --out from its last checkpoint (with a larger --steps, a finished run
        /// trains on to that step).
        #[arg(long)]
        resume: bool,
        /// cpu, or cuda when built with --features cuda.
        #[arg(long, default_value = "cpu")]
        device: String,
    },
    /// Evaluate goal reaching of a trained run (its latent controller and the oracle on the same
    /// tasks).
    Eval {
        /// Run folder written by `procl train`.
        #[arg(long)]
        run: PathBuf,
        #[arg(long, default_value_t = 50)]
        episodes: usize,
        /// Seed of the start/goal pairs.
        #[arg(long, default_value_t = 1000)]
        seed: u64,
        /// Steps per episode (default: the env's protocol horizon).
        #[arg(long)]
        horizon: Option<usize>,
        /// Controller on the latent (default: the method's own): pd (procl and pc3 runs, the
        /// run's gains) | pid (nvae runs) | mpc (procl and pc3 runs: CEM through the learned
        /// dynamics, horizon 10; writes eval-mpc.json, reach-mpc.png, ...) | ilqr (procl and
        /// pc3 runs: iLQR through the learned dynamics, PC3's controller; eval-ilqr.json, ...) |
        /// p (nvae runs: the PID's Kp alone, the NewtonianVAE paper's controller; eval-p.json).
        #[arg(long)]
        controller: Option<String>,
        /// MPC (CEM and iLQR) planning horizon in steps.
        #[arg(long, default_value_t = 10)]
        mpc_horizon: usize,
    },
    /// Generate demonstration trajectories (smooth paths followed by the oracle) for tracking.
    Demonstrate {
        /// Environment: point-mass | reacher | fetch (or the one --env-config configures).
        #[arg(long, required_unless_present = "env_config")]
        env: Option<String>,
        /// A TOML file configuring a variant of the environment, as for `procl collect`.
        #[arg(long)]
        env_config: Option<PathBuf>,
        /// Path family: circle | figure-eight | spline.
        #[arg(long, default_value = "circle")]
        shape: String,
        /// Number of demonstrations (each a different random path).
        #[arg(long, default_value_t = 4)]
        episodes: usize,
        /// Control steps per demonstration (one loop of a circle or figure-eight).
        #[arg(long, default_value_t = 500)]
        steps: usize,
        #[arg(long, default_value_t = 0)]
        seed: u64,
        /// Output .npz file (the dataset layout).
        #[arg(long)]
        out: PathBuf,
        #[arg(long)]
        force: bool,
    },
    /// Track demonstrations with a trained run's latent PD (and the oracle): track.json, track.png.
    Track {
        /// Run folder written by `procl train`.
        #[arg(long)]
        run: PathBuf,
        /// Demonstrations written by `procl demonstrate`.
        #[arg(long)]
        demo: PathBuf,
    },
    /// Latent diagnostics of a trained run: latent_map.png and the R^2 of q from h.
    Diagnose {
        #[arg(long)]
        run: PathBuf,
    },
    /// The end-to-end demo on point mass: collect, train ProCL and PC3, evaluate, report.html.
    Demo {
        /// Output folder (reused stages are skipped, so an interrupted demo resumes).
        #[arg(long, default_value = "runs/demo")]
        out: PathBuf,
        /// Tiny budget (seconds): the smoke test of the whole pipeline.
        #[arg(long)]
        quick: bool,
        /// Training steps per method (default 600; quick: 15).
        #[arg(long)]
        steps: Option<u64>,
    },
    /// The paper's experiments on all three environments (resumable stages): datasets, ProCL,
    /// PC3 and NewtonianVAE trained and evaluated, the latent-noise ablation, Fetch tracking,
    /// report.html and summary.json.
    Experiment {
        /// Which experiment (`paper`).
        #[arg(value_parser = ["paper"])]
        name: String,
        /// Every stage on a tiny budget (about a minute): the smoke test.
        #[arg(long)]
        quick: bool,
        /// Output folder (finished stages in it are reused).
        #[arg(long, default_value = "results")]
        out: PathBuf,
        /// Run nothing: rebuild report.html and summary.json from the finished stages.
        #[arg(long)]
        report_only: bool,
        /// Rewrite this README's results section (between `<!-- experiment:begin -->` and
        /// `<!-- experiment:end -->`), copying the main figures into docs/img/experiment beside it.
        #[arg(long)]
        readme: Option<PathBuf>,
    },
    /// Train and evaluate every cell of an ablation grid over several seeds (resumable).
    Ablate {
        /// Environment (a 10k-transition dataset with seed 0 is collected into --out), or the
        /// one --env-config configures.
        #[arg(long, required_unless_present = "env_config")]
        env: Option<String>,
        /// A TOML file configuring a variant of the environment to collect from and evaluate
        /// in, as for `procl collect`.
        #[arg(long)]
        env_config: Option<PathBuf>,
        /// Record the data as custom, as `procl collect --as-custom`: every cell starts from
        /// the recipe `procl train` picks for data from elsewhere, not the environment's
        /// preset.
        #[arg(long)]
        as_custom: bool,
        /// The grid TOML ([base] over the preset, [[cell]] with a name and overrides).
        #[arg(long)]
        grid: PathBuf,
        #[arg(long, default_value_t = 3)]
        seeds: u64,
        /// Run only this cell of the grid (to split a grid across processes or machines).
        #[arg(long)]
        cell: Option<String>,
        /// Train nothing: summarise the results already in --out (ablation.jsonl and each
        /// task's result.json).
        #[arg(long)]
        report_only: bool,
        /// Run only task N of the grid (a job-array index: cells x seeds, cell by cell; see
        /// --list-tasks); writes its result.json and no summary.
        #[arg(long, conflicts_with = "report_only")]
        task_index: Option<usize>,
        /// Print the grid's tasks (index, cell, seed) and exit.
        #[arg(long)]
        list_tasks: bool,
        /// First training seed (seeds are seed_start .. seed_start + seeds).
        #[arg(long, default_value_t = 0)]
        seed_start: u64,
        /// Evaluation episodes per seed (and per task set).
        #[arg(long, default_value_t = 50)]
        episodes: usize,
        /// Evaluate each trained seed on this many sets of --episodes tasks (task seeds 1000,
        /// 2000, ...): a seed's success moves with the set of tasks as much as with the
        /// training seed, and the summary's min-max then runs over both.
        #[arg(long, default_value_t = 1)]
        task_sets: u64,
        /// Override the env's protocol horizon.
        #[arg(long)]
        horizon: Option<usize>,
        /// Dataset transitions (default: the paper's size for the env, 10,000; fetch 50,000).
        #[arg(long)]
        transitions: Option<usize>,
        /// Steps per dataset episode (default: `collect`'s for the env, 100; reacher 10).
        #[arg(long)]
        episode_len: Option<usize>,
        #[arg(long)]
        out: PathBuf,
    },
    /// Render a strip of frames from a random episode to a PNG.
    Render {
        /// Environment: point-mass | reacher | fetch (or the one --env-config configures).
        #[arg(long, required_unless_present = "env_config")]
        env: Option<String>,
        /// A TOML file configuring a variant of the environment, as for `procl collect`.
        #[arg(long)]
        env_config: Option<PathBuf>,
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

/// Progress of a long command: indicatif's bar on a terminal; otherwise (a log file, CI, a
/// cluster job) a plain line on stderr every 30 s, with the step, the ETA and the latest
/// message.
struct Progress {
    bar: ProgressBar,
    lines: Option<std::cell::RefCell<(ThrottledLine, String)>>,
    what: String,
}

fn progress_bar(len: u64, what: &str) -> Progress {
    use std::io::IsTerminal;
    let bar = ProgressBar::new(len);
    bar.set_style(
        ProgressStyle::with_template(
            "{prefix} [{bar:30}] {pos}/{len} ({per_sec}, eta {eta}) {msg}",
        )
        .unwrap_or_else(|_| ProgressStyle::default_bar()),
    );
    bar.set_prefix(what.to_string());
    let lines = (!std::io::stderr().is_terminal()).then(|| {
        let every = std::time::Duration::from_secs(30);
        std::cell::RefCell::new((ThrottledLine::first_after(every), String::new()))
    });
    Progress {
        bar,
        lines,
        what: what.trim().to_string(),
    }
}

impl Progress {
    fn set_length(&self, len: u64) {
        self.bar.set_length(len);
    }

    fn set_message(&self, message: String) {
        if let Some(lines) = &self.lines {
            lines.borrow_mut().1 = message.clone();
        }
        self.bar.set_message(message);
    }

    fn set_position(&self, position: u64) {
        self.bar.set_position(position);
        if let Some(lines) = &self.lines {
            let (throttle, message) = &mut *lines.borrow_mut();
            let len = self.bar.length().unwrap_or(0);
            if let Some(eta) = throttle.due(position, len) {
                eprintln!("{}: {position}/{len}, eta {eta} {message}", self.what);
            }
        }
    }

    fn finish_and_clear(&self) {
        self.bar.finish_and_clear();
    }
}

/// The environment configuration of `--env` and `--env-config` (which must agree when both are
/// given): the file's variant, or the named environment's defaults.
fn resolve_env_config(env: Option<&str>, file: Option<&Path>) -> anyhow::Result<EnvConfig> {
    let named: Option<EnvKind> = env.map(str::parse).transpose()?;
    let Some(file) = file else {
        let kind = named.context("--env or --env-config is required")?;
        return Ok(kind.into());
    };
    let config = EnvConfig::load(file)?;
    if let Some(kind) = named
        && kind != config.kind()
    {
        anyhow::bail!(
            "{} configures {}, not --env {kind}",
            file.display(),
            config.kind()
        );
    }
    Ok(config)
}

/// A share as a percentage with two decimals, `-` when undefined.
/// The readout check in words: the turn from the action axes and the estimate's spread.
fn describe_readout(r: &procl::eval::ReadoutCheck) -> String {
    let turn = match r.turn_deg {
        Some(turn) => format!("turned {turn:.1} deg from the action axes"),
        None => "a mirror image of the action axes".into(),
    };
    let spread = r.spread_deg.map_or("-".into(), |x| format!("{x:.1} deg"));
    format!(
        "{turn} by its {}-step response to the action ({} samples; refits on resampled episodes within {spread})",
        r.horizon, r.samples
    )
}

fn percent(share: Option<f64>) -> String {
    share.map_or("-".into(), |x| format!("{:.2}%", 100.0 * x))
}

fn run(cli: Cli) -> anyhow::Result<()> {
    match cli.command {
        Command::Collect {
            env,
            env_config,
            as_custom,
            transitions,
            episode_len,
            seed,
            out,
            force,
        } => {
            let env_config = resolve_env_config(env.as_deref(), env_config.as_deref())?;
            let env = env_config.kind();
            procl::check_writable(&out, force)?;
            let defaults = CollectConfig::new(env, seed);
            let config = CollectConfig {
                env: env_config,
                as_custom,
                transitions: transitions.unwrap_or(defaults.transitions),
                episode_len: episode_len.unwrap_or(defaults.episode_len),
                ..defaults
            };
            let bar = progress_bar(config.transitions as u64, "collect");
            let data = collect(&config, |done| bar.set_position(done as u64))?;
            bar.finish_and_clear();
            data.save(&out, force)?;
            let variant = match (config.env.is_default(), as_custom) {
                (true, false) => "",
                (false, false) => " (a variant)",
                (true, true) => ", recorded as custom data",
                (false, true) => " (a variant), recorded as custom data",
            };
            println!(
                "wrote {} ({} episodes x {} steps of {env}{variant}, seed {seed})",
                out.display(),
                data.episodes(),
                data.steps()
            );
        }
        Command::Config {
            env,
            method,
            preset,
        } => {
            let env: EnvKind = env.parse()?;
            let mut table = toml::Table::new();
            table.insert("preset".into(), toml::Value::String(preset));
            let config = procl::train::config_from_table(table, env, Some(method.parse()?))?;
            print!("{}", toml::to_string(&config)?);
        }
        Command::Info { data } => {
            let dataset = procl::data::Dataset::load(&data)?;
            let m = &dataset.meta;
            println!(
                "{}: {} ({}), {} episodes x {} steps = {} transitions, dt {} s, seed {}, du {}, {}",
                data.display(),
                m.source_name(),
                m.source,
                dataset.episodes(),
                dataset.steps(),
                dataset.transitions(),
                m.control_dt_s,
                m.seed,
                dataset.action_dim(),
                dataset
                    .config_dim()
                    .map_or("no true states".into(), |dq| format!("dq {dq}"))
            );
            if let Some(config) = &m.env_config {
                println!(
                    "simulator: {} as configured here (evaluation runs in it):\n{}",
                    config.kind(),
                    toml::to_string(config)?.trim_end()
                );
            }
            let spread = procl::data::PixelSpread::of_frames(dataset.every_frame());
            if let Some(hub) = spread.hub_candidate() {
                let [col, row] = hub.pixels();
                println!(
                    "{} pixel (column {col:.2}, row {row:.2}; (32, 32) is the centre): radial R^2 {:.3} (a hub from {}), core spread {:.3} of the peak (a hub up to {})",
                    if hub.is_accepted() {
                        "frames turn about a hub at"
                    } else {
                        "frames turn about no hub; the likeliest centre is"
                    },
                    hub.radial_r2,
                    procl::data::HUB_MIN_RADIAL_R2,
                    hub.core_share,
                    procl::data::HUB_MAX_CORE_SHARE
                );
                if hub.is_accepted() {
                    println!(
                        "polar keypoints' cut, where the frames change least about the hub: \
                         {:.1} degrees (0 along the columns, 90 down the rows)",
                        spread.quietest_angle_deg(hub.centre)
                    );
                }
            }
        }
        Command::Train {
            data,
            method,
            out,
            config,
            preset_env,
            seed,
            steps,
            resume,
            device,
        } => {
            let dataset = procl::data::Dataset::load(&data)?;
            let recipe = preset_env
                .map(|e| e.parse::<procl::train::Recipe>())
                .transpose()?;
            let base = procl::train::ConfigBase::for_dataset(&dataset, recipe)?;
            if let Some(line) = base.describe() {
                println!("{line}");
            }
            let method = method.map(|m| m.parse::<Method>()).transpose()?;
            let mut table = match &config {
                Some(path) => procl::train::read_config_table(path)?,
                None => toml::Table::new(),
            };
            if let Some(seed) = seed {
                table.insert("seed".into(), toml::Value::Integer(seed as i64));
            }
            if let Some(steps) = steps {
                table.insert("steps".into(), toml::Value::Integer(steps as i64));
            }
            let config =
                procl::train::config_from_table(table, base, method).with_context(|| {
                    format!(
                        "configuration{}",
                        config
                            .map(|p| format!(" {}", p.display()))
                            .unwrap_or_default()
                    )
                })?;
            let device = procl::model::device_by_name(&device)?;
            let run = RunPaths::new(&out);
            let bar = progress_bar(config.steps, "train");
            let summary =
                procl::train::train(&config, &dataset, &run, resume, &device, |step, v| {
                    if step % 10 == 1 {
                        bar.set_message(v.to_string());
                    }
                    bar.set_position(step);
                })?;
            bar.finish_and_clear();
            println!(
                "trained {} steps in {:.0} s -> {}",
                summary.steps_done,
                summary.seconds,
                out.display()
            );
            if let Some(v) = summary.last {
                println!("final losses: {v}");
            }
            let Some(d) = procl::eval::write_diagnostics(&run)? else {
                println!(
                    "latent diagnostics skipped: they sweep the true states of a procl environment, and this run's data is custom"
                );
                return Ok(());
            };
            println!(
                "latent: linear R^2 of q from h = {:.3}, 5-NN R^2 = {:.3}, folded pairs {:.3}%, pairs PD pushes away {}, locally unstable {}, near-singular {}, det(q -> h map) = {} (latent_map.png, diagnostics.json)",
                d.linear_r2,
                d.knn_r2,
                100.0 * d.folded_share,
                percent(d.pushes_away_share),
                percent(d.locally_unstable_share),
                percent(d.near_singular_share),
                d.config_to_latent_det
                    .map_or("-".into(), |x| format!("{x:.3}"))
            );
            if let Some(r) = &d.readout {
                println!("readout: {}", describe_readout(r));
            }
        }
        Command::Eval {
            run,
            episodes,
            seed,
            horizon,
            controller,
            mpc_horizon,
        } => {
            let paths = RunPaths::new(&run);
            let config = paths.load_config()?;
            let own = if config.method == Method::Nvae {
                "pid"
            } else {
                "pd"
            };
            let controller = match controller.as_deref().unwrap_or(own) {
                name if name == own => procl::eval::Controller::Feedback,
                "mpc" => procl::eval::Controller::Mpc(procl::baselines::mpc::MpcConfig {
                    horizon: mpc_horizon,
                    ..Default::default()
                }),
                "ilqr" => procl::eval::Controller::Ilqr(procl::baselines::ilqr::IlqrConfig {
                    horizon: mpc_horizon,
                    ..Default::default()
                }),
                "p" => procl::eval::Controller::Proportional,
                other => anyhow::bail!(
                    "invalid value for `--controller`: `{other}` ({} runs: {own}{}, or leave it out)",
                    config.method.label(),
                    if own == "pd" {
                        ", mpc or ilqr"
                    } else {
                        " or p"
                    }
                ),
            };
            let mut protocol = ReachConfig::for_env(paths.simulator(&config)?.kind(), seed);
            if episodes == 0 {
                anyhow::bail!("--episodes must be at least 1");
            }
            protocol.episodes = episodes;
            if let Some(h) = horizon {
                protocol.horizon = h;
            }
            let bar = progress_bar(episodes as u64, "eval");
            let report = procl::eval::evaluate_run_with(&paths, &protocol, &controller, |k| {
                bar.set_position(k as u64)
            })?;
            bar.finish_and_clear();
            print_report(&report);
            let out = procl::eval::EvalOutputs::for_controller(&paths, &controller);
            let names: Vec<String> = [&out.json, &out.reach_png, &out.latent_png, &out.gif]
                .iter()
                .filter_map(|p| p.file_name().map(|n| n.to_string_lossy().into_owned()))
                .collect();
            println!("wrote {} in {}", names.join(", "), run.display());
        }
        Command::Demonstrate {
            env,
            env_config,
            shape,
            episodes,
            steps,
            seed,
            out,
            force,
        } => {
            let env_config = resolve_env_config(env.as_deref(), env_config.as_deref())?;
            let env = env_config.kind();
            let shape: procl::control::PathShape = shape.parse()?;
            procl::check_writable(&out, force)?;
            let config = procl::control::ReferenceConfig {
                env: env_config,
                episodes,
                steps,
                ..procl::control::ReferenceConfig::new(env, shape, seed)
            };
            let data = procl::control::generate_reference(&config, |_| {})?;
            data.save(&out, force)?;
            println!(
                "wrote {} ({episodes} {} demonstrations x {steps} steps of {env}, seed {seed})",
                out.display(),
                shape.name()
            );
        }
        Command::Track { run, demo } => {
            let paths = RunPaths::new(&run);
            let bar = progress_bar(0, "track");
            let report = procl::eval::track_run(&paths, &demo, |done, total| {
                bar.set_length(total as u64);
                bar.set_position(done as u64);
            })?;
            bar.finish_and_clear();
            println!(
                "{}: {} demonstrations ({}) x {} steps; error = distance to the reference ({})",
                report.env,
                report.demonstrations,
                report.source,
                report.steps,
                report.distance_unit
            );
            println!(
                "{:<26} {:>12} {:>12} {:>12} {:>18}",
                "method", "mean error", "rms error", "final error", "control p50/p99 us"
            );
            for m in &report.methods {
                let s = &m.per_step;
                println!(
                    "{:<26} {:>12.4} {:>12.4} {:>12.4} {:>18}",
                    s.method,
                    m.mean_error,
                    m.rms_error,
                    s.final_mean,
                    match (s.control_time_us_p50, s.control_time_us_p99) {
                        (Some(a), Some(b)) => format!("{a:.0}/{b:.0}"),
                        _ => "-".into(),
                    }
                );
            }
            println!("wrote track.json, track.png in {}", run.display());
        }
        Command::Diagnose { run } => {
            let d = procl::eval::write_diagnostics(&RunPaths::new(&run))?;
            println!("{}", serde_json::to_string_pretty(&d)?);
        }
        Command::Demo { out, quick, steps } => {
            let mut config = if quick {
                DemoConfig::quick(&out)
            } else {
                DemoConfig::full(&out)
            };
            if let Some(steps) = steps {
                config.train_steps = steps;
            }
            let clock = std::time::Instant::now();
            let result = procl::runner::demo::run_demo(&config, |line| {
                println!("[{:>5.0} s] {line}", clock.elapsed().as_secs_f64())
            })?;
            println!();
            println!(
                "{:<26} {:>8} {:>22} {:>18}",
                "method", "success", "final distance (m)", "control p50 us"
            );
            for row in &result.rows {
                let s = &row.summary;
                println!(
                    "{:<26} {:>7.0}% {:>11.4} +- {:<8.4} {:>18}",
                    s.method,
                    100.0 * s.success_rate,
                    s.final_mean,
                    s.final_std,
                    s.control_time_us_p50
                        .map_or("-".into(), |t| format!("{t:.0}"))
                );
            }
            println!(
                "\nreport: {} ({:.0} s in all)",
                result.report_html.display(),
                clock.elapsed().as_secs_f64()
            );
        }
        Command::Experiment {
            name: _,
            quick,
            out,
            report_only,
            readme,
        } => {
            if quick && readme.is_some() {
                anyhow::bail!("--readme is for the full experiment's results, not --quick's");
            }
            let config = if quick {
                ExperimentConfig::quick(&out)
            } else {
                ExperimentConfig::paper(&out)
            };
            let mut bar: Option<Progress> = None;
            let summary =
                procl::runner::experiment::run_experiment(&config, report_only, &mut |event| {
                    match event {
                        Event::Start(k, total, name) => println!("[{k}/{total}] {name}"),
                        Event::Progress(done, of) => {
                            let bar = bar.get_or_insert_with(|| progress_bar(of, "   "));
                            bar.set_position(done);
                        }
                        Event::Finish(_, outcome, seconds) => {
                            if let Some(bar) = bar.take() {
                                bar.finish_and_clear();
                            }
                            let seconds = seconds.map_or("-".into(), |s| format!("{s:.0} s"));
                            match outcome {
                                Outcome::Ran => println!("      done in {seconds}"),
                                Outcome::Reused => {
                                    println!("      reused (took {seconds} when it ran)")
                                }
                            }
                        }
                    }
                })?;
            println!();
            print!("{}", procl::runner::experiment::markdown_table(&summary));
            if let Some(readme) = readme {
                procl::runner::experiment::update_readme(
                    &readme,
                    Path::new("docs/img/experiment"),
                    &config,
                    &summary,
                )?;
                println!("rewrote the results section of {}", readme.display());
            }
            println!(
                "\nreport: {} (stages took {:.0} s in all)",
                out.join("report.html").display(),
                summary.total_seconds
            );
        }
        Command::Ablate {
            env,
            env_config,
            as_custom,
            grid,
            cell,
            report_only,
            task_index,
            list_tasks,
            seeds,
            seed_start,
            episodes,
            task_sets,
            horizon,
            transitions,
            episode_len,
            out,
        } => {
            let env_config = resolve_env_config(env.as_deref(), env_config.as_deref())?;
            let env = env_config.kind();
            let mut grid = procl::runner::ablate::Grid::from_toml(&grid)?;
            if let Some(name) = cell {
                grid.cells.retain(|(n, _)| n == &name);
                if grid.cells.is_empty() {
                    anyhow::bail!("the grid has no cell named `{name}`");
                }
            }
            if seeds == 0 || episodes == 0 || task_sets == 0 {
                anyhow::bail!("--seeds, --episodes and --task-sets must be at least 1");
            }
            if list_tasks {
                // Custom data's recipe comes from its frames, which are not collected yet; any
                // recipe checks the cells' fields, and a custom base checks their `env` key as
                // the run will.
                let base = if as_custom {
                    let sim = env_config.make();
                    procl::train::ConfigBase::Custom {
                        action_dim: sim.action_dim(),
                        control_dt_s: sim.control_dt_s(),
                        recipe: procl::train::Recipe::Generic,
                        hub: None,
                    }
                } else {
                    env.into()
                };
                grid.cell_configs(base)?;
                let tasks = grid.tasks(seed_start..seed_start + seeds);
                for (index, (name, seed)) in tasks.iter().enumerate() {
                    println!("{index}\t{name}\tseed {seed}");
                }
                println!(
                    "{} tasks (--task-index 0 to {})",
                    tasks.len(),
                    tasks.len() - 1
                );
                return Ok(());
            }
            let work = match (task_index, report_only) {
                (Some(index), _) => GridWork::Task(index),
                (None, true) => GridWork::ReportOnly,
                (None, false) => GridWork::TrainMissing,
            };
            let defaults = CollectConfig::new(env, 0);
            let transitions = transitions.unwrap_or(defaults.transitions);
            let collect_config = CollectConfig {
                env: env_config,
                as_custom,
                transitions,
                episode_len: episode_len.unwrap_or(defaults.episode_len).min(transitions),
                ..defaults
            };
            // Sizes are checked before the output folder is made.
            collect_config.episodes()?;
            std::fs::create_dir_all(&out).with_context(|| format!("creating {}", out.display()))?;
            let data_path = out.join(format!("{env}.npz"));
            let (data, _) =
                procl::runner::stages::collect_or_reuse(&collect_config, &data_path, |_| {})?;
            let protocol = procl::runner::stages::reach_protocol(env, episodes, horizon);
            let task_sets: Vec<_> = (0..task_sets)
                .map(|set| procl::eval::ReachConfig {
                    seed: protocol.seed + 1000 * set,
                    ..protocol.clone()
                })
                .collect();
            let mut line = ThrottledLine::first_after(std::time::Duration::from_secs(30));
            let results = procl::runner::ablate::run_grid(
                &grid,
                &data,
                seed_start..seed_start + seeds,
                &task_sets,
                &out,
                work,
                |r| {
                    println!(
                        "{} seed {}: success {:.1}%{}, final {:.4}, R^2 {:.3}, det {}, {:.0} s",
                        r.cell,
                        r.seed,
                        100.0 * r.success_rate,
                        match r.success_per_task_set.as_slice() {
                            [_, _, ..] => format!(
                                " (task sets: {})",
                                r.success_per_task_set
                                    .iter()
                                    .map(|s| format!("{:.1}%", 100.0 * s))
                                    .collect::<Vec<_>>()
                                    .join(", ")
                            ),
                            _ => String::new(),
                        },
                        r.final_mean,
                        r.linear_r2,
                        r.det.map_or("-".into(), |d| format!("{d:.2}")),
                        r.train_seconds
                    )
                },
                |cell, seed, step, steps, values| {
                    // One plain line every 30 s, on a terminal or not: a cell trains for minutes.
                    if step == 1 {
                        line = ThrottledLine::first_after(std::time::Duration::from_secs(30));
                    }
                    if let Some(eta) = line.due(step, steps) {
                        eprintln!("{cell} seed {seed}: step {step}/{steps}, eta {eta}, {values}");
                    }
                },
            )?;
            match work {
                GridWork::Task(index) => println!(
                    "task {index} done; {} of {} results in {}",
                    results.len(),
                    grid.tasks(seed_start..seed_start + seeds).len(),
                    out.display()
                ),
                _ => println!(
                    "{} results; wrote {}",
                    results.len(),
                    out.join("ablation.md").display()
                ),
            }
        }
        Command::Render {
            env,
            env_config,
            seed,
            frames,
            scale,
            out,
            force,
        } => {
            let env_config = resolve_env_config(env.as_deref(), env_config.as_deref())?;
            let env = env_config.kind();
            procl::check_writable(&out, force)?;
            let image = procl::data::render_strip(&env_config, seed, frames, scale)
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

/// Prints the results table of an evaluation.
fn print_report(report: &procl::eval::ReachReport) {
    let p = &report.protocol;
    println!(
        "{}: {} episodes, {} steps, success = final distance < {} {}",
        report.env, p.episodes, p.horizon, p.success_threshold, p.distance_unit
    );
    println!(
        "{:<26} {:>8} {:>22} {:>18} {:>10} {:>9}",
        "method", "success", "final distance", "control p50/p99 us", "reversals", "late std"
    );
    for m in &report.methods {
        let time = match (m.control_time_us_p50, m.control_time_us_p99) {
            (Some(a), Some(b)) => format!("{a:.0} / {b:.0}"),
            _ => "-".into(),
        };
        println!(
            "{:<26} {:>7.1}% {:>11.4} +- {:<8.4} {:>18} {:>10.2} {:>9.4}",
            m.method,
            100.0 * m.success_rate,
            m.final_mean,
            m.final_std,
            time,
            m.reversals_mean,
            m.late_distance_std_mean
        );
    }
    for m in &report.methods {
        if let (Some(mean), Some(std)) = (m.final_fingertip_mean_m, m.final_fingertip_std_m) {
            println!(
                "{:<26} final fingertip distance {mean:.4} +- {std:.4} m",
                m.method
            );
        }
    }
}

fn main() -> ExitCode {
    // Before any tensor exists: training spends about half its wall time in page faults
    // otherwise (src/allocator.rs).
    procl::allocator::retain_freed_memory();
    match run(Cli::parse()) {
        Ok(()) => ExitCode::SUCCESS,
        Err(error) => {
            eprintln!("error: {}", format!("{error:#}").replace('\n', " "));
            ExitCode::FAILURE
        }
    }
}
