#!/usr/bin/env python
"""Branch recall of the reachability stage on 6R arms, against an independent enumeration.

Work: ``configs/bottle_side.yaml`` (the bottle on the table, approach 10 cm)
run with ``robot.spec`` set to the shipped UR5 and to a user's UR10 spec
(``configs/robots/ur10.yaml``: example-robot-data's UR10 with the UR5's
gripper). The reachability stage decides every grasp
(:func:`gcm_pipeline.pipeline.check_reachability`).

Reference, for **every** grasp of the run: every IK branch, from two
enumerations that share no code with the stage's branch search:

* EAIK built here from the Pinocchio model itself (joint axes and origins
  from ``pin.forwardKinematics`` at q = 0; not the package's chain or solver);
* a dense multi-start Levenberg-Marquardt (``--starts`` uniform random
  starts per grasp, clamped to the joint limits), whose converged answers
  are merged with EAIK's modulo 2π.

Each branch is checked with the run's own checker (the engine's ``check``:
collisions, approach, retreat) at its 2π copy inside the limits nearest home;
a branch that fails a move (approach or retreat) is checked again at each of
its other copies inside the limits (the move's path, not the grasp, depends
on the copy). A grasp is reachable by the reference when some branch passes.

Figures: recall = |reachable by the stage and the reference| / |reachable by
the reference|; ``stage_only`` = grasps the stage reaches and the reference
does not (0 when the reference is complete); false positives = reachable rows
that fail an independent re-check (FK by a fresh ``pin.Data``, the strict
joint limits, ``pin.computeCollisions`` over every pair of the grasp's world
with contact information on: coal's complete answer, see :func:`complete_answers`).

Speed: the reachability stage on each arm, median of ``--repeats`` runs (one
engine, warm), and ``gcm run`` of the UR5 config (no HTML, no plots), median of
``--pipeline-repeats``; with ``--before CHECKOUT`` (a checkout of the code
before) the same figures of that code in the same run (a child process; the
``gcm run`` timings alternate between the two).

Run from the repository root: ``python benchmarks/bench_branches.py
[--before ../main]``; writes ``benchmarks/results/branches.json``.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import sys
import tempfile
import time
from datetime import datetime, timezone
from pathlib import Path
from typing import Any

import numpy as np
import pinocchio as pin

ROOT = Path(__file__).resolve().parents[1]
if "GCM_BENCH_CHILD" not in os.environ:
    sys.path.insert(0, str(ROOT))  # run from a clone, no install (a child uses PYTHONPATH)

from gcm_pipeline import pipeline as P  # noqa: E402
from gcm_pipeline.config import load_config  # noqa: E402
from gcm_pipeline.geometry.dualquat import dq_to_matrix  # noqa: E402

try:  # the package's layout; --before may name a checkout from before its moves
    from gcm_pipeline.pipeline import make_checker
    from gcm_pipeline.robot.ik.lm import PinocchioIKOptions, levenberg_marquardt
except ImportError:  # pragma: no cover - a checkout of 0.1.0's layout
    from gcm_pipeline.robot.ik_pinocchio import PinocchioIKOptions
    from gcm_pipeline.robot.ik_pinocchio import _lm as levenberg_marquardt
    from gcm_pipeline.stages.collision import make_checker
from gcm_pipeline.robot.model import Robot  # noqa: E402

try:  # a 6R solver keeps its last poses' EAIK answers; --before may predate that
    from gcm_pipeline.robot.ik.analytic_6r import forget_answers
except ImportError:  # pragma: no cover - a checkout whose solver keeps none

    def forget_answers(robot: Any) -> None:
        """Nothing to forget."""


CONFIG = ROOT / "configs" / "bottle_side.yaml"
UR10 = ROOT / "configs" / "robots" / "ur10.yaml"
ARMS = {"ur5": "ur5", "ur10_spec": str(UR10), "ur10_limited": ""}


def ur10_limited_spec() -> str:
    """The UR10 spec on example-robot-data's ``ur10_limited`` (every joint in [-pi, pi])."""
    path = Path("/tmp") / f"gcm_bench_ur10_limited_{os.getpid()}.yaml"
    text = UR10.read_text().replace(
        "example_robot_data: ur10\n", "example_robot_data: ur10_limited\n"
    )
    path.write_text(text.replace("name: ur10\n", "name: ur10_limited\n"))
    return str(path)


TWO_PI = 2.0 * np.pi


# --- the reference ------------------------------------------------------------------------


def eaik_from_pinocchio(robot: Robot) -> Any:
    """An EAIK robot of the arm, from Pinocchio's own kinematics at q = 0."""
    import eaik.pybindings.EAIK as EAIK  # noqa: N811

    model = robot.model
    data = model.createData()
    q0 = np.zeros(model.nq)
    pin.forwardKinematics(model, data, q0)
    pin.updateFramePlacements(model, data)
    # each joint's axis in the world: its column of the world-frame Jacobian (angular part)
    jac = pin.computeJointJacobians(model, data, q0)
    axes = [np.asarray(jac[3:, model.joints[j].idx_v]) for j in range(1, model.njoints)]
    origins = [np.asarray(data.oMi[j].translation) for j in range(1, model.njoints)]
    origins_arr = np.array(origins)
    tcp = data.oMf[robot.grasp_frame_id]
    offsets = np.vstack(
        [origins_arr[0], np.diff(origins_arr, axis=0), tcp.translation - origins_arr[-1]]
    )
    return EAIK.Robot(np.array(axes).T, offsets.T, np.asarray(tcp.rotation), [], True)


def wrap(q: np.ndarray) -> np.ndarray:
    return np.remainder(q + np.pi, TWO_PI) - np.pi


def copies(q: np.ndarray, lower: np.ndarray, upper: np.ndarray) -> list[np.ndarray]:
    """Every configuration q + 2 pi k (per joint) inside the limits."""
    per_joint = []
    for j in range(len(q)):
        ks = np.arange(
            np.ceil((lower[j] - q[j]) / TWO_PI), np.floor((upper[j] - q[j]) / TWO_PI) + 1
        )
        per_joint.append(q[j] + TWO_PI * ks)
    if any(len(v) == 0 for v in per_joint):
        return []
    grid = np.meshgrid(*per_joint, indexing="ij")
    return list(np.stack([g.ravel() for g in grid], axis=1))


def reference_branches(
    robot: Robot, targets: np.ndarray, starts: int, tol: tuple[float, float]
) -> tuple[list[np.ndarray], dict[str, int]]:
    """Per target, its branches (K, 6) in (-pi, pi]: EAIK's exact ones and the LM's, merged."""
    bot = eaik_from_pinocchio(robot)
    n, nq = len(targets), robot.nq
    lower, upper = robot.lower, robot.upper
    # dense multi-start LM, clamped to the limits
    rng = np.random.default_rng(0xB7A)
    q0 = rng.uniform(lower, upper, size=(n * starts, nq))
    rep = np.repeat(np.arange(n), starts)
    opts = PinocchioIKOptions(max_iterations=60, stall_ratio=0.0)
    q_lm, conv, _, _ = levenberg_marquardt(
        robot.chain,
        q0,
        targets[rep, :3, :3],
        targets[rep, :3, 3],
        lower,
        upper,
        0.05 * tol[0],
        0.05 * tol[1],
        opts,
    )
    out: list[np.ndarray] = []
    stats = {"eaik_branches": 0, "lm_only_branches": 0}
    for i in range(n):
        sol = bot.calculate_IK(targets[i])
        ea = np.asarray(sol.Q, dtype=float).reshape(-1, nq)
        ea = wrap(ea[~np.asarray(sol.is_LS, dtype=bool).reshape(-1)])
        lm = wrap(q_lm[i * starts : (i + 1) * starts][conv[i * starts : (i + 1) * starts]])
        merged: list[np.ndarray] = []
        for src, q in (("eaik", ea), ("lm", lm)):
            for qi in q:
                same = [np.max(np.abs(wrap(qi - m))) < 1e-3 for m in merged]
                if not any(same):
                    merged.append(qi)
                    stats["eaik_branches" if src == "eaik" else "lm_only_branches"] += 1
        out.append(np.array(merged).reshape(-1, nq))
    return out, stats


def reference_reachable(
    engine: Any, robot: Robot, targets: np.ndarray, branches: list[np.ndarray]
) -> np.ndarray:
    """Targets (N,) bool with a branch that passes the engine's checks at some 2 pi copy."""
    lower, upper, home = robot.lower + 1e-9, robot.upper - 1e-9, np.asarray(robot.home)
    rows, qs, alts = [], [], []
    for i, b in enumerate(branches):
        for qb in b:
            cps = copies(qb, lower, upper)
            if not cps:
                continue
            cps.sort(key=lambda c: float(np.sum((c - home) ** 2)))
            rows.append(i)
            qs.append(cps[0])
            alts.append(cps[1:])
    ok = np.zeros(len(targets), dtype=bool)
    if not rows:
        return ok
    r = np.array(rows)
    chk = engine.check(targets[r], np.array(qs))
    ok[r[chk.passed]] = True
    # a branch that failed a move: its other copies (the path differs, the grasp does not)
    again = [k for k in np.flatnonzero(np.isin(chk.stage, (1, 2))) if not ok[r[k]]]
    rr, qq = [], []
    for k in again:
        for c in alts[k]:
            rr.append(r[k])
            qq.append(c)
    if rr:
        chk2 = engine.check(targets[np.array(rr)], np.array(qq))
        ok[np.array(rr)[chk2.passed]] = True
    return ok


def complete_answers(gd: Any) -> Any:
    """``gd`` (a ``pin.GeometryData``) asking coal for its complete answer: contact on.

    With contact information EPA runs whenever GJK finds contact; Pinocchio's
    default requests ask without it, and coal's ``collide`` then can call
    overlapping geometry free (GJK ending within its tolerance of the origin,
    at any depth). Written here, not the checker's requests: the re-check shares
    no code with the checker's narrow phase; nor imported from ``bench_collision``,
    whose imports need the current layout (a ``--before`` child runs an older one).
    """
    for req in gd.collisionRequests:
        req.enable_contact = True
    return gd


def verify(robot: Robot, cfg: Any, q: np.ndarray, targets: np.ndarray) -> dict[str, int]:
    """Independent re-check of reachable rows: FK, strict limits, every collision pair."""
    model = robot.model
    data = model.createData()
    base = cfg.robot.base_pose.matrix()
    checker = make_checker(robot, cfg.environment, cfg.object, base)
    gm = checker.geom_model
    gd = complete_answers(pin.GeometryData(gm))
    bad_fk = bad_limits = bad_collision = 0
    for qi, t in zip(q, targets, strict=True):
        pin.forwardKinematics(model, data, qi)
        pin.updateFramePlacements(model, data)
        m = data.oMf[robot.grasp_frame_id]
        pe = np.linalg.norm(m.translation - t[:3, 3])
        re = np.linalg.norm(pin.log3(t[:3, :3].T @ m.rotation))
        bad_fk += not (pe <= cfg.ik.position_tolerance and re <= cfg.ik.orientation_tolerance)
        bad_limits += not (
            np.all(qi > model.lowerPositionLimit) and np.all(qi < model.upperPositionLimit)
        )
        bad_collision += bool(pin.computeCollisions(model, data, gm, gd, qi, True))
    return {
        "fk_failures": int(bad_fk),
        "limit_failures": int(bad_limits),
        "collision_failures": int(bad_collision),
        "false_positives": int(bad_fk + bad_limits + bad_collision),
    }


# --- one arm -------------------------------------------------------------------------------


def run_arm(
    name: str, overrides: list[str], repeats: int, starts: int, reference: bool = True
) -> dict[str, Any]:
    """The stage on one arm: its timing and (``reference``) recall and false positives."""
    spec = ARMS[name] or ur10_limited_spec()
    cfg = load_config(CONFIG, [f"robot.spec={spec}", *overrides])
    candidates = P.generate_candidates(cfg)
    grasps = P.densify(candidates, P.build_manifold(candidates, cfg), cfg)
    robot = P.robot_from_config(cfg)
    if not ARMS[name]:
        Path(spec).unlink()
    engine = P.reachability_engine(robot, cfg)
    walls = []
    try:
        for _ in range(repeats):
            forget_answers(robot)  # each repeat solves as the first did
            t0 = time.perf_counter()
            done = P.check_reachability(grasps, robot, cfg, engine=engine)
            walls.append(time.perf_counter() - t0)
        if not reference:
            return {"stage_wall_s": [round(w, 4) for w in walls]}
        reach = np.asarray(done["reachable"], dtype=bool)
        base = cfg.robot.base_pose.matrix()
        targets = np.linalg.inv(base) @ dq_to_matrix(np.asarray(done["dq"]))
        tol = (cfg.ik.position_tolerance, cfg.ik.orientation_tolerance)
        t0 = time.perf_counter()
        branches, stats = reference_branches(robot, targets, starts, tol)
        ref = reference_reachable(engine, robot, targets, branches)
        ref_s = time.perf_counter() - t0
    finally:
        engine.close()
    q = np.asarray(done["q"], dtype=float)
    fp = verify(robot, cfg, q[reach], targets[reach])
    both = int(np.count_nonzero(reach & ref))
    missed = np.flatnonzero(ref & ~reach)
    reasons = np.asarray(done["reason"]).astype(str)
    return {
        "spec": name if ARMS[name] == "" else os.path.relpath(spec, ROOT),
        "grasps": len(done),
        "reachable_stage": int(reach.sum()),
        "reachable_reference": int(ref.sum()),
        "rejected": int((~reach).sum()),
        "missed": int(missed.size),
        "missed_reasons": {
            str(k): int(v)
            for k, v in zip(*np.unique(reasons[missed], return_counts=True), strict=True)
        },
        "stage_only": int(np.count_nonzero(reach & ~ref)),
        "recall": both / max(int(ref.sum()), 1),
        **fp,
        "reference_branches": stats,
        "reference_s": round(ref_s, 2),
        "stage_wall_s": [round(w, 4) for w in walls],
        "stage_wall_median_s": float(np.median(walls)),
    }


def child(path: str, arms: list[str], overrides: list[str], repeats: int, starts: int) -> None:
    out = {name: run_arm(name, overrides, repeats, starts) for name in arms}
    Path(path).write_text(json.dumps(out, indent=2) + "\n")


def before(checkout: str, arms: list[str], overrides: list[str], repeats: int, starts: int) -> Any:
    """The same figures of another checkout's code, in a child process."""
    out = Path("/tmp") / f"bench_branches_before_{os.getpid()}.json"
    env = dict(os.environ, PYTHONPATH=os.path.abspath(checkout), GCM_BENCH_CHILD="1")
    cmd = [sys.executable, __file__, "--child", str(out), "--arms", *arms]
    cmd += ["--repeats", str(repeats), "--starts", str(starts)]
    cmd += [a for o in overrides for a in ("--set", o)]
    subprocess.run(cmd, env=env, check=True)
    try:
        return json.loads(out.read_text())
    finally:
        out.unlink(missing_ok=True)


def pipeline_runs(checkouts: dict[str, str], repeats: int) -> dict[str, Any]:
    """``gcm run`` of the bottle config on the UR5 (no HTML, no plots), wall time per checkout.

    The runs of the checkouts alternate (the load of a shared machine hits both alike).
    """
    walls: dict[str, list[float]] = {name: [] for name in checkouts}
    with tempfile.TemporaryDirectory() as tmp:
        for _ in range(repeats):
            for name, path in checkouts.items():
                cmd = [sys.executable, "-m", "gcm_pipeline", "run", str(CONFIG)]
                cmd += ["--set", "robot.spec=ur5", "--set", "publish.html=false"]
                cmd += ["--set", "publish.plots=false", "--out", f"{tmp}/{name}", "--force"]
                env = dict(os.environ, PYTHONPATH=os.path.abspath(path))
                t0 = time.perf_counter()
                subprocess.run(cmd, env=env, cwd=tmp, check=True, capture_output=True)
                walls[name].append(round(time.perf_counter() - t0, 3))
    return {name: {"wall_s": w, "median_s": float(np.median(w))} for name, w in walls.items()}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--arms", nargs="+", default=list(ARMS), choices=list(ARMS))
    parser.add_argument("--repeats", type=int, default=3, help="stage runs per arm (median)")
    parser.add_argument("--starts", type=int, default=64, help="LM starts per grasp (reference)")
    parser.add_argument("--set", action="append", default=[], help="config override key=value")
    parser.add_argument("--before", help="a checkout of the code before, timed in the same run")
    parser.add_argument("--out", default=str(ROOT / "benchmarks" / "results" / "branches.json"))
    parser.add_argument(
        "--pipeline-repeats", type=int, default=3, help="gcm run on the UR5 per checkout (0: none)"
    )
    parser.add_argument("--child", help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.child:
        child(args.child, args.arms, args.set, args.repeats, args.starts)
        return
    import gcm_pipeline

    result: dict[str, Any] = {
        # the command as run from the repository root (no machine-specific paths)
        "command": " ".join(
            ["python", "benchmarks/bench_branches.py"]
            + [a if not a.startswith("/") else os.path.relpath(a, ROOT) for a in sys.argv[1:]]
        ),
        "date": datetime.now(timezone.utc).isoformat(timespec="seconds"),
        "machine": {"python": platform.python_version(), "cpus": os.cpu_count()},
        "load_before": os.getloadavg(),
        "package": gcm_pipeline.__version__,
        "arms": {},
    }
    for name in args.arms:
        result["arms"][name] = run_arm(name, args.set, args.repeats, args.starts)
    if args.before:
        result["before"] = before(args.before, args.arms, args.set, args.repeats, args.starts)
        # and once more now, so that both codes are timed under the same load
        for name in args.arms:
            again = run_arm(name, args.set, args.repeats, args.starts, reference=False)
            result["arms"][name]["stage_wall_s"] += again["stage_wall_s"]
            result["arms"][name]["stage_wall_median_s"] = float(
                np.median(result["arms"][name]["stage_wall_s"])
            )
    if args.pipeline_repeats:
        checkouts = {"after": str(ROOT)}
        if args.before:
            checkouts["before"] = args.before
        result["pipeline_ur5"] = pipeline_runs(checkouts, args.pipeline_repeats)
    result["load_after"] = os.getloadavg()
    for name, r in result["arms"].items():
        line = (
            f"{name}: {r['grasps']} grasps, stage reaches {r['reachable_stage']}, reference "
            f"{r['reachable_reference']}; recall {r['recall']:.4f} (missed {r['missed']} "
            f"{r['missed_reasons']}), stage-only {r['stage_only']}, false positives "
            f"{r['false_positives']}; stage {r['stage_wall_median_s']:.3f} s (median)"
        )
        print(line)
        if "before" in result:
            b = result["before"][name]
            print(
                f"  before: stage reaches {b['reachable_stage']}, recall {b['recall']:.4f} "
                f"(missed {b['missed']}), false positives {b['false_positives']}; "
                f"stage {b['stage_wall_median_s']:.3f} s (median)"
            )
    for name, r in result.get("pipeline_ur5", {}).items():
        print(f"gcm run, UR5 bottle ({name}): {r['median_s']:.2f} s (median of {r['wall_s']})")
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    Path(args.out).write_text(json.dumps(result, indent=2) + "\n")
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
