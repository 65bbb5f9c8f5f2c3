"""gcm_pipeline: grasp configuration manifolds and their reachability.

The public API is listed in ``__all__``; every name in it imports.
Importing the package loads Pinocchio (robot models, IK, collisions) but not
mink, MuJoCo, meshcat or Ray: those load when the ``mink`` IK backend, the
meshcat publisher or a placement study (:class:`Study`) is used.
"""

from gcm_pipeline.config import Config, load_config
from gcm_pipeline.errors import (
    ConfigError,
    FrameNotFoundError,
    GcmError,
    GeometryError,
    InputError,
    OutputError,
    PublishError,
    RobotSpecError,
)
from gcm_pipeline.geometry.dualquat import (
    dib,
    dlb,
    dq_from_matrix,
    dq_from_pos_quat,
    dq_mul,
    dq_to_matrix,
    dq_to_pos_quat,
    sclerp,
)
from gcm_pipeline.geometry.surface import Location
from gcm_pipeline.io import read_run
from gcm_pipeline.pipeline import (
    Pipeline,
    RunResult,
    build_manifold,
    check_reachability,
    densify,
    generate_candidates,
    publish,
    rank,
)
from gcm_pipeline.query import BestGrasps, GraspManifold, NearestReachable, load_manifold
from gcm_pipeline.robot.collision import CollisionChecker
from gcm_pipeline.robot.ik import IKResult, solve_ik
from gcm_pipeline.robot.manipulability import (
    inverse_condition_number,
    joint_limit_margin,
    manipulability,
    manipulability_metrics,
    translational_manipulability,
    yoshikawa,
)
from gcm_pipeline.robot.model import Robot, available_robots, load_robot
from gcm_pipeline.stages.collision import combined_score
from gcm_pipeline.stages.manifold import Manifold
from gcm_pipeline.study import Study, StudyResult
from gcm_pipeline.table import GraspTable

__version__ = "0.1.0"

__all__ = [
    "BestGrasps",
    "CollisionChecker",
    "Config",
    "ConfigError",
    "FrameNotFoundError",
    "GcmError",
    "GeometryError",
    "GraspManifold",
    "GraspTable",
    "IKResult",
    "InputError",
    "Location",
    "Manifold",
    "NearestReachable",
    "OutputError",
    "Pipeline",
    "PublishError",
    "Robot",
    "RobotSpecError",
    "RunResult",
    "Study",
    "StudyResult",
    "__version__",
    "available_robots",
    "build_manifold",
    "check_reachability",
    "combined_score",
    "densify",
    "dib",
    "dlb",
    "dq_from_matrix",
    "dq_from_pos_quat",
    "dq_mul",
    "dq_to_matrix",
    "dq_to_pos_quat",
    "generate_candidates",
    "inverse_condition_number",
    "joint_limit_margin",
    "load_config",
    "load_manifold",
    "load_robot",
    "manipulability",
    "manipulability_metrics",
    "publish",
    "rank",
    "read_run",
    "sclerp",
    "solve_ik",
    "translational_manipulability",
    "yoshikawa",
]
