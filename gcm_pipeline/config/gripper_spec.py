"""Gripper YAML files: the registry's definitions read into :class:`GripperSpec` objects.

One file per gripper, shipped in ``gcm_pipeline/grippers/<name>.yaml`` or the
user's own (``candidates.gripper: path/to/my_gripper.yaml``, ``robot.tool``)::

    name: robotiq_2f_85                # required; a shipped file's name is its stem
    description: Robotiq 2F-85         # optional, free text
    aliases: [robotiq85]               # other names grasp files give it
    kind: parallel_jaw                 # or suction (no fingers)
    base_to_tcp: 0.1303                # the TCP along the base frame's +z [m]
    closing_axis: x                    # base frame axis the fingers close along (x or y)
    max_width: 0.085                   # parallel_jaw: largest opening [m]
    finger_depth: 0.035                # parallel_jaw: pad depth along the approach [m]
    hand:                              # parallel_jaw: the antipodal sampler's hand [m]
      {finger_length, finger_tip, finger_thickness, finger_width, palm_size: [x, y, z]}
    mount: {xyz: [0, 0, 0]}            # the gripper base in an arm's flange frame
    color: [0.2, 0.2, 0.25, 1.0]       # RGBA of the drawn tool
    collision: [shapes]                # required, the robot spec tool's shape format,
    visual: [shapes]                   #   poses in the base frame, fingers given closed
    robot_model: {hand_frame, finger_joints}   # a hand that robot models carry (the Panda)

The base frame is the grasp synthesiser's (ACRONYM, GraspGen, Contact-GraspNet):
origin at the hand's base, z = approach. The robot's grasp frame (z = approach,
fingers closing along its y, origin at the TCP) is that frame moved
``base_to_tcp`` along z and turned so that its y is ``closing_axis``
(:meth:`GripperSpec.to_tool`). Shapes (``box``, ``cylinder``, ``capsule``,
``sphere``, ``mesh``) are those of a robot spec's ``tool`` section
(:mod:`gcm_pipeline.config.tool_spec`); a ``parallel_jaw`` gripper tags its
finger shapes ``finger: left`` / ``right``, given closed and opened to
``max_width`` along ``closing_axis`` on an arm.

Validation is strict as for run configs and robot specs: unknown keys are
refused (naming the closest), sizes are positive; each problem is a
:class:`~gcm_pipeline.errors.ConfigError` of one line
``<key>: gripper '<path>': <key in the file>: <problem>``.
"""

from __future__ import annotations

import dataclasses
from functools import cache
from pathlib import Path
from typing import TYPE_CHECKING, Annotated, Any, Literal

from pydantic import BaseModel, ConfigDict, Field, Strict, model_validator

from gcm_pipeline.config.sections import NonNegLength, PositiveLength
from gcm_pipeline.config.tool_spec import (
    Color,
    Fingers,
    PoseSpec,
    Shapes,
    ToolSection,
    build_tool,
    check_tool_files,
    spec_special,
)
from gcm_pipeline.config.validation import validated_file
from gcm_pipeline.errors import ConfigError, RobotSpecError, choice_error, clip
from gcm_pipeline.safe_yaml import load_yaml, read_yaml_file
from gcm_pipeline.sources.grippers import (
    GripperSpec,
    is_gripper_path,
    registry_dir,
    shipped_grippers,
)

if TYPE_CHECKING:  # the robot layer loads Pinocchio: configs read without it
    from gcm_pipeline.robot.model import RobotSpec

__all__ = [
    "GripperFile",
    "HandSizes",
    "gripper_registry",
    "load_gripper",
    "mount_gripper",
    "parse_gripper",
]

Text = Annotated[str, Strict()]
Name = Annotated[str, Strict(), Field(min_length=1)]
_AXES = {"x": (1.0, 0.0, 0.0), "y": (0.0, 1.0, 0.0)}


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


class HandSizes(_Strict):
    """The antipodal sampler's hand, in the robot's grasp frame [m].

    ``finger_length``: from the TCP back to the palm; ``finger_tip``: how far
    the fingertips reach past the TCP; ``finger_thickness`` along the closing
    axis, ``finger_width`` across; ``palm_size``: the palm box (x across,
    y along the closing axis, z along the approach).
    """

    finger_length: PositiveLength
    finger_tip: NonNegLength
    finger_thickness: PositiveLength
    finger_width: PositiveLength
    palm_size: tuple[PositiveLength, PositiveLength, PositiveLength]


class RobotHand(_Strict):
    """A hand that robot models carry: its base link and finger joints (MoveIt postures)."""

    hand_frame: Name
    finger_joints: tuple[Name, ...] = ()


class GripperFile(_Strict):
    """A gripper YAML file, validated (see the module docstring)."""

    name: Name
    description: Text = ""
    aliases: tuple[Name, ...] = ()
    kind: Literal["parallel_jaw", "suction"] = "parallel_jaw"
    base_to_tcp: NonNegLength
    closing_axis: Literal["x", "y"] = "x"
    max_width: PositiveLength | None = None
    finger_depth: PositiveLength | None = None
    hand: HandSizes | None = None
    robot_model: RobotHand | None = None
    mount: PoseSpec | None = None
    color: Color | None = None
    collision: Annotated[Shapes, Field(min_length=1)]
    visual: Annotated[Shapes, Field(min_length=1)] | None = None

    @model_validator(mode="after")
    def _kind_keys(self) -> GripperFile:
        fingers = [
            s.label(i)
            for shapes in (self.collision, self.visual or [])
            for i, s in enumerate(shapes)
            if s.finger is not None
        ]
        if self.kind == "parallel_jaw":
            missing = [k for k in ("max_width", "finger_depth", "hand") if getattr(self, k) is None]
            if missing:
                raise ValueError(f"a parallel_jaw gripper needs {', '.join(missing)}")
            if not fingers:
                raise ValueError(
                    "a parallel_jaw gripper tags its finger shapes 'finger: left' and "
                    "'finger: right'; none is tagged"
                )
        else:
            given = [k for k in ("max_width", "finger_depth", "hand") if getattr(self, k)]
            if given or fingers:
                what = ", ".join(given + [f"finger shape {n}" for n in fingers])
                raise ValueError(f"a suction gripper has no fingers; remove {what}")
        return self


def _spec(f: GripperFile, path: Path) -> GripperSpec:
    """The :class:`GripperSpec` of a validated file (mesh paths against its folder)."""
    hand = f.hand
    spec = GripperSpec(
        name=f.name,
        description=f.description,
        max_width=f.max_width or 0.0,
        finger_depth=f.finger_depth or 0.0,
        base_to_tcp=f.base_to_tcp,
        kind=f.kind,
        closing_axis=f.closing_axis,
        finger_joints=() if f.robot_model is None else f.robot_model.finger_joints,
        hand_frame="" if f.robot_model is None else f.robot_model.hand_frame,
        aliases=tuple(a.lower() for a in f.aliases),
        path=path,
        **({} if hand is None else hand.model_dump()),
    )
    rows = tuple(tuple(float(v) for v in row) for row in spec.to_tool("base"))
    section = ToolSection(
        name=f.name,
        description=f.description or None,
        flange="flange",  # the arm's: set when mounted (mount_gripper)
        mount=f.mount,
        tcp=PoseSpec(matrix=rows),
        fingers=None
        if f.kind == "suction"
        else Fingers(opening=f.max_width, axis=_AXES[f.closing_axis]),
        color=f.color,
        collision=f.collision,
        visual=f.visual,
    )
    return dataclasses.replace(spec, tool=build_tool(section, path.parent))


def parse_gripper(raw: Any, path: Path, where: str) -> GripperSpec:
    """Validate a gripper file's document and build its spec.

    Args:
        raw: The document as read from YAML.
        path: The file (mesh paths resolve against its folder).
        where: What messages name first (``candidates.gripper: gripper '<path>'``).

    Raises:
        ConfigError: One line naming the key at fault.
    """
    f = validated_file(raw, GripperFile, where, ConfigError, spec_special)
    spec = _spec(f, path)
    assert spec.tool is not None
    try:
        check_tool_files(where, spec.tool)
    except RobotSpecError as exc:  # the same line, as a config problem
        raise ConfigError(str(exc).replace(f"{where}: tool.", f"{where}: ", 1)) from None
    return spec


@cache
def _shipped(name: str) -> GripperSpec:
    res = registry_dir() / f"{name}.yaml"
    path = Path(str(res))
    where = f"gripper {str(path)!r}"
    raw = load_yaml(res.read_text(encoding="utf-8"), str(path), ConfigError)
    spec = parse_gripper(raw, path, where)
    if spec.name != name:
        raise ConfigError(f"{where}: name: {spec.name!r} is not the file's name {name!r}")
    return spec


def gripper_registry() -> dict[str, GripperSpec]:
    """The shipped grippers by name (read once)."""
    return {name: _shipped(name) for name in shipped_grippers()}


def load_gripper(name_or_path: str | Path, key: str = "candidates.gripper") -> GripperSpec:
    """A shipped gripper by name, or a gripper YAML file.

    Args:
        name_or_path: A shipped name (``robotiq_2f_85``) or a path (ends in
            ``.yaml``/``.yml`` or has a ``/``).
        key: The config key that names it (for messages).

    Raises:
        ConfigError: An unknown name (lists the shipped grippers), a missing or
            unreadable file, or an invalid one (one line naming the key at fault).
    """
    text = str(name_or_path)
    if not (isinstance(name_or_path, Path) or is_gripper_path(text)):
        names = shipped_grippers()
        if text not in names:
            raise choice_error(ConfigError, "gripper", text, names, key=key, prefix=f"{key}: ")
        return _shipped(text)
    path = Path(text).expanduser()
    try:
        found = path.is_file()
    except (OSError, ValueError):
        found = False
    if not found:
        raise ConfigError(
            f"{key}: gripper file {clip(text)} does not exist (or give one of: "
            f"{', '.join(shipped_grippers())})",
            key=key,
            value=text,
        )
    raw = read_yaml_file(path, f"{key}: gripper", ConfigError)
    return parse_gripper(raw, path.resolve(), f"{key}: gripper {str(path)!r}")


def mount_gripper(spec: RobotSpec, gripper: GripperSpec, key: str = "robot.tool") -> RobotSpec:
    """The robot spec with ``gripper`` as its tool, on the flange of the spec's own tool.

    Raises:
        ConfigError: The spec has no ``tool`` section (its hand is part of its
            model, like the Panda's): there is no bare flange to mount on.
    """
    if spec.tool is None:
        raise ConfigError(
            f"{key}: robot {spec.name!r} (grasp frame {spec.grasp_frame!r}) has no tool "
            f"section, so no flange to mount {gripper.name!r} on: robot.tool replaces the tool "
            "a spec mounts on a bare flange (e.g. ur5's on tool0); a hand that is part of the "
            "model (the Panda's) is not replaced, a bare arm's spec names its flange in a tool "
            "section",
            key=key,
            value=gripper.name,
        )
    assert gripper.tool is not None
    tool = dataclasses.replace(gripper.tool, flange=spec.tool.flange)
    return dataclasses.replace(spec, tool=tool)
