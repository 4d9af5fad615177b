#!/usr/bin/env bash
# The main job end to end on the built-in default input: installs what is missing (FFmpeg for
# the sweep video; ONNX Runtime and the FastDepth model into the model cache), builds, synthesises a scene, layers it by depth slicing, renders a
# viewpoint sweep and scores novel views against ray-cast ground truth. Output: out/demo/.
set -euo pipefail
cd "$(dirname "$0")/.."
if ! command -v ffmpeg >/dev/null 2>&1; then
  SUDO=""; [ "$(id -u)" -eq 0 ] || SUDO="sudo"
  $SUDO apt-get update -qq && $SUDO env DEBIAN_FRONTEND=noninteractive apt-get install -y -qq ffmpeg >/dev/null
fi
bash scripts/setup-models.sh >/dev/null   # ONNX Runtime + FastDepth, for `cpsl slice --depth-model`
cargo build --release -p cpsl
./target/release/cpsl demo -o "${1:-out/demo}"
