#!/usr/bin/env bash
# Streaming benchmarks, as recorded in BENCHMARKS.md: `cpsl bench serve` (200 clients for 30 s
# on loopback) side by side with nginx serving the same folder, then the browser player's
# playback in headless Chromium. Installs nginx-light (Debian) on first use; needs the demo's
# package (runs the demo if out/demo/clip.cpsl is missing). JSON reports go to out/bench/.
set -euo pipefail
cd "$(dirname "$0")/.."
cargo build --release -p cpsl
cpsl=./target/release/cpsl
mkdir -p out/bench
[ -f out/demo/clip.cpsl/manifest.json ] || $cpsl demo -o out/demo >/dev/null
if ! command -v nginx >/dev/null; then
  SUDO=""; [ "$(id -u)" -eq 0 ] || SUDO="sudo"
  $SUDO apt-get update -qq
  $SUDO env DEBIAN_FRONTEND=noninteractive apt-get install -y -qq nginx-light >/dev/null
fi
conf=$(mktemp -d)
cat > "$conf/nginx.conf" <<CONF
worker_processes auto;
pid $conf/nginx.pid;
error_log $conf/error.log;
events { worker_connections 4096; }
http {
  access_log off;
  sendfile on;
  tcp_nopush on;
  keepalive_requests 1000000;
  types { video/mp4 mp4; application/json json; application/octet-stream bin; }
  server { listen 127.0.0.1:8081; location /files/ { alias $PWD/out/demo/; } }
}
CONF
nginx -c "$conf/nginx.conf"
trap 'nginx -c "$conf/nginx.conf" -s stop 2>/dev/null; rm -rf "$conf"' EXIT
$cpsl bench serve out/demo --clients 200 --seconds "${SECONDS_LOAD:-30}" --peer 127.0.0.1:8081 \
  --json out/bench/serve.json
bash scripts/setup-web.sh
(cd web && CPSL_BIN="$PWD/../target/release/cpsl" node test/bench.mjs ../out/demo 10) | tee out/bench/player.json
