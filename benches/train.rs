//! Training throughput: one optimiser step of the point-mass presets and the reacher preset
//! (batch 128, every frame of a sample encoded, all loss terms, backward, Adam), reported as
//! samples per second; benches/twin/ times the same step in PyTorch. Also the NewtonianVAE's
//! reacher step (16 windows of 10 frames: 160 encoded, 128 decoded), in windows per second,
//! with its decoder on the host as training on the CPU runs it and, for reference, in burn's
//! graph as on other devices.
//! Uses every core burn-flex is given (rayon's global pool): 2 on the reference machine.

use burn::tensor::{Tensor, TensorData};
use criterion::{Criterion, Throughput, criterion_group, criterion_main};
use procl::Adam;
use procl::baselines::nvae::{ElboInputs, Targets, elbo_loss};
use procl::data::{CollectConfig, Dataset, collect};
use procl::envs::EnvKind;
use procl::losses::procl_loss;
use procl::model::{cpu_device, frames_to_tensor};
use procl::train::{Method, Preset, TrainConfig, WindowFrames, loss_inputs, window_frames};

/// 2000 transitions of `env`'s own episodes (the reacher's 10 steps hold the sign term's reach).
fn dataset(env: EnvKind) -> Dataset {
    collect(
        &CollectConfig {
            transitions: 2000,
            ..CollectConfig::new(env, 0)
        },
        |_| {},
    )
    .expect("dataset")
}

fn train_step(c: &mut Criterion) {
    // As the binary does at start (src/allocator.rs), so the figure is the one users get.
    procl::allocator::retain_freed_memory();
    let mut group = c.benchmark_group("train_step");
    group.sample_size(10);
    let cases = [
        (EnvKind::PointMass, Preset::Procl),
        (EnvKind::PointMass, Preset::Paper),
        (EnvKind::Reacher, Preset::Procl),
    ];
    for (env, preset) in cases {
        let data = dataset(env);
        let config = TrainConfig::preset(preset, Method::Procl, env);
        let device = cpu_device().autodiff();
        let mut model = Some(config.model.init(0, &device).expect("model"));
        let mut adam = Adam::default();
        let mut step = 0u64;
        group.throughput(Throughput::Elements(config.batch_size as u64));
        let name = format!("{env}_{preset:?}").to_lowercase();
        group.bench_function(name, |b| {
            b.iter(|| {
                let current = model.take().expect("model");
                let (inputs, trunk) = loss_inputs(&current, &data, &config, step, &device);
                let terms = procl_loss(
                    &config.loss,
                    &current.dynamics,
                    inputs,
                    data.meta.control_dt_s,
                );
                let mut grads = terms.total.backward();
                if let Some(trunk) = trunk {
                    trunk.backward(&mut grads);
                }
                model = Some(adam.step(
                    config.learning_rate,
                    config.gradient_clip_percentile,
                    current,
                    &grads,
                ));
                step += 1;
            })
        });
    }
    group.finish();
}

fn nvae_train_step(c: &mut Criterion) {
    procl::allocator::retain_freed_memory();
    let mut group = c.benchmark_group("train_step");
    group.sample_size(10);
    let env = EnvKind::Reacher;
    let data = dataset(env);
    let config = TrainConfig::preset(Preset::Procl, Method::Nvae, env);
    let nvae = config
        .nvae
        .as_ref()
        .expect("the nvae preset has nvae settings");
    let device = cpu_device().autodiff();
    let mut model = Some(nvae.init(0, &device).expect("model"));
    let mut adam = Adam::default();
    let (windows, len, du) = (config.batch_size, nvae.sequence_len, data.action_dim());
    let dt = nvae.dt(data.meta.control_dt_s);
    let data = &data;
    let mut step = 0usize;
    group.throughput(Throughput::Elements(windows as u64));
    for (name, decode_on_host) in [("reacher_nvae", true), ("reacher_nvae_burn_decoder", false)] {
        group.bench_function(name, |b| {
            b.iter(|| {
                let current = model.take().expect("model");
                // A window from the start of each of `windows` episodes, other ones each step.
                let starts: Vec<(usize, usize)> = (0..windows)
                    .map(|k| ((step * windows + k) % data.episodes(), 0))
                    .collect();
                let WindowFrames { frames, targets, u } = window_frames(data, &starts, len);
                let u = Tensor::from_data(TensorData::new(u, [targets.len(), du]), &device);
                let (mean, log_std, tape) = current.encoder.posterior_training(&frames, &device);
                let inputs = ElboInputs {
                    posterior_noise: mean.zeros_like(),
                    prior_noise: u.zeros_like(),
                    mean,
                    log_std,
                    targets: if decode_on_host {
                        Targets::Frames(&targets)
                    } else {
                        Targets::Pixels(frames_to_tensor(targets.iter().copied(), &device))
                    },
                    u,
                    windows,
                };
                let terms = elbo_loss(&current, nvae, inputs, 1.0, dt);
                let mut grads = terms.total.backward();
                terms.host_backward(tape).backward(&mut grads);
                model = Some(adam.step(
                    config.learning_rate,
                    config.gradient_clip_percentile,
                    current,
                    &grads,
                ));
                step += 1;
            })
        });
    }
    group.finish();
}

criterion_group! {
    name = benches;
    config = Criterion::default().without_plots();
    targets = train_step, nvae_train_step
}
criterion_main!(benches);
