"""Pairs dropped because no configuration brings them together (``collision/apart.py``).

A link whose every joint turns about the vertical keeps its height over the
table: the checker drops the pair when the link clears the table at home. The
tests measure what the proof claims with coal itself (the distance of the pair
is the same in every configuration) and check that a tilt, a shelf beside the
link and the checker's answers behave as they should.
"""

from __future__ import annotations

import coal
import numpy as np
import pinocchio as pin
import pytest
from helpers import ROOT

from gcm_pipeline import pipeline as P
from gcm_pipeline.config import EnvironmentConfig, load_config
from gcm_pipeline.pipeline import make_checker
from gcm_pipeline.robot.collision import apart as apart_module
from gcm_pipeline.robot.collision.broadphase import BROAD_MARGIN


@pytest.fixture(scope="module", params=["bottle_side.yaml", "bottle_side_ur5.yaml"])
def scene(request: pytest.FixtureRequest):
    cfg = load_config(ROOT / "configs" / request.param)
    robot = P.robot_from_config(cfg)
    return cfg, robot


def _pair_distances(checker, robot, link: str, shape: str, qs: np.ndarray) -> np.ndarray:
    """coal's distance between a link's geometries and a world shape, per configuration."""
    gm = checker._gm
    names = [g.name for g in gm.geometryObjects]
    one = gm.copy()
    one.removeAllCollisionPairs()
    w = names.index(shape)
    for i, name in enumerate(checker.link_names):
        if name == link:
            one.addCollisionPair(pin.CollisionPair(i, w))
    gd = pin.GeometryData(one)
    data = robot.model.createData()
    out = np.empty(len(qs))
    for r, q in enumerate(qs):
        pin.computeDistances(robot.model, data, one, gd, q)
        out[r] = min(res.min_distance for res in gd.distanceResults)
    return out


def test_the_shoulder_over_the_table_is_apart_and_its_distance_never_changes(scene) -> None:
    cfg, robot = scene
    checker = make_checker(robot, cfg.environment, cfg.object, cfg.robot.base_pose.matrix())
    shoulder = "panda_link1" if robot.nq == 7 else "shoulder_link"
    assert checker.pairs_apart == ((shoulder, "table"),)
    qs = robot.random_configurations(400, 5)
    d = _pair_distances(checker, robot, shoulder, "table", qs)
    assert d.min() > BROAD_MARGIN
    assert d.max() - d.min() < 1e-9  # the same height in every configuration
    # the next link is not: joint 2 lifts it
    upper = "panda_link2" if robot.nq == 7 else "upper_arm_link"
    d2 = _pair_distances(checker, robot, upper, "table", qs)
    assert d2.max() - d2.min() > 0.01


def test_the_checker_without_the_apart_pairs_gives_the_same_reasons(scene, monkeypatch) -> None:
    """Dropping the pairs changes no answer: the same reasons as a checker that checks them,
    on random configurations and ones leaning toward the table, in large batches and in
    coal's pools. (``test_near_contact.py`` compares the checker with coal over every
    pair on both sides of contact.)"""
    cfg, robot = scene
    base = cfg.robot.base_pose.matrix()
    checker = make_checker(robot, cfg.environment, cfg.object, base)
    monkeypatch.setattr(apart_module, "pairs_apart", lambda *a, **k: set())
    monkeypatch.setattr("gcm_pipeline.robot.collision.checker.pairs_apart", lambda *a, **k: set())
    every = make_checker(robot, cfg.environment, cfg.object, base)
    assert every.pairs_apart == () and checker.pairs_apart
    rng = np.random.default_rng(8)
    qs = robot.random_configurations(3000, rng)
    qs[:1000, 1] = np.clip(qs[:1000, 1] + 1.2, robot.lower[1], robot.upper[1])  # toward the table
    for mode in ("grasp", "approach"):
        mine = checker.check(qs, mode)
        np.testing.assert_array_equal(mine, every.check(qs, mode))
        np.testing.assert_array_equal(checker.check(qs[:12], mode), mine[:12])  # coal's pools
    assert (checker.check(qs) == "collision_environment").any()


def test_a_tilted_base_or_a_shelf_beside_the_shoulder_keeps_the_pair(panda) -> None:
    """Only heights no joint changes count: a base tilted by a degree lifts the shoulder as
    joint 1 turns; a shelf beside it is at the shoulder's height. A shelf high above is apart."""
    robot = panda
    env = EnvironmentConfig.model_validate({"table": {"height": 0.0}})
    tilt = np.eye(4)
    tilt[:3, :3] = pin.utils.rpyToMatrix(np.deg2rad(1.0), 0.0, 0.0)
    assert make_checker(robot, env, None, tilt).pairs_apart == ()
    shelves = EnvironmentConfig.model_validate(
        {
            "table": {"height": 0.0},
            "obstacles": [
                {"shape": "box", "dims": {"size": [0.2, 0.2, 0.1]}, "pose": {"xyz": [0.3, 0, 0.3]}},
                {"shape": "box", "dims": {"size": [2.0, 2.0, 0.1]}, "pose": {"xyz": [0, 0, 2.0]}},
            ],
        }
    )
    checker = make_checker(robot, shelves, None)
    assert set(checker.pairs_apart) == {("panda_link1", "table"), ("panda_link1", "obstacle_1")}
    assert isinstance(checker._gm.geometryObjects[-1].geometry, coal.Box)
