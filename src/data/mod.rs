//! Datasets: seeded random-control collection, the NPZ store, and training-sample batching.

mod collect;
mod store;

pub use collect::{CollectConfig, collect};
pub use store::{DATASET_FORMAT_VERSION, Dataset, DatasetMeta};
