"""The checker's decisions near contact equal an independent implementation of its rules.

:meth:`CollisionChecker.check` in the ``grasp`` and ``approach`` modes against a
reference written here from the documented rules
(:mod:`gcm_pipeline.robot.collision.pairs`), simply and without the checker's
code: coal's complete ``collide`` (contact information on) on every pair the
rules count, on geometry placed by Pinocchio's own kinematics.

* self: every two robot geometries on different joints that are neither the
  same nor parent and child, minus the SRDF's ``disable_collisions`` (read
  here with ElementTree);
* environment: every robot geometry against the table, except geometries of the
  base (joints 0 and 1) that touch it in the home configuration;
* object: arm links against the bottle (a cylinder) in both modes; the gripper
  (its links written out below for each robot) against the bottle in
  ``approach``, against the bottle shrunk by the contact tolerance (radius and
  half-height minus it) in ``grasp``.

Robots: the Panda, the UR5 with the Robotiq 2F-85 and two user URDFs
(``write_arm``: cylinders; ``write_mixed_arm``: cylinders, a sphere, boxes, a
concave and a convex STL mesh, so every level of the broad phase), in the
bottle's world. Configurations: random ones,
IK solutions with the grasp frame around the bottle, and both sides of
contact bisected 14 times between free and colliding ones in each mode.

It also holds the regression of issue 33's trust question: coal's ``collide``
without contact information (as Pinocchio calls it) reported overlapping
cylinders of the user arm free, up to 0.58 mm deep, where GJK ends within its
tolerance of the origin (:func:`~gcm_pipeline.robot.collision.pairs.checker_requests`).
"""

from __future__ import annotations

import xml.etree.ElementTree as ET

import coal
import numpy as np
import pinocchio as pin
import pytest
from helpers import ROOT, around_the_bottle, decision_contact
from urdfs import write_arm, write_mixed_arm

from gcm_pipeline import pipeline as P
from gcm_pipeline.config import load_config
from gcm_pipeline.pipeline import make_checker

#: Each test starts with the kernels on, whatever the environment says.
pytestmark = pytest.mark.usefixtures("kernels_on")

#: The gripper of each robot, as the rules define it (the body carrying the grasp
#: frame and the links below it), written out by hand.
_GRIPPER = {
    "panda": {"panda_hand", "panda_leftfinger", "panda_rightfinger"},
    "ur5_robotiq": {"tool0"},
    "user_arm": {"wrist_3_link"},  # tool0, the grasp frame, is a link without geometry
    "user_mixed": {"wrist_3_link"},
}


def _config(name, tmp_path_factory):
    if name == "panda":
        return load_config(ROOT / "configs" / "bottle_side.yaml")
    if name == "ur5_robotiq":
        return load_config(ROOT / "configs" / "bottle_side_ur5.yaml")
    folder = tmp_path_factory.mktemp("arm")
    spec = write_mixed_arm(folder) if name == "user_mixed" else write_arm(folder)
    return load_config(ROOT / "configs" / "bottle_side.yaml", [f"robot.spec={spec}"])


class Rules:
    """The documented pair rules, implemented independently: coal on every counted pair."""

    def __init__(self, robot, world, gripper, tolerance):
        self.model, self.data = robot.model, robot.model.createData()
        self.gm = robot.build_geometry("collision")
        self.gd = pin.GeometryData(self.gm)
        geoms = list(self.gm.geometryObjects)
        link = [self.model.frames[g.parentFrame].name for g in geoms]
        joint = [int(g.parentJoint) for g in geoms]
        parent = list(self.model.parents)
        disabled = set()
        if robot.srdf_path is not None:
            for e in ET.parse(robot.srdf_path).getroot().iter("disable_collisions"):
                disabled.add(frozenset((e.get("link1"), e.get("link2"))))
        self.self_pairs = [
            (a, b)
            for a in range(len(geoms))
            for b in range(a + 1, len(geoms))
            if joint[a] != joint[b]
            and parent[joint[a]] != joint[b]
            and parent[joint[b]] != joint[a]
            and frozenset((link[a], link[b])) not in disabled
        ]
        table = next(s for s in world if s.name == "table")
        bottle = next(s for s in world if s.kind == "object")
        assert isinstance(bottle.geometry, coal.Cylinder)
        self.table = (table.geometry, _tf(table.placement))
        self.bottle = (bottle.geometry, _tf(bottle.placement))
        r, h = bottle.geometry.radius, bottle.geometry.halfLength
        self.contact = (coal.Cylinder(r - tolerance, 2 * (h - tolerance)), self.bottle[1])
        self.gripper = [g for g in range(len(geoms)) if link[g] in gripper]
        assert len({link[g] for g in self.gripper}) == len(gripper), gripper
        self.arm = [g for g in range(len(geoms)) if g not in self.gripper]
        # the base's geometries standing on the table (touching it at home) are exempt
        home = self._placed(robot.home)
        self.on_table = [
            g
            for g in range(len(geoms))
            if joint[g] in (0, 1)
            and coal.distance(*home[g], *self.table, coal.DistanceRequest(), coal.DistanceResult())
            <= 1e-6
        ]
        self.against_table = [g for g in range(len(geoms)) if g not in self.on_table]

    def _placed(self, q):
        pin.updateGeometryPlacements(self.model, self.data, self.gm, self.gd, q)
        return [
            (go.geometry, _tf(self.gd.oMg[g].homogeneous))
            for g, go in enumerate(self.gm.geometryObjects)
        ]

    def reasons(self, qs, modes):
        """The reason of each configuration in each mode: {mode: (N,) str}."""
        out = {m: [] for m in modes}
        for q in qs:
            placed = self._placed(q)
            first = ""
            if any(_collide(placed[g], self.table) for g in self.against_table):
                first = "collision_environment"
            elif any(_collide(placed[a], placed[b]) for a, b in self.self_pairs):
                first = "collision_self"
            elif any(_collide(placed[g], self.bottle) for g in self.arm):
                first = "collision_object"
            for m in modes:
                bottle = self.contact if m == "grasp" else self.bottle
                if not first and any(_collide(placed[g], bottle) for g in self.gripper):
                    out[m].append("collision_object")
                else:
                    out[m].append(first)
        return {m: np.array(v) for m, v in out.items()}


def _tf(m):
    return coal.Transform3s(np.ascontiguousarray(m[:3, :3]), np.ascontiguousarray(m[:3, 3]))


def _collide(x, y):
    """coal's complete answer: contact information on (EPA runs when GJK finds contact)."""
    return coal.collide(*x, *y, coal.CollisionRequest(), coal.CollisionResult()) > 0


@pytest.fixture(scope="module", params=sorted(_GRIPPER))
def case(request, tmp_path_factory):
    cfg = _config(request.param, tmp_path_factory)
    robot = P.robot_from_config(cfg)
    checker = make_checker(robot, cfg.environment, cfg.object)
    assert {checker.link_names[g] for g in checker.gripper_geoms} == _GRIPPER[request.param]
    rules = Rules(robot, checker.world, _GRIPPER[request.param], checker.contact_tolerance)
    q = np.concatenate([robot.random_configurations(300, 3), around_the_bottle(robot, 300, 4)])
    q = np.concatenate(
        [q, decision_contact(checker, q, "grasp"), decision_contact(checker, q, "approach")]
    )
    return checker, q, rules.reasons(q, ("grasp", "approach"))


@pytest.mark.parametrize("mode", ["grasp", "approach"])
def test_decisions_equal_the_rules_near_contact(case, mode, numpy_code):
    checker, q, ref = case
    got = checker.check(q, mode)
    bad = np.flatnonzero(got != ref[mode])
    assert bad.size == 0, [(int(i), str(got[i]), str(ref[mode][i])) for i in bad[:10]]
    np.testing.assert_array_equal(numpy_code(checker.check, q, mode), got)
    # a few configurations at a time (under _FEW_COMPILED, and _FEW with NumPy) go to
    # coal's AABB-tree pools: the same answers
    few = np.concatenate([checker.check(q[a : a + 10], mode) for a in range(0, len(q), 10)])
    np.testing.assert_array_equal(few, got)
    # every reason occurs, and the contact tolerance is exercised: free to grasp,
    # colliding on the way in
    assert set(ref[mode].tolist()) == {
        "",
        "collision_environment",
        "collision_self",
        "collision_object",
    }
    assert np.any((ref["grasp"] == "") & (ref["approach"] == "collision_object"))


#: User-arm configurations (``write_arm``, cylinders) in which two links overlap by
#: this much [m] (a point lies this deep inside both) and which coal's ``collide``
#: without contact information called free: (q, link a, link b, depth).
_OVERLAPS = [
    (
        [-5.685890432348625, -2.0573935667773524, -4.514855819674166,
         0.6225212162261491, 4.005490520977267, -5.388062868777713],
        "forearm_link", "wrist_3_link", 1e-4,
    ),
    (
        [1.004257046255782, 4.184933038881574, -2.6688812052352477,
         3.028432817076655, 5.6095673745822285, 2.407261513861137],
        "upper_arm_link", "wrist_2_link", 1e-5,
    ),
    (
        [-1.879086110223966, 4.164946740868147, -3.339353744268462,
         -2.666943171934361, -1.3866531336218595, 0.9754403831734431],
        "upper_arm_link", "wrist_1_link", 1e-5,
    ),
]  # fmt: skip


def _depth_in_cylinder(geometry, placement, p):
    """How deep point ``p`` (3,) lies inside a placed coal cylinder [m] (< 0: outside)."""
    local = placement.actInv(p)
    return min(geometry.radius - np.hypot(local[0], local[1]), geometry.halfLength - abs(local[2]))


def test_overlapping_links_are_not_free(tmp_path):
    """Regression: these overlaps were called free (GJK within its tolerance, no contact asked)."""
    cfg = load_config(
        ROOT / "configs" / "bottle_side.yaml", [f"robot.spec={write_arm(tmp_path / 'arm')}"]
    )
    robot = P.robot_from_config(cfg)
    checker = make_checker(robot, cfg.environment, cfg.object)
    gm = robot.build_geometry("collision")
    data, gd = robot.model.createData(), pin.GeometryData(gm)
    names = [go.name for go in gm.geometryObjects]
    for q, a, b, depth in _OVERLAPS:
        pin.updateGeometryPlacements(robot.model, data, gm, gd, np.array(q))
        ga, gb = (names.index(f"{link}_0") for link in (a, b))
        placed = [(gm.geometryObjects[g].geometry, gd.oMg[g]) for g in (ga, gb)]
        # independent proof of the overlap: the middle of coal's two witness points
        # (each inside the other cylinder) lies inside both
        (g1, m1), (g2, m2) = placed
        res = coal.CollisionResult()
        coal.collide(g1, _tf(m1.homogeneous), g2, _tf(m2.homogeneous), coal.CollisionRequest(), res)
        c = res.getContact(0)
        mid = 0.5 * (c.getNearestPoint1() + c.getNearestPoint2())
        inside = min(_depth_in_cylinder(g, m, mid) for g, m in placed)
        assert inside > depth, (a, b, inside)
        assert checker.check(q)[0] == "collision_self", (a, b)
        assert (a, b) in {(x[:-2], y[:-2]) for x, y, _ in checker.colliding_pairs(q)}


def test_carried_object_decisions_at_contact_follow_the_frames(case, numpy_code):
    """``retreat`` with a carried object, both sides of contact bisected to the last bit.

    The carried object's narrow phase places the arm links by the joint frames, with no
    margin: at contact its answer follows their last bits. Where the compiled path's
    frames (libm's cosines and sines) equal the NumPy code's to the bit, as on this
    machine's CPU, it must decide as the NumPy code does; another CPU's OpenBLAS can
    sum the NumPy code's frames in another order, and those rows are not compared.
    """
    checker, q, _ = case
    # the object held as at the grasps around the bottle (case's rows 300..599)
    grasps = np.linalg.inv(checker.robot.fk(q[300:600])) @ checker.object.placement
    held_all = grasps[np.random.default_rng(5).integers(len(grasps), size=len(q))]

    def check(x, rows):
        return checker.check(x, "retreat", carried=held_all[rows])

    hit = check(q, np.arange(len(q))) != ""
    free, coll = np.flatnonzero(~hit), np.flatnonzero(hit)
    m = min(free.size, coll.size, 300)
    a, b, rows = q[free[:m]].copy(), q[coll[:m]].copy(), free[:m]
    for _ in range(60):
        mid = 0.5 * (a + b)
        mh = check(mid, rows) != ""
        b[mh], a[~mh] = mid[mh], mid[~mh]
    near = np.concatenate([a, b])
    both = np.concatenate([rows, rows])

    def frames(x):
        return np.stack(checker._frames.compute(x, libm=True).transforms, axis=1)

    same = np.all(frames(near) == numpy_code(frames, near), axis=(1, 2, 3))
    if not same.any():
        pytest.skip("no configuration whose frames both paths compute to the bit on this CPU")
    got = check(near, both)
    ref = numpy_code(check, near, both)
    bad = np.flatnonzero((got != ref) & same)
    assert bad.size == 0, [(int(i), str(got[i]), str(ref[i])) for i in bad[:5]]
