"""Shared helpers of the bac_sim tests."""

from __future__ import annotations

import numpy as np
import pytest

from bac_sim.roads import Road


@pytest.fixture
def flat_road() -> Road:
    """A perfectly flat road from -100 m to 2000 m."""
    n = 21001
    return Road("flat", -100.0, 0.1, np.zeros(n), np.zeros(n), {"kpi_start_m": 0.0, "kpi_end_m": 100.0})
