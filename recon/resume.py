"""Going on with an interrupted training: Ctrl-C stops a stage at the end of its current step,
and what it needs to go on (parameters, the optimiser's moments, the random generators' states,
its logs, and everything it derived at its start) is saved beside the reconstruction's
checkpoint, with the settings and the session it was started with; the same command then
continues from that step. What a stage derived at its start (the render grids, the scene's
volume, stage II's visibility, light bounces, normals, edge maps and distillation targets) is
taken from the state, never built again: built again on another machine, or with another number
of threads, a count or a choice made on a float could come out otherwise.
"""

from __future__ import annotations

import hashlib
import pickle
import signal
import threading
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path

import numpy as np
import torch

from evcap import __version__
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


# the layout of a saved training state: raised whenever what a state holds changes (2: what the
# stages derived at their start kept in it; 3: the settings nested by component, the
# densification's state under "densify")
STATE_FORMAT = 3


def digest(*parts: np.ndarray | torch.Tensor | object) -> str:
    """A digest of arrays (their dtype, shape and bytes) and other values (their repr)."""
    h = hashlib.sha1()
    for part in parts:
        if isinstance(part, torch.Tensor):
            part = part.detach().cpu().numpy()
        if isinstance(part, np.ndarray):
            h.update(repr((part.dtype.str, part.shape)).encode())
            h.update(np.ascontiguousarray(part).tobytes())
        else:
            h.update(repr(part).encode())
    return h.hexdigest()


def session_fingerprint(session: Session) -> str:
    """What a training depends on in the session: its events' count and span, the poses and
    the calibration (a digest)."""
    arrays: list[np.ndarray | None] = []
    if Poses.present(session):
        poses = Poses.read(session)
        arrays += [poses.t, poses.T_world_cam]
    if Calibration.present(session):
        c = Calibration.read(session)
        arrays += [c.K, c.dist, c.threshold_on, c.threshold_off, c.hot_pixels]
    kept = [a for a in arrays if a is not None]
    return digest((session.n_events, session.time_range()), *kept)


def save_state(path: Path, state: dict, settings: dict) -> None:
    """Write a training state; a crash mid-write leaves the previous one."""
    stamp = {"settings": settings, "format": STATE_FORMAT, "evcap": __version__}
    with atomic_path(path) as partial:
        torch.save({**state, **stamp}, partial)


def load_state(path: Path) -> dict | None:
    """The training state saved at ``path``; None when there is none."""
    if not path.exists():
        return None
    try:
        return torch.load(path, map_location="cpu", weights_only=True)
    except (RuntimeError, ValueError, EOFError, OSError, pickle.UnpicklingError) as e:
        raise InputError(
            f"{path}: the saved training state cannot be read ({e}); pass --force to start over"
        ) from e


def misfit(state: dict, settings: dict) -> str:
    """Why a saved ``state`` cannot be gone on from with these ``settings``: another version of
    evcap saved it, it was started on another session, or with other settings (named, with
    their values then and now); "" when it can."""
    if state.get("format") != STATE_FORMAT:
        saved_by = state.get("evcap", "an earlier evcap")
        return (
            f"another version of evcap saved it ({saved_by}, state format "
            f"{state.get('format', 1)}; this evcap {__version__} goes on from format "
            f"{STATE_FORMAT})"
        )
    then = _flat(state.get("settings", {}))
    now = _flat(settings)
    if then.get("session") != now.get("session"):
        return (
            "it was started on another session (or this one's events, poses or calibration "
            "changed since)"
        )

    def shown(values: dict, name: str) -> str:
        return repr(values[name]) if name in values else "none"

    changed = [
        f"{name} {shown(then, name)} (now {shown(now, name)})"
        for name in sorted(set(then) | set(now))
        if then.get(name) != now.get(name)
    ]
    return f"it was started with other settings: {', '.join(changed)}" if changed else ""


def remedy(state: dict) -> str:
    """What to do with a saved ``state`` that does not fit (misfit)."""
    if state.get("format") != STATE_FORMAT:
        return "pass --force to start over (or go on with the evcap that saved it)"
    return "run the command it was started with to go on, or pass --force to start over"


def _flat(settings: dict, prefix: str = "") -> dict:
    """Settings as one level, by the names a user gives them: stage I's and stage II's configs
    by their dotted names (stage1.densify.every), then the seed, the session, the ablations."""
    out = {}
    for key, value in settings.items():
        name = prefix + (
            key if prefix else {"config": "stage1", "material": "stage2"}.get(key, key)
        )
        if isinstance(value, dict):
            out.update(_flat(value, name + "."))
        else:
            out[name] = value
    return out


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
