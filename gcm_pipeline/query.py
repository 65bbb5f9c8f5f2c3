"""The grasp manifold as an object you can query after a run.

:class:`GraspManifold` joins the manifold's triangles (:class:`~gcm_pipeline.
stages.manifold.Manifold`), the candidate poses at their corners, the run's
blend method and the run's grasp table (reachability, IK solutions,
metrics). Every point of a triangle is a grasp, so the queries work on the
continuous manifold, not only on the densified rows:

================================ ==============================================
``sample(triangles, weights)``   the grasp at any barycentric point (the
                                 run's DLB or DIB; exact at the vertices)
``locate(poses)``                the manifold point nearest to each query pose
                                 (pose metric of :mod:`gcm_pipeline.geometry.
                                 surface`: position [m] plus 0.1 m per radian)
``nearest_reachable(poses)``     the nearest grasp the robot reaches, with its
                                 verified IK solution
``best(metric, region)``         a continuous search for grasps better than
                                 the best row of the run by a ranking metric
================================ ==============================================

Get one from a run with :func:`load_manifold` (a run directory) or
``RunResult.grasp_manifold`` (a run in memory). The robot and the config of
the run are used for the IK checks; they can be overridden per call.

Reachability of new points is decided exactly as in the run (same IK backend,
tolerances, collision world and approach check; see
:class:`~gcm_pipeline.pipeline.ReachabilityCheck`), warm-started from the IK
solutions of nearby rows, so neighbouring grasps keep the same IK branch.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any, NamedTuple

import numpy as np
import numpy.typing as npt
from scipy.spatial import cKDTree

from gcm_pipeline.config import Config, load_config
from gcm_pipeline.errors import GeometryError, InputError, unknown_choice
from gcm_pipeline.geometry.dualquat import dq_from_matrix, dq_translation
from gcm_pipeline.geometry.surface import (
    BLEND_METHODS,
    ORIENTATION_SCALE,
    Location,
    TriangleLocator,
    blend,
    pose_distance,
    pose_features,
    project_onto_triangles,
)
from gcm_pipeline.limits import MAX_LENGTH
from gcm_pipeline.stages.lattice import RowMesh, interpolate, row_memberships, row_mesh
from gcm_pipeline.stages.manifold import Manifold
from gcm_pipeline.table import GraspTable

if TYPE_CHECKING:
    from gcm_pipeline.pipeline import ReachabilityCheck, RunResult
    from gcm_pipeline.robot.model import Robot

__all__ = [
    "QUERY_METRICS",
    "BestGrasps",
    "GraspManifold",
    "Location",
    "NearestReachable",
    "as_query_poses",
    "load_manifold",
]

#: Metrics :meth:`GraspManifold.best` optimises (the ranking metrics).
QUERY_METRICS = (
    "yoshikawa",
    "translational",
    "inverse_condition",
    "joint_limit_margin",
    "clearance",
    "combined",
    "margin",
)

_UNIT_TOL = 1e-6


class NearestReachable(NamedTuple):
    """The nearest reachable grasps of M query poses.

    Attributes:
        dq: (M, 8) the grasp (world), on the manifold; NaN where none was found.
        q: (M, nq) its IK solution [rad], verified by Pinocchio FK, collision
            free and approachable as in the run.
        distance: (M,) pose-metric distance [m] from the query to the grasp.
        triangle: (M,) manifold triangle of the grasp (-1 if none).
        weights: (M, 3) its barycentric weights there.
        found: (M,) bool, False when no reachable grasp was found near the query.
        located: (M,) distance [m] from the query to the manifold itself
            (:meth:`GraspManifold.locate`); equal to ``distance`` when the
            nearest manifold point is reachable.
    """

    dq: np.ndarray
    q: np.ndarray
    distance: np.ndarray
    triangle: np.ndarray
    weights: np.ndarray
    found: np.ndarray
    located: np.ndarray


class BestGrasps(NamedTuple):
    """Grasps found by :meth:`GraspManifold.best`, best first.

    Attributes:
        dq: (K, 8) the grasps (world), points of the manifold.
        q: (K, nq) their verified IK solutions [rad].
        value: (K,) the metric at each grasp (same scale as the run's column).
        triangle: (K,) manifold triangle of each grasp.
        weights: (K, 3) barycentric weights there.
        start_row: (K,) the table row each search started from.
        start_value: (K,) the metric of that row; ``value >= start_value``.
        metric: The metric's name.
    """

    dq: np.ndarray
    q: np.ndarray
    value: np.ndarray
    triangle: np.ndarray
    weights: np.ndarray
    start_row: np.ndarray
    start_value: np.ndarray
    metric: str


def _check_positions(xyz: np.ndarray, name: str) -> None:
    """Positions within the scene's bounds (``MAX_LENGTH`` per coordinate, as the config's)."""
    bad = (np.abs(xyz) > MAX_LENGTH).any(axis=1)
    if bad.any():
        i = int(np.argmax(bad))
        raise GeometryError(
            f"{name} {i}: position [{', '.join(f'{v:.10g}' for v in xyz[i])}] m is outside the "
            f"scene (at most {MAX_LENGTH:g} m per coordinate)"
        )


def as_query_poses(poses: Any, name: str = "query pose") -> np.ndarray:
    """Validate query poses and return them as unit dual quaternions (M, 8).

    Args:
        poses: (M, 4, 4) or (4, 4) rigid transforms, or (M, 8) or (8,) unit
            dual quaternions ``[r_w, r_x, r_y, r_z, d_w, d_x, d_y, d_z]``.
        name: How to call them in messages.

    Raises:
        GeometryError: Another shape, non-finite values, a matrix that is not
            rigid or a dual quaternion that is not unit (names the first bad one).
    """
    try:
        arr = np.asarray(poses, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise GeometryError(f"{name}s must be numbers: {exc}") from None
    if arr.shape[-2:] == (4, 4) and arr.ndim in (2, 3):
        mats = arr.reshape(-1, 4, 4)
        xyz = mats[:, :3, 3]
        _check_positions(np.where(np.isfinite(xyz), xyz, 0.0), name)  # non-finite: said below
        try:
            return dq_from_matrix(mats)
        except GeometryError as exc:
            raise GeometryError(f"{name}: {exc}") from None
    if arr.ndim in (1, 2) and arr.shape[-1] == 8:
        dq = arr.reshape(-1, 8)
        bad = ~np.isfinite(dq).all(axis=1)
        if bad.any():
            i = int(np.argmax(bad))
            raise GeometryError(f"{name} {i} has non-finite values: {dq[i].tolist()}")
        norm = np.linalg.norm(dq[:, :4], axis=1)
        dot = np.einsum("ij,ij->i", dq[:, :4], dq[:, 4:])
        bad = (np.abs(norm - 1.0) > _UNIT_TOL) | (np.abs(dot) > _UNIT_TOL)
        if bad.any():
            i = int(np.argmax(bad))
            raise GeometryError(
                f"{name} {i} is not a unit dual quaternion (|real| = {norm[i]:.6g}, "
                f"real.dual = {dot[i]:.2e}); pass (4, 4) matrices or dq_from_pos_quat(...)"
            )
        _check_positions(dq_translation(dq), name)
        return dq.copy()
    raise GeometryError(
        f"{name}s must be (M, 4, 4) / (4, 4) matrices or (M, 8) / (8,) dual quaternions, "
        f"got shape {arr.shape}"
    )


class GraspManifold:
    """A grasp manifold you can sample and query (see the module docstring).

    Args:
        mesh: The manifold's triangles over the candidates.
        grasps: The run's grasp table: the candidates first (rows ``0 ..
            V - 1`` are the manifold's vertices), then the other rows, with
            the reachability columns for the reachability queries.
        method: The blend of the run, ``dlb`` or ``dib``.
        config: The run's config (IK, collisions and approach of the
            reachability checks; ranking weights).
        robot: The run's robot (else loaded from ``config`` when needed).
        orientation_scale: ``L`` [m/rad] of the pose metric (default:
            ``config.manifold.orientation_scale``, else 0.1).

    Raises:
        InputError: The table has fewer rows than the manifold has vertices,
            or no ``dq`` column.
        GeometryError: Unknown blend method.
    """

    def __init__(
        self,
        mesh: Manifold,
        grasps: GraspTable,
        *,
        method: str = "dlb",
        config: Config | None = None,
        robot: Robot | None = None,
        orientation_scale: float | None = None,
    ) -> None:
        if method not in BLEND_METHODS:
            raise GeometryError(unknown_choice("blend method", method, BLEND_METHODS))
        if "dq" not in grasps:
            raise InputError("the grasp table of a manifold needs a 'dq' column")
        n_v = mesh.n_vertices
        if len(grasps) < n_v:
            raise InputError(
                f"the grasp table has {len(grasps)} rows, fewer than the manifold's {n_v} vertices"
            )
        self.mesh = mesh
        self.grasps = grasps
        self.method = method
        self.config = config
        self._robot = robot
        if orientation_scale is None:
            orientation_scale = (
                config.manifold.orientation_scale if config is not None else ORIENTATION_SCALE
            )
        self.orientation_scale = float(orientation_scale)
        self.poses = np.asarray(grasps["dq"], dtype=np.float64)[:n_v]
        self._locator: TriangleLocator | None = None
        self._rows: RowMesh | None = None
        self._checks: dict[int, ReachabilityCheck] = {}

    # ------------------------------------------------------------ construction
    @classmethod
    def from_run(cls, result: RunResult) -> GraspManifold:
        """The manifold of a run in memory (:class:`~gcm_pipeline.pipeline.RunResult`)."""
        cfg = result.config
        return cls(
            result.manifold,
            result.grasps,
            method=cfg.densify.method,
            config=cfg,
            robot=result.robot,
        )

    # ------------------------------------------------------------ properties
    @property
    def triangles(self) -> np.ndarray:
        """(T, 3) candidate row ids of the triangles."""
        return self.mesh.triangles

    @property
    def robot(self) -> Robot:
        """The run's robot (loaded from the config on first use)."""
        if self._robot is None:
            if self.config is None:
                raise InputError("this manifold has no config: pass robot= and cfg= to the query")
            from gcm_pipeline.robot.model import load_robot

            self._robot = load_robot(self.config.robot.spec)
        return self._robot

    @property
    def locator(self) -> TriangleLocator:
        """The nearest-point index over the triangles (built on first use)."""
        if self._locator is None:
            self._locator = TriangleLocator(
                self.poses[self.triangles],
                method=self.method,
                orientation_scale=self.orientation_scale,
            )
        return self._locator

    @property
    def row_mesh(self) -> RowMesh:
        """The rows of the table as a mesh (:func:`~gcm_pipeline.stages.lattice.row_mesh`)."""
        if self._rows is None:
            self._rows = row_mesh(self.grasps, self.triangles, self.mesh.n_vertices)
        return self._rows

    def __len__(self) -> int:
        """Number of triangles."""
        return len(self.triangles)

    def close(self) -> None:
        """Stop the worker processes of the reachability checks made so far (if any ran)."""
        for check in self._checks.values():
            check.close()
        self._checks.clear()

    def __enter__(self) -> GraspManifold:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def __repr__(self) -> str:
        reach = self.grasps.get("reachable")
        nr = "" if reach is None else f", {int(np.count_nonzero(reach))} reachable"
        return (
            f"GraspManifold({len(self)} triangles, {self.mesh.n_vertices} vertices, "
            f"{len(self.grasps)} rows{nr}, method={self.method!r}, "
            f"projection={self.mesh.projection!r})"
        )

    # ------------------------------------------------------------ geometry
    def sample(self, triangles: npt.ArrayLike, weights: npt.ArrayLike) -> np.ndarray:
        """Grasps at barycentric points of triangles, blended as in the run.

        Args:
            triangles: (M,) triangle ids (rows of :attr:`triangles`).
            weights: (M, 3) barycentric weights, >= 0, summing to 1.

        Returns:
            (M, 8) unit dual quaternions (world). A weight row with a single
            1 returns that vertex's pose bit for bit.

        Raises:
            GeometryError: Triangle ids out of range, weights of the wrong
                shape, negative, non-finite or not summing to 1.
        """
        tri, w = self._check_points(triangles, weights)
        return blend(self.poses[self.triangles[tri]], w, self.method)

    def _check_points(
        self, triangles: npt.ArrayLike, weights: npt.ArrayLike
    ) -> tuple[np.ndarray, np.ndarray]:
        tri = np.asarray(triangles)
        if not np.issubdtype(tri.dtype, np.integer):
            raise GeometryError(f"triangle ids must be integers, got dtype {tri.dtype}")
        tri = tri.astype(np.int64).reshape(-1)
        w = np.asarray(weights, dtype=np.float64).reshape(-1, 3) if np.size(weights) else None
        if w is None or w.shape != (len(tri), 3):
            raise GeometryError(f"weights must have shape ({len(tri)}, 3), got {np.shape(weights)}")
        bad = (tri < 0) | (tri >= len(self))
        if bad.any():
            i = int(np.argmax(bad))
            raise GeometryError(f"triangle id {int(tri[i])} at {i} is outside 0..{len(self) - 1}")
        off = ~np.isfinite(w).all(axis=1) | (w < -1e-12).any(axis=1)
        off |= np.abs(w.sum(axis=1) - 1.0) > 1e-9
        if off.any():
            i = int(np.argmax(off))
            raise GeometryError(
                f"weights at {i} must be finite, >= 0 and sum to 1, got {w[i].tolist()}"
            )
        return tri, np.clip(w, 0.0, None)

    def locate(self, poses: Any) -> Location:
        """The manifold point nearest to each query pose.

        The metric is position [m] plus orientation at ``L`` =
        :attr:`orientation_scale` metres per radian (see
        :mod:`gcm_pipeline.geometry.surface`); the search is exact up to the
        projection's tolerance (no triangle that could hold a nearer point is
        skipped).

        Args:
            poses: (M, 4, 4) or (M, 8) query poses in the world (one pose: (4, 4) or (8,)).

        Returns:
            :class:`~gcm_pipeline.geometry.surface.Location`: ``triangle``
            (M,), ``weights`` (M, 3), ``distance`` (M,) [m], ``dq`` (M, 8).

        Raises:
            GeometryError: Query poses not rigid, not finite or of a wrong shape.
        """
        return self.locator.locate(as_query_poses(poses))

    # ------------------------------------------------------------ reachability
    def _checker(self, robot: Robot | None, cfg: Config | None) -> ReachabilityCheck:
        from gcm_pipeline.pipeline import ReachabilityCheck

        cfg = cfg if cfg is not None else self.config
        if cfg is None:
            raise InputError("this manifold has no config: pass cfg= (and robot=)")
        robot = robot if robot is not None else self.robot
        key = hash((id(robot), id(cfg)))
        check = self._checks.get(key)
        if check is None or check.robot is not robot or check.config is not cfg:
            check = ReachabilityCheck(robot, cfg)
            self._checks[key] = check
        return check

    def _reachable_rows(self) -> tuple[np.ndarray, np.ndarray]:
        if "reachable" not in self.grasps or "q" not in self.grasps:
            raise InputError(
                "the grasp table has no reachability columns ('reachable', 'q'): "
                "run the reachability stage first"
            )
        reach = np.asarray(self.grasps["reachable"], dtype=bool)
        q = np.asarray(self.grasps["q"], dtype=np.float64)
        return np.flatnonzero(reach & np.isfinite(q).all(axis=1)), q

    def nearest_reachable(
        self,
        poses: Any,
        robot: Robot | None = None,
        cfg: Config | None = None,
        *,
        neighbours: int = 4,
        bisections: int = 8,
    ) -> NearestReachable:
        """The nearest grasp of the continuous manifold that the robot reaches.

        For each query: its nearest manifold point (:meth:`locate`) is checked
        first, warm-started from the solutions of its triangle's vertices and
        of the nearest reachable rows. If it is not reachable, the query is
        projected onto the triangles of the ``neighbours`` nearest reachable
        rows; each projection is checked, and where it is unreachable the
        boundary is found by ``bisections`` halvings of the segment (in
        barycentric weights) from the reachable row towards it. The nearest
        reachable point found wins; it is never farther than the nearest
        reachable row of the run.

        Args:
            poses: (M, 4, 4) or (M, 8) query poses in the world.
            robot: The robot (default: the run's).
            cfg: The config whose ``ik``, ``environment``, ``object`` and
                ``approach`` decide reachability (default: the run's).
            neighbours: Reachable rows whose triangles are searched per query.
            bisections: Halvings of each segment towards the boundary.

        Returns:
            :class:`NearestReachable`.

        Raises:
            GeometryError: Bad query poses.
            InputError: No reachability columns, or no config to check with.
        """
        query = as_query_poses(poses)
        m = len(query)
        check = self._checker(robot, cfg)
        nq = check.robot.nq
        rows_ok, q_table = self._reachable_rows()
        loc = self.locator.locate(query)
        out_dq = np.full((m, 8), np.nan)
        out_q = np.full((m, nq), np.nan)
        out_d = np.full(m, np.inf)
        out_t = np.full(m, -1, dtype=np.int64)
        out_w = np.full((m, 3), np.nan)
        if m == 0:
            return NearestReachable(
                out_dq, out_q, out_d, out_t, out_w, np.zeros(0, bool), loc.distance
            )

        def offer(
            i: np.ndarray, dq: np.ndarray, q: np.ndarray, t: np.ndarray, w: np.ndarray
        ) -> None:
            if not len(i):
                return
            d = pose_distance(dq, query[i], self.orientation_scale)
            # several offers for one query: keep the nearest (lexsort by distance)
            order = np.lexsort((d, i))
            i, dq, q, t, w, d = i[order], dq[order], q[order], t[order], w[order], d[order]
            first = np.r_[True, i[1:] != i[:-1]]
            i, dq, q, t, w, d = i[first], dq[first], q[first], t[first], w[first], d[first]
            better = d < out_d[i]
            i = i[better]
            out_dq[i], out_q[i], out_d[i] = dq[better], q[better], d[better]
            out_t[i], out_w[i] = t[better], w[better]

        # nearest reachable rows of every query (pose metric, both quaternion signs)
        k = min(int(neighbours), rows_ok.size)
        near = np.zeros((m, 0), dtype=np.int64)
        if k > 0:
            feat = pose_features(self.grasps["dq"][rows_ok], self.orientation_scale)
            flip = feat.copy()
            flip[:, 3:] *= -1.0
            tree = cKDTree(np.concatenate((feat, flip)))
            _, idx = tree.query(pose_features(query, self.orientation_scale), k=2 * k)
            idx = np.asarray(idx).reshape(m, 2 * k) % rows_ok.size
            near = _first_unique(idx, k)
            near = rows_ok[near]
        # 1. the nearest manifold point, warm-started from its vertices and the nearest rows
        tri_rows = self.triangles[loc.triangle]
        by_weight = np.take_along_axis(tri_rows, np.argsort(-loc.weights, axis=1), axis=1)
        seed_rows = np.concatenate((by_weight, near), axis=1)
        res = check(loc.dq, q_table[seed_rows])
        ok = np.asarray(res["reachable"], dtype=bool)
        idx_ok = np.flatnonzero(ok)
        offer(idx_ok, loc.dq[ok], np.asarray(res["q"])[ok], loc.triangle[ok], loc.weights[ok])
        todo = np.flatnonzero(~ok)
        if todo.size and k > 0:
            self._search_near_rows(query, todo, near[todo], q_table, check, bisections, offer)
        found = np.isfinite(out_d)
        out_d[~found] = np.nan
        return NearestReachable(out_dq, out_q, out_d, out_t, out_w, found, loc.distance)

    def _search_near_rows(
        self,
        query: np.ndarray,
        todo: np.ndarray,
        near: np.ndarray,
        q_table: np.ndarray,
        check: ReachabilityCheck,
        bisections: int,
        offer: Callable[..., None],
    ) -> None:
        """Step 2 of :meth:`nearest_reachable` for the queries ``todo``."""
        n_v = self.mesh.n_vertices
        mem_row, mem_tri, mem_w = row_memberships(self.grasps, self.triangles, n_v)
        order = np.argsort(mem_row, kind="stable")
        mem_row, mem_tri, mem_w = mem_row[order], mem_tri[order], mem_w[order]
        # the rows themselves, re-checked from their own solutions
        rows = np.unique(near)
        res = check(self.grasps["dq"][rows], q_table[rows][:, None, :])
        good = np.asarray(res["reachable"], dtype=bool)
        q_row = np.full((len(self.grasps), q_table.shape[1]), np.nan)
        q_row[rows[good]] = np.asarray(res["q"])[good]
        # pairs (query, membership of a near row)
        qi = np.repeat(todo, near.shape[1])
        r = near.ravel()
        keep = np.isfinite(q_row[r]).all(axis=1)
        qi, r = qi[keep], r[keep]
        lo = np.searchsorted(mem_row, r, side="left")
        hi = np.searchsorted(mem_row, r, side="right")
        counts = hi - lo
        pair_q = np.repeat(qi, counts)
        pair_r = np.repeat(r, counts)
        pos = (
            np.concatenate([np.arange(a, b) for a, b in zip(lo, hi, strict=True)])
            if len(lo)
            else np.zeros(0, np.int64)
        )
        pair_t, pair_w0 = mem_tri[pos], mem_w[pos]
        row_dq = np.asarray(self.grasps["dq"])[pair_r]
        offer(pair_q, row_dq, q_row[pair_r], pair_t, pair_w0)
        if not len(pair_q):
            return
        corners = self.poses[self.triangles[pair_t]]
        w_y, _ = project_onto_triangles(
            query[pair_q],
            corners,
            pair_w0[:, 1:],
            method=self.method,
            orientation_scale=self.orientation_scale,
        )
        # the projections: reachable ones are offered, the others bisected
        y = blend(corners, w_y, self.method)
        res = check(y, q_row[pair_r][:, None, :])
        ok = np.asarray(res["reachable"], dtype=bool)
        offer(pair_q[ok], y[ok], np.asarray(res["q"])[ok], pair_t[ok], w_y[ok])
        b = np.flatnonzero(~ok)
        s_lo = np.zeros(len(b))
        s_hi = np.ones(len(b))
        q_lo = q_row[pair_r[b]]
        for _ in range(int(bisections)):
            if not len(b):
                break
            s = 0.5 * (s_lo + s_hi)
            w = (1.0 - s)[:, None] * pair_w0[b] + s[:, None] * w_y[b]
            pts = blend(corners[b], w, self.method)
            res = check(pts, q_lo[:, None, :])
            ok = np.asarray(res["reachable"], dtype=bool)
            s_lo = np.where(ok, s, s_lo)
            s_hi = np.where(ok, s_hi, s)
            q_lo[ok] = np.asarray(res["q"])[ok]
        moved = s_lo > 0
        if moved.any():
            bb = b[moved]
            w = (1.0 - s_lo[moved])[:, None] * pair_w0[bb] + s_lo[moved][:, None] * w_y[bb]
            offer(pair_q[bb], blend(corners[bb], w, self.method), q_lo[moved], pair_t[bb], w)

    # ------------------------------------------------------------ optimisation
    def metric_values(self, table: GraspTable, metric: str) -> np.ndarray:
        """A ranking metric of the rows of ``table`` (``reachable``, ``q``, ...); NaN: unreachable.

        Scales are the run's: ``combined`` normalises each metric by its range
        over the run's reachable rows (as the run's ``combined`` column does),
        so values of new grasps compare with the run's rows.

        Raises:
            InputError: Unknown metric, or a column the metric needs is missing.
        """
        from gcm_pipeline.ranking.metrics import weighted_sum
        from gcm_pipeline.robot.manipulability import METRICS, manipulability_metrics

        if metric not in QUERY_METRICS:
            raise InputError(unknown_choice("metric", metric, QUERY_METRICS))
        reach = np.asarray(table["reachable"], dtype=bool)
        q = np.where(reach[:, None], np.asarray(table["q"], dtype=np.float64), np.nan)
        if metric in METRICS:
            return manipulability_metrics(self.robot, q)[metric]
        if metric in ("clearance", "margin"):
            if metric not in table:
                raise InputError(f"metric {metric!r} needs the {metric!r} column; the run has none")
            return np.where(reach, np.asarray(table[metric], dtype=np.float64), np.nan)
        weights = self._combined_weights()
        values = {name: self.metric_values(table, name) for name in weights}
        ref = self._reference_ranges(tuple(weights))
        return np.where(reach, weighted_sum(values, weights, ref, len(table)), np.nan)

    def _combined_weights(self) -> dict[str, float]:
        from gcm_pipeline.ranking.metrics import DEFAULT_COMBINED_WEIGHTS

        w = None if self.config is None else self.config.ranking.weights
        return {k: float(v) for k, v in (w or DEFAULT_COMBINED_WEIGHTS).items() if v > 0}

    def _reference_ranges(self, names: tuple[str, ...]) -> dict[str, tuple[float, float]]:
        from gcm_pipeline.ranking.metrics import value_range

        out = {}
        for name in names:
            out[name] = value_range(self.metric_values(self.grasps, name))
        return out

    def best(
        self,
        metric: str | None = None,
        region: Sequence[int] | npt.ArrayLike | Callable[[np.ndarray], Any] | None = None,
        *,
        starts: int = 8,
        iterations: int = 12,
        robot: Robot | None = None,
        cfg: Config | None = None,
    ) -> BestGrasps:
        """Search the continuous manifold for the grasps best by a ranking metric.

        Starts from the ``starts`` best reachable rows (in ``region``) and
        climbs inside their triangles by a pattern search on the barycentric
        weights: six directions, the step halving when none improves. Every
        trial point is checked like a row of the run (IK warm-started from the
        current solution, so the search stays on its IK branch; collisions;
        approach) and its metric computed from its own solution; a move is
        taken only if it is reachable, in ``region`` and strictly better. So
        each result is at least as good as the row it started from, and the
        first one at least as good as the best row of the run.

        Args:
            metric: One of :data:`QUERY_METRICS` (default: the run's ranking metric).
            region: None (the whole manifold), triangle ids, or a callable
                taking poses (M, 8) and returning a boolean mask (M,).
            starts: How many of the best rows to start from.
            iterations: Pattern-search iterations.
            robot: The robot (default: the run's).
            cfg: The config deciding reachability (default: the run's).

        Returns:
            :class:`BestGrasps`, one per start row, best first.

        Raises:
            InputError: Unknown metric, no reachability columns, no reachable
                row in ``region``.
        """
        if metric is None:
            metric = self.config.ranking.metric if self.config is not None else "yoshikawa"
        if metric not in QUERY_METRICS:
            raise InputError(unknown_choice("metric", metric, QUERY_METRICS))
        check = self._checker(robot, cfg)
        rows_ok, q_table = self._reachable_rows()
        row_values = self.metric_values(self.grasps, metric)
        inside = self._region_mask(region)
        mem_row, mem_tri, mem_w = row_memberships(self.grasps, self.triangles, self.mesh.n_vertices)
        in_region = inside(mem_tri, self.grasps["dq"][mem_row])
        candidates = np.unique(mem_row[in_region])
        candidates = candidates[np.isin(candidates, rows_ok) & np.isfinite(row_values[candidates])]
        if not candidates.size:
            raise InputError(f"no reachable row with a finite {metric!r} in the region")
        order = np.lexsort((candidates, -row_values[candidates]))
        start_rows = candidates[order][: max(1, int(starts))]
        # one search per (start row, triangle around it)
        sel = np.isin(mem_row, start_rows) & in_region
        s_row, t, w = mem_row[sel], mem_tri[sel], mem_w[sel].copy()
        q_cur = q_table[s_row].copy()
        val = row_values[s_row].copy()
        dq_cur = np.asarray(self.grasps["dq"])[s_row].copy()
        step = np.full(len(t), 0.5 * self._cell_size())
        directions = np.array(
            [[1, -1, 0], [-1, 1, 0], [0, 1, -1], [0, -1, 1], [-1, 0, 1], [1, 0, -1]], float
        )
        min_step = step / 64.0
        for _ in range(int(iterations)):
            act = np.flatnonzero(step >= min_step)
            if not act.size:
                break
            trial_w = (w[act, None, :] + step[act, None, None] * directions[None]).reshape(-1, 3)
            owner = np.repeat(act, len(directions))
            valid = (trial_w >= -1e-12).all(axis=1)
            trial_w = np.clip(trial_w, 0.0, None)
            trial_w /= trial_w.sum(axis=1, keepdims=True)
            trial_t = t[owner]
            pts = blend(self.poses[self.triangles[trial_t]], trial_w, self.method)
            valid &= inside(trial_t, pts)
            gain = np.full(len(owner), -np.inf)
            new_q = np.full((len(owner), q_table.shape[1]), np.nan)
            trial_vals = np.full(len(owner), np.nan)
            if valid.any():
                v = np.flatnonzero(valid)
                res = check(pts[v], q_cur[owner[v]][:, None, :])
                vals = self._point_values(res, metric, trial_t[v], trial_w[v])
                good = np.asarray(res["reachable"], dtype=bool) & np.isfinite(vals)
                gain[v[good]] = vals[good] - val[owner[v[good]]]
                new_q[v[good]] = np.asarray(res["q"])[good]
                trial_vals[v] = vals
            gains = gain.reshape(len(act), len(directions))
            pick = np.argmax(gains, axis=1)
            best_gain = gains[np.arange(len(act)), pick]
            moved = best_gain > 0
            flat = np.arange(len(act)) * len(directions) + pick
            mv = act[moved]
            w[mv] = trial_w[flat[moved]]
            q_cur[mv] = new_q[flat[moved]]
            val[mv] = trial_vals[flat[moved]]
            dq_cur[mv] = pts[flat[moved]]
            step[act[~moved]] *= 0.5
        # best search per start row, then best first
        order = np.lexsort((-val, s_row))
        s_row, t, w, q_cur, val, dq_cur = (
            s_row[order],
            t[order],
            w[order],
            q_cur[order],
            val[order],
            dq_cur[order],
        )
        first = np.r_[True, s_row[1:] != s_row[:-1]]
        keep = np.flatnonzero(first)
        keep = keep[np.lexsort((s_row[keep], -val[keep]))]
        return BestGrasps(
            dq=dq_cur[keep],
            q=q_cur[keep],
            value=val[keep],
            triangle=t[keep],
            weights=w[keep],
            start_row=s_row[keep],
            start_value=row_values[s_row[keep]],
            metric=metric,
        )

    def _point_values(
        self, res: GraspTable, metric: str, tri: np.ndarray, w: np.ndarray
    ) -> np.ndarray:
        """Metric of checked new points; ``margin`` is interpolated from the rows."""
        if metric == "margin":
            if "margin" not in self.grasps:
                raise InputError("metric 'margin' needs the 'margin' column; the run has none")
            m = interpolate(self.row_mesh, self.grasps["margin"], tri, w)
            return np.where(np.asarray(res["reachable"], dtype=bool), m, np.nan)
        if metric == "combined" and "margin" in self._combined_weights():
            m = interpolate(self.row_mesh, self.grasps["margin"], tri, w)
            res = res.with_columns(margin=m)
        return self.metric_values(res, metric)

    def _cell_size(self) -> float:
        """Typical size of a row-mesh face in barycentric weights."""
        rm = self.row_mesh
        if not len(rm.weights):
            return 0.25
        edge = np.abs(rm.weights[:, 1] - rm.weights[:, 0]).max(axis=1)
        return float(np.clip(np.median(edge), 1e-3, 1.0))

    def _region_mask(self, region: Any) -> Callable[[np.ndarray, np.ndarray], np.ndarray]:
        """``inside(triangles (M,), poses (M, 8)) -> (M,) bool`` for a region argument."""
        if region is None:
            return lambda tri, dq: np.ones(len(tri), dtype=bool)
        if callable(region):

            def inside(tri: np.ndarray, dq: np.ndarray) -> np.ndarray:
                mask = np.asarray(region(np.asarray(dq)), dtype=bool).reshape(-1)
                if mask.shape != (len(dq),):
                    raise InputError(
                        f"region must return a boolean mask of shape ({len(dq)},), got {mask.shape}"
                    )
                return mask

            return inside
        ids = np.asarray(region)
        if ids.ndim != 1 or (ids.size and not np.issubdtype(ids.dtype, np.integer)):
            raise InputError("region must be None, triangle ids or a callable on poses")
        if not ids.size:
            raise InputError("region holds no triangle id; pass None for the whole manifold")
        if ids.size and (ids.min() < 0 or ids.max() >= len(self)):
            raise InputError(f"region triangle ids must be in 0..{len(self) - 1}")
        allowed = np.zeros(len(self), dtype=bool)
        allowed[ids] = True
        return lambda tri, dq: allowed[tri]


def _first_unique(values: np.ndarray, k: int) -> np.ndarray:
    """The first ``k`` distinct entries of each row of ``values`` (M, P), in order.

    Each row must hold at least ``k`` distinct values.
    """
    earlier = np.triu(np.ones((values.shape[1],) * 2, dtype=bool), k=1)  # [a, b]: a before b
    dup = ((values[:, :, None] == values[:, None, :]) & earlier[None]).any(axis=1)
    order = np.argsort(dup, axis=1, kind="stable")[:, :k]
    return np.take_along_axis(values, order, axis=1)


def load_manifold(run_dir: str | Path) -> GraspManifold:
    """Load the queryable manifold of a run directory (``gcm run`` output).

    Reads ``grasps.csv``, ``manifold.npz``, ``summary.json`` and
    ``config.yaml`` (the blend method, the robot and what decides
    reachability).

    Raises:
        InputError: Not a run directory, or a file in it is missing or unreadable.
        ConfigError: Its ``config.yaml`` is invalid.
    """
    from gcm_pipeline.io import read_run

    run = read_run(run_dir)
    path = Path(run_dir) / "config.yaml"
    if not path.is_file():
        raise InputError(f"not a run directory: {run_dir} lacks config.yaml")
    cfg = load_config(path)
    return GraspManifold(run.manifold, run.grasps, method=cfg.densify.method, config=cfg)
