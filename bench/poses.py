"""Poses from the events against the truth: `evcap poses` on simulated sessions with a known
trajectory (an orbit, and a hand-held path), the estimate aligned to the truth by a similarity;
then the reconstruction (stage I, the demo's settings) of the single-object scene and of the
demo's capture on the true poses, on the estimated ones, and on those refined by the
reconstruction, whose errors against the truth are measured too. Prints the figures and writes
results/poses.json (results/poses_SCENES.json for other scenes than the default).

    python bench/poses.py [--scenes single_object charuco_board demo] [--frames filter]
                          [--no-gyro] [--seeds 0 1 2]
"""

from __future__ import annotations

import argparse
import shutil
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import RESULTS, report, scene_label, session_of  # noqa: E402

FIXTURES = Path(__file__).resolve().parents[1] / "app" / "demo_data"
RECONSTRUCTED = ("single_object", "demo")  # scenes whose held-out views are scored


def demo_session(work: Path) -> Path:
    """The demo's capture as `evcap demo` makes it (both bundled recordings replayed through
    the driver, the calibration recording calibrating the scene's), with the simulator's truth
    and, as /poses, its true path."""
    from evcap.app.demo import SCENE, demo_pipeline
    from evcap.sim.truth import copy_truth

    out = work / "demo"
    out.mkdir(parents=True)
    pipeline = demo_pipeline(out, fixtures=FIXTURES, say=lambda line: None)
    pipeline.run(pipeline.names()[:3])  # the two recordings, the calibration
    copy_truth(FIXTURES / SCENE / "truth.h5", pipeline.workspace.session, poses=True)
    return pipeline.workspace.session


def poses_against_truth(path: Path, work: Path, kind: str, gyro: bool) -> tuple[dict, Path]:
    """Estimate the poses of a copy of the session; errors after a similarity alignment.
    Returns the figures and the copy, whose /poses then holds the aligned estimate."""
    from evcap.poses.estimate import estimate_poses
    from evcap.records import Poses
    from evcap.session import Session
    from evcap.trajectory_alignment import apply_similarity, pose_errors

    copy = work / f"{path.stem}_{kind}.h5"
    shutil.copy(path, copy)
    with Session.open(path) as s:
        truth = Poses.read(s)  # a simulated session's /poses: the true path, densely sampled
    t0 = time.perf_counter()
    result = estimate_poses(copy, kind=kind, gyro=gyro)
    seconds = time.perf_counter() - t0
    estimate = result.record()
    inside = (estimate.t >= truth.start) & (estimate.t <= truth.end)
    T_true = truth.at(estimate.t[inside])
    T_est = estimate.T_world_cam[inside]
    errors = pose_errors(T_est, T_true)
    by_poses = pose_errors(T_est, T_true, by="poses")
    RESULTS.mkdir(parents=True, exist_ok=True)
    np.savez(
        RESULTS / f"poses_{path.stem}_{kind}.npz",
        t_us=estimate.t[inside],
        T_est=T_est,
        T_true=T_true,
    )
    # by orientations and centres, as the demo registers its poses and the reconstruction
    # brings the held-out views into a refined world: the centres of an arc leave it a tilt
    s_, R, t = by_poses["scale"], by_poses["R"], by_poses["t"]
    points = estimate.points_xyz
    estimate.replace(
        T_world_cam=apply_similarity(estimate.T_world_cam, s_, R, t),
        points_xyz=None if points is None else s_ * points @ R.T + t,
    ).write(copy)
    name = f"{path.stem}_{kind}" + ("" if gyro else "_no_gyro")
    figures = {
        f"{name}_orientations": result.turned,
        f"{name}_frames": result.frames,
        f"{name}_registered": result.registered,
        f"{name}_rate_hz": result.rate_hz,
        f"{name}_mean_reprojection_px": result.mean_reprojection_px,
        f"{name}_seconds": seconds,
    }
    figures.update({f"{name}_{k}": v for k, v in errors.items() if np.isscalar(v)})
    for k in ("rotation_median_deg", "rotation_rms_deg", "translation_median_pct"):
        figures[f"{name}_{k}_aligned_by_poses"] = by_poses[k]
    return figures, copy


def reconstruction_difference(
    true_session: Path, estimated: Path, work: Path, seeds: list[int]
) -> dict:
    """Stage I (the demo's: 1,000 steps at half scale) on the true poses, on the aligned
    estimated ones, and on those refined by stage I itself (`--refine-poses on`), once per
    seed: the held-out views' object figures, the whole image's, and the refined poses'
    errors against the truth (the first seed's keys unsuffixed, the others' with _seedN;
    the object figure's mean over the seeds as _mean)."""
    from evcap.recon.options import ReconstructOptions
    from evcap.recon.reconstruct import reconstruct
    from evcap.records import GroundTruth, Poses, ReconstructionFolder
    from evcap.session import Session
    from evcap.trajectory_alignment import pose_errors

    with Session.open(true_session) as s:
        truth = GroundTruth.read(s).poses()
    with Session.open(estimated) as s:
        given = Poses.read(s)
    out, names = {}, ("true", "estimated", "refined")
    for seed in seeds:
        tag = "" if seed == seeds[0] else f"_seed{seed}"
        runs = (("true", true_session, "off"), ("estimated", estimated, "off"))
        for name, session, refine in (*runs, ("refined", estimated, "on")):
            settings = {"stage1.poses.refine": refine}
            options = ReconstructOptions(
                preset="small", stage="radiance", seed=seed, settings=settings
            )
            t0 = time.perf_counter()
            f = reconstruct(session, work / f"recon_{name}{tag}", options).figures
            out[f"recon_{name}_poses_seconds{tag}"] = time.perf_counter() - t0
            for key in (
                "object_psnr",
                "object_psnr_gain",
                "object_psnr_constant",
                "normal_mae_deg",
                "render_psnr",
                "render_psnr_gain",
            ):
                out[f"recon_{name}_poses_{key}{tag}"] = getattr(f, key)
        for name in names[1:]:
            out[f"recon_object_psnr_gain_loss_db_{name}{tag}"] = (
                out[f"recon_true_poses_object_psnr_gain{tag}"]
                - out[f"recon_{name}_poses_object_psnr_gain{tag}"]
            )
        refined = Poses.read_file(ReconstructionFolder(work / f"recon_refined{tag}").poses)
        for name, poses in (("estimated", given), ("refined", refined)):
            if name == "estimated" and tag:
                continue  # the same poses for every seed
            inside = (poses.t >= truth.start) & (poses.t <= truth.end)
            T_true = truth.at(poses.t[inside])
            for by in ("centres", "poses"):
                e = pose_errors(poses.T_world_cam[inside], T_true, by=by)
                for k in ("rotation_median_deg", "translation_median_pct"):
                    out[f"{name}_{k}_aligned_by_{by}{tag}"] = e[k]
    for name in names:
        key = f"recon_{name}_poses_object_psnr_gain"
        runs = [out[key + ("" if s == seeds[0] else f"_seed{s}")] for s in seeds]
        out[f"{key}_mean"] = float(np.mean(runs))
    for name in names[1:]:
        out[f"recon_object_psnr_gain_loss_db_{name}_mean"] = (
            out["recon_true_poses_object_psnr_gain_mean"]
            - out[f"recon_{name}_poses_object_psnr_gain_mean"]
        )
    return out


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    default = ["single_object", "charuco_board"]
    ap.add_argument("--scenes", nargs="+", default=default)
    ap.add_argument("--frames", default="filter", choices=["filter", "e2vid", "firenet"])
    ap.add_argument("--no-gyro", action="store_true", help="structure from motion's orientations")
    ap.add_argument(
        "--seeds",
        nargs="+",
        type=int,
        default=[0],
        help="the reconstructions' seeds (one run each)",
    )
    args = ap.parse_args(argv)
    figures: dict = {"frames": args.frames, "gyro": not args.no_gyro}
    with tempfile.TemporaryDirectory() as tmp:
        work = Path(tmp)
        for scene in args.scenes:
            path = demo_session(work) if scene == "demo" else session_of(scene)
            part, copy = poses_against_truth(path, work, args.frames, not args.no_gyro)
            figures.update(part)
            if scene in RECONSTRUCTED:
                part = reconstruction_difference(path, copy, work / scene, args.seeds)
                figures.update({f"{scene}_{k}": v for k, v in part.items()})
    labels = "_".join(map(scene_label, args.scenes))
    name = "poses" + ("" if args.scenes == default else f"_{labels}")
    report(name + ("_no_gyro" if args.no_gyro else ""), figures)


if __name__ == "__main__":
    main()
