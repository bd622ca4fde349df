//! The fuzz targets on stable Rust: every target's seed inputs parse, the inputs that once
//! failed stay fixed (`tests/fuzz_regressions/<target>/`), and a fixed budget of seeded
//! mutations (`PROCL_FUZZ_EXECS` per target, default 200) neither panics nor prints more than
//! one line. Coverage-guided runs: `fuzz/README.md`.

use std::path::Path;

use procl::fuzz::{Harness, Target};
use rand::{RngExt, SeedableRng};
use rand_chacha::ChaCha8Rng;

/// Bytes that sit on parsers' boundaries.
const INTERESTING: &[u8] = &[
    0, 1, 0x7f, 0x80, 0xff, b'\n', b'"', b'[', b'{', b'=', b'-', b'9',
];

/// One to four random edits of `input` (or a splice with another seed).
fn mutate(rng: &mut ChaCha8Rng, input: &[u8], seeds: &[Vec<u8>]) -> Vec<u8> {
    let mut out = input.to_vec();
    for _ in 0..rng.random_range(1..=4) {
        let len = out.len();
        let at = if len == 0 {
            0
        } else {
            rng.random_range(0..len)
        };
        match rng.random_range(0..8) {
            0 if len > 0 => out[at] ^= 1 << rng.random_range(0..8),
            1 if len > 0 => out[at] = INTERESTING[rng.random_range(0..INTERESTING.len())],
            2 if len > 0 => {
                let end = (at + rng.random_range(1..=64)).min(len);
                out.drain(at..end);
            }
            3 if len > 0 => {
                let end = (at + rng.random_range(1..=64)).min(len);
                let copy = out[at..end].to_vec();
                let to = rng.random_range(0..=out.len());
                out.splice(to..to, copy);
            }
            4 => {
                let bytes: Vec<u8> = (0..rng.random_range(1..=16))
                    .map(|_| rng.random())
                    .collect();
                out.splice(at..at, bytes);
            }
            5 => out.truncate(at),
            6 if len >= 8 => {
                // A boundary integer over 4 or 8 bytes: sizes, offsets, shape entries.
                let values = [u64::MAX, u32::MAX as u64, i64::MAX as u64, 1 << 40, 0];
                let value = values[rng.random_range(0..values.len())].to_le_bytes();
                let width = if rng.random() { 4 } else { 8 };
                let at = at.min(len - width);
                out[at..at + width].copy_from_slice(&value[..width]);
            }
            _ => {
                let other = &seeds[rng.random_range(0..seeds.len())];
                if !other.is_empty() {
                    let from = rng.random_range(0..other.len());
                    let take = rng.random_range(1..=(other.len() - from).min(256));
                    out.splice(at..at, other[from..from + take].iter().copied());
                }
            }
        }
    }
    out
}

fn executions() -> usize {
    std::env::var("PROCL_FUZZ_EXECS")
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(200)
}

#[test]
fn every_parser_survives_its_seeds_regressions_and_mutations() {
    let regressions = Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/fuzz_regressions");
    let scratch = tempfile::tempdir().unwrap();
    let mut findings = vec![];
    for target in Target::ALL {
        let harness = Harness::new(target, &scratch.path().join(target.name())).unwrap();
        let seeds = harness.seeds().unwrap();
        for seed in &seeds {
            harness
                .run(seed)
                .unwrap_or_else(|e| panic!("{}: a seed input fails: {e}", target.name()));
        }
        let mut inputs: Vec<Vec<u8>> = std::fs::read_dir(regressions.join(target.name()))
            .into_iter()
            .flatten()
            .flatten()
            .map(|entry| std::fs::read(entry.path()).unwrap())
            .collect();
        let mut rng = ChaCha8Rng::seed_from_u64(target as u64);
        for _ in 0..executions() {
            let base = &seeds[rng.random_range(0..seeds.len())];
            inputs.push(mutate(&mut rng, base, &seeds));
        }
        let mut rejected = 0;
        for input in &inputs {
            match std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| harness.run(input))) {
                Ok(Ok(())) => {}
                Ok(Err(_)) => rejected += 1,
                Err(_) => findings.push((target.name(), input.clone())),
            }
        }
        eprintln!(
            "{}: {} inputs, {rejected} refused with one line, {} accepted",
            target.name(),
            inputs.len(),
            inputs.len() - rejected
        );
    }
    if !findings.is_empty() {
        let dir = Path::new(env!("CARGO_TARGET_TMPDIR")).join("fuzz-findings");
        for (k, (name, input)) in findings.iter().enumerate() {
            std::fs::create_dir_all(dir.join(name)).unwrap();
            std::fs::write(dir.join(name).join(format!("finding-{k}")), input).unwrap();
        }
        panic!(
            "{} inputs panicked; saved under {}",
            findings.len(),
            dir.display()
        );
    }
}
