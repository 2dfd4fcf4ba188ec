"""The XCP memory layout codec: conversions, data types, byte orders, quantization, runs."""

from __future__ import annotations

import math
import struct

import numpy as np
import pytest

from bac_common.errors import DefinitionError, OutOfBoundsError
from bac_common.paramspace import CalibrationDefinition, EcuAddress, RawParameter
from bac_ecu_bridge.errors import ProtocolConfigError
from bac_ecu_bridge.xcp.layout import XcpLayout, XcpParam


def param(name: str, index: int, where: EcuAddress, lower: float = 0.0, upper: float = 1.0) -> RawParameter:
    return RawParameter(name, index, lower, upper, (lower + upper) / 2, 0.0001, xcp=where)


def test_linear_rat_func_and_identical_conversions() -> None:
    lin = XcpParam.of(param("a", 0, EcuAddress(0x100, "UWORD", conversion="LINEAR", coeffs=(0.0001, 0.0))))
    rat = XcpParam.of(param("b", 1, EcuAddress(0x102, "UWORD", conversion="RAT_FUNC", coeffs=(0, 10000, 0, 0, 0, 1))))
    assert lin.factor == pytest.approx(0.0001) and rat.factor == pytest.approx(0.0001)
    assert lin.encode(0.12346) == rat.encode(0.12346) == struct.pack("<H", 1235)
    assert lin.quantize(0.12346) == rat.quantize(0.12346) == pytest.approx(0.1235)
    ident = XcpParam.of(param("c", 2, EcuAddress(0x104, "SWORD"), -100.0, 100.0))
    assert ident.encode(-12.4) == struct.pack("<h", -12) and ident.quantize(-12.6) == -13.0
    # an offset: p = 0.5 x - 40 (a temperature in a byte)
    temp = XcpParam.of(param("t", 3, EcuAddress(0x106, "UBYTE", conversion="LINEAR", coeffs=(0.5, -40.0)), -40, 87.5))
    assert temp.encode(20.2) == bytes([120]) and temp.quantize(20.2) == 20.0


def test_byte_order_and_extension() -> None:
    big = XcpParam.of(
        param(
            "a", 0, EcuAddress(0x100, "ULONG", byte_order="MSB_FIRST", conversion="LINEAR", coeffs=(0.01, 0)), 0, 1000
        )
    )
    assert big.encode(500.0) == struct.pack(">I", 50000)
    assert big.decode(struct.pack(">I", 12345)) == pytest.approx(123.45)


def test_values_never_leave_the_bounds_and_the_grid_is_clamped_into_them() -> None:
    # bounds off the conversion's grid: the nearest internal values inside them are taken
    p = XcpParam.of(param("a", 0, EcuAddress(0, "UWORD", conversion="LINEAR", coeffs=(0.3, 0.0)), 0.1, 2.0))
    assert (p.x_min, p.x_max) == (1, 6)
    assert p.quantize(0.1) == pytest.approx(0.3) and p.quantize(2.0) == pytest.approx(1.8)
    for bad in (0.0999, 2.0001, math.nan, math.inf):
        with pytest.raises(OutOfBoundsError):
            p.encode(bad)
    # a data type too small for the range is refused at load time
    with pytest.raises(ProtocolConfigError, match=r"need internal values -300..-290, beyond what a UBYTE holds"):
        XcpParam.of(param("b", 1, EcuAddress(0, "UBYTE", conversion="LINEAR", coeffs=(1.0, 300.0)), 0, 10))
    # also when only part of the range is beyond it: a UBYTE with bounds 0..300 wrote 255 for 256..300 (review
    # 2026-11-29); -10..100 wrote 0 below 0
    for lo, hi in ((0, 300), (-10, 100)):
        with pytest.raises(ProtocolConfigError, match=r"beyond what a UBYTE holds \(0..255\)"):
            XcpParam.of(param("c", 2, EcuAddress(0, "UBYTE"), lo, hi))
    with pytest.raises(ProtocolConfigError, match=r"beyond what a SBYTE holds \(-128..127\)"):
        XcpParam.of(param("d", 3, EcuAddress(0, "SBYTE"), -200, 100))


def test_float32_values_stay_inside_the_bounds() -> None:
    p = XcpParam.of(param("f", 0, EcuAddress(0, "FLOAT32_IEEE"), 0.0, 0.1))
    q = p.quantize(0.1)  # 0.1 as float32 is 0.10000000149: nudged back to the float32 below it
    assert q <= 0.1 and q == pytest.approx(0.1, rel=1e-7)
    assert q == float(np.float32(q))
    assert p.decode(p.encode(0.05)) == float(np.float32(0.05))


def test_runs_group_contiguous_parameters_and_overlaps_are_refused() -> None:
    d = CalibrationDefinition(
        "d",
        (
            param("a", 0, EcuAddress(0x100, "UWORD")),
            param("b", 1, EcuAddress(0x102, "UWORD")),
            param("c", 2, EcuAddress(0x200, "UBYTE")),
            param("e", 3, EcuAddress(0x100, "UWORD", extension=1)),
        ),
    )
    layout = XcpLayout(d)
    assert [(r.extension, r.address, r.size, [p.name for p in r.params]) for r in layout.runs] == [
        (0, 0x100, 4, ["a", "b"]),
        (0, 0x200, 1, ["c"]),
        (1, 0x100, 2, ["e"]),
    ]
    image = layout.image({"a": 1.0, "b": 0.0, "c": 1.0, "e": 0.0})
    assert layout.decode(image) == {"a": 1.0, "b": 0.0, "c": 1.0, "e": 0.0}
    with pytest.raises(ProtocolConfigError, match="missing"):
        layout.image({"a": 1.0})
    clash = CalibrationDefinition(
        "x", (param("a", 0, EcuAddress(0x100, "ULONG")), param("b", 1, EcuAddress(0x102, "UWORD")))
    )
    with pytest.raises(ProtocolConfigError, match="overlap"):
        XcpLayout(clash)
    with pytest.raises(ProtocolConfigError, match="has no XCP address"):
        XcpLayout(CalibrationDefinition("y", (RawParameter("a", 0, 0, 1, 0.5, 0.1),)))


def test_ecu_address_validation_and_yaml_round_trip(tmp_path: object) -> None:
    with pytest.raises(DefinitionError, match="not linear"):
        EcuAddress(0, "UWORD", conversion="RAT_FUNC", coeffs=(1, 2, 0, 0, 0, 1))
    with pytest.raises(DefinitionError, match="datatype"):
        EcuAddress(0, "UINT16")
    with pytest.raises(DefinitionError, match="takes 2 coefficients"):
        EcuAddress(0, "UWORD", conversion="LINEAR", coeffs=(1.0,))
    where = EcuAddress(0x40000000, "SLONG", "MSB_FIRST", 3, "LINEAR", (0.5, 1.0), "Ctrl.Gain")
    d = CalibrationDefinition("z", (param("g", 0, where, -10, 10),), xcp={"can_id_master": 0x7E0})
    again = CalibrationDefinition.from_dict(d.to_dict())
    assert again.parameters[0].xcp == where and again.xcp == {"can_id_master": 0x7E0}


def test_a_definition_off_the_ecus_grid_is_named() -> None:
    """The bridge warns of a hand-written definition whose agent grid (lower + k x resolution) is not the ECU's: the
    value told would not be the value held (outside review 2026-11-29: asks of 6 and 10 both wrote 8)."""
    on = XcpParam.of(RawParameter("g", 0, 4.0, 60.0, 32.0, 4.0, xcp=EcuAddress(0, "UBYTE", conversion="LINEAR",
                                                                            coeffs=(4.0, 0.0))))  # fmt: skip
    assert on.off_grid(4.0) == "" and on.off_grid(8.0) == ""
    assert "lower 2, upper 62 not on it" in XcpParam.of(
        RawParameter("g", 0, 2.0, 62.0, 30.0, 4.0, xcp=on.where)
    ).off_grid(4.0)
    assert "resolution 0.0001 no multiple of 4" in on.off_grid(0.0001)
    assert XcpParam.of(param("f", 1, EcuAddress(0, "FLOAT32_IEEE"), 0.1, 0.3)).off_grid(0.0001) == ""
