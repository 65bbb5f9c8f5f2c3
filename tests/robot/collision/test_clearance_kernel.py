"""The clearance's compiled kernels against the NumPy code and against coal on every pair.

On the Panda and on the UR5 with the Robotiq 2F-85, in the bottle's world with a box,
a sphere and a tilted cylinder beside the arm, on random configurations and IK
solutions near the shapes: each kernel of
:mod:`~gcm_pipeline.robot.collision.clearance_kernel` equals its NumPy reference to
1e-12 m (the sphere bounds, the exact distances over a box's face, the hull
vertices' bounds); and the clearance, compiled and NumPy, keeps its contract
against the slow exact reference (coal's distance of every pair): a real distance,
at most ``precision`` above the minimum, the minimum itself with ``precision=0``.
"""

from __future__ import annotations

import numpy as np
import pinocchio as pin
import pytest
from helpers import ROOT
from scipy.spatial.transform import Rotation

from gcm_pipeline import pipeline as P
from gcm_pipeline.config import EnvironmentConfig, load_config
from gcm_pipeline.pipeline import make_checker
from gcm_pipeline.pipeline.reach import reach_options
from gcm_pipeline.robot.collision.broadphase import stacked
from gcm_pipeline.robot.ik import solve_ik

#: Each test starts with the kernels on, whatever the environment says.
pytestmark = pytest.mark.usefixtures("kernels_on")

_OBSTACLES = [
    {"shape": "box", "dims": {"size": [0.2, 0.2, 0.4]}, "pose": {"xyz": [0.2, -0.4, 0.2]}},
    {"shape": "sphere", "dims": {"radius": 0.08}, "pose": {"xyz": [0.35, 0.3, 0.5]}},
    {
        "shape": "cylinder",
        "dims": {"radius": 0.05, "height": 0.3},
        "pose": {"xyz": [0.3, -0.35, 0.45], "rpy": [0.7, 0.2, 0.0]},
    },
]
_CENTRES = np.array([[0.2, -0.4, 0.2], [0.35, 0.3, 0.5], [0.3, -0.35, 0.45], [0.5, 0.0, 0.15]])


@pytest.fixture(scope="module", params=["panda", "ur5_robotiq"])
def case(request):
    """A checker of the robot among the shapes, and configurations near and far from them."""
    name = "bottle_side.yaml" if request.param == "panda" else "bottle_side_ur5.yaml"
    cfg = load_config(ROOT / "configs" / name)
    robot = P.robot_from_config(cfg)
    env = EnvironmentConfig.model_validate({"obstacles": _OBSTACLES})
    checker = make_checker(robot, env, cfg.object, reach_options(cfg).base_pose)
    rng = np.random.default_rng(5)
    n = 400
    t = np.tile(np.eye(4), (n, 1, 1))
    t[:, :3, :3] = Rotation.random(n, random_state=6).as_matrix()
    t[:, :3, 3] = _CENTRES[rng.integers(0, len(_CENTRES), n)] + rng.normal(0, 0.1, (n, 3))
    res = solve_ik(robot, t)
    qs = np.concatenate([res.q[res.success], robot.random_configurations(300, 7)])
    return checker, qs


def _same(got, ref, what):
    """Equal to 1e-12 m, NaN where the reference is NaN."""
    assert np.array_equal(np.isnan(got), np.isnan(ref)), what
    np.testing.assert_allclose(got, ref, rtol=0, atol=1e-12, err_msg=what)


def test_kernels_equal_the_numpy_code(case, compiled):
    checker, qs = case
    frames = checker._frames.compute(qs)
    tfs = stacked(frames.transforms)
    cov = checker._cover
    packed = checker._clearance_packed()
    centres = checker._place(frames, cov.joint, cov.centre)
    bound = checker._sphere_bounds(centres)
    _same(compiled.sphere_bounds(tfs, *packed.spheres), bound, "sphere bounds")
    # every pair's face distance, then only those that can still be the nearest
    for lower in (np.full_like(bound, -np.inf), bound):
        ref = checker._face_distances(frames, centres, lower)
        _same(compiled.face_distances(tfs, *packed.faces, lower), ref, "face distances")
    assert np.isfinite(checker._face_distances(frames, centres, -np.inf * bound)).sum() > 1000
    need = np.ones(bound.shape, dtype=bool)
    need[::3] = False
    for precision in (1e-3, 0.02):
        upper, below = checker._vertex_distances(frames, need, precision)
        got = compiled.vertex_distances(tfs, need, *packed.vertices, precision)
        _same(got[0], upper, "vertex distances")
        _same(got[1], below, "separating planes")
        assert np.isfinite(upper).sum() > 500


def _every_pair(checker, qs):
    """The slow exact reference: coal's distance of every clearance pair, (N, P)."""
    model = checker.robot.model
    data = model.createData()
    dm, dd = checker._dist_model, checker._dist_data
    out = np.empty((len(qs), len(dm.collisionPairs)))
    for i, q in enumerate(qs):
        pin.computeDistances(model, data, dm, dd, q)
        out[i] = [r.min_distance for r in dd.distanceResults]
    return out


def test_clearance_keeps_its_contract_against_every_pair(case, numpy_code):
    checker, qs = case
    best = _every_pair(checker, qs).min(axis=1)
    free = best > 0
    assert free.sum() > 200 and (~free).sum() > 10
    # coal's GJK stops at a relative tolerance of about 1e-6
    tol = 2e-6 + 4e-6 * best[free]
    for precision in (0.0, 1e-3, 0.01):
        fast = checker.clearance(qs, precision)
        ref = numpy_code(checker.clearance, qs, precision)
        # compiled and NumPy: the same pairs decide, to round-off
        np.testing.assert_allclose(fast, ref, rtol=0, atol=1e-12)
        for got in (fast, ref):
            # penetrating: a penetration with precision 0, else at most precision above
            assert np.all(got[~free] <= precision)
            assert np.all(got[free] >= best[free] - tol)
            assert np.all(got[free] <= best[free] + precision + tol)
