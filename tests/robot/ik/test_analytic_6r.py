"""Closed-form branches of 6R arms (EAIK): who gets them, exactness, completeness, 2 pi copies."""

from __future__ import annotations

import numpy as np
import pytest
from helpers import CONFIGS, in_threads, tilted_elbow_chain
from poses import pin_poses

from gcm_pipeline.config.robot_spec import load_robot
from gcm_pipeline.robot.ik import analytic_6r, solve_ik
from gcm_pipeline.robot.ik.analytic_6r import (
    SixRAnalyticIK,
    branch_gap,
    nearest_copy,
    repeated_branches,
    same_as_earlier,
    six_r_solver,
    wide_joints,
)
from gcm_pipeline.robot.ik.lm import PinocchioIKOptions
from gcm_pipeline.robot.model import Robot

UR10_SPEC = CONFIGS / "robots" / "ur10.yaml"


@pytest.fixture(scope="module", params=["ur5", "ur10"])
def arm(request: pytest.FixtureRequest) -> Robot:
    return load_robot("ur5" if request.param == "ur5" else UR10_SPEC)


def test_which_arms_get_closed_form_branches(panda) -> None:
    assert six_r_solver(panda) is None  # 7 joints: its own closed form
    ur5 = load_robot("ur5")
    assert isinstance(six_r_solver(ur5), SixRAnalyticIK)
    assert isinstance(six_r_solver(load_robot(UR10_SPEC)), SixRAnalyticIK)
    # a UR5 whose elbow axis is tilted by 0.05 rad (no longer parallel to the shoulder's
    # and wrist 1's) has no decomposition EAIK knows: the iterative solver keeps it
    assert SixRAnalyticIK.for_chain(tilted_elbow_chain(ur5)) is None


def test_every_branch_is_exact_distinct_inside_the_limits_and_the_original_is_one(
    arm: Robot,
) -> None:
    solver = six_r_solver(arm)
    assert solver is not None
    q = arm.random_configurations(500, np.random.default_rng(7))
    poses = pin_poses(arm, q)
    idx, cq = solver.solve(poses[:, :3, :3], poses[:, :3, 3], arm.lower, arm.upper, arm.home)
    assert idx.size >= 500
    reached = pin_poses(arm, cq)
    assert np.max(np.linalg.norm(reached[:, :3, 3] - poses[idx, :3, 3], axis=1)) < 1e-9
    assert np.max(np.abs(reached[:, :3, :3] - poses[idx, :3, :3])) < 1e-9
    assert np.all(arm.within_limits(cq, strict=False))
    wide = wide_joints(arm.lower, arm.upper)
    assert wide.sum() == 5  # +-2 pi everywhere but the elbow
    # the configuration that made the pose is one of its branches (modulo 2 pi)
    hit = np.all(branch_gap(cq, q[idx], wide) < 1e-7, axis=1)
    assert np.array_equal(np.unique(idx[hit]), np.arange(500))
    # no branch twice: two answers of one pose differ modulo 2 pi
    for i in range(500):
        b = cq[idx == i]
        gap = np.max(branch_gap(b[:, None], b[None], wide), axis=2)
        assert np.all(gap[~np.eye(len(b), dtype=bool)] > 1e-6)


def test_each_branch_comes_at_its_copy_nearest_the_reference(arm: Robot) -> None:
    solver = six_r_solver(arm)
    assert solver is not None
    q = np.array([[-0.3, -1.2, 1.4, -1.9, -1.6, -0.2]])
    pose = pin_poses(arm, q)
    # near home: the copy in (-pi, pi]; near q + 2 pi on the wide joints: that copy
    shifted = q + np.where(wide_joints(arm.lower, arm.upper), 2 * np.pi, 0.0)
    for ref in (q[0], shifted[0]):
        _, cq = solver.solve(pose[:, :3, :3], pose[:, :3, 3], arm.lower, arm.upper, ref)
        nearest = cq[np.argmin(np.sum((cq - ref) ** 2, axis=1))]
        np.testing.assert_allclose(nearest, ref, atol=1e-7)


def test_nearest_copy_keeps_the_limits() -> None:
    lower, upper = np.array([-6.0, -1.0]), np.array([6.0, 1.0])
    q = np.array([[3.0, 0.5], [-3.0, 0.9], [0.0, 3.0]])
    ref = np.array([[-3.0, 0.0], [5.9, 0.0], [0.0, 0.0]])
    out = nearest_copy(q, ref, lower, upper)
    np.testing.assert_allclose(out[0], [3.0 - 2 * np.pi, 0.5])
    np.testing.assert_allclose(out[1], [-3.0 + 2 * np.pi, 0.9])
    assert np.isnan(out[2, 1]) and out[2, 0] == 0.0  # 3 rad has no copy in [-1, 1]


def test_solve_ik_takes_the_branch_nearest_the_seed(arm: Robot) -> None:
    q = arm.random_configurations(200, np.random.default_rng(3))
    q = np.clip(q, arm.lower + 0.1, arm.upper - 0.1)
    poses = pin_poses(arm, q)
    res = solve_ik(arm, poses, seeds=q[:, None, :] + 0.01)
    assert res.success.all()
    np.testing.assert_allclose(res.q, q, atol=1e-6)  # the seed's own branch and copy
    # several answers: distinct branches modulo 2 pi
    res = solve_ik(arm, poses[:20], return_all=True, min_solutions=8)
    cand = res.candidates
    assert cand is not None
    wide = wide_joints(arm.lower, arm.upper)
    for i in range(20):
        b = cand.q[cand.index == i]
        assert len(b) >= 2
        gap = np.max(branch_gap(b[:, None], b[None], wide), axis=2)
        assert np.all(gap[~np.eye(len(b), dtype=bool)] > 1e-6)


def test_solve_ik_takes_the_nearest_branch_the_validator_accepts(arm: Robot) -> None:
    """Branches are offered nearest home first; one the validator rejects is passed over.

    The validator rejects about a third of all configurations: each answer of
    an unseeded target is the nearest valid branch (squared joint distance to
    home, clipped to the limits), in the batches of ranks 0, 1, 2-3, ...
    (where no branch is valid, only the iterative rounds may still find a
    valid answer).
    """
    eps = PinocchioIKOptions.limit_epsilon
    lower, upper = arm.lower + eps, arm.upper - eps
    rng = np.random.default_rng(21)
    q = np.clip(arm.random_configurations(300, rng), lower, upper)
    poses = pin_poses(arm, q)
    home = np.clip(arm.home, lower, upper)

    def validator(c: np.ndarray) -> np.ndarray:
        bucket = np.floor(np.abs(np.sin(c @ np.arange(1.0, 7.0) * 37.0)) * 3)
        return np.where(bucket == 0, "collision_self", "")

    res = solve_ik(arm, poses, validator=validator)
    solver = six_r_solver(arm)
    assert solver is not None
    idx, cq = solver.solve(poses[:, :3, :3], poses[:, :3, 3], lower, upper, home)
    valid = validator(cq) == ""
    passed_over = 0
    for i in range(len(q)):
        mine = np.flatnonzero(idx == i)
        order = mine[np.argsort(np.sum((cq[mine] - home) ** 2, axis=1), kind="stable")]
        ok = order[valid[order]]
        passed_over += int(ok.size > 0 and ok[0] != order[0])
        if ok.size:
            assert res.success[i]
            np.testing.assert_array_equal(res.q[i], cq[ok[0]])
        elif res.success[i]:
            assert validator(res.q[i : i + 1])[0] == ""
    assert passed_over > 50  # the nearest branch was rejected often enough to test it


@pytest.mark.parametrize("analytic", [True, False])
def test_alternatives_are_other_arm_shapes_not_whole_turns(arm: Robot, analytic: bool) -> None:
    """Step 3's alternatives differ from the rejected solution and from each other modulo
    2 pi (a whole turn of a wrist is the same arm in the same collision); with closed-form
    branches they are every other branch."""
    from gcm_pipeline.reach.engine import ReachabilityEngine

    q = arm.random_configurations(40, np.random.default_rng(5))
    q = np.clip(q, arm.lower + 0.1, arm.upper - 0.1)
    poses = pin_poses(arm, q)
    engine = ReachabilityEngine(arm, alternatives=4, ik_options={"analytic": analytic})
    # the rejected solution, given at a copy a turn away where the limits allow it
    wide = wide_joints(arm.lower, arm.upper)
    turned = np.where(wide & (q < 0), q + 2 * np.pi, q)
    idx, rank, alt, err = engine._alternatives(poses, turned)
    assert idx.size and np.all(err[:, 0] <= 1e-4) and np.all(err[:, 1] <= 1e-3)
    assert np.all(np.max(branch_gap(alt, q[idx], wide), axis=1) >= 1e-3)
    for i in np.unique(idx):
        b = alt[idx == i]
        gap = np.max(branch_gap(b[:, None], b[None], wide), axis=2)
        assert np.all(gap[~np.eye(len(b), dtype=bool)] >= 1e-3)
    if analytic:
        solver = six_r_solver(arm)
        assert solver is not None
        every, _ = solver.solve(poses[:, :3, :3], poses[:, :3, 3], arm.lower, arm.upper, arm.home)
        # every branch but the rejected one (the limits are not binding here)
        np.testing.assert_array_equal(np.bincount(idx, minlength=40) + 1, np.bincount(every))
        assert rank.max() >= 4  # more than `alternatives`: all of them


@pytest.mark.parametrize(
    "wide", [np.zeros(7, bool), np.array([1, 0, 1, 0, 0, 1, 1], bool), np.ones(6, bool)]
)
def test_branch_gap_wraps_only_the_wide_joints(wide: np.ndarray) -> None:
    """A whole turn is no gap on a joint of range over 2 pi, a gap of 2 pi on any other."""
    rng = np.random.default_rng(3)
    nq = wide.size
    a = rng.uniform(-3.0, 3.0, (50, 1, nq))
    turns = rng.integers(-2, 3, (1, 4, nq)).astype(float)
    b = a + 2.0 * np.pi * turns + rng.uniform(-0.1, 0.1, (1, 4, nq))  # broadcast (50, 4, nq)
    gap = branch_gap(a, b, wide)
    assert gap.shape == (50, 4, nq)
    plain = np.abs(a - b)
    assert np.array_equal(gap[..., ~wide], np.broadcast_to(plain, gap.shape)[..., ~wide])
    assert np.all(gap[..., wide] <= 0.1 + 1e-12)  # the turns removed, the small part kept
    assert np.all(gap >= 0.0)
    assert np.isnan(branch_gap(np.full(nq, np.nan), np.zeros(nq), wide)).all()


WIDE = np.array([1, 0, 1, 0, 0, 1], bool)


def _by_branch_gap(j: int, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    return branch_gap(x[:, None], y[:, None], WIDE[j : j + 1])[:, 0] < 1e-3


@pytest.mark.parametrize("how", ["repeated_branches", "branch_gap"])
def test_same_as_earlier_finds_the_rows_close_to_an_earlier_row_of_their_group(how: str) -> None:
    """Against every pair written out: a repeat is close to an earlier row in all joints.

    Groups of up to 17 rows, joints drawn from five values (so pairs share
    joints, as a UR's branches share the shoulder's), with planted copies a
    hair inside and outside the tolerance, some across the wrap at +-pi (EAIK's
    repeated answers, 1e-6 modulo 2 pi; the alternatives' ``branch_gap`` below
    1e-3, modulo 2 pi on the wide joints only).
    """
    tol = 1e-6 if how == "repeated_branches" else 1e-3
    rng = np.random.default_rng(11)
    values = np.array([-np.pi, -1.0, 0.0, 1.0, np.nextafter(np.pi, 0.0)])
    repeats = 0
    for trial in range(400):
        n = int(rng.integers(0, 30))
        idx = np.repeat(np.arange(n), rng.integers(0, 18, n))
        m = idx.size
        if trial % 2:
            q = rng.choice(values, size=(m, 6))
        else:
            q = rng.uniform(-np.pi, np.pi, (m, 6))
        for i in rng.integers(0, max(m, 1), m // 2 if m else 0):
            j = int(rng.choice(np.flatnonzero(idx == idx[i])))
            hair = rng.choice([0.0, 0.5, 0.99, 1.01, 3.0], 6) * tol * rng.choice([-1, 1], 6)
            q[j] = np.remainder(q[i] + hair + np.pi, 2.0 * np.pi) - np.pi
        expected = np.zeros(m, dtype=bool)
        for b in range(m):
            for a in range(b):
                if idx[a] == idx[b]:
                    d = np.abs(q[a] - q[b])
                    wrap = np.ones(6, bool) if how == "repeated_branches" else WIDE
                    d[wrap] = np.minimum(d[wrap], 2.0 * np.pi - d[wrap])
                    expected[b] |= bool(np.all(d < tol))
        if how == "repeated_branches":
            got = repeated_branches(idx, q)
        else:
            got = same_as_earlier(idx, q, _by_branch_gap)
        assert np.array_equal(got, expected), trial
        repeats += int(expected.sum())
    assert repeats > 300  # the planted copies are there to be found


def test_poses_solved_again_get_eaiks_answers_to_the_bit(
    arm: Robot, monkeypatch: pytest.MonkeyPatch
) -> None:
    # a solver keeps the answers of the poses it solved last: a pose solved again (in
    # any order, mixed with new ones, twice in one call) gets them, as a fresh solver
    # would give them; only the last ``_RECENT_POSES`` are kept
    monkeypatch.setattr(analytic_6r, "_RECENT_POSES", 150)
    q = arm.random_configurations(400, np.random.default_rng(11))
    poses = pin_poses(arm, q)
    rot, pos = poses[:, :3, :3], poses[:, :3, 3]
    solver = SixRAnalyticIK.for_chain(arm.chain)
    assert solver is not None
    solver.raw(rot[:200], pos[:200])
    assert len(solver._recent.slot_of) == 150  # the oldest 50 dropped
    again = np.random.default_rng(3).permutation(np.r_[np.arange(20, 260), np.arange(100, 130)])
    for take in (again, np.arange(400)[::-1]):
        fresh = SixRAnalyticIK.for_chain(arm.chain)
        assert fresh is not None
        for want, got in zip(
            fresh._answers(rot[take], pos[take]), solver._answers(rot[take], pos[take]), strict=True
        ):
            assert want.dtype == got.dtype
            assert np.array_equal(want, got)
        assert len(solver._recent.slot_of) <= 150
    idx, cq = solver.solve(rot, pos, arm.lower, arm.upper, arm.home)
    fresh = SixRAnalyticIK.for_chain(arm.chain)
    assert fresh is not None
    want_idx, want_q = fresh.solve(rot, pos, arm.lower, arm.upper, arm.home)
    assert np.array_equal(idx, want_idx)
    assert np.array_equal(cq, want_q)


def test_the_ring_of_recent_answers_grows_wraps_and_never_maps_a_pose_to_another() -> None:
    # synthetic answers: pose p has p % 4 + (p > 20) * 5 answers, angle rows p + rank / 10
    ring = analytic_6r._RecentAnswers(8)
    stored: dict[bytes, int] = {}

    def keep(poses: list[int]) -> None:
        counts = np.array([p % 4 + (p > 20) * 5 for p in poses], dtype=np.intp)
        q = np.concatenate(
            [
                np.full((c, 6), p + np.arange(c)[:, None] / 10)
                for p, c in zip(poses, counts, strict=True)
            ]
        )
        exact = np.concatenate([np.arange(c) % 2 == 0 for c in counts])
        ring.keep([bytes([p]) * 8 for p in poses], counts, q, exact)
        stored.update({bytes([p]) * 8: p for p in poses})

    keep([1, 2, 3])
    keep([4, 5, 2, 2])  # a pose twice in one call, and one kept before
    keep(list(range(21, 31)))  # more than the ring holds, and more answers per pose (grows)
    keep([6, 7])
    for key, slot in ring.slot_of.items():
        p = stored[key]
        c = p % 4 + (p > 20) * 5
        assert ring.count[slot] == c
        q, exact = ring.answers(np.full(c, slot), np.arange(c))
        assert np.array_equal(q, np.full((c, 6), p + np.arange(c)[:, None] / 10))
        assert np.array_equal(exact, np.arange(c) % 2 == 0)
    # the last 8 poses kept are found; nothing older
    assert sorted(stored[k] for k in ring.slot_of) == [6, 7, 25, 26, 27, 28, 29, 30]
    assert np.array_equal(
        ring.find([bytes([p]) * 8 for p in (1, 30, 6)]),
        [-1, ring.slot_of[bytes([30]) * 8], ring.slot_of[bytes([6]) * 8]],
    )


def test_forget_answers_makes_the_robots_solver_solve_again(arm: Robot) -> None:
    """A benchmark's repeat times solving, not the kept answers; the answers stay the same."""
    q = arm.random_configurations(50, np.random.default_rng(5))
    poses = pin_poses(arm, q)
    solver = analytic_6r.six_r_solver(arm)
    assert solver is not None
    first = solver._answers(poses[:, :3, :3], poses[:, :3, 3])
    assert len(solver._recent.slot_of) >= 50
    analytic_6r.forget_answers(arm)
    assert len(solver._recent.slot_of) == 0
    again = solver._answers(poses[:, :3, :3], poses[:, :3, 3])
    for want, got in zip(first, again, strict=True):
        assert np.array_equal(want, got)
    analytic_6r.forget_answers(arm)  # a robot whose solver holds nothing: no error


def test_threads_sharing_a_solver_get_each_poses_own_answers(
    arm: Robot, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Python API users may solve from several threads with one robot: the kept
    answers (a small ring here, overwritten all the time) never give one pose's
    answers to another."""
    monkeypatch.setattr(analytic_6r, "_RECENT_POSES", 64)
    q = arm.random_configurations(600, np.random.default_rng(17))
    poses = pin_poses(arm, q)
    rot, pos = poses[:, :3, :3], poses[:, :3, 3]
    fresh = SixRAnalyticIK.for_chain(arm.chain)
    assert fresh is not None
    want = [fresh.raw(rot[i : i + 1], pos[i : i + 1]) for i in range(len(rot))]
    shared = SixRAnalyticIK.for_chain(arm.chain)
    assert shared is not None
    wrong: list[int] = []

    def work(seed: int) -> None:
        rng = np.random.default_rng(seed)
        for _ in range(60):
            take = rng.choice(len(rot), size=int(rng.integers(1, 40)), replace=True)
            idx, got = shared.raw(rot[take], pos[take])
            for k, t in enumerate(take.tolist()):
                if not np.array_equal(got[idx == k], want[t][1]):
                    wrong.append(t)

    in_threads(work, 4)
    assert wrong == []
