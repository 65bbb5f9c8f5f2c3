"""A fused depth scene around configs/bottle_side.yaml's bottle: N points with noise.

Surfaces sampled uniformly by area: the table top in front of the robot (its base
region left out), two boxes beside the bottle, a shelf behind it (two boards and
two side walls), the room around them (floor, two walls), and the bottle's own
surface (dropped when read by ``exclude_object_distance``). Gaussian noise of
``--noise`` [m] on every point.

    python benchmarks/make_cloud.py OUT.npy [--points 3000000] [--seed 0]
"""

from __future__ import annotations

import argparse

import numpy as np


def box_faces(lo, hi):
    """The faces of box ``lo``..``hi`` but its bottom, as (axis, value, lo2, hi2)."""
    lo, hi = np.asarray(lo, float), np.asarray(hi, float)
    faces = []
    for axis in range(3):
        for side in (lo[axis], hi[axis]):
            if axis == 2 and side == lo[2]:
                continue  # the bottom face lies on the table
            o = [k for k in range(3) if k != axis]
            faces.append((axis, side, lo[o], hi[o]))
    return faces


def sample_rect(rng, n, axis, value, lo, hi):
    """``n`` points uniform on the axis-aligned rectangle at ``value`` along ``axis``."""
    o = [k for k in range(3) if k != axis]
    p = np.empty((n, 3))
    p[:, axis] = value
    p[:, o] = rng.uniform(lo, hi, (n, 2))
    return p


def main() -> None:
    """Write the cloud."""
    ap = argparse.ArgumentParser()
    ap.add_argument("out")
    ap.add_argument("--points", type=int, default=3_000_000)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--noise", type=float, default=0.002)
    a = ap.parse_args()
    rng = np.random.default_rng(a.seed)
    rects = []  # (axis, value, lo2, hi2)
    # table top z = 0 in front of the robot (x from 0.25 m: the base stands before its edge)
    rects.append((2, 0.0, np.array([0.25, -0.6]), np.array([1.0, 0.6])))
    # two boxes beside the bottle
    rects += box_faces([0.40, 0.18, 0.0], [0.55, 0.30, 0.12])
    rects += box_faces([0.42, -0.32, 0.0], [0.58, -0.20, 0.18])
    # a shelf behind the bottle: side walls, a middle and a top board
    rects += box_faces([0.75, -0.45, 0.0], [0.95, -0.43, 0.6])
    rects += box_faces([0.75, 0.43, 0.0], [0.95, 0.45, 0.6])
    rects += box_faces([0.75, -0.43, 0.30], [0.95, 0.43, 0.32])
    rects += box_faces([0.75, -0.43, 0.58], [0.95, 0.43, 0.60])
    # the room a fused scan also sees: the floor under the table (z = -0.75), the wall
    # behind the shelf and one to the side, the table's front edge
    rects.append((2, -0.75, np.array([-0.8, -1.5]), np.array([1.6, 1.5])))
    rects.append((0, 1.3, np.array([-1.5, -0.75]), np.array([1.5, 1.2])))
    rects.append((1, 1.2, np.array([-0.8, -0.75]), np.array([1.3, 1.2])))
    rects.append((0, 1.0, np.array([-0.6, -0.75]), np.array([0.6, 0.0])))
    areas = np.array([np.prod(hi - lo) for _, _, lo, hi in rects])
    # the bottle's surface (r 0.035, h 0.22 at (0.5, 0, 0)): as dense as the rest
    bottle_area = 2 * np.pi * 0.035 * 0.22 + np.pi * 0.035**2
    total = areas.sum() + bottle_area
    counts = np.floor(a.points * np.append(areas, bottle_area) / total).astype(int)
    counts[0] += a.points - counts.sum()
    parts = [sample_rect(rng, c, *r) for c, r in zip(counts[:-1], rects, strict=True)]
    nb = counts[-1]
    side = rng.random(nb) < (2 * np.pi * 0.035 * 0.22) / bottle_area
    th = rng.uniform(0, 2 * np.pi, nb)
    r = np.where(side, 0.035, 0.035 * np.sqrt(rng.random(nb)))
    z = np.where(side, rng.uniform(0, 0.22, nb), 0.22)
    parts.append(np.stack([0.5 + r * np.cos(th), r * np.sin(th), z], axis=1))
    pts = np.concatenate(parts)
    pts += rng.normal(0.0, a.noise, pts.shape)
    rng.shuffle(pts)
    np.save(a.out, pts.astype(np.float32))
    print(a.out, pts.shape, "bottle points", nb)


if __name__ == "__main__":
    main()
