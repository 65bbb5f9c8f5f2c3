"""Plots stage: chart axis labels and the cylindrical chart's period."""

from __future__ import annotations

import numpy as np
import pytest

from gcm_pipeline.geometry.dualquat import dq_from_matrix
from gcm_pipeline.manifold.build import build_manifold
from gcm_pipeline.manifold.charts import STANDOFF
from gcm_pipeline.outputs.plots import chart_axis_labels, chart_period
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
