"""Controller II: which parameters matter (issue 3: a one-at-a-time table from a good point)."""

from __future__ import annotations

import numpy as np
import pytest

from bac_sim.problems import get_problem
from bac_sim.sensitivity import format_table, main, one_at_a_time


@pytest.fixture(scope="module")
def sweep():  # type: ignore[no-untyped-def]
    # 3 values per parameter (the ends and the middle of the range): 61 runs of the test road
    return one_at_a_time(get_problem("road_c2"), points=3)


def test_important_and_unimportant_parameters_split(sweep) -> None:  # type: ignore[no-untyped-def]
    loss = dict(zip(sweep.names, sweep.loss, strict=True))
    # no effect at all on a straight road at 60 km/h: the speed table away from 60 km/h, the cornering gain
    for name in ("p15", "p17", "p18", "p19"):
        assert abs(loss[name]) < 1e-12, name
    # the controller's floor, cap and groundhook decide much (paper's T = 5 %)
    for name in ("p08", "p11", "p14"):
        assert loss[name] > 0.10, name
    significant = sweep.significant(0.05)
    assert 5 <= len(significant) <= 16
    assert sum(v < 0.02 for v in loss.values()) >= 5  # the reduction has parameters to drop
    # the sweep starts from a good point: no single change gains more than 2 %
    assert sweep.j.min() > 0.98 * sweep.j0


def test_table_prints_every_parameter_sorted_by_loss(sweep, capsys: pytest.CaptureFixture[str]) -> None:  # type: ignore[no-untyped-def]
    text = format_table(sweep, reveal=True)
    lines = text.splitlines()
    rows = [ln for ln in lines if ln[:1] == "p" and ln[1:3].isdigit()]
    assert len(rows) == 20
    losses = [float(r.split()[5]) for r in rows]
    assert losses == sorted(losses, reverse=True)
    assert "groundhook" in text
    assert lines[-1].startswith("significant (")


def test_cli_runs_on_a_controller_i_problem(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["--problem", "bump_c1", "--points", "3"]) == 0
    out = capsys.readouterr().out
    assert "damping_front" in out and "damping_rear" in out
    p = get_problem("bump_c1")
    assert f"{p.j_star:.5f}" in out
    assert np.isfinite(p.j_star)
