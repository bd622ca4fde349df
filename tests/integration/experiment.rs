//! `procl experiment paper --quick`: every stage on all three environments, resumed without
//! redoing a finished stage, the report's contents, the README section and a conflicting run.

use procl::envs::EnvKind;
use procl::runner::experiment::{
    Event, ExperimentConfig, README_BEGIN, README_END, run_experiment, update_readme,
};
use procl::runner::stages::Outcome;

/// Runs the experiment; the (stage, outcome) of every finished stage.
fn run(
    config: &ExperimentConfig,
    report_only: bool,
) -> (procl::runner::experiment::Summary, Vec<(String, Outcome)>) {
    procl::allocator::retain_freed_memory();
    let mut finished = vec![];
    let summary = run_experiment(config, report_only, &mut |event| {
        if let Event::Finish(name, outcome, _) = event {
            finished.push((name.to_string(), outcome));
        }
    })
    .unwrap();
    (summary, finished)
}

#[test]
fn quick_experiment_covers_every_env_and_method_and_resumes() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("results");
    let config = ExperimentConfig::quick(&out);
    let (summary, finished) = run(&config, false);

    // 3 envs x (collect + 3 methods x (train + eval + learning curve) + CEM and iLQR on ProCL
    // and PC3), 2 ablation runs x 2, demonstrate, track.
    assert_eq!(finished.len(), 48, "{finished:?}");
    assert!(finished.iter().all(|(_, o)| *o == Outcome::Ran));
    let envs: Vec<EnvKind> = summary.envs.iter().map(|e| e.env).collect();
    assert_eq!(envs, [EnvKind::PointMass, EnvKind::Reacher, EnvKind::Fetch]);
    for results in &summary.envs {
        let methods: Vec<&str> = results.rows.iter().map(|r| r.method.as_str()).collect();
        assert_eq!(
            methods,
            [
                "ProCL + PD",
                "ProCL + MPC",
                "ProCL + iLQR",
                "PC3 + PD",
                "PC3 + MPC",
                "PC3 + iLQR",
                "NewtonianVAE + PID",
                "oracle PD (true state)"
            ],
            "{}",
            results.env
        );
        // The planners act on the same runs; their step time is measured against PD's.
        for row in results
            .rows
            .iter()
            .filter(|r| r.method.ends_with("MPC") || r.method.ends_with("iLQR"))
        {
            assert!(
                row.control_time_vs_feedback.is_some_and(|x| x > 0.0),
                "{}",
                row.method
            );
            assert!(out.join(row.run.as_ref().unwrap()).exists());
        }
        let feedback = results
            .rows
            .iter()
            .filter(|r| r.method.ends_with("+ PD") || r.method.ends_with("+ PID"));
        for row in feedback {
            assert!(row.final_mean.is_finite() && row.control_time_us_p50.is_some());
            assert!(row.train_seconds.is_some() && row.linear_r2.is_some());
            // Every env's latent has as many dimensions as its configuration.
            assert!(
                row.pushes_away_share
                    .is_some_and(|x| (0.0..=1.0).contains(&x))
            );
            // The local maps are read on the 2-D configurations' grid only.
            let local = row.locally_unstable_share;
            match results.env {
                EnvKind::Fetch => assert_eq!(local, None),
                _ => assert!(local.is_some_and(|x| (0.0..=1.0).contains(&x))),
            }
            let run = out.join(row.run.as_ref().unwrap());
            for file in ["latent_traj.png", "latent_map.png", "eval.json"] {
                assert!(run.join(file).exists(), "{}", run.join(file).display());
            }
        }
        assert!(out.join(results.env.name()).join("reach_all.png").exists());
        assert!(out.join(results.env.name()).join("learning.png").exists());
        // Snapshots every 2 of 6 steps: the curve holds steps 2 and 4, then the final weights.
        let curves: Vec<(&str, Vec<u64>)> = results
            .curves
            .iter()
            .map(|c| (c.method.as_str(), c.points.iter().map(|p| p.step).collect()))
            .collect();
        assert_eq!(
            curves,
            [
                ("ProCL + PD", vec![2, 4, 6]),
                ("PC3 + PD", vec![2, 4, 6]),
                ("NewtonianVAE + PID", vec![2, 4, 6])
            ],
            "{}",
            results.env
        );
        for curve in &results.curves {
            assert!(curve.points.windows(2).all(|w| w[0].seconds < w[1].seconds));
        }
        // The equal budget is ProCL's own training time, so ProCL's row is its final weights.
        let budget = results.equal_budget_seconds.unwrap();
        let procl = &results.equal_budget[0];
        assert_eq!((procl.method.as_str(), procl.step), ("ProCL + PD", Some(6)));
        let point = procl.point.as_ref().unwrap();
        assert_eq!((point.step, point.seconds), (6, budget));
        assert_eq!(results.equal_budget.len(), 3);
        for row in &results.equal_budget {
            assert!(row.point.as_ref().is_none_or(|p| p.seconds <= budget));
        }
    }
    let eps: Vec<f64> = summary
        .ablation
        .iter()
        .map(|a| a.latent_noise_std)
        .collect();
    assert_eq!(eps, [0.001, 0.01, 0.1]);
    let tracking = summary.tracking.as_ref().unwrap();
    assert_eq!((tracking.env, tracking.demonstrations), (EnvKind::Fetch, 1));
    assert!(out.join("point-mass/ablation.png").exists());
    assert!(out.join("fetch/procl/track.png").exists());
    assert_eq!(summary.stage_seconds.len(), 48);
    let html = std::fs::read_to_string(out.join("report.html")).unwrap();
    for needle in [
        "fetch/reach_all.png",
        "NewtonianVAE + PID",
        "Tracking on Fetch-3D",
        "point-mass/ablation.png",
        "reacher/pc3/latent_traj.png",
        "pairs PD pushes away",
        "Equal training budget",
        "reacher/learning.png",
    ] {
        assert!(html.contains(needle), "{needle}");
    }
    let json: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(out.join("summary.json")).unwrap()).unwrap();
    assert_eq!(json["envs"].as_array().unwrap().len(), 3);

    // A rerun reuses every stage and leaves the weights alone.
    let weights = out.join("reacher/procl/model.safetensors");
    let before = std::fs::read(&weights).unwrap();
    let (again, finished) = run(&config, false);
    assert_eq!(finished.len(), 48);
    assert!(
        finished.iter().all(|(_, o)| *o == Outcome::Reused),
        "{finished:?}"
    );
    assert_eq!(std::fs::read(&weights).unwrap(), before);
    assert_eq!(again.stage_seconds, summary.stage_seconds);

    // New weights make the run's evaluation stale: only that stage runs again.
    let pc3 = out.join("point-mass/pc3/model.safetensors");
    // (Over a second: some file systems keep modification times in whole seconds.)
    std::thread::sleep(std::time::Duration::from_millis(1100));
    std::fs::write(&pc3, std::fs::read(&pc3).unwrap()).unwrap();
    let (_, finished) = run(&config, false);
    let ran: Vec<&str> = finished
        .iter()
        .filter(|(_, o)| *o == Outcome::Ran)
        .map(|(n, _)| n.as_str())
        .collect();
    assert_eq!(
        ran,
        [
            "point-mass/pc3/eval",
            "point-mass/pc3/eval-mpc",
            "point-mass/pc3/eval-ilqr"
        ]
    );

    // --report-only runs nothing.
    let (_, finished) = run(&config, true);
    assert!(finished.is_empty());

    // On a full disk the report is not replaced: the last good one stays, with one line of error.
    let report = out.join("report.html");
    let good = std::fs::read(&report).unwrap();
    let full = crate::faults::full_disk_for(&report);
    let err = run_experiment(&config, true, &mut |_| {})
        .unwrap_err()
        .to_string();
    assert!(
        err.contains("No space left") && !err.contains('\n'),
        "{err}"
    );
    assert_eq!(std::fs::read(&report).unwrap(), good);
    assert!(!full.exists(), "the temporary file is left behind");

    // The README section is rewritten in place, the rest kept, the figures copied beside it.
    let readme = dir.path().join("README.md");
    std::fs::write(
        &readme,
        format!("# title\n\nbefore\n{README_BEGIN}\nold table\n{README_END}\nafter\n"),
    )
    .unwrap();
    update_readme(&readme, std::path::Path::new("img"), &config, &summary).unwrap();
    let text = std::fs::read_to_string(&readme).unwrap();
    assert!(
        text.starts_with("# title\n\nbefore\n")
            && text.ends_with(&format!("{README_END}\nafter\n"))
    );
    assert!(!text.contains("old table") && text.contains("| fetch | ProCL + PD |"));
    assert!(text.contains("](img/point-mass_reach.png)"));
    assert!(dir.path().join("img/fetch_reach.png").exists());
    assert!(text.contains("](img/reacher_learning.png)") && text.contains("| budget (s) |"));
    for (text, expected) in [
        ("no marks\n".to_string(), "has no"),
        (
            format!("{README_BEGIN}\n{README_BEGIN}\n{README_END}\n"),
            "more than once",
        ),
        (format!("{README_END}\n{README_BEGIN}\n"), "after"),
    ] {
        std::fs::write(&readme, &text).unwrap();
        let err = update_readme(&readme, std::path::Path::new("img"), &config, &summary)
            .unwrap_err()
            .to_string();
        assert!(err.contains("README.md") && err.contains(expected), "{err}");
        assert_eq!(std::fs::read_to_string(&readme).unwrap(), text);
    }

    // A dataset of another size is refused by name, not silently reused.
    let mut bigger = config.clone();
    bigger.envs[0].transitions = 300;
    let err = run_experiment(&bigger, false, &mut |_| {})
        .unwrap_err()
        .to_string();
    assert!(
        err.contains("point-mass/data.npz") && err.contains("episodes"),
        "{err}"
    );

    // A run folder holding another configuration is refused, not overwritten.
    let weights = out.join("point-mass/procl/model.safetensors");
    let before = std::fs::read(&weights).unwrap();
    let mut other = config.clone();
    other.batch_size = Some(8);
    let err = run_experiment(&other, false, &mut |_| {})
        .unwrap_err()
        .to_string();
    assert!(err.contains("another configuration"), "{err}");
    assert_eq!(std::fs::read(&weights).unwrap(), before);
}
