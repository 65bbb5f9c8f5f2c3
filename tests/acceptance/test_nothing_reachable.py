"""A run with nothing reachable completes: it warns, reads back, shows and plots."""

from __future__ import annotations

import numpy as np
from helpers import FLAT

from gcm_pipeline.rundir import run as run_files


def test_a_run_with_nothing_reachable_reads_shows_and_plots(cli, tmp_path):
    cfg = tmp_path / "far.yaml"
    cfg.write_text(FLAT.read_text().replace("xyz: [0.45, 0.0, 0.03]", "xyz: [2.5, 0.0, 0.03]"))
    out = tmp_path / "run"
    code, _, err = cli("run", cfg, "--out", out, "--set", "publish.html=false")
    assert code == 0, err
    assert "WARNING" in err and "no grasp is reachable (out_of_reach 66)" in err
    run = run_files.read_run(out)
    assert len(run.grasps) == 66 and not run.grasps["reachable"].any()
    assert np.isnan(run.grasps["pos_err"]).all()
    code, text, err = cli("show", out)
    assert code == 0, err
    assert "reachable 0" in text and "(no reachable grasp)" in text
    for png in out.glob("*.png"):
        png.unlink()
    code, text, err = cli("plot", out)
    assert code == 0, err
    assert len(list(out.glob("*.png"))) == 3
