"""``grasps.csv`` through Arrow: the same bytes as the Python writer, the same table and errors.

The reference is the Python code the Arrow path replaced: :func:`python_write`
(the former writer, kept here) and the module's Python reader
(``_table(_Cells(...))``, which stays the fallback for files Arrow does not
read and the source of every error message).
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
from helpers import BOTTLE, assert_same_table, python_read_grasps, same_read_outcome

from gcm_pipeline.config import load_config
from gcm_pipeline.errors import InputError
from gcm_pipeline.pipeline import Pipeline
from gcm_pipeline.rundir import csv_text
from gcm_pipeline.rundir import grasps_csv as G
from gcm_pipeline.table import GraspTable


def _python_cells(values: np.ndarray, dtype: str) -> list[str]:
    """The former writer's cells of a column (``repr`` floats, NaN empty)."""
    if dtype == "bool" or values.dtype.kind == "b":
        return ["true" if b else "false" for b in np.asarray(values, dtype=bool).tolist()]
    if dtype == "int" or values.dtype.kind in "iu":
        return [str(v) for v in np.asarray(values, dtype=np.int64).tolist()]
    if dtype == "str" or values.dtype.kind in "US":
        return [G._quote(str(s)) for s in np.asarray(values).tolist()]
    return G.format_floats(values)


def python_write(grasps: GraspTable, path: Path) -> None:
    """The Python writer ``write_grasps_csv`` was before the Arrow path (rows joined in Python)."""
    order = G._row_order(grasps)
    g = grasps.take(order)
    n = len(g)
    csv_row = np.empty(n, dtype=np.int64)
    csv_row[order] = np.arange(n)
    header: list[str] = []
    cols: list[list[str]] = []
    for name, spec in G._LEADING.items():
        values = G._leading_values(g, name, csv_row)
        cells = list(spec.csv)
        if G.PER_JOINT in spec.csv[0]:
            width = 0 if values is None else values.shape[1]
            cells = [spec.csv[0].format(j=j + 1) for j in range(width)]
        header += cells
        for k in range(len(cells)):
            cols.append([""] * n if values is None else _python_cells(values[:, k], spec.dtype))
    for name in G._extra_columns(g):
        header.append(name)
        cols.append(_python_cells(np.asarray(g[name]), ""))
    with Path(path).open("w", newline="", encoding="utf-8") as fh:
        fh.write(",".join(header) + "\n")
        fh.writelines(",".join(row) + "\n" for row in zip(*cols, strict=True))


def arrow_read(path: Path) -> GraspTable:
    """The Arrow reader on its own (fails the test if it would fall back)."""
    split = csv_text.read_text_columns(path)
    assert split is not None, "the Arrow reader refused the file"
    return G._table(csv_text.ArrowCells(path, *split))[0]


def test_the_arrow_float_text_is_in_use():
    assert csv_text.arrow_floats_ok(G.format_floats)


def test_arrow_float_layout_is_repr():
    import pyarrow as pa
    import pyarrow.compute as pc

    x = np.concatenate([np.asarray(_edge_table()["metric"]), np.logspace(-330, 308, 20_000)])
    with np.errstate(all="ignore"):  # inf and NaN among them
        x = np.concatenate([x, -x, np.round(x * 1e6) / 1e6, np.floor(x)])
    assert csv_text._arrow_floats(x, G.format_floats, pa, pc).to_pylist() == G.format_floats(x)


def test_real_run_byte_identical_and_read_back_bit_identical(tmp_path):
    cfg = load_config(BOTTLE, ("publish.html=false", "publish.plots=false"))
    grasps = Pipeline(cfg).run(progress=False, write=False).grasps
    assert len(grasps) > 1000 and "q" in grasps and "clearance" in grasps
    new, old = tmp_path / "new.csv", tmp_path / "old.csv"
    G.write_grasps_csv(grasps, new)
    python_write(grasps, old)
    assert new.read_bytes() == old.read_bytes()
    assert_same_table(arrow_read(new), python_read_grasps(new))
    table, pose = G.read_grasps_csv_pose(new)
    assert_same_table(table, python_read_grasps(new))
    cells = [line.split(",")[9:16] for line in new.read_text().splitlines()[1:]]
    assert pose.tolist() == [[float(c) for c in row] for row in cells]


def _edge_table(n_random: int = 50_000) -> GraspTable:
    rng = np.random.default_rng(7)
    specials = [math.nan, math.inf, -math.inf, -0.0, 0.0, 1e-300, -1e-300, 5e-324, -5e-324]
    specials += [2.2250738585072014e-308, 2.225073858507201e-308, 1e-310, 1.7976931348623157e308]
    specials += [1e16, 1e15, 9999999999999998.0, 2.0**53, 2.0**53 + 2, 1e22, 1.5e10, 1e-4]
    specials += [9.999999999999999e-05, 1e-5, 3.2e-9, 0.1, 1 / 3, 123.0, -7.0, 1e100, 0.5]
    bits = rng.integers(-(2**63), 2**63 - 1, size=n_random, dtype=np.int64).view(np.float64)
    scaled = rng.random(n_random) * 10.0 ** rng.integers(-12, 18, size=n_random)
    floats = np.concatenate([specials, bits, -scaled])
    n = len(floats)
    angles = rng.normal(size=(n, 3))
    half = np.linalg.norm(angles, axis=1) / 2
    axis = angles / np.linalg.norm(angles, axis=1)[:, None]
    quat = np.column_stack([np.cos(half), axis * np.sin(half)[:, None]])
    dq = np.zeros((n, 8))
    dq[:, :4] = quat
    dq[:, 4:] = rng.normal(size=(n, 4)) * 0.1
    ints = rng.integers(-(2**63), 2**63 - 1, size=n, dtype=np.int64)
    ints[:4] = [np.iinfo(np.int64).min, np.iinfo(np.int64).max, 0, -1]
    q = rng.permutation(floats.repeat(2)).reshape(n, 2)
    with np.errstate(invalid="ignore", over="ignore"):
        single = floats.astype(np.float32)
    words = np.array(["", "plain", 'qu"ote', "com,ma", "new\nline", "cr\rlf", "√ünïcødé 🤖"])
    return GraspTable(
        {
            "dq": dq,
            "rank": np.where(rng.random(n) < 0.5, rng.permutation(n) + 1, 0),
            "origin": rng.choice(["candidate", "interpolated"], size=n),
            "triangle": rng.integers(-1, 1000, size=n),
            "vertices": rng.integers(-1, n, size=(n, 3)),
            "weights": rng.permutation(floats.repeat(3)).reshape(n, 3),
            "reachable": (rng.random(n) < 0.5) & np.isfinite(q).all(axis=1),
            "reason": rng.choice(["", "no_ik", "approach"], size=n),
            "pos_err": rng.permutation(floats),
            "q": q,
            "metric": floats,
            "big": ints,
            "unsigned": np.full(n, 2**64 - 5, dtype=np.uint64),
            "single": single,
            "flag": rng.random(n) < 0.3,
            "label": rng.choice(words, size=n),
            "raw": rng.choice(np.array([b"ab", b"c,d"]), size=n),
        }
    )


def test_edge_values_byte_identical(tmp_path):
    grasps = _edge_table()
    new, old = tmp_path / "new.csv", tmp_path / "old.csv"
    G.write_grasps_csv(grasps, new)
    python_write(grasps, old)
    assert new.read_bytes() == old.read_bytes()


def test_edge_values_without_text_are_read_by_arrow_bit_for_bit(tmp_path):
    grasps = _edge_table()
    plain = GraspTable({k: grasps[k] for k in grasps.columns if k not in ("label", "raw")})
    path = tmp_path / "g.csv"
    G.write_grasps_csv(plain, path)
    table = arrow_read(path)
    assert_same_table(table, python_read_grasps(path))
    assert table["metric"].dtype == float and np.isinf(table["metric"]).sum() == 2
    assert np.signbit(table["metric"][np.asarray(table["metric"]) == 0]).any()  # -0.0 kept


def test_text_with_a_nul_is_written_whole(tmp_path):
    # Arrow's conversion of a numpy <U array ends a string at its first NUL
    grasps = _edge_table(n_random=0)
    words = np.array(["a\x00b", "\x00x", "c"])
    grasps = grasps.with_columns(label=words[np.arange(len(grasps)) % 3])
    new, old = tmp_path / "new.csv", tmp_path / "old.csv"
    G.write_grasps_csv(grasps, new)
    python_write(grasps, old)
    assert b"a\x00b" in new.read_bytes() and new.read_bytes() == old.read_bytes()


@pytest.mark.parametrize("n", [0, 1, csv_text.CHUNK_ROWS + 3])
def test_sizes_byte_identical(tmp_path, n):
    grasps = _edge_table(n_random=0)
    rows = np.arange(n) % len(grasps)
    grasps = grasps.take(rows).with_columns(rank=np.arange(n))
    new, old = tmp_path / "new.csv", tmp_path / "old.csv"
    G.write_grasps_csv(grasps, new)
    python_write(grasps, old)
    assert new.read_bytes() == old.read_bytes()


def test_text_with_quotes_is_read_by_python_the_same(tmp_path):
    grasps = _edge_table(n_random=100)
    path = tmp_path / "g.csv"
    G.write_grasps_csv(grasps, path)
    assert csv_text.read_text_columns(path) is None  # quotes: the Python reader
    table = G.read_grasps_csv(path)
    assert_same_table(table, python_read_grasps(path))
    assert "new\nline" in set(table["label"].tolist())


HEADER = "rank,origin,x,y,z,qw,qx,qy,qz,reachable,q1,extra\n"
GOOD = "1,candidate,0.5,0,0.25,1,0,0,0,true,0.5,7\n"


@pytest.mark.parametrize(
    "body",
    [
        GOOD + "2,candidate,nan,0,0.25,1,0,0,0,true,0.5,7\n",  # nan in a pose cell
        GOOD + "2,candidate,0.5,0,0.25,1,0,0,0,true,nan(1),7\n",  # Arrow's NaN, not Python's
        GOOD + "2,candidate,0.5,0,0.25,1,0,0,0,true,x,7\n",  # text in a float column
        GOOD + "2,candidate,0.5,0,0.25,1,0,0,0,true,1_0,7\n",  # Python's float, not Arrow's
        GOOD + "2,candidate, 0.5,0,0.25,1,0,0,0,true,0.5,7\n",  # space: Python's float
        GOOD + "+2,candidate,0.5,0,0.25,1,0,0,0,true,0.5,7\n",  # not an integer for Python
        GOOD + "1234567890123456789,candidate,0.5,0,0.25,1,0,0,0,true,0.5,7\n",  # 19 digits
        GOOD + "2,candidate,0.5,0,0.25,1,0,0,0,True,0.5,7\n",  # not true or false
        GOOD + "2,candidate,0.5,0,0.25,1,0,0,0,,0.5,7\n",  # empty switch
        GOOD + "2,candidate,0.5,0,0.25,1,0,0,0,true,,7\n",  # reachable without q
        GOOD + "-1,candidate,0.5,0,0.25,1,0,0,0,true,0.5,7\n",  # negative rank
        GOOD + "2,bogus,0.5,0,0.25,1,0,0,0,true,0.5,7\n",  # odd origin
        GOOD + "2,candidate,0.5,0,0.25,2,0,0,0,true,0.5,7\n",  # not a unit quaternion
        GOOD + "2,candidate,0.5,0,0.25,1,0,0,0,true,0.5\n",  # a field short
        GOOD + "2,candidate,0.5,0,0.25,1,0,0,0,true,0.5,7,8\n",  # a field more
        GOOD + ",,,,,,,,,,,\n" + GOOD,  # a blank row: Python skips it
        GOOD + "\n\n" + GOOD,  # blank lines
        GOOD + "2,candidate,0.5,0,0.25,1,0,0,0,true,0.5," + "9" * 300 + "\n",  # a long cell
        GOOD + "2,candidate,0.5,0,0.25,1,0,0,0,true,0.5,nan\n",  # nan in a further column
        GOOD + "2,candidate,0.5,0,0.25,1,0,0,0,true,0.5,1e400\n",  # inf in a further column
        GOOD + "2,candidate,0.5,0,0.25,1,0,0,0,true,0.5,\n",  # empty further cell: float
        GOOD + "2,candidate,0.5,0,0.25,1,0,0,0,true,0.5,word\n",  # text further column
        GOOD + "2,candidate,0.5,0,0.25,1,0,0,0,true,0.5,false\n",  # int and bool mixed
        GOOD.replace("\n", "\r\n") * 2,  # CRLF
        GOOD + "2,candidate,0.5,0,0.25,1,0,0,0,true,0.5,a\x00b\n",  # NUL
        GOOD + '2,candidate,0.5,0,0.25,1,0,0,0,true,0.5,"7"\n',  # quoted
        GOOD.rstrip("\n"),  # no final newline
        "",  # header only
    ],
)
def test_hostile_cells_same_table_or_same_error(tmp_path, body):
    path = tmp_path / "grasps.csv"
    path.write_text(HEADER + body, encoding="utf-8")
    same_read_outcome(path)


@pytest.mark.parametrize(
    "data",
    [
        b"\xef\xbb\xbf" + (HEADER + GOOD).encode(),  # byte order mark
        (HEADER + GOOD).encode()[:-20],  # truncated inside a row
        (HEADER + GOOD).encode() + b"2,candidate,0.5,0,0.25,1,0,0,0,true,0.5,\xff\n",  # not UTF-8
        ("rank,x,y,z,qw,qx,qy\n" + "1,0.5,0,0.25,1,0,0\n").encode(),  # qz missing
        ("rank,rank,x,y,z,qw,qx,qy,qz\n" + "1,1,0.5,0,0.25,1,0,0,0\n").encode(),  # named twice
        b"",  # empty file
        b"\n\n",  # blank lines only
        ("\n" + HEADER + GOOD).encode(),  # a blank line before the header
        ("r\u00e9ach," + HEADER + "x," + GOOD).encode(),  # unicode header cell
    ],
)
def test_hostile_files_same_table_or_same_error(tmp_path, data):
    path = tmp_path / "grasps.csv"
    path.write_bytes(data)
    same_read_outcome(path)


def test_missing_file_same_error(tmp_path):
    with pytest.raises(InputError, match="not a run directory: .* is missing"):
        G.read_grasps_csv(tmp_path / "grasps.csv")
