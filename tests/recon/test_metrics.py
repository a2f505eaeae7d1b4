"""The object figures: what a render scores on the object's pixels, beside a constant color,
and the blurred truth over the whole image."""

import numpy as np
import pytest

from evcap.images import fit_color_correction, fit_gain
from evcap.recon.evaluate.metrics import (
    background_clear,
    blur_psnr,
    depth_rel_err,
    depth_within,
    object_metrics,
    psnr,
    silhouette_iou,
    srgb,
)
from evcap.records import TruthViews


@pytest.fixture(scope="module")
def scene() -> tuple[np.ndarray, np.ndarray]:
    """Two 40 x 60 views: a checkered disc (the object, at depth 2) on a smooth environment."""
    y, x = np.mgrid[:40, :60]
    disc = (x - 30) ** 2 + (y - 20) ** 2 < 14**2
    checker = ((x // 4 + y // 4) % 2).astype(float)
    sky = np.stack([0.3 + 0.2 * x / 60, 0.4 + 0.0 * x, 0.5 - 0.2 * y / 40], -1)
    image = np.where(disc[..., None], 0.1 + 0.6 * checker[..., None] * [1.0, 0.8, 0.5], sky)
    radiance = np.stack([image, image[:, ::-1]]).astype(np.float32)
    depth = np.stack([np.where(disc, 2.0, 0.0)] * 2).astype(np.float32)
    return radiance, depth


def test_the_truth_scores_far_above_a_constant(scene):
    radiance, depth = scene
    m = object_metrics(radiance, radiance, depth > 0)
    assert m["object_psnr_gain"] > 60 and m["object_ssim_gain"] > 0.99
    assert m["object_psnr_constant"] < 15  # the checker: 0.1 against 0.7 at its brightest


def test_a_constant_object_scores_no_better_than_the_constant(scene):
    radiance, depth = scene
    pred = radiance.copy()
    pred[depth > 0] = radiance[depth > 0].mean(0)
    m = object_metrics(pred, radiance, depth > 0)
    assert m["object_psnr_gain"] <= m["object_psnr_constant"] + 0.5
    assert m["object_ssim_gain"] < 0.5


def test_the_environment_does_not_count(scene):
    radiance, depth = scene
    pred = radiance.copy()
    pred[depth == 0] = 0.0  # a black environment; the object as it is
    m = object_metrics(pred, radiance, depth > 0)
    assert m["object_psnr_gain"] > 60


def test_one_gain_forgives_a_gain_per_channel_and_the_affine_diagnostic_also_haze(scene):
    radiance, depth = scene
    tinted = object_metrics(radiance * np.array([0.5, 1.2, 0.8]), radiance, depth > 0)
    assert tinted["object_psnr_gain"] > 60
    assert tinted["object_psnr"] < 25  # as rendered, the gain counts
    hazy = object_metrics(0.5 * radiance + 0.1, radiance, depth > 0)
    assert hazy["object_psnr_gain"] < 30  # haze is the render's, not the events' freedom
    assert hazy["object_psnr_affine_per_view"] > 50


def test_the_gain_is_fitted_once_over_all_views_not_per_view(scene):
    """A render whose views disagree in brightness is a wrong render: one gain cannot undo
    it, a fit per view (the diagnostic) can."""
    radiance, depth = scene
    pred = radiance * np.array([0.6, 1.4])[:, None, None, None]
    m = object_metrics(pred, radiance, depth > 0)
    assert m["object_psnr_gain"] < 30
    assert m["object_psnr_affine_per_view"] > 60


def test_the_gain_alone_forgives_a_gain_per_channel_but_not_haze(scene):
    """What events leave undetermined is a gain per channel: fit_gain undoes that exactly; an
    offset (haze) stays in the figure, where the affine correction would forgive it."""
    radiance, _ = scene
    gains = np.array([0.5, 1.5, 0.8])
    np.testing.assert_allclose(fit_gain(radiance * gains, radiance), 1 / gains, rtol=1e-6)
    hazy = radiance * gains + 0.1
    corrected = hazy * fit_gain(hazy, radiance)
    assert psnr(srgb(corrected), srgb(radiance)) < 30
    cc = fit_color_correction(hazy, radiance)
    assert psnr(srgb(hazy * cc[:, 0] + cc[:, 1]), srgb(radiance)) > 50


def test_the_blurred_truth_is_below_the_truth_and_above_a_constant(scene):
    radiance, depth = scene
    blur = blur_psnr(radiance)
    truth = srgb(radiance)
    assert psnr(np.broadcast_to(truth.mean((0, 1, 2)), truth.shape), truth) < blur < 40


def test_without_an_object_no_object_figures(scene):
    radiance, depth = scene
    assert object_metrics(radiance, radiance, np.zeros_like(depth) > 0) == {}


def test_depth_error_relative_to_the_distance(scene):
    _, depth = scene
    assert depth_rel_err(depth * 1.02, depth) == pytest.approx(0.02, rel=1e-5)
    assert np.isnan(depth_rel_err(depth, np.zeros_like(depth)))


def test_the_radiance_as_base_color_baseline(scene):
    """Shading that is one tint over the object is what the correction forgives: the radiance
    itself then scores as the base color; shading that varies across it is not."""
    from evcap.recon.evaluate.views import material_metrics

    base, depth = scene
    surface = depth > 0
    normal = np.where(surface[..., None], [0.0, 0.0, -1.0], 0.0).astype(np.float32)
    truth = TruthViews(np.tile(np.eye(4), (len(base), 1, 1)), base_color=base, normal=normal)
    views = {"base_color": base, "normal": normal}
    tint = material_metrics(views, truth, base * [0.9, 0.7, 0.4])
    assert tint["base_color_psnr_gain_baseline"] > 60
    x = np.linspace(0.3, 1.0, base.shape[2])
    varying = material_metrics(views, truth, base * x[None, None, :, None])
    assert varying["base_color_psnr_gain_baseline"] < 30 < varying["base_color_psnr_gain"]
    # a checkered base color: the best constant color over the surface scores low
    assert tint["base_color_psnr_constant"] < 15


def test_the_share_of_the_object_within_five_percent():
    truth = np.zeros((1, 4, 4), np.float32)
    truth[0, :2, :2] = 2.0  # four object pixels
    pred = truth.copy()
    pred[0, 0, 0] = 2.2  # 10 % off
    pred[0, 0, 1] = 2.09  # 4.5 % off: within
    assert depth_within(pred, truth) == pytest.approx(0.75)
    assert depth_within(pred, truth, share=0.2) == 1.0
    assert np.isnan(depth_within(pred, np.zeros_like(truth)))  # no object: no figure


def test_the_backdrop_seen_through():
    mask = np.zeros((1, 2, 3), bool)
    mask[0, 0, 0] = True
    alpha = np.array([[[1.0, 0.9, 0.1], [0.49, 0.5, 0.0]]])
    # off the object: 0.9, 0.1, 0.49, 0.5, 0.0 -> three below 0.5; the object's alpha not counted
    assert background_clear(alpha, mask) == pytest.approx(3 / 5)
    assert np.isnan(background_clear(alpha, np.ones_like(mask)))


def test_the_silhouette_against_the_objects():
    mask = np.zeros((1, 2, 3), bool)
    mask[0, 0, :2] = True
    alpha = np.array([[[1.0, 0.4, 0.0], [0.5, 0.0, 0.0]]])
    # shown: (0, 0) and (1, 0); the object (0, 0) and (0, 1): one shared of three
    assert silhouette_iou(alpha, mask) == pytest.approx(1 / 3)
    assert silhouette_iou(mask.astype(float), mask) == 1.0
    assert np.isnan(silhouette_iou(np.zeros((1, 2, 3)), np.zeros_like(mask)))
