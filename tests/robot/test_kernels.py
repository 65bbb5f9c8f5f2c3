"""Loading the compiled kernels (gcm_pipeline.robot.kernels) and the inputs they take.

The loader: Numba is imported on the first use, never with the package; switches
that select the NumPy code; a notice while compiling. The conversion: every array
layout, dtype and row count a NumPy reference takes reaches its kernel, and
answers as the reference; shapes a kernel does not expect get the reference's
errors. And the whole reachability check with and without the kernels. Each
kernel against its reference: the test module beside the kernel's
(``test_chain_kernel``, ``collision/test_broadphase_kernel``,
``collision/test_clearance_kernel``, ``ik/test_lm_kernel``, ``ik/test_panda_kernel``).

What is compared is what a user relies on, with tolerances that hold on any
x86-64 or arm64 CPU (another CPU changes the NumPy code's last bits: OpenBLAS
picks its dgemm kernel at run time, NumPy its SIMD sine and cosine): decisions
equal, values to tolerances far above round-off, never the last bits.
"""

from __future__ import annotations

import os
import subprocess
import sys

import numpy as np
import pytest
from helpers import ROOT

from gcm_pipeline import pipeline as P
from gcm_pipeline.config import load_config
from gcm_pipeline.config.robot_spec import load_robot
from gcm_pipeline.geometry.dualquat import dq_to_matrix
from gcm_pipeline.pipeline import make_checker
from gcm_pipeline.robot import kernels

#: Each test starts with the kernels on, whatever the environment says.
pytestmark = pytest.mark.usefixtures("kernels_on")


# --- loading ----------------------------------------------------------------------------


def test_the_package_and_its_command_line_do_not_import_numba():
    code = (
        "import sys\n"
        "from gcm_pipeline.__main__ import entry\n"
        "from gcm_pipeline.config import load_config\n"
        "import gcm_pipeline.pipeline, gcm_pipeline.robot.collision\n"
        "load_config('configs/bottle_side.yaml')\n"
        "for argv in (['--help'], ['validate', 'configs/bottle_side.yaml']):\n"
        "    sys.argv = ['gcm', *argv]\n"
        "    try:\n"
        "        entry()\n"
        "    except SystemExit:\n"
        "        pass\n"
        "print('numba' in sys.modules, file=sys.stderr)\n"
    )
    out = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, check=True, cwd=ROOT
    )
    assert "usage" in out.stdout and "bottle_side.yaml: ok" in out.stdout
    assert out.stderr.strip().splitlines()[-1] == "False"


def test_gcm_jit_0_selects_the_numpy_code(monkeypatch, panda, compiled):
    def fail(*args):
        raise AssertionError("the compiled kernels were called")

    monkeypatch.setattr(kernels, "_load", fail)
    monkeypatch.setenv("GCM_JIT", "0")
    assert kernels.get() is None
    q = panda.random_configurations(300, 0)
    rot, pos, jac = panda.chain._forward(q, True)  # the NumPy path, not the kernel
    assert rot.shape == (300, 3, 3) and jac is not None and jac.shape == (300, 6, 7)
    checker = make_checker(panda)
    assert checker.check(q).shape == (300,)
    monkeypatch.setenv("GCM_JIT", "1")
    with pytest.raises(AssertionError, match="were called"):
        kernels.get()


#: The modules that import Numba, by :func:`kernels.get` only.
KERNEL_MODULES = [
    "gcm_pipeline.robot.kernel_common",
    "gcm_pipeline.robot.chain_kernel",
    "gcm_pipeline.robot.collision.broadphase_kernel",
    "gcm_pipeline.robot.collision.clearance_kernel",
    "gcm_pipeline.robot.ik.lm_kernel",
    "gcm_pipeline.robot.ik.panda_kernel",
]


def test_without_numba_the_numpy_code_is_used():
    kernels._load.cache_clear()
    try:
        with pytest.MonkeyPatch.context() as mp:
            mp.setitem(sys.modules, "numba", None)  # import numba raises ImportError
            for name in KERNEL_MODULES:  # imported again, they would import numba
                mp.delitem(sys.modules, name, raising=False)
                parent, _, leaf = name.rpartition(".")
                mp.delattr(sys.modules[parent], leaf, raising=False)
            assert kernels.get() is None
    finally:
        kernels._load.cache_clear()
    assert kernels.get() is not None


def test_numbas_own_switch_and_other_spellings_select_numpy(monkeypatch):
    # NUMBA_DISABLE_JIT would run the kernels as Python (and the FMA intrinsic cannot)
    code = (
        "from gcm_pipeline.robot import kernels\n"
        "from gcm_pipeline.config.robot_spec import load_robot\n"
        "from gcm_pipeline.robot.ik import solve_ik\n"
        "r = load_robot('panda')\n"
        "res = solve_ik(r, r.fk(r.random_configurations(20, 1)))\n"
        "print(kernels.get() is None, bool(res.success.all()))\n"
    )
    env = {k: v for k, v in os.environ.items() if k != "GCM_JIT"}
    out = subprocess.run(
        [sys.executable, "-c", code],
        capture_output=True,
        text=True,
        check=True,
        cwd=ROOT,
        env={**env, "NUMBA_DISABLE_JIT": "1", "PYTHONPATH": str(ROOT)},
    )
    assert out.stdout.split() == ["True", "True"], out.stderr
    for value in ("off", "False", " no "):
        monkeypatch.setenv("GCM_JIT", value)
        assert kernels.get() is None
    monkeypatch.setenv("GCM_JIT", "1")
    assert kernels.get() is not None
    with kernels.suppressed():
        assert kernels.get() is None
    assert kernels.get() is not None


def test_a_long_load_says_that_it_compiles(monkeypatch, caplog):
    import time

    real = kernels._import

    def slow():
        time.sleep(0.3)  # as a first run's compilation, only shorter
        return real()

    monkeypatch.setattr(kernels, "_NOTICE_AFTER", 0.05)
    for load, said in ((slow, True), (real, False)):
        monkeypatch.setattr(kernels, "_import", load)
        kernels._load.cache_clear()
        caplog.clear()
        try:
            with caplog.at_level("WARNING", logger="gcm_pipeline.robot.kernels"):
                assert kernels.get() is not None
                time.sleep(0.1)  # a notice still pending would fire now
        finally:
            kernels._load.cache_clear()
        assert ("compiling the package's kernels" in caplog.text) is said
        assert caplog.text.count("compiling") <= 1


def test_reachability_with_and_without_kernels(compiled, numpy_code, pose_errors):
    """The whole check: the same decisions, configurations equal to round-off."""
    cfg = load_config(ROOT / "configs" / "bottle_side.yaml", ["ik.workers=1"])
    cand = P.generate_candidates(cfg)
    grasps = P.densify(cand, P.build_manifold(cand, cfg), cfg)
    robot = P.robot_from_config(cfg)
    out = P.check_reachability(grasps, robot, cfg)
    ref = numpy_code(P.check_reachability, grasps, robot, cfg)
    np.testing.assert_array_equal(out["reachable"], ref["reachable"])
    np.testing.assert_array_equal(out["reason"], ref["reason"])
    ok = np.asarray(out["reachable"])
    assert 0 < ok.sum() < len(ok)
    # each answer, checked by Pinocchio and the NumPy checker: at its grasp within the
    # IK tolerances, inside the limits, collision-free
    q = np.asarray(out["q"])[ok]
    target = np.linalg.inv(cfg.robot.base_pose.matrix()) @ dq_to_matrix(
        np.asarray(grasps["dq"])[ok]
    )
    pe, re = pose_errors(robot, q, target[:, :3, :3], target[:, :3, 3])
    assert pe.max() <= cfg.ik.position_tolerance * (1 + 1e-6)
    assert re.max() <= cfg.ik.orientation_tolerance * (1 + 1e-6)
    assert robot.within_limits(q).all()
    checker = make_checker(robot, cfg.environment, cfg.object)
    assert (numpy_code(checker.check, q, "grasp") == "").all()
    # the same solutions (not to the last bits: an iterative solver's answer moves
    # with round-off anywhere in its tolerance ball; 1e-3 rad is that ball's size,
    # far below the distance between two branches), the clearance to its precision
    np.testing.assert_allclose(q, np.asarray(ref["q"])[ok], rtol=0, atol=1e-3)
    np.testing.assert_allclose(
        np.asarray(out["clearance"])[ok], np.asarray(ref["clearance"])[ok], rtol=0, atol=1e-3
    )


def test_kernels_never_read_past_mismatched_arrays(compiled, panda, numpy_code):
    """Shapes the kernels do not expect get the NumPy code (its errors), not stray memory."""
    from gcm_pipeline.robot.ik.lm import PinocchioIKOptions, levenberg_marquardt
    from gcm_pipeline.robot.ik.panda import analytic_solver

    q = panda.random_configurations(5, 1)
    with pytest.raises(IndexError):
        panda.chain.pose(q[:, :3])  # too few joints
    rot, pos = panda.chain.pose(q)
    solver = analytic_solver(panda)
    with pytest.raises(IndexError):
        solver.solve(rot, pos, np.zeros((40, 1)), panda.lower, panda.upper)  # q7 rows
    got = solver.solve(rot, pos, q[:, 6:7], panda.lower, panda.upper)
    ref = numpy_code(solver.solve, rot, pos, q[:, 6:7], panda.lower, panda.upper)
    assert np.array_equal(got[0], ref[0]) and set(got[0]) == set(range(5))
    # an iteration budget far beyond memory: the stall test needs only the last scores
    opts = PinocchioIKOptions(max_iterations=2**40)
    args = (panda.chain, q + 0.1, rot, pos, panda.lower, panda.upper, 1e-6, 1e-5, opts)
    conv = levenberg_marquardt(*args)[1]
    assert np.array_equal(conv, numpy_code(levenberg_marquardt, *args)[1])


# --- every input a NumPy reference takes ------------------------------------------------


def _layouts(a):
    """``a`` (float64, C order) as a caller may hand it over: every variant, by name."""
    read_only = a.copy()
    read_only.setflags(write=False)
    out = {
        "C": a,
        "fortran": np.asfortranarray(a),
        "read-only": read_only,
        "float32": a.astype(np.float32),
        "reversed": a[::-1].copy()[::-1],
    }
    if a.ndim == 2 and len(a):
        out["strided"] = np.repeat(a, 2, axis=0)[::2]
    return out


@pytest.mark.parametrize("n", [0, 1, 5])
def test_kernels_take_any_layout_dtype_and_row_count(monkeypatch, compiled, n, numpy_code):
    """Zero rows, one row, Fortran order, strides, read-only, float32 or int arrays:
    each kernel (not the NumPy fallback) takes them and answers as the NumPy code."""
    from gcm_pipeline.reach.deviation import lever_arms, segment_bounds
    from gcm_pipeline.robot.ik.lm import PinocchioIKOptions, levenberg_marquardt
    from gcm_pipeline.robot.ik.panda import analytic_solver

    calls = {}

    def counting(name, fn):
        def wrapped(*args):
            calls[name] = calls.get(name, 0) + 1
            return fn(*args)

        return wrapped

    real = kernels.get()
    spied = kernels.Kernels(*(counting(f, getattr(real, f)) for f in kernels.Kernels._fields))
    monkeypatch.setattr(kernels, "_load", lambda: spied)
    robots = {name: load_robot(name) for name in ("panda", "ur5")}
    for robot in robots.values():
        q0 = robot.random_configurations(n, 1)
        rot, pos = robot.chain.pose(q0)
        lev = lever_arms(robot)
        opts = PinocchioIKOptions()
        for layout, q in {**_layouts(q0), "int": np.round(q0).astype(int)}.items():
            qf = np.asarray(q, dtype=float)
            for got, want in zip(
                robot.chain._forward(q, True),
                numpy_code(robot.chain._forward, qf, True),
                strict=True,
            ):
                np.testing.assert_allclose(got, want, rtol=0, atol=1e-12, err_msg=layout)
            lm = (robot.chain, q, rot, pos, robot.lower, robot.upper, 1e-6, 1e-5, opts)
            got, want = (
                levenberg_marquardt(*lm),
                numpy_code(levenberg_marquardt, robot.chain, qf, *lm[2:]),
            )
            np.testing.assert_array_equal(got[1], want[1], err_msg=layout)
            seg = (robot, lev, q, qf + 0.05, pos, rot, np.full((n, 3), 0.01), 0.12, 1e-3, np.inf)
            np.testing.assert_allclose(
                segment_bounds(*seg),
                numpy_code(segment_bounds, robot, lev, qf, *seg[3:]),
                rtol=1e-9,
                atol=1e-12,
                err_msg=layout,
            )
        for layout, r in _layouts(rot).items():  # targets too
            got = levenberg_marquardt(robot.chain, q0, r, _layouts(pos)[layout], robot.lower,
                                      robot.upper, 1e-6, 1e-5, opts)  # fmt: skip
            assert got[0].shape == q0.shape and got[0].dtype == np.float64, layout
    solver = analytic_solver(robots["panda"])
    panda = robots["panda"]
    q0 = panda.random_configurations(n, 2)
    rot, pos = panda.chain.pose(q0)
    for layout, q7 in {**_layouts(q0[:, 6:7]), "int": np.zeros((n, 2), int)}.items():
        args = (rot, pos, q7, list(panda.lower), tuple(panda.upper))
        got = solver.solve(*args)
        want = numpy_code(solver.solve, rot, pos, np.asarray(q7, float), *args[3:])
        np.testing.assert_array_equal(got[0], want[0], err_msg=layout)
        np.testing.assert_allclose(got[1], want[1], rtol=0, atol=1e-6, err_msg=layout)
    assert solver.solve(rot, pos, np.zeros((n, 0)), panda.lower, panda.upper)[1].shape == (0, 7)
    # every call above went to a kernel (n = 0: those that do not return early)
    assert {"chain_forward", "levenberg_marquardt", "panda_ik"} <= set(calls)
    assert ("segment_samples" in calls) == (n > 0)


def test_a_kernel_converts_safely_or_says_why(compiled, panda):
    """Empty arrays of any dtype and safe casts convert; lossy casts and wrong
    dimensions are a caller's mistake, named, not Numba's 'No matching definition'."""
    q_index, placement, tool = panda.chain.packed
    rot, pos, jac = compiled.chain_forward(
        np.zeros((0, 7), np.int32), q_index, placement, tool, 7, True
    )
    assert rot.shape == (0, 3, 3) and jac.shape == (0, 6, 7)
    rot, _, _ = compiled.chain_forward(
        np.zeros((2, 7)), q_index.astype(np.int32), placement, tool, np.int16(7), 1
    )
    np.testing.assert_allclose(rot, panda.chain.pose(np.zeros((2, 7)))[0], atol=1e-12)
    unaligned = np.frombuffer(bytes(1 + 2 * 7 * 8), np.float64, 14, 1).reshape(2, 7)
    assert not unaligned.flags.aligned
    rot, _, _ = compiled.chain_forward(unaligned, q_index, placement, tool, 7, True)
    np.testing.assert_allclose(rot, panda.chain.pose(np.zeros((2, 7)))[0], atol=1e-12)
    with pytest.raises(TypeError, match="chain_forward: argument 1 of dtype float64"):
        compiled.chain_forward(np.zeros((2, 7)), q_index + 0.5, placement, tool, 7, True)
    with pytest.raises(TypeError, match="chain_forward: argument 0 has 1 dimensions, not 2"):
        compiled.chain_forward(np.zeros(7), q_index, placement, tool, 7, True)
    with pytest.raises(TypeError):  # a float for an integer: not truncated
        compiled.chain_forward(np.zeros((2, 7)), q_index, placement, tool, 7.5, True)
    # no pair, no world shape: nothing open (the broad phase of an empty screen)
    empty_i, empty_f = np.zeros(0, int), np.zeros(0)
    out = compiled.broad_phase(
        np.zeros((3, 4, 3, 4)), empty_i, np.zeros((0, 3)), np.zeros((0, 3)), np.zeros(1, int),
        empty_f, empty_f, empty_f, empty_f, empty_f, empty_f, empty_f, empty_f, empty_f,
        np.zeros((0, 21)),
    )  # fmt: skip
    assert out.shape == (0, 4)


def test_one_blas_thread_limits_and_restores_the_pools():
    from threadpoolctl import threadpool_info

    from gcm_pipeline.robot.kernels import one_blas_thread

    def blas_threads() -> list[int]:
        return [p["num_threads"] for p in threadpool_info() if p["user_api"] == "blas"]

    before = blas_threads()
    assert before  # NumPy's BLAS is loaded
    with one_blas_thread(10):  # small work: left as it is
        assert blas_threads() == before
    with one_blas_thread(1000):
        assert blas_threads() == [1] * len(before)
    assert blas_threads() == before


def _blas_threads() -> list[int]:
    from threadpoolctl import threadpool_info

    return [p["num_threads"] for p in threadpool_info() if p["user_api"] == "blas"]


def test_one_blas_thread_on_several_threads_restores_the_pools():
    """``one_blas_thread`` blocks on three threads at once, many times (three checkers'
    ``clearance``): afterwards the pools have their thread counts from before (each
    block restoring the limits it found left BLAS on one thread for good)."""
    import threading
    import time

    from gcm_pipeline.robot.kernels import one_blas_thread

    before = _blas_threads()
    if max(before) < 2:
        pytest.skip("BLAS runs on one thread here: no limit to leave behind")

    def many() -> None:
        for _ in range(100):
            with one_blas_thread(1000):
                time.sleep(0.0005)  # the blocks overlap

    threads = [threading.Thread(target=many) for _ in range(3)]
    for t in threads:
        t.start()
    for t in threads:
        t.join(30)
    assert _blas_threads() == before


def test_one_blas_thread_limits_on_the_main_thread_only():
    """The main thread's block limits BLAS to one thread while another thread's block
    overlaps it; the other thread's leaves the pools as they are."""
    import threading

    from threadpoolctl import threadpool_limits

    from gcm_pipeline.robot.kernels import one_blas_thread

    first_in, second_in, first_out = threading.Event(), threading.Event(), threading.Event()
    seen = {}

    def second() -> None:  # enters after the main thread's block, leaves after it
        first_in.wait(10)
        with one_blas_thread(1000):
            second_in.set()
            first_out.wait(10)
            seen["alone"] = _blas_threads()

    with threadpool_limits(limits=2, user_api="blas"):  # more than one, on any machine
        before = _blas_threads()
        other = threading.Thread(target=second)
        other.start()
        with one_blas_thread(1000):
            first_in.set()
            assert second_in.wait(10)
            assert _blas_threads() == [1] * len(before)
        first_out.set()
        other.join(10)
        assert seen["alone"] == before
        assert _blas_threads() == before
