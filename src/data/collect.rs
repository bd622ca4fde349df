//! Random-control data collection (paper section IV): uniform actions held for 1-5 steps, episodes
//! from uniformly random configurations at rest, every episode seeded from (seed, episode).

use ndarray::{Array3, Array5};
use rand::{RngExt, SeedableRng};
use rand_chacha::ChaCha8Rng;

use super::store::{DATASET_FORMAT_VERSION, Dataset, DatasetMeta};
use crate::envs::{Env, EnvConfig, EnvKind, FRAME_PX, Frame, State};
use crate::error::{Error, Result};

/// What to collect.
#[derive(Debug, Clone, PartialEq)]
pub struct CollectConfig {
    /// Environment to drive, with its configuration (the default, or a variant).
    pub env: EnvConfig,
    /// Record the data as custom: training then uses the recipe for data from elsewhere,
    /// which knows nothing of the environment, while the metadata keeps the configuration
    /// for evaluation in the simulator.
    pub as_custom: bool,
    /// Total transitions (episodes x steps per episode).
    pub transitions: usize,
    /// Steps per episode `T`; the dataset holds `T + 1` frames per episode.
    pub episode_len: usize,
    /// Master seed: episode `k` draws from ChaCha8 stream `k` of this seed.
    pub seed: u64,
    /// An action is held for a uniformly drawn 1..=`max_hold_steps` steps.
    pub max_hold_steps: usize,
}

impl CollectConfig {
    /// The paper's defaults for `env`: 10,000 transitions (Fetch: 50,000) in episodes of 100 steps
    /// (reacher: 10 steps).
    pub fn new(env: EnvKind, seed: u64) -> Self {
        Self {
            env: env.into(),
            as_custom: false,
            transitions: match env {
                EnvKind::PointMass | EnvKind::Reacher => 10_000,
                EnvKind::Fetch => 50_000,
            },
            // Random torques drive the light arm into its joint limits and hold it there: over
            // 100-step episodes 14.6% of the frames lie within 10 degrees of a shoulder limit and
            // 21.7% of a wrist limit (6.3% and 12.5% if uniform). CPC spreads the latent over
            // where the frames are, and the preset's latent hooked at the shoulder's ends, where
            // PD failed most goals. Episodes of 10 steps from uniform starts give 6.2% and 15.5%,
            // and the preset reached 84.5% on seed 0 against 74% (docs/design.md, "Reacher").
            episode_len: match env {
                EnvKind::Reacher => 10,
                EnvKind::PointMass | EnvKind::Fetch => 100,
            },
            seed,
            max_hold_steps: 5,
        }
    }

    /// The dataset metadata's `env` and `env_config` for this collection: the environment, or
    /// `custom` with `as_custom`; the configuration where `env` does not imply it.
    pub fn recorded_env(&self) -> (Option<EnvKind>, Option<EnvConfig>) {
        let env = (!self.as_custom).then(|| self.env.kind());
        let config = (self.as_custom || !self.env.is_default()).then(|| self.env.clone());
        (env, config)
    }

    /// Number of episodes, after checking that the sizes are usable.
    pub fn episodes(&self) -> Result<usize> {
        if self.transitions == 0 {
            return Err(Error::config("transitions", "must be at least 1"));
        }
        if self.episode_len < 2 {
            return Err(Error::config(
                "episode_len",
                "must be at least 2 (a training sample spans 3 frames)",
            ));
        }
        if self.max_hold_steps == 0 {
            return Err(Error::config("max_hold_steps", "must be at least 1"));
        }
        let len = self.episode_len.min(self.transitions);
        if !self.transitions.is_multiple_of(len) {
            return Err(Error::config(
                "transitions",
                format!(
                    "{} is not a multiple of the episode length {len}",
                    self.transitions
                ),
            ));
        }
        Ok(self.transitions / len)
    }
}

/// A dataset being rolled out: the arrays of `episodes` episodes of `steps` steps of one env,
/// filled one step at a time (by [`collect`] and by the demonstration generator).
pub(crate) struct Recording {
    env: EnvKind,
    obs: Array5<u8>,
    actions: Array3<f32>,
    states: Array3<f32>,
    frame: Frame,
}

impl Recording {
    pub(crate) fn new(env: &dyn Env, episodes: usize, steps: usize) -> Self {
        let (du, dq) = (env.action_dim(), env.config_dim());
        Self {
            env: env.kind(),
            obs: Array5::zeros((episodes, steps + 1, FRAME_PX, FRAME_PX, 3)),
            actions: Array3::zeros((episodes, steps, du)),
            states: Array3::zeros((episodes, steps + 1, 2 * dq)),
            frame: [0; crate::envs::FRAME_BYTES],
        }
    }

    /// Renders `env` and stores the frame and the true state as frame `t` of `episode`;
    /// returns the state.
    pub(crate) fn observe(&mut self, env: &mut dyn Env, episode: usize, t: usize) -> State {
        env.render(&mut self.frame);
        let flat = self.obs.slice_mut(ndarray::s![episode, t, .., .., ..]);
        // A freshly zeroed Array5 is in standard layout, so each frame slice is contiguous.
        if let Some(dst) = flat.into_slice() {
            dst.copy_from_slice(&self.frame);
        }
        let state = env.state();
        for (i, x) in state.to_vec().into_iter().enumerate() {
            self.states[[episode, t, i]] = x as f32;
        }
        state
    }

    /// Stores the action taken at step `t` of `episode`.
    pub(crate) fn act(&mut self, episode: usize, t: usize, u: &[f64]) {
        for (i, &a) in u.iter().enumerate() {
            self.actions[[episode, t, i]] = a as f32;
        }
    }

    /// The finished dataset, with its metadata.
    pub(crate) fn finish(self, control_dt_s: f64, seed: u64, source: String) -> Result<Dataset> {
        let meta = DatasetMeta {
            format_version: DATASET_FORMAT_VERSION,
            env: Some(self.env),
            control_dt_s,
            seed,
            source,
            procl_version: env!("CARGO_PKG_VERSION").into(),
            env_config: None,
        };
        Dataset::new(meta, self.obs, self.actions, Some(self.states))
    }
}

/// Collects a dataset; `progress` is called with the number of finished transitions.
pub fn collect(config: &CollectConfig, mut progress: impl FnMut(usize)) -> Result<Dataset> {
    let episodes = config.episodes()?;
    let steps = config.episode_len.min(config.transitions);
    config.env.validate()?;
    let mut env = config.env.make();
    let du = env.action_dim();
    let mut recording = Recording::new(env.as_ref(), episodes, steps);

    for episode in 0..episodes {
        let mut rng = ChaCha8Rng::seed_from_u64(config.seed);
        rng.set_stream(episode as u64);
        let start = env.sample_config(&mut rng);
        env.set_state(&State {
            qd: vec![0.0; start.len()],
            q: start,
        })?;
        let mut action = vec![0.0; du];
        let mut hold_left = 0;
        for t in 0..=steps {
            recording.observe(env.as_mut(), episode, t);
            if t == steps {
                break;
            }
            if hold_left == 0 {
                action
                    .iter_mut()
                    .for_each(|a| *a = rng.random_range(-1.0..=1.0));
                hold_left = rng.random_range(1..=config.max_hold_steps);
            }
            hold_left -= 1;
            recording.act(episode, t, &action);
            env.step(&action);
        }
        progress((episode + 1) * steps);
    }
    let mut data = recording.finish(env.control_dt_s(), config.seed, "random-control".into())?;
    (data.meta.env, data.meta.env_config) = config.recorded_env();
    Ok(data)
}

/// Steps between the frames of a [`render_strip`].
pub const STRIP_STRIDE: usize = 10;

/// Renders `frames` frames (every [`STRIP_STRIDE`]th step) of a seeded random-control episode
/// side by side, each upscaled `scale` times: what a model trained on `env` sees.
pub fn render_strip(
    env: &EnvConfig,
    seed: u64,
    frames: usize,
    scale: usize,
) -> Result<crate::RgbImage> {
    if frames == 0 || scale == 0 {
        return Err(Error::config("frames/scale", "must be at least 1"));
    }
    let mut config = CollectConfig {
        env: env.clone(),
        ..CollectConfig::new(env.kind(), seed)
    };
    config.transitions = ((frames - 1) * STRIP_STRIDE).max(2);
    config.episode_len = config.transitions;
    let data = collect(&config, |_| {})?;
    let side = FRAME_PX * scale;
    let gap = scale.max(1);
    let mut image = crate::RgbImage::new(frames * side + (frames - 1) * gap, side);
    image.pixels.fill(255);
    for k in 0..frames {
        image.blit_scaled(
            data.frame(0, k * STRIP_STRIDE),
            FRAME_PX,
            k * (side + gap),
            0,
            scale,
        );
    }
    Ok(image)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn sizes_are_checked() {
        let mut config = CollectConfig::new(EnvKind::PointMass, 0);
        config.transitions = 0;
        assert!(collect(&config, |_| {}).is_err());
        config.transitions = 150;
        assert!(
            collect(&config, |_| {})
                .unwrap_err()
                .to_string()
                .contains("multiple")
        );
        config.transitions = 30;
        let data = collect(&config, |_| {}).unwrap();
        assert_eq!(data.obs.shape(), &[1, 31, 64, 64, 3]);
    }

    #[test]
    fn short_reacher_episodes_keep_the_arm_off_its_shoulder_limits() {
        // The share of frames within 10 degrees of a shoulder limit (+-160 degrees): random
        // torques pile long episodes up against the limits (uniform: 6.25%).
        let near_limit_share = |episode_len: usize| {
            let config = CollectConfig {
                transitions: 4000,
                episode_len,
                ..CollectConfig::new(EnvKind::Reacher, 0)
            };
            let data = collect(&config, |_| {}).unwrap();
            let states = data.states.unwrap();
            let shoulder = states.index_axis(ndarray::Axis(2), 0);
            let near = shoulder
                .iter()
                .filter(|q| q.abs().to_degrees() > 150.0)
                .count();
            near as f64 / shoulder.len() as f64
        };
        assert_eq!(CollectConfig::new(EnvKind::Reacher, 0).episode_len, 10);
        let (short, long) = (near_limit_share(10), near_limit_share(100));
        // Measured: 8.4% and 17.1%.
        assert!(
            short < 0.10 && long > 0.14,
            "10 steps: {short}, 100 steps: {long}"
        );
    }

    #[test]
    fn actions_are_held_and_bounded() {
        let mut config = CollectConfig::new(EnvKind::Reacher, 3);
        (config.transitions, config.episode_len) = (200, 200);
        let data = collect(&config, |_| {}).unwrap();
        let a = &data.actions;
        assert!(a.iter().all(|x| (-1.0..=1.0).contains(x)));
        // Held for 1-5 steps: at most 5 equal in a row, and some repeats exist.
        let (mut run, mut max_run, mut repeats) = (1, 1, 0);
        for t in 1..a.shape()[1] {
            if a[[0, t, 0]] == a[[0, t - 1, 0]] {
                run += 1;
                repeats += 1;
            } else {
                run = 1;
            }
            max_run = max_run.max(run);
        }
        assert!(
            max_run <= 5 && repeats > 20,
            "max_run {max_run}, repeats {repeats}"
        );
    }
}
