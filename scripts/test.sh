#!/usr/bin/env bash
# Lint and run the test suite (the default run skips tests marked slow or hardware) in two
# processes, each test file whole in one of them (its module fixtures made once), the longest
# files dealt first (tests/conftest.py orders them); `-n 0` after it runs them in this one.
set -euo pipefail
cd "$(dirname "$0")/.."
.venv/bin/ruff check .
.venv/bin/ruff format --check .
.venv/bin/python -m pytest -n 2 --dist loadfile --no-loadscope-reorder "$@"
