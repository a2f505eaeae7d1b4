"""Pose refinement's pieces: the corrections, their gauge, and the render's gradient to a pose."""

import shutil

import numpy as np
import pytest
import torch

from evcap.recon.options import Feedback, ReconstructOptions
from evcap.recon.radiance.pose_refinement import PoseCorrections, exp_so3
from evcap.recon.radiance.stage import RadianceField
from evcap.recon.reconstruct import reconstruct
from evcap.recon.scene.gaussians import Background, Gaussians
from evcap.recon.scene.optics import RenderGrid
from evcap.records import Poses, ReconstructionFolder
from evcap.rotations import exp_so3 as exp_so3_numpy
from evcap.session import Session
from evcap.sim.scene import load_scene
from evcap.sim.simulate import simulate
from evcap.sim.trajectory import look_at


def arc(n: int = 5) -> Poses:
    """Cameras on an arc about the origin, looking at it, 0.1 s apart."""
    angles = np.linspace(0, 0.6, n)
    eyes = np.stack([2 * np.sin(angles), -2 * np.cos(angles), 0.3 * angles], 1)
    T = np.tile(np.eye(4), (n, 1, 1))
    T[:, :3, :3] = [look_at(e, np.zeros(3)) for e in eyes]
    T[:, :3, 3] = eyes
    return Poses(np.arange(n) * 100_000, T)


def test_exp_so3_matches_the_numpy_one():
    for w in ([0, 0, 0], [1e-4, 0, -2e-4], [0.02, -0.05, 0.01], [0.3, 0.2, -0.4]):
        got = exp_so3(torch.tensor(w, dtype=torch.float64)).numpy()
        np.testing.assert_allclose(got, exp_so3_numpy(np.array(w, float)), atol=1e-8)


def test_zero_corrections_leave_the_track_as_it_was():
    track = arc()
    c = PoseCorrections(track, track.start, track.end, 50_000, extent=1.0)
    assert len(c) == 9
    refined = c.refined(track)
    np.testing.assert_allclose(refined.T_world_cam, track.at(refined.t), atol=1e-12)
    assert refined.source.startswith("evcap reconstruct: refined")
    assert refined.notes["refined_from"] == track.source


def test_the_gauge_fixes_the_first_keyframe_and_the_scale():
    track = arc()
    c = PoseCorrections(track, track.start, track.end, 100_000, extent=2.0)
    with torch.no_grad():
        c.rotation.normal_(0, 0.01)
        c.shift.normal_(0, 0.01)
        c.shift += 0.05 * (c.base - c.base[0]) / c.extent  # a pure stretch, to be removed
    c.fix_gauge()
    assert c.rotation[0].abs().max() == 0 and c.shift[0].abs().max() == 0
    d = (c.base - c.base[0]).numpy()
    refined = c.refined(track).T_world_cam[np.isin(c.refined(track).t, c.times)]
    moved = refined[:, :3, 3] - refined[0, :3, 3]
    scale = (moved * d).sum() / (d * d).sum()
    assert scale == pytest.approx(1.0, abs=1e-12)


def test_corrections_are_linear_between_keyframes_and_constant_beyond():
    track = arc()
    c = PoseCorrections(track, 100_000, 300_000, 100_000, extent=1.0)
    with torch.no_grad():
        c.rotation[:] = torch.tensor([[0.0, 0, 0], [0.02, 0, 0], [0.04, 0, 0]])
    w, _ = c.at(np.array([0, 150_000, 250_000, 400_000]))
    np.testing.assert_allclose(w[:, 0].detach().numpy(), [0.0, 0.01, 0.03, 0.04], atol=1e-12)


def field_and_grid() -> tuple[RadianceField, RenderGrid]:
    g = torch.Generator().manual_seed(0)
    points = torch.rand(300, 3, generator=g).numpy() - 0.5
    gaussians = Gaussians.random(points, 0, g, 0.08)
    with torch.no_grad():
        gaussians.sh_dc[:, 0] = torch.rand(300, 3, generator=g) * 2 - 1
        gaussians.opacity_logits[:] = 1.0
    field = RadianceField(gaussians, Background(8), backend="torch")
    K = torch.tensor([[40.0, 0, 24], [0, 40, 18], [0, 0, 1]])
    return field, RenderGrid(K, 48, 36, torch.zeros(1, 1, 0, 2))


def corrected_view() -> tuple[PoseCorrections, np.ndarray, np.ndarray]:
    """Random corrections of the arc, its pose at a time between two keyframes, that time."""
    track = arc()
    c = PoseCorrections(track, track.start, track.end, 100_000, extent=1.0)
    with torch.no_grad():
        c.rotation.normal_(0, 0.02, generator=torch.Generator().manual_seed(2))
        c.shift.normal_(0, 0.02, generator=torch.Generator().manual_seed(3))
    t = np.array([150_000])
    return c, track.at(t), t


def test_a_corrected_pose_renders_as_that_pose_and_gets_its_gradient():
    field, grid = field_and_grid()
    c, base, t = corrected_view()
    T = c.apply(base, t)[0]
    a = field.render(T, grid).color
    b = field.render(T.detach().numpy(), grid).color
    torch.testing.assert_close(a, b, atol=2e-5, rtol=0)


def test_the_corrections_get_the_same_gradient_from_either_cpu_backend():
    """The pose's gradient comes through the rasterizer's camera: the compiled backend's
    hand-written one equals the torch backend's autograd."""
    field, grid = field_and_grid()
    c, base, t = corrected_view()
    target = torch.rand(36, 48, 3, generator=torch.Generator().manual_seed(1))

    def grads() -> torch.Tensor:
        c.zero_grad()
        ((field.render(c.apply(base, t)[0], grid).color - target) ** 2).sum().backward()
        return torch.cat([c.rotation.grad[1:3].ravel(), c.shift.grad[1:3].ravel()])

    by_torch = grads()
    assert by_torch.abs().max() > 1
    assert c.rotation.grad[[0, 3, 4]].abs().max() == 0  # keyframes the view does not touch
    field.backend = "cpu"
    torch.testing.assert_close(grads(), by_torch, rtol=0.02, atol=0.02)


@pytest.fixture(scope="module")
def simulated(tiny_scene, tmp_path_factory):
    session = tmp_path_factory.mktemp("session") / "s.h5"
    simulate(load_scene(tiny_scene()), session)
    return session


def test_reconstruct_refines_estimated_poses_and_writes_them(simulated, tmp_path):
    """auto refines poses that `evcap poses` estimated: OUT/poses.h5 holds the refined path
    (its source says so); stage II alone then reads it; --write-poses (with stage I, which
    refines them) puts it in the session."""
    session = shutil.copy(simulated, tmp_path / "s.h5")
    with Session.open(session) as s:
        truth = Poses.read(s)
    truth.replace(source="evcap poses (filter frames, pycolmap)").write(session)
    out = tmp_path / "out"
    settings = {"stage1.iterations": 12, "stage1.poses.start": 0.0}
    options = ReconstructOptions(preset="tiny", stage="radiance", settings=settings)
    result = reconstruct(session, out, options)
    refined = Poses.read_file(ReconstructionFolder(out).poses)
    assert refined.source == "evcap reconstruct: refined (evcap poses (filter frames, pycolmap))"
    assert refined.start == truth.start and refined.end == truth.end
    assert 0 < refined.notes["refinement_max_deg"] < 5
    assert np.isfinite(result.figures.object_psnr_gain)
    options = ReconstructOptions(preset="tiny", stage="material", settings={"stage2.iterations": 2})
    material = reconstruct(session, out, options)
    assert material.material_iterations == 2
    with Session.open(session) as s:
        assert Poses.read(s).source == "evcap poses (filter frames, pycolmap)"  # OUT's alone
    # --write-poses goes with a run of stage I (with --stage material alone it is refused)
    written = tmp_path / "written"
    options = ReconstructOptions(
        preset="tiny", stage="radiance", settings=settings, write_poses=True
    )
    reconstruct(session, written, options)
    refined_again = Poses.read_file(ReconstructionFolder(written).poses)
    assert refined_again.source == refined.source
    with Session.open(session) as s:
        now = Poses.read(s)
    assert now.source == refined.source
    np.testing.assert_array_equal(now.T_world_cam, refined_again.T_world_cam)
    settings["stage1.poses.refine"] = "off"
    options = ReconstructOptions(preset="tiny", stage="radiance", settings=settings)
    off = reconstruct(session, tmp_path / "off", options)
    assert off.iterations == 12 and not (ReconstructionFolder(tmp_path / "off").poses).exists()


def test_an_interrupted_refinement_goes_on_as_if_it_had_not_stopped(simulated, tmp_path):
    session = simulated
    settings = {"stage1.iterations": 40, "stage1.poses.start": 0.1, "stage1.poses.refine": "on"}
    run = ReconstructOptions(preset="tiny", stage="radiance", settings=settings)
    whole = reconstruct(session, tmp_path / "whole", run)

    def ctrl_c_at_step_25(done: int, total: int, status: str = "") -> None:
        if done == 25:
            raise KeyboardInterrupt

    first = reconstruct(session, tmp_path / "cut", run, Feedback(progress=ctrl_c_at_step_25))
    assert first.interrupted and first.iterations == 25
    again = reconstruct(session, tmp_path / "cut", run)
    assert again.iterations == whole.iterations == 40
    expected = Poses.read_file(ReconstructionFolder(tmp_path / "whole").poses)
    got = Poses.read_file(ReconstructionFolder(tmp_path / "cut").poses)
    assert expected.notes["refinement_max_deg"] > 0
    np.testing.assert_allclose(got.T_world_cam, expected.T_world_cam, atol=1e-9)
    with Session.open(session) as s:
        assert Poses.read(s).source == "ground truth"  # the session's own, untouched
