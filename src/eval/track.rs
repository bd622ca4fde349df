//! Trajectory tracking: latent PD follows a demonstration's frames (their encodings and
//! finite-difference latent velocities), the oracle follows its true states; the error is the
//! distance to the reference configuration at every step.

use std::path::{Path, PathBuf};

use burn::tensor::Device;

use super::plots::save_track_plot;
use super::reach::{EpisodeRecord, ReachConfig, TrackSummary, summarise};
use super::run::run_policy;
use crate::control::{OraclePdPolicy, Policy, Target, oracle_gains};
use crate::data::Dataset;
use crate::envs::{EnvConfig, EnvKind, FRAME_BYTES, State};
use crate::error::{Error, Result};
use crate::model::{LatentEncoder, cpu_device, frames_to_tensor, to_vec};
use crate::train::RunPaths;

/// The reference of one demonstration: per frame `t`, the true state and (for latent policies)
/// `h*_t = e(frame_t)` and `v*_t = (h*_t - h*_{t-1}) / dt`, the same finite difference that
/// defines the latent velocity `v` (at `t = 0` the forward difference stands in).
pub struct Reference {
    pub states: Vec<State>,
    pub frames: Vec<Vec<u8>>,
    pub h: Vec<Vec<f64>>,
    pub v: Vec<Vec<f64>>,
}

impl Reference {
    /// The reference of `episode` in `demo`, whose true `states` are given, without latents
    /// (for the oracle).
    pub fn from_demo(demo: &Dataset, states: &ndarray::Array3<f32>, episode: usize) -> Self {
        let dq = states.shape()[2] / 2;
        let frames = (0..=demo.steps())
            .map(|t| demo.frame(episode, t).to_vec())
            .collect();
        let states = (0..=demo.steps())
            .map(|t| {
                let row: Vec<f64> = (0..2 * dq)
                    .map(|i| states[[episode, t, i]] as f64)
                    .collect();
                State {
                    q: row[..dq].to_vec(),
                    qd: row[dq..].to_vec(),
                }
            })
            .collect();
        Self {
            states,
            frames,
            h: vec![],
            v: vec![],
        }
    }

    /// Encodes every reference frame once (one batch) and differences the encodings.
    pub fn encode(&mut self, encoder: &dyn LatentEncoder, device: &Device, dt: f64) {
        let batch = frames_to_tensor(self.frames.iter().map(Vec::as_slice), device);
        let [n, du] = [self.frames.len(), encoder.latent_dim()];
        let flat = to_vec(encoder.encode(batch));
        self.h = (0..n)
            .map(|t| {
                flat[t * du..(t + 1) * du]
                    .iter()
                    .map(|&x| x as f64)
                    .collect()
            })
            .collect();
        self.v = (0..n)
            .map(|t| {
                let (a, b) = if t == 0 {
                    (1.min(n - 1), 0)
                } else {
                    (t, t - 1)
                };
                self.h[a]
                    .iter()
                    .zip(&self.h[b])
                    .map(|(x, y)| (x - y) / dt)
                    .collect()
            })
            .collect();
    }
}

/// Runs `policy` along `reference` from its first state. The action at step `t` aims at the
/// reference at `t + 1` (the state that action produces), as the demonstrator's did.
pub fn track_episode(
    env: &EnvConfig,
    policy: &mut dyn Policy,
    reference: &Reference,
) -> Result<EpisodeRecord> {
    let mut sim = env.make();
    let steps = reference.states.len() - 1;
    sim.set_state(&reference.states[0])?;
    let mut frame = [0u8; FRAME_BYTES];
    let mut u = vec![0.0; sim.action_dim()];
    let mut record = EpisodeRecord::default();
    policy.start_tracking();
    let mut state = sim.state();
    for t in 0..=steps {
        let target_state = &reference.states[t];
        record
            .distances
            .push(sim.config_distance(&state.q, &target_state.q));
        record.configs.push(state.q.clone());
        if t == steps {
            break;
        }
        sim.render(&mut frame);
        let empty: &[f64] = &[];
        policy.set_target(&Target {
            h: reference.h.get(t + 1).map_or(empty, Vec::as_slice),
            v: reference.v.get(t + 1).map_or(empty, Vec::as_slice),
            state: &reference.states[t + 1],
        });
        policy.act(&frame, &state, &mut u);
        let h = policy.latent();
        if !h.is_empty() {
            record.latents.push(h);
        }
        sim.step(&u);
        state = sim.state();
    }
    Ok(record)
}

/// The figure [`track_run`] draws into a run folder.
pub const TRACK_FIGURE: &str = "track.png";

/// The `track.json` document.
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct TrackReport {
    pub env: EnvKind,
    pub demo: PathBuf,
    /// The demonstration file's `source` (e.g. `demonstration:circle`).
    pub source: String,
    pub demonstrations: usize,
    pub steps: usize,
    pub distance_unit: String,
    pub methods: Vec<TrackSummary>,
}

fn summarise_tracking(
    method: &str,
    episodes: &[EpisodeRecord],
    protocol: &ReachConfig,
    control_times_s: &[f64],
) -> TrackSummary {
    let all: Vec<f64> = episodes
        .iter()
        .flat_map(|e| e.distances.iter().copied())
        .collect();
    let n = all.len().max(1) as f64;
    TrackSummary {
        per_step: summarise(method, episodes, protocol, control_times_s),
        mean_error: all.iter().sum::<f64>() / n,
        rms_error: (all.iter().map(|x| x * x).sum::<f64>() / n).sqrt(),
        max_error: all.iter().copied().fold(0.0, f64::max),
    }
}

/// Tracks every demonstration in `demo_path` with the run's own controller (latent PD with its
/// training gains, or PID for a NewtonianVAE) and with the oracle, and writes `track.json` and
/// `track.png` into the run folder. `progress` gets (demonstrations done, demonstrations in
/// all).
pub fn track_run(
    run: &RunPaths,
    demo_path: &Path,
    mut progress: impl FnMut(usize, usize),
) -> Result<TrackReport> {
    let device = cpu_device();
    let (config, model) = run.load_trained(&device)?;
    let sim = run.simulator(&config)?;
    let env = sim.kind();
    let demo = Dataset::load(demo_path)?;
    if demo.meta.env != Some(env) {
        return Err(Error::dataset(
            demo_path,
            format!(
                "holds {} demonstrations but the run {} controls {env}",
                demo.meta.source_name(),
                run.dir.display()
            ),
        ));
    }
    if demo.meta.simulator().as_ref() != Some(&sim) {
        return Err(Error::dataset(
            demo_path,
            format!(
                "was recorded in another configuration of {env} than the one the run {} controls (its dataset's)",
                run.dir.display()
            ),
        ));
    }
    let Some(states) = &demo.states else {
        return Err(Error::dataset(
            demo_path,
            "has no `states`; tracking compares the paths with the demonstrations' true states",
        ));
    };
    let (label, dt, mut latent_policy) = run_policy(&config, model, device.clone())?;
    let mut oracle = OraclePdPolicy::new(oracle_gains(env));
    let (mut latent_runs, mut oracle_runs, mut reference_paths) = (vec![], vec![], vec![]);
    for episode in 0..demo.episodes() {
        let mut reference = Reference::from_demo(&demo, states, episode);
        oracle_runs.push(track_episode(&sim, &mut oracle, &reference)?);
        reference.encode(latent_policy.encoder(), &device, dt);
        let mut record = track_episode(&sim, latent_policy.as_mut(), &reference)?;
        record.goal_latent = reference.h.last().cloned().unwrap_or_default();
        reference_paths.push(reference.states.iter().map(|s| s.q.clone()).collect());
        latent_runs.push(record);
        progress(episode + 1, demo.episodes());
    }
    let protocol = ReachConfig::for_env(env, 0);
    let label = label.as_str();
    let times = latent_policy.take_control_times();
    let report = TrackReport {
        env,
        demo: demo_path.to_path_buf(),
        source: demo.meta.source.clone(),
        demonstrations: demo.episodes(),
        steps: demo.steps(),
        distance_unit: protocol.distance_unit.clone(),
        methods: vec![
            summarise_tracking(label, &latent_runs, &protocol, &times),
            summarise_tracking("oracle PD (true state)", &oracle_runs, &protocol, &[]),
        ],
    };
    let title = format!("{env}: tracking {} ({})", demo.meta.source, label);
    save_track_plot(
        &run.dir.join(TRACK_FIGURE),
        &title,
        &reference_paths,
        &latent_runs,
        &oracle_runs,
        &report.methods,
        &protocol,
    )?;
    // Last, so that tracking interrupted while plotting is not taken for a finished one.
    crate::fsutil::write_json(&run.dir.join("track.json"), &report)?;
    Ok(report)
}
