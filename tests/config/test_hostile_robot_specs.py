"""Broken robot specs are one line naming ``robot.spec`` and what is wrong in it."""

from __future__ import annotations

from pathlib import Path

import pytest
from helpers import FLAT, ROBOT_SPECS, assert_one_line_error

from gcm_pipeline.errors import RobotSpecError


def _spec(tmp_path, name: str, text: str) -> Path:
    path = tmp_path / name
    path.write_text(text)
    return path


def _panda_urdf() -> Path:
    from example_robot_data.robots_loader import getModelPath

    sub = "panda_description/urdf/panda.urdf"
    return Path(getModelPath(sub)) / sub


SPEC_TAIL = (
    "grasp_frame: panda_hand_tcp\n"
    "locked_joints: {panda_finger_joint1: 0.04, panda_finger_joint2: 0.04}\n"
)


def test_bad_robot_specs_are_found_by_validate(cli, tmp_path):
    panda = (ROBOT_SPECS / "panda.yaml").read_text()
    latin = tmp_path / "latin.yaml"
    latin.write_bytes(("# caf\xe9\n" + panda).encode("latin-1"))
    urdf = _panda_urdf()
    (tmp_path / "bad.srdf").write_text("<robot><disable_collisions link1=")
    (tmp_path / "copy.urdf").write_text(urdf.read_text())
    cases = {
        latin: "robot spec is not UTF-8 text",
        _spec(
            tmp_path, "a.yaml", f"name: p\nmodel: {{urdf: {urdf}, srdf: nope.srdf}}\n" + SPEC_TAIL
        ): "model.srdf",
        _spec(tmp_path, "b.yaml", "name: p\nmodel: {example_robot_data: pandaa}\n" + SPEC_TAIL): (
            "unknown example_robot_data robot 'pandaa'"
        ),
        _spec(tmp_path, "c.yaml", "name: p\nmodel: {urdf: nope.urdf}\n" + SPEC_TAIL): "model.urdf",
        _spec(
            tmp_path, "d.yaml", f"name: p\nmodel: {{urdf: {urdf}, srdf: bad.srdf}}\n" + SPEC_TAIL
        ): "is not readable XML",
        _spec(
            tmp_path,
            "e.yaml",
            panda.replace("panda_finger_joint1: 0.04", "panda_finger_joint1: 1000"),
        ): "locked_joints.panda_finger_joint1 = 1000 is outside the joint's range [0, 0.04]",
        # a copy of the URDF away from its meshes: the mesh is named, and the fix
        _spec(tmp_path, "f.yaml", "name: p\nmodel: {urdf: copy.urdf}\n" + SPEC_TAIL): (
            "link 'panda_link0': visual mesh 'package://example-robot-data/robots/"
            "panda_description/meshes/visual/link0.dae' not found"
        ),
    }
    for spec, fragment in cases.items():
        code, out, err = cli("validate", FLAT, "--set", f"robot.spec={spec}")
        assert_one_line_error(code, err, "robot.spec: ", fragment)
        assert out == ""


def test_a_robot_name_too_long_for_a_file_name_is_unknown(cli):
    # it used to be looked up as a file: OSError "File name too long", the name in full
    code, out, err = cli("validate", FLAT, "--set", "robot.spec=" + "a" * 300)
    assert_one_line_error(code, err, "robot.spec: ", "unknown robot 'aaaa")
    assert "(300 characters); valid: panda, ur5" in err and len(err) < 400
    from gcm_pipeline import load_robot

    with pytest.raises(RobotSpecError, match="unknown robot"):
        load_robot("a" * 5000)
