"""Study files: a base run config and a sweep of placements, read and validated.

A study file (YAML) names a base config and what to sweep::

    base: ../bottle_side.yaml        # a config file (relative to this file) or an inline mapping
    set: [densify.subdivisions=2]    # overrides of the base, as with gcm run --set
    sweep:
      object_pose:                   # the object (and its candidates) moved in the world
        x: {from: 0.3, to: 0.7, steps: 9}
        y: {from: -0.4, to: 0.4, steps: 9}
        yaw_deg: [0, 90]
        region: table                # or {min: [x, y], max: [x, y]}: keep placements inside
      base_pose: {x: [0.0, -0.1]}    # the robot base, same keys
      objects:                       # several objects, each over the same placements
        - {name: bottle}
        - {name: can, object: {...}, candidates: {...}}
    refine: {rounds: 2, shrink: 0.5} # re-grid the ranges around the best placement
    max_placements: 1000             # larger studies need --force

:func:`read_study` reads such a file (or a mapping) and its base config into
a :class:`StudyFile`; planning the placements and running them is
:mod:`gcm_pipeline.study`'s. Pose axes are absolute: ``x, y, z`` [m] set the
position in the world, ``yaw_deg`` [deg] the yaw of the pose's roll-pitch-yaw.
"""

from __future__ import annotations

import collections
import difflib
import os
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Any, ClassVar, Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, Strict, ValidationError, model_validator

from gcm_pipeline.bounds import MAX_LENGTH, MAX_RANGE_STEPS
from gcm_pipeline.config.run import Config, read_yaml
from gcm_pipeline.config.validation import describe
from gcm_pipeline.errors import ConfigError, clip

__all__ = [
    "AXES",
    "DEFAULT_MAX_PLACEMENTS",
    "OBJECT_SECTIONS",
    "BoxRegion",
    "ObjectEntry",
    "PoseSweep",
    "RangeSpec",
    "Refine",
    "StudyFile",
    "StudySpec",
    "Sweep",
    "file_kind",
    "parse_study",
    "read_study",
    "rounded",
]

#: Pose keys a sweep may name, per pose.
AXES = ("x", "y", "z", "yaw_deg")

#: Placements a study may have without ``--force`` (``max_placements`` raises it).
DEFAULT_MAX_PLACEMENTS = 1000

#: Decimals kept of grid values (so 0.35 is not 0.35000000000000003 in an override).
DECIMALS = 10

#: A swept value: x, y, z [m] or yaw_deg [deg], a number (not ``true``) within the scene's bounds.
FiniteFloat = Annotated[float, Strict(), Field(allow_inf_nan=False, ge=-MAX_LENGTH, le=MAX_LENGTH)]


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True, populate_by_name=True)


class RangeSpec(_Strict):
    """``{from, to, steps}``: ``steps`` evenly spaced values from ``from`` to ``to``."""

    start: FiniteFloat = Field(alias="from")
    to: FiniteFloat
    steps: int = Field(strict=True)

    @model_validator(mode="after")
    def _valid(self) -> RangeSpec:
        if self.steps < 1:
            raise ValueError(f"steps must be >= 1, got {self.steps}")
        if self.steps > MAX_RANGE_STEPS:
            raise ValueError(f"steps must be <= {MAX_RANGE_STEPS:,}, got {self.steps:,}")
        if self.start > self.to:
            raise ValueError(f"inverted range: from {self.start} > to {self.to}")
        if self.steps > 1 and self.start == self.to:
            raise ValueError(
                f"empty range: from == to == {self.start} with steps {self.steps}; "
                "give one value as [v] or steps: 1"
            )
        if self.steps == 1 and self.start != self.to:
            raise ValueError(
                f"steps: 1 needs from == to (got {self.start}, {self.to}); give one value as [v]"
            )
        return self

    def values(self) -> list[float]:
        """The grid values."""
        return rounded(np.linspace(self.start, self.to, self.steps))


Axis = RangeSpec | Annotated[list[FiniteFloat], Field(min_length=1)]


class BoxRegion(_Strict):
    """An axis-aligned box of the world: ``min`` and ``max`` corners, 2 (x, y) or 3 values [m]."""

    min: tuple[FiniteFloat, ...]
    max: tuple[FiniteFloat, ...]

    @model_validator(mode="after")
    def _valid(self) -> BoxRegion:
        if len(self.min) not in (2, 3) or len(self.max) != len(self.min):
            raise ValueError(
                "min and max need 2 (x, y) or 3 (x, y, z) values each, "
                f"got {len(self.min)} and {len(self.max)}"
            )
        for i, (lo, hi) in enumerate(zip(self.min, self.max, strict=True)):
            if lo >= hi:
                raise ValueError(f"empty region: min[{i}] {lo} >= max[{i}] {hi}")
        return self

    def contains(self, xyz: Sequence[float]) -> bool:
        """Whether a position lies inside the box (bounds included)."""
        return all(lo <= v <= hi for lo, v, hi in zip(self.min, xyz, self.max, strict=False))


class PoseSweep(_Strict):
    """Grids over the pose keys ``x, y, z`` [m] and ``yaw_deg`` [deg], optionally in a region.

    Each axis is a list of values or a range ``{from, to, steps}``; the
    placements are every combination of the axes' values (x varies slowest).
    ``region: table`` keeps the positions over the base config's table top,
    ``region: {min, max}`` those inside a box.
    """

    #: What an unknown key of this section is called in messages.
    key_noun: ClassVar[str] = "pose key"

    x: Axis | None = None
    y: Axis | None = None
    z: Axis | None = None
    yaw_deg: Axis | None = None
    region: Literal["table"] | BoxRegion | None = None

    @model_validator(mode="after")
    def _some_axis(self) -> PoseSweep:
        if all(getattr(self, a) is None for a in AXES):
            raise ValueError(f"give at least one pose key to sweep: {', '.join(AXES)}")
        return self

    def axes(self) -> dict[str, list[float]]:
        """Swept axis -> its values, in :data:`AXES` order."""
        out: dict[str, list[float]] = {}
        for name in AXES:
            spec = getattr(self, name)
            if spec is None:
                continue
            values = spec.values() if isinstance(spec, RangeSpec) else rounded(spec)
            if len(set(values)) != len(values):
                dup = next(v for v, n in collections.Counter(values).items() if n > 1)
                raise ConfigError(f"{name}: value {dup} appears twice")
            out[name] = values
        return out

    def ranges(self) -> dict[str, RangeSpec]:
        """The axes given as ranges (the ones :class:`Refine` re-grids)."""
        return {a: getattr(self, a) for a in AXES if isinstance(getattr(self, a), RangeSpec)}


class ObjectEntry(BaseModel):
    """One object of ``sweep.objects``: a name and the config sections it replaces.

    ``object``, ``candidates``, ``manifold``, ``densify`` and ``ranking`` replace
    the base config's section of that name (``--set object={...}``); ``set``
    adds further ``KEY=VALUE`` overrides. Relative file paths resolve against
    the study file's folder.
    """

    model_config = ConfigDict(extra="forbid", frozen=True)

    name: Annotated[str, Field(min_length=1, pattern=r"^[A-Za-z0-9_.-]+$")]
    object: dict[str, Any] | None = None
    candidates: dict[str, Any] | None = None
    manifold: dict[str, Any] | None = None
    densify: dict[str, Any] | None = None
    ranking: dict[str, Any] | None = None
    set: tuple[str, ...] = ()


#: Sections an object entry may replace, in override order.
OBJECT_SECTIONS = ("object", "candidates", "manifold", "densify", "ranking")


class Sweep(_Strict):
    """What a study varies: the object pose, the robot base pose, the object."""

    object_pose: PoseSweep | None = None
    base_pose: PoseSweep | None = None
    objects: Annotated[list[ObjectEntry], Field(min_length=1)] | None = None

    @model_validator(mode="after")
    def _unique_names(self) -> Sweep:
        if self.objects is not None:
            names = [o.name for o in self.objects]
            dup = next((n for n in names if names.count(n) > 1), None)
            if dup is not None:
                raise ValueError(f"objects: name {dup!r} appears twice")
        return self


class Refine(_Strict):
    """Refinement: ``rounds`` re-grids around the best placement, each ``shrink`` times smaller."""

    rounds: int = Field(default=1, ge=0, strict=True)
    shrink: float = Field(default=0.5, gt=0, lt=1)


class StudySpec(_Strict):
    """A study file, validated (see the module docstring)."""

    base: str | dict[str, Any]
    set: tuple[str, ...] = ()
    sweep: Sweep
    refine: Refine | None = None
    max_placements: int = Field(default=DEFAULT_MAX_PLACEMENTS, gt=0, strict=True)


def rounded(values: Iterable[float]) -> list[float]:
    """Grid values rounded to :data:`DECIMALS` (so 0.35 is not 0.35000000000000003)."""
    return [round(float(v), DECIMALS) + 0.0 for v in values]


# ------------------------------------------------------------------ reading

#: The keys only a study file has at its top (``set``, ``refine``, ``max_placements`` too).
STUDY_MARKS = ("base", "sweep")


def file_kind(data: Any, name: str) -> Literal["run", "study"]:
    """Whether a YAML document is a run config or a study file (``gcm validate``).

    A mapping with ``base`` or ``sweep`` is a study file (a wrong key in it is
    then reported as the study's); one with any run config section a run
    config; one with only the study's other keys (``set``, ``refine``,
    ``max_placements``) a study file missing its ``base``; one whose keys are
    close to one kind's (``candidats``) that kind, so that its message names
    the key meant.

    Raises:
        ConfigError: Neither: ``<name>: neither a run config nor a study file
            (tried both: ...)``, with the keys found.
    """
    if isinstance(data, dict) and data:
        keys = {str(k) for k in data}
        if keys & set(STUDY_MARKS):
            return "study"
        if keys & set(Config.model_fields):
            return "run"
        if keys & set(StudySpec.model_fields):
            return "study"
        # a misspelt key ('candidats') is reported by its kind, with the key it meant
        for kind, valid in (("run", Config.model_fields), ("study", StudySpec.model_fields)):
            if any(difflib.get_close_matches(k, list(valid), n=1, cutoff=0.8) for k in keys):
                return kind  # type: ignore[return-value]
        got = f"its keys: {', '.join(sorted(keys)[:8])}"
    else:
        got = "it is empty" if data in (None, {}) else f"it holds {clip(data)}"
    raise ConfigError(
        f"{name}: neither a run config nor a study file (tried both: a run config is a "
        f"mapping of sections such as robot, object, candidates; a study file has base and "
        f"sweep); {got}"
    )


def _special(err: dict[str, Any], key: str, loc: list[Any]) -> str | None:
    """The study's own wording: a region or an axis of the wrong kind."""
    shown = clip(err.get("input"))
    if key.endswith(".region") and err["type"] in ("literal_error", "model_type"):
        return f"{key}: expected 'table' or {{min: [x, y], max: [x, y]}}, got {shown}"
    if loc and loc[-1] in AXES and err["type"] in ("model_type", "list_type"):
        return f"{key}: expected a list of values or {{from: A, to: B, steps: N}}, got {shown}"
    return None


def parse_study(data: Any, name: str) -> StudySpec:
    """Validate a study's content.

    Args:
        data: The study as plain data.
        name: What to name in messages (the file).

    Raises:
        ConfigError: ``<name>: <key>: <problem>``.
    """
    if not isinstance(data, dict):
        raise ConfigError(f"{name}: a study is a mapping with 'base' and 'sweep', got {clip(data)}")
    try:
        return StudySpec.model_validate(data)
    except ValidationError as exc:
        problem = describe(exc, data, StudySpec, special=_special)
        raise problem.error(f"{name}: {problem.message}") from None


@dataclass(frozen=True)
class StudyFile:
    """A study file read and validated, with its base config as read.

    Attributes:
        spec: The validated study.
        name: What messages name (the file as given, or ``study`` for a mapping).
        source: The study file (None for a mapping).
        study_dir: The study file's folder (the working directory for a mapping).
        base_path: The base config file, or None when the base is inline.
        base_data: The base config as read (a mapping, before overrides).
        base_dir: Folder against which the base's relative paths resolve.
    """

    spec: StudySpec
    name: str
    source: Path | None
    study_dir: Path
    base_path: Path | None
    base_data: dict[str, Any]
    base_dir: Path


def read_study(source: str | os.PathLike[str] | dict[str, Any], *, where: str = "") -> StudyFile:
    """Read and validate a study file (or a mapping) and read its base config.

    Args:
        source: The study YAML file, or its content as a mapping (relative
            paths then resolve against the working directory).
        where: Name used in errors for a mapping (default ``study``).

    Raises:
        ConfigError: One line naming the file, the key and the problem.
    """
    if isinstance(source, dict):
        data: Any = source
        path: Path | None = None
        name = where or "study"
        study_dir = Path.cwd()
    else:
        path = Path(os.path.abspath(source))
        data = read_yaml(path)
        name = str(source)
        study_dir = path.parent
    spec = parse_study(data, name)
    if isinstance(spec.base, str):
        base_path: Path | None = Path(spec.base).expanduser()
        if not base_path.is_absolute():
            base_path = study_dir / base_path
        base_path = Path(os.path.abspath(base_path))
        try:
            base_data = read_yaml(base_path)
        except ConfigError as exc:
            raise ConfigError(f"{name}: base: {exc}") from None
        if base_data is None:
            base_data = {}
        if not isinstance(base_data, dict):
            raise ConfigError(f"{base_path}: a config is a mapping of sections")
        base_dir = base_path.parent
    else:
        base_path, base_data, base_dir = None, dict(spec.base), study_dir
    return StudyFile(spec, name, path, study_dir, base_path, base_data, base_dir)
