"""gcm export: MoveIt YAML, Parquet and NPZ read back and compared with grasps.csv.

The run behind these tests imports a GraspGen file (so a per-candidate
``score`` column flows through to the exports) of top grasps on a box.
"""

from __future__ import annotations

import csv
import json
from pathlib import Path

import numpy as np
import pytest
import yaml
from scipy.spatial.transform import Rotation

from gcm_pipeline.cli import main
from gcm_pipeline.errors import InputError
from gcm_pipeline.formats.exporters import export_run
from gcm_pipeline.pipeline import Pipeline

BASE_XYZ = [0.05, -0.02, 0.0]


def graspgen_top_grasps(path: Path, box_top: float) -> None:
    """Six GraspGen grasps from above on the box top (base-link frames, object frame)."""
    transforms, scores = [], []
    for i, (dx, dy) in enumerate([(-0.012, -0.01), (0, -0.01), (0.012, -0.01)] * 2):
        dy = dy if i < 3 else -dy
        yaw = np.radians(6.0 * (i - 2.5))
        r = Rotation.from_euler("xz", [np.pi, yaw]).as_matrix()  # z down, x along +-x
        r = r @ Rotation.from_euler("z", np.pi / 2).as_matrix()  # fingers (x) along y
        t = np.eye(4)
        t[:3, :3] = r
        t[:3, 3] = [dx, dy, box_top] - 0.1034 * r[:, 2]
        transforms.append(t.tolist())
        scores.append(0.5 + 0.08 * i)
    path.write_text(
        json.dumps({"grasps": {"transforms": transforms, "confidences": scores}}), encoding="utf-8"
    )


def make_run(root: Path, *, object_x: float = 0.5, html: bool = False) -> Path:
    root.mkdir(parents=True, exist_ok=True)
    data = root / "box_grasps.json"
    graspgen_top_grasps(data, 0.05)
    cfg = {
        "robot": {"spec": "panda", "base_pose": {"xyz": BASE_XYZ, "rpy_deg": [0, 0, 10]}},
        "object": {
            "shape": "box",
            "dims": {"size": [0.06, 0.06, 0.10]},
            "pose": {"xyz": [object_x, 0.0, 0.05]},
        },
        "candidates": {"source": "file", "path": str(data), "frame": "object"},
        "manifold": {"projection": "xy"},
        "densify": {"subdivisions": 2},
        "approach": {"distance": 0.05, "steps": 5},
        "ranking": {"metric": "combined", "top_k": 3},
        "publish": {"html": html, "plots": False},
    }
    out = root / "run"
    Pipeline.from_dict(cfg).run(out, progress=False)
    return out


@pytest.fixture(scope="module")
def run(tmp_path_factory) -> Path:
    return make_run(tmp_path_factory.mktemp("export"))


def csv_rows(run: Path) -> tuple[list[str], list[list[str]]]:
    with (run / "grasps.csv").open(newline="") as fh:
        rows = list(csv.reader(fh))
    return rows[0], rows[1:]


def column(header, rows, name, kind=float):
    j = header.index(name)
    return np.array([kind(r[j]) if r[j] != "" else np.nan for r in rows])


def test_run_carries_the_imported_scores(run):
    header, rows = csv_rows(run)
    assert header[-2:] == ["score", "source_id"]
    origin = [r[header.index("origin")] for r in rows]
    score = column(header, rows, "score")
    cand = np.array(origin) == "candidate"
    assert sorted(score[cand].round(6).tolist()) == [round(0.5 + 0.08 * i, 6) for i in range(6)]
    assert np.isfinite(score).all()  # interpolated rows get the blend of their vertices
    assert column(header, rows, "reachable", str).tolist().count("true") >= 10


def test_moveit_export_matches_grasps_csv(run, tmp_path):
    out = tmp_path / "grasps.yaml"
    result = export_run(run, "moveit", out=out)
    grasps = yaml.safe_load(out.read_text())
    header, rows = csv_rows(run)
    rank = column(header, rows, "rank", int)
    ranked = [r for r, k in zip(rows, rank, strict=True) if k > 0]
    assert result.rows == len(grasps) == len(ranked) > 0
    base = np.eye(4)
    base[:3, :3] = Rotation.from_euler("z", 10, degrees=True).as_matrix()
    base[:3, 3] = BASE_XYZ
    fields = [
        "id",
        "pre_grasp_posture",
        "grasp_posture",
        "grasp_pose",
        "grasp_quality",
        "pre_grasp_approach",
        "post_grasp_retreat",
        "post_place_retreat",
        "max_contact_force",
        "allowed_touch_objects",
    ]
    for g, row in zip(grasps, ranked, strict=True):
        assert list(g) == fields  # moveit_msgs/Grasp, in the message's order
        world = np.eye(4)
        world[:3, 3] = [float(row[header.index(c)]) for c in "xyz"]
        q = [float(row[header.index(c)]) for c in ("qx", "qy", "qz", "qw")]
        world[:3, :3] = Rotation.from_quat(q).as_matrix()
        want = np.linalg.inv(base) @ world
        pose = g["grasp_pose"]
        assert pose["header"]["frame_id"] == "panda_link0"
        p = pose["pose"]["position"]
        np.testing.assert_allclose([p["x"], p["y"], p["z"]], want[:3, 3], atol=1e-9)
        o = pose["pose"]["orientation"]
        got = Rotation.from_quat([o["x"], o["y"], o["z"], o["w"]]).as_matrix()
        np.testing.assert_allclose(got, want[:3, :3], atol=1e-9)
        assert g["grasp_quality"] == pytest.approx(float(row[header.index("combined")]))
        assert g["id"] == f"rank_{row[0]}"
        app = g["pre_grasp_approach"]
        assert app["direction"]["header"]["frame_id"] == "panda_hand_tcp"
        assert app["direction"]["vector"] == {"x": 0.0, "y": 0.0, "z": 1.0}
        assert app["desired_distance"] == app["min_distance"] == 0.05
        assert g["pre_grasp_posture"]["joint_names"] == [
            "panda_finger_joint1",
            "panda_finger_joint2",
        ]
        assert g["pre_grasp_posture"]["points"][0]["positions"] == [0.04, 0.04]
        assert g["grasp_posture"]["points"][0]["positions"] == [0.0, 0.0]  # no width in the file
    assert [g["grasp_quality"] for g in grasps] == sorted(
        (g["grasp_quality"] for g in grasps), reverse=True
    )


def test_parquet_export_matches_grasps_csv(run, tmp_path):
    import pyarrow.parquet as pq

    out = tmp_path / "g.parquet"
    export_run(run, "parquet", out=out)
    table = pq.read_table(out).to_pydict()
    header, rows = csv_rows(run)
    qnames = [h for h in header if h[0] == "q" and h[1:].isdigit()]
    assert [c for c in table if c != "q"] == [h for h in header if h not in qnames]
    for name in header:
        if name in qnames:
            continue
        want = [r[header.index(name)] for r in rows]
        got = table[name]
        if name in ("origin", "reason"):
            assert got == want
        elif set(want) <= {"true", "false"}:  # reachable, top
            assert got == [w == "true" for w in want]
        else:
            np.testing.assert_array_equal(
                np.array(got, dtype=float), np.array([w or "nan" for w in want], dtype=float)
            )
    q = np.array([[float(r[header.index(c)] or "nan") for c in qnames] for r in rows])
    np.testing.assert_array_equal(np.array(table["q"], dtype=float), q)


def test_npz_export_and_top(run, tmp_path):
    out = tmp_path / "g.npz"
    result = export_run(run, "npz", top=3, out=out)
    assert result.rows == 3
    header, rows = csv_rows(run)
    with np.load(out, allow_pickle=False) as data:
        assert data["rank"].tolist() == [1, 2, 3]
        np.testing.assert_array_equal(data["x"], column(header, rows[:3], "x"))
        np.testing.assert_array_equal(data["score"], column(header, rows[:3], "score"))
        assert data["q"].shape == (3, 7) and data["pose"].shape == (3, 4, 4)
        np.testing.assert_allclose(data["pose"][:, :3, 3], np.c_[data["x"], data["y"], data["z"]])
        assert data["origin"].dtype.kind == "U"


def test_cli_export_and_an_empty_run(run, tmp_path, capsys):
    assert main(["export", str(run), "--format", "parquet", "--out", str(tmp_path / "a.pq")]) == 0
    assert "wrote" in capsys.readouterr().out
    # a run whose object is out of reach: no reachable grasp
    empty = make_run(tmp_path / "far", object_x=3.0)
    assert "no grasp is reachable" in capsys.readouterr().err  # the run warned
    out = tmp_path / "none.yaml"
    assert main(["export", str(empty), "--format", "moveit", "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "no reachable grasp to export" in err[0]
    assert yaml.safe_load(out.read_text()) == []  # empty but valid
    with pytest.raises(InputError, match="not a run directory"):
        export_run(tmp_path, "npz")
    assert not list(tmp_path.glob(".*.tmp"))  # nothing half-written
