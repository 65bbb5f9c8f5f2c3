"""Write configs/data/mug.obj: a solid mug (cylinder body and a ring handle) for the examples.

The body is a closed cylinder (radius 40 mm, height 100 mm, standing on its
base at z = 0 of the mesh frame) and the handle a torus (ring radius 30 mm,
tube radius 7 mm) standing in the xz plane on the +x side; the two are
united into one watertight mesh with trimesh's boolean union (manifold3d,
in the ``dev`` extra). Run from the repository root::

    python scripts/make_mug.py
"""

from __future__ import annotations

import math
from pathlib import Path

import trimesh

OUT = Path(__file__).resolve().parent.parent / "configs" / "data" / "mug.obj"


def mug() -> trimesh.Trimesh:
    """The mug mesh [m]."""
    body = trimesh.creation.cylinder(radius=0.04, height=0.10, sections=48)
    body.apply_translation([0.0, 0.0, 0.05])
    handle = trimesh.creation.torus(
        major_radius=0.03, minor_radius=0.007, major_sections=32, minor_sections=12
    )
    handle.apply_transform(trimesh.transformations.rotation_matrix(math.pi / 2, [1, 0, 0]))
    handle.apply_translation([0.052, 0.0, 0.055])
    return trimesh.boolean.union([body, handle], engine="manifold")


def main() -> None:
    """Write the mesh and print its size."""
    mesh = mug()
    assert mesh.is_watertight
    OUT.parent.mkdir(parents=True, exist_ok=True)
    mesh.export(OUT, digits=6)
    print(f"{OUT}: {len(mesh.vertices)} vertices, {len(mesh.faces)} faces, watertight")


if __name__ == "__main__":
    main()
