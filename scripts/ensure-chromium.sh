#!/usr/bin/env bash
# Installs Debian's Chromium for the `browser` tests (the live 3D view) when it is missing.
# Playwright drives this system binary (never `playwright install`: no browser download).
set -euo pipefail
if command -v chromium >/dev/null 2>&1 || [ -x /usr/bin/chromium ]; then
  exit 0
fi
if [ "$(id -u)" = "0" ] && command -v apt-get >/dev/null 2>&1; then
  echo "installing chromium (needed by the browser tests)..."
  export DEBIAN_FRONTEND=noninteractive
  # the package lists may be missing or stale on a fresh machine: update once, then retry
  apt-get install -y -qq chromium >/dev/null 2>&1 || {
    apt-get update -qq
    apt-get install -y -qq chromium >/dev/null
  }
else
  echo "chromium is missing and cannot be installed here (not root or no apt-get);" \
       "the browser tests will be skipped." >&2
fi
