"""Plots of the ``families`` structure: drawn in the world, not in a chart atlas."""

from __future__ import annotations

import dataclasses
import json
import struct

import numpy as np
from helpers import ROOT
from scipy.spatial.transform import Rotation

import gcm_pipeline as gcm
from gcm_pipeline.cli import main
from gcm_pipeline.geometry.dualquat import dq_from_pos_quat
from gcm_pipeline.manifold.build import build_manifold
from gcm_pipeline.outputs.plots import write_plots
from gcm_pipeline.outputs.pose_view import approach_angles
from gcm_pipeline.table import GraspTable


def _png_size(path) -> tuple[int, int]:
    head = path.read_bytes()[:24]
    assert head[:8] == b"\x89PNG\r\n\x1a\n"
    return struct.unpack(">II", head[16:24])


def _dq(rotations: Rotation, pos=(0.5, 0.0, 0.1)) -> np.ndarray:
    xyzw = rotations.as_quat().reshape(-1, 4)
    return dq_from_pos_quat(
        np.tile(pos, (len(xyzw), 1)), np.column_stack((xyzw[:, 3], xyzw[:, :3]))
    )


def test_approach_angles_name_where_the_gripper_comes_from() -> None:
    down = Rotation.from_euler("x", 180, degrees=True)  # tool z -> world -z: from above
    along_y = Rotation.from_euler("x", -90, degrees=True)  # tool z -> world +y
    along_minus_x = Rotation.from_euler("y", -90, degrees=True)  # tool z -> world -x
    angles = approach_angles(_dq(Rotation.concatenate([down, along_y, along_minus_x])))
    np.testing.assert_allclose(angles[0, 1], -90.0, atol=1e-9)
    np.testing.assert_allclose(angles[1], [90.0, 0.0], atol=1e-9)
    np.testing.assert_allclose(abs(angles[2, 0]), 180.0, atol=1e-9)
    np.testing.assert_allclose(angles[2, 1], 0.0, atol=1e-9)


def test_grasps_from_straight_above_share_one_approach_direction() -> None:
    # four grasps turned about the vertical: one approach direction, one point in the panel
    yaw = Rotation.from_euler("z", np.array([0.0, 90.0, 180.0, 37.0])[:, None], degrees=True)
    angles = approach_angles(_dq(yaw * Rotation.from_euler("x", 180, degrees=True)))
    np.testing.assert_allclose(angles[:, 1], -90.0, atol=1e-9)
    np.testing.assert_array_equal(angles[:, 0], angles[0, 0])


def _table(n: int, rng: np.random.Generator) -> GraspTable:
    """Grasps on a 4 cm patch at three orientations a quarter turn apart, half reachable."""
    rot = Rotation.from_euler("z", rng.choice([0.0, 90.0, 180.0], n)[:, None], degrees=True) * (
        Rotation.from_euler("x", 180, degrees=True)
    )
    pos = np.column_stack((0.5 + rng.uniform(0, 0.04, n), rng.uniform(0, 0.04, n), np.full(n, 0.1)))
    xyzw = rot.as_quat()
    reach = rng.random(n) < 0.5
    return GraspTable(
        {
            "dq": dq_from_pos_quat(pos, np.column_stack((xyzw[:, 3], xyzw[:, :3]))),
            "origin": np.full(n, "candidate"),
            "reachable": reach,
            "manipulability": np.where(reach, rng.uniform(0.02, 0.1, n), np.nan),
            "reason": np.where(reach, "", "no_ik"),
            "patch": np.where(reach, rng.integers(0, 12, n), -1),
        }
    )


def test_families_plots_show_the_world_and_charts_stay_charts(tmp_path) -> None:
    grasps = _table(240, np.random.default_rng(3))
    fam = build_manifold(grasps, structure="families")
    assert fam.family.max() >= 2  # the three orientations are three families
    chart = build_manifold(grasps, structure="chart", projection="xy")
    widths = {}
    for name, m in (("families", fam), ("chart", chart)):
        out = tmp_path / name
        out.mkdir()
        paths = write_plots(grasps, m, {"candidates": len(grasps)}, out)
        assert {"manifold.png", "patches.png"} <= {p.name for p in paths}
        widths[name] = {p.name: _png_size(p)[0] for p in paths}
    # the world view: positions in 3-D beside the approach directions, twice a chart's width
    assert widths["families"]["manifold.png"] > 1.5 * widths["chart"]["manifold.png"]
    assert widths["families"]["patches.png"] > 1.5 * widths["chart"]["patches.png"]


def test_the_run_says_how_many_candidates_the_families_link(tmp_path, capsys) -> None:
    cfg = gcm.load_config(ROOT / "configs" / "box.yaml")
    assert cfg.manifold.structure == "families"
    code = main(
        [
            "run",
            str(ROOT / "configs" / "box.yaml"),
            "--out",
            str(tmp_path / "box"),
            "--set",
            "publish.html=false",
            "--set",
            "publish.plots=false",
        ]
    )
    assert code == 0
    line = next(s for s in capsys.readouterr().out.splitlines() if "triangles" in s)
    c = json.loads((tmp_path / "box" / "summary.json").read_text())["counts"]
    linked = c["candidates"] - sum(c["isolated_by_reason"].values())
    assert f"{c['triangles']} in {c['families']} families; " in line
    assert f"{linked} of {c['candidates']} candidates linked" in line
    assert "dropped" not in line  # the pruned chart triangles are a build step, not a loss


def test_families_plots_of_a_manifold_without_family_labels(tmp_path) -> None:
    grasps = _table(60, np.random.default_rng(5))
    fam = build_manifold(grasps, structure="families")
    bare = dataclasses.replace(fam, family=None, isolation=None)  # a hand-written manifold.npz
    names = {p.name for p in write_plots(grasps, bare, {"candidates": len(grasps)}, tmp_path)}
    assert {"manifold.png", "patches.png"} <= names
