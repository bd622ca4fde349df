//! Adam and checkpoints: model weights and Adam moments keyed by parameter path, in one
//! safetensors file written atomically (temp file + rename).
//!
//! procl keeps its own small Adam rather than burn's optimizer because burn keys optimizer state
//! by random parameter ids, which do not survive a save/load; keying by module path makes
//! `--resume` exact and the file readable by any safetensors tool.

use std::collections::BTreeMap;
use std::path::Path;

use burn::module::{Module, ModuleMapper, ModuleVisitor, Param};
use burn::tensor::{Device, Gradients, Tensor, TensorData};
use safetensors::tensor::{Dtype, TensorView};

use crate::error::{Error, Result};
use crate::fsutil::write_atomically;

/// Adam (Kingma & Ba) with bias correction, state keyed by parameter path.
#[derive(Debug, Clone)]
pub struct Adam {
    pub beta1: f64,
    pub beta2: f64,
    pub epsilon: f64,
    /// Updates applied so far.
    pub step: u64,
    /// First and second moments, flattened, by parameter path.
    moments: BTreeMap<String, (Tensor<1>, Tensor<1>)>,
    /// The global gradient norm of every clipped step so far, ascending: the history the
    /// clipping threshold is a percentile of.
    gradient_norms: Vec<f64>,
}

impl Default for Adam {
    fn default() -> Self {
        Self {
            beta1: 0.9,
            beta2: 0.999,
            epsilon: 1e-8,
            step: 0,
            moments: BTreeMap::new(),
            gradient_norms: Vec::new(),
        }
    }
}

impl Adam {
    /// Applies one update with learning rate `lr` to every parameter that has a gradient. With
    /// `clip_percentile`, the gradient is first scaled down to that percentile of the global
    /// norms of the run's gradients so far, this one's included (AutoClip, Seetharaman et al.
    /// 2020): a step whose gradient spikes moves the weights no further than a typical one.
    pub fn step<M: Module>(
        &mut self,
        lr: f64,
        clip_percentile: Option<f64>,
        module: M,
        grads: &Gradients,
    ) -> M {
        self.step += 1;
        let scale = match clip_percentile {
            Some(percentile) => {
                let mut norm = GradientNorm { grads, sum: None };
                module.visit(&mut norm);
                let norm = norm
                    .sum
                    .map_or(0.0, |sum| f64::from(crate::model::to_vec(sum)[0]).sqrt());
                clip_scale(&mut self.gradient_norms, norm, percentile)
            }
            None => 1.0,
        };
        let mut mapper = AdamMapper {
            adam: self,
            grads,
            lr,
            scale,
            path: vec![],
        };
        module.map(&mut mapper)
    }
}

/// Records `norm` in the ascending history `norms` and returns the factor that brings it down
/// to the history's `percentile` (nearest rank), or 1 where it is not above it. A non-finite
/// norm is not recorded and not scaled: the step's loss then stops the run.
fn clip_scale(norms: &mut Vec<f64>, norm: f64, percentile: f64) -> f64 {
    if !norm.is_finite() {
        return 1.0;
    }
    let at = norms.partition_point(|&x| x < norm);
    norms.insert(at, norm);
    let rank = (percentile / 100.0 * (norms.len() - 1) as f64).round() as usize;
    let threshold = norms[rank.min(norms.len() - 1)];
    if norm > threshold {
        threshold / norm
    } else {
        1.0
    }
}

/// Sums the squares of every parameter's gradient (one device scalar).
struct GradientNorm<'a> {
    grads: &'a Gradients,
    sum: Option<Tensor<1>>,
}

impl ModuleVisitor for GradientNorm<'_> {
    fn visit_float<const D: usize>(&mut self, param: &Param<Tensor<D>>) {
        if let Some(grad) = param.val().grad(self.grads) {
            let squares = grad.powi_scalar(2).sum();
            self.sum = Some(match self.sum.take() {
                Some(sum) => sum + squares,
                None => squares,
            });
        }
    }
}

struct AdamMapper<'a> {
    adam: &'a mut Adam,
    grads: &'a Gradients,
    lr: f64,
    /// The clipping factor of this step's gradient.
    scale: f64,
    path: Vec<String>,
}

impl ModuleMapper for AdamMapper<'_> {
    fn enter_module(&mut self, name: &str, _: &str) {
        self.path.push(name.to_string());
    }
    fn exit_module(&mut self, _: &str, _: &str) {
        self.path.pop();
    }
    fn map_float<const D: usize>(&mut self, param: Param<Tensor<D>>) -> Param<Tensor<D>> {
        let value = param.val();
        let Some(grad) = value.grad(self.grads) else {
            return param;
        };
        let dims = value.dims();
        let count: usize = dims.iter().product();
        let grad = grad.reshape([count]);
        // An unclipped step (and every step of an unclipped run) skips the multiply.
        let grad = if self.scale == 1.0 {
            grad
        } else {
            grad * self.scale
        };
        let (b1, b2) = (self.adam.beta1, self.adam.beta2);
        let key = self.path.join(".");
        let (m, v) = match self.adam.moments.remove(&key) {
            Some((m, v)) => (
                m * b1 + grad.clone() * (1.0 - b1),
                v * b2 + grad.powi_scalar(2) * (1.0 - b2),
            ),
            None => (grad.clone() * (1.0 - b1), grad.powi_scalar(2) * (1.0 - b2)),
        };
        let t = self.adam.step as i32;
        let m_hat = m.clone() / (1.0 - b1.powi(t));
        let v_hat = v.clone() / (1.0 - b2.powi(t));
        let update = m_hat / (v_hat.sqrt() + self.adam.epsilon) * self.lr;
        self.adam.moments.insert(key, (m, v));
        let (lr_update, dims_out) = (update.reshape(dims), dims);
        param.map(|tensor| {
            let updated = tensor.inner() - lr_update;
            Tensor::from_inner(updated.reshape(dims_out)).require_grad()
        })
    }
}

/// Collects every float parameter as (path, dims, values).
struct Collect {
    path: Vec<String>,
    tensors: Vec<(String, Vec<usize>, Vec<f32>)>,
}

impl ModuleVisitor for Collect {
    fn enter_module(&mut self, name: &str, _: &str) {
        self.path.push(name.to_string());
    }
    fn exit_module(&mut self, _: &str, _: &str) {
        self.path.pop();
    }
    fn visit_float<const D: usize>(&mut self, param: &Param<Tensor<D>>) {
        let value = param.val();
        self.tensors.push((
            self.path.join("."),
            value.dims().to_vec(),
            crate::model::to_vec(value),
        ));
    }
}

/// Replaces every float parameter by the stored tensor of the same path and shape.
struct Restore<'a> {
    path: Vec<String>,
    stored: &'a BTreeMap<String, (Vec<usize>, Vec<f32>)>,
    file: &'a Path,
    error: Option<Error>,
}

impl ModuleMapper for Restore<'_> {
    fn enter_module(&mut self, name: &str, _: &str) {
        self.path.push(name.to_string());
    }
    fn exit_module(&mut self, _: &str, _: &str) {
        self.path.pop();
    }
    fn map_float<const D: usize>(&mut self, param: Param<Tensor<D>>) -> Param<Tensor<D>> {
        let key = format!("model.{}", self.path.join("."));
        let dims = param.val().dims();
        match self.stored.get(&key) {
            Some((shape, values)) if shape.as_slice() == dims.as_slice() => {
                let values = values.clone();
                // Keep each parameter's own trainability: the orientation is never trained.
                param.map(|tensor| {
                    let device = tensor.device();
                    let require_grad = tensor.is_require_grad();
                    Tensor::from_data(TensorData::new(values, dims), &device)
                        .set_require_grad(require_grad)
                })
            }
            // A checkpoint without the polar centre was trained about the image centre, the
            // parameter's initial value.
            None if self.path.last().map(String::as_str) == Some(crate::model::POLAR_CENTRE) => {
                param
            }
            found => {
                let what = match found {
                    Some((shape, _)) => {
                        format!("`{key}` has shape {shape:?}, the model expects {dims:?}")
                    }
                    None => format!("missing tensor `{key}`"),
                };
                // The run's config.json builds the model, so the two disagree only for weights
                // written by a procl whose layers differ.
                let what =
                    format!("{what} (weights from a procl with other layers: retrain the run)");
                self.error
                    .get_or_insert(Error::checkpoint(self.file.to_path_buf(), what));
                param
            }
        }
    }
}

/// The checkpoint's metadata as stored: [`CheckpointMeta`] and the Adam step count.
#[derive(serde::Serialize, serde::Deserialize)]
struct StoredMeta {
    #[serde(flatten)]
    meta: CheckpointMeta,
    adam_step: u64,
    /// The clipping history ([`Adam`]), so that `--resume` clips as the uninterrupted run.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    gradient_norms: Vec<f64>,
}

/// What a checkpoint holds besides tensors.
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct CheckpointMeta {
    /// Training steps completed.
    pub step: u64,
    /// The objective's stopping rule ended the run here, before its configured steps: the run
    /// is finished, and `--resume` has nothing to continue.
    #[serde(default, skip_serializing_if = "std::ops::Not::not")]
    pub stopped_early: bool,
}

impl CheckpointMeta {
    /// A checkpoint after `step` steps of a run that goes on (or ends at its configured steps).
    pub fn at(step: u64) -> Self {
        Self {
            step,
            stopped_early: false,
        }
    }
}

/// Writes model weights (and Adam state, if given) to `path` atomically, replacing it.
pub fn save_checkpoint<M: Module>(
    path: &Path,
    model: &M,
    adam: Option<&Adam>,
    meta: &CheckpointMeta,
) -> Result<()> {
    let mut collect = Collect {
        path: vec![],
        tensors: vec![],
    };
    model.visit(&mut collect);
    let mut entries: Vec<(String, Vec<usize>, Vec<f32>)> = collect
        .tensors
        .into_iter()
        .map(|(p, d, v)| (format!("model.{p}"), d, v))
        .collect();
    if let Some(adam) = adam {
        for (key, (m, v)) in &adam.moments {
            let n = m.dims()[0];
            entries.push((
                format!("adam.m.{key}"),
                vec![n],
                crate::model::to_vec(m.clone()),
            ));
            entries.push((
                format!("adam.v.{key}"),
                vec![n],
                crate::model::to_vec(v.clone()),
            ));
        }
    }
    let bytes: Vec<(String, Vec<usize>, Vec<u8>)> = entries
        .into_iter()
        .map(|(name, dims, values)| {
            (
                name,
                dims,
                values.iter().flat_map(|x| x.to_le_bytes()).collect(),
            )
        })
        .collect();
    // One metadata key: safetensors writes a HashMap's keys in its randomised iteration order,
    // and the same run must give the same bytes.
    let stored_meta = StoredMeta {
        meta: meta.clone(),
        adam_step: adam.map_or(0, |a| a.step),
        gradient_norms: adam.map_or_else(Vec::new, |a| a.gradient_norms.clone()),
    };
    let json =
        serde_json::to_string(&stored_meta).map_err(|e| Error::checkpoint(path, e.to_string()))?;
    let metadata = std::collections::HashMap::from([("procl".to_string(), json)]);
    let views: Vec<(String, TensorView<'_>)> = bytes
        .iter()
        .map(|(name, dims, data)| {
            TensorView::new(Dtype::F32, dims.clone(), data)
                .map(|view| (name.clone(), view))
                .map_err(|e| Error::checkpoint(path, e.to_string()))
        })
        .collect::<Result<_>>()?;
    let serialized = safetensors::serialize(views, Some(metadata))
        .map_err(|e| Error::checkpoint(path, e.to_string()))?;
    write_atomically(path, true, |w| {
        std::io::Write::write_all(w, &serialized).map_err(|e| Error::io(path, e))
    })
}

/// The procl metadata in a checkpoint file's header.
fn stored_meta(path: &Path, bytes: &[u8]) -> Result<StoredMeta> {
    let corrupt = |message: String| Error::checkpoint(path, message);
    let (_, header) = safetensors::SafeTensors::read_metadata(bytes)
        .map_err(|e| corrupt(format!("not a readable safetensors file ({e})")))?;
    header
        .metadata()
        .as_ref()
        .and_then(|m| m.get("procl"))
        .and_then(|s| serde_json::from_str(s).ok())
        .ok_or_else(|| corrupt("missing procl metadata".into()))
}

/// The metadata of the checkpoint at `path` (how many steps it holds) without loading weights.
pub fn read_checkpoint_meta(path: &Path) -> Result<CheckpointMeta> {
    let bytes = std::fs::read(path).map_err(|e| Error::io(path, e))?;
    Ok(stored_meta(path, &bytes)?.meta)
}

/// Loads weights into `model` (same architecture) and returns the Adam state and metadata.
pub fn load_checkpoint<M: Module>(
    path: &Path,
    model: M,
    device: &Device,
) -> Result<(M, Adam, CheckpointMeta)> {
    let corrupt = |message: String| Error::checkpoint(path, message);
    let bytes = std::fs::read(path).map_err(|e| match e.kind() {
        std::io::ErrorKind::NotFound => {
            corrupt("not found (train a model with `procl train` first)".into())
        }
        _ => Error::io(path, e),
    })?;
    let stored_meta = stored_meta(path, &bytes)?;
    let tensors = safetensors::SafeTensors::deserialize(&bytes)
        .map_err(|e| corrupt(format!("not a readable safetensors file ({e})")))?;
    let meta = stored_meta.meta.clone();
    let mut stored = BTreeMap::new();
    for (name, view) in tensors.tensors() {
        if view.dtype() != Dtype::F32 {
            return Err(corrupt(format!(
                "tensor `{name}` is {:?}, expected F32",
                view.dtype()
            )));
        }
        let values: Vec<f32> = view
            .data()
            .chunks_exact(4)
            .map(|b| f32::from_le_bytes([b[0], b[1], b[2], b[3]]))
            .collect();
        if values.iter().any(|x| !x.is_finite()) {
            return Err(corrupt(format!("tensor `{name}` holds non-finite values")));
        }
        stored.insert(name, (view.shape().to_vec(), values));
    }
    let mut restore = Restore {
        path: vec![],
        stored: &stored,
        file: path,
        error: None,
    };
    let model = model.map(&mut restore);
    if let Some(error) = restore.error {
        return Err(error);
    }
    let mut adam = Adam {
        step: stored_meta.adam_step,
        gradient_norms: stored_meta.gradient_norms,
        ..Adam::default()
    };
    for (name, (shape, values)) in &stored {
        if let Some(key) = name.strip_prefix("adam.m.") {
            let v_name = format!("adam.v.{key}");
            let (_, v_values) = stored
                .get(&v_name)
                .ok_or_else(|| corrupt(format!("missing `{v_name}`")))?;
            let make = |vals: &Vec<f32>| {
                Tensor::from_data(TensorData::new(vals.clone(), shape.clone()), device)
            };
            adam.moments
                .insert(key.to_string(), (make(values), make(v_values)));
        }
    }
    Ok((model, adam, meta))
}

#[cfg(test)]
mod tests {
    use super::clip_scale;

    #[test]
    fn clipping_brings_a_spike_down_to_the_percentile_of_the_history() {
        let mut norms = vec![];
        // The first norm is its own history: nothing to clip.
        assert_eq!(clip_scale(&mut norms, 4.0, 10.0), 1.0);
        for norm in [2.0, 1.0, 3.0] {
            clip_scale(&mut norms, norm, 50.0);
        }
        assert_eq!(norms, [1.0, 2.0, 3.0, 4.0]);
        // History 1, 2, 3, 4, 100: the median (rank round(0.5 * 4) = 2) is 3.
        assert_eq!(clip_scale(&mut norms, 100.0, 50.0), 0.03);
        // 10th percentile of 1, 2, 3, 4, 5, 100: rank round(0.1 * 5) = 1, so 2.
        assert_eq!(clip_scale(&mut norms, 5.0, 10.0), 0.4);
        // Below the threshold: unscaled.
        assert_eq!(clip_scale(&mut norms, 1.5, 100.0), 1.0);
        // A non-finite norm is neither scaled nor kept.
        assert_eq!(clip_scale(&mut norms, f64::NAN, 10.0), 1.0);
        assert_eq!(norms, [1.0, 1.5, 2.0, 3.0, 4.0, 5.0, 100.0]);
    }
}
