"""The bar a reconstruction must reach (evcap/recovered.py), with the figures the
reconstruction prints (recon/evaluate/views.metrics): the truth itself clears it; a disc facing
the camera, a blob and an empty scene do not, each for what a user would see wrong."""

import numpy as np
import pytest

from evcap.recon.evaluate.views import metrics
from evcap.records.truth import TruthViews
from evcap.recovered import Bar, shortfalls

SIZE, FOCAL, DISTANCE, RADIUS = 96, 90.0, 2.0, 0.45
BACKDROP = np.array([0.30, 0.28, 0.25], np.float32)


def _rays() -> np.ndarray:
    """[H, W, 3] unit rays of a pinhole camera at the origin looking along +z (OpenCV axes)."""
    v, u = np.mgrid[0:SIZE, 0:SIZE] + 0.5
    d = np.stack([(u - SIZE / 2) / FOCAL, (v - SIZE / 2) / FOCAL, np.ones_like(u)], -1)
    return d / np.linalg.norm(d, axis=-1, keepdims=True)


def _sphere(radius: float, centre: np.ndarray) -> dict[str, np.ndarray]:
    """A sphere's maps in one view: where its surface is, the camera z, the normal, a texture."""
    rays = _rays()
    b = rays @ centre
    disc = b**2 - (centre @ centre - radius**2)
    hit = disc > 0
    t = np.where(hit, b - np.sqrt(np.maximum(disc, 0)), 0)
    point = rays * t[..., None]
    normal = np.where(hit[..., None], (point - centre) / radius, 0)
    # stripes of latitude and longitude on the surface: the object's pixels have structure
    stripes = 0.5 + 0.4 * np.sin(9 * normal[..., 0]) * np.cos(7 * normal[..., 1])
    color = np.stack([stripes, 0.8 * stripes + 0.1, 0.5 * (1 - stripes) + 0.2], -1)
    radiance = np.where(hit[..., None], color, BACKDROP)
    return {"hit": hit, "depth": point[..., 2], "normal": normal, "radiance": radiance}


CENTRES = [np.array([0.0, 0.0, DISTANCE]), np.array([0.15, -0.1, DISTANCE + 0.3])]


@pytest.fixture(scope="module")
def truth() -> TruthViews:
    views = [_sphere(RADIUS, c) for c in CENTRES]
    return TruthViews(
        np.repeat(np.eye(4)[None], len(views), 0),
        radiance=np.stack([v["radiance"] for v in views]).astype(np.float32),
        depth=np.stack([v["depth"] for v in views]).astype(np.float32),
        normal=np.stack([v["normal"] for v in views]).astype(np.float32),
        mask=np.stack([v["hit"] for v in views]),
    )


def _figures(truth: TruthViews, views: list[dict[str, np.ndarray]]) -> dict:
    stacked = {k: np.stack([v[k] for v in views]).astype(np.float32) for k in views[0]}
    return metrics(stacked, truth)


def _render(maps: dict[str, np.ndarray], alpha: np.ndarray) -> dict[str, np.ndarray]:
    return {
        "radiance": maps["radiance"],
        "depth": np.where(alpha > 0, maps["depth"], 0),
        "normal": maps["normal"],
        "alpha": alpha.astype(np.float32),
    }


def test_the_truth_at_another_gain_clears_the_bar(truth):
    # the events leave each channel's gain free: a render at another gain is the object
    views = []
    for c in CENTRES:
        maps = _sphere(RADIUS, c)
        maps["radiance"] = maps["radiance"] * np.array([0.7, 1.2, 0.9])
        views.append(_render(maps, maps["hit"]))
    assert shortfalls(_figures(truth, views)) == []


def test_a_disc_facing_the_camera_misses_the_normals(truth):
    # the sphere's silhouette and colors, flat where it fits the depth best, facing the camera
    views = []
    for c in CENTRES:
        maps = _sphere(RADIUS, c)
        maps["depth"] = np.full_like(maps["depth"], c[2] - 2 * RADIUS / 3)
        maps["normal"] = np.where(maps["hit"][..., None], [0.0, 0.0, -1.0], 0)
        views.append(_render(maps, maps["hit"]))
    figures = _figures(truth, views)
    missed = shortfalls(figures)
    assert figures["silhouette_iou"] == 1.0 and figures["normal_mae_deg"] > 30
    assert missed[0].startswith("normals") and not any("IoU" in m for m in missed)


def test_a_blob_misses_the_silhouette(truth):
    # 1.4 times the sphere, one constant color: the demo's lump
    views = []
    for c in CENTRES:
        maps = _sphere(1.4 * RADIUS, c)
        maps["radiance"] = np.where(maps["hit"][..., None], [0.5, 0.5, 0.35], BACKDROP)
        views.append(_render(maps, maps["hit"]))
    figures = _figures(truth, views)
    missed = " / ".join(shortfalls(figures))
    assert figures["silhouette_iou"] < 0.6
    assert "silhouette IoU" in missed and "object over a constant color" in missed


def test_an_empty_scene_misses_every_figure_on_the_object(truth):
    empty = [
        {
            "radiance": np.broadcast_to(BACKDROP, (SIZE, SIZE, 3)),
            "depth": np.zeros((SIZE, SIZE)),
            "normal": np.zeros((SIZE, SIZE, 3)),
            "alpha": np.zeros((SIZE, SIZE)),
        }
        for _ in CENTRES
    ]
    figures = _figures(truth, empty)
    missed = [m.split(" ")[0] for m in shortfalls(figures)]
    assert figures["background_clear"] == 1.0  # the bar on the backdrop alone would pass it
    assert missed == ["silhouette", "normals", "depth", "object"]


def test_a_figure_not_measured_counts_as_missed():
    figures = {"silhouette_iou": 0.95, "normal_mae_deg": float("nan"), "depth_rel_err": 0.01}
    missed = shortfalls(figures, Bar(background_clear=0.0))
    assert [m.split(" ")[0] for m in missed] == ["normals", "object", "backdrop"]
    assert "not measured" in missed[1] and "nan" in missed[0]
