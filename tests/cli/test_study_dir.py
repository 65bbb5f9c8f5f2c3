"""Results commands on a study directory: gcm show summarises it, query answers on best/.

One small study (6 placements in this process, ``engine="inline"``, with
``best/``) is shared by the module; a test that damages it works on a copy.
"""

from __future__ import annotations

import csv
import json
import shutil
from pathlib import Path

import pytest
import yaml
from helpers import BOTTLE, assert_one_line_error

from gcm_pipeline.study import Study

#: A small bottle: 2 rings of 9 candidates, 45 grasps.
SMALL = [
    "candidates.count=18",
    "manifold.max_edge_length=0.15",
    "densify.subdivisions=2",
    "approach.steps=4",
    "publish.html=false",
    "publish.plots=false",
]


@pytest.fixture(scope="module")
def study_dir(tmp_path_factory) -> Path:
    """A finished study of 6 placements (x and yaw swept), with best/."""
    folder = tmp_path_factory.mktemp("study")
    path = folder / "study.yaml"
    data = {
        "base": str(BOTTLE),
        "set": SMALL,
        "sweep": {"object_pose": {"x": [0.35, 0.45, 0.55], "yaw_deg": [0, 20]}},
    }
    path.write_text(yaml.safe_dump(data, sort_keys=False))
    out = folder / "out"
    Study.from_yaml(path).run(out, engine="inline", progress=False)
    return out


@pytest.fixture
def copy(study_dir, tmp_path) -> Path:
    """A copy of the shared study directory, to damage."""
    out = tmp_path / "study"
    shutil.copytree(study_dir, out)
    return out


def test_show_prints_the_study_summary_and_where_best_is(cli, study_dir):
    code, text, err = cli("show", study_dir, "--top", "3")
    assert code == 0, err
    summary = json.loads((study_dir / "summary.json").read_text())
    best = summary["best"]
    lines = text.splitlines()
    assert lines[0].startswith(f"study {study_dir} (from ")
    assert "  placements  6 of 6 finished (0 failed), 1 round(s); complete" in lines
    with open(study_dir / "placements.csv") as f:
        coverages = sorted(float(row["coverage"]) for row in csv.DictReader(f))
    median = 0.5 * (coverages[2] + coverages[3])
    assert (
        f"  coverage    best {coverages[-1]:.3f}, median {median:.3f} (over 6 placements)" in lines
    )
    # the best placement: its swept pose only (x and yaw), its coverage
    yaw = f"{best['object_yaw_deg']:g}"
    assert (
        f"  best        #{best['id']} cylinder: coverage {best['coverage']:.3f} "
        f"({best['reachable']} / {best['densified']} reachable); "
        f"object x {best['object_x']:g}, yaw {yaw}°"
    ) in lines
    assert f"  reproduce   {best['command']}" in lines
    assert "  engine      inline, 1 worker(s); " in text
    assert "  timings [s] startup " in text and "best_run" in text
    assert "top 3 placements by coverage:" in lines
    top = lines[lines.index("top 3 placements by coverage:") + 1]
    assert top.startswith(f"  #{best['id']} ")
    assert f"best placement's run: {study_dir / 'best'}" in lines
    assert (
        f"  look at it  gcm show {study_dir / 'best'}  (also gcm view, query, export on it)"
        in lines
    )
    assert f"coverage map: {study_dir / 'coverage.png'}" in lines
    assert f"study report: {(study_dir / 'study.html').as_uri()}" in lines
    # and the run it points to is one gcm show reads
    code, text, err = cli("show", study_dir / "best", "--top", "1")
    assert code == 0 and text.startswith(f"run {study_dir / 'best'}"), err


def test_query_on_a_study_directory_answers_on_best_with_a_note(cli, study_dir):
    pose = ["0.35", "0", "0.1", "1", "0", "0", "0"]
    code, text, err = cli("query", study_dir, "--pose", *pose, "--json")
    assert code == 0, err
    assert err == (
        f"note: {study_dir} is a study directory; gcm query answers on its best "
        f"placement's run {study_dir / 'best'}\n"
    )
    on_best = cli("query", study_dir / "best", "--pose", *pose, "--json")
    assert on_best[0] == 0 and on_best[2] == ""
    assert json.loads(text) == json.loads(on_best[1])  # the same answer, stdout stays JSON


@pytest.mark.parametrize(
    "argv", [["export", "--format", "npz"], ["view", "--no-wait"]], ids=["export", "view"]
)
def test_export_and_view_name_the_study_directory_and_best(cli, study_dir, argv):
    code, _, err = cli(argv[0], study_dir, *argv[1:])
    assert_one_line_error(
        code,
        err,
        f"not a run directory: {study_dir}",
        f"it is a study directory: its best placement's run is {study_dir / 'best'}",
        f"gcm show {study_dir} summarises the study",
    )
    assert not (study_dir / "grasps.npz").exists()


def test_without_best_show_says_it_is_missing_and_the_others_say_so(cli, copy):
    shutil.rmtree(copy / "best")
    code, text, err = cli("show", copy)
    assert code == 0, err
    summary = json.loads((copy / "summary.json").read_text())
    source = summary["study"]["source"]
    assert (
        f"best placement's run: missing ({copy / 'best'}): the study did not finish or ran "
        f"with --no-best; gcm study {source} --out {copy} writes it\n"
    ) in text
    for argv in (
        ["query", copy, "--pose", "0.35", "0", "0.1", "1", "0", "0", "0"],
        ["export", copy, "--format", "npz"],
    ):
        code, _, err = cli(*argv)
        assert_one_line_error(code, err, f"not a run directory: {copy}", "has no best/")


def test_an_unfinished_study_says_so_and_how_to_finish_it(cli, copy):
    path = copy / "summary.json"
    summary = json.loads(path.read_text())
    summary.update(complete=False)
    summary["counts"].update(placements=9)
    path.write_text(json.dumps(summary))
    shutil.rmtree(copy / "best")
    code, text, err = cli("show", copy)
    assert code == 0, err
    assert (
        "  placements  6 of 9 finished (0 failed), 1 round(s); not complete: run the study "
        "again to finish it\n"
    ) in text
    assert f"gcm study {summary['study']['source']} --out {copy} writes it" in text


def test_without_placements_show_is_one_line(cli, copy):
    shutil.rmtree(copy / "placements")
    code, _, err = cli("show", copy)
    assert_one_line_error(code, err, f"{copy}: study directory without placements/")


def test_without_summary_show_is_one_line(cli, copy):
    (copy / "summary.json").unlink()
    code, _, err = cli("show", copy)
    assert_one_line_error(code, err, f"{copy / 'summary.json'} is missing")


@pytest.mark.parametrize(
    ("change", "fragment"),
    [
        (lambda s: s["counts"].update(finished="six"), "counts.finished"),
        (lambda s: s["counts"].update(finished=60), "finished 60 > placements 6"),
        (lambda s: s["best"].update(coverage=1.5), "best.coverage"),
        (lambda s: s["best"].pop("command"), "best.command"),
        (lambda s: s["engine"].update(workers=-1), "engine.workers"),
        (lambda s: s.update(timings_s={"total": "slow"}), "timings_s.total"),
        (lambda s: s.pop("complete"), "complete"),
        (lambda s: s["best"].update(id=999), "best placement #999 is not in placements.csv"),
        (lambda s: s["best"].update(coverage=0.0123), "has coverage 0.0123 but "),
    ],
    ids=[
        *("count-type", "count-sum", "coverage", "command", "workers", "timings", "complete"),
        *("best-id", "best-coverage"),
    ],
)
def test_a_tampered_summary_is_one_line_naming_the_key(cli, copy, change, fragment):
    path = copy / "summary.json"
    summary = json.loads(path.read_text())
    change(summary)
    path.write_text(json.dumps(summary))
    code, _, err = cli("show", copy)
    assert_one_line_error(code, err, f"{path}: ", fragment)


@pytest.mark.parametrize(
    ("text", "fragment"),
    [("{not json", "not JSON"), ("[1, 2]", "expected a mapping")],
    ids=["not-json", "list"],
)
def test_a_summary_that_is_not_a_studys_is_one_line(cli, copy, text, fragment):
    (copy / "summary.json").write_text(text)
    code, _, err = cli("show", copy)
    assert_one_line_error(code, err, str(copy / "summary.json"), fragment)


@pytest.mark.parametrize(
    ("key", "value", "fragment"),
    [
        ("coverage", "lots", "coverage is not a number: 'lots'"),
        ("reachable", "1e999", "reachable is not a whole number >= 0: '1e999'"),
        ("densified", "-3", "densified is not a whole number >= 0: '-3'"),
        ("reachable", "2.5", "reachable is not a whole number >= 0: '2.5'"),
    ],
    ids=["coverage-text", "reachable-inf", "densified-negative", "reachable-fraction"],
)
def test_a_tampered_placements_csv_is_one_line_naming_the_line(cli, copy, key, value, fragment):
    path = copy / "placements.csv"
    with open(path) as f:
        rows = list(csv.DictReader(f))
    rows[1][key] = value
    with open(path, "w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=list(rows[0]), lineterminator="\n")
        writer.writeheader()
        writer.writerows(rows)
    code, _, err = cli("show", copy)
    assert_one_line_error(code, err, f"{path}: line 3: {fragment}")


def test_a_folder_with_a_foreign_marker_is_not_a_study(cli, tmp_path):
    (tmp_path / "x").mkdir()
    (tmp_path / "x" / ".gcm.json").write_text('{"kind": "study"}')  # not gcm_pipeline's marker
    code, _, err = cli("show", tmp_path / "x")
    assert_one_line_error(code, err, "not a run directory")


def test_show_on_a_relative_study_path_prints_the_reports_address(cli, copy, monkeypatch):
    code, _, err = cli("plot", copy)
    assert code == 0, err
    monkeypatch.chdir(copy.parent)
    code, text, err = cli("show", copy.name)
    assert code == 0, err
    assert f"study report: {(copy / 'study.html').resolve().as_uri()}" in text.splitlines()
