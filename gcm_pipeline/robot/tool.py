"""The tool of a robot spec: a gripper for an arm that has none (read by config.robot_spec).

An arm such as the UR5 of example-robot-data ends in a bare flange. The spec's
``tool`` section mounts a hand on it, made of primitives or meshes, and defines
the grasp (TCP) frame that IK targets::

    grasp_frame: gripper_tcp           # the TCP frame the tool adds (a new frame name)
    tool:
      name: parallel_jaw_85            # free text
      flange: tool0                    # model frame the tool is mounted on
      mount: {xyz: [0, 0, 0], rpy_deg: [0, 0, 0]}   # tool base in the flange frame
      tcp: {xyz: [0, 0, 0.15]}         # grasp frame in the tool base frame
      fingers: {opening: 0.085, axis: [0, 1, 0]}     # optional, see below
      color: [0.25, 0.25, 0.28, 1.0]   # RGBA of the drawn tool
      collision:                       # list of shapes, poses in the tool base frame
        - {name: body, shape: box, size: [0.07, 0.095, 0.085], xyz: [0, 0, 0.0575]}
        - {name: finger_l, shape: box, size: [0.022, 0.012, 0.06], xyz: [0, 0.006, 0.13],
           finger: left}
        - {name: coupling, shape: cylinder, radius: 0.0375, length: 0.015, xyz: [0, 0, 0.0075]}
        - {name: cover, shape: mesh, mesh: cover.stl, scale: 0.001}
      visual: [...]                    # optional, same format; default: the collision shapes

Shapes: ``box`` (``size: [x, y, z]``), ``cylinder`` and ``capsule`` (``radius``,
``length``, axis z), ``sphere`` (``radius``), ``mesh`` (``mesh: path`` relative
to the spec file, ``scale``: a number or three). A pose is ``xyz`` [m] plus one
of ``rpy`` [rad], ``rpy_deg``, ``quat`` ([w, x, y, z], unit) or a ``matrix``
(4 x 4 rigid transform); each must be rigid.

A tool may be a TCP only: without ``collision`` (or with ``collision: []``) it
adds the grasp frame and nothing else. The hand is then not collision-checked
(only the arm's own links are), which the robot says in a warning when it is
built.

Lengths, positions, the opening and a mesh's scale are at most
:data:`~gcm_pipeline.bounds.MAX_LENGTH` (1,000 m, or a factor) in magnitude, as
in a run's config: coal's bounding volumes break on astronomic sizes.

Fingers: shapes tagged ``finger: left`` / ``finger: right`` are given closed
(touching at the tool's axis) and are moved by ``+opening / 2`` / ``-opening / 2``
along ``fingers.axis`` (tool base frame), like two symmetric prismatic finger
joints locked at the given opening. Convention for the TCP, as for the Panda's
``panda_hand_tcp``: z = approach, fingers closing along y, origin between the
fingertips, so grasp generators and imported grasp files fit every arm.

The tool is part of the robot: :meth:`Robot.build_geometry` returns its shapes
with the arm's, attached to the flange's joint, named ``tool/<name>``; the
collision checker treats them as the gripper (the contact tolerance applies to
them), scenes draw them.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from gcm_pipeline.errors import RobotSpecError
from gcm_pipeline.geometry.meshes import MeshReadError, read_mesh

__all__ = ["ToolShape", "ToolSpec", "shape_geometry"]


@dataclass(frozen=True, eq=False)
class ToolShape:
    """One shape of a tool.

    Attributes:
        name: Shape name (unique within its list).
        shape: ``box``, ``cylinder``, ``capsule``, ``sphere`` or ``mesh``.
        size: ``box``: (x, y, z); ``cylinder``/``capsule``: (radius, length);
            ``sphere``: (radius,) [m].
        mesh: Mesh file (``mesh`` shapes), resolved against the spec's folder.
        scale: Mesh scale per axis (3,).
        pose: Pose of the shape in the tool base frame (4, 4) [m], before the
            finger offset.
        finger: ``left``, ``right`` or None.
        color: RGBA or None (the tool's colour).
    """

    name: str
    shape: str
    size: tuple[float, ...] = ()
    mesh: Path | None = None
    scale: tuple[float, float, float] = (1.0, 1.0, 1.0)
    pose: np.ndarray = field(default_factory=lambda: np.eye(4))
    finger: str | None = None
    color: tuple[float, float, float, float] | None = None


@dataclass(frozen=True, eq=False)
class ToolSpec:
    """A validated tool section (see the module docstring).

    Attributes:
        name: Tool name.
        description: Free text.
        flange: Model frame the tool is mounted on.
        mount: Tool base in the flange frame (4, 4) [m].
        tcp: Grasp frame in the tool base frame (4, 4) [m].
        opening: Finger opening [m] or None (no finger shapes).
        axis: Closing axis of the fingers in the tool base frame (3,), unit.
        color: RGBA of the drawn tool.
        collision: Collision shapes (empty: a TCP only, the hand is not collision-checked).
        visual: Visual shapes (the collision shapes when the spec gives none).
    """

    name: str
    flange: str
    mount: np.ndarray
    tcp: np.ndarray
    collision: tuple[ToolShape, ...]
    visual: tuple[ToolShape, ...]
    description: str = ""
    opening: float | None = None
    axis: np.ndarray = field(default_factory=lambda: np.array([0.0, 1.0, 0.0]))
    color: tuple[float, float, float, float] = (0.25, 0.25, 0.28, 1.0)

    def shape_pose(self, shape: ToolShape) -> np.ndarray:
        """Pose (4, 4) [m] of a shape in the tool base frame, fingers at ``opening``."""
        pose = np.array(shape.pose, dtype=float)
        if shape.finger is not None and self.opening is not None:
            sign = 1.0 if shape.finger == "left" else -1.0
            pose[:3, 3] += sign * 0.5 * self.opening * self.axis
        return pose

    def __repr__(self) -> str:
        return (
            f"ToolSpec({self.name!r}, flange={self.flange!r}, "
            f"tcp_xyz={np.round(self.tcp[:3, 3], 4).tolist()}, opening={self.opening}, "
            f"collision={[s.name for s in self.collision]})"
        )


def shape_geometry(shape: ToolShape, where: str) -> Any:
    """The coal geometry of a tool shape, in the shape's frame.

    Raises:
        RobotSpecError: A mesh file coal cannot read, one without triangles or with a
            vertex that is not finite.
    """
    import coal

    if shape.shape == "box":
        return coal.Box(*shape.size)
    if shape.shape == "cylinder":
        return coal.Cylinder(*shape.size)
    if shape.shape == "capsule":
        return coal.Capsule(*shape.size)
    if shape.shape == "sphere":
        return coal.Sphere(shape.size[0])
    assert shape.mesh is not None
    try:
        return read_mesh(shape.mesh, shape.scale)
    except MeshReadError as exc:
        raise RobotSpecError(f"{where}.mesh: {exc}") from exc
