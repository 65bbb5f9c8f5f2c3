"""Reachability stage: columns, base pose, warm starts, validator, errors."""

from __future__ import annotations

import numpy as np
import pytest

from gcm_pipeline.errors import GeometryError, InputError
from gcm_pipeline.geometry.dualquat import dq_from_matrix
from gcm_pipeline.reach.check import check_reachability, world_to_base_targets
from gcm_pipeline.reach.options import ReachOptions
from gcm_pipeline.robot.ik import verify_solutions
from gcm_pipeline.robot.model import Robot
from gcm_pipeline.table import GraspTable


def _base() -> np.ndarray:
    c, s = np.cos(0.7), np.sin(0.7)
    base = np.eye(4)
    base[:3, :3] = [[c, -s, 0], [s, c, 0], [0, 0, 1]]
    base[:3, 3] = [0.4, -0.2, 0.75]
    return base


def _table(panda: Robot, base: np.ndarray) -> tuple[GraspTable, np.ndarray]:
    """10 candidates, 10 interpolated copies of candidate poses, 2 far poses."""
    q = panda.random_configurations(10, 3)
    local = panda.fk(q)
    far = local[:2].copy()
    far[:, :3, 3] += [2.0, 0.0, 0.0]
    local = np.concatenate([local, local, far])
    n = len(local)
    origin = np.array(["candidate"] * 10 + ["interpolated"] * 10 + ["candidate"] * 2)
    vertices = np.full((n, 3), -1)
    weights = np.full((n, 3), np.nan)
    for i in range(10):
        # row 10 + i has the pose of candidate i, which carries the largest weight
        vertices[10 + i] = [(i + 1) % 10, i, (i + 2) % 10]
        weights[10 + i] = [0.2, 0.7, 0.1]
    table = GraspTable(
        {
            "dq": dq_from_matrix(base @ local),
            "origin": origin,
            "vertices": vertices,
            "weights": weights,
        }
    )
    return table, local


def test_columns_and_base_pose(panda: Robot):
    base = _base()
    grasps, local = _table(panda, base)
    out = check_reachability(grasps, panda, ReachOptions(base_pose=base))
    n = len(grasps)
    for col in ("dq", "origin", "vertices", "weights"):
        assert out[col] is grasps[col]
    assert out["reachable"].dtype == bool and out["reachable"].shape == (n,)
    assert out["q"].shape == (n, 7) and out["pos_err"].shape == (n,)
    assert out["reachable"][:20].all()
    assert not out["reachable"][20:].any()
    assert list(out["reason"][20:]) == ["out_of_reach"] * 2
    assert np.all(out["reason"][:20] == "")
    assert np.isnan(out["q"][20:]).all()
    ok = out["reachable"]
    pe, re, inside = verify_solutions(panda, out["q"][ok], local[ok])
    assert np.all(pe <= 1e-4) and np.all(re <= 1e-3) and inside.all()
    np.testing.assert_allclose(world_to_base_targets(grasps["dq"], base), local, atol=1e-12)


def test_interpolated_rows_are_seeded_by_their_heaviest_vertex(panda: Robot):
    base = _base()
    grasps, _ = _table(panda, base)
    out = check_reachability(grasps, panda, ReachOptions(base_pose=base))
    # a warm start at the exact solution converges without moving
    np.testing.assert_allclose(out["q"][10:20], out["q"][:10], atol=1e-12)
    cold = check_reachability(grasps, panda, ReachOptions(base_pose=base, warm_start=False))
    assert cold["reachable"][:20].all()


def test_validator_and_candidates(panda: Robot):
    grasps, _ = _table(panda, np.eye(4))

    def wrist_rule(q: np.ndarray) -> np.ndarray:
        return np.where(q[:, 6] > 0, "collision_self", "")

    out, cand = check_reachability(
        grasps,
        panda,
        ReachOptions(ik_options={"first_round_seeds": 2}),
        validator=wrist_rule,
        return_candidates=True,
    )
    assert np.all(out["q"][out["reachable"], 6] <= 0)
    assert set(out["reason"][~out["reachable"]]) <= {"collision_self", "out_of_reach"}
    assert cand.q.shape[1] == 7 and np.all(cand.index < len(grasps))
    assert set(cand.reason) <= {"", "collision_self"}


def test_table_without_provenance_and_mink(panda: Robot):
    local = panda.fk(panda.random_configurations(4, 0))
    grasps = GraspTable({"dq": dq_from_matrix(local)})
    out = check_reachability(grasps, panda, ReachOptions(backend="mink"))
    assert out["reachable"].all()


def test_errors(panda: Robot):
    with pytest.raises(InputError, match="no column 'dq'"):
        check_reachability(GraspTable({"x": np.zeros(3)}), panda)
    dq = dq_from_matrix(panda.fk(panda.home))
    bad = np.repeat(dq, 2, axis=0)
    bad[1, :4] *= 2.0
    with pytest.raises(GeometryError, match="row 1 is not a unit dual quaternion"):
        check_reachability(GraspTable({"dq": bad}), panda)
    with pytest.raises(GeometryError, match=r"shape \(N, 8\)"):
        check_reachability(GraspTable({"dq": np.zeros((2, 7))}), panda)
    base = np.eye(4)
    base[0, 0] = 2.0
    with pytest.raises(GeometryError, match="base_pose"):
        check_reachability(GraspTable({"dq": dq}), panda, ReachOptions(base_pose=base))
    grasps = GraspTable({"dq": dq, "vertices": np.array([[5, -1, -1]])})
    with pytest.raises(InputError, match="'vertices' row 0"):
        check_reachability(grasps, panda)
    with pytest.raises(InputError, match="position_tolerance"):
        check_reachability(GraspTable({"dq": dq}), panda, ReachOptions(position_tolerance=0))


def test_collisions_and_approach(panda: Robot):
    from gcm_pipeline.config import ApproachConfig, EnvironmentConfig
    from gcm_pipeline.pipeline import approach_move, make_checker

    grasps = GraspTable({"dq": dq_from_matrix(panda.fk(panda.random_configurations(12, 5)))})
    env = EnvironmentConfig()
    approach = ReachOptions(approach=approach_move(ApproachConfig()))
    out = check_reachability(grasps, panda, approach, checker=make_checker(panda, env))
    ok = out["reachable"]
    checker = make_checker(panda, env)
    assert np.all(checker.check(out["q"][ok]) == "")
    assert np.all(np.isnan(out["clearance"][~ok])) and np.all(out["clearance"][ok] > 0)
    allowed = {"", "collision_self", "collision_environment", "collision_object", "approach"}
    assert set(out["reason"]) <= allowed | {"out_of_reach", "joint_limits", "no_ik"}
    # a prebuilt checker does the same; another validator runs after it
    same = check_reachability(grasps, panda, approach, checker=checker)
    assert np.array_equal(same["reason"], out["reason"])
    vetoed = check_reachability(
        grasps, panda, checker=checker, validator=lambda q: np.full(len(q), "veto")
    )
    assert not vetoed["reachable"].any()
    assert set(vetoed["reason"]) <= (allowed - {"", "approach"}) | {"veto", "out_of_reach"}
    assert "veto" in set(vetoed["reason"])
    # without a checker: pure IK, no clearance
    assert "clearance" not in check_reachability(grasps, panda).columns
