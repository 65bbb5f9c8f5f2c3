"""The compiled kernels (gcm_pipeline.robot.kernels) against the NumPy code they replace."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from gcm_pipeline import pipeline as P
from gcm_pipeline.config import load_config
from gcm_pipeline.geometry.dualquat import dq_to_matrix
from gcm_pipeline.robot import kernels
from gcm_pipeline.robot.chain import KinematicChain
from gcm_pipeline.robot.collision import (
    _BROAD_MARGIN,
    _INSIDE_DEPTH,
    _beyond_a_face,
    _in_frame,
    _stacked,
)
from gcm_pipeline.robot.ik import solve_ik
from gcm_pipeline.robot.model import load_robot
from gcm_pipeline.stages.collision import make_checker

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(autouse=True)
def _kernels_on(monkeypatch):
    """Each test starts with the kernels on, whatever the environment says."""
    monkeypatch.delenv("GCM_JIT", raising=False)


@pytest.fixture(scope="module")
def compiled():
    with pytest.MonkeyPatch.context() as mp:
        mp.delenv("GCM_JIT", raising=False)
        out = kernels.get()
    assert out is not None, "numba is a dependency: the kernels must load"
    return out


@pytest.fixture(scope="module")
def panda():
    return load_robot("panda")


def _numpy(monkeypatch, fn, *args):
    """``fn(*args)`` with the NumPy code (GCM_JIT=0)."""
    monkeypatch.setenv("GCM_JIT", "0")
    try:
        return fn(*args)
    finally:
        monkeypatch.delenv("GCM_JIT")


# --- loading ----------------------------------------------------------------------------


def test_the_package_and_its_command_line_do_not_import_numba():
    code = (
        "import sys\n"
        "from gcm_pipeline.__main__ import entry\n"
        "from gcm_pipeline.config import load_config\n"
        "import gcm_pipeline.pipeline, gcm_pipeline.robot.collision\n"
        "load_config('configs/bottle_side.yaml')\n"
        "for argv in (['--help'], ['validate', 'configs/bottle_side.yaml']):\n"
        "    sys.argv = ['gcm', *argv]\n"
        "    try:\n"
        "        entry()\n"
        "    except SystemExit:\n"
        "        pass\n"
        "print('numba' in sys.modules, file=sys.stderr)\n"
    )
    out = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, check=True, cwd=ROOT
    )
    assert "usage" in out.stdout and "bottle_side.yaml: ok" in out.stdout
    assert out.stderr.strip().splitlines()[-1] == "False"


def test_gcm_jit_0_selects_the_numpy_code(monkeypatch, panda, compiled):
    def fail(*args):
        raise AssertionError("the compiled kernels were called")

    monkeypatch.setattr(kernels, "_load", fail)
    monkeypatch.setenv("GCM_JIT", "0")
    assert kernels.get() is None
    q = panda.random_configurations(300, 0)
    rot, pos, jac = panda.chain._forward(q, True)  # the NumPy path, not the kernel
    assert rot.shape == (300, 3, 3) and jac is not None and jac.shape == (300, 6, 7)
    checker = make_checker(panda)
    assert checker.check(q).shape == (300,)
    monkeypatch.setenv("GCM_JIT", "1")
    with pytest.raises(AssertionError, match="were called"):
        kernels.get()


def test_without_numba_the_numpy_code_is_used():
    import gcm_pipeline.robot as package

    kernels._load.cache_clear()
    try:
        with pytest.MonkeyPatch.context() as mp:
            mp.setitem(sys.modules, "numba", None)  # import numba raises ImportError
            mp.delitem(sys.modules, "gcm_pipeline.robot._compiled", raising=False)
            mp.delattr(package, "_compiled", raising=False)
            assert kernels.get() is None
    finally:
        kernels._load.cache_clear()
    assert kernels.get() is not None


def test_numbas_own_switch_and_other_spellings_select_numpy(monkeypatch):
    # NUMBA_DISABLE_JIT would run the kernels as Python (and the FMA intrinsic cannot)
    code = (
        "from gcm_pipeline.robot import kernels\n"
        "from gcm_pipeline.robot.model import load_robot\n"
        "from gcm_pipeline.robot.ik import solve_ik\n"
        "r = load_robot('panda')\n"
        "res = solve_ik(r, r.fk(r.random_configurations(20, 1)))\n"
        "print(kernels.get() is None, bool(res.success.all()))\n"
    )
    env = {k: v for k, v in os.environ.items() if k != "GCM_JIT"}
    out = subprocess.run(
        [sys.executable, "-c", code],
        capture_output=True,
        text=True,
        check=True,
        cwd=ROOT,
        env={**env, "NUMBA_DISABLE_JIT": "1", "PYTHONPATH": str(ROOT)},
    )
    assert out.stdout.split() == ["True", "True"], out.stderr
    for value in ("off", "False", " no "):
        monkeypatch.setenv("GCM_JIT", value)
        assert kernels.get() is None
    monkeypatch.setenv("GCM_JIT", "1")
    assert kernels.get() is not None
    with kernels.suppressed():
        assert kernels.get() is None
    assert kernels.get() is not None


def test_a_long_load_says_that_it_compiles(monkeypatch, caplog):
    import time

    real = kernels._import

    def slow():
        time.sleep(0.3)  # as a first run's compilation, only shorter
        return real()

    monkeypatch.setattr(kernels, "_NOTICE_AFTER", 0.05)
    for load, said in ((slow, True), (real, False)):
        monkeypatch.setattr(kernels, "_import", load)
        kernels._load.cache_clear()
        caplog.clear()
        try:
            with caplog.at_level("WARNING", logger="gcm_pipeline.robot.kernels"):
                assert kernels.get() is not None
                time.sleep(0.1)  # a notice still pending would fire now
        finally:
            kernels._load.cache_clear()
        assert ("compiling the package's kernels" in caplog.text) is said
        assert caplog.text.count("compiling") <= 1


# --- forward kinematics -----------------------------------------------------------------


def _chains():
    panda, ur5 = load_robot("panda"), load_robot("ur5")
    link4 = panda.model.getFrameId("panda_link4")
    return {
        "panda": panda.chain,
        "ur5_tool": ur5.chain,
        # joints 1-4 of 7: q_index is not 0..nq-1, the Jacobian's last columns are zero
        "panda_link4": KinematicChain(panda.model, link4),
    }


@pytest.mark.parametrize("name", ["panda", "ur5_tool", "panda_link4"])
@pytest.mark.parametrize("n", [0, 1, 1000])
def test_fk_kernel_equals_numpy(monkeypatch, compiled, name, n):
    chain = _chains()[name]
    rng = np.random.default_rng(n)
    q = rng.uniform(-np.pi, np.pi, (n, chain.nq))
    q.setflags(write=False)  # read-only arrays are taken too (a robot's home is one)
    ref = _numpy(monkeypatch, chain._forward, q, True)
    out = chain._forward(q, True)
    for got, want in zip(out, ref, strict=True):
        assert got.shape == want.shape
        np.testing.assert_allclose(got, want, rtol=0, atol=1e-12)
    if name == "panda_link4":
        assert list(chain.q_index) == [0, 1, 2, 3] and chain.nq == 7
        assert not out[2][:, :, 4:].any()
    rot, pos, jac = chain._forward(q, False)
    assert jac is None
    np.testing.assert_allclose(rot, ref[0], rtol=0, atol=1e-12)
    np.testing.assert_allclose(pos, ref[1], rtol=0, atol=1e-12)
    # the public API, in chunks (a strided q is accepted too)
    big = np.repeat(q, 3, axis=0)[::3] if n else q
    np.testing.assert_allclose(chain.pose_jacobian(big)[2], ref[2], rtol=0, atol=1e-12)


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
def test_collision_reasons_equal_numpy(monkeypatch, compiled, bottle, mode):
    checker, qs, held = bottle
    carried = held if mode == "retreat" else None
    ref = _numpy(monkeypatch, checker.check, qs, mode, carried)
    out = checker.check(qs, mode, carried)
    np.testing.assert_array_equal(out, ref)
    kinds = dict(zip(*np.unique(ref, return_counts=True), strict=True))
    assert kinds[""] > 300 and len(kinds) >= 3  # free and colliding of several kinds


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
def test_the_kernels_leave_open_what_numpy_leaves_open(monkeypatch, compiled, bottle, mode):
    """Every (pair, configuration) that NumPy sends to coal, the kernels send too.

    For a pair without a box that is the set levels 1 and 2 leave open; with a
    box, what level 3 leaves undecided after them.
    """
    checker, qs, _ = bottle
    ref = _coal_calls(checker, lambda: _numpy(monkeypatch, checker.check, qs, mode))
    out = _coal_calls(checker, lambda: checker.check(qs, mode))
    assert sum(len(v) for v in ref.values()) > 1000
    for pool, rows in ref.items():
        assert rows <= out.get(pool, set())
    # conservative, not loose: only entries within the slack of a threshold are added
    extra = sum(len(out[p] - ref.get(p, set())) for p in out)
    assert extra <= 0.01 * sum(len(v) for v in ref.values())


def test_open_pairs_contain_the_colliding_ones(compiled, bottle):
    checker, qs, _ = bottle
    screen = checker._screens[1]
    frames = checker._frames.compute(qs[:2048])
    broad, _ = checker._compiled_screen(screen)
    open_ = compiled.broad_phase(_stacked_checked(frames), *broad)
    hit = checker._pair_hits_compiled(compiled, qs[:2048], frames, screen)
    assert hit.any() and not (hit.T & ~open_).any()


def _stacked_checked(frames):
    """The frames as one array, as the kernels take them: a view, not a copy."""
    tfs = _stacked(frames.transforms)
    assert tfs.base is None and tfs is frames.transforms[0].base  # no copy
    taken = frames.take(np.arange(5))
    np.testing.assert_array_equal(_stacked(taken.transforms), tfs[:, :5])
    return tfs


def test_level_3_agrees_with_numpy_wherever_it_decides(compiled, bottle):
    checker, qs, _ = bottle
    screen = checker._screens[1]
    frames = checker._frames.compute(qs)
    rots, poss = frames.rots, frames.poss
    tfs = np.stack(frames.transforms)
    _, boxes = checker._compiled_screen(screen)
    assert boxes
    rows = np.arange(len(qs))
    decided = {kernels.FREE: 0, kernels.COLLIDES: 0}
    for k, (joint, verts, inv, beyond, deep) in boxes.items():
        status = compiled.hull_vs_box(tfs[joint], rows, verts, inv, beyond, deep)
        # the NumPy level 3 on every vertex: colliding when one lies deep inside,
        # free when all lie beyond one face plane
        halfs = screen.boxes[k][3]
        local = _in_frame((rots[joint], poss[joint], inv), rows, verts)
        lim = halfs[None, :, None]
        inside = np.all(np.abs(local) < lim - _INSIDE_DEPTH, axis=1).any(axis=1)
        free = _beyond_a_face(local, lim) & ~inside
        assert inside[status == kernels.COLLIDES].all()
        assert free[status == kernels.FREE].all()
        # and undecided only where the NumPy level is undecided too (or within the slack)
        assert not ((status == kernels.UNDECIDED) & (inside | free)).any()
        for s in decided:
            decided[s] += int((status == s).sum())
    assert decided[kernels.FREE] > 1000 and decided[kernels.COLLIDES] > 100


def test_kernel_limits_are_the_numpy_ones_plus_the_slack(bottle):
    checker, _, _ = bottle
    screen = checker._screens[1]
    broad, boxes = checker._compiled_screen(screen)
    assert checker._compiled_screen(screen)[0] is broad  # built once
    world, limit1 = broad[6], broad[7]
    own = world < 0
    cov = checker._cover
    ra = cov.ball_radius[screen.geom_a]
    np.testing.assert_allclose(limit1[~own], ra[~own] + _BROAD_MARGIN + kernels.SLACK, rtol=0)
    assert (np.sqrt(limit1[own]) > ra[own] + _BROAD_MARGIN).all()
    for k, (_, _, _, beyond, deep) in boxes.items():
        halfs = screen.boxes[k][3]
        assert (beyond > halfs + _BROAD_MARGIN).all() and (deep < halfs - _INSIDE_DEPTH).all()


# --- IK iterations, the approach's deviation, the Panda's closed form -------------------


def _near_targets(robot, n, seed):
    """Targets (rotations, positions) of random configurations and seeds around them.

    Seeds 0.02-0.6 rad away: most converge, some stall or stop at a joint limit;
    a tenth start half a turn of joint 7 away (the orientation error's half-turn case).
    """
    rng = np.random.default_rng(seed)
    q = robot.random_configurations(n, rng)
    rot, pos = robot.chain.pose(q)
    scale = rng.choice([0.02, 0.2, 0.6], size=(n, 1))
    seeds = np.clip(q + scale * rng.normal(size=q.shape), robot.lower, robot.upper)
    flip = rng.random(n) < 0.1
    seeds[flip, 6] = np.clip(q[flip, 6] + np.pi, robot.lower[6], robot.upper[6])
    return seeds, rot, pos


@pytest.mark.parametrize("clamp", [True, False])
def test_lm_kernel_equals_numpy(monkeypatch, compiled, panda, clamp):
    from gcm_pipeline.robot.ik_pinocchio import PinocchioIKOptions, _lm

    seeds, rot, pos = _near_targets(panda, 3000, 11)
    for opts in (PinocchioIKOptions(), PinocchioIKOptions(stall_ratio=0.0, max_iterations=6)):
        args = (panda.chain, seeds, rot, pos, panda.lower, panda.upper, 1e-6, 1e-5, opts, clamp)
        q, conv, pe, re = _lm(*args)
        q_ref, conv_ref, pe_ref, re_ref = _numpy(monkeypatch, _lm, *args)
        np.testing.assert_array_equal(conv, conv_ref)
        assert 0.3 < conv.mean() < 0.97  # converged and failed rows both tested
        np.testing.assert_allclose(q, q_ref, rtol=0, atol=1e-8)
        np.testing.assert_allclose(pe, pe_ref, rtol=1e-6, atol=1e-12)
        np.testing.assert_allclose(re, re_ref, rtol=1e-6, atol=1e-12)
        assert np.all(pe[conv] <= 1e-6) and np.all(re[conv] <= 1e-5)
        if clamp:
            assert np.all((q >= panda.lower) & (q <= panda.upper))
    # a half turn away in orientation: the rotation vector's length is pi
    flip = np.diag([1.0, -1.0, -1.0])
    q0 = panda.random_configurations(1, 3)
    r0, p0 = panda.chain.pose(q0)
    one = (panda.chain, q0, r0 @ flip, p0, panda.lower, panda.upper, 1e-6, 1e-5)
    got = _lm(*one, PinocchioIKOptions(max_iterations=0))
    ref = _numpy(monkeypatch, _lm, *one, PinocchioIKOptions(max_iterations=0))
    assert got[3][0] == pytest.approx(np.pi) and ref[3][0] == pytest.approx(np.pi)


@pytest.mark.parametrize("reject", [np.inf, 2e-3])
def test_segment_bound_kernel_equals_numpy(monkeypatch, compiled, panda, reject):
    from gcm_pipeline.robot.approach import _segment_bounds, lever_arms

    rng = np.random.default_rng(12)
    n = 2000
    q_a = panda.random_configurations(n, rng)
    # short and long joint segments: 2 to 64 samples
    q_b = q_a + rng.choice([0.005, 0.05, 0.3], size=(n, 1)) * rng.normal(size=q_a.shape)
    rot, pos = panda.chain.pose(q_a)
    offsets = rng.normal(0.0, 0.05, (n, 3))
    offsets[:10] = 0.0  # a move of zero length
    args = (panda, lever_arms(panda), q_a, q_b, pos, rot, offsets, 0.12, 1e-3, reject)
    got = _segment_bounds(*args)
    ref = _numpy(monkeypatch, _segment_bounds, *args)
    np.testing.assert_allclose(got, ref, rtol=1e-9, atol=1e-12)
    assert np.unique(got > 5e-3).size == 2
    # arrays in any memory layout (the kernel takes C arrays)
    strided = (*args[:2], np.asfortranarray(q_a), q_b[:, ::-1][:, ::-1], *args[4:])
    np.testing.assert_array_equal(_segment_bounds(*strided), got)


@pytest.mark.parametrize("near", [False, True])
def test_closed_form_kernel_equals_numpy(monkeypatch, compiled, panda, near):
    from gcm_pipeline.robot.ik_pinocchio import analytic_solver

    solver = analytic_solver(panda)
    rng = np.random.default_rng(13)
    q = panda.random_configurations(2000, rng)
    rot, pos = panda.chain.pose(q)
    q7 = q[:, 6:7] + np.array([0.0, -0.05, 0.05, 0.4, -1.5, 3.5])  # some outside the limits
    pos[:20] += 5.0  # out of reach: no solution
    args = (rot, pos, q7, panda.lower, panda.upper, (q, 0.3) if near else None)
    got = solver.solve(*args)
    ref = _numpy(monkeypatch, solver.solve, *args)
    for name, a, b in zip(("index", "q", "branch", "column"), got, ref, strict=True):
        assert a.shape == b.shape, name
        np.testing.assert_allclose(a, b, rtol=0, atol=1e-12, err_msg=name)
    assert len(got[0]) > 2000 and not np.isin(np.arange(20), got[0]).any()
    # every solution reaches its target
    r, p = panda.chain.pose(got[1])
    np.testing.assert_allclose(p, pos[got[0]], atol=1e-9)
    np.testing.assert_allclose(r, rot[got[0]], atol=1e-9)
    assert solver.solve(rot[:0], pos[:0], q7[:0], panda.lower, panda.upper)[1].shape == (0, 7)


def test_reachability_with_and_without_kernels(monkeypatch, compiled):
    """The whole check: the same decisions, configurations equal to round-off."""
    cfg = load_config(ROOT / "configs" / "bottle_side.yaml", ["ik.workers=1"])
    cand = P.generate_candidates(cfg)
    grasps = P.densify(cand, P.build_manifold(cand, cfg), cfg)
    robot = P.robot_from_config(cfg)
    out = P.check_reachability(grasps, robot, cfg)
    ref = _numpy(monkeypatch, P.check_reachability, grasps, robot, cfg)
    np.testing.assert_array_equal(out["reachable"], ref["reachable"])
    np.testing.assert_array_equal(out["reason"], ref["reason"])
    assert 0 < out["reachable"].sum() < len(out["reachable"])
    for key in ("q", "q_pregrasp", "clearance"):
        np.testing.assert_allclose(np.asarray(out[key]), np.asarray(ref[key]), atol=1e-8)


def test_kernels_never_read_past_mismatched_arrays(monkeypatch, compiled, panda):
    """Shapes the kernels do not expect get the NumPy code (its errors), not stray memory."""
    from gcm_pipeline.robot.ik_pinocchio import PinocchioIKOptions, _lm, analytic_solver

    q = panda.random_configurations(5, 1)
    with pytest.raises(IndexError):
        panda.chain.pose(q[:, :3])  # too few joints
    rot, pos = panda.chain.pose(q)
    solver = analytic_solver(panda)
    with pytest.raises(IndexError):
        solver.solve(rot, pos, np.zeros((40, 1)), panda.lower, panda.upper)  # q7 rows
    got = solver.solve(rot, pos, q[:, 6:7], panda.lower, panda.upper)
    ref = _numpy(monkeypatch, solver.solve, rot, pos, q[:, 6:7], panda.lower, panda.upper)
    assert np.array_equal(got[0], ref[0]) and set(got[0]) == set(range(5))
    # an iteration budget far beyond memory: the stall test needs only the last scores
    opts = PinocchioIKOptions(max_iterations=2**40)
    args = (panda.chain, q + 0.1, rot, pos, panda.lower, panda.upper, 1e-6, 1e-5, opts)
    conv = _lm(*args)[1]
    assert np.array_equal(conv, _numpy(monkeypatch, _lm, *args)[1])
