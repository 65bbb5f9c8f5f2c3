"""gcm export: MoveIt YAML, Parquet and NPZ read back and compared with grasps.csv.

The run behind these tests imports a GraspGen file (so a per-candidate
``score`` column flows through to the exports) of top grasps on a box.
"""

from __future__ import annotations

import csv
import json
import os
from pathlib import Path

import numpy as np
import pytest
import yaml
from helpers import CONFIGS, DATA, assert_one_line_error
from scipy.spatial.transform import Rotation

from gcm_pipeline.cli import main
from gcm_pipeline.errors import InputError
from gcm_pipeline.pipeline import Pipeline
from gcm_pipeline.pipeline.outputs import export_run

BASE_XYZ = [0.05, -0.02, 0.0]


def graspgen_top_grasps(path: Path, box_top: float) -> None:
    """Six GraspGen grasps from above on the box top (base-link frames, object frame)."""
    transforms, scores = [], []
    for i, (dx, dy) in enumerate([(-0.012, -0.01), (0, -0.01), (0.012, -0.01)] * 2):
        dy = dy if i < 3 else -dy
        yaw = np.radians(6.0 * (i - 2.5))
        r = Rotation.from_euler("xz", [np.pi, yaw]).as_matrix()  # z down, x along +-x
        r = r @ Rotation.from_euler("z", np.pi / 2).as_matrix()  # fingers (x) along y
        t = np.eye(4)
        t[:3, :3] = r
        t[:3, 3] = [dx, dy, box_top] - 0.1034 * r[:, 2]
        transforms.append(t.tolist())
        scores.append(0.5 + 0.08 * i)
    path.write_text(
        json.dumps({"grasps": {"transforms": transforms, "confidences": scores}}), encoding="utf-8"
    )


def make_run(root: Path, *, object_x: float = 0.5, html: bool = False) -> Path:
    root.mkdir(parents=True, exist_ok=True)
    data = root / "box_grasps.json"
    graspgen_top_grasps(data, 0.05)
    cfg = {
        "robot": {"spec": "panda", "base_pose": {"xyz": BASE_XYZ, "rpy_deg": [0, 0, 10]}},
        "object": {
            "shape": "box",
            "dims": {"size": [0.06, 0.06, 0.10]},
            "pose": {"xyz": [object_x, 0.0, 0.05]},
        },
        "candidates": {
            "source": "file",
            "path": str(data),
            "frame": "object",
            "gripper": "franka_panda",
        },
        "manifold": {"projection": "xy"},
        "densify": {"subdivisions": 2},
        "approach": {"distance": 0.05, "steps": 5},
        "ranking": {"metric": "combined", "top_k": 3},
        "publish": {"html": html, "plots": False},
    }
    out = root / "run"
    Pipeline.from_dict(cfg).run(out, progress=False)
    return out


@pytest.fixture(scope="module")
def run(tmp_path_factory) -> Path:
    return make_run(tmp_path_factory.mktemp("export"))


def csv_rows(run: Path) -> tuple[list[str], list[list[str]]]:
    with (run / "grasps.csv").open(newline="") as fh:
        rows = list(csv.reader(fh))
    return rows[0], rows[1:]


def column(header, rows, name, kind=float):
    j = header.index(name)
    return np.array([kind(r[j]) if r[j] != "" else np.nan for r in rows])


def test_run_carries_the_imported_scores(run):
    header, rows = csv_rows(run)
    assert header[-2:] == ["score", "source_id"]
    origin = [r[header.index("origin")] for r in rows]
    score = column(header, rows, "score")
    cand = np.array(origin) == "candidate"
    assert sorted(score[cand].round(6).tolist()) == [round(0.5 + 0.08 * i, 6) for i in range(6)]
    assert np.isfinite(score).all()  # interpolated rows get the blend of their vertices
    assert column(header, rows, "reachable", str).tolist().count("true") >= 10


def test_moveit_export_matches_grasps_csv(run, tmp_path):
    out = tmp_path / "grasps.yaml"
    result = export_run(run, "moveit", out=out)
    grasps = yaml.safe_load(out.read_text())
    header, rows = csv_rows(run)
    rank = column(header, rows, "rank", int)
    ranked = [r for r, k in zip(rows, rank, strict=True) if k > 0]
    assert result.rows == len(grasps) == len(ranked) > 0
    base = np.eye(4)
    base[:3, :3] = Rotation.from_euler("z", 10, degrees=True).as_matrix()
    base[:3, 3] = BASE_XYZ
    fields = [
        "id",
        "pre_grasp_posture",
        "grasp_posture",
        "grasp_pose",
        "grasp_quality",
        "pre_grasp_approach",
        "post_grasp_retreat",
        "post_place_retreat",
        "max_contact_force",
        "allowed_touch_objects",
    ]
    for g, row in zip(grasps, ranked, strict=True):
        assert list(g) == fields  # moveit_msgs/Grasp, in the message's order
        world = np.eye(4)
        world[:3, 3] = [float(row[header.index(c)]) for c in "xyz"]
        q = [float(row[header.index(c)]) for c in ("qx", "qy", "qz", "qw")]
        world[:3, :3] = Rotation.from_quat(q).as_matrix()
        want = np.linalg.inv(base) @ world
        pose = g["grasp_pose"]
        assert pose["header"]["frame_id"] == "panda_link0"
        p = pose["pose"]["position"]
        np.testing.assert_allclose([p["x"], p["y"], p["z"]], want[:3, 3], atol=1e-9)
        o = pose["pose"]["orientation"]
        got = Rotation.from_quat([o["x"], o["y"], o["z"], o["w"]]).as_matrix()
        np.testing.assert_allclose(got, want[:3, :3], atol=1e-9)
        assert g["grasp_quality"] == pytest.approx(float(row[header.index("combined")]))
        assert g["id"] == f"rank_{row[0]}"
        app = g["pre_grasp_approach"]
        assert app["direction"]["header"]["frame_id"] == "panda_hand_tcp"
        assert app["direction"]["vector"] == {"x": 0.0, "y": 0.0, "z": 1.0}
        assert app["desired_distance"] == app["min_distance"] == 0.05
        assert g["pre_grasp_posture"]["joint_names"] == [
            "panda_finger_joint1",
            "panda_finger_joint2",
        ]
        assert g["pre_grasp_posture"]["points"][0]["positions"] == [0.04, 0.04]
        assert g["grasp_posture"]["points"][0]["positions"] == [0.0, 0.0]  # no width in the file
    assert [g["grasp_quality"] for g in grasps] == sorted(
        (g["grasp_quality"] for g in grasps), reverse=True
    )


def test_parquet_export_matches_grasps_csv(run, tmp_path):
    import pyarrow.parquet as pq

    out = tmp_path / "g.parquet"
    export_run(run, "parquet", out=out)
    table = pq.read_table(out).to_pydict()
    header, rows = csv_rows(run)
    qnames = [h for h in header if h[0] == "q" and h[1:].isdigit()]
    assert [c for c in table if c != "q"] == [h for h in header if h not in qnames]
    for name in header:
        if name in qnames:
            continue
        want = [r[header.index(name)] for r in rows]
        got = table[name]
        if name in ("origin", "reason"):
            assert got == [w or None for w in want]  # an empty cell is null
        elif set(want) <= {"true", "false"}:  # reachable, top
            assert got == [w == "true" for w in want]
        else:
            assert [g is None for g in got] == [w == "" for w in want], name
            np.testing.assert_array_equal(
                np.array(got, dtype=float), np.array([w or "nan" for w in want], dtype=float)
            )
    q = [
        [float(r[header.index(c)]) for c in qnames] if r[header.index("q1")] else None for r in rows
    ]
    assert table["q"] == q


def test_npz_export_and_top(run, tmp_path):
    out = tmp_path / "g.npz"
    result = export_run(run, "npz", top=3, out=out)
    assert result.rows == 3
    header, rows = csv_rows(run)
    with np.load(out, allow_pickle=False) as data:
        assert data["rank"].tolist() == [1, 2, 3]
        np.testing.assert_array_equal(data["x"], column(header, rows[:3], "x"))
        np.testing.assert_array_equal(data["score"], column(header, rows[:3], "score"))
        assert data["q"].shape == (3, 7) and data["pose"].shape == (3, 4, 4)
        np.testing.assert_allclose(data["pose"][:, :3, 3], np.c_[data["x"], data["y"], data["z"]])
        assert data["origin"].dtype.kind == "U"


def test_cli_export_and_an_empty_run(run, tmp_path, capsys):
    assert main(["export", str(run), "--format", "parquet", "--out", str(tmp_path / "a.pq")]) == 0
    assert "wrote" in capsys.readouterr().out
    # a run whose object is out of reach: no reachable grasp
    empty = make_run(tmp_path / "far", object_x=3.0)
    assert "no grasp is reachable" in capsys.readouterr().err  # the run warned
    out = tmp_path / "none.yaml"
    assert main(["export", str(empty), "--format", "moveit", "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "no reachable grasp to export" in err[0]
    assert yaml.safe_load(out.read_text()) == []  # empty but valid
    with pytest.raises(InputError, match="not a run directory"):
        export_run(tmp_path, "npz")
    assert not list(tmp_path.glob(".*.tmp"))  # nothing half-written


def test_export_to_a_device_pipe_or_folder_is_refused_and_a_link_is_kept(run, tmp_path, capsys):
    """A rename would replace /dev/null, a pipe or a folder with a file: refused in one line."""
    fifo = tmp_path / "pipe"
    os.mkfifo(fifo)
    for target, what in (
        ("/dev/null", "not a regular file"),
        (fifo, "not a regular file"),
        (tmp_path, "a directory"),
    ):
        assert main(["export", str(run), "--format", "npz", "--out", str(target)]) == 2
        assert (
            capsys.readouterr().err
            == f"error: cannot write {target}: it is {what}; give a file name\n"
        )
    assert Path("/dev/null").is_char_device() and fifo.is_fifo()
    # a symbolic link stays a link; the file it names gets the export
    real = tmp_path / "real.npz"
    real.write_bytes(b"old")
    link = tmp_path / "link.npz"
    link.symlink_to(real)
    assert main(["export", str(run), "--format", "npz", "--out", str(link)]) == 0
    assert link.is_symlink() and np.load(link)["x"].shape == np.load(real)["x"].shape
    assert real.read_bytes()[:2] == b"PK"
    folder = str(tmp_path / "x") + "/"  # a folder's name: never a file named x
    assert main(["export", str(run), "--format", "npz", "--out", folder]) == 2
    assert capsys.readouterr().err == (
        f"error: cannot write {folder}: a file name, not a folder, is needed\n"
    )
    assert not (tmp_path / "x").exists()
    loop = tmp_path / "loop.npz"
    loop.symlink_to(loop)
    assert main(["export", str(run), "--format", "npz", "--out", str(loop)]) == 2
    err = capsys.readouterr().err
    assert err.startswith(f"error: cannot write {loop}: ") and err.count("\n") == 1


# ------------------------------------------------ tampered runs, odd arguments


def _copy_run(run: Path, dest: Path) -> Path:
    import shutil

    shutil.copytree(run, dest)
    return dest


def test_export_reads_grasps_csv_as_the_run_reader_does(run, tmp_path):
    """Blank lines, a byte order mark and CRLF line ends are read (read_grasps_csv ignores
    them), so the exports of the edited file equal those of the original."""
    edited = _copy_run(run, tmp_path / "edited")
    lines = (run / "grasps.csv").read_text(encoding="utf-8").splitlines()
    lines.insert(3, "")
    lines.append("")
    text = "\ufeff" + "\r\n".join(lines) + "\r\n"
    (edited / "grasps.csv").write_bytes(text.encode("utf-8"))
    for fmt in ("moveit", "parquet", "npz"):
        a = export_run(run, fmt, top=4, out=tmp_path / f"a.{fmt}")
        b = export_run(edited, fmt, top=4, out=tmp_path / f"b.{fmt}")
        assert a.rows == b.rows == 4
        if fmt == "moveit":
            assert (tmp_path / "a.moveit").read_text() == (tmp_path / "b.moveit").read_text()


@pytest.mark.parametrize("fmt", ["moveit", "parquet", "npz"])
def test_an_empty_export_is_a_valid_file_in_every_format(run, tmp_path, fmt):
    """A run whose grasps.csv has no row (or no reachable one with --top) still exports an
    empty file of the format, then says so in one line."""
    empty = _copy_run(run, tmp_path / "empty")
    header = (run / "grasps.csv").read_text(encoding="utf-8").splitlines()[0]
    (empty / "grasps.csv").write_text(header + "\n", encoding="utf-8")
    out = tmp_path / f"none.{fmt}"
    with pytest.raises(InputError, match="no reachable grasp to export; wrote an empty"):
        export_run(empty, fmt, top=5, out=out)
    if fmt == "moveit":
        assert yaml.safe_load(out.read_text()) == []
    elif fmt == "parquet":
        import pyarrow.parquet as pq

        table = pq.read_table(out)
        assert table.num_rows == 0 and "q" in table.column_names
    else:
        with np.load(out, allow_pickle=False) as data:
            assert data["pose"].shape == (0, 4, 4) and data["q"].shape[0] == 0


def test_top_must_ask_for_at_least_one_grasp(run, tmp_path, capsys):
    for top in ("0", "-1"):
        out = tmp_path / f"top{top}.yaml"
        code = main(["export", str(run), "--format", "moveit", "--top", top, "--out", str(out)])
        err = capsys.readouterr().err.strip().splitlines()
        assert code == 2 and len(err) == 1 and "--top must be >= 1" in err[0], err
        assert not out.exists()


def test_out_never_overwrites_the_run_itself(run, tmp_path, capsys):
    copy = _copy_run(run, tmp_path / "copy")
    before = {p.name: p.read_bytes() for p in copy.iterdir() if p.is_file()}
    for name in ("grasps.csv", "config.yaml", "summary.json", "manifold.npz", ".gcm.json"):
        code = main(["export", str(copy), "--format", "parquet", "--out", str(copy / name)])
        err = capsys.readouterr().err.strip().splitlines()
        assert code == 2 and len(err) == 1 and "the run's own" in err[0], err
    assert {p.name: p.read_bytes() for p in copy.iterdir() if p.is_file()} == before
    # a previous export of the run is fine to replace
    assert main(["export", str(copy), "--format", "parquet", "--out", str(copy / "a.pq")]) == 0
    assert main(["export", str(copy), "--format", "parquet", "--out", str(copy / "a.pq")]) == 0


def test_out_where_no_file_can_be_made_is_one_line(run, capsys):
    code = main(["export", str(run), "--format", "npz", "--out", "/proc/gcm-export.npz"])
    line = assert_one_line_error(code, capsys.readouterr().err)
    assert line.startswith("error: cannot write"), line


def test_out_into_a_missing_folder_says_it_does_not_exist(run, tmp_path, capsys):
    missing = tmp_path / "no" / "such"
    for fmt in ("moveit", "parquet", "npz"):
        code = main(["export", str(run), "--format", fmt, "--out", str(missing / "g")])
        line = assert_one_line_error(code, capsys.readouterr().err)
        assert line == f"error: cannot write {missing / 'g'}: {missing} does not exist"
    assert not (tmp_path / "no").exists()


@pytest.mark.parametrize(
    "config",
    [
        "robot: 5\ncandidates: {source: plane, count: 3}\n",
        "robot: {base_pose: {xyz: [1, 2]}}\ncandidates: {source: plane, count: 3}\n",
        "approach: {distance: abc}\ncandidates: {source: plane, count: 3}\n",
        "retreat: 5\ncandidates: {source: plane, count: 3}\n",
        "[1, 2\n",
    ],
)
def test_a_tampered_config_yaml_is_one_line(run, tmp_path, capsys, config):
    bad = _copy_run(run, tmp_path / "bad")
    (bad / "config.yaml").write_text(config)
    code = main(["export", str(bad), "--format", "moveit", "--out", str(tmp_path / "m.yaml")])
    assert_one_line_error(code, capsys.readouterr().err, "config.yaml")
    assert not (tmp_path / "m.yaml").exists()


# ------------------------------------------- real clients: DuckDB, polars, rosbags

BOX = CONFIGS / "box.yaml"
#: configs/box.yaml made quick: 110 grasps, 71 reachable, 16 of them with margin inf
QUICK_BOX = ("densify.subdivisions=2", "publish.html=false", "publish.plots=false")


def box_run(root: Path, metric: str, *more: str) -> Path:
    from gcm_pipeline.config import load_config

    out = root / f"box_{metric}"
    cfg = load_config(BOX, (*QUICK_BOX, f"ranking.metric={metric}", *more))
    Pipeline(cfg).run(out, progress=False)
    return out


@pytest.fixture(scope="module")
def margin_run(tmp_path_factory) -> Path:
    return box_run(tmp_path_factory.mktemp("margin"), "margin")


def _client_columns(header: list[str]) -> list[tuple[str, str]]:
    """(grasps.csv column, the same values in the Parquet file) for every column."""
    return [(h, f"q[{h[1:]}]" if h[0] == "q" and h[1:].isdigit() else h) for h in header if h != ""]


@pytest.mark.parametrize("which", ["combined", "margin"])
def test_duckdb_and_polars_aggregate_parquet_as_grasps_csv(run, margin_run, tmp_path, which):
    """count/avg/min/max of every column agree between grasps.csv and the Parquet export.

    grasps.csv leaves a missing value empty (an unreachable grasp's metrics, joint values,
    error columns, a candidate's weights, a reachable grasp's reason); DuckDB and polars
    read that as null, so the Parquet file must hold null there, not NaN.
    """
    import duckdb
    import polars as pl

    src = {"combined": run, "margin": margin_run}[which]
    out = tmp_path / "g.parquet"
    export_run(src, "parquet", out=out)
    csv_path = src / "grasps.csv"
    header, rows = csv_rows(src)
    empty = {h for j, h in enumerate(header) if any(r[j] == "" for r in rows)}
    if which == "margin":  # the run this test is about: unreachable rows and empty cells
        assert {"manipulability", "reason", "q1", "combined"} - empty == {"combined"}
    con = duckdb.connect()
    parquet = pl.read_parquet(out)
    # the CSV read with the Parquet file's column types (DuckDB's sniffer takes a column of
    # only "inf" for a DATE); q1..qN as q's element type
    types = {row[0]: row[1] for row in con.sql(f"describe select * from '{out}'").fetchall()}
    qnames = [h for h in header if h[0] == "q" and h[1:].isdigit()]
    element = types.pop("q").removesuffix("[]")
    types.update({h: element for h in qnames})
    csv_types = "{" + ", ".join(f"'{k}': '{v}'" for k, v in types.items()) + "}"
    from_csv = pl.read_csv(
        csv_path, schema_overrides={h: pl.Float64 for h, t in types.items() if t == "DOUBLE"}
    )
    for name, pq_name in _client_columns(header):
        aggs = ["count", "min", "max"] + (["avg"] if types[name] in ("DOUBLE", "BIGINT") else [])
        col = pq_name if "[" in pq_name else f'"{pq_name}"'
        want_sql = ", ".join(f'{a}("{name}")' for a in aggs)
        want = con.sql(f"select {want_sql} from read_csv('{csv_path}', types={csv_types})")
        got_sql = ", ".join(f"{a}({col})" for a in aggs)
        got = con.sql(f"select {got_sql} from '{out}'")
        assert got.fetchall() == want.fetchall(), (which, name)
        # polars: the same counts and aggregates (nulls left out)
        pcol = parquet["q"].list.get(int(name[1:]) - 1) if "[" in pq_name else parquet[name]
        ccol = from_csv[name]
        assert pcol.null_count() == ccol.null_count(), (which, name)
        if types[name] in ("DOUBLE", "BIGINT"):
            assert pcol.mean() == pytest.approx(ccol.mean(), rel=1e-12, nan_ok=True), name
            assert (pcol.min(), pcol.max()) == (ccol.min(), ccol.max()), name
    # the case: the mean manipulability over the reachable grasps, not NaN
    ((mean, count),) = con.sql(
        f"select avg(manipulability), count(manipulability) from '{out}'"
    ).fetchall()
    assert count == sum(r[header.index("reachable")] == "true" for r in rows)
    assert np.isfinite(mean)
    if which == "margin":
        assert count < len(rows)


def _moveit_typestore():
    from rosbags.typesys import Stores, get_types_from_msg, get_typestore

    store = get_typestore(Stores.ROS2_HUMBLE)
    types = {}
    for f in sorted((DATA / "moveit_msgs" / "msg").glob("*.msg")):
        types.update(get_types_from_msg(f.read_text(), f"moveit_msgs/msg/{f.stem}"))
    store.register(types)
    return store


def _ros_message(store, typename: str, data):
    """A rosbags message built from a YAML mapping that has exactly the message's fields."""
    from rosbags.typesys.store import Nodetype

    msgdef = store.get_msgdef(typename)
    names = [name for name, _ in msgdef.fields]
    assert isinstance(data, dict) and list(data) == names, (typename, data)

    def value(node, spec, v):
        if node == Nodetype.NAME:
            return _ros_message(store, spec, v)
        if node in (Nodetype.SEQUENCE, Nodetype.ARRAY):
            (sub_node, sub_spec), _ = spec
            assert isinstance(v, list), (typename, v)
            if sub_node == Nodetype.BASE and sub_spec[0] != "string":
                return np.array(v, dtype=np.dtype(sub_spec[0].replace("float", "float")))
            return [value(sub_node, sub_spec, x) for x in v]
        typ = spec[0]
        if typ == "string":
            assert isinstance(v, str)
            return v
        if typ.startswith("float"):
            assert isinstance(v, (int, float)) and not isinstance(v, bool)
            return float(v)
        assert isinstance(v, int) and not isinstance(v, bool), (typename, v)
        return v

    return msgdef.cls(**{name: value(*spec, data[name]) for name, spec in msgdef.fields})


def _through_a_bag(store, grasps: list, bag: Path) -> list:
    """The grasps as moveit_msgs/msg/Grasp written to a rosbag2 bag and read back."""
    from rosbags.rosbag2 import Reader, Writer

    msgtype = "moveit_msgs/msg/Grasp"
    with Writer(bag, version=9) as writer:
        conn = writer.add_connection("/grasps", msgtype, typestore=store)
        for i, g in enumerate(grasps):
            writer.write(conn, i + 1, store.serialize_cdr(_ros_message(store, msgtype, g), msgtype))
    with Reader(bag) as reader:
        return [store.deserialize_cdr(raw, conn.msgtype) for conn, _, raw in reader.messages()]


ALL_METRICS = [
    ("yoshikawa",),
    ("translational",),
    ("inverse_condition",),
    ("joint_limit_margin",),
    ("clearance",),
    ("margin",),
    ("combined",),
    ("combined", "ranking.weights={yoshikawa: 1.0, margin: 1.0}"),
]


@pytest.mark.parametrize("metric", ALL_METRICS, ids=lambda m: "+".join(m).split("=")[-1])
def test_moveit_grasp_quality_never_increases_down_the_list(tmp_path, margin_run, metric):
    """Every ranking metric, inf margins included: read back with rosbags and moveit_msgs.

    MoveIt's pick sorts its grasps by grasp_quality, best first; an infinite margin exported
    as 0 sent the best grasps to the end.
    """
    from gcm_pipeline.ranking.metrics import METRIC_COLUMNS

    src = margin_run if metric == ("margin",) else box_run(tmp_path, *metric)
    out = tmp_path / "grasps.yaml"
    export_run(src, "moveit", out=out)
    msgs = _through_a_bag(_moveit_typestore(), yaml.safe_load(out.read_text()), tmp_path / "bag")
    header, rows = csv_rows(src)
    rank = column(header, rows, "rank", int)
    ranked = [r for r, k in zip(rows, rank, strict=True) if k > 0]
    assert len(msgs) == len(ranked) > 10
    assert [m.id for m in msgs] == [f"rank_{k}" for k in range(1, len(ranked) + 1)]
    quality = np.array([m.grasp_quality for m in msgs])
    assert np.isfinite(quality).all()
    assert (np.diff(quality) <= 0).all(), quality
    value = column(header, ranked, METRIC_COLUMNS[metric[0]])
    infinite = np.isposinf(value)
    np.testing.assert_array_equal(quality[~infinite], value[~infinite])
    if metric == ("margin",):
        assert 0 < infinite.sum() < len(value)  # the case of the issue
        np.testing.assert_array_equal(quality[infinite], value[~infinite].max())
    for m, row in zip(msgs, ranked, strict=True):
        p = m.grasp_pose.pose.position
        assert m.grasp_pose.header.frame_id == "panda_link0"
        assert np.isfinite([p.x, p.y, p.z]).all()
        assert row[header.index("reachable")] == "true"


def test_moveit_export_refuses_a_grasps_csv_whose_ranks_and_values_disagree(run, tmp_path):
    copy = _copy_run(run, tmp_path / "copy")
    header, rows = csv_rows(copy)
    j = header.index("combined")
    rows[1][j] = repr(float(rows[0][j]) + 1.0)  # rank 2 better than rank 1
    with (copy / "grasps.csv").open("w", newline="") as fh:
        csv.writer(fh, lineterminator="\n").writerows([header, *rows])
    with pytest.raises(InputError, match=r"rank 2 has combined .* more than"):
        export_run(copy, "moveit", out=tmp_path / "g.yaml")


def test_gcm_show_on_a_grasps_csv_with_a_huge_cell_is_one_line(run, tmp_path, capsys):
    """A 423 KiB grasps.csv with one 100,000-character cell asked gcm show for 26.8 GiB."""
    copy = _copy_run(run, tmp_path / "copy")
    header, rows = csv_rows(copy)
    rows[2][header.index("origin")] = "x" * 100_000
    with (copy / "grasps.csv").open("w", newline="") as fh:
        csv.writer(fh, lineterminator="\n").writerows([header, *rows])
    assert main(["show", str(copy)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err == [
        f"error: {copy / 'grasps.csv'}:4: column 'origin': a cell of 100,000 characters; "
        "a CSV cell holds at most 256 (gcm_pipeline.bounds.MAX_CSV_CELL)"
    ]
