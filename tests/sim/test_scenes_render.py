"""What scenes can hold renders as it should: a ChArUco board OpenCV finds where the truth
says, image textures and environments, point lights, meshes, every kind of path."""

import numpy as np
import pytest

from evcap.sim.render import Renderer
from evcap.sim.scene import load_scene
from evcap.sim.trajectory import Trajectory

BOARD = """
[[objects]]
type = "charuco"
center = [0.0, 0.0, 0.0]
rotation_deg = [90.0, 0.0, 10.0]
squares_x = 7
squares_y = 5
square_length = 0.04
marker_length = 0.03
dictionary = "DICT_4X4_50"
"""


def board_corners_world(board: dict, cb) -> np.ndarray:
    """The board's inner corners in the world, from its definition and pose."""
    corners = cb.getChessboardCorners()  # OpenCV: origin at the top-left corner, y down
    local = np.stack(
        [
            board["margin"] + corners[:, 0] - board["width"] / 2,
            board["height"] / 2 - board["margin"] - corners[:, 1],
            np.zeros(len(corners)),
        ],
        1,
    )
    return local @ np.asarray(board["rotation"]).T + np.asarray(board["center"])


def test_charuco_board_is_found_where_the_truth_says(tiny_scene):
    import cv2

    path = tiny_scene(
        objects=BOARD,
        width=346,
        height=260,
        fx=300.0,
        trajectory='kind = "static"\nposition = [0.05, -0.4, 0.04]\nlook_at = [0, 0, 0]',
        lighting='environment = "sky"\nsky = { zenith = [0.8, 0.8, 0.8], '
        "horizon = [0.8, 0.8, 0.8], ground = [0.6, 0.6, 0.6] }",
    )
    scene = load_scene(path)
    r = Renderer(scene)
    T = Trajectory(scene.trajectory).pose(0.0)
    img = r.render_full(T)["radiance"]
    gray = (np.clip(img.mean(-1), 0, 1) ** (1 / 2.2) * 255).astype(np.uint8)
    board = next(b for b in r.boards if b)
    dictionary = cv2.aruco.getPredefinedDictionary(cv2.aruco.DICT_4X4_50)
    cb = cv2.aruco.CharucoBoard((7, 5), 0.04, 0.03, dictionary)
    corners, ids, _, _ = cv2.aruco.CharucoDetector(cb).detectBoard(gray)
    assert ids is not None and len(ids) >= 20
    world = board_corners_world(board, cb)[ids.ravel()]
    cam = (world - T[:3, 3]) @ T[:3, :3]
    expected = r.camera.project(cam)
    error = np.linalg.norm(corners.reshape(-1, 2) - expected, axis=1)
    assert np.median(error) < 0.3 and error.max() < 1.0


def test_image_texture_environment_and_point_light(tiny_scene, tmp_path):
    import cv2

    texture = np.zeros((8, 8, 3), np.uint8)
    texture[:, :4] = (0, 0, 255)  # BGR: red left half
    texture[:, 4:] = (255, 0, 0)  # blue right half
    cv2.imwrite(str(tmp_path / "tex.png"), texture)
    env = np.zeros((16, 32, 3), np.float32)
    env[:8] = (0.2, 0.4, 0.9)  # the upper hemisphere blue (BGR: 0.9 is red... set below)
    cv2.imwrite(str(tmp_path / "env.hdr"), env)
    objects = (
        '[[objects]]\ntype = "plane"\nsize = [2.0, 2.0]\nmaterial = "tex"\n'
        f'[materials.tex]\ntexture = "{tmp_path / "tex.png"}"\nroughness = 1.0'
    )
    top = 'kind = "static"\nposition = [0.001, 0.0, 2.0]\nlook_at = [0, 0, 0]'
    for lighting in (
        f'environment = "{tmp_path / "env.hdr"}"',
        'environment = "sky"\nsky = { zenith = [0, 0, 0], horizon = [0, 0, 0], '
        "ground = [0, 0, 0] }\npoints = [{ position = [0.0, 0.0, 1.0], "
        "intensity = 2.0 }]",
    ):
        scene = load_scene(tiny_scene(objects=objects, trajectory=top, lighting=lighting))
        r = Renderer(scene)
        out = r.render_full(Trajectory(scene.trajectory).pose(0.0))
        base = out["base_color"][out["depth"] > 0]
        h, w = out["depth"].shape
        # the texture's halves: about as much red as blue
        red = (np.argmax(base, 1) == 0).mean()
        assert 0.35 < red < 0.65 and (np.argmax(base, 1) == 2).mean() == pytest.approx(1 - red)
        assert (out["radiance"][out["depth"] > 0] > 0).all()
    # the point light: 2 / 1^2 irradiance straight below it, Lambert: albedo * 2 / pi
    center = out["radiance"][h // 2, w // 2]
    albedo = out["base_color"][h // 2, w // 2]
    np.testing.assert_allclose(center.max(), albedo.max() * 2 / np.pi, rtol=0.1)


def test_mesh_objects_and_paths(tiny_scene, tmp_path):
    cube = [
        "v 0 0 0",
        "v 1 0 0",
        "v 1 1 0",
        "v 0 1 0",
        "v 0 0 1",
        "v 1 0 1",
        "v 1 1 1",
        "v 0 1 1",
        "f 1 4 3 2",
        "f 5 6 7 8",
        "f 1 2 6 5",
        "f 2 3 7 6",
        "f 3 4 8 7",
        "f 4 1 5 8",
    ]
    (tmp_path / "cube.obj").write_text("\n".join(cube) + "\n")
    objects = (
        f'[[objects]]\ntype = "mesh"\npath = "{tmp_path / "cube.obj"}"\nscale = 0.5\n'
        'material = "paint"'
    )
    for trajectory in (
        'kind = "linear"\nstart = [2, -0.5, 0.3]\nend = [2, 0.5, 0.3]',
        'kind = "handheld"\nstart = [2, 0, 0.3]\nshake_deg = 2.0',
        'kind = "orbit"\nradius = 2.0',
    ):
        scene = load_scene(tiny_scene(objects=objects, trajectory=trajectory))
        r, traj = Renderer(scene), Trajectory(scene.trajectory, seed=1)
        for t in (0.0, 1.0):
            out = r.render_full(traj.pose(t))
            assert (out["depth"] > 0).mean() > 0.02  # the cube is in view
            hit = out["depth"] > 0
            # the cube's faces: normals along the cube's axes (rotated into the camera frame)
            n_world = out["normal"][hit] @ traj.pose(t)[:3, :3].T
            assert np.abs(n_world).max(axis=1).min() > 0.99
    shaky = Trajectory(
        load_scene(
            tiny_scene(
                objects=objects,
                trajectory='kind = "handheld"\nstart = [2, 0, 0.3]\nshake_deg = 2.0',
            )
        ).trajectory,
        seed=1,
    )
    still = Trajectory(
        load_scene(
            tiny_scene(objects=objects, trajectory='kind = "linear"\nstart = [2, 0, 0.3]')
        ).trajectory
    )
    angle = [
        np.degrees(
            np.arccos(
                np.clip((np.trace(shaky.pose(t)[:3, :3].T @ still.pose(t)[:3, :3]) - 1) / 2, -1, 1)
            )
        )
        for t in np.linspace(0, 1, 50)
    ]
    assert 0.2 < max(angle) < 3.0  # the shake: about its amplitude, smooth
