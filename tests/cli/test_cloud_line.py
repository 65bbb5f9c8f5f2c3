"""``gcm run`` says what it made of each point cloud: points read, kept, voxels, and why
the others were dropped (non-finite depth included), so a user sees a wrong crop or a
wrong segment at once."""

from __future__ import annotations

from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[2]
CLUTTER = REPO / "configs" / "clutter_scene.yaml"
QUIET = ("--set", "publish.html=false", "--set", "publish.plots=false")


def test_gcm_run_prints_one_line_per_cloud(cli, tmp_path):
    status, out, _ = cli("run", CLUTTER, "--out", tmp_path / "run", *QUIET)
    assert status == 0
    lines = [ln for ln in out.splitlines() if ln.lstrip().startswith("cloud ")]
    assert lines == [
        "  cloud         clutter: 12,511 of 76,800 points kept -> 973 voxels of 1 cm "
        "(18,560 no depth, 43,022 outside the crop, 2,707 in excluded segments)"
    ]


def test_non_finite_depth_is_dropped_and_counted(cli, tmp_path):
    scene = dict(np.load(REPO / "tests" / "data" / "clutter" / "scene.npz"))
    depth = scene["depth"].copy()
    depth[:10, :] = np.nan  # 10 rows of 320 pixels: what a depth camera gives at edges
    depth[10, :5] = np.inf
    np.savez(tmp_path / "scene.npz", **(scene | {"depth": depth}))
    status, out, _ = cli(
        "run", CLUTTER, "--out", tmp_path / "run", *QUIET,
        "--set", f"environment.point_clouds=[{{path: {tmp_path / 'scene.npz'}, "
        "exclude_segments: [1], crop_min: [-2, -2, 0.005], name: nan}]",
    )  # fmt: skip
    assert status == 0, out
    line = next(ln for ln in out.splitlines() if ln.lstrip().startswith("cloud "))
    assert "3,205 not finite (dropped)" in line, line


def test_a_cloud_npz_with_a_member_name_cut_at_a_nul_byte_is_one_line(cli, tmp_path):
    """zipfile cuts a member name at a NUL byte; cut to nothing, it raised IndexError."""
    from io import BytesIO

    from helpers import assert_one_line_error

    buf = BytesIO()
    np.savez(buf, xyz=np.random.default_rng(0).uniform(0.3, 0.6, (100, 3)))
    data = bytearray(buf.getvalue())
    data[data.find(b"PK\x01\x02") + 46] = 0  # the first byte of the first member's name
    (tmp_path / "cloud.npz").write_bytes(bytes(data))
    status, _, err = cli(
        "run", CLUTTER, "--out", tmp_path / "run", *QUIET,
        "--set", f"environment.point_clouds=[{{path: {tmp_path / 'cloud.npz'}, frame: world}}]",
    )  # fmt: skip
    assert_one_line_error(status, err)
    assert "cloud.npz" in err
    assert not (tmp_path / "run").exists()


def test_gcm_show_prints_the_runs_clouds_and_skips_a_damaged_entry(cli, tmp_path):
    import json

    run = tmp_path / "run"
    assert cli("run", CLUTTER, "--out", run, *QUIET)[0] == 0
    status, out, _ = cli("show", run, "--top", "0")
    assert status == 0
    assert "  cloud clutter: 12,511 of 76,800 points kept -> 973 voxels of 1 cm" in out
    summary = json.loads((run / "summary.json").read_text())
    summary["point_clouds"] = [7, {"name": "x", "voxel_size": "big", "counts": {}}]
    (run / "summary.json").write_text(json.dumps(summary))
    status, out, err = cli("show", run, "--top", "0")
    assert status == 0 and "cloud" not in out and not err
