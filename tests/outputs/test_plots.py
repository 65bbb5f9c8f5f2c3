"""Plots: counts in pipeline order, named patches, fitted charts with the robot side.

The figures are read back from their matplotlib axes before they are saved.
"""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from gcm_pipeline.geometry.dualquat import dq_from_matrix
from gcm_pipeline.manifold.build import build_manifold
from gcm_pipeline.manifold.charts import STANDOFF
from gcm_pipeline.outputs.chart_marks import approach_from_base, robot_side
from gcm_pipeline.outputs.plots import (
    chart_axis_labels,
    chart_period,
    counts_figure,
    hist_figure,
    manifold_figure,
    patch_sizes,
    patches_figure,
    reason_palette,
    stage_bars,
    unreachable_reasons,
)
from gcm_pipeline.rundir.run import read_run
from gcm_pipeline.table import GraspTable


def axis_grasps(angles: int = 12, heights: int = 3) -> np.ndarray:
    """Radial side grasps whose tool points lie on the z axis (1 mm noise)."""
    a, h = np.meshgrid(np.arange(angles) * 2 * np.pi / angles, np.linspace(0.02, 0.2, heights))
    a, h = a.ravel(), h.ravel()
    radial = np.column_stack((np.cos(a), np.sin(a), np.zeros_like(a)))
    m = np.tile(np.eye(4), (a.size, 1, 1))
    m[:, :3, 0] = [0.0, 0.0, 1.0]
    m[:, :3, 2] = -radial
    m[:, :3, 1] = np.cross(m[:, :3, 2], m[:, :3, 0])
    m[:, :3, 3] = np.column_stack((np.zeros((a.size, 2)), h))
    m[:, :3, 3] += 0.001 * np.random.default_rng(0).normal(size=(a.size, 3))
    return dq_from_matrix(m)


def test_chart_axis_labels_units():
    assert chart_axis_labels("cylindrical") == ("arc length R·θ [m]", "height along the axis [m]")
    assert chart_axis_labels("xy") == ("world x [m]", "world y [m]")
    # stereographic coordinates are dimensionless
    assert chart_axis_labels("spherical") == ("stereographic u", "stereographic v")
    assert chart_axis_labels(None) == ("chart u [m]", "chart v [m]")


def test_chart_period_is_the_manifolds():
    grasps = GraspTable({"dq": axis_grasps()})
    m = build_manifold(grasps, projection="cylindrical", frame=np.eye(4))
    assert chart_period(grasps, m) == m.period == pytest.approx(2 * np.pi * STANDOFF, rel=1e-2)
    flat = build_manifold(grasps, projection="pca")
    assert chart_period(grasps, flat) is None


# --------------------------------------------------------------------------- counts
def reason_table(reasons: dict[str, int], reachable: int, top: int = 0) -> GraspTable:
    """A table with ``reachable`` rows and the unreachable ones by ``reasons``."""
    bad = [r for r, n in reasons.items() for _ in range(n)]
    n = reachable + len(bad)
    return GraspTable(
        {
            "dq": np.tile([1.0, 0, 0, 0, 0, 0, 0, 0], (n, 1)),
            "reachable": np.r_[np.ones(reachable, bool), np.zeros(len(bad), bool)],
            "reason": np.array([""] * reachable + bad),
            "top": np.arange(n) < top,
        }
    )


def bar_segments(ax) -> dict[str, list[tuple[float, float, float]]]:
    """``{"<stage>:<segment>": [(x, bottom, height)]}`` of the bar containers on ``ax``."""
    out: dict[str, list[tuple[float, float, float]]] = {}
    for cont in ax.containers:
        for rect in cont:
            out.setdefault(rect.get_gid(), []).append(
                (rect.get_x() + 0.5 * rect.get_width(), rect.get_y(), rect.get_height())
            )
    return out


def test_counts_bars_follow_the_pipeline_on_a_linear_scale():
    reasons = {"approach": 206, "out_of_reach": 150, "collision_environment": 33, "no_ik": 5}
    grasps = reason_table(reasons, reachable=650, top=10)
    # the pipeline's summary counts, in its (not the pipeline's) key order
    counts = {
        "reachable": 650,
        "interpolated": 972,
        "densified": 1044,
        "triangles_dropped": 11,
        "triangles": 126,
        "candidates": 72,
    }
    ax = counts_figure(counts, grasps).axes[0]
    ticks = [t.get_text() for t in ax.get_xticklabels()]
    assert ticks == [
        "candidates",
        "manifold\ntriangles",
        "densified\ngrasps",
        "unreachable\n(by reason)",
        "reachable",
        "top-k\n(ranked)",
    ]
    assert ax.get_yscale() == "linear" and ax.get_ylim()[0] == 0
    seg = bar_segments(ax)
    assert seg["candidates:candidates"] == [(0, 0, 72)]
    assert seg["triangles:kept"] == [(1, 0, 126)] and seg["triangles:dropped"] == [(1, 126, 11)]
    assert seg["densified:densified"] == [(2, 0, 1044)]
    assert seg["reachable:reachable"] == [(4, 0, 650)] and seg["top:top"] == [(5, 0, 10)]
    # 650 of 1,044 reads as 62 %: the notes above the bars and the title say so
    notes = {t.get_text() for t in ax.texts}
    assert {"650 (62 %)", "394 (38 %)", "10 (1 %)", "1,044", "126 (+11 dropped)"} <= notes
    assert ax.get_title() == "Per-stage counts: 650 of 1,044 grasps reachable (62 %)"


def test_unreachable_reasons_stack_to_the_unreachable_count():
    reasons = {"approach": 206, "out_of_reach": 150, "collision_environment": 33, "no_ik": 5}
    grasps = reason_table(reasons, reachable=650)
    counts = {"candidates": 72, "densified": 1044, "reachable": 650}
    ax = counts_figure(counts, grasps).axes[0]
    seg = bar_segments(ax)
    stack = [(k.split(":", 1)[1], *v[0]) for k, v in seg.items() if k.startswith("unreachable:")]
    # most frequent at the bottom, each segment on top of the one below
    assert [s[0] for s in stack] == list(reasons)
    assert [s[3] for s in stack] == list(reasons.values())
    assert [s[2] for s in stack] == [0, 206, 356, 389]
    assert sum(s[3] for s in stack) == 1044 - 650
    # each reason its own colour, the scene's, and named with its count in the legend
    palette = reason_palette(list(reasons))
    rects = {r.get_gid(): r for c in ax.containers for r in c}
    for reason in reasons:
        np.testing.assert_allclose(
            rects[f"unreachable:{reason}"].get_facecolor()[:3], palette[reason]
        )
    legend = [t.get_text() for t in ax.get_legend().get_texts()]
    assert legend == ["no_ik: 5", "collision_environment: 33", "out_of_reach: 150", "approach: 206"]
    # the large segments carry their count inside
    inside = {t.get_text() for t in ax.texts}
    assert {"206", "150"} <= inside


def test_counts_without_the_tables_reasons_stack_one_unknown_segment():
    counts = {"densified": 100, "reachable": 60}
    bars = stage_bars(counts, None)
    assert [b.key for b in bars] == ["densified", "unreachable", "reachable"]
    assert bars[1].segments[0][:2] == ("unknown", 40) and bars[1].note == "40 (40 %)"
    # a table that is not the one the counts describe is not read for reasons
    other = reason_table({"no_ik": 3}, reachable=2)
    assert unreachable_reasons(other, counts) is None
    assert stage_bars(counts, other)[1].segments[0][:2] == ("unknown", 40)
    # nothing unreachable: no segment, the bar stays (0 %)
    assert stage_bars({"densified": 5, "reachable": 5})[1].segments == ()


def test_counts_of_a_real_run_stack_its_summarys_reasons(flat_run):
    run = read_run(flat_run)
    summary = run.summary["counts"]
    counts = {k: v for k, v in summary.items() if isinstance(v, int)}
    bars = {b.key: b for b in stage_bars(counts, run.grasps)}
    got = {name: n for name, n, _ in bars["unreachable"].segments}
    assert got == summary["unreachable_by_reason"]
    assert bars["unreachable"].total + bars["reachable"].total == bars["densified"].total


# --------------------------------------------------------------------------- patches
def patch_table(sizes: list[int]) -> tuple[GraspTable, object]:
    """36 side grasps around the z axis (a cylindrical manifold), split into patches of
    ``sizes`` (largest ids first: patch ids are not by size) and unreachable rows."""
    dq = axis_grasps()
    patch = np.full(len(dq), -1)
    start = 0
    for pid, n in zip(range(len(sizes) - 1, -1, -1), sizes, strict=True):
        patch[start : start + n] = pid
        start += n
    grasps = GraspTable({"dq": dq, "patch": patch, "reachable": patch >= 0})
    return grasps, build_manifold(grasps, projection="cylindrical", frame=np.eye(4))


def test_patch_legend_names_each_coloured_patch_and_counts_the_rest():
    sizes = [9, 6, 4, 3, 2, 2, 2, 1, 1, 1, 1]  # 11 patches, 32 grasps; 4 unreachable
    grasps, m = patch_table(sizes)
    assert patch_sizes(grasps)[:2] == [(10, 9), (9, 6)]
    fig = patches_figure(grasps, m)
    ax = fig.axes[0]
    title = ax.get_title()
    assert title.startswith("IK patches (branches): 11 patches (cylindrical projection)\n")
    assert "the 8 largest coloured, the other 3 (3 grasps) grey" in title
    legend = [t.get_text() for t in ax.get_legend().get_texts()]
    # largest first, ties by id
    named = [f"patch {i}: {n} grasps" for i, n in ((10, 9), (9, 6), (8, 4), (7, 3), (4, 2))]
    named += ["patch 5: 2 grasps", "patch 6: 2 grasps", "patch 0: 1 grasp"]
    assert [t for t in legend if t.startswith("patch ")] == named
    assert "other 3 patches: 3 grasps" in legend and "unreachable: 4 grasps" in legend
    # one colour per named patch, none of them the rest's grey
    colours = {}
    for coll in ax.collections:
        if coll.get_label().startswith(("patch ", "other ")):
            colours[coll.get_label()] = tuple(np.round(coll.get_facecolor()[0][:3], 6))
    named_colours = [colours[label] for label in named]
    assert len(set(named_colours)) == 8
    grey = colours["other 3 patches: 3 grasps"]
    assert grey[0] == grey[1] == grey[2] and grey not in named_colours


def test_a_few_patches_are_all_named():
    grasps, m = patch_table([20, 12])
    ax = patches_figure(grasps, m).axes[0]
    assert ax.get_title().startswith("IK patches (branches): 2 patches (cylindrical projection)")
    assert "grey" not in ax.get_title()
    legend = [t.get_text() for t in ax.get_legend().get_texts()]
    assert "patch 1: 20 grasps" in legend and "patch 0: 12 grasps" in legend
    assert not any(t.startswith("other") for t in legend)


# --------------------------------------------------------------------------- charts
def test_robot_side_of_a_cylindrical_chart_faces_the_base():
    grasps = GraspTable({"dq": axis_grasps()})
    frame = np.eye(4)
    frame[:3, 3] = [0.5, 0.0, 0.0]  # the object 0.5 m in front of the base
    m = build_manifold(grasps, projection="cylindrical", frame=frame)
    base = np.eye(4)
    # base at the world origin: straight -x from the object, theta = pi -> the seam -period/2
    side = robot_side(m, base)
    assert side.kind == "u" and float(side.value) == pytest.approx(-0.5 * m.period)
    base[:3, 3] = [0.5, 2.0, 1.0]  # +y of the axis (its height does not matter): theta = pi/2
    assert float(robot_side(m, base).value) == pytest.approx(0.25 * m.period)
    base[:3, 3] = [0.5, 0.0, -1.0]  # on the axis: no side
    assert robot_side(m, base) is None
    assert robot_side(m, None) is None


def test_manifold_plot_marks_the_robot_side_where_the_base_is():
    grasps = GraspTable({"dq": axis_grasps()})
    m = build_manifold(grasps, projection="cylindrical", frame=np.eye(4))
    base = np.eye(4)
    base[:3, 3] = [0.0, 1.0, 0.0]  # +y: theta = pi/2
    ax = manifold_figure(grasps, m, base).axes[0]
    lines = [ln for ln in ax.get_lines() if ln.get_label() == "robot side (facing the base)"]
    assert len(lines) == 1
    assert lines[0].get_xdata()[0] == pytest.approx(0.25 * m.period)
    assert any(t.get_text() == "robot side" for t in ax.texts)
    # no base, no mark
    ax = manifold_figure(grasps, m).axes[0]
    assert not [ln for ln in ax.get_lines() if "robot" in str(ln.get_label())]


def test_robot_side_of_spherical_and_planar_charts():
    sphere = SimpleNamespace(projection="spherical", frame=np.eye(4), structure="chart")
    base = np.eye(4)
    base[:3, 3] = [-3.0, 4.0, -1.0]
    side = robot_side(sphere, base)
    assert side.kind == "ray" and side.value == pytest.approx([-0.6, 0.8])
    flat = SimpleNamespace(projection="xy", frame=None, structure="chart")
    side = robot_side(flat, base)
    assert side.kind == "point" and side.value == pytest.approx([-3.0, 4.0])
    families = SimpleNamespace(projection="families", frame=None, structure="families")
    assert robot_side(families, base) is None


def test_chart_axes_are_fitted_to_the_data():
    grasps = GraspTable({"dq": axis_grasps()})
    m = build_manifold(grasps, projection="cylindrical", frame=np.eye(4))
    ax = manifold_figure(grasps, m).axes[0]
    corners = m.chart[m.triangles].reshape(-1, 2)
    pts = np.vstack((m.chart, corners))
    # with the seam unwrapped, the triangles may reach half a turn beyond the stored chart
    lo, hi = pts.min(axis=0), pts.max(axis=0)
    x0, x1 = ax.get_xlim()
    y0, y1 = ax.get_ylim()
    span_y = hi[1] - lo[1]
    assert y0 == pytest.approx(lo[1] - 0.04 * span_y) and y1 == pytest.approx(hi[1] + 0.04 * span_y)
    assert x0 < lo[0] and x1 > hi[0] and (x1 - x0) < 1.2 * (m.period + (hi[0] - lo[0]))
    # a strip 2 pi R wide and 18 cm tall is not drawn to scale (and says so)
    assert ax.get_aspect() == "auto" and "axes not to scale" in ax.get_title()


def test_manipulability_histogram_says_what_it_counts():
    rng = np.random.default_rng(1)
    n = 50
    grasps = GraspTable(
        {
            "reachable": np.arange(n) < 40,
            "manipulability": np.where(np.arange(n) < 40, rng.uniform(0.02, 0.12, n), np.nan),
        }
    )
    ax = hist_figure(grasps).axes[0]
    assert ax.get_title() == "Manipulability of the reachable grasps: 40 of 50"
    assert ax.get_ylabel() == "reachable grasps per bin"
    assert ax.get_xlabel().startswith("manipulability: Yoshikawa index")
    assert sum(p.get_height() for p in ax.patches) == 40


def test_a_flat_run_is_drawn_to_scale_with_an_arrow_to_the_base(flat_run):
    run = read_run(flat_run)
    base = np.eye(4)  # configs/flat_surface.yaml: the Panda at the origin, the grasps beyond
    fig = manifold_figure(run.grasps, run.manifold, base)
    ax = fig.axes[0]
    assert ax.get_aspect() == 1.0 and "not to scale" not in ax.get_title()
    legend = [t.get_text() for t in ax.get_legend().get_texts()]
    assert any(t.startswith("toward the robot base (") for t in legend)
    # the arrow points from inside the data toward the base, ending inside the axes
    arrow = next(t for t in ax.texts if t.get_text() == "" and t.arrow_patch is not None)
    tip, tail = np.asarray(arrow.xy), np.asarray(arrow.xyann)
    centre = np.array([np.mean(ax.get_xlim()), np.mean(ax.get_ylim())])
    assert np.dot(tip - tail, -centre) > 0  # toward the origin
    assert ax.get_xlim()[0] <= tip[0] <= ax.get_xlim()[1]
    assert ax.get_ylim()[0] <= tip[1] <= ax.get_ylim()[1]


def test_families_plots_mark_the_approach_from_the_robot():
    grasps = GraspTable({"dq": axis_grasps()})
    base = np.eye(4)
    base[:3, 3] = [-1.0, 0.0, 0.3]  # the grasps' centre is straight +x of the base
    assert approach_from_base(grasps, base) == pytest.approx(0.0, abs=0.2)
    base[:3, 3] = [0.0, 1.0, 0.0]  # +y of the base: approached toward -y
    assert approach_from_base(grasps, base) == pytest.approx(-90.0, abs=0.2)
    base[:3, 3] = [0.0, 0.0, -1.0]  # straight below: no horizontal direction
    assert approach_from_base(grasps, base) is None
    m = build_manifold(grasps, structure="families", max_edge_length=0.1, max_edge_angle_deg=60)
    base[:3, 3] = [0.0, 1.0, 0.0]
    fig = manifold_figure(grasps, m, base)
    directions = fig.axes[1]
    lines = [ln for ln in directions.get_lines() if ln.get_linestyle() == "--"]
    assert len(lines) == 1 and lines[0].get_xdata()[0] == pytest.approx(-90.0, abs=0.2)
    legend = [t.get_text() for t in fig.legends[0].get_texts()]
    assert "approach from the robot side" in legend


def test_gcm_plot_takes_the_base_from_the_runs_config(flat_run):
    from gcm_pipeline.cli.results import _run_base_pose

    run = read_run(flat_run)
    np.testing.assert_allclose(_run_base_pose(run.summary), np.eye(4), atol=1e-12)
    moved = {"config": {"robot": {"base_pose": {"xyz": [0.1, 0.2, 0.0], "rpy_deg": [0, 0, 90]}}}}
    expected = np.array([[0.0, -1, 0, 0.1], [1, 0, 0, 0.2], [0, 0, 1, 0], [0, 0, 0, 1]])
    np.testing.assert_allclose(_run_base_pose(moved), expected, atol=1e-12)
    # a summary without a usable base: the plots are drawn without the robot side
    assert _run_base_pose({}) is None
    assert _run_base_pose({"config": {"robot": {"base_pose": {"xyz": "here"}}}}) is None
