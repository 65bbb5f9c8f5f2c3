"""Straight-line moves (approach, retreat) on the real Panda model, with independent checks.

The soundness tests re-check accepted moves without the module's bounds: the
joint path is sampled densely and every corner of the gripper's collision
geometry, placed by Pinocchio's own kinematics, must stay within
``max_deviation`` of its straight line; every grid point must be collision-free
for Pinocchio's ``computeCollisions`` over all pairs (coal's complete answer:
contact information on).
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pinocchio as pin
import pytest
from helpers import complete_answers

from gcm_pipeline.config import EnvironmentConfig
from gcm_pipeline.errors import InputError
from gcm_pipeline.pipeline import make_checker
from gcm_pipeline.reach.deviation import gripper_radius
from gcm_pipeline.reach.move_check import check_moves
from gcm_pipeline.reach.moves import Move, move_poses
from gcm_pipeline.reach.path import SUBSTEPS, plan_moves
from gcm_pipeline.robot.collision import REASON_ENVIRONMENT, gripper_links
from gcm_pipeline.robot.ik import solve_ik


def _pose(p, z):
    z = np.asarray(z, float) / np.linalg.norm(z)
    x = np.cross([0.0, 1.0, 0.0], z)
    x /= np.linalg.norm(x)
    t = np.eye(4)
    t[:3, :3] = np.c_[x, np.cross(z, x), z]
    t[:3, 3] = p
    return t


TOP_DOWN = _pose([0.5, 0.0, 0.2], [0, 0, -1])  # clear, approach from above
FROM_BELOW = _pose([0.45, 0.1, 0.3], [0, 0, 1])  # approach upward, from under the table
APPROACH = Move(distance=0.10, direction=(0, 0, -1), frame="grasp", steps=10)


def _approach(checker):
    return lambda q, rows: checker.check(q, mode="approach")


@pytest.fixture(scope="module")
def robot(panda):
    """The shared Panda (conftest.py) under this module's name."""
    return panda


@pytest.fixture(scope="module")
def checker(robot):
    return make_checker(robot, EnvironmentConfig())


@pytest.fixture(scope="module")
def radius(robot):
    return gripper_radius(robot)


@pytest.fixture(scope="module")
def solved(robot, checker):
    targets = np.array([TOP_DOWN, FROM_BELOW])
    res = solve_ik(robot, targets)
    assert res.success.all(), res.reason
    assert (checker.check(res.q) == "").all()  # both grasps themselves are free
    return targets, res


def test_move_offsets_and_poses():
    poses = np.array([TOP_DOWN, FROM_BELOW])
    d = APPROACH.offsets(poses)
    np.testing.assert_allclose(d, [[0, 0, 0.1], [0, 0, -0.1]], atol=1e-12)  # back along z
    lift = Move(distance=0.05, direction=(0, 0, 2.0), frame="base", holding=True)
    np.testing.assert_allclose(lift.offsets(poses), [[0, 0, 0.05]] * 2)
    wp = move_poses(poses, d, 4)
    assert wp.shape == (5, 2, 4, 4)
    np.testing.assert_allclose(wp[0], poses)
    back = np.eye(4)
    back[2, 3] = -0.1
    np.testing.assert_allclose(wp[-1, 0], TOP_DOWN @ back, atol=1e-12)
    np.testing.assert_allclose(wp[:, :, :3, :3], np.broadcast_to(poses[:, :3, :3], (5, 2, 3, 3)))


def test_gripper_radius_bounds_the_hand(robot, radius):
    # the Panda hand is about 0.2 m wide, its base 0.1034 m behind the TCP
    assert 0.12 < radius < 0.25


def test_top_down_accepted_from_below_rejected(robot, checker, solved, radius):
    targets, res = solved
    out = check_moves(robot, targets, res.q, APPROACH, _approach(checker), gripper_radius=radius)
    assert out.ok.tolist() == [True, False]
    assert out.reason[1] == REASON_ENVIRONMENT  # the arm goes through the table
    assert 1 <= out.failed_step[1] <= 10
    # the pre-grasp configuration reaches the pre-grasp pose, collision-free
    pre = move_poses(targets[:1], APPROACH.offsets(targets[:1]), 10)[-1, 0]
    reached = robot.fk_pinocchio(out.q_end[0])[0]
    np.testing.assert_allclose(reached, pre, atol=2e-4)
    assert checker.check(out.q_end[0])[0] == ""
    assert 0 < out.deviation[0] <= APPROACH.max_deviation
    assert np.isnan(out.q_end[1]).all() and np.isnan(out.q_path[1]).all()
    np.testing.assert_allclose(out.q_path[0, 0], res.q[0])


def test_joint_step_bound_zero_distance_and_invalid(robot, checker, solved, radius):
    targets, res = solved
    tight = dataclasses.replace(APPROACH, max_joint_step=1e-4)
    out = check_moves(
        robot, targets[:1], res.q[:1], tight, _approach(checker), gripper_radius=radius
    )
    assert out.reason.tolist() == ["joint_step"] and out.failed_step[0] == 1
    zero = dataclasses.replace(APPROACH, distance=0.0)
    out = check_moves(robot, targets, res.q, zero, _approach(checker), gripper_radius=radius)
    assert out.ok.all()
    np.testing.assert_allclose(out.q_end, res.q)
    nan_q = np.full((1, robot.nq), np.nan)
    out = check_moves(
        robot, targets[:1], nan_q, APPROACH, _approach(checker), gripper_radius=radius
    )
    assert out.reason.tolist() == ["invalid"]


def test_deviation_bound_can_reject(robot, solved, radius):
    targets, res = solved
    strict = dataclasses.replace(APPROACH, max_deviation=1e-7)
    plan = plan_moves(robot, targets[:1], res.q[:1], strict, gripper_radius=radius)
    assert plan.reason.tolist() == ["deviation"]


def test_colliding_path_gets_a_second_path_with_grid_waypoints(robot, radius):
    """A path rejected at a grid point is planned again with a waypoint at every grid
    point; it is accepted only when those grid points pass the check too."""
    rng = np.random.default_rng(5)
    q0 = robot.random_configurations(80, rng)
    poses = robot.fk(q0)
    offsets = APPROACH.offsets(poses)
    line = move_poses(poses, offsets, APPROACH.steps)  # (steps + 1, N, 4, 4)
    checked = []

    def near_line(q, rows):
        """'collision' for grid points more than 0.2 mm off every grid pose of their line.

        (Grid poses are 1 cm apart: the nearest is a point's own.)
        """
        want = line[1:, rows, :3, 3]  # (K, steps, 3)
        off = np.linalg.norm(robot.fk(q)[:, None, :3, 3] - want, axis=2).min(axis=1)
        checked.append((q.copy(), off))
        return np.where(off > 2e-4, "collision_test", "")

    first = plan_moves(robot, poses, q0, APPROACH, gripper_radius=radius)
    out = check_moves(robot, poses, q0, APPROACH, near_line, gripper_radius=radius)
    assert first.ok.sum() >= 20
    # first paths interpolate between few waypoints: most grid points are off by more;
    # the second plans' grid waypoints are checked in up to four batches after the first
    # paths': where each first path collided, before it, the rest of the inner ones, the ends
    assert 2 <= len(checked) <= 5
    rejected_first = np.flatnonzero(first.ok)[
        (checked[0][1].reshape(-1, APPROACH.steps) > 2e-4).any(axis=1)
    ]
    assert rejected_first.size >= 10
    # the second paths put every grid point on the line (waypoint tolerance 0.1 mm)
    assert out.ok[rejected_first].sum() >= 0.8 * rejected_first.size
    for i in np.flatnonzero(out.ok):
        reached = robot.fk(out.q_path[i])[:, :3, 3]
        assert np.linalg.norm(reached - line[:, i, :3, 3], axis=1).max() <= 2e-4
        assert out.deviation[i] <= APPROACH.max_deviation
    assert set(out.reason[~out.ok]) <= {"collision_test", "no_ik", "joint_step", "deviation"}


def test_knot_check_only_stops_moves_that_would_collide(robot, radius):
    """Checking grid waypoints as they are found gives the moves whose finished
    grid path is free: the same paths, no more and no fewer."""
    rng = np.random.default_rng(9)
    q0 = robot.random_configurations(120, rng)
    poses = robot.fk(q0)

    # a 'collision' depending on the configuration only: elbow and wrist bent together
    def check(q, rows):
        return np.where(q[:, 3] + q[:, 5] > 1.2, "collision_test", "")

    plain = plan_moves(robot, poses, q0, APPROACH, gripper_radius=radius, grid_knots=True)
    early = plan_moves(
        robot, poses, q0, APPROACH, gripper_radius=radius, grid_knots=True, knot_check=check
    )
    # checking each move's waypoints up to some step first changes nothing
    pause = rng.integers(1, APPROACH.steps + 1, size=len(poses))
    paused = plan_moves(
        robot,
        poses,
        q0,
        APPROACH,
        gripper_radius=radius,
        grid_knots=True,
        knot_check=check,
        check_first=pause,
    )
    # the same moves pass, on the same paths; a failing move may report another failure
    for field in ("ok", "q_path", "deviation", "waypoints", "knots"):
        np.testing.assert_array_equal(getattr(early, field), getattr(paused, field))
    rows = np.flatnonzero(plain.ok)
    free = rows[
        (check(plain.q_path[rows, 1:].reshape(-1, robot.nq), None) == "")
        .reshape(rows.size, -1)
        .all(axis=1)
    ]
    assert 10 <= free.size < rows.size
    np.testing.assert_array_equal(np.flatnonzero(early.ok), free)
    np.testing.assert_array_equal(early.q_path[free], plain.q_path[free])
    stopped = np.setdiff1d(rows, free)
    assert set(early.reason[stopped]) == {"collision_test"}
    # the step at which a move stops is its first colliding grid point
    hit = (check(plain.q_path[stopped, 1:].reshape(-1, robot.nq), None) != "").reshape(
        stopped.size, -1
    )
    np.testing.assert_array_equal(early.failed_step[stopped], hit.argmax(axis=1) + 1)
    # with check_first, the waypoint there is checked first: a move colliding there fails there
    at_pause = stopped[hit[np.arange(stopped.size), pause[stopped] - 1]]
    at_pause = at_pause[pause[at_pause] < APPROACH.steps]  # the end is never checked first
    assert at_pause.size >= 5
    assert set(paused.reason[at_pause]) == {"collision_test"}
    np.testing.assert_array_equal(paused.failed_step[at_pause], pause[at_pause])
    assert np.any(paused.failed_step[at_pause] != early.failed_step[at_pause])


@pytest.mark.parametrize(
    ("kw", "match"),
    [
        ({"distance": -0.1}, "distance"),
        ({"steps": 0}, "steps"),
        ({"max_joint_step": 0}, "max_joint_step"),
        ({"max_deviation": 0}, "max_deviation"),
        ({"direction": (0, 0, 0)}, "direction"),
        ({"frame": "world"}, "frame"),
    ],
)
def test_move_errors(kw, match):
    with pytest.raises(InputError, match=match):
        Move(**kw)


def _gripper_corners(robot):
    """Corners of every gripper collision geometry's local box: (geometry index, (8, 3))."""
    links = gripper_links(robot)
    gm = robot.build_geometry("collision")
    out = []
    for k, go in enumerate(gm.geometryObjects):
        if robot.model.frames[go.parentFrame].name not in links:
            continue
        go.geometry.computeLocalAABB()
        lo = np.asarray(go.geometry.aabb_local.min_)
        hi = np.asarray(go.geometry.aabb_local.max_)
        corners = np.array(
            [[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])]
        )
        out.append((k, corners))
    return gm, out


def _dense_deviation(robot, knots, offset, per_step=40):
    """Largest distance of a gripper corner from its straight line along the joint path
    (piecewise linear through the IK waypoints ``knots``, NaN rows skipped)."""
    q_path = knots[np.all(np.isfinite(knots), axis=1)]
    gm, corners = _gripper_corners(robot)
    model = robot.model
    data, gd = model.createData(), pin.GeometryData(gm)

    def points(q):
        pin.forwardKinematics(model, data, q)
        pin.updateGeometryPlacements(model, data, gm, gd)
        return np.concatenate(
            [c @ gd.oMg[k].rotation.T + gd.oMg[k].translation for k, c in corners]
        )

    start = points(q_path[0])
    worst = 0.0
    for a, b in zip(q_path[:-1], q_path[1:], strict=True):
        for s in np.linspace(0.0, 1.0, per_step + 1):
            rel = points(a + s * (b - a)) - start
            t = np.clip(rel @ offset / (offset @ offset), 0.0, 1.0)
            worst = max(worst, float(np.linalg.norm(rel - t[:, None] * offset, axis=1).max()))
    return worst


def _exhaustive_collisions(robot, checker, q):
    """Every pair of the checker's full geometry model, Pinocchio's own loop: colliding?"""
    gm = checker.geom_model
    gd = complete_answers(pin.GeometryData(gm))
    data = robot.model.createData()
    return pin.computeCollisions(robot.model, data, gm, gd, q, False)


def test_accepted_moves_are_sound_on_sampled_grasps(robot, radius):
    """No accepted move leaves its line by more than max_deviation (dense samples,
    independent kinematics) or collides at a grid point (exhaustive pair loop)."""
    rng = np.random.default_rng(11)
    checker = make_checker(robot, EnvironmentConfig())
    q0 = robot.random_configurations(400, rng)
    poses = robot.fk(q0)
    free = (checker.check(q0) == "") & (poses[:, 2, 3] > 0.05)
    poses, q0 = poses[free][:60], q0[free][:60]
    moves = [
        APPROACH,
        Move(distance=0.15, direction=(0, 0, 1), frame="base", steps=6, holding=True),
        Move(distance=0.08, direction=(1, 0, 0), frame="grasp", steps=4, max_deviation=0.0005),
    ]
    accepted = 0
    for move, grid_knots in [(m, False) for m in moves] + [(moves[0], True)]:
        if grid_knots:  # the second path of check_moves: a waypoint at every grid point
            plan = plan_moves(robot, poses, q0, move, gripper_radius=radius, grid_knots=True)
            free = np.array(
                [
                    plan.ok[i] and (checker.check(plan.q_path[i, 1:], mode="approach") == "").all()
                    for i in range(len(poses))
                ]
            )
            out = plan._replace(ok=free)
        else:
            out = check_moves(robot, poses, q0, move, _approach(checker), gripper_radius=radius)
        offsets = move.offsets(poses)
        for i in np.flatnonzero(out.ok)[:12]:
            accepted += 1
            dev = _dense_deviation(robot, out.knots[i], offsets[i])
            assert dev <= move.max_deviation + 1e-9, (move, i, dev)
            assert dev <= out.deviation[i] + 1e-9
            for q in out.q_path[i, 1:]:
                assert not _exhaustive_collisions(robot, checker, q)
            # the grid points lie on the path through the waypoints
            fine = np.flatnonzero(np.all(np.isfinite(out.knots[i]), axis=1))
            grid = np.arange(move.steps + 1) * SUBSTEPS
            path = np.stack(
                [np.interp(grid, fine, out.knots[i, fine, j]) for j in range(robot.nq)], axis=1
            )
            np.testing.assert_allclose(out.q_path[i], path, atol=1e-12)
        # every grid point of the path keeps the grasp frame on its line: within
        # max_deviation of the straight segment (a grid point between two IK waypoints
        # is a joint-space blend, so it may sit elsewhere along the line than s_k)
        for i in np.flatnonzero(out.ok)[:5]:
            reached = robot.fk_pinocchio(out.q_path[i])[:, :3, 3]
            line = move_poses(poses[i : i + 1], offsets[i : i + 1], move.steps)[:, 0, :3, 3]
            a, d = line[0], line[-1] - line[0]
            t = np.clip((reached - a) @ d / (d @ d), 0.0, 1.0)
            off_line = np.linalg.norm(reached - a - t[:, None] * d, axis=1)
            assert np.all(off_line <= move.max_deviation), off_line
    assert accepted >= 20
