"""``bac replay`` takes ``-p node.param:=value`` and ``--params-file`` as ``bac launch`` does, and refuses a wrong
one before anything starts (exit 2, the reason on stderr)."""

from __future__ import annotations

from pathlib import Path

import pytest

from bac_bringup.tools import replay_main


@pytest.fixture
def bag(tmp_path: Path) -> Path:
    p = tmp_path / "some_bag"
    p.mkdir()
    return p


@pytest.mark.parametrize(
    ("args", "reason"),
    [
        (["-p", "nosuch.rate:=2"], "overrides for unknown nodes ['nosuch'] in profile 'replay'"),
        (["--params-file", "{tmp}/missing.yaml"], "--params-file {tmp}/missing.yaml: no such file"),
        (["--params-file", "{tmp}/flat.yaml"], "--params-file {tmp}/flat.yaml: not a ROS parameter file"),
    ],
)
def test_a_wrong_parameter_is_refused_before_the_graph_starts(
    bag: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str], args: list[str], reason: str
) -> None:
    (tmp_path / "flat.yaml").write_text("rate: 2\n")
    argv = [str(bag), *(a.format(tmp=tmp_path) for a in args)]
    assert replay_main(argv) == 2
    assert f"bac replay: {reason.format(tmp=tmp_path)}" in capsys.readouterr().err


def test_a_malformed_assignment_is_a_usage_error(bag: Path, capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as exc:
        replay_main([str(bag), "-p", "rate:=2"])
    assert exc.value.code == 2 and "expected node.param:=value, got 'rate:=2'" in capsys.readouterr().err


def test_a_param_wins_over_the_options_and_reaches_the_profile(bag: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    seen: dict[str, dict[str, object]] = {}

    def fake_run_graph(profile: object, single_process: bool = False) -> int:
        seen.update({n.name: dict(n.params) for n in profile.nodes})  # type: ignore[attr-defined]
        return 0

    monkeypatch.setattr("bac_bringup.tools.run_graph", fake_run_graph)
    argv = [str(bag), "--rate", "3", "-p", "bag_player.rate:=7.5", "-p", "kpi_scorer.weight_pitch_rate:=0.0"]
    assert replay_main(argv) == 0
    assert seen["bag_player"]["rate"] == 7.5 and seen["bag_player"]["bags"] == [str(bag.resolve())]
    assert seen["kpi_scorer"]["weight_pitch_rate"] == 0.0
