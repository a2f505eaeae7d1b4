"""Densification's confinement: what leaves the foreground's ball goes, through the run."""

import numpy as np
import torch

from evcap.recon.radiance.densify import DefaultStrategy, DensifyConfig
from evcap.recon.scene.gaussians import Background, Gaussians, LearningRates, make_optimizer
from evcap.recon.scene.optics import RenderGrid
from evcap.recon.scene.volume import Ball


def strategy(confine: float) -> DefaultStrategy:
    config = DensifyConfig(start=0.1, stop=0.5, every=10, confine=confine)
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
