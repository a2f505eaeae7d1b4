"""How often the monitor redraws its live event image, headless (textual's Pilot), while a
replay camera streams the color scene in real time.

    .venv/bin/python bench/tui_refresh.py [--seconds S] [--size 120x40]
"""

from __future__ import annotations

import argparse
import asyncio
import shutil
import tempfile
import time
from pathlib import Path

from _common import report

from evcap.acquire.device import Davis346, DeviceSpec
from evcap.acquire.recorder import Recorder
from evcap.tui import make_app

FIXTURE = Path(__file__).resolve().parent.parent / "hw-fixtures" / "color-scene"


async def measure(app, seconds: float, size: tuple[int, int]) -> tuple[int, float]:
    async with app.run_test(size=size) as pilot:
        view = app.query_one("#events")
        while app.live.totals["events"] == 0:
            await pilot.pause(0.01)
        start, first = time.perf_counter(), view.updates
        await pilot.pause(seconds)
        updates, elapsed = view.updates - first, time.perf_counter() - start
        await pilot.press("q")
    return updates, elapsed


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--seconds", type=float, default=2.5)
    parser.add_argument("--size", default="120x40")
    args = parser.parse_args(argv)
    size = tuple(int(v) for v in args.size.split("x"))
    with tempfile.TemporaryDirectory() as tmp:
        fixture = Path(tmp) / "scene"
        shutil.copytree(FIXTURE, fixture)
        with Davis346.open(DeviceSpec("replay", path=fixture, speed=1.0)) as cam:
            app = make_app(Recorder(cam, None), output_dir=tmp)
            updates, elapsed = asyncio.run(measure(app, args.seconds, size))
    report(
        "tui_refresh",
        {
            "terminal": args.size,
            "updates": updates,
            "seconds": elapsed,
            "updates_per_s": updates / elapsed,
        },
    )


if __name__ == "__main__":
    main()
