"""Shared by the benchmarks: where results go and how they are printed."""

from __future__ import annotations

import json
import os
import platform
from pathlib import Path

RESULTS = Path(__file__).resolve().parent / "results"


def machine() -> dict:
    return {
        "cpu_count": os.cpu_count(),
        "machine": platform.machine(),
        "python": platform.python_version(),
    }


def report(name: str, figures: dict) -> None:
    """Print ``figures`` and write them with the machine description to results/NAME.json."""
    RESULTS.mkdir(exist_ok=True)
    for key, value in figures.items():
        print(f"{key:<32} {value:,.3f}" if isinstance(value, float) else f"{key:<32} {value}")
    out = RESULTS / f"{name}.json"
    out.write_text(json.dumps({"benchmark": name, "machine": machine(), **figures}, indent=2))
    print(f"-> {out}")
