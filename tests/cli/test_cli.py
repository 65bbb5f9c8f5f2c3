"""The gcm command line: commands, summaries and one-line user errors (exit 2)."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from helpers import FLAT, QUICK, ROOT, assert_one_line_error, gcm_env, run_gcm

from gcm_pipeline.cli import main


def _config(tmp_path, text: str) -> Path:
    path = tmp_path / "cfg.yaml"
    path.write_text(text)
    return path


GRASP_FILE_CFG = """
candidates: {{source: file, path: {path}, format: {fmt}}}
densify: {{subdivisions: 2}}
"""


@pytest.fixture
def out(tmp_path):
    """An output directory inside an otherwise empty parent."""
    parent = tmp_path / "results"
    parent.mkdir()
    return parent / "run"


def _nothing_left(out: Path):
    assert not out.exists()
    assert list(out.parent.iterdir()) == []  # no temporary siblings either


def test_validate_and_schema(cli):
    code, text, _ = cli("validate", FLAT)
    assert code == 0 and "ok" in text and "plane" in text
    code, text, _ = cli("schema")
    assert code == 0
    schema = json.loads(text)
    assert "candidates" in schema["properties"]


def test_run_prints_a_summary_then_show_and_plot(cli, out):
    code, text, err = cli("run", FLAT, "--out", out, "--set", "publish.html=false")
    assert code == 0, err
    for fragment in (
        "candidates    3",
        "reachable",
        "timings [s]",
        "top 5 grasps",
        "run directory:",
    ):
        assert fragment in text
    assert "--meshcat" in text
    assert (out / "grasps.csv").is_file() and (out / "manifold.png").is_file()
    code, text, err = cli("show", out, "--top", "3")
    assert code == 0, err
    rows = [line for line in text.splitlines() if line.strip()[:1].isdigit()]
    assert [int(r.split()[0]) for r in rows] == [1, 2, 3]
    for p in out.glob("*.png"):
        p.unlink()
    code, text, err = cli("plot", out)
    assert code == 0, err
    assert (out / "manifold.png").is_file() and "manifold.png" in text


def test_quiet_prints_only_the_run_dir(cli, out):
    code, text, err = cli("run", FLAT, "--out", out, "--quiet", *QUICK)
    assert code == 0
    assert text.strip() == str(out.absolute())
    assert err == ""


def test_existing_output_needs_force(cli, out):
    assert cli("run", FLAT, "--out", out, "-q", *QUICK)[0] == 0
    before = (out / "grasps.csv").read_bytes()
    code, _, err = cli("run", FLAT, "--out", out, *QUICK)
    assert_one_line_error(code, err, "already exists", "--force")
    assert (out / "grasps.csv").read_bytes() == before
    code, _, err = cli("run", FLAT, "--out", out, "--force", "-q", *QUICK, "--set", "seed=4")
    assert code == 0, err
    assert sorted(p.name for p in out.parent.iterdir()) == ["run"]


BAD_CONFIGS = {
    "unknown_key": (
        "candidates: {source: plane, cont: 3}\n",
        ["candidates.cont", "did you mean 'candidates.count'"],
    ),
    "zero_count": (
        "object: {shape: plane, dims: {size: [0.3, 0.3]}}\ncandidates: {source: plane, count: 0}\n",
        ["candidates.count"],
    ),
    "negative_size": (
        "object: {shape: plane, dims: {size: [-0.3, 0.3]}}\ncandidates: {source: plane}\n",
        ["object.dims.size"],
    ),
    "wrong_type": ("seed: zero\ncandidates: {source: plane}\n", ["seed"]),
    "malformed": ("candidates:\n  source: plane\n   count: 3\n", ["malformed YAML", "cfg.yaml:3:"]),
    "empty": ("", ["empty"]),
}


@pytest.mark.parametrize("name", sorted(BAD_CONFIGS))
def test_bad_configs(cli, tmp_path, out, name):
    text, fragments = BAD_CONFIGS[name]
    code, _, err = cli("run", _config(tmp_path, text), "--out", out)
    assert_one_line_error(code, err, *fragments)
    _nothing_left(out)


def test_missing_config(cli, tmp_path, out):
    code, _, err = cli("run", tmp_path / "nope.yaml", "--out", out)
    assert_one_line_error(code, err, "not found", "nope.yaml")
    _nothing_left(out)


def test_bad_override(cli, out):
    code, _, err = cli("run", FLAT, "--out", out, "--set", "ik.backnd=mink")
    assert_one_line_error(code, err, "unknown key 'ik.backnd'", "did you mean 'ik.backend'")
    _nothing_left(out)
    code, _, err = cli("validate", FLAT, "--set", "densify.subdivisions=-2")
    assert_one_line_error(code, err, "densify.subdivisions")


def _poses(n):
    t = np.tile(np.eye(4), (n, 1, 1))
    t[:, 0, 3] = 0.4 + 0.05 * np.arange(n)
    t[:, 1, 3] = 0.05 * (np.arange(n) % 2)
    t[:, 2, 3] = 0.3
    t[:, :3, :3] = np.diag([1.0, -1.0, -1.0])  # approach from above
    return t


def test_grasp_file_errors(cli, tmp_path, out):
    bad_shape = tmp_path / "shape.npy"
    np.save(bad_shape, np.zeros((4, 3, 4)))
    code, _, err = cli(
        "run",
        _config(tmp_path, GRASP_FILE_CFG.format(path=bad_shape, fmt="npy")),
        "--out",
        out,
    )
    assert_one_line_error(code, err, "shape.npy", "(N, 4, 4)", "(4, 3, 4)")
    _nothing_left(out)

    poses = _poses(5)
    poses[2, :3, :3] *= 2.0
    scaled = tmp_path / "scaled.npy"
    np.save(scaled, poses)
    code, _, err = cli(
        "run",
        _config(tmp_path, GRASP_FILE_CFG.format(path=scaled, fmt="npy")),
        "--out",
        out,
    )
    assert_one_line_error(code, err, "grasp 2", "not a rigid transform")
    _nothing_left(out)

    code, _, err = cli(
        "run",
        _config(tmp_path, GRASP_FILE_CFG.format(path=tmp_path / "missing.npy", fmt="npy")),
        "--out",
        out,
    )
    assert_one_line_error(code, err, "grasp file not found", "missing.npy")
    _nothing_left(out)


def test_acronym_file_missing_key(cli, tmp_path, out):
    h5py = pytest.importorskip("h5py")
    path = tmp_path / "grasps.h5"
    with h5py.File(path, "w") as f:
        f["grasps/transforms"] = _poses(4)
    code, _, err = cli(
        "run",
        _config(tmp_path, GRASP_FILE_CFG.format(path=path, fmt="acronym")),
        "--out",
        out,
    )
    assert_one_line_error(code, err, "grasps.h5", "grasps/qualities/flex/object_in_gripper")
    _nothing_left(out)


def test_acronym_file_runs(cli, tmp_path, out):
    h5py = pytest.importorskip("h5py")
    trimesh = pytest.importorskip("trimesh")
    path = tmp_path / "grasps.h5"
    with h5py.File(path, "w") as f:
        f["grasps/transforms"] = _poses(4)
        f["grasps/qualities/flex/object_in_gripper"] = np.array([1, 1, 0, 1])
        f["object/file"] = "meshes/Box/x.obj"
        f["object/scale"] = 1.0
    (tmp_path / "meshes" / "Box").mkdir(parents=True)  # the mesh the file names, found
    trimesh.creation.box(extents=(0.04, 0.04, 0.1)).export(tmp_path / "meshes/Box/x.obj")
    text = GRASP_FILE_CFG.format(path=path, fmt="acronym").replace(
        "format: acronym", "format: acronym, success_only: true"
    )
    code, _, err = cli("run", _config(tmp_path, text), "--out", out, "-q", *QUICK)
    assert code == 0, err
    assert json.loads((out / "summary.json").read_text())["counts"]["candidates"] == 3


def test_output_path_problems(cli, tmp_path):
    f = tmp_path / "file"
    f.write_text("x")
    code, _, err = cli("run", FLAT, "--out", f)
    assert_one_line_error(code, err, "not a directory")
    assert f.read_text() == "x"
    code, _, err = cli("run", FLAT, "--out", "/proc/gcm_run")
    assert_one_line_error(code, err, "not writable")
    if os.geteuid() != 0:
        ro = tmp_path / "ro"
        ro.mkdir(mode=0o500)
        code, _, err = cli("run", FLAT, "--out", ro / "run")
        assert_one_line_error(code, err, "not writable")


def test_show_on_a_non_run(cli, tmp_path):
    code, _, err = cli("show", tmp_path)
    assert_one_line_error(code, err, "not a run directory")


def test_debug_shows_the_traceback(cli, tmp_path):
    code, _, err = cli("run", tmp_path / "nope.yaml", "--debug")
    assert code == 2
    assert "Traceback" in err and err.strip().splitlines()[-1].startswith("error: ")


@pytest.mark.parametrize(
    ("argv", "fragment"),
    [
        (["run"], "gcm run: the following arguments are required: CONFIG"),
        (["bogus"], "gcm: argument COMMAND: invalid choice: 'bogus'"),
        ([], "gcm: the following arguments are required: COMMAND"),
        (["query", "r", "--pose", "1", "2"], "gcm query: argument --pose: expected 7 arguments"),
        (["export", "r", "--format", "csv"], "gcm export: argument --format: invalid choice"),
        (["show", "r", "--top", "x"], "gcm show: argument --top: invalid int value: 'x'"),
        (["run", "c.yaml", "--bogus"], "gcm: unrecognized arguments: --bogus"),
    ],
)
def test_usage_errors_are_one_line_and_exit_2(capsys, argv, fragment):
    with pytest.raises(SystemExit) as info:
        main(argv)
    assert info.value.code == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.startswith("error: "), err
    assert fragment in err and err.rstrip().endswith("--help)"), err


def test_python_dash_m(tmp_path):
    out = tmp_path / "run"
    proc = run_gcm("run", FLAT, "--out", out, "--quiet", *QUICK, cwd=tmp_path, timeout=120)
    assert proc.returncode == 0, proc.stderr
    assert (out / "grasps.csv").is_file()
    proc = subprocess.run(
        [sys.executable, "-m", "gcm_pipeline.cli", "run", str(FLAT), "--out", str(out)],
        capture_output=True,
        text=True,
        env=gcm_env(),
        cwd=tmp_path,
        timeout=120,
    )
    assert_one_line_error(proc.returncode, proc.stderr)


def test_meshcat_viewer_opens_after_the_run(cli, out, monkeypatch):
    from gcm_pipeline.outputs import live

    events = []

    class FakeViewer:
        url = "http://127.0.0.1:7000/static/"
        server_pid = 4242

        def close(self):
            events.append("closed")

    def fake_open(grasps, manifold, robot, config, detach=False):
        events.append(("open", (out / "grasps.csv").is_file(), len(grasps), detach))
        return FakeViewer()

    monkeypatch.setattr(live, "open_viewer", fake_open)
    monkeypatch.setattr(live, "probe_server", lambda url, timeout: FakeViewer.url)
    # --no-wait returns at once: only a server the user runs keeps the scene alive
    server = ["--set", "publish.zmq_url=tcp://127.0.0.1:6000"]
    code, text, err = cli("run", FLAT, "--out", out, "--meshcat", "--no-wait", *server, *QUICK)
    assert code == 0, err
    # the run directory is complete first; --no-wait leaves the server running
    assert events == [("open", True, 66, True), "closed"]
    assert "meshcat viewer: http://127.0.0.1:7000/static/" in text
    assert "keeps running (pid 4242)" in text


def test_no_wait_with_gcms_own_server_is_refused_before_the_run(cli, out):
    code, text, err = cli("run", FLAT, "--out", out, "--meshcat", "--no-wait", *QUICK)
    assert_one_line_error(code, err, "--no-wait", "publish.zmq_url")
    assert text == ""
    _nothing_left(out)


# ------------------------------------------------- QA review: run / CLI plumbing


def _tree(root: Path) -> dict[str, bytes]:
    """Every file under ``root`` (hidden ones too) with its content."""
    return {
        str(p.relative_to(root)): p.read_bytes() for p in sorted(root.rglob("*")) if p.is_file()
    }


@pytest.fixture
def workdir(tmp_path, monkeypatch):
    """``S/precious.txt`` and ``S/sub/cfg.yaml``, with ``S`` the working directory."""
    s = tmp_path / "S"
    (s / "sub").mkdir(parents=True)
    (s / "precious.txt").write_text("precious")
    (s / "sub" / "cfg.yaml").write_text(FLAT.read_text())
    monkeypatch.chdir(s)
    return s


def test_force_replaces_only_run_directories(cli, workdir):
    (workdir / "configs").mkdir()
    (workdir / "configs" / "other.yaml").write_text("x")
    before = _tree(workdir.parent)
    cases = [
        (".", f"refusing to replace {workdir}: it is the working directory or one of its parents"),
        ("..", "it is the working directory or one of its parents"),
        ("sub", f"refusing to replace {workdir / 'sub'}: it holds {workdir / 'sub' / 'cfg.yaml'}"),
        (
            "configs",
            f"refusing to replace {workdir / 'configs'}: it is not a gcm run directory "
            "(no valid .gcm.json marker, which gcm writes into every run); choose another --out",
        ),
    ]
    for target, message in cases:
        for force in (["--force"], []):
            code, text, err = cli("run", "sub/cfg.yaml", "--out", target, *force, *QUICK)
            assert_one_line_error(code, err, message)
            assert text == ""
            assert _tree(workdir.parent) == before, (target, force)
    # an empty directory needs no --force; a previous run is replaced with it
    (workdir / "empty").mkdir()
    code, _, err = cli("run", "sub/cfg.yaml", "--out", "empty", "-q", *QUICK)
    assert code == 0, err
    code, _, err = cli("run", "sub/cfg.yaml", "--out", "empty", "-q", *QUICK)
    assert_one_line_error(code, err, "already exists", "pass --force (CLI) or force=True (Python)")
    code, _, err = cli("run", "sub/cfg.yaml", "--out", "empty", "--force", "-q", *QUICK)
    assert code == 0, err
    # the config.yaml of a run is re-runnable, but not into its own folder
    code, _, err = cli("run", "empty/config.yaml", "--out", "empty", "--force", "-q", *QUICK)
    assert_one_line_error(code, err, f"it holds {workdir / 'empty' / 'config.yaml'}")
    assert (workdir / "empty" / "config.yaml").is_file()
    assert sorted(p.name for p in workdir.iterdir()) == [
        "configs",
        "empty",
        "precious.txt",
        "sub",
    ]


def _free_port() -> int:
    import socket

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


PREFLIGHT_ERRORS = {
    "robot": (["robot.spec=kuka"], ["robot.spec: unknown robot 'kuka'", "valid: panda, ur5"]),
    "object_mesh": (
        ["object={shape: mesh, mesh: nope.stl}", "candidates.source=file", "candidates.path=g.npy"],
        ["object.mesh: mesh file not found:", "nope.stl"],
    ),
    "obstacle_mesh": (
        [
            "environment.obstacles=[{shape: box, dims: {size: [1, 1, 1]}},"
            " {shape: mesh, mesh: o.stl}]"
        ],
        ["environment.obstacles.1.mesh: mesh file not found:", "o.stl"],
    ),
    "grasp_file": (
        ["candidates={source: file, path: missing.npy}"],
        ["candidates.path: grasp file not found:", "missing.npy"],
    ),
    "zmq_url": (["publish.zmq_url=notaurl"], ["publish.zmq_url: expected tcp://HOST:PORT"]),
    "dead_server": (
        ["publish.zmq_url=tcp://127.0.0.1:{port}", "publish.meshcat=true"],
        ["publish.zmq_url: meshcat server at tcp://127.0.0.1:", "did not answer"],
    ),
}


@pytest.mark.parametrize("name", sorted(PREFLIGHT_ERRORS))
def test_validate_and_run_reject_the_same_configs(cli, tmp_path, out, monkeypatch, name):
    from gcm_pipeline import pipeline

    def boom(cfg):
        raise AssertionError("a stage ran")

    # `gcm validate` looks the step up on the package, `Pipeline.run` in its module
    for where in (pipeline, pipeline.run):
        monkeypatch.setattr(where, "generate_candidates", boom)
    np.save(tmp_path / "g.npy", _poses(3))
    cfg = tmp_path / "cfg.yaml"
    cfg.write_text(FLAT.read_text())
    overrides, fragments = PREFLIGHT_ERRORS[name]
    port = _free_port()
    sets = [a for o in overrides for a in ("--set", o.replace("{port}", str(port)))]
    sets += ["--set", "publish.connect_timeout_s=0.3"]
    code, text, err = cli("validate", cfg, *sets)
    assert_one_line_error(code, err, *fragments)
    assert text == ""
    code, text, err = cli("run", cfg, "--out", out, *sets, *QUICK)
    assert_one_line_error(code, err, *fragments)
    assert text == ""
    _nothing_left(out)


def test_meshcat_flag_probes_the_server_before_the_run(cli, tmp_path, out, monkeypatch):
    from gcm_pipeline import pipeline

    def boom(cfg):
        raise AssertionError("a stage ran")

    # `gcm validate` looks the step up on the package, `Pipeline.run` in its module
    for where in (pipeline, pipeline.run):
        monkeypatch.setattr(where, "generate_candidates", boom)
    url = f"tcp://127.0.0.1:{_free_port()}"
    code, _, err = cli(
        "run",
        FLAT,
        "--out",
        out,
        "--meshcat",
        "--no-wait",
        "--set",
        f"publish.zmq_url={url}",
        "--set",
        "publish.connect_timeout_s=0.3",
    )
    assert_one_line_error(code, err, f"publish.zmq_url: meshcat server at {url} did not answer")
    _nothing_left(out)


def test_zmq_url_without_the_viewer_warns_once(cli, out):
    url = f"tcp://127.0.0.1:{_free_port()}"
    code, _, err = cli("run", FLAT, "--out", out, "--set", f"publish.zmq_url={url}", *QUICK)
    assert code == 0, err
    warning = "publish.zmq_url is set but the live viewer is off; add --meshcat"
    assert err.count(warning) == 1, err
    code, _, err = cli("validate", FLAT, "--set", f"publish.zmq_url={url}")
    assert code == 0 and err.count(warning) == 1, err


def test_the_run_config_reproduces_the_run(cli, tmp_path, monkeypatch):
    monkeypatch.chdir(ROOT)
    a = tmp_path / "a"
    code, _, err = cli("run", "configs/from_file.yaml", "--out", a, "-q", *QUICK)
    assert code == 0, err
    saved = (a / "config.yaml").read_text()
    assert f"path: {ROOT / 'configs' / 'data' / 'mug_grasps.npy'}" in saved
    monkeypatch.chdir(tmp_path)
    code, _, err = cli("run", "a/config.yaml", "--out", "b", "-q")
    assert code == 0, err
    assert (tmp_path / "b" / "grasps.csv").read_bytes() == (a / "grasps.csv").read_bytes()
    assert (tmp_path / "b" / "config.yaml").read_text() == saved


def test_quiet_help_says_what_it_does(capsys):
    with pytest.raises(SystemExit):
        main(["run", "--help"])
    text = " ".join(capsys.readouterr().out.split())
    assert "gcm run prints only the run directory's path on stdout" in text


def test_counts_by_reason_and_the_verbose_reachability_line(cli, out):
    code, _, err = cli("run", ROOT / "configs" / "box.yaml", "--out", out, "-v", *QUICK)
    assert code == 0, err
    counts = json.loads((out / "summary.json").read_text())["counts"]
    assert sum(counts["dropped_by_reason"].values()) == counts["triangles_dropped"]
    assert set(counts["dropped_by_reason"]) <= {"edge_length", "edge_angle"}
    unreachable = counts["unreachable_by_reason"]
    assert sum(unreachable.values()) == counts["densified"] - counts["reachable"] > 0
    assert "" not in unreachable
    breakdown = ", ".join(f"{k} {v}" for k, v in unreachable.items())
    line = f"reachable {counts['reachable']}/{counts['densified']} (unreachable: {breakdown})"
    assert line in err
    code, text, err = cli("show", out, "--top", "1")
    assert code == 0, err
    assert "unreachable_by_reason (" in text


# ------------------------------------------------- hardening: rough edges of the CLI


def test_validate_prints_the_resolved_config_which_loads_again(cli, tmp_path):
    code, text, err = cli("validate", FLAT, "--set", "densify.subdivisions=3")
    assert code == 0, err
    assert text.startswith(f"# {FLAT}: ok\n")
    resolved = tmp_path / "resolved.yaml"
    resolved.write_text(text)
    from gcm_pipeline.config import load_config

    again = load_config(resolved)
    assert again == load_config(FLAT, ["densify.subdivisions=3"])
    assert "position_tolerance: 0.0001" in text  # defaults filled in


def test_a_closed_pipe_is_not_a_traceback():
    """``gcm schema | head -1``: the reader leaves before gcm writes."""
    proc = subprocess.Popen(
        [sys.executable, "-m", "gcm_pipeline", "schema"],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        env=gcm_env(),
    )
    proc.stdout.close()  # before the interpreter has even started
    err = proc.stderr.read().decode()
    assert proc.wait(timeout=60) == 141
    assert err == ""


def test_default_output_dir_is_named_after_the_config(cli, tmp_path, monkeypatch):
    cfg = tmp_path / "cfgs" / "my_plane.yaml"
    cfg.parent.mkdir()
    cfg.write_text(FLAT.read_text().replace("output:", "# output:"))
    monkeypatch.chdir(tmp_path)
    code, text, err = cli("run", cfg, "-q", *QUICK)
    assert code == 0, err
    assert text.strip() == str(tmp_path / "cfgs" / "results" / "my_plane")
    assert (tmp_path / "cfgs" / "results" / "my_plane" / "grasps.csv").is_file()


def test_live_viewer_hint_repeats_the_overrides(cli, out):
    code, text, err = cli("run", FLAT, "--out", out, "--set", "densify.subdivisions=3", *QUICK)
    assert code == 0, err
    (hint,) = [ln for ln in text.splitlines() if ln.startswith("live viewer:")]
    import shlex

    words = shlex.split(hint.partition(":")[2])
    assert words[:3] == ["gcm", "run", str(FLAT)]
    sets = [words[i + 1] for i, w in enumerate(words) if w == "--set"]
    assert sets == ["densify.subdivisions=3", "publish.html=false", "publish.plots=false"]
    assert words[-4:] == ["--meshcat", "--force", "--out", str(out)]


def test_show_top_zero_prints_only_the_counts(cli, out):
    code, _, err = cli("run", FLAT, "--out", out, *QUICK)
    assert code == 0, err
    code, text, err = cli("show", out, "--top", "0")
    assert code == 0, err
    assert "reachable" in text and "no reachable grasp" not in text and "grasps by" not in text


def test_validate_says_why_it_keeps_some_of_a_files_grasps(cli, tmp_path):
    np.savez(tmp_path / "g.npz", transforms=_poses(4), success=[1, 0, 1, 1])
    cfg = tmp_path / "cfg.yaml"
    cfg.write_text("candidates: {source: file, path: g.npz}\n")
    code, text, _ = cli("validate", cfg)
    assert code == 0
    assert ": 3 grasps (of 4 in the file: labelled successful)\n" in text
