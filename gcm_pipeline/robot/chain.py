r"""Vectorised forward kinematics and Jacobians of one frame of a serial chain.

The chain is read out of a Pinocchio model once (joint placements and axes)
and then evaluated for N configurations at once with NumPy, which is what the
batched IK and the manipulability metrics need. Each joint ``i`` contributes

.. math::

    {}^{0}T_i = {}^{0}T_{\mathrm{parent}(i)} \; M_i \; \mathrm{Rot}(a_i, q_i),

where :math:`M_i` is Pinocchio's ``jointPlacements[i]`` and :math:`a_i` the
joint axis; the frame is :math:`{}^{0}T_f = {}^{0}T_{j(f)} \, M_f`. The results
equal Pinocchio's ``forwardKinematics`` + ``updateFramePlacements`` and
``getFrameJacobian(..., LOCAL_WORLD_ALIGNED)`` to round-off (tested to 1e-12).
"""

from __future__ import annotations

import numpy as np
import pinocchio as pin

from gcm_pipeline.errors import RobotSpecError

__all__ = ["KinematicChain"]

_AXES = {"JointModelRX": (1.0, 0.0, 0.0), "JointModelRY": (0.0, 1.0, 0.0)}
_AXES["JointModelRZ"] = (0.0, 0.0, 1.0)


def _skew(a: np.ndarray) -> np.ndarray:
    return np.array([[0.0, -a[2], a[1]], [a[2], 0.0, -a[0]], [-a[1], a[0], 0.0]])


class KinematicChain:
    """Serial chain from the model root to one frame, evaluated in batches.

    Args:
        model: A Pinocchio model whose joints are all 1-DoF revolute joints
            (``nq == nv == njoints - 1``).
        frame_id: Index of the frame whose pose and Jacobian are computed.

    Raises:
        RobotSpecError: If the model has a joint type other than revolute.
    """

    def __init__(self, model: pin.Model, frame_id: int) -> None:
        if model.nq != model.nv or model.nq != model.njoints - 1:
            raise RobotSpecError(
                f"model {model.name!r}: only 1-DoF revolute joints are supported "
                f"(nq={model.nq}, nv={model.nv}, joints={model.njoints - 1})"
            )
        frame = model.frames[frame_id]
        chain: list[int] = []
        j = int(frame.parentJoint)
        while j > 0:
            chain.append(j)
            j = int(model.parents[j])
        chain.reverse()
        self.nq = int(model.nq)
        self.joint_ids = np.array(chain, dtype=int)
        self.q_index = np.array([model.joints[j].idx_q for j in chain], dtype=int)
        a0, a1, a2, trans, axes = [], [], [], [], []
        for j in chain:
            jm = model.joints[j]
            kind = jm.shortname()
            if kind in _AXES:
                axis = np.array(_AXES[kind])
            elif kind == "JointModelRevoluteUnaligned":
                axis = np.asarray(jm.extract().axis, dtype=float).copy()
            else:
                raise RobotSpecError(
                    f"joint {model.names[j]!r} has unsupported type {kind}; "
                    "only revolute joints are supported"
                )
            placement = model.jointPlacements[j]
            rot = np.asarray(placement.rotation)
            k = _skew(axis)
            a0.append(rot)
            a1.append(rot @ k)
            a2.append(rot @ k @ k)
            trans.append(np.asarray(placement.translation).copy())
            axes.append(axis)
        self._a0 = np.array(a0)
        self._a1 = np.array(a1)
        self._a2 = np.array(a2)
        self._t = np.array(trans)
        self._axes = np.array(axes)
        self._tool_r = np.asarray(frame.placement.rotation).copy()
        self._tool_t = np.asarray(frame.placement.translation).copy()
        # the first joint's origin does not depend on q (its parent is the root)
        self.root_origin = self._t[0].copy() if chain else np.zeros(3)

    def _forward(
        self, q: np.ndarray, jacobian: bool
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
        n = q.shape[0]
        rot = np.broadcast_to(np.eye(3), (n, 3, 3))
        pos = np.zeros((n, 3))
        origins = np.empty((len(self.joint_ids), n, 3))
        zaxes = np.empty((len(self.joint_ids), n, 3))
        for k, qi in enumerate(self.q_index):
            angle = q[:, qi]
            s = np.sin(angle)[:, None, None]
            c1 = (1.0 - np.cos(angle))[:, None, None]
            local = self._a0[k] + s * self._a1[k] + c1 * self._a2[k]
            if k == 0:
                pos = np.broadcast_to(self._t[0], (n, 3)).copy()
                rot = local
            else:
                pos = pos + rot @ self._t[k]
                rot = rot @ local
            if jacobian:
                origins[k] = pos
                zaxes[k] = rot @ self._axes[k]
        tool_p = pos + rot @ self._tool_t
        tool_r = rot @ self._tool_r
        if not jacobian:
            return tool_r, tool_p, None
        jac = np.zeros((n, 6, self.nq))
        lin = np.cross(zaxes, tool_p[None] - origins)  # (k, n, 3)
        jac[:, :3, self.q_index] = lin.transpose(1, 2, 0)
        jac[:, 3:, self.q_index] = zaxes.transpose(1, 2, 0)
        return tool_r, tool_p, jac

    def pose(self, q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Rotation and position of the frame.

        Args:
            q: Configurations, shape (N, nq) [rad].

        Returns:
            ``(R, p)``: rotations (N, 3, 3) and positions (N, 3) [m] in the base frame.
        """
        r, p, _ = self._forward(np.asarray(q, dtype=float), jacobian=False)
        return r, p

    def pose_jacobian(self, q: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Pose and LOCAL_WORLD_ALIGNED Jacobian of the frame.

        Args:
            q: Configurations, shape (N, nq) [rad].

        Returns:
            ``(R, p, J)``: rotations (N, 3, 3), positions (N, 3) [m] and Jacobians
            (N, 6, nq), rows ``[v; omega]``: linear velocity of the frame origin
            and angular velocity, both in base-frame axes.
        """
        r, p, jac = self._forward(np.asarray(q, dtype=float), jacobian=True)
        assert jac is not None
        return r, p, jac

    def link_lengths(self) -> np.ndarray:
        """Distances between consecutive joint origins and to the frame [m].

        Their sum bounds the distance from the first joint's origin to the frame.
        """
        return np.concatenate([np.linalg.norm(self._t[1:], axis=1), [np.linalg.norm(self._tool_t)]])
