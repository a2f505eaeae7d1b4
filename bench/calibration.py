"""Calibration against the truth: `evcap calibrate` on the simulator's ChArUco scene (a real
DAVIS346 calibration as its camera; threshold spread, hot pixels and noise on), with and
without its APS frames, and on the real DAVIS346 recording (hot pixels, noise and the pixels'
footprint: it shows no board). Prints the figures and writes results/calibration.json.

    python bench/calibration.py [--scene charuco_board] [--board SPEC] [--real PATH.aedat4]
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import report, session_of  # noqa: E402

from evcap.calib.board import DEFAULT_BOARD, Board, parse_board  # noqa: E402

SAMPLE = (
    Path(__file__).resolve().parents[2] / "shared/data/davis346-sample/davis346_test_data.aedat4"
)


def against_truth(path: Path, frames: bool, board: Board = DEFAULT_BOARD) -> dict:
    """Calibrate the session (or a copy without its frames) and compare with its /gt."""
    from evcap.calib.calibrate import calibrate
    from evcap.records import GroundTruth
    from evcap.session import Session, SessionWriter

    with tempfile.TemporaryDirectory() as tmp:
        if not frames:
            with Session.open(path) as s:
                sensor, ev = s.sensor, s.events()
            blind = Path(tmp) / "blind.h5"
            with SessionWriter(blind, sensor) as w:
                w.append_events(ev)
            path_used = blind
        else:
            path_used = path
        t0 = time.perf_counter()
        cal = calibrate(path_used, board=board)
        seconds = time.perf_counter() - t0
    with Session.open(path) as s:
        truth = GroundTruth.read(s)
        effects = json.loads(s.attrs["effects"])
    K, on_t, off_t = truth.K, truth.threshold_on, truth.threshold_off
    hot_t = np.zeros(on_t.size, bool)
    hot_t[truth.hot_pixels] = True
    est = cal.record()
    hot = est.hot().ravel()
    tp = int((hot & hot_t).sum())
    ba = effects.get("background_activity", {}).get("rate_hz", 0.0)
    shot = effects.get("shot_noise", {}).get("rate_hz", 0.0)
    prefix = "aps" if frames else "events_only"
    out = {
        f"{prefix}_seconds": seconds,
        f"{prefix}_fx_err_pct": 100 * float(est.K[0, 0] / K[0, 0] - 1),
        f"{prefix}_fy_err_pct": 100 * float(est.K[1, 1] / K[1, 1] - 1),
        f"{prefix}_cx_err_pct": 100 * float(est.K[0, 2] / K[0, 2] - 1),
        f"{prefix}_cy_err_pct": 100 * float(est.K[1, 2] / K[1, 2] - 1),
        f"{prefix}_rms_reprojection_px": est.rms_reprojection_px,
        f"{prefix}_views_used": len(cal.intrinsics.per_view) if cal.intrinsics else 0,
        f"{prefix}_hot_precision": tp / max(int(hot.sum()), 1),
        f"{prefix}_hot_recall": tp / max(int(hot_t.sum()), 1),
        f"{prefix}_background_activity_hz": est.background_activity_hz,
        f"{prefix}_shot_noise_hz": est.shot_noise_hz,
        f"{prefix}_refractory_us": est.refractory_period_us,
        "true_background_activity_hz": ba,
        "true_shot_noise_hz": shot,
        "true_refractory_us": effects.get("refractory", {}).get("period_us", 0),
    }
    if cal.thresholds is not None:
        on, off = est.thresholds()
        good = est.threshold_confidence >= 0.5
        err = np.concatenate([(on - on_t)[good], (off - off_t)[good]])
        out[f"{prefix}_threshold_rmse_confident"] = float(np.sqrt(np.mean(err**2)))
        out[f"{prefix}_threshold_confident_share"] = float(good.mean())
        allerr = np.concatenate([(on - on_t).ravel(), (off - off_t).ravel()])
        out[f"{prefix}_threshold_rmse_all"] = float(np.sqrt(np.mean(allerr**2)))
    return out


def real_recording(aedat4: Path) -> dict:
    """Hot pixels and noise of the real DAVIS346 recording (no board in it), and its pixels'
    footprint from its frames' median (the camera is still)."""
    from evcap.calib.calibrate import calibrate
    from evcap.calib.footprint import footprint
    from evcap.importers.aedat4 import import_aedat4
    from evcap.session import Session

    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "real.h5"
        import_aedat4(aedat4, path)
        t0 = time.perf_counter()
        cal = calibrate(path, skip=frozenset({"intrinsics"}))
        seconds = time.perf_counter() - t0
        with Session.open(path) as s:
            fp = footprint(np.median(np.asarray(s.frames().data, np.float64), axis=0))
    est = cal.record()
    on, off = est.thresholds()
    return {
        "real_seconds": seconds,
        "real_hot_pixels": int(est.hot().sum()),
        "real_background_activity_hz": est.background_activity_hz,
        "real_shot_noise_hz": est.shot_noise_hz,
        "real_refractory_us": est.refractory_period_us,
        "real_threshold_confident_share": float((est.threshold_confidence >= 0.5).mean()),
        "real_thresholds_on_off_mean": [float(on.mean()), float(off.mean())],
        "real_footprint_px": fp.sigma_px,  # the sharpest tenth of its straight edges
        "real_footprint_median_px": fp.median_px,
        "real_footprint_edges": fp.edges,
    }


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--scene", default="charuco_board")
    ap.add_argument("--board", type=parse_board, default=DEFAULT_BOARD, help="the scene's board")
    ap.add_argument("--real", type=Path, default=SAMPLE)
    args = ap.parse_args(argv)
    from evcap.errors import CalibrationError

    path = session_of(args.scene)
    figures = {"scene": args.scene}
    figures.update(against_truth(path, frames=True, board=args.board))
    try:
        figures.update(against_truth(path, frames=False, board=args.board))
    except CalibrationError as e:
        figures["events_only_error"] = str(e)
    if args.real.exists():
        figures.update(real_recording(args.real))
    report("calibration", figures)


if __name__ == "__main__":
    main()
