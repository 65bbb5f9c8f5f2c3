"""Paths and assertions shared by the tests (the fixtures are in ``conftest.py``)."""

from __future__ import annotations

import os
import re
import subprocess
import sys
from pathlib import Path
from typing import Any

#: The repository's root (this checkout, wherever a test file sits under ``tests/``).
ROOT = Path(__file__).resolve().parents[1]
CONFIGS = ROOT / "configs"
DATA = ROOT / "tests" / "data"
FLAT = CONFIGS / "flat_surface.yaml"
BOTTLE = CONFIGS / "bottle_side.yaml"
#: The robot specs shipped with the package (``load_robot("panda")`` reads panda.yaml).
ROBOT_SPECS = ROOT / "gcm_pipeline" / "robot" / "specs"
#: ``gcm run`` without the HTML scene and the plots (the slow part of a small run).
QUICK = ["--set", "publish.html=false", "--set", "publish.plots=false"]
#: Settings (``--set``) of a small bottle for studies: 2 rings of 9 candidates, 45 grasps
#: (about 0.4 s per placement).
SMALL_STUDY = [
    "candidates.count=18",
    "manifold.max_edge_length=0.15",
    "densify.subdivisions=2",
    "approach.steps=4",
    "publish.html=false",
    "publish.plots=false",
]


def random_rigid(rng: Any, reach: float = 0.2) -> Any:
    """A random rigid transform (4, 4): a uniform rotation, a translation within ``reach`` [m]."""
    import numpy as np

    rot, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    tf = np.eye(4)
    tf[:3, :3] = rot * np.sign(np.linalg.det(rot))
    tf[:3, 3] = rng.uniform(-reach, reach, 3)
    return tf


def triangle_corners(config: Path = BOTTLE) -> Any:
    """The corners (T, 3, 8) of every triangle of a config's manifold, as dual quaternions."""
    import numpy as np

    import gcm_pipeline as gcm

    cfg = gcm.load_config(config)
    cand = gcm.generate_candidates(cfg)
    mesh = gcm.build_manifold(cand, cfg)
    return np.asarray(cand["dq"])[mesh.triangles]


def complete_answers(gd: Any) -> Any:
    """``gd`` (a ``pin.GeometryData``) asking coal for its complete collision answer.

    Contact information on, so EPA runs whenever GJK finds contact. Pinocchio's
    default requests ask without it, and coal's ``collide`` then can call
    overlapping geometry free where GJK ends within its tolerance of the origin
    (overlapping cylinders came back free 0.58 mm deep, see
    ``tests/robot/collision/test_near_contact.py``). An independent reference
    (``pin.computeCollisions`` over every pair) prepares its data with this; it
    shares nothing with the checker's own requests. It may differ from the
    checker within about a micrometre of contact: the checker counts geometry
    within 1e-6 m as touching, coal's complete answer called some pairs
    1.0-1.4e-6 m apart colliding (with zero depth).
    """
    for req in gd.collisionRequests:
        req.enable_contact = True
    return gd


def assert_one_line_error(code: int, err: str, *fragments: str, warnings: bool = False) -> str:
    """The error contract of ``gcm``: exit 2, one line ``error: ...`` on stderr, no traceback.

    Args:
        code: The command's exit status.
        err: What it wrote to stderr.
        *fragments: Texts the error line must contain (the key, file, value, choices).
        warnings: Allow ``WARNING ...`` log lines before the error line.

    Returns:
        The error line.
    """
    assert code == 2, err
    assert "Traceback" not in err, err
    lines = err.splitlines()
    if warnings:
        lines = [ln for ln in lines if not ln.startswith("WARNING")]
    assert len(lines) == 1 and lines[0].startswith("error: ") and err.endswith("\n"), err
    assert len(lines[0]) <= 2000, len(lines[0])
    for f in fragments:
        assert f in lines[0], (f, lines[0])
    return lines[0]


def gcm_env(**extra: str) -> dict[str, str]:
    """This process's environment for a subprocess that imports this checkout's package."""
    return {**os.environ, "PYTHONPATH": str(ROOT), **extra}


def run_gcm(
    *argv: object,
    env: dict[str, str] | None = None,
    cwd: Path | None = None,
    timeout: float | None = 600,
) -> subprocess.CompletedProcess[str]:
    """``gcm ARGV`` in a subprocess of this checkout: what a user's terminal shows.

    C++ output of the libraries included. ``env`` is added to this process's
    environment.
    """
    return subprocess.run(
        [sys.executable, "-m", "gcm_pipeline", *map(str, argv)],
        capture_output=True,
        text=True,
        timeout=timeout,
        env=gcm_env(**(env or {})),
        cwd=cwd,
    )


_B64 = re.compile(r"data:application/octet-binary;base64,([A-Za-z0-9+/=]+)")


def decode_commands(html: str) -> list[dict]:
    """The meshcat commands embedded in a static scene page."""
    import base64

    import umsgpack

    return [umsgpack.unpackb(base64.b64decode(m)) for m in _B64.findall(html)]


def decision_contact(checker: Any, q: Any, mode: str, steps: int = 14, most: int = 200) -> Any:
    """Both sides of a checker's decision in ``mode``: ``most`` free and colliding rows of
    ``q``, each pair of them bisected ``steps`` times towards the contact."""
    import numpy as np

    hit = checker.check(q, mode) != ""
    free, coll = q[~hit], q[hit]
    m = min(len(free), len(coll), most)
    a, b = free[:m].copy(), coll[:m].copy()
    for _ in range(steps):
        mid = 0.5 * (a + b)
        mh = checker.check(mid, mode) != ""
        b[mh], a[~mh] = mid[mh], mid[~mh]
    return np.concatenate([a, b])


def pair_contact(checker: Any, q: Any, c: int, steps: int = 14, most: int = 150) -> Any:
    """Both sides of a checker's pair ``c``'s contact: ``most`` free and colliding rows of
    ``q``, each pair of them bisected ``steps`` times towards the contact."""
    import numpy as np

    pool = checker._pair_pool[c]
    hit = checker._run(pool, q)
    m = min(int(hit.sum()), int((~hit).sum()), most)
    if m == 0:
        return q[:0]
    a, b = q[~hit][:m].copy(), q[hit][:m].copy()
    for _ in range(steps):
        mid = 0.5 * (a + b)
        mh = checker._run(pool, mid)
        b[mh], a[~mh] = mid[mh], mid[~mh]
    return np.concatenate([a, b])


def around_the_bottle(robot: Any, n: int, seed: int) -> Any:
    """IK solutions with the grasp frame near the bottle of ``configs/bottle_side.yaml``
    (0.5 m ahead, 22 cm tall), approaching its axis, off by cm."""
    import numpy as np

    from gcm_pipeline.robot.ik import solve_ik

    rng = np.random.default_rng(seed)
    a = rng.uniform(-np.pi / 2, np.pi / 2, n) + np.pi  # the side facing the robot
    t = np.tile(np.eye(4), (n, 1, 1))
    z = -np.stack([np.cos(a), np.sin(a), np.zeros(n)], axis=1)  # toward the axis
    t[:, :3, 2] = z
    t[:, :3, 1] = [0.0, 0.0, 1.0]
    t[:, :3, 0] = np.cross(t[:, :3, 1], z)
    centre = np.column_stack([np.full(n, 0.5), np.zeros(n), rng.uniform(0.03, 0.2, n)])
    back = rng.uniform(-0.01, 0.06, n)[:, None]  # frame behind the axis: the hand reaches it
    side = rng.uniform(-0.02, 0.02, n)[:, None]
    t[:, :3, 3] = centre - back * z + side * t[:, :3, 1]
    res = solve_ik(robot, t)
    return res.q[res.success]


def in_threads(work: Any, count: int) -> None:
    """Run ``work(k)`` for k in range(count) on as many threads at once, switching between
    them as often as Python allows; returns when all are done."""
    import threading

    interval = sys.getswitchinterval()
    sys.setswitchinterval(1e-6)
    try:
        threads = [threading.Thread(target=work, args=(k,)) for k in range(count)]
        for t in threads:
            t.start()
        for t in threads:
            t.join()
    finally:
        sys.setswitchinterval(interval)


def tilted_elbow_chain(ur5: Any) -> Any:
    """The UR5's chain with its elbow axis tilted by 0.05 rad: no longer parallel to the
    shoulder's and wrist 1's (no UR geometry, no decomposition EAIK knows)."""
    import numpy as np
    import pinocchio as pin

    from gcm_pipeline.robot.chain import KinematicChain

    model = ur5.model.copy()
    j = model.getJointId("elbow_joint")
    placement = model.jointPlacements[j].copy()
    placement.rotation = placement.rotation @ pin.exp3(np.array([0.05, 0.0, 0.0]))
    model.jointPlacements[j] = placement
    return KinematicChain(model, ur5.grasp_frame_id)


def python_read_grasps(path: Path) -> Any:
    """``grasps.csv`` read by the Python reader alone (the reference of the Arrow reader)."""
    from gcm_pipeline.rundir import grasps_csv

    return grasps_csv._table(grasps_csv._Cells(path, *grasps_csv._read_rows(path)))[0]


def assert_same_table(a: Any, b: Any) -> None:
    """Two grasp tables with the same columns, dtypes, shapes and bits (NaN payloads included)."""
    import numpy as np

    assert a.columns == b.columns
    for name in a.columns:
        x, y = np.asarray(a[name]), np.asarray(b[name])
        assert (x.dtype, x.shape) == (y.dtype, y.shape), name
        assert x.tobytes() == y.tobytes(), name


def same_read_outcome(path: Path) -> None:
    """read_grasps_csv (Arrow first) and the Python reader: same table, or same one-line error."""
    import pytest

    from gcm_pipeline.errors import InputError
    from gcm_pipeline.rundir import grasps_csv

    try:
        expected = python_read_grasps(path)
    except InputError as exc:
        with pytest.raises(InputError) as got:
            grasps_csv.read_grasps_csv(path)
        assert str(got.value) == str(exc) and "\n" not in str(exc)
        assert (got.value.row, got.value.key) == (exc.row, exc.key)
        return
    assert_same_table(grasps_csv.read_grasps_csv(path), expected)
