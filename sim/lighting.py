"""Light: the environment (an analytic sky, or an equirectangular image), the sun and point
lights, and the GGX reflectance (metallic 0) the renderer shades with.

World axes: z is up. Radiance is linear RGB. The environment's integrals are in
evcap.sim.integrals; the sun and point lights are analytic.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from evcap.errors import InputError
from evcap.images import read_image_linear
from evcap.sim.scene import Lighting

F0 = 0.04  # normal-incidence Fresnel reflectance of a dielectric (metallic = 0)


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
        known = {
            "zenith",
            "horizon",
            "ground",
            "sun_direction",
            "sun_irradiance",
            "sun_radius_deg",
            "lobe_direction",
            "lobe_radiance",
            "lobe_width_deg",
        }
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
        # a broad glow from one side (a window, a lamp behind a diffuser): light with a direction
        # that a smooth environment table still holds
        lobe = np.asarray(sky.get("lobe_direction", [1.0, 0.0, 0.0]), np.float64)
        self.lobe_direction = lobe / np.linalg.norm(lobe)
        lobe_rgb = sky.get("lobe_radiance", 0.0)
        self.lobe_radiance = np.broadcast_to(np.asarray(lobe_rgb, np.float64), (3,)).copy()
        self.lobe_width = np.deg2rad(float(sky.get("lobe_width_deg", 30.0)))

    def radiance(self, dirs: np.ndarray) -> np.ndarray:
        """[N, 3] world directions -> [N, 3] radiance (without the sun, which is analytic)."""
        # into the environment's own frame
        d = dirs if self.spec.rotation_deg == 0 else dirs @ self.rotation
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
        out = self.horizon + (self.zenith - self.horizon) * np.sqrt(np.clip(z, 0, 1))
        # a smooth blend into the ground below the horizon (no discontinuity to fire events)
        out += (self.ground - out) * np.clip(-z / 0.05, 0, 1)
        if self.lobe_radiance.any():
            # falls to 1/e at lobe_width from its direction
            fall = (1 - d @ self.lobe_direction) / (1 - np.cos(self.lobe_width))
            out = out + np.exp(-fall)[:, None] * self.lobe_radiance
        return out * self.scale

    def table(self, width: int = 1024) -> np.ndarray:
        """The radiance [width / 2, width, 3] on a latitude-longitude grid of world directions
        (azimuth from +x, top row the zenith; texel centres), for compiled lookups."""
        h = width // 2
        lat = (0.5 - (np.arange(h) + 0.5) / h) * np.pi
        lon = ((np.arange(width) + 0.5) / width - 0.5) * 2 * np.pi
        lat, lon = np.meshgrid(lat, lon, indexing="ij")
        dirs = np.stack([np.cos(lat) * np.cos(lon), np.cos(lat) * np.sin(lon), np.sin(lat)], -1)
        return self.radiance(dirs.reshape(-1, 3)).reshape(h, width, 3)

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


def tangents(n: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    a = np.where(np.abs(n[:, 2:3]) < 0.999, np.array([[0, 0, 1.0]]), np.array([[1.0, 0, 0]]))
    t1 = np.cross(a, n)
    t1 /= np.linalg.norm(t1, axis=1, keepdims=True)
    return t1, np.cross(n, t1)


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
