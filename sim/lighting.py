"""Light: the environment (an analytic sky, or an equirectangular image), the sun and point
lights, and the integrals the renderer needs for Lambert + GGX shading.

World axes: z is up. Radiance is linear RGB. The environment is integrated numerically
(irradiance: a fixed Fibonacci set of directions; specular: GGX importance sampling into
prefiltered maps, and the split-sum DFG table); the sun and point lights are analytic.
All sample sets are fixed, so a rendered value is a smooth function of the view: no Monte
Carlo noise from frame to frame (it would fire events).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from evcap.errors import InputError
from evcap.sim.scene import Lighting

F0 = 0.04  # normal-incidence Fresnel reflectance of a dielectric (metallic = 0)


def fibonacci_sphere(n: int) -> np.ndarray:
    """``n`` nearly uniform unit directions."""
    k = np.arange(n) + 0.5
    z = 1 - 2 * k / n
    phi = np.pi * (1 + 5**0.5) * k
    r = np.sqrt(1 - z * z)
    return np.stack([r * np.cos(phi), r * np.sin(phi), z], 1)


def hammersley(n: int) -> np.ndarray:
    bits = np.arange(n, dtype=np.uint32)
    rev = np.zeros(n, np.float64)
    for b in range(32):
        rev += ((bits >> b) & 1) * 2.0 ** (-b - 1)
    return np.stack([(np.arange(n) + 0.5) / n, rev], 1)


def srgb_to_linear(c: np.ndarray) -> np.ndarray:
    return np.where(c <= 0.04045, c / 12.92, ((c + 0.055) / 1.055) ** 2.4)


def read_image_linear(path: Path) -> np.ndarray:
    """An image as linear RGB float (HDR files as they are, 8/16-bit ones from sRGB)."""
    import cv2

    img = cv2.imread(str(path), cv2.IMREAD_ANYCOLOR | cv2.IMREAD_ANYDEPTH | cv2.IMREAD_UNCHANGED)
    if img is None:
        raise InputError(f"{path}: cannot read the image")
    if img.ndim == 2:
        img = np.repeat(img[..., None], 3, axis=2)
    img = img[..., :3][..., ::-1]  # BGR -> RGB
    if img.dtype == np.uint8:
        return srgb_to_linear(img.astype(np.float64) / 255)
    if img.dtype == np.uint16:
        return srgb_to_linear(img.astype(np.float64) / 65535)
    return img.astype(np.float64)


class Environment:
    """Radiance arriving from each direction, and the sun."""

    def __init__(self, spec: Lighting) -> None:
        self.spec = spec
        self.scale = spec.intensity
        c, s = np.cos(np.deg2rad(spec.rotation_deg)), np.sin(np.deg2rad(spec.rotation_deg))
        self.rotation = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1.0]])
        self.image = None
        sky = dict(spec.sky)
        if spec.environment != "sky":
            self.image = read_image_linear(Path(spec.environment))
        known = {"zenith", "horizon", "ground", "sun_direction", "sun_irradiance", "sun_radius_deg"}
        if set(sky) - known:
            raise InputError(f"lighting.sky: unknown key(s) {', '.join(sorted(set(sky) - known))}")
        self.zenith = np.asarray(sky.get("zenith", [0.35, 0.55, 1.0]), np.float64)
        self.horizon = np.asarray(sky.get("horizon", [0.9, 0.9, 0.85]), np.float64)
        self.ground = np.asarray(sky.get("ground", [0.25, 0.22, 0.2]), np.float64)
        sun = np.asarray(sky.get("sun_direction", [0.4, -0.3, 0.8]), np.float64)
        self.sun_direction = sun / np.linalg.norm(sun)
        irr = sky.get("sun_irradiance", 0.0)
        self.sun_irradiance = np.broadcast_to(np.asarray(irr, np.float64), (3,)).copy()
        self.sun_radius = np.deg2rad(float(sky.get("sun_radius_deg", 0.5)))

    def radiance(self, dirs: np.ndarray) -> np.ndarray:
        """[N, 3] world directions -> [N, 3] radiance (without the sun, which is analytic)."""
        d = dirs @ self.rotation  # into the environment's own frame
        if self.image is not None:
            h, w = self.image.shape[:2]
            u = (np.arctan2(d[:, 1], d[:, 0]) / (2 * np.pi) + 0.5) * w - 0.5
            v = (0.5 - np.arcsin(np.clip(d[:, 2], -1, 1)) / np.pi) * h - 0.5
            x0, y0 = np.floor(u).astype(int), np.clip(np.floor(v).astype(int), 0, h - 1)
            fx, fy = u - x0, np.clip(v - y0, 0, 1)
            y1 = np.clip(y0 + 1, 0, h - 1)
            x0, x1 = x0 % w, (x0 + 1) % w
            img = self.image
            out = (img[y0, x0] * (1 - fx)[:, None] + img[y0, x1] * fx[:, None]) * (1 - fy)[
                :, None
            ] + (img[y1, x0] * (1 - fx)[:, None] + img[y1, x1] * fx[:, None]) * fy[:, None]
            return out * self.scale
        z = d[:, 2:3]
        up = np.clip(z, 0, 1) ** 0.5
        sky = self.horizon + (self.zenith - self.horizon) * up
        # a smooth blend into the ground below the horizon (no discontinuity to fire events)
        below = np.clip(-z / 0.05, 0, 1)
        return (sky * (1 - below) + self.ground * below) * self.scale

    def background(self, dirs: np.ndarray) -> np.ndarray:
        """What a camera sees of the environment: the radiance, and the sun's disk."""
        out = self.radiance(dirs)
        if self.image is None and self.sun_irradiance.any():
            cos = dirs @ self.sun_direction
            solid = 2 * np.pi * (1 - np.cos(self.sun_radius))
            edge = np.clip(
                (cos - np.cos(self.sun_radius * 1.2))
                / (np.cos(self.sun_radius) - np.cos(self.sun_radius * 1.2)),
                0,
                1,
            )
            out = out + edge[:, None] * self.sun_irradiance * self.scale / solid
        return out

    # -- the integrals the renderer uses ------------------------------------------------------

    def irradiance(
        self, normals: np.ndarray, samples: int = 256, visible: np.ndarray | None = None
    ) -> np.ndarray:
        """Irradiance from the environment at surfaces with these normals, through the fixed
        directions of ``fibonacci_sphere(samples)``; ``visible`` [N, samples] masks the
        directions that reach the sky."""
        dirs = fibonacci_sphere(samples)
        radiance = self.radiance(dirs)  # [S, 3]
        cos = np.clip(normals @ dirs.T, 0, None)  # [N, S]
        if visible is not None:
            cos = cos * visible
        return cos @ radiance * (4 * np.pi / samples)

    def prefilter(
        self, roughness_levels: np.ndarray, size: tuple[int, int] = (64, 32), samples: int = 256
    ) -> np.ndarray:
        """GGX-prefiltered environment [levels, h, w, 3] on a lat-long grid (n = v = r)."""
        w, h = size
        u, v = np.meshgrid((np.arange(w) + 0.5) / w, (np.arange(h) + 0.5) / h)
        phi, lat = (u - 0.5) * 2 * np.pi, (0.5 - v) * np.pi
        n = (
            np.stack(
                [np.cos(lat) * np.cos(phi), np.cos(lat) * np.sin(phi), np.sin(lat)], -1
            ).reshape(-1, 3)
            @ self.rotation.T
        )
        t1, t2 = _tangents(n)
        xi = hammersley(samples)
        out = []
        for rough in roughness_levels:
            a = max(rough, 0.02) ** 2
            cos_h = np.sqrt((1 - xi[:, 1]) / (1 + (a * a - 1) * xi[:, 1]))
            sin_h = np.sqrt(1 - cos_h**2)
            ph = 2 * np.pi * xi[:, 0]
            hl = np.stack([sin_h * np.cos(ph), sin_h * np.sin(ph), cos_h], 1)  # [S, 3]
            total = np.zeros((len(n), 3))
            weight = np.zeros(len(n))
            for s in range(samples):
                half = t1 * hl[s, 0] + t2 * hl[s, 1] + n * hl[s, 2]
                light = 2 * (n * half).sum(1, keepdims=True) * half - n
                ndl = (n * light).sum(1)
                ok = ndl > 0
                total[ok] += self.radiance(light[ok]) * ndl[ok, None]
                weight[ok] += ndl[ok]
            out.append((total / np.maximum(weight, 1e-12)[:, None]).reshape(h, w, 3))
        return np.stack(out)


def _tangents(n: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    a = np.where(np.abs(n[:, 2:3]) < 0.999, np.array([[0, 0, 1.0]]), np.array([[1.0, 0, 0]]))
    t1 = np.cross(a, n)
    t1 /= np.linalg.norm(t1, axis=1, keepdims=True)
    return t1, np.cross(n, t1)


def dfg_table(size: int = 32, samples: int = 256) -> np.ndarray:
    """The split-sum table [n.v, roughness] -> (A, B): specular = prefiltered * (F0 A + B)."""
    xi = hammersley(samples)
    table = np.zeros((size, size, 2))
    for i, ndv in enumerate((np.arange(size) + 0.5) / size):
        v = np.array([np.sqrt(1 - ndv * ndv), 0.0, ndv])
        for j, rough in enumerate((np.arange(size) + 0.5) / size):
            a = max(rough, 0.02) ** 2
            cos_h = np.sqrt((1 - xi[:, 1]) / (1 + (a * a - 1) * xi[:, 1]))
            sin_h = np.sqrt(1 - cos_h**2)
            ph = 2 * np.pi * xi[:, 0]
            h = np.stack([sin_h * np.cos(ph), sin_h * np.sin(ph), cos_h], 1)
            vdh = h @ v
            light = 2 * vdh[:, None] * h - v
            ndl, ndh = np.clip(light[:, 2], 0, 1), np.clip(h[:, 2], 0, 1)
            ok = ndl > 0
            g = smith_g(ndv, ndl[ok], a)
            g_vis = g * vdh[ok] / np.maximum(ndh[ok] * ndv, 1e-12)
            fc = (1 - vdh[ok]) ** 5
            table[i, j, 0] = ((1 - fc) * g_vis).sum() / samples
            table[i, j, 1] = (fc * g_vis).sum() / samples
    return table


def smith_g(ndv, ndl, alpha):
    """Smith's height-correlated-free (separable) GGX masking-shadowing G(n.v) G(n.l)."""
    k = alpha * alpha
    gv = 2 * ndv / (ndv + np.sqrt(k + (1 - k) * ndv * ndv))
    gl = 2 * ndl / (ndl + np.sqrt(k + (1 - k) * ndl * ndl))
    return gv * gl


def ggx_specular(n, v, light, roughness) -> np.ndarray:
    """Cook-Torrance GGX BRDF times n.l, per row (dielectric, F0 = 0.04), for a light
    direction ``light``; [N] values to multiply by the light's irradiance."""
    h = v + light
    h /= np.maximum(np.linalg.norm(h, axis=1, keepdims=True), 1e-12)
    ndl = np.clip((n * light).sum(1), 0, 1)
    ndv = np.clip((n * v).sum(1), 1e-4, 1)
    ndh = np.clip((n * h).sum(1), 0, 1)
    vdh = np.clip((v * h).sum(1), 0, 1)
    a = np.maximum(roughness, 0.02) ** 2
    d = a * a / (np.pi * (ndh * ndh * (a * a - 1) + 1) ** 2)
    f = F0 + (1 - F0) * (1 - vdh) ** 5
    g = smith_g(ndv, ndl, a)
    return d * f * g / np.maximum(4 * ndv, 1e-12) * (ndl > 0)
