"""Several objects in one run: the ``objects`` list and the ``target`` that picks one (or all).

``objects`` lists named objects, each an ``object`` section with a ``name``;
``target`` names the one whose grasps the run analyses. That object becomes
the run's ``object`` (the gripper may touch it within
``environment.contact_tolerance``) and every other object joins
``environment.obstacles`` under its name (full collision, kind
``environment``). ``target: all`` analyses each object in turn, one run
directory per object (:mod:`gcm_pipeline.pipeline.objects`).
"""

from __future__ import annotations

from typing import Annotated

from pydantic import Field

from gcm_pipeline.config.sections import ObjectConfig
from gcm_pipeline.errors import unknown_choice

__all__ = ["TARGET_ALL", "NamedObjectConfig", "check_objects"]

#: ``target`` value that analyses every object in turn.
TARGET_ALL = "all"

#: An object name: a run directory's folder name under ``objects/``.
ObjectName = Annotated[
    str, Field(min_length=1, max_length=64, pattern=r"^[A-Za-z0-9][A-Za-z0-9_.-]*$")
]


class NamedObjectConfig(ObjectConfig):
    """One of ``objects``: the keys of ``object`` and a unique ``name``.

    ``name`` (letters, digits, ``_ . -``; not ``all``) names the object as the
    ``target``, as an obstacle of the other objects' runs and as the folder of
    its run directory under ``objects/`` with ``target: all``.
    """

    name: ObjectName


def check_objects(
    object_: ObjectConfig | None,
    objects: tuple[NamedObjectConfig, ...] | None,
    target: str | None,
    free_obstacles: int,
) -> tuple[ObjectConfig, ...]:
    """The objects whose grasps a config analyses, after checking ``objects`` and ``target``.

    Args:
        object_: The config's ``object`` section.
        objects: Its ``objects`` list.
        target: Its ``target``.
        free_obstacles: How many more obstacles ``environment.obstacles`` may take.

    Returns:
        ``(object_,)`` without ``objects`` (``()`` without either); else the
        target, or every object for ``target: all``.

    Raises:
        ValueError: ``object`` and ``objects`` together, ``target`` without
            ``objects`` or missing, an empty list, a duplicate or reserved
            name, an unknown target (the message lists the names), a plane
            that would be another object's obstacle, too many obstacles.
    """
    if objects is None:
        if target is not None:
            raise ValueError(f"target {target!r} needs an 'objects' list to choose from")
        return () if object_ is None else (object_,)
    if object_ is not None:
        raise ValueError("give 'object' (one object) or 'objects' (a list with a target), not both")
    if not objects:
        raise ValueError("objects: the list is empty; give at least one object")
    names = [o.name for o in objects]
    for i, name in enumerate(names):
        if name == TARGET_ALL:
            raise ValueError(f"objects.{i}.name: {name!r} is reserved (target: all)")
        if name in names[:i]:
            raise ValueError(f"objects.{i}.name: {name!r} is used twice; names are unique")
        same = [n for n in names[:i] if n.lower() == name.lower()]
        if same:  # objects/<name> folders: one folder on a case-insensitive file system
            raise ValueError(
                f"objects.{i}.name: {name!r} differs from {same[0]!r} only in case; names are "
                "unique ignoring case (each names a folder objects/<name>)"
            )
    if target is None:
        raise ValueError(f"objects: give 'target', one of {', '.join(names)} or {TARGET_ALL!r}")
    if target != TARGET_ALL and target not in names:
        raise ValueError(unknown_choice("target", target, [*names, TARGET_ALL]))
    chosen = objects if target == TARGET_ALL else tuple(o for o in objects if o.name == target)
    for i, o in enumerate(objects):
        if o.shape == "plane" and any(t is not o for t in chosen):
            raise ValueError(
                f"objects.{i} ({o.name}): shape 'plane' can only be the target, it cannot "
                "be an obstacle of another object (use a thin box)"
            )
    if len(objects) - 1 > free_obstacles:
        raise ValueError(
            f"objects: {len(objects) - 1} other objects do not fit in environment.obstacles "
            f"({free_obstacles} places left)"
        )
    return chosen
