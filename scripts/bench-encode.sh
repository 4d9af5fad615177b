#!/usr/bin/env bash
# Encoding speed and memory, side by side in one run, as recorded in BENCHMARKS.md ("Coding
# and packages"): `cpsl encode` at constant quality and under a budget on the same 60-frame
# testsrc2 clip, interleaved, RUNS times each, with the peak resident memory. Set SIZES to
# add sizes (e.g. SIZES="1280x720:3M 1920x1080:6M 3840x2160:8M"; 4K takes minutes per run).
set -euo pipefail
cd "$(dirname "$0")/.."
cargo build --release -p cpsl
cpsl=./target/release/cpsl
mkdir -p out/bench
echo "| clip | mode | run | seconds | frames/s | kbit/s | peak memory MB |"
echo "|---|---|---|---|---|---|---|"
for case in ${SIZES:-1280x720:3M}; do
  size=${case%%:*} budget=${case##*:}
  clip="out/bench/testsrc2_${size}.mp4"
  [ -f "$clip" ] || ffmpeg -loglevel error -y -f lavfi -i "testsrc2=size=${size}:rate=30" \
    -frames:v 60 -c:v libx264 -pix_fmt yuv420p "$clip"
  for run in $(seq "${RUNS:-3}"); do
    for mode in "--quality 24" "--bitrate $budget"; do
      log=$(mktemp)
      /usr/bin/time -f "%M" -o "$log.mem" $cpsl encode "$clip" -o out/bench/encode.cpsl $mode >"$log" 2>&1
      # "wrote ... (60 frames, ..., h264 at N kbit/s ...) in S s (F frames/s; ...)"
      line=$(grep '^wrote' "$log")
      secs=$(sed -E 's/.* in ([0-9.]+) s .*/\1/' <<<"$line")
      fps=$(sed -E 's/.*\(([0-9.]+) frames\/s;.*/\1/' <<<"$line")
      kbps=$(sed -E 's/.* at ([0-9]+) kbit\/s.*/\1/' <<<"$line")
      mem=$(( $(tail -1 "$log.mem") / 1024 ))
      echo "| $size | ${mode} | $run | $secs | $fps | $kbps | $mem |"
      rm -f "$log" "$log.mem"
    done
  done
done
rm -rf out/bench/encode.cpsl
