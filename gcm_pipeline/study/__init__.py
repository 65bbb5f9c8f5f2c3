"""Placement studies: sweep object poses, robot base poses and objects, on Ray.

``gcm study STUDY.yaml --out DIR`` and :class:`Study` run many placements of
one base config (each one the base plus ``--set`` style overrides, the same
answer as ``gcm run`` with those overrides) on Ray actors and write a study
directory: ``placements.csv``, ``reachability.npz``, ``summary.json``,
``coverage.png``, ``best/`` and ``study.html`` (:mod:`~gcm_pipeline.study.report`).
See :mod:`gcm_pipeline.study.study` for the sequence,
:mod:`~gcm_pipeline.study.execution` for one run of it,
:mod:`~gcm_pipeline.study.spec` for the study file,
:mod:`~gcm_pipeline.study.store` for the directory and
:mod:`~gcm_pipeline.study.runner` for Ray. Ray is imported only when a study
runs.
"""

from gcm_pipeline.study.execution import StudyResult
from gcm_pipeline.study.runner import EngineError
from gcm_pipeline.study.spec import Placement, StudyPlan, load_study
from gcm_pipeline.study.study import Study

__all__ = ["EngineError", "Placement", "Study", "StudyPlan", "StudyResult", "load_study"]
