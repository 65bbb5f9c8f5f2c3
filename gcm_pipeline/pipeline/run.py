"""The one list of steps (:data:`STEPS`), the :class:`Pipeline` that runs them, its result."""

from __future__ import annotations

import functools
import logging
import time
from collections.abc import Callable, Iterable, Iterator, Mapping
from contextlib import AbstractContextManager, contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from gcm_pipeline.config.objects import TARGET_ALL
from gcm_pipeline.config.run import Config, load_config
from gcm_pipeline.errors import ConfigError
from gcm_pipeline.geometry.clouds import PointCloud
from gcm_pipeline.manifold.build import Manifold
from gcm_pipeline.manifold.query import GraspManifold
from gcm_pipeline.outputs.scene_glyphs import legend
from gcm_pipeline.pipeline.clouds import cloud_summary, scene_clouds
from gcm_pipeline.pipeline.file_object import place_file_object
from gcm_pipeline.pipeline.manifold import (
    adaptive_counts,
    add_continuity,
    build_manifold,
    densify,
    densify_adaptive,
)
from gcm_pipeline.pipeline.objects import target_config
from gcm_pipeline.pipeline.outputs import publish, top_grasps
from gcm_pipeline.pipeline.preflight import input_files, preflight
from gcm_pipeline.pipeline.queries import grasp_manifold
from gcm_pipeline.pipeline.ranking import rank, select_branches
from gcm_pipeline.pipeline.reach import ReachabilityCheck, check_reachability
from gcm_pipeline.pipeline.sources import generate_candidates
from gcm_pipeline.progress import bar as progress_bar
from gcm_pipeline.robot.model import Robot
from gcm_pipeline.rundir import run as run_files
from gcm_pipeline.rundir import transaction
from gcm_pipeline.rundir.clouds import CLOUD_FILE, write_clouds
from gcm_pipeline.table import GraspTable

log = logging.getLogger(__name__)


@dataclass
class RunResult:
    """What a pipeline run produced.

    Attributes:
        grasps: The final grasp table (candidates first, then interpolated;
            with reachability and ranking columns).
        manifold: The manifold (triangles over candidate row ids).
        robot: The robot model used.
        counts: ``candidates, triangles, triangles_dropped, dropped_by_reason``
            (dict), ``densified, interpolated, reachable, unreachable_by_reason``
            (dict: reason -> count).
        timings: Seconds per stage, in run order.
        config: The resolved config.
        run_dir: The run directory, or None when nothing was written.
        grasp_manifold: The manifold as a queryable
            :class:`~gcm_pipeline.manifold.query.GraspManifold` (built on first use).
        grasp_frame: How a grasp file's gripper frame was mapped onto the
            robot's grasp frame (``format``, ``gripper``, ``chosen_by``,
            ``file_gripper``, ``describe``), None for other sources.
        selection: What ``candidates.success_only``, ``min_score`` and ``limit``
            kept of a grasp file (:class:`gcm_pipeline.sources.files.select.Selection`),
            None when the run kept every grasp of the file and set neither of the others.
        clouds: The processed ``environment.point_clouds`` (world frame, voxelised;
            written to ``cloud.npz``).
    """

    grasps: GraspTable
    manifold: Manifold
    robot: Robot
    counts: dict[str, Any]
    timings: dict[str, float]
    config: Config
    run_dir: Path | None = None
    files: list[Path] = field(default_factory=list)
    grasp_frame: dict[str, Any] | None = None
    selection: dict[str, Any] | None = None
    clouds: list[PointCloud] = field(default_factory=list)

    @functools.cached_property
    def grasp_manifold(self) -> GraspManifold:
        """The run's manifold as a queryable object (sample, locate, nearest reachable, best).

        See :class:`gcm_pipeline.manifold.query.GraspManifold`; the same as
        :func:`gcm_pipeline.load_manifold` on the run directory.
        """
        return grasp_manifold(self.manifold, self.grasps, self.config, self.robot)

    def top(self, n: int | None = None) -> list[dict[str, Any]]:
        """The best-ranked grasps (default: ``ranking.top_k`` of them)."""
        r = self.config.ranking
        return top_grasps(self.grasps, r.top_k if n is None else n, r.metric)

    def summary(self) -> dict[str, Any]:
        """The content of ``summary.json``.

        ``legend`` is the colour scale of the scene and the plots: the
        colormap, the manipulability range it spans and the colour and count
        of every unreachable reason.
        """
        return {
            "counts": dict(self.counts),
            "timings_s": {k: round(v, 6) for k, v in self.timings.items()},
            "ranking": {"metric": self.config.ranking.metric, "top": self.top()},
            **({"grasp_frame": self.grasp_frame} if self.grasp_frame else {}),
            **({"selection": self.selection} if self.selection else {}),
            **({"point_clouds": cloud_summary(self.clouds)} if self.clouds else {}),
            "legend": legend(self.grasps),
            "config": self.config.to_dict(),
            "versions": run_files.versions(),
        }

    def __repr__(self) -> str:
        c = self.counts
        total = sum(self.timings.values())
        return (
            f"RunResult(candidates={c.get('candidates')}, triangles={c.get('triangles')} "
            f"(+{c.get('triangles_dropped')} dropped), densified={c.get('densified')}, "
            f"reachable={c.get('reachable')}, metric={self.config.ranking.metric!r}, "
            f"time={total:.2f}s, run_dir={str(self.run_dir) if self.run_dir else None!r})"
        )


#: The steps of a run, in order (the progress bar, the timings and the order of
#: :meth:`Pipeline.run` all follow this one list; the last two write the run directory).
STEPS = (
    "candidates",
    "manifold",
    "densify",
    "robot",
    "reachability",
    "continuity",
    "ranking",
    "write",
    "publish",
)
WRITE_STEPS = ("write", "publish")


class Pipeline:
    """Runs every stage of a config in order.

    Example:
        >>> result = Pipeline.from_yaml("configs/bottle_side.yaml").run("results/bottle")
        >>> result.counts["reachable"]  # doctest: +SKIP

    Args:
        config: The validated config.
    """

    def __init__(self, config: Config, *, source: str | Path | None = None) -> None:
        if not isinstance(config, Config):
            raise TypeError(f"Pipeline needs a Config, got {type(config).__name__}")
        self.config = config
        #: The config file (from :meth:`from_yaml`); a run never replaces its folder.
        self.source = Path(source).absolute() if source is not None else None

    @classmethod
    def from_yaml(cls, path: str | Path, overrides: Iterable[str] | str = ()) -> Pipeline:
        """Load a YAML config with ``key=value`` overrides (or one as a string); see load_config."""
        over = (overrides,) if isinstance(overrides, str) else tuple(overrides)
        return cls(load_config(path, over), source=path)

    @classmethod
    def from_dict(cls, data: Mapping[str, Any]) -> Pipeline:
        """Validate a plain dict into a config, see :meth:`Config.from_dict`."""
        return cls(Config.from_dict(dict(data)))

    def __repr__(self) -> str:
        c = self.config
        return (
            f"Pipeline(source={c.candidates.source!r}, robot={c.robot.spec!r}, "
            f"projection={c.manifold.projection!r}, ik={c.ik.backend!r}, "
            f"metric={c.ranking.metric!r}, out={str(c.output.dir)!r})"
        )

    def run(
        self,
        out_dir: str | Path | None = None,
        progress: bool = True,
        *,
        force: bool = False,
        write: bool = True,
        viewer: bool = False,
        robot: Robot | None = None,
    ) -> RunResult:
        """Run every stage and write the run directory.

        Args:
            out_dir: The run directory (default: ``output.dir``, relative to
                the working directory).
            progress: Show progress bars on the slow stages.
            force: Replace an existing previous run directory (one with
                ``summary.json`` and ``grasps.csv``; only at the end, when the
                new one is complete). Other non-empty directories, the working
                directory, its parents and the config's folder are never
                replaced; an empty directory is used without ``force``.
            write: Write the run directory (False: only return the result).
            viewer: The caller opens the live viewer afterwards (``gcm run
                --meshcat``): a ``publish.zmq_url`` server is probed first.
            robot: The robot of ``robot.spec``, built before by the caller, who
                also did the :func:`preflight`: a placement study runs many
                configs on one robot and its caches (seed library, geometry).
                None: :func:`preflight` checks the config and builds it.

        Returns:
            The result; ``run_dir`` is the directory written (or None).

        Raises:
            GcmError: A user error (config, input, output path, robot spec);
                checked before any work where possible. Nothing is left
                behind on failure.
        """
        if self.config.target == TARGET_ALL:
            raise ConfigError(
                "target: 'all' analyses each object in its own run directory: run it with "
                "gcm run, or gcm_pipeline.pipeline.run_objects(...)",
                key="target",
            )
        # the target of 'objects' and the object a grasp file names, stood on the table
        # (before anything reads cfg.object)
        cfg = self.config = place_file_object(target_config(self.config))
        out = Path(out_dir) if out_dir is not None else Path(cfg.output.dir)
        keep = self._inputs()
        # what the config refers to first: a bad robot spec is not hidden behind "--force"
        t0 = time.perf_counter()
        if robot is None:
            robot = preflight(cfg, viewer=viewer)  # builds the robot: the "robot" stage's work
        robot_s = time.perf_counter() - t0
        if write:
            out = transaction.check_output_dir(out, force=force, keep=keep)
        timings: dict[str, float] = {}
        names = [n for n in STEPS if write or n not in WRITE_STEPS]
        expected = iter(names)
        # one bar over the stages (the slow ones, IK and publishing, take seconds);
        # when stderr is not a terminal, a line naming the running stage every few seconds
        bar = progress_bar(
            len(names), "gcm", "stage", enabled=progress, leave=False, lines=True, stages=True
        )

        @contextmanager
        def stage(name: str) -> Iterator[None]:
            # the steps run in the order of STEPS, each once: the one list
            step = next(expected, None)
            if step != name:
                raise RuntimeError(f"pipeline step {name!r} runs where STEPS has {step!r}")
            t0 = time.perf_counter()
            log.debug("stage %s ...", name)
            bar.set_postfix_str(name)
            yield
            timings[name] = time.perf_counter() - t0
            bar.update(1)
            log.info("stage %-12s %8.3f s", name, timings[name])

        try:
            return self._run(
                out, stage, timings, robot, robot_s, force=force, write=write, progress=progress
            )
        finally:
            bar.close()

    def _inputs(self) -> list[Path]:
        """The config file and the files it reads: a run never replaces their folder."""
        files = list(input_files(self.config).values())
        return files if self.source is None else [self.source, *files]

    def _run(
        self,
        out: Path,
        stage: Callable[[str], AbstractContextManager[None]],
        timings: dict[str, float],
        robot: Robot,
        robot_s: float,
        *,
        force: bool,
        write: bool,
        progress: bool,
    ) -> RunResult:
        cfg = self.config
        source: dict[str, Any] = {}
        with stage("candidates"):
            candidates = generate_candidates(cfg, report=source)
        with stage("manifold"):
            manifold = build_manifold(candidates, cfg)
        adaptive = cfg.densify.adaptive is not None
        check: ReachabilityCheck | None = None
        with stage("densify"):
            if not adaptive:  # adaptive densification solves as it refines, below
                grasps = densify(candidates, manifold, cfg)
        with stage("robot"):
            pass  # built by preflight
        timings["robot"] = robot_s
        try:
            with stage("reachability"):
                if adaptive:
                    check = ReachabilityCheck(robot, cfg)
                    grasps = densify_adaptive(candidates, manifold, robot, cfg, check=check)
                else:
                    grasps = check_reachability(grasps, robot, cfg, progress=progress)
                grasps = select_branches(grasps, manifold, robot, cfg)
            unreachable = _count_by(grasps["reason"][~np.asarray(grasps["reachable"], dtype=bool)])
            log.info(
                "reachable %d/%d%s",
                len(grasps) - sum(unreachable.values()),
                len(grasps),
                " (unreachable: " + ", ".join(f"{k} {v}" for k, v in unreachable.items()) + ")"
                if unreachable
                else "",
            )
            with stage("continuity"):
                if cfg.continuity.reseed and check is None:
                    check = ReachabilityCheck(robot, cfg)
                grasps, continuity = add_continuity(grasps, manifold, cfg, check=check)
        finally:
            if check is not None:
                check.close()
        with stage("ranking"):
            grasps = rank(grasps, robot, cfg)
        counts = {
            "candidates": len(candidates),
            "triangles": int(len(manifold.triangles)),
            "triangles_dropped": int(len(manifold.dropped)),
            "dropped_by_reason": _count_by(manifold.dropped_reason),
            "densified": len(grasps),
            "interpolated": len(grasps) - len(candidates),
            "reachable": int(np.count_nonzero(grasps["reachable"])),
            "unreachable_by_reason": unreachable,
        }
        if manifold.isolation is not None:  # the families structure: how many, why isolated
            counts["families"] = int(manifold.family.max(initial=-1) + 1)
            counts["isolated_by_reason"] = manifold.isolated_counts
            log.info(
                "manifold: %d families, bounds %.4g m / %.4g deg, isolated: %s",
                counts["families"],
                manifold.max_edge_length,
                manifold.max_edge_angle_deg,
                counts["isolated_by_reason"] or "none",
            )
        _warn_empty(counts, cfg)
        if adaptive:
            counts["adaptive"] = adaptive_counts(grasps, manifold, cfg)
        counts["continuity"] = continuity
        result = RunResult(grasps, manifold, robot, counts, timings, cfg)
        result.grasp_frame = source.get("grasp_frame")
        result.selection = source.get("selection")
        result.clouds = scene_clouds(cfg.environment, cfg.object, cfg.candidates.camera_pose)
        if not write:
            return result
        with transaction.atomic_run_dir(out, force=force, keep=self._inputs()) as tmp:
            with stage("write"):
                run_files.write_run_files(tmp, grasps, manifold, cfg.to_dict())
                if result.clouds:
                    write_clouds(result.clouds, tmp / CLOUD_FILE)
            with stage("publish"):
                published = publish(result, cfg, tmp)
            run_files.write_summary(result.summary(), tmp / "summary.json")
        result.run_dir = out
        result.files = sorted(p for p in out.iterdir() if p.name != transaction.MARKER)
        log.info("run directory %s (%d published files)", out, len(published))
        return result


def _warn_empty(counts: Mapping[str, Any], cfg: Config) -> None:
    """Warn about a run that produced nothing to look at (no triangle, no reachable grasp)."""
    if counts["triangles"] == 0:
        dropped = counts["dropped_by_reason"]
        why = ", ".join(f"{k} {v}" for k, v in dropped.items())
        other = (
            "manifold.structure: families"
            if cfg.manifold.structure == "chart"
            else "unsetting them (bounds from the data)"
        )
        log.warning(
            "no triangle is left%s, so no grasp was interpolated; raise "
            "manifold.max_edge_length / manifold.max_edge_angle_deg or try %s",
            f" (dropped: {why})" if why else "",
            other,
        )
    if counts["reachable"] == 0 and counts["densified"]:
        log.warning("%s", unreachable_hint(counts["unreachable_by_reason"]))


#: What to try when most grasps fail for a reason (see :func:`unreachable_hint`).
_HINTS = {
    "out_of_reach": "the grasps lie beyond the arm's reach: move the object (object.pose) "
    "or the robot (robot.base_pose) closer, and check that a grasp file's positions are in "
    "metres (not millimetres)",
    "no_ik": "no IK solution: these grasp orientations may be impossible for this arm here; "
    "try another robot.base_pose or grasps approached from other sides",
    "joint_limits": "the solutions leave the joint limits: check the robot spec's joint_limits "
    "and limit_margin",
    "collision_object": "the robot hits the object at the grasp: is the grasp frame the "
    "robot's TCP? An arm without a hand needs a tool in its robot spec (see ur5.yaml), or map "
    "the grasps onto its grasp frame with candidates.grasp_to_tool; "
    "environment.contact_tolerance sets how deep the gripper may touch",
    "collision_environment": "the arm hits the table or an obstacle: check "
    "environment.table.height and the object's pose",
    "collision_self": "every solution collides with the arm itself: try grasps approached "
    "from other sides or another robot.base_pose",
    "approach": "the pre-grasp approach fails: shorten approach.distance or turn it off "
    "(approach: null)",
    "retreat": "the post-grasp retreat fails: shorten retreat.distance or turn it off "
    "(retreat: null)",
}


def unreachable_hint(unreachable: Mapping[str, int]) -> str:
    """Why no grasp is reachable and what to try, in one line.

    Args:
        unreachable: Unreachable grasps by reason, most frequent first (the
            run's ``counts["unreachable_by_reason"]``).

    Returns:
        ``"no grasp is reachable (r1 n1, r2 n2, ...); try: ..."``: every
        reason with its count, and what to try for the two most frequent.
    """
    reasons = ", ".join(f"{k} {v}" for k, v in unreachable.items()) or "no reason recorded"
    tips = [_HINTS[k] for k in list(unreachable)[:2] if k in _HINTS]
    tip = "; ".join(tips) or "check robot.base_pose, the object pose and the environment"
    return f"no grasp is reachable ({reasons}); try: {tip}"


def _count_by(labels: Any) -> dict[str, int]:
    """How often each label occurs, most frequent first (ties by name)."""
    names, n = np.unique(np.asarray(labels, dtype=str).reshape(-1), return_counts=True)
    pairs = sorted(zip(names.tolist(), n.tolist(), strict=True), key=lambda p: (-p[1], p[0]))
    return {str(k): int(v) for k, v in pairs}
