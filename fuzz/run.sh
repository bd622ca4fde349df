#!/usr/bin/env bash
# Fuzzes every target for $1 seconds (default 60) from the seed corpus and the regressions;
# crashes land in fuzz/artifacts/<target>/.
set -euo pipefail
cd "$(dirname "$0")"
seconds=${1:-60}
cargo run --quiet --release --bin seeds
for target in npz config_toml grid_toml checkpoint run_config_json stages_json ablation_results; do
    mkdir -p "../tests/fuzz_regressions/$target"
    cargo +nightly fuzz run --sanitizer none "$target" "corpus/$target" "../tests/fuzz_regressions/$target" \
        -- -max_total_time="$seconds" -rss_limit_mb=4096 2>&1 | grep -E "^#[0-9]+ *DONE|Done [0-9]+ runs|ERROR|SUMMARY" || true
done
