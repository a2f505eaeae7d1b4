"""Densification's pruning: what leaves the foreground's ball goes, through the run, and what
never shows (its largest blending weight under densify.min_weight)."""

import numpy as np
import pytest
import torch

from evcap.errors import InputError
from evcap.recon.radiance.densify import DefaultStrategy, DensifyConfig
from evcap.recon.raster.rasterize import Render
from evcap.recon.scene.gaussians import Background, Gaussians, LearningRates, make_optimizer
from evcap.recon.scene.optics import RenderGrid
from evcap.recon.scene.volume import Ball


def strategy(confine: float, min_weight: float = 0.0) -> DefaultStrategy:
    config = DensifyConfig(start=0.1, stop=0.5, every=10, confine=confine, min_weight=min_weight)
    return DefaultStrategy.for_run(config, 100, 1.0, Ball((1.0, 0.0, 0.0), 0.5))


def field(points: np.ndarray):
    gaussians = Gaussians.random(points, 0, torch.Generator().manual_seed(0), 0.01)
    optimizer = make_optimizer(gaussians, Background(4), LearningRates(), 1.0)
    return gaussians, optimizer


def test_gaussians_that_leave_the_foreground_are_pruned_to_the_end_of_the_run():
    rng = np.random.default_rng(0)
    inner = np.array([1.0, 0, 0]) + rng.uniform(-0.2, 0.2, (50, 3))
    outer = np.array([1.0, 0, 0]) + rng.uniform(0.7, 1.0, (10, 3))
    gaussians, optimizer = field(np.concatenate([inner, outer]))
    s = strategy(confine=1.2)  # 0.6 about (1, 0, 0)
    state = s.initialize_state()
    grid = RenderGrid.__new__(RenderGrid)  # no render this test: no gradients observed
    s.step_post_backward(gaussians, optimizer, state, 20, [], grid)  # a densification
    assert len(gaussians) == 50
    with torch.no_grad():  # one drifts out after densification stopped
        gaussians.means[0] = torch.tensor([3.0, 0, 0])
    s.step_post_backward(gaussians, optimizer, state, 85, [], grid)  # not a multiple of 10
    assert len(gaussians) == 50
    s.step_post_backward(gaussians, optimizer, state, 90, [], grid)
    assert len(gaussians) == 49 and len(optimizer.param_groups[0]["params"][0]) == 49
    assert len(state["grad_sum"]) == 49


def test_unconfined_keeps_them():
    gaussians, optimizer = field(np.random.default_rng(1).uniform(-5, 5, (40, 3)))
    s = strategy(confine=0.0)
    assert s.confine_radius == 0
    state = s.initialize_state()
    s.step_post_backward(gaussians, optimizer, state, 90, [], RenderGrid.__new__(RenderGrid))
    assert len(gaussians) == 40


def render_with_peaks(peak: list[float]) -> Render:
    """A render's part that densification reads: no gradient, these largest weights."""
    n = len(peak)
    means2d = torch.zeros(n, 2, requires_grad=True)
    means2d.grad = torch.zeros(n, 2)
    nothing = torch.zeros(1, 1)
    return Render(nothing, nothing, nothing, nothing, means2d, torch.ones(n, dtype=torch.bool),
                  torch.tensor(peak))  # fmt: skip


def test_gaussians_that_never_show_are_pruned():
    gaussians, optimizer = field(np.random.default_rng(2).uniform(0.8, 1.2, (4, 3)))
    s = strategy(confine=0.0, min_weight=0.1)
    state = s.initialize_state()
    grid = RenderGrid.__new__(RenderGrid)
    grid.width = grid.height = 8
    s.step_post_backward(gaussians, optimizer, state, 20, [], grid)  # no view counted: all kept
    assert len(gaussians) == 4
    with torch.no_grad():
        gaussians.opacity_logits[:] = 3.0  # not pruned for their opacity
    kept = gaussians.means.detach()[[0, 2]].clone()
    s.step_post_backward(gaussians, optimizer, state, 21, [render_with_peaks([0.3, 0, 0, 0])], grid)
    s.step_post_backward(
        gaussians, optimizer, state, 30, [render_with_peaks([0, 0.05, 0.2, 0])], grid
    )
    assert torch.equal(gaussians.means.detach(), kept)  # the largest over the views counts
    assert len(state["peak"]) == 2 and state["views"] == 0
    # after densification stops, a Gaussian that fades goes too
    s.step_post_backward(gaussians, optimizer, state, 90, [render_with_peaks([0.5, 0.09])], grid)
    assert len(gaussians) == 1


def test_a_blending_weight_of_one_is_refused():
    with pytest.raises(InputError, match="densify.min_weight"):
        DensifyConfig(min_weight=1.0)


def test_a_given_box_holds_the_foreground():
    config = DensifyConfig(start=0.1, stop=0.5, every=10, bounds=(0.5, -1, -1, 1.5, 1, 1))
    s = DefaultStrategy.for_run(config, 100, 1.0, None)  # no ball: the box alone
    points = np.array([[1.0, 0, 0], [1.4, 0.9, -0.9], [1.6, 0, 0], [1.0, 0, 1.2]])
    gaussians, optimizer = field(points)
    state = s.initialize_state()
    s.step_post_backward(gaussians, optimizer, state, 20, [], RenderGrid.__new__(RenderGrid))
    assert torch.equal(gaussians.means.detach(), torch.tensor(points[:2], dtype=torch.float32))
