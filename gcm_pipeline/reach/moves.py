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
computed from the grasp outwards.

The joint path is piecewise linear through waypoints (knots) on a grid
:math:`SUBSTEPS` times finer than the steps :math:`s_k = k / \mathrm{steps}`
(:func:`plan_moves`), all moves of a batch at once:

0. **Ends beyond reach**: a move whose end no configuration reaches within
   the IK tolerances fails (``no_ik``) without any IK; this is proved from
   the Panda's elbow range (:func:`unreachable_ends`), not searched for.
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
   steps to a small share of the deviation budget (``_KNOT_TOLERANCE``): their
   error is part of what the bound measures, so they need not meet the IK
   tolerance. A waypoint that does not converge, a jump within one grid step
   or a deviation within one fine step fails the move.

The bound is computed on the actual joint path, so the path is sound whatever
its waypoints are: every gripper point stays within ``max_deviation`` of its
line. A move whose first path collides at a grid point gets a second path with
a waypoint at every grid point (:func:`check_moves`), so that a collision found
does not depend on where the first path's waypoints fell.

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
from gcm_pipeline.robot import kernels
from gcm_pipeline.robot.ik import solve_ik, verify_solutions
from gcm_pipeline.robot.ik_pinocchio import (
    PinocchioIKOptions,
    _analytic_blocks,
    _lm,
    _pose_errors,
    analytic_solver,
)
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
    "unreachable_ends",
]

#: Why a move fails (``MoveResult.reason``), besides the checker's collision reasons.
MOVE_REASONS = ("invalid", "no_ik", "joint_step", "deviation")

#: Samples per unit of the segment parameter are chosen so that the h^2 terms
#: of the deviation bound use at most this share of ``max_deviation``.
_SLACK_SHARE = 0.25
#: At most this many samples per segment (a segment needing more is split).
_MAX_SAMPLES = 64
#: Share of ``max_deviation`` a split segment's parts aim at.
_AIM = 0.6
#: Waypoints may sit this many times closer than the steps where the path bends.
SUBSTEPS = 8
#: Interior waypoints converge to this share of ``max_deviation`` (position) and
#: of ``max_deviation / gripper_radius`` (orientation): their error is part of
#: the deviation the bound measures, not an IK tolerance.
_KNOT_TOLERANCE = 0.05
#: LM options of the interior waypoints (they start close: early stall exits).
_KNOT_OPTIONS = PinocchioIKOptions()
#: Where one IK cannot reach the end of a move from the grasp, the line is
#: followed in pieces of about this length [m] (continuation).
_REACH = 0.025

#: Joint-7 offsets [rad] around the start's where the closed form looks for the end of a
#: move, and the largest joint change [rad] of an end it keeps (else LM from the start).
_END_Q7 = np.array([0.0, -0.01, 0.01, -0.025, 0.025, -0.05, 0.05, -0.1, 0.1, -0.2, 0.2])
_NEAR_END = 0.3


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
        if u.shape != (3,) or not np.all(np.isfinite(u)) or not np.any(u):
            raise InputError(f"move direction must be a non-zero 3-vector, got {self.direction!r}")
        u = u / np.abs(u).max()  # first: the norm of [1e300, 1e300, 1e300] overflows
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
    reject_above: float = np.inf,
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
        reject_above: Segments whose deviation at the midpoint already exceeds
            this [m] get that value (a lower bound of their bound) without
            further samples.
    """
    m = q_a.shape[0]
    if m == 0:
        return np.zeros(0)
    out = np.empty(m)
    todo = np.arange(m)
    compiled = kernels.get()
    if np.isfinite(reject_above):
        if compiled is not None:
            dist, turn = _samples(
                compiled, robot, q_a, q_b, np.zeros(m, dtype=np.intp), start, rot0, offsets
            )
            mid = dist + radius * turn
        else:
            mid = _sample_deviation(robot, 0.5 * (q_a + q_b), start, rot0, offsets, radius)
        far = mid > reject_above
        out[far] = mid[far]
        todo = np.flatnonzero(~far)
        if todo.size == 0:
            return out
        q_a, q_b, start, rot0, offsets = (
            q_a[todo],
            q_b[todo],
            start[todo],
            rot0[todo],
            offsets[todo],
        )
        m = todo.size
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
    n_rows = np.clip(2 ** np.ceil(np.log2(np.maximum(need, 2.0))), 2, _MAX_SAMPLES).astype(np.intp)
    if compiled is not None:
        dist, turn = _samples(compiled, robot, q_a, q_b, n_rows, start, rot0, offsets)
        h2 = 1.0 / n_rows**2
        out[todo] = dist + k_pos * h2 / 8.0 + radius * (turn + k_rot * h2 / 8.0)
        return out
    res = np.empty(m)
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
        res[sel] = dist + k_pos[sel] * h2 / 8.0 + radius * (rdist + k_rot[sel] * h2 / 8.0)
    out[todo] = res
    return out


def _samples(compiled: Any, robot: Robot, *arrays: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The compiled kernel's deviation samples (its arguments as C arrays)."""
    out: tuple[np.ndarray, np.ndarray] = compiled.segment_samples(
        *(np.ascontiguousarray(a) for a in arrays), *robot.chain.packed
    )
    return out


def _sample_deviation(
    robot: Robot,
    q: np.ndarray,
    start: np.ndarray,
    rot0: np.ndarray,
    offsets: np.ndarray,
    radius: float,
) -> np.ndarray:
    """Sampled deviation (M,) [m] at configurations ``q`` (M, nq) [rad].

    The distance of the grasp frame from its move's line segment plus
    ``radius`` times the orientation change ``||R - R_g||_F``.
    """
    rot, pos = robot.chain.pose(q)
    rel = pos - start
    t = np.einsum("ij,ij->i", rel, offsets) / np.maximum(
        np.einsum("ij,ij->i", offsets, offsets), 1e-300
    )
    t = np.clip(t, 0.0, 1.0)
    dist = np.linalg.norm(rel - t[:, None] * offsets, axis=1)
    rdist = np.linalg.norm((rot - rot0).reshape(-1, 9), axis=1)
    return dist + radius * rdist


def unreachable_ends(
    robot: Robot,
    poses: np.ndarray,
    move: Move,
    position_tolerance: float,
    orientation_tolerance: float,
) -> np.ndarray:
    """Moves whose end no configuration reaches within the IK tolerances, (N,) bool.

    A proof, not a search (:meth:`~gcm_pipeline.robot.analytic.PandaAnalyticIK.unreachable`:
    the end lies beyond what the elbow's limits let the arm reach, whatever
    joint 7 is); such a move fails whatever configuration it starts from. All
    False for a robot without the Panda's kinematics.

    Args:
        robot: The robot.
        poses: Grasp poses (N, 4, 4) in the base frame [m].
        move: The move.
        position_tolerance: IK tolerance of the end of the move [m].
        orientation_tolerance: IK tolerance [rad].
    """
    tg = np.asarray(poses, dtype=float).reshape(-1, 4, 4)
    solver = analytic_solver(robot)
    if solver is None or move.distance == 0 or tg.shape[0] == 0:
        return np.zeros(tg.shape[0], dtype=bool)
    with np.errstate(invalid="ignore"):
        out = solver.unreachable(
            tg[:, :3, :3],
            tg[:, :3, 3] + move.offsets(tg),
            position_tolerance,
            orientation_tolerance,
            (robot.lower[3], robot.upper[3]),
        )
    return out & np.all(np.isfinite(tg), axis=(1, 2))


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
        knot_check: With ``grid_knots``: ``knot_check(q, move) -> reasons``
            (as ``collisions`` of :func:`check_moves`) is called on the grid
            waypoints found, in at most two batches (see ``check_first``); a
            move fails at its first waypoint that gets a reason, with that
            reason (the grid waypoints are the path's grid points). Ignored
            without ``grid_knots``.
        check_first: With ``knot_check``: per move (N,) the grid step up to
            which its waypoints are found and checked before the rest of its
            line is followed (e.g. where its first path collided: most moves
            fail there, and their later waypoints are never computed). The
            result does not depend on it. None: the whole line, then the checks.
        **ik_options: Further backend options of the end's IK (seeded only
            with the grasp's configuration unless given otherwise).

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
    if check_first is not None:
        check_first = np.asarray(check_first)
        if check_first.shape != (n,) or not np.issubdtype(check_first.dtype, np.integer):
            raise InputError(f"check_first must be (N,) = ({n},) ints, got {check_first.shape}")
    ok = np.all(np.isfinite(qg), axis=1) & np.all(np.isfinite(tg), axis=(1, 2))
    reason = np.where(ok, "", "invalid").astype(object)
    failed = np.zeros(n, dtype=int)
    q_path = np.full((n, steps + 1, nq), np.nan)
    deviation = np.where(ok, 0.0, np.nan)
    waypoints = np.zeros(n, dtype=int)
    sub = SUBSTEPS
    fine_steps = steps * sub
    knots = np.full((n, fine_steps + 1, nq), np.nan)
    knots[:, 0] = qg
    if move.distance == 0 or not np.any(ok):
        q_path[ok] = qg[ok, None, :]
        knots[:, 1:] = np.where(ok[:, None, None], qg[:, None, :], np.nan)
        knots[~ok] = np.nan
        return MovePlan(ok, reason.astype(str), failed, q_path, deviation, waypoints, knots)

    if backend == "pinocchio":
        ik_options = {
            "library_seeds": 0,
            "random_restarts": 0,
            "home_seed": False,
            "diagnose_limits": False,
            "analytic_samples": 0,  # closed form at and around the last waypoint's joint 7
            **ik_options,
        }
    elif backend == "mink":
        ik_options = {"library_seeds": 0, "random_restarts": 0, "home_seed": False, **ik_options}
    offsets = move.offsets(tg)
    tol = move.max_deviation

    def fail(rows: np.ndarray, at: np.ndarray, why: Any) -> None:
        """Rows fail at fine positions ``at`` (the first per row counts)."""
        if rows.size == 0:
            return
        first = np.full(n, fine_steps)
        np.minimum.at(first, rows, at)
        bad = np.unique(rows)
        ok[bad] = False
        reason[bad] = why if isinstance(why, str) else why[bad]
        failed[bad] = np.minimum(first[bad] // sub + 1, steps)

    def advance(rows: np.ndarray, lo: np.ndarray, hi: np.ndarray, pieces: int) -> np.ndarray:
        """Waypoints ``lo + 1 .. hi`` (per row) of the line cut in ``pieces``.

        Each starts from the previous one (waypoint 0 is the grasp); a waypoint
        that does not converge stops its row. Returns (M,) bool: the rows that
        got them all.
        """
        alive = np.ones(rows.size, dtype=bool)
        for i in range(1, pieces + 1):
            sel = np.flatnonzero(alive & (lo < i) & (i <= hi))
            if sel.size == 0:
                continue
            r = rows[sel]
            at, prev = (i * fine_steps) // pieces, ((i - 1) * fine_steps) // pieces
            target = tg[r].copy()
            target[:, :3, 3] += (at / fine_steps) * offsets[r]
            seed = knots[r, prev]
            if at < fine_steps:
                q_new, conv = _waypoints(robot, seed, target, tol, gripper_radius)
            else:
                res = solve_ik(
                    robot,
                    target,
                    backend,
                    position_tolerance=position_tolerance,
                    orientation_tolerance=orientation_tolerance,
                    seeds=seed[:, None, :],
                    **ik_options,
                )
                q_new, conv = res.q, res.success
            knots[r[conv], at] = q_new[conv]
            failed_at[r[~conv]] = prev
            alive[sel[~conv]] = False
        return alive

    def check_grid(rows: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> None:
        """``knot_check`` on the grid waypoints ``lo + 1 .. hi`` found (per row), one batch.

        A row fails at its first waypoint the check rejects.
        """
        k = np.arange(1, steps + 1)
        grid = knots[rows[:, None], k * sub]  # (m, steps, nq), NaN where not found
        found = np.isfinite(grid[:, :, 0]) & (k > lo[:, None]) & (k <= hi[:, None])
        owner = np.broadcast_to(rows[:, None], found.shape)
        why = np.full(found.shape, "", dtype=object)
        if found.any():
            assert knot_check is not None
            why[found] = np.asarray(knot_check(grid[found], owner[found]), dtype=object)
        hit = why != ""
        bad = np.flatnonzero(hit.any(axis=1))
        first = hit[bad].argmax(axis=1)
        row_why = np.full(n, "", dtype=object)
        row_why[rows[bad]] = why[bad, first]
        fail(rows[bad], (first + 1) * sub - 1, row_why)  # fails at grid step first + 1

    def follow(rows: np.ndarray, pieces: int) -> np.ndarray:
        """The rows that reach the end following the line from the grasp in pieces.

        Each waypoint starts from the previous one; a failure fails the row. With
        ``knot_check`` (``pieces == steps``: the waypoints are the grid points) the
        waypoints are checked in batches: each row's up to its ``check_first``
        step, then, for the rows still free, the rest of the line. A row fails at
        its first waypoint the check rejects, as if each had been checked when
        found (later ones only start from it).
        """
        start, zero = rows, np.zeros(rows.size, dtype=int)
        end = np.full(rows.size, pieces)
        if knot_check is None or not grid_knots or rows.size == 0:
            rows = rows[advance(rows, zero, end, pieces)]
        else:
            pause = end if check_first is None else np.clip(check_first[rows], 1, pieces)
            got = advance(rows, zero, pause, pieces)
            check_grid(rows, zero, pause)
            got &= ok[rows]
            more = got & (pause < pieces)
            got[more] = advance(rows[more], pause[more], end[more], pieces)
            check_grid(rows[more], pause[more], end[more])
            rows = rows[got & ok[rows]]
        knots[np.setdiff1d(start, rows), 1:] = np.nan
        return rows

    # 0. ends proved beyond reach fail at once, whatever the IK would try
    beyond = np.flatnonzero(
        ok & unreachable_ends(robot, tg, move, position_tolerance, orientation_tolerance)
    )
    fail(beyond, np.full(beyond.size, fine_steps), "no_ik")

    # 1. the end of the move: one IK seeded from the grasp's configuration; where it
    # fails, the line is followed from the grasp in pieces of about _REACH
    # (continuation: each waypoint started from the previous ones and converged to
    # the waypoint tolerance, the last to the IK tolerances)
    failed_at = np.zeros(n, dtype=int)
    pieces = int(np.clip(np.ceil(move.distance / _REACH), 1, steps))
    rows = np.flatnonzero(ok)
    if grid_knots:
        reached = follow(rows, steps)
    else:
        ends = tg[rows].copy()
        ends[:, :3, 3] += offsets[rows]
        q_end, done = _end_of_move(
            robot, ends, qg[rows], backend, position_tolerance, orientation_tolerance, ik_options
        )
        knots[rows[done], fine_steps] = q_end[done]
        reached = rows[done]
        retry = rows[~done]
        reached = np.union1d(reached, follow(retry, pieces))
    lost = np.setdiff1d(rows, reached)
    lost = lost[ok[lost]]  # not those a knot check failed
    fail(lost, failed_at[lost], "no_ik")

    # 2. segments between known waypoints: accepted under the deviation bound, else
    # split; a new waypoint starts from the segment's joint interpolation
    r_idx, pos = np.nonzero(np.isfinite(knots[:, :, 0]) & ok[:, None])
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
                fine_steps,
                tol,
                gripper_radius,
                fail,
            )
            keep = ok[s_row]
            s_row, s_a, s_b = s_row[keep], s_a[keep], s_b[keep]
        if s_row.size == 0:
            break
        qa, qb = knots[s_row, s_a], knots[s_row, s_b]
        span = s_b - s_a
        # the change per grid step: segments of a step or more change every step
        # alike; shorter ones may not change more than one step's worth
        jump = np.max(np.abs(qb - qa), axis=1) * sub / np.maximum(span, sub)
        over = jump > move.max_joint_step
        dev = np.full(s_row.size, np.inf)
        fine = np.flatnonzero(~over)
        dev[fine] = _segment_bounds(
            robot,
            lever_arms(robot),
            qa[fine],
            qb[fine],
            tg[s_row[fine], :3, 3],
            tg[s_row[fine], :3, :3],
            offsets[s_row[fine]],
            gripper_radius,
            _SLACK_SHARE * tol,
            reject_above=tol,
        )
        good = ~over & (dev <= tol)
        np.maximum.at(deviation, s_row[good], dev[good])
        np.add.at(waypoints, s_row[good], 1)
        # a jump within one grid step, a deviation within one fine step: the move fails
        dead = (over & (span <= sub)) | (~over & ~good & (span <= 1))
        why = np.full(n, "deviation", dtype=object)
        why[s_row[dead & over]] = "joint_step"
        fail(s_row[dead], s_a[dead], why)
        again = ~good & ~dead & ok[s_row]
        # the deviation falls with the square of a segment's length
        need = np.where(
            over, np.ceil(jump / move.max_joint_step), np.ceil(np.sqrt(dev / (_AIM * tol)))
        )
        parts = np.clip(np.nan_to_num(need, nan=2.0, posinf=2.0), 2, np.maximum(span, 2))
        s_row, s_a, s_b, parts = s_row[again], s_a[again], s_b[again], parts[again].astype(int)

    # the grid points on the piecewise linear path through the knots
    rows = np.flatnonzero(ok)
    if rows.size:
        kn = knots[rows]
        have = np.isfinite(kn[:, :, 0])
        idx = np.arange(fine_steps + 1)
        prev = np.maximum.accumulate(np.where(have, idx, 0), axis=1)
        nxt = np.minimum.accumulate(np.where(have, idx, fine_steps)[:, ::-1], axis=1)[:, ::-1]
        grid = np.arange(steps + 1) * sub
        pa, pb = prev[:, grid], nxt[:, grid]
        ka = np.take_along_axis(kn, pa[:, :, None], axis=1)
        kb = np.take_along_axis(kn, pb[:, :, None], axis=1)
        f = ((grid - pa) / np.maximum(pb - pa, 1))[:, :, None]
        q_path[rows] = ka + f * (kb - ka)
        # the change of every joint between consecutive grid points
        big = np.abs(np.diff(q_path[rows], axis=1)).max(axis=2) > move.max_joint_step
        over = np.flatnonzero(big.any(axis=1))
        if over.size:
            fail(rows[over], np.argmax(big[over], axis=1) * sub, "joint_step")
    q_path[~ok] = np.nan
    knots[~ok] = np.nan
    deviation[~ok] = np.nan
    waypoints[~ok] = 0
    return MovePlan(ok, reason.astype(str), failed, q_path, deviation, waypoints, knots)


def _end_of_move(
    robot: Robot,
    ends: np.ndarray,
    q_start: np.ndarray,
    backend: str,
    position_tolerance: float,
    orientation_tolerance: float,
    ik_options: dict[str, Any],
) -> tuple[np.ndarray, np.ndarray]:
    """IK of the end poses (M, 4, 4) seeded only from ``q_start`` (M, nq).

    With the Panda's closed form (pinocchio backend) the end is first solved at
    joint-7 values around the start's (offsets up to 0.2 rad), keeping the
    solution whose largest joint change from the start is smallest, if that is
    at most ``_NEAR_END`` [rad]. The other rows (no such solution: a window of
    joint 7 between the samples, or a far end) get LM from the start, as
    without the closed form.

    Returns:
        ``(q, reached)``: configurations (M, nq) and whether each reaches its
        pose within the IK tolerances (verified by Pinocchio FK, strictly
        inside the limits).
    """
    m = len(ends)
    if backend != "pinocchio":
        res = solve_ik(
            robot,
            ends,
            backend,
            position_tolerance=position_tolerance,
            orientation_tolerance=orientation_tolerance,
            seeds=q_start[:, None, :],
            **ik_options,
        )
        return res.q, res.success
    opts = PinocchioIKOptions.from_kwargs(ik_options)
    q = np.full((m, robot.nq), np.nan)
    conv = np.zeros(m, dtype=bool)
    solver = analytic_solver(robot) if opts.analytic else None
    if solver is not None and m:
        eps = opts.limit_epsilon
        lower, upper = robot.lower + eps, robot.upper - eps
        start = np.clip(q_start, lower, upper)
        q7 = np.clip(start[:, 6:7] + _END_Q7, lower[6], upper[6])
        # only ends within _NEAR_END of the start in every joint can be kept
        at, cand, _, _ = _analytic_blocks(
            solver, ends[:, :3, :3], ends[:, :3, 3], q7, lower, upper, (start, _NEAR_END)
        )
        change = np.max(np.abs(cand - start[at]), axis=1)
        order = np.lexsort((change, at))
        at, cand, change = at[order], cand[order], change[order]
        first = np.flatnonzero(np.r_[True, at[1:] != at[:-1]]) if at.size else at
        near = first[change[first] <= _NEAR_END]
        # exact away from singularities: a pick off its pose leaves the row to the LM
        tol_p = position_tolerance * opts.inner_tolerance
        tol_r = orientation_tolerance * opts.inner_tolerance
        pe, re = _pose_errors(
            robot.chain, cand[near], ends[at[near], :3, :3], ends[at[near], :3, 3]
        )
        near = near[(pe <= tol_p) & (re <= tol_r)]
        q[at[near]], conv[at[near]] = cand[near], True
    rest = np.flatnonzero(~conv)
    if rest.size:
        q[rest], conv[rest] = _lm_inside(
            robot,
            q_start[rest],
            ends[rest],
            position_tolerance * opts.inner_tolerance,
            orientation_tolerance * opts.inner_tolerance,
            opts,
        )
    reached = np.zeros(m, dtype=bool)
    rows = np.flatnonzero(conv)
    pe, re, inside = verify_solutions(robot, q[rows], ends[rows])
    reached[rows] = (pe <= position_tolerance) & (re <= orientation_tolerance) & inside
    return q, reached


def _waypoints(
    robot: Robot, seed: np.ndarray, target: np.ndarray, tol: float, radius: float
) -> tuple[np.ndarray, np.ndarray]:
    """Waypoints on the line: configurations (M, nq) near ``target`` poses (M, 4, 4).

    Batched Levenberg-Marquardt from ``seed`` (M, nq), inside the joint limits,
    to ``_KNOT_TOLERANCE`` of the deviation budget ``tol`` [m] (the orientation
    scaled by the gripper ``radius`` [m]). Returns ``(q, converged)``.
    """
    return _lm_inside(
        robot,
        seed,
        target,
        _KNOT_TOLERANCE * tol,
        _KNOT_TOLERANCE * tol / max(radius, 1e-3),
        _KNOT_OPTIONS,
    )


def _lm_inside(
    robot: Robot,
    seed: np.ndarray,
    target: np.ndarray,
    tol_p: float,
    tol_r: float,
    opts: PinocchioIKOptions,
) -> tuple[np.ndarray, np.ndarray]:
    """Batched LM from ``seed`` (M, nq) to ``target`` poses (M, 4, 4).

    Kept ``opts.limit_epsilon`` inside the joint limits; returns ``(q, converged)``.
    """
    eps = opts.limit_epsilon
    lower, upper = robot.lower + eps, robot.upper - eps
    q, conv, _, _ = _lm(
        robot.chain,
        np.clip(seed, lower, upper),
        target[:, :3, :3],
        target[:, :3, 3],
        lower,
        upper,
        tol_p,
        tol_r,
        opts,
    )
    return q, conv


def _split_segments(
    robot: Robot,
    poses: np.ndarray,
    offsets: np.ndarray,
    knots: np.ndarray,
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
    converges to its pose on the line within ``_KNOT_TOLERANCE`` of the
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
    target = poses[row].copy()
    target[:, :3, 3] += (at / fine_steps)[:, None] * offsets[row]
    q_new, conv = _waypoints(robot, seed, target, tol, radius)
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

    A move whose path collides is planned once more with a waypoint at every
    grid point (``grid_knots``) and accepted if that path is free.

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
    opts = dict(
        gripper_radius=gripper_radius,
        position_tolerance=position_tolerance,
        orientation_tolerance=orientation_tolerance,
        backend=backend,
        **ik_options,
    )
    tg = np.asarray(poses, dtype=float)
    if tg.ndim == 2:
        tg = tg[None]
    q0 = np.asarray(q_start, dtype=float)
    if q0.ndim == 1:
        q0 = q0[None]
    plan = plan_moves(robot, tg, q0, move, **opts)
    # the plan's own arrays, changed in place (knots: (N, 8 steps + 1, nq) floats)
    ok, failed, q_path, knots, dev = (
        plan.ok,
        plan.failed_step,
        plan.q_path,
        plan.knots,
        plan.deviation,
    )
    reason = plan.reason.astype(object)
    if collisions is not None and move.distance > 0:
        rows = np.flatnonzero(ok)
        hit_rows, why, first = _grid_collisions(collisions, q_path, rows, robot.nq)
        ok[hit_rows] = False
        reason[hit_rows] = why
        failed[hit_rows] = first
        if hit_rows.size:
            # a path that collides gets a second plan with a waypoint at every grid
            # point (on the line within the waypoint tolerance): a collision then
            # does not depend on where the first plan's waypoints fell
            again = plan_moves(
                robot,
                tg[hit_rows],
                q0[hit_rows],
                move,
                grid_knots=True,
                # a waypoint that collides fails its move at once (it is a grid point)
                knot_check=lambda q, i: collisions(q, hit_rows[i]),
                check_first=first,  # where the first path collided
                **opts,
            )
            # its grid points are its waypoints, each checked as it was found
            good = np.flatnonzero(again.ok)
            r = hit_rows[good]
            ok[r], reason[r], failed[r] = True, "", 0
            q_path[r], knots[r] = again.q_path[good], again.knots[good]
            dev[r] = again.deviation[good]
    q_path[~ok] = np.nan
    knots[~ok] = np.nan
    dev[~ok] = np.nan
    return MoveResult(ok, reason.astype(str), failed, q_path[:, -1].copy(), q_path, dev, knots)


def _grid_collisions(
    collisions: Callable[[np.ndarray, np.ndarray], Any],
    q_path: np.ndarray,
    rows: np.ndarray,
    nq: int,
    ids: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Rows of ``rows`` whose grid points ``k >= 1`` collide, their first reason and step."""
    if rows.size == 0:
        return rows, np.zeros(0, dtype=object), np.zeros(0, dtype=int)
    steps = q_path.shape[1] - 1
    samples = q_path[rows, 1:].reshape(-1, nq)
    which = np.repeat(rows if ids is None else ids[rows], steps)
    why = np.asarray(collisions(samples, which)).reshape(rows.size, steps)
    hit = why != ""
    bad = np.flatnonzero(hit.any(axis=1))
    first = np.argmax(hit[bad], axis=1)
    return rows[bad], why[bad, first], first + 1
