"""One thread count for PyTorch and the compiled kernels: the one torch is set to use; and
torch on one thread where a stage derives what it starts from.

numba's OpenMP pool, when it starts (at the first parallel kernel or thread setting of the
process), sets OpenMP's count, which torch shares, to numba's own (every core): a process
started with OMP_NUM_THREADS=1, or told torch.set_num_threads(1), then ran on every core from
the first cube-map lookup on. Every compiled entry point calls ``follow_torch_threads`` first.

The compiled kernels give the same values on any number of threads (each thread's share is
fixed, and summed in a fixed order). torch's CPU operations do not: each thread takes a run of
the values and computes the ends of its run by other instructions than its middle (softplus
came out otherwise on 5 of 116,640 values between one and two threads, measured), and a
reduction sums each thread's part apart. Where a stage decides something from such values at
its start (which Gaussians block the light, which effects explain the radiance best), it
therefore computes them with torch on one thread (``torch_on_one_thread``). Thread counts are
the process's, torch's as these: one reconstruction at a time per process.
"""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager

import numba
import torch

_kernel_threads: int | None = None  # the compiled kernels' threads inside torch_on_one_thread


def follow_torch_threads() -> None:
    """The compiled kernels on as many threads as torch is set to use (inside
    ``torch_on_one_thread``: as it was set to before), and torch kept so."""
    n = torch.get_num_threads()
    numba.set_num_threads(max(1, min(_kernel_threads or n, numba.config.NUMBA_NUM_THREADS)))
    if torch.get_num_threads() != n:  # the pool started just now and reset OpenMP's count
        torch.set_num_threads(n)


@contextmanager
def torch_on_one_thread() -> Iterator[None]:
    """torch's CPU operations on one thread inside, the compiled kernels on as many as
    before; the counts as they were afterwards."""
    global _kernel_threads
    follow_torch_threads()  # the pool started before torch's count is changed
    before, outer = torch.get_num_threads(), _kernel_threads
    _kernel_threads = outer or before
    torch.set_num_threads(1)
    try:
        yield
    finally:
        torch.set_num_threads(before)
        _kernel_threads = outer
