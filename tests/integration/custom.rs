//! Data from elsewhere: frames, actions and a control period make a dataset that trains with
//! the recipe its frames call for (the generic one, or the arm's when they turn about a hub),
//! or an environment's, without true states.

use std::path::Path;

use ndarray::{Array0, Array3, Array5};
use ndarray_npy::NpzWriter;
use procl::data::{CollectConfig, Dataset, IMPORTED_SOURCE, collect};
use procl::envs::EnvKind;

use crate::cli::{fails_with, path_str, strs, succeeds, tiny_ablate};

/// Writes the three arrays a custom dataset needs, and nothing else.
fn write_custom(path: &Path, obs: &Array5<u8>, actions: &Array3<f32>, control_dt_s: Option<f64>) {
    let mut npz = NpzWriter::new(std::fs::File::create(path).unwrap());
    npz.add_array("obs", obs).unwrap();
    npz.add_array("actions", actions).unwrap();
    if let Some(dt) = control_dt_s {
        npz.add_array("control_dt_s", &Array0::from_elem((), dt))
            .unwrap();
    }
    npz.finish().unwrap();
}

/// Point-mass frames and actions of `episodes` x `steps`, as another system would record them.
fn recorded(episodes: usize, steps: usize) -> (Array5<u8>, Array3<f32>) {
    let config = CollectConfig {
        transitions: episodes * steps,
        episode_len: steps,
        ..CollectConfig::new(EnvKind::PointMass, 4)
    };
    let data = collect(&config, |_| {}).unwrap();
    (data.obs, data.actions)
}

#[test]
fn frames_actions_and_a_period_are_a_dataset() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("camera.npz");
    let (obs, actions) = recorded(3, 12);
    write_custom(&path, &obs, &actions, Some(0.05));
    let data = Dataset::load(&path).unwrap();
    assert_eq!(data.meta.env, None);
    assert_eq!(data.meta.source_name(), "custom");
    assert_eq!(data.meta.source, IMPORTED_SOURCE);
    assert_eq!(data.meta.control_dt_s, 0.05);
    assert_eq!((data.states.as_ref(), data.config_dim()), (None, None));
    assert_eq!((data.obs, data.actions), (obs, actions));
    // Saved by procl it keeps its metadata and still has no states.
    let again = dir.path().join("again.npz");
    let loaded = Dataset::load(&path).unwrap();
    loaded.save(&again, false).unwrap();
    assert_eq!(Dataset::load(&again).unwrap(), loaded);
}

#[test]
fn broken_custom_arrays_get_one_line_errors() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("bad.npz");
    let (obs, actions) = recorded(2, 6);
    let message = |obs: &Array5<u8>, actions: &Array3<f32>, dt: Option<f64>| {
        write_custom(&path, obs, actions, dt);
        let msg = Dataset::load(&path).unwrap_err().to_string();
        assert!(msg.contains(path_str(&path)), "{msg}");
        assert!(!msg.contains('\n'), "{msg}");
        msg
    };
    assert!(message(&obs, &actions, None).contains("missing array `control_dt_s`"));
    assert!(message(&obs, &actions, Some(0.0)).contains("`control_dt_s` = 0"));
    let small_frames = Array5::<u8>::zeros((2, 7, 48, 48, 3));
    let msg = message(&small_frames, &actions, Some(0.1));
    assert!(msg.contains("expected [2, 7, 64, 64, 3]"), "{msg}");
    let mut strong = actions.clone();
    strong[[1, 2, 0]] = 1.5;
    let msg = message(&obs, &strong, Some(0.1));
    assert!(msg.contains("`actions`[1, 2, 0] is 1.5"), "{msg}");
    assert!(msg.contains("[-1, 1]"), "{msg}");
    let mut nan = actions.clone();
    nan[[0, 5, 1]] = f32::NAN;
    assert!(message(&obs, &nan, Some(0.1)).contains("`actions`[0, 5, 1] is NaN"));
    let short_obs = obs.slice(ndarray::s![.., ..2, .., .., ..]).to_owned();
    let short_actions = actions.slice(ndarray::s![.., ..1, ..]).to_owned();
    let msg = message(&short_obs, &short_actions, Some(0.1));
    assert!(msg.contains("at least 1 episode of 2 steps"), "{msg}");
}

#[test]
fn a_corrupted_byte_in_an_uncompressed_file_is_caught_by_its_checksum() {
    // np.savez stores arrays uncompressed, so a flipped pixel still parses as a pixel; the
    // archive's CRC-32 is what refuses it.
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("camera.npz");
    let (obs, actions) = recorded(2, 6);
    write_custom(&path, &obs, &actions, Some(0.05));
    let mut bytes = std::fs::read(&path).unwrap();
    bytes[4096] ^= 0x10; // inside `obs`' pixels (the archive starts with it)
    std::fs::write(&path, &bytes).unwrap();
    let err = Dataset::load(&path).unwrap_err().to_string();
    assert!(
        err.contains("array `obs`") && err.contains("checksum"),
        "{err}"
    );
}

#[test]
fn custom_data_trains_from_the_command_line_without_state_diagnostics() {
    let dir = tempfile::tempdir().unwrap();
    let data = dir.path().join("camera.npz");
    let (obs, actions) = recorded(4, 10);
    write_custom(&data, &obs, &actions, Some(0.05));
    let info = succeeds(&["info", "--data", path_str(&data)]);
    let info = String::from_utf8_lossy(&info.stdout);
    assert!(info.contains("custom (imported)"), "{info}");
    assert!(info.contains("no true states"), "{info}");
    assert!(info.contains("frames turn about no hub"), "{info}");

    let run = dir.path().join("run");
    let args = [
        "train",
        "--data",
        path_str(&data),
        "--out",
        path_str(&run),
        "--steps",
        "2",
    ];
    let out = succeeds(&args);
    let stdout = String::from_utf8_lossy(&out.stdout);
    assert!(stdout.contains("latent diagnostics skipped"), "{stdout}");
    assert!(stdout.contains("the generic recipe"), "{stdout}");
    let config: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(run.join("config.json")).unwrap()).unwrap();
    assert_eq!(config["env"], "custom");
    assert_eq!(config["control_dt_s"], 0.05);
    // The generic recipe orients the latent by its response to the action.
    assert_eq!(config["orientation_criterion"], "action-response");
    assert!(!run.join("diagnostics.json").exists());
    fails_with(&["eval", "--run", path_str(&run)], "trained on custom data");

    // An environment's recipe on custom data, and the option refused on an environment's data.
    let reacher_recipe = dir.path().join("reacher-recipe");
    succeeds(&[
        "train",
        "--data",
        path_str(&data),
        "--out",
        path_str(&reacher_recipe),
        "--steps",
        "1",
        "--preset-env",
        "reacher",
    ]);
    let config: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(reacher_recipe.join("config.json")).unwrap())
            .unwrap();
    assert_eq!(config["model"]["encoder"]["head"]["polar"], true);
    assert_eq!(config["env"], "custom");
    let pm = dir.path().join("pm.npz");
    succeeds(&[
        "collect",
        "--env",
        "point-mass",
        "--transitions",
        "40",
        "--episode-len",
        "10",
        "--out",
        path_str(&pm),
    ]);
    fails_with(
        &[
            "train",
            "--data",
            path_str(&pm),
            "--out",
            path_str(&dir.path().join("x")),
            "--preset-env",
            "fetch",
        ],
        "preset-env",
    );
    // A config file written for an environment is refused on custom data by name.
    let toml = dir.path().join("pm.toml");
    std::fs::write(&toml, "env = \"point-mass\"\n").unwrap();
    fails_with(
        &[
            "train",
            "--data",
            path_str(&data),
            "--out",
            path_str(&dir.path().join("y")),
            "--config",
            path_str(&toml),
        ],
        "the dataset is from custom",
    );
}

#[test]
fn a_custom_action_dimension_sizes_the_latent() {
    // Three action components (as a 3-D end effector would take), frames from the point mass.
    let (obs, actions) = recorded(2, 8);
    let mut actions3 = Array3::<f32>::zeros((2, 8, 3));
    actions3
        .slice_mut(ndarray::s![.., .., ..2])
        .assign(&actions);
    let meta = procl::data::DatasetMeta::custom(0.1);
    let data = Dataset::new(meta, obs, actions3, None).unwrap();
    let base = procl::train::ConfigBase::for_dataset(&data, None).unwrap();
    let config = procl::train::config_from_table(toml::Table::new(), base, None).unwrap();
    assert_eq!(config.model.encoder.latent_dim, 3);
    assert_eq!(config.model.dynamics.latent_dim, 3);
    assert_eq!(config.control_dt_s(), 0.1);
    let nvae =
        procl::train::config_from_table(toml::Table::new(), base, Some(procl::train::Method::Nvae))
            .unwrap();
    assert_eq!(nvae.nvae.map(|n| n.latent_dim), Some(3));
    let dir = tempfile::tempdir().unwrap();
    let mut config = config;
    config.steps = 1;
    config.batch_size = 4;
    crate::support::train_into(&config, &data, dir.path(), false);
}

#[test]
fn a_variant_recorded_as_custom_trains_with_the_recipe_its_frames_call_for_and_evaluates_in_its_simulator()
 {
    let dir = tempfile::tempdir().unwrap();
    let variant = dir.path().join("variant.toml");
    std::fs::write(
        &variant,
        "[reacher]\nbase_m = [0.035, -0.025]\narm_rgb = [0.3, 0.6, 0.8]\n",
    )
    .unwrap();
    let data = dir.path().join("variant.npz");
    let collect = |extra: &[&str], out: &Path| {
        let mut args = vec![
            "collect",
            "--env-config",
            path_str(&variant),
            "--transitions",
            "400",
            "--episode-len",
            "10",
            "--out",
            path_str(out),
        ];
        args.extend_from_slice(extra);
        args.into_iter().map(String::from).collect::<Vec<_>>()
    };
    let args = collect(&["--as-custom"], &data);
    succeeds(&args.iter().map(String::as_str).collect::<Vec<_>>());
    let info = succeeds(&["info", "--data", path_str(&data)]);
    let info = String::from_utf8_lossy(&info.stdout);
    assert!(info.contains("frames turn about a hub at"), "{info}");
    assert!(info.contains("polar keypoints' cut"), "{info}");
    let loaded = Dataset::load(&data).unwrap();
    assert_eq!(loaded.meta.env, None);
    let recorded = loaded.meta.env_config.clone().unwrap();
    assert_eq!(recorded.kind(), EnvKind::Reacher);
    assert!(loaded.states.is_some());

    // The frames are the variant's: the same seed in the default reacher draws another image.
    let plain = dir.path().join("plain.npz");
    succeeds(&[
        "collect",
        "--env",
        "reacher",
        "--transitions",
        "400",
        "--episode-len",
        "10",
        "--out",
        path_str(&plain),
    ]);
    let plain = Dataset::load(&plain).unwrap();
    assert_eq!(plain.meta.env_config, None);
    assert_eq!(plain.actions, loaded.actions);
    assert_ne!(plain.obs, loaded.obs);

    // Training reads nothing of the simulator, only the frames: they turn about the moved
    // shoulder, so the arm's recipe trains them, with polar keypoints about it.
    let run = dir.path().join("run");
    let out = succeeds(&[
        "train",
        "--data",
        path_str(&data),
        "--out",
        path_str(&run),
        "--steps",
        "2",
    ]);
    let stdout = String::from_utf8_lossy(&out.stdout);
    assert!(stdout.contains("turn about a hub at pixel"), "{stdout}");
    let config: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(run.join("config.json")).unwrap()).unwrap();
    assert_eq!(config["env"], "custom");
    assert_eq!(config["model"]["encoder"]["head"]["polar"], true);
    let (_, model) = procl::train::RunPaths::new(&run)
        .load_trained(&procl::model::cpu_device())
        .unwrap();
    let procl::train::TrainedModel::Procl(model) = model else {
        panic!("a ProCL run");
    };
    // The shoulder is at pixel (35.6, 34.6), image coordinates (0.1125, 0.0804).
    let [x, y] = model.encoder.polar_centre().unwrap();
    assert!(
        (x - 0.1125).abs() < 1.0 / 32.0 && (y - 0.0804).abs() < 1.0 / 32.0,
        "{x} {y}"
    );
    // The NewtonianVAE baseline gets the same recipe's head about the same hub.
    let nvae = dir.path().join("nvae");
    succeeds(&[
        "train",
        "--data",
        path_str(&data),
        "--out",
        path_str(&nvae),
        "--method",
        "nvae",
        "--steps",
        "1",
    ]);
    let (_, model) = procl::train::RunPaths::new(&nvae)
        .load_trained(&procl::model::cpu_device())
        .unwrap();
    let procl::train::TrainedModel::Nvae(model) = model else {
        panic!("a NewtonianVAE run");
    };
    assert_eq!(model.encoder.polar_centre(), Some([x, y]));
    let generic = dir.path().join("generic");
    succeeds(&[
        "train",
        "--data",
        path_str(&data),
        "--out",
        path_str(&generic),
        "--steps",
        "1",
        "--preset-env",
        "generic",
    ]);
    let config: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(generic.join("config.json")).unwrap())
            .unwrap();
    assert_eq!(config["model"]["encoder"]["head"]["polar"], false);
    // Evaluation steps the recorded variant.
    succeeds(&["eval", "--run", path_str(&run), "--episodes", "2"]);
    let report: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(run.join("eval.json")).unwrap()).unwrap();
    assert_eq!(report["env"], "reacher");
    assert_eq!(
        report["env_config"]["reacher"]["base_m"],
        serde_json::json!([0.035, -0.025])
    );
    assert_eq!(report["protocol"]["distance_unit"], "rad (joint space)");

    // The variant renders, and its demonstrations are tracked by the run trained on it; the
    // default reacher's are refused.
    let strip = dir.path().join("strip.png");
    succeeds(&[
        "render",
        "--env-config",
        path_str(&variant),
        "--frames",
        "2",
        "--out",
        path_str(&strip),
    ]);
    assert!(strip.exists());
    // A camera that cannot draw the frames is refused by its field, before anything is written.
    let blind = dir.path().join("blind.toml");
    std::fs::write(&blind, "[reacher.camera]\nfovy_deg = 0.0\n").unwrap();
    let blind_strip = dir.path().join("blind.png");
    fails_with(
        &[
            "render",
            "--env-config",
            path_str(&blind),
            "--out",
            path_str(&blind_strip),
        ],
        "reacher.camera.fovy_deg",
    );
    assert!(!blind_strip.exists());
    let demo = |extra: &[&str], out: &Path| {
        let mut args = vec![
            "demonstrate",
            "--episodes",
            "1",
            "--steps",
            "20",
            "--out",
            path_str(out),
        ];
        args.extend_from_slice(extra);
        args.into_iter().map(String::from).collect::<Vec<_>>()
    };
    let variant_demo = dir.path().join("variant-demo.npz");
    let args = demo(&["--env-config", path_str(&variant)], &variant_demo);
    succeeds(&args.iter().map(String::as_str).collect::<Vec<_>>());
    succeeds(&[
        "track",
        "--run",
        path_str(&run),
        "--demo",
        path_str(&variant_demo),
    ]);
    let plain_demo = dir.path().join("plain-demo.npz");
    let args = demo(&["--env", "reacher"], &plain_demo);
    succeeds(&args.iter().map(String::as_str).collect::<Vec<_>>());
    fails_with(
        &[
            "track",
            "--run",
            path_str(&run),
            "--demo",
            path_str(&plain_demo),
        ],
        "another configuration of reacher",
    );

    // A file for another environment than --env, and an arm out of view, are refused by name.
    let args = collect(&["--env", "point-mass"], &dir.path().join("x.npz"));
    let args: Vec<&str> = args.iter().map(String::as_str).collect();
    fails_with(&args, "configures reacher, not --env point-mass");
    std::fs::write(&variant, "[reacher]\nbase_m = [0.1, 0.0]\n").unwrap();
    let args = collect(&[], &dir.path().join("y.npz"));
    let args: Vec<&str> = args.iter().map(String::as_str).collect();
    fails_with(&args, "reacher.base_m");
    assert!(!dir.path().join("y.npz").exists());
}

/// An ablation grid on a variant recorded as custom: its cells start from the recipe the frames
/// call for (the arm's, with polar keypoints), and each run is evaluated in the variant.
#[test]
fn an_ablation_grid_on_a_variant_recorded_as_custom_starts_from_the_recipe_of_its_frames() {
    let dir = tempfile::tempdir().unwrap();
    let variant = dir.path().join("variant.toml");
    std::fs::write(&variant, "[reacher]\nbase_m = [0.035, -0.025]\n").unwrap();
    let grid = dir.path().join("grid.toml");
    std::fs::write(
        &grid,
        "[base]\nsteps = 2\nbatch_size = 8\n[[cell]]\nname = \"default\"\n",
    )
    .unwrap();
    let out = dir.path().join("grid");
    let ablate = |variant: &Path, grid: &Path, extra: &[&str]| {
        let source = ["--env-config", path_str(variant), "--as-custom"];
        tiny_ablate(&source, grid, 1, 400, &out, extra)
    };
    // Listing checks the cells as the run will: against a custom base, which refuses the
    // environment's name.
    let named = dir.path().join("named.toml");
    std::fs::write(
        &named,
        "[base]\nenv = \"reacher\"\n[[cell]]\nname = \"default\"\n",
    )
    .unwrap();
    fails_with(
        &strs(&ablate(&variant, &named, &["--list-tasks"])),
        "custom",
    );
    succeeds(&strs(&ablate(&variant, &grid, &["--list-tasks"])));
    succeeds(&strs(&ablate(&variant, &grid, &[])));
    let data = Dataset::load(&out.join("reacher.npz")).unwrap();
    assert_eq!(data.meta.env, None);
    let run = out.join("default/seed-0");
    let config: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(run.join("config.json")).unwrap()).unwrap();
    assert_eq!(config["env"], "custom");
    assert_eq!(config["model"]["encoder"]["head"]["polar"], true);
    let report: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(run.join("eval.json")).unwrap()).unwrap();
    assert_eq!(
        report["env_config"]["reacher"]["base_m"],
        serde_json::json!([0.035, -0.025])
    );
    let results: Vec<serde_json::Value> =
        serde_json::from_str(&std::fs::read_to_string(out.join("ablation.json")).unwrap()).unwrap();
    assert_eq!(results.len(), 1);
    // The folder's dataset is this variant's: another one is refused, by name.
    let other = dir.path().join("other.toml");
    std::fs::write(&other, "[reacher]\nbase_m = [0.02, 0.0]\n").unwrap();
    fails_with(
        &strs(&ablate(&other, &grid, &[])),
        "another environment configuration",
    );
}
