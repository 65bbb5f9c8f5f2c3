"""Densify stage: lattice counts, shared points once, provenance, smooth blends, errors."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from gcm_pipeline.errors import GeometryError, InputError
from gcm_pipeline.geometry.dualquat import (
    dq_angle_distance,
    dq_distance,
    dq_from_pos_quat,
    dq_to_matrix,
    dq_translation,
)
from gcm_pipeline.geometry.pose_blend import dib, dlb, sclerp
from gcm_pipeline.manifold.build import Manifold, build_manifold
from gcm_pipeline.manifold.densify import _points_general, _points_uniform, densify
from gcm_pipeline.table import GraspTable

IDENT = np.array([1.0, 0.0, 0.0, 0.0])


def quats(rotvecs: np.ndarray) -> np.ndarray:
    xyzw = Rotation.from_rotvec(rotvecs).as_quat()
    return np.column_stack((xyzw[:, 3], xyzw[:, :3]))


def triangle_table(angle_deg: float = 10.0, seed: int = 0) -> GraspTable:
    rng = np.random.default_rng(seed)
    pos = np.array([[0.0, 0.0, 0.1], [0.1, 0.0, 0.1], [0.03, 0.08, 0.1]])
    rv = rng.normal(size=(3, 3))
    rv *= np.deg2rad(angle_deg) / np.linalg.norm(rv, axis=1, keepdims=True)
    return GraspTable({"dq": dq_from_pos_quat(pos, quats(rv))})


def square_table() -> GraspTable:
    pos = np.array([[0.0, 0.0, 0.0], [0.1, 0.0, 0.0], [0.0, 0.1, 0.0], [0.1, 0.1, 0.02]])
    return GraspTable({"dq": dq_from_pos_quat(pos, quats(np.deg2rad(5) * np.eye(4)[:, :3]))})


def random_table(n: int = 60, seed: int = 1) -> GraspTable:
    rng = np.random.default_rng(seed)
    pos = np.column_stack((rng.random((n, 2)) * 0.3, rng.normal(scale=0.01, size=n)))
    return GraspTable({"dq": dq_from_pos_quat(pos, quats(rng.normal(scale=0.2, size=(n, 3))))})


def unique_positions(dq: np.ndarray) -> int:
    return len(np.unique(np.round(dq_translation(dq), 12), axis=0))


# ----------------------------------------------------------------------------- counts
@pytest.mark.parametrize("n", [1, 2, 3, 4, 7])
def test_single_triangle_gives_the_full_lattice(n):
    g = triangle_table()
    out = densify(g, build_manifold(g), subdivisions=n)
    assert len(out) == (n + 1) * (n + 2) // 2
    assert unique_positions(out["dq"]) == len(out)


@pytest.mark.parametrize("n", [1, 2, 3, 5])
def test_shared_edge_points_appear_once(n):
    g = square_table()
    m = build_manifold(g)
    assert len(m.triangles) == 2
    out = densify(g, m, subdivisions=n)
    # 4 vertices, 5 edges with n - 1 points each, 2 interiors
    assert len(out) == 4 + 5 * (n - 1) + 2 * (n - 1) * (n - 2) // 2
    assert unique_positions(out["dq"]) == len(out)


def test_many_triangles_no_duplicates_and_euler_count():
    g = random_table(80)
    m = build_manifold(g)
    n = 4
    out = densify(g, m, subdivisions=n)
    tris = m.triangles
    edges = np.unique(
        np.sort(np.concatenate([tris[:, [0, 1]], tris[:, [1, 2]], tris[:, [2, 0]]]), 1), axis=0
    )
    expected = len(g) + len(edges) * (n - 1) + len(tris) * (n - 1) * (n - 2) // 2
    assert len(out) == expected
    assert unique_positions(out["dq"]) == expected


def test_spacing_chooses_n_from_the_longest_edge():
    g = triangle_table()
    p = dq_translation(g["dq"])
    longest = np.linalg.norm(p - np.roll(p, 1, axis=0), axis=1).max()
    out = densify(g, build_manifold(g), spacing=longest / 4)
    assert len(out) == 15  # n = 4
    out = densify(g, build_manifold(g), spacing=longest / 4 * 1.01)
    assert len(out) == 15  # ceil(3.96) = 4
    out = densify(g, build_manifold(g), spacing=1.0, subdivisions=None)
    assert len(out) == 3  # n = 1: the vertices only


def test_spacing_with_different_n_per_triangle_keeps_shared_points_once():
    pos = np.array([[0.0, 0.0, 0.0], [0.0, 0.1, 0.0], [-0.05, 0.05, 0.0], [0.4, 0.05, 0.0]])
    g = GraspTable({"dq": dq_from_pos_quat(pos, IDENT)})
    m = build_manifold(g)
    assert len(m.triangles) == 2
    out = densify(g, m, spacing=0.05)
    assert unique_positions(out["dq"]) == len(out)
    # Small triangle: n = 2 (its longest edge is 0.1); big one: n = 9 (longest 0.4031).
    # The shared edge (0.1 long) has the midpoint from both; the big triangle's
    # other points on it (fractions k/9) are its own.
    small, big = 2, 9
    expected = 4 + (3 * (small - 1) + (small - 1) * (small - 2) // 2)
    expected += 3 * (big - 1) + (big - 1) * (big - 2) // 2
    shared_common = 0  # 1/2 is not a multiple of 1/9
    assert len(out) == expected - shared_common


def test_uniform_and_general_dedup_agree():
    g = random_table(50)
    tris = build_manifold(g).triangles
    for n in (1, 2, 3, 6):
        a = _points_uniform(tris, n)
        b = _points_general(tris, np.full(len(tris), n))
        for x, y in zip(a, b, strict=True):
            np.testing.assert_array_equal(x, y)


def test_general_dedup_with_commensurate_subdivisions():
    """n = 2 and n = 4 on a shared edge share its midpoint (2/4 = 1/2)."""
    tris = np.array([[0, 1, 2], [1, 0, 3]])
    tri, ijk, n = _points_general(tris, np.array([2, 4]))
    # triangle 0 (n = 2): 3 edge midpoints;
    # triangle 1 (n = 4): 9 edge + 3 interior points, minus the shared midpoint
    assert (tri == 0).sum() == 3
    assert (tri == 1).sum() == 9 + 3 - 1


# ----------------------------------------------------------------------------- provenance
def test_candidates_first_bit_for_bit_then_interpolated_with_provenance():
    g = random_table(40)
    dq_in = g["dq"]
    m = build_manifold(g, max_edge_length=0.12)
    out = densify(g, m, subdivisions=3)
    n = len(g)
    assert out.columns[:5] == ("dq", "origin", "triangle", "vertices", "weights")
    np.testing.assert_array_equal(out["dq"][:n].view(np.uint64), dq_in.view(np.uint64))
    assert (out["origin"][:n] == "candidate").all()
    assert (out["origin"][n:] == "interpolated").all()
    assert (out["triangle"][:n] == -1).all()
    assert (out["vertices"][:n] == -1).all()
    assert np.isnan(out["weights"][:n]).all()
    tri = out["triangle"][n:]
    assert tri.min() >= 0 and tri.max() < len(m.triangles)
    assert (np.diff(tri) >= 0).all()  # ordered by triangle
    np.testing.assert_array_equal(out["vertices"][n:], m.triangles[tri])
    w = out["weights"][n:]
    np.testing.assert_allclose(w.sum(axis=1), 1.0, atol=1e-15)
    assert (w >= 0).all() and (w < 1).all()
    expected = dlb(dq_in[out["vertices"][n:]], w)
    np.testing.assert_allclose(out["dq"][n:], expected, atol=1e-15)


def test_unused_candidates_stay_in_the_table():
    g = random_table(30)
    m = build_manifold(g, max_edge_length=0.08)
    assert len(m.unused) > 0
    out = densify(g, m, subdivisions=2)
    assert (out["origin"] == "candidate").sum() == len(g)
    np.testing.assert_array_equal(out["dq"][m.unused], g["dq"][m.unused])


def test_no_kept_triangles_gives_only_the_candidates():
    g = triangle_table()
    m = build_manifold(g, max_edge_length=0.01)
    assert len(m.triangles) == 0
    out = densify(g, m, subdivisions=4)
    assert len(out) == 3 and out["weights"].shape == (3, 3) and out["vertices"].dtype == np.int64


def test_other_candidate_columns_are_carried_and_filled():
    g = triangle_table()
    g = g.with_columns(
        quality=np.array([0.1, 0.2, 0.3]), label=np.array(["a", "b", "c"]), ok=np.ones(3, bool)
    )
    out = densify(g, build_manifold(g), subdivisions=2)
    assert out.columns == (
        "dq",
        "origin",
        "triangle",
        "vertices",
        "weights",
        "quality",
        "label",
        "ok",
    )
    np.testing.assert_array_equal(out["quality"][:3], [0.1, 0.2, 0.3])
    assert np.isnan(out["quality"][3:]).all()  # not a known blend column: missing
    assert out["label"][3:].tolist() == [""] * 3
    assert not out["ok"][3:].any()


def test_score_and_width_are_blended_ids_are_missing():
    g = triangle_table()
    score = np.array([0.2, 0.5, 0.8])
    width = np.array([0.02, 0.04, np.nan])
    g = g.with_columns(score=score, width=width, source_id=np.array([7, 8, 9]))
    out = densify(g, build_manifold(g), subdivisions=4)
    inter = out["origin"] == "interpolated"
    w, v = out["weights"][inter], out["vertices"][inter]
    # hand-computed: the barycentric blend of the three vertex scores
    np.testing.assert_allclose(out["score"][inter], (w * score[v]).sum(axis=1))
    np.testing.assert_array_equal(out["score"][:3], score)
    # a NaN vertex value makes the blend NaN where its weight counts, not elsewhere
    uses_nan = ((v == 2) & (w > 0)).any(axis=1)
    assert np.isnan(out["width"][inter][uses_nan]).all()
    ok = np.where(v == 2, 0.0, w * np.nan_to_num(width[v]))
    np.testing.assert_allclose(out["width"][inter][~uses_nan], ok[~uses_nan].sum(axis=1))
    assert out["source_id"].dtype.kind == "i"
    assert (out["source_id"][inter] == -1).all()
    np.testing.assert_array_equal(out["source_id"][:3], [7, 8, 9])


# ----------------------------------------------------------------------------- the paper's intent
def _barycentric(pos: np.ndarray, verts: np.ndarray) -> np.ndarray:
    t = np.column_stack((verts[1] - verts[0], verts[2] - verts[0]))
    lam = np.linalg.lstsq(t, (pos - verts[0]).T, rcond=None)[0].T
    return np.column_stack((1 - lam.sum(1), lam))


def test_pure_translations_blend_linearly_inside_the_triangle():
    g = triangle_table(angle_deg=0.0)
    out = densify(g, build_manifold(g), subdivisions=10)
    verts = dq_translation(g["dq"])
    pos = dq_translation(out["dq"])
    assert (_barycentric(pos, verts) >= -1e-12).all()
    w = out["weights"][3:]
    np.testing.assert_allclose(pos[3:], w @ verts[out["vertices"][3]], atol=1e-15)


@pytest.mark.parametrize("angle_deg", [2.0, 8.0, 20.0])
def test_small_rotations_stay_inside_the_triangle_up_to_the_screw_bend(angle_deg):
    """DLB follows screw motions, not straight lines (the paper's known problem 3).

    The blended positions leave the triangle by at most a fraction of the
    relative rotation angle [rad] times the triangle size, and the vertices
    are the candidates themselves.
    """
    g = triangle_table(angle_deg=angle_deg)
    out = densify(g, build_manifold(g), subdivisions=10)
    verts = dq_translation(g["dq"])
    rel = dq_angle_distance(g["dq"][[0, 1, 2]], g["dq"][[1, 2, 0]]).max()
    bary = _barycentric(dq_translation(out["dq"]), verts)
    assert bary.min() >= -0.2 * rel
    np.testing.assert_array_equal(out["dq"][:3], g["dq"])
    # the lattice corners (one-hot weights) would give the vertices exactly
    np.testing.assert_allclose(dlb(g["dq"], np.eye(3)), g["dq"], atol=1e-15)


def test_continuity_along_shared_edges():
    g = square_table()
    m = build_manifold(g)
    out = densify(g, m, subdivisions=6)
    n = len(g)
    shared = set(m.triangles[0].tolist()) & set(m.triangles[1].tolist())
    a, b = sorted(shared)
    rows = np.flatnonzero((out["weights"][n:] == 0).any(axis=1)) + n
    for r in rows:
        verts = out["vertices"][r]
        w = out["weights"][r]
        if set(verts[w > 0].tolist()) != {a, b}:
            continue
        other = 1 - out["triangle"][r]
        ov = m.triangles[other]
        ow = np.array([w[verts.tolist().index(v)] if v in (a, b) else 0.0 for v in ov])
        recomputed = dlb(g["dq"][ov], ow)
        np.testing.assert_allclose(dq_to_matrix(recomputed), dq_to_matrix(out["dq"][r]), atol=1e-14)


def test_interior_is_smooth():
    g = triangle_table(angle_deg=20.0)
    m = build_manifold(g)
    for n in (8, 16):
        out = densify(g, m, subdivisions=n)
        dq = out["dq"]
        # weights over the candidate ids 0, 1, 2 (candidates are one-hot)
        full = np.eye(3)[[0, 1, 2]]
        w = np.zeros((len(out) - 3, 3))
        np.put_along_axis(w, out["vertices"][3:], out["weights"][3:], axis=1)
        w = np.vstack((full, w))
        # lattice neighbours differ by one step 1/n in two weights
        diff = np.abs(w[:, None] - w[None]).sum(2)
        i, j = np.nonzero(np.triu(np.isclose(diff, 2.0 / n)))
        assert len(i) == 3 * n * (n + 1) // 2
        d, ang = dq_distance(dq[i], dq[j])
        assert d.max() < 0.15 / n and ang.max() < np.deg2rad(40) / n


def test_dib_method_matches_sclerp_on_edges_and_dlb_nearby():
    g = triangle_table(angle_deg=15.0)
    m = build_manifold(g)
    out_dib = densify(g, m, subdivisions=4, method="dib")
    out_dlb = densify(g, m, subdivisions=4)
    assert len(out_dib) == len(out_dlb)
    np.testing.assert_array_equal(out_dib["weights"], out_dlb["weights"])
    d, ang = dq_distance(out_dib["dq"], out_dlb["dq"])
    assert d.max() < 1e-3 and ang.max() < 1e-3
    n = len(g)
    w = out_dib["weights"][n:]
    on_edge = (w == 0).any(axis=1)
    for r in np.flatnonzero(on_edge) + n:
        verts, wr = out_dib["vertices"][r], out_dib["weights"][r]
        (i, j) = np.flatnonzero(wr > 0)
        ref = sclerp(g["dq"][verts[i]], g["dq"][verts[j]], wr[j])
        assert dq_angle_distance(ref, out_dib["dq"][r]) < 1e-9
        np.testing.assert_allclose(
            dq_translation(ref), dq_translation(out_dib["dq"][r]), atol=1e-12
        )
    np.testing.assert_allclose(
        out_dib["dq"][n:], dib(g["dq"][out_dib["vertices"][n:]], w), atol=1e-12
    )


def test_works_with_any_object_having_triangles():
    g = square_table()
    stored = Manifold(
        chart=np.zeros((4, 2)),
        triangles=np.array([[0, 1, 2]]),
        dropped=np.zeros((0, 3), dtype=np.int64),
        dropped_reason=np.zeros(0, dtype=str),
        projection="xy",
    )
    assert len(densify(g, stored, subdivisions=2)) == 4 + 3


# ----------------------------------------------------------------------------- errors
@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"subdivisions": 0}, r"subdivisions must be an integer >= 1, got 0"),
        ({"subdivisions": 2.5}, r"subdivisions must be an integer >= 1, got 2.5"),
        ({"subdivisions": True}, r"subdivisions must be an integer >= 1, got True"),
        ({"subdivisions": None}, r"needs subdivisions or spacing, got neither"),
        ({"spacing": -0.01}, r"spacing must be a positive length \[m\], got -0.01"),
        ({"spacing": 1e-9}, r"asks for 106,301,459 subdivisions of a triangle \(max 32,768\)"),
        ({"spacing": 1e-300}, r"asks for 1.06e\+299 subdivisions"),  # no int64 overflow
        ({"method": "slerp"}, r"unknown densify method 'slerp'; valid: dib, dlb"),
    ],
)
def test_errors(kwargs, message):
    g = triangle_table()
    with pytest.raises(GeometryError, match=message):
        densify(g, build_manifold(g), **kwargs)


def test_error_triangles_out_of_range():
    g = triangle_table()
    bad = Manifold(
        chart=np.zeros((3, 2)),
        triangles=np.array([[0, 1, 5]]),
        dropped=np.zeros((0, 3), dtype=np.int64),
        dropped_reason=np.zeros(0, dtype=str),
        projection="xy",
    )
    with pytest.raises(
        GeometryError, match=r"manifold triangle 0 \[0, 1, 5\] indexes a candidate outside 0..2"
    ):
        densify(g, bad)


def test_error_missing_dq_and_bad_poses():
    with pytest.raises(InputError, match=r"no column 'dq'"):
        densify(GraspTable({"x": np.zeros(3)}), build_manifold(triangle_table()))
    g = triangle_table()
    dq = g["dq"].copy()
    dq[1, 0] = np.inf
    with pytest.raises(GeometryError, match=r"non-finite values at row 1"):
        densify(GraspTable({"dq": dq}), build_manifold(g))
