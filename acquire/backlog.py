"""The host's backlog while recording, and what to tell users when it grows.

``Backlog`` is what the recorder reports with every ``Stats`` (once a second): the data
received from the camera and not yet in the session. ``BehindWatch`` follows those reports and
says, in words, when the host falls behind, when it has caught up, and when the camera drops
events (its own counters, as they grow): the monitor and ``evcap record`` show its words
while it happens.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass

REPEAT_S = 5.0  # a warning that still holds is said again this often


@dataclass(frozen=True)
class Backlog:
    """Data received from the camera and not yet in the session (or, while not recording,
    not yet decoded). While the host keeps up it stays small; when it grows the host is
    falling behind, and once the reader holds transfers back the camera holds the data, and
    drops events when its own buffer overflows (its counters: Stats.device_dropped)."""

    received_bytes: int = 0  # received, waiting to be decoded (the reader's queue)
    received_limit: int = 1  # past this the reader holds transfers back
    held_transfers: int = 0  # transfers held back now: the camera is holding the data
    decoded_bytes: int = 0  # decoded, waiting for the session writer
    decoded_limit: int = 1  # past this the recorder waits for the writer

    @property
    def total_bytes(self) -> int:
        return self.received_bytes + self.decoded_bytes

    @property
    def fill(self) -> float:
        """How full the fuller of the two queues is, 0..1 (or a little over)."""
        return max(
            self.received_bytes / self.received_limit, self.decoded_bytes / self.decoded_limit
        )

    @property
    def falling_behind(self) -> bool:
        """The host is not keeping up: transfers held back, or a queue a quarter full (more
        than a few of the recorder's batches)."""
        return self.held_transfers > 0 or self.fill >= 0.25

    def describe(self) -> str:
        """E.g. "24.1 MB waiting (38 % of the buffer)"."""
        text = f"{self.total_bytes / 1e6:.1f} MB waiting ({100 * self.fill:.0f} % of the buffer)"
        if self.held_transfers:
            text += f", {self.held_transfers} USB transfers held back"
        return text


class BehindWatch:
    """Turns the recorder's successive Stats into warnings (``update``), and keeps what the
    last one said (``behind``, ``new_drops``) for a display."""

    def __init__(self, clock: Callable[[], float] = time.monotonic) -> None:
        self._clock = clock
        self.behind = False  # the host is falling behind now
        self.backlog = Backlog()
        self.dropped: int | None = None  # the camera's counters at the last Stats, all together
        self.new_drops = 0  # events the camera dropped between the last two Stats
        self._said = float("-inf")  # when the falling-behind warning was last given

    def update(self, backlog: Backlog, dropped: int) -> list[tuple[str, str]]:
        """What to tell users of a new Stats (its backlog, its dropped-event total):
        (severity, text) pairs, the severity "warning" or "information"."""
        now = self._clock()
        said = []
        self.backlog = backlog
        # the first reading is the baseline: counters can hold drops from before the start
        self.new_drops = 0 if self.dropped is None else max(0, dropped - self.dropped)
        self.dropped = dropped
        if backlog.falling_behind:
            if not self.behind or now - self._said >= REPEAT_S:
                said.append(("warning", f"the host is falling behind: {backlog.describe()}"))
                self._said = now
            self.behind = True
        elif self.behind:
            self.behind = False
            said.append(("information", f"the host has caught up: {backlog.describe()}"))
        if self.new_drops:
            said.append(
                (
                    "warning",
                    f"the camera dropped {self.new_drops:,} events in the last second "
                    f"({dropped:,} since it started): the host or the USB link is not keeping up",
                )
            )
        return said
