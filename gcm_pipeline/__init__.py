"""gcm_pipeline: grasp configuration manifolds and their reachability.

The public API is :mod:`gcm_pipeline.api` (its imports and ``__all__``, the one
list), re-exported here on first use (:pep:`562`): ``import gcm_pipeline`` and
the ``gcm`` command start fast, and Ctrl-C during start-up is an ordinary
interrupt. mink, MuJoCo, meshcat and Ray load only when the ``mink`` IK
backend, the meshcat publisher or a placement study (:class:`Study`) is used.
"""

import importlib
import importlib.util
from typing import TYPE_CHECKING, Any

__version__ = "0.1.0"

if TYPE_CHECKING:  # type checkers see the API itself
    from gcm_pipeline.api import *  # noqa: F403
    from gcm_pipeline.api import __all__ as _api_all

    __all__ = ["__version__", *_api_all]
else:

    def __getattr__(name: str) -> Any:
        """The public names (and ``__all__``), or a subpackage, on first use (PEP 562)."""
        if not name.startswith("_") and importlib.util.find_spec(f"{__name__}.{name}"):
            # a subpackage (``from gcm_pipeline import interrupts``): no public name is one
            value = importlib.import_module(f"{__name__}.{name}")
        elif name == "__all__" or not name.startswith("_"):
            # api.py holds the one list; imported here so that ``import gcm_pipeline`` stays light
            api = importlib.import_module("gcm_pipeline.api")
            if name == "__all__":
                value = sorted(["__version__", *api.__all__])
            elif name in api.__all__:
                value = getattr(api, name)
            else:
                raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
        else:
            raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
        globals()[name] = value  # the next access is a plain lookup
        return value

    def __dir__() -> list[str]:
        """The module's names, the public ones included before they load."""
        return sorted(set(globals()) | set(__getattr__("__all__")))
