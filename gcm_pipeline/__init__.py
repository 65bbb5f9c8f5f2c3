"""gcm_pipeline: grasp configuration manifolds and their reachability.

The public API is listed in ``__all__``; every name in it imports. The names
load on first use (``gcm_pipeline.Pipeline`` imports the pipeline, and
Pinocchio with it), so ``import gcm_pipeline`` and the ``gcm`` command start
fast and Ctrl-C during start-up is an ordinary interrupt. mink, MuJoCo, meshcat
and Ray load only when the ``mink`` IK backend, the meshcat publisher or a
placement study (:class:`Study`) is used.
"""

import importlib
import importlib.util
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:  # the names for type checkers; at run time they load on first use
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

#: Public name -> the module that defines it.
_LAZY = {
    "BestGrasps": "gcm_pipeline.manifold.search",
    "CollisionChecker": "gcm_pipeline.robot.collision",
    "Config": "gcm_pipeline.config",
    "ConfigError": "gcm_pipeline.errors",
    "FrameNotFoundError": "gcm_pipeline.errors",
    "GcmError": "gcm_pipeline.errors",
    "GeometryError": "gcm_pipeline.errors",
    "GraspManifold": "gcm_pipeline.manifold.query",
    "GraspTable": "gcm_pipeline.table",
    "IKResult": "gcm_pipeline.robot.ik",
    "InputError": "gcm_pipeline.errors",
    "Location": "gcm_pipeline.manifold.locate",
    "Manifold": "gcm_pipeline.manifold.build",
    "NearestReachable": "gcm_pipeline.manifold.search",
    "OutputError": "gcm_pipeline.errors",
    "Pipeline": "gcm_pipeline.pipeline",
    "PublishError": "gcm_pipeline.errors",
    "Robot": "gcm_pipeline.robot.model",
    "RobotSpecError": "gcm_pipeline.errors",
    "RunResult": "gcm_pipeline.pipeline",
    "Study": "gcm_pipeline.study",
    "StudyResult": "gcm_pipeline.study",
    "available_robots": "gcm_pipeline.config.robot_spec",
    "build_manifold": "gcm_pipeline.pipeline",
    "check_reachability": "gcm_pipeline.pipeline",
    "combined_score": "gcm_pipeline.ranking.metrics",
    "densify": "gcm_pipeline.pipeline",
    "dib": "gcm_pipeline.geometry.pose_blend",
    "dlb": "gcm_pipeline.geometry.pose_blend",
    "dq_from_matrix": "gcm_pipeline.geometry.dualquat",
    "dq_from_pos_quat": "gcm_pipeline.geometry.dualquat",
    "dq_mul": "gcm_pipeline.geometry.dualquat",
    "dq_to_matrix": "gcm_pipeline.geometry.dualquat",
    "dq_to_pos_quat": "gcm_pipeline.geometry.dualquat",
    "generate_candidates": "gcm_pipeline.pipeline",
    "inverse_condition_number": "gcm_pipeline.robot.manipulability",
    "joint_limit_margin": "gcm_pipeline.robot.manipulability",
    "load_config": "gcm_pipeline.config",
    "load_manifold": "gcm_pipeline.pipeline",
    "load_robot": "gcm_pipeline.config.robot_spec",
    "manipulability": "gcm_pipeline.robot.manipulability",
    "manipulability_metrics": "gcm_pipeline.robot.manipulability",
    "publish": "gcm_pipeline.pipeline",
    "rank": "gcm_pipeline.pipeline",
    "read_run": "gcm_pipeline.rundir.run",
    "sclerp": "gcm_pipeline.geometry.pose_blend",
    "solve_ik": "gcm_pipeline.robot.ik",
    "translational_manipulability": "gcm_pipeline.robot.manipulability",
    "yoshikawa": "gcm_pipeline.robot.manipulability",
}

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


if not TYPE_CHECKING:  # type checkers see the imports above, and typos stay errors

    def __getattr__(name: str) -> Any:
        """Load a public name, or a subpackage (``gcm_pipeline.rundir``), on first use (PEP 562)."""
        module = _LAZY.get(name)
        if module is not None:
            value = getattr(importlib.import_module(module), name)
        elif not name.startswith("_") and importlib.util.find_spec(f"{__name__}.{name}"):
            value = importlib.import_module(f"{__name__}.{name}")
        else:
            raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
        globals()[name] = value  # the next access is a plain lookup
        return value

    def __dir__() -> list[str]:
        """The module's names, the public ones included before they load."""
        return sorted(set(globals()) | set(_LAZY))
