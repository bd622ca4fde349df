//! A run folder: its files, its configuration and the trained model it holds.

use std::path::PathBuf;

use burn::tensor::Device;

use super::{Method, TrainConfig};
use crate::baselines::nvae::NvaeModel;
use crate::envs::EnvConfig;
use crate::error::{Error, Result};
use crate::model::ProclModel;
use crate::train::checkpoint::load_checkpoint;

/// Files of a run folder.
pub struct RunPaths {
    pub dir: PathBuf,
}

impl RunPaths {
    pub fn new(dir: impl Into<PathBuf>) -> Self {
        Self { dir: dir.into() }
    }
    pub fn config(&self) -> PathBuf {
        self.dir.join("config.json")
    }
    pub fn checkpoint(&self) -> PathBuf {
        self.dir.join("model.safetensors")
    }
    pub fn metrics(&self) -> PathBuf {
        self.dir.join("metrics.csv")
    }
    /// `validation.csv`: the validation ELBO of a NewtonianVAE run, one row per validation.
    pub fn validation(&self) -> PathBuf {
        self.dir.join("validation.csv")
    }
    /// `data.json`: which dataset the run trains on ([`DataRecord`]).
    pub fn data_record(&self) -> PathBuf {
        self.dir.join("data.json")
    }

    /// The run folder of the weights kept after `step` steps (`snapshot_every`).
    pub fn snapshot(&self, step: u64) -> RunPaths {
        RunPaths::new(self.dir.join("snapshots").join(format!("step-{step:06}")))
    }

    /// The steps of the run's finished snapshots, in increasing order (none without any).
    pub fn snapshot_steps(&self) -> Vec<u64> {
        let Ok(entries) = std::fs::read_dir(self.dir.join("snapshots")) else {
            return vec![];
        };
        let mut steps: Vec<u64> = entries
            .filter_map(|entry| {
                let name = entry.ok()?.file_name();
                let step = name.to_str()?.strip_prefix("step-")?.parse().ok()?;
                // The weights are written last: a folder without them is unfinished.
                self.snapshot(step).checkpoint().exists().then_some(step)
            })
            .collect();
        steps.sort_unstable();
        steps
    }

    /// Refuses to resume on another dataset than the one the run started on (runs without a
    /// `data.json` are not checked).
    pub fn check_same_data(&self, record: &DataRecord) -> Result<()> {
        let Some(saved) = self.saved_data_record("resume")? else {
            return Ok(());
        };
        if saved.sha256 != record.sha256 {
            return Err(Error::config(
                "resume",
                format!(
                    "the dataset is not the one {} started on ({}; given {}); resume with the original, or start a new run",
                    self.dir.display(),
                    saved.describe(),
                    record.describe()
                ),
            ));
        }
        Ok(())
    }

    /// The simulator a run controls in evaluation: the one its dataset recorded (a variant, or
    /// custom data from one of procl's simulators), else its environment's default; an error
    /// naming the run for custom data from elsewhere.
    pub fn simulator(&self, config: &TrainConfig) -> Result<EnvConfig> {
        match self.recorded_simulator(config)? {
            Some(sim) => Ok(sim),
            None => config.simulated_env(&self.dir).map(EnvConfig::from),
        }
    }

    /// [`RunPaths::simulator`], or `None` for a run on custom data from elsewhere.
    pub fn recorded_simulator(&self, config: &TrainConfig) -> Result<Option<EnvConfig>> {
        let recorded = self
            .saved_data_record("run")?
            .and_then(|record| record.env_config);
        match (recorded, config.env) {
            (Some(recorded), Some(env)) if recorded.kind() != env => Err(Error::config(
                "run",
                format!(
                    "{} records a {} simulator for a {env} run",
                    self.data_record().display(),
                    recorded.kind()
                ),
            )),
            (Some(recorded), _) => Ok(Some(recorded)),
            (None, env) => Ok(env.map(EnvConfig::from)),
        }
    }

    /// The run's `data.json`, if it has one; a file that does not parse is an error of `field`.
    fn saved_data_record(&self, field: &str) -> Result<Option<DataRecord>> {
        let path = self.data_record();
        let Ok(text) = std::fs::read_to_string(&path) else {
            return Ok(None);
        };
        serde_json::from_str(&text)
            .map(Some)
            .map_err(|e| Error::config(field, format!("{}: {e}", path.display())))
    }

    /// Reads the resolved config of a finished or running run.
    pub fn load_config(&self) -> Result<TrainConfig> {
        let path = self.config();
        let text = std::fs::read_to_string(&path).map_err(|e| match e.kind() {
            std::io::ErrorKind::NotFound => Error::config(
                "run",
                format!(
                    "{} not found: is {} a training run?",
                    path.display(),
                    self.dir.display()
                ),
            ),
            _ => Error::io(&path, e),
        })?;
        let mut value: serde_json::Value = serde_json::from_str(&text)
            .map_err(|e| Error::config("run", format!("{}: {e}", path.display())))?;
        drop_retired_options(&mut value)
            .map_err(|field| Error::config(field, format!("{} uses an option procl no longer has (docs/research/ names the commit that has it)", path.display())))?;
        serde_json::from_value(value)
            .map_err(|e| Error::config("run", format!("{}: {e}", path.display())))
    }

    /// Rebuilds the trained model, of whichever method, from `config.json` and the checkpoint.
    pub fn load_trained(&self, device: &Device) -> Result<(TrainConfig, TrainedModel)> {
        let config = self.load_config()?;
        let model = match (config.method, &config.nvae) {
            (Method::Nvae, Some(nvae)) => {
                let model = nvae.init(config.seed, device)?;
                TrainedModel::Nvae(load_checkpoint(&self.checkpoint(), model, device)?.0)
            }
            (Method::Nvae, None) => {
                return Err(Error::config(
                    "nvae",
                    format!(
                        "{} has method nvae but no nvae table",
                        self.config().display()
                    ),
                ));
            }
            _ => {
                let model = config.model.init(config.seed, device)?;
                TrainedModel::Procl(load_checkpoint(&self.checkpoint(), model, device)?.0)
            }
        };
        Ok((config, model))
    }

    /// Rebuilds a trained ProCL or PC3 model (the latent with learned dynamics `g`).
    pub fn load_model(&self, device: &Device) -> Result<(TrainConfig, ProclModel)> {
        match self.load_trained(device)? {
            (config, TrainedModel::Procl(model)) => Ok((config, model)),
            (_, TrainedModel::Nvae(_)) => Err(Error::config(
                "run",
                format!(
                    "{} is a NewtonianVAE run; this needs a ProCL or PC3 run",
                    self.dir.display()
                ),
            )),
        }
    }
}

/// Options a `config.json` may still hold from a procl that had them, each with the value that
/// meant "off" besides `null` (`None`: any value, a setting of a term that is off unless its
/// weight is set).
const RETIRED_OPTIONS: &[(&str, Option<&str>)] = &[
    ("risk_warmup_steps", Some("0")),
    ("batch_group_size", Some("1")),
    ("batch_group_window", None),
    ("loss.detach_targets", Some("false")),
    ("loss.normalise_risk", Some("false")),
    ("loss.variance_floor", Some("0.0")),
    ("loss.variance_weight", None),
    ("loss.variance_axes", Some("\"coordinates\"")),
    ("loss.decorrelation_weight", Some("0.0")),
    ("loss.action_response_weight", Some("0.0")),
    ("loss.action_response_turn_weight", Some("0.0")),
    ("loss.action_response_grouping", Some("\"principal-axis\"")),
    ("loss.action_response_sign_form", Some("\"diagonal\"")),
    ("loss.action_response_regions_across", Some("1")),
    ("loss.separation_weight", Some("0.0")),
    ("loss.separation_ratio", None),
    ("loss.decoder_weight", Some("0.0")),
    ("loss.decoder_noise", None),
    ("loss.decoder_standardise", Some("false")),
    ("loss.decoder_head_only", Some("false")),
    ("loss.stretch_weight", Some("0.0")),
    ("loss.stretch_ratio", None),
    ("loss.state_supervision_weight", Some("0.0")),
    ("model.feature_decoder_width", Some("0")),
    ("model.dynamics.input", Some("{\"kind\":\"mlp\"}")),
    ("model.dynamics.full_covariance", Some("false")),
    ("model.encoder.keypoint_upsample", Some("1")),
    ("model.encoder.polar_cut_deg", Some("null")),
    ("model.encoder.polar_cut_fade_deg", Some("0.0")),
    ("model.encoder.polar_angle_inner_fade", Some("0.0")),
    ("model.encoder.relative_angles", Some("false")),
    ("model.encoder.relative_reference_radius", Some("0.0")),
    ("model.encoder.head.with_cartesian", Some("false")),
    ("model.encoder.head.linear_base", Some("false")),
    ("learning_rate_schedule", Some("\"constant\"")),
];

/// Removes the retired options that are off from a run's configuration, so runs trained by a
/// procl that had them still load; `Err(field)` names one that is on.
fn drop_retired_options(config: &mut serde_json::Value) -> std::result::Result<(), String> {
    for (path, off) in RETIRED_OPTIONS {
        let (parents, key) = path.rsplit_once('.').map_or(("", *path), |(p, k)| (p, k));
        let parent = parents
            .split('.')
            .filter(|p| !p.is_empty())
            .try_fold(&mut *config, |v, p| v.get_mut(p));
        let Some(serde_json::Value::Object(map)) = parent else {
            continue;
        };
        let Some(value) = map.get(key) else {
            continue;
        };
        // An unset optional option (`null`) is off whatever its "off" value.
        let is_off = value.is_null()
            || off.is_none_or(|off| {
                serde_json::from_str::<serde_json::Value>(off).is_ok_and(|off| {
                    off == *value || (off.as_f64().is_some() && off.as_f64() == value.as_f64())
                })
            });
        if !is_off {
            return Err((*path).to_string());
        }
        map.remove(key);
    }
    Ok(())
}

/// The dataset a run trains on: its size, [`crate::data::Dataset::content_sha256`], and the
/// simulator configuration it records (a variant, or a simulator recorded as custom data).
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct DataRecord {
    pub sha256: String,
    pub episodes: usize,
    pub steps: usize,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub env_config: Option<EnvConfig>,
}

impl DataRecord {
    pub fn of(data: &crate::data::Dataset) -> Self {
        Self {
            sha256: data.content_sha256(),
            episodes: data.episodes(),
            steps: data.steps(),
            env_config: data.meta.env_config.clone(),
        }
    }

    fn describe(&self) -> String {
        let short = &self.sha256[..12.min(self.sha256.len())];
        format!(
            "{} episodes x {} steps, sha256 {short}",
            self.episodes, self.steps
        )
    }
}

/// A trained model as [`RunPaths::load_trained`] rebuilds it.
// Both variants are a few kB of tensor handles, built once per command: no reason to box.
#[allow(clippy::large_enum_variant)]
pub enum TrainedModel {
    /// ProCL or PC3: encoder and latent dynamics.
    Procl(ProclModel),
    /// The NewtonianVAE.
    Nvae(NvaeModel),
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn retired_options_that_are_off_are_dropped_and_one_that_is_on_is_named() {
        let mut config: serde_json::Value = serde_json::from_str(
            r#"{"risk_warmup_steps": 0, "loss": {"detach_targets": false, "separation_ratio": 0.1,
                "kp": 10.0}, "model": {"dynamics": {"input": {"kind": "mlp"}, "hidden": 64},
                "encoder": {"head": {"kind": "soft-argmax", "linear_base": false}}}}"#,
        )
        .unwrap();
        drop_retired_options(&mut config).unwrap();
        let want: serde_json::Value = serde_json::from_str(
            r#"{"loss": {"kp": 10.0}, "model": {"dynamics": {"hidden": 64},
                "encoder": {"head": {"kind": "soft-argmax"}}}}"#,
        )
        .unwrap();
        assert_eq!(config, want);
        let mut on: serde_json::Value =
            serde_json::from_str(r#"{"loss": {"stretch_weight": 2.0}}"#).unwrap();
        assert_eq!(
            drop_retired_options(&mut on),
            Err("loss.stretch_weight".to_string())
        );
    }
}
