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

from gcm_pipeline import signals
from gcm_pipeline.cli import main
from gcm_pipeline.study import Study
from gcm_pipeline.study.runner import EngineError, probe_address

ROOT = Path(__file__).resolve().parents[1]
BOTTLE = ROOT / "configs" / "bottle_side.yaml"
#: A small bottle: 45 grasps, about 0.4 s per placement (as in test_study.py).
SMALL = [
    "candidates.count=18",
    "manifold.max_edge_length=0.15",
    "densify.subdivisions=2",
    "approach.steps=4",
    "publish.html=false",
    "publish.plots=false",
]
QUICK = ["--set", "publish.html=false", "--set", "publish.plots=false"]


def _cli(capsys, *argv):
    code = main([str(a) for a in argv])
    out, err = capsys.readouterr()
    return code, out, err


def _one_line_error(code, err, *fragments):
    lines = [ln for ln in err.strip().splitlines() if not ln.startswith("WARNING")]
    assert code == 2, err
    assert len(lines) == 1 and lines[0].startswith("error: "), err
    for f in fragments:
        assert f in lines[0], (f, lines[0])


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
def test_an_address_where_no_ray_listens_is_one_line(tmp_path, capsys, request, server):
    """A silent socket or a web server: an error within seconds, not Ray retrying for minutes."""
    port = request.getfixturevalue(server)
    out = tmp_path / "out"
    code, _, err = _cli(
        capsys, "study", _study_file(tmp_path), "--out", out, "--address", f"127.0.0.1:{port}"
    )
    why = "no HTTP/2 answer within 5 s" if server == "silent_port" else "does not speak HTTP/2"
    _one_line_error(code, err, f"--address 127.0.0.1:{port}: no Ray cluster answers there", why)
    assert not out.exists()


def test_sigterm_stops_the_address_probe(silent_port):
    """The probe waits on a socket in Python: SIGTERM ends it at once, as everywhere in gcm."""
    previous = signals.install()
    timer = threading.Timer(0.5, os.kill, (os.getpid(), signal.SIGTERM))
    try:
        timer.start()
        with pytest.raises(signals.Terminated):
            probe_address(f"127.0.0.1:{silent_port}", timeout=300)
    finally:
        timer.cancel()
        for sig, handler in previous.items():
            signal.signal(sig, handler)
        signals.clear()


@pytest.mark.parametrize("address", ["[::1:6379", "[::1", "ray://[fe80::1:10001", "http://h:1"])
def test_a_malformed_address_is_one_line(tmp_path, capsys, address):
    code, _, err = _cli(
        capsys, "study", _study_file(tmp_path), "--out", tmp_path / "out", "--address", address
    )
    _one_line_error(code, err, f"--address {address!r}: expected HOST:PORT")
    assert not (tmp_path / "out").exists()
    with pytest.raises(EngineError, match="expected HOST:PORT"):
        probe_address(address)
