"""Collision checker on the real Panda model (example-robot-data), no mocks."""

from __future__ import annotations

import coal
import example_robot_data
import numpy as np
import pinocchio as pin
import pytest
from helpers import complete_answers
from scipy.spatial.transform import Rotation

from gcm_pipeline.config import Config, EnvironmentConfig, ObjectConfig, ObstacleConfig
from gcm_pipeline.errors import ConfigError, InputError
from gcm_pipeline.geometry.shapes import shape_geometry
from gcm_pipeline.pipeline import make_checker
from gcm_pipeline.ranking.metrics import combined_score
from gcm_pipeline.robot.collision import (
    REASON_ENVIRONMENT,
    REASON_OBJECT,
    REASON_SELF,
    CollisionChecker,
    WorldShape,
)
from gcm_pipeline.robot.collision.pairs import KINDS, checker_requests

BOTTLE = {
    "shape": "cylinder",
    "dims": {"radius": 0.035, "height": 0.22},
    "pose": {"xyz": [0.5, 0, 0]},
}


@pytest.fixture(scope="module")
def robot(panda):
    """The shared Panda (conftest.py) under this module's name."""
    return panda


@pytest.fixture(scope="module")
def checker(robot):
    return make_checker(robot, EnvironmentConfig(), ObjectConfig.model_validate(BOTTLE))


def _q(robot, **joints):
    q = np.array(robot.home, dtype=float)
    for k, v in joints.items():
        q[int(k[1:]) - 1] = v
    return q


def test_home_is_free(robot, checker):
    assert checker.check(robot.home).tolist() == [""]
    assert checker.colliding_pairs(robot.home) == []


def test_arm_through_table_is_environment(robot, checker):
    q = _q(robot, j2=1.6, j4=-0.5)  # leaning forward: the hand ends 0.1 m below z = 0
    assert robot.fk(q)[0, 2, 3] < 0
    assert checker.check(q).tolist() == [REASON_ENVIRONMENT]
    pairs = checker.colliding_pairs(q)
    assert ("panda_hand_0", "table", "environment") in pairs


def test_folded_arm_is_self_collision(robot, checker):
    q = _q(robot, j2=1.7, j4=-3.0)  # elbow folded shut, wrist back onto the base
    assert checker.check(q).tolist() == [REASON_SELF]
    kinds = {k for _, _, k in checker.colliding_pairs(q)}
    assert kinds == {"self"}


def test_object_at_hand_is_object_collision(robot):
    tcp = robot.fk(robot.home)[0]
    at_wrist = (tcp[:3, 3] - 0.09 * tcp[:3, 2]).tolist()  # 9 cm behind the TCP: in the hand
    obj = ObjectConfig.model_validate(
        {"shape": "box", "dims": {"size": [0.05, 0.05, 0.05]}, "pose": {"xyz": at_wrist}}
    )
    c = make_checker(robot, EnvironmentConfig(), obj)
    assert c.check(robot.home).tolist() == [REASON_OBJECT]


def test_contact_tolerance_at_finger_pads(robot):
    """A sphere between the open fingers: touching within the tolerance is a grasp."""
    tcp = robot.fk(robot.home)[0, :3, 3].tolist()

    def reason(radius, tol):
        obj = ObjectConfig.model_validate(
            {"shape": "sphere", "dims": {"radius": radius}, "pose": {"xyz": tcp}}
        )
        c = make_checker(robot, EnvironmentConfig(contact_tolerance=tol), obj)
        return c.check(robot.home)[0]

    assert reason(0.030, 0.0) == ""  # fits between the fingers (8 cm opening)
    assert reason(0.041, 0.0) == REASON_OBJECT  # presses 1 mm into the pads
    assert reason(0.041, 0.005) == ""  # 1 mm < tolerance: contact allowed
    assert reason(0.050, 0.005) == REASON_OBJECT  # 10 mm > tolerance


def test_clearance_free_and_colliding(robot, checker):
    c_home = checker.clearance(robot.home)[0]
    tcp_z = robot.fk(robot.home)[0, 2, 3]
    assert 0.05 < c_home < tcp_z  # nearest link above the table, below the hand height
    q = _q(robot, j2=1.6, j4=-0.5)
    assert checker.clearance(q)[0] <= 0.0
    # lowering the arm toward the table decreases the clearance
    qs = np.array([_q(robot, j2=a, j4=-0.5) for a in (0.5, 1.0, 1.3)])
    cl = checker.clearance(qs)
    assert np.all(np.diff(cl) < 0) and cl[-1] > 0


def test_batch_shapes_and_nonfinite(robot, checker):
    qs = np.vstack([robot.home, np.full(robot.nq, np.nan)])
    assert checker.check(qs).tolist() == ["", ""]
    assert np.isnan(checker.clearance(qs)[1])
    assert checker.check(np.zeros((0, robot.nq))).shape == (0,)
    with pytest.raises(InputError, match="shape"):
        checker.check(np.zeros((2, 3)))


@pytest.mark.parametrize("precision", [float("nan"), float("inf"), -1e-3, "1 mm", None])
def test_clearance_rejects_a_precision_that_is_not_a_distance(robot, checker, precision):
    # a NaN precision measured no pair: rows far above their minimum, or inf on a robot
    # without polytopes; one clear error instead
    with pytest.raises(InputError, match="precision"):
        checker.clearance(robot.home, precision)
    assert checker.clearance(robot.home, 0) == checker.clearance(robot.home, 0.0)


def _oracle(obj_pose, obstacle_xyz):
    """Independent world on the *unreduced* example-robot-data model and its own geometry."""
    erd = example_robot_data.load("panda")
    model, gm = erd.model, erd.collision_model.copy()  # SRDF pairs already applied by erd
    n_rob = gm.ngeoms
    self_pairs = [(int(p.first), int(p.second)) for p in gm.collisionPairs]
    table = pin.GeometryObject(
        "t", 0, 0, pin.SE3(np.eye(3), np.array([0.0, 0.0, -0.025])), coal.Box(2.0, 2.0, 0.05)
    )
    obj = pin.GeometryObject(
        "o", 0, 0, pin.SE3(np.eye(3), np.array(obj_pose) + [0, 0, 0.11]), coal.Cylinder(0.035, 0.22)
    )
    sph = pin.GeometryObject(
        "s", 0, 0, pin.SE3(np.eye(3), np.array(obstacle_xyz)), coal.Sphere(0.1)
    )
    it, io, is_ = gm.addGeometryObject(table), gm.addGeometryObject(obj), gm.addGeometryObject(sph)
    gm.removeAllCollisionPairs()
    kinds = []
    link0 = gm.getGeometryId("panda_link0_0")
    for a, b in self_pairs:
        gm.addCollisionPair(pin.CollisionPair(a, b))
        kinds.append("self")
    for i in range(n_rob):
        if i != link0:
            gm.addCollisionPair(pin.CollisionPair(i, it))
            kinds.append("environment")
        gm.addCollisionPair(pin.CollisionPair(i, is_))
        kinds.append("environment")
        gm.addCollisionPair(pin.CollisionPair(i, io))
        kinds.append("object")
    return model, gm, np.array(kinds)


def test_agrees_with_pinocchio_compute_collisions(robot):
    obstacle = [0.3, -0.35, 0.45]
    env = EnvironmentConfig.model_validate(
        {
            "contact_tolerance": 0.0,
            "obstacles": [{"shape": "sphere", "dims": {"radius": 0.1}, "pose": {"xyz": obstacle}}],
        }
    )
    c = make_checker(robot, env, ObjectConfig.model_validate(BOTTLE))
    model, gm, kinds = _oracle([0.5, 0.0, 0.0], obstacle)
    data, gd = model.createData(), complete_answers(pin.GeometryData(gm))
    rng = np.random.default_rng(7)
    qs = robot.random_configurations(600, rng)
    # plus configurations near the bottle: perturbed home poses leaning forward
    near = _q(robot, j2=0.9, j4=-1.2, j6=2.0) + rng.normal(0, 0.25, (200, robot.nq))
    qs = np.vstack([qs, np.clip(near, robot.lower, robot.upper)])
    reasons = c.check(qs)
    expect = []
    for q in qs:
        pin.computeCollisions(model, data, gm, gd, np.concatenate([q, [0.04, 0.04]]), False)
        hit = np.array([r.isCollision() for r in gd.collisionResults])
        for kind, reason in (
            ("environment", REASON_ENVIRONMENT),
            ("self", REASON_SELF),
            ("object", REASON_OBJECT),
        ):
            if hit[kinds == kind].any():
                expect.append(reason)
                break
        else:
            expect.append("")
    expect = np.array(expect)
    assert (reasons == expect).all(), np.flatnonzero(reasons != expect)
    for r in ("", REASON_ENVIRONMENT, REASON_SELF, REASON_OBJECT):
        assert (expect == r).sum() >= 5, f"too few samples with reason {r!r}"


def test_table_exempts_only_base_link(checker):
    assert checker.table_exempt == ("panda_link0",)
    assert "panda_hand" in {checker.link_names[i] for i in checker.gripper_geoms}
    assert "panda_link7" not in {checker.link_names[i] for i in checker.gripper_geoms}


def test_base_pose_moves_the_world(robot):
    # robot mounted 0.5 m above the table: the through-table configuration is now free
    q = _q(robot, j2=1.6, j4=-0.5)
    c = make_checker(robot, EnvironmentConfig(), None, None)
    assert c.check(q)[0] == REASON_ENVIRONMENT
    raised = np.eye(4)
    raised[2, 3] = 0.5
    c2 = make_checker(robot, EnvironmentConfig(), None, raised)
    assert c2.check(q)[0] == ""
    assert c2.table_exempt == ()  # nothing stands on the table any more


def test_mesh_obstacle(robot):
    link0 = robot.mesh_dir / "meshes" / "collision" / "link0.stl"
    env = EnvironmentConfig.model_validate(
        {
            "obstacles": [
                {"shape": "mesh", "mesh": str(link0), "scale": 2.0, "pose": {"xyz": [0.8, 0, 0]}}
            ]
        }
    )
    c = make_checker(robot, env)
    assert c.check(robot.home)[0] == ""
    assert c.check(_q(robot, j2=1.3, j4=-0.5))[0] == REASON_ENVIRONMENT  # hand at x 0.76, z 0.1


# --- errors -----------------------------------------------------------------------------


def test_unreadable_mesh_names_the_file(robot, tmp_path):
    bad = tmp_path / "broken.stl"
    bad.write_text("not a mesh")
    env = EnvironmentConfig(obstacles=(ObstacleConfig(shape="mesh", mesh=bad),))
    with pytest.raises(InputError, match="broken.stl"):
        make_checker(robot, env)
    env = EnvironmentConfig(obstacles=(ObstacleConfig(shape="mesh", mesh=tmp_path / "nope.obj"),))
    with pytest.raises(InputError, match="nope.obj"):
        make_checker(robot, env)


@pytest.mark.parametrize(
    ("section", "value", "match"),
    [
        ("environment", {"obstacles": [{"shape": "cone", "dims": {"radius": 1}}]}, "cone"),
        ("environment", {"obstacles": [{"shape": "sphere", "dims": {"radius": 0}}]}, "radius"),
        ("environment", {"obstacles": [{"shape": "box", "dims": {"size": [1, -1, 1]}}]}, "size"),
        ("environment", {"table": {"size": [1.0, 0.0, 0.05]}}, "size"),
        ("environment", {"contact_tolerance": -0.001}, "contact_tolerance"),
        ("approach", {"distance": -0.1}, "distance"),
        ("ranking", {"metric": "combined", "weights": {"yoshikawa": 0, "clearance": 0}}, "weight"),
        ("ranking", {"metric": "combined", "weights": {"clearance": -1.0}}, "clearance"),
    ],
)
def test_config_errors(section, value, match):
    with pytest.raises(ConfigError, match=match):
        Config.from_dict({"candidates": {"source": "plane"}, section: value})


# --- combined ranking score ---------------------------------------------------------------


def test_combined_score_normalises_and_weights():
    cols = {
        "yoshikawa": np.array([0.01, 0.03, 0.02, np.nan]),
        "clearance": np.array([0.30, 0.10, 0.20, 0.5]),
        "joint_limit_margin": np.array([0.5, 0.5, 0.5, 0.5]),
    }
    mask = np.array([True, True, True, False])
    only_y = combined_score(cols, {"yoshikawa": 2.0, "clearance": 0.0}, mask=mask)
    np.testing.assert_allclose(only_y[:3], [0.0, 1.0, 0.5])
    assert np.isnan(only_y[3])
    both = combined_score(cols, {"yoshikawa": 1.0, "clearance": 1.0}, mask=mask)
    np.testing.assert_allclose(both[:3], [0.5, 0.5, 0.5])  # opposite orders cancel
    # a constant metric gives every row its full share; weights are divided by their sum
    const = combined_score(cols, {"yoshikawa": 3.0, "joint_limit_margin": 1.0}, mask=mask)
    np.testing.assert_allclose(const[:3], [0.25, 1.0, 0.625])
    default = combined_score(cols, mask=mask)  # yoshikawa 1, clearance 0.5, margin 0.2
    assert np.all((default[:3] >= 0) & (default[:3] <= 1)) and np.argmax(default[:3]) == 1
    ranked = combined_score(cols, {"clearance": 1.0}, mask=mask, normalization="rank")
    np.testing.assert_allclose(ranked[:3], [1.0, 0.0, 0.5])


@pytest.mark.parametrize(
    ("weights", "match"),
    [
        ({"yoshikawa": 0.0, "clearance": 0.0}, "positive"),
        ({"yoshikawa": -1.0}, "yoshikawa"),
        ({"clearance": float("nan")}, "clearance"),
        ({"inverse_condition": 1.0}, "inverse_condition"),
    ],
)
def test_combined_score_errors(weights, match):
    cols = {"yoshikawa": np.ones(3), "clearance": np.ones(3)}
    with pytest.raises(ConfigError, match=match):
        combined_score(cols, weights)


def _bottle_and_box_checker(robot):
    """Table, the bottle and a box obstacle beside the arm."""
    box = {"shape": "box", "dims": {"size": [0.2, 0.2, 0.4]}, "pose": {"xyz": [0.2, -0.4, 0.2]}}
    env = EnvironmentConfig.model_validate({"obstacles": [box]})
    return make_checker(robot, env, ObjectConfig.model_validate(BOTTLE))


def test_clearance_broad_phase_equals_all_pairs(robot):
    """The pruned clearance equals the minimum over every distance pair (computeDistances)."""
    c = _bottle_and_box_checker(robot)
    qs = robot.random_configurations(300, 3)
    fast = c.clearance(qs)
    dm, dd = c._dist_model, c._dist_data
    data = robot.model.createData()
    ref = []
    for q in qs:
        pin.computeDistances(robot.model, data, dm, dd, q)
        ref.append(min(r.min_distance for r in dd.distanceResults))
    ref = np.array(ref)
    free = ref > 0
    assert free.sum() > 100 and (~free).sum() > 5
    exact = c.clearance(qs, precision=0.0)
    np.testing.assert_allclose(exact[free], ref[free], atol=1e-9)
    assert np.all(exact[~free] <= 0)
    # the default precision: a real distance, at most 1 mm above the minimum (to coal's
    # GJK tolerance, about 1e-6: distances from hull vertices are exact)
    tol = 2e-6 + 4e-6 * ref[free]
    assert np.all(fast[free] >= ref[free] - tol) and np.all(fast[free] <= ref[free] + 1e-3)


def test_clearance_vertex_bounds_hold_against_coal(robot):
    """A link's nearest hull vertex gives U >= d and a separating plane L <= d (d: coal's
    distance of the pair), U - L <= precision where kept; the clearance near a sphere, a
    cylinder and the bottle stays a real distance at most ``precision`` above the minimum."""
    env = EnvironmentConfig.model_validate(
        {
            "obstacles": [
                {"shape": "sphere", "dims": {"radius": 0.08}, "pose": {"xyz": [0.35, 0.3, 0.5]}},
                {
                    "shape": "cylinder",
                    "dims": {"radius": 0.05, "height": 0.3},
                    "pose": {"xyz": [0.3, -0.35, 0.45], "rpy": [0.7, 0.2, 0.0]},
                },
            ]
        }
    )
    c = make_checker(robot, env, ObjectConfig.model_validate(BOTTLE))
    from gcm_pipeline.robot.ik import solve_ik

    rng = np.random.default_rng(12)
    n = 300
    t = np.tile(np.eye(4), (n, 1, 1))
    t[:, :3, :3] = Rotation.random(n, random_state=13).as_matrix()
    centres = np.array([[0.35, 0.3, 0.5], [0.3, -0.35, 0.45], [0.5, 0.0, 0.15]])
    t[:, :3, 3] = centres[rng.integers(0, 3, n)] + rng.normal(0, 0.12, (n, 3))
    res = solve_ik(robot, t)
    qs = np.concatenate([res.q[res.success], robot.random_configurations(100, 14)])
    dm, dd = c._dist_model, c._dist_data
    data = robot.model.createData()
    ref = np.empty((len(qs), len(dm.collisionPairs)))
    for i, q in enumerate(qs):
        pin.computeDistances(robot.model, data, dm, dd, q)
        ref[i] = [r.min_distance for r in dd.distanceResults]
    frames = c._frames.compute(qs)
    upper, lower = c._vertex_distances(frames, np.ones(ref.shape, dtype=bool), 1e-3)
    kept = np.isfinite(upper)
    worlds = {c._gm.geometryObjects[int(w)].name for w in c._dist_world[kept.any(axis=0)]}
    assert {"obstacle_0", "obstacle_1", "object"} <= worlds
    assert kept.sum() > 1000
    # coal's GJK stops at about 1e-6 (on curved shapes, seen: 8e-7 m above the exact
    # distance of a finger box from the tilted cylinder, which the vertex bounds pin down)
    tol = 2e-6 + 4e-6 * np.abs(ref[kept])
    assert np.all(lower[kept] <= ref[kept] + tol)
    assert np.all(upper[kept] >= ref[kept] - tol)
    assert np.all(upper[kept] - lower[kept] <= 1e-3 + 1e-12)
    # the whole clearance: a real distance, at most 1 mm above the minimum
    fast, best = c.clearance(qs), ref.min(axis=1)
    free = best > 0
    assert free.sum() > 200
    tol = 2e-6 + 4e-6 * best[free]
    assert np.all(fast[free] >= best[free] - tol) and np.all(fast[free] <= best[free] + 1e-3)
    assert np.all(fast[~free] <= 0)


@pytest.mark.parametrize(
    "geometry",
    [coal.Sphere(0.1), coal.Cylinder(0.05, 0.3), coal.Capsule(0.04, 0.2), coal.Box(0.1, 0.2, 0.3)],
    ids=["sphere", "cylinder", "capsule", "box"],
)
def test_shape_nearest_points_and_support(geometry):
    """The primitives' nearest points and support functions, against the distance bound."""
    from gcm_pipeline.robot.collision.broadphase import ShapeBound

    placement = np.eye(4)
    placement[:3, :3] = Rotation.from_euler("xyz", [0.3, -0.5, 1.1]).as_matrix()
    placement[:3, 3] = [0.1, -0.2, 0.3]
    shape = ShapeBound(geometry, placement)
    assert shape.exact
    rng = np.random.default_rng(3)
    local = rng.normal(0, 0.2, (2000, 3))
    near = shape.nearest(local)
    base = local @ placement[:3, :3].T + placement[:3, 3]
    near_base = near @ placement[:3, :3].T + placement[:3, 3]
    # the nearest point lies in the shape, at the point's distance
    np.testing.assert_allclose(shape.lower(near_base), 0.0, atol=1e-12)
    np.testing.assert_allclose(
        np.linalg.norm(local - near, axis=1), shape.lower(base), rtol=1e-9, atol=1e-12
    )
    # the support function: attained by a point of the shape, never exceeded by one
    n = rng.normal(0, 1, (200, 3))
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    h = shape.support(n)
    far = shape.nearest(n * 1e6)  # (nearly) the point farthest along n of a convex shape
    np.testing.assert_allclose(np.einsum("ij,ij->i", far, n), h, atol=1e-9)
    inside = near[shape.lower(near_base) == 0.0]
    assert np.all(inside @ n.T <= h[None, :] + 1e-12)


def test_clearance_face_shortcut_equals_coal(robot):
    """Distances taken from hull vertices (a link in the region of one face of a box:
    the table, a box obstacle on any side) equal coal's distance of that pair."""
    c = _bottle_and_box_checker(robot)
    qs = robot.random_configurations(400, 4)
    frames = c._frames.compute(qs)
    centres = c._place(frames, c._cover.joint, c._cover.centre)
    anything = np.full((len(qs), c._dist_owner.size), -np.inf)  # no pair left out
    exact = c._face_distances(frames, centres, anything)
    known = np.isfinite(exact)
    assert known.sum() > 2000  # most link-table pairs and some link-obstacle pairs
    worlds = {c._gm.geometryObjects[int(w)].name for w in c._dist_world[known.any(axis=0)]}
    assert worlds == {"table", "obstacle_0"}
    dm, dd = c._dist_model, c._dist_data
    data = robot.model.createData()
    for i, q in enumerate(qs):
        pin.updateGeometryPlacements(robot.model, data, dm, dd, q)
        for p in np.flatnonzero(known[i]):
            ref = pin.computeDistance(dm, dd, int(p)).min_distance
            # coal's GJK stops at a relative tolerance of about 1e-6
            assert abs(exact[i, p] - ref) < 1e-9 + 2e-6 * abs(ref), (i, p, exact[i, p], ref)
    # with the pairs' sphere bounds, pairs that cannot be nearer than a distance found
    # are left out: fewer distances, the same minimum of each row
    bound = np.full_like(anything, np.inf)
    for w in np.unique(c._dist_world).tolist():
        cols = np.flatnonzero(c._dist_world == w)
        d = c._bounds_for(w).lower(centres) - c._cover.radius
        bound[:, cols] = np.minimum.reduceat(d, c._cover.start[:-1], axis=1)[:, c._dist_owner[cols]]
    some = c._face_distances(frames, centres, bound)
    assert np.isfinite(some).sum() < 0.5 * known.sum()
    assert np.all((some == exact) | np.isnan(some))
    np.testing.assert_array_equal(
        np.nanmin(np.where(known, exact, np.inf), axis=1),
        np.nanmin(np.where(np.isfinite(some), some, np.inf), axis=1),
    )


def test_switches_self_collision_and_object(robot):
    folded = _q(robot, j2=1.7, j4=-3.0)
    tcp = robot.fk(robot.home)[0]
    at_wrist = (tcp[:3, 3] - 0.09 * tcp[:3, 2]).tolist()
    obj = ObjectConfig.model_validate(
        {"shape": "box", "dims": {"size": [0.05, 0.05, 0.05]}, "pose": {"xyz": at_wrist}}
    )
    off = make_checker(robot, EnvironmentConfig(self_collision=False, check_object=False), obj)
    assert off.check(np.vstack([folded, robot.home])).tolist() == ["", ""]
    assert "object" not in {s.name for s in off.world}
    no_table = make_checker(robot, EnvironmentConfig(table=None))
    assert no_table.check(_q(robot, j2=1.6, j4=-0.5))[0] == ""
    assert np.isinf(no_table.clearance(robot.home)[0])  # nothing to measure against
    assert "CollisionChecker(robot='panda'" in repr(no_table)


def _cube_stl(path, half):
    v = np.array([[x, y, z] for x in (-half, half) for y in (-half, half) for z in (-half, half)])
    faces = [(0, 1, 3), (0, 3, 2), (4, 6, 7), (4, 7, 5), (0, 4, 5), (0, 5, 1),
             (2, 3, 7), (2, 7, 6), (0, 2, 6), (0, 6, 4), (1, 5, 7), (1, 7, 3)]  # fmt: skip
    lines = ["solid cube"]
    for f in faces:
        a, b, c = v[list(f)]
        n = np.cross(b - a, c - a)
        lines.append(f"facet normal {n[0]} {n[1]} {n[2]}\nouter loop")
        lines += [f"vertex {p[0]} {p[1]} {p[2]}" for p in (a, b, c)]
        lines.append("endloop\nendfacet")
    lines.append("endsolid cube")
    path.write_text("\n".join(lines) + "\n")
    return path


def test_mesh_object_contact_tolerance_on_the_gripper(robot, tmp_path):
    """A mesh object is not eroded; the gripper's pieces are (robot.collision.contact)."""
    stl = _cube_stl(tmp_path / "cube.stl", 0.05)
    full, _ = shape_geometry("mesh", None, mesh=stl)
    full.computeLocalAABB()
    np.testing.assert_allclose(full.aabb_local.max_, [0.05] * 3, atol=1e-9)
    with pytest.raises(ValueError, match="not eroded"):
        shape_geometry("mesh", None, mesh=stl, erode=0.005)
    tcp = robot.fk(robot.home)[0, :3, 3].tolist()
    obj = ObjectConfig.model_validate({"shape": "mesh", "mesh": str(stl), "pose": {"xyz": tcp}})
    c = make_checker(robot, EnvironmentConfig(), obj)
    assert c.check(robot.home)[0] == REASON_OBJECT  # a 10 cm cube does not fit the 8 cm opening
    snug = _cube_stl(tmp_path / "snug.stl", 0.041)  # 1 mm into each pad, 4 mm into the palm
    obj = ObjectConfig.model_validate({"shape": "mesh", "mesh": str(snug), "pose": {"xyz": tcp}})
    assert make_checker(robot, EnvironmentConfig(), obj).check(robot.home)[0] == ""
    strict = EnvironmentConfig(contact_tolerance=0.0)
    assert make_checker(robot, strict, obj).check(robot.home)[0] == REASON_OBJECT


def test_piece_inside_a_mesh_object_collides(robot, tmp_path):
    """A slab between the fingertips wider than the opening: the eroded fingertip pieces lie
    wholly inside it and cross none of its triangles; the inside test still finds them."""
    trimesh = pytest.importorskip("trimesh")
    tcp = robot.fk(robot.home)[0]
    rpy = Rotation.from_matrix(tcp[:3, :3]).as_euler("xyz", degrees=True).tolist()
    for half_width, expect in ((0.044, ""), (0.06, REASON_OBJECT)):  # fingers at +-0.04 m
        stl = tmp_path / f"slab{half_width}.stl"
        trimesh.creation.box((0.06, 2 * half_width, 0.024)).export(stl)
        pose = {"xyz": tcp[:3, 3].tolist(), "rpy_deg": rpy}
        obj = ObjectConfig.model_validate({"shape": "mesh", "mesh": str(stl), "pose": pose})
        c = make_checker(robot, EnvironmentConfig(), obj)
        assert c.check(robot.home)[0] == expect
    pairs = c.colliding_pairs(robot.home)
    assert ("panda_leftfinger_3_contact", "object (inside)", "object") in pairs
    assert all(b == "object (inside)" for _, b, _ in pairs)  # no triangle is crossed


def _every_pair_reasons(robot, checker, qs, mode):
    """Reasons from Pinocchio's computeCollisions over every pair of ``mode`` (no broad phase)."""
    bit = {"grasp": 1, "approach": 2, "retreat": 4}[mode]
    gm = checker._gm.copy()
    gm.removeAllCollisionPairs()
    kinds = []
    for p in checker._pairs:
        if p.modes & bit:
            gm.addCollisionPair(pin.CollisionPair(p.a, p.b))
            kinds.append(p.kind)
    kinds = np.array(kinds)
    # the checker's coal settings: no GJK guess carried over from the previous query (with
    # it, answers within about 1e-5 m of contact depend on the queries before), and GJK's
    # "within tolerance" end counted as contact (pairs.checker_requests)
    gd, data = checker_requests(pin.GeometryData(gm)), robot.model.createData()
    out = []
    for q in qs:
        pin.computeCollisions(robot.model, data, gm, gd, q, False)
        hit = np.array([r.isCollision() for r in gd.collisionResults])
        out.append(
            next(
                (
                    f"collision_{k}"
                    for k in ("environment", "self", "object")
                    if hit[kinds == k].any()
                ),
                "",
            )
        )
    return np.array(out)


@pytest.mark.parametrize("mode", ["grasp", "approach", "retreat"])
def test_broad_phase_agrees_with_every_pair(robot, checker, mode):
    """The broad-phase pools give the reason of every pair run one by one, in each mode."""
    qs = robot.random_configurations(2000, 11)
    # and configurations around the bottle: IK solutions of grasps on it
    from gcm_pipeline.robot.ik import solve_ik

    t = np.tile(np.eye(4), (200, 1, 1))
    rng = np.random.default_rng(2)
    a = rng.uniform(-np.pi, np.pi, 200)
    z = -np.stack([np.cos(a), np.sin(a), np.zeros(200)], axis=1)
    t[:, :3, 2] = z
    t[:, :3, 1] = [0.0, 0.0, 1.0]
    t[:, :3, 0] = np.cross(t[:, :3, 1], z)
    t[:, :3, 3] = np.stack(
        [0.5 + 0.03 * np.cos(a), 0.03 * np.sin(a), rng.uniform(0.02, 0.2, 200)], 1
    )
    res = solve_ik(robot, t)
    qs = np.concatenate([qs, res.q[res.success]])
    ref = _every_pair_reasons(robot, checker, qs, mode)
    assert (ref == "").sum() > 100 and len(set(ref)) == (3 if mode == "retreat" else 4)
    np.testing.assert_array_equal(checker.check(qs, mode), ref)
    # a few configurations at a time take coal's tree pools instead of the NumPy broad phase
    few = [checker.check(qs[a : a + 50], mode) for a in range(0, len(qs), 50)]
    np.testing.assert_array_equal(np.concatenate(few), ref)
    # and so does a checker with two threads, in every batch
    two = make_checker(robot, EnvironmentConfig(), ObjectConfig.model_validate(BOTTLE), threads=2)
    np.testing.assert_array_equal(two.check(qs, mode), ref)


def test_modes_differ_only_at_the_object(robot, checker):
    """A finger pad pressed 3 mm into the bottle: a grasp, not an approach; the retreat holds it."""
    from gcm_pipeline.robot.ik import solve_ik

    t = np.eye(4)
    t[:3, :3] = [[0.0, 0.0, 1.0], [0.0, 1.0, 0.0], [-1.0, 0.0, 0.0]]  # approach +x, fingers along y
    t[:3, 3] = [0.5, 0.008, 0.12]  # on the axis, 8 mm aside: one pad 3 mm into the bottle
    q = solve_ik(robot, t).q
    assert np.isfinite(q).all()
    reasons = {m: checker.check(q, m)[0] for m in ("grasp", "approach", "retreat")}
    assert reasons == {"grasp": "", "approach": REASON_OBJECT, "retreat": ""}
    with pytest.raises(InputError, match="collision mode"):
        checker.check(q, "lift")


def test_carried_object_agrees_with_coal_on_every_pair(robot, checker):
    """While the bottle is held (retreat), its sphere-pruned checks against the table
    and the arm links give coal's answer on every pair."""
    from gcm_pipeline.robot.collision import gripper_links
    from gcm_pipeline.robot.ik import solve_ik

    n = 300  # (150 held no arm-object case once the joint ranges had their 0.1 rad margin)
    rng = np.random.default_rng(5)
    a = rng.uniform(-np.pi / 2, np.pi / 2, n) + np.pi  # the side facing the robot
    z = -np.stack([np.cos(a), np.sin(a), np.zeros(n)], axis=1)
    t = np.tile(np.eye(4), (n, 1, 1))
    t[:, :3, 2] = z
    t[:, :3, 1] = [0.0, 0.0, 1.0]
    t[:, :3, 0] = np.cross(t[:, :3, 1], z)
    t[:, :3, 3] = np.stack(
        [0.5 + 0.025 * np.cos(a), 0.025 * np.sin(a), rng.uniform(0.03, 0.2, n)], 1
    )
    # the LM's solutions: perturbed, they give every kind of collision this test needs
    res = solve_ik(robot, t, analytic=False)
    ok = res.success
    held = np.linalg.inv(t[ok]) @ checker.object.placement
    # move the arm around the grasp: the bottle goes down into the table, up, sideways
    qs = res.q[ok] + rng.normal(0.0, 0.25, (ok.sum(), robot.nq))
    qs = np.clip(qs, robot.lower + 1e-6, robot.upper - 1e-6)
    fast = checker.check(qs, "retreat", carried=held)

    ref = _every_pair_reasons(robot, checker, qs, "retreat")
    gm = checker._gm
    links = gripper_links(robot)
    arm = [
        i
        for i in range(checker.n_robot_geoms)
        if robot.model.frames[gm.geometryObjects[i].parentFrame].name not in links
    ]
    env = [i for i, go in enumerate(gm.geometryObjects) if go.name == "table"]
    data, gd = robot.model.createData(), pin.GeometryData(gm)
    obj = checker.object
    req = coal.CollisionRequest()

    def hits(g1, m1, g2, m2):
        res = coal.CollisionResult()
        tf = lambda m: coal.Transform3s(m[:3, :3].copy(), m[:3, 3].copy())  # noqa: E731
        return coal.collide(g1, tf(m1), g2, tf(m2), req, res) > 0

    for k, q in enumerate(qs):
        if ref[k]:
            continue
        pin.forwardKinematics(robot.model, data, q)
        pin.updateGeometryPlacements(robot.model, data, gm, gd)
        pin.updateFramePlacement(robot.model, data, robot.grasp_frame_id)
        pose = data.oMf[robot.grasp_frame_id].homogeneous @ held[k]
        if any(
            hits(
                obj.geometry,
                pose,
                gm.geometryObjects[w].geometry,
                gm.geometryObjects[w].placement.homogeneous,
            )
            for w in env
        ):
            ref[k] = "collision_environment"
        elif any(
            hits(gm.geometryObjects[i].geometry, gd.oMg[i].homogeneous, obj.geometry, pose)
            for i in arm
        ):
            ref[k] = "collision_object"
    assert {"", "collision_environment", "collision_object"} <= set(ref)
    np.testing.assert_array_equal(fast, ref)


def test_answers_do_not_depend_on_the_order_of_the_queries(robot, checker):
    """coal's cached GJK guesses are off: a configuration's clearance and reason are the
    same whatever was asked before (so chunks and workers cannot change a result)."""
    qs = robot.random_configurations(1500, 4)
    perm = np.random.default_rng(1).permutation(len(qs))
    a = checker.clearance(qs, precision=0.0)
    b = np.empty_like(a)
    b[perm] = checker.clearance(qs[perm], precision=0.0)
    np.testing.assert_array_equal(a, b)
    r = checker.check(qs)
    s = np.empty_like(r)
    s[perm] = checker.check(qs[perm])
    np.testing.assert_array_equal(r, s)


def _every_pair_hits(robot, checker, qs, screen):
    """Each pair of a mode's screen run through coal alone, (N, P) bool (no broad phase)."""
    gm = checker._gm.copy()
    gm.removeAllCollisionPairs()
    for k in screen.pairs:
        p = checker._pairs[k]
        gm.addCollisionPair(pin.CollisionPair(p.a, p.b))
    gd, data = checker_requests(pin.GeometryData(gm)), robot.model.createData()
    out = np.zeros((len(qs), screen.pairs.size), dtype=bool)
    for i, q in enumerate(qs):
        pin.computeCollisions(robot.model, data, gm, gd, q, False)
        out[i] = [r.isCollision() for r in gd.collisionResults]
    return out


def _first_kind(hit, screen):
    """Each configuration's first kind (index of KINDS) ``hit`` (N, P) has, else len(KINDS)."""
    rank = np.array([KINDS.index(k) for k in screen.kind.tolist()])
    return np.where(hit, rank, len(KINDS)).min(axis=1, initial=len(KINDS))


def test_broad_phase_pair_by_pair_with_rotated_boxes(robot, monkeypatch):
    """Every pair's answer equals coal's, with tilted boxes (the hull-vertex shortcut) around.

    A tilted box obstacle over the bottle, a tilted box object and a tilted
    table: configurations near all of them (IK of poses on and around them)
    and random ones. Each of the three broad-phase levels decides some pairs,
    and coal the rest; no decision differs from coal's on that pair. Asked for
    each configuration's first kind only (``first``, what the reasons need), both
    paths give the complete answer's first kind, with fewer pairs decided.
    """
    from gcm_pipeline.robot.ik import solve_ik

    env = EnvironmentConfig.model_validate(
        {
            "table": {"height": -0.02},
            "obstacles": [
                {
                    "shape": "box",
                    "dims": {"size": [0.3, 0.08, 0.05]},
                    "pose": {"xyz": [0.45, 0.15, 0.45], "rpy": [0.4, 0.3, 0.8]},
                }
            ],
        }
    )
    obj = ObjectConfig.model_validate(
        {
            "shape": "box",
            "dims": {"size": [0.06, 0.05, 0.2]},
            "pose": {"xyz": [0.5, -0.1, 0.1], "rpy": [0.0, 0.0, 0.6]},
        }
    )
    base = np.eye(4)  # the robot mounted slightly tilted: the table is tilted in its frame
    base[:3, :3] = Rotation.from_euler("xyz", [0.05, -0.04, 0.3]).as_matrix()
    c = make_checker(robot, env, obj, base)
    rng = np.random.default_rng(5)
    n = 400
    t = np.tile(np.eye(4), (n, 1, 1))
    rot = Rotation.random(n, random_state=6).as_matrix()
    t[:, :3, :3] = rot
    centres = np.array([[0.45, 0.15, 0.45], [0.5, -0.1, 0.1], [0.4, 0.0, 0.05]])
    t[:, :3, 3] = centres[rng.integers(0, 3, n)] + rng.normal(0, 0.06, (n, 3))
    res = solve_ik(robot, t)
    qs = np.concatenate([res.q[res.success], robot.random_configurations(1500, 8)])
    for bit in (1, 2):  # grasp, approach
        screen = c._screens[bit]
        got = c._pair_hits(qs, c._frames.compute(qs), screen)
        ref = _every_pair_hits(robot, c, qs, screen)
        bad = np.argwhere(got != ref)
        assert bad.size == 0, [(int(i), c._pairs[screen.pairs[k]]) for i, k in bad[:5]]
        for jit in ("1", "0"):  # the compiled kernels, the NumPy code
            monkeypatch.setenv("GCM_JIT", jit)
            first = c._pair_hits(qs, c._frames.compute(qs), screen, first=True)
            np.testing.assert_array_equal(_first_kind(first, screen), _first_kind(ref, screen))
            assert not (first & ~ref).any()
            # configurations with two kinds of collision, or two pairs: skipped
            assert first.sum() < ref.sum()
        monkeypatch.delenv("GCM_JIT")
        # the test exercises every kind and both box outcomes
        for kind in ("environment", "self", "object"):
            assert ref[:, screen.kind == kind].any(), kind
    assert len(c._screens[1].boxes) > 10


def test_an_obstacle_overlapping_the_base_collides_in_every_batch(robot, caplog):
    """A pair of two geometries fixed to the world (the base link and a pedestal box that
    is not the support) collides in every configuration, in large and small batches."""
    env = EnvironmentConfig.model_validate(
        {
            "table": {"height": -0.3},
            "obstacles": [
                {"shape": "box", "dims": {"size": [0.3, 0.3, 0.3]}, "pose": {"xyz": [0, 0, -0.149]}}
            ],
        }
    )
    with caplog.at_level("WARNING"):
        c = make_checker(robot, env, None)
    assert c.static_collisions == (("panda_link0", "obstacle_0"),)
    assert "obstacle_0 overlaps the robot's fixed panda_link0" in caplog.text
    qs = robot.random_configurations(200, 0)
    ref = _every_pair_reasons(robot, c, qs, "grasp")
    assert set(ref) == {REASON_ENVIRONMENT}
    np.testing.assert_array_equal(c.check(qs), ref)
    np.testing.assert_array_equal(
        np.concatenate([c.check(qs[a : a + 50]) for a in range(0, 200, 50)]), ref
    )
    # an object at the base: its reason, unless the table or the arm comes first
    obj = ObjectConfig.model_validate(
        {"shape": "box", "dims": {"size": [0.1, 0.1, 0.1]}, "pose": {"xyz": [-0.1, 0.0, 0.05]}}
    )
    c2 = make_checker(robot, EnvironmentConfig(), obj)
    qs = np.concatenate([qs, [_q(robot, j2=1.6, j4=-0.5)]])  # and one through the table
    for mode in ("grasp", "approach"):
        ref = _every_pair_reasons(robot, c2, qs, mode)
        assert {REASON_OBJECT, REASON_ENVIRONMENT} <= set(ref) and "" not in set(ref)
        np.testing.assert_array_equal(c2.check(qs, mode), ref)
        np.testing.assert_array_equal(c2.check(qs[:50], mode), ref[:50])


def test_finger_boxes_at_a_box_agree_with_coal_near_contact(robot):
    """A finger box with a corner pressed 3e-7 to 1e-3 m into a small tilted box, or 1e-5 m
    short of it: the large-batch path (hull vertices) and the small-batch path (coal's tree
    pools) give coal's answer (coal misses some of the shallowest box-box contacts)."""
    base = CollisionChecker(robot, [], self_collision=False)
    q = np.asarray(robot.home, dtype=float)
    rots, poss, _ = base._frames.compute(q[None])
    finger = base.link_names.index("panda_rightfinger")
    joint, v = base._hull(finger)
    v = v @ rots[joint][0].T + poss[joint][0]
    rng = np.random.default_rng(0)
    answers = set()
    for _ in range(30):
        n = rng.normal(size=3)
        n /= np.linalg.norm(n)
        low = v[np.argmin(v @ n)]
        rot = Rotation.align_vectors([n], [[0, 0, 1]])[0].as_matrix()
        for depth in (-1e-5, 3e-7, 3e-6, 3e-5, 1e-3):
            size = 0.004
            place = np.eye(4)
            place[:3, :3] = rot
            place[:3, 3] = (low @ n + depth - size / 2) * n + (low - (low @ n) * n)
            box = WorldShape("obstacle", coal.Box(size, size, size), place, "environment")
            c = CollisionChecker(robot, [box], self_collision=False)
            ref = _every_pair_reasons(robot, c, q[None], "grasp")[0]
            assert c.check(np.tile(q, (128, 1)))[0] == ref, (n, depth)
            assert c.check(q[None])[0] == ref, (n, depth)
            answers.add(ref)
    assert answers == {"", REASON_ENVIRONMENT}


def test_clearance_of_a_row_does_not_depend_on_its_batch(robot, checker):
    """A configuration's clearance is the same, to the bit, alone or in any batch (chunks
    and workers of the engine give identical answers); NumPy computes a single row
    through another BLAS routine, which rounds differently."""
    c = _bottle_and_box_checker(robot)
    qs = robot.random_configurations(60, 11)
    for chk in (checker, c):
        batch = chk.clearance(qs)
        alone = np.array([chk.clearance(q[None])[0] for q in qs])
        pairs = np.array([chk.clearance(qs[i : i + 2])[0] for i in range(len(qs) - 1)])
        np.testing.assert_array_equal(alone, batch)
        np.testing.assert_array_equal(pairs, batch[:-1])
