"""Closed-form Panda IK: exactness, completeness on random poses, who gets it, selection."""

from __future__ import annotations

import numpy as np
import pinocchio as pin
import pytest
from poses import backward_poses

from gcm_pipeline.config.robot_spec import load_robot
from gcm_pipeline.errors import InputError
from gcm_pipeline.reach.waypoints import end_of_move
from gcm_pipeline.robot.chain import KinematicChain
from gcm_pipeline.robot.ik import PinocchioIKOptions, solve_ik, verify_solutions
from gcm_pipeline.robot.ik import panda as panda_ik
from gcm_pipeline.robot.ik.panda import PandaAnalyticIK, analytic_solver
from gcm_pipeline.robot.model import Robot

TOL_P, TOL_R = 1e-4, 1e-3


def _pin_pose(robot: Robot, q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Grasp-frame rotations and positions by Pinocchio itself (no project code)."""
    data = robot.model.createData()
    rot, pos = np.empty((len(q), 3, 3)), np.empty((len(q), 3))
    for i, qi in enumerate(q):
        pin.forwardKinematics(robot.model, data, qi)
        pin.updateFramePlacements(robot.model, data)
        m = data.oMf[robot.grasp_frame_id]
        rot[i], pos[i] = m.rotation, m.translation
    return rot, pos


def test_only_panda_kinematics_get_the_closed_form(panda: Robot) -> None:
    assert isinstance(analytic_solver(panda), PandaAnalyticIK)
    assert analytic_solver(load_robot("ur5")) is None
    # a Panda whose forearm is 1 cm longer is not a Panda: the check at load says so
    model = panda.model.copy()
    j5 = model.getJointId("panda_joint5")
    placement = model.jointPlacements[j5].copy()
    placement.translation = placement.translation + np.array([0.0, 0.01, 0.0])
    model.jointPlacements[j5] = placement
    assert PandaAnalyticIK.for_chain(KinematicChain(model, panda.grasp_frame_id)) is None


def test_every_solution_is_exact_inside_the_limits_and_the_original_is_among_them(
    panda: Robot,
) -> None:
    """At the joint 7 of a random configuration, the closed form returns that very
    configuration among its solutions, and every solution reaches the pose (Pinocchio's
    own FK) inside the limits."""
    solver = analytic_solver(panda)
    assert solver is not None
    q = panda.random_configurations(3000, np.random.default_rng(11))
    rot, pos = _pin_pose(panda, q)
    at, sol, branch, column = solver.solve(rot, pos, q[:, 6:7], panda.lower, panda.upper)
    assert np.all(column == 0)
    assert len(at) >= len(q)
    assert np.all(np.diff(at) >= 0)  # grouped by target
    assert np.all((branch >= 0) & (branch < 8))
    # at most one solution per branch for one value of joint 7
    assert len(np.unique(at * 8 + branch)) == len(at)
    assert np.all((sol >= panda.lower) & (sol <= panda.upper))
    np.testing.assert_array_equal(sol[:, 6], q[at, 6])
    r2, p2 = _pin_pose(panda, sol)
    assert np.max(np.linalg.norm(p2 - pos[at], axis=1)) < 1e-9
    assert np.max(np.abs(r2 - rot[at])) < 1e-9
    found = np.zeros(len(q), dtype=bool)
    found[at[np.max(np.abs(sol - q[at]), axis=1) < 1e-7]] = True
    assert found.all()


@pytest.mark.parametrize("reach", [0.05, 0.3, 1.0])
def test_near_keeps_exactly_the_solutions_within_reach_of_the_reference(
    panda: Robot, reach: float
) -> None:
    """Pruning by a reference configuration returns exactly the full solution set's
    members within ``reach`` in every joint, in the same order (the approach's end
    of move relies on it to pick the same end)."""
    solver = analytic_solver(panda)
    assert solver is not None
    rng = np.random.default_rng(12)
    q = panda.random_configurations(800, rng)
    rot, pos = _pin_pose(panda, q)
    ref = np.clip(q + rng.normal(0.0, reach / 3, q.shape), panda.lower, panda.upper)
    q7 = np.clip(ref[:, 6:7] + np.linspace(-0.2, 0.2, 5), panda.lower[6], panda.upper[6])
    full = solver.solve(rot, pos, q7, panda.lower, panda.upper)
    near = solver.solve(rot, pos, q7, panda.lower, panda.upper, (ref, reach))
    inside = np.all(np.abs(full[1] - ref[full[0]]) <= reach, axis=1)
    assert 0 < inside.sum() < inside.size
    for a, b in zip(full, near, strict=True):
        np.testing.assert_array_equal(a[inside], b)


def test_out_of_reach_and_backward_poses_have_no_solution(panda: Robot) -> None:
    solver = analytic_solver(panda)
    assert solver is not None
    n = 300
    poses = backward_poses(panda, n, np.random.default_rng(3), 0.85)
    rot = poses[:, :3, :3]  # the hand points back at the shoulder
    near = poses[:, :3, 3]
    far = panda.shoulder - 1.2 * poses[:, :3, 2]
    grid = np.broadcast_to(np.linspace(panda.lower[6], panda.upper[6], 512), (n, 512))
    for pos in (near, far):
        at, _, _, _ = solver.solve(rot, pos, grid, panda.lower, panda.upper)
        assert at.size == 0


def test_solve_ik_reaches_every_random_pose_and_each_answer_verifies(panda: Robot) -> None:
    """Recall on poses of random configurations: every one, where the LM alone misses
    some (joint limits, narrow windows); each answer re-checked by Pinocchio FK."""
    q = panda.random_configurations(4000, np.random.default_rng(5))
    targets = panda.fk_pinocchio(q)
    res = solve_ik(panda, targets)
    assert res.success.all()
    rot, pos = _pin_pose(panda, res.q)
    assert np.max(np.linalg.norm(pos - targets[:, :3, 3], axis=1)) <= TOL_P
    ang = np.array(
        [np.linalg.norm(pin.log3(t[:3, :3].T @ r)) for t, r in zip(targets, rot, strict=True)]
    )
    assert ang.max() <= TOL_R
    assert np.all((res.q > panda.lower) & (res.q < panda.upper))
    lm = solve_ik(panda, targets, analytic=False)
    assert lm.success.sum() < len(q)


def test_a_seed_picks_the_nearest_solution(panda: Robot) -> None:
    """With a seed, the answer is the solution nearest to it: a pose a small move from the
    seed's gives a configuration a small move from the seed (continuity on a manifold)."""
    rng = np.random.default_rng(8)
    q0 = panda.random_configurations(500, rng)
    q0 = np.clip(q0, panda.lower + 0.1, panda.upper - 0.1)
    moved = q0 + rng.normal(0.0, 0.01, q0.shape)
    targets = panda.fk_pinocchio(moved)
    res = solve_ik(panda, targets, seeds=q0[:, None, :])
    assert res.success.all()
    assert np.max(np.abs(res.q - q0)) < 0.2
    # without a seed the answer is nearest to home: another branch for many
    far = solve_ik(panda, targets)
    assert np.mean(np.max(np.abs(far.q - q0), axis=1) > 0.5) > 0.3


def test_several_solutions_come_from_different_branches(panda: Robot) -> None:
    q = panda.random_configurations(200, np.random.default_rng(2))
    targets = panda.fk_pinocchio(q)
    res = solve_ik(panda, targets, return_all=True, min_solutions=4)
    cand = res.candidates
    assert cand is not None
    solver = analytic_solver(panda)
    assert solver is not None
    for t in range(0, 200, 20):
        rows = cand.q[cand.index == t]
        assert 1 <= len(rows) <= 4
        # distinct configurations (the closed form's values of joint 7 around a preferred
        # one may be clipped together at a limit: the engine's kept solutions apply their
        # own 0.2 rad distinctness, tested in test_branches.py)
        gaps = np.max(np.abs(rows[:, None] - rows[None]), axis=2)
        assert np.all(gaps[~np.eye(len(rows), dtype=bool)] > 1e-3)
        # and more than one branch of the closed form among them where several exist
        if len(rows) > 1:
            assert gaps.max() > 0.5


def test_analytic_off_is_the_lm(panda: Robot) -> None:
    q = panda.random_configurations(50, np.random.default_rng(4))
    targets = panda.fk_pinocchio(q)
    a = solve_ik(panda, targets, analytic=False)
    b = solve_ik(panda, targets, analytic=False)
    np.testing.assert_array_equal(a.q, b.q)
    with pytest.raises(Exception, match="analytic_samplez"):
        PinocchioIKOptions.from_kwargs({"analytic_samplez": 3})


def test_end_of_move_is_near_the_start_and_at_least_as_good_as_the_lm(panda: Robot) -> None:
    """The approach's end of move: reached ends verify, stay near the start, and every
    end the LM alone reaches from the start is reached (the closed form is a fast path)."""
    rng = np.random.default_rng(6)
    q = panda.random_configurations(600, rng)  # near the limits too
    grasp = panda.fk_pinocchio(q)
    ends = grasp.copy()
    ends[:, :3, 3] -= 0.1 * grasp[:, :3, 2]  # 10 cm back along the approach axis
    opts = {"library_seeds": 0, "random_restarts": 0, "home_seed": False}
    qe, reached = end_of_move(panda, ends, q, "pinocchio", TOL_P, TOL_R, opts)
    q_lm, reached_lm = end_of_move(
        panda, ends, q, "pinocchio", TOL_P, TOL_R, {**opts, "analytic": False}
    )
    assert reached.sum() > 300
    assert np.all(reached[reached_lm])
    _, pos = _pin_pose(panda, qe[reached])
    assert np.max(np.linalg.norm(pos - ends[reached, :3, 3], axis=1)) <= TOL_P
    assert np.all((qe[reached] > panda.lower) & (qe[reached] < panda.upper))
    change = np.max(np.abs(qe - q), axis=1)
    change_lm = np.max(np.abs(q_lm - q), axis=1)
    both = reached & reached_lm
    # the closed form's end is no farther than the LM's, up to the 0.3 rad it accepts
    assert np.all(change[both] <= np.maximum(change_lm[both], 0.3) + 1e-9)


def test_a_validator_sees_candidates_in_batches_not_all_of_them(panda: Robot) -> None:
    """A validator that rejects everything is asked about each closed-form candidate
    at most once, in doubling batches of preference: the LM alone asks about 9 per
    target; the closed form stays within a small multiple of that per grid round."""
    q = panda.random_configurations(60, np.random.default_rng(9))
    targets = panda.fk_pinocchio(q)
    seen: list[int] = []

    def reject(qs: np.ndarray) -> np.ndarray:
        seen.append(len(qs))
        return np.full(len(qs), "collision_self", dtype=object)

    res = solve_ik(panda, targets, validator=reject)
    assert not res.success.any()
    assert set(res.reason) == {"collision_self"}
    assert sum(seen) < 700 * len(q)  # every candidate of every round once at most
    half: list[int] = []

    def reject_half(qs: np.ndarray) -> np.ndarray:
        half.append(len(qs))
        return np.where(np.arange(len(qs)) % 2, "collision_self", "").astype(object)

    res = solve_ik(panda, targets, validator=reject_half)
    assert res.success.all()
    assert sum(half) <= 4 * len(q)  # the first batches settle them


def test_bad_closed_form_options_are_one_line_errors(panda: Robot) -> None:
    t = panda.fk_pinocchio(panda.random_configurations(2, np.random.default_rng(1)))
    for key, value in [
        ("analytic_samples", -1),
        ("analytic_samples", 2.5),
        ("analytic_samples", True),
        ("fallback_library_seeds", -3),
        ("analytic", "yes"),
        # the LM's numbers (the compiled iteration takes exactly these types)
        ("stall_after", 1),
        ("max_iterations", 1.5),
        ("min_damping", 1e-13),
        ("damping", float("nan")),
        ("stall_ratio", "half"),
    ]:
        with pytest.raises(InputError, match=key) as info:
            solve_ik(panda, t, **{key: value})
        assert "\n" not in str(info.value)


def test_joint7_outside_its_limits_gives_nothing_and_blocks_change_nothing(
    panda: Robot, monkeypatch: pytest.MonkeyPatch
) -> None:
    solver = analytic_solver(panda)
    assert solver is not None
    q = panda.random_configurations(50, np.random.default_rng(12))
    rot, pos = _pin_pose(panda, q)
    outside = np.full((50, 1), panda.upper[6] + 0.1)
    at, _, _, _ = solver.solve(rot, pos, outside, panda.lower, panda.upper)
    assert at.size == 0
    targets = panda.fk_pinocchio(q)
    whole = solve_ik(panda, targets)
    monkeypatch.setattr(panda_ik, "_ANALYTIC_ROWS", 7)  # blocks of one target
    blocks = solve_ik(panda, targets)
    np.testing.assert_array_equal(whole.q, blocks.q)


def test_analytic_false_reaches_every_ik_of_the_engine(
    panda: Robot, monkeypatch: pytest.MonkeyPatch
) -> None:
    """``ik_options={"analytic": False}`` holds for the first solve, the other branches
    and the approach's end of move: the closed form is never called."""
    from gcm_pipeline.reach.engine import ReachabilityEngine
    from gcm_pipeline.reach.moves import Move

    def refuse(*args: object, **kwargs: object) -> None:
        raise AssertionError("closed form called")

    q = panda.random_configurations(40, np.random.default_rng(13))
    targets = panda.fk_pinocchio(q)
    monkeypatch.setattr(PandaAnalyticIK, "solve", refuse)
    eng = ReachabilityEngine(
        panda, ik_options={"analytic": False}, approach=Move(distance=0.05), solutions=2
    )
    with eng:
        res = eng.run(targets)
    assert res.reachable.sum() > 20


def test_reporting_flags_and_empty_seeds_do_not_change_the_answer(panda: Robot) -> None:
    """return_all, a validator that accepts everything, or an extra all-NaN seed column
    give the same answer as the plain call (they change what is reported, not chosen)."""
    rng = np.random.default_rng(21)
    q = panda.random_configurations(600, rng)
    targets = panda.fk_pinocchio(q)
    seeds = np.clip(q + rng.normal(0.0, 0.3, q.shape), panda.lower, panda.upper)[:, None, :]
    plain = solve_ik(panda, targets, seeds=seeds)

    def accept_all(qs: np.ndarray) -> np.ndarray:
        return np.full(len(qs), "", dtype=object)

    nan_col = np.concatenate([seeds, np.full_like(seeds, np.nan)], axis=1)
    for other in (
        solve_ik(panda, targets, seeds=seeds, return_all=True),
        solve_ik(panda, targets, seeds=seeds, validator=accept_all),
        solve_ik(panda, targets, seeds=nan_col),
    ):
        np.testing.assert_array_equal(other.success, plain.success)
        np.testing.assert_array_equal(other.q, plain.q)
    # several answers: the closed form's are the same (the LM's rounds, for what the
    # closed form leaves, depend on the seed columns, as without it)
    several = solve_ik(panda, targets, seeds=seeds, min_solutions=3, return_all=True)
    with_nan = solve_ik(panda, targets, seeds=nan_col, min_solutions=3, return_all=True)
    assert several.candidates is not None and with_nan.candidates is not None
    np.testing.assert_array_equal(several.candidates.q, with_nan.candidates.q)
    assert len(several.candidates.q) == 3 * len(q)
    with pytest.raises(InputError, match="min_solutions"):
        solve_ik(panda, targets[:2], min_solutions=0)


def test_reach_proof_never_rejects_a_pose_the_arm_reaches(panda: Robot) -> None:
    """Poses of random configurations, of configurations at the elbow's limits (the
    reach's extremes) and targets moved off them by up to the IK tolerances: none is
    counted unreachable."""
    solver = analytic_solver(panda)
    assert solver is not None
    rng = np.random.default_rng(21)
    q = panda.random_configurations(20000, rng)
    q[:4000, 3] = panda.lower[3]
    q[4000:8000, 3] = panda.upper[3]
    rot, pos = _pin_pose(panda, q)
    elbow = (panda.lower[3], panda.upper[3])
    assert not solver.unreachable(rot, pos, elbow_limits=elbow).any()
    assert not solver.unreachable(rot, pos).any()
    # any elbow angle, limits or not: the arm's reach itself
    q_any = q[:2000].copy()
    q_any[:, 3] = rng.uniform(-np.pi, np.pi, size=2000)
    assert not solver.unreachable(*_pin_pose(panda, q_any)).any()
    # targets off the reached pose by the tolerances: still not counted
    step = rng.normal(size=(len(q), 3))
    pos_off = pos + TOL_P * step / np.linalg.norm(step, axis=1, keepdims=True)
    axis = rng.normal(size=(len(q), 3))
    axis *= TOL_R / np.linalg.norm(axis, axis=1, keepdims=True)
    rot_off = np.array([r @ pin.exp3(a) for r, a in zip(rot, axis, strict=True)])
    for limits in (elbow, None):
        assert not solver.unreachable(rot_off, pos_off, TOL_P, TOL_R, limits).any()


def test_reach_proof_catches_far_and_folded_poses_that_no_seed_reaches(panda: Robot) -> None:
    solver = analytic_solver(panda)
    assert solver is not None
    rng = np.random.default_rng(22)
    q = panda.random_configurations(200, rng)
    rot, pos = _pin_pose(panda, q)
    shoulder = np.array([0.0, 0.0, 0.333])
    ray = pos - shoulder
    ray /= np.linalg.norm(ray, axis=1, keepdims=True)
    far = shoulder + 1.2 * ray  # beyond the stretched arm
    # frame 7 at the shoulder: the elbow cannot fold the wrist that close
    near = shoulder + (rot @ solver.tool_rotation.T) @ solver.tool_translation
    elbow = (panda.lower[3], panda.upper[3])
    for p, limits in ((far, None), (near, elbow)):
        assert solver.unreachable(rot, p, TOL_P, TOL_R, limits).all()
    # what the proof rejects, an exhaustive iterative search does not reach either
    targets = np.broadcast_to(np.eye(4), (40, 4, 4)).copy()
    targets[:, :3, :3] = rot[:40]
    targets[:20, :3, 3], targets[20:, :3, 3] = far[:20], near[20:40]
    res = solve_ik(panda, targets, analytic=False, library_seeds=32, random_restarts=16)
    assert not res.success.any()


def test_reach_proof_allows_for_rotations_orthonormal_only_to_1e6(panda: Robot) -> None:
    """check_targets accepts rotations with |R^T R - I| up to 1e-6: a configuration
    that reaches such a target within the tolerances is not ruled out by the proof,
    however small the orientation tolerance (a case found by review)."""
    solver = analytic_solver(panda)
    assert solver is not None
    q = np.array([1.6280484756265108, 1.0565746597690184, -0.1300437666720563,
                  -0.46700241680492438, -6.1123488380520348e-08, 1.8013213083624451,
                  -0.40036142126962676])  # fmt: skip
    target = np.array(
        [
            [-0.9300912460116731, 0.3503456618307057, 0.11040403064220272, 0.0048364334499967935],
            [0.36732738430370526, 0.8879106228985715, 0.27691993858825525, 0.8377622368507478],
            [-0.0010106411894930246, 0.29811628520272127, -0.9545289622651606, 0.3419384590035645],
            [0.0, 0.0, 0.0, 1.0],
        ]
    )
    tol_p, tol_r = 1e-4, 1e-8
    pe, re, inside = verify_solutions(panda, q[None], target[None])
    assert pe[0] <= tol_p and re[0] <= tol_r and inside[0]  # reached, as the IK counts it
    assert not solver.unreachable(target[None, :3, :3], target[None, :3, 3], tol_p, tol_r)[0]
    res = solve_ik(panda, target[None], position_tolerance=tol_p, orientation_tolerance=tol_r)
    assert res.reason[0] != "out_of_reach"
    with pytest.raises(ValueError, match="elbow_limits"):
        solver.unreachable(target[None, :3, :3], target[None, :3, 3], elbow_limits=(-1.0, -2.0))


def test_a_joint7_value_given_twice_is_solved_once_in_its_first_column(panda: Robot) -> None:
    """Repeats (offsets clipped to a limit) add no solution and keep the first column's."""
    solver = analytic_solver(panda)
    assert solver is not None
    q = panda.random_configurations(40, np.random.default_rng(21))
    rot, pos = _pin_pose(panda, q)
    distinct = np.stack([q[:, 6], q[:, 6] - 0.3, q[:, 6] + 0.2], axis=1)
    distinct = np.clip(distinct, panda.lower[6], panda.upper[6])
    with_repeats = distinct[:, [0, 1, 0, 2, 1, 1]]  # columns 2, 4, 5 repeat earlier ones
    at, cq, branch, column = panda_ik.analytic_blocks(
        solver, rot, pos, with_repeats, panda.lower, panda.upper
    )
    ref_at, ref_q, ref_branch, ref_column = panda_ik.analytic_blocks(
        solver, rot, pos, distinct, panda.lower, panda.upper
    )
    assert set(np.unique(column)) <= {0, 1, 3}  # the repeats' columns never appear
    np.testing.assert_array_equal(at, ref_at)
    np.testing.assert_array_equal(cq, ref_q)
    np.testing.assert_array_equal(branch, ref_branch)
    np.testing.assert_array_equal(column, np.array([0, 1, 3])[ref_column])
    key = np.column_stack([at, branch, cq[:, 6]])
    assert len(np.unique(key, axis=0)) == len(key)  # every solution once
