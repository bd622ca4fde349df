//! Datasets: seeded random-control collection and the NPZ store.
