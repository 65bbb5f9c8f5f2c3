"""Robot specs, model loading, vectorised kinematics against Pinocchio."""

from __future__ import annotations

import pickle
from pathlib import Path

import numpy as np
import pinocchio as pin
import pytest
from helpers import ROBOT_SPECS, ROOT
from urdfs import write_arm

from gcm_pipeline.config.robot_spec import available_robots, load_robot
from gcm_pipeline.errors import FrameNotFoundError, GcmError, RobotSpecError
from gcm_pipeline.robot.chain import JointFrames
from gcm_pipeline.robot.model import Robot

PANDA_SPEC = ROBOT_SPECS / "panda.yaml"


@pytest.fixture(scope="module")
def ur5() -> Robot:
    return load_robot("ur5")


def _write_spec(tmp_path: Path, text: str) -> Path:
    path = tmp_path / "spec.yaml"
    path.write_text(text)
    return path


def test_available_robots_ship_panda_and_ur5():
    assert {"panda", "ur5"} <= set(available_robots())


def test_every_shipped_spec_is_available_by_name():
    assert set(available_robots()) == {p.stem for p in ROBOT_SPECS.glob("*.yaml")}


def test_panda_model(panda: Robot):
    assert panda.nq == 7
    assert panda.grasp_frame == "panda_hand_tcp"
    assert panda.joint_names == tuple(f"panda_joint{i}" for i in range(1, 8))
    # the model's limits, 0.1 rad inside (the spec's limit_margin)
    np.testing.assert_allclose(panda.lower, panda.model.lowerPositionLimit + 0.1)
    np.testing.assert_allclose(panda.upper, panda.model.upperPositionLimit - 0.1)
    assert panda.within_limits(panda.home).all()
    np.testing.assert_allclose(panda.home[3], -2.356194)
    assert panda.urdf_path.is_file() and panda.srdf_path is not None and panda.srdf_path.is_file()
    assert (panda.mesh_dir / "meshes").is_dir()
    # the fingers are locked at the spec's value
    fid = panda.full_model.getJointId("panda_finger_joint1")
    assert panda.locked_q[panda.full_model.joints[fid].idx_q] == 0.04
    text = repr(panda)
    assert "panda" in text and "nq=7" in text and "panda_hand_tcp" in text


def test_load_by_path_matches_name(panda: Robot):
    for path in (PANDA_SPEC, ROBOT_SPECS / "panda.yaml", str(PANDA_SPEC)):
        other = load_robot(path)
        q = panda.random_configurations(5, 1)
        np.testing.assert_allclose(other.fk(q), panda.fk(q), atol=1e-15)


@pytest.mark.parametrize("name", ["panda", "ur5"])
def test_chain_fk_and_jacobian_equal_pinocchio(name: str):
    robot = load_robot(name)
    q = robot.random_configurations(200, 3)
    fk = robot.fk(q)
    jac = robot.jacobian(q)
    model, data, fid = robot.model, robot.data, robot.grasp_frame_id
    for i, qi in enumerate(q):
        pin.forwardKinematics(model, data, qi)
        pin.updateFramePlacements(model, data)
        np.testing.assert_allclose(fk[i], data.oMf[fid].homogeneous, rtol=0, atol=1e-12)
        ref = pin.computeFrameJacobian(model, data, qi, fid, pin.LOCAL_WORLD_ALIGNED)
        np.testing.assert_allclose(jac[i], ref, rtol=0, atol=1e-12)
    np.testing.assert_allclose(robot.fk_pinocchio(q), fk, rtol=0, atol=1e-12)


def test_max_reach_bounds_every_configuration(panda: Robot, ur5: Robot):
    for robot in (panda, ur5):
        p = robot.fk(robot.random_configurations(5000, 0))[:, :3, 3]
        assert np.linalg.norm(p - robot.shoulder, axis=1).max() <= robot.max_reach
        assert robot.max_reach <= robot.reach_bound
    # Panda: shoulder-elbow, elbow-wrist and wrist-TCP segments stretched in line
    assert panda.max_reach == pytest.approx(0.3266 + 0.3928 + 0.2281 + 2e-3, abs=1e-3)


def test_ur5_spec(ur5: Robot):
    assert ur5.nq == 6 and ur5.grasp_frame == "gripper_tcp"  # the TCP of its tool
    assert ur5.spec.tool is not None and ur5.spec.tool.flange == "tool0"
    assert ur5.within_limits(ur5.home).all()


def test_robot_with_tool_pickles(ur5: Robot):
    other = pickle.loads(pickle.dumps(ur5))
    q = ur5.random_configurations(3, 0)
    np.testing.assert_allclose(other.fk(q), ur5.fk(q))
    assert [g.name for g in other.build_geometry().geometryObjects][-1] == "tool/finger_right"


def test_robot_pickles(panda: Robot):
    other = pickle.loads(pickle.dumps(panda))
    q = panda.random_configurations(3, 0)
    np.testing.assert_allclose(other.fk(q), panda.fk(q))


def test_collision_geometry_is_reduced(panda: Robot):
    geom = panda.build_geometry("collision")
    assert geom.ngeoms > 0
    assert all(g.parentJoint < panda.model.njoints for g in geom.geometryObjects)
    with pytest.raises(RobotSpecError, match="valid: collision, visual"):
        panda.build_geometry("visuals")


def test_unknown_robot_lists_available():
    with pytest.raises(RobotSpecError, match=r"unknown robot 'pand'.*did you mean 'panda'.*ur5"):
        load_robot("pand")


def test_unknown_key_names_it_and_suggests(tmp_path: Path):
    text = PANDA_SPEC.read_text().replace("grasp_frame:", "grasp_fram:")
    with pytest.raises(RobotSpecError, match=r"key 'grasp_fram'.*mean 'grasp_frame'"):
        load_robot(_write_spec(tmp_path, text))
    text = PANDA_SPEC.read_text().replace("example_robot_data:", "example_robot_dat:")
    with pytest.raises(RobotSpecError, match="example_robot_dat"):
        load_robot(_write_spec(tmp_path, text))


def test_missing_grasp_frame_lists_close_names(tmp_path: Path):
    text = PANDA_SPEC.read_text().replace(
        "grasp_frame: panda_hand_tcp", "grasp_frame: panda_hand_tpc"
    )
    with pytest.raises(FrameNotFoundError, match=r"'panda_hand_tpc'.*closest: panda_hand_tcp"):
        load_robot(_write_spec(tmp_path, text))


def test_spec_errors(tmp_path: Path):
    with pytest.raises(RobotSpecError, match="does not exist"):
        load_robot(tmp_path / "nope.yaml")
    bad = PANDA_SPEC.read_text().replace("panda_finger_joint2: 0.04", "panda_fingr_joint2: 0.04")
    with pytest.raises(RobotSpecError, match="did you mean 'panda_finger_joint2'"):
        load_robot(_write_spec(tmp_path, bad))
    bad = PANDA_SPEC.read_text().replace("limit_margin: 0.1", "limit_margin: -1")
    with pytest.raises(RobotSpecError, match="limit_margin"):
        load_robot(_write_spec(tmp_path, bad))
    bad = PANDA_SPEC.read_text().replace("panda_joint4: -2.356194", "panda_joint4: 1.0")
    with pytest.raises(RobotSpecError, match="outside the joint limits"):
        load_robot(_write_spec(tmp_path, bad))
    assert issubclass(RobotSpecError, GcmError)


def test_limit_margin_and_joint_limits(tmp_path: Path, panda: Robot):
    text = PANDA_SPEC.read_text().replace("limit_margin: 0.1", "limit_margin: 0.05")
    text += "joint_limits:\n  panda_joint1: [-1.0, 5.0]\n"
    robot = load_robot(_write_spec(tmp_path, text))
    np.testing.assert_allclose(robot.lower[0], -1.0 + 0.05)
    np.testing.assert_allclose(robot.upper[0], panda.upper[0] + 0.1 - 0.05)
    np.testing.assert_allclose(robot.lower[1:], panda.lower[1:] - 0.1 + 0.05)


def test_ik_package_exports_resolve_without_mink():
    import subprocess
    import sys

    code = (
        "import sys, gcm_pipeline.robot.ik as r; "
        "assert all(hasattr(r, n) for n in r.__all__); "
        "assert 'mink' not in sys.modules and 'mujoco' not in sys.modules"
    )
    subprocess.run([sys.executable, "-c", code], check=True, cwd=ROOT)


def test_default_limit_margin_keeps_joints_off_their_limits(tmp_path: Path, panda: Robot) -> None:
    # shipped specs and a spec without the key: 0.1 rad inside the model's limits per side
    model = panda.model
    np.testing.assert_allclose(panda.lower, np.asarray(model.lowerPositionLimit) + 0.1)
    np.testing.assert_allclose(panda.upper, np.asarray(model.upperPositionLimit) - 0.1)
    text = "\n".join(
        line for line in PANDA_SPEC.read_text().splitlines() if "limit_margin" not in line
    )
    assert "limit_margin" not in text
    assert load_robot(_write_spec(tmp_path, text)).spec.limit_margin == 0.1
    # 0 on request: the model's own limits
    zero = load_robot(_write_spec(tmp_path, text + "\nlimit_margin: 0\n"))
    np.testing.assert_array_equal(zero.lower, np.asarray(model.lowerPositionLimit))
    np.testing.assert_array_equal(zero.upper, np.asarray(model.upperPositionLimit))
    ur5 = load_robot("ur5")
    np.testing.assert_allclose(ur5.upper, np.asarray(ur5.model.upperPositionLimit) - 0.1)


#: Joint axes a URDF may give near -z: a float32 export of -z, a hair off it, and further.
_NEAR_MINUS_Z = {
    "shoulder_pan_joint": "0 -8.742278e-08 -1",
    "shoulder_lift_joint": "0 1e-8 -1",
    "elbow_joint": "1e-6 0 -1",
    "wrist_1_joint": "0 0.6 -0.8",
    "wrist_2_joint": "0 0 -1",
    "wrist_3_joint": "-0.3 1e-5 -0.9",
}


def _arm_with_axes(folder: Path, axes: dict[str, str]) -> Path:
    """The test arm with the given joints' axes replaced."""
    spec = write_arm(folder)
    urdf = folder / "arm.urdf"
    text = urdf.read_text()
    for joint, axis in axes.items():
        head = f'<joint name="{joint}"'
        start = text.index(head)
        at = text.index("<axis xyz=", start)
        end = text.index("/>", at)
        text = text[:at] + f'<axis xyz="{axis}"' + text[end:]
    urdf.write_text(text)
    return spec


@pytest.mark.parametrize("compiled_on", [True, False])
def test_axes_near_minus_z_give_pinocchio_s_frames(tmp_path, compiled_on, compiled, numpy_code):
    """Regression: a joint axis within 1e-5 rad of -z (not exactly -z) put the joint frames
    of the collision checks and of the chain millimetres off Pinocchio's (4.7 mm for a float32
    -z), and a hair off (1e-8) made them NaN."""
    robot = load_robot(_arm_with_axes(tmp_path, _NEAR_MINUS_Z))
    q = robot.random_configurations(200, 9)
    frames = JointFrames(robot.model)
    got = np.stack((frames.compute(q) if compiled_on else numpy_code(frames.compute, q)).transforms)
    fk = robot.fk(q) if compiled_on else numpy_code(robot.fk, q)
    model, data = robot.model, robot.data
    for i, qi in enumerate(q):
        pin.forwardKinematics(model, data, qi)
        pin.updateFramePlacements(model, data)
        np.testing.assert_allclose(fk[i], data.oMf[robot.grasp_frame_id].homogeneous, atol=1e-12)
        _assert_frames_are_pinocchio_s(frames, got[:, i], model, data)


def _assert_frames_are_pinocchio_s(frames, got, model, data) -> None:
    """``got`` (J, 3, 4), one configuration's joint frames, against ``data.oMi`` (after FK)."""
    for j in range(1, model.njoints):
        # a point and a direction given in Pinocchio's joint frame, placed both ways
        rot, trans = frames.local(j, np.eye(3), np.array([0.01, -0.02, 0.03]))
        mine = got[j, :, :3] @ trans + got[j, :, 3]
        np.testing.assert_allclose(mine, data.oMi[j].act(np.array([0.01, -0.02, 0.03])), atol=1e-12)
        np.testing.assert_allclose(got[j, :, :3] @ rot, data.oMi[j].rotation, atol=1e-12)


@pytest.mark.parametrize("name", ["panda", "ur5", "user_arm"])
def test_joint_frames_equal_pinocchio_compiled_and_numpy(name, tmp_path, compiled, numpy_code):
    """Every joint's frame (the collision checks' kinematics): the compiled kernel and the
    NumPy code against Pinocchio's joint placements, and against each other to 1e-12."""
    robot = load_robot(write_arm(tmp_path) if name == "user_arm" else name)
    frames = JointFrames(robot.model)
    q = robot.random_configurations(300, 4)
    got = np.stack(frames.compute(q).transforms)  # (J, N, 3, 4), the rotated convention
    ref = np.stack(numpy_code(frames.compute, q).transforms)
    np.testing.assert_allclose(got, ref, rtol=0, atol=1e-12)
    model, data = robot.model, robot.data
    for i, qi in enumerate(q[:50]):
        pin.forwardKinematics(model, data, qi)
        _assert_frames_are_pinocchio_s(frames, got[:, i], model, data)
    # a single configuration, other shapes and dtypes: the kernel or the NumPy code's errors
    one = np.stack(frames.compute(q[:1].astype(np.float32)).transforms)
    np.testing.assert_allclose(one, got[:, :1], atol=1e-6)
    assert np.stack(frames.compute(q[:0]).transforms).shape == (model.njoints, 0, 3, 4)
