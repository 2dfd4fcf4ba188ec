"""The gap metric shared by every part of bac."""

from __future__ import annotations

import math

import numpy as np
import pytest

from bac_common.progress import FOUND_GAP, ProgressError, found, gap, median_j, runs_to_optimum, runs_to_stay_found


def test_gap_values() -> None:
    np.testing.assert_allclose(gap([1.0, 2.0, 3.0, 1.1], j_star=1.0, j_med=3.0), [0.0, 0.5, 1.0, 0.05])
    assert FOUND_GAP == 0.05
    assert found([0.05, 0.0500001, math.nan, -0.1]).tolist() == [True, False, False, True]
    with pytest.raises(ProgressError, match="J\\* < J_med"):
        gap(1.0, j_star=2.0, j_med=1.0)


def test_runs_to_optimum_is_first_hit() -> None:
    assert runs_to_optimum([0.9, 0.3, 0.04, 0.2, 0.01]) == 3.0
    assert runs_to_optimum([0.9, 0.3]) == math.inf


def test_runs_to_stay_found_ignores_a_lucky_early_recommendation() -> None:
    assert runs_to_stay_found([0.04, 0.3, 0.2, 0.01, 0.0]) == 4.0  # the first run's hit was luck
    assert runs_to_stay_found([0.01, 0.02]) == 1.0
    assert runs_to_stay_found([0.01, 0.2]) == math.inf
    assert runs_to_stay_found([]) == math.inf


def test_median_j_of_a_known_function() -> None:
    # J = x on [0, 2]: the median over uniform x is 1
    assert median_j(lambda t: t[:, 0], [[0.0, 2.0]], n=100_000) == pytest.approx(1.0, abs=0.01)
    with pytest.raises(ProgressError, match="bounds"):
        median_j(lambda t: t[:, 0], [[1.0, 0.0]])
