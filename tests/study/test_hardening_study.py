"""Hostile input to studies, caches, run directories and signals: one line, exit 2, nothing lost.

The third adversarial pass: ``--address`` where no Ray cluster answers,
named pipes where files are expected, a study that refines forever, an
export over the run's own files, headers that promise terabytes, a full
file system, tampered study parts. Each case ends in one line ``error: ...``
and exit 2 (or 130/143 on a signal), never a hang, a traceback or a
half-written directory.
"""

from __future__ import annotations

import errno
import http.server
import json
import os
import signal
import socket
import subprocess
import sys
import threading
from pathlib import Path

import numpy as np
import pytest
import yaml
from helpers import BOTTLE, QUICK, ROOT, assert_one_line_error
from helpers import SMALL_STUDY as SMALL

from gcm_pipeline import interrupts
from gcm_pipeline.cli import main
from gcm_pipeline.study import Study
from gcm_pipeline.study.runner import EngineError, probe_address


def _study_file(tmp_path: Path, sweep: dict | None = None, **extra) -> Path:
    data = {"base": str(BOTTLE), "set": list(SMALL)}
    data["sweep"] = sweep or {"object_pose": {"x": [0.5]}}
    data.update(extra)
    path = tmp_path / "study.yaml"
    path.write_text(yaml.safe_dump(data, sort_keys=False))
    return path


# ------------------------------------------------------------------ --address


@pytest.fixture
def silent_port():
    """A port where the kernel accepts connections and nobody ever says a word."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        s.listen(16)
        yield s.getsockname()[1]


@pytest.fixture
def http_port():
    """A port where an HTTP/1 web server answers."""

    class Quiet(http.server.SimpleHTTPRequestHandler):
        def log_message(self, *args):
            pass

    server = http.server.ThreadingHTTPServer(("127.0.0.1", 0), Quiet)
    thread = threading.Thread(target=server.serve_forever, daemon=True)
    thread.start()
    try:
        yield server.server_address[1]
    finally:
        server.shutdown()
        server.server_close()


@pytest.mark.parametrize("server", ["silent_port", "http_port"])
def test_an_address_where_no_ray_listens_is_one_line(tmp_path, cli, request, server):
    """A silent socket or a web server: an error within seconds, not Ray retrying for minutes."""
    port = request.getfixturevalue(server)
    out = tmp_path / "out"
    code, _, err = cli(
        "study", _study_file(tmp_path), "--out", out, "--address", f"127.0.0.1:{port}"
    )
    why = "no HTTP/2 answer within 5 s" if server == "silent_port" else "does not speak HTTP/2"
    assert_one_line_error(
        code, err, f"--address 127.0.0.1:{port}: no Ray cluster answers there", why
    )
    assert not out.exists()


def test_sigterm_stops_the_address_probe(silent_port):
    """The probe waits on a socket in Python: SIGTERM ends it at once, as everywhere in gcm."""
    previous = interrupts.install()
    timer = threading.Timer(0.5, os.kill, (os.getpid(), signal.SIGTERM))
    try:
        timer.start()
        with pytest.raises(interrupts.Terminated):
            probe_address(f"127.0.0.1:{silent_port}", timeout=300)
    finally:
        timer.cancel()
        for sig, handler in previous.items():
            signal.signal(sig, handler)
        interrupts.clear()


@pytest.mark.parametrize("address", ["[::1:6379", "[::1", "ray://[fe80::1:10001", "http://h:1"])
def test_a_malformed_address_is_one_line(tmp_path, cli, address):
    code, _, err = cli(
        "study", _study_file(tmp_path), "--out", tmp_path / "out", "--address", address
    )
    assert_one_line_error(code, err, f"--address {address!r}: expected HOST:PORT")
    assert not (tmp_path / "out").exists()
    with pytest.raises(EngineError, match="expected HOST:PORT"):
        probe_address(address)


# ------------------------------------------------------------------ study directories


@pytest.fixture(scope="module")
def finished_study(tmp_path_factory):
    """A finished two-placement study (inline engine, with best/): (study file, directory)."""
    folder = tmp_path_factory.mktemp("study")
    path = _study_file(folder, {"object_pose": {"x": [0.45, 0.5]}})
    out = folder / "out"
    Study.from_yaml(path).run(out, engine="inline", progress=False, best_run=True)
    return path, out


def _copy_study(finished, tmp_path):
    import shutil

    path, out = finished
    copy = tmp_path / "copy"
    shutil.copytree(out, copy, symlinks=True)
    return path, copy


def _edit_part(study_dir: Path, pid: int, **changes) -> None:
    part = study_dir / "placements" / f"{pid:06d}.npz"
    with np.load(part) as z:
        data = {k: z[k] for k in z.files}
    row = json.loads(str(data["row"]))
    for key, value in changes.items():
        row[key] = value(row[key]) if callable(value) else value
    data["row"] = np.array(json.dumps(row))
    with open(part, "wb") as fh:
        np.savez(fh, **data)


def _finishes(fn, *args, seconds=120.0):
    """Run ``fn`` in a thread; return its result, or fail when it is still blocked."""
    box: dict = {}

    def target():
        try:
            box["value"] = fn(*args)
        except BaseException as exc:  # handed to the test
            box["error"] = exc

    thread = threading.Thread(target=target, daemon=True)
    thread.start()
    thread.join(seconds)
    assert not thread.is_alive(), f"{fn.__name__} is blocked"
    if "error" in box:
        raise box["error"]
    return box.get("value")


def _unblock(fifo: Path) -> None:
    """Open a named pipe for writing once, so a reader blocked on it (a failing test) goes on."""
    try:
        os.close(os.open(fifo, os.O_WRONLY | os.O_NONBLOCK))
    except OSError:
        pass


def test_a_placement_file_that_is_a_named_pipe_runs_again(finished_study, tmp_path, caplog):
    path, out = _copy_study(finished_study, tmp_path)
    part = out / "placements" / "000001.npz"
    part.unlink()
    os.mkfifo(part)
    try:
        result = _finishes(
            lambda: Study.from_yaml(path).run(out, engine="inline", progress=False, best_run=False)
        )
    finally:
        _unblock(part)
    assert result.complete and len(result.rows) == 2 and not result.failed
    assert part.is_file() and not part.is_fifo()  # written again, whole
    assert f"ignoring {part}" in caplog.text and "not a regular file" in caplog.text


@pytest.mark.parametrize(
    "edit, why",
    [
        ({"round": "first"}, "round 'first' is not a whole number"),
        ({"overrides": 5}, "overrides '5' is not a list of KEY=VALUE strings"),
        (
            {"overrides": lambda o: [x.replace("approach.steps=4", "approach.steps=9") for x in o]},
            "overrides: approach.steps is 'approach.steps=9', the plan's 'approach.steps=4'",
        ),
    ],
    ids=["round-text", "overrides-number", "overrides-tampered"],
)
def test_a_tampered_placement_file_runs_again(finished_study, tmp_path, caplog, edit, why):
    """Never a traceback, and best/ never runs overrides the study did not plan."""
    path, out = _copy_study(finished_study, tmp_path)
    before = json.loads((out / "summary.json").read_text())["best"]
    for pid in (0, 1):
        _edit_part(out, pid, **edit)
    result = Study.from_yaml(path).run(out, engine="inline", progress=False, best_run=True)
    assert result.complete and len(result.rows) == 2 and not result.failed
    for pid in (0, 1):
        assert f"ignoring {out / 'placements' / f'{pid:06d}.npz'}" in caplog.text
    assert why in caplog.text
    assert result.best["overrides"] == before["overrides"]
    assert yaml.safe_load((out / "best" / "config.yaml").read_text())["approach"]["steps"] == 4
    rows = (out / "placements.csv").read_text()
    assert "approach.steps=9" not in rows


@pytest.mark.parametrize("name", ["placements.csv", "summary.json", "coverage.png"])
def test_a_study_output_that_is_a_directory_is_one_line_before_any_work(
    finished_study, tmp_path, cli, name
):
    path, out = _copy_study(finished_study, tmp_path)
    (out / name).unlink()
    (out / name).mkdir()
    before = sorted(p.name for p in out.rglob("*"))
    code, _, err = cli("study", path, "--out", out)
    assert_one_line_error(code, err, f"{out / name} is a directory", f"writes its {name} there")
    assert sorted(p.name for p in out.rglob("*")) == before


def test_a_huge_study_json_is_refused_before_it_is_read(finished_study, tmp_path, cli):
    """A sparse 3 GiB study.json: one line with the bound, nothing read into memory."""
    path, out = _copy_study(finished_study, tmp_path)
    with open(out / "study.json", "r+b") as fh:
        fh.truncate(3 * 1024**3)
    code, _, err = cli("study", path, "--out", out)
    assert_one_line_error(code, err, f"{out / 'study.json'} is 3,221,225,472 bytes", "16,777,216")
    assert (out / "study.json").stat().st_size == 3 * 1024**3  # left alone


def test_a_study_json_that_is_a_named_pipe_is_one_line(finished_study, tmp_path, cli):
    path, out = _copy_study(finished_study, tmp_path)
    (out / "study.json").unlink()
    os.mkfifo(out / "study.json")
    try:
        code, _, err = _finishes(cli, "study", path, "--out", out)
    finally:
        _unblock(out / "study.json")
    assert_one_line_error(code, err, f"{out / 'study.json'} is not a regular file")


# ------------------------------------------------------------------ refinement


def test_refinement_rounds_that_add_nothing_cost_nothing(tmp_path, capsys):
    """refine.rounds: 999998 on a one-placement grid: 1 placement, no --force, at once."""
    path = _study_file(
        tmp_path,
        {"object_pose": {"x": {"from": 0.5, "to": 0.5, "steps": 1}}},
        refine={"rounds": 999998},
    )
    study = Study.from_yaml(path)
    assert study.size() == (1, 0)
    result = study.run(tmp_path / "out", engine="inline", progress=False, best_run=False)
    assert result.complete and len(result.rows) == 1
    assert result.summary["counts"]["rounds"] == 1


def test_refinement_stops_exactly_where_rounds_stop_adding():
    """Past refine_rounds() every round's values round to the best placement's own."""
    study = Study.from_dict(
        {
            "base": str(BOTTLE),
            "sweep": {"object_pose": {"x": {"from": 0.3, "to": 0.7, "steps": 3}}},
            "refine": {"rounds": 999998, "shrink": 0.5},
        }
    )
    plan = study.plan
    last = plan.refine_rounds()
    assert 30 <= last <= 40  # 0.4 m * 0.5**r >= 1e-10 m: r <= 31.9
    assert study.size() == (3, last * 3)
    placements = plan.grid()
    best = {0: placements[1]}
    added = 0
    for rnd in range(1, last + 6):
        more = plan.refined(rnd, best, placements)
        placements += more
        if rnd > last:
            assert more == [], rnd
        added += len(more)
    assert added > 0


# ------------------------------------------------------------------ the mesh cache


@pytest.fixture
def panda_mesh(tmp_path, monkeypatch, panda):
    """One of the Panda's visual meshes, simplified once into an empty cache: (mesh, entry)."""
    from gcm_pipeline.outputs import robot_view

    path = next(o.meshPath for o in panda.build_geometry("visual").geometryObjects if o.meshPath)
    monkeypatch.setenv("GCM_CACHE_DIR", str(tmp_path / "cache"))
    robot_view._simplified_mesh_cached.cache_clear()
    first = robot_view._simplified_mesh(path)
    (entry,) = (tmp_path / "cache" / "meshes").iterdir()
    robot_view._simplified_mesh_cached.cache_clear()
    yield path, entry, [len(m.faces) for _, m in first]
    robot_view._simplified_mesh_cached.cache_clear()


def _npy(arr: np.ndarray) -> bytes:
    import io as _io

    buf = _io.BytesIO()
    np.save(buf, arr)
    return buf.getvalue()


def test_a_mesh_cache_entry_that_is_a_named_pipe_is_simplified_again(panda_mesh):
    from gcm_pipeline.outputs import robot_view

    path, entry, faces = panda_mesh
    entry.unlink()
    os.mkfifo(entry)
    try:
        assert _finishes(robot_view._read_mesh_cache, entry) is None
        again = _finishes(robot_view._simplified_mesh, path)
    finally:
        _unblock(entry)
    assert [len(m.faces) for _, m in again] == faces
    assert entry.is_file() and robot_view._read_mesh_cache(entry) is not None  # replaced, whole


def test_a_mesh_cache_header_claiming_a_terabyte_allocates_nothing(panda_mesh):
    """v0's header claims 1e11 x 3 float32 (1.2 TB) in a 2 kB file: the entry is rebuilt."""
    import zipfile

    import numpy.lib.format as npf

    from gcm_pipeline.outputs import robot_view

    path, entry, faces = panda_mesh
    import io as _io

    header = _io.BytesIO()
    npf.write_array_header_1_0(
        header, {"descr": "<f4", "fortran_order": False, "shape": (10**11, 3)}
    )
    with zipfile.ZipFile(entry, "w") as zf:
        zf.writestr("colors.npy", _npy(np.array([0xFF0000], np.int64)))
        zf.writestr("v0.npy", header.getvalue() + bytes(1200))
        zf.writestr("f0.npy", _npy(np.zeros((1, 3), np.uint32)))
    assert entry.stat().st_size < 4096
    assert robot_view._read_mesh_cache(entry) is None
    assert [len(m.faces) for _, m in robot_view._simplified_mesh(path)] == faces


# ------------------------------------------------------------------ export


@pytest.fixture(scope="module")
def run_with_branches(tmp_path_factory):
    """A run with ik.solutions: 3 (so it has solutions.npz)."""
    out = tmp_path_factory.mktemp("run") / "run"
    sets = [a for s in SMALL for a in ("--set", s)] + ["--set", "ik.solutions=3"]
    assert main(["run", str(BOTTLE), "--out", str(out), "-q", *sets]) == 0
    assert (out / "solutions.npz").is_file()
    return out


def test_export_never_overwrites_the_runs_solutions_npz(run_with_branches, tmp_path, cli):
    import shutil

    run = tmp_path / "run"
    shutil.copytree(run_with_branches, run)
    other = tmp_path / "other"
    shutil.copytree(run_with_branches, other)
    link = tmp_path / "link.npz"
    link.symlink_to(run / "solutions.npz")
    before = {p: p.read_bytes() for d in (run, other) for p in d.iterdir()}
    for out in (run / "solutions.npz", link, other / "solutions.npz", other / "grasps.csv"):
        code, _, err = cli("export", run, "--format", "npz", "--out", out)
        assert_one_line_error(code, err, "would overwrite", "choose another file")
    assert {p: p.read_bytes() for d in (run, other) for p in d.iterdir()} == before
    # the default name, and a new file beside the run's own ones, are fine
    assert cli("export", run, "--format", "npz")[0] == 0
    assert cli("export", run, "--format", "npz", "--out", run / "mine.npz")[0] == 0


def test_export_never_overwrites_a_studys_files(finished_study, tmp_path, cli):
    _, study = _copy_study(finished_study, tmp_path)
    run = study / "best"
    before = {p: p.read_bytes() for p in study.rglob("*") if p.is_file()}
    for out in (
        study / "placements.csv",
        study / "study.json",
        study / "placements" / "000000.npz",
    ):
        code, _, err = cli("export", run, "--format", "npz", "--out", out)
        assert_one_line_error(code, err, "would overwrite")
    assert {p: p.read_bytes() for p in study.rglob("*") if p.is_file()} == before


# ------------------------------------------------------------------ a full file system


@pytest.fixture
def tiny_tmpfs(tmp_path):
    """A 200 kB tmpfs (root only); skipped where mounting is not permitted."""
    where = tmp_path / "full"
    where.mkdir()
    proc = subprocess.run(
        ["mount", "-t", "tmpfs", "-o", "size=200k", "tmpfs", str(where)],
        capture_output=True,
        text=True,
        check=False,
    )
    if proc.returncode != 0:
        pytest.skip(f"cannot mount a tmpfs here: {proc.stderr.strip() or proc.returncode}")
    try:
        yield where
    finally:
        subprocess.run(["umount", str(where)], check=False)


def test_gcm_run_on_a_full_file_system_is_one_line(tiny_tmpfs, cli):
    """The bottle's grasps.csv does not fit in 200 kB: ENOSPC named, no directory left."""
    out = tiny_tmpfs / "run"
    code, _, err = cli("run", BOTTLE, "--out", out, "-q", *QUICK)
    assert_one_line_error(code, err, f"cannot write {out}: No space left on device (ENOSPC)")
    assert list(tiny_tmpfs.iterdir()) == []


def test_disk_full_while_writing_is_one_line_in_process(tmp_path, cli, monkeypatch):
    from gcm_pipeline.rundir import run as run_files

    def full(*args, **kwargs):
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

    monkeypatch.setattr(run_files, "write_grasps_csv", full)
    out = tmp_path / "run"
    sets = [a for s in SMALL for a in ("--set", s)]
    code, _, err = cli("run", BOTTLE, "--out", out, "-q", *sets)
    assert_one_line_error(code, err, f"cannot write {out}: No space left on device (ENOSPC)")
    assert list(tmp_path.iterdir()) == []


def test_a_study_on_a_full_file_system_is_one_line(tmp_path, monkeypatch):
    """write_coverage_png on a full disk: OutputError naming coverage.png; placements kept."""
    from gcm_pipeline.errors import OutputError
    from gcm_pipeline.study import coverage

    def full(rows, swept, path, **kwargs):
        Path(path).write_bytes(b"\x89PNG")
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

    monkeypatch.setattr(coverage, "write_coverage_png", full)
    path = _study_file(tmp_path)
    out = tmp_path / "out"
    with pytest.raises(OutputError) as info:
        Study.from_yaml(path).run(out, engine="inline", progress=False, best_run=False)
    assert str(info.value).startswith(f"cannot write {out / 'coverage.png'}: No space left")
    assert "(ENOSPC)" in str(info.value)
    assert not (out / "coverage.png").exists()
    assert [p.name for p in out.iterdir() if p.name.startswith(".coverage")] == []
    assert (out / "placements" / "000000.npz").is_file()  # a rerun resumes


def test_gcm_study_on_a_full_file_system_is_one_line(tiny_tmpfs, tmp_path, capsys):
    """``gcm study`` in a subprocess, placements inline (the CLI without Ray's start-up)."""
    path = _study_file(tmp_path, {"object_pose": {"x": [0.45, 0.5]}})
    out = tiny_tmpfs / "study"
    # fill the file system so that the placements fit and the coverage plot does not
    code = (
        "import sys\n"
        "from gcm_pipeline.study import runner\n"
        "runner.RayExecutor = lambda workers, address, warm, **_: runner.InlineExecutor(warm)\n"
        "from gcm_pipeline.cli import main\n"
        f"sys.exit(main(['study', {str(path)!r}, '--out', {str(out)!r}, '-q', '--no-best']))\n"
    )
    filler = tiny_tmpfs / "filler"
    filler.write_bytes(bytes(150_000))
    proc = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, timeout=600, cwd=ROOT
    )
    lines = [ln for ln in proc.stderr.strip().splitlines() if not ln.startswith("WARNING")]
    assert proc.returncode == 2, proc.stderr[-3000:]
    assert len(lines) == 1 and "No space left on device (ENOSPC)" in lines[0], proc.stderr
    assert lines[0].startswith(f"error: cannot write {out}")
    assert not [p for p in out.rglob(".*tmp*")]  # no temporary file left


# ------------------------------------------------------------------ signals while Ray joins


def test_a_held_interrupt_is_raised_after_its_grace():
    """interrupts.held(grace): SIGTERM waits at most ``grace`` seconds, then cuts the block."""
    import time

    previous = interrupts.install()
    try:
        with pytest.raises(interrupts.Terminated):
            with interrupts.held(0.2) as got:
                os.kill(os.getpid(), signal.SIGTERM)
                for _ in range(600):  # 60 s at most: the interrupt ends it long before
                    time.sleep(0.1)
        assert got == [signal.SIGTERM]
        with interrupts.held() as got:  # no grace: held to the end of the block
            os.kill(os.getpid(), signal.SIGTERM)
            time.sleep(0.5)
        assert got == [signal.SIGTERM]
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)
        interrupts.clear()


def test_sigterm_while_ray_joins_a_silent_address_exits_143(tmp_path, silent_port):
    """ray.init retrying an address that never answers (probe bypassed) still honours SIGTERM."""
    path = _study_file(tmp_path)
    out = tmp_path / "out"
    code = (
        "import sys\n"
        "from gcm_pipeline.study import runner\n"
        "runner.probe_address = lambda address, timeout=5.0: None\n"
        "from gcm_pipeline.cli import main\n"
        f"sys.exit(main(['study', {str(path)!r}, '--out', {str(out)!r}, '-q',"
        f" '--address', '127.0.0.1:{silent_port}']))\n"
    )
    env = dict(os.environ, RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER="0")
    proc = subprocess.Popen(
        [sys.executable, "-c", code], stderr=subprocess.PIPE, text=True, cwd=ROOT, env=env
    )
    seen = []
    try:
        for line in proc.stderr:  # Ray's driver logs its first failed attempt
            seen.append(line)
            if "127.0.0.1:" in line and "GCS" in line:
                break
        proc.send_signal(signal.SIGTERM)
        rest = proc.communicate(timeout=300)[1]
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate()
    assert proc.returncode == 143, "".join(seen)[-2000:] + rest[-2000:]
    assert rest.strip().splitlines()[-1] == "interrupted (SIGTERM)"
    assert "Traceback" not in rest
    assert not out.exists()
