"""Clearance: the distance of the robot to the environment and the object.

The same sphere covers as the broad phase give lower bounds; coal's exact
distance runs only for pairs that can still be the nearest, and hull vertices
give exact or near-exact distances to primitives without coal (see
:meth:`ClearanceQueries.clearance`). The steps before coal run as compiled
kernels (:mod:`~gcm_pipeline.robot.collision.clearance_kernel`) when
:func:`~gcm_pipeline.robot.kernels.get` gives them; the NumPy code here is their
reference (``GCM_JIT=0``).
"""

from __future__ import annotations

from typing import Any, NamedTuple

import coal
import numpy as np
import pinocchio as pin

from gcm_pipeline.errors import InputError
from gcm_pipeline.robot import kernels
from gcm_pipeline.robot.collision.broadphase import (
    BLOCK,
    BroadPhase,
    height_over_face,
    in_frame,
    row_matmul,
    squared_norms,
    stacked,
)
from gcm_pipeline.robot.collision.octree_near import near_distance
from gcm_pipeline.robot.collision.pairs import (
    MODE_BIT,
    Pair,
    coal_transform,
    without_cached_guess,
)
from gcm_pipeline.robot.collision.spheres import POLYTOPES

__all__ = ["ClearanceQueries"]


class _Packed(NamedTuple):
    """The arguments of the clearance's compiled kernels (:mod:`.clearance_kernel`)."""

    spheres: tuple[np.ndarray, ...]  # sphere_bounds
    faces: tuple[np.ndarray, ...]  # face_distances, but the bounds
    vertices: tuple[np.ndarray, ...]  # vertex_distances, between need and precision
    octree_cols: np.ndarray  # pairs against an octree: bounded by NumPy (its cells)


def _starts(parts: list[np.ndarray]) -> np.ndarray:
    """Offsets (K + 1,) of parts (V_k, 3) stacked by :func:`_stack`."""
    return np.concatenate([[0], np.cumsum([len(p) for p in parts])]).astype(np.intp)


def _stack(parts: list[np.ndarray]) -> np.ndarray:
    """Parts (V_k, 3) as one (V, 3) float array."""
    return np.concatenate([np.zeros((0, 3)), *parts]).astype(float).reshape(-1, 3)


class ClearanceQueries(BroadPhase):
    """The clearance queries of :class:`~gcm_pipeline.robot.collision.checker.CollisionChecker`.

    A base class of the checker: :meth:`_init_clearance` builds the distance
    model when the checker is built.
    """

    robot: Any
    world: tuple[Any, ...]
    _data: Any

    def _init_clearance(
        self,
        gm: Any,
        pairs: list[Pair],
        world_ids: dict[str, int],
        joint_of: list[int],
        gripper: set[int],
    ) -> None:
        """The distance model: robot vs environment, arm links (not gripper) vs the object."""
        robot_ids = range(len(joint_of))
        # clearance: robot vs environment, arm links (not gripper) vs the full object;
        # base links (universe, first joint) vs a support are left out: their distance
        # to it does not depend on the configuration and would mask the arm's
        base_links = {i for i in robot_ids if joint_of[i] in (0, 1)}
        supports = {world_ids[s.name] for s in self.world if s.support}
        dist = [
            p
            for p in pairs
            if (p.kind == "environment" and not (p.a in base_links and p.b in supports))
            or (p.kind == "object" and p.a not in gripper and p.modes & MODE_BIT["grasp"])
        ]
        self._dist_model: Any = None
        #: clearance pairs against an octree: the robot geometry's (joint, hull vertices)
        self._octree_pairs: dict[int, tuple[int, np.ndarray]] = {}
        self._packed: _Packed | None = None  # the compiled kernels' arguments, when asked
        if dist:
            dm = gm.copy()
            dm.removeAllCollisionPairs()
            for p in dist:
                dm.addCollisionPair(pin.CollisionPair(p.a, p.b))
            self._dist_model = dm
            self._dist_data = without_cached_guess(pin.GeometryData(dm))
            self._dist_owner = np.array([p.owner for p in dist], dtype=int)
            self._dist_world = np.array([p.b for p in dist], dtype=int)
            # a robot polytope against a primitive: its hull vertices give distances
            # (exact to boxes in a face's region, else within a known margin)
            self._box_pairs: dict[int, tuple[np.ndarray, np.ndarray, int]] = {}
            self._vertex_pairs: dict[int, tuple[int, int]] = {}
            for col, p in enumerate(dist):
                world = gm.geometryObjects[p.b]
                robot_geom = gm.geometryObjects[p.a].geometry
                if isinstance(world.geometry, coal.OcTree):
                    self._octree_pairs[col] = (
                        self._hull(p.a)
                        if isinstance(robot_geom, POLYTOPES)
                        else (0, np.zeros((0, 3)))
                    )
                if not isinstance(robot_geom, POLYTOPES) or p.a != p.owner:
                    continue
                if self._bounds_for(p.b).exact:
                    self._vertex_pairs[col] = (p.a, p.b)
                if not isinstance(world.geometry, coal.Box):
                    continue
                self._hull(p.a)
                self._box_pairs[col] = (
                    np.linalg.inv(world.placement.homogeneous),
                    np.asarray(world.geometry.halfSide, dtype=float),
                    p.a,
                )

    def clearance(self, q: Any, precision: float = 1e-3) -> np.ndarray:
        """Minimum distance of the robot to the environment and the object [m].

        Pairs: every robot link vs every environment shape, except the base
        links (fixed to the universe or the first joint) vs a support (the
        table), whose distance to it does not change with the configuration
        (0.14 m for ``panda_link1``), and every *arm* link vs the object. The
        gripper (hand and fingers) vs the object is left out: at a grasp it
        touches the object by design. Penetrating pairs give a distance <= 0
        (a penetration, not necessarily the deepest one).

        Distances are computed in increasing order of the pairs' lower bounds
        (sphere covers), and only while a pair's bound is below the best
        distance found minus ``precision``: exact ones by coal on the meshes,
        or, from the hull vertices (vectorised), the exact distance of a link
        in the region of one face of a box, and the distance of a link's
        nearest vertex from a primitive shape where a separating plane proves
        it within ``precision`` of the pair's. The result is a real distance
        of the robot to the world (between two of their points), at most
        ``precision`` above the minimum (the ranking needs no more).

        Args:
            q: Configurations (N, nq) or (nq,) [rad].
            precision: How far above the true minimum the result may be [m], >= 0.

        Returns:
            (N,) distances [m]; ``inf`` when there is nothing to measure against,
            NaN for non-finite configurations.

        Raises:
            InputError: ``precision`` is not a finite distance >= 0.
        """
        qs = self.robot.as_configurations(q)
        try:
            valid = 0 <= float(precision) < np.inf  # NaN would measure no pair
        except (TypeError, ValueError):
            valid = False
        if not valid:
            raise InputError(f"precision must be a finite distance >= 0 [m], got {precision!r}")
        out = np.full(len(qs), np.inf)
        finite = np.all(np.isfinite(qs), axis=1)
        out[~finite] = np.nan
        rows = np.flatnonzero(finite)
        if self._dist_model is None or rows.size == 0:
            return out
        with kernels.one_blas_thread(rows.size):
            self._clearance_blocks(qs, rows, out, precision)
        return out

    def _clearance_blocks(
        self, qs: np.ndarray, rows: np.ndarray, out: np.ndarray, precision: float
    ) -> None:
        """:meth:`clearance` of the finite configurations ``qs[rows]``, into ``out``."""
        model, data = self.robot.model, self._data
        dm, dd = self._dist_model, self._dist_data
        compiled = kernels.get()
        packed = None if compiled is None else self._clearance_packed()
        for a in range(0, rows.size, BLOCK):
            block = rows[a : a + BLOCK]
            frames = self._frames.compute(qs[block])
            if compiled is None or packed is None:
                exact, bound = self._bounds_and_faces(frames)
            else:
                tfs = stacked(frames.transforms)
                bound = self._sphere_bounds_compiled(compiled, packed, frames, tfs)
                exact = compiled.face_distances(tfs, *packed.faces, bound)
            # exact: distances to boxes where a link lies in the region of one face, and
            # where they can still be the nearest
            known = np.isfinite(exact)
            bound[known] = exact[known]
            best0 = np.where(known, exact, np.inf).min(axis=1)
            need = ~known & (bound < best0[:, None] - precision)
            # the nearest hull vertex's distance where it is within precision of the pair's
            # (its lower bound stays the pair's bound: what it may still be)
            need &= precision > 0
            if compiled is None or packed is None:
                upper, lower = self._vertex_distances(frames, need, precision)
            else:
                upper, lower = compiled.vertex_distances(tfs, need, *packed.vertices, precision)
            found = np.isfinite(upper)
            exact[found], known[found], bound[found] = upper[found], True, lower[found]
            best0 = np.where(known, exact, np.inf).min(axis=1)
            # coal only for rows with a pair that may still be nearer than best - precision
            need = ~known & (bound < best0[:, None] - precision)
            open_ = need.any(axis=1)
            todo = np.flatnonzero(open_)
            out[block[~open_]] = best0[~open_]
            order = np.argsort(bound[todo], axis=1)
            near = self._octree_near(frames, todo) if self._octree_pairs else None
            for k, i in enumerate(todo.tolist()):
                n = int(block[i])
                pin.updateGeometryPlacements(model, data, dm, dd, qs[n])
                best = np.inf
                lb = bound[i]
                for p in order[k].tolist():
                    if lb[p] >= best - precision:
                        break
                    if known[i, p]:
                        d = exact[i, p]
                    elif near is not None and p in self._octree_pairs:
                        d = self._octree_distance(p, near, k, best)
                    else:
                        d = pin.computeDistance(dm, dd, p).min_distance
                    if d < best:
                        best = d
                out[n] = best

    def _octree_near(self, frames: Any, rows: np.ndarray) -> tuple[Any, np.ndarray]:
        """What :meth:`_octree_distance` needs of the configurations ``rows`` of a block.

        The joint frames (J, M, 3, 4) and the cover spheres' centres (M, S, 3), base frame.
        """
        cov = self._cover
        return stacked(frames.transforms)[:, rows], self._place(frames, cov.joint, cov.centre, rows)

    def _octree_distance(self, p: int, near: tuple[Any, np.ndarray], k: int, cap: float) -> float:
        """The distance by coal of clearance pair ``p`` (a link and an octree) below ``cap``.

        Over the octree's cells near the geometry
        (:func:`~gcm_pipeline.robot.collision.octree_near.near_distance`);
        ``near`` from :meth:`_octree_near`, ``k`` the configuration's row in it;
        the geometry placements of :attr:`_dist_data` are the configuration's.
        """
        tfs, centres = near
        pair = self._dist_model.collisionPairs[p]
        a, w = int(pair.first), int(pair.second)
        g = int(self._dist_owner[p])
        shape = self._bounds_for(w)
        cov = self._cover
        sph = slice(cov.start[g], cov.start[g + 1])
        inv = shape.inv
        local = centres[k, sph] @ inv[:3, :3].T + inv[:3, 3]
        joint, verts = self._octree_pairs[p]
        tf = tfs[joint, k]
        rot = inv[:3, :3] @ tf[:, :3]
        pts = verts @ rot.T + (inv[:3, :3] @ tf[:, 3] + inv[:3, 3])
        dm, dd = self._dist_model, self._dist_data
        return near_distance(
            dm.geometryObjects[a].geometry,
            coal_transform(dd.oMg[a].homogeneous),
            dm.geometryObjects[w].geometry,
            coal_transform(dd.oMg[w].homogeneous),
            shape.cells,
            shape.cell_reach,
            local,
            cov.radius[sph],
            pts,
            cap,
            dd.distanceRequests[p],
        )

    def _bounds_and_faces(self, frames: Any) -> tuple[np.ndarray, np.ndarray]:
        """The NumPy reference of a block's first steps: exact face distances and bounds.

        Returns ``(exact, bound)`` (N, P): :meth:`_face_distances` and the pairs'
        lower bounds from the sphere covers (:meth:`_sphere_bounds`).
        """
        cov = self._cover
        centres = self._place(frames, cov.joint, cov.centre)
        bound = self._sphere_bounds(centres)
        return self._face_distances(frames, centres, bound), bound

    def _sphere_bounds(self, centres: np.ndarray, bound: np.ndarray | None = None) -> np.ndarray:
        """Lower bounds (N, P) of the pairs' distances from the placed cover spheres (N, S, 3).

        ``bound``: only the pairs of its NaN columns, into it.
        """
        cov = self._cover
        worlds = self._dist_world
        if bound is None:
            bound = np.empty((centres.shape[0], self._dist_owner.size))
        else:
            worlds = worlds[np.isnan(bound).any(axis=0)]
        for w in np.unique(worlds).tolist():
            cols = np.flatnonzero(self._dist_world == w)
            d = self._bounds_for(w).lower(centres) - cov.radius
            per_owner = np.minimum.reduceat(d, cov.start[:-1], axis=1)
            bound[:, cols] = per_owner[:, self._dist_owner[cols]]
        return bound

    def _sphere_bounds_compiled(
        self, compiled: Any, packed: _Packed, frames: Any, tfs: np.ndarray
    ) -> np.ndarray:
        """:meth:`_sphere_bounds` by the compiled kernel (an octree's columns by NumPy)."""
        bound = compiled.sphere_bounds(tfs, *packed.spheres)
        if packed.octree_cols.size:  # its cells bound tighter than the kernel's box
            cov = self._cover
            bound[:, packed.octree_cols] = np.nan
            self._sphere_bounds(self._place(frames, cov.joint, cov.centre), bound)
        return bound

    def _clearance_packed(self) -> _Packed:
        """The compiled kernels' arguments (built once per checker)."""
        if self._packed is not None:
            return self._packed
        cov = self._cover
        worlds = np.unique(self._dist_world)
        shapes = np.array([self._bounds_for(int(w)).packed() for w in worlds.tolist()])
        octree = [self._bounds_for(int(w)).cells is not None for w in self._dist_world.tolist()]
        world = np.searchsorted(worlds, self._dist_world)
        spheres = (cov.joint, cov.centre, cov.radius, cov.start, self._dist_owner, world, shapes)
        boxes = self._box_pairs
        order = self._box_order()
        hulls = [self._hull(boxes[k][2]) for k in order]
        faces = (
            cov.joint,
            cov.centre,
            cov.radius,
            cov.start,
            np.array([j for j, _ in hulls], dtype=np.intp),
            np.array(order, dtype=np.intp),
            np.array([boxes[k][2] for k in order], dtype=np.intp),
            np.array([boxes[k][0][:3].reshape(-1) for k in order]).reshape(-1, 12),
            _starts([v for _, v in hulls]),
            _stack([v for _, v in hulls]),
            np.array([boxes[k][1] for k in order]).reshape(-1, 3),
        )
        npair = self._dist_owner.size
        vertex = self._vertex_pairs
        vhulls = [self._hull(vertex[p][0]) if p in vertex else None for p in range(npair)]
        vertices = (
            np.array([-1 if h is None else h[0] for h in vhulls], dtype=np.intp),
            world,
            _starts([np.zeros((0, 3)) if h is None else h[1] for h in vhulls]),
            np.ascontiguousarray(
                _stack([np.zeros((0, 3)) if h is None else h[1] for h in vhulls]).T
            ),
            shapes,
        )
        self._packed = _Packed(spheres, faces, vertices, np.flatnonzero(octree))
        return self._packed

    def _box_order(self) -> list[int]:
        """The box pairs' columns in the order both face-distance codes visit them.

        The links farthest along the chain first (at a grasp they are usually the
        nearest), then by column: a fixed order, so a row's result does not depend
        on the other rows of its batch.
        """
        cov, boxes = self._cover, self._box_pairs
        return sorted(boxes, key=lambda k: (-int(cov.ball_joint[boxes[k][2]]), k))

    def _vertex_distances(
        self, frames: Any, need: np.ndarray, precision: float
    ) -> tuple[np.ndarray, np.ndarray]:
        """Bounds ``(U, L)`` (N, P) of the clearance pairs' distances, NaN where not known.

        Only the pairs ``need`` (N, P) are looked at.

        For a robot polytope against a primitive shape: ``U``, the distance of
        its nearest hull vertex (a point of the robot) from the shape, bounds
        the pair's distance ``d`` from above. From below, the plane through
        the shape's nearest point normal to that direction separates the shape
        from the hull by ``L = min_v n . v - h(n)`` (``h`` the shape's support
        function), and the robot's geometry lies in its hull: ``L <= d <= U``.
        Both are kept where ``U - L <= precision`` (the vertex is outside the shape).
        """
        out = np.full(need.shape, np.nan)
        below = np.full(need.shape, np.nan)
        rots, poss = frames.rots, frames.poss
        for col in np.flatnonzero(need.any(axis=0)).tolist():
            pair = self._vertex_pairs.get(col)
            if pair is None:
                continue
            rows = np.flatnonzero(need[:, col])
            g, w = pair
            joint, verts = self._hull(g)
            shape = self._bounds_for(w)
            pts = in_frame((rots[joint], poss[joint], shape.inv), rows, verts.T)
            pts = pts.transpose(0, 2, 1)  # (M, V, 3) in the shape's frame
            gap = pts - shape.nearest(pts)
            dist = np.sqrt(squared_norms(gap))
            at = np.argmin(dist, axis=1)
            m = np.arange(rows.size)
            upper = dist[m, at]
            outside = upper > 0
            normal = gap[m, at] / np.where(outside, upper, 1.0)[:, None]
            lower = np.einsum("mvi,mi->mv", pts, normal).min(axis=1) - shape.support(normal)
            keep = outside & (upper - lower <= precision)
            out[rows[keep], col] = upper[keep]
            below[rows[keep], col] = lower[keep]
        return out, below

    def _face_distances(self, frames: Any, centres: np.ndarray, bound: np.ndarray) -> np.ndarray:
        """Exact distances (N, P) of the clearance pairs against boxes, NaN where unknown.

        A robot geometry that lies in the region of one face of a box (its
        covering spheres inside the face's rectangle, its hull vertices beyond
        the face's plane) is at the distance of its nearest hull vertex from
        that plane: the distance to the box is linear in that region, so its
        minimum over the geometry is at a hull vertex (what coal computes on
        the mesh, to round-off).

        Pairs whose lower bound ``bound`` (N, P) is no less than an exact
        distance already found for the row are left unknown: their distance
        cannot be below the row's minimum, so the clearance is the same. The
        pairs are visited in a fixed order, the links farthest along the chain first
        (at a grasp they are usually the nearest): a row's result does not depend on
        the other rows of the batch (two pairs can be at the same distance, e.g. the
        two fingers over a table, to round-off).
        """
        n = centres.shape[0]
        out = np.full((n, self._dist_owner.size), np.nan)
        best = np.full(n, np.inf)
        cov = self._cover
        rots, poss = frames.rots, frames.poss
        pairs = self._box_pairs
        for col in self._box_order():
            inv, halfs, g = pairs[col]
            sph = np.arange(cov.start[g], cov.start[g + 1])
            may = np.flatnonzero(bound[:, col] < best)
            if may.size == 0:
                continue
            pts = centres[may][:, sph]
            c = (row_matmul(pts.reshape(-1, 3), inv[:3, :3].T) + inv[:3, 3]).reshape(pts.shape)
            r = cov.radius[sph]
            joint, verts = self._hulls[g]
            for axis in range(3):
                other = [k for k in range(3) if k != axis]
                lateral = np.all(np.abs(c[:, :, other]) + r[None, :, None] <= halfs[other], axis=2)
                rows = np.flatnonzero(lateral.all(axis=1))
                if rows.size == 0:
                    continue
                # the face on the geometry's side
                sign = np.where(c[rows, 0, axis] >= 0, 1.0, -1.0)
                at = may[rows]
                frame = (rots[joint][at], poss[joint][at], inv)
                height = height_over_face(frame, verts.T, halfs, np.full(rows.size, axis), sign)
                above = height >= 0
                out[at[above], col] = height[above]
                np.minimum.at(best, at[above], height[above])
        return out
