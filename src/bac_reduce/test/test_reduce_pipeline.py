"""The whole phase end to end on small problems: run_reduction, the files, the CLI, the simulator path."""

from __future__ import annotations

import json
import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest
import yaml

from bac_common.paramspace import CalibrationDefinition
from bac_reduce import cli as reduce_cli
from bac_reduce.analysis import Group, ReductionError, reduced_definition
from bac_reduce.objectives import SimulatedCar, SyntheticObjective, make_objective
from bac_reduce.pipeline import ReduceConfig, run_reduction, start_point
from bac_reduce.report import write_outputs

QUICK = {
    "gp": {"draws": 0, "restarts": 0, "maxiter": 30, "mean": "constant"},
    "n_candidates": 128,
    "n_local": 64,
    "acq_restarts": 1,
    "design_margin": 0.02,  # the whole-range initial design these tests were written for (as the phase's own engine)
}
LAST = re.compile(
    r"^reduce_minutes (\d+\.\d+) params_kept (\d+) loss_pct (-?\d+\.\d+|nan) loss_vs_phase_pct (-?\d+\.\d+|nan)$"
)


def tiny(**over: object) -> ReduceConfig:
    base = {
        "problem": "synthetic",
        "campaigns": 2,
        "trials": 16,
        "n_initial": 6,
        "engine": QUICK,
        "optimizer": "agent",  # the paper's path with the agent's engine; turbo and the polish: below
        "batch": 4,
        "polish_evals": 0,
        "global_method": "none",
        "workers": 1,
        "verify_points": 5,
        "validate_repeats": 2,
        "validate_trials": 8,
        "polish_iterations": 6,
    }
    base.update(over)
    return ReduceConfig(**base)  # type: ignore[arg-type]


def test_the_phase_end_to_end_on_the_synthetic_problem(tmp_path: Path) -> None:
    obj = SyntheticObjective()
    lines: list[str] = []
    res = run_reduction(tiny(), obj, log=lines.append)
    assert len(res.campaigns) == 2 and all(c.y.size == 16 for c in res.campaigns)
    # θ̄ is the campaign with the smallest J_i; J_mu(θ̄) is a J of the problem's size
    assert res.theta_bar_index == int(np.argmin(res.j_i))
    assert 0.9 < res.curves.j_bar < 1.5
    # q8 costs at most 0.5 %: even a rough surrogate of 32 runs cannot call it significant; q4 (25.6 %) is kept
    assert "q8" not in res.kept and "q4" in res.kept
    # every parameter is either tuned (alone or in a meta-parameter) or fixed, exactly once
    d = res.definition
    tuned_raw = [m for g in res.groups for m in g.members]
    assert sorted(tuned_raw + list(d.fixed)) == sorted(d.parameter_names)
    assert len(d.dimensions) == len(res.groups) == res.dims_reduced
    # the fixed values are θ̄'s (quantized)
    pos = {n: i for i, n in enumerate(res.curves.names)}
    for n, v in d.fixed.items():
        assert v == pytest.approx(res.theta_bar[pos[n]], abs=0.006)
    # the simulator check swept the same parameters; the validation ran on the reduced definition
    assert res.true_curves is not None and res.true_curves.names == res.curves.names
    v = res.validation
    assert v is not None and v.reduced_true_j.size == 2 and v.full_true_j.size == 2
    assert v.j_star_known == pytest.approx(1.0) and v.j_full_best == pytest.approx(v.full_true_j.min())
    assert v.j_star_reduced >= 1.0 - 1e-12 and v.loss_vs_known_pct >= 0  # nothing beats the true optimum
    assert v.loss_vs_phase_pct == pytest.approx(100 * (v.j_star_reduced / v.j_full_best - 1))
    assert v.loss_pct == pytest.approx(v.loss_vs_known_pct)  # judged against the best known J* when there is one
    assert v.table_pct == pytest.approx(100 * (v.reduced_true_j.mean() / v.full_true_j.mean() - 1))
    assert (
        v.j_star_reduced
        <= min(
            v.reduced_true_j.min(),
            obj.with_definition(d).true_j(np.array([[start_point(res)[x.name] for x in d.dimensions]]))[0],
        )
        + 1e-12
    )
    assert v.j_med_reduced > v.j_star_reduced
    assert any("campaigns done" in s for s in lines)
    # files
    files = write_outputs(res, tmp_path / "out", plots=False)
    loaded = CalibrationDefinition.load(files["definition"])
    assert loaded.tuned == d.tuned and loaded.fixed == d.fixed
    text = files["definition"].read_text()
    assert text.startswith("# Meta-parameter file written by `bac reduce`")
    data = json.loads(files["result"].read_text())
    assert data["kept"] == list(res.kept) and len(data["campaigns"]) == 2
    assert LAST.match(files["report"].read_text().splitlines()[-1])
    # and its CAN description beside it: the raw parameters on the bus, one signal each
    import cantools

    db = cantools.database.load_file(str(files["dbc"]))
    signals = {s.name for m in db.messages for s in m.signals}
    assert files["dbc"] == files["definition"].with_suffix(".dbc")
    assert {f"P_{x.name}" for x in d.parameters} <= signals, signals


def test_fixed_at_nominal_and_the_plain_average(tmp_path: Path) -> None:
    res = run_reduction(tiny(fixed_at="nominal", surrogate="mean", verify_points=0, validate_repeats=0))
    assert all(v == 500.0 for v in res.definition.fixed.values())
    assert res.true_curves is None and res.validation is None
    assert res.other_curves is not None  # the other average, for the report's comparison column
    files = write_outputs(res, tmp_path, plots=False)
    assert files["report"].read_text().splitlines()[-1].endswith("loss_pct nan loss_vs_phase_pct nan")


def test_the_cli_writes_the_file_the_plots_and_ends_with_the_figure_line(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    meta = tmp_path / "calibrations" / "synthetic_small.yaml"
    argv = ["--problem", "synthetic", "-M", "2", "-N", "14", "--n-initial", "6", "--workers", "1", "--batch", "4"]
    argv += ["--optimizer", "agent", "--polish-evals", "0", "--global-method", "morris", "--global-runs", "90"]
    argv += ["--engine-config", json.dumps(QUICK), "--validate-repeats", "2", "--validate-trials", "8"]
    argv += ["--verify-points", "5", "--out", str(tmp_path / "out"), "--definition-out", str(meta)]
    argv += ["--name", "synthetic_small", "--quiet"]
    assert reduce_cli.main(argv) == 0
    out = capsys.readouterr().out.strip().splitlines()
    m = LAST.match(out[-1])
    assert m, out[-1]
    d = CalibrationDefinition.load(meta)
    assert d.name == "synthetic_small" and int(m.group(2)) == len(d.dimensions)
    assert any(line.startswith("== similarity:") for line in out)
    for png in ("optima_boxplot", "worst_loss", "sensitivity_kept", "campaigns", "validation"):
        p = tmp_path / "out" / f"{png}.png"
        assert p.stat().st_size > 10_000, png  # a real figure, not an empty canvas
    # the stored campaigns can be re-analysed with other thresholds without running them again
    first = json.loads((tmp_path / "out" / "result.json").read_text())
    argv2 = ["--from-result", str(tmp_path / "out" / "result.json"), "--threshold", "0.15", "--quiet"]
    argv2 += ["--validate-repeats", "0", "--verify-points", "0", "--no-plots", "--out", str(tmp_path / "again")]
    assert reduce_cli.main(argv2) == 0
    again = json.loads((tmp_path / "again" / "result.json").read_text())
    assert again["campaigns"] == first["campaigns"] and again["backend"] == "stored campaigns"
    assert again["curves"]["loss"] == pytest.approx(first["curves"]["loss"])
    names, losses = first["curves"]["names"], first["curves"]["loss"]
    assert set(again["kept"]) == {n for n, s in zip(names, losses, strict=True) if s > 0.15}
    capsys.readouterr()
    # the values the ECU would receive for any point of the reduced space stay within the raw bounds
    dims = d.dimensions
    rng = np.random.default_rng(0)
    for _ in range(20):
        raw = d.expand({x.name: x.lower + rng.random() * (x.upper - x.lower) for x in dims})
        d.check_raw(raw)


def test_cli_errors_are_reported_not_raised(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    argv = ["--problem", "synthetic", "-M", "1", "-N", "6", "--workers", "1", "--fixed-at", "optimum", "--batch", "2"]
    argv += ["--optimizer", "agent", "--polish-evals", "0", "--global-method", "none"]
    argv += ["--threshold", "5.0", "--engine-config", json.dumps(QUICK), "--out", str(tmp_path)]
    assert reduce_cli.main(argv) == 2
    assert "no parameter has a worst loss above T = 500 %" in capsys.readouterr().err
    with pytest.raises(ReductionError, match="unknown problem"):
        make_objective("road_c9")


def test_an_already_reduced_definition_is_refused() -> None:
    obj = SyntheticObjective()
    red = reduced_definition(
        obj.definition,
        [Group(("q1", "q2"), 0.8, ((0.8, 0.8), (0.8, 0.8)))],
        dict.fromkeys(obj.definition.parameter_names, 1.0),
    )
    with pytest.raises(ReductionError, match="already reduced"):
        run_reduction(tiny(), obj.with_definition(red))


def test_the_simulated_car_through_a_meta_parameter_file_is_the_same_car() -> None:
    """road_c2 via a reduced definition gives the J of the expanded raw calibration (what the ECU gets)."""
    car = SimulatedCar("road_c2")
    base = car.definition
    theta = dict.fromkeys(base.parameter_names, 500.0)
    groups = [Group(("p02", "p03", "p05"), 1.0, ((1.0, 1.0),) * 3), Group(("p06",), 0.5, ((0.5, 0.5),))]
    red = reduced_definition(base, groups, theta)
    reduced = car.with_definition(red)
    assert tuple(x.name for x in reduced.definition.dimensions) == ("m1", "p06")
    raw = red.expand({"m1": 900.0, "p06": 250.0})
    assert raw["p02"] == raw["p03"] == raw["p05"] == 900.0 and raw["p06"] == 250.0 and raw["p01"] == 500.0
    j_red = reduced.true_j(np.array([[900.0, 250.0]]))
    j_full = car.true_j(np.array([[raw[n] for n in base.parameter_names]]))
    np.testing.assert_allclose(j_red, j_full, rtol=1e-12)
    assert 0.5 < float(j_red[0]) < 2.0
    yaml.safe_dump(red.to_dict())  # serializable as the meta-parameter file


def test_the_phase_output_is_a_transfer_prior_for_the_agent(tmp_path: Path) -> None:
    """issue 23: bo_agent's prior_source reads a bac reduce output: J_mu through the meta-parameter file."""
    from bac_agent.bo import SearchSpace
    from bac_agent.transfer import TransferError, load_source
    from bac_reduce.pipeline import PosteriorMean

    res = run_reduction(tiny(verify_points=0, validate_repeats=0))
    files = write_outputs(res, tmp_path / "out", plots=False)
    d = CalibrationDefinition.load(files["definition"])
    src = load_source(tmp_path / "out", d, points=64)
    assert src.dim == len(d.dimensions) and "J_mu of 2 campaigns" in src.label
    # the surface is the phase's own J_mu (bac_reduce.pipeline.PosteriorMean) through the definition
    space = SearchSpace.from_definition(d)
    j_mu = PosteriorMean.from_campaigns(res.campaigns)
    U = np.random.default_rng(0).random((10, space.dim))
    names = list(res.campaigns[0].names)
    R = np.array([[d.expand(space.to_params(space.from_unit(u)))[n] for n in names] for u in U])
    want = j_mu(R)
    assert np.max(np.abs(src.predict_j(U) - want)) < 0.02 * (np.max(want) - np.min(want) + 1e-9) + 1e-3
    # the same file as a result.json path; a folder that is neither output is refused with a clear message
    assert load_source(files["result"], d, points=64).X.shape == src.X.shape
    with pytest.raises(TransferError, match="neither a bac reduce output"):
        load_source(tmp_path, d)


@dataclass(frozen=True)
class WithTravel(SyntheticObjective):
    """The synthetic J, and a travel each run reports: 80 mm soft (r1 = 0) to 40 mm firm, + 10 r4 (issue 23)."""

    @staticmethod
    def travel(raw: np.ndarray) -> np.ndarray:
        r = np.atleast_2d(raw) / 1000.0
        return np.asarray(80.0 - 40.0 * r[:, 0] + 10.0 * r[:, 3])

    def evaluate_runs(self, thetas: np.ndarray, rng: object) -> tuple[np.ndarray, dict[str, np.ndarray]]:
        return self.evaluate(thetas, rng), {"max_travel_mm": self.travel(self._raw(thetas))}  # type: ignore[arg-type]

    def with_definition(self, definition: CalibrationDefinition) -> WithTravel:
        s = super().with_definition(definition)
        return WithTravel(s.terms, s.j0, s.coupling, s.noise_rel, s.lower, s.upper, s.tuned, s.meta, s.fixed)


def test_the_phase_records_the_runs_outcomes_and_they_are_the_cars_outcome_priors(tmp_path: Path) -> None:
    """issue 23: the simulation phase keeps what each run reports besides J (result.json schema 2), and bo_agent's
    prior_source builds the limited outcomes' priors from them through the meta-parameter file; a result.json from
    before (schema 1, no outcomes) still loads and gives none."""
    from bac_agent.bo import SearchSpace
    from bac_agent.transfer import TransferError, load_outcome_sources, load_source
    from bac_reduce.campaigns import CampaignResult

    obj = WithTravel()
    res = run_reduction(tiny(verify_points=0, validate_repeats=0), obj)
    for c in res.campaigns:  # every run's travel, in the order of its runs
        assert set(c.outcomes) == {"max_travel_mm"}
        np.testing.assert_allclose(c.outcomes["max_travel_mm"], obj.travel(c.X))
        again = CampaignResult.from_dict(json.loads(json.dumps(c.to_dict())))
        np.testing.assert_array_equal(again.outcomes["max_travel_mm"], c.outcomes["max_travel_mm"])
    files = write_outputs(res, tmp_path / "out", plots=False)
    data = json.loads(files["result"].read_text())
    assert data["schema_version"] == 2 and len(data["campaigns"][0]["outcomes"]["max_travel_mm"]) == 16
    d = CalibrationDefinition.load(files["definition"])
    got = load_outcome_sources(tmp_path / "out", d, ["max_travel_mm", "lift_off_ms"])
    assert set(got) == {"max_travel_mm"}  # lift_off_ms: no run reported it
    assert (
        got["max_travel_mm"].label.startswith("max_travel_mm: bac reduce")
        and "32 runs of 2 campaigns" in got["max_travel_mm"].label
    )
    space = SearchSpace.from_definition(d)
    U = np.random.default_rng(0).random((20, space.dim))
    names = list(res.campaigns[0].names)
    R = np.array([[d.expand(space.to_params(space.from_unit(u)))[n] for n in names] for u in U])
    # the surrogate through the meta-parameter file: within a few mm of the travel (a 40 mm range)
    assert np.median(np.abs(got["max_travel_mm"].predict_j(U) - obj.travel(R))) < 3.0
    # the same from the result.json path; a result.json from before outcomes (schema 1) gives none, J still loads
    assert set(load_outcome_sources(files["result"], d, ["max_travel_mm"])) == {"max_travel_mm"}
    old = dict(data)
    del old["schema_version"]
    old["campaigns"] = [{k: v for k, v in c.items() if k != "outcomes"} for c in data["campaigns"]]
    (tmp_path / "old.json").write_text(json.dumps(old))
    assert load_outcome_sources(tmp_path / "old.json", d, ["max_travel_mm"]) == {}
    assert load_source(tmp_path / "old.json", d, points=64).dim == space.dim
    assert CampaignResult.from_dict(old["campaigns"][0]).outcomes == {}
    (tmp_path / "new.json").write_text(json.dumps({**data, "schema_version": 3}))
    with pytest.raises(TransferError, match="newer bac"):
        load_outcome_sources(tmp_path / "new.json", d, ["max_travel_mm"])
