"""Going on with an interrupted training: Ctrl-C stops a stage at the end of its current step,
and what it needs to go on (parameters, the optimiser's moments, the random generators' states,
its logs) is saved beside the reconstruction's checkpoint, with the settings and the session it
was started with; the same command then continues from that step."""

from __future__ import annotations

import hashlib
import signal
import threading
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path

import numpy as np
import torch

from evcap.atomic_write import atomic_path
from evcap.errors import InputError
from evcap.records import Calibration, Poses
from evcap.session import Session


@contextmanager
def stop_after_step() -> Iterator[Callable[[], bool]]:
    """Yield ``requested()``: true once Ctrl-C was pressed, for a training loop to stop at the
    end of its step, so that what it saves is whole. A second Ctrl-C interrupts at once.
    Outside the main thread (no signal handlers there) Ctrl-C interrupts as usual."""
    if threading.current_thread() is not threading.main_thread():
        yield lambda: False
        return
    asked = threading.Event()

    def handler(signum, frame) -> None:
        if asked.is_set():
            raise KeyboardInterrupt
        asked.set()

    previous = signal.signal(signal.SIGINT, handler)
    try:
        yield asked.is_set
    finally:
        signal.signal(signal.SIGINT, previous if previous is not None else signal.SIG_DFL)


def session_fingerprint(session: Session) -> str:
    """What a training depends on in the session: its events' count and span, the poses and
    the calibration (a digest)."""
    digest = hashlib.sha1()
    digest.update(repr((session.n_events, session.time_range())).encode())
    arrays: list[np.ndarray | None] = []
    if Poses.present(session):
        poses = Poses.read(session)
        arrays += [poses.t, poses.T_world_cam]
    if Calibration.present(session):
        c = Calibration.read(session)
        arrays += [c.K, c.dist, c.threshold_on, c.threshold_off, c.hot_pixels]
    for a in arrays:
        if a is not None:
            digest.update(np.ascontiguousarray(a).tobytes())
    return digest.hexdigest()


def save_state(path: Path, state: dict, settings: dict) -> None:
    """Write a training state; a crash mid-write leaves the previous one."""
    with atomic_path(path) as partial:
        torch.save({**state, "settings": settings}, partial)


def load_state(path: Path, settings: dict) -> dict | None:
    """The training state saved at ``path`` when it was started with these ``settings``;
    None when there is none, or it was started with others."""
    if not path.exists():
        return None
    try:
        state = torch.load(path, map_location="cpu", weights_only=True)
    except (RuntimeError, ValueError, EOFError, OSError) as e:
        raise InputError(
            f"{path}: the saved training state cannot be read ({e}); pass --force to start over"
        ) from e
    return state if state.get("settings") == settings else None


def random_states(rng: np.random.Generator) -> dict:
    states = {"numpy": rng.bit_generator.state, "torch": torch.get_rng_state()}
    if torch.cuda.is_available() and torch.cuda.is_initialized():
        states["cuda"] = torch.cuda.get_rng_state()
    return states


def restore_random_states(rng: np.random.Generator, states: dict) -> None:
    rng.bit_generator.state = states["numpy"]
    torch.set_rng_state(states["torch"])
    if "cuda" in states and torch.cuda.is_available():
        torch.cuda.set_rng_state(states["cuda"])


class Steps:
    """The bookkeeping of a training loop that can stop and go on: its step, its training time
    (without the time spent saving or evaluating), Ctrl-C taken at the end of a step, and its
    state given to ``save`` every ``every_s`` seconds and when it stops part-way. ``resume``:
    a saved state, to go on from its step and time."""

    def __init__(
        self,
        total: int,
        save: Callable[[dict], None] | None,
        every_s: float,
        clock: Callable[[], float],
        resume: dict | None = None,
    ) -> None:
        self.total, self.save, self.every_s, self.clock = total, save, every_s, clock
        self.step = int(resume["step"]) if resume is not None else 0
        self.started = clock() - (float(resume["seconds"]) if resume is not None else 0.0)
        self.paused = 0.0
        self.interrupted = False
        self.whole = True  # no step is half done
        self.last_save = clock()
        self.state: Callable[[], dict] = dict
        self.requested: Callable[[], bool] = lambda: False

    def seconds(self) -> float:
        return self.clock() - self.started - self.paused

    @contextmanager
    def paused_clock(self) -> Iterator[None]:
        before = self.clock()
        try:
            yield
        finally:
            self.paused += self.clock() - before

    @contextmanager
    def running(self, state: Callable[[], dict]) -> Iterator[None]:
        """Around the loop: Ctrl-C ends it with what was learnt, and ``state()`` is saved
        then, unless a second Ctrl-C cut a step in two (the last whole one stays)."""
        self.state = state
        with stop_after_step() as self.requested:
            try:
                yield
            except KeyboardInterrupt:
                self.interrupted = True
        if self.interrupted and self.whole and self.save is not None:
            self.save(state())

    def next(self) -> bool:
        """Begin the next step; False when all are done or Ctrl-C asked to stop."""
        if self.step >= self.total:
            return False
        if self.requested():
            self.interrupted = True
            return False
        self.whole = False
        self.step += 1
        return True

    def end(self) -> None:
        """The step is whole: save the state when it is time."""
        self.whole = True
        if self.save is not None and self.clock() - self.last_save >= self.every_s:
            with self.paused_clock():
                self.save(self.state())
            self.last_save = self.clock()
