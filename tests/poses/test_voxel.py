"""The voxel grid (NumPy reference and torch) and its normalisation."""

import numpy as np
import pytest
import torch

from evcap.errors import InputError
from evcap.poses.voxel import normalize_voxels, voxel_grid, voxel_grid_torch


def test_each_event_is_split_between_its_two_nearest_bins():
    # 5 bins over 0..100 us: t = 30 is at 1.2, t = 50 at 2.0
    x, y = [0, 1, 2, 2], [0, 0, 1, 1]
    t, p = [0, 30, 50, 100], [1, 0, 1, 1]
    v = voxel_grid(x, y, t, p, width=3, height=2, bins=5)
    assert v.shape == (5, 2, 3) and v.dtype == np.float32
    assert v[0, 0, 0] == 1.0  # the first event: all in bin 0
    assert v[1, 0, 1] == pytest.approx(-0.8) and v[2, 0, 1] == pytest.approx(-0.2)
    assert v[2, 1, 2] == 1.0 and v[4, 1, 2] == 1.0  # on a bin: all of it there
    assert np.count_nonzero(v) == 5
    # every event keeps its polarity in total
    assert v.sum() == pytest.approx(1 - 1 + 1 + 1)


def test_a_window_at_one_time_and_an_empty_one():
    v = voxel_grid([1, 1], [0, 0], [7, 7], [1, 1], width=2, height=1, bins=3)
    assert v[0, 0, 1] == 2.0 and np.count_nonzero(v) == 1
    empty = voxel_grid([], [], [], [], width=4, height=3, bins=5)
    assert empty.shape == (5, 3, 4) and not empty.any()
    assert not voxel_grid_torch([], [], [], [], width=4, height=3).any()
    one_bin = voxel_grid([0, 1], [0, 0], [0, 10], [1, 0], width=2, height=1, bins=1)
    np.testing.assert_array_equal(one_bin, [[[1.0, -1.0]]])


@pytest.mark.parametrize("bins", [1, 3, 5, 9])
def test_torch_matches_the_reference(bins):
    rng = np.random.default_rng(bins)
    n, width, height = 3000, 32, 24
    x = rng.integers(0, width, n).astype(np.uint16)
    y = rng.integers(0, height, n).astype(np.uint16)
    # large absolute times: the window, not the epoch, sets the precision
    t = np.sort(rng.integers(0, 40_000, n)).astype(np.int64) + 1_700_000_000_000_000
    p = rng.integers(0, 2, n).astype(np.uint8)
    ref = voxel_grid(x, y, t, p, width, height, bins)
    fast = voxel_grid_torch(x, y, t, p, width, height, bins)
    assert fast.dtype == torch.float32 and fast.shape == (bins, height, width)
    np.testing.assert_allclose(fast.numpy(), ref, atol=1e-5)
    # tensors in, same grid out
    as_tensors = [torch.from_numpy(a.astype(np.int64)) for a in (x, y, t, p)]
    fast2 = voxel_grid_torch(*as_tensors, width, height, bins)
    np.testing.assert_allclose(fast2.numpy(), ref, atol=1e-5)
    assert ref.sum() == pytest.approx(np.where(p > 0, 1, -1).sum(), abs=1e-3)


@pytest.mark.parametrize("make", [voxel_grid, voxel_grid_torch])
def test_bad_events_are_refused(make):
    with pytest.raises(InputError, match="x outside 0..3"):
        make([4], [0], [0], [1], width=4, height=2)
    with pytest.raises(InputError, match="y outside 0..1"):
        make([0], [-1], [0], [1], width=4, height=2)
    with pytest.raises(InputError, match="2 x, 1 y"):
        make([0, 1], [0], [0], [1], width=4, height=2)
    with pytest.raises(InputError, match="bins=0"):
        make([0], [0], [0], [1], width=4, height=2, bins=0)


def test_normalisation_over_the_nonzero_voxels_only():
    rng = np.random.default_rng(0)
    v = np.zeros((5, 24, 32), np.float32)
    mask = rng.random(v.shape) < 0.1
    v[mask] = rng.normal(3.0, 2.5, mask.sum())
    out = normalize_voxels(v)
    assert out.dtype == np.float32
    assert not out[~mask].any()
    assert out[mask].mean() == pytest.approx(0.0, abs=1e-5)
    assert out[mask].std() == pytest.approx(1.0, abs=1e-5)
    assert not v[~mask].any() and v[mask].mean() > 1  # the input is left alone


def test_normalisation_of_degenerate_grids_makes_no_nan():
    zero = normalize_voxels(np.zeros((5, 4, 4), np.float32))
    assert not zero.any()
    single = np.zeros((5, 4, 4), np.float32)
    single[2, 1, 1] = 0.7
    out = normalize_voxels(single)
    assert np.isfinite(out).all() and not out.any()
