"""The README's figure of the demo: each held-out view's truth beside what the demo recovered
(radiance after the one gain per channel object_psnr_gain uses, normals, depth; stage II's base
color and the view relit under the truth's second light, as written), drawn as the report
draws them.

    .venv/bin/python scripts/demo_figure.py evcap-demo docs/figures/demo.png
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
from PIL import Image

from evcap.recon.evaluate.views import shown_gain
from evcap.records import GroundTruth
from evcap.records.reconstruction_folder import ReconstructionFolder
from evcap.report.images import depth_image, depth_range, normal_image, srgb8
from evcap.session import Session


def main(demo: Path, out: Path) -> None:
    folder = ReconstructionFolder(demo / "reconstruction")
    with Session.open(demo / "scene.h5") as s:
        truth = GroundTruth.read(s).held_out_views()
    stage_one = dict(np.load(folder.views_values("radiance", "test")))
    stage_two = dict(np.load(folder.views_values("material", "test")))
    gain = shown_gain(stage_one["radiance"], truth)
    rows = []
    for i in range(len(truth)):
        lo, hi = depth_range(truth.depth[i], stage_one["depth"][i])
        rows.append(
            [
                srgb8(truth.radiance[i]),
                srgb8(stage_one["radiance"][i] * gain),
                normal_image(truth.normal[i]),
                normal_image(stage_one["normal"][i]),
                depth_image(truth.depth[i], lo, hi),
                depth_image(stage_one["depth"][i], lo, hi),
                srgb8(truth.base_color[i]),
                srgb8(stage_two["base_color"][i]),
                srgb8(truth.relit_radiance[i]),
                np.asarray(Image.open(folder.view_image("relit", "test", i, "radiance")))[..., :3],
            ]
        )
    grid = np.concatenate([np.concatenate(r, 1) for r in rows], 0)
    Image.fromarray(grid).save(out)


if __name__ == "__main__":
    main(Path(sys.argv[1]), Path(sys.argv[2]))
