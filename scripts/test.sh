#!/usr/bin/env bash
# Lint and run the test suite (the default run skips tests marked slow or hardware).
set -euo pipefail
cd "$(dirname "$0")/.."
.venv/bin/ruff check .
.venv/bin/ruff format --check .
.venv/bin/python -m pytest "$@"
