"""A run's config as the manifold queries take it; the queryable manifold of a run (directory)."""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from gcm_pipeline.config.run import Config, load_config
from gcm_pipeline.errors import InputError
from gcm_pipeline.manifold.build import Manifold
from gcm_pipeline.manifold.query import GraspManifold
from gcm_pipeline.pipeline.reach import ReachabilityCheck, robot_from_config
from gcm_pipeline.ranking.metrics import DEFAULT_COMBINED_WEIGHTS
from gcm_pipeline.robot.manipulability import manipulability_metrics
from gcm_pipeline.robot.model import Robot
from gcm_pipeline.rundir import run as run_files
from gcm_pipeline.table import GraspTable


@dataclass(frozen=True)
class ConfigRunQueries:
    """A run's config as the queries take it (a :class:`~.manifold.run_queries.RunQueries`).

    Args:
        config: The run's config.
    """

    config: Config

    @property
    def ranking_metric(self) -> str:
        """``ranking.metric``."""
        return self.config.ranking.metric

    @property
    def combined_weights(self) -> Mapping[str, float]:
        """``ranking.weights``, else the default weights of the ``combined`` metric."""
        return self.config.ranking.weights or DEFAULT_COMBINED_WEIGHTS

    def load_robot(self) -> Robot:
        """The robot of ``robot.spec``."""
        return robot_from_config(self.config)

    def reachability(self, robot: Robot, cfg: Config) -> ReachabilityCheck:
        """A :class:`ReachabilityCheck` of ``robot`` with ``cfg``."""
        return ReachabilityCheck(robot, cfg)

    def robot_metrics(self, robot: Robot, q: np.ndarray) -> Mapping[str, np.ndarray]:
        """The manipulability metrics of configurations ``q`` (N, nq) [rad]."""
        return manipulability_metrics(robot, q)


def grasp_manifold(
    manifold: Manifold, grasps: GraspTable, cfg: Config, robot: Robot | None = None
) -> GraspManifold:
    """The queryable manifold of a run: its triangles and grasp table, queried as ``cfg`` says.

    ``densify.method`` is the blend, ``manifold.orientation_scale`` the pose
    metric's ``L``; reachability, robot metrics and ranking weights come from
    the rest of ``cfg`` (:class:`ConfigRunQueries`).
    """
    return GraspManifold(
        manifold,
        grasps,
        method=cfg.densify.method,
        run=ConfigRunQueries(cfg),
        robot=robot,
        orientation_scale=cfg.manifold.orientation_scale,
    )


def load_manifold(run_dir: str | Path) -> GraspManifold:
    """Load the queryable manifold of a run directory (``gcm run`` output).

    Reads ``grasps.csv``, ``manifold.npz``, ``summary.json`` and
    ``config.yaml`` (the blend method, the robot and what decides
    reachability).

    Raises:
        InputError: Not a run directory, or a file in it is missing or unreadable.
        ConfigError: Its ``config.yaml`` is invalid.
    """
    run = run_files.read_run(run_dir)
    path = Path(run_dir) / "config.yaml"
    if not path.is_file():
        raise InputError(f"not a run directory: {run_dir} lacks config.yaml")
    return grasp_manifold(run.manifold, run.grasps, load_config(path))
