r"""Targets a 6R arm of the Universal Robots' geometry cannot reach, proved in closed form.

The arms this applies to (the UR family; checked on the loaded chain at q = 0,
the tool and the base offset included): the axes of joints 1 and 2 meet at a
point :math:`S` and are perpendicular; joints 2, 3 and 4 turn about parallel
axes (direction :math:`n`); the axes of joints 5 and 6 meet at a point
:math:`W`, and axis 5 is perpendicular to both :math:`n` and axis 6. Then, for
every configuration:

* :math:`n \perp a_1` turns with joint 1 alone, and :math:`n \cdot (W - S)`
  is a constant :math:`d` (joints 2-4 turn about axes parallel to :math:`n`,
  joint 1 turns :math:`n` and :math:`W` together about an axis through
  :math:`S`);
* axis 5 is :math:`\pm (n \times z_6) / |n \times z_6|` (:math:`z_6`, the
  direction of axis 6, is fixed in the grasp frame, as :math:`W` is);
* the point :math:`W - c\,a_5` (a fixed offset :math:`c` along axis 5) lies on
  axis 4, so its distance from axis 2 in the plane normal to :math:`n`,
  :math:`L = |W - S - d\,n - c\,a_5|`, is what the two links between axes 2,
  3 and 4 span: at most :math:`\ell_2 + \ell_3`.

A target fixes :math:`W` and :math:`z_6`; :math:`n \cdot (W - S) = d` gives
two shoulder directions (none where :math:`W` is nearer axis 1 than
:math:`|d|`), and each two directions of axis 5. If all four :math:`L` exceed
:math:`\ell_2 + \ell_3`, no configuration reaches the target, whatever the
joint limits. A configuration within the IK tolerances of a target has its
:math:`W` within ``position_tolerance`` + ``orientation_tolerance`` times
:math:`|W|` (grasp frame) and its :math:`z_6` turned by at most
``orientation_tolerance``; the bounds of how far that moves :math:`n`,
:math:`a_5` and so each :math:`L` widen the test, so a target counted here has
no IK solution within the tolerances either. Near the singular poses (the
wrist over axis 1, axis 6 along :math:`n`) those bounds grow and nothing is
proved. The test is the counterpart of the Panda's
(:meth:`~gcm_pipeline.robot.ik.panda.PandaAnalyticIK.unreachable`).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from gcm_pipeline.robot.ik.per_robot import per_robot

__all__ = ["SixRReach", "joint_frames", "six_r_reach"]

#: Axes closer than this to parallel, perpendicular or meeting count as such [m, rad].
_EXACT = 1e-9
#: A target rotation may be orthonormal only to about 1e-6 (what
#: :func:`~gcm_pipeline.robot.ik.check_targets` accepts): points and axes read off
#: it move by up to this times their length.
_SKEW = 1e-5
#: Allowance [m] for round-off and for axes off the geometry by up to ``_EXACT``
#: (over the arm's lengths, a metre or two).
_ROUND_OFF = 1e-8


def joint_frames(chain: Any) -> np.ndarray:
    """Each joint's frame at q = 0 and the grasp frame, in the base frame, (nq + 1, 4, 4).

    ``chain`` is a :class:`~gcm_pipeline.robot.chain.KinematicChain`; a joint
    turns about the z axis of its frame.
    """
    _, placement, tool = chain.packed
    nq = len(placement)
    frames = np.empty((nq + 1, 4, 4))
    t = np.eye(4)
    for k in range(nq):
        t = t @ placement[k]
        frames[k] = t
    frames[nq] = t @ tool
    return frames


def _meet(p1: np.ndarray, d1: np.ndarray, p2: np.ndarray, d2: np.ndarray) -> np.ndarray | None:
    """The point where two lines (point, unit direction) meet, or None if they do not."""
    normal = np.cross(d1, d2)
    nn = float(normal @ normal)
    if nn < _EXACT:
        return None
    t1 = float(np.cross(p2 - p1, d2) @ normal) / nn
    t2 = float(np.cross(p2 - p1, d1) @ normal) / nn
    x1, x2 = p1 + t1 * d1, p2 + t2 * d2
    if np.linalg.norm(x1 - x2) > _EXACT:
        return None
    out: np.ndarray = 0.5 * (x1 + x2)
    return out


@dataclass(frozen=True)
class SixRReach:
    r"""The reach test of a 6R arm of the UR geometry (see the module doc).

    Attributes:
        shoulder: :math:`S` (3,), where axes 1 and 2 meet, base frame [m].
        axis1: Direction of axis 1 (3,), base frame.
        plane: (2, 3) orthonormal directions normal to axis 1.
        offset: :math:`d = n \cdot (W - S)` [m].
        wrist: :math:`W` (3,) in the grasp frame [m].
        wrist_axis: :math:`z_6` (3,) in the grasp frame.
        lever: :math:`c`, the offset of :math:`W` from axis 4 along axis 5 [m].
        reach: :math:`\ell_2 + \ell_3` [m].
    """

    shoulder: np.ndarray
    axis1: np.ndarray
    plane: np.ndarray
    offset: float
    wrist: np.ndarray
    wrist_axis: np.ndarray
    lever: float
    reach: float

    @classmethod
    def for_chain(cls, chain: Any) -> SixRReach | None:
        """The test of a chain of exactly 6 joints with the UR geometry, or None."""
        if (
            chain.nq != 6
            or len(chain.joint_ids) != 6
            or not np.array_equal(chain.q_index, np.arange(6))
        ):
            return None
        frames = joint_frames(chain)
        axis = frames[:6, :3, 2]
        origin = frames[:6, :3, 3]
        n = axis[1]
        shoulder = _meet(origin[0], axis[0], origin[1], axis[1])
        wrist = _meet(origin[4], axis[4], origin[5], axis[5])
        if (
            shoulder is None
            or wrist is None
            or abs(axis[0] @ n) > _EXACT
            or np.linalg.norm(np.cross(n, axis[2])) > _EXACT
            or np.linalg.norm(np.cross(n, axis[3])) > _EXACT
            or abs(axis[4] @ n) > _EXACT
            or abs(axis[4] @ axis[5]) > _EXACT
        ):
            return None

        def across(v: np.ndarray) -> np.ndarray:
            out: np.ndarray = v - (v @ n) * n
            return out

        # W's offset from axis 4 in the plane normal to n: along axis 5 only
        off = across(wrist - origin[3])
        lever = float(off @ axis[4])
        if np.linalg.norm(off - lever * axis[4]) > _EXACT:
            return None
        first = np.cross(axis[0], np.eye(3)[int(np.argmin(np.abs(axis[0])))])
        first /= np.linalg.norm(first)
        grasp = frames[6]
        return cls(
            shoulder=shoulder,
            axis1=axis[0].copy(),
            plane=np.stack([first, np.cross(axis[0], first)]),
            offset=float(n @ (wrist - shoulder)),
            wrist=grasp[:3, :3].T @ (wrist - grasp[:3, 3]),
            wrist_axis=grasp[:3, :3].T @ axis[5],
            lever=lever,
            reach=float(
                np.linalg.norm(across(origin[2] - origin[1]))
                + np.linalg.norm(across(origin[3] - origin[2]))
            ),
        )

    def unreachable(
        self,
        rot: np.ndarray,
        pos: np.ndarray,
        position_tolerance: float = 0.0,
        orientation_tolerance: float = 0.0,
    ) -> np.ndarray:
        """Targets that no configuration reaches within the tolerances (see the module doc).

        Args:
            rot: Target rotations of the grasp frame (N, 3, 3), base frame.
            pos: Target positions (N, 3) [m].
            position_tolerance: IK tolerance [m], >= 0.
            orientation_tolerance: IK tolerance [rad], >= 0 (angle of the
                rotation between the reached and the target orientation).

        Returns:
            (N,) bool, True where the target is proved unreachable (False for
            a target that is not finite).
        """
        rot = np.asarray(rot, dtype=float).reshape(-1, 3, 3)
        pos = np.asarray(pos, dtype=float).reshape(-1, 3)
        d, c = self.offset, self.lever
        w = pos + rot @ self.wrist - self.shoulder  # W - S
        x, y = w @ self.plane[0], w @ self.plane[1]
        rho = np.hypot(x, y)  # distance of W from axis 1
        # how far W and z6 may be from the target's, for a configuration within the
        # tolerances
        moved = (
            position_tolerance
            + (orientation_tolerance + _SKEW) * float(np.linalg.norm(self.wrist))
            + _ROUND_OFF
        )
        out = np.zeros(len(pos), dtype=bool)
        with np.errstate(invalid="ignore"):
            # on every branch L <= |W - S - d n| + |c| = sqrt(|W - S|^2 - d^2) + |c|: a
            # target within that bound of the links' reach is not proved (most are not)
            bound = self.reach - abs(c)
            far = np.einsum("ij,ij->i", w, w) - d * d > bound * abs(bound)
            rows = np.flatnonzero(far | (rho <= abs(d) + moved))
        if rows.size:
            out[rows] = self._proved(
                rot.take(rows, axis=0), w[rows], x[rows], y[rows], rho[rows], moved,
                orientation_tolerance + _SKEW,
            )  # fmt: skip
        return out & np.all(np.isfinite(pos), axis=1) & np.all(np.isfinite(rot), axis=(1, 2))

    def _proved(
        self,
        rot: np.ndarray,
        w: np.ndarray,
        x: np.ndarray,
        y: np.ndarray,
        rho: np.ndarray,
        moved: float,
        turned: float,
    ) -> np.ndarray:
        """:meth:`unreachable` of M targets, each branch bounded.

        Rotations (M, 3, 3), ``W - S`` (M, 3) and its coordinates ``x``, ``y``
        (M,) normal to axis 1, at distance ``rho`` (M,) from it; ``moved`` [m]
        and ``turned`` [rad] bound how far W and z6 may be off them.
        """
        d, c = self.offset, self.lever
        z6 = rot @ self.wrist_axis
        with np.errstate(invalid="ignore", divide="ignore"):
            # the shoulder directions phi = theta +- acos(d / rho) turn by at most
            # asin(moved / rho) + max |d (acos(d / r)) / dr| * moved over r >= rho - moved
            near = rho - moved
            dphi = np.arcsin(np.minimum(moved / near, 1.0)) + abs(d) * moved / (
                near * np.sqrt(near * near - d * d)
            )
            theta = np.arctan2(y, x)
            half = np.arccos(np.clip(d / rho, -1.0, 1.0))
            least = np.full(len(w), np.inf)
            for sign in (1.0, -1.0):
                phi = theta + sign * half
                n = np.cos(phi)[:, None] * self.plane[0] + np.sin(phi)[:, None] * self.plane[1]
                u = np.cross(n, z6)
                size = np.linalg.norm(u, axis=1)
                u /= size[:, None]
                # |a/|a| - b/|b|| <= 2 |a - b| / |a|, and at most 2
                du = np.minimum(2.0 * (dphi + turned) / size, 2.0)
                margin = moved + abs(d) * dphi + abs(c) * du
                axis4 = w - d * n
                for side in (c, -c):
                    span = np.linalg.norm(axis4 - side * u, axis=1)
                    least = np.minimum(least, span - margin)
            # every shoulder direction leaves the links too short, or there is none
            out: np.ndarray = ((near > abs(d)) & (least > self.reach)) | (rho + moved < abs(d))
        return out


def six_r_reach(robot: Any) -> SixRReach | None:
    """The reach test of ``robot``'s arm (cached) if it has the UR geometry, else None."""
    return per_robot(robot, ("reach_6r",), SixRReach.for_chain)
