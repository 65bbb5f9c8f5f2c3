"""Reachability: IK, collision checks and the approach and retreat moves of every grasp.

* :mod:`~gcm_pipeline.reach.engine`: :class:`ReachabilityEngine`, the one place
  the decision is made (its module docstring states the sequence), with
  :mod:`~gcm_pipeline.reach.chunk` (steps 1-5 of one chunk of targets),
  :mod:`~gcm_pipeline.reach.solution_checks` (step 2: collisions, validator,
  moves), :mod:`~gcm_pipeline.reach.alternatives` (steps 3-4: other IK
  solutions), :mod:`~gcm_pipeline.reach.workers` (chunks on worker processes)
  and :mod:`~gcm_pipeline.reach.result` (its typed results);
* :mod:`~gcm_pipeline.reach.options`: :class:`ReachOptions`, the frozen options
  of a check (``gcm_pipeline.pipeline`` maps a config onto them);
* :mod:`~gcm_pipeline.reach.moves`: the straight-line approach and retreat,
  planned by :mod:`~gcm_pipeline.reach.path` through the waypoints of
  :mod:`~gcm_pipeline.reach.waypoints`, within the bound of
  :mod:`~gcm_pipeline.reach.deviation`, their collisions checked by
  :mod:`~gcm_pipeline.reach.move_check`;
* :mod:`~gcm_pipeline.reach.check`: the engine run on a grasp table;
* :mod:`~gcm_pipeline.reach.branches`: one IK branch per grasp out of several.
"""
