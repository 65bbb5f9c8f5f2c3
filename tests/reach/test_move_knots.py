"""The waypoints (knots) of planned moves: their store, the grid path through them, ``knots=False``.

The planner keeps its waypoints in a compact store (a slot per move and fine
position) instead of the dense (N, 8 steps + 1, nq) array it returns; these
tests compare the two representations and the answers with and without the
dense array, bit for bit.
"""

from __future__ import annotations

import numpy as np
import pytest

from gcm_pipeline.reach.deviation import gripper_radius
from gcm_pipeline.reach.move_check import check_moves
from gcm_pipeline.reach.moves import Move
from gcm_pipeline.reach.path import SUBSTEPS, _Knots, _nonzero_2d, plan_moves
from gcm_pipeline.reach.waypoints import largest_change

APPROACH = Move(distance=0.10, direction=(0, 0, -1), frame="grasp", steps=10)


@pytest.fixture(scope="module")
def moves(panda):
    """Random Panda grasps (some invalid) and their radius."""
    rng = np.random.default_rng(11)
    q0 = panda.random_configurations(150, rng)
    poses = panda.fk(q0)
    q0[3] = np.nan  # an invalid row
    return poses, q0, gripper_radius(panda)


def _bent(q, rows):
    """A 'collision' of the configuration alone: elbow and wrist bent together."""
    return np.where(q[:, 3] + q[:, 5] > 1.2, "collision_test", "")


def test_knot_store_reads_as_the_dense_array():
    """Random writes (NaN ones too) and clears: the store reads and builds as a dense array."""
    rng = np.random.default_rng(3)
    n, positions, nq = 40, 17, 3
    q0 = rng.normal(size=(n, nq))
    q0[5] = np.nan
    store, dense = _Knots(q0, positions), np.full((n, positions, nq), np.nan)
    dense[:, 0] = q0
    for _ in range(60):
        if rng.random() < 0.15:
            rows = rng.choice(n, size=5, replace=False)
            store.clear(rows)
            dense[rows, 1:] = np.nan
            continue
        rows = rng.choice(n, size=rng.integers(1, 30), replace=False)
        at = (
            rng.integers(0, positions)
            if rng.random() < 0.5
            else rng.integers(0, positions, rows.size)
        )
        values = rng.normal(size=(rows.size, nq))
        values[rng.random(rows.size) < 0.1, 0] = np.nan
        store[rows, at] = values
        dense[rows, at] = values
    have = np.isfinite(dense[:, :, 0])
    np.testing.assert_array_equal(store.have, have)
    rows = np.arange(n)[:, None]
    at = np.arange(positions)
    np.testing.assert_array_equal(store[rows, at][have], dense[have])
    assert np.isnan(store[rows, at][~have]).all()
    ok = rng.random(n) < 0.7
    want = np.where((ok[:, None] & have)[:, :, None], dense, np.nan)
    np.testing.assert_array_equal(store.dense(ok), want)


@pytest.mark.parametrize("shape", [(40, 81), (1, 5), (7, 1), (0, 4), (3, 0)])
@pytest.mark.parametrize("fill", [0.0, 0.05, 1.0])
def test_nonzero_2d_is_numpys(shape, fill):
    """The knots' flat search gives ``np.nonzero``'s rows and columns, in its order."""
    mask = np.random.default_rng(5).random(shape) < fill
    got, want = _nonzero_2d(mask), np.nonzero(mask)
    for g, w in zip(got, want, strict=True):
        assert g.dtype == w.dtype
        np.testing.assert_array_equal(g, w)


@pytest.mark.parametrize("rows", [0, 1, 500])
def test_largest_change_is_numpys_max(rows):
    """Per row, the largest joint change: ``np.max(np.abs(q - ref), axis=1)``, NaN included."""
    rng = np.random.default_rng(8)
    q, ref = rng.normal(size=(2, rows, 7))
    if rows > 3:
        q[1, 4], ref[2, 0], q[3, 6] = np.nan, np.nan, np.inf
    want = np.max(np.abs(q - ref), axis=1)
    assert largest_change(q, ref).tobytes() == want.tobytes()


def _grid_path_from_dense(knots, steps):
    """The grid points on the piecewise linear path through dense knots (the former algorithm)."""
    fine_steps = knots.shape[1] - 1
    have = np.isfinite(knots[:, :, 0])
    idx = np.arange(fine_steps + 1)
    prev = np.maximum.accumulate(np.where(have, idx, 0), axis=1)
    nxt = np.minimum.accumulate(np.where(have, idx, fine_steps)[:, ::-1], axis=1)[:, ::-1]
    grid = np.arange(steps + 1) * SUBSTEPS
    pa, pb = prev[:, grid], nxt[:, grid]
    rows = np.arange(knots.shape[0])[:, None]
    ka, kb = knots[rows, pa], knots[rows, pb]
    f = ((grid - pa) / np.maximum(pb - pa, 1))[:, :, None]
    return ka + f * (kb - ka)


@pytest.mark.parametrize("grid_knots", [False, True])
def test_grid_path_is_the_knots_interpolation_to_the_bit(panda, moves, grid_knots):
    poses, q0, radius = moves
    plan = plan_moves(panda, poses, q0, APPROACH, gripper_radius=radius, grid_knots=grid_knots)
    ok = np.flatnonzero(plan.ok)
    assert ok.size >= 50
    if not grid_knots:  # split segments put waypoints between the grid points
        assert (np.isfinite(plan.knots[ok, :, 0]).sum(axis=1) > 2).any()
    want = _grid_path_from_dense(plan.knots[ok], APPROACH.steps)
    assert want.tobytes() == plan.q_path[ok].tobytes()


@pytest.mark.parametrize("move", [APPROACH, Move(distance=0.0, steps=3)])
def test_without_knots_the_same_answers(panda, moves, move):
    """``knots=False`` leaves out the waypoints and changes nothing else, to the bit."""
    poses, q0, radius = moves
    for grid_knots in (False, True):
        kw = dict(gripper_radius=radius, grid_knots=grid_knots, knot_check=_bent)
        full = plan_moves(panda, poses, q0, move, **kw)
        bare = plan_moves(panda, poses, q0, move, knots=False, **kw)
        assert bare.knots is None and full.knots.shape == (len(poses), 8 * move.steps + 1, 7)
        for name in ("ok", "reason", "failed_step", "q_path", "deviation", "waypoints"):
            a, b = getattr(full, name), getattr(bare, name)
            assert a.dtype == b.dtype and a.tobytes() == b.tobytes(), name
    full = check_moves(panda, poses, q0, move, _bent, gripper_radius=radius)
    bare = check_moves(panda, poses, q0, move, _bent, gripper_radius=radius, knots=False)
    assert bare.knots is None
    if move.distance:
        assert (full.reason == "collision_test").any() and full.ok.sum() >= 20
    for name in ("ok", "reason", "failed_step", "q_end", "q_path", "deviation"):
        a, b = getattr(full, name), getattr(bare, name)
        assert a.dtype == b.dtype and a.tobytes() == b.tobytes(), name
