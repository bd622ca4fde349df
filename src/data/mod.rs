//! Datasets: seeded random-control collection and the NPZ store (demonstrations for tracking
//! are recorded by [`crate::control::generate_reference`] in the same layout).

mod collect;
mod hub;
mod store;

pub(crate) use collect::Recording;
pub use collect::{CollectConfig, STRIP_STRIDE, collect, render_strip};
pub use hub::{HUB_MAX_CORE_SHARE, HUB_MIN_RADIAL_R2, Hub, PixelSpread};
pub use store::{DATASET_FORMAT_VERSION, Dataset, DatasetMeta, IMPORTED_SOURCE};
