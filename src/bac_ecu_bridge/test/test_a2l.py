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


def test_every_truncation_of_an_a2l_is_refused_and_never_read_to_a_wrong_bound(tmp_path: Path) -> None:
    # outside review 2026-11-29: pya2ldb logs "Premature end of file" and goes on; a file cut within damping_rear's
    # limits ("... 0.0 0.9" of 0.95) gave an upper bound of 0.9 with exit code 0
    text = shipped_a2l("controller_i").read_text().replace("0.0 1.0\n", "0.0 0.95\n")
    whole = tmp_path / "whole.a2l"
    whole.write_text(text)
    assert definition_from_a2l(whole, ["damping_rear"], values={"damping_rear": 0.5}).parameters[0].upper == 0.95
    cut = tmp_path / "cut.a2l"
    cut.write_text(text[: text.rindex("0.95") + 3])  # "... 0.0 0.9"
    with pytest.raises(A2lError, match=r"ends inside /begin CHARACTERISTIC \(line 94\).*truncated"):
        definition_from_a2l(cut, ["damping_rear"], values={"damping_rear": 0.5})
    argv = ["from-a2l", str(cut), "-c", "damping_rear", "--set", "damping_rear=0.5", "-o", str(tmp_path / "d.yaml")]
    assert definition_main(argv) == 2 and not (tmp_path / "d.yaml").exists()
    lines = text.splitlines(keepends=True)
    for k in range(1, len(lines)):  # every cut after a whole line, the last /end PROJECT's included
        with pytest.raises(A2lError, match=r"truncated|never ends|not an A2L file"):
            read_a2l_text(tmp_path, "".join(lines[:k]))


def read_a2l_text(tmp_path: Path, text: str) -> object:
    p = tmp_path / "t.a2l"
    p.write_text(text)
    return read_a2l(p)


def test_a_broken_block_structure_is_named_and_comments_and_strings_do_not_count(tmp_path: Path) -> None:
    text = shipped_a2l("controller_i").read_text()
    with pytest.raises(A2lError, match=r"line 96: /end MODULE closes /begin CHARACTERISTIC of line 94"):
        read_a2l_text(tmp_path, text.replace("    /end CHARACTERISTIC\n  /end MODULE", "  /end MODULE", 1))
    with pytest.raises(A2lError, match="a comment that never ends"):
        read_a2l_text(tmp_path, text.replace("/end PROJECT", "/end PROJECT /* cut"))
    with pytest.raises(A2lError, match="not an A2L file"):
        read_a2l_text(tmp_path, "ASAP2_VERSION 1 71\n")
    # a /begin or /end within a comment or a string is text, not a block
    noisy = text.replace('"constant damping command of both rear dampers"', '"rear /end MODULE"').replace(
        "/end PROJECT", "/* /begin MODULE x */ // /end PROJECT\n/end PROJECT"
    )
    assert read_a2l_text(tmp_path, noisy).characteristics["damping_rear"].description == "rear /end MODULE"


def test_a_limit_that_is_not_a_number_is_named_without_the_parsers_sql(tmp_path: Path) -> None:
    text = shipped_a2l("controller_i").read_text().replace("CM_controller_i_1 0.0 1.0\n", "CM_controller_i_1 0.0 NaN\n")
    with pytest.raises(A2lError, match="a CHARACTERISTIC has no valid upperLimit") as err:
        read_a2l_text(tmp_path, text)
    assert "SQL" not in str(err.value) and "INSERT" not in str(err.value)
