"""The command lines' number arguments: refused by argparse within the range the receiving node declares."""

from __future__ import annotations

import argparse

import pytest

from bac_common.console import in_range


def test_in_range_takes_the_nodes_range_and_names_what_is_wrong() -> None:
    # outside review 2026-11-29: bac demo --budget 0 and --seed -1 started the whole graph, then died in rclpy
    budget = in_range(int, 1, 10_000)
    assert budget("3") == 3 and budget("10000") == 10_000
    with pytest.raises(argparse.ArgumentTypeError, match=r"^0 is outside \[1, 10000\]$"):
        budget("0")
    with pytest.raises(argparse.ArgumentTypeError, match="'x' is not an int"):
        budget("x")
    with pytest.raises(argparse.ArgumentTypeError, match=r"^-1 is outside \[0, 2147483647\]$"):
        in_range(int, 0, 2**31 - 1)("-1")
    rate = in_range(float, 0.01, 1000.0)
    assert rate("0.5") == 0.5
    with pytest.raises(argparse.ArgumentTypeError, match=r"0.0 is outside \[0.01, 1000.0\]"):
        rate("0")
    with pytest.raises(argparse.ArgumentTypeError, match="is outside"):
        rate("nan")
