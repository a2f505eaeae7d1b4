"""The truth file of a simulated recording (evcap.sim.truth): written small, and copied into a
session without ground truth (as one recorded from a fixture) where the evaluation finds it."""

import h5py
import numpy as np
import pytest

from evcap.errors import InputError, SessionFormatError
from evcap.events import Events
from evcap.records import GroundTruth
from evcap.session import SensorInfo, Session, SessionWriter
from evcap.sim.scene import load_scene
from evcap.sim.simulate import simulate
from evcap.sim.truth import copy_truth, write_truth

# the truth file's images (float16): the held-out views' and the second light
GT_IMAGES = ("test_radiance", "test_depth", "test_normal", "test_base_color", "test_roughness")
GT_OPTIONAL = ("relight_environment", "test_relit_radiance")


@pytest.fixture(scope="module")
def simulated(tiny_scene, tmp_path_factory):
    """A tiny simulated session with 2 held-out views, and its truth file."""
    folder = tmp_path_factory.mktemp("truth")
    session = folder / "sim.h5"
    simulate(load_scene(tiny_scene()), session)
    write_truth(session, folder / "truth.h5")
    return session, folder / "truth.h5"


def held_out_views(s):
    """The held-out poses [N, 4, 4] and whatever truth a session has for them (none without
    ground truth), as the evaluation reads them."""
    if not GroundTruth.present(s):
        return np.zeros((0, 4, 4)), {}
    views = GroundTruth.read(s).held_out_views()
    return views.T_world_cam, views.maps()


def recorded(path, width=48, height=36):
    """A session as the driver would record it: events, no /gt."""
    sensor = SensorInfo("Color-DAVIS346", width, height, "RGBG", "00000346")
    with SessionWriter(path, sensor) as w:
        w.append_events(Events([1, 2], [3, 4], [10, 20], [1, 0], width, height, "RGBG"))
    return path


def test_truth_file_is_small_and_holds_what_the_evaluation_needs(simulated):
    session, truth = simulated
    with h5py.File(truth) as f, h5py.File(session) as s:
        assert set(f["gt"]) == {
            "t",
            "T_world_cam",
            "K",
            "test_T_world_cam",
            *GT_IMAGES,
            *GT_OPTIONAL,
        }
        for key in GT_IMAGES + GT_OPTIONAL:
            d = f["gt"][key]
            assert d.dtype == np.float16 and d.compression == "gzip" and d.shuffle
        np.testing.assert_array_equal(f["poses/T_world_cam"][:], s["poses/T_world_cam"][:])
        np.testing.assert_array_equal(f["gt/test_T_world_cam"][:], s["gt/test_T_world_cam"][:])
        assert f["gt"].attrs["scene"] == s["gt"].attrs["scene"]


def test_held_out_views_under_a_second_light(simulated):
    session, _ = simulated
    with Session.open(session) as s:
        g = s.group("gt")
        lit, relit = g["test_radiance"][:], g["test_relit_radiance"][:]
        surface, env = g["test_depth"][:] > 0, g["relight_environment"][:]
    assert relit.shape == lit.shape and env.shape == (128, 256, 3)
    # the second light is a warm sky over a dark ground: the zenith red, the surface warmer
    assert env[0, :, 0].mean() > env[0, :, 2].mean() and env[-1].mean() < env[0].mean()
    warmth = lambda img: img[surface][:, 0].mean() / img[surface][:, 2].mean()  # noqa: E731
    assert warmth(relit) > 1.5 * warmth(lit)


def test_copy_truth_gives_a_recorded_session_its_held_out_views(simulated, tmp_path):
    session, truth = simulated
    target = recorded(tmp_path / "rec.h5")
    with Session.open(target) as s:
        assert held_out_views(s)[0].shape == (0, 4, 4)
    copy_truth(truth, target)
    with Session.open(session) as s:
        want_poses, want = held_out_views(s)
        want_t, want_T = s.group("gt")["t"][:], s.group("gt")["T_world_cam"][:]
    with Session.open(target) as s:
        poses, got = held_out_views(s)
        g = s.group("gt")
        np.testing.assert_array_equal(g["t"][:], want_t)
        np.testing.assert_array_equal(g["T_world_cam"][:], want_T)
        stored = {key: g[f"test_{key}"].dtype for key in got}
        assert "poses" not in s.groups  # the estimated poses' place is left alone
    np.testing.assert_array_equal(poses, want_poses)
    assert len(poses) == 2
    assert {"radiance", "depth", "normal", "base_color", "roughness"} <= set(got)
    for key, value in got.items():
        assert value.dtype == stored[key] == np.float32
        np.testing.assert_allclose(value, want[key], rtol=1e-3, atol=1e-4)


def test_copy_truth_refuses_what_does_not_fit(simulated, tmp_path):
    _, truth = simulated
    target = recorded(tmp_path / "rec.h5")
    copy_truth(truth, target, poses=True)
    with Session.open(target) as s:
        assert s.group("poses").attrs["source"] == "ground truth"
    with pytest.raises(SessionFormatError, match="already has /gt"):
        copy_truth(truth, target)
    copy_truth(truth, target, replace=True)
    with pytest.raises(InputError, match="48 x 36 camera"):
        copy_truth(truth, recorded(tmp_path / "big.h5", 64, 48))
    with pytest.raises(SessionFormatError, match="not a truth file"):
        copy_truth(recorded(tmp_path / "plain.h5"), target, replace=True)
