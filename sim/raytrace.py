"""Ray casting against the scene's triangles: a bounding-volume hierarchy (built with numpy)
and compiled traversal (numba) for the closest hit and for any hit (shadow rays)."""

from __future__ import annotations

import numba
import numpy as np

LEAF_SIZE = 4


class Bvh:
    """A BVH over triangles (vertices [V, 3], faces [F, 3])."""

    def __init__(self, vertices: np.ndarray, faces: np.ndarray) -> None:
        tri = vertices[faces]  # [F, 3, 3]
        lo, hi = tri.min(axis=1), tri.max(axis=1)
        centroid = tri.mean(axis=1)
        order = np.arange(len(faces))
        node_lo, node_hi, left, right, start, count = [], [], [], [], [], []
        stack = [(0, len(faces), -1, False)]
        while stack:
            a, b, parent, is_right = stack.pop()
            index = len(node_lo)
            idx = order[a:b]
            node_lo.append(lo[idx].min(axis=0))
            node_hi.append(hi[idx].max(axis=0))
            left.append(-1)
            right.append(-1)
            start.append(a)
            count.append(b - a)
            if parent >= 0:
                (right if is_right else left)[parent] = index
            if b - a <= LEAF_SIZE:
                continue
            c = centroid[idx]
            axis = int(np.argmax(c.max(axis=0) - c.min(axis=0)))
            mid = (b - a) // 2
            part = np.argpartition(c[:, axis], mid)
            order[a:b] = idx[part]
            count[index] = 0  # an inner node
            stack.append((a + mid, b, index, True))
            stack.append((a, a + mid, index, False))
        self.lo = np.array(node_lo)
        self.hi = np.array(node_hi)
        self.left = np.array(left, np.int64)
        self.right = np.array(right, np.int64)
        self.start = np.array(start, np.int64)
        self.count = np.array(count, np.int64)
        self.tri_index = order.astype(np.int64)
        t = tri[order]
        self.v0, self.e1, self.e2 = t[:, 0].copy(), (t[:, 1] - t[:, 0]), (t[:, 2] - t[:, 0])

    def _arrays(self):
        return (
            self.lo,
            self.hi,
            self.left,
            self.right,
            self.start,
            self.count,
            self.v0,
            self.e1,
            self.e2,
        )

    def closest(self, origins: np.ndarray, directions: np.ndarray, t_max: float = np.inf):
        """(distance, face index (-1: no hit), barycentric u, v) of each ray's first hit."""
        n = len(directions)
        t = np.full(n, np.inf)
        face = np.full(n, -1, np.int64)
        u = np.zeros(n)
        v = np.zeros(n)
        origins = np.ascontiguousarray(np.broadcast_to(origins, directions.shape), np.float64)
        _closest(
            origins,
            np.ascontiguousarray(directions, np.float64),
            t_max,
            *self._arrays(),
            t,
            face,
            u,
            v,
        )
        found = face >= 0
        face[found] = self.tri_index[face[found]]
        return t, face, u, v

    def occluded(
        self, origins: np.ndarray, directions: np.ndarray, t_max: np.ndarray
    ) -> np.ndarray:
        """Whether anything lies on each ray before t_max."""
        n = len(directions)
        out = np.zeros(n, np.bool_)
        origins = np.ascontiguousarray(np.broadcast_to(origins, directions.shape), np.float64)
        t_max = np.ascontiguousarray(np.broadcast_to(t_max, (n,)), np.float64)
        _any(origins, np.ascontiguousarray(directions, np.float64), t_max, *self._arrays(), out)
        return out


CHUNK = 256  # rays per task of the compiled loops (each task keeps one traversal stack)


@numba.njit(cache=True, inline="always")
def _entry(ox, oy, oz, ix, iy, iz, lo, hi, node, t_max):
    """Where the ray enters the node's box (inf: it misses it before t_max)."""
    a, b = (lo[node, 0] - ox) * ix, (hi[node, 0] - ox) * ix
    t0, t1 = min(a, b), max(a, b)
    a, b = (lo[node, 1] - oy) * iy, (hi[node, 1] - oy) * iy
    t0, t1 = max(t0, min(a, b)), min(t1, max(a, b))
    a, b = (lo[node, 2] - oz) * iz, (hi[node, 2] - oz) * iz
    t0, t1 = max(t0, min(a, b), 0.0), min(t1, max(a, b), t_max)
    return t0 if t0 <= t1 else np.inf


@numba.njit(cache=True, inline="always")
def _inverse(d):
    return 1.0 / d if abs(d) > 1e-15 else 1e15


@numba.njit(cache=True, inline="always")
def _triangle(o, d, v0, e1, e2):
    """Moller-Trumbore: (t, u, v), t = inf when missed."""
    px = d[1] * e2[2] - d[2] * e2[1]
    py = d[2] * e2[0] - d[0] * e2[2]
    pz = d[0] * e2[1] - d[1] * e2[0]
    det = e1[0] * px + e1[1] * py + e1[2] * pz
    if abs(det) < 1e-14:
        return np.inf, 0.0, 0.0
    inv = 1.0 / det
    sx, sy, sz = o[0] - v0[0], o[1] - v0[1], o[2] - v0[2]
    u = (sx * px + sy * py + sz * pz) * inv
    # A small tolerance closes the cracks between triangles (rays through shared edges and
    # vertices, e.g. a sphere's poles, must not slip through).
    if u < -1e-9 or u > 1.0 + 1e-9:
        return np.inf, 0.0, 0.0
    qx = sy * e1[2] - sz * e1[1]
    qy = sz * e1[0] - sx * e1[2]
    qz = sx * e1[1] - sy * e1[0]
    v = (d[0] * qx + d[1] * qy + d[2] * qz) * inv
    if v < -1e-9 or u + v > 1.0 + 1e-9:
        return np.inf, 0.0, 0.0
    t = (e2[0] * qx + e2[1] * qy + e2[2] * qz) * inv
    if t <= 1e-9:
        return np.inf, 0.0, 0.0
    return t, u, v


@numba.njit(cache=True, parallel=True)
def _closest(
    origins,
    dirs,
    t_max,
    lo,
    hi,
    left,
    right,
    start,
    count,
    v0,
    e1,
    e2,
    t_out,
    face_out,
    u_out,
    v_out,
):
    n = dirs.shape[0]
    for chunk in numba.prange((n + CHUNK - 1) // CHUNK):
        stack = np.empty(64, np.int64)
        for i in range(chunk * CHUNK, min(n, (chunk + 1) * CHUNK)):
            o, d = origins[i], dirs[i]
            ox, oy, oz = o[0], o[1], o[2]
            ix, iy, iz = _inverse(d[0]), _inverse(d[1]), _inverse(d[2])
            best, best_f, best_u, best_v = t_max, -1, 0.0, 0.0
            top = 0
            if _entry(ox, oy, oz, ix, iy, iz, lo, hi, 0, best) < np.inf:
                stack[0] = 0
                top = 1
            while top > 0:
                top -= 1
                node = stack[top]
                if count[node] > 0:
                    for k in range(start[node], start[node] + count[node]):
                        t, u, v = _triangle(o, d, v0[k], e1[k], e2[k])
                        if t < best:
                            best, best_f, best_u, best_v = t, k, u, v
                    continue
                # the nearer child is visited first: its hits cut the farther one's search
                a, b = left[node], right[node]
                ta = _entry(ox, oy, oz, ix, iy, iz, lo, hi, a, best)
                tb = _entry(ox, oy, oz, ix, iy, iz, lo, hi, b, best)
                if ta > tb:
                    a, b, ta, tb = b, a, tb, ta
                if tb < np.inf:
                    stack[top] = b
                    top += 1
                if ta < np.inf:
                    stack[top] = a
                    top += 1
                # a node popped later may lie beyond a hit found since it was pushed
                while (
                    top > 0
                    and _entry(ox, oy, oz, ix, iy, iz, lo, hi, stack[top - 1], best) == np.inf
                ):
                    top -= 1
            if best_f >= 0:
                t_out[i], face_out[i], u_out[i], v_out[i] = best, best_f, best_u, best_v


@numba.njit(cache=True, parallel=True)
def _any(origins, dirs, t_max, lo, hi, left, right, start, count, v0, e1, e2, out):
    n = dirs.shape[0]
    for chunk in numba.prange((n + CHUNK - 1) // CHUNK):
        stack = np.empty(64, np.int64)
        for i in range(chunk * CHUNK, min(n, (chunk + 1) * CHUNK)):
            o, d = origins[i], dirs[i]
            ox, oy, oz = o[0], o[1], o[2]
            ix, iy, iz = _inverse(d[0]), _inverse(d[1]), _inverse(d[2])
            stack[0] = 0
            top = 1
            hit = False
            while top > 0 and not hit:
                top -= 1
                node = stack[top]
                if _entry(ox, oy, oz, ix, iy, iz, lo, hi, node, t_max[i]) == np.inf:
                    continue
                if count[node] > 0:
                    for k in range(start[node], start[node] + count[node]):
                        t, _, _ = _triangle(o, d, v0[k], e1[k], e2[k])
                        if t < t_max[i]:
                            hit = True
                            break
                else:
                    stack[top] = left[node]
                    stack[top + 1] = right[node]
                    top += 2
            out[i] = hit
