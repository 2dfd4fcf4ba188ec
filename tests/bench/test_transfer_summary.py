"""bench/transfer.py --from-json: what the results files record is pooled, or refused when the files disagree
(the summary's heading comes from the files, not from the command line)."""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path
from types import ModuleType
from typing import Any

import pytest

BENCH = Path(__file__).resolve().parents[2] / "bench"


def _transfer() -> ModuleType:
    sys.path.insert(0, str(BENCH))  # transfer.py imports its sibling problem_families
    spec = importlib.util.spec_from_file_location("bench_transfer", BENCH / "transfer.py")
    assert spec is not None and spec.loader is not None
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


T = _transfer()


def _run(**kw: Any) -> dict[str, Any]:
    return {"split": "tuning", "budget": 4, "bac_config": "", "grid_truth": 33, "seed_list": False, **kw}


def _results(n: int, runs: int) -> list[dict[str, Any]]:
    return [{"gaps": [1.0] * runs} for _ in range(n)]


def test_one_config_spelled_two_ways_is_pooled_and_the_heading_says_it() -> None:
    a, b = _run(bac_config='{"limit_reach":0.1}'), _run(bac_config='{"limit_reach": 0.1}')
    out = T.pooled_run([a, b], _results(3, 4))
    assert out["bac_config"] == '{"limit_reach":0.1}' and out["runs_per_campaign"] == 4 and out["budget"] == 4
    head = T.heading(out, "", [0, 1], [0], "summarized from 2 file(s)")
    assert "split tuning" in head and "budget 4" in head and '{"limit_reach":0.1}' in head


@pytest.mark.parametrize(
    ("runs", "results", "says"),
    [
        ([_run(), _run(bac_config='{"limit_reach": 0.2}')], _results(2, 4), "different bac_config"),
        ([_run(), _run(budget=5)], _results(2, 4), "different budget"),
        ([_run(), None], _results(2, 4) + _results(1, 5), "campaigns of [4, 5] runs"),
        ([_run()], _results(2, 5), "record budget 4 but hold campaigns of 5"),
        ([_run()], [], "hold no campaigns"),
    ],
)
def test_files_that_disagree_or_hold_nothing_are_refused(
    runs: list[dict[str, Any] | None], results: list[dict[str, Any]], says: str
) -> None:
    with pytest.raises(T.SummaryError, match=says.replace("[", r"\[").replace("]", r"\]")):
        T.pooled_run(runs, results)


def test_a_file_from_before_the_record_makes_every_value_unknown() -> None:
    out = T.pooled_run([_run(), None], _results(2, 4))
    assert all(out[k] is None for k in T.RUN_KEYS) and out["seed_list"] is None and out["runs_per_campaign"] == 4
    assert "split unknown" in T.heading(out, "", [], [], "")
    assert "budget unknown (campaigns of 4 runs)" in T.heading(out, "", [], [], "")
