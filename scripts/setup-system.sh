#!/usr/bin/env bash
# Installs the Debian packages cpsl builds and runs against, if any is missing: FFmpeg (the
# `ffmpeg` tool for sweep videos and test clips, and the libav* development files and clang that
# the ffmpeg-next crate builds against; see ../shared/STACK.md) and OpenCV 4.6 (the headers and
# libraries the opencv crate binds to, for stereo matching in cpsl-stereo and tracking and
# multi-view depth in cpsl-track; its ximgproc module comes with libopencv-contrib-dev, which
# libopencv-dev depends on).
set -euo pipefail
PKGS="ffmpeg libavcodec-dev libavformat-dev libavutil-dev libswscale-dev libswresample-dev
libavfilter-dev libavdevice-dev pkg-config clang libclang-dev libopencv-dev"
missing=""
for p in $PKGS; do
  dpkg -s "$p" >/dev/null 2>&1 || missing="$missing $p"
done
if [ -n "$missing" ]; then
  SUDO=""; [ "$(id -u)" -eq 0 ] || SUDO="sudo"
  echo "installing:$missing" >&2
  $SUDO apt-get update -qq
  # shellcheck disable=SC2086
  $SUDO env DEBIAN_FRONTEND=noninteractive apt-get install -y -qq $missing >/dev/null
fi
