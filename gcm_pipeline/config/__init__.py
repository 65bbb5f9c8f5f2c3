"""Configuration: YAML files into validated, frozen objects.

One home for everything a user writes in YAML:

* :mod:`~gcm_pipeline.config.run`: the run config (:class:`Config`,
  :func:`load_config`, ``--set`` overrides, the JSON schema); its sections are
  in :mod:`~gcm_pipeline.config.sections` (field types, poses, shapes, object,
  candidates, manifold, densify), :mod:`~gcm_pipeline.config.reach_sections`
  (robot, ik, environment, approach, retreat, continuity) and
  :mod:`~gcm_pipeline.config.output_sections` (ranking, publish, output);
* :mod:`~gcm_pipeline.config.robot_spec`: robot specs and their tools
  (``load_spec``, ``load_robot``, ``available_robots``; the tool section's
  models are in :mod:`~gcm_pipeline.config.tool_spec`); imported by name, not
  here: it builds robots (Pinocchio), and a config is read without them;
* :mod:`~gcm_pipeline.config.study`: study files (:class:`StudySpec`,
  :func:`read_study`); planning and running them is :mod:`gcm_pipeline.study`'s;
* :mod:`~gcm_pipeline.config.validation`: the one formatter of invalid values
  (key path, value, choices);

The YAML reader (:mod:`gcm_pipeline.safe_yaml`: size, depth, alias and
duplicate-key limits, one-line errors naming file, line and column) and the
input-size bounds (:mod:`gcm_pipeline.bounds`) sit in the bottom layer beside
:mod:`gcm_pipeline.errors`: grasp-file readers and the run directory check
them too, and they sit below this package.
"""

from gcm_pipeline.config.output_sections import OutputConfig, PublishConfig, RankingConfig
from gcm_pipeline.config.reach_sections import (
    ApproachConfig,
    ContinuityConfig,
    EnvironmentConfig,
    IKConfig,
    ObstacleConfig,
    RetreatConfig,
    RobotConfig,
    TableConfig,
)
from gcm_pipeline.config.run import Config, as_config, config_schema, load_config, takes_config
from gcm_pipeline.config.sections import (
    AdaptiveConfig,
    CandidatesConfig,
    DensifyConfig,
    ManifoldConfig,
    NoiseConfig,
    ObjectConfig,
    Pose,
    ShapeDims,
)
from gcm_pipeline.config.study import StudyFile, StudySpec, read_study
from gcm_pipeline.safe_yaml import load_yaml, read_yaml_file

__all__ = [
    "AdaptiveConfig",
    "ApproachConfig",
    "CandidatesConfig",
    "Config",
    "ContinuityConfig",
    "DensifyConfig",
    "EnvironmentConfig",
    "IKConfig",
    "ManifoldConfig",
    "NoiseConfig",
    "ObjectConfig",
    "ObstacleConfig",
    "OutputConfig",
    "Pose",
    "PublishConfig",
    "RankingConfig",
    "RetreatConfig",
    "RobotConfig",
    "ShapeDims",
    "StudyFile",
    "StudySpec",
    "TableConfig",
    "as_config",
    "config_schema",
    "load_config",
    "load_yaml",
    "read_study",
    "read_yaml_file",
    "takes_config",
]
