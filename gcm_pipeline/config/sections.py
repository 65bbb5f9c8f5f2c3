"""Run config sections of the grasps, and the field types every section uses.

The strict field types, the base section, poses and shapes, then ``object``,
``candidates``, ``manifold`` and ``densify``.

Poses are ``{xyz: [x, y, z], rpy: [roll, pitch, yaw]}`` in metres and radians,
or ``rpy_deg`` in degrees. Roll, pitch and yaw are rotations about the fixed x,
y and z axes (the URDF convention): ``R = Rz(yaw) @ Ry(pitch) @ Rx(roll)``.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Annotated, Any, Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, Strict, field_validator, model_validator

from gcm_pipeline.bounds import (
    DEFAULT_MAX_CANDIDATES,
    DEFAULT_MAX_POSES,
    MAX_ADAPTIVE_LEVEL,
    MAX_LENGTH,
)
from gcm_pipeline.sources.grippers import check_gripper_ref

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
    at z = 0 of the frame); boxes and spheres are centred on the frame origin
    (standing on the table: z at half their height); a plane lies in the
    frame's xy plane. An object reaching more than 1 mm into the table, or
    lying under it, is warned about.
    """

    shape: Literal["cylinder", "box", "sphere", "plane", "mesh"]


class NoiseConfig(_Section):
    """Noise added to generated candidates: position [m] and angle [deg] (standard deviations)."""

    position: NonNegLength = 0.0
    angle_deg: NonNegFloat = 0.0


class PlacementConfig(_Section):
    """Where the object a grasp file names stands on the table (``candidates.placement``).

    The mesh rests in one of its stable poses (trimesh's): ``upright`` (the
    one that keeps the mesh's own +z up, as it was modelled) or a number, the
    stable poses ranked by probability (0: the most probable; a mug's lies it
    on its side). It is turned by ``yaw_deg`` about the vertical, the centre
    of its footprint at ``xy`` [m] and its lowest point on the table top
    (``environment.table.height``, else z = 0).
    """

    xy: tuple[Length, Length] = (0.5, 0.0)
    yaw_deg: FiniteFloat = 0.0
    stable_pose: Literal["upright"] | Annotated[int, Strict(), Field(ge=0)] = "upright"


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
        frame: ``file``: the poses are in the ``world`` or the ``object`` frame
            (default: ``object`` when the object comes from the grasp file, see
            ``mesh_root``, else ``world``).
        grasp_to_tool: Fixed transform from the file's (or the generator's) gripper frame
            to the robot's grasp frame, applied on the right (``T_tool = T_grasp @
            grasp_to_tool``), for every source. ACRONYM's Franka frame written as
            ``npy``/``npz``/``csv`` needs ``{xyz: [0, 0, 0.1034], rpy_deg: [0, 0, -90]}``.
            Generated and sampled grasps (z = approach) may only be shifted and turned
            about z: the approach, retreat and manifold take the grasp frame's z as the
            approach, so a map that turns z is refused.
        success_only: ``file``: keep only grasps labelled successful (ACRONYM's
            ``object_in_gripper``, a ``success`` column). Default: whenever the
            file has such labels (a grasp its simulation saw fail is not a
            candidate); ``false`` keeps every grasp; ``true`` without labels is
            an error.
        min_score: ``file``, ``antipodal``: keep only grasps whose ``score`` (the
            file's quality, the sampler's antipodal quality) is at least this; a
            file without a score is an error.
        limit: ``file``: keep at most this many grasps (after filtering): the best
            by ``score`` when the file has one (ties: the earlier row), else the
            first ones; the log and ``summary.json`` (``selection``) say which.
        gripper: The gripper whose frame convention maps the file's poses onto the
            robot's grasp frame (:mod:`gcm_pipeline.sources.grippers`; default: the
            gripper the file names, else the format's dataset gripper, ``franka_panda``
            for ``acronym``, ``contact_graspnet``, ``graspnet``, else ``robot.tool``;
            a ``graspgen`` file naming none on a robot without a tool needs it), or
            whose opening and finger depth the ``antipodal`` sampler uses. Replaces
            ``grasp_to_tool``.
        friction: ``antipodal``: friction coefficient of the contacts (the cone's half
            angle is ``atan(friction)``).
        camera_pose: ``contact_graspnet`` (required) and ``graspnet``: the pose in the
            world of the camera's optical frame (OpenCV: x right, y down, z forward)
            in which the file's grasps are given.
        max_count: Ceiling of ``count`` and of the rows of a grasp file (checked
            before anything is read or generated; see :mod:`gcm_pipeline.bounds`).
        mesh_root: ``acronym``/``graspgen`` files that name their object's mesh: the
            folder the name is relative to (relative to the config file's directory;
            default: ACRONYM's layout, the parent of the grasp file's folder, then
            the grasp file's folder). Without an ``object`` section and ``frame``
            the named mesh, scaled by the file's scale, becomes the object and the
            grasps follow it (``frame: object``).
        placement: Where that object stands (:class:`PlacementConfig`).
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
    frame: Literal["object", "world"] | None = None
    grasp_to_tool: Pose | None = None
    success_only: Bool | None = None
    min_score: FiniteFloat | None = None
    limit: PositiveInt | None = None
    gripper: str | None = None
    camera_pose: Pose | None = None
    max_count: PositiveInt = DEFAULT_MAX_CANDIDATES
    friction: PositiveFloat = 0.5
    mesh_root: Path | None = None
    placement: PlacementConfig = PlacementConfig()

    @model_validator(mode="after")
    def _file_needs_path(self) -> CandidatesConfig:
        if self.source == "file" and self.path is None:
            raise ValueError("source 'file' needs 'path'")
        if self.min_score is not None and self.source not in ("file", "antipodal"):
            raise ValueError(
                f"min_score: generator {self.source!r} gives no score; min_score applies to "
                "source 'file' (a file with a score) or 'antipodal'"
            )
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

    @field_validator("gripper")
    @classmethod
    def _gripper_ref(cls, v: str | None) -> str | None:
        return v if v is None else check_gripper_ref(v)  # a shipped name or a YAML path

    @model_validator(mode="after")
    def _gripper_and_camera(self) -> CandidatesConfig:
        if self.gripper is not None and self.grasp_to_tool is not None:
            raise ValueError("give 'gripper' or 'grasp_to_tool', not both")
        if self.gripper is not None and self.source == "file" and self.format in _POSE_FORMATS:
            raise ValueError(
                f"'gripper' needs a format with a documented gripper frame (acronym, "
                f"graspgen, contact_graspnet, graspnet); {self.format} poses are taken as "
                "the robot's grasp frame (use grasp_to_tool)"
            )
        if self.source != "file" and self.grasp_to_tool is not None:
            # generated and sampled grasps follow the convention (z = approach); the
            # approach, retreat, manifold bounds and scene take the mapped frame's z as
            # the approach, so a map that turns z makes them all move sideways
            tilt = math.degrees(math.acos(min(1.0, self.grasp_to_tool.matrix()[2, 2])))
            if tilt > 1e-6:
                raise ValueError(
                    f"'grasp_to_tool' turns the approach axis (z) of {self.source} grasps by "
                    f"{tilt:.3g} deg; the approach, retreat and manifold take the grasp "
                    "frame's z as the approach: give the robot a grasp frame that follows "
                    "the convention (its spec's tool.tcp) and turn grasp_to_tool about z only"
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
    """Triangles linking the grasp candidates (see docs/concepts.md, *The manifold*).

    ``structure``: ``families`` links grasps near in the pose metric, one
    chart per family, and derives unset bounds from the data's spacing;
    ``chart`` is the paper's one 2-D chart of the positions (``projection``)
    with Delaunay triangles pruned by the bounds (unset: no pruning). A
    section that names a ``projection`` but no ``structure`` is the chart
    structure (as before ``structure`` existed); ``families`` ignores it.
    ``orientation_scale`` [m/rad] weighs orientation against position in the
    manifold's pose metric (nearest points, the ``margin`` column): a
    rotation of 1 rad counts like a move of this length.
    """

    structure: Literal["families", "chart"] = "families"
    projection: Literal["xy", "pca", "cylindrical", "spherical"] = "xy"
    triangulator: Literal["qhull", "bowyer_watson"] = "qhull"
    max_edge_length: PositiveLength | None = None
    max_edge_angle_deg: Annotated[float, Strict(), Field(gt=0, le=180)] | None = None
    orientation_scale: PositiveFloat = 0.1

    @model_validator(mode="before")
    @classmethod
    def _structure(cls, data: Any) -> Any:
        if isinstance(data, dict) and "projection" in data and "structure" not in data:
            return {**data, "structure": "chart"}
        return data


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
