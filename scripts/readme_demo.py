"""The README's paragraph of the demo's figures, generated, not typed: from what `evcap demo`
wrote (DIR/pipeline.json: each step's time and summary; DIR/reconstruction/metrics.json: the
figures), kept in docs/figures/demo.json and written into README.md between its two markers.

    .venv/bin/python scripts/readme_demo.py evcap-demo

tests/test_demo.py checks that README.md holds the paragraph docs/figures/demo.json gives.
"""

from __future__ import annotations

import datetime
import json
import os
import re
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
FACTS = ROOT / "docs" / "figures" / "demo.json"
README = ROOT / "README.md"
BEGIN, END = "<!-- demo figures: scripts/readme_demo.py -->", "<!-- end of the demo figures -->"
FIGURES = (
    "object_psnr",
    "object_psnr_gain",
    "object_psnr_constant",
    "radiance_normal_mae_deg",
    "normal_mae_deg",
    "depth_rel_err",
    "depth_within_5pct",
    "background_clear",
    "base_color_psnr",
    "base_color_psnr_gain",
    "base_color_psnr_constant",
    "base_color_psnr_gain_baseline",
    "relit_object_psnr",
    "relit_object_psnr_gain",
    "relit_object_psnr_constant",
    "relit_object_psnr_gain_baseline",
)


def facts(demo: Path) -> dict:
    """What the paragraph says, read from a finished demo's folder."""
    state = json.loads((demo / "pipeline.json").read_text())
    metrics = json.loads((demo / "reconstruction" / "metrics.json").read_text())
    done = state["done"]
    missing = [k for k in FIGURES if metrics.get(k) is None]
    if missing:
        raise SystemExit(f"{demo}: metrics.json lacks {', '.join(missing)}; run the whole demo")
    step = {name.split(" ")[0]: value for name, value in done.items()}
    registered = re.match(r"(\d+) of (\d+) frames registered", step["poses"]["summary"])
    return {
        "date": datetime.date.today().isoformat(),
        "cpus": os.cpu_count(),
        "preset": metrics["preset"],
        "seed": metrics["seed"],
        "seconds": sum(v["seconds"] for v in done.values()),
        "poses_seconds": step["poses"]["seconds"],
        "reconstruct_seconds": step["reconstruct"]["seconds"],
        "frames_registered": [int(registered[1]), int(registered[2])],
        "poses_against_truth": step["register"]["summary"].removeprefix("against the truth: "),
        "figures": {k: metrics[k] for k in FIGURES},
    }


def paragraph(f: dict) -> str:
    """The paragraph, wrapped as the README is."""
    g = f["figures"]
    used, total = f["frames_registered"]
    text = (
        f"As `evcap demo` wrote it ({f['date']}, {f['cpus']} CPU cores; `{f['preset']}`, seed "
        f"{f['seed']}): the steps took {f['seconds']:.0f} s in all (poses "
        f"{f['poses_seconds']:.0f} s, reconstruct {f['reconstruct_seconds']:.0f} s). Structure "
        f"from motion registered {used} of {total} frames; the poses against the truth: "
        f"{f['poses_against_truth']}. On the held-out views the object's pixels score "
        f"{g['object_psnr']:.1f} dB as rendered and {g['object_psnr_gain']:.1f} dB after one "
        f"gain per color channel fitted once over all held-out views (what the events leave "
        f"undetermined), against a constant color's {g['object_psnr_constant']:.1f} dB; normals "
        f"{g['radiance_normal_mae_deg']:.1f} degrees off (stage II's "
        f"{g['normal_mae_deg']:.1f}), depth {100 * g['depth_rel_err']:.1f} % of the distance "
        f"({100 * g['depth_within_5pct']:.0f} % of the object's pixels within 5 %), and "
        f"{100 * g['background_clear']:.0f} % of the backdrop is seen through, not fogged. "
        f"Stage II's base color: {g['base_color_psnr']:.1f} dB as rendered, "
        f"{g['base_color_psnr_gain']:.1f} after one gain, against a constant color's "
        f"{g['base_color_psnr_constant']:.1f} and stage I's radiance taken as the base color "
        f"{g['base_color_psnr_gain_baseline']:.1f}. Relit under the truth's second light, the "
        f"object scores {g['relit_object_psnr']:.1f} dB as rendered and "
        f"{g['relit_object_psnr_gain']:.1f} with the gain of the views under the first light, "
        f"against a constant color's {g['relit_object_psnr_constant']:.1f} "
        f"({g['relit_object_psnr_gain_baseline']:.1f} for the views never relit)."
    )
    return wrap(text)


def wrap(text: str, width: int = 96) -> str:
    lines, line = [], ""
    for word in text.split(" "):
        if line and len(line) + 1 + len(word) > width:
            lines.append(line)
            line = word
        else:
            line = f"{line} {word}" if line else word
    return "\n".join([*lines, line])


def bounds(readme: str) -> tuple[int, int]:
    """Where the text between README's markers starts and ends."""
    return readme.index(BEGIN) + len(BEGIN), readme.index(END)


def section(readme: str) -> str:
    """The text between README's markers."""
    start, end = bounds(readme)
    return readme[start:end].strip("\n")


def main(demo: Path) -> None:
    found = facts(demo)
    FACTS.write_text(json.dumps(found, indent=2) + "\n")
    readme = README.read_text()
    start, end = bounds(readme)
    README.write_text(readme[:start] + "\n" + paragraph(found) + "\n" + readme[end:])
    print(f"-> {FACTS}, {README}")


if __name__ == "__main__":
    main(Path(sys.argv[1]))
