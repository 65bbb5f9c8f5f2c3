"""Placement studies: study files, the study directory, and real Ray runs.

The Ray tests share one two-node ``ray.cluster_utils.Cluster`` started on this
machine's loopback address with its own temporary directory (so no stale
``ray_current_cluster`` file is joined) and shut down at the end; the CLI
runs in subprocesses join it with ``--address``. One test starts Ray the way
``gcm study`` does without ``--address`` (local, in a subprocess).
"""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import pytest
import yaml
from helpers import BOTTLE, ROOT, assert_one_line_error
from helpers import SMALL_STUDY as SMALL

from gcm_pipeline.cli import main
from gcm_pipeline.config import Config, load_config
from gcm_pipeline.errors import ConfigError, OutputError
from gcm_pipeline.geometry.dualquat import dq_to_matrix, dq_to_pos_quat
from gcm_pipeline.pipeline import generate_candidates
from gcm_pipeline.rundir.grasps_csv import read_grasps_csv
from gcm_pipeline.study import Study, load_study
from gcm_pipeline.study.runner import probe_address
from gcm_pipeline.study.store import CSV_COLUMNS, StudyDir
from gcm_pipeline.study.targets import format_value

# Ray swaps a loopback address for the machine's own when a driver joins a
# cluster, unless this is off; Ray reads it when first imported, so it is set
# before anything here imports Ray (the subprocesses inherit it).
os.environ["RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER"] = "0"

FROM_FILE = ROOT / "configs" / "from_file.yaml"


def _study_file(tmp_path: Path, data: dict, name: str = "study.yaml") -> Path:
    path = tmp_path / name
    path.write_text(yaml.safe_dump(data, sort_keys=False))
    return path


def _broken_grasp_file(folder: Path) -> Path:
    """A damaged ``.npy`` grasp file: its placements fail when the run reads it."""
    broken = folder / "broken.npy"
    broken.write_bytes(b"\x93NUMPY this is not a grasp file")
    return broken


def _small(sweep: dict, **extra) -> dict:
    return {"base": str(BOTTLE), "set": list(SMALL), "sweep": sweep, **extra}


# ------------------------------------------------------------------ study files


def test_grid_order_overrides_and_values_round_trip(tmp_path):
    study = Study.from_dict(
        _small({"object_pose": {"x": {"from": 0.3, "to": 0.7, "steps": 9}, "yaw_deg": [0, 90]}})
    )
    grid = study.placements()
    assert len(grid) == 18
    assert [p.id for p in grid] == list(range(18))
    assert [p.object_pose["x"] for p in grid[:4]] == [0.3, 0.3, 0.35, 0.35]  # x slowest, rounded
    p = grid[3]
    assert p.overrides[: len(SMALL)] == tuple(SMALL)
    assert "object.pose.xyz=[0.35, 0.0, 0.0]" in p.overrides
    assert "object.pose.rpy_deg=[0.0, 0.0, 90.0]" in p.overrides
    cfg = study.plan.resolve(p.overrides)
    assert cfg.object.pose.xyz == (0.35, 0.0, 0.0)
    assert cfg.object.pose.rpy_deg == (0.0, 0.0, 90.0)
    # a --set value reads back as the same float, also with an exponent
    for v in (1e-05, 0.35000000000000003, -2.5e-12, 3.0):
        assert yaml.safe_load(format_value([v]))[0] == v


def test_a_pose_override_is_written_as_yaml_writes_it():
    """The fast path for number lists gives PyYAML's text (placements' overrides unchanged)."""
    rng = np.random.default_rng(0)
    values = [1e-05, -2.5e-12, 1e16, 1.5e300, 5e-324, -0.0, 0.0, 3, -7, 0.1 + 0.2]
    values += [float("nan"), float("inf"), float("-inf")]
    values += list(rng.normal(0.0, 1.0, 200) * 10.0 ** rng.integers(-20, 20, 200))
    for i in range(0, len(values), 3):
        chunk = [v if isinstance(v, int) else float(v) for v in values[i : i + 3]]
        want = yaml.safe_dump(chunk, default_flow_style=True, width=float("inf")).strip()
        assert format_value(chunk) == want
    assert format_value([True, 1.0]) == "[true, 1.0]"  # not numbers: YAML's own dump


def test_yaw_keeps_radians_when_the_base_uses_rpy(tmp_path):
    base = tmp_path / "base.yaml"
    data = yaml.safe_load(BOTTLE.read_text())
    data["object"]["pose"] = {"xyz": [0.5, 0.0, 0.0], "rpy": [0.0, 0.1, 0.0]}
    base.write_text(yaml.safe_dump(data))
    study = Study.from_dict({"base": str(base), "sweep": {"object_pose": {"yaw_deg": [90]}}})
    (p,) = study.placements()
    assert p.overrides == ("object.pose.rpy=[0.0, 0.1, 1.5707963267948966]",)


def test_resolved_config_round_trips_through_a_dict():
    for path in sorted((ROOT / "configs").glob("*.yaml")):
        cfg = load_config(path)
        assert Config.from_dict(cfg.to_dict()) == cfg


def test_object_pose_moves_the_candidates_with_the_object():
    """Generated and object-frame file candidates keep their pose relative to the object."""
    for base in (BOTTLE, FROM_FILE):
        study = Study.from_dict(
            {"base": str(base), "sweep": {"object_pose": {"x": [0.3, 0.6], "yaw_deg": [0, 75]}}}
        )
        local = None
        for p in study.placements():
            cfg = study.plan.resolve(p.overrides)
            world = dq_to_matrix(generate_candidates(cfg)["dq"])
            rel = np.linalg.inv(cfg.object.pose.matrix()) @ world
            if local is None:
                local = rel
            assert np.allclose(rel, local, atol=1e-12)


def test_world_frame_grasp_files_are_refused():
    with pytest.raises(ConfigError, match="would not move with the object"):
        load_study(
            {
                "base": str(FROM_FILE),
                "set": ["candidates.frame=world"],
                "sweep": {"object_pose": {"x": [0.5]}},
            }
        )


def test_region_table_and_box_restrict_the_grid():
    sweep = {"x": {"from": 0.0, "to": 1.6, "steps": 5}, "y": [0.0, 1.5]}
    table = Study.from_dict(_small({"object_pose": {**sweep, "region": "table"}}))
    # the default table is 2 m x 2 m around the origin: x <= 1.0, y <= 1.0
    assert {(p.object_pose["x"], p.object_pose["y"]) for p in table.placements()} == {
        (0.0, 0.0),
        (0.4, 0.0),
        (0.8, 0.0),
    }
    box = Study.from_dict(
        _small({"object_pose": {**sweep, "region": {"min": [0.3, -1], "max": [1.3, 2]}}})
    )
    assert len(box.placements()) == 6  # x 0.4, 0.8, 1.2 times y 0.0, 1.5
    assert {p.object_pose["x"] for p in box.placements()} == {0.4, 0.8, 1.2}
    # the size is counted axis by axis, before any placement is built
    assert table.size() == (3, 0) and box.size() == (6, 0)
    base = Study.from_dict(
        _small(
            {
                "object_pose": {
                    **sweep,
                    "z": [0.0, 0.5],
                    "region": {"min": [0.3, -1, -0.1], "max": [1.3, 2, 0.1]},
                },
                "base_pose": {"y": [-0.2, 0.0, 0.2], "region": {"min": [-1, -0.1], "max": [1, 1]}},
            }
        )
    )
    assert base.size() == (6 * 2, 0) and len(base.placements()) == 12


def test_objects_and_base_pose_multiply(tmp_path):
    study = Study.from_dict(
        _small(
            {
                "object_pose": {"x": [0.45, 0.55]},
                "base_pose": {"y": [0.0, 0.1], "yaw_deg": [0, 10]},
                "objects": [
                    {"name": "bottle"},
                    {
                        "name": "can",
                        "object": {"shape": "cylinder", "dims": {"radius": 0.033, "height": 0.12}},
                        "set": ["candidates.count=12"],
                    },
                ],
            }
        )
    )
    grid = study.placements()
    assert len(grid) == 2 * 4 * 2
    assert [p.object for p in grid].count("can") == 8
    can = study.plan.resolve(grid[-1].overrides)
    assert can.object.dims.radius == 0.033 and can.candidates.count == 12
    assert can.object.pose.xyz == (0.55, 0.0, 0.0)
    assert can.robot.base_pose.xyz == (0.0, 0.1, 0.0)
    # the base config gives the base's rpy in radians: the sweep's yaw follows
    assert can.robot.base_pose.rpy == (0.0, 0.0, np.radians(10.0))


def test_refine_regrids_around_the_best_and_skips_repeats():
    study = Study.from_dict(
        _small(
            {"object_pose": {"x": {"from": 0.3, "to": 0.7, "steps": 5}, "yaw_deg": [0, 90]}},
            refine={"rounds": 2, "shrink": 0.5},
        )
    )
    grid = study.placements()
    best = {0: grid[2]}  # x 0.4, yaw 0
    r1 = study.plan.refined(1, best, grid)
    xs = [p.object_pose["x"] for p in r1]
    # span 0.4 * 0.5 = 0.2 around 0.4 over 5 steps: 0.3 .. 0.5 by 0.05; 0.3, 0.4, 0.5 exist
    assert xs == [0.35, 0.45]
    assert {p.object_pose["yaw_deg"] for p in r1} == {0.0}
    assert [p.id for p in r1] == [10, 11] and {p.round for p in r1} == {1}
    r2 = study.plan.refined(2, {0: r1[0]}, grid + r1)
    assert [p.object_pose["x"] for p in r2] == [0.325, 0.375]


@pytest.mark.parametrize(
    ("sweep", "fragment"),
    [
        ({"object_pose": {"x": []}}, "sweep.object_pose.x: empty list"),
        ({"object_pose": {"x": {"from": 0.5, "to": 0.5, "steps": 3}}}, "empty range"),
        ({"object_pose": {"x": {"from": 0.7, "to": 0.3, "steps": 3}}}, "inverted range"),
        ({"object_pose": {"x": {"from": 0.3, "to": 0.7, "steps": 0}}}, "steps must be >= 1"),
        ({"object_pose": {"radius": [0.1]}}, "unknown pose key 'sweep.object_pose.radius'"),
        ({"base_pose": {"pitch_deg": [1]}}, "unknown pose key 'sweep.base_pose.pitch_deg'"),
        ({"densify": {"subdivisions": [1, 2]}}, "unknown key 'sweep.densify'"),
        ({"object_pose": {"x": [0.5], "region": {"min": [2, 2], "max": [3, 3]}}}, "no placement"),
        ({"object_pose": {"x": "0.5"}}, "expected a list of values or {from"),
        ({"object_pose": {"x": [True]}}, "sweep.object_pose.x"),
        ({"object_pose": {"yaw_deg": [1e20]}}, "less than or equal to 1000"),
        ({"base_pose": {"x": {"from": 0, "to": 1e300, "steps": 2}}}, "less than or equal to 1000"),
    ],
)
def test_bad_study_is_one_line_and_writes_nothing(tmp_path, capsys, sweep, fragment):
    path = _study_file(tmp_path, _small(sweep))
    out = tmp_path / "out"
    code = main(["study", str(path), "--out", str(out)])
    assert_one_line_error(code, capsys.readouterr().err, fragment)
    assert not out.exists()


def test_an_unreadable_mesh_stops_the_study_before_any_work(tmp_path, capsys):
    broken = tmp_path / "broken.stl"
    broken.write_text("solid nothing\nthis is not an STL file\n")
    data = _small(
        {
            "objects": [
                {
                    "name": "b",
                    "object": {"shape": "mesh", "mesh": str(broken)},
                    "candidates": {
                        "source": "file",
                        "path": str(FROM_FILE.parent / "data" / "mug_grasps.npy"),
                        "frame": "object",
                    },
                }
            ]
        }
    )
    out = tmp_path / "out"
    code = main(["study", str(_study_file(tmp_path, data)), "--out", str(out)])
    err = capsys.readouterr().err
    assert code == 2 and err.count("\n") == 1 and "broken.stl" in err, err
    assert not out.exists()


def test_a_missing_file_of_any_object_stops_the_study_before_any_work(tmp_path, capsys):
    data = _small(
        {
            "objects": [
                {"name": "bottle"},
                {"name": "mug", "set": [f"candidates.path={tmp_path / 'missing.npy'}"]},
            ]
        }
    )
    data["base"] = str(FROM_FILE)
    out = tmp_path / "out"
    code = main(["study", str(_study_file(tmp_path, data)), "--out", str(out)])
    err = capsys.readouterr().err
    assert code == 2 and err.count("\n") == 1, err
    assert "(mug): candidates.path: file not found" in err and "missing.npy" in err
    assert not out.exists()


def test_a_study_above_its_limit_needs_force(tmp_path, capsys):
    data = _small({"object_pose": {"x": {"from": 0.3, "to": 0.7, "steps": 30}}}, max_placements=20)
    out = tmp_path / "out"
    code = main(["study", str(_study_file(tmp_path, data)), "--out", str(out)])
    err = capsys.readouterr().err
    assert code == 2 and "30 placements, more than max_placements 20" in err
    assert "--force" in err
    assert not out.exists()
    study = Study.from_dict(data)
    assert study.check(out, force=True) is False  # accepted with force, still nothing written
    assert not out.exists()


_WIDE = {"from": 0.2, "to": 0.8, "steps": 100_000}


@pytest.mark.parametrize(
    ("sweep", "fragment"),
    [
        ({"x": _WIDE, "y": _WIDE}, "10,000,000,000 placements; one study holds at most 1,000,000"),
        (
            {"x": {"from": 0.3, "to": 0.7, "steps": 10**9}},
            "steps must be <= 1,000,000, got 1,000,000,000",
        ),
    ],
)
def test_a_huge_study_is_refused_before_it_is_built(tmp_path, sweep, fragment):
    """Counted per axis and refused in one line, even with --force (it cannot help).

    The CLI runs in a subprocess with its address space capped at 2 GiB, so
    building the placements or the grid values (tens of GB) fails there
    instead of on this machine.
    """
    path = _study_file(tmp_path, _small({"object_pose": sweep}))
    out = tmp_path / "out"
    cap = "import resource; resource.setrlimit(resource.RLIMIT_AS, (2 << 30, 2 << 30)); "
    for extra in ([], ["--force"]):
        code = cap + (
            "import sys; from gcm_pipeline.cli import main; "
            f"sys.exit(main(['study', {str(path)!r}, '--out', {str(out)!r}, *{extra!r}]))"
        )
        proc = subprocess.run(
            [sys.executable, "-c", code], capture_output=True, text=True, cwd=ROOT, timeout=600
        )
        assert proc.returncode == 2, proc.stderr[-2000:]
        assert proc.stderr.count("\n") == 1 and fragment in proc.stderr, proc.stderr[-2000:]
        assert not out.exists()


def test_unreachable_address_is_one_line(tmp_path, capsys):
    import socket

    with socket.socket() as s:  # a free port on this machine: nobody listens there
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    path = _study_file(tmp_path, _small({"object_pose": {"x": [0.5]}}))
    out = tmp_path / "out"
    t0 = time.perf_counter()
    code = main(["study", str(path), "--out", str(out), "--address", f"127.0.0.1:{port}"])
    line = assert_one_line_error(code, capsys.readouterr().err)
    assert line.startswith("error: --address 127.0.0.1:"), line
    assert time.perf_counter() - t0 < 30
    assert not out.exists()


def test_more_workers_than_this_machine_has_cpus_is_one_line(tmp_path, capsys):
    """Without --address, Ray would take --workers for CPUs and start that many actors."""
    path = _study_file(tmp_path, _small({"object_pose": {"x": [0.5]}}))
    out = tmp_path / "out"
    cpus = os.cpu_count()
    assert main(["study", str(path), "--out", str(out), "--workers", "100000"]) == 2
    assert capsys.readouterr().err == (
        f"error: --workers 100000: this machine has {cpus} CPUs; use --workers {cpus} or "
        "fewer, or --address to run on a cluster\n"
    )
    assert not out.exists()


def test_a_directory_of_another_study_is_refused(tmp_path):
    study = Study.from_dict(_small({"object_pose": {"x": [0.5]}}))
    other = Study.from_dict(_small({"object_pose": {"x": [0.6]}}))
    out = tmp_path / "out"
    assert study.check(out) is False
    StudyDir(out).create({"key": study.plan.key(), "source": "a.yaml"})
    assert study.check(out) is True  # the same study resumes
    with pytest.raises(OutputError, match="holds a different study"):
        other.check(out)
    (tmp_path / "mine").mkdir()
    (tmp_path / "mine" / "notes.txt").write_text("keep me")
    with pytest.raises(OutputError, match="not a gcm study directory"):
        study.check(tmp_path / "mine")
    assert (tmp_path / "mine" / "notes.txt").read_text() == "keep me"


def test_a_study_directory_in_use_is_refused_and_left_alone(tmp_path, capsys):
    """A second study into the directory of a running one stops in one line, writing nothing."""
    path = _study_file(tmp_path, _small({"object_pose": {"x": [0.5]}}))
    out = tmp_path / "out"
    with StudyDir(out).lock():  # what a running study holds
        before = sorted(p.name for p in out.iterdir())
        assert main(["study", str(path), "--out", str(out)]) == 2
        err = capsys.readouterr().err
        assert err == (
            f"error: {out} is in use by another gcm study (pid {os.getpid()}); wait for it "
            "to finish or choose another --out\n"
        )
        assert sorted(p.name for p in out.iterdir()) == before == [".study.lock"]
    # released: the study runs, and a later run of it resumes
    result = Study.from_yaml(path).run(out, engine="inline", progress=False, best_run=False)
    assert result.complete and len(result.rows) == 1
    # a lock that is a symbolic link is not followed (its target was overwritten), nor a pipe
    victim = tmp_path / "victim.txt"
    victim.write_text("keep me")
    for odd in ("link", "fifo"):
        other = tmp_path / f"out_{odd}"
        other.mkdir()
        if odd == "link":
            (other / ".study.lock").symlink_to(victim)
        else:
            os.mkfifo(other / ".study.lock")
        assert main(["study", str(path), "--out", str(other)]) == 2
        err = capsys.readouterr().err
        assert (
            err.startswith(f"error: cannot lock study directory {other}: ") and err.count("\n") == 1
        )
        assert "is not a regular file" in err
    assert victim.read_text() == "keep me"


def _rewrite_part(path: Path, **change) -> None:
    with np.load(path) as data:
        arrays = {k: data[k] for k in data.files}
    row = json.loads(str(arrays.pop("row")))
    row.update(change.pop("row", {}))
    arrays.update(change)
    np.savez(path, row=np.array(json.dumps(row)), **arrays)


def test_a_damaged_or_foreign_placement_file_runs_again(tmp_path, caplog):
    """Resume trusts only part files that hold their own placement; the others run again."""
    path = _study_file(tmp_path, _small({"object_pose": {"x": [0.45, 0.5, 0.55]}}))
    out = tmp_path / "out"
    first = Study.from_yaml(path).run(out, engine="inline", progress=False, best_run=False)
    reach = np.load(out / "reachability.npz")["reachable"]
    parts = out / "placements"
    shutil.copy(parts / "000000.npz", parts / "000001.npz")  # another placement's file
    _rewrite_part(parts / "000001.npz", row={"id": 1})  # ... claiming to be this one
    _rewrite_part(parts / "000000.npz", reachable_mask=np.ones(3, dtype=bool))  # wrong length
    _rewrite_part(parts / "000002.npz", row={"coverage": 5.0})  # it would become the best
    again = Study.from_yaml(path).run(out, engine="inline", progress=False, best_run=False)
    assert again.summary["counts"]["resumed"] == 0 and again.summary["counts"]["run"] == 3
    assert [r["reachable"] for r in again.rows] == [r["reachable"] for r in first.rows]
    assert np.array_equal(np.load(out / "reachability.npz")["reachable"], reach)
    text = caplog.text
    assert "000000.npz, placement runs again (arrays of different lengths: reachable_mask 3" in text
    assert "000001.npz, it is not placement 1" in text
    assert "000002.npz, placement runs again (coverage 5.0 is not within [0, 1])" in text


def test_import_does_not_load_ray():
    code = "import sys, gcm_pipeline; print('ray' in sys.modules, hasattr(gcm_pipeline, 'Study'))"
    out = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, check=True, cwd=ROOT
    )
    assert out.stdout.split() == ["False", "True"]


# ------------------------------------------------------------------ real Ray


@pytest.fixture(scope="module")
def cluster():
    """A two-node Ray cluster on this machine's loopback (1 CPU each), with its own temp dir."""
    ray = pytest.importorskip("ray")
    from ray.cluster_utils import Cluster

    tmp = tempfile.mkdtemp(prefix="gcm-ray-", dir="/tmp")  # short: Ray's socket paths
    env = {"RAY_TMPDIR": tmp, "RAY_USAGE_STATS_ENABLED": "0"}
    saved = {k: os.environ.get(k) for k in env}
    os.environ.update(env)
    head = {"num_cpus": 1, "node_ip_address": "127.0.0.1", "include_dashboard": False}
    c = Cluster(initialize_head=True, head_node_args=head)
    try:
        c.add_node(num_cpus=1, node_ip_address="127.0.0.1")
        c.wait_for_nodes()
        probe_address(c.address)  # fails at once where Ray would retry for minutes
        ray.init(address=c.address, log_to_driver=False, logging_level="ERROR")
        yield c
    finally:
        ray.shutdown()
        c.shutdown()
        for k, v in saved.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v
        shutil.rmtree(tmp, ignore_errors=True)


def _same_as_gcm_run(tmp_path: Path, base: Path, part: dict, tag: str) -> None:
    """The placement's grasps equal those of ``gcm run base --set <overrides>``."""
    out = tmp_path / f"run_{tag}"
    argv = ["run", str(base), "--out", str(out), "--quiet"]
    for o in part["row"]["overrides"]:
        argv += ["--set", o]
    assert main(argv) == 0
    grasps = read_grasps_csv(out / "grasps.csv")
    pos, quat = dq_to_pos_quat(grasps["dq"])
    quat = np.where(quat[:, :1] < 0, -quat, quat)
    run_pose = np.concatenate([pos, quat], axis=1)
    a = part["arrays"]
    assert len(run_pose) == len(a["pose"]) == part["row"]["densified"]
    order_run = np.lexsort(np.round(run_pose, 9).T[::-1])
    order_study = np.lexsort(np.round(a["pose"], 9).T[::-1])
    assert np.allclose(run_pose[order_run], a["pose"][order_study], atol=1e-12)
    reach_run = np.asarray(grasps["reachable"], dtype=bool)[order_run]
    assert np.array_equal(reach_run, a["reachable_mask"][order_study])
    assert reach_run.sum() == part["row"]["reachable"]
    manip_run = np.asarray(grasps["manipulability"], dtype=float)[order_run]
    manip_study = a["manipulability"][order_study]
    assert np.allclose(manip_run[reach_run], manip_study[reach_run], rtol=1e-12, atol=0)


def _part(out: Path, pid: int) -> dict:
    with np.load(out / "placements" / f"{pid:06d}.npz") as data:
        return {
            "row": json.loads(str(data["row"])),
            "arrays": {k: data[k] for k in data.files if k != "row"},
        }


def test_study_across_two_nodes_matches_gcm_run(cluster, tmp_path):
    data = _small(
        {"object_pose": {"x": {"from": 0.4, "to": 0.6, "steps": 2}, "yaw_deg": [0, 120]}},
        refine={"rounds": 1, "shrink": 0.5},
    )
    study = Study.from_yaml(_study_file(tmp_path, data))
    out = tmp_path / "study"
    result = study.run(out, workers=2, address=cluster.address, progress=False, best_run=True)
    assert result.complete and not result.failed
    s = result.summary
    assert s["engine"]["name"] == "ray" and s["engine"]["workers"] == 2
    assert len(s["engine"]["worker_nodes"]) == 2  # one actor on each node
    assert {r["node"] for r in result.rows} == set(s["engine"]["worker_nodes"])
    assert s["counts"]["rounds"] == 2 and len(result.rows) > 4  # refinement added placements
    # outputs
    for name in ("placements.csv", "reachability.npz", "summary.json", "coverage.png"):
        assert (out / name).is_file(), name
    header = (out / "placements.csv").read_text().splitlines()[0].split(",")
    assert tuple(header) == CSV_COLUMNS
    with np.load(out / "reachability.npz") as npz:
        assert npz["reachable"].shape == (
            len(result.rows),
            max(r["densified"] for r in result.rows),
        )
        assert npz["same_grasps"].all()  # the object moved its grasps with it
        survive = npz["reachable"].all(axis=0)
        assert survive.sum() <= min(r["reachable"] for r in result.rows)
    best = result.best
    assert best["coverage"] == max(r["coverage"] for r in result.rows)
    assert (out / "best" / "grasps.csv").is_file()
    # sampled placements: the same answer as gcm run with the same overrides
    _same_as_gcm_run(tmp_path, BOTTLE, _part(out, best["id"]), "best")
    _same_as_gcm_run(tmp_path, BOTTLE, _part(out, 1), "p1")
    best_run = read_grasps_csv(out / "best" / "grasps.csv")
    assert int(np.asarray(best_run["reachable"]).sum()) == best["reachable"]


def test_a_failing_placement_is_recorded_and_the_study_goes_on(cluster, tmp_path):
    """One object of the list has a corrupt grasp file: its placement fails, the rest runs.

    ``gcm run``'s preflight (which the study repeats) checks that input files
    exist; reading them is the run's work, so a damaged file among many objects
    fails only that object's placements.
    """
    broken = _broken_grasp_file(tmp_path)
    data = {
        "base": str(FROM_FILE),
        "set": ["densify.subdivisions=1", "approach=null", "publish.html=false"],
        "sweep": {
            "object_pose": {"x": [0.45]},
            "objects": [
                {"name": "mug"},
                {"name": "broken", "set": [f"candidates.path={broken}"]},
            ],
        },
    }
    out = tmp_path / "study"
    study = Study.from_yaml(_study_file(tmp_path, data))
    result = study.run(out, workers=2, address=cluster.address, progress=False, best_run=False)
    rows = {r["object"]: r for r in result.rows}
    assert rows["mug"]["error"] == "" and rows["mug"]["reachable"] > 0
    assert rows["broken"]["error"].startswith("InputError: ")
    assert "broken.npy" in rows["broken"]["error"]
    assert result.best["object"] == "mug"
    assert result.summary["counts"]["failed"] == 1
    assert result.summary["failed"][0]["id"] == rows["broken"]["id"]
    text = (out / "placements.csv").read_text()
    assert "InputError" in text


def test_a_finished_study_run_again_lists_every_failure_and_no_engine(tmp_path, capsys):
    """Rerunning a finished study (no Ray started) names the failures beyond the first three."""
    broken = _broken_grasp_file(tmp_path)
    data = {
        "base": str(FROM_FILE),
        "set": ["densify.subdivisions=1", "approach=null", "publish.html=false"],
        "sweep": {
            "object_pose": {"x": [0.40, 0.45, 0.50, 0.55]},
            "objects": [
                {"name": "mug"},
                {"name": "broken", "set": [f"candidates.path={broken}"]},
            ],
        },
    }
    path = _study_file(tmp_path, data)
    out = tmp_path / "study"
    first = Study.from_yaml(path).run(out, engine="inline", progress=False, best_run=False)
    assert first.summary["counts"]["failed"] == 4
    assert main(["study", str(path), "--out", str(out), "--no-best"]) == 0
    text = capsys.readouterr().out
    assert text.count("  failed      #") == 3
    assert "  failed      ... and 1 more (column 'error' of placements.csv)" in text
    assert "  engine      ray not started: nothing left to run\n" in text
    # --workers is checked against this machine even when Ray would not start
    assert main(["study", str(path), "--out", str(out), "--workers", "100000"]) == 2
    assert "--workers 100000: this machine has" in capsys.readouterr().err


def test_quiet_study_whose_every_placement_failed_says_so_in_one_line(tmp_path, capsys):
    broken = _broken_grasp_file(tmp_path)
    data = {
        "base": str(FROM_FILE),
        "set": ["densify.subdivisions=1", f"candidates.path={broken}", "publish.html=false"],
        "sweep": {"object_pose": {"x": [0.40, 0.45]}},
    }
    path = _study_file(tmp_path, data)
    out = tmp_path / "study"
    first = Study.from_yaml(path).run(out, engine="inline", progress=False, best_run=False)
    assert first.best is None and first.summary["counts"]["failed"] == 2
    assert main(["study", str(path), "--out", str(out), "--quiet"]) == 2
    captured = capsys.readouterr()
    assert captured.out == f"{out}\n"
    assert captured.err == f"error: every placement failed; see {out / 'placements.csv'}\n"


def test_a_run_directory_is_not_a_study_directory(tmp_path, capsys):
    """--out of the other kind of gcm directory is refused naming what it is."""
    run = tmp_path / "run"
    sets = ["densify.subdivisions=1", "publish.html=false", "publish.plots=false"]
    assert main(["run", str(FROM_FILE), "--out", str(run), *(f"--set={s}" for s in sets)]) == 0
    path = _study_file(tmp_path, _small({"object_pose": {"x": [0.4]}}))
    capsys.readouterr()
    code = main(["study", str(path), "--out", str(run)])
    line = assert_one_line_error(code, capsys.readouterr().err)
    assert line.startswith("error: refusing to replace ")
    assert "it is a gcm run directory, not a study directory" in line
    files = ".gcm.json config.yaml configurations.npz grasps.csv manifold.npz summary.json"
    assert sorted(p.name for p in run.iterdir()) == files.split()


def _wait_for_parts(out: Path, n: int, proc: subprocess.Popen, timeout: float = 120.0) -> None:
    t0 = time.perf_counter()
    while time.perf_counter() - t0 < timeout:
        if proc.poll() is not None:
            raise AssertionError(f"the study ended early: {proc.communicate()}")
        parts = list((out / "placements").glob("*.npz")) if (out / "placements").is_dir() else []
        if len(parts) >= n:
            return
        time.sleep(0.05)
    raise AssertionError("no placement finished in time")


def _gcm_study(path: Path, out: Path, address: str) -> subprocess.Popen:
    argv = [sys.executable, "-m", "gcm_pipeline", "study", str(path), "--out", str(out)]
    argv += ["--address", address, "--workers", "1", "--no-best"]
    return subprocess.Popen(argv, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


def test_kill_resume_and_ctrl_c(cluster, tmp_path):
    data = _small({"object_pose": {"x": [0.35, 0.45, 0.55, 0.65], "yaw_deg": [0, 90]}})
    path = _study_file(tmp_path, data)
    out = tmp_path / "study"
    # 1. killed outright (SIGKILL) after a placement finished
    proc = _gcm_study(path, out, cluster.address)
    _wait_for_parts(out, 1, proc)
    proc.kill()
    proc.communicate()
    first = {p.name: p.stat().st_mtime_ns for p in (out / "placements").glob("*.npz")}
    assert 1 <= len(first) < 8
    assert not list((out / "placements").glob(".*"))  # no half-written file is visible
    # 2. resumed, then Ctrl-C: workers stop, the finished placements stay
    proc = _gcm_study(path, out, cluster.address)
    _wait_for_parts(out, len(first) + 1, proc)
    proc.send_signal(signal.SIGINT)
    stdout, stderr = proc.communicate(timeout=60)
    assert proc.returncode == 130, stderr
    assert "Traceback" not in stderr and "interrupted" in stderr
    second = {p.name: p.stat().st_mtime_ns for p in (out / "placements").glob("*.npz")}
    assert len(second) > len(first)
    assert all(second[k] == v for k, v in first.items())  # not recomputed
    # 3. resumed to the end: only the missing placements run
    result = Study.from_yaml(path).run(
        out, workers=1, address=cluster.address, progress=False, best_run=False
    )
    c = result.summary["counts"]
    assert c["finished"] == 8 and c["resumed"] == len(second) and c["run"] == 8 - len(second)
    third = {p.name: p.stat().st_mtime_ns for p in (out / "placements").glob("*.npz")}
    assert all(third[k] == v for k, v in second.items())
    assert [r["id"] for r in result.rows] == list(range(8))


def _in_session(sid: int) -> list[str]:
    """Command lines of the processes of session ``sid`` (the driver's, started with setsid)."""
    out = []
    for d in Path("/proc").iterdir():
        if not d.name.isdigit():
            continue
        try:
            if os.getsid(int(d.name)) == sid:
                out.append((d / "cmdline").read_bytes().replace(b"\0", b" ").decode()[:200])
        except OSError:  # gone meanwhile
            continue
    return out


def _session_ends(sid: int, timeout: float = 60.0) -> list[str]:
    """Wait until no process of session ``sid`` is left; return those still there."""
    t0 = time.perf_counter()
    while (left := _in_session(sid)) and time.perf_counter() - t0 < timeout:
        time.sleep(0.2)
    return left


def test_gcm_study_starts_ray_on_this_machine(tmp_path):
    """Without --address: Ray starts locally and stops again, also on SIGTERM; a rerun resumes."""
    data = _small({"object_pose": {"x": [0.35, 0.4, 0.45, 0.5, 0.55, 0.6]}})
    path = _study_file(tmp_path, data)
    out = tmp_path / "study"
    env = dict(os.environ)
    env["RAY_TMPDIR"] = tempfile.mkdtemp(prefix="gcm-ray-", dir="/tmp")
    argv = [sys.executable, "-m", "gcm_pipeline", "study", str(path), "--out", str(out)]
    argv += ["--workers", "1"]
    try:
        # SIGTERM (a process manager stopping it): like Ctrl-C, status 143, nothing of Ray left
        proc = subprocess.Popen(
            argv,
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
            env=env,
            start_new_session=True,  # Ray's processes join the driver's session
        )
        _wait_for_parts(out, 1, proc)
        proc.terminate()
        _, stderr = proc.communicate(timeout=120)
        assert proc.returncode == 143, stderr
        assert stderr.endswith("run the same command to resume\ninterrupted (SIGTERM)\n"), stderr
        assert _session_ends(proc.pid) == []
        first = len(list((out / "placements").glob("*.npz")))
        proc = subprocess.run(argv, capture_output=True, text=True, env=env, timeout=300)
    finally:
        shutil.rmtree(env["RAY_TMPDIR"], ignore_errors=True)
    assert proc.returncode == 0, proc.stderr
    assert "best placement #" in proc.stdout
    assert "ray" in proc.stdout and "local" in proc.stdout
    summary = json.loads((out / "summary.json").read_text())
    assert summary["engine"]["mode"] == "local" and summary["complete"]
    assert summary["counts"]["resumed"] == first and summary["counts"]["finished"] == 6
    assert (out / "best" / "summary.json").is_file()
    # a finished study run again: every placement resumed, Ray not even started
    again = subprocess.run(argv, capture_output=True, text=True, env=env, timeout=300)
    assert again.returncode == 0, again.stderr
    assert "0 run now, 6 resumed" in again.stdout and "not started" in again.stdout
    summary2 = json.loads((out / "summary.json").read_text())
    assert summary2["engine"]["mode"].startswith("not started") and summary2["complete"]
    assert summary2["counts"]["run"] == 0 and summary2["timings_s"]["startup"] == 0
    assert summary2["best"]["id"] == summary["best"]["id"]


def test_ctrl_c_while_ray_starts_stops_it_whole(tmp_path):
    """Ctrl-C inside Ray's start-up (once its raylet runs): status 130, one line, nothing left.

    Cut in the middle, the start-up left Ray's agents running and sometimes crashed
    the interpreter at exit (status 139); the interrupt now waits for the start-up.
    """
    path = _study_file(tmp_path, _small({"object_pose": {"x": [0.4, 0.5]}}))
    out = tmp_path / "study"
    env = dict(os.environ)
    env["RAY_TMPDIR"] = tempfile.mkdtemp(prefix="gcm-ray-", dir="/tmp")
    argv = [sys.executable, "-m", "gcm_pipeline", "study", str(path), "--out", str(out)]
    try:
        proc = subprocess.Popen(
            [*argv, "--workers", "1", "-q"],
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
            env=env,
            start_new_session=True,
        )
        t0 = time.perf_counter()
        while not any("raylet" in c for c in _in_session(proc.pid)):
            assert proc.poll() is None and time.perf_counter() - t0 < 60
            time.sleep(0.02)
        proc.send_signal(signal.SIGINT)
        _, stderr = proc.communicate(timeout=120)
        assert proc.returncode == 130, stderr
        assert stderr == "interrupted\n"
        assert _session_ends(proc.pid) == []
        assert not out.exists()  # nothing was written: the directory went again
    finally:
        shutil.rmtree(env["RAY_TMPDIR"], ignore_errors=True)


def test_a_small_region_of_a_huge_sweep_builds_only_what_is_inside():
    """10^10 combinations cut down by a box region to a few: only those are built.

    Run under a 2 GiB address-space cap: building every combination first and
    filtering afterwards (tens of GB) fails there.
    """
    wide = {"from": 0.0, "to": 1.0, "steps": 100_001}  # spacing 1e-5
    region = {"min": [0.49999, -0.00001, -1.0], "max": [0.50001, 0.00001, 1.0]}
    data = _small({"object_pose": {"x": wide, "y": wide, "region": region}})
    code = (
        "import resource; resource.setrlimit(resource.RLIMIT_AS, (2 << 30, 2 << 30)); "
        "import json, sys; from gcm_pipeline import Study; "
        f"s = Study.from_dict(json.loads({json.dumps(json.dumps(data))})); "
        "p = s.placements(); "
        "print(len(p), s.size()[0], sorted({round(x.object_pose['x'], 6) for x in p}))"
    )
    proc = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, cwd=ROOT, timeout=300
    )
    assert proc.returncode == 0, proc.stderr[-2000:]
    n, size, xs = proc.stdout.strip().split(" ", 2)
    assert int(n) == int(size) == 6 and xs == "[0.49999, 0.5, 0.50001]"  # y: 0, 1e-5
