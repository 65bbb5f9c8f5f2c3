"""Study plans: the placements of a study file, as ``--set`` overrides of its base config.

The study file itself is read and validated by :mod:`gcm_pipeline.config.study`.
Every placement is the base config plus ``--set`` style overrides
(:attr:`Placement.overrides`): ``gcm run BASE --set ...`` with the same
overrides gives the same answer. Pose axes are absolute: ``x, y, z`` [m] set
the position in the world, ``yaw_deg`` [deg] the yaw of the pose's
roll-pitch-yaw; axes that are not swept keep the base config's value.
Moving the object moves its candidates with it (generated candidates and
files in the object frame are placed by the object pose; a file in the world
frame is refused, its grasps would stay behind). An object its grasp file
names (no ``object`` section) moves by ``candidates.placement``: ``x, y``
are the centre of its footprint on the table, ``yaw_deg`` its turn about the
vertical; its stable pose fixes its height, so ``z`` is refused.
"""

from __future__ import annotations

import copy
import hashlib
import itertools
import json
import math
import os
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from gcm_pipeline import __version__
from gcm_pipeline.bounds import MAX_STUDY_PLACEMENTS
from gcm_pipeline.config.objects import TARGET_ALL
from gcm_pipeline.config.run import Config, config_from_data, resolve_paths
from gcm_pipeline.config.study import (
    DECIMALS,
    OBJECT_SECTIONS,
    PoseSweep,
    RangeSpec,
    StudySpec,
    read_study,
    rounded,
)
from gcm_pipeline.errors import ConfigError, GcmError
from gcm_pipeline.pipeline import input_files, place_file_object
from gcm_pipeline.study.targets import PlacementTarget, PoseTarget, format_value

__all__ = ["Placement", "StudyPlan", "load_study"]


# ------------------------------------------------------------------ placements


@dataclass(frozen=True)
class Placement:
    """One run of a study: the base config plus :attr:`overrides`.

    Attributes:
        id: Index in the study (round 0 first, then each refinement round).
        round: 0 for the grid, r for the r-th refinement round.
        object: Name of the object (``sweep.objects``; else the base's shape name).
        object_pose: ``x, y, z, yaw_deg`` of the object's pose as swept (only swept keys).
        base_pose: The same for the robot base.
        overrides: ``KEY=VALUE`` strings, in order: the study's ``set``, the
            object entry's sections and ``set``, then the pose keys.
    """

    id: int
    round: int
    object: str
    object_pose: dict[str, float] = field(default_factory=dict)
    base_pose: dict[str, float] = field(default_factory=dict)
    overrides: tuple[str, ...] = ()

    def label(self) -> str:
        """A short human-readable description (object, swept pose keys)."""
        parts = [self.object]
        for prefix, pose in (("object", self.object_pose), ("base", self.base_pose)):
            if pose:
                parts.append(prefix + " " + " ".join(f"{k} {v:g}" for k, v in pose.items()))
        return ", ".join(parts)


#: Position axes of a pose sweep and their coordinate index.
_XYZ = {"x": 0, "y": 1, "z": 2}


def _grid(axes: dict[str, list[float]]) -> list[dict[str, float]]:
    """Every combination of the axes' values (first axis slowest); [{}] without axes."""
    names = list(axes)
    return [dict(zip(names, combo, strict=True)) for combo in itertools.product(*axes.values())]


# ------------------------------------------------------------------ the study


class StudyPlan:
    """A validated study: the base config, the placements and how to resolve them.

    Built by :func:`load_study`; :class:`gcm_pipeline.study.Study` wraps it.

    Attributes:
        spec: The validated study file.
        source: The study file (None for a dict).
        base_path: The base config file, or None when the base is inline.
        base_data: The base config as read (a mapping, before overrides).
        base_dir: Folder against which the base's relative paths resolve.
    """

    def __init__(
        self,
        spec: StudySpec,
        *,
        source: Path | None,
        base_path: Path | None,
        base_data: dict[str, Any],
        base_dir: Path,
        study_dir: Path,
    ) -> None:
        self.spec = spec
        self.source = source
        self.base_path = base_path
        self.base_data = base_data
        self.base_dir = base_dir
        self.study_dir = study_dir
        self._key: str | None = None
        self._objects = self._object_entries()
        self._targets: dict[int, PoseTarget] = {}
        self._placed: dict[int, Config] = {}
        self.base_config = self.resolve(list(spec.set), where="base config")
        self._check()
        # counted per axis, so a study far too large is refused before it is built
        self._count = self._count_grid()
        if self._count == 0:
            raise ConfigError("sweep: no placement lies inside the region")
        self._grid: list[Placement] | None = None

    # --- resolving configs ----------------------------------------------------------

    def resolve(self, overrides: Sequence[str], *, where: str = "") -> Config:
        """The config of the base plus ``overrides``, as ``gcm run BASE --set ...`` reads it.

        Raises:
            ConfigError: Naming ``where`` (e.g. the placement) and the key at fault.
        """
        # the base as read when the study was loaded (a file edited meanwhile is
        # another study: its key differs), resolved as load_config resolves it
        path = self.base_path or (self.source or self.study_dir / "study.yaml")
        try:
            cfg = config_from_data(copy.deepcopy(self.base_data), path, list(overrides))
            if cfg.target == TARGET_ALL:  # one run per object: not one placement's run
                raise ConfigError(f"{path}: target: a study runs one target object, not 'all'")
        except ConfigError as exc:
            raise ConfigError(f"{where}: {exc}" if where else str(exc)) from None
        return cfg

    def _object_entries(self) -> list[tuple[str, list[str]]]:
        """(name, overrides) of each object; one entry named after the base's object when none."""
        entries = self.spec.sweep.objects
        if entries is None:
            obj = self.base_data.get("object") if isinstance(self.base_data, dict) else None
            shape = obj.get("shape") if isinstance(obj, dict) else None
            return [(str(shape) if shape else "object", [])]
        out = []
        for entry in entries:
            sets: list[str] = []
            for section in OBJECT_SECTIONS:
                value = getattr(entry, section)
                if value is None:
                    continue
                value = copy.deepcopy(value)
                holder = {section: value}
                resolve_paths(holder, self.study_dir)
                sets.append(f"{section}={format_value(holder[section])}")
            sets.extend(entry.set)
            out.append((entry.name, sets))
        return out

    def _object_target(self, index: int) -> PoseTarget:
        if index not in self._targets:
            cfg = self.object_config(index)
            if cfg.object is None and self._placed_config(index).object is not None:
                table = cfg.environment.table
                z = 0.0 if table is None else table.height
                self._targets[index] = PlacementTarget(cfg.candidates.placement.xy, z)
            else:
                pose = cfg.object.pose.model_dump() if cfg.object is not None else None
                self._targets[index] = PoseTarget("object.pose", pose)
        return self._targets[index]

    def file_object_pose(self, index: int, cfg: Config) -> list[float] | None:
        """``x, y, z, yaw_deg`` of object ``index`` in ``cfg`` when its grasp file names it.

        The centre of its footprint on the table and its yaw
        (``candidates.placement``); None for an object the config gives, and
        when the study does not sweep ``object_pose`` (its objects are not read).
        """
        if self.spec.sweep.object_pose is None:
            return None
        if not isinstance(self._object_target(index), PlacementTarget):
            return None
        p, table = cfg.candidates.placement, cfg.environment.table
        return [*p.xy, 0.0 if table is None else table.height, p.yaw_deg]

    def _placed_config(self, index: int) -> Config:
        """Object ``index``'s config with the object its grasp file names, if any, placed."""
        if index not in self._placed:
            self._placed[index] = place_file_object(self.object_config(index))
        return self._placed[index]

    def _base_target(self) -> PoseTarget:
        if -1 not in self._targets:
            pose = self.base_config.robot.base_pose.model_dump()
            self._targets[-1] = PoseTarget("robot.base_pose", pose)
        return self._targets[-1]

    def object_config(self, index: int) -> Config:
        """The config of object ``index`` before any pose override."""
        name, sets = self._objects[index]
        return self.resolve([*self.spec.set, *sets], where=f"objects[{index}] ({name})")

    @property
    def object_names(self) -> list[str]:
        """Names of the swept objects, in order."""
        return [name for name, _ in self._objects]

    # --- checks ------------------------------------------------------------------

    def _check(self) -> None:
        sweep = self.spec.sweep
        if sweep.object_pose is None and sweep.base_pose is None and sweep.objects is None:
            raise ConfigError("sweep: give at least one of object_pose, base_pose, objects")
        for key, pose in (("object_pose", sweep.object_pose), ("base_pose", sweep.base_pose)):
            if pose is None:
                continue
            try:
                pose.axes()
            except ConfigError as exc:
                raise ConfigError(f"sweep.{key}.{exc}") from None
            if key == "base_pose" and pose.region == "table":
                raise ConfigError(
                    "sweep.base_pose.region: 'table' is a region for the object; "
                    "give a box {min: [x, y], max: [x, y]}"
                )
        for i, name in enumerate(self.object_names):
            if sweep.object_pose is None:
                continue
            cfg = self._placed_config(i)
            if cfg.object is None and cfg.objects is not None:
                raise ConfigError(
                    f"sweep.object_pose: the base config lists 'objects' (target {cfg.target!r}) "
                    "and a study moves one 'object': give the target as 'object' and the other "
                    "objects as environment.obstacles, or sweep base_pose",
                    key="sweep.object_pose",
                )
            if cfg.object is None:
                raise ConfigError(
                    f"sweep.object_pose: {name}: the config has no 'object' section to move "
                    "(nor a grasp file that names its object)"
                )
            if sweep.object_pose.z is not None and isinstance(
                self._object_target(i), PlacementTarget
            ):
                raise ConfigError(
                    f"sweep.object_pose.z: {name}: the object comes from the grasp file and "
                    "stands on the table in a stable pose (candidates.placement), which fixes "
                    "its height; sweep x, y and yaw_deg",
                    key="sweep.object_pose.z",
                )
            c = cfg.candidates
            if c.source == "file" and c.frame != "object":  # None: world, with an object
                raise ConfigError(
                    f"sweep.object_pose: {name}: candidates.frame is 'world', so the grasps "
                    "would not move with the object; give the file's grasps in the object "
                    "frame (candidates.frame: object)"
                )
            if sweep.object_pose.region == "table" and cfg.environment.table is None:
                raise ConfigError(
                    f"sweep.object_pose.region: 'table' needs a table ({name}: "
                    "environment.table is null)"
                )
        refine = self.spec.refine
        if refine is not None and refine.rounds > 0 and not self._ranges():
            raise ConfigError(
                "refine: no range to re-grid; give a pose key as {from, to, steps} "
                "(lists are kept as they are)"
            )

    def _ranges(self) -> dict[str, dict[str, RangeSpec]]:
        sweep = self.spec.sweep
        out = {}
        for key, pose in (("object_pose", sweep.object_pose), ("base_pose", sweep.base_pose)):
            if pose is not None and pose.ranges():
                out[key] = pose.ranges()
        return out

    # --- placements ------------------------------------------------------------------

    def _inside(self, pose: PoseSweep | None, axis: int, value: float) -> bool:
        """Whether coordinate ``axis`` (0 x, 1 y, 2 z) of a position is inside the region.

        Both regions (the table top, a box) are boxes, so a position is inside
        when each coordinate is: the grid's size is counted axis by axis.
        """
        if pose is None or pose.region is None:
            return True
        if pose.region == "table":
            if axis > 1:
                return True
            table = self.base_config.environment.table
            assert table is not None
            half = 0.5 * table.size[axis]
            return abs(value - table.center_xy[axis]) <= half + 1e-12
        box = pose.region
        return axis >= len(box.min) or box.min[axis] <= value <= box.max[axis]

    def _count_poses(
        self, pose: PoseSweep | None, axes: dict[str, list[float]], target: PoseTarget
    ) -> int:
        """How many of the combinations of ``axes`` lie inside ``pose``'s region."""
        n = len(axes.get("yaw_deg", [0.0]))
        for i, a in enumerate(("x", "y", "z")):
            values = axes[a] if a in axes else [target.xyz[i]]
            n *= sum(1 for v in values if self._inside(pose, i, v))
        return n

    def _count_grid(self) -> int:
        sweep = self.spec.sweep
        object_axes = sweep.object_pose.axes() if sweep.object_pose else {}
        base_axes = sweep.base_pose.axes() if sweep.base_pose else {}
        bases = self._count_poses(sweep.base_pose, base_axes, self._base_target())
        if not object_axes:
            return bases * len(self._objects)
        return bases * sum(
            self._count_poses(sweep.object_pose, object_axes, self._object_target(k))
            for k in range(len(self._objects))
        )

    def count(self) -> int:
        """The number of placements of round 0 (the grid), without building them."""
        return self._count

    def _combos(
        self,
        object_axes: dict[str, list[float]],
        base_axes: dict[str, list[float]],
        objects: Iterable[int],
    ) -> list[tuple[int, dict[str, float], dict[str, float]]]:
        sweep = self.spec.sweep
        bases = self._poses_in_region(sweep.base_pose, base_axes, self._base_target())
        out: list[tuple[int, dict[str, float], dict[str, float]]] = []
        for k in objects:
            poses = (
                self._poses_in_region(sweep.object_pose, object_axes, self._object_target(k))
                if object_axes
                else [{}]
            )
            out.extend((k, o, b) for b in bases for o in poses)
        return out

    def _poses_in_region(
        self, pose: PoseSweep | None, axes: dict[str, list[float]], target: PoseTarget
    ) -> list[dict[str, float]]:
        """The combinations of ``axes`` inside ``pose``'s region, in grid order.

        Each axis is filtered before the combinations are built (both regions
        are boxes): a large sweep cut down by a small region builds only what
        is inside it, as :meth:`_count_poses` counts it.
        """
        kept: dict[str, list[float]] = {}
        for name, values in axes.items():
            i = _XYZ.get(name)
            kept[name] = values if i is None else [v for v in values if self._inside(pose, i, v)]
        fixed_inside = all(
            self._inside(pose, i, target.xyz[i]) for a, i in _XYZ.items() if a not in axes
        )
        return _grid(kept) if fixed_inside else []

    def _placement(
        self, pid: int, rnd: int, k: int, obj: dict[str, float], base: dict[str, float]
    ) -> Placement:
        name, sets = self._objects[k]
        overrides = [*self.spec.set, *sets]
        if obj:
            overrides += self._object_target(k).overrides(obj)
        if base:
            overrides += self._base_target().overrides(base)
        return Placement(pid, rnd, name, dict(obj), dict(base), tuple(overrides))

    def grid(self) -> list[Placement]:
        """The placements of round 0 (the grid), in id order.

        Built on the first call.

        Raises:
            ConfigError: The grid has more than
                :data:`~gcm_pipeline.bounds.MAX_STUDY_PLACEMENTS` placements.
        """
        if self._grid is None:
            if self._count > MAX_STUDY_PLACEMENTS:
                raise ConfigError(
                    f"study has {self._count:,} placements; one study holds at most "
                    f"{MAX_STUDY_PLACEMENTS:,} (split it into several studies)"
                )
            sweep = self.spec.sweep
            object_axes = sweep.object_pose.axes() if sweep.object_pose else {}
            base_axes = sweep.base_pose.axes() if sweep.base_pose else {}
            combos = self._combos(object_axes, base_axes, range(len(self._objects)))
            self._grid = [self._placement(i, 0, *c) for i, c in enumerate(combos)]
        return list(self._grid)

    def refine_rounds(self) -> int:
        """The refinement rounds that can add a placement (at most ``refine.rounds``).

        Round ``r`` re-grids each range over ``shrink ** r`` of its span; once
        that span is below the rounding of grid values (``1e-10``), every value
        rounds to the best placement's own, so no later round adds anything
        (a range of one value adds nothing at all). ``rounds: 999998`` on such
        a grid costs nothing instead of running until killed.
        """
        refine = self.spec.refine
        if refine is None or refine.rounds == 0:
            return 0
        spans = [r.to - r.start for axes in self._ranges().values() for r in axes.values()]
        widest = max((w for w in spans if w > 0), default=0.0)
        unit = 10.0**-DECIMALS
        if widest < unit:
            return 0
        # the last r with widest * shrink**r >= unit, plus one against rounding
        last = math.floor(math.log(unit / widest) / math.log(refine.shrink)) + 1
        return max(0, min(refine.rounds, last))

    def refine_size(self) -> int:
        """Upper bound of the placements one refinement round adds (per object)."""
        if self.refine_rounds() == 0:
            return 0
        n = 1
        for axes in self._ranges().values():
            for r in axes.values():
                n *= r.steps
        return n * len(self._objects)

    def refined(
        self, rnd: int, best: dict[int, Placement], existing: Sequence[Placement]
    ) -> list[Placement]:
        """The placements of refinement round ``rnd`` around each object's best placement.

        Each range axis is re-gridded with its ``steps`` over ``shrink ** rnd``
        of its span, centred on the best value and clipped to the range; other
        axes keep the best placement's values. Placements already in
        ``existing`` (same overrides) are left out.

        Args:
            rnd: The round, >= 1.
            best: Object index -> its best placement so far.
            existing: Every placement so far (ids continue after them).
        """
        refine = self.spec.refine
        assert refine is not None
        seen = {p.overrides for p in existing}
        ranges = self._ranges()
        out: list[Placement] = []
        next_id = max((p.id for p in existing), default=-1) + 1
        for k in sorted(best):
            centre = best[k]
            axes: dict[str, dict[str, list[float]]] = {}
            for key, pose_values in (
                ("object_pose", centre.object_pose),
                ("base_pose", centre.base_pose),
            ):
                pose_axes: dict[str, list[float]] = {}
                for a, v in pose_values.items():
                    r = ranges.get(key, {}).get(a)
                    if r is None:
                        pose_axes[a] = [v]
                        continue
                    half = 0.5 * (r.to - r.start) * refine.shrink**rnd
                    lo, hi = max(r.start, v - half), min(r.to, v + half)
                    vals = rounded(np.linspace(lo, hi, r.steps)) if hi > lo else [v]
                    pose_axes[a] = list(dict.fromkeys(vals))
                axes[key] = pose_axes
            for _, obj, base in self._combos(axes["object_pose"], axes["base_pose"], [k]):
                p = self._placement(next_id, rnd, k, obj, base)
                if p.overrides in seen:
                    continue
                seen.add(p.overrides)
                out.append(p)
                next_id += 1
        return out

    # --- identity ---------------------------------------------------------------------

    def key(self) -> str:
        """A digest of everything that decides the study's results.

        The base config as read, the study's sweep, ``set`` and refinement, and
        the contents of every input file; not ``max_placements``, workers or
        address. A study directory holds one study: the same key resumes.
        """
        if self._key is not None:
            return self._key
        files: dict[str, str] = {}
        for i in range(len(self._objects)):  # placed: with the mesh its grasp file names
            try:  # whatever the sweep: an edited mesh is another study, not a resume
                cfg = self._placed_config(i)
            except GcmError:  # an unreadable file fails its own placements, not the study
                cfg = self.object_config(i)
            for name, path in input_files(cfg).items():
                files[f"{i}:{name}"] = _file_digest(path)
        data = {
            "gcm_pipeline": __version__,
            "base": self.base_data,
            "base_dir": str(self.base_dir),
            "study": self.spec.model_dump(mode="json", exclude={"max_placements"}, by_alias=True),
            "study_dir": str(self.study_dir),
            "files": files,
        }
        text = json.dumps(data, sort_keys=True, default=str)
        self._key = hashlib.sha256(text.encode()).hexdigest()[:16]
        return self._key

    def to_dict(self) -> dict[str, Any]:
        """The study as plain data (``study.json``): file, base, sweep."""
        return {
            "source": str(self.source) if self.source else None,
            "base": str(self.base_path) if self.base_path else self.base_data,
            "study": self.spec.model_dump(mode="json", by_alias=True, exclude_none=True),
        }


def _file_digest(path: Path) -> str:
    h = hashlib.sha256()
    try:
        with open(path, "rb") as f:
            for chunk in iter(lambda: f.read(1 << 20), b""):
                h.update(chunk)
    except OSError:
        return "missing"
    return h.hexdigest()[:16]


# ------------------------------------------------------------------ loading


def load_study(source: str | os.PathLike[str] | dict[str, Any], *, where: str = "") -> StudyPlan:
    """Read and validate a study file (or a mapping) into a :class:`StudyPlan`.

    Args:
        source: The study YAML file, or its content as a mapping (relative
            paths then resolve against the working directory).
        where: Name used in errors for a mapping (default ``study``).

    Raises:
        ConfigError: One line naming the file, the key and the problem.
    """
    study = read_study(source, where=where)
    name = study.name
    try:
        return StudyPlan(
            study.spec,
            source=study.source,
            base_path=study.base_path,
            base_data=study.base_data,
            base_dir=study.base_dir,
            study_dir=study.study_dir,
        )
    except ConfigError as exc:
        text = str(exc)
        raise ConfigError(text if text.startswith(name) else f"{name}: {text}") from None
