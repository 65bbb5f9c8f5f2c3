"""Compiled kernels: Numba versions of the hottest NumPy loops of the robot checks.

These loops run as compiled kernels, one configuration (or one target) at a
time, where the NumPy code runs array operation after array operation over
all of them:

* the batched forward kinematics and Jacobian of a chain
  (:meth:`KinematicChain._forward <gcm_pipeline.robot.chain.KinematicChain>`), every
  joint's frame (:meth:`JointFrames.compute <gcm_pipeline.robot.chain.JointFrames>`), and
  the approach's deviation samples along joint segments
  (:func:`~gcm_pipeline.reach.deviation.segment_bounds`), and a move's joint path at
  its grid points through its waypoints (``_grid_points`` of
  :mod:`~gcm_pipeline.reach.path`): :mod:`~gcm_pipeline.robot.chain_kernel`;
* the IK's Levenberg-Marquardt iterations
  (:func:`~gcm_pipeline.robot.ik.lm.levenberg_marquardt`), per (target, seed) pair:
  :mod:`~gcm_pipeline.robot.ik.lm_kernel`;
* the Panda's closed form (:meth:`~gcm_pipeline.robot.ik.panda.PandaAnalyticIK.solve`),
  per (target, joint-7 value): :mod:`~gcm_pipeline.robot.ik.panda_kernel`;
* a 6R arm's closed-form branches after EAIK's answers (exact ones, one branch
  once, each at its 2 pi copy nearest a reference inside the limits:
  :meth:`~gcm_pipeline.robot.ik.analytic_6r.SixRAnalyticIK.solve`), per target:
  :mod:`~gcm_pipeline.robot.ik.analytic_6r_kernel`;
* levels 1 and 2 of the collision broad phase (one bounding sphere per
  geometry, then the sphere covers), level 3 (a robot polytope's hull
  vertices against a box of the world, or against a robot box in the
  frames of the box's joint) and level 4 (its longest edges inside a world
  primitive), see :mod:`gcm_pipeline.robot.collision`:
  :mod:`~gcm_pipeline.robot.collision.broadphase_kernel`;
* the clearance's steps before coal (the pairs' sphere bounds, the exact
  distances over a box's face, the hull vertices' bounds):
  :mod:`~gcm_pipeline.robot.collision.clearance_kernel`.

Each kernel module sits beside its NumPy reference; what they share (signature
types, the FMA, a chain's frames) is in :mod:`~gcm_pipeline.robot.kernel_common`.

**Loading.** :func:`get` returns them, or None for the NumPy code. Importing
the package does not import Numba: the first forward kinematics or collision
check of a process does, once, and compiles the kernels, or loads the machine
code an earlier process compiled from Numba's cache (``cache=True``: the
``__pycache__`` folder beside the package's sources, or Numba's folder in the
user's cache directory when that is not writable; ``NUMBA_CACHE_DIR`` moves
it). Compiling takes about 17 s, once per cache (a warning line says so after
3 s); loading about 0.7 s per process (the Numba import included). The
reachability engine loads them before it forks its workers, so the workers
inherit them.

**Switches.** ``GCM_JIT=0`` (or ``false``, ``off``, ``no``; read at each call)
selects the NumPy code, and so do Numba's ``NUMBA_DISABLE_JIT``, a Python
without Numba, a failing load (a warning says why) and :func:`suppressed`.
The NumPy code is the reference.

**Same answers.**

* Forward kinematics: the kernel sums each matrix product in the order of
  OpenBLAS's dgemm kernel (one FMA chain) and each complex product as
  NumPy's loop does, so on the x86-64 machine this was measured on the
  results equal NumPy's to the bit. That order is a property of the BLAS
  kernel picked at run time, so on another CPU the last bit may differ
  (the tests compare to 1e-12).
* Broad phase, levels 1 and 2: *conservative*. A pair is ruled out only when
  its bound clears the NumPy threshold by :data:`SLACK` (far above the
  round-off by which the two summation orders can differ), so every (pair,
  configuration) the NumPy levels leave open stays open; coal decides the
  few more that stay open, with the same answers.
* Level 3: stricter than the NumPy level on both sides by :data:`SLACK`
  (free when all hull vertices lie beyond one face plane by the margin plus
  the slack, colliding when one lies deeper than the depth plus the slack;
  against a cylinder, its cap planes and one side plane, the same way):
  whatever it decides, the NumPy level decides the same (against a robot's
  box or a cylinder the NumPy code leaves the pair to coal; its reference
  level is tested against the kernel); coal the rest.
* Level 4 (edges inside a primitive): colliding only where an edge point lies
  deeper than the depth plus the slack: the NumPy level decides the same.
* Every joint's frame (the collision checks' kinematics): the products in
  the same order as the NumPy code's, the angles' cosines and sines from one
  vectorised range reduction and fdlibm's polynomials (``chain_kernel.cos_sin``,
  within an ulp or two of libm's; the NumPy code takes them from ``exp(-i q)``):
  equal to round-off (tested to 1e-12, and against Pinocchio). The broad
  phase decides with margins far above round-off; the checks that use the
  frames without one (coal's answer for a carried object, a point in a mesh
  object) take libm's ``cos`` and ``sin``: the NumPy code's frames to the bit.
* Clearance: the NumPy code's arithmetic summed in another order, equal to
  round-off (tested to 1e-12 m). Which pairs coal measures follows from these
  numbers, so a bound within round-off of its threshold could send a pair to coal
  in one and not the other (either result within the clearance's contract); on the
  dense bottle's rows and 20,000 random ones (Panda, UR5 with its tool) the
  clearances were the same to 1e-16 m.
* The closed form: the same arithmetic and the same solutions; the angles
  differ by round-off (1e-13 rad measured; acos near +-1 can amplify an
  ulp to 2e-8 rad).
* A move's grid points: the NumPy code's differences, products and sums,
  each rounded once, in its order: equal to the bit (tested).
* A 6R arm's branches: the NumPy code's operations on each angle, each
  rounded once (IEEE: fmod and rint are exact), in the same order: the same
  branches and angles to the bit.
* The LM iterates each pair alone and solves its 6x6 system by Cholesky,
  and the deviation samples step each joint's sine and cosine by angle
  addition: their numbers differ from the NumPy code's in the last digits
  (the decisions of the reachability check were the same on every example
  config; iterations run long without the stall test amplify the digits,
  and so does a joint crossing its limit by an ulp, frozen in one and not
  the other: 3.7e-8 rad on one row of 3,000). The tests compare what does
  not depend on the CPU: convergence flags, each answer's pose error as
  Pinocchio computes it, the limits, the decisions.

**Any input.** Each kernel is compiled for one signature (C-contiguous
float64 and intp arrays); :class:`_Kernel` converts what a NumPy function
would take (other layouts, read-only arrays, safe dtype casts, empty
arrays of any dtype) before the call, so no input the NumPy code accepts
ends in Numba's "No matching definition".
"""

from __future__ import annotations

import contextlib
import functools
import logging
import operator
import os
import threading
from collections.abc import Callable, Iterator
from typing import Any, NamedTuple

import numpy as np

__all__ = [
    "COLLIDES",
    "FREE",
    "SHAPE_KINDS",
    "SLACK",
    "UNDECIDED",
    "Kernels",
    "blas_controller",
    "get",
    "one_blas_thread",
    "suppressed",
]

log = logging.getLogger(__name__)

#: Distance [m] by which a bound must clear a NumPy threshold before a
#: broad-phase kernel decides on it (the summation orders differ by ~1e-16 m).
SLACK = 1e-9
#: Kinds of world shapes the broad phase bounds exactly, by their code in a
#: packed shape row; any other shape is bounded by its box (code 3).
SHAPE_KINDS = ("sphere", "cylinder", "capsule", "box")
#: Values of ``GCM_JIT`` that select the NumPy code.
_OFF = ("0", "false", "off", "no")
#: Inside :func:`suppressed`.
_SUPPRESSED = False
#: Seconds of loading after which a line says that the kernels are being compiled.
_NOTICE_AFTER = 3.0
_COMPILING = (
    "compiling the package's kernels with Numba (once per install, about 20 s; "
    "later runs read them from Numba's cache)"
)
#: Level-3 answers of :attr:`Kernels.hull_vs_box`, :attr:`Kernels.hull_vs_robot_box` and
#: :attr:`Kernels.hull_vs_cylinder`.
FREE, COLLIDES, UNDECIDED = 0, 1, 2


class Kernels(NamedTuple):
    """The compiled kernels (Numba dispatchers); arguments as documented there.

    Attributes:
        chain_forward: Forward kinematics and Jacobian of a chain, (N, ...) at once.
        joint_frames: Every joint's frame of a tree of revolute joints, (J, N, 3, 4).
        broad_phase: Levels 1 and 2: the (pair, configuration) entries left open.
        hull_vs_box: Level 3: :data:`FREE`, :data:`COLLIDES` or :data:`UNDECIDED`.
        edges_inside: Level 4: where a robot polytope's edge lies inside a world primitive.
        levenberg_marquardt: The IK's Levenberg-Marquardt iterations, per (target, seed).
        segment_samples: The approach's deviation samples along joint segments.
        panda_ik: The Panda's closed-form IK, per (target, q7).
        cos_sin: The cosines and sines of angles (N, M), both from one range reduction.
        sphere_bounds: The clearance pairs' lower bounds from the sphere covers.
        face_distances: The clearance's exact distances of a polytope over a box's face.
        vertex_distances: The clearance's bounds from a polytope's nearest hull vertex.
        six_r_branches: A 6R arm's closed-form branches from EAIK's answers, per target.
        hull_vs_cylinder: Level 3 against a cylinder: :data:`FREE`, :data:`COLLIDES` or
            :data:`UNDECIDED`.
        hull_vs_robot_box: Level 3 against a robot's own box, in its joint's frame:
            :data:`FREE`, :data:`COLLIDES` or :data:`UNDECIDED`.
        hulls_apart: Level 3 of two robot polytopes: where a face of one's box
            separates them (free).
        grid_path: A move's joint path at its grid points, through its waypoints.
    """

    chain_forward: Callable[..., Any]
    broad_phase: Callable[..., Any]
    hull_vs_box: Callable[..., Any]
    levenberg_marquardt: Callable[..., Any]
    segment_samples: Callable[..., Any]
    panda_ik: Callable[..., Any]
    edges_inside: Callable[..., Any]
    joint_frames: Callable[..., Any]
    cos_sin: Callable[..., Any]
    sphere_bounds: Callable[..., Any]
    face_distances: Callable[..., Any]
    vertex_distances: Callable[..., Any]
    six_r_branches: Callable[..., Any]
    hull_vs_cylinder: Callable[..., Any]
    hull_vs_robot_box: Callable[..., Any]
    hulls_apart: Callable[..., Any]
    grid_path: Callable[..., Any]


@functools.cache
def blas_controller() -> Any:
    """The process's thread pools (BLAS), inspected once (it reads the loaded libraries)."""
    from threadpoolctl import ThreadpoolController

    return ThreadpoolController()


#: Fewest rows for which :func:`one_blas_thread` limits the pools (the limit costs ~8 us).
_BLAS_LIMIT_ROWS = 64


@contextlib.contextmanager
def one_blas_thread(rows: int = _BLAS_LIMIT_ROWS) -> Iterator[None]:
    """BLAS on one thread meanwhile, for work of ``rows`` rows (fewer: left as it is).

    The checks' matrix products are thin (rows by 3 by a link's vertices): BLAS's
    threads gain nothing there, and on a core another job keeps busy they wait
    for each other (``clearance`` of the dense bottle's reachable rows: 1.9x slower
    beside one busy process on two cores). The reachability engine runs every
    chunk so; this is for the checks called on their own.

    On the main thread only: the pools are process-wide, and blocks overlapping
    on several threads would each restore the limits they found (the last to
    leave could leave BLAS on one thread for good); OpenBLAS also ignores a
    limit set from another thread. Elsewhere the pools are left as they are.
    """
    if rows < _BLAS_LIMIT_ROWS or threading.current_thread() is not threading.main_thread():
        yield
        return
    with blas_controller().limit(limits=1, user_api="blas"):
        yield


def get() -> Kernels | None:
    """The compiled kernels, loaded on the first call of the process; None: use NumPy.

    None when the environment variable ``GCM_JIT`` is ``0`` (or ``false``,
    ``off``, ``no``), inside :func:`suppressed`, when Numba's own switch
    ``NUMBA_DISABLE_JIT`` is on, or when Numba cannot be imported or fails to
    compile them (a warning says why).
    """
    if os.environ.get("GCM_JIT", "").strip().lower() in _OFF or _SUPPRESSED:
        return None
    return _load()


@contextlib.contextmanager
def suppressed() -> Iterator[None]:
    """The NumPy code inside the block, without loading the kernels (e.g. a config check)."""
    global _SUPPRESSED
    before, _SUPPRESSED = _SUPPRESSED, True
    try:
        yield
    finally:
        _SUPPRESSED = before


def _import() -> Kernels | None:
    """The compiled kernels (importing their modules compiles them or reads the cache).

    None when Numba's ``NUMBA_DISABLE_JIT`` is on: its kernels would run as
    Python (far too slow, and the FMA intrinsic cannot run at all).
    """
    # The package's one guarded import of Numba: Numba and the kernel modules (which
    # import it at their top) are imported here, on the first call, never at module
    # top, so that importing the package does not import Numba.
    from numba.core import config

    if config.DISABLE_JIT:  # type: ignore[attr-defined]  # set at import, not declared
        log.info("NUMBA_DISABLE_JIT is on: the NumPy code is used")
        return None
    from gcm_pipeline.robot import chain_kernel, kernel_common
    from gcm_pipeline.robot.collision import broadphase_kernel, clearance_kernel
    from gcm_pipeline.robot.ik import analytic_6r_kernel, lm_kernel, panda_kernel

    return Kernels(
        *(
            _Kernel(dispatcher, kernel_common.parameters(dispatcher))
            for dispatcher in (
                chain_kernel.chain_forward,
                broadphase_kernel.broad_phase,
                broadphase_kernel.hull_vs_box,
                lm_kernel.levenberg_marquardt,
                chain_kernel.segment_samples,
                panda_kernel.panda_ik,
                broadphase_kernel.edges_inside,
                chain_kernel.joint_frames,
                chain_kernel.cos_sin,
                clearance_kernel.sphere_bounds,
                clearance_kernel.face_distances,
                clearance_kernel.vertex_distances,
                analytic_6r_kernel.six_r_branches,
                broadphase_kernel.hull_vs_cylinder,
                broadphase_kernel.hull_vs_robot_box,
                broadphase_kernel.hulls_apart,
                chain_kernel.grid_path,
            )
        )
    )


@functools.cache
def _load() -> Kernels | None:
    """Import (compile or load from the cache) the kernels, once per process."""
    # loading from the cache takes well under a second; longer means compiling: say so
    notice = threading.Timer(_NOTICE_AFTER, log.warning, (_COMPILING,))
    notice.daemon = True
    notice.start()
    try:
        return _import()
    except ImportError as exc:
        log.warning("Numba cannot be imported (%s): the NumPy code is used", exc)
        return None
    except Exception as exc:  # any failure of Numba leaves the NumPy code
        log.warning(
            "compiled kernels failed to load (%s: %s), NumPy code used; if Numba's cache is "
            "damaged, delete it (NUMBA_CACHE_DIR, or the __pycache__ folders under %s)",
            type(exc).__name__,
            exc,
            os.path.dirname(os.path.abspath(__file__)),
        )
        return None
    finally:
        notice.cancel()


class _Kernel:
    """A compiled kernel that takes its arguments as a NumPy function would.

    Each kernel is compiled for one signature: C-contiguous float64 or intp
    arrays of fixed dimensions, an integer, a float or a bool per scalar. A
    Numba dispatcher refuses anything else ("No matching definition"), so each
    array is first converted: to the kernel's dtype when the cast is safe
    (``np.can_cast(..., "safe")``: int32 to intp, float32 or an int to
    float64; bool) or when the array is empty (``np.array([])`` is float64,
    whatever it would have held), and to C order (a copy of a Fortran-order,
    strided, negatively strided or unaligned array; read-only arrays are
    taken as they are). Integer scalars must be integers
    (:func:`operator.index`), not floats that Numba would truncate.

    Raises:
        TypeError: An array of the wrong dimension or a dtype that does not
            cast safely (a float array of indices), naming the kernel and the
            argument: a caller's mistake, not an input to convert.
    """

    def __init__(self, dispatcher: Any, parameters: list[tuple[str, Any, int]]) -> None:
        """A dispatcher and its arguments (``kernel_common.parameters``)."""
        self.dispatcher = dispatcher
        self.__name__ = dispatcher.__name__
        self.__doc__ = dispatcher.__doc__
        scalar: dict[str, Callable[[Any], Any]] = {
            "bool": bool,
            "int": operator.index,
            "float": float,
        }
        self._convert: list[Callable[[Any], Any]] = [
            functools.partial(self._array, i, dtype, ndim) if kind == "array" else scalar[kind]
            for i, (kind, dtype, ndim) in enumerate(parameters)
        ]

    def _array(self, i: int, dtype: Any, ndim: int, value: Any) -> Any:
        if type(value) is np.ndarray and value.ndim == ndim and value.dtype == dtype:
            flags = value.flags
            if flags.c_contiguous and flags.aligned:
                return value  # as the kernel takes it (most calls): nothing to convert
        a = np.asarray(value)
        if a.ndim != ndim:
            raise TypeError(
                f"kernel {self.__name__}: argument {i} has {a.ndim} dimensions, not {ndim}"
            )
        if a.dtype != dtype:
            if a.size and not np.can_cast(a.dtype, dtype, "safe"):
                raise TypeError(
                    f"kernel {self.__name__}: argument {i} of dtype {a.dtype} does not cast "
                    f"safely to {dtype}"
                )
            a = a.astype(dtype)
        a = np.ascontiguousarray(a)
        return a if a.flags.aligned else a.copy()  # e.g. np.frombuffer at an odd offset

    def __call__(self, *args: Any) -> Any:
        if len(args) != len(self._convert):
            raise TypeError(
                f"kernel {self.__name__} takes {len(self._convert)} arguments, not {len(args)}"
            )
        return self.dispatcher(*(f(a) for f, a in zip(self._convert, args, strict=True)))
