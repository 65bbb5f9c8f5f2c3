"""The broad-phase kernels (gcm_pipeline.robot.collision.broadphase_kernel) against NumPy.

Levels 1 and 2 (bounding spheres, sphere covers) are conservative: every (pair,
configuration) the NumPy levels leave open stays open; level 3 (hull vertices
against a box) decides only what the NumPy level decides the same. Compared: the
collision reasons, what is sent to coal, the bound of each world shape kind, the
limits; decisions equal except within coal's tolerance of a threshold.
"""

from __future__ import annotations

import coal
import numpy as np
import pinocchio as pin
import pytest
from helpers import ROOT, random_rigid

from gcm_pipeline import pipeline as P
from gcm_pipeline.config import load_config
from gcm_pipeline.geometry.dualquat import dq_to_matrix
from gcm_pipeline.pipeline import make_checker
from gcm_pipeline.robot import kernels
from gcm_pipeline.robot.collision.broadphase import (
    BROAD_MARGIN,
    INSIDE_DEPTH,
    ShapeBound,
    beyond_a_face,
    in_frame,
    relative_transforms,
    stacked,
)
from gcm_pipeline.robot.collision.pairs import MODE_BIT
from gcm_pipeline.robot.ik import solve_ik

#: Each test starts with the kernels on, whatever the environment says.
pytestmark = pytest.mark.usefixtures("kernels_on")


#: Distance [m] from a decision's threshold within which two checkers may decide
#: differently: coal's own tolerance. The kernels decide only where a bound clears
#: the NumPy code's by ``kernels.SLACK`` (1e-9 m) and leave the rest to coal, as
#: the NumPy code does, so a different decision needs a pair at its threshold.
_CONTACT_EPS = 1e-6


def _threshold_distance(checker, q):
    """Per configuration, the distance of the pair nearest its collision threshold [m].

    Every pair of the checker's geometry, by coal: ``min |d|`` and
    ``|d + contact_tolerance|`` (the gripper may press into the object that much).
    """
    model = checker.robot.model
    data, gm = model.createData(), checker.geom_model
    gd = pin.GeometryData(gm)
    out = np.full(len(q), np.inf)
    for i, qi in enumerate(np.atleast_2d(q)):
        pin.computeDistances(model, data, gm, gd, qi)
        d = np.array([r.min_distance for r in gd.distanceResults])
        if d.size:
            out[i] = min(np.abs(d).min(), np.abs(d + checker.contact_tolerance).min())
    return out


def _same_decisions(checker, q, got, want):
    """Equal collision reasons, except (at most 0.1 % of rows) where a pair is at its threshold."""
    differ = np.flatnonzero(np.asarray(got) != np.asarray(want))
    assert differ.size <= 1e-3 * len(q), (differ.size, len(q))
    if differ.size:
        near = _threshold_distance(checker, q[differ])
        assert np.all(near <= _CONTACT_EPS), list(zip(differ, near, strict=True))


# --- collision broad phase --------------------------------------------------------------


@pytest.fixture(scope="module")
def bottle():
    """The world of configs/bottle_side.yaml and configurations near contact in it.

    IK solutions of its side grasps (the fingers around the bottle, the hand
    near the table for the low rings), perturbed by 1 mrad to 0.1 rad, and
    random configurations (deep in the table or in the arm itself).
    """
    cfg = load_config(ROOT / "configs" / "bottle_side.yaml")
    robot = P.robot_from_config(cfg)
    checker = make_checker(robot, cfg.environment, cfg.object)
    targets = dq_to_matrix(P.generate_candidates(cfg)["dq"])
    res = solve_ik(robot, targets)
    seeds = res.q[res.success]
    assert len(seeds) > 40
    rng = np.random.default_rng(5)
    near = [seeds + rng.normal(0.0, s, (20, *seeds.shape)) for s in (1e-3, 1e-2, 0.1)]
    qs = np.concatenate([seeds, *[x.reshape(-1, robot.nq) for x in near]])
    qs = np.concatenate([qs, robot.random_configurations(1500, 6)])
    # retreat: the bottle in the hand as grasped at the seed (a random one for random rows)
    grasped = np.linalg.inv(robot.fk(seeds)) @ checker.object.placement
    seed_of = np.concatenate(
        [np.tile(np.arange(len(seeds)), 61), rng.integers(0, len(seeds), 1500)]
    )
    return checker, qs, grasped[seed_of]


@pytest.mark.parametrize("mode", ["grasp", "approach", "retreat"])
def test_collision_reasons_equal_numpy(compiled, bottle, mode, numpy_code):
    checker, qs, held = bottle
    carried = held if mode == "retreat" else None
    ref = numpy_code(checker.check, qs, mode, carried)
    out = checker.check(qs, mode, carried)
    _same_decisions(checker, qs, out, ref)
    kinds = dict(zip(*np.unique(ref, return_counts=True), strict=True))
    assert kinds[""] > 300 and len(kinds) >= 3  # free and colliding of several kinds
    # the allowance's measure: at IK solutions of the bottle's grasps the fingers are
    # at the bottle
    assert _threshold_distance(checker, qs[:3]).max() < 0.01


def _coal_calls(checker, fn):
    """Which configurations ``fn`` sends to coal, pair by pair: {pool id: set of rows}."""
    calls: dict[int, set[bytes]] = {}
    run = checker._run

    def record(pool, q):
        calls.setdefault(id(pool), set()).update(row.tobytes() for row in q)
        return run(pool, q)

    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(checker, "_run", record)
        fn()
    return calls


@pytest.mark.parametrize("mode", ["grasp", "approach"])
def test_the_kernels_leave_open_what_numpy_leaves_open(compiled, bottle, mode, numpy_code):
    """Every (pair, configuration) that NumPy sends to coal, the kernels send too.

    For a pair without a box that is the set levels 1 and 2 leave open; with a
    world box, what level 3 leaves undecided after them. A pair of a robot
    polytope and a robot box (the Panda's finger boxes), of two robot polytopes
    (the Panda's links) or of a robot polytope and a cylinder (the bottle) gets
    level 3 from the kernels only: they send a subset of NumPy's rows there.
    """
    checker, qs, _ = bottle
    ref = _coal_calls(checker, lambda: numpy_code(checker.check, qs, mode))
    out = _coal_calls(checker, lambda: checker.check(qs, mode))
    # (a configuration's pairs after its first collision are not sent: 590 in grasp mode)
    assert sum(len(v) for v in ref.values()) > 400
    screen = checker._screens[MODE_BIT[mode]]
    own_box, cylinder, hulls = set(), set(), set()
    for cols, pools in (
        (screen.self_boxes, own_box),
        (screen.cylinders, cylinder),
        (screen.self_hulls, hulls),
    ):
        for k in cols:
            c = int(screen.pairs[k])
            pools |= {id(checker._pair_pool[c]), id(checker._hull_pools.get(c))}
            pools.add(id(checker._piece_pools.get(c)))
    for pool, rows in ref.items():
        if pool in own_box | cylinder | hulls:
            assert out.get(pool, set()) <= rows
        else:
            assert rows <= out.get(pool, set())
    assert any(pool in own_box for pool in ref)  # the robot-box level was exercised
    # the two polytopes' level was exercised: the kernels send fewer rows there
    assert sum(len(ref[p]) - len(out.get(p, set())) for p in ref if p in hulls) > 50
    # the cylinder level was exercised: the kernels send fewer rows there
    assert sum(len(ref[p]) - len(out.get(p, set())) for p in ref if p in cylinder) > 50
    # conservative, not loose: only entries within the slack of a threshold are added
    extra = sum(len(out[p] - ref.get(p, set())) for p in out)
    assert extra <= 0.01 * sum(len(v) for v in ref.values())


def test_open_pairs_contain_the_colliding_ones(compiled, bottle):
    checker, qs, _ = bottle
    screen = checker._screens[1]
    frames = checker._frames.compute(qs[:2048])
    broad, _, _, _, _ = checker._compiled_screen(screen)
    open_ = compiled.broad_phase(_stacked_checked(frames), *broad)
    hit = checker._pair_hits_compiled(compiled, qs[:2048], frames, screen)
    assert hit.any() and not (hit.T & ~open_).any()


def _stacked_checked(frames):
    """The frames as one array, as the kernels take them: a view, not a copy."""
    tfs = stacked(frames.transforms)
    assert tfs is frames.transforms[0].base  # no copy: the array the frames are views of
    taken = frames.take(np.arange(5))
    np.testing.assert_array_equal(stacked(taken.transforms), tfs[:, :5])
    return tfs


def test_level_3_agrees_with_numpy_wherever_it_decides(compiled, bottle):
    checker, qs, _ = bottle
    screen = checker._screens[1]
    frames = checker._frames.compute(qs)
    rots, poss = frames.rots, frames.poss
    tfs = np.stack(frames.transforms)
    _, boxes, _, _, _ = checker._compiled_screen(screen)
    assert boxes
    rows = np.arange(len(qs))
    decided = {kernels.FREE: 0, kernels.COLLIDES: 0}
    for k, (joint, verts, inv, beyond, deep) in boxes.items():
        status = compiled.hull_vs_box(tfs[joint], rows, verts, inv, beyond, deep)
        assert compiled.hull_vs_box(tfs[joint], rows[:0], verts, inv, beyond, deep).shape == (0,)
        # the NumPy level 3 on every vertex: colliding when one lies deep inside,
        # free when all lie beyond one face plane
        halfs = screen.boxes[k][3]
        local = in_frame((rots[joint], poss[joint], inv), rows, verts)
        lim = halfs[None, :, None]
        inside = np.all(np.abs(local) < lim - INSIDE_DEPTH, axis=1).any(axis=1)
        free = beyond_a_face(local, lim) & ~inside
        assert inside[status == kernels.COLLIDES].all()
        assert free[status == kernels.FREE].all()
        # and undecided only where the NumPy level is undecided too (or within the slack)
        assert not ((status == kernels.UNDECIDED) & (inside | free)).any()
        for s in decided:
            decided[s] += int((status == s).sum())
    assert decided[kernels.FREE] > 1000 and decided[kernels.COLLIDES] > 100


def test_level_3_corners_hold_every_vertex():
    """Level 3 first tests the corners of a box around the hull's vertices (of two boxes,
    one per half, for a long hull): a corner beyond a face puts every vertex beyond it only
    if each vertex lies inside one of the boxes, by more than the rounding of its
    coordinates."""
    from gcm_pipeline.robot.collision.broadphase_kernel import CORNER_PAD, _enclosing_corners

    rng = np.random.default_rng(3)
    for stretch, parts in (((1.0, 1.0, 1.0), 1), ((0.3, 4.0, 0.5), 2), ((1.0, 0.2, 2.5), 2)):
        for scale in (1e-3, 0.1, 2.0):
            verts = rng.normal(size=(3, 60)) * np.array(stretch)[:, None] * scale
            verts += rng.normal(size=(3, 1))
            corners, centre = _enclosing_corners(np.ascontiguousarray(verts))
            assert corners.shape == (3, 8 * parts)
            lo, hi = verts.min(axis=1), verts.max(axis=1)
            np.testing.assert_allclose(centre, 0.5 * (lo + hi))
            held = np.zeros(verts.shape[1], dtype=bool)
            for box in np.split(corners, parts, axis=1):
                assert np.unique(box.T, axis=0).shape == (8, 3)
                blo, bhi = box.min(axis=1)[:, None], box.max(axis=1)[:, None]
                held |= np.all(verts - blo >= 0.999 * CORNER_PAD, axis=0) & np.all(
                    bhi - verts >= 0.999 * CORNER_PAD, axis=0
                )
            assert held.all()
            if parts == 2:  # the halves' boxes are smaller than the whole's
                assert (np.ptp(corners[:, :8], axis=1) < hi - lo + 3 * CORNER_PAD).all()
                assert np.ptp(corners[:, :8], axis=1).max() < 0.7 * (hi - lo).max()
            assert CORNER_PAD > 1e3 * np.spacing(np.abs(verts).max() + 10.0)


def test_kernel_limits_are_the_numpy_ones_plus_the_slack(bottle):
    checker, _, _ = bottle
    screen = checker._screens[1]
    broad, boxes, _, _, _ = checker._compiled_screen(screen)
    assert checker._compiled_screen(screen)[0] is broad  # built once
    world, limit1 = broad[6], broad[7]
    own = world < 0
    cov = checker._cover
    ra = cov.ball_radius[screen.geom_a]
    np.testing.assert_allclose(limit1[~own], ra[~own] + BROAD_MARGIN + kernels.SLACK, rtol=0)
    assert (np.sqrt(limit1[own]) > ra[own] + BROAD_MARGIN).all()
    for k, (_, _, _, beyond, deep) in boxes.items():
        halfs = screen.boxes[k][3]
        assert (beyond > halfs + BROAD_MARGIN).all() and (deep < halfs - INSIDE_DEPTH).all()


@pytest.mark.parametrize("robot_name", ["panda", "ur5"])
def test_a_world_without_collision_pairs_is_checked(compiled, robot_name):
    """No table, no object, no self-collision: no pair at all, every configuration free."""
    cfg = load_config(
        ROOT / "configs" / "bottle_side.yaml",
        [
            f"robot.spec={robot_name}",
            "environment.table=null",
            "environment.check_object=false",
            "environment.self_collision=false",
        ],
    )
    robot = P.robot_from_config(cfg)
    checker = make_checker(robot, cfg.environment, cfg.object)
    q = robot.random_configurations(300, 4)
    for mode in ("grasp", "approach", "retreat"):
        carried = np.broadcast_to(np.eye(4), (300, 4, 4)) if mode == "retreat" else None
        for rows in (q, q[:1], q[:0], np.asfortranarray(q)):
            got = checker.check(rows, mode, None if carried is None else carried[: len(rows)])
            assert got.shape == (len(rows),) and (got == "").all()
    assert checker.clearance(q[:3]).shape == (3,)


#: One geometry of each kind the broad phase bounds: the four it bounds exactly,
#: and two it bounds by their box (any other coal geometry takes that path).
_SHAPES = {
    "sphere": lambda: coal.Sphere(0.07),
    "cylinder": lambda: coal.Cylinder(0.05, 0.3),
    "capsule": lambda: coal.Capsule(0.04, 0.2),
    "box": lambda: coal.Box(0.3, 0.1, 0.05),
    "cone (its box)": lambda: coal.Cone(0.06, 0.2),
    "ellipsoid (its box)": lambda: coal.Ellipsoid(0.1, 0.05, 0.02),
}


@pytest.mark.parametrize("kind", [*_SHAPES, "self pair"])
@pytest.mark.parametrize("n", [0, 1, 3000])
def test_levels_1_and_2_bound_each_shape_kind_as_numpy(compiled, kind, n):
    """One pair, one sphere test: open exactly where the NumPy bound is within the limit.

    A point geometry on a joint whose frame moves it to random points around the
    shape (and through it); the pair is open in a configuration where
    :meth:`ShapeBound.lower` (a self pair: the distance to a second point) is at
    most the limit. Summation orders differ: only within 1e-9 m of the limit may
    the two disagree.
    """
    rng = np.random.default_rng(len(kind) + n)
    points = rng.uniform(-0.4, 0.4, (n, 3))
    tfs = np.zeros((2, n, 3, 4))
    tfs[:, :, :, :3] = np.eye(3)
    tfs[0, :, :, 3] = points
    tfs[1, :, :, 3] = rng.uniform(-0.4, 0.4, (n, 3))  # the other point of a self pair
    if kind == "self pair":
        world, shapes = -1, np.zeros((0, 21))
        want = np.linalg.norm(points - tfs[1, :, :, 3], axis=1)
    else:
        bound = ShapeBound(_SHAPES[kind](), random_rigid(rng))
        world, shapes = 0, bound.packed()[None]
        want = bound.lower(points)
        assert bound.exact == ("box)" not in kind)
    one, zero, origin = np.ones(1, np.intp), np.zeros(1, np.intp), np.zeros((2, 3))
    joints = np.arange(2)
    for limit in (0.0, 0.01, 0.05, 0.2):
        # a self pair's limits are squared distances
        lim = np.full(1, limit**2 if world < 0 else limit)
        # geometries 0 and 1, each one sphere at its joint's origin
        open_ = compiled.broad_phase(
            tfs, joints, origin, origin, np.arange(3), zero, one, np.full(1, world), lim, zero,
            one, zero, one, lim, shapes,
        )[0]  # fmt: skip
        assert open_.shape == (n,)
        assert np.all(want[open_] <= limit + 1e-9)
        assert np.all(open_[want <= limit - 1e-9])
        if n > 1 and limit == 0.2:
            assert 0 < open_.sum() < n  # both sides of the limit are tested


def test_level_3_of_a_robot_box_agrees_with_coal_and_the_numpy_level(compiled):
    """The UR5's 2F-85 body (a box from the gripper registry) against its forearm's mesh.

    In the frames of the box's joint: wherever the kernel or the NumPy level
    decides, coal's answer for the pair is the same (free where it says free:
    a vertex deep inside the box, the other answer, is rare for this pair and
    none of these configurations has one); and the checker's answers equal
    coal's over every pair.
    """
    cfg = load_config(ROOT / "configs" / "bottle_side_ur5.yaml")
    robot = P.robot_from_config(cfg)
    checker = make_checker(robot, cfg.environment, cfg.object, cfg.robot.base_pose.matrix())
    screen = checker._screens[1]
    assert screen.self_boxes, "no self pair with a box"
    names = [g.name for g in checker._gm.geometryObjects]
    columns = {
        tuple(
            sorted(
                (
                    names[checker._pairs[int(screen.pairs[k])].a],
                    names[checker._pairs[int(screen.pairs[k])].b],
                )
            )
        ): k
        for k in screen.self_boxes
    }
    k = columns[("forearm_link_0", "tool/body")]
    rng = np.random.default_rng(12)
    qs = robot.random_configurations(4000, rng)
    qs[:, 3] = rng.uniform(-3.2, 3.2, 4000)  # the wrist folded toward the forearm
    qs[:, 4] = rng.uniform(-2.5, 2.5, 4000)
    frames = checker._frames.compute(qs)
    rows = np.arange(len(qs))
    joint, box_joint, verts, inv, halfs = screen.self_boxes[k]
    rel = relative_transforms(np.stack(frames.transforms), joint, box_joint, rows)
    slack = kernels.SLACK  # the limits of _pair_hits_compiled
    beyond, deep = halfs + (BROAD_MARGIN + slack), halfs - (INSIDE_DEPTH + slack)
    status = compiled.hull_vs_box(rel, rows, verts, inv, beyond, deep)
    # the fused kernel places the hull by the same relative frames, row by row
    tfs = stacked(frames.transforms)
    some = rng.permutation(len(qs))[:3000]
    fused = compiled.hull_vs_robot_box(tfs, joint, box_joint, some, verts, inv, beyond, deep)
    np.testing.assert_array_equal(fused, status[some])
    assert compiled.hull_vs_robot_box(
        tfs, joint, box_joint, some[:0], verts, inv, beyond, deep
    ).shape == (0,)
    local = in_frame((rel[:, :, :3], rel[:, :, 3], inv), rows, verts)
    lim = halfs[None, :, None]
    inside = np.all(np.abs(local) < lim - INSIDE_DEPTH, axis=1).any(axis=1)
    free = beyond_a_face(local, lim) & ~inside
    assert inside[status == kernels.COLLIDES].all() and free[status == kernels.FREE].all()
    coal_says = checker._narrow(int(screen.pairs[k]), qs)
    assert not coal_says[free].any() and coal_says[inside].all()
    assert free.sum() > 500 and coal_says.sum() > 50  # both sides of the pair
    # the checker's answers with the level are coal's over every pair (grasp mode)
    ref = np.zeros(len(qs), dtype=bool)
    for c, pair in enumerate(checker._pairs):
        if pair.modes & 1:
            ref |= checker._run(checker._pair_pool[c], qs)
    np.testing.assert_array_equal(checker.check(qs) != "", ref)


def _broad_phase_one_by_one(tfs, broad):
    """Levels 1 and 2 (P, N) configuration by configuration, pair by pair, test by test.

    Python floats: the kernel's arithmetic in its order (each placed point as
    ``_place``, the bounds as ``_lower``), so the answers must be equal.
    """
    (ball_joint, ball_centre, sphere_centre, _, geom_a, geom_b, world, limit1,
     first_test, n_tests, sphere_a, sphere_b, limit2, shapes) = broad  # fmt: skip
    from gcm_pipeline.robot.collision import broadphase_kernel as bk  # imports Numba

    place, lower = bk._place.py_func, bk._lower.py_func
    out = np.zeros((geom_a.size, tfs.shape[1]), dtype=bool)
    for i in range(tfs.shape[1]):
        ball = np.empty((ball_joint.size, 3))
        for g, j in enumerate(ball_joint):
            place(tfs[j, i], ball_centre[g], ball[g])
        sphere = np.empty((sphere_centre.shape[0], 3))
        for e in range(sphere.shape[0]):
            # a cover sphere's joint: its geometry's (the bounding sphere's)
            g = np.searchsorted(broad[3], e, side="right") - 1
            place(tfs[ball_joint[g], i], sphere_centre[e], sphere[e])
        for k in range(geom_a.size):
            w = world[k]
            if w < 0:
                d = ball[geom_a[k]] - ball[geom_b[k]]
                near = d[0] * d[0] + d[1] * d[1] + d[2] * d[2] <= limit1[k]
            else:
                near = lower(ball[geom_a[k]], shapes[w]) <= limit1[k]
            for e in range(first_test[k], first_test[k] + n_tests[k]) if near else ():
                a = sphere[sphere_a[e]]
                if w < 0:
                    d = a - sphere[sphere_b[e]]
                    bound = d[0] * d[0] + d[1] * d[1] + d[2] * d[2]
                else:
                    bound = lower(a, shapes[w])
                if bound <= limit2[e]:
                    out[k, i] = True
                    break
    return out


def test_levels_1_and_2_equal_one_configuration_at_a_time(compiled, bottle):
    """The chunked kernel's answers are those of each (pair, configuration) on its own.

    Every route of level 2 is exercised: every test over a chunk where level 1
    left many configurations open, the open ones alone where it left few (pair
    by pair with covers placed for the chunk, configuration by configuration
    with covers placed there).
    """
    from gcm_pipeline.robot.collision import broadphase_kernel as bk

    checker, qs, _ = bottle
    screen = checker._screens[1]
    frames = checker._frames.compute(qs[:300])
    broad, _, _, _, _ = checker._compiled_screen(screen)
    tfs = stacked(frames.transforms)
    open_ = compiled.broad_phase(tfs, *broad)
    want = _broad_phase_one_by_one(tfs, broad)
    np.testing.assert_array_equal(open_, want)
    assert 0 < want.sum() < want.size
    # level 1's open counts per (pair, chunk) (one test, always within reach):
    # both of level 2's ways ran
    ones = (np.ones_like(broad[9]),)
    inf = np.full_like(broad[12], np.inf)
    level1 = compiled.broad_phase(tfs, *broad[:9], *ones, broad[10], broad[11], inf, broad[13])
    geom_a, geom_b, world = broad[4], broad[5], broad[6]
    routes = set()
    for i0 in range(0, 300, bk.CHUNK):
        near = level1[:, i0 : i0 + bk.CHUNK]
        m = near.shape[1]
        count = np.empty(geom_a.size, dtype=np.intp)
        whole = np.empty(broad[0].size, dtype=np.intp)
        bk._plan_chunk.py_func(m, near, geom_a, geom_b, world, count, whole)
        placed = (whole[geom_a] > 0) & ((world >= 0) | (whole[geom_b] > 0))
        every = (count * bk.DENSE >= m) | (placed & (count * 2 * bk.DENSE >= m))
        routes |= {"all"} if (every & (count > 0)).any() else set()
        routes |= {"open"} if (placed & ~every & (count > 0)).any() else set()
        routes |= {"each"} if (~placed & (count > 0)).any() else set()
    assert routes == {"all", "open", "each"}
