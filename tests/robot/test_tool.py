"""The robot spec's tool section: a gripper for the UR5's bare flange (real model, no mocks)."""

from __future__ import annotations

import coal
import numpy as np
import pinocchio as pin
import pytest
import yaml
from helpers import BOTTLE, FLAT, QUICK, ROBOT_SPECS, ROOT, assert_one_line_error, run_gcm

import gcm_pipeline as gcm
from gcm_pipeline.config import EnvironmentConfig, ObjectConfig
from gcm_pipeline.config.robot_spec import load_robot, load_spec
from gcm_pipeline.config.tool_spec import parse_pose
from gcm_pipeline.errors import FrameNotFoundError, RobotSpecError
from gcm_pipeline.geometry.dualquat import dq_to_matrix
from gcm_pipeline.pipeline import make_checker
from gcm_pipeline.robot.collision import REASON_OBJECT

UR5_SPEC = yaml.safe_load((ROBOT_SPECS / "ur5.yaml").read_text())


@pytest.fixture(scope="module")
def ur5():
    return load_robot("ur5")


def _spec(tmp_path, **tool_changes):
    spec = yaml.safe_load(yaml.safe_dump(UR5_SPEC))
    for key, value in tool_changes.items():
        if value is None:
            spec["tool"].pop(key, None)
        else:
            spec["tool"][key] = value
    path = tmp_path / "spec.yaml"
    path.write_text(yaml.safe_dump(spec))
    return path


def test_tcp_frame_sits_on_the_flange(ur5):
    assert ur5.grasp_frame == "gripper_tcp" and ur5.nq == 6
    qs = ur5.random_configurations(50, 2)
    data = ur5.model.createData()
    flange = ur5.model.getFrameId("tool0")
    offset = np.eye(4)
    offset[2, 3] = 0.15
    for q, tcp in zip(qs, ur5.fk(qs), strict=True):
        pin.framesForwardKinematics(ur5.model, data, q)
        np.testing.assert_allclose(tcp, data.oMf[flange].homogeneous @ offset, atol=1e-12)
    np.testing.assert_allclose(ur5.fk_pinocchio(qs), ur5.fk(qs), atol=1e-12)


def test_tool_is_in_the_collision_and_visual_models(ur5):
    flange = ur5.model.getFrameId("tool0")
    joint = ur5.model.frames[flange].parentJoint
    q = ur5.home
    tcp = ur5.fk(q)[0]
    for kind in ("collision", "visual"):
        gm = ur5.build_geometry(kind)
        tool = {g.name: g for g in gm.geometryObjects if g.name.startswith("tool/")}
        assert set(tool) == {"tool/coupling", "tool/body", "tool/finger_left", "tool/finger_right"}
        assert all(g.parentJoint == joint for g in tool.values())
        gd = pin.GeometryData(gm)
        pin.updateGeometryPlacements(ur5.model, ur5.model.createData(), gm, gd, q)
        left = np.linalg.inv(tcp) @ gd.oMg[gm.getGeometryId("tool/finger_left")].homogeneous
        right = np.linalg.inv(tcp) @ gd.oMg[gm.getGeometryId("tool/finger_right")].homogeneous
        # pads 85 mm apart (12 mm thick fingers), centred 23 mm behind the TCP
        np.testing.assert_allclose(left[:3, 3], [0, 0.0425 + 0.006, -0.023], atol=1e-12)
        np.testing.assert_allclose(right[:3, 3], [0, -0.0425 - 0.006, -0.023], atol=1e-12)
    vm = ur5.build_geometry("visual")
    body = vm.geometryObjects[vm.getGeometryId("tool/body")]
    assert body.overrideMaterial and isinstance(body.geometry, coal.Box)


def test_tool_pieces_are_the_gripper_and_touch_within_the_tolerance(ur5):
    """A sphere between the open fingers (pads at +-42.5 mm) as in the Panda's test."""
    tcp = ur5.fk(ur5.home)[0, :3, 3].tolist()

    def reason(radius, tol):
        obj = ObjectConfig.model_validate(
            {"shape": "sphere", "dims": {"radius": radius}, "pose": {"xyz": tcp}}
        )
        c = make_checker(ur5, EnvironmentConfig(contact_tolerance=tol, table=None), obj)
        return c.check(ur5.home)[0]

    c = make_checker(ur5, EnvironmentConfig())
    assert {c.link_names[i] for i in c.gripper_geoms} == {"tool0"}
    assert reason(0.040, 0.0) == ""
    assert reason(0.0445, 0.0) == REASON_OBJECT  # 2 mm into the pads
    assert reason(0.0445, 0.005) == ""
    assert reason(0.050, 0.005) == REASON_OBJECT  # 7.5 mm


def test_mink_backend_targets_the_tool_frame(ur5):
    q = ur5.random_configurations(12, 5)
    res = gcm.solve_ik(ur5, ur5.fk(q), backend="mink")
    assert res.success.mean() >= 0.9
    np.testing.assert_allclose(ur5.fk(res.q[res.success]), ur5.fk(q)[res.success], atol=2e-4)


def test_bottle_with_the_ur5_gives_a_plausible_answer(ur5):
    """Side grasps of the paper's bottle: most are reachable, and the gripper really is
    around the bottle (coal on the tool pieces and the bottle, directly)."""
    cfg = gcm.load_config(ROOT / "configs" / "bottle_side.yaml", overrides=["robot.spec=ur5"])
    result = gcm.Pipeline(cfg).run(write=False, progress=False)
    reach = np.asarray(result.grasps["reachable"], dtype=bool)
    assert 0.4 * len(reach) < reach.sum() < len(reach)
    gm = ur5.build_geometry("collision")
    gd, data = pin.GeometryData(gm), ur5.model.createData()
    bottle = coal.Cylinder(0.035, 0.22)
    tb = coal.Transform3s()
    tb.setTranslation(np.array([0.5, 0.0, 0.11]))
    pads = [gm.getGeometryId(n) for n in ("tool/finger_left", "tool/finger_right")]
    rows = np.flatnonzero(reach)
    for i in rows[:: max(1, len(rows) // 60)]:
        q = result.grasps["q"][i]
        np.testing.assert_allclose(ur5.fk(q)[0], dq_to_matrix(result.grasps["dq"][i]), atol=2e-4)
        pin.updateGeometryPlacements(ur5.model, data, gm, gd, q)
        for k in pads:  # one pad on each side of the bottle, none deeper than 5 mm inside
            m = gd.oMg[k].homogeneous
            tf = coal.Transform3s()
            tf.setRotation(np.ascontiguousarray(m[:3, :3]))
            tf.setTranslation(np.ascontiguousarray(m[:3, 3]))
            eroded = coal.Box(*(2 * np.asarray(gm.geometryObjects[k].geometry.halfSide) - 0.01))
            res = coal.CollisionResult()
            assert not coal.collide(eroded, tf, bottle, tb, coal.CollisionRequest(), res)


@pytest.mark.parametrize(
    "changes, match",
    [
        (
            {
                "collision": [{"name": "cover", "shape": "mesh", "mesh": "nowhere.stl"}],
                "fingers": None,
            },
            r"tool\.collision\[0\]\.mesh: file .*nowhere\.stl' does not exist",
        ),
        (
            {
                "collision": [{"name": "cover", "shape": "mesh", "mesh": "empty.stl"}],
                "fingers": None,
            },
            r"tool\.collision\[0\]\.mesh: file .*empty\.stl' is empty",
        ),
        (
            {"tcp": {"quat": [1.0, 0.1, 0, 0]}},
            r"tool\.tcp\.quat: \[w, x, y, z\] has norm 1\.00499, not 1: not a rotation",
        ),
        (
            {"tcp": {"matrix": [[1, 0, 0, 0], [0, 2, 0, 0], [0, 0, 1, 0.15], [0, 0, 0, 1]]}},
            r"tool\.tcp\.matrix: not a rigid transform",
        ),
        (
            {"tcp": {"matrix": [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0.15], [0, 0, 1, 1]]}},
            r"tool\.tcp\.matrix: not a rigid transform: last row",
        ),
        ({"mount": {"rpy_deg": [0, 0, 90], "quat": [1, 0, 0, 0]}}, r"tool\.mount: give one of"),
        ({"collision": "box"}, r"tool\.collision: Input should be a valid list \(got 'box'\)"),
        (
            {"fingers": None},
            r"tool: shapes finger_left, finger_right are fingers, but fingers is missing",
        ),
        ({"flange": None}, r"tool\.flange"),
        ({"gripper": "x"}, r"unknown key 'tool\.gripper'"),
        (
            {"collision": [{"name": "b", "shape": "box", "size": [0.1, -0.1, 0.1]}]},
            r"tool\.collision\[0\]\.size\[1\]: Input should be greater than 0 \(got -0\.1\)",
        ),
        (
            {"collision": [{"name": "b", "shape": "cone"}]},
            r"tool\.collision\[0\]\.shape: unknown value 'cone'; valid: box, capsule, cylinder",
        ),
    ],
)
def test_bad_tool_sections_name_the_key(tmp_path, changes, match):
    (tmp_path / "empty.stl").write_bytes(b"")
    with pytest.raises(RobotSpecError, match=match):
        load_spec(_spec(tmp_path, **changes))


def test_bad_flange_and_existing_grasp_frame(tmp_path):
    with pytest.raises(FrameNotFoundError, match="tool.flange 'tool9'.*closest: tool0"):
        load_robot(_spec(tmp_path, flange="tool9"))
    spec = yaml.safe_load(_spec(tmp_path).read_text())
    spec["grasp_frame"] = "wrist_3_link"
    (tmp_path / "dup.yaml").write_text(yaml.safe_dump(spec))
    with pytest.raises(RobotSpecError, match="grasp_frame 'wrist_3_link' already exists"):
        load_robot(tmp_path / "dup.yaml")


def test_unreadable_tool_mesh_fails_before_anything_is_written(tmp_path):
    (tmp_path / "bad.stl").write_text("solid x\nendsolid x\n")
    cover = {"name": "cover", "shape": "mesh", "mesh": "bad.stl"}
    spec = _spec(tmp_path, collision=[*UR5_SPEC["tool"]["collision"], cover])
    out = tmp_path / "run"
    proc = run_gcm(
        "run", BOTTLE, "--set", f"robot.spec={spec}", "--out", out, cwd=tmp_path, timeout=300
    )
    assert_one_line_error(proc.returncode, proc.stderr, "tool.collision[4].mesh")
    assert not out.exists()
    assert {p.name for p in tmp_path.iterdir()} == {"bad.stl", "spec.yaml"}


def test_tool_mesh_shapes_load(tmp_path):
    trimesh = pytest.importorskip("trimesh")
    trimesh.creation.box((0.05, 0.05, 0.02)).export(tmp_path / "cover.stl")
    cover = {"name": "cover", "shape": "mesh", "mesh": "cover.stl", "xyz": [0, 0, 0.1]}
    collision = [*UR5_SPEC["tool"]["collision"], cover]
    robot = load_robot(_spec(tmp_path, collision=collision))
    gm = robot.build_geometry("visual")
    cover = gm.geometryObjects[gm.getGeometryId("tool/cover")]
    assert cover.meshPath.endswith("cover.stl") and cover.geometry.num_tris == 12


def test_parse_pose_forms_agree():
    a = parse_pose("p", {"xyz": [0.1, 0, 0.2], "rpy_deg": [0, 0, 90]})
    b = parse_pose("p", {"xyz": [0.1, 0, 0.2], "quat": [np.sqrt(0.5), 0, 0, np.sqrt(0.5)]})
    c = parse_pose("p", {"matrix": a.tolist()})
    np.testing.assert_allclose(a, b, atol=1e-12)
    np.testing.assert_allclose(a, c, atol=1e-12)


def test_grasp_to_tool_applies_to_generators():
    base = gcm.load_config(ROOT / "configs" / "bottle_side.yaml")
    shifted = gcm.load_config(
        ROOT / "configs" / "bottle_side.yaml",
        overrides=["candidates.grasp_to_tool={xyz: [0, 0, -0.05], rpy_deg: [0, 0, 90]}"],
    )
    a = dq_to_matrix(gcm.generate_candidates(base)["dq"])
    b = dq_to_matrix(gcm.generate_candidates(shifted)["dq"])
    offset = np.eye(4)
    offset[:3, :3] = [[0, -1, 0], [1, 0, 0], [0, 0, 1]]
    offset[2, 3] = -0.05
    np.testing.assert_allclose(b, a @ offset, atol=1e-9)


def test_grasp_to_tool_that_turns_generated_grasps_approach_axis_is_refused():
    # mapping the generators' TCP (z = approach) onto an end-effector frame whose z is not
    # the approach (Kinova's j2s6s200_end_effector: approach along x) made the IK targets
    # right but the approach and retreat move along the wrong axis and the manifold's
    # angle bounds drop most triangles (20 of 126 kept on the bottle instead of 115)
    proc = run_gcm(
        "validate",
        BOTTLE,
        "--set",
        "candidates.grasp_to_tool={xyz: [0, 0, 0.03], rpy_deg: [0, -90, 0]}",
    )
    assert_one_line_error(
        proc.returncode,
        proc.stderr,
        "'grasp_to_tool' turns the approach axis (z) of cylinder_side grasps by 90 deg",
        "tool.tcp",
    )


def test_zero_reachable_says_why_and_what_to_try(tmp_path, caplog):
    """The UR5's bare flange (no tool) at the bottle: nothing reachable, and a hint."""
    spec = yaml.safe_load(yaml.safe_dump(UR5_SPEC))
    spec.pop("tool")
    spec["grasp_frame"] = "tool0"
    (tmp_path / "bare.yaml").write_text(yaml.safe_dump(spec))
    out = tmp_path / "run"
    proc = run_gcm(
        "run", BOTTLE, "--set", f"robot.spec={tmp_path / 'bare.yaml'}", *QUICK, "--out", out,
        cwd=tmp_path, timeout=300,
    )  # fmt: skip
    assert proc.returncode == 0, proc.stderr
    assert "reachable     0 / 1044" in proc.stdout
    hint = [ln for ln in proc.stdout.splitlines() if "no grasp is reachable (" in ln]
    assert hint and "collision_object" in hint[0] and "tool in its robot spec" in hint[0]
    assert "WARNING" in proc.stderr and "tool in its robot spec" in proc.stderr


def test_scene_draws_the_ur5_with_its_gripper(ur5):
    """The scene's robot is the visual model: the tool's boxes are drawn and posed with it."""
    from helpers import decode_commands

    from gcm_pipeline.config import Config
    from gcm_pipeline.geometry.dualquat import dq_from_matrix
    from gcm_pipeline.outputs import html
    from gcm_pipeline.pipeline.outputs import scene_options
    from gcm_pipeline.table import GraspTable

    q = ur5.home.copy()
    grasps = GraspTable({"dq": dq_from_matrix(ur5.fk(q)), "q": q[None], "rank": np.array([1])})
    cfg = Config.from_dict(
        {"robot": {"spec": "ur5"}, "candidates": {"source": "file", "path": "x.npy"}}
    )
    commands = decode_commands(html.render_scene_html(grasps, None, ur5, scene_options(cfg))[0])
    paths = {c["path"] for c in commands}
    for name in ("coupling", "body", "finger_left", "finger_right"):
        assert any(p.startswith(f"/meshcat/robot/visuals/tool/{name}") for p in paths), name


def test_readme_tool_section_is_the_shipped_one():
    readme = (ROOT / "docs" / "robots.md").read_text()  # the Tools section of the docs
    blocks = [b.split("```")[0] for b in readme.split("```yaml")[1:]]
    # the Tools section's block (the robot spec sketch before it has a model and a TCP-only tool)
    block = next(b for b in blocks if "\ntool:" in b and "\nmodel:" not in b)
    data = yaml.safe_load(block)
    shipped = {k: UR5_SPEC["tool"][k] for k in ("flange", "mount", "tcp", "fingers", "collision")}
    assert {k: data["tool"][k] for k in shipped} == shipped
    assert data["grasp_frame"] == UR5_SPEC["grasp_frame"]


def test_a_tool_may_be_a_tcp_only(tmp_path, ur5, caplog):
    spec = _spec(tmp_path, collision=None, fingers=None)
    with caplog.at_level("WARNING", logger="gcm_pipeline"):
        robot = load_robot(spec)
    assert "is a TCP only (no collision shapes): the hand is not collision-checked" in caplog.text
    assert robot.spec.tool.collision == () and robot.spec.tool.visual == ()
    for kind in ("collision", "visual"):
        names = [g.name for g in robot.build_geometry(kind).geometryObjects]
        assert not any(n.startswith("tool/") for n in names)
        assert len(names) == len(ur5.build_geometry(kind).geometryObjects) - 4
    q = ur5.random_configurations(20, seed=4)
    np.testing.assert_allclose(robot.fk(q), ur5.fk(q), atol=1e-12)  # the same TCP frame
    # no gripper geometry then (tool0 has none): every arm link is checked against the object
    cfg = _bottle_config()
    checker = make_checker(robot, cfg.environment, cfg.object)
    assert checker.gripper_geoms == ()
    assert list(checker.pair_kind).count("object") == checker.n_robot_geoms == 8
    spec = _spec(tmp_path, collision=[], fingers=None)
    assert load_robot(spec).spec.tool.collision == ()


def _bottle_config():
    from gcm_pipeline.config import load_config

    return load_config(ROOT / "configs" / "bottle_side.yaml", ["robot.spec=ur5"])


@pytest.mark.parametrize(
    ("changes", "key"),
    [
        (
            {"fingers": {"opening": 1e300}},
            "tool.fingers.opening: Input should be less than or equal to 1000 (got 1e+300)",
        ),
        (
            {"tcp": {"xyz": [0, 0, 1e30]}},
            "tool.tcp.xyz[2]: Input should be less than or equal to 1000 (got 1e+30)",
        ),
        (
            {"collision": [{"name": "b", "shape": "box", "size": [0.1, 1e20, 0.1]}]},
            "tool.collision[0].size[1]: Input should be less than or equal to 1000 (got 1e+20)",
        ),
    ],
)
def test_astronomic_tool_numbers_are_one_line(tmp_path, changes, key):
    spec = _spec(tmp_path, **changes)
    proc = run_gcm("validate", FLAT, "--set", f"robot.spec={spec}", timeout=300)
    assert_one_line_error(proc.returncode, proc.stderr, key)
