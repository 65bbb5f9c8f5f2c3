"""How reachability is decided: one frozen options object, plain values only.

:mod:`gcm_pipeline.pipeline` maps a config onto it (``ik``, ``robot.base_pose``,
``approach``, ``retreat``, ``seed``); :func:`~gcm_pipeline.reach.check.make_engine`
and :func:`~gcm_pipeline.reach.check.check_reachability` take it.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from types import MappingProxyType
from typing import Any

import numpy as np

from gcm_pipeline.reach.moves import Move

__all__ = ["ReachOptions", "shared_ik_options"]


@dataclass(frozen=True, eq=False)
class ReachOptions:
    """The options of a reachability check (the engine's and the table's).

    Attributes:
        backend: IK backend, ``"pinocchio"`` or ``"mink"``.
        position_tolerance: [m], > 0.
        orientation_tolerance: [rad], > 0.
        approach: The pre-grasp approach (None: not checked).
        retreat: The post-grasp retreat, in the base or the grasp frame (None:
            not checked).
        alternatives: Other IK solutions tried per grasp that fails a check.
        workers: Processes (``"auto"`` or 0: decided per run, from its size
            and the idle cores; see ``ReachabilityEngine``). The result does
            not depend on it.
        chunk_size: Most targets per chunk of the engine (None: by backend).
        solutions: IK branches kept per reachable grasp (the engine's step 4).
        seed: Random seed of the IK's seed library and restarts.
        base_pose: Robot base in the world (4, 4) [m]; None: identity.
        warm_start: Seed interpolated rows from their vertices' solutions.
        ik_options: Backend options (see :func:`~gcm_pipeline.robot.ik.solve_ik`).
    """

    backend: str = "pinocchio"
    position_tolerance: float = 1e-4
    orientation_tolerance: float = 1e-3
    approach: Move | None = None
    retreat: Move | None = None
    alternatives: int = 4
    workers: int | str = 1
    chunk_size: int | None = None
    solutions: int = 1
    seed: int | None = None
    base_pose: np.ndarray | None = None
    warm_start: bool = True
    ik_options: Mapping[str, Any] = field(default_factory=lambda: MappingProxyType({}))

    def __post_init__(self) -> None:
        object.__setattr__(self, "ik_options", MappingProxyType(dict(self.ik_options)))
        if self.base_pose is not None:
            base = np.array(self.base_pose, dtype=float)
            base.setflags(write=False)
            object.__setattr__(self, "base_pose", base)


def shared_ik_options(backend: str, ik_options: Mapping[str, Any]) -> dict[str, Any]:
    """The IK options that hold for every IK of the engine, not only step 1.

    That is whether the pinocchio backend uses the closed form.
    """
    if backend != "pinocchio":
        return {}
    return {k: v for k, v in ik_options.items() if k in ("analytic",)}
