"""Other IK solutions of a grasp (reach.alternatives): the early stop keeps the answers.

The default backend hands its candidates to ``other_solutions`` as it finds
them and stops searching for a target once its first alternatives are known.
The answers must be exactly those of verifying every candidate of a full
search (``_verified_distinct``), as before the early stop.
"""

import numpy as np
import pytest

from gcm_pipeline.reach.alternatives import _verified_distinct, other_solutions
from gcm_pipeline.robot.ik import solve_ik

TOL_P, TOL_R = 1e-4, 1e-3


def _targets(robot, n, seed):
    """Poses of random configurations inside the limits, and those configurations."""
    rng = np.random.default_rng(seed)
    q = rng.uniform(robot.lower, robot.upper, size=(n, robot.nq))
    return robot.fk_pinocchio(q), q


def _full_search(robot, targets, q_first, k, separation, library, restarts, ik_options):
    """``other_solutions`` without the early stop: every candidate, then verified."""
    opts = {
        "min_solutions": 2 * (k + 1),
        "first_round_seeds": k + 1,
        "round_seeds": k + 1,
        "library_seeds": library,
        "random_restarts": restarts,
        **ik_options,
    }
    res = solve_ik(
        robot,
        targets,
        "pinocchio",
        position_tolerance=TOL_P,
        orientation_tolerance=TOL_R,
        return_all=True,
        **opts,
    )
    cand = res.candidates
    return _verified_distinct(
        robot, targets, q_first, cand.index, cand.q, k, separation, TOL_P, TOL_R
    )


def _both(robot, targets, q_first, k, separation, library, restarts, ik_options):
    """``other_solutions`` (with the early stop) and the full search, on the same inputs."""
    got = other_solutions(
        robot,
        targets,
        q_first,
        count=k,
        every_branch=False,
        backend="pinocchio",
        position_tolerance=TOL_P,
        orientation_tolerance=TOL_R,
        ik_options=ik_options,
        shared_options={"analytic": ik_options["analytic"]},
        separation=separation,
        library=library,
        restarts=restarts,
    )
    want = _full_search(robot, targets, q_first, k, separation, library, restarts, ik_options)
    return got, want


@pytest.mark.parametrize(
    ("k", "separation", "library", "restarts", "analytic", "n"),
    [
        (4, 1e-3, 8, 0, True, 120),  # the re-solve of step 3
        (4, 0.3, 16, 8, True, 60),  # the branches of step 4, a wide separation
        (1, 1e-3, 8, 0, True, 60),
        (2, 1e-3, 4, 2, False, 25),  # the LM alone
    ],
)
def test_early_stop_gives_the_full_searchs_answers(
    panda, k, separation, library, restarts, analytic, n
):
    targets, q_first = _targets(panda, n, seed=k + library)
    ik_options = {"random_seed": 0, "analytic": analytic}
    got, want = _both(panda, targets, q_first, k, separation, library, restarts, ik_options)
    assert len(got[0]) > 0
    for g, w in zip(got, want, strict=True):
        assert g.dtype == w.dtype
        np.testing.assert_array_equal(g, w)  # bit for bit: same rows, order, q, errors


def test_early_stop_on_an_arm_with_joints_wider_than_a_turn() -> None:
    # the UR5's LM alone (no closed form): five joints of +-2 pi, where q and q + 2 pi
    # are one arm shape; the first solutions given at the other 2 pi copy of half of
    # the poses' configurations, so their copies must be dropped as the full search does
    from gcm_pipeline.config.robot_spec import load_robot
    from gcm_pipeline.robot.ik.analytic_6r import wide_joints

    ur5 = load_robot("ur5")
    targets, q = _targets(ur5, 24, seed=8)
    shift = np.where(wide_joints(ur5.lower, ur5.upper), 2 * np.pi, 0.0)
    shifted = np.where(q + shift <= ur5.upper, q + shift, q - shift)
    q_first = np.where((np.arange(24) % 2 == 0)[:, None], shifted, q)
    ik_options = {"random_seed": 0, "analytic": False}
    k, separation, library, restarts = 3, 1e-3, 8, 4
    got, want = _both(ur5, targets, q_first, k, separation, library, restarts, ik_options)
    assert len(got[0]) > 24
    for g, w in zip(got, want, strict=True):
        assert g.dtype == w.dtype
        np.testing.assert_array_equal(g, w)
