"""``gcm run`` with a grasp file's score: ranking by it, limit, and one-line errors (exit 2)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import yaml
from helpers import QUICK, assert_one_line_error

from gcm_pipeline.config import Config
from gcm_pipeline.geometry.dualquat import dq_to_matrix
from gcm_pipeline.pipeline import generate_candidates, load_manifold

PLANE = {
    "shape": "plane",
    "dims": {"size": [0.3, 0.3]},
    "pose": {"xyz": [0.45, 0.0, 0.03]},
}


def _grasps(n: int) -> np.ndarray:
    """``n`` grasps from above on the plane in front of the Panda (the plane generator's)."""
    cfg = Config.from_dict({"object": PLANE, "candidates": {"source": "plane", "count": n}})
    return dq_to_matrix(generate_candidates(cfg)["dq"])


def _config(tmp_path: Path, grasp_file: Path, **sections: object) -> Path:
    doc = {
        "robot": {"spec": "panda"},
        "object": PLANE,
        "candidates": {"source": "file", "path": str(grasp_file)},
        "manifold": {"projection": "xy", "triangulator": "bowyer_watson"},
        "densify": {"subdivisions": 2},
        "approach": None,
        "environment": {"table": {"height": 0.0}},
        **sections,
    }
    path = tmp_path / "c.yaml"
    path.write_text(yaml.safe_dump(doc))
    return path


@pytest.mark.parametrize(
    "kind,sections,fragments",
    [
        ("nan_csv", {}, ("g.csv:3", "score is nan")),
        ("short_npz", {}, ("g.npz", "array 'score' has 2 scores for 3 grasps")),
        ("npy", {"ranking": {"metric": "score"}}, ("ranking.metric", "'score'", "g.npy")),
        (
            "npy",
            {"ranking": {"metric": "combined", "weights": {"score": 1.0}}},
            ("ranking.weights.score",),
        ),
        ("npy_min", {}, ("candidates.min_score", "g.npy", "has none")),
    ],
)
def test_bad_scores_are_one_line_errors(tmp_path, cli, kind, sections, fragments):
    poses = _grasps(3)
    if kind == "nan_csv":
        grasp_file = tmp_path / "g.csv"
        lines = ["x,y,z,qw,qx,qy,qz,score"]
        lines += [f"{0.4 + 0.02 * i},0,0.03,0,1,0,0,{s}" for i, s in enumerate(["1", "nan", "0"])]
        grasp_file.write_text("\n".join(lines) + "\n")
    elif kind == "short_npz":
        grasp_file = tmp_path / "g.npz"
        np.savez(grasp_file, transforms=poses, score=np.array([0.5, 0.2]))
    else:
        grasp_file = tmp_path / "g.npy"
        np.save(grasp_file, poses)
    cfg = _config(tmp_path, grasp_file, **sections)
    if kind == "npy_min":
        cfg = _config(tmp_path, grasp_file)
        doc = yaml.safe_load(cfg.read_text())
        doc["candidates"]["min_score"] = 0.5
        cfg.write_text(yaml.safe_dump(doc))
    out = tmp_path / "run"
    code, _, err = cli("run", cfg, "--out", out, "--quiet", *QUICK)
    assert_one_line_error(code, err, *fragments)
    assert not out.exists()


def test_run_ranked_by_score_keeps_the_best_by_score(tmp_path, cli):
    poses = _grasps(6)
    score = np.array([0.1, 0.9, 0.4, 0.8, 0.2, 0.7])
    grasp_file = tmp_path / "g.npz"
    np.savez(grasp_file, transforms=poses, score=score)
    cfg = _config(
        tmp_path,
        grasp_file,
        candidates={"source": "file", "path": str(grasp_file), "limit": 3},
        ranking={"metric": "score", "top_k": 3},
    )
    out = tmp_path / "run"
    code, _, err = cli("run", cfg, "--out", out, "--quiet", *QUICK)
    assert code == 0, err
    summary = json.loads((out / "summary.json").read_text())
    assert summary["selection"] == {
        "read": 6,
        "kept": 3,
        "success_only": False,
        "min_score": None,
        "limit": 3,
        "limit_by": "score",
    }
    assert summary["counts"]["candidates"] == 3
    top = summary["ranking"]["top"]
    assert summary["ranking"]["metric"] == "score" and len(top) == 3
    scores = [t["score"] for t in top]
    assert scores == sorted(scores, reverse=True)
    assert scores[0] == pytest.approx(0.9)  # the best candidate (reachable from above)
    # the manifold's search by the run's metric: the score interpolated between rows
    found = load_manifold(out).best(starts=2, iterations=3)
    assert found.metric == "score"
    assert found.value[0] == pytest.approx(0.9) and (found.value >= found.start_value).all()
    assert (found.value <= 0.9 + 1e-9).all()  # a blend never beats its best vertex
