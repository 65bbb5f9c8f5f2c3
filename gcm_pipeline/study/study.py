"""Placement studies: many runs of one base config over object poses, base poses and objects.

:class:`Study` reads a study file (:mod:`gcm_pipeline.study.spec`), checks it
and its output directory before any work, runs the placements on Ray
(:mod:`gcm_pipeline.study.runner`) and writes the study directory
(:mod:`gcm_pipeline.study.store`) as placements finish
(:class:`~gcm_pipeline.study.execution.StudyRun`):

1. round 0, the grid: every combination of the swept values, inside the region;
2. with ``refine``, each round re-grids the ranges around each object's best
   placement so far;
3. the consolidated outputs (``placements.csv``, ``reachability.npz``,
   ``summary.json``, ``coverage.png``) and ``best/``, the full run directory of
   the best placement (``gcm run`` with its overrides: ``scene.html`` and all).

The best placement has the highest coverage (reachable fraction of the
densified grasps), then the highest mean manipulability, then the lowest id.
A rerun on the same directory resumes: finished placements (failed ones
included) are read back, not recomputed.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Iterable, Iterator, Mapping
from pathlib import Path
from typing import Any, Literal

from gcm_pipeline import interrupts
from gcm_pipeline.bounds import MAX_STUDY_PLACEMENTS
from gcm_pipeline.errors import ConfigError, InputError
from gcm_pipeline.pipeline import input_files, preflight
from gcm_pipeline.study import runner
from gcm_pipeline.study.execution import StudyResult, StudyRun
from gcm_pipeline.study.spec import Placement, StudyPlan, load_study
from gcm_pipeline.study.store import StudyDir

__all__ = ["Study"]


class Study:
    """A placement study (see the module docstring).

    Example:
        >>> study = Study.from_yaml("configs/studies/bottle_placement.yaml")
        >>> result = study.run("results/bottle_placement", workers=2)  # doctest: +SKIP
        >>> result.best["coverage"]  # doctest: +SKIP

    Args:
        plan: The validated study (:func:`~gcm_pipeline.study.spec.load_study`).
    """

    def __init__(self, plan: StudyPlan) -> None:
        self.plan = plan

    @classmethod
    def from_yaml(cls, path: str | Path) -> Study:
        """Read a study file.

        Raises:
            ConfigError: One line naming the file, key and problem.
        """
        return cls(load_study(path))

    @classmethod
    def from_dict(cls, data: Mapping[str, Any]) -> Study:
        """A study from a mapping (relative paths against the working directory)."""
        return cls(load_study(dict(data)))

    def __repr__(self) -> str:
        spec = self.plan.spec
        base = self.plan.base_path or "inline"
        return (
            f"Study(base={str(base)!r}, objects={self.plan.object_names}, "
            f"grid={self.plan.count()}, refine={spec.refine!r})"
        )

    def placements(self) -> list[Placement]:
        """The grid's placements (round 0)."""
        return self.plan.grid()

    def size(self) -> tuple[int, int]:
        """(grid placements, at most this many more from refinement), counted, not built."""
        return self.plan.count(), self.plan.refine_rounds() * self.plan.refine_size()

    def check(self, out_dir: str | Path, *, force: bool = False) -> bool:
        """Check the study and its directory before any work; True when it resumes.

        Checks the size limits (``max_placements``, or ``force``; at most
        :data:`~gcm_pipeline.bounds.MAX_STUDY_PLACEMENTS` in any case), ``gcm run``'s
        preflight on the first placement (robot, meshes, files), that the first
        placement of every other object resolves and its files exist (a damaged
        file fails that object's placements, recorded, as reading files is a
        placement's work: a list of thousands of objects does not wait for all
        of them to load), and that ``out_dir`` is empty, new or holds this very
        study.

        Raises:
            ConfigError: The study is too large (without ``force``), or a placement
                config is invalid.
            OutputError: ``out_dir`` cannot hold this study.
        """
        keep = self.check_inputs(force=force)
        return StudyDir(out_dir).check(self.plan.key(), keep=keep)

    def check_inputs(self, *, force: bool = False) -> list[Path]:
        """The checks of :meth:`check` but the output directory's (``gcm validate``).

        Returns:
            The input files (the study file, the base config, the files each
            object reads): the study directory must not hold them.

        Raises:
            ConfigError: The study is too large (without ``force``), or a placement
                config is invalid.
            InputError: An input file is missing or unreadable.
        """
        grid, extra = self.size()
        limit = self.plan.spec.max_placements
        more = f" + up to {extra:,} from refinement" if extra else ""
        if grid + extra > MAX_STUDY_PLACEMENTS:
            raise ConfigError(
                f"study has {grid:,} placements{more}; one study holds at most "
                f"{MAX_STUDY_PLACEMENTS:,} (split it into several studies)"
            )
        if grid + extra > limit and not force:
            raise ConfigError(
                f"study has {grid:,} placements{more}, more than max_placements {limit:,}; "
                "pass --force (CLI) or force=True to run it, or raise max_placements in the "
                "study file"
            )
        grid_placements = self.placements()
        keep: list[Path] = [p for p in (self.plan.source, self.plan.base_path) if p]
        seen: set[str] = set()
        for p in grid_placements:
            if p.object in seen:
                continue
            where = f"placement {p.id} ({p.label()})"
            cfg = self.plan.resolve(p.overrides, where=where)
            if not seen:  # gcm run's preflight once: the robot, meshes, files
                preflight(cfg)
            else:  # every other object: its files exist (reading them is its placements' work)
                for key, path in input_files(cfg).items():
                    if not path.is_file():
                        raise InputError(f"{where}: {key}: file not found: {path}")
            seen.add(p.object)
            keep += list(input_files(cfg).values())
        return keep

    def run(
        self,
        out_dir: str | Path,
        *,
        workers: int | None = None,
        address: str | None = None,
        force: bool = False,
        progress: bool = True,
        engine: Literal["ray", "inline"] = "ray",
        best_run: bool = True,
    ) -> StudyResult:
        """Run the study into ``out_dir`` (resuming a previous run of the same study).

        Args:
            out_dir: The study directory.
            workers: Ray workers (one CPU each); None: every CPU of this
                machine, or of the cluster with ``address``.
            address: An existing Ray cluster to join (``HOST:PORT``,
                ``ray://HOST:PORT`` or ``auto``); None starts Ray here.
            force: Run a study larger than its ``max_placements``.
            progress: Show a progress bar over the placements (off a terminal: a line
                every few seconds, and one each when Ray starts and is ready).
            engine: ``ray``, or ``inline`` (this process, one placement after
                the other: the reference for Ray's overhead).
            best_run: Write ``best/``, the full run directory of the best placement.

        Returns:
            The :class:`StudyResult`.

        Raises:
            GcmError: A user error, raised before anything is written: invalid
                study, too large without ``force``, unusable ``out_dir``, Ray
                unreachable (:class:`~gcm_pipeline.study.runner.EngineError`).
            KeyboardInterrupt: Ctrl-C (``gcm study`` also turns SIGTERM and SIGHUP
                into one): workers are stopped, finished placements stay in
                ``out_dir`` and a rerun resumes.
        """
        t_start = time.perf_counter()
        if engine not in ("ray", "inline"):
            raise ConfigError(f"engine must be 'ray' or 'inline', got {engine!r}")
        if engine == "ray" and address is None:
            runner.check_local_workers(
                workers
            )  # also when Ray will not start (nothing left to run)
        elif engine == "ray" and address is not None:
            runner.probe_address(address)  # seconds, before the preflight and before Ray retries
        self.check(out_dir, force=force)
        store = StudyDir(out_dir)
        # one study at a time in a directory; what it holds is read again under the lock
        with store.lock():
            resumed = store.holds(self.plan.key())
            return self._run_locked(
                store, resumed, t_start, workers, address, engine, progress, best_run
            )

    def _run_locked(
        self,
        store: StudyDir,
        resumed: bool,
        t_start: float,
        workers: int | None,
        address: str | None,
        engine: str,
        progress: bool,
        best_run: bool,
    ) -> StudyResult:
        plan = self.plan
        warm = plan.base_config.to_dict()
        if engine == "inline":
            executor: Any = runner.InlineExecutor(warm)
        elif resumed and self._grid_done(store):
            # a resumed study whose grid is finished may have nothing left to run:
            # Ray starts only if a refinement round still has placements to run
            executor = _Deferred(
                lambda: runner.RayExecutor(workers, address, warm, progress=progress)
            )
        else:
            executor = runner.RayExecutor(workers, address, warm, progress=progress)
        run = StudyRun(self.plan, store, executor, progress=progress)
        try:
            store.create({"key": plan.key(), "created": time.time(), **plan.to_dict()})
            result = run.execute(resumed=resumed, t_start=t_start, best_run=best_run)
        except BaseException as exc:
            if interrupts.interrupt_cause(exc) is not None:  # also one a library wrapped
                executor.close()
                run.finish(complete=False, t_start=t_start)
            raise
        finally:
            executor.close()
        return result

    def _grid_done(self, store: StudyDir) -> bool:
        """Whether every placement of the grid (round 0) is finished in ``store``."""
        done = store.finished_ids()
        return all(p.id in done for p in self.plan.grid())


class _Deferred:
    """An executor built on its first :meth:`run` (nothing to run: never built)."""

    def __init__(self, make: Callable[[], Any]) -> None:
        self._make = make
        self._real: Any = None

    def run(self, jobs: Iterable[dict[str, Any]]) -> Iterator[dict[str, Any]]:
        """Build the executor if needed and run the jobs on it."""
        if self._real is None:
            self._real = self._make()
        return self._real.run(jobs)

    def info(self) -> dict[str, Any]:
        """The executor's info, or that it was not started."""
        if self._real is not None:
            return self._real.info()
        return {
            "name": "ray",
            "mode": "not started: nothing left to run",
            "workers": 0,
            "nodes": 0,
            "startup_s": 0.0,
        }

    def close(self) -> None:
        """Close the executor if it was built."""
        if self._real is not None:
            self._real.close()
