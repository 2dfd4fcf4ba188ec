"""A2L features a supplier's file may hold that bac cannot write as one value: refused with the reason, never read
to a wrong address, value or page (outside review 2026-11-29; each case was read silently before)."""

from __future__ import annotations

import struct
from pathlib import Path

import pytest
from a2l_builder import MODPAR, a2l

from bac_ecu_bridge.xcp.a2l import A2lError, definition_from_a2l, read_a2l
from bac_ecu_bridge.xcp.layout import XcpParam


def char(name: str = "C1", address: str = "0x40000000", layout: str = "RL_UBYTE", cm: str = "CM_ID",
         lo: str = "0", hi: str = "15", extra: str = "", kind: str = "VALUE") -> str:  # fmt: skip
    return f'/begin CHARACTERISTIC {name} "d" {kind} {address} {layout} 0 {cm} {lo} {hi} {extra} /end CHARACTERISTIC'


def write(tmp_path: Path, body: str, name: str = "ecu.a2l", **kw: str) -> Path:
    p = tmp_path / name
    p.write_text(a2l(body, **kw))
    return p


@pytest.mark.parametrize(
    ("body", "reason"),
    [
        (char(extra="BIT_MASK 0xF0"), "BIT_MASK 0xf0: the value is some bits of a UBYTE"),
        (char(extra="READ_ONLY"), "READ_ONLY"),
        (char(extra="CALIBRATION_ACCESS NO_CALIBRATION"), "CALIBRATION_ACCESS NO_CALIBRATION"),
        (char(extra="CALIBRATION_ACCESS OFFLINE_CALIBRATION"), "CALIBRATION_ACCESS OFFLINE_CALIBRATION"),
        (
            char(layout="RL_PTR") + "\n/begin RECORD_LAYOUT RL_PTR FNC_VALUES 1 UWORD ROW_DIR PLONG /end RECORD_LAYOUT",
            "through a pointer (FNC_VALUES ... PLONG)",
        ),
        (
            char(layout="RL_OFF")
            + "\n/begin RECORD_LAYOUT RL_OFF RESERVED 1 BYTE FNC_VALUES 2 UWORD ROW_DIR DIRECT /end RECORD_LAYOUT",
            "puts 1 element(s) (RESERVED, IDENTIFICATION) before FNC_VALUES",
        ),
        (char(layout="RL_NONE"), "its RECORD_LAYOUT RL_NONE is not in the A2L"),
        (char() + "\n" + char(address="0x40000100", hi="250"), "defined 2 times (at 0x40000000, 0x40000100)"),
        (char(extra="BYTE_ORDER BIG_ENDIAN"), "BYTE_ORDER BIG_ENDIAN (deprecated"),
    ],
    ids=[
        "bit_mask",
        "read_only",
        "no_calibration",
        "offline",
        "pointer",
        "reserved_first",
        "no_layout",
        "twice",
        "big_endian",
    ],
)
def test_a_characteristic_bac_cannot_write_as_one_value_is_refused(tmp_path: Path, body: str, reason: str) -> None:
    path = write(tmp_path, body)
    with pytest.raises(A2lError, match="bac cannot write C1: ") as exc:
        definition_from_a2l(path, ["C1"], midpoint=True)
    assert reason in str(exc.value)
    assert reason.split(" (", maxsplit=1)[0] in read_a2l(path).problems["C1"]
    with pytest.raises(A2lError, match=r"no characteristic bac can write \(C1: "):  # --all, and nothing else
        definition_from_a2l(path, None, midpoint=True)


def test_a_curve_is_refused_by_what_it_is(tmp_path: Path) -> None:
    path = write(tmp_path, char() + "\n" + char("Gain", "0x40000010", kind="CURVE"))
    with pytest.raises(A2lError, match="bac cannot write Gain: a CURVE: bac tunes VALUE characteristics"):
        definition_from_a2l(path, ["Gain"], midpoint=True)
    notes: list[str] = []
    d = definition_from_a2l(path, None, midpoint=True, notes=notes)  # --all: the curve is left out, and said so
    assert [p.name for p in d.parameters] == ["C1"] and any(n.startswith("left out Gain: a CURVE") for n in notes)


def test_the_page_segment_is_the_one_holding_the_characteristics(tmp_path: Path) -> None:
    ram = MODPAR.replace(
        "    /end MOD_PAR",
        """      /begin MEMORY_SEGMENT RamData "ram" DATA RAM INTERN 0x70000000 0x100 -1 -1 -1 -1 -1
        /begin IF_DATA XCP /begin SEGMENT 1 1 0 0 0 /end SEGMENT /end IF_DATA
      /end MEMORY_SEGMENT
    /end MOD_PAR""",
    )
    path = write(tmp_path, char() + "\n" + char("R1", "0x70000010"), modpar=ram)
    xcp = definition_from_a2l(path, ["C1"], midpoint=True).xcp  # the last segment (RamData, one page) was taken
    assert (xcp["segment"], xcp["pages"], xcp["working_page"]) == (0, True, 1)
    xcp = definition_from_a2l(path, ["R1"], midpoint=True).xcp
    assert (xcp["segment"], xcp["pages"]) == (1, False)
    with pytest.raises(A2lError, match="lie in memory segments paged differently"):
        definition_from_a2l(path, ["C1", "R1"], midpoint=True)
    outside = write(tmp_path, char(address="0x50000000"), name="outside.a2l")
    with pytest.raises(A2lError, match=r"C1 at 0x50000000 \(1 bytes\) lies in no MEMORY_SEGMENT of the A2L \(CalData"):
        definition_from_a2l(outside, ["C1"], midpoint=True)


def test_a_truncated_included_file_is_refused(tmp_path: Path) -> None:
    (tmp_path / "inc_ok.a2l").write_text(char("INC1", "0x40000010", hi="0.95", cm="CM_RAT", layout="RL_UWORD") + "\n")
    (tmp_path / "inc_cut.a2l").write_text('/begin CHARACTERISTIC INC1 "d" VALUE 0x40000010 RL_UWORD 0 CM_RAT 0 0.9\n')
    good = write(tmp_path, char() + '\n/include "inc_ok.a2l"', name="good.a2l")
    assert definition_from_a2l(good, ["INC1"], midpoint=True).parameters[0].upper == 0.95
    cut = write(tmp_path, char() + '\n/include "inc_cut.a2l"', name="cut.a2l")
    with pytest.raises(A2lError, match=r"inc_cut.a2l: the file ends inside /begin CHARACTERISTIC"):
        definition_from_a2l(cut, ["INC1"], midpoint=True)
    missing = write(tmp_path, char() + '\n/include "nope.a2l"', name="missing.a2l")
    with pytest.raises(A2lError, match=r"/include nope.a2l: no such file"):
        read_a2l(missing)
    # an /include in a comment or a string is none
    quiet = write(tmp_path, char(extra='/* /include "x.a2l" */') + '\n/* /include "y.a2l" */', name="quiet.a2l")
    assert read_a2l(quiet).characteristics["C1"].upper == 15


def test_limits_are_moved_onto_the_ecus_grid_so_what_is_told_is_what_the_ecu_holds(tmp_path: Path) -> None:
    cm = '/begin COMPU_METHOD CM_Q "" LINEAR "%6.0" "-" COEFFS_LINEAR 4 0 /end COMPU_METHOD'
    path = write(tmp_path, cm + "\n" + char("P_Gain", cm="CM_Q", lo="2", hi="62"))
    (p,) = definition_from_a2l(path, ["P_Gain"], midpoint=True).parameters
    assert (p.lower, p.upper, p.resolution, p.nominal) == (4.0, 60.0, 4.0, 32.0)
    # the midpoint stays inside limits kept at the A2L's digits (0.95 is 9500 x 0.0001 with float noise)
    rat = char("R", "0x40000010", layout="RL_UWORD", cm="CM_RAT4", lo="0.9499", hi="0.95")
    cm4 = '/begin COMPU_METHOD CM_RAT4 "" RAT_FUNC "%8.4" "-" COEFFS 0 10000 0 0 0 1 /end COMPU_METHOD'
    (r,) = definition_from_a2l(write(tmp_path, cm4 + "\n" + rat, name="r.a2l"), ["R"], midpoint=True).parameters
    assert r.lower <= r.nominal <= r.upper == 0.95
    x = XcpParam.of(p)
    for k in range(15):  # every value the agent can ask is one the ECU holds, and reads back
        v = p.quantize(p.lower + k * p.resolution)
        assert x.decode(x.encode(v)) == v
    with pytest.raises(A2lError, match=r"the value 6 is not one the ECU can hold \(the nearest is 8"):
        definition_from_a2l(path, ["P_Gain"], values={"P_Gain": 6})


@pytest.mark.parametrize(("layout", "lo", "hi", "need"),
                         [("RL_UBYTE", "0", "300", "0..300"), ("RL_UBYTE", "-10", "100", "-10..100"),
                          ("RL_SBYTE", "-200", "100", "-200..100")])  # fmt: skip
def test_limits_beyond_the_data_type_are_refused(tmp_path: Path, layout: str, lo: str, hi: str, need: str) -> None:
    path = write(tmp_path, char(layout=layout, lo=lo, hi=hi) + "\n" + char("C2", "0x40000010"))
    with pytest.raises(A2lError, match=rf"need internal values {need}, beyond what a"):
        definition_from_a2l(path, ["C1"], midpoint=True)
    notes: list[str] = []  # --all: left out and said, the others kept
    assert [p.name for p in definition_from_a2l(path, None, midpoint=True, notes=notes).parameters] == ["C2"]
    assert any(n.startswith("left out C1: its limits") for n in notes)


def test_a_64_bit_types_own_range_as_limits_is_accepted(tmp_path: Path) -> None:
    u64 = char(layout="RL_U64", lo="0", hi="18446744073709551615")
    i64 = char("C2", "0x40000010", layout="RL_I64", lo="-9223372036854775808", hi="9223372036854775807")
    rl = "/begin RECORD_LAYOUT RL_I64 FNC_VALUES 1 A_INT64 ROW_DIR DIRECT /end RECORD_LAYOUT"
    d = definition_from_a2l(write(tmp_path, "\n".join((u64, i64, rl))), ["C1", "C2"], midpoint=True)
    assert [(p.lower, p.upper) for p in d.parameters] == [(0.0, 2.0**64), (-(2.0**63), 2.0**63)]


def test_nested_segments_page_by_the_one_that_says_its_paging(tmp_path: Path) -> None:
    flash = MODPAR.replace(
        '    /begin MOD_PAR ""',
        """    /begin MOD_PAR ""
      /begin MEMORY_SEGMENT Flash "code" CODE FLASH INTERN 0x40000000 0x100000 -1 -1 -1 -1 -1 /end MEMORY_SEGMENT""",
    )
    xcp = definition_from_a2l(write(tmp_path, char(), modpar=flash), ["C1"], midpoint=True).xcp
    assert (xcp["segment"], xcp["pages"]) == (0, True)
    cross = write(tmp_path, char(address="0x40000fff", layout="RL_UWORD", hi="100"), name="cross.a2l")
    with pytest.raises(A2lError, match=r"C1 at 0x40000fff \(2 bytes\) crosses the end of MEMORY_SEGMENT CalData"):
        definition_from_a2l(cross, ["C1"], midpoint=True)


def test_can_ids_missing_or_given_twice(tmp_path: Path) -> None:
    notes: list[str] = []
    d = definition_from_a2l(write(tmp_path, char(), ifdata=""), ["C1"], midpoint=True, notes=notes)
    assert "can_id_master" not in d.xcp and any("no CAN_ID_MASTER / CAN_ID_SLAVE pair" in n for n in notes)
    two = """    /begin IF_DATA XCP
      /begin XCP_ON_CAN 0x0100 CAN_ID_MASTER 0x7E0 CAN_ID_SLAVE 0x7E1 /end XCP_ON_CAN
      /begin XCP_ON_CAN 0x0100 CAN_ID_MASTER 0x6F0 CAN_ID_SLAVE 0x6F1 /end XCP_ON_CAN
    /end IF_DATA"""
    with pytest.raises(A2lError, match=r"several CAN id pairs \(CAN_ID_MASTER 0x6f0, 0x7e0"):
        read_a2l(write(tmp_path, char(), name="two.a2l", ifdata=two))


def test_a_utf8_file_keeps_its_umlauts(tmp_path: Path) -> None:
    body = char().replace('"d"', '"Dämpfung µ"')
    (tmp_path / "u.a2l").write_bytes(a2l(body).encode("utf-8"))
    assert definition_from_a2l(tmp_path / "u.a2l", ["C1"], midpoint=True).parameters[0].description == "Dämpfung µ"
    (tmp_path / "l.a2l").write_bytes(a2l(body).encode("latin-1"))
    assert definition_from_a2l(tmp_path / "l.a2l", ["C1"], midpoint=True).parameters[0].description == "Dämpfung µ"


def test_a_value_at_each_bound_round_trips_through_the_bytes(tmp_path: Path) -> None:
    cm = '/begin COMPU_METHOD CM_L "" LINEAR "%8.2" "Nm" COEFFS_LINEAR 0.01 -10.0 /end COMPU_METHOD'
    path = write(
        tmp_path, cm + "\n" + char(layout="RL_SWORD", cm="CM_L", lo="-300", hi="300", extra="BYTE_ORDER MSB_FIRST")
    )
    (p,) = definition_from_a2l(path, ["C1"], midpoint=True).parameters
    x = XcpParam.of(p)
    assert x.encode(-300.0) == struct.pack(">h", -29000) and x.encode(300.0) == struct.pack(">h", 31000)


def test_phys_unit_and_a_floats_step_size(tmp_path: Path) -> None:
    cm = '/begin COMPU_METHOD CM_L "" LINEAR "%8.2" "Nm" COEFFS_LINEAR 0.01 -10.0 /end COMPU_METHOD'
    c1 = char(layout="RL_SWORD", cm="CM_L", lo="-100", hi="100", extra='PHYS_UNIT "km/h"')
    f1 = char("F1", "0x40000010", layout="RL_F32", lo="0", hi="2", extra='FORMAT "%5.0" STEP_SIZE 0.05')
    f2 = char("F2", "0x40000020", layout="RL_F32", lo="0", hi="2", extra='FORMAT "%5.0"')
    d = definition_from_a2l(write(tmp_path, "\n".join((cm, c1, f1, f2))), ["C1", "F1", "F2"], midpoint=True)
    (c, f, g) = d.parameters
    assert c.unit == "km/h" and c.resolution == pytest.approx(0.01)
    assert f.resolution == 0.05 and g.resolution == 1.0  # without a STEP_SIZE: the FORMAT's decimals


def _whole(path: Path) -> object:
    """The module as pya2ldb reads the whole file, without bac's slimming (what it was before 2026-11-29)."""
    from bac_ecu_bridge.xcp import a2l as a2l_mod

    pya2l, model = a2l_mod._load_pya2l()
    session = pya2l.import_a2l(str(path), in_memory=True, progress_bar=False, loglevel="ERROR", encoding="utf-8")
    try:
        return a2l_mod._module(session, model, path)
    finally:
        session.close()


def measurement(i: int) -> str:
    return (
        f'/begin MEASUREMENT M{i} "m /end CHARACTERISTIC in a string" SWORD CM_LIN 1 100 -327.68 327.67\n'
        f"  ECU_ADDRESS 0x{0x50000000 + 2 * i:X}\n  /begin IF_DATA XCP /end IF_DATA\n/end MEASUREMENT"
    )


SUPPLIER_BODY = "\n".join(
    [
        '/* a comment: /begin MEASUREMENT X "" /end MEASUREMENT */',
        char("C1", extra='FORMAT "%6.2"\n  PHYS_UNIT "Nm"'),
        *(measurement(i) for i in range(30)),
        '/begin FUNCTION F1 "f" /begin DEF_CHARACTERISTIC C1 C2 /end DEF_CHARACTERISTIC /end FUNCTION',
        '/begin GROUP G1 "g" /begin REF_CHARACTERISTIC C1 /end REF_CHARACTERISTIC /end GROUP',
        char("C2", address="0x40000002", layout="RL_UWORD", cm="CM_LIN", lo="-10", hi="100"),
        char("C3", address="0x40000004", extra="READ_ONLY"),
        "// a line comment /begin CHARACTERISTIC Z",
        char("C4", address="0x40000006", layout="RL_F32", lo="0", hi="1", extra="STEP_SIZE 0.01"),
    ]
)


def test_slimming_gives_what_the_whole_file_gives_and_keeps_its_line_numbers(tmp_path: Path) -> None:
    """A supplier's A2L of 5 MB took 23 s and 0.7 GB in pya2ldb, most of it measurements bac never reads: they
    are left out before it parses; every characteristic, problem and XCP setting is what the whole file gives."""
    from bac_ecu_bridge.xcp.a2l import slim_a2l

    path = write(tmp_path, SUPPLIER_BODY)
    whole = _whole(path)
    got = read_a2l(path)
    assert got.characteristics == whole.characteristics and set(got.characteristics) == {"C1", "C2", "C4"}
    assert got.problems == whole.problems and "READ_ONLY" in got.problems["C3"]
    assert (got.xcp, got.segments, got.notes) == (whole.xcp, whole.segments, whole.notes)
    assert got.all_characteristics == {"C1", "C2", "C3", "C4"}
    out = tmp_path / "slim"
    out.mkdir()
    slim = slim_a2l(path, out).read_text().splitlines()
    text = path.read_text().splitlines()
    assert len(slim) == len(text) and "MEASUREMENT M" not in "\n".join(slim) and "FUNCTION F1" not in "\n".join(slim)
    for i, line in enumerate(text):  # every line kept is where it was (pya2ldb's messages name the file's lines)
        if line.lstrip().startswith(("/begin CHARACTERISTIC", "/begin MOD_PAR", "/begin COMPU_METHOD")):
            assert slim[i] == line, i


def test_only_the_named_characteristics_are_read_and_the_others_still_known(tmp_path: Path) -> None:
    path = write(tmp_path, SUPPLIER_BODY + "\n" + char("C2", address="0x40000100"))  # C2 defined twice
    got = read_a2l(path, only=["C1", "C2"])
    assert set(got.characteristics) == {"C1"} and "defined 2 times" in got.problems["C2"]
    assert "C3" not in got.problems and got.all_characteristics == {"C1", "C2", "C3", "C4"}
    d = definition_from_a2l(path, ["C4", "C1"], midpoint=True)
    assert [p.name for p in d.parameters] == ["C4", "C1"] and d.parameters[1].unit == "Nm"
    with pytest.raises(A2lError, match=r"no VALUE characteristic \['C9'\] \(known: C1, C2, C3, C4\)"):
        definition_from_a2l(path, ["C1", "C9"], midpoint=True)


def test_an_included_file_is_slimmed_and_found_where_it_was(tmp_path: Path) -> None:
    sub = tmp_path / "parts"
    sub.mkdir()
    (sub / "meas.a2l").write_text("\n".join(measurement(i) for i in range(5)) + "\n" + char("C7", address="0x40000010"))
    path = write(tmp_path, char() + '\n/include "parts/meas.a2l"', name="main.a2l")
    got = read_a2l(path)
    assert set(got.characteristics) == {"C1", "C7"} and got.characteristics["C7"].address == 0x40000010
    assert got.characteristics == _whole(path).characteristics


def test_nothing_inside_an_if_data_or_the_a2ml_is_left_out(tmp_path: Path) -> None:
    """A supplier's A2ML may define blocks named like the ones bac leaves out (GROUP, FRAME): inside IF_DATA (and
    in an included file there) they are the supplier's, and stay."""
    from bac_ecu_bridge.xcp.a2l import slim_a2l

    (tmp_path / "vendor.a2l").write_text("/begin FRAME 3 /end FRAME\n")
    body = (
        '/begin IF_DATA VENDOR\n  /begin GROUP 7 /end GROUP\n  /include "vendor.a2l"\n/end IF_DATA\n'
        '/begin GROUP G1 "g" /end GROUP\n' + char()
    )
    path = write(tmp_path, body)
    out = tmp_path / "slim"
    out.mkdir()
    slim = slim_a2l(path, out).read_text()
    assert "/begin GROUP 7 /end GROUP" in slim and "GROUP G1" not in slim and "CHARACTERISTIC C1" in slim
    included = [f for f in out.iterdir() if f.name.endswith("vendor.a2l")]
    assert included and "/begin FRAME 3 /end FRAME" in included[0].read_text()
