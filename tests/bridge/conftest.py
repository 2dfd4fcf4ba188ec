"""Fixtures of the ECU bridge tests."""

from __future__ import annotations

from collections.abc import Iterator

import pytest
from bridge_rig import RigFactory, rig_factory


@pytest.fixture
def make_rig() -> Iterator[RigFactory]:
    make, close = rig_factory()
    try:
        yield make
    finally:
        close()
