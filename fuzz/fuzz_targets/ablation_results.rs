//! Fuzzes procl's ablation_results parser (`procl::fuzz::Target::AblationResults`).
#![no_main]

use std::sync::OnceLock;

use libfuzzer_sys::fuzz_target;
use procl::fuzz::{Harness, Target};

fn harness() -> &'static Harness {
    static HARNESS: OnceLock<Harness> = OnceLock::new();
    HARNESS.get_or_init(|| {
        let dir = std::env::temp_dir().join(format!("procl-fuzz-ablation_results-{}", std::process::id()));
        Harness::new(Target::AblationResults, &dir).expect("scratch folder")
    })
}

fuzz_target!(|bytes: &[u8]| {
    let _ = harness().run(bytes);
});
