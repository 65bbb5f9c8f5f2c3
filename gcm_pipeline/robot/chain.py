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

from typing import NamedTuple

import numpy as np
import pinocchio as pin

from gcm_pipeline.errors import RobotSpecError
from gcm_pipeline.robot import kernels

__all__ = ["Frames", "JointFrames", "KinematicChain"]

_AXES = {"JointModelRX": (1.0, 0.0, 0.0), "JointModelRY": (0.0, 1.0, 0.0)}
_AXES["JointModelRZ"] = (0.0, 0.0, 1.0)


#: The half turn about x: maps z onto -z (its own inverse).
_FLIP = np.diag([1.0, -1.0, -1.0])


def _z_to(axis: np.ndarray) -> np.ndarray:
    """A rotation that maps the z axis onto the unit vector ``axis``.

    Rodrigues' formula about ``z x axis`` divides by ``1 + cos``, which loses
    every digit as the axis nears -z (a URDF axis ``0 -8.7e-08 -1``, a float32
    export of -z, gave joint origins 4.7 mm off). An axis below the xy plane
    is first flipped to the upper half by the half turn about x, so the
    division is by at least 1.
    """
    if axis[2] < 0.0:
        return _FLIP @ _z_to(_FLIP @ axis)
    z = np.array([0.0, 0.0, 1.0])
    v = np.cross(z, axis)
    c = float(axis @ z)
    if np.linalg.norm(v) < 1e-12:
        return np.eye(3)
    k = np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])
    return np.eye(3) + k + k @ k / (1.0 + c)


def _homogeneous(rot: np.ndarray, trans: np.ndarray) -> np.ndarray:
    """Transforms (K, 4, 4) of rotations (K, 3, 3) and translations (K, 3)."""
    out = np.zeros((len(rot), 4, 4))
    out[:, :3, :3] = rot
    out[:, :3, 3] = trans
    out[:, 3, 3] = 1.0
    return out


def _joint_frame(
    out: np.ndarray, parent: np.ndarray | None, placement: np.ndarray, turn: np.ndarray
) -> None:
    """A joint's frames (N, 3, 4), in place: parent @ placement @ Rz(q).

    ``parent`` (N, 3, 4) is None at the root; ``turn`` (N,) is exp(-i q). The
    placement is one (3N, 4) @ (4, 4) product; Rz(q) changes only the x and y
    columns, (x + i y) * exp(-i q): one complex product on a complex view.
    """
    if parent is None:
        out[:] = placement[:3]
    else:
        np.matmul(parent.reshape(-1, 4), placement, out=out.reshape(-1, 4))
    out.view(np.complex128)[:, :, 0] *= turn[:, None]


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
    name = model.names[j]
    raise RobotSpecError(
        f"joint {name!r} has unsupported type {kind}; only revolute joints are supported: "
        f"lock it at a value (locked_joints: {{{name}: value}})"
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

    CHUNK = 2048

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
        # joint placements and the tool as transforms (4, 4)
        self._placement = _homogeneous(
            np.array(rots).reshape(-1, 3, 3), np.array(trans).reshape(-1, 3)
        )
        tool = frame.placement
        self._tool = _homogeneous(
            (post @ np.asarray(tool.rotation))[None], (post @ np.asarray(tool.translation))[None]
        )[0]
        self._all_joints = bool(np.array_equal(self.q_index, np.arange(self.nq)))
        # the first joint's origin does not depend on q (its parent is the root)
        self.root_origin = self._placement[0, :3, 3].copy() if chain else np.zeros(3)
        #: ``(q_index, placement, tool)``: the chain as the compiled kernels take it
        self.packed = (self.q_index, self._placement, self._tool)

    def _forward(
        self, q: np.ndarray, jacobian: bool
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
        compiled = kernels.get()
        # the kernel reads without bounds checks: other shapes get the NumPy code's errors
        if compiled is not None and q.ndim == 2 and q.shape[1] == self.nq:
            rot, pos, jac = compiled.chain_forward(
                np.ascontiguousarray(q), *self.packed, self.nq, jacobian
            )
            return rot, pos, jac if jacobian else None
        # each joint's frame as a (N, 3, 4) transform (see _joint_frame)
        n = q.shape[0]
        nj = len(self.joint_ids)
        turn = np.exp(-1j * q[:, self.q_index])  # (N, nj)
        frames = np.empty((nj, n, 3, 4))
        for k in range(nj):
            _joint_frame(frames[k], frames[k - 1] if k else None, self._placement[k], turn[:, k])
        last = frames[-1] if nj else np.broadcast_to(np.eye(4)[:3], (n, 3, 4))
        tool = (last.reshape(-1, 4) @ self._tool).reshape(n, 3, 4)
        tool_r, tool_p = tool[:, :, :3], tool[:, :, 3]
        if not jacobian:
            return tool_r, tool_p, None
        # columns of the Jacobian, component-major (3, nj, N): contiguous rows
        origin = frames[:nj, :, :, 3].transpose(2, 0, 1)
        z = frames[:nj, :, :, 2].transpose(2, 0, 1)
        d = tool_p.T[:, None, :] - origin
        cols = np.empty((6, nj, n))
        cols[0] = z[1] * d[2] - z[2] * d[1]
        cols[1] = z[2] * d[0] - z[0] * d[2]
        cols[2] = z[0] * d[1] - z[1] * d[0]
        cols[3:] = z
        if self._all_joints:
            return tool_r, tool_p, np.ascontiguousarray(cols.transpose(2, 0, 1))
        jac = np.zeros((n, 6, self.nq))
        jac[:, :, self.q_index] = cols.transpose(2, 0, 1)
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
        steps = np.concatenate([self._placement[1:, :3, 3], self._tool[None, :3, 3]])
        return np.linalg.norm(steps, axis=1)


class Frames(NamedTuple):
    """Frames of every joint for N configurations (:meth:`JointFrames.compute`).

    Attributes:
        rots: Per joint, rotations (N, 3, 3) (views of ``transforms``).
        poss: Per joint, origins (N, 3) [m] (views of ``transforms``).
        transforms: Per joint, the frames as (N, 3, 4) transforms ``[R | p]``
            (one matrix product places points: ``T.reshape(-1, 4) @ [x; 1]``).
    """

    rots: list[np.ndarray]
    poss: list[np.ndarray]
    transforms: list[np.ndarray]

    def take(self, rows: np.ndarray) -> Frames:
        """The frames of configurations ``rows`` only."""
        tfs = [t[rows] for t in self.transforms]
        return Frames([t[:, :, :3] for t in tfs], [t[:, :, 3] for t in tfs], tfs)


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
        rot = np.zeros((nj, 3, 3))
        trans = np.zeros((nj, 3))
        self._post = np.zeros((nj, 3, 3))  # R_a^T of each joint: rotated -> Pinocchio frame
        self._post[0] = np.eye(3)
        rot[0] = np.eye(3)
        for j in range(1, nj):
            axis = _joint_axis(model, j)
            ra = _z_to(axis)
            pre = self._post[self.parent[j]]
            placement = model.jointPlacements[j]
            rot[j] = pre @ np.asarray(placement.rotation) @ ra
            trans[j] = pre @ np.asarray(placement.translation)
            self._post[j] = ra.T
        self._placement = _homogeneous(rot, trans)
        #: ``(parent, q_index, placement)``: the joints as the compiled kernel takes them
        self.packed = (
            np.ascontiguousarray(self.parent, np.intp),
            np.ascontiguousarray(self.q_index, np.intp),
            self._placement,
        )

    def local(
        self, joint: int, rot: np.ndarray, trans: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]:
        """A placement in Pinocchio's frame of ``joint`` in the rotated convention."""
        post = self._post[joint]
        return post @ rot, post @ trans

    def compute(self, q: np.ndarray, libm: bool = False) -> Frames:
        """Frames of every joint (index 0: the universe).

        Args:
            q: Configurations (N, nq) [rad].
            libm: The compiled path takes the angles' cosines and sines from
                NumPy's ``cos`` and ``sin`` (libm), not from ``cos_sin`` (an ulp
                or two apart): the frames of the NumPy code to the bit, for the
                decisions that use them without a margin (coal's answer for the
                carried object, a point in the mesh object).

        Returns:
            The :class:`Frames`: per joint, rotations (N, 3, 3) in the rotated
            convention and origins (N, 3) [m], base frame, and both as (N, 3, 4)
            transforms.
        """
        q = np.asarray(q, dtype=float)
        n = q.shape[0]
        compiled = kernels.get()
        # the kernel reads without bounds checks: other shapes get the NumPy code's errors
        if compiled is not None and q.ndim == 2 and q.shape[1] == self.njoints - 1:
            cos_sin = (np.cos(q), np.sin(q)) if libm else compiled.cos_sin(q)
            frames = compiled.joint_frames(*cos_sin, *self.packed)
        else:
            turn = np.exp(-1j * q)
            frames = np.empty((self.njoints, n, 3, 4))  # (N, 3, 4) transforms, see _joint_frame
            frames[0] = np.eye(4)[:3]
            for j in range(1, self.njoints):
                p = self.parent[j]
                cur = frames[j]
                parent = frames[p] if p else None
                _joint_frame(cur, parent, self._placement[j], turn[:, self.q_index[j]])
        tfs = list(frames)
        return Frames([t[:, :, :3] for t in tfs], [t[:, :, 3] for t in tfs], tfs)
