"""Structure from motion on rendered frames: poses against the truth, and clear failures."""

import time

import numpy as np
import pytest

from evcap.errors import InputError, PosesError
from evcap.poses.model_join import Piece
from evcap.poses.sfm import (
    GOOD_REPROJECTION_PX,
    MAX_KEYFRAMES,
    OVERLAP,
    _rank,
    colmap_camera,
    loop_pairs,
    reprojection_px,
    run_sfm,
)
from evcap.sim.render import Renderer
from evcap.sim.scene import load_scene
from evcap.sim.trajectory import Trajectory
from evcap.trajectory_alignment import pose_errors

pytest.importorskip("pycolmap")

TEXTURED = """[[objects]]
type = "plane"
size = [4.0, 4.0]
material = "floor"

[[objects]]
type = "box"
center = [-0.3, 0.2, 0.3]
size = [0.6, 0.6, 0.6]
rotation_deg = [0.0, 0.0, 20.0]
material = "crate"

[[objects]]
type = "box"
center = [0.5, -0.3, 0.2]
size = [0.4, 0.5, 0.4]
material = "crate"

[materials.floor]
texture = "{floor}"
roughness = 0.9

[materials.crate]
texture = "{crate}"
roughness = 0.9
"""

# a rising and falling quarter orbit: camera centres spread in 3D, so that aligning them to
# the truth fixes the rotation well
ORBIT = """kind = "orbit"
radius = 2.0
height = 1.6
height_swing = 0.5
degrees = 90.0
duration_s = 1.0
look_at = [0.0, 0.0, 0.2]"""

GRAY = """[[objects]]
type = "plane"
size = [40.0, 40.0]
material = "gray"

[materials.gray]
base_color = [0.5, 0.5, 0.5]
roughness = 1.0
"""


def blobs(path, seed: int, count: int, radii: tuple[int, int]) -> None:
    """A texture of overlapping coloured discs, slightly blurred: corners and blobs for SIFT,
    and no detail finer than a pixel of the render (which is not antialiased)."""
    import cv2

    rng = np.random.default_rng(seed)
    img = np.full((512, 512, 3), 128, np.uint8)
    for _ in range(count):
        centre = tuple(int(v) for v in rng.integers(0, 512, 2))
        colour = tuple(int(v) for v in rng.integers(20, 236, 3))
        cv2.circle(img, centre, int(rng.integers(*radii)), colour, -1, lineType=cv2.LINE_AA)
    cv2.imwrite(str(path), cv2.GaussianBlur(img, (0, 0), 1.5))


def render(scene_path, n: int) -> tuple[list[np.ndarray], np.ndarray, np.ndarray, np.ndarray]:
    """``n`` frames over the path, tone-mapped to uint8 RGB; their times, poses and K."""
    scene = load_scene(scene_path)
    renderer = Renderer(scene)
    path = Trajectory(scene.trajectory)
    times = np.linspace(0.0, path.duration_s, n)
    images, poses = [], []
    for t in times:
        T = path.pose(t)
        radiance = renderer.render_full(T)["radiance"]
        images.append((np.clip(radiance, 0, 1) ** (1 / 2.2) * 255).astype(np.uint8))
        poses.append(T)
    return images, (times * 1e6).round().astype(np.int64), np.stack(poses), renderer.camera.K


@pytest.fixture(scope="module")
def textured(tiny_scene, tmp_path_factory):
    folder = tmp_path_factory.mktemp("textures")
    blobs(folder / "floor.png", 0, 1500, (3, 10))
    blobs(folder / "crate.png", 1, 150, (8, 30))
    objects = TEXTURED.format(floor=folder / "floor.png", crate=folder / "crate.png")
    path = tiny_scene(width=200, height=150, fx=160.0, trajectory=ORBIT, objects=objects)
    return render(path, 30)


def test_poses_of_a_rendered_orbit_match_the_truth(textured, tmp_path):
    images, times, T_true, K = textured
    seen = []
    t0 = time.perf_counter()
    result = run_sfm(
        images, times, K, np.zeros(0), workdir=tmp_path, progress=lambda *a: seen.append(a)
    )
    seconds = time.perf_counter() - t0
    assert result.total == 30 and result.registered == 30
    assert result.registered == len(result.t_us) == len(result.T_world_cam)
    assert len(result.unregistered_times) == 30 - result.registered
    assert set(result.t_us) | set(result.unregistered_times) == set(times)
    assert np.all(np.diff(result.t_us) > 0)
    assert result.T_world_cam.shape == (result.registered, 4, 4)
    R = result.T_world_cam[:, :3, :3]
    np.testing.assert_allclose(
        R @ np.swapaxes(R, 1, 2), np.broadcast_to(np.eye(3), R.shape), atol=1e-9
    )
    np.testing.assert_allclose(result.T_world_cam[:, 3], [[0, 0, 0, 1.0]] * result.registered)
    assert result.model_count == 1 and result.points > 300
    assert result.mean_reprojection_px < 0.5
    assert result.seconds <= seconds
    errors = pose_errors(result.T_world_cam, T_true[np.searchsorted(times, result.t_us)])
    # the bar is 0.5 deg and 0.5 % of the extent; measured: 0.14 to 0.17 deg and 0.09 %
    assert errors["rotation_median_deg"] < 0.3
    assert errors["translation_median_pct"] < 0.25
    assert {stage for _, _, stage in seen} >= {"features", "matching", "mapping"}
    assert (tmp_path / "database.db").exists() and (tmp_path / "images" / "000029.png").exists()


def test_the_same_frames_give_the_same_poses(textured):
    images, times, _, K = textured
    first, again = (run_sfm(images[::2], times[::2], K, np.zeros(0)) for _ in range(2))
    np.testing.assert_array_equal(first.t_us, again.t_us)
    np.testing.assert_array_equal(first.T_world_cam, again.T_world_cam)
    with pytest.raises(InputError, match="threads"):
        run_sfm(images, times, K, np.zeros(0), threads=-1)


def test_intrinsics_stay_fixed_and_strays_are_left_out(textured, tmp_path):
    import pycolmap

    images, times, _, K = textured
    images, times = images[::3], times[::3]
    # two frames of noise, which match nothing: left out, and their times reported
    rng = np.random.default_rng(1)
    noise = [(rng.random(images[0].shape) * 255).astype(np.uint8) for _ in range(2)]
    images = images[:4] + noise[:1] + images[4:8] + noise[1:] + images[8:]
    times = np.sort(np.concatenate([times, times[[3, 7]] + 1]))
    (tmp_path / "sparse" / "7").mkdir(parents=True)  # an earlier run's model: replaced
    result = run_sfm(images, times, K, np.zeros(0), workdir=tmp_path)
    assert result.total == 12 and result.registered == 10
    np.testing.assert_array_equal(result.unregistered_times, times[[4, 9]])
    assert [p.name for p in (tmp_path / "sparse").iterdir()] == ["0"]
    model = pycolmap.Reconstruction(tmp_path / "sparse" / "0")
    (camera,) = model.cameras.values()
    assert camera.model_name == "PINHOLE"
    np.testing.assert_allclose(camera.params, colmap_camera(K, [])[1], rtol=1e-12)


def test_distortion_is_modelled(tiny_scene, tmp_path):
    import pycolmap

    blobs(tmp_path / "floor.png", 0, 1500, (3, 10))
    blobs(tmp_path / "crate.png", 1, 150, (8, 30))
    dist = [-0.25, 0.08, 0.002, -0.001]
    path = tiny_scene(
        width=200,
        height=150,
        # the template has no slot for these: they follow fx in its [camera] table
        fx=f'160.0\ndistortion_model = "radtan"\ndistortion = {dist}',
        trajectory=ORBIT,
        objects=TEXTURED.format(floor=tmp_path / "floor.png", crate=tmp_path / "crate.png"),
    )
    images, times, T_true, K = render(path, 24)
    result = run_sfm(images, times, K, np.array(dist), workdir=tmp_path / "sfm")
    assert result.registered == 24
    errors = pose_errors(result.T_world_cam, T_true)
    # measured: 0.20 deg and 0.08 %; with the distortion left out, 3 deg
    assert errors["rotation_median_deg"] < 0.4 and errors["translation_median_pct"] < 0.25
    (camera,) = pycolmap.Reconstruction(tmp_path / "sfm" / "sparse" / "0").cameras.values()
    assert camera.model_name == "OPENCV"
    np.testing.assert_allclose(camera.params[4:], dist)


def test_a_textureless_scene_fails_and_says_why(tiny_scene):
    path = tiny_scene(
        width=200,
        height=150,
        fx=160.0,
        trajectory=ORBIT,
        objects=GRAY,
        lighting='environment = "sky"\nsky = { zenith = [0.6, 0.6, 0.6], '
        "horizon = [0.6, 0.6, 0.6], ground = [0.6, 0.6, 0.6] }",
    )
    images, times, _, K = render(path, 12)
    with pytest.raises(PosesError) as raised:
        run_sfm(images, times, K, np.zeros(0))
    message = str(raised.value)
    assert message.startswith("structure from motion failed: ")
    assert "features per frame" in message or "no features" in message
    assert "too little texture" in message and "\n" not in message
    assert isinstance(raised.value, ValueError)  # an InputError: the CLI's one-line message


def test_frames_that_never_move_fail_and_say_why():
    rng = np.random.default_rng(0)
    still = [(rng.random((150, 200)) * 255).astype(np.uint8)] * 8
    K = np.array([[160.0, 0, 99.5], [0, 160, 74.5], [0, 0, 1]])
    with pytest.raises(PosesError, match="must move, not only turn"):
        run_sfm(still, np.arange(8) * 10_000, K, np.zeros(0))


def test_colmap_camera_models_and_the_half_pixel():
    K = np.array([[300.0, 0, 172.5], [0, 301, 129.5], [0, 0, 1]])
    assert colmap_camera(K, np.zeros(0)) == ("PINHOLE", [300.0, 301.0, 173.0, 130.0])
    assert colmap_camera(K, np.zeros(5))[0] == "PINHOLE"
    model, params = colmap_camera(K, [-0.3, 0.1, 1e-3, -2e-3])
    assert model == "OPENCV" and params == [300.0, 301.0, 173.0, 130.0, -0.3, 0.1, 1e-3, -2e-3]
    model, params = colmap_camera(K, [[-0.3, 0.1, 1e-3, -2e-3, 0.05]])
    assert model == "FULL_OPENCV" and params[4:] == [-0.3, 0.1, 1e-3, -2e-3, 0.05, 0, 0, 0]
    assert colmap_camera(K, [0.1, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0])[0] == "OPENCV"
    with pytest.raises(InputError, match="thin-prism"):
        colmap_camera(K, [0.1, 0, 0, 0, 0, 0, 0, 0, 0.01])
    with pytest.raises(InputError, match="3 x 3"):
        colmap_camera(K[:2], [])
    with pytest.raises(InputError, match="positive"):
        colmap_camera(np.diag([0.0, 1.0, 1.0]), [])


def test_loop_pairs_join_keyframes_beyond_the_overlap():
    pairs = loop_pairs(100, 10)
    assert len(pairs) == sum(1 for i in range(0, 100, 10) for j in range(0, 100, 10) if j - i > 10)
    assert all(i % 10 == 0 and j % 10 == 0 and j - i > OVERLAP for i, j in pairs)
    assert (0, 90) in pairs and (0, 10) not in pairs
    assert loop_pairs(10, 10) == []
    # a long recording: the keyframes spread out, and their pairs stay bounded
    long = loop_pairs(5000, 10)
    keys = {i for pair in long for i in pair}
    assert len(keys) <= MAX_KEYFRAMES and max(keys) >= 4800
    assert len(long) <= MAX_KEYFRAMES * (MAX_KEYFRAMES - 1) // 2


def seen(frames: int, error_px: float, rng: np.random.Generator) -> Piece:
    """Cameras on a line looking along z at points 3 to 5 ahead, every point seen by every
    frame ``error_px`` off (a random direction) from where it projects."""
    T = np.tile(np.eye(4), (frames, 1, 1))
    T[:, 0, 3] = np.linspace(-0.5, 0.5, frames)
    xyz = rng.uniform([-1, -1, 3], [1, 1, 5], (50, 3))
    rows = [(f, p) for f in range(frames) for p in range(len(xyz))]
    f, p = np.array(rows).T
    Y = xyz[p] - T[f, :3, 3]
    xy = Y[:, :2] / Y[:, 2:] * 200 + 160
    turn = rng.uniform(0, 2 * np.pi, len(f))
    xy += error_px * np.stack([np.cos(turn), np.sin(turn)], 1)
    return Piece(np.arange(frames), T, xyz, f, p, p, xy)


def test_a_model_whose_points_fit_beats_a_bent_one_with_more_frames():
    rng = np.random.default_rng(0)
    K, dist = np.array([[200.0, 0, 160], [0, 200.0, 160], [0, 0, 1]]), np.zeros(0)
    fits, bent, more = seen(26, 0.8, rng), seen(39, 2.85, rng), seen(45, 0.8, rng)
    assert reprojection_px(fits, K, dist) == pytest.approx(0.8)
    assert reprojection_px(bent, K, dist) > GOOD_REPROJECTION_PX

    def rank(p: Piece) -> tuple:
        return _rank(p, K, dist)

    assert rank(fits) > rank(bent) and rank(more) > rank(fits)
    # both bent, or both fitting: more frames, then the closer fit
    assert rank(seen(40, 3.0, rng)) > rank(bent)
    assert rank(seen(45, 0.5, rng)) > rank(more)


@pytest.mark.parametrize(
    ("images", "times", "message"),
    [
        ([np.zeros((10, 10), np.uint8)] * 2, np.arange(2), "at least 3 frames"),
        ([np.zeros((10, 10), np.uint8)] * 4, np.arange(3), "times of shape"),
        ([np.zeros((10, 10), np.uint8)] * 4, np.arange(4.0), "integer microseconds"),
        ([np.zeros((10, 10), np.float32)] * 4, np.arange(4), "uint8"),
        (
            [np.zeros((10, 10), np.uint8)] * 3 + [np.zeros((10, 11), np.uint8)],
            np.arange(4),
            "shape",
        ),
        ([np.zeros((10, 10, 4), np.uint8)] * 4, np.arange(4), "shape"),
    ],
)
def test_bad_input_is_refused(images, times, message):
    K = np.array([[10.0, 0, 5], [0, 10, 5], [0, 0, 1]])
    with pytest.raises(InputError, match=message):
        run_sfm(images, times, K, np.zeros(0))


@pytest.mark.slow
def test_a_full_orbit_closes_its_loop(tiny_scene, tmp_path):
    import pycolmap

    blobs(tmp_path / "floor.png", 0, 1500, (3, 10))
    blobs(tmp_path / "crate.png", 1, 150, (8, 30))
    path = tiny_scene(
        width=200,
        height=150,
        fx=160.0,
        trajectory=ORBIT.replace("degrees = 90.0", "degrees = 360.0").replace(
            "height_swing = 0.5", "height_swing = 0.5\nswings = 2"
        ),
        objects=TEXTURED.format(floor=tmp_path / "floor.png", crate=tmp_path / "crate.png"),
    )
    images, times, T_true, K = render(path, 97)  # the last frame is the first again
    result = run_sfm(images, times, K, np.zeros(0), workdir=tmp_path / "sfm")
    assert result.registered == 97 and result.model_count == 1
    errors = pose_errors(result.T_world_cam, T_true)
    assert errors["rotation_median_deg"] < 0.3 and errors["translation_median_pct"] < 0.25
    # the loop pairs joined the end to the start: keyframes 0 and 90 share verified matches
    with pycolmap.Database.open(tmp_path / "sfm" / "database.db") as db:
        first, last = (db.read_image_with_name(f"{i:06d}.png").image_id for i in (0, 90))
        assert db.read_two_view_geometry(first, last).inlier_matches.shape[0] >= 50
