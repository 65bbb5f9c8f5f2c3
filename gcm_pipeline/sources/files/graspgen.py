"""``format: graspgen``: GraspGen's grasp data (JSON or YAML) and its ``isaac_grasp`` YAML.

Dataset layout: ``grasps.transforms`` (N, 4, 4) poses of the gripper's base
link in the object mesh frame, optional ``grasps.object_in_gripper`` (N,)
success mask and ``grasps.confidences`` (N,), ``object.file`` /
``object.scale``, an optional ``gripper`` (a name or ``{name: ...}``).
Inference output in the ``isaac_grasp`` format: ``format: isaac_grasp``,
``grasps: {name: {confidence, position: [x, y, z], orientation: {w, xyz: [x,
y, z]}}}``. Sources: GraspGen's ``docs/GRASP_DATASET_FORMAT.md`` and its
``save_to_isaac_grasp_format``; the Isaac Sim grasp-editor page on the
``isaac_grasp`` file.
"""

from __future__ import annotations

import json
import logging
import math
from pathlib import Path
from typing import Any

import numpy as np
from scipy.spatial.transform import Rotation

from gcm_pipeline.bounds import DEFAULT_MAX_CANDIDATES
from gcm_pipeline.errors import InputError, clip
from gcm_pipeline.safe_yaml import load_yaml
from gcm_pipeline.sources.files.common import (
    ImportedGrasps,
    check_bytes,
    check_count,
    check_poses,
    check_positions,
    score_column,
    success_labels,
    vector,
)
from gcm_pipeline.sources.files.sniff import check_format

__all__ = ["graspgen_object", "read_graspgen"]

log = logging.getLogger(__name__)

#: Bytes a grasp may take in a text (JSON/YAML) file (the slack on top holds the
#: object, gripper and comments): a file larger than ``max_count`` grasps can fill is refused.
_TEXT_BYTES_PER_GRASP = 2048
#: YAML or JSON values a grasp may take (YAML after aliases; 16 for its pose and a few more).
_YAML_VALUES_PER_GRASP = 64


def _read_structured(path: Path, max_count: int) -> Any:
    try:
        check_bytes(path, path.stat().st_size, max_count, _TEXT_BYTES_PER_GRASP, "its grasps")
        text = path.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as exc:
        raise InputError(f"{path}: cannot read: {exc}", path=path) from None
    max_values = max(_YAML_VALUES_PER_GRASP * max_count, 100_000)
    if path.suffix.lower() == ".json":
        # a value takes up to ~70 bytes parsed ("[]," is 3 bytes of text and a list of 56):
        # counted from the separators before anything is built
        values = 1 + text.count(",") + text.count("[") + text.count("{")
        if values > max_values:
            raise InputError(
                f"{path}: holds about {values:,} JSON values, more than {max_count:,} grasps "
                f"(candidates.max_count) need (at most {max_values:,}); raise "
                "candidates.max_count to read it",
                path=path,
            )
        try:
            return json.loads(text)
        except ValueError as exc:
            raise InputError(
                f"{path}: not valid JSON: {' '.join(str(exc).split())}", path=path
            ) from None
        except RecursionError:
            raise InputError(
                f"{path}: not a GraspGen grasp file: JSON nested too deeply", path=path
            ) from None
    return load_yaml(text.removeprefix("\ufeff"), str(path), InputError, max_values=max_values)


def read_graspgen(path: str | Path, *, max_count: int = DEFAULT_MAX_CANDIDATES) -> ImportedGrasps:
    """Read a GraspGen grasp file (JSON/YAML dataset layout or ``isaac_grasp`` YAML).

    Args:
        path: The file.
        max_count: Most grasps the file may hold (``candidates.max_count``);
            a larger file is refused before it is parsed.

    Returns:
        Gripper base-link poses (``base`` convention, object mesh frame) with
        ``score`` (the confidences, when the file has them) and ``source_id``
        (the grasp's index in the file); ``success`` from
        ``object_in_gripper``.

    Raises:
        InputError: Unreadable file, a layout that is not GraspGen's, bad values.
    """
    path = Path(path)
    check_format(path, "graspgen")
    data = _read_structured(path, max_count)
    if not isinstance(data, dict):
        raise InputError(
            f"{path}: not a GraspGen grasp file: expected a mapping with 'grasps', "
            f"got {type(data).__name__}",
            path=path,
        )
    if data.get("format") == "isaac_grasp":
        return _read_isaac_grasp(path, data, max_count)
    grasps = data.get("grasps")
    if not isinstance(grasps, dict) or "transforms" not in grasps:
        raise InputError(
            f"{path}: not a GraspGen grasp file: expected 'grasps: {{transforms: [...]}}' "
            f"or 'format: isaac_grasp' (keys: {', '.join(map(str, data)) or 'none'})",
            path=path,
        )
    if isinstance(grasps["transforms"], list):
        check_count(path, len(grasps["transforms"]), max_count)
    try:
        raw = np.asarray(grasps["transforms"], dtype=float)
    except (TypeError, ValueError):
        raise InputError(
            f"{path}: grasps.transforms must be (N, 4, 4) numbers", path=path
        ) from None
    if raw.size == 0:
        raw = raw.reshape(0, 4, 4)
    poses = check_poses(path, raw, "grasps.transforms")
    n = len(poses)
    columns: dict[str, np.ndarray] = {}
    for key in ("confidences", "confidence", "scores"):
        if key in grasps:
            columns["score"] = score_column(path, grasps[key], n, f"grasps.{key}")
            break
    success = None
    if "object_in_gripper" in grasps:
        labels = vector(path, grasps["object_in_gripper"], n, "grasps.object_in_gripper")
        success = success_labels(path, labels, n, "grasps.object_in_gripper")
    columns["source_id"] = np.arange(n, dtype=np.int64)
    obj = data.get("object")
    if isinstance(obj, dict) and "file" in obj:
        log.info("%s: GraspGen grasps of %s (scale %s)", path, obj.get("file"), obj.get("scale"))
    gripper = data.get("gripper")
    if isinstance(gripper, dict):
        gripper = gripper.get("name")
    return ImportedGrasps(
        poses, "base", columns, success, gripper=str(gripper) if gripper else None
    )


def graspgen_object(path: str | Path, max_count: int) -> tuple[str | None, float]:
    """``object.file`` (None when the file names no mesh) and ``object.scale`` (default 1).

    Raises:
        InputError: An unreadable file, a ``file`` that is not a text, or a
            scale that is not a positive finite number.
    """
    path = Path(path)
    data = _read_structured(path, max_count)
    obj = data.get("object") if isinstance(data, dict) else None
    if not isinstance(obj, dict) or obj.get("file") is None:
        return None, 1.0
    name, scale = obj["file"], obj.get("scale", 1.0)
    if not isinstance(name, str) or not name:
        raise InputError(f"{path}: object.file must be a mesh path, got {clip(name)}", path=path)
    if isinstance(scale, list) and len(scale) == 1:
        scale = scale[0]
    if isinstance(scale, bool) or not isinstance(scale, (int, float)):
        raise InputError(f"{path}: object.scale must be a number, got {clip(scale)}", path=path)
    if not (math.isfinite(scale) and scale > 0):
        raise InputError(
            f"{path}: object.scale must be a positive number, got {scale!r}", path=path
        )
    return name, float(scale)


def _read_isaac_grasp(path: Path, data: dict[str, Any], max_count: int) -> ImportedGrasps:
    grasps = data.get("grasps")
    if not isinstance(grasps, dict):
        raise InputError(f"{path}: isaac_grasp file without a 'grasps' mapping", path=path)
    n = len(grasps)
    check_count(path, n, max_count)
    pos = np.empty((n, 3))
    quat = np.empty((n, 4))  # w, x, y, z
    score = np.full(n, np.nan)
    scored = np.zeros(n, dtype=bool)
    for i, (name, g) in enumerate(grasps.items()):
        try:
            pos[i] = np.asarray(g["position"], dtype=float).reshape(3)
            o = g["orientation"]
            quat[i, 0] = float(o["w"])
            quat[i, 1:] = np.asarray(o["xyz"], dtype=float).reshape(3)
            if "confidence" in g:
                score[i], scored[i] = float(g["confidence"]), True
        except (KeyError, TypeError, ValueError):
            raise InputError(
                f"{path}: grasp {clip(name)}: expected position: [x, y, z] and "
                "orientation: {w: .., xyz: [x, y, z]}",
                path=path,
            ) from None
        if not np.isfinite(pos[i]).all():
            raise InputError(
                f"{path}: grasp {clip(name)}: position {pos[i].tolist()} is not finite", path=path
            )
    check_positions(path, pos, lambda i: f"{path}: grasp {clip(list(grasps)[i])}")
    norm = np.linalg.norm(quat, axis=1)
    bad = np.flatnonzero(~np.isfinite(norm) | (np.abs(norm - 1.0) > 1e-3))
    if bad.size:
        name = list(grasps)[int(bad[0])]
        raise InputError(
            f"{path}: grasp {clip(name)}: orientation has norm {norm[bad[0]]:.6g}, not 1", path=path
        )
    poses = np.zeros((n, 4, 4))
    if n:
        poses[:, :3, :3] = Rotation.from_quat((quat / norm[:, None])[:, [1, 2, 3, 0]]).as_matrix()
    poses[:, :3, 3] = pos
    poses[:, 3, 3] = 1.0
    columns = {"source_id": np.arange(n, dtype=np.int64)}
    if scored.any():  # all or none: a file without confidences has no score column
        names = list(grasps)
        if not scored.all():
            i = int(np.flatnonzero(~scored)[0])
            raise InputError(
                f"{path}: grasp {clip(names[i])} has no confidence, though "
                f"{int(scored.sum()):,} of {n:,} grasps have one",
                path=path,
                key="confidence",
                row=i,
            )
        columns["score"] = score_column(
            path, score, n, "confidence", where=lambda i: f"{path}: grasp {clip(names[i])}"
        )
    return ImportedGrasps(poses, "base", columns)
