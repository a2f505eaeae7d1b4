"""The ground truth's Monte Carlo integrals: known answers, and converged below the sensor's
noise at the sample counts the renderer uses."""

import numpy as np
import pytest

from evcap.sim import integrals
from evcap.sim.lighting import Environment
from evcap.sim.scene import RELIGHT_SKY, Lighting

SKY = {"zenith": [0.35, 0.55, 1.0], "horizon": [0.95, 0.92, 0.85], "ground": [0.3, 0.25, 0.2]}
SKIES = pytest.mark.parametrize("sky", [SKY, RELIGHT_SKY], ids=["scenes", "relight"])


def directions(n: int, seed: int = 0) -> np.ndarray:
    d = np.random.default_rng(seed).normal(size=(n, 3))
    return d / np.linalg.norm(d, axis=1, keepdims=True)


def irradiance(env: Environment, normals: np.ndarray, count: int) -> np.ndarray:
    local = integrals.cosine_cells(*integrals.cell_grid(count))
    dirs = np.einsum("ci,vij->vcj", local, integrals.frames(normals))
    return env.radiance(dirs.reshape(-1, 3)).reshape(len(normals), -1, 3).mean(1) * np.pi


def views(normals: np.ndarray, seed: int = 1) -> np.ndarray:
    v = directions(len(normals), seed)
    return np.where(((normals * v).sum(1) < 0)[:, None], -v, v)


def test_cosine_cells_tile_the_hemisphere_evenly():
    rings, sectors = integrals.cell_grid(256)
    local = integrals.cosine_cells(rings, sectors)
    assert len(local) == rings * sectors >= 250
    np.testing.assert_allclose(np.linalg.norm(local, axis=1), 1, atol=1e-12)
    cells = [integrals.cell_of(*d, rings, sectors) for d in local]
    np.testing.assert_array_equal(cells, np.arange(len(local)))
    # equal cosine-weighted measure: the mean of cos over the cells is E[cos] = 2/3
    assert local[:, 2].mean() == pytest.approx(2 / 3, abs=2e-3)


def test_uniform_sky_irradiance_is_pi_and_a_smooth_mirror_reflects_f0():
    white = Environment(Lighting(sky={"zenith": [1] * 3, "horizon": [1] * 3, "ground": [1] * 3}))
    n = directions(200)
    np.testing.assert_allclose(irradiance(white, n, 256), np.pi, rtol=1e-9)
    spec = integrals.specular_environment(white.table(64), n, n, np.full(200, 0.02))
    np.testing.assert_allclose(spec, 0.04, rtol=0.02)  # head-on: Fresnel F0, nothing masked
    # rough and grazing: less than all of the light comes back, never more
    v = views(n)
    spec = integrals.specular_environment(white.table(64), n, v, np.full(200, 1.0))
    assert (spec > 0).all() and (spec < 1).all()


@SKIES
def test_diffuse_cells_converged_below_the_sensors_noise(sky):
    # 256 cells against 16k on the scenes' sky and on the relighting's glow from one side: the
    # threshold's pixel-to-pixel spread is 0.03 in log intensity, so 1 % of the light is a third.
    # (16k cells are within 0.0005 of 64k at the 99th percentile, a twentieth of the bound.)
    env = Environment(Lighting(sky=sky))
    n = directions(1000)
    ref, est = irradiance(env, n, 16384), irradiance(env, n, 256)
    err = np.abs(est - ref).sum(1) / ref.sum(1)
    assert np.median(err) < 0.003 and np.quantile(err, 0.99) < 0.012


@SKIES
@pytest.mark.parametrize("roughness", [0.1, 0.25, 0.5, 1.0])
def test_specular_samples_converged_below_the_sensors_noise(roughness, sky):
    # the renderer's 12 x 12 samples against 96 x 96; the sky's light is about 1 (the glow's 2)
    env = Environment(Lighting(sky=sky))
    table = env.table()
    n = directions(1000)
    v = views(n)
    r = np.full(len(n), roughness)
    ref = integrals.specular_environment(table, n, v, r, side=96)
    est = integrals.specular_environment(table, n, v, r)
    err = np.abs(est - ref).max(1)
    assert np.median(err) < 0.001 and np.quantile(err, 0.99) < 0.007
