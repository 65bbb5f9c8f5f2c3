"""Robot specs and their tools: YAML into the plain spec objects a :class:`Robot` is built from.

A robot spec is a small YAML file (``gcm_pipeline/robot/specs/<name>.yaml``)::

    name: panda                          # required
    description: Franka Panda            # optional, free text
    model:                               # required: exactly one source
      example_robot_data: panda          #   a loader name of example-robot-data
      # or robot_descriptions: ur10e_description   # a robot_descriptions module
      # or urdf: path.urdf               #   a URDF (relative paths: to the spec file)
      #    srdf: path.srdf               #   optional (disabled collision pairs)
      #    package_dirs: [dir, ...]      #   optional, resolves package:// URIs; the
      #                                  #   URDF's folder and its parents are tried after
    grasp_frame: panda_hand_tcp          # required: frame whose pose IK targets
    locked_joints: {joint: value}        # optional: joints removed at this value [rad or m]
    home: {joint: value} | [values]      # optional: home configuration [rad] (default: middle)
    limit_margin: 0.1                    # optional: tighten every revolute range per side [rad]
                                         #   (default 0.1; 0: the model's full ranges)
    joint_limits: {joint: [lo, hi]}      # optional: ranges intersected with the model's [rad];
                                         #   a continuous joint's range (default [-2pi, 2pi])
    tool: {flange, mount, tcp, collision, ...}  # optional: a gripper for a bare flange;
                                         #   grasp_frame then names the TCP frame it adds
                                         #   (see gcm_pipeline.robot.tool)
    hand_links: [link, ...]              # optional: the hand's links (MoveIt's end-effector
                                         #   group), which may touch the object at a grasp;
                                         #   default: found from the model
                                         #   (see gcm_pipeline.robot.hand)
    drop_collision: [link, ...]          # optional: links whose collision geometry is not
                                         #   loaded (a safety box around the hand)

The ``tool`` section mounts a gripper on a bare flange and defines the grasp
(TCP) frame that IK targets::

    grasp_frame: gripper_tcp           # the TCP frame the tool adds (a new frame name)
    tool:
      name: parallel_jaw_85            # free text
      flange: tool0                    # model frame the tool is mounted on
      mount: {xyz: [0, 0, 0], rpy_deg: [0, 0, 0]}   # tool base in the flange frame
      tcp: {xyz: [0, 0, 0.15]}         # grasp frame in the tool base frame
      fingers: {opening: 0.085, axis: [0, 1, 0]}     # optional
      color: [0.25, 0.25, 0.28, 1.0]   # RGBA of the drawn tool
      collision: [{name: body, shape: box, size: [0.07, 0.095, 0.085], xyz: [0, 0, 0.0575]}]
      visual: [...]                    # optional, same format; default: the collision shapes

The shapes, poses and fingers are described in :mod:`gcm_pipeline.robot.tool`
(:class:`~gcm_pipeline.robot.tool.ToolSpec`); the section's models are in
:mod:`gcm_pipeline.config.tool_spec`. Lengths, positions, the opening and a
mesh's scale are at most :data:`~gcm_pipeline.bounds.MAX_LENGTH` (1,000 m, or
a factor) in magnitude, as in a run's config.

The file (read by :mod:`gcm_pipeline.safe_yaml`) is validated by
:class:`RobotSpecFile`, a frozen pydantic model with the run config's
conventions: unknown keys are forbidden, numbers are strict (``true`` or
``"0.1"`` is no number), strings are strings. :func:`build_spec` then makes
the :class:`~gcm_pipeline.robot.model.RobotSpec` the robot layer takes,
relative model and mesh paths resolved against the spec's folder, and the
files it names are checked to exist. Every problem is a
:class:`~gcm_pipeline.errors.RobotSpecError` of one line
``robot spec '<path>': <key>: <problem>`` worded by
:func:`~gcm_pipeline.config.validation.describe`, as for run configs and
studies (an unknown key names the closest and the valid keys); list indices
are written ``tool.collision[1].size``.
"""

from __future__ import annotations

import os
from importlib import resources
from pathlib import Path
from typing import Annotated, Any

from pydantic import AfterValidator, BaseModel, ConfigDict, Field, Strict, model_validator

from gcm_pipeline.config.gripper_spec import load_gripper, mount_gripper
from gcm_pipeline.config.sections import FiniteFloat, NonNegFloat
from gcm_pipeline.config.tool_spec import ToolSection, build_tool, check_tool_files, spec_special
from gcm_pipeline.config.validation import validated_file
from gcm_pipeline.errors import RobotSpecError, choice_error, clip
from gcm_pipeline.robot.model import Robot, RobotSpec
from gcm_pipeline.robot.model_files import model_files
from gcm_pipeline.safe_yaml import load_yaml, read_yaml_file

__all__ = [
    "ModelSource",
    "RobotSpecFile",
    "available_robots",
    "build_spec",
    "load_robot",
    "load_spec",
]

_SOURCES = ("example_robot_data", "robot_descriptions", "urdf")

Text = Annotated[str, Strict()]


def _ordered(limits: tuple[float, float]) -> tuple[float, float]:
    if not limits[0] < limits[1]:
        raise ValueError(f"needs lower < upper, got {list(limits)}")
    return limits


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


class ModelSource(_Strict):
    """A spec's ``model``: exactly one of a loader, a description or a URDF file."""

    example_robot_data: Text | None = None
    robot_descriptions: Text | None = None
    urdf: Text | None = None
    srdf: Text | None = None
    package_dirs: Text | list[Text] | None = None

    @model_validator(mode="after")
    def _one_source(self) -> ModelSource:
        given = [k for k in _SOURCES if getattr(self, k) is not None]
        if len(given) != 1:
            raise ValueError(
                f"needs exactly one of {', '.join(_SOURCES)}, got {', '.join(given) or 'none'}"
            )
        if self.robot_descriptions is not None and (self.srdf is not None or self.package_dirs):
            raise ValueError(
                "robot_descriptions brings its own SRDF and package folders; "
                "remove model.srdf / model.package_dirs (or use model.urdf)"
            )
        return self

    def folders(self) -> list[str]:
        """``package_dirs`` as a list (a single folder, or none)."""
        dirs = self.package_dirs or []
        return [dirs] if isinstance(dirs, str) else list(dirs)


class RobotSpecFile(_Strict):
    """A robot spec file, validated (see the module docstring)."""

    name: Text
    description: Text | None = None
    model: ModelSource
    grasp_frame: Text
    locked_joints: dict[Text, FiniteFloat] | None = None
    home: dict[Text, FiniteFloat] | list[FiniteFloat] | None = None
    limit_margin: NonNegFloat = RobotSpec.limit_margin
    joint_limits: (
        dict[Text, Annotated[tuple[FiniteFloat, FiniteFloat], AfterValidator(_ordered)]] | None
    ) = None
    tool: ToolSection | None = None
    hand_links: Annotated[list[Text], Field(min_length=1)] | None = None
    drop_collision: list[Text] | None = None


def _spec_dir() -> Any:
    return resources.files("gcm_pipeline") / "robot" / "specs"


def available_robots() -> list[str]:
    """Names of the robot specs shipped with the package (sorted)."""
    return sorted(
        p.name[: -len(".yaml")] for p in _spec_dir().iterdir() if p.name.endswith(".yaml")
    )


def load_spec(name_or_path: str | os.PathLike[str], tool: str | None = None) -> RobotSpec:
    """Read and validate a robot spec.

    Args:
        name_or_path: A shipped spec name (``"panda"``, ``"ur5"``) or a path
            to a YAML file.
        tool: ``robot.tool``: a registry gripper's name or a gripper YAML
            path, mounted instead of the spec's own tool
            (:func:`~gcm_pipeline.config.gripper_spec.mount_gripper`).

    Returns:
        The validated spec.

    Raises:
        RobotSpecError: Unknown name (lists the available specs), unreadable
            file, unknown key (names it and suggests the closest), bad value, or
            a file it names (model, mesh) that does not exist; one line
            ``robot spec '<path>': <key>: <problem>``.
        ConfigError: ``robot.tool: ...``: an unknown or invalid gripper, or a
            spec without a tool section (no bare flange).
    """
    path, raw = _read_spec_file(name_or_path)
    where = f"robot spec {str(path)!r}"
    spec_file = validated_file(raw, RobotSpecFile, where, RobotSpecError, spec_special)
    spec = build_spec(spec_file, path)
    if spec.tool is not None:
        check_tool_files(where, spec.tool)
    _check_model_files(where, spec)
    if tool is not None:
        spec = mount_gripper(spec, load_gripper(tool, "robot.tool"))
    return spec


def build_spec(spec: RobotSpecFile, path: Path) -> RobotSpec:
    """The :class:`RobotSpec` of a validated file; relative paths resolve against its folder."""
    base = path.parent

    def _resolve(p: str) -> Path:
        q = Path(p).expanduser()
        return q if q.is_absolute() else (base / q)

    model = spec.model
    home: dict[str, float] | tuple[float, ...] = (
        tuple(spec.home) if isinstance(spec.home, list) else dict(spec.home or {})
    )
    return RobotSpec(
        name=spec.name,
        description=spec.description or "",
        path=path,
        grasp_frame=spec.grasp_frame,
        example_robot_data=model.example_robot_data,
        robot_descriptions=model.robot_descriptions,
        urdf=None if model.urdf is None else _resolve(model.urdf),
        srdf=None if model.srdf is None else _resolve(model.srdf),
        package_dirs=tuple(_resolve(p) for p in model.folders()),
        locked_joints=dict(spec.locked_joints or {}),
        home=home,
        limit_margin=spec.limit_margin,
        joint_limits=dict(spec.joint_limits or {}),
        tool=None if spec.tool is None else build_tool(spec.tool, base),
        hand_links=None if spec.hand_links is None else tuple(spec.hand_links),
        drop_collision=tuple(spec.drop_collision or ()),
    )


def _read_spec_file(name_or_path: str | os.PathLike[str]) -> tuple[Path, Any]:
    """The spec's path and its YAML document: a shipped name or a file."""
    text = str(name_or_path)
    if isinstance(name_or_path, os.PathLike) or text.endswith((".yaml", ".yml")) or os.sep in text:
        path = Path(text).expanduser()
        try:
            found = path.is_file()
        except (OSError, ValueError):
            found = False
        if not found:
            raise RobotSpecError(f"robot spec file {clip(text)} does not exist")
        raw = read_yaml_file(path, "robot spec", RobotSpecError)
        path = path.resolve()
    else:
        names = available_robots()
        if text not in names:  # (no file lookup: a name of 300 characters is no file name)
            raise choice_error(RobotSpecError, "robot", text, names)
        res = _spec_dir() / f"{text}.yaml"
        path = Path(str(res))
        raw = load_yaml(res.read_text(encoding="utf-8"), str(path), RobotSpecError)
    return path, raw


def _check_model_files(where: str, spec: RobotSpec) -> None:
    """The model a spec names exists.

    A loader of example-robot-data or robot_descriptions that loads the robot it
    is named after, or URDF/SRDF files.
    """
    if spec.example_robot_data is not None or spec.robot_descriptions is not None:
        urdf = model_files(spec)[0]
        if not urdf.is_file():  # pragma: no cover - a broken example-robot-data install
            raise RobotSpecError(f"{where}: the model's URDF {str(urdf)!r} does not exist")
        return
    files = [("model.urdf", spec.urdf), ("model.srdf", spec.srdf)]
    for key, file in files:
        if file is not None and not file.is_file():
            raise RobotSpecError(f"{where}: {key}: file {str(file)!r} does not exist")
    for d in spec.package_dirs:
        if not d.is_dir():
            raise RobotSpecError(f"{where}: model.package_dirs: {str(d)!r} is not a directory")


def load_robot(name_or_path: str | os.PathLike[str] | Robot, tool: str | None = None) -> Robot:
    """Load a robot from a shipped spec name or a spec file.

    Args:
        name_or_path: ``"panda"``, ``"ur5"`` (see :func:`available_robots`), a path
            to a YAML spec, or a :class:`Robot` (returned as is).
        tool: ``robot.tool``, a gripper mounted instead of the spec's tool (:func:`load_spec`).

    Returns:
        The robot.

    Raises:
        RobotSpecError: Unknown robot or invalid spec.
        FrameNotFoundError: The grasp frame is not in the model (lists close names).
    """
    if isinstance(name_or_path, Robot):
        return name_or_path
    return Robot(load_spec(name_or_path, tool))
