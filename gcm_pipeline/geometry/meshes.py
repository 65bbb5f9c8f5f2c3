"""Reading a triangle mesh file into a coal BVH mesh, with one-line errors."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import coal
import numpy as np

__all__ = ["MeshReadError", "read_mesh"]


class MeshReadError(ValueError):
    """A mesh file that cannot be used; the message is one line naming the file."""


def read_mesh(path: str | Path, scale: Any = 1.0) -> Any:
    """A mesh file (STL, OBJ, DAE, ... through coal's assimp loader) as a coal BVH mesh.

    Args:
        path: The file.
        scale: One factor or three (per axis).

    Returns:
        A ``coal.BVHModelOBBRSS`` in the file's frame, scaled [m].

    Raises:
        MeshReadError: The file does not exist, cannot be read, has no
            triangles or has a vertex that is not finite.
    """
    p = Path(path).expanduser()
    if not p.is_file():
        raise MeshReadError(f"mesh file {str(p)!r} does not exist")
    bad = _first_nonfinite_vertex(p)  # before coal: its BVH fit prints on NaN input
    if bad is not None:
        raise MeshReadError(f"mesh file {str(p)!r}: vertex {bad} is not finite")
    factors = np.broadcast_to(np.asarray(scale, dtype=float), (3,)).copy()
    try:
        mesh = coal.MeshLoader().load(str(p), factors)
    except Exception as exc:  # coal raises ValueError with a multi-line message
        raise MeshReadError(f"cannot read mesh file {str(p)!r}: {_coal_reason(exc)}") from exc
    if mesh.num_tris == 0:
        raise MeshReadError(f"mesh file {str(p)!r} has no triangles")
    verts = np.asarray(mesh.vertices())
    if not np.isfinite(verts).all():
        i = int(np.flatnonzero(~np.isfinite(verts).all(axis=1))[0])
        raise MeshReadError(f"mesh file {str(p)!r}: vertex {i} is not finite")
    return mesh


def _coal_reason(exc: Exception) -> str:
    """The reason in coal's multi-line loader message, without its C++ source location.

    coal says ``From file: /project/src/mesh_loader/assimp.cpp``, ``in function: ...``,
    ``at line: ...``, ``message: Could not load resource <file>``, then assimp's
    reason (``STL: Invalid number of vertices``) and a hint: the reason is kept.
    """
    lines = [ln.strip() for ln in str(exc).strip().splitlines() if ln.strip()]
    skip = ("From file:", "in function:", "at line:", "Hint:", "message: Could not load resource")
    useful = [ln for ln in lines if not ln.startswith(skip)]
    return " ".join(useful)[:300] or "assimp cannot read it"


def _first_nonfinite_vertex(path: Path) -> int | None:
    """Index of the first NaN/inf vertex of a mesh file trimesh can read, else None."""
    try:
        import trimesh

        mesh: Any = trimesh.load(str(path), force="mesh", process=False)
        verts = np.asarray(mesh.vertices, dtype=float).reshape(-1, 3)
    except Exception:  # coal reads it (or says why not)
        return None
    bad = np.flatnonzero(~np.isfinite(verts).all(axis=1))
    return int(bad[0]) if bad.size else None
