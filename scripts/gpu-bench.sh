#!/usr/bin/env bash
# GPU figures on a machine with a Vulkan driver and nothing else (BENCHMARKS.md "GPU renderer").
#
#   bash scripts/gpu-bench.sh prepare   # here: builds and gathers everything into .gpubench/
#   bash scripts/gpu-bench.sh run       # there: writes reports into $OUT (default out/gpu)
#
# `prepare` builds cpsl-gpu-bench (the render benchmark: links neither FFmpeg nor ONNX
# Runtime) and cpsl-gpu-play (package playback; decodes with FFmpeg, whose Debian libraries it
# packs next to it, about 48 MB compressed), fetches the Vulkan loader packages, and copies the
# 1080p30 playback package of scripts/bench.sh (and the fox's, when made). Copy or carry
# .gpubench/ to the GPU machine; `run` needs only it and the GPU's driver. Each step of `run`
# has a time limit (RENDER_TIMEOUT, PASSES_TIMEOUT, PLAY_TIMEOUT; about 7 minutes in all) and
# the render benchmark writes its JSON after every case, so a step cut short keeps its figures.
set -euo pipefail
cd "$(dirname "$0")/.."
dir=.gpubench

prepare() {
  cargo build --release -p cpsl-gpu-bench
  rm -rf "$dir" && mkdir -p "$dir/gl"
  # Both binaries, stripped, and the playback binary's libraries except the C and C++
  # runtimes (the machine's are used), compressed: the whole folder must travel in 64 MiB.
  stage=$(mktemp -d)
  mkdir -p "$stage/bin" "$stage/lib"
  for b in cpsl-gpu-bench cpsl-gpu-play; do
    cp "target/release/$b" "$stage/bin/" && strip "$stage/bin/$b"
  done
  tar -C "$stage" -cf - bin | xz -9e -T0 > "$dir/bin.tar.xz"
  ldd "$stage/bin/cpsl-gpu-play" | awk '$3 ~ /^\// {print $3}' |
    grep -v -E '/(libc|libm|libpthread|libdl|librt|libgcc_s|libstdc\+\+)\.so' |
    while read -r lib; do cp -L "$lib" "$stage/lib/"; done
  tar -C "$stage" -cf - lib | xz -9e -T0 > "$dir/ffmpeg-libs.tar.xz"
  rm -rf "$stage"
  # The Vulkan loader (and GL dispatch) as Debian packages, unpacked there.
  (cd "$dir/gl" && apt-get download libvulkan1 libegl1 libglvnd0 libopengl0 libgl1 libglx0 libgles2)
  pkg=out/bench/play_1920x1080.cpsl
  if [ ! -e "$pkg" ]; then
    cargo build --release -p cpsl
    clip=out/bench/testsrc2_1920x1080.mp4
    mkdir -p out/bench
    [ -f "$clip" ] || ffmpeg -loglevel error -y -f lavfi -i "testsrc2=size=1920x1080:rate=30" \
      -frames:v 60 -c:v libx264 -pix_fmt yuv420p "$clip"
    target/release/cpsl encode "$clip" -o "$pkg" --bitrate 6M
  fi
  cp -r "$pkg" "$dir/"
  [ ! -e out/bench/play_fox.cpsl ] || cp -r out/bench/play_fox.cpsl "$dir/"
  du -sh "$dir"
}

run() {
  out=${OUT:-out/gpu}
  mkdir -p "$out"
  for f in "$dir"/gl/*.deb; do dpkg -x "$f" /; done
  ldconfig
  icd=/usr/local/nvidia/share/vulkan/icd.d/nvidia_icd.json
  [ ! -f "$icd" ] || export VK_DRIVER_FILES=$icd
  export WGPU_BACKEND=${WGPU_BACKEND:-vulkan}
  nvidia-smi --query-gpu=name,driver_version,memory.total,clocks.max.sm --format=csv \
    > "$out/nvidia-smi.csv" 2>&1 || true
  tmp=$(mktemp -d)
  xz -dc "$dir/bin.tar.xz" | tar -x -C "$tmp"
  xz -dc "$dir/ffmpeg-libs.tar.xz" | tar -x -C "$tmp"
  failed=0
  # The render benchmark: every case with compute passes, then compute against fragment
  # passes on 1080p, K = 8. Each run writes its JSON after every case.
  render() { # name timeout args...
    local name=$1 limit=$2
    shift 2
    timeout "$limit" "$tmp/bin/cpsl-gpu-bench" --json "$out/$name.json" "$@" || failed=1
  }
  # shellcheck disable=SC2086 # the *_ARGS hold several arguments
  render gpu-render "${RENDER_TIMEOUT:-270}" --passes compute ${RENDER_ARGS:-}
  # shellcheck disable=SC2086
  render gpu-render-passes "${PASSES_TIMEOUT:-60}" --sizes 1920x1080 --layers 8 \
    --passes compute,fragment ${PASSES_ARGS:-}
  for pkg in "$dir"/play_*.cpsl; do
    name=$(basename "$pkg" .cpsl)
    LD_LIBRARY_PATH="$tmp/lib" timeout "${PLAY_TIMEOUT:-45}" "$tmp/bin/cpsl-gpu-play" "$pkg" \
      --frames "${PLAY_FRAMES:-150}" --cpu --json "$out/gpu-$name.json" || failed=1
  done
  return $failed
}

case "${1:-}" in
  prepare) prepare ;;
  run) run ;;
  *) echo "usage: $0 prepare|run" >&2; exit 2 ;;
esac
