"""The broad phase: which (configuration, pair) entries coal must decide.

Vectorised over all configurations (NumPy), in four levels. Every robot
collision geometry is covered by a few spheres
(:func:`~gcm_pipeline.robot.collision.spheres.sphere_cover`: the geometry
cut into slabs along its long axis, each slab's part inside one sphere, so the
union of the spheres contains the geometry) and by one sphere around those; all are placed for all
configurations at once by vectorised forward kinematics
(:class:`~gcm_pipeline.robot.chain.JointFrames`). (1) A pair whose bounding
spheres are apart (from each other, or from the world shape: exact point
distances for boxes, cylinders, spheres and capsules, the local bounding box
of meshes) cannot collide; (2) nor can one whose sphere covers are apart.
(3) A robot polytope against a box (the table, box obstacles; with the
compiled kernels also a robot's own box: a gripper body from the registry
against an arm link) is free when its convex hull's vertices all lie beyond
the plane of one face of the box, and collides when one of them lies more
than 0.1 mm inside the box (the vertex of one of its triangles; shallower
ones are left to coal). With the compiled kernels, against a cylinder (the
bottle) the same, with its cap planes and the side plane tangent to it
across the direction from its axis to the vertices' centroid (a plane the
whole cylinder lies behind). (4) A robot
polytope against a box, a sphere or a cylinder collides when a point of one of
its :data:`EDGE_COUNT` longest triangle edges lies more than 0.1 mm inside the
shape (:func:`segments_inside`: an edge is part of the surface coal checks; a
long link crossing a thin table has no vertex inside it).
These levels only skip work, they never change an answer (tested pair by pair
against coal on every pair). The compiled kernels (:mod:`gcm_pipeline.robot.kernels`)
run the same four levels one configuration at a time, conservatively, and
level 3 on a robot's own boxes too (the NumPy code leaves those pairs to coal:
its test of every vertex costs more there than coal's hull check): the same
answers. The NumPy code leaves a robot polytope against a robot box or a
cylinder to coal (:func:`_world_cylinder_level` is the reference of the
cylinder's kernel): its test of every vertex costs more there than coal's hull
check (the UR5's dense bottle: 0.33 s on 61,006 rows, to save coal 0.07 s).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any, NamedTuple

import coal
import numpy as np
from scipy.spatial import cKDTree

from gcm_pipeline.robot import kernels
from gcm_pipeline.robot.collision.pairs import GJK_MARGIN, KINDS, PIECES, Pair, hull_pair_pool
from gcm_pipeline.robot.collision.spheres import (
    POLYTOPES,
    RobotCover,
    hull_vertices,
    polytope_edges,
)

__all__ = [
    "BLOCK",
    "BROAD_MARGIN",
    "COMPILED_BLOCK",
    "EDGE_COUNT",
    "INSIDE_DEPTH",
    "BroadPhase",
    "Screen",
    "ShapeBound",
    "beyond_a_face",
    "height_over_face",
    "in_frame",
    "octree_box",
    "row_matmul",
    "segments_inside",
    "squared_norms",
    "stacked",
]

#: A pair is ruled out by the broad phase when its lower bound exceeds this [m]:
#: coal's narrow phase counts a pair within ``GJK_MARGIN`` as touching, plus a
#: margin far above the round-off of the vectorised kinematics (~1e-12 m).
BROAD_MARGIN = GJK_MARGIN + 1e-7
#: Configurations placed per block by the broad phase (temporaries stay in cache).
BLOCK = 2048
#: Configurations per block with the compiled kernels: they keep no temporaries of
#: the block's size but the frames (16,384 configurations of the Panda: 14 MB), and
#: each pair left open costs a few calls per block (on 20,000 random Panda
#: configurations, 1.76 us per configuration in blocks of 2,048, 1.52 us in these).
COMPILED_BLOCK = 16384
#: Edges of a robot polytope tested against a world primitive (level 4), longest first.
EDGE_COUNT = 64
#: World primitives the edges of level 4 are tested against.
EDGE_SHAPES = (coal.Box, coal.Sphere, coal.Cylinder)
#: A hull vertex (level 3) or a point of an edge (level 4) this deep inside a box
#: [m] makes the pair collide without coal; shallower ones are left to coal.
#: (Called as Pinocchio calls it, without the margin of
#: :func:`~gcm_pipeline.robot.collision.pairs.checker_requests`, coal missed box-box
#: penetrations up to 0.3 mm: 19 of 20,000 random overlaps of 1e-7 to 3e-4 m.)
INSIDE_DEPTH = 1e-4


class ShapeBound:
    """Lower bound of the distance from points to a placed coal geometry (exact for primitives).

    Boxes, spheres, cylinders and capsules give the exact distance (0 inside);
    an octree the distance to the box around its occupied cells
    (:func:`octree_box`), any other geometry to its local bounding box.
    """

    def __init__(self, geometry: Any, placement: np.ndarray) -> None:
        self.inv = np.linalg.inv(placement)
        self.kind = "box"
        self.centre = np.zeros(3)
        #: the shape itself (a primitive), not a box around it
        self.exact = isinstance(geometry, (coal.Sphere, coal.Cylinder, coal.Capsule, coal.Box))
        #: an octree's occupied cells (a k-d tree of their centres) and the largest
        #: cell's half diagonal: a point's distance to the cells is at least its
        #: distance to the nearest centre minus that
        self.cells: Any = None
        self.cell_reach = 0.0
        if isinstance(geometry, coal.Sphere):
            self.kind, self.radius = "sphere", float(geometry.radius)
        elif isinstance(geometry, coal.Cylinder):
            self.kind, self.radius = "cylinder", float(geometry.radius)
            self.half = float(geometry.halfLength)
        elif isinstance(geometry, coal.Capsule):
            self.kind, self.radius = "capsule", float(geometry.radius)
            self.half = float(geometry.halfLength)
        elif isinstance(geometry, coal.Box):
            self.halfs = np.asarray(geometry.halfSide, dtype=float)
        elif isinstance(geometry, coal.OcTree):
            lo, hi = octree_box(geometry)
            self.centre = 0.5 * (lo + hi)
            self.halfs = 0.5 * (hi - lo)
            self.cells, self.cell_reach = octree_cells(geometry)
        else:
            geometry.computeLocalAABB()
            box = geometry.aabb_local
            lo, hi = np.asarray(box.min_, dtype=float), np.asarray(box.max_, dtype=float)
            self.centre = 0.5 * (lo + hi)
            self.halfs = 0.5 * (hi - lo)

    def lower(self, points: np.ndarray) -> np.ndarray:
        """Distances (...,) [m] (>= 0) from points (..., 3) in the base frame."""
        pts = np.asarray(points, dtype=float)
        return self.lower_xyz(pts.reshape(-1, 3).T).reshape(pts.shape[:-1])

    def lower_xyz(self, xyz: np.ndarray) -> np.ndarray:
        """:meth:`lower` of points given by their coordinates (3, ...) (component first)."""
        # each coordinate a contiguous row; einsum, not matmul: OpenBLAS takes ten
        # times longer on a (3, 3) @ (3, K) product
        loc = np.einsum("ij,jk->ik", self.inv[:3, :3], xyz.reshape(3, -1))
        # in place from here on (the same arithmetic; fewer temporaries of K floats)
        loc += self.inv[:3, 3:4]
        x, y, z = loc
        shape = xyz.shape[1:]
        if self.kind == "sphere":
            out = x * x
            out += y * y
            out += z * z
            np.sqrt(out, out=out)
            out -= self.radius
        elif self.kind == "cylinder":
            radial = x * x
            radial += y * y
            np.sqrt(radial, out=radial)
            radial -= self.radius
            axial = np.abs(z, out=z)
            axial -= self.half
            np.maximum(radial, 0.0, out=radial)
            np.maximum(axial, 0.0, out=axial)
            radial *= radial
            axial *= axial
            radial += axial
            return np.sqrt(radial, out=radial).reshape(shape)
        elif self.kind == "capsule":
            along = z - np.clip(z, -self.half, self.half)
            out = x * x
            out += y * y
            out += along * along
            np.sqrt(out, out=out)
            out -= self.radius
        else:
            local = None if self.cells is None else loc.T.copy()
            loc -= self.centre[:, None]
            np.abs(loc, out=loc)
            loc -= self.halfs[:, None]
            np.maximum(loc, 0.0, out=loc)
            loc *= loc
            out = x + y
            out += z
            np.sqrt(out, out=out)
            if local is not None:  # an octree: its cells bound tighter than its box
                near, _ = self.cells.query(local)
                np.maximum(out, near - self.cell_reach, out=out)
            return out.reshape(shape)
        return np.maximum(out, 0.0, out=out).reshape(shape)

    def packed(self) -> np.ndarray:
        """The bound as a row (21,) of the compiled broad phase.

        The inverse placement's first three rows (12), the kind's index in
        :data:`~gcm_pipeline.robot.kernels.SHAPE_KINDS`, the radius, the half
        length, the box's centre (3) and half sizes (3) (0 where they do not apply).
        """
        row = np.zeros(21)
        row[:12] = self.inv[:3].reshape(-1)
        row[12] = kernels.SHAPE_KINDS.index(self.kind)
        if self.kind == "box":
            row[15:18] = self.centre
            row[18:21] = self.halfs
        else:
            row[13] = self.radius
            row[14] = getattr(self, "half", 0.0)
        return row

    def nearest(self, p: np.ndarray) -> np.ndarray:
        """Nearest points (..., 3) of the shape to points ``p`` (..., 3) given in its frame.

        Exact for the primitives (a point inside is its own nearest point).
        """
        if self.kind == "sphere":
            norm = np.sqrt(squared_norms(p))[..., None]
            return np.where(norm > self.radius, p * (self.radius / np.maximum(norm, 1e-300)), p)
        if self.kind == "cylinder":
            radial = np.sqrt(p[..., 0] ** 2 + p[..., 1] ** 2)[..., None]
            scale = np.minimum(1.0, self.radius / np.maximum(radial, 1e-300))
            out = p * scale
            out[..., 2] = np.clip(p[..., 2], -self.half, self.half)
            return out
        if self.kind == "capsule":
            axis = np.zeros_like(p)
            axis[..., 2] = np.clip(p[..., 2], -self.half, self.half)
            rel = p - axis
            norm = np.sqrt(squared_norms(rel))[..., None]
            return axis + np.where(
                norm > self.radius, rel * (self.radius / np.maximum(norm, 1e-300)), rel
            )
        return self.centre + np.clip(p - self.centre, -self.halfs, self.halfs)

    def support(self, n: np.ndarray) -> np.ndarray:
        """Support function ``max_{x in shape} n . x`` (...,) of directions ``n`` (..., 3).

        In the shape's frame; exact for the primitives.
        """
        if self.kind == "sphere":
            return self.radius * np.sqrt(squared_norms(n))
        if self.kind == "cylinder":
            return self.radius * np.sqrt(n[..., 0] ** 2 + n[..., 1] ** 2) + self.half * np.abs(
                n[..., 2]
            )
        if self.kind == "capsule":
            return self.radius * np.sqrt(squared_norms(n)) + self.half * np.abs(n[..., 2])
        return row_matmul(n, self.centre) + row_matmul(np.abs(n), self.halfs)


def octree_box(tree: Any) -> tuple[np.ndarray, np.ndarray]:
    """Corners (3,), (3,) of the box holding every occupied cell of a coal octree [m].

    From the cells themselves (centre +- half their size), grown by 1e-6 m:
    coal's own bounding box is in single precision and may fall short by ~1e-8 m.
    """
    cells = np.array([np.asarray(b) for b in tree.toBoxes()], dtype=float).reshape(-1, 6)
    if not len(cells):
        return np.zeros(3), np.zeros(3)
    half = 0.5 * cells[:, 3:4]
    return (cells[:, :3] - half).min(axis=0) - 1e-6, (cells[:, :3] + half).max(axis=0) + 1e-6


def octree_cells(tree: Any) -> tuple[Any, float]:
    """A k-d tree of a coal octree's occupied cell centres and the largest half diagonal [m].

    Every point of a cell lies within the half diagonal of its centre, so a
    point's distance to the occupied cells is at least its distance to the
    nearest centre minus the largest half diagonal.
    """
    cells = np.array([np.asarray(b) for b in tree.toBoxes()], dtype=float).reshape(-1, 6)
    if not len(cells):
        return cKDTree(np.full((1, 3), 1e30)), 0.0
    return cKDTree(cells[:, :3]), float(cells[:, 3].max()) * 0.5 * math.sqrt(3.0) + 1e-6


def squared_norms(v: np.ndarray) -> np.ndarray:
    """Squared norms (...,) of vectors (..., 3) (faster than ``norm`` along a short axis)."""
    return np.einsum("...i,...i->...", v, v)


class Screen(NamedTuple):
    """The broad phase of one mode's pairs (columns ``k`` index ``pairs``)."""

    pairs: np.ndarray  # (P,) indices of the checker's pairs
    kind: np.ndarray  # (P,) their kinds
    geom_a: np.ndarray  # (P,) robot geometry whose spheres bound side a
    geom_b: np.ndarray  # (P,) the other robot geometry (self pairs), else -1
    world: np.ndarray  # (P,) world geometry (world pairs), else -1
    # the sphere tests of column k: entries first_test[k]:first_test[k] + n_tests[k]
    # of sphere_a / sphere_b (-1 against the world shape) / bound (reach^2 of two
    # spheres; the radius against a world shape)
    first_test: np.ndarray
    n_tests: np.ndarray
    sphere_a: np.ndarray
    sphere_b: np.ndarray
    bound: np.ndarray
    # robot polytope vs box, by column: (joint, hull vertices (3, V), inverse placement, halfs)
    boxes: dict[int, tuple[int, np.ndarray, np.ndarray, np.ndarray]]
    # robot polytope vs a box, sphere or cylinder, by column: (joint, edge ends (3, E)
    # and (3, E), the shape's inverse placement (4, 4), its packed row (21,))
    edges: dict[int, tuple[int, np.ndarray, np.ndarray, np.ndarray, np.ndarray]]
    # robot polytope vs a robot box (self pairs; compiled level 3 only), by column: (the
    # polytope's joint, the box's joint, the polytope's hull vertices (3, V), the box's
    # inverse placement in its joint's frame (4, 4), halfs)
    self_boxes: dict[int, tuple[int, int, np.ndarray, np.ndarray, np.ndarray]]
    # robot polytope vs a world cylinder, by column: (joint, hull vertices (3, V), the
    # cylinder's inverse placement (4, 4), its radius, its half length)
    cylinders: dict[int, tuple[int, np.ndarray, np.ndarray, float, float]]
    # two robot polytopes (self pairs; compiled level 3 only), by column: each one's
    # (joint, hull vertices (3, V), the box of those vertices in its joint's frame as
    # (centre, half sizes) (2, 3)), a's then b's
    self_hulls: dict[int, tuple[tuple[int, np.ndarray, np.ndarray], ...]]


class BroadPhase:
    """The broad phase of :class:`~gcm_pipeline.robot.collision.checker.CollisionChecker`.

    A base class of the checker: its methods use the checker's robot geometry
    (``_gm``), pairs (``_pairs``), sphere covers (``_cover``), joint frames
    (``_frames``) and narrow phase (``_run``, ``_pair_pool``; the convex-hull
    pre-check's ``_hull_pools``, ``_piece_pools`` and ``_mesh_hulls``, built when
    a pair first reaches coal, with the robot's ``_model``).
    """

    _gm: Any
    _pairs: list[Pair]
    _cover: RobotCover
    _frames: Any
    _pair_pool: list[Any]
    _groups: dict[bytes, list[tuple[int, np.ndarray]]]
    _compiled_args: dict[int, tuple[Any, ...]]
    _bounds: dict[int, ShapeBound]
    _model: Any
    threads: int
    _hull_pools: dict[int, Any]
    _piece_pools: dict[int, Any]
    _mesh_hulls: dict[tuple[int, int], Any]
    _hulls: dict[int, tuple[int, np.ndarray]]
    _edge_cache: dict[int, tuple[int, np.ndarray, np.ndarray]]
    _run: Callable[[Any, np.ndarray], np.ndarray]

    def _hull(self, g: int) -> tuple[int, np.ndarray]:
        """Hull vertices of robot geometry ``g < n_robot_geoms``: ``(joint, (V, 3))`` (cached)."""
        if g not in self._hulls:
            self._hulls[g] = hull_vertices(self._gm.geometryObjects[g], self._frames)
        return self._hulls[g]

    def _hull_box(self, g: int) -> tuple[int, np.ndarray, np.ndarray]:
        """Robot polytope ``g``'s ``(joint, hull vertices (3, V), their box (2, 3))``.

        The box, (centre, half sizes) in the joint's frame, holds the vertices,
        so the hull and the geometry.
        """
        joint, verts = self._hull(g)
        lo, hi = verts.min(axis=0), verts.max(axis=0)
        return joint, verts.T.copy(), np.array([0.5 * (lo + hi), 0.5 * (hi - lo)])

    def _edges(self, g: int) -> tuple[int, np.ndarray, np.ndarray]:
        """:data:`EDGE_COUNT` longest edges of robot polytope ``g``: ``(joint, (E, 3), (E, 3))``."""
        if g not in self._edge_cache:
            go = self._gm.geometryObjects[g]
            self._edge_cache[g] = polytope_edges(go, self._frames, EDGE_COUNT)
        return self._edge_cache[g]

    def _screen(self, cols: list[int]) -> Screen:
        """The broad phase of the pairs ``cols`` (indices of ``self._pairs``) of one mode."""
        cov, gm = self._cover, self._gm
        sa, sb, bound = [], [], []
        boxes, edges, self_boxes, cylinders, self_hulls = {}, {}, {}, {}, {}
        for k, c in enumerate(cols):
            p = self._pairs[c]
            own = np.arange(cov.start[p.owner], cov.start[p.owner + 1])
            if p.kind == "self":
                oth = np.arange(cov.start[p.other], cov.start[p.other + 1])
                ia, ib = np.repeat(own, oth.size), np.tile(oth, own.size)
                sa.append(ia)
                sb.append(ib)
                bound.append((cov.radius[ia] + cov.radius[ib] + BROAD_MARGIN) ** 2)
                box = self._self_box(p.a, p.b)
                if box is not None:
                    self_boxes[k] = box
                if all(isinstance(gm.geometryObjects[g].geometry, POLYTOPES) for g in (p.a, p.b)):
                    self_hulls[k] = (self._hull_box(p.a), self._hull_box(p.b))
                continue
            sa.append(own)
            sb.append(np.full(own.size, -1))
            bound.append(cov.radius[own])
            shape = gm.geometryObjects[p.b]
            if p.a != p.owner or not isinstance(gm.geometryObjects[p.a].geometry, POLYTOPES):
                continue
            inv = np.linalg.inv(shape.placement.homogeneous)
            if isinstance(shape.geometry, coal.Box):
                joint, verts = self._hull(p.a)
                boxes[k] = (joint, verts.T.copy(), inv, np.asarray(shape.geometry.halfSide))
            if isinstance(shape.geometry, coal.Cylinder):
                joint, verts = self._hull(p.a)
                cyl = shape.geometry
                cylinders[k] = (
                    joint,
                    verts.T.copy(),
                    inv,
                    float(cyl.radius),
                    float(cyl.halfLength),
                )
            if isinstance(shape.geometry, EDGE_SHAPES):
                joint, ea, eb = self._edges(p.a)
                edges[k] = (joint, ea.T.copy(), eb.T.copy(), inv, self._bounds_for(p.b).packed())
        pairs = [self._pairs[c] for c in cols]
        count = np.array([x.size for x in sa], dtype=int)

        def cat(parts: list[np.ndarray], dtype: Any) -> np.ndarray:
            return np.concatenate(parts).astype(dtype) if parts else np.zeros(0, dtype=dtype)

        return Screen(
            np.array(cols, dtype=int),
            np.array([p.kind for p in pairs], dtype=object),
            np.array([p.owner for p in pairs], dtype=int),
            np.array([p.other if p.kind == "self" else -1 for p in pairs], dtype=int),
            np.array([-1 if p.kind == "self" else p.b for p in pairs], dtype=int),
            np.cumsum(count) - count,
            count,
            cat(sa, int),
            cat(sb, int),
            cat(bound, float),
            boxes,
            edges,
            self_boxes,
            cylinders,
            self_hulls,
        )

    def _self_box(
        self, a: int, b: int
    ) -> tuple[int, int, np.ndarray, np.ndarray, np.ndarray] | None:
        """Level 3 of a self pair: a robot polytope against a robot box, or None.

        ``(polytope's joint, box's joint, hull vertices (3, V), the box's inverse
        placement in its joint's frame (4, 4), halfs)`` for the robot geometries
        ``a`` and ``b`` (either may be the box).
        """
        gm = self._gm
        for box, poly in ((b, a), (a, b)):
            shape = gm.geometryObjects[box]
            if not isinstance(shape.geometry, coal.Box):
                continue
            if not isinstance(gm.geometryObjects[poly].geometry, POLYTOPES):
                continue
            joint, verts = self._hull(poly)
            box_joint = int(shape.parentJoint)
            rot, trans = self._frames.local(
                box_joint, np.asarray(shape.placement.rotation), shape.placement.translation
            )
            placement = np.eye(4)
            placement[:3, :3], placement[:3, 3] = rot, trans
            halfs = np.asarray(shape.geometry.halfSide, dtype=float)
            return joint, box_joint, verts.T.copy(), np.linalg.inv(placement), halfs
        return None

    def _place(
        self,
        frames: Any,
        joints: np.ndarray,
        local: np.ndarray,
        rows: np.ndarray | None = None,
    ) -> np.ndarray:
        """Points (N, P, 3) [m], base frame, of ``local`` (P, 3) fixed to ``joints`` (P,).

        ``rows``: only these configurations of ``frames`` (M,), giving (M, P, 3).
        """
        tfs = frames.transforms
        n = tfs[0].shape[0] if rows is None else rows.size
        groups = self._groups.get(joints.tobytes())
        if groups is None:
            groups = self._groups[joints.tobytes()] = [
                (j, np.flatnonzero(joints == j)) for j in np.unique(joints).tolist()
            ]
        out = np.empty((n, len(joints), 3)) if len(groups) != 1 else None
        for j, cols in groups:
            tf = tfs[j] if rows is None else tfs[j][rows]
            # (N * 3, 4) @ (4, P_j), the points in homogeneous coordinates: one BLAS call
            # per joint, rotation and translation at once
            homo = np.ones((4, cols.size))
            homo[:3] = local[cols].T
            placed = (tf.reshape(-1, 4) @ homo).reshape(n, 3, cols.size).transpose(0, 2, 1)
            if out is None:  # every point on one joint
                return np.ascontiguousarray(placed)
            out[:, cols] = placed
        assert out is not None
        return out

    def _pair_hits(
        self, q: np.ndarray, frames: Any, screen: Screen, first: bool = False
    ) -> np.ndarray:
        """Which pairs of ``screen`` collide in each configuration, (N, P) bool.

        The transpose of a C-contiguous (P, N) array (a pair's configurations contiguous).

        With ``first``, each configuration's first kind of collision only (in the order
        of ``pairs.KINDS``, the reasons'): the pairs run kind by kind, each skipping the
        configurations an earlier one hits (its entries there stay False).

        Broad phase, in three levels: a pair whose geometries' bounding spheres
        are apart (from each other, or from the world shape) is free; so is
        one whose sphere covers are. A robot polytope against a box (of the
        world; compiled, also a robot's own against another link) is free if
        its hull vertices all lie beyond one face's plane, and collides if one
        of them lies ``INSIDE_DEPTH`` inside the box (a vertex of one of its
        triangles, or of the solid). A robot polytope against a box, sphere or
        cylinder collides if a point of one of its longest edges lies that deep
        inside the shape. coal's narrow phase decides the rest, pair by pair,
        only on the configurations left.
        """
        if screen.pairs.size == 0:  # e.g. no table, no object, no self-collision
            return np.zeros((len(q), 0), dtype=bool)
        compiled = kernels.get()
        if compiled is not None:
            return self._pair_hits_compiled(compiled, q, frames, screen, first)
        cov, rots, poss = self._cover, frames[0], frames[1]
        # 1. one bounding sphere per robot geometry
        ball = self._place(frames, cov.ball_joint, cov.ball_centre)  # (N, G, 3)
        # coordinates first, (3, G, N): gathers of whole rows, contiguous arithmetic
        xyz = np.ascontiguousarray(ball.transpose(2, 1, 0))
        open_ = np.zeros((screen.pairs.size, len(q)), dtype=bool)  # (P, N)
        own = screen.geom_b >= 0
        if own.any():
            ga, gb = screen.geom_a[own], screen.geom_b[own]
            # one coordinate at a time: temporaries of (pairs, N), not (3, pairs, N)
            # (large temporaries cost page faults)
            sq = np.zeros((ga.size, len(q)))
            for c in xyz:
                d = c[ga] - c[gb]
                sq += d * d
            reach = cov.ball_radius[ga] + cov.ball_radius[gb]
            open_[own] = sq <= ((reach + BROAD_MARGIN) ** 2)[:, None]
        for w in np.unique(screen.world[screen.world >= 0]).tolist():
            at = np.flatnonzero(screen.world == w)
            g = screen.geom_a[at]
            lb = self._bounds_for(w).lower_xyz(xyz[:, g]) - cov.ball_radius[g][:, None]
            open_[at] = lb <= BROAD_MARGIN
        hit = np.zeros((screen.pairs.size, len(q)), dtype=bool)  # (P, N), returned as (N, P)
        decided = np.zeros(len(q), dtype=bool)  # ``first``: hit by a pair before
        for k in _open_pairs(open_, screen, first):
            rows = np.flatnonzero(open_[k] & ~decided)
            if rows.size == 0:
                continue
            # 2. the sphere covers
            span = slice(screen.first_test[k], screen.first_test[k] + screen.n_tests[k])
            a, b, bound = screen.sphere_a[span], screen.sphere_b[span], screen.bound[span]
            ca = self._place(frames, cov.joint[a], cov.centre[a], rows)
            if screen.world[k] < 0:
                gap = ca - self._place(frames, cov.joint[b], cov.centre[b], rows)
                near = (squared_norms(gap) <= bound).any(axis=1)
            else:
                lb = self._bounds_for(int(screen.world[k])).lower(ca) - bound
                near = (lb <= BROAD_MARGIN).any(axis=1)
            rows = rows[near]
            # 3. hull vertices against a world box (a robot box: compiled only, below)
            box = screen.boxes.get(k)
            if box is not None and rows.size:
                rows, inside = _world_box_level(frames, rows, box, ball[rows, screen.geom_a[k]])
                hit[k, rows[inside]] = True
                rows = rows[~inside]
            # 4. the polytope's longest edges inside a primitive
            edge = screen.edges.get(k)
            if edge is not None and rows.size:
                joint, ea, eb, inv, packed = edge
                frame = (rots[joint], poss[joint], inv)
                inside = segments_inside(
                    in_frame(frame, rows, ea), in_frame(frame, rows, eb), packed, INSIDE_DEPTH
                )
                hit[k, rows[inside]] = True
                rows = rows[~inside]
            if rows.size:
                hit[k, rows] = self._narrow(int(screen.pairs[k]), q[rows])
            if first:
                decided |= hit[k]
        return hit.T

    def _pair_hits_compiled(
        self,
        compiled: kernels.Kernels,
        q: np.ndarray,
        frames: Any,
        screen: Screen,
        first: bool = False,
    ) -> np.ndarray:
        """:meth:`_pair_hits` by the compiled kernels (see :mod:`~gcm_pipeline.robot.kernels`).

        The same answers: levels 1 and 2 for all pairs in one pass, then level 3
        and coal pair by pair.
        """
        tfs = stacked(frames.transforms)
        broad, boxes, edges, cylinders, apart = self._compiled_screen(screen)
        open_ = compiled.broad_phase(tfs, *broad)  # (P, N)
        hit = np.zeros((screen.pairs.size, len(q)), dtype=bool)  # (P, N), returned as (N, P)
        decided = np.zeros(len(q), dtype=bool)  # ``first``: hit by a pair before
        for k in _open_pairs(open_, screen, first):
            rows = np.flatnonzero(open_[k] & ~decided) if first else np.flatnonzero(open_[k])
            if rows.size == 0:
                continue
            for level, pools in (
                (compiled.hull_vs_box, boxes),
                (compiled.hull_vs_cylinder, cylinders),
            ):
                shape = pools.get(k)
                if shape is not None:
                    joint, *limits = shape
                    status = level(tfs[joint], rows, *limits)
                    hit[k, rows[status == kernels.COLLIDES]] = True
                    rows = rows[status == kernels.UNDECIDED]
            own_box = screen.self_boxes.get(k)
            if own_box is not None and rows.size:
                # in the frames of the box's joint; the limits as for a world box
                joint, box_joint, verts, inv, halfs = own_box
                beyond, deep = (
                    halfs + (BROAD_MARGIN + kernels.SLACK),
                    halfs - (INSIDE_DEPTH + kernels.SLACK),
                )
                status = compiled.hull_vs_robot_box(
                    tfs, joint, box_joint, rows, verts, inv, beyond, deep
                )
                hit[k, rows[status == kernels.COLLIDES]] = True
                rows = rows[status == kernels.UNDECIDED]
            hulls = apart.get(k)
            if hulls is not None and rows.size:
                (ja, va, box_a), (jb, vb, box_b) = hulls
                rows = rows[~compiled.hulls_apart(tfs, ja, jb, rows, va, box_a, vb, box_b)]
            edge = edges.get(k)
            if edge is not None and rows.size:
                joint, *ends = edge
                inside = compiled.edges_inside(tfs[joint], rows, *ends)
                hit[k, rows[inside]] = True
                rows = rows[~inside]
            if rows.size:
                hit[k, rows] = self._narrow(int(screen.pairs[k]), q[rows])
            if first:
                decided |= hit[k]
        return hit.T

    def _compiled_screen(
        self, screen: Screen
    ) -> tuple[tuple[Any, ...], dict[int, Any], dict[int, Any], dict[int, Any], dict[int, Any]]:
        """The compiled broad phase's arguments for ``screen`` (built once per screen).

        Returns the arguments of ``broad_phase`` after the frames, the level-3
        arguments ``(joint, vertices, inverse placement, beyond, deep)`` of each
        column with a box, the level-4 arguments ``(joint, edge ends, other
        ends, packed shape, depth)`` of each column with a primitive, and the
        level-3 arguments ``(joint, vertices, inverse placement, (radius, half
        length, beyond, deep))`` of each column with a cylinder, and the
        level-3 arguments ``((joint, vertices, box), (joint, vertices, box))``
        of each column of two robot polytopes (each box's half sizes plus the
        margin). Each limit is the NumPy level's plus
        :data:`~gcm_pipeline.robot.kernels.SLACK` (levels 3 and 4: the depths
        plus it too, stricter); two polytopes' boxes are the margin and the
        slack wider (no NumPy level).
        """
        known = self._compiled_args.get(id(screen))
        if known is not None and known[0] is screen:
            return known[1], known[2], known[3], known[4], known[5]
        cov, slack = self._cover, kernels.SLACK
        worlds = sorted({int(w) for w in screen.world.tolist() if w >= 0})
        # explicit dtypes: without a world shape or a pair these lists are empty
        # (and np.array([]) is float64)
        shapes = np.array([self._bounds_for(w).packed() for w in worlds], float).reshape(-1, 21)
        world = np.array(
            [worlds.index(w) if w >= 0 else -1 for w in screen.world.tolist()], np.intp
        )
        own = world < 0
        ra = cov.ball_radius[screen.geom_a]
        rb = cov.ball_radius[np.where(own, screen.geom_b, 0)]
        # self pairs compare squared gaps with squared limits; world pairs distances
        limit1 = np.where(own, (ra + rb + BROAD_MARGIN + slack) ** 2, ra + BROAD_MARGIN + slack)
        limit2 = np.where(
            np.repeat(own, screen.n_tests),
            (np.sqrt(screen.bound) + slack) ** 2,
            screen.bound + BROAD_MARGIN + slack,
        )
        # a geometry's cover spheres are on its joint, the bounding sphere's
        assert np.array_equal(cov.joint, np.repeat(cov.ball_joint, np.diff(cov.start)))
        args = [cov.ball_joint, cov.ball_centre, cov.centre, cov.start, screen.geom_a]
        args += [screen.geom_b, world, limit1, screen.first_test, screen.n_tests]
        args += [screen.sphere_a, screen.sphere_b, limit2, shapes]
        # indices as intp, all C-contiguous (the kernels' signature)
        broad = tuple(
            np.ascontiguousarray(a, np.float64 if a.dtype.kind == "f" else np.intp) for a in args
        )
        boxes = {
            k: (
                joint,
                np.ascontiguousarray(verts, float),
                np.ascontiguousarray(inv, float),
                halfs + (BROAD_MARGIN + slack),
                halfs - (INSIDE_DEPTH + slack),
            )
            for k, (joint, verts, inv, halfs) in screen.boxes.items()
        }
        edges = {
            k: (joint, ea, eb, packed, INSIDE_DEPTH + slack)
            for k, (joint, ea, eb, inv, packed) in screen.edges.items()
        }
        cylinders = {
            k: (
                joint,
                np.ascontiguousarray(verts, float),
                np.ascontiguousarray(inv, float),
                np.array([radius, half, BROAD_MARGIN + slack, INSIDE_DEPTH + slack]),
            )
            for k, (joint, verts, inv, radius, half) in screen.cylinders.items()
        }
        apart = {
            k: tuple(
                (joint, verts, box + np.array([[0.0], [BROAD_MARGIN + slack]]))
                for joint, verts, box in hulls
            )
            for k, hulls in screen.self_hulls.items()
        }
        self._compiled_args[id(screen)] = (screen, broad, boxes, edges, cylinders, apart)
        return broad, boxes, edges, cylinders, apart

    def _narrow(self, c: int, q: np.ndarray) -> np.ndarray:
        """Coal's answer for pair ``c`` (an index of ``_pairs``) in configurations (M, nq).

        A pair with a robot mesh is first checked on the convex hulls
        (:func:`~gcm_pipeline.robot.collision.pairs.hull_pair_pool`, touching within
        :data:`~gcm_pipeline.robot.collision.pairs.HULL_MARGIN`): apart there, apart
        here. Where they touch, a long mesh's pieces' hulls next
        (:func:`~gcm_pipeline.robot.collision.pairs.hull_pieces`; the UR5's forearm
        beside the bottle): apart there, apart here too. coal checks the meshes only
        where those touch. The same answers.
        """
        if c not in self._hull_pools:
            self._hull_pools[c] = hull_pair_pool(
                self._model, self._gm, self._pairs[c], self.threads, self._mesh_hulls
            )
        hull = self._hull_pools[c]
        if hull is None:
            return self._run(self._pair_pool[c], q)
        out = self._run(hull, q)
        touch = np.flatnonzero(out)
        if touch.size:
            if c not in self._piece_pools:
                self._piece_pools[c] = hull_pair_pool(
                    self._model, self._gm, self._pairs[c], self.threads, self._mesh_hulls, PIECES
                )
            pieces = self._piece_pools[c]
            if pieces is not None:
                out[touch] = self._run(pieces, q[touch])
                touch = touch[out[touch]]
        if touch.size:
            out[touch] = self._run(self._pair_pool[c], q[touch])
        return out

    def _bounds_for(self, w: int) -> ShapeBound:
        bound = self._bounds.get(w)
        if bound is None:
            go = self._gm.geometryObjects[w]
            bound = self._bounds[w] = ShapeBound(go.geometry, go.placement.homogeneous)
        return bound


def _open_pairs(open_: np.ndarray, screen: Screen, first: bool) -> list[int]:
    """The columns of ``screen`` that ``open_`` (P, N) leaves open in some configuration.

    With ``first`` (:meth:`BroadPhase._pair_hits`), kind by kind in the order of
    :data:`~gcm_pipeline.robot.collision.pairs.KINDS` (stable: the screen's order
    within a kind).
    """
    cols = np.flatnonzero(open_.any(axis=1))
    if first:
        rank = np.array([KINDS.index(kind) for kind in screen.kind[cols].tolist()], dtype=int)
        cols = cols[np.argsort(rank, kind="stable")]
    return cols.tolist()


def stacked(tfs: list[np.ndarray]) -> np.ndarray:
    """Joint frames (N, 3, 4) as one (J, N, 3, 4) array: the array they are views of, if any."""
    base = tfs[0].base
    if (
        isinstance(base, np.ndarray)
        and base.shape == (len(tfs), *tfs[0].shape)
        and base.dtype == np.float64
        and base.flags.c_contiguous
        and all(
            t.base is base and t.ctypes.data == base.ctypes.data + j * base.strides[0]
            for j, t in enumerate(tfs)
        )
    ):
        return base
    return np.stack(tfs)


def row_matmul(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """``a @ b`` for a 2-D ``a``, each row's result the same whatever the number of rows.

    NumPy computes a single row with BLAS's vector routine, whose sums can differ
    in the last bit from the matrix routine's; a configuration's answer must not
    depend on the batch it comes in (chunks, workers), so one row is computed as two.
    """
    if a.ndim == 2 and a.shape[0] == 1:
        return (np.concatenate([a, a]) @ b)[:1]
    return a @ b


def _world_box_level(
    frames: Any,
    rows: np.ndarray,
    box: tuple[int, np.ndarray, np.ndarray, np.ndarray],
    centre: np.ndarray,
) -> tuple[np.ndarray, np.ndarray]:
    """Level 3 of a robot polytope against a world box (NumPy), for configurations ``rows``.

    ``centre`` (M, 3) is the polytope's bounding sphere's centre per row. The
    face nearest it first: its lowest hull vertex over that face's plane (one
    coordinate), then all vertices. Returns the rows left undecided or
    colliding, and which of them collide (a vertex deeper than
    ``INSIDE_DEPTH``); the others were free.
    """
    rots, poss = frames[0], frames[1]
    joint, verts, inv, halfs = box
    lim = halfs[None, :, None]
    local_centre = row_matmul(centre, inv[:3, :3].T) + inv[:3, 3]
    axis = np.argmax(np.abs(local_centre) - halfs, axis=1)
    sign = np.where(local_centre[np.arange(rows.size), axis] >= 0, 1.0, -1.0)
    frame = (rots[joint][rows], poss[joint][rows], inv)
    height = height_over_face(frame, verts, halfs, axis, sign)
    rows = rows[height <= BROAD_MARGIN]
    local = in_frame((rots[joint], poss[joint], inv), rows, verts)
    inside = np.all(np.abs(local) < lim - INSIDE_DEPTH, axis=1).any(axis=1)
    keep = beyond_a_face(local, lim) & ~inside  # free: dropped
    return rows[~keep], inside[~keep]


def _world_cylinder_level(
    frames: Any, rows: np.ndarray, cyl: tuple[int, np.ndarray, np.ndarray, float, float]
) -> tuple[np.ndarray, np.ndarray]:
    """Level 3 of a robot polytope against a world cylinder (NumPy), for configurations ``rows``.

    The reference of the compiled ``hull_vs_cylinder``, not called by the NumPy
    broad phase (see the module's doc). Free when the whole cylinder lies more
    than ``BROAD_MARGIN`` beyond a face of the box of the hull vertices in the
    joint's frame. In the cylinder's frame (axis z): free
    when every hull vertex lies more than ``BROAD_MARGIN`` beyond a cap's plane,
    or beyond the side plane tangent to the cylinder across the direction from
    its axis to the vertices' centroid; colliding when a vertex lies deeper than
    ``INSIDE_DEPTH`` inside it (a hull vertex is a point of the geometry).
    Returns the rows left undecided or colliding, and which of them collide;
    the others were free.
    """
    rots, poss = frames[0], frames[1]
    joint, verts, inv, radius, half = cyl
    frame = (rots[joint], poss[joint], inv)
    x, y, z = in_frame(frame, rows, verts).transpose(1, 0, 2)  # (M, V) each
    mid = in_frame(frame, rows, verts.mean(axis=1, keepdims=True))[:, :, 0]  # (M, 3)
    norm = np.hypot(mid[:, 0], mid[:, 1])
    with np.errstate(invalid="ignore", divide="ignore"):
        u = mid[:, :2] / norm[:, None]
    side = (norm > 0.0) & np.all(u[:, :1] * x + u[:, 1:] * y > radius + BROAD_MARGIN, axis=1)
    caps = np.all(z > half + BROAD_MARGIN, axis=1) | np.all(z < -half - BROAD_MARGIN, axis=1)
    inner = radius - INSIDE_DEPTH
    inside = np.zeros(rows.size, dtype=bool)
    if inner > 0.0 and half > INSIDE_DEPTH:
        deep = (x * x + y * y < inner * inner) & (np.abs(z) < half - INSIDE_DEPTH)
        inside = deep.any(axis=1)
    # the cylinder in the joint's frame: centre R^T (P - p), axis R^T A
    rot = inv[:3, :3] @ rots[joint][rows]  # the joint's frame in the cylinder's
    off = row_matmul(poss[joint][rows], inv[:3, :3].T) + inv[:3, 3]
    centre = -np.einsum("nji,nj->ni", rot, off)
    axis = rot[:, 2, :]
    reach = half * np.abs(axis) + radius * np.sqrt(np.maximum(1.0 - axis * axis, 0.0))
    lo, hi = verts.min(axis=1), verts.max(axis=1)
    gap = np.abs(centre - 0.5 * (lo + hi)) - reach
    boxed = np.any(gap > 0.5 * (hi - lo) + BROAD_MARGIN, axis=1)
    keep = (caps | side | boxed) & ~inside  # free: dropped
    return rows[~keep], inside[~keep]


def relative_transforms(tfs: np.ndarray, joint: int, base: int, rows: np.ndarray) -> np.ndarray:
    """Joint ``joint``'s frames in joint ``base``'s, for configurations ``rows``: (M, 3, 4).

    ``tfs`` (J, N, 3, 4) are the joints' frames in the base frame: the result is
    ``Rb^T Ra`` and ``Rb^T (pa - pb)``. The reference of the frames the compiled
    ``hull_vs_robot_box`` places a hull by (the NumPy code leaves a robot's own
    box to coal).
    """
    a, b = tfs[joint][rows], tfs[base][rows]
    out = np.empty((rows.size, 3, 4))
    out[:, :, :3] = np.einsum("nji,njk->nik", b[:, :, :3], a[:, :, :3])
    out[:, :, 3] = np.einsum("nji,nj->ni", b[:, :, :3], a[:, :, 3] - b[:, :, 3])
    return out


def in_frame(frame: tuple[Any, Any, np.ndarray], rows: np.ndarray, points: np.ndarray) -> Any:
    """Points (3, V) fixed to a joint, in a world shape's frame, for configurations ``rows``.

    ``frame`` is the joint's rotations (N, 3, 3) and origins (N, 3) and the
    shape's inverse placement (4, 4). Returns (M, 3, V).
    """
    rots, poss, inv = frame
    m = rows.size
    rot = (inv[:3, :3] @ rots[rows]).reshape(3 * m, 3)
    off = row_matmul(poss[rows], inv[:3, :3].T) + inv[:3, 3]
    return (rot @ points).reshape(m, 3, points.shape[1]) + off[:, :, None]


def height_over_face(
    frame: tuple[np.ndarray, np.ndarray, np.ndarray],
    points: np.ndarray,
    halfs: np.ndarray,
    axis: np.ndarray,
    sign: np.ndarray,
) -> np.ndarray:
    """Height (M,) of the lowest of points (3, V) fixed to a joint over one face of a box.

    ``frame`` is the joint's rotations (M, 3, 3) and origins (M, 3) and the
    box's inverse placement (4, 4); the face is the one across ``axis`` (M,)
    on the side ``sign`` (M,, +-1) of the box ``|x| <= halfs``. The height of a
    point v is ``u . (R v + o) + t`` with ``u`` the face's outward normal.
    """
    rots, poss, inv = frame
    normal = sign[:, None] * inv[axis, :3]  # base frame
    w = np.einsum("ni,nij->nj", normal, rots)  # R^T u, the joint's frame
    return (
        row_matmul(w, points).min(axis=1)
        + np.einsum("ni,ni->n", normal, poss)
        + sign * inv[axis, 3]
        - halfs[axis]
    )


def beyond_a_face(local: np.ndarray, lim: np.ndarray) -> np.ndarray:
    """Whether all points (M, 3, V) lie beyond one face plane of the box ``|x| <= lim``, (M,)."""
    return (
        np.all(local > lim + BROAD_MARGIN, axis=2) | np.all(local < -lim - BROAD_MARGIN, axis=2)
    ).any(axis=1)


def segments_inside(a: np.ndarray, b: np.ndarray, row: np.ndarray, depth: float) -> np.ndarray:
    """Whether a point of one of the segments ``a``-``b`` lies deeper than ``depth`` in a primitive.

    Level 4 of the broad phase: such a point is a point of the robot geometry
    (an edge of its triangles) inside the world shape, a contact coal finds.

    Args:
        a: First ends (M, 3, E) in the shape's frame [m].
        b: Second ends (M, 3, E).
        row: The shape's :meth:`ShapeBound.packed` row: a box, a sphere or a
            cylinder (along z); any other kind gives False.
        depth: [m], >= 0: the shape shrunk by it must hold the point.

    Returns:
        (M,) bool.
    """
    kind = kernels.SHAPE_KINDS[int(row[12])]
    d = b - a
    m, _, e = a.shape
    lo, hi = np.zeros((m, e)), np.ones((m, e))
    with np.errstate(divide="ignore", invalid="ignore"):
        if kind == "box":
            half = row[18:21] - depth
            if np.any(half <= 0.0):
                return np.zeros(m, dtype=bool)
            for ax in range(3):
                _clip(lo, hi, a[:, ax] - row[15 + ax], d[:, ax], half[ax])
        elif kind == "sphere":
            r = row[13] - depth
            dd = np.einsum("mie,mie->me", d, d)
            t = np.clip(-np.einsum("mie,mie->me", a, d) / np.where(dd > 0.0, dd, 1.0), 0.0, 1.0)
            p = a + t[:, None, :] * d
            return bool(r > 0.0) & (np.einsum("mie,mie->me", p, p) < r * r).any(axis=1)
        elif kind == "cylinder":
            r, half = row[13] - depth, row[14] - depth
            if r <= 0.0 or half <= 0.0:
                return np.zeros(m, dtype=bool)
            _clip(lo, hi, a[:, 2], d[:, 2], half)
            qa = d[:, 0] ** 2 + d[:, 1] ** 2
            qb = 2.0 * (a[:, 0] * d[:, 0] + a[:, 1] * d[:, 1])
            qc = a[:, 0] ** 2 + a[:, 1] ** 2 - r * r
            disc = qb * qb - 4.0 * qa * qc
            root = np.sqrt(np.maximum(disc, 0.0))
            flat = qa <= 0.0  # parallel to the axis: inside for all t, or for none
            t0 = np.where(flat, np.where(qc < 0.0, -np.inf, np.inf), (-qb - root) / (2.0 * qa))
            t1 = np.where(flat, np.where(qc < 0.0, np.inf, -np.inf), (-qb + root) / (2.0 * qa))
            t0 = np.where(~flat & (disc <= 0.0), np.inf, t0)
            np.maximum(lo, t0, out=lo)
            np.minimum(hi, t1, out=hi)
        else:
            return np.zeros(m, dtype=bool)
    return (lo < hi).any(axis=1)


def _clip(lo: np.ndarray, hi: np.ndarray, x: np.ndarray, dx: np.ndarray, half: float) -> None:
    """Narrow ``[lo, hi]`` (M, E) to the t with ``|x + t dx| < half`` (one slab), in place."""
    flat = dx == 0.0
    t0 = (-half - x) / dx
    t1 = (half - x) / dx
    enter = np.where(flat, np.where(np.abs(x) < half, -np.inf, np.inf), np.minimum(t0, t1))
    leave = np.where(flat, np.where(np.abs(x) < half, np.inf, -np.inf), np.maximum(t0, t1))
    np.maximum(lo, enter, out=lo)
    np.minimum(hi, leave, out=hi)
