"""Meshes and ray casting."""

import numpy as np
import pytest

from evcap.errors import InputError
from evcap.sim.meshes import box, load_obj, load_ply, sphere
from evcap.sim.raytrace import Bvh

CUBE_V = [[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0], [0, 0, 1], [1, 0, 1], [1, 1, 1], [0, 1, 1]]
CUBE_F = [[0, 3, 2, 1], [4, 5, 6, 7], [0, 1, 5, 4], [1, 2, 6, 5], [2, 3, 7, 6], [3, 0, 4, 7]]


def test_obj_with_polygons_and_uvs(tmp_path):
    lines = [f"v {x} {y} {z}" for x, y, z in CUBE_V] + ["vt 0 0", "vt 1 0", "vt 1 1", "vt 0 1"]
    lines += ["f " + " ".join(f"{i + 1}/{k + 1}" for k, i in enumerate(face)) for face in CUBE_F]
    (tmp_path / "cube.obj").write_text("\n".join(lines) + "\n")
    m = load_obj(tmp_path / "cube.obj")
    assert m.faces.shape == (12, 3)  # quads fanned into triangles
    area = np.linalg.norm(
        np.cross(
            m.vertices[m.faces[:, 1]] - m.vertices[m.faces[:, 0]],
            m.vertices[m.faces[:, 2]] - m.vertices[m.faces[:, 0]],
        ),
        axis=1,
    )
    assert area.sum() / 2 == pytest.approx(6.0)
    (tmp_path / "bad.obj").write_text("v 0 0 0\nf 1 2 3\n")
    with pytest.raises(InputError, match="does not exist"):
        load_obj(tmp_path / "bad.obj")


@pytest.mark.parametrize("binary", [False, True])
def test_ply_ascii_and_binary(tmp_path, binary):
    v = np.array(CUBE_V, np.float32)
    header = [
        "ply",
        "format " + ("binary_little_endian" if binary else "ascii") + " 1.0",
        "element vertex 8",
        "property float x",
        "property float y",
        "property float z",
        "element face 6",
        "property list uchar int vertex_indices",
        "end_header",
    ]
    body = b""
    if binary:
        body = v.tobytes() + b"".join(
            np.uint8(4).tobytes() + np.array(f, "<i4").tobytes() for f in CUBE_F
        )
    else:
        body = (
            "\n".join(" ".join(map(str, p)) for p in CUBE_V)
            + "\n"
            + "\n".join("4 " + " ".join(map(str, f)) for f in CUBE_F)
            + "\n"
        ).encode()
    (tmp_path / "cube.ply").write_bytes(("\n".join(header) + "\n").encode() + body)
    m = load_ply(tmp_path / "cube.ply")
    assert m.faces.shape == (12, 3)
    assert np.allclose(np.unique(m.vertices, axis=0), np.unique(v, axis=0))
    # sharp edges keep the faces flat: 3 normals per corner, each along an axis, outwards
    assert len(m.vertices) == 24
    center = m.vertices[m.faces].mean(1)
    n = m.normals[m.faces]
    assert np.allclose(n, n[:, :1]) and np.allclose(np.abs(n).max(-1), 1)
    assert (np.einsum("ij,ij->i", n[:, 0], center - 0.5) > 0).all()


def test_bvh_matches_brute_force():
    rng = np.random.default_rng(0)
    tri = rng.uniform(-1, 1, (300, 3, 3))
    vertices, faces = tri.reshape(-1, 3), np.arange(900).reshape(300, 3)
    bvh = Bvh(vertices, faces)
    origins = rng.uniform(-2, 2, (500, 3))
    dirs = rng.normal(size=(500, 3))
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    t, face, u, v = bvh.closest(origins, dirs)
    # brute force, with numpy
    e1, e2 = tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]
    best = np.full(500, np.inf)
    for i in range(500):
        p = np.cross(dirs[i], e2)
        det = np.einsum("ij,ij->i", e1, p)
        s = origins[i] - tri[:, 0]
        uu = np.einsum("ij,ij->i", s, p) / det
        q = np.cross(s, e1)
        vv = q @ dirs[i] / det
        tt = np.einsum("ij,ij->i", e2, q) / det
        ok = (uu >= 0) & (vv >= 0) & (uu + vv <= 1) & (tt > 1e-9)
        if ok.any():
            best[i] = tt[ok].min()
    np.testing.assert_allclose(t, best, rtol=1e-9)
    hit = np.isfinite(best)
    assert hit.sum() > 50
    occluded = bvh.occluded(origins, dirs, np.where(hit, best * 1.01, 10.0))
    assert (occluded == hit).all()
    assert not bvh.occluded(origins, dirs, np.where(hit, best * 0.99, 1e-6)).any()


def test_primitives_are_closed_and_outward():
    for mesh in (sphere(32, 16), box(4)):
        center = mesh.vertices[mesh.faces].mean(1)
        fn = np.cross(
            mesh.vertices[mesh.faces[:, 1]] - mesh.vertices[mesh.faces[:, 0]],
            mesh.vertices[mesh.faces[:, 2]] - mesh.vertices[mesh.faces[:, 0]],
        )
        assert (np.einsum("ij,ij->i", fn, center) > 0).all()  # counter-clockwise from outside
        bvh = Bvh(mesh.vertices, mesh.faces)
        d = np.random.default_rng(1).normal(size=(2000, 3))
        d /= np.linalg.norm(d, axis=1, keepdims=True)
        t, face, _, _ = bvh.closest(np.zeros(3), d)
        assert (face >= 0).all()  # no ray escapes through a crack
