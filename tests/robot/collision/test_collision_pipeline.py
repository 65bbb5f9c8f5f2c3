"""Acceptance of issue #5 "Reachable means collision-free" on configs/bottle_side.yaml.

The whole pipeline runs (candidates -> manifold -> densify -> reachability with
collision and approach checks -> ranking); then every reachable grasp's
configuration is checked by Pinocchio's own ``computeCollisions`` (coal's complete
answer: contact information on) on a world built here from the config values, on
the *unreduced* example-robot-data model and its own collision geometry (fingers
set to the spec's opening), sharing no code with the stage: no arm link below the
table or through it, no arm link in the bottle, the gripper at most
``contact_tolerance`` deep in it, no self-collision.
"""

from __future__ import annotations

import coal
import example_robot_data
import numpy as np
import pinocchio as pin
import pytest
from helpers import BOTTLE, complete_answers

from gcm_pipeline.geometry.dualquat import dq_to_matrix
from gcm_pipeline.pipeline import Pipeline

GRIPPER = ("panda_hand", "panda_leftfinger", "panda_rightfinger")


@pytest.fixture(scope="module")
def run():
    return Pipeline.from_yaml(BOTTLE).run(write=False, progress=False)


def _world(cfg):
    """Robot (9 DoF) + table + bottle, pairs by what must never touch."""
    erd = example_robot_data.load("panda")
    model, gm = erd.model, erd.collision_model.copy()  # SRDF-filtered self pairs
    n_rob = gm.ngeoms
    self_pairs = [(int(p.first), int(p.second)) for p in gm.collisionPairs]
    base_inv = np.linalg.inv(cfg.robot.base_pose.matrix())

    table = cfg.environment.table
    sx, sy, sz = table.size
    t_world = np.eye(4)
    t_world[:3, 3] = [table.center_xy[0], table.center_xy[1], table.height - sz / 2]
    obj = cfg.object
    assert obj.shape == "cylinder"
    r, h = obj.dims.radius, obj.dims.height
    tol = cfg.environment.contact_tolerance
    centre = np.eye(4)
    centre[2, 3] = h / 2  # the bottle stands on its base
    o_world = obj.pose.matrix() @ centre

    def add(name, world, geom):
        m = base_inv @ world
        return gm.addGeometryObject(
            pin.GeometryObject(name, 0, 0, pin.SE3(m[:3, :3], m[:3, 3]), geom)
        )

    it = add("table", t_world, coal.Box(sx, sy, sz))
    io = add("bottle", o_world, coal.Cylinder(r, h))
    ic = add("bottle_core", o_world, coal.Cylinder(r - tol, h - 2 * tol))
    gm.removeAllCollisionPairs()
    kinds = []
    for a, b in self_pairs:
        gm.addCollisionPair(pin.CollisionPair(a, b))
        kinds.append("self")
    for i in range(n_rob):
        name = gm.geometryObjects[i].name
        if not name.startswith("panda_link0"):  # the base stands on the table
            gm.addCollisionPair(pin.CollisionPair(i, it))
            kinds.append("table")
        gripper = name.rsplit("_", 1)[0] in GRIPPER
        gm.addCollisionPair(pin.CollisionPair(i, ic if gripper else io))
        kinds.append("bottle")
    return model, gm, np.array(kinds)


def test_bottle_side_reachable_grasps_are_collision_free(run):
    cfg, g = run.config, run.grasps
    assert cfg.environment.table is not None and cfg.environment.table.height == 0.0
    assert cfg.object is not None and cfg.object.pose.xyz[0] == pytest.approx(0.5)
    reachable = np.asarray(g["reachable"], dtype=bool)
    reasons = np.asarray(g["reason"]).astype(str)
    assert reachable.sum() >= 100
    # the checks did reject grasps (not a vacuous pass)
    rejected = np.isin(reasons, ["collision_environment", "collision_self", "collision_object"])
    assert rejected.sum() + (reasons == "approach").sum() > 0

    model, gm, kinds = _world(cfg)
    data, gd = model.createData(), complete_answers(pin.GeometryData(gm))
    fingers = list(run.robot.spec.locked_joints.values())  # open: 0.04 m each
    q_all = np.asarray(g["q"], dtype=float)[reachable]
    assert np.all(np.isfinite(q_all))
    # the oracle sees collisions: leaning forward puts the hand through the table
    lean = np.array([0.0, 1.6, 0.0, -0.5, 0.0, 1.57, 0.785, *fingers])
    pin.computeCollisions(model, data, gm, gd, lean, False)
    assert any(
        res.isCollision() for res, k in zip(gd.collisionResults, kinds, strict=True) if k == "table"
    )
    hits: dict[str, int] = {"self": 0, "table": 0, "bottle": 0}
    lowest = np.inf
    for q in q_all:
        full = np.concatenate([q, fingers])
        pin.computeCollisions(model, data, gm, gd, full, False)
        hit = np.array([res.isCollision() for res in gd.collisionResults])
        for kind in hits:
            hits[kind] += int(hit[kinds == kind].any())
        # no joint origin and no collision mesh vertex of the arm below the table
        for k, go in enumerate(gm.geometryObjects):
            if go.parentJoint == 0 or not isinstance(go.geometry, coal.BVHModelBase):
                continue
            verts = np.asarray(go.geometry.vertices())
            world = cfg.robot.base_pose.matrix() @ gd.oMg[k].homogeneous
            z = verts @ world[2, :3] + world[2, 3]
            lowest = min(lowest, float(z.min()))
    assert hits == {"self": 0, "table": 0, "bottle": 0}
    assert lowest > 0.0
    # the stage's own clearance agrees: the arm touches neither table nor bottle
    clearance = np.asarray(g["clearance"], dtype=float)[reachable]
    assert np.all(clearance > 0)
    # and a reachable grasp is really reached
    assert np.nanmax(np.asarray(g["pos_err"])[reachable]) <= cfg.ik.position_tolerance


def test_bottle_side_reachable_grasps_have_an_approach_and_a_pregrasp(run):
    """Every reachable grasp has a pre-grasp configuration that reaches the pre-grasp
    pose (Pinocchio FK) and touches neither table nor bottle (the independent world,
    no finger contact allowed: the whole bottle for every link), within the joint
    steps the approach allows; every grasp that failed for ``approach`` has no solution."""
    cfg, g = run.config, run.grasps
    reachable = np.asarray(g["reachable"], dtype=bool)
    rows = np.flatnonzero(reachable)
    assert rows.size > 100
    appr = cfg.approach
    model, gm, kinds = _world(cfg)
    # no contact tolerance on the way in: the gripper against the whole bottle too
    bottle = next(i for i, go in enumerate(gm.geometryObjects) if go.name == "bottle")
    core = next(i for i, go in enumerate(gm.geometryObjects) if go.name == "bottle_core")
    for k, cp in enumerate(gm.collisionPairs):
        if cp.second == core:
            gm.collisionPairs[k] = pin.CollisionPair(int(cp.first), bottle)
    data, gd = model.createData(), complete_answers(pin.GeometryData(gm))
    fingers = list(run.robot.spec.locked_joints.values())
    base = cfg.robot.base_pose.matrix()
    back = np.eye(4)
    back[2, 3] = -appr.distance
    q, q_pre = np.asarray(g["q"])[rows], np.asarray(g["q_pregrasp"])[rows]
    assert np.all(np.isfinite(q_pre))
    assert np.all(np.abs(q_pre - q) <= appr.steps * appr.max_joint_step)
    targets = np.linalg.inv(base) @ dq_to_matrix(g["dq"][rows]) @ back
    reached = run.robot.fk_pinocchio(q_pre)
    pos = np.linalg.norm(reached[:, :3, 3] - targets[:, :3, 3], axis=1)
    assert pos.max() <= cfg.ik.position_tolerance
    for qp in q_pre:
        pin.computeCollisions(model, data, gm, gd, np.concatenate([qp, fingers]), False)
        assert not any(res.isCollision() for res in gd.collisionResults)
    approach_rows = np.asarray(g["reason"]) == "approach"
    assert approach_rows.any()
    assert np.isnan(g["q"][approach_rows]).all()
    assert np.isfinite(g["q_rejected"][approach_rows]).all()
