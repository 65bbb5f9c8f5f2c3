"""The README and the docs cannot drift: their Python snippets run, their config sketches
validate, the README's Quickstart block holds the two commands CI relies on."""

from __future__ import annotations

import re
from pathlib import Path

import pytest
import yaml
from helpers import ROOT

from gcm_pipeline.config import Config

README = (ROOT / "README.md").read_text(encoding="utf-8")
#: The README and every docs page, by path relative to the repository root.
PAGES = {"README.md": README} | {
    f"docs/{p.name}": p.read_text(encoding="utf-8") for p in sorted((ROOT / "docs").glob("*.md"))
}


def _blocks(lang: str, text: str = README) -> list[str]:
    return re.findall(rf"^```{lang}\n(.*?)^```", text, flags=re.S | re.M)


def _all_blocks(lang: str) -> list[tuple[str, str]]:
    """(page, block) for every ``lang`` block of the README and the docs, each text once."""
    seen: dict[str, str] = {}
    for page, text in PAGES.items():
        for block in _blocks(lang, text):
            seen.setdefault(block, page)
    return [(page, block) for block, page in seen.items()]


def test_quickstart_has_exactly_two_commands() -> None:
    section = README.split("## Quickstart", 1)[1]
    block = re.search(r"^```bash\n(.*?)^```", section, flags=re.S | re.M)
    assert block is not None
    lines = [
        ln for ln in block.group(1).splitlines() if ln.strip() and not ln.lstrip().startswith("#")
    ]
    assert len(lines) == 2
    assert "gcm run configs/" in lines[0]
    assert "pytest" in lines[1]
    config = re.search(r"gcm run (configs/\S+\.yaml)", lines[0])
    assert config is not None and (ROOT / config.group(1)).is_file()


@pytest.mark.parametrize("index", range(len(_all_blocks("python"))))
def test_python_snippet_runs(index: int, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    page, code = _all_blocks("python")[index]
    # Snippets use paths relative to the repository root, as a user in a clone would.
    monkeypatch.chdir(ROOT)
    exec(compile(code, f"{page} python block", "exec"), {"__name__": "__readme__"})


def test_readme_has_python_snippets() -> None:
    assert _blocks("python"), "the README lost its Python example"
    assert len(_all_blocks("python")) >= 3, "the docs lost their Python examples"


def test_config_sketch_validates() -> None:
    assert any(
        "candidates" in yaml.safe_load(text)
        for text in _blocks("yaml", PAGES["docs/configuration.md"])
    ), "docs/configuration.md lost its config sketch"
    for page, text in _all_blocks("yaml"):
        data = yaml.safe_load(text)
        if isinstance(data, list):  # an export's output shown (MoveIt grasps), not a config
            assert data and all(isinstance(g, dict) and "id" in g for g in data), page
            continue
        if "model" in data:  # a robot spec of a user's URDF: written and loaded
            _load_readme_spec(data)
            continue
        if "base_to_tcp" in data:  # a gripper file (see Grippers)
            from gcm_pipeline.config.gripper_spec import parse_gripper

            gripper = parse_gripper(data, ROOT / "my_gripper.yaml", page)
            assert gripper.tool is not None and gripper.tool.collision
            continue
        if "tool" in data:  # a robot spec's tool section (see Tools)
            from gcm_pipeline.config.tool_spec import parse_tool

            tool = parse_tool(page, data["tool"], ROOT)
            assert data["grasp_frame"] and tool.collision
            continue
        cfg = Config.from_dict(data, source=page)
        assert cfg.candidates.source


def test_study_sketch_matches_the_example_study() -> None:
    """The study file shown in docs/studies.md is configs/studies/bottle_placement.yaml, minus
    comments."""
    from gcm_pipeline.study import load_study

    blocks = re.findall(r"^```(\w*)\n(.*?)^```", PAGES["docs/studies.md"], flags=re.S | re.M)
    sketch = yaml.safe_load(next(text for lang, text in blocks if not lang))
    example = ROOT / "configs" / "studies" / "bottle_placement.yaml"
    assert sketch == {k: v for k, v in yaml.safe_load(example.read_text()).items()} | {"set": []}
    load_study(example)


def test_every_example_config_is_listed() -> None:
    listing = PAGES["docs/configuration.md"]
    for path in sorted((ROOT / "configs").glob("*.yaml")):
        assert f"configs/{path.name}" in listing, (
            f"docs/configuration.md does not mention {path.name}"
        )


def test_benchmark_scripts_named_in_readme_exist() -> None:
    texts = [*PAGES.values(), (ROOT / "CHANGELOG.md").read_text(encoding="utf-8")]
    named = [s for text in texts for s in re.findall(r"python (benchmarks/\S+\.py)", text)]
    assert named, "the docs name no benchmark script"
    for script in named:
        assert (ROOT / script).is_file(), script


def test_readme_is_short_and_links_the_docs() -> None:
    """The README stays a five-minute read; the reference lives in docs/."""
    assert len(README.splitlines()) <= 250
    for page in sorted((ROOT / "docs").glob("*.md")):
        assert f"docs/{page.name}" in README, f"README does not link docs/{page.name}"


def _load_readme_spec(data: dict) -> None:
    import tempfile

    from urdfs import arm_urdf

    from gcm_pipeline.config.robot_spec import load_robot

    with tempfile.TemporaryDirectory() as tmp:
        spec = Path(tmp) / "spec.yaml"
        if "urdf" not in data["model"]:  # a model of example-robot-data (the hand's examples)
            spec.write_text(yaml.safe_dump(data))
            assert load_robot(spec).grasp_frame == data["grasp_frame"]
            return
        urdf = Path(tmp) / data["model"]["urdf"]
        urdf.parent.mkdir(parents=True)
        urdf.write_text(arm_urdf())
        spec.write_text(yaml.safe_dump(data))
        robot = load_robot(spec)
        assert robot.grasp_frame == data["grasp_frame"]
        assert robot.upper[5] == 3.1416 - 0.1  # the stated range, less the limit margin
