"""pyxcp as the master (the bridge's XCP backend) against the simulated XCP ECU on a python-can virtual bus."""

from __future__ import annotations

import os
import subprocess
import sys
import time
from dataclasses import replace
from pathlib import Path
from typing import Any

import can
import pytest
from bridge_rig import load
from xcp_rig import XFAST, XcpRigFactory, make_xcp_rig_fixture  # noqa: F401  (the make_xcp_rig fixture)

from bac_common.errors import OutOfBoundsError
from bac_ecu_bridge.backend import Holds
from bac_ecu_bridge.errors import BridgeError, ErrorCode
from bac_ecu_bridge.faults import FaultConfig
from bac_ecu_bridge.protocol import resolve_request
from bac_ecu_bridge.xcp.client import XcpCalibrationClient, XcpCommandError, XcpConfig, XcpSettings
from bac_ecu_bridge.xcp.seedkey import xor_algorithm
from bac_sim.xcp_ecu import SimulatedXcpEcu
from bac_sim.xcp_slave import Cmd

II = load("controller_ii")


def ramp(offset: float = 0.0) -> dict[str, float]:
    return {p.name: 10.0 + 47.123 * k + offset for k, p in enumerate(II.parameters)}


def test_a_20_parameter_apply_read_back_page_switch_and_baseline_restore(make_xcp_rig: XcpRigFactory) -> None:
    rig = make_xcp_rig("controller_ii")
    client, ecu = rig.client, rig.ecu
    assert client.read_active().values == client.quantize(II.baseline_values())  # the working page at power-up
    want = ramp()
    res = client.apply(want)
    assert res.values == client.quantize(want) == ecu.active  # every value read back, exactly what the ECU holds
    assert res.values["p02"] == pytest.approx(57.12) and res.read_back
    assert list(res.values) == [p.name for p in II.parameters]
    assert ecu.ecu_page == 1  # the ECU application runs on the working page
    assert (
        ecu.slave.stats.page_switches == 2
    )  # to the reference page while writing, back to the working page: the commit
    assert ecu.slave.page_values(0) == client.quantize(II.baseline_values())  # the reference page never changes
    rd = client.read_active()
    assert rd.values == res.values and rd.note == "working page" and rd.crc == res.crc
    assert client.status().crc == res.crc
    restored = client.restore_baseline()  # a page switch to the reference page, read back
    assert ecu.ecu_page == 0 and restored.values == ecu.active == client.quantize(II.baseline_values())
    assert "reference page 0" in restored.note
    assert client.read_active().note == "reference page"
    again = client.apply(ramp(1.0))  # the working page still holds the last trial: written again, switched back
    assert again.values == ecu.active == client.quantize(ramp(1.0)) and ecu.ecu_page == 1
    assert client.stats.applies_ok == 2


def test_out_of_bounds_values_are_refused_before_anything_is_sent(make_xcp_rig: XcpRigFactory) -> None:
    rig = make_xcp_rig("controller_ii")
    sniffer = rig.sniffer()
    bad = ramp()
    bad["p07"] = 1000.01
    with pytest.raises(OutOfBoundsError, match="p07"):
        rig.client.apply(bad)
    assert sniffer.recv(timeout=0.1) is None


def test_meta_parameters_of_bac_reduce_run_over_xcp(make_xcp_rig: XcpRigFactory) -> None:
    reduced = load("controller_ii_reduced")
    rig = make_xcp_rig(reduced)
    raw = resolve_request(reduced, ["m1", "m2", "m3"], [250.0, 750.0, 400.0])  # the bridge expands meta-parameters
    res = rig.client.apply(raw)
    assert len(res.values) == 20 and res.values == rig.ecu.active == rig.client.quantize(raw)
    assert res.values["p01"] == res.values["p11"] == 250.0 and res.values["p03"] == 750.0
    assert res.values["p04"] == res.values["p07"] == 400.0
    assert res.values["p02"] == reduced.fixed["p02"]  # a fixed parameter at the file's value


def test_busy_while_driving_names_the_xcp_error_and_keeps_the_previous_calibration(
    make_xcp_rig: XcpRigFactory,
) -> None:
    rig = make_xcp_rig("controller_i")
    first = rig.client.apply({"damping_front": 0.2, "damping_rear": 0.8})
    rig.ecu.set_driving(True)
    with pytest.raises(BridgeError, match="ERR_RESOURCE_TEMPORARY_NOT_ACCESSIBLE") as err:
        rig.client.apply({"damping_front": 0.4, "damping_rear": 0.4})
    assert err.value.code == ErrorCode.ECU_BUSY and "SET_CAL_PAGE" in str(err.value)
    assert err.value.ecu_state is not None and err.value.ecu_state.holds is Holds.PREVIOUS
    assert rig.ecu.active == first.values  # the ECU refused to switch: the previous calibration stays in force
    rig.ecu.set_driving(False)
    assert rig.client.apply({"damping_front": 0.4, "damping_rear": 0.4}).values == rig.ecu.active


# refused always, these commands keep the bridge from reading the ECU back (a session, the page); a refused UPLOAD
# does not: the ECU's CRC-32 of the page names the set it holds
UNREADABLE = {Cmd.GET_CAL_PAGE, Cmd.GET_STATUS}


@pytest.mark.parametrize(
    ("command", "error", "name", "code"),
    [
        (Cmd.SET_CAL_PAGE, 0x26, "ERR_PAGE_NOT_VALID", ErrorCode.UNKNOWN_PARAMETER),
        (Cmd.SET_CAL_PAGE, 0x27, "ERR_MODE_NOT_VALID", ErrorCode.UNKNOWN_PARAMETER),
        (Cmd.SET_CAL_PAGE, 0x28, "ERR_SEGMENT_NOT_VALID", ErrorCode.UNKNOWN_PARAMETER),
        (Cmd.SET_CAL_PAGE, 0x25, "ERR_ACCESS_LOCKED", ErrorCode.INVALID_REQUEST),
        (Cmd.DOWNLOAD, 0x22, "ERR_OUT_OF_RANGE", ErrorCode.ECU_OUT_OF_RANGE),
        (Cmd.DOWNLOAD, 0x23, "ERR_WRITE_PROTECTED", ErrorCode.ECU_OUT_OF_RANGE),
        (Cmd.DOWNLOAD, 0x24, "ERR_ACCESS_DENIED", ErrorCode.UNKNOWN_PARAMETER),
        (Cmd.DOWNLOAD, 0x29, "ERR_SEQUENCE", ErrorCode.SEQUENCE),
        (Cmd.DOWNLOAD, 0x30, "ERR_MEMORY_OVERFLOW", ErrorCode.ECU_OUT_OF_RANGE),
        (Cmd.DOWNLOAD, 0x31, "ERR_GENERIC", ErrorCode.SEQUENCE),
        (Cmd.DOWNLOAD, 0x10, "ERR_CMD_BUSY", ErrorCode.ECU_BUSY),
        (Cmd.DOWNLOAD, 0x33, "ERR_RESOURCE_TEMPORARY_NOT_ACCESSIBLE", ErrorCode.ECU_BUSY),
        (Cmd.BUILD_CHECKSUM, 0x22, "ERR_OUT_OF_RANGE", ErrorCode.ECU_OUT_OF_RANGE),
        (Cmd.UPLOAD, 0x24, "ERR_ACCESS_DENIED", ErrorCode.UNKNOWN_PARAMETER),
        (Cmd.GET_CAL_PAGE, 0x20, "ERR_CMD_UNKNOWN", ErrorCode.INVALID_REQUEST),
        (Cmd.GET_STATUS, 0x31, "ERR_GENERIC", ErrorCode.SEQUENCE),
    ],
    ids=lambda v: v.name if isinstance(v, Cmd) else (v if isinstance(v, str) else None),
)
def test_every_negative_response_surfaces_as_a_clear_error_naming_the_xcp_error(
    make_xcp_rig: XcpRigFactory, command: Cmd, error: int, name: str, code: ErrorCode
) -> None:
    # an apply the ECU's CRC-32 confirms reads nothing back unless asked to: UPLOAD is refused on a client that reads
    # every written byte back
    config = replace(XFAST, verify_readback=True) if command is Cmd.UPLOAD else XFAST
    rig = make_xcp_rig("controller_i", refuse={int(command): error}, config=config)
    t0 = time.monotonic()
    with pytest.raises(BridgeError) as err:
        rig.client.apply({"damping_front": 0.3, "damping_rear": 0.6})
    text = str(err.value)
    assert name in text and f"(0x{error:02X}: " in text and f"XCP {command.name}" in text, text
    assert err.value.code == code
    state = err.value.ecu_state
    assert state is not None
    if command in UNREADABLE:  # the ECU refuses to be read: what it holds is unknown, and the state says why
        assert state.holds is Holds.UNKNOWN and name in state.detail, state
    else:
        assert state.holds is not Holds.UNKNOWN, state
        assert rig.ecu.active == state.values  # what the bridge reports is what the ECU holds
    assert time.monotonic() - t0 < XFAST.timeout_s + XFAST.settle_timeout_s


def test_the_ecus_crc32_confirms_an_apply_without_reading_it_back_unless_asked(make_xcp_rig: XcpRigFactory) -> None:
    """By default the ECU's CRC-32 of each written run, equal to the host's, confirms the apply (INCA's and
    CANape's download verification): no UPLOAD is sent, so an ECU that refuses UPLOAD is still calibrated, and
    what the result reports is what the ECU holds. ``verify_readback`` reads every byte back besides."""
    refuse_upload = {int(Cmd.UPLOAD): 0x24}  # ERR_ACCESS_DENIED
    rig = make_xcp_rig("controller_ii", refuse=refuse_upload)
    res = rig.client.apply(ramp())
    assert res.values == rig.ecu.active == rig.client.quantize(ramp()) and res.read_back
    strict = make_xcp_rig("controller_ii", refuse=refuse_upload, config=replace(XFAST, verify_readback=True))
    with pytest.raises(XcpCommandError, match="XCP UPLOAD"):
        strict.client.apply(ramp())


def test_an_ecu_without_build_checksum_is_verified_by_read_back_alone(make_xcp_rig: XcpRigFactory) -> None:
    rig = make_xcp_rig("controller_ii", refuse={int(Cmd.BUILD_CHECKSUM): 0x20})  # ERR_CMD_UNKNOWN
    res = rig.client.apply(ramp())
    assert res.values == rig.ecu.active == rig.client.quantize(ramp()) and res.read_back
    assert rig.client.read_active().values == res.values


def test_seed_and_key_unlocks_the_calibration(make_xcp_rig: XcpRigFactory) -> None:
    secret = bytes.fromhex("5a17c3")
    rig = make_xcp_rig("controller_i", key_algorithm="xor:5a17c3")
    with pytest.raises(BridgeError, match="ERR_ACCESS_LOCKED") as err:  # no key algorithm configured
        rig.client.apply({"damping_front": 0.3, "damping_rear": 0.6})
    assert "xcp.key_algorithm" in str(err.value)
    client = rig.client_with(config=XFAST, key_algorithm=xor_algorithm(secret))
    assert client.apply({"damping_front": 0.3, "damping_rear": 0.6}).values == rig.ecu.active
    assert client.stats.unlocks == 1
    wrong = rig.client_with(config=XFAST, settings=XcpSettings.of(rig.definition, key_algorithm="xor:000001"))
    rig.ecu.slave.connected = False  # a new session
    with pytest.raises(BridgeError, match="ERR_ACCESS_LOCKED"):
        wrong.apply({"damping_front": 0.5, "damping_rear": 0.5})


def test_an_ecu_with_one_page_is_written_in_place_and_restored_by_values(make_xcp_rig: XcpRigFactory) -> None:
    d = load("controller_i")
    rig = make_xcp_rig(d, pages=False, settings=XcpSettings.of(d, pages=False))
    res = rig.client.apply({"damping_front": 0.25, "damping_rear": 0.75})
    assert res.values == rig.ecu.active == {"damping_front": 0.25, "damping_rear": 0.75}
    assert rig.ecu.slave.stats.page_switches == 0
    restored = rig.client.restore_baseline()
    assert restored.values == rig.ecu.active == {"damping_front": 0.5, "damping_rear": 0.5}


def _swallow(rig: Any, predicate: Any, then: Any = None) -> None:
    """The ECU executes requests matching ``predicate`` but answers none of them (``then`` runs after each)."""
    slave = rig.ecu.slave
    honest = slave.handle

    def handle(frame: bytes) -> list[bytes]:
        out = honest(frame)
        if predicate(bytes(frame)):
            if then is not None:
                then()
            return []
        return out

    slave.handle = handle


def test_an_unanswered_commit_is_settled_by_reading_the_ecu_back(make_xcp_rig: XcpRigFactory) -> None:
    rig = make_xcp_rig("controller_ii")
    _swallow(rig, lambda f: f[:4] == bytes([0xEB, 0x01, 0x00, 0x01]))  # SET_CAL_PAGE(ECU, working): the commit
    res = rig.client.apply(ramp())
    assert res.values == rig.ecu.active == rig.client.quantize(ramp())
    assert "read back" in res.note and rig.client.stats.settled == 1


def test_an_ecu_that_falls_back_to_its_reference_page_unanswered_is_reported_as_such(
    make_xcp_rig: XcpRigFactory,
) -> None:
    rig = make_xcp_rig("controller_ii", config=XcpConfig(step_timeout_s=0.02, step_retries=2, max_attempts=1))
    slave = rig.ecu.slave

    def fall_back() -> None:  # a watchdog of the ECU puts the reference page back
        slave.ecu_page = 0

    _swallow(rig, lambda f: f[:4] == bytes([0xEB, 0x01, 0x00, 0x01]), fall_back)
    with pytest.raises(BridgeError) as err:
        rig.client.apply(ramp())
    state = err.value.ecu_state
    assert err.value.uncertain and state is not None and state.read_back and state.holds is Holds.BASELINE
    assert state.values == rig.ecu.active == rig.client.quantize(II.baseline_values())
    assert "reference page 0" in state.detail


def test_a_settlement_that_finds_the_ecu_on_values_outside_the_bounds_switches_it_back_and_says_so(
    make_xcp_rig: XcpRigFactory,
) -> None:
    """The commit goes unanswered and the working page the application now uses holds a value outside the
    bounds (a garbled write that landed late): the settlement does not leave the ECU running on it, it switches
    the application back to the reference page and the state names what happened."""
    rig = make_xcp_rig("controller_ii", config=XcpConfig(step_timeout_s=0.02, step_retries=2, max_attempts=1))
    slave = rig.ecu.slave

    def garbled() -> None:  # p01 (ULONG, factor 0.01, 0..1000) becomes 42949672.95
        slave.pages[1][0:4] = b"\xff\xff\xff\xff"

    _swallow(rig, lambda f: f[:4] == bytes([0xEB, 0x01, 0x00, 0x01]), garbled)
    with pytest.raises(BridgeError) as err:
        rig.client.apply(ramp())
    state = err.value.ecu_state
    assert err.value.uncertain and state is not None and state.holds is Holds.BASELINE, state
    assert "switched it to the reference page" in state.detail and "working page 1 was in use" in state.detail
    assert rig.ecu.ecu_page == 0 and state.values == rig.ecu.active == rig.client.quantize(II.baseline_values())
    assert rig.client.stats.restored_in_settle == 1


def _garble_once(rig: Any, prefix: bytes, into: bytes, armed: Any = None) -> list[int]:
    """The first command starting with ``prefix`` (once ``armed()`` is true) reaches the ECU as ``into`` + the
    rest: a corrupted payload that CAN's CRC would catch on a real bus but XCP on CAN does not. The list counts
    the frames garbled."""
    slave = rig.ecu.slave
    honest = slave.handle
    done: list[int] = []

    def handle(frame: bytes | bytearray) -> list[bytes]:
        f = bytes(frame)
        if not done and f.startswith(prefix) and (armed is None or armed()):
            done.append(1)
            f = into + f[len(into) :]
        return honest(f)

    slave.handle = handle  # type: ignore[method-assign]
    return done


SET_XCP_WORKING = bytes([0xEB, 0x02, 0x00, 0x01])  # SET_CAL_PAGE(XCP, segment 0, working page 1)
ON_THE_REFERENCE_PAGE = bytes([0xEB, 0x02, 0x00, 0x00])  # ... its page byte garbled 1 -> 0 (answered positively)


def test_a_settlement_confirms_where_xcp_access_went_before_naming_the_page_by_its_crc(
    make_xcp_rig: XcpRigFactory,
) -> None:
    """The commit is executed but its answer lost (every time), and a garbled write left p01 = 42949672.95 (out of
    bounds) on the working page the application now uses. The settlement moves XCP's access to that page and
    names it by the ECU's CRC-32; its SET_CAL_PAGE(XCP, working) is garbled in the page byte and acknowledged
    without being performed: XCP's access stays on the reference page, whose CRC-32 is the baseline's. Trusting
    the acknowledgment reported 'the ECU application uses its working page 1' holding the previous calibration
    while the ECU ran on p01 = 42949672.95; the page is confirmed with GET_CAL_PAGE(XCP) first."""
    rig = make_xcp_rig("controller_ii", config=XcpConfig(step_timeout_s=0.02, step_retries=2, max_attempts=1))
    client, slave = rig.client, rig.ecu.slave
    client.read_active()
    client.restore_baseline()
    committed: list[int] = []

    def bad_write() -> None:
        if not committed:
            slave.pages[1][0:4] = b"\xff\xff\xff\xff"  # p01 (ULONG, factor 0.01, 0..1000) = 42949672.95
        committed.append(1)

    _swallow(rig, lambda f: f[:4] == bytes([0xEB, 0x01, 0x00, 0x01]), bad_write)  # the commit, unanswered
    garbled = _garble_once(rig, SET_XCP_WORKING, ON_THE_REFERENCE_PAGE, armed=lambda: bool(committed))
    with pytest.raises(BridgeError) as err:
        client.apply(ramp())
    state = err.value.ecu_state
    assert garbled and state is not None and state.read_back, state
    assert state.values == rig.ecu.active, state  # what the bridge reports is what the application uses
    assert rig.ecu.ecu_page == 0 and rig.ecu.active["p01"] == 500.0  # switched back: nothing out of bounds in use
    assert "switched it to the reference page" in state.detail and client.stats.restored_in_settle == 1


def test_reading_the_working_page_confirms_where_xcp_access_went(make_xcp_rig: XcpRigFactory) -> None:
    """After an apply XCP's access is parked on the reference page; reading the working page in use moves it
    there. A SET_CAL_PAGE(XCP, working) garbled into page 0, answered positively, left the read on the reference
    page: its CRC-32 matched the baseline, and read_active reported the baseline as the working page's set."""
    rig = make_xcp_rig("controller_ii")
    res = rig.client.apply(ramp())
    rig.client._page_bytes = {}  # nothing known of the pages: the bridge reads the working page
    garbled = _garble_once(rig, SET_XCP_WORKING, ON_THE_REFERENCE_PAGE)
    rd = rig.client.read_active()
    assert garbled and rd.note == "working page"
    assert rd.values == res.values == rig.ecu.active == rig.client.quantize(ramp())
    assert rig.ecu.slave.xcp_page == 0  # parked again after the read


def test_status_after_a_failed_apply_leaves_xcp_access_on_the_half_written_working_page(
    make_xcp_rig: XcpRigFactory,
) -> None:
    """An apply fails half-way (the ECU stops answering DOWNLOADs): the application stays on the reference page,
    XCP's access on the half-written working page. status(), which the node asks every diagnostics period,
    answers the reference page from what the bridge read of it, without moving XCP's access: moving it to the
    reference page made the next apply send SET_CAL_PAGE(XCP, working), one flipped bit (mode 0x02 -> 0x03) from
    switching the application onto the half-written page. That command is not sent before the page is checked."""
    rig = make_xcp_rig(
        "controller_ii", config=XcpConfig(step_timeout_s=0.02, step_retries=1, max_attempts=1, timeout_s=1.0)
    )
    client, slave = rig.client, rig.ecu.slave
    client.read_active()
    baseline = client.restore_baseline()
    honest = slave.handle
    downloads = [0]

    def stops_after_two_downloads(frame: bytes | bytearray) -> list[bytes]:
        f = bytes(frame)
        if f[:1] in (b"\xf0", b"\xef"):  # DOWNLOAD, DOWNLOAD_NEXT: neither executed nor answered after two
            downloads[0] += 1
            if downloads[0] > 2:
                return []
        return honest(f)

    slave.handle = stops_after_two_downloads  # type: ignore[method-assign]
    with pytest.raises(BridgeError):
        client.apply(ramp())
    assert slave.ecu_page == 0 and slave.xcp_page == 1 and slave.pages[1] != slave.pages[0]  # half written
    sent: list[bytes] = []

    def spy(frame: bytes | bytearray) -> list[bytes]:
        sent.append(bytes(frame))
        return honest(frame)

    slave.handle = spy  # type: ignore[method-assign]
    st = client.status()
    assert st.crc == baseline.crc and st.count == 20
    assert not [f for f in sent if f[0] == 0xEB] and slave.xcp_page == 1  # XCP's access was not moved
    sent.clear()
    res = client.apply(ramp(1.0))
    assert res.values == rig.ecu.active == client.quantize(ramp(1.0))
    first_check = next(k for k, f in enumerate(sent) if f[0] == 0xF3)  # BUILD_CHECKSUM of the written page
    assert SET_XCP_WORKING not in [f[:4] for f in sent[:first_check]]


def test_an_anomaly_during_the_commit_has_the_committed_page_checked_again(make_xcp_rig: XcpRigFactory) -> None:
    """The commit's answer is lost once (SYNCH and repeat) and a garbled write has changed the working page after
    its check (p01 = 42949672.95, out of bounds): the apply reported success while the application ran on it. An
    anomaly at or after the last check of the contents has the ECU's CRC-32s asked again after the commit: the
    attempt fails, the next one writes the page again and the apply ends on the requested values."""
    rig = make_xcp_rig("controller_ii")
    slave = rig.ecu.slave
    lost: list[int] = []

    def bad_write() -> None:
        slave.pages[1][0:4] = b"\xff\xff\xff\xff"
        lost.append(1)

    honest = slave.handle

    def handle(frame: bytes | bytearray) -> list[bytes]:
        out = honest(frame)
        if not lost and bytes(frame[:4]) == bytes([0xEB, 0x01, 0x00, 0x01]):  # the first commit
            bad_write()
            return []
        return out

    slave.handle = handle  # type: ignore[method-assign]
    res = rig.client.apply(ramp())
    assert res.values == rig.ecu.active == rig.client.quantize(ramp())
    assert lost and res.attempts == 2
    assert rig.ecu.ecu_page == 1


def test_a_one_page_ecu_is_read_without_get_cal_page_whatever_its_reference_page(
    make_xcp_rig: XcpRigFactory,
) -> None:
    """xcp.pages false with xcp.reference_page 1: the ECU has one page (0) and need not implement GET_CAL_PAGE."""
    d = load("controller_i")
    settings = XcpSettings.of(d, pages=False, reference_page=1)
    rig = make_xcp_rig(d, pages=False, settings=settings, refuse={int(Cmd.GET_CAL_PAGE): 0x20})
    res = rig.client.apply({"damping_front": 0.25, "damping_rear": 0.75})
    rd = rig.client.read_active()
    assert rd.values == res.values == rig.ecu.active == {"damping_front": 0.25, "damping_rear": 0.75}
    assert rig.client.status().crc == rd.crc


def test_an_ecu_that_acknowledges_writes_it_does_not_make_is_caught(make_xcp_rig: XcpRigFactory) -> None:
    rig = make_xcp_rig("controller_i", config=XcpConfig(step_timeout_s=0.05, max_attempts=2))
    slave = rig.ecu.slave
    honest_write = slave._write

    rear = rig.definition.parameter("damping_rear").xcp
    assert rear is not None

    def lying_write(data: bytes) -> list[bytes] | None:  # damping_rear's bytes are never written, but acknowledged
        start = slave.mta
        keep = max(0, min(len(data), rear.address - start))  # the bytes before damping_rear are written
        if keep:
            refused = honest_write(data[:keep])
            if refused is not None:
                return refused
        slave.mta = start + len(data)
        return None

    slave._write = lying_write  # type: ignore[method-assign]
    with pytest.raises(BridgeError, match="does not take the written bytes") as err:
        rig.client.apply({"damping_front": 0.3, "damping_rear": 0.9})
    assert err.value.code == ErrorCode.CRC_MISMATCH
    assert err.value.ecu_state is not None and err.value.ecu_state.holds is Holds.BASELINE  # the reference page
    assert rig.ecu.active == {"damping_front": 0.5, "damping_rear": 0.5} and rig.ecu.ecu_page == 0


def test_a_read_command_garbled_into_a_write_never_changes_the_calibration_in_use(
    make_xcp_rig: XcpRigFactory,
) -> None:
    """XCP on CAN has no check of its own: one flipped bit (0x04 of the command code) turns SHORT_UPLOAD (0xF4,
    8 bytes) into a DOWNLOAD of 7 bytes that writes its own address bytes at the MTA. Reading back the page the
    application uses, frame by frame, must not be able to change it (at 30 % faults it did, 8 times in 40
    applies); the bridge's reads are 2-byte UPLOADs, which nothing garbled this way turns into a write."""
    rig = make_xcp_rig("controller_ii")
    res = rig.client.apply(ramp())
    before = rig.ecu.commits
    slave = rig.ecu.slave
    honest = slave.handle
    reads = [0]

    def garbling(frame: bytes | bytearray) -> list[bytes]:
        f = bytes(frame)
        if f[:1] in (b"\xf4", b"\xf5"):
            reads[0] += 1
            if reads[0] % 3 == 0:
                f = bytes([f[0] ^ 0x04]) + f[1:]  # SHORT_UPLOAD -> DOWNLOAD, UPLOAD -> 0xF1 (unknown)
        return honest(f)

    slave.handle = garbling  # type: ignore[method-assign]
    client = rig.client
    for _ in range(3):
        client._degraded = True  # one answered command per frame, as after block transfers failed
        client._page_bytes = {}  # nothing known: every byte is read back
        client.last_confirmed = None
        assert client.read_active().values == res.values
    assert reads[0] >= 9  # the reads went frame by frame, and some were garbled
    assert rig.ecu.active == res.values and rig.ecu.commits == before


def test_a_silent_ecu_times_out_within_the_bound(make_xcp_rig: XcpRigFactory) -> None:
    config = XcpConfig(step_timeout_s=0.01, step_retries=2, max_attempts=3, timeout_s=0.5)
    rig = make_xcp_rig("controller_i", ecu_faults=FaultConfig(silent=True), config=config)
    t0 = time.monotonic()
    with pytest.raises(BridgeError, match="CONNECT") as err:
        rig.client.apply({"damping_front": 0.3, "damping_rear": 0.3})
    assert err.value.code == ErrorCode.TIMEOUT and not err.value.uncertain
    assert err.value.ecu_state is not None and err.value.ecu_state.holds is Holds.PREVIOUS  # it never answered
    assert time.monotonic() - t0 < 0.5 + 1.0  # the bound plus scheduling on a loaded machine


def test_lost_and_garbled_answers_at_10_percent_never_give_a_false_success(make_xcp_rig: XcpRigFactory) -> None:
    faults = FaultConfig(
        drop=0.05, corrupt=0.05, duplicate=0.03, delay=0.03, delay_s=0.005, reorder_hold_s=0.005, seed=4
    )
    config = XcpConfig(step_timeout_s=0.02, step_retries=8, max_attempts=3, timeout_s=5.0, settle_s=0.02)
    rig = make_xcp_rig("controller_ii", bridge_faults=faults, config=config)
    for k in range(8):
        want = ramp(k)
        try:
            res = rig.client.apply(want)
        except BridgeError as err:  # rarely (about 1 in 100 applies): the state reported is what the ECU holds
            assert err.ecu_state is not None and err.ecu_state.values == rig.ecu.active
            continue
        assert res.values == rig.ecu.active == rig.client.quantize(want)
    assert rig.client.stats.applies_ok >= 6
    assert rig.bridge_bus.counts.dropped > 0 and rig.bridge_bus.counts.corrupted > 0  # type: ignore[attr-defined]


def test_pyxcp_is_imported_without_changing_the_process_hooks_or_writing_files(tmp_path: Path) -> None:
    code = (
        "import sys; hooks = (sys.excepthook, sys.displayhook)\n"
        "from bac_ecu_bridge.xcp import _pyxcp; _pyxcp.load()\n"
        "from bac_ecu_bridge.xcp.a2l import read_a2l, shipped_a2l; read_a2l(shipped_a2l('controller_i'))\n"
        "print((sys.excepthook, sys.displayhook) == hooks)\n"
    )
    env = {**os.environ, "HOME": str(tmp_path / "home")}
    (tmp_path / "home").mkdir()
    out = subprocess.run(
        [sys.executable, "-c", code], cwd=tmp_path, env=env, capture_output=True, text=True, check=True
    )
    assert out.stdout.strip() == "True", out.stderr
    assert sorted(p.name for p in tmp_path.iterdir()) == ["home"] and not list((tmp_path / "home").iterdir())


class _LateCrcBus(can.BusABC):
    """The bridge's side of a bus that delays one BUILD_CHECKSUM answer of a status() poll by ``delay_s`` (the
    bus's worst delay, below the client's settle_s) and, should the next apply ask a checksum before it arrives,
    hands it that late answer in place of its own (which is lost)."""

    def __init__(self, inner: can.BusABC, delay_s: float) -> None:
        self.inner = inner
        self.delay_s = delay_s
        self.phase = ""
        self.held: can.Message | None = None
        self.held_at = 0.0
        self.swapped = False
        self.channel_info = "late-crc"
        super().__init__(channel="late-crc")

    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        self.inner.send(msg, timeout)

    def _recv_internal(self, timeout: float | None) -> tuple[can.Message | None, bool]:
        end = None if timeout is None else time.monotonic() + timeout
        while True:
            if self.held is not None and time.monotonic() - self.held_at >= self.delay_s:
                late, self.held = self.held, None  # its delay is over: it arrives, late
                return late, False
            left = 0.002 if end is None else max(0.0, min(0.002, end - time.monotonic()))
            msg = self.inner.recv(left)
            if msg is None:
                if end is not None and time.monotonic() >= end:
                    return None, False
                continue
            d = bytes(msg.data)
            is_crc = len(d) == 8 and d[0] == 0xFF and d[1] == 0x09  # a positive XCP_CRC_32 answer
            if is_crc and self.phase == "status" and self.held is None and not self.swapped:
                self.held, self.held_at = msg, time.monotonic()
                continue
            if is_crc and self.phase == "apply" and self.held is not None:
                late, self.held = self.held, None
                self.swapped = True
                return late, False
            return msg, False

    def shutdown(self) -> None:
        super().shutdown()
        self.inner.shutdown()


def test_a_late_checksum_answer_of_a_status_poll_never_confirms_the_next_apply() -> None:
    """The node polls status() between applies. A BUILD_CHECKSUM answer of that poll, delayed on the bus (less than
    settle_s), must not stand in for the next apply's check: applied again, the same set has the same CRC-32, and
    a DOWNLOAD garbled in its data would be confirmed. Every call starts once the frames of the calls before it
    have landed (found by an outside review: a false success with p01 = 168,172 on a 0-1000 parameter)."""
    d = load("controller_ii")
    channel = f"xcp-late-crc-{time.monotonic_ns()}"
    ecu_bus = can.Bus(interface="virtual", channel=channel)
    bus = _LateCrcBus(can.Bus(interface="virtual", channel=channel), delay_s=0.1)
    ecu = SimulatedXcpEcu(ecu_bus, d)
    ecu.start()
    client = XcpCalibrationClient(bus, d, None, XcpConfig(step_timeout_s=0.02, settle_s=0.25))
    try:
        want = {p.name: p.lower + 0.4 * (p.upper - p.lower) for p in d.parameters}
        client.apply(want)
        slave = ecu.slave
        honest = slave.handle
        garble = [False]

        def handle(frame: bytes | bytearray) -> list[bytes]:
            f = bytearray(frame)
            if garble[0] and f and f[0] == 0xF0 and len(f) >= 6:  # a DOWNLOAD: one bit of p01 flipped
                f[5] ^= 0x01
                garble[0] = False
            return honest(bytes(f))

        slave.handle = handle  # type: ignore[method-assign]
        bus.phase = "status"
        client.status()
        assert bus.held is not None or bus.swapped or client.stats.stale_frames  # the premise: an answer was late
        bus.phase, garble[0] = "apply", True
        try:
            res = client.apply(want)  # the same calibration again (a trial driven again, a resumed campaign)
        except BridgeError as exc:
            assert exc.ecu_state is not None and exc.ecu_state.values == ecu.active, exc.ecu_state
        else:
            assert res.values == client.quantize(want) == ecu.active
        assert not bus.swapped, "a late answer of status() stood in for one of the apply's"
    finally:
        client.close()
        ecu.stop()
        bus.shutdown()
        ecu_bus.shutdown()


def test_an_ecu_with_another_checksum_type_is_verified_by_read_back(make_xcp_rig: XcpRigFactory) -> None:
    """Many XCP drivers build XCP_ADD_44 or XCP_CRC_16 by default: the bridge reads every written byte back
    instead of refusing the ECU."""
    rig = make_xcp_rig("controller_ii")
    slave = rig.ecu.slave
    honest = slave.handle

    def crc16(frame: bytes | bytearray) -> list[bytes]:
        out = honest(frame)
        if frame and frame[0] == Cmd.BUILD_CHECKSUM and out and out[0][0] == 0xFF:
            b = bytearray(out[0])
            b[1] = 0x07  # XCP_CRC_16
            b[4:8] = (int.from_bytes(b[4:8], "little") & 0xFFFF).to_bytes(4, "little")
            out = [bytes(b)]
        return out

    slave.handle = crc16  # type: ignore[method-assign]
    res = rig.client.apply(ramp())
    assert res.values == rig.ecu.active == rig.client.quantize(ramp())
    assert rig.client.read_active().values == res.values


def test_an_ecu_whose_checksum_does_not_cover_the_range_it_is_given_is_refused_by_name(
    make_xcp_rig: XcpRigFactory,
) -> None:
    """A non-conforming XCP driver whose BUILD_CHECKSUM is not over the MTA range it is given (here: one byte
    less) disagrees with the bytes UPLOAD reads, round after round: the error says so, and the application
    stays on the baseline."""
    rig = make_xcp_rig("controller_ii")
    slave = rig.ecu.slave
    honest = slave.handle

    def off_by_one(frame: bytes | bytearray) -> list[bytes]:
        f = bytearray(frame)
        if f and f[0] == Cmd.BUILD_CHECKSUM and len(f) >= 8:
            f[4] -= 1  # the block size's low byte (little endian): one byte less than asked
        return honest(bytes(f))

    slave.handle = off_by_one  # type: ignore[method-assign]
    with pytest.raises(BridgeError, match="does not cover that range of the page") as err:
        rig.client.apply(ramp())
    assert err.value.ecu_state is not None and err.value.ecu_state.holds is not Holds.UNKNOWN
    assert rig.ecu.active == rig.client.quantize(rig.definition.baseline_values())  # nothing of the request in use


def test_a_refused_build_checksum_is_asked_again_in_the_next_session(make_xcp_rig: XcpRigFactory) -> None:
    """A refusal of BUILD_CHECKSUM (confirmed, but on a bus that garbles frames it may be one) does not turn the
    full read-back on for the client's whole life: after the ECU's reset the checksum is asked again."""
    rig = make_xcp_rig("controller_ii", refuse={int(Cmd.BUILD_CHECKSUM): 0x20})  # ERR_CMD_UNKNOWN
    assert rig.client.apply(ramp()).values == rig.ecu.active
    slave = rig.ecu.slave
    slave.refuse = {int(Cmd.UPLOAD): 0x24}  # now the ECU builds checksums and refuses reads
    slave.reset()  # a power cycle: a new session
    res = rig.client.apply(ramp(0.1))
    assert res.values == rig.ecu.active == rig.client.quantize(ramp(0.1))
