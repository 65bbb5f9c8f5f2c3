"""The object painted by reachability: per surface point, the share of nearby grasps reachable.

REACH's heat map, built into the scene. The object's surface is remeshed
into a skin of about :data:`PAINT_POINTS` vertices (long edges split, a large
mesh decimated; the same on every run); each
grasp is placed on the surface at its *anchor*: its contact point when the
table has ``contact_x``, ``contact_y``, ``contact_z``, else the point where
its approach axis meets the surface (among the surface points that face the
oncoming gripper, the one nearest the axis; a grasp away from the object, or
whose axis misses it, paints nothing). A surface point's value is the
share of reachable grasps among the (at most :data:`NEIGHBOURS`) anchors
within a radius of it (:func:`paint_radius`, from the object's size); a point
with no anchor that near has no value and is drawn dark grey.

The skin is drawn as one vertex-coloured mesh at ``/object_reachability``,
0.5 mm outside the object, coloured by :data:`PAINT_COLORMAP` (red: none
reachable, blue: all reachable; between vertices the colours blend), a
colormap apart from the glyphs' viridis.
Above :data:`MAX_PAINT_GRASPS` grasps a uniform sample of them paints.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass
from typing import Any

import numpy as np

from gcm_pipeline.errors import GcmError
from gcm_pipeline.geometry.dualquat import dq_to_matrix
from gcm_pipeline.outputs.meshcat_lib import load_meshcat
from gcm_pipeline.outputs.plots import colormap
from gcm_pipeline.outputs.scene_glyphs import hex_color
from gcm_pipeline.outputs.scene_shapes import SceneShape
from gcm_pipeline.sources.antipodal import object_mesh
from gcm_pipeline.table import GraspTable

__all__ = [
    "NO_DATA_COLOR",
    "PAINT_COLORMAP",
    "PAINT_POINTS",
    "PaintResult",
    "draw_paint",
    "paint_radius",
    "reachability_paint",
    "surface_samples",
    "surface_skin",
]

#: Surface points painted.
PAINT_POINTS = 3000
#: Colormap of the share reachable (0 red, 1 blue): apart from the glyphs' viridis.
PAINT_COLORMAP = "RdBu"
#: Colour (RGB in [0, 1]) of surface points with no grasp nearby.
NO_DATA_COLOR = (0.3, 0.3, 0.3)
#: Most anchors a surface point's share counts.
NEIGHBOURS = 32
#: Most grasps that paint (a uniform sample of larger tables).
MAX_PAINT_GRASPS = 20_000
#: Surface points an approach axis is met at (every third: the anchor lies well
#: within the neighbourhood's radius of where the axis meets the surface).
_ENTRY_STRIDE = 3
_HIST_BINS = 10
#: How far the painted skin lies outside the object's surface (no z-fighting) [m].
_SKIN_OFFSET = 0.0005
#: Most faces of the painted skin (a larger mesh is decimated).
_MAX_SKIN_FACES = 20_000
_CHUNK = 2000
_CONTACTS = ("contact_x", "contact_y", "contact_z")


def _object_trimesh(obj: SceneShape) -> Any:
    """The object's surface as a trimesh in its own frame."""
    import trimesh

    if obj.shape == "plane":
        sx, sy = obj.size or (0.1, 0.1)
        return trimesh.creation.box(extents=[sx, sy, 0.002])
    return object_mesh(
        obj.shape,
        radius=obj.radius,
        height=obj.height,
        size=obj.size,
        mesh=obj.mesh,
        scale=obj.scale,
    )


def _cylinder_skin(radius: float, height: float, edge: float) -> Any:
    """A closed cylinder (axis z, base at z = 0 as the object's), vertices about ``edge`` apart."""
    import trimesh

    n_r = max(int(np.ceil(radius / edge)), 1)
    n_h = max(int(np.ceil(height / edge)), 1)
    r = np.r_[
        np.linspace(0.0, radius, n_r + 1),
        np.full(n_h - 1, radius),
        np.linspace(radius, 0.0, n_r + 1),
    ]
    z = np.r_[
        np.full(n_r + 1, 0.0),
        np.linspace(0.0, height, n_h + 1)[1:-1],
        np.full(n_r + 1, height),
    ]
    sections = max(int(np.ceil(2.0 * np.pi * radius / edge)), 8)
    mesh = trimesh.creation.revolve(np.column_stack([r, z]), sections=sections)
    mesh.merge_vertices()
    mesh.update_faces(mesh.nondegenerate_faces())
    mesh.fix_normals()
    return mesh


def surface_skin(obj: SceneShape, count: int = PAINT_POINTS) -> tuple[Any, Any, Any]:
    """The object's surface as a skin of about ``count`` vertices, in the world.

    Long edges are split until the vertices are about evenly spaced (a
    cylinder is a revolved profile); a skin of more than
    :data:`_MAX_SKIN_FACES` faces (a large mesh) is then decimated.

    Returns:
        Vertices (M, 3), their outward normals (M, 3) and the faces (F, 3).

    Raises:
        GcmError: A mesh file that cannot be read.
    """
    import trimesh

    mesh = _object_trimesh(obj)
    edge = float(np.sqrt(max(float(mesh.area), 1e-12) / (0.43 * count)))
    if obj.shape == "cylinder":  # trimesh's has long thin sides: revolve a profile instead
        skin = _cylinder_skin(float(obj.radius or 0.0), float(obj.height or 0.0), edge)
    else:
        verts, faces = trimesh.remesh.subdivide_to_size(mesh.vertices, mesh.faces, max_edge=edge)
        skin = trimesh.Trimesh(verts, faces, process=True)
    if len(skin.faces) > _MAX_SKIN_FACES:  # a large mesh
        try:
            skin = skin.simplify_quadric_decimation(face_count=_MAX_SKIN_FACES)
        except (ImportError, ValueError):  # the skin stays right, only larger
            pass
    rot, t = obj.pose[:3, :3], obj.pose[:3, 3]
    normals = np.asarray(skin.vertex_normals, dtype=float) @ rot.T
    points = np.asarray(skin.vertices, dtype=float) @ rot.T + t
    return points, normals, np.asarray(skin.faces, dtype=np.int64)


def surface_samples(obj: SceneShape, count: int = PAINT_POINTS) -> tuple[np.ndarray, np.ndarray]:
    """Points (M, 3) on the object's surface and their outward normals (M, 3), in the world.

    The vertices of :func:`surface_skin`.

    Raises:
        GcmError: A mesh file that cannot be read.
    """
    points, normals, _ = surface_skin(obj, count)
    return points, normals


def paint_radius(points: np.ndarray) -> float:
    """The neighbourhood of a surface point [m]: 15 % of the object's diagonal, at least 5 mm."""
    if not len(points):
        return 0.005
    diag = float(np.linalg.norm(np.ptp(points, axis=0)))
    return max(0.15 * diag, 0.005)


def _entry_points(
    origins: np.ndarray,
    approach: np.ndarray,
    surface: np.ndarray,
    normals: np.ndarray,
    radius: float,
) -> np.ndarray:
    """Per grasp, the surface point where its approach axis meets the surface (K, 3).

    Among the surface points facing the oncoming gripper (normal against the
    approach), the one nearest the approach axis; NaN when the axis passes
    farther than ``radius`` from every one (the grasp is not at the object).
    Distances by products (BLAS), in chunks.
    """
    out = np.full((len(origins), 3), np.nan)
    s = surface.astype(np.float32)
    ss = np.einsum("mi,mi->m", s, s)
    n_t = normals.T.astype(np.float32)
    for lo in range(0, len(origins), _CHUNK):
        o = origins[lo : lo + _CHUNK].astype(np.float32)
        a = approach[lo : lo + _CHUNK].astype(np.float32)
        v2 = ss[None, :] - 2.0 * (o @ s.T) + np.einsum("ki,ki->k", o, o)[:, None]
        along = a @ s.T - np.einsum("ki,ki->k", o, a)[:, None]
        perp = np.where(a @ n_t < 0.0, v2 - along**2, np.inf)
        best = np.argmin(perp, axis=1)
        hit = perp[np.arange(len(o)), best] <= radius**2
        out[lo : lo + len(o)][hit] = surface[best[hit]]
    return out


def _anchors(
    grasps: GraspTable, rows: np.ndarray, surface: np.ndarray, normals: np.ndarray, radius: float
) -> np.ndarray:
    """Where each grasp of ``rows`` sits on the surface (K, 3): contact, else approach entry.

    NaN for a grasp without a contact point whose frame lies farther from
    the object than ``radius`` beyond its bounding sphere, or whose approach
    axis misses it.
    """
    out = np.full((len(rows), 3), np.nan)
    if all(k in grasps for k in _CONTACTS):
        out = np.column_stack([np.asarray(grasps[k], dtype=float)[rows] for k in _CONTACTS])
    todo = ~np.all(np.isfinite(out), axis=1)
    if todo.any():
        m = dq_to_matrix(np.asarray(grasps["dq"], dtype=float)[rows[todo]])
        centre = 0.5 * (surface.min(axis=0) + surface.max(axis=0))
        reach = float(np.linalg.norm(surface - centre, axis=1).max()) + radius
        near = np.linalg.norm(m[:, :3, 3] - centre, axis=1) <= reach
        coarse = slice(None, None, _ENTRY_STRIDE)
        entry = np.full((len(m), 3), np.nan)
        entry[near] = _entry_points(
            m[near, :3, 3], m[near, :3, 2], surface[coarse], normals[coarse], radius
        )
        out[todo] = entry
    return out


@dataclass(frozen=True, eq=False)
class PaintResult:
    """The painted surface.

    Attributes:
        points: Surface points (M, 3) in the world [m].
        share: Share of reachable grasps near each (M,); NaN: no grasp near.
        radius: The neighbourhood's radius [m].
        spacing: Median distance between neighbouring surface points [m].
        normals: Outward normals (M, 3) of the points.
        faces: Triangles (F, 3) of the skin whose vertices the points are.
    """

    points: np.ndarray
    share: np.ndarray
    radius: float
    spacing: float
    normals: np.ndarray
    faces: np.ndarray

    def summary(self) -> dict[str, Any]:
        """JSON-ready: points, painted (with a value), mean share, a histogram over [0, 1]."""
        ok = np.isfinite(self.share)
        hist = np.histogram(self.share[ok], bins=_HIST_BINS, range=(0.0, 1.0))[0]
        return {
            "points": len(self.share),
            "painted": int(ok.sum()),
            "mean": float(self.share[ok].mean()) if ok.any() else None,
            "histogram": hist.astype(int).tolist(),
            "bins": np.linspace(0.0, 1.0, _HIST_BINS + 1).tolist(),
            "radius": self.radius,
            "spacing": self.spacing,
            "colormap": PAINT_COLORMAP,
            "no_data_color": hex_color(NO_DATA_COLOR),
        }


def reachability_paint(
    obj: SceneShape, grasps: GraspTable, reachable: np.ndarray, count: int = PAINT_POINTS
) -> PaintResult:
    """The share of reachable grasps near each of ``count`` surface points of ``obj``.

    Args:
        obj: The object.
        grasps: The grasp table (``dq``; ``contact_x/y/z`` when present).
        reachable: (N,) bool, the reachable rows.
        count: Surface points.

    Raises:
        GcmError: The object's mesh file cannot be read.
    """
    from scipy.spatial import cKDTree

    surface, normals, faces = surface_skin(obj, count)
    radius = paint_radius(surface)
    spacing = float(np.median(cKDTree(surface).query(surface, k=2)[0][:, 1]))
    rows = np.arange(len(grasps))
    if len(rows) > MAX_PAINT_GRASPS:
        rng = np.random.default_rng(0)
        rows = np.sort(rng.choice(len(rows), size=MAX_PAINT_GRASPS, replace=False))
    share = np.full(len(surface), np.nan)
    if not len(rows):
        return PaintResult(surface, share, radius, spacing, normals, faces)
    anchors = _anchors(grasps, rows, surface, normals, radius)
    ok = np.all(np.isfinite(anchors), axis=1)
    anchors, good = anchors[ok], np.asarray(reachable, dtype=bool)[rows[ok]]
    if not len(anchors):
        return PaintResult(surface, share, radius, spacing, normals, faces)
    k = min(NEIGHBOURS, len(anchors))
    dist, idx = cKDTree(anchors).query(surface, k=k, distance_upper_bound=radius)
    dist, idx = dist.reshape(len(surface), k), idx.reshape(len(surface), k)
    near = np.isfinite(dist)
    hits = np.where(near, good[np.minimum(idx, len(anchors) - 1)], False).sum(axis=1)
    n_near = near.sum(axis=1)
    share[n_near > 0] = hits[n_near > 0] / n_near[n_near > 0]
    return PaintResult(surface, share, radius, spacing, normals, faces)


def draw_paint(vis: Any, obj: SceneShape, grasps: GraspTable, reachable: np.ndarray) -> Any:
    """Draw the painted object at ``/object_reachability``.

    Returns:
        The :class:`PaintResult`, drawn only when a grasp is near the object
        (the object is not covered by a grey skin of no data); None when the
        object cannot be sampled (a warning says why; the rest of the scene
        is drawn).
    """
    try:
        paint = reachability_paint(obj, grasps, reachable)
    except GcmError as exc:
        warnings.warn(f"object not painted by reachability: {exc}", stacklevel=3)
        return None
    if not np.isfinite(paint.share).any():
        return paint
    colors = np.tile(np.asarray(NO_DATA_COLOR, dtype=np.float32), (len(paint.share), 1))
    ok = np.isfinite(paint.share)
    colors[ok] = colormap(PAINT_COLORMAP)(paint.share[ok])[:, :3]
    mg = load_meshcat().geometry
    skin = (paint.points + _SKIN_OFFSET * paint.normals).astype(np.float32)
    geometry = mg.TriangularMeshGeometry(skin, paint.faces.astype(np.uint32), color=colors)
    material = mg.MeshLambertMaterial(vertexColors=True)
    vis["object_reachability"].set_object(geometry, material)
    return paint
