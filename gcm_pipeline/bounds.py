"""Size limits checked before anything large is allocated.

A run refuses work whose size it can estimate in advance and that would
exhaust memory, with a message that gives the estimate and the config key
that raises the ceiling. The ceilings a user can raise are config keys; the
fixed ones are bounds of the config schema:

- ``candidates.max_count`` (default 1,000,000): the generated ``count``; the
  grasps in a file, from its header, before reading.
- ``densify.max_poses`` (default 2,000,000): candidates plus lattice points,
  the sum over the triangles of (n+1)(n+2)/2, before the lattice is built.
- ``densify.adaptive.max_level``: at most 10 (schema bound; 2**10 subdivisions
  per candidate edge); the table is checked against ``densify.max_poses``
  before each level of adaptive refinement.
- ``approach.steps``, ``retreat.steps``: at most 1,000 (schema bound; 0.1 mm
  steps over 10 cm).
- ``ik.workers``: at most 256 (schema bound).
- ``environment.obstacles``: at most 100 (schema bound; each costs the
  collision checker about 4.5 MB: 2,000 took 8.9 GB; a cluttered scene is
  one mesh).
- ``ik.solutions``: at most 16 IK branches per grasp (schema bound).
- Lengths and positions of the scene (poses, shape dims, the table, the
  approach and retreat distances, the contact tolerance) and a mesh's
  ``scale``: at most 1,000 (m, or a factor) in magnitude (schema bound). A
  robot's world is metres across; at 1e20 coal's bounding volumes break, and
  a box of 1e308 m makes Eigen's eigen-solver give up.
- Studies: a range ``{from, to, steps}`` has at most 1,000,000 steps; a study
  plans at most 1,000,000 placements even with ``--force`` (above
  ``max_placements``, default 1,000, it needs ``--force``). The count is
  worked out per axis before any placement is built.
- Point clouds (``environment.point_clouds``): at most
  :data:`MAX_POINT_CLOUDS` clouds; each is read in chunks of
  :data:`CLOUD_CHUNK` points and voxelised while reading, so memory follows
  the occupied voxels (at most :data:`MAX_CLOUD_VOXELS` per cloud), not the
  points (.npy, .npz, .pcd ascii/binary, depth images); formats read whole
  (``.ply``, a pickled ``.npy`` dict) at most :data:`MAX_CLOUD_FILE_BYTES`.
- YAML files and ``--set`` values: 1 MiB, depth 64, 100,000 values after
  aliases (:mod:`gcm_pipeline.safe_yaml`).
- A study directory's ``study.json``: 16 MiB (a study writes a few kB
  there; a larger one is refused in one line before it is read).
- Grasp files: a grasp's position at most ``MAX_LENGTH`` (1,000 m) from the
  file's origin (:data:`MAX_GRASP_DISTANCE`); a CSV cell (a grasp file's or
  ``grasps.csv``'s) at most :data:`MAX_CSV_CELL` characters (text columns
  are arrays as wide as their longest cell: one 100,000-character cell made
  20,000 rows ask for 59.6 GiB); an HDF5 text (ACRONYM's ``object/file``)
  at most :data:`MAX_HDF5_TEXT` bytes as declared, checked before it is read.

Any stage that grows the table (adaptive refinement included) checks its
estimate with :func:`check_size` against the same key.
"""

from __future__ import annotations

import numpy as np

from gcm_pipeline.errors import ConfigError

__all__ = [
    "DEFAULT_MAX_CANDIDATES",
    "DEFAULT_MAX_POSES",
    "CLOUD_CHUNK",
    "MAX_ADAPTIVE_LEVEL",
    "MAX_APPROACH_STEPS",
    "MAX_CLOUD_FILE_BYTES",
    "MAX_CLOUD_VOXELS",
    "MAX_CSV_CELL",
    "MAX_GRASP_DISTANCE",
    "MAX_HDF5_TEXT",
    "MAX_IK_SOLUTIONS",
    "MAX_IK_WORKERS",
    "MAX_LENGTH",
    "MAX_OBSTACLES",
    "MAX_POINT_CLOUDS",
    "MAX_RANGE_STEPS",
    "MAX_STUDY_PLACEMENTS",
    "check_size",
    "lattice_size",
]

DEFAULT_MAX_CANDIDATES = 1_000_000
DEFAULT_MAX_POSES = 2_000_000
MAX_APPROACH_STEPS = 1_000
MAX_ADAPTIVE_LEVEL = 10
MAX_IK_WORKERS = 256
MAX_IK_SOLUTIONS = 16
#: Largest length or coordinate of a scene [m], and mesh scale.
MAX_LENGTH = 1_000.0
#: Farthest a grasp file's grasp may lie from the file's origin [m].
MAX_GRASP_DISTANCE = MAX_LENGTH
#: Most characters of one CSV cell (grasp files and ``grasps.csv``).
MAX_CSV_CELL = 256
#: Most bytes an HDF5 text value (a mesh file name, a gripper name) may declare.
MAX_HDF5_TEXT = 4096
#: Most ``environment.obstacles`` (each costs the collision checker about 4.5 MB).
MAX_OBSTACLES = 100
MAX_RANGE_STEPS = 1_000_000
#: Most ``environment.point_clouds``.
MAX_POINT_CLOUDS = 16
#: Points (or depth pixels) read and voxelised at a time.
CLOUD_CHUNK = 1 << 20
#: Most occupied (voxel, segment) rows of one cloud (about 40 bytes each).
MAX_CLOUD_VOXELS = 20_000_000
#: Largest cloud file read whole (``.ply`` through trimesh, a pickled ``.npy`` dict) [bytes].
MAX_CLOUD_FILE_BYTES = 1 << 30
MAX_STUDY_PLACEMENTS = 1_000_000


def check_size(estimate: int, limit: int, what: str, key: str, hint: str = "") -> None:
    """Refuse work whose estimated size is above a ceiling.

    Args:
        estimate: The estimated count (poses, grasps, rows).
        limit: The ceiling (the value of ``key``).
        what: What is counted, e.g. ``"densify: 1 triangle x (30001 x 30002 / 2) points"``.
        key: The config key holding ``limit``.
        hint: What else lowers the estimate, e.g. ``"lower densify.subdivisions or "``.

    Raises:
        ConfigError: ``<what>: <estimate> ... above <key> (<limit>); <hint>raise <key> ...``.
    """
    if estimate > limit:
        raise ConfigError(
            f"{what}: {estimate:,} is above {key} ({limit:,}); {hint}raise {key} to allow it"
        )


def lattice_size(subdivisions: np.ndarray) -> int:
    """Upper bound of the lattice points of triangles with ``n`` subdivisions each.

    Args:
        subdivisions: (T,) subdivisions per triangle.

    Returns:
        ``sum((n + 1)(n + 2) / 2)`` (capped at 2**62): points shared by
        neighbouring triangles are counted once per triangle.
    """
    n = np.asarray(subdivisions, dtype=np.float64).reshape(-1)
    total = float(np.sum((n + 1.0) * (n + 2.0) / 2.0))  # float: no int64 overflow
    return int(min(total, 2.0**62))
