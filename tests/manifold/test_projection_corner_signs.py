"""A projection depends on the poses of a triangle's corners, not on their signs.

A dual quaternion and its negation are one pose; a run's candidates are stored
with either sign (10 of the bottle's 126 triangles have a corner of the other
sign than the first). The blend signs its output like the heaviest corner, so
on such a triangle the surface's quaternion changes sign inside it; a projection
holding the query's sign must see one sign throughout.
"""

from __future__ import annotations

import numpy as np
import pytest
from helpers import triangle_corners

from gcm_pipeline.geometry.dualquat import dq_from_pos_quat
from gcm_pipeline.manifold.surface import project_onto_triangles


@pytest.fixture(scope="module")
def corners() -> np.ndarray:
    return triangle_corners()


@pytest.mark.parametrize("method", ["dlb", "dib"])
def test_a_corner_of_the_other_sign_projects_the_same(corners: np.ndarray, method: str) -> None:
    rng = np.random.default_rng(23)
    n = 4000
    d = rng.normal(size=(n, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    r = rng.normal(size=(n, 4))
    r /= np.linalg.norm(r, axis=1, keepdims=True)
    # some near the manifold, some a metre or more away; every orientation (the
    # query's quaternion meets many triangles with either sign)
    q = dq_from_pos_quat(d * rng.uniform(0.0, 3.0, (n, 1)), r)
    t = rng.integers(0, len(corners), n)
    uv0 = rng.dirichlet((1, 1, 1), n)[:, 1:]
    signs = np.where(rng.random((n, 3)) < 0.5, -1.0, 1.0)
    _, want = project_onto_triangles(q, corners[t], uv0, method=method)
    _, got = project_onto_triangles(q, corners[t] * signs[:, :, None], uv0, method=method)
    np.testing.assert_allclose(got, want, rtol=0, atol=1e-9)
