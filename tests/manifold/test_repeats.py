"""Repeated grasps (exact and near) are one pose in the manifold; every row is still answered."""

from __future__ import annotations

import numpy as np
import pytest
from helpers import ROOT
from scipy.spatial.distance import cdist
from test_families import face_grasps

import gcm_pipeline as gcm
from gcm_pipeline.geometry.dualquat import (
    dq_from_matrix,
    dq_from_pos_quat,
    dq_to_matrix,
    dq_to_pos_quat,
    quat_mul,
)
from gcm_pipeline.geometry.pose_metric import pose_distance, pose_features
from gcm_pipeline.manifold.build import build_manifold
from gcm_pipeline.manifold.repeats import (
    NEAR_REPEAT,
    _crowded,
    _first_equal,
    first_rows,
    same_pose_rows,
)
from gcm_pipeline.table import GraspTable

SCALE = 0.1


def _copies(dq: np.ndarray, copies: int, kind: str, seed: int = 1) -> tuple[np.ndarray, np.ndarray]:
    """Each pose ``copies`` times, shuffled; the first copy exact, the others changed by ``kind``.

    ``kind``: a jitter in metres (moved that far, turned that many radians, random
    directions), ``float32`` (the pose rounded to float32 and read back) or ``digits6``
    (position and quaternion written with 6 significant digits). Every third copy has
    its quaternion negated. Returns the rows and each row's pose.
    """
    rng = np.random.default_rng(seed)
    pose = rng.permutation(np.repeat(np.arange(len(dq)), copies))
    pos, quat = dq_to_pos_quat(dq[pose])
    n = len(pose)
    if kind == "float32":
        pos, quat = pos.astype(np.float32).astype(float), quat.astype(np.float32).astype(float)
    elif kind == "digits6":
        pos, quat = (
            np.array([float(f"{v:.6g}") for v in a.ravel()]).reshape(a.shape) for a in (pos, quat)
        )
    else:
        size = float(kind)
        step = rng.normal(size=(n, 3))
        pos = pos + size * step / np.linalg.norm(step, axis=1, keepdims=True)
        axis = rng.normal(size=(n, 3))
        axis /= np.linalg.norm(axis, axis=1, keepdims=True)
        turn = np.column_stack((np.full(n, np.cos(size / 2)), np.sin(size / 2) * axis))
        quat = quat_mul(quat, turn)
    rows = dq_from_pos_quat(pos, quat / np.linalg.norm(quat, axis=1, keepdims=True))
    _, first = np.unique(pose, return_index=True)
    rows[first] = dq[pose[first]]  # the first copy of each pose is the pose itself
    rows[::3] *= -1.0
    return rows, pose


def _first_of_pose(pose: np.ndarray) -> np.ndarray:
    """(N,) the first row with each row's pose."""
    _, first, inverse = np.unique(pose, return_index=True, return_inverse=True)
    return first[inverse.reshape(-1)]


@pytest.mark.parametrize("kind", ["1e-12", "1e-9", "1e-6", "float32", "digits6"])
def test_near_copies_are_the_first_row_of_their_pose(kind) -> None:
    dq, _ = face_grasps(per_face=24)
    rows, pose = _copies(dq, 40, kind)
    assert len(np.unique(first_rows(rows))) > len(dq)  # the copies are not exact repeats
    assert np.array_equal(same_pose_rows(rows, SCALE), _first_of_pose(pose))


def test_rows_farther_apart_than_the_tolerance_stay_apart() -> None:
    # a row of poses 1.01 NEAR_REPEAT apart, and the same turned by 1.01 NEAR_REPEAT / (2 L)
    # rad steps (chord 2 L * 2 sin(a/4) ~ L a): nothing to merge, the exact repeats' answer
    dq, _ = face_grasps(per_face=4)
    pos, quat = dq_to_pos_quat(np.repeat(dq[:1], 40, axis=0))
    pos[:, 0] += 1.01 * NEAR_REPEAT * np.arange(40)
    a = 1.01 * NEAR_REPEAT / SCALE * np.arange(1, 41)
    turned = quat_mul(quat, np.column_stack((np.cos(a / 2), np.sin(a / 2), 0 * a, 0 * a)))
    rows = np.concatenate(
        (dq_from_pos_quat(pos, quat), dq_from_pos_quat(pos[:1] + 0 * pos, turned))
    )
    rows = np.concatenate((rows, rows[:5]))  # and five exact repeats
    far = dq_from_pos_quat([[1e15, 0, 0], [1e15 + 1, 0, 0], [1e15, 0, 0]], quat[:3])
    rows = np.concatenate((rows, far))  # 1e15 m out (beyond the grid's integers), 1 m apart
    gap = cdist(pose_features(rows[:80], SCALE), pose_features(rows[:80], SCALE))
    assert gap[np.triu_indices(80, 1)].min() > NEAR_REPEAT
    assert np.array_equal(same_pose_rows(rows, SCALE), first_rows(rows))
    assert first_rows(rows)[-1] == len(rows) - 3


def test_kept_rows_are_apart_and_repeats_near_them() -> None:
    # a cloud denser than the tolerance: no pose to recover, only the rule's guarantees
    rng = np.random.default_rng(3)
    dq, _ = face_grasps(per_face=4)
    pos, quat = dq_to_pos_quat(np.repeat(dq[:1], 1500, axis=0))
    rows = dq_from_pos_quat(pos + rng.uniform(0, 4 * NEAR_REPEAT, pos.shape), quat)
    rep = same_pose_rows(rows, SCALE)
    kept = np.flatnonzero(rep == np.arange(len(rows)))
    assert 2 < len(kept) < len(rows) and np.all(rep <= np.arange(len(rows)))
    assert np.array_equal(rep[rep], rep)
    far = cdist(pose_features(rows[kept], SCALE), pose_features(rows[kept], SCALE))
    assert far[np.triu_indices(len(kept), 1)].min() > NEAR_REPEAT
    assert pose_distance(rows, rows[rep], SCALE).max() <= 1.5 * NEAR_REPEAT


def test_rows_exactly_the_tolerance_apart_are_one_pose() -> None:
    # "at most NEAR_REPEAT apart": a distance of exactly 1e-5 m (x = 0 and x = 1e-5) is in
    # reach, so the second row is a repeat of the first (kept rows are more than it apart)
    quat = np.array([[1.0, 0.0, 0.0, 0.0]] * 3)
    rows = dq_from_pos_quat([[0.0, 0.0, 0.0], [NEAR_REPEAT, 0.0, 0.0], [0.5, 0.0, 0.0]], quat)
    assert pose_distance(rows[0], rows[1], SCALE) == NEAR_REPEAT
    assert same_pose_rows(rows, SCALE).tolist() == [0, 0, 2]


def test_a_half_turn_with_either_quaternion_sign_is_one_pose() -> None:
    # r_w ~ 0: the copies' features take opposite signs of r (grid cells far apart)
    m = np.diag([1.0, -1.0, -1.0, 1.0])  # a half turn about x: r = (0, 1, 0, 0)
    m[:3, 3] = [0.5, 0.1, 0.2]
    dq = dq_from_matrix(np.stack([m] * 3))
    dq[1, :4] = [3e-7, 1.0, 0.0, 0.0]
    dq[2, :4] = [-3e-7, 1.0, 0.0, 0.0]
    dq[1:, :4] /= np.linalg.norm(dq[1:, :4], axis=1, keepdims=True)
    dq[1:, 4:] = dq_from_pos_quat(np.repeat([m[:3, 3]], 2, axis=0), dq[1:, :4])[:, 4:]
    other = dq_from_matrix(np.stack([np.eye(4)] * 2)) + [0] * 8
    other[1, 4:] = dq_from_pos_quat([[0.0, 0.0, 0.5]], [[1.0, 0.0, 0.0, 0.0]])[0, 4:]
    rows = np.concatenate((dq, other))
    assert np.array_equal(same_pose_rows(rows, SCALE), [0, 0, 0, 3, 4])


def _manifolds(rows: np.ndarray, first: np.ndarray, **kw):
    return build_manifold(GraspTable({"dq": rows}), **kw), build_manifold(
        GraspTable({"dq": rows[first]}), **kw
    )


@pytest.mark.parametrize("kind", ["1e-9", "1e-6", "float32"])
@pytest.mark.parametrize(
    "kw",
    [
        {"structure": "families"},
        {"structure": "families", "max_edge_length": 0.03, "max_edge_angle_deg": 40},
        {"structure": "chart", "projection": "pca", "max_edge_length": 0.05},
        {
            "structure": "chart",
            "projection": "cylindrical",
            "triangulator": "bowyer_watson",
            "max_edge_length": 0.03,
            "frame": np.eye(4),
        },
    ],
)
def test_near_copies_give_the_manifold_of_the_distinct_poses(kind, kw) -> None:
    # 1,000 rows for each pose: once every copy a vertex (slivers among the copies, bounds
    # derived from the jitter, a false "fewer than 3 distinct poses", minutes of search)
    dq, _ = face_grasps(per_face=24)
    rows, pose = _copies(dq[:40], 1000, kind)
    first = np.flatnonzero(_first_of_pose(pose) == np.arange(len(rows)))
    m, one = _manifolds(rows, first, **kw)
    assert len(one.triangles) >= 10  # a real mesh
    assert m.n_vertices == len(rows) and np.isin(m.triangles, first).all()
    assert np.array_equal(m.triangles, first[one.triangles])
    assert np.array_equal(m.dropped, first[one.dropped])
    assert np.array_equal(m.dropped_reason, one.dropped_reason)
    if kw["structure"] == "families":
        assert (m.max_edge_length, m.max_edge_angle_deg) == (
            one.max_edge_length,
            one.max_edge_angle_deg,
        )
        assert np.array_equal(m.family[first], one.family)
        assert np.array_equal(m.isolation[first], one.isolation)
        assert m.isolated_counts.get("duplicate", 0) == len(rows) - len(first)
    else:  # the chart of the distinct poses, each once; a repeat at its first row's point
        assert np.array_equal(m.chart, one.chart[np.searchsorted(first, _first_of_pose(pose))])
        assert np.array_equal(m.frame, one.frame) and m.period == one.period


def test_every_row_of_a_file_of_near_copies_is_answered(tmp_path) -> None:
    # the 24 mug grasps of configs/from_file.yaml, 25 rows each (1e-7 m jitter, every other
    # row float32): one pose in the manifold, yet each row checked and in the run's table
    poses = np.load(ROOT / "configs" / "data" / "mug_grasps.npy")
    rows, pose = _copies(dq_from_matrix(poses), 25, "1e-7", seed=2)
    mats = dq_to_matrix(rows)
    mats[1::2] = mats[1::2].astype(np.float32).astype(float)
    first = np.flatnonzero(_first_of_pose(pose) == np.arange(len(rows)))
    np.save(tmp_path / "copies.npy", mats)
    np.save(tmp_path / "distinct.npy", mats[first])
    runs = []
    for name in ("copies", "distinct"):
        over = [
            f"candidates.path={tmp_path / name}.npy",
            "publish.html=false",
            "publish.plots=false",
        ]
        cfg = gcm.load_config(ROOT / "configs" / "from_file.yaml", over)
        runs.append(gcm.Pipeline(cfg).run(write=False, progress=False))
    run, one = runs
    assert run.counts["candidates"] == 600 and run.manifold.n_vertices == 600
    assert len(one.manifold.triangles) >= 5
    assert np.array_equal(run.manifold.triangles, first[one.manifold.triangles])
    g = run.grasps
    assert np.array_equal(np.asarray(g["origin"]) == "candidate", np.arange(len(g)) < 600)
    reason = np.asarray(g["reason"])[:600]
    reachable = np.asarray(g["reachable"], dtype=bool)[:600]
    assert np.all(reachable == (reason == "")) and reachable.any() and not reachable.all()
    # each copy answered as its pose's first row is (the copies are within 2e-7 m of it)
    assert np.array_equal(reachable, reachable[_first_of_pose(pose)])
    assert np.array_equal(reachable[first], np.asarray(one.grasps["reachable"], bool)[:24])
    assert len(g) - 600 == len(one.grasps) - 24  # the same interpolated rows


def test_rows_sharing_a_hash_are_still_told_apart() -> None:
    # two-word rows made to share _first_equal's hash: the first word's hash h1 xor the
    # second word is what the second round mixes, so (a, b) and (a', b ^ h1(a) ^ h1(a'))
    # collide; the rows are compared, and sorted themselves when a hash is shared
    def h1(a: int) -> int:
        h = ((0xCBF29CE484222325 ^ a) * 0x100000001B3) % 2**64
        return h ^ (h >> 31)

    a, b, a2 = 5, 7, 11
    keys = np.array([[a, b], [a2, b ^ h1(a) ^ h1(a2)], [a, b], [3, 3]], dtype=np.uint64)
    assert np.array_equal(_first_equal(keys), [0, 1, 0, 3])
    rng = np.random.default_rng(0)
    many = rng.integers(0, 3, (5000, 3)).astype(np.uint64)
    _, first, inverse = np.unique(many, axis=0, return_index=True, return_inverse=True)
    assert np.array_equal(_first_equal(many), first[inverse.reshape(-1)])


def test_the_grids_miss_no_row_with_another_within_reach() -> None:
    # pairs just within reach, in every direction and at every place against the grids'
    # cells (the exact search after them sees only the rows they keep)
    rng = np.random.default_rng(5)
    n = 4000
    base = rng.uniform(-0.5, 0.5, (n, 7))
    step = rng.normal(size=(n, 7))
    step[: n // 2, 3:] = 0.0  # half of them moved in position only
    step *= rng.uniform(0.5, 0.999, (n, 1)) * NEAR_REPEAT / np.linalg.norm(step, axis=1)[:, None]
    feats = np.concatenate((base, base + step, rng.uniform(-0.5, 0.5, (n, 7))))
    feats[:, 3] = np.abs(feats[:, 3]) + 0.01  # r_w > 0 (no sign to try)
    crowded = _crowded(feats)
    assert crowded[: 2 * n].all()
    assert crowded[2 * n :].sum() < n // 100  # the lone rows mostly left out
