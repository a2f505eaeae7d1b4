"""The collection side by side: OUTDIR/summary.json, summary.csv and index.html, one row per
recording (its status, its one-line error, each step's time, the reconstruction's figures)."""

from __future__ import annotations

import csv
import html
import io
import json
from dataclasses import asdict, dataclass, field
from pathlib import Path

from evcap.atomic_write import write_text_atomic
from evcap.pipeline import STEPS, Status, StepResult, Workspace
from evcap.records import Figures
from evcap.records.result import SHOWN


@dataclass
class RecordingRow:
    name: str
    path: str
    steps: dict[str, StepResult] = field(default_factory=dict)

    @property
    def status(self) -> Status:
        states = [r.status for r in self.steps.values()]
        for worst in ("failed", "stopped", "not run"):
            if worst in states:
                return worst
        return "done" if states else "not run"

    @property
    def error(self) -> str:
        for r in self.steps.values():
            if r.status in ("failed", "not run") and r.error:
                return f"{r.name}: {r.error}"
        return ""

    @property
    def seconds(self) -> float:
        return sum(r.seconds for r in self.steps.values())

    @property
    def figures(self) -> dict:
        r = self.steps.get("reconstruct")
        return dict(r.figures) if r is not None else {}

    def to_json(self) -> dict:
        return {
            "name": self.name,
            "path": self.path,
            "status": self.status,
            "error": self.error,
            "seconds": self.seconds,
            "figures": self.figures,
            "steps": {k: asdict(v) for k, v in self.steps.items()},
        }


def write_summary(out: Path, rows: list[RecordingRow], about: dict) -> None:
    """summary.json (everything), summary.csv (a row per recording) and index.html."""
    out.mkdir(parents=True, exist_ok=True)
    document = {**about, "recordings": [r.to_json() for r in rows]}
    write_text_atomic(out / "summary.json", json.dumps(document, indent=2))
    columns = ["name", "status", "error", "seconds"]
    columns += [f"{s}_{k}" for s in STEPS for k in ("status", "seconds")]
    columns += list(SHOWN)
    lines = []
    for r in rows:
        line = {
            "name": r.name,
            "status": r.status,
            "error": r.error,
            "seconds": round(r.seconds, 1),
        }
        for s, step in r.steps.items():
            line[f"{s}_status"], line[f"{s}_seconds"] = step.status, round(step.seconds, 1)
        lines.append({**line, **{k: round(v, 4) for k, v in r.figures.items()}})
    table = io.StringIO(newline="")
    writer = csv.DictWriter(table, columns)
    writer.writeheader()
    writer.writerows(lines)
    write_text_atomic(out / "summary.csv", table.getvalue())
    write_text_atomic(out / "index.html", _page(out, rows, about))


def _page(out: Path, rows: list[RecordingRow], about: dict) -> str:
    e = html.escape
    head = ["recording", "status", *STEPS, *(_label(k) for k in SHOWN), "error"]
    body = []
    for r in rows:
        name = e(r.name)
        report = Workspace(out / r.name).report
        if report.exists():
            name = f'<a href="{e(report.relative_to(out).as_posix())}">{name}</a>'
        cells = [name, f'<span class="{e(r.status)}">{e(r.status)}</span>']
        for s in STEPS:
            step = r.steps.get(s)
            cells.append("" if step is None else f"{e(step.status)}<br>{step.seconds:.1f} s")
        figures = r.figures
        cells += [_number(figures.get(k), k) for k in SHOWN]
        cells.append(e(r.error))
        body.append("<tr>" + "".join(f"<td>{c}</td>" for c in cells) + "</tr>")
    counts = {s: sum(r.status == s for r in rows) for s in ("done", "failed", "stopped", "not run")}
    tally = ", ".join(f"{n} {s}" for s, n in counts.items() if n)
    facts = "".join(
        f"<li>{e(str(k))}: {e(str(v))}</li>" for k, v in about.items() if k != "calibrations"
    )
    calibrations = "".join(
        f"<li>{e(c['name'])}: {e(c['status'])} {e(c['summary'] or c['error'])}</li>"
        for c in about.get("calibrations", [])
    )
    return f"""<!doctype html>
<html><head><meta charset="utf-8"><title>evcap batch: {e(str(out))}</title>
<style>
body {{ font-family: sans-serif; margin: 2em; }}
table {{ border-collapse: collapse; }}
td, th {{ border: 1px solid #ccc; padding: 0.3em 0.6em; text-align: right; vertical-align: top; }}
td:first-child, td:last-child {{ text-align: left; }}
.done {{ color: #176117; }} .failed {{ color: #a01010; font-weight: bold; }}
.stopped, .not {{ color: #8a6d00; }}
</style></head><body>
<h1>evcap batch</h1>
<p>{len(rows)} recordings: {e(tally)}</p>
<ul>{facts}</ul>
{f"<h2>Calibrations</h2><ul>{calibrations}</ul>" if calibrations else ""}
<table><tr>{"".join(f"<th>{e(h)}</th>" for h in head)}</tr>
{"".join(body)}
</table></body></html>
"""


def _label(key: str) -> str:
    name, unit, _ = Figures.describe(key)
    return f"{name} ({unit})" if unit else name


def _number(value: object, key: str) -> str:
    if not isinstance(value, int | float):
        return ""
    return f"{100 * value:.1f} %" if key == "depth_rel_err" else f"{value:.2f}"
