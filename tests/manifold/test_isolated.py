"""Every candidate is a point of the manifold: locate, nearest_reachable, best, margin."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from helpers import ROOT
from hypothesis import given, settings
from hypothesis import strategies as st

import gcm_pipeline as gcm
from gcm_pipeline.cli import main
from gcm_pipeline.geometry.dualquat import dq_exp, dq_mul, dq_to_matrix
from gcm_pipeline.geometry.pose_metric import pose_distance
from gcm_pipeline.manifold.locate import TriangleLocator
from gcm_pipeline.manifold.margin import margin

ACRONYM = ROOT / "tests" / "data" / "acronym"
MUG_H5 = ACRONYM / "Mug_10f6e09036350e92b3f21f1137c3c347_0.0002682457830986903.h5"
MUG_OBJ = ACRONYM / "10f6e09036350e92b3f21f1137c3c347.obj"


def _mug_config(path: Path, limit: int, max_edge_length: float) -> Path:
    """ACRONYM's mug (successful grasps) standing on the table 0.5 m in front of the Panda."""
    path.write_text(
        f"""
seed: 0
robot: {{spec: panda}}
object:
  shape: mesh
  mesh: {MUG_OBJ}
  scale: 0.0002682457830986903
  pose: {{xyz: [0.5, 0.0, -0.0514294], rpy_deg: [0, 0, 0]}}  # mesh bottom at z = 0
candidates:
  source: file
  path: {MUG_H5}
  format: acronym
  frame: object
  success_only: true
  limit: {limit}
manifold: {{projection: cylindrical, max_edge_length: {max_edge_length}, max_edge_angle_deg: 50}}
densify: {{subdivisions: 2, method: dlb}}
environment: {{table: {{height: 0.0}}}}
publish: {{html: false, plots: false}}
"""
    )
    return path


def _run(tmp: Path, limit: int, max_edge_length: float) -> gcm.RunResult:
    pytest.importorskip("h5py")
    cfg = gcm.load_config(_mug_config(tmp / "mug.yaml", limit, max_edge_length))
    return gcm.Pipeline(cfg).run(out_dir=tmp / "run", progress=False)


@pytest.fixture(scope="module")
def mug_run(tmp_path_factory: pytest.TempPathFactory) -> gcm.RunResult:
    return _run(tmp_path_factory.mktemp("mug"), 240, 0.08)


@pytest.fixture(scope="module")
def mug(mug_run: gcm.RunResult) -> gcm.GraspManifold:
    assert mug_run.run_dir is not None
    return gcm.load_manifold(mug_run.run_dir)


@pytest.fixture(scope="module")
def lonely_run(tmp_path_factory: pytest.TempPathFactory) -> gcm.RunResult:
    """Every candidate isolated: no triangle survives a 0.1 mm edge bound."""
    return _run(tmp_path_factory.mktemp("lonely"), 40, 0.0001)


def _isolated_reachable(m: gcm.GraspManifold) -> np.ndarray:
    reach = np.asarray(m.grasps["reachable"], dtype=bool)
    unused = m.mesh.unused
    return unused[reach[unused]]


def _off(dq: np.ndarray, rng: np.random.Generator, dist: float) -> np.ndarray:
    """Poses ``dist`` [m] away in the pose metric, in random directions of SE(3)."""
    twist = rng.normal(size=(len(dq), 6))
    twist[:, :3] *= 0.5  # rotation [rad] ... scaled below
    out = dq_mul(dq, dq_exp(twist))
    d = pose_distance(out, dq)
    return dq_mul(dq, dq_exp(twist * (dist / d)[:, None]))


def _verify(run: gcm.RunResult, dq: np.ndarray, q: np.ndarray) -> None:
    """Pinocchio FK of each solution reproduces its grasp (base frame) within the IK tolerances."""
    cfg = run.config
    target = np.linalg.inv(cfg.robot.base_pose.matrix()) @ dq_to_matrix(dq)
    reached = run.robot.fk_pinocchio(q)
    assert np.abs(reached[:, :3, 3] - target[:, :3, 3]).max() < cfg.ik.position_tolerance
    rel = np.einsum("nji,njk->nik", target[:, :3, :3], reached[:, :3, :3])
    angle = np.arccos(np.clip((np.trace(rel, axis1=1, axis2=2) - 1) / 2, -1, 1))
    assert angle.max() < cfg.ik.orientation_tolerance


# --------------------------------------------------------------------------- locator
def _random_manifold(seed: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Triangles (T, 3, 8), isolated points (P, 8) and queries (Q, 8) in one 10 cm box."""
    rng = np.random.default_rng(seed)
    n_t, n_p = int(rng.integers(0, 12)), int(rng.integers(1, 30))
    centre = dq_exp(np.c_[rng.normal(size=(n_t + n_p, 3)), 0.05 * rng.normal(size=(n_t + n_p, 3))])
    corners = dq_mul(
        np.repeat(centre[:n_t], 3, axis=0), dq_exp(0.02 * rng.normal(size=(3 * n_t, 6)))
    ).reshape(n_t, 3, 8)
    points = centre[n_t:]
    some = np.concatenate((points, corners.reshape(-1, 8)))
    queries = dq_mul(some[rng.integers(0, len(some), 40)], dq_exp(0.03 * rng.normal(size=(40, 6))))
    return corners, points, np.concatenate((queries, points))


@settings(max_examples=30, deadline=None)
@given(st.integers(0, 2**32 - 1))
def test_isolated_points_are_points_of_the_manifold(seed: int) -> None:
    corners, points, queries = _random_manifold(seed)
    ids = np.arange(100, 100 + len(points))
    loc = TriangleLocator(corners, points=points, point_ids=ids)
    got = loc.locate(queries)
    # the reference: every query projected onto every triangle, and every point
    to_points = pose_distance(points[None], queries[:, None]).min(axis=1)
    ref_d = to_points
    if len(corners):
        ref = TriangleLocator(corners).locate(queries, exhaustive=True)
        ref_d = np.minimum(ref.distance, to_points)
    assert np.all(np.abs(got.distance - ref_d) <= 1e-12)
    assert np.allclose(pose_distance(got.dq, queries), got.distance, atol=1e-12)
    # exhaustive search with the points gives the same answer
    full = loc.locate(queries, exhaustive=True)
    assert np.all(np.abs(full.distance - got.distance) <= 1e-12)
    # and so does one query at a time (a batch with nothing left to search)
    one = loc.locate(queries, batch=1)
    assert np.array_equal(one.distance, got.distance)
    # an isolated answer names its point; a triangle answer names no point
    iso = got.vertex >= 0
    assert np.array_equal(iso, got.triangle == -1)
    assert np.array_equal(got.dq[iso], points[got.vertex[iso] - 100])
    assert np.all(got.weights[iso] == [1.0, 0.0, 0.0])
    # at a point's exact pose the answer is that point
    at = got.distance[-len(points) :]
    assert np.all(at == 0.0)


def test_a_query_at_an_isolated_point_far_from_every_triangle() -> None:
    # no triangle is near enough to be searched at all (each query alone, as gcm query asks)
    tri = dq_exp(np.c_[np.zeros((3, 3)), np.eye(3) * 0.01]).reshape(1, 3, 8)
    point = dq_exp(np.array([[0.0, 0.0, 0.0, 1.0, 0.0, 0.0]]))
    loc = TriangleLocator(tri, points=point, point_ids=[7])
    for q in (point, point[:, [0, 1, 2, 3, 4, 5, 6, 7]] * [[-1] * 8]):  # both quaternion signs
        got = loc.locate(q)
        assert got.vertex.tolist() == [7] and got.triangle.tolist() == [-1]
        assert got.distance.tolist() == [0.0]
    near_tri = loc.locate(tri[0, :1])
    assert near_tri.triangle.tolist() == [0] and near_tri.distance[0] < 1e-9


def test_locator_needs_a_triangle_or_a_point() -> None:
    with pytest.raises(gcm.GeometryError, match="no triangle and no point"):
        TriangleLocator(np.zeros((0, 3, 8)))
    with pytest.raises(gcm.GeometryError, match=r"points must have shape \(P, 8\)"):
        TriangleLocator(np.zeros((0, 3, 8)), points=np.zeros((3, 7)))


# --------------------------------------------------------------------------- margin
def test_margin_of_an_isolated_reachable_row_is_zero() -> None:
    dq = dq_exp(np.c_[np.zeros((5, 3)), np.arange(15.0).reshape(5, 3) * 0.01])
    reach = np.array([True, True, False, True, True])
    # rows 0-1-2 linked, row 3 and 4 on no edge
    got = margin(dq, reach, np.array([[0, 1], [1, 2]]))
    assert got[3] == 0.0 and got[4] == 0.0 and got[2] == 0.0
    assert got[1] == pytest.approx(0.5 * pose_distance(dq[1], dq[2]))
    # no edge at all: every row is isolated
    assert np.array_equal(margin(dq, reach, np.zeros((0, 2), np.int64)), np.zeros(5))
    # a linked component with nothing unreachable keeps margin inf
    all_reach = np.array([True, True, True, True, False])
    assert np.array_equal(margin(dq, all_reach, np.array([[0, 1], [1, 2]]))[:4], [np.inf] * 3 + [0])


# --------------------------------------------------------------------------- a real run
def test_the_mug_has_isolated_reachable_rows(mug: gcm.GraspManifold) -> None:
    iso = _isolated_reachable(mug)
    assert len(mug) > 0 and len(iso) > 10
    # they are points of the manifold: locate finds each at distance 0
    loc = mug.locate(mug.poses[iso])
    assert np.array_equal(loc.vertex, iso) and np.all(loc.triangle == -1)
    assert np.all(loc.distance == 0.0)
    with pytest.raises(gcm.GeometryError, match="-1: an isolated candidate"):
        mug.sample(loc.triangle[:1], loc.weights[:1])
    # and their margin is 0 (isolated), though reachable
    assert np.all(np.asarray(mug.grasps["margin"])[iso] == 0.0)


def test_nearest_reachable_at_every_reachable_row_is_that_row(
    mug_run: gcm.RunResult, mug: gcm.GraspManifold
) -> None:
    g = mug.grasps
    reach = np.flatnonzero(np.asarray(g["reachable"], dtype=bool))
    dq = np.asarray(g["dq"])[reach]
    ans = mug.nearest_reachable(dq)
    assert ans.found.all()
    assert ans.distance.max() <= 1e-6
    _verify(mug_run, ans.dq, ans.q)
    iso = np.isin(reach, mug.mesh.unused)
    assert np.array_equal(ans.vertex[iso], reach[iso]) and np.all(ans.triangle[iso] == -1)
    assert np.all(ans.vertex[~iso] == -1) and np.all(ans.triangle[~iso] >= 0)


def test_nearest_reachable_5mm_off_is_never_farther_than_the_nearest_reachable_row(
    mug_run: gcm.RunResult, mug: gcm.GraspManifold
) -> None:
    g = mug.grasps
    rng = np.random.default_rng(30)
    dq = np.asarray(g["dq"])
    reach = np.asarray(g["reachable"], dtype=bool)
    rows = np.flatnonzero(reach)
    queries = np.concatenate(
        [_off(dq[rows], rng, 0.005), _off(dq[_isolated_reachable(mug)], rng, 0.005)]
    )
    ans = mug.nearest_reachable(queries)
    nearest_row = pose_distance(dq[reach][None], queries[:, None]).min(axis=1)
    assert ans.found.all()
    assert np.all(ans.distance <= nearest_row + 1e-12)
    _verify(mug_run, ans.dq, ans.q)


def test_best_starts_from_isolated_rows(mug: gcm.GraspManifold) -> None:
    values = mug.metric_values(mug.grasps, "yoshikawa")
    best = mug.best("yoshikawa", starts=40, iterations=2)
    assert best.value[0] >= np.nanmax(values) - 1e-12
    iso = best.triangle == -1
    assert iso.any()  # some of the 40 best rows are in no triangle
    assert np.isin(best.start_row[iso], mug.mesh.unused).all()
    assert np.array_equal(best.dq[iso], np.asarray(mug.grasps["dq"])[best.start_row[iso]])
    assert np.array_equal(best.value[iso], best.start_value[iso])
    # a region of triangle ids holds no isolated row
    tri = mug.best("yoshikawa", region=np.arange(len(mug)), starts=5, iterations=1)
    assert np.all(tri.triangle >= 0)


def test_gcm_query_at_an_isolated_row_answers_with_it(
    mug_run: gcm.RunResult, mug: gcm.GraspManifold, capsys: pytest.CaptureFixture[str]
) -> None:
    row = int(_isolated_reachable(mug)[0])
    pos, quat = gcm.dq_to_pos_quat(np.asarray(mug.grasps["dq"])[row : row + 1])
    pose = [repr(float(v)) for v in (*pos[0], *quat[0])]
    run_dir = str(mug_run.run_dir)
    assert main(["query", run_dir, "--pose", *pose, "--json"]) == 0
    (item,) = json.loads(capsys.readouterr().out)
    assert item["found"] and item["row"] == row and item["triangle"] == -1
    assert item["distance"] <= 1e-6 and item["manifold_distance"] <= 1e-6
    assert main(["query", run_dir, "--pose", *pose]) == 0
    assert f"candidate row {row}, in no triangle" in capsys.readouterr().out


# --------------------------------------------------------------------------- no triangle at all
def test_a_run_without_triangles_answers_from_its_rows(
    lonely_run: gcm.RunResult, capsys: pytest.CaptureFixture[str]
) -> None:
    assert lonely_run.run_dir is not None
    m = gcm.load_manifold(lonely_run.run_dir)
    assert len(m) == 0 and len(m.mesh.unused) == m.mesh.n_vertices
    dq = np.asarray(m.grasps["dq"])
    reach = np.asarray(m.grasps["reachable"], dtype=bool)
    loc = m.locate(dq)
    assert np.all(loc.distance == 0.0) and np.array_equal(loc.vertex, np.arange(len(dq)))
    rng = np.random.default_rng(1)
    queries = np.concatenate((dq[reach], _off(dq, rng, 0.005)))
    ans = m.nearest_reachable(queries)
    nearest_row = pose_distance(dq[reach][None], queries[:, None]).min(axis=1)
    assert ans.found.all() and np.all(ans.distance <= nearest_row + 1e-12)
    assert np.all(ans.distance[: reach.sum()] <= 1e-6)
    _verify(lonely_run, ans.dq, ans.q)
    best = m.best("yoshikawa", starts=3)
    values = m.metric_values(m.grasps, "yoshikawa")
    assert best.value[0] == np.nanmax(values) and np.all(best.triangle == -1)
    assert np.all(np.asarray(m.grasps["margin"]) == 0.0)
    assert (
        main(["query", str(lonely_run.run_dir), "--pose", "0.5", "0", "0.1", "0", "1", "0", "0"])
        == 0
    )
    assert "in no triangle" in capsys.readouterr().out
    # bad queries are still one-line errors
    with pytest.raises(gcm.GeometryError, match="non-finite"):
        m.nearest_reachable(np.full(8, np.nan))
    with pytest.raises(gcm.GeometryError, match="not a unit dual quaternion"):
        m.locate(2.0 * dq[0])
