"""The pipeline: candidates -> manifold -> densify -> reachability -> ranking -> publish.

Each step is usable alone with the full :class:`~gcm_pipeline.config.Config`;
these functions map the config sections onto the arguments of the packages
below (one module per group of steps: ``sources``, ``manifold``, ``reach``,
``ranking``, ``outputs``; ``preflight`` checks a config before any work,
``queries`` makes a run's manifold queryable, ``run`` holds :data:`STEPS`,
:class:`Pipeline` and :class:`RunResult`):

======================================== =====================================
function                                 reads / adds
======================================== =====================================
:func:`generate_candidates` ``(cfg)``    ``candidates``, ``object``, ``seed``
                                         -> table with ``dq``
:func:`build_manifold` ``(grasps, cfg)`` ``manifold`` (+ object pose as the
                                         chart frame) -> ``Manifold``
:func:`densify` ``(grasps, manifold,     ``densify`` -> table with ``origin``,
cfg)``                                   ``triangle``, ``vertices``, ``weights``
:func:`robot_from_config` ``(cfg)``      ``robot.spec`` -> ``Robot``
:func:`check_reachability` ``(grasps,    ``ik``, ``robot.base_pose``,
robot, cfg)``                            ``environment``, ``approach``, ``retreat``,
                                         ``object`` -> ``reachable, reason, q, ...``
:func:`rank` ``(grasps, robot, cfg)``    ``ranking`` -> ``manipulability``, ``rank``
:func:`publish` ``(result, cfg,          ``publish`` -> ``scene.html``, ``*.png``
out_dir)``
======================================== =====================================

``densify`` takes the candidate table as well as the manifold: the manifold
holds row ids into the candidate table, not poses, so that the poses live in
one place (the table's ``dq`` column) only.

:class:`Pipeline` runs them in order, times them, writes the run directory
atomically (:mod:`gcm_pipeline.rundir`) and returns a :class:`RunResult`. Before
any stage runs, the output directory is checked and :func:`preflight` (also
behind ``gcm validate``) checks what the config refers to: the robot spec,
every input file (named by its config key) and, with the live viewer on, the
meshcat server at ``publish.zmq_url``.
"""

from __future__ import annotations

from gcm_pipeline.pipeline.file_object import place_file_object
from gcm_pipeline.pipeline.manifold import (
    add_continuity,
    build_manifold,
    densify,
    densify_adaptive,
)
from gcm_pipeline.pipeline.objects import target_config
from gcm_pipeline.pipeline.outputs import (
    publish,
    top_grasps,
)
from gcm_pipeline.pipeline.preflight import (
    input_files,
    preflight,
)
from gcm_pipeline.pipeline.queries import (
    ConfigRunQueries,
    grasp_manifold,
    load_manifold,
)
from gcm_pipeline.pipeline.ranking import (
    branch_scores,
    rank,
    select_branches,
)
from gcm_pipeline.pipeline.reach import (
    ReachabilityCheck,
    approach_move,
    check_reachability,
    collision_world,
    make_checker,
    reach_options,
    reachability_engine,
    retreat_move,
    robot_from_config,
)
from gcm_pipeline.pipeline.reach import (
    load_robot as load_robot,
)
from gcm_pipeline.pipeline.run import (
    STEPS,
    Pipeline,
    RunResult,
    unreachable_hint,
)
from gcm_pipeline.pipeline.run_objects import ObjectsResult, run_objects
from gcm_pipeline.pipeline.sources import (
    candidate_poses,
    generate_candidates,
)

__all__ = [
    "STEPS",
    "ConfigRunQueries",
    "ObjectsResult",
    "Pipeline",
    "ReachabilityCheck",
    "RunResult",
    "add_continuity",
    "approach_move",
    "branch_scores",
    "build_manifold",
    "candidate_poses",
    "check_reachability",
    "collision_world",
    "densify",
    "densify_adaptive",
    "generate_candidates",
    "grasp_manifold",
    "input_files",
    "load_manifold",
    "make_checker",
    "place_file_object",
    "preflight",
    "publish",
    "rank",
    "reach_options",
    "reachability_engine",
    "retreat_move",
    "robot_from_config",
    "run_objects",
    "select_branches",
    "target_config",
    "top_grasps",
    "unreachable_hint",
]
