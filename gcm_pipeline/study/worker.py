"""The placement worker: one process that runs placements one after the other.

A :class:`PlacementWorker` keeps what every placement of a study shares: the
robot model, its IK seed library (cached on the robot by the IK backend) and
the robot's collision geometry (cached on the robot by
:meth:`~gcm_pipeline.robot.model.Robot.build_geometry`), built once when the
worker starts. Per placement it runs :meth:`Pipeline.run
<gcm_pipeline.pipeline.Pipeline.run>` (``write=False``) on the placement's
config with that robot, so a placement gives what ``gcm run`` gives for the
same config; only the collision world (the robot's cached geometry placed with
the placement's object and base poses) is assembled anew.

Under Ray each worker is an actor (:mod:`gcm_pipeline.study.runner`); the same
class runs placements in-process. Results are plain dicts of scalars and NumPy
arrays (no per-grasp objects). The IK runs on one process per worker (no nested
process pools): the study's parallelism is the workers.
"""

from __future__ import annotations

import math
import os
import sys
import time
from typing import Any

import numpy as np

from gcm_pipeline.config.robot_spec import load_robot
from gcm_pipeline.config.run import Config
from gcm_pipeline.errors import GcmError
from gcm_pipeline.geometry.dualquat import dq_from_matrix, dq_to_matrix, dq_to_pos_quat
from gcm_pipeline.pipeline import Pipeline
from gcm_pipeline.ranking.metrics import METRIC_COLUMNS
from gcm_pipeline.robot.ik import solve_ik

__all__ = ["PlacementWorker", "placement_summary"]


def _yaw_deg(matrix: np.ndarray) -> float:
    """Yaw [deg] of a rotation (the z angle of roll-pitch-yaw, fixed axes)."""
    return math.degrees(math.atan2(matrix[1, 0], matrix[0, 0]))


def placement_summary(grasps: Any, cfg: Config) -> dict[str, Any]:
    """The row of ``placements.csv`` for a ranked grasp table (counts and metrics).

    Args:
        grasps: The ranked grasp table of the placement.
        cfg: Its config.

    Returns:
        ``candidates, densified, reachable, coverage, candidates_reachable,
        best_metric, mean_metric, best_manipulability, mean_manipulability``.
    """
    reachable = np.asarray(grasps["reachable"], dtype=bool)
    is_candidate = np.asarray(grasps["origin"]).astype(str) == "candidate"
    metric = np.asarray(grasps[METRIC_COLUMNS[cfg.ranking.metric]], dtype=float)
    manip = np.asarray(grasps["manipulability"], dtype=float)
    n = len(grasps)

    def stat(values: np.ndarray, fn: Any) -> float:
        v = values[reachable & np.isfinite(values)]
        return float(fn(v)) if v.size else math.nan

    return {
        "candidates": int(is_candidate.sum()),
        "densified": int(n),
        "reachable": int(reachable.sum()),
        "coverage": float(reachable.sum() / n) if n else 0.0,
        "candidates_reachable": int((reachable & is_candidate).sum()),
        "best_metric": stat(metric, np.max),
        "mean_metric": stat(metric, np.mean),
        "best_manipulability": stat(manip, np.max),
        "mean_manipulability": stat(manip, np.mean),
    }


def _pose7(dq: np.ndarray) -> np.ndarray:
    """Poses (N, 7) ``x, y, z, qw, qx, qy, qz`` (``qw >= 0``) of unit dual quaternions (N, 8)."""
    pos, quat = dq_to_pos_quat(dq)
    quat = np.where(quat[:, :1] < 0, -quat, quat)
    return np.concatenate([pos, quat], axis=1)


class PlacementWorker:
    """Runs placements with a robot, seed library and collision geometry built once.

    Args:
        warm: A resolved config dict (``Config.to_dict()``) whose robot, seed
            library and collision geometry are built right away, so the first
            placement does not pay for them; None builds them on first use.
    """

    def __init__(self, warm: dict[str, Any] | None = None) -> None:
        self._robots: dict[tuple[str, str | None], Any] = {}
        self.node = self._node()
        self.pid = os.getpid()
        if warm is not None:
            cfg = Config.from_dict(warm, source="study base config")
            robot = self._robot(cfg.robot.spec, cfg.robot.tool)
            self._warm(robot, cfg.seed)

    @staticmethod
    def _node() -> str:
        # a Ray actor's process has imported Ray; an in-process worker asks nothing of it
        ray = sys.modules.get("ray")
        try:
            if ray is not None and ray.is_initialized():
                return str(ray.get_runtime_context().get_node_id())[:8]
        except Exception:  # pragma: no cover - not under Ray
            pass
        return "local"

    def _robot(self, spec: str, tool: str | None) -> Any:
        robot = self._robots.get((spec, tool))
        if robot is None:
            robot = self._robots[(spec, tool)] = load_robot(spec, tool)
        return robot

    @staticmethod
    def _warm(robot: Any, seed: int) -> None:
        """Build the seed library (first IK call) and the collision geometry now."""
        targets = robot.fk(robot.random_configurations(4, seed=seed))
        solve_ik(robot, targets, random_seed=int(seed))
        robot.build_geometry("collision")

    def ready(self) -> dict[str, Any]:
        """Where the worker runs: ``{"node", "pid"}`` (Ray: the call that waits for start-up)."""
        return {"node": self.node, "pid": self.pid}

    def run(self, job: dict[str, Any]) -> dict[str, Any]:
        """Run one placement.

        Args:
            job: ``{"id": int, "config": dict}`` (the resolved config of the
                placement, ``Config.to_dict()``).

        Returns:
            ``{"id", "node", "time_s", "error"}`` plus, on success, the row
            fields of :func:`placement_summary` and the arrays
            ``reachable_mask`` (G,) bool, ``metric`` (G,) and ``manipulability``
            (G,) (NaN where unreachable), ``pose`` (G, 7)
            world grasp poses ``x, y, z, qw, qx, qy, qz``, ``pose_object`` (G, 7)
            the same in the object's frame, ``is_candidate`` (G,), and for the
            study report ``reason_code`` (G,) uint8 (0 reachable, k: the k-th of
            ``reason_names``), ``reason_names`` (K,) and ``q_best`` (nq,) the
            top-ranked grasp's configuration (empty when none is reachable).
            A failure (any exception but an interrupt) comes back as
            ``error = "<Type>: <message>"``.
        """
        t0 = time.perf_counter()
        out: dict[str, Any] = {"id": int(job["id"]), "node": self.node, "error": ""}
        try:
            out.update(self._run(job["config"]))
        except GcmError as exc:
            out["error"] = f"{type(exc).__name__}: {' '.join(str(exc).split())}"
        except Exception as exc:  # a bug or a library error: recorded, the study goes on
            out["error"] = f"{type(exc).__name__}: {' '.join(str(exc).split())}"[:2000]
        out["time_s"] = time.perf_counter() - t0
        return out

    def _run(self, data: dict[str, Any]) -> dict[str, Any]:
        cfg = Config.from_dict(data, source="placement config")
        # one IK process per worker: the study runs the workers in parallel
        cfg = cfg.model_copy(update={"ik": cfg.ik.model_copy(update={"workers": 1})})
        robot = self._robot(cfg.robot.spec, cfg.robot.tool)
        # the pipeline's own sequence of stages (what gcm run does), on this worker's robot
        result = Pipeline(cfg).run(progress=False, write=False, robot=robot)
        grasps = result.grasps
        # the run's config: an object its grasp file names is in it, placed on the table
        cfg = result.config
        reachable = np.asarray(grasps["reachable"], dtype=bool)
        object_pose = cfg.object.pose.matrix() if cfg.object is not None else np.eye(4)
        local = dq_from_matrix(np.linalg.inv(object_pose) @ dq_to_matrix(grasps["dq"]))
        metric = np.asarray(grasps[METRIC_COLUMNS[cfg.ranking.metric]], dtype=float)
        manip = np.asarray(grasps["manipulability"], dtype=float)
        row = placement_summary(grasps, cfg)
        row.update(
            reachable_mask=reachable,
            metric=np.where(reachable, metric, np.nan),
            manipulability=np.where(reachable, manip, np.nan),
            pose=_pose7(grasps["dq"]),
            pose_object=_pose7(local),
            is_candidate=np.asarray(grasps["origin"]).astype(str) == "candidate",
            **_reasons_and_best_q(grasps, reachable),
        )
        return row


def _reasons_and_best_q(grasps: Any, reachable: np.ndarray) -> dict[str, np.ndarray]:
    """``reason_code``, ``reason_names`` and ``q_best`` of a ranked grasp table (the report's)."""
    n = len(grasps)
    reason = np.asarray(grasps["reason"]).astype(str) if "reason" in grasps else np.full(n, "")
    reason = np.where(reachable, "", np.where(reason == "", "unreachable", reason))
    names, codes = np.unique(reason[~reachable], return_inverse=True)
    code = np.zeros(n, dtype=np.uint8)
    code[~reachable] = np.minimum(codes + 1, 255)
    q_best = np.empty(0)
    if "q" in grasps and "rank" in grasps and reachable.any():
        rank = np.asarray(grasps["rank"], dtype=np.int64)
        ranked = np.flatnonzero(rank > 0)
        if ranked.size:
            q_best = np.asarray(grasps["q"], dtype=float)[ranked[np.argmin(rank[ranked])]]
    return {"reason_code": code, "reason_names": names.astype(str), "q_best": q_best}
