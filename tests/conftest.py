"""Session set-up shared by the tests."""

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
