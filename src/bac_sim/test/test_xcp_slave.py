"""The simulated XCP slave, frame by frame: byte-exact responses and error codes of the standard."""

from __future__ import annotations

import struct
import zlib

import pytest

from bac_common.paramspace import CalibrationDefinition, EcuAddress, RawParameter
from bac_ecu_bridge.xcp.seedkey import xor_algorithm
from bac_sim.xcp_slave import XcpSlave

BASE = 0x40000100
DEF = CalibrationDefinition(
    "four",
    tuple(
        RawParameter(
            f"p{k}",
            k,
            0.0,
            1000.0,
            500.0,
            0.01,
            xcp=EcuAddress(BASE + 4 * k, "ULONG", conversion="LINEAR", coeffs=(0.01, 0)),
        )
        for k in range(4)
    ),
)
RAW_500 = struct.pack("<I", 50_000)


def connected(**kw: object) -> XcpSlave:
    s = XcpSlave(DEF, **kw)  # type: ignore[arg-type]
    assert s.handle(bytes([0xFF, 0x00])) == [bytes([0xFF, 0x01, 0xC0, 0x08, 0x08, 0x00, 0x01, 0x01])]
    return s


def mta(address: int, ext: int = 0) -> bytes:
    return bytes([0xF6, 0, 0, ext]) + struct.pack("<I", address)


def test_nothing_is_answered_before_connect() -> None:
    s = XcpSlave(DEF)
    assert s.handle(bytes([0xFD])) == []  # GET_STATUS
    assert s.handle(mta(BASE)) == []
    assert s.stats.ignored == 2


def test_connect_status_synch_and_comm_mode_info() -> None:
    s = connected()
    # RESOURCE CAL/PAG, COMM_MODE_BASIC: Intel, byte granularity, slave block mode, optional; MAX_CTO 8, MAX_DTO 8
    assert s.handle(bytes([0xFD])) == [bytes([0xFF, 0x00, 0x00, 0x00, 0x00, 0x00])]
    assert s.handle(bytes([0xFC])) == [bytes([0xFE, 0x00])]  # SYNCH -> ERR_CMD_SYNCH
    # GET_COMM_MODE_INFO: master block mode, MAX_BS 32, MIN_ST 0, QUEUE_SIZE 0, driver version 0x10
    assert s.handle(bytes([0xFB])) == [bytes([0xFF, 0x00, 0x01, 0x00, 0x20, 0x00, 0x00, 0x10])]
    assert s.handle(bytes([0xFE])) == [bytes([0xFF])]  # DISCONNECT
    assert s.handle(bytes([0xFD])) == []


def test_motorola_byte_order_is_announced_and_used() -> None:
    s = XcpSlave(DEF, byte_order="MSB_FIRST")
    assert s.handle(bytes([0xFF, 0x00]))[0][2] == 0xC1
    assert s.handle(bytes([0xF6, 0, 0, 0]) + struct.pack(">I", BASE)) == [b"\xff"]
    assert s.handle(bytes([0xF5, 0x04])) == [b"\xff" + RAW_500]  # the values keep their own byte order


def test_upload_short_upload_and_slave_block_mode() -> None:
    s = connected()
    assert s.handle(mta(BASE)) == [b"\xff"]
    assert s.handle(bytes([0xF5, 0x04])) == [b"\xff" + RAW_500]
    assert s.handle(bytes([0xF5, 0x04])) == [b"\xff" + RAW_500]  # the MTA moved on by 4
    assert s.handle(bytes([0xF4, 0x04, 0x00, 0x00]) + struct.pack("<I", BASE + 12)) == [b"\xff" + RAW_500]
    assert s.handle(mta(BASE)) == [b"\xff"]
    frames = s.handle(bytes([0xF5, 16]))  # 16 bytes: 7 + 7 + 2, each frame a positive response
    assert frames == [b"\xff" + (RAW_500 * 4)[:7], b"\xff" + (RAW_500 * 4)[7:14], b"\xff" + (RAW_500 * 4)[14:]]


def test_build_checksum_is_crc32_over_the_block() -> None:
    s = connected()
    s.handle(mta(BASE))
    got = s.handle(bytes([0xF3, 0, 0, 0]) + struct.pack("<I", 16))
    assert got == [bytes([0xFF, 0x09, 0x00, 0x00]) + struct.pack("<I", zlib.crc32(RAW_500 * 4))]


def test_download_writes_the_xcp_page_and_block_mode_answers_once() -> None:
    s = connected()
    s.handle(mta(BASE))
    assert s.handle(bytes([0xF0, 0x04]) + struct.pack("<I", 123)) == [b"\xff"]
    assert s.page_values(1)["p0"] == 1.23 and s.active_values()["p0"] == 1.23  # the ECU runs on the working page
    # master block mode: DOWNLOAD announces 12 bytes and carries 6, DOWNLOAD_NEXT the rest; one answer at the end
    data = struct.pack("<III", 1, 2, 3)
    assert s.handle(bytes([0xF0, 12]) + data[:6]) == []
    assert s.handle(bytes([0xEF, 6]) + data[6:]) == [b"\xff"]
    assert [s.page_values(1)[f"p{k}"] for k in (1, 2, 3)] == [0.01, 0.02, 0.03]


def test_block_transfer_out_of_sequence() -> None:
    s = connected()
    s.handle(mta(BASE))
    assert s.handle(bytes([0xF0, 12]) + bytes(6)) == []
    assert s.handle(bytes([0xEF, 5]) + bytes(5)) == [bytes([0xFE, 0x29, 6])]  # ERR_SEQUENCE, 6 expected
    assert s.handle(bytes([0xEF, 6]) + bytes(6)) == [bytes([0xFE, 0x29, 0])]  # no block open any more


def test_pages_reference_is_write_protected_and_page_switches() -> None:
    s = connected()
    assert s.handle(bytes([0xEA, 0x01, 0x00])) == [bytes([0xFF, 0, 0, 1])]  # GET_CAL_PAGE ECU: working
    assert s.handle(bytes([0xEB, 0x02, 0x00, 0x00])) == [b"\xff"]  # XCP accesses the reference page
    s.handle(mta(BASE))
    assert s.handle(bytes([0xF0, 0x04]) + bytes(4)) == [bytes([0xFE, 0x23])]  # ERR_WRITE_PROTECTED
    assert s.handle(bytes([0xEB, 0x01, 0x00, 0x00])) == [b"\xff"]  # the ECU runs on the reference page
    assert s.handle(bytes([0xEA, 0x01, 0x00])) == [bytes([0xFF, 0, 0, 0])]
    assert s.stats.page_switches == 1
    assert s.handle(bytes([0xEB, 0x01, 0x00, 0x02])) == [bytes([0xFE, 0x26])]  # ERR_PAGE_NOT_VALID
    assert s.handle(bytes([0xEB, 0x01, 0x01, 0x00])) == [bytes([0xFE, 0x28])]  # ERR_SEGMENT_NOT_VALID
    assert s.handle(bytes([0xEB, 0x00, 0x00, 0x00])) == [bytes([0xFE, 0x27])]  # ERR_MODE_NOT_VALID
    assert s.handle(bytes([0xEA, 0x03, 0x00])) == [bytes([0xFE, 0x27])]


def test_access_outside_the_calibration_segment_is_denied() -> None:
    s = connected()
    s.handle(mta(BASE + 14))
    assert s.handle(bytes([0xF0, 0x04]) + bytes(4)) == [bytes([0xFE, 0x24])]  # ERR_ACCESS_DENIED
    assert s.handle(bytes([0xF4, 0x04, 0x00, 0x00]) + struct.pack("<I", 0x1000)) == [bytes([0xFE, 0x24])]
    assert s.handle(bytes([0xF4, 0x04, 0x00, 0x01]) + struct.pack("<I", BASE)) == [bytes([0xFE, 0x24])]  # extension
    assert s.handle(bytes([0xF4, 0x08, 0x00, 0x00]) + struct.pack("<I", BASE)) == [bytes([0xFE, 0x22])]  # > 7 bytes


def test_changes_of_what_the_ecu_uses_are_refused_while_driving() -> None:
    s = connected()
    s.driving = True
    assert s.handle(bytes([0xEB, 0x01, 0x00, 0x00])) == [bytes([0xFE, 0x33])]  # ERR_RESOURCE_TEMPORARY_NOT_ACCESSIBLE
    s.handle(mta(BASE))
    assert s.handle(bytes([0xF0, 0x04]) + bytes(4)) == [bytes([0xFE, 0x33])]  # into the page the ECU runs on
    assert s.handle(bytes([0xEB, 0x02, 0x00, 0x00])) == [b"\xff"]  # XCP access may change
    s.driving = False
    assert s.handle(bytes([0xEB, 0x01, 0x00, 0x00])) == [b"\xff"]  # ECU on the reference page
    s.driving = True
    assert s.handle(bytes([0xEB, 0x02, 0x00, 0x01])) == [b"\xff"]
    s.handle(mta(BASE))
    assert s.handle(bytes([0xF0, 0x04]) + bytes(4)) == [b"\xff"]  # the working page, which the ECU does not use


def test_seed_and_key() -> None:
    key = xor_algorithm(bytes.fromhex("5a17c3"))
    s = connected(key_algorithm=key, seed=1)
    assert s.handle(bytes([0xFD]))[0][2] == 0x01  # CAL/PAG protected
    s.handle(mta(BASE))
    assert s.handle(bytes([0xF0, 0x04]) + bytes(4)) == [bytes([0xFE, 0x25])]  # ERR_ACCESS_LOCKED
    assert s.handle(bytes([0xF7, 0x02, 1, 2])) == [bytes([0xFE, 0x29])]  # UNLOCK before GET_SEED: ERR_SEQUENCE
    seed_frame = s.handle(bytes([0xF8, 0x00, 0x01]))[0]
    assert seed_frame[:2] == bytes([0xFF, 0x04])
    k = key(1, seed_frame[2:])
    assert s.handle(bytes([0xF7, len(k)]) + k) == [bytes([0xFF, 0x00])]  # unlocked: protection status 0
    s.handle(mta(BASE))
    assert s.handle(bytes([0xF0, 0x04]) + bytes(4)) == [b"\xff"]
    # a wrong key ends the session
    s2 = connected(key_algorithm=key, seed=2)
    s2.handle(bytes([0xF8, 0x00, 0x01]))
    assert s2.handle(bytes([0xF7, 0x04, 0, 0, 0, 0])) == [bytes([0xFE, 0x25])]
    assert s2.handle(bytes([0xFD])) == []


def test_unknown_and_malformed_commands() -> None:
    s = connected()
    assert s.handle(bytes([0xD0])) == [bytes([0xFE, 0x20])]  # ERR_CMD_UNKNOWN
    assert s.handle(bytes([0xF6, 0x00])) == [bytes([0xFE, 0x21])]  # SET_MTA too short: ERR_CMD_SYNTAX
    assert s.handle(bytes([0xF0, 0x04, 0x01])) == [bytes([0xFE, 0x21])]  # DOWNLOAD with too few data bytes


def test_the_working_page_may_start_on_another_calibration_and_reset_reloads_it() -> None:
    s = XcpSlave(DEF, initial={"p0": 7.0})
    assert s.active_values()["p0"] == 7.0 and s.page_values(0)["p0"] == 500.0
    s.reset()
    assert s.active_values()["p0"] == 500.0


@pytest.mark.parametrize("pages", [True, False])
def test_one_page_only(pages: bool) -> None:
    s = connected(pages=pages)
    s.handle(mta(BASE))
    assert s.handle(bytes([0xF0, 0x04]) + struct.pack("<I", 7)) == [b"\xff"]
    assert s.active_values()["p0"] == 0.07
    reply = s.handle(bytes([0xEB, 0x01, 0x00, 0x01]))
    assert reply == ([b"\xff"] if pages else [bytes([0xFE, 0x26])])
