"""``grasps.csv`` of a run: a grasp file's extra columns carried, ``v1``-``v3`` its rows."""

from __future__ import annotations

import csv

import pytest
from helpers import FLAT, QUICK


def test_extra_csv_columns_are_carried_to_grasps_csv(cli, tmp_path):
    cfg = tmp_path / "cfg.yaml"
    (tmp_path / "g.csv").write_text(
        "ID,x,y,z,qw,qx,qy,qz,score,Grasp Label,success\n"
        "17,0.45,0,0.25,0,1,0,0,0.9,a,1\n"
        "23,0.45,0.1,0.25,0,1,0,0,0.7,b,1\n"
        "42,0.55,0,0.25,0,1,0,0,0.2,c,0\n"  # every row needs a score: an empty one is NaN
        "51,0.55,0.1,0.25,0,1,0,0,0.5,d,1\n"
    )
    cfg.write_text(
        "candidates: {source: file, path: g.csv, success_only: true}\n"
        "densify: {subdivisions: 2}\npublish: {html: false, plots: false}\n"
    )
    code, _, err = cli("run", cfg, "--out", tmp_path / "run", "-q")
    assert code == 0, err
    with (tmp_path / "run" / "grasps.csv").open() as fh:
        rows = list(csv.DictReader(fh))
    cand = {int(r["id"]): r for r in rows if r["origin"] == "candidate"}
    assert sorted(cand) == [17, 23, 51]  # row 42 failed success_only
    assert cand[23]["score"] == "0.7" and cand[23]["grasp_label"] == "b"
    assert cand[51]["source_id"] == "3"  # its row in the input file (0-based)
    interp = [r for r in rows if r["origin"] == "interpolated"]
    assert interp and all(r["id"] == "-1" and r["grasp_label"] == "" for r in interp)
    # score is blended inside a triangle: between its vertices' scores
    scores = [float(r["score"]) for r in interp]
    assert min(scores) >= 0.5 - 1e-12 and max(scores) <= 0.9 + 1e-12


def test_v1_v3_are_rows_of_grasps_csv(cli, tmp_path):
    code, _, err = cli("run", FLAT, "--out", tmp_path / "run", "-q", *QUICK)
    assert code == 0, err
    with (tmp_path / "run" / "grasps.csv").open() as fh:
        rows = list(csv.DictReader(fh))
    assert rows[0]["rank"] == "1"  # ranked rows first: ids cannot be table order
    for r in rows:
        if r["origin"] != "interpolated":
            continue
        w = [float(r[f"w{k}"]) for k in (1, 2, 3)]
        corners = [rows[int(r[f"v{k}"])] for k in (1, 2, 3)]
        assert all(c["origin"] == "candidate" for c in corners)
        if max(w) == 1.0:  # a lattice point on a vertex is that vertex
            c = corners[w.index(1.0)]
            assert [float(c[k]) for k in "xyz"] == pytest.approx([float(r[k]) for k in "xyz"])
