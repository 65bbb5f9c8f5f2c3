"""gcm_pipeline: grasp configuration manifolds and their reachability.

The public API is listed in ``__all__``; every name in it imports.
"""

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
from gcm_pipeline.table import GraspTable

__version__ = "0.1.0"

__all__ = [
    "ConfigError",
    "FrameNotFoundError",
    "GcmError",
    "GeometryError",
    "GraspTable",
    "InputError",
    "OutputError",
    "PublishError",
    "RobotSpecError",
    "__version__",
]
