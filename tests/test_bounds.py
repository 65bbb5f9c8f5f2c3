"""Size limits (``gcm_pipeline.bounds``): work too large is refused at once, naming the key.

Nothing is written when a ceiling refuses a run, and raising the ceiling lets
the same run through.
"""

from __future__ import annotations

import pytest
from helpers import BOTTLE, FLAT, QUICK, assert_one_line_error


@pytest.mark.parametrize(
    ("override", "fragment"),
    [
        ("densify.subdivisions=30000", "raise densify.max_poses"),
        ("densify.spacing=0.00001", "raise densify.max_poses"),
        ("candidates.count=1000000000", "raise candidates.max_count"),
        ("approach={distance: 0.1, steps: 100000000}", "approach.steps"),
    ],
)
def test_resource_bombs_are_refused_at_once(cli, tmp_path, override, fragment):
    code, _, err = cli("run", FLAT, "--out", tmp_path / "run", "--set", override, *QUICK)
    assert_one_line_error(code, err, fragment)
    assert list(tmp_path.iterdir()) == []


def test_a_raised_ceiling_lets_the_run_through(cli, tmp_path):
    sets = ["--set", "densify.subdivisions=30", "--set", "densify.max_poses=400"]
    code, _, err = cli("run", FLAT, "--out", tmp_path / "a", *sets, *QUICK)
    assert_one_line_error(
        code, err, "densify: 3 candidates and 1 triangles", "above densify.max_poses"
    )
    sets[-1] = "densify.max_poses=600"
    code, _, err = cli("run", FLAT, "--out", tmp_path / "b", *sets, *QUICK, "-q")
    assert code == 0, err


@pytest.mark.parametrize(
    ("override", "key"),
    [
        # coal: "The bounding volume has a negative volume" (a traceback)
        ("environment.table.height=1e20", "environment.table.height"),
        ("robot.base_pose.xyz=[0, -1e20, 0]", "robot.base_pose.xyz.1"),
        # accepted: Eigen printed "too many iterations", every grasp inside the table
        ("environment.table.size=[1e308, 1e308, 1e308]", "environment.table.size.0"),
        ("environment.obstacles=[{shape: sphere, dims: {radius: 1e308}}]", "dims.radius"),
        ("object.pose.xyz=[1e20, 0, 0]", "object.pose.xyz.0"),  # was: row 4 not a unit dq
        ("object.scale=1e300", "object.scale"),
    ],
)
def test_a_scene_of_astronomic_size_is_refused_naming_the_key(cli, override, key):
    code, _, err = cli("validate", BOTTLE, "--set", override)
    assert_one_line_error(code, err, f"{key}: Input should be ", "1000")


def test_more_obstacles_than_the_bound_are_refused(cli):
    # each costs the collision checker about 4.5 MB: 2,000 took 8.9 GB
    many = "[" + ", ".join(["{shape: sphere, dims: {radius: 0.01}}"] * 101) + "]"
    code, _, err = cli("validate", BOTTLE, "--set", f"environment.obstacles={many}")
    assert_one_line_error(code, err, "environment.obstacles: ", "at most 100 items")
