//! The `procl` binary: exit codes, one-line errors, no clobbering.

use std::path::{Path, PathBuf};
use std::process::{Command, Output};

pub(crate) fn procl(args: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_procl"))
        .args(args)
        .output()
        .expect("run procl")
}

/// Asserts that `procl train` wrote everything it promises into the run folder `run`.
pub(crate) fn assert_train_outputs(run: &Path) {
    for file in [
        "config.json",
        "model.safetensors",
        "metrics.csv",
        "latent_map.png",
        "diagnostics.json",
    ] {
        assert!(run.join(file).exists(), "train did not write {file}");
    }
}

/// Runs `procl args` and asserts that it succeeded.
pub(crate) fn succeeds(args: &[&str]) -> Output {
    let out = procl(args);
    assert!(
        out.status.success(),
        "{args:?}: {}",
        String::from_utf8_lossy(&out.stderr)
    );
    out
}

/// Runs procl with `args`, which must fail with one line of stderr containing `needle`;
/// returns that line.
pub(crate) fn fails_with(args: &[&str], needle: &str) -> String {
    let out = procl(args);
    let stderr = String::from_utf8_lossy(&out.stderr).into_owned();
    assert!(!out.status.success(), "{args:?} succeeded");
    assert_eq!(
        stderr.trim_end().lines().count(),
        1,
        "{args:?}: not one line: {stderr}"
    );
    assert!(
        stderr.contains(needle),
        "{args:?}: {stderr:?} lacks {needle:?}"
    );
    stderr
}

pub(crate) fn path_str(p: &Path) -> &str {
    p.to_str().unwrap()
}

/// Owned arguments as the `&str`s [`succeeds`] and [`fails_with`] take.
pub(crate) fn strs(args: &[String]) -> Vec<&str> {
    args.iter().map(String::as_str).collect()
}

/// `procl ablate` on a tiny budget: the data from `source` (`--env E` or `--env-config V`),
/// `transitions` in 10-step episodes, `seeds` seeds, one 5-step episode each, into `out`, then
/// `extra`.
pub(crate) fn tiny_ablate(
    source: &[&str],
    grid: &Path,
    seeds: usize,
    transitions: usize,
    out: &Path,
    extra: &[&str],
) -> Vec<String> {
    let (seeds, transitions) = (seeds.to_string(), transitions.to_string());
    let mut args = vec!["ablate"];
    args.extend_from_slice(source);
    args.extend([
        "--grid",
        path_str(grid),
        "--seeds",
        &seeds,
        "--episodes",
        "1",
        "--horizon",
        "5",
        "--transitions",
        &transitions,
        "--episode-len",
        "10",
        "--out",
        path_str(out),
    ]);
    args.extend_from_slice(extra);
    args.into_iter().map(String::from).collect()
}

/// `dir/grid.toml`: `cells` over a base of 2 training steps on batches of 8.
fn tiny_grid(dir: &Path, cells: &str) -> PathBuf {
    let grid = dir.join("grid.toml");
    std::fs::write(&grid, format!("[base]\nsteps = 2\nbatch_size = 8\n{cells}")).unwrap();
    grid
}

#[test]
fn collect_render_info_and_bad_input() {
    let dir = tempfile::tempdir().unwrap();
    let npz = dir.path().join("pm.npz");
    let out = procl(&[
        "collect",
        "--env",
        "point-mass",
        "--transitions",
        "200",
        "--seed",
        "3",
        "--out",
        path_str(&npz),
    ]);
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let run = dir.path().join("run");
    let out = procl(&[
        "train",
        "--data",
        path_str(&npz),
        "--out",
        path_str(&run),
        "--steps",
        "2",
    ]);
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    assert!(String::from_utf8_lossy(&out.stdout).contains("linear R^2"));
    assert_train_outputs(&run);
    let info = procl(&["info", "--data", path_str(&npz)]);
    assert!(String::from_utf8_lossy(&info.stdout).contains("point-mass"));

    // An existing output survives without --force.
    let before = std::fs::read(&npz).unwrap();
    fails_with(
        &[
            "collect",
            "--env",
            "point-mass",
            "--transitions",
            "100",
            "--out",
            path_str(&npz),
        ],
        "--force",
    );
    assert_eq!(std::fs::read(&npz).unwrap(), before);

    fails_with(
        &["collect", "--env", "cartpole", "--out", "x.npz"],
        "unknown environment `cartpole`",
    );
    fails_with(
        &[
            "collect",
            "--env",
            "reacher",
            "--transitions",
            "0",
            "--out",
            "x.npz",
        ],
        "transitions",
    );
    let unwritable = dir.path().join("pm.npz").join("below-a-file.npz");
    fails_with(
        &[
            "collect",
            "--env",
            "reacher",
            "--transitions",
            "10",
            "--out",
            path_str(&unwritable),
        ],
        "pm.npz",
    );

    // The reacher's default episodes hold 10 steps; a length below 2 is refused by `collect`
    // and `ablate` alike, before anything is written.
    let reacher = dir.path().join("reacher.npz");
    let out = procl(&[
        "collect",
        "--env",
        "reacher",
        "--transitions",
        "40",
        "--out",
        path_str(&reacher),
    ]);
    assert!(out.status.success());
    let data = procl::data::Dataset::load(&reacher).unwrap();
    assert_eq!((data.episodes(), data.steps()), (4, 10));
    let ablate_out = dir.path().join("ablate");
    fails_with(
        &[
            "collect",
            "--env",
            "reacher",
            "--episode-len",
            "1",
            "--out",
            "y.npz",
        ],
        "episode_len",
    );
    fails_with(
        &[
            "ablate",
            "--env",
            "reacher",
            "--grid",
            "ablation/reacher.toml",
            "--episode-len",
            "1",
            "--out",
            path_str(&ablate_out),
        ],
        "episode_len",
    );
    assert!(!ablate_out.exists());

    let png = dir.path().join("strip.png");
    let out = procl(&["render", "--env", "reacher", "--out", path_str(&png)]);
    assert!(out.status.success());
    assert_eq!(&std::fs::read(&png).unwrap()[1..4], b"PNG");

    let truncated = dir.path().join("cut.npz");
    std::fs::write(&truncated, &before[..before.len() / 3]).unwrap();
    fails_with(&["info", "--data", path_str(&truncated)], "cut.npz");
    fails_with(&["info", "--data", "/definitely/missing.npz"], "not found");
}

#[test]
fn demonstrate_and_track_reject_bad_input() {
    let dir = tempfile::tempdir().unwrap();
    let demo = dir.path().join("demo.npz");
    fails_with(
        &[
            "demonstrate",
            "--env",
            "point-mass",
            "--shape",
            "square",
            "--out",
            path_str(&demo),
        ],
        "square",
    );
    fails_with(
        &["demonstrate", "--env", "cartpole", "--out", path_str(&demo)],
        "cartpole",
    );
    let out = procl(&[
        "demonstrate",
        "--env",
        "point-mass",
        "--episodes",
        "1",
        "--steps",
        "20",
        "--out",
        path_str(&demo),
    ]);
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    // An existing file is kept unless --force.
    let before = std::fs::read(&demo).unwrap();
    fails_with(
        &[
            "demonstrate",
            "--env",
            "point-mass",
            "--seed",
            "9",
            "--out",
            path_str(&demo),
        ],
        "already exists",
    );
    assert_eq!(std::fs::read(&demo).unwrap(), before);
    fails_with(
        &[
            "track",
            "--run",
            path_str(&dir.path().join("no-run")),
            "--demo",
            path_str(&demo),
        ],
        "config.json",
    );
}

/// One writer per output folder: while a folder is locked (here by this test process), a
/// second `procl train`, `ablate` or `demo` into it is refused with one line naming the folder
/// and the holder's pid, and nothing in it is touched; readers keep working.
#[test]
fn a_second_writer_into_a_locked_folder_is_refused() {
    let dir = tempfile::tempdir().unwrap();
    let npz = dir.path().join("pm.npz");
    succeeds(&[
        "collect",
        "--env",
        "point-mass",
        "--transitions",
        "60",
        "--episode-len",
        "20",
        "--out",
        path_str(&npz),
    ]);
    let run = dir.path().join("run");
    let lock = procl::FolderLock::acquire(&run).unwrap();
    let pid = std::process::id().to_string();
    let train = [
        "train",
        "--data",
        path_str(&npz),
        "--out",
        path_str(&run),
        "--steps",
        "2",
    ];
    fails_with(&train, &pid);
    fails_with(&train, path_str(&run));
    assert!(
        !run.join("config.json").exists(),
        "the refused writer wrote"
    );
    fails_with(&["demo", "--quick", "--out", path_str(&run)], &pid);
    // Readers do not take the lock.
    succeeds(&["info", "--data", path_str(&npz)]);
    drop(lock);
    succeeds(&train);
    assert!(run.join("model.safetensors").exists());
}

#[test]
fn ablation_tasks_run_one_per_job_array_index_and_merge() {
    let dir = tempfile::tempdir().unwrap();
    let grid = tiny_grid(
        dir.path(),
        "[[cell]]\nname = \"default\"\n[[cell]]\nname = \"q_v=0\"\nloss = { q_v = 0.0 }\n",
    );
    let out = dir.path().join("grid");
    let args = |extra: &[&str]| tiny_ablate(&["--env", "point-mass"], &grid, 2, 40, &out, extra);
    let run = |extra: &[&str]| succeeds(&strs(&args(extra)));
    let listed = String::from_utf8_lossy(&run(&["--list-tasks"]).stdout).into_owned();
    assert!(listed.contains("0\tdefault\tseed 0"), "{listed}");
    assert!(listed.contains("3\tq_v=0\tseed 1"), "{listed}");
    assert!(listed.contains("4 tasks"), "{listed}");
    assert!(!out.exists(), "listing wrote {}", out.display());

    run(&["--task-index", "3"]);
    run(&["--task-index", "0"]);
    assert!(out.join("q_v=0/seed-1/result.json").exists());
    assert!(out.join("default/seed-0/result.json").exists());
    assert!(!out.join("default/seed-1").exists());
    assert!(!out.join("ablation.md").exists());
    fails_with(&strs(&args(&["--task-index", "4"])), "the grid has 4 tasks");

    run(&["--report-only"]);
    let merged: Vec<serde_json::Value> =
        serde_json::from_str(&std::fs::read_to_string(out.join("ablation.json")).unwrap()).unwrap();
    let seen: Vec<(String, u64)> = merged
        .iter()
        .map(|r| {
            (
                r["cell"].as_str().unwrap().to_string(),
                r["seed"].as_u64().unwrap(),
            )
        })
        .collect();
    assert_eq!(seen, [("default".into(), 0), ("q_v=0".into(), 1)]);
    // The whole grid trains only the two tasks still missing.
    run(&[]);
    let merged: Vec<serde_json::Value> =
        serde_json::from_str(&std::fs::read_to_string(out.join("ablation.json")).unwrap()).unwrap();
    assert_eq!(merged.len(), 4);
    let jsonl = std::fs::read_to_string(out.join("ablation.jsonl")).unwrap();
    assert_eq!(jsonl.lines().count(), 2);
}

#[test]
fn ablation_evaluates_each_seed_on_every_task_set() {
    let dir = tempfile::tempdir().unwrap();
    let grid = tiny_grid(dir.path(), "[[cell]]\nname = \"default\"\n");
    let out = dir.path().join("grid");
    let args = |extra: &[&str]| tiny_ablate(&["--env", "point-mass"], &grid, 1, 40, &out, extra);
    fails_with(&strs(&args(&["--task-sets", "0"])), "--task-sets");
    assert!(!out.exists());
    succeeds(&strs(&args(&["--task-sets", "3"])));
    let result: serde_json::Value = serde_json::from_str(
        &std::fs::read_to_string(out.join("default/seed-0/result.json")).unwrap(),
    )
    .unwrap();
    let sets: Vec<f64> = result["success_per_task_set"]
        .as_array()
        .unwrap()
        .iter()
        .map(|s| s.as_f64().unwrap())
        .collect();
    assert_eq!(sets.len(), 3);
    let mean = sets.iter().sum::<f64>() / 3.0;
    assert!((result["success_rate"].as_f64().unwrap() - mean).abs() < 1e-12);
    // The run's eval.json is the first set's, the protocol's own task seed.
    let report: serde_json::Value = serde_json::from_str(
        &std::fs::read_to_string(out.join("default/seed-0/eval.json")).unwrap(),
    )
    .unwrap();
    assert_eq!(report["protocol"]["seed"], 1000);
    let summary = std::fs::read_to_string(out.join("ablation.md")).unwrap();
    assert!(summary.contains("on each of 3 task sets"), "{summary}");
    // A result outside the seeds asked for is reported as it was evaluated, beside a new seed
    // on one set: the summary says so.
    let more = tiny_ablate(
        &["--env", "point-mass"],
        &grid,
        1,
        40,
        &out,
        &["--seed-start", "1"],
    );
    succeeds(&strs(&more));
    let summary = std::fs::read_to_string(out.join("ablation.md")).unwrap();
    assert!(summary.contains("on 1 to 3 task sets"), "{summary}");
}

#[test]
fn ablation_reevaluates_results_of_other_task_sets_and_refuses_a_changed_cell() {
    let dir = tempfile::tempdir().unwrap();
    let grid = tiny_grid(dir.path(), "[[cell]]\nname = \"default\"\n");
    let out = dir.path().join("grid");
    let run = out.join("default/seed-0");
    let modified = |file: &str| {
        std::fs::metadata(run.join(file))
            .unwrap()
            .modified()
            .unwrap()
    };
    let read = |file: &str| -> serde_json::Value {
        serde_json::from_str(&std::fs::read_to_string(run.join(file)).unwrap()).unwrap()
    };
    let ablate = |extra: &[&str]| tiny_ablate(&["--env", "point-mass"], &grid, 1, 40, &out, extra);
    succeeds(&strs(&ablate(&["--task-sets", "2"])));
    let (weights, first) = (modified("model.safetensors"), read("result.json"));
    assert_eq!(first["task_sets"].as_array().unwrap().len(), 2);
    // The same protocol: the result is reused as it is.
    succeeds(&strs(&ablate(&["--task-sets", "2"])));
    assert_eq!(read("result.json"), first);
    // Another protocol (one task set): evaluated again from the same weights, keeping the
    // training time, and the summary and ablation.jsonl carry the new result only.
    succeeds(&strs(&ablate(&[])));
    let again = read("result.json");
    assert_eq!(modified("model.safetensors"), weights);
    assert_eq!(again["train_seconds"], first["train_seconds"]);
    assert_eq!(again["task_sets"].as_array().unwrap().len(), 1);
    assert_eq!(again["success_per_task_set"].as_array().unwrap().len(), 1);
    let summary = std::fs::read_to_string(out.join("ablation.md")).unwrap();
    assert!(!summary.contains("task sets"), "{summary}");
    let lines = std::fs::read_to_string(out.join("ablation.jsonl")).unwrap();
    assert_eq!(lines.lines().count(), 2, "{lines}");
    let report: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(out.join("ablation.json")).unwrap()).unwrap();
    assert_eq!(report.as_array().unwrap().len(), 1);
    assert_eq!(report[0], again);
    // A job-array task evaluates it again on two sets and writes only its result.json, which
    // a report then reads over the older line of ablation.jsonl.
    succeeds(&strs(&ablate(&["--task-index", "0", "--task-sets", "2"])));
    succeeds(&strs(&ablate(&["--report-only", "--task-sets", "2"])));
    let report: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(out.join("ablation.json")).unwrap()).unwrap();
    assert_eq!(report[0]["task_sets"].as_array().unwrap().len(), 2);
    let again = read("result.json");
    // A report of another protocol than its results' is refused, not headed with the wrong
    // protocol; so is a result of another protocol whose run cannot be evaluated again.
    let err = fails_with(&strs(&ablate(&["--report-only"])), "cell `default` seed 0");
    assert!(err.contains("2 sets of"), "{err}");
    let weights = std::fs::read(run.join("model.safetensors")).unwrap();
    std::fs::remove_file(run.join("model.safetensors")).unwrap();
    let err = fails_with(&strs(&ablate(&[])), "cell `default` seed 0");
    assert!(err.contains("no complete run"), "{err}");
    assert_eq!(read("result.json"), again);
    std::fs::write(run.join("model.safetensors"), weights).unwrap();
    // The cell edited after training: its folder is refused by name, nothing is rewritten.
    std::fs::write(
        &grid,
        "[base]\nsteps = 2\nbatch_size = 8\n[[cell]]\nname = \"default\"\nlearning_rate = 0.002\n",
    )
    .unwrap();
    let err = fails_with(&strs(&ablate(&[])), "cell `default`");
    assert!(err.contains("another configuration"), "{err}");
    assert_eq!(read("result.json"), again);
}
