r"""Every IK branch of a 6R arm in closed form (EAIK), one representative per branch.

Six-joint arms whose axes intersect or are parallel in the right places (the
Universal Robots family, spherical-wrist arms and others) have finitely many
IK solutions per pose, up to 16, found exactly by subproblem decomposition:
`EAIK <https://github.com/OstermD/EAIK>`_ (Ostermeier et al., 2024, PyPI
``eaik``). A robot gets this solver only if

* its grasp frame hangs on a chain of exactly its 6 joints (a tool adds a fixed
  transform; locked joints are already removed from the model);
* EAIK knows a decomposition of the chain's axes (``hasKnownDecomposition``);
* EAIK's forward kinematics equals the chain's at ``checks`` random
  configurations (:meth:`SixRAnalyticIK.for_chain`), like the Panda's closed
  form (:mod:`~gcm_pipeline.robot.ik.panda`).

The EAIK robot is built from the loaded chain itself (each joint's frame at
q = 0 in the base frame, axis z, and the grasp frame), so the tool, a TCP or a
base offset are part of it. Any other arm keeps the iterative solver.

**Branches modulo 2π.** A branch is a configuration modulo 2π: on a joint
whose range exceeds 2π (±2π on a UR) the same arm shape is reachable at
several angles. :meth:`SixRAnalyticIK.solve` returns each branch once, at the
copy inside the joint limits nearest a reference configuration (the home
posture or a seed), and drops a branch with no copy inside them. EAIK's
approximate answers (``is_LS``: least squares where no exact one exists) are
dropped; the rest are returned unverified: callers verify every answer by
Pinocchio's forward kinematics and the joint limits, as every IK answer of
the project is verified.

The default backend's stage for such an arm, :func:`six_round`, offers every
branch to its targets, nearest the preferred configuration first.

**Poses solved again.** A solver keeps EAIK's answers of the last 16,384 poses
it solved (plain arrays, by the pose's bytes) and gives them again for a pose
equal to one of them to the bit: EAIK's answer is a function of the pose. The
reachability stage asks again for a chunk's targets whose first branch failed
a check (their other branches) and for the ends of moves planned twice.
"""

from __future__ import annotations

import collections
import itertools
import threading
from collections.abc import Callable
from typing import Any

import numpy as np

from gcm_pipeline.robot import kernels
from gcm_pipeline.robot.ik.candidates import SolveContext, rank_in_runs
from gcm_pipeline.robot.ik.lm import pose_errors
from gcm_pipeline.robot.ik.per_robot import per_robot
from gcm_pipeline.robot.ik.reach_6r import joint_frames

__all__ = [
    "SixRAnalyticIK",
    "branch_gap",
    "forget_answers",
    "nearest_copy",
    "repeated_branches",
    "same_as_earlier",
    "six_r_solver",
    "six_round",
    "wide_joints",
]

#: Two EAIK answers closer than this modulo 2π in every joint are one branch [rad].
_SAME_BRANCH = 1e-6
#: Poses whose EAIK answers a solver keeps for a later call with the same pose (two
#: chunks of the engine's 8,192 targets: a chunk's targets are solved again after its
#: moves' end poses).
_RECENT_POSES = 16384
#: Defaults of ``dict.pop`` over a map.
_NONES = itertools.repeat(None)


def wide_joints(lower: np.ndarray, upper: np.ndarray) -> np.ndarray:
    """Joints (nq,) bool whose range exceeds 2π: angles there are compared modulo 2π."""
    span = np.asarray(upper, dtype=float) - np.asarray(lower, dtype=float)
    return span > 2.0 * np.pi + 1e-9  # [-pi, pi] is not wide (its ends are one angle)


def branch_gap(a: np.ndarray, b: np.ndarray, wide: np.ndarray) -> np.ndarray:
    """Per-joint distance of configurations ``a`` and ``b`` (broadcast), modulo 2π on ``wide``.

    Two configurations whose gap is small in every joint are the same branch
    (the same arm shape): ``q`` and ``q + 2π`` on a joint of range 4π have gap 0.
    """
    d = np.abs(np.asarray(a, dtype=float) - np.asarray(b, dtype=float))
    wide = np.asarray(wide, dtype=bool)
    if not wide.any():
        return d  # no joint turns more than once (the Panda): nothing to wrap
    wrapped = np.abs(np.remainder(d[..., wide] + np.pi, 2.0 * np.pi) - np.pi)
    d[..., wide] = wrapped
    return d


def nearest_copy(
    q: np.ndarray, reference: np.ndarray, lower: np.ndarray, upper: np.ndarray
) -> np.ndarray:
    """Each angle of ``q`` (M, nq) moved by whole turns to the copy nearest ``reference``.

    Only copies inside ``[lower, upper]`` count; where a joint has none the
    row gets NaN there. ``reference`` (M, nq) should lie inside the limits.
    """
    two_pi = 2.0 * np.pi
    # the copy nearest the reference, then the one a turn to its other side
    base = q + two_pi * np.round((reference - q) / two_pi)
    other = np.where(base > reference, base - two_pi, base + two_pi)
    inside_b = (base >= lower) & (base <= upper)
    inside_o = (other >= lower) & (other <= upper)
    return np.where(inside_b, base, np.where(inside_o, other, np.nan))


def same_as_earlier(
    group: np.ndarray, q: np.ndarray, close: Callable[[int, np.ndarray, np.ndarray], np.ndarray]
) -> np.ndarray:
    """(M,) bool: the rows of ``q`` (M, nq) close to an earlier row of their group in every joint.

    ``group`` (M,) is sorted; ``close(j, x, y)`` says per pair whether joint
    ``j``'s angles ``x`` and ``y`` (K,) are close. Every row is compared with
    every earlier row of its group (those found to repeat included). The pairs
    are narrowed joint by joint: two distinct solutions mostly differ in their
    first joints, so few pairs reach the later ones.
    """
    m = group.size
    first = np.searchsorted(group, group, side="left")
    rank = np.arange(m) - first  # earlier rows of the group
    b = np.repeat(np.arange(m), rank)
    a = np.arange(b.size) - np.repeat(np.cumsum(rank) - rank, rank) + first[b]
    for j in range(q.shape[1]):
        near = close(j, q[a, j], q[b, j])
        a, b = a[near], b[near]
    repeat = np.zeros(m, dtype=bool)
    repeat[b] = True
    return repeat


def _same_angle(j: int, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Angles in (-π, π] closer than ``_SAME_BRANCH`` modulo 2π (any joint ``j``)."""
    d = np.abs(x - y)
    return np.minimum(d, 2.0 * np.pi - d) < _SAME_BRANCH


def repeated_branches(idx: np.ndarray, q: np.ndarray) -> np.ndarray:
    """(M,) bool: EAIK's answers that repeat an earlier answer of their target.

    ``idx`` (M,) sorted target of each answer, ``q`` (M, 6) its angles in
    (-π, π]: two answers closer than ``_SAME_BRANCH`` modulo 2π in every joint
    are one branch (:func:`same_as_earlier`).
    """
    return same_as_earlier(idx, q, _same_angle)


class _RecentAnswers:
    """EAIK's answers of the last ``size`` poses solved, by the pose's bytes (a ring of slots).

    Plain arrays and a dict of ints: no objects for the garbage collector to
    walk (a tuple per pose cost more than EAIK saved).
    """

    def __init__(self, size: int) -> None:
        self.size = size
        self.slot_of: dict[bytes, int] = {}
        self.key_at: list[bytes | None] = [None] * size  # the key in each slot
        self.count = np.zeros(size, dtype=np.intp)
        self.q = np.zeros((size, 0, 6))  # (slot, answer, joint)
        self.exact = np.zeros((size, 0), dtype=bool)
        self.next = 0

    def find(self, keys: list[bytes]) -> np.ndarray:
        """The slot (N,) of each pose's key, -1 where its answers are not kept."""
        found = map(self.slot_of.get, keys, itertools.repeat(-1))
        return np.fromiter(found, dtype=np.intp, count=len(keys))

    def keep(self, keys: list[bytes], counts: np.ndarray, q: np.ndarray, exact: np.ndarray) -> None:
        """Keep the answers of new poses (the last ``size``), over the oldest kept.

        ``counts`` (M,) answers per pose, ``q`` (sum, 6) and ``exact`` (sum,)
        grouped by pose, as :meth:`SixRAnalyticIK._answers` returns them.
        """
        m = len(keys)
        if m == 0 or self.size == 0:
            return
        width = int(counts.max())
        if width > self.q.shape[1]:  # room for the most answers of one pose
            q_old, exact_old = self.q, self.exact
            self.q = np.zeros((self.size, width, 6))
            self.exact = np.zeros((self.size, width), dtype=bool)
            self.q[:, : q_old.shape[1]], self.exact[:, : exact_old.shape[1]] = q_old, exact_old
        start = np.cumsum(counts) - counts
        take = np.arange(max(m - self.size, 0), m)  # the last ``size``
        slots = (self.next + np.arange(take.size)) % self.size
        self.next = int((self.next + take.size) % self.size)
        # the overwritten slots' keys go first (a key kept twice loses both: a miss, not a
        # wrong answer), then the new keys take the slots
        slot_of, key_at = self.slot_of, self.key_at
        taken, at = keys[m - take.size :], slots.tolist()
        collections.deque(map(slot_of.pop, map(key_at.__getitem__, at), _NONES), maxlen=0)
        collections.deque(map(key_at.__setitem__, at, taken), maxlen=0)
        slot_of.update(zip(taken, at, strict=True))
        c = counts[take]
        self.count[slots] = c
        of = np.repeat(np.arange(take.size), c)
        rank = np.arange(of.size) - (np.cumsum(c) - c)[of]
        if take.size < m:  # the answers of the poses kept
            q, exact = q[start[take][of] + rank], exact[start[take][of] + rank]
        at_slot = slots[of] * self.q.shape[1] + rank  # rows of the flat buffers
        self.q.reshape(-1, 6)[at_slot] = q
        self.exact.reshape(-1)[at_slot] = exact

    def answers(self, slot: np.ndarray, rank: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Answers ``rank`` (K,) of the poses in slots ``slot`` (K,): angles (K, 6), exact (K,)."""
        at_slot = slot * self.q.shape[1] + rank
        return self.q.reshape(-1, 6)[at_slot], self.exact.reshape(-1)[at_slot]


class SixRAnalyticIK:
    """All closed-form IK branches of a 6R chain (see the module doc).

    Args:
        robot: The EAIK robot (``eaik.IK_Homogeneous.HomogeneousRobot``) of the
            chain, whose forward kinematics equal the chain's.
    """

    def __init__(self, robot: Any) -> None:
        self._robot = robot
        self.family = str(robot.getKinematicFamily())
        self._recent = _RecentAnswers(_RECENT_POSES)  # EAIK's answers of the last poses
        self._lock = threading.Lock()  # one thread at a time reads and keeps them

    @classmethod
    def for_chain(
        cls, chain: Any, checks: int = 32, tolerance: float = 1e-9
    ) -> SixRAnalyticIK | None:
        """The solver for a chain, or None when EAIK does not fit it.

        ``chain`` is a :class:`~gcm_pipeline.robot.chain.KinematicChain`. The
        chain qualifies when it moves exactly the model's 6 joints, in order,
        EAIK knows a decomposition of its axes, and EAIK's forward kinematics
        equals the chain's at ``checks`` random configurations to
        ``tolerance`` [m, rad].
        """
        if (
            chain.nq != 6
            or len(chain.joint_ids) != 6
            or not np.array_equal(chain.q_index, np.arange(6))
        ):
            return None
        try:
            from eaik.IK_Homogeneous import HomogeneousRobot
        except ImportError:  # pragma: no cover - eaik is a dependency
            return None
        try:
            robot = HomogeneousRobot(joint_frames(chain))
            if not robot.hasKnownDecomposition():
                return None
            rng = np.random.default_rng(0x6E41C)
            q = rng.uniform(-np.pi, np.pi, size=(checks, 6))
            fk = np.array([robot.fwdKin(qi) for qi in q])
        except (RuntimeError, ValueError):  # EAIK refuses the geometry
            return None
        rot, pos = chain.pose(q)
        if (
            np.max(np.abs(fk[:, :3, :3] - rot)) > tolerance
            or np.max(np.abs(fk[:, :3, 3] - pos)) > tolerance
        ):
            return None
        return cls(robot)

    def raw(self, rot: np.ndarray, pos: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """EAIK's exact answers for N poses, angles in (-π, π], repeats removed.

        Args:
            rot: Rotations (N, 3, 3) of the grasp frame in the base frame.
            pos: Positions (N, 3) [m].

        Returns:
            ``(index, q)``: target (M,) and configuration (M, 6) [rad] of each
            answer, grouped by target in EAIK's order.
        """
        n = len(rot)
        counts, q, exact = self._answers(rot, pos)
        if q.shape[0] == 0:
            return np.zeros(0, dtype=int), np.zeros((0, 6))
        idx = np.repeat(np.arange(n), counts)
        keep = exact & np.all(np.isfinite(q), axis=1)
        idx, q = idx[keep], np.remainder(q[keep] + np.pi, 2.0 * np.pi) - np.pi
        # at singularities EAIK may give one branch twice: keep its first
        first = ~repeated_branches(idx, q)
        return idx[first], q[first]

    def _answers(
        self, rot: np.ndarray, pos: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """EAIK's answers for N poses: count per pose (N,), angles (M, 6), exact (M,) bool.

        A pose equal to one of the last ``_RECENT_POSES`` solved (bit for
        bit) takes their answers again: EAIK's answer is a function of the
        pose (a stage solves a chunk's targets, then the same targets again
        for their other branches where the first failed a check). Threads
        sharing the solver take turns (the kept answers are read and replaced
        in one step).
        """
        with self._lock:
            return self._answers_of(rot, pos)

    def _answers_of(
        self, rot: np.ndarray, pos: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """:meth:`_answers` inside the lock."""
        n = len(rot)
        poses = np.zeros((n, 4, 4))
        poses[:, :3, :3] = rot
        poses[:, :3, 3] = pos
        poses[:, 3, 3] = 1.0
        keys = poses.reshape(n, 16).view(np.dtype((np.void, 128))).ravel().tolist()
        slot = self._recent.find(keys)
        new = np.flatnonzero(slot < 0)
        counts = np.zeros(n, dtype=np.intp)
        counts[slot >= 0] = self._recent.count[slot[slot >= 0]]
        q_new, exact_new = np.zeros((0, 6)), np.zeros(0, dtype=bool)
        if new.size:
            qs, ls = [], []
            for s in self._robot.IK_batched(poses[new], 1):
                qs.append(s.Q)  # (k, 6) float64
                ls.append(s.is_LS)
            counts[new] = np.fromiter(map(len, qs), dtype=np.intp, count=new.size)
            if counts[new].sum():
                q_new = np.concatenate([x for x in qs if len(x)], dtype=float).reshape(-1, 6)
                exact_new = ~np.concatenate(ls, dtype=bool)
        total = int(counts.sum())
        q, exact = q_new, exact_new
        if total and new.size < n:
            # each pose's answers in order: the new ones as EAIK gave them, the others kept
            of = np.repeat(np.arange(n), counts)  # the pose of each answer
            rank = np.arange(total) - (np.cumsum(counts) - counts)[of]
            fresh = slot[of] < 0
            q = np.empty((total, 6))
            exact = np.empty(total, dtype=bool)
            q[fresh], exact[fresh] = q_new, exact_new
            kept = ~fresh
            q[kept], exact[kept] = self._recent.answers(slot[of[kept]], rank[kept])
        # then the new poses' answers are kept (over the oldest: after the reads above)
        self._recent.keep([keys[i] for i in new.tolist()], counts[new], q_new, exact_new)
        if total == 0:
            return counts, np.zeros((0, 6)), np.zeros(0, dtype=bool)
        return counts, q, exact

    def solve(
        self,
        rot: np.ndarray,
        pos: np.ndarray,
        lower: np.ndarray,
        upper: np.ndarray,
        reference: np.ndarray,
    ) -> tuple[np.ndarray, np.ndarray]:
        """Every branch of N poses, each once, at its copy nearest ``reference``.

        Args:
            rot: Target rotations of the grasp frame (N, 3, 3), base frame.
            pos: Target positions (N, 3) [m].
            lower: Lower joint limits (6,) [rad].
            upper: Upper joint limits (6,) [rad].
            reference: Configurations (N, 6) or (6,) [rad]: of the 2π copies of
                a branch inside the limits, the one nearest this is returned.

        Returns:
            ``(index, q)``: target (M,) and configuration (M, 6) [rad] of each
            branch with a copy inside the limits, grouped by target.
            Unverified (see the module doc).
        """
        rot = np.asarray(rot, dtype=float).reshape(-1, 3, 3)
        pos = np.asarray(pos, dtype=float).reshape(-1, 3)
        ref = np.broadcast_to(np.asarray(reference, dtype=float), (len(rot), 6))
        compiled = kernels.get()
        if compiled is not None and np.shape(lower) == np.shape(upper) == (6,):
            counts, answers, exact = self._answers(rot, pos)
            found: tuple[np.ndarray, np.ndarray] = compiled.six_r_branches(
                answers, counts, exact, ref, lower, upper, _SAME_BRANCH
            )
            return found
        idx, q = self.raw(rot, pos)
        if idx.size == 0:
            return idx, q
        q = nearest_copy(q, ref[idx], lower, upper)
        keep = np.all(np.isfinite(q), axis=1)
        return idx[keep], q[keep]


def forget_answers(robot: Any) -> None:
    """Drop the EAIK answers ``robot``'s 6R solver keeps (if it has one).

    For timing the same poses again as the first time (a benchmark's repeats):
    otherwise the repeats take the kept answers instead of solving.
    """
    solver = robot.cache.get(("analytic_6r",))
    if solver is not None:
        with solver._lock:
            solver._recent = _RecentAnswers(_RECENT_POSES)


def six_r_solver(robot: Any) -> SixRAnalyticIK | None:
    """The closed-form branch solver (EAIK) of ``robot``'s 6R arm (cached), or None."""
    return per_robot(robot, ("analytic_6r",), SixRAnalyticIK.for_chain)


def six_round(six: SixRAnalyticIK, ctx: SolveContext, pref: np.ndarray) -> np.ndarray:
    """Every closed-form branch of a 6R arm, nearest the preferred configuration first.

    Each branch comes at its 2 pi copy inside the limits nearest ``pref``
    (N, nq); per target, as many as it needs (``opts.min_solutions``, at least
    ``first_round_seeds`` when the best manipulability decides, else 1) in
    order of distance, verified by the chain's forward kinematics; with a
    validator, in batches of ranks 0, 1, 2-3, 4-7, ... for the targets still
    short of valid ones. A branch is verified only when it may be offered: a
    target's nearest first, its others where that one is off its pose or the
    target needs more (the same branches are offered as if all were verified).

    Returns:
        The targets (K,) that got an exact branch inside the limits: every one
        of their branches has been offered (the enumeration is complete).
    """
    opts, tally = ctx.opts, ctx.tally
    n_valid = tally.n_valid
    least = ctx.first if ctx.by_manipulability else 1
    at, cq = six.solve(ctx.trot, ctx.tpos, ctx.lower, ctx.upper, pref)
    if at.size == 0:
        return at
    dist = np.sum((cq - pref[at]) ** 2, axis=1)
    order = np.lexsort((dist, at))
    at, cq, dist = at[order], cq[order], dist[order]
    heads = np.flatnonzero(np.r_[True, at[1:] != at[:-1]])
    branches = _Verified(ctx, at, cq)
    branches.verify(heads)  # each target's nearest
    branches.verify_targets(~branches.conv & branches.known)  # where that one is off its pose
    # the batches of ranks up to the most branches of a target (no rank beyond: empty)
    top = int(np.max(np.diff(np.r_[heads, at.size])))
    bounds = [0, top]
    if ctx.validate:
        bounds = [0, *(1 << i for i in range(max(1, top).bit_length())), top]
    for lo, hi in zip(bounds[:-1], bounds[1:], strict=True):
        short = n_valid[at] < opts.min_solutions
        need = np.maximum(np.maximum(opts.min_solutions - n_valid[at], 1), least)
        # the targets that may take a branch past their nearest: all of theirs verified
        if lo > 0:
            branches.verify_targets(short)
        elif not ctx.validate:
            branches.verify_targets(short & (need > 1))
        rows = np.flatnonzero(branches.conv)  # by target, nearest first
        rank = rank_in_runs(at[rows])
        take = short[rows] & (rank >= lo) & (rank < hi)
        if not ctx.validate:
            take &= rank < need[rows]
        rows = rows[take]
        if rows.size == 0:
            continue
        ids = at[rows]
        tally.attempted(ids, branches.pe[rows], branches.re[rows], cq[rows])
        tally.accept(ids, cq[rows], 1.0 / (1.0 + dist[rows]))
    return np.unique(at[branches.conv])


class _Verified:
    """The branches ``cq`` of targets ``at`` (sorted), verified by the chain's FK as needed.

    ``known`` says which are verified, ``pe``/``re`` their errors (NaN until
    verified), ``conv`` which of them are within the IK tolerances.
    """

    def __init__(self, ctx: SolveContext, at: np.ndarray, cq: np.ndarray) -> None:
        self.ctx, self.at, self.cq = ctx, at, cq
        self.pe = np.full(at.size, np.nan)
        self.re = np.full(at.size, np.nan)
        self.known = np.zeros(at.size, dtype=bool)
        self.conv = np.zeros(at.size, dtype=bool)

    def verify(self, rows: np.ndarray) -> None:
        """Verify the branches ``rows`` (not yet verified)."""
        if rows.size == 0:
            return
        ctx, ids = self.ctx, self.at[rows]
        pe, re = pose_errors(ctx.chain, self.cq[rows], ctx.trot[ids], ctx.tpos[ids])
        self.pe[rows], self.re[rows], self.known[rows] = pe, re, True
        self.conv[rows] = (pe <= ctx.tol_p) & (re <= ctx.tol_r)

    def verify_targets(self, rows: np.ndarray) -> None:
        """Verify every branch of the targets of ``rows`` (M,) bool not yet verified."""
        if not rows.any():
            return
        whole = np.zeros(self.ctx.tally.n_valid.size, dtype=bool)
        whole[self.at[rows]] = True
        self.verify(np.flatnonzero(whole[self.at] & ~self.known))
