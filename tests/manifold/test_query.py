"""The queryable manifold: sample, locate, nearest_reachable, best, gcm query."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from helpers import BOTTLE, ROOT, assert_one_line_error

import gcm_pipeline as gcm
from gcm_pipeline.cli import main
from gcm_pipeline.geometry.dualquat import dq_exp, dq_mul, dq_to_matrix
from gcm_pipeline.geometry.pose_metric import pose_distance, pose_features
from gcm_pipeline.manifold.locate import TriangleLocator, _cells
from gcm_pipeline.manifold.surface import blend
from gcm_pipeline.pipeline import make_checker


@pytest.fixture(scope="module")
def bottle_run(tmp_path_factory: pytest.TempPathFactory) -> gcm.RunResult:
    out = tmp_path_factory.mktemp("query") / "bottle"
    cfg = gcm.load_config(BOTTLE, ["publish.html=false", "publish.plots=false"])
    return gcm.Pipeline(cfg).run(out_dir=out, progress=False)


@pytest.fixture(scope="module")
def bottle(bottle_run: gcm.RunResult) -> gcm.GraspManifold:
    assert bottle_run.run_dir is not None
    return gcm.load_manifold(bottle_run.run_dir)


def _noisy(dq: np.ndarray, rng: np.random.Generator, pos: float, ang: float) -> np.ndarray:
    twist = np.concatenate((rng.normal(size=(len(dq), 3)) * ang, rng.normal(size=(len(dq), 3))), 1)
    twist[:, 3:] *= pos
    return dq_mul(dq, dq_exp(twist))


def test_loaded_manifold_matches_the_run(
    bottle_run: gcm.RunResult, bottle: gcm.GraspManifold
) -> None:
    live = bottle_run.grasp_manifold
    assert len(live) == len(bottle) == len(bottle_run.manifold.triangles)
    # grasps.csv holds positions and quaternions (qw >= 0): the same poses
    assert pose_distance(live.poses, bottle.poses).max() < 1e-12
    assert bottle.method == "dlb"
    assert "126 triangles" in repr(bottle)


def test_sample_is_exact_at_the_vertices(bottle: gcm.GraspManifold) -> None:
    t = np.repeat(np.arange(len(bottle)), 3)
    w = np.tile(np.eye(3), (len(bottle), 1))
    got = bottle.sample(t, w)
    want = bottle.poses[bottle.triangles.ravel()]
    assert np.array_equal(got, want)  # bit for bit


def test_sample_reproduces_the_densified_rows(bottle: gcm.GraspManifold) -> None:
    g = bottle.grasps
    inner = np.asarray(g["origin"]) == "interpolated"
    got = bottle.sample(np.asarray(g["triangle"])[inner], np.asarray(g["weights"])[inner])
    # grasps.csv stores positions and quaternions with repr: equal up to conversion
    assert np.max(pose_distance(got, np.asarray(g["dq"])[inner])) < 1e-12


def test_sample_is_continuous_inside(bottle: gcm.GraspManifold) -> None:
    rng = np.random.default_rng(3)
    t = rng.integers(0, len(bottle), 500)
    w = rng.dirichlet((2, 2, 2), 500)
    step = 1e-4 * rng.normal(size=(500, 3))
    step -= step.mean(axis=1, keepdims=True)  # stays on the plane sum(w) = 1
    a, b = bottle.sample(t, w), bottle.sample(t, w + step)
    d = pose_distance(a, b)
    # Lipschitz: a weight change of 1e-4 moves a grasp by far less than a millimetre
    edge = pose_distance(bottle.poses[bottle.triangles[t, 0]], bottle.poses[bottle.triangles[t, 1]])
    assert np.all(d <= 5 * np.abs(step).max(axis=1) * edge.max())
    assert np.all(d > 0)


def test_sample_rejects_bad_points(bottle: gcm.GraspManifold) -> None:
    with pytest.raises(gcm.GeometryError, match="outside"):
        bottle.sample([len(bottle)], [[1.0, 0, 0]])
    with pytest.raises(gcm.GeometryError, match="sum to 1"):
        bottle.sample([0], [[0.5, 0.2, 0.2]])
    with pytest.raises(gcm.GeometryError, match="sum to 1"):
        bottle.sample([0], [[np.nan, 0.5, 0.5]])
    with pytest.raises(gcm.GeometryError, match="shape"):
        bottle.sample([0, 1], [[1.0, 0, 0]])


def test_locate_matches_brute_force_on_a_fine_lattice(bottle: gcm.GraspManifold) -> None:
    rng = np.random.default_rng(7)
    corners = bottle.poses[bottle.triangles]
    t = rng.integers(0, len(bottle), 400)
    on = bottle.sample(t, rng.dirichlet((1, 1, 1), 400))
    queries = np.concatenate((_noisy(on[:200], rng, 0.01, 0.05), _noisy(on[200:], rng, 0.05, 0.3)))
    got = bottle.locate(queries)
    # brute force: every point of a 30-subdivided lattice on every triangle
    lat = _cells(30)[1].reshape(-1, 3)
    bt = np.repeat(np.arange(len(corners)), len(lat))
    pts = blend(corners[bt], np.tile(lat, (len(corners), 1)))
    from scipy.spatial import cKDTree

    feat = pose_features(pts)
    flip = feat.copy()
    flip[:, 3:] *= -1
    brute, _ = cKDTree(np.concatenate((feat, flip))).query(pose_features(queries))
    assert np.all(got.distance <= brute + 1e-12)  # never worse than any lattice point
    assert np.all(brute - got.distance < 3e-4)  # and the lattice is that fine
    assert np.allclose(pose_distance(got.dq, queries), got.distance, atol=1e-12)
    assert np.array_equal(got.dq, bottle.sample(got.triangle, got.weights))


def test_locate_finds_points_of_the_manifold_exactly(bottle: gcm.GraspManifold) -> None:
    rng = np.random.default_rng(11)
    t = rng.integers(0, len(bottle), 300)
    w = rng.dirichlet((1, 1, 1), 300)
    got = bottle.locate(bottle.sample(t, w))
    assert got.distance.max() < 1e-7
    # a vertex query lands on the vertex
    vtx = bottle.locate(bottle.poses[bottle.triangles[:20, 0]])
    assert vtx.distance.max() < 1e-9


def test_locate_takes_matrices_and_one_pose(bottle: gcm.GraspManifold) -> None:
    dq = bottle.poses[:4]
    a = bottle.locate(dq)
    b = bottle.locate(dq_to_matrix(dq))
    assert np.allclose(a.distance, b.distance, atol=1e-12)
    one = bottle.locate(dq_to_matrix(dq[0]))
    assert one.distance.shape == (1,)


@pytest.mark.parametrize(
    "pose, match",
    [
        (np.full((4, 4), np.nan), "non-finite"),
        (np.diag([2.0, 1.0, 1.0, 1.0]), "rigid|orthonormal"),
        (np.diag([-1.0, 1.0, 1.0, 1.0]), "rigid|orthonormal|reflect"),
        (np.ones(8), "not a unit dual quaternion"),
        (np.zeros((3, 3)), "must be"),
        ([1, 0, 0, 0, 0, 0, np.inf, 0], "non-finite"),
        ([1, 0, 0, 0, 0, 5e159, 0, 0], r"position \[1e\+160, 0, 0\] m is outside the scene"),
        (np.diag([1.0, 1.0, 1.0, 1.0]) + np.eye(4, k=3) * 1001, "outside the scene"),
        ([[1, 0, 0, np.inf], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]], "non-finite"),
        (np.diag([1.0, 1.0, 1.0, 1.0]) + np.eye(4, k=3) * 1000.001, r"\[1000.001, 0, 0\] m"),
    ],
)
def test_query_poses_must_be_rigid_and_finite(
    bottle: gcm.GraspManifold, pose: object, match: str
) -> None:
    with pytest.raises(gcm.GeometryError, match=match):
        bottle.locate(pose)


@pytest.fixture(scope="module")
def many_triangles() -> TriangleLocator:
    """The bottle with 2,000 side grasps: about 4,000 small triangles (the benchmark's)."""
    over = ["candidates.count=2000", "manifold.max_edge_length=0.03"]
    cfg = gcm.load_config(BOTTLE, over)
    cand = gcm.generate_candidates(cfg)
    mesh = gcm.build_manifold(cand, cfg)
    assert len(mesh.triangles) > 3000
    return TriangleLocator(np.asarray(cand["dq"])[mesh.triangles], method=cfg.densify.method)


def _far_queries(corners: np.ndarray, n: int, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    t = rng.integers(0, len(corners), n)
    on = blend(corners[t], rng.dirichlet((1, 1, 1), n))
    return _noisy(on, rng, 0.05, np.deg2rad(15.0))


def test_pruned_locate_equals_exhaustive_projection(
    bottle: gcm.GraspManifold, many_triangles: TriangleLocator
) -> None:
    # pruning skips only triangles that cannot hold a nearer point: the answer
    # is the one of projecting every query onto every triangle
    # and on triangles turning by up to about 3 rad, some with corners whose
    # quaternions disagree in sign pairwise (DLB signs them point by point there)
    rng = np.random.default_rng(1)
    twist = np.zeros((90, 6))
    twist[:, :3] = rng.normal(size=(90, 3)) * 1.5
    twist[:, 3:] = rng.normal(size=(90, 3)) * 0.05
    wide = TriangleLocator(dq_exp(twist).reshape(30, 3, 8))
    for loc, n in ((bottle.locator, 300), (many_triangles, 40), (wide, 200)):
        queries = _far_queries(loc.corners, n, seed=len(loc))
        got = loc.locate(queries)
        ref = loc.locate(queries, exhaustive=True)
        assert np.all(np.abs(got.distance - ref.distance) <= 1e-12)
        assert np.array_equal(got.triangle, ref.triangle)


def test_locator_bounds_are_lower_bounds(
    bottle: gcm.GraspManifold, many_triangles: TriangleLocator
) -> None:
    # every bound used for pruning is at most the distance to any point of the
    # triangle; checked where it matters, on each query's 8 lowest-bound triangles
    inner, corners = _cells(24)
    pts_w = np.concatenate((inner, corners.reshape(-1, 3)))
    for loc in (bottle.locator, many_triangles):
        rng = np.random.default_rng(5)
        queries = np.concatenate(
            (_far_queries(loc.corners, 25, 1), _noisy(loc.corners[:25, 0], rng, 0.01, 0.05))
        )
        m, t = len(queries), len(loc)
        rows = np.repeat(np.arange(m), t)
        feat = pose_features(queries, loc.orientation_scale)
        kept, bound, _ = loc._bounds(feat, rows, np.tile(np.arange(t), m), np.full(m, np.inf))
        assert len(kept) == len(rows)
        lowest = np.argsort(bound.reshape(m, t), axis=1)[:, :8]  # (m, 8)
        tris = lowest.ravel()
        pts = blend(np.repeat(loc.corners[tris], len(pts_w), 0), np.tile(pts_w, (len(tris), 1)))
        dist = pose_distance(pts.reshape(m, 8, -1, 8), queries[:, None, None]).min(axis=2)
        assert np.all(np.take_along_axis(bound.reshape(m, t), lowest, 1) <= dist + 1e-12)
        # and the first distance to beat is that of a point of the manifold
        tri, w, d = loc._upper(queries, feat)
        assert np.allclose(pose_distance(blend(loc.corners[tri], w), queries), d, atol=1e-15)


def test_triangle_locator_needs_triangles() -> None:
    with pytest.raises(gcm.GeometryError, match="no triangle"):
        TriangleLocator(np.zeros((0, 3, 8)))


def _verify(run: gcm.RunResult, dq: np.ndarray, q: np.ndarray) -> None:
    """FK of q is the grasp (base frame), inside the limits, collision free."""
    cfg = run.config
    base = cfg.robot.base_pose.matrix()
    target = np.linalg.inv(base) @ dq_to_matrix(dq)
    reached = run.robot.fk_pinocchio(q)
    assert np.abs(reached[:, :3, 3] - target[:, :3, 3]).max() < cfg.ik.position_tolerance
    rel = np.einsum("nji,njk->nik", target[:, :3, :3], reached[:, :3, :3])
    angle = np.arccos(np.clip((np.trace(rel, axis1=1, axis2=2) - 1) / 2, -1, 1))
    assert angle.max() < cfg.ik.orientation_tolerance
    assert run.robot.within_limits(q).all()
    checker = make_checker(run.robot, cfg.environment, cfg.object, base)
    assert np.all(checker.check(q) == "")


def test_nearest_reachable_returns_verified_solutions_on_the_manifold(
    bottle_run: gcm.RunResult, bottle: gcm.GraspManifold
) -> None:
    g = bottle.grasps
    rng = np.random.default_rng(5)
    reach = np.asarray(g["reachable"])
    # queries near reachable and near unreachable rows
    rows = np.concatenate(
        (rng.choice(np.flatnonzero(reach), 6), rng.choice(np.flatnonzero(~reach), 6))
    )
    queries = _noisy(np.asarray(g["dq"])[rows], rng, 0.01, 0.05)
    ans = bottle.nearest_reachable(queries)
    assert ans.found.all()
    _verify(bottle_run, ans.dq, ans.q)
    # the answer is a point of the manifold
    assert bottle.locate(ans.dq).distance.max() < 1e-7
    assert np.allclose(bottle.sample(ans.triangle, ans.weights), ans.dq, atol=1e-12)
    assert np.allclose(pose_distance(ans.dq, queries), ans.distance, atol=1e-12)
    # never farther than the nearest reachable row, never nearer than the manifold
    d_rows = pose_distance(np.asarray(g["dq"])[reach][None], queries[:, None]).min(axis=1)
    assert np.all(ans.distance <= d_rows + 1e-12)
    assert np.all(ans.distance >= ans.located - 1e-12)
    # near unreachable rows the continuous search beats the lattice somewhere
    assert np.any(ans.distance[6:] < d_rows[6:] - 1e-4)


def test_best_is_at_least_the_best_row(
    bottle_run: gcm.RunResult, bottle: gcm.GraspManifold
) -> None:
    best = bottle.best(starts=3)
    ranked = np.asarray(bottle.grasps["rank"])
    top = int(np.flatnonzero(ranked == 1)[0])
    top_value = float(bottle.grasps["combined"][top])
    assert best.metric == "combined"
    assert best.value[0] >= top_value - 1e-12
    assert np.all(best.value >= best.start_value)
    assert np.all(np.diff(best.value) <= 0)
    _verify(bottle_run, best.dq, best.q)
    # the values are the metric of the returned solutions, on the run's scale
    table = gcm.GraspTable(
        {
            "dq": best.dq,
            "reachable": np.ones(len(best.dq), bool),
            "q": best.q,
            "clearance": make_checker(
                bottle_run.robot,
                bottle_run.config.environment,
                bottle_run.config.object,
                bottle_run.config.robot.base_pose.matrix(),
            ).clearance(best.q),
        }
    )
    assert np.allclose(bottle.metric_values(table, "combined"), best.value, atol=1e-9)


def test_best_in_a_region_and_by_another_metric(bottle: gcm.GraspManifold) -> None:
    low = bottle.best(
        "yoshikawa", region=lambda dq: gcm.dq_to_pos_quat(dq)[0][:, 2] < 0.1, starts=3
    )
    assert np.all(gcm.dq_to_pos_quat(low.dq)[0][:, 2] < 0.1)
    manip = np.asarray(bottle.grasps["manipulability"])
    z = gcm.dq_to_pos_quat(np.asarray(bottle.grasps["dq"]))[0][:, 2]
    assert low.value[0] >= np.nanmax(np.where(z < 0.1, manip, np.nan)) - 1e-12
    tri = bottle.best("joint_limit_margin", region=[0, 1, 2], starts=2)
    assert np.isin(tri.triangle, [0, 1, 2]).all()
    with pytest.raises(gcm.InputError, match="unknown metric"):
        bottle.best("speed")
    with pytest.raises(gcm.InputError, match="region holds no triangle id"):
        bottle.best(region=[])


def test_gcm_query_prints_the_nearest_reachable_grasp(
    bottle_run: gcm.RunResult, capsys: pytest.CaptureFixture[str]
) -> None:
    run_dir = str(bottle_run.run_dir)
    pose = ["0.5", "-0.05", "0.12", "0.5", "-0.5", "-0.5", "-0.5"]
    assert main(["query", run_dir, "--pose", *pose, "--json"]) == 0
    (item,) = json.loads(capsys.readouterr().out)
    assert item["found"] and len(item["q"]) == 7
    assert item["distance"] >= item["manifold_distance"] - 1e-12
    assert main(["query", run_dir, "--pose", *pose]) == 0
    out = capsys.readouterr().out
    assert "nearest reachable grasp" in out and "q7" in out
    # the same pose in the robot base frame (identity here) and the object frame
    assert main(["query", run_dir, "--pose", *pose, "--frame", "base", "--json"]) == 0
    assert json.loads(capsys.readouterr().out)[0]["distance"] == pytest.approx(item["distance"])
    obj = ["0.0", "-0.05", "0.12", "0.5", "-0.5", "-0.5", "-0.5"]  # bottle at x = 0.5
    assert main(["query", run_dir, "--pose", *obj, "--frame", "object", "--json"]) == 0
    assert json.loads(capsys.readouterr().out)[0]["distance"] == pytest.approx(item["distance"])


@pytest.mark.parametrize(
    "pose, match",
    [
        (["0.5", "0", "0.1", "2", "0", "0", "0"], "norm 1"),
        (["0.5", "0", "nan", "1", "0", "0", "0"], "finite"),
        (["0.5", "0", "x", "1", "0", "0", "0"], "7 numbers"),
        (["1e160", "0", "0.1", "1", "0", "0", "0"], "--pose 1: position 1e160 0 0.1 m is outside"),
    ],
)
def test_gcm_query_bad_poses_are_one_line_errors(
    bottle_run: gcm.RunResult, capsys: pytest.CaptureFixture[str], pose: list[str], match: str
) -> None:
    code = main(["query", str(bottle_run.run_dir), "--pose", *pose])
    assert_one_line_error(code, capsys.readouterr().err, match)


def test_gcm_query_needs_a_run_with_a_manifold(
    bottle_run: gcm.RunResult, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    import shutil

    broken = tmp_path / "run"
    assert bottle_run.run_dir is not None
    shutil.copytree(bottle_run.run_dir, broken)
    (broken / "manifold.npz").unlink()
    assert main(["query", str(broken), "--pose", "0.5", "0", "0.1", "1", "0", "0", "0"]) == 2
    err = capsys.readouterr().err
    assert "manifold.npz" in err and err.count("\n") == 1
    with pytest.raises(gcm.InputError, match="manifold.npz"):
        gcm.load_manifold(broken)


def test_nothing_reachable_is_an_answer_not_an_error(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    far = tmp_path / "far.yaml"
    text = (ROOT / "configs" / "flat_surface.yaml").read_text()
    far.write_text(text.replace("xyz: [0.45, 0.0, 0.03]", "xyz: [2.5, 0.0, 0.03]"))
    out = tmp_path / "run"
    cfg = gcm.load_config(far, ["publish.html=false", "publish.plots=false"])
    gcm.Pipeline(cfg).run(out, progress=False)
    with gcm.load_manifold(out) as m:
        ans = m.nearest_reachable(m.poses[:2])
    assert not ans.found.any() and np.isnan(ans.distance).all() and np.isnan(ans.q).all()
    assert np.allclose(ans.located, 0.0, atol=1e-9)
    assert main(["query", str(out), "--pose", "2.5", "0", "0.1", "0", "1", "0", "0"]) == 0
    assert "no reachable grasp found" in capsys.readouterr().out
