"""Run config sections of the robot and its checks.

``robot``, ``ik``, ``environment`` (table, obstacles), ``approach``, ``retreat``
and ``continuity``.
"""

from __future__ import annotations

import typing
from pathlib import Path
from typing import Annotated, Any, Literal

import numpy as np
from pydantic import Field, Strict, field_validator, model_validator

from gcm_pipeline.bounds import (
    MAX_APPROACH_STEPS,
    MAX_IK_SOLUTIONS,
    MAX_IK_WORKERS,
    MAX_OBSTACLES,
    MAX_POINT_CLOUDS,
)
from gcm_pipeline.config.sections import (
    Bool,
    FiniteFloat,
    Length,
    NonNegLength,
    Point3,
    Pose,
    PositiveFloat,
    PositiveLength,
    Vec3,
    _Section,
    _ShapeSection,
)
from gcm_pipeline.sources.grippers import check_gripper_ref


class RobotConfig(_Section):
    """Robot spec (a name under ``robots/`` or a YAML path), its base pose and tool.

    Attributes:
        spec: A shipped spec name or a spec YAML path.
        base_pose: The robot's base in the world.
        tool: A gripper of the registry (``robotiq_2f_85``) or a gripper YAML
            path, mounted instead of the tool the spec mounts on its bare
            flange (the UR5's); a spec whose hand is part of its model (the
            Panda) has none to replace.
    """

    spec: str = "panda"
    base_pose: Pose = Pose()
    tool: str | None = None

    @field_validator("tool")
    @classmethod
    def _gripper(cls, v: str | None) -> str | None:
        return v if v is None else check_gripper_ref(v)


class IKConfig(_Section):
    """Inverse kinematics backend, acceptance tolerances and parallelism.

    Attributes:
        backend: ``pinocchio`` (batched, default) or ``mink``.
        position_tolerance: Largest position error of a solution [m].
        orientation_tolerance: Largest orientation error of a solution [rad].
        workers: Processes of the reachability engine: ``auto`` or a number.
            ``auto`` decides per run: a quarter chunk (2,048 poses with
            pinocchio) runs on this process while auto reads how busy the
            cores are (``/proc/stat``, this process's own use not counted);
            then one worker per core that other jobs leave at least 80 %
            idle, no more than the cores this process may use (CPU affinity,
            a cgroup CPU quota rounded down) nor one per two full chunks of
            what is left. When that is one (a busy machine, or under 34,816
            poses on two cores), the rest runs on this process in the chunks
            of ``workers: 1`` (the first one cut in two). The results do not depend on it.
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


class PointCloudConfig(_Section):
    """A scene point cloud as an obstacle (see docs/point-clouds.md).

    Read from ``.npy`` (N, 3) points or (H, W) depth, ``.npz`` (Contact-GraspNet's
    scene layout: ``depth``, ``K``, ``segmap``, ``rgb``, or ``xyz``, ``xyz_color``),
    ``.ply``, ``.pcd`` or a ``.png`` depth image (GraspNet-1Billion's); voxelised
    on the world grid while reading and checked as octrees.

    Attributes:
        path: The cloud file (relative to the config file's directory).
        frame: ``camera`` (the camera's optical frame, OpenCV: x right, y down,
            z forward; placed by ``camera_pose``) or ``world``.
        camera_pose: The camera's pose in the world (default: ``candidates.camera_pose``).
        intrinsics: A depth image's camera matrix ``[[fx, 0, cx], [0, fy, cy], [0, 0, 1]]``
            (default: the ``.npz``'s ``K``).
        depth_scale: Depth units to metres (0.001 for millimetres).
        segmap: A ``.npy`` or label ``.png`` (H, W) of segment ids for a depth image
            (default: the ``.npz``'s ``segmap``).
        voxel_size: Edge of the voxels [m] (>= 0.001): the resolution of the obstacle.
        max_depth: Points farther than this along the camera's z are dropped [m].
        crop_min, crop_max: Corners of a world box; points outside are dropped
            (e.g. the table's own points: ``crop_min: [-1, -1, 0.005]``).
        exclude_segments: Segment ids that are not obstacles (the target object's).
        exclude_grasp_segment: Candidates with a ``segment`` column (Contact-GraspNet's
            per-segment predictions): each grasp is checked without its own segment
            (an interpolated grasp: its vertices' segment when they share one).
        exclude_object_distance: Points within this distance of the ``object`` are
            dropped [m] (the object's own points; it is checked as its shape).
        name: Name of the cloud (default ``cloud_<i>``).
    """

    path: Path
    frame: Literal["camera", "world"] = "camera"
    camera_pose: Pose | None = None
    intrinsics: (
        tuple[
            tuple[FiniteFloat, FiniteFloat, FiniteFloat],
            tuple[FiniteFloat, FiniteFloat, FiniteFloat],
            tuple[FiniteFloat, FiniteFloat, FiniteFloat],
        ]
        | None
    ) = None
    depth_scale: PositiveFloat = 1.0
    segmap: Path | None = None
    voxel_size: Annotated[float, Strict(), Field(ge=0.001, le=1.0, allow_inf_nan=False)] = 0.01
    max_depth: PositiveLength | None = None
    crop_min: Point3 | None = None
    crop_max: Point3 | None = None
    exclude_segments: tuple[Annotated[int, Strict()], ...] = ()
    exclude_grasp_segment: Bool = True
    exclude_object_distance: NonNegLength | None = None
    name: str | None = None

    @model_validator(mode="after")
    def _frame_keys(self) -> PointCloudConfig:
        if self.frame == "world" and self.camera_pose is not None:
            raise ValueError("'camera_pose' applies to frame 'camera'")
        if self.frame == "world" and self.max_depth is not None:
            raise ValueError("'max_depth' is a camera-frame depth; it applies to frame 'camera'")
        if self.crop_min is not None and self.crop_max is not None:
            if any(a > b for a, b in zip(self.crop_min, self.crop_max, strict=True)):
                raise ValueError(f"crop_min {list(self.crop_min)} exceeds crop_max")
        return self


class EnvironmentConfig(_Section):
    """Collision world: the table (on by default), extra obstacles, point clouds, the object."""

    table: TableConfig | None = TableConfig()
    obstacles: Annotated[tuple[ObstacleConfig, ...], Field(max_length=MAX_OBSTACLES)] = ()
    point_clouds: Annotated[tuple[PointCloudConfig, ...], Field(max_length=MAX_POINT_CLOUDS)] = ()
    check_object: Bool = True
    self_collision: Bool = True
    contact_tolerance: NonNegLength = 0.005

    @model_validator(mode="after")
    def _unique_names(self) -> EnvironmentConfig:
        # the collision checker finds the world's shapes by name: each needs its own
        taken = {"table": "the table", "object": "the object"}
        for i, obs in enumerate(self.obstacles):
            name = obs.name or f"obstacle_{i}"
            if name in taken:
                raise ValueError(f"obstacles[{i}]: name {name!r} is taken by {taken[name]}")
            taken[name] = f"obstacles[{i}]"
        clouds: dict[str, str] = {}
        for i, pc in enumerate(self.point_clouds):
            name = pc.name or f"cloud_{i}"
            if name in clouds:
                raise ValueError(f"point_clouds[{i}]: name {name!r} is taken by {clouds[name]}")
            clouds[name] = f"point_clouds[{i}]"
        for shape, owner in taken.items():  # a cloud's tiles are <name>_0, <name>_1, ...
            head, _, tile = shape.rpartition("_")
            if tile.isdigit() and head in clouds:
                raise ValueError(
                    f"{owner}: name {shape!r} is the name of a tile of {clouds[head]} "
                    f"({head!r}); rename one of them"
                )
        return self


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
    "score",
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
