"""The compiled kernels (gcm_pipeline.robot.kernels) against the NumPy code they replace.

What is compared is what a user relies on, with tolerances that hold on any
x86-64 or arm64 CPU (another CPU changes the NumPy code's last bits: OpenBLAS
picks its dgemm kernel at run time, NumPy its SIMD sine and cosine):

* closed forms (forward kinematics, Jacobians, the Panda's IK): values to
  tolerances far above round-off (no iteration amplifies it), and checked
  against Pinocchio;
* iterative solvers (the IK's Levenberg-Marquardt): convergence flags, the
  pose error of each answer recomputed by Pinocchio, the joint limits;
  never the last bits of q;
* decisions (collision reasons, reachable flags): equal.
"""

from __future__ import annotations

import os
import subprocess
import sys

import numpy as np
import pinocchio as pin
import pytest
from helpers import ROOT

from gcm_pipeline import pipeline as P
from gcm_pipeline.config import load_config
from gcm_pipeline.config.robot_spec import load_robot
from gcm_pipeline.geometry.dualquat import dq_to_matrix
from gcm_pipeline.pipeline import make_checker
from gcm_pipeline.robot import kernels
from gcm_pipeline.robot.chain import KinematicChain
from gcm_pipeline.robot.collision.broadphase import (
    BROAD_MARGIN,
    INSIDE_DEPTH,
    beyond_a_face,
    in_frame,
    stacked,
)
from gcm_pipeline.robot.ik import solve_ik


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


def _numpy(monkeypatch, fn, *args):
    """``fn(*args)`` with the NumPy code (GCM_JIT=0)."""
    monkeypatch.setenv("GCM_JIT", "0")
    try:
        return fn(*args)
    finally:
        monkeypatch.delenv("GCM_JIT")


def _pin_frames(model, frame_id, q):
    """Pose (rotations (N, 3, 3), positions (N, 3)) and world-aligned Jacobians of a
    frame, by Pinocchio itself, one configuration at a time."""
    data = model.createData()
    rot, pos, jac = [], [], []
    for qi in np.atleast_2d(q):
        pin.computeJointJacobians(model, data, qi)
        pin.updateFramePlacements(model, data)
        placement = data.oMf[frame_id]
        rot.append(placement.rotation.copy())
        pos.append(placement.translation.copy())
        jac.append(
            pin.getFrameJacobian(model, data, frame_id, pin.ReferenceFrame.LOCAL_WORLD_ALIGNED)
        )
    return np.array(rot), np.array(pos), np.array(jac)


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


def _pose_errors(robot, q, rot, pos):
    """Position [m] and rotation [rad] error of each configuration's grasp frame, by Pinocchio."""
    tf = robot.fk_pinocchio(q)
    pe = np.linalg.norm(tf[:, :3, 3] - pos, axis=1)
    rel = np.einsum("nij,nkj->nik", rot, tf[:, :3, :3])  # target @ reached^T
    re = np.array([np.linalg.norm(pin.log3(r)) for r in rel])
    return pe, re


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


#: The modules that import Numba, by :func:`kernels.get` only.
KERNEL_MODULES = [
    "gcm_pipeline.robot.kernel_common",
    "gcm_pipeline.robot.chain_kernel",
    "gcm_pipeline.robot.collision.broadphase_kernel",
    "gcm_pipeline.robot.ik.lm_kernel",
    "gcm_pipeline.robot.ik.panda_kernel",
]


def test_without_numba_the_numpy_code_is_used():
    kernels._load.cache_clear()
    try:
        with pytest.MonkeyPatch.context() as mp:
            mp.setitem(sys.modules, "numba", None)  # import numba raises ImportError
            for name in KERNEL_MODULES:  # imported again, they would import numba
                mp.delitem(sys.modules, name, raising=False)
                parent, _, leaf = name.rpartition(".")
                mp.delattr(sys.modules[parent], leaf, raising=False)
            assert kernels.get() is None
    finally:
        kernels._load.cache_clear()
    assert kernels.get() is not None


def test_numbas_own_switch_and_other_spellings_select_numpy(monkeypatch):
    # NUMBA_DISABLE_JIT would run the kernels as Python (and the FMA intrinsic cannot)
    code = (
        "from gcm_pipeline.robot import kernels\n"
        "from gcm_pipeline.config.robot_spec import load_robot\n"
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


def _chains(panda):
    """Chains by name: (chain, the model, the frame's id in it)."""
    ur5 = load_robot("ur5")
    link4 = panda.model.getFrameId("panda_link4")
    return {
        "panda": (panda.chain, panda.model, panda.grasp_frame_id),
        "ur5_tool": (ur5.chain, ur5.model, ur5.grasp_frame_id),
        # joints 1-4 of 7: q_index is not 0..nq-1, the Jacobian's last columns are zero
        "panda_link4": (KinematicChain(panda.model, link4), panda.model, link4),
    }


@pytest.mark.parametrize("name", ["panda", "ur5_tool", "panda_link4"])
@pytest.mark.parametrize("n", [0, 1, 1000])
def test_fk_kernel_equals_numpy(monkeypatch, compiled, panda, name, n):
    """Forward kinematics is a closed form: no iteration amplifies round-off.

    The kernel and the NumPy code sum in other orders on other CPUs; each
    result is within a few ulps of the exact one, so they agree, and agree
    with Pinocchio, to 1e-12 (about 5,000 ulps of values of order 1).
    """
    chain, model, frame_id = _chains(panda)[name]
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
    # and what Pinocchio computes (the first 50 rows: a Python loop)
    if n:
        want = _pin_frames(model, frame_id, q[:50])
        for got, exact in zip(out, want, strict=True):
            np.testing.assert_allclose(got[:50], exact, rtol=0, atol=1e-12)


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
    tfs = stacked(frames.transforms)
    assert tfs.base is None and tfs is frames.transforms[0].base  # no copy
    taken = frames.take(np.arange(5))
    np.testing.assert_array_equal(stacked(taken.transforms), tfs[:, :5])
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


def test_kernel_limits_are_the_numpy_ones_plus_the_slack(bottle):
    checker, _, _ = bottle
    screen = checker._screens[1]
    broad, boxes = checker._compiled_screen(screen)
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


#: Rows of an iterative solver whose convergence flag may differ from the NumPy
#: code's: round-off differs between CPUs, and the LM amplifies it where a
#: decision is taken at its threshold (a joint that crosses its limit by an
#: ulp is frozen or not; a stall test at its ratio). 0 of 3,000 rows differed
#: on an x86-64 machine, with the native and the generic build (and the NumPy
#: code against itself from seeds moved by one ulp); a damping 5 % off flips
#: 18 and moves 1,601 of the 2,640 converged rows by more than 1e-6 rad.
_FLIP_SHARE = 1e-3


@pytest.mark.parametrize("clamp", [True, False])
def test_lm_kernel_equals_numpy(monkeypatch, compiled, panda, clamp):
    """The compiled LM decides as the NumPy LM and its answers are what it says.

    Compared: the convergence flags (all but :data:`_FLIP_SHARE` of the rows),
    the pose error of every answer recomputed by Pinocchio (within the
    tolerances where converged, equal to the error the kernel reports), the
    joint limits; the rows converged by both end at the same solution (all
    but 1 % within 1e-6 rad: the tolerances allow a solver to stop anywhere in
    a small ball, but from the same seed by the same steps only round-off
    amplified at a threshold moves an answer; a different step rule moves
    most). Never q to the last bits.
    """
    from gcm_pipeline.robot.ik.lm import PinocchioIKOptions, levenberg_marquardt

    seeds, rot, pos = _near_targets(panda, 3000, 11)
    tol_p, tol_r = 1e-6, 1e-5
    for opts in (PinocchioIKOptions(), PinocchioIKOptions(stall_ratio=0.0, max_iterations=6)):
        args = (panda.chain, seeds, rot, pos, panda.lower, panda.upper, tol_p, tol_r, opts, clamp)
        q, conv, pe, re = levenberg_marquardt(*args)
        q_ref, conv_ref, pe_ref, re_ref = _numpy(monkeypatch, levenberg_marquardt, *args)
        assert 0.3 < conv_ref.mean() < 0.97  # converged and failed rows both tested
        assert (conv != conv_ref).sum() <= _FLIP_SHARE * len(conv)
        # every answer: its error as Pinocchio computes it, within the tolerances if converged
        pin_pe, pin_re = _pose_errors(panda, q, rot, pos)
        np.testing.assert_allclose(pe, pin_pe, rtol=1e-6, atol=1e-12)
        np.testing.assert_allclose(re, pin_re, rtol=1e-6, atol=1e-12)
        assert np.all(pin_pe[conv] <= tol_p * (1 + 1e-6)) and np.all(
            pin_re[conv] <= tol_r * (1 + 1e-6)
        )
        # not converged: the pose is not within the tolerances (the flag is not dropped)
        assert np.all((pin_pe[~conv] > tol_p * (1 - 1e-6)) | (pin_re[~conv] > tol_r * (1 - 1e-6)))
        if clamp:
            assert np.all((q >= panda.lower) & (q <= panda.upper))
        both = conv & conv_ref
        apart = np.abs(q[both] - q_ref[both]).max(axis=1)
        assert (apart > 1e-6).mean() <= 0.01, np.sort(apart)[-10:]
    # a half turn away in orientation: the rotation vector's length is pi
    flip = np.diag([1.0, -1.0, -1.0])
    q0 = panda.random_configurations(1, 3)
    r0, p0 = panda.chain.pose(q0)
    one = (panda.chain, q0, r0 @ flip, p0, panda.lower, panda.upper, 1e-6, 1e-5)
    got = levenberg_marquardt(*one, PinocchioIKOptions(max_iterations=0))
    ref = _numpy(monkeypatch, levenberg_marquardt, *one, PinocchioIKOptions(max_iterations=0))
    assert got[3][0] == pytest.approx(np.pi) and ref[3][0] == pytest.approx(np.pi)


@pytest.mark.parametrize("reject", [np.inf, 2e-3])
def test_segment_bound_kernel_equals_numpy(monkeypatch, compiled, panda, reject):
    from gcm_pipeline.reach.deviation import lever_arms, sample_deviation, segment_bounds

    rng = np.random.default_rng(12)
    n = 2000
    q_a = panda.random_configurations(n, rng)
    # short and long joint segments: 2 to 64 samples
    q_b = q_a + rng.choice([0.005, 0.05, 0.3], size=(n, 1)) * rng.normal(size=q_a.shape)
    rot, pos = panda.chain.pose(q_a)
    offsets = rng.normal(0.0, 0.05, (n, 3))
    offsets[:10] = 0.0  # a move of zero length
    args = (panda, lever_arms(panda), q_a, q_b, pos, rot, offsets, 0.12, 1e-3, reject)
    got = segment_bounds(*args)
    ref = _numpy(monkeypatch, segment_bounds, *args)
    # sums of a few samples' distances: round-off only (1e-9 is 10^7 ulps); except a
    # segment whose midpoint lies within round-off of ``reject`` (its bound is either
    # the midpoint's or the full one): none of the 2,000 here, on any CPU
    mid = _numpy(monkeypatch, sample_deviation, panda, 0.5 * (q_a + q_b), pos, rot, offsets, 0.12)
    sure = np.abs(mid - reject) > 1e-9
    assert sure.all()
    np.testing.assert_allclose(got, ref, rtol=1e-9, atol=1e-12)
    assert np.unique(got > 5e-3).size == 2
    # what matters: a segment whose midpoint exceeds ``reject`` is rejected; any other
    # gets a bound, above the deviation sampled 8x finer than any row's samples
    assert np.all(got[mid > reject] > reject)
    s = np.linspace(0.0, 1.0, 513)
    rows = np.arange(0, n, 10)
    qs = q_a[rows, None] + s[None, :, None] * (q_b - q_a)[rows, None]
    fine = sample_deviation(
        panda,
        qs.reshape(-1, panda.nq),
        np.repeat(pos[rows], s.size, axis=0),
        np.repeat(rot[rows], s.size, axis=0),
        np.repeat(offsets[rows], s.size, axis=0),
        0.12,
    ).reshape(rows.size, s.size)
    kept = mid[rows] <= reject
    assert kept.sum() >= 10
    assert np.all(got[rows][kept] >= fine.max(axis=1)[kept] - 1e-12)
    # arrays in any memory layout (the kernel takes C arrays)
    strided = (*args[:2], np.asfortranarray(q_a), q_b[:, ::-1][:, ::-1], *args[4:])
    np.testing.assert_array_equal(segment_bounds(*strided), got)


@pytest.mark.parametrize("near", [False, True])
def test_closed_form_kernel_equals_numpy(monkeypatch, compiled, panda, near):
    from gcm_pipeline.robot.ik.panda import analytic_solver

    solver = analytic_solver(panda)
    rng = np.random.default_rng(13)
    q = panda.random_configurations(2000, rng)
    rot, pos = panda.chain.pose(q)
    q7 = q[:, 6:7] + np.array([0.0, -0.05, 0.05, 0.4, -1.5, 3.5])  # some outside the limits
    pos[:20] += 5.0  # out of reach: no solution
    args = (rot, pos, q7, panda.lower, panda.upper, (q, 0.3) if near else None)
    got = solver.solve(*args)
    ref = _numpy(monkeypatch, solver.solve, *args)
    # the same solutions, as (target, branch, q7 column); a solution within round-off
    # of a joint limit (or of acos's domain) may be kept by one and not the other:
    # at most 0.1 % (none on the machines measured)
    keys = [set(zip(a[0].tolist(), a[2].tolist(), a[3].tolist(), strict=True)) for a in (got, ref)]
    assert len(keys[0] ^ keys[1]) <= 1e-3 * len(keys[1])
    assert len(got[0]) > 2000 and not np.isin(np.arange(20), got[0]).any()
    # in the same order, the same angles: a closed form, where only acos near +-1
    # amplifies round-off (an input off by 1 ulp moves the angle by up to
    # sqrt(2 eps) = 2e-8 rad; 1e-6 rad leaves 50x)
    common = keys[0] & keys[1]
    at = [np.array([k in common for k in zip(a[0], a[2], a[3], strict=True)]) for a in (got, ref)]
    fields = zip(("index", "branch", "column"), got[::2] + got[3:], ref[::2] + ref[3:], strict=True)
    for name, a, b in fields:
        np.testing.assert_array_equal(a[at[0]], b[at[1]], err_msg=name)
    np.testing.assert_allclose(got[1][at[0]], ref[1][at[1]], rtol=0, atol=1e-6)
    # every solution reaches its target, as Pinocchio computes it, within the limits
    pe, re = _pose_errors(panda, got[1], rot[got[0]], pos[got[0]])
    assert pe.max() < 1e-9 and re.max() < 1e-9
    assert np.all((got[1] >= panda.lower) & (got[1] <= panda.upper))
    if near:
        assert np.all(np.abs(got[1] - q[got[0]]) <= 0.3)
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
    ok = np.asarray(out["reachable"])
    assert 0 < ok.sum() < len(ok)
    # each answer, checked by Pinocchio and the NumPy checker: at its grasp within the
    # IK tolerances, inside the limits, collision-free
    q = np.asarray(out["q"])[ok]
    target = np.linalg.inv(cfg.robot.base_pose.matrix()) @ dq_to_matrix(
        np.asarray(grasps["dq"])[ok]
    )
    pe, re = _pose_errors(robot, q, target[:, :3, :3], target[:, :3, 3])
    assert pe.max() <= cfg.ik.position_tolerance * (1 + 1e-6)
    assert re.max() <= cfg.ik.orientation_tolerance * (1 + 1e-6)
    assert robot.within_limits(q).all()
    checker = make_checker(robot, cfg.environment, cfg.object)
    assert (_numpy(monkeypatch, checker.check, q, "grasp") == "").all()
    # the same solutions (not to the last bits: an iterative solver's answer moves
    # with round-off anywhere in its tolerance ball; 1e-3 rad is that ball's size,
    # far below the distance between two branches), the clearance to its precision
    np.testing.assert_allclose(q, np.asarray(ref["q"])[ok], rtol=0, atol=1e-3)
    np.testing.assert_allclose(
        np.asarray(out["clearance"])[ok], np.asarray(ref["clearance"])[ok], rtol=0, atol=1e-3
    )


def test_kernels_never_read_past_mismatched_arrays(monkeypatch, compiled, panda):
    """Shapes the kernels do not expect get the NumPy code (its errors), not stray memory."""
    from gcm_pipeline.robot.ik.lm import PinocchioIKOptions, levenberg_marquardt
    from gcm_pipeline.robot.ik.panda import analytic_solver

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
    conv = levenberg_marquardt(*args)[1]
    assert np.array_equal(conv, _numpy(monkeypatch, levenberg_marquardt, *args)[1])


# --- every input a NumPy reference takes ------------------------------------------------


def _layouts(a):
    """``a`` (float64, C order) as a caller may hand it over: every variant, by name."""
    read_only = a.copy()
    read_only.setflags(write=False)
    out = {
        "C": a,
        "fortran": np.asfortranarray(a),
        "read-only": read_only,
        "float32": a.astype(np.float32),
        "reversed": a[::-1].copy()[::-1],
    }
    if a.ndim == 2 and len(a):
        out["strided"] = np.repeat(a, 2, axis=0)[::2]
    return out


@pytest.mark.parametrize("n", [0, 1, 5])
def test_kernels_take_any_layout_dtype_and_row_count(monkeypatch, compiled, n):
    """Zero rows, one row, Fortran order, strides, read-only, float32 or int arrays:
    each kernel (not the NumPy fallback) takes them and answers as the NumPy code."""
    from gcm_pipeline.reach.deviation import lever_arms, segment_bounds
    from gcm_pipeline.robot.ik.lm import PinocchioIKOptions, levenberg_marquardt
    from gcm_pipeline.robot.ik.panda import analytic_solver

    calls = {}

    def counting(name, fn):
        def wrapped(*args):
            calls[name] = calls.get(name, 0) + 1
            return fn(*args)

        return wrapped

    real = kernels.get()
    spied = kernels.Kernels(*(counting(f, getattr(real, f)) for f in kernels.Kernels._fields))
    monkeypatch.setattr(kernels, "_load", lambda: spied)
    robots = {name: load_robot(name) for name in ("panda", "ur5")}
    for robot in robots.values():
        q0 = robot.random_configurations(n, 1)
        rot, pos = robot.chain.pose(q0)
        lev = lever_arms(robot)
        opts = PinocchioIKOptions()
        for layout, q in {**_layouts(q0), "int": np.round(q0).astype(int)}.items():
            qf = np.asarray(q, dtype=float)
            for got, want in zip(
                robot.chain._forward(q, True),
                _numpy(monkeypatch, robot.chain._forward, qf, True),
                strict=True,
            ):
                np.testing.assert_allclose(got, want, rtol=0, atol=1e-12, err_msg=layout)
            lm = (robot.chain, q, rot, pos, robot.lower, robot.upper, 1e-6, 1e-5, opts)
            got, want = (
                levenberg_marquardt(*lm),
                _numpy(monkeypatch, levenberg_marquardt, robot.chain, qf, *lm[2:]),
            )
            np.testing.assert_array_equal(got[1], want[1], err_msg=layout)
            seg = (robot, lev, q, qf + 0.05, pos, rot, np.full((n, 3), 0.01), 0.12, 1e-3, np.inf)
            np.testing.assert_allclose(
                segment_bounds(*seg),
                _numpy(monkeypatch, segment_bounds, robot, lev, qf, *seg[3:]),
                rtol=1e-9,
                atol=1e-12,
                err_msg=layout,
            )
        for layout, r in _layouts(rot).items():  # targets too
            got = levenberg_marquardt(robot.chain, q0, r, _layouts(pos)[layout], robot.lower,
                                      robot.upper, 1e-6, 1e-5, opts)  # fmt: skip
            assert got[0].shape == q0.shape and got[0].dtype == np.float64, layout
    solver = analytic_solver(robots["panda"])
    panda = robots["panda"]
    q0 = panda.random_configurations(n, 2)
    rot, pos = panda.chain.pose(q0)
    for layout, q7 in {**_layouts(q0[:, 6:7]), "int": np.zeros((n, 2), int)}.items():
        args = (rot, pos, q7, list(panda.lower), tuple(panda.upper))
        got = solver.solve(*args)
        want = _numpy(monkeypatch, solver.solve, rot, pos, np.asarray(q7, float), *args[3:])
        np.testing.assert_array_equal(got[0], want[0], err_msg=layout)
        np.testing.assert_allclose(got[1], want[1], rtol=0, atol=1e-6, err_msg=layout)
    assert solver.solve(rot, pos, np.zeros((n, 0)), panda.lower, panda.upper)[1].shape == (0, 7)
    # every call above went to a kernel (n = 0: those that do not return early)
    assert {"chain_forward", "levenberg_marquardt", "panda_ik"} <= set(calls)
    assert ("segment_samples" in calls) == (n > 0)


def test_a_kernel_converts_safely_or_says_why(compiled, panda):
    """Empty arrays of any dtype and safe casts convert; lossy casts and wrong
    dimensions are a caller's mistake, named, not Numba's 'No matching definition'."""
    q_index, placement, tool = panda.chain.packed
    rot, pos, jac = compiled.chain_forward(
        np.zeros((0, 7), np.int32), q_index, placement, tool, 7, True
    )
    assert rot.shape == (0, 3, 3) and jac.shape == (0, 6, 7)
    rot, _, _ = compiled.chain_forward(
        np.zeros((2, 7)), q_index.astype(np.int32), placement, tool, np.int16(7), 1
    )
    np.testing.assert_allclose(rot, panda.chain.pose(np.zeros((2, 7)))[0], atol=1e-12)
    unaligned = np.frombuffer(bytes(1 + 2 * 7 * 8), np.float64, 14, 1).reshape(2, 7)
    assert not unaligned.flags.aligned
    rot, _, _ = compiled.chain_forward(unaligned, q_index, placement, tool, 7, True)
    np.testing.assert_allclose(rot, panda.chain.pose(np.zeros((2, 7)))[0], atol=1e-12)
    with pytest.raises(TypeError, match="chain_forward: argument 1 of dtype float64"):
        compiled.chain_forward(np.zeros((2, 7)), q_index + 0.5, placement, tool, 7, True)
    with pytest.raises(TypeError, match="chain_forward: argument 0 has 1 dimensions, not 2"):
        compiled.chain_forward(np.zeros(7), q_index, placement, tool, 7, True)
    with pytest.raises(TypeError):  # a float for an integer: not truncated
        compiled.chain_forward(np.zeros((2, 7)), q_index, placement, tool, 7.5, True)
    # no pair, no world shape: nothing open (the broad phase of an empty screen)
    empty_i, empty_f = np.zeros(0, int), np.zeros(0)
    out = compiled.broad_phase(
        np.zeros((3, 4, 3, 4)), empty_i, np.zeros((0, 3)), empty_i, np.zeros((0, 3)),
        empty_f, empty_f, empty_f, empty_f, empty_f, empty_f, empty_f, empty_f, empty_f,
        np.zeros((0, 21)),
    )  # fmt: skip
    assert out.shape == (0, 4)


@pytest.mark.parametrize("robot_name", ["panda", "ur5"])
def test_a_world_without_collision_pairs_is_checked(monkeypatch, compiled, robot_name):
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
