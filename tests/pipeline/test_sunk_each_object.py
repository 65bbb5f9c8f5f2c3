"""With ``objects``, the sunk-object warning names the object, for every object.

``gcm validate --target all`` checks each object's run config; ``gcm run`` of a
``target: all`` config (``run_objects``) checks the first one's config only
(one robot for every run), so the others' table check is its own.
"""

from __future__ import annotations

import logging

import pytest
from helpers import ROOT

from gcm_pipeline.config import load_config
from gcm_pipeline.errors import GcmError
from gcm_pipeline.pipeline import run_objects

TWO = ROOT / "configs" / "two_objects.yaml"  # a bottle and a can on the table, target bottle
CAN_SUNK = "objects.1.pose.xyz=[0.5,0.11,-0.05]"


def _sunk(text: str) -> list[str]:
    return [line for line in text.splitlines() if "the table" in line and "raise its" in line]


def test_validate_names_each_sunk_object(cli):
    code, _, err = cli("validate", TWO, "--set", CAN_SUNK, "--target", "all")
    assert code == 0, err
    sunk = _sunk(err)
    assert len(sunk) == 1
    assert "object 'can' reaches 50.0 mm into the table" in sunk[0]


def test_run_objects_warns_about_a_sunk_object_after_the_first(tmp_path, caplog):
    out = tmp_path / "out"
    out.mkdir()
    (out / "mine.txt").write_text("not a run")  # the run stops before any work
    cfg = load_config(TWO, [CAN_SUNK, "target=all"])
    with caplog.at_level(logging.WARNING), pytest.raises(GcmError):
        run_objects(cfg, out, progress=False)
    sunk = _sunk(caplog.text)
    assert len(sunk) == 1
    assert "object 'can' reaches 50.0 mm into the table" in sunk[0]
