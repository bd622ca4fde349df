//! Datasets: seeded random-control collection, demonstration paths for tracking, the NPZ store.

mod collect;
mod reference;
mod store;

pub use collect::{CollectConfig, STRIP_STRIDE, collect, render_strip};
pub use reference::{PathShape, ReferenceConfig, generate_reference};
pub use store::{DATASET_FORMAT_VERSION, Dataset, DatasetMeta};
