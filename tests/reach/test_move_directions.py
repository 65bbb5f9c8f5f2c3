"""An approach or retreat direction of any length is a direction (``reach.moves``)."""

from __future__ import annotations

import pytest
from helpers import BOTTLE

from gcm_pipeline.config import load_config
from gcm_pipeline.errors import GcmError


def test_a_retreat_direction_of_any_length_is_a_direction():
    from gcm_pipeline.reach.moves import Move

    unit = Move(distance=0.1, direction=(1, 1, 1)).direction
    # the norm of the first overflowed: the move went nowhere and every retreat failed
    assert Move(distance=0.1, direction=(1e300, 1e300, 1e300)).direction == unit
    assert Move(distance=0.1, direction=(1e-320, 0, 0)).direction == (1.0, 0.0, 0.0)
    cfg = load_config(BOTTLE, ["retreat.direction=[1e308, 1e308, 1e308]"])
    assert cfg.retreat.direction == (1e308, 1e308, 1e308)
    with pytest.raises(GcmError, match="must not be the zero vector"):
        load_config(BOTTLE, ["retreat.direction=[0, 0, 0]"])
