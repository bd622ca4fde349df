//! One latent PD control step from a 64x64 frame (encode the new frame + PD law), on one
//! thread, and beside it one CEM-MPC step on the same latent (encode + plan through the
//! learned dynamics, horizon 10): the run-time cost ratio ProCL is about. Target: PD <= 0.1
//! ms. Weights are freshly initialised: the cost does not depend on their values.

use criterion::{Criterion, criterion_group, criterion_main};
use procl::baselines::mpc::{CemMpc, MpcConfig, MpcPolicy};
use procl::control::{LatentPdPolicy, PdController, Policy};
use procl::envs::{EnvKind, FRAME_BYTES, State};
use procl::model::{ModelConfig, cpu_device};
use procl::train::{Method, Preset, TrainConfig};

fn control_step(c: &mut Criterion) {
    // burn-flex parallelises on rayon's current pool; a 1-thread pool makes this one core.
    let pool = rayon::ThreadPoolBuilder::new()
        .num_threads(1)
        .build()
        .expect("rayon pool");
    let mut group = c.benchmark_group("control_step_1thread");
    // The point-mass presets' trunk subsamples twice; the reacher's second convolution keeps
    // 32x32 maps (stride 1), four times its arithmetic.
    for (preset, env_kind) in [
        (Preset::Procl, EnvKind::PointMass),
        (Preset::Paper, EnvKind::PointMass),
        (Preset::Procl, EnvKind::Reacher),
    ] {
        let config: ModelConfig = TrainConfig::preset(preset, Method::Procl, env_kind).model;
        let device = cpu_device();
        let model = config.init(0, &device).expect("model");
        let law =
            CemMpc::new(model.dynamics, device.clone(), MpcConfig::default(), 0.02).expect("mpc");
        let mut mpc = MpcPolicy::new(model.encoder.clone(), device.clone(), law, 0.02);
        let mut policy = LatentPdPolicy::new(
            model.encoder,
            device,
            PdController { kp: 10.0, kd: 2.0 },
            0.02,
        );
        let mut env = env_kind.make();
        env.reset(0).expect("reset");
        let mut frame = [0u8; FRAME_BYTES];
        env.render(&mut frame);
        let state = State {
            q: vec![0.0; 2],
            qd: vec![0.0; 2],
        };
        policy.reset(&frame, &state);
        mpc.reset(&frame, &state);
        let mut u = [0.0; 2];
        let name = format!("{preset:?}_{env_kind:?}").to_lowercase();
        group.bench_function(format!("{name}_pd"), |b| {
            pool.install(|| b.iter(|| policy.act(std::hint::black_box(&frame), &state, &mut u)))
        });
        group.bench_function(format!("{name}_mpc_h10"), |b| {
            pool.install(|| b.iter(|| mpc.act(std::hint::black_box(&frame), &state, &mut u)))
        });
    }
    group.finish();
}

criterion_group! {
    name = benches;
    config = Criterion::default().without_plots();
    targets = control_step
}
criterion_main!(benches);
