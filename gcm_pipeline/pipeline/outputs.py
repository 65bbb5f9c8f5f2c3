"""The ``publish`` step and the best grasps of a run as plain dicts."""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from gcm_pipeline.config.run import Config, takes_config
from gcm_pipeline.geometry.dualquat import dq_to_pos_quat
from gcm_pipeline.table import GraspTable

if TYPE_CHECKING:  # the run module imports this one
    from gcm_pipeline.pipeline.run import RunResult


@takes_config
def publish(result: RunResult, cfg: Config, out_dir: str | Path) -> list[Path]:
    """Write ``scene.html`` / PNG plots into ``out_dir`` (section ``publish``).

    Returns:
        The files written.
    """
    from gcm_pipeline.outputs import html

    counts = {k: v for k, v in result.counts.items() if isinstance(v, int)}
    files = html.publish(
        result.grasps, result.manifold, result.robot, cfg, Path(out_dir), counts=counts
    )
    return list(files)


def top_grasps(grasps: GraspTable, n: int, metric: str = "yoshikawa") -> list[dict[str, Any]]:
    """The ``n`` best-ranked grasps as plain dicts (rank, pose, metrics, q).

    Each has ``rank, row, origin, x, y, z, qw, qx, qy, qz`` (``qw >= 0``),
    ``manipulability``, the ranking metric's column when it is another one,
    and ``q``. Rows without a ``rank`` column, or unranked (rank 0), are left out.
    """
    from gcm_pipeline.ranking.metrics import METRIC_COLUMNS

    if "rank" not in grasps or n <= 0:
        return []
    rank_col = np.asarray(grasps["rank"])
    rows = np.flatnonzero(rank_col > 0)
    rows = rows[np.argsort(rank_col[rows], kind="stable")][:n]
    if rows.size == 0:
        return []
    pos, quat = dq_to_pos_quat(grasps["dq"][rows])
    quat = np.where(quat[:, :1] < 0, -quat, quat)
    out = []
    for k, i in enumerate(rows.tolist()):
        item: dict[str, Any] = {"rank": int(rank_col[i]), "row": i}
        if "origin" in grasps:
            item["origin"] = str(grasps["origin"][i])
        item.update(zip(("x", "y", "z"), pos[k].tolist(), strict=True))
        item.update(zip(("qw", "qx", "qy", "qz"), quat[k].tolist(), strict=True))
        for name in dict.fromkeys(("manipulability", METRIC_COLUMNS.get(metric, metric))):
            if name in grasps:
                item[name] = float(grasps[name][i])
        if "q" in grasps:
            item["q"] = np.asarray(grasps["q"][i], dtype=float).tolist()
        out.append(item)
    return out
