"""Fixtures shared by the tests (paths and assertions: ``helpers.py``, poses: ``poses.py``)."""

from __future__ import annotations

import subprocess
import sys
import tempfile

import pytest


@pytest.fixture(scope="session", autouse=True)
def _compiled_kernels_ready():
    """Compile (or read) the compiled kernels once, before any test runs.

    Both copies a test can import: this process's, and the one a subprocess
    started outside the repository imports (the installed package, when the
    tests run against a checkout). Otherwise the first test whose subprocess
    loads them would pay the compilation, and print its one-time notice, in
    the middle of what it checks.
    """
    from gcm_pipeline.robot import kernels

    kernels.get()
    with tempfile.TemporaryDirectory() as elsewhere:
        subprocess.run(
            [sys.executable, "-c", "from gcm_pipeline.robot import kernels; kernels.get()"],
            cwd=elsewhere,
            check=False,
            capture_output=True,
            timeout=600,
        )


@pytest.fixture(scope="session")
def panda():
    """The shipped Panda, loaded once for the session: tests read it, never change it.

    (A test that patches it does so with ``monkeypatch``, undone when it ends.)
    """
    from gcm_pipeline.config.robot_spec import load_robot

    return load_robot("panda")


@pytest.fixture(scope="session")
def flat_run(tmp_path_factory):
    """A finished ``gcm run`` of configs/flat_surface.yaml (``QUICK``: no scene, no plots).

    Shared by the session: tests read it; one that changes it copies it first.
    """
    from helpers import FLAT, QUICK

    from gcm_pipeline.cli import main

    out = tmp_path_factory.mktemp("flat") / "run"
    assert main(["run", str(FLAT), "--out", str(out), "-q", *QUICK]) == 0
    return out


@pytest.fixture
def cli(capsys):
    """``gcm ARGV`` in this process: ``cli(*argv) -> (exit code, stdout, stderr)``.

    Arguments are passed through ``str`` (paths welcome); the output captured so far
    in the test is read and cleared with each call.
    """
    from gcm_pipeline.cli import main

    def run(*argv: object) -> tuple[int, str, str]:
        code = main([str(a) for a in argv])
        out, err = capsys.readouterr()
        return code, out, err

    return run
