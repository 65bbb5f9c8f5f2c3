"""The grasp manifold as an object you can query after a run.

:class:`GraspManifold` joins the manifold's triangles (:class:`~gcm_pipeline.
manifold.build.Manifold`), the candidate poses at their corners, the run's
blend method and the run's grasp table (reachability, IK solutions,
metrics). Every point of a triangle is a grasp, so the queries work on the
continuous manifold, not only on the densified rows:

================================ ==============================================
``sample(triangles, weights)``   the grasp at any barycentric point (the
                                 run's DLB or DIB; exact at the vertices)
``locate(poses)``                the manifold point nearest to each query pose
                                 (pose metric of :mod:`gcm_pipeline.geometry.
                                 pose_metric`: position [m] plus 0.1 m per radian)
``nearest_reachable(poses)``     the nearest grasp the robot reaches, with its
                                 verified IK solution
``best(metric, region)``         a continuous search for grasps better than
                                 the best row of the run by a ranking metric
================================ ==============================================

Get one from a run with :func:`gcm_pipeline.load_manifold` (a run directory)
or ``RunResult.grasp_manifold`` (a run in memory). The robot and the config of
the run are used for the IK checks; they can be overridden per call.

Reachability of new points is decided exactly as in the run (same IK backend,
tolerances, collision world and approach check), warm-started from the IK
solutions of nearby rows, so neighbouring grasps keep the same IK branch. This
module never reads a config: what the queries need from the run (its robot,
its reachability check, the robot's metrics, the ranking's weights) comes
through a :class:`~gcm_pipeline.manifold.run_queries.RunQueries` object, which
:mod:`gcm_pipeline.pipeline` builds from the run's config; a ``cfg`` passed to
a query is handed back to it unread.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any

import numpy as np
import numpy.typing as npt
from scipy.spatial import cKDTree

from gcm_pipeline.errors import GeometryError, InputError, choice_error
from gcm_pipeline.geometry.pose_metric import (
    ORIENTATION_SCALE,
    other_sign_features,
    pose_features,
)
from gcm_pipeline.manifold.build import Manifold
from gcm_pipeline.manifold.lattice import RowMesh, interpolate, row_memberships, row_mesh
from gcm_pipeline.manifold.locate import Location, TriangleLocator, as_query_poses
from gcm_pipeline.manifold.run_queries import PoseCheck, RunQueries
from gcm_pipeline.manifold.search import (
    Answers,
    BestGrasps,
    NearestReachable,
    first_unique,
    pattern_search,
    search_near_rows,
)
from gcm_pipeline.manifold.surface import BLEND_METHODS, blend
from gcm_pipeline.ranking.metrics import value_range, weighted_sum
from gcm_pipeline.table import GraspTable

__all__ = [
    "QUERY_METRICS",
    "GraspManifold",
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
    "score",
)

#: The metrics of :data:`QUERY_METRICS` the robot computes from a configuration.
_ROBOT_METRICS = ("yoshikawa", "translational", "inverse_condition", "joint_limit_margin")

_NO_CONFIG = "this manifold has no config"

#: Most query poses whose nearest rows :func:`nearest_of_both_signs` finds by brute force
#: (each costs one pass over the rows; more share one KD-tree).
_BRUTE_QUERIES = 8

#: Relative gap under which two squared distances count as tied (far above rounding).
_TIE = 1e-9


def nearest_of_both_signs(
    feat: np.ndarray, queries: np.ndarray, k: int
) -> tuple[np.ndarray, np.ndarray]:
    """``cKDTree(points).query(queries, k)``, points: ``feat`` then its other sign.

    ``feat`` (N, 7) are rows' :func:`~gcm_pipeline.geometry.pose_metric.pose_features`;
    returns (M, k) distances and indices into the 2N points. For a few
    queries the k nearest are found by one pass over the rows instead of
    building the tree: where the k + 1 nearest are apart by more than
    :data:`_TIE` (relative), the answer has only one order, and the k are
    measured by a KD-tree of their own (the tree's distance, bit for bit);
    a query with near ties gets the whole tree's answer (its order among equals).
    """
    n, m = len(feat), len(queries)
    if m > _BRUTE_QUERIES or k > 2 * n:
        dist, idx = _both_signs_tree(feat).query(queries, k=k)
        return np.reshape(dist, (m, k)), np.reshape(idx, (m, k))
    dist, idx = np.empty((m, k)), np.empty((m, k), dtype=np.intp)
    square = np.empty_like(feat)
    tree = None
    for i, query in enumerate(queries):
        d2 = np.empty(2 * n)
        for half, other in enumerate((query, other_sign_features(query))):
            # |q - p'| for p' = p with r negated is |q' - p| (q' = q with r negated), term by term
            np.square(np.subtract(feat, other, out=square), out=square)
            d2[half * n : (half + 1) * n] = square.sum(axis=1)
        part = np.argpartition(d2, min(k, 2 * n - 1))[: k + 1]
        part = part[np.argsort(d2[part], kind="stable")]
        if (np.diff(d2[part]) <= _TIE * d2[part][1:]).any():  # near ties: the tree's order
            tree = _both_signs_tree(feat) if tree is None else tree
            d, j = tree.query(query, k=k)
            dist[i], idx[i] = np.reshape(d, k), np.reshape(j, k)
            continue
        chosen = part[:k]
        own = feat[chosen % n]
        own[chosen >= n] = other_sign_features(own[chosen >= n])
        d, j = cKDTree(own).query(query, k=k)
        dist[i], idx[i] = np.reshape(d, k), chosen[np.reshape(j, k)]
    return dist, idx


def _both_signs_tree(feat: np.ndarray) -> cKDTree:
    """A KD-tree over ``feat`` (N, 7) and then its other sign (row ``N + i``: row ``i``)."""
    return cKDTree(np.concatenate((feat, other_sign_features(feat))))


class GraspManifold:
    """A grasp manifold you can sample and query (see the module docstring).

    Args:
        mesh: The manifold's triangles over the candidates.
        grasps: The run's grasp table: the candidates first (rows ``0 ..
            V - 1`` are the manifold's vertices), then the other rows, with
            the reachability columns for the reachability queries.
        method: The blend of the run, ``dlb`` or ``dib``.
        run: What the reachability and ranking queries need from the run
            (its config's IK, collisions, approach and ranking weights); None:
            geometry only.
        robot: The run's robot (else loaded through ``run`` when needed).
        orientation_scale: ``L`` [m/rad] of the pose metric.

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
        run: RunQueries | None = None,
        robot: Any = None,
        orientation_scale: float = ORIENTATION_SCALE,
    ) -> None:
        if method not in BLEND_METHODS:
            raise choice_error(GeometryError, "blend method", method, BLEND_METHODS)
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
        self.run = run
        self._robot = robot
        self.orientation_scale = float(orientation_scale)
        self.poses = np.asarray(grasps["dq"], dtype=np.float64)[:n_v]
        self._locator: TriangleLocator | None = None
        self._rows: RowMesh | None = None
        self._checks: dict[int, PoseCheck] = {}

    # ------------------------------------------------------------ properties
    @property
    def config(self) -> Any:
        """The run's config (None without a run)."""
        return None if self.run is None else self.run.config

    def _run(self, message: str) -> RunQueries:
        """The run's queries, or ``InputError(message)`` on a manifold without a run."""
        if self.run is None:
            raise InputError(message)
        return self.run

    @property
    def triangles(self) -> np.ndarray:
        """(T, 3) candidate row ids of the triangles."""
        return self.mesh.triangles

    @property
    def robot(self) -> Any:
        """The run's robot (loaded from the config on first use)."""
        if self._robot is None:
            run = self._run(f"{_NO_CONFIG}: pass robot= and cfg= to the query")
            self._robot = run.load_robot()
        return self._robot

    @property
    def locator(self) -> TriangleLocator:
        """The nearest-point index over the triangles and isolated candidates (built on first use).

        Candidates that no triangle uses (:attr:`~gcm_pipeline.manifold.build.
        Manifold.unused`) are points of the manifold: ``locate`` reports one
        as ``triangle`` -1 with its row in ``vertex``.
        """
        if self._locator is None:
            unused = self.mesh.unused
            self._locator = TriangleLocator(
                self.poses[self.triangles],
                points=self.poses[unused],
                point_ids=unused,
                method=self.method,
                orientation_scale=self.orientation_scale,
            )
        return self._locator

    @property
    def row_mesh(self) -> RowMesh:
        """The rows of the table as a mesh (:func:`~gcm_pipeline.manifold.lattice.row_mesh`)."""
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
            hint = " (-1: an isolated candidate, its pose is Location.dq)" if tri[i] == -1 else ""
            raise GeometryError(
                f"triangle id {int(tri[i])} at {i} is outside 0..{len(self) - 1}{hint}"
            )
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
        :mod:`gcm_pipeline.geometry.pose_metric`); the search is exact up to the
        projection's tolerance (no triangle that could hold a nearer point is
        skipped).

        Args:
            poses: (M, 4, 4) or (M, 8) query poses in the world (one pose: (4, 4) or (8,)).

        A candidate that no triangle uses is a point of the manifold too: at
        its exact pose the answer is that candidate, ``triangle`` -1 and its
        row in ``vertex``.

        Returns:
            :class:`~gcm_pipeline.manifold.locate.Location`: ``triangle``
            (M,), ``weights`` (M, 3), ``distance`` (M,) [m], ``dq`` (M, 8),
            ``vertex`` (M,) (the isolated candidate's row, else -1).

        Raises:
            GeometryError: Query poses not rigid, not finite or of a wrong shape.
        """
        return self.locator.locate(as_query_poses(poses))

    # ------------------------------------------------------------ reachability
    def _checker(self, robot: Any, cfg: Any) -> PoseCheck:
        run = self._run(f"{_NO_CONFIG}: pass cfg= (and robot=)")
        cfg = cfg if cfg is not None else run.config
        robot = robot if robot is not None else self.robot
        key = hash((id(robot), id(cfg)))
        check = self._checks.get(key)
        if check is None or check.robot is not robot or check.config is not cfg:
            check = run.reachability(robot, cfg)
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
        robot: Any = None,
        cfg: Any = None,
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
        answer = Answers(query, nq, self.orientation_scale)
        if m == 0:
            return answer.result(loc.distance)
        # nearest reachable rows of every query (pose metric, both quaternion signs)
        k = min(int(neighbours), rows_ok.size)
        near = np.zeros((m, 0), dtype=np.int64)
        d_near = np.full(m, np.inf)  # distance to the nearest reachable row
        if k > 0:
            feat = pose_features(self.grasps["dq"][rows_ok], self.orientation_scale)
            dist, idx = nearest_of_both_signs(
                feat, pose_features(query, self.orientation_scale), 2 * k
            )
            d_near = np.asarray(dist).reshape(m, 2 * k)[:, 0]
            idx = np.asarray(idx).reshape(m, 2 * k) % rows_ok.size
            near = first_unique(idx, k)
            near = rows_ok[near]
        # 1. the nearest manifold point, warm-started from its vertices and the nearest rows
        own = np.repeat(np.maximum(loc.vertex, 0)[:, None], 3, axis=1)  # an isolated candidate
        on = loc.triangle >= 0
        own[on] = self.triangles[loc.triangle[on]]
        by_weight = np.take_along_axis(own, np.argsort(-loc.weights, axis=1), axis=1)
        seed_rows = np.concatenate((by_weight, near), axis=1)
        res = check(loc.dq, q_table[seed_rows])
        ok = np.asarray(res["reachable"], dtype=bool)
        answer.offer(
            np.flatnonzero(ok),
            loc.dq[ok],
            np.asarray(res["q"])[ok],
            loc.triangle[ok],
            loc.weights[ok],
            loc.vertex[ok],
        )
        # a projection is a local minimum: where a reachable row is nearer than
        # the located point (far from the manifold), step 2 offers the rows too
        todo = np.flatnonzero(~ok | (loc.distance > d_near + 1e-12))
        if todo.size and k > 0:
            search_near_rows(
                self, query, todo, near[todo], q_table, check, bisections, answer.offer
            )
        return answer.result(loc.distance)

    # ------------------------------------------------------------ optimisation
    def metric_values(self, table: GraspTable, metric: str) -> np.ndarray:
        """A ranking metric of the rows of ``table`` (``reachable``, ``q``, ...); NaN: unreachable.

        Scales are the run's: ``combined`` normalises each metric by its range
        over the run's reachable rows (as the run's ``combined`` column does),
        so values of new grasps compare with the run's rows.

        Raises:
            InputError: Unknown metric, or a column the metric needs is missing.
        """
        if metric not in QUERY_METRICS:
            raise choice_error(InputError, "metric", metric, QUERY_METRICS)
        reach = np.asarray(table["reachable"], dtype=bool)
        q = np.where(reach[:, None], np.asarray(table["q"], dtype=np.float64), np.nan)
        if metric in _ROBOT_METRICS:
            robot = self.robot
            run = self._run(f"{_NO_CONFIG}: pass robot= and cfg= to the query")
            return run.robot_metrics(robot, q)[metric]
        if metric in ("clearance", "margin", "score"):
            if metric not in table:
                raise InputError(f"metric {metric!r} needs the {metric!r} column; the run has none")
            return np.where(reach, np.asarray(table[metric], dtype=np.float64), np.nan)
        weights = self._combined_weights()
        values = {name: self.metric_values(table, name) for name in weights}
        ref = self._reference_ranges(tuple(weights))
        return np.where(reach, weighted_sum(values, weights, ref, len(table)), np.nan)

    def _combined_weights(self) -> dict[str, float]:
        w = self._run(f"{_NO_CONFIG}: the combined metric takes the run's weights")
        return {k: float(v) for k, v in w.combined_weights.items() if v > 0}

    def _reference_ranges(self, names: tuple[str, ...]) -> dict[str, tuple[float, float]]:
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
        robot: Any = None,
        cfg: Any = None,
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
        first one at least as good as the best row of the run. A candidate in
        no triangle (an isolated point of the manifold) is a start like any
        row; with nowhere to climb, its result is the row itself (``triangle``
        -1, weights ``(1, 0, 0)``).

        Args:
            metric: One of :data:`QUERY_METRICS` (default: the run's ranking metric).
            region: None (the whole manifold), triangle ids (no isolated
                candidate is in them), or a callable taking poses (M, 8) and
                returning a boolean mask (M,).
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
            metric = self.run.ranking_metric if self.run is not None else "yoshikawa"
        if metric not in QUERY_METRICS:
            raise choice_error(InputError, "metric", metric, QUERY_METRICS)
        check = self._checker(robot, cfg)
        rows_ok, q_table = self._reachable_rows()
        row_values = self.metric_values(self.grasps, metric)
        inside = self._region_mask(region)
        mem_row, mem_tri, mem_w = self._memberships()
        in_region = inside(mem_tri, self.grasps["dq"][mem_row])
        candidates = np.unique(mem_row[in_region])
        candidates = candidates[np.isin(candidates, rows_ok) & np.isfinite(row_values[candidates])]
        if not candidates.size:
            raise InputError(f"no reachable row with a finite {metric!r} in the region")
        order = np.lexsort((candidates, -row_values[candidates]))
        start_rows = candidates[order][: max(1, int(starts))]
        # one search per (start row, triangle around it); an isolated row stays where it is
        sel = np.isin(mem_row, start_rows) & in_region
        s_row, t, w = mem_row[sel], mem_tri[sel], mem_w[sel].copy()
        q_cur, val = q_table[s_row].copy(), row_values[s_row].copy()
        dq_cur = np.asarray(self.grasps["dq"])[s_row].copy()
        move = t >= 0
        if move.any():
            w[move], q_cur[move], val[move], dq_cur[move] = pattern_search(
                self,
                t[move],
                w[move],
                q_cur[move],
                val[move],
                dq_cur[move],
                step=0.5 * self._cell_size(),
                iterations=int(iterations),
                check=check,
                values=lambda res, tri, wt: self._point_values(res, metric, tri, wt),
                inside=inside,
            )
        # best search per start row, then best first
        order = np.lexsort((-val, s_row))
        s_row, t, w, q_cur, val, dq_cur = (a[order] for a in (s_row, t, w, q_cur, val, dq_cur))
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

    def _memberships(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Every (row, triangle, weights) of :func:`row_memberships`, then the isolated ones.

        An isolated candidate (in no triangle) is ``(row, -1, (1, 0, 0))``.
        """
        mem_row, mem_tri, mem_w = row_memberships(self.grasps, self.triangles, self.mesh.n_vertices)
        alone = self.mesh.unused
        return (
            np.concatenate((mem_row, alone)),
            np.concatenate((mem_tri, np.full(len(alone), -1, dtype=np.int64))),
            np.concatenate((mem_w, np.tile([1.0, 0.0, 0.0], (len(alone), 1)))),
        )

    def _point_values(
        self, res: GraspTable, metric: str, tri: np.ndarray, w: np.ndarray
    ) -> np.ndarray:
        """Metric of checked new points; ``margin`` and ``score`` are interpolated from the rows."""
        if metric in ("margin", "score"):
            if metric not in self.grasps:
                raise InputError(f"metric {metric!r} needs the {metric!r} column; the run has none")
            m = interpolate(self.row_mesh, self.grasps[metric], tri, w)
            return np.where(np.asarray(res["reachable"], dtype=bool), m, np.nan)
        for name in ("margin", "score"):  # not computed from a configuration: interpolated
            if metric == "combined" and name in self._combined_weights():
                res = res.with_columns(
                    **{name: interpolate(self.row_mesh, self.grasps[name], tri, w)}
                )
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
        return lambda tri, dq: (tri >= 0) & allowed[np.maximum(tri, 0)]
