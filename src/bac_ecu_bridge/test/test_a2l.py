"""Calibration definitions from A2L files (pya2ldb) and back: addresses, types, byte orders, conversions, bounds,
resolutions and the XCP-on-CAN settings survive both ways."""

from __future__ import annotations

from pathlib import Path

import pytest
import yaml

from bac_common.paramspace import CalibrationDefinition, EcuAddress, RawParameter
from bac_common.paths import resolve_definition
from bac_ecu_bridge.definition_cli import main as definition_main
from bac_ecu_bridge.xcp.a2l import A2lError, a2l_text, definition_from_a2l, read_a2l, shipped_a2l


def shipped(name: str) -> CalibrationDefinition:
    return CalibrationDefinition.load(resolve_definition(name))


def same_parameters(a: CalibrationDefinition, b: CalibrationDefinition) -> None:
    assert [p.name for p in a.parameters] == [p.name for p in b.parameters]
    for p, q in zip(a.parameters, b.parameters, strict=True):
        assert (p.index, p.lower, p.upper, p.nominal) == (q.index, q.lower, q.upper, q.nominal), p.name
        assert p.resolution == pytest.approx(q.resolution, rel=1e-12), p.name
        assert p.xcp == q.xcp, p.name  # address, extension, data type, byte order, conversion and its coefficients
    for key in ("can_id_master", "can_id_slave", "reference_page", "working_page", "segment"):
        assert a.xcp.get(key) == b.xcp.get(key), key


@pytest.mark.parametrize("name", ["controller_i", "controller_ii"])
def test_the_shipped_a2l_reads_to_the_shipped_definition_and_back(name: str, tmp_path: Path) -> None:
    d = shipped(name)
    names = [p.name for p in d.parameters]
    from_a2l = definition_from_a2l(shipped_a2l(name), names, name=name, values=d.baseline_values())
    same_parameters(from_a2l, d)
    assert from_a2l.xcp["can_id_master"] == 0x7E0 and from_a2l.xcp["can_id_slave"] == 0x7E1
    assert from_a2l.xcp["pages"] is True
    # and the A2L written from the definition reads back to it again
    out = tmp_path / f"{name}.a2l"
    out.write_text(a2l_text(from_a2l))
    same_parameters(definition_from_a2l(out, names, name=name, values=d.baseline_values()), d)


def test_identical_float_motorola_and_an_address_extension_round_trip(tmp_path: Path) -> None:
    params = (
        RawParameter("gain", 0, -2.5, 2.5, 0.5, 1e-4, unit="1",
                     xcp=EcuAddress(0x2000_0010, "FLOAT32_IEEE", "MSB_FIRST", 1, "IDENTICAL")),
        RawParameter("offset_mm", 1, -40.0, 40.0, 0.0, 0.5, unit="mm",
                     xcp=EcuAddress(0x2000_0014, "SWORD", "MSB_FIRST", 1, "LINEAR", (0.5, 0.0))),
    )  # fmt: skip
    xcp = {"can_id_master": 0x600, "can_id_slave": 0x601, "segment": 0, "reference_page": 0, "working_page": 1}
    d = CalibrationDefinition("bench", params, baseline={"gain": 0.5, "offset_mm": 0.0}, xcp=xcp)
    out = tmp_path / "bench.a2l"
    out.write_text(a2l_text(d))
    module = read_a2l(out)
    assert module.characteristics["gain"].byte_order == "MSB_FIRST" and module.characteristics["gain"].extension == 1
    back = definition_from_a2l(out, ["gain", "offset_mm"], name="bench", values=d.baseline_values())
    same_parameters(back, d)
    assert back.parameters[1].unit == "mm"


def test_a_nonlinear_rat_func_is_refused_with_its_reason(tmp_path: Path) -> None:
    text = shipped_a2l("controller_i").read_text()
    linear = "COEFFS 0.0 10000.0 0.0 0.0 0.0 1.0"
    assert linear in text
    bad = tmp_path / "bad.a2l"
    bad.write_text(text.replace(linear, "COEFFS 1.0 10000.0 0.0 0.0 0.0 1.0"))  # a x^2 term
    with pytest.raises(A2lError, match="RAT_FUNC"):
        definition_from_a2l(bad, ["damping_front"], values={"damping_front": 0.5})


def test_bac_definition_from_a2l_writes_a_definition_the_bridge_loads(tmp_path: Path) -> None:
    out = tmp_path / "ii.yaml"
    argv = ["from-a2l", str(shipped_a2l("controller_ii")), "-c", "p03", "p01", "-o", str(out), "--name", "two"]
    assert definition_main([*argv, "--set", "p01=250", "--set", "p03=750"]) == 0
    d = CalibrationDefinition.load(out)
    assert d.name == "two" and [p.name for p in d.parameters] == ["p03", "p01"]  # the order given is the index order
    assert d.baseline_values() == {"p03": 750.0, "p01": 250.0}
    ii = shipped("controller_ii")
    assert d.parameters[0].xcp == ii.parameter("p03").xcp and d.parameters[1].xcp == ii.parameter("p01").xcp
    assert yaml.safe_load(out.read_text())["xcp"]["can_id_master"] == 0x7E0
    # without values the definition is refused (the baseline is what a car is left on)
    assert definition_main(["from-a2l", str(shipped_a2l("controller_ii")), "-c", "p01"]) == 2
