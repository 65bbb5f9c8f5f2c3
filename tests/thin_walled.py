"""Thin-walled test objects built with trimesh: a mug with a handle, a bowl, a plate.

Each is a list of closed (watertight) parts; the mug's handle overlaps its wall.
"""

from __future__ import annotations

import coal
import numpy as np
import trimesh


def _revolve(profile, sections=72):
    m = trimesh.creation.revolve(np.asarray(profile, dtype=float), sections=sections)
    if m.volume < 0:
        m.invert()
    assert m.is_watertight and m.is_volume
    return m


def _tube(path, radius, sides=24):
    """Closed tube of circular section along a polyline, capped at both ends."""
    path = np.asarray(path, dtype=float)
    tangent = np.gradient(path, axis=0)
    tangent /= np.linalg.norm(tangent, axis=1, keepdims=True)
    ref = np.array([0.0, 1.0, 0.0])
    u = np.cross(tangent, ref)
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    v = np.cross(tangent, u)
    ang = np.linspace(0, 2 * np.pi, sides, endpoint=False)
    ring = path[:, None] + radius * (
        np.cos(ang)[None, :, None] * u[:, None] + np.sin(ang)[None, :, None] * v[:, None]
    )
    verts = np.vstack([ring.reshape(-1, 3), path[[0, -1]]])
    n, faces = len(path), []
    for i in range(n - 1):
        for j in range(sides):
            a, b = i * sides + j, i * sides + (j + 1) % sides
            faces += [[a, b, b + sides], [a, b + sides, a + sides]]
    c0, c1 = n * sides, n * sides + 1
    for j in range(sides):
        faces.append([c0, (j + 1) % sides, j])
        faces.append([c1, (n - 1) * sides + j, (n - 1) * sides + (j + 1) % sides])
    m = trimesh.Trimesh(verts, np.array(faces), process=True)
    trimesh.repair.fix_normals(m)
    assert m.is_watertight and m.is_volume
    return m


def cup_parts():
    """A mug: 3 mm wall, 4 mm bottom, r = 40 mm, h = 100 mm, a handle 8 mm thick."""
    r, h, wall, bottom = 0.040, 0.100, 0.003, 0.004
    body = _revolve([[0, 0], [r, 0], [r, h], [r - wall, h], [r - wall, bottom], [0, bottom]])
    theta = np.linspace(-np.pi / 2, np.pi / 2, 40)
    arc = np.stack([r - 0.001 + 0.025 * np.cos(theta), 0 * theta, 0.055 + 0.025 * np.sin(theta)], 1)
    return [body, _tube(arc, 0.004)]


def bowl_parts():
    """A hemispherical bowl, 2 mm wall, outer radius 80 mm, open 65 deg from the bottom."""
    ro, w = 0.080, 0.002
    phi = np.linspace(0, np.radians(65), 40)
    outer = np.stack([ro * np.sin(phi), ro - ro * np.cos(phi)], 1)
    inner = np.stack([(ro - w) * np.sin(phi), ro - (ro - w) * np.cos(phi)], 1)[::-1]
    return [_revolve(np.vstack([outer, inner]))]


def plate_parts():
    """A flat plate, 200 x 150 x 2 mm."""
    return [trimesh.creation.box((0.20, 0.15, 0.002))]


def to_bvh(mesh):
    """A trimesh mesh as a coal BVH mesh (its surface), built directly."""
    bvh = coal.BVHModelOBBRSS()
    bvh.beginModel(len(mesh.faces), len(mesh.vertices))
    bvh.addVertices(np.asarray(mesh.vertices, dtype=float))
    bvh.addTriangles(np.asarray(mesh.faces, dtype=int))
    bvh.endModel()
    return bvh


def coal_transform(m):
    """A (4, 4) transform as a coal.Transform3s."""
    t = coal.Transform3s()
    t.setRotation(np.ascontiguousarray(m[:3, :3]))
    t.setTranslation(np.ascontiguousarray(m[:3, 3]))
    return t
