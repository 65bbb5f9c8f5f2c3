"""``target: all``: one run per object, each in ``<out>/objects/<name>/``, and their summary.

Each object's run is a complete run directory (``gcm show``, ``plot``,
``query`` read it): the config :func:`~gcm_pipeline.pipeline.objects.target_config`
makes for that object, run by :class:`~gcm_pipeline.pipeline.run.Pipeline`.
The top directory holds the config as given (``config.yaml``) and
``summary.json``: every object's counts and run directory. It is written as
one: a failure in any object's run leaves nothing behind.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from gcm_pipeline.config.run import Config
from gcm_pipeline.errors import ConfigError, GcmError
from gcm_pipeline.pipeline.objects import target_config
from gcm_pipeline.pipeline.preflight import input_files, preflight, warn_sunk_objects
from gcm_pipeline.pipeline.run import Pipeline, RunResult
from gcm_pipeline.robot.model import Robot
from gcm_pipeline.rundir import run as run_files
from gcm_pipeline.rundir import transaction

__all__ = ["OBJECTS_KIND", "ObjectsResult", "run_objects"]

log = logging.getLogger(__name__)

#: The marker kind of the top directory (not a run directory itself).
OBJECTS_KIND = "objects"


@dataclass
class ObjectsResult:
    """The runs of a ``target: all`` config, one per object (in the order of ``objects``).

    Attributes:
        results: Object name -> its run's result (``run_dir`` under the top directory).
        config: The config as given (``objects``, ``target: all``).
        run_dir: The top directory, or None when nothing was written.
        files: The files and folders of the top directory (``config.yaml``,
            ``objects``, ``summary.json``).
    """

    results: dict[str, RunResult]
    config: Config
    run_dir: Path | None = None
    files: list[Path] = field(default_factory=list)

    def summary(self) -> dict[str, Any]:
        """The content of the top ``summary.json``: each object's counts and run directory."""
        objects = {}
        for name, result in self.results.items():
            c = result.counts
            objects[name] = {
                "run_dir": f"objects/{name}",
                "candidates": c["candidates"],
                "densified": c["densified"],
                "reachable": c["reachable"],
                "unreachable_by_reason": c["unreachable_by_reason"],
            }
        return {
            "target": "all",
            "objects": objects,
            "config": self.config.to_dict(),
            "versions": run_files.versions(),
        }


def run_objects(
    cfg: Config,
    out_dir: str | Path | None = None,
    progress: bool = True,
    *,
    force: bool = False,
    source: str | Path | None = None,
    robot: Robot | None = None,
) -> ObjectsResult:
    """Run a config once per object (its ``target: all``, or any ``objects`` config).

    Args:
        cfg: A config with ``objects``.
        out_dir: The top directory (default: ``output.dir``); each object's run
            goes to ``objects/<name>/`` in it.
        progress: Show progress bars.
        force: Replace a previous top directory of this kind (only when all is done).
        source: The config file (never inside a directory being replaced).
        robot: The robot of ``robot.spec``, built before (None: built by :func:`preflight`).

    Returns:
        The runs, in the order of ``objects``.

    Raises:
        GcmError: As :meth:`Pipeline.run`; every object's config and the files
            it reads are checked before any work, and nothing is written on failure.
    """
    configs = {o.name: target_config(cfg, o.name) for o in cfg.objects or ()}
    if not configs:
        raise ConfigError("objects: run_objects needs a config with an 'objects' list")
    out = Path(out_dir) if out_dir is not None else Path(cfg.output.dir)
    keep = [*input_files(cfg).values(), *([Path(source).absolute()] if source else [])]
    if robot is None:
        # the first object's config holds every object (its target and the others as
        # obstacles): one check covers every mesh, and one robot serves every run
        first, *others = configs
        robot = preflight(configs[first], name=first)
        for name in others:  # the table check of each object (its runs skip the preflight)
            warn_sunk_objects(configs[name], name=name)
    results: dict[str, RunResult] = {}
    with transaction.atomic_dir(out, kind=OBJECTS_KIND, force=force, keep=keep) as tmp:
        for name, sub in configs.items():
            log.info("object %s: %d of %d", name, len(results) + 1, len(configs))
            pipeline = Pipeline(sub, source=source)
            try:
                results[name] = pipeline.run(tmp / "objects" / name, progress, robot=robot)
            except GcmError as exc:  # which object's run failed (nothing is written)
                evidence = {k: getattr(exc, k) for k in ("key", "value", "choices", "path", "row")}
                raise type(exc)(f"objects[{name}]: {exc}", **evidence) from exc
        result = ObjectsResult(results, cfg)
        run_files.write_config(cfg.to_dict(), tmp / "config.yaml")
        run_files.write_summary(result.summary(), tmp / "summary.json")
    for name, sub_result in results.items():
        sub_result.run_dir = out / "objects" / name
        sub_result.files = sorted(
            p for p in sub_result.run_dir.iterdir() if p.name != transaction.MARKER
        )
    result.run_dir = out
    result.files = sorted(p for p in out.iterdir() if p.name != transaction.MARKER)
    return result
