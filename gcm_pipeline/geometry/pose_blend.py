r"""Blends of rigid poses (unit dual quaternions, :mod:`gcm_pipeline.geometry.dualquat`).

* :func:`dlb`: dual quaternion linear blending (Kavan et al.), closed form,
  fast, approximates the bi-invariant mean.
* :func:`dib`: dual quaternion iterative blending (Kavan et al.), the exact
  bi-invariant weighted mean, iterating :func:`~gcm_pipeline.geometry.dualquat.dq_log`
  / :func:`~gcm_pipeline.geometry.dualquat.dq_exp` around the current estimate.
* :func:`sclerp`: screw linear interpolation between two poses.

:math:`\hat q` and :math:`-\hat q` are the same pose: every blend aligns signs
to a pivot first.
"""

from __future__ import annotations

import warnings
from typing import Literal

import numpy as np
import numpy.typing as npt

from gcm_pipeline.errors import GeometryError, choice_error
from gcm_pipeline.geometry.dualquat import (
    as_dq,
    dq_conj,
    dq_exp,
    dq_log,
    dq_mul,
    first_bad_index,
    unit_from_blend,
)

__all__ = ["dib", "dlb", "sclerp"]

_WEIGHT_TOL = 1e-9
_ZERO_NORM = 1e-12  # a blend's rotation norm below this has no rotation

_PIVOTS = ("first", "heaviest")


def sclerp(
    a: npt.ArrayLike, b: npt.ArrayLike, t: npt.ArrayLike, *, check: bool = True
) -> np.ndarray:
    r"""Screw linear interpolation :math:`\hat a (\hat a^{-1} \hat b)^t`.

    The relative motion :math:`\hat a^{-1} \hat b` is taken the short way
    (its logarithm has rotation angle <= pi), so the signs of ``a`` and ``b``
    do not matter.

    Args:
        a: Start poses (..., 8), unit dual quaternions.
        b: End poses (..., 8), broadcast against ``a``.
        t: Interpolation parameter(s) [-], broadcast against the batch shape;
            0 gives ``a``, 1 gives ``b`` (up to sign).
        check: Validate finiteness.

    Returns:
        Interpolated unit dual quaternions (..., 8).
    """
    a = as_dq(a, "a", check)
    b = as_dq(b, "b", check)
    t = np.asarray(t, dtype=np.float64)
    if check and not np.isfinite(t).all():
        raise GeometryError(f"sclerp parameter t has non-finite values: {t}")
    rel = dq_mul(dq_conj(a), b)
    return dq_mul(a, dq_exp(dq_log(rel) * t[..., None]))


def _check_weights(w: np.ndarray) -> None:
    bad = ~np.isfinite(w)
    if bad.any():
        raise GeometryError(f"blend weights have non-finite values at index {first_bad_index(bad)}")
    bad = w < -_WEIGHT_TOL
    if bad.any():
        i = first_bad_index(bad)
        raise GeometryError(f"blend weights must be >= 0, got {float(w[i]):.6g} at index {i}")
    total = w.sum(-1)
    bad = np.abs(total - 1.0) > _WEIGHT_TOL
    if np.ndim(total) == 0:
        if bad:
            raise GeometryError(f"blend weights must sum to 1, got {float(total):.12g}")
    elif bad.any():
        i = first_bad_index(bad)
        raise GeometryError(f"blend weights must sum to 1, got {float(total[i]):.12g} at index {i}")


def _blend_inputs(
    dqs: npt.ArrayLike, weights: npt.ArrayLike, check: bool
) -> tuple[np.ndarray, np.ndarray]:
    dqs = as_dq(dqs, "dqs", check)
    w = np.asarray(weights, dtype=np.float64)
    if dqs.ndim < 2:
        raise GeometryError(f"dqs must have shape (..., K, 8), got {dqs.shape}")
    if w.ndim < 1 or w.shape[-1] != dqs.shape[-2]:
        raise GeometryError(
            f"weights must have shape (..., K) with K = {dqs.shape[-2]} poses, got {w.shape}"
        )
    try:
        np.broadcast_shapes(dqs.shape[:-2], w.shape[:-1])
    except ValueError:
        raise GeometryError(
            f"batch shapes of dqs {dqs.shape} and weights {w.shape} do not broadcast"
        ) from None
    if check:
        _check_weights(w)
    return dqs, w


def _aligned_weights(dqs: np.ndarray, w: np.ndarray, pivot: str) -> np.ndarray:
    """Weights with each pose's sign folded in: negated where ``r_k . r_pivot < 0``."""
    r = dqs[..., :4]
    if dqs.ndim == 2:  # K shared poses: a (K, K) table of dot products
        gram = r @ r.T
        dots = gram[np.argmax(w, axis=-1)] if pivot == "heaviest" else gram[0]
    elif pivot == "first":
        dots = np.einsum("...kc,...c->...k", r, r[..., 0, :])
    else:
        onehot = (np.arange(w.shape[-1]) == np.argmax(w, axis=-1)[..., None]).astype(np.float64)
        piv = np.einsum("...k,...kc->...c", onehot, r)
        dots = np.einsum("...kc,...c->...k", r, piv)
    return np.where(dots < 0, -w, w)


def dlb(
    dqs: npt.ArrayLike,
    weights: npt.ArrayLike,
    *,
    pivot: Literal["heaviest", "first"] = "heaviest",
    check: bool = True,
) -> np.ndarray:
    r"""Dual quaternion linear blending (DLB, Kavan et al. 2008).

    .. math::

        \mathrm{DLB}(w; \hat q_1, \dots, \hat q_K) =
        \frac{\sum_k w_k s_k \hat q_k}{\lVert \sum_k w_k s_k \hat q_k \rVert},
        \qquad s_k = \operatorname{sign}(r_k \cdot r_{\mathrm{pivot}})

    The signs :math:`s_k` align every pose with the pivot (antipodality: q and
    -q are the same pose and must not cancel). The norm is the dual norm
    (Kavan's normalisation, see :func:`dq_normalize`).

    Args:
        dqs: K unit dual quaternions, (K, 8) shared by all weight rows or
            (..., K, 8) broadcast against the weights' batch shape.
        weights: Blend weights (..., K) [-], each row >= 0 and summing to 1.
        pivot: ``"heaviest"`` (per weight row, default; the blend can never
            vanish) or ``"first"`` (the first pose).
        check: Validate finiteness and the weights (cheap, vectorised).
            ``False`` for trusted internal calls.

    Returns:
        Blended unit dual quaternions (..., 8), sign-aligned with the pivot.

    Raises:
        GeometryError: On shapes that do not fit, non-finite values, negative
            weights or weights not summing to 1 (tolerance 1e-9).
    """
    if pivot not in _PIVOTS:
        raise choice_error(GeometryError, "DLB pivot", pivot, _PIVOTS)
    dqs, w = _blend_inputs(dqs, weights, check)
    ws = _aligned_weights(dqs, w, pivot)
    if dqs.ndim == 2:
        blended = ws @ dqs
    else:
        blended = np.einsum("...k,...kc->...c", ws, dqs)
    if check:
        n2 = np.einsum("...i,...i->...", blended[..., :4], blended[..., :4])
        if (n2 < _ZERO_NORM**2).any():
            i = first_bad_index(n2 < _ZERO_NORM**2)
            raise GeometryError(f"DLB blend has a zero-norm rotation at index {i}")
    return unit_from_blend(blended)


def dib(
    dqs: npt.ArrayLike,
    weights: npt.ArrayLike,
    *,
    tol: float = 1e-12,
    max_iter: int = 50,
    check: bool = True,
) -> np.ndarray:
    r"""Dual quaternion iterative blending (DIB, Kavan et al.): the bi-invariant mean.

    Starting from :func:`dlb`, iterate

    .. math::

        x = \sum_k w_k \log(\hat b^{-1} \hat q_k), \qquad \hat b \leftarrow \hat b \exp(x)

    until :math:`\lVert x \rVert_\infty <` ``tol``. The fixed point is
    invariant to left and right multiplication of all poses; for two poses it
    is exactly :func:`sclerp` at ``t = w_2``.

    Args:
        dqs: K unit dual quaternions, (K, 8) or (..., K, 8).
        weights: Blend weights (..., K), >= 0, summing to 1.
        tol: Convergence threshold on the update twist [rad, m].
        max_iter: Maximum number of iterations.
        check: Validate finiteness and the weights.

    Returns:
        Blended unit dual quaternions (..., 8).

    Raises:
        GeometryError: As :func:`dlb`.

    Warns:
        RuntimeWarning: If some blends have not converged after ``max_iter``
            iterations (their last estimate is returned).
    """
    dqs, w = _blend_inputs(dqs, weights, check)
    batch = np.broadcast_shapes(dqs.shape[:-2], w.shape[:-1])
    k = dqs.shape[-2]
    poses = np.broadcast_to(dqs, batch + (k, 8)).reshape(-1, k, 8)
    wf = np.broadcast_to(w, batch + (k,)).reshape(-1, k)
    b = dlb(poses, wf, check=False)
    active = np.arange(len(b))  # rows not converged yet: only they are iterated
    for _ in range(max_iter):
        if not len(active):
            break
        q, wa, ba = poses[active], wf[active], b[active]
        x = np.einsum("nk,nkc->nc", wa, dq_log(dq_mul(dq_conj(ba)[:, None, :], q)))
        b[active] = unit_from_blend(dq_mul(ba, dq_exp(x)))
        active = active[np.abs(x).max(axis=1) >= tol]
    if len(active):
        warnings.warn(
            f"DIB did not converge to {tol:g} in {max_iter} iterations for {len(active)} "
            f"of {len(b)} blends (poses near the cut locus, 180 deg apart?)",
            RuntimeWarning,
            stacklevel=2,
        )
    return b.reshape(batch + (8,))
