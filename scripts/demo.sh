#!/usr/bin/env bash
# The main job end to end on the built-in default input: installs what is missing (FFmpeg and
# its libraries; ONNX Runtime and the FastDepth model into the model cache), builds, synthesises
# a scene, layers it, renders a viewpoint sweep and scores novel views against ray-cast ground
# truth, then encodes a moving clip of the scene into a package and plays it back along a sweep.
# Output: out/demo/.
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup-system.sh              # FFmpeg (tool and libraries), clang, OpenCV
bash scripts/setup-models.sh >/dev/null   # ONNX Runtime + FastDepth, for `cpsl demo --depth-model`
cargo build --release -p cpsl
./target/release/cpsl demo -o "${1:-out/demo}"
