"""Calibration definitions: bounds, meta-parameters, (de)serialization."""

from __future__ import annotations

from pathlib import Path

import pytest

from bac_common.errors import DefinitionError, OutOfBoundsError, UnknownParameterError
from bac_common.paramspace import CalibrationDefinition, MetaParameter, RawParameter, uniform_parameters

CALIB = Path(__file__).resolve().parents[1] / "calibrations"


def controller_ii(**kw: object) -> CalibrationDefinition:
    return CalibrationDefinition(
        name="c2",
        parameters=uniform_parameters("p", 20, 0.0, 1000.0, 500.0, 0.01),
        **kw,  # type: ignore[arg-type]
    )


def test_shipped_definitions_load() -> None:
    c1 = CalibrationDefinition.load(CALIB / "controller_i.yaml")
    assert c1.tuned == ("damping_front", "damping_rear")
    assert [(d.lower, d.upper) for d in c1.dimensions] == [(0.0, 1.0), (0.0, 1.0)]
    c2 = CalibrationDefinition.load(CALIB / "controller_ii.yaml")
    assert len(c2.dimensions) == 20 and c2.parameter("p20").index == 19
    assert c2.baseline_values()["p07"] == 500.0


def test_expand_meta_parameters_and_fixed_values() -> None:
    d = controller_ii(
        tuned=("m1", "p08"),
        meta=(MetaParameter("m1", ("p05", "p06", "p07"), 0.0, 1000.0),),
        fixed={"p01": 123.0},
    )
    raw = d.expand({"m1": 250.0, "p08": 900.0})
    assert raw["p05"] == raw["p06"] == raw["p07"] == 250.0
    assert raw["p08"] == 900.0 and raw["p01"] == 123.0 and raw["p02"] == 500.0
    assert len(raw) == 20


def test_meta_parameter_maps_relative_position_into_each_members_range() -> None:
    d = CalibrationDefinition(
        name="x",
        parameters=(RawParameter("a", 0, 0.0, 1.0, 0.5, 1e-4), RawParameter("b", 1, 100.0, 300.0, 200.0, 0.1)),
        tuned=("m",),
        meta=(MetaParameter("m", ("a", "b"), 0.0, 10.0),),
    )
    raw = d.expand({"m": 2.5})
    assert raw["a"] == pytest.approx(0.25) and raw["b"] == pytest.approx(150.0)


def test_the_baseline_in_the_tuned_dimensions_is_what_an_optimizer_can_start_from() -> None:
    c1 = CalibrationDefinition.load(CALIB / "controller_i.yaml")
    assert c1.baseline_tuned() == {"damping_front": 0.5, "damping_rear": 0.5}
    d = CalibrationDefinition(
        name="x",
        parameters=(RawParameter("a", 0, 0.0, 1.0, 0.5, 1e-4), RawParameter("b", 1, 100.0, 300.0, 200.0, 0.1)),
        tuned=("m",),
        meta=(MetaParameter("m", ("a", "b"), 0.0, 10.0),),
        baseline={"a": 0.2, "b": 180.0},  # relative positions 0.2 and 0.4
    )
    assert d.baseline_tuned() == {"m": pytest.approx(3.0)}
    assert d.expand(d.baseline_tuned())["a"] == pytest.approx(0.3)


@pytest.mark.parametrize("value", [-0.001, 1.0001, float("nan"), float("inf")])
def test_out_of_bounds_values_are_refused(value: float) -> None:
    c1 = CalibrationDefinition.load(CALIB / "controller_i.yaml")
    with pytest.raises(OutOfBoundsError, match="damping_rear"):
        c1.expand({"damping_front": 0.5, "damping_rear": value})


def test_unknown_and_missing_names() -> None:
    c1 = CalibrationDefinition.load(CALIB / "controller_i.yaml")
    with pytest.raises(UnknownParameterError, match="damping_middle"):
        c1.expand({"damping_front": 0.5, "damping_rear": 0.5, "damping_middle": 0.1})
    with pytest.raises(DefinitionError, match="lacks"):
        c1.expand({"damping_front": 0.5})


def test_quantize_to_can_resolution() -> None:
    p = RawParameter("x", 0, 0.0, 1000.0, 500.0, 0.01)
    assert p.quantize(123.456) == pytest.approx(123.46)
    assert p.quantize(1000.0) == 1000.0
    with pytest.raises(OutOfBoundsError):
        p.quantize(1000.01)


@pytest.mark.parametrize(
    ("kw", "match"),
    [
        ({"tuned": ("p01", "p01")}, "twice"),
        ({"tuned": ("m1", "p05"), "meta": (MetaParameter("m1", ("p05", "p06")),)}, "also driven"),
        ({"tuned": ("zz",)}, "neither"),
        ({"fixed": {"p01": 5000.0}}, "outside"),
        ({"tuned": ("p01",), "fixed": {"p01": 1.0}}, "both fixed and tuned"),
    ],
)
def test_malformed_definitions_are_refused(kw: dict[str, object], match: str) -> None:
    with pytest.raises((DefinitionError, OutOfBoundsError), match=match):
        controller_ii(**kw)


def test_yaml_round_trip(tmp_path: Path) -> None:
    d = controller_ii(tuned=("m1", "p08"), meta=(MetaParameter("m1", ("p05", "p06", "p07"), 0.0, 1000.0),))
    d.save(tmp_path / "d.yaml")
    assert CalibrationDefinition.load(tmp_path / "d.yaml") == d


def test_best_guess_is_kept_checked_and_round_trips(tmp_path: Path) -> None:
    meta = (MetaParameter("m1", ("p05", "p06"), 0.0, 1000.0),)
    d = controller_ii(tuned=("m1", "p08"), meta=meta, best_guess={"m1": 0.0, "p08": 750.0})
    d.save(tmp_path / "d.yaml")
    assert CalibrationDefinition.load(tmp_path / "d.yaml").best_guess == {"m1": 0.0, "p08": 750.0}
    with pytest.raises(DefinitionError, match="every tuned dimension"):
        controller_ii(tuned=("m1", "p08"), meta=meta, best_guess={"m1": 0.0})
    with pytest.raises(DefinitionError, match="outside"):
        controller_ii(tuned=("m1", "p08"), meta=meta, best_guess={"m1": 1200.0, "p08": 1.0})
    shipped = CalibrationDefinition.load(CALIB / "controller_ii_reduced.yaml")
    assert set(shipped.best_guess) == set(shipped.tuned)
