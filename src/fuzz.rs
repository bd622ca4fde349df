//! Fuzz targets: each feeds arbitrary bytes to one of procl's parsers the way a user's file
//! reaches it (written to a file, then read by the loader the commands use). A target must
//! never panic or abort, and every error it returns must be one line. `fuzz/` runs them under
//! libFuzzer (nightly Rust); `tests/integration/fuzz.rs` replays their seed inputs, the
//! inputs that once failed, and a fixed budget of seeded mutations on stable Rust.

use std::path::{Path, PathBuf};

use crate::error::{Error, Result};

/// One parser under test.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Target {
    /// A dataset `.npz` (zip, npy headers, arrays, metadata JSON): `Dataset::load`.
    Npz,
    /// A training config file (TOML over a preset): `config_from_toml`, for every environment.
    ConfigToml,
    /// An ablation grid file (TOML): `Grid::from_toml`, then its cells' configurations.
    GridToml,
    /// A run's checkpoint (safetensors with procl's metadata): `RunPaths::load_trained`.
    Checkpoint,
    /// A run's `config.json`: `RunPaths::load_config`.
    RunConfigJson,
    /// An experiment's `stages.json`.
    StagesJson,
    /// An ablation's `ablation.jsonl` and a task's `result.json`.
    AblationResults,
}

impl Target {
    pub const ALL: [Target; 7] = [
        Target::Npz,
        Target::ConfigToml,
        Target::GridToml,
        Target::Checkpoint,
        Target::RunConfigJson,
        Target::StagesJson,
        Target::AblationResults,
    ];

    /// The target's name (the fuzz crate's binary and the regression folder).
    pub fn name(self) -> &'static str {
        match self {
            Target::Npz => "npz",
            Target::ConfigToml => "config_toml",
            Target::GridToml => "grid_toml",
            Target::Checkpoint => "checkpoint",
            Target::RunConfigJson => "run_config_json",
            Target::StagesJson => "stages_json",
            Target::AblationResults => "ablation_results",
        }
    }
}

/// A scratch folder for one target's executions, with what the target reads besides the
/// fuzzed file (the checkpoint's `config.json`).
pub struct Harness {
    target: Target,
    dir: PathBuf,
}

impl Harness {
    /// Prepares `dir` (created if missing) for `target`.
    pub fn new(target: Target, dir: &Path) -> Result<Self> {
        std::fs::create_dir_all(dir).map_err(|e| Error::io(dir, e))?;
        if target == Target::Checkpoint {
            crate::fsutil::write_json(&dir.join("config.json"), &point_mass_config())?;
        }
        Ok(Self {
            target,
            dir: dir.to_path_buf(),
        })
    }

    /// Feeds `bytes` to the target's parser and returns its verdict. Panics only where the
    /// parser breaks its contract: an error message of more than one line.
    pub fn run(&self, bytes: &[u8]) -> Result<()> {
        self.parse(bytes).map_err(|e| self.one_line(e))
    }

    /// `error`, after asserting that its message is one line.
    fn one_line(&self, error: Error) -> Error {
        let message = error.to_string();
        assert!(
            !message.contains('\n'),
            "{}: multi-line error: {message:?}",
            self.target.name()
        );
        error
    }

    fn write(&self, name: &str, bytes: &[u8]) -> Result<PathBuf> {
        let path = self.dir.join(name);
        std::fs::write(&path, bytes).map_err(|e| Error::io(&path, e))?;
        Ok(path)
    }

    fn parse(&self, bytes: &[u8]) -> Result<()> {
        use crate::envs::EnvKind;
        match self.target {
            Target::Npz => crate::data::Dataset::load(&self.write("data.npz", bytes)?).map(drop),
            Target::ConfigToml => {
                // A config names at most one environment: accepted if any takes it, and every
                // refusal is one line.
                let path = self.write("config.toml", bytes)?;
                let mut verdict = Ok(());
                for env in [EnvKind::PointMass, EnvKind::Reacher, EnvKind::Fetch] {
                    match crate::train::config_from_toml(&path, env, None) {
                        Ok(_) => return Ok(()),
                        Err(e) => verdict = Err(self.one_line(e)),
                    }
                }
                verdict
            }
            Target::GridToml => {
                let grid =
                    crate::runner::ablate::Grid::from_toml(&self.write("grid.toml", bytes)?)?;
                grid.cell_configs(EnvKind::PointMass.into()).map(drop)
            }
            Target::Checkpoint => {
                self.write("model.safetensors", bytes)?;
                crate::train::RunPaths::new(&self.dir)
                    .load_trained(&crate::model::cpu_device())
                    .map(drop)
            }
            Target::RunConfigJson => {
                self.write("config.json", bytes)?;
                crate::train::RunPaths::new(&self.dir)
                    .load_config()
                    .map(drop)
            }
            Target::StagesJson => {
                crate::runner::experiment::read_stage_times(&self.write("stages.json", bytes)?)
                    .map(drop)
            }
            Target::AblationResults => {
                let jsonl = self.write("ablation.jsonl", bytes)?;
                let task = self.dir.join("cell").join("seed-0");
                std::fs::create_dir_all(&task).map_err(|e| Error::io(&task, e))?;
                let result = task.join(crate::runner::ablate::TASK_RESULT);
                std::fs::write(&result, bytes).map_err(|e| Error::io(&result, e))?;
                let tasks = [("cell".to_string(), 0), ("other".to_string(), 1)];
                crate::runner::ablate::read_results(&self.dir, &jsonl, &tasks).map(drop)
            }
        }
    }

    /// Valid inputs written by procl itself: the starting points of mutation.
    pub fn seeds(&self) -> Result<Vec<Vec<u8>>> {
        use crate::envs::EnvKind;
        let read = |path: &Path| std::fs::read(path).map_err(|e| Error::io(path, e));
        let seed_dir = self.dir.join("seeds");
        std::fs::create_dir_all(&seed_dir).map_err(|e| Error::io(&seed_dir, e))?;
        Ok(match self.target {
            Target::Npz => {
                let config = crate::data::CollectConfig {
                    transitions: 8,
                    episode_len: 4,
                    ..crate::data::CollectConfig::new(EnvKind::PointMass, 0)
                };
                let data = crate::data::collect(&config, |_| {})?;
                let path = seed_dir.join("data.npz");
                data.save(&path, true)?;
                // Stored (uncompressed) too, so that mutations reach the npy headers and the
                // arrays instead of stopping at the deflate stream.
                let mut stored = std::io::Cursor::new(Vec::new());
                let mut npz = ndarray_npy::NpzWriter::new(&mut stored);
                let fail = |e: ndarray_npy::WriteNpzError| Error::config("seed", e.to_string());
                npz.add_array("obs", &data.obs).map_err(fail)?;
                npz.add_array("actions", &data.actions).map_err(fail)?;
                npz.add_array("control_dt_s", &ndarray::arr0(data.meta.control_dt_s))
                    .map_err(fail)?;
                npz.finish().map_err(fail)?;
                vec![read(&path)?, stored.into_inner()]
            }
            Target::ConfigToml => vec![
                b"preset = \"paper\"\nseed = 3\n[loss]\nkp = 2.0\n".to_vec(),
                b"method = \"nvae\"\n[nvae]\nkl_standard_weight = 0.5\n".to_vec(),
                toml::to_string(&point_mass_config())
                    .map_err(|e| Error::config("seed", e.to_string()))?
                    .into_bytes(),
            ],
            Target::GridToml => vec![
                b"[base]\nsteps = 10\n[[cell]]\nname = \"default\"\n[[cell]]\nname = \"q_v=0\"\nloss = { q_v = 0.0 }\n"
                    .to_vec(),
            ],
            Target::Checkpoint => {
                let config = point_mass_config();
                let model = config.model.init(0, &crate::model::cpu_device())?;
                let path = seed_dir.join("model.safetensors");
                crate::train::checkpoint::save_checkpoint(
                    &path,
                    &model,
                    None,
                    &crate::train::checkpoint::CheckpointMeta::at(1),
                )?;
                vec![read(&path)?]
            }
            Target::RunConfigJson => vec![
                serde_json::to_vec_pretty(&point_mass_config())
                    .map_err(|e| Error::config("seed", e.to_string()))?,
            ],
            Target::StagesJson => vec![br#"[["collect point-mass", 1.5], ["train procl", 200.0]]"#.to_vec()],
            Target::AblationResults => vec![
                br#"{"cell":"cell","seed":0,"success_rate":1.0,"final_mean":0.001,"linear_r2":0.99,"det":1.2,"oracle_success_rate":1.0,"train_seconds":12.0}"#
                    .to_vec(),
            ],
        })
    }
}

/// The point-mass ProCL preset: the configuration the checkpoint target loads weights into.
fn point_mass_config() -> crate::train::TrainConfig {
    crate::train::TrainConfig::preset(
        crate::train::Preset::Procl,
        crate::train::Method::Procl,
        crate::envs::EnvKind::PointMass,
    )
}
