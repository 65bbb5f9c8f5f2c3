"""Reading a user's URDF: the quirks of real files handled before Pinocchio sees them.

:func:`prepare_urdf` reads a URDF file with Python's XML parser (a malformed
file is one line naming the line and column) and returns the text Pinocchio
builds the model from:

- **Continuous joints** become revolute joints over a stated range,
  :data:`CONTINUOUS_RANGE` = [-2π, 2π] (two turns: every orientation twice, so
  IK and trajectories do not wrap at ±π), or the spec's ``joint_limits`` for
  that joint. The URDF standard ignores a continuous joint's ``lower``/``upper``;
  so does this. The model then keeps one coordinate per joint (nq == nv), like
  every other arm.
- **Meshes** are resolved to absolute paths: ``package://PKG/...`` against the
  spec's ``package_dirs`` (a folder that holds ``PKG/`` or is ``PKG/``), then
  the URDF's folder and its parents as ROS-style package roots (the ancestor
  named ``PKG``, or one holding ``PKG/``); ``file://`` and absolute paths as
  they are; relative paths against the URDF's folder, then ``package_dirs``.
  A mesh that is not found is one line naming the link, the mesh and where it
  was looked for.
- **A moving joint with the zero axis** is one line (Pinocchio would divide by
  its norm). **Mimic joints** are recorded with the joint they follow, the
  multiplier and the offset (:attr:`PreparedUrdf.mimic`): a robot locks them
  where the joint they follow is locked.

:func:`build_model` builds the Pinocchio model with urdfdom's console output
captured at the file-descriptor level (urdfdom prints its errors on stderr
before Pinocchio raises): its message ends up in the one-line error instead.
:func:`resolve_frame` finds a frame by name and type: a link and a joint of one
name (common in users' URDFs) resolve to the link's BODY frame.
"""

from __future__ import annotations

import contextlib
import difflib
import math
import os
import sys
import tempfile
import xml.etree.ElementTree as ET
from collections.abc import Iterator, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import NamedTuple

import pinocchio as pin

from gcm_pipeline.errors import FrameNotFoundError, RobotSpecError, clip

__all__ = [
    "CONTINUOUS_RANGE",
    "MAX_URDF_BYTES",
    "MeshRef",
    "Mimic",
    "PreparedUrdf",
    "build_model",
    "captured_output",
    "prepare_urdf",
    "resolve_frame",
]

#: Range [rad] a continuous joint gets unless the spec's ``joint_limits`` gives one.
CONTINUOUS_RANGE = (-2.0 * math.pi, 2.0 * math.pi)
#: Largest URDF file read [bytes].
MAX_URDF_BYTES = 64 * 1024 * 1024
_FRAME_TYPES = {
    pin.FrameType.BODY: "link (BODY)",
    pin.FrameType.JOINT: "joint (JOINT)",
    pin.FrameType.FIXED_JOINT: "fixed joint (FIXED_JOINT)",
    pin.FrameType.OP_FRAME: "operational frame (OP_FRAME)",
    pin.FrameType.SENSOR: "sensor (SENSOR)",
}


@dataclass(frozen=True)
class MeshRef:
    """A mesh a URDF link names.

    Attributes:
        link: The link.
        kind: ``"visual"`` or ``"collision"``.
        uri: The filename as written in the URDF.
        path: The file it resolved to.
        scale: ``scale`` attribute as written (or ``""``).
    """

    link: str
    kind: str
    uri: str
    path: Path
    scale: str = ""


class Mimic(NamedTuple):
    """A URDF ``<mimic>``: the joint is at ``multiplier * leader + offset``."""

    leader: str
    multiplier: float = 1.0
    offset: float = 0.0


@dataclass(frozen=True)
class PreparedUrdf:
    """A URDF read and rewritten for Pinocchio (see the module docstring).

    Attributes:
        path: The file read.
        xml: The rewritten text (continuous joints revolute, mesh paths absolute).
        robot_name: ``<robot name>``.
        root_link: The link that is no joint's child.
        continuous: Joints that were continuous, with the range they got [rad].
        unbounded: Revolute or prismatic joints without ``lower``/``upper`` (urdfdom
            reads [0, 0]; the spec's ``joint_limits`` range is written in when given).
        meshes: Every mesh of every link.
        package_dirs: Folders that resolved ``package://`` URIs (for other readers).
        mimic: Joints with a ``<mimic>`` element, each with the joint it follows.
            (:class:`Mimic`: leader, multiplier, offset).
        moving: Joints of a moving type (revolute, continuous, prismatic, ...: not fixed).
    """

    path: Path
    xml: str
    robot_name: str
    root_link: str
    continuous: Mapping[str, tuple[float, float]]
    unbounded: tuple[str, ...]
    meshes: tuple[MeshRef, ...]
    package_dirs: tuple[Path, ...]
    mimic: Mapping[str, Mimic] = field(default_factory=dict)
    moving: frozenset[str] = frozenset()


@contextlib.contextmanager
def captured_output() -> Iterator[list[str]]:
    """Capture what C++ code prints on stdout and stderr (file descriptors 1 and 2).

    Yields a list that holds the captured text (one string) once the block ends.
    Python's own buffered output is flushed first and goes where it went before.
    """
    box: list[str] = []
    for stream in (sys.stdout, sys.stderr):
        with contextlib.suppress(Exception):
            stream.flush()
    saved: list[tuple[int, int]] = []
    with tempfile.TemporaryFile() as tmp:
        try:
            for fd in (1, 2):
                try:
                    saved.append((fd, os.dup(fd)))
                except OSError:  # no such descriptor (a daemon): nothing to capture
                    continue
                os.dup2(tmp.fileno(), fd)
            yield box
        finally:
            for fd, old in saved:
                os.dup2(old, fd)
                os.close(old)
            tmp.seek(0)
            box.append(tmp.read(1 << 20).decode("utf-8", errors="replace"))


def _read_xml(path: Path, what: str) -> ET.Element:
    try:
        size = path.stat().st_size
        if size > MAX_URDF_BYTES:
            raise RobotSpecError(
                f"{what} {str(path)!r} is {size / 2**20:.0f} MiB; at most "
                f"{MAX_URDF_BYTES // 2**20} MiB is read"
            )
        data = path.read_bytes()
    except OSError as exc:
        raise RobotSpecError(f"cannot read {what} {str(path)!r}: {exc.strerror or exc}") from None
    try:
        return ET.fromstring(data)
    except ET.ParseError as exc:
        raise RobotSpecError(f"{what} {str(path)!r} is not valid XML: {exc}") from None


def _ancestors(folder: Path, depth: int = 12) -> list[Path]:
    out = [folder]
    for p in folder.parents:
        if len(out) > depth:
            break
        out.append(p)
    return out


def _mesh_candidates(
    uri: str, folder: Path, package_dirs: Sequence[Path]
) -> tuple[list[Path], str]:
    """Files a mesh URI may name, in order of preference, and a hint for the message."""
    if uri.startswith("package://"):
        rest = uri[len("package://") :]
        pkg, _, rel = rest.partition("/")
        cands: list[Path] = []
        for d in package_dirs:
            cands += [d / pkg / rel] + ([d / rel] if d.name == pkg else [])
        for a in _ancestors(folder):
            cands += ([a / rel] if a.name == pkg else []) + [a / pkg / rel]
        hint = f"set model.package_dirs to the folder that holds the package {pkg!r}"
        return cands, hint
    if uri.startswith("file://"):
        return [Path(uri[len("file://") :])], "fix the path in the URDF"
    if "://" in uri:
        scheme = uri.split("://", 1)[0]
        raise RobotSpecError(
            f"mesh {clip(uri)}: URI scheme {scheme!r} is not supported "
            "(package://, file://, absolute or relative paths)"
        )
    p = Path(uri).expanduser()
    if p.is_absolute():
        return [p], "fix the path in the URDF"
    hint = "relative mesh paths resolve against the URDF's folder, then model.package_dirs"
    return [folder / p] + [d / p for d in package_dirs], hint


def _joint_limit(joint: ET.Element, rng: tuple[float, float]) -> None:
    limit = joint.find("limit")
    if limit is None:
        limit = ET.SubElement(joint, "limit")
    limit.set("lower", repr(float(rng[0])))
    limit.set("upper", repr(float(rng[1])))
    limit.set("effort", limit.get("effort", "0"))
    limit.set("velocity", limit.get("velocity", "0"))


def _check_axis(joint: ET.Element, name: str, where: str) -> None:
    """Refuse a moving joint whose ``<axis>`` is zero (Pinocchio divides by its norm)."""
    axis = joint.find("axis")
    if joint.get("type") not in ("revolute", "continuous", "prismatic") or axis is None:
        return
    try:
        xyz = [float(v) for v in axis.get("xyz", "1 0 0").split()]
    except ValueError:
        return  # urdfdom names the malformed vector
    if len(xyz) == 3 and all(map(math.isfinite, xyz)) and not any(xyz):
        raise RobotSpecError(
            f"{where}: joint {name!r} has the zero axis {axis.get('xyz')!r}; "
            "give the direction it turns about (or slides along)"
        )


def prepare_urdf(
    path: Path,
    package_dirs: Sequence[Path] = (),
    joint_limits: Mapping[str, tuple[float, float]] | None = None,
    *,
    check_meshes: bool = True,
) -> PreparedUrdf:
    """Read a URDF and rewrite it for Pinocchio (see the module docstring).

    Args:
        path: The URDF file.
        package_dirs: Folders resolving ``package://`` URIs, tried first.
        joint_limits: The spec's range overrides [rad]; a continuous joint named
            here gets this range instead of :data:`CONTINUOUS_RANGE`.
        check_meshes: Resolve the meshes (else they are left as written).

    Raises:
        RobotSpecError: One line: unreadable or malformed XML, no ``<robot>`` root,
            no root link, a mesh that is not found (names the link and the mesh).
    """
    where = f"URDF {str(path)!r}"
    root = _read_xml(path, "URDF")
    if root.tag != "robot":
        raise RobotSpecError(f"{where}: root element is <{root.tag[:40]}>, expected <robot>")
    limits = dict(joint_limits or {})
    continuous: dict[str, tuple[float, float]] = {}
    unbounded: list[str] = []
    mimic: dict[str, Mimic] = {}
    children = set()
    for joint in root.findall("joint"):
        child = joint.find("child")
        if child is not None:
            children.add(child.get("link"))
        name = str(joint.get("name"))
        _check_axis(joint, name, where)
        if joint.find("mimic") is not None:
            mimic[name] = _mimic(joint.find("mimic"), name, where)  # type: ignore[arg-type]
        if joint.get("type") == "continuous":
            rng = limits.get(name, CONTINUOUS_RANGE)
            joint.set("type", "revolute")
            _joint_limit(joint, rng)
            continuous[name] = (float(rng[0]), float(rng[1]))
        elif joint.get("type") in ("revolute", "prismatic"):
            limit = joint.find("limit")
            if limit is None or (limit.get("lower") is None and limit.get("upper") is None):
                unbounded.append(name)  # urdfdom reads [0, 0]
                if name in limits:  # the spec's range is the range
                    _joint_limit(joint, limits[name])
    links = [str(link.get("name")) for link in root.findall("link")]
    roots = [n for n in links if n not in children]
    if not links or not roots:
        raise RobotSpecError(f"{where}: has no root link (a link that is no joint's child)")
    folder = path.parent.resolve()
    pkg_dirs = tuple(Path(d).resolve() for d in package_dirs)
    meshes: list[MeshRef] = []
    for link in root.findall("link") if check_meshes else ():
        for kind in ("visual", "collision"):
            for el in link.findall(kind):
                for mesh in el.iter("mesh"):
                    uri = mesh.get("filename", "")
                    if not uri:
                        raise RobotSpecError(
                            f"{where}: link {link.get('name')!r} has a {kind} mesh without filename"
                        )
                    try:
                        cands, hint = _mesh_candidates(uri, folder, pkg_dirs)
                    except RobotSpecError as exc:
                        raise RobotSpecError(f"{where}: link {link.get('name')!r}: {exc}") from None
                    found = next((c for c in cands if c.is_file()), None)
                    if found is None:
                        looked = ", ".join(str(c) for c in cands[:3])
                        more = f" and {len(cands) - 3} more" if len(cands) > 3 else ""
                        raise RobotSpecError(
                            f"{where}: link {link.get('name')!r}: {kind} mesh {clip(uri)} "
                            f"not found (looked for {looked}{more}); {hint}"
                        )
                    found = found.resolve()
                    mesh.set("filename", str(found))
                    meshes.append(
                        MeshRef(str(link.get("name")), kind, uri, found, mesh.get("scale", ""))
                    )
    return PreparedUrdf(
        path=path,
        xml=ET.tostring(root, encoding="unicode"),
        robot_name=str(root.get("name", "")),
        root_link=roots[0],
        continuous=continuous,
        unbounded=tuple(unbounded),
        meshes=tuple(meshes),
        package_dirs=tuple(dict.fromkeys([*pkg_dirs, folder])),
        mimic=mimic,
        moving=frozenset(
            str(j.get("name")) for j in root.findall("joint") if j.get("type") != "fixed"
        ),
    )


def _mimic(element: ET.Element, joint: str, where: str) -> Mimic:
    """A ``<mimic joint multiplier offset>`` element (URDF defaults: 1 and 0)."""
    values = []
    for attr, default in (("multiplier", 1.0), ("offset", 0.0)):
        text = element.get(attr)
        try:
            value = default if text is None else float(text)
        except ValueError:
            value = math.nan
        if not math.isfinite(value):
            raise RobotSpecError(
                f"{where}: joint {joint!r}: <mimic {attr}={clip(text)}> is not a finite number"
            )
        values.append(value)
    return Mimic(str(element.get("joint")), values[0], values[1])


def _urdfdom_message(text: str) -> str:
    """The informative part of urdfdom's console output (one line)."""
    lines = [" ".join(ln.split()) for ln in text.splitlines()]
    keep = [ln for ln in lines if ln and not ln.startswith("at line ")]
    return "; ".join(keep)


def build_model(urdf: PreparedUrdf) -> pin.Model:
    """The Pinocchio model of a prepared URDF; urdfdom's console output is kept quiet.

    Raises:
        RobotSpecError: One line with urdfdom's reason (e.g. a joint naming a
            parent link that does not exist).
    """
    try:
        with captured_output() as out:
            model = pin.buildModelFromXML(urdf.xml)
    except Exception as exc:  # pinocchio raises ValueError/RuntimeError
        said = _urdfdom_message(out[0] if out else "")
        first = _urdfdom_message(str(exc))
        reason = clip(said or first, 600)
        raise RobotSpecError(
            f"URDF {str(urdf.path)!r} is not a valid URDF model: {reason}"
        ) from None
    return model


def frame_candidates(model: pin.Model, name: str) -> list[int]:
    """Indices of the frames called ``name``."""
    return [i for i, f in enumerate(model.frames) if f.name == name]


def resolve_frame(model: pin.Model, name: str, what: str, where: str) -> int:
    """Index of the frame ``name``, by name and type.

    A name several frames share resolves to the one BODY (link) frame among
    them: a URDF whose joint and link have one name (``tool0`` the joint,
    ``tool0`` the link) works. Without a single BODY frame it is ambiguous.

    Args:
        model: The model.
        name: The frame name.
        what: The spec key, for messages (``grasp_frame``, ``tool.flange``).
        where: The robot, for messages.

    Raises:
        FrameNotFoundError: No frame of that name (lists the closest).
        RobotSpecError: Several frames of that name and not exactly one link.
    """
    ids = frame_candidates(model, name)
    if len(ids) == 1:
        return ids[0]
    if not ids:
        names = list(dict.fromkeys(f.name for f in model.frames))
        close = difflib.get_close_matches(name, names, n=5, cutoff=0.4)
        raise FrameNotFoundError(
            f"{where}: {what} {name!r} is not a frame of the model; "
            f"closest: {', '.join(close) or '(none)'}; all frames: {', '.join(names)}"
        )
    bodies = [i for i in ids if model.frames[i].type == pin.FrameType.BODY]
    if len(bodies) == 1:
        return bodies[0]
    kinds = ", ".join(
        _FRAME_TYPES.get(model.frames[i].type, str(model.frames[i].type)) for i in ids
    )
    raise RobotSpecError(
        f"{where}: {what} {name!r} is ambiguous: {len(ids)} frames have that name ({kinds}) "
        "and not exactly one is a link; rename one in the URDF"
    )


def frame_kind(model: pin.Model, index: int) -> str:
    """``link``, ``joint``, ``fixed joint``, ``operational frame`` or ``sensor``."""
    return _FRAME_TYPES.get(model.frames[index].type, "frame").split(" (")[0]
