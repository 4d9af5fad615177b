#!/usr/bin/env bash
# The whole test suite: formatting, lints, every test (unit, property, golden, bad input, CLI,
# architecture), and a build of the benchmarks.
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup-system.sh   # FFmpeg libraries and clang, which the build needs
cargo fmt --all --check
cargo clippy --workspace --all-targets --locked -- -D warnings
cargo test --workspace --locked
cargo bench --workspace --locked --no-run
