"""gcm_pipeline: grasp configuration manifolds and their reachability.

The public API is listed in ``__all__``; every name in it imports.
"""

from gcm_pipeline.config import Config, load_config
from gcm_pipeline.errors import (
    ConfigError,
    FrameNotFoundError,
    GcmError,
    GeometryError,
    InputError,
    OutputError,
    PublishError,
    RobotSpecError,
)
from gcm_pipeline.geometry.dualquat import (
    dib,
    dlb,
    dq_from_matrix,
    dq_from_pos_quat,
    dq_mul,
    dq_to_matrix,
    dq_to_pos_quat,
    sclerp,
)
from gcm_pipeline.io import read_run
from gcm_pipeline.pipeline import (
    Pipeline,
    RunResult,
    build_manifold,
    check_reachability,
    densify,
    generate_candidates,
    publish,
    rank,
)
from gcm_pipeline.table import GraspTable

__version__ = "0.1.0"

__all__ = [
    "Config",
    "ConfigError",
    "FrameNotFoundError",
    "GcmError",
    "GeometryError",
    "GraspTable",
    "InputError",
    "OutputError",
    "Pipeline",
    "PublishError",
    "RobotSpecError",
    "RunResult",
    "__version__",
    "build_manifold",
    "check_reachability",
    "densify",
    "dib",
    "dlb",
    "dq_from_matrix",
    "dq_from_pos_quat",
    "dq_mul",
    "dq_to_matrix",
    "dq_to_pos_quat",
    "generate_candidates",
    "load_config",
    "publish",
    "rank",
    "read_run",
    "sclerp",
]
