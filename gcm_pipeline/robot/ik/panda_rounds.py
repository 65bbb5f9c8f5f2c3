"""The default backend's closed-form stage for arms with the Panda's kinematics.

:func:`closed_form_rounds` solves with :class:`~gcm_pipeline.robot.ik.panda.PandaAnalyticIK`
at the preferred joint 7 (the first given seed's, else the home
configuration's), then at values around it and on grids of 8, 64 and 512
values over its range for the targets still unsolved. Each target keeps the
solution nearest the preferred configuration (lever-weighted,
:func:`joint_levers`). Where several solutions are wanted, they come first
from the seeds (given ones, then the library's nearest configurations: the
closed-form solution nearest each, :func:`seeded_round`), then from the grids,
the nearest of each branch first. Every solution is checked by forward
kinematics like an LM answer.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import pinocchio as pin

from gcm_pipeline.robot.ik.candidates import SolveContext, first_smallest, rank_in_runs
from gcm_pipeline.robot.ik.lm import pose_errors
from gcm_pipeline.robot.ik.panda import PandaAnalyticIK, analytic_blocks
from gcm_pipeline.robot.ik.seeds import SeedLibrary, seed_library

__all__ = ["MIN_LEVER", "closed_form_rounds", "joint_levers", "seeded_round"]

#: Smallest weight [m] of a joint in :func:`joint_levers` (a wrist joint whose axis
#: passes through the grasp frame still turns the hand).
MIN_LEVER = 0.05

#: Offsets [rad] of joint 7 around its preferred value, tried with the first grid.
_NEAR_Q7 = np.array([0.0, -0.05, 0.05, -0.1, 0.1, -0.2, 0.2, -0.4, 0.4])


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


def seeded_round(
    solver: PandaAnalyticIK, lib: SeedLibrary, seeds: np.ndarray | None, ctx: SolveContext
) -> None:
    """Closed-form solutions nearest each seed (given seeds, then library neighbours).

    For each target still short of ``opts.min_solutions`` and each of its seeds
    in order, the solution nearest the seed among those at the seed's joint 7
    and around it (``_NEAR_Q7``); repeats dropped; verified; accepted in seed
    order (what the LM from those seeds would give, exactly).
    """
    opts, tally, trot, tpos = ctx.opts, ctx.tally, ctx.trot, ctx.tpos
    lower, upper, n_valid = ctx.lower, ctx.upper, ctx.tally.n_valid
    todo = ctx.short()
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
    at, cq, _, col = analytic_blocks(solver, trot[todo], tpos[todo], q7s, lower, upper)
    real = ok7[at, col]  # not from a NaN seed's placeholder
    at, cq, col = at[real], cq[real], col[real]
    if at.size == 0:
        return
    seed = col // _NEAR_Q7.size  # the seed each solution came from
    dist = np.sum((cq - near[at, seed]) ** 2, axis=1)
    dist = np.where(np.isfinite(dist), dist, np.inf)
    # the nearest of each (target, seed), the first of ties; the solutions come
    # grouped by target, then column (so seed)
    first = first_smallest(at.astype(np.int64) * near.shape[1] + seed, dist)
    first = first[np.isfinite(dist[first])]
    at, cq, seed = at[first], cq[first], seed[first]
    # one solution reached from two seeds counts once
    key = np.round(cq, 9)
    order = np.lexsort((*key.T[::-1], at))
    same = np.r_[
        False, (at[order][1:] == at[order][:-1]) & np.all(key[order][1:] == key[order][:-1], axis=1)
    ]
    keep = np.sort(order[~same])
    at, cq, seed = at[keep], cq[keep], seed[keep]
    if not ctx.validate:  # as many as a target needs (a validator may reject some)
        rank = rank_in_runs(at)
        need = np.maximum(opts.min_solutions - n_valid[todo[at]], max(1, opts.first_round_seeds))
        take = rank < need
        at, cq, seed = at[take], cq[take], seed[take]
    ids = todo[at]
    pe, re = pose_errors(ctx.chain, cq, trot[ids], tpos[ids])
    conv = (pe <= ctx.tol_p) & (re <= ctx.tol_r)
    if not np.any(conv):
        return
    ids, cq, pe, re, seed = ids[conv], cq[conv], pe[conv], re[conv], seed[conv]
    tally.attempted(ids, pe, re, cq)
    tally.accept(ids, cq, -seed.astype(float))


def closed_form_rounds(
    solver: PandaAnalyticIK, ctx: SolveContext, seeds: np.ndarray | None, pref: np.ndarray
) -> None:
    """The closed-form stage: solutions at chosen joint-7 values, nearest ``pref`` first.

    Rounds (around the preferred joint 7 too, grid size): the preferred joint 7
    (one answer each: alone first), values around it and a grid over its range
    (the self-motion may turn back just short of the preferred value), then a
    finer grid (one answer each: and a finer one still), each round only for
    the targets still short of solutions. Where several solutions are wanted,
    :func:`seeded_round` first offers the solutions nearest each seed.

    Args:
        solver: The arm's closed form.
        ctx: The solve call's targets, limits, tolerances and tally.
        seeds: Given seeds (N, K, nq) [rad] or None.
        pref: Preferred configuration per target (N, nq) [rad], inside the limits.
    """
    opts = ctx.opts
    lower, upper = ctx.lower, ctx.upper
    k = opts.analytic_samples
    levers = joint_levers(ctx.robot)
    grids = [(False, 8 * k)] if k else []
    if ctx.one_each:  # the finest grid finds narrow windows; choice needs no more
        # the preferred joint 7 with values around it at once: the branch nearest
        # the preferred posture may sit just beside the preferred joint 7 (at home's
        # joint 7 alone, the Panda's bottle grasps took a q1 1.3 rad from home)
        rounds = [(True, k), *grids, *([(False, 64 * k)] if k else [])]
    else:
        rounds = [(True, k), *grids]
    if (opts.min_solutions > 1 or ctx.by_manipulability) and opts.library_seeds > 0:
        # several solutions wanted: first, like the LM from each seed (the given
        # ones, then the library's nearest), the closed form's solution nearest
        # each seed at its joint 7 and around: solutions spread where the seeds are
        seeded_round(solver, seed_library(ctx.robot, opts), seeds, ctx)
    tried = np.zeros(0)
    for with_pref, samples in rounds:
        ctx.tally.checkpoint()  # the settled targets need no more candidates
        todo = ctx.short()
        if todo.size == 0:
            break
        grid = np.linspace(lower[6], upper[6], samples)  # the ends too: some poses need them
        # a finer grid repeats the coarser one's values: not their solutions again
        new = np.min(np.abs(grid[:, None] - tried[None, :]), axis=1, initial=np.inf) > 1e-12
        grid, tried = grid[new], np.concatenate([tried, grid[new]])
        samples = grid.size
        # the preferred q7 (and, for one answer each, values around it: the
        # self-motion may turn back just short of it)
        near = pref[todo, 6:7] + (_NEAR_Q7 if with_pref and ctx.one_each else 0.0)
        q7s = np.concatenate(
            [np.clip(near, lower[6], upper[6]), np.broadcast_to(grid, (todo.size, samples))],
            axis=1,
        )
        # lever-weighted: a radian at the shoulder moves the hand far more than
        # one at the wrist, so "nearest the preferred posture" is in metres
        only_nearest = ctx.one_each and not ctx.validate
        at, cq, branch, _ = analytic_blocks(
            solver,
            ctx.trot[todo],
            ctx.tpos[todo],
            q7s,
            lower,
            upper,
            # one answer each: only each target's nearest is offered (rank 0)
            nearest_to=(pref[todo], levers) if only_nearest else None,
        )
        if at.size == 0:
            continue
        dist = np.sum(((cq - pref[todo[at]]) * levers) ** 2, axis=1)
        if only_nearest:
            order = np.arange(at.size)
        elif ctx.one_each:  # per target, the nearest to the preferred configuration
            order = np.lexsort((dist, at))
        else:
            # per target, the nearest of each branch first (nearest branch first),
            # then the second nearest of each, ...: choice across branches
            order = np.lexsort((dist, branch, at))
            within = rank_in_runs(at.astype(np.int64)[order] * 8 + branch[order])
            order = order[np.lexsort((dist[order], within, at[order]))]
        _offer_by_rank(ctx, todo, at[order], cq[order], dist[order])


def _offer_by_rank(
    ctx: SolveContext, todo: np.ndarray, at: np.ndarray, cq: np.ndarray, dist: np.ndarray
) -> None:
    """Offer closed-form solutions ``cq`` of targets ``todo[at]`` in order of preference.

    As many as a target still needs (one each: the first; by manipulability: at
    least ``first_round_seeds``); with a validator, in batches of ranks 0, 1,
    2-3, 4-7, ... for the targets still short of valid ones. Each is verified
    by the chain's forward kinematics first.
    """
    opts, tally = ctx.opts, ctx.tally
    n_valid = tally.n_valid
    rank = rank_in_runs(at)
    top = int(rank.max(initial=-1)) + 1
    bounds = [0, top]
    if ctx.validate:
        bounds = [0, *(1 << i for i in range(max(1, top).bit_length())), top]
    for lo, hi in zip(bounds[:-1], bounds[1:], strict=True):
        short = n_valid[todo[at]] < opts.min_solutions
        need = np.maximum(opts.min_solutions - n_valid[todo[at]], 1)
        if ctx.by_manipulability:
            need = np.maximum(need, ctx.first)
        take = short & (rank >= lo) & (rank < hi)
        if not ctx.validate:
            take &= rank < need
        rows = np.flatnonzero(take)
        if rows.size == 0:
            continue
        ids = todo[at[rows]]
        pe, re = pose_errors(ctx.chain, cq[rows], ctx.trot[ids], ctx.tpos[ids])
        conv = (pe <= ctx.tol_p) & (re <= ctx.tol_r)
        if not np.any(conv):
            continue
        rows, ids, pe, re = rows[conv], ids[conv], pe[conv], re[conv]
        tally.attempted(ids, pe, re, cq[rows])
        tally.accept(ids, cq[rows], 1.0 / (1.0 + dist[rows]))
