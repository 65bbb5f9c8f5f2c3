"""The preflight checks of a config's files run before anything is written or replaced."""

from __future__ import annotations

import pytest
from helpers import FLAT, QUICK, ROOT, assert_one_line_error

from gcm_pipeline.cli import main
from gcm_pipeline.config import load_config
from gcm_pipeline.errors import InputError
from gcm_pipeline.pipeline import preflight


def test_a_bad_spec_is_reported_before_the_existing_output(cli, tmp_path):
    code, _, err = cli("run", FLAT, "--out", tmp_path / "run", "-q", *QUICK)
    assert code == 0, err
    code, _, err = cli("run", FLAT, "--out", tmp_path / "run", "--set", "robot.spec=pandaa", *QUICK)
    assert_one_line_error(code, err, "robot.spec: unknown robot 'pandaa'")
    assert "--force" not in err


def test_a_mesh_with_nan_vertices_is_refused(tmp_path, capfd):
    (tmp_path / "m.obj").write_text(
        "v 0 0 0\nv 1 0 0\nv 0 nan 0\nv 0 0 1\nf 1 2 3\nf 1 3 4\nf 1 2 4\nf 2 3 4\n"
    )
    cfg = tmp_path / "cfg.yaml"
    cfg.write_text(
        FLAT.read_text().replace(
            "environment: {table: {height: 0.0}}",
            "environment: {obstacles: [{shape: mesh, mesh: m.obj, pose: {xyz: [0.4, 0.3, 0.1]}}]}",
        )
    )
    with pytest.raises(InputError, match=r"environment.obstacles.0: mesh file .*m.obj.*not finite"):
        preflight(load_config(cfg))
    capfd.readouterr()
    code = main(["validate", str(cfg)])
    out, err = capfd.readouterr()  # file-descriptor level: the mesh library prints nothing
    assert_one_line_error(code, err, "vertex 2 is not finite")


def test_a_path_that_exists_but_is_no_file_is_not_called_missing(cli, tmp_path):
    cfg = ROOT / "configs" / "from_file.yaml"
    for odd in ("/dev/zero", str(tmp_path)):  # it was "grasp file not found: /dev/zero"
        code, _, err = cli("validate", cfg, "--set", f"candidates.path={odd}")
        assert_one_line_error(code, err, f"candidates.path: grasp file {odd} is not a regular file")
