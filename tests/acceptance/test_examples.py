"""Every config in configs/ runs through ``gcm run`` and gives a complete run directory."""

from __future__ import annotations

import csv
import json

import numpy as np
import pytest
import yaml
from helpers import ROOT

from gcm_pipeline.config import Config, load_config
from gcm_pipeline.geometry.dualquat import dq_to_pos_quat
from gcm_pipeline.pipeline import (
    build_manifold,
    generate_candidates,
    place_file_object,
    target_config,
)
from gcm_pipeline.rundir.grasps_csv import CSV_COLUMNS
from gcm_pipeline.rundir.run import read_run

CONFIGS = sorted((ROOT / "configs").glob("*.yaml"))


def test_the_examples_exist():
    names = {p.stem for p in CONFIGS}
    assert {"flat_surface", "bottle_side", "box", "from_file"} <= names


@pytest.mark.parametrize("path", CONFIGS, ids=lambda p: p.stem)
def test_example_runs(path, tmp_path, cli):
    out = tmp_path / path.stem
    code, text, err = cli("run", path, "--out", out, "--no-wait")
    assert code == 0, err
    assert "run directory:" in text
    cfg = load_config(path)
    for name in ("grasps.csv", "summary.json", "manifold.npz", "config.yaml"):
        assert (out / name).is_file(), name
    if cfg.publish.html:
        assert (out / "scene.html").is_file()
    if cfg.publish.plots:
        assert (out / "manifold.png").is_file()

    summary = json.loads((out / "summary.json").read_text())
    counts = summary["counts"]
    assert set(summary) >= {"counts", "timings_s", "ranking", "config", "versions"}
    assert counts["candidates"] >= 3 and counts["triangles"] >= 1
    assert counts["densified"] > counts["candidates"]
    # a meaningful share of the grasps is reachable for the Panda at the origin
    assert counts["reachable"] >= 0.25 * counts["densified"], counts
    # the run's config: the object a grasp file names, placed (configs/acronym_mug.yaml);
    # the target as the object, the other objects obstacles (configs/two_objects.yaml)
    cfg = place_file_object(target_config(cfg))
    assert Config.from_dict(yaml.safe_load((out / "config.yaml").read_text())) == cfg

    with (out / "grasps.csv").open() as fh:
        rows = list(csv.DictReader(fh))
    header = list(rows[0])
    assert header[: len(CSV_COLUMNS)] == list(CSV_COLUMNS)
    assert len(rows) == counts["densified"]
    assert sum(r["reachable"] == "true" for r in rows) == counts["reachable"]
    ranks = [int(r["rank"]) for r in rows[: counts["reachable"]]]
    assert ranks == list(range(1, counts["reachable"] + 1))
    assert summary["ranking"]["metric"] == cfg.ranking.metric
    if path.stem == "bottle_side":
        # Yoshikawa alone put the best grasp 3.8 mm above the table
        assert float(rows[0]["clearance"]) > 0.02, rows[0]

    run = read_run(out)
    m = run.manifold
    assert m.triangles.max() < counts["candidates"]
    assert (
        list(run.grasps["origin"][: counts["candidates"]]) == ["candidate"] * counts["candidates"]
    )
    q = np.linalg.norm(run.grasps["dq"][:, :4], axis=1)
    assert np.allclose(q, 1.0)


def test_bottle_opposite_sides_are_not_linked():
    cfg = load_config(ROOT / "configs" / "bottle_side.yaml")
    cand = generate_candidates(cfg)
    m = build_manifold(cand, cfg)
    assert len(m.triangles) >= 100
    pos, _ = dq_to_pos_quat(cand["dq"])
    rel = pos[:, :2] - np.asarray(cfg.object.pose.xyz[:2])
    theta = np.arctan2(rel[:, 1], rel[:, 0])
    tri = theta[m.triangles]
    # largest angular gap between two vertices of a triangle, around the circle
    diff = np.abs(tri[:, :, None] - tri[:, None, :])
    diff = np.minimum(diff, 2 * np.pi - diff)
    assert np.degrees(diff.max()) < 90


def test_example_metrics():
    metrics = {p.stem: load_config(p).ranking for p in CONFIGS}
    assert metrics["bottle_side"].metric == "combined"
    assert metrics["bottle_side"].weights == {
        "yoshikawa": 1.0,
        "clearance": 0.5,
        "joint_limit_margin": 0.2,
    }
    for name in ("flat_surface", "box", "from_file"):
        assert metrics[name].metric == "yoshikawa"
