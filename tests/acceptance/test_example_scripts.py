"""Every script in examples/ runs as a user runs it and prints what it promises.

Each script runs in a subprocess (``python examples/NN_name.py OUT_DIR``, a
fresh OUT_DIR) with this checkout's package; the assertions read its
printed output and the files it wrote.
"""

from __future__ import annotations

import json
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pyarrow.parquet as pq
import yaml
from helpers import ROOT, gcm_env

EXAMPLES = ROOT / "examples"


def run_example(name: str, out: Path) -> str:
    """Run ``examples/<name>`` into ``out``; its stdout (fails on a non-zero exit)."""
    proc = subprocess.run(
        [sys.executable, str(EXAMPLES / name), str(out)],
        cwd=out.parent,  # not the repository: the scripts find their inputs themselves
        env=gcm_env(),
        capture_output=True,
        text=True,
        timeout=900,
    )
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert "Traceback" not in proc.stderr
    return proc.stdout


def count(pattern: str, text: str) -> tuple[int, int]:
    """The two integers of ``pattern`` (``N of M``) in ``text``."""
    m = re.search(pattern, text)
    assert m, f"{pattern!r} not in output:\n{text}"
    return int(m.group(1)), int(m.group(2))


def test_the_numbered_examples_exist():
    names = sorted(p.name for p in EXAMPLES.glob("[0-9][0-9]_*.py"))
    assert names == ["01_run.py", "02_query.py", "03_study.py", "04_export.py", "05_user_robot.py"]
    for name in names:  # short enough to read
        assert len((EXAMPLES / name).read_text().splitlines()) <= 60, name


def test_01_run(tmp_path):
    out = tmp_path / "out"
    text = run_example("01_run.py", out)
    reachable, total = count(r"reachable: (\d+) of (\d+) grasps", text)
    summary = json.loads((out / "bottle" / "summary.json").read_text())
    assert 0 < reachable <= total
    assert (reachable, total) == (summary["counts"]["reachable"], summary["counts"]["densified"])
    ranks = re.findall(r"^#(\d+): p = \[", text, flags=re.M)
    assert ranks == ["1", "2", "3", "4", "5"]
    best = summary["ranking"]["top"][0]
    assert f"p = [{best['x']:.3f}, {best['y']:.3f}, {best['z']:.3f}]" in text


def test_02_query(tmp_path):
    text = run_example("02_query.py", tmp_path / "out")
    manifold = float(re.search(r"nearest manifold point: triangle \d+, ([\d.]+) m away", text)[1])
    reachable = float(re.search(r"nearest reachable grasp: ([\d.]+) m away", text)[1])
    # the nearest reachable grasp is a point of the manifold: never nearer than the nearest one
    assert 0 <= manifold <= reachable < 0.2
    q = json.loads(re.search(r"its joint solution \[rad\]: (\[.*\])", text)[1])
    assert len(q) == 7 and all(np.isfinite(q))


def test_03_study(tmp_path):
    out = tmp_path / "out"
    text = run_example("03_study.py", out)
    assert len(re.findall(r"^placement: ", text, flags=re.M)) == 4
    lines = re.findall(
        r"^x = ([\d.]+) m, yaw = +(\d+) deg: (\d+) of (\d+) grasps reachable", text, re.M
    )
    assert len(lines) == 4
    assert {(x, yaw) for x, yaw, _, _ in lines} == {
        ("0.35", "0"),
        ("0.35", "20"),
        ("0.55", "0"),
        ("0.55", "20"),
    }
    assert all(0 < int(n) <= int(m) for _, _, n, m in lines)
    summary = json.loads((out / "study" / "summary.json").read_text())
    assert summary["complete"] and summary["engine"]["name"] == "ray"
    assert summary["counts"]["finished"] == 4
    with np.load(out / "study" / "reachability.npz") as r:
        assert r["reachable"].shape[0] == 4
        everywhere = int(r["reachable"].all(axis=0).sum())
    assert count(r"(\d+) of (\d+) grasps reachable everywhere", text)[0] == everywhere
    best = summary["best"]
    assert f"best: x = {best['object_x']:.2f} m" in text
    assert best["reachable"] == max(int(n) for _, _, n, _ in lines)


def test_04_export(tmp_path):
    out = tmp_path / "out"
    text = run_example("04_export.py", out)
    grasps = yaml.safe_load((out / "grasps_moveit.yaml").read_text())
    assert len(grasps) == 10 and grasps[0]["id"] == "rank_1"
    assert grasps[0]["grasp_pose"]["header"]["frame_id"] == "panda_link0"
    table = pq.read_table(out / "grasps.parquet")
    with (out / "flat" / "grasps.csv").open() as fh:
        assert table.num_rows == sum(1 for _ in fh) - 1  # every row of the run
    assert f"grasps.parquet: {table.num_rows} rows" in text
    assert f"reachable rows: {sum(table.column('reachable').to_pylist())}" in text


def test_05_user_robot(tmp_path):
    out = tmp_path / "out"
    text = run_example("05_user_robot.py", out)
    assert text.startswith("ur10: 6 joints")
    assert "tool/finger_left" in text and "'gripper_tcp'" in text
    reachable, total = count(r"reachable with the UR10: (\d+) of (\d+) grasps", text)
    assert 0 < reachable <= total
    config = yaml.safe_load((out / "bottle_ur10" / "config.yaml").read_text())
    assert Path(config["robot"]["spec"]).name == "ur10.yaml"
    summary = json.loads((out / "bottle_ur10" / "summary.json").read_text())
    assert summary["counts"]["reachable"] == reachable
    assert len(summary["ranking"]["top"][0]["q"]) == 6


def test_an_example_without_argument_writes_into_a_temp_folder(tmp_path):
    """No OUT_DIR: the script still runs and names a folder that exists."""
    proc = subprocess.run(
        [sys.executable, str(EXAMPLES / "04_export.py")],
        cwd=tmp_path,
        env=gcm_env(TMPDIR=str(tmp_path)),
        capture_output=True,
        text=True,
    )
    assert proc.returncode == 0, proc.stderr[-3000:]
    run_dir = Path(re.search(r"^run directory: (.+)$", proc.stdout, re.M)[1])
    assert run_dir.is_relative_to(tmp_path) and (run_dir / "grasps.csv").is_file()
    assert (run_dir.parent / "grasps.parquet").is_file()
