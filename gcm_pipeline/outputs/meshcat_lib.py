"""meshcat, the scene's viewer library: the one module that imports it, on first use.

Importing meshcat loads its server's stack (tornado, ZMQ, IPython's display
helpers), about a fifth of a second: importing the package, or running
without a scene, does not pay for it. Every module of the scene takes the
library from :func:`load_meshcat`.
"""

from __future__ import annotations

import functools
from types import ModuleType

from gcm_pipeline.errors import PublishError

__all__ = ["load_meshcat"]


@functools.cache
def load_meshcat() -> ModuleType:
    """The ``meshcat`` package, with ``geometry``, ``animation`` and ``servers.tree`` loaded.

    Raises:
        PublishError: meshcat cannot be imported.
    """
    try:
        import meshcat
        import meshcat.animation
        import meshcat.geometry
        import meshcat.servers.tree
    except ImportError as exc:  # pragma: no cover - meshcat is a dependency
        raise PublishError(f"the scene needs meshcat, which cannot be imported: {exc}") from None
    return meshcat
