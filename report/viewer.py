"""OUT/viewer.html: the reconstruction in 3D in a browser, one self-contained page (WebGL 2, no
library, no network): the textured mesh (base color, shaded, roughness or normals), the
Gaussians' centres and the camera path with its views' frusta. Drag to turn, shift-drag or
right-drag to move, the wheel to come closer; the view starts from the path's first camera."""

from __future__ import annotations

import base64
import io
import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from evcap.atomic_write import write_text_atomic
from evcap.images import srgb

FRUSTA = 12  # views along the path drawn as frusta
MAX_VIEWS = 8  # rendered views in the page's strip


@dataclass
class Scene3D:
    """What the page draws, in the world's frame (z up)."""

    vertices: np.ndarray | None  # [V, 3], None: no mesh
    faces: np.ndarray | None  # [F, 3]
    normals: np.ndarray | None  # [V, 3]
    uv: np.ndarray | None  # [V, 2], v down
    base_color: np.ndarray | None  # [S, S, 3] linear
    roughness: np.ndarray | None  # [S, S]
    points: np.ndarray  # [P, 3] the Gaussians' centres
    point_colors: np.ndarray  # [P, 3] linear
    path: np.ndarray  # [N, 4, 4] camera to world, along the path
    K: np.ndarray  # [3, 3] the sensor's
    size: tuple[int, int]  # the sensor's (width, height)
    note: str = ""  # what the page says about itself (where the mesh came from)
    views: list[Path] = field(default_factory=list)  # rendered views' PNGs, shown in a strip


def write_viewer(scene: Scene3D, path: Path, title: str) -> Path:
    """The page drawing ``scene``."""
    data: dict[str, object] = {
        "points": _b64(scene.points, np.float32),
        "pointColors": _b64(np.clip(srgb(scene.point_colors), 0, 1) * 255, np.uint8),
        "path": _b64(scene.path[:, :3, 3], np.float32),
        "frusta": _b64(_frusta(scene.path, scene.K, scene.size), np.float32),
        "axes": _b64(_axes(scene), np.float32),
        "note": scene.note,
        "views": [
            "data:image/png;base64," + base64.b64encode(p.read_bytes()).decode()
            for p in scene.views[:MAX_VIEWS]
        ],
    }
    if scene.vertices is not None:
        data["mesh"] = {
            "positions": _b64(scene.vertices, np.float32),
            "normals": _b64(scene.normals, np.float32),
            "uv": _b64(scene.uv, np.float32),
            "indices": _b64(scene.faces, np.uint32),
            "baseColor": _png(np.clip(srgb(scene.base_color), 0, 1) * 255),
            "roughness": _png(np.repeat(scene.roughness[..., None], 3, -1) * 255),
        }
    page = (Path(__file__).parent / "viewer_page.html").read_text()
    # "</" inside a script would end it (a path or a message in the note may hold one)
    script = json.dumps(data).replace("</", "<\\/")
    html = page.replace("__TITLE__", _escape(title)).replace("__DATA__", script)
    write_text_atomic(path, html)
    return path


def _b64(a: np.ndarray, dtype) -> str:
    return base64.b64encode(np.ascontiguousarray(a, dtype).tobytes()).decode()


def _png(rgb: np.ndarray) -> str:
    from PIL import Image

    buffer = io.BytesIO()
    Image.fromarray((rgb + 0.5).clip(0, 255).astype(np.uint8)).save(buffer, "PNG")
    return "data:image/png;base64," + base64.b64encode(buffer.getvalue()).decode()


def _escape(text: str) -> str:
    from html import escape

    return escape(text)


def _axes(scene: Scene3D) -> np.ndarray:
    """[6, 3] the world's x, y and z axes from its origin (their ends), as long as the path
    is wide: what `evcap export --bounds` is read against."""
    span = float(np.linalg.norm(np.ptp(scene.path[:, :3, 3], axis=0))) if len(scene.path) else 1
    return np.concatenate([np.zeros((3, 3)), np.eye(3) * (span or 1.0)], 1).reshape(6, 3)


def _frusta(path: np.ndarray, K: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    """[S * 16, 3] line segments' ends: a small pyramid for each of FRUSTA views."""
    if not len(path):
        return np.zeros((0, 3))
    centres = path[:, :3, 3]
    span = float(np.linalg.norm(centres.max(0) - centres.min(0))) or 1.0
    depth = 0.08 * span
    w, h = size
    corners = np.array([[0, 0], [w, 0], [w, h], [0, h]], float)
    rays = np.c_[(corners - K[:2, 2]) / np.diag(K)[:2], np.ones(4)] * depth
    lines = []
    for T in path[np.linspace(0, len(path) - 1, min(FRUSTA, len(path))).astype(int)]:
        c, ends = T[:3, 3], rays @ T[:3, :3].T + T[:3, 3]
        for k in range(4):
            lines += [c, ends[k], ends[k], ends[(k + 1) % 4]]
    return np.array(lines)
