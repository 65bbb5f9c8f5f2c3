"""The ``tool`` section of a robot spec: poses, shapes and fingers as frozen pydantic models.

The section's YAML is described in :mod:`gcm_pipeline.robot.tool`. Its models
follow the run config's conventions (:mod:`gcm_pipeline.config.sections`):
unknown keys are forbidden, numbers are strict (``true`` is no number, a
string is none), lengths, positions, the opening and a mesh's scale are at
most :data:`~gcm_pipeline.bounds.MAX_LENGTH` (1,000 m, or a factor) in
magnitude. Errors are reported by :func:`gcm_pipeline.config.validation.describe`.

:func:`build_tool` turns a validated :class:`ToolSection` into the
:class:`~gcm_pipeline.robot.tool.ToolSpec` the robot layer takes, resolving
mesh paths against the spec's folder; :func:`check_tool_files` then checks
that those files exist, which validation does not look at.
"""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Any, Literal

import numpy as np
from pydantic import (
    AfterValidator,
    BaseModel,
    BeforeValidator,
    ConfigDict,
    Field,
    Strict,
    ValidationError,
    model_validator,
)
from scipy.spatial.transform import Rotation

from gcm_pipeline.config.sections import Length, NonNegLength, Point3, PositiveLength
from gcm_pipeline.config.validation import describe
from gcm_pipeline.errors import RobotSpecError, clip
from gcm_pipeline.robot.tool import ToolShape, ToolSpec

__all__ = [
    "SHAPES",
    "Fingers",
    "PoseSpec",
    "ShapeSpec",
    "ToolSection",
    "build_tool",
    "check_tool_files",
    "parse_pose",
    "parse_tool",
    "spec_special",
]

#: Shape kinds of a tool.
SHAPES = ("box", "cylinder", "capsule", "sphere", "mesh")
#: Keys of a shape that give its dimensions, per kind, and how they read in messages.
_DIMS = {
    "box": ("size",),
    "cylinder": ("radius", "length"),
    "capsule": ("radius", "length"),
    "sphere": ("radius",),
    "mesh": ("mesh",),
}
_DIM_HINTS = {
    "size": "size: [x, y, z] [m]",
    "radius": "radius [m]",
    "length": "length [m]",
    "mesh": "mesh: <file path>",
}
_ROTATIONS = ("rpy", "rpy_deg", "quat", "matrix")
_RIGID_TOL = 1e-6
_DEFAULT_COLOR = (0.25, 0.25, 0.28, 1.0)

Text = Annotated[str, Strict()]
Name = Annotated[str, Strict(), Field(min_length=1)]
#: A colour channel in [0, 1].
Unit = Annotated[float, Strict(), Field(ge=0, le=1, allow_inf_nan=False)]


def _quat_is_unit(q: tuple[float, float, float, float]) -> tuple[float, float, float, float]:
    w, x, y, z = q
    norm = float(np.sqrt(w * w + x * x + y * y + z * z))
    if abs(norm - 1.0) > _RIGID_TOL:
        raise ValueError(f"[w, x, y, z] has norm {norm:.6g}, not 1: not a rotation")
    return q


def _rigid_matrix(rows: tuple[tuple[float, ...], ...]) -> tuple[tuple[float, ...], ...]:
    if len(rows) != 4 or any(len(r) != 4 for r in rows):
        raise ValueError(f"expected 4 rows of 4 numbers, got {clip([list(r) for r in rows])}")
    m = np.array(rows, dtype=float)
    rot = m[:3, :3]
    err = float(np.abs(rot.T @ rot - np.eye(3)).max())
    det = float(np.linalg.det(rot))
    if err > _RIGID_TOL or det <= 0:
        raise ValueError(
            "not a rigid transform: its rotation part is not orthonormal with determinant +1 "
            f"(max |R^T R - I| = {err:.3g}, det = {det:.3g})"
        )
    if np.abs(m[3] - [0, 0, 0, 1]).max() > _RIGID_TOL:
        raise ValueError(f"not a rigid transform: last row {m[3].tolist()}, not [0, 0, 0, 1]")
    return rows


def _listed(value: Any) -> Any:
    """A single number as a list of one (``scale: 0.001``)."""
    if isinstance(value, (int, float)) and not isinstance(value, bool):
        return [value]
    return value


def _one_or_three(scale: tuple[float, ...]) -> tuple[float, ...]:
    if len(scale) not in (1, 3):
        raise ValueError(f"give one number or three, got {len(scale)}: {clip(list(scale))}")
    return scale


def _rgba(color: tuple[float, ...]) -> tuple[float, ...]:
    if len(color) not in (3, 4):
        raise ValueError(f"expected [r, g, b] or [r, g, b, a] in [0, 1], got {clip(list(color))}")
    return color


def _nonzero(axis: tuple[float, float, float]) -> tuple[float, float, float]:
    if np.linalg.norm(axis) < 1e-9:
        raise ValueError(f"must not be zero, got {list(axis)}")
    return axis


Quat = Annotated[tuple[Length, Length, Length, Length], AfterValidator(_quat_is_unit)]
Matrix = Annotated[tuple[tuple[Length, ...], ...], AfterValidator(_rigid_matrix)]
Scale = Annotated[
    tuple[PositiveLength, ...], BeforeValidator(_listed), AfterValidator(_one_or_three)
]
Color = Annotated[tuple[Unit, ...], AfterValidator(_rgba)]


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


class PoseSpec(_Strict):
    """A rigid pose: ``xyz`` [m] and at most one rotation.

    The rotation is ``rpy`` [rad], ``rpy_deg``, ``quat`` ([w, x, y, z], unit) or
    ``matrix`` (4 x 4 rigid transform, with the position in it).
    """

    xyz: Point3 | None = None
    rpy: Point3 | None = None
    rpy_deg: Point3 | None = None
    quat: Quat | None = None
    matrix: Matrix | None = None

    @model_validator(mode="after")
    def _one_rotation(self) -> PoseSpec:
        given = [k for k in _ROTATIONS if getattr(self, k) is not None]
        if len(given) > 1:
            raise ValueError(f"give one of {', '.join(given)}, not several")
        if self.matrix is not None and self.xyz is not None:
            raise ValueError("give xyz inside the matrix, not beside it")
        return self

    def transform(self) -> np.ndarray:
        """The pose as a rigid (4, 4) transform [m]."""
        if self.matrix is not None:
            m = np.array(self.matrix, dtype=float)
            m[3] = [0.0, 0.0, 0.0, 1.0]
            return m
        out = np.eye(4)
        if self.xyz is not None:
            out[:3, 3] = self.xyz
        if self.rpy is not None:
            out[:3, :3] = Rotation.from_euler("xyz", self.rpy).as_matrix()
        elif self.rpy_deg is not None:
            out[:3, :3] = Rotation.from_euler("xyz", self.rpy_deg, degrees=True).as_matrix()
        elif self.quat is not None:
            w, x, y, z = self.quat
            out[:3, :3] = Rotation.from_quat([x, y, z, w]).as_matrix()
        return out


class ShapeSpec(PoseSpec):
    """One shape of a tool: its kind, dimensions [m], pose in the tool base frame, finger tag."""

    name: Text = ""
    shape: Literal["box", "cylinder", "capsule", "sphere", "mesh"]
    size: tuple[PositiveLength, PositiveLength, PositiveLength] | None = None
    radius: PositiveLength | None = None
    length: PositiveLength | None = None
    mesh: Name | None = None
    scale: Scale = (1.0,)
    finger: Literal["left", "right"] | None = None
    color: Color | None = None

    @model_validator(mode="after")
    def _dimensions(self) -> ShapeSpec:
        missing = [k for k in _DIMS[self.shape] if getattr(self, k) is None]
        if missing:
            need = " and ".join(_DIM_HINTS[k] for k in missing)
            raise ValueError(f"shape {self.shape!r} needs {need}")
        return self

    def label(self, index: int) -> str:
        """The shape's name: given, or ``<kind>_<index in its list>``."""
        return self.name if "name" in self.model_fields_set else f"{self.shape}_{index}"


def _unique_names(shapes: list[ShapeSpec]) -> list[ShapeSpec]:
    names = [s.label(i) for i, s in enumerate(shapes)]
    dup = sorted({n for n in names if names.count(n) > 1})
    if dup:
        raise ValueError(f"shape names must be unique, repeated: {', '.join(dup)}")
    return shapes


Shapes = Annotated[list[ShapeSpec], AfterValidator(_unique_names)]


class Fingers(_Strict):
    """The fingers' opening [m] and closing axis (tool base frame)."""

    opening: NonNegLength
    axis: Annotated[Point3, AfterValidator(_nonzero)] = (0.0, 1.0, 0.0)


class ToolSection(_Strict):
    """A robot spec's ``tool`` (see :mod:`gcm_pipeline.robot.tool`)."""

    name: Text = "tool"
    description: Text | None = None
    flange: Name
    mount: PoseSpec | None = None
    tcp: PoseSpec | None = None
    fingers: Fingers | None = None
    color: Color | None = None
    # no collision shapes: a TCP only (the hand is not collision-checked)
    collision: Shapes | None = None
    visual: Annotated[Shapes, Field(min_length=1)] | None = None

    @model_validator(mode="after")
    def _fingers_tagged(self) -> ToolSection:
        tagged: list[str] = []
        for shapes in (self.collision or [], self.visual or []):
            tagged += [s.label(i) for i, s in enumerate(shapes) if s.finger is not None]
        tagged = list(dict.fromkeys(tagged))
        if self.fingers is not None and not tagged:
            raise ValueError(
                "fingers is given, but no shape is tagged 'finger: left' or 'finger: right'"
            )
        if self.fingers is None and tagged:
            raise ValueError(
                f"shapes {', '.join(tagged)} are fingers, but fingers is missing "
                "(give fingers: {opening: <m>})"
            )
        return self


class _ToolOnly(_Strict):
    tool: ToolSection


def spec_special(err: dict[str, Any], key: str, loc: list[Any]) -> str | None:
    """A robot spec's own wording: the flange, a shape kind, ``home`` and ``joint_limits``."""
    shown, kind = clip(err.get("input")), err["type"]
    if key.endswith("tool.flange") and kind in ("string_type", "missing", "too_short"):
        got = "" if kind == "missing" else f", got {shown}"
        return f"{key}: name the model frame the tool is mounted on (e.g. tool0){got}"
    if key.endswith(".shape") and kind == "missing":
        return f"{key}: missing; give one of {', '.join(sorted(SHAPES))}"
    if key == "home" and kind in ("dict_type", "list_type"):
        return f"home: expected {{joint: value}} or a list of values [rad], got {shown}"
    if len(loc) >= 2 and loc[0] == "joint_limits" and kind in ("too_long", "missing", "tuple_type"):
        return f"joint_limits.{loc[1]}: expected [lower, upper] [rad or m], got {shown}"
    return None


def _shape(spec: ShapeSpec, index: int, base: Path) -> ToolShape:
    size: tuple[float, ...] = ()
    mesh: Path | None = None
    scale = (1.0, 1.0, 1.0)
    if spec.shape == "box":
        assert spec.size is not None
        size = spec.size
    elif spec.shape in ("cylinder", "capsule"):
        assert spec.radius is not None and spec.length is not None
        size = (spec.radius, spec.length)
    elif spec.shape == "sphere":
        assert spec.radius is not None
        size = (spec.radius,)
    else:
        assert spec.mesh is not None
        mesh = Path(spec.mesh).expanduser()
        mesh = mesh if mesh.is_absolute() else base / mesh
        s = spec.scale
        scale = (s[0], s[0], s[0]) if len(s) == 1 else (s[0], s[1], s[2])
    color = None if spec.color is None else _color(spec.color)
    return ToolShape(
        spec.label(index), spec.shape, size, mesh, scale, spec.transform(), spec.finger, color
    )


def _color(c: tuple[float, ...]) -> tuple[float, float, float, float]:
    return (c[0], c[1], c[2], c[3] if len(c) == 4 else 1.0)


def build_tool(section: ToolSection, base: Path) -> ToolSpec:
    """The tool a validated section describes (mesh paths resolved against ``base``)."""
    collision = tuple(_shape(s, i, base) for i, s in enumerate(section.collision or []))
    visual = (
        collision
        if section.visual is None
        else tuple(_shape(s, i, base) for i, s in enumerate(section.visual))
    )
    opening: float | None = None
    axis = np.array([0.0, 1.0, 0.0])
    if section.fingers is not None:
        opening = section.fingers.opening
        axis = np.array(section.fingers.axis)
        axis = axis / np.linalg.norm(axis)
    return ToolSpec(
        name=section.name,
        description=section.description or "",
        flange=section.flange,
        mount=np.eye(4) if section.mount is None else section.mount.transform(),
        tcp=np.eye(4) if section.tcp is None else section.tcp.transform(),
        collision=collision,
        visual=visual,
        opening=opening,
        axis=axis,
        color=_DEFAULT_COLOR if section.color is None else _color(section.color),
    )


def check_tool_files(where: str, tool: ToolSpec) -> None:
    """Every mesh file of a tool exists and is not empty.

    Raises:
        RobotSpecError: ``<where>: tool.<list>[<i>].mesh: file '...' does not exist``.
    """
    lists = [("collision", tool.collision)]
    if tool.visual is not tool.collision:
        lists.append(("visual", tool.visual))
    for key, shapes in lists:
        for i, shape in enumerate(shapes):
            if shape.mesh is None:
                continue
            at = f"{where}: tool.{key}[{i}].mesh"
            if not shape.mesh.is_file():
                what = "is not a regular file" if shape.mesh.exists() else "does not exist"
                raise RobotSpecError(f"{at}: file {str(shape.mesh)!r} {what}")
            if shape.mesh.stat().st_size == 0:
                raise RobotSpecError(f"{at}: file {str(shape.mesh)!r} is empty")


def parse_tool(where: str, raw: Any, base: Path) -> ToolSpec:
    """Validate a spec's ``tool`` section on its own and build the tool.

    Args:
        where: What messages name first (``robot spec '<path>'``); keys follow as ``tool.<key>``.
        raw: The section as read from YAML.
        base: Folder that relative mesh paths resolve against.

    Raises:
        RobotSpecError: One line naming the key at fault: unknown keys (with the
            closest), a mesh file that is missing or empty, a pose that is not
            rigid, bad sizes, finger shapes without ``fingers`` (or the reverse).
    """
    data = {"tool": raw}
    try:
        section = _ToolOnly.model_validate(data).tool
    except ValidationError as exc:
        problem = describe(exc, data, _ToolOnly, special=spec_special, brackets=True)
        raise RobotSpecError(f"{where}: {problem.message}") from None
    tool = build_tool(section, base)
    check_tool_files(where, tool)
    return tool


def parse_pose(where: str, raw: Any) -> np.ndarray:
    """A pose mapping as a rigid (4, 4) transform (None: the identity).

    Args:
        where: What messages name first.
        raw: None or a mapping with ``xyz`` and at most one of ``rpy`` [rad],
            ``rpy_deg``, ``quat`` ([w, x, y, z]) or ``matrix`` (4 x 4).

    Raises:
        RobotSpecError: Unknown key, bad numbers, or a transform that is not
            rigid (a non-unit quaternion, a matrix whose rotation part is not
            orthonormal with determinant +1 or whose last row is not [0, 0, 0, 1]).
    """
    if raw is None:
        return np.eye(4)
    try:
        return PoseSpec.model_validate(raw).transform()
    except ValidationError as exc:
        problem = describe(exc, raw, PoseSpec, brackets=True)
        raise RobotSpecError(f"{where}: {problem.message}") from None
