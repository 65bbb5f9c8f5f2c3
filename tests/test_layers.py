"""The package's layers hold: import-linter's contracts, and imports at module top."""

from __future__ import annotations

import ast
import os
import subprocess
import sys
from pathlib import Path

import grimp
from helpers import ROOT

PACKAGE = ROOT / "gcm_pipeline"

# The only places that import the package's own modules inside functions:
# - cli/: each command imports what it runs, so `gcm --help` starts without NumPy;
# - __init__.py: the public API of api.py, re-exported on first use (PEP 562);
# - __main__.py: the command line, imported after the signal handlers are installed.
LAZY_ON_PURPOSE = ("cli/", "__init__.py", "__main__.py")
# (module, function) whose own-module imports stay inside the function, and why
GUARDED_IMPORTS = {
    # the compiled kernel modules import Numba at their top and compile (or read the
    # cache) on import: they are Numba's guarded import, done on the first call only
    ("robot/kernels.py", "_import"),
}


def test_import_contracts_are_kept():
    # lint-imports comes with the test extra, beside this interpreter; it reads the
    # contracts from pyproject.toml and analyses this checkout's package
    exe = Path(sys.executable).parent / "lint-imports"
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    proc = subprocess.run(
        [str(exe)], cwd=ROOT, env=env, capture_output=True, text=True, timeout=600
    )
    assert proc.returncode == 0, proc.stdout[-4000:] + proc.stderr[-2000:]
    assert "0 broken" in proc.stdout, proc.stdout[-2000:]


def _cycles(graph: grimp.ImportGraph) -> list[list[str]]:
    """One import chain closing each cycle: ``[a, b, ..., a]`` for a direct import a -> b."""
    cycles = []
    for importer in sorted(graph.modules):
        for imported in sorted(graph.find_modules_directly_imported_by(importer)):
            back = graph.find_shortest_chain(importer=imported, imported=importer)
            if back:
                cycles.append([importer, *back])
    return cycles


def test_the_package_has_no_import_cycles():
    # the layers contract forbids upward imports between layers; this also covers
    # modules of one layer (pipeline.reach <-> pipeline.manifold, say). Imports under
    # TYPE_CHECKING do not run, as in the contracts.
    graph = grimp.build_graph("gcm_pipeline", cache_dir=None, exclude_type_checking_imports=True)
    assert "gcm_pipeline.pipeline.run" in graph.modules  # this checkout's package
    cycles = _cycles(graph)
    assert not cycles, "import cycles:\n" + "\n".join(" -> ".join(c) for c in cycles)


def test_the_cycle_check_finds_a_cycle():
    graph = grimp.ImportGraph()
    for a, b in [("p.a", "p.b"), ("p.b", "p.c"), ("p.c", "p.a"), ("p.c", "p.d")]:
        graph.add_import(importer=a, imported=b)
    assert _cycles(graph) == [
        ["p.a", "p.b", "p.c", "p.a"],
        ["p.b", "p.c", "p.a", "p.b"],
        ["p.c", "p.a", "p.b", "p.c"],
    ]
    graph.remove_import(importer="p.c", imported="p.a")
    assert _cycles(graph) == []


def _own_module(node: ast.AST) -> str | None:
    """The package module an import statement or call names, else None."""
    if isinstance(node, ast.Import):
        names = [a.name for a in node.names if a.name.split(".")[0] == "gcm_pipeline"]
        return ", ".join(names) or None
    if isinstance(node, ast.ImportFrom):
        if node.level:  # a relative import is always the package's own
            return "." * node.level + (node.module or "")
        if node.module and node.module.split(".")[0] == "gcm_pipeline":
            return node.module
        return None
    if isinstance(node, ast.Call) and node.args:  # importlib.import_module("gcm_pipeline.x")
        func = node.func
        name = func.attr if isinstance(func, ast.Attribute) else getattr(func, "id", None)
        arg = node.args[0]
        if (
            name in ("import_module", "__import__")
            and isinstance(arg, ast.Constant)
            and isinstance(arg.value, str)
            and arg.value.split(".")[0] == "gcm_pipeline"
        ):
            return arg.value
    return None


def _imports_inside_functions(path: Path) -> list[str]:
    """``line: module (in function)`` of each own-module import inside a function of ``path``."""
    found = []

    def visit(node: ast.AST, function: str | None) -> None:
        for child in ast.iter_child_nodes(node):
            if isinstance(child, (ast.FunctionDef, ast.AsyncFunctionDef, ast.Lambda)):
                visit(child, getattr(child, "name", "<lambda>"))
                continue
            module = _own_module(child) if function is not None else None
            if module is not None:
                found.append(f"{child.lineno}: {module} (in {function})")
            visit(child, function)

    visit(ast.parse(path.read_text(encoding="utf-8"), str(path)), None)
    return found


def test_the_library_imports_its_own_modules_at_module_top():
    # Inside the library an import is at module top, so the import graph (and its
    # cycles) is what import-linter sees; a heavy optional library (mink, Ray, h5py,
    # Numba, ...) sits behind one guarded import, and that is not one of ours.
    modules = sorted(PACKAGE.rglob("*.py"))
    assert len(modules) > 50  # the package, not an empty glob
    lazy = []
    for path in modules:
        rel = path.relative_to(PACKAGE).as_posix()
        if rel.startswith(LAZY_ON_PURPOSE):  # (top-level __init__ and __main__ only)
            continue
        hits = _imports_inside_functions(path)
        lazy += [
            f"gcm_pipeline/{rel}:{hit}"
            for hit in hits
            if (rel, hit.rsplit("(in ", 1)[1].rstrip(")")) not in GUARDED_IMPORTS
        ]
    assert not lazy, "import these at module top:\n" + "\n".join(lazy)


def test_the_check_finds_an_import_inside_a_function(tmp_path):
    # the check above reads what it must: own modules inside functions (also nested,
    # relative and importlib's), not module-top, TYPE_CHECKING or third-party imports
    src = tmp_path / "m.py"
    src.write_text(
        "from typing import TYPE_CHECKING\n"
        "import numpy as np\n"
        "from gcm_pipeline.table import GraspTable\n"
        "if TYPE_CHECKING:\n"
        "    from gcm_pipeline.robot.model import Robot\n"
        "def f():\n"
        "    import h5py\n"
        "    from gcm_pipeline.errors import GcmError\n"
        "class C:\n"
        "    def g(self):\n"
        "        def h():\n"
        "            from . import sibling\n"
        "        import gcm_pipeline.geometry, json\n"
        "async def k():\n"
        "    importlib.import_module('gcm_pipeline.api')\n"
    )
    assert _imports_inside_functions(src) == [
        "8: gcm_pipeline.errors (in f)",
        "12: . (in h)",
        "13: gcm_pipeline.geometry (in g)",
        "15: gcm_pipeline.api (in k)",
    ]
