"""The ``families`` manifold structure: membership, locality, defaults, errors, downstream."""

from __future__ import annotations

import numpy as np
import pytest
from helpers import ROOT, assert_one_line_error
from scipy.spatial.transform import Rotation

import gcm_pipeline as gcm
from gcm_pipeline.cli import main
from gcm_pipeline.errors import GeometryError, InputError
from gcm_pipeline.geometry.dualquat import (
    dq_angle_distance,
    dq_from_pos_quat,
    dq_mul,
    dq_translation,
)
from gcm_pipeline.geometry.pose_metric import other_sign_features, pose_distance
from gcm_pipeline.manifold.build import build_manifold
from gcm_pipeline.manifold.families import ANGLE_FACTOR, LENGTH_FACTOR, family_triangles
from gcm_pipeline.outputs.plots import candidate_coverage, plot_coverage
from gcm_pipeline.rundir.arrays import read_manifold, write_manifold
from gcm_pipeline.table import GraspTable

BOX = ROOT / "configs" / "box.yaml"
LENGTH, ANGLE = 0.03, 40.0


def face_grasps(seed: int = 0, per_face: int = 60) -> tuple[np.ndarray, np.ndarray]:
    """Grasps on the six faces of a 10 cm cube (approach along the inward normal).

    Per face: random tool points on the face, yaw about the approach within
    +-15 deg; a fan of 8 orientations at one point of face 0; a few stray
    grasps (a lone one, a lone pair). Returns the
    poses (N, 8) and the face of each grasp (the family it must belong to).
    """
    rng = np.random.default_rng(seed)
    normals = np.array([[1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1]], float)
    dq, face = [], []
    for f, n in enumerate(normals):
        base = Rotation.align_vectors([-n], [[0.0, 0.0, 1.0]])[0]  # tool z = -n (into the cube)
        u = np.cross(n, [0.3, 0.5, 0.7])
        u /= np.linalg.norm(u)
        v = np.cross(n, u)
        s, t = rng.uniform(-0.04, 0.04, (2, per_face))
        pos = 0.5 * np.array([0.5, 0.0, 0.3]) + 0.05 * n + s[:, None] * u + t[:, None] * v
        yaw = Rotation.from_euler("z", rng.uniform(-15, 15, (per_face, 1)), degrees=True)
        xyzw = (base * yaw).as_quat()
        dq.append(dq_from_pos_quat(pos, np.column_stack((xyzw[:, 3], xyzw[:, :3]))))
        face += [f] * per_face
    # a fan: many orientations at one position (the paper's known problem 1)
    fan = Rotation.from_euler("z", np.arange(-14.0, 15.0, 4.0)[:, None], degrees=True)
    xyzw = (Rotation.align_vectors([-normals[0]], [[0.0, 0.0, 1.0]])[0] * fan).as_quat()
    centre = np.repeat([0.5 * np.array([0.5, 0.0, 0.3]) + 0.05 * normals[0]], len(xyzw), axis=0)
    dq.append(dq_from_pos_quat(centre, np.column_stack((xyzw[:, 3], xyzw[:, :3]))))
    face += [0] * len(xyzw)
    dq = np.concatenate(dq)
    lone = dq[:1].copy()
    lone[:, 4:] = dq_from_pos_quat(dq_translation(dq[:1]) + [0, 0, 1.0], dq[:1, :4])[:, 4:]
    pair = np.concatenate([dq[:1], dq[:1]])
    pair[:, 4:] = dq_from_pos_quat(
        dq_translation(dq[:1]) + [[0, 0, -1.0], [0.01, 0, -1.0]], dq[:1, :4]
    )[:, 4:]
    return np.concatenate((dq, lone, pair)), np.array(face + [6, 7, 7])


def neighbours(dq: np.ndarray, length: float, angle_deg: float) -> np.ndarray:
    """(N, N) brute-force neighbour matrix under both bounds (no self-pairs)."""
    p = dq_translation(dq)
    near = np.linalg.norm(p[:, None] - p[None], axis=2) <= length
    near &= dq_angle_distance(dq[:, None], dq[None]) <= np.deg2rad(angle_deg)
    np.fill_diagonal(near, False)
    return near


def linkable(near: np.ndarray) -> np.ndarray:
    """Rows in some triple pairwise within the bounds (brute force)."""
    nn = near.astype(np.int64)
    return np.diag(nn @ nn @ nn) > 0  # a triangle through the row in the neighbour graph


@pytest.fixture(scope="module")
def faces() -> dict[str, object]:
    dq, face = face_grasps()
    m = build_manifold(
        GraspTable({"dq": dq}),
        structure="families",
        max_edge_length=LENGTH,
        max_edge_angle_deg=ANGLE,
    )
    return {"dq": dq, "face": face, "m": m, "near": neighbours(dq, LENGTH, ANGLE)}


def test_every_linkable_candidate_is_in_a_triangle(faces: dict) -> None:
    dq, m, near = faces["dq"], faces["m"], faces["near"]
    used = np.zeros(len(dq), dtype=bool)
    used[m.triangles.ravel()] = True
    link = linkable(near)
    assert link.sum() >= 6 * 50  # the faces are dense enough for most grasps
    assert np.array_equal(used, link)  # linkable <=> in a triangle
    # and each isolated candidate says why
    degree = near.sum(axis=1)
    assert np.array_equal(m.isolation == "", used)
    assert np.array_equal(m.isolation == "no_neighbour", degree == 0)
    assert np.array_equal(m.isolation == "no_triple", (degree > 0) & ~used)
    assert m.isolated_counts == {"no_neighbour": 1, "no_triple": int(((degree > 0) & ~used).sum())}


def test_every_triangle_is_within_the_bounds_and_inside_one_family(faces: dict) -> None:
    dq, m, face = faces["dq"], faces["m"], faces["face"]
    t = m.triangles
    assert len(t) > len(dq)  # a mesh, not one triangle per candidate
    p = dq_translation(dq)[t]
    q = dq[t]
    for a, b in ((0, 1), (1, 2), (2, 0)):
        assert np.linalg.norm(p[:, a] - p[:, b], axis=1).max() <= LENGTH
        assert dq_angle_distance(q[:, a], q[:, b]).max() <= np.deg2rad(ANGLE)
    # no triangle joins two faces of the cube, and the families are the faces
    assert np.all(face[t] == face[t[:, :1]])
    fam = m.family
    assert np.all(fam[t] == fam[t[:, :1]])
    for f in range(6):
        assert len(np.unique(fam[face == f])) == 1
    assert len(np.unique(fam[face < 6])) == 6
    assert len(np.unique(np.sort(t, axis=1), axis=0)) == len(t)  # each triangle once
    assert np.all(t[:, 0] != t[:, 1]) and np.all(t[:, 1] != t[:, 2]) and np.all(t[:, 0] != t[:, 2])


def test_families_are_deterministic(faces: dict) -> None:
    again = build_manifold(
        GraspTable({"dq": faces["dq"]}),
        structure="families",
        max_edge_length=LENGTH,
        max_edge_angle_deg=ANGLE,
    )
    m = faces["m"]
    for name in ("chart", "triangles", "dropped", "dropped_reason", "family", "isolation"):
        assert np.array_equal(getattr(m, name), getattr(again, name)), name


def test_unset_bounds_come_from_the_spacing(faces: dict) -> None:
    dq = faces["dq"][faces["face"] < 6]
    fm = family_triangles(dq, max_edge_length=None, max_edge_angle_deg=None, orientation_scale=0.1)
    d = pose_distance(dq[:, None], dq[None])
    np.fill_diagonal(d, np.inf)
    spacing = np.median(np.sort(d, axis=1)[:, 1])
    assert fm.max_edge_length == pytest.approx(LENGTH_FACTOR * spacing, rel=1e-9)
    angle = min(60.0, np.degrees(ANGLE_FACTOR * spacing / 0.1))
    assert fm.max_edge_angle_deg == pytest.approx(angle, rel=1e-9)
    used = np.zeros(len(dq), dtype=bool)
    used[fm.triangles.ravel()] = True
    assert np.array_equal(used, linkable(neighbours(dq, fm.max_edge_length, fm.max_edge_angle_deg)))


def test_manifold_npz_keeps_families_and_reasons(faces: dict, tmp_path) -> None:
    m = faces["m"]
    write_manifold(m, tmp_path / "manifold.npz")
    back = read_manifold(tmp_path / "manifold.npz")
    assert back.structure == "families" and back.projection == "families"
    assert np.array_equal(back.family, m.family)
    assert np.array_equal(back.isolation, m.isolation)
    assert np.array_equal(back.triangles, m.triangles)
    assert back.max_edge_length == LENGTH and back.max_edge_angle_deg == ANGLE
    arrays = dict(np.load(tmp_path / "manifold.npz"))
    arrays["family"] = arrays["family"][:-1]  # one value short
    np.savez(tmp_path / "bad.npz", **arrays)
    with pytest.raises(InputError, match="array 'family' must be"):
        read_manifold(tmp_path / "bad.npz")


def test_coverage_figure_says_linked_and_isolated(faces: dict, tmp_path) -> None:
    m = faces["m"]
    cover = candidate_coverage(m)
    reasons, counts = np.unique(cover[cover != "linked"], return_counts=True)
    assert dict(zip(reasons.tolist(), counts.tolist(), strict=True)) == m.isolated_counts
    assert (cover == "linked").sum() == len(np.unique(m.triangles))
    path = plot_coverage(GraspTable({"dq": faces["dq"]}), m, tmp_path / "coverage.png")
    assert path.stat().st_size > 10_000 and path.read_bytes()[:4] == b"\x89PNG"


def test_chart_structure_is_unchanged_and_a_projection_selects_it() -> None:
    cfg = gcm.load_config(ROOT / "configs" / "flat_surface.yaml")
    assert cfg.manifold.structure == "chart"
    m = gcm.build_manifold(gcm.generate_candidates(cfg), cfg)
    assert m.structure == "chart" and m.family is None and m.isolation is None
    assert m.triangles.tolist() == [[0, 1, 2]]  # the paper's Fig. 1: one triangle
    over = gcm.load_config(BOX, ["manifold={projection: spherical}"])
    assert over.manifold.structure == "chart"  # a projection alone keeps the chart
    assert gcm.load_config(BOX, ["manifold={}"]).manifold.structure == "families"
    dq, _ = face_grasps(per_face=20)
    tab = GraspTable({"dq": dq[:120]})
    a = build_manifold(tab, projection="pca", max_edge_length=0.05)
    b = build_manifold(tab, structure="chart", projection="pca", max_edge_length=0.05)
    assert np.array_equal(a.triangles, b.triangles) and np.array_equal(a.chart, b.chart)


def test_all_grasps_at_one_pose_and_two_grasps_are_one_line_errors(tmp_path, capsys) -> None:
    dq, _ = face_grasps(per_face=5)
    same = GraspTable({"dq": np.repeat(dq[:1], 10, axis=0)})
    with pytest.raises(GeometryError, match="fewer than 3 distinct poses"):
        build_manifold(same, structure="families")
    with pytest.raises(GeometryError, match="at least 3 grasp poses"):
        build_manifold(GraspTable({"dq": dq[:2]}), structure="families")
    two = GraspTable({"dq": np.concatenate((dq[:2], dq[:2], -dq[:2]))})  # 2 poses, 6 rows
    with pytest.raises(GeometryError, match="the 6 grasps have fewer than 3 distinct poses"):
        build_manifold(two, structure="families")
    # with bounds given, one pose is a defined manifold with no triangle
    m = build_manifold(same, structure="families", max_edge_length=0.01, max_edge_angle_deg=5)
    assert len(m.triangles) == 0 and m.isolation.tolist() == ["no_neighbour"] + ["duplicate"] * 9
    # and the CLI says so in one line
    poses = np.repeat(np.eye(4)[None], 10, axis=0)
    poses[:, :3, 3] = [0.5, 0.0, 0.1]
    np.save(tmp_path / "one.npy", poses)
    cfg = tmp_path / "one.yaml"
    cfg.write_text(
        "robot: {spec: panda}\n"
        f"candidates: {{source: file, path: {tmp_path / 'one.npy'}, format: npy}}\n"
        "publish: {html: false, plots: false}\n"
    )
    code = main(["run", str(cfg), "--out", str(tmp_path / "run"), "--quiet"])
    assert_one_line_error(code, capsys.readouterr().err, "fewer than 3 distinct poses")
    assert not (tmp_path / "run").exists()


def test_densify_adaptive_continuity_and_locate_on_families(tmp_path) -> None:
    over = [
        "publish.html=false",
        "publish.plots=false",
        "densify.adaptive={max_level: 2}",
        "continuity.reseed=true",
    ]
    cfg = gcm.load_config(ROOT / "configs" / "mug_antipodal.yaml", over)
    assert cfg.manifold.structure == "families"
    run = gcm.Pipeline(cfg).run(out_dir=tmp_path / "mug", progress=False)
    m, g = run.manifold, run.grasps
    assert m.structure == "families" and len(m.triangles) > len(m.family)
    inner = np.asarray(g["origin"]) == "interpolated"
    assert inner.sum() > len(m.triangles)  # every triangle densified (adaptive: level >= 1)
    corners = np.asarray(g["dq"])[: m.n_vertices][np.asarray(g["vertices"])[inner]]
    step = np.linalg.norm(
        dq_translation(np.asarray(g["dq"])[inner])[:, None] - dq_translation(corners), axis=2
    )
    assert step.min(axis=1).max() <= m.max_edge_length  # inside its triangle
    assert "patch" in g and "margin" in g and run.counts["continuity"]["patches"] >= 1
    assert run.counts["isolated_by_reason"] == m.isolated_counts
    assert run.counts["families"] == m.family.max() + 1
    gm = gcm.load_manifold(tmp_path / "mug")
    used = np.unique(m.triangles)
    loc = gm.locate(np.asarray(g["dq"])[used])
    assert np.all(loc.distance <= 1e-9)  # every linked candidate is a point of the manifold


def test_a_line_of_grasps_no_chart_can_triangulate_is_still_linked() -> None:
    # six grasps 1 cm apart on a line, one orientation: collinear in every
    # chart, yet every triple of consecutive grasps is within the bounds
    pos = np.column_stack((0.4 + 0.01 * np.arange(6), np.zeros(6), np.full(6, 0.1)))
    dq = dq_from_pos_quat(pos, np.tile([0.0, 1.0, 0.0, 0.0], (6, 1)))
    m = build_manifold(
        GraspTable({"dq": dq}), structure="families", max_edge_length=0.025, max_edge_angle_deg=5
    )
    assert sorted(np.unique(m.triangles).tolist()) == list(range(6))
    assert np.all(np.abs(np.diff(np.sort(m.triangles, axis=1), axis=1)) <= 2)  # neighbours only
    assert set(m.isolation.tolist()) == {""}


def test_a_lattice_set_on_the_bound_gives_the_same_structure_wherever_it_stands() -> None:
    """Grasps from above in exact 30-degree roll steps, with the angle bound at 30 degrees.

    Like ACRONYM's sets (orientations in exact steps), many pairs lie exactly on
    the bound. They are linked at any placement of the set in the world, so
    rounding (which moves with the placement and the CPU) does not decide the
    families or which candidates are linked.
    """
    down = Rotation.from_euler("x", 180, degrees=True)
    local = []
    for x in range(3):
        for y in range(3):
            for roll in (0.0, 30.0, 60.0):
                xyzw = (down * Rotation.from_euler("z", roll, degrees=True)).as_quat()
                pos = [0.01 * x, 0.01 * y, 0.1]
                local.append(dq_from_pos_quat(pos, np.r_[xyzw[3], xyzw[:3]]))
    local = np.asarray(local)
    rng = np.random.default_rng(7)
    for k in range(40):
        xyzw = Rotation.random(random_state=rng).as_quat() if k else np.array([0, 0, 0, 1.0])
        place = dq_from_pos_quat(
            rng.uniform(-1, 1, 3) if k else np.zeros(3), np.r_[xyzw[3], xyzw[:3]]
        )
        fm = family_triangles(
            dq_mul(place, local),
            max_edge_length=0.015,
            max_edge_angle_deg=30.0,
            orientation_scale=0.1,
        )
        assert fm.family.tolist() == [0] * len(local), k  # the roll layers link: one family
        assert fm.isolation.tolist() == [""] * len(local), k


def test_a_turned_and_moved_set_gives_the_same_triangles_in_the_same_order(faces: dict) -> None:
    """The triangles (and so the densified rows) of a grasp set do not depend on where it stands.

    A study compares one object's grasps row by row across placements.
    """
    dq, first = faces["dq"], faces["m"]
    rng = np.random.default_rng(11)
    for k in range(5):
        xyzw = Rotation.random(random_state=rng).as_quat()
        place = dq_from_pos_quat(rng.uniform(-1, 1, 3), np.r_[xyzw[3], xyzw[:3]])
        m = build_manifold(
            GraspTable({"dq": dq_mul(place, dq)}),
            structure="families",
            max_edge_length=LENGTH,
            max_edge_angle_deg=ANGLE,
        )
        np.testing.assert_array_equal(m.triangles, first.triangles, err_msg=str(k))
        np.testing.assert_array_equal(m.family, first.family, err_msg=str(k))


def _repeated(dq: np.ndarray, copies: int, seed: int = 1) -> tuple[np.ndarray, np.ndarray]:
    """``dq`` with each pose ``copies`` times in shuffled order, every third copy sign-flipped.

    Returns the rows and the first row of each pose, in the order of ``dq``'s poses' first
    appearance (ascending).
    """
    rng = np.random.default_rng(seed)
    pose = rng.permutation(np.repeat(np.arange(len(dq)), copies))
    rows = dq[pose].copy()
    rows[::3] *= -1.0  # q and -q are one pose
    _, first = np.unique(pose, return_index=True)
    return rows, np.sort(first)


@pytest.mark.parametrize("bounds", [(None, None), (LENGTH, ANGLE)])
def test_exact_duplicate_rows_get_what_the_distinct_poses_get(bounds) -> None:
    # 24 poses 2,000 times each: the neighbour search once ran on every copy (O(N^2) pairs
    # of identical rows, minutes), and the spacing skipped every row with 8 copies or more
    # (a false "fewer than 3 distinct poses"). Each pose now counts once.
    dq, _ = face_grasps(per_face=24)
    rows, first = _repeated(dq[:24], 2000)
    length, angle = bounds
    kw = {"max_edge_length": length, "max_edge_angle_deg": angle, "orientation_scale": 0.1}
    fm = family_triangles(rows, **kw)
    one = family_triangles(rows[first], **kw)
    assert len(one.triangles) >= 10 and (one.isolation == "").sum() >= 12  # a real mesh
    assert (fm.max_edge_length, fm.max_edge_angle_deg) == (
        one.max_edge_length,
        one.max_edge_angle_deg,
    )
    assert np.array_equal(fm.triangles, first[one.triangles])
    assert np.array_equal(fm.dropped, first[one.dropped])
    assert np.array_equal(fm.dropped_reason, one.dropped_reason)
    assert np.array_equal(fm.family[first], one.family)
    assert np.array_equal(fm.isolation[first], one.isolation)
    assert np.array_equal(fm.chart[first], one.chart)
    dup = np.ones(len(rows), dtype=bool)
    dup[first] = False
    assert np.all(fm.family[dup] == -1) and np.all(fm.isolation[dup] == "duplicate")
    assert np.all(fm.chart[dup] == 0.0)


@pytest.mark.parametrize("triangulator", ["qhull", "bowyer_watson"])
def test_exact_duplicate_rows_are_one_vertex_of_the_cylindrical_chart(triangulator) -> None:
    # the cylindrical chart's tie-breaking offsets once parted the copies of a pose: each copy
    # a vertex (a million rows, a million vertices for Bowyer-Watson), triangles among copies
    dq, _ = face_grasps(per_face=24)
    rows, first = _repeated(dq[:24], 500)
    m = build_manifold(
        GraspTable({"dq": rows}),
        structure="chart",
        projection="cylindrical",
        triangulator=triangulator,
        max_edge_length=0.03,
        frame=np.eye(4),
    )
    assert len(m.triangles) >= 10
    assert np.isin(m.triangles, first).all()  # only the first row of each pose
    pose = np.unique(np.abs(rows), axis=0, return_inverse=True)[1].reshape(-1)
    assert np.array_equal(m.chart, m.chart[first][np.argsort(pose[first])][pose])


def _query_pairs_reference(dq: np.ndarray, length: float, angle_deg: float, scale: float):
    """The neighbour search in one call (``query_pairs``), as it was before the blocks."""
    from scipy.spatial import cKDTree

    from gcm_pipeline.manifold import families as fam

    n = len(dq)
    feats = fam.pose_features(dq, scale)
    angle = np.deg2rad(angle_deg)
    radius = np.hypot(length, 4.0 * scale * np.sin(angle / 4.0)) * (1 + 1e-9) + 1e-12
    tree = cKDTree(np.concatenate((feats, other_sign_features(feats))))
    raw = tree.query_pairs(radius, output_type="ndarray") % n
    raw = raw[raw[:, 0] != raw[:, 1]].astype(np.int64)
    keys = np.unique(fam._pair_keys(raw[:, 0], raw[:, 1], n))
    pairs = np.column_stack((keys // n, keys % n))
    pos = dq_translation(dq)
    tie = 1.0 + fam.BOUND_TOLERANCE
    ok = np.linalg.norm(pos[pairs[:, 0]] - pos[pairs[:, 1]], axis=1) <= length * tie
    ok &= dq_angle_distance(dq[pairs[:, 0]], dq[pairs[:, 1]]) <= angle * tie
    pairs = pairs[ok].astype(np.int64)
    return keys, pairs, pose_distance(dq[pairs[:, 0]], dq[pairs[:, 1]], scale)


def _block_inputs() -> list[tuple[np.ndarray, float, float]]:
    """Grasp sets for the block tests: faces (a fan, near strays), a lattice on the bound,
    random poses with near-duplicates and sign-flipped rows."""
    rng = np.random.default_rng(3)
    down = Rotation.from_euler("x", 180, degrees=True)
    lattice = []
    for x in range(4):
        for y in range(4):
            for roll in (0.0, 30.0, 60.0, 90.0):
                xyzw = (down * Rotation.from_euler("z", roll, degrees=True)).as_quat()
                lattice.append(
                    dq_from_pos_quat([0.01 * x, 0.01 * y, 0.1], np.r_[xyzw[3], xyzw[:3]])
                )
    n = 600
    xyzw = Rotation.random(n, random_state=rng.integers(2**31)).as_quat()
    rand = dq_from_pos_quat(
        rng.uniform(-0.05, 0.05, (n, 3)), np.column_stack((xyzw[:, 3], xyzw[:, :3]))
    )
    rand[::7] *= -1.0  # the other sign of the same pose
    near = rand[:40] + rng.normal(0.0, 1e-12, (40, 8))  # near-duplicates, not exact repeats
    rand = np.concatenate((rand, near / np.linalg.norm(near[:, :4], axis=1, keepdims=True)))
    return [
        (face_grasps()[0], LENGTH, ANGLE),
        (np.asarray(lattice), 0.01, 30.0),
        (rand, 0.02, 35.0),
    ]


def test_the_neighbour_search_in_blocks_finds_the_pairs_of_one_search(monkeypatch) -> None:
    """The k-d tree is searched in blocks of rows (so a signal is handled between them):
    small blocks crossing every kind of input give the pairs, the order and the
    distances of the one-call search bit for bit, and the same raw pairs."""
    from gcm_pipeline.manifold import families as fam

    for dq, length, angle in _block_inputs():
        keys, ref_pairs, ref_dist = _query_pairs_reference(dq, length, angle, 0.1)
        for first, low, high, aim in ((3, 1, 7, 10), (1, 1, 1, 1), (50, 16, 64, 200)):
            monkeypatch.setattr(fam, "_FIRST_BLOCK", first)
            monkeypatch.setattr(fam, "_MIN_BLOCK", low)
            monkeypatch.setattr(fam, "_MAX_BLOCK", high)
            monkeypatch.setattr(fam, "_BLOCK_PAIRS", aim)
            pairs, dist = fam._neighbour_pairs(dq, length, angle, 0.1)
            assert pairs.dtype == ref_pairs.dtype and np.array_equal(pairs, ref_pairs)
            assert np.array_equal(dist, ref_dist)
            feats = fam.pose_features(dq, 0.1)
            tree = fam.cKDTree(np.concatenate((feats, other_sign_features(feats))))
            radius = np.hypot(length, 0.4 * np.sin(np.deg2rad(angle) / 4.0)) * (1 + 1e-9) + 1e-12
            blocks = list(fam._ball_pairs(tree, feats, radius))
            assert len(blocks) > 1
            assert np.array_equal(np.concatenate(blocks), keys)  # sorted, each pair once
        assert len(ref_pairs) > 50


def test_the_structure_is_the_same_whatever_the_block_sizes(monkeypatch) -> None:
    """The whole families structure, bounds derived, with tiny blocks: every array equal."""
    from gcm_pipeline.manifold import families as fam

    for dq, _, _ in _block_inputs():
        whole = family_triangles(
            dq, max_edge_length=None, max_edge_angle_deg=None, orientation_scale=0.1
        )
        monkeypatch.setattr(fam, "_QUERY_BLOCK", 7)
        monkeypatch.setattr(fam, "_FIRST_BLOCK", 5)
        monkeypatch.setattr(fam, "_MAX_BLOCK", 9)
        small = family_triangles(
            dq, max_edge_length=None, max_edge_angle_deg=None, orientation_scale=0.1
        )
        monkeypatch.undo()
        for name in whole.__dataclass_fields__:
            a, b = getattr(whole, name), getattr(small, name)
            assert np.array_equal(a, b), name
            assert np.asarray(a).dtype == np.asarray(b).dtype, name
