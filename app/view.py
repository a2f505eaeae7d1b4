"""`evcap view`: OUT/viewer.html gathered from a reconstruction folder: its mesh (exported first
when missing or out of date), its Gaussians' centres and its camera path, drawn by
report/viewer.py."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import numpy as np
import torch

from evcap.errors import InputError
from evcap.recon.export import load_checkpoint
from evcap.recon.mesh.config import MeshConfig
from evcap.recon.mesh.export import export_mesh, read_glb
from evcap.recon.scene.optics import SensorOptics
from evcap.recon.scene.sh import C0
from evcap.records import Poses
from evcap.records.reconstruction_folder import ReconstructionFolder
from evcap.report.viewer import Scene3D, write_viewer
from evcap.session import Session

MAX_POINTS = 60_000  # Gaussians' centres drawn (the most opaque)


def write_folder_viewer(
    out: str | Path,
    session: str | Path | None = None,
    config: MeshConfig | None = None,
    say: Callable[[str], None] = print,
) -> Path:
    """OUT/viewer.html for the reconstruction folder ``out``: its mesh (OUT/mesh.glb, exported
    again when it is missing, older than the reconstruction, or ``config`` asks for another),
    its Gaussians and its camera path; returns the page's path."""
    folder = ReconstructionFolder(out)
    folder.check()
    session_path = Path(session) if session is not None else folder.session()
    asset, note = None, ""
    why = _export_again(folder, config)
    if why is None:
        say(f"showing {folder.mesh}, made earlier")
        asset, note = read_glb(folder.mesh), f"mesh: {folder.mesh.name}"
    else:
        say(f"{why}: exporting the mesh first")
        try:
            asset = export_mesh(folder.root, session_path, config, say)
            asset.write(folder.mesh)
            note = f"mesh: {asset.summary()}"
        except InputError as e:  # the Gaussians and the path are still worth seeing
            note = f"no mesh: {e}"
            say(note)
    if asset is not None:  # what --bounds is read against
        lo, hi = asset.vertices.min(0), asset.vertices.max(0)
        note += "; the mesh spans " + ", ".join(
            f"{a} {lo[k]:.3g} to {hi[k]:.3g}" for k, a in enumerate("xyz")
        )
    field, _ = load_checkpoint(folder.checkpoint("radiance"))
    g = field.gaussians
    with torch.no_grad():
        opacity = g.opacities.numpy()
        order = np.argsort(-opacity)[:MAX_POINTS]
        order = order[opacity[order] > 0.5]
        points = g.means.numpy()[order]
        colors = torch.nn.functional.softplus(C0 * g.sh_dc[order, 0]).clamp(0, 1).numpy()
    with Session.open(session_path) as s:
        optics = SensorOptics.from_session(s)
        track = Poses.read_file(folder.poses) if folder.poses.exists() else Poses.read(s)
    path = track.at(np.linspace(track.start, track.end, 200).astype(np.int64))
    scene = Scene3D(
        *(
            (
                asset.vertices,
                asset.faces,
                asset.normals,
                asset.uv,
                asset.base_color,
                asset.roughness,
            )
            if asset is not None
            else (None,) * 6
        ),
        points,
        colors,
        path,
        optics.K,
        (optics.width, optics.height),
        note,
        folder.shown_views(),
    )
    return write_viewer(scene, folder.viewer, folder.root.name)


def _export_again(folder: ReconstructionFolder, config: MeshConfig | None) -> str | None:
    """Why OUT/mesh.glb is to be made again; None when it holds this reconstruction as asked."""
    if not folder.mesh.exists():
        return f"no {folder.mesh.name} yet"
    if config is not None and config != MeshConfig():
        return "mesh options given"
    made = folder.mesh.stat().st_mtime
    stages = [folder.checkpoint(stage) for stage in ("radiance", "material")]
    if any(p.exists() and p.stat().st_mtime > made for p in stages):
        return f"{folder.mesh.name} is older than the reconstruction"
    return None
