"""The environment's specular light shared between renders close in time.

The specular integral (integrals.specular_environment: side x side GGX samples a pixel) is most
of a render's cost, and the simulator renders the scene every half pixel of image motion. Where
a pixel sees the same smooth surface through a short stretch of the camera's path, the integral
changes smoothly with time; computed exactly at the stretch's two ends, it is interpolated
linearly between them. A pixel gets the exact integral instead where what it sees is not the
same surface: another object or material at either end, a normal that bends off the line
between the ends' normals by more than MAX_BEND_DEG, or a hit that lies off the line between
the ends' hits by more than MAX_OFF_LINE of its distance (a fold, an edge of the same object).
The error this leaves is measured against the exact integral on every bundled scene
(bench/sim_throughput.py) and bounded in tests/sim/test_specular_reuse.py.
"""

from __future__ import annotations

from dataclasses import dataclass

import numba
import numpy as np

from evcap.sim.render import Renderer, SpecularInputs

MAX_BEND_DEG = 0.5  # a normal this far off the interpolated one: not the same smooth surface
MAX_OFF_LINE = 0.002  # a hit this far (over its distance) off the line between the ends' hits
# the light changing by more than this between the ends (a light of about 1): it may not change
# linearly (a narrow lobe crossing the horizon, a contact shadow's edge)
MAX_CHANGE = 0.02


@dataclass
class SpecularFrame:
    """A render's environment specular light at every pixel, with what it depends on
    (obj -1 where the pixel sees no surface)."""

    obj: np.ndarray  # [P]
    roughness: np.ndarray  # [P]
    normal: np.ndarray  # [P, 3] world frame
    point: np.ndarray  # [P, 3] world frame
    specular: np.ndarray  # [P, 3]

    @classmethod
    def of(cls, n_pixels: int, inputs: SpecularInputs, specular: np.ndarray) -> SpecularFrame:
        """The frame of a full render's specular inputs (rows: pixel indices) and light."""
        frame = cls(
            np.full(n_pixels, -1, np.int64),
            np.zeros(n_pixels),
            np.zeros((n_pixels, 3)),
            np.zeros((n_pixels, 3)),
            np.zeros((n_pixels, 3)),
        )
        rows = inputs.rows
        frame.obj[rows] = inputs.obj
        frame.roughness[rows] = inputs.roughness
        frame.normal[rows] = inputs.normal
        frame.point[rows] = inputs.point
        frame.specular[rows] = specular
        return frame


def specular_between(
    renderer: Renderer,
    a: SpecularFrame,
    b: SpecularFrame,
    s: np.ndarray | float,
    inputs: SpecularInputs,
    pixels: np.ndarray,
) -> tuple[np.ndarray, int]:
    """([H, 3] the environment's specular light at the hits at ``pixels``, a fraction ``s`` of
    the way from ``a``'s time to ``b``'s: interpolated on the same surface, else exact; how
    many were exact)."""
    out = np.empty((len(pixels), 3))
    same = np.empty(len(pixels), np.bool_)
    _interpolate(
        a.obj,
        a.roughness,
        a.normal,
        a.point,
        a.specular,
        b.obj,
        b.roughness,
        b.normal,
        b.point,
        b.specular,
        np.ascontiguousarray(np.broadcast_to(np.asarray(s, np.float64), pixels.shape)),
        np.ascontiguousarray(pixels, np.int64),
        inputs.obj,
        inputs.roughness,
        np.ascontiguousarray(inputs.normal),
        np.ascontiguousarray(inputs.point),
        inputs.distance,
        np.cos(np.deg2rad(MAX_BEND_DEG)),
        MAX_OFF_LINE,
        MAX_CHANGE,
        same,
        out,
    )
    exact = ~same
    if exact.any():
        out[exact] = renderer.environment_specular(inputs.take(exact))
    return out, int(exact.sum())


@numba.njit(cache=True, parallel=True)
def _interpolate(
    a_obj, a_rough, a_n, a_x, a_spec, b_obj, b_rough, b_n, b_x, b_spec, s, pixels,
    obj, rough, n, x, distance, min_cos, off_line, max_change, same, out,
):  # fmt: skip  # pragma: no cover - compiled
    """same[i]: whether hit i lies on the surface the pixel saw in both frames (the same
    object and roughness, its normal within acos(min_cos) of the interpolated one, its point
    within off_line x distance of the interpolated one) and the light there changed by at most
    max_change between them; out[i]: the interpolated light."""
    for i in numba.prange(len(pixels)):
        p, w = pixels[i], s[i]
        ok = a_obj[p] == obj[i] and b_obj[p] == obj[i]
        ok = ok and a_rough[p] == rough[i] and b_rough[p] == rough[i]
        if ok:
            m0 = a_n[p, 0] * (1 - w) + b_n[p, 0] * w
            m1 = a_n[p, 1] * (1 - w) + b_n[p, 1] * w
            m2 = a_n[p, 2] * (1 - w) + b_n[p, 2] * w
            dot = m0 * n[i, 0] + m1 * n[i, 1] + m2 * n[i, 2]
            ok = dot >= min_cos * np.sqrt(m0 * m0 + m1 * m1 + m2 * m2)
        if ok:
            for k in range(3):
                ok = ok and abs(a_spec[p, k] - b_spec[p, k]) <= max_change
        if ok:
            off = 0.0
            for k in range(3):
                d = a_x[p, k] * (1 - w) + b_x[p, k] * w - x[i, k]
                off += d * d
            ok = off <= (off_line * distance[i]) ** 2
        same[i] = ok
        if ok:
            for k in range(3):
                out[i, k] = a_spec[p, k] * (1 - w) + b_spec[p, k] * w
