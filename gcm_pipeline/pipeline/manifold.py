"""The ``manifold``, ``densify`` and ``continuity`` steps: a config onto the manifold package."""

from __future__ import annotations

import functools
from collections.abc import Callable

import numpy as np

from gcm_pipeline.config.run import Config, takes_config
from gcm_pipeline.errors import ConfigError
from gcm_pipeline.manifold import adaptive, continuity
from gcm_pipeline.manifold import build as manifold_build
from gcm_pipeline.manifold import densify as manifold_densify
from gcm_pipeline.manifold.build import Manifold
from gcm_pipeline.manifold.lattice import row_mesh
from gcm_pipeline.manifold.margin import margin
from gcm_pipeline.pipeline.reach import ReachabilityCheck, robot_from_config
from gcm_pipeline.ranking import rank as ranking
from gcm_pipeline.robot.model import Robot
from gcm_pipeline.table import GraspTable


@takes_config
def build_manifold(grasps: GraspTable, cfg: Config) -> Manifold:
    """The manifold's triangles over the candidates (config section ``manifold``).

    The object pose (if the config has an ``object``) is the frame of the
    cylindrical and spherical charts.

    Args:
        grasps: The candidate table (``dq``).
        cfg: The full config.

    Returns:
        A :class:`gcm_pipeline.manifold.build.Manifold`.
    """
    m = cfg.manifold
    return manifold_build.build_manifold(
        grasps,
        structure=m.structure,
        projection=m.projection,
        triangulator=m.triangulator,
        max_edge_length=m.max_edge_length,
        max_edge_angle_deg=m.max_edge_angle_deg,
        frame=cfg.object.pose.matrix() if cfg.object is not None else None,
        orientation_scale=m.orientation_scale,
    )


@takes_config
def densify(grasps: GraspTable, manifold: Manifold, cfg: Config) -> GraspTable:
    """Densify the manifold's triangles (config section ``densify``).

    Args:
        grasps: The candidate table; the manifold's triangles index its rows.
        manifold: From :func:`build_manifold`.
        cfg: The full config.

    Returns:
        All candidates (first, in input order) and the interpolated grasps,
        with ``dq, origin, triangle, vertices, weights``.
    """
    d = cfg.densify
    return manifold_densify.densify(
        grasps,
        manifold,
        subdivisions=d.subdivisions,
        spacing=d.spacing,
        method=d.method,
        max_poses=d.max_poses,
    )


@takes_config
def refinement_score(robot: Robot, cfg: Config) -> Callable[[GraspTable], np.ndarray]:
    """The metric adaptive refinement follows: the ranking metric of ``cfg``.

    ``combined`` is normalised over the reachable rows checked so far;
    ``margin`` (which needs the finished manifold) falls back to Yoshikawa's
    index.
    """
    r = cfg.ranking
    return functools.partial(
        ranking.reachable_score, robot=robot, metric=r.metric, weights=r.weights
    )


@takes_config
def densify_adaptive(
    grasps: GraspTable,
    manifold: Manifold,
    robot: Robot,
    cfg: Config,
    *,
    check: ReachabilityCheck | None = None,
) -> GraspTable:
    """Densify where reachability or the metric changes, checking as it refines.

    Section ``densify.adaptive`` (see :mod:`gcm_pipeline.manifold.adaptive`);
    reachability is decided as in :func:`check_reachability`, so the result
    has the columns of densify and of the reachability stage, plus ``level``.

    Args:
        grasps: The candidate table; the manifold's triangles index its rows.
        manifold: From :func:`build_manifold`.
        robot: From :func:`robot_from_config`.
        cfg: The full config (``densify.adaptive`` set).
        check: A :class:`ReachabilityCheck` to use (its ``solved`` counts the IK solves).

    Raises:
        ConfigError: No ``densify.adaptive`` section, or the table would grow
            beyond ``densify.max_poses``.
    """
    a = cfg.densify.adaptive
    if a is None:
        raise ConfigError("densify_adaptive needs a densify.adaptive section")
    own = check is None
    check = ReachabilityCheck(robot, cfg) if check is None else check
    try:
        return adaptive.refine(
            grasps,
            manifold,
            check,
            max_level=a.max_level,
            min_level=a.min_level,
            criteria=a.refine,
            score=refinement_score(robot, cfg) if "metric" in a.refine else None,
            metric_threshold=a.metric_threshold,
            method=cfg.densify.method,
            max_poses=cfg.densify.max_poses,
        )
    finally:
        if own:
            check.close()


@takes_config
def adaptive_counts(grasps: GraspTable, manifold: Manifold, cfg: Config) -> dict[str, int]:
    """``counts["adaptive"]`` of a run: IK solves, rows per level, the uniform lattice's size.

    Keys: ``max_level``, ``ik_solves``, ``level_0`` .. ``level_L`` (rows first
    made at each level), ``uniform_subdivisions`` and ``uniform_rows`` (the
    uniform lattice with ``2**max_level`` subdivisions).
    """
    a = cfg.densify.adaptive
    assert a is not None
    levels, per_level = np.unique(np.asarray(grasps["level"]), return_counts=True)
    out = {"max_level": a.max_level, "ik_solves": len(grasps)}
    out.update({f"level_{k}": int(v) for k, v in zip(levels, per_level, strict=True)})
    out["uniform_subdivisions"] = 1 << a.max_level
    out["uniform_rows"] = adaptive.uniform_size(
        manifold.triangles, manifold.n_vertices, a.max_level
    )
    return out


@takes_config
def add_continuity(
    grasps: GraspTable,
    manifold: Manifold,
    cfg: Config,
    *,
    check: ReachabilityCheck | None = None,
) -> tuple[GraspTable, dict[str, int]]:
    """IK continuity and the robustness margin (sections ``continuity``, ``manifold``).

    Adds ``ik_jump`` [rad] and ``patch`` (:mod:`gcm_pipeline.manifold.continuity`)
    and ``margin`` [m] (:mod:`gcm_pipeline.manifold.margin`); with
    ``continuity.reseed`` first re-solves border grasps of smaller patches from
    their neighbours in larger ones (that needs ``check``, or the robot to
    build one).

    Returns:
        The table and ``counts["continuity"]``: ``patches`` and, with
        re-seeding, ``patches_before_reseed``, ``reseeded`` (grasps that took a
        new solution) and ``reseed_ik_solves``.
    """
    c = cfg.continuity
    edges = row_mesh(grasps, manifold.triangles, manifold.n_vertices).edges
    counts: dict[str, int] = {}
    if c.reseed:
        own = check is None
        check = ReachabilityCheck(robot_from_config(cfg), cfg) if check is None else check
        try:
            grasps, report = continuity.reseed(
                grasps, edges, check, threshold=c.threshold, max_rounds=c.max_rounds
            )
        finally:
            if own:
                check.close()
        counts.update(
            patches_before_reseed=report.patches_before,
            reseeded=report.moved,
            reseed_ik_solves=report.solved,
        )
    cols = continuity.continuity_columns(grasps, edges, c.threshold)
    counts = {"patches": int(cols["patch"].max(initial=-1) + 1), **counts}
    cols["margin"] = margin(
        np.asarray(grasps["dq"], dtype=np.float64),
        np.asarray(grasps["reachable"], dtype=bool),
        edges,
        cfg.manifold.orientation_scale,
    )
    return grasps.with_columns(**cols), counts
