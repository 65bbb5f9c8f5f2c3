"""Robot specs and their tools read like run configs: one line naming the file, the key, the
value and the choices; accepted specs become the RobotSpec/ToolSpec the robot layer takes."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import yaml
from helpers import FLAT, ROBOT_SPECS, assert_one_line_error

from gcm_pipeline.config.robot_spec import load_spec
from gcm_pipeline.config.tool_spec import parse_pose, parse_tool
from gcm_pipeline.errors import RobotSpecError

UR5 = yaml.safe_load((ROBOT_SPECS / "ur5.yaml").read_text())
PANDA = yaml.safe_load((ROBOT_SPECS / "panda.yaml").read_text())


def _write(tmp_path: Path, spec: dict, name: str = "arm.yaml") -> Path:
    path = tmp_path / name
    path.write_text(yaml.safe_dump(spec, sort_keys=False))
    return path


def _with_tool(**changes) -> dict:
    spec = yaml.safe_load(yaml.safe_dump(UR5))
    spec["tool"].update(changes)
    return spec


def _error(path: Path) -> str:
    with pytest.raises(RobotSpecError) as info:
        load_spec(path)
    text = str(info.value)
    assert "\n" not in text
    prefix = f"robot spec {str(path.resolve())!r}: "
    assert text.startswith(prefix), text
    return text[len(prefix) :]


@pytest.mark.parametrize(
    ("spec", "message"),
    [
        (
            {**PANDA, "limit_margn": 0.1},
            "unknown key 'limit_margn' (did you mean 'limit_margin'?); valid keys here: "
            "description, drop_collision, grasp_frame, hand_links, home, joint_limits, "
            "limit_margin, locked_joints, model, name, tool",
        ),
        (
            _with_tool(collision=[{"shape": "sphere", "radus": 0.1}]),
            "unknown key 'tool.collision[0].radus' (did you mean 'tool.collision[0].radius'?); "
            "valid keys here: color, finger, length, matrix, mesh, name, quat, radius, rpy, "
            "rpy_deg, scale, shape, size, xyz",
        ),
        (
            _with_tool(mount={"rpydeg": [0, 0, 90]}),
            "unknown key 'tool.mount.rpydeg' (did you mean 'tool.mount.rpy_deg'?); valid keys "
            "here: matrix, quat, rpy, rpy_deg, xyz",
        ),
    ],
)
def test_an_unknown_key_is_named_with_the_closest_and_the_valid_keys(tmp_path, spec, message):
    assert _error(_write(tmp_path, spec)) == message


@pytest.mark.parametrize(
    ("change", "message"),
    [
        ({"limit_margin": "0.1"}, "limit_margin: Input should be a valid number (got '0.1')"),
        ({"limit_margin": True}, "limit_margin: Input should be a valid number (got True)"),
        ({"name": 5}, "name: Input should be a valid string (got 5)"),
        (
            {"home": {"panda_joint1": "0"}},
            "home.panda_joint1: Input should be a valid number (got '0')",
        ),
        ({"home": [0, None]}, "home[1]: Input should be a valid number (got None)"),
        ({"home": "up"}, "home: expected {joint: value} or a list of values [rad], got 'up'"),
        (
            {"locked_joints": [0.04]},
            "locked_joints: expected a mapping of keys, got list [0.04]",
        ),
        (
            {"joint_limits": {"panda_joint1": [1.0]}},
            "joint_limits.panda_joint1: expected [lower, upper] [rad or m], got [1.0]",
        ),
        (
            {"joint_limits": {"panda_joint1": [1.0, -1.0]}},
            "joint_limits.panda_joint1: needs lower < upper, got [1.0, -1.0]",
        ),
        ({"model": "panda"}, "model: expected a mapping of keys, got str 'panda'"),
        (
            {"model": {"example_robot_data": "panda", "urdf": "x.urdf"}},
            "model: needs exactly one of example_robot_data, robot_descriptions, urdf, "
            "got example_robot_data, urdf",
        ),
    ],
)
def test_a_value_of_the_wrong_type_names_the_key_and_the_value(tmp_path, change, message):
    assert _error(_write(tmp_path, {**PANDA, **change})) == message


@pytest.mark.parametrize("margin", [-0.1, -1, float("-inf"), float("nan")])
def test_a_negative_or_non_finite_limit_margin_is_refused(tmp_path, margin):
    message = _error(_write(tmp_path, {**PANDA, "limit_margin": margin}))
    assert message.startswith("limit_margin: Input should be "), message
    assert message.endswith(f"(got {margin!r})"), message


@pytest.mark.parametrize(
    ("pose", "message"),
    [
        (
            {"xyz": [0, 0, 0.15], "quat": [1, 0.2, 0, 0]},
            "tool.tcp.quat: [w, x, y, z] has norm 1.0198, not 1: not a rotation",
        ),
        ({"xyz": [0, 0.15]}, "tool.tcp.xyz: expected 3 values, got 2 ([0, 0.15])"),
        (
            {"rpy": [0, 0, 1], "rpy_deg": [0, 0, 90]},
            "tool.tcp: give one of rpy, rpy_deg, not several",
        ),
        (
            {"matrix": [[1, 0, 0], [0, 1, 0], [0, 0, 1]]},
            "tool.tcp.matrix: expected 4 rows of 4 numbers, got [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0],"
            " [0.0, 0.0, 1.0]]",
        ),
        (
            {"matrix": [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]], "xyz": [0, 0, 1]},
            "tool.tcp: give xyz inside the matrix, not beside it",
        ),
        ({"xyz": [0, 0, "0.15"]}, "tool.tcp.xyz[2]: Input should be a valid number (got '0.15')"),
        (
            {"xyz": [0, 0, 2000]},
            "tool.tcp.xyz[2]: Input should be less than or equal to 1000 (got 2000)",
        ),
    ],
)
def test_a_bad_pose_names_the_key(tmp_path, pose, message):
    assert _error(_write(tmp_path, _with_tool(tcp=pose))) == message


@pytest.mark.parametrize(
    ("shape", "message"),
    [
        (
            {"name": "b", "shape": "cube", "size": [0.1, 0.1, 0.1]},
            "tool.collision[0].shape: unknown value 'cube'; valid: box, capsule, cylinder, "
            "mesh, sphere",
        ),
        (
            {"name": "b", "size": [0.1, 0.1, 0.1]},
            "tool.collision[0].shape: missing; give one of box, capsule, cylinder, mesh, sphere",
        ),
        (
            {"name": "b", "shape": "cylinder", "radius": 0.02},
            "tool.collision[0]: shape 'cylinder' needs length [m]",
        ),
        (
            {"name": "b", "shape": "box", "size": [0.1, 0, 0.1]},
            "tool.collision[0].size[1]: Input should be greater than 0 (got 0)",
        ),
        (
            {"name": "b", "shape": "sphere", "radius": 0.1, "finger": "middle"},
            "tool.collision[0].finger: unknown value 'middle'; valid: left, right",
        ),
        (
            {"name": "b", "shape": "sphere", "radius": 0.1, "color": [1, 0]},
            "tool.collision[0].color: expected [r, g, b] or [r, g, b, a] in [0, 1], got [1.0, 0.0]",
        ),
    ],
)
def test_a_bad_shape_names_the_key_and_the_choices(tmp_path, shape, message):
    spec = _with_tool(collision=[shape])
    del spec["tool"]["fingers"]
    assert _error(_write(tmp_path, spec)) == message


def test_a_missing_or_empty_mesh_file_names_the_shape_and_the_file(tmp_path):
    cover = {"name": "cover", "shape": "mesh", "mesh": "meshes/cover.stl"}
    spec = _write(tmp_path, _with_tool(collision=[*UR5["tool"]["collision"], cover]))
    mesh = tmp_path / "meshes" / "cover.stl"
    assert _error(spec) == f"tool.collision[4].mesh: file {str(mesh)!r} does not exist"
    mesh.parent.mkdir()
    mesh.write_bytes(b"")
    assert _error(spec) == f"tool.collision[4].mesh: file {str(mesh)!r} is empty"
    mesh.write_text("solid x\nendsolid x\n")  # read by coal when the robot is built, not here
    assert load_spec(spec).tool.collision[4].mesh == mesh


def test_fingers_and_finger_shapes_go_together(tmp_path):
    spec = _with_tool()
    del spec["tool"]["fingers"]
    assert _error(_write(tmp_path, spec)) == (
        "tool: shapes finger_left, finger_right are fingers, but fingers is missing "
        "(give fingers: {opening: <m>})"
    )
    spec = _with_tool(collision=[{"shape": "sphere", "radius": 0.05}])
    assert _error(_write(tmp_path, spec)) == (
        "tool: fingers is given, but no shape is tagged 'finger: left' or 'finger: right'"
    )


def test_model_files_are_checked_after_validation_against_the_specs_folder(tmp_path):
    spec = {"name": "u", "model": {"urdf": "urdf/arm.urdf"}, "grasp_frame": "tool0"}
    urdf = tmp_path / "urdf" / "arm.urdf"
    assert _error(_write(tmp_path, spec)) == f"model.urdf: file {str(urdf)!r} does not exist"
    urdf.parent.mkdir()
    urdf.write_text("<robot name='arm'/>")
    spec["model"]["package_dirs"] = "pkgs"
    assert _error(_write(tmp_path, spec)) == (
        f"model.package_dirs: {str(tmp_path / 'pkgs')!r} is not a directory"
    )
    (tmp_path / "pkgs").mkdir()
    loaded = load_spec(_write(tmp_path, spec))
    assert loaded.urdf == urdf and loaded.package_dirs == (tmp_path / "pkgs",)


def test_accepted_forms_build_the_robot_layers_objects(tmp_path):
    (tmp_path / "cover.stl").write_text("solid x\nendsolid x\n")
    spec = _with_tool(
        mount={"rpy_deg": [0, 0, 90]},
        color=[1, 0, 0],
        collision=[
            *UR5["tool"]["collision"],
            {"shape": "mesh", "mesh": "cover.stl", "scale": 0.001},
            {"shape": "capsule", "radius": 0.01, "length": 0.1, "finger": "left"},
        ],
        fingers={"opening": 0.05, "axis": [0, 2, 0]},
    )
    spec.update(home=[0, -1.5708, 1.5708, -1.5708, -1.5708, 0], limit_margin=0)
    loaded = load_spec(_write(tmp_path, spec))
    tool = loaded.tool
    assert loaded.home == (0.0, -1.5708, 1.5708, -1.5708, -1.5708, 0.0)
    assert loaded.limit_margin == 0.0 and isinstance(loaded.limit_margin, float)
    assert tool.color == (1.0, 0.0, 0.0, 1.0) and tool.opening == 0.05
    np.testing.assert_array_equal(tool.axis, [0.0, 1.0, 0.0])
    np.testing.assert_allclose(tool.mount[:3, :3], [[0, -1, 0], [1, 0, 0], [0, 0, 1]], atol=1e-15)
    mesh, capsule = tool.collision[4:]
    assert (mesh.name, mesh.mesh, mesh.scale) == ("mesh_4", tmp_path / "cover.stl", (0.001,) * 3)
    assert (capsule.name, capsule.size, capsule.finger) == ("capsule_5", (0.01, 0.1), "left")
    assert tool.visual is tool.collision


def test_pose_forms_agree_and_parse_tool_reads_a_section_alone(tmp_path):
    a = parse_pose("p", {"xyz": [0.1, 0, 0.2], "rpy": [0, 0, np.pi / 2]})
    b = parse_pose("p", {"matrix": a.tolist()})
    np.testing.assert_array_equal(a, b)
    with pytest.raises(RobotSpecError, match=r"^p: unknown key 'xzy' \(did you mean 'xyz'\?\)"):
        parse_pose("p", {"xzy": [0, 0, 0]})
    tool = parse_tool("page", UR5["tool"], tmp_path)
    assert [s.name for s in tool.collision] == [s["name"] for s in UR5["tool"]["collision"]]
    with pytest.raises(RobotSpecError) as info:
        parse_tool("page", {"tcp": {"xyz": [0, 0, 0.1]}}, tmp_path)
    assert str(info.value) == (
        "page: tool.flange: name the model frame the tool is mounted on (e.g. tool0)"
    )


def test_gcm_robot_and_validate_report_a_bad_spec_in_one_line(cli, tmp_path):
    spec = _write(tmp_path, _with_tool(collision=[{"name": "b", "shape": "cone"}]))
    code, out, err = cli("robot", spec)
    assert_one_line_error(code, err, str(spec), "tool.collision[0].shape: unknown value 'cone'")
    assert out == ""
    code, out, err = cli("validate", FLAT, "--set", f"robot.spec={spec}")
    assert_one_line_error(code, err, "robot.spec: ", str(spec), "valid: box, capsule, cylinder")
    spec = _write(tmp_path, {**PANDA, "limit_margin": -0.1}, "neg.yaml")
    code, out, err = cli("robot", spec)
    assert_one_line_error(code, err, "neg.yaml", "limit_margin: Input should be greater than")
