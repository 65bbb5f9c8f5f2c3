"""Several objects in one config: the target becomes the ``object``, the others obstacles.

A config with ``objects`` and ``target`` (:mod:`gcm_pipeline.config.objects`)
runs as the config :func:`target_config` makes of it: the target is its
``object`` (kind ``object``: the gripper may touch it within
``environment.contact_tolerance``), every other object is appended to
``environment.obstacles`` under its name (kind ``environment``: full
collision), and ``objects``/``target`` are gone. That config is the one the
run directory records, so it re-runs as it ran.
"""

from __future__ import annotations

from gcm_pipeline.config.objects import TARGET_ALL, NamedObjectConfig
from gcm_pipeline.config.reach_sections import ObstacleConfig
from gcm_pipeline.config.run import Config, takes_config
from gcm_pipeline.config.sections import ObjectConfig
from gcm_pipeline.errors import ConfigError, choice_error
from gcm_pipeline.pipeline.preflight import check_input_files

__all__ = ["target_config", "target_names"]


def target_names(cfg: Config) -> list[str]:
    """The objects whose grasps ``cfg`` analyses: its target, every object for ``all``.

    Empty for a config without ``objects``.
    """
    if cfg.objects is None:
        return []
    if cfg.target == TARGET_ALL:
        return [o.name for o in cfg.objects]
    assert cfg.target is not None  # the config's validation
    return [cfg.target]


@takes_config
def target_config(cfg: Config, name: str | None = None) -> Config:
    """``cfg`` with object ``name`` (default: ``target``) as its object, the others obstacles.

    A config without ``objects`` is returned as it is. The files the config
    reads are checked first (:func:`check_input_files`), so a missing mesh is
    named by its ``objects.<i>.mesh`` key.

    Args:
        cfg: The config.
        name: The object to analyse; needed when ``target`` is ``all``.

    Returns:
        The config of one object's run: ``object`` the target (without its
        name), ``environment.obstacles`` followed by the other objects (named),
        no ``objects`` nor ``target``.

    Raises:
        ConfigError: ``name`` is not one of the objects, or is missing with ``target: all``.
        InputError: A file the config reads is missing.
    """
    if cfg.objects is None:
        return cfg
    check_input_files(cfg)
    name = cfg.target if name is None else name
    names = [o.name for o in cfg.objects]
    if name == TARGET_ALL:
        raise ConfigError(
            f"target: 'all' runs each object in turn; one object's config needs its name "
            f"(one of {', '.join(names)})",
            key="target",
        )
    if name not in names:
        raise choice_error(ConfigError, "target", name, names, key="target")
    target = next(o for o in cfg.objects if o.name == name)
    others = tuple(_as_obstacle(o) for o in cfg.objects if o.name != name)
    env = cfg.environment.model_copy(update={"obstacles": (*cfg.environment.obstacles, *others)})
    return cfg.model_copy(
        update={
            "object": ObjectConfig.model_validate(target.model_dump(exclude={"name"})),
            "objects": None,
            "target": None,
            "environment": env,
        }
    )


def _as_obstacle(obj: NamedObjectConfig) -> ObstacleConfig:
    """An object that is not the target, as an ``environment.obstacles`` entry."""
    return ObstacleConfig.model_validate(obj.model_dump())
