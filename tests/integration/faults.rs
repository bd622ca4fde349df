//! Faults a user meets: kill -9 in mid-training, a full disk, a read-only destination, a
//! dataset changed under a resumed run. Each leaves every previous good file in place and ends
//! with one line of error.

use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};

use procl::data::{CollectConfig, Dataset, collect};
use procl::envs::EnvKind;

use crate::cli::{fails_with, path_str, procl, succeeds};

/// Makes writing `path` atomically from this process fail as on a full disk: the temporary
/// file procl writes first (`.<name>.tmp-<pid>` beside it) becomes a link to `/dev/full`,
/// where every write fails with ENOSPC. Returns the link, which procl removes on failure.
pub(crate) fn full_disk_for(path: &Path) -> PathBuf {
    let name = path.file_name().unwrap().to_string_lossy();
    let temp = path.with_file_name(format!(".{name}.tmp-{}", std::process::id()));
    std::os::unix::fs::symlink("/dev/full", &temp).unwrap();
    temp
}

fn small_dataset(seed: u64) -> Dataset {
    let config = CollectConfig {
        transitions: 60,
        episode_len: 10,
        ..CollectConfig::new(EnvKind::PointMass, seed)
    };
    collect(&config, |_| {}).unwrap()
}

#[test]
fn a_full_disk_while_saving_a_dataset_keeps_the_old_file() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("pm.npz");
    small_dataset(0).save(&path, false).unwrap();
    let good = std::fs::read(&path).unwrap();
    let full = full_disk_for(&path);
    let err = small_dataset(1).save(&path, true).unwrap_err().to_string();
    assert!(
        err.contains("No space left") && !err.contains('\n'),
        "{err}"
    );
    assert_eq!(std::fs::read(&path).unwrap(), good);
    assert!(!full.exists(), "the temporary file is left behind");
}

/// The child half of the next test: saving onto a full disk in a process of its own, whose
/// stderr the parent reads.
#[test]
fn full_disk_dataset_save_child() {
    let Some(dir) = std::env::var_os("PROCL_FULL_DISK_CHILD") else {
        return;
    };
    let path = Path::new(&dir).join("pm.npz");
    full_disk_for(&path);
    let err = small_dataset(0).save(&path, false).unwrap_err();
    eprintln!("error: {err}");
}

#[test]
fn a_full_disk_puts_nothing_but_the_error_on_stderr() {
    // The zip writer under the NPZ writer finishes the archive when dropped and prints its
    // own debug line when that fails; procl keeps it quiet.
    let dir = tempfile::tempdir().unwrap();
    let out = Command::new(std::env::current_exe().unwrap())
        .args([
            "--exact",
            "faults::full_disk_dataset_save_child",
            "--nocapture",
        ])
        .env("PROCL_FULL_DISK_CHILD", dir.path())
        .stdin(Stdio::null())
        .output()
        .unwrap();
    let stderr = String::from_utf8_lossy(&out.stderr);
    let lines: Vec<&str> = stderr.lines().filter(|l| !l.trim().is_empty()).collect();
    assert_eq!(lines.len(), 1, "{stderr}");
    assert!(lines[0].contains("No space left"), "{stderr}");
    assert!(!stderr.contains("ZipWriter"), "{stderr}");
    assert!(std::fs::read_dir(dir.path()).unwrap().next().is_none());
}

/// A tiny point-mass dataset and a config of `steps` steps with a checkpoint every 5.
fn tiny_training(dir: &Path, steps: u64) -> (PathBuf, PathBuf) {
    let data = dir.join("pm.npz");
    if !data.exists() {
        small_dataset(0).save(&data, false).unwrap();
    }
    let config = dir.join(format!("steps-{steps}.toml"));
    std::fs::write(
        &config,
        format!(
            "steps = {steps}\nbatch_size = 8\ncheckpoint_every = 5\norientation_search_every = 5\n"
        ),
    )
    .unwrap();
    (data, config)
}

fn train_args<'a>(data: &'a Path, config: &'a Path, out: &'a Path) -> Vec<&'a str> {
    vec![
        "train",
        "--data",
        path_str(data),
        "--config",
        path_str(config),
        "--out",
        path_str(out),
    ]
}

#[test]
fn kill_minus_9_at_any_step_then_resume_gives_the_same_weights() {
    let dir = tempfile::tempdir().unwrap();
    let (data, config) = tiny_training(dir.path(), 60);
    let reference = dir.path().join("reference");
    succeeds(&train_args(&data, &config, &reference));
    let want = std::fs::read(reference.join("model.safetensors")).unwrap();
    let mut interrupted = 0;
    for kill_after in [3, 17, 34, 52] {
        let out = dir.path().join(format!("killed-{kill_after}"));
        let mut child = Command::new(env!("CARGO_BIN_EXE_procl"))
            .args(train_args(&data, &config, &out))
            .stdout(Stdio::null())
            .stderr(Stdio::null())
            .spawn()
            .unwrap();
        // metrics.csv holds a header and one row per finished step.
        let metrics = out.join("metrics.csv");
        loop {
            let rows = std::fs::read_to_string(&metrics)
                .map_or(0, |t| t.lines().count().saturating_sub(1));
            if rows >= kill_after || child.try_wait().unwrap().is_some() {
                break;
            }
            std::thread::sleep(std::time::Duration::from_millis(2));
        }
        child.kill().unwrap(); // SIGKILL
        let status = child.wait().unwrap();
        interrupted += usize::from(!status.success());
        if out.join("model.safetensors").exists() {
            let mut args = train_args(&data, &config, &out);
            args.push("--resume");
            succeeds(&args);
        } else {
            // Killed before its first checkpoint: a fresh start is the only way on.
            std::fs::remove_dir_all(&out).unwrap();
            succeeds(&train_args(&data, &config, &out));
        }
        assert_eq!(
            std::fs::read(out.join("model.safetensors")).unwrap(),
            want,
            "killed after {kill_after} steps"
        );
        let rows = std::fs::read_to_string(out.join("metrics.csv")).unwrap();
        assert_eq!(
            rows.lines().count(),
            61,
            "metrics.csv after the kill at {kill_after}"
        );
    }
    assert!(
        interrupted >= 3,
        "only {interrupted} of 4 runs were killed mid-training"
    );
}

#[test]
fn a_finished_run_trained_on_to_a_larger_budget_gives_the_weights_of_one_trained_there() {
    let dir = tempfile::tempdir().unwrap();
    let (data, long) = tiny_training(dir.path(), 40);
    let reference = dir.path().join("reference");
    succeeds(&train_args(&data, &long, &reference));
    let (_, short) = tiny_training(dir.path(), 20);
    let out = dir.path().join("extended");
    succeeds(&train_args(&data, &short, &out));
    let mut args = train_args(&data, &short, &out);
    args.extend(["--steps", "40", "--resume"]);
    succeeds(&args);
    let weights = |run: &Path| std::fs::read(run.join("model.safetensors")).unwrap();
    assert_eq!(weights(&out), weights(&reference));
    let rows = std::fs::read_to_string(out.join("metrics.csv")).unwrap();
    assert_eq!(rows.lines().count(), 41);
    let config: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(out.join("config.json")).unwrap()).unwrap();
    assert_eq!(config["steps"], 40);
    // A budget below the step reached, or another change, is refused and leaves the run as is.
    let mut args = train_args(&data, &short, &out);
    args.push("--resume");
    fails_with(&args, "steps");
    let mut args = train_args(&data, &long, &out);
    args.extend(["--seed", "7", "--resume"]);
    fails_with(&args, "differs from this run's configuration");
    assert_eq!(weights(&out), weights(&reference));
}

#[test]
fn a_full_disk_at_a_checkpoint_keeps_the_last_one_and_resumes() {
    let dir = tempfile::tempdir().unwrap();
    let (data, config_path) = tiny_training(dir.path(), 10);
    let reference = dir.path().join("reference");
    succeeds(&train_args(&data, &config_path, &reference));

    let out = dir.path().join("run");
    let dataset = Dataset::load(&data).unwrap();
    let config = procl::train::config_from_toml(&config_path, EnvKind::PointMass, None).unwrap();
    let device = procl::model::cpu_device();
    let run = procl::train::RunPaths::new(&out);
    let checkpoint = out.join("model.safetensors");
    // The disk fills up after the checkpoint of step 5: the one of step 10 cannot be written.
    let mut kept = None;
    let mut full = None;
    let err = procl::train::train(&config, &dataset, &run, false, &device, |step, _| {
        if step == 6 {
            kept = Some(std::fs::read(&checkpoint).unwrap());
            full = Some(full_disk_for(&checkpoint));
        }
    })
    .unwrap_err()
    .to_string();
    assert!(
        err.contains("No space left") && !err.contains('\n'),
        "{err}"
    );
    assert_eq!(Some(std::fs::read(&checkpoint).unwrap()), kept);
    assert!(!full.unwrap().exists(), "the temporary file is left behind");
    // With space again, the run resumes from the kept checkpoint to the same weights.
    procl::train::train(&config, &dataset, &run, true, &device, |_, _| {}).unwrap();
    assert_eq!(
        std::fs::read(&checkpoint).unwrap(),
        std::fs::read(reference.join("model.safetensors")).unwrap()
    );
}

#[test]
fn a_read_only_destination_is_refused_in_one_line() {
    // /proc takes no new files, not even from root (permission bits would not stop root).
    fails_with(
        &[
            "collect",
            "--env",
            "point-mass",
            "--transitions",
            "20",
            "--out",
            "/proc/procl/pm.npz",
        ],
        "/proc/procl",
    );
    let dir = tempfile::tempdir().unwrap();
    let (data, config) = tiny_training(dir.path(), 5);
    fails_with(
        &train_args(&data, &config, Path::new("/proc/procl-run")),
        "/proc/procl-run",
    );
    let out = procl(&["info", "--data", path_str(&data)]);
    assert!(out.status.success());
}

#[test]
fn a_misspelt_key_in_a_nested_config_table_is_refused_before_training() {
    let dir = tempfile::tempdir().unwrap();
    let (data, config) = tiny_training(dir.path(), 5);
    let text = std::fs::read_to_string(&config).unwrap();
    std::fs::write(
        &config,
        format!("{text}[model.encoder]\nkeypoint_sharpnes = 2.0\n"),
    )
    .unwrap();
    let out = dir.path().join("run");
    let line = fails_with(&train_args(&data, &config, &out), "keypoint_sharpnes");
    assert!(line.contains("model.encoder"), "{line}");
    assert!(!out.exists(), "a refused run left a folder");
}

#[test]
fn resume_refuses_a_dataset_changed_under_the_run() {
    let dir = tempfile::tempdir().unwrap();
    let (data, config) = tiny_training(dir.path(), 5);
    let out = dir.path().join("run");
    succeeds(&train_args(&data, &config, &out));
    let checkpoint = std::fs::read(out.join("model.safetensors")).unwrap();
    // Same file name, other contents: another seed's episodes.
    small_dataset(7).save(&data, true).unwrap();
    let mut args = train_args(&data, &config, &out);
    args.push("--resume");
    fails_with(&args, "the dataset is not the one");
    assert_eq!(
        std::fs::read(out.join("model.safetensors")).unwrap(),
        checkpoint
    );
    // The original contents again (rewritten, so not the same file): the run resumes.
    small_dataset(0).save(&data, true).unwrap();
    succeeds(&args);
}

#[test]
fn an_interrupted_run_keeps_its_last_checkpoint_and_resumes_to_the_same_weights() {
    let dir = tempfile::tempdir().unwrap();
    let (data, config_path) = tiny_training(dir.path(), 10);
    let reference = dir.path().join("reference");
    succeeds(&train_args(&data, &config_path, &reference));
    let dataset = Dataset::load(&data).unwrap();
    let config = procl::train::config_from_toml(&config_path, EnvKind::PointMass, None).unwrap();
    let device = procl::model::cpu_device();
    let run = procl::train::RunPaths::new(dir.path().join("run"));
    let stop_after = |last: u64| {
        move |step: u64, _: &procl::losses::StepValues| {
            if step == last {
                std::ops::ControlFlow::Break(())
            } else {
                std::ops::ControlFlow::Continue(())
            }
        }
    };
    let err =
        procl::train::train_interruptible(&config, &dataset, &run, false, &device, stop_after(7))
            .unwrap_err();
    assert!(matches!(err, procl::Error::Interrupted(_)), "{err}");
    let message = err.to_string();
    assert!(
        message.contains("after step 7") && message.contains("step 5"),
        "{message}"
    );
    procl::train::train(&config, &dataset, &run, true, &device, |_, _| {}).unwrap();
    assert_eq!(
        std::fs::read(run.checkpoint()).unwrap(),
        std::fs::read(reference.join("model.safetensors")).unwrap()
    );
}
