"""The reachability engine: which grasp poses can the robot take, approach and leave?

One sequence, for every chunk of targets (grasp-frame poses in the robot's
base frame), in :meth:`ReachabilityEngine.run`:

1. **IK** (:func:`~gcm_pipeline.robot.ik.solve_ik`): one solution per target,
   batched; seeds are the given warm starts, the seed library, home and random
   restarts (for a row whose neighbours all failed IK after their full seed
   schedule, no random restarts and 2 library seeds); targets beyond the arm's
   reach are rejected first (``out_of_reach``: farther than the arm reaches,
   or for the Panda's kinematics proved by the elbow's range), the others get
   ``no_ik`` or ``joint_limits`` when no seed converges. Every solution is
   **verified** by Pinocchio's forward kinematics and lies strictly inside the
   joint limits.
2. **Check** each solution (:meth:`ReachabilityEngine.check`), in this order,
   stopping at the first failure:

   a. collisions at the grasp (self, environment, object; the gripper may
      touch the object by the checker's contact tolerance), then a user's
      ``validator`` if given;
   b. the **approach** (:mod:`~gcm_pipeline.reach.moves`): the straight line
      from the pre-grasp to the grasp, followable with bounded joint steps and
      deviation, collision-free with no finger contact;
   c. the **retreat**: the straight line away from the grasp holding the
      object (the gripper may touch it).
3. **Re-solve the failures of 2 on other IK branches**: for each target whose
   solution failed a check, up to ``alternatives`` other distinct solutions
   (more seeds: library, random restarts), each checked as in 2, in seed
   order; the first that passes every check is the answer. A 6R arm with
   closed-form branches (:mod:`~gcm_pipeline.robot.ik.analytic_6r`) tries
   **every** other branch instead, nearest home first, so a branch that
   passes is found whenever one exists. Solutions are distinct modulo 2π on
   joints whose range exceeds a turn (``q + 2π`` is the same arm shape and
   is never re-tried). Nothing else is
   re-solved: a target with no IK solution had every seed already, and one
   whose solution failed a move that ends beyond reach (proved for the
   Panda's kinematics and 6R arms of the UR geometry,
   :func:`~gcm_pipeline.reach.moves.unreachable_ends`)
   fails that move with any solution. Such moves are not planned either: they
   fail in 2 without IK.
4. **More branches** (``solutions`` > 1): for every reachable target, further
   IK solutions (more library seeds and random restarts; a 6R arm's other
   closed-form branches, nearest home first), each differing from the ones
   kept by more than ``solution_separation`` in some joint (modulo 2π where
   the range exceeds a turn), checked as in 2; up to ``solutions`` passing
   ones are kept (the answer of 1-3 first, then in seed order). Which one a
   grasp takes is decided later, by the stage (ranking metric or continuity
   with the neighbours).
5. **Clearance** of the reachable rows (distance of the arm to the world), and
   of every kept branch.

A row's ``reason`` is ``''`` when reachable; else the IK's reason, or the
furthest check any of its solutions reached: a collision reason (or the
validator's), ``approach``, ``retreat``. ``q_rejected`` keeps that solution (the
one that collided or whose approach or retreat failed) so a user can see what
went wrong.

Every decision is per target, so a target's result does not depend on the
other targets, on the chunking or on the number of worker processes. Rows
with ``neighbours`` (densified poses) are solved after the rows they refer to
and seeded from those rows' final, checked solutions. Chunks of
at most ``chunk_size`` targets stream through the sequence (on several
workers the last ones smaller), so memory is bounded by the chunk size,
and several chunks run at once on ``workers`` forked
processes that inherit the robot, seed library and collision world.

The engine takes plain arrays and shapes (a robot, a collision checker,
:class:`~gcm_pipeline.reach.moves.Move` objects), no config;
:mod:`gcm_pipeline.pipeline` maps a config onto it. Build it once
and :meth:`~ReachabilityEngine.run` it on many target sets.
"""

from __future__ import annotations

import multiprocessing as mp
from collections.abc import Callable, Iterator, Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np

from gcm_pipeline.errors import InputError
from gcm_pipeline.reach.chunk import ChunkSteps
from gcm_pipeline.reach.moves import Move
from gcm_pipeline.reach.result import Branches, ReachResult
from gcm_pipeline.reach.solution_checks import SolutionChecks
from gcm_pipeline.reach.workers import (
    POOLS,
    WORKER,
    IdleProbe,
    auto_workers,
    blas_controller,
    guided_chunks,
    quota_cores,
    solve_in_worker,
)
from gcm_pipeline.robot import kernels
from gcm_pipeline.robot.ik import IKCandidates, check_targets, solve_ik
from gcm_pipeline.robot.ik.backend import check_neighbours, check_seeds
from gcm_pipeline.robot.ik.pool import ForkPool
from gcm_pipeline.robot.ik.pool import cores as _cores
from gcm_pipeline.robot.ik.pool import worker_signals as _worker_signals
from gcm_pipeline.robot.model import Robot

__all__ = ["ReachabilityEngine", "available_cores"]

#: IK reasons of a neighbour that tried its whole seed schedule and failed.
_RAN_EVERY_SEED = ("no_ik", "joint_limits")

#: ``workers: auto`` reads the idle cores from the run's start while this process
#: works alone; when a phase starts before it has read them for ``AUTO_WATCH_S``, it
#: solves the first ``chunk_size // AUTO_PROBE_SHARE`` targets (2,048 of the default
#: 8,192: about 0.1 s of the Panda's stage) meanwhile, then forks (see
#: :meth:`ReachabilityEngine._solve_phase`).
AUTO_PROBE_SHARE = 4
#: Shortest reading of the idle cores ``workers: auto`` decides on [s]: ten ticks of the
#: kernel's 10 ms per-CPU times, so that a core's idle share is read to about 10 %.
AUTO_WATCH_S = 0.1
#: Oldest reading ``workers: auto`` decides on [s]: a run's first phase that took longer
#: is read afresh (the load may have changed), over a quarter chunk.
AUTO_WATCH_RECENT_S = 1.0
#: Default most targets per chunk, by backend (see ``chunk_size``).
_CHUNK = {"pinocchio": 8192, "mink": 2048}
#: Worker processes start by forking (they inherit the engine); elsewhere one process.
_CAN_FORK = "fork" in mp.get_all_start_methods()


@dataclass(frozen=True)
class _Phase:
    """The targets of one phase of a run and what each chunk of them is solved with."""

    targets: np.ndarray  # (M, 4, 4)
    seeds: np.ndarray | None  # (M, K, nq) or None
    hopeless: np.ndarray | None  # (M,) bool or None
    candidates: bool  # return step 1's candidates

    def args(self, at: np.ndarray) -> tuple[Any, ...]:
        """:meth:`ReachabilityEngine.solve`'s arguments for the positions ``at``."""
        return (
            self.targets[at],
            None if self.seeds is None else self.seeds[at],
            self.candidates,
            None if self.hopeless is None else self.hopeless[at],
        )


def available_cores() -> int:
    """Cores this process may run on (its CPU affinity), at least 1."""
    return _cores()


class ReachabilityEngine(ChunkSteps):
    """IK, collision, approach and retreat checks of grasp poses (see the module doc).

    Args:
        robot: The robot.
        checker: The collision world
            (:class:`~gcm_pipeline.robot.collision.CollisionChecker`), or None
            for pure kinematics (no collision checks, no clearance).
        backend: IK backend, ``"pinocchio"`` or ``"mink"``.
        position_tolerance: IK acceptance [m], > 0.
        orientation_tolerance: IK acceptance [rad], > 0.
        approach: The pre-grasp approach (a :class:`Move` with ``holding=False``)
            or None.
        retreat: The post-grasp retreat (``holding=True``) or None.
        validator: Optional extra check of grasp configurations,
            ``q (M, nq) -> (M,) str`` (``''`` = valid), run after the collision check.
        alternatives: Other IK solutions tried per target that fails a check (0:
            none; a 6R arm with closed-form branches tries every branch).
        workers: Processes (1: this one; ``"auto"``: at most :func:`available_cores`
            within a cgroup CPU quota, per run as
            :func:`~gcm_pipeline.reach.workers.auto_workers` decides from the run's
            size and the cores other processes leave idle, read while this
            process works alone: from the run's start, or a quarter chunk more
            when that was under 0.1 s; when it decides one, the run is
            ``workers=1``'s).
        chunk_size: Most targets per chunk (memory and progress granularity); on
            several workers the last chunks are smaller, so they finish together.
            None: 8,192 for the pinocchio backend (fewer, larger NumPy calls),
            2,048 for mink (it solves one target at a time: progress every few
            seconds).
        ik_options: Backend options for the IK of step 1 (e.g. ``random_seed``).
        solutions: Branches kept per reachable target (step 4; 1: only the answer).
        solution_separation: Two kept branches differ by more than this in
            some joint [rad].

    Raises:
        InputError: Bad tolerances, workers, chunk size or alternatives.
    """

    def __init__(
        self,
        robot: Robot,
        checker: Any | None = None,
        *,
        backend: str = "pinocchio",
        position_tolerance: float = 1e-4,
        orientation_tolerance: float = 1e-3,
        approach: Move | None = None,
        retreat: Move | None = None,
        validator: Callable[[np.ndarray], Any] | None = None,
        alternatives: int = 4,
        workers: int | str = 1,
        chunk_size: int | None = None,
        ik_options: Mapping[str, Any] | None = None,
        solutions: int = 1,
        solution_separation: float = 0.2,
    ) -> None:
        self.robot = robot
        self.checker = checker
        self.backend = backend
        self.position_tolerance = float(position_tolerance)
        self.orientation_tolerance = float(orientation_tolerance)
        for name, v in (
            ("position_tolerance", self.position_tolerance),
            ("orientation_tolerance", self.orientation_tolerance),
        ):
            if not np.isfinite(v) or v <= 0:
                raise InputError(f"{name} must be a positive finite number, got {v!r}")
        self.approach = approach
        self.retreat = retreat
        self.validator = validator
        if int(alternatives) != alternatives or alternatives < 0:
            raise InputError(f"alternatives must be an int >= 0, got {alternatives!r}")
        self.alternatives = int(alternatives)
        #: ``workers: auto``: each run decides its worker count (:func:`auto_workers`).
        self.auto = isinstance(workers, str) and workers == "auto"
        if self.auto:
            workers = quota_cores(available_cores())
        if isinstance(workers, bool) or not isinstance(workers, (int, np.integer)) or workers < 1:
            raise InputError(f"workers must be 'auto' or an int >= 1, got {workers!r}")
        self.workers = int(workers)
        #: Worker processes of the last run (``auto``: decided per run).
        self.workers_used = self.workers
        #: ``auto``: the idle cores its last decision read (None: none read, or unreadable).
        self.idle_seen: float | None = None
        if chunk_size is None:
            chunk_size = _CHUNK.get(backend, _CHUNK["mink"])
        if isinstance(chunk_size, bool) or int(chunk_size) != chunk_size or chunk_size < 1:
            raise InputError(f"chunk_size must be an int >= 1, got {chunk_size!r}")
        self.chunk_size = int(chunk_size)
        self.ik_options = dict(ik_options or {})
        if isinstance(solutions, bool) or int(solutions) != solutions or solutions < 1:
            raise InputError(f"solutions must be an int >= 1, got {solutions!r}")
        self.solutions = int(solutions)
        self.solution_separation = float(solution_separation)
        if not np.isfinite(self.solution_separation) or self.solution_separation <= 0:
            raise InputError(
                f"solution_separation must be a positive angle [rad], got {solution_separation!r}"
            )
        self._checks = SolutionChecks(
            robot,
            checker,
            validator,
            approach,
            retreat,
            backend=backend,
            position_tolerance=self.position_tolerance,
            orientation_tolerance=self.orientation_tolerance,
            ik_options=self.ik_options,
            spent=self._spent,
        )
        self._pool: Any = None
        self._pool_size = 0
        #: CPU time [s] of each step of the last :meth:`run`, summed over chunks
        #: and workers: ``ik``, ``collisions``, ``approach``, ``retreat``,
        #: ``alternatives`` (their IK), ``clearance``.
        self.timings: dict[str, float] = {}

    def __repr__(self) -> str:
        def move(m: Move | None) -> str:
            return "None" if m is None else f"{m.distance} m/{m.steps} steps"

        return (
            f"ReachabilityEngine(robot={self.robot.name!r}, backend={self.backend!r}, "
            f"collisions={self.checker is not None}, approach={move(self.approach)}, "
            f"retreat={move(self.retreat)}, alternatives={self.alternatives}, "
            f"solutions={self.solutions}, "
            f"workers={self.workers}, chunk_size={self.chunk_size})"
        )

    # --- the whole run ---------------------------------------------------------------------

    def run(
        self,
        targets: Any,
        *,
        neighbours: Any = None,
        seeds: Any = None,
        progress: Callable[[int], None] | None = None,
        return_candidates: bool = False,
    ) -> ReachResult:
        """Steps 1-5 for N targets, in chunks, on the engine's workers.

        Args:
            targets: Grasp-frame poses (N, 4, 4) in the robot's base frame [m].
            neighbours: Optional (N, K) int: row ``i`` is seeded from the final
                solutions of rows ``neighbours[i]`` (in that order; -1 = none);
                rows with neighbours are solved after all rows without.
            seeds: Optional warm starts (N, K, nq) [rad] tried after the
                neighbours' (NaN = none).
            progress: Called with the number of targets finished, after every chunk.
            return_candidates: Also return every converged IK candidate of step 1.

        Returns:
            The :class:`ReachResult`.

        Raises:
            InputError: Bad neighbours or seeds.
            GeometryError: Targets of the wrong shape, non-finite or non-rigid.
        """
        tgt = check_targets(targets)
        n, nq = tgt.shape[0], self.robot.nq
        seed_arr = check_seeds(seeds, n, nq)
        nb = check_neighbours(neighbours, n)
        nb = None if nb is None else nb.astype(int)
        out = _run_arrays(n, nq, self.solutions, self.checker is not None)
        cands: list[tuple[np.ndarray, np.ndarray, np.ndarray]] = []
        timings: dict[str, float] = {}
        if nb is None:
            phases = [np.arange(n)]
        else:
            has_nb = np.any(nb >= 0, axis=1)
            phases = [np.flatnonzero(~has_nb), np.flatnonzero(has_nb)]
        used, self.idle_seen = 1, None
        # what auto reads: the cores' idle time from here, while this process works alone
        watch = IdleProbe() if self.auto and _CAN_FORK else None
        for phase, rows in enumerate(phases):
            if rows.size == 0:
                continue
            sub = None if seed_arr is None else seed_arr[rows]
            hopeless = None
            if phase == 1:
                assert nb is not None
                sub, hopeless = _neighbour_seeds(nb[rows], out, sub)
            work = _Phase(tgt[rows], sub, hopeless, return_candidates)
            for at, part in self._solve_phase(work, watch):
                chunk_rows = rows[at]
                for key, arr in out.items():
                    if arr is not None:
                        arr[chunk_rows] = part[key]
                for key, value in part["timings"].items():
                    timings[key] = timings.get(key, 0.0) + value
                if part["candidates"] is not None:
                    i, cq, cr = part["candidates"]
                    cands.append((chunk_rows[i], cq, cr))
                if progress is not None:
                    progress(int(chunk_rows.size))
            used = max(used, self.workers_used)
            if self.workers_used > 1:  # the workers' CPU would read as other jobs' load
                watch = None
        self.workers_used = used
        self.timings = timings
        candidates = _gather_candidates(cands, nq) if return_candidates else None
        return _reach_result(out, candidates, self.solutions, self.checker is not None)

    # --- workers --------------------------------------------------------------------------

    def _solve_phase(
        self, work: _Phase, watch: IdleProbe | None
    ) -> Iterator[tuple[np.ndarray, dict[str, Any]]]:
        """Each chunk's positions in ``work`` and its solved part, in order.

        A fixed ``workers``: :func:`guided_chunks` of the whole phase on that
        many processes. ``workers: auto``: as many workers as :func:`auto_workers`
        decides from the phase's size and the idle cores ``watch`` read since
        the run started, while this process worked alone (the set-up, a first
        phase solved here; None once workers ran: their CPU reads as other
        jobs'). When it has read them for less than ``AUTO_WATCH_S`` or more
        than ``AUTO_WATCH_RECENT_S``, or there is none, the first quarter chunk
        runs on this process while it reads on (or a new one reads), and the
        decision is for the rest; one worker then solves the rest of the first
        chunk and one worker's chunks (the chunks of ``workers: 1``, the first
        cut in two). A decision read from the run's start costs no chunk: one
        worker solves exactly the chunks of ``workers: 1``.
        """
        n, start = len(work.targets), 0
        workers = self.workers
        if self.auto:
            # the probe's chunk: long enough for the kernel's CPU times (10 ms ticks),
            # short enough that the other cores do not wait long for the decision
            probe_size = max(1, self.chunk_size // AUTO_PROBE_SHARE)
            workers = auto_workers(n - probe_size, self.chunk_size, self.workers, None)
            if workers > 1 and _CAN_FORK:
                if watch is not None and watch.watched_s() > AUTO_WATCH_RECENT_S:
                    watch = None  # an old reading: the load may have changed since
                if watch is None or watch.watched_s() < AUTO_WATCH_S:
                    watch = watch if watch is not None else IdleProbe()
                    first = np.arange(probe_size)
                    yield first, self.solve(*work.args(first))
                    start = probe_size
                self.idle_seen = watch.idle_cores()
                workers = auto_workers(n - start, self.chunk_size, workers, self.idle_seen)
        if workers == 1 and 0 < start < n:
            # one worker: the rest of the first chunk, then the chunks of ``workers: 1``
            first_end = max(start, min(n, self.chunk_size))
            ats = [np.arange(start, first_end)] if first_end > start else []
            ats += [at + first_end for at in guided_chunks(n - first_end, self.chunk_size, 1)]
        else:
            ats = [at + start for at in guided_chunks(n - start, self.chunk_size, workers)]
        self.workers_used = min(workers, len(ats)) if len(ats) > 1 and _CAN_FORK else 1
        yield from zip(ats, self._map([work.args(at) for at in ats], workers), strict=True)

    def _map(self, work: list[tuple[Any, ...]], workers: int) -> Iterator[dict[str, Any]]:
        """Solve the chunks (:meth:`solve`'s arguments) in order, here or on ``workers``."""
        if workers == 1 or len(work) < 2 or not _CAN_FORK:
            for args in work:
                yield self.solve(*args)
            return
        pool = self._get_pool(min(workers, len(work)))
        try:
            yield from pool.ordered(solve_in_worker, work)
        except BaseException:
            # Ctrl-C or a failing chunk: stop the workers before anything else
            self.close()
            raise

    def _get_pool(self, size: int) -> Any:
        """``size`` worker processes (the chunks' count at most: 64 workers for 5 chunks: 5)."""
        if self._pool is not None and (
            self._pool_size < size or (self.auto and self._pool_size > size)
        ):
            self.close()  # a larger run than the pool was started for, or auto chose fewer
        if self._pool is None:
            # warm the caches (seed library, MuJoCo model) so that workers inherit them
            probe = self.robot.fk(self.robot.home)
            solve_ik(self.robot, probe, self.backend, **self.ik_options)
            blas_controller()  # it reads the loaded libraries (about 10 ms): once, here
            kernels.get()  # compiled or read from Numba's cache once, here, not per worker
            WORKER["engine"] = self
            self._pool = ForkPool(size, initializer=_worker_signals)
            self._pool_size = size
            POOLS.add(self)
        return self._pool

    def close(self) -> None:
        """Stop the worker processes (they start again when needed)."""
        pool, self._pool = self._pool, None
        if pool is not None:
            pool.terminate()
            pool.join()

    def __enter__(self) -> ReachabilityEngine:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def __getstate__(self) -> dict[str, Any]:
        state = dict(self.__dict__)
        state["_pool"], state["_pool_size"] = None, 0
        return state


def _run_arrays(n: int, nq: int, k: int, clearance: bool) -> dict[str, Any]:
    """The result arrays of a run of N targets, before any chunk (``k`` branches kept)."""
    out: dict[str, Any] = {
        "reachable": np.zeros(n, dtype=bool),
        "reason": np.full(n, "", dtype=object),
        "q": np.full((n, nq), np.nan),
        "pos_err": np.full(n, np.nan),
        "rot_err": np.full(n, np.nan),
        "clearance": np.full(n, np.nan) if clearance else None,
        "q_pregrasp": np.full((n, nq), np.nan),
        "q_retreat": np.full((n, nq), np.nan),
        "q_rejected": np.full((n, nq), np.nan),
    }
    if k > 1:
        out.update(
            b_q=np.full((n, k, nq), np.nan),
            b_q_pregrasp=np.full((n, k, nq), np.nan),
            b_q_retreat=np.full((n, k, nq), np.nan),
            b_clearance=np.full((n, k), np.nan),
            b_count=np.zeros(n, dtype=np.int64),
        )
    return out


def _neighbour_seeds(
    ref: np.ndarray, out: dict[str, Any], sub: np.ndarray | None
) -> tuple[np.ndarray, np.ndarray]:
    """Seeds and short-schedule rows of the rows with neighbours ``ref`` (M, K).

    The neighbours' final solutions come first, then the given seeds ``sub``; a
    row gets a short seed schedule where every neighbour failed IK after its own
    full one (out of reach: no seed ran, so it does not count).
    """
    warm = np.where((ref >= 0)[:, :, None], out["q"][np.clip(ref, 0, None)], np.nan)
    seeds = warm if sub is None else np.concatenate([warm, sub], axis=1)
    no_ik = np.isin(out["reason"][np.clip(ref, 0, None)], _RAN_EVERY_SEED)
    hopeless = np.all(no_ik | (ref < 0), axis=1) & np.any(ref >= 0, axis=1)
    return seeds, hopeless


def _gather_candidates(
    cands: list[tuple[np.ndarray, np.ndarray, np.ndarray]], nq: int
) -> IKCandidates:
    """The chunks' IK candidates (rows of the run), sorted by row."""
    if cands:
        index = np.concatenate([c[0] for c in cands]).astype(int)
        cq = np.concatenate([c[1] for c in cands]).reshape(-1, nq)
        cr = np.concatenate([c[2] for c in cands]).astype(str)
    else:
        index, cq, cr = np.zeros(0, int), np.zeros((0, nq)), np.zeros(0, str)
    order = np.argsort(index, kind="stable")
    return IKCandidates(index[order], cq[order], cr[order])


def _reach_result(
    out: dict[str, Any], candidates: IKCandidates | None, k: int, clearance: bool
) -> ReachResult:
    """The :class:`ReachResult` of a run's filled arrays (``k`` branches kept)."""
    branches = None
    if k > 1:
        branches = Branches(
            q=out["b_q"],
            q_pregrasp=out["b_q_pregrasp"],
            q_retreat=out["b_q_retreat"],
            clearance=out["b_clearance"] if clearance else None,
            count=out["b_count"],
        )
    return ReachResult(
        reachable=out["reachable"],
        reason=out["reason"].astype(str),
        q=out["q"],
        pos_err=out["pos_err"],
        rot_err=out["rot_err"],
        clearance=out["clearance"],
        q_pregrasp=out["q_pregrasp"],
        q_retreat=out["q_retreat"],
        q_rejected=out["q_rejected"],
        candidates=candidates,
        branches=branches,
    )
