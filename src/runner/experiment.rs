//! `procl experiment paper` : the paper's experiments on Point mass-2D, Reacher-2D and
//! Fetch-3D in one resumable command. Datasets, training, goal-reaching evaluation of every
//! method, the latent-noise ablation and Fetch tracking are stages whose finished outputs are
//! reused on a rerun; `report.html` and `summary.json` are rebuilt from what is on disk.

use std::path::{Path, PathBuf};
use std::time::Instant;

use crate::baselines::ilqr::IlqrConfig;
use crate::baselines::mpc::MpcConfig;
use crate::control::{PathShape, ReferenceConfig, generate_reference};
use crate::data::{CollectConfig, Dataset};
use crate::envs::EnvKind;
use crate::error::{Error, Result};
use crate::eval::{
    Controller, EvalOutputs, LATENT_MAP, LatentDiagnostics, MethodSummary, ReachConfig,
    TRACK_FIGURE, TrackReport, save_learning_plot, save_reach_plot, track_run, write_diagnostics,
};
use crate::runner::stages::{
    Outcome, collect_or_reuse, evaluate_or_reuse, evaluate_or_reuse_with, is_complete,
    reach_protocol, read_current, read_eval, read_eval_with, set_budget, shrink_networks,
    train_or_reuse, training_clock, training_seconds,
};
use crate::train::{Method, Preset, RunPaths, TrainConfig};

/// One environment's budget.
#[derive(Debug, Clone, PartialEq)]
pub struct EnvBudget {
    pub env: EnvKind,
    pub transitions: usize,
    pub episode_len: usize,
    /// Training steps of every method on this environment (`None`: each method's own preset
    /// budget).
    pub train_steps: Option<u64>,
    /// Steps between the weights kept for the learning curves and the equal-budget comparison.
    pub snapshot_every: u64,
}

/// What `procl experiment paper` runs.
#[derive(Debug, Clone, PartialEq)]
pub struct ExperimentConfig {
    pub out: PathBuf,
    /// Seed of the datasets and of every training run.
    pub seed: u64,
    pub envs: Vec<EnvBudget>,
    pub methods: Vec<Method>,
    /// Batch size of every run (`None`: each method's preset).
    pub batch_size: Option<usize>,
    pub eval_episodes: usize,
    /// Episode length of the evaluation (`None`: the protocol's).
    pub eval_horizon: Option<usize>,
    /// Latent noise std `eps` of the ProCL ablation on point mass (the preset's own value
    /// reuses the main ProCL run).
    pub ablation_noise: Vec<f64>,
    /// Tracking on Fetch-3D: path shape, demonstrations and steps of each.
    pub track_shape: PathShape,
    pub track_demos: usize,
    pub track_steps: usize,
    /// Model-predictive controllers also evaluated on the ProCL and PC3 latents (through
    /// their learned dynamics `g`): what PD gives up in success and saves in time.
    pub planners: Vec<Controller>,
    /// Shrinks every network (the `--quick` smoke run).
    pub tiny_model: bool,
}

impl ExperimentConfig {
    /// The full experiment: the paper's dataset sizes, every method trained to its own
    /// convergence (its preset), 50 evaluation episodes, eps in {0.001, 0.01, 0.1}.
    pub fn paper(out: impl Into<PathBuf>) -> Self {
        let budget = |env, snapshot_every| {
            let defaults = CollectConfig::new(env, 0);
            EnvBudget {
                env,
                transitions: defaults.transitions,
                episode_len: defaults.episode_len,
                train_steps: None,
                snapshot_every,
            }
        };
        Self {
            out: out.into(),
            seed: 0,
            // About a dozen snapshots of a ProCL run, so that the equal-budget comparison
            // finds every method's weights within a few seconds of ProCL's training time.
            envs: vec![
                budget(EnvKind::PointMass, 50),
                budget(EnvKind::Reacher, 100),
                budget(EnvKind::Fetch, 50),
            ],
            methods: vec![Method::Procl, Method::Pc3, Method::Nvae],
            batch_size: None,
            eval_episodes: 50,
            eval_horizon: None,
            ablation_noise: vec![0.001, 0.01, 0.1],
            track_shape: PathShape::FigureEight,
            track_demos: 4,
            track_steps: 500,
            planners: vec![
                Controller::Mpc(MpcConfig::default()),
                Controller::Ilqr(IlqrConfig::default()),
            ],
            tiny_model: false,
        }
    }

    /// Every stage on a tiny budget (about a minute on 2 cores), for CI.
    pub fn quick(out: impl Into<PathBuf>) -> Self {
        let mut config = Self::paper(out);
        for budget in &mut config.envs {
            (budget.transitions, budget.episode_len) = (200, 25);
            (budget.train_steps, budget.snapshot_every) = (Some(6), 2);
        }
        config.batch_size = Some(16);
        config.eval_episodes = 2;
        config.eval_horizon = Some(40);
        config.track_demos = 1;
        config.track_steps = 40;
        config.tiny_model = true;
        config
    }

    /// The training configuration of `method` on `budget`'s environment.
    pub fn train_config(&self, budget: &EnvBudget, method: Method) -> TrainConfig {
        let mut config = TrainConfig::preset(Preset::Procl, method, budget.env);
        config.seed = self.seed;
        let steps = budget.train_steps.unwrap_or(config.steps);
        set_budget(&mut config, steps, self.batch_size);
        config.snapshot_every = budget.snapshot_every;
        if self.tiny_model {
            shrink_networks(&mut config);
        }
        config
    }

    fn protocol(&self, env: EnvKind) -> ReachConfig {
        reach_protocol(env, self.eval_episodes, self.eval_horizon)
    }

    fn env_dir(&self, env: EnvKind) -> PathBuf {
        self.out.join(env.name())
    }

    fn run(&self, env: EnvKind, method: Method) -> RunPaths {
        RunPaths::new(self.env_dir(env).join(method.dir_name()))
    }

    /// The ablation's run for `eps` (the main ProCL run where `eps` is the preset's).
    fn ablation_run(&self, eps: f64) -> (RunPaths, bool) {
        let main = self.train_config(&self.envs[0], Method::Procl);
        if main.loss.latent_noise_std == eps {
            (self.run(EnvKind::PointMass, Method::Procl), true)
        } else {
            let dir = self.env_dir(EnvKind::PointMass).join("ablation");
            (RunPaths::new(dir.join(format!("eps={eps}"))), false)
        }
    }

    /// The ProCL configuration of the ablation's cell `eps` on point mass (without snapshots:
    /// the ablation has no learning curves).
    fn ablation_config(&self, eps: f64) -> TrainConfig {
        let mut config = self.train_config(&self.envs[0], Method::Procl);
        config.loss.latent_noise_std = eps;
        config.snapshot_every = 0;
        config
    }

    /// The planners evaluated on `method`'s runs (those with a learned dynamics `g`).
    fn planners_of(&self, method: Method) -> &[Controller] {
        match method {
            Method::Procl | Method::Pc3 => &self.planners,
            Method::Nvae => &[],
        }
    }

    /// The training budget of the equal-budget comparison on `env`: the wall-clock seconds
    /// ProCL's run took over its whole training budget (`None` before it has finished, or
    /// without ProCL among the methods).
    fn equal_budget_seconds(&self, env: EnvKind) -> Option<f64> {
        let budget = self.envs.iter().find(|b| b.env == env)?;
        if !self.methods.contains(&Method::Procl) {
            return None;
        }
        let run = self.run(env, Method::Procl);
        let steps = self.train_config(budget, Method::Procl).steps;
        is_complete(&run, steps).then(|| training_seconds(&run))?
    }

    fn has_fetch(&self) -> bool {
        self.envs.iter().any(|b| b.env == EnvKind::Fetch)
    }

    fn demo_path(&self) -> PathBuf {
        self.env_dir(EnvKind::Fetch)
            .join(format!("demo-{}.npz", self.track_shape.name()))
    }

    /// Checks the plan before hours are spent on it.
    pub fn validate(&self) -> Result<()> {
        if self.envs.first().map(|b| b.env) != Some(EnvKind::PointMass) {
            return Err(Error::config(
                "experiment",
                "the first environment must be point-mass (the ablation's)",
            ));
        }
        if self.eval_episodes == 0 {
            return Err(Error::config("episodes", "must be at least 1"));
        }
        for budget in &self.envs {
            for method in &self.methods {
                self.train_config(budget, *method).validate()?;
            }
        }
        for (k, eps) in self.ablation_noise.iter().enumerate() {
            if !(eps.is_finite() && *eps >= 0.0) || self.ablation_noise[..k].contains(eps) {
                return Err(Error::config(
                    "ablation_noise",
                    format!("{eps} is not a new noise std >= 0"),
                ));
            }
        }
        Ok(())
    }
}

/// What the experiment reports on its way.
pub enum Event<'a> {
    /// A stage starts: its number (from 1), the number of stages, its name.
    Start(usize, usize, &'a str),
    /// Progress inside the running stage: (done, of).
    Progress(u64, u64),
    /// The stage finished now, or was found finished; its seconds (when first run).
    Finish(&'a str, Outcome, Option<f64>),
}

/// Seconds each stage took when it last ran, in the order stages first ran, kept in
/// `stages.json` so that a resumed experiment still reports how long its reused stages took.
#[derive(Debug, Clone, Default, serde::Serialize, serde::Deserialize)]
pub(crate) struct StageTimes(Vec<(String, f64)>);

/// The stage log at `path` (empty when there is none yet).
pub(crate) fn read_stage_times(path: &Path) -> Result<StageTimes> {
    match std::fs::read_to_string(path) {
        Ok(text) => serde_json::from_str(&text).map_err(|e| {
            Error::config(
                path.display().to_string(),
                format!("not procl's stage log ({e}); move it away"),
            )
        }),
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => Ok(StageTimes::default()),
        Err(e) => Err(Error::io(path, e)),
    }
}

impl StageTimes {
    fn get(&self, name: &str) -> Option<f64> {
        self.0.iter().find(|(n, _)| n == name).map(|(_, s)| *s)
    }

    fn set(&mut self, name: &str, seconds: f64) {
        match self.0.iter_mut().find(|(n, _)| n == name) {
            Some(entry) => entry.1 = seconds,
            None => self.0.push((name.to_string(), seconds)),
        }
    }
}

struct Stages<'a> {
    path: PathBuf,
    times: StageTimes,
    started: usize,
    total: usize,
    log: &'a mut dyn FnMut(Event),
}

impl Stages<'_> {
    /// Runs stage `name`: `work` gets a progress callback and says whether it ran or reused.
    fn run<T>(
        &mut self,
        name: &str,
        work: impl FnOnce(&mut dyn FnMut(u64, u64)) -> Result<(T, Outcome)>,
    ) -> Result<T> {
        self.started += 1;
        (self.log)(Event::Start(self.started, self.total, name));
        let start = Instant::now();
        let log = &mut self.log;
        let (value, outcome) = work(&mut |done, of| log(Event::Progress(done, of)))?;
        if outcome == Outcome::Ran {
            self.times.set(name, start.elapsed().as_secs_f64());
            crate::fsutil::write_json(&self.path, &self.times)?;
        }
        (self.log)(Event::Finish(name, outcome, self.times.get(name)));
        Ok(value)
    }
}

/// Runs (or resumes) every stage, then writes the report. With `report_only` nothing is run:
/// the report covers whatever finished stages are on disk.
pub fn run_experiment(
    config: &ExperimentConfig,
    report_only: bool,
    log: &mut dyn FnMut(Event),
) -> Result<Summary> {
    config.validate()?;
    std::fs::create_dir_all(&config.out).map_err(|e| Error::io(&config.out, e))?;
    // Running stages writes the folder; rebuilding the report from it only reads what is there.
    let _writer = (!report_only)
        .then(|| crate::fsutil::FolderLock::acquire(&config.out))
        .transpose()?;
    let stages_path = config.out.join("stages.json");
    let times = read_stage_times(&stages_path)?;
    let mut stages = Stages {
        path: stages_path,
        times,
        started: 0,
        total: count_stages(config),
        log,
    };
    if !report_only {
        run_stages(config, &mut stages)?;
    }
    let summary = summarise(config, &stages.times);
    write_outputs(config, &summary)?;
    Ok(summary)
}

/// How many stages [`run_stages`] runs for `config`.
fn count_stages(config: &ExperimentConfig) -> usize {
    let ablation_runs = config
        .ablation_noise
        .iter()
        .filter(|eps| !config.ablation_run(**eps).1)
        .count();
    let tracking = if config.has_fetch() { 2 } else { 0 };
    let planned: usize = config
        .methods
        .iter()
        .map(|m| config.planners_of(*m).len())
        .sum();
    config.envs.len() * (1 + 3 * config.methods.len() + planned) + 2 * ablation_runs + tracking
}

fn run_stages(config: &ExperimentConfig, stages: &mut Stages) -> Result<()> {
    for budget in &config.envs {
        let env = budget.env;
        let dir = config.env_dir(env);
        std::fs::create_dir_all(&dir).map_err(|e| Error::io(&dir, e))?;
        let data_path = dir.join("data.npz");
        let collect_config = CollectConfig {
            transitions: budget.transitions,
            episode_len: budget.episode_len,
            ..CollectConfig::new(env, config.seed)
        };
        let episodes = collect_config.episodes()? as u64;
        let data = stages.run(&format!("{env}/collect"), |progress| {
            collect_or_reuse(&collect_config, &data_path, |done| {
                progress(done as u64, episodes)
            })
        })?;
        for method in &config.methods {
            let train_config = config.train_config(budget, *method);
            let run = config.run(env, *method);
            let name = format!("{env}/{}", method.dir_name());
            let protocol = config.protocol(env);
            train_and_evaluate(stages, &name, &train_config, &data, &run, &protocol)?;
            let budget_seconds = config.equal_budget_seconds(env);
            stages.run(&format!("{name}/curve"), |progress| {
                let within = budget_seconds.and_then(|b| within_budget(&run, b));
                let steps = curve_snapshots(&run, within);
                let mut outcome = Outcome::Reused;
                for (k, step) in steps.iter().enumerate() {
                    let (_, ran) = evaluate_or_reuse(&run.snapshot(*step), &protocol, |_| {})?;
                    if ran == Outcome::Ran {
                        outcome = Outcome::Ran;
                    }
                    progress(k as u64 + 1, steps.len() as u64);
                }
                Ok(((), outcome))
            })?;
            for planner in config.planners_of(*method) {
                let file = EvalOutputs::for_controller(&run, planner).json;
                let stem = file.file_stem().map(|s| s.to_string_lossy().into_owned());
                stages.run(
                    &format!("{name}/{}", stem.unwrap_or_default()),
                    |progress| {
                        let episodes = protocol.episodes as u64;
                        evaluate_or_reuse_with(&run, &protocol, planner, |done| {
                            progress(done as u64, episodes)
                        })
                    },
                )?;
            }
        }
    }
    let mut data = None;
    for eps in &config.ablation_noise {
        let (run, is_main) = config.ablation_run(*eps);
        if is_main {
            continue;
        }
        let data = match &mut data {
            Some(data) => data,
            None => data.insert(Dataset::load(
                &config.env_dir(EnvKind::PointMass).join("data.npz"),
            )?),
        };
        let train_config = config.ablation_config(*eps);
        train_and_evaluate(
            stages,
            &format!("point-mass/ablation/eps={eps}"),
            &train_config,
            data,
            &run,
            &config.protocol(EnvKind::PointMass),
        )?;
    }
    if config.has_fetch() {
        let demo_path = config.demo_path();
        let reference = ReferenceConfig {
            episodes: config.track_demos,
            steps: config.track_steps,
            ..ReferenceConfig::new(EnvKind::Fetch, config.track_shape, config.seed)
        };
        let source = format!("demonstration:{}", config.track_shape.name());
        stages.run("fetch/demonstrate", |progress| {
            if demo_path.exists() {
                let demos = Dataset::load(&demo_path)?;
                let found = (demos.meta.source.as_str(), demos.episodes(), demos.steps());
                if found != (source.as_str(), reference.episodes, reference.steps) {
                    return Err(Error::dataset(
                        &demo_path,
                        format!(
                            "holds {} x {} steps of {}, tracking needs {} x {} of {source}; move it away",
                            found.1, found.2, found.0, reference.episodes, reference.steps
                        ),
                    ));
                }
                return Ok(((), Outcome::Reused));
            }
            let demos = generate_reference(&reference, |done| {
                progress(done as u64, reference.episodes as u64)
            })?;
            demos.save(&demo_path, false)?;
            Ok(((), Outcome::Ran))
        })?;
        let run = config.run(EnvKind::Fetch, Method::Procl);
        stages.run("fetch/procl/track", |progress| {
            let current = read_track(&run).is_some_and(|t| {
                (t.source.as_str(), t.demonstrations, t.steps)
                    == (source.as_str(), reference.episodes, reference.steps)
            });
            if current {
                return Ok(((), Outcome::Reused));
            }
            track_run(&run, &demo_path, |done, of| {
                progress(done as u64, of as u64)
            })?;
            Ok(((), Outcome::Ran))
        })?;
    }
    Ok(())
}

/// Indices (from 1) of the snapshots a learning curve evaluates out of `count`: 1, 2, 3, 4, 6,
/// 8, 12, 16, ... (the powers of two and 1.5 times them), so the points spread evenly over a
/// log time axis, and the last one.
fn curve_indices(count: usize) -> Vec<usize> {
    let mut indices = vec![];
    let mut power = 1usize;
    while power <= count {
        indices.push(power);
        if power >= 2 && power / 2 * 3 <= count {
            indices.push(power / 2 * 3);
        }
        let Some(next) = power.checked_mul(2) else {
            break;
        };
        power = next;
    }
    if count > 0 && indices.last() != Some(&count) {
        indices.push(count);
    }
    indices
}

/// The weights of `run` the equal-budget comparison evaluates: the latest of its snapshots
/// and its final checkpoint that it had trained within `budget_seconds`, as (step, training
/// seconds at it, whether it is the final checkpoint). `None` when even the first took longer.
fn within_budget(run: &RunPaths, budget_seconds: f64) -> Option<(u64, f64, bool)> {
    let last = crate::read_checkpoint_meta(&run.checkpoint()).ok()?.step;
    let clock = training_clock(run)?;
    let mut steps = run.snapshot_steps();
    steps.retain(|&step| step < last);
    steps.push(last);
    steps
        .into_iter()
        .filter_map(|step| Some((step, seconds_at(&clock, step)?, step == last)))
        // A hair of slack, so ProCL's own run counts as within its own time.
        .rfind(|(_, seconds, _)| *seconds <= budget_seconds * (1.0 + 1e-9))
}

/// The training seconds at `step` on a run's [`training_clock`].
fn seconds_at(clock: &[(u64, f64)], step: u64) -> Option<f64> {
    let k = clock.binary_search_by_key(&step, |(s, _)| *s).ok()?;
    Some(clock[k].1)
}

/// The snapshot steps of `run` its learning curve evaluates: [`curve_indices`] of its
/// snapshots and `within`, the weights [`within_budget`] picked (if a snapshot), without the
/// final checkpoint (the run's own evaluation).
fn curve_snapshots(run: &RunPaths, within: Option<(u64, f64, bool)>) -> Vec<u64> {
    let Ok(meta) = crate::read_checkpoint_meta(&run.checkpoint()) else {
        return vec![];
    };
    let snapshots: Vec<u64> = run
        .snapshot_steps()
        .into_iter()
        .filter(|&step| step < meta.step)
        .collect();
    let mut steps: Vec<u64> = curve_indices(snapshots.len())
        .into_iter()
        .map(|k| snapshots[k - 1])
        .collect();
    if let Some((step, _, false)) = within {
        steps.push(step);
    }
    steps.sort_unstable();
    steps.dedup();
    steps
}

/// The train stage and the eval stage of one run.
fn train_and_evaluate(
    stages: &mut Stages,
    name: &str,
    train_config: &TrainConfig,
    data: &Dataset,
    run: &RunPaths,
    protocol: &ReachConfig,
) -> Result<()> {
    let steps = train_config.steps;
    stages.run(&format!("{name}/train"), |progress| {
        let outcome = train_or_reuse(train_config, data, run, |step, _| progress(step, steps))?;
        if read_diagnostics(run).is_none() {
            write_diagnostics(run)?;
        }
        Ok(((), outcome))
    })?;
    stages.run(&format!("{name}/eval"), |progress| {
        let episodes = protocol.episodes as u64;
        evaluate_or_reuse(run, protocol, |done| progress(done as u64, episodes))
    })?;
    Ok(())
}

fn read_track(run: &RunPaths) -> Option<TrackReport> {
    read_current(run, &run.dir.join("track.json"))
}

fn read_diagnostics(run: &RunPaths) -> Option<LatentDiagnostics> {
    read_current(run, &run.dir.join("diagnostics.json"))
}

/// One method on one environment.
#[derive(Debug, Clone, serde::Serialize)]
pub struct Row {
    pub method: String,
    /// The run folder, relative to the experiment's folder (none for the oracle).
    pub run: Option<PathBuf>,
    pub success_rate: f64,
    pub final_mean: f64,
    pub final_std: f64,
    pub control_time_us_p50: Option<f64>,
    /// The control step's p50 over the feedback law's (PD or PID) on the same run, measured
    /// in the same experiment.
    pub control_time_vs_feedback: Option<f64>,
    pub control_time_us_p99: Option<f64>,
    pub linear_r2: Option<f64>,
    pub knn_r2: Option<f64>,
    /// The share of latent-map pairs whose first PD torque pushes away from the goal
    /// ([`crate::eval::pushes_away_share`]).
    pub pushes_away_share: Option<f64>,
    /// The share of latent-map cells whose local map PD cannot hold a goal with
    /// ([`crate::eval::local_map_shares`]; 2-D configurations only).
    #[serde(default)]
    pub locally_unstable_share: Option<f64>,
    pub train_seconds: Option<f64>,
    /// Training steps the run took (its preset's, or fewer where its stopping rule ended it).
    #[serde(default)]
    pub train_steps: Option<u64>,
    /// Per-step distance to the goal (mean and std over episodes): the main figure's curve.
    #[serde(skip)]
    pub curve: MethodSummary,
}

/// One method's weights at one point of its training, evaluated.
#[derive(Debug, Clone, serde::Serialize)]
pub struct CurvePoint {
    pub step: u64,
    /// Wall-clock training seconds up to `step`.
    pub seconds: f64,
    pub success_rate: f64,
    pub final_mean: f64,
    pub final_std: f64,
}

/// One method's success over its training: its learning curve.
#[derive(Debug, Clone, serde::Serialize)]
pub struct LearningCurve {
    pub method: String,
    pub points: Vec<CurvePoint>,
}

/// One method at the equal training budget: its latest weights trained within it.
#[derive(Debug, Clone, serde::Serialize)]
pub struct BudgetRow {
    pub method: String,
    /// The step of those weights; `None` when even the method's first snapshot took longer.
    pub step: Option<u64>,
    /// Their evaluation; `None` until the run's curve stage has evaluated them.
    pub point: Option<CurvePoint>,
}

/// One environment's results.
#[derive(Debug, Clone, serde::Serialize)]
pub struct EnvResults {
    pub env: EnvKind,
    pub protocol: ReachConfig,
    /// Every method trained on its own terms (its preset's steps; the NewtonianVAE until its
    /// stopping rule ends it), with the planners on its latent.
    pub rows: Vec<Row>,
    /// The equal-budget comparison's wall-clock training seconds (ProCL's own).
    pub equal_budget_seconds: Option<f64>,
    pub equal_budget: Vec<BudgetRow>,
    pub curves: Vec<LearningCurve>,
}

/// One cell of the latent-noise ablation.
#[derive(Debug, Clone, serde::Serialize)]
pub struct AblationRow {
    pub latent_noise_std: f64,
    pub success_rate: f64,
    pub final_mean: f64,
    pub final_std: f64,
    pub linear_r2: Option<f64>,
    /// Per-step distance to the goal, labelled with `eps`: the ablation figure's curve.
    #[serde(skip)]
    pub curve: MethodSummary,
}

/// Everything `summary.json` holds.
#[derive(Debug, Clone, serde::Serialize)]
pub struct Summary {
    pub seed: u64,
    pub envs: Vec<EnvResults>,
    pub ablation: Vec<AblationRow>,
    pub tracking: Option<TrackReport>,
    /// Seconds each stage took when it ran, in stage order.
    pub stage_seconds: Vec<(String, f64)>,
    pub total_seconds: f64,
}

fn summarise(config: &ExperimentConfig, times: &StageTimes) -> Summary {
    let relative = |run: &RunPaths| {
        run.dir
            .strip_prefix(&config.out)
            .ok()
            .map(Path::to_path_buf)
    };
    let mut envs = vec![];
    for budget in &config.envs {
        let env = budget.env;
        let protocol = config.protocol(env);
        let mut rows = vec![];
        let mut oracle = None;
        let budget_seconds = config.equal_budget_seconds(env);
        let (mut curves, mut equal_budget) = (vec![], vec![]);
        for method in &config.methods {
            let run = config.run(env, *method);
            let Some(report) = read_eval(&run).filter(|r| r.protocol == protocol) else {
                continue;
            };
            let mut methods = report.methods.into_iter();
            let Some(latent) = methods.next() else {
                continue;
            };
            oracle = oracle.or(methods.next());
            let diagnostics = read_diagnostics(&run);
            let pd_time = latent.control_time_us_p50;
            let planned: Vec<MethodSummary> = config
                .planners_of(*method)
                .iter()
                .filter_map(|planner| {
                    let report =
                        read_eval_with(&run, planner).filter(|r| r.protocol == protocol)?;
                    report.methods.into_iter().next()
                })
                .collect();
            rows.push(Row {
                method: latent.method.clone(),
                run: relative(&run),
                success_rate: latent.success_rate,
                final_mean: latent.final_mean,
                final_std: latent.final_std,
                control_time_us_p50: latent.control_time_us_p50,
                control_time_vs_feedback: Some(1.0),
                control_time_us_p99: latent.control_time_us_p99,
                linear_r2: diagnostics.as_ref().map(|d| d.linear_r2),
                knn_r2: diagnostics.as_ref().map(|d| d.knn_r2),
                pushes_away_share: diagnostics.as_ref().and_then(|d| d.pushes_away_share),
                locally_unstable_share: diagnostics.as_ref().and_then(|d| d.locally_unstable_share),
                train_seconds: training_seconds(&run),
                train_steps: crate::read_checkpoint_meta(&run.checkpoint())
                    .ok()
                    .map(|m| m.step),
                curve: latent.clone(),
            });
            let (curve, budget_row) = learning_curve(&run, &latent, &protocol, budget_seconds);
            curves.push(curve);
            equal_budget.extend(budget_row);
            for plan in planned {
                rows.push(Row {
                    method: plan.method.clone(),
                    run: relative(&run),
                    success_rate: plan.success_rate,
                    final_mean: plan.final_mean,
                    final_std: plan.final_std,
                    control_time_us_p50: plan.control_time_us_p50,
                    control_time_vs_feedback: plan
                        .control_time_us_p50
                        .zip(pd_time)
                        .map(|(t, pd)| t / pd),
                    control_time_us_p99: plan.control_time_us_p99,
                    linear_r2: None,
                    knn_r2: None,
                    pushes_away_share: None,
                    locally_unstable_share: None,
                    train_seconds: None,
                    train_steps: None,
                    curve: plan,
                });
            }
        }
        if let Some(oracle) = oracle {
            rows.push(Row {
                method: oracle.method.clone(),
                run: None,
                success_rate: oracle.success_rate,
                final_mean: oracle.final_mean,
                final_std: oracle.final_std,
                control_time_us_p50: None,
                control_time_vs_feedback: None,
                control_time_us_p99: None,
                linear_r2: None,
                knn_r2: None,
                pushes_away_share: None,
                locally_unstable_share: None,
                train_seconds: None,
                train_steps: None,
                curve: oracle,
            });
        }
        envs.push(EnvResults {
            env,
            protocol,
            rows,
            equal_budget_seconds: budget_seconds,
            equal_budget,
            curves,
        });
    }
    let protocol = config.protocol(EnvKind::PointMass);
    let ablation = config
        .ablation_noise
        .iter()
        .filter_map(|eps| {
            let (run, _) = config.ablation_run(*eps);
            let report = read_eval(&run).filter(|r| r.protocol == protocol)?;
            let mut curve = report.methods.into_iter().next()?;
            curve.method = format!("ProCL + PD, eps = {eps}");
            Some(AblationRow {
                latent_noise_std: *eps,
                success_rate: curve.success_rate,
                final_mean: curve.final_mean,
                final_std: curve.final_std,
                linear_r2: read_diagnostics(&run).map(|d| d.linear_r2),
                curve,
            })
        })
        .collect();
    let tracking = read_track(&config.run(EnvKind::Fetch, Method::Procl));
    let stage_seconds = times.0.clone();
    let total_seconds = stage_seconds.iter().map(|(_, s)| s).sum();
    Summary {
        seed: config.seed,
        envs,
        ablation,
        tracking,
        stage_seconds,
        total_seconds,
    }
}

/// The learning curve of `run` (its evaluated snapshots, then its final weights, whose
/// evaluation is `last`) and its row of the equal-budget comparison.
fn learning_curve(
    run: &RunPaths,
    last: &MethodSummary,
    protocol: &ReachConfig,
    budget_seconds: Option<f64>,
) -> (LearningCurve, Option<BudgetRow>) {
    let clock = training_clock(run).unwrap_or_default();
    let point = |step: u64, eval: &MethodSummary| {
        Some(CurvePoint {
            step,
            seconds: seconds_at(&clock, step)?,
            success_rate: eval.success_rate,
            final_mean: eval.final_mean,
            final_std: eval.final_std,
        })
    };
    let snapshot_point = |step: u64| {
        let report = read_eval(&run.snapshot(step)).filter(|r| &r.protocol == protocol)?;
        point(step, report.methods.first()?)
    };
    let final_step = crate::read_checkpoint_meta(&run.checkpoint())
        .ok()
        .map(|m| m.step);
    let within = budget_seconds.and_then(|b| within_budget(run, b));
    let mut points: Vec<CurvePoint> = curve_snapshots(run, within)
        .into_iter()
        .filter_map(snapshot_point)
        .collect();
    points.extend(final_step.and_then(|step| point(step, last)));
    let budget_row = budget_seconds.map(|_| BudgetRow {
        method: last.method.clone(),
        step: within.map(|(step, _, _)| step),
        point: within.and_then(|(step, _, is_final)| {
            if is_final {
                point(step, last)
            } else {
                snapshot_point(step)
            }
        }),
    });
    let curve = LearningCurve {
        method: last.method.clone(),
        points,
    };
    (curve, budget_row)
}

/// The main figure of `env` (every method's distance curve), relative to the experiment folder.
fn reach_figure(env: EnvKind) -> String {
    format!("{}/reach_all.png", env.name())
}

/// The learning curves of `env`, relative to the experiment folder.
fn learning_figure(env: EnvKind) -> String {
    format!("{}/learning.png", env.name())
}

const ABLATION_FIGURE: &str = "point-mass/ablation.png";

fn write_outputs(config: &ExperimentConfig, summary: &Summary) -> Result<()> {
    for results in &summary.envs {
        if results.rows.is_empty() {
            continue;
        }
        let curves: Vec<MethodSummary> = results.rows.iter().map(|r| r.curve.clone()).collect();
        save_reach_plot(
            &config.out.join(reach_figure(results.env)),
            &format!(
                "{}: goal reaching from pixels, {} episodes",
                results.env, results.protocol.episodes
            ),
            &curves,
            results.protocol.success_threshold,
            &results.protocol.distance_unit,
        )?;
        if !results.curves.is_empty() {
            let curves: Vec<(String, Vec<(f64, f64)>)> = results
                .curves
                .iter()
                .map(|c| {
                    let points = c.points.iter().map(|p| (p.seconds, p.success_rate));
                    (c.method.clone(), points.collect())
                })
                .collect();
            save_learning_plot(
                &config.out.join(learning_figure(results.env)),
                &format!("{}: goals reached against training time", results.env),
                &curves,
                results.equal_budget_seconds,
            )?;
        }
    }
    let protocol = config.protocol(EnvKind::PointMass);
    let ablation_curves: Vec<MethodSummary> =
        summary.ablation.iter().map(|a| a.curve.clone()).collect();
    if !ablation_curves.is_empty() {
        save_reach_plot(
            &config.out.join(ABLATION_FIGURE),
            "point mass: latent noise eps (ProCL + PD)",
            &ablation_curves,
            protocol.success_threshold,
            &protocol.distance_unit,
        )?;
    }
    crate::fsutil::write_json(&config.out.join("summary.json"), summary)?;
    let html = report_html(config, summary);
    let path = config.out.join("report.html");
    crate::write_atomically(&path, true, |w| {
        std::io::Write::write_all(w, html.as_bytes()).map_err(|e| Error::io(&path, e))
    })
}

fn optional(value: Option<f64>, digits: usize) -> String {
    value.map_or("-".into(), |v| format!("{v:.digits$}"))
}

/// The results tables as Markdown (README): every method trained on its own terms
/// (env, method, success, final distance, control time, training), then every method at the
/// equal training budget.
pub fn markdown_table(summary: &Summary) -> String {
    let mut md = String::from(
        "| environment | method | success | final distance | control step p50 (us) | step time / PD or PID | R^2 of q from h | training steps | training (s) |\n|---|---|---|---|---|---|---|---|---|\n",
    );
    for results in &summary.envs {
        for row in &results.rows {
            md.push_str(&format!(
                "| {} | {} | {:.0}% | {:.4} +- {:.4} {} | {} | {} | {} | {} | {} |\n",
                results.env,
                row.method,
                100.0 * row.success_rate,
                row.final_mean,
                row.final_std,
                results.protocol.distance_unit,
                optional(row.control_time_us_p50, 0),
                row.control_time_vs_feedback
                    .map_or("-".into(), |x| format!("{x:.1}x")),
                optional(row.linear_r2, 3),
                row.train_steps.map_or("-".into(), |s| s.to_string()),
                optional(row.train_seconds, 0),
            ));
        }
    }
    md.push_str(&format!("\n{}", budget_markdown(summary)));
    md
}

/// The equal-budget comparison as a Markdown table (empty without one).
fn budget_markdown(summary: &Summary) -> String {
    let mut md = String::new();
    for results in &summary.envs {
        let Some(budget) = results.equal_budget_seconds else {
            continue;
        };
        for row in &results.equal_budget {
            let cells = match (&row.point, row.step) {
                (Some(p), _) => format!(
                    "{} | {:.0} | {:.0}% | {:.4} +- {:.4} {}",
                    p.step,
                    p.seconds,
                    100.0 * p.success_rate,
                    p.final_mean,
                    p.final_std,
                    results.protocol.distance_unit
                ),
                (None, Some(step)) => format!("{step} | - | not evaluated yet | -"),
                (None, None) => "- | - | no weights within the budget | -".into(),
            };
            md.push_str(&format!(
                "| {} | {budget:.0} | {} | {cells} |\n",
                results.env, row.method
            ));
        }
    }
    if md.is_empty() {
        return md;
    }
    format!(
        "| environment | budget (s) | method | step | training (s) | success | final distance |\n|---|---|---|---|---|---|---|\n{md}"
    )
}

/// A Markdown table (header, rule, rows) as an HTML table.
fn html_table(markdown: &str) -> String {
    let cells = |line: &str| -> Vec<String> {
        let line = line.trim().trim_start_matches('|').trim_end_matches('|');
        line.split('|')
            .map(|cell| cell.trim().replace("+-", "&plusmn;"))
            .collect()
    };
    let mut lines = markdown.lines().filter(|l| !l.trim().is_empty());
    let header = lines.next().map(cells).unwrap_or_default();
    let mut html = format!("<table><tr><th>{}</th></tr>\n", header.join("</th><th>"));
    for line in lines.skip(1) {
        html.push_str(&format!(
            "<tr><td>{}</td></tr>\n",
            cells(line).join("</td><td>")
        ));
    }
    html + "</table>"
}

fn report_html(config: &ExperimentConfig, summary: &Summary) -> String {
    let mut body = String::new();
    let mut table = String::new();
    for results in &summary.envs {
        for row in &results.rows {
            table.push_str(&format!(
                "<tr><td>{}</td><td>{}</td><td>{:.0}%</td><td>{:.4} &plusmn; {:.4} {}</td><td>{} / {}</td><td>{}</td><td>{}</td><td>{}</td><td>{}</td><td>{}</td><td>{}</td><td>{}</td></tr>\n",
                results.env,
                row.method,
                100.0 * row.success_rate,
                row.final_mean,
                row.final_std,
                results.protocol.distance_unit,
                optional(row.control_time_us_p50, 0),
                optional(row.control_time_us_p99, 0),
                row.control_time_vs_feedback
                    .map_or("-".into(), |x| format!("{x:.1}x")),
                optional(row.linear_r2, 3),
                optional(row.knn_r2, 3),
                optional(row.pushes_away_share.map(|x| 100.0 * x), 1),
                optional(row.locally_unstable_share.map(|x| 100.0 * x), 1),
                row.train_steps.map_or("-".into(), |s| s.to_string()),
                optional(row.train_seconds, 0),
            ));
        }
    }
    body.push_str(&format!(
        "<h2>Goal reaching</h2><p>Per environment: {} episodes from random starts to random goals (the goal given only as an image); success = final distance under the environment's threshold (point mass and Fetch: metres, reacher: joint-space radians). Every method is trained on the same dataset on its own terms: ProCL and PC3 for their presets' steps, the NewtonianVAE until its stopping rule on the validation ELBO ends it; the learning curves below show where each levels off; CEM and iLQR plan through the ProCL and PC3 runs' learned dynamics, on the same latents as their PD.</p>\
<table><tr><th>environment</th><th>method</th><th>success</th><th>final distance</th><th>control step p50 / p99 (&micro;s)</th><th>step time / PD or PID</th><th>linear R&sup2; of q from h</th><th>5-NN R&sup2;</th><th>pairs PD pushes away (%)</th><th>locally unstable cells (%)</th><th>training steps</th><th>training (s)</th></tr>\n{table}</table>\n",
        config.eval_episodes
    ));
    let budget = budget_markdown(summary);
    if !budget.is_empty() {
        body.push_str(&format!(
            "<h2>Equal training budget</h2><p>Every method's latest weights trained within the wall-clock time ProCL's run took, as the runs measured it while training (snapshots every few steps), evaluated on the same goals.</p>{}\n",
            html_table(&budget)
        ));
    }
    for results in &summary.envs {
        if results.rows.is_empty() {
            continue;
        }
        let env = results.env;
        body.push_str(&format!(
            "<h2>{env}</h2><p>Success threshold {} {}.</p><img src=\"{}\">\n",
            results.protocol.success_threshold,
            results.protocol.distance_unit,
            reach_figure(env)
        ));
        if !results.curves.is_empty() {
            body.push_str(&format!(
                "<h3>Learning curves</h3><p>Goals reached by the weights kept during training, against wall-clock training time.</p><img src=\"{}\">\n",
                learning_figure(env)
            ));
        }
        body.push_str("<h3>Latent trajectories and latent maps</h3>\n");
        for row in &results.rows {
            if let Some(run) = &row.run {
                let run = RunPaths::new(run);
                body.push_str(&format!(
                    "<p>{}</p><img src=\"{}\" width=\"48%\"> <img src=\"{}\" width=\"48%\">\n",
                    row.method,
                    EvalOutputs::in_run(&run).latent_png.display(),
                    run.dir.join(LATENT_MAP).display()
                ));
            }
        }
    }
    if !summary.ablation.is_empty() {
        let mut rows = String::new();
        for row in &summary.ablation {
            rows.push_str(&format!(
                "<tr><td>{}</td><td>{:.0}%</td><td>{:.4} &plusmn; {:.4}</td><td>{}</td></tr>\n",
                row.latent_noise_std,
                100.0 * row.success_rate,
                row.final_mean,
                row.final_std,
                optional(row.linear_r2, 3)
            ));
        }
        body.push_str(&format!(
            "<h2>Ablation: latent noise &epsilon; (point mass, ProCL + PD)</h2>\
<table><tr><th>&epsilon;</th><th>success</th><th>final distance (m)</th><th>R&sup2;</th></tr>\n{rows}</table><img src=\"{ABLATION_FIGURE}\">\n"
        ));
    }
    if let Some(track) = &summary.tracking {
        let mut rows = String::new();
        for m in &track.methods {
            rows.push_str(&format!(
                "<tr><td>{}</td><td>{:.4}</td><td>{:.4}</td><td>{:.4}</td></tr>\n",
                m.per_step.method, m.mean_error, m.rms_error, m.max_error
            ));
        }
        body.push_str(&format!(
            "<h2>Tracking on Fetch-3D</h2><p>{} demonstrations ({}) of {} steps; error = distance to the reference ({}).</p>\
<table><tr><th>method</th><th>mean error</th><th>RMS error</th><th>max error</th></tr>\n{rows}</table><img src=\"{}\">\n",
            track.demonstrations,
            track.source,
            track.steps,
            track.distance_unit,
            Path::new(EnvKind::Fetch.name())
                .join(Method::Procl.dir_name())
                .join(TRACK_FIGURE)
                .display()
        ));
    }
    let mut stage_rows = String::new();
    for (name, seconds) in &summary.stage_seconds {
        stage_rows.push_str(&format!("<tr><td>{name}</td><td>{seconds:.0}</td></tr>\n"));
    }
    body.push_str(&format!(
        "<h2>Stages</h2><p>Seconds each stage took when it ran ({:.0} s in all).</p><table><tr><th>stage</th><th>seconds</th></tr>\n{stage_rows}</table>\n",
        summary.total_seconds
    ));
    format!(
        r#"<!doctype html><html><head><meta charset="utf-8"><title>procl: the paper's experiments</title>
<style>body{{font-family:sans-serif;max-width:1100px;margin:2em auto}}td,th{{padding:4px 10px;border-bottom:1px solid #ddd}}img{{max-width:100%}}</style></head><body>
<h1>procl: PD control from pixels on Point mass-2D, Reacher-2D and Fetch-3D</h1>
<p>ProCL + PD, PC3 + PD (same networks, &lambda;<sub>R</sub> = 0), NewtonianVAE + PID, and the oracle PD on the true state. Seed {seed}.</p>
{body}</body></html>
"#,
        seed = summary.seed
    )
}

/// Marks of the README section `--readme` rewrites.
pub const README_BEGIN: &str = "<!-- experiment:begin -->";
pub const README_END: &str = "<!-- experiment:end -->";

/// Rewrites the part of `readme` between [`README_BEGIN`] and [`README_END`] with the results
/// table and the main figures, copied into `figures` (a folder relative to the README's).
pub fn update_readme(
    readme: &Path,
    figures: &Path,
    config: &ExperimentConfig,
    summary: &Summary,
) -> Result<()> {
    let bad = |message: String| Error::config(readme.display().to_string(), message);
    if let Some(missing) = summary.envs.iter().find(|e| e.rows.is_empty()) {
        return Err(bad(format!(
            "not rewritten: {} has no finished evaluation in {} yet",
            missing.env,
            config.out.display()
        )));
    }
    let text = std::fs::read_to_string(readme).map_err(|e| Error::io(readme, e))?;
    let begin = match text
        .match_indices(README_BEGIN)
        .map(|(i, _)| i)
        .collect::<Vec<_>>()[..]
    {
        [begin] => begin,
        [] => {
            return Err(bad(format!(
                "has no {README_BEGIN} ... {README_END} section to rewrite"
            )));
        }
        _ => return Err(bad(format!("has {README_BEGIN} more than once"))),
    };
    let Some(end) = text[begin..].find(README_END).map(|i| begin + i) else {
        return Err(bad(format!("has no {README_END} after {README_BEGIN}")));
    };
    let base = readme.parent().unwrap_or(Path::new("."));
    let figure_dir = base.join(figures);
    std::fs::create_dir_all(&figure_dir).map_err(|e| Error::io(&figure_dir, e))?;
    let mut section = format!(
        "{README_BEGIN}\n<!-- written by `procl experiment paper --readme README.md`; edits here are overwritten -->\n\n\
{} evaluation episodes per method, seed {}. The first table trains every method on its own \
terms (ProCL and PC3 for their presets' steps, the NewtonianVAE until its stopping rule ends it); \
the second evaluates every \
method's latest weights trained within the wall-clock time ProCL's run took, as the runs measured \
it while training. Stages took {:.0} s in all on the machine that ran them.\n\n{}\n",
        config.eval_episodes,
        summary.seed,
        summary.total_seconds,
        markdown_table(summary)
    );
    if !summary.ablation.is_empty() {
        let cells: Vec<String> = summary
            .ablation
            .iter()
            .map(|a| {
                format!(
                    "eps = {}: {:.0}% ({:.2e} m)",
                    a.latent_noise_std,
                    100.0 * a.success_rate,
                    a.final_mean
                )
            })
            .collect();
        section.push_str(&format!(
            "Latent-noise ablation (point mass, ProCL + PD, success and final distance): {}.\n\n",
            cells.join(", ")
        ));
    }
    if let Some(track) = &summary.tracking {
        let methods: Vec<String> = track
            .methods
            .iter()
            .map(|m| {
                format!(
                    "{} {:.4} {}",
                    m.per_step.method, m.mean_error, track.distance_unit
                )
            })
            .collect();
        section.push_str(&format!(
            "Tracking on Fetch-3D ({} demonstrations, {}, {} steps), mean distance to the reference: {}.\n\n",
            track.demonstrations,
            track.source,
            track.steps,
            methods.join(", ")
        ));
    }
    for results in &summary.envs {
        let figures_of_env = [
            (reach_figure(results.env), "reach", "distance to goal"),
            (
                learning_figure(results.env),
                "learning",
                "goals reached against training time",
            ),
        ];
        for (figure, suffix, alt) in figures_of_env {
            let source = config.out.join(figure);
            if results.rows.is_empty() || !source.exists() {
                continue;
            }
            let name = format!("{}_{suffix}.png", results.env.name());
            let target = figure_dir.join(&name);
            let bytes = std::fs::read(&source).map_err(|e| Error::io(&source, e))?;
            crate::write_atomically(&target, true, |w| {
                std::io::Write::write_all(w, &bytes).map_err(|e| Error::io(&target, e))
            })?;
            section.push_str(&format!(
                "![{alt}, {}]({})\n\n",
                results.env,
                figures.join(&name).display()
            ));
        }
    }
    section.push_str(README_END);
    let updated = format!(
        "{}{}{}",
        &text[..begin],
        section,
        &text[end + README_END.len()..]
    );
    crate::write_atomically(readme, true, |w| {
        std::io::Write::write_all(w, updated.as_bytes()).map_err(|e| Error::io(readme, e))
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn curve_indices_grow_by_at_most_half_and_end_at_the_last_snapshot() {
        assert_eq!(curve_indices(0), Vec::<usize>::new());
        assert_eq!(curve_indices(1), [1]);
        assert_eq!(curve_indices(5), [1, 2, 3, 4, 5]);
        assert_eq!(curve_indices(12), [1, 2, 3, 4, 6, 8, 12]);
        assert_eq!(
            curve_indices(80),
            [1, 2, 3, 4, 6, 8, 12, 16, 24, 32, 48, 64, 80]
        );
    }

    /// A run folder with a checkpoint after `last` steps, snapshots at `snapshots` and a
    /// metrics.csv whose clock restarts at `resumed_at` (a resumed run), a second a step.
    fn fake_run(dir: &Path, last: u64, snapshots: &[u64], resumed_at: u64) -> RunPaths {
        let run = RunPaths::new(dir);
        let write_weights = |run: &RunPaths, step| {
            std::fs::create_dir_all(&run.dir).unwrap();
            let model = crate::model::ModelConfig::for_action_dim(2)
                .init(0, &crate::model::cpu_device())
                .unwrap();
            let meta = crate::train::checkpoint::CheckpointMeta::at(step);
            crate::train::checkpoint::save_checkpoint(&run.checkpoint(), &model, None, &meta)
                .unwrap();
        };
        write_weights(&run, last);
        for step in snapshots {
            write_weights(&run.snapshot(*step), *step);
        }
        // An unfinished snapshot (no weights yet) is not one.
        std::fs::create_dir_all(run.dir.join("snapshots/step-000099")).unwrap();
        let mut csv = String::from("step,total,seconds\n");
        for step in 1..=last {
            let seconds = if step > resumed_at {
                step - resumed_at
            } else {
                step
            };
            csv.push_str(&format!("{step},0.5,{seconds}.000\n"));
        }
        std::fs::write(run.metrics(), csv).unwrap();
        run
    }

    #[test]
    fn the_equal_budget_takes_the_latest_weights_trained_within_it() {
        let dir = tempfile::tempdir().unwrap();
        // Resumed after step 5: the clock reads 1..5, then 1..5 again for steps 6..10.
        let steps: Vec<u64> = (1..=10).collect();
        let run = fake_run(dir.path(), 10, &steps, 5);
        assert_eq!(run.snapshot_steps(), steps);
        let clock = training_clock(&run).unwrap();
        assert_eq!(clock[5], (6, 6.0));
        assert_eq!(training_seconds(&run), Some(10.0));
        assert_eq!(within_budget(&run, 7.5), Some((7, 7.0, false)));
        assert_eq!(within_budget(&run, 10.0), Some((10, 10.0, true)));
        assert_eq!(within_budget(&run, 0.5), None);
        // The curve: snapshots 1, 2, 3, 4, 6, 8 and 9 of the nine before the final weights,
        // and the budget's (step 7).
        assert_eq!(curve_snapshots(&run, None), [1, 2, 3, 4, 6, 8, 9]);
        let within = within_budget(&run, 7.5);
        assert_eq!(curve_snapshots(&run, within), [1, 2, 3, 4, 6, 7, 8, 9]);
    }
}
