"""The reconstruction on a CUDA GPU: both stages of one session with each rasterizer backend
(gsplat's CUDA kernels, the torch reference on the GPU) beside the compiled CPU backend on the
same machine, each from scratch with the same preset and seed: the wall time of each stage and
the figures against the session's truth, so that the CUDA path is shown to work and to score
as the CPU one does.

    python bench/gpu.py SESSION.h5 [--preset tiny] [--backends gsplat torch cpu]
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import torch
from _common import flag_settings, report

from evcap.recon.options import Feedback, ReconstructOptions
from evcap.recon.reconstruct import reconstruct

FIGURES = (
    "object_psnr",
    "object_psnr_gain",
    "object_psnr_constant",
    "radiance_normal_mae_deg",
    "normal_mae_deg",
    "depth_rel_err",
    "base_color_psnr",
    "base_color_psnr_gain",
    "pbr_render_psnr",
    "pbr_render_psnr_gain",
)

STARTED = time.perf_counter()


def progress(step: int, total: int, text: str) -> None:
    if step % 100 == 0 or step == total:
        elapsed = time.perf_counter() - STARTED
        print(f"  {elapsed:6.0f} s: step {step} of {total}: {text}", flush=True)


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("session", type=Path)
    parser.add_argument("--preset", default="tiny")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--backends", nargs="+", default=["gsplat", "torch", "cpu"])
    parser.add_argument("--iterations", type=int, help="stage I's steps (default: the preset's)")
    parser.add_argument("--material-iterations", type=int, help="stage II's (the preset's)")
    args = parser.parse_args(argv)
    cuda = torch.cuda.is_available()
    if not cuda and args.backends != ["cpu"]:
        raise SystemExit("no CUDA GPU visible to PyTorch here: this benchmark is for one")
    gpu = torch.cuda.get_device_name() if cuda else None
    figures: dict = {"gpu": gpu, "preset": args.preset}
    for backend in args.backends:
        device = "cpu" if backend == "cpu" else "cuda"
        with tempfile.TemporaryDirectory() as out:
            seconds = {}
            for stage in ("radiance", "material"):
                settings = flag_settings(
                    stage, iterations=args.iterations, material_iterations=args.material_iterations
                )
                options = ReconstructOptions(
                    preset=args.preset,
                    stage=stage,
                    device=device,
                    backend=backend,
                    seed=args.seed,
                    settings=settings,
                )
                start = time.perf_counter()
                result = reconstruct(args.session, out, options, Feedback(progress=progress))
                seconds[stage] = time.perf_counter() - start
            measured = result.figures.measured()
        figures[f"{backend}_stage_1_s"] = seconds["radiance"]
        figures[f"{backend}_stage_2_s"] = seconds["material"]
        for name in FIGURES:
            if name in measured:
                figures[f"{backend}_{name}"] = measured[name]
        print(
            f"{backend} done: stage I {seconds['radiance']:.0f} s, stage II "
            f"{seconds['material']:.0f} s",
            flush=True,
        )
    report(f"gpu_{args.preset}", figures)


if __name__ == "__main__":
    main()
