//! Demonstrations and trajectory tracking: the generator's file, the expert's fidelity, the
//! tracking loop's encoding budget and outputs, and bad input on the command line.

use procl::control::{LatentPdPolicy, OraclePdPolicy, PdController, Policy, oracle_gains};
use procl::control::{PathShape, ReferenceConfig, generate_reference};
use procl::data::Dataset;
use procl::envs::EnvKind;
use procl::eval::{Reference, track_episode, track_run};
use procl::model::cpu_device;
use procl::train::{Method, Preset, TrainConfig};

use super::support::tiny_procl_run;

fn small_reference(env: EnvKind, shape: PathShape, seed: u64) -> ReferenceConfig {
    ReferenceConfig {
        episodes: 2,
        steps: 120,
        ..ReferenceConfig::new(env, shape, seed)
    }
}

#[test]
fn demonstrations_are_seeded_files_in_the_dataset_layout() {
    let dir = tempfile::tempdir().unwrap();
    let config = small_reference(EnvKind::Reacher, PathShape::FigureEight, 5);
    let data = generate_reference(&config, |_| {}).unwrap();
    assert_eq!(data.meta.source, "demonstration:figure-eight");
    assert_eq!((data.episodes(), data.steps()), (2, 120));
    let path = dir.path().join("demo.npz");
    data.save(&path, false).unwrap();
    assert_eq!(Dataset::load(&path).unwrap(), data);
    // Same seed, same bytes; another seed, another path.
    let again = dir.path().join("again.npz");
    generate_reference(&config, |_| {})
        .unwrap()
        .save(&again, false)
        .unwrap();
    assert_eq!(
        std::fs::read(&path).unwrap(),
        std::fs::read(&again).unwrap()
    );
    let other = generate_reference(
        &small_reference(EnvKind::Reacher, PathShape::FigureEight, 6),
        |_| {},
    )
    .unwrap();
    assert_ne!(other.states, data.states);
    // Bad sizes are refused by name.
    let err = generate_reference(
        &ReferenceConfig {
            episodes: 0,
            ..config.clone()
        },
        |_| {},
    )
    .unwrap_err();
    assert!(err.to_string().contains("episodes"), "{err}");
}

#[test]
fn the_oracle_follows_every_shape_in_every_env() {
    for env in [EnvKind::PointMass, EnvKind::Reacher, EnvKind::Fetch] {
        for shape in [PathShape::Circle, PathShape::FigureEight, PathShape::Spline] {
            let demo = generate_reference(&small_reference(env, shape, 1), |_| {}).unwrap();
            // The reference moves: otherwise a tracker that stands still would score well.
            let first = demo.config(0, 0).unwrap();
            let last = demo.config(0, demo.steps()).unwrap();
            let travelled: f64 = first.iter().zip(&last).map(|(a, b)| (a - b).abs()).sum();
            assert!(travelled > 1e-3, "{env} {shape:?} does not move");
            let reference = Reference::from_demo(&demo, demo.states.as_ref().unwrap(), 0);
            let mut oracle = OraclePdPolicy::new(oracle_gains(env));
            let record = track_episode(&env.into(), &mut oracle, &reference).unwrap();
            assert_eq!(record.distances.len(), demo.steps() + 1);
            // PD lags a moving reference; it must still do far better than standing still at
            // the start (the error of a tracker that ignores the reference).
            let sim = env.make();
            let mean = |xs: Vec<f64>| xs.iter().sum::<f64>() / xs.len() as f64;
            let standing = mean(
                (0..=demo.steps())
                    .map(|t| sim.config_distance(&first, &demo.config(0, t).unwrap()))
                    .collect(),
            );
            let tracking = mean(record.distances.clone());
            assert!(
                tracking < 0.25 * standing,
                "{env} {shape:?}: oracle error {tracking} vs standing still {standing}"
            );
        }
    }
}

#[test]
fn latent_tracking_encodes_each_frame_once_and_uses_the_references() {
    let env = EnvKind::PointMass;
    let device = cpu_device();
    let config = TrainConfig::preset(Preset::Procl, Method::Procl, env);
    let model = config.model.init(0, &device).unwrap();
    let demo = generate_reference(&small_reference(env, PathShape::Circle, 2), |_| {}).unwrap();
    let mut reference = Reference::from_demo(&demo, demo.states.as_ref().unwrap(), 1);
    reference.encode(&model.encoder, &device, 0.02);
    assert_eq!(reference.h.len(), demo.steps() + 1);
    // v*_t is the backward difference of the reference's encodings.
    let t = 17;
    for i in 0..2 {
        let expected = (reference.h[t][i] - reference.h[t - 1][i]) / 0.02;
        assert!((reference.v[t][i] - expected).abs() < 1e-9);
    }
    let mut policy = LatentPdPolicy::new(
        model.encoder,
        device,
        PdController { kp: 10.0, kd: 2.0 },
        0.02,
    );
    let record = track_episode(&env.into(), &mut policy as &mut dyn Policy, &reference).unwrap();
    // The reference frames were encoded in one batch beforehand; the loop encodes each new
    // frame once.
    assert_eq!(policy.frames_encoded, demo.steps());
    assert_eq!(record.latents.len(), demo.steps());
    assert_eq!(record.configs.len(), demo.steps() + 1);
    // The final target is the last reference latent.
    assert_eq!(policy.goal_latent(), reference.h[demo.steps()]);
    // Starts on the reference.
    assert!(record.distances[0] < 1e-6);
}

#[test]
fn track_writes_its_outputs_and_refuses_another_envs_demo() {
    let dir = tempfile::tempdir().unwrap();
    let env = EnvKind::PointMass;
    let run = tiny_procl_run(dir.path(), env, (120, 40), (2, 8, 1));

    let demo_path = dir.path().join("circle.npz");
    let demo = generate_reference(&small_reference(env, PathShape::Circle, 0), |_| {}).unwrap();
    demo.save(&demo_path, false).unwrap();
    let mut calls = vec![];
    let report = track_run(&run, &demo_path, |done, total| calls.push((done, total))).unwrap();
    assert_eq!(calls, vec![(1, 2), (2, 2)]);
    assert!(run.dir.join("track.png").exists());
    let json: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(run.dir.join("track.json")).unwrap())
            .unwrap();
    assert_eq!(json["source"], "demonstration:circle");
    let methods = json["methods"].as_array().unwrap();
    assert_eq!(methods.len(), 2);
    for (m, summary) in methods.iter().zip(&report.methods) {
        for key in [
            "method",
            "per_step_mean",
            "mean_error",
            "rms_error",
            "max_error",
        ] {
            assert!(m.get(key).is_some(), "track.json lacks {key}");
        }
        assert_eq!(
            m["per_step_mean"].as_array().unwrap().len(),
            demo.steps() + 1
        );
        assert_eq!(m["mean_error"].as_f64().unwrap(), summary.mean_error);
        assert!(summary.rms_error >= summary.mean_error && summary.max_error >= summary.rms_error);
    }

    let reacher_demo = dir.path().join("reacher.npz");
    generate_reference(
        &small_reference(EnvKind::Reacher, PathShape::Circle, 0),
        |_| {},
    )
    .unwrap()
    .save(&reacher_demo, false)
    .unwrap();
    let err = track_run(&run, &reacher_demo, |_, _| {})
        .unwrap_err()
        .to_string();
    assert!(
        err.contains("reacher.npz") && err.contains("point-mass"),
        "{err}"
    );
}

#[test]
fn fetch_tracking_draws_its_paths_in_3d() {
    let dir = tempfile::tempdir().unwrap();
    let env = EnvKind::Fetch;
    let run = tiny_procl_run(dir.path(), env, (60, 20), (1, 4, 0));
    let demo_path = dir.path().join("fetch.npz");
    let demo = ReferenceConfig {
        episodes: 1,
        steps: 20,
        ..ReferenceConfig::new(env, PathShape::Spline, 0)
    };
    generate_reference(&demo, |_| {})
        .unwrap()
        .save(&demo_path, false)
        .unwrap();
    let report = track_run(&run, &demo_path, |_, _| {}).unwrap();
    assert_eq!(report.env, EnvKind::Fetch);
    assert_eq!(report.methods[0].per_step.per_step_mean.len(), 21);
    let png = std::fs::read(run.dir.join("track.png")).unwrap();
    assert_eq!(&png[1..4], b"PNG");
}
