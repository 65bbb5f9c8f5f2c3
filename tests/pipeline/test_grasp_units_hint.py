"""Grasps written in millimetres are all out of reach; the warning names the units.

"Move the object closer" alone sends a user whose grasp file is in mm (1,000
times too far) to the wrong key.
"""

from __future__ import annotations

import numpy as np
from helpers import CONFIGS, QUICK


def test_grasps_in_millimetres_get_a_units_hint(cli, tmp_path):
    poses = np.load(CONFIGS / "data" / "mug_grasps.npy")
    poses[:, :3, 3] *= 1000.0  # metres written as millimetres
    np.save(tmp_path / "mm.npy", poses)
    code, _, err = cli(
        "run",
        CONFIGS / "from_file.yaml",
        "--out",
        tmp_path / "run",
        "--set",
        f"candidates.path={tmp_path / 'mm.npy'}",
        *QUICK,
    )
    assert code == 0, err
    line = next(ln for ln in err.splitlines() if "no grasp is reachable" in ln)
    assert "out_of_reach" in line and "in metres" in line, line
