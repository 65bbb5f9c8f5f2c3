"""Inverse kinematics of the grasp frame: backend dispatch and verification.

:func:`solve_ik` validates the targets, drops the ones beyond the arm's reach,
hands the rest to a backend (``pinocchio``: batched Levenberg-Marquardt,
:mod:`gcm_pipeline.robot.ik.pinocchio_backend`; ``mink``: MuJoCo differential IK,
:mod:`gcm_pipeline.robot.ik.mink_backend`) and **verifies every success with
Pinocchio's own forward kinematics** (``pin.forwardKinematics`` +
``updateFramePlacement``) and the joint limits: a target is reported
reachable only if a configuration strictly inside the limits puts the grasp
frame within ``position_tolerance`` [m] and ``orientation_tolerance`` [rad].

An IK that fails is not an error: its row has ``success=False`` and a reason:

=========================== ==================================================
``out_of_reach``            farther from the shoulder than the arm reaches, or
                            (Panda kinematics) no elbow angle puts the wrist at
                            the distance from the shoulder the target asks
                            (:meth:`~gcm_pipeline.robot.ik.panda.PandaAnalyticIK.unreachable`)
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
(:class:`IKCandidates`), valid or not; the pinocchio backend can also hand
them, as it finds them, to a ``settle`` callback that stops the search for the
targets that need no more.

A backend is a function of the :class:`IKBackend` protocol; it returns raw,
unverified answers, which :func:`solve_ik` verifies.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, Protocol

import numpy as np

from gcm_pipeline.errors import GeometryError, InputError, choice_error
from gcm_pipeline.geometry.dualquat import dq_to_matrix
from gcm_pipeline.robot.ik import mink_backend, pinocchio_backend
from gcm_pipeline.robot.ik.answer import BackendAnswer
from gcm_pipeline.robot.ik.lm import rotation_angle
from gcm_pipeline.robot.ik.panda import analytic_solver
from gcm_pipeline.robot.ik.pool import cores, run_backend
from gcm_pipeline.robot.model import Robot, RobotSpec, as_robot

__all__ = [
    "BACKENDS",
    "IK_REASONS",
    "IKBackend",
    "IKCandidates",
    "IKResult",
    "Validator",
    "check_targets",
    "solve_ik",
    "verify_solutions",
    "world_to_base_targets",
]

BACKENDS = ("pinocchio", "mink")

#: Reasons of targets that no IK solution reaches.
IK_REASONS = ("out_of_reach", "joint_limits", "no_ik", "verification_failed")

Validator = Callable[[np.ndarray], Any]


class IKBackend(Protocol):
    """An IK backend: raw, unverified answers for validated targets.

    Args:
        robot: The robot.
        targets: Grasp-frame poses (N, 4, 4) in the base frame, already validated.
        position_tolerance: [m], > 0.
        orientation_tolerance: [rad], > 0.
        seeds: Optional warm starts (N, K, nq) [rad]; NaN rows are skipped.
        validator: Optional ``q (M, nq) -> (M,) str`` reasons ('' = valid),
            applied to converged candidates before one is chosen.
        return_all: Also return every converged candidate.
        **options: The backend's own options (unknown names: :class:`InputError`).

    Returns:
        The :class:`~gcm_pipeline.robot.ik.answer.BackendAnswer` (with the
        ``all_*`` candidates when ``return_all``).
    """

    def __call__(
        self,
        robot: Any,
        targets: np.ndarray,
        *,
        position_tolerance: float,
        orientation_tolerance: float,
        seeds: np.ndarray | None = None,
        validator: Validator | None = None,
        return_all: bool = False,
        **options: Any,
    ) -> BackendAnswer:
        """Raw answers for ``targets`` (see the class docstring)."""
        ...


_SOLVERS: dict[str, IKBackend] = {
    "pinocchio": pinocchio_backend.solve,
    "mink": mink_backend.solve,
}


@dataclass(frozen=True, eq=False)
class IKCandidates:
    """Every converged IK candidate (``return_all=True``).

    Attributes:
        index: Target row of each candidate (M,) int.
        q: Candidate configurations (M, nq) [rad], inside the joint limits.
        reason: Validator reason per candidate (M,) str, ``''`` if valid.
    """

    index: np.ndarray
    q: np.ndarray
    reason: np.ndarray


@dataclass(frozen=True, eq=False, repr=False)
class IKResult:
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


def _backend(name: str) -> IKBackend:
    solve = _SOLVERS.get(name) if isinstance(name, str) else None
    if solve is None:
        raise choice_error(InputError, "IK backend", name, BACKENDS)
    return solve


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


def solve_ik(
    robot: Robot | RobotSpec,
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
    settle: Callable[[np.ndarray, np.ndarray], np.ndarray] | None = None,
    **options: Any,
) -> IKResult:
    """Solve the inverse kinematics of the grasp frame for N target poses.

    Args:
        robot: A :class:`Robot` or a :class:`RobotSpec` (by name: ``gcm_pipeline.load_robot``).
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
        settle: With ``return_all`` (pinocchio): ``(index, q) -> (N,) bool`` gets each
            candidate once as the stages find them (a target's in the order of
            ``result.candidates``), returns the targets that need no more (then skipped).
            The search then runs in this process, whatever ``workers`` says.
        **options: Backend options, e.g. ``max_iterations`` (see
            :class:`~gcm_pipeline.robot.ik.lm.PinocchioIKOptions` and
            :class:`~gcm_pipeline.robot.ik.mink_backend.MinkIKOptions`).

    Returns:
        The :class:`IKResult`; every success verified by Pinocchio FK.

    Raises:
        InputError: Unknown backend or option, tolerance <= 0, bad seeds or
            neighbours; ``settle`` without the pinocchio backend and
            ``return_all``, or answering other than (N,).
        GeometryError: Targets of the wrong shape, non-finite or non-rigid.
    """
    robot = as_robot(robot)
    solve = _backend(backend)
    tol_p = _tolerance("position_tolerance", position_tolerance)
    tol_r = _tolerance("orientation_tolerance", orientation_tolerance)
    tgt = check_targets(targets)
    n, nq = tgt.shape[0], robot.nq
    processes = _processes(workers)
    seed_arr = check_seeds(seeds, n, nq)
    nb = check_neighbours(neighbours, n)
    kwargs = _backend_kwargs(options, tol_p, tol_r, backend, return_all, settle)

    q = np.full((n, nq), np.nan)
    success = np.zeros(n, dtype=bool)
    pos_err = np.full(n, np.nan)
    rot_err = np.full(n, np.nan)
    reason = np.full(n, "", dtype=object)
    cand: list[tuple[np.ndarray, np.ndarray, np.ndarray]] = []

    far = _out_of_reach(robot, tgt, tol_p, tol_r)
    reason[far] = "out_of_reach"

    for phase, rows in enumerate(_phases(far, nb)):
        if rows.size == 0:
            continue
        sub_seeds = _phase_seeds(phase, rows, seed_arr, nb, q)
        kw = kwargs if settle is None else {**kwargs, "settle": _settle_rows(settle, rows, n)}
        raw = run_backend(solve, robot, tgt[rows], sub_seeds, validator, return_all, processes, kw)
        ok, good, q_rows, pe, re = _verify(robot, tgt[rows], raw, tol_p, tol_r)
        pos_err[rows] = raw.pos_err
        rot_err[rows] = raw.rot_err
        pos_err[rows[ok]] = pe
        rot_err[rows[ok]] = re
        success[rows] = good
        q[rows[good]] = q_rows[good]
        reason[rows] = np.asarray(raw.reason, dtype=object)
        reason[rows[ok & ~good]] = "verification_failed"
        reason[rows[good]] = ""
        if return_all:
            assert raw.all_index is not None and raw.all_q is not None
            assert raw.all_reason is not None
            cand.append((rows[raw.all_index], raw.all_q, raw.all_reason))
    return IKResult(
        q=q,
        success=success,
        pos_err=pos_err,
        rot_err=rot_err,
        reason=reason.astype(str),
        backend=backend,
        candidates=_gather_candidates(cand, nq) if return_all else None,
    )


def _backend_kwargs(
    options: dict[str, Any],
    tol_p: float,
    tol_r: float,
    backend: str,
    return_all: bool,
    settle: Callable[[np.ndarray, np.ndarray], np.ndarray] | None,
) -> dict[str, Any]:
    """The backend's options with the tolerances; a ``settle`` it cannot take is an error."""
    if settle is not None and (backend != "pinocchio" or not return_all):
        raise InputError("settle needs the pinocchio backend and return_all")
    return dict(options, position_tolerance=tol_p, orientation_tolerance=tol_r)


def _settle_rows(
    settle: Callable[[np.ndarray, np.ndarray], np.ndarray], rows: np.ndarray, n: int
) -> Callable[[np.ndarray, np.ndarray], np.ndarray]:
    """``settle`` of all ``n`` targets as a callback of the backend's targets ``rows``."""

    def local(index: np.ndarray, q: np.ndarray) -> np.ndarray:
        settled = np.asarray(settle(rows[index], q))
        if settled.shape != (n,):
            raise InputError(f"settle returned shape {settled.shape}, expected ({n},)")
        return settled.astype(bool)[rows]

    return local


def _phases(far: np.ndarray, nb: np.ndarray | None) -> list[np.ndarray]:
    """The rows solved in each phase: without neighbours first, then those seeded by them."""
    if nb is None:
        return [np.flatnonzero(~far)]
    has_nb = np.any(nb >= 0, axis=1)
    return [np.flatnonzero(~far & ~has_nb), np.flatnonzero(~far & has_nb)]


def _phase_seeds(
    phase: int, rows: np.ndarray, seeds: np.ndarray | None, nb: np.ndarray | None, q: np.ndarray
) -> np.ndarray | None:
    """Seeds (len(rows), K, nq) of a phase's rows.

    The neighbours' solutions ``q`` (second phase; NaN where none), then the given seeds.
    """
    sub_seeds = None if seeds is None else seeds[rows]
    if phase == 1:
        assert nb is not None
        ref = nb[rows]
        warm = np.where((ref >= 0)[:, :, None], q[np.clip(ref, 0, None)], np.nan)
        sub_seeds = warm if sub_seeds is None else np.concatenate([warm, sub_seeds], axis=1)
    return sub_seeds


def _processes(workers: Any) -> int:
    """Worker processes of ``workers`` (``"auto"`` or 0: the usable cores)."""
    if isinstance(workers, bool) or not (
        workers == "auto" or (isinstance(workers, (int, np.integer)) and workers >= 0)
    ):
        raise InputError(f"workers must be 'auto' or an int >= 0 (0: all cores), got {workers!r}")
    return int(workers) if workers not in ("auto", 0) else cores()


def check_seeds(seeds: Any, n: int, nq: int) -> np.ndarray | None:
    """Warm starts as (n, K, nq) floats; one per target may come as (n, nq)."""
    if seeds is None:
        return None
    seed_arr = np.asarray(seeds, dtype=float)
    if seed_arr.ndim == 2:
        seed_arr = seed_arr[:, None, :]
    if seed_arr.ndim != 3 or seed_arr.shape[0] != n or seed_arr.shape[2] != nq:
        raise InputError(f"seeds must have shape ({n}, K, {nq}), got {np.shape(seeds)}")
    return seed_arr


def check_neighbours(neighbours: Any, n: int) -> np.ndarray | None:
    """Neighbour rows as (n, K) ints in [-1, n - 1]; one per target may come as (n,)."""
    if neighbours is None:
        return None
    nb = np.asarray(neighbours)
    if nb.ndim == 1:
        nb = nb[:, None]
    if nb.ndim != 2 or nb.shape[0] != n or not np.issubdtype(nb.dtype, np.integer):
        raise InputError(
            f"neighbours must be an int array of shape ({n}, K), got {np.shape(neighbours)}"
        )
    if np.any((nb < -1) | (nb >= n)):
        raise InputError(f"neighbours must be row ids in [-1, {n - 1}]")
    return nb


def _gather_candidates(
    cand: list[tuple[np.ndarray, np.ndarray, np.ndarray]], nq: int
) -> IKCandidates:
    """The candidates of every phase, in target order (stable)."""
    if cand:
        index = np.concatenate([c[0] for c in cand]).astype(int)
        cq = np.concatenate([c[1] for c in cand]).reshape(-1, nq)
        creason = np.concatenate([c[2] for c in cand]).astype(str)
    else:
        index, cq, creason = np.zeros(0, int), np.zeros((0, nq)), np.zeros(0, str)
    order = np.argsort(index, kind="stable")
    return IKCandidates(index[order], cq[order], creason[order])


def _out_of_reach(robot: Robot, tgt: np.ndarray, tol_p: float, tol_r: float) -> np.ndarray:
    """Targets (N,) bool that no configuration reaches, by a cheap test.

    Beyond the arm's reach from the shoulder, and for the Panda's kinematics
    where no elbow angle puts the wrist at the distance the target asks.
    """
    dist = np.linalg.norm(tgt[:, :3, 3] - robot.shoulder, axis=1)
    far = dist > robot.max_reach + tol_p
    solver = analytic_solver(robot)
    if solver is not None and tgt.shape[0]:
        far |= solver.unreachable(tgt[:, :3, :3], tgt[:, :3, 3], tol_p, tol_r)
    return far


def _verify(
    robot: Robot, tgt: np.ndarray, raw: BackendAnswer, tol_p: float, tol_r: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Independent verification of a backend's successes by Pinocchio FK + joint limits.

    Returns:
        ``(ok, good, q, pos_err, rot_err)``: the backend's successes (M,), those
        verified (M,), its configurations (M, nq) [rad], and the verified
        errors of the successes (count of ``ok``,) [m], [rad].
    """
    ok = np.asarray(raw.success, dtype=bool)
    q_rows = np.asarray(raw.q, dtype=float)
    pe, re, inside = verify_solutions(robot, q_rows[ok], tgt[ok])
    good = np.zeros(ok.size, dtype=bool)
    good[ok] = (pe <= tol_p) & (re <= tol_r) & inside
    return ok, good, q_rows, pe, re
