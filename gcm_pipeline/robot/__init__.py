"""Robot models, kinematics, inverse kinematics and manipulability.

* :mod:`~gcm_pipeline.robot.model`: parsed robot specs -> reduced Pinocchio
  models (:class:`Robot`; by name or spec file:
  :func:`gcm_pipeline.config.robot_spec.load_robot`), forward kinematics and grasp-frame
  Jacobians (``LOCAL_WORLD_ALIGNED``);
* :mod:`~gcm_pipeline.robot.ik`: :func:`solve_ik` with the ``pinocchio``
  (batched LM, default) and ``mink`` backends, every success verified by
  Pinocchio forward kinematics;
* :mod:`~gcm_pipeline.robot.manipulability`: Yoshikawa (6-D and
  translational), inverse condition number, joint-limit margin.

Importing this package does not import mink or MuJoCo (only
:mod:`~gcm_pipeline.robot.ik.mink_backend` does, when the backend is used).
"""

from gcm_pipeline.robot.ik import BACKENDS, IKCandidates, IKResult, solve_ik
from gcm_pipeline.robot.manipulability import (
    METRICS,
    inverse_condition_number,
    joint_limit_margin,
    manipulability,
    manipulability_metrics,
    translational_manipulability,
    yoshikawa,
)
from gcm_pipeline.robot.model import Robot, RobotSpec, as_robot

__all__ = [
    "BACKENDS",
    "IKCandidates",
    "IKResult",
    "METRICS",
    "Robot",
    "RobotSpec",
    "as_robot",
    "inverse_condition_number",
    "joint_limit_margin",
    "manipulability",
    "manipulability_metrics",
    "solve_ik",
    "translational_manipulability",
    "yoshikawa",
]
