"""The synthesiser's score: every format's quality as the ``score`` column, min_score, limit.

Real data: ACRONYM's mug file (tests/data/acronym); the other formats are small
files written here in each synthesiser's layout.
"""

from __future__ import annotations

import json
import logging
import shutil
from pathlib import Path

import numpy as np
import pytest
import yaml
from helpers import DATA

from gcm_pipeline.config import Config
from gcm_pipeline.errors import ConfigError, InputError
from gcm_pipeline.pipeline import build_manifold, densify, generate_candidates
from gcm_pipeline.sources.files import read_grasps

MUG_H5 = DATA / "acronym" / "Mug_10f6e09036350e92b3f21f1137c3c347_0.0002682457830986903.h5"
SUCCESS = "grasps/qualities/flex/object_in_gripper"


def _mug_success() -> np.ndarray:
    h5py = pytest.importorskip("h5py")
    with h5py.File(MUG_H5, "r") as fh:
        return np.asarray(fh[SUCCESS][()])


def _poses(n: int) -> np.ndarray:
    """``n`` grasps from above on a row along x, 1 cm apart."""
    p = np.tile(np.eye(4), (n, 1, 1))
    p[:, :3, :3] = np.diag([1.0, -1.0, -1.0])
    p[:, 0, 3] = 0.4 + 0.01 * np.arange(n)
    p[:, 2, 3] = 0.1
    return p


def _npz(path: Path, n: int, **arrays: object) -> Path:
    np.savez(path, transforms=_poses(n), **arrays)
    return path


def _csv(path: Path, scores: list[str]) -> Path:
    rows = ["x,y,z,qw,qx,qy,qz,score"]
    rows += [f"{0.4 + 0.01 * i},0,0.1,0,1,0,0,{s}" for i, s in enumerate(scores)]
    path.write_text("\n".join(rows) + "\n")
    return path


def _cfg(path: Path, **candidates: object) -> Config:
    return Config.from_dict(
        {
            "object": {"shape": "plane", "dims": {"size": [0.3, 0.3]}},
            "candidates": {"source": "file", "path": str(path), **candidates},
        }
    )


# ------------------------------------------------------------------ ACRONYM


def test_acronym_score_is_object_in_gripper():
    success = _mug_success()
    grasps = read_grasps(MUG_H5, "acronym", success_only=False)
    score = grasps.columns["score"]
    assert score.dtype == np.float64 and len(score) == len(success) == 2000
    np.testing.assert_array_equal(score, success.astype(float))
    assert 0.6 < score.mean() < 0.7  # 1,290 of 2,000 grasps held the mug
    only = read_grasps(MUG_H5, "acronym", success_only=True)
    assert len(only.poses) == int(success.sum()) and (only.columns["score"] == 1.0).all()
    # the default: a file that labels success keeps its successful grasps, and says so
    default = read_grasps(MUG_H5, "acronym")
    np.testing.assert_array_equal(default.columns["source_id"], np.flatnonzero(success))
    assert default.selection.success_only and default.selection.read == 2000


def test_acronym_limit_keeps_the_successful_grasps_first_in_file_order(caplog):
    success = _mug_success()
    with caplog.at_level(logging.INFO, logger="gcm_pipeline"):
        grasps = read_grasps(MUG_H5, "acronym", success_only=False, limit=50)
    # the best 50 by score are successful ones; ties broken by row: the first 50 of them
    np.testing.assert_array_equal(grasps.columns["source_id"], np.flatnonzero(success)[:50])
    assert grasps.selection.limit_by == "score" and grasps.selection.kept == 50
    assert "keeps the best 50 of 2000 grasps by score" in caplog.text


def test_acronym_nan_quality_names_the_file_and_row(tmp_path):
    h5py = pytest.importorskip("h5py")
    path = tmp_path / "mug.h5"
    shutil.copy(MUG_H5, path)
    with h5py.File(path, "r+") as fh:
        values = fh[SUCCESS][()].astype(float)
        values[7] = np.nan
        del fh[SUCCESS]
        fh[SUCCESS] = values
    with pytest.raises(InputError) as info:
        read_grasps(path, "acronym")
    msg = str(info.value)
    assert "\n" not in msg and str(path) in msg and SUCCESS in msg and "grasp 7 " in msg


# ------------------------------------------------------------------ GraspGen


def _graspgen(path: Path, confidences: list[float]) -> Path:
    poses = _poses(3)
    doc = {"grasps": {"transforms": poses.tolist(), "confidences": confidences}}
    path.write_text(json.dumps(doc))  # json writes NaN as NaN, which json reads back
    return path


def test_graspgen_confidences_are_the_score(tmp_path):
    grasps = read_grasps(_graspgen(tmp_path / "g.json", [0.2, 0.9, 0.5]), "graspgen")
    np.testing.assert_array_equal(grasps.columns["score"], [0.2, 0.9, 0.5])


@pytest.mark.parametrize(
    "confidences,fragments",
    [
        ([0.2, float("nan"), 0.5], ("grasps.confidences", "grasp 1 ", "nan")),
        ([0.2, 0.9], ("grasps.confidences", "2 scores for 3 grasps")),
    ],
)
def test_graspgen_bad_confidences_are_one_line_errors(tmp_path, confidences, fragments):
    path = _graspgen(tmp_path / "g.json", confidences)
    with pytest.raises(InputError) as info:
        read_grasps(path, "graspgen")
    msg = str(info.value)
    assert "\n" not in msg and str(path) in msg
    for fragment in fragments:
        assert fragment in msg


def _isaac(path: Path, confidences: list[float | None]) -> Path:
    grasps = {}
    for i, c in enumerate(confidences):
        g = {"position": [0.01 * i, 0, 0], "orientation": {"w": 1.0, "xyz": [0, 0, 0]}}
        if c is not None:
            g["confidence"] = c
        grasps[f"grasp_{i}"] = g
    path.write_text(yaml.safe_dump({"format": "isaac_grasp", "grasps": grasps}))
    return path


def test_isaac_grasp_scores_are_all_or_none(tmp_path):
    scored = read_grasps(_isaac(tmp_path / "a.yaml", [0.3, 0.6]), "graspgen")
    np.testing.assert_array_equal(scored.columns["score"], [0.3, 0.6])
    none = read_grasps(_isaac(tmp_path / "b.yaml", [None, None]), "graspgen")
    assert "score" not in none.columns  # no confidence in the file: no score, not NaN
    with pytest.raises(InputError, match=r"grasp 'grasp_1' has no confidence, though 1 of 2"):
        read_grasps(_isaac(tmp_path / "c.yaml", [0.3, None]), "graspgen")
    with pytest.raises(InputError, match=r"grasp 'grasp_0': score is nan"):
        read_grasps(_isaac(tmp_path / "d.yaml", [float("nan"), 0.2]), "graspgen")


# ---------------------------------------------------------- Contact-GraspNet


def test_contact_graspnet_scores(tmp_path):
    poses = _poses(3)
    path = tmp_path / "predictions.npz"
    np.savez(path, pred_grasps_cam={2: poses[:2], 5: poses[2:]}, scores={2: [0.4, 0.7], 5: [0.1]})
    got = read_grasps(path, "contact_graspnet")
    np.testing.assert_allclose(got.columns["score"], [0.4, 0.7, 0.1])
    np.savez(path, pred_grasps_cam={2: poses})
    assert "score" not in read_grasps(path, "contact_graspnet").columns
    np.savez(path, pred_grasps_cam={2: poses[:2], 5: poses[2:]}, scores={2: [0.4, 0.7]})
    with pytest.raises(InputError, match=r"scores has no entry for segment 5"):
        read_grasps(path, "contact_graspnet")
    np.savez(path, pred_grasps_cam={2: poses}, scores={2: [0.4, np.nan, 0.1]})
    with pytest.raises(InputError, match=r"scores\[2\]: grasp 1 \(0-based\): score is nan"):
        read_grasps(path, "contact_graspnet")
    np.savez(path, pred_grasps_cam={2: poses}, scores={2: [0.4, 0.1]})
    with pytest.raises(InputError, match=r"scores\[2\] has 2 scores for 3 grasps"):
        read_grasps(path, "contact_graspnet")


# ------------------------------------------------------------------ GraspNet


def test_graspnet_score_column(tmp_path):
    rows = np.zeros((3, 17))
    rows[:, 4:13] = np.eye(3).reshape(-1)
    rows[:, 13] = [0.0, 0.01, 0.02]
    rows[:, 0] = [0.3, 0.8, 0.1]
    path = tmp_path / "g.npy"
    np.save(path, rows)
    np.testing.assert_allclose(read_grasps(path, "graspnet").columns["score"], rows[:, 0])
    rows[2, 0] = np.nan
    np.save(path, rows)
    with pytest.raises(InputError, match=r"column 0 \(score\): grasp 2 \(0-based\): score is nan"):
        read_grasps(path, "graspnet")


# ------------------------------------------------------------------ npz, csv, npy


def test_npz_score_array(tmp_path):
    path = _npz(tmp_path / "g.npz", 3, score=np.array([1, 3, 2]))
    score = read_grasps(path, "npz").columns["score"]
    assert score.dtype == np.float64 and score.tolist() == [1.0, 3.0, 2.0]  # blendable floats
    path = _npz(tmp_path / "g.npz", 3, score=np.array([0.5, 0.2]))
    with pytest.raises(InputError) as info:  # was skipped with a log line: now an error
        read_grasps(path, "npz")
    assert str(path) in str(info.value) and "array 'score' has 2 scores for 3 grasps" in str(
        info.value
    )
    path = _npz(tmp_path / "g.npz", 3, score=np.array([0.5, np.inf, 0.2]))
    with pytest.raises(InputError, match=r"array 'score': grasp 1 \(0-based\): score is inf"):
        read_grasps(path, "npz")


def test_csv_score_column(tmp_path):
    path = _csv(tmp_path / "g.csv", ["1", "0", "2"])
    score = read_grasps(path, "csv").columns["score"]
    assert score.dtype == np.float64 and score.tolist() == [1.0, 0.0, 2.0]
    path = _csv(tmp_path / "g.csv", ["0.5", "", "0.2"])  # an empty cell on line 3
    with pytest.raises(InputError) as info:
        read_grasps(path, "csv")
    assert f"{path}:3: score is nan" in str(info.value) and info.value.row == 1
    path = _csv(tmp_path / "g.csv", ["0.5", "good", "0.2"])
    with pytest.raises(InputError, match=r"g.csv:3: column 'score': not a number: 'good'"):
        read_grasps(path, "csv")


def test_a_file_without_a_score_has_none_and_min_score_names_the_key(tmp_path):
    path = tmp_path / "g.npy"
    np.save(path, _poses(3))
    grasps = read_grasps(path, "npy")
    assert "score" not in grasps.columns
    with pytest.raises(InputError) as info:
        read_grasps(path, "npy", min_score=0.5)
    assert info.value.key == "candidates.min_score" and "has none" in str(info.value)


# ------------------------------------------------------------------ min_score and limit


@pytest.mark.parametrize(
    "scores,limit,rows",
    [
        ([0.1, 0.9, 0.5, 0.9, 0.3], 2, [1, 3]),
        ([0.1, 0.9, 0.5, 0.9, 0.3], 3, [1, 2, 3]),
        ([0.5, 0.9, 0.5, 0.5], 2, [0, 1]),  # a tie at the cut: the earlier row
        ([0.5, 0.9], 5, [0, 1]),
    ],
)
def test_limit_keeps_the_best_by_score_in_file_order(tmp_path, scores, limit, rows):
    path = _npz(tmp_path / "g.npz", len(scores), score=np.array(scores))
    got = read_grasps(path, "npz", limit=limit)
    assert got.columns["source_id"].tolist() == rows
    np.testing.assert_array_equal(got.poses, _poses(len(scores))[rows])


def test_limit_without_a_score_keeps_the_first_and_says_so(tmp_path, caplog):
    path = tmp_path / "g.npy"
    np.save(path, _poses(5))
    with caplog.at_level(logging.INFO, logger="gcm_pipeline"):
        got = read_grasps(path, "npy", limit=2)
    assert got.columns["source_id"].tolist() == [0, 1] and got.selection.limit_by == "file order"
    assert "keeps the first 2 of 5 grasps in file order (the file has no score)" in caplog.text


def test_min_score_then_limit_in_the_candidate_step(tmp_path):
    path = _npz(tmp_path / "g.npz", 6, score=np.array([0.1, 0.9, 0.5, 0.7, 0.3, 0.6]))
    report: dict = {}
    table = generate_candidates(_cfg(path, min_score=0.5, limit=2), report=report)
    assert table["source_id"].tolist() == [1, 3] and table["score"].tolist() == [0.9, 0.7]
    assert report["selection"] == {
        "read": 6,
        "kept": 2,
        "success_only": False,
        "min_score": 0.5,
        "limit": 2,
        "limit_by": "score",
    }
    table = generate_candidates(_cfg(path, min_score=0.6))
    assert table["source_id"].tolist() == [1, 3, 5]  # score >= 0.6, the bound kept
    with pytest.raises(
        InputError,
        match=r"min_score 0.95 keeps none of its 6 grasps \(their scores are 0.1 to 0.9\)",
    ):
        generate_candidates(_cfg(path, min_score=0.95))


def test_min_score_is_refused_for_a_generator_without_score():
    with pytest.raises(ConfigError, match="min_score: generator 'plane' gives no score"):
        Config.from_dict(
            {
                "object": {"shape": "plane", "dims": {"size": [0.3, 0.3]}},
                "candidates": {"source": "plane", "count": 3, "min_score": 0.5},
            }
        )


def test_score_metric_without_a_score_is_a_config_error_naming_the_key(tmp_path):
    path = tmp_path / "g.npy"
    np.save(path, _poses(3))
    for ranking, key in (
        ({"metric": "score"}, "ranking.metric"),
        ({"metric": "combined", "weights": {"yoshikawa": 1, "score": 1}}, "ranking.weights.score"),
    ):
        cfg = Config.from_dict({**_cfg(path).to_dict(), "ranking": ranking})
        with pytest.raises(ConfigError) as info:
            generate_candidates(cfg)
        assert info.value.key == key and str(info.value).startswith(f"{key}: 'score'")


# ------------------------------------------------------------------ interpolated rows


def test_interpolated_rows_carry_the_blended_score(tmp_path):
    poses = _poses(3)
    poses[1, 1, 3] = 0.02  # a triangle, not a line
    np.savez(tmp_path / "g.npz", transforms=poses, score=np.array([0.2, 1.0, 0.5]))
    cfg = Config.from_dict(
        {
            **_cfg(tmp_path / "g.npz").to_dict(),
            "manifold": {"projection": "xy", "triangulator": "bowyer_watson"},
            "densify": {"subdivisions": 4},
        }
    )
    candidates = generate_candidates(cfg)
    manifold = build_manifold(candidates, cfg)
    table = densify(candidates, manifold, cfg)
    new = np.asarray(table["triangle"]) >= 0
    assert new.sum() == 15 - 3  # the lattice of 4 subdivisions, less the candidates
    w, v = table["weights"][new], table["vertices"][new]
    np.testing.assert_allclose(table["score"][new], (w * candidates["score"][v]).sum(axis=1))
    np.testing.assert_array_equal(table["score"][~new], [0.2, 1.0, 0.5])
    assert 0.2 < table["score"][new].min() and table["score"][new].max() < 1.0


def test_min_score_filters_the_antipodal_samplers_grasps():
    def sampled(**extra: object):
        cfg = Config.from_dict(
            {
                "object": {"shape": "box", "dims": {"size": [0.05, 0.07, 0.12]}},
                "candidates": {"source": "antipodal", "count": 40, "seed": 1, **extra},
            }
        )
        return generate_candidates(cfg)

    every, kept = sampled(), sampled(min_score=0.97)
    want = every["score"] >= 0.97
    assert 0 < want.sum() < len(want)  # the bound splits this sample
    np.testing.assert_array_equal(kept["score"], every["score"][want])
    np.testing.assert_array_equal(kept["dq"], every["dq"][want])


def test_a_filter_that_keeps_nothing_says_which_and_why(tmp_path):
    poses = np.tile(np.eye(4), (4, 1, 1))
    poses[:, 0, 3] = np.arange(4) * 0.01
    path = tmp_path / "g.npz"
    np.savez(path, transforms=poses, success=np.zeros(4), score=[0.1, 0.2, 0.3, 0.4])
    with pytest.raises(InputError) as info:
        read_grasps(path, "npz")
    assert str(info.value) == (
        f"{path}: none of its 4 grasps is labelled successful "
        "(candidates.success_only: false keeps them all)"
    )
    assert info.value.key == "candidates.success_only"
    with pytest.raises(InputError, match=r"min_score 0.5 keeps none of its 4 grasps \(their "):
        read_grasps(path, "npz", success_only=False, min_score=0.5)
    kept = read_grasps(path, "npz", success_only=False, min_score=0.3)
    assert kept.columns["source_id"].tolist() == [2, 3]


def test_success_only_true_on_a_file_of_failures_says_so(tmp_path):
    poses = np.tile(np.eye(4), (3, 1, 1))
    poses[:, 0, 3] = np.arange(3) * 0.01
    path = tmp_path / "g.npz"
    np.savez(path, transforms=poses, success=np.zeros(3))
    with pytest.raises(InputError) as info:
        read_grasps(path, "npz", success_only=True)
    assert str(info.value).startswith(f"{path}: none of its 3 grasps is labelled successful")
    assert info.value.key == "candidates.success_only"
