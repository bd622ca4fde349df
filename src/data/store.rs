//! The dataset on disk: one `.npz` readable by `numpy.load`, validated on load.
//!
//! Arrays: `obs` u8 `[episodes, T+1, 64, 64, 3]`, `actions` f32 `[episodes, T, du]` in
//! [-1, 1], the scalar `control_dt_s` f64, and optionally `states` f32 `[episodes, T+1, 2 dq]`
//! (`q` then `qd`), `meta` u8 `[n]` holding the metadata as UTF-8 JSON
//! (`json.loads(bytes(np.load(f)["meta"]))`) and the scalar `seed` u64. The first three are a
//! whole dataset: frames and actions recorded from any system train as `custom` data.

use std::fs::File;
use std::io::{BufReader, Read, Seek};
use std::path::Path;

use ndarray::{Array0, Array1, Array3, Array5, ArrayBase, Dimension};
use ndarray_npy::{NpzReader, NpzWriter, ReadableElement};

use crate::envs::{EnvConfig, EnvKind, FRAME_PX, source_name};
use crate::error::{Error, Result};
use crate::fsutil::write_atomically;

/// Version of the on-disk layout; bumped on any incompatible change.
pub const DATASET_FORMAT_VERSION: u32 = 1;

/// What a dataset is and where it came from.
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct DatasetMeta {
    /// [`DATASET_FORMAT_VERSION`] at writing time.
    pub format_version: u32,
    /// Environment the frames come from; `None` (written `custom`) for data from elsewhere.
    #[serde(with = "crate::envs::env_or_custom")]
    pub env: Option<EnvKind>,
    /// Time between consecutive frames, seconds.
    pub control_dt_s: f64,
    /// Seed the data was generated from.
    pub seed: u64,
    /// How the actions were chosen: `random-control`, `demonstration:<path shape>`, or
    /// [`IMPORTED_SOURCE`] for a file without metadata.
    pub source: String,
    /// procl version that wrote the file.
    pub procl_version: String,
    /// The simulator the frames were rendered by, when training cannot read it off `env`: a
    /// variant of an environment, or one of procl's simulators recorded as custom data (which
    /// trains with the recipe for data from elsewhere). Runs trained on the data are evaluated
    /// in it.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub env_config: Option<EnvConfig>,
}

/// The `source` of a dataset whose file carries no `meta` array.
pub const IMPORTED_SOURCE: &str = "imported";

impl DatasetMeta {
    /// Metadata of frames and actions from elsewhere, sampled every `control_dt_s` seconds.
    pub fn custom(control_dt_s: f64) -> Self {
        Self {
            format_version: DATASET_FORMAT_VERSION,
            env: None,
            control_dt_s,
            seed: 0,
            source: IMPORTED_SOURCE.into(),
            procl_version: String::new(),
            env_config: None,
        }
    }

    /// The environment's name, or `custom`.
    pub fn source_name(&self) -> &'static str {
        source_name(self.env)
    }

    /// The simulator that rendered the frames, if one of procl's did: the recorded
    /// configuration, else `env`'s default.
    pub fn simulator(&self) -> Option<EnvConfig> {
        self.env_config.clone().or(self.env.map(EnvConfig::from))
    }
}

/// A validated dataset in memory.
#[derive(Debug, Clone, PartialEq)]
pub struct Dataset {
    pub meta: DatasetMeta,
    /// `[episodes, T+1, 64, 64, 3]` RGB frames.
    pub obs: Array5<u8>,
    /// `[episodes, T, du]` actions in [-1, 1]; `actions[e, t]` moves frame `t` to frame `t+1`.
    pub actions: Array3<f32>,
    /// `[episodes, T+1, 2 dq]` true states `(q, qd)`, when the source knows them; every
    /// diagnostic that compares the latent with the state needs them.
    pub states: Option<Array3<f32>>,
}

impl Dataset {
    /// Wraps arrays after checking that their shapes agree with each other and with the env.
    pub fn new(
        meta: DatasetMeta,
        obs: Array5<u8>,
        actions: Array3<f32>,
        states: Option<Array3<f32>>,
    ) -> Result<Self> {
        Self::validate(
            Path::new("<memory>"),
            &meta,
            &obs,
            &actions,
            states.as_ref(),
        )?;
        Ok(Self {
            meta,
            obs,
            actions,
            states,
        })
    }

    /// Number of episodes.
    pub fn episodes(&self) -> usize {
        self.actions.shape()[0]
    }
    /// Steps per episode `T` (frames per episode is `T + 1`).
    pub fn steps(&self) -> usize {
        self.actions.shape()[1]
    }
    /// Action dimension `du`.
    pub fn action_dim(&self) -> usize {
        self.actions.shape()[2]
    }
    /// Configuration dimension `dq` (states hold `q` and `qd`), when the states are known.
    pub fn config_dim(&self) -> Option<usize> {
        self.states.as_ref().map(|s| s.shape()[2] / 2)
    }
    /// The configuration `q` at step `t` of `episode`, when the states are known.
    pub fn config(&self, episode: usize, t: usize) -> Option<Vec<f64>> {
        let states = self.states.as_ref()?;
        let dq = states.shape()[2] / 2;
        Some((0..dq).map(|i| states[[episode, t, i]] as f64).collect())
    }
    /// Total transitions.
    pub fn transitions(&self) -> usize {
        self.episodes() * self.steps()
    }
    /// The frame `t` of `episode`, 64*64*3 bytes, row-major RGB.
    pub fn frame(&self, episode: usize, t: usize) -> &[u8] {
        let start = (episode * (self.steps() + 1) + t) * crate::envs::FRAME_BYTES;
        // `obs` is always in standard layout (built by `zeros` or read from npy in C order).
        &self.obs.as_slice().unwrap_or(&[])[start..start + crate::envs::FRAME_BYTES]
    }

    /// Every frame of every episode, in order.
    pub fn every_frame(&self) -> impl Iterator<Item = &[u8]> {
        (0..self.episodes()).flat_map(move |e| (0..=self.steps()).map(move |t| self.frame(e, t)))
    }

    /// SHA-256 of what training reads: the source, the control period, and the frames and
    /// actions (not the file's bytes, which depend on compression), as lowercase hex.
    pub fn content_sha256(&self) -> String {
        use sha2::Digest;
        let mut hash = sha2::Sha256::new();
        hash.update(self.meta.source_name().as_bytes());
        hash.update(self.meta.control_dt_s.to_le_bytes());
        for dim in self.obs.shape().iter().chain(self.actions.shape()) {
            hash.update((*dim as u64).to_le_bytes());
        }
        match self.obs.as_slice() {
            Some(bytes) => hash.update(bytes),
            None => self.obs.iter().for_each(|b| hash.update([*b])),
        }
        for a in self.actions.iter() {
            hash.update(a.to_le_bytes());
        }
        hash.finalize().iter().map(|b| format!("{b:02x}")).collect()
    }

    /// Writes the dataset to `path` atomically; refuses to replace a file unless `force`.
    pub fn save(&self, path: &Path, force: bool) -> Result<()> {
        let meta_json =
            serde_json::to_vec(&self.meta).map_err(|e| Error::dataset(path, e.to_string()))?;
        write_atomically(path, force, |file| {
            let mut first_error = None;
            let mut npz = NpzWriter::new_compressed(QuietAfterError {
                inner: file,
                first_error: &mut first_error,
            });
            let written = (|| {
                npz.add_array("obs", &self.obs)?;
                npz.add_array("actions", &self.actions)?;
                if let Some(states) = &self.states {
                    npz.add_array("states", states)?;
                }
                npz.add_array("meta", &Array1::from(meta_json))?;
                npz.add_array(
                    "control_dt_s",
                    &Array0::from_elem((), self.meta.control_dt_s),
                )?;
                npz.add_array("seed", &Array0::from_elem((), self.meta.seed))?;
                npz.finish().map(drop)
            })();
            // The writer's own error on a failed write is a bare "i/o error"; the operating
            // system's (a full disk, a lost mount) is the one worth reading.
            written.map_err(|e| match first_error.take() {
                Some(io) => Error::io(path, io),
                None => Error::dataset(path, format!("writing npz: {e}")),
            })
        })
    }

    /// Reads and validates a dataset; every failure names the file and what is wrong.
    pub fn load(path: &Path) -> Result<Self> {
        let file = File::open(path).map_err(|e| match e.kind() {
            std::io::ErrorKind::NotFound => {
                Error::dataset(path, "file not found (create one with `procl collect`)")
            }
            _ => Error::io(path, e),
        })?;
        let mut npz = NpzReader::new(BufReader::new(file))
            .map_err(|e| Error::dataset(path, format!("not a readable .npz archive ({e})")))?;
        let meta = match read_optional_array::<_, u8, ndarray::Ix1>(&mut npz, path, "meta")? {
            Some(bytes) => {
                serde_json::from_slice(bytes.as_slice().unwrap_or(&[])).map_err(|e| {
                    Error::dataset(
                        path,
                        format!("array `meta` is not valid metadata JSON: {e}"),
                    )
                })?
            }
            None => {
                let dt: Array0<f64> = read_array(&mut npz, path, "control_dt_s")?;
                let mut meta = DatasetMeta::custom(dt.into_scalar());
                if let Some(seed) =
                    read_optional_array::<_, u64, ndarray::Ix0>(&mut npz, path, "seed")?
                {
                    meta.seed = seed.into_scalar();
                }
                meta
            }
        };
        if meta.format_version != DATASET_FORMAT_VERSION {
            return Err(Error::dataset(
                path,
                format!(
                    "format version {} (this procl reads {DATASET_FORMAT_VERSION})",
                    meta.format_version
                ),
            ));
        }
        let obs: Array5<u8> = read_array(&mut npz, path, "obs")?;
        let actions: Array3<f32> = read_array(&mut npz, path, "actions")?;
        let states: Option<Array3<f32>> = read_optional_array(&mut npz, path, "states")?;
        // Arrays read from .npy in Fortran order would not be in standard layout.
        let obs = if obs.is_standard_layout() {
            obs
        } else {
            obs.as_standard_layout().to_owned()
        };
        Self::validate(path, &meta, &obs, &actions, states.as_ref())?;
        Ok(Self {
            meta,
            obs,
            actions,
            states,
        })
    }

    fn validate(
        path: &Path,
        meta: &DatasetMeta,
        obs: &Array5<u8>,
        actions: &Array3<f32>,
        states: Option<&Array3<f32>>,
    ) -> Result<()> {
        let (o, a) = (obs.shape(), actions.shape());
        let fail = |message: String| Err(Error::dataset(path, message));
        if a[0] == 0 || a[1] < 2 || a[2] == 0 {
            return fail(format!(
                "`actions` has shape {a:?}; need at least 1 episode of 2 steps (a training sample spans 3 frames) and 1 action component"
            ));
        }
        if o != [a[0], a[1] + 1, FRAME_PX, FRAME_PX, 3] {
            return fail(format!(
                "`obs` has shape {o:?}, expected [{}, {}, {FRAME_PX}, {FRAME_PX}, 3] (64x64 RGB frames, one more per episode than `actions` {a:?}; resize other frames before saving)",
                a[0],
                a[1] + 1
            ));
        }
        if let (Some(env), Some(config)) = (meta.env, &meta.env_config)
            && config.kind() != env
        {
            return fail(format!(
                "metadata names the environment {env} but a {} configuration",
                config.kind()
            ));
        }
        if let Some(config) = &meta.env_config {
            config
                .validate()
                .map_err(|e| Error::dataset(path, format!("metadata `env_config`: {e}")))?;
        }
        let simulator = meta.simulator().map(|config| config.make());
        if let Some(sim) = &simulator {
            let du = sim.action_dim();
            if a[2] != du {
                return fail(format!(
                    "`actions` has {} components per step; {} takes {du}",
                    a[2],
                    sim.kind()
                ));
            }
        }
        if let Some(bad) = actions.iter().position(|x| !x.is_finite() || x.abs() > 1.0) {
            let index = unravel(bad, a);
            return fail(format!(
                "`actions`{index:?} is {} (actions must be finite and in [-1, 1]; scale them by the actuator limits)",
                actions.iter().nth(bad).copied().unwrap_or(f32::NAN)
            ));
        }
        if let Some(states) = states {
            let s = states.shape();
            let dq = simulator.as_ref().map(|sim| sim.config_dim());
            let expected_width = dq.map_or(s[2] >= 2 && s[2] % 2 == 0, |dq| s[2] == 2 * dq);
            if s[..2] != [a[0], a[1] + 1] || !expected_width {
                return fail(format!(
                    "`states` has shape {s:?}, expected [{}, {}, {}] (q then qd per frame)",
                    a[0],
                    a[1] + 1,
                    dq.map_or("2 dq".to_string(), |dq| (2 * dq).to_string())
                ));
            }
            if let Some(bad) = states.iter().position(|x| !x.is_finite()) {
                return fail(format!("`states`{:?} is not finite", unravel(bad, s)));
            }
        }
        if !(meta.control_dt_s.is_finite() && meta.control_dt_s > 0.0) {
            return fail(format!(
                "`control_dt_s` = {} must be a positive number of seconds",
                meta.control_dt_s
            ));
        }
        Ok(())
    }
}

/// The index of the `flat`-th element of a C-order array of `shape`.
fn unravel(mut flat: usize, shape: &[usize]) -> Vec<usize> {
    let mut index = vec![0; shape.len()];
    for (i, &n) in shape.iter().enumerate().rev() {
        index[i] = flat % n.max(1);
        flat /= n.max(1);
    }
    index
}

/// Reads one named array, or `None` when the archive has no entry of that name; a wrong dtype
/// or rank becomes a plain message.
fn read_optional_array<R, A, D>(
    npz: &mut NpzReader<R>,
    path: &Path,
    name: &str,
) -> Result<Option<ArrayBase<ndarray::OwnedRepr<A>, D>>>
where
    R: Read + Seek,
    A: ReadableElement,
    D: Dimension,
{
    let names = archive_names(npz, path)?;
    let entry = [name.to_string(), format!("{name}.npy")]
        .into_iter()
        .find(|n| names.contains(n));
    let Some(entry) = entry else {
        return Ok(None);
    };
    npz.by_name(&entry).map(Some).map_err(|e| {
        Error::dataset(
            path,
            format!(
                "array `{name}` could not be read as {} with {} dimensions: {e}",
                std::any::type_name::<A>(),
                D::NDIM.map_or("any".into(), |n| n.to_string())
            ),
        )
    })
}

fn archive_names<R: Read + Seek>(npz: &mut NpzReader<R>, path: &Path) -> Result<Vec<String>> {
    npz.names()
        .map_err(|e| Error::dataset(path, format!("corrupt archive: {e}")))
}

/// A writer that keeps its first error and then accepts and discards everything: the zip
/// writer under `NpzWriter` finishes the archive when dropped after a failed write, and prints
/// its own debug line to stderr when that fails too. The kept error reaches the caller, whose
/// temporary file is then removed, so nothing is lost by discarding the rest.
struct QuietAfterError<'a, W> {
    inner: W,
    first_error: &'a mut Option<std::io::Error>,
}

impl<W> QuietAfterError<'_, W> {
    /// `result`, with an error kept and replaced by one of the same kind for the zip writer.
    fn keep<T>(&mut self, result: std::io::Result<T>) -> std::io::Result<T> {
        result.map_err(|e| {
            let kind = e.kind();
            *self.first_error = Some(e);
            std::io::Error::from(kind)
        })
    }
}

impl<W: std::io::Write> std::io::Write for QuietAfterError<'_, W> {
    fn write(&mut self, buf: &[u8]) -> std::io::Result<usize> {
        if self.first_error.is_some() {
            return Ok(buf.len());
        }
        let result = self.inner.write(buf);
        self.keep(result)
    }
    fn flush(&mut self) -> std::io::Result<()> {
        if self.first_error.is_some() {
            return Ok(());
        }
        let result = self.inner.flush();
        self.keep(result)
    }
}

impl<W: Seek> Seek for QuietAfterError<'_, W> {
    fn seek(&mut self, pos: std::io::SeekFrom) -> std::io::Result<u64> {
        if self.first_error.is_some() {
            return Ok(0);
        }
        let result = self.inner.seek(pos);
        self.keep(result)
    }
}

/// Reads one named array, turning "missing", "wrong dtype" and "wrong rank" into plain messages.
fn read_array<R, A, D>(
    npz: &mut NpzReader<R>,
    path: &Path,
    name: &str,
) -> Result<ArrayBase<ndarray::OwnedRepr<A>, D>>
where
    R: Read + Seek,
    A: ReadableElement,
    D: Dimension,
{
    match read_optional_array(npz, path, name)? {
        Some(array) => Ok(array),
        None => Err(Error::dataset(
            path,
            format!(
                "missing array `{name}` (found: {})",
                archive_names(npz, path)?.join(", ")
            ),
        )),
    }
}
