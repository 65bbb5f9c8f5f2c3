"""An input file that is a symbolic link to nothing is named as such, not as missing.

``ls`` shows a dangling link (a dataset moved) or a loop of links, so "not
found" would send a user looking for a file that is plainly there.
"""

from __future__ import annotations

import os

import pytest
from helpers import assert_one_line_error


def _config(tmp_path, grasps: str):
    cfg = tmp_path / "c.yaml"
    cfg.write_text(
        f"robot: {{spec: panda}}\ncandidates: {{source: file, path: {grasps}, format: npy}}\n"
    )
    return cfg


@pytest.mark.parametrize("kind", ["dangling", "loop"])
def test_a_link_to_nothing_is_named(cli, tmp_path, kind):
    if kind == "dangling":
        os.symlink(tmp_path / "moved_away.npy", tmp_path / "g.npy")
    else:
        os.symlink(tmp_path / "h.npy", tmp_path / "g.npy")
        os.symlink(tmp_path / "g.npy", tmp_path / "h.npy")
    code, _, err = cli("validate", _config(tmp_path, "g.npy"))
    assert_one_line_error(
        code,
        err,
        f"candidates.path: grasp file {tmp_path / 'g.npy'} is a symbolic link",
        "dangling, or a loop of links",
    )


def test_a_missing_file_is_still_not_found(cli, tmp_path):
    code, _, err = cli("validate", _config(tmp_path, "g.npy"))
    assert_one_line_error(code, err, "candidates.path: grasp file not found")
