#!/usr/bin/env bash
# Installs what the browser player's build and end-to-end test need, if missing: Debian's
# Chromium (headless, driven by npm playwright-core; never `npx playwright install`) and the
# player's npm dev dependencies (TypeScript, playwright-core) from the npm registry.
set -euo pipefail
cd "$(dirname "$0")/.."
if ! command -v chromium >/dev/null; then
  SUDO=""; [ "$(id -u)" -eq 0 ] || SUDO="sudo"
  echo "installing: chromium" >&2
  $SUDO apt-get update -qq
  $SUDO env DEBIAN_FRONTEND=noninteractive apt-get install -y -qq chromium >/dev/null
fi
command -v npm >/dev/null || { echo "npm is missing (Node 20 or newer is needed to build and test the player)" >&2; exit 1; }
(cd web && npm ci --no-audit --no-fund --loglevel=error)
