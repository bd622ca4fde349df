#!/usr/bin/env bash
# procl's tests: the Rust workspace's suite, then the Python package built from this tree
# (in a virtual environment under target/) and its pytest suite.
set -euo pipefail
cd "$(dirname "$0")/.."
cargo test --release
venv=target/python-test-venv
python3 -m venv "$venv"
"$venv/bin/pip" install --quiet --upgrade pip
"$venv/bin/pip" install --quiet maturin pytest
"$venv/bin/pip" install --quiet ./python
"$venv/bin/python" -m pytest -q python/tests
