r"""The batched Levenberg-Marquardt of the default IK backend, its options and pose errors.

All (target, seed) pairs are solved at once. The chain (joint placements and axes read out
of the Pinocchio model, see :class:`~gcm_pipeline.robot.chain.KinematicChain`)
is evaluated in vectorised NumPy (or the compiled kernel,
:mod:`~gcm_pipeline.robot.kernels`); each iteration takes, for every still-active
(target, seed) pair, the damped least-squares step

.. math::

    \Delta q = J^\top (J J^\top + \lambda I)^{-1} e, \qquad
    \lambda = \lambda_0 \lVert e \rVert^2 + \lambda_{\min},

where ``e = [p* - p; log(R* R^T)]`` is the pose error in base-frame axes and
``J`` the LOCAL_WORLD_ALIGNED grasp-frame Jacobian. Joints that the step would
push across a limit are frozen at it and the step is re-solved with the others
(clamped DLS), so iterates stay inside the limits; a (target, seed) pair whose
error stops shrinking is dropped early.

:func:`raise_manipulability` adds null-space steps that raise the Yoshikawa
manipulability of solutions at fixed pose.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from gcm_pipeline.errors import InputError, choice_error
from gcm_pipeline.robot import kernels
from gcm_pipeline.robot.manipulability import yoshikawa

__all__ = [
    "PinocchioIKOptions",
    "levenberg_marquardt",
    "log3",
    "pose_errors",
    "raise_manipulability",
    "rotation_angle",
    "yoshikawa_of",
]


@dataclass(frozen=True)
class PinocchioIKOptions:
    r"""Options of the batched LM solver (pass them as keywords to ``solve_ik``).

    Attributes:
        analytic: Solve first in closed form where the arm has the Panda's
            kinematics (:mod:`~gcm_pipeline.robot.ik.panda`); the LM rounds
            then run only for the targets that this leaves unsolved.
        analytic_samples: Values of joint 7 tried with the preferred one (that
            of the first seed, else of home), evenly spaced over its range; the
            targets this leaves unsolved get 8 times as many, then 64 times
            (0: only the preferred value and values around it, no grid).
        unseeded: The closed form's preferred configuration for a target
            without a given seed: ``home`` (the solution nearest the home
            configuration) or ``library`` (nearest the library's configuration
            nearest in pose, where the LM would start; a KD-tree query per target).
        fallback_library_seeds: After a closed-form search over the whole grid,
            the LM's library seeds are cut to this many.
        fallback_random_restarts: ... and its random restarts to this many.
        max_iterations: LM iterations per seed.
        stall_after: Iteration from which stalled pairs are dropped.
        stall_ratio: A pair is dropped when its error is not below this
            fraction of its error two iterations earlier (0 disables).
        library_size: Random configurations in the seed library.
        library_seeds: Nearest library entries tried per target (in rounds).
        random_restarts: Extra uniformly random seeds for targets still failing.
        give_up_position: Random restarts are skipped for targets whose best
            attempt from the given, library and home seeds stayed farther than
            this [m] (0: never skip). Reachable targets that the first seeds miss
            end within a few cm; unreachable ones stay far, and would otherwise
            cost every restart.
        first_round_seeds: Seeds solved at once in the first round; with more
            than one, the converged solution of best manipulability is kept.
        round_seeds: Seeds solved at once per target in the next rounds.
        sequential_rounds: Rounds run before all remaining given, library and
            home seeds are tried at once (fewer, larger batches).
        min_solutions: Stop trying seeds for a target once it has this many
            valid converged solutions (more gives more choice, costs time).
        home_seed: Try the home configuration after the library seeds (a
            path's waypoints turn it off: a solution far from the previous
            waypoint is of no use there).
        diagnose_limits: For targets no seed reaches, run once more without
            the joint limits to tell ``joint_limits`` from ``no_ik`` (a path's
            waypoints do not need the distinction).
        manipulability_steps: Null-space steps that raise the Yoshikawa index
            of each solution while holding the pose (0: off).
        manipulability_step: Length of one such step in joint space [rad].
        damping: :math:`\lambda_0` of the adaptive damping.
        min_damping: :math:`\lambda_{\min}`.
        orientation_weight: Length scale [m] that weights the quaternion in the
            library's KD-tree (0.5 m per unit quaternion distance).
        library_eps: Approximation of the KD-tree queries (seeds need not be
            the exact nearest neighbours).
        inner_tolerance: Fraction of the user's tolerances used as the
            convergence threshold (converging further than asked makes the
            independent verification robust).
        limit_epsilon: Solutions are kept this far inside the joint limits [rad].
        random_seed: Seed of the library and the random restarts.
    """

    analytic: bool = True
    analytic_samples: int = 8
    fallback_library_seeds: int = 2
    unseeded: str = "home"
    fallback_random_restarts: int = 0
    max_iterations: int = 15
    stall_after: int = 4
    stall_ratio: float = 0.5
    library_size: int = 50000
    library_seeds: int = 8
    random_restarts: int = 8
    give_up_position: float = 0.15
    first_round_seeds: int = 1
    round_seeds: int = 1
    sequential_rounds: int = 3
    min_solutions: int = 1
    home_seed: bool = True
    diagnose_limits: bool = True
    manipulability_steps: int = 0
    manipulability_step: float = 0.05
    damping: float = 1e-3
    min_damping: float = 1e-9
    orientation_weight: float = 0.5
    library_eps: float = 0.5
    inner_tolerance: float = 0.05
    limit_epsilon: float = 1e-9
    random_seed: int = 0

    @classmethod
    def from_kwargs(cls, options: dict[str, Any]) -> PinocchioIKOptions:
        """Build from keyword options; unknown names are an :class:`InputError`."""
        names = cls.__dataclass_fields__
        for key in options:
            if key not in names:
                raise choice_error(InputError, "pinocchio IK option", key, names)
        # whole numbers (the stall test compares with two iterations back; a damping of
        # at least 1e-12 keeps J J^T + lam I positive definite in floats)
        wholes = (
            ("analytic_samples", 0),
            ("fallback_library_seeds", 0),
            ("fallback_random_restarts", 0),
            ("min_solutions", 1),
            ("max_iterations", 0),
            ("stall_after", 2),
        )
        for key, least in wholes:
            value = options.get(key, least)
            if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < least:
                raise InputError(
                    f"pinocchio IK option {key}: expected a whole number >= {least}, got {value!r}"
                )
        for key, bound in (("stall_ratio", 0.0), ("damping", 0.0), ("min_damping", 1e-12)):
            value = options.get(key, 1.0)
            if (
                isinstance(value, bool)
                or not isinstance(value, (int, float, np.integer, np.floating))
                or not np.isfinite(value)
                or value < bound
            ):
                raise InputError(
                    f"pinocchio IK option {key}: expected a finite number >= {bound:g}, "
                    f"got {value!r}"
                )
        if options.get("unseeded", "home") not in ("home", "library"):
            raise choice_error(
                InputError,
                "pinocchio IK option unseeded",
                options["unseeded"],
                ("home", "library"),
                key="unseeded",
            )
        if not isinstance(options.get("analytic", True), (bool, np.bool_)):
            raise InputError(
                f"pinocchio IK option analytic: expected true or false, got {options['analytic']!r}"
            )
        return cls(**options)


def log3(rot: np.ndarray) -> np.ndarray:
    """Rotation vectors of rotation matrices (batched SO(3) logarithm).

    Args:
        rot: Rotation matrices (N, 3, 3).

    Returns:
        Rotation vectors (N, 3) [rad], angle in [0, pi].
    """
    v = 0.5 * np.stack(
        [rot[:, 2, 1] - rot[:, 1, 2], rot[:, 0, 2] - rot[:, 2, 0], rot[:, 1, 0] - rot[:, 0, 1]],
        axis=1,
    )
    c = 0.5 * (rot[:, 0, 0] + rot[:, 1, 1] + rot[:, 2, 2] - 1.0)
    s = np.linalg.norm(v, axis=1)
    angle = np.arctan2(s, c)
    scale = np.ones_like(s)
    big = s > 1e-12
    scale[big] = angle[big] / s[big]
    out = v * scale[:, None]
    near_pi = (~big) & (c < 0)
    if np.any(near_pi):
        b = 0.5 * (rot[near_pi] + np.eye(3))
        k = np.argmax(np.diagonal(b, axis1=1, axis2=2), axis=1)
        axis = b[np.arange(len(k)), :, k]
        axis /= np.linalg.norm(axis, axis=1, keepdims=True)
        out[near_pi] = np.pi * axis
    return out


def rotation_angle(rot: np.ndarray) -> np.ndarray:
    """Angles of rotation matrices (N, 3, 3) -> (N,) [rad], accurate near 0 and pi."""
    s = 0.5 * np.linalg.norm(
        np.stack(
            [rot[:, 2, 1] - rot[:, 1, 2], rot[:, 0, 2] - rot[:, 2, 0], rot[:, 1, 0] - rot[:, 0, 1]],
            axis=1,
        ),
        axis=1,
    )
    c = 0.5 * (rot[:, 0, 0] + rot[:, 1, 1] + rot[:, 2, 2] - 1.0)
    return np.arctan2(s, c)


def _errors(
    rot: np.ndarray, pos: np.ndarray, trot: np.ndarray, tpos: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    ep = tpos - pos
    ew = log3(trot @ rot.transpose(0, 2, 1))
    return ep, ew


def levenberg_marquardt(
    chain: Any,
    q: np.ndarray,
    trot: np.ndarray,
    tpos: np.ndarray,
    lower: np.ndarray,
    upper: np.ndarray,
    tol_p: float,
    tol_r: float,
    opts: PinocchioIKOptions,
    clamp: bool = True,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Run LM on a batch of (target, seed) pairs.

    Returns:
        ``(q, converged, pos_err, rot_err)``; errors are those of the returned q.
    """
    compiled = kernels.get()
    m = len(q)
    # the kernel reads without bounds checks: other shapes get the NumPy code's errors
    if (
        compiled is not None
        and np.shape(q) == (m, chain.nq)
        and np.shape(trot) == (m, 3, 3)
        and np.shape(tpos) == (m, 3)
        and np.shape(lower) == np.shape(upper) == (chain.nq,)
    ):
        out: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray] = compiled.levenberg_marquardt(
            np.ascontiguousarray(q, dtype=float),
            np.ascontiguousarray(trot, dtype=float),
            np.ascontiguousarray(tpos, dtype=float),
            np.ascontiguousarray(lower, dtype=float),
            np.ascontiguousarray(upper, dtype=float),
            tol_p,
            tol_r,
            opts.max_iterations,
            opts.stall_after,
            opts.stall_ratio,
            opts.damping,
            opts.min_damping,
            clamp,
            *chain.packed,
        )
        return out
    q = q.copy()
    converged = np.zeros(m, dtype=bool)
    pos_err = np.full(m, np.inf)
    rot_err = np.full(m, np.inf)
    active = np.arange(m)
    eye = np.eye(6)
    history: list[np.ndarray] = []  # scaled error per iteration, full length m
    for it in range(opts.max_iterations + 1):
        qa = q[active]
        rot, pos, jac = chain.pose_jacobian(qa)
        ep, ew = _errors(rot, pos, trot[active], tpos[active])
        pe = np.linalg.norm(ep, axis=1)
        re = np.linalg.norm(ew, axis=1)
        pos_err[active] = pe
        rot_err[active] = re
        done = (pe <= tol_p) & (re <= tol_r)
        converged[active[done]] = True
        keep = ~done
        if opts.stall_ratio > 0:
            score = np.full(m, np.inf)
            score[active] = pe / tol_p + re / tol_r
            history.append(score)
            if it >= opts.stall_after:
                # a pair converging (quadratically, near the end) shrinks its
                # error fast; one that stalls (local minimum, limits) is dropped
                # and its target gets the next seed
                keep &= score[active] < opts.stall_ratio * history[-3][active]
        if it == opts.max_iterations or not np.any(keep):
            break
        active = active[keep]
        jac = jac[keep]
        e = np.concatenate([ep[keep], ew[keep]], axis=1)
        lam = opts.damping * np.einsum("ij,ij->i", e, e) + opts.min_damping
        a = jac @ jac.transpose(0, 2, 1) + lam[:, None, None] * eye
        y = np.linalg.solve(a, e[:, :, None])
        dq = (jac.transpose(0, 2, 1) @ y)[:, :, 0]
        qa = q[active]
        qn = qa + dq
        if clamp:
            viol = (qn < lower) | (qn > upper)
            rows = np.flatnonzero(viol.any(axis=1))
            if rows.size:
                # joints that would cross a limit are frozen at it and the
                # step is re-solved with the remaining joints (clamped DLS)
                jr = jac[rows] * (~viol[rows])[:, None, :]
                qr = np.clip(qn[rows], lower, upper)
                jr_dq = np.einsum("nij,nj->ni", jac[rows], qr - qa[rows])
                er = e[rows] - jr_dq
                ar = jr @ jr.transpose(0, 2, 1) + lam[rows, None, None] * eye
                yr = np.linalg.solve(ar, er[:, :, None])
                qn[rows] = qr + (jr.transpose(0, 2, 1) @ yr)[:, :, 0]
            np.clip(qn, lower, upper, out=qn)
        q[active] = qn
    return q, converged, pos_err, rot_err


def pose_errors(
    chain: Any, q: np.ndarray, trot: np.ndarray, tpos: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Position and orientation errors (M,) of configurations q (M, nq) at their targets."""
    rot, pos = chain.pose(q)
    ep, ew = _errors(rot, pos, trot, tpos)
    return np.linalg.norm(ep, axis=1), np.linalg.norm(ew, axis=1)


def yoshikawa_of(chain: Any, q: np.ndarray) -> np.ndarray:
    """Yoshikawa manipulability sqrt(det(J J^T)) of configurations (N, nq)."""
    return yoshikawa(chain.pose_jacobian(q)[2])


def raise_manipulability(
    chain: Any,
    q: np.ndarray,
    trot: np.ndarray,
    tpos: np.ndarray,
    lower: np.ndarray,
    upper: np.ndarray,
    tol_p: float,
    tol_r: float,
    opts: PinocchioIKOptions,
    validator: Callable[[np.ndarray], np.ndarray] | None,
) -> np.ndarray:
    """Null-space steps that raise Yoshikawa's index while holding the pose.

    Each step moves along the manipulability gradient (finite differences)
    projected onto the Jacobian's null space, by at most
    ``manipulability_step`` [rad], re-converges onto the target with LM and
    keeps the new configuration only where it converged (inside the limits),
    passes the validator, and has a larger index.
    """
    q = q.copy()
    nq = q.shape[1]
    h = 1e-6
    eye = np.eye(6)
    for _ in range(opts.manipulability_steps):
        jac = chain.pose_jacobian(q)[2]
        w0 = np.sqrt(np.clip(np.linalg.det(jac @ jac.transpose(0, 2, 1)), 0.0, None))
        grad = np.empty_like(q)
        for k in range(nq):
            qk = q.copy()
            qk[:, k] += h
            grad[:, k] = (yoshikawa_of(chain, qk) - w0) / h
        jjt = jac @ jac.transpose(0, 2, 1) + 1e-9 * eye
        proj = jac.transpose(0, 2, 1) @ np.linalg.solve(jjt, (jac @ grad[:, :, None]))
        step = grad - proj[:, :, 0]
        norm = np.linalg.norm(step, axis=1, keepdims=True)
        step *= opts.manipulability_step / np.maximum(norm, 1e-12)
        moved = np.clip(q + step, lower, upper)
        moved, conv, _, _ = levenberg_marquardt(
            chain, moved, trot, tpos, lower, upper, tol_p, tol_r, opts
        )
        better = conv & (yoshikawa_of(chain, moved) > w0)
        if validator is not None and np.any(better):
            rows = np.flatnonzero(better)
            better[rows] = np.asarray(validator(moved[rows]), dtype=object) == ""
        if not np.any(better):
            break
        q[better] = moved[better]
    return q
