#!/usr/bin/env bash
# Install the headless browser the staff console's page test drives (tests/console/test_page.py):
#   Debian's chromium and chromium-driver (selenium itself comes with the test extra).
# Idempotent; exits non-zero (and says why) when it cannot.
set -euo pipefail
if command -v chromium >/dev/null && command -v chromedriver >/dev/null; then
    exit 0
fi
if [ "$(id -u)" != 0 ]; then
    echo "[browser] not root: cannot apt-get install chromium chromium-driver" >&2
    exit 1
fi
echo "[browser] installing chromium chromium-driver (apt)"
export DEBIAN_FRONTEND=noninteractive
apt-get update -qq >/dev/null || true
apt-get install -y -qq chromium chromium-driver >/dev/null
command -v chromium >/dev/null && command -v chromedriver >/dev/null \
    || { echo "[browser] chromium or chromedriver still missing after apt-get" >&2; exit 1; }
