"""Grasps that do not spread out in the chart: one line suggesting another projection."""

from __future__ import annotations

from helpers import assert_one_line_error


def test_a_degenerate_chart_suggests_another_projection(cli, tmp_path):
    (tmp_path / "g.csv").write_text(
        "x,y,z,qw,qx,qy,qz\n0.5,0,0.2,0,1,0,0\n0.5,0.1,0.2,0,1,0,0\n0.5,0.2,0.2,0,1,0,0\n"
    )
    cfg = tmp_path / "cfg.yaml"
    cfg.write_text("candidates: {source: file, path: g.csv}\nmanifold: {projection: xy}\n")
    code, _, err = cli("run", cfg, "--out", tmp_path / "run")
    assert_one_line_error(
        code, err, "collinear", "try another manifold.projection (cylindrical, pca, spherical)"
    )
