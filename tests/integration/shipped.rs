//! The trained runs shipped in `models/`: each loads, and the point mass's reaches its goals.

use std::path::Path;

use procl::envs::EnvKind;
use procl::eval::{ReachConfig, evaluate_run};
use procl::model::cpu_device;
use procl::train::RunPaths;

fn shipped(env: EnvKind) -> std::path::PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("models")
        .join(env.name())
}

#[test]
fn every_shipped_run_loads_as_its_environments_procl_run() {
    for env in [EnvKind::PointMass, EnvKind::Reacher, EnvKind::Fetch] {
        let (config, model) = RunPaths::new(shipped(env))
            .load_trained(&cpu_device())
            .unwrap_or_else(|e| panic!("{env}: {e}"));
        assert_eq!(config.env, Some(env));
        assert_eq!(config.method, procl::train::Method::Procl);
        let procl::train::TrainedModel::Procl(model) = model else {
            panic!("{env}: a ProCL run loads as ProCL");
        };
        // The reacher's polar head sits on the hub its frames turn about, the shoulder at the
        // image centre (within a pixel: 2/64 in the head's coordinates); the others have none.
        match model.encoder.polar_centre() {
            Some([x, y]) => assert!(
                env == EnvKind::Reacher && x.hypot(y) < 2.0 / 64.0,
                "{env}: centre {x}, {y}"
            ),
            None => assert_ne!(env, EnvKind::Reacher),
        }
    }
}

#[test]
fn the_shipped_point_mass_run_reaches_its_goals() {
    // Evaluation writes its outputs into the run folder: work on a copy.
    let dir = tempfile::tempdir().unwrap();
    for file in ["config.json", "model.safetensors"] {
        std::fs::copy(
            shipped(EnvKind::PointMass).join(file),
            dir.path().join(file),
        )
        .unwrap();
    }
    let protocol = ReachConfig {
        episodes: 10,
        ..ReachConfig::for_env(EnvKind::PointMass, 1000)
    };
    let report = evaluate_run(&RunPaths::new(dir.path()), &protocol, |_| {}).unwrap();
    assert_eq!(
        report.methods[0].success_rate, 1.0,
        "{:?}",
        report.methods[0]
    );
}

#[test]
fn the_readout_check_sees_a_known_turn_of_the_shipped_point_mass_latent() {
    let (_, model) = RunPaths::new(shipped(EnvKind::PointMass))
        .load_model(&cpu_device())
        .unwrap();
    let env = procl::envs::EnvConfig::from(EnvKind::PointMass);
    let check = |model: &procl::model::ProclModel| {
        procl::eval::readout_check(&env, &model.encoder, &cpu_device())
            .unwrap()
            .expect("random control spans both actions")
    };
    let before = check(&model);
    assert!(!before.mirrored);
    let turn = before.turn_deg.unwrap();
    // The point mass answers its actions alike everywhere: the estimate is tight.
    assert!(before.spread_deg.unwrap() < 5.0, "{before:?}");
    // Turn h by 30 degrees more, against the turn found (its sign from the fitted response).
    let b = &before.response;
    let sign = if b[2] - b[1] > 0.0 { 1.0f32 } else { -1.0 };
    let (c, s) = (30f32.to_radians().cos(), sign * 30f32.to_radians().sin());
    let after = check(&model.reorient_latent(&[c, -s, s, c]));
    let want = turn + 30.0;
    let got = after.turn_deg.unwrap();
    assert!(
        (got - want).abs() < 1.0,
        "turned by 30 more: {got}, want {want}"
    );
}
