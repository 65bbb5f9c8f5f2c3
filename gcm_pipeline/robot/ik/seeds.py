"""Seeds of the LM: the seed library, the random restarts and the per-target seed schedule.

Seeds are tried in rounds, only for the targets that still fail, in a fixed
per-target order (a target's result does not depend on the rest of the batch):
given seeds (warm starts from solved neighbours), the nearest entries of a
library of random configurations (KD-tree over position and scaled
quaternion, both quaternion signs), the home configuration, then a last round
with all random restarts at once.
"""

from __future__ import annotations

from dataclasses import replace
from typing import Any

import numpy as np
from scipy.spatial import cKDTree

from gcm_pipeline.geometry.dualquat import quat_from_rotation
from gcm_pipeline.robot.ik.candidates import SolveContext
from gcm_pipeline.robot.ik.lm import PinocchioIKOptions, levenberg_marquardt

__all__ = ["SeedLibrary", "SeedSchedule", "lm_rounds", "restart_seeds", "seed_library"]

_LIBRARY_STREAM = 0x5EED11B
_RESTART_STREAM = 0x5EED2E5


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


class SeedSchedule:
    """The seed columns of a target, in the order the LM tries them.

    Columns: the given seeds, the library's nearest configurations (queried
    lazily: one for everyone, more for the failures), home, then the random
    restarts. After a closed-form search over the whole range of joint 7
    (``closed_form_searched``), the LM is left the poses the closed form cannot
    settle (near singularities, joint-7 windows narrower than its finest grid),
    with a short schedule (``fallback_library_seeds``,
    ``fallback_random_restarts``).
    """

    def __init__(
        self, ctx: SolveContext, seeds: np.ndarray | None, closed_form_searched: bool
    ) -> None:
        robot, opts = ctx.robot, ctx.opts
        self.ctx = ctx
        self.seeds = seeds
        self.lib = seed_library(robot, opts)
        n_lib = max(0, opts.library_seeds)
        self.n_given = 0 if seeds is None else seeds.shape[1]
        self.knn = np.full((ctx.n, n_lib), -1, dtype=int)
        self.n_home = 1 if opts.home_seed else 0
        n_random = max(0, opts.random_restarts)
        if closed_form_searched:
            n_lib = min(n_lib, max(0, opts.fallback_library_seeds))
            n_random = min(n_random, max(0, opts.fallback_random_restarts))
        self.n_lib = n_lib
        #: Columns of the given, library and home seeds.
        self.n_fixed = self.n_given + n_lib + self.n_home
        #: All columns, the random restarts last.
        self.n_rounds = self.n_fixed + n_random
        self.restarts = restart_seeds(robot, n_random, opts.random_seed)

    def column(self, c: int, ids: np.ndarray) -> np.ndarray:
        """Seed column ``c`` (len(ids), nq) [rad] of targets ``ids`` (NaN rows: none)."""
        ctx = self.ctx
        if c < self.n_given:
            assert self.seeds is not None
            return np.asarray(self.seeds[ids, c], dtype=float)
        c -= self.n_given
        if c < self.n_lib:
            # neighbours are queried lazily: one for everyone, more for the failures
            missing = ids[self.knn[ids, c] < 0]
            if missing.size:
                k = 1 if c == 0 else self.n_lib
                self.knn[missing, :k] = self.lib.nearest(
                    ctx.trot[missing], ctx.tpos[missing], k, ctx.opts.library_eps
                )
            return self.lib.q[self.knn[ids, c]]
        if c < self.n_lib + self.n_home:
            return np.broadcast_to(ctx.robot.home, (len(ids), ctx.robot.nq)).copy()
        return np.broadcast_to(
            self.restarts[c - self.n_lib - self.n_home], (len(ids), ctx.robot.nq)
        ).copy()

    def batch(
        self, c: int, width: int, todo: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Columns ``c .. c + width`` of targets ``todo``, finite seeds only.

        Returns:
            ``(ids, q0, cols)``: target (M,), seed clipped to the limits
            (M, nq) [rad] and column (M,) of each (target, seed) pair.
        """
        ids_list, q0_list, col_list = [], [], []
        for cc in range(c, min(c + width, self.n_rounds)):
            q0 = self.column(cc, todo)
            ok = np.all(np.isfinite(q0), axis=1)
            ids_list.append(todo[ok])
            q0_list.append(np.clip(q0[ok], self.ctx.lower, self.ctx.upper))
            col_list.append(np.full(int(ok.sum()), cc))
        return np.concatenate(ids_list), np.concatenate(q0_list), np.concatenate(col_list)


def lm_rounds(
    ctx: SolveContext,
    seeds: np.ndarray | None,
    complete: np.ndarray,
    closed_form_searched: bool,
) -> None:
    """The LM from each target's seeds in rounds, for the targets still short of solutions.

    Every decision is per target, so a target's result does not depend on the
    other targets of the batch (nor on chunking over workers): rounds over the
    given seeds, the library neighbours and home (``round_seeds`` at a time,
    ``first_round_seeds`` in the first), then one last round with all the
    random restarts at once, longer runs and a lenient stall exit. Targets
    ``complete`` (every closed-form branch offered) or settled (the tally's
    ``settle`` needs no more of them, asked before each round) are skipped.
    """
    opts, tally = ctx.opts, ctx.tally
    schedule = SeedSchedule(ctx, seeds, closed_form_searched)
    n_fixed, n_rounds = schedule.n_fixed, schedule.n_rounds
    final_opts = replace(
        opts, stall_ratio=0.9, stall_after=8, max_iterations=2 * opts.max_iterations
    )
    c = 0
    r = 0
    while c < n_rounds:
        tally.checkpoint()  # the settled targets need no more candidates
        todo = ctx.short()
        todo = todo[~complete[todo]]
        run_opts = opts
        if c < n_fixed:
            if r == 0:
                width = ctx.first
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
                todo = todo[tally.att_p[todo] <= opts.give_up_position]
        if todo.size == 0:
            if c >= n_fixed:
                break
            c += width
            continue
        ids, q0, cols = schedule.batch(c, width, todo)
        c += width
        if ids.size == 0:
            continue
        q, conv, pe, re = levenberg_marquardt(
            ctx.chain,
            q0,
            ctx.trot[ids],
            ctx.tpos[ids],
            ctx.lower,
            ctx.upper,
            ctx.tol_p,
            ctx.tol_r,
            run_opts,
        )
        _keep_best_attempts(ctx, ids, q, pe, re)
        if np.any(conv):
            tally.accept(ids[conv], q[conv], -cols[conv].astype(float))


def _keep_best_attempts(
    ctx: SolveContext, ids: np.ndarray, q: np.ndarray, pe: np.ndarray, re: np.ndarray
) -> None:
    """Remember each target's best attempt (for the error report of failures)."""
    tally = ctx.tally
    tol_p, tol_r = ctx.position_tolerance, ctx.orientation_tolerance
    score_att = pe / tol_p + re / tol_r
    order = np.argsort(-score_att)  # best last, so it wins the fancy assignment
    cur = tally.att_p[ids[order]] / tol_p + tally.att_r[ids[order]] / tol_r
    better = score_att[order] < cur
    sel = order[better]
    tally.att_p[ids[sel]] = pe[sel]
    tally.att_r[ids[sel]] = re[sel]
    tally.att_q[ids[sel]] = q[sel]
