//! Writes each target's seed inputs (valid files procl writes itself) into
//! `corpus/<target>/`, the starting corpus of `cargo fuzz run`.

use procl::fuzz::{Harness, Target};

fn main() -> procl::Result<()> {
    let root = std::path::Path::new(env!("CARGO_MANIFEST_DIR"));
    for target in Target::ALL {
        let scratch = std::env::temp_dir().join(format!("procl-fuzz-seeds-{}", target.name()));
        let seeds = Harness::new(target, &scratch)?.seeds()?;
        let corpus = root.join("corpus").join(target.name());
        std::fs::create_dir_all(&corpus).map_err(|e| procl::Error::io(&corpus, e))?;
        for (k, seed) in seeds.iter().enumerate() {
            let path = corpus.join(format!("seed-{k}"));
            std::fs::write(&path, seed).map_err(|e| procl::Error::io(&path, e))?;
        }
        println!("{}: {} seeds", target.name(), seeds.len());
    }
    Ok(())
}
