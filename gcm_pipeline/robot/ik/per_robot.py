"""Objects built once per robot from its kinematic chain (closed-form solvers, reach tests)."""

from __future__ import annotations

from collections.abc import Callable, Hashable
from typing import Any, TypeVar

__all__ = ["per_robot"]

T = TypeVar("T")


def per_robot(robot: Any, key: Hashable, build: Callable[[Any], T]) -> T:
    """``build(robot.chain)``, made on the first call for ``robot`` and kept in its cache."""
    cache = robot.cache
    if key not in cache:
        cache[key] = build(robot.chain)
    out: T = cache[key]
    return out
