"""The Python entry points read their arguments as the command line does."""

from __future__ import annotations

import numpy as np
import pytest
from helpers import FLAT

from gcm_pipeline.config import load_config
from gcm_pipeline.errors import ConfigError
from gcm_pipeline.pipeline import Pipeline, build_manifold, generate_candidates
from gcm_pipeline.safe_yaml import read_yaml_file


def test_api_arguments_that_were_read_oddly():
    # one override string, not its characters ("--set 'i'")
    assert load_config(FLAT, "ik.workers=2").ik.workers == 2
    assert Pipeline.from_yaml(FLAT, "ik.workers=2").config.ik.workers == 2
    # a stage function takes the config as a plain mapping too (it was an AttributeError)
    as_read = generate_candidates(read_yaml_file(FLAT, "config", ConfigError))
    assert np.array_equal(as_read["dq"], generate_candidates(load_config(FLAT))["dq"])
    with pytest.raises(ConfigError, match="cfg must be a Config .* or a mapping, got list"):
        build_manifold(as_read, cfg=[1])
