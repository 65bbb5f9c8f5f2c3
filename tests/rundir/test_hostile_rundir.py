"""Tampered run directories: ``read_run``, ``gcm show`` and ``gcm plot`` say one line.

A good run (``flat_run``) is copied and one file changed (``summary.json``, ``manifold.npz``,
``grasps.csv``); the reader names the file and what is wrong with it.
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest
from helpers import ROOT, assert_one_line_error

from gcm_pipeline.errors import InputError
from gcm_pipeline.rundir import run as run_files


def _edit_summary(change):
    def edit(d: Path) -> None:
        s = json.loads((d / "summary.json").read_text())
        change(s)
        (d / "summary.json").write_text(json.dumps(s))

    return edit


def _edit_npz(change):
    def edit(d: Path) -> None:
        with np.load(d / "manifold.npz") as z:
            arrays = dict(z)
        change(arrays)
        np.savez(d / "manifold.npz", **arrays)

    return edit


def _edit_csv(column: str, value: str, row: int = 1):
    def edit(d: Path) -> None:
        lines = (d / "grasps.csv").read_text().splitlines()
        head = lines[0].split(",")
        cells = lines[row].split(",")
        cells[head.index(column)] = value
        lines[row] = ",".join(cells)
        (d / "grasps.csv").write_text("\n".join(lines) + "\n")

    return edit


TAMPERED = {
    "summary.json not an object": (
        lambda d: (d / "summary.json").write_text("[1, 2]"),
        "expected a JSON object",
    ),
    "summary.json not JSON": (lambda d: (d / "summary.json").write_text("{"), "not valid JSON"),
    "summary.json nested deeply": (
        lambda d: (d / "summary.json").write_text("[" * 100_000 + "]" * 100_000),
        "summary.json",
    ),
    "counts a list": (_edit_summary(lambda s: s.update(counts=[1, 2])), "'counts' must be"),
    "a count a string": (
        _edit_summary(lambda s: s["counts"].update(reachable="x")),
        "counts.reachable must be a count",
    ),
    "ranking a string": (_edit_summary(lambda s: s.update(ranking="x")), "'ranking' must be"),
    "corrupt manifold.npz": (
        lambda d: (d / "manifold.npz").write_bytes(b"PK\x03\x04garbage"),
        "not a readable .npz",
    ),
    "triangle ids out of range": (
        _edit_npz(lambda a: a.update(triangles=np.array([[0, 1, 99]]))),
        "'triangles' has vertex ids outside",
    ),
    "chart of the wrong shape": (
        _edit_npz(lambda a: a.update(chart=np.zeros((2, 5)))),
        "'chart' must be (V, 2)",
    ),
    "vertex ids out of range": (
        _edit_npz(lambda a: a.update(vertex_ids=np.array([0, 1, 10**6]))),
        "'vertex_ids' names rows outside",
    ),
    "qw=5": (_edit_csv("qw", "5"), "not a pose"),
    "x=inf": (_edit_csv("x", "inf"), "not a pose"),
    "v1 out of range": (_edit_csv("v1", "99999", row=60), "not a row of this file"),
    "reachable=maybe": (_edit_csv("reachable", "maybe"), "not true or false"),
    "rank=-3": (_edit_csv("rank", "-3"), "negative"),
    # row 1 is the best-ranked grasp, reachable: its joint solution must be there
    "q1=inf in a reachable row": (_edit_csv("q1", "inf"), "column 'q1': a reachable grasp needs"),
    "q3 empty in a reachable row": (_edit_csv("q3", ""), "column 'q3': a reachable grasp needs"),
}


@pytest.mark.parametrize("case", sorted(TAMPERED))
def test_tampered_run_directories(cli, tmp_path, flat_run, case):
    tamper, fragment = TAMPERED[case]
    d = tmp_path / "run"
    shutil.copytree(flat_run, d)
    tamper(d)
    with pytest.raises(InputError, match=None) as info:
        run_files.read_run(d)
    assert fragment in str(info.value), str(info.value)
    code, out, err = cli("show", d)
    assert_one_line_error(code, err, fragment)


def test_plot_on_a_tampered_run_is_one_line(cli, tmp_path, flat_run):
    d = tmp_path / "run"
    shutil.copytree(flat_run, d)
    TAMPERED["triangle ids out of range"][0](d)
    code, out, err = cli("plot", d)
    assert_one_line_error(code, err, "'triangles' has vertex ids outside")
    assert not list(d.glob("*.png"))


def test_show_on_a_file_names_its_folder(cli):
    code, _, err = cli("show", ROOT / "README.md")
    assert_one_line_error(code, err, "README.md is a file (give its folder)")


def test_an_npz_member_name_cut_at_a_nul_byte_is_one_line(cli, tmp_path, flat_run):
    """zipfile cuts a member name at a NUL byte; a name cut to nothing failed ``is_dir()``
    with an IndexError (found by the fuzz test): ``gcm show`` says one line instead."""
    run = tmp_path / "run"
    shutil.copytree(flat_run, run)
    data = bytearray((run / "manifold.npz").read_bytes())
    entry = data.find(b"PK\x01\x02")  # the first central directory entry
    data[entry + 46] = 0  # the first byte of its file name
    (run / "manifold.npz").write_bytes(bytes(data))
    code, _, err = cli("show", run)
    assert_one_line_error(code, err)
    assert "manifold.npz: not a readable .npz archive" in err
