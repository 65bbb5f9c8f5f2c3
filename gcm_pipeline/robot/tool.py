"""The tool section of a robot spec: a gripper for an arm that has none.

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
:data:`~gcm_pipeline.limits.MAX_LENGTH` (1,000 m, or a factor) in magnitude, as
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

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from scipy.spatial.transform import Rotation

from gcm_pipeline.errors import RobotSpecError, unknown_choice
from gcm_pipeline.geometry.meshes import MeshReadError, read_mesh
from gcm_pipeline.limits import MAX_LENGTH

__all__ = ["ToolShape", "ToolSpec", "parse_pose", "parse_tool"]

_TOOL_KEYS = (
    "name",
    "description",
    "flange",
    "mount",
    "tcp",
    "fingers",
    "color",
    "collision",
    "visual",
)
_SHAPE_KEYS = (
    "name",
    "shape",
    "size",
    "radius",
    "length",
    "mesh",
    "scale",
    "finger",
    "color",
    "xyz",
    "rpy",
    "rpy_deg",
    "quat",
    "matrix",
)
_POSE_KEYS = ("xyz", "rpy", "rpy_deg", "quat", "matrix")
_SHAPES = ("box", "cylinder", "capsule", "sphere", "mesh")
_RIGID_TOL = 1e-6


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


def _section(where: str, raw: Any, keys: tuple[str, ...]) -> Mapping[str, Any]:
    """``raw`` as a mapping whose keys are all in ``keys`` (else a one-line error)."""
    if not isinstance(raw, Mapping):
        raise RobotSpecError(f"{where} must be a mapping with keys {', '.join(keys)}, got {raw!r}")
    for key in raw:
        if key not in keys:
            raise RobotSpecError(f"{where}: " + unknown_choice("key", key, keys))
    return raw


def _numbers(where: str, value: Any, n: int | None = None) -> tuple[float, ...]:
    if isinstance(value, (int, float)) and not isinstance(value, bool):
        value = [value]
    if not isinstance(value, Sequence) or isinstance(value, str):
        raise RobotSpecError(f"{where} must be a list of numbers, got {value!r}")
    out = []
    for v in value:
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not np.isfinite(v):
            raise RobotSpecError(f"{where} must hold finite numbers, got {value!r}")
        out.append(float(v))
    if n is not None and len(out) != n:
        raise RobotSpecError(f"{where} needs {n} numbers, got {len(out)}: {value!r}")
    big = next((v for v in out if abs(v) > MAX_LENGTH), None)
    if big is not None:
        raise RobotSpecError(
            f"{where}: {big:g} is beyond +-{MAX_LENGTH:g} (m, or a factor); a tool is "
            "metres across at most"
        )
    return tuple(out)


def _positive(where: str, value: Any) -> float:
    (v,) = _numbers(where, value, 1)
    if v <= 0:
        raise RobotSpecError(f"{where} must be > 0 [m], got {value!r}")
    return v


def parse_pose(where: str, raw: Any) -> np.ndarray:
    """A pose mapping as a rigid (4, 4) transform.

    Args:
        where: Spec location for messages (``robot spec '...': tool.tcp``).
        raw: None (identity) or a mapping with ``xyz`` and at most one of
            ``rpy`` [rad], ``rpy_deg``, ``quat`` ([w, x, y, z]) or ``matrix`` (4 x 4).

    Returns:
        (4, 4) transform [m].

    Raises:
        RobotSpecError: Unknown key, bad numbers, or a transform that is not
            rigid (a non-unit quaternion, a matrix whose rotation part is not
            orthonormal with determinant +1 or whose last row is not [0, 0, 0, 1]).
    """
    out = np.eye(4)
    if raw is None:
        return out
    raw = _section(where, raw, _POSE_KEYS)
    rot_keys = [k for k in ("rpy", "rpy_deg", "quat", "matrix") if k in raw]
    if len(rot_keys) > 1:
        raise RobotSpecError(f"{where}: give one of {', '.join(rot_keys)}, not several")
    if "matrix" in raw:
        if "xyz" in raw:
            raise RobotSpecError(f"{where}: give xyz inside the matrix, not beside it")
        rows = raw["matrix"]
        if not isinstance(rows, Sequence) or len(rows) != 4:
            raise RobotSpecError(f"{where}.matrix must be 4 rows of 4 numbers, got {rows!r}")
        m = np.array([_numbers(f"{where}.matrix[{i}]", r, 4) for i, r in enumerate(rows)])
        rot = m[:3, :3]
        err = float(np.abs(rot.T @ rot - np.eye(3)).max())
        if err > _RIGID_TOL or np.linalg.det(rot) <= 0:
            raise RobotSpecError(
                f"{where}.matrix is not a rigid transform: its rotation part is not orthonormal "
                f"with determinant +1 (max |R^T R - I| = {err:.3g}, det = {np.linalg.det(rot):.3g})"
            )
        if np.abs(m[3] - [0, 0, 0, 1]).max() > _RIGID_TOL:
            raise RobotSpecError(
                f"{where}.matrix is not a rigid transform: last row {m[3].tolist()}"
            )
        m[3] = [0.0, 0.0, 0.0, 1.0]
        return m
    if "xyz" in raw:
        out[:3, 3] = _numbers(f"{where}.xyz", raw["xyz"], 3)
    if "rpy" in raw:
        out[:3, :3] = Rotation.from_euler(
            "xyz", _numbers(f"{where}.rpy", raw["rpy"], 3)
        ).as_matrix()
    elif "rpy_deg" in raw:
        rpy = _numbers(f"{where}.rpy_deg", raw["rpy_deg"], 3)
        out[:3, :3] = Rotation.from_euler("xyz", rpy, degrees=True).as_matrix()
    elif "quat" in raw:
        w, x, y, z = _numbers(f"{where}.quat", raw["quat"], 4)
        norm = float(np.sqrt(w * w + x * x + y * y + z * z))
        if abs(norm - 1.0) > _RIGID_TOL:
            raise RobotSpecError(
                f"{where}.quat is not a rotation: [w, x, y, z] has norm {norm:.6g}, not 1"
            )
        out[:3, :3] = Rotation.from_quat([x, y, z, w]).as_matrix()
    return out


def _color(where: str, raw: Any) -> tuple[float, float, float, float]:
    c = _numbers(where, raw)
    if len(c) not in (3, 4) or min(c) < 0 or max(c) > 1:
        raise RobotSpecError(f"{where} must be [r, g, b] or [r, g, b, a] in [0, 1], got {raw!r}")
    return (c[0], c[1], c[2], c[3] if len(c) == 4 else 1.0)


def _shape(where: str, raw: Any, base: Path, index: int) -> ToolShape:
    raw = _section(where, raw, _SHAPE_KEYS)
    kind = raw.get("shape")
    if kind not in _SHAPES:
        raise RobotSpecError(f"{where}.shape: " + unknown_choice("shape", kind, _SHAPES))
    name = str(raw.get("name", f"{kind}_{index}"))
    size: tuple[float, ...] = ()
    mesh: Path | None = None
    scale = (1.0, 1.0, 1.0)
    if kind == "box":
        size = tuple(
            _positive(f"{where}.size", s) for s in _numbers(f"{where}.size", raw.get("size"), 3)
        )
    elif kind in ("cylinder", "capsule"):
        size = (
            _positive(f"{where}.radius", raw.get("radius")),
            _positive(f"{where}.length", raw.get("length")),
        )
    elif kind == "sphere":
        size = (_positive(f"{where}.radius", raw.get("radius")),)
    else:
        if not isinstance(raw.get("mesh"), str) or not raw["mesh"]:
            raise RobotSpecError(f"{where}.mesh: shape 'mesh' needs a mesh file path")
        mesh = Path(raw["mesh"]).expanduser()
        mesh = mesh if mesh.is_absolute() else base / mesh
        if not mesh.is_file():
            raise RobotSpecError(f"{where}.mesh: file {str(mesh)!r} does not exist")
        if mesh.stat().st_size == 0:
            raise RobotSpecError(f"{where}.mesh: file {str(mesh)!r} is empty")
        s = _numbers(f"{where}.scale", raw.get("scale", 1.0))
        if len(s) not in (1, 3) or min(s) <= 0:
            raise RobotSpecError(f"{where}.scale must be one or three numbers > 0, got {s!r}")
        scale = (s[0], s[0], s[0]) if len(s) == 1 else (s[0], s[1], s[2])
    finger = raw.get("finger")
    if finger not in (None, "left", "right"):
        raise RobotSpecError(
            f"{where}.finger: " + unknown_choice("finger", finger, ("left", "right"))
        )
    pose = parse_pose(where, {k: raw[k] for k in _POSE_KEYS if k in raw} or None)
    color = None if raw.get("color") is None else _color(f"{where}.color", raw["color"])
    return ToolShape(name, kind, size, mesh, scale, pose, finger, color)


def _shapes(where: str, raw: Any, base: Path, empty: bool = False) -> tuple[ToolShape, ...]:
    if raw is None and empty:
        return ()
    if not isinstance(raw, Sequence) or isinstance(raw, str) or (not raw and not empty):
        raise RobotSpecError(f"{where} must be a non-empty list of shapes, got {raw!r}")
    out = tuple(_shape(f"{where}[{i}]", item, base, i) for i, item in enumerate(raw))
    names = [s.name for s in out]
    dup = sorted({n for n in names if names.count(n) > 1})
    if dup:
        raise RobotSpecError(f"{where}: shape names must be unique, repeated: {', '.join(dup)}")
    return out


def parse_tool(where: str, raw: Any, base: Path) -> ToolSpec:
    """Validate a spec's ``tool`` section.

    Args:
        where: ``robot spec '<path>'`` (messages name ``tool.<key>`` after it).
        raw: The section as read from YAML.
        base: Folder that relative mesh paths resolve against.

    Returns:
        The tool.

    Raises:
        RobotSpecError: One line naming the key at fault: unknown keys, a mesh
            file that is missing or empty, a pose that is not rigid, bad sizes,
            finger shapes without ``fingers`` (or the reverse).
    """
    w = f"{where}: tool"
    raw = _section(w, raw, _TOOL_KEYS)
    flange = raw.get("flange")
    if not isinstance(flange, str) or not flange:
        raise RobotSpecError(
            f"{w}.flange: name the model frame the tool is mounted on (e.g. tool0)"
        )
    # no collision shapes: a TCP only (the hand is not collision-checked)
    collision = _shapes(f"{w}.collision", raw.get("collision"), base, empty=True)
    visual = collision if raw.get("visual") is None else _shapes(f"{w}.visual", raw["visual"], base)
    fingers = raw.get("fingers")
    opening: float | None = None
    axis = np.array([0.0, 1.0, 0.0])
    tagged = [s.name for s in (*collision, *visual) if s.finger is not None]
    if fingers is not None:
        fingers = _section(f"{w}.fingers", fingers, ("opening", "axis"))
        (opening,) = _numbers(f"{w}.fingers.opening", fingers.get("opening"), 1)
        if opening < 0:
            raise RobotSpecError(f"{w}.fingers.opening must be >= 0 [m], got {opening}")
        axis = np.array(_numbers(f"{w}.fingers.axis", fingers.get("axis", [0, 1, 0]), 3))
        if np.linalg.norm(axis) < 1e-9:
            raise RobotSpecError(f"{w}.fingers.axis must not be zero")
        axis = axis / np.linalg.norm(axis)
        if not tagged:
            raise RobotSpecError(
                f"{w}.fingers: no shape is tagged 'finger: left' or 'finger: right'"
            )
    elif tagged:
        raise RobotSpecError(
            f"{w}.fingers: missing, but shapes {', '.join(tagged)} are fingers (give an opening)"
        )
    color = (
        (0.25, 0.25, 0.28, 1.0) if raw.get("color") is None else _color(f"{w}.color", raw["color"])
    )
    return ToolSpec(
        name=str(raw.get("name", "tool")),
        description=str(raw.get("description", "") or ""),
        flange=flange,
        mount=parse_pose(f"{w}.mount", raw.get("mount")),
        tcp=parse_pose(f"{w}.tcp", raw.get("tcp")),
        collision=collision,
        visual=visual,
        opening=opening,
        axis=axis,
        color=color,
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
