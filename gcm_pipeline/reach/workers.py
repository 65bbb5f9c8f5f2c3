"""How the reachability engine shares a run out: chunks of targets on forked worker processes.

A run is cut into contiguous chunks (:func:`guided_chunks`); with several
workers, the engine forks a pool whose processes inherit it (:data:`WORKER`,
set just before the fork) and solve chunks with :func:`solve_in_worker`. The
pools still open are closed at exit. How many workers ``workers: auto`` forks
for a run is :func:`auto_workers`'s decision, from the run's size, the cores
this process may use (:func:`quota_cores`) and their idle capacity, read
from the run's start while this process works alone (:class:`IdleProbe`).
"""

from __future__ import annotations

import atexit
import math
import os
import time
import weakref
from typing import Any, Protocol

import numpy as np

from gcm_pipeline.robot.kernels import blas_controller

__all__ = [
    "POOLS",
    "WORKER",
    "IdleProbe",
    "Solver",
    "auto_workers",
    "blas_controller",
    "guided_chunks",
    "quota_cores",
    "solve_in_worker",
]

#: Fewest targets of a chunk when a few thousand are shared out (see guided_chunks).
_LEAST_SHARE = 256
#: Chunks each worker of ``workers: auto`` must have at least (see auto_workers).
AUTO_CHUNKS_PER_WORKER = 2
#: Fraction of a core that must be idle for ``workers: auto`` to count it (see auto_workers).
AUTO_IDLE_CORE = 0.8


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


def auto_workers(n: int, chunk_size: int, cores: int, idle: float | None) -> int:
    """Worker processes for ``workers: auto`` on ``n`` targets left to solve (at least 1).

    The fewest of: the ``cores`` this process may use (:func:`quota_cores`);
    one worker per ``AUTO_CHUNKS_PER_WORKER`` full chunks of ``chunk_size``
    targets (below that, forking and the smaller chunks cost more than a
    second worker saves); and the cores other processes leave idle, ``idle``
    [cores] from :class:`IdleProbe`, each counted when at least
    ``AUTO_IDLE_CORE`` of it is idle (a core another job keeps busy is left
    to it). ``idle`` None (not measurable): the cores. The engine calls it
    when a phase starts (after a probe's chunk when it had read the cores for
    too short a time), with ``n`` the targets left to solve. Only the
    worker count depends on the load, never a result;
    ``benchmarks/bench_workers.py`` measures it against one worker.
    """
    by_size = n // max(1, AUTO_CHUNKS_PER_WORKER * chunk_size)
    by_load = cores if idle is None else math.floor(idle + 1.0 - AUTO_IDLE_CORE)
    return max(1, min(cores, by_size, by_load))


def quota_cores(cores: int, root: str = "/sys/fs/cgroup") -> int:
    """``cores``, or fewer when a CPU quota of the cgroup allows fewer (at least 1).

    The quota of the cgroup mounted at ``root`` (cgroup v2 ``cpu.max``, or v1
    ``cpu/cpu.cfs_quota_us`` over ``cpu.cfs_period_us``), rounded down: 1.5
    CPUs' worth of time is one worker's full core, and a second worker would
    only share it. No quota or nothing readable: ``cores``.
    """
    for quota_file, period_file in (
        ("cpu.max", None),
        ("cpu/cpu.cfs_quota_us", "cpu/cpu.cfs_period_us"),
    ):
        try:
            with open(os.path.join(root, quota_file), encoding="ascii") as f:
                fields = f.read().split()
            if period_file is not None:
                with open(os.path.join(root, period_file), encoding="ascii") as f:
                    fields += f.read().split()
            quota, period = float(fields[0]), float(fields[1])
        except (OSError, ValueError, IndexError):
            continue  # "max" (v2) or not this cgroup version
        if quota > 0 and period > 0:  # v1 says -1 for none
            return max(1, min(cores, int(quota // period)))
        return cores
    return cores


def _cpu_times(cpus: set[int]) -> tuple[float, float] | None:
    """Idle and total jiffies of ``cpus`` summed, from ``/proc/stat`` (None: unreadable)."""
    try:
        with open("/proc/stat", encoding="ascii") as f:
            lines = f.readlines()
    except OSError:
        return None
    idle = total = 0.0
    for line in lines:
        name, *fields = line.split()
        if not name.startswith("cpu") or name == "cpu" or int(name[3:]) not in cpus:
            continue
        ticks = [float(x) for x in fields[:8]]  # user nice system idle iowait irq softirq steal
        idle += ticks[3] + ticks[4]
        total += sum(ticks)
    return idle, total


class IdleProbe:
    """The capacity [cores] other processes leave idle, from now until :meth:`idle_cores`.

    Read from the kernel's per-CPU times (``/proc/stat``) of the cores this
    process may use, at the start and at the end; this process's own CPU
    time meanwhile is not counted as busy, so the probe can watch while the
    process works (the engine goes on with its run meanwhile: measuring
    costs no time). It reads nothing of its children: their CPU time is
    counted as other processes'.
    """

    def __init__(self) -> None:
        self.cpus = os.sched_getaffinity(0) if hasattr(os, "sched_getaffinity") else set()
        self.start = _cpu_times(self.cpus)
        self.wall = time.perf_counter()
        self.own = time.process_time()

    def watched_s(self) -> float:
        """Wall time since the probe started [s]."""
        return time.perf_counter() - self.wall

    def idle_cores(self) -> float | None:
        """Cores other processes left idle since the probe started; None: not readable."""
        end = _cpu_times(self.cpus)
        wall = time.perf_counter() - self.wall
        if self.start is None or end is None or end[1] <= self.start[1] or wall <= 0:
            return None
        n = len(self.cpus)
        busy = n * (1.0 - (end[0] - self.start[0]) / (end[1] - self.start[1]))
        own = (time.process_time() - self.own) / wall
        return min(float(n), max(0.0, n - max(0.0, busy - own)))
