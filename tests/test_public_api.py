"""The public surface: every name in ``__all__`` imports and is documented."""

from __future__ import annotations

import importlib

import pytest
from helpers import ROOT

import gcm_pipeline


def test_all_names_resolve() -> None:
    missing = [name for name in gcm_pipeline.__all__ if not hasattr(gcm_pipeline, name)]
    assert missing == []


def test_all_is_sorted_and_unique() -> None:
    names = list(gcm_pipeline.__all__)
    assert len(names) == len(set(names))
    assert names == sorted(names, key=str.lower) or names == sorted(names)


@pytest.mark.parametrize("name", [n for n in gcm_pipeline.__all__ if not n.startswith("_")])
def test_public_names_have_docstrings(name: str) -> None:
    obj = getattr(gcm_pipeline, name)
    if callable(obj):
        assert (obj.__doc__ or "").strip(), f"{name} has no docstring"


@pytest.mark.parametrize(
    "module",
    [
        "gcm_pipeline.errors",
        "gcm_pipeline.table",
        "gcm_pipeline.config",
    ],
)
def test_module_all_resolves(module: str) -> None:
    mod = importlib.import_module(module)
    for name in getattr(mod, "__all__", []):
        assert hasattr(mod, name), f"{module}.__all__ lists {name!r} but it is not defined"


def test_the_command_line_starts_without_the_heavy_libraries() -> None:
    """``gcm`` installs its Ctrl-C handling before NumPy and Pinocchio load.

    The public names load on first use, so importing the package or its
    command line loads neither; an interrupt while they load (inside ``main``)
    is then an ordinary ``interrupted``, not a traceback.
    """
    import subprocess
    import sys

    code = (
        "import sys, gcm_pipeline, gcm_pipeline.cli; "
        "print(sorted(m for m in ('numpy', 'pinocchio', 'scipy') if m in sys.modules))"
    )
    out = subprocess.run(  # in this checkout, not another install
        [sys.executable, "-c", code], capture_output=True, text=True, check=True, cwd=ROOT
    )
    assert out.stdout.strip() == "[]"


def test_names_load_on_first_use_and_unknown_names_fail() -> None:
    assert gcm_pipeline.Pipeline is importlib.import_module("gcm_pipeline.pipeline").Pipeline
    assert "Pipeline" in dir(gcm_pipeline)
    with pytest.raises(AttributeError, match="no attribute 'nope'"):
        gcm_pipeline.nope  # noqa: B018


def test_no_public_name_is_also_a_subpackage() -> None:
    # a subpackage imported by anything becomes the package's attribute and would
    # hide a public name of the same spelling (gcm_pipeline.publish, the function)
    import pkgutil

    subpackages = {m.name for m in pkgutil.iter_modules(gcm_pipeline.__path__)}
    assert not subpackages & set(gcm_pipeline.__all__)
