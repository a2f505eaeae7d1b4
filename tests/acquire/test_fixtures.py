"""The fixtures in hw-fixtures/ are what their generator makes."""

import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]


def test_generator_reproduces_the_committed_fixtures():
    r = subprocess.run(
        [sys.executable, str(ROOT / "hw-fixtures" / "generate.py"), "--check"],
        capture_output=True,
        text=True,
    )
    assert r.returncode == 0, r.stdout + r.stderr
