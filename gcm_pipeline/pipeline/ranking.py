"""The ``ranking`` step and the IK branch choice: a config onto :mod:`gcm_pipeline.ranking`."""

from __future__ import annotations

import numpy as np

from gcm_pipeline.config.run import Config, takes_config
from gcm_pipeline.manifold.build import Manifold
from gcm_pipeline.manifold.lattice import row_mesh
from gcm_pipeline.ranking import rank as ranking
from gcm_pipeline.reach import branches
from gcm_pipeline.robot.model import Robot
from gcm_pipeline.table import GraspTable


@takes_config
def branch_scores(grasps: GraspTable, robot: Robot, cfg: Config) -> np.ndarray:
    """The ranking metric of every IK branch (N, K) (``solutions`` column), higher is better.

    ``combined`` normalises each metric over all branches of all reachable
    grasps; ``margin`` and ``score`` are the same for every branch of a grasp, so
    branches are compared by Yoshikawa's index instead (also their weights in
    ``combined`` are left out).
    """
    clearance = grasps["solutions_clearance"] if "solutions_clearance" in grasps else None
    r = cfg.ranking
    return ranking.branch_scores(
        grasps["solutions"], robot, metric=r.metric, weights=r.weights, clearance=clearance
    )


@takes_config
def select_branches(
    grasps: GraspTable, manifold: Manifold, robot: Robot, cfg: Config
) -> GraspTable:
    """Choose one IK branch per grasp (``ik.select``; needs ``ik.solutions`` > 1).

    See :mod:`gcm_pipeline.reach.branches`. A table without branch columns is
    returned unchanged.
    """
    if "solutions" not in grasps:
        return grasps
    edges = row_mesh(grasps, manifold.triangles, manifold.n_vertices).edges
    return branches.select_branches(
        grasps,
        edges,
        branch_scores(grasps, robot, cfg),
        method=cfg.ik.select,
        threshold=cfg.continuity.threshold,
    )


@takes_config
def rank(grasps: GraspTable, robot: Robot, cfg: Config) -> GraspTable:
    """Manipulability metrics and ranks of the reachable grasps (``ranking``).

    See :func:`gcm_pipeline.ranking.rank.rank`; the ``clearance`` and
    ``combined`` metrics need the ``clearance`` column of the collision checks.

    Returns:
        The table with ``manipulability`` (and the other metric columns),
        ``rank`` (1-based among reachable grasps, 0 for unreachable) and
        ``top`` added.
    """
    r = cfg.ranking
    return ranking.rank(grasps, robot, metric=r.metric, top_k=r.top_k, weights=r.weights)
