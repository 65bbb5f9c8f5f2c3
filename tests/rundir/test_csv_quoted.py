"""``grasps.csv`` with quoted text cells: split by Arrow only when Python's ``csv`` reads the same.

The reference is the Python reader (``_table(_Cells(...))``): Arrow's split
must give the same table, and any file Arrow cannot vouch for must end in
the Python reader's table or its one-line error.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from helpers import assert_same_table, python_read_grasps, same_read_outcome

from gcm_pipeline.errors import InputError
from gcm_pipeline.rundir import csv_text
from gcm_pipeline.rundir import grasps_csv as G
from gcm_pipeline.table import GraspTable

HEADER = "rank,origin,x,y,z,qw,qx,qy,qz,reachable,q1,label\n"
ROW = "1,candidate,0.5,0,0.25,1,0,0,0,true,0.5,"

#: Text cells that need quotes, and some that do not.
TEXTS = [
    "a, b",
    'say "hi"',
    "two\nlines",
    'x,"y"\nz',
    '"',
    '""',
    ",",
    "\n",
    "\n\n",
    " lead, trail ",
    "caf\u00e9, \u00fcber",
    "plain",
    "",
    "a\tb",
]


def _table(labels: list[str], seed: int = 0) -> GraspTable:
    n = len(labels)
    rng = np.random.default_rng(seed)
    q = rng.normal(size=(n, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    dq = np.zeros((n, 8))
    dq[:, :4] = q
    return GraspTable(
        {
            "dq": dq,
            "rank": np.arange(n),
            "origin": np.full(n, "candidate"),
            "triangle": np.full(n, -1),
            "vertices": np.full((n, 3), -1),
            "reachable": np.zeros(n, dtype=bool),
            "reason": np.array(labels[::-1] or [], dtype=str),
            "label": np.array(labels, dtype=str),
            "score": rng.random(n),
        }
    )


def test_a_written_file_with_quoted_text_is_split_by_arrow_as_python_reads_it(tmp_path):
    path = tmp_path / "grasps.csv"
    G.write_grasps_csv(_table(TEXTS), path)
    assert b'"' in path.read_bytes()
    split = csv_text.read_text_columns(path)
    assert split is not None, "the Arrow reader refused a file the writer quoted"
    assert_same_table(G._table(csv_text.ArrowCells(path, *split))[0], python_read_grasps(path))
    assert_same_table(G.read_grasps_csv(path), python_read_grasps(path))


@pytest.mark.parametrize("seed", range(6))
def test_random_quoted_text_reads_the_same_through_arrow(tmp_path, seed):
    rng = np.random.default_rng(seed)
    alphabet = np.array(list('ab ,"\n\u00e9'))
    labels = ["".join(rng.choice(alphabet, size=rng.integers(0, 9))) for _ in range(300)]
    path = tmp_path / "grasps.csv"
    G.write_grasps_csv(_table(labels, seed), path)
    split = csv_text.read_text_columns(path)
    assert split is not None
    got = G._table(csv_text.ArrowCells(path, *split))[0]
    assert_same_table(got, python_read_grasps(path))
    assert got["label"].tolist() == python_read_grasps(path)["label"].tolist()


@pytest.mark.parametrize(
    "body",
    [
        ROW + '"7"\n',  # quoted without need: Python reads 7, the writer would not quote it
        ROW + 'a"b\n',  # a quote inside an unquoted cell: Python keeps it
        ROW + '"a"b\n',  # text after the closing quote: Python appends it
        ROW + '"a" \n',  # a space after the closing quote
        ROW + '"abc\n',  # never closed
        ROW + '"a\n' + ROW + 'b"\n',  # closed on a later line: one cell of two lines
        ROW + '""\n',  # an empty quoted cell
        ROW + 'a""b\n',  # doubled quotes in an unquoted cell
        ROW + '"a,b",c\n',  # a field more, behind a quoted comma
        '1,candidate,"0.5",0,0.25,1,0,0,0,true,0.5,"a,b"\n',  # a quoted number
        ROW + '"a,b"\n\n' + ROW + '"c\nd"\n',  # a blank line between quoted rows
        ROW + '"a,b"\n' + ",,,,,,,,,,,\n",  # a blank row: Python skips it
        ROW + '"a,b"',  # no final newline
        ROW + '"' + "x," * 200 + '"\n',  # a quoted cell past the longest allowed
        ROW + '"a,b"\n' + ROW.replace("1,0,0,0", "2,0,0,0") + '"c"""\n',  # not a unit quaternion
    ],
)
def test_hostile_quoted_cells_same_table_or_same_error(tmp_path, body):
    path = tmp_path / "grasps.csv"
    path.write_text(HEADER + body, encoding="utf-8")
    _same_outcome(path)


@pytest.mark.parametrize(
    "data",
    [
        b"\xef\xbb\xbf" + (HEADER + ROW + '"a,\n""b"""\n').encode(),  # byte order mark
        (HEADER.replace("label", '"la,bel"') + ROW + '"a,b"\n').encode(),  # a quoted header
        (HEADER + ROW + '"a,b"\r\n').encode(),  # CRLF
        (HEADER + ROW + '"a\x00b"\n').encode(),  # NUL
        (HEADER + ROW + '"a,b\xff"\n').encode(),  # not UTF-8
    ],
)
def test_hostile_quoted_files_same_table_or_same_error(tmp_path, data):
    path = tmp_path / "grasps.csv"
    path.write_bytes(data)
    _same_outcome(path)


def test_quoting_the_writer_would_not_write_is_left_to_python(tmp_path):
    path = tmp_path / "grasps.csv"
    path.write_text(HEADER + ROW + '"7"\n' + ROW + '"a,b"\n', encoding="utf-8")
    assert csv_text.read_text_columns(path) is None
    assert G.read_grasps_csv(path)["label"].tolist() == ["7", "a,b"]


def _same_outcome(path: Path) -> None:
    """The Python reader's outcome; and what Arrow splits, it splits as Python does."""
    same_read_outcome(path)
    split = csv_text.read_text_columns(path)
    if split is None:
        return
    try:
        expected = python_read_grasps(path)
        got = G._table(csv_text.ArrowCells(path, *split))[0]
    except (InputError, csv_text.Fallback):  # a fault: the Python reader's error, checked above
        return
    assert_same_table(got, expected)
