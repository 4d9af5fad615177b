#!/usr/bin/env bash
# End-to-end renderer benchmark, side by side with OpenCV, as recorded in BENCHMARKS.md.
# Installs opencv-python-headless + numpy into .venv-bench (PyPI) on first use.
set -euo pipefail
cd "$(dirname "$0")/.."
if [ ! -x .venv-bench/bin/python ]; then
  python3 -m venv .venv-bench
  .venv-bench/bin/pip install --quiet opencv-python-headless numpy
fi
cargo build --release -p cpsl
mkdir -p out/bench
for size in "1920 1080" "1280 720"; do
  set -- $size
  ./target/release/cpsl bench render --width "$1" --height "$2" --layers 6 --frames "${FRAMES:-60}" \
    --opencv .venv-bench/bin/python --save "out/bench/render_${1}x${2}.json"
done
