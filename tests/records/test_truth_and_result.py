"""/gt and OUT/metrics.json: their records read back what they wrote."""

import json
import math

import h5py
import numpy as np
import pytest

from evcap.errors import InputError
from evcap.records import (
    Figures,
    GroundTruth,
    ReconstructionFolder,
    ReconstructionResult,
    TruthViews,
)

H, W = 6, 8


def truth(n_path: int = 3, n_test: int = 2) -> GroundTruth:
    rng = np.random.default_rng(0)

    def views(n: int, relit: bool) -> TruthViews:
        return TruthViews(
            np.tile(np.eye(4), (n, 1, 1)),
            radiance=rng.uniform(0, 2, (n, H, W, 3)).astype(np.float32),
            depth=rng.uniform(0, 3, (n, H, W)).astype(np.float32),
            normal=rng.normal(size=(n, H, W, 3)).astype(np.float32),
            relit_radiance=rng.uniform(0, 1, (n, H, W, 3)).astype(np.float32) if relit else None,
        )

    return GroundTruth(
        source="evcap simulate",
        t=np.arange(n_path) * 1000,
        path=views(n_path, False),
        held_out=views(n_test, True),
        K=np.diag([10.0, 10.0, 1.0]),
        threshold_on=np.full((H, W), 0.2, np.float32),
        threshold_off=np.full((H, W), 0.25, np.float32),
        relight_environment=np.ones((4, 8, 3), np.float32),
        renderer_version=3,
        hot_pixels=np.array([3, 5]),
        notes={"scene": "cube", "seed": 7},
    )


@pytest.mark.parametrize("half", [False, True])
def test_truth_round_trip(tmp_path, half):
    gt = truth()
    path = tmp_path / "t.h5"
    h5py.File(path, "w").close()
    gt.write(path, half=half)
    with h5py.File(path, "r") as f:
        back = GroundTruth.read(f)
        along = GroundTruth.read(f, along_path=True)
    assert back.path.radiance is None and along.path.radiance is not None
    tol = 2e-3 if half else 0
    np.testing.assert_allclose(back.held_out.radiance, gt.held_out.radiance, rtol=tol)
    np.testing.assert_allclose(back.held_out.relit_radiance, gt.held_out.relit_radiance, rtol=tol)
    np.testing.assert_allclose(along.path.depth, gt.path.depth, rtol=tol)
    assert back.renderer_version == 3 and back.notes == {"scene": "cube", "seed": 7}
    assert np.array_equal(back.hot_pixels, [3, 5]) and np.array_equal(back.t, gt.t)
    assert back.held_out[:1].radiance.shape == (1, H, W, 3)
    assert np.array_equal(back.held_out.object_mask(), gt.held_out.depth > 0)
    poses = back.poses()
    assert poses.source == "ground truth" and np.allclose(poses.at(500), np.eye(4))


def test_truth_views_of_unequal_lengths_are_refused():
    with pytest.raises(InputError, match="1 depth images for 2 views"):
        TruthViews(np.tile(np.eye(4), (2, 1, 1)), depth=np.zeros((1, H, W)))


def test_no_truth_is_said_so(tmp_path):
    path = tmp_path / "t.h5"
    h5py.File(path, "w").close()
    with h5py.File(path, "r") as f:
        assert not GroundTruth.present(f)
        with pytest.raises(InputError, match="no ground truth"):
            GroundTruth.read(f)


def test_result_round_trip(tmp_path):
    result = ReconstructionResult(
        views="held-out test views",
        figures=Figures(object_psnr_gain=21.5, normal_mae_deg=float("nan")),
        iterations=100,
        seconds=12.5,
        effects={"visibility": True},
        training_log={"radiance": [{"step": 0, "loss": 1.0}]},
    )
    ReconstructionFolder(tmp_path).write_result(result)
    data = json.loads((tmp_path / "metrics.json").read_text())
    assert data["object_psnr_gain"] == 21.5 and data["normal_mae_deg"] is None
    back = ReconstructionFolder(tmp_path).read_result()
    assert back.figures.object_psnr_gain == 21.5 and math.isnan(back.figures.normal_mae_deg)
    assert back.figures.depth_rel_err is None
    assert back.iterations == 100 and back.training_log == result.training_log
    assert Figures.describe("object_psnr_gain") == (
        "object PSNR, after one gain",
        "dB",
        "stage I (radiance)",
    )


@pytest.mark.parametrize(
    "text, message", [("{", "not readable JSON"), ("[1]", "not hold a table"), (None, "not there")]
)
def test_a_damaged_result_is_named(tmp_path, text, message):
    if text is not None:
        (tmp_path / "metrics.json").write_text(text)
    with pytest.raises(InputError, match=message):
        ReconstructionFolder(tmp_path).read_result()
