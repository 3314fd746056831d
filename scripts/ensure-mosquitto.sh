#!/usr/bin/env bash
# Installs the Mosquitto broker binary for the `broker` tests when it is missing.
# Tests start and stop their own broker on a free loopback port; nothing is left running.
set -euo pipefail
if command -v mosquitto >/dev/null 2>&1 || [ -x /usr/sbin/mosquitto ]; then
  exit 0
fi
if [ "$(id -u)" = "0" ] && command -v apt-get >/dev/null 2>&1; then
  echo "installing mosquitto (needed by the broker tests)..."
  apt-get update -qq
  DEBIAN_FRONTEND=noninteractive apt-get install -y -qq mosquitto >/dev/null
  # Debian starts the packaged service; the tests run their own broker.
  (command -v systemctl >/dev/null 2>&1 && systemctl stop mosquitto 2>/dev/null) || true
else
  echo "mosquitto is missing and cannot be installed here (not root or no apt-get);" \
       "the broker tests will be skipped." >&2
fi
