"""The specular light shared between key renders: within a small fraction of a threshold of the
exact integral, and exact wherever a pixel's surface changes."""

import numpy as np
import pytest

from evcap.sim import integrals
from evcap.sim.scene import load_scene
from evcap.sim.simulate import Simulator
from evcap.sim.specular_reuse import SpecularFrame, specular_between

SCENE = """
[scene]
name = "reuse"
seed = 3
[camera]
width = 120
height = 90
fx = 100.0
[trajectory]
kind = "orbit"
radius = 2.2
height = 0.8
height_swing = 0.3
degrees = 60.0
duration_s = 0.5
[lighting]
environment = "sky"
shadows = true
indirect = true
[materials.glossy]
base_color = [0.7, 0.3, 0.2]
roughness = 0.15
[materials.matte]
base_color = [0.6, 0.6, 0.6]
roughness = 0.7
[[objects]]
type = "sphere"
center = [0.0, 0.0, 0.5]
radius = 0.5
material = "glossy"
[[objects]]
type = "plane"
center = [0.0, 0.0, 0.0]
size = [4.0, 4.0]
material = "matte"
"""


@pytest.fixture(scope="module")
def stretch(tmp_path_factory):
    """The key renders between two anchors, each with its exact specular light."""
    path = tmp_path_factory.mktemp("reuse") / "scene.toml"
    path.write_text(SCENE)
    sim = Simulator(load_scene(path))
    times = [0.2e6]
    times += sim._key_times(times[0], 0.5e6)
    renders = [sim._render(t) for t in times]
    exact = [sim.renderer.environment_specular(r.specular_inputs) for r in renders]
    n = sim.camera.width * sim.camera.height
    ends = [SpecularFrame.of(n, renders[i].specular_inputs, exact[i]) for i in (0, -1)]
    return sim, times, renders, exact, ends


def test_shared_light_within_a_small_part_of_a_threshold(stretch):
    sim, times, renders, exact, (a, b) = stretch
    errors, integrated, total, off_dense = [], 0, 0, []
    rr = sim.renderer
    for t, r, truth in zip(times[1:-1], renders[1:-1], exact[1:-1], strict=True):
        inputs = r.specular_inputs
        s = (t - times[0]) / (times[-1] - times[0])
        shared, count = specular_between(rr, a, b, s, inputs, inputs.rows)
        rest = r.radiance[inputs.rows]
        e = np.abs(np.log(rest + shared + 1e-3) - np.log(rest + truth + 1e-3)).max(1)
        errors.append(e)
        integrated, total = integrated + count, total + len(inputs.rows)
        # where sharing differs most from the renderer's estimate: against 16 times its samples
        worst = inputs.take(np.argsort(e)[-20:])
        sky = (worst.triangle, worst.weights, rr.vertex_frames, rr.vertex_open, *rr.cells)
        dense = integrals.specular_environment(
            rr.sky_table, worst.normal, worst.view, worst.roughness, 48, sky
        )
        off_dense.append(np.abs(shared[np.argsort(e)[-20:]] - dense).max(1))
    e = np.concatenate(errors)
    # the threshold is about 0.2 in log radiance; the Monte Carlo estimate itself is good to
    # about 0.007 of a light of 1 at the 99th percentile (test_integrals)
    assert np.quantile(e, 0.99) < 0.004 and e.max() < 0.05
    assert np.concatenate(off_dense).max() < 0.007
    assert integrated < 0.1 * total  # most of the light is shared


def test_light_interpolated_in_time_not_reused_as_it_was(stretch):
    # holding the first anchor's light instead of interpolating is measurably worse: the
    # bound above can fail
    sim, times, renders, exact, (a, b) = stretch
    r, truth = renders[len(times) // 2], exact[len(times) // 2]
    inputs = r.specular_inputs
    s = (times[len(times) // 2] - times[0]) / (times[-1] - times[0])
    shared, _ = specular_between(sim.renderer, a, b, s, inputs, inputs.rows)
    held = a.specular[inputs.rows]
    assert np.abs(shared - truth).mean() < 0.5 * np.abs(held - truth).mean()


def test_exact_where_the_surface_changes(stretch):
    sim, times, renders, exact, (a, b) = stretch
    r, truth = renders[1], exact[1]
    inputs = r.specular_inputs
    s = (times[1] - times[0]) / (times[-1] - times[0])
    px = inputs.rows
    # pixels whose object differs between the anchors: the sphere's outline moving
    changed = (a.obj[px] != inputs.obj) | (b.obj[px] != inputs.obj)
    assert changed.sum() > 10
    shared, count = specular_between(sim.renderer, a, b, s, inputs, px)
    assert count >= changed.sum()
    np.testing.assert_allclose(shared[changed], truth[changed], rtol=1e-12, atol=1e-12)
