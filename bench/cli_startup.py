"""How long `evcap --help` takes from the shell (median of several runs).

.venv/bin/python bench/cli_startup.py [--runs 10]
"""

from __future__ import annotations

import argparse
import statistics
import subprocess
import sys
import time

from _common import report


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--runs", type=int, default=10)
    args = parser.parse_args(argv)
    times = []
    for _ in range(args.runs):
        start = time.perf_counter()
        subprocess.run([sys.executable, "-m", "evcap", "--help"], check=True, capture_output=True)
        times.append(time.perf_counter() - start)
    report("cli_startup", {"help_median_s": statistics.median(times), "help_max_s": max(times)})


if __name__ == "__main__":
    main()
