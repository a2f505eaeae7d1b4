"""The event loss of a step's windows on the CPU, compiled: each view read in the pixel's own
channel and its log taken, the change between two views compared with the window's C_on ON -
C_off OFF, the pixels with and without events averaged apart, every window at once, in one
pass over the sensor's pixels, and its gradient in another, where PyTorch takes some thirty
operations over them a window each way. loss.py's reference (loss.window_loss window by
window) is what it is tested against, and what runs on a GPU.

Sums are taken in float64 in CHUNKS runs of pixels, then added in order: a run repeats bit for
bit whatever the number of threads.
"""

from __future__ import annotations

import math

import numba
import numpy as np
import torch

from evcap.recon._threads import follow_torch_threads
from evcap.recon.config import ZeroEvents

CHUNKS = 64


@numba.njit(cache=True, inline="always")
def _window(before, crowded, on, off, noise, w, i, j, p):
    """(target C_on ON - C_off OFF, events, whether some were crowded) of pixel p between
    views i and j, less the window's expected noise events ``noise[w]`` (ON, OFF);
    ``crowded`` [K, 2 P] counts the crowded events ([K, 0]: none counted)."""
    n_on = before[j, 2 * p + 1] - before[i, 2 * p + 1]
    n_off = before[j, 2 * p] - before[i, 2 * p]
    target = on[p] * (n_on - noise[w, 0]) - off[p] * (n_off - noise[w, 1])
    near = False
    if crowded.shape[1] > 0:
        near = crowded[j, 2 * p + 1] + crowded[j, 2 * p] > crowded[i, 2 * p + 1] + crowded[i, 2 * p]
    return target, n_on + n_off, near


@numba.njit(cache=True, inline="always")
def _log_views(seen, weights, eps, p, x, logs):
    for k in range(seen.shape[0]):
        v = 0.0
        for c in range(3):
            v += weights[p, c] * seen[k, p, c]
        x[k] = v
        logs[k] = math.log(max(v, 0.0) + eps)


@numba.njit(cache=True, inline="always")
def _error(pred, target, events, near, on, off, bound):
    """(|pred - target|, or for a pixel without events under ``bound`` the hinge outside
    [-C_off, C_on], or for one with crowded events (``near``) the hinge short of the target;
    its derivative)."""
    if bound and events == 0:
        err, d = 0.0, 0.0
        if pred - on > 0:
            err, d = pred - on, 1.0
        if -pred - off > 0:
            err, d = err - pred - off, d - 1.0
        return err, d
    e = pred - target
    if near and target > 0:
        return (-e, -1.0) if e < 0 else (0.0, 0.0)
    if near and target < 0:
        return (e, 1.0) if e > 0 else (0.0, 0.0)
    return abs(e), 1.0 if e > 0 else -1.0 if e < 0 else 0.0


@numba.njit(cache=True, parallel=True)
def _forward(seen, weights, eps, before, crowded, pairs, noise, on, off, mask, bound, sums):
    """sums [CHUNKS, windows, 4]: (error, pixels) with events, (error, pixels) without."""
    n = seen.shape[1]
    for chunk in numba.prange(CHUNKS):
        x, logs = np.empty(seen.shape[0]), np.empty(seen.shape[0])
        for p in range(chunk * n // CHUNKS, (chunk + 1) * n // CHUNKS):
            if not mask[p]:
                continue
            _log_views(seen, weights, eps, p, x, logs)
            for w in range(pairs.shape[0]):
                i, j = pairs[w, 0], pairs[w, 1]
                target, events, near = _window(before, crowded, on, off, noise, w, i, j, p)
                err, _ = _error(logs[j] - logs[i], target, events, near, on[p], off[p], bound)
                quiet = 2 if events == 0 else 0
                sums[chunk, w, quiet] += err
                sums[chunk, w, quiet + 1] += 1.0


@numba.njit(cache=True, parallel=True)
def _backward(
    seen, weights, eps, before, crowded, pairs, noise, on, off, mask, bound, coeff, v_seen
):
    """v_seen [K, P, 3]: the gradient of sum over windows of coeff[w, with events or not] *
    the pixel's error."""
    n = seen.shape[1]
    for chunk in numba.prange(CHUNKS):
        k_views = seen.shape[0]
        x, logs, v_logs = np.empty(k_views), np.empty(k_views), np.empty(k_views)
        for p in range(chunk * n // CHUNKS, (chunk + 1) * n // CHUNKS):
            if not mask[p]:
                for k in range(k_views):
                    for c in range(3):
                        v_seen[k, p, c] = 0.0
                continue
            _log_views(seen, weights, eps, p, x, logs)
            v_logs[:] = 0.0
            for w in range(pairs.shape[0]):
                i, j = pairs[w, 0], pairs[w, 1]
                target, events, near = _window(before, crowded, on, off, noise, w, i, j, p)
                _, d = _error(logs[j] - logs[i], target, events, near, on[p], off[p], bound)
                g = d * coeff[w, 1 if events == 0 else 0]
                v_logs[j] += g
                v_logs[i] -= g
            for k in range(k_views):
                # log(max(x, 0) + eps): no gradient below 0 (clamp's, which passes at 0)
                g = v_logs[k] / (max(x[k], 0.0) + eps) if x[k] >= 0 else 0.0
                for c in range(3):
                    v_seen[k, p, c] = weights[p, c] * g


class _EventLoss(torch.autograd.Function):
    @staticmethod
    def forward(
        ctx, seen, weights, eps, before, crowded, pairs, noise, on, off, mask, bound, silent
    ):
        none = np.zeros((len(before), 0), np.int64)
        arrays = (
            np.ascontiguousarray(seen.detach().numpy(), dtype=np.float64),
            np.ascontiguousarray(weights.numpy(), dtype=np.float64),
            float(eps),
            np.ascontiguousarray(before.numpy()),
            none if crowded is None else np.ascontiguousarray(crowded.numpy()),
            np.asarray(pairs, np.int64).reshape(-1, 2),
            np.asarray(noise, np.float64).reshape(-1, 2),
            np.ascontiguousarray(on.numpy(), dtype=np.float64),
            np.ascontiguousarray(off.numpy(), dtype=np.float64),
            np.ascontiguousarray(mask.numpy()),
            bool(bound),
        )
        windows = len(arrays[5])
        sums = np.zeros((CHUNKS, windows, 4))
        _forward(*arrays, sums)
        loud, n_loud, quiet, n_quiet = sums.sum(0).T
        if silent is None:  # one mean over every pixel
            scale = np.stack([1 / np.maximum(n_loud + n_quiet, 1)] * 2, 1)
        else:
            scale = np.stack(
                [(1 - silent) / np.maximum(n_loud, 1), silent / np.maximum(n_quiet, 1)], 1
            )
        per_window = scale[:, 0] * loud + scale[:, 1] * quiet
        ctx.state = (arrays, scale / windows, seen.dtype)
        return torch.tensor(per_window.mean(), dtype=seen.dtype)

    @staticmethod
    def backward(ctx, grad):
        arrays, scale, dtype = ctx.state
        v_seen = np.empty_like(arrays[0])
        _backward(*arrays, scale * float(grad), v_seen)
        return (torch.from_numpy(v_seen).to(dtype), *([None] * 11))


def event_loss_cpu(
    seen: list[torch.Tensor],
    channel_weights: torch.Tensor,
    eps: float,
    before: torch.Tensor,
    pairs: list[tuple[int, int]],
    noise: np.ndarray,
    threshold_on: torch.Tensor,
    threshold_off: torch.Tensor,
    mask: torch.Tensor,
    zero_events: ZeroEvents,
    silent_weight: float | None,
    crowded: torch.Tensor | None = None,
) -> torch.Tensor:
    """The mean over the windows ``pairs`` (i, j) between the views ``seen`` ([P, 3] each, at
    the sensor's pixels) of loss.window_loss of log(L_j) - log(L_i) in each pixel's channel
    (``channel_weights`` [P, 3]) against the events counted by ``before`` [K, 2 P], less each
    window's expected noise events ``noise`` [windows, 2] (ON, OFF), the crowded ones counted
    by ``crowded`` [K, 2 P] (None: none)."""
    follow_torch_threads()
    return _EventLoss.apply(
        torch.stack(seen),
        channel_weights,
        eps,
        before,
        crowded,
        pairs,
        noise,
        threshold_on,
        threshold_off,
        mask,
        zero_events == "bound",
        silent_weight,
    )
