r"""Default IK backend: closed form where the arm has one, then batched Levenberg-Marquardt.

**Closed form first.** An arm with the Franka Panda's kinematics (checked at
load, :mod:`~gcm_pipeline.robot.ik.panda`,
:mod:`~gcm_pipeline.robot.ik.panda_rounds`) is solved exactly for given values
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
:mod:`~gcm_pipeline.robot.ik.analytic_6r`) gets every IK branch in closed form,
each once modulo 2π, at its copy inside the limits nearest the preferred
configuration (the first given seed's, else home's); a target takes the
nearest branch (several answers: in order of distance), and the LM runs only
for targets without an exact branch inside the limits (singular poses). Any
other arm, or ``analytic=False``, uses the LM alone.

**LM** (:mod:`~gcm_pipeline.robot.ik.lm`). Seeds are tried in rounds, only for
the targets that still fail, in a fixed per-target order
(:mod:`~gcm_pipeline.robot.ik.seeds`): given seeds (warm starts from solved
neighbours), the nearest entries of a library of random configurations, the
home configuration, then a last round with all random restarts at once. Where
several seeds of a target converge (``first_round_seeds`` or
``min_solutions`` > 1) the one with the largest Yoshikawa manipulability is
kept; ``manipulability_steps`` adds null-space steps that raise it at fixed
pose. Targets that no seed reaches get one run without joint limits: if that
converges outside the limits their reason is ``joint_limits``, else ``no_ik``.

The stages share one :class:`~gcm_pipeline.robot.ik.candidates.SolveContext`.
This module reports raw candidates; :func:`gcm_pipeline.robot.ik.solve_ik`
verifies every success with Pinocchio's own forward kinematics.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np

from gcm_pipeline.robot.ik.analytic_6r import six_r_solver, six_round
from gcm_pipeline.robot.ik.answer import BackendAnswer
from gcm_pipeline.robot.ik.candidates import SolveContext, Tally
from gcm_pipeline.robot.ik.lm import PinocchioIKOptions, levenberg_marquardt, raise_manipulability
from gcm_pipeline.robot.ik.panda import analytic_solver
from gcm_pipeline.robot.ik.panda_rounds import closed_form_rounds
from gcm_pipeline.robot.ik.seeds import lm_rounds, seed_library

__all__ = ["solve"]

#: A closed-form answer farther than this from its given seed in some joint [rad] is
#: compared with the LM's from the seed.
_SEED_JUMP = 0.2


def solve(
    robot: Any,
    targets: np.ndarray,
    *,
    position_tolerance: float,
    orientation_tolerance: float,
    seeds: np.ndarray | None = None,
    validator: Callable[[np.ndarray], np.ndarray] | None = None,
    return_all: bool = False,
    settle: Callable[[np.ndarray, np.ndarray], np.ndarray] | None = None,
    **options: Any,
) -> BackendAnswer:
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
        settle: With ``return_all``, ``(index (M,), q (M, nq)) -> (N,) bool``:
            given every candidate once, in order, between the stages; the later
            stages skip the targets it returns True for (they need no more).
        **options: :class:`~gcm_pipeline.robot.ik.lm.PinocchioIKOptions` fields.

    Returns:
        The :class:`~gcm_pipeline.robot.ik.answer.BackendAnswer`: ``q`` (N, nq)
        (NaN if none), ``success`` (N,), ``pos_err``, ``rot_err`` (N,) of the
        chosen or best attempt, ``reason`` (N,) and, with ``return_all``,
        ``all_index``, ``all_q``, ``all_reason``.
    """
    opts = PinocchioIKOptions.from_kwargs(options)
    ctx = _context(
        robot,
        targets,
        position_tolerance,
        orientation_tolerance,
        opts,
        validator,
        return_all,
        settle,
    )
    n, tally = ctx.n, ctx.tally
    solver = analytic_solver(robot) if opts.analytic else None
    six = six_r_solver(robot) if opts.analytic and solver is None else None
    closed_form = solver is not None or six is not None
    has, pref = _preferred(ctx, seeds, closed_form)
    # targets whose every branch the closed form has offered: no seed can add one
    complete = np.zeros(n, dtype=bool)
    if six is not None and n:
        # every branch in closed form (EAIK), each at its 2 pi copy nearest the
        # preferred configuration; nearest first
        complete[six_round(six, ctx, pref)] = True
    if solver is not None and n:
        # closed form first: the preferred joint 7 (the first seed's, else home's),
        # then a grid over its range for the targets still short of solutions
        closed_form_rounds(solver, ctx, seeds, pref)
    if closed_form and ctx.one_each and seeds is not None and seeds.shape[1]:
        _nearer_from_seeds(ctx, has, pref)
    lm_rounds(ctx, seeds, complete, solver is not None and opts.analytic_samples > 0)
    success = tally.n_valid > 0
    if opts.manipulability_steps > 0 and np.any(success):
        ids = np.flatnonzero(success)
        tally.best_q[ids] = raise_manipulability(
            ctx.chain,
            tally.best_q[ids],
            ctx.trot[ids],
            ctx.tpos[ids],
            ctx.lower,
            ctx.upper,
            ctx.tol_p,
            ctx.tol_r,
            opts,
            validator,
        )
    reason = _diagnose_failures(ctx, success)
    tally.checkpoint()  # the last candidates: settle has seen every one
    if not return_all:
        return BackendAnswer(tally.best_q, success, tally.att_p, tally.att_r, reason)
    nq = robot.nq
    return BackendAnswer(
        tally.best_q,
        success,
        tally.att_p,
        tally.att_r,
        reason,
        all_index=np.concatenate(tally.all_index) if tally.all_index else np.zeros(0, int),
        all_q=np.concatenate(tally.all_q) if tally.all_q else np.zeros((0, nq)),
        all_reason=(
            np.concatenate(tally.all_reason) if tally.all_reason else np.zeros(0, dtype=object)
        ),
    )


def _context(
    robot: Any,
    targets: np.ndarray,
    position_tolerance: float,
    orientation_tolerance: float,
    opts: PinocchioIKOptions,
    validator: Callable[[np.ndarray], np.ndarray] | None,
    return_all: bool,
    settle: Callable[[np.ndarray, np.ndarray], np.ndarray] | None = None,
) -> SolveContext:
    """The targets, limits, tolerances and an empty tally of one solve call."""
    n = targets.shape[0]
    eps = opts.limit_epsilon
    first = max(1, opts.first_round_seeds)
    # among several valid solutions of a target: best manipulability when the
    # user asks for choice, else the first seed in schedule order (which makes
    # merged rounds give the same result as one seed at a time)
    by_manipulability = first > 1 or opts.min_solutions > 1
    return SolveContext(
        robot=robot,
        trot=np.ascontiguousarray(targets[:, :3, :3]),
        tpos=np.ascontiguousarray(targets[:, :3, 3]),
        lower=robot.lower + eps,
        upper=robot.upper - eps,
        tol_p=position_tolerance * opts.inner_tolerance,
        tol_r=orientation_tolerance * opts.inner_tolerance,
        position_tolerance=position_tolerance,
        orientation_tolerance=orientation_tolerance,
        opts=opts,
        tally=Tally.empty(
            n, robot.nq, robot.chain, validator, return_all, by_manipulability, settle
        ),
    )


def _preferred(
    ctx: SolveContext, seeds: np.ndarray | None, closed_form: bool
) -> tuple[np.ndarray, np.ndarray]:
    """The closed form's preferred configuration per target.

    The first finite given seed's, else home's (or, with ``unseeded="library"``,
    the library's configuration nearest in pose, where the LM would start),
    clipped to the limits.

    Returns:
        ``(has, pref)``: whether a target has a given seed (N,), and the
        preferred configurations (N, nq) [rad] (home, unclipped, without a
        closed form).
    """
    robot, opts, n = ctx.robot, ctx.opts, ctx.n
    has = np.zeros(n, dtype=bool)
    pref = np.broadcast_to(np.asarray(robot.home, dtype=float), (n, robot.nq)).copy()
    if not (closed_form and n):
        return has, pref
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
            near0 = lib0.nearest(ctx.trot[unseeded], ctx.tpos[unseeded], 1, opts.library_eps)
            pref[unseeded] = lib0.q[near0[:, 0]]
    return has, np.clip(pref, ctx.lower, ctx.upper)


def _nearer_from_seeds(ctx: SolveContext, has: np.ndarray, pref: np.ndarray) -> None:
    """Where the closed-form answer jumps far from the given seed, the LM from the seed.

    The sampled joint-7 values may miss a seed's own neighbourhood (near a turn
    of the self-motion, a narrow window inside the limits): where the answer
    jumps far from the given seed, the LM's answer from the seed replaces it if
    it lands nearer.
    """
    tally = ctx.tally
    best_q = tally.best_q
    jump = np.max(np.abs(best_q - pref), axis=1)
    far = np.flatnonzero(has & (tally.n_valid > 0) & (jump > _SEED_JUMP))
    if not far.size:
        return
    qf, conv, pe, re = levenberg_marquardt(
        ctx.chain,
        pref[far],
        ctx.trot[far],
        ctx.tpos[far],
        ctx.lower,
        ctx.upper,
        ctx.tol_p,
        ctx.tol_r,
        ctx.opts,
    )
    nearer = conv & (np.max(np.abs(qf - pref[far]), axis=1) < jump[far])
    ids, qf, pe, re = far[nearer], qf[nearer], pe[nearer], re[nearer]
    if ids.size:
        before = best_q[ids].copy()
        tally.accept(ids, qf, np.full(ids.size, 2.0))  # above any closed-form rank
        took = np.any(best_q[ids] != before, axis=1)
        tally.att_q[ids[took]], tally.att_p[ids[took]], tally.att_r[ids[took]] = (
            qf[took],
            pe[took],
            re[took],
        )


def _diagnose_failures(ctx: SolveContext, success: np.ndarray) -> np.ndarray:
    """Reasons (N,) of the targets without a solution; updates ``success`` in place.

    A validator's last reason where it rejected every candidate, else ``no_ik``;
    with ``diagnose_limits``, one run without the joint limits from the best
    attempt tells ``joint_limits`` (it converges outside them) from ``no_ik``
    (and, rarely, finds a solution inside them after all: a success).
    """
    tally, opts = ctx.tally, ctx.opts
    lower, upper, validator = ctx.lower, ctx.upper, tally.validator
    reason = np.full(ctx.n, "", dtype=object)
    fail = np.flatnonzero(~success)
    if not fail.size:
        return reason
    reason[fail] = "no_ik"
    rejected = fail[tally.last_reason[fail] != ""]
    reason[rejected] = tally.last_reason[rejected]
    # would the target be reached without the joint limits?
    plain = fail[tally.last_reason[fail] == ""] if opts.diagnose_limits else fail[:0]
    start = tally.att_q[plain]
    ok = np.all(np.isfinite(start), axis=1)
    plain = plain[ok]
    if not plain.size:
        return reason
    qf, conv, pe, re = levenberg_marquardt(
        ctx.chain,
        start[ok],
        ctx.trot[plain],
        ctx.tpos[plain],
        lower,
        upper,
        ctx.tol_p,
        ctx.tol_r,
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
        if tally.return_all:
            tally.all_index.append(plain[rows])
            tally.all_q.append(qf[rows])
            tally.all_reason.append(why)
        reason[plain[rows[why != ""]]] = why[why != ""]
        good = rows[why == ""]
        ids = plain[good]
        tally.best_q[ids], success[ids], reason[ids] = qf[good], True, ""
        tally.att_p[ids], tally.att_r[ids] = pe[good], re[good]
    reason[plain[conv & ~inside]] = "joint_limits"
    return reason
