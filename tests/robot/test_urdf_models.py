"""Users' URDFs: the quirks real files have, each handled or refused in one line.

The URDFs are small UR5-like arms written by the tests (:mod:`urdfs`), plus
example-robot-data's Kinova (continuous joints) and UR3 loader (loads the UR5).
"""

from __future__ import annotations

import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pinocchio as pin
import pytest
import trimesh
from helpers import BOTTLE, FLAT, QUICK, ROBOT_SPECS, assert_one_line_error, run_gcm
from urdfs import UR5_JOINTS, arm_urdf, write_arm

from gcm_pipeline.config.robot_spec import load_robot, load_spec
from gcm_pipeline.errors import FrameNotFoundError, RobotSpecError
from gcm_pipeline.robot import model_files
from gcm_pipeline.robot.model_files import root_link
from gcm_pipeline.robot.urdf import CONTINUOUS_RANGE, resolve_frame
from gcm_pipeline.rundir.run import read_run

TCP_ONLY = "tool: {name: tcp_only, flange: tool0, tcp: {xyz: [0, 0, 0.15]}}\n"


def _with_grasp_frame(spec: Path, frame: str) -> Path:
    spec.write_text(spec.read_text().replace("grasp_frame: tool0", f"grasp_frame: {frame}"))
    return spec


def _box_stl(path: Path) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    trimesh.creation.box(extents=[0.06, 0.06, 0.04]).export(path)


# ------------------------------------------------------------ a link and a joint of one name


def test_a_link_and_a_joint_of_one_name_resolve_to_the_link(tmp_path):
    plain = load_robot(write_arm(tmp_path / "plain"))
    robot = load_robot(write_arm(tmp_path / "dup", flange_joint="tool0"))
    frame = robot.model.frames[robot.grasp_frame_id]
    assert frame.name == "tool0" and frame.type == pin.FrameType.BODY
    # both frames exist in the model: the joint's is not the one taken
    kinds = {
        robot.full_model.frames[i].type
        for i, f in enumerate(robot.full_model.frames)
        if f.name == "tool0"
    }
    assert kinds == {pin.FrameType.BODY, pin.FrameType.FIXED_JOINT}
    q = plain.random_configurations(50, seed=3)
    np.testing.assert_allclose(robot.fk(q), plain.fk(q), atol=1e-12)
    np.testing.assert_allclose(robot.fk_pinocchio(q), plain.fk(q), atol=1e-12)
    # a tool on that flange, and its geometry
    tooled = load_robot(
        _with_grasp_frame(write_arm(tmp_path / "t", TCP_ONLY, flange_joint="tool0"), "tcp")
    )
    np.testing.assert_allclose(
        tooled.fk(q)[:, :3, 3], (plain.fk(q) @ _translation(0.15))[:, :3, 3], atol=1e-12
    )
    assert tooled.build_geometry("collision").ngeoms == 7


def test_a_tool_on_a_flange_named_by_a_link_and_a_joint_with_a_locked_joint(tmp_path):
    # Sawyer's right_hand is a link and a joint: locking any joint (its head_pan) made
    # Pinocchio's buildReducedModel raise "Several frames match the filter" (a traceback)
    extra = TCP_ONLY + "locked_joints: {shoulder_pan_joint: 0.3}\n"
    robots = [
        load_robot(_with_grasp_frame(write_arm(tmp_path / name, extra, **kw), "tcp"))
        for name, kw in (("plain", {}), ("dup", {"flange_joint": "tool0"}))
    ]
    bare = load_robot(write_arm(tmp_path / "bare"))
    q = robots[0].random_configurations(50, seed=4)
    full_q = np.hstack([np.full((50, 1), 0.3), q])  # the locked joint at its value
    want = bare.fk(full_q) @ _translation(0.15)
    for robot in robots:
        assert robot.nq == 5
        np.testing.assert_allclose(robot.fk(q), want, atol=1e-12)
        np.testing.assert_allclose(robot.fk_pinocchio(q), want, atol=1e-12)
        assert robot.tool_tcp_link()[0] == "tool0"
        assert robot.build_geometry("collision").ngeoms == 7


def _translation(z: float) -> np.ndarray:
    t = np.eye(4)
    t[2, 3] = z
    return t


def test_an_ambiguous_frame_says_which_frames_share_the_name():
    model = pin.buildModelFromXML(arm_urdf())
    jid = model.getJointId("elbow_joint")
    model.addFrame(pin.Frame("elbow_joint", jid, 0, pin.SE3.Identity(), pin.FrameType.OP_FRAME))
    with pytest.raises(
        RobotSpecError,
        match=r"grasp frame 'elbow_joint' is ambiguous: 2 frames "
        r"have that name \(joint \(JOINT\), operational frame \(OP_FRAME\)\)",
    ):
        resolve_frame(model, "elbow_joint", "grasp frame", "robot 'x'")
    with pytest.raises(FrameNotFoundError, match=r"'tool9' is not a frame.*closest: tool0"):
        resolve_frame(model, "tool9", "grasp frame", "robot 'x'")


def test_gcm_run_on_a_urdf_whose_link_and_joint_share_a_name(cli, tmp_path):
    spec = _with_grasp_frame(write_arm(tmp_path / "dup", TCP_ONLY, flange_joint="tool0"), "tcp")
    code, out, err = cli("validate", BOTTLE, "--set", f"robot.spec={spec}")
    assert code == 0, err
    code, out, err = cli(
        "run", BOTTLE, "--set", f"robot.spec={spec}", "--out", tmp_path / "run", *QUICK
    )
    assert code == 0, err
    assert "is a TCP only (no collision shapes): the hand is not collision-checked" in err
    run = read_run(tmp_path / "run")
    assert 0 < int(run.grasps["reachable"].sum()) < len(run.grasps)


# ------------------------------------------------------------------------ continuous joints


def test_continuous_joints_are_revolute_over_two_turns(tmp_path):
    rev = load_robot(write_arm(tmp_path / "rev"))
    cont = load_robot(write_arm(tmp_path / "cont", joint_type="continuous", limits=None))
    assert cont.model.nq == cont.model.nv == cont.nq == 6
    assert set(cont.continuous_joints) == set(cont.joint_names)
    assert all(r == CONTINUOUS_RANGE for r in cont.continuous_joints.values())
    np.testing.assert_allclose(cont.lower, -2 * math.pi)
    np.testing.assert_allclose(cont.upper, 2 * math.pi)
    q = rev.random_configurations(100, seed=1)
    np.testing.assert_allclose(cont.fk(q), rev.fk(q), atol=1e-12)
    # a continuous joint's URDF lower/upper are ignored (the URDF standard), the spec's are not
    spec = write_arm(
        tmp_path / "lim",
        "joint_limits: {wrist_3_joint: [-9.0, 9.0]}\n",
        joint_type={"wrist_3_joint": "continuous"},
        limits=(-1.0, 1.0),
    )
    robot = load_robot(spec)
    assert robot.continuous_joints == {"wrist_3_joint": (-9.0, 9.0)}
    # wider than 2 pi: the spec's, less the limit margin (a stated range is a limit)
    np.testing.assert_allclose((robot.lower[5], robot.upper[5]), (-8.9, 8.9))
    np.testing.assert_allclose(robot.lower[:5], -1.0 + 0.1)


def test_kinova_with_continuous_joints_loads_and_its_fk_is_the_urdfs(tmp_path):
    robot = load_robot(
        _write(
            tmp_path,
            "name: kinova\nmodel: {example_robot_data: kinova}\n"
            "grasp_frame: j2s6s200_end_effector\n",
        )
    )
    assert robot.nq == robot.model.nv == 6
    assert sorted(robot.continuous_joints) == [
        "j2s6s200_joint_1",
        "j2s6s200_joint_4",
        "j2s6s200_joint_6",
    ]
    # Pinocchio's own model of the original URDF: a continuous joint is (cos, sin)
    original = pin.buildModelFromUrdf(str(robot.urdf_path))
    data = original.createData()
    fid = original.getFrameId("j2s6s200_end_effector", pin.FrameType.BODY)
    qs = robot.random_configurations(40, seed=2)
    ref = []
    for q in qs:
        full = []
        for j, name in enumerate(robot.joint_names):
            jm = original.joints[original.getJointId(name)]
            full += [math.cos(q[j]), math.sin(q[j])] if jm.nq == 2 else [q[j]]
        pin.framesForwardKinematics(original, data, np.array(full))
        ref.append(data.oMf[fid].homogeneous.copy())
    np.testing.assert_allclose(robot.fk(qs), np.array(ref), atol=1e-12)
    # IK on it: poses of random configurations are found again
    from gcm_pipeline import solve_ik

    res = solve_ik(robot, robot.fk(qs))
    assert res.success.all()
    np.testing.assert_allclose(robot.fk(res.q)[:, :3, 3], robot.fk(qs)[:, :3, 3], atol=2e-4)


def _write(folder: Path, text: str, name: str = "spec.yaml") -> Path:
    path = folder / name
    path.write_text(text)
    return path


def test_gcm_run_with_continuous_joints_equals_two_turn_revolute(cli, tmp_path):
    counts = {}
    for kind, kw in {"rev": {}, "cont": {"joint_type": "continuous", "limits": None}}.items():
        spec = _with_grasp_frame(write_arm(tmp_path / kind, TCP_ONLY, **kw), "tcp")
        code, _, err = cli(
            "run",
            BOTTLE,
            "--set",
            f"robot.spec={spec}",
            "--out",
            tmp_path / f"run_{kind}",
            *QUICK,
        )
        assert code == 0, err
        g = read_run(tmp_path / f"run_{kind}").grasps
        counts[kind] = (int(g["reachable"].sum()), np.asarray(g["reachable"]).tolist())
        q = np.asarray(g["q"])[np.asarray(g["reachable"], bool)]
        assert q.shape[1] == 6 and np.all(np.abs(q) <= 2 * math.pi)
    assert counts["rev"] == counts["cont"]
    assert counts["cont"][0] > 0


# ------------------------------------------------------------------------------------ meshes


def test_relative_and_package_meshes_resolve_without_package_dirs(tmp_path):
    # relative to the URDF's folder
    _box_stl(tmp_path / "rel" / "meshes" / "w3.stl")
    robot = load_robot(write_arm(tmp_path / "rel", mesh="meshes/w3.stl"))
    geom = robot.build_geometry("collision")
    mesh = next(g for g in geom.geometryObjects if g.name.startswith("wrist_3_link"))
    assert Path(mesh.meshPath) == (tmp_path / "rel" / "meshes" / "w3.stl").resolve()
    # package://my_arm/... with the URDF in my_arm/urdf/: the parent named my_arm is the package
    _box_stl(tmp_path / "ws" / "my_arm" / "meshes" / "w3.stl")
    spec = write_arm(tmp_path / "ws" / "my_arm" / "urdf", mesh="package://my_arm/meshes/w3.stl")
    geom = load_robot(spec).build_geometry("visual")
    assert any(g.meshPath.endswith("my_arm/meshes/w3.stl") for g in geom.geometryObjects)
    # a URDF away from its package: model.package_dirs names the folder holding it
    (tmp_path / "away").mkdir()
    (tmp_path / "away" / "arm.urdf").write_text(arm_urdf(mesh="package://my_arm/meshes/w3.stl"))
    spec = tmp_path / "away" / "spec.yaml"
    spec.write_text("name: a\nmodel: {urdf: arm.urdf}\ngrasp_frame: tool0\n")
    with pytest.raises(
        RobotSpecError,
        match=r"link 'wrist_3_link': visual mesh "
        r"'package://my_arm/meshes/w3.stl' not found .*model.package_dirs to the "
        r"folder that holds the package 'my_arm'",
    ):
        load_robot(spec)
    spec.write_text(
        spec.read_text().replace("arm.urdf}", f"arm.urdf, package_dirs: [{tmp_path / 'ws'}]}}")
    )
    assert load_robot(spec).build_geometry("collision").ngeoms == 7
    # the mink backend reads the same resolved URDF (MuJoCo has no package folders)
    from gcm_pipeline.robot.ik.mink_backend import mujoco_model

    mujoco_model(load_robot(write_arm(tmp_path / "rel", mesh="meshes/w3.stl")))


@pytest.mark.parametrize("case", ["missing", "corrupt"])
def test_a_bad_mesh_names_the_link_and_the_file_not_assimp(tmp_path, case):
    if case == "corrupt":
        (tmp_path / "meshes").mkdir()
        (tmp_path / "meshes" / "w3.stl").write_text(
            "solid x\n facet normal 0 0 1\n outer loop\n"
            " vertex 0 0 0\n endloop\n endfacet\nendsolid\n"
        )
    spec = write_arm(tmp_path, mesh="meshes/w3.stl")
    proc = run_gcm("validate", FLAT, "--set", f"robot.spec={spec}")
    line = assert_one_line_error(
        proc.returncode, proc.stderr, "link 'wrist_3_link'", "meshes/w3.stl"
    )
    assert "assimp" not in line and "/project/" not in line and "Hint" not in line
    if case == "corrupt":
        assert "STL: Invalid number of vertices" in line
    assert proc.stdout == ""


# ------------------------------------------------------------------------- malformed URDFs


@pytest.mark.parametrize(
    ("text", "fragment"),
    [
        ('<robot name="a"><link name="a">', "is not valid XML: no element found: line 1"),
        (
            arm_urdf().replace('<parent link="wrist_2_link"/>', '<parent link="nolink"/>'),
            "parent link [nolink] of joint [wrist_3_joint] not found",
        ),
        ("<sdf/>", "root element is <sdf>, expected <robot>"),
    ],
)
def test_a_malformed_urdf_is_one_line_and_nothing_of_urdfdom(tmp_path, text, fragment):
    (tmp_path / "arm.urdf").write_text(text)
    (tmp_path / "spec.yaml").write_text("name: a\nmodel: {urdf: arm.urdf}\ngrasp_frame: tool0\n")
    proc = run_gcm("validate", FLAT, "--set", f"robot.spec={tmp_path / 'spec.yaml'}")
    line = assert_one_line_error(proc.returncode, proc.stderr, "arm.urdf", fragment)
    assert proc.stderr.count("\n") == 1, proc.stderr  # urdfdom printed nothing of its own
    assert "at line" not in line and proc.stdout == ""


def test_urdf_joint_limits_of_1e308_are_refused_naming_the_joint(tmp_path):
    spec = write_arm(tmp_path, limits=(-1e308, 1e308))
    proc = run_gcm("validate", FLAT, "--set", f"robot.spec={spec}")
    assert_one_line_error(
        proc.returncode,
        proc.stderr,
        "joint 'shoulder_pan_joint' has the range [-1e+308, 1e+308]",
        "joint_limits: {shoulder_pan_joint: [lower, upper]}",
    )
    # the workaround: the spec's joint_limits
    limits = ", ".join(
        f"{j}: [-6.3, 6.3]"
        for j in (
            "shoulder_pan_joint",
            "shoulder_lift_joint",
            "elbow_joint",
            "wrist_1_joint",
            "wrist_2_joint",
            "wrist_3_joint",
        )
    )
    spec.write_text(spec.read_text() + f"joint_limits: {{{limits}}}\n")
    robot = load_robot(spec)
    np.testing.assert_allclose(robot.upper, 6.3 - 0.1)  # the stated range, less the margin
    assert np.isfinite(robot.max_reach) and robot.max_reach < 1.1


# ------------------------------------------------------- loaders that load another robot


def test_the_ur3_loader_that_loads_the_ur5_is_refused_with_the_ur3_urdf(tmp_path):
    spec = tmp_path / "ur3.yaml"
    spec.write_text("name: ur3\nmodel: {example_robot_data: ur3}\ngrasp_frame: tool0\n")
    with pytest.raises(RobotSpecError) as info:
        load_spec(spec)
    msg = str(info.value)
    assert "model.example_robot_data 'ur3' loads another robot's model: ur5_robot.urdf" in msg
    urdf = msg.split("use model: {urdf: ")[1].split("}")[0]
    assert urdf.endswith("ur_description/urdf/ur3_robot.urdf") and Path(urdf).is_file()
    # the workaround loads a UR3: its upper arm is 0.24365 m, the UR5's 0.425 m
    spec.write_text(f"name: ur3\nmodel: {{urdf: {urdf}}}\ngrasp_frame: tool0\n")
    ur3, ur5 = (
        load_robot(spec),
        load_robot(
            _write(
                tmp_path,
                "name: u\nmodel: {example_robot_data: ur5}\ngrasp_frame: tool0\n",
                "5.yaml",
            )
        ),
    )
    assert ur3.max_reach < ur5.max_reach - 0.25


def test_no_other_example_robot_data_loader_is_refused():
    from example_robot_data.robots_loader import ROBOTS

    refused = []
    for name, loader in ROBOTS.items():
        if not loader.urdf_filename:
            continue
        urdf = model_files._erd_paths(name)[0]
        try:
            model_files._check_same_robot("example_robot_data", name, urdf)
        except RobotSpecError:
            refused.append(name)
    assert refused == ["ur3"]


# --------------------------------------------------------------------- robot_descriptions


def _git(*args, cwd):
    subprocess.run(
        ["git", "-c", "user.name=t", "-c", "user.email=t@t", *args],
        cwd=cwd,
        check=True,
        capture_output=True,
    )


def _fake_cache(tmp_path: Path, cache_path: str, files: dict[str, str | Path]) -> tuple[Path, str]:
    """A robot_descriptions cache holding a git clone of ``files`` (text, or a path linked to).

    robot_descriptions checks the clone's commit: ``ROBOT_DESCRIPTION_COMMIT`` set to
    the clone's own commit makes it use ``<cache>/<cache_path>-<commit>/<cache_path>``.
    """
    repo = tmp_path / "build" / cache_path
    for rel, content in files.items():
        target = repo / rel
        target.parent.mkdir(parents=True, exist_ok=True)
        if isinstance(content, Path):
            target.symlink_to(content)
        else:
            target.write_text(content)
    _git("init", "-q", ".", cwd=repo)
    _git("add", "-A", cwd=repo)
    _git("commit", "-qm", "description", cwd=repo)
    sha = subprocess.run(
        ["git", "rev-parse", "HEAD"], cwd=repo, capture_output=True, text=True, check=True
    ).stdout.strip()
    cache = tmp_path / "cache"
    (cache / f"{cache_path}-{sha}").mkdir(parents=True)
    repo.rename(cache / f"{cache_path}-{sha}" / cache_path)
    return cache, sha


@pytest.fixture
def rd_env(monkeypatch):
    """robot_descriptions modules imported afresh (their import clones), no https."""
    monkeypatch.setenv("GIT_ALLOW_PROTOCOL", "file")  # never a real download in a test
    model_files._RD_PATHS.clear()
    for name in [m for m in sys.modules if m.startswith("robot_descriptions.")]:
        if not name.startswith("robot_descriptions._") and name != "robot_descriptions.loaders":
            monkeypatch.delitem(sys.modules, name)
    yield monkeypatch
    model_files._RD_PATHS.clear()


def test_a_robot_descriptions_model_loads_from_its_cache(tmp_path, rd_env, panda):
    from example_robot_data.robots_loader import getModelPath

    erd = Path(getModelPath("panda_description/urdf/panda.urdf")) / "panda_description"
    cache, sha = _fake_cache(
        tmp_path,
        "example-robot-data",
        {
            "robots/panda_description/urdf/panda.urdf": (erd / "urdf" / "panda.urdf").read_text(),
            "robots/panda_description/srdf/panda.srdf": (erd / "srdf" / "panda.srdf").read_text(),
            "robots/panda_description/meshes": erd / "meshes",
        },
    )
    rd_env.setenv("ROBOT_DESCRIPTIONS_CACHE", str(cache))
    rd_env.setenv("ROBOT_DESCRIPTION_COMMIT", sha)
    text = (ROBOT_SPECS / "panda.yaml").read_text()
    spec = tmp_path / "rd.yaml"
    spec.write_text(
        text.replace("example_robot_data: panda", "robot_descriptions: panda_description")
    )
    robot = load_robot(spec)
    assert str(robot.urdf_path).startswith(str(cache)) and robot.srdf_path is not None
    q = panda.random_configurations(30, seed=5)
    np.testing.assert_allclose(robot.fk(q), panda.fk(q), atol=1e-12)
    assert robot.build_geometry("collision").ngeoms == panda.build_geometry("collision").ngeoms
    assert root_link(robot.spec) == "panda_link0"
    # the command line, in a fresh process
    proc = run_gcm(
        "robot",
        spec,
        env={
            "ROBOT_DESCRIPTIONS_CACHE": str(cache),
            "ROBOT_DESCRIPTION_COMMIT": sha,
            "GIT_ALLOW_PROTOCOL": "file",
        },
    )
    assert proc.returncode == 0, proc.stderr
    assert "robot_descriptions 'panda_description'" in proc.stdout


def test_a_xacro_robot_descriptions_model_is_rendered(tmp_path, rd_env):
    pytest.importorskip("xacrodoc")
    body = arm_urdf().split("\n", 2)[2].rsplit("</robot>", 1)[0]  # links and joints
    xacro = (
        '<?xml version="1.0"?>\n<robot xmlns:xacro="http://www.ros.org/wiki/xacro" '
        'name="$(arg name)">\n<xacro:arg name="ur_type" default="ur5x"/>\n'
        '<xacro:arg name="name" default="ur"/>\n' + body + "</robot>\n"
    )
    cache, sha = _fake_cache(tmp_path, "ur_description", {"urdf/ur.urdf.xacro": xacro})
    rd_env.setenv("ROBOT_DESCRIPTIONS_CACHE", str(cache))
    rd_env.setenv("ROBOT_DESCRIPTION_COMMIT", sha)
    spec = tmp_path / "ur10e.yaml"
    spec.write_text(
        "name: ur10e\nmodel: {robot_descriptions: ur10e_description}\ngrasp_frame: tool0\n"
    )
    robot = load_robot(spec)
    assert robot.urdf.robot_name == "ur10e" and robot.nq == 6
    plain = load_robot(write_arm(tmp_path / "plain"))
    q = plain.random_configurations(20, seed=1)
    np.testing.assert_allclose(robot.fk(q), plain.fk(q), atol=1e-12)


def test_a_robot_descriptions_model_not_in_the_cache_is_one_line(tmp_path, rd_env):
    spec = tmp_path / "rd.yaml"
    spec.write_text("name: x\nmodel: {robot_descriptions: ur10e_description}\ngrasp_frame: tool0\n")
    proc = run_gcm(
        "validate",
        FLAT,
        "--set",
        f"robot.spec={spec}",
        env={"ROBOT_DESCRIPTIONS_CACHE": str(tmp_path / "cache"), "GIT_ALLOW_PROTOCOL": "file"},
    )
    assert_one_line_error(
        proc.returncode,
        proc.stderr,
        "model.robot_descriptions 'ur10e_description'",
        f"not in the cache {tmp_path / 'cache'}",
        "Universal_Robots_ROS2_Description",
        f"into {tmp_path / 'cache' / 'ur_description'}",
        warnings=True,  # the notice that robot_descriptions is about to clone
    )
    assert "Cloning" not in proc.stdout + proc.stderr
    # the failed clone leaves nothing behind: the message's advice (clone it there) works
    assert not (tmp_path / "cache" / "ur_description").exists()
    for text, fragment in [
        ("ur10f_description", "unknown robot_descriptions model 'ur10f_description'"),
        (
            "ur10e_mj_description",
            "is an MJCF (MuJoCo) model; a URDF one is needed: ur10e_description",
        ),
    ]:
        spec.write_text(f"name: x\nmodel: {{robot_descriptions: {text}}}\ngrasp_frame: tool0\n")
        with pytest.raises(RobotSpecError, match=re_escape(fragment)):
            load_spec(spec)


def re_escape(text: str) -> str:
    import re

    return re.escape(text)


# ------------------------------------------------------------------------------ gcm robot


def test_gcm_robot_prints_what_a_spec_configures(cli, tmp_path):
    code, out, err = cli("robot", "panda", "--out", tmp_path / "panda.html")
    assert code == 0, err
    for fragment in [
        "panda_joint4  revolute",
        "-2.9718   -0.1698   -2.3562",  # the model's range, 0.1 rad inside (limit_margin)
        "locked       panda_finger_joint1 = 0.04",
        "base panda_link0",
        "grasp frame panda_hand_tcp (link fixed to panda_hand)",
        "tool         none",
        "self-collision pairs checked",
        "panda_link0-panda_link2 (SRDF)",
        "panda_hand-panda_leftfinger (one body)",
        "panda_link6-panda_hand (adjacent)",
        "/robot, /grasps/reachable",
    ]:
        assert fragment in out, (fragment, out)
    assert (tmp_path / "panda.html").stat().st_size > 100_000
    code, out, err = cli("robot", "ur5")
    assert code == 0, err
    assert "flange tool0" in out and "fingers open 0.085 m along [0, 1, 0]" in out
    assert "finger_left (box 0.022 x 0.012 x 0.066, finger left)" in out
    spec = _with_grasp_frame(
        write_arm(
            tmp_path / "u",
            TCP_ONLY,
            flange_joint="tool0",
            joint_type={"wrist_3_joint": "continuous"},
        ),
        "tcp",
    )
    code, out, err = cli("robot", spec, "--out", tmp_path / "u.html")
    assert code == 0, err
    assert "wrist_3_joint        continuous (as revolute)   -6.2832    6.2832" in out
    assert "TCP only: no collision shapes, the hand is not collision-checked" in out
    assert "grasp frame tcp (operational frame on link tool0)" in out
    assert "6 link pairs not checked" in out and "15 self-collision pairs" in out
    assert (tmp_path / "u.html").is_file()
    code, out, err = cli("robot", "pandaa")
    assert_one_line_error(code, err, "unknown robot 'pandaa'")


# ------------------------------------------------------------------------------ exports


def test_moveit_export_when_the_runs_urdf_is_no_longer_valid_xml(cli, tmp_path):
    spec = _with_grasp_frame(write_arm(tmp_path / "arm", TCP_ONLY), "tcp")
    code, _, err = cli(
        "run", BOTTLE, "--set", f"robot.spec={spec}", "--out", tmp_path / "run", *QUICK
    )
    assert code == 0, err
    code, out, err = cli("export", tmp_path / "run", "--format", "moveit", "--top", "2")
    assert code == 0, err
    assert "robot root frame 'base_link'" in (tmp_path / "run" / "grasps_moveit.yaml").read_text()
    (tmp_path / "arm" / "arm.urdf").write_text("<robot><link name=")
    code, _, err = cli(
        "export", tmp_path / "run", "--format", "moveit", "--out", tmp_path / "m.yaml"
    )
    assert_one_line_error(code, err, "arm.urdf", "is not valid XML")
    assert not (tmp_path / "m.yaml").exists()


def test_root_link_is_the_moveit_frame_of_the_shipped_specs():
    assert root_link(load_spec("panda")) == "panda_link0"
    assert root_link(load_spec("ur5")) == "world"


def test_a_revolute_joint_without_lower_upper_takes_the_specs_range(tmp_path):
    spec = write_arm(tmp_path, limits=None)  # urdfdom reads [0, 0]
    with pytest.raises(RobotSpecError, match=re_escape(
        "joint 'shoulder_pan_joint' has an empty range [0.1, -0.1] after joint_limits and "
        "limit_margin (0.1) (the URDF gives it no lower/upper; give joint_limits: "
        "{shoulder_pan_joint: [lower, upper]})"
    )):  # fmt: skip
        load_robot(spec)
    joints = [j[0] for j in UR5_JOINTS]
    spec.write_text(
        spec.read_text() + "joint_limits: {" + ", ".join(f"{j}: [-3, 3]" for j in joints) + "}\n"
    )
    robot = load_robot(spec)
    np.testing.assert_allclose(robot.lower, -3.0 + 0.1)  # the spec's range, less the margin
    np.testing.assert_allclose(robot.upper, 3.0 - 0.1)


# ------------------------------------------------------------- zero axes and mimic joints


def _elbow(spec: Path, extra: str) -> Path:
    """Put ``extra`` into the elbow joint's element, before its closing tag."""
    urdf = spec.parent / "arm.urdf"
    lines = urdf.read_text().splitlines()
    i = next(k for k, line in enumerate(lines) if '<joint name="elbow_joint"' in line)
    lines[i] = lines[i].replace("</joint>", extra + "</joint>")
    urdf.write_text("\n".join(lines))
    return spec


def test_a_zero_joint_axis_is_one_line(cli, tmp_path):
    # Pinocchio normalises the axis: 0/0 made every joint frame NaN and the seed library's
    # k-d tree raised a traceback in the middle of the run
    spec = write_arm(tmp_path / "z")
    urdf = spec.parent / "arm.urdf"
    text = urdf.read_text()
    elbow = next(line for line in text.splitlines() if '<joint name="elbow_joint"' in line)
    axis = elbow.split('<axis xyz="')[1].split('"')[0]
    urdf.write_text(
        text.replace(elbow, elbow.replace(f'<axis xyz="{axis}"/>', '<axis xyz="0 0 0"/>'))
    )
    with pytest.raises(RobotSpecError, match=r"joint 'elbow_joint' has the zero axis '0 0 0'"):
        load_robot(spec)
    code, _, err = cli(
        "run", BOTTLE, "--set", f"robot.spec={spec}", "--out", tmp_path / "run", *QUICK
    )
    assert_one_line_error(code, err, "elbow_joint", "zero axis")
    assert not (tmp_path / "run").exists()


def test_a_free_mimic_joint_is_refused_a_locked_one_loads(tmp_path):
    # Pinocchio (without mimic=True) reads a mimic joint as an independent joint: the IK
    # moved it freely, so every answer was one the arm cannot take
    spec = _elbow(write_arm(tmp_path / "m"), '<mimic joint="shoulder_lift_joint"/>')
    with pytest.raises(
        RobotSpecError,
        match=r"joint 'elbow_joint' mimics 'shoulder_lift_joint' in the URDF.*"
        r"lock 'shoulder_lift_joint' \(locked_joints: \{shoulder_lift_joint: value\}",
    ):
        load_robot(spec)
    text = spec.read_text()
    spec.write_text(text + "locked_joints: {elbow_joint: 0.5}\n")
    with pytest.raises(
        RobotSpecError,
        match=r"joint 'elbow_joint' is locked but mimics 'shoulder_lift_joint', which is free",
    ):
        load_robot(spec)
    spec.write_text(text + "locked_joints: {elbow_joint: 0.5, shoulder_lift_joint: 0.5}\n")
    robot = load_robot(spec)
    assert robot.nq == 4 and "elbow_joint" not in robot.joint_names


@pytest.mark.parametrize(
    "extra",
    [
        "",  # the grasp frame on the base link itself
        # the shoulder link, whose one joint is locked (the joints after it stay free)
        "locked_joints: {shoulder_pan_joint: 0.0}\n",
    ],
)
def test_a_grasp_frame_no_free_joint_moves_is_one_line(cli, tmp_path, extra):
    # the IK can move nothing: every grasp read "out_of_reach", with the hint to move
    # the object closer
    spec = write_arm(tmp_path / "b", extra)
    frame = "base_link" if not extra else "shoulder_link"
    spec.write_text(spec.read_text().replace("grasp_frame: tool0", f"grasp_frame: {frame}"))
    with pytest.raises(RobotSpecError, match=rf"no free joint moves the grasp frame '{frame}'"):
        load_robot(spec)
    code, _, err = cli(
        "run", BOTTLE, "--set", f"robot.spec={spec}", "--out", tmp_path / "run", *QUICK
    )
    assert_one_line_error(code, err, "no free joint moves the grasp frame")
    assert not (tmp_path / "run").exists()


def test_a_free_prismatic_joint_is_one_line_that_says_to_lock_it(cli, tmp_path):
    # only revolute joints are solved; a prismatic torso or finger must be locked
    spec = write_arm(tmp_path / "p", joint_type={"elbow_joint": "prismatic"})
    code, _, err = cli(
        "run", BOTTLE, "--set", f"robot.spec={spec}", "--out", tmp_path / "run", *QUICK
    )
    assert_one_line_error(
        code, err, "robot.spec:", "'elbow_joint'", "only revolute", "locked_joints: {elbow_joint:"
    )
    assert not (tmp_path / "run").exists()
    spec.write_text(spec.read_text() + "locked_joints: {elbow_joint: 0.05}\n")
    robot = load_robot(spec)
    assert robot.nq == 5 and "elbow_joint" not in robot.joint_names


# ------------------------------------------------- free joints that do not move the grasp frame


def test_a_free_joint_that_does_not_move_the_grasp_frame_is_refused_with_the_lock(tmp_path):
    # a mobile manipulator's head or wheels, a hand's fingers beside its grasp frame: the
    # IK cannot set them (zero Jacobian columns), so they kept their seeds' arbitrary
    # values (random restarts, the seed library) in every solution and collision check
    head = (
        '  <link name="head_link"><collision><geometry><box size="0.05 0.05 0.05"/>'
        "</geometry></collision></link>\n"
        '  <joint name="head_joint" type="revolute"><parent link="base_link"/>'
        '<child link="head_link"/><origin xyz="-0.3 0 0.5"/><axis xyz="0 0 1"/>'
        '<limit lower="-1" upper="1" effort="1" velocity="1"/></joint>\n'
    )
    spec = write_arm(tmp_path)
    urdf = tmp_path / "arm.urdf"
    urdf.write_text(urdf.read_text().replace("</robot>", head + "</robot>"))
    proc = run_gcm("robot", str(spec))
    assert_one_line_error(
        proc.returncode,
        proc.stderr,
        "1 free joint(s) do not move the grasp frame 'tool0': head_joint",
        "locked_joints: {head_joint: 0}",
    )
    spec.write_text(spec.read_text() + "locked_joints: {head_joint: 0.5}\n")
    robot = load_robot(spec)
    assert robot.nq == 6 and robot.joint_names == tuple(j[0] for j in UR5_JOINTS)


def test_a_tcp_only_tool_on_a_hand_of_the_model_says_the_hand_is_checked(cli, tmp_path):
    # Unitree Z1, Bravo 7: the gripper's links are in the URDF, fixed below the flange a
    # TCP-only tool is mounted on; they are collision-checked, and the warning said not
    jaw = (
        '  <link name="jaw"><collision><geometry><box size="0.02 0.08 0.06"/></geometry>'
        "</collision></link>\n"
        '  <joint name="jaw_joint" type="fixed"><parent link="tool0"/><child link="jaw"/>'
        '<origin xyz="0 0 0.03"/></joint>\n'
    )
    spec = _with_grasp_frame(write_arm(tmp_path, TCP_ONLY), "tcp")
    urdf = tmp_path / "arm.urdf"
    urdf.write_text(urdf.read_text().replace("</robot>", jaw + "</robot>"))
    code, out, err = cli("robot", spec)
    assert code == 0, err
    assert "not collision-checked" not in out + err
    assert "the hand is the model's links, collision-checked: jaw" in out
    geometry = load_robot(spec).build_geometry()
    assert any(g.name.startswith("jaw") for g in geometry.geometryObjects)
