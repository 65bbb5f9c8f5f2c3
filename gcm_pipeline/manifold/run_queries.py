"""What the grasp manifold's queries take from the run: its robot, checks and metrics.

:class:`~gcm_pipeline.manifold.query.GraspManifold` never reads a config; a
:class:`RunQueries` object (:class:`gcm_pipeline.pipeline.ConfigRunQueries`,
built from the run's config) gives it the run's robot, a :class:`PoseCheck`
that decides reachability exactly as the run did, the robot's metrics and
the ranking's weights.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any, Protocol

import numpy as np

from gcm_pipeline.table import GraspTable

__all__ = ["PoseCheck", "RunQueries"]


class PoseCheck(Protocol):
    """Checks grasp poses the way the run's reachability stage does (one robot, one config)."""

    robot: Any
    config: Any

    def __call__(self, dq: np.ndarray, seeds: np.ndarray | None = None) -> GraspTable:
        """Rows ``dq, reachable, reason, q, ...`` for poses (M, 8), warm starts (M, K, nq)."""
        ...

    def close(self) -> None:
        """Stop any worker processes."""
        ...


class RunQueries(Protocol):
    """What the queries take from the run beyond its geometry.

    :mod:`gcm_pipeline.pipeline` implements it from the run's config; this
    module hands ``config`` (or a ``cfg`` given to a query) back to it unread.
    """

    #: The run's config (``GraspManifold.config``), opaque here.
    config: Any
    #: The ranking metric :meth:`GraspManifold.best` optimises by default.
    ranking_metric: str
    #: Metric -> weight of the ``combined`` metric (the run's ranking weights).
    combined_weights: Mapping[str, float]

    def load_robot(self) -> Any:
        """The run's robot."""
        ...

    def reachability(self, robot: Any, cfg: Any) -> PoseCheck:
        """A check of poses with ``robot`` as a run with config ``cfg`` does it."""
        ...

    def robot_metrics(self, robot: Any, q: np.ndarray) -> Mapping[str, np.ndarray]:
        """The robot's metrics (``yoshikawa`` ...) of configurations (N, nq) [rad]."""
        ...
