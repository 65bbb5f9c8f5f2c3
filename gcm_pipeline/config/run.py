"""Run configuration: YAML into validated, frozen config objects.

A config is read once, at the boundary, by :func:`load_config` (or
:meth:`Config.from_dict`); stages receive the frozen section objects and never
re-parse dicts. Unknown keys are errors that name the key and suggest the
closest valid one; every error is a :class:`~gcm_pipeline.errors.ConfigError`
whose message names the file, the dotted key and the value at fault.

Sections (see DESIGN.md): ``seed``, ``robot``, ``object``, ``candidates``,
``manifold``, ``densify``, ``ik``, ``environment``, ``approach``, ``retreat``,
``continuity``, ``ranking``, ``publish``, ``output``. Only ``candidates`` is required.

Poses are ``{xyz: [x, y, z], rpy: [roll, pitch, yaw]}`` in metres and radians,
or ``rpy_deg`` in degrees. Roll, pitch and yaw are rotations about the fixed x,
y and z axes (the URDF convention): ``R = Rz(yaw) @ Ry(pitch) @ Rx(roll)``.
"""

from __future__ import annotations

import copy
import difflib
import functools
import inspect
import math
import os
import re
import typing
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import Annotated, Any, Literal, ParamSpec, TypeVar

import numpy as np
from pydantic import (
    BaseModel,
    ConfigDict,
    Field,
    Strict,
    ValidationError,
    field_validator,
    model_validator,
)

from gcm_pipeline.bounds import (
    DEFAULT_MAX_CANDIDATES,
    DEFAULT_MAX_POSES,
    MAX_ADAPTIVE_LEVEL,
    MAX_APPROACH_STEPS,
    MAX_IK_SOLUTIONS,
    MAX_IK_WORKERS,
    MAX_LENGTH,
    MAX_OBSTACLES,
)
from gcm_pipeline.config.validation import describe
from gcm_pipeline.errors import ConfigError, clip, unknown_choice
from gcm_pipeline.safe_yaml import MAX_YAML_DEPTH, load_yaml, read_yaml_file

__all__ = [
    "as_config",
    "takes_config",
    "AdaptiveConfig",
    "ApproachConfig",
    "CandidatesConfig",
    "Config",
    "ContinuityConfig",
    "DensifyConfig",
    "EnvironmentConfig",
    "IKConfig",
    "ManifoldConfig",
    "NoiseConfig",
    "ObjectConfig",
    "ObstacleConfig",
    "OutputConfig",
    "Pose",
    "PublishConfig",
    "RankingConfig",
    "RetreatConfig",
    "RobotConfig",
    "ShapeDims",
    "TableConfig",
    "config_schema",
    "load_config",
]

# Numbers and switches are strict: a bool is not a number (``--set
# densify.subdivisions=true`` is an error, not 1), a number is not a bool, a
# string is neither, a float with a fraction is not an int. Every int, float
# and bool field of a section uses one of these (tests/config/test_config.py checks).
Bool = Annotated[bool, Strict()]
FiniteFloat = Annotated[float, Strict(), Field(allow_inf_nan=False)]
PositiveFloat = Annotated[float, Strict(), Field(gt=0, allow_inf_nan=False)]
NonNegFloat = Annotated[float, Strict(), Field(ge=0, allow_inf_nan=False)]
PositiveInt = Annotated[int, Strict(), Field(gt=0)]
#: Seeds of NumPy's generators are non-negative.
Seed = Annotated[int, Strict(), Field(ge=0)]
Vec3 = tuple[FiniteFloat, FiniteFloat, FiniteFloat]
#: Lengths and coordinates of the scene [m], within MAX_LENGTH (see gcm_pipeline.bounds).
Length = Annotated[float, Strict(), Field(ge=-MAX_LENGTH, le=MAX_LENGTH, allow_inf_nan=False)]
PositiveLength = Annotated[float, Strict(), Field(gt=0, le=MAX_LENGTH, allow_inf_nan=False)]
NonNegLength = Annotated[float, Strict(), Field(ge=0, le=MAX_LENGTH, allow_inf_nan=False)]
Point3 = tuple[Length, Length, Length]

#: ``output.dir`` of a config given as a dict (relative to the working directory).
DEFAULT_OUTPUT_DIR = "results/run"


class _Section(BaseModel):
    """Base of every config section: frozen, unknown keys forbidden."""

    model_config = ConfigDict(extra="forbid", frozen=True, populate_by_name=True)

    def __repr__(self) -> str:
        fields = ", ".join(f"{k}={v!r}" for k, v in self.model_dump(exclude_defaults=True).items())
        return f"{type(self).__name__}({fields})"


class Pose(_Section):
    """A rigid pose: position [m] and roll-pitch-yaw [rad] (or ``rpy_deg`` [deg])."""

    xyz: Point3 = (0.0, 0.0, 0.0)
    rpy: Vec3 | None = None
    rpy_deg: Vec3 | None = None

    @model_validator(mode="after")
    def _one_rotation(self) -> Pose:
        if self.rpy is not None and self.rpy_deg is not None:
            raise ValueError("give either 'rpy' (radians) or 'rpy_deg' (degrees), not both")
        return self

    @property
    def rpy_rad(self) -> tuple[float, float, float]:
        """Roll, pitch, yaw in [rad]."""
        if self.rpy_deg is not None:
            return tuple(math.radians(a) for a in self.rpy_deg)  # type: ignore[return-value]
        return self.rpy if self.rpy is not None else (0.0, 0.0, 0.0)

    def matrix(self) -> np.ndarray:
        """Return the pose as a (4, 4) homogeneous transform."""
        roll, pitch, yaw = self.rpy_rad
        cr, sr = math.cos(roll), math.sin(roll)
        cp, sp = math.cos(pitch), math.sin(pitch)
        cy, sy = math.cos(yaw), math.sin(yaw)
        m = np.eye(4)
        m[:3, :3] = [
            [cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr],
            [sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr],
            [-sp, cp * sr, cp * cr],
        ]
        m[:3, 3] = self.xyz
        return m


class ShapeDims(_Section):
    """Dimensions of a primitive shape [m]; which keys are needed depends on the shape."""

    radius: PositiveLength | None = None
    height: PositiveLength | None = None
    size: tuple[PositiveLength, ...] | None = None


_SHAPE_DIMS: dict[str, tuple[str, ...]] = {
    "cylinder": ("radius", "height"),
    "box": ("size",),
    "sphere": ("radius",),
    "plane": ("size",),
    "mesh": (),
}


def _check_shape(shape: str, dims: ShapeDims, mesh: Path | None) -> None:
    for key in _SHAPE_DIMS[shape]:
        if getattr(dims, key) is None:
            raise ValueError(f"shape {shape!r} needs dims.{key}")
    want = {"box": 3, "plane": 2}.get(shape)
    if want is not None and dims.size is not None and len(dims.size) != want:
        raise ValueError(
            f"shape {shape!r} needs dims.size with {want} values, got {len(dims.size)}"
        )
    if shape == "mesh" and mesh is None:
        raise ValueError("shape 'mesh' needs 'mesh: <path to .stl/.obj/.dae>'")


class _ShapeSection(_Section):
    """A primitive or mesh placed in the world (shape, dims, pose, mesh, scale).

    Subclasses narrow ``shape`` to the shapes they allow; the dims each shape
    needs are checked once here.
    """

    shape: str
    dims: ShapeDims = ShapeDims()
    pose: Pose = Pose()
    mesh: Path | None = None
    scale: PositiveLength = 1.0

    @model_validator(mode="after")
    def _dims_for_shape(self) -> _ShapeSection:
        _check_shape(self.shape, self.dims, self.mesh)
        return self


class ObjectConfig(_ShapeSection):
    """The object being grasped; ``pose`` is its frame in the world.

    Cylinders stand on their base with the axis along the frame's z (the base
    at z = 0 of the frame); boxes and spheres are centred on the frame origin;
    a plane lies in the frame's xy plane.
    """

    shape: Literal["cylinder", "box", "sphere", "plane", "mesh"]


class RobotConfig(_Section):
    """Robot spec (a name under ``robots/`` or a YAML path) and its base pose in the world."""

    spec: str = "panda"
    base_pose: Pose = Pose()


class NoiseConfig(_Section):
    """Noise added to generated candidates: position [m] and angle [deg] (standard deviations)."""

    position: NonNegLength = 0.0
    angle_deg: NonNegFloat = 0.0


class CandidatesConfig(_Section):
    """Where the grasp candidates come from: a generator or a file.

    Generators stand in for a grasp synthesiser: ``plane`` (grasps from above
    on a flat surface), ``cylinder_side`` (rings around a standing cylinder),
    ``box`` (faces), ``sphere``. ``file`` imports ``npy``/``npz`` (N, 4, 4),
    ``csv`` (x,y,z,qw,qx,qy,qz columns) or ``acronym`` HDF5 files.

    Attributes:
        source: Generator name or ``file``.
        count: Number of generated grasps (generators only).
        seed: Seed of the generator's noise and sampling (default: top-level ``seed``).
        noise: Standard deviations of the position [m] and angle [deg] noise.
        rings: ``cylinder_side``: number of rings (default ``round(sqrt(count / 3))``).
        depth: How far the grasp frame lies past the surface along the approach [m]
            (default 0 for ``plane``, 0.01 otherwise).
        path: ``file``: the grasp file (relative to the config file's directory).
        format: ``file``: ``acronym`` | ``npy`` | ``npz`` | ``csv`` (default: from the suffix).
        frame: ``file``: the poses are in the ``world`` or the ``object`` frame.
        grasp_to_tool: Fixed transform from the file's (or the generator's) gripper frame
            to the robot's grasp frame, applied on the right (``T_tool = T_grasp @
            grasp_to_tool``), for every source. ACRONYM's Franka frame written as
            ``npy``/``npz``/``csv`` needs ``{xyz: [0, 0, 0.1034], rpy_deg: [0, 0, -90]}``.
        success_only: ``file``: keep only grasps labelled successful.
        limit: ``file``: keep at most this many grasps (the first ones, after filtering).
        gripper: The gripper whose frame convention maps the file's poses onto the
            robot's grasp frame (:mod:`gcm_pipeline.sources.grippers`; default: the
            gripper the file names, else the format's dataset gripper, ``franka_panda``
            for ``acronym``, ``contact_graspnet``, ``graspnet``; a ``graspgen`` file
            naming none needs it), or whose opening and finger depth the ``antipodal``
            sampler uses. Replaces ``grasp_to_tool``.
        friction: ``antipodal``: friction coefficient of the contacts (the cone's half
            angle is ``atan(friction)``).
        camera_pose: ``contact_graspnet`` (required) and ``graspnet``: the pose in the
            world of the camera's optical frame (OpenCV: x right, y down, z forward)
            in which the file's grasps are given.
        max_count: Ceiling of ``count`` and of the rows of a grasp file (checked
            before anything is read or generated; see :mod:`gcm_pipeline.bounds`).
    """

    source: Literal["plane", "cylinder_side", "box", "sphere", "file", "antipodal"]
    count: PositiveInt = 24
    seed: Seed | None = None
    noise: NoiseConfig = NoiseConfig()
    rings: PositiveInt | None = None
    depth: Length | None = None
    path: Path | None = None
    format: (
        Literal["acronym", "npy", "npz", "csv", "graspgen", "contact_graspnet", "graspnet"] | None
    ) = None
    frame: Literal["object", "world"] = "world"
    grasp_to_tool: Pose | None = None
    success_only: Bool = False
    limit: PositiveInt | None = None
    gripper: str | None = None
    camera_pose: Pose | None = None
    max_count: PositiveInt = DEFAULT_MAX_CANDIDATES
    friction: PositiveFloat = 0.5

    @model_validator(mode="after")
    def _file_needs_path(self) -> CandidatesConfig:
        if self.source == "file" and self.path is None:
            raise ValueError("source 'file' needs 'path'")
        if self.source != "file" and self.count > self.max_count:
            raise ValueError(
                f"count {self.count:,} is above candidates.max_count ({self.max_count:,}); "
                "raise candidates.max_count to allow it"
            )
        return self

    @model_validator(mode="before")
    @classmethod
    def _format_from_suffix(cls, data: Any) -> Any:
        # GraspGen's JSON / YAML grasp files are the only structured-text format
        if isinstance(data, dict) and data.get("format") is None and data.get("path"):
            if str(data["path"]).lower().endswith((".json", ".yaml", ".yml")):
                data = {**data, "format": "graspgen"}
        return data

    @model_validator(mode="after")
    def _gripper_and_camera(self) -> CandidatesConfig:
        if self.gripper is not None:
            # here, not at the top: gcm_pipeline.sources loads SciPy and the file readers
            # (about 1 s); a config that names no gripper is read without them
            from gcm_pipeline.sources.grippers import GRIPPERS

            if self.gripper not in GRIPPERS:
                raise ValueError(unknown_choice("gripper", self.gripper, GRIPPERS))
        if self.gripper is not None and self.grasp_to_tool is not None:
            raise ValueError("give 'gripper' or 'grasp_to_tool', not both")
        if self.gripper is not None and self.source == "file" and self.format in _POSE_FORMATS:
            raise ValueError(
                f"'gripper' needs a format with a documented gripper frame (acronym, "
                f"graspgen, contact_graspnet, graspnet); {self.format} poses are taken as "
                "the robot's grasp frame (use grasp_to_tool)"
            )
        if self.camera_pose is not None and not (
            self.source == "file" and self.format in ("contact_graspnet", "graspnet")
        ):
            raise ValueError("'camera_pose' applies to format contact_graspnet or graspnet")
        if self.camera_pose is not None and self.frame == "object":
            raise ValueError(
                "give 'camera_pose' (the grasps are in the camera frame) or 'frame: object', "
                "not both"
            )
        if self.source == "file" and self.format == "contact_graspnet" and not self.camera_pose:
            raise ValueError(
                "'camera_pose' is missing: format 'contact_graspnet' predicts grasps in "
                "the camera frame (OpenCV: x right, y down, z forward); give the camera's "
                "pose in the world, e.g. camera_pose: {xyz: [0.5, 0, 0.8], rpy_deg: [180, 0, 0]} "
                "(looking straight down)"
            )
        return self


_POSE_FORMATS = ("npy", "npz", "csv")

#: Object shape each generator needs.
GENERATOR_SHAPES = {"plane": "plane", "cylinder_side": "cylinder", "box": "box", "sphere": "sphere"}


class ManifoldConfig(_Section):
    """Delaunay manifold over a 2-D chart of the grasp positions.

    ``orientation_scale`` [m/rad] weighs orientation against position in the
    manifold's pose metric (nearest points, the ``margin`` column): a
    rotation of 1 rad counts like a move of this length.
    """

    projection: Literal["xy", "pca", "cylindrical", "spherical"] = "xy"
    triangulator: Literal["qhull", "bowyer_watson"] = "qhull"
    max_edge_length: PositiveLength | None = None
    max_edge_angle_deg: Annotated[float, Strict(), Field(gt=0, le=180)] | None = None
    orientation_scale: PositiveFloat = 0.1


class AdaptiveConfig(_Section):
    """Adaptive refinement (see :mod:`gcm_pipeline.manifold.adaptive`).

    Triangles are split into four where their corners disagree on
    reachability (``boundary``) or their ranking metric varies by more than
    ``metric_threshold`` times its range (``metric``), down to ``max_level``
    (``2**max_level`` subdivisions per candidate edge at most); ``min_level``
    levels are refined everywhere first.
    """

    max_level: Annotated[int, Strict(), Field(ge=1, le=MAX_ADAPTIVE_LEVEL)]
    min_level: Annotated[int, Strict(), Field(ge=0, le=MAX_ADAPTIVE_LEVEL)] = 0
    refine: tuple[Literal["boundary", "metric"], ...] = ("boundary", "metric")
    metric_threshold: Annotated[float, Strict(), Field(gt=0, le=1, allow_inf_nan=False)] = 0.1

    @model_validator(mode="after")
    def _levels(self) -> AdaptiveConfig:
        if self.min_level > self.max_level:
            raise ValueError(
                f"min_level ({self.min_level}) must not exceed max_level ({self.max_level})"
            )
        if not self.refine:
            raise ValueError("refine needs at least one of 'boundary', 'metric'")
        return self


class DensifyConfig(_Section):
    """Densification inside each triangle: a regular grid or a target spacing [m].

    ``max_poses`` is the ceiling of the densified table (candidates plus
    lattice points, estimated before the lattice is built; see
    :mod:`gcm_pipeline.bounds`). With ``adaptive`` the lattice is refined
    where reachability or the metric changes instead (``subdivisions`` and
    ``spacing`` are then not used).
    """

    subdivisions: PositiveInt | None = 4
    spacing: PositiveLength | None = None
    method: Literal["dlb", "dib"] = "dlb"
    max_poses: PositiveInt = DEFAULT_MAX_POSES
    adaptive: AdaptiveConfig | None = None

    @model_validator(mode="after")
    def _some_density(self) -> DensifyConfig:
        if self.subdivisions is None and self.spacing is None:
            raise ValueError("give 'subdivisions' or 'spacing'")
        return self


class IKConfig(_Section):
    """Inverse kinematics backend, acceptance tolerances and parallelism.

    Attributes:
        backend: ``pinocchio`` (batched, default) or ``mink``.
        position_tolerance: Largest position error of a solution [m].
        orientation_tolerance: Largest orientation error of a solution [rad].
        workers: Processes of the reachability engine: ``auto`` (the cores this
            process may use) or a number. The results do not depend on it.
        solutions: Distinct IK solutions (branches) kept per reachable grasp,
            each verified and passing every check (``solutions.npz``); 1: only
            the first one found.
        select: Which branch a grasp takes when there are several: ``metric``
            (the best by the ranking metric) or ``continuity`` (the one nearest
            to its neighbours' on the manifold, fewer IK patches).
    """

    backend: Literal["pinocchio", "mink"] = "pinocchio"
    position_tolerance: PositiveFloat = 1.0e-4
    orientation_tolerance: PositiveFloat = 1.0e-3
    workers: Literal["auto"] | Annotated[int, Strict(), Field(gt=0, le=MAX_IK_WORKERS)] = "auto"
    solutions: Annotated[int, Strict(), Field(ge=1, le=MAX_IK_SOLUTIONS)] = 1
    select: Literal["metric", "continuity"] = "metric"

    @field_validator("workers", mode="before")
    @classmethod
    def _auto_or_count(cls, v: Any) -> Any:
        if v == "auto" and isinstance(v, str):
            return v
        whole = isinstance(v, (int, np.integer)) and not isinstance(v, bool)
        if not whole or not 0 < v <= MAX_IK_WORKERS:
            raise ValueError(
                f"expected 'auto' or a whole number from 1 to {MAX_IK_WORKERS}, got {v!r}"
            )
        return int(v)


class TableConfig(_Section):
    """Support table: a box whose top face is at ``height`` [m] in the world."""

    height: Length = 0.0
    size: tuple[PositiveLength, PositiveLength, PositiveLength] = (2.0, 2.0, 0.05)
    center_xy: tuple[Length, Length] = (0.0, 0.0)


class ObstacleConfig(_ShapeSection):
    """An extra collision obstacle in the world."""

    shape: Literal["box", "cylinder", "sphere", "mesh"]
    name: str | None = None


class EnvironmentConfig(_Section):
    """Collision world: the table (on by default), extra obstacles, the object."""

    table: TableConfig | None = TableConfig()
    obstacles: Annotated[tuple[ObstacleConfig, ...], Field(max_length=MAX_OBSTACLES)] = ()
    check_object: Bool = True
    self_collision: Bool = True
    contact_tolerance: NonNegLength = 0.005


class ApproachConfig(_Section):
    """Pre-grasp approach check along the grasp frame's approach axis (z).

    The pre-grasp is the grasp frame backed off by ``distance`` [m] along its
    z; the hand must move from there to the grasp in a straight line at fixed
    orientation (see :mod:`gcm_pipeline.reach.moves`).

    Attributes:
        distance: Length of the straight line [m] (0: no check).
        steps: The line is cut into this many equal steps; the joint path is
            collision-checked at the end of every step, and IK waypoints are
            placed at most at every step.
        max_joint_step: Largest change of any joint between the ends of one step [rad].
        max_deviation: Largest distance [m] by which any point of the gripper
            may leave its straight-line path (a bound over the whole path, not
            only at the steps).
    """

    distance: NonNegLength = 0.10
    steps: Annotated[int, Strict(), Field(gt=0, le=MAX_APPROACH_STEPS)] = 10
    max_joint_step: PositiveFloat = 0.25
    max_deviation: PositiveLength = 0.002


class RetreatConfig(ApproachConfig):
    """Post-grasp retreat: the grasp frame moves ``distance`` along ``direction``.

    The gripper holds the object: it may touch it (see
    :mod:`gcm_pipeline.reach.engine`).

    Attributes:
        direction: Direction of the move (normalised; must not be zero).
        frame: ``world`` (e.g. ``[0, 0, 1]`` lifts straight up) or ``grasp``
            (the grasp frame's axes: ``[0, 0, -1]`` backs out along the approach).
    """

    direction: Vec3 = (0.0, 0.0, 1.0)
    frame: Literal["world", "grasp"] = "world"

    @field_validator("direction")
    @classmethod
    def _nonzero_direction(cls, v: tuple[float, float, float]) -> tuple[float, float, float]:
        if not any(v):  # any other length: the direction is what counts
            raise ValueError(f"must not be the zero vector, got {list(v)}")
        return v


Metric = Literal[
    "yoshikawa",
    "translational",
    "inverse_condition",
    "joint_limit_margin",
    "clearance",
    "margin",
    "combined",
]
_METRICS: tuple[str, ...] = typing.get_args(Metric)


class ContinuityConfig(_Section):
    """IK continuity between neighbouring grasps (see :mod:`gcm_pipeline.manifold.continuity`).

    ``threshold`` [rad] is the largest joint jump (L-infinity) between
    neighbours of one patch (one IK branch). With ``reseed``, grasps at the
    border of a smaller patch are re-solved from their neighbours in a larger
    one (collisions and approach checked as in the run) until patches stop
    growing or ``max_rounds`` rounds have run.
    """

    threshold: PositiveFloat = 0.5
    reseed: Bool = False
    max_rounds: Annotated[int, Strict(), Field(ge=1, le=10_000)] = 100


class RankingConfig(_Section):
    """Ranking of the reachable grasps by a manipulability metric."""

    metric: Metric = "yoshikawa"
    top_k: PositiveInt = 10
    weights: dict[str, NonNegFloat] | None = None

    @field_validator("weights")
    @classmethod
    def _known_weights(cls, v: dict[str, float] | None) -> dict[str, float] | None:
        if v is None:
            return v
        valid = [m for m in _METRICS if m != "combined"]
        for key in v:
            if key not in valid:
                close = difflib.get_close_matches(key, valid, n=1)
                hint = f" (did you mean {close[0]!r}?)" if close else ""
                raise ValueError(f"unknown metric {clip(key)}{hint}; valid: {', '.join(valid)}")
        if not any(w > 0 for w in v.values()):
            raise ValueError("weights must have at least one positive value")
        return v


#: ``tcp://host:port`` (host: a name, an IPv4 address or ``[IPv6]``).
_ZMQ_URL = re.compile(r"tcp://(\[[0-9A-Fa-f:.]+\]|[A-Za-z0-9_.-]+):([0-9]{1,5})")


class PublishConfig(_Section):
    """What to publish: live meshcat, a self-contained HTML scene, PNG plots."""

    meshcat: Bool = False
    zmq_url: str | None = None
    wait: Bool = True
    html: Bool = True
    plots: Bool = True
    connect_timeout_s: PositiveFloat = 5.0

    @field_validator("zmq_url")
    @classmethod
    def _zmq_url_format(cls, v: str | None) -> str | None:
        if v is None:
            return v
        match = _ZMQ_URL.fullmatch(v)
        if match is None or not 0 < int(match.group(2)) < 65536:
            raise ValueError(f"expected tcp://HOST:PORT, e.g. tcp://127.0.0.1:6000, got {clip(v)}")
        return v


class OutputConfig(_Section):
    """Where the run directory goes (``gcm run --out DIR`` overrides it).

    A relative ``dir`` is relative to the config file's folder, like every
    other path of a config (:func:`load_config`); the default is
    ``results/<config name>`` there (``results/run`` in the working directory
    for a config given as a dict).
    """

    dir: Path = Path(DEFAULT_OUTPUT_DIR)


class Config(_Section):
    """A whole run. Only ``candidates`` is required."""

    seed: Seed = 0
    robot: RobotConfig = RobotConfig()
    object: ObjectConfig | None = None
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
        shape = GENERATOR_SHAPES.get(c.source)
        if shape is not None and (self.object is None or self.object.shape != shape):
            got = (
                "no 'object' section"
                if self.object is None
                else f"object.shape {self.object.shape!r}"
            )
            raise ValueError(
                f"candidates.source {c.source!r} needs object.shape {shape!r}, got {got}"
            )
        if c.source == "antipodal" and self.object is None:
            raise ValueError("candidates.source 'antipodal' samples an object: add 'object'")
        if c.source == "file" and c.frame == "object" and self.object is None:
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
                raise ConfigError(f"{source}: {message}") from None
            k = given[-1]
            named = message.startswith((f"{k}: ", f"{k}."))
            raise ConfigError(f"--set {message}" if named else f"--set {k}: {message}") from None
        except RecursionError:
            raise ConfigError(f"{source}: config nested too deeply") from None

    def to_dict(self) -> dict[str, Any]:
        """The resolved config as plain JSON/YAML-ready data (all defaults filled in)."""
        return self.model_dump(mode="json")


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
        raise ConfigError(f"--set {clip(assignment)}: expected KEY=VALUE, e.g. ik.backend=mink")
    key, _, raw = assignment.partition("=")
    parts = key.strip().split(".")
    if not all(parts):
        raise ConfigError(f"--set {clip(assignment)}: empty key part in {clip(key)}")
    value = load_yaml(raw, f"--set {key.strip()[:200]}", ConfigError, plain_on_syntax_error=True)
    node = data
    for part in parts[:-1]:
        nxt = node.get(part)
        if nxt is None:
            nxt = {}
            node[part] = nxt
        if not isinstance(nxt, dict):
            raise ConfigError(f"--set {clip(assignment)}: {clip(part)} is not a section")
        node = nxt
    node[parts[-1]] = value


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
    if isinstance(overrides, str):  # one assignment, not its characters one by one
        overrides = (overrides,)
    for assignment in overrides:
        _set_override(data, assignment)
    resolve_paths(data, Path(os.path.abspath(path)).parent, default_out=f"results/{path.stem}")
    set_keys = [a.partition("=")[0].strip() for a in overrides]
    return Config.from_dict(data or None, source=str(path), set_keys=set_keys)


def resolve_paths(data: dict[str, Any], base: Path, default_out: str = DEFAULT_OUTPUT_DIR) -> None:
    """Make the paths in the config absolute, relative ones against ``base``.

    ``candidates.path``, ``object.mesh``, ``environment.obstacles[].mesh``,
    ``output.dir`` (``default_out`` when missing) and a ``robot.spec`` that is
    a path (ends in ``.yaml``/``.yml`` or has a ``/``) become absolute
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
    fix(data.get("object"), "mesh", "object.mesh")
    fix(data.get("robot"), "spec", "robot.spec", only_paths=True)
    env = data.get("environment")
    if isinstance(env, dict) and isinstance(env.get("obstacles"), list):
        for i, obstacle in enumerate(env["obstacles"]):
            fix(obstacle, "mesh", f"environment.obstacles.{i}.mesh")
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
