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


#: Libraries a command that only reads a config (``gcm validate``'s parsing, ``gcm schema``)
#: must not load: the robot, the kernels, plots, the viewer, Ray, grasp files, meshes.
HEAVY = ("pinocchio", "numba", "matplotlib", "meshcat", "ray", "h5py", "trimesh", "coal")


def _loaded_after(imports: str, names: tuple[str, ...]) -> list[str]:
    """The ``names`` in ``sys.modules`` of a fresh interpreter (this checkout) after ``imports``."""
    import json
    import subprocess
    import sys

    code = (
        f"import sys, json, {imports}; "
        f"print(json.dumps(sorted(m for m in {names!r} if m in sys.modules)))"
    )
    out = subprocess.run(  # in this checkout, not another install
        [sys.executable, "-c", code], capture_output=True, text=True, check=True, cwd=ROOT
    )
    return json.loads(out.stdout)


def test_the_command_line_starts_without_the_heavy_libraries() -> None:
    """``gcm`` installs its Ctrl-C handling before NumPy and Pinocchio load.

    The public names load on first use, so importing the package or its
    command line loads neither; an interrupt while they load (inside ``main``)
    is then an ordinary ``interrupted``, not a traceback.
    """
    assert _loaded_after("gcm_pipeline, gcm_pipeline.cli", ("numpy", "pinocchio", "scipy")) == []


def test_reading_a_config_loads_no_heavy_library() -> None:
    """The config (its models, schema and gripper names) loads without the robot or grasp files.

    ``gcm schema`` and the config half of ``gcm validate`` stay fast: the config
    reads the gripper names from their registry module, and the ``sources`` and
    ``robot`` packages import nothing on their own.
    """
    imports = "gcm_pipeline.config, gcm_pipeline.config.run, gcm_pipeline.cli, gcm_pipeline.cli.run"
    assert _loaded_after(imports, HEAVY) == []
    # the check sees a heavy library when one loads
    assert "pinocchio" in _loaded_after("gcm_pipeline.robot.model", HEAVY)


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
