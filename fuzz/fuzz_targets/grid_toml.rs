//! Fuzzes procl's grid_toml parser (`procl::fuzz::Target::GridToml`).
#![no_main]

use std::sync::OnceLock;

use libfuzzer_sys::fuzz_target;
use procl::fuzz::{Harness, Target};

fn harness() -> &'static Harness {
    static HARNESS: OnceLock<Harness> = OnceLock::new();
    HARNESS.get_or_init(|| {
        let dir = std::env::temp_dir().join(format!("procl-fuzz-grid_toml-{}", std::process::id()));
        Harness::new(Target::GridToml, &dir).expect("scratch folder")
    })
}

fuzz_target!(|bytes: &[u8]| {
    let _ = harness().run(bytes);
});
