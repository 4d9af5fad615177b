#!/usr/bin/env bash
# The whole test suite: formatting, lints, every test (unit, property, golden, bad input, CLI,
# architecture), a build of the benchmarks and of the fuzz targets.
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup-system.sh   # FFmpeg libraries and clang, which the build needs
cargo fmt --all --check
cargo clippy --workspace --all-targets --locked -- -D warnings
cargo test --workspace --locked
cargo bench --workspace --locked --no-run
# The fuzz targets of the package readers build (cargo-fuzz, on stable with no sanitizer).
command -v cargo-fuzz >/dev/null || cargo install cargo-fuzz --locked --version 0.13.2
(cd fuzz && cargo fuzz build -s none)
