"""IK continuity (ik_jump, patches, re-seeding) and the robustness margin."""

from __future__ import annotations

import numpy as np
import pytest
from helpers import BOTTLE

import gcm_pipeline as gcm
from gcm_pipeline.geometry.pose_metric import pose_distance
from gcm_pipeline.manifold import continuity
from gcm_pipeline.manifold.build import build_manifold
from gcm_pipeline.manifold.densify import densify
from gcm_pipeline.manifold.lattice import row_mesh
from gcm_pipeline.manifold.margin import margin
from gcm_pipeline.pipeline import ReachabilityCheck, make_checker
from gcm_pipeline.table import GraspTable


def _flat(subdivisions: int = 20) -> tuple[GraspTable, np.ndarray]:
    """A flat triangle of grasps with one orientation, densified; its row edges."""
    pos = np.array([[0.0, 0.0, 0.0], [0.2, 0.0, 0.0], [0.0, 0.2, 0.0]])
    cand = GraspTable({"dq": gcm.dq_from_pos_quat(pos, np.tile([1.0, 0, 0, 0], (3, 1)))})
    mesh = build_manifold(cand, projection="xy")
    table = densify(cand, mesh, subdivisions=subdivisions)
    return table, row_mesh(table, mesh.triangles, 3).edges


def test_ik_jump_and_patches_on_a_branch_flip() -> None:
    table, edges = _flat(10)
    x = gcm.dq_to_pos_quat(table["dq"])[0][:, 0]
    q = np.zeros((len(table), 7))
    q[:, 0] = 0.5 * x  # smooth along x ...
    q[x > 0.1, 3] = 2.0  # ... but joint 4 flips past x = 0.1
    reach = np.ones(len(table), bool)
    reach[0] = False
    jump = continuity.ik_jumps(q, reach, edges)
    assert np.isnan(jump[0])
    near_flip = (x > 0.075) & (x < 0.125) & reach
    assert np.all(jump[near_flip & (np.abs(x - 0.1) < 0.011)] >= 2.0)
    assert np.all(jump[reach & (np.abs(x - 0.1) > 0.03)] < 0.05)
    pid = continuity.patches(q, reach, edges, threshold=0.5)
    assert pid[0] == -1
    assert set(np.unique(pid[reach])) == {0, 1}
    assert np.all(pid[reach & (x > 0.1)] == pid[np.flatnonzero(reach & (x > 0.1))[0]])
    # patch 0 is the larger one
    sizes = np.bincount(pid[reach])
    assert sizes[0] >= sizes[1]
    with pytest.raises(gcm.InputError, match="threshold"):
        continuity.patches(q, reach, edges, threshold=0.0)


def test_margin_is_the_distance_to_the_boundary_along_the_manifold() -> None:
    table, edges = _flat(20)
    pos = gcm.dq_to_pos_quat(table["dq"])[0]
    x_b = 0.105  # the boundary: reachable left of it
    reach = pos[:, 0] < x_b
    m = margin(np.asarray(table["dq"]), reach, edges)
    assert np.all(m[~reach] == 0.0)
    h = 0.2 / 20  # lattice spacing
    # zero at the boundary: rows next to an unreachable one are within half an edge
    border = np.zeros(len(table), bool)
    e = edges[reach[edges[:, 0]] != reach[edges[:, 1]]]
    border[e.ravel()] = True
    assert np.all(m[border & reach] <= 0.5 * h * np.sqrt(2) + 1e-12)
    assert np.all(m[border & reach] > 0)
    # elsewhere: the distance to the boundary segment {x = x_b, y <= 0.2 - x_b} of
    # the triangle, up to half an edge and the lattice's detours (at most sqrt 2
    # on this right-angled lattice)
    p = pos[reach, :2]
    foot = np.column_stack((np.full(len(p), x_b), np.clip(p[:, 1], 0.0, 0.2 - x_b)))
    d = np.linalg.norm(p - foot, axis=1)
    got = m[reach]
    assert np.all(got >= d - 0.5 * h * np.sqrt(2) - 1e-12)
    assert np.all(got <= np.sqrt(2) * d + h)
    assert np.corrcoef(got, d)[0, 1] > 0.99
    # no unreachable row: unbounded
    assert np.all(np.isinf(margin(np.asarray(table["dq"]), np.ones(len(table), bool), edges)))


def test_margin_counts_orientation() -> None:
    dq = gcm.dq_from_pos_quat(
        np.zeros((3, 3)), [[1, 0, 0, 0], [np.cos(0.1), np.sin(0.1), 0, 0], [0, 1, 0, 0]]
    )
    edges = np.array([[0, 1], [1, 2]])
    m = margin(dq, np.array([True, True, False]), edges, orientation_scale=0.1)
    first = pose_distance(dq[0], dq[1], 0.1)  # a 0.2 rad turn: about 0.02 m
    assert 0.019 < first < 0.021
    assert m[0] == pytest.approx(first + 0.5 * pose_distance(dq[1], dq[2], 0.1))


@pytest.fixture(scope="module")
def bottle() -> gcm.RunResult:
    cfg = gcm.load_config(BOTTLE, ["continuity.reseed=true", "ranking.metric=margin"])
    return gcm.Pipeline(cfg).run(write=False, progress=False)


def test_reseeding_merges_patches_and_keeps_valid_solutions(bottle: gcm.RunResult) -> None:
    c = bottle.counts["continuity"]
    assert c["patches"] < c["patches_before_reseed"]
    assert c["reseeded"] > 0
    g = bottle.grasps
    reach = np.asarray(g["reachable"])
    assert int(reach.sum()) == 647  # reachability never changes (0.1 rad limit margin)
    pid = np.asarray(g["patch"])
    assert pid.max() + 1 == c["patches"]
    assert np.all((pid >= 0) == reach)
    # patches are the components of the edges within the threshold: no such edge
    # joins two patches, and ik_jump is the largest jump at each grasp
    edges = row_mesh(g, bottle.manifold.triangles, bottle.manifold.n_vertices).edges
    both = reach[edges[:, 0]] & reach[edges[:, 1]]
    q = np.asarray(g["q"])
    jump = np.abs(q[edges[:, 0]] - q[edges[:, 1]]).max(axis=1)
    across = both & (pid[edges[:, 0]] != pid[edges[:, 1]])
    assert np.all(jump[across] > 0.5)
    ik_jump = np.asarray(g["ik_jump"])
    for row in np.flatnonzero(reach)[::37]:
        at = both & ((edges[:, 0] == row) | (edges[:, 1] == row))
        assert ik_jump[row] == pytest.approx(jump[at].max()) if at.any() else np.isnan(ik_jump[row])
    # every solution is still verified, inside the limits and collision free
    cfg = bottle.config
    base = cfg.robot.base_pose.matrix()
    target = np.linalg.inv(base) @ gcm.dq_to_matrix(np.asarray(g["dq"])[reach])
    reached = bottle.robot.fk_pinocchio(q[reach])
    assert np.abs(reached[:, :3, 3] - target[:, :3, 3]).max() < cfg.ik.position_tolerance
    checker = make_checker(bottle.robot, cfg.environment, cfg.object, base)
    assert np.all(checker.check(q[reach]) == "")


def test_reseed_reports_before_and_after() -> None:
    cfg = gcm.load_config(BOTTLE)
    res = gcm.Pipeline(cfg).run(write=False, progress=False)
    g = res.grasps
    edges = row_mesh(g, res.manifold.triangles, res.manifold.n_vertices).edges
    check = ReachabilityCheck(res.robot, cfg)
    before = continuity.patches(g["q"], g["reachable"], edges)
    new, report = continuity.reseed(g, edges, check)
    after = continuity.patches(new["q"], new["reachable"], edges)
    assert report.patches_before == before.max() + 1 == res.counts["continuity"]["patches"]
    assert report.patches_after == after.max() + 1 < report.patches_before
    assert np.bincount(after[after >= 0]).max() > np.bincount(before[before >= 0]).max()
    assert report.solved == check.solved


def test_margin_ranking_and_columns(bottle: gcm.RunResult) -> None:
    g = bottle.grasps
    reach = np.asarray(g["reachable"])
    m = np.asarray(g["margin"])
    assert np.all(m[~reach] == 0) and np.all(m[reach] > 0)
    rank = np.asarray(g["rank"])
    ranked = np.flatnonzero(rank > 0)
    ranked = ranked[np.argsort(rank[ranked])]
    assert len(ranked) == reach.sum()
    capped = np.where(np.isinf(m), np.max(m[np.isfinite(m)]), m)[ranked]
    assert np.all(np.diff(capped) <= 0)  # ranked by margin, inf counting as the largest
    # combined with a margin weight runs and uses it
    cfg = gcm.load_config(
        BOTTLE, ["ranking.weights={yoshikawa: 1.0, margin: 1.0}", "ranking.metric=combined"]
    )
    res = gcm.Pipeline(cfg).run(write=False, progress=False)
    top = int(np.flatnonzero(np.asarray(res.grasps["rank"]) == 1)[0])
    assert res.grasps["margin"][top] > np.nanmedian(np.asarray(res.grasps["margin"])[reach])
