"""The preflight checks of a config's files run before anything is written or replaced."""

from __future__ import annotations

import pytest
from helpers import FLAT, QUICK, ROOT, assert_one_line_error

from gcm_pipeline.cli import main
from gcm_pipeline.config import load_config
from gcm_pipeline.errors import InputError
from gcm_pipeline.pipeline import preflight


def test_a_bad_spec_is_reported_before_the_existing_output(cli, tmp_path):
    code, _, err = cli("run", FLAT, "--out", tmp_path / "run", "-q", *QUICK)
    assert code == 0, err
    code, _, err = cli("run", FLAT, "--out", tmp_path / "run", "--set", "robot.spec=pandaa", *QUICK)
    assert_one_line_error(code, err, "robot.spec: unknown robot 'pandaa'")
    assert "--force" not in err


def test_a_mesh_with_nan_vertices_is_refused(tmp_path, capfd):
    (tmp_path / "m.obj").write_text(
        "v 0 0 0\nv 1 0 0\nv 0 nan 0\nv 0 0 1\nf 1 2 3\nf 1 3 4\nf 1 2 4\nf 2 3 4\n"
    )
    cfg = tmp_path / "cfg.yaml"
    cfg.write_text(
        FLAT.read_text().replace(
            "environment: {table: {height: 0.0}}",
            "environment: {obstacles: [{shape: mesh, mesh: m.obj, pose: {xyz: [0.4, 0.3, 0.1]}}]}",
        )
    )
    with pytest.raises(InputError, match=r"environment.obstacles.0: mesh file .*m.obj.*not finite"):
        preflight(load_config(cfg))
    capfd.readouterr()
    code = main(["validate", str(cfg)])
    out, err = capfd.readouterr()  # file-descriptor level: the mesh library prints nothing
    assert_one_line_error(code, err, "vertex 2 is not finite")


def test_a_path_that_exists_but_is_no_file_is_not_called_missing(cli, tmp_path):
    cfg = ROOT / "configs" / "from_file.yaml"
    for odd in ("/dev/zero", str(tmp_path)):  # it was "grasp file not found: /dev/zero"
        code, _, err = cli("validate", cfg, "--set", f"candidates.path={odd}")
        assert_one_line_error(code, err, f"candidates.path: grasp file {odd} is not a regular file")


BOX = ROOT / "configs" / "box.yaml"  # a 6 x 6 x 15 cm box standing on the table at z = 0.075


@pytest.mark.parametrize(
    ("overrides", "depth_mm"),
    [
        ([], None),  # standing on the table: touching it is not sunk
        (["object.pose.xyz=[0.45,-0.15,0]"], 75.0),  # placed like the bottle: half in
        (["object.pose.xyz=[0.45,-0.15,0.0745]"], None),  # 0.5 mm in: within SUNK_DEPTH
        (["object.pose.xyz=[0.45,-0.15,0.05]"], 25.0),
        (["object.pose.xyz=[0.45,-0.15,0]", "environment.table=null"], None),  # no table
        (["object.pose.xyz=[3.0,-0.15,0]"], None),  # beside the 2 m table
        # wholly under the slab (z's sign slipped): how far its lowest point is below the top
        (["object.pose.xyz=[0.45,-0.15,-0.5]"], -575.0),
        (["object.pose.xyz=[0.45,-0.15,-0.5]", "environment.table.size=[2,2,0.5]"], 575.0),
        (["object.pose.xyz=[3.0,-0.15,-0.5]"], None),  # beside the table, below its top
    ],
)
def test_an_object_sunk_into_the_table_is_warned_about(cli, overrides, depth_mm):
    """`gcm validate` (and `gcm run`'s preflight) says how deep, why, and how to lift it.

    A negative ``depth_mm``: the object is wholly under the table's slab.
    """
    args = [a for o in overrides for a in ("--set", o)]
    code, _, err = cli("validate", BOX, *args)
    assert code == 0, err
    sunk = [line for line in err.splitlines() if "the table" in line and "raise its" in line]
    if depth_mm is None:
        assert sunk == []
    else:
        assert len(sunk) == 1
        if depth_mm < 0:
            depth_mm = -depth_mm
            assert f"lies under the table, {depth_mm:.1f} mm below its top" in sunk[0]
            assert "the arm must reach through the table" in sunk[0]
        else:
            assert f"reaches {depth_mm:.1f} mm into the table" in sunk[0]
        assert "a box is centred on its pose" in sunk[0]
        assert f"raise its pose's z by {depth_mm / 1e3:.4g}" in sunk[0]


def test_depth_into_the_table_of_each_shape():
    """coal's penetration depth for primitives, the lowest vertex for a mesh."""
    import numpy as np

    from gcm_pipeline.robot.collision import depth_below, depth_into, object_shape, table_shape

    table = table_shape((2.0, 2.0, 0.05), (0.0, 0.0), 0.1, np.eye(4))  # top at z = 0.1

    class Dims:
        radius, height, size = 0.04, 0.2, (0.1, 0.2, 0.3)

    def at(z, rpy_x=0.0):
        c, s = np.cos(rpy_x), np.sin(rpy_x)
        pose = np.eye(4)
        pose[:3, :3] = [[1, 0, 0], [0, c, -s], [0, s, c]]
        pose[:3, 3] = (0.3, 0.2, z)
        return pose

    mesh = ROOT / "tests" / "data" / "acronym" / "10f6e09036350e92b3f21f1137c3c347.obj"
    cases = [
        ("box", at(0.1), 0.15),  # centred on the top face: half its 0.3 m height
        ("box", at(0.25), 0.0),  # standing on it
        ("box", at(0.1, np.pi / 2), 0.1),  # turned: its 0.2 m side is vertical
        ("sphere", at(0.08), 0.06),
        ("cylinder", at(0.05), 0.05),  # stands on its base: the base 5 cm down
        ("cylinder", at(0.2), 0.0),
    ]
    for shape, pose, want in cases:
        got = depth_into(object_shape(shape, Dims, pose, np.eye(4)), table)
        assert got == pytest.approx(want, abs=1e-9), (shape, pose[2, 3], got)
    lowest = 0.0514294931319397  # the mug's lowest vertex above its frame [m] (scaled)
    for z, want in ((0.1 - lowest, 0.0), (0.1 - lowest - 0.03, 0.03), (0.5, 0.0)):
        shape = object_shape("mesh", None, at(z), np.eye(4), mesh=mesh, scale=0.0002682458)
        assert depth_into(shape, table) == pytest.approx(want, abs=1e-6), z
        # under the top, the slab or not: the lowest vertex
        below = max(0.0, 0.1 - lowest - z)
        assert depth_below(shape, 0.1) == pytest.approx(below, abs=1e-9), z
    # the lowest point under a plane, in the slab or far below it
    for shape, pose, want in [
        ("box", at(-2.0), 2.25),  # a 0.3 m box: lowest at -2.15
        ("box", at(-2.0, np.pi / 2), 2.2),  # turned: the 0.2 m side vertical
        ("sphere", at(0.08), 0.06),
        ("cylinder", at(-1.0), 1.1),  # its base at its pose
        ("cylinder", at(0.2), 0.0),  # above
    ]:
        got = depth_below(object_shape(shape, Dims, pose, np.eye(4)), 0.1)
        assert got == pytest.approx(want, abs=1e-9), (shape, pose[2, 3], got)


def test_preflight_takes_a_plain_mapping_like_every_stage(caplog):
    """The Python API's stage functions take a config or a plain mapping."""
    import yaml

    data = yaml.safe_load(BOX.read_text())
    data["object"]["pose"]["xyz"] = [0.45, -0.15, 0.0]  # half in the table
    data["output"] = {"dir": "unused"}
    with caplog.at_level("WARNING"):
        robot = preflight(data)
    assert robot.nq == 7
    assert any("reaches 75.0 mm into the table" in r.getMessage() for r in caplog.records)
