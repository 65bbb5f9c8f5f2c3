"""A run whose manifold is left empty warns and names the keys that would keep it."""

from __future__ import annotations

from helpers import FLAT, QUICK


def test_a_run_with_no_triangle_left_warns_and_suggests(cli, tmp_path):
    code, _, err = cli(
        "run",
        FLAT,
        "--out",
        tmp_path / "run",
        "--set",
        "manifold.max_edge_length=0.001",
        *QUICK,
    )
    assert code == 0, err
    assert "no triangle is left (dropped: edge_length 1)" in err
    assert "manifold.max_edge_length" in err
