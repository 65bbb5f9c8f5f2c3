"""The reachability decisions with the compiled kernels equal those without, on every world.

The grid: the table on or off, the object checked or not, self-collision on
or off, 0, 1 or 3 obstacles, on the Panda, the UR5 and a robot a user brings
as a URDF file (example-robot-data's UR10 file with the UR5's tool), each
checked with the kernels and with the NumPy code (``kernels.suppressed()``, as
``GCM_JIT=0``), in this process: 72 worlds x 2, 54 grasps each. Every
grasp's ``reachable`` and ``reason`` must be the same. A bare flange (no
tool) is checked too, and a few ``gcm run`` subprocesses prove the command
line's path with ``GCM_JIT`` on and off.
"""

from __future__ import annotations

import csv
import itertools
from pathlib import Path

import numpy as np
import pytest
import yaml
from helpers import BOTTLE, ROBOT_SPECS, run_gcm

from gcm_pipeline import pipeline as P
from gcm_pipeline.config import load_config
from gcm_pipeline.robot import kernels
from gcm_pipeline.table import GraspTable

#: Few grasps, no manifold: 2 rings of 9 around the bottle, one worker (in-process).
FAST = [
    "candidates.count=18",
    "candidates.rings=2",
    "ik.workers=1",
    "publish.html=false",
    "publish.plots=false",
]
#: Obstacles beside the bottle (a box at the +y side grasps, a cylinder at the -y
#: side, a sphere above it), so that they decide some grasps.
OBSTACLES = [
    "{shape: box, dims: {size: [0.06, 0.06, 0.3]}, pose: {xyz: [0.5, 0.13, 0.15]}}",
    "{shape: cylinder, dims: {radius: 0.03, height: 0.3}, pose: {xyz: [0.42, -0.12, 0.0]}}",
    "{shape: sphere, dims: {radius: 0.05}, pose: {xyz: [0.62, 0.0, 0.32]}}",
]
WORLDS = list(itertools.product([True, False], [True, False], [True, False], [0, 1, 3]))
#: The grasps of every world: the bottle's, off by up to a few cm and 10 deg (some
#: push a finger into it), and those of bottles near the base and behind it (the
#: arm folds onto itself), all checked against the bottle at its place.
GRASP_SETS = [
    ["candidates.noise.position=0.015", "candidates.noise.angle_deg=10"],
    ["object.pose.xyz=[0.15, 0.0, 0.25]"],
    ["object.pose.xyz=[-0.2, 0.0, 0.3]"],
]


@pytest.fixture(autouse=True)
def _kernels_on(monkeypatch):
    """Each test starts with the kernels on, whatever the environment says."""
    monkeypatch.delenv("GCM_JIT", raising=False)


@pytest.fixture(scope="module")
def user_urdf_spec(tmp_path_factory):
    """A robot spec of a URDF file (example-robot-data's UR10) with the UR5's tool."""
    from example_robot_data.robots_loader import getModelPath

    rel = "ur_description/urdf/ur10_robot.urdf"
    robots = Path(getModelPath(rel))  # .../share/example-robot-data/robots
    spec = yaml.safe_load((ROBOT_SPECS / "ur5.yaml").read_text())
    spec["name"] = "ur10_user"
    spec["description"] = "example-robot-data's UR10 URDF file with the UR5's tool"
    # its meshes are package://example-robot-data/robots/...: the folder above resolves them
    spec["model"] = {"urdf": str(robots / rel), "package_dirs": [str(robots.parent.parent)]}
    path = tmp_path_factory.mktemp("spec") / "ur10_user.yaml"
    path.write_text(yaml.safe_dump(spec))
    return path


def _overrides(spec, table, check_object, self_collision, obstacles):
    return [
        *FAST,
        f"robot.spec={spec}",
        "environment.table=" + ("{height: 0.0}" if table else "null"),
        f"environment.check_object={str(check_object).lower()}",
        f"environment.self_collision={str(self_collision).lower()}",
        "environment.obstacles=[" + ", ".join(OBSTACLES[:obstacles]) + "]",
    ]


@pytest.mark.parametrize("robot_name", ["panda", "ur5", "user_urdf"])
def test_decisions_equal_with_and_without_kernels_on_every_world(robot_name, user_urdf_spec):
    spec = str(user_urdf_spec) if robot_name == "user_urdf" else robot_name
    parts = [P.generate_candidates(load_config(BOTTLE, [*FAST, *extra])) for extra in GRASP_SETS]
    grasps = GraspTable({c: np.concatenate([p[c] for p in parts]) for c in parts[0].columns})
    assert len(grasps) == 54
    robot = P.robot_from_config(load_config(BOTTLE, _overrides(spec, *WORLDS[0])))  # shared
    seen: dict[str, int] = {}
    by_world = {}
    for world in WORLDS:
        cfg = load_config(BOTTLE, _overrides(spec, *world))
        out = P.check_reachability(grasps, robot, cfg)
        with kernels.suppressed():
            ref = P.check_reachability(grasps, robot, cfg)
        where = f"{robot_name}, table/object/self/obstacles = {world}"
        np.testing.assert_array_equal(out["reachable"], ref["reachable"], err_msg=where)
        np.testing.assert_array_equal(out["reason"], ref["reason"], err_msg=where)
        for reason in np.asarray(out["reason"]).tolist():
            seen[reason] = seen.get(reason, 0) + 1
        by_world[world] = np.asarray(out["reachable"])
    # not a grid of one answer: reachable grasps and collisions with the world and the
    # object (a 6R arm tries every closed-form branch, so none of its 54 grasps is left
    # with a self-collision only; the Panda still has some)
    kinds = {"", "collision_environment", "collision_object"}
    if robot_name == "panda":
        kinds.add("collision_self")
    assert kinds <= set(seen), seen
    # the obstacles and the checks decide grasps: the fullest world reaches fewer
    # than the empty one
    assert by_world[(True, True, True, 3)].sum() < by_world[(False, False, False, 0)].sum()


def _gcm_run(tmp_path, name, overrides, jit):
    out = tmp_path / name
    args = ["run", BOTTLE, "--out", out, "--force", "--quiet"]
    args += [x for o in overrides for x in ("--set", o)]
    res = run_gcm(*args, env={"GCM_JIT": "1" if jit else "0"}, cwd=tmp_path, timeout=None)
    assert res.returncode == 0, res.stderr[-2000:]
    assert "Traceback" not in res.stderr
    with open(out / "grasps.csv", newline="") as f:
        rows = list(csv.DictReader(f))
    # every reachable grasp is ranked (the clearance of a world without a collision pair
    # is infinite: the largest, not a NaN score)
    assert all(int(row["rank"]) > 0 for row in rows if row["reachable"] == "true")
    return [(row["reachable"], row["reason"]) for row in rows]


@pytest.mark.parametrize(
    ("robot_name", "world"),
    [
        ("panda", (False, False, False, 0)),  # pure kinematics: no collision pair at all
        ("ur5", (False, False, False, 0)),
        ("user_urdf", (True, True, True, 3)),
    ],
)
def test_gcm_run_decides_the_same_with_gcm_jit_on_and_off(
    tmp_path, user_urdf_spec, robot_name, world
):
    spec = str(user_urdf_spec) if robot_name == "user_urdf" else robot_name
    overrides = _overrides(spec, *world)
    on = _gcm_run(tmp_path, "on", overrides, jit=True)
    off = _gcm_run(tmp_path, "off", overrides, jit=False)
    assert on == off and len(on) == 18
    assert any(reachable == "true" for reachable, _ in on)


def test_a_bare_flange_decides_the_same_with_and_without_kernels(tmp_path):
    """No tool (the UR5's flange as the grasp frame): no gripper geometry, no contact pair."""
    spec = yaml.safe_load((ROBOT_SPECS / "ur5.yaml").read_text())
    del spec["tool"]
    spec["grasp_frame"], spec["name"] = "tool0", "ur5_bare"
    path = tmp_path / "ur5_bare.yaml"
    path.write_text(yaml.safe_dump(spec))
    robot = P.robot_from_config(load_config(BOTTLE, _overrides(path, *WORLDS[0])))
    grasps = P.generate_candidates(load_config(BOTTLE, [*FAST, *GRASP_SETS[0]]))
    seen = set()
    for world in WORLDS[::3]:  # each (table, object, self) once, with 0 obstacles
        cfg = load_config(BOTTLE, _overrides(path, *world))
        out = P.check_reachability(grasps, robot, cfg)
        with kernels.suppressed():
            ref = P.check_reachability(grasps, robot, cfg)
        np.testing.assert_array_equal(out["reason"], ref["reason"], err_msg=str(world))
        seen |= set(np.asarray(out["reason"]).tolist())
    assert {"", "collision_object", "collision_environment"} <= seen, seen
