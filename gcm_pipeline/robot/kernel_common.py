"""What the compiled kernels share: signature types, the FMA, a chain's frames.

The kernel modules (:mod:`~gcm_pipeline.robot.chain_kernel`,
:mod:`~gcm_pipeline.robot.collision.broadphase_kernel`,
:mod:`~gcm_pipeline.robot.ik.lm_kernel`, :mod:`~gcm_pipeline.robot.ik.panda_kernel`)
and this one import Numba at their top, so only
:func:`gcm_pipeline.robot.kernels.get` imports them (never the package's import).
``fastmath`` stays off in every kernel, so LLVM does not contract ``a * b + c`` into
an FMA by itself: the only FMAs are the explicit :func:`fma` calls.

The chain's frames and Jacobian columns are ``inline="always"``: Numba copies them
into each kernel that calls them (forward kinematics, the LM iterations, the
deviation samples). Numba's cache checks only the source file of the kernel it
caches, not the functions it inlines from here (numba/numba#1833): after editing
this module, delete the cache (``__pycache__/*.nbi`` and ``*.nbc`` beside the kernel
modules) or point ``NUMBA_CACHE_DIR`` at a fresh directory.
"""

from __future__ import annotations

from typing import Any

from llvmlite import ir
from numba import njit, types
from numba.core import cgutils
from numba.extending import intrinsic
from numba.np.numpy_support import as_dtype

# C-contiguous arrays: inputs read-only (so that read-only arrays are taken
# too), the results writable
F1 = types.Array(types.float64, 1, "C", readonly=True)
F2 = types.Array(types.float64, 2, "C", readonly=True)
F3 = types.Array(types.float64, 3, "C", readonly=True)
F4 = types.Array(types.float64, 4, "C", readonly=True)
I1 = types.Array(types.intp, 1, "C", readonly=True)
I2 = types.Array(types.intp, 2, "C", readonly=True)
I1W = types.intp[::1]


def _fma_typer(typingctx: Any, a: Any, b: Any, c: Any) -> Any:
    """``a * b + c`` with one rounding (``llvm.fma.f64``), for float64 arguments."""
    sig = types.float64(types.float64, types.float64, types.float64)

    def codegen(context: Any, builder: Any, signature: Any, args: Any) -> Any:
        d = ir.DoubleType()
        fn = cgutils.get_or_insert_function(
            builder.module, ir.FunctionType(d, [d, d, d]), "llvm.fma.f64"
        )
        return builder.call(fn, args)

    return sig, codegen


#: ``fma(a, b, c)``: ``a * b + c`` with one rounding, in compiled code.
fma: Any = intrinsic(_fma_typer)


@njit(cache=True, inline="always")
def dot4(a: Any, r: int, b: Any, c: int) -> float:
    """``(a @ b)[r, c]`` of a (3, 4) and a (4, 4) matrix, summed as OpenBLAS's dgemm does.

    Its Haswell/Zen kernel sums ``k = 0..3`` as one FMA chain:
    ``fma(a3, b3, fma(a2, b2, fma(a1, b1, a0 * b0)))``.
    """
    acc = a[r, 0] * b[0, c]
    acc = fma(a[r, 1], b[1, c], acc)
    acc = fma(a[r, 2], b[2, c], acc)
    return fma(a[r, 3], b[3, c], acc)


@njit(cache=True, inline="always")
def frames(turn: Any, placement: Any, tool: Any, frame: Any, tcp: Any) -> None:
    """Every joint's frame and the tool frame of one configuration of a chain, in place.

    Each joint's frame is its parent's times its placement, then turned about
    z by its angle q: the x and y columns times ``exp(-i q)`` as a complex
    product, ``re = fma(x, c, -(y s))``, ``im = fma(x, s, y c)`` with
    ``c = cos q``, ``s = -sin q`` (NumPy's AVX2 loop).

    Args:
        turn: ``(cos q, sin q)`` of each joint of the chain (nj, 2).
        placement: Joint placements (nj, 4, 4), axes turned onto z.
        tool: The frame's placement on the last joint (4, 4).
        frame: Out: the joints' frames (nj, 3, 4).
        tcp: Out: the tool frame (3, 4).
    """
    nj = turn.shape[0]
    for k in range(nj):
        c = turn[k, 0]
        s = -turn[k, 1]
        f = frame[k]
        for r in range(3):
            if k == 0:
                for col in range(4):
                    f[r, col] = placement[0, r, col]
            else:
                for col in range(4):
                    f[r, col] = dot4(frame[k - 1], r, placement[k], col)
            x = f[r, 0]
            y = f[r, 1]
            f[r, 0] = fma(x, c, -(y * s))
            f[r, 1] = fma(x, s, y * c)
    for r in range(3):
        for col in range(4):
            tcp[r, col] = dot4(frame[nj - 1], r, tool, col) if nj else tool[r, col]


@njit(cache=True, inline="always")
def jacobian_columns(frame: Any, tcp: Any, jac: Any) -> None:
    """Jacobian columns (6, nj) in chain order: linear ``z x (p_tool - p_joint)``, angular ``z``."""
    for k in range(frame.shape[0]):
        f = frame[k]
        d0 = tcp[0, 3] - f[0, 3]
        d1 = tcp[1, 3] - f[1, 3]
        d2 = tcp[2, 3] - f[2, 3]
        jac[0, k] = f[1, 2] * d2 - f[2, 2] * d1
        jac[1, k] = f[2, 2] * d0 - f[0, 2] * d2
        jac[2, k] = f[0, 2] * d1 - f[1, 2] * d0
        jac[3, k] = f[0, 2]
        jac[4, k] = f[1, 2]
        jac[5, k] = f[2, 2]


def parameters(dispatcher: Any) -> list[tuple[str, Any, int]]:
    """The arguments of a kernel's one compiled signature, in NumPy's terms.

    Returns:
        Per argument ``("array", dtype, ndim)``, or ``("bool" | "int" | "float", None, 0)``.
    """
    (signature,) = dispatcher.nopython_signatures  # compiled for exactly one
    out: list[tuple[str, Any, int]] = []
    for t in signature.args:
        if isinstance(t, types.Array):
            out.append(("array", as_dtype(t.dtype), t.ndim))
        elif isinstance(t, types.Boolean):
            out.append(("bool", None, 0))
        elif isinstance(t, types.Integer):
            out.append(("int", None, 0))
        else:
            out.append(("float", None, 0))
    return out
