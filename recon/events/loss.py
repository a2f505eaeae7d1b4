"""The event loss (method.md), used by both stages: for every window between two of a step's
views, the change of log radiance each pixel's channel saw, against its events' C_on ON -
C_off OFF. One function, ``event_loss``, over two paths that give the same values: the
compiled CPU pass (_loss_cpu.py, every window at once, its backward written by hand) and the
PyTorch reference (``window_loss`` window by window), which runs on a GPU and which the
compiled pass is tested against (tests/recon/test_event_loss.py)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal, Protocol, assert_never

import numpy as np
import torch
import torch.nn.functional as F

from evcap.errors import InputError
from evcap.recon.config import ZERO_EVENTS, ZeroEvents
from evcap.recon.events.windows import EventWindows
from evcap.recon.scene.optics import SensorOptics
from evcap.recon.step_timer import UNTIMED, StepTimer

Path = Literal["auto", "compiled", "reference"]  # auto: compiled on the CPU, else the reference


@dataclass(frozen=True)
class EventLossConfig:
    """How the rendered change is compared with the events."""

    log_eps: float = 1e-3
    """Added to the radiance before the log (the sensor's dark level)."""
    zero_events: ZeroEvents = "target"
    """What a pixel without events says: "target", its change is 0; "bound", |change| < C."""
    silent_weight: float | None = 0.3
    """The share of the loss of the pixels without events (the others take the rest); None:
    one mean over all pixels, as the method's sum."""
    noise_rates: bool = False
    """The calibration's noise rates taken from each window's counts before they are compared
    (the window's expected background-activity and shot-noise events)."""

    def __post_init__(self) -> None:
        if self.log_eps <= 0:
            raise InputError("event_loss.log_eps must be above 0")
        if self.zero_events not in ZERO_EVENTS:
            raise InputError('event_loss.zero_events must be "target" or "bound"')
        if self.silent_weight is not None and not 0 <= self.silent_weight <= 1:
            raise InputError("event_loss.silent_weight is a share, in [0, 1] (or none)")


class EventData(Protocol):
    """What the loss reads beside the renders: the windows' counts, what each sensor pixel sees
    of (R, G, B) [P, 3], which pixels count [P] (hot ones left out), the calibration's noise
    rates."""

    windows: EventWindows
    channel_weights: torch.Tensor
    mask: torch.Tensor
    optics: SensorOptics


def log_radiance(radiance: torch.Tensor, eps: float) -> torch.Tensor:
    """log(L + eps): finite for black (and for the tiny negatives of interpolation)."""
    return torch.log(radiance.clamp(min=0) + eps)


def event_loss(
    seen: list[torch.Tensor],
    frames: np.ndarray,
    data: EventData,
    config: EventLossConfig,
    timer: StepTimer = UNTIMED,
    path: Path = "auto",
) -> torch.Tensor:
    """The mean event loss of every window between two of the views ``seen`` ([P, 3] each:
    the renders at the sensor's pixels) at the frame indices ``frames``."""
    w = data.windows
    with timer("events"):
        before = w.before_frames(frames)
        crowded = w.crowded.before_frames(frames) if w.crowded is not None else None
    pairs = [
        (i, j)
        for i in range(len(frames))
        for j in range(i + 1, len(frames))
        if frames[j] != frames[i]
    ]
    if not pairs:
        return seen[0].sum() * 0
    noise = expected_noise(data, config, frames, pairs)
    if path == "auto":
        path = "compiled" if seen[0].device.type == "cpu" else "reference"
    match path:
        case "compiled":
            from evcap.recon.events._loss_cpu import event_loss_cpu

            return event_loss_cpu(
                seen,
                data.channel_weights,
                config.log_eps,
                before,
                pairs,
                noise,
                w.threshold_on,
                w.threshold_off,
                data.mask,
                config.zero_events,
                config.silent_weight,
                crowded,
            )
        case "reference":
            return _reference(data, config, before, pairs, noise, seen, crowded)
        case _:
            assert_never(path)


def expected_noise(
    data: EventData, config: EventLossConfig, frames: np.ndarray, pairs: list[tuple[int, int]]
) -> np.ndarray:
    """[windows, 2] the noise events (ON, OFF) a pixel fires in each window at the
    calibration's rates (config.noise_rates; else 0)."""
    out = np.zeros((len(pairs), 2))
    if config.noise_rates:
        t = data.windows.frame_times[np.asarray(frames)]
        seconds = np.array([(t[j] - t[i]) * 1e-6 for i, j in pairs])
        out[:, 0] = data.optics.noise_on_hz * seconds
        out[:, 1] = data.optics.noise_off_hz * seconds
    return out


def _reference(
    data: EventData,
    config: EventLossConfig,
    before: torch.Tensor,
    pairs: list[tuple[int, int]],
    noise: np.ndarray,
    seen: list[torch.Tensor],
    crowded: torch.Tensor | None,
) -> torch.Tensor:
    """event_loss in PyTorch operations: window_loss window by window."""
    w = data.windows
    logs = [log_radiance((s * data.channel_weights).sum(1), config.log_eps) for s in seen]
    losses = []
    for (i, j), (mu_on, mu_off) in zip(pairs, noise, strict=True):
        target, counts = w.change(*w.between(before[i], before[j]))
        target = target - (w.threshold_on * float(mu_on) - w.threshold_off * float(mu_off))
        near = None
        if crowded is not None:
            near = sum(w.crowded.between(crowded[i], crowded[j]))
        losses.append(
            window_loss(
                logs[j] - logs[i],
                target,
                counts,
                w.threshold_on,
                w.threshold_off,
                data.mask,
                config.zero_events,
                config.silent_weight,
                near,
            )
        )
    return torch.stack(losses).mean()


def window_loss(
    predicted: torch.Tensor,
    measured: torch.Tensor,
    counts: torch.Tensor,
    threshold_on: torch.Tensor,
    threshold_off: torch.Tensor,
    mask: torch.Tensor,
    zero_events: ZeroEvents = "target",
    silent_weight: float | None = None,
    crowded: torch.Tensor | None = None,
) -> torch.Tensor:
    """One window's loss: the mean L1 between the rendered log change and C_on ON - C_off OFF,
    over ``mask``.

    Most pixels of a window have no event; left to a plain mean they teach only "nothing
    changes", whose cheapest answer is an empty scene. With ``silent_weight`` s, the pixels
    with events and those without are averaged apart and weighted 1 - s and s (EventNeRF
    draws 90 % of its rays from pixels with events: s = 0.1).

    With ``zero_events="bound"``, a pixel without events is not told "no change" but only
    -C_off < change < C_on (a hinge): what a silent pixel really says.

    A pixel with ``crowded`` events (counts; windows.py) lost part of its change to its
    refractory period: its measured change is only a lower bound on the change's size, in its
    direction (a hinge again).
    """
    err = (predicted - measured).abs()
    if crowded is not None:
        short = torch.where(
            measured > 0, F.relu(measured - predicted), F.relu(predicted - measured)
        )
        err = torch.where((crowded > 0) & (measured != 0), short, err)
    match zero_events:
        case "target":
            pass
        case "bound":
            silent = counts == 0
            inside = F.relu(predicted - threshold_on) + F.relu(-predicted - threshold_off)
            err = torch.where(silent, inside, err)
        case _:
            assert_never(zero_events)
    m = mask.to(err.dtype)
    if silent_weight is None:
        return (err * m).sum() / m.sum().clamp(min=1)
    loud = m * (counts > 0).to(err.dtype)
    quiet = m - loud
    return (1 - silent_weight) * (err * loud).sum() / loud.sum().clamp(min=1) + silent_weight * (
        err * quiet
    ).sum() / quiet.sum().clamp(min=1)
