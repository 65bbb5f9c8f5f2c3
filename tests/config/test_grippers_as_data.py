"""The gripper registry as YAML data: importers, the antipodal sampler and ``robot.tool``.

Real data only: the shipped YAML files, GraspGen's Robotiq 2F-140 output in
``tests/data/graspgen`` and example-robot-data's UR5.
"""

from __future__ import annotations

import json

import numpy as np
import pinocchio as pin
import pytest
import yaml
from helpers import CONFIGS, DATA, QUICK, ROOT, assert_one_line_error

from gcm_pipeline.config import Config
from gcm_pipeline.config.gripper_spec import gripper_registry, load_gripper
from gcm_pipeline.config.robot_spec import load_robot, load_spec
from gcm_pipeline.errors import ConfigError, InputError
from gcm_pipeline.geometry.dualquat import dq_to_matrix
from gcm_pipeline.pipeline import generate_candidates
from gcm_pipeline.pipeline.sources import sampler_gripper
from gcm_pipeline.sources.grippers import shipped_grippers

REGISTRY = ROOT / "gcm_pipeline" / "grippers"
ROBOTIQ_140 = DATA / "graspgen" / "example_mesh_antipodal.yaml"
MUG_H5 = next((DATA / "acronym").glob("Mug_*.h5"))


@pytest.fixture(scope="module")
def ur5_robotiq():
    return load_robot("ur5", "robotiq_2f_85")


def test_the_registry_ships_four_grippers_read_from_their_files():
    names = ["franka_panda", "robotiq_2f_140", "robotiq_2f_85", "single_suction_cup_30mm"]
    assert shipped_grippers() == names
    assert sorted(p.stem for p in REGISTRY.glob("*.yaml")) == names
    reg = gripper_registry()
    assert [reg[n].name for n in names] == names
    # the sizes the data sheets and GraspGen's gripper configs give (see each file's comment)
    assert (reg["robotiq_2f_85"].max_width, reg["robotiq_2f_85"].base_to_tcp) == (0.085, 0.1303)
    assert (reg["robotiq_2f_140"].max_width, reg["robotiq_2f_140"].base_to_tcp) == (0.136, 0.195)
    assert reg["single_suction_cup_30mm"].kind == "suction"
    # every file says where its numbers come from
    for path in REGISTRY.glob("*.yaml"):
        assert "Sources:" in path.read_text(), path


def test_a_graspgen_robotiq_file_imports_by_name_as_the_hand_made_transform_did():
    """GraspGen's 2F-140 grasps: ``gripper: robotiq_2f_140`` puts the TCP where the README's
    ``grasp_to_tool: {xyz: [0, 0, 0.195]}`` did, and turns it so the fingers close along y."""
    base = {"source": "file", "path": str(ROBOTIQ_140), "format": "graspgen", "frame": "world"}
    by_name = Config.from_dict({"candidates": {**base, "gripper": "robotiq_2f_140"}})
    by_hand = Config.from_dict({"candidates": {**base, "grasp_to_tool": {"xyz": [0, 0, 0.195]}}})
    report: dict = {}
    named = dq_to_matrix(generate_candidates(by_name, report=report)["dq"])
    hand = dq_to_matrix(generate_candidates(by_hand)["dq"])
    assert len(named) == len(hand) == 40
    np.testing.assert_allclose(named[:, :3, 3], hand[:, :3, 3], atol=1e-9)
    np.testing.assert_allclose(named[:, :3, 2], hand[:, :3, 2], atol=1e-9)  # approach
    np.testing.assert_allclose(named[:, :3, 1], hand[:, :3, 0], atol=1e-9)  # closing: file x
    assert report["grasp_frame"]["gripper"] == "robotiq_2f_140"
    assert report["grasp_frame"]["chosen_by"] == "config"


def test_a_graspgen_file_naming_no_gripper_takes_the_robots_tool():
    """A GraspGen file names no gripper: on a robot carrying a registry hand
    (``robot.tool``) its grasps are that hand's, mapped as if ``candidates.gripper``
    named it, and the run says so; a file that names its gripper (ACRONYM's Franka
    hand) keeps that one whatever the robot carries."""
    base = {"source": "file", "path": str(ROBOTIQ_140), "format": "graspgen", "frame": "world"}
    named = Config.from_dict({"candidates": {**base, "gripper": "robotiq_2f_140"}})
    carried = Config.from_dict(
        {"robot": {"spec": "ur5", "tool": "robotiq_2f_140"}, "candidates": base}
    )
    report: dict = {}
    by_tool = dq_to_matrix(generate_candidates(carried, report=report)["dq"])
    np.testing.assert_allclose(by_tool, dq_to_matrix(generate_candidates(named)["dq"]), atol=1e-12)
    assert report["grasp_frame"]["chosen_by"] == "robot_tool"
    assert "the robot's tool" in report["grasp_frame"]["describe"]
    with pytest.raises(InputError, match="robot.tool"):  # no tool: refused, the key named
        generate_candidates(Config.from_dict({"candidates": base}))
    acronym = {"source": "file", "path": str(MUG_H5), "format": "acronym"}
    report = {}
    generate_candidates(
        Config.from_dict(
            {"robot": {"spec": "ur5", "tool": "robotiq_2f_85"}, "candidates": acronym}
        ),
        report=report,
    )
    assert report["grasp_frame"]["gripper"] == "franka_panda"
    assert report["grasp_frame"]["chosen_by"] == "file"  # the file names the Franka hand


def test_a_users_gripper_file_maps_like_the_shipped_one(tmp_path):
    doc = yaml.safe_load((REGISTRY / "robotiq_2f_140.yaml").read_text())
    doc["name"] = "my_140"
    (tmp_path / "grippers").mkdir()
    (tmp_path / "grippers" / "my_140.yaml").write_text(yaml.safe_dump(doc))
    cfg = tmp_path / "c.yaml"
    cfg.write_text(
        yaml.safe_dump(
            {
                "candidates": {
                    "source": "file",
                    "path": str(ROBOTIQ_140),
                    "frame": "world",
                    "gripper": "grippers/my_140.yaml",  # relative to the config's folder
                }
            }
        )
    )
    from gcm_pipeline.config import load_config

    mine = load_config(cfg)
    assert mine.candidates.gripper == str(tmp_path / "grippers" / "my_140.yaml")
    candidates = {k: v for k, v in mine.candidates.model_dump().items() if v is not None}
    shipped = Config.from_dict({"candidates": {**candidates, "gripper": "robotiq_2f_140"}})
    np.testing.assert_allclose(
        generate_candidates(mine)["dq"], generate_candidates(shipped)["dq"], atol=0
    )


def test_robot_tool_mounts_the_registry_gripper_on_the_ur5_flange(ur5_robotiq):
    robot = ur5_robotiq
    spec = load_spec("ur5", "robotiq_2f_85")
    assert spec.tool is not None and spec.tool.flange == "tool0"
    # the grasp frame: 0.1303 m out of the flange, fingers closing along the flange's x
    flange = robot.model.getFrameId("tool0")
    data = robot.model.createData()
    qs = robot.random_configurations(20, 3)
    want = load_gripper("robotiq_2f_85").to_tool("base")
    for q, tcp in zip(qs, robot.fk(qs), strict=True):
        pin.framesForwardKinematics(robot.model, data, q)
        np.testing.assert_allclose(
            np.linalg.inv(data.oMf[flange].homogeneous) @ tcp, want, atol=1e-12
        )
    np.testing.assert_allclose(want[:3, 3], [0, 0, 0.1303])
    # its shapes replace the spec's box gripper; the fingers open to 85 mm along x
    gm = robot.build_geometry("collision")
    tool = {g.name for g in gm.geometryObjects if g.name.startswith("tool/")}
    assert tool == {"tool/body", "tool/finger_left", "tool/finger_right"}
    gd = pin.GeometryData(gm)
    pin.updateGeometryPlacements(robot.model, data, gm, gd, robot.home)
    pin.framesForwardKinematics(robot.model, data, robot.home)
    in_flange = np.linalg.inv(data.oMf[flange].homogeneous)
    left = in_flange @ gd.oMg[gm.getGeometryId("tool/finger_left")].homogeneous
    np.testing.assert_allclose(left[:3, 3], [0.0425 + 0.01, 0, 0.11125], atol=1e-12)


def test_the_sampler_sizes_its_hand_by_the_robots_tool():
    """A box 78 mm across: too wide for the Panda's hand (75 mm usable), not for the 2F-85."""
    doc = {
        "robot": {"spec": "ur5"},
        "object": {
            "shape": "box",
            "dims": {"size": [0.078, 0.078, 0.2]},
            "pose": {"xyz": [0.5, 0, 0.1]},
        },
        "candidates": {"source": "antipodal", "count": 30},
    }
    panda_hand = Config.from_dict(doc)
    assert sampler_gripper(panda_hand).name == "franka_panda"
    with pytest.raises(InputError, match="no collision-free antipodal grasp.*franka_panda"):
        generate_candidates(panda_hand)
    robotiq = Config.from_dict({**doc, "robot": {"spec": "ur5", "tool": "robotiq_2f_85"}})
    assert sampler_gripper(robotiq).name == "robotiq_2f_85"
    table = generate_candidates(robotiq)
    assert len(table) == 30
    assert np.all(table["width"] <= 0.085 - 0.005) and np.all(table["width"] > 0.075)


def test_the_ur5_with_a_registry_robotiq_runs_the_bottle_example(tmp_path, cli):
    out = tmp_path / "run"
    code, _, err = cli(
        "run", CONFIGS / "bottle_side_ur5.yaml", "--out", out, "--quiet", *QUICK,
        "--set", "densify.subdivisions=1",
    )  # fmt: skip
    assert code == 0, err
    summary = json.loads((out / "summary.json").read_text())
    assert summary["config"]["robot"] == summary["config"]["robot"] | {
        "spec": "ur5",
        "tool": "robotiq_2f_85",
    }
    grasps = np.genfromtxt(out / "grasps.csv", delimiter=",", names=True, dtype=None)
    q = np.load(out / "configurations.npz")["q"]
    ok = np.asarray(grasps["reachable"]).astype(str) == "True"
    assert ok.sum() > 0.5 * len(ok)
    # the solutions put the registry 2F-85's TCP (not the spec's box tool's) on the grasps
    tcp = load_robot("ur5", "robotiq_2f_85").fk(q[ok])
    pos = np.stack([grasps[k][ok] for k in ("x", "y", "z")], axis=1)
    np.testing.assert_allclose(tcp[:, :3, 3], pos, atol=2e-4)
    box_tool = load_robot("ur5").fk(q[ok])
    assert np.linalg.norm(box_tool[:, :3, 3] - pos, axis=1).min() > 0.015


def _gripper_file(tmp_path, **changes):
    doc = yaml.safe_load((REGISTRY / "robotiq_2f_85.yaml").read_text())
    for key, value in changes.items():
        doc[key] = value
    path = tmp_path / "g.yaml"
    path.write_text(yaml.safe_dump(doc))
    return path


def _bad(tmp_path, kind):
    if kind == "negative":
        body = {"name": "body", "shape": "box", "size": [0.086, -0.066, 0.075]}
        return str(_gripper_file(tmp_path, collision=[body])), ("g.yaml", "collision[0].size[1]")
    if kind == "unknown_key":
        return str(_gripper_file(tmp_path, max_widht=0.1)), ("g.yaml", "'max_widht'", "max_width")
    if kind == "missing":
        return str(tmp_path / "nope.yaml"), ("nope.yaml", "not found")
    return "robotiq_2f58", ("'robotiq_2f58'", "robotiq_2f_85", "single_suction_cup_30mm")


@pytest.mark.parametrize("key", ["candidates.gripper", "robot.tool"])
@pytest.mark.parametrize("kind", ["negative", "unknown_key", "missing", "unknown_name"])
@pytest.mark.parametrize("command", ["validate", "run"])
def test_a_bad_gripper_is_one_line_exit_2_and_nothing_written(tmp_path, cli, key, kind, command):
    value, fragments = _bad(tmp_path, kind)
    cfg = tmp_path / "c.yaml"
    doc = {
        "robot": {"spec": "ur5"},
        "object": {"shape": "cylinder", "dims": {"radius": 0.035, "height": 0.22}},
        "candidates": {"source": "antipodal", "count": 10},
    }
    section, name = key.split(".")
    doc[section][name] = value
    cfg.write_text(yaml.safe_dump(doc))
    out = tmp_path / "run"
    args = ("run", cfg, "--out", out, *QUICK) if command == "run" else ("validate", cfg)
    code, stdout, err = cli(*args)
    assert_one_line_error(code, err, key, *fragments)
    assert not out.exists() and stdout == ""


@pytest.mark.parametrize(
    ("changes", "fragments"),
    [
        ({"robot": {"spec": "panda", "tool": "robotiq_2f_85"}}, ("robot.tool", "'panda'", "tool0")),
        (
            {
                "candidates": {
                    "source": "antipodal",
                    "count": 5,
                    "gripper": "single_suction_cup_30mm",
                }
            },
            ("candidates.source 'antipodal'", "'single_suction_cup_30mm'", "suction"),
        ),
        (
            {
                "robot": {"spec": "ur5", "tool": "robotiq_2f_85"},
                "candidates": {"source": "antipodal", "count": 5, "gripper": "franka_panda"},
            },
            ("candidates.gripper", "'franka_panda'", "robot.tool 'robotiq_2f_85'"),
        ),
    ],
)
def test_grippers_that_do_not_fit_are_refused(tmp_path, cli, changes, fragments):
    doc = {
        "robot": {"spec": "ur5"},
        "object": {"shape": "cylinder", "dims": {"radius": 0.035, "height": 0.22}},
        "candidates": {"source": "antipodal", "count": 5},
        **changes,
    }
    cfg = tmp_path / "c.yaml"
    cfg.write_text(yaml.safe_dump(doc))
    out = tmp_path / "run"
    code, _, err = cli("run", cfg, "--out", out, *QUICK)
    assert_one_line_error(code, err, *fragments)
    assert not out.exists()


def test_robot_tool_on_a_bare_arm_spec_without_a_tool_section_says_what_it_needs(tmp_path, cli):
    spec = tmp_path / "bare.yaml"
    spec.write_text(
        yaml.safe_dump(
            {"name": "bare", "model": {"example_robot_data": "ur5"}, "grasp_frame": "tool0"}
        )
    )
    cfg = tmp_path / "c.yaml"
    cfg.write_text(
        yaml.safe_dump(
            {
                "robot": {"spec": str(spec), "tool": "robotiq_2f_85"},
                "object": {"shape": "cylinder", "dims": {"radius": 0.035, "height": 0.22}},
                "candidates": {"source": "cylinder_side", "count": 9},
            }
        )
    )
    code, _, err = cli("validate", cfg)
    line = assert_one_line_error(
        code, err, "robot.tool", "'bare'", "'robotiq_2f_85'", "tool section"
    )
    assert "its hand is part of its model" not in line  # a bare arm has no hand


@pytest.mark.parametrize("what", ["dir", "device"])
def test_a_gripper_mesh_that_is_no_regular_file_is_named_so(tmp_path, what):
    mesh = tmp_path / "m.stl" if what == "dir" else "/dev/zero"
    if what == "dir":
        mesh.mkdir()
    body = {"name": "body", "shape": "mesh", "mesh": str(mesh)}
    path = _gripper_file(
        tmp_path,
        collision=[
            body,
            *yaml.safe_load((REGISTRY / "robotiq_2f_85.yaml").read_text())["collision"][1:],
        ],
    )
    with pytest.raises(ConfigError, match=r"collision\[0\]\.mesh: file .* is not a regular file"):
        load_gripper(path)


def test_a_gripper_mesh_that_does_not_load_is_named_by_the_gripper_file(tmp_path, cli):
    (tmp_path / "body.stl").write_text("not a mesh\n")
    body = {"name": "body", "shape": "mesh", "mesh": "body.stl"}
    fingers = yaml.safe_load((REGISTRY / "robotiq_2f_85.yaml").read_text())["collision"][1:]
    gripper = _gripper_file(tmp_path, collision=[body, *fingers])
    cfg = tmp_path / "c.yaml"
    doc = {
        "robot": {"spec": "ur5", "tool": str(gripper)},
        "object": {"shape": "cylinder", "dims": {"radius": 0.035, "height": 0.22}},
        "candidates": {"source": "cylinder_side", "count": 9},
    }
    cfg.write_text(yaml.safe_dump(doc))
    out = tmp_path / "run"
    code, _, err = cli("run", cfg, "--out", out, *QUICK)
    line = assert_one_line_error(code, err, "robot.tool: gripper", "g.yaml", "collision[0].mesh")
    assert "ur5.yaml" not in line  # the robot spec is not at fault
    assert not out.exists()


def test_a_suction_gripper_file_with_fingers_is_refused(tmp_path):
    doc = yaml.safe_load((REGISTRY / "single_suction_cup_30mm.yaml").read_text())
    doc["max_width"] = 0.05
    path = tmp_path / "cup.yaml"
    path.write_text(yaml.safe_dump(doc))
    with pytest.raises(ConfigError, match=r"cup\.yaml.*suction gripper has no fingers.*max_width"):
        load_gripper(path)


def test_the_same_gripper_file_in_both_keys_is_no_mismatch(tmp_path):
    path = _gripper_file(tmp_path)
    cfg = Config.from_dict(
        {
            "robot": {"spec": "ur5", "tool": str(path)},
            "object": {"shape": "cylinder", "dims": {"radius": 0.035, "height": 0.22}},
            "candidates": {"source": "antipodal", "count": 5, "gripper": str(path)},
        }
    )
    assert sampler_gripper(cfg).path == path.resolve()
