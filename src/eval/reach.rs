//! Goal reaching: seeded start/goal pairs, a fixed horizon, per-step distance to the goal in the
//! true configuration space, success rate and control time.

use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;

use crate::control::Policy;
use crate::envs::{EnvConfig, EnvKind, FRAME_BYTES, Frame, State};

/// The protocol's settings for one environment.
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct ReachConfig {
    pub episodes: usize,
    /// Seed of the start/goal pairs (episode k uses ChaCha8 stream k).
    pub seed: u64,
    /// Control steps per episode, long enough for the oracle PD to converge.
    pub horizon: usize,
    /// An episode succeeds when its final distance is below this (units of `distance_unit`).
    pub success_threshold: f64,
    /// What distances measure.
    pub distance_unit: String,
}

impl ReachConfig {
    /// 50 episodes of 500 steps (10 s); point mass succeeds below 0.02 m,
    /// reacher below 0.1 rad of joint-space distance. Fetch: 250 steps (10 s at dt 0.04; the
    /// oracle needs 2.2 s) and FetchReach's goal tolerance, 0.05 m.
    pub fn for_env(env: EnvKind, seed: u64) -> Self {
        match env {
            EnvKind::PointMass => Self {
                episodes: 50,
                seed,
                horizon: 500,
                success_threshold: 0.02,
                distance_unit: "m".into(),
            },
            EnvKind::Reacher => Self {
                episodes: 50,
                seed,
                horizon: 500,
                success_threshold: 0.1,
                distance_unit: "rad (joint space)".into(),
            },
            EnvKind::Fetch => Self {
                episodes: 50,
                seed,
                horizon: 250,
                success_threshold: 0.05,
                distance_unit: "m".into(),
            },
        }
    }
}

/// Start and goal states of every episode (both at rest, uniform over the configuration space).
pub fn reach_tasks(env: &EnvConfig, config: &ReachConfig) -> Vec<(State, State)> {
    let sim = env.make();
    (0..config.episodes)
        .map(|k| {
            let mut rng = ChaCha8Rng::seed_from_u64(config.seed);
            rng.set_stream(k as u64);
            let start = sim.sample_config(&mut rng);
            let goal = sim.sample_config(&mut rng);
            let at_rest = |q: Vec<f64>| State {
                qd: vec![0.0; q.len()],
                q,
            };
            (at_rest(start), at_rest(goal))
        })
        .collect()
}

/// What one closed-loop episode did.
#[derive(Debug, Clone, Default, serde::Serialize)]
pub struct EpisodeRecord {
    /// Distance to the goal configuration before each step and after the last (`horizon + 1`).
    pub distances: Vec<f64>,
    /// True configuration `q` at the same steps.
    pub configs: Vec<Vec<f64>>,
    /// Latent `h` at each step (empty for the oracle).
    pub latents: Vec<Vec<f64>>,
    pub goal_latent: Vec<f64>,
    /// The goal's true configuration.
    pub goal_config: Vec<f64>,
    /// True velocity `qd` after the last step (joint rates, or Fetch's gripper velocity):
    /// whether an episode that ended short of its goal had stopped there.
    pub final_velocity: Vec<f64>,
    /// The fingertip's distance to the goal's after the last step (m; the reacher only, see
    /// [`crate::envs::Env::fingertip_distance_m`]).
    pub final_fingertip_distance_m: Option<f64>,
    /// Frames, when recorded (for the GIF), and the goal image.
    #[serde(skip)]
    pub frames: Vec<Frame>,
    #[serde(skip)]
    pub goal_frame: Option<Frame>,
}

/// Runs `policy` from `start` toward `goal` for `horizon` steps.
pub fn run_episode(
    env: &EnvConfig,
    policy: &mut dyn Policy,
    start: &State,
    goal: &State,
    horizon: usize,
    record_frames: bool,
) -> crate::Result<EpisodeRecord> {
    let mut sim = env.make();
    let mut goal_frame = [0u8; FRAME_BYTES];
    sim.set_state(goal)?;
    sim.render(&mut goal_frame);
    sim.set_state(start)?;
    let mut frame = [0u8; FRAME_BYTES];
    sim.render(&mut frame);
    let mut record = EpisodeRecord {
        goal_frame: record_frames.then_some(goal_frame),
        goal_config: goal.q.clone(),
        ..Default::default()
    };
    let mut u = vec![0.0; sim.action_dim()];
    let mut state = sim.state();
    policy.reset(&goal_frame, goal);
    record.goal_latent = policy.goal_latent();
    for step in 0..=horizon {
        record
            .distances
            .push(sim.config_distance(&state.q, &goal.q));
        record.configs.push(state.q.clone());
        if record_frames {
            record.frames.push(frame);
        }
        if step == horizon {
            record.final_fingertip_distance_m = sim.fingertip_distance_m(&state.q, &goal.q);
            record.final_velocity = state.qd.clone();
            break;
        }
        policy.act(&frame, &state, &mut u);
        let h = policy.latent();
        if !h.is_empty() {
            record.latents.push(h);
        }
        sim.step(&u);
        sim.render(&mut frame);
        state = sim.state();
    }
    Ok(record)
}

/// Aggregate results of one method over all episodes.
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct MethodSummary {
    pub method: String,
    pub per_step_mean: Vec<f64>,
    pub per_step_std: Vec<f64>,
    pub final_distances: Vec<f64>,
    /// Each episode's start, goal and final true configuration, in episode order: where a
    /// failed episode ended (at a joint limit, or short of the goal in free space).
    #[serde(default)]
    pub start_configs: Vec<Vec<f64>>,
    #[serde(default)]
    pub goal_configs: Vec<Vec<f64>>,
    #[serde(default)]
    pub final_configs: Vec<Vec<f64>>,
    /// Each episode's true velocity `qd` after the last step.
    #[serde(default)]
    pub final_velocities: Vec<Vec<f64>>,
    /// For latent policies, each episode's goal latent `h*` and the latent `h` of its first
    /// and last frames acted on (empty for the oracle): a failed episode that stopped with
    /// `h` at `h*` ended on a fold of the latent (two configurations, one `h`), one that
    /// stopped elsewhere was held off by a limit or the action bounds.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub goal_latents: Vec<Vec<f64>>,
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub start_latents: Vec<Vec<f64>>,
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub final_latents: Vec<Vec<f64>>,
    pub final_mean: f64,
    pub final_std: f64,
    /// The reacher's final fingertip distance to the goal's per episode (m), and its mean and
    /// std; empty and absent for the other envs.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub final_fingertip_distances_m: Vec<f64>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub final_fingertip_mean_m: Option<f64>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub final_fingertip_std_m: Option<f64>,
    pub success_rate: f64,
    /// Oscillation about the goal, per episode and averaged over episodes: the times the
    /// distance turns from falling to rising by more than half the success threshold
    /// ([`reversals`]), and the std of the distance over the last [`LATE_STEPS`] steps.
    #[serde(default)]
    pub reversals_mean: f64,
    #[serde(default)]
    pub late_distance_std_mean: f64,
    /// Control time per step (encode one frame + PD), microseconds; absent for the oracle.
    pub control_time_us_p50: Option<f64>,
    pub control_time_us_p99: Option<f64>,
}

/// The `eval.json` document.
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct ReachReport {
    pub env: EnvKind,
    /// The simulator's configuration where it is not the environment's default (a variant).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub env_config: Option<EnvConfig>,
    pub protocol: ReachConfig,
    pub methods: Vec<MethodSummary>,
}

fn mean_std(xs: &[f64]) -> (f64, f64) {
    let n = xs.len().max(1) as f64;
    let mean = xs.iter().sum::<f64>() / n;
    let var = xs.iter().map(|x| (x - mean).powi(2)).sum::<f64>() / n;
    (mean, var.sqrt())
}

/// The closing steps over which [`MethodSummary::late_distance_std_mean`] measures how much
/// the distance still moves.
pub const LATE_STEPS: usize = 100;

/// How many times `distances` turns from falling to rising, each turn by more than
/// `tolerance` (a rise of `tolerance` above the lowest point since the last turn, then a fall
/// of `tolerance` below the highest before the next): an overshoot or an orbit of the goal
/// counts, jitter under `tolerance` does not.
pub fn reversals(distances: &[f64], tolerance: f64) -> usize {
    let Some(&first) = distances.first() else {
        return 0;
    };
    let (mut falling, mut extreme, mut count) = (true, first, 0);
    for &d in &distances[1..] {
        if falling {
            if d < extreme {
                extreme = d;
            } else if d > extreme + tolerance {
                (falling, extreme, count) = (false, d, count + 1);
            }
        } else if d > extreme {
            extreme = d;
        } else if d < extreme - tolerance {
            (falling, extreme) = (true, d);
        }
    }
    count
}

fn percentile(sorted: &[f64], p: f64) -> f64 {
    if sorted.is_empty() {
        return f64::NAN;
    }
    let idx = ((sorted.len() - 1) as f64 * p).round() as usize;
    sorted[idx]
}

/// One latent per episode picked by `pick`, or empty where an episode has none (the oracle).
fn latent_column(
    episodes: &[EpisodeRecord],
    pick: impl Fn(&EpisodeRecord) -> Option<Vec<f64>>,
) -> Vec<Vec<f64>> {
    let column: Option<Vec<Vec<f64>>> = episodes
        .iter()
        .map(|e| pick(e).filter(|h| !h.is_empty()))
        .collect();
    column.unwrap_or_default()
}

/// Summarises episodes (and, for latent policies, their control times in seconds).
pub fn summarise(
    method: &str,
    episodes: &[EpisodeRecord],
    config: &ReachConfig,
    control_times_s: &[f64],
) -> MethodSummary {
    let steps = episodes.first().map_or(0, |e| e.distances.len());
    let (mut per_step_mean, mut per_step_std) = (vec![], vec![]);
    for t in 0..steps {
        let column: Vec<f64> = episodes.iter().map(|e| e.distances[t]).collect();
        let (m, s) = mean_std(&column);
        per_step_mean.push(m);
        per_step_std.push(s);
    }
    let finals: Vec<f64> = episodes
        .iter()
        .filter_map(|e| e.distances.last().copied())
        .collect();
    let (final_mean, final_std) = mean_std(&finals);
    let fingertip: Vec<f64> = episodes
        .iter()
        .filter_map(|e| e.final_fingertip_distance_m)
        .collect();
    let fingertip_mean_std = (!fingertip.is_empty()).then(|| mean_std(&fingertip));
    let successes = finals
        .iter()
        .filter(|&&d| d < config.success_threshold)
        .count();
    let per_episode = |f: &dyn Fn(&[f64]) -> f64| {
        mean_std(&episodes.iter().map(|e| f(&e.distances)).collect::<Vec<_>>()).0
    };
    let tolerance = config.success_threshold / 2.0;
    let reversals_mean = per_episode(&|d| reversals(d, tolerance) as f64);
    let late_distance_std_mean =
        per_episode(&|d| mean_std(&d[d.len().saturating_sub(LATE_STEPS)..]).1);
    let mut times: Vec<f64> = control_times_s.iter().map(|t| t * 1e6).collect();
    times.sort_by(f64::total_cmp);
    let timed = !times.is_empty();
    MethodSummary {
        method: method.to_string(),
        per_step_mean,
        per_step_std,
        final_distances: finals.clone(),
        start_configs: episodes
            .iter()
            .filter_map(|e| e.configs.first().cloned())
            .collect(),
        goal_configs: episodes.iter().map(|e| e.goal_config.clone()).collect(),
        final_configs: episodes
            .iter()
            .filter_map(|e| e.configs.last().cloned())
            .collect(),
        final_velocities: episodes.iter().map(|e| e.final_velocity.clone()).collect(),
        goal_latents: latent_column(episodes, |e| Some(e.goal_latent.clone())),
        start_latents: latent_column(episodes, |e| e.latents.first().cloned()),
        final_latents: latent_column(episodes, |e| e.latents.last().cloned()),
        final_mean,
        final_std,
        final_fingertip_mean_m: fingertip_mean_std.map(|(mean, _)| mean),
        final_fingertip_std_m: fingertip_mean_std.map(|(_, std)| std),
        final_fingertip_distances_m: fingertip,
        success_rate: successes as f64 / finals.len().max(1) as f64,
        reversals_mean,
        late_distance_std_mean,
        control_time_us_p50: timed.then(|| percentile(&times, 0.5)),
        control_time_us_p99: timed.then(|| percentile(&times, 0.99)),
    }
}

/// Runs every task with `policy` (reset per episode, so a latent policy's encoder is built
/// once), recording the frames of the first episode if `record_first`.
pub fn evaluate_reach(
    env: &EnvConfig,
    config: &ReachConfig,
    policy: &mut dyn Policy,
    record_first: bool,
    mut progress: impl FnMut(usize),
) -> crate::Result<Vec<EpisodeRecord>> {
    let tasks = reach_tasks(env, config);
    let mut records = Vec::with_capacity(tasks.len());
    for (k, (start, goal)) in tasks.iter().enumerate() {
        records.push(run_episode(
            env,
            policy,
            start,
            goal,
            config.horizon,
            record_first && k == 0,
        )?);
        progress(k + 1);
    }
    Ok(records)
}

/// Tracking results of one method over all demonstrations.
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct TrackSummary {
    /// Per-step error (mean, std over demonstrations), final error, and the fraction of
    /// demonstrations whose final error is under the env's goal-reaching threshold.
    #[serde(flatten)]
    pub per_step: MethodSummary,
    /// Mean error over every step of every demonstration.
    pub mean_error: f64,
    /// Root mean square of the same.
    pub rms_error: f64,
    /// Largest error seen.
    pub max_error: f64,
}

#[cfg(test)]
mod tests {
    use super::reversals;

    #[test]
    fn reversals_count_turns_larger_than_the_tolerance() {
        // A monotone approach has none; jitter under the tolerance is ignored.
        assert_eq!(reversals(&[1.0, 0.5, 0.2, 0.1, 0.0], 0.05), 0);
        assert_eq!(reversals(&[1.0, 0.5, 0.52, 0.49, 0.51, 0.3], 0.05), 0);
        // Two overshoots: down to 0.1, up to 0.4, down to 0.05, up to 0.2, settling at 0.
        let orbit = [1.0, 0.1, 0.4, 0.05, 0.2, 0.0];
        assert_eq!(reversals(&orbit, 0.05), 2);
        // A rise counts once however long it lasts; a larger tolerance hides the small one.
        assert_eq!(reversals(&[0.5, 0.0, 0.1, 0.2, 0.3, 0.0], 0.05), 1);
        assert_eq!(reversals(&orbit, 0.2), 1);
        assert_eq!(reversals(&[], 0.1), 0);
    }
}
