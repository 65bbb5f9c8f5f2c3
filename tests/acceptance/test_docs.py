"""The docs cannot go stale: generated pages match their sources, links resolve, and the
column registry they are generated from names every column a run produces."""

from __future__ import annotations

import importlib.util
import json
import re
import tempfile
from pathlib import Path

import pytest
from helpers import ROOT

DOCS = ROOT / "docs"


def _gen():
    spec = importlib.util.spec_from_file_location("gen_docs", ROOT / "scripts" / "gen_docs.py")
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


GEN = _gen()


@pytest.mark.parametrize("name", sorted(GEN.PAGES))
def test_generated_page_is_current(name: str) -> None:
    path = DOCS / name
    expected = GEN.expected_pages()[path]
    assert path.read_text(encoding="utf-8") == expected, (
        f"docs/{name} is stale: run `{GEN.COMMAND}` and commit the result"
    )


def test_a_page_without_markers_is_refused() -> None:
    with pytest.raises(SystemExit, match="markers"):
        GEN.splice("# a page\n", "body", "x.md")


def test_splice_replaces_only_the_generated_part() -> None:
    page = f"# head\n\nby hand\n\n{GEN.BEGIN}\nold\n{GEN.END}\n\nafter\n"
    out = GEN.splice(page, "new\n")
    assert out.startswith("# head\n\nby hand\n\n") and out.endswith("\n\nafter\n")
    assert "new" in out and "old" not in out
    assert GEN.splice(out, "new\n") == out  # idempotent


def test_benchmarks_page_has_every_result_with_its_record() -> None:
    page = (DOCS / "benchmarks.md").read_text(encoding="utf-8")
    for path in sorted((ROOT / "benchmarks" / "results").glob("*.json")):
        data = json.loads(path.read_text(encoding="utf-8"))
        section = page.split(f"\n## {path.stem}\n", 1)[1].split("\n## ", 1)[0]
        assert f"`benchmarks/results/{path.name}`" in section
        for key in ("command", "date", "machine", "load average"):
            assert f"- {key}: " in section, (path.name, key)
        if "command" in data:
            assert f"`{data['command']}`" in section
        for key in ("date", "date_utc", "time"):
            if key in data:
                assert str(data[key]) in section


def test_config_reference_names_every_key() -> None:
    from gcm_pipeline import Config

    page = (DOCS / "configuration.md").read_text(encoding="utf-8")
    schema = Config.model_json_schema(mode="validation")
    for model in [schema, *schema["$defs"].values()]:
        for key in model.get("properties", {}):
            assert f"| `{key}` |" in page, key


_LINK = re.compile(r"!?\[[^\]]*\]\(([^)\s]+)\)")


def _anchors(markdown: str) -> set[str]:
    """Heading anchors as mkdocs and GitHub make them (lower case, spaces to dashes)."""
    found = set()
    for heading in re.findall(r"^#{1,6} (.+)$", markdown, flags=re.M):
        text = re.sub(r"[`*]", "", heading).strip().lower()
        found.add(re.sub(r"\s+", "-", re.sub(r"[^\w\s-]", "", text)))
    return found


def _pages() -> list[Path]:
    return [ROOT / "README.md", ROOT / "CHANGELOG.md", *sorted(DOCS.glob("*.md"))]


@pytest.mark.parametrize("page", _pages(), ids=lambda p: str(p.relative_to(ROOT)))
def test_relative_links_resolve(page: Path) -> None:
    text = page.read_text(encoding="utf-8")
    text = re.sub(r"^```.*?^```", "", text, flags=re.S | re.M)  # not in code blocks
    for target in _LINK.findall(text):
        if re.match(r"[a-z]+:", target):
            continue  # http(s), mailto
        path, _, anchor = target.partition("#")
        file = (page.parent / path).resolve() if path else page
        assert file.exists(), f"{page.name}: link to {target}: no file {file}"
        if anchor and file.suffix == ".md":
            assert anchor in _anchors(file.read_text(encoding="utf-8")), (
                f"{page.name}: link to {target}: no heading #{anchor}"
            )


# a repository path named in a shipped file's comments or a data README (docs/robots.md)
_REPO_PATH = re.compile(
    r"(?<![\w/.])((?:docs|configs|scripts|benchmarks|tests|gcm_pipeline)/[\w./-]*\w"
    r"\.(?:md|yaml|py|npz|json|obj))"
)


def _shipped_texts() -> list[Path]:
    globs = ("gcm_pipeline/grippers/*.yaml", "gcm_pipeline/robot/specs/*.yaml", "configs/**/*.yaml")
    return [
        *(p for g in globs for p in sorted(ROOT.glob(g))),
        *sorted(ROOT.glob("tests/data/*/README.md")),
    ]


@pytest.mark.parametrize("text", _shipped_texts(), ids=lambda p: str(p.relative_to(ROOT)))
def test_repository_paths_named_in_shipped_files_exist(text: Path) -> None:
    for name in _REPO_PATH.findall(text.read_text(encoding="utf-8")):
        assert (ROOT / name).exists(), (
            f"{text.relative_to(ROOT)} names {name}, which does not exist"
        )


def test_column_registry_names_every_column_of_a_run() -> None:
    """docs/run-directory.md is generated from COLUMNS: a column a run adds must be there."""
    import gcm_pipeline as gcm
    from gcm_pipeline.table import CANDIDATE_COLUMNS, COLUMNS

    overrides = [
        "ik.solutions=2",
        "densify.adaptive={max_level: 1}",
        "ranking.metric=combined",
        "publish.html=false",
        "publish.plots=false",
    ]
    pipeline = gcm.Pipeline.from_yaml(ROOT / "configs" / "flat_surface.yaml", overrides)
    with tempfile.TemporaryDirectory() as tmp:
        result = pipeline.run(Path(tmp) / "run", progress=False)
        header = (Path(tmp) / "run" / "grasps.csv").read_text().splitlines()[0].split(",")
    table = result.grasps
    assert not set(table.columns) - set(COLUMNS) - set(CANDIDATE_COLUMNS)
    cells = {c for col in COLUMNS.values() for c in col.csv}  # grasps.csv: registered too
    for cell in header:
        assert cell in cells | set(COLUMNS) | set(CANDIDATE_COLUMNS) or re.fullmatch(
            r"q[0-9]+", cell
        ), cell
    kinds = {"float": "f", "int": "iu", "bool": "b", "str": "UO"}
    for name, col in COLUMNS.items():
        assert col.shape.startswith("(N") and col.stage and col.meaning, name
        if name in table.columns:  # every column of this run: its dtype and its dimensions
            assert table[name].dtype.kind in kinds[col.dtype], (name, table[name].dtype)
            assert table[name].ndim == col.shape.count(",") + (not col.shape.endswith(",)")), name
