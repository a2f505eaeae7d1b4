"""Where a training step's time goes (bench/steps.py): the trainers wrap each part of a step
(events, render, loss, backward, optimizer, densification) in ``timer(part)``. The default
timer does nothing. A measuring one waits for the device at each part's ends, which takes away
the GPU's lead over the host: it is for finding the shares, not for the speed itself."""

from __future__ import annotations

import time
from collections.abc import Iterator
from contextlib import AbstractContextManager, contextmanager, nullcontext

import torch

PARTS = ("events", "render", "loss", "backward", "optimizer", "densification")


class StepTimer:
    """Seconds spent in each part of the steps timed (``measuring``), else nothing."""

    def __init__(self, device: torch.device | str | None = None) -> None:
        self.measuring = device is not None
        self.device = torch.device(device) if device is not None else None
        self.seconds: dict[str, float] = {}
        self._inner: list[float] = []  # the time of the parts inside each open one

    def __call__(self, part: str) -> AbstractContextManager[None]:
        return self._timed(part) if self.measuring else nullcontext()

    @contextmanager
    def _timed(self, part: str) -> Iterator[None]:
        """A part's time, less that of the parts timed inside it (counted as theirs)."""
        self._wait()
        start = time.perf_counter()
        self._inner.append(0.0)
        try:
            yield
        finally:
            self._wait()
            elapsed = time.perf_counter() - start
            inner = self._inner.pop()
            self.seconds[part] = self.seconds.get(part, 0.0) + elapsed - inner
            if self._inner:
                self._inner[-1] += elapsed

    def _wait(self) -> None:
        if self.device is not None and self.device.type == "cuda":
            torch.cuda.synchronize(self.device)

    def shares(self) -> dict[str, float]:
        """Each part's share of the time measured."""
        total = sum(self.seconds.values()) or 1.0
        return {k: v / total for k, v in self.seconds.items()}


UNTIMED = StepTimer()
