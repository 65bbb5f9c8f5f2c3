r"""Straight-line moves of the grasp frame: the pre-grasp approach and the post-grasp retreat.

A move starts at a grasp pose :math:`T_g` (reached by :math:`q_g`) and
translates the grasp frame by a vector :math:`d` (base frame) at fixed
orientation:

.. math::

    T(s) = \operatorname{translate}(s\,d)\,T_g, \qquad s \in [0, 1].

The **approach** is the move with :math:`d = -\mathrm{distance}\,z_g` (the
pre-grasp lies behind the grasp along its approach axis; the robot runs it
from :math:`s = 1` to :math:`s = 0`); the **retreat** moves ``distance`` along a
direction given in the base or the grasp frame (see :class:`Move`). Both are
computed from the grasp outwards, so the path stays on the grasp solution's
IK branch.

The joint path is piecewise linear through IK waypoints placed on the grid
:math:`s_k = k / \mathrm{steps}`. It is built by tracking from the grasp with an
adaptive step: from the last waypoint :math:`a` the IK solves the pose at
:math:`b = a + \mathrm{step}` seeded with :math:`q_a` (no other seeds: a solution
elsewhere is of no use), and the segment is accepted when

* the IK converged (verified by Pinocchio FK, strictly inside the limits),
* no joint changes by more than ``max_joint_step`` per grid step, and
* a **bound** on the deviation of the gripper from its straight-line path over
  the whole segment is at most ``max_deviation`` [m];

otherwise the step shrinks (down to one grid step, where a failure fails the
move) and after an accepted segment it grows: the deviation grows with the
square of a segment's length, so the next length is the one expected to use
about half the tolerance (halved after an IK or joint-step failure). A move
that needs no waypoint in between costs one IK.

Deviation bound. Along a segment :math:`q(s) = q_a + s\,\Delta q` the grasp
frame's position :math:`p(s)` has :math:`|p''| \le K = \sum_{j,k} r_{\max(j,k)}
|\Delta q_j| |\Delta q_k|`, with :math:`r_k` a bound of the distance of the
grasp frame from joint :math:`k`'s axis (the link lengths beyond it), because
:math:`\partial^2 p / \partial q_j \partial q_k = a_j \times (a_k \times (p -
o_k))` for :math:`j \le k`. Sampled at spacing :math:`h`, the distance of
:math:`p(s)` from the line segment is at most the largest sampled distance plus
:math:`K h^2 / 8` (the error of linear interpolation; the distance to a
segment is convex). Likewise :math:`\|R''\|_F \le \tfrac{3}{\sqrt 2} A^2` with
:math:`A = \sum_j |\Delta q_j|`, so :math:`\|R(s) - R_g\|_F` is at most its
largest sample plus :math:`\tfrac{3}{8\sqrt 2} A^2 h^2`. A point of the gripper
at distance at most :math:`\rho` from the grasp frame then leaves its straight
path by at most ``position bound`` + :math:`\rho` ``rotation bound``: that is
the deviation compared with ``max_deviation``. The samples are dense enough
for the :math:`h^2` terms to use at most a quarter of it.

Collisions are checked by :func:`check_moves` at every grid point
:math:`s_k, k \ge 1` of the joint path (the grasp itself, :math:`k = 0`, is the
caller's), with the check the caller gives (the approach: no contact allowed;
the retreat: the gripper holds the object, which moves with it).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, NamedTuple

import numpy as np

from gcm_pipeline.errors import InputError
from gcm_pipeline.robot.ik import solve_ik
from gcm_pipeline.robot.model import Robot

__all__ = [
    "MOVE_REASONS",
    "Move",
    "MovePlan",
    "MoveResult",
    "SUBSTEPS",
    "check_moves",
    "gripper_radius",
    "lever_arms",
    "move_poses",
    "plan_moves",
]

#: Why a move fails (``MoveResult.reason``), besides the checker's collision reasons.
MOVE_REASONS = ("invalid", "no_ik", "joint_step", "deviation")

#: Samples per unit of the segment parameter are chosen so that the h^2 terms
#: of the deviation bound use at most this share of ``max_deviation``.
_SLACK_SHARE = 0.25
#: At most this many samples per segment (a segment needing more is split).
_MAX_SAMPLES = 64
#: Share of ``max_deviation`` the next segment's length aims at.
_AIM = 0.6
#: IK waypoints may sit this many times closer than the steps where the path bends.
SUBSTEPS = 8


@dataclass(frozen=True)
class Move:
    """A straight-line move of the grasp frame (plain values; the stage maps the config).

    Attributes:
        distance: Length of the move [m], >= 0 (0: nothing to check).
        direction: Direction (3,), normalised here; in the grasp frame
            (``frame="grasp"``) or the robot's base frame (``frame="base"``).
        frame: ``"grasp"`` or ``"base"``.
        steps: Grid steps along the line (collision samples, finest waypoints), >= 1.
        max_joint_step: Largest change of any joint per grid step [rad], > 0.
        max_deviation: Largest deviation of any gripper point from its straight
            path [m], > 0.
        holding: The gripper holds the object (a retreat): the caller checks
            collisions with the object attached.
    """

    distance: float = 0.10
    direction: tuple[float, float, float] = (0.0, 0.0, -1.0)
    frame: str = "grasp"
    steps: int = 10
    max_joint_step: float = 0.25
    max_deviation: float = 0.002
    holding: bool = False

    def __post_init__(self) -> None:
        if not np.isfinite(self.distance) or self.distance < 0:
            raise InputError(f"move distance must be >= 0 [m], got {self.distance!r}")
        if int(self.steps) != self.steps or self.steps < 1:
            raise InputError(f"move steps must be an int >= 1, got {self.steps!r}")
        if not np.isfinite(self.max_joint_step) or self.max_joint_step <= 0:
            raise InputError(f"move max_joint_step must be > 0 [rad], got {self.max_joint_step!r}")
        if not np.isfinite(self.max_deviation) or self.max_deviation <= 0:
            raise InputError(f"move max_deviation must be > 0 [m], got {self.max_deviation!r}")
        if self.frame not in ("grasp", "base"):
            raise InputError(f"move frame must be 'grasp' or 'base', got {self.frame!r}")
        u = np.asarray(self.direction, dtype=float)
        if u.shape != (3,) or not np.all(np.isfinite(u)) or np.linalg.norm(u) < 1e-9:
            raise InputError(f"move direction must be a non-zero 3-vector, got {self.direction!r}")
        object.__setattr__(self, "direction", tuple((u / np.linalg.norm(u)).tolist()))
        object.__setattr__(self, "steps", int(self.steps))

    def offsets(self, poses: np.ndarray) -> np.ndarray:
        """Displacement :math:`d` (M, 3) [m] of each grasp pose (M, 4, 4), base frame."""
        u = np.asarray(self.direction)
        if self.frame == "grasp":
            return self.distance * (poses[:, :3, :3] @ u)
        return np.broadcast_to(self.distance * u, (poses.shape[0], 3)).copy()


class MovePlan(NamedTuple):
    """Kinematics of N moves (:func:`plan_moves`).

    Attributes:
        ok: (N,) bool, the joint path exists within the bounds.
        reason: (N,) str, ``''`` or one of :data:`MOVE_REASONS`.
        failed_step: (N,) int, grid step 1..steps where tracking failed, 0 if ok.
        q_path: (N, steps + 1, nq) [rad] joint path at the grid points (index 0
            is the grasp); NaN rows where not ok.
        deviation: (N,) bound of the gripper's deviation from its line [m] (NaN if not ok).
        waypoints: (N,) int, IK waypoints solved after the grasp.
        knots: (N, steps * substeps + 1, nq) [rad] the IK waypoints on the fine
            grid ``s = j / (steps * substeps)``, NaN between them: the move is the
            piecewise linear joint path through them (``q_path`` samples it).
    """

    ok: np.ndarray
    reason: np.ndarray
    failed_step: np.ndarray
    q_path: np.ndarray
    deviation: np.ndarray
    waypoints: np.ndarray
    knots: np.ndarray


class MoveResult(NamedTuple):
    """Kinematics and collisions of N moves (:func:`check_moves`).

    Attributes:
        ok: (N,) bool, the move is followable and collision-free at every grid point.
        reason: (N,) str, ``''``, one of :data:`MOVE_REASONS` or a collision reason.
        failed_step: (N,) int, first failing grid step (1..steps), 0 if ok.
        q_end: (N, nq) [rad] configuration at the end of the move (the
            pre-grasp of an approach), NaN where not ok.
        q_path: (N, steps + 1, nq) joint path at the grid points (NaN where not ok).
        deviation: (N,) deviation bound [m] (NaN where not ok).
        knots: The IK waypoints (see :class:`MovePlan`), NaN where not ok.
    """

    ok: np.ndarray
    reason: np.ndarray
    failed_step: np.ndarray
    q_end: np.ndarray
    q_path: np.ndarray
    deviation: np.ndarray
    knots: np.ndarray


def move_poses(poses: np.ndarray, offsets: np.ndarray, steps: int) -> np.ndarray:
    """Grasp-frame poses at the grid points of moves.

    Args:
        poses: Grasp poses (N, 4, 4) [m].
        offsets: Displacements (N, 3) [m] (see :meth:`Move.offsets`).
        steps: Grid steps, >= 1.

    Returns:
        (steps + 1, N, 4, 4): index 0 is the grasp, ``steps`` the end of the move.
    """
    poses = np.asarray(poses, dtype=float)
    frac = np.arange(steps + 1) / steps
    out = np.broadcast_to(poses, (steps + 1, *poses.shape)).copy()
    out[..., :3, 3] += frac[:, None, None] * offsets[None]
    return out


def gripper_radius(robot: Robot) -> float:
    """Largest distance of a point of the gripper's collision geometry from the grasp frame [m].

    The gripper is the body carrying the grasp frame and the links below it
    (rigid in the reduced model); each geometry is bounded by the corners of
    its local bounding box.
    """
    import pinocchio as pin

    from gcm_pipeline.robot.collision import gripper_links

    cached = robot.cache.get("gripper_radius")
    if cached is not None:
        return float(cached)
    links = gripper_links(robot)
    gm = robot.build_geometry("collision")
    model = robot.model
    data, gd = model.createData(), pin.GeometryData(gm)
    pin.forwardKinematics(model, data, robot.home)
    pin.updateGeometryPlacements(model, data, gm, gd)
    pin.updateFramePlacement(model, data, robot.grasp_frame_id)
    inv = data.oMf[robot.grasp_frame_id].inverse()
    radius = 0.0
    for k, go in enumerate(gm.geometryObjects):
        if model.frames[go.parentFrame].name not in links:
            continue
        go.geometry.computeLocalAABB()
        box = go.geometry.aabb_local
        lo, hi = np.asarray(box.min_, dtype=float), np.asarray(box.max_, dtype=float)
        corners = np.array(
            [[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])]
        )
        m = (inv * gd.oMg[k]).homogeneous
        pts = corners @ m[:3, :3].T + m[:3, 3]
        radius = max(radius, float(np.linalg.norm(pts, axis=1).max()))
    robot.cache["gripper_radius"] = radius
    return radius


def lever_arms(robot: Robot) -> np.ndarray:
    """Bounds (nq,) [m] of the grasp frame's distance from each joint's axis, by q index.

    The sum of the link offsets from the joint's origin to the grasp frame
    (see :meth:`~gcm_pipeline.robot.chain.KinematicChain.link_lengths`).
    """
    chain = robot.chain
    lengths = chain.link_lengths()  # joint k -> k+1 ..., last -> frame
    beyond = np.cumsum(lengths[::-1])[::-1]  # from joint k's origin to the frame
    out = np.zeros(robot.nq)
    out[chain.q_index] = beyond
    return out


def _segment_bounds(
    robot: Robot,
    lever: np.ndarray,
    q_a: np.ndarray,
    q_b: np.ndarray,
    start: np.ndarray,
    rot0: np.ndarray,
    offsets: np.ndarray,
    radius: float,
    budget: float,
) -> np.ndarray:
    """Bound of the gripper's deviation (M,) [m] over the joint segments ``q_a -> q_b``.

    Args:
        robot: The robot.
        lever: :func:`lever_arms` (nq,).
        q_a: Segment starts (M, nq) [rad].
        q_b: Segment ends (M, nq) [rad].
        start: Start of each move's line, the grasp position (M, 3) [m].
        rot0: Grasp orientation (M, 3, 3).
        offsets: Each move's displacement (M, 3) [m].
        radius: Largest distance of a gripper point from the grasp frame [m].
        budget: What the h^2 terms may use [m]; more samples if needed.
    """
    m = q_a.shape[0]
    if m == 0:
        return np.zeros(0)
    dq = np.abs(q_b - q_a)
    order = robot.chain.q_index
    d = dq[:, order]
    before = np.cumsum(d, axis=1) - d  # sum of |dq_j| over the joints before k
    k_pos = np.sum(lever[order] * d * (d + 2.0 * before), axis=1)  # |p''| bound [m]
    a_rot = dq.sum(axis=1)
    k_rot = 3.0 / np.sqrt(2.0) * a_rot**2  # ||R''||_F bound
    curvature = k_pos + radius * k_rot
    # h^2 / 8 * curvature <= budget  ->  intervals n >= sqrt(curvature / (8 budget)),
    # rounded up to a power of two so that rows share a few sample counts
    need = np.sqrt(curvature / (8.0 * budget))
    n_rows = np.clip(2 ** np.ceil(np.log2(np.maximum(need, 2.0))), 2, _MAX_SAMPLES).astype(int)
    out = np.empty(m)
    for n in np.unique(n_rows).tolist():
        sel = np.flatnonzero(n_rows == n)
        s = np.linspace(0.0, 1.0, n + 1)
        qa, qb = q_a[sel], q_b[sel]
        qs = qa[:, None, :] + s[None, :, None] * (qb - qa)[:, None, :]
        rot, pos = robot.chain.pose(qs.reshape(-1, robot.nq))
        pos = pos.reshape(sel.size, n + 1, 3)
        rot = rot.reshape(sel.size, n + 1, 9)
        # distance of each sample from its move's line segment
        d = offsets[sel]
        rel = pos - start[sel, None, :]
        t = (
            np.einsum("msj,mj->ms", rel, d)
            / np.maximum(np.einsum("ij,ij->i", d, d), 1e-300)[:, None]
        )
        t = np.clip(t, 0.0, 1.0)
        dist = np.linalg.norm(rel - t[:, :, None] * d[:, None, :], axis=2).max(axis=1)
        rdist = np.linalg.norm(rot - rot0[sel].reshape(-1, 1, 9), axis=2).max(axis=1)
        h2 = 1.0 / n**2
        out[sel] = dist + k_pos[sel] * h2 / 8.0 + radius * (rdist + k_rot[sel] * h2 / 8.0)
    return out


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
    **ik_options: Any,
) -> MovePlan:
    """Joint paths of N moves from their grasps, batched over the moves (see module doc).

    Args:
        robot: The robot.
        poses: Grasp poses (N, 4, 4) in the base frame [m].
        q_start: Configurations reaching them (N, nq) [rad]; NaN rows fail (``invalid``).
        move: The move.
        gripper_radius: Largest distance of a gripper point from the grasp frame [m].
        position_tolerance: IK tolerance of the waypoints [m].
        orientation_tolerance: IK tolerance of the waypoints [rad].
        backend: IK backend.
        **ik_options: Further backend options (waypoints use only the previous
            waypoint as seed unless given otherwise).

    Returns:
        The :class:`MovePlan`.

    Raises:
        InputError: Arrays of the wrong shape.
    """
    tg = np.asarray(poses, dtype=float)
    if tg.ndim == 2:
        tg = tg[None]
    qg = np.asarray(q_start, dtype=float)
    if qg.ndim == 1:
        qg = qg[None]
    n, nq, steps = tg.shape[0], robot.nq, move.steps
    if tg.shape != (n, 4, 4) or qg.shape != (n, nq):
        raise InputError(
            f"poses must be (N, 4, 4) and q_start (N, {nq}) with the same N, "
            f"got {tg.shape} and {qg.shape}"
        )
    ok = np.all(np.isfinite(qg), axis=1) & np.all(np.isfinite(tg), axis=(1, 2))
    reason = np.where(ok, "", "invalid").astype(object)
    failed = np.zeros(n, dtype=int)
    q_path = np.full((n, steps + 1, nq), np.nan)
    q_path[:, 0] = qg
    deviation = np.where(ok, 0.0, np.nan)
    waypoints = np.zeros(n, dtype=int)
    knots = np.full((n, steps * SUBSTEPS + 1, nq), np.nan)
    knots[:, 0] = qg
    if move.distance == 0 or not np.any(ok):
        q_path[ok] = qg[ok, None, :]
        q_path[~ok] = np.nan
        knots[:, 1:] = np.where(ok[:, None, None], qg[:, None, :], np.nan)
        knots[~ok] = np.nan
        return MovePlan(ok, reason.astype(str), failed, q_path, deviation, waypoints, knots)

    if backend == "pinocchio":
        ik_options = {
            "library_seeds": 0,
            "random_restarts": 0,
            "home_seed": False,
            "diagnose_limits": False,
            **ik_options,
        }
    elif backend == "mink":
        ik_options = {"library_seeds": 0, "random_restarts": 0, "home_seed": False, **ik_options}
    offsets = move.offsets(tg)
    lever = lever_arms(robot)
    budget = _SLACK_SHARE * move.max_deviation
    sub = SUBSTEPS
    fine_steps = steps * sub  # waypoints sit on a grid finer than the steps
    at = np.zeros(n, dtype=int)  # last accepted waypoint, in fine units
    step = np.full(n, fine_steps // 3)
    q_at = qg.copy()
    active = ok.copy()
    while np.any(active):
        rows = np.flatnonzero(active)
        a = at[rows]
        b = np.minimum(a + step[rows], fine_steps)
        target = tg[rows].copy()
        target[:, :3, 3] += (b / fine_steps)[:, None] * offsets[rows]
        q_a = q_at[rows]
        res = solve_ik(
            robot,
            target,
            backend,
            position_tolerance=position_tolerance,
            orientation_tolerance=orientation_tolerance,
            seeds=q_a[:, None, :],
            **ik_options,
        )
        why = np.where(res.success, "", "no_ik").astype(object)
        conv = np.flatnonzero(res.success)
        q_b = res.q
        span = (b - a).astype(float)  # fine units
        guess = ((b - a) // 2).astype(int)  # after an IK or joint-step failure: halve
        # the change per step: segments of a step or more change every step alike;
        # shorter ones may not change more than one step's worth (the grid
        # points are checked once the path is complete)
        jump = np.max(np.abs(q_b[conv] - q_a[conv]), axis=1) * sub / np.maximum(span[conv], sub)
        why[conv[jump > move.max_joint_step]] = "joint_step"
        fine = conv[jump <= move.max_joint_step]
        if fine.size:
            dev = _segment_bounds(
                robot,
                lever,
                q_a[fine],
                q_b[fine],
                tg[rows[fine], :3, 3],
                tg[rows[fine], :3, :3],
                offsets[rows[fine]],
                gripper_radius,
                budget,
            )
            too_far = dev > move.max_deviation
            why[fine[too_far]] = "deviation"
            # the deviation grows with the square of the segment's length: the
            # next try (shorter after a failure, longer after a success) aims at
            # _AIM of the tolerance
            scale = np.sqrt(_AIM * move.max_deviation / np.maximum(dev, 1e-12))
            guess[fine] = np.floor(span[fine] * np.minimum(scale, 4.0)).astype(int)
            good = fine[~too_far]
            g_rows = rows[good]
            deviation[g_rows] = np.maximum(deviation[g_rows], dev[~too_far])
            waypoints[g_rows] += 1
            ga, gb = a[good], b[good]
            for k in range(1, steps + 1):
                sel = (ga < k * sub) & (k * sub <= gb)
                if np.any(sel):
                    f = ((k * sub - ga[sel]) / (gb[sel] - ga[sel]))[:, None]
                    q_path[g_rows[sel], k] = q_a[good[sel]] + f * (q_b[good[sel]] - q_a[good[sel]])
            at[g_rows] = gb
            q_at[g_rows] = q_b[good]
            knots[g_rows, gb] = q_b[good]
            step[g_rows] = np.clip(guess[good], 1, fine_steps)
            active[g_rows[gb == fine_steps]] = False
        bad = np.flatnonzero(why != "")
        if bad.size:
            # an IK failure or a jump within one step fails the move (as a step-by-step
            # tracking would); a deviation may still be cured by waypoints within a step
            limit = np.where(why[bad] == "deviation", 1, sub)
            short = (b[bad] - a[bad]) <= limit
            dead = rows[bad[short]]
            ok[dead] = False
            active[dead] = False
            reason[dead] = why[bad[short]]
            failed[dead] = a[bad[short]] // sub + 1
            retry = bad[~short]
            lower = np.where(why[retry] == "deviation", 1, np.minimum(sub, b[retry] - a[retry] - 1))
            step[rows[retry]] = np.clip(guess[retry], lower, b[retry] - a[retry] - 1)
    # the change of every joint between consecutive grid points
    steps_ok = np.all(np.abs(np.diff(q_path[ok], axis=1)) <= move.max_joint_step, axis=(1, 2))
    over = np.flatnonzero(ok)[~steps_ok]
    if over.size:
        big = np.abs(np.diff(q_path[over], axis=1)).max(axis=2) > move.max_joint_step
        ok[over] = False
        reason[over] = "joint_step"
        failed[over] = np.argmax(big, axis=1) + 1
    q_path[~ok] = np.nan
    knots[~ok] = np.nan
    deviation[~ok] = np.nan
    return MovePlan(ok, reason.astype(str), failed, q_path, deviation, waypoints, knots)


def check_moves(
    robot: Robot,
    poses: Any,
    q_start: Any,
    move: Move,
    collisions: Callable[[np.ndarray, np.ndarray], Any] | None,
    *,
    gripper_radius: float,
    position_tolerance: float = 1e-4,
    orientation_tolerance: float = 1e-3,
    backend: str = "pinocchio",
    **ik_options: Any,
) -> MoveResult:
    """Plan N moves (:func:`plan_moves`) and check their grid points for collisions.

    Args:
        robot: The robot.
        poses: Grasp poses (N, 4, 4) in the base frame [m].
        q_start: Configurations reaching them (N, nq) [rad].
        move: The move.
        collisions: ``collisions(q, move) -> reasons``: the collision reason
            (``''`` = free) of configurations ``q`` (K, nq) on the moves with
            indices ``move`` (K,), for the grid points ``k >= 1``; e.g.
            ``lambda q, i: checker.check(q, mode="approach")``. None: no
            collision checks.
        gripper_radius: Largest distance of a gripper point from the grasp frame [m].
        position_tolerance: IK tolerance [m].
        orientation_tolerance: IK tolerance [rad].
        backend: IK backend.
        **ik_options: Further backend options.

    Returns:
        The :class:`MoveResult`.
    """
    plan = plan_moves(
        robot,
        poses,
        q_start,
        move,
        gripper_radius=gripper_radius,
        position_tolerance=position_tolerance,
        orientation_tolerance=orientation_tolerance,
        backend=backend,
        **ik_options,
    )
    ok = plan.ok.copy()
    reason = plan.reason.astype(object)
    failed = plan.failed_step.copy()
    q_path = plan.q_path
    rows = np.flatnonzero(ok)
    if collisions is not None and rows.size and move.distance > 0:
        steps = move.steps
        samples = q_path[rows, 1:].reshape(-1, robot.nq)
        which = np.repeat(rows, steps)
        why = np.asarray(collisions(samples, which), dtype=object).reshape(rows.size, steps)
        hit = why != ""
        bad = np.flatnonzero(hit.any(axis=1))
        first = np.argmax(hit[bad], axis=1)
        ok[rows[bad]] = False
        reason[rows[bad]] = why[bad, first]
        failed[rows[bad]] = first + 1
    q_path = np.where(ok[:, None, None], q_path, np.nan)
    knots = np.where(ok[:, None, None], plan.knots, np.nan)
    dev = np.where(ok, plan.deviation, np.nan)
    return MoveResult(ok, reason.astype(str), failed, q_path[:, -1].copy(), q_path, dev, knots)
