"""One execution of a placement study: its rounds, its rows and its consolidated outputs.

:class:`StudyRun` is what :meth:`Study.run <gcm_pipeline.study.study.Study.run>`
does once the study and its directory are checked: it sends the placements of
each round to an executor (:mod:`gcm_pipeline.study.runner`), records every
finished one in the study directory (:mod:`gcm_pipeline.study.store`), re-grids
around each object's best placement (:func:`best_row`) and writes
``placements.csv``, ``reachability.npz``, ``summary.json``, ``coverage.png``,
``best/`` and ``study.html``; :class:`StudyResult` is what it returns.
"""

from __future__ import annotations

import logging
import math
import shlex
import time
from collections.abc import Iterator, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from gcm_pipeline import interrupts
from gcm_pipeline.config.run import Config
from gcm_pipeline.errors import GcmError
from gcm_pipeline.pipeline import Pipeline
from gcm_pipeline.progress import bar as progress_bar
from gcm_pipeline.progress import note
from gcm_pipeline.ranking.metrics import METRIC_COLUMNS
from gcm_pipeline.rundir import run as run_files
from gcm_pipeline.rundir import transaction
from gcm_pipeline.safe_yaml import read_yaml_file
from gcm_pipeline.study import coverage, runner
from gcm_pipeline.study.report import write_study_html
from gcm_pipeline.study.spec import Placement, StudyPlan
from gcm_pipeline.study.store import POSE_COLUMNS, REPORT_ARRAYS, StudyDir

__all__ = ["StudyResult", "StudyRun", "best_row"]

log = logging.getLogger(__name__)

#: Seconds between rewrites of placements.csv / summary.json while a study runs.
_FLUSH_S = 5.0


def best_row(rows: Sequence[Mapping[str, Any]]) -> Mapping[str, Any] | None:
    """The best finished placement: highest coverage, then mean manipulability, then lowest id."""
    ok = [r for r in rows if not r.get("error")]
    if not ok:
        return None

    def key(r: Mapping[str, Any]) -> tuple[float, float, int]:
        m = r.get("mean_manipulability")
        m = float(m) if m is not None and math.isfinite(float(m)) else -math.inf
        return (float(r["coverage"]), m, -int(r["id"]))

    return max(ok, key=key)


@dataclass
class StudyResult:
    """What a study produced.

    Attributes:
        out_dir: The study directory.
        rows: One dict per finished placement (the ``placements.csv`` fields), by id.
        best: The best placement's row (None when every placement failed).
        summary: The content of ``summary.json``.
        complete: Every placement (all rounds) finished.
    """

    out_dir: Path
    rows: list[dict[str, Any]]
    best: dict[str, Any] | None
    summary: dict[str, Any]
    complete: bool = True
    files: list[Path] = field(default_factory=list)

    @property
    def failed(self) -> list[dict[str, Any]]:
        """The rows of the placements that failed."""
        return [r for r in self.rows if r.get("error")]

    def __repr__(self) -> str:
        best = self.best
        text = (
            f"placement {best['id']} ({best['object']}, coverage {best['coverage']:.3f})"
            if best
            else None
        )
        return (
            f"StudyResult(placements={len(self.rows)}, failed={len(self.failed)}, "
            f"best={text!r}, complete={self.complete}, out_dir={str(self.out_dir)!r})"
        )


def _pose_columns(cfg: Config, file_object: list[float] | None) -> dict[str, float]:
    """A placement's pose columns: its object's and its robot base's.

    ``file_object``: ``x, y, z, yaw_deg`` of an object its grasp file names
    (:meth:`StudyPlan.file_object_pose`), else None (the config's ``object.pose``).
    """
    out: dict[str, float] = {}
    poses = {"object": cfg.object.pose if cfg.object is not None else None}
    poses["base"] = cfg.robot.base_pose
    for prefix, pose in poses.items():
        if prefix == "object" and file_object is not None:  # candidates.placement
            keys = ("object_x", "object_y", "object_z", "object_yaw_deg")
            out.update(zip(keys, file_object, strict=True))
            continue
        if pose is None:
            for a in ("x", "y", "z", "yaw_deg"):
                out[f"{prefix}_{a}"] = math.nan
            continue
        for a, v in zip(("x", "y", "z"), pose.xyz, strict=True):
            out[f"{prefix}_{a}"] = float(v)
        if pose.rpy_deg is not None:
            out[f"{prefix}_yaw_deg"] = float(pose.rpy_deg[2])
        else:
            out[f"{prefix}_yaw_deg"] = math.degrees(pose.rpy_rad[2])
    return out


class StudyRun:
    """One execution of a study: the rounds, the outputs, the bookkeeping."""

    def __init__(self, plan: StudyPlan, store: StudyDir, executor: Any, *, progress: bool) -> None:
        self.plan = plan
        self.store = store
        self.executor = executor
        self.progress = progress
        self.rows: dict[int, dict[str, Any]] = {}
        self.placements: list[Placement] = []
        self.resumed = 0
        self.ran = 0
        self.timings: dict[str, float] = {"startup": float(executor.info().get("startup_s", 0.0))}
        self.best: dict[str, Any] | None = None
        self._last_flush = 0.0
        self.bar: Any = None

    # --- jobs --------------------------------------------------------------------------

    def _jobs(self, todo: list[Placement]) -> Iterator[dict[str, Any]]:
        for p in todo:
            interrupts.check()  # an interrupt dropped on the way stops the study here
            row = self._row_base(p)
            try:
                cfg = self.plan.resolve(p.overrides, where=f"placement {p.id}")
            except GcmError as exc:
                row["error"] = f"{type(exc).__name__}: {exc}"
                self._finished(row, {})
                continue
            # swept keys keep the sweep's values; the others come from the config
            placed = self.plan.file_object_pose(self.plan.object_names.index(p.object), cfg)
            row.update({k: v for k, v in _pose_columns(cfg, placed).items() if math.isnan(row[k])})
            self._meta[p.id] = row
            yield {"id": p.id, "config": cfg.to_dict()}

    def _row_base(self, p: Placement) -> dict[str, Any]:
        row: dict[str, Any] = {"id": p.id, "round": p.round, "object": p.object}
        for prefix, pose in (("object", p.object_pose), ("base", p.base_pose)):
            for a in ("x", "y", "z", "yaw_deg"):
                row[f"{prefix}_{a}"] = pose.get(a, math.nan)
        row["overrides"] = list(p.overrides)
        row["error"] = ""
        return row

    def _finished(self, row: dict[str, Any], arrays: Mapping[str, np.ndarray]) -> None:
        self.store.write_part(row, arrays)
        row = dict(row)
        row["arrays"] = dict(arrays)
        self.rows[int(row["id"])] = row
        self.ran += 1
        if self.bar is not None:
            self.bar.update(1)
            best = best_row(list(self.rows.values()))
            if best is not None:
                self.bar.set_postfix_str(f"best {best['coverage']:.3f} (#{best['id']})")
        now = time.perf_counter()
        if now - self._last_flush > _FLUSH_S:
            self._last_flush = now
            self.write_tables(complete=False)

    def _collect(self, result: dict[str, Any]) -> None:
        row = dict(self._meta.pop(int(result["id"])))
        arrays: dict[str, np.ndarray] = {}
        for key in (
            "reachable_mask",
            "metric",
            "manipulability",
            "pose",
            "pose_object",
            *REPORT_ARRAYS,
        ):
            if key in result:
                arrays[key] = np.asarray(result.pop(key))
        if "is_candidate" in result:
            arrays["is_candidate"] = np.asarray(result.pop("is_candidate"), dtype=bool)
        row.update(result)
        self._finished(row, arrays)

    def _round(self, todo: list[Placement]) -> None:
        if not todo:
            return
        self._meta: dict[int, dict[str, Any]] = {}
        t0 = time.perf_counter()
        started = self.timings["startup"]
        for result in self.executor.run(self._jobs(todo)):
            self._collect(result)
        # a deferred executor starts inside run(): its start-up is not placement time
        self.timings["startup"] = float(self.executor.info().get("startup_s", 0.0))
        self.timings["placements"] = self.timings.get("placements", 0.0) + (
            time.perf_counter() - t0 - (self.timings["startup"] - started)
        )

    # --- rounds ------------------------------------------------------------------------

    def execute(self, *, resumed: bool, t_start: float, best_run: bool) -> StudyResult:
        """Run the grid and the refinement rounds (``resumed``: finished placements kept)."""
        done = self.store.load_parts() if resumed else {}
        grid = self.plan.grid()
        self.rows = self._own(grid, done)
        self.resumed = len(self.rows)
        rounds = self.plan.refine_rounds()  # later rounds could add nothing
        self.bar = progress_bar(
            len(grid),
            "study",
            "placement",
            enabled=self.progress,
            initial=sum(1 for p in grid if p.id in self.rows),
            dynamic_ncols=True,
            lines=True,  # off a terminal: a line every few seconds
        )
        try:
            self.placements = list(grid)
            self._round([p for p in grid if p.id not in self.rows])
            for rnd in range(1, rounds + 1):
                best = self._best_per_object()
                if not best:
                    break
                more = self.plan.refined(rnd, best, self.placements)
                self.placements += more
                self.rows.update(self._own(more, done))
                todo = [p for p in more if p.id not in self.rows]
                self.bar.total += len(more)
                self.bar.update(len(more) - len(todo))
                self.bar.refresh()
                self._round(todo)
        finally:
            self.bar.close()
            self.bar = None
        # rows left from an earlier plan cannot exist (same key), but keep only known ids
        known = {p.id for p in self.placements}
        self.rows = {k: v for k, v in self.rows.items() if k in known}
        return self.finish(complete=True, t_start=t_start, best_run=best_run)

    def _own(
        self, placements: list[Placement], done: Mapping[int, dict[str, Any]]
    ) -> dict[int, dict[str, Any]]:
        """The finished rows of ``placements`` in ``done``.

        A part whose object, pose, round or overrides are not its placement's
        (a file from elsewhere, or edited) is ignored with a warning naming the
        file and the first key that differs: that placement runs again, so
        ``best/`` never re-runs overrides the study did not plan.
        """
        own: dict[int, dict[str, Any]] = {}
        for p in placements:
            row = done.get(p.id)
            if row is None:
                continue
            want = self._row_base(p)
            keys = ["object", "round"] + [k for k in POSE_COLUMNS if not math.isnan(want[k])]
            differ = next((f"{k} {row.get(k)!r}" for k in keys if row.get(k) != want[k]), None)
            if differ is None and row.get("overrides") != want["overrides"]:
                differ = _first_override_difference(row.get("overrides"), want["overrides"])
            if differ is not None:
                log.warning(
                    "study: ignoring %s, it is not placement %d (%s): %s; it runs again",
                    self.store.part_path(p.id),
                    p.id,
                    p.label(),
                    differ,
                )
                continue
            own[p.id] = row
        return own

    def _best_per_object(self) -> dict[int, Placement]:
        by_id = {p.id: p for p in self.placements}
        names = self.plan.object_names
        out: dict[int, Placement] = {}
        for k, name in enumerate(names):
            rows = [r for r in self.rows.values() if r["object"] == name and r["id"] in by_id]
            best = best_row(rows)
            if best is not None:
                out[k] = by_id[int(best["id"])]
        return out

    # --- outputs -----------------------------------------------------------------------

    def _sorted_rows(self) -> list[dict[str, Any]]:
        return [self.rows[k] for k in sorted(self.rows)]

    def write_tables(self, *, complete: bool) -> None:
        """Rewrite ``placements.csv`` and ``summary.json`` from the rows so far."""
        rows = self._sorted_rows()
        self.store.write_csv(rows)
        self.store.write_json("summary.json", self.summary(complete=complete))

    def summary(self, *, complete: bool, best_dir: Path | None = None) -> dict[str, Any]:
        """The content of ``summary.json`` (``best_dir``: where ``best/`` was written)."""
        rows = self._sorted_rows()
        best = best_row(rows)
        plan = self.plan
        failed = [r for r in rows if r.get("error")]
        placements_s = self.timings.get("placements", 0.0)
        best_info = None
        if best is not None:
            best_info = {k: v for k, v in best.items() if k != "arrays"}
            best_info["command"] = self._command(best)
            if best_dir is not None:
                best_info["run_dir"] = str(best_dir)
        metric = plan.base_config.ranking.metric
        return {
            "study": plan.to_dict() | {"key": plan.key()},
            "complete": complete,
            "counts": {
                "placements": len(self.placements),
                "finished": len(rows),
                "failed": len(failed),
                "resumed": self.resumed,
                "run": self.ran,
                "rounds": 1 + max((int(r["round"]) for r in rows), default=0),
            },
            "metric": {"name": metric, "column": METRIC_COLUMNS[metric]},
            "best": best_info,
            "best_per_object": {
                name: {"id": r["id"], "coverage": r["coverage"], "reachable": r["reachable"]}
                for name in plan.object_names
                if (r := best_row([x for x in rows if x["object"] == name])) is not None
            },
            "failed": [{"id": r["id"], "error": r["error"]} for r in failed[:20]],
            "engine": self.executor.info(),
            "timings_s": {k: round(v, 3) for k, v in self.timings.items()},
            "placements_per_s": round(self.ran / placements_s, 4) if placements_s > 0 else None,
            "versions": run_files.versions() | runner.ray_version(),
        }

    def _command(self, row: Mapping[str, Any]) -> str:
        """The ``gcm run`` command line that reproduces a placement."""
        plan = self.plan
        base = str(plan.base_path) if plan.base_path else "<base config>"
        args = ["gcm", "run", base]
        for o in row.get("overrides", []):
            args += ["--set", o]
        args += ["--out", str(self.store.path / f"placement_{row['id']}")]
        return shlex.join(args)

    def reachability(self) -> dict[str, np.ndarray]:
        """The arrays of ``reachability.npz`` (placements x grasps, padded)."""
        rows = self._sorted_rows()
        names = self.plan.object_names
        n = np.array([len(r["arrays"].get("reachable_mask", ())) for r in rows], dtype=np.int64)
        g = int(n.max()) if n.size else 0
        p = len(rows)
        reach = np.zeros((p, g), dtype=bool)
        metric = np.full((p, g), np.nan)
        manip = np.full((p, g), np.nan)
        ref_pose = np.full((len(names), g, 7), np.nan)
        ref_cand = np.zeros((len(names), g), dtype=bool)
        ref_n = np.zeros(len(names), dtype=np.int64)
        have_ref = [False] * len(names)
        same = np.zeros(p, dtype=bool)
        for i, r in enumerate(rows):
            a = r["arrays"]
            k = names.index(r["object"]) if r["object"] in names else 0
            m = int(n[i])
            if m == 0:
                continue
            reach[i, :m] = a["reachable_mask"]
            metric[i, :m] = a["metric"]
            manip[i, :m] = a["manipulability"]
            if not have_ref[k]:
                have_ref[k] = True
                ref_pose[k, :m] = a["pose_object"]
                ref_cand[k, :m] = a["is_candidate"]
                ref_n[k] = m
            same[i] = m == ref_n[k] and _same_poses(a["pose_object"], ref_pose[k, :m])
        return {
            "placement_id": np.array([int(r["id"]) for r in rows], dtype=np.int64),
            "object": np.array([str(r["object"]) for r in rows], dtype=str),
            "n_grasps": n,
            "reachable": reach,
            "metric": metric,
            "manipulability": manip,
            "same_grasps": same,
            "objects": np.array(names, dtype=str),
            "grasp_pose_object": ref_pose,
            "is_candidate": ref_cand,
            "metric_name": np.array(self.plan.base_config.ranking.metric),
        }

    def finish(self, *, complete: bool, t_start: float, best_run: bool = False) -> StudyResult:
        """Write the consolidated outputs (and ``best/`` when complete)."""
        rows = self._sorted_rows()
        store = self.store
        files = [store.write_csv(rows)]
        files.append(store.write_npz("reachability.npz", self.reachability()))
        best = best_row(rows)
        files.append(self._coverage(rows, best))
        best_dir = None
        if complete and best_run and best is not None:
            t0 = time.perf_counter()
            best_dir = self._best_run(best)
            self.timings["best_run"] = time.perf_counter() - t0
        self.timings["total"] = time.perf_counter() - t_start
        summary = self.summary(complete=complete, best_dir=best_dir)
        files.append(store.write_json("summary.json", summary))
        if best_dir is not None:
            files.append(best_dir)
        if complete:  # not while an interrupt waits: gcm plot STUDY_DIR writes it later
            try:  # the report is a view of the files above: failing to draw it loses nothing
                files.append(write_study_html(store.path))
            except Exception as exc:
                log.warning("study: study.html not written: %s", " ".join(str(exc).split())[:300])
        clean = [{k: v for k, v in r.items() if k != "arrays"} for r in rows]
        return StudyResult(
            store.path, clean, summary["best"], summary, complete=complete, files=files
        )

    def _coverage(self, rows: list[dict[str, Any]], best: Mapping[str, Any] | None) -> Path:
        sweep = self.plan.spec.sweep
        swept = {
            "object": list(sweep.object_pose.axes()) if sweep.object_pose else [],
            "base": list(sweep.base_pose.axes()) if sweep.base_pose else [],
        }
        title = "coverage: reachable fraction of the densified grasps"
        if best is not None:
            where = ", ".join(
                f"{k.replace('_deg', '').replace('_', ' ')} {best[k]:g}"
                for k in POSE_COLUMNS
                if k.split("_", 1)[1] in swept[k.split("_", 1)[0]]
            )
            title += f"; best #{best['id']}: {best['coverage']:.3f}" + (
                f" at {where}" if where else ""
            )

        def draw(tmp: Path) -> None:
            coverage.write_coverage_png(
                rows, swept, tmp, best_id=int(best["id"]) if best else None, title=title
            )

        return self.store.write_with("coverage.png", draw)

    def _best_run(self, best: Mapping[str, Any]) -> Path:
        """``best/``: ``gcm run`` of the best placement (kept when it is already there)."""
        out = self.store.path / "best"
        cfg = self.plan.resolve(best["overrides"], where=f"placement {best['id']}")
        if transaction.looks_like_run_dir(out) and (out / "config.yaml").is_file():
            try:  # bounded (1 MiB, as any config), never a pipe: else write best/ again
                old = read_yaml_file(out / "config.yaml", "config", GcmError)
            except GcmError:
                old = None
            if old == run_files.json_clean(cfg.to_dict()):
                return out
        note(f"study: writing best/, the run of placement #{best['id']}", enabled=self.progress)
        Pipeline(cfg, source=self.plan.base_path).run(out, progress=self.progress, force=True)
        return out


def _first_override_difference(got: Any, want: Sequence[str]) -> str:
    """``overrides: KEY is 'KEY=A', the plan's 'KEY=B'`` for the first override that differs."""
    got = list(got) if isinstance(got, (list, tuple)) else []
    for k in range(max(len(got), len(want))):
        a = got[k] if k < len(got) else None
        b = want[k] if k < len(want) else None
        if a != b:
            key = str(a if a is not None else b).split("=", 1)[0]
            return f"overrides: {key} is {a!r}, the plan's {b!r}"
    return "overrides differ"


def _same_poses(a: np.ndarray, b: np.ndarray, tol: float = 1e-9) -> bool:
    """Whether two (G, 7) pose arrays are the same grasps (positions and rotations)."""
    if a.shape != b.shape:
        return False
    pos = np.abs(a[:, :3] - b[:, :3]).max(initial=0.0)
    dot = np.abs(np.sum(a[:, 3:] * b[:, 3:], axis=1))
    return bool(pos <= tol and (1.0 - dot).max(initial=0.0) <= tol)
