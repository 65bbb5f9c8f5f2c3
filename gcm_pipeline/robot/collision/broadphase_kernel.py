"""Compiled kernels of the collision broad phase (levels 1 to 4).

Kernels of :class:`~gcm_pipeline.robot.collision.broadphase.BroadPhase` (the NumPy
reference, beside this module): :func:`broad_phase` (levels 1 and 2: one bounding
sphere per geometry, then the sphere covers), :func:`hull_vs_box`,
:func:`hull_vs_robot_box` and :func:`hull_vs_cylinder` (level 3: a robot polytope's
hull vertices against a world box, a robot's own box, a cylinder), :func:`hulls_apart`
(level 3 of two robot polytopes: a face of one's box between them) and
:func:`edges_inside` (level 4: its longest edges inside a box, sphere or cylinder).
Imported by
:func:`gcm_pipeline.robot.kernels.get` only (it imports Numba).
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
from numba import njit, types

from gcm_pipeline.robot.kernel_common import F1, F2, F3, F4, I1


@njit(cache=True, inline="always")
def _place(tf: Any, centre: Any, out: Any) -> None:
    """``out`` (3,) = the point ``centre`` (3,) fixed to a joint whose frame is ``tf`` (3, 4)."""
    for r in range(3):
        out[r] = tf[r, 0] * centre[0] + tf[r, 1] * centre[1] + tf[r, 2] * centre[2] + tf[r, 3]


@njit(cache=True, inline="always")
def _lower(p: Any, shape: Any) -> float:
    """Lower bound of the distance from point ``p`` (3,) to a world shape (a packed row).

    The row is ``ShapeBound.packed`` (:mod:`gcm_pipeline.robot.collision.broadphase`): the
    shape's inverse placement's first three rows (12), its kind, radius, half
    length, box centre (3), half sizes (3). The same bound as ``ShapeBound.lower``.
    """
    x = shape[0] * p[0] + shape[1] * p[1] + shape[2] * p[2] + shape[3]
    y = shape[4] * p[0] + shape[5] * p[1] + shape[6] * p[2] + shape[7]
    z = shape[8] * p[0] + shape[9] * p[1] + shape[10] * p[2] + shape[11]
    kind = int(shape[12])
    if kind == 0:  # sphere
        return max(math.sqrt(x * x + y * y + z * z) - shape[13], 0.0)
    if kind == 1:  # cylinder
        radial = max(math.sqrt(x * x + y * y) - shape[13], 0.0)
        axial = max(abs(z) - shape[14], 0.0)
        return math.sqrt(radial * radial + axial * axial)
    if kind == 2:  # capsule
        along = z - min(max(z, -shape[14]), shape[14])
        return max(math.sqrt(x * x + y * y + along * along) - shape[13], 0.0)
    bx = max(abs(x - shape[15]) - shape[18], 0.0)  # box
    by = max(abs(y - shape[16]) - shape[19], 0.0)
    bz = max(abs(z - shape[17]) - shape[20], 0.0)
    return math.sqrt(bx * bx + by * by + bz * bz)


@njit(cache=True, inline="always")
def _sq_gap(a: Any, b: Any) -> float:
    """Squared distance of two points (3,)."""
    d0 = a[0] - b[0]
    d1 = a[1] - b[1]
    d2 = a[2] - b[2]
    return d0 * d0 + d1 * d1 + d2 * d2


@njit(cache=True, inline="always")
def _column_gap(a: Any, b: Any, i: int) -> float:
    """Squared distance of the points ``a[:, i]`` and ``b[:, i]`` (columns of (3, m) arrays)."""
    d0 = a[0, i] - b[0, i]
    d1 = a[1, i] - b[1, i]
    d2 = a[2, i] - b[2, i]
    return d0 * d0 + d1 * d1 + d2 * d2


#: Configurations whose level 1 the broad phase computes together, one pair at a time
#: (a loop LLVM vectorises); their bounding spheres (3 coordinates each) stay in the
#: L1 cache.
CHUNK = 64


@njit(cache=True, inline="always")
def _place_point(tfs: Any, i0: int, m: int, j: int, centre: Any, k: int, out: Any) -> None:
    """``out[k, :, i]`` (3, m): point ``centre[k]`` of joint j's frame in configuration i0 + i."""
    c0, c1, c2 = centre[k, 0], centre[k, 1], centre[k, 2]
    for i in range(m):
        tf = tfs[j, i0 + i]
        for r in range(3):
            out[k, r, i] = tf[r, 0] * c0 + tf[r, 1] * c1 + tf[r, 2] * c2 + tf[r, 3]


@njit(cache=True, inline="always")
def _place_balls(tfs: Any, i0: int, m: int, ball_joint: Any, ball_centre: Any, ball: Any) -> None:
    """``ball[g, :, i]`` (G, 3, m): bounding sphere g's centre in configuration ``i0 + i``."""
    for g in range(ball_joint.shape[0]):
        _place_point(tfs, i0, m, ball_joint[g], ball_centre, g, ball)


@njit(cache=True, inline="always")
def _shape_numbers(s: Any) -> Any:
    """A packed shape row's numbers, read once before a loop over points.

    ``(placement, kind, radius, half, box)``: the inverse placement's first three
    rows (12), the kind's index, the radius, the half height, and a box's centre
    and half sizes (6) (:func:`_lower`'s row).
    """
    placement = (s[0], s[1], s[2], s[3], s[4], s[5], s[6], s[7], s[8], s[9], s[10], s[11])
    return placement, int(s[12]), s[13], s[14], (s[15], s[16], s[17], s[18], s[19], s[20])


@njit(cache=True, inline="always")
def _point_bound(p0: float, p1: float, p2: float, shape: Any) -> float:
    """:func:`_lower` of the point (p0, p1, p2) from a shape's :func:`_shape_numbers`.

    Its distance from the primitive, 0 inside; with the numbers as locals of the
    caller's loop, LLVM vectorises the loop (not one that inlines :func:`_lower`).
    """
    t, kind, radius, half, box = shape
    x = t[0] * p0 + t[1] * p1 + t[2] * p2 + t[3]
    y = t[4] * p0 + t[5] * p1 + t[6] * p2 + t[7]
    z = t[8] * p0 + t[9] * p1 + t[10] * p2 + t[11]
    if kind == 0:  # sphere
        return max(math.sqrt(x * x + y * y + z * z) - radius, 0.0)
    if kind == 1:  # cylinder
        radial = max(math.sqrt(x * x + y * y) - radius, 0.0)
        axial = max(abs(z) - half, 0.0)
        return math.sqrt(radial * radial + axial * axial)
    if kind == 2:  # capsule
        along = z - min(max(z, -half), half)
        return max(math.sqrt(x * x + y * y + along * along) - radius, 0.0)
    bx = max(abs(x - box[0]) - box[3], 0.0)  # box
    by = max(abs(y - box[1]) - box[4], 0.0)
    bz = max(abs(z - box[2]) - box[5], 0.0)
    return math.sqrt(bx * bx + by * by + bz * bz)


@njit(cache=True, inline="always")
def _world_level1(a: Any, m: int, s: Any, lim: float, near: Any) -> None:
    """``near[i]`` (m,): ``_lower(a[:, i], s) <= lim`` for points ``a`` (3, m).

    :func:`_lower`'s bound by :func:`_point_bound`, the shape's numbers read once
    (the shape kinds' tests compare both).
    """
    shape = _shape_numbers(s)
    for i in range(m):
        near[i] = _point_bound(a[0, i], a[1, i], a[2, i], shape) <= lim


@njit(cache=True, inline="always")
def _level1(
    ball: Any, m: int, geom_a: Any, geom_b: Any, world: Any, limit1: Any, shapes: Any, near: Any
) -> None:
    """``near[k, i]`` (P, m): pair k's bounding spheres within reach in configuration i."""
    for k in range(geom_a.shape[0]):
        a = ball[geom_a[k]]
        lim = limit1[k]
        w = world[k]
        if w < 0:
            b = ball[geom_b[k]]
            for i in range(m):
                near[k, i] = _column_gap(a, b, i) <= lim
        else:
            _world_level1(a, m, shapes[w], lim, near[k])


#: Level 2's routes through a chunk, pair by pair (``count``: the configurations level 1
#: left open there, of ``m``). A pair with ``count * DENSE >= m`` is tested in every
#: configuration at once (a loop LLVM vectorises), as is one with
#: ``count * 2 * DENSE >= m`` whose covers are placed for the chunk anyway; the others
#: in their open configurations only, each up to its first test within reach. A
#: geometry's covers are placed for the whole chunk (vectorised) when the counts of
#: its pairs add up to ``m / DENSE``, else in the configurations that need them, one by
#: one (random Panda configurations: ~5 of 64 open per pair, and every cover placed
#: for every chunk cost 0.1 us per configuration, a tenth of the check).
DENSE = 4


@njit(cache=True, inline="always")
def _place_cover(
    tfs: Any, i0: int, m: int, j: int, e0: int, e1: int, centre: Any, sphere: Any
) -> None:
    """``sphere[e, :, i]`` (S, 3, m): cover spheres ``e0 .. e1 - 1`` of joint j placed.

    In configuration ``i0 + i``; the arithmetic of :func:`_place_balls`.
    """
    for e in range(e0, e1):
        _place_point(tfs, i0, m, j, centre, e, sphere)


@njit(cache=True, inline="always")
def _plan_chunk(m: int, near: Any, geom_a: Any, geom_b: Any, world: Any, count: Any, whole: Any):
    """Level 2's plan of a chunk: ``count[k]`` (P,) and ``whole[g]`` (G,), by :data:`DENSE`.

    ``count[k]``: the configurations of the chunk's ``m`` that level 1 left open
    for pair k (``near`` (P, m)); ``whole[g]``: geometry g's covers are placed for
    the whole chunk (its pairs' counts add up to ``m / DENSE``).
    """
    whole[:] = 0
    for k in range(geom_a.shape[0]):
        c = 0
        for i in range(m):
            c += near[k, i]
        count[k] = c
        whole[geom_a[k]] += c
        if world[k] < 0:
            whole[geom_b[k]] += c
    for g in range(whole.shape[0]):
        whole[g] = whole[g] * DENSE >= m


@njit(cache=True, inline="always")
def _first_within(i: int, tests: Any, w: int, pair_tests: Any, shapes: Any, sphere: Any) -> bool:
    """Whether one of a pair's ``tests`` is within reach in column i of the placed covers.

    ``pair_tests`` is ``(sphere_a, sphere_b, limit2)``, ``w`` the pair's world
    shape (-1: a self pair), ``sphere`` the placed covers (S, 3, CHUNK).
    """
    sphere_a, sphere_b, limit2 = pair_tests
    for e in tests:
        a = sphere[sphere_a[e]]
        if w < 0:
            hit = _column_gap(a, sphere[sphere_b[e]], i) <= limit2[e]
        else:
            hit = _point_bound(a[0, i], a[1, i], a[2, i], _shape_numbers(shapes[w])) <= limit2[e]
        if hit:
            return True
    return False


@njit(cache=True, inline="always")
def _level2_open(
    m: int, near: Any, tests: Any, w: int, pair_tests: Any, shapes: Any, sphere: Any, out: Any
) -> None:
    """``out[i]`` (m,): a pair's level 2 in the configurations level 1 left open (``near``).

    Configuration by configuration, its tests ``tests`` until the first within
    reach (:func:`_first_within`).
    """
    for i in range(m):
        out[i] = near[i] and _first_within(i, tests, w, pair_tests, shapes, sphere)


@njit(cache=True, inline="always")
def _level2_all(
    m: int, near: Any, tests: Any, w: int, pair_tests: Any, shapes: Any, sphere: Any, out: Any
) -> None:
    """:func:`_level2_open` by every test in every configuration (vectorised), then ``near``.

    The same arithmetic per test, so the same answers; ``out`` (m,) is
    used as scratch.
    """
    sphere_a, sphere_b, limit2 = pair_tests
    out[:m] = False
    for e in tests:
        a = sphere[sphere_a[e]]
        lim = limit2[e]
        if w < 0:
            b = sphere[sphere_b[e]]
            for i in range(m):
                out[i] |= _column_gap(a, b, i) <= lim
        else:
            shape = _shape_numbers(shapes[w])
            for i in range(m):
                out[i] |= _point_bound(a[0, i], a[1, i], a[2, i], shape) <= lim
    for i in range(m):
        out[i] = out[i] and near[i]


@njit(cache=True, inline="always")
def _level2_pairs(
    i0: int,
    m: int,
    near: Any,
    count: Any,
    whole: Any,
    pairs: Any,
    pair_tests: Any,
    shapes: Any,
    sphere: Any,
    few: Any,
    open_: Any,
) -> int:
    """Level 2 of a chunk's pairs whose covers are placed for it, pair by pair.

    In every configuration at once or in the open ones (:data:`DENSE`), into
    ``open_[k, i0 : i0 + m]``; the other open pairs go to ``few`` (for
    :func:`_level2_each`). Returns how many did.
    """
    geom_a, geom_b, world, first_test, n_tests = pairs
    hit = np.empty(m, dtype=np.bool_)
    nfew = 0
    for k in range(geom_a.shape[0]):
        if count[k] == 0:
            continue
        tests = range(first_test[k], first_test[k] + n_tests[k])
        placed = whole[geom_a[k]] and (world[k] >= 0 or whole[geom_b[k]])
        if count[k] * DENSE >= m or (placed and count[k] * 2 * DENSE >= m):
            _level2_all(m, near[k], tests, world[k], pair_tests, shapes, sphere, hit)
        elif placed:
            _level2_open(m, near[k], tests, world[k], pair_tests, shapes, sphere, hit)
        else:
            few[nfew] = k
            nfew += 1
            continue
        open_[k, i0 : i0 + m] = hit
    return nfew


@njit(cache=True, inline="always")
def _level2_each(
    tfs: Any,
    i0: int,
    m: int,
    near: Any,
    few: Any,
    cover: Any,
    pairs: Any,
    pair_tests: Any,
    shapes: Any,
    sphere: Any,
    open_: Any,
) -> None:
    """Level 2 of the pairs ``few`` configuration by configuration, placing covers on the way.

    A geometry's covers not placed for the whole chunk (``cover`` is
    ``(ball_joint, sphere_centre, sphere_start, whole, placed)``; ``placed[g]``:
    the configuration they were last placed in) are placed in column i of
    ``sphere`` when a pair first needs them in configuration ``i0 + i``.
    ``pairs`` is ``(geom_a, geom_b, world, first_test, n_tests)``.
    """
    ball_joint, sphere_centre, sphere_start, whole, placed = cover
    geom_a, geom_b, world, first_test, n_tests = pairs
    for i in range(m):
        for k in few:
            if not near[k, i]:
                continue
            w = world[k]
            for g in (geom_a[k], geom_b[k] if w < 0 else geom_a[k]):
                if not whole[g] and placed[g] != i0 + i:
                    placed[g] = i0 + i
                    e0, e1 = sphere_start[g], sphere_start[g + 1]
                    _place_cover(
                        tfs, i0 + i, 1, ball_joint[g], e0, e1, sphere_centre, sphere[:, :, i:]
                    )
            tests = range(first_test[k], first_test[k] + n_tests[k])
            open_[k, i0 + i] = _first_within(i, tests, w, pair_tests, shapes, sphere)


@njit(
    types.boolean[:, ::1](F4, I1, F2, F2, I1, I1, I1, I1, F1, I1, I1, I1, I1, F1, F2),
    cache=True,
)
def broad_phase(
    tfs,
    ball_joint,
    ball_centre,
    sphere_centre,
    sphere_start,
    geom_a,
    geom_b,
    world,
    limit1,
    first_test,
    n_tests,
    sphere_a,
    sphere_b,
    limit2,
    shapes,
):
    """Levels 1 and 2 of the broad phase: the (pair, configuration) entries left open.

    Pair ``k`` is a self pair when ``world[k] < 0`` (geometries ``geom_a[k]``
    and ``geom_b[k]``), else geometry ``geom_a[k]`` against the world shape
    ``shapes[world[k]]``. It stays open in a configuration when (1) its
    bounding spheres are within reach, ``|ca - cb|^2 <= limit1[k]`` (self) or
    ``lower(ca) <= limit1[k]`` (world), and (2) one of its sphere tests
    ``e = first_test[k] .. first_test[k] + n_tests[k] - 1`` is within reach:
    ``|pa - pb|^2 <= limit2[e]`` or ``lower(pa) <= limit2[e]``. The limits
    hold the radii, the margin and the slack.

    Level 1 runs over :data:`CHUNK` configurations at a time, pair by pair
    (vectorised, no branch per pair); level 2 chunk by chunk too, by the routes
    of :data:`DENSE`: the cover spheres of the geometries many of the chunk's
    configurations need are placed for the whole chunk, then the pairs many
    configurations left open are tested in all of them (vectorised), the others
    in their open ones, each up to its first test within reach (pair by pair
    where their covers are placed for the chunk, else configuration by
    configuration, placing the covers a configuration needs). The same
    arithmetic as one configuration at a time, so the same answers.

    Args:
        tfs: Joint frames (J, N, 3, 4).
        ball_joint: Joint of each geometry (G,): its bounding sphere's and its cover
            spheres' (:func:`~gcm_pipeline.robot.collision.spheres.robot_covers`).
        ball_centre: The bounding spheres' centres in the joints' frames (G, 3) [m].
        sphere_centre: Cover sphere centres in the joints' frames (S, 3) [m].
        sphere_start: Cover spheres of geometry g:
            ``sphere_start[g] .. sphere_start[g + 1] - 1`` (G + 1,).
        geom_a: Robot geometry of each pair (P,).
        geom_b: The other robot geometry of a self pair (P,).
        world: Row of ``shapes`` of a world pair, -1 for a self pair (P,).
        limit1: Level-1 limit of each pair (P,).
        first_test: First sphere test of each pair (P,).
        n_tests: Number of sphere tests of each pair (P,).
        sphere_a: Cover sphere of ``geom_a`` of each test (E,).
        sphere_b: Cover sphere of ``geom_b`` of a self pair's test (E,).
        limit2: Level-2 limit of each test (E,).
        shapes: World shapes as packed rows (W, 21) (see :func:`_lower`).

    Returns:
        (P, N) bool: True where the pair is left open.
    """
    n = tfs.shape[1]
    npairs = geom_a.shape[0]
    ngeoms = ball_joint.shape[0]
    open_ = np.zeros((npairs, n), dtype=np.bool_)
    ball = np.empty((ngeoms, 3, CHUNK))
    near = np.empty((npairs, CHUNK), dtype=np.bool_)
    sphere = np.empty((sphere_centre.shape[0], 3, CHUNK))
    count = np.empty(npairs, dtype=np.intp)
    whole = np.empty(ngeoms, dtype=np.intp)
    placed = np.full(ngeoms, -1)
    few = np.empty(npairs, dtype=np.intp)
    cover = (ball_joint, sphere_centre, sphere_start, whole, placed)
    pairs = (geom_a, geom_b, world, first_test, n_tests)
    pair_tests = (sphere_a, sphere_b, limit2)
    for i0 in range(0, n, CHUNK):
        m = min(CHUNK, n - i0)
        # 1. one bounding sphere per geometry
        _place_balls(tfs, i0, m, ball_joint, ball_centre, ball)
        _level1(ball, m, geom_a, geom_b, world, limit1, shapes, near)
        # 2. the sphere covers: those many configurations need, for the whole chunk
        _plan_chunk(m, near, geom_a, geom_b, world, count, whole)
        for g in range(ngeoms):
            if whole[g]:
                e0, e1 = sphere_start[g], sphere_start[g + 1]
                _place_cover(tfs, i0, m, ball_joint[g], e0, e1, sphere_centre, sphere)
        nfew = _level2_pairs(
            i0, m, near, count, whole, pairs, pair_tests, shapes, sphere, few, open_
        )
        # the others configuration by configuration, their covers placed on the way
        _level2_each(tfs, i0, m, near, few[:nfew], cover, pairs, pair_tests, shapes, sphere, open_)
    return open_


@njit(cache=True, inline="always")
def _beyond_nearest_face(rot: Any, off: Any, verts: Any, mid: Any, beyond: Any) -> bool:
    """Whether every vertex lies beyond the plane of the box face nearest their centroid.

    One coordinate per vertex, stopping at the first vertex short of the plane: the
    free configurations of :func:`hull_vs_box` are mostly proven by this face
    alone; the full test runs where it fails (the same answers).
    """
    axis, gap = 0, -np.inf
    for a in range(3):
        c = rot[a, 0] * mid[0] + rot[a, 1] * mid[1] + rot[a, 2] * mid[2] + off[a]
        if abs(c) - beyond[a] > gap:
            axis, gap = a, abs(c) - beyond[a]
            sign = 1.0 if c >= 0.0 else -1.0
    r0, r1, r2, o, lim = rot[axis, 0], rot[axis, 1], rot[axis, 2], off[axis], beyond[axis]
    for v in range(verts.shape[1]):
        x = r0 * verts[0, v] + r1 * verts[1, v] + r2 * verts[2, v] + o
        if not sign * x > lim:
            return False
    return True


#: How far [m] the box of :func:`_enclosing_corners` reaches beyond the vertices: far more
#: than the rounding of a vertex's or a corner's coordinates (about 1e-15 m), so that
#: a corner beyond a face puts every vertex beyond it in floating point too.
CORNER_PAD = 1e-9


@njit(cache=True)
def _enclosing_corners(verts: Any) -> tuple[Any, Any]:
    """The corners (3, 8 K) of K boxes holding the vertices, padded; the centre (3,) of all.

    In the vertices' frame. A long hull (its longest extent more than twice the
    next: an arm link) is cut across the middle of that extent and each half
    gets its own box (K = 2), which hugs the hull closer than one box does;
    otherwise one box (K = 1). Every vertex (3, V) is a convex combination of
    the corners of its half's box, ``CORNER_PAD`` inside it: a plane every
    corner lies beyond by ``d`` has every vertex beyond it by more than ``d``.
    """
    lo = np.empty(3)
    hi = np.empty(3)
    for a in range(3):
        lo[a] = verts[a].min() - CORNER_PAD
        hi[a] = verts[a].max() + CORNER_PAD
    extent = hi - lo
    order = np.argsort(extent)
    long = order[2]
    parts = 2 if extent[long] > 2.0 * extent[order[1]] else 1
    cut = 0.5 * (lo[long] + hi[long])
    corners = np.empty((3, 8 * parts))
    for p in range(parts):
        # the half p of the vertices (both halves hold the vertices on the cut)
        plo = np.full(3, np.inf)
        phi = np.full(3, -np.inf)
        for v in range(verts.shape[1]):
            x = verts[long, v]
            if parts == 1 or (x <= cut if p == 0 else x >= cut):
                for a in range(3):
                    plo[a] = min(plo[a], verts[a, v])
                    phi[a] = max(phi[a], verts[a, v])
        for c in range(8):
            for a in range(3):
                corners[a, 8 * p + c] = phi[a] + CORNER_PAD if (c >> a) & 1 else plo[a] - CORNER_PAD
    return corners, 0.5 * (lo + hi)


@njit(cache=True, inline="always")
def _in_shape_frame(inv: Any, tf: Any, rot: Any, off: Any) -> None:
    """``rot`` (3, 3), ``off`` (3,): the joint frame ``tf`` (3, 4) in a shape's, ``inv @ tf``."""
    for a in range(3):
        for b in range(4):
            v = inv[a, 0] * tf[0, b] + inv[a, 1] * tf[1, b] + inv[a, 2] * tf[2, b]
            if b < 3:
                rot[a, b] = v
            else:
                off[a] = v + inv[a, 3]


@njit(cache=True, inline="always")
def _hull_box_status(
    rot: Any, off: Any, verts: Any, mid: Any, corners: Any, centre: Any, beyond: Any, deep: Any
) -> int:
    """Level 3 of one configuration: the hull ``verts`` (3, V) placed by ``rot``, ``off``.

    ``rot`` (3, 3) and ``off`` (3,) take the joint's frame into the box's; ``mid``
    is the vertices' centroid and ``corners``, ``centre`` the boxes of
    :func:`_enclosing_corners`. Returns 0 free, 1 collides, 2 undecided (see
    :func:`hull_vs_box`).
    """
    nv = verts.shape[1]
    # the 8 corners of a box holding the hull first: beyond a face, so is every vertex
    if nv > corners.shape[1] and _beyond_nearest_face(rot, off, corners, centre, beyond):
        return 0
    if _beyond_nearest_face(rot, off, verts, mid, beyond):
        return 0
    above0 = above1 = above2 = below0 = below1 = below2 = True
    for v in range(nv):
        x0 = rot[0, 0] * verts[0, v] + rot[0, 1] * verts[1, v]
        x0 += rot[0, 2] * verts[2, v] + off[0]
        x1 = rot[1, 0] * verts[0, v] + rot[1, 1] * verts[1, v]
        x1 += rot[1, 2] * verts[2, v] + off[1]
        x2 = rot[2, 0] * verts[0, v] + rot[2, 1] * verts[1, v]
        x2 += rot[2, 2] * verts[2, v] + off[2]
        above0 = above0 and x0 > beyond[0]
        below0 = below0 and x0 < -beyond[0]
        above1 = above1 and x1 > beyond[1]
        below1 = below1 and x1 < -beyond[1]
        above2 = above2 and x2 > beyond[2]
        below2 = below2 and x2 < -beyond[2]
        if abs(x0) < deep[0] and abs(x1) < deep[1] and abs(x2) < deep[2]:
            return 1
    if above0 or below0 or above1 or below1 or above2 or below2:
        return 0
    return 2


@njit(cache=True, inline="always")
def _centroid(verts: Any) -> Any:
    """The centroid (3,) of vertices (3, V), summed in the order of :func:`hull_vs_box`."""
    nv = verts.shape[1]
    mid = np.zeros(3)
    for v in range(nv):
        for a in range(3):
            mid[a] += verts[a, v] / nv
    return mid


@njit(types.int8[::1](F3, I1, F2, F2, F1, F1), cache=True)
def hull_vs_box(tfs, rows, verts, inv, beyond, deep):
    """Level 3 of the broad phase: a robot polytope's hull vertices against a box.

    In the box's frame, ``x = inv @ T @ [v; 1]`` for each hull vertex ``v``.
    The 8 corners of the vertices' box in the joint's frame, or the 16 of the
    two halves' boxes of a long hull (:func:`_enclosing_corners`), are tested
    first: beyond a face, every vertex is, and the row is free at the cost of
    8 or 16 vertices (the UR5's upper arm over the table: 171; its forearm
    against the 2F-85's body: 220). The same answers as testing the vertices.

    Args:
        tfs: Frames of the polytope's joint (N, 3, 4).
        rows: Configurations to decide (M,).
        verts: Hull vertices (3, V) in the joint's frame [m].
        inv: The box's inverse placement (4, 4).
        beyond: Free when, along one axis ``a``, every vertex has
            ``x_a > beyond[a]`` or every vertex ``x_a < -beyond[a]`` (3,).
        deep: Collides when a vertex has ``|x_a| < deep[a]`` on all three axes (3,).

    Returns:
        (M,) int8: 0 free, 1 collides, 2 undecided.
    """
    m = rows.shape[0]
    out = np.empty(m, dtype=np.int8)
    rot = np.empty((3, 3))
    off = np.empty(3)
    mid = _centroid(verts)  # the joint's frame
    corners, centre = _enclosing_corners(verts)
    for r in range(m):
        _in_shape_frame(inv, tfs[rows[r]], rot, off)
        out[r] = _hull_box_status(rot, off, verts, mid, corners, centre, beyond, deep)
    return out


@njit(cache=True, inline="always")
def _frame_in(tfs: Any, j: int, base: int, i: int, rel: Any) -> None:
    """``rel`` (3, 4): joint j's frame in joint ``base``'s in configuration i.

    ``Rb^T Ra`` and ``Rb^T (pa - pb)`` (the arithmetic of
    ``broadphase.relative_transforms``).
    """
    a, b = tfs[j, i], tfs[base, i]
    d0, d1, d2 = a[0, 3] - b[0, 3], a[1, 3] - b[1, 3], a[2, 3] - b[2, 3]
    for r in range(3):
        for k in range(3):
            rel[r, k] = b[0, r] * a[0, k] + b[1, r] * a[1, k] + b[2, r] * a[2, k]
        rel[r, 3] = b[0, r] * d0 + b[1, r] * d1 + b[2, r] * d2


@njit(types.int8[::1](F4, types.intp, types.intp, I1, F2, F2, F1, F1), cache=True)
def hull_vs_robot_box(tfs, joint, box_joint, rows, verts, inv, beyond, deep):
    """:func:`hull_vs_box` against a robot's own box (a gripper body from the registry).

    The polytope's joint frame is taken into the box's joint's (``Rb^T Ra``,
    ``Rb^T (pa - pb)``, the arithmetic of ``broadphase.relative_transforms``)
    configuration by configuration, then into the box's frame by ``inv`` (its
    inverse placement on that joint): no (M, 3, 4) array of relative frames.

    Args:
        tfs: Every joint's frames (J, N, 3, 4).
        joint: The polytope's joint.
        box_joint: The box's joint.
        rows: Configurations to decide (M,).
        verts: Hull vertices (3, V) in the polytope's joint's frame [m].
        inv: The box's inverse placement in its joint's frame (4, 4).
        beyond: As :func:`hull_vs_box` (3,).
        deep: As :func:`hull_vs_box` (3,).

    Returns:
        (M,) int8: 0 free, 1 collides, 2 undecided.
    """
    m = rows.shape[0]
    out = np.empty(m, dtype=np.int8)
    rel = np.empty((3, 4))
    rot = np.empty((3, 3))
    off = np.empty(3)
    mid = _centroid(verts)
    corners, centre = _enclosing_corners(verts)
    for r in range(m):
        _frame_in(tfs, joint, box_joint, rows[r], rel)
        _in_shape_frame(inv, rel, rot, off)
        out[r] = _hull_box_status(rot, off, verts, mid, corners, centre, beyond, deep)
    return out


@njit(cache=True, inline="always")
def _beyond_box(
    tfs: Any,
    j: int,
    base: int,
    i: int,
    verts: Any,
    box: Any,
    mid: Any,
    corners: Any,
    centre: Any,
    scratch: Any,
) -> bool:
    """Whether every vertex (3, V) of joint j lies beyond a face of joint ``base``'s ``box``.

    In configuration i; ``box`` is (centre, half sizes plus the margin) in
    ``base``'s frame, ``mid``, ``corners`` and ``centre`` the vertices' centroid and
    boxes (:func:`_hull_box_status`'s), ``scratch`` three arrays (3, 4), (3, 3), (3,).
    """
    rel, rot, off = scratch
    _frame_in(tfs, j, base, i, rel)
    for a in range(3):
        for k in range(3):
            rot[a, k] = rel[a, k]
        off[a] = rel[a, 3] - box[0, a]
    never = (-1.0, -1.0, -1.0)  # no vertex is this deep: never "collides"
    return _hull_box_status(rot, off, verts, mid, corners, centre, box[1], never) == 0


@njit(types.boolean[::1](F4, types.intp, types.intp, I1, F2, F2, F2, F2), cache=True)
def hulls_apart(tfs, joint_a, joint_b, rows, verts_a, box_a, verts_b, box_b):
    """Level 3 of a self pair of two robot polytopes: a face of one's box between them.

    Each polytope's hull vertices lie in a box of its joint's frame (the box of
    those vertices: it holds the hull, so the geometry). The pair is free where
    every hull vertex of b lies beyond the plane of one face of a's box by more
    than the margin, or every one of a beyond a face of b's box: the plane
    separates the two hulls (the test of :func:`hull_vs_box`, its corners first,
    never "collides": a vertex inside the other's box is no contact).

    Args:
        tfs: Every joint's frames (J, N, 3, 4).
        joint_a: Polytope a's joint.
        joint_b: Polytope b's joint.
        rows: Configurations to decide (M,).
        verts_a: a's hull vertices (3, Va) in its joint's frame [m].
        box_a: a's box (2, 3): its centre in the joint's frame, then its half
            sizes plus the margin (a vertex beyond that is apart) [m].
        verts_b: As ``verts_a``, of b (3, Vb).
        box_b: As ``box_a``, of b.

    Returns:
        (M,) bool: True where the pair is proved free.
    """
    m = rows.shape[0]
    out = np.zeros(m, dtype=np.bool_)
    scratch = (np.empty((3, 4)), np.empty((3, 3)), np.empty(3))
    mid_a, mid_b = _centroid(verts_a), _centroid(verts_b)
    corners_a, centre_a = _enclosing_corners(verts_a)
    corners_b, centre_b = _enclosing_corners(verts_b)
    for r in range(m):
        i = rows[r]
        out[r] = _beyond_box(
            tfs, joint_b, joint_a, i, verts_b, box_a, mid_b, corners_b, centre_b, scratch
        ) or _beyond_box(
            tfs, joint_a, joint_b, i, verts_a, box_b, mid_a, corners_a, centre_a, scratch
        )
    return out


@njit(cache=True, inline="always")
def _slab(x: float, dx: float, half: float, lo: float, hi: float) -> tuple[float, float]:
    """``[lo, hi]`` narrowed to the t with ``|x + t dx| < half``."""
    if dx == 0.0:
        if abs(x) < half:
            return lo, hi
        return 1.0, 0.0
    t0 = (-half - x) / dx
    t1 = (half - x) / dx
    if t0 > t1:
        t0, t1 = t1, t0
    return max(lo, t0), min(hi, t1)


@njit(cache=True, inline="always")
def _segment_inside(a: Any, b: Any, shape: Any, depth: float) -> bool:
    """Whether a point of the segment ``a``-``b`` (shape frame) lies deeper than ``depth`` in it."""
    kind = int(shape[12])
    dx, dy, dz = b[0] - a[0], b[1] - a[1], b[2] - a[2]
    lo, hi = 0.0, 1.0
    if kind == 3:  # box
        hx, hy, hz = shape[18] - depth, shape[19] - depth, shape[20] - depth
        if hx <= 0.0 or hy <= 0.0 or hz <= 0.0:
            return False
        lo, hi = _slab(a[0] - shape[15], dx, hx, lo, hi)
        lo, hi = _slab(a[1] - shape[16], dy, hy, lo, hi)
        lo, hi = _slab(a[2] - shape[17], dz, hz, lo, hi)
        return lo < hi
    if kind == 0:  # sphere
        r = shape[13] - depth
        if r <= 0.0:
            return False
        dd = dx * dx + dy * dy + dz * dz
        t = 0.0
        if dd > 0.0:
            t = min(max(-(a[0] * dx + a[1] * dy + a[2] * dz) / dd, 0.0), 1.0)
        px, py, pz = a[0] + t * dx, a[1] + t * dy, a[2] + t * dz
        return px * px + py * py + pz * pz < r * r
    if kind == 1:  # cylinder along z
        r, half = shape[13] - depth, shape[14] - depth
        if r <= 0.0 or half <= 0.0:
            return False
        lo, hi = _slab(a[2], dz, half, lo, hi)
        qa = dx * dx + dy * dy
        qc = a[0] * a[0] + a[1] * a[1] - r * r
        if qa <= 0.0:
            return qc < 0.0 and lo < hi
        qb = 2.0 * (a[0] * dx + a[1] * dy)
        disc = qb * qb - 4.0 * qa * qc
        if disc <= 0.0:
            return False
        root = math.sqrt(disc)
        lo = max(lo, (-qb - root) / (2.0 * qa))
        hi = min(hi, (-qb + root) / (2.0 * qa))
        return lo < hi
    return False


@njit(types.boolean[::1](F3, I1, F2, F2, F1, types.float64), cache=True)
def edges_inside(tfs, rows, ends_a, ends_b, shape, depth):
    """Level 4 of the broad phase: a robot polytope's edges inside a world primitive.

    The edge ends are placed by the joint's frame, then taken into the shape's
    frame by its packed row's inverse placement (as :func:`_lower`).

    Args:
        tfs: Frames of the polytope's joint (N, 3, 4).
        rows: Configurations to decide (M,).
        ends_a: First ends of the edges (3, E) in the joint's frame [m].
        ends_b: Second ends (3, E).
        shape: The world shape's packed row (21,): a box, sphere or cylinder.
        depth: A point must lie deeper than this inside the shape [m].

    Returns:
        (M,) bool: True where an edge reaches deeper than ``depth`` (the pair collides).
    """
    m = rows.shape[0]
    out = np.zeros(m, dtype=np.bool_)
    rot = np.empty((3, 3))
    off = np.empty(3)
    a = np.empty(3)
    b = np.empty(3)
    for r in range(m):
        tf = tfs[rows[r]]
        for i in range(3):
            for j in range(4):
                v = shape[4 * i] * tf[0, j] + shape[4 * i + 1] * tf[1, j]
                v += shape[4 * i + 2] * tf[2, j]
                if j < 3:
                    rot[i, j] = v
                else:
                    off[i] = v + shape[4 * i + 3]
        for e in range(ends_a.shape[1]):
            for i in range(3):
                a[i] = rot[i, 0] * ends_a[0, e] + rot[i, 1] * ends_a[1, e]
                a[i] += rot[i, 2] * ends_a[2, e] + off[i]
                b[i] = rot[i, 0] * ends_b[0, e] + rot[i, 1] * ends_b[1, e]
                b[i] += rot[i, 2] * ends_b[2, e] + off[i]
            if _segment_inside(a, b, shape, depth):
                out[r] = True
                break
    return out


@njit(cache=True)
def _vertex_box(verts: Any) -> Any:
    """The box (2, 3) of vertices (3, V): its centre, then its half sizes."""
    box = np.empty((2, 3))
    for a in range(3):
        lo, hi = verts[a].min(), verts[a].max()
        box[0, a], box[1, a] = 0.5 * (lo + hi), 0.5 * (hi - lo)
    return box


@njit(cache=True, inline="always")
def _cylinder_beyond_box(
    rot: Any, off: Any, radius: float, half: float, box: Any, beyond: float
) -> bool:
    """Whether a cylinder lies wholly beyond a face of ``box`` (2, 3), by more than ``beyond``.

    ``rot``, ``off`` take the box's frame (a joint's) into the cylinder's (axis
    z, centred): there the cylinder's centre is ``-rot^T off`` and its axis
    ``rot[2]``. Along the box's axis ``a`` the cylinder's extent from its centre is
    ``half |axis_a| + radius sqrt(1 - axis_a^2)`` (a solid cylinder's support).
    """
    for a in range(3):
        c = -(rot[0, a] * off[0] + rot[1, a] * off[1] + rot[2, a] * off[2]) - box[0, a]
        ax = rot[2, a]
        reach = half * abs(ax) + radius * math.sqrt(max(1.0 - ax * ax, 0.0))
        gap = box[1, a] + beyond
        if c - reach > gap or -c - reach > gap:
            return True
    return False


@njit(types.int8[::1](F3, I1, F2, F2, F1), cache=True)
def hull_vs_cylinder(tfs, rows, verts, inv, limits):
    """Level 3 of the broad phase against a cylinder: a robot polytope's hull vertices.

    In the cylinder's frame (axis z), ``x = inv @ T @ [v; 1]`` for each hull
    vertex ``v``. Free when the whole cylinder lies beyond a face of the box of
    the vertices in the joint's frame (:func:`_cylinder_beyond_box`: the UR5's
    upper arm beside the bottle), when every vertex lies beyond a cap's plane, or
    beyond the side plane tangent to the cylinder across the direction ``u`` from
    its axis to the vertices' centroid (``u . x > radius + beyond``, a plane the
    cylinder lies wholly behind); collides when a vertex lies deeper than ``deep`` inside it
    (``x^2 + y^2 < (radius - deep)^2`` and ``|z| < half - deep``): a hull vertex
    is a vertex of the geometry's triangles, a point of it.

    Args:
        tfs: Frames of the polytope's joint (N, 3, 4).
        rows: Configurations to decide (M,).
        verts: Hull vertices (3, V) in the joint's frame [m].
        inv: The cylinder's inverse placement (4, 4).
        limits: ``(radius, half length, beyond, deep)`` (4,) [m].

    Returns:
        (M,) int8: 0 free, 1 collides, 2 undecided.
    """
    radius, half, beyond, deep = limits[0], limits[1], limits[2], limits[3]
    inner = radius - deep
    inner_sq = inner * inner if inner > 0.0 and half > deep else -1.0  # no depth test
    m = rows.shape[0]
    nv = verts.shape[1]
    out = np.empty(m, dtype=np.int8)
    rot = np.empty((3, 3))
    off = np.empty(3)
    mid = _centroid(verts)  # the joint's frame
    box = _vertex_box(verts)
    for r in range(m):
        _in_shape_frame(inv, tfs[rows[r]], rot, off)
        if _cylinder_beyond_box(rot, off, radius, half, box, beyond):
            out[r] = 0
            continue
        cx = rot[0, 0] * mid[0] + rot[0, 1] * mid[1] + rot[0, 2] * mid[2] + off[0]
        cy = rot[1, 0] * mid[0] + rot[1, 1] * mid[1] + rot[1, 2] * mid[2] + off[1]
        norm = math.sqrt(cx * cx + cy * cy)
        ux, uy = (cx / norm, cy / norm) if norm > 0.0 else (0.0, 0.0)
        above = below = side = True
        inside = False
        for v in range(nv):
            x = rot[0, 0] * verts[0, v] + rot[0, 1] * verts[1, v] + rot[0, 2] * verts[2, v] + off[0]
            y = rot[1, 0] * verts[0, v] + rot[1, 1] * verts[1, v] + rot[1, 2] * verts[2, v] + off[1]
            z = rot[2, 0] * verts[0, v] + rot[2, 1] * verts[1, v] + rot[2, 2] * verts[2, v] + off[2]
            above = above and z > half + beyond
            below = below and z < -half - beyond
            side = side and ux * x + uy * y > radius + beyond
            if x * x + y * y < inner_sq and abs(z) < half - deep:
                inside = True
                break
        if inside:
            out[r] = 1
        elif above or below or (side and norm > 0.0):
            out[r] = 0
        else:
            out[r] = 2
    return out
