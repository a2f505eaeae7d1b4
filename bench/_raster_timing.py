"""One view rendered and differentiated, timed (bench/rasterizer.py), in this process or in a
process of its own that runs another checkout's rasterizer (``BaselineRasterizer``), so that
the two take turns round by round in one run.

The other process imports evcap from the checkout it is given (bench/steps.py ``use_code``),
reads a view's Gaussians, camera and output weights once from a file, and then times as many
rounds as it is asked for, one a line on its standard input.
"""

from __future__ import annotations

import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import torch

BENCH = Path(__file__).resolve().parent


def _rasterizer():
    """(Camera, rasterize) of the evcap imported: recon/raster/ since the rasterizer had a
    package of its own, recon/rasterize.py before."""
    try:
        from evcap.recon.raster.rasterize import Camera, rasterize
    except ImportError:
        from evcap.recon.rasterize import Camera, rasterize
    return Camera, rasterize


def sync(device: str) -> None:
    if device == "cuda":
        torch.cuda.synchronize()


def time_once(backend, params, view, weights, device="cpu") -> tuple[float, float, float]:
    """(forward, forward+backward) seconds of one view, and its mean alpha. ``view``:
    (viewmat, K, width, height); ``weights`` [H, W, D + 5] weigh the outputs in the loss the
    backward pass starts from."""
    Camera, rasterize = _rasterizer()
    params = [p.detach().to(device).requires_grad_(True) for p in params]
    viewmat, K, width, height = view
    cam = Camera(viewmat.to(device), K.to(device), width, height)
    weights = weights.to(device)
    means, quats, log_scales, opacities, features = params
    sync(device)
    start = time.perf_counter()
    r = rasterize(means, quats, log_scales.exp(), opacities, features, cam, backend=backend)
    sync(device)
    mid = time.perf_counter()
    maps = torch.cat([r.color, r.depth[..., None], r.alpha[..., None], r.normal], -1)
    (maps * weights).sum().backward()
    sync(device)
    return mid - start, time.perf_counter() - start, float(r.alpha.detach().mean())


class BaselineRasterizer:
    """The compiled CPU rasterizer of the checkout at ``code``, timed in a process of its own."""

    def __init__(self, code: Path) -> None:
        self.code = code
        self._folder = tempfile.TemporaryDirectory()
        script = (
            "import sys\n"
            f"sys.path.insert(0, {str(BENCH)!r})\n"
            "from pathlib import Path\n"
            "from steps import use_code\n"
            f"use_code(Path({str(code)!r}))\n"
            "from _raster_timing import serve\n"
            "serve()\n"
        )
        self._process = subprocess.Popen(
            [sys.executable, "-c", script],
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            text=True,
        )

    def load(self, params, view, weights) -> None:
        """The view the next rounds time."""
        path = Path(self._folder.name) / "view.torch"  # read once by the other process
        torch.save({"params": params, "view": view, "weights": weights}, path)
        self._ask({"load": str(path)})

    def time_once(self, threads: int) -> tuple[float, float, float]:
        return tuple(self._ask({"threads": threads}))

    def _ask(self, request: dict):
        self._process.stdin.write(json.dumps(request) + "\n")
        self._process.stdin.flush()
        line = self._process.stdout.readline()
        if not line:
            raise RuntimeError(f"the rasterizer of {self.code} ended (its error is above)")
        return json.loads(line)

    def close(self) -> None:
        self._process.stdin.close()
        self._process.wait()
        self._folder.cleanup()

    def __enter__(self) -> BaselineRasterizer:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def serve() -> None:
    """The other process's loop (see the module's docstring)."""
    job = None
    for line in sys.stdin:
        request = json.loads(line)
        if "load" in request:
            job = torch.load(request["load"])
            reply = "loaded"
        else:
            torch.set_num_threads(request["threads"])
            reply = time_once("cpu", job["params"], job["view"], job["weights"])
        print(json.dumps(reply), flush=True)
