"""Every branch of a 6R arm: the stage reaches what an independent enumeration reaches.

The bottle config (smaller) on the shipped UR5 and on a user's UR10 spec: for every
grasp, every IK branch from EAIK built from Pinocchio's own kinematics plus a
multi-start LM (``benchmarks/bench_branches.py``'s reference, which shares no code with
the stage's branch search), each checked with the run's checker at every 2 pi copy
where a move failed. The stage must reach >= 99 % of what the reference reaches, and
nothing the independent re-check (FK, limits, every collision pair) refutes.
"""

from __future__ import annotations

import sys

import numpy as np
import pytest
from helpers import ROOT

from gcm_pipeline import pipeline as P
from gcm_pipeline.config import load_config
from gcm_pipeline.geometry.dualquat import dq_to_matrix

sys.path.insert(0, str(ROOT / "benchmarks"))

import bench_branches as bench  # noqa: E402

SMALL = ["candidates.count=36", "densify.subdivisions=2"]


@pytest.mark.parametrize("arm", ["ur5", "ur10_spec"])
def test_stage_reaches_every_grasp_some_branch_reaches(arm: str) -> None:
    cfg = load_config(bench.CONFIG, [f"robot.spec={bench.ARMS[arm]}", *SMALL])
    candidates = P.generate_candidates(cfg)
    grasps = P.densify(candidates, P.build_manifold(candidates, cfg), cfg)
    robot = P.robot_from_config(cfg)
    with P.reachability_engine(robot, cfg) as engine:
        done = P.check_reachability(grasps, robot, cfg, engine=engine)
        targets = np.linalg.inv(cfg.robot.base_pose.matrix()) @ dq_to_matrix(np.asarray(done["dq"]))
        tol = (cfg.ik.position_tolerance, cfg.ik.orientation_tolerance)
        branches, stats = bench.reference_branches(robot, targets, 16, tol)
        ref = bench.reference_reachable(engine, robot, targets, branches)
        # the first branch alone (no step 3) misses some: the test can fail
        engine.alternatives = 0
        first_only = np.asarray(
            P.check_reachability(grasps, robot, cfg, engine=engine)["reachable"], dtype=bool
        )
    reach = np.asarray(done["reachable"], dtype=bool)
    assert stats["eaik_branches"] >= 4 * len(done)
    assert np.count_nonzero(ref & ~first_only) > 0
    assert np.count_nonzero(reach & ref) / np.count_nonzero(ref) >= 0.99
    q = np.asarray(done["q"], dtype=float)
    fp = bench.verify(robot, cfg, q[reach], targets[reach])
    assert fp["false_positives"] == 0, fp
    assert np.count_nonzero(reach & ~ref) == 0  # nothing the reference cannot reach either
