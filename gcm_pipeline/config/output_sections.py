"""Run config sections of the results: ``ranking``, ``publish`` and ``output``."""

from __future__ import annotations

import difflib
import re
from pathlib import Path

from pydantic import field_validator

from gcm_pipeline.config.reach_sections import _METRICS, Metric
from gcm_pipeline.config.sections import (
    DEFAULT_OUTPUT_DIR,
    Bool,
    NonNegFloat,
    PositiveFloat,
    PositiveInt,
    _Section,
)
from gcm_pipeline.errors import clip


class RankingConfig(_Section):
    """Ranking of the reachable grasps by a manipulability metric."""

    metric: Metric = "yoshikawa"
    top_k: PositiveInt = 10
    weights: dict[str, NonNegFloat] | None = None

    @field_validator("weights")
    @classmethod
    def _known_weights(cls, v: dict[str, float] | None) -> dict[str, float] | None:
        if v is None:
            return v
        valid = [m for m in _METRICS if m != "combined"]
        for key in v:
            if key not in valid:
                close = difflib.get_close_matches(key, valid, n=1)
                hint = f" (did you mean {close[0]!r}?)" if close else ""
                raise ValueError(f"unknown metric {clip(key)}{hint}; valid: {', '.join(valid)}")
        if not any(w > 0 for w in v.values()):
            raise ValueError("weights must have at least one positive value")
        return v


#: ``tcp://host:port`` (host: a name, an IPv4 address or ``[IPv6]``).
_ZMQ_URL = re.compile(r"tcp://(\[[0-9A-Fa-f:.]+\]|[A-Za-z0-9_.-]+):([0-9]{1,5})")


class PublishConfig(_Section):
    """What to publish: live meshcat, a self-contained HTML scene, PNG plots."""

    meshcat: Bool = False
    zmq_url: str | None = None
    wait: Bool = True
    html: Bool = True
    plots: Bool = True
    connect_timeout_s: PositiveFloat = 5.0

    @field_validator("zmq_url")
    @classmethod
    def _zmq_url_format(cls, v: str | None) -> str | None:
        if v is None:
            return v
        match = _ZMQ_URL.fullmatch(v)
        if match is None or not 0 < int(match.group(2)) < 65536:
            raise ValueError(f"expected tcp://HOST:PORT, e.g. tcp://127.0.0.1:6000, got {clip(v)}")
        return v


class OutputConfig(_Section):
    """Where the run directory goes (``gcm run --out DIR`` overrides it).

    A relative ``dir`` is relative to the config file's folder, like every
    other path of a config (:func:`load_config`); the default is
    ``results/<config name>`` there (``results/run`` in the working directory
    for a config given as a dict).
    """

    dir: Path = Path(DEFAULT_OUTPUT_DIR)
