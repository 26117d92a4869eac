#!/usr/bin/env bash
# Make sure a headless Chromium is present for the leaderboard page's browser test
# (`make test-slow`). Installs Debian's chromium with apt-get when missing.
set -euo pipefail

for candidate in chromium chromium-browser google-chrome; do
  command -v "$candidate" >/dev/null 2>&1 && exit 0
done

if command -v apt-get >/dev/null 2>&1 && [ "$(id -u)" -eq 0 ]; then
  echo "Installing Chromium for the leaderboard page's browser test"
  export DEBIAN_FRONTEND=noninteractive
  apt-get update -qq
  apt-get install -y -qq --no-install-recommends chromium >/dev/null
  exit 0
fi

echo "error: the browser test needs Chromium; install it (Debian/Ubuntu: sudo apt-get install chromium)" >&2
exit 1
