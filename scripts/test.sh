#!/usr/bin/env bash
# The whole test suite: formatting, lints, the API documentation, every test (unit, property, golden, bad input, CLI,
# architecture, HTTP server), the browser player (its committed build is current; headless
# Chromium renders match the CPU reference), a build of the benchmarks and of the fuzz targets.
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup-system.sh   # FFmpeg libraries, clang and OpenCV, which the build needs
cargo fmt --all --check
cargo clippy --workspace --all-targets --locked -- -D warnings
# The API documentation builds without broken or private links.
RUSTDOCFLAGS="-D warnings" cargo doc --workspace --no-deps --locked
cargo test --workspace --locked
# The browser player: the embedded build in web/dist must be what its sources compile to, and
# the end-to-end test plays packages served by the `cpsl` binary the tests just built.
bash scripts/setup-web.sh
(cd web && rm -rf /tmp/cpsl-web-check && npx tsc -p . --outDir /tmp/cpsl-web-check \
  && diff -r /tmp/cpsl-web-check dist \
  || { echo "web/dist is stale: run (cd web && npm run build) and commit it" >&2; exit 1; })
(cd web && CPSL_BIN="${CARGO_TARGET_DIR:-$PWD/../target}/debug/cpsl" node test/e2e.mjs)
# The criterion benches build (with the test profile, whose dependencies the tests just built:
# building them under the bench profile, LTO and all, took 18 of CI's 54 minutes).
cargo test --workspace --benches --locked --no-run
# The fuzz targets of the package readers build (cargo-fuzz, on stable with no sanitizer).
command -v cargo-fuzz >/dev/null || cargo install cargo-fuzz --locked --version 0.13.2
(cd fuzz && cargo fuzz build -s none)
