"""Run directory: grasps.csv contract and round trip, manifold.npz, atomic writes."""

from __future__ import annotations

import csv
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from gcm_pipeline.errors import InputError, OutputError
from gcm_pipeline.geometry.dualquat import dq_from_matrix, dq_to_matrix
from gcm_pipeline.manifold.build import Manifold
from gcm_pipeline.rundir import arrays, grasps_csv, transaction
from gcm_pipeline.rundir import run as run_files
from gcm_pipeline.table import CANDIDATE_COLUMNS, COLUMNS, GraspTable

N, NC, NQ = 9, 3, 7


def _table(seed=0) -> GraspTable:
    rng = np.random.default_rng(seed)
    t = np.zeros((N, 4, 4))
    t[:, :3, :3] = Rotation.random(N, random_state=seed).as_matrix()
    t[:, :3, 3] = rng.uniform(-1, 1, (N, 3))
    t[:, 3, 3] = 1
    dq = dq_from_matrix(t)
    dq[1] *= -1  # the other cover: same pose
    reachable = np.array([1, 0, 1, 1, 0, 1, 1, 0, 1], dtype=bool)
    manip = np.where(reachable, rng.uniform(0.01, 0.1, N), np.nan)
    rank = np.zeros(N, dtype=np.int64)
    rows = np.flatnonzero(reachable)
    rank[rows[np.argsort(-manip[rows])]] = np.arange(1, rows.size + 1)
    vertices = np.full((N, 3), -1)
    vertices[NC:] = [0, 1, 2]
    weights = np.full((N, 3), np.nan)
    weights[NC:] = rng.dirichlet([1, 1, 1], N - NC)
    q = np.where(reachable[:, None], rng.uniform(-2, 2, (N, NQ)), np.nan)
    return GraspTable(
        {
            "dq": dq,
            "origin": np.array(["candidate"] * NC + ["interpolated"] * (N - NC)),
            "triangle": np.array([-1] * NC + [0] * (N - NC)),
            "vertices": vertices,
            "weights": weights,
            "reachable": reachable,
            "reason": np.where(reachable, "", "no_ik"),
            "q": q,
            "pos_err": rng.uniform(0, 1e-5, N),
            "rot_err": rng.uniform(0, 1e-4, N),
            "manipulability": manip,
            "inverse_condition": np.where(reachable, 0.5, np.nan),
            "rank": rank,
        }
    )


def _manifold() -> Manifold:
    return Manifold(
        chart=np.array([[0.0, 0.0], [0.1, 0.0], [0.0, 0.1]]),
        triangles=np.array([[0, 1, 2]]),
        dropped=np.zeros((0, 3), dtype=np.int64),
        dropped_reason=np.zeros(0, dtype=str),
        projection="xy",
        triangulator="qhull",
        frame=np.eye(4),
    )


def test_csv_header_order_and_ranked_rows_first(tmp_path):
    g = _table()
    path = tmp_path / "grasps.csv"
    order = grasps_csv.write_grasps_csv(g, path)
    with path.open() as fh:
        rows = list(csv.reader(fh))
    header = rows[0]
    assert header[: len(grasps_csv.CSV_COLUMNS)] == list(grasps_csv.CSV_COLUMNS)
    assert header[len(grasps_csv.CSV_COLUMNS) : len(grasps_csv.CSV_COLUMNS) + NQ] == [
        f"q{i}" for i in range(1, 8)
    ]
    assert header[-1] == "inverse_condition"
    ranks = [int(r[0]) for r in rows[1:]]
    n_ranked = int(np.count_nonzero(g["reachable"]))
    assert ranks[:n_ranked] == list(range(1, n_ranked + 1))
    assert ranks[n_ranked:] == [0] * (N - n_ranked)
    # unranked rows keep table order
    assert list(order[n_ranked:]) == sorted(order[n_ranked:])
    # candidates: -1 provenance, empty weights; booleans as true/false
    first_candidate = rows[1 + int(np.flatnonzero(order == 0)[0])]
    assert first_candidate[2:9] == ["-1", "-1", "-1", "-1", "", "", ""]
    assert {r[16] for r in rows[1:]} == {"true", "false"}
    text = path.read_text()
    assert "nan" not in text and "\r" not in text


def test_grasps_csv_leads_with_the_documented_columns():
    """The file format users parse: a registry edit must not reorder or rename these."""
    assert grasps_csv.CSV_COLUMNS == (
        *("rank", "origin", "triangle", "v1", "v2", "v3", "w1", "w2", "w3"),
        *("x", "y", "z", "qw", "qx", "qy", "qz", "reachable", "reason"),
        *("pos_err", "rot_err", "manipulability"),
    )


def _every_registered_column(n: int, nq: int = 3, k: int = 2) -> GraspTable:
    """A table with every column of the registry (by its dtype and shape) and two per-candidate."""
    rng = np.random.default_rng(1)
    dims = {"N": n, "nq": nq, "K": k, "3": 3, "8": 8}
    make = {
        "float": lambda shape: rng.uniform(-1, 1, shape),
        "int": lambda shape: rng.integers(-1, n, shape),
        "bool": lambda shape: rng.integers(0, 2, shape).astype(bool),
        "str": lambda shape: np.full(shape, "candidate"),
    }
    cols = {}
    for name, col in COLUMNS.items():
        shape = tuple(dims[d.strip()] for d in col.shape.strip("()").split(",") if d.strip())
        cols[name] = make[col.dtype](shape)
    t = np.tile(np.eye(4), (n, 1, 1))
    t[:, :3, 3] = rng.uniform(-1, 1, (n, 3))
    cols["dq"] = dq_from_matrix(t)
    cols["rank"] = np.arange(n)
    cols["q"] = np.where(cols["reachable"][:, None], cols["q"], np.nan)
    return GraspTable({**cols, "score": rng.uniform(0, 1, n), "source_id": np.arange(n)})


def test_every_column_grasps_csv_writes_is_in_the_registry(tmp_path):
    """A column the writer emits (under its own or a cell name) must be a registered column."""
    g = _every_registered_column(6)
    path = tmp_path / "grasps.csv"
    grasps_csv.write_grasps_csv(g, path)
    header = path.read_text().splitlines()[0].split(",")
    cells = {c: name for name, col in COLUMNS.items() for c in col.csv}
    registered = []
    for h in header:
        if h in cells or h in CANDIDATE_COLUMNS:
            registered.append(h)
        elif h[:1] == "q" and h[1:].isdigit():
            registered.append("q{j}")
        else:
            assert h in COLUMNS and not COLUMNS[h].csv and COLUMNS[h].shape == "(N,)", h
            registered.append(h)
    # leading cells in registry order, then the other 1-D columns, then the per-candidate ones
    lead = [c for col in COLUMNS.values() for c in col.csv]
    expected_q = [f"q{j}" for j in (1, 2, 3)]
    assert header[: len(lead) + 2] == lead[:-1] + expected_q
    rest = [n for n, c in COLUMNS.items() if not c.csv and c.shape == "(N,)"]
    assert header[len(lead) + 2 :] == [*rest, "score", "source_id"]
    back = grasps_csv.read_grasps_csv(path)
    for name, col in COLUMNS.items():  # every written column is read back with its dtype
        if col.csv or col.shape == "(N,)":
            kinds = {"float": "f", "int": "iu", "bool": "b", "str": "U"}[col.dtype]
            assert back[name].dtype.kind in kinds, (name, back[name].dtype)


def test_a_bad_cell_of_grasps_csv_carries_the_file_line_column_and_text(tmp_path):
    path = tmp_path / "grasps.csv"
    grasps_csv.write_grasps_csv(_table(), path)
    lines = path.read_text().splitlines()
    header = lines[0].split(",")
    row = lines[3].split(",")
    row[header.index("pos_err")] = "fast"
    path.write_text("\n".join([*lines[:3], ",".join(row), *lines[4:]]) + "\n")
    with pytest.raises(InputError) as info:
        grasps_csv.read_grasps_csv(path)
    assert str(info.value) == f"{path}:4: column 'pos_err': not a number: 'fast'"
    err = info.value
    assert (err.path, err.row, err.key, err.value) == (path, 4, "pos_err", "fast")
    row[header.index("pos_err")] = "0"
    row[header.index("qw")] = "2"
    path.write_text("\n".join([*lines[:3], ",".join(row), *lines[4:]]) + "\n")
    with pytest.raises(InputError, match="not a pose") as info:
        grasps_csv.read_grasps_csv(path)
    assert (info.value.path, info.value.row) == (path, 4)
    path.write_text("\n".join([*lines[:3], ",".join(row[:-1]), *lines[4:]]) + "\n")
    with pytest.raises(InputError, match="fields, header has") as info:
        grasps_csv.read_grasps_csv(path)
    assert (info.value.path, info.value.row, info.value.value) == (path, 4, len(row) - 1)


def test_csv_round_trip_is_exact(tmp_path):
    g = _table()
    path = tmp_path / "grasps.csv"
    order = grasps_csv.write_grasps_csv(g, path)
    back = grasps_csv.read_grasps_csv(path)
    ref = g.take(order)
    assert np.allclose(dq_to_matrix(back["dq"]), dq_to_matrix(ref["dq"]), atol=1e-15)
    for name in ("rank", "triangle", "reachable", "origin", "reason"):
        assert np.array_equal(back[name], ref[name]), name
    # v1..v3 name rows of the file: the rows where those candidates were written
    csv_row = np.argsort(order)
    v = ref["vertices"]
    assert np.array_equal(back["vertices"], np.where(v >= 0, csv_row[np.maximum(v, 0)], -1))
    for name in ("weights", "q", "pos_err", "rot_err", "manipulability", "inverse_condition"):
        assert np.array_equal(back[name], ref[name], equal_nan=True), name  # repr: bit-exact
    # quaternion written with qw >= 0
    assert np.all(back["dq"][:, 0] >= 0)


def test_manifold_round_trip(tmp_path):
    path = tmp_path / "manifold.npz"
    arrays.write_manifold(_manifold(), path, csv_rows=np.array([4, 0, 7]))
    m = arrays.read_manifold(path)
    assert isinstance(m, Manifold)
    assert np.array_equal(m.triangles, [[0, 1, 2]]) and m.projection == "xy"
    assert m.triangulator == "qhull" and np.array_equal(m.frame, np.eye(4))
    # every field of the manifold survives, scalars included
    import dataclasses

    if any(f.name == "period" for f in dataclasses.fields(Manifold)):
        m2 = dataclasses.replace(_manifold(), projection="cylindrical", period=0.25)
        arrays.write_manifold(m2, tmp_path / "m2.npz")
        back = arrays.read_manifold(tmp_path / "m2.npz")
        assert back.period == 0.25 and back.projection == "cylindrical"
    assert np.array_equal(np.load(path)["vertex_ids"], [4, 0, 7])
    with np.load(path, allow_pickle=False) as data:  # no pickled objects
        assert {"chart", "triangles", "dropped", "dropped_reason"} <= set(data.files)


def test_read_run_restores_candidates_first(tmp_path):
    g = _table()
    with transaction.atomic_run_dir(tmp_path / "run") as tmp:
        run_files.write_run_files(tmp, g, _manifold(), {"seed": 0, "robot": {"spec": "panda"}})
        run_files.write_summary(
            {"counts": {"candidates": NC}, "x": float("nan")}, tmp / "summary.json"
        )
    run = run_files.read_run(tmp_path / "run")
    assert run.summary["counts"] == {"candidates": NC} and run.summary["x"] is None
    assert list(run.grasps["origin"][:NC]) == ["candidate"] * NC
    assert np.allclose(dq_to_matrix(run.grasps["dq"][:NC]), dq_to_matrix(g["dq"][:NC]))
    assert len(run.grasps) == N
    # read back, the vertices index the table again (the candidates, first)
    interp = run.grasps["origin"] == "interpolated"
    assert np.array_equal(np.unique(run.grasps["vertices"][interp]), np.arange(NC))
    assert (tmp_path / "run" / "config.yaml").read_text().startswith("seed: 0")


def _siblings(parent: Path) -> list[str]:
    return sorted(p.name for p in parent.iterdir())


def test_atomic_dir_success_and_failure(tmp_path):
    out = tmp_path / "run"
    with transaction.atomic_run_dir(out) as tmp:
        assert tmp.parent == tmp_path and tmp.name.startswith(".run.tmp-")
        (tmp / "a.txt").write_text("a")
        assert not out.exists()
    assert (out / "a.txt").read_text() == "a"
    assert _siblings(tmp_path) == ["run"]

    for exc in (RuntimeError("boom"), KeyboardInterrupt()):
        with pytest.raises(type(exc)):
            with transaction.atomic_run_dir(tmp_path / "other") as tmp:
                (tmp / "partial.csv").write_text("x")
                raise exc
        assert _siblings(tmp_path) == ["run"]


def _fake_run(path: Path, marker: str = "old") -> Path:
    """A directory that gcm wrote (its marker) with two files."""
    path.mkdir(parents=True, exist_ok=True)
    transaction.write_marker(path, "run")
    for name in ("summary.json", "grasps.csv"):
        (path / name).write_text(marker)
    return path


def test_looks_like_run_dir_needs_the_marker(tmp_path):
    assert not transaction.looks_like_run_dir(tmp_path)
    assert not transaction.looks_like_run_dir(tmp_path / "nope")
    (tmp_path / "summary.json").write_text("{}")
    (tmp_path / "grasps.csv").write_text("")
    assert not transaction.looks_like_run_dir(tmp_path)  # file names prove nothing
    for text in (
        "{}",
        '{"project": "gcm_pipeline", "kind": "run", "id": "x"}',
        '{"project": "other", "kind": "run", "id": "' + "a" * 32 + '"}',
        "[1, 2]",
        "not json",
        '{"project": "gcm_pipeline", "kind": "run", "id": "'
        + "a" * 32
        + '", "x": "'
        + "y" * 5000
        + '"}',
    ):
        (tmp_path / transaction.MARKER).write_text(text)
        assert not transaction.looks_like_run_dir(tmp_path), text
    ident = transaction.write_marker(tmp_path, "run")
    assert transaction.looks_like_run_dir(tmp_path)
    assert transaction.read_marker(tmp_path)["id"] == ident
    assert not transaction.is_project_dir(tmp_path, "study")  # another kind
    assert not transaction.looks_like_run_dir(tmp_path / "grasps.csv")


def test_existing_run_needs_force_and_is_replaced_at_the_end(tmp_path):
    out = _fake_run(tmp_path / "run")
    msg = "already exists.*--force \\(CLI\\) or force=True \\(Python\\)"
    with pytest.raises(OutputError, match=msg):
        transaction.check_output_dir(out)
    with pytest.raises(OutputError):
        with transaction.atomic_run_dir(out):
            pass
    # a failing forced run leaves the old run untouched
    with pytest.raises(RuntimeError):
        with transaction.atomic_run_dir(out, force=True) as tmp:
            (tmp / "new.txt").write_text("new")
            raise RuntimeError
    assert _siblings(out) == [".gcm.json", "grasps.csv", "summary.json"]
    assert _siblings(tmp_path) == ["run"]
    with transaction.atomic_run_dir(out, force=True) as tmp:
        (tmp / "new.txt").write_text("new")
        assert (out / "summary.json").exists()  # still the old one until the end
    assert _siblings(out) == [".gcm.json", "new.txt"] and _siblings(tmp_path) == ["run"]


def test_force_replaces_only_run_directories(tmp_path):
    out = tmp_path / "data"
    out.mkdir()
    (out / "precious.txt").write_text("precious")
    (out / "summary.json").write_text("{}")  # a look-alike is not a run
    (out / "grasps.csv").write_text("")
    for force in (False, True):
        with pytest.raises(OutputError) as info:
            transaction.check_output_dir(out, force=force)
        assert str(info.value) == (
            f"refusing to replace {out}: it is not a gcm run directory (no valid .gcm.json "
            "marker, which gcm writes into every run); choose another --out"
        )
        with pytest.raises(OutputError, match="not a gcm run directory"):
            with transaction.atomic_run_dir(out, force=force):
                pass
    assert _siblings(out) == ["grasps.csv", "precious.txt", "summary.json"]
    assert _siblings(tmp_path) == ["data"]


def test_force_never_replaces_the_working_directory_or_a_folder_of_inputs(tmp_path, monkeypatch):
    work = _fake_run(tmp_path / "work")
    monkeypatch.chdir(work)
    for path in (work, Path("."), tmp_path, Path("..")):
        with pytest.raises(OutputError, match="working directory or one of its parents"):
            transaction.check_output_dir(path, force=True)
    runs = _fake_run(tmp_path / "runs")
    cfg = runs / "config.yaml"
    cfg.write_text("x")
    with pytest.raises(OutputError, match=f"it holds {cfg}, an input of this run"):
        transaction.check_output_dir(runs, force=True, keep=[cfg])
    with pytest.raises(OutputError, match="an input of this run"):
        with transaction.atomic_run_dir(runs, force=True, keep=[cfg]):
            pass
    # another run next to the input is fine
    assert (
        transaction.check_output_dir(tmp_path / "other", force=True, keep=[cfg])
        == tmp_path / "other"
    )
    assert _siblings(runs) == [".gcm.json", "config.yaml", "grasps.csv", "summary.json"]
    assert _siblings(tmp_path) == ["runs", "work"]


def test_a_directory_appearing_during_the_run_is_checked_again(tmp_path):
    out = tmp_path / "run"
    with pytest.raises(OutputError, match="not a gcm run directory"):
        with transaction.atomic_run_dir(out, force=True) as tmp:
            (tmp / "a").write_text("")
            out.mkdir()
            (out / "precious.txt").write_text("x")
    assert _siblings(out) == ["precious.txt"] and _siblings(tmp_path) == ["run"]


def test_failed_run_removes_the_parents_it_created(tmp_path):
    with pytest.raises(RuntimeError):
        with transaction.atomic_run_dir(tmp_path / "a" / "b" / "run") as tmp:
            assert tmp.parent == tmp_path / "a" / "b"
            raise RuntimeError
    assert list(tmp_path.iterdir()) == []
    with transaction.atomic_run_dir(tmp_path / "a" / "b" / "run"):
        pass
    assert (tmp_path / "a" / "b" / "run").is_dir()


def test_empty_existing_directory_is_fine(tmp_path):
    (tmp_path / "run").mkdir()
    with transaction.atomic_run_dir(tmp_path / "run") as tmp:
        (tmp / "a").write_text("")
    assert _siblings(tmp_path / "run") == [".gcm.json", "a"]


def test_output_path_problems(tmp_path):
    f = tmp_path / "file"
    f.write_text("x")
    with pytest.raises(OutputError, match="not a directory"):
        transaction.check_output_dir(f)
    with pytest.raises(OutputError, match="not a directory"):
        transaction.check_output_dir(f / "sub" / "run")
    with pytest.raises(OutputError, match="not writable"):
        transaction.check_output_dir("/proc/gcm_test_run")
    ro = tmp_path / "ro"
    ro.mkdir()
    os.chmod(ro, 0o500)
    try:
        if os.access(ro, os.W_OK) and os.geteuid() != 0:  # pragma: no cover
            pytest.skip("cannot make a read-only directory here")
        if os.geteuid() != 0:
            with pytest.raises(OutputError, match="not writable"):
                transaction.check_output_dir(ro / "run")
    finally:
        os.chmod(ro, 0o700)
    # nested new parents are fine and are not created by the check
    assert (
        transaction.check_output_dir(tmp_path / "a" / "b" / "run") == tmp_path / "a" / "b" / "run"
    )
    assert not (tmp_path / "a").exists()


def test_read_run_errors(tmp_path):
    with pytest.raises(InputError, match="run directory not found"):
        run_files.read_run(tmp_path / "nope")
    (tmp_path / "empty").mkdir()
    with pytest.raises(InputError, match="not a run directory.*grasps.csv"):
        run_files.read_run(tmp_path / "empty")


def test_csv_quotes_odd_reasons_and_handles_empty_tables(tmp_path):
    g = _table()
    odd = np.array(g["reason"], dtype=object)
    odd[1] = 'collision: a, b "c"'
    g = g.with_columns(reason=odd.astype(str))
    path = tmp_path / "grasps.csv"
    order = grasps_csv.write_grasps_csv(g, path)
    back = grasps_csv.read_grasps_csv(path)
    assert np.array_equal(back["reason"], g["reason"][order])
    empty = g.take(np.zeros(0, dtype=int))
    grasps_csv.write_grasps_csv(empty, path)
    assert len(grasps_csv.read_grasps_csv(path)) == 0


def test_per_candidate_columns_follow_the_metrics_and_round_trip(tmp_path):
    g = _table()
    score = np.r_[0.9, 0.5, 0.25, np.full(N - NC, np.nan)]
    g = GraspTable(
        {
            "score": score,
            "source_id": np.r_[12, 3, 7, np.full(N - NC, -1)],
            "segment": np.array(["mug", "a,b", "x"] + [""] * (N - NC)),
            **{k: g[k] for k in g.columns},
        }
    )
    path = tmp_path / "grasps.csv"
    order = grasps_csv.write_grasps_csv(g, path)
    header = path.read_text().splitlines()[0].split(",")
    # documented columns, q, the metric, then the candidates' own columns
    assert header[-4:] == ["inverse_condition", "score", "source_id", "segment"]
    back = grasps_csv.read_grasps_csv(path)
    assert back["source_id"].dtype.kind == "i"
    np.testing.assert_array_equal(back["source_id"], g["source_id"][order])
    np.testing.assert_array_equal(back["score"], g["score"][order])  # NaN == NaN here
    assert back["segment"].tolist() == g["segment"][order].tolist()


def test_a_long_cell_in_grasps_csv_is_refused_and_text_costs_its_size(tmp_path):
    """gcm show on a 423 KiB grasps.csv with one 100,000-character cell asked for 26.8 GiB.

    Every cell of the file went into one text array as wide as the longest cell.
    """
    import tracemalloc

    base = _table()
    g = base.take(np.arange(2_000) % NC)  # 2,000 candidates (no triangles)
    n = len(g)
    g = g.with_columns(
        reason=np.array(["no_ik"] * n),
        reachable=np.zeros(n, dtype=bool),
        rank=np.zeros(n, dtype=np.int64),
        label=np.array(["a"] * (n - 1) + ["b" * 250]),  # a carried text column
    )
    path = tmp_path / "grasps.csv"
    grasps_csv.write_grasps_csv(g, path)
    tracemalloc.start()
    try:
        back = grasps_csv.read_grasps_csv(path)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert back["label"][-1] == "b" * 250
    width = len(path.read_text().splitlines()[0].split(","))
    # the old 2-D array: 2,000 rows x all columns x 250 characters x 4 bytes (46 MB)
    assert peak < n * width * 250 * 4 / 3, (peak, width)
    lines = path.read_text().splitlines()
    lines[3] = lines[3].replace(",no_ik,", "," + "r" * 100_000 + ",")
    path.write_text("\n".join(lines) + "\n")
    with pytest.raises(InputError) as info:
        grasps_csv.read_grasps_csv(path)
    assert str(info.value) == (
        f"{path}:4: column 'reason': a cell of 100,000 characters; a CSV cell holds at most "
        "256 (gcm_pipeline.bounds.MAX_CSV_CELL)"
    )
    assert (info.value.path, info.value.row, info.value.value) == (path, 4, 100_000)


# ------------------------------------------------- replacement: concurrency, permissions


def _writer(out: Path, me: str, rounds: int) -> None:
    for i in range(rounds):
        with transaction.atomic_run_dir(out, force=True) as tmp:
            for name in ("grasps.csv", "manifold.npz", "summary.json"):
                (tmp / name).write_text(f"{me} {i}")
                time.sleep(0.002)


def test_concurrent_forced_replacements_leave_one_complete_run(tmp_path):
    """8 processes x 12 forced replacements of one directory (forked: no imports to wait for)."""
    import multiprocessing

    out = tmp_path / "run"
    ctx = multiprocessing.get_context("fork")
    procs = [ctx.Process(target=_writer, args=(out, f"w{k}", 12)) for k in range(8)]
    for p in procs:
        p.start()
    for p in procs:
        p.join(timeout=120)
        assert p.exitcode == 0
    assert _siblings(tmp_path) == ["run"]  # no .tmp-* / .old-* left
    assert transaction.looks_like_run_dir(out)
    texts = {(out / n).read_text() for n in ("grasps.csv", "manifold.npz", "summary.json")}
    assert len(texts) == 1  # the files of one writer's one round: a complete run
    assert _siblings(out) == [".gcm.json", "grasps.csv", "manifold.npz", "summary.json"]


def test_a_previous_run_that_cannot_be_removed_stays_as_it_was(tmp_path):
    out = _fake_run(tmp_path / "run")
    locked = out / "grasps.csv"
    if subprocess.run(["chattr", "+i", str(locked)], capture_output=True).returncode != 0:
        pytest.skip("chattr +i is not available here (needs root on a filesystem with flags)")
    try:
        with pytest.raises(OutputError) as info:
            with transaction.atomic_run_dir(out, force=True) as tmp:
                (tmp / "new.txt").write_text("new")
        assert str(info.value) == (
            f"cannot replace {out}: {locked} is immutable, so it cannot be removed; "
            "it is left as it was"
        )
        subprocess.run(["chattr", "-i", str(locked)], check=True)
        subprocess.run(["chattr", "+i", str(out)], check=True)  # the directory itself
        with pytest.raises(OutputError, match=f"cannot replace {out}: .*left as it was"):
            with transaction.atomic_run_dir(out, force=True) as tmp:
                (tmp / "new.txt").write_text("new")
    finally:
        subprocess.run(["chattr", "-i", str(locked), str(out)], capture_output=True)
    assert _siblings(out) == [".gcm.json", "grasps.csv", "summary.json"]
    assert locked.read_text() == "old"
    assert _siblings(tmp_path) == ["run"]


def test_leftovers_of_a_killed_run_are_removed_by_the_next(tmp_path):
    out = tmp_path / "run"
    proc = subprocess.Popen(
        [
            sys.executable,
            "-c",
            "import sys, time\nfrom gcm_pipeline.rundir import transaction\n"
            "with transaction.atomic_run_dir(sys.argv[1]) as tmp:\n"
            "    (tmp / 'partial.csv').write_text('x')\n    print(tmp, flush=True)\n"
            "    time.sleep(60)\n",
            str(out),
        ],
        stdout=subprocess.PIPE,
        text=True,
    )
    tmp = Path(proc.stdout.readline().strip())
    proc.kill()  # SIGKILL: no clean-up possible
    proc.wait()
    assert tmp.is_dir() and tmp.name.startswith(f".run.tmp-{proc.pid}-")
    # a look-alike left by someone else is not ours: kept
    foreign = tmp_path / f".run.tmp-{proc.pid}-abc"
    foreign.mkdir()
    with transaction.atomic_run_dir(out) as new:
        (new / "a").write_text("")
    assert _siblings(tmp_path) == [foreign.name, "run"]


def test_a_symbolic_link_is_never_replaced(tmp_path):
    real = _fake_run(tmp_path / "real")
    (tmp_path / "link").symlink_to(real)
    with pytest.raises(OutputError, match="it is a symbolic link"):
        transaction.check_output_dir(tmp_path / "link", force=True)
    assert transaction.looks_like_run_dir(real)
