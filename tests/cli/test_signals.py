"""Signals stop a ``gcm run`` cleanly: one line, no traceback, nothing half-written.

Each test starts a real ``gcm run`` in its own process group and signals it
as a terminal (Ctrl-C, hang-up) or a process manager (SIGTERM) would, at a
moment it can observe: IK worker processes running, or the temporary run
directory being written. The rule for any IK engine: with ``ik.workers: 2``
a Ctrl-C ends the run with ``interrupted`` and exit status 130, and no
worker prints a traceback.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from helpers import BOTTLE, FLAT, QUICK, ROOT, gcm_env


def _start(config: Path, out: Path, *sets: str, force: bool = False) -> subprocess.Popen:
    args = [sys.executable, "-m", "gcm_pipeline", "run", str(config), "--out", str(out)]
    for s in sets:
        args += ["--set", s]
    return subprocess.Popen(
        [*args, *(["--force"] if force else [])],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        start_new_session=True,  # its own process group, like a shell job
        cwd=out.parent,
        env=gcm_env(),
    )


def _children(pid: int) -> list[int]:
    try:
        text = Path(f"/proc/{pid}/task/{pid}/children").read_text()
    except OSError:
        return []
    return [int(p) for p in text.split()]


def _wait_for(condition, proc: subprocess.Popen, timeout: float = 90.0) -> None:
    t0 = time.monotonic()
    while not condition():
        if proc.poll() is not None:
            out, err = proc.communicate()
            pytest.fail(f"gcm ended before the signal (status {proc.returncode}): {err}")
        if time.monotonic() - t0 > timeout:
            os.killpg(proc.pid, signal.SIGKILL)
            pytest.fail("the moment to signal never came")
        time.sleep(0.01)


def _finish(proc: subprocess.Popen) -> tuple[int, list[str]]:
    try:
        _, err = proc.communicate(timeout=60)
    except subprocess.TimeoutExpired:
        os.killpg(proc.pid, signal.SIGKILL)
        proc.communicate()
        pytest.fail("gcm did not stop after the signal")
    return proc.returncode, err.strip().splitlines()


@pytest.mark.skipif(not Path("/proc/self/task").is_dir(), reason="needs /proc (Linux)")
def test_ctrl_c_with_two_ik_workers_is_one_line(tmp_path):
    out = tmp_path / "run"
    proc = _start(BOTTLE, out, "densify.subdivisions=12", "ik.workers=2", "publish.html=false")
    _wait_for(lambda: len(_children(proc.pid)) >= 2, proc)  # the workers are solving
    time.sleep(0.3)
    os.killpg(proc.pid, signal.SIGINT)  # the whole group, as a terminal's Ctrl-C does
    status, lines = _finish(proc)
    assert status == 130, lines
    assert lines == ["interrupted"]
    assert list(tmp_path.iterdir()) == []


@pytest.mark.skipif(not Path("/proc/self/task").is_dir(), reason="needs /proc (Linux)")
def test_a_killed_worker_ends_the_run_with_one_line(tmp_path):
    # what the out-of-memory killer does to one worker: the run must not wait for ever
    out = tmp_path / "run"
    proc = _start(BOTTLE, out, "densify.subdivisions=12", "ik.workers=2", "publish.html=false")
    _wait_for(lambda: len(_children(proc.pid)) >= 2, proc)
    time.sleep(0.3)
    os.kill(_children(proc.pid)[0], signal.SIGKILL)
    status, lines = _finish(proc)
    assert status == 1, lines
    assert len(lines) == 1 and lines[0].startswith("error: worker process "), lines
    assert "killed by SIGKILL" in lines[0] and "memory" in lines[0]
    assert list(tmp_path.iterdir()) == []


def test_sigterm_while_writing_leaves_the_previous_run(cli, tmp_path):
    sig = "SIGTERM"
    out = tmp_path / "run"
    assert cli("run", FLAT, "--out", out, "-q", *QUICK)[0] == 0
    before = {p.name: p.read_bytes() for p in out.iterdir()}
    proc = _start(FLAT, out, "densify.subdivisions=12", force=True)
    _wait_for(lambda: any(p.name.startswith(".run.tmp-") for p in tmp_path.iterdir()), proc)
    time.sleep(0.2)  # the html scene and plots are being written
    os.killpg(proc.pid, getattr(signal, sig))
    status, lines = _finish(proc)
    assert status == 128 + getattr(signal, sig), lines
    assert lines == [f"interrupted ({sig})"]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["run"]  # no .tmp-*, no .old-*
    assert {p.name: p.read_bytes() for p in out.iterdir()} == before


def test_sighup_in_process_unwinds_like_ctrl_c(cli, tmp_path, monkeypatch):
    """``gcm`` turns SIGHUP (and SIGTERM) into an interrupt of the main thread."""
    from gcm_pipeline.rundir import run as run_files

    written = run_files.write_run_files

    def hang_up(out_dir, *args, **kwargs):
        written(out_dir, *args, **kwargs)
        os.kill(os.getpid(), signal.SIGHUP)
        time.sleep(5)  # the handler raises long before this ends

    monkeypatch.setattr(run_files, "write_run_files", hang_up)
    before = signal.getsignal(signal.SIGHUP)
    out = tmp_path / "run"
    status, _, err = cli("run", FLAT, "--out", out, "--set", "publish.html=false")
    assert status == 128 + signal.SIGHUP
    assert err.strip().splitlines() == ["interrupted (SIGHUP)"]
    assert list(tmp_path.iterdir()) == []
    assert signal.getsignal(signal.SIGHUP) == before  # handlers restored


def _interrupted_rerun(cli, tmp_path, monkeypatch, write_run_files):
    """A complete run, then ``--force`` over it with ``write_run_files`` patched to get
    interrupted: one line, status 130, the first run kept as it was."""
    from gcm_pipeline.rundir import run as run_files

    out = tmp_path / "run"
    assert cli("run", FLAT, "--out", out, "-q", *QUICK)[0] == 0
    before = {p.name: p.read_bytes() for p in out.iterdir()}
    monkeypatch.setattr(run_files, "write_run_files", write_run_files)
    code, _, err = cli("run", FLAT, "--out", out, "--force", *QUICK)
    assert code == 130
    assert err.strip().splitlines() == ["interrupted"]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["run"]
    assert {p.name: p.read_bytes() for p in out.iterdir()} == before
    return out


def test_an_interrupt_wrapped_by_a_library_is_still_one_line(cli, tmp_path, monkeypatch):
    """pydantic turns a Ctrl-C that arrives while it serialises a config into an error
    of its own, caused by the KeyboardInterrupt: ``gcm`` still says ``interrupted``
    (status 130), keeps the previous run, and ``gcm study`` says what it kept (if any)."""
    from pydantic import BaseModel, field_serializer

    from gcm_pipeline.rundir import run as run_files
    from gcm_pipeline.study import Study

    class Slow(BaseModel):
        x: int = 0

        @field_serializer("x")
        def _ser(self, value: int) -> int:
            raise KeyboardInterrupt  # the signal lands inside the serialiser

    def wrapped(*args, **kwargs):
        Slow().model_dump()  # raises pydantic's error, caused by the interrupt

    out = _interrupted_rerun(cli, tmp_path, monkeypatch, wrapped)

    monkeypatch.setattr(Study, "run", lambda self, *a, **k: wrapped())
    study = ROOT / "configs" / "studies" / "bottle_placement.yaml"
    code, _, err = cli("study", study, "--out", tmp_path / "study", "-q")
    assert code == 130
    assert err == "interrupted\n"  # nothing finished: nothing kept
    (tmp_path / "study" / "placements").mkdir(parents=True)
    (tmp_path / "study" / "placements" / "000000.npz").write_bytes(b"")
    code, _, err = cli("study", study, "--out", tmp_path / "study", "-q")
    assert code == 130
    err = err.strip().splitlines()
    assert err[-1] == "interrupted" and "finished placements are kept" in err[0]
    # an error that is not an interrupt still shows as one
    monkeypatch.setattr(run_files, "write_run_files", lambda *a, **k: 1 / 0)
    with pytest.raises(ZeroDivisionError):
        cli("run", FLAT, "--out", out, "--force", *QUICK)


def test_an_interrupt_python_drops_still_stops_the_run(cli, tmp_path, monkeypatch):
    """An interrupt raised inside a finaliser is dropped by Python ("Exception
    ignored"): the run would go on and replace the previous one. The handler recorded
    it, so the swap does not happen: one line, status 130, the previous run kept."""
    from gcm_pipeline import Pipeline, interrupts, load_config
    from gcm_pipeline.rundir import run as run_files

    class Finalised:
        def __del__(self) -> None:
            interrupts.raise_interrupt(signal.SIGINT)  # as if Ctrl-C landed in here

    written = run_files.write_run_files

    def dropped(*args, **kwargs):
        Finalised()  # collected at once: the interrupt is raised and dropped
        return written(*args, **kwargs)

    out = _interrupted_rerun(cli, tmp_path, monkeypatch, dropped)
    # the handled interrupt does not outlive the command: the Python API and the next
    # command write their runs
    monkeypatch.setattr(run_files, "write_run_files", written)
    cfg = load_config(FLAT, ["publish.html=false", "publish.plots=false"])
    Pipeline(cfg).run(out_dir=tmp_path / "api", progress=False)
    assert (tmp_path / "api" / "summary.json").is_file()
    assert cli("run", FLAT, "--out", out, "--force", "-q", *QUICK)[0] == 0


def test_gcm_answers_signals_while_it_loads_and_ignores_them_once_done(monkeypatch, capsys):
    """``python -m gcm_pipeline`` (and ``gcm``) handle the signals before the command
    line loads: an interrupt then is the same one line and status; after the command
    they are ignored while the process exits."""
    import types

    from gcm_pipeline import __main__ as entry_point
    from gcm_pipeline import interrupts

    class Loading(types.ModuleType):
        def __getattr__(self, name: str):
            os.kill(os.getpid(), signal.SIGTERM)  # arrives while the CLI loads
            time.sleep(5)

    saved = {s: signal.getsignal(s) for s in (signal.SIGINT, signal.SIGTERM, signal.SIGHUP)}
    try:
        monkeypatch.setitem(sys.modules, "gcm_pipeline.cli", Loading("gcm_pipeline.cli"))
        assert entry_point.entry() == 128 + signal.SIGTERM
        assert capsys.readouterr().err.strip().splitlines() == ["interrupted (SIGTERM)"]
        for s in saved:
            assert signal.getsignal(s) == signal.SIG_IGN
        interrupts.check()  # the handled interrupt is not raised again later
    finally:
        for s, handler in saved.items():
            signal.signal(s, handler)


@pytest.mark.skipif(not Path("/proc/self/task").is_dir(), reason="needs /proc (Linux)")
def test_sigterm_at_once_is_one_line(tmp_path):
    """A SIGTERM as soon as the interpreter has loaded this project's entry point."""
    probe = (
        "import os, signal, sys; sys.argv = ['gcm', 'run', sys.argv[1], '--out', sys.argv[2]]; "
        "from gcm_pipeline.__main__ import entry; "
        "import gcm_pipeline.interrupts as s; orig = s.install; "
        "s.install = lambda *a: (orig(*a), os.kill(os.getpid(), signal.SIGTERM))[0]; "
        "sys.exit(entry())"
    )
    proc = subprocess.run(
        [sys.executable, "-c", probe, str(FLAT), str(tmp_path / "run")],
        capture_output=True,
        text=True,
        timeout=120,
        env=gcm_env(),
    )
    assert proc.returncode == 128 + signal.SIGTERM, proc.stderr
    assert proc.stderr.strip().splitlines() == ["interrupted (SIGTERM)"]
    assert list(tmp_path.iterdir()) == []


@pytest.mark.skipif(not Path("/proc/self/task").is_dir(), reason="needs /proc (Linux)")
def test_sigterm_inside_the_neighbour_search_of_many_grasps_stops_at_once(tmp_path):
    """30,000 random grasps with wide bounds: the families' k-d tree search finds about 90
    million pairs. Done in one scipy call and one ``np.unique`` (seconds and minutes, during
    which Python does not act on a signal) a SIGTERM a second in waited about 10 s; in
    blocks of rows the run ends with its one line and status 143 at once, nothing left."""
    from scipy.spatial.transform import Rotation

    rng = np.random.default_rng(0)
    poses = np.zeros((30_000, 4, 4))
    poses[:, :3, :3] = Rotation.random(len(poses), random_state=1).as_matrix()
    poses[:, :3, 3] = rng.uniform(-0.05, 0.05, (len(poses), 3)) + (0.0, 0.0, 0.05)
    poses[:, 3, 3] = 1.0
    np.save(tmp_path / "grasps.npy", poses)
    config = tmp_path / "many.yaml"
    config.write_text(
        "robot: {spec: panda}\n"
        "object: {shape: cylinder, dims: {radius: 0.04, height: 0.1}, pose: {xyz: [0.45, 0, 0]}}\n"
        "candidates: {source: file, path: grasps.npy, format: npy, frame: object}\n"
        "manifold: {structure: families, max_edge_length: 0.1, max_edge_angle_deg: 60}\n"
        "publish: {html: false, plots: false}\n"
    )
    out = tmp_path / "out" / "run"
    out.parent.mkdir()
    scratch = tmp_path / "tmp"
    scratch.mkdir()
    proc = subprocess.Popen(
        [sys.executable, "-m", "gcm_pipeline", "run", str(config), "--out", str(out), "-v"],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
        text=True,
        start_new_session=True,
        env=gcm_env(TMPDIR=str(scratch)),
    )
    for line in proc.stderr:  # the log names each stage when it is done
        if "stage candidates" in line:
            break
    else:
        pytest.fail(f"the run ended before its manifold stage (status {proc.wait()})")
    time.sleep(1.0)  # the tree is built in milliseconds: this is inside its search
    assert proc.poll() is None
    t0 = time.monotonic()
    proc.send_signal(signal.SIGTERM)
    status, lines = _finish(proc)
    waited = time.monotonic() - t0
    assert status == 128 + signal.SIGTERM, lines
    assert lines[-1] == "interrupted (SIGTERM)"
    assert waited < 5.0, f"{waited:.1f} s from SIGTERM to exit"  # not a speed figure: was 10-200 s
    assert list(out.parent.iterdir()) == [] and list(scratch.iterdir()) == []


def test_sigterm_inside_the_clearance_against_a_cloud_leaves_nothing(cli, tmp_path, monkeypatch):
    """A cloud run spends its time in coal's distances of links to octree tiles (the
    clearance): a SIGTERM landing in one ends the run with its one line, nothing written."""
    from gcm_pipeline.robot.collision import clearance

    near = clearance.near_distance
    calls = []

    def terminated(*args, **kwargs):
        calls.append(1)
        os.kill(os.getpid(), signal.SIGTERM)
        return near(*args, **kwargs)  # the handler raises in this call or right after it

    monkeypatch.setattr(clearance, "near_distance", terminated)
    out = tmp_path / "run"
    status, _, err = cli("run", ROOT / "configs" / "clutter_scene.yaml", "--out", out, *QUICK)
    assert calls
    assert status == 128 + signal.SIGTERM
    assert err.strip().splitlines() == ["interrupted (SIGTERM)"]
    assert list(tmp_path.iterdir()) == []


def test_gcm_exits_without_a_last_collection_over_what_it_loaded(tmp_path):
    """At exit the interpreter's last garbage collection walks every object the command
    loaded (seconds after a big cloud's run, and after its interrupt); ``gcm`` freezes
    them first, so the process ends at once. Seen from an exit handler that runs after
    gcm's: the objects are frozen."""
    probe = (
        "import atexit, gc, sys; "
        "atexit.register(lambda: print('frozen', gc.get_freeze_count() > 0)); "
        "sys.argv = ['gcm', 'schema']; "
        "from gcm_pipeline.__main__ import entry; status = entry(); sys.exit(status)"
    )
    proc = subprocess.run(
        [sys.executable, "-c", probe],
        capture_output=True,
        text=True,
        timeout=120,
        env=gcm_env(),
        cwd=tmp_path,
    )
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.strip().splitlines()[-1] == "frozen True"
