"""The plane the scene stands on (a floor, a table), from the events' stereo points.

A support without texture makes events only where something marks it: the contact lines of
what stands on it, the outlines of shadows, its far edges. Its inside is one colour, which a
background at infinity paints as well as a surface can, so stage I leaves it to the background
(multi_object: 71 % of the floor's pixels seen through). The marks lie on one plane, with the
cameras on one side and nearly all the structure above it: that plane, where the stereo finds
one, starts as flat discs, and the pixels whose rays meet it inside the foreground's ball and
its outline (its marks and, unless something is seen below it there, on to under the cameras)
are asked to be opaque where the others are asked to be clear (the backdrop is not seen
through a floor).
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
import torch

from evcap.errors import InputError
from evcap.recon.scene.volume import Ball

# a point counts as below the plane only this many tolerances under it: the stereo's depth
# spreads wider on a floor seen at a grazing angle (multi_object: 3.3 % of the points lie more
# than one tolerance under the true floor, 0.2 % more than three); at 3 a plane 4.4 deg off the
# floor, through the objects' feet, passes, at 2 one 1.9 deg off (it held the most points)
BELOW_BY = 2.0
# the support is not run on under the cameras when more points than this share of those it
# holds lie below it there (multi_object: none of 170 points below lie there)
BEYOND_MARKS = 0.02
# the fit leaves out a point with structure straight above it: within BODY_RADIUS of the
# foreground ball's radius along the plane, between two tolerances and BODY_REACH radii over it
# (an object's bottom, which lies above the floor, not the floor's mark)
BODY_RADIUS, BODY_REACH = 0.02, 0.5
# the fit's smooth score: a point at height h weighs exp(-(h / (HELD_WIDTH tolerances))^2 / 2)
# held, and, below the plane, a sigmoid over BELOW_EDGE tolerances about one tolerance under it
HELD_WIDTH, BELOW_EDGE = 0.6, 0.2
REFINED = 5  # the planes through three points that hold the most, each refined


@dataclass(frozen=True)
class SupportConfig:
    """Finding the plane the scene stands on (support_plane)."""

    tolerance: float = 0.02
    """A point lies on the plane within this share of the foreground ball's radius."""
    holds: float = 0.1
    """The plane holds at least this share of the stereo points ..."""
    below: float = 0.03
    """... and at most this share lies below it, away from the cameras, by more than
    `BELOW_BY` tolerances."""
    tries: int = 2000
    """Planes tried through three points each (RANSAC)."""
    below_weight: float = 1.5
    """In the fit, a point more than a tolerance below the plane counts against it this many
    times a point it holds: nothing lies under a floor but the stereo's spread (3.3 % of
    multi_object's points lie that far under the true floor), and a plane tilted through the
    objects' feet holds more points (1,392 against the floor's 1,087) with more below it
    (7.1 %)."""

    def __post_init__(self) -> None:
        if self.tolerance <= 0 or not 0 < self.holds <= 1 or not 0 <= self.below < 1:
            raise InputError(
                "init.support needs tolerance > 0, holds in (0, 1] and below in [0, 1)"
            )
        if self.below_weight < 0:
            raise InputError("init.support.below_weight must be >= 0")
        if self.tries < 1:
            raise InputError("init.support.tries must be at least 1")


@dataclass(frozen=True)
class Plane:
    """The points x with normal . x = offset; the normal towards the cameras. ``outline``:
    where the support reaches, a convex polygon in the plane's own coordinates (`axes`),
    counter-clockwise; None: everywhere."""

    normal: tuple[float, float, float]
    offset: float
    outline: tuple[tuple[float, float], ...] | None = None

    def axes(self) -> tuple[np.ndarray, np.ndarray]:
        """Two unit vectors along the plane, at right angles (u, v, normal right-handed)."""
        normal = np.asarray(self.normal)
        u = np.cross(normal, [1.0, 0, 0] if abs(normal[0]) < 0.9 else [0, 1.0, 0])
        u /= np.linalg.norm(u)
        return u, np.cross(normal, u)

    def inside(self, points: np.ndarray) -> np.ndarray:
        """[N] bool: whether the feet of ``points`` [N, 3] on the plane lie inside the outline."""
        if self.outline is None:
            return np.ones(len(points), bool)
        u, v = self.axes()
        return _in_polygon(np.stack([points @ u, points @ v], -1), np.asarray(self.outline))

    def state(self) -> dict:
        outline = None if self.outline is None else [list(c) for c in self.outline]
        return {"normal": list(self.normal), "offset": self.offset, "outline": outline}

    @classmethod
    def from_state(cls, state: dict) -> Plane:
        outline = state.get("outline")
        return cls(
            tuple(float(c) for c in state["normal"]),
            float(state["offset"]),
            None if outline is None else tuple((float(a), float(b)) for a, b in outline),
        )


def _in_polygon(xy, polygon):
    """Whether each point of ``xy`` [..., 2] lies inside the convex, counter-clockwise
    ``polygon`` [E, 2] (numpy or torch alike)."""
    edge = polygon[[*range(1, len(polygon)), 0]] - polygon
    rel = xy[..., None, :] - polygon
    cross = edge[:, 0] * rel[..., 1] - edge[:, 1] * rel[..., 0]
    return (cross >= 0).all(-1)


def support_plane(
    points: np.ndarray, cameras: np.ndarray, radius: float, config: SupportConfig
) -> Plane | None:
    """The plane under ``points`` [N, 3] (see the module's text), the ``cameras`` [C, 3] all
    above it; None when no plane holds enough of them with little below. ``radius``: the
    foreground ball's, the tolerance's unit."""
    if len(points) < 3 or len(cameras) == 0:
        return None
    rng = np.random.default_rng(0)  # the session's plane, whatever the run's seed
    within = config.tolerance * radius
    needed = int(np.ceil(config.holds * len(points)))
    found: list[tuple[int, tuple[np.ndarray, float]]] = []
    for _ in range(config.tries):
        plane = _through(points[rng.choice(len(points), 3, replace=False)], cameras)
        if plane is None:
            continue
        held = _accept(plane, points, cameras, within, config.below)
        if held >= needed and _wide(plane, points, within):
            found.append((held, plane))
    if not found:
        return None
    found.sort(key=lambda f: -f[0])
    normal, offset = found[0][1]
    # three points fix a plane only to their own spread: the best few refined, the one that
    # scores best kept, if still a support
    best = None
    for _, start in found[:REFINED]:
        refined, score = _refine(start, points, within, radius, config.below_weight)
        if (best is None or score > best) and (
            _accept(refined, points, cameras, within, config.below) >= needed
            and _wide(refined, points, within)
        ):
            best, (normal, offset) = score, refined
    plane = Plane(tuple(float(c) for c in normal), float(offset))
    return replace(plane, outline=_outline(plane, points, cameras, within))


def _outline(
    plane: Plane, points: np.ndarray, cameras: np.ndarray, within: float
) -> tuple[tuple[float, float], ...]:
    """Where the support reaches, counter-clockwise: the convex hull of the feet of the points
    it holds (its marks: the far edges against what lies beyond, the contact lines and shadows
    inside) and of the cameras. A support runs on under the cameras: between its marks and the
    cameras it is one colour and makes no events, and an edge there in view would have marked
    it (one out of view, under the cameras, no view sees either). Not so when stereo points
    lie below the plane in that added part (a table's near edge, the floor seen beyond it):
    then the marks' hull alone."""
    import cv2

    normal = np.asarray(plane.normal)
    height = points @ normal - plane.offset
    u, v = plane.axes()

    def hull(p: np.ndarray) -> np.ndarray:
        h = cv2.convexHull(np.stack([p @ u, p @ v], 1).astype(np.float32))[:, 0]
        h = h.astype(np.float64)
        return h[::-1] if _area(h) < 0 else h  # OpenCV's orientation follows its y axis

    held = points[np.abs(height) < within]
    marks = hull(held)
    feet = cameras - (cameras @ normal - plane.offset)[:, None] * normal
    wider = hull(np.concatenate([held, feet]))
    below = points[height < -BELOW_BY * within]
    flat = np.stack([below @ u, below @ v], 1)
    beyond = _in_polygon(flat, wider) & ~_in_polygon(flat, marks)
    chosen = marks if beyond.sum() > BEYOND_MARKS * len(held) else wider
    return tuple((float(a), float(b)) for a, b in chosen)


def _refine(
    plane: tuple[np.ndarray, float],
    points: np.ndarray,
    within: float,
    radius: float,
    below_weight: float,
) -> tuple[tuple[np.ndarray, float], float]:
    """The plane near ``plane`` through the densest layer of the support's marks, and its score
    (the marks it holds less ``below_weight`` times those more than a tolerance under it). The
    marks: the points without structure straight above them (an object's bottom lies above the
    floor and, near the cameras, where no floor mark is, alone: least squares over all a plane
    held tilted towards them, on multi_object 1.9 deg off the floor and 13 cm over it 2 m
    towards the cameras). Nelder-Mead over a tilt along the plane's two axes and its offset, on
    the score's smooth form."""
    from scipy.optimize import minimize
    from scipy.spatial import cKDTree

    normal, offset = plane
    height = points @ normal - offset
    u, v = Plane(tuple(normal), offset).axes()
    flat = np.stack([points @ u, points @ v], 1)
    body = (height > 2 * within) & (height < BODY_REACH * radius)
    marks = points
    if body.any():
        gap = cKDTree(flat[body]).query(flat, distance_upper_bound=BODY_RADIUS * radius)[0]
        marks = points[~np.isfinite(gap)]

    def at(p: np.ndarray) -> tuple[np.ndarray, float]:
        n = normal + p[0] * u + p[1] * v
        return n / np.linalg.norm(n), float(p[2])

    def cost(p: np.ndarray) -> float:
        n, o = at(p)
        h = (marks @ n - o) / within
        held = np.exp(-0.5 * (h / HELD_WIDTH) ** 2).sum()
        below = (1 / (1 + np.exp(np.clip((h + 1) / BELOW_EDGE, -50, 50)))).sum()
        return float(below_weight * below - held)

    options = {"xatol": 1e-6, "fatol": 1e-4, "maxiter": 2000}
    n, o = at(minimize(cost, np.array([0.0, 0.0, offset]), method="Nelder-Mead", options=options).x)
    h = (marks @ n - o) / within
    return (n, o), float((np.abs(h) < 1).sum() - below_weight * (h < -1).sum())


def _area(polygon: np.ndarray) -> float:
    x, y = polygon[:, 0], polygon[:, 1]
    return 0.5 * float(np.sum(x * np.roll(y, -1) - np.roll(x, -1) * y))


def _through(three: np.ndarray, cameras: np.ndarray) -> tuple[np.ndarray, float] | None:
    normal = np.cross(three[1] - three[0], three[2] - three[0])
    norm = np.linalg.norm(normal)
    if norm < 1e-12:
        return None
    normal = normal / norm
    if np.median(cameras @ normal) < normal @ three[0]:
        normal = -normal
    return normal, float(normal @ three[0])


def _accept(
    plane: tuple[np.ndarray, float],
    points: np.ndarray,
    cameras: np.ndarray,
    within: float,
    below: float,
) -> int:
    """How many points the plane holds; 0 where a camera is not above it or too many points
    are below."""
    normal, offset = plane
    if (cameras @ normal - offset).min() <= within:
        return 0
    height = points @ normal - offset
    if (height < -BELOW_BY * within).mean() > below:
        return 0
    return int((np.abs(height) < within).sum())


def _wide(plane: tuple[np.ndarray, float], points: np.ndarray, within: float) -> bool:
    """Whether what the plane holds spreads over it (not along one line: the smaller in-plane
    spread at least a quarter of the larger) and reaches wider than what stands on it (a
    painted ring on an object is a plane too, inside the object's own outline)."""
    normal, offset = plane
    height = points @ normal - offset
    on, above = np.abs(height) < within, height >= within
    if on.sum() < 3 or above.sum() < 3:
        return bool(on.sum() >= 3)
    flat = points - height[:, None] * normal  # each point's foot on the plane
    spread = np.linalg.eigvalsh(np.cov(flat[on].T))[1:]  # the plane's two directions
    if spread[0] < 0.0625 * spread[1]:
        return False
    middle = flat[above].mean(0)
    reach = np.percentile(np.linalg.norm(flat[on] - middle, axis=1), 90)
    return bool(reach > np.percentile(np.linalg.norm(flat[above] - middle, axis=1), 90))


def on_plane(
    plane: Plane,
    ball: Ball,
    T_world_cam: np.ndarray,
    K: np.ndarray,
    width: int,
    height: int,
    n: int,
    rng: np.random.Generator,
) -> np.ndarray:
    """n points [n, 3] evenly at random on the plane inside the ball and its outline, each in
    some camera's view; none where the plane misses the ball."""
    normal, centre = np.asarray(plane.normal), np.asarray(ball.center)
    foot = centre - (centre @ normal - plane.offset) * normal
    reach2 = ball.radius**2 - float(np.sum((foot - centre) ** 2))
    if n <= 0 or reach2 <= 0:
        return np.zeros((0, 3))
    u, v = plane.axes()
    out: list[np.ndarray] = []
    for _ in range(50):  # a plane out of every view gives none, not an endless loop
        r = np.sqrt(reach2 * rng.uniform(0, 1, 4 * n))
        angle = rng.uniform(0, 2 * np.pi, 4 * n)
        pts = foot + (r * np.cos(angle))[:, None] * u + (r * np.sin(angle))[:, None] * v
        out.append(pts[plane.inside(pts) & _seen(pts, T_world_cam, K, width, height)])
        if sum(len(o) for o in out) >= n:
            break
    return np.concatenate(out)[:n]


def _seen(points: np.ndarray, T_world_cam: np.ndarray, K: np.ndarray, w: int, h: int) -> np.ndarray:
    seen = np.zeros(len(points), bool)
    for T in T_world_cam[:: max(1, len(T_world_cam) // 16)]:
        cam = (points - T[:3, 3]) @ T[:3, :3]
        z = np.maximum(cam[:, 2], 1e-9)
        x, y = K[0, 0] * cam[:, 0] / z + K[0, 2], K[1, 1] * cam[:, 1] / z + K[1, 2]
        seen |= (cam[:, 2] > 0) & (x >= 0) & (x < w) & (y >= 0) & (y < h)
    return seen


def rays_meet(
    plane: Plane, ball: Ball, directions: torch.Tensor, origin: torch.Tensor
) -> torch.Tensor:
    """[h, w] bool: the rays from ``origin`` [3] along ``directions`` [h, w, 3] that meet the
    plane inside the ball and the plane's outline."""
    normal = directions.new_tensor(plane.normal)
    centre = directions.new_tensor(ball.center)
    along = directions @ normal
    t = (plane.offset - origin @ normal) / torch.where(along.abs() > 1e-9, along, 1e-9)
    hit = origin + t[..., None] * directions
    meets = (t > 0) & ((hit - centre).norm(dim=-1) <= ball.radius)
    if plane.outline is None:
        return meets
    u, v = (directions.new_tensor(a) for a in plane.axes())
    inside = _in_polygon(torch.stack([hit @ u, hit @ v], -1), directions.new_tensor(plane.outline))
    return meets & inside
