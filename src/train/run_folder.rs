//! A run folder: its files, its configuration and the trained model it holds.

use std::path::PathBuf;

use burn::tensor::Device;

use super::{Method, TrainConfig};
use crate::baselines::nvae::NvaeModel;
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
        serde_json::from_str(&text)
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

/// A trained model as [`RunPaths::load_trained`] rebuilds it.
// Both variants are a few kB of tensor handles, built once per command: no reason to box.
#[allow(clippy::large_enum_variant)]
pub enum TrainedModel {
    /// ProCL or PC3: encoder and latent dynamics.
    Procl(ProclModel),
    /// The NewtonianVAE.
    Nvae(NvaeModel),
}
