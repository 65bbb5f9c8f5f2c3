"""How the reachability engine shares a run out: chunks of targets on forked worker processes.

A run is cut into contiguous chunks (:func:`guided_chunks`); with several
workers, the engine forks a pool whose processes inherit it (:data:`WORKER`,
set just before the fork) and solve chunks with :func:`solve_in_worker`. The
pools still open are closed at exit.
"""

from __future__ import annotations

import atexit
import functools
import weakref
from typing import Any, Protocol

import numpy as np
from threadpoolctl import ThreadpoolController

__all__ = ["POOLS", "WORKER", "Solver", "blas_controller", "guided_chunks", "solve_in_worker"]

#: Fewest targets of a chunk when a few thousand are shared out (see guided_chunks).
_LEAST_SHARE = 256


class Solver(Protocol):
    """What a worker process runs: the engine's :meth:`solve` of one chunk."""

    def solve(
        self,
        targets: np.ndarray,
        seeds: np.ndarray | None = None,
        return_candidates: bool = False,
        no_restarts: np.ndarray | None = None,
    ) -> dict[str, Any]:
        """Steps 1-5 of one chunk of targets."""
        ...

    def close(self) -> None:
        """Stop the worker processes."""
        ...


# the engine of this worker process (set in the parent just before the pool forks)
WORKER: dict[str, Solver] = {}
POOLS: weakref.WeakSet[Solver] = weakref.WeakSet()


def solve_in_worker(
    args: tuple[np.ndarray, np.ndarray | None, bool, np.ndarray | None],
) -> dict[str, Any]:
    """One chunk solved by this worker's engine (``args``: those of :meth:`Solver.solve`)."""
    return WORKER["engine"].solve(*args)


@atexit.register
def _close_pools() -> None:
    for engine in list(POOLS):
        engine.close()


@functools.cache
def blas_controller() -> Any:
    """The process's thread pools (BLAS), inspected once."""
    return ThreadpoolController()


def guided_chunks(n: int, most: int, workers: int) -> list[np.ndarray]:
    """Positions ``0..n-1`` in contiguous chunks of at most ``most``, shrinking at the end.

    On several workers a chunk takes a share of what is left (guided
    scheduling), at least ``most // 4``: large chunks while there is much to
    do (fewer, larger NumPy calls), small ones at the end so that the workers
    finish together. A set of at most ``most // 4`` is one chunk, solved on
    this process (starting workers costs about as much as they save there);
    up to ``workers`` times that, it is shared out equally, one chunk per
    worker (3,000 targets on two: 1,500 each, not 2,048 and 952), but not
    in chunks under ``_LEAST_SHARE`` (or ``most // 4`` if smaller). Results
    do not depend on the chunks (every decision is per target).
    """
    least = max(most // 4, 1)
    if workers > 1 and least < n <= workers * least:
        least = most = max(-(-n // workers), min(least, _LEAST_SHARE))
    out, a = [], 0
    while a < n:
        size = most if workers == 1 else min(most, max(least, -(-(n - a) // (2 * workers))))
        out.append(np.arange(a, min(a + size, n)))
        a += size
    return out
