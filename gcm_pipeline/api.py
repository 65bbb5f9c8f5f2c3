"""The public API of gcm_pipeline, written once: these imports and ``__all__``.

``import gcm_pipeline`` stays light (the command line installs its signal
handling before NumPy and Pinocchio load): the package re-exports this module's
names on first use of any of them (:pep:`562`). ``from gcm_pipeline.api import
Pipeline`` and ``gcm_pipeline.Pipeline`` are the same object.
"""

from gcm_pipeline.config import Config, load_config
from gcm_pipeline.config.robot_spec import available_robots, load_robot
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
    dq_from_matrix,
    dq_from_pos_quat,
    dq_mul,
    dq_to_matrix,
    dq_to_pos_quat,
)
from gcm_pipeline.geometry.pose_blend import dib, dlb, sclerp
from gcm_pipeline.manifold.build import Manifold
from gcm_pipeline.manifold.locate import Location
from gcm_pipeline.manifold.query import GraspManifold
from gcm_pipeline.manifold.search import BestGrasps, NearestReachable
from gcm_pipeline.pipeline import (
    Pipeline,
    RunResult,
    build_manifold,
    check_reachability,
    densify,
    generate_candidates,
    load_manifold,
    publish,
    rank,
)
from gcm_pipeline.pipeline.outputs import export_run
from gcm_pipeline.ranking.metrics import combined_score
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
from gcm_pipeline.robot.model import Robot
from gcm_pipeline.rundir.run import read_run
from gcm_pipeline.study import Study, StudyResult
from gcm_pipeline.table import GraspTable

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
    "export_run",
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
