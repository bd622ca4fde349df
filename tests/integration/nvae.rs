//! The NewtonianVAE baseline end to end: training lowers the ELBO, runs are deterministic, and
//! `procl eval`, `diagnose` and `track` control an nvae run with PID.

use std::path::Path;

use procl::data::{CollectConfig, Dataset, collect};
use procl::envs::EnvKind;
use procl::model::{EncoderHead, cpu_device};
use procl::train::{Method, Preset, RunPaths, TrainConfig, config_from_table, train};

use super::cli::{assert_train_outputs, fails_with, path_str, succeeds};
use super::support::train_error;

fn point_mass_data(transitions: usize) -> Dataset {
    let config = CollectConfig {
        transitions,
        episode_len: 50,
        ..CollectConfig::new(EnvKind::PointMass, 3)
    };
    collect(&config, |_| {}).unwrap()
}

/// The nvae preset shrunk for a 2-core test machine.
fn tiny_config(steps: u64) -> TrainConfig {
    let mut config = TrainConfig::preset(Preset::Procl, Method::Nvae, EnvKind::PointMass);
    (config.seed, config.steps, config.batch_size) = (2, steps, 4);
    (config.checkpoint_every, config.orientation_search_every) = (steps, steps);
    config.learning_rate = 3e-3;
    let nvae = config.nvae.as_mut().unwrap();
    nvae.sequence_len = 6;
    nvae.trunk_channels = [8, 8];
    nvae.encoder_head = EncoderHead::Mlp { hidden: 16 };
    nvae.decoder_hidden = 16;
    nvae.decoder_channels = [8, 8, 4];
    config
}

/// metrics.csv rows as (total, recon, kl, kl_std, beta), checking the header.
fn metrics(dir: &Path) -> Vec<Vec<f64>> {
    let text = std::fs::read_to_string(RunPaths::new(dir).metrics()).unwrap();
    let mut lines = text.lines();
    assert_eq!(
        lines.next(),
        Some("step,total,recon,kl,kl_std,beta,seconds")
    );
    lines
        .map(|line| {
            let row: Vec<f64> = line.split(',').map(|x| x.parse().unwrap()).collect();
            row[1..6].to_vec()
        })
        .collect()
}

#[test]
fn nvae_settings_are_checked_by_field_name() {
    let parse = |text: &str| {
        let table: toml::Table = text.parse().unwrap();
        config_from_table(table, EnvKind::PointMass, None)
    };
    let config =
        parse("method = \"nvae\"\n[nvae]\nrecon_std = 0.05\n[nvae.pid]\nki = 0.0\n").unwrap();
    let nvae = config.nvae.unwrap();
    assert_eq!((nvae.recon_std, nvae.pid.ki, nvae.pid.kp), (0.05, 0.0, 8.0));
    // The procl preset fixes the transition as its paper's appendix does; the paper preset
    // learns it.
    assert_eq!(nvae.fixed_transition, Some([0.0, 0.0, 1.0]));
    let paper = parse("preset = \"paper\"\nmethod = \"nvae\"\n").unwrap();
    assert_eq!(paper.nvae.unwrap().fixed_transition, None);
    // The readout is oriented by the action response; the risk is ProCL's.
    assert_eq!(config.orientation_search_every, 50);
    assert_eq!(
        config.orientation_criterion,
        procl::train::orientation::OrientationCriterion::ActionResponse
    );
    for (text, needle) in [
        ("[nvae]\nrecon_std = 0.05\n", "method nvae only"),
        (
            "method = \"nvae\"\n[nvae]\nrecon_std = -1.0\n",
            "nvae.recon_std",
        ),
        (
            "method = \"nvae\"\n[nvae]\nlatent_dim = 3\n",
            "nvae.latent_dim",
        ),
        ("method = \"nvae\"\n[nvae]\nreconstd = 0.1\n", "reconstd"),
        (
            "method = \"nvae\"\norientation_criterion = \"risk\"\n",
            "orientation_criterion",
        ),
        (
            "method = \"nvae\"\n[nvae]\nfixed_transition = [0.0, 0.5, 1.0]\n",
            "nvae.fixed_transition",
        ),
    ] {
        let err = parse(text).unwrap_err().to_string();
        assert!(err.contains(needle), "{text:?}: {err}");
    }
}

#[test]
fn training_lowers_the_elbo() {
    let data = point_mass_data(600);
    let dir = tempfile::tempdir().unwrap();
    // beta = 1 from the start, so every step's total is the same objective (the negative
    // ELBO up to the decoder's constant). Nearly all of the fall is reconstruction: the decoder
    // learns the background first.
    let mut config = tiny_config(40);
    let nvae = config.nvae.as_mut().unwrap();
    nvae.kl_anneal_steps = 0;
    nvae.validate_every = 20;
    let mut totals = vec![];
    let summary = train(
        &config,
        &data,
        &RunPaths::new(dir.path()),
        false,
        &cpu_device(),
        |_, values| totals.push(values.total()),
    )
    .unwrap();
    assert_eq!(summary.steps_done, 40);
    let rows = metrics(dir.path());
    assert_eq!(rows.len(), 40);
    let mean = |rows: &[Vec<f64>], k: usize| rows.iter().map(|r| r[k]).sum::<f64>() / 5.0;
    let (first, last) = (&rows[..5], &rows[35..]);
    assert!(
        mean(last, 0) < 0.5 * mean(first, 0),
        "total {} -> {}",
        mean(first, 0),
        mean(last, 0)
    );
    assert!(mean(last, 1) < mean(first, 1), "recon did not fall");
    for (row, total) in rows.iter().zip(&totals) {
        assert_eq!(row[4], 1.0, "beta");
        // total = recon + beta kl + kl_standard_weight kl_std (the csv has 6 decimals).
        let sum = row[1] + row[2] + row[3];
        assert!((row[0] - sum).abs() < 1e-3 * sum.abs().max(1.0), "{row:?}");
        assert!((total - row[0]).abs() < 1e-3 * total.abs().max(1.0));
    }
    // The held-out episodes are scored every 20 steps.
    let validation = std::fs::read_to_string(RunPaths::new(dir.path()).validation()).unwrap();
    let lines: Vec<&str> = validation.lines().collect();
    assert_eq!(lines[0], "step,total,recon,kl,kl_std");
    assert_eq!(lines.len(), 3, "{validation}");
    assert!(lines[1].starts_with("20,") && lines[2].starts_with("40,"));
}

#[test]
fn a_plateaued_validation_elbo_ends_the_run_with_a_checkpoint() {
    let data = point_mass_data(600);
    let dir = tempfile::tempdir().unwrap();
    // A tolerance of 1000% counts no validation after the first as an improvement, so with
    // patience 1 the run ends at the second validation, step 4 of 10.
    let mut config = tiny_config(10);
    let nvae = config.nvae.as_mut().unwrap();
    (nvae.kl_anneal_steps, nvae.validate_every) = (0, 2);
    (nvae.plateau_patience, nvae.plateau_tolerance) = (1, 10.0);
    let run = RunPaths::new(dir.path());
    let summary = train(&config, &data, &run, false, &cpu_device(), |_, _| {}).unwrap();
    assert_eq!(summary.steps_done, 4);
    assert_eq!(metrics(dir.path()).len(), 4);
    let validation = std::fs::read_to_string(run.validation()).unwrap();
    assert_eq!(validation.lines().count(), 3, "{validation}");
    let meta = procl::read_checkpoint_meta(&run.checkpoint()).unwrap();
    assert!(meta.step == 4 && meta.stopped_early);
    // The rule ended the run: there is nothing to resume.
    let err = train_error(&config, &data, dir.path(), true);
    assert!(err.contains("finished") && err.contains("step 4"), "{err}");
    // A run interrupted after the first validation reads the rule's state back on resume, and
    // stops at the second, as the uninterrupted run did (without the state it would count
    // the second validation as its first, and go on).
    let other = dir.path().join("interrupted");
    let interrupted = TrainConfig {
        checkpoint_every: 2,
        orientation_search_every: 2,
        ..config.clone()
    };
    let paths = RunPaths::new(&other);
    let stop_at_2 = |step: u64, _: &procl::losses::StepValues| {
        if step == 2 {
            std::ops::ControlFlow::Break(())
        } else {
            std::ops::ControlFlow::Continue(())
        }
    };
    procl::train::train_interruptible(&interrupted, &data, &paths, false, &cpu_device(), stop_at_2)
        .unwrap_err();
    let summary = train(&interrupted, &data, &paths, true, &cpu_device(), |_, _| {}).unwrap();
    assert_eq!(summary.steps_done, 4);
    // Patience without validation episodes is refused by name.
    let mut bad = config.clone();
    bad.nvae.as_mut().unwrap().validation_share = 0.0;
    let err = train_error(&bad, &data, &dir.path().join("other"), false);
    assert!(err.contains("nvae.plateau_patience"), "{err}");
}

#[test]
fn same_seed_gives_the_same_nvae_and_resume_is_refused_for_a_changed_config() {
    let data = point_mass_data(200);
    let dir = tempfile::tempdir().unwrap();
    let config = tiny_config(3);
    let [a, b] = ["a", "b"].map(|name| dir.path().join(name));
    for run in [&a, &b] {
        train(
            &config,
            &data,
            &RunPaths::new(run),
            false,
            &cpu_device(),
            |_, _| {},
        )
        .unwrap();
    }
    let bytes = |run: &Path| std::fs::read(RunPaths::new(run).checkpoint()).unwrap();
    assert!(bytes(&a) == bytes(&b), "same seed, different checkpoints");
    assert_eq!(metrics(&a), metrics(&b));
    // The readout's action response was fitted over the window that ends at step 3.
    let response = std::fs::read_to_string(a.join("action_response.csv")).unwrap();
    let rows: Vec<&str> = response.lines().collect();
    assert!(rows.len() == 2 && rows[1].starts_with("3,"), "{response}");
    // The nvae table is part of the resolved config: a changed one cannot resume the run.
    let mut other = config.clone();
    other.steps = 6;
    other.nvae.as_mut().unwrap().recon_std = 0.2;
    let err = train_error(&other, &data, &a, true);
    assert!(err.contains("resume"), "{err}");
    // A ProCL-only loader names the problem.
    let err = RunPaths::new(&a)
        .load_model(&cpu_device())
        .err()
        .unwrap()
        .to_string();
    assert!(err.contains("NewtonianVAE"), "{err}");
}

#[test]
fn eval_diagnose_and_track_an_nvae_run_with_pid() {
    let dir = tempfile::tempdir().unwrap();
    let npz = dir.path().join("pm.npz");
    succeeds(&[
        "collect",
        "--env",
        "point-mass",
        "--transitions",
        "200",
        "--out",
        path_str(&npz),
    ]);
    let tiny = dir.path().join("tiny.toml");
    std::fs::write(
        &tiny,
        "batch_size = 8\ncheckpoint_every = 2\norientation_search_every = 1\n[nvae]\ntrunk_channels = [4, 4]\n\
         decoder_hidden = 8\ndecoder_channels = [4, 4, 4]\n\
         [nvae.encoder_head]\nkind = \"mlp\"\nhidden = 8\n",
    )
    .unwrap();
    let run = dir.path().join("run");
    let out = succeeds(&[
        "train",
        "--method",
        "nvae",
        "--data",
        path_str(&npz),
        "--config",
        path_str(&tiny),
        "--steps",
        "2",
        "--out",
        path_str(&run),
    ]);
    let stdout = String::from_utf8_lossy(&out.stdout);
    assert!(
        stdout.contains("recon") && stdout.contains("linear R^2"),
        "{stdout}"
    );
    assert_train_outputs(&run);

    let out = succeeds(&[
        "eval",
        "--run",
        path_str(&run),
        "--episodes",
        "2",
        "--horizon",
        "12",
    ]);
    assert!(String::from_utf8_lossy(&out.stdout).contains("NewtonianVAE + PID"));
    for file in ["eval.json", "reach.png", "latent_traj.png", "episode.gif"] {
        assert!(run.join(file).exists(), "eval did not write {file}");
    }
    let json: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(run.join("eval.json")).unwrap()).unwrap();
    let methods = json["methods"].as_array().unwrap();
    assert_eq!(methods[0]["method"], "NewtonianVAE + PID");
    assert_eq!(methods[1]["method"], "oracle PD (true state)");
    assert_eq!(methods[0]["per_step_mean"].as_array().unwrap().len(), 13);
    assert!(methods[0]["control_time_us_p50"].as_f64().unwrap() > 0.0);
    // Naming the controller works, P alone too (its own files); MPC and PD are ProCL's,
    // refused in one line.
    for name in ["pid", "p"] {
        succeeds(&[
            "eval",
            "--run",
            path_str(&run),
            "--episodes",
            "1",
            "--horizon",
            "3",
            "--controller",
            name,
        ]);
    }
    let json: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(run.join("eval-p.json")).unwrap()).unwrap();
    assert_eq!(json["methods"][0]["method"], "NewtonianVAE + P");
    for mpc in ["mpc", "ilqr"] {
        fails_with(
            &["eval", "--run", path_str(&run), "--controller", mpc],
            "NewtonianVAE",
        );
    }
    fails_with(
        &["eval", "--run", path_str(&run), "--controller", "pd"],
        "pid",
    );

    let out = succeeds(&["diagnose", "--run", path_str(&run)]);
    assert!(String::from_utf8_lossy(&out.stdout).contains("linear_r2"));

    let demo = dir.path().join("demo.npz");
    succeeds(&[
        "demonstrate",
        "--env",
        "point-mass",
        "--episodes",
        "1",
        "--steps",
        "10",
        "--out",
        path_str(&demo),
    ]);
    succeeds(&["track", "--run", path_str(&run), "--demo", path_str(&demo)]);
    let track: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(run.join("track.json")).unwrap()).unwrap();
    assert_eq!(track["methods"][0]["method"], "NewtonianVAE + PID");
}
