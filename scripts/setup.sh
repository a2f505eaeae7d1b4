#!/usr/bin/env bash
# Create .venv (if missing) and install evcap with its test tools and Ray (evcap batch) into it;
# and a browser for the browser tests where the machine allows.
# torch goes first, pinned to the local CPU build; every later install is constrained by the
# lock, constraints.txt (scripts/lock.sh), which pins torch and every other package, so that no
# dependency can pull a CUDA build of torch from PyPI and two fresh clones get the same numerics. --no-compile: pip would
# byte-compile every module it installs (torch's thousands: about a minute of the setup here);
# Python compiles the ones it imports when it first imports them.
set -euo pipefail
cd "$(dirname "$0")/.."
python3 -m venv .venv
.venv/bin/python -m pip install --quiet --upgrade pip
.venv/bin/python -m pip install --quiet --no-compile torch==2.13.0
.venv/bin/python -m pip install --quiet --no-compile -c constraints.txt -e '.[test,cluster]'
# Debian's Chromium, for the browser tests (the report's page, the 3D viewer), where this machine
# allows it (root and apt; about 40 s); elsewhere those tests skip
if [ ! -x /usr/bin/chromium ] && [ "$(id -u)" = 0 ] && command -v apt-get > /dev/null; then
    { apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq \
        --no-install-recommends chromium; } > /dev/null 2>&1 ||
        echo "setup: Chromium not installed: the browser tests will skip"
fi
