"""Fixtures of the robot tests: the compiled kernels and their NumPy references."""

from __future__ import annotations

import numpy as np
import pinocchio as pin
import pytest

from gcm_pipeline.robot import kernels


@pytest.fixture
def kernels_on(monkeypatch):
    """The kernels on for the test, whatever the environment's ``GCM_JIT`` says."""
    monkeypatch.delenv("GCM_JIT", raising=False)


@pytest.fixture(scope="session")
def compiled():
    """The compiled kernels (numba is a dependency: they must load)."""
    with pytest.MonkeyPatch.context() as mp:
        mp.delenv("GCM_JIT", raising=False)
        out = kernels.get()
    assert out is not None, "numba is a dependency: the kernels must load"
    return out


@pytest.fixture
def numpy_code(monkeypatch):
    """``numpy_code(fn, *args)``: ``fn(*args)`` with the NumPy code (``GCM_JIT=0``)."""

    def run(fn, *args):
        monkeypatch.setenv("GCM_JIT", "0")
        try:
            return fn(*args)
        finally:
            monkeypatch.delenv("GCM_JIT")

    return run


@pytest.fixture
def pose_errors():
    """``pose_errors(robot, q, rot, pos)``: position [m] and rotation [rad] error of each
    configuration's grasp frame from the targets, by Pinocchio."""

    def errors(robot, q, rot, pos):
        tf = robot.fk_pinocchio(q)
        pe = np.linalg.norm(tf[:, :3, 3] - pos, axis=1)
        rel = np.einsum("nij,nkj->nik", rot, tf[:, :3, :3])  # target @ reached^T
        re = np.array([np.linalg.norm(pin.log3(r)) for r in rel])
        return pe, re

    return errors
