"""Pipeline: stage functions with the full config, Pipeline.run, RunResult, outputs."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from helpers import FLAT, ROOT

from gcm_pipeline import pipeline
from gcm_pipeline.config import Config, load_config
from gcm_pipeline.errors import OutputError
from gcm_pipeline.geometry.dualquat import dq_to_matrix
from gcm_pipeline.pipeline import (
    Pipeline,
    RunResult,
    build_manifold,
    check_reachability,
    densify,
    generate_candidates,
    load_robot,
    rank,
)
from gcm_pipeline.rundir import grasps_csv, transaction
from gcm_pipeline.rundir import run as run_files

QUICK = ("publish.html=false", "publish.plots=false")


@pytest.fixture(scope="module")
def cfg() -> Config:
    return load_config(FLAT, QUICK)


@pytest.fixture(scope="module")
def robot(cfg):
    return load_robot(cfg)


def test_stages_one_by_one(cfg, robot):
    cand = generate_candidates(cfg)
    assert cand.columns == ("dq",) and len(cand) == 3
    manifold = build_manifold(cand, cfg)
    assert manifold.triangles.shape == (1, 3) and manifold.projection == "xy"
    dense = densify(cand, manifold, cfg)
    assert len(dense) == 66  # (10 + 1)(10 + 2) / 2 lattice points
    assert np.array_equal(dense["dq"][:3], cand["dq"])  # candidates first, shared poses
    assert {"origin", "triangle", "vertices", "weights"} <= set(dense.columns)
    reach = check_reachability(dense, robot, cfg)
    assert {"reachable", "reason", "q", "pos_err", "rot_err"} <= set(reach.columns)
    assert reach["dq"] is dense["dq"]  # columns are shared, not copied
    ranked = rank(reach, robot, cfg)
    assert {"manipulability", "rank"} <= set(ranked.columns)
    n_ok = int(np.count_nonzero(ranked["reachable"]))
    assert sorted(ranked["rank"][ranked["reachable"]]) == list(range(1, n_ok + 1))
    assert np.all(ranked["rank"][~ranked["reachable"]] == 0)


def test_run_writes_the_directory_and_returns_a_result(tmp_path):
    result = Pipeline.from_yaml(FLAT, QUICK).run(tmp_path / "run", progress=False)
    assert isinstance(result, RunResult)
    assert result.run_dir == (tmp_path / "run").absolute()
    names = sorted(p.name for p in result.files)
    assert names == [
        "config.yaml",
        "configurations.npz",
        "grasps.csv",
        "manifold.npz",
        "summary.json",
    ]
    c = result.counts
    assert c["candidates"] == 3 and c["triangles"] == 1 and c["densified"] == 66
    assert c["reachable"] == int(np.count_nonzero(result.grasps["reachable"])) > 0
    assert list(result.timings)[:7] == [
        "candidates",
        "manifold",
        "densify",
        "robot",
        "reachability",
        "continuity",
        "ranking",
    ]
    text = repr(result)
    assert text.startswith("RunResult(") and "reachable=" in text and "run_dir=" in text
    assert "Pipeline(" in repr(Pipeline.from_yaml(FLAT))
    run = run_files.read_run(result.run_dir)
    assert run.summary["counts"] == c
    # configurations.npz: the (N, nq) configuration columns in grasps.csv row order
    csv = grasps_csv.read_grasps_csv(result.run_dir / "grasps.csv")
    with np.load(result.run_dir / "configurations.npz") as conf:
        assert set(conf.files) == {"q", "q_pregrasp", "q_retreat", "q_rejected"}
        np.testing.assert_array_equal(conf["q"], csv["q"])
        assert conf["q_rejected"].shape == (len(csv), 7)
    assert run.summary["ranking"]["metric"] == "yoshikawa"
    assert len(run.summary["ranking"]["top"]) == 5
    legend = run.summary["legend"]
    assert legend["colormap"] == "viridis"
    assert legend["reachable"] == c["reachable"]
    reachable_manip = result.grasps["manipulability"][result.grasps["reachable"]]
    vmin, vmax = legend["metric_range"]
    assert vmin <= reachable_manip.min() and vmax >= reachable_manip.max()
    # the table read back is the same set of poses
    assert np.allclose(dq_to_matrix(run.grasps["dq"][:3]), dq_to_matrix(result.grasps["dq"][:3]))
    assert (
        Config.from_dict(__import__("yaml").safe_load((result.run_dir / "config.yaml").read_text()))
        == result.config
    )


def test_same_config_same_bytes(tmp_path):
    p = Pipeline.from_yaml(FLAT, QUICK)
    a = p.run(tmp_path / "a", progress=False).run_dir
    b = Pipeline.from_yaml(FLAT, QUICK).run(tmp_path / "b", progress=False).run_dir
    assert (a / "grasps.csv").read_bytes() == (b / "grasps.csv").read_bytes()
    assert (a / "manifold.npz").read_bytes() == (b / "manifold.npz").read_bytes()
    assert (a / "config.yaml").read_bytes() == (b / "config.yaml").read_bytes()


def test_write_false_returns_only_the_result(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    result = Pipeline.from_yaml(FLAT, QUICK).run(progress=False, write=False)
    assert result.run_dir is None and result.files == []
    assert not any(tmp_path.iterdir())


def test_output_problems_are_found_before_any_work(tmp_path, monkeypatch):
    def boom(cfg):
        raise AssertionError("stage ran")

    monkeypatch.setattr(pipeline.run, "generate_candidates", boom)
    f = tmp_path / "file"
    f.write_text("x")
    with pytest.raises(OutputError):
        Pipeline.from_yaml(FLAT, QUICK).run(f)
    full = tmp_path / "full"
    full.mkdir()
    for name in ("summary.json", "grasps.csv"):
        (full / name).write_text("previous run")
    transaction.write_marker(full, "run")
    with pytest.raises(OutputError) as info:
        Pipeline.from_yaml(FLAT, QUICK).run(full)
    assert str(info.value) == (
        f"output directory {full} already exists and is not empty; pass --force (CLI) or "
        "force=True (Python) to replace it, or choose another --out"
    )
    (tmp_path / "data").mkdir()
    (tmp_path / "data" / "x").write_text("x")
    with pytest.raises(OutputError, match="not a gcm run directory"):
        Pipeline.from_yaml(FLAT, QUICK).run(tmp_path / "data", force=True)
    assert (tmp_path / "data" / "x").read_text() == "x"


def test_failure_leaves_nothing_behind(tmp_path, monkeypatch):
    def broken_publish(result, cfg, out_dir):
        (Path(out_dir) / "scene.html").write_text("half")
        raise RuntimeError("publish crashed")

    monkeypatch.setattr(pipeline.run, "publish", broken_publish)
    with pytest.raises(RuntimeError):
        Pipeline.from_yaml(FLAT, QUICK).run(tmp_path / "run", progress=False)
    assert list(tmp_path.iterdir()) == []
    # and a forced run that fails keeps the previous run
    old = tmp_path / "old"
    old.mkdir()
    (old / "grasps.csv").write_text("previous")
    (old / "summary.json").write_text("{}")
    transaction.write_marker(old, "run")
    with pytest.raises(RuntimeError):
        Pipeline.from_yaml(FLAT, QUICK).run(old, progress=False, force=True)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["old"]
    assert (old / "grasps.csv").read_text() == "previous"
    assert transaction.looks_like_run_dir(old)


def test_output_dir_from_config(tmp_path, monkeypatch):
    """output.dir (also from --set) is relative to the config's folder, not the working one."""
    (tmp_path / "cfg").mkdir()
    (tmp_path / "elsewhere").mkdir()
    config = tmp_path / "cfg" / "flat.yaml"
    config.write_text(FLAT.read_text())
    monkeypatch.chdir(tmp_path / "elsewhere")
    result = Pipeline.from_yaml(config, (*QUICK, "output.dir=out/flat")).run(progress=False)
    assert result.run_dir == tmp_path / "cfg" / "out" / "flat"
    assert (tmp_path / "cfg" / "out" / "flat" / "grasps.csv").is_file()
    assert list((tmp_path / "elsewhere").iterdir()) == []


def test_top_grasps_are_sorted(tmp_path):
    result = Pipeline.from_yaml(FLAT, QUICK).run(progress=False, write=False)
    top = result.top(4)
    assert [t["rank"] for t in top] == [1, 2, 3, 4]
    m = [t["manipulability"] for t in top]
    assert m == sorted(m, reverse=True)
    assert all(t["qw"] >= 0 and len(t["q"]) == 7 for t in top)


@pytest.mark.parametrize("metric", ["clearance", "combined", "joint_limit_margin"])
def test_every_config_metric_ranks(metric):
    cfg = load_config(FLAT, (*QUICK, f"ranking.metric={metric}"))
    result = Pipeline(cfg).run(progress=False, write=False)
    g = result.grasps
    column = {"clearance": "clearance", "combined": "combined"}.get(metric, metric)
    ok = g["rank"] > 0
    order = np.argsort(g["rank"][ok])
    values = np.asarray(g[column], dtype=float)[ok][order]
    assert np.all(np.diff(values) <= 1e-12)  # best first
    assert int(ok.sum()) == result.counts["reachable"]


def test_preflight_names_the_key_before_any_work(tmp_path, monkeypatch):
    from gcm_pipeline.errors import InputError, RobotSpecError

    def boom(cfg):
        raise AssertionError("stage ran")

    monkeypatch.setattr(pipeline.run, "generate_candidates", boom)
    cfg = load_config(FLAT, (*QUICK, "robot.spec=kuka"))
    with pytest.raises(RobotSpecError, match="^robot.spec: unknown robot 'kuka'"):
        pipeline.preflight(cfg)
    with pytest.raises(RobotSpecError, match="^robot.spec: "):
        Pipeline(cfg).run(tmp_path / "run")
    cfg = load_config(FLAT, (*QUICK, "environment.obstacles=[{shape: mesh, mesh: x.stl}]"))
    assert pipeline.input_files(cfg) == {"environment.obstacles.0.mesh": FLAT.parent / "x.stl"}
    with pytest.raises(InputError, match="^environment.obstacles.0.mesh: mesh file not found"):
        Pipeline(cfg).run(tmp_path / "run")
    assert list(tmp_path.iterdir()) == []


def test_a_run_never_replaces_the_folder_of_its_config(tmp_path):
    first = Pipeline.from_yaml(FLAT, QUICK).run(tmp_path / "a", progress=False).run_dir
    assert first is not None
    again = Pipeline.from_yaml(first / "config.yaml")
    with pytest.raises(OutputError, match="an input of this run"):
        again.run(first, force=True, progress=False)
    assert again.run(tmp_path / "b", progress=False).run_dir == tmp_path / "b"


def test_counts_break_down_dropped_and_unreachable(tmp_path):
    chart = ("manifold.structure=chart", "manifold.projection=spherical")  # drops triangles
    cfg = load_config(ROOT / "configs" / "box.yaml", (*QUICK, *chart))
    result = Pipeline(cfg).run(progress=False, write=False)
    c = result.counts
    assert sum(c["dropped_by_reason"].values()) == c["triangles_dropped"] > 0
    reasons = np.asarray(result.grasps["reason"])[~np.asarray(result.grasps["reachable"])]
    assert c["unreachable_by_reason"] == {
        str(k): int(v) for k, v in zip(*np.unique(reasons, return_counts=True), strict=True)
    }
    assert list(c["unreachable_by_reason"].values()) == sorted(
        c["unreachable_by_reason"].values(), reverse=True
    )


def test_reach_options_map_the_config_sections():
    """ik, seed, robot.base_pose, approach and retreat become one frozen ReachOptions."""
    cfg = load_config(
        FLAT,
        (
            *QUICK,
            "robot.base_pose={xyz: [0.1, 0.2, 0.0], rpy_deg: [0, 0, 90]}",
            "approach={distance: 0.05, steps: 4}",
            "retreat={distance: 0.08, direction: [1, 0, 0], frame: world}",
            "ik.solutions=3",
            "seed=7",
        ),
    )
    opt = pipeline.reach_options(cfg)
    np.testing.assert_allclose(opt.base_pose, cfg.robot.base_pose.matrix())
    assert opt.seed == 7 and opt.solutions == 3 and opt.backend == cfg.ik.backend
    assert opt.position_tolerance == cfg.ik.position_tolerance and opt.warm_start
    # the approach backs out along the grasp frame's z
    assert opt.approach is not None and opt.approach.frame == "grasp"
    assert opt.approach.distance == 0.05 and opt.approach.steps == 4
    assert opt.approach.direction == (0.0, 0.0, -1.0) and not opt.approach.holding
    # a world retreat direction is turned into the robot's base frame (base yawed 90 deg)
    assert opt.retreat is not None and opt.retreat.frame == "base" and opt.retreat.holding
    np.testing.assert_allclose(opt.retreat.direction, (0.0, -1.0, 0.0), atol=1e-12)
    # frozen: a check cannot change the options it was given
    with pytest.raises(AttributeError):
        opt.seed = 8  # type: ignore[misc]
    with pytest.raises(TypeError):
        opt.ik_options["random_seed"] = 1  # type: ignore[index]
    with pytest.raises(ValueError):
        opt.base_pose[0, 3] = 1.0
    # without approach and retreat sections (flat_surface.yaml) there is nothing to move
    plain = pipeline.reach_options(load_config(FLAT, QUICK))
    assert plain.approach is None and plain.retreat is None
