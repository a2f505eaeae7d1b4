#!/usr/bin/env bash
# Write constraints.txt, the lock that scripts/setup.sh installs through: every package evcap and
# its extras (test, cluster, bench) pull in, at the version pip resolves today in a fresh venv,
# pinned with ==. Run it to move the pins on, then the default tests, and commit the file with
# their result. torch stays pinned to the local CPU build (2.13.0), first, as in setup.sh.
set -euo pipefail
cd "$(dirname "$0")/.."
fresh=$(mktemp -d)
trap 'rm -rf "$fresh"' EXIT
python3 -m venv "$fresh/venv"
"$fresh/venv/bin/python" -m pip install --quiet --upgrade pip
"$fresh/venv/bin/python" -m pip install --quiet --no-compile torch==2.13.0
echo "torch==2.13.0" > "$fresh/torch.txt"
"$fresh/venv/bin/python" -m pip install --quiet --no-compile -c "$fresh/torch.txt" \
    -e '.[test,cluster,bench]'
{
    echo "# The lock: what scripts/setup.sh installs, every package pinned (scripts/lock.sh wrote it"
    echo "# on $(date -u +%Y-%m-%d) with Python $("$fresh/venv/bin/python" -c 'import platform; print(platform.python_version())')). torch: the local CPU build, installed first."
    echo "torch==2.13.0"
    "$fresh/venv/bin/python" -m pip freeze --exclude-editable | grep -v -i '^torch=='
} > constraints.txt
echo "constraints.txt: $(grep -c '==' constraints.txt) packages pinned"
