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

__all__ = ["JointFrames", "KinematicChain"]

_AXES = {"JointModelRX": (1.0, 0.0, 0.0), "JointModelRY": (0.0, 1.0, 0.0)}
_AXES["JointModelRZ"] = (0.0, 0.0, 1.0)


def _z_to(axis: np.ndarray) -> np.ndarray:
    """A rotation that maps the z axis onto the unit vector ``axis``."""
    z = np.array([0.0, 0.0, 1.0])
    v = np.cross(z, axis)
    c = float(axis @ z)
    if np.linalg.norm(v) < 1e-12:
        return np.eye(3) if c > 0 else np.diag([1.0, -1.0, -1.0])
    k = np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])
    return np.eye(3) + k + k @ k / (1.0 + c)


def _check_one_dof(model: pin.Model) -> None:
    """Raise :class:`RobotSpecError` unless every joint has one degree of freedom."""
    if model.nq != model.nv or model.nq != model.njoints - 1:
        raise RobotSpecError(
            f"model {model.name!r}: only 1-DoF revolute joints are supported "
            f"(nq={model.nq}, nv={model.nv}, joints={model.njoints - 1})"
        )


def _joint_axis(model: pin.Model, j: int) -> np.ndarray:
    """Unit axis (3,) of revolute joint ``j`` in its own frame.

    Raises:
        RobotSpecError: If the joint is not revolute.
    """
    jm = model.joints[j]
    kind = jm.shortname()
    if kind in _AXES:
        return np.array(_AXES[kind])
    if kind == "JointModelRevoluteUnaligned":
        axis = np.asarray(jm.extract().axis, dtype=float).copy()
        return axis / np.linalg.norm(axis)
    raise RobotSpecError(
        f"joint {model.names[j]!r} has unsupported type {kind}; only revolute joints are supported"
    )


class KinematicChain:
    """Serial chain from the model root to one frame, evaluated in batches.

    Args:
        model: A Pinocchio model whose joints are all 1-DoF revolute joints
            (``nq == nv == njoints - 1``).
        frame_id: Index of the frame whose pose and Jacobian are computed.

    Raises:
        RobotSpecError: If the model has a joint type other than revolute.
    """

    CHUNK = 4096

    def __init__(self, model: pin.Model, frame_id: int) -> None:
        _check_one_dof(model)
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
        rots, trans = [], []
        post = np.eye(3)  # rotation carried over from the previous joint's axis change
        for j in chain:
            axis = _joint_axis(model, j)
            placement = model.jointPlacements[j]
            # rotate the joint frame so that its axis is z: Rot(a, q) = Ra Rz(q) Ra^T,
            # the trailing Ra^T is folded into the next placement
            ra = _z_to(axis)
            rots.append(post @ np.asarray(placement.rotation) @ ra)
            trans.append(post @ np.asarray(placement.translation))
            post = ra.T
        self._rot = np.array(rots)
        self._t = np.array(trans)
        self._tool_r = post @ np.asarray(frame.placement.rotation)
        self._tool_t = post @ np.asarray(frame.placement.translation)
        # the first joint's origin does not depend on q (its parent is the root)
        self.root_origin = self._t[0].copy() if chain else np.zeros(3)

    def _forward(
        self, q: np.ndarray, jacobian: bool
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
        n = q.shape[0]
        nj = len(self.joint_ids)
        rot = np.broadcast_to(np.eye(3), (n, 3, 3))
        pos = np.zeros((n, 3))
        origins = np.empty((nj, n, 3))
        zaxes = np.empty((nj, n, 3))
        cos = np.cos(q[:, self.q_index])
        sin = np.sin(q[:, self.q_index])
        for k in range(nj):
            if k == 0:
                pos = np.broadcast_to(self._t[0], (n, 3))
                b = np.broadcast_to(self._rot[0], (n, 3, 3))
            else:
                pos = pos + (rot.reshape(-1, 3) @ self._t[k]).reshape(n, 3)
                b = (rot.reshape(-1, 3) @ self._rot[k]).reshape(n, 3, 3)
            c = cos[:, k, None]
            s = sin[:, k, None]
            b0, b1 = b[:, :, 0], b[:, :, 1]
            new = np.empty((n, 3, 3))
            new[:, :, 0] = c * b0 + s * b1
            new[:, :, 1] = c * b1 - s * b0
            new[:, :, 2] = b[:, :, 2]
            rot = new
            if jacobian:
                origins[k] = pos
                zaxes[k] = b[:, :, 2]
        tool_p = pos + (rot.reshape(-1, 3) @ self._tool_t).reshape(n, 3)
        tool_r = (rot.reshape(-1, 3) @ self._tool_r).reshape(n, 3, 3)
        if not jacobian:
            return tool_r, tool_p, None
        jac = np.zeros((n, 6, self.nq))
        d = tool_p[None] - origins  # (k, n, 3)
        z = zaxes
        lin = np.empty_like(d)
        lin[..., 0] = z[..., 1] * d[..., 2] - z[..., 2] * d[..., 1]
        lin[..., 1] = z[..., 2] * d[..., 0] - z[..., 0] * d[..., 2]
        lin[..., 2] = z[..., 0] * d[..., 1] - z[..., 1] * d[..., 0]
        jac[:, :3, self.q_index] = lin.transpose(1, 2, 0)
        jac[:, 3:, self.q_index] = zaxes.transpose(1, 2, 0)
        return tool_r, tool_p, jac

    def _chunked(
        self, q: np.ndarray, jacobian: bool
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
        """:meth:`_forward` in blocks of ``CHUNK`` rows (temporaries stay in cache)."""
        n = q.shape[0]
        if n <= self.CHUNK:
            return self._forward(q, jacobian)
        rot = np.empty((n, 3, 3))
        pos = np.empty((n, 3))
        jac = np.empty((n, 6, self.nq)) if jacobian else None
        for a in range(0, n, self.CHUNK):
            b = min(n, a + self.CHUNK)
            r, p, j = self._forward(q[a:b], jacobian)
            rot[a:b], pos[a:b] = r, p
            if jac is not None:
                jac[a:b] = j
        return rot, pos, jac

    def pose(self, q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Rotation and position of the frame.

        Args:
            q: Configurations, shape (N, nq) [rad].

        Returns:
            ``(R, p)``: rotations (N, 3, 3) and positions (N, 3) [m] in the base frame.
        """
        r, p, _ = self._chunked(np.asarray(q, dtype=float), jacobian=False)
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
        r, p, jac = self._chunked(np.asarray(q, dtype=float), jacobian=True)
        assert jac is not None
        return r, p, jac

    def link_lengths(self) -> np.ndarray:
        """Distances between consecutive joint origins and to the frame [m].

        Their sum bounds the distance from the first joint's origin to the frame.
        """
        return np.concatenate([np.linalg.norm(self._t[1:], axis=1), [np.linalg.norm(self._tool_t)]])


class JointFrames:
    """Placements of every joint of a model of revolute joints, N configurations at once.

    One pass over the joints (parents before children) computes each joint's
    frame with the same parameters as :class:`KinematicChain`, so a set of
    points fixed to the links (collision spheres, geometry placements) is
    placed for all configurations with a few array operations.

    Frames are returned in a *rotated* convention: each joint's frame is turned
    so that its axis is z. :meth:`local` converts a point or rotation given in
    Pinocchio's joint frame into that convention once, ahead of time.

    Args:
        model: A Pinocchio model whose joints are all 1-DoF revolute joints.

    Raises:
        RobotSpecError: If the model has a joint type other than revolute.
    """

    def __init__(self, model: pin.Model) -> None:
        _check_one_dof(model)
        nj = int(model.njoints)
        self.njoints = nj
        self.parent = np.array([int(model.parents[j]) for j in range(nj)], dtype=int)
        self.q_index = np.array([-1] + [model.joints[j].idx_q for j in range(1, nj)], dtype=int)
        self._rot = np.zeros((nj, 3, 3))
        self._t = np.zeros((nj, 3))
        self._post = np.zeros((nj, 3, 3))  # R_a^T of each joint: rotated -> Pinocchio frame
        self._post[0] = np.eye(3)
        self._rot[0] = np.eye(3)
        for j in range(1, nj):
            axis = _joint_axis(model, j)
            ra = _z_to(axis)
            pre = self._post[self.parent[j]]
            placement = model.jointPlacements[j]
            self._rot[j] = pre @ np.asarray(placement.rotation) @ ra
            self._t[j] = pre @ np.asarray(placement.translation)
            self._post[j] = ra.T

    def local(
        self, joint: int, rot: np.ndarray, trans: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]:
        """A placement in Pinocchio's frame of ``joint`` in the rotated convention."""
        post = self._post[joint]
        return post @ rot, post @ trans

    def compute(self, q: np.ndarray) -> tuple[list[np.ndarray], list[np.ndarray]]:
        """Frames of every joint (index 0: the universe).

        Args:
            q: Configurations (N, nq) [rad].

        Returns:
            ``(R, p)``: per joint, rotations (N, 3, 3) in the rotated convention
            and origins (N, 3) [m], base frame.
        """
        q = np.asarray(q, dtype=float)
        n = q.shape[0]
        rots = [np.broadcast_to(np.eye(3), (n, 3, 3))]
        poss = [np.zeros((n, 3))]
        cos = np.cos(q)
        sin = np.sin(q)
        for j in range(1, self.njoints):
            p = self.parent[j]
            rp = rots[p].reshape(-1, 3)
            poss.append(poss[p] + (rp @ self._t[j]).reshape(n, 3))
            b = (rp @ self._rot[j]).reshape(n, 3, 3)
            c = cos[:, self.q_index[j], None]
            s = sin[:, self.q_index[j], None]
            b0, b1 = b[:, :, 0], b[:, :, 1]
            new = np.empty((n, 3, 3))
            new[:, :, 0] = c * b0 + s * b1
            new[:, :, 1] = c * b1 - s * b0
            new[:, :, 2] = b[:, :, 2]
            rots.append(new)
        return rots, poss
