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
(:class:`~gcm_pipeline.robot.tool.ToolSpec`). Lengths, positions, the opening
and a mesh's scale are at most :data:`~gcm_pipeline.bounds.MAX_LENGTH`
(1,000 m, or a factor) in magnitude, as in a run's config.

Every problem is a :class:`~gcm_pipeline.errors.RobotSpecError` of one line
naming the spec file and the key (an unknown key in the words of
:func:`~gcm_pipeline.config.validation.unknown_key`, as for run configs and
studies); the file is read by :mod:`gcm_pipeline.safe_yaml`.
"""

from __future__ import annotations

import os
from collections.abc import Mapping, Sequence
from importlib import resources
from pathlib import Path
from typing import Any

import numpy as np
from scipy.spatial.transform import Rotation

from gcm_pipeline.bounds import MAX_LENGTH
from gcm_pipeline.config.validation import unknown_key
from gcm_pipeline.errors import RobotSpecError, clip, unknown_choice
from gcm_pipeline.robot.model import Robot, RobotSpec
from gcm_pipeline.robot.model_files import model_files
from gcm_pipeline.robot.tool import ToolShape, ToolSpec
from gcm_pipeline.safe_yaml import load_yaml, read_yaml_file

__all__ = [
    "available_robots",
    "load_robot",
    "load_spec",
    "parse_pose",
    "parse_tool",
]

_SPEC_KEYS = (
    "name",
    "description",
    "model",
    "grasp_frame",
    "locked_joints",
    "home",
    "limit_margin",
    "joint_limits",
    "tool",
)
_MODEL_KEYS = ("example_robot_data", "robot_descriptions", "urdf", "srdf", "package_dirs")

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


def _spec_dir() -> Any:
    return resources.files("gcm_pipeline") / "robot" / "specs"


def available_robots() -> list[str]:
    """Names of the robot specs shipped with the package (sorted)."""
    return sorted(
        p.name[: -len(".yaml")] for p in _spec_dir().iterdir() if p.name.endswith(".yaml")
    )


def _check_keys(where: str, section: str, data: Mapping[str, Any], valid: Sequence[str]) -> None:
    """Every key of ``data`` is in ``valid`` (else ``<where>: unknown key '<section.key>' ...``)."""
    for key in data:
        if key not in valid:
            prefix = f"{where}: " if where else ""
            raise RobotSpecError(prefix + unknown_key(section, key, valid))


def _number(where: str, key: str, value: Any) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise RobotSpecError(f"{where}: {key} must be a number, got {clip(value)}")
    if not np.isfinite(value):
        raise RobotSpecError(f"{where}: {key} must be finite, got {clip(value)}")
    return float(value)


def _mapping(where: str, key: str, value: Any) -> Mapping[str, Any]:
    if value is None:
        return {}
    if not isinstance(value, Mapping):
        raise RobotSpecError(f"{where}: {key} must be a mapping, got {clip(value)}")
    return value


def load_spec(name_or_path: str | os.PathLike[str]) -> RobotSpec:
    """Read and validate a robot spec.

    Args:
        name_or_path: A shipped spec name (``"panda"``, ``"ur5"``) or a path
            to a YAML file.

    Returns:
        The validated spec.

    Raises:
        RobotSpecError: Unknown name (lists the available specs), unreadable
            file, unknown key (names it and suggests the closest) or bad value.
    """
    path, raw = _read_spec_file(name_or_path)
    where = f"robot spec {str(path)!r}"
    if not isinstance(raw, Mapping):
        raise RobotSpecError(f"{where}: expected a mapping at the top level, got {clip(raw)}")
    _check_keys(where, "", raw, _SPEC_KEYS)
    for key in ("name", "model", "grasp_frame"):
        if key not in raw:
            raise RobotSpecError(f"{where}: missing required key {key!r}")
    if not isinstance(raw["name"], str) or not isinstance(raw["grasp_frame"], str):
        raise RobotSpecError(f"{where}: name and grasp_frame must be strings")
    model = _mapping(where, "model", raw["model"])
    _check_keys(where, "model", model, _MODEL_KEYS)
    erd_name = model.get("example_robot_data")
    rd_name = model.get("robot_descriptions")
    urdf = model.get("urdf")
    sources = ("example_robot_data", "robot_descriptions", "urdf")
    given = [k for k in sources if model.get(k) is not None]
    if len(given) != 1:
        raise RobotSpecError(
            f"{where}: model needs exactly one of {', '.join(sources)}, got "
            f"{', '.join(given) or 'none'}"
        )
    for key in ("example_robot_data", "robot_descriptions", "urdf", "srdf"):
        if model.get(key) is not None and not isinstance(model[key], str):
            raise RobotSpecError(f"{where}: model.{key} must be a string, got {clip(model[key])}")
    if rd_name is not None and (model.get("srdf") is not None or model.get("package_dirs")):
        raise RobotSpecError(
            f"{where}: model.robot_descriptions brings its own SRDF and package folders; "
            "remove model.srdf / model.package_dirs (or use model.urdf)"
        )
    base = path.parent

    def _resolve(p: Any) -> Path:
        q = Path(str(p)).expanduser()
        return q if q.is_absolute() else (base / q)

    locked = {
        str(k): _number(where, f"locked_joints.{k}", v)
        for k, v in _mapping(where, "locked_joints", raw.get("locked_joints")).items()
    }
    home = _home_of(where, raw.get("home"))
    margin = _number(where, "limit_margin", raw.get("limit_margin", RobotSpec.limit_margin))
    if margin < 0:
        raise RobotSpecError(f"{where}: limit_margin must be >= 0, got {margin}")
    limits = _joint_limits_of(where, raw.get("joint_limits"))
    pkg = model.get("package_dirs") or []
    if isinstance(pkg, str):
        pkg = [pkg]
    if not isinstance(pkg, (list, tuple)) or not all(isinstance(d, str) for d in pkg):
        raise RobotSpecError(
            f"{where}: model.package_dirs must be a folder or a list of folders, got {clip(pkg)}"
        )
    spec = RobotSpec(
        name=raw["name"],
        description=str(raw.get("description", "") or ""),
        path=path,
        grasp_frame=raw["grasp_frame"],
        example_robot_data=None if erd_name is None else str(erd_name),
        robot_descriptions=None if rd_name is None else str(rd_name),
        urdf=None if urdf is None else _resolve(urdf),
        srdf=None if model.get("srdf") is None else _resolve(model["srdf"]),
        package_dirs=tuple(_resolve(p) for p in pkg),
        locked_joints=locked,
        home=home,
        limit_margin=margin,
        joint_limits=limits,
        tool=None if raw.get("tool") is None else parse_tool(where, raw["tool"], base),
    )
    _check_model_files(where, spec)
    return spec


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
            raise RobotSpecError(unknown_choice("robot", text, names))
        res = _spec_dir() / f"{text}.yaml"
        path = Path(str(res))
        raw = load_yaml(res.read_text(encoding="utf-8"), str(path), RobotSpecError)
    return path, raw


def _home_of(where: str, home_raw: Any) -> Mapping[str, float] | tuple[float, ...]:
    """``home``: joint name -> value, or one value per joint [rad]; empty when not given."""
    home: Mapping[str, float] | tuple[float, ...]
    if home_raw is None:
        home = {}
    elif isinstance(home_raw, (list, tuple)):
        home = tuple(_number(where, f"home[{i}]", v) for i, v in enumerate(home_raw))
    else:
        home = {
            str(k): _number(where, f"home.{k}", v)
            for k, v in _mapping(where, "home", home_raw).items()
        }
    return home


def _joint_limits_of(where: str, raw_limits: Any) -> dict[str, tuple[float, float]]:
    """``joint_limits``: joint name -> (lower, upper) [rad or m], lower < upper."""
    limits: dict[str, tuple[float, float]] = {}
    for k, v in _mapping(where, "joint_limits", raw_limits).items():
        if not isinstance(v, (list, tuple)) or len(v) != 2:
            raise RobotSpecError(f"{where}: joint_limits.{k} must be [lower, upper], got {clip(v)}")
        lo = _number(where, f"joint_limits.{k}", v[0])
        hi = _number(where, f"joint_limits.{k}", v[1])
        if not lo < hi:
            raise RobotSpecError(f"{where}: joint_limits.{k} needs lower < upper, got {clip(v)}")
        limits[str(k)] = (lo, hi)
    return limits


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
            raise RobotSpecError(f"{where}: {key} {str(file)!r} does not exist")
    for d in spec.package_dirs:
        if not d.is_dir():
            raise RobotSpecError(f"{where}: model.package_dirs: {str(d)!r} is not a directory")


def _section(where: str, raw: Any, keys: tuple[str, ...]) -> Mapping[str, Any]:
    """``raw`` as a mapping whose keys are all in ``keys`` (else a one-line error)."""
    if not isinstance(raw, Mapping):
        raise RobotSpecError(f"{where} must be a mapping with keys {', '.join(keys)}, got {raw!r}")
    head, _, path = where.rpartition(": ")
    _check_keys(head, path, raw, keys)
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


def load_robot(name_or_path: str | os.PathLike[str] | Robot) -> Robot:
    """Load a robot from a shipped spec name or a spec file.

    Args:
        name_or_path: ``"panda"``, ``"ur5"`` (see :func:`available_robots`), a path
            to a YAML spec, or a :class:`Robot` (returned as is).

    Returns:
        The robot.

    Raises:
        RobotSpecError: Unknown robot or invalid spec.
        FrameNotFoundError: The grasp frame is not in the model (lists close names).
    """
    if isinstance(name_or_path, Robot):
        return name_or_path
    return Robot(load_spec(name_or_path))
