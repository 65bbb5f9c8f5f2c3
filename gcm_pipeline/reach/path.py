r"""Joint paths of straight-line moves: waypoints on the line, bounded deviation between them.

The joint path is piecewise linear through waypoints (knots) on a grid
:math:`SUBSTEPS` times finer than the steps :math:`s_k = k / \mathrm{steps}`
(:func:`plan_moves`), all moves of a batch at once:

0. **Ends beyond reach**: a move whose end no configuration reaches within
   the IK tolerances fails (``no_ik``) without any IK; this is proved from
   the Panda's elbow range or, for a 6R arm of the UR geometry, the reach of its upper arm and
   forearm (:func:`~gcm_pipeline.reach.moves.unreachable_ends`), not searched for.
1. **The end of the move**: one IK of the pose at :math:`s = 1` seeded with
   :math:`q_g` only (a solution elsewhere is of no use), to the IK tolerances
   (verified by Pinocchio FK, strictly inside the limits). Where that fails
   (a long jump near a singularity), the line is followed from the grasp in
   pieces of about ``_REACH`` (2.5 cm), each waypoint started from the
   previous one; a piece that fails fails the move (``no_ik``).
2. **Segments** between consecutive known waypoints (first the whole move) are
   accepted when no joint changes by more than ``max_joint_step`` per grid step
   and a **bound** on the deviation of the gripper from its straight-line path
   over the whole segment is at most ``max_deviation`` [m]. Otherwise the
   segment is split into :math:`k` parts (the deviation falls with the square
   of a segment's length: :math:`k` is the count expected to bring each part
   to ``_AIM`` of the tolerance) with new waypoints on the line, started from
   the segment's joint interpolation and converged by a few Levenberg-Marquardt
   steps to a small share of the deviation budget (``KNOT_TOLERANCE`` of
   :mod:`~gcm_pipeline.reach.waypoints`): their error is part of what the bound
   measures, so they need not meet the IK tolerance. A waypoint that does not
   converge, a jump within one grid step or a deviation within one fine step
   fails the move.

The bound is computed on the actual joint path, so the path is sound whatever
its waypoints are: every gripper point stays within ``max_deviation`` of its
line. The paths' collisions are checked by
:func:`~gcm_pipeline.reach.move_check.check_moves`.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from gcm_pipeline.errors import InputError
from gcm_pipeline.reach.deviation import lever_arms, segment_bounds
from gcm_pipeline.reach.moves import Move, MovePlan, unreachable_ends
from gcm_pipeline.reach.waypoints import (
    end_of_move,
    largest_change,
    line_waypoints,
    max_over_joints,
)
from gcm_pipeline.robot import kernels
from gcm_pipeline.robot.ik import solve_ik
from gcm_pipeline.robot.model import Robot

__all__ = ["SUBSTEPS", "plan_moves"]

#: Samples per unit of the segment parameter are chosen so that the h^2 terms
#: of the deviation bound use at most this share of ``max_deviation``.
_SLACK_SHARE = 0.25
#: Share of ``max_deviation`` a split segment's parts aim at.
_AIM = 0.6
#: Waypoints may sit this many times closer than the steps where the path bends.
SUBSTEPS = 8
#: Where one IK cannot reach the end of a move from the grasp, the line is
#: followed in pieces of about this length [m] (continuation).
_REACH = 0.025


def plan_moves(
    robot: Robot,
    poses: Any,
    q_start: Any,
    move: Move,
    *,
    gripper_radius: float,
    position_tolerance: float = 1e-4,
    orientation_tolerance: float = 1e-3,
    backend: str = "pinocchio",
    grid_knots: bool = False,
    knot_check: Callable[[np.ndarray, np.ndarray], Any] | None = None,
    check_first: Any = None,
    knots: bool = True,
    **ik_options: Any,
) -> MovePlan:
    """Joint paths of N moves from their grasps, batched over the moves (see module doc).

    Args:
        robot: The robot.
        poses: Grasp poses (N, 4, 4) in the base frame [m].
        q_start: Configurations reaching them (N, nq) [rad]; NaN rows fail (``invalid``).
        move: The move.
        gripper_radius: Largest distance of a gripper point from the grasp frame [m].
        position_tolerance: IK tolerance of the end of the move [m].
        orientation_tolerance: IK tolerance of the end of the move [rad].
        backend: IK backend of the end of the move.
        grid_knots: Start with a waypoint at every grid point (on the line
            within the waypoint tolerance) instead of none.
        knot_check: With ``grid_knots``: ``knot_check(q, move) -> reasons`` (as
            ``collisions`` of :func:`~gcm_pipeline.reach.move_check.check_moves`)
            on the grid waypoints found; a move fails at its first waypoint
            (in the order of checks) that gets a reason, with that reason.
        check_first: With ``knot_check``: per move (N,) the grid step, clipped to
            ``1 .. steps - 1``, up to which its waypoints are found first (where
            its first path collided: most moves fail there). That waypoint is
            checked first, then the earlier ones, the later inner ones, the
            end's (its IK only if every other waypoint is free). Which moves
            pass, and their paths, do not depend on it (a failing move's reason
            may); None: the whole line, then the checks in order.
        knots: False: the plan's ``knots`` is None (for a caller that needs only
            the path: the (N, 8 steps + 1, nq) array is not built).
        **ik_options: Further backend options of the end's IK (seeded only
            with the grasp's configuration unless given otherwise).

    Returns:
        The :class:`MovePlan`.

    Raises:
        InputError: Arrays of the wrong shape.
    """
    tg, qg, check_first = _checked_inputs(robot, poses, q_start, check_first)
    n, nq, steps = tg.shape[0], robot.nq, move.steps
    ok = np.all(np.isfinite(qg), axis=1) & np.all(np.isfinite(tg), axis=(1, 2))
    reason = np.where(ok, "", "invalid").astype(object)
    failed = np.zeros(n, dtype=int)
    q_path = np.full((n, steps + 1, nq), np.nan)
    deviation = np.where(ok, 0.0, np.nan)
    waypoints = np.zeros(n, dtype=int)
    fine_steps = steps * SUBSTEPS
    if move.distance == 0 or not np.any(ok):
        q_path[ok] = qg[ok, None, :]
        dense = None
        if knots:
            dense = np.full((n, fine_steps + 1, nq), np.nan)
            dense[ok] = qg[ok, None, :]
        return MovePlan(ok, reason.astype(str), failed, q_path, deviation, waypoints, dense)

    batch = _MoveBatch(
        robot=robot,
        move=move,
        tg=tg,
        qg=qg,
        offsets=move.offsets(tg),
        ok=ok,
        reason=reason,
        failed=failed,
        knots=_Knots(qg, fine_steps + 1),
        failed_at=np.zeros(n, dtype=int),
        gripper_radius=gripper_radius,
        position_tolerance=position_tolerance,
        orientation_tolerance=orientation_tolerance,
        backend=backend,
        ik_options=_end_ik_options(backend, ik_options),
        grid_knots=grid_knots,
        knot_check=knot_check,
        check_first=check_first,
    )
    _reach_ends(batch)
    _settle_segments(batch, deviation, waypoints)
    _grid_path(batch, q_path)
    q_path[~ok] = np.nan
    deviation[~ok] = np.nan
    waypoints[~ok] = 0
    dense = batch.knots.dense(ok) if knots else None
    return MovePlan(ok, reason.astype(str), failed, q_path, deviation, waypoints, dense)


def _checked_inputs(
    robot: Robot, poses: Any, q_start: Any, check_first: Any
) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """``poses`` (N, 4, 4), ``q_start`` (N, nq) and ``check_first`` (N,) ints or None, checked.

    Raises:
        InputError: Arrays of the wrong shape.
    """
    tg = np.asarray(poses, dtype=float)
    if tg.ndim == 2:
        tg = tg[None]
    qg = np.asarray(q_start, dtype=float)
    if qg.ndim == 1:
        qg = qg[None]
    n, nq = tg.shape[0], robot.nq
    if tg.shape != (n, 4, 4) or qg.shape != (n, nq):
        raise InputError(
            f"poses must be (N, 4, 4) and q_start (N, {nq}) with the same N, "
            f"got {tg.shape} and {qg.shape}"
        )
    if check_first is not None:
        check_first = np.asarray(check_first)
        if check_first.shape != (n,) or not np.issubdtype(check_first.dtype, np.integer):
            raise InputError(f"check_first must be (N,) = ({n},) ints, got {check_first.shape}")
    return tg, qg, check_first


def _end_ik_options(backend: str, ik_options: dict[str, Any]) -> dict[str, Any]:
    """The options of the end's IK: seeded with the grasp's configuration only, unless given."""
    if backend == "pinocchio":
        return {
            "library_seeds": 0,
            "random_restarts": 0,
            "home_seed": False,
            "diagnose_limits": False,
            "analytic_samples": 0,  # closed form at and around the last waypoint's joint 7
            **ik_options,
        }
    if backend == "mink":
        return {"library_seeds": 0, "random_restarts": 0, "home_seed": False, **ik_options}
    return ik_options


def _nonzero_2d(mask: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``np.nonzero`` of a 2-D ``mask``: its rows and columns, in row-major order.

    By one search of the flat mask (about 4x faster than ``np.nonzero`` on the
    knots' slots: a few positions of 81 set per row).
    """
    flat = np.flatnonzero(mask)
    row = flat // mask.shape[1]
    return row, flat - row * mask.shape[1]


class _Knots:
    """The waypoints found so far, by move and fine position: ``knots[rows, at]``.

    A compact stand-in for the (N, positions, nq) array of :attr:`MovePlan.knots`
    (most positions of most moves stay empty): ``slot`` (N, positions) indexes the
    rows of ``q`` (-1: none). Reading an empty position gives NaN, as that array
    would; a waypoint whose first joint is not finite counts as none (as there);
    :meth:`dense` builds the array.
    """

    def __init__(self, q0: np.ndarray, positions: int) -> None:
        n, nq = q0.shape
        self.q = np.empty((3 * n, nq))
        small = self.q.shape[0] <= np.iinfo(np.int32).max  # slots widen as q grows
        self.slot = np.full((n, positions), -1, dtype=np.int32 if small else np.int64)
        self.size = 0
        self[np.arange(n), 0] = q0

    @property
    def have(self) -> np.ndarray:
        """(N, positions) bool: where a waypoint is known."""
        return self.slot >= 0

    def _flat(self, rows: Any, at: Any) -> Any:
        """Positions of ``slot[rows, at]`` in the flat ``slot`` (broadcast as indexing does)."""
        return rows * self.slot.shape[1] + at

    def __getitem__(self, index: tuple[Any, Any]) -> np.ndarray:
        # np.take on flat positions: NumPy's fancy indexing gathers rows several times slower
        slot = self.slot.take(self._flat(*index))
        out = self.q.take(slot, axis=0)
        none = slot < 0
        if none.any():
            out[none] = np.nan
        return out

    def __setitem__(self, index: tuple[np.ndarray, Any], values: np.ndarray) -> None:
        """Waypoints ``values`` (M, nq) at ``index = (rows (M,), at (M,) or one int)``."""
        rows, at = index
        keep = np.isfinite(values[:, 0])
        if not keep.all():
            at = np.broadcast_to(at, rows.shape)
            self.slot[rows[~keep], at[~keep]] = -1
            rows, at, values = rows[keep], at[keep], values[keep]
        end = self.size + rows.size
        if end > self.q.shape[0]:
            grown = np.empty((max(end, 2 * self.q.shape[0]), self.q.shape[1]))
            grown[: self.size] = self.q[: self.size]
            self.q = grown
            if grown.shape[0] > np.iinfo(self.slot.dtype).max:
                self.slot = self.slot.astype(np.int64)
        self.q[self.size : end] = values
        np.put(self.slot, self._flat(rows, at), np.arange(self.size, end))
        self.size = end

    def clear(self, rows: np.ndarray) -> None:
        """Forget every waypoint of ``rows`` but the first (the grasp)."""
        self.slot[rows, 1:] = -1

    def dense(self, ok: np.ndarray) -> np.ndarray:
        """The (N, positions, nq) array of the waypoints of the rows ``ok``, NaN elsewhere."""
        n, positions = self.slot.shape
        out = np.full((n, positions, self.q.shape[1]), np.nan)
        r, p = _nonzero_2d(self.have & ok[:, None])
        out[r, p] = self.q[self.slot[r, p]]
        return out


@dataclass
class _MoveBatch:
    """One batch of N moves being planned: its inputs and the arrays the steps fill in.

    ``ok``, ``reason`` and ``failed`` are the moves' verdicts so far (a move
    fails once, at its first failure); ``knots`` the waypoints found (at the
    fine positions 0 .. fine steps); ``failed_at`` the fine step where a move's
    line following stopped.
    """

    robot: Robot
    move: Move
    tg: np.ndarray
    qg: np.ndarray
    offsets: np.ndarray
    ok: np.ndarray
    reason: np.ndarray
    failed: np.ndarray
    knots: _Knots
    failed_at: np.ndarray
    gripper_radius: float
    position_tolerance: float
    orientation_tolerance: float
    backend: str
    ik_options: dict[str, Any]
    grid_knots: bool
    knot_check: Callable[[np.ndarray, np.ndarray], Any] | None
    check_first: np.ndarray | None

    @property
    def n(self) -> int:
        """Moves in the batch."""
        return self.tg.shape[0]

    @property
    def steps(self) -> int:
        """Grid steps of every move."""
        return self.move.steps

    @property
    def fine_steps(self) -> int:
        """Positions of waypoints: ``SUBSTEPS`` per grid step."""
        return self.move.steps * SUBSTEPS

    def fail(self, rows: np.ndarray, at: np.ndarray, why: Any) -> None:
        """Rows fail at fine positions ``at`` (the first per row counts)."""
        if rows.size == 0:
            return
        first = np.full(self.n, self.fine_steps)
        np.minimum.at(first, rows, at)
        hit = np.zeros(self.n, dtype=bool)
        hit[rows] = True
        bad = np.flatnonzero(hit)  # np.unique(rows), without its sort
        self.ok[bad] = False
        self.reason[bad] = why if isinstance(why, str) else why[bad]
        self.failed[bad] = np.minimum(first[bad] // SUBSTEPS + 1, self.steps)

    def advance(self, rows: np.ndarray, lo: np.ndarray, hi: np.ndarray, pieces: int) -> np.ndarray:
        """Waypoints ``lo + 1 .. hi`` (per row) of the line cut in ``pieces``.

        Each starts from the previous one (waypoint 0 is the grasp); a waypoint
        that does not converge stops its row. Returns (M,) bool: the rows that
        got them all.
        """
        fine_steps, knots = self.fine_steps, self.knots
        alive = np.ones(rows.size, dtype=bool)
        for i in range(1, pieces + 1):
            sel = np.flatnonzero(alive & (lo < i) & (i <= hi))
            if sel.size == 0:
                continue
            r = rows[sel]
            at, prev = (i * fine_steps) // pieces, ((i - 1) * fine_steps) // pieces
            target = self.tg.take(r, axis=0)
            target[:, :3, 3] += (at / fine_steps) * self.offsets.take(r, axis=0)
            seed = knots[r, prev]
            if at < fine_steps:
                q_new, conv = line_waypoints(
                    self.robot, seed, target, self.move.max_deviation, self.gripper_radius
                )
            else:
                res = solve_ik(
                    self.robot,
                    target,
                    self.backend,
                    position_tolerance=self.position_tolerance,
                    orientation_tolerance=self.orientation_tolerance,
                    seeds=seed[:, None, :],
                    **self.ik_options,
                )
                q_new, conv = res.q, res.success
            knots[r[conv], at] = q_new[conv]
            self.failed_at[r[~conv]] = prev
            alive[sel[~conv]] = False
        return alive

    def check_grid(self, rows: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> None:
        """``knot_check`` on the grid waypoints ``lo + 1 .. hi`` found (per row), one batch.

        A row fails at its first waypoint the check rejects.
        """
        sub = SUBSTEPS
        k = np.arange(1, self.steps + 1)
        grid = self.knots[rows[:, None], k * sub]  # (m, steps, nq), NaN where not found
        found = np.isfinite(grid[:, :, 0]) & (k > lo[:, None]) & (k <= hi[:, None])
        owner = np.broadcast_to(rows[:, None], found.shape)
        why = np.full(found.shape, "", dtype=object)
        if found.any():
            assert self.knot_check is not None
            why[found] = np.asarray(self.knot_check(grid[found], owner[found]), dtype=object)
        hit = why != ""
        bad = np.flatnonzero(hit.any(axis=1))
        first = hit[bad].argmax(axis=1)
        row_why = np.full(self.n, "", dtype=object)
        row_why[rows[bad]] = why[bad, first]
        self.fail(rows[bad], (first + 1) * sub - 1, row_why)  # fails at grid step first + 1

    def follow(self, rows: np.ndarray, pieces: int) -> np.ndarray:
        """The rows that reach the end following the line from the grasp in pieces.

        Each waypoint starts from the previous one; a failure fails the row. With
        ``knot_check`` (``pieces == steps``: the waypoints are the grid points)
        the waypoints are checked too: without ``check_first`` all at once when
        the line is followed, a row failing at its first waypoint the check
        rejects. With it, each row's waypoints up to its ``check_first`` step
        are found, the one at that step is checked (where the first path
        collided: most rows fail there), then the earlier ones; then the rest
        of the line's inner waypoints are found and checked, and last the
        end's (its IK is the dearest waypoint) for the rows still free. The
        rows that pass do not depend on ``check_first``; a row that fails may
        fail at another of its failures (see :func:`plan_moves`).
        """
        start, zero = rows, np.zeros(rows.size, dtype=int)
        end = np.full(rows.size, pieces)
        if self.knot_check is None or not self.grid_knots or rows.size == 0:
            rows = rows[self.advance(rows, zero, end, pieces)]
        elif self.check_first is None:
            got = self.advance(rows, zero, end, pieces)
            self.check_grid(rows, zero, end)
            rows = rows[got & self.ok[rows]]
        else:
            pause = np.clip(self.check_first[rows], 1, max(pieces - 1, 1))
            got = self.advance(rows, zero, pause, pieces)
            for lo, hi in ((pause - 1, pause), (zero, pause - 1)):
                self.check_grid(rows[got], lo[got], hi[got])
                got &= self.ok[rows]
            # the rest of the line: its inner waypoints, then the end's
            for lo, hi in ((pause, np.maximum(end - 1, pause)), (np.maximum(end - 1, pause), end)):
                sel = np.flatnonzero(got & (lo < hi))
                found = self.advance(rows[sel], lo[sel], hi[sel], pieces)
                got[sel] = found
                sel = sel[found]
                self.check_grid(rows[sel], lo[sel], hi[sel])
                got &= self.ok[rows]
            rows = rows[got]
        lost = np.ones(self.n, dtype=bool)
        lost[rows] = False
        self.knots.clear(start[lost[start]])
        return rows


def _reach_ends(b: _MoveBatch) -> None:
    """Steps 0 and 1: the ends of the moves (waypoints at the last fine step), or failures."""
    ok, move, tg, offsets, knots = b.ok, b.move, b.tg, b.offsets, b.knots
    # 0. ends proved beyond reach fail at once, whatever the IK would try
    beyond = np.flatnonzero(
        ok & unreachable_ends(b.robot, tg, move, b.position_tolerance, b.orientation_tolerance)
    )
    b.fail(beyond, np.full(beyond.size, b.fine_steps), "no_ik")

    # 1. the end of the move: one IK seeded from the grasp's configuration; where it
    # fails, the line is followed from the grasp in pieces of about _REACH
    # (continuation: each waypoint started from the previous ones and converged to
    # the waypoint tolerance, the last to the IK tolerances)
    pieces = int(np.clip(np.ceil(move.distance / _REACH), 1, b.steps))
    rows = np.flatnonzero(ok)
    if b.grid_knots:
        reached = b.follow(rows, b.steps)
    else:
        ends = tg.take(rows, axis=0)
        ends[:, :3, 3] += offsets.take(rows, axis=0)
        q_end, done = end_of_move(
            b.robot,
            ends,
            b.qg.take(rows, axis=0),
            b.backend,
            b.position_tolerance,
            b.orientation_tolerance,
            b.ik_options,
        )
        knots[rows[done], b.fine_steps] = q_end[done]
        reached = np.concatenate([rows[done], b.follow(rows[~done], pieces)])
    got = np.zeros(b.n, dtype=bool)
    got[reached] = True
    lost = rows[~got[rows] & ok[rows]]  # not those a knot check failed
    b.fail(lost, b.failed_at[lost], "no_ik")


def _settle_segments(b: _MoveBatch, deviation: np.ndarray, waypoints: np.ndarray) -> None:
    """Step 2: every segment accepted under the bounds, or split, or its move failed.

    ``deviation`` (N,) and ``waypoints`` (N,) get each move's largest bound and
    its count of accepted segments.
    """
    robot, move, tg, offsets, knots, ok = b.robot, b.move, b.tg, b.offsets, b.knots, b.ok
    sub, tol = SUBSTEPS, move.max_deviation
    # the lines' starts and orientations as whole arrays: rows by np.take (NumPy's fancy
    # indexing gathers them several times slower, mixed with slices far slower)
    line_start, line_rot = np.ascontiguousarray(tg[:, :3, 3]), np.ascontiguousarray(tg[:, :3, :3])
    # segments between known waypoints: accepted under the deviation bound, else
    # split; a new waypoint starts from the segment's joint interpolation
    r_idx, pos = _nonzero_2d(knots.have & ok[:, None])
    inner = r_idx[1:] == r_idx[:-1]
    s_row, s_a, s_b = r_idx[1:][inner], pos[:-1][inner], pos[1:][inner]
    parts = np.ones(s_row.size, dtype=int)
    while s_row.size:
        split = np.flatnonzero(parts > 1)
        if split.size:
            s_row, s_a, s_b = _split_segments(
                robot,
                tg,
                offsets,
                knots,
                s_row,
                s_a,
                s_b,
                split,
                parts[split],
                b.fine_steps,
                tol,
                b.gripper_radius,
                b.fail,
            )
            keep = ok[s_row]
            s_row, s_a, s_b = s_row[keep], s_a[keep], s_b[keep]
        if s_row.size == 0:
            break
        qa, qb = knots[s_row, s_a], knots[s_row, s_b]
        span = s_b - s_a
        # the change per grid step: segments of a step or more change every step
        # alike; shorter ones may not change more than one step's worth
        jump = largest_change(qb, qa) * sub / np.maximum(span, sub)
        over = jump > move.max_joint_step
        dev = np.full(s_row.size, np.inf)
        fine = np.flatnonzero(~over)
        on = s_row.take(fine)
        dev[fine] = segment_bounds(
            robot,
            lever_arms(robot),
            qa.take(fine, axis=0),
            qb.take(fine, axis=0),
            line_start.take(on, axis=0),
            line_rot.take(on, axis=0),
            offsets.take(on, axis=0),
            b.gripper_radius,
            _SLACK_SHARE * tol,
            reject_above=tol,
        )
        good = ~over & (dev <= tol)
        np.maximum.at(deviation, s_row[good], dev[good])
        np.add.at(waypoints, s_row[good], 1)
        # a jump within one grid step, a deviation within one fine step: the move fails
        dead = (over & (span <= sub)) | (~over & ~good & (span <= 1))
        if dead.any():
            why = np.full(b.n, "deviation", dtype=object)
            why[s_row[dead & over]] = "joint_step"
            b.fail(s_row[dead], s_a[dead], why)
        again = ~good & ~dead & ok[s_row]
        # the deviation falls with the square of a segment's length
        need = np.where(
            over, np.ceil(jump / move.max_joint_step), np.ceil(np.sqrt(dev / (_AIM * tol)))
        )
        parts = np.clip(np.nan_to_num(need, nan=2.0, posinf=2.0), 2, np.maximum(span, 2))
        s_row, s_a, s_b, parts = s_row[again], s_a[again], s_b[again], parts[again].astype(int)


def _grid_path(b: _MoveBatch, q_path: np.ndarray) -> None:
    """The grid points (in ``q_path``) on the piecewise linear path through the knots.

    A move whose joints change by more than ``max_joint_step`` between two grid
    points fails (``joint_step``).
    """
    rows = np.flatnonzero(b.ok)
    if rows.size == 0:
        return
    compiled = kernels.get()
    # the kernel does the reference's arithmetic row by row (equal to the bit)
    points = _grid_points if compiled is None else compiled.grid_path
    path, jump_at = points(
        b.knots.slot.take(rows, axis=0),
        b.knots.q[: b.knots.size],
        SUBSTEPS,
        b.move.max_joint_step,
    )
    q_path[rows] = path
    over = np.flatnonzero(jump_at >= 0)
    if over.size:
        b.fail(rows[over], jump_at[over] * SUBSTEPS, "joint_step")


def _grid_points(
    slot: np.ndarray, knots: np.ndarray, sub: int, max_step: float
) -> tuple[np.ndarray, np.ndarray]:
    """Joint paths at the grid points through their waypoints, and their first jump.

    The NumPy reference of :func:`~gcm_pipeline.robot.chain_kernel.grid_path`
    (same arguments and results): ``slot`` (M, steps * sub + 1) the row of
    ``knots`` at each fine position (-1: none; every path has waypoints at its
    first and last); returns the paths (M, steps + 1, nq) and each one's first
    grid step (0-based) whose largest joint change exceeds ``max_step``, -1 if none.
    """
    m, width = slot.shape
    steps = (width - 1) // sub
    # the knots on each side of every grid point: the last at or before it and
    # the first at or after it (np.take throughout: NumPy's fancy indexing
    # gathers several times slower)
    keys = np.flatnonzero(slot >= 0)  # row * width + position, sorted
    pos = keys % width
    slot = slot.take(keys)
    grid = np.arange(steps + 1) * sub
    query = (np.arange(m)[:, None] * width + grid).ravel()
    shape = (m, steps + 1)
    before = np.searchsorted(keys, query, side="right") - 1
    # the first at or after: that knot where one sits on the grid point, else the next
    # (the keys are distinct)
    after = before + (keys.take(before) != query)
    pa, pb = pos.take(before).reshape(shape), pos.take(after).reshape(shape)
    ka = knots.take(slot.take(before), axis=0).reshape(*shape, -1)
    f = ((grid - pa) / np.maximum(pb - pa, 1))[:, :, None]
    # ka + f * (kb - ka), in one array
    path = knots.take(slot.take(after), axis=0).reshape(*shape, -1)
    path -= ka
    path *= f
    path += ka
    # the change of every joint between consecutive grid points
    step = np.subtract(path[:, 1:], path[:, :-1])
    np.abs(step, out=step)
    big = max_over_joints(step) > max_step
    jump_at = np.where(big.any(axis=1), np.argmax(big, axis=1), -1)
    return path, jump_at


def _split_segments(
    robot: Robot,
    poses: np.ndarray,
    offsets: np.ndarray,
    knots: _Knots,
    s_row: np.ndarray,
    s_a: np.ndarray,
    s_b: np.ndarray,
    split: np.ndarray,
    parts: np.ndarray,
    fine_steps: int,
    tol: float,
    radius: float,
    fail: Callable[[np.ndarray, np.ndarray, str], None],
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Split segments ``split`` into ``parts`` pieces with new waypoints (in ``knots``).

    A new waypoint starts from the joint interpolation of its segment and
    converges to its pose on the line within ``KNOT_TOLERANCE`` of the
    deviation budget (batched Levenberg-Marquardt, inside the joint limits);
    a row whose waypoint does not converge fails (``no_ik``).

    Returns:
        The segments ``(row, a, b)`` after the split, the others unchanged.
    """
    cnt = parts - 1
    owner = np.repeat(split, cnt)
    i = np.arange(owner.size) - np.repeat(np.cumsum(cnt) - cnt, cnt) + 1
    a, b = s_a[owner], s_b[owner]
    at = a + (i * (b - a)) // parts[np.repeat(np.arange(split.size), cnt)]
    row = s_row[owner]
    qa, qb = knots[row, a], knots[row, b]
    seed = qa + ((at - a) / (b - a))[:, None] * (qb - qa)
    target = poses.take(row, axis=0)
    target[:, :3, 3] += (at / fine_steps)[:, None] * offsets.take(row, axis=0)
    q_new, conv = line_waypoints(robot, seed, target, tol, radius)
    knots[row[conv], at[conv]] = q_new[conv]
    fail(row[~conv], at[~conv], "no_ik")
    # every split segment becomes its parts: boundaries sorted within each segment
    seg = np.concatenate([split, owner])
    start = np.concatenate([s_a[split], at])
    o = np.lexsort((start, seg))
    seg, start = seg[o], start[o]
    stop = np.empty_like(start)
    stop[:-1] = start[1:]
    last = np.ones(seg.size, dtype=bool)
    last[:-1] = seg[1:] != seg[:-1]
    stop[last] = s_b[seg[last]]
    rest = np.ones(s_row.size, dtype=bool)
    rest[split] = False
    return (
        np.concatenate([s_row[rest], s_row[seg]]),
        np.concatenate([s_a[rest], start]),
        np.concatenate([s_b[rest], stop]),
    )
