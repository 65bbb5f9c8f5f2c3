"""The grasp table: equal-length NumPy columns keyed by name.

One table flows through the stages. Each stage reads the columns it needs and
returns a new table with its own columns added; the arrays of the columns it
did not touch are shared, never copied, and no stage turns the poses into
per-grasp Python objects.

Columns: :data:`COLUMNS` names each with its dtype, shape, unit, the stage
that adds it, its meaning and the ``grasps.csv`` cells it is written as (the
CSV's column order, its reader and the run-directory reference of the docs
are generated from it).

Per-candidate columns: a candidate source (an importer, the antipodal
sampler) may add more 1-D columns to the candidate table, such as a
synthesiser's ``score``, the finger opening ``width`` or the ``source_id``
(row in the grasp file) of each candidate. They flow through every stage:
densify keeps them for the candidate rows and fills them for the
interpolated rows by the rule :data:`CANDIDATE_COLUMNS` gives (see
:func:`candidate_fill`), and ``grasps.csv`` writes them after the documented
columns and the metric columns.
"""

from __future__ import annotations

from collections.abc import Iterator, Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np
import numpy.typing as npt

from gcm_pipeline.errors import InputError

__all__ = ["CANDIDATE_COLUMNS", "COLUMNS", "FILL_RULES", "Column", "GraspTable", "candidate_fill"]


@dataclass(frozen=True)
class Column:
    """One documented column of the grasp table.

    Attributes:
        dtype: Kind of the values: ``float``, ``int``, ``bool`` or ``str``.
        shape: Array shape, N rows (``nq``: joints, ``K``: ``ik.solutions``).
        unit: Unit of the values (``""`` for none).
        stage: The stage that adds the column.
        meaning: What a value says.
        csv: The cells ``grasps.csv`` writes it as among its leading columns,
            in order (``q{j}``: one cell per joint, ``q1`` .. ``q{nq}``). Empty:
            a 1-D column is written after them (with the further metric
            columns), a wider one not at all.
    """

    dtype: str
    shape: str
    unit: str
    stage: str
    meaning: str
    csv: tuple[str, ...] = ()


#: The grasp table's columns: the single source of ``grasps.csv``'s leading columns
#: (the ``csv`` cells, in this order; :mod:`gcm_pipeline.rundir.grasps_csv` writes
#: and reads them by ``dtype``) and of the run-directory reference
#: (``scripts/gen_docs.py`` renders it into ``docs/run-directory.md``). The columns
#: ``grasps.csv`` leads with come first, the others follow in the order a run adds
#: them. Per-candidate columns of a source are listed in :data:`CANDIDATE_COLUMNS`.
COLUMNS: dict[str, Column] = {
    "rank": Column(
        "int", "(N,)", "", "ranking", "1 = best among the reachable, 0 = unreachable", csv=("rank",)
    ),
    "origin": Column(
        "str", "(N,)", "", "densify", "`candidate` or `interpolated`", csv=("origin",)
    ),
    "triangle": Column(
        "int",
        "(N,)",
        "",
        "densify",
        "provenance: the manifold triangle of the row (-1 for candidates)",
        csv=("triangle",),
    ),
    "vertices": Column(
        "int",
        "(N, 3)",
        "",
        "densify",
        "provenance: the triangle's three candidate rows (-1 for candidates)",
        csv=("v1", "v2", "v3"),
    ),
    "weights": Column(
        "float",
        "(N, 3)",
        "",
        "densify",
        "provenance: barycentric weights of the blend (NaN for candidates)",
        csv=("w1", "w2", "w3"),
    ),
    "dq": Column(
        "float",
        "(N, 8)",
        "",
        "candidates, densify",
        "unit dual quaternion of the grasp frame in the world",
        csv=("x", "y", "z", "qw", "qx", "qy", "qz"),
    ),
    "reachable": Column(
        "bool",
        "(N,)",
        "",
        "reachability",
        "an IK solution that passes every check exists",
        csv=("reachable",),
    ),
    "reason": Column(
        "str",
        "(N,)",
        "",
        "reachability",
        "`''` or why not: `out_of_reach`, `no_ik`, `joint_limits`, `collision_self`, "
        "`collision_environment`, `collision_object`, `approach`, `retreat`",
        csv=("reason",),
    ),
    "pos_err": Column(
        "float", "(N,)", "m", "reachability", "verified position error of `q`", csv=("pos_err",)
    ),
    "rot_err": Column(
        "float",
        "(N,)",
        "rad",
        "reachability",
        "verified orientation error of `q`",
        csv=("rot_err",),
    ),
    "manipulability": Column(
        "float",
        "(N,)",
        "",
        "ranking",
        "Yoshikawa index (6-D grasp-frame Jacobian)",
        csv=("manipulability",),
    ),
    "q": Column(
        "float", "(N, nq)", "rad", "reachability", "IK solution (NaN if none)", csv=("q{j}",)
    ),
    "level": Column(
        "int",
        "(N,)",
        "",
        "densify (adaptive)",
        "adaptive densification only: refinement level of the row (0 = candidate)",
    ),
    "q_pregrasp": Column(
        "float",
        "(N, nq)",
        "rad",
        "reachability",
        "configuration at the pre-grasp, the start of the approach (NaN where none)",
    ),
    "q_retreat": Column(
        "float",
        "(N, nq)",
        "rad",
        "reachability",
        "configuration at the end of the retreat (NaN where none)",
    ),
    "q_rejected": Column(
        "float",
        "(N, nq)",
        "rad",
        "reachability",
        "for an unreachable grasp that had an IK solution: the solution that "
        "collided or whose approach or retreat failed (NaN where none)",
    ),
    "clearance": Column(
        "float",
        "(N,)",
        "m",
        "reachability",
        "minimum distance of the arm to table, obstacles and object (at most 1 mm above it)",
    ),
    "solutions": Column(
        "float",
        "(N, K, nq)",
        "rad",
        "reachability (`ik.solutions` > 1)",
        "every kept IK branch of the grasp (NaN where fewer)",
    ),
    "solutions_q_pregrasp": Column(
        "float",
        "(N, K, nq)",
        "rad",
        "reachability (`ik.solutions` > 1)",
        "pre-grasp configuration of each kept branch",
    ),
    "solutions_q_retreat": Column(
        "float",
        "(N, K, nq)",
        "rad",
        "reachability (`ik.solutions` > 1)",
        "end of the retreat of each kept branch",
    ),
    "solutions_clearance": Column(
        "float", "(N, K)", "m", "reachability (`ik.solutions` > 1)", "clearance of each kept branch"
    ),
    "n_solutions": Column(
        "int", "(N,)", "", "reachability (`ik.solutions` > 1)", "IK branches kept"
    ),
    "solution": Column(
        "int",
        "(N,)",
        "",
        "reachability (`ik.solutions` > 1)",
        "which kept branch `q` is (-1 = unreachable)",
    ),
    "ik_jump": Column(
        "float",
        "(N,)",
        "rad",
        "continuity",
        "largest joint jump (L-infinity) to the reachable neighbours on the manifold",
    ),
    "patch": Column(
        "int", "(N,)", "", "continuity", "IK-branch patch id (0 = largest, -1 = unreachable)"
    ),
    "margin": Column(
        "float",
        "(N,)",
        "m",
        "continuity",
        "distance along the manifold to the nearest unreachable point "
        "(0 at the boundary and beyond and on a candidate in no triangle, `inf` if none)",
    ),
    "manip_translation": Column(
        "float", "(N,)", "", "ranking", "translational Yoshikawa index (3 rows)"
    ),
    "inverse_condition": Column(
        "float", "(N,)", "", "ranking", "inverse condition number of the Jacobian"
    ),
    "joint_limit_margin": Column(
        "float", "(N,)", "", "ranking", "normalised distance to the joint limits"
    ),
    "combined": Column(
        "float",
        "(N,)",
        "",
        "ranking (`metric: combined`)",
        "weighted sum of the min-max normalised metrics",
    ),
    "top": Column("bool", "(N,)", "", "ranking", "among the `ranking.top_k` best"),
}

#: How densify fills a per-candidate column for the interpolated rows.
#: ``blend``: the barycentric blend ``sum_j w_j * value[v_j]`` of the three
#: vertices' values (float columns; NaN if a vertex value is NaN);
#: ``missing``: the dtype's missing value (NaN for floats, -1 for signed
#: integers, 0 for unsigned, False for booleans, ``""`` for strings).
FILL_RULES = ("blend", "missing")

#: Known per-candidate columns and their fill rule (any other extra column is
#: filled with ``missing``). ``score``: the source's grasp quality (the
#: synthesiser's confidence or score, the sampler's antipodal quality), ``width``:
#: finger opening [m]; ids name the candidate's origin and are not blended;
#: ``contact_x``, ``contact_y``, ``contact_z``: the synthesiser's contact point
#: in the world [m] (Contact-GraspNet's ``contact_pts``), none for a blend.
CANDIDATE_COLUMNS: dict[str, str] = {
    "score": "blend",
    "width": "blend",
    "id": "missing",
    "source_id": "missing",
    "object_id": "missing",
    "segment": "missing",
    "success": "missing",
    "contact_x": "missing",
    "contact_y": "missing",
    "contact_z": "missing",
}


def candidate_fill(name: str) -> str:
    """The fill rule (one of :data:`FILL_RULES`) of a per-candidate column ``name``."""
    return CANDIDATE_COLUMNS.get(name, "missing")


class GraspTable:
    """Named columns (NumPy arrays, read-only) of equal length N; ``len(table) == N``.

    Args:
        columns: Column name to array-like; every array's first axis has the
            same length N.

    Raises:
        InputError: If the columns differ in length or one is a scalar.
    """

    __slots__ = ("_cols", "_n")

    def __init__(self, columns: Mapping[str, npt.ArrayLike] | None = None) -> None:
        cols: dict[str, np.ndarray] = {}
        n: int | None = None
        for name, values in (columns or {}).items():
            arr = np.asarray(values)
            if arr.ndim == 0:
                raise InputError(f"grasp table column {name!r} must be an array, got a scalar")
            if n is None:
                n = arr.shape[0]
            elif arr.shape[0] != n:
                raise InputError(
                    f"grasp table column {name!r} has {arr.shape[0]} rows, expected {n}"
                )
            arr.setflags(write=False)
            cols[name] = arr
        self._cols = cols
        self._n = 0 if n is None else n

    def __getitem__(self, name: str) -> np.ndarray:
        try:
            return self._cols[name]
        except KeyError:
            raise KeyError(
                f"grasp table has no column {name!r}; columns: {', '.join(self._cols)}"
            ) from None

    def __contains__(self, name: object) -> bool:
        return name in self._cols

    def __iter__(self) -> Iterator[str]:
        """Iterate over column names."""
        return iter(self._cols)

    def __len__(self) -> int:
        """Number of grasps (rows) N."""
        return self._n

    def get(self, name: str, default: Any = None) -> Any:
        """Return column ``name`` or ``default`` when the table lacks it."""
        return self._cols.get(name, default)

    @property
    def columns(self) -> tuple[str, ...]:
        """Column names in insertion order."""
        return tuple(self._cols)

    def with_columns(self, **new: npt.ArrayLike) -> GraspTable:
        """Return a table with ``new`` columns added or replaced.

        Arrays of the other columns are shared, not copied.
        """
        merged: dict[str, Any] = dict(self._cols)
        merged.update(new)
        out = GraspTable(merged)
        if self._cols and out._n != self._n:
            raise InputError(f"new columns have {out._n} rows, table has {self._n}")
        return out

    def take(self, index: npt.ArrayLike) -> GraspTable:
        """Return the rows selected by an integer index or boolean mask."""
        idx = np.asarray(index)
        return GraspTable({k: v[idx] for k, v in self._cols.items()})

    def __repr__(self) -> str:
        cols = ", ".join(f"{k}{tuple(v.shape[1:]) or ''}" for k, v in self._cols.items())
        return f"GraspTable({self._n} rows: {cols})"
