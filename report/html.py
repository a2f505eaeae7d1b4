"""`evcap report OUT`: OUT/report.html, one self-contained page of a reconstruction folder and
its session: first the recovered maps beside the truth, the relit views, the metrics and the
accuracy-versus-time plot; then how it was made: the session's summary, the calibration maps,
the trajectory, event edge maps.

Every image is a PNG data URI and every plot inline SVG, so the page opens with no network.
A section whose data is not there says so in one line.
"""

from __future__ import annotations

import contextlib
import json
import math
import re
import zipfile
import zlib
from datetime import datetime
from html import escape
from pathlib import Path

import numpy as np

from evcap.atomic_write import write_text_atomic
from evcap.errors import InputError, InputNotFoundError
from evcap.records import (
    Calibration,
    Figures,
    GroundTruth,
    Poses,
    ReconstructionFolder,
    ReconstructionResult,
    TruthViews,
)
from evcap.records.result import RUN, STAGE_I, STAGE_II
from evcap.report.images import (
    colormap,
    depth_image,
    depth_range,
    event_image,
    file_data_uri,
    gray_image,
    mark_pixels,
    normal_image,
    png_data_uri,
    ramp_image,
    srgb8,
    value_range,
)
from evcap.report.svg import COLORS, Series, Track, line_plot, trajectory_views
from evcap.session import Session

# the sections, in order: (anchor, heading). The page opens with what was recovered beside the
# truth, the figures after it, and then how it was made
SECTIONS = (
    ("maps", "Recovered maps and the truth"),
    ("relit", "Relit views and the light"),
    ("metrics", "Metrics"),
    ("progress", "Accuracy versus time"),
    ("session", "Session"),
    ("calibration", "Calibration"),
    ("trajectory", "Trajectory"),
    ("edges", "Event edge maps"),
)
EDGE_MAPS = 3  # each takes about 2 s for a 346 x 260 sensor on one CPU core
EDGE_SLICE_MS = 10.0  # stage II's default, when its settings do not say
MAX_VIEWS = 3  # test views shown side by side with the truth
VIEW_PX = 200  # displayed width of each view's maps
MAP_PX = 346  # displayed width of a calibration map

# the run's fields of the result, as shown: (readable name, unit, group); the figures describe
# themselves (evcap.records.Figures)
RUN_FIELDS = {
    "iterations": ("iterations", "", STAGE_I),
    "gaussians": ("Gaussians", "", STAGE_I),
    "seconds": ("time", "s", STAGE_I),
    "material_iterations": ("iterations", "", STAGE_II),
    "material_seconds": ("time", "s", STAGE_II),
    "effects": ("effects modelled", "", STAGE_II),
    "relit": ("relit under a new light", "", STAGE_II),
    "views": ("views evaluated", "", RUN),
    "preset": ("preset", "", RUN),
    "seed": ("seed", "", RUN),
    "zero_events": ("pixels without events", "", RUN),
    "device": ("device", "", RUN),
    "backend": ("rasterizer", "", RUN),
    "interrupted": ("interrupted (Ctrl-C)", "", RUN),
}

STYLE = """
body { font-family: sans-serif; margin: 24px auto; max-width: 1180px; color: #222; }
h1 { font-size: 22px; } h2 { font-size: 18px; border-bottom: 1px solid #ccc; margin-top: 32px; }
table { border-collapse: collapse; margin: 8px 0; }
td, th { border: 1px solid #ddd; padding: 3px 8px; text-align: left; vertical-align: top; }
td.num { text-align: right; font-variant-numeric: tabular-nums; }
th.group { background: #f2f2f2; }
pre { background: #f7f7f7; padding: 8px; overflow-x: auto; }
figure { display: inline-block; margin: 4px 12px 12px 0; vertical-align: top; }
figcaption { font-size: 12px; }
img { image-rendering: pixelated; }
figure img, .views img { border: 1px solid #ddd; }
.views img { display: block; }
.bar { font-size: 11px; } .bar img { vertical-align: middle; margin: 0 4px; }
.pair { display: inline-block; margin-right: 16px; }
.missing { color: #666; font-style: italic; }
.plots svg { margin: 0 12px 12px 0; }
nav a { margin-right: 10px; }
"""


def write_report(out: str | Path, session: str | Path | None = None) -> Path:
    """Write the report of the reconstruction folder ``out`` and its session (default: the one
    it was made from); returns the page's path (OUT/report.html)."""
    folder = ReconstructionFolder(out)
    folder.check()
    session_path = _session_path(folder, session)
    result, result_note = _read_result(folder)
    run = folder.settings("reconstruct")
    with Session.open(session_path) as s:
        bodies = {
            "session": _session_section(s, run),
            "calibration": _calibration_section(s),
            "trajectory": _trajectory_section(s),
            "edges": _edges_section(s, folder.settings("stage2")),
            "maps": _maps_section(folder, s),
        }
    bodies["relit"] = _relit_section(folder)
    bodies["metrics"] = result_note or _metrics_section(result)
    bodies["progress"] = _progress_section(result or ReconstructionResult())
    top = _viewer_link(folder) + (_glance(result) if result is not None else "")
    write_text_atomic(folder.report, _page(folder.root, bodies, top))
    return folder.report


# -- inputs ----------------------------------------------------------------------------------


def _session_path(folder: ReconstructionFolder, session: str | Path | None) -> Path:
    if session is None:
        return folder.session()
    path = Path(session)
    if not path.is_file():
        raise InputNotFoundError(f"session {path}: no such file (check --session)")
    return path


def _read_result(folder: ReconstructionFolder) -> tuple[ReconstructionResult | None, str]:
    """(OUT's result, "") or (None, a note saying why there is none)."""
    try:
        return folder.read_result(), ""
    except InputError as e:
        return None, _missing(str(e))


# -- small pieces of HTML --------------------------------------------------------------------


def _missing(text: str) -> str:
    return f'<p class="missing">{escape(text)}</p>'


def _number(value: object, digits: int = 4) -> str:
    """A value for a table: numbers to ``digits`` significant digits, NaN, infinity and None
    as n/a."""
    if value is None:
        return "n/a"
    if isinstance(value, bool | np.bool_):
        return "yes" if value else "no"
    if isinstance(value, int | np.integer):
        return f"{int(value):,}"
    if isinstance(value, float | np.floating):
        v = float(value)
        return f"{v:.{digits}g}" if math.isfinite(v) else "n/a"
    return str(value)


def _table(rows: list[tuple[str, str]]) -> str:
    body = "".join(f"<tr><th>{escape(k)}</th><td>{escape(v)}</td></tr>" for k, v in rows)
    return f"<table>{body}</table>"


def _figure(uri: str, caption: str, width: int) -> str:
    """An image with its caption (HTML: it may hold a color bar) under it."""
    alt = re.sub(r"<[^>]*>", " ", caption.split("<br>")[0])
    return (
        f'<figure style="max-width: {width + 2}px"><img src="{uri}" width="{width}" '
        f'alt="{escape(alt, quote=True)}"><figcaption>{caption}</figcaption></figure>'
    )


def _color_bar(lo: float, hi: float, unit: str = "") -> str:
    """The color map's ramp between its end values (HTML, for a caption)."""
    return (
        f'<span class="bar">{escape(_number(lo, 3))}'
        f'<img src="{png_data_uri(ramp_image())}" width="120" height="10" alt="color bar">'
        f"{escape(_number(hi, 3))} {escape(unit)}</span>"
    )


def _viewer_link(folder: ReconstructionFolder) -> str:
    """A line linking the 3D viewer beside the page, or saying how to make it."""
    if folder.viewer.exists():
        return (
            f'<p>In 3D (mesh, Gaussians, camera path): <a href="{folder.viewer.name}">'
            f"{folder.viewer.name}</a>.</p>"
        )
    return "<p>In 3D: <code>evcap view OUT</code> writes the mesh and a viewer beside it.</p>"


def _glance(result: ReconstructionResult) -> str:
    """The first screen's verdict: the object's figures against the bar a user judges it by
    (evcap/recovered.py), the object beside what a constant color scores; nothing
    without held-out truth."""
    from evcap.recovered import checks

    figures = result.figures.measured()
    found = [c for c in checks(figures) if c.value is not None]
    if not found:
        return ""
    rows = []
    for c in found:
        shown = f"{_number(c.value, 3)}{c.unit}"
        if c.name == "object over a constant color":
            gain, constant = figures["object_psnr_gain"], figures["object_psnr_constant"]
            shown = (
                f"{_number(gain, 3)} dB after one gain against {_number(constant, 3)} dB for "
                f"a constant color: {c.value:+.2f} dB"
                if math.isfinite(c.value)
                else "n/a"
            )
        rows.append(
            f"<tr><td>{escape(c.name)}</td><td>{escape(shown)}</td>"
            f"<td>{escape(f'{c.sense} {c.limit:g}{c.unit}')}</td>"
            f"<td>{'met' if c.met else '<b>missed</b>'}</td></tr>"
        )
    missed = len(found) - sum(c.met for c in found)
    verdict = (
        "The object is recovered: every figure measured meets its bar."
        if not missed
        else f"{missed} of {len(found)} figures miss their bar."
    )
    return (
        f"<p>{escape(verdict)} Held-out views against the truth:</p><table>"
        "<tr><th>figure</th><th>measured</th><th>bar</th><th></th></tr>"
        + "".join(rows)
        + "</table>"
    )


def _page(out: Path, bodies: dict[str, str], viewer: str = "") -> str:
    nav = " ".join(f'<a href="#{key}">{escape(title)}</a>' for key, title in SECTIONS)
    sections = "".join(
        f'<section id="{key}"><h2>{k}. {escape(title)}</h2>{bodies[key]}</section>'
        for k, (key, title) in enumerate(SECTIONS, start=1)
    )
    written = datetime.now().astimezone().isoformat(timespec="seconds")
    return (
        "<!DOCTYPE html>\n"
        f'<html lang="en"><head><meta charset="utf-8"><title>evcap report: '
        f"{escape(out.name)}</title><style>{STYLE}</style></head><body>"
        f"<h1>evcap report: {escape(str(out))}</h1>"
        f"<p>Written {escape(written)} by <code>evcap report</code>.</p>{viewer}"
        f"<nav>{nav}</nav>{sections}</body></html>\n"
    )


# -- the session --------------------------------------------------------------------------


def _session_section(s: Session, run: dict) -> str:
    """The session's summary, and how the reconstruction was asked for (``run``)."""
    from evcap.summary import format_summary, summarize

    parts = [f"<pre>{escape(format_summary(summarize(s)))}</pre>"]
    if run:
        keys = ("stage", "preset", "device", "backend", "seed", "ablate", "relight")
        rows = [(k, str(run[k])) for k in keys if k in run and run[k] != ""]
        parts.append("<p>Reconstructed with:</p>" + _table(rows))
    return "".join(parts)


# -- the calibration ----------------------------------------------------------------------


def _calibration_section(s: Session) -> str:
    if not Calibration.present(s):
        return _missing("The session has no /calibration group (run `evcap calibrate` on it).")
    try:
        cal = Calibration.read(s)
    except InputError as e:
        return _missing(f"The calibration cannot be read: {e}")
    notes = cal.notes
    rows = [("source", cal.source)]
    for key in ("intrinsics_source", "threshold_source"):
        if key in notes:
            rows.append((key.replace("_", " "), str(notes[key])))
    if cal.K is not None:
        K = cal.K
        rows.append(
            (
                "intrinsics K",
                f"fx {_number(K[0, 0])}, fy {_number(K[1, 1])}, cx {_number(K[0, 2])}, "
                f"cy {_number(K[1, 2])} px",
            )
        )
        coefficients = " ".join(f"{d:+.4g}" for d in cal.dist) if len(cal.dist) else "none"
        rows.append(("distortion", f"{cal.distortion_model}: {coefficients}"))
    else:
        rows.append(("intrinsics", "not measured"))
    rows.append(("RMS reprojection error", f"{_number(cal.rms_reprojection_px)} px"))
    if cal.views is not None:
        rows.append(("board views used", f"{len(cal.views.rms_px)}"))
    for value, name, unit in (
        (cal.refractory_period_us, "refractory period", "µs"),
        (cal.background_activity_hz, "background activity", "Hz per pixel"),
        (cal.shot_noise_hz, "shot noise", "Hz per pixel"),
        (notes.get("threshold_confident_share"), "pixels with confident thresholds", "fraction"),
    ):
        if value is not None:
            rows.append((name, f"{_number(value)} {unit}"))
    if cal.hot_pixels is not None:
        rows.append(("hot pixels", f"{int(cal.hot_pixels.sum()):,}"))
    if "warnings" in notes:
        rows.append(("warnings", "; ".join(_json_list(notes["warnings"]))))
    return _table(rows) + _calibration_maps(cal)


def _json_list(raw: object) -> list[str]:
    try:
        value = json.loads(str(raw))
    except json.JSONDecodeError:
        return [str(raw)]
    return [str(v) for v in value] if isinstance(value, list) else [str(value)]


def _calibration_maps(cal: Calibration) -> str:
    figures = []
    hot = cal.hot_pixels
    maps = [m.astype(np.float64) for m in (cal.threshold_on, cal.threshold_off) if m is not None]
    if len(maps) == 2:
        # one range for both, so that ON and OFF compare at a glance
        lo, hi = value_range(np.concatenate([m.ravel() for m in maps]))
        for name, m in zip(("ON", "OFF"), maps, strict=True):
            finite = m[np.isfinite(m)]
            if finite.size and np.ptp(finite) == 0:
                caption = f"{name} threshold: {_number(finite[0], 3)} log units everywhere"
            else:
                mean = finite.mean() if finite.size else None
                caption = f"{name} threshold (mean {_number(mean, 3)} log units)<br>" + _color_bar(
                    lo, hi, "log"
                )
            figures.append(_figure(png_data_uri(colormap(m, lo, hi)), caption, MAP_PX))
    if cal.threshold_confidence is not None:
        c = cal.threshold_confidence.astype(np.float64)
        share = float((c >= 0.5).mean()) if c.size else 0.0
        figures.append(
            _figure(
                png_data_uri(colormap(c, 0.0, 1.0)),
                f"threshold fit confidence ({share:.0%} of pixels ≥ 0.5)<br>"
                + _color_bar(0.0, 1.0),
                MAP_PX,
            )
        )
    if cal.event_rate_hz is not None:
        rate = np.log10(np.maximum(cal.event_rate_hz.astype(np.float64), 1e-3))
        lo, hi = value_range(rate, (1, 99.9))
        image = colormap(rate, lo, hi)
        if hot is not None and hot.shape == rate.shape:
            image = mark_pixels(image, hot)
        n = int(hot.sum()) if hot is not None else 0
        figures.append(
            _figure(
                png_data_uri(image),
                f"event rate, {n} hot pixels circled<br>" + _color_bar(lo, hi, "log10 Hz"),
                MAP_PX,
            )
        )
    elif hot is not None and hot.any():
        image = mark_pixels(np.full(hot.shape + (3,), 255, np.uint8), hot)
        figures.append(_figure(png_data_uri(image), f"{int(hot.sum())} hot pixels", MAP_PX))
    if not figures:
        return _missing("The calibration holds no per-pixel maps.")
    if cal.event_rate_hz is None:
        figures.append(_missing("No event-rate map (the calibration did not measure the noise)."))
    return "<div>" + "".join(figures) + "</div>"


# -- the trajectory -----------------------------------------------------------------------


def _trajectory_section(s: Session) -> str:
    from evcap.trajectory_alignment import apply_similarity, errors_against_truth

    if not Poses.present(s):
        return _missing("The session has no /poses group (run `evcap poses` on it).")
    try:
        poses = Poses.read(s)
        truth = GroundTruth.read(s).poses() if GroundTruth.present(s) else None
    except InputError as e:
        return _missing(f"The poses cannot be read: {e}")
    t, T, source, arbitrary = poses.t, poses.T_world_cam, poses.source, poses.arbitrary_scale
    rows = [("source", source), ("poses", f"{len(t):,}"), ("scale", poses.scale)]
    parts: list[str] = []
    estimate = Track("poses", T[:, :3, 3], COLORS[0], T[:, :3, 2])
    tracks = [estimate]
    units = "arbitrary units" if arbitrary else "scene units"
    if truth is not None and source == "ground truth":
        parts.append("<p>The poses are the simulator's truth: nothing to compare.</p>")
    elif truth is not None:
        T_true = truth.T_world_cam
        try:
            errors = errors_against_truth(poses, truth)
        except InputError as e:
            parts.append(_missing(f"The poses cannot be compared with the truth: {e}"))
        else:
            if arbitrary:
                aligned = apply_similarity(T, errors["scale"], errors["R"], errors["t"])
                estimate.centres, estimate.forward = aligned[:, :3, 3], aligned[:, :3, 2]
                estimate.label = "poses, aligned (similarity)"
                units = "scene units"
            estimate.dashed = True
            tracks.insert(0, Track("truth", T_true[:, :3, 3], COLORS[1], T_true[:, :3, 2]))
            rows += [
                (
                    "compared at",
                    f"{errors['compared']} true poses, aligned by {errors['aligned_by']}",
                ),
                (
                    "rotation error",
                    f"median {_number(errors['rotation_median_deg'], 3)} deg, "
                    f"RMS {_number(errors['rotation_rms_deg'], 3)} deg",
                ),
                (
                    "translation error",
                    f"median {_number(errors['translation_median_pct'], 3)} %, "
                    f"RMS {_number(errors['translation_rms_pct'], 3)} % of the path's extent "
                    f"({_number(errors['extent'], 3)} scene units)",
                ),
            ]
            seconds = errors["seconds"]
            parts.append(
                '<div class="plots">'
                + line_plot(
                    [
                        Series("rotation (deg)", seconds, errors["rotation_deg"], COLORS[0]),
                        Series(
                            "translation (% of extent)",
                            seconds,
                            errors["translation_pct"],
                            COLORS[1],
                        ),
                    ],
                    title="pose errors against the truth",
                    x_label="time (s)",
                    y_label="error",
                )
                + "</div>"
            )
    else:
        parts.append("<p>The session has no true poses (/gt) to compare with.</p>")
    note = (
        "<p>Camera centres; strokes show where a few of the cameras look, a dot where the path "
        "starts. Simulated worlds have z up.</p>"
    )
    return _table(rows) + note + trajectory_views(tracks, units=units) + "".join(parts)


# -- event edge maps ----------------------------------------------------------------------


def _edges_section(s: Session, material: dict) -> str:
    """Edge maps as stage II makes them (``material``: its settings, for the slice)."""
    from evcap.edge_maps import edge_map

    span = s.time_range()
    if span is None or s.n_events == 0:
        return _missing("The session has no events.")
    slice_ms = material.get("edges", {}).get("slice_ms", EDGE_SLICE_MS)
    slice_us = round(float(slice_ms) * 1000)
    if span[1] - span[0] < slice_us:
        return _missing("The session is shorter than one edge map's slice of events.")
    w, h = s.sensor.width, s.sensor.height
    hot = np.zeros(w * h, bool)
    if Calibration.present(s):
        with contextlib.suppress(InputError):  # the calibration's own section says why
            hot = Calibration.read(s).hot().ravel()
    times = np.linspace(span[0] + slice_us, span[1], EDGE_MAPS + 2)[1:-1].astype(np.int64)
    figures = []
    for t in times:
        ev = s.events(int(t) - slice_us, int(t))
        keep = ~hot[ev.y.astype(np.int64) * w + ev.x]
        x, y = ev.x[keep].astype(np.int64), ev.y[keep].astype(np.int64)
        p, te = ev.p[keep], ev.t[keep]
        edges, _ = edge_map(np.stack([x, y], 1), te, int(t), w, h)
        when = f"{t / 1e6:.3f} s, {len(te):,} events"
        figures.append(
            _figure(png_data_uri(event_image(x, y, p, w, h)), f"events as they came ({when})", 260)
        )
        figures.append(
            _figure(png_data_uri(gray_image(edges)), f"edge map, motion-compensated ({when})", 260)
        )
    note = (
        "<p>Stage II computes its edge maps for its own training frames and does not save "
        f"them; these {len(times)} are made here the same way (evcap.edge_maps, contrast "
        f"maximisation) from the {slice_us / 1000:g} ms of events before each time, hot "
        "pixels left out. Left: the events as they came (ON red, OFF blue); right: the edge "
        "map (white: an edge).</p>"
    )
    return note + '<div class="views">' + _pairs(figures) + "</div>"


def _pairs(figures: list[str]) -> str:
    return "".join(
        f'<div class="pair">{a}{b}</div>' for a, b in zip(figures[::2], figures[1::2], strict=True)
    )


# -- recovered maps and the truth ---------------------------------------------------------


def _maps_section(folder: ReconstructionFolder, s: Session) -> str:
    truth, unreadable = None, []
    if GroundTruth.present(s):
        try:
            truth = GroundTruth.read(s).held_out
        except InputError as e:
            unreadable.append(_missing(f"The session's truth cannot be read: {e}"))
    stages = []
    for label, kind in (
        ("stage I: radiance field", "radiance"),
        ("stage II: material, shaded", "material"),
    ):
        for split in ("test", "path"):
            path = folder.views_values(kind, split)
            if path.exists():
                try:
                    stages.append((label, split, dict(np.load(path))))
                except (OSError, ValueError, EOFError, zipfile.BadZipFile, zlib.error) as e:
                    where = path.relative_to(folder.root)
                    unreadable.append(_missing(f"{where} is not readable ({e}); run again."))
                break
    notes = "".join(unreadable)
    if not stages:
        pngs = folder.rendered_images()
        if not pngs:
            return notes + _missing("There are no rendered views (renders/ is missing or empty).")
        figures = [_figure(file_data_uri(p), escape(p.name), VIEW_PX) for p in pngs[:24]]
        return (
            notes
            + _missing("No readable renders/*.npz: the PNGs as they were written.")
            + ("".join(figures))
        )
    kind = stages[0][1]
    intro = (
        "Held-out test views beside the session's truth."
        if truth is not None
        else "Views along the camera path (the session has no truth for them)."
    )
    if truth is not None and truth.radiance is not None:
        intro += (
            " Radiance is shown after one gain per channel (all events leave undetermined) "
            "fitted to the truth over all views on the object's pixels where the truth has "
            "depth, as object_psnr_gain is."
        )
    count = min([MAX_VIEWS, *(len(v["radiance"]) for _, _, v in stages if "radiance" in v)])
    tables = [_view_table(i, stages, truth) for i in range(count)]
    return notes + f"<p>{escape(intro)} ({kind} views; {count} shown)</p>" + "".join(tables)


MAP_COLUMNS = (
    ("radiance", "radiance"),
    ("normal", "normal (camera frame)"),
    ("depth", "depth"),
    ("base_color", "base color"),
    ("roughness", "roughness"),
)


def _view_table(i: int, stages: list, truth: TruthViews | None) -> str:
    from evcap.images import fit_gain

    known = truth.maps() if truth is not None else {}
    rows = []
    all_depths = [v["depth"][i] for _, _, v in stages if "depth" in v and len(v["depth"]) > i]
    if truth is not None and truth.depth is not None and len(truth) > i:
        all_depths.append(truth.depth[i])
    lo, hi = depth_range(*all_depths)
    columns = [k for k, _ in MAP_COLUMNS if any(k in v for _, _, v in stages) or k in known]
    for label, _, views in stages:
        images = {}
        for key in columns:
            if key not in views or len(views[key]) <= i:
                continue
            value = views[key][i]
            if key == "radiance" and truth is not None and truth.radiance is not None:
                pred, gt = views["radiance"], truth.radiance
                if pred.shape == gt.shape and np.isfinite(pred).all():
                    # fitted where object_psnr_gain is, on the object, when the truth says where
                    surface = truth.object_mask()
                    if surface is not None and surface.shape == pred.shape[:-1] and surface.any():
                        pred, gt = pred[surface], gt[surface]
                    value = value * fit_gain(pred, gt)
            images[key] = _map_image(key, value, lo, hi)
        rows.append((label, images))
    if truth is not None and len(truth) > i:
        images = {key: _map_image(key, known[key][i], lo, hi) for key in columns if key in known}
        rows.append(("truth", images))
    names = dict(MAP_COLUMNS)
    head = "".join(f"<th>{escape(names[k])}</th>" for k in columns)
    body = ""
    for label, images in rows:
        cells = "".join(
            f'<td><img src="{images[k]}" width="{VIEW_PX}" alt="{escape(label)} {k}"></td>'
            if k in images
            else "<td>&mdash;</td>"
            for k in columns
        )
        body += f"<tr><th>{escape(label)}</th>{cells}</tr>"
    bar = (
        f"<p>depth: {_color_bar(lo, hi, 'scene units')}; dark: no surface; magenta: not a "
        "number</p>"
    )
    return f"<h3>view {i}</h3><table class='views'><tr><th></th>{head}</tr>{body}</table>{bar}"


def _map_image(key: str, value: np.ndarray, lo: float, hi: float) -> str:
    if key == "normal":
        return png_data_uri(normal_image(value))
    if key == "depth":
        return png_data_uri(depth_image(value, lo, hi))
    if key == "roughness":
        return png_data_uri(gray_image(value))
    return png_data_uri(srgb8(value))


# -- relit views and the light ------------------------------------------------------------


def _relit_section(folder: ReconstructionFolder) -> str:
    parts = []
    if folder.environment.exists():
        parts.append(
            _figure(
                file_data_uri(folder.environment),
                "the light stage II learnt (latitude-longitude, z up)",
                360,
            )
        )
    views = folder.relit_views()
    if folder.relit_environment.exists():
        parts.append(
            _figure(file_data_uri(folder.relit_environment), "the new light (--relight)", 360)
        )
    if not parts:
        return _missing("No environment map and no relit views (stage II did not run).")
    html = "<div>" + "".join(parts) + "</div>"
    if not views:
        return html + _missing(
            "No relit views: the reconstruction was not given a new light (--relight ENV)."
        )
    figures = [_figure(file_data_uri(p), escape(p.stem), VIEW_PX + 60) for p in views]
    return html + "<p>The views relit under the new light:</p><div>" + "".join(figures) + "</div>"


# -- metrics ------------------------------------------------------------------------------


def _metrics_section(result: ReconstructionResult) -> str:
    rows = []
    for key, value in result.figures.measured().items():
        name, unit, group = Figures.describe(key)
        if key == "normal_mae_deg" and result.figures.radiance_normal_mae_deg is None:
            group = STAGE_I  # stage I only: its normals are the last
        rows.append((group, name, f'<td class="num">{escape(_number(value))}</td>', unit))
    for key, (name, unit, group) in RUN_FIELDS.items():
        value = getattr(result, key)
        if value is None:
            continue
        if isinstance(value, dict):
            text = ", ".join(f"{k}: {'on' if v else 'off'}" for k, v in value.items())
            cell = f"<td>{escape(text)}</td>"
        elif isinstance(value, int | float) and not isinstance(value, bool):
            cell = f'<td class="num">{escape(_number(value))}</td>'
        else:
            cell = f"<td>{escape(_number(value))}</td>"
        rows.append((group, name, cell, unit))
    if not rows:
        return _missing("metrics.json holds no figures.")
    body = ""
    for group in (STAGE_I, STAGE_II, RUN):
        lines = [
            f"<tr><td>{escape(name)}</td>{cell}<td>{escape(unit)}</td></tr>"
            for g, name, cell, unit in rows
            if g == group
        ]
        if lines:
            body += f'<tr><th class="group" colspan="3">{escape(group)}</th></tr>' + "".join(lines)
    note = (
        "<p>PSNR and SSIM compare the sRGB images with the truth, raw first; after one gain: "
        "one gain per color channel, fitted once by least squares (linear radiance) over the "
        "scored pixels of all held-out views; relit views keep the gain of the un-relit fit. "
        "The affine fit per view is a diagnostic only.</p>"
    )
    return note + f"<table><tr><th>metric</th><th>value</th><th>unit</th></tr>{body}</table>"


# -- accuracy versus time -----------------------------------------------------------------


def _progress_section(result: ReconstructionResult) -> str:
    plots, notes = [], []
    logs = result.training_log
    if logs.get("radiance"):
        log = logs["radiance"]
        plots.append(
            line_plot(
                [
                    Series(key, _column(log, "seconds"), _column(log, key), color)
                    for key, color in zip(("loss", "event", "anchor"), COLORS, strict=False)
                    if key in log[0]
                ],
                title="stage I: training loss",
                x_label="training time (s)",
                y_label="loss",
                log_y=True,
            )
        )
    else:
        notes.append(_missing("No stage-I training log in metrics.json."))
    if logs.get("material"):
        log = logs["material"]
        plots.append(
            line_plot(
                [
                    Series(key, _column(log, "seconds"), _column(log, key), color)
                    for key, color in zip(("loss", "event", "distill", "tv"), COLORS, strict=False)
                    if key in log[0]
                ],
                title="stage II: training loss",
                x_label="training time (s), edge maps included",
                y_label="loss",
                log_y=True,
            )
        )
    history = result.history
    if history and all(isinstance(h, dict) for h in history):
        seconds = np.array([_float(h.get("seconds")) for h in history])
        series = [
            Series(label, seconds, np.array([_float(h.get(key)) for h in history]), color, dashed)
            for key, label, color, dashed in (
                ("object_psnr_gain", "object, after one gain", COLORS[0], False),
                ("object_psnr_constant", "object: a constant color", COLORS[0], True),
                ("render_psnr_gain", "whole image, after one gain", COLORS[1], False),
            )
            if any(key in h for h in history)
        ]
        if series:
            views = history[-1].get("views")
            some = f"its first {views}" if isinstance(views, int) else "some of its"
            notes.append(
                f"<p>Along the way stage I is scored on {some} held-out views "
                "only, with the poses as they came in; the metrics above are over every "
                "held-out view, with the poses as refined (where they were): the curve's last "
                "point and the table need not agree.</p>"
            )
            plots.append(
                line_plot(
                    series,
                    title="stage I: PSNR on held-out views",
                    x_label="training time (s)",
                    y_label="PSNR (dB)",
                )
            )
        else:
            notes.append(_missing("metrics.json's history holds no PSNR."))
    else:
        notes.append(
            _missing(
                "No accuracy history in metrics.json (a reconstruction without held-out "
                "truth, or made before it was recorded)."
            )
        )
    return "".join(notes) + '<div class="plots">' + "".join(plots) + "</div>"


def _float(value: object) -> float:
    try:
        return float(value)  # type: ignore[arg-type]
    except (TypeError, ValueError):
        return math.nan


def _column(log: list[dict], key: str) -> np.ndarray:
    return np.array([_float(x.get(key)) for x in log])
