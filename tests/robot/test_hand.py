"""The robot's hand (the links that may touch the object at a grasp), ``hand_links``,
``drop_collision`` and mimic joints, on small URDFs written by the tests."""

from __future__ import annotations

from pathlib import Path

import coal
import numpy as np
import pinocchio as pin
import pytest
from helpers import assert_one_line_error
from urdfs import write_arm

from gcm_pipeline.config.robot_spec import load_robot
from gcm_pipeline.errors import RobotSpecError
from gcm_pipeline.robot.collision import REASON_OBJECT, CollisionChecker, gripper_links
from gcm_pipeline.robot.collision.world import WorldShape

# tool0's pose in wrist_3_link (tests/urdfs.py): links fixed there with this origin are
# siblings of tool0 whose frame is tool0's (z out of the flange)
FLANGE = '<origin xyz="0 0.0823 0" rpy="-1.5707963 0 0"/>'
TCP = 0.10  # [m] along the flange's z
TCP_ONLY = f"tool: {{name: tcp_only, flange: tool0, tcp: {{xyz: [0, 0, {TCP}]}}}}\n"


def _fixed_box(name: str, size: str, xyz: str, mass: float = 0.05) -> str:
    """A box link fixed to the wrist link with tool0's origin (``mass`` 0: a marker)."""
    return (
        f'  <link name="{name}"><collision><origin xyz="{xyz}"/><geometry><box size="{size}"/>'
        f'</geometry></collision><inertial><mass value="{mass}"/>'
        '<inertia ixx="1e-5" iyy="1e-5" izz="1e-5" ixy="0" ixz="0" iyz="0"/></inertial></link>\n'
        f'  <joint name="{name}_joint" type="fixed"><parent link="wrist_3_link"/>'
        f'<child link="{name}"/>{FLANGE}</joint>\n'
    )


# a Jaco-like hand: fingers fixed to the wrist link beside the flange, 10 mm thick, their
# inner faces 25 mm either side of the TCP
FINGERS = _fixed_box("finger_left", "0.02 0.01 0.04", f"0 0.03 {TCP}") + _fixed_box(
    "finger_right", "0.02 0.01 0.04", f"0 -0.03 {TCP}"
)
# TIAGo's hand_safety_box: a box around the whole hand, beside the flange
SAFETY_BOX = _fixed_box("safety_box", "0.12 0.12 0.16", f"0 0 {TCP - 0.02}")


def _arm(folder: Path, links: str, spec_extra: str = "") -> Path:
    """``write_arm`` with ``links`` added to the URDF and a TCP-only tool on tool0."""
    spec = write_arm(folder, TCP_ONLY + spec_extra)
    spec.write_text(spec.read_text().replace("grasp_frame: tool0", "grasp_frame: tcp"))
    urdf = folder / "arm.urdf"
    urdf.write_text(urdf.read_text().replace("</robot>", links + "</robot>"))
    return spec


def _box_at_tcp(robot, q: np.ndarray, half_width: float) -> WorldShape:
    """A box object centred on the TCP, ``half_width`` along the fingers' axis (y)."""
    pose = robot.fk(q)[0]
    geometry = coal.Box(0.04, 2 * half_width, 0.03)  # x, y, z in the TCP frame
    return WorldShape("object", geometry, pose, "object")


def _reason(robot, q: np.ndarray, half_width: float, mode: str = "grasp") -> str:
    checker = CollisionChecker(robot, (_box_at_tcp(robot, q, half_width),), contact_tolerance=0.005)
    return str(checker.check(q[None], mode)[0])


def test_fingers_beside_the_flange_may_touch_the_object_by_the_contact_tolerance(tmp_path):
    # Kinova Jaco2, TIAGo: a TCP-only tool on a marker frame whose fingers are its siblings;
    # the fingers were arm links then, so a finger pad closing on the object collided
    # UR's ee_link: a massless marker box beside the flange is no part of the hand
    marker = _fixed_box("marker", "0.01 0.01 0.01", "0 0 -0.01", mass=0)
    robot = load_robot(_arm(tmp_path, FINGERS + marker))
    assert gripper_links(robot) == {"tool0", "finger_left", "finger_right"}
    assert robot.model_hand_links == ["finger_left", "finger_right"]
    q = robot.home
    assert _reason(robot, q, 0.027) == ""  # 2 mm into each finger: a grasp
    assert _reason(robot, q, 0.027, "approach") == REASON_OBJECT  # no contact on the way in
    assert _reason(robot, q, 0.033) == REASON_OBJECT  # 8 mm: deeper than the tolerance
    assert _reason(robot, q, 0.020) == ""  # 5 mm of air
    # a tool with collision shapes is the hand: the links beside its flange are not
    spec = _arm(tmp_path / "tool", FINGERS)
    tool = (
        "tool: {name: jaw, flange: tool0, tcp: {xyz: [0, 0, 0.1]}, collision: "
        "[{name: body, shape: box, size: [0.05, 0.05, 0.03], xyz: [0, 0, 0.02]}]}\n"
    )
    spec.write_text(spec.read_text().replace(TCP_ONLY, tool))
    assert gripper_links(load_robot(spec)) == {"tool0"}


def test_hand_links_lists_the_hand_and_refuses_what_is_not_one(cli, tmp_path):
    spec = _arm(tmp_path, FINGERS, "hand_links: [finger_left]\n")
    robot = load_robot(spec)
    assert gripper_links(robot) == {"finger_left"}
    assert _reason(robot, robot.home, 0.027) == REASON_OBJECT  # the right finger is arm
    text = spec.read_text()
    for links, fragments in [
        ("[finger_lft]", ("hand_links", "unknown link 'finger_lft'", "finger_left")),
        ("[finger_left, wrist_2_link]", ("hand_links", "'wrist_2_link'", "an arm link")),
        ("[]", ("hand_links", "empty list")),
    ]:
        spec.write_text(text.replace("[finger_left]", links))
        code, _, err = cli("robot", spec)
        assert_one_line_error(code, err, *fragments)
        with pytest.raises(RobotSpecError, match="hand_links"):
            load_robot(spec)


def test_drop_collision_removes_a_links_collision_geometry(cli, tmp_path):
    spec = _arm(tmp_path, FINGERS + SAFETY_BOX)
    robot = load_robot(spec)
    assert _reason(robot, robot.home, 0.027) == REASON_OBJECT  # the box holds the object
    spec.write_text(spec.read_text() + "drop_collision: [safety_box]\n")
    robot = load_robot(spec)
    assert _reason(robot, robot.home, 0.027) == ""
    names = [g.name for g in robot.build_geometry("collision").geometryObjects]
    assert not [n for n in names if n.startswith("safety_box")]
    assert [n for n in names if n.startswith("finger_left")]
    code, out, err = cli("robot", spec)
    assert code == 0, err
    assert "dropped      collision geometry of safety_box" in out
    text = spec.read_text()
    for links, fragments in [
        ("[safety_bx]", ("drop_collision", "unknown link 'safety_bx'", "safety_box")),
        ("[tool0]", ("drop_collision", "link 'tool0' has no collision geometry")),
    ]:
        spec.write_text(text.replace("[safety_box]", links))
        code, _, err = cli("robot", spec)
        assert_one_line_error(code, err, *fragments)


# a parallel jaw: the left finger's prismatic joint drives, the right one mimics it with
# multiplier -1 and an offset (the URDF's range of the right joint is written for the
# other sign, as the Robotiq 2F-85's mimic joints are)
JAW = """  <link name="palm"><collision><geometry><box size="0.04 0.08 0.03"/></geometry>
    </collision></link>
  <joint name="palm_joint" type="fixed"><parent link="tool0"/><child link="palm"/>
    <origin xyz="0 0 0.015"/></joint>
  <link name="left"><collision><origin xyz="0 0 0.05"/><geometry><box size="0.02 0.01 0.05"/>
    </geometry></collision></link>
  <joint name="left_joint" type="prismatic"><parent link="palm"/><child link="left"/>
    <axis xyz="0 1 0"/><limit lower="0" upper="0.04" effort="1" velocity="1"/></joint>
  <link name="right"><collision><origin xyz="0 0 0.05"/><geometry><box size="0.02 0.01 0.05"/>
    </geometry></collision></link>
  <joint name="right_joint" type="prismatic"><parent link="palm"/><child link="right"/>
    <axis xyz="0 1 0"/><limit lower="0" upper="0.04" effort="1" velocity="1"/>
    <mimic joint="left_joint" multiplier="-1" offset="0.005"/></joint>
"""


def test_locking_a_leader_puts_its_mimic_joints_where_they_follow(cli, tmp_path):
    # a mimic joint had to be locked by hand at a value of the user's choice, and its
    # URDF range refused the value the mechanism takes
    spec = _arm(tmp_path, JAW, "locked_joints: {left_joint: 0.03}\n")
    robot = load_robot(spec)
    assert robot.locked_values == {"left_joint": 0.03, "right_joint": pytest.approx(-0.025)}
    assert robot.nq == 6
    # the geometry is the full model's with both joints where the mechanism holds them
    full = pin.buildModelFromUrdf(str(tmp_path / "arm.urdf"))
    geom = pin.buildGeomFromUrdf(full, str(tmp_path / "arm.urdf"), pin.COLLISION)
    q_full = pin.neutral(full)
    for name, value in [*zip(robot.joint_names, robot.home, strict=True), ("left_joint", 0.03)]:
        q_full[full.joints[full.getJointId(name)].idx_q] = value
    q_full[full.joints[full.getJointId("right_joint")].idx_q] = -1 * 0.03 + 0.005
    want = pin.GeometryData(geom)
    pin.updateGeometryPlacements(full, full.createData(), geom, want, q_full)
    mine = robot.build_geometry("collision")
    got = pin.GeometryData(mine)
    pin.updateGeometryPlacements(robot.model, robot.model.createData(), mine, got, robot.home)
    for name in ("left_0", "right_0", "palm_0"):
        a = want.oMg[geom.getGeometryId(name)].homogeneous
        b = got.oMg[mine.getGeometryId(name)].homogeneous
        np.testing.assert_allclose(b, a, atol=1e-12)
    tcp = robot.fk(robot.home)[0]
    left = got.oMg[mine.getGeometryId("left_0")].translation
    right = got.oMg[mine.getGeometryId("right_0")].translation
    assert np.dot(left - right, tcp[:3, 1]) == pytest.approx(0.055)  # 0.03 - (-0.025)
    code, out, err = cli("robot", spec)
    assert code == 0, err
    assert "right_joint = -0.025 (mimics left_joint)" in out

    text = spec.read_text()
    spec.write_text(text.replace("{left_joint: 0.03}", "{left_joint: 0.03, right_joint: 0.03}"))
    code, _, err = cli("robot", spec)
    assert_one_line_error(
        code, err, "locked_joints.right_joint = 0.03", "mimics 'left_joint'", "= -0.025"
    )
    spec.write_text(text.replace("{left_joint: 0.03}", "{right_joint: -0.025}"))
    code, _, err = cli("robot", spec)
    assert_one_line_error(code, err, "'right_joint' is locked but mimics 'left_joint'")
    spec.write_text(text.replace("locked_joints: {left_joint: 0.03}\n", ""))
    code, _, err = cli("robot", spec)
    assert_one_line_error(code, err, "lock 'left_joint'", "the joints that mimic it follow")


def test_a_grasp_frame_on_a_wrist_link_leaves_the_link_before_its_joint_to_the_arm(tmp_path):
    """The grasp frame is the wrist link itself (no tool): the hand is that link and what is
    fixed to it; the link before the wrist joint, which the joint turns relative to the grasp
    frame, is arm (its clearance to the object counts; it may not press into the object)."""
    spec = write_arm(tmp_path)
    spec.write_text(spec.read_text().replace("grasp_frame: tool0", "grasp_frame: wrist_3_link"))
    robot = load_robot(spec)
    assert {"wrist_3_link", "tool0"} <= robot.hand_links
    assert "wrist_2_link" not in robot.hand_links
    assert "wrist_2_link" not in gripper_links(robot)
    # the same set as the spec's hand_links accepts: no link a free joint moves
    with pytest.raises(RobotSpecError, match="wrist_2_link"):
        load_robot(_with_hand_links(spec, "wrist_2_link", tmp_path))


def _with_hand_links(spec: Path, link: str, folder: Path) -> Path:
    out = folder / "hand_spec.yaml"
    out.write_text(spec.read_text() + f"hand_links: [{link}]\n")
    return out
