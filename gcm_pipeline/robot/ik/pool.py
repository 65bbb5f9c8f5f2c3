"""The fork pool of the IK and of the reachability engine, and how solve_ik splits its work.

:class:`ForkPool` is the project's one pool of forked worker processes: its
``terminate()`` cannot hang on a killed worker, and :meth:`ForkPool.ordered`
raises :class:`~gcm_pipeline.errors.WorkerLostError` when a worker dies instead
of waiting for ever. :func:`run_backend` splits the targets of one
:func:`~gcm_pipeline.robot.ik.solve_ik` call into chunks and solves them in
this process or over a pool kept for the next call with the same state (the
workers inherit the robot, the validator and the backend's caches by forking,
so nothing heavy is pickled).
"""

from __future__ import annotations

import atexit
import multiprocessing as mp
import multiprocessing.pool
import os
import signal
import threading
import time
from collections.abc import Callable, Iterable, Iterator
from typing import Any

import numpy as np

from gcm_pipeline.errors import WorkerLostError
from gcm_pipeline.robot.ik.answer import BackendAnswer
from gcm_pipeline.robot.model import Robot

__all__ = ["ForkPool", "cores", "run_backend", "worker_signals"]

# targets per backend call: large batches vectorise well, memory stays bounded
_CHUNK = 16384

# state shared with forked worker processes (set just before the pool forks)
_FORK_STATE: dict[str, Any] = {}
_POOL: dict[str, Any] = {}


def _close_pool() -> None:
    pool = _POOL.pop("pool", None)
    _POOL.pop("key", None)
    if pool is not None:
        pool.terminate()
        pool.join()
    _FORK_STATE.clear()


def _pool(
    solve: Callable[..., BackendAnswer],
    robot: Robot,
    validator: Callable[[np.ndarray], Any] | None,
    return_all: bool,
    workers: int,
    kwargs: dict[str, Any],
    warm_targets: np.ndarray,
) -> Any:
    """A forked worker pool holding this robot and these options, reused across calls.

    The workers inherit the robot, the validator and the backend's caches
    (seed library, MuJoCo model) by forking, so nothing heavy is pickled; the
    pool is kept for the next call with the same state (the state holds strong
    references, so the ids in the key cannot be reused) and closed at exit.
    """
    key = (solve, id(robot), id(validator), return_all, workers, repr(sorted(kwargs.items())))
    if _POOL.get("key") == key:
        return _POOL["pool"]
    _close_pool()
    # warm the backend's caches before forking
    solve(robot, warm_targets, seeds=None, validator=None, return_all=False, **kwargs)
    _FORK_STATE.update(
        solve=solve, robot=robot, validator=validator, return_all=return_all, kwargs=kwargs
    )
    pool = ForkPool(workers, initializer=worker_signals)
    if not _POOL.get("atexit"):
        atexit.register(_close_pool)
        _POOL["atexit"] = True
    _POOL.update(key=key, pool=pool)
    return pool


class ForkPool(multiprocessing.pool.Pool):
    """A pool of forked workers whose ``terminate()`` cannot hang on a killed worker.

    An idle worker waits for its next task holding the task queue's read lock;
    killed then (SIGTERM to the process group), it never releases it, and the
    standard ``Pool.terminate()`` waits for that lock for ever before it drains
    the queue. Here it waits at most a second, then drains the queue anyway:
    the pool is being torn down and no worker reads it any more.
    """

    def __init__(self, processes: int, initializer: Any = None) -> None:
        super().__init__(processes, initializer=initializer, context=mp.get_context("fork"))
        self._first_pids = {p.pid for p in self._pool}  # type: ignore[attr-defined]
        self._abandoned = False

    def terminate(self) -> None:
        """Stop the workers; after a worker died, without waiting on the queues.

        A worker killed while it sends its result holds the result queue's
        write lock and leaves half a message in the pipe: the standard
        teardown then waits for ever, on that lock (to send its own sentinel)
        or on the result thread (reading the rest of the message). When a
        worker has died, the others are killed and the pool's threads (daemon
        threads, blocked on the dead worker's pipe) are left behind.
        """
        handler = self._worker_handler  # type: ignore[attr-defined]
        handler._state = multiprocessing.pool.TERMINATE  # no new workers from here on
        self._change_notifier.put(None)  # type: ignore[attr-defined]
        if handler.is_alive() and threading.current_thread() is not handler:
            handler.join(timeout=_HANDLER_WAIT)
        procs = list(self._pool)  # type: ignore[attr-defined]
        died = any(p.exitcode is not None for p in procs)
        if not died and {p.pid for p in procs} == self._first_pids:
            super().terminate()
            return
        self._abandoned = True
        self._state = multiprocessing.pool.TERMINATE  # type: ignore[attr-defined]
        self._terminate.cancel()  # type: ignore[attr-defined]
        for p in procs:
            if p.exitcode is None:
                p.kill()
        for p in procs:
            p.join(timeout=_HANDLER_WAIT)

    def join(self) -> None:
        """Wait for the workers (only for them after a worker died, see :meth:`terminate`)."""
        if not self._abandoned:
            super().join()

    def ordered(self, func: Callable[[Any], Any], items: Iterable[Any]) -> Iterator[Any]:
        """``imap(func, items)``: results in order, as they come.

        A worker that dies (killed, e.g. by the out-of-memory killer) takes its
        task with it: the standard pool starts a new worker and waits for that
        result for ever. Here the workers are looked at while waiting, and a
        dead one raises :class:`~gcm_pipeline.errors.WorkerLostError`.
        """
        # the pool replaces a dead worker in _pool: these are the originals
        workers = list(self._pool)  # type: ignore[attr-defined]
        results = self.imap(func, items)
        while True:
            try:
                yield results.next(timeout=_WORKER_POLL)
            except StopIteration:
                return
            except mp.TimeoutError:
                pass
            for proc in workers:
                if proc.exitcode is not None:
                    raise WorkerLostError(_worker_death(proc.pid, proc.exitcode))

    @staticmethod
    def _help_stuff_finish(inqueue: Any, task_handler: Any, size: int) -> None:
        inqueue._rlock.acquire(True, 1.0)
        while task_handler.is_alive() and inqueue._reader.poll():
            inqueue._reader.recv()
            time.sleep(0)


def cores() -> int:
    """Cores this process may run on (its CPU affinity), at least 1."""
    if hasattr(os, "sched_getaffinity"):
        return max(1, len(os.sched_getaffinity(0)))
    return max(1, os.cpu_count() or 1)  # pragma: no cover - not Linux


#: How often the workers are looked at while a result is awaited [s].
_WORKER_POLL = 0.25
#: How long a teardown waits for the pool's worker thread and for a killed worker [s].
_HANDLER_WAIT = 5.0


def _worker_death(pid: int | None, code: int) -> str:
    """What to tell a user whose worker process ``pid`` ended with ``code``."""
    if code < 0:
        try:
            how = f"killed by {signal.Signals(-code).name}"
        except ValueError:
            how = f"killed by signal {-code}"
    else:
        how = f"exit status {code}"
    hint = "; out of memory? Fewer workers or fewer targets at once need less" if code == -9 else ""
    return f"worker process {pid} died ({how}) before returning its result{hint}"


def worker_signals() -> None:
    """In a worker: Ctrl-C and hang-ups are the parent's to handle, SIGTERM ends it.

    The parent stops the pool on an interrupt (:func:`run_backend`); a worker
    that raised KeyboardInterrupt itself would print a traceback and leave
    ``pool.map`` waiting for a result that never comes.
    """
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    if hasattr(signal, "SIGHUP"):
        signal.signal(signal.SIGHUP, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, signal.SIG_DFL)


def _worker(args: tuple[np.ndarray, np.ndarray | None]) -> BackendAnswer:
    targets, seeds = args
    st = _FORK_STATE
    return st["solve"](
        st["robot"],
        targets,
        seeds=seeds,
        validator=st["validator"],
        return_all=st["return_all"],
        **st["kwargs"],
    )


def _chunk_kwargs(
    kwargs: dict[str, Any],
    settle: Callable[[np.ndarray, np.ndarray], np.ndarray] | None,
    a: int,
    b: int,
) -> dict[str, Any]:
    """The backend options of the chunk of targets ``a:b`` (its own ``settle`` indices)."""
    if settle is None:
        return kwargs

    def local(index: np.ndarray, q: np.ndarray) -> np.ndarray:
        return np.asarray(settle(index + a, q), dtype=bool)[a:b]

    return {**kwargs, "settle": local}


def run_backend(
    solve: Callable[..., BackendAnswer],
    robot: Robot,
    targets: np.ndarray,
    seeds: np.ndarray | None,
    validator: Callable[[np.ndarray], Any] | None,
    return_all: bool,
    workers: int,
    kwargs: dict[str, Any],
) -> BackendAnswer:
    """The raw answer of backend ``solve`` for ``targets``, in chunks, over ``workers``.

    Chunks of at most 16,384 targets (a multiple of the workers when they run
    in parallel: at least two targets per worker and the fork start method);
    the chunks' answers are concatenated in order, candidate rows re-indexed.
    A ``settle`` callback among ``kwargs`` keeps the chunks in this process.
    Ctrl-C or SIGTERM while the workers run stops them (no half-done pool).
    """
    n = targets.shape[0]
    settle = kwargs.get("settle")
    parallel = (
        workers > 1
        and n >= 2 * workers
        and "fork" in mp.get_all_start_methods()
        and settle is None  # a callback of this process
    )
    n_chunks = -(-n // _CHUNK)
    if parallel:
        n_chunks = workers * -(-n_chunks // workers)  # a multiple of the workers
    if not parallel and n_chunks == 1:
        return solve(
            robot, targets, seeds=seeds, validator=validator, return_all=return_all, **kwargs
        )
    bounds = np.linspace(0, n, n_chunks + 1).astype(int)
    chunks = [
        (targets[a:b], None if seeds is None else seeds[a:b])
        for a, b in zip(bounds[:-1], bounds[1:], strict=True)
    ]
    if parallel:
        pool = _pool(solve, robot, validator, return_all, workers, kwargs, targets[:1])
        try:
            parts = list(pool.ordered(_worker, chunks))
        except BaseException:  # Ctrl-C, SIGTERM: stop the workers, no half-done pool
            _close_pool()
            raise
    else:
        parts = [
            solve(
                robot,
                t,
                seeds=s,
                validator=validator,
                return_all=return_all,
                **_chunk_kwargs(kwargs, settle, a, b),
            )
            for (t, s), a, b in zip(chunks, bounds[:-1], bounds[1:], strict=True)
        ]
    return BackendAnswer.concatenate(parts, list(bounds[:-1]), return_all)
