"""Ranking: the metrics of the reachable grasps and their rank.

* :mod:`~gcm_pipeline.ranking.metrics`: the metric names, their columns and
  the ``combined`` metric;
* :mod:`~gcm_pipeline.ranking.rank`: the metric columns, ``rank`` and ``top``.
"""
