#!/usr/bin/env python
"""Benchmark: the reachability stage against its per-core limit.

One run measures, for each robot of ``--robot`` (default ``both``), on the
table and the bottle of its run config (``CONFIGS``): the Panda of
``configs/bottle_side.yaml`` (the world of ``bench_collision.py``) and the UR5
with its Robotiq 2F-85 of ``configs/bottle_side_ur5.yaml`` (the same world;
robot and tool built by the pipeline from the config); the dense work is
``bench_pipeline.DENSE`` on either config. On each robot:

* **IK per pose** on 2,000 reachable targets (forward kinematics of random
  in-limit configurations): gcm's default backend (batched LM), and, when
  ``frankik`` is installed (``pip install ".[bench]"``), the analytic frankik
  library called per pose (its ``fk`` gives gcm's grasp frame, its IK takes the
  flange: the target times the hand's inverse offset): ``ik_sample_q7`` (60
  samples of q7 over its range, every branch: the library's full IK) and ``ik_full`` with the
  target's own q7 given (the closed form alone, every branch: a lower bound
  that needs q7 from elsewhere); a success is a finite solution whose frankik FK
  is within 0.1 mm / 1 mrad of the target. On the UR5 (a 6R arm: gcm's
  default backend is itself EAIK's closed form, then LM where it has no
  branch), EAIK's closed form alone when ``eaik`` is installed (the robot built
  from Pinocchio's kinematics as ``bench_branches.py`` does; every branch,
  ``calculate_IK`` one pose per call and ``calculate_IK_batched`` on one
  thread; a success is an exact branch with a 2π copy inside the limits on
  the target). ``gcm_move_end_*``: gcm's IK of the end of an approach move
  (the pose 10 cm back along its approach axis) from the grasp's
  configuration, as the stage solves it. The model's ``t_ik`` is the fastest
  IK with recall >= 99 % (frankik's closed form given q7 is not an IK of the
  pose alone).
* **Collision checks per configuration**, on two sets: ``front`` (random
  configurations with the hand in front of the robot above the table, as
  ``bench_collision.py``) and ``stage`` (a random sample of the configurations
  the reachability stage really checked on the dense bottle, recorded by the
  counting run below). On each: gcm's :meth:`CollisionChecker.check` on the
  whole array (its use in the stage) and one configuration per call;
  Pinocchio's loop (``pin.computeCollisions`` over every pair, stop at first, on
  the first ``--loop-configs``), timed with Pinocchio's default requests (the
  speed figure); coal's exact answer, which every comparison uses
  (``gcm_differs_from_pinocchio``, ``colliding_fraction_coal``, the outer
  spheres, VAMP's disagreements with coal), is the same loop asking coal's
  complete answer (contact information on, ``bench_collision.complete_answers``:
  without it coal's ``collide`` can call overlapping geometry free), untimed;
  ``pinocchio_default_missed`` counts the configurations the timed loop called
  free that the complete answer finds colliding; and VAMP's Panda
  checker where installed (a venv of its own given by
  ``--vamp-python``): through its Python binding (``vamp_py_*``,
  ``benchmarks/vamp/vamp_check.py``: ``validate``, one configuration per call,
  the binding's call cost included) and in C++ (``vamp_cpp_*``,
  ``benchmarks/vamp/vamp_bench.cc``: the same ``validate_motion<Panda, 8, 1>(q,
  q)`` one configuration per call, and ``Panda::fkcc<8>`` on blocks of 8
  distinct configurations that gcm finds free, VAMP's best case).
  VAMP's scene: the table as four cuboids around the base's footprint (see
  ``BASE_HOLE``), the bottle (a cylinder) as a capsule on the cylinder's axis
  (VAMP has no flat-capped cylinder: the capsule adds a half-ball at each
  end). VAMP approximates the links by spheres: its decisions are compared with
  coal's (``vamp_disagreements_with_coal``, first ``--loop-configs``) and with
  gcm's exact ones on the whole set (``vamp_disagreements_with_gcm``).
  VAMP is not run on the UR5 (``vamp`` says why): VAMP's ``ur5`` model is the
  bare arm, without the gripper, so it is not the robot checked here.
* **Outer spheres** (``outer_spheres``, first ``--loop-configs`` of each set):
  the configurations that the generated outer link spheres
  (:mod:`gcm_pipeline.robot.collision.link_spheres`, not yet used by the
  checker) prove free, pair by pair of the checker's collision pairs (sphere
  against sphere, or against the world box / cylinder exactly), as a fraction
  of those coal finds free; ``proven_free_but_colliding`` must be 0;
  ``pairs_touching_most_on_free``: the pairs whose spheres touch on the most
  configurations coal finds free (what keeps the spheres from proving more).
* **Approach motions in blocks** (``approach_blocks``, Panda only): VAMP's
  ``validate_motion`` (binding) on the stage's grasp -> pre-grasp joint-space
  segments (blocks of 8 interpolated configurations at its resolution), against
  gcm's ``approach``-mode check of the same interpolated configurations.
* **Checks per pose**: one run of the stage on the dense bottle (80 side
  grasps, subdivisions 28, approach 10 cm / 10 steps: ``bench_pipeline.py``'s
  work) with ``ik.workers: 1`` and :meth:`CollisionChecker.check` and
  :meth:`CollisionChecker.clearance` wrapped (in this process only, the library
  is not changed) to count the rows checked, by mode; the stage's IK calls are
  wrapped too, to count their target rows by purpose (``IK_CALLERS``). The
  wrappers also sum the wall time inside the calls: ``wall_s_per_pose`` splits
  that run's time per pose into IK by purpose, checks, clearance and ``rest``
  (the moves' planning: interior waypoints, deviation bounds, grid paths; the
  proofs that ends are out of reach; bookkeeping), the part of the stage the
  cost model below leaves out besides the moves' IK.
* **The stage's rate** (same work, one process, unwrapped, median of
  ``--repeats`` runs) as a fraction of the limit
  ``1 / (t_ik + checks_per_pose * t_check)`` with ``t_check`` the fastest
  check per configuration measured on the stage's configurations (VAMP's C++
  blocks where built; the approach-motion figure is not used: an invalid motion
  stops early, so its per-configuration cost is an estimate), and of the limit
  at gcm's own check rate (``*_at_gcm_checks``: the UR5's only limit, and the
  one to compare between the robots). ``*_with_move_ends``: the limit with
  the moves' ends (IK the stage cannot skip, ``move_ends_per_pose`` of them at
  ``t_move_end_s`` each) added.

``side_by_side`` sets the main figures of the robots next to each other;
``robots.<name>`` holds every figure of one robot, with the load average over
its part of the run.

Rates of different runs are not comparable (the machine is shared): the report
gives ratios of one run, medians of ``--repeats``, and the load average.

Run from the repository root: ``python benchmarks/bench_limit.py
[--robot panda|ur5|both] [--vamp-python VENV/bin/python]`` (a few minutes per
robot); writes ``benchmarks/results/limit.json``.
"""

from __future__ import annotations

import argparse
import contextlib
import importlib
import json
import os
import platform
import subprocess
import sys
import tempfile
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pinocchio as pin

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))

from bench_collision import complete_answers, front_configurations, timed  # noqa: E402
from bench_pipeline import DENSE, stage_run  # noqa: E402

from gcm_pipeline.config import load_config  # noqa: E402
from gcm_pipeline.pipeline import make_checker, robot_from_config  # noqa: E402
from gcm_pipeline.reach.waypoints import end_of_move  # noqa: E402
from gcm_pipeline.robot.collision import CollisionChecker  # noqa: E402
from gcm_pipeline.robot.collision.link_spheres import geometry_spheres  # noqa: E402
from gcm_pipeline.robot.ik import solve_ik  # noqa: E402
from gcm_pipeline.robot.ik.analytic_6r import forget_answers, nearest_copy  # noqa: E402
from gcm_pipeline.robot.model import Robot  # noqa: E402

VAMP_SCRIPT = ROOT / "benchmarks" / "vamp" / "vamp_check.py"
#: The run config of each robot: its arm, tool and world (the dense work: ``DENSE``).
CONFIGS = {
    "panda": ROOT / "configs" / "bottle_side.yaml",
    "ur5": ROOT / "configs" / "bottle_side_ur5.yaml",
}
#: Why the UR5 has no VAMP figures.
NO_VAMP_UR5 = (
    "not run: VAMP's ur5 model is the bare arm (no gripper), not the UR5 with its "
    "Robotiq 2F-85 checked here"
)
TOL_P, TOL_R = 1e-4, 1e-3
#: frankik's q7 sampling span [deg] (60 samples): the arm's whole q7 range; the
#: library's default, 40, finds only 54-59 % of random reachable targets.
Q7_SPAN_DEG = 330


# --- IK -----------------------------------------------------------------------------------


def _frankik_ok(frankik: Any, target: np.ndarray, q: Any) -> bool:
    q = np.asarray(q, dtype=float).reshape(-1, 7)
    q = q[np.all(np.isfinite(q), axis=1)]
    for qi in q:
        t = frankik.fk(qi)
        rot = np.linalg.norm(pin.log3(t[:3, :3].T @ target[:3, :3]))
        if np.linalg.norm(t[:3, 3] - target[:3, 3]) <= TOL_P and rot <= TOL_R:
            return True
    return False


def ik_figures(name: str, robot: Robot, n: int, repeats: int) -> dict[str, Any]:
    """Seconds per pose and recall of each IK on ``n`` reachable targets.

    gcm's default backend and its move end on every arm; frankik on the Panda,
    EAIK's closed form on a 6R arm.
    """
    rng = np.random.default_rng(0)
    q = robot.random_configurations(n, rng)
    targets = robot.fk_pinocchio(q)
    solve_ik(robot, targets[:50])  # compiled kernels loaded before timing
    # each repeat solves as the first did (a 6R solver keeps its last poses' answers)
    dt, res = timed(lambda: (forget_answers(robot), solve_ik(robot, targets))[1], repeats)
    out: dict[str, Any] = {
        "targets": n,
        "gcm_s_per_pose": dt / n,
        "gcm_recall": float(np.mean(res.success)),
    }
    # the end of an approach move: the pose 10 cm back along its own approach
    # axis, solved from the grasp's configuration as the stage does
    ends = targets.copy()
    ends[:, :3, 3] -= 0.1 * targets[:, :3, 2]
    dt, (_, reached) = timed(
        lambda: (
            forget_answers(robot),
            end_of_move(robot, ends, q, "pinocchio", TOL_P, TOL_R, {}),
        )[1],
        repeats,
    )
    out["gcm_move_end_s_per_pose"] = dt / n
    out["gcm_move_end_reached"] = float(np.mean(reached))
    if name == "panda":
        out.update(frankik_figures(q, repeats))
    elif robot.nq == 6:
        out.update(eaik_figures(robot, q, targets, repeats))
    return out


def frankik_figures(q: np.ndarray, repeats: int) -> dict[str, Any]:
    """The Panda's analytic frankik library per pose (see the module doc), or why not."""
    try:
        import frankik
    except ImportError:
        return {"frankik": "not installed"}
    n, out = len(q), dict[str, Any]()
    # frankik's fk gives the hand's TCP (gcm's grasp frame); its IK takes the
    # flange: the TCP pose times the inverse of the hand's offset
    c = np.sqrt(0.5)
    hand = np.array([[c, c, 0, 0], [-c, c, 0, 0], [0, 0, 1, 0.1034], [0, 0, 0, 1]])
    tcp = [np.asarray(frankik.fk(qi)) for qi in q]
    flange = [t @ np.linalg.inv(hand) for t in tcp]
    home = np.asarray(frankik.kQDefault, dtype=float)
    dt, sols = timed(
        lambda: [frankik.ik_sample_q7(t, home, False, 60, Q7_SPAN_DEG, True) for t in flange],
        repeats,
    )
    out["frankik_sampled_q7_s_per_pose"] = dt / n
    out["frankik_sampled_q7_samples_span_deg"] = [60, Q7_SPAN_DEG]
    out["frankik_sampled_q7_recall"] = float(
        np.mean([_frankik_ok(frankik, t, s) for t, s in zip(tcp, sols, strict=True)])
    )
    dt, sols = timed(
        lambda: [
            frankik.ik_full(t, home, float(qi[6]), False) for t, qi in zip(flange, q, strict=True)
        ],
        repeats,
    )
    out["frankik_closed_form_given_q7_s_per_pose"] = dt / n
    out["frankik_closed_form_given_q7_recall"] = float(
        np.mean([_frankik_ok(frankik, t, s) for t, s in zip(tcp, sols, strict=True)])
    )
    return out


def _eaik_recall(robot: Robot, targets: np.ndarray, sols: list[Any]) -> float:
    """Share of targets with an exact EAIK branch, at a copy inside the limits, on the pose."""
    ok = np.zeros(len(targets), dtype=bool)
    for i, (t, sol) in enumerate(zip(targets, sols, strict=True)):
        qs = np.asarray(sol.Q, dtype=float).reshape(-1, robot.nq)
        qs = qs[~np.asarray(sol.is_LS, dtype=bool).reshape(-1)]
        if not len(qs):
            continue
        home = np.broadcast_to(robot.home, qs.shape)
        qs = nearest_copy(qs, home, robot.lower, robot.upper)
        qs = qs[np.all(np.isfinite(qs), axis=1)]
        if not len(qs):
            continue
        fk = robot.fk_pinocchio(qs)
        dp = np.linalg.norm(fk[:, :3, 3] - t[:3, 3], axis=1)
        dr = [np.linalg.norm(pin.log3(t[:3, :3].T @ f[:3, :3])) for f in fk]
        ok[i] = bool(np.any((dp <= TOL_P) & (np.asarray(dr) <= TOL_R)))
    return float(np.mean(ok))


def eaik_figures(robot: Robot, q: np.ndarray, targets: np.ndarray, repeats: int) -> dict[str, Any]:
    """EAIK's closed form (every branch) per pose on a 6R arm, or why there is none.

    The EAIK robot is built from Pinocchio's kinematics
    (``bench_branches.eaik_from_pinocchio``); called one pose per call
    (``calculate_IK``) and on the whole array on one thread
    (``calculate_IK_batched``). A target is solved when some exact branch, at
    its 2π copy inside the limits nearest home, is on the pose (0.1 mm / 1 mrad).
    """
    try:
        from bench_branches import eaik_from_pinocchio
    except ImportError:
        return {"eaik": "not installed"}
    bot = eaik_from_pinocchio(robot)
    if not bot.has_known_decomposition():
        return {"eaik": "EAIK knows no decomposition of this arm"}
    poses = [np.ascontiguousarray(t) for t in targets]
    n, out = len(poses), dict[str, Any]()
    dt, sols = timed(lambda: [bot.calculate_IK(t) for t in poses], repeats)
    out["eaik_one_per_call_s_per_pose"] = dt / n
    out["eaik_recall"] = _eaik_recall(robot, targets, sols)
    dt, sols = timed(lambda: bot.calculate_IK_batched(poses, 1), repeats)
    out["eaik_batched_one_thread_s_per_pose"] = dt / n
    out["eaik_batched_recall"] = _eaik_recall(robot, targets, sols)
    out["eaik_branches_per_pose"] = float(
        np.mean([np.count_nonzero(~np.asarray(s.is_LS, dtype=bool)) for s in sols])
    )
    return out


def best_ik(ik: dict[str, Any]) -> tuple[str, float]:
    """The fastest IK with recall >= 99 % (frankik's closed form given q7 is no full IK)."""
    options = [("gcm", ik["gcm_s_per_pose"], ik["gcm_recall"])]
    if "frankik_sampled_q7_s_per_pose" in ik:
        options.append(
            ("frankik", ik["frankik_sampled_q7_s_per_pose"], ik["frankik_sampled_q7_recall"])
        )
    if "eaik_one_per_call_s_per_pose" in ik:
        options.append(("eaik", ik["eaik_one_per_call_s_per_pose"], ik["eaik_recall"]))
        options.append(
            ("eaik_batched", ik["eaik_batched_one_thread_s_per_pose"], ik["eaik_batched_recall"])
        )
    name, t, _ = min((o for o in options if o[2] >= 0.99), key=lambda o: o[1])
    return name, t


# --- the stage: counted checks and its rate -------------------------------------------------


#: Where the stage calls IK, by purpose: the module and the name it calls.
IK_CALLERS = {
    "first": ("gcm_pipeline.reach.chunk", "solve_ik"),
    "alternatives": ("gcm_pipeline.reach.alternatives", "solve_ik"),
    "move_end_lm": ("gcm_pipeline.reach.waypoints", "solve_ik"),
    "move_continuation": ("gcm_pipeline.reach.path", "solve_ik"),
    "move_end": ("gcm_pipeline.reach.path", "end_of_move"),
}


@contextlib.contextmanager
def _adding_time(into: dict[str, float], key: str) -> Iterator[None]:
    """Adds the block's wall time [s] to ``into[key]``."""
    t0 = time.perf_counter()
    try:
        yield
    finally:
        into[key] += time.perf_counter() - t0


@contextlib.contextmanager
def _counting_ik_rows() -> Iterator[tuple[dict[str, int], dict[str, float]]]:
    """Inside the block, each IK call of the stage (in this process) counts its target rows.

    By purpose (:data:`IK_CALLERS`): ``move_end`` counts the end poses of approach
    and retreat moves given to :func:`~gcm_pipeline.reach.waypoints.end_of_move`
    (the Panda's closed form first); ``move_end_lm`` the rows of those it hands to LM.
    Yields ``(rows, seconds)``: ``seconds`` sums each purpose's wall time inside its
    calls (``move_end_lm``'s is part of ``move_end``'s).
    """
    rows = dict.fromkeys(IK_CALLERS, 0)
    seconds = dict.fromkeys(IK_CALLERS, 0.0)
    originals = []
    for purpose, (module_name, name) in IK_CALLERS.items():
        module = importlib.import_module(module_name)
        original = getattr(module, name)

        def counting(robot, targets, *a, _p=purpose, _f=original, **k):  # type: ignore[no-untyped-def]
            rows[_p] += len(np.asarray(targets).reshape(-1, 4, 4))
            with _adding_time(seconds, _p):
                return _f(robot, targets, *a, **k)

        setattr(module, name, counting)
        originals.append((module, name, original))
    try:
        yield rows, seconds
    finally:
        for module, name, original in originals:
            setattr(module, name, original)


def counted_stage(config: Path, sample: int) -> dict[str, Any]:
    """One stage run of ``config`` (one process) with check/clearance wrapped to count rows."""
    counts: dict[str, int] = {"check_calls": 0, "clearance_rows": 0}
    seconds = {"check": 0.0, "clearance": 0.0}
    kept: list[np.ndarray] = []
    rng = np.random.default_rng(1)
    check, clearance = CollisionChecker.check, CollisionChecker.clearance

    def counting_check(self, q, mode="grasp", carried=None):  # type: ignore[no-untyped-def]
        qs = np.asarray(q, dtype=float).reshape(-1, self.robot.nq)
        counts["check_calls"] += 1
        counts[f"check_rows_{mode}"] = counts.get(f"check_rows_{mode}", 0) + len(qs)
        kept.append(qs[rng.random(len(qs)) < 0.05])
        with _adding_time(seconds, "check"):
            return check(self, q, mode, carried)

    def counting_clearance(self, q, *a, **k):  # type: ignore[no-untyped-def]
        counts["clearance_rows"] += len(np.asarray(q, dtype=float).reshape(-1, self.robot.nq))
        with _adding_time(seconds, "clearance"):
            return clearance(self, q, *a, **k)

    CollisionChecker.check = counting_check  # type: ignore[method-assign]
    CollisionChecker.clearance = counting_clearance  # type: ignore[method-assign]
    try:
        with _counting_ik_rows() as (ik_rows, ik_seconds):
            run = stage_run(DENSE, "1", config)
    finally:
        CollisionChecker.check = check  # type: ignore[method-assign]
        CollisionChecker.clearance = clearance  # type: ignore[method-assign]
    counts.update({f"ik_rows_{k}": v for k, v in ik_rows.items()})
    rows = sum(v for k, v in counts.items() if k.startswith("check_rows_"))
    seen = np.concatenate(kept) if kept else np.zeros((0, run["robot"].nq))
    seen = seen[np.all(np.isfinite(seen), axis=1)]
    pick = np.random.default_rng(2).permutation(len(seen))[:sample]
    done = run["grasps"]
    ok = np.asarray(done["reachable"], dtype=bool)
    return {
        "poses": run["poses"],
        "counts": counts,
        "checks_per_pose": rows / run["poses"],
        "ik_rows_per_pose": sum(ik_rows.values()) / run["poses"],
        "clearance_per_pose": counts["clearance_rows"] / run["poses"],
        "wall_s_per_pose": _wall_per_pose(run, seconds, ik_seconds),
        "configurations": seen[pick],
        "approach": (np.asarray(done["q"])[ok], np.asarray(done["q_pregrasp"])[ok]),
    }


def _wall_per_pose(
    run: dict[str, Any], seconds: dict[str, float], ik_seconds: dict[str, float]
) -> dict[str, float]:
    """Where the counted run's time went, per pose [s]: IK by purpose, checks, the rest.

    The wrapped calls' own wall time (the wrappers' bookkeeping is in the rest):
    ``ik_*`` by purpose (``move_end`` includes its LM rows), ``check`` every
    configuration check (the approach's grid points, its waypoints' checks, the
    grasps), ``clearance``; ``rest`` is everything else of the stage: the moves'
    planning (interior waypoints, deviation bounds, grid paths), the proofs
    that move ends are out of reach, the engine's bookkeeping.
    """
    n = run["poses"]
    out = {f"ik_{k}": v / n for k, v in ik_seconds.items() if k != "move_end_lm"}
    out["check"] = seconds["check"] / n
    out["clearance"] = seconds["clearance"] / n
    out["total"] = run["wall_s"] / n
    out["rest"] = out["total"] - sum(v for k, v in out.items() if k != "total")
    return out


# --- collision checks -------------------------------------------------------------------------


#: Half-width [m] of the square of the table under the robot's base left out of
#: VAMP's table: VAMP's link0 sphere (r 8 cm, centre 5 cm up) reaches 3 cm into
#: the table, which gcm exempts (base links touching their support are not
#: checked against it); VAMP has no such exemption, so the table is four boxes
#: around the base's footprint.
BASE_HOLE = 0.08


def _support_boxes(c: np.ndarray, half: np.ndarray) -> list[dict[str, Any]]:
    """A support box (centre ``c``, half extents ``half``) less the base's footprint."""
    h, (hx, hy, hz) = BASE_HOLE, half
    parts = [  # (x range, y range) of four boxes around |x|, |y| < h
        ((h, hx), (-hy, hy)),
        ((-hx, -h), (-hy, hy)),
        ((-h, h), (h, hy)),
        ((-h, h), (-hy, -h)),
    ]
    return [
        {
            "cuboid": {
                "center": [c[0] + (x0 + x1) / 2, c[1] + (y0 + y1) / 2, c[2]],
                "euler_xyz": [0, 0, 0],
                "half_extents": [(x1 - x0) / 2, (y1 - y0) / 2, hz],
            }
        }
        for (x0, x1), (y0, y1) in parts
    ]


def vamp_scene(checker: CollisionChecker) -> list[dict[str, Any]]:
    """The checker's world as VAMP primitives (boxes, cylinders as capsules, spheres)."""
    import coal

    scene: list[dict[str, Any]] = []
    for shape in checker.world:
        g, t = shape.geometry, np.asarray(shape.placement)
        if not np.allclose(t[:3, :3], np.eye(3)):
            raise SystemExit(f"bench_limit: {shape.name} is rotated; only axis-aligned shapes")
        c = t[:3, 3].tolist()
        if isinstance(g, coal.Box) and shape.support:
            boxes = _support_boxes(t[:3, 3], np.asarray(g.halfSide))
            scene.extend({"cuboid": {**b["cuboid"], "name": shape.name}} for b in boxes)
        elif isinstance(g, coal.Box):
            scene.append(
                {
                    "cuboid": {
                        "center": c,
                        "euler_xyz": [0, 0, 0],
                        "half_extents": list(g.halfSide),
                        "name": shape.name,
                    }
                }
            )
        elif isinstance(g, coal.Cylinder):
            scene.append(
                {
                    "capsule": {
                        "center": c,
                        "euler_xyz": [0, 0, 0],
                        "radius": g.radius,
                        "length": 2 * g.halfLength,
                        "name": shape.name,
                    }
                }
            )
        elif isinstance(g, coal.Sphere):
            scene.append({"sphere": {"center": c, "radius": g.radius, "name": shape.name}})
        else:
            raise SystemExit(f"bench_limit: {shape.name} ({type(g).__name__}) has no VAMP shape")
    return scene


def _scene_text(scene: list[dict[str, Any]]) -> str:
    """The scene in ``vamp_bench``'s text format (see benchmarks/vamp/vamp_bench.cc)."""
    lines = []
    for item in scene:
        ((kind, p),) = item.items()
        if kind == "cuboid":
            vals = [*p["center"], *p["euler_xyz"], *p["half_extents"]]
        elif kind == "capsule":
            vals = [*p["center"], *p["euler_xyz"], p["radius"], p["length"]]
        else:
            vals = [*p["center"], p["radius"]]
        lines.append(" ".join([kind, *(f"{float(v):.9g}" for v in vals)]))
    return "\n".join(lines) + "\n"


def run_vamp_cpp(
    binary: Path, scene: list, q: np.ndarray, free: np.ndarray, repeats: int
) -> dict[str, Any]:
    """``vamp_bench`` (C++, no binding in the loop): one per call and blocks of free ones."""
    with tempfile.TemporaryDirectory() as tmp:
        d = Path(tmp)
        (d / "scene.txt").write_text(_scene_text(scene))
        np.ascontiguousarray(q, dtype=np.float32).tofile(d / "q.bin")
        np.ascontiguousarray(free, dtype=np.float32).tofile(d / "free.bin")
        cmd = [str(binary), str(d / "scene.txt"), str(d / "q.bin"), str(len(q))]
        cmd += [str(d / "free.bin"), str(len(free)), str(repeats), str(d / "valid.bin")]
        proc = subprocess.run(cmd, capture_output=True, text=True)
        if proc.returncode != 0:
            return {"error": proc.stderr.strip()}
        out = json.loads(proc.stdout)
        out["valid"] = np.fromfile(d / "valid.bin", dtype=np.uint8).astype(bool)
    return out


def run_vamp(
    python: str,
    scene: list,
    q: np.ndarray,
    pairs: np.ndarray,
    repeats: int,
    exact_collides: np.ndarray | None = None,
) -> dict[str, Any] | str:
    """VAMP's figures through its Python binding, from its own venv, or why there are none."""
    if not python or not Path(python).is_file():
        return f"no VAMP venv at {python!r} (give --vamp-python: a venv with vamp-planner)"
    with tempfile.TemporaryDirectory() as tmp:
        inp, out = Path(tmp) / "in.npz", Path(tmp) / "out.json"
        np.savez(
            inp, robot="panda", scene=json.dumps(scene), q=q.astype(np.float32),
            pairs=pairs.astype(np.float32), repeats=repeats,
            exact_collides=np.zeros(0, bool) if exact_collides is None else exact_collides,
        )  # fmt: skip
        proc = subprocess.run(
            [python, str(VAMP_SCRIPT), str(inp), str(out)], capture_output=True, text=True
        )
        if proc.returncode != 0:
            return "VAMP failed: " + (proc.stderr.strip().splitlines() or ["?"])[-1]
        return json.loads(out.read_text())


def pin_loop(
    robot: Robot, checker: CollisionChecker, q: np.ndarray, complete: bool = False
) -> np.ndarray:
    """Pinocchio's loop over the checker's pairs (stop at first): (N,) collides.

    ``complete``: coal's exact answer (contact information on,
    :func:`bench_collision.complete_answers`); else Pinocchio's default requests,
    the speed reference, which can call overlapping geometry free.
    """
    model, gm = robot.model, checker.geom_model
    data, gd = model.createData(), pin.GeometryData(gm)
    if complete:
        complete_answers(gd)
    return np.array([pin.computeCollisions(model, data, gm, gd, qi, True) for qi in q])


def disagreements(vamp_valid: np.ndarray, exact_hit: np.ndarray) -> dict[str, int]:
    return {
        "vamp_collision_coal_free": int(np.count_nonzero(~vamp_valid & ~exact_hit)),
        "vamp_free_coal_collision": int(np.count_nonzero(vamp_valid & exact_hit)),
        "configurations": len(exact_hit),
    }


def explain_counts(explained: list[dict[str, Any]], exact: np.ndarray) -> dict[str, int]:
    """VAMP's disagreements with the exact answer by what VAMP's spheres hit."""
    out: dict[str, int] = {}
    for e in explained:
        side = "vamp_collision_exact_free" if not exact[e["index"]] else "vamp_free_exact_collision"
        hits = [*e["environment"], *(["self"] if e["self"] else [])]
        key = f"{side}: {'+'.join(hits) or 'nothing'}"
        out[key] = out.get(key, 0) + 1
    return dict(sorted(out.items()))


def _world_gap(centres: np.ndarray, go: Any) -> np.ndarray | None:
    """Distance from points (..., 3) [world] to a world box or cylinder; None: other shape."""
    import coal

    t = np.asarray(go.placement.homogeneous)
    p = (centres - t[:3, 3]) @ t[:3, :3]  # in the shape's frame
    g = go.geometry
    if isinstance(g, coal.Box):
        return np.linalg.norm(np.maximum(np.abs(p) - np.asarray(g.halfSide), 0.0), axis=-1)
    if isinstance(g, coal.Cylinder):
        dr = np.maximum(np.linalg.norm(p[..., :2], axis=-1) - g.radius, 0.0)
        dz = np.maximum(np.abs(p[..., 2]) - g.halfLength, 0.0)
        return np.hypot(dr, dz)
    return None


def outer_sphere_figures(
    robot: Robot, checker: CollisionChecker, q: np.ndarray, hit: np.ndarray
) -> dict[str, Any]:
    """How many configurations the outer link spheres prove free, against coal's answer.

    Every collision pair of the checker's geometry model is tested with the outer
    spheres of its robot geometries (:func:`geometry_spheres`) against the other
    geometry's spheres or the world box / cylinder exactly; a configuration whose
    pairs are all apart is proven free. Conservative: none may collide by coal.
    """
    gm, model = checker.geom_model, robot.model
    data = model.createData()
    nr = checker.n_robot_geoms
    covers = [geometry_spheres(gm.geometryObjects[i].geometry) for i in range(nr)]
    local = []
    for i, cov in enumerate(covers):
        pl = gm.geometryObjects[i].placement
        local.append(cov.centres @ np.asarray(pl.rotation).T + np.asarray(pl.translation))
    joint = [int(gm.geometryObjects[i].parentJoint) for i in range(nr)]
    world = np.empty((len(q), sum(len(c) for c in local), 3))
    start = np.cumsum([0] + [len(c) for c in local])
    for k, qk in enumerate(q):
        pin.forwardKinematics(model, data, qk)
        for i in range(nr):
            m = data.oMi[joint[i]]
            world[k, start[i] : start[i + 1]] = local[i] @ np.asarray(m.rotation).T + m.translation
    near = np.zeros(len(q), dtype=bool)
    by_pair: dict[str, int] = {}
    for pair in gm.collisionPairs:
        a, b = int(pair.first), int(pair.second)
        if a >= nr:
            a, b = b, a
        ca, ra = world[:, start[a] : start[a + 1]], covers[a].radii
        if b < nr:
            cb, rb = world[:, start[b] : start[b + 1]], covers[b].radii
            d = np.linalg.norm(ca[:, :, None] - cb[:, None, :], axis=-1) - ra[:, None] - rb
            touch = np.any(d <= 0, axis=(1, 2))
        else:
            gap = _world_gap(ca, gm.geometryObjects[b])
            touch = np.ones(len(q), bool) if gap is None else np.any(gap <= ra, axis=1)
        near |= touch
        names = f"{gm.geometryObjects[a].name}|{gm.geometryObjects[b].name}"
        by_pair[names] = int(np.count_nonzero(touch & ~hit))
    free = ~hit
    top = sorted(by_pair.items(), key=lambda kv: -kv[1])[:5]
    return {
        # the pairs whose spheres touch on the most exact-free configurations
        "pairs_touching_most_on_free": dict(top),
        "spheres": int(start[-1]),
        "configurations": len(q),
        "exact_free": int(np.count_nonzero(free)),
        "proven_free": int(np.count_nonzero(~near)),
        "proven_free_fraction_of_free": float(np.count_nonzero(~near) / max(1, free.sum())),
        "proven_free_but_colliding": int(np.count_nonzero(~near & hit)),
    }


def check_figures(
    robot: Robot, checker: CollisionChecker, q: np.ndarray, args: argparse.Namespace, vamp: bool
) -> dict[str, Any]:
    """gcm (array, per call), Pinocchio's loop and (``vamp``) VAMP on one set of configurations."""
    n, m = len(q), min(len(q), args.loop_configs)
    out: dict[str, Any] = {"configurations": n}
    dt, reasons = timed(lambda: checker.check(q), args.repeats)
    out["gcm_s_per_config"] = dt / n
    dt, _ = timed(lambda: [checker.check(qi) for qi in q[:m]], args.repeats)
    out["gcm_one_per_call_s_per_config"] = dt / m
    dt, fast = timed(lambda: pin_loop(robot, checker, q[:m]), args.repeats)
    out["pinocchio_loop_s_per_config"] = dt / m
    hit = pin_loop(robot, checker, q[:m], complete=True)  # the exact answer
    out["pinocchio_default_missed"] = int(np.count_nonzero(hit & ~np.asarray(fast)))
    gcm_hit = np.asarray(reasons)[:m] != ""
    out["gcm_differs_from_pinocchio"] = int(np.count_nonzero(gcm_hit != hit))
    out["colliding_fraction_coal"] = float(np.mean(hit))
    out["outer_spheres"] = outer_sphere_figures(robot, checker, q[:m], hit)
    if not vamp:
        out["vamp"] = NO_VAMP_UR5
        return out
    out.update(vamp_check_figures(checker, q, np.asarray(reasons) != "", hit, args))
    if "vamp_cpp_s_per_config" in out:
        g = out["gcm_s_per_config"]
        out["ratio_gcm_rate_over_vamp_one_per_call"] = out["vamp_cpp_s_per_config"] / g
        out["ratio_gcm_rate_over_vamp_blocks"] = out["vamp_cpp_block_s_per_config"] / g
    return out


def vamp_check_figures(
    checker: CollisionChecker,
    q: np.ndarray,
    exact: np.ndarray,
    hit: np.ndarray,
    args: argparse.Namespace,
) -> dict[str, Any]:
    """VAMP's Panda checker (binding, C++) on ``q``: against gcm's ``exact``, coal's ``hit``."""
    m = len(hit)
    out: dict[str, Any] = {}
    scene = vamp_scene(checker)
    vamp = run_vamp(args.vamp_python, scene, q, np.zeros((0, 2, 7)), args.repeats, exact)
    if isinstance(vamp, str):
        out["vamp"] = vamp
        return out
    out["vamp_disagreements_explained"] = explain_counts(vamp["explain"], exact)
    out["vamp_py_s_per_config"] = vamp["validate_s_per_call"]
    out["vamp_py_empty_binding_call_s"] = vamp["empty_call_s"]
    out["vamp_py_disagreements_with_coal"] = disagreements(np.asarray(vamp["valid"])[:m], hit)
    binary = Path(args.vamp_python).parent / "vamp_bench"
    if not binary.exists():
        out["vamp_cpp"] = f"no {binary} (benchmarks/vamp/vamp_bench.cc compiled beside that python)"
        return out
    free = q[~exact]
    cpp = run_vamp_cpp(binary, scene, q, free, max(15, args.repeats))  # loops of a few ms
    if "error" in cpp:
        out["vamp_cpp"] = cpp["error"]
        return out
    out["vamp_cpp_s_per_config"] = cpp["one_per_call_s_per_config"]
    out["vamp_cpp_block_s_per_config"] = cpp["block_s_per_config"]
    out["vamp_cpp_blocks"] = {k: cpp[k] for k in ("blocks", "free_blocks", "rake")}
    out["vamp_cpp_same_as_binding"] = bool(np.array_equal(cpp["valid"], vamp["valid"]))
    out["vamp_disagreements_with_coal"] = disagreements(cpp["valid"][:m], hit)
    gcm_all = disagreements(cpp["valid"], exact)
    out["vamp_disagreements_with_gcm"] = {k.replace("coal", "gcm"): v for k, v in gcm_all.items()}
    return out


def motion_figures(
    robot: Robot, checker: CollisionChecker, grasp: np.ndarray, pre: np.ndarray, args: Any
) -> dict[str, Any]:
    """VAMP's blocks on the approach motions against gcm on the same interpolated rows."""
    k = min(len(grasp), args.motions)
    pairs = np.stack([grasp[:k], pre[:k]], axis=1)
    vamp = run_vamp(args.vamp_python, vamp_scene(checker), pairs[:1, 0], pairs, args.repeats)
    if isinstance(vamp, str):
        return {"vamp": vamp}
    res, lanes = vamp["resolution"], vamp["simd_lanes"]
    dist = np.linalg.norm((pre[:k] - grasp[:k]).astype(np.float32), axis=1)
    blocks = np.maximum(np.ceil(dist / lanes * res), 1).astype(int)
    # the configurations VAMP checks: lanes * blocks per motion, evenly along it
    rows = [
        grasp[i] + np.outer(np.arange(1, lanes * b + 1) / (lanes * b), pre[i] - grasp[i])
        for i, b in enumerate(blocks)
    ]
    qs = np.concatenate(rows)
    dt, reasons = timed(lambda: checker.check(qs, mode="approach"), args.repeats)
    valid = np.asarray(vamp["motion_valid"])
    out = {
        "motions": k,
        "configurations": len(qs),
        "vamp_valid_motions": int(np.count_nonzero(valid)),
        "vamp_s_per_motion": vamp["validate_motion_s_per_call"],
        # exact when every motion is valid (an invalid one stops at its first bad block)
        "vamp_s_per_config": vamp["validate_motion_s_per_call"] * k / len(qs),
        "gcm_approach_s_per_config": dt / len(qs),
        "gcm_free_configurations": int(np.count_nonzero(np.asarray(reasons) == "")),
    }
    out["ratio_gcm_over_vamp_rate"] = out["vamp_s_per_config"] / out["gcm_approach_s_per_config"]
    return out


# --- the report -----------------------------------------------------------------------------


def model_figures(report: dict[str, Any], stage_rate: float) -> dict[str, Any]:
    """The cost model's limits and the stage's fraction of each."""
    ik_name, t_ik = best_ik(report["ik"])
    cpp = report["stage_counts"]["checks_per_pose"]
    stage = report["checks"]["stage"]
    checks = {"gcm": stage["gcm_s_per_config"]}
    for key, name in (
        ("vamp_cpp_s_per_config", "vamp_one_per_call"),
        ("vamp_cpp_block_s_per_config", "vamp_blocks_of_free"),
    ):
        if key in stage:
            checks[name] = stage[key]
    best = min(checks, key=checks.__getitem__)
    limit = 1.0 / (t_ik + cpp * checks[best])
    limit_gcm = 1.0 / (t_ik + cpp * checks["gcm"])
    # the moves' ends are IK the stage cannot skip (one per approach or retreat
    # planned): the limit with them, at the measured cost of one move end
    counts = report["stage_counts"]["counts"]
    moves = counts.get("ik_rows_move_end", 0) / report["stage_counts"]["poses"]
    t_move = report["ik"]["gcm_move_end_s_per_pose"]
    limit_moves = 1.0 / (t_ik + moves * t_move + cpp * checks[best])
    limit_moves_gcm = 1.0 / (t_ik + moves * t_move + cpp * checks["gcm"])
    return {
        "t_ik_s": t_ik,
        "t_ik_from": ik_name,
        "checks_per_pose": cpp,
        "t_check_s": checks,
        "t_check_from": best,
        "limit_poses_per_s": limit,
        "limit_at_gcm_checks_poses_per_s": limit_gcm,
        "stage_poses_per_s_one_process": stage_rate,
        "stage_fraction_of_limit": stage_rate / limit,
        "stage_fraction_of_limit_at_gcm_checks": stage_rate / limit_gcm,
        "move_ends_per_pose": moves,
        "t_move_end_s": t_move,
        "limit_with_move_ends_poses_per_s": limit_moves,
        "stage_fraction_of_limit_with_move_ends": stage_rate / limit_moves,
        "limit_with_move_ends_at_gcm_checks_poses_per_s": limit_moves_gcm,
        "stage_fraction_of_limit_with_move_ends_at_gcm_checks": stage_rate / limit_moves_gcm,
    }


#: The figures set side by side for every robot run: name -> path in its section.
SIDE_BY_SIDE = {
    "t_ik_s": ("model", "t_ik_s"),
    "t_ik_from": ("model", "t_ik_from"),
    "gcm_ik_s_per_pose": ("ik", "gcm_s_per_pose"),
    "checks_per_pose": ("model", "checks_per_pose"),
    "move_ends_per_pose": ("model", "move_ends_per_pose"),
    "t_move_end_s": ("model", "t_move_end_s"),
    "gcm_check_stage_s_per_config": ("checks", "stage", "gcm_s_per_config"),
    "gcm_check_front_s_per_config": ("checks", "front", "gcm_s_per_config"),
    "gcm_differs_from_pinocchio_stage": ("checks", "stage", "gcm_differs_from_pinocchio"),
    "gcm_differs_from_pinocchio_front": ("checks", "front", "gcm_differs_from_pinocchio"),
    "outer_spheres_proven_free_stage": (
        "checks", "stage", "outer_spheres", "proven_free_fraction_of_free"
    ),
    "stage_poses_per_s_one_process": ("model", "stage_poses_per_s_one_process"),
    "t_check_from": ("model", "t_check_from"),
    "stage_fraction_of_limit": ("model", "stage_fraction_of_limit"),
    "stage_fraction_of_limit_at_gcm_checks": ("model", "stage_fraction_of_limit_at_gcm_checks"),
    "stage_fraction_of_limit_with_move_ends": ("model", "stage_fraction_of_limit_with_move_ends"),
    "stage_fraction_of_limit_with_move_ends_at_gcm_checks": (
        "model", "stage_fraction_of_limit_with_move_ends_at_gcm_checks"
    ),
    "counted_run_s_per_pose_total": ("stage_counts", "wall_s_per_pose", "total"),
    "counted_run_s_per_pose_ik_first": ("stage_counts", "wall_s_per_pose", "ik_first"),
    "counted_run_s_per_pose_ik_move_end": ("stage_counts", "wall_s_per_pose", "ik_move_end"),
    "counted_run_s_per_pose_check": ("stage_counts", "wall_s_per_pose", "check"),
    "counted_run_s_per_pose_rest": ("stage_counts", "wall_s_per_pose", "rest"),
}  # fmt: skip


def side_by_side(robots: dict[str, dict[str, Any]]) -> dict[str, dict[str, Any]]:
    """Each :data:`SIDE_BY_SIDE` figure of every robot run: figure -> robot -> value."""
    out: dict[str, dict[str, Any]] = {}
    for figure, path in SIDE_BY_SIDE.items():
        for name, section in robots.items():
            value: Any = section
            for key in path:
                value = value.get(key) if isinstance(value, dict) else None
            out.setdefault(figure, {})[name] = value
    return out


def robot_report(name: str, args: argparse.Namespace) -> dict[str, Any]:
    """Every figure of one robot (``CONFIGS[name]``, the dense work ``DENSE``)."""
    load_start = os.getloadavg()
    cfg = load_config(CONFIGS[name], DENSE)
    robot = robot_from_config(cfg)
    checker = make_checker(robot, cfg.environment, cfg.object, cfg.robot.base_pose.matrix())
    vamp = name == "panda"  # VAMP's ur5 is the bare arm: see NO_VAMP_UR5
    report: dict[str, Any] = {
        "config": str(CONFIGS[name].relative_to(ROOT)),
        "overrides": DENSE,
        "ik": ik_figures(name, robot, args.ik_targets, args.repeats),
    }
    counted = counted_stage(CONFIGS[name], args.configs)
    report["stage_counts"] = {
        k: v for k, v in counted.items() if k not in ("configurations", "approach")
    }
    front = front_configurations(robot, args.configs)
    report["checks"] = {
        "front": check_figures(robot, checker, front, args, vamp),
        "stage": check_figures(robot, checker, counted["configurations"], args, vamp),
    }
    if vamp:
        report["approach_blocks"] = motion_figures(robot, checker, *counted["approach"], args)
    else:
        report["approach_blocks"] = {"vamp": NO_VAMP_UR5}
    runs = [stage_run(DENSE, "1", CONFIGS[name]) for _ in range(args.repeats)]
    walls = [r["wall_s"] for r in runs]
    report["stage_wall_s_runs"] = walls
    # where the stage's time goes (CPU seconds by step, the median run)
    report["stage_cpu_s_by_step"] = runs[int(np.argsort(walls)[len(walls) // 2])]["cpu_s_by_step"]
    report["model"] = model_figures(report, counted["poses"] / float(np.median(walls)))
    report["load_average"] = {"start": load_start, "end": os.getloadavg()}
    return report


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--robot", choices=("panda", "ur5", "both"), default="both")
    parser.add_argument("--ik-targets", type=int, default=2000)
    parser.add_argument("--configs", type=int, default=20000)
    parser.add_argument("--loop-configs", type=int, default=3000, help="per-call loops")
    parser.add_argument("--motions", type=int, default=2000)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--vamp-python", default=os.environ.get("GCM_VAMP_PYTHON", ""))
    parser.add_argument("--out", type=Path, default=ROOT / "benchmarks" / "results" / "limit.json")
    args = parser.parse_args()
    load_start = os.getloadavg()
    names = list(CONFIGS) if args.robot == "both" else [args.robot]
    robots = {name: robot_report(name, args) for name in names}
    report: dict[str, Any] = {"side_by_side": side_by_side(robots), "robots": robots}
    report["machine"] = {
        "cpu_count": os.cpu_count(),
        "python": platform.python_version(),
        "pinocchio": pin.__version__,
        "vamp_python": args.vamp_python,
    }
    report["command"] = " ".join(["python benchmarks/bench_limit.py", *sys.argv[1:]])
    report["load_average_start"] = load_start
    report["load_average_end"] = os.getloadavg()
    report["date"] = time.strftime("%Y-%m-%dT%H:%M:%S+00:00", time.gmtime())
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(report, indent=2) + "\n", encoding="utf-8")
    print(json.dumps(report, indent=2))
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
