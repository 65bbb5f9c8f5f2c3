r"""Default IK backend: closed form where the arm has one, then batched Levenberg-Marquardt.

**Closed form first.** An arm with the Franka Panda's kinematics (checked at
load, :mod:`~gcm_pipeline.robot.analytic`) is solved exactly for given values
of joint 7, all branches at once: at the preferred joint 7 (the first given
seed's, else the home configuration's), then at values around it and on grids
of 8, 64 and 512 values over its range for the targets still unsolved. Each
target keeps the solution nearest the preferred configuration; where that jumps
far from a given seed (a turn of the self-motion between the sampled values),
the LM from the seed decides if it lands nearer. Where several solutions are
wanted, they come first from the seeds (given ones, then the library's nearest
configurations: the closed-form solution nearest each), then from the grids,
the nearest of each branch first. Every solution is checked by forward
kinematics like an LM answer. Targets the closed form leaves unsolved (near a
singularity, or a joint-7 window narrower than the finest grid) go on to the
LM with a short schedule (``fallback_library_seeds``,
``fallback_random_restarts``).

A 6R arm that EAIK decomposes (the UR family and others, checked at load,
:mod:`~gcm_pipeline.robot.analytic_6r`) gets every IK branch in closed form,
each once modulo 2π, at its copy inside the limits nearest the preferred
configuration (the first given seed's, else home's); a target takes the
nearest branch (several answers: in order of distance), and the LM runs only
for targets without an exact branch inside the limits (singular poses). Any
other arm, or ``analytic=False``, uses the LM alone.

**LM.** All targets are solved at once. The chain (joint placements and axes read out
of the Pinocchio model, see :class:`~gcm_pipeline.robot.chain.KinematicChain`)
is evaluated in vectorised NumPy; each iteration takes, for every still-active
(target, seed) pair, the damped least-squares step

.. math::

    \Delta q = J^\top (J J^\top + \lambda I)^{-1} e, \qquad
    \lambda = \lambda_0 \lVert e \rVert^2 + \lambda_{\min},

where ``e = [p* - p; log(R* R^T)]`` is the pose error in base-frame axes and
``J`` the LOCAL_WORLD_ALIGNED grasp-frame Jacobian. Joints that the step would
push across a limit are frozen at it and the step is re-solved with the others
(clamped DLS), so iterates stay inside the limits; a (target, seed) pair whose
error stops shrinking is dropped early.

Seeds are tried in rounds, only for the targets that still fail, in a fixed
per-target order (a target's result does not depend on the rest of the batch):
given seeds (warm starts from solved neighbours), the nearest entries of a
library of random configurations (KD-tree over position and scaled
quaternion, both quaternion signs), the home configuration, then a last round
with all random restarts at once. Where several seeds of a target converge
(``first_round_seeds`` or ``min_solutions`` > 1) the one with the largest
Yoshikawa manipulability is kept; ``manipulability_steps`` adds null-space
steps that raise it at fixed pose. Targets that no seed reaches get one run
without joint limits: if that converges outside the limits their reason is
``joint_limits``, else ``no_ik``.

This module reports raw candidates; :func:`gcm_pipeline.robot.ik.solve_ik`
verifies every success with Pinocchio's own forward kinematics.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, replace
from typing import Any

import numpy as np
import pinocchio as pin
from scipy.spatial import cKDTree

from gcm_pipeline.errors import InputError, unknown_choice
from gcm_pipeline.geometry.dualquat import quat_from_rotation
from gcm_pipeline.robot import kernels
from gcm_pipeline.robot.analytic import PandaAnalyticIK
from gcm_pipeline.robot.analytic_6r import SixRAnalyticIK
from gcm_pipeline.robot.manipulability import yoshikawa

__all__ = [
    "PinocchioIKOptions",
    "SeedLibrary",
    "log3",
    "restart_seeds",
    "rotation_angle",
    "seed_library",
    "six_r_solver",
    "solve",
]

#: Offsets [rad] of joint 7 around its preferred value, tried with the first grid.
#: Smallest weight [m] of a joint in :func:`joint_levers` (a wrist joint whose axis
#: passes through the grasp frame still turns the hand).
MIN_LEVER = 0.05
_NEAR_Q7 = np.array([0.0, -0.05, 0.05, -0.1, 0.1, -0.2, 0.2, -0.4, 0.4])

#: (target, joint-7) rows of one closed-form call: about 340 bytes each. Blocks of
#: 16,384 rows ran 1.5x faster than of 262,144 (20,000 targets x 8 values: 159 against
#: 248 ms): their temporaries stay in the cache and cost no page faults.
_ANALYTIC_ROWS = 1 << 14

#: A closed-form answer farther than this from its given seed in some joint [rad] is
#: compared with the LM's from the seed.
_SEED_JUMP = 0.2

_LIBRARY_STREAM = 0x5EED11B
_RESTART_STREAM = 0x5EED2E5


@dataclass(frozen=True)
class PinocchioIKOptions:
    r"""Options of the batched LM solver (pass them as keywords to ``solve_ik``).

    Attributes:
        analytic: Solve first in closed form where the arm has the Panda's
            kinematics (:mod:`~gcm_pipeline.robot.analytic`); the LM rounds
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
                raise InputError(unknown_choice("pinocchio IK option", key, names))
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
            raise InputError(
                unknown_choice(
                    "pinocchio IK option unseeded", options["unseeded"], ("home", "library")
                )
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


class SeedLibrary:
    """Random configurations and their grasp-frame poses in a KD-tree.

    Keys are ``[p, w * quat]`` with both quaternion signs stored, so the
    nearest neighbour respects the double cover.

    Args:
        robot: The robot (a :class:`~gcm_pipeline.robot.model.Robot`).
        size: Number of random configurations.
        weight: Length scale [m] per unit of quaternion distance.
        seed: Random seed.
    """

    def __init__(self, robot: Any, size: int, weight: float, seed: int) -> None:
        # a tagged stream: never the same draws as a user's default_rng(seed)
        rng = np.random.default_rng([seed, _LIBRARY_STREAM])
        self.q = robot.random_configurations(size, rng)
        rot, pos = robot.chain.pose(self.q)
        self.weight = weight
        quat = quat_from_rotation(rot)
        keys = np.concatenate(
            [np.hstack([pos, weight * quat]), np.hstack([pos, -weight * quat])], axis=0
        )
        self.tree = cKDTree(keys)
        self.size = size

    def nearest(self, rot: np.ndarray, pos: np.ndarray, k: int, eps: float = 0.0) -> np.ndarray:
        """Indices (N, k) of the library configurations nearest to the poses.

        Args:
            rot: Rotations (N, 3, 3).
            pos: Positions (N, 3) [m].
            k: Neighbours per pose.
            eps: Approximation: each neighbour is within (1 + eps) of the true one.
        """
        keys = np.hstack([pos, self.weight * quat_from_rotation(rot)])
        # both signs of one entry are 2 * weight apart: duplicates are rare and harmless
        _, idx = self.tree.query(keys, k=max(1, min(k, 2 * self.size)), eps=eps)
        return np.asarray(idx, dtype=int).reshape(keys.shape[0], -1) % self.size


def restart_seeds(robot: Any, count: int, seed: int) -> np.ndarray:
    """The random restart configurations (count, nq), the same for every target."""
    rng = np.random.default_rng([seed, _RESTART_STREAM])
    return robot.random_configurations(count, rng)


def seed_library(robot: Any, opts: PinocchioIKOptions) -> SeedLibrary:
    """The cached seed library of ``robot`` for these options."""
    key = ("seed_library", opts.library_size, opts.random_seed, opts.orientation_weight)
    lib = robot.cache.get(key)
    if lib is None:
        lib = SeedLibrary(robot, opts.library_size, opts.orientation_weight, opts.random_seed)
        robot.cache[key] = lib
    return lib


def _errors(
    rot: np.ndarray, pos: np.ndarray, trot: np.ndarray, tpos: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    ep = tpos - pos
    ew = log3(trot @ rot.transpose(0, 2, 1))
    return ep, ew


def _lm(
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


def joint_levers(robot: Any) -> np.ndarray:
    """Per joint (nq,), the distance [m] from its axis to the grasp frame at home.

    Turning a revolute joint by one radian moves the grasp frame by about this
    much: the weights of a distance between postures in metres. A joint whose
    axis passes through or near the grasp frame (a last wrist joint) still turns
    the hand: at least :data:`MIN_LEVER`. Other joints weigh 1. Cached on the robot.
    """
    cached = robot.cache.get("joint_levers")
    if cached is not None:
        return cached
    model = robot.model
    data = model.createData()
    home = np.clip(np.asarray(robot.home, dtype=np.float64), robot.lower, robot.upper)
    pin.computeJointJacobians(model, data, home)
    pin.updateFramePlacements(model, data)
    tcp = data.oMf[robot.grasp_frame_id].translation
    out = np.ones(robot.nq)
    for j in range(1, model.njoints):
        joint = model.joints[j]
        if joint.nq != 1 or joint.nv != 1:
            continue
        axis = pin.getJointJacobian(model, data, j, pin.ReferenceFrame.LOCAL_WORLD_ALIGNED)[
            3:, joint.idx_v
        ]
        if np.linalg.norm(axis) < 0.5:  # prismatic
            continue
        axis = axis / np.linalg.norm(axis)
        r = tcp - data.oMi[j].translation
        out[joint.idx_q] = max(MIN_LEVER, float(np.linalg.norm(r - (r @ axis) * axis)))
    robot.cache["joint_levers"] = out
    return out


def analytic_solver(robot: Any) -> PandaAnalyticIK | None:
    """The closed-form solver of ``robot``'s arm (cached), or None if it has none."""
    key = ("analytic_ik",)
    if key not in robot.cache:
        robot.cache[key] = PandaAnalyticIK.for_chain(robot.chain)
    solver: PandaAnalyticIK | None = robot.cache[key]
    return solver


def _rank_in_runs(key: np.ndarray) -> np.ndarray:
    """Position of each element in its run of equal consecutive ``key`` values."""
    start = np.flatnonzero(np.r_[True, key[1:] != key[:-1]])
    return np.arange(key.size) - np.repeat(start, np.diff(np.r_[start, key.size]))


def _pose_errors(
    chain: Any, q: np.ndarray, trot: np.ndarray, tpos: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Position and orientation errors (M,) of configurations q (M, nq) at their targets."""
    rot, pos = chain.pose(q)
    ep, ew = _errors(rot, pos, trot, tpos)
    return np.linalg.norm(ep, axis=1), np.linalg.norm(ew, axis=1)


def _seeded_round(
    solver: PandaAnalyticIK,
    lib: SeedLibrary,
    seeds: np.ndarray | None,
    trot: np.ndarray,
    tpos: np.ndarray,
    lower: np.ndarray,
    upper: np.ndarray,
    opts: PinocchioIKOptions,
    n_valid: np.ndarray,
    chain: Any,
    tol_p: float,
    tol_r: float,
    attempts: tuple[np.ndarray, np.ndarray, np.ndarray],
    accept: Callable[[np.ndarray, np.ndarray, np.ndarray], None],
    validate: bool,
) -> None:
    """Closed-form solutions nearest each seed (given seeds, then library neighbours).

    For each target still short of ``opts.min_solutions`` and each of its seeds
    in order, the solution nearest the seed among those at the seed's joint 7
    and around it (``_NEAR_Q7``); repeats dropped; verified; accepted in seed
    order (what the LM from those seeds would give, exactly).
    """
    todo = np.flatnonzero(n_valid < opts.min_solutions)
    if todo.size == 0:
        return
    parts = []
    if seeds is not None and seeds.shape[1]:
        parts.append(np.asarray(seeds[todo], dtype=float))
    knn = lib.nearest(trot[todo], tpos[todo], opts.library_seeds, opts.library_eps)
    parts.append(lib.q[knn])
    near = np.clip(np.concatenate(parts, axis=1), lower, upper)  # (m, J, nq); NaN stays
    m = near.shape[0]
    q7s = np.clip(near[:, :, 6:7] + _NEAR_Q7, lower[6], upper[6]).reshape(m, -1)
    ok7 = np.isfinite(q7s)
    q7s = np.where(ok7, q7s, lower[6] - 1.0)  # outside the limits: no solution
    at, cq, _, col = _analytic_blocks(solver, trot[todo], tpos[todo], q7s, lower, upper)
    real = ok7[at, col]  # not from a NaN seed's placeholder
    at, cq, col = at[real], cq[real], col[real]
    if at.size == 0:
        return
    seed = col // _NEAR_Q7.size  # the seed each solution came from
    dist = np.sum((cq - near[at, seed]) ** 2, axis=1)
    dist = np.where(np.isfinite(dist), dist, np.inf)
    order = np.lexsort((dist, seed, at))
    at, cq, seed, dist = at[order], cq[order], seed[order], dist[order]
    first = np.r_[True, (at[1:] != at[:-1]) | (seed[1:] != seed[:-1])] & np.isfinite(dist)
    at, cq, seed = at[first], cq[first], seed[first]
    # one solution reached from two seeds counts once
    key = np.round(cq, 9)
    order = np.lexsort((*key.T[::-1], at))
    same = np.r_[
        False, (at[order][1:] == at[order][:-1]) & np.all(key[order][1:] == key[order][:-1], axis=1)
    ]
    keep = np.sort(order[~same])
    at, cq, seed = at[keep], cq[keep], seed[keep]
    if not validate:  # as many as a target needs (a validator may reject some)
        rank = _rank_in_runs(at)
        need = np.maximum(opts.min_solutions - n_valid[todo[at]], max(1, opts.first_round_seeds))
        take = rank < need
        at, cq, seed = at[take], cq[take], seed[take]
    ids = todo[at]
    pe, re = _pose_errors(chain, cq, trot[ids], tpos[ids])
    conv = (pe <= tol_p) & (re <= tol_r)
    if not np.any(conv):
        return
    att_p, att_r, att_q = attempts
    ids, cq, pe, re, seed = ids[conv], cq[conv], pe[conv], re[conv], seed[conv]
    att_p[ids], att_r[ids], att_q[ids] = pe, re, cq
    accept(ids, cq, -seed.astype(float))


def six_r_solver(robot: Any) -> SixRAnalyticIK | None:
    """The closed-form branch solver (EAIK) of ``robot``'s 6R arm (cached), or None."""
    key = ("analytic_6r",)
    if key not in robot.cache:
        robot.cache[key] = SixRAnalyticIK.for_chain(robot.chain)
    solver: SixRAnalyticIK | None = robot.cache[key]
    return solver


def _six_round(
    six: SixRAnalyticIK,
    trot: np.ndarray,
    tpos: np.ndarray,
    lower: np.ndarray,
    upper: np.ndarray,
    pref: np.ndarray,
    opts: PinocchioIKOptions,
    n_valid: np.ndarray,
    chain: Any,
    tol_p: float,
    tol_r: float,
    attempts: tuple[np.ndarray, np.ndarray, np.ndarray],
    accept: Callable[[np.ndarray, np.ndarray, np.ndarray], None],
    validate: bool,
    least: int,
) -> np.ndarray:
    """Every closed-form branch of a 6R arm, nearest the preferred configuration first.

    Each branch comes at its 2 pi copy inside the limits nearest ``pref``
    (N, nq); per target, as many as it needs (``opts.min_solutions``, at least
    ``least``) in order of distance, verified by the chain's forward
    kinematics; with a validator, in batches of ranks 0, 1, 2-3, 4-7, ... for
    the targets still short of valid ones.

    Returns:
        The targets (K,) that got an exact branch inside the limits: every one
        of their branches has been offered (the enumeration is complete).
    """
    at, cq = six.solve(trot, tpos, lower, upper, pref)
    if at.size == 0:
        return at
    pe, re = _pose_errors(chain, cq, trot[at], tpos[at])
    conv = (pe <= tol_p) & (re <= tol_r)
    at, cq, pe, re = at[conv], cq[conv], pe[conv], re[conv]
    if at.size == 0:
        return at
    dist = np.sum((cq - pref[at]) ** 2, axis=1)
    order = np.lexsort((dist, at))
    at, cq, pe, re, dist = at[order], cq[order], pe[order], re[order], dist[order]
    rank = _rank_in_runs(at)
    top = int(rank.max()) + 1
    bounds = [0, top]
    if validate:
        bounds = [0, *(1 << i for i in range(max(1, top).bit_length())), top]
    att_p, att_r, att_q = attempts
    for lo, hi in zip(bounds[:-1], bounds[1:], strict=True):
        short = n_valid[at] < opts.min_solutions
        need = np.maximum(np.maximum(opts.min_solutions - n_valid[at], 1), least)
        take = short & (rank >= lo) & (rank < hi)
        if not validate:
            take &= rank < need
        rows = np.flatnonzero(take)
        if rows.size == 0:
            continue
        ids = at[rows]
        att_p[ids], att_r[ids], att_q[ids] = pe[rows], re[rows], cq[rows]
        accept(ids, cq[rows], 1.0 / (1.0 + dist[rows]))
    return np.unique(at)


def _analytic_blocks(
    solver: PandaAnalyticIK,
    rot: np.ndarray,
    pos: np.ndarray,
    q7: np.ndarray,
    lower: np.ndarray,
    upper: np.ndarray,
    near: tuple[np.ndarray, float] | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """:meth:`PandaAnalyticIK.solve` in blocks of targets, without repeats.

    Blocks bound the memory; a repeat is one joint-7 value given twice to a
    target (e.g. two offsets clipped to a limit): its first column is kept.
    ``near``: ``(reference (N, 7), reach)``, as for the solver.
    """
    n, k = q7.shape
    step = max(1, _ANALYTIC_ROWS // max(k, 1))
    starts = range(0, max(n, 1), step)
    parts = [
        solver.solve(
            rot[a : a + step],
            pos[a : a + step],
            q7[a : a + step],
            lower,
            upper,
            None if near is None else (near[0][a : a + step], near[1]),
        )
        for a in starts
    ]
    at = np.concatenate([p[0] + a for p, a in zip(parts, starts, strict=True)])
    cq = np.concatenate([p[1] for p in parts])
    branch = np.concatenate([p[2] for p in parts])
    column = np.concatenate([p[3] for p in parts])
    values = np.sort(q7, axis=1)
    if at.size and np.any(values[:, 1:] == values[:, :-1]):
        order = np.lexsort((column, cq[:, 6], branch, at))
        key = np.column_stack([at[order], branch[order], cq[order, 6]])
        repeat = np.r_[False, np.all(key[1:] == key[:-1], axis=1)]
        keep = np.sort(order[~repeat])  # back to the solver's order
        at, cq, branch, column = at[keep], cq[keep], branch[keep], column[keep]
    return at, cq, branch, column


def yoshikawa_of(chain: Any, q: np.ndarray) -> np.ndarray:
    """Yoshikawa manipulability sqrt(det(J J^T)) of configurations (N, nq)."""
    return yoshikawa(chain.pose_jacobian(q)[2])


def _raise_manipulability(
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
        moved, conv, _, _ = _lm(chain, moved, trot, tpos, lower, upper, tol_p, tol_r, opts)
        better = conv & (yoshikawa_of(chain, moved) > w0)
        if validator is not None and np.any(better):
            rows = np.flatnonzero(better)
            better[rows] = np.asarray(validator(moved[rows]), dtype=object) == ""
        if not np.any(better):
            break
        q[better] = moved[better]
    return q


def solve(
    robot: Any,
    targets: np.ndarray,
    *,
    position_tolerance: float,
    orientation_tolerance: float,
    seeds: np.ndarray | None = None,
    validator: Callable[[np.ndarray], np.ndarray] | None = None,
    return_all: bool = False,
    **options: Any,
) -> dict[str, Any]:
    """Solve IK for targets with the batched LM (raw, unverified results).

    Args:
        robot: The robot.
        targets: Grasp-frame poses (N, 4, 4) in the base frame, already validated.
        position_tolerance: [m].
        orientation_tolerance: [rad].
        seeds: Optional warm starts (N, K, nq) [rad]; NaN rows are skipped.
        validator: Optional ``q (M, nq) -> (M,) str`` reasons ('' = valid),
            applied to converged candidates before one is chosen.
        return_all: Also return every converged candidate.
        **options: :class:`PinocchioIKOptions` fields.

    Returns:
        A dict with ``q`` (N, nq) (NaN if none), ``success`` (N,), ``pos_err``,
        ``rot_err`` (N,) of the chosen or best attempt, ``reason`` (N,) and,
        with ``return_all``, ``all_index``, ``all_q``, ``all_reason``.
    """
    opts = PinocchioIKOptions.from_kwargs(options)
    n = targets.shape[0]
    nq = robot.nq
    chain = robot.chain
    eps = opts.limit_epsilon
    lower = robot.lower + eps
    upper = robot.upper - eps
    tol_p = position_tolerance * opts.inner_tolerance
    tol_r = orientation_tolerance * opts.inner_tolerance
    trot = np.ascontiguousarray(targets[:, :3, :3])
    tpos = np.ascontiguousarray(targets[:, :3, 3])

    best_q = np.full((n, nq), np.nan)
    best_score = np.full(n, -np.inf)
    n_valid = np.zeros(n, dtype=int)
    att_p = np.full(n, np.inf)
    att_r = np.full(n, np.inf)
    att_q = np.full((n, nq), np.nan)
    last_reason = np.full(n, "", dtype=object)
    all_index: list[np.ndarray] = []
    all_q: list[np.ndarray] = []
    all_reason: list[np.ndarray] = []

    first = max(1, opts.first_round_seeds)
    # among several valid solutions of a target: best manipulability when the
    # user asks for choice, else the first seed in schedule order (which makes
    # merged rounds give the same result as one seed at a time)
    by_manipulability = first > 1 or opts.min_solutions > 1

    def accept(cids: np.ndarray, cq: np.ndarray, rank: np.ndarray) -> None:
        """Record converged candidates ``cq`` of targets ``cids``.

        ``rank``: higher wins (when not by manipulability).
        """
        if validator is not None:
            reasons = np.asarray(validator(cq), dtype=object)
            if reasons.shape != (cq.shape[0],):
                raise InputError(
                    f"validator returned shape {reasons.shape}, expected ({cq.shape[0]},)"
                )
        else:
            reasons = np.full(cq.shape[0], "", dtype=object)
        if return_all:
            all_index.append(cids)
            all_q.append(cq)
            all_reason.append(reasons)
        valid = reasons == ""
        last_reason[cids[~valid]] = reasons[~valid]
        if not np.any(valid):
            return
        vids, vq = cids[valid], cq[valid]
        score = yoshikawa_of(chain, vq) if by_manipulability else rank[valid]
        np.add.at(n_valid, vids, 1)
        order = np.argsort(score, kind="stable")  # ascending: the best is written last
        vids, vq, score = vids[order], vq[order], score[order]
        better = score > best_score[vids]
        best_q[vids[better]] = vq[better]
        best_score[vids[better]] = score[better]

    solver = analytic_solver(robot) if opts.analytic else None
    six = six_r_solver(robot) if opts.analytic and solver is None else None
    # one answer per target (a validator or return_all does not change which)
    one_each = not (opts.min_solutions > 1 or by_manipulability)
    has = np.zeros(n, dtype=bool)
    pref = np.broadcast_to(np.asarray(robot.home, dtype=float), (n, nq)).copy()
    if (solver is not None or six is not None) and n:
        # the preferred configuration: the first seed's, else home's (or the library's)
        if seeds is not None and seeds.shape[1]:
            finite = np.all(np.isfinite(seeds), axis=2)
            has = finite.any(axis=1)
            col0 = np.argmax(finite, axis=1)
            pref[has] = seeds[np.flatnonzero(has), col0[has]]
        if opts.unseeded == "library":
            # the library's nearest configuration, as the LM would start from it
            unseeded = np.flatnonzero(~has)
            if unseeded.size:
                lib0 = seed_library(robot, opts)
                near0 = lib0.nearest(trot[unseeded], tpos[unseeded], 1, opts.library_eps)
                pref[unseeded] = lib0.q[near0[:, 0]]
        pref = np.clip(pref, lower, upper)
    # targets whose every branch the closed form has offered: no seed can add one
    complete = np.zeros(n, dtype=bool)
    if six is not None and n:
        # every branch in closed form (EAIK), each at its 2 pi copy nearest the
        # preferred configuration; nearest first
        complete[
            _six_round(
                six,
                trot,
                tpos,
                lower,
                upper,
                pref,
                opts,
                n_valid,
                chain,
                tol_p,
                tol_r,
                (att_p, att_r, att_q),
                accept,
                validator is not None,
                first if by_manipulability else 1,
            )
        ] = True
    if solver is not None and n:
        # closed form first: the preferred joint 7 (the first seed's, else home's),
        # then a grid over its range for the targets still short of solutions
        # rounds: (around the preferred joint 7 too, grid size): the preferred joint 7
        # (one answer each: alone first), values around it and a grid over its range
        # (the self-motion may turn back just short of the preferred value), then a
        # finer grid (one answer each: and a finer one still)
        k = opts.analytic_samples
        levers = joint_levers(robot)
        grids = [(False, 8 * k)] if k else []
        if one_each:  # the finest grid finds narrow windows; choice needs no more
            # the preferred joint 7 with values around it at once: the branch nearest
            # the preferred posture may sit just beside the preferred joint 7 (at home's
            # joint 7 alone, the Panda's bottle grasps took a q1 1.3 rad from home)
            rounds = [(True, k), *grids, *([(False, 64 * k)] if k else [])]
        else:
            rounds = [(True, k), *grids]
        if (opts.min_solutions > 1 or by_manipulability) and opts.library_seeds > 0:
            # several solutions wanted: first, like the LM from each seed (the given
            # ones, then the library's nearest), the closed form's solution nearest
            # each seed at its joint 7 and around: solutions spread where the seeds are
            _seeded_round(
                solver,
                seed_library(robot, opts),
                seeds,
                trot,
                tpos,
                lower,
                upper,
                opts,
                n_valid,
                chain,
                tol_p,
                tol_r,
                (att_p, att_r, att_q),
                accept,
                validator is not None,
            )
        tried = np.zeros(0)
        for with_pref, samples in rounds:
            todo = np.flatnonzero(n_valid < opts.min_solutions)
            if todo.size == 0:
                break
            grid = np.linspace(lower[6], upper[6], samples)  # the ends too: some poses need them
            # a finer grid repeats the coarser one's values: not their solutions again
            new = np.min(np.abs(grid[:, None] - tried[None, :]), axis=1, initial=np.inf) > 1e-12
            grid, tried = grid[new], np.concatenate([tried, grid[new]])
            samples = grid.size
            # the preferred q7 (and, for one answer each, values around it: the
            # self-motion may turn back just short of it)
            near = pref[todo, 6:7] + (_NEAR_Q7 if with_pref and one_each else 0.0)
            q7s = np.concatenate(
                [np.clip(near, lower[6], upper[6]), np.broadcast_to(grid, (todo.size, samples))],
                axis=1,
            )
            at, cq, branch, _ = _analytic_blocks(solver, trot[todo], tpos[todo], q7s, lower, upper)
            if at.size == 0:
                continue
            # lever-weighted: a radian at the shoulder moves the hand far more than
            # one at the wrist, so "nearest the preferred posture" is in metres
            dist = np.sum(((cq - pref[todo[at]]) * levers) ** 2, axis=1)
            if one_each:  # per target, the nearest to the preferred configuration
                order = np.lexsort((dist, at))
            else:
                # per target, the nearest of each branch first (nearest branch first),
                # then the second nearest of each, ...: choice across branches
                order = np.lexsort((dist, branch, at))
                within = _rank_in_runs(at.astype(np.int64)[order] * 8 + branch[order])
                order = order[np.lexsort((dist[order], within, at[order]))]
            at, cq, dist = at[order], cq[order], dist[order]
            rank = _rank_in_runs(at)
            # in order of preference, as many as a target still needs (one each: the
            # first; by manipulability: at least first_round_seeds); with a validator, in
            # batches of ranks 0, 1, 2-3, 4-7, ... for the targets still short of valid ones
            top = int(rank.max(initial=-1)) + 1
            bounds = [0, top]
            if validator is not None:
                bounds = [0, *(1 << i for i in range(max(1, top).bit_length())), top]
            for lo, hi in zip(bounds[:-1], bounds[1:], strict=True):
                short = n_valid[todo[at]] < opts.min_solutions
                need = np.maximum(opts.min_solutions - n_valid[todo[at]], 1)
                if by_manipulability:
                    need = np.maximum(need, first)
                take = short & (rank >= lo) & (rank < hi)
                if validator is None:
                    take &= rank < need
                rows = np.flatnonzero(take)
                if rows.size == 0:
                    continue
                ids = todo[at[rows]]
                pe, re = _pose_errors(chain, cq[rows], trot[ids], tpos[ids])
                conv = (pe <= tol_p) & (re <= tol_r)
                if not np.any(conv):
                    continue
                rows, ids, pe, re = rows[conv], ids[conv], pe[conv], re[conv]
                att_p[ids], att_r[ids], att_q[ids] = pe, re, cq[rows]
                accept(ids, cq[rows], 1.0 / (1.0 + dist[rows]))
    if (
        (solver is not None or six is not None)
        and one_each
        and seeds is not None
        and seeds.shape[1]
    ):
        # the sampled joint-7 values may miss a seed's own neighbourhood (near a turn
        # of the self-motion, a narrow window inside the limits): where the answer
        # jumps far from the given seed, the LM from the seed, if it lands nearer
        jump = np.max(np.abs(best_q - pref), axis=1)
        far = np.flatnonzero(has & (n_valid > 0) & (jump > _SEED_JUMP))
        if far.size:
            qf, conv, pe, re = _lm(
                chain, pref[far], trot[far], tpos[far], lower, upper, tol_p, tol_r, opts
            )
            nearer = conv & (np.max(np.abs(qf - pref[far]), axis=1) < jump[far])
            ids, qf, pe, re = far[nearer], qf[nearer], pe[nearer], re[nearer]
            if ids.size:
                before = best_q[ids].copy()
                accept(ids, qf, np.full(ids.size, 2.0))  # above any closed-form rank
                took = np.any(best_q[ids] != before, axis=1)
                att_q[ids[took]], att_p[ids[took]], att_r[ids[took]] = (
                    qf[took],
                    pe[took],
                    re[took],
                )

    # Seed schedule. Every decision is per target, so a target's result does not
    # depend on the other targets of the batch (nor on chunking over workers):
    # rounds over the given seeds, the library neighbours and home (``round_seeds``
    # at a time, ``first_round_seeds`` in the first), then one last round with
    # all the random restarts at once, longer runs and a lenient stall exit.
    lib = seed_library(robot, opts)
    n_lib = max(0, opts.library_seeds)
    n_given = 0 if seeds is None else seeds.shape[1]
    knn = np.full((n, n_lib), -1, dtype=int)
    n_home = 1 if opts.home_seed else 0
    n_fixed = n_given + n_lib + n_home
    n_random = max(0, opts.random_restarts)
    if solver is not None and opts.analytic_samples > 0:
        # the closed form has searched the whole range of joint 7: the LM is left
        # the poses it cannot settle (near singularities, joint-7 windows narrower
        # than its finest grid), with a short schedule
        n_lib = min(n_lib, max(0, opts.fallback_library_seeds))
        n_random = min(n_random, max(0, opts.fallback_random_restarts))
        n_fixed = n_given + n_lib + n_home
    n_rounds = n_fixed + n_random
    restarts = restart_seeds(robot, n_random, opts.random_seed)
    final_opts = replace(
        opts, stall_ratio=0.9, stall_after=8, max_iterations=2 * opts.max_iterations
    )

    def column(c: int, ids: np.ndarray) -> np.ndarray:
        if c < n_given:
            assert seeds is not None
            return np.asarray(seeds[ids, c], dtype=float)
        c -= n_given
        if c < n_lib:
            # neighbours are queried lazily: one for everyone, more for the failures
            missing = ids[knn[ids, c] < 0]
            if missing.size:
                k = 1 if c == 0 else n_lib
                knn[missing, :k] = lib.nearest(trot[missing], tpos[missing], k, opts.library_eps)
            return lib.q[knn[ids, c]]
        if c < n_lib + n_home:
            return np.broadcast_to(robot.home, (len(ids), nq)).copy()
        return np.broadcast_to(restarts[c - n_lib - n_home], (len(ids), nq)).copy()

    c = 0
    r = 0
    while c < n_rounds:
        todo = np.flatnonzero((n_valid < opts.min_solutions) & ~complete)
        run_opts = opts
        if c < n_fixed:
            if r == 0:
                width = first
            elif r < opts.sequential_rounds:
                width = max(1, opts.round_seeds)
            else:
                width = n_fixed - c  # the remaining fixed seeds at once
            width = min(width, n_fixed - c)
            r += 1
        else:
            width = n_rounds - c
            run_opts = final_opts
            if opts.give_up_position > 0:
                # random restarts only for targets that some seed brought close
                todo = todo[att_p[todo] <= opts.give_up_position]
        if todo.size == 0:
            if c >= n_fixed:
                break
            c += width
            continue
        ids_list, q0_list, col_list = [], [], []
        for cc in range(c, min(c + width, n_rounds)):
            q0 = column(cc, todo)
            ok = np.all(np.isfinite(q0), axis=1)
            ids_list.append(todo[ok])
            q0_list.append(np.clip(q0[ok], lower, upper))
            col_list.append(np.full(int(ok.sum()), cc))
        c += width
        ids = np.concatenate(ids_list)
        if ids.size == 0:
            continue
        q0 = np.concatenate(q0_list)
        cols = np.concatenate(col_list)
        q, conv, pe, re = _lm(chain, q0, trot[ids], tpos[ids], lower, upper, tol_p, tol_r, run_opts)
        # remember the best attempt (for error reporting of failures)
        score_att = pe / position_tolerance + re / orientation_tolerance
        order = np.argsort(-score_att)  # best last, so it wins the fancy assignment
        cur = att_p[ids[order]] / position_tolerance + att_r[ids[order]] / orientation_tolerance
        better = score_att[order] < cur
        sel = order[better]
        att_p[ids[sel]] = pe[sel]
        att_r[ids[sel]] = re[sel]
        att_q[ids[sel]] = q[sel]
        if np.any(conv):
            accept(ids[conv], q[conv], -cols[conv].astype(float))

    success = n_valid > 0
    if opts.manipulability_steps > 0 and np.any(success):
        ids = np.flatnonzero(success)
        best_q[ids] = _raise_manipulability(
            chain, best_q[ids], trot[ids], tpos[ids], lower, upper, tol_p, tol_r, opts, validator
        )
    reason = np.full(n, "", dtype=object)
    fail = np.flatnonzero(~success)
    if fail.size:
        reason[fail] = "no_ik"
        rejected = fail[last_reason[fail] != ""]
        reason[rejected] = last_reason[rejected]
        # would the target be reached without the joint limits?
        plain = fail[last_reason[fail] == ""] if opts.diagnose_limits else fail[:0]
        start = att_q[plain]
        ok = np.all(np.isfinite(start), axis=1)
        plain = plain[ok]
        if plain.size:
            qf, conv, pe, re = _lm(
                chain,
                start[ok],
                trot[plain],
                tpos[plain],
                lower,
                upper,
                tol_p,
                tol_r,
                opts,
                clamp=False,
            )
            inside = conv & np.all((qf >= lower) & (qf <= upper), axis=1)
            if np.any(inside):
                # the unclamped run found a solution inside the limits after all
                rows = np.flatnonzero(inside)
                why = (
                    np.full(rows.size, "", dtype=object)
                    if validator is None
                    else np.asarray(validator(qf[rows]), dtype=object)
                )
                if return_all:
                    all_index.append(plain[rows])
                    all_q.append(qf[rows])
                    all_reason.append(why)
                reason[plain[rows[why != ""]]] = why[why != ""]
                good = rows[why == ""]
                ids = plain[good]
                best_q[ids], success[ids], reason[ids] = qf[good], True, ""
                att_p[ids], att_r[ids] = pe[good], re[good]
            reason[plain[conv & ~inside]] = "joint_limits"
    out: dict[str, Any] = {
        "q": best_q,
        "success": success,
        "pos_err": att_p,
        "rot_err": att_r,
        "reason": reason,
    }
    if return_all:
        out["all_index"] = np.concatenate(all_index) if all_index else np.zeros(0, int)
        out["all_q"] = np.concatenate(all_q) if all_q else np.zeros((0, nq))
        out["all_reason"] = np.concatenate(all_reason) if all_reason else np.zeros(0, dtype=object)
    return out
