"""The README cannot drift: its Python snippets run, its config sketch validates,
its Quickstart block holds the two commands CI relies on."""

from __future__ import annotations

import re
from pathlib import Path

import pytest
import yaml

from gcm_pipeline.config import Config

ROOT = Path(__file__).resolve().parents[1]
README = (ROOT / "README.md").read_text(encoding="utf-8")


def _blocks(lang: str) -> list[str]:
    return re.findall(rf"^```{lang}\n(.*?)^```", README, flags=re.S | re.M)


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


@pytest.mark.parametrize("index", range(len(_blocks("python"))))
def test_python_snippet_runs(index: int, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    code = _blocks("python")[index]
    # Snippets use paths relative to the repository root, as a user in a clone would.
    monkeypatch.chdir(ROOT)
    exec(compile(code, f"README.md python block {index}", "exec"), {"__name__": "__readme__"})


def test_readme_has_python_snippets() -> None:
    assert len(_blocks("python")) >= 3


def test_config_sketch_validates() -> None:
    yaml_blocks = _blocks("yaml")
    assert yaml_blocks, "README lost its config sketch"
    for text in yaml_blocks:
        data = yaml.safe_load(text)
        if "model" in data:  # a robot spec of a user's URDF: written and loaded
            _load_readme_spec(data)
            continue
        if "tool" in data:  # a robot spec's tool section (see Tools)
            from gcm_pipeline.config.robot_spec import parse_tool

            tool = parse_tool("README.md", data["tool"], ROOT)
            assert data["grasp_frame"] and tool.collision
            continue
        cfg = Config.from_dict(data, source="README.md")
        assert cfg.candidates.source


def test_study_sketch_matches_the_example_study() -> None:
    """The study file shown in Studies is configs/studies/bottle_placement.yaml, minus comments."""
    from gcm_pipeline.study import load_study

    section = README.split("## Studies", 1)[1]
    blocks = re.findall(r"^```(\w*)\n(.*?)^```", section, flags=re.S | re.M)
    sketch = yaml.safe_load(next(text for lang, text in blocks if not lang))
    example = ROOT / "configs" / "studies" / "bottle_placement.yaml"
    assert sketch == {k: v for k, v in yaml.safe_load(example.read_text()).items()} | {"set": []}
    load_study(example)


def test_every_example_config_is_listed() -> None:
    for path in sorted((ROOT / "configs").glob("*.yaml")):
        assert f"configs/{path.name}" in README, f"README does not mention {path.name}"


def test_benchmark_scripts_named_in_readme_exist() -> None:
    for script in re.findall(r"python (benchmarks/\S+\.py)", README):
        assert (ROOT / script).is_file(), script


def _load_readme_spec(data: dict) -> None:
    import tempfile

    from urdfs import arm_urdf

    from gcm_pipeline.config.robot_spec import load_robot

    with tempfile.TemporaryDirectory() as tmp:
        urdf = Path(tmp) / data["model"]["urdf"]
        urdf.parent.mkdir(parents=True)
        urdf.write_text(arm_urdf())
        spec = Path(tmp) / "spec.yaml"
        spec.write_text(yaml.safe_dump(data))
        robot = load_robot(spec)
        assert robot.grasp_frame == data["grasp_frame"] and robot.upper[5] == 3.1416
