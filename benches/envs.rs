//! Environment throughput: one step + one 64x64 render per iteration, single thread.
//! Targets : point mass >= 20,000 frames/s, reacher >= 10,000 frames/s per core;
//! fetch >= 500 frames/s per core.

use criterion::{Criterion, Throughput, criterion_group, criterion_main};
use procl::envs::{EnvKind, FRAME_BYTES};

fn step_and_render(c: &mut Criterion) {
    let mut group = c.benchmark_group("env_step_render");
    group.throughput(Throughput::Elements(1));
    for kind in [EnvKind::PointMass, EnvKind::Reacher, EnvKind::Fetch] {
        let mut env = kind.make();
        env.reset(0).expect("reset");
        let mut frame = [0u8; FRAME_BYTES];
        let mut k = 0u32;
        group.bench_function(kind.name(), |b| {
            b.iter(|| {
                // A slowly rotating action keeps the system moving without leaving the arena.
                k = k.wrapping_add(1);
                let phase = k as f64 * 0.01;
                env.step(&[phase.sin(), phase.cos(), (0.7 * phase).sin()]);
                env.render(&mut frame);
                std::hint::black_box(&frame);
            })
        });
    }
    group.finish();
}

criterion_group! {
    name = benches;
    // No plots: criterion's plotters backend needs system fonts this project does not assume.
    config = Criterion::default().without_plots();
    targets = step_and_render
}
criterion_main!(benches);
