"""Several IK branches per grasp (ik.solutions, ik.select, solutions.npz)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from helpers import BOTTLE, assert_one_line_error

import gcm_pipeline as gcm
from gcm_pipeline.cli import main
from gcm_pipeline.manifold.continuity import patches
from gcm_pipeline.manifold.lattice import row_mesh
from gcm_pipeline.pipeline import branch_scores, make_checker
from gcm_pipeline.robot.ik.analytic_6r import six_r_solver
from gcm_pipeline.rundir.grasps_csv import read_grasps_csv

SMALL = ["candidates.count=45", "densify.subdivisions=3", "ik.solutions=4"]


@pytest.fixture(scope="module")
def runs(tmp_path_factory: pytest.TempPathFactory) -> dict[str, gcm.RunResult]:
    out = {}
    for select in ("metric", "continuity"):
        cfg = gcm.load_config(
            BOTTLE, [*SMALL, f"ik.select={select}", "publish.html=false", "publish.plots=false"]
        )
        path = tmp_path_factory.mktemp(select) / "run"
        out[select] = gcm.Pipeline(cfg).run(path, progress=False)
    return out


def test_every_kept_branch_is_verified_distinct_and_collision_free(runs: dict) -> None:
    run = runs["metric"]
    g, cfg = run.grasps, run.config
    sol = np.asarray(g["solutions"])
    count = np.asarray(g["n_solutions"])
    reach = np.asarray(g["reachable"])
    assert sol.shape[1:] == (4, run.robot.nq)
    assert np.all(count[~reach] == 0) and np.all((count[reach] >= 1) & (count[reach] <= 4))
    assert (count[reach] > 1).mean() > 0.5  # most grasps have several branches
    valid = np.arange(4)[None, :] < count[:, None]
    assert np.all(np.isfinite(sol[valid])) and np.all(np.isnan(sol[~valid]))
    rows, branch = np.nonzero(valid)
    base = cfg.robot.base_pose.matrix()
    target = np.linalg.inv(base) @ gcm.dq_to_matrix(np.asarray(g["dq"])[rows])
    reached = run.robot.fk_pinocchio(sol[rows, branch])
    assert np.abs(reached[:, :3, 3] - target[:, :3, 3]).max() < cfg.ik.position_tolerance
    assert run.robot.within_limits(sol[rows, branch]).all()
    checker = make_checker(run.robot, cfg.environment, cfg.object, base)
    assert np.all(checker.check(sol[rows, branch]) == "")
    # distinct: every pair of kept branches differs by more than 0.2 rad somewhere
    for r in np.flatnonzero(count > 1)[:200]:
        s = sol[r, : count[r]]
        d = np.abs(s[:, None] - s[None]).max(axis=2) + np.eye(len(s)) * 9
        assert d.min() > 0.2


def test_metric_selection_takes_the_best_branch(runs: dict) -> None:
    run = runs["metric"]
    g = run.grasps
    reach = np.asarray(g["reachable"])
    scores = branch_scores(g, run.robot, run.config)
    chosen = np.asarray(g["solution"])
    assert np.all(chosen[~reach] == -1)
    count = np.asarray(g["n_solutions"])
    valid = np.arange(4)[None, :] < count[:, None]
    best = np.where(valid, scores, -np.inf).max(axis=1)
    rows = np.flatnonzero(reach)
    assert np.allclose(scores[rows, chosen[rows]], best[rows])
    assert np.all(scores[rows, chosen[rows]] >= scores[rows, 0] - 1e-12)  # not the first found
    assert np.array_equal(np.asarray(g["q"])[rows], np.asarray(g["solutions"])[rows, chosen[rows]])


def test_continuity_selection_gives_fewer_patches(runs: dict) -> None:
    by_metric = runs["metric"].counts["continuity"]["patches"]
    by_continuity = runs["continuity"].counts["continuity"]["patches"]
    g = runs["continuity"].grasps
    mesh = runs["continuity"].manifold
    edges = row_mesh(g, mesh.triangles, mesh.n_vertices).edges
    first = patches(np.asarray(g["solutions"])[:, 0], g["reachable"], edges)
    assert by_continuity < by_metric
    assert by_continuity <= first.max() + 1  # never worse than the first branch found
    # the same reachability either way
    assert np.array_equal(runs["metric"].grasps["reachable"], g["reachable"])


def test_solutions_npz_in_csv_order(runs: dict) -> None:
    run = runs["continuity"]
    assert run.run_dir is not None
    with (
        np.load(run.run_dir / "solutions.npz") as s,
        np.load(run.run_dir / "configurations.npz") as c,
    ):
        assert set(s.files) == {"q", "q_pregrasp", "q_retreat", "clearance", "count", "chosen"}
        chosen = s["chosen"]
        rows = np.flatnonzero(chosen >= 0)
        assert np.array_equal(s["q"][rows, chosen[rows]], c["q"][rows])
    table = read_grasps_csv(run.run_dir / "grasps.csv")
    assert np.array_equal(table["solution"], chosen)


def test_a_6r_arm_keeps_every_passing_closed_form_branch(tmp_path: Path) -> None:
    # the branches step asked the closed form for the 2 (K - 1) branches nearest home
    # only: on the UR5's bottle with K = 2 and no approach, 269 of 344 reachable grasps
    # kept one branch while a second, farther one was in the limits and free
    k = 2
    over = ["robot.spec=ur5", "candidates.count=24", "densify.subdivisions=2", f"ik.solutions={k}"]
    over += ["approach=null", "publish.html=false", "publish.plots=false", "ik.workers=1"]
    cfg = gcm.load_config(BOTTLE, over)
    run = gcm.Pipeline(cfg).run(tmp_path / "run", progress=False)
    g, robot = run.grasps, run.robot
    base = cfg.robot.base_pose.matrix()
    target = np.linalg.inv(base) @ gcm.dq_to_matrix(np.asarray(g["dq"]))
    six = six_r_solver(robot)
    assert six is not None
    eps = 1e-9  # the closed form's branches strictly inside the limits, as the engine asks
    idx, cq = six.solve(
        target[:, :3, :3], target[:, :3, 3], robot.lower + eps, robot.upper - eps, robot.home
    )
    free = make_checker(robot, cfg.environment, cfg.object, base).check(cq) == ""
    n_free = np.bincount(idx[free], minlength=len(target))
    reach = np.asarray(g["reachable"])
    assert np.array_equal(reach, n_free > 0)
    kept = np.asarray(g["n_solutions"])
    assert (n_free[reach] >= k).sum() > 20
    assert np.array_equal(kept[reach], np.minimum(k, n_free[reach]))


@pytest.mark.parametrize("value", ["0", "17", "-1", "true", "2.5"])
def test_bad_solution_counts_are_one_line_errors(
    value: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "x"
    code = main(["run", str(BOTTLE), "--out", str(out), "--set", f"ik.solutions={value}"])
    assert_one_line_error(code, capsys.readouterr().err, "ik.solutions")
    assert not out.exists()
    with pytest.raises(gcm.ConfigError, match="ik.select"):
        gcm.load_config(BOTTLE, ["ik.select=best"])
