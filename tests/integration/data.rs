//! Datasets: determinism, the NPZ round trip, and validation of broken files.

use std::path::Path;

use ndarray::{Array1, Array3, Array5};
use ndarray_npy::NpzWriter;
use procl::data::{CollectConfig, Dataset, collect};
use procl::envs::EnvKind;

fn small(env: EnvKind, seed: u64) -> Dataset {
    let config = CollectConfig {
        transitions: 60,
        episode_len: 20,
        ..CollectConfig::new(env, seed)
    };
    collect(&config, |_| {}).unwrap()
}

#[test]
fn round_trip_and_identical_bytes() {
    let dir = tempfile::tempdir().unwrap();
    let (a, b) = (dir.path().join("a.npz"), dir.path().join("b.npz"));
    small(EnvKind::Reacher, 5).save(&a, false).unwrap();
    small(EnvKind::Reacher, 5).save(&b, false).unwrap();
    assert_eq!(std::fs::read(&a).unwrap(), std::fs::read(&b).unwrap());
    let loaded = Dataset::load(&a).unwrap();
    assert_eq!(loaded, small(EnvKind::Reacher, 5));
    assert_eq!((loaded.episodes(), loaded.steps()), (3, 20));
    assert_ne!(small(EnvKind::Reacher, 6).obs, loaded.obs);
}

#[test]
fn existing_file_is_not_clobbered() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("keep.npz");
    std::fs::write(&path, b"precious").unwrap();
    let err = small(EnvKind::PointMass, 0).save(&path, false).unwrap_err();
    assert!(err.to_string().contains("--force"));
    assert_eq!(std::fs::read(&path).unwrap(), b"precious");
    small(EnvKind::PointMass, 0).save(&path, true).unwrap();
    assert!(Dataset::load(&path).is_ok());
}

fn load_err(path: &Path) -> String {
    let msg = Dataset::load(path).unwrap_err().to_string();
    assert!(
        msg.contains(&path.display().to_string()),
        "message does not name the file: {msg}"
    );
    assert!(!msg.contains('\n'), "multi-line message: {msg}");
    msg
}

#[test]
fn missing_truncated_and_corrupt_files_are_reported() {
    let dir = tempfile::tempdir().unwrap();
    let good = dir.path().join("good.npz");
    small(EnvKind::PointMass, 1).save(&good, false).unwrap();
    let bytes = std::fs::read(&good).unwrap();

    assert!(load_err(&dir.path().join("nope.npz")).contains("not found"));
    let truncated = dir.path().join("truncated.npz");
    std::fs::write(&truncated, &bytes[..bytes.len() / 2]).unwrap();
    load_err(&truncated);
    let garbage = dir.path().join("garbage.npz");
    std::fs::write(&garbage, b"this is not a zip file at all").unwrap();
    assert!(load_err(&garbage).contains("npz"));
    // Flip bytes in the middle of the compressed payload.
    let mut flipped = bytes.clone();
    for b in &mut flipped[bytes.len() / 3..bytes.len() / 3 + 64] {
        *b ^= 0x5a;
    }
    let corrupt = dir.path().join("corrupt.npz");
    std::fs::write(&corrupt, &flipped).unwrap();
    load_err(&corrupt);
}

/// Writes an npz with the given arrays and valid metadata for `env`.
fn write_npz(
    path: &Path,
    obs: &Array5<u8>,
    actions: &Array3<f32>,
    states: &Array3<f32>,
    env: &str,
) {
    let meta = format!(
        r#"{{"format_version":1,"env":"{env}","control_dt_s":0.02,"seed":0,"source":"random-control","procl_version":"0"}}"#
    );
    let mut npz = NpzWriter::new(std::fs::File::create(path).unwrap());
    npz.add_array("obs", obs).unwrap();
    npz.add_array("actions", actions).unwrap();
    npz.add_array("states", states).unwrap();
    npz.add_array("meta", &Array1::from(meta.into_bytes()))
        .unwrap();
    npz.finish().unwrap();
}

#[test]
fn wrong_shapes_and_values_are_reported() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("bad.npz");
    let obs = Array5::<u8>::zeros((2, 11, 64, 64, 3));
    let actions = Array3::<f32>::zeros((2, 10, 2));
    let states = Array3::<f32>::zeros((2, 11, 4));

    write_npz(
        &path,
        &Array5::zeros((2, 11, 32, 32, 3)),
        &actions,
        &states,
        "point-mass",
    );
    assert!(load_err(&path).contains("`obs` has shape"));
    write_npz(
        &path,
        &obs,
        &Array3::zeros((2, 10, 3)),
        &states,
        "point-mass",
    );
    assert!(load_err(&path).contains("components"));
    write_npz(
        &path,
        &obs,
        &actions,
        &Array3::zeros((2, 11, 6)),
        "point-mass",
    );
    assert!(load_err(&path).contains("`states` has shape"));
    let mut nan_actions = actions.clone();
    nan_actions[[1, 3, 0]] = f32::NAN;
    write_npz(&path, &obs, &nan_actions, &states, "point-mass");
    assert!(load_err(&path).contains("finite"));
    write_npz(&path, &obs, &actions, &states, "cartpole");
    assert!(load_err(&path).contains("meta"));
    write_npz(&path, &obs, &actions, &states, "reacher");
    assert!(Dataset::load(&path).is_ok());
}
