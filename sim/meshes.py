"""Triangle meshes of the scene: primitives (sphere, box, plane, ChArUco board) and files
(OBJ, PLY), merged into one mesh with per-face material and object indices."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from evcap.errors import InputError
from evcap.sim.scene import Scene, SceneObject


@dataclass
class Mesh:
    vertices: np.ndarray  # [V, 3] float64
    normals: np.ndarray  # [V, 3] unit
    uvs: np.ndarray  # [V, 2]
    faces: np.ndarray  # [F, 3] int64
    material: np.ndarray = field(default=None)  # [F] int: index into the material list
    object_id: np.ndarray = field(default=None)  # [F] int

    def transformed(
        self, rotation: np.ndarray, translation: np.ndarray, scale: float = 1.0
    ) -> Mesh:
        return Mesh(
            self.vertices * scale @ rotation.T + translation,
            self.normals @ rotation.T,
            self.uvs,
            self.faces,
            self.material,
            self.object_id,
        )


def euler_deg(angles) -> np.ndarray:
    """R = Rz @ Ry @ Rx for angles (x, y, z) in degrees."""
    x, y, z = np.deg2rad(np.asarray(angles, np.float64))
    rx = np.array([[1, 0, 0], [0, np.cos(x), -np.sin(x)], [0, np.sin(x), np.cos(x)]])
    ry = np.array([[np.cos(y), 0, np.sin(y)], [0, 1, 0], [-np.sin(y), 0, np.cos(y)]])
    rz = np.array([[np.cos(z), -np.sin(z), 0], [np.sin(z), np.cos(z), 0], [0, 0, 1]])
    return rz @ ry @ rx


def sphere(segments: int = 64, rings: int = 32) -> Mesh:
    """A unit sphere; u runs around z, v from the south pole to the north."""
    u, v = np.meshgrid(np.linspace(0, 1, segments + 1), np.linspace(0, 1, rings + 1))
    phi, theta = 2 * np.pi * u, np.pi * (v - 0.5)
    p = np.stack([np.cos(theta) * np.cos(phi), np.cos(theta) * np.sin(phi), np.sin(theta)], -1)
    idx = np.arange((rings + 1) * (segments + 1)).reshape(rings + 1, segments + 1)
    a, b, c, d = idx[:-1, :-1], idx[:-1, 1:], idx[1:, 1:], idx[1:, :-1]
    faces = np.concatenate(
        [np.stack([a, b, c], -1).reshape(-1, 3), np.stack([a, c, d], -1).reshape(-1, 3)]
    )
    p = p.reshape(-1, 3)
    area = np.linalg.norm(
        np.cross(p[faces[:, 1]] - p[faces[:, 0]], p[faces[:, 2]] - p[faces[:, 0]]), axis=1
    )
    faces = faces[area > 1e-12]  # the poles' degenerate triangles
    return Mesh(p, p.copy(), np.stack([u.ravel(), v.ravel()], 1), faces)


def grid(n: int) -> Mesh:
    """The square [-0.5, 0.5]^2 in the z = 0 plane, facing +z, n x n cells."""
    u, v = np.meshgrid(np.linspace(0, 1, n + 1), np.linspace(0, 1, n + 1))
    p = np.stack([u - 0.5, v - 0.5, np.zeros_like(u)], -1).reshape(-1, 3)
    idx = np.arange((n + 1) ** 2).reshape(n + 1, n + 1)
    a, b, c, d = idx[:-1, :-1], idx[:-1, 1:], idx[1:, 1:], idx[1:, :-1]
    faces = np.concatenate(
        [np.stack([a, b, c], -1).reshape(-1, 3), np.stack([a, c, d], -1).reshape(-1, 3)]
    )
    normals = np.tile([0.0, 0.0, 1.0], (p.shape[0], 1))
    # v grows downwards in images: image row 0 is at the plane's +y edge
    return Mesh(p, normals, np.stack([u.ravel(), 1 - v.ravel()], 1), faces)


def box(n: int = 8) -> Mesh:
    """The unit cube centred at 0, each face an n x n grid with its own (flat) normals."""
    face = grid(n)
    parts = []
    for r in (
        np.eye(3),
        euler_deg([180, 0, 0]),
        euler_deg([90, 0, 0]),
        euler_deg([-90, 0, 0]),
        euler_deg([0, 90, 0]),
        euler_deg([0, -90, 0]),
    ):
        parts.append(face.transformed(r, r @ np.array([0, 0, 0.5])))
    return merge(parts)


def merge(parts: list[Mesh]) -> Mesh:
    offsets = np.cumsum([0] + [m.vertices.shape[0] for m in parts[:-1]])
    return Mesh(
        np.concatenate([m.vertices for m in parts]),
        np.concatenate([m.normals for m in parts]),
        np.concatenate([m.uvs for m in parts]),
        np.concatenate([m.faces + o for m, o in zip(parts, offsets, strict=True)]),
        np.concatenate([m.material for m in parts]) if parts[0].material is not None else None,
        np.concatenate([m.object_id for m in parts]) if parts[0].object_id is not None else None,
    )


def smooth_shaded(
    vertices: np.ndarray, faces: np.ndarray, uvs: np.ndarray, sharp_deg: float = 40.0
) -> Mesh:
    """The mesh with normals smoothed across edges flatter than ``sharp_deg`` and split at
    sharper ones (a cube keeps flat faces, a sphere is smooth), like an auto-smooth."""
    raw = np.cross(
        vertices[faces[:, 1]] - vertices[faces[:, 0]], vertices[faces[:, 2]] - vertices[faces[:, 0]]
    )  # length: twice the area
    unit = raw / np.maximum(np.linalg.norm(raw, axis=1, keepdims=True), 1e-300)
    _, position = np.unique(vertices, axis=0, return_inverse=True)  # across UV seams too
    corner_pos = position.ravel()[faces.ravel()]
    corner_face = np.repeat(np.arange(len(faces)), 3)
    order = np.argsort(corner_pos, kind="stable")
    bounds = np.flatnonzero(np.diff(corner_pos[order], prepend=-1, append=-2))
    normals = np.zeros((len(corner_pos), 3))
    cos_sharp = np.cos(np.deg2rad(sharp_deg))
    for a, b in zip(bounds[:-1], bounds[1:], strict=True):
        corners = order[a:b]
        fs = corner_face[corners]
        similar = unit[fs] @ unit[fs].T > cos_sharp
        normals[corners] = similar @ raw[fs]
    normals /= np.maximum(np.linalg.norm(normals, axis=1, keepdims=True), 1e-300)
    # one vertex per (vertex, normal): corners on both sides of a sharp edge part
    keys = np.concatenate([faces.ravel()[:, None].astype(np.float64), np.round(normals, 6)], 1)
    unique, first, inverse = np.unique(keys, axis=0, return_index=True, return_inverse=True)
    source = faces.ravel()[first]
    return Mesh(vertices[source], normals[first], uvs[source], inverse.reshape(-1, 3))


def load_obj(path: Path) -> Mesh:
    """Vertices, texture coordinates and faces of an OBJ file (polygons are fanned)."""
    v, vt, vn, faces, face_vt, face_vn = [], [], [], [], [], []
    for line_no, line in enumerate(path.read_text(errors="replace").splitlines(), 1):
        parts = line.split()
        if not parts:
            continue
        try:
            if parts[0] == "v":
                v.append([float(x) for x in parts[1:4]])
            elif parts[0] == "vt":
                vt.append([float(x) for x in parts[1:3]])
            elif parts[0] == "vn":
                vn.append([float(x) for x in parts[1:4]])
            elif parts[0] == "f":
                refs = [p.split("/") for p in parts[1:]]
                idx = [int(r[0]) for r in refs]
                tex = [int(r[1]) if len(r) > 1 and r[1] else 0 for r in refs]
                nor = [int(r[2]) if len(r) > 2 and r[2] else 0 for r in refs]
                for k in range(1, len(idx) - 1):
                    faces.append([idx[0], idx[k], idx[k + 1]])
                    face_vt.append([tex[0], tex[k], tex[k + 1]])
                    face_vn.append([nor[0], nor[k], nor[k + 1]])
        except (ValueError, IndexError):
            raise InputError(f"{path}:{line_no}: cannot read {line.strip()!r}") from None
    if not v or not faces:
        raise InputError(f"{path}: no vertices or faces")
    v = np.asarray(v, np.float64)
    f = np.asarray(faces, np.int64)
    f = np.where(f < 0, f + len(v), f - 1)  # OBJ counts from 1; negative counts from the end
    if f.min() < 0 or f.max() >= len(v):
        raise InputError(f"{path}: a face refers to a vertex that does not exist")
    # one vertex per (position, texture coordinate) corner, so that UV seams stay sharp
    ft = np.asarray(face_vt, np.int64)
    if vt and (ft > 0).all():
        t = np.asarray(vt, np.float64)
        keys = np.stack([f.ravel(), ft.ravel() - 1], 1)
        unique, inverse = np.unique(keys, axis=0, return_inverse=True)
        vertices, uvs = v[unique[:, 0]], t[unique[:, 1]]
        f = inverse.reshape(-1, 3)
    else:
        vertices, uvs = v, np.zeros((len(v), 2))
    return smooth_shaded(vertices, f, uvs)


def load_ply(path: Path) -> Mesh:
    """Vertices (x, y, z, optional u/v or s/t) and faces of an ASCII or binary PLY file."""
    data = path.read_bytes()
    end = data.find(b"end_header")
    if not data.startswith(b"ply") or end < 0:
        raise InputError(f"{path}: not a PLY file")
    header = data[:end].decode("ascii", "replace").splitlines()
    body = data[data.index(b"\n", end) + 1 :]
    fmt = next((h.split()[1] for h in header if h.startswith("format")), "")
    types = {
        "char": "i1",
        "uchar": "u1",
        "short": "i2",
        "ushort": "u2",
        "int": "i4",
        "uint": "u4",
        "float": "f4",
        "double": "f8",
        "int8": "i1",
        "uint8": "u1",
        "int16": "i2",
        "uint16": "u2",
        "int32": "i4",
        "uint32": "u4",
        "float32": "f4",
        "float64": "f8",
    }
    elements, current = [], None
    for h in header:
        p = h.split()
        if p[0] == "element":
            current = {"name": p[1], "count": int(p[2]), "props": []}
            elements.append(current)
        elif p[0] == "property" and current is not None:
            current["props"].append(p[1:])
    endian = {"binary_little_endian": "<", "binary_big_endian": ">"}.get(fmt)
    vertex = face = None
    if fmt == "ascii":
        lines = iter(body.decode("ascii", "replace").split("\n"))
        for el in elements:
            rows = [next(lines).split() for _ in range(el["count"])]
            if el["name"] == "vertex":
                names = [p[-1] for p in el["props"]]
                vertex = {n: np.array([float(r[i]) for r in rows]) for i, n in enumerate(names)}
            elif el["name"] == "face":
                face = [[int(x) for x in r[1 : 1 + int(r[0])]] for r in rows]
    elif endian:
        offset = 0
        for el in elements:
            if el["name"] == "face":
                count_t, index_t = types[el["props"][0][1]], types[el["props"][0][2]]
                face = []
                for _ in range(el["count"]):
                    n = int(np.frombuffer(body, endian + count_t, 1, offset)[0])
                    offset += np.dtype(count_t).itemsize
                    face.append(np.frombuffer(body, endian + index_t, n, offset).tolist())
                    offset += n * np.dtype(index_t).itemsize
            else:
                dtype = np.dtype([(p[-1], endian + types[p[0]]) for p in el["props"]])
                rows = np.frombuffer(body, dtype, el["count"], offset)
                offset += dtype.itemsize * el["count"]
                if el["name"] == "vertex":
                    vertex = {n: rows[n].astype(np.float64) for n in dtype.names}
    else:
        raise InputError(f"{path}: PLY format {fmt!r} not supported")
    if vertex is None or not face:
        raise InputError(f"{path}: no vertices or faces")
    v = np.stack([vertex["x"], vertex["y"], vertex["z"]], 1)
    f = np.array([[p[0], p[k], p[k + 1]] for p in face for k in range(1, len(p) - 1)], np.int64)
    uk = next(
        ((a, b) for a, b in (("u", "v"), ("s", "t"), ("texture_u", "texture_v")) if a in vertex),
        None,
    )
    uvs = np.stack([vertex[uk[0]], vertex[uk[1]]], 1) if uk else np.zeros((len(v), 2))
    return smooth_shaded(v, f, uvs)


def charuco_board(params: dict) -> tuple[Mesh, dict]:
    """A flat ChArUco board (its face is +z) and what defines it (for the texture and the
    ground truth of calibration)."""
    sx, sy = int(params.get("squares_x", 7)), int(params.get("squares_y", 5))
    square = float(params.get("square_length", 0.04))
    board = {
        "squares_x": sx,
        "squares_y": sy,
        "square_length": square,
        "marker_length": float(params.get("marker_length", square * 0.75)),
        "dictionary": str(params.get("dictionary", "DICT_4X4_50")),
        "margin": float(params.get("margin", square * 0.5)),
    }
    width, height = sx * square + 2 * board["margin"], sy * square + 2 * board["margin"]
    mesh = grid(int(params.get("subdivisions", 16)))
    mesh.vertices = mesh.vertices * [width, height, 1.0]
    board["width"], board["height"] = width, height
    return mesh, board


def object_mesh(obj: SceneObject) -> tuple[Mesh, dict | None]:
    """The mesh of one scene object, in world coordinates; the board's definition for a
    ChArUco board."""
    p = obj.params
    rotation = euler_deg(p.get("rotation_deg", [0, 0, 0]))
    center = np.asarray(p.get("center", [0, 0, 0]), np.float64)
    extra = None
    if obj.kind == "sphere":
        r = float(p.get("radius", 0.5))
        m = sphere(int(p.get("segments", 64)), int(p.get("rings", 32)))
        m = Mesh(m.vertices * r, m.normals, m.uvs, m.faces)
    elif obj.kind == "box":
        size = np.asarray(p.get("size", [1, 1, 1]), np.float64)
        m = box(int(p.get("subdivisions", 8)))
        m = Mesh(m.vertices * size, m.normals, m.uvs, m.faces)
    elif obj.kind == "plane":
        size = np.asarray(p.get("size", [2, 2]), np.float64)
        m = grid(int(p.get("subdivisions", 32)))
        m = Mesh(m.vertices * [size[0], size[1], 1.0], m.normals, m.uvs, m.faces)
    elif obj.kind == "charuco":
        m, extra = charuco_board(p)
    else:
        path = Path(p["path"])
        m = load_ply(path) if path.suffix.lower() == ".ply" else load_obj(path)
        if p.get("center_and_fit", True):  # centred at the origin, fitting the unit sphere
            lo, hi = m.vertices.min(0), m.vertices.max(0)
            m.vertices = (m.vertices - (lo + hi) / 2) / (np.linalg.norm(hi - lo) / 2)
        m = Mesh(m.vertices * float(p.get("scale", 1.0)), m.normals, m.uvs, m.faces)
    return m.transformed(rotation, center), extra


def sample_surface(mesh: Mesh, count: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray, float]:
    """``count`` points spread over the mesh by area, each with its face's normal [count, 3],
    and their mean spacing (the side of the square each point stands for)."""
    a, b, c = (mesh.vertices[mesh.faces[:, i]] for i in range(3))
    cross = np.cross(b - a, c - a)
    area = np.linalg.norm(cross, axis=1) / 2
    rng = np.random.default_rng(seed)
    face = rng.choice(len(area), count, p=area / area.sum())
    u, v = rng.random((2, count))
    flip = u + v > 1  # fold the square's far half back into the triangle
    u, v = np.where(flip, 1 - u, u), np.where(flip, 1 - v, v)
    points = a[face] + u[:, None] * (b - a)[face] + v[:, None] * (c - a)[face]
    normals = cross[face] / np.maximum(2 * area[face], 1e-12)[:, None]
    return points, normals, float(np.sqrt(area.sum() / count))


def build_mesh(scene: Scene) -> tuple[Mesh, list[str], list[dict | None]]:
    """All objects in one mesh; the material names (indexed by Mesh.material); per object, the
    ChArUco board definition (with its pose) or None."""
    names = list(scene.materials)
    parts, boards = [], []
    for i, obj in enumerate(scene.objects):
        m, board = object_mesh(obj)
        m.material = np.full(len(m.faces), names.index(obj.material))
        m.object_id = np.full(len(m.faces), i)
        parts.append(m)
        if board is not None:
            board["rotation"] = euler_deg(obj.params.get("rotation_deg", [0, 0, 0]))
            board["center"] = np.asarray(obj.params.get("center", [0, 0, 0]), np.float64)
        boards.append(board)
    return merge(parts), names, boards
