//! Shared set-up of the integration tests: tiny trained runs and training calls.

use std::path::Path;

use procl::data::{CollectConfig, Dataset, collect};
use procl::envs::EnvKind;
use procl::model::cpu_device;
use procl::train::{Method, Preset, RunPaths, TrainConfig, train};

/// Trains `config` on `data` into `dir` (continuing it with `resume`), which must succeed.
pub fn train_into(config: &TrainConfig, data: &Dataset, dir: &Path, resume: bool) {
    procl::allocator::retain_freed_memory();
    train(
        config,
        data,
        &RunPaths::new(dir),
        resume,
        &cpu_device(),
        |_, _| {},
    )
    .unwrap();
}

/// Trains `config` on `data` into `dir`, which must fail; the error's message.
pub fn train_error(config: &TrainConfig, data: &Dataset, dir: &Path, resume: bool) -> String {
    procl::allocator::retain_freed_memory();
    train(
        config,
        data,
        &RunPaths::new(dir),
        resume,
        &cpu_device(),
        |_, _| {},
    )
    .unwrap_err()
    .to_string()
}

/// A ProCL run in `dir/run` with a 4-channel trunk, trained for `steps` at batch `batch_size`
/// (a checkpoint at the end, the orientation searched every `search_every` steps, 0: never) on
/// `transitions` random-control transitions of `env` (seed 1) in episodes of `episode_len`.
pub fn tiny_procl_run(
    dir: &Path,
    env: EnvKind,
    (transitions, episode_len): (usize, usize),
    (steps, batch_size, search_every): (u64, usize, u64),
) -> RunPaths {
    procl::allocator::retain_freed_memory();
    let data = collect(
        &CollectConfig {
            transitions,
            episode_len,
            ..CollectConfig::new(env, 1)
        },
        |_| {},
    )
    .unwrap();
    let mut config = TrainConfig::preset(Preset::Procl, Method::Procl, env);
    (
        config.steps,
        config.batch_size,
        config.checkpoint_every,
        config.orientation_search_every,
    ) = (steps, batch_size, steps, search_every);
    config.model.encoder.trunk_channels = [4, 4];
    let run = dir.join("run");
    train_into(&config, &data, &run, false);
    RunPaths::new(run)
}
