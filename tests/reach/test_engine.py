"""The reachability engine: sequence, retreat, diagnostics, workers and chunks (real Panda)."""

from __future__ import annotations

import os
import signal

import numpy as np
import pytest
from helpers import ROOT
from poses import backward_poses

from gcm_pipeline.config import EnvironmentConfig, ObjectConfig, load_config
from gcm_pipeline.errors import InputError, WorkerLostError
from gcm_pipeline.geometry.dualquat import dq_to_matrix
from gcm_pipeline.pipeline import generate_candidates, make_checker
from gcm_pipeline.reach import engine as engine_module
from gcm_pipeline.reach.engine import (
    _RAN_EVERY_SEED,
    AUTO_PROBE_SHARE,
    ReachabilityEngine,
    available_cores,
)
from gcm_pipeline.reach.moves import Move, move_poses
from gcm_pipeline.reach.workers import IdleProbe, auto_workers, guided_chunks, quota_cores
from gcm_pipeline.robot.ik import solve_ik, verify_solutions

BOTTLE = {
    "shape": "cylinder",
    "dims": {"radius": 0.035, "height": 0.22},
    "pose": {"xyz": [0.5, 0, 0]},
}
APPROACH = Move(distance=0.10, direction=(0, 0, -1), frame="grasp", steps=10)
LIFT = Move(distance=0.10, direction=(0, 0, 1), frame="base", steps=10, holding=True)


def _side_grasps():
    """The bottle example's 72 side grasps (world = base frame)."""
    cfg = load_config(ROOT / "configs" / "bottle_side.yaml")
    return dq_to_matrix(generate_candidates(cfg)["dq"])


@pytest.fixture(scope="module")
def robot(panda):
    """The shared Panda (conftest.py) under this module's name."""
    return panda


@pytest.fixture(scope="module")
def checker(robot):
    return make_checker(robot, EnvironmentConfig(), ObjectConfig.model_validate(BOTTLE))


@pytest.fixture(scope="module")
def grasps():
    return _side_grasps()


@pytest.fixture(scope="module")
def result(robot, checker, grasps):
    eng = ReachabilityEngine(robot, checker, approach=APPROACH, retreat=LIFT, chunk_size=16)
    return eng.run(grasps)


def test_reachable_rows_pass_every_check(robot, checker, grasps, result):
    ok = result.reachable
    assert 5 <= ok.sum() < len(grasps)
    pe, re, inside = verify_solutions(robot, result.q[ok], grasps[ok])
    assert np.all(pe <= 1e-4) and np.all(re <= 1e-3) and inside.all()
    assert np.all(checker.check(result.q[ok]) == "")
    assert np.all(result.reason[ok] == "")
    assert np.all(result.clearance[ok] > 0) and np.isnan(result.clearance[~ok]).all()
    # pre-grasp and retreat configurations reach their poses
    pre = move_poses(grasps[ok], APPROACH.offsets(grasps[ok]), 10)[-1]
    up = move_poses(grasps[ok], LIFT.offsets(grasps[ok]), 10)[-1]
    for q_end, want in ((result.q_pregrasp[ok], pre), (result.q_retreat[ok], up)):
        reached = robot.fk_pinocchio(q_end)
        assert np.max(np.linalg.norm(reached[:, :3, 3] - want[:, :3, 3], axis=1)) < 2e-3
    assert np.isnan(result.q_pregrasp[~ok]).all() and np.isnan(result.q_retreat[~ok]).all()


def test_unreachable_rows_keep_their_rejected_solution(robot, checker, grasps, result):
    bad = ~result.reachable
    assert np.isnan(result.q[bad]).all()
    had_ik = bad & ~np.isin(result.reason, ["no_ik", "out_of_reach", "joint_limits"])
    assert had_ik.any()
    assert np.isfinite(result.q_rejected[had_ik]).all()
    assert np.isnan(result.q_rejected[~had_ik]).all()
    # a row rejected for a collision: its kept solution really collides that way
    coll = np.flatnonzero(np.char.startswith(result.reason.astype(str), "collision"))
    if coll.size:
        assert np.array_equal(checker.check(result.q_rejected[coll]), result.reason[coll])
    pe, _, _ = verify_solutions(robot, result.q_rejected[had_ik], grasps[had_ik])
    assert np.all(pe <= 1e-4)


def test_retreat_removes_grasps_and_down_fails(robot, checker, grasps, result):
    eng = ReachabilityEngine(robot, checker, approach=APPROACH)
    no_retreat = eng.run(grasps)
    assert np.all(no_retreat.reachable >= result.reachable)
    assert np.isnan(no_retreat.q_retreat).all()
    lost = no_retreat.reachable & ~result.reachable
    assert np.all(result.reason[lost] == "retreat")
    # pushing the held bottle down into the table: nothing survives the retreat
    down = Move(distance=0.10, direction=(0, 0, -1), frame="base", steps=10, holding=True)
    pushed = ReachabilityEngine(robot, checker, approach=APPROACH, retreat=down).run(grasps)
    assert not pushed.reachable.any()
    assert set(pushed.reason[no_retreat.reachable]) == {"retreat"}


def test_moves_proved_beyond_reach_change_no_result(robot, checker, grasps, monkeypatch):
    """A 30 cm approach puts many pre-grasps beyond the arm's reach: the engine fails
    them without planning and tries no other solution for them; the result is the
    one of planning every move and trying every alternative."""
    import gcm_pipeline.reach.moves as approach_module
    import gcm_pipeline.reach.path as path_module
    import gcm_pipeline.reach.solution_checks as checks_module

    long_approach = Move(distance=0.30, direction=(0, 0, -1), frame="grasp", steps=10)
    proved = approach_module.unreachable_ends(robot, grasps, long_approach, 1e-4, 1e-3)
    fast = ReachabilityEngine(robot, checker, approach=long_approach, retreat=LIFT).run(grasps)
    assert np.count_nonzero(proved & (fast.reason == "approach")) >= 10
    assert not (proved & fast.reachable).any()

    def nothing_proved(robot, poses, *args):
        return np.zeros(len(poses), dtype=bool)

    monkeypatch.setattr(path_module, "unreachable_ends", nothing_proved)
    monkeypatch.setattr(checks_module, "unreachable_ends", nothing_proved)
    slow = ReachabilityEngine(robot, checker, approach=long_approach, retreat=LIFT).run(grasps)
    for a, b in zip(fast, slow, strict=True):
        if a is None:
            assert b is None
        else:
            np.testing.assert_array_equal(a, b)


def test_workers_and_chunks_do_not_change_the_result(robot, checker, grasps, result):
    assert available_cores() >= 1
    for kw in ({"workers": 2, "chunk_size": 7}, {"workers": 1, "chunk_size": 1000}):
        with ReachabilityEngine(robot, checker, approach=APPROACH, retreat=LIFT, **kw) as eng:
            other = eng.run(grasps)
        for a, b in zip(result, other, strict=True):
            if a is None:
                assert b is None
            else:
                np.testing.assert_array_equal(a, b)


@pytest.mark.parametrize(
    ("n", "most", "workers"), [(56214, 8192, 2), (10, 3, 2), (5, 8, 4), (9, 4, 1)]
)
def test_chunks_cover_every_target_once_in_order(n, most, workers):
    chunks = guided_chunks(n, most, workers)
    np.testing.assert_array_equal(np.concatenate(chunks), np.arange(n))
    sizes = [c.size for c in chunks]
    assert max(sizes) <= most
    # on several workers they shrink towards the end; one worker takes the largest
    assert sizes == sorted(sizes, reverse=True)
    if workers == 1:
        assert sizes[:-1] == [most] * (len(sizes) - 1)


@pytest.mark.parametrize(
    ("n", "workers", "sizes"),
    [
        (2048, 2, [2048]),
        (2049, 2, [1025, 1024]),
        (3001, 2, [1501, 1500]),
        (6000, 3, [2000, 2000, 2000]),
        (2100, 64, [256] * 8 + [52]),  # not 33 chunks of 64
        (5000, 2, [2048, 2048, 904]),
    ],
)
def test_a_few_thousand_targets_are_shared_out_equally(n, workers, sizes):
    # one chunk per worker, not 2,048 and the rest on one of them; beyond
    # workers * most // 4 the guided chunks of test_chunks_cover_every_target_once_in_order
    assert [c.size for c in guided_chunks(n, 8192, workers)] == sizes


def test_neighbours_seed_from_final_solutions(robot, checker, grasps):
    eng = ReachabilityEngine(robot, checker, approach=APPROACH)
    n = len(grasps)
    targets = np.concatenate([grasps, grasps])
    nb = np.concatenate([np.full((n, 1), -1), np.arange(n)[:, None]])
    calls = []
    res = eng.run(targets, neighbours=nb, progress=calls.append)
    assert sum(calls) == 2 * n
    # a copy seeded with its twin's checked solution lands on that solution
    both = res.reachable[:n] & res.reachable[n:]
    assert both.sum() >= 5
    np.testing.assert_allclose(res.q[n:][both], res.q[:n][both], atol=1e-9)


def test_small_seed_budget_where_every_neighbour_failed_ik(robot):
    """A row whose neighbours all failed IK after their own full seed schedule (no_ik,
    joint_limits) gets no random restarts and 2 library seeds; a row with a solved
    neighbour, none, or neighbours only out of reach (no seed ran) keeps the full
    schedule. (The LM schedule alone: the closed-form round would solve these rows.)"""
    lm = {"analytic": False}
    targets = robot.fk_pinocchio(robot.random_configurations(4000, np.random.default_rng(0)))
    with_restarts = solve_ik(robot, targets, **lm)
    without = solve_ik(robot, targets, random_restarts=0, **lm)
    rescued = targets[with_restarts.success & ~without.success]
    assert len(rescued) >= 3  # targets only the random restarts reach
    k = len(rescued)
    # 0.5 m from the shoulder, the hand pointing back at it: not proved out of reach,
    # but some are reached by no seed (joint_limits)
    behind = backward_poses(robot, 400, np.random.default_rng(1), 0.5)
    tried = solve_ik(robot, behind, **lm)
    failing = behind[np.isin(tried.reason, _RAN_EVERY_SEED)][:k]
    assert len(failing) == k
    far = rescued.copy()
    far[:, :3, 3] += 2.0  # out of reach: rejected before any seed
    eng = ReachabilityEngine(robot, ik_options=lm)
    rows = np.concatenate([failing, far, rescued, rescued, rescued])
    nb = np.full((5 * k, 1), -1)
    nb[2 * k : 3 * k, 0] = np.arange(k)  # neighbours that failed IK after every seed
    nb[3 * k : 4 * k, 0] = k + np.arange(k)  # neighbours out of reach
    res = eng.run(rows, neighbours=nb)
    assert set(res.reason[:k]) <= {"no_ik", "joint_limits"}
    assert set(res.reason[k : 2 * k]) == {"out_of_reach"}
    small = solve_ik(robot, rescued, random_restarts=0, library_seeds=2, **lm)
    full = solve_ik(robot, rescued, **lm)
    assert not small.success.all() and full.success.all()
    np.testing.assert_array_equal(res.reachable[2 * k : 3 * k], small.success)
    np.testing.assert_array_equal(res.q[2 * k : 3 * k], small.q)
    for part in (slice(3 * k, 4 * k), slice(4 * k, 5 * k)):  # out of reach; no neighbours
        np.testing.assert_array_equal(res.reachable[part], full.success)
        np.testing.assert_array_equal(res.q[part], full.q)


def test_engine_errors(robot):
    with pytest.raises(InputError, match="workers"):
        ReachabilityEngine(robot, workers=0)
    with pytest.raises(InputError, match="chunk_size"):
        ReachabilityEngine(robot, chunk_size=0)
    with pytest.raises(InputError, match="position_tolerance"):
        ReachabilityEngine(robot, position_tolerance=-1)
    eng = ReachabilityEngine(robot)
    with pytest.raises(InputError, match="neighbours"):
        eng.run(robot.fk(robot.home), neighbours=np.array([[3]]))
    with pytest.raises(InputError, match="seeds"):
        eng.run(robot.fk(robot.home), seeds=np.zeros((1, 1, 3)))
    assert "ReachabilityEngine(robot='panda'" in repr(eng)


def _dies_in_a_worker(parent: int):
    """A validator that kills the process it runs in, unless that is ``parent``."""

    def validator(q):
        if os.getpid() != parent:
            os.kill(os.getpid(), signal.SIGKILL)  # what the out-of-memory killer does
        return np.full(len(q), "")

    return validator


def test_a_worker_that_dies_stops_the_run_instead_of_hanging(robot, checker, grasps):
    # the standard pool replaces the dead worker and waits for its task for ever
    eng = ReachabilityEngine(
        robot, checker, validator=_dies_in_a_worker(os.getpid()), workers=2, chunk_size=4
    )
    with eng, pytest.raises(WorkerLostError, match=r"died \(killed by SIGKILL\).*memory"):
        eng.run(grasps)
    # the engine starts new workers for the next run, which completes
    with ReachabilityEngine(robot, checker, workers=2, chunk_size=4) as eng:
        assert eng.run(grasps).reachable.any()


def test_a_worker_that_dies_stops_solve_ik(robot, grasps):
    with pytest.raises(WorkerLostError, match="SIGKILL"):
        solve_ik(robot, grasps, workers=2, validator=_dies_in_a_worker(os.getpid()))


def test_no_more_workers_start_than_there_are_chunks(robot, checker, grasps):
    n = len(grasps)
    with ReachabilityEngine(robot, checker, workers=64, chunk_size=100) as eng:
        eng.run(grasps)
        assert eng._pool_size == len(guided_chunks(n, 100, 64)) == 3  # forked 3, not 64
        eng.chunk_size = 16
        more = eng.run(grasps)  # more chunks: a larger pool
        assert eng._pool_size == len(guided_chunks(n, 16, 64)) == 18
        np.testing.assert_array_equal(more.reachable, eng.run(grasps).reachable)


@pytest.mark.parametrize(
    ("n", "cores", "idle", "workers"),
    [
        (56294, 2, 2.0, 2),  # dense bottle, idle machine: both cores
        (56294, 2, 1.85, 2),  # a core counts when 80 % of it is idle
        (56294, 2, 1.7, 1),  # another job takes a third of a core: one worker
        (56294, 2, 1.0, 1),  # a CPU hog on one core
        (56294, 2, 0.0, 1),  # every core busy
        (56294, 2, None, 2),  # load not readable: the cores
        (56294, 8, 8.0, 3),  # 3 workers of two full chunks each
        (16383, 2, 2.0, 1),  # under two full chunks per worker left: not worth forking
        (32767, 2, 2.0, 1),
        (32768, 2, 2.0, 2),  # a run of 40,960: its first chunk, then 2 x 2 chunks
        (10**6, 64, 7.5, 7),
        (10**6, 1, 4.0, 1),  # one core: this process only
    ],
)
def test_auto_workers_from_size_and_idle_cores(n, cores, idle, workers):
    # n: the targets left after the first chunk, which auto solves on this process
    assert auto_workers(n, 8192, cores, idle) == workers


def test_idle_probe_is_within_the_cores_this_process_may_use():
    probe = IdleProbe()
    sum(i * i for i in range(200_000))  # this process's own work is not counted as busy
    idle = probe.idle_cores()
    assert idle is None or 0.0 <= idle <= len(os.sched_getaffinity(0))


def test_auto_decides_after_the_first_chunk_and_keeps_the_answers(robot, checker, grasps, result):
    # chunks of 8: enough of them for auto to consider a second worker, whatever it
    # decides from the load it reads; the answers are one worker's either way
    eng = ReachabilityEngine(robot, checker, approach=APPROACH, retreat=LIFT, workers="auto")
    eng.chunk_size = 8
    probe = 8 // AUTO_PROBE_SHARE  # solved on this process while auto reads the cores
    sizes: list[int] = []
    with eng:
        other = eng.run(grasps, progress=sizes.append)
        left = len(grasps) - probe
        cores = eng.workers  # the cores this process may use, within a CPU quota
        assert eng.workers_used == auto_workers(left, 8, cores, eng.idle_seen)
        assert (eng._pool is not None) == (eng.workers_used > 1)
    one = [c.size for c in guided_chunks(len(grasps), 8, 1)]
    if cores > 1:
        assert eng.idle_seen is None or 0.0 <= eng.idle_seen <= cores
        if eng.workers_used > 1:  # the probe's chunk, the rest chunked for the choice
            assert sizes == [probe] + [c.size for c in guided_chunks(left, 8, eng.workers_used)]
        else:  # one worker's chunks, the first cut in two
            assert sizes == [probe, one[0] - probe] + one[1:]
    else:  # nothing probed: exactly one worker's chunks
        assert sizes == one
    for a, b in zip(result, other, strict=True):
        if a is None:
            assert b is None
        else:
            np.testing.assert_array_equal(a, b)


@pytest.mark.parametrize("chunk", [1, 2, 3, 8])
@pytest.mark.parametrize("idle", [0.0, None])
def test_auto_chunks_for_either_decision(robot, checker, grasps, result, monkeypatch, chunk, idle):
    # the load auto reads, fixed: 0 idle cores (one worker) or unreadable (every core)
    monkeypatch.setattr(IdleProbe, "idle_cores", lambda self: idle)
    eng = ReachabilityEngine(robot, checker, approach=APPROACH, retreat=LIFT, workers="auto")
    eng.chunk_size = chunk
    probe = max(1, chunk // AUTO_PROBE_SHARE)
    sizes: list[int] = []
    with eng:
        other = eng.run(grasps, progress=sizes.append)
        cores = eng.workers
    assert sum(sizes) == len(grasps) and min(sizes) > 0
    one = [c.size for c in guided_chunks(len(grasps), chunk, 1)]
    if cores == 1:
        assert sizes == one
    elif idle == 0.0:  # the probe's chunk, the rest of the first one, then one worker's
        assert eng.workers_used == 1
        assert sizes == ([probe, chunk - probe] if chunk > probe else [probe]) + one[1:]
    else:
        assert eng.workers_used == min(cores, (len(grasps) - probe) // (2 * chunk))
    np.testing.assert_array_equal(other.reachable, result.reachable)
    np.testing.assert_array_equal(other.q, result.q)


def _two_phases(n: int, first: int) -> np.ndarray:
    """Neighbours (n, 1) making a run of two phases: rows ``0..first-1`` alone, then the rest."""
    nb = np.full((n, 1), -1)
    nb[first:, 0] = np.arange(n - first) % first
    return nb


@pytest.mark.parametrize("idle", [0.0, None])
def test_auto_decides_from_the_runs_start_without_a_probe_chunk(
    robot, checker, grasps, monkeypatch, idle
):
    # a first phase solved on this process, read long enough: the second phase is
    # chunked for the decision at once, with no quarter chunk solved first
    monkeypatch.setattr(engine_module, "AUTO_WATCH_S", 0.0)
    monkeypatch.setattr(IdleProbe, "idle_cores", lambda self: idle)
    nb = _two_phases(len(grasps), 8)
    one = ReachabilityEngine(robot, checker, approach=APPROACH, retreat=LIFT, chunk_size=4)
    want = one.run(grasps, neighbours=nb)
    eng = ReachabilityEngine(robot, checker, approach=APPROACH, retreat=LIFT, workers="auto")
    eng.chunk_size = 4
    sizes: list[int] = []
    with eng:
        got = eng.run(grasps, neighbours=nb, progress=sizes.append)
        cores, used = eng.workers, eng.workers_used
    rest = len(grasps) - 8
    first = [c.size for c in guided_chunks(8, 4, 1)]  # too few for a second worker
    if cores == 1 or idle == 0.0:  # exactly the chunks of workers: 1
        assert used == 1
        assert sizes == first + [c.size for c in guided_chunks(rest, 4, 1)]
    else:
        assert used == min(cores, rest // 8) > 1
        assert sizes == first + [c.size for c in guided_chunks(rest, 4, used)]
    for field in ("reachable", "reason", "q", "q_pregrasp", "q_retreat", "clearance"):
        np.testing.assert_array_equal(getattr(got, field), getattr(want, field))


def test_auto_reads_an_old_reading_afresh(robot, checker, grasps, monkeypatch):
    # a first phase that took longer than AUTO_WATCH_RECENT_S: the load may have
    # changed, so the second phase reads the cores again over a quarter chunk
    monkeypatch.setattr(engine_module, "AUTO_WATCH_S", 0.0)
    monkeypatch.setattr(engine_module, "AUTO_WATCH_RECENT_S", -1.0)  # every reading is old
    monkeypatch.setattr(IdleProbe, "idle_cores", lambda self: 0.0)  # one worker
    eng = ReachabilityEngine(robot, checker, approach=APPROACH, retreat=LIFT, workers="auto")
    eng.chunk_size = 4
    if eng.workers < 2:
        pytest.skip("one core: auto never reads the load")
    sizes: list[int] = []
    with eng:
        eng.run(grasps, neighbours=_two_phases(len(grasps), 8), progress=sizes.append)
    assert eng.workers_used == 1
    rest = [c.size for c in guided_chunks(len(grasps) - 8, 4, 1)]
    assert sizes == [4, 4] + [1, 3] + rest[1:]  # the first phase, then probe + rest of chunk


def test_auto_probes_again_after_its_workers_ran(robot, checker, grasps, monkeypatch):
    # workers that ran in the first phase would read as other jobs' load: the second
    # phase reads the cores afresh, over a quarter chunk solved on this process
    monkeypatch.setattr(engine_module, "AUTO_WATCH_S", 0.0)
    monkeypatch.setattr(IdleProbe, "idle_cores", lambda self: None)  # every core idle
    eng = ReachabilityEngine(robot, checker, approach=APPROACH, retreat=LIFT, workers="auto")
    eng.chunk_size = 4
    if eng.workers < 2:
        pytest.skip("one core: auto never forks")
    started: list[IdleProbe] = []
    real = IdleProbe.__init__

    def count(self: IdleProbe) -> None:
        started.append(self)
        real(self)

    monkeypatch.setattr(IdleProbe, "__init__", count)
    sizes: list[int] = []
    with eng:
        eng.run(grasps, neighbours=_two_phases(len(grasps), 40), progress=sizes.append)
    assert eng.workers_used > 1
    assert len(started) == 2  # the run's, then the second phase's
    at = np.cumsum(sizes)
    assert 40 in at  # the first phase's chunks end there
    second = sizes[int(np.flatnonzero(at == 40)[0]) + 1 :]
    assert second[0] == 1  # the probe's chunk: 4 // AUTO_PROBE_SHARE


def test_auto_runs_a_small_set_on_this_process(robot, checker, grasps, result):
    with ReachabilityEngine(robot, checker, approach=APPROACH, retreat=LIFT, workers="auto") as eng:
        other = eng.run(grasps)
        assert eng.workers == quota_cores(available_cores()) and eng.workers_used == 1
        assert eng._pool is None and eng.idle_seen is None  # nothing forked, nothing read
    np.testing.assert_array_equal(other.reachable, result.reachable)


@pytest.mark.parametrize(
    ("files", "cores", "want"),
    [
        ({}, 2, 2),  # no cgroup files: the cores
        ({"cpu.max": "max 100000"}, 2, 2),  # v2, no quota
        ({"cpu.max": "150000 100000"}, 2, 1),  # 1.5 CPUs: one full core
        ({"cpu.max": "50000 100000"}, 2, 1),  # under a core: still one process
        ({"cpu.max": "400000 100000"}, 2, 2),  # more quota than cores: the cores
        ({"cpu.max": "250000 100000"}, 8, 2),
        ({"cpu/cpu.cfs_quota_us": "-1", "cpu/cpu.cfs_period_us": "100000"}, 2, 2),  # v1, none
        ({"cpu/cpu.cfs_quota_us": "100000", "cpu/cpu.cfs_period_us": "100000"}, 4, 1),
        ({"cpu/cpu.cfs_quota_us": "300000", "cpu/cpu.cfs_period_us": "100000"}, 4, 3),
        ({"cpu.max": "garbage"}, 2, 2),  # unreadable: the cores
    ],
)
def test_auto_honours_a_cgroup_cpu_quota(tmp_path, files, cores, want):
    for name, text in files.items():
        (tmp_path / name).parent.mkdir(parents=True, exist_ok=True)
        (tmp_path / name).write_text(text + "\n")
    assert quota_cores(cores, str(tmp_path)) == want
