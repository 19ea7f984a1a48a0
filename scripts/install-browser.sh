#!/usr/bin/env bash
# Install Debian's headless-capable Chromium and its chromedriver for the viewer's browser tests
# (tests/test_viewer.py, marker "browser"). Idempotent and never fatal: when the browser cannot be
# installed it prints one line and exits 0, and those tests skip themselves.
#
# Usage: bash scripts/install-browser.sh        (CI calls it before pytest)
set -u

CHROMIUM=/usr/bin/chromium
CHROMEDRIVER=/usr/bin/chromedriver

if [ -x "$CHROMIUM" ] && [ -x "$CHROMEDRIVER" ]; then
    exit 0
fi

skip() {
    echo "install-browser: $1; the browser tests (pytest -m browser) will be skipped"
    exit 0
}

[ "$(id -u)" = "0" ] || skip "not root, cannot apt-get install chromium chromium-driver"
command -v apt-get >/dev/null 2>&1 || skip "no apt-get on this machine"

export DEBIAN_FRONTEND=noninteractive
if ! apt-get update -qq >/dev/null 2>&1; then
    skip "apt-get update failed"
fi
if ! apt-get install -y -qq chromium chromium-driver >/dev/null 2>&1; then
    skip "apt-get install chromium chromium-driver failed"
fi
if [ -x "$CHROMIUM" ] && [ -x "$CHROMEDRIVER" ]; then
    echo "install-browser: installed $("$CHROMIUM" --version 2>/dev/null | head -n 1)"
else
    skip "chromium or chromedriver still missing after apt-get install"
fi
exit 0
