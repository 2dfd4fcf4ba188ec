"""The calibration protocol's codec: frame layouts, checksums, parameter encodings, request resolution."""

from __future__ import annotations

import itertools
import math
import struct
import zlib

import pytest

from bac_common.errors import DefinitionError, OutOfBoundsError, UnknownParameterError
from bac_common.paramspace import CalibrationDefinition, MetaParameter, RawParameter, uniform_parameters
from bac_common.paths import resolve_definition
from bac_ecu_bridge.errors import FrameError, InvalidRequestError, ProtocolConfigError
from bac_ecu_bridge.protocol import (
    Ack,
    Begin,
    BeginOk,
    CalibrationCodec,
    CanIds,
    Commit,
    Nack,
    Op,
    ParamCodec,
    Read,
    Reason,
    Staged,
    StatusOk,
    StatusRequest,
    Value,
    Write,
    crc8,
    decode,
    decode_request,
    decode_response,
    encode,
    resolve_request,
    set_crc,
)

ALL_PDUS = [
    Begin(7, 20),
    Write(7, 3, 123456),
    Commit(7, 20, 0xDEADBEEF),
    Read(7, 19),
    StatusRequest(255),
    BeginOk(7, 20),
    Staged(7, 3, 123456),
    Ack(7, 20, 0xDEADBEEF),
    Value(0, 255, 0xFFFFFFFF),
    StatusOk(9, 20, 1),
    Nack(7, int(Op.WRITE), int(Reason.OUT_OF_RANGE), 4, 0x1234),
]


def test_crc8_is_sae_j1850() -> None:
    # the catalogued check value of CRC-8/SAE-J1850 (reveng: width=8 poly=0x1d init=0xff xorout=0xff)
    assert crc8(b"123456789") == 0x4B
    assert crc8(b"") == 0x00


def test_set_crc_is_crc32_over_index_raw_pairs_in_index_order() -> None:
    raw = {5: 100, 1: 0xFFFFFFFF, 3: 0}
    expected = zlib.crc32(struct.pack("<BI", 1, 0xFFFFFFFF) + struct.pack("<BI", 3, 0) + struct.pack("<BI", 5, 100))
    assert set_crc(raw) == expected
    assert set_crc(dict(reversed(list(raw.items())))) == expected
    assert set_crc({5: 101, 1: 0xFFFFFFFF, 3: 0}) != expected


@pytest.mark.parametrize("pdu", ALL_PDUS, ids=lambda p: type(p).__name__)
def test_every_frame_round_trips(pdu: object) -> None:
    data = encode(pdu)  # type: ignore[arg-type]
    assert len(data) == 8
    assert data[1] == int(pdu.op)  # type: ignore[attr-defined]
    assert data[2] == pdu.seq  # type: ignore[attr-defined]
    assert data[0] == crc8(data[1:])
    assert decode(data) == pdu


def test_known_frame_bytes() -> None:
    # WRITE seq 0x12, index 3, raw 0x00012345: little-endian fields behind CRC-8, op, seq
    data = encode(Write(0x12, 3, 0x12345))
    assert data[1:] == bytes([0x02, 0x12, 0x03, 0x45, 0x23, 0x01, 0x00])
    assert encode(Nack(1, 3, 4, 0, 0xABCD))[1:] == bytes([0x7F, 0x01, 0x03, 0x04, 0x00, 0xCD, 0xAB])


def test_every_single_and_double_bit_flip_is_detected() -> None:
    for pdu in ALL_PDUS:
        data = encode(pdu)
        bits = range(64)
        for flips in itertools.chain(((b,) for b in bits), itertools.combinations(bits, 2)):
            garbled = bytearray(data)
            for b in flips:
                garbled[b // 8] ^= 1 << (b % 8)
            with pytest.raises(FrameError):
                decode(bytes(garbled))


def test_garbage_is_refused_with_a_reason() -> None:
    with pytest.raises(FrameError, match="7 data bytes"):
        decode(b"\x00" * 7)
    with pytest.raises(FrameError, match="unknown opcode"):
        decode(bytes([crc8(bytes([0x10, 0, 0, 0, 0, 0, 0])), 0x10, 0, 0, 0, 0, 0, 0]))
    body = bytes([0x01, 0, 5, 1, 0, 0, 0])  # BEGIN with a reserved byte set
    with pytest.raises(FrameError, match="reserved"):
        decode(bytes([crc8(body)]) + body)
    with pytest.raises(FrameError, match="is a response"):
        decode_request(encode(Ack(1, 1, 1)))
    with pytest.raises(FrameError, match="is a request"):
        decode_response(encode(Write(1, 1, 1)))


def test_encode_refuses_fields_that_do_not_fit() -> None:
    with pytest.raises(ValueError, match="seq"):
        encode(Begin(256, 1))
    with pytest.raises(ValueError, match="raw"):
        encode(Write(1, 1, 1 << 32))
    with pytest.raises(ValueError, match="index"):
        encode(Read(1, 300))


def test_param_codec_scale_offset_and_bounds() -> None:
    p = ParamCodec.of(RawParameter("k", 4, lower=-2.5, upper=2.5, nominal=0.0, resolution=0.01))
    assert p.max_raw == 500
    assert p.encode(-2.5) == 0
    assert p.encode(2.5) == 500
    assert p.encode(0.123) == 262  # round(2.623 / 0.01)
    assert p.decode(262) == pytest.approx(0.12)
    assert p.quantize(0.126) == pytest.approx(0.13)
    for bad in (-2.51, 2.5000001, math.nan, math.inf):
        with pytest.raises(OutOfBoundsError):
            p.encode(bad)
    with pytest.raises(FrameError):
        p.decode(501)


def test_quantized_value_never_exceeds_upper_when_the_range_is_not_a_multiple_of_the_step() -> None:
    p = ParamCodec.of(RawParameter("k", 0, lower=0.0, upper=1.0, nominal=0.5, resolution=0.3))
    assert p.max_raw == 3  # 0, 0.3, 0.6, 0.9
    assert p.encode(1.0) == 3  # round(3.33) = 3
    assert p.decode(p.encode(1.0)) <= 1.0
    q = ParamCodec.of(RawParameter("k", 0, lower=0.0, upper=1.0, nominal=0.5, resolution=0.4))
    assert q.encode(1.0) == 2  # round(2.5) = 2; never 3 (1.2 > upper)
    assert all(q.decode(q.encode(v)) <= 1.0 for v in (0.8, 0.95, 1.0))


def test_agrees_with_the_definitions_own_quantization() -> None:
    d = CalibrationDefinition.load(resolve_definition("controller_ii"))
    codec = CalibrationCodec(d)
    for v in (0.0, 0.004, 0.005, 123.456789, 999.995, 1000.0):
        assert codec.param("p07").quantize(v) == d.parameter("p07").quantize(v)


def test_parameters_too_fine_for_32_bits_are_refused() -> None:
    with pytest.raises(ProtocolConfigError, match="coarser resolution"):
        ParamCodec.of(RawParameter("k", 0, lower=0.0, upper=1e6, nominal=0.0, resolution=1e-4))


def test_can_ids_are_checked() -> None:
    assert CanIds().request_id == 0x6C0
    with pytest.raises(ProtocolConfigError, match="11-bit"):
        CanIds(0x800, 0x6C1)
    assert CanIds(0x18DA00F1, 0x18DAF100, extended=True).extended
    with pytest.raises(ProtocolConfigError, match="differ"):
        CanIds(0x100, 0x100)


def test_codec_encodes_sets_by_name_and_refuses_before_sending() -> None:
    d = CalibrationDefinition.load(resolve_definition("controller_i"))
    codec = CalibrationCodec(d)
    assert codec.encode_set({"damping_rear": 0.25, "damping_front": 1.0}) == {1: 2500, 0: 10000}
    with pytest.raises(UnknownParameterError, match="damping_middle"):
        codec.encode_set({"damping_middle": 0.1})
    with pytest.raises(OutOfBoundsError, match="damping_front"):
        codec.encode_set({"damping_front": 1.2})


META = CalibrationDefinition(
    "meta",
    uniform_parameters("p", 4, 0.0, 1000.0, 500.0, 0.01),
    tuned=("m1", "p04"),
    meta=(MetaParameter("m1", ("p01", "p02"), 0.0, 1.0),),
    fixed={"p03": 250.0},
)


def test_resolve_expands_meta_parameters_and_fixed_values() -> None:
    raw = resolve_request(META, ["p04", "m1"], [10.0, 0.25])
    assert raw == {"p01": 250.0, "p02": 250.0, "p03": 250.0, "p04": 10.0}
    # the full raw set is accepted as well
    full = resolve_request(META, ["p01", "p02", "p03", "p04"], [1.0, 2.0, 3.0, 4.0])
    assert full == {"p01": 1.0, "p02": 2.0, "p03": 3.0, "p04": 4.0}


@pytest.mark.parametrize(
    ("names", "values", "error", "match"),
    [
        (["m1"], [0.5, 1.0], InvalidRequestError, "2 values"),
        (["m1", "m1"], [0.5, 0.5], InvalidRequestError, "twice"),
        (["m1", "p04"], [math.nan, 1.0], InvalidRequestError, "finite"),
        (["m1"], [0.5], InvalidRequestError, "lacks"),
        (["m1", "p03"], [0.5, 1.0], InvalidRequestError, "not tuned"),
        ([], [], InvalidRequestError, "no parameter"),
        (["m1", "zz"], [0.5, 1.0], UnknownParameterError, "zz"),
        (["m1", "p04"], [1.5, 1.0], OutOfBoundsError, "m1"),
        (["p01", "p02", "p03", "p04"], [1.0, 2.0, 3.0, 1000.5], OutOfBoundsError, "p04"),
    ],
)
def test_resolve_refuses_bad_requests(names: list[str], values: list[float], error: type, match: str) -> None:
    with pytest.raises(error, match=match):
        resolve_request(META, names, values)


def test_definitions_that_do_not_fit_one_transaction_are_refused() -> None:
    with pytest.raises(ProtocolConfigError, match="at most 255"):
        CalibrationCodec(CalibrationDefinition("big", uniform_parameters("p", 256, 0, 1, 0.5, 0.01)))
    with pytest.raises(DefinitionError):  # and bac_common refuses indices beyond 255 itself
        RawParameter("x", 256, 0, 1, 0.5, 0.1)
