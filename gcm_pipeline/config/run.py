"""Run configuration: YAML into validated, frozen config objects.

A config is read once, at the boundary, by :func:`load_config` (or
:meth:`Config.from_dict`); stages receive the frozen section objects and never
re-parse dicts. Unknown keys are errors that name the key and suggest the
closest valid one; every error is a :class:`~gcm_pipeline.errors.ConfigError`
whose message names the file, the dotted key and the value at fault.

Sections (see DESIGN.md): ``seed``, ``robot``, ``object`` (or ``objects`` and
``target``, :mod:`~gcm_pipeline.config.objects`), ``candidates``,
``manifold``, ``densify``, ``ik``, ``environment``, ``approach``, ``retreat``,
``continuity``, ``ranking``, ``publish``, ``output``. Only ``candidates`` is required.
The section models live in :mod:`~gcm_pipeline.config.sections` (field types,
poses, shapes, object, candidates, manifold, densify),
:mod:`~gcm_pipeline.config.reach_sections` (robot, ik, environment, approach,
retreat, continuity) and :mod:`~gcm_pipeline.config.output_sections` (ranking,
publish, output).
"""

from __future__ import annotations

import copy
import functools
import inspect
import os
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import Annotated, Any, ParamSpec, TypeVar

import numpy as np
from pydantic import Field, ValidationError, model_validator

from gcm_pipeline.bounds import MAX_OBSTACLES
from gcm_pipeline.config.objects import NamedObjectConfig, check_objects
from gcm_pipeline.config.output_sections import OutputConfig, PublishConfig, RankingConfig
from gcm_pipeline.config.reach_sections import (
    ApproachConfig,
    ContinuityConfig,
    EnvironmentConfig,
    IKConfig,
    RetreatConfig,
    RobotConfig,
)
from gcm_pipeline.config.sections import (
    DEFAULT_OUTPUT_DIR,
    GENERATOR_SHAPES,
    CandidatesConfig,
    DensifyConfig,
    ManifoldConfig,
    ObjectConfig,
    Seed,
    _Section,
)
from gcm_pipeline.config.validation import describe
from gcm_pipeline.errors import ConfigError, clip
from gcm_pipeline.safe_yaml import MAX_YAML_DEPTH, load_yaml, read_yaml_file

__all__ = [
    "as_config",
    "takes_config",
    "Config",
    "config_schema",
    "load_config",
]


class Config(_Section):
    """A whole run. Only ``candidates`` is required."""

    seed: Seed = 0
    robot: RobotConfig = RobotConfig()
    object: ObjectConfig | None = None
    objects: Annotated[tuple[NamedObjectConfig, ...], Field(max_length=MAX_OBSTACLES)] | None = None
    target: str | None = None
    candidates: CandidatesConfig
    manifold: ManifoldConfig = ManifoldConfig()
    densify: DensifyConfig = DensifyConfig()
    ik: IKConfig = IKConfig()
    environment: EnvironmentConfig = EnvironmentConfig()
    approach: ApproachConfig | None = None
    retreat: RetreatConfig | None = None
    continuity: ContinuityConfig = ContinuityConfig()
    ranking: RankingConfig = RankingConfig()
    publish: PublishConfig = PublishConfig()
    output: OutputConfig = OutputConfig()

    @model_validator(mode="after")
    def _object_for_candidates(self) -> Config:
        c = self.candidates
        free = MAX_OBSTACLES - len(self.environment.obstacles)
        # the object(s) whose grasps are analysed (see gcm_pipeline.config.objects)
        for obj in check_objects(self.object, self.objects, self.target, free) or (None,):
            shape = GENERATOR_SHAPES.get(c.source)
            if shape is not None and (obj is None or obj.shape != shape):
                got = "no 'object' section" if obj is None else f"{_shape_key(obj)} {obj.shape!r}"
                raise ValueError(
                    f"candidates.source {c.source!r} needs object.shape {shape!r}, got {got}"
                )
        if c.source == "antipodal" and self.object is None and self.objects is None:
            raise ValueError("candidates.source 'antipodal' samples an object: add 'object'")
        if c.source == "file" and c.frame == "object" and not (self.object or self.objects):
            raise ValueError("candidates.frame 'object' needs an 'object' section (its pose)")
        return self

    @classmethod
    def from_dict(
        cls, data: Any, *, source: str = "config", set_keys: Sequence[str] = ()
    ) -> Config:
        """Validate a plain dict (as read from YAML) into a :class:`Config`.

        Relative paths (``candidates.path``, meshes, a ``robot.spec`` path,
        ``output.dir``, default ``results/run``) are made absolute against the
        working directory. NumPy scalars and arrays are taken as the Python
        numbers and lists they hold.

        Args:
            data: The config as plain data.
            source: What to name in messages (the file).
            set_keys: Dotted keys given by ``--set``: an error at or under one
                of them names ``--set``, not ``source``.

        Raises:
            ConfigError: Naming ``source`` (or ``--set``), the dotted key and the problem.
        """
        if data is None:
            raise ConfigError(
                f"{source}: config is empty; it needs at least a 'candidates' section"
            )
        if not isinstance(data, dict):
            raise ConfigError(
                f"{source}: a config is a mapping of sections, got {type(data).__name__}"
            )
        data = _plain(data, source)
        resolve_paths(data, Path.cwd())
        try:
            return cls.model_validate(data)
        except ValidationError as exc:
            problem = describe(exc, data, Config)
            message, key = problem.message, problem.key
            unknown = problem.kind == "extra_forbidden"
            given = [
                k
                for k in set_keys
                if key == k or key.startswith(k + ".") or (unknown and k.startswith(key + "."))
            ]
            if not given:
                raise problem.error(f"{source}: {message}") from None
            k = given[-1]
            named = message.startswith((f"{k}: ", f"{k}."))
            raise problem.error(f"--set {message}" if named else f"--set {k}: {message}") from None
        except RecursionError:
            raise ConfigError(f"{source}: config nested too deeply") from None

    def to_dict(self) -> dict[str, Any]:
        """The resolved config as plain JSON/YAML-ready data (all defaults filled in).

        ``objects`` and ``target`` appear only when set (a run's recorded config has
        neither: see :mod:`gcm_pipeline.pipeline.objects`).
        """
        unset = {k for k in ("objects", "target") if getattr(self, k) is None}
        return self.model_dump(mode="json", exclude=unset)


def _shape_key(obj: ObjectConfig) -> str:
    """``object.shape`` or ``objects[<name>].shape``: where an object's shape was given."""
    return f"objects[{obj.name}].shape" if isinstance(obj, NamedObjectConfig) else "object.shape"


def _plain(data: Any, source: str, depth: int = 0) -> Any:
    """A copy of ``data`` with NumPy scalars and arrays as Python values (depth-limited)."""
    if depth > MAX_YAML_DEPTH:
        raise ConfigError(f"{source}: config nested deeper than {MAX_YAML_DEPTH} levels")
    if isinstance(data, dict):
        return {k: _plain(v, source, depth + 1) for k, v in data.items()}
    if isinstance(data, (list, tuple)):
        return [_plain(v, source, depth + 1) for v in data]
    if isinstance(data, (np.ndarray, np.generic)):
        return _plain(data.tolist(), source, depth + 1)
    if isinstance(data, os.PathLike):
        return os.fspath(data)
    return copy.deepcopy(data)


def _set_override(data: dict[str, Any], assignment: str) -> None:
    """Apply one ``dotted.key=value`` override (value parsed as YAML) to ``data``.

    The value is read with the same limits as a config file
    (:mod:`gcm_pipeline.safe_yaml`); text that is not valid YAML syntax is
    taken as a plain string.
    """
    if "=" not in assignment:
        raise ConfigError(
            f"--set {clip(assignment)}: expected KEY=VALUE, e.g. ik.backend=mink", value=assignment
        )
    key, _, raw = assignment.partition("=")
    parts = key.strip().split(".")
    if not all(parts):
        raise ConfigError(
            f"--set {clip(assignment)}: empty key part in {clip(key)}", key=key, value=assignment
        )
    value = load_yaml(raw, f"--set {key.strip()[:200]}", ConfigError, plain_on_syntax_error=True)
    node: Any = data
    for depth, part in enumerate(parts[:-1]):
        if isinstance(node, list):  # an entry of a list: environment.point_clouds.0.voxel_size
            nxt = node[_list_index(node, parts, depth, assignment)]
        else:
            nxt = node.get(part)
            if nxt is None:
                nxt = {}
                node[part] = nxt
        if not isinstance(nxt, (dict, list)):
            raise ConfigError(
                f"--set {clip(assignment)}: {clip(part)} is not a section",
                key=key.strip(),
                value=assignment,
            )
        node = nxt
    if isinstance(node, list):
        node[_list_index(node, parts, len(parts) - 1, assignment)] = value
    else:
        node[parts[-1]] = value


def _list_index(entries: list[Any], parts: list[str], at: int, assignment: str) -> int:
    """The list index ``parts[at]`` of ``--set``, checked against the list's length."""
    part, listed = parts[at], ".".join(parts[:at])
    if part.isascii() and part.isdigit() and int(part) < len(entries):
        return int(part)
    n = len(entries)
    how = (
        f"is a list of {n} entr{'y' if n == 1 else 'ies'}; give an index from 0 to {n - 1} "
        f"after it, got {clip(part)}"
        if n
        else "is an empty list; set the whole list instead, e.g. --set KEY=[{...}]"
    )
    raise ConfigError(
        f"--set {clip(assignment)}: {clip(listed)} {how}", key=".".join(parts), value=assignment
    )


def read_yaml(path: Path) -> Any:
    """Read a YAML config file; errors name the file, line and column.

    See :func:`gcm_pipeline.safe_yaml.read_yaml_file` for the limits (size,
    depth, aliases, duplicate keys).
    """
    return read_yaml_file(path, "config", ConfigError)


def load_config(path: str | Path, overrides: list[str] | tuple[str, ...] = ()) -> Config:
    """Load, override and validate a YAML config.

    One path rule: every relative path in the config or in an override
    (``candidates.path``, ``object.mesh``, ``environment.obstacles[].mesh``, a
    ``robot.spec`` path and ``output.dir``) is resolved against the config
    file's folder and stored as an absolute path, so the resolved config (the
    run directory's ``config.yaml``) reads and writes the same files from
    anywhere. Without ``output.dir`` the run goes to ``results/<config name>``
    in the config's folder.

    Args:
        path: The YAML file.
        overrides: ``dotted.key=value`` strings applied before validation,
            e.g. ``["ik.backend=mink", "densify.subdivisions=6"]``.

    Returns:
        The validated, frozen config.

    Raises:
        ConfigError: Missing or malformed file, unknown key, wrong type or value.
    """
    path = Path(path)
    return config_from_data(read_yaml(path), path, overrides)


def config_from_data(
    data: Any, path: str | Path, overrides: list[str] | tuple[str, ...] = ()
) -> Config:
    """:func:`load_config` of a config file's content already read (``data`` is changed).

    The same steps as :func:`load_config` after reading ``path``: overrides,
    paths resolved against ``path``'s folder, validation. A placement study
    reads its base config once and resolves every placement from it.
    """
    path = Path(path)
    if data is None:
        data = {}
    if not isinstance(data, dict):
        raise ConfigError(f"{path}: a config is a mapping of sections, got {type(data).__name__}")
    if "sweep" in data and "base" in data:  # not "unknown key 'base'"
        raise ConfigError(
            f"{path}: a placement study (base, sweep), not a run config; "
            f"run it with gcm study {path} --out DIR (it is checked before any work)"
        )
    if isinstance(overrides, str):  # one assignment, not its characters one by one
        overrides = (overrides,)
    for assignment in overrides:
        _set_override(data, assignment)
    resolve_paths(data, Path(os.path.abspath(path)).parent, default_out=f"results/{path.stem}")
    set_keys = [a.partition("=")[0].strip() for a in overrides]
    return Config.from_dict(data or None, source=str(path), set_keys=set_keys)


def resolve_paths(data: dict[str, Any], base: Path, default_out: str = DEFAULT_OUTPUT_DIR) -> None:
    """Make the paths in the config absolute, relative ones against ``base``.

    ``candidates.path``, ``candidates.mesh_root``, ``object.mesh``,
    ``objects[].mesh``, ``environment.obstacles[].mesh``,
    ``environment.point_clouds[].path`` and ``segmap``, ``output.dir``
    (``default_out`` when missing) and a ``robot.spec``, ``robot.tool`` or
    ``candidates.gripper`` that is a path (ends in ``.yaml``/``.yml`` or has a
    ``/``) become absolute
    (normalised, symlinks kept); ``base`` is absolute.

    Raises:
        ConfigError: A path with a NUL character.
    """

    def fix(section: Any, key: str, where: str, only_paths: bool = False) -> None:
        if not isinstance(section, dict) or not isinstance(section.get(key), str):
            return
        text = section[key]
        if only_paths and not (text.endswith((".yaml", ".yml")) or "/" in text):
            return
        if "\0" in text:
            raise ConfigError(f"{where}: a path cannot contain a NUL character: {clip(text)}")
        p = Path(text).expanduser()
        section[key] = os.path.abspath(p if p.is_absolute() else base / p)

    fix(data.get("candidates"), "path", "candidates.path")
    fix(data.get("candidates"), "mesh_root", "candidates.mesh_root")
    fix(data.get("object"), "mesh", "object.mesh")
    if isinstance(data.get("objects"), list):
        for i, obj in enumerate(data["objects"]):
            fix(obj, "mesh", f"objects.{i}.mesh")
    fix(data.get("robot"), "spec", "robot.spec", only_paths=True)
    fix(data.get("robot"), "tool", "robot.tool", only_paths=True)
    fix(data.get("candidates"), "gripper", "candidates.gripper", only_paths=True)
    env = data.get("environment")
    if isinstance(env, dict) and isinstance(env.get("obstacles"), list):
        for i, obstacle in enumerate(env["obstacles"]):
            fix(obstacle, "mesh", f"environment.obstacles.{i}.mesh")
    if isinstance(env, dict) and isinstance(env.get("point_clouds"), list):
        for i, cloud in enumerate(env["point_clouds"]):
            fix(cloud, "path", f"environment.point_clouds.{i}.path")
            fix(cloud, "segmap", f"environment.point_clouds.{i}.segmap")
    if data.get("output") is None:
        data["output"] = {}
    output = data["output"]
    if isinstance(output, dict):
        if output.get("dir") is None:
            output["dir"] = default_out
        fix(output, "dir", "output.dir")


def config_schema() -> dict[str, Any]:
    """The JSON Schema (draft 2020-12) of a config file, as printed by ``gcm schema``."""
    schema = Config.model_json_schema(mode="validation")
    schema["$schema"] = "https://json-schema.org/draft/2020-12/schema"
    schema["title"] = "gcm_pipeline config"
    return schema


def as_config(cfg: Any) -> Config:
    """``cfg`` as a :class:`Config`: a Config as it is, a mapping through :meth:`Config.from_dict`.

    Raises:
        ConfigError: Neither, or an invalid mapping.
    """
    if isinstance(cfg, Config):
        return cfg
    if isinstance(cfg, Mapping):
        return Config.from_dict(dict(cfg), source="cfg")
    raise ConfigError(
        f"cfg must be a Config (load_config, Config.from_dict) or a mapping, got "
        f"{type(cfg).__name__}"
    )


_P = ParamSpec("_P")
_R = TypeVar("_R")


def takes_config(func: Callable[_P, _R]) -> Callable[_P, _R]:
    """Let a stage function's ``cfg`` argument also be a plain mapping (see :func:`as_config`)."""
    sig = inspect.signature(func)

    @functools.wraps(func)
    def wrapper(*args: _P.args, **kwargs: _P.kwargs) -> _R:
        bound = sig.bind(*args, **kwargs)
        if "cfg" in bound.arguments and not isinstance(bound.arguments["cfg"], Config):
            bound.arguments["cfg"] = as_config(bound.arguments["cfg"])
            return func(*bound.args, **bound.kwargs)
        return func(*args, **kwargs)

    return wrapper
