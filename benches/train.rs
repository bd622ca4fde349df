//! Training throughput: one optimiser step of the point-mass presets and the reacher preset
//! (batch 128, every frame of a sample encoded, all loss terms, backward, Adam), reported as
//! samples per second; benches/twin/ times the same step in PyTorch.
//! Uses every core burn-flex is given (rayon's global pool): 2 on the reference machine.

use criterion::{Criterion, Throughput, criterion_group, criterion_main};
use procl::Adam;
use procl::data::{CollectConfig, collect};
use procl::envs::EnvKind;
use procl::losses::procl_loss;
use procl::model::cpu_device;
use procl::train::{Method, Preset, TrainConfig, loss_inputs};

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
        // Each environment's own episodes (the reacher's 10 steps hold the sign term's reach).
        let data = collect(
            &CollectConfig {
                transitions: 2000,
                ..CollectConfig::new(env, 0)
            },
            |_| {},
        )
        .expect("dataset");
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
                model = Some(adam.step(config.learning_rate, current, &grads));
                step += 1;
            })
        });
    }
    group.finish();
}

criterion_group! {
    name = benches;
    config = Criterion::default().without_plots();
    targets = train_step
}
criterion_main!(benches);
