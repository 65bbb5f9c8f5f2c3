"""A plot that cannot be written leaves no part of itself: ``gcm plot`` on a full disk.

A file size limit of 0 (``RLIMIT_FSIZE``, with ``SIGXFSZ`` ignored so a write
fails with ``EFBIG`` as one on a full disk fails with ``ENOSPC``) stops the
first PNG when its buffer is flushed (Pillow removes a file it created only
when the failure comes before that); the run directory must hold what it
held before, no empty ``manifold.png`` beside it.
"""

from __future__ import annotations

import shutil
import subprocess
import sys

from helpers import assert_one_line_error, gcm_env

_PLOT_UNDER_LIMIT = """
import resource, signal, sys
signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
resource.setrlimit(resource.RLIMIT_FSIZE, (0, 0))
from gcm_pipeline.cli import main
sys.exit(main(["plot", sys.argv[1]]))
"""


def test_a_plot_cut_short_leaves_no_file(tmp_path, flat_run):
    d = tmp_path / "run"
    shutil.copytree(flat_run, d)
    before = sorted(p.name for p in d.iterdir())
    assert "manifold.png" not in before  # the run was made without plots
    proc = subprocess.run(
        [sys.executable, "-c", _PLOT_UNDER_LIMIT, str(d)],
        capture_output=True,
        text=True,
        timeout=300,
        env=gcm_env(),
    )
    assert_one_line_error(proc.returncode, proc.stderr, "cannot write plot", "manifold.png")
    assert sorted(p.name for p in d.iterdir()) == before
