"""Where a robot spec's model files come from: example-robot-data, robot_descriptions, a URDF.

:func:`model_files` gives a spec's URDF, SRDF and ``package://`` folders: an
example-robot-data loader's files, a ``robot_descriptions`` module's (cloned into
robot_descriptions' cache on first use, announced; a failed clone is removed and
named in one line), or the spec's own URDF. A loader whose model numbers
contradict its URDF's (example-robot-data's ``ur3`` loads ``ur5_robot.urdf``) is
refused. :func:`root_link` names the URDF's root link (the base frame);
:func:`check_srdf` refuses an SRDF that is not readable XML.

A ``robot_descriptions`` module is imported when a spec names it (its import
clones the repository and prints: inside a captured output).
"""

from __future__ import annotations

import contextlib
import difflib
import importlib
import io
import logging
import os
import re
import shutil
import xml.etree.ElementTree as ET
from pathlib import Path
from typing import TYPE_CHECKING

from example_robot_data.robots_loader import ROBOTS, getModelPath
from robot_descriptions._descriptions import DESCRIPTIONS
from robot_descriptions._repositories import REPOSITORIES

from gcm_pipeline.errors import RobotSpecError, choice_error, clip
from gcm_pipeline.robot.urdf import captured_output, prepare_urdf

if TYPE_CHECKING:
    from gcm_pipeline.robot.model import RobotSpec

__all__ = ["check_srdf", "model_files", "root_link"]

log = logging.getLogger(__name__)


def _erd_paths(name: str) -> tuple[Path, Path | None, Path]:
    """URDF, SRDF and model directory of an example-robot-data loader."""
    if name not in ROBOTS:
        raise choice_error(RobotSpecError, "example_robot_data robot", name, ROBOTS)
    loader = ROBOTS[name]
    if not loader.urdf_filename:
        raise RobotSpecError(
            f"example_robot_data robot {name!r} is an SDF model ({loader.sdf_filename}); "
            "only URDF models are read: give its URDF with model.urdf"
        )
    sub = f"{loader.path}/{loader.urdf_subpath}/{loader.urdf_filename}"
    robots_dir = Path(getModelPath(sub)).resolve()
    urdf = robots_dir / sub
    srdf = None
    if loader.srdf_filename:
        cand = robots_dir / loader.path / loader.srdf_subpath / loader.srdf_filename
        srdf = cand if cand.is_file() else None
    return urdf, srdf, robots_dir / loader.path


_MODEL_TOKEN = re.compile(r"([a-z]+)(\d+)([a-z]?)")


def _model_tokens(text: str) -> dict[str, set[str]]:
    """Model numbers in a name, by letter prefix: ``ur10e_description`` -> {ur: {ur10e}}."""
    out: dict[str, set[str]] = {}
    for part in re.split(r"[^a-z0-9]+", text.lower()):
        m = _MODEL_TOKEN.fullmatch(part)
        if m:
            out.setdefault(m.group(1), set()).add(part)
    return out


def _urdf_robot_name(urdf: Path) -> str:
    """``<robot name>`` of a URDF, read from its first 64 KiB ('' if not found)."""
    try:
        with open(urdf, "rb") as fh:
            head = fh.read(1 << 16).decode("utf-8", errors="replace")
    except OSError:
        return ""
    m = re.search(r"<robot\b[^>]*?\bname\s*=\s*[\"']([^\"']*)", head)
    return m.group(1) if m else ""


def _check_same_robot(source: str, name: str, urdf: Path) -> None:
    """Refuse a loader that loads another robot's model.

    Example-robot-data's ``ur3`` loads ``ur5_robot.urdf``: a model number in the
    loader's name (ur3) that the URDF's file name and robot name contradict (ur5).
    """
    robot = _urdf_robot_name(urdf)
    got: dict[str, set[str]] = {}
    for text in (urdf.stem, robot):
        for prefix, tokens in _model_tokens(text).items():
            got.setdefault(prefix, set()).update(tokens)
    for prefix, tokens in _model_tokens(name).items():
        for token in tokens:
            others = got.get(prefix, set())
            if not others or token in others:
                continue
            ships = sorted(
                (
                    p
                    for p in urdf.parent.glob("*.urdf")
                    if token in _model_tokens(p.stem).get(prefix, ())
                ),
                key=lambda p: (p.stem != f"{token}_robot", p.name),
            )
            fix = (
                f"use model: {{urdf: {ships[0]}}} instead"
                if ships
                else f"no URDF of the {token} ships beside it; give your own with model.urdf"
            )
            raise RobotSpecError(
                f"model.{source} {name!r} loads another robot's model: {urdf.name} "
                f"(robot {robot or '?'!r}, a {', '.join(sorted(others))}); {fix}"
            )


#: robot_descriptions modules resolved in this process: name -> (urdf, srdf, package dirs)
_RD_PATHS: dict[str, tuple[Path, Path | None, tuple[Path, ...]]] = {}


def _rd_cache_dir() -> str:
    return os.path.expanduser(
        os.environ.get("ROBOT_DESCRIPTIONS_CACHE", "~/.cache/robot_descriptions")
    )


def _rd_paths(name: str) -> tuple[Path, Path | None, tuple[Path, ...]]:
    """URDF, SRDF and package folders of a ``robot_descriptions`` module.

    Importing the module clones its repository into robot_descriptions' cache
    (``ROBOT_DESCRIPTIONS_CACHE``, default ``~/.cache/robot_descriptions``) on first
    use; a Xacro description is rendered to a URDF there (needs ``xacrodoc``).
    """
    if name in _RD_PATHS:
        return _RD_PATHS[name]
    if name not in DESCRIPTIONS:
        urdf_names = [k for k, d in DESCRIPTIONS.items() if d.has_urdf]
        raise choice_error(RobotSpecError, "robot_descriptions model", name, urdf_names)
    desc = DESCRIPTIONS[name]
    if not desc.has_urdf:
        urdf_names = [k for k, d in DESCRIPTIONS.items() if d.has_urdf]
        close = difflib.get_close_matches(name.replace("_mj_", "_"), urdf_names, n=3, cutoff=0.5)
        raise RobotSpecError(
            f"model.robot_descriptions {name!r} is an MJCF (MuJoCo) model; a URDF one is "
            f"needed: {', '.join(close) or 'see robot_descriptions --help'}"
        )
    cache = _rd_cache_dir()
    clone = _rd_clone_dir(desc.repository, cache)
    fresh = clone is not None and not clone.exists()
    _rd_announce(desc.repository, cache)
    try:
        # its clone prints a progress bar and git's messages: kept out of the output
        with (
            contextlib.redirect_stdout(io.StringIO()),
            contextlib.redirect_stderr(io.StringIO()),
            captured_output(),
        ):
            # imported here, not at module top: they import GitPython (0.1 s), and
            # fail (caught below) without xacrodoc
            from robot_descriptions._package_dirs import get_package_dirs
            from robot_descriptions._xacro import get_urdf_path

            module = importlib.import_module(f"robot_descriptions.{name}")
            urdf = Path(get_urdf_path(module))
            dirs = tuple(Path(d) for d in get_package_dirs(module))
            srdf_path = getattr(module, "SRDF_PATH", None)
    except Exception as exc:  # git, network, xacro: whatever the download raised
        if fresh and clone is not None and clone.exists():
            # a clone that failed leaves an empty repository, which robot_descriptions
            # then takes for its cache and `git clone` (the message's advice) refuses
            shutil.rmtree(clone, ignore_errors=True)
        raise RobotSpecError(_rd_fetch_error(name, desc.repository, cache, exc)) from None
    srdf = Path(srdf_path) if srdf_path and Path(srdf_path).is_file() else None
    _RD_PATHS[name] = (urdf, srdf, dirs)
    return _RD_PATHS[name]


def _rd_clone_dir(repository: str | None, cache: str) -> Path | None:
    """Where robot_descriptions keeps the clone of ``repository`` (None: not a download)."""
    repo = REPOSITORIES.get(repository or "")
    if repo is None:
        return None
    commit = os.environ.get("ROBOT_DESCRIPTION_COMMIT")  # robot_descriptions' own variable
    sub = f"{repo.cache_path}-{commit}/{repo.cache_path}" if commit else repo.cache_path
    return Path(cache) / sub


def _rd_announce(repository: str | None, cache: str) -> None:
    """Say so when robot_descriptions is about to clone a repository (it may take minutes)."""
    clone = _rd_clone_dir(repository, cache)
    if clone is not None and not clone.is_dir():
        log.warning(
            "robot_descriptions: cloning %s into %s (first use; this can take minutes)",
            REPOSITORIES[repository or ""].url,
            clone,
        )


def _rd_fetch_error(name: str, repository: str | None, cache: str, exc: Exception) -> str:
    """One line: what could not be fetched, where it was expected, how to provide it."""
    lines = [ln.strip(" '\"") for ln in str(exc).strip().splitlines() if ln.strip(" '\"")]
    why = lines[-1] if lines else type(exc).__name__
    why = why.removeprefix("stderr: ").strip(" '\"")[:200]
    repo = REPOSITORIES.get(repository or "")
    if repo is None:  # not a download: e.g. a Xacro that does not render
        return f"model.robot_descriptions {name!r}: cannot be loaded: {why}"
    target = os.path.join(cache, repo.cache_path)
    return (
        f"model.robot_descriptions {name!r}: not in the cache {cache} and cannot be fetched "
        f"from {repo.url} ({why}); run once with network access, or clone that repository "
        f"into {target} yourself (its commit {repo.commit[:12]} must be in it; "
        "ROBOT_DESCRIPTIONS_CACHE sets the cache folder)"
    )


def model_files(spec: RobotSpec) -> tuple[Path, Path | None, tuple[Path, ...]]:
    """URDF, SRDF and ``package://`` folders of a spec's model.

    Raises:
        RobotSpecError: An unknown loader or description, a loader that loads
            another robot's model, a description that cannot be fetched.
    """
    if spec.example_robot_data is not None:
        urdf, srdf, mesh_dir = _erd_paths(spec.example_robot_data)
        _check_same_robot("example_robot_data", spec.example_robot_data, urdf)
        return urdf, srdf, (mesh_dir.parent.parent.parent,)
    if spec.robot_descriptions is not None:
        urdf, srdf, dirs = _rd_paths(spec.robot_descriptions)
        _check_same_robot("robot_descriptions", spec.robot_descriptions, urdf)
        return urdf, srdf, dirs
    assert spec.urdf is not None
    return spec.urdf, spec.srdf, spec.package_dirs


def root_link(spec: RobotSpec) -> str:
    """Name of the root link of a spec's URDF (the robot's base frame).

    Raises:
        RobotSpecError: One line: the URDF is missing, not valid XML or has no root link.
    """
    urdf, _, dirs = model_files(spec)
    if not urdf.is_file():
        raise RobotSpecError(f"robot {spec.name!r}: URDF {str(urdf)!r} does not exist")
    return prepare_urdf(urdf, dirs, spec.joint_limits, check_meshes=False).root_link


def check_srdf(name: str, srdf: Path) -> None:
    """An SRDF that is not readable XML is an error of the spec (not a parser traceback)."""
    try:
        root = ET.parse(srdf).getroot()
    except (OSError, ET.ParseError) as exc:
        raise RobotSpecError(
            f"robot {name!r}: SRDF {str(srdf)!r} is not readable XML: {exc}"
        ) from None
    if root.tag != "robot":
        raise RobotSpecError(
            f"robot {name!r}: SRDF {str(srdf)!r} has root <{clip(root.tag, 40)}>, expected <robot>"
        )
