#!/usr/bin/env bash
# Pictures of the layer geometries on real footage (EVALUATION.md, "A sweep of the fox"): the
# fox's frames as a 720x1280 clip, its first frames layered frame by frame (`--gop 1`: each
# from its own depth) with depth from the video under each `--geometry`, and frame $FRAME (17
# by default: the fox's head, the picture frame and the wallpaper in view) rendered along a
# sideways sweep. Writes out/geometry-sweep/{plane,slanted,mesh}_sweep/ (frames, sheet.png,
# sweep.mp4) and, with ImageMagick, compare.jpg (the sweep's two ends, a row per geometry).
# The pictures are the dataset's: they stay in out/, never in the repository.
set -euo pipefail
cd "$(dirname "$0")/.."
data=${DATA:-../shared/data}/instant_ngp_fox_video_frames
frame=${FRAME:-17}
out=out/geometry-sweep
mkdir -p "$out"
cargo build --release -p cpsl
cpsl=./target/release/cpsl
clip="$out/fox720.mp4"
[ -f "$clip" ] || ffmpeg -loglevel error -y -framerate 30 -pattern_type glob -i "$data/images/*.jpg" \
  -vf scale=720:1280 -c:v libx264 -crf 16 "$clip"
for g in plane slanted mesh; do
  $cpsl layer-video "$clip" --fov 42.87 --geometry "$g" --gop 1 --max-frames $((frame + 1)) \
    -o "$out/$g"
  rm -rf "$out/${g}_sweep"
  $cpsl render "$out/$g/$(printf 'frame_%06d' "$frame")" --sweep tx:-0.1:0.1:5 -o "$out/${g}_sweep"
done
if command -v convert >/dev/null; then
  for g in plane slanted mesh; do
    convert "$out/${g}_sweep/frame_000.png" "$out/${g}_sweep/frame_004.png" +append -resize 50% \
      "$out/$g.row.png"
  done
  convert "$out/plane.row.png" "$out/slanted.row.png" "$out/mesh.row.png" -append "$out/compare.jpg"
  rm -f "$out"/*.row.png
  echo "wrote $out/compare.jpg (rows: plane, slanted, mesh; columns: tx = -0.1, +0.1)"
fi
