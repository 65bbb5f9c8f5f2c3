"""Inverse kinematics of the grasp frame: backend dispatch and verification.

:func:`solve_ik` validates the targets, drops the ones beyond the arm's reach,
hands the rest to a backend (``pinocchio``: batched Levenberg-Marquardt,
:mod:`gcm_pipeline.robot.ik_pinocchio`; ``mink``: MuJoCo differential IK,
:mod:`gcm_pipeline.robot.ik_mink`) and **verifies every success with
Pinocchio's own forward kinematics** (``pin.forwardKinematics`` +
``updateFramePlacement``) and the joint limits: a target is reported
reachable only if a configuration strictly inside the limits puts the grasp
frame within ``position_tolerance`` [m] and ``orientation_tolerance`` [rad].

An IK that fails is not an error: its row has ``success=False`` and a reason:

=========================== ==================================================
``out_of_reach``            farther from the shoulder than the arm reaches, or
                            (Panda kinematics) no elbow angle puts the wrist at
                            the distance from the shoulder the target asks
                            (:meth:`~gcm_pipeline.robot.analytic.PandaAnalyticIK.unreachable`)
``joint_limits``            reached only with joints outside their limits
``no_ik``                   no seed converged
``verification_failed``     the backend converged but Pinocchio disagrees
validator reasons           e.g. ``collision_self`` (see ``validator``)
=========================== ==================================================

Validators (for collision checking): ``validator(q)`` takes configurations
(M, nq) [rad] and returns (M,) strings, ``''`` for a valid configuration or a
reason. It is applied to every converged candidate before one is chosen, so a
target whose first solution collides keeps trying other seeds; if no valid
candidate remains, the last validator reason is the row's reason. With
``return_all=True`` the result also lists every converged candidate
(:class:`IKCandidates`), valid or not.
"""

from __future__ import annotations

import atexit
import multiprocessing as mp
import multiprocessing.pool
import os
import signal
import time
from collections.abc import Callable, Iterable, Iterator
from typing import Any, NamedTuple

import numpy as np

from gcm_pipeline.errors import GeometryError, InputError, WorkerLostError, unknown_choice
from gcm_pipeline.geometry.dualquat import dq_to_matrix
from gcm_pipeline.robot.ik_pinocchio import analytic_solver, rotation_angle
from gcm_pipeline.robot.model import Robot, load_robot

__all__ = [
    "BACKENDS",
    "IK_REASONS",
    "IKCandidates",
    "IKResult",
    "check_targets",
    "solve_ik",
    "verify_solutions",
    "world_to_base_targets",
]

BACKENDS = ("pinocchio", "mink")

#: Reasons of targets that no IK solution reaches.
IK_REASONS = ("out_of_reach", "joint_limits", "no_ik", "verification_failed")

Validator = Callable[[np.ndarray], Any]


class IKCandidates(NamedTuple):
    """Every converged IK candidate (``return_all=True``).

    Attributes:
        index: Target row of each candidate (M,) int.
        q: Candidate configurations (M, nq) [rad], inside the joint limits.
        reason: Validator reason per candidate (M,) str, ``''`` if valid.
    """

    index: np.ndarray  # type: ignore[assignment]  # shadows tuple.index on purpose
    q: np.ndarray
    reason: np.ndarray


class IKResult(NamedTuple):
    """Result of :func:`solve_ik` for N targets.

    Attributes:
        q: Solutions (N, nq) [rad]; NaN rows where ``success`` is False.
        success: (N,) bool, True only for solutions verified by Pinocchio FK.
        pos_err: Position error (N,) [m] of the solution, or of the best
            attempt for failures (NaN if none was made).
        rot_err: Orientation error (N,) [rad], geodesic angle, same rules.
        reason: (N,) str, ``''`` for successes, else why (see module doc).
        backend: Name of the backend that solved.
        candidates: Every converged candidate when ``return_all=True``, else None.
    """

    q: np.ndarray
    success: np.ndarray
    pos_err: np.ndarray
    rot_err: np.ndarray
    reason: np.ndarray
    backend: str = "pinocchio"
    candidates: IKCandidates | None = None

    def __repr__(self) -> str:
        n = len(self.success)
        ok = int(np.count_nonzero(self.success))
        reasons, counts = np.unique(self.reason[~self.success].astype(str), return_counts=True)
        fails = ", ".join(f"{r}: {c}" for r, c in zip(reasons, counts, strict=False))
        return (
            f"IKResult(backend={self.backend!r}, {ok}/{n} reached"
            + (f", failures {{{fails}}}" if fails else "")
            + ")"
        )


def _backend(name: str) -> Callable[..., dict[str, Any]]:
    if name == "pinocchio":
        from gcm_pipeline.robot import ik_pinocchio

        return ik_pinocchio.solve
    if name == "mink":
        from gcm_pipeline.robot import ik_mink

        return ik_mink.solve
    raise InputError(unknown_choice("IK backend", name, BACKENDS))


def check_targets(targets: Any, name: str = "targets") -> np.ndarray:
    """Validate poses and return them as a float array (N, 4, 4).

    Args:
        targets: Homogeneous transforms (N, 4, 4) or one (4, 4).
        name: How to call them in error messages.

    Raises:
        GeometryError: Wrong shape, non-finite values, or a non-rigid matrix
            (names the first bad row).
    """
    arr = np.asarray(targets, dtype=float)
    if arr.shape == (4, 4):
        arr = arr[None]
    if arr.ndim != 3 or arr.shape[1:] != (4, 4):
        raise GeometryError(f"{name} must have shape (N, 4, 4), got {np.shape(targets)}")
    bad = ~np.all(np.isfinite(arr), axis=(1, 2))
    if np.any(bad):
        i = int(np.flatnonzero(bad)[0])
        raise GeometryError(f"{name}[{i}] has non-finite values: {arr[i].tolist()}")
    rot = arr[:, :3, :3]
    ortho = np.abs(rot.transpose(0, 2, 1) @ rot - np.eye(3)).max(axis=(1, 2))
    det = np.linalg.det(rot)
    bottom = np.abs(arr[:, 3] - np.array([0.0, 0.0, 0.0, 1.0])).max(axis=1)
    bad = (ortho > 1e-6) | (det < 0) | (bottom > 1e-9)
    if np.any(bad):
        i = int(np.flatnonzero(bad)[0])
        raise GeometryError(
            f"{name}[{i}] is not a rigid transform (|R^T R - I| = {ortho[i]:.2e}, "
            f"det R = {det[i]:.6f}, last row {arr[i, 3].tolist()})"
        )
    return arr


def world_to_base_targets(dq: Any, base_pose: Any = None) -> np.ndarray:
    """Grasp-frame poses in the robot base frame from world dual quaternions.

    Args:
        dq: Unit dual quaternions (N, 8) of the grasp frame in the world,
            layout ``[rw, rx, ry, rz, dw, dx, dy, dz]``.
        base_pose: Robot base in the world, (4, 4) or an object with a
            ``matrix()`` method (a config ``Pose``);
            identity if None.

    Returns:
        Homogeneous transforms (N, 4, 4): ``inv(base_pose) @ T_world``.

    Raises:
        GeometryError: Wrong shape, non-finite or non-unit dual quaternions,
            or a non-rigid ``base_pose``.
    """
    arr = np.asarray(dq, dtype=float)
    if arr.ndim != 2 or arr.shape[1] != 8:
        raise GeometryError(f"grasp column 'dq' must have shape (N, 8), got {np.shape(dq)}")
    bad = ~np.all(np.isfinite(arr), axis=1)
    if np.any(bad):
        i = int(np.flatnonzero(bad)[0])
        raise GeometryError(f"grasp column 'dq' row {i} has non-finite values: {arr[i].tolist()}")
    norm = np.linalg.norm(arr[:, :4], axis=1)
    dot = np.einsum("ij,ij->i", arr[:, :4], arr[:, 4:])
    bad = (np.abs(norm - 1.0) > 1e-6) | (np.abs(dot) > 1e-6)
    if np.any(bad):
        i = int(np.flatnonzero(bad)[0])
        raise GeometryError(
            f"grasp column 'dq' row {i} is not a unit dual quaternion "
            f"(|real| = {norm[i]:.6f}, real.dual = {dot[i]:.2e})"
        )
    world = dq_to_matrix(arr)
    if base_pose is None:
        return world
    if hasattr(base_pose, "matrix"):
        base_pose = base_pose.matrix()
    base = check_targets(base_pose, name="base_pose")
    if base.shape[0] != 1:
        raise GeometryError(f"base_pose must have shape (4, 4), got {np.shape(base_pose)}")
    inv = np.eye(4)
    rot = base[0, :3, :3]
    inv[:3, :3] = rot.T
    inv[:3, 3] = -rot.T @ base[0, :3, 3]
    return inv @ world


def _tolerance(name: str, value: Any) -> float:
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise InputError(f"{name} must be a number, got {value!r}") from None
    if not np.isfinite(v) or v <= 0:
        raise InputError(f"{name} must be a positive finite number, got {value!r}")
    return v


def verify_solutions(
    robot: Robot, q: np.ndarray, targets: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Errors of configurations against targets, with Pinocchio's own FK.

    Args:
        robot: The robot.
        q: Configurations (M, nq) [rad].
        targets: Poses (M, 4, 4) in the base frame.

    Returns:
        ``(pos_err [m], rot_err [rad], inside)``: (M,) each; ``inside`` says
        whether q is strictly inside the joint limits.
    """
    if q.shape[0] == 0:
        z = np.zeros(0)
        return z, z, np.zeros(0, dtype=bool)
    reached = robot.fk_pinocchio(q)
    pos_err = np.linalg.norm(reached[:, :3, 3] - targets[:, :3, 3], axis=1)
    rot_err = rotation_angle(targets[:, :3, :3].transpose(0, 2, 1) @ reached[:, :3, :3])
    return pos_err, rot_err, robot.within_limits(q, strict=True)


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
    solve: Callable[..., dict[str, Any]],
    robot: Robot,
    validator: Validator | None,
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
    pool = ForkPool(workers, initializer=_worker_signals)
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


def _cores() -> int:
    """Cores this process may run on (its CPU affinity), at least 1."""
    if hasattr(os, "sched_getaffinity"):
        return max(1, len(os.sched_getaffinity(0)))
    return max(1, os.cpu_count() or 1)  # pragma: no cover - not Linux


#: How often the workers are looked at while a result is awaited [s].
_WORKER_POLL = 0.25


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


def _worker_signals() -> None:
    """In a worker: Ctrl-C and hang-ups are the parent's to handle, SIGTERM ends it.

    The parent stops the pool on an interrupt (:func:`_run_backend`); a worker
    that raised KeyboardInterrupt itself would print a traceback and leave
    ``pool.map`` waiting for a result that never comes.
    """
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    if hasattr(signal, "SIGHUP"):
        signal.signal(signal.SIGHUP, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, signal.SIG_DFL)


def _worker(args: tuple[np.ndarray, np.ndarray | None]) -> dict[str, Any]:
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


def _run_backend(
    solve: Callable[..., dict[str, Any]],
    robot: Robot,
    targets: np.ndarray,
    seeds: np.ndarray | None,
    validator: Validator | None,
    return_all: bool,
    workers: int,
    kwargs: dict[str, Any],
) -> dict[str, Any]:
    n = targets.shape[0]
    parallel = workers > 1 and n >= 2 * workers and "fork" in mp.get_all_start_methods()
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
            solve(robot, t, seeds=s, validator=validator, return_all=return_all, **kwargs)
            for t, s in chunks
        ]
    out: dict[str, Any] = {}
    for key in ("q", "success", "pos_err", "rot_err", "reason"):
        out[key] = np.concatenate([p[key] for p in parts])
    if return_all:
        out["all_index"] = np.concatenate(
            [p["all_index"] + a for p, a in zip(parts, bounds[:-1], strict=False)]
        )
        out["all_q"] = np.concatenate([p["all_q"] for p in parts])
        out["all_reason"] = np.concatenate([p["all_reason"] for p in parts])
    return out


def solve_ik(
    robot: Robot | str,
    targets: Any,
    backend: str = "pinocchio",
    *,
    position_tolerance: float = 1e-4,
    orientation_tolerance: float = 1e-3,
    seeds: Any = None,
    neighbours: Any = None,
    validator: Validator | None = None,
    return_all: bool = False,
    workers: int | str = 1,
    **options: Any,
) -> IKResult:
    """Solve the inverse kinematics of the grasp frame for N target poses.

    Args:
        robot: A :class:`Robot` or a spec name/path for :func:`load_robot`.
        targets: Grasp-frame poses (N, 4, 4) in the robot base frame [m].
        backend: ``"pinocchio"`` (default, batched LM) or ``"mink"``.
        position_tolerance: Max position error of a success [m], > 0.
        orientation_tolerance: Max orientation error (geodesic angle) [rad], > 0.
        seeds: Optional warm-start configurations (N, K, nq) [rad] tried first;
            NaN rows are ignored.
        neighbours: Optional (N, K) int: for row i, rows of ``targets`` whose
            solutions seed row i (in that order; -1 = none). Rows without
            neighbours are solved first, then the others seeded from them.
        validator: Optional ``q (M, nq) -> (M,) str`` ('' = valid) applied to
            converged candidates before one is chosen (see module doc).
        return_all: Also return every converged candidate (``result.candidates``).
        workers: Processes to split the targets over (``"auto"`` or ``0``: the
            cores this process may run on).
        **options: Backend options, e.g. ``max_iterations`` (see
            :class:`~gcm_pipeline.robot.ik_pinocchio.PinocchioIKOptions` and
            :class:`~gcm_pipeline.robot.ik_mink.MinkIKOptions`).

    Returns:
        The :class:`IKResult`; every success verified by Pinocchio FK.

    Raises:
        InputError: Unknown backend or option, tolerance <= 0, bad seeds or
            neighbours.
        GeometryError: Targets of the wrong shape, non-finite or non-rigid.
    """
    robot = load_robot(robot)
    solve = _backend(backend)
    tol_p = _tolerance("position_tolerance", position_tolerance)
    tol_r = _tolerance("orientation_tolerance", orientation_tolerance)
    tgt = check_targets(targets)
    n, nq = tgt.shape[0], robot.nq
    if isinstance(workers, bool) or not (
        workers == "auto" or (isinstance(workers, (int, np.integer)) and workers >= 0)
    ):
        raise InputError(f"workers must be 'auto' or an int >= 0 (0: all cores), got {workers!r}")
    processes = int(workers) if workers not in ("auto", 0) else _cores()
    seed_arr: np.ndarray | None = None
    if seeds is not None:
        seed_arr = np.asarray(seeds, dtype=float)
        if seed_arr.ndim == 2:
            seed_arr = seed_arr[:, None, :]
        if seed_arr.ndim != 3 or seed_arr.shape[0] != n or seed_arr.shape[2] != nq:
            raise InputError(f"seeds must have shape ({n}, K, {nq}), got {np.shape(seeds)}")
    nb: np.ndarray | None = None
    if neighbours is not None:
        nb = np.asarray(neighbours)
        if nb.ndim == 1:
            nb = nb[:, None]
        if nb.ndim != 2 or nb.shape[0] != n or not np.issubdtype(nb.dtype, np.integer):
            raise InputError(
                f"neighbours must be an int array of shape ({n}, K), got {np.shape(neighbours)}"
            )
        if np.any((nb < -1) | (nb >= n)):
            raise InputError(f"neighbours must be row ids in [-1, {n - 1}]")
    kwargs = dict(options, position_tolerance=tol_p, orientation_tolerance=tol_r)

    q = np.full((n, nq), np.nan)
    success = np.zeros(n, dtype=bool)
    pos_err = np.full(n, np.nan)
    rot_err = np.full(n, np.nan)
    reason = np.full(n, "", dtype=object)
    cand: list[tuple[np.ndarray, np.ndarray, np.ndarray]] = []

    # cheap pre-filter: beyond the arm's reach from the shoulder, and for the Panda's
    # kinematics where no elbow angle puts the wrist at the distance the target asks
    dist = np.linalg.norm(tgt[:, :3, 3] - robot.shoulder, axis=1)
    far = dist > robot.max_reach + tol_p
    solver = analytic_solver(robot)
    if solver is not None and n:
        far |= solver.unreachable(tgt[:, :3, :3], tgt[:, :3, 3], tol_p, tol_r)
    reason[far] = "out_of_reach"

    phases: list[np.ndarray]
    if nb is None:
        phases = [np.flatnonzero(~far)]
    else:
        has_nb = np.any(nb >= 0, axis=1)
        phases = [np.flatnonzero(~far & ~has_nb), np.flatnonzero(~far & has_nb)]
    for phase, rows in enumerate(phases):
        if rows.size == 0:
            continue
        sub_seeds = None if seed_arr is None else seed_arr[rows]
        if phase == 1:
            assert nb is not None
            ref = nb[rows]
            warm = np.where((ref >= 0)[:, :, None], q[np.clip(ref, 0, None)], np.nan)
            sub_seeds = warm if sub_seeds is None else np.concatenate([warm, sub_seeds], axis=1)
        raw = _run_backend(
            solve, robot, tgt[rows], sub_seeds, validator, return_all, processes, kwargs
        )
        ok = np.asarray(raw["success"], dtype=bool)
        q_rows = np.asarray(raw["q"], dtype=float)
        # independent verification of every success by Pinocchio FK + joint limits
        pe, re, inside = verify_solutions(robot, q_rows[ok], tgt[rows][ok])
        good = np.zeros(rows.size, dtype=bool)
        good[ok] = (pe <= tol_p) & (re <= tol_r) & inside
        pos_err[rows] = raw["pos_err"]
        rot_err[rows] = raw["rot_err"]
        pos_err[rows[ok]] = pe
        rot_err[rows[ok]] = re
        success[rows] = good
        q[rows[good]] = q_rows[good]
        reason[rows] = np.asarray(raw["reason"], dtype=object)
        reason[rows[ok & ~good]] = "verification_failed"
        reason[rows[good]] = ""
        if return_all:
            cand.append((rows[raw["all_index"]], raw["all_q"], raw["all_reason"]))
    candidates = None
    if return_all:
        if cand:
            index = np.concatenate([c[0] for c in cand]).astype(int)
            cq = np.concatenate([c[1] for c in cand]).reshape(-1, nq)
            creason = np.concatenate([c[2] for c in cand]).astype(str)
        else:
            index, cq, creason = np.zeros(0, int), np.zeros((0, nq)), np.zeros(0, str)
        order = np.argsort(index, kind="stable")
        candidates = IKCandidates(index[order], cq[order], creason[order])
    return IKResult(
        q=q,
        success=success,
        pos_err=pos_err,
        rot_err=rot_err,
        reason=reason.astype(str),
        backend=backend,
        candidates=candidates,
    )
