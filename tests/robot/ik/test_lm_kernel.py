"""The LM kernel (gcm_pipeline.robot.ik.lm_kernel) against the NumPy Levenberg-Marquardt.

An iterative solver: compared are the convergence flags, each answer's pose error
as Pinocchio computes it, the joint limits, and the distance between answers the
two converge to; never q to the last bits.
"""

from __future__ import annotations

import numpy as np
import pytest

#: Each test starts with the kernels on, whatever the environment says.
pytestmark = pytest.mark.usefixtures("kernels_on")


def _near_targets(robot, n, seed):
    """Targets (rotations, positions) of random configurations and seeds around them.

    Seeds 0.02-0.6 rad away: most converge, some stall or stop at a joint limit;
    a tenth start half a turn of joint 7 away (the orientation error's half-turn case).
    """
    rng = np.random.default_rng(seed)
    q = robot.random_configurations(n, rng)
    rot, pos = robot.chain.pose(q)
    scale = rng.choice([0.02, 0.2, 0.6], size=(n, 1))
    seeds = np.clip(q + scale * rng.normal(size=q.shape), robot.lower, robot.upper)
    flip = rng.random(n) < 0.1
    seeds[flip, 6] = np.clip(q[flip, 6] + np.pi, robot.lower[6], robot.upper[6])
    return seeds, rot, pos


#: Rows of an iterative solver whose convergence flag may differ from the NumPy
#: code's: round-off differs between CPUs, and the LM amplifies it where a
#: decision is taken at its threshold (a joint that crosses its limit by an
#: ulp is frozen or not; a stall test at its ratio). 0 of 3,000 rows differed
#: on an x86-64 machine, with the native and the generic build (and the NumPy
#: code against itself from seeds moved by one ulp); a damping 5 % off flips
#: 18 and moves 1,601 of the 2,640 converged rows by more than 1e-6 rad.
_FLIP_SHARE = 1e-3


@pytest.mark.parametrize("clamp", [True, False])
def test_lm_kernel_equals_numpy(compiled, panda, clamp, numpy_code, pose_errors):
    """The compiled LM decides as the NumPy LM and its answers are what it says.

    Compared: the convergence flags (all but :data:`_FLIP_SHARE` of the rows),
    the pose error of every answer recomputed by Pinocchio (within the
    tolerances where converged, equal to the error the kernel reports), the
    joint limits; the rows converged by both end at the same solution (all
    but 1 % within 1e-6 rad: the tolerances allow a solver to stop anywhere in
    a small ball, but from the same seed by the same steps only round-off
    amplified at a threshold moves an answer; a different step rule moves
    most). Never q to the last bits.
    """
    from gcm_pipeline.robot.ik.lm import PinocchioIKOptions, levenberg_marquardt

    seeds, rot, pos = _near_targets(panda, 3000, 11)
    tol_p, tol_r = 1e-6, 1e-5
    for opts in (PinocchioIKOptions(), PinocchioIKOptions(stall_ratio=0.0, max_iterations=6)):
        args = (panda.chain, seeds, rot, pos, panda.lower, panda.upper, tol_p, tol_r, opts, clamp)
        q, conv, pe, re = levenberg_marquardt(*args)
        q_ref, conv_ref, pe_ref, re_ref = numpy_code(levenberg_marquardt, *args)
        assert 0.3 < conv_ref.mean() < 0.97  # converged and failed rows both tested
        assert (conv != conv_ref).sum() <= _FLIP_SHARE * len(conv)
        # every answer: its error as Pinocchio computes it, within the tolerances if converged
        pin_pe, pin_re = pose_errors(panda, q, rot, pos)
        np.testing.assert_allclose(pe, pin_pe, rtol=1e-6, atol=1e-12)
        np.testing.assert_allclose(re, pin_re, rtol=1e-6, atol=1e-12)
        assert np.all(pin_pe[conv] <= tol_p * (1 + 1e-6)) and np.all(
            pin_re[conv] <= tol_r * (1 + 1e-6)
        )
        # not converged: the pose is not within the tolerances (the flag is not dropped)
        assert np.all((pin_pe[~conv] > tol_p * (1 - 1e-6)) | (pin_re[~conv] > tol_r * (1 - 1e-6)))
        if clamp:
            assert np.all((q >= panda.lower) & (q <= panda.upper))
        both = conv & conv_ref
        apart = np.abs(q[both] - q_ref[both]).max(axis=1)
        assert (apart > 1e-6).mean() <= 0.01, np.sort(apart)[-10:]
    # a half turn away in orientation: the rotation vector's length is pi
    flip = np.diag([1.0, -1.0, -1.0])
    q0 = panda.random_configurations(1, 3)
    r0, p0 = panda.chain.pose(q0)
    one = (panda.chain, q0, r0 @ flip, p0, panda.lower, panda.upper, 1e-6, 1e-5)
    got = levenberg_marquardt(*one, PinocchioIKOptions(max_iterations=0))
    ref = numpy_code(levenberg_marquardt, *one, PinocchioIKOptions(max_iterations=0))
    assert got[3][0] == pytest.approx(np.pi) and ref[3][0] == pytest.approx(np.pi)
