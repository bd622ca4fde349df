//! Training through the library API: loss goes down, runs are deterministic, `resume` is exact,
//! checkpoints round-trip, and bad configurations, datasets and files are rejected by name.

use std::collections::BTreeMap;
use std::path::Path;

use super::support::{train_error, train_into};
use procl::data::{CollectConfig, Dataset, collect};
use procl::envs::EnvKind;
use procl::model::{EncoderHead, ProclModel, cpu_device, frames_to_tensor, to_vec};
use procl::train::{Method, Preset, RunPaths, TrainConfig, config_from_table, train};
use procl::{CheckpointMeta, load_checkpoint, save_checkpoint};

fn dataset(env: EnvKind, transitions: usize, episode_len: usize, seed: u64) -> Dataset {
    let config = CollectConfig {
        transitions,
        episode_len,
        ..CollectConfig::new(env, seed)
    };
    collect(&config, |_| {}).unwrap()
}

/// 600 point-mass transitions in episodes of 50 steps.
fn point_mass_data() -> Dataset {
    dataset(EnvKind::PointMass, 600, 50, 3)
}

/// The procl preset shrunk for a 2-core test machine: batch 16, a narrow trunk, 8 keypoints,
/// 32 hidden dynamics units.
fn tiny_config(steps: u64, checkpoint_every: u64) -> TrainConfig {
    let mut config = TrainConfig::preset(Preset::Procl, Method::Procl, EnvKind::PointMass);
    config.seed = 5;
    config.steps = steps;
    config.batch_size = 16;
    config.checkpoint_every = checkpoint_every;
    config.model.encoder.trunk_channels = [8, 8];
    config.model.encoder.head = EncoderHead::SoftArgmax {
        keypoints: 8,
        hidden: 0,
        polar: false,
        pairwise_angles: false,
    };
    config.model.dynamics.hidden = 32;
    // The procl preset searches the latent orientation every 50 steps, which must divide
    // checkpoint_every; search at every checkpoint instead.
    config.orientation_search_every = checkpoint_every;
    config
}

/// The rows of a run's metrics.csv without the wall-clock `seconds` column, checking the header.
fn metrics_rows(dir: &Path) -> Vec<Vec<f64>> {
    let text = std::fs::read_to_string(RunPaths::new(dir).metrics()).unwrap();
    let mut lines = text.lines();
    assert_eq!(
        lines.next(),
        Some("step,total,cpc,cons,curv,lyap,sign,seconds")
    );
    lines
        .map(|line| {
            let mut row: Vec<f64> = line.split(',').map(|x| x.parse().unwrap()).collect();
            assert_eq!(row.len(), 8, "bad row {line}");
            row.pop();
            row
        })
        .collect()
}

fn checkpoint_bytes(dir: &Path) -> Vec<u8> {
    std::fs::read(RunPaths::new(dir).checkpoint()).unwrap()
}

type Tensors = BTreeMap<String, (Vec<usize>, Vec<u8>)>;

/// A run's checkpoint as (metadata, tensors by name), to say what differs.
fn checkpoint_contents(dir: &Path) -> (BTreeMap<String, String>, Tensors) {
    let bytes = checkpoint_bytes(dir);
    let (_, header) = safetensors::SafeTensors::read_metadata(&bytes).unwrap();
    let metadata = header.metadata().clone().unwrap_or_default();
    let tensors = safetensors::SafeTensors::deserialize(&bytes).unwrap();
    let tensors = tensors
        .tensors()
        .into_iter()
        .map(|(name, view)| (name, (view.shape().to_vec(), view.data().to_vec())))
        .collect();
    (metadata.into_iter().collect(), tensors)
}

/// The two runs' checkpoints hold the same tensors and metadata, and are the same bytes.
fn assert_same_checkpoint(a: &Path, b: &Path, what: &str) {
    let ((meta_a, tensors_a), (meta_b, tensors_b)) =
        (checkpoint_contents(a), checkpoint_contents(b));
    assert_eq!(meta_a, meta_b, "{what}: checkpoint metadata differs");
    let only = |x: &Tensors, y: &Tensors| {
        x.keys()
            .filter(|name| !y.contains_key(*name))
            .cloned()
            .collect::<Vec<_>>()
    };
    let (only_a, only_b) = (only(&tensors_a, &tensors_b), only(&tensors_b, &tensors_a));
    assert!(
        only_a.is_empty() && only_b.is_empty(),
        "{what}: tensors only in the first: {only_a:?}; only in the second: {only_b:?}"
    );
    let differing: Vec<&String> = tensors_a
        .keys()
        .filter(|name| tensors_a[*name] != tensors_b[*name])
        .collect();
    assert!(
        differing.is_empty(),
        "{what}: tensors differ: {differing:?}"
    );
    assert!(
        checkpoint_bytes(a) == checkpoint_bytes(b),
        "{what}: same tensors and metadata, different bytes (metadata key order?)"
    );
}

fn mean_column(rows: &[Vec<f64>], column: usize) -> f64 {
    rows.iter().map(|r| r[column]).sum::<f64>() / rows.len() as f64
}

#[test]
fn training_lowers_cpc_and_total_loss() {
    let data = point_mass_data();
    let dir = tempfile::tempdir().unwrap();
    // CPC sits at chance for the first ~60 steps (fresh soft-argmax latents barely differ
    // between frames), then drops; lr 3e-3 over 150 steps gets clearly past that (measured:
    // CPC 2.77 -> 0.74, total -10.6 -> -14.3 in the first vs last 5 steps; lr 1e-3 still sat
    // at 2.77 after 150 steps).
    let steps = 150;
    let mut config = tiny_config(steps, 50);
    config.learning_rate = 3e-3;
    let mut seen = vec![];
    let summary = train(
        &config,
        &data,
        &RunPaths::new(dir.path()),
        false,
        &cpu_device(),
        |step, values| seen.push((step, values.total())),
    )
    .unwrap();
    assert_eq!(summary.steps_done, steps);
    assert_eq!(
        seen.iter().map(|s| s.0).collect::<Vec<_>>(),
        (1..=steps).collect::<Vec<_>>()
    );

    let rows = metrics_rows(dir.path());
    assert_eq!(rows.len(), steps as usize);
    for (k, row) in rows.iter().enumerate() {
        assert_eq!(row[0], (k + 1) as f64);
        assert!(row.iter().all(|x| x.is_finite()), "row {k}: {row:?}");
    }
    // The progress callback and the csv report the same totals (the csv has 6 decimals).
    for ((_, total), row) in seen.iter().zip(&rows) {
        assert!((total - row[1]).abs() < 1e-5, "{total} vs {}", row[1]);
    }
    let (first, last) = (&rows[..5], &rows[rows.len() - 5..]);
    let (cpc0, cpc1) = (mean_column(first, 2), mean_column(last, 2));
    let (total0, total1) = (mean_column(first, 1), mean_column(last, 1));
    // CPC starts at chance, ln K = ln 16 = 2.7726, and must at least halve.
    assert!((cpc0 - 16f64.ln()).abs() < 0.05, "initial CPC {cpc0}");
    assert!(cpc1 < 0.5 * cpc0, "CPC {cpc0} -> {cpc1}");
    assert!(total1 < total0 - 1.0, "total {total0} -> {total1}");
    // The final checkpoint holds the last step.
    let model = config.model.init(config.seed, &cpu_device()).unwrap();
    let (_, adam, meta) = load_checkpoint(
        &RunPaths::new(dir.path()).checkpoint(),
        model,
        &cpu_device(),
    )
    .unwrap();
    assert_eq!(meta, CheckpointMeta::at(steps));
    assert_eq!(adam.step, steps);
}

#[test]
fn same_config_and_seed_give_identical_checkpoints() {
    let data = point_mass_data();
    let dir = tempfile::tempdir().unwrap();
    let config = tiny_config(30, 10);
    let [a, b, c] = ["a", "b", "c"].map(|name| dir.path().join(name));
    train_into(&config, &data, &a, false);
    train_into(&config, &data, &b, false);
    assert_same_checkpoint(&a, &b, "same config and seed");
    assert_eq!(metrics_rows(&a), metrics_rows(&b));
    // The comparison can fail: another seed gives other weights.
    let other = TrainConfig {
        seed: config.seed + 1,
        ..config.clone()
    };
    train_into(&other, &data, &c, false);
    assert!(checkpoint_contents(&a).1 != checkpoint_contents(&c).1);
    // A second fresh run into a finished folder refuses to overwrite it.
    let err = train_error(&config, &data, &a, false);
    assert!(
        err.contains("already holds a trained model") && err.contains("--resume"),
        "{err}"
    );
}

#[test]
fn resumed_run_equals_uninterrupted_run() {
    let data = point_mass_data();
    let dir = tempfile::tempdir().unwrap();
    let (k, every) = (20, 10);
    // Clipped at a low percentile, nearly every step's gradient depends on the norms of all
    // the steps before it, which the checkpoint must carry across the resume.
    let full = TrainConfig {
        gradient_clip_percentile: Some(10.0),
        ..tiny_config(2 * k, every)
    };
    let (a, b) = (dir.path().join("a"), dir.path().join("b"));
    train_into(&full, &data, &a, false);

    // Run B stops at step k (a checkpoint step, as after a crash), then resumes to 2k.
    let half = TrainConfig {
        steps: k,
        ..full.clone()
    };
    train_into(&half, &data, &b, false);
    let paths_b = RunPaths::new(&b);
    let model = full.model.init(full.seed, &cpu_device()).unwrap();
    let (_, _, meta) = load_checkpoint(&paths_b.checkpoint(), model, &cpu_device()).unwrap();
    assert_eq!(meta.step, k);
    // Resuming requires the saved config to be this one, but for a larger budget.
    let other = TrainConfig {
        seed: full.seed + 1,
        ..full.clone()
    };
    let err = train(&other, &data, &paths_b, true, &cpu_device(), |_, _| {})
        .unwrap_err()
        .to_string();
    assert!(err.contains("resume"), "{err}");
    let mut resumed_steps = vec![];
    train(&full, &data, &paths_b, true, &cpu_device(), |step, _| {
        resumed_steps.push(step)
    })
    .unwrap();
    assert_eq!(resumed_steps, ((k + 1)..=(2 * k)).collect::<Vec<_>>());

    // Rows 1..k come from B's first run, k+1..2k from the resumed one.
    let (rows_a, rows_b) = (metrics_rows(&a), metrics_rows(&b));
    assert_eq!(rows_a.len(), 2 * k as usize);
    assert_eq!(rows_a[..k as usize], rows_b[..k as usize]);
    // Weights, Adam moments and the orientation first (names what differs), then the losses.
    assert_same_checkpoint(&a, &b, "resumed vs uninterrupted");
    assert_eq!(rows_a, rows_b, "metrics differ (seconds column ignored)");
}

#[test]
fn a_snapshot_holds_the_weights_of_a_run_that_stopped_at_its_step() {
    let data = point_mass_data();
    let dir = tempfile::tempdir().unwrap();
    let full = TrainConfig {
        snapshot_every: 10,
        ..tiny_config(20, 10)
    };
    let short = TrainConfig {
        steps: 10,
        snapshot_every: 0,
        ..full.clone()
    };
    let (a, b) = (dir.path().join("a"), dir.path().join("b"));
    train_into(&full, &data, &a, false);
    train_into(&short, &data, &b, false);
    let run = RunPaths::new(&a);
    assert_eq!(run.snapshot_steps(), [10, 20]);
    // The snapshot is a run folder of its own: it loads as one, with the run's config.
    let snapshot = run.snapshot(10);
    let (config, _) = snapshot.load_model(&cpu_device()).unwrap();
    assert_eq!(config, full);
    let weights = |dir: &Path| {
        let mut tensors = checkpoint_contents(dir).1;
        tensors.retain(|name, _| name.starts_with("model."));
        tensors
    };
    assert_eq!(weights(&snapshot.dir), weights(&b));
    assert!(weights(&run.snapshot(20).dir) != weights(&b));
    assert_eq!(weights(&run.snapshot(20).dir), weights(&a));
}

/// A few frames of the dataset as the network input.
fn frame_batch(data: &Dataset) -> burn::tensor::Tensor<4> {
    let frames: Vec<&[u8]> = (0..6).map(|t| data.frame(t % 2, 3 * t)).collect();
    frames_to_tensor(frames.into_iter(), &cpu_device())
}

fn encode(model: &ProclModel, data: &Dataset) -> Vec<f32> {
    to_vec(model.encoder.forward(frame_batch(data)))
}

#[test]
fn checkpoint_round_trip_gives_identical_outputs() {
    let data = point_mass_data();
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("model.safetensors");
    let config = tiny_config(1, 1).model;
    let device = cpu_device();
    // A non-identity orientation (swap the axes, flip one: a signed permutation), so the
    // non-trained orientation has to round-trip too.
    let orientation = [0.0, -1.0, 1.0, 0.0];
    let saved = config
        .init(1, &device)
        .unwrap()
        .reorient_latent(&orientation);
    save_checkpoint(&path, &saved, None, &CheckpointMeta::at(7)).unwrap();

    let fresh = config.init(2, &device).unwrap();
    let before = encode(&fresh, &data);
    let want = encode(&saved, &data);
    assert!(before != want, "different seeds gave the same encoder");
    let (loaded, adam, meta) = load_checkpoint(&path, fresh, &device).unwrap();
    assert_eq!(meta, CheckpointMeta::at(7));
    assert_eq!(adam.step, 0);
    assert_eq!(encode(&loaded, &data), want);
    assert_eq!(loaded.latent_transform(), orientation.to_vec());
    // The dynamics came back too.
    let h = loaded.encoder.forward(frame_batch(&data));
    let dyn_out = |m: &ProclModel| {
        to_vec(
            m.dynamics
                .forward(h.clone(), h.clone() * 0.5, h.clone() * -1.0, 0.02)
                .z(),
        )
    };
    assert_eq!(dyn_out(&loaded), dyn_out(&saved));

    // A checkpoint of another architecture is refused by tensor name and shape, with the fix.
    let mut wide = config.clone();
    wide.encoder.trunk_channels = [16, 8];
    let err = load_checkpoint(&path, wide.init(0, &device).unwrap(), &device)
        .unwrap_err()
        .to_string();
    assert!(
        err.contains("shape") && err.contains("conv1") && err.contains("retrain"),
        "{err}"
    );
}

fn config_err(toml_text: &str) -> String {
    let table: toml::Table = toml_text.parse().unwrap();
    config_from_table(table, EnvKind::PointMass, None)
        .unwrap_err()
        .to_string()
}

#[test]
fn bad_configs_are_rejected_by_field_name() {
    // A valid table works and overrides the preset.
    let table: toml::Table = "learning_rate = 0.002\n[loss]\nkp = 5.0\n".parse().unwrap();
    let config = config_from_table(table, EnvKind::PointMass, None).unwrap();
    assert_eq!((config.learning_rate, config.loss.kp), (0.002, 5.0));
    assert_eq!(config.method, Method::Procl);

    let err = config_err("learning_rate = -1.0");
    assert!(err.contains("learning_rate"), "{err}");
    for bad in [
        "learning_rate = nan",
        "learning_rate = inf",
        "learning_rate = 0.0",
    ] {
        let err = config_err(bad);
        assert!(err.contains("learning_rate"), "{bad}: {err}");
    }
    let err = config_err("method = \"foo\"");
    assert!(err.contains("method") && err.contains("foo"), "{err}");
    let err = config_err("[loss]\nlatent_noise_std = -0.1");
    assert!(err.contains("loss.latent_noise_std"), "{err}");
    let err = config_err("[loss]\nkp = 0.0");
    assert!(err.contains("loss.kp"), "{err}");
    let err = config_err("batch_size = 1");
    assert!(err.contains("batch_size"), "{err}");
    let err = config_err("lerning_rate = 0.1");
    assert!(err.contains("lerning_rate"), "unknown key not named: {err}");
    // Unknown keys in nested tables are refused too, with their table's path.
    for (bad, table, key) in [
        (
            "[model]
encoders = 1",
            "model",
            "encoders",
        ),
        (
            "[model.encoder]
polar_angle_fall_off = 0.4",
            "model.encoder",
            "polar_angle_fall_off",
        ),
        (
            "[model.encoder.head]
keypoint = 8",
            "model.encoder.head",
            "keypoint",
        ),
        (
            "[model.dynamics]
hiden = 8",
            "model.dynamics",
            "hiden",
        ),
        (
            "[loss]
kp_ = 8.0",
            "loss",
            "kp_",
        ),
    ] {
        let err = config_err(bad);
        assert!(err.contains(table) && err.contains(key), "{bad}: {err}");
    }
    let err = config_err("method = \"pc3\"\n[loss]\nlambda_r = 1.0");
    assert!(err.contains("loss.lambda_r"), "{err}");

    // A non-finite learning rate given to `train` directly is refused before anything is
    // written.
    let data = dataset(EnvKind::PointMass, 40, 20, 0);
    let dir = tempfile::tempdir().unwrap();
    let run = dir.path().join("run");
    for lr in [f64::NAN, f64::INFINITY] {
        let config = TrainConfig {
            learning_rate: lr,
            ..tiny_config(2, 1)
        };
        let err = train_error(&config, &data, &run, false);
        assert!(err.contains("learning_rate"), "{err}");
    }
    assert!(!run.exists());
}

#[test]
fn dataset_of_another_env_is_rejected() {
    let reacher = dataset(EnvKind::Reacher, 40, 20, 0);
    let dir = tempfile::tempdir().unwrap();
    let run = dir.path().join("run");
    let err = train_error(&tiny_config(2, 1), &reacher, &run, false);
    assert!(
        err.contains("reacher") && err.contains("point-mass"),
        "{err}"
    );
    assert!(!run.exists(), "a refused run left a folder");
}

#[test]
fn corrupt_or_missing_checkpoints_are_reported_with_the_file() {
    let dir = tempfile::tempdir().unwrap();
    let device = cpu_device();
    let config = tiny_config(1, 1).model;
    let load_err = |path: &Path| {
        let err = load_checkpoint(path, config.init(0, &device).unwrap(), &device)
            .unwrap_err()
            .to_string();
        assert!(
            err.contains(&path.display().to_string()),
            "message does not name the file: {err}"
        );
        err
    };
    // Random bytes (a fixed LCG).
    let garbage = dir.path().join("garbage.safetensors");
    let mut state = 9u64;
    let bytes: Vec<u8> = (0..4096)
        .map(|_| {
            state = state
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            (state >> 56) as u8
        })
        .collect();
    std::fs::write(&garbage, &bytes).unwrap();
    load_err(&garbage);
    // A valid checkpoint cut in half.
    let good = dir.path().join("good.safetensors");
    save_checkpoint(
        &good,
        &config.init(0, &device).unwrap(),
        None,
        &CheckpointMeta::at(1),
    )
    .unwrap();
    let whole = std::fs::read(&good).unwrap();
    let truncated = dir.path().join("truncated.safetensors");
    std::fs::write(&truncated, &whole[..whole.len() / 2]).unwrap();
    load_err(&truncated);
    assert!(load_err(&dir.path().join("missing.safetensors")).contains("not found"));
    // The intact file loads.
    assert!(load_checkpoint(&good, config.init(0, &device).unwrap(), &device).is_ok());
}
