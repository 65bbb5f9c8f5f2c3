"""Compiled kernel of a 6R arm's closed-form branches after EAIK: one target at a time.

The kernel of the steps :meth:`gcm_pipeline.robot.ik.analytic_6r.SixRAnalyticIK.solve`
takes after EAIK's answers (the NumPy reference, beside this module): exact
answers only, angles into (-pi, pi], one branch once, each at its 2 pi copy
nearest a reference inside the limits. Imported by
:func:`gcm_pipeline.robot.kernels.get` only (it imports Numba).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit, types

from gcm_pipeline.robot.kernel_common import F1, F2, I1

#: EAIK's answers: whether each is exact (not a least-squares one).
B1 = types.Array(types.boolean, 1, "C", readonly=True)
_TWO_PI = 2.0 * math.pi


@njit(cache=True, inline="always")
def _remainder(x: float, y: float) -> float:
    """``np.remainder(x, y)`` for ``y > 0``: fmod moved into ``[0, y)`` (+0.0 for none)."""
    mod = np.fmod(x, y)
    if mod == 0.0:
        return 0.0
    if mod < 0.0:
        mod += y
    return mod


@njit(
    types.Tuple((types.intp[::1], types.float64[:, ::1]))(F2, I1, B1, F2, F1, F1, types.float64),
    cache=True,
)
def six_r_branches(q, counts, exact, reference, lower, upper, same):
    """EAIK's answers of N targets to branches inside the limits, as ``SixRAnalyticIK.solve``.

    Per target, in EAIK's order: its exact, finite answers, angles taken into
    (-pi, pi] (``remainder(q + pi, 2 pi) - pi``); an answer within ``same`` of an
    earlier one of its target (any of them, repeats included) in every joint,
    modulo 2 pi, is dropped; each angle then moves by whole turns to the copy
    nearest the target's reference (else the one a turn to its other side)
    inside ``[lower, upper]``; an answer with a joint that has none is dropped.

    Args:
        q: EAIK's answers (M, 6) [rad], grouped by target.
        counts: Answers per target (N,), summing to M.
        exact: Whether each answer is exact (M,) (EAIK's ``not is_LS``).
        reference: Per target (N, 6) [rad], inside the limits.
        lower: Lower joint limits (6,) [rad].
        upper: Upper joint limits (6,) [rad].
        same: Two angles closer than this modulo 2 pi are one [rad].

    Returns:
        ``(index, q)``: target (K,) and configuration (K, 6) [rad] of each branch kept.
    """
    m = q.shape[0]
    index = np.empty(m, dtype=np.intp)
    out = np.empty((m, 6))
    wrapped = np.empty((m, 6))  # the target's answers kept so far, into (-pi, pi]
    copy = np.empty(6)
    k = 0
    row = 0
    for t in range(counts.shape[0]):
        start = row
        row += counts[t]
        w0 = 0  # the target's first row of ``wrapped``
        w = 0
        for r in range(start, row):
            if not exact[r]:
                continue
            finite = True
            for j in range(6):
                finite = finite and math.isfinite(q[r, j])
            if not finite:
                continue
            for j in range(6):
                wrapped[w, j] = _remainder(q[r, j] + math.pi, _TWO_PI) - math.pi
            repeat = False
            for e in range(w0, w):
                close = True
                for j in range(6):
                    d = abs(wrapped[e, j] - wrapped[w, j])
                    close = close and min(d, _TWO_PI - d) < same
                if close:
                    repeat = True
                    break
            w += 1  # a repeat stays: later answers are compared with it too
            if repeat:
                continue
            inside = True
            for j in range(6):
                a, ref = wrapped[w - 1, j], reference[t, j]
                base = a + _TWO_PI * np.rint((ref - a) / _TWO_PI)
                other = base - _TWO_PI if base > ref else base + _TWO_PI
                if lower[j] <= base <= upper[j]:
                    copy[j] = base
                elif lower[j] <= other <= upper[j]:
                    copy[j] = other
                else:
                    inside = False
                    break
            if inside:
                index[k] = t
                out[k] = copy
                k += 1
    return index[:k].copy(), out[:k].copy()
