//! The dataset on disk: one `.npz` readable by `numpy.load`, validated on load.
//!
//! Arrays: `obs` u8 `[episodes, T+1, 64, 64, 3]`, `actions` f32 `[episodes, T, du]`,
//! `states` f32 `[episodes, T+1, 2 dq]` (`q` then `qd`), `meta` u8 `[n]` holding the metadata as
//! UTF-8 JSON (`json.loads(bytes(np.load(f)["meta"]))`), and for convenience the scalars
//! `control_dt_s` f64 and `seed` u64.

use std::fs::File;
use std::io::{BufReader, Read, Seek};
use std::path::Path;

use ndarray::{Array0, Array1, Array3, Array5, ArrayBase, Dimension};
use ndarray_npy::{NpzReader, NpzWriter, ReadableElement};

use crate::envs::{EnvKind, FRAME_PX};
use crate::error::{Error, Result};
use crate::fsutil::write_atomically;

/// Version of the on-disk layout; bumped on any incompatible change.
pub const DATASET_FORMAT_VERSION: u32 = 1;

/// What a dataset is and where it came from.
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct DatasetMeta {
    /// [`DATASET_FORMAT_VERSION`] at writing time.
    pub format_version: u32,
    /// Environment the frames come from.
    pub env: EnvKind,
    /// Time between consecutive frames, seconds.
    pub control_dt_s: f64,
    /// Seed the data was generated from.
    pub seed: u64,
    /// How the actions were chosen: `random-control` or `demonstration:<path shape>`.
    pub source: String,
    /// procl version that wrote the file.
    pub procl_version: String,
}

/// A validated dataset in memory.
#[derive(Debug, Clone, PartialEq)]
pub struct Dataset {
    pub meta: DatasetMeta,
    /// `[episodes, T+1, 64, 64, 3]` RGB frames.
    pub obs: Array5<u8>,
    /// `[episodes, T, du]` actions in [-1, 1]; `actions[e, t]` moves frame `t` to frame `t+1`.
    pub actions: Array3<f32>,
    /// `[episodes, T+1, 2 dq]` true states `(q, qd)`.
    pub states: Array3<f32>,
}

impl Dataset {
    /// Wraps arrays after checking that their shapes agree with each other and with the env.
    pub fn new(
        meta: DatasetMeta,
        obs: Array5<u8>,
        actions: Array3<f32>,
        states: Array3<f32>,
    ) -> Result<Self> {
        Self::validate(Path::new("<memory>"), &meta, &obs, &actions, &states)?;
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
    /// Configuration dimension `dq` (states hold `q` and `qd`).
    pub fn config_dim(&self) -> usize {
        self.states.shape()[2] / 2
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
    /// The configuration `q` at step `t` of `episode`.
    pub fn config(&self, episode: usize, t: usize) -> Vec<f64> {
        (0..self.config_dim())
            .map(|i| self.states[[episode, t, i]] as f64)
            .collect()
    }

    /// Writes the dataset to `path` atomically; refuses to replace a file unless `force`.
    pub fn save(&self, path: &Path, force: bool) -> Result<()> {
        let meta_json =
            serde_json::to_vec(&self.meta).map_err(|e| Error::dataset(path, e.to_string()))?;
        write_atomically(path, force, |file| {
            let npz_err =
                |e: ndarray_npy::WriteNpzError| Error::dataset(path, format!("writing npz: {e}"));
            let mut npz = NpzWriter::new_compressed(file);
            npz.add_array("obs", &self.obs).map_err(npz_err)?;
            npz.add_array("actions", &self.actions).map_err(npz_err)?;
            npz.add_array("states", &self.states).map_err(npz_err)?;
            npz.add_array("meta", &Array1::from(meta_json))
                .map_err(npz_err)?;
            npz.add_array(
                "control_dt_s",
                &Array0::from_elem((), self.meta.control_dt_s),
            )
            .map_err(npz_err)?;
            npz.add_array("seed", &Array0::from_elem((), self.meta.seed))
                .map_err(npz_err)?;
            npz.finish().map_err(npz_err)?;
            Ok(())
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
        let meta_bytes: Array1<u8> = read_array(&mut npz, path, "meta")?;
        let meta: DatasetMeta = serde_json::from_slice(meta_bytes.as_slice().unwrap_or(&[]))
            .map_err(|e| {
                Error::dataset(
                    path,
                    format!("array `meta` is not valid metadata JSON: {e}"),
                )
            })?;
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
        let states: Array3<f32> = read_array(&mut npz, path, "states")?;
        // Arrays read from .npy in Fortran order would not be in standard layout.
        let obs = if obs.is_standard_layout() {
            obs
        } else {
            obs.as_standard_layout().to_owned()
        };
        Self::validate(path, &meta, &obs, &actions, &states)?;
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
        states: &Array3<f32>,
    ) -> Result<()> {
        let env = meta.env.make();
        let (du, dq) = (env.action_dim(), env.config_dim());
        let (o, a, s) = (obs.shape(), actions.shape(), states.shape());
        let fail = |message: String| Err(Error::dataset(path, message));
        if a[0] == 0 || a[1] < 2 {
            return fail(format!(
                "`actions` has shape {a:?}; need at least 1 episode of 2 steps"
            ));
        }
        if o != [a[0], a[1] + 1, FRAME_PX, FRAME_PX, 3] {
            return fail(format!(
                "`obs` has shape {o:?}, expected [{}, {}, {FRAME_PX}, {FRAME_PX}, 3] to match `actions` {a:?}",
                a[0],
                a[1] + 1
            ));
        }
        if a[2] != du {
            return fail(format!(
                "`actions` has {} components per step; {} takes {du}",
                a[2], meta.env
            ));
        }
        if s != [a[0], a[1] + 1, 2 * dq] {
            return fail(format!(
                "`states` has shape {s:?}, expected [{}, {}, {}]",
                a[0],
                a[1] + 1,
                2 * dq
            ));
        }
        if let Some(bad) = actions.iter().position(|x| !x.is_finite() || x.abs() > 1.0) {
            return fail(format!(
                "`actions` entry {bad} is {} (must be finite, in [-1, 1])",
                actions.iter().nth(bad).copied().unwrap_or(f32::NAN)
            ));
        }
        if states.iter().any(|x| !x.is_finite()) {
            return fail("`states` holds a non-finite value".into());
        }
        if !(meta.control_dt_s.is_finite() && meta.control_dt_s > 0.0) {
            return fail(format!(
                "metadata control_dt_s = {} must be positive",
                meta.control_dt_s
            ));
        }
        Ok(())
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
    let names = npz
        .names()
        .map_err(|e| Error::dataset(path, format!("corrupt archive: {e}")))?;
    let entry = [name.to_string(), format!("{name}.npy")]
        .into_iter()
        .find(|n| names.contains(n));
    let Some(entry) = entry else {
        return Err(Error::dataset(
            path,
            format!("missing array `{name}` (found: {})", names.join(", ")),
        ));
    };
    npz.by_name(&entry).map_err(|e| {
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
