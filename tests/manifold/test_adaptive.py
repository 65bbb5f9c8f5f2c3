"""Adaptive densification: refine where reachability changes, agree with the uniform lattice."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from helpers import BOTTLE, ROOT, assert_one_line_error
from scipy.spatial import cKDTree

import gcm_pipeline as gcm
from gcm_pipeline.cli import main
from gcm_pipeline.geometry.pose_metric import pose_features
from gcm_pipeline.manifold.adaptive import refine, uniform_size
from gcm_pipeline.manifold.lattice import interpolate, row_mesh
from gcm_pipeline.pipeline import ReachabilityCheck, densify_adaptive
from gcm_pipeline.table import GraspTable

LEVEL = 3


@pytest.fixture(scope="module")
def bottle() -> dict[str, object]:
    cfg = gcm.load_config(BOTTLE, [f"densify.adaptive={{max_level: {LEVEL}}}"])
    cand = gcm.generate_candidates(cfg)
    mesh = gcm.build_manifold(cand, cfg)
    robot = gcm.load_robot(cfg.robot.spec)
    check = ReachabilityCheck(robot, cfg)
    adaptive = densify_adaptive(cand, mesh, robot, cfg, check=check)
    ucfg = gcm.load_config(BOTTLE, [f"densify.subdivisions={2**LEVEL}"])
    uniform = gcm.check_reachability(gcm.densify(cand, mesh, ucfg), robot, ucfg)
    return {
        "cfg": cfg,
        "cand": cand,
        "mesh": mesh,
        "adaptive": adaptive,
        "uniform": uniform,
        "solved": check.solved,
    }


def test_adaptive_rows_are_rows_of_the_uniform_lattice(bottle: dict) -> None:
    ad, uni, cand = bottle["adaptive"], bottle["uniform"], bottle["cand"]
    n_c = len(cand)
    assert np.array_equal(ad["dq"][:n_c], cand["dq"])  # candidates first, bit for bit
    assert np.all(ad["origin"][:n_c] == "candidate") and np.all(ad["level"][:n_c] == 0)
    inner = ad["origin"] == "interpolated"
    assert np.all(ad["level"][inner] >= 1) and ad["level"].max() == LEVEL
    # weights are multiples of 2**-LEVEL and every pose is that lattice point of the uniform run
    w = np.asarray(ad["weights"])[inner]
    assert np.array_equal(w * 2**LEVEL, np.round(w * 2**LEVEL))
    feat = pose_features(np.asarray(uni["dq"]))
    flip = feat.copy()
    flip[:, 3:] *= -1
    d, _ = cKDTree(np.concatenate((feat, flip))).query(pose_features(np.asarray(ad["dq"])))
    assert d.max() < 1e-12  # every adaptive pose is a pose of the uniform lattice
    # no point twice
    assert len(np.unique(np.round(np.asarray(ad["dq"]), 12), axis=0)) == len(ad)


def test_adaptive_reproduces_the_uniform_classification_with_fewer_solves(bottle: dict) -> None:
    ad, uni, mesh, cand = bottle["adaptive"], bottle["uniform"], bottle["mesh"], bottle["cand"]
    assert bottle["solved"] == len(ad)
    assert len(uni) == uniform_size(mesh.triangles, len(cand), LEVEL)
    rows = row_mesh(ad, mesh.triangles, len(cand))
    inner = np.asarray(uni["origin"]) == "interpolated"
    predicted = np.zeros(len(uni), dtype=bool)
    predicted[~inner] = np.asarray(ad["reachable"])[: len(cand)]
    value = interpolate(
        rows, np.asarray(ad["reachable"], float), uni["triangle"][inner], uni["weights"][inner]
    )
    assert np.isfinite(value).all()
    predicted[inner] = value >= 0.5
    agreement = float(np.mean(predicted == np.asarray(uni["reachable"])))
    assert agreement >= 0.99
    assert len(ad) * 3 <= len(uni)  # L = 3 here; the benchmark measures L = 4, 5
    # the refinement concentrates at the boundary: faces at the deepest level are
    # mixed (corners disagree) far more often than faces of the uniform lattice
    reach = np.asarray(ad["reachable"])
    mixed = reach[rows.faces].any(axis=1) & ~reach[rows.faces].all(axis=1)
    deep = np.isin(rows.faces, np.flatnonzero(np.asarray(ad["level"]) == LEVEL)).any(axis=1)
    ufaces = row_mesh(uni, mesh.triangles, len(cand)).faces
    ureach = np.asarray(uni["reachable"])[ufaces]
    uniform_mixed = (ureach.any(axis=1) & ~ureach.all(axis=1)).mean()
    assert mixed[deep].mean() > 3 * uniform_mixed


def test_metric_refinement_splits_where_the_metric_varies(bottle: dict) -> None:
    cand, mesh = bottle["cand"], bottle["mesh"]
    seen: list[int] = []

    def check(dq: np.ndarray, seeds: object) -> GraspTable:
        seen.append(len(dq))
        z = gcm.dq_to_pos_quat(dq)[0][:, 2]
        return GraspTable(
            {
                "dq": dq,
                "reachable": np.ones(len(dq), bool),
                "q": np.zeros((len(dq), 7)),
                "z": z,
            }
        )

    flat = refine(cand, mesh, check, max_level=2, criteria=("boundary",))
    assert len(flat) == len(cand)  # all reachable: nothing to refine
    steep = refine(
        cand,
        mesh,
        check,
        max_level=2,
        criteria=("metric",),
        score=lambda t: np.asarray(t["z"]),
        metric_threshold=0.01,
    )
    assert len(steep) == uniform_size(mesh.triangles, len(cand), 2)  # z varies everywhere
    assert steep["level"].max() == 2


@pytest.mark.parametrize(
    "kwargs, match",
    [
        ({"max_level": 11}, "max_level"),
        ({"max_level": 0}, "max_level"),
        ({"max_level": 2, "min_level": 3}, "min_level"),
        ({"max_level": 2, "criteria": ("edges",)}, "criterion"),
        ({"max_level": 2, "metric_threshold": 0.0}, "metric_threshold"),
    ],
)
def test_refine_rejects_bad_parameters(bottle: dict, kwargs: dict, match: str) -> None:
    with pytest.raises(gcm.GcmError, match=match):
        refine(bottle["cand"], bottle["mesh"], lambda dq, s: None, **kwargs)  # type: ignore[arg-type]


def test_adaptive_respects_max_poses(bottle: dict) -> None:
    cfg = gcm.load_config(
        BOTTLE, ["densify.adaptive={max_level: 3, min_level: 3}", "densify.max_poses=500"]
    )
    robot = gcm.load_robot(cfg.robot.spec)
    with pytest.raises(gcm.ConfigError, match="densify.max_poses"):
        densify_adaptive(bottle["cand"], bottle["mesh"], robot, cfg)


def test_gcm_run_adaptive_and_bad_levels(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    cfg = ROOT / "configs" / "flat_surface.yaml"
    out = tmp_path / "flat"
    assert (
        main(["run", str(cfg), "--out", str(out), "--set", "densify.adaptive={max_level: 2}", "-q"])
        == 0
    )
    run = gcm.read_run(out)
    assert "level" in run.grasps and run.summary["counts"]["adaptive"]["max_level"] == 2
    assert (out / "levels.png").is_file() and (out / "patches.png").is_file()
    capsys.readouterr()
    bad = [
        "run",
        str(cfg),
        "--out",
        str(tmp_path / "x"),
        "--set",
        "densify.adaptive={max_level: 12}",
    ]
    code = main(bad)
    assert_one_line_error(code, capsys.readouterr().err, "max_level")
    assert not (tmp_path / "x").exists()
