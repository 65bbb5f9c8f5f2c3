"""Reachability: IK, collision checks and the approach and retreat moves of every grasp.

* :mod:`~gcm_pipeline.reach.engine`: :class:`ReachabilityEngine`, the one place
  the decision is made (its module docstring states the sequence);
* :mod:`~gcm_pipeline.reach.moves`: the straight-line approach and retreat;
* :mod:`~gcm_pipeline.reach.check`: the engine run on a grasp table;
* :mod:`~gcm_pipeline.reach.branches`: one IK branch per grasp out of several.
"""
