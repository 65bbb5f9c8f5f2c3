r"""Closed-form IK of the Franka Panda's arm, batched, with joint 7 as the free parameter.

The Panda's joints 1-3 meet at the shoulder :math:`O_2` (a spherical shoulder),
joint 4 is the elbow, and the axes of joints 5 and 6 meet at :math:`O_6`. Fix
joint 7 at :math:`q_7` and the pose of frame 6 follows from the target; then

1. the distance :math:`|O_6 - O_2|` depends on :math:`q_4` alone (law of
   cosines in the arm plane): two elbow solutions;
2. the arm plane (spanned by :math:`O_2`, :math:`O_4`, :math:`O_6`, with normal
   :math:`z_4`) turns about the line :math:`O_2 O_6` by a swivel angle; the axis
   of joint 5 lies in that plane and must be perpendicular to the axis of
   joint 6: :math:`A \sin\varphi + B \cos\varphi = C`, two swivel solutions;
3. the shoulder rotation :math:`R_{03} = R_z(q_1) R_y(q_2) R_z(q_3)` gives two
   Euler solutions, and :math:`R_{46} = R_y(q_5) R_z(q_6)` gives :math:`q_5, q_6`.

That is up to 8 configurations per :math:`q_7`, all of them exact (no
iteration). The frames are Craig's modified Denavit-Hartenberg frames of the
Panda (Franka's published table), which the example-robot-data URDF uses. A
robot gets this solver only if its kinematic chain equals these frames plus a
fixed tool transform, checked at load against the chain's forward kinematics
(:meth:`PandaAnalyticIK.for_chain`); any other arm keeps the iterative solver.

Configurations are returned unverified and unfiltered (NaN where a step has no
real solution); callers keep those inside the joint limits and verify them by
forward kinematics, as every IK answer of the project is verified.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from gcm_pipeline.robot import kernels
from gcm_pipeline.robot.ik.per_robot import per_robot

__all__ = ["PandaAnalyticIK", "analytic_blocks", "analytic_solver"]

#: (target, joint-7) rows of one closed-form call: about 340 bytes each. Blocks of
#: 16,384 rows ran 1.5x faster than of 262,144 (20,000 targets x 8 values: 159 against
#: 248 ms): their temporaries stay in the cache and cost no page faults.
_ANALYTIC_ROWS = 1 << 14

# Craig's modified DH parameters of the Panda arm (Franka's table) [m]
_D1, _D3, _D5 = 0.333, 0.316, 0.384
_A4, _A5, _A7 = 0.0825, -0.0825, 0.088
#: How far a target rotation that check_targets accepts (|R^T R - I| <= 1e-6 per
#: element, so within 3e-6 of a rotation) may turn a vector, relative to its length,
#: with a margin (the reach proof's allowance).
_SKEW = 1e-5


def _dh_forward(q: np.ndarray) -> np.ndarray:
    """Frame 7 of the modified-DH chain, (N, 4, 4), for configurations (N, 7)."""
    d = np.array([_D1, 0.0, _D3, 0.0, _D5, 0.0, 0.0])
    a = np.array([0.0, 0.0, 0.0, _A4, _A5, 0.0, _A7])
    alpha = np.array([0.0, -np.pi / 2, np.pi / 2, np.pi / 2, -np.pi / 2, np.pi / 2, np.pi / 2])
    n = q.shape[0]
    out = np.broadcast_to(np.eye(4), (n, 4, 4)).copy()
    for i in range(7):
        ca, sa = np.cos(alpha[i]), np.sin(alpha[i])
        ct, st = np.cos(q[:, i]), np.sin(q[:, i])
        t = np.zeros((n, 4, 4))
        t[:, 0, 0], t[:, 0, 1], t[:, 0, 3] = ct, -st, a[i]
        t[:, 1, 0], t[:, 1, 1], t[:, 1, 2], t[:, 1, 3] = st * ca, ct * ca, -sa, -sa * d[i]
        t[:, 2, 0], t[:, 2, 1], t[:, 2, 2], t[:, 2, 3] = st * sa, ct * sa, ca, ca * d[i]
        t[:, 3, 3] = 1.0
        out = out @ t
    return out


def _wrap(angle: np.ndarray) -> np.ndarray:
    """Angles in (-2 pi, 2 pi) (sums of two angles of at most pi) into [-pi, pi]."""
    out = np.where(angle > np.pi, angle - 2.0 * np.pi, angle)
    return np.where(out < -np.pi, out + 2.0 * np.pi, out)


class PandaAnalyticIK:
    """All closed-form IK solutions of a Panda-kinematics chain for given :math:`q_7`.

    Args:
        tool_rotation: Rotation (3, 3) of the grasp frame in DH frame 7.
        tool_translation: Position (3,) of the grasp frame in DH frame 7 [m].
    """

    BRANCHES = 8

    def __init__(self, tool_rotation: np.ndarray, tool_translation: np.ndarray) -> None:
        self.tool_rotation = np.asarray(tool_rotation, dtype=float)
        self.tool_translation = np.asarray(tool_translation, dtype=float)
        # |O6 - O2|^2 = k + alpha cos q4 + beta sin q4 = k + rho4 cos(q4 - gamma)
        # (arm plane, frame 4)
        self._k = _A5**2 + _D5**2 + _A4**2 + _D3**2
        alpha = 2.0 * (_A5 * _A4 + _D5 * _D3)
        beta = 2.0 * (_A5 * _D3 - _D5 * _A4)
        self._rho4 = float(np.hypot(alpha, beta))
        self._gamma = float(np.arctan2(beta, alpha))
        #: the constants as the compiled kernel takes them
        self._dims = np.array(
            [self._k, self._rho4, self._gamma, _A4, _A5, _A7, _D1, _D3, _D5], dtype=float
        )

    @classmethod
    def for_chain(
        cls, chain: Any, checks: int = 32, tolerance: float = 1e-9
    ) -> PandaAnalyticIK | None:
        """The solver for a chain, or None when its kinematics are not the Panda's.

        ``chain`` is a :class:`~gcm_pipeline.robot.chain.KinematicChain`. The
        tool transform is read off the chain at one configuration; the chain
        qualifies when DH frame 7 times that transform equals the chain's
        forward kinematics at ``checks`` random configurations to
        ``tolerance`` [m, rad].
        """
        if (
            chain.nq != 7
            or len(chain.joint_ids) != 7
            or not np.array_equal(chain.q_index, np.arange(7))
        ):
            return None
        rng = np.random.default_rng(0x5A7A)
        q = rng.uniform(-np.pi, np.pi, size=(checks + 1, 7))
        rot, pos = chain.pose(q)
        frame7 = _dh_forward(q)
        r7, p7 = frame7[0, :3, :3], frame7[0, :3, 3]
        tool_r = r7.T @ rot[0]
        tool_t = r7.T @ (pos[0] - p7)
        exp_r = frame7[:, :3, :3] @ tool_r
        exp_p = frame7[:, :3, 3] + frame7[:, :3, :3] @ tool_t
        if np.max(np.abs(exp_r - rot)) > tolerance or np.max(np.abs(exp_p - pos)) > tolerance:
            return None
        return cls(tool_r, tool_t)

    def unreachable(
        self,
        rot: np.ndarray,
        pos: np.ndarray,
        position_tolerance: float = 0.0,
        orientation_tolerance: float = 0.0,
        elbow_limits: tuple[float, float] | None = None,
    ) -> np.ndarray:
        r"""Targets that no configuration reaches, proved by the elbow's range.

        The distance :math:`|O_6 - O_2|` is a function of :math:`q_4` alone,
        :math:`\sqrt{k + \rho_4 \cos(q_4 - \gamma)}`, so it lies in an interval
        (over every angle, or over joint 4's limits). The target fixes frame 7
        (:math:`O_7`, :math:`z_7`); :math:`O_6 = O_7 - a_7 x_6` with
        :math:`x_6 \perp z_7`, so whatever :math:`q_7` is, :math:`O_6` lies on
        the circle of radius :math:`a_7` about :math:`O_7` normal to
        :math:`z_7`, whose distances from :math:`O_2` span an interval.
        Disjoint intervals: no configuration reaches the target (with
        ``elbow_limits``: none with joint 4 inside them).

        A configuration within the tolerances of a target has its :math:`O_7`
        within ``position_tolerance`` + ``orientation_tolerance`` times the
        tool's length, and its circle turned by at most
        ``orientation_tolerance`` (points moved by at most :math:`a_7` times
        it): the intervals are widened by that much, so a target counted here
        has no IK solution within the tolerances either. A target rotation may
        be orthonormal only to about 1e-6 (what
        :func:`~gcm_pipeline.robot.ik.check_targets` accepts): that moves
        frame 7 and its circle by up to ``_SKEW`` times the lengths involved
        (the tool, :math:`a_7` and :math:`|O_7 - O_2|`), which widens the
        intervals too, with 1e-9 m for round-off.

        Args:
            rot: Target rotations of the grasp frame (N, 3, 3), base frame.
            pos: Target positions (N, 3) [m].
            position_tolerance: IK tolerance [m], >= 0.
            orientation_tolerance: IK tolerance [rad], >= 0 (angle of the
                rotation between the reached and the target orientation).
            elbow_limits: ``(lower, upper)`` of joint 4 [rad], or None for
                any elbow angle (the arm's reach itself).

        Returns:
            (N,) bool, True where the target is proved unreachable.
        """
        rot = np.asarray(rot, dtype=float).reshape(-1, 3, 3)
        pos = np.asarray(pos, dtype=float).reshape(-1, 3)
        # elbow: |O6 - O2|^2 = k + rho4 cos(x), x = q4 - gamma over the limits
        lo, hi = (-np.pi, np.pi) if elbow_limits is None else elbow_limits
        if not lo <= hi:
            raise ValueError(
                f"elbow_limits must be (lower, upper) with lower <= upper, got {elbow_limits!r}"
            )
        lo, hi = float(lo) - self._gamma, float(hi) - self._gamma
        turns = np.arange(np.floor(lo / (2 * np.pi)) - 1, np.ceil(hi / (2 * np.pi)) + 2)
        cos_hi = 1.0 if np.any((2 * np.pi * turns >= lo) & (2 * np.pi * turns <= hi)) else None
        odd = 2 * np.pi * turns + np.pi
        cos_lo = -1.0 if np.any((odd >= lo) & (odd <= hi)) else None
        ends = (np.cos(lo), np.cos(hi))
        cos_hi = max(ends) if cos_hi is None else cos_hi
        cos_lo = min(ends) if cos_lo is None else cos_lo
        near = np.sqrt(max(self._k + self._rho4 * cos_lo, 0.0))
        far = np.sqrt(self._k + self._rho4 * cos_hi)
        # the circle of O6 over joint 7
        r7 = rot @ self.tool_rotation.T
        v = pos - r7 @ self.tool_translation
        v[:, 2] -= _D1  # O7 - O2
        z7 = r7[:, :, 2]
        along = np.einsum("ij,ij->i", v, z7)
        across = np.linalg.norm(v - along[:, None] * z7, axis=1)
        closest = np.hypot(along, np.maximum(across - abs(_A7), 0.0))
        farthest = np.hypot(along, across + abs(_A7))
        lever = float(np.linalg.norm(self.tool_translation)) + abs(_A7)
        slack = (
            position_tolerance
            + orientation_tolerance * lever
            + _SKEW * (lever + np.linalg.norm(v, axis=1))
            + 1e-9
        )
        return (farthest < near - slack) | (closest > far + slack)

    def solve(
        self,
        rot: np.ndarray,
        pos: np.ndarray,
        q7: np.ndarray,
        lower: np.ndarray,
        upper: np.ndarray,
        near: tuple[np.ndarray, float] | None = None,
        nearest_to: tuple[np.ndarray, np.ndarray] | None = None,
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Every closed-form solution inside the joint limits, for each (target, :math:`q_7`).

        The branches are pruned joint by joint (elbow, then joint 6, then the
        shoulder and joint 5), so rows that leave the limits early cost little;
        with ``near``, so do rows that leave the given neighbourhood.

        Args:
            rot: Target rotations of the grasp frame (N, 3, 3), base frame.
            pos: Target positions (N, 3) [m].
            q7: Values of joint 7 (N, K) [rad], inside its limits.
            lower: Lower joint limits (7,) [rad].
            upper: Upper joint limits (7,) [rad].
            near: ``(reference, reach)``: only the solutions within ``reach``
                [rad] of ``reference[index]`` (N, 7) in every joint (exactly
                those of all the solutions; the others are not computed past
                the joint that leaves).
            nearest_to: ``(pref, levers)``: only each target's solution nearest
                ``pref[index]`` (N, 7) [rad] in the distance
                ``sum(((q - pref[index]) * levers) ** 2)`` (7,) [m/rad] (the first
                of ties in the order below); the compiled kernel keeps only those.

        Returns:
            ``(index, q, branch, column)``: target index (M,), configuration
            (M, 7) [rad], branch (M,) and column of ``q7`` (M,) of each solution,
            grouped by target in (q7 column, branch) order. The branch (0-7) numbers the roots of
            the elbow, joint 6 and the shoulder; along a branch the solution
            moves continuously with :math:`q_7` (away from singularities).
            Unverified: near a singularity of the shoulder or the wrist a row
            may be inexact, so callers verify by forward kinematics.
        """
        n, k = q7.shape
        lower = np.asarray(lower, dtype=float)
        upper = np.asarray(upper, dtype=float)
        compiled = kernels.get()
        # the kernel reads without bounds checks: other shapes get the NumPy code's errors
        shapes_fit = (
            np.shape(rot) == (n, 3, 3)
            and np.shape(pos) == (n, 3)
            and lower.shape == upper.shape == (7,)
            and (near is None or np.shape(near[0]) == (n, 7))
            and (nearest_to is None or np.shape(nearest_to[0]) == (n, 7))
            and (nearest_to is None or np.shape(nearest_to[1]) == (7,))
        )
        if compiled is not None and shapes_fit:
            r7 = rot @ self.tool_rotation.T
            p7 = pos - r7 @ self.tool_translation
            out: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray] = compiled.panda_ik(
                np.ascontiguousarray(r7),
                np.ascontiguousarray(p7),
                np.ascontiguousarray(q7, dtype=float),
                np.ascontiguousarray(lower),
                np.ascontiguousarray(upper),
                np.zeros((0, 7)) if near is None else np.ascontiguousarray(near[0], dtype=float),
                0.0 if near is None else float(near[1]),
                near is not None,
                self._dims,
                np.zeros((0, 7)) if nearest_to is None else np.ascontiguousarray(nearest_to[0]),
                np.zeros(7) if nearest_to is None else np.ascontiguousarray(nearest_to[1]),
            )
            return out
        out = self._solve_numpy(rot, pos, q7, lower, upper, near)
        if nearest_to is None or out[0].size == 0:
            return out
        pref, levers = nearest_to
        dist = np.sum(((out[1] - pref[out[0]]) * levers) ** 2, axis=1)
        order = np.lexsort((dist, out[0]))  # stable: the first of ties
        first = order[np.r_[True, out[0][order][1:] != out[0][order][:-1]]]
        return out[0][first], out[1][first], out[2][first], out[3][first]

    # one derivation in order (elbow, swivel, shoulder, wrist), each step's arrays feeding the
    # next: cut into functions it would pass a dozen arrays around (reason for > 100 lines)
    def _solve_numpy(
        self,
        rot: np.ndarray,
        pos: np.ndarray,
        q7: np.ndarray,
        lower: np.ndarray,
        upper: np.ndarray,
        near: tuple[np.ndarray, float] | None,
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """:meth:`solve` in NumPy, all (target, q7) rows at once (the kernel's reference)."""
        n, k = q7.shape

        def within(j: int, angle: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
            """Angle of joint j moved a turn up where below its limit, and inside-mask.

            The Panda's joint 6 goes past pi.
            """
            angle = np.where(angle < lower[j], angle + 2.0 * np.pi, angle)
            return angle, (angle >= lower[j]) & (angle <= upper[j])

        # frame 7 of the targets; components as separate arrays (NumPy is slow on
        # axes of length 3)
        r7 = rot @ self.tool_rotation.T
        p7 = pos - r7 @ self.tool_translation
        t = np.repeat(np.arange(n), k)
        q7f = np.asarray(q7, dtype=float).reshape(-1)
        c7, s7 = np.cos(q7f), np.sin(q7f)
        ra = [r7[t, i, 0] for i in range(3)]
        rb = [r7[t, i, 1] for i in range(3)]
        # frame 6 for each q7: x6 = R7 (c7, -s7, 0), z6 = R7 (s7, c7, 0), y6 = -z7
        x6 = [ra[i] * c7 - rb[i] * s7 for i in range(3)]
        z6 = [ra[i] * s7 + rb[i] * c7 for i in range(3)]
        y6 = [-r7[t, i, 2] for i in range(3)]
        v = [p7[t, i] - _A7 * x6[i] for i in range(3)]  # O6 - O2
        v[2] = v[2] - _D1
        length2 = v[0] * v[0] + v[1] * v[1] + v[2] * v[2]

        # 1. elbow: |O6 - O2| fixes q4 (two roots); keep those inside the limits (and
        #    the values of joint 7 inside its own)
        with np.errstate(invalid="ignore"):
            half = np.arccos((length2 - self._k) / self._rho4)  # NaN out of reach
        q4 = _wrap(np.concatenate([self._gamma + half, self._gamma - half]))
        q4, ok = within(3, q4)
        q7_ok = (q7f >= lower[6]) & (q7f <= upper[6])
        if near is not None:
            ref, reach = np.asarray(near[0], dtype=float), float(near[1])
            q7_ok &= np.abs(q7f - ref[t, 6]) <= reach
            ok &= np.abs(q4 - np.tile(ref[t, 3], 2)) <= reach
        ok &= np.tile(q7_ok, 2)
        rows = np.flatnonzero(ok)
        src = rows % (n * k)  # row of the (target, q7) table
        branch = rows // (n * k) * 4  # elbow root
        q4 = q4[rows]
        length = np.sqrt(length2[src])
        u = [v[i][src] / length for i in range(3)]
        x6 = [c[src] for c in x6]
        y6 = [c[src] for c in y6]
        z6 = [c[src] for c in z6]
        c4, s4 = np.cos(q4), np.sin(q4)
        # (O6 - O2) / |O6 - O2| in frame 4: (ux, uy, 0)
        ux = (_A5 + _A4 * c4 + _D3 * s4) / length
        uy = (_D5 - _A4 * s4 + _D3 * c4) / length

        # 2. joint 6: the axis of joint 5 is y4 = sin(q6) x6 + cos(q6) y6 and makes
        #    the fixed angle y4 . u = uy with the line O2-O6: two roots
        xu = x6[0] * u[0] + x6[1] * u[1] + x6[2] * u[2]
        yu = y6[0] * u[0] + y6[1] * u[1] + y6[2] * u[2]
        with np.errstate(invalid="ignore", divide="ignore"):
            spread = np.arccos(uy / np.hypot(xu, yu))
        centre = np.arctan2(xu, yu)
        q6 = _wrap(np.concatenate([centre + spread, centre - spread]))
        q6, ok = within(5, q6)
        if near is not None:
            ok &= np.abs(q6 - np.tile(ref[src // k, 5], 2)) <= reach
        rows2 = np.flatnonzero(ok)
        sel = rows2 % len(rows)
        q6 = q6[rows2]

        def pick(cols: list[np.ndarray]) -> list[np.ndarray]:
            return [c[sel] for c in cols]

        u, x6, y6, z6 = pick(u), pick(x6), pick(y6), pick(z6)
        ux, uy, c4, s4 = ux[sel], uy[sel], c4[sel], s4[sel]
        src, q4 = src[sel], q4[sel]
        branch = branch[sel] + rows2 // len(rows) * 2  # joint 6 root
        s6, c6 = np.sin(q6), np.cos(q6)
        y4 = [s6 * x6[i] + c6 * y6[i] for i in range(3)]
        # y4 = uy u + ux (z4 x u): recover z4 x u, then z4 = u x (z4 x u), x4 = y4 x z4
        with np.errstate(invalid="ignore", divide="ignore"):
            w = [(y4[i] - uy * u[i]) / ux for i in range(3)]
        z4 = [u[1] * w[2] - u[2] * w[1], u[2] * w[0] - u[0] * w[2], u[0] * w[1] - u[1] * w[0]]
        x4 = [ux * u[i] - uy * w[i] for i in range(3)]

        # 3. shoulder: R03 = R04 Rz(q4)^T Rx(pi/2)^T = Rz(q1) Ry(q2) Rz(q3), two roots;
        #    x3 = c4 x4 - s4 y4, y3 = -z4, z3 = s4 x4 + c4 y4
        z3 = [s4 * x4[i] + c4 * y4[i] for i in range(3)]
        x3z = c4 * x4[2] - s4 * y4[2]
        sb = np.hypot(z3[0], z3[1])
        # joint 5: R46 = R04^T R06 = Ry(q5) Rz(q6)
        q5 = np.arctan2(
            x4[0] * z6[0] + x4[1] * z6[1] + x4[2] * z6[2],
            z4[0] * z6[0] + z4[1] * z6[1] + z4[2] * z6[2],
        )
        m = len(src)
        out_q = np.empty((2 * m, 7))
        for half_, sign in ((slice(0, m), 1.0), (slice(m, 2 * m), -1.0)):
            out_q[half_, 0] = np.arctan2(sign * z3[1], sign * z3[0])
            out_q[half_, 1] = np.arctan2(sign * sb, z3[2])
            out_q[half_, 2] = np.arctan2(-sign * z4[2], -sign * x3z)
        out_q[:, 3] = np.tile(q4, 2)
        out_q[:, 4] = np.tile(q5, 2)
        out_q[:, 5] = np.tile(q6, 2)
        out_q[:, 6] = np.tile(q7f[src], 2)
        ok = np.ones(2 * m, dtype=bool)
        for j in (0, 1, 2, 4):
            out_q[:, j], inside = within(j, out_q[:, j])
            ok &= inside
        if near is not None:
            ok &= np.all(np.abs(out_q - ref[np.tile(src // k, 2)]) <= reach, axis=1)
        keep = np.flatnonzero(ok)
        target = np.tile(src, 2)[keep] // k
        branch = np.concatenate([branch, branch + 1])[keep]  # shoulder root
        order = np.lexsort((branch, np.tile(src, 2)[keep] % k, target))
        column = (np.tile(src, 2)[keep] % k)[order]
        return target[order], out_q[keep[order]], branch[order], column


def analytic_solver(robot: Any) -> PandaAnalyticIK | None:
    """The closed-form solver of ``robot``'s arm (cached), or None if it has none."""
    return per_robot(robot, ("analytic_ik",), PandaAnalyticIK.for_chain)


def analytic_blocks(
    solver: PandaAnalyticIK,
    rot: np.ndarray,
    pos: np.ndarray,
    q7: np.ndarray,
    lower: np.ndarray,
    upper: np.ndarray,
    near: tuple[np.ndarray, float] | None = None,
    nearest_to: tuple[np.ndarray, np.ndarray] | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """:meth:`PandaAnalyticIK.solve` in blocks of targets, without repeats.

    Blocks bound the memory; a repeat is one joint-7 value given twice to a
    target (e.g. two offsets clipped to a limit): its first column is kept
    (the later ones are not solved: NaN is outside joint 7's limits).
    ``near``: ``(reference (N, 7), reach)``; ``nearest_to``: ``(pref (N, 7),
    levers (7,))``, as for the solver.
    """
    q7 = _first_of_repeats(np.asarray(q7, dtype=float))
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
            None if nearest_to is None else (nearest_to[0][a : a + step], nearest_to[1]),
        )
        for a in starts
    ]
    at = np.concatenate([p[0] + a for p, a in zip(parts, starts, strict=True)])
    cq = np.concatenate([p[1] for p in parts])
    branch = np.concatenate([p[2] for p in parts])
    column = np.concatenate([p[3] for p in parts])
    return at, cq, branch, column


def _first_of_repeats(q7: np.ndarray) -> np.ndarray:
    """``q7`` (N, K) with every value a row already has in an earlier column set to NaN."""
    if q7.ndim != 2 or q7.shape[1] < 2:
        return q7
    order = np.argsort(q7, axis=1, kind="stable")  # equal values: earlier column first
    values = np.take_along_axis(q7, order, axis=1)
    repeat = values[:, 1:] == values[:, :-1]
    if not repeat.any():
        return q7
    r, c = np.nonzero(repeat)
    out = q7.copy()
    out[r, order[r, c + 1]] = np.nan
    return out
