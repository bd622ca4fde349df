//! procl from Python: the environments as reach tasks stepped in Rust, a trained run's
//! latent controller, and collect / train / info on files. `python/procl` wraps these in
//! gymnasium's `Env` and `VectorEnv`.

use std::ops::ControlFlow;
use std::path::PathBuf;

use numpy::ndarray::{Array1, Array2, Array4};
use numpy::{IntoPyArray, PyArray1, PyArray2, PyArray3, PyArray4, PyReadonlyArray1};
use numpy::{PyReadonlyArray2, PyReadonlyArrayDyn, PyUntypedArrayMethods};
use pyo3::create_exception;
use pyo3::exceptions::{PyException, PyKeyboardInterrupt};
use pyo3::prelude::*;
use pyo3::types::PyDict;
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;

use procl::envs::{EnvKind, FRAME_BYTES, FRAME_PX, Frame, State};
use procl::eval::{ReachConfig, RunPolicy, run_policy};
use procl::model::{cpu_device, frames_to_tensor, to_vec};
use procl::train::RunPaths;

create_exception!(
    _procl,
    ProclError,
    PyException,
    "A procl error: bad input, a missing or broken file, an invalid configuration. The message is the command line's one-line error."
);

/// procl's error as a Python exception with the same one-line message.
fn py_err(error: impl std::fmt::Display) -> PyErr {
    ProclError::new_err(error.to_string())
}

fn frame_array<'py>(py: Python<'py>, frame: &Frame) -> Bound<'py, PyArray3<u8>> {
    numpy::ndarray::Array3::from_shape_vec((FRAME_PX, FRAME_PX, 3), frame.to_vec())
        .map(|a| a.into_pyarray(py))
        .unwrap_or_else(|_| numpy::ndarray::Array3::zeros((FRAME_PX, FRAME_PX, 3)).into_pyarray(py))
}

/// The bytes of one `[64, 64, 3]` u8 frame, or an error naming `what` and the shape it has.
fn frame_bytes<'a>(frame: &'a PyReadonlyArrayDyn<'_, u8>, what: &str) -> PyResult<&'a [u8]> {
    if frame.shape() != [FRAME_PX, FRAME_PX, 3] {
        return Err(py_err(format!(
            "`{what}` has shape {:?}, expected [{FRAME_PX}, {FRAME_PX}, 3] (one 64x64 RGB frame, uint8)",
            frame.shape()
        )));
    }
    frame.as_slice().map_err(|_| {
        py_err(format!(
            "`{what}` must be C-contiguous (np.ascontiguousarray)"
        ))
    })
}

/// One environment as a goal-reaching task: a start and a goal drawn from the task seed, the
/// goal shown as an image, reward minus the distance to the goal, success below the
/// evaluation protocol's threshold, and its horizon as the time limit.
struct ReachTask {
    kind: EnvKind,
    sim: Box<dyn procl::envs::Env>,
    protocol: ReachConfig,
    /// Draws the start and goal of each episode (reseeded by `reset` with a seed).
    rng: ChaCha8Rng,
    goal: State,
    goal_frame: Frame,
    frame: Frame,
    steps: usize,
    action: Vec<f64>,
}

/// What one step returns besides the frame.
struct StepOutcome {
    reward: f64,
    terminated: bool,
    truncated: bool,
}

impl ReachTask {
    fn new(config: &procl::envs::EnvConfig, horizon: Option<usize>) -> Self {
        let kind = config.kind();
        let sim = config.make();
        let mut protocol = ReachConfig::for_env(kind, 0);
        if let Some(h) = horizon {
            protocol.horizon = h;
        }
        let action = vec![0.0; sim.action_dim()];
        let goal = sim.state();
        Self {
            kind,
            sim,
            protocol,
            rng: ChaCha8Rng::seed_from_u64(0),
            goal,
            goal_frame: [0; FRAME_BYTES],
            frame: [0; FRAME_BYTES],
            steps: 0,
            action,
        }
    }

    /// Starts an episode: the task seed reseeds the draws when given; `start` and `goal`
    /// configurations, when given, replace the drawn ones. Both start at rest.
    fn reset(
        &mut self,
        seed: Option<u64>,
        start: Option<Vec<f64>>,
        goal: Option<Vec<f64>>,
    ) -> procl::Result<()> {
        if let Some(seed) = seed {
            self.rng = ChaCha8Rng::seed_from_u64(seed);
        }
        let drawn_start = self.sim.sample_config(&mut self.rng);
        let drawn_goal = self.sim.sample_config(&mut self.rng);
        let at_rest = |q: Vec<f64>| State {
            qd: vec![0.0; q.len()],
            q,
        };
        let goal = at_rest(goal.unwrap_or(drawn_goal));
        self.sim.set_state(&goal)?;
        self.sim.render(&mut self.goal_frame);
        self.sim.set_state(&at_rest(start.unwrap_or(drawn_start)))?;
        self.sim.render(&mut self.frame);
        self.goal = goal;
        self.steps = 0;
        Ok(())
    }

    fn distance(&self) -> f64 {
        self.sim.config_distance(&self.sim.state().q, &self.goal.q)
    }

    fn step(&mut self, action: &[f64]) -> StepOutcome {
        self.action.copy_from_slice(action);
        self.sim.step(&self.action);
        self.sim.render(&mut self.frame);
        self.steps += 1;
        let distance = self.distance();
        StepOutcome {
            reward: -distance,
            terminated: distance < self.protocol.success_threshold,
            truncated: self.steps >= self.protocol.horizon,
        }
    }

    fn info<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyDict>> {
        let state = self.sim.state();
        let info = PyDict::new(py);
        info.set_item("q", PyArray1::from_vec(py, state.q))?;
        info.set_item("qd", PyArray1::from_vec(py, state.qd))?;
        info.set_item("goal_q", PyArray1::from_vec(py, self.goal.q.clone()))?;
        info.set_item("goal_frame", frame_array(py, &self.goal_frame))?;
        info.set_item("distance", self.distance())?;
        info.set_item(
            "is_success",
            self.distance() < self.protocol.success_threshold,
        )?;
        Ok(info)
    }

    fn check_action(&self, action: &[f64]) -> PyResult<()> {
        if action.len() != self.action.len() {
            return Err(py_err(format!(
                "`action` has {} components; {} takes {}",
                action.len(),
                self.kind,
                self.action.len()
            )));
        }
        Ok(())
    }
}

fn env_kind(name: &str) -> PyResult<EnvKind> {
    name.parse().map_err(py_err)
}

/// The configuration of the environment `name`, with the fields of the JSON object
/// `variant_json` changed when given.
fn env_config(name: &str, variant_json: Option<&str>) -> PyResult<procl::envs::EnvConfig> {
    let kind = env_kind(name)?;
    match variant_json {
        Some(fields) => env_variant(kind, fields).map_err(py_err),
        None => Ok(kind.into()),
    }
}

fn optional_config(options: Option<&Bound<'_, PyDict>>, key: &str) -> PyResult<Option<Vec<f64>>> {
    match options.map(|o| o.get_item(key)).transpose()?.flatten() {
        Some(value) if !value.is_none() => Ok(Some(value.extract()?)),
        _ => Ok(None),
    }
}

/// One procl environment as a reach task (the Rust core of `procl.make`).
#[pyclass(unsendable, module = "procl._procl")]
struct ReachEnv {
    task: ReachTask,
}

#[pymethods]
impl ReachEnv {
    #[new]
    #[pyo3(signature = (env, horizon=None, variant_json=None))]
    fn new(env: &str, horizon: Option<usize>, variant_json: Option<&str>) -> PyResult<Self> {
        Ok(Self {
            task: ReachTask::new(&env_config(env, variant_json)?, horizon),
        })
    }

    /// Starts an episode; returns the first frame and the info dict.
    #[pyo3(signature = (seed=None, options=None))]
    fn reset<'py>(
        &mut self,
        py: Python<'py>,
        seed: Option<u64>,
        options: Option<&Bound<'py, PyDict>>,
    ) -> PyResult<(Bound<'py, PyArray3<u8>>, Bound<'py, PyDict>)> {
        let start = optional_config(options, "start_q")?;
        let goal = optional_config(options, "goal_q")?;
        self.task.reset(seed, start, goal).map_err(py_err)?;
        Ok((frame_array(py, &self.task.frame), self.task.info(py)?))
    }

    /// One control period under `action`; returns (frame, reward, terminated, truncated, info).
    #[allow(clippy::type_complexity)]
    fn step<'py>(
        &mut self,
        py: Python<'py>,
        action: PyReadonlyArray1<'py, f64>,
    ) -> PyResult<(
        Bound<'py, PyArray3<u8>>,
        f64,
        bool,
        bool,
        Bound<'py, PyDict>,
    )> {
        let action = action.as_slice().map_err(py_err)?;
        self.task.check_action(action)?;
        let outcome = self.task.step(action);
        Ok((
            frame_array(py, &self.task.frame),
            outcome.reward,
            outcome.terminated,
            outcome.truncated,
            self.task.info(py)?,
        ))
    }

    /// The current frame, `[64, 64, 3]` uint8.
    fn render<'py>(&self, py: Python<'py>) -> Bound<'py, PyArray3<u8>> {
        frame_array(py, &self.task.frame)
    }

    #[getter]
    fn action_dim(&self) -> usize {
        self.task.action.len()
    }
    #[getter]
    fn config_dim(&self) -> usize {
        self.task.sim.config_dim()
    }
    #[getter]
    fn control_dt_s(&self) -> f64 {
        self.task.sim.control_dt_s()
    }
    #[getter]
    fn horizon(&self) -> usize {
        self.task.protocol.horizon
    }
    #[getter]
    fn success_threshold(&self) -> f64 {
        self.task.protocol.success_threshold
    }
    #[getter]
    fn name(&self) -> &'static str {
        self.task.kind.name()
    }
}

/// `n` copies of one environment stepped together, with next-step autoreset: the step after
/// an episode ends resets that copy (its action ignored, reward 0) to a task drawn from its
/// own stream (the Rust core of `procl.make_vec`).
#[pyclass(unsendable, module = "procl._procl")]
struct ReachVecEnv {
    tasks: Vec<ReachTask>,
    done: Vec<bool>,
}

type VecStep<'py> = (
    Bound<'py, PyArray4<u8>>,
    Bound<'py, PyArray1<f64>>,
    Bound<'py, PyArray1<bool>>,
    Bound<'py, PyArray1<bool>>,
    Bound<'py, PyDict>,
);

impl ReachVecEnv {
    fn frames<'py>(&self, py: Python<'py>) -> Bound<'py, PyArray4<u8>> {
        let mut data = Vec::with_capacity(self.tasks.len() * FRAME_BYTES);
        for task in &self.tasks {
            data.extend_from_slice(&task.frame);
        }
        Array4::from_shape_vec((self.tasks.len(), FRAME_PX, FRAME_PX, 3), data)
            .unwrap_or_else(|_| Array4::zeros((0, FRAME_PX, FRAME_PX, 3)))
            .into_pyarray(py)
    }

    /// Info of every copy as arrays with a leading copy axis.
    fn infos<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyDict>> {
        let n = self.tasks.len();
        let rows = |f: &dyn Fn(&ReachTask) -> Vec<f64>| {
            let rows: Vec<Vec<f64>> = self.tasks.iter().map(f).collect();
            let width = rows.first().map_or(0, Vec::len);
            Array2::from_shape_vec((n, width), rows.concat()).map(|a| a.into_pyarray(py))
        };
        let info = PyDict::new(py);
        info.set_item("q", rows(&|t| t.sim.state().q).map_err(py_err)?)?;
        info.set_item("qd", rows(&|t| t.sim.state().qd).map_err(py_err)?)?;
        info.set_item("goal_q", rows(&|t| t.goal.q.clone()).map_err(py_err)?)?;
        let distance: Vec<f64> = self.tasks.iter().map(ReachTask::distance).collect();
        let success: Vec<bool> = self
            .tasks
            .iter()
            .zip(&distance)
            .map(|(t, d)| *d < t.protocol.success_threshold)
            .collect();
        info.set_item("distance", PyArray1::from_vec(py, distance))?;
        info.set_item("is_success", PyArray1::from_vec(py, success))?;
        let mut goals = Vec::with_capacity(n * FRAME_BYTES);
        for task in &self.tasks {
            goals.extend_from_slice(&task.goal_frame);
        }
        let goals = Array4::from_shape_vec((n, FRAME_PX, FRAME_PX, 3), goals).map_err(py_err)?;
        info.set_item("goal_frame", goals.into_pyarray(py))?;
        Ok(info)
    }
}

#[pymethods]
impl ReachVecEnv {
    #[new]
    #[pyo3(signature = (env, n, horizon=None, variant_json=None))]
    fn new(
        env: &str,
        n: usize,
        horizon: Option<usize>,
        variant_json: Option<&str>,
    ) -> PyResult<Self> {
        if n == 0 {
            return Err(py_err("`n` must be at least 1"));
        }
        let config = env_config(env, variant_json)?;
        Ok(Self {
            tasks: (0..n).map(|_| ReachTask::new(&config, horizon)).collect(),
            done: vec![false; n],
        })
    }

    /// Reseeds copy `i` with `seeds[i]` and starts every copy; returns frames `[n, 64, 64, 3]`
    /// and the info dict of arrays.
    fn reset<'py>(
        &mut self,
        py: Python<'py>,
        seeds: Vec<u64>,
    ) -> PyResult<(Bound<'py, PyArray4<u8>>, Bound<'py, PyDict>)> {
        if seeds.len() != self.tasks.len() {
            return Err(py_err(format!(
                "{} seeds for {} environments",
                seeds.len(),
                self.tasks.len()
            )));
        }
        for (task, seed) in self.tasks.iter_mut().zip(seeds) {
            task.reset(Some(seed), None, None).map_err(py_err)?;
        }
        self.done.fill(false);
        Ok((self.frames(py), self.infos(py)?))
    }

    /// Steps every copy under `actions [n, du]` (with next-step autoreset).
    fn step<'py>(
        &mut self,
        py: Python<'py>,
        actions: PyReadonlyArray2<'py, f64>,
    ) -> PyResult<VecStep<'py>> {
        let n = self.tasks.len();
        let du = self.tasks[0].action.len();
        if actions.shape() != [n, du] {
            return Err(py_err(format!(
                "`actions` has shape {:?}, expected [{n}, {du}]",
                actions.shape()
            )));
        }
        let actions = actions.as_array();
        let mut rewards = Array1::zeros(n);
        let mut terminated = Array1::from_elem(n, false);
        let mut truncated = Array1::from_elem(n, false);
        for (i, task) in self.tasks.iter_mut().enumerate() {
            if self.done[i] {
                task.reset(None, None, None).map_err(py_err)?;
                self.done[i] = false;
                continue;
            }
            let action: Vec<f64> = actions.row(i).to_vec();
            let outcome = task.step(&action);
            rewards[i] = outcome.reward;
            terminated[i] = outcome.terminated;
            truncated[i] = outcome.truncated;
            self.done[i] = outcome.terminated || outcome.truncated;
        }
        Ok((
            self.frames(py),
            rewards.into_pyarray(py),
            terminated.into_pyarray(py),
            truncated.into_pyarray(py),
            self.infos(py)?,
        ))
    }

    /// Current frames `[n, 64, 64, 3]`.
    fn render<'py>(&self, py: Python<'py>) -> Bound<'py, PyArray4<u8>> {
        self.frames(py)
    }

    #[getter]
    fn num_envs(&self) -> usize {
        self.tasks.len()
    }
    #[getter]
    fn action_dim(&self) -> usize {
        self.tasks[0].action.len()
    }
    #[getter]
    fn horizon(&self) -> usize {
        self.tasks[0].protocol.horizon
    }
}

/// A trained run's controller: latent PD (ProCL, PC3) or PID (NewtonianVAE) on frames from any
/// source, with its latent velocity estimate kept inside.
#[pyclass(unsendable, module = "procl._procl")]
struct Controller {
    policy: Box<dyn RunPolicy>,
    label: String,
    env: &'static str,
    dt: f64,
    action_dim: usize,
    no_state: State,
    started: bool,
}

#[pymethods]
impl Controller {
    /// Loads the run folder written by `procl train`.
    #[staticmethod]
    fn load(run_dir: PathBuf) -> PyResult<Self> {
        let run = RunPaths::new(&run_dir);
        let device = cpu_device();
        let (config, model) = run.load_trained(&device).map_err(py_err)?;
        let (label, dt, policy) = run_policy(&config, model, device).map_err(py_err)?;
        Ok(Self {
            action_dim: policy.encoder().latent_dim(),
            policy,
            label,
            env: procl::envs::source_name(config.env),
            dt,
            no_state: State {
                q: vec![],
                qd: vec![],
            },
            started: false,
        })
    }

    /// Sets the goal image (the target is the goal at rest) and forgets the previous frame.
    fn reset(&mut self, goal_frame: PyReadonlyArrayDyn<'_, u8>) -> PyResult<()> {
        let goal = frame_bytes(&goal_frame, "goal_frame")?;
        self.policy.reset(goal, &self.no_state);
        self.started = true;
        Ok(())
    }

    /// The action for the newest frame, `[du]` float32 in [-1, 1] (clipped as the
    /// environments clip it).
    fn act<'py>(
        &mut self,
        py: Python<'py>,
        frame: PyReadonlyArrayDyn<'py, u8>,
    ) -> PyResult<Bound<'py, PyArray1<f32>>> {
        if !self.started {
            return Err(py_err("call reset(goal_frame) before act(frame)"));
        }
        let bytes = frame_bytes(&frame, "frame")?;
        let mut u = vec![0.0; self.action_dim];
        self.policy.act(bytes, &self.no_state, &mut u);
        Ok(PyArray1::from_vec(
            py,
            u.iter().map(|&x| x.clamp(-1.0, 1.0) as f32).collect(),
        ))
    }

    /// Latent configurations `h` of frames `[n, 64, 64, 3]` (or one `[64, 64, 3]`) as `[n, du]`.
    fn encode<'py>(
        &self,
        py: Python<'py>,
        frames: PyReadonlyArrayDyn<'py, u8>,
    ) -> PyResult<Bound<'py, PyArray2<f32>>> {
        let shape = frames.shape().to_vec();
        let n = match shape.as_slice() {
            [n, FRAME_PX, FRAME_PX, 3] => *n,
            [FRAME_PX, FRAME_PX, 3] => 1,
            _ => {
                return Err(py_err(format!(
                    "`frames` has shape {shape:?}, expected [n, {FRAME_PX}, {FRAME_PX}, 3] (uint8)"
                )));
            }
        };
        let bytes = frames
            .as_slice()
            .map_err(|_| py_err("`frames` must be C-contiguous (np.ascontiguousarray)"))?;
        let device = cpu_device();
        let tensor = frames_to_tensor(bytes.chunks_exact(FRAME_BYTES), &device);
        let h = to_vec(self.policy.encoder().encode(tensor));
        let array = Array2::from_shape_vec((n, self.action_dim), h).map_err(py_err)?;
        Ok(array.into_pyarray(py))
    }

    /// `h` of the last frame `act` saw.
    #[getter]
    fn latent<'py>(&self, py: Python<'py>) -> Bound<'py, PyArray1<f64>> {
        PyArray1::from_vec(py, self.policy.latent())
    }
    /// `h*` of the goal image.
    #[getter]
    fn goal_latent<'py>(&self, py: Python<'py>) -> Bound<'py, PyArray1<f64>> {
        PyArray1::from_vec(py, self.policy.goal_latent())
    }
    /// `ProCL + PD`, `PC3 + PD` or `NewtonianVAE + PID`.
    #[getter]
    fn label(&self) -> &str {
        &self.label
    }
    /// The environment the run was trained on, or `custom`.
    #[getter]
    fn env(&self) -> &'static str {
        self.env
    }
    /// Seconds between frames that the velocity estimate assumes.
    #[getter]
    fn control_dt_s(&self) -> f64 {
        self.dt
    }
    #[getter]
    fn action_dim(&self) -> usize {
        self.action_dim
    }
}

/// Collects a random-control dataset of an environment to `out` (an `.npz`); returns a summary.
/// `variant_json` holds the fields of the environment's configuration to change (a JSON
/// object); `as_custom` records the data as custom, as `procl collect --as-custom` does.
#[pyfunction]
#[pyo3(signature = (env, out, seed=0, transitions=None, episode_len=None, force=false, variant_json=None, as_custom=false))]
#[allow(clippy::too_many_arguments)]
fn collect<'py>(
    py: Python<'py>,
    env: &str,
    out: PathBuf,
    seed: u64,
    transitions: Option<usize>,
    episode_len: Option<usize>,
    force: bool,
    variant_json: Option<String>,
    as_custom: bool,
) -> PyResult<Bound<'py, PyDict>> {
    let env = env_config(env, variant_json.as_deref())?;
    let mut config = procl::data::CollectConfig::new(env.kind(), seed);
    config.env = env;
    config.as_custom = as_custom;
    if let Some(t) = transitions {
        config.transitions = t;
    }
    if let Some(l) = episode_len {
        config.episode_len = l;
    }
    let data = py
        .detach(|| -> procl::Result<procl::data::Dataset> {
            if out.exists() && !force {
                return Err(procl::Error::config(
                    "out",
                    format!("{} exists (pass force=True to replace it)", out.display()),
                ));
            }
            let data = procl::data::collect(&config, |_| {})?;
            data.save(&out, force)?;
            Ok(data)
        })
        .map_err(py_err)?;
    dataset_summary(py, &data)
}

/// The configuration of `kind` with the fields of the JSON object `fields` changed.
fn env_variant(kind: EnvKind, fields: &str) -> procl::Result<procl::envs::EnvConfig> {
    let fields: serde_json::Value =
        serde_json::from_str(fields).map_err(|e| procl::Error::config("variant", e.to_string()))?;
    let tagged = serde_json::json!({ kind.name(): fields });
    let config: procl::envs::EnvConfig = serde_json::from_value(tagged)
        .map_err(|e| procl::Error::config("variant", e.to_string()))?;
    config.validate()?;
    Ok(config)
}

fn dataset_summary<'py>(
    py: Python<'py>,
    data: &procl::data::Dataset,
) -> PyResult<Bound<'py, PyDict>> {
    let summary = PyDict::new(py);
    summary.set_item("env", data.meta.source_name())?;
    summary.set_item("source", &data.meta.source)?;
    summary.set_item("episodes", data.episodes())?;
    summary.set_item("steps", data.steps())?;
    summary.set_item("transitions", data.transitions())?;
    summary.set_item("action_dim", data.action_dim())?;
    summary.set_item("config_dim", data.config_dim())?;
    summary.set_item("control_dt_s", data.meta.control_dt_s)?;
    summary.set_item("seed", data.meta.seed)?;
    let variant = match &data.meta.env_config {
        Some(config) => Some(
            serde_json::to_string(config)
                .map_err(|e| procl::Error::config("env_config", e.to_string()))
                .map_err(py_err)?,
        ),
        None => None,
    };
    summary.set_item("env_config_json", variant)?;
    Ok(summary)
}

/// Validates a dataset and describes it (what `procl info` prints).
#[pyfunction]
fn info<'py>(py: Python<'py>, data: PathBuf) -> PyResult<Bound<'py, PyDict>> {
    let dataset = procl::data::Dataset::load(&data).map_err(py_err)?;
    let summary = dataset_summary(py, &dataset)?;
    let spread = procl::data::PixelSpread::of_frames(dataset.every_frame());
    let hub = match spread.hub_candidate() {
        Some(hub) => {
            let fields = PyDict::new(py);
            fields.set_item("pixel", hub.pixels().to_vec())?;
            fields.set_item("radial_r2", hub.radial_r2)?;
            fields.set_item("core_share", hub.core_share)?;
            fields.set_item("accepted", hub.is_accepted())?;
            fields.set_item("cut_deg", spread.quietest_angle_deg(hub.centre))?;
            Some(fields)
        }
        None => None,
    };
    summary.set_item("hub", hub)?;
    Ok(summary)
}

/// Trains on `data` into the run folder `out`, as `procl train` does: the TOML file
/// `config_path`, then the top-level keys of `overrides_json` (a config table as JSON), over
/// the preset. Returns steps done, seconds and final losses.
#[pyfunction]
#[pyo3(signature = (data, out, method=None, config_path=None, overrides_json=None, preset_env=None, resume=false))]
#[allow(clippy::too_many_arguments)]
fn train<'py>(
    py: Python<'py>,
    data: PathBuf,
    out: PathBuf,
    method: Option<String>,
    config_path: Option<PathBuf>,
    overrides_json: Option<String>,
    preset_env: Option<String>,
    resume: bool,
) -> PyResult<Bound<'py, PyDict>> {
    // Training runs without the GIL; between steps it takes the GIL back long enough to see a
    // Ctrl-C, and stops as a killed run would (the last checkpoint kept for `resume`).
    let mut interrupt: Option<PyErr> = None;
    let outcome = py.detach(|| -> procl::Result<procl::train::TrainSummary> {
        let dataset = procl::data::Dataset::load(&data)?;
        let method = method.map(|m| m.parse()).transpose()?;
        let recipe = preset_env.map(|e| e.parse()).transpose()?;
        let mut table = match &config_path {
            Some(path) => procl::train::read_config_table(path)?,
            None => toml::Table::new(),
        };
        if let Some(text) = overrides_json {
            let overrides: toml::Table = serde_json::from_str(&text)
                .map_err(|e| procl::Error::config("config", e.to_string()))?;
            table.extend(overrides);
        }
        let base = procl::train::ConfigBase::for_dataset(&dataset, recipe)?;
        let config = procl::train::config_from_table(table, base, method)?;
        let run = RunPaths::new(&out);
        let summary = procl::train::train_interruptible(
            &config,
            &dataset,
            &run,
            resume,
            &cpu_device(),
            |_, _| match Python::attach(|py| py.check_signals()) {
                Ok(()) => ControlFlow::Continue(()),
                Err(e) => {
                    interrupt = Some(e);
                    ControlFlow::Break(())
                }
            },
        )?;
        procl::eval::write_diagnostics(&run)?;
        Ok(summary)
    });
    let summary = match (outcome, interrupt) {
        (Err(procl::Error::Interrupted(message)), Some(signal)) => {
            // The signal's own exception (KeyboardInterrupt), saying what was kept.
            return Err(if signal.is_instance_of::<PyKeyboardInterrupt>(py) {
                PyKeyboardInterrupt::new_err(message)
            } else {
                signal
            });
        }
        (outcome, _) => outcome.map_err(py_err)?,
    };
    let result = PyDict::new(py);
    result.set_item("steps", summary.steps_done)?;
    result.set_item("seconds", summary.seconds)?;
    result.set_item("final_losses", summary.last.map(|v| v.to_string()))?;
    Ok(result)
}

#[pymodule]
fn _procl(m: &Bound<'_, PyModule>) -> PyResult<()> {
    m.add("ProclError", m.py().get_type::<ProclError>())?;
    m.add("FRAME_PX", FRAME_PX)?;
    m.add("ENV_NAMES", EnvKind::NAMES.to_vec())?;
    m.add_class::<ReachEnv>()?;
    m.add_class::<ReachVecEnv>()?;
    m.add_class::<Controller>()?;
    m.add_function(wrap_pyfunction!(collect, m)?)?;
    m.add_function(wrap_pyfunction!(info, m)?)?;
    m.add_function(wrap_pyfunction!(train, m)?)?;
    Ok(())
}
