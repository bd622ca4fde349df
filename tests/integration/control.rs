//! Control and evaluation: the oracle upper bound, the closed loop's encoding budget, the
//! eval.json schema, and the demo end to end on a tiny budget (the CI smoke test).

use procl::baselines::mpc::MpcConfig;
use procl::control::{LatentPdPolicy, PdController, Policy};
use procl::envs::EnvKind;
use procl::eval::{
    Controller, ReachConfig, evaluate_oracle, evaluate_run, evaluate_run_with, reach_tasks,
    run_episode,
};
use procl::model::cpu_device;
use procl::train::{Method, Preset, TrainConfig};

use super::support::tiny_procl_run;

#[test]
fn oracle_reaches_every_goal_in_every_env() {
    // How far the goals start, in success thresholds: Fetch's 0.05 m (FetchReach's tolerance) is
    // a sixth of its workspace side, so its random goals start only ~4 thresholds away on
    // average (0.2 m between two uniform points of the 0.3 m cube), fewer over 10 episodes.
    for (env, start_in_thresholds) in [
        (EnvKind::PointMass, 10.0),
        (EnvKind::Reacher, 10.0),
        (EnvKind::Fetch, 2.0),
    ] {
        let mut protocol = ReachConfig::for_env(env, 7);
        protocol.episodes = 10;
        let oracle = evaluate_oracle(&env.into(), &protocol).unwrap();
        assert_eq!(
            oracle.success_rate, 1.0,
            "{env}: {:?}",
            oracle.final_distances
        );
        assert_eq!(oracle.per_step_mean.len(), protocol.horizon + 1);
        // Distances start large and end far below the threshold.
        assert!(
            oracle.per_step_mean[0] > start_in_thresholds * protocol.success_threshold,
            "{env}: goals start {} away",
            oracle.per_step_mean[0]
        );
        assert!(oracle.final_mean < 0.1 * protocol.success_threshold);
        // Each episode's start, goal and final configuration, in task order.
        let tasks = reach_tasks(&env.into(), &protocol);
        assert_eq!(oracle.final_configs.len(), tasks.len());
        assert_eq!(oracle.final_velocities.len(), tasks.len());
        for (k, (start, goal)) in tasks.iter().enumerate() {
            assert_eq!(oracle.start_configs[k], start.q, "{env} episode {k}");
            assert_eq!(oracle.goal_configs[k], goal.q, "{env} episode {k}");
            assert_eq!(
                oracle.final_velocities[k].len(),
                goal.qd.len(),
                "{env} episode {k}"
            );
            let gap = oracle.final_configs[k]
                .iter()
                .zip(&goal.q)
                .map(|(a, b)| (a - b).abs())
                .fold(0.0, f64::max);
            assert!(gap < protocol.success_threshold, "{env} episode {k}: {gap}");
        }
        // The reacher also reports its fingertip's final distance in metres ,
        // one per episode; the other envs' distances are already positions in metres.
        if env == EnvKind::Reacher {
            assert_eq!(oracle.final_fingertip_distances_m.len(), tasks.len());
            // A joint-space error e moves the fingertip by at most 0.36 e m (0.24 m from the
            // shoulder, 0.12 m from the wrist), and the oracle ends within a tenth of the
            // threshold.
            let mean = oracle.final_fingertip_mean_m.unwrap();
            let bound = 0.36 * 0.1 * protocol.success_threshold;
            assert!((0.0..bound).contains(&mean), "{mean}");
        } else {
            assert!(oracle.final_fingertip_distances_m.is_empty(), "{env}");
            assert_eq!(oracle.final_fingertip_mean_m, None, "{env}");
        }
    }
}

#[test]
fn closed_loop_encodes_each_frame_once() {
    let env = EnvKind::PointMass;
    let device = cpu_device();
    let config = TrainConfig::preset(Preset::Procl, Method::Procl, env);
    let model = config.model.init(0, &device).unwrap();
    let mut policy = LatentPdPolicy::new(
        model.encoder,
        device,
        PdController { kp: 10.0, kd: 2.0 },
        0.02,
    );
    let protocol = ReachConfig {
        episodes: 2,
        horizon: 25,
        ..ReachConfig::for_env(env, 3)
    };
    let tasks = reach_tasks(&env.into(), &protocol);
    for (start, goal) in &tasks {
        let record = run_episode(
            &env.into(),
            &mut policy as &mut dyn Policy,
            start,
            goal,
            protocol.horizon,
            false,
        )
        .unwrap();
        assert_eq!(record.distances.len(), protocol.horizon + 1);
        assert_eq!(record.latents.len(), protocol.horizon);
    }
    // Per episode: the goal image once, then one new frame per control step.
    assert_eq!(policy.frames_encoded, tasks.len() * (1 + protocol.horizon));
    assert_eq!(policy.control_times_s.len(), tasks.len() * protocol.horizon);
    // Same start and goal: the same actions, so the same record (deterministic closed loop).
    let again = run_episode(
        &env.into(),
        &mut policy as &mut dyn Policy,
        &tasks[0].0,
        &tasks[0].1,
        protocol.horizon,
        false,
    )
    .unwrap();
    let first = run_episode(
        &env.into(),
        &mut policy as &mut dyn Policy,
        &tasks[0].0,
        &tasks[0].1,
        protocol.horizon,
        false,
    )
    .unwrap();
    assert_eq!(again.distances, first.distances);
}

#[test]
fn eval_writes_the_documented_outputs() {
    let dir = tempfile::tempdir().unwrap();
    let env = EnvKind::PointMass;
    let run = tiny_procl_run(dir.path(), env, (120, 40), (2, 8, 1));
    // The orientation logs every window's fitted action response: a header, then one line per
    // window (every step here): the step, the samples, the 2x2 response and its distance to
    // the identity.
    let windows = std::fs::read_to_string(run.dir.join("action_response.csv")).unwrap();
    let lines: Vec<&str> = windows.lines().collect();
    assert_eq!(lines.len(), 3, "{windows}");
    assert!(lines[0].starts_with("step,samples,b00"));
    assert!(lines[1..].iter().all(|l| l.split(',').count() == 7));
    let protocol = ReachConfig {
        episodes: 2,
        horizon: 12,
        ..ReachConfig::for_env(env, 4)
    };
    let report = evaluate_run(&run, &protocol, |_| {}).unwrap();
    for file in ["eval.json", "reach.png", "latent_traj.png", "episode.gif"] {
        assert!(run.dir.join(file).exists(), "{file} missing");
    }
    let json: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(run.dir.join("eval.json")).unwrap()).unwrap();
    assert_eq!(json["env"], "point-mass");
    assert_eq!(json["protocol"]["episodes"], 2);
    let methods = json["methods"].as_array().unwrap();
    assert_eq!(methods.len(), 2);
    for (m, summary) in methods.iter().zip(&report.methods) {
        for key in [
            "method",
            "per_step_mean",
            "per_step_std",
            "final_distances",
            "start_configs",
            "goal_configs",
            "final_configs",
            "final_velocities",
            "final_mean",
            "final_std",
            "success_rate",
        ] {
            assert!(m.get(key).is_some(), "eval.json lacks {key}");
        }
        assert_eq!(
            m["per_step_mean"].as_array().unwrap().len(),
            protocol.horizon + 1
        );
        assert_eq!(m["success_rate"].as_f64().unwrap(), summary.success_rate);
    }
    // Latent PD reports each episode's goal, first and last latent; the oracle has none.
    for key in ["goal_latents", "start_latents", "final_latents"] {
        assert_eq!(methods[0][key].as_array().unwrap().len(), 2, "{key}");
        assert!(methods[1].get(key).is_none(), "oracle {key}");
    }
    // Latent PD is timed, the oracle is not.
    assert!(methods[0]["control_time_us_p50"].as_f64().unwrap() > 0.0);
    assert!(methods[1]["control_time_us_p50"].is_null());

    // MPC on the same latent writes its own files and leaves PD's alone.
    let pd_json = std::fs::read(run.dir.join("eval.json")).unwrap();
    let mpc = Controller::Mpc(MpcConfig {
        samples: 16,
        elites: 4,
        iterations: 2,
        ..MpcConfig::default()
    });
    let report = evaluate_run_with(&run, &protocol, &mpc, |_| {}).unwrap();
    assert_eq!(report.methods[0].method, "ProCL + MPC");
    assert!(report.methods[0].control_time_us_p50.unwrap() > 0.0);
    for file in [
        "eval-mpc.json",
        "reach-mpc.png",
        "latent_traj-mpc.png",
        "episode-mpc.gif",
    ] {
        assert!(run.dir.join(file).exists(), "{file} missing");
    }
    assert_eq!(std::fs::read(run.dir.join("eval.json")).unwrap(), pd_json);

    // So does iLQR, PC3's own controller.
    let ilqr = Controller::Ilqr(procl::baselines::ilqr::IlqrConfig {
        candidates: 2,
        iterations: 2,
        ..Default::default()
    });
    let report = evaluate_run_with(&run, &protocol, &ilqr, |_| {}).unwrap();
    assert_eq!(report.methods[0].method, "ProCL + iLQR");
    assert!(report.methods[0].control_time_us_p50.unwrap() > 0.0);
    assert!(run.dir.join("eval-ilqr.json").exists());
    assert_eq!(std::fs::read(run.dir.join("eval.json")).unwrap(), pd_json);
}

#[test]
fn demo_quick_runs_end_to_end() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("demo");
    let run = std::process::Command::new(env!("CARGO_BIN_EXE_procl"))
        .args(["demo", "--quick", "--out", out.to_str().unwrap()])
        .output()
        .unwrap();
    let stdout = String::from_utf8_lossy(&run.stdout);
    assert!(
        run.status.success(),
        "{}",
        String::from_utf8_lossy(&run.stderr)
    );
    for needle in ["ProCL + PD", "PC3 + PD", "oracle PD", "report:"] {
        assert!(stdout.contains(needle), "summary lacks {needle}: {stdout}");
    }
    for file in [
        "report.html",
        "summary.json",
        "reach_all.png",
        "point-mass.npz",
        "procl/latent_map.png",
        "pc3/eval.json",
    ] {
        assert!(out.join(file).exists(), "{file} missing");
    }
    let html = std::fs::read_to_string(out.join("report.html")).unwrap();
    assert!(html.contains("reach_all.png") && html.contains("procl/episode.gif"));
    // A second run reuses every stage (nothing retrained) and gives the same table.
    let again = std::process::Command::new(env!("CARGO_BIN_EXE_procl"))
        .args(["demo", "--quick", "--out", out.to_str().unwrap()])
        .output()
        .unwrap();
    let again_stdout = String::from_utf8_lossy(&again.stdout);
    assert!(
        again_stdout.contains("reusing trained procl"),
        "{again_stdout}"
    );
}
