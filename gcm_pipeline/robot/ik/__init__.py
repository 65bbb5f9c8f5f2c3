"""Inverse kinematics of the grasp frame: :func:`solve_ik`, its backends and result.

* :mod:`~gcm_pipeline.robot.ik.backend`: :func:`solve_ik` (validation, the
  reach pre-filter, backend dispatch, verification by Pinocchio FK), the
  :class:`IKBackend` protocol (raw answers: :class:`BackendAnswer`) and the
  typed :class:`IKResult`;
* :mod:`~gcm_pipeline.robot.ik.pinocchio_backend`: the default backend, in
  stages: closed forms (:mod:`~gcm_pipeline.robot.ik.panda`,
  :mod:`~gcm_pipeline.robot.ik.panda_rounds`,
  :mod:`~gcm_pipeline.robot.ik.analytic_6r`), seeded LM rounds
  (:mod:`~gcm_pipeline.robot.ik.seeds`, :mod:`~gcm_pipeline.robot.ik.lm`),
  sharing one :class:`~gcm_pipeline.robot.ik.candidates.SolveContext`;
* :mod:`~gcm_pipeline.robot.ik.mink_backend`: mink + MuJoCo (imported on first use);
* :mod:`~gcm_pipeline.robot.ik.pool`: the fork pool the targets are split over.
"""

from gcm_pipeline.robot.ik.answer import BackendAnswer
from gcm_pipeline.robot.ik.backend import (
    BACKENDS,
    IK_REASONS,
    IKBackend,
    IKCandidates,
    IKResult,
    Validator,
    check_targets,
    solve_ik,
    verify_solutions,
    world_to_base_targets,
)
from gcm_pipeline.robot.ik.lm import PinocchioIKOptions
from gcm_pipeline.robot.ik.mink_backend import MinkIKOptions

__all__ = [
    "BACKENDS",
    "BackendAnswer",
    "IK_REASONS",
    "IKBackend",
    "IKCandidates",
    "IKResult",
    "MinkIKOptions",
    "PinocchioIKOptions",
    "Validator",
    "check_targets",
    "solve_ik",
    "verify_solutions",
    "world_to_base_targets",
]
