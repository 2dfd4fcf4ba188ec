"""The cockpit's state: what the graph's messages and the journal make of it (no ROS runtime, no web server)."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
from campaign_maker import make_campaign, segment_signals

from bac_cockpit.folder import read_folder
from bac_cockpit.state import (
    HEADLINES,
    KIND_NAMES,
    STATE_NAMES,
    CockpitState,
    calibration_from_msg,
    decimate,
    diagnostics_from_msg,
    score_from_msg,
    segment_from_msg,
    trial_from_msg,
)
from bac_msgs.msg import Calibration, RunScore, RunSegment, Trial


def trial_msg(state: int, trial_id: int = 1, attempt: int = 1, j: float = math.nan, reason: str = "",
              params: tuple[float, float] = (0.2, 0.3), kind: int = 1) -> Trial:  # fmt: skip
    m = Trial()
    m.campaign_id, m.trial_id, m.attempt, m.state, m.kind = "c1", trial_id, attempt, state, kind
    m.calibration = Calibration(trial_id=trial_id, names=["damping_front", "damping_rear"], values=list(params))
    m.budget, m.trials_done = 5, trial_id - 1
    m.last_j, m.best_j, m.best_trial_id = j, j, trial_id if math.isfinite(j) else 0
    m.predicted_j, m.predicted_j_std = 0.95, 0.01
    m.instruction, m.reason = f"instruction {state}", reason
    return m


def segment_msg(trial_id: int, attempt: int = 1, valid: bool = True, n: int = 500, scale: float = 1.0) -> RunSegment:
    az, q = segment_signals(n, scale, seed=trial_id)
    m = RunSegment()
    m.campaign_id, m.trial_id, m.attempt = "c1", trial_id, attempt
    m.sample_rate_hz, m.mean_speed_mps, m.target_speed_mps = 200.0, 8.2, 8.3333
    m.accel_z, m.pitch_rate = az.tolist(), q.tolist()
    m.valid, m.reason = valid, "" if valid else "too slow: 6.1 m/s"
    return m


def score_msg(trial_id: int, j: float, attempt: int = 1, psd: bool = True) -> RunScore:
    m = RunScore()
    m.campaign_id, m.trial_id, m.attempt, m.j, m.valid, m.kpi = "c1", trial_id, attempt, j, True, "rms"
    if psd:
        m.psd_frequency_hz, m.psd_accel_z, m.psd_pitch_rate = [0.0, 0.5, 1.0], [1.0, 2.0, 3.0], [0.1, 0.2, 0.3]
    return m


def test_the_contract_numbers_are_the_messages() -> None:
    for value, name in STATE_NAMES.items():
        assert getattr(Trial, f"STATE_{name}") == value
    for value, name in KIND_NAMES.items():
        assert getattr(Trial, f"KIND_{name.upper()}") == value
    assert HEADLINES[Trial.STATE_READY_TO_DRIVE] == ("READY TO DRIVE", "go")
    assert HEADLINES[Trial.STATE_APPLYING][0] == "DO NOT DRIVE"


def test_topics_alone_give_the_state_and_the_trials() -> None:
    st = CockpitState()
    assert st.on_trial(trial_from_msg(trial_msg(Trial.STATE_APPLYING))) == ["trial", "trials", "signals", "spectra"]
    assert st.part("trial")["headline"] == "DO NOT DRIVE"
    st.on_trial(trial_from_msg(trial_msg(Trial.STATE_READY_TO_DRIVE)))
    snap = st.snapshot()
    assert snap["trial"]["headline"] == "READY TO DRIVE" and snap["trial"]["tone"] == "go"
    st.on_trial(trial_from_msg(trial_msg(Trial.STATE_REJECTED, reason="too slow: 6.1 m/s")))
    st.on_trial(trial_from_msg(trial_msg(Trial.STATE_READY_TO_DRIVE, attempt=2, reason="too slow: 6.1 m/s")))
    st.on_trial(trial_from_msg(trial_msg(Trial.STATE_SCORED, attempt=2, j=0.97)))
    rows = st.part("trials")
    assert rows[0]["j"] == 0.97 and rows[0]["status"] == "scored" and rows[0]["attempts"] == 2
    assert rows[0]["rejected"] == [[1, "too slow: 6.1 m/s"]]
    assert st.part("best")["trial_id"] == 1
    done = trial_msg(Trial.STATE_DONE, trial_id=2, params=(0.21, 0.33))
    st.on_trial(trial_from_msg(done))
    assert st.part("recommendation")["params"] == {"damping_front": 0.21, "damping_rear": 0.33}
    json.dumps(st.snapshot(), allow_nan=False)  # strict JSON: no NaN reaches a browser


def test_signals_are_the_last_run_against_the_best_and_their_spectra() -> None:
    st = CockpitState()
    for tid, j in ((1, 1.05), (2, 0.93), (3, 0.99)):
        st.on_trial(trial_from_msg(trial_msg(Trial.STATE_SCORED, trial_id=tid, j=j)))
        st.on_segment(segment_from_msg(segment_msg(tid, scale=j)))
        st.on_score(score_from_msg(score_msg(tid, j, psd=tid != 3)))
    sig = st.part("signals")
    assert sig["last"]["trial_id"] == 3 and sig["best"]["trial_id"] == 2
    assert sig["best"]["j"] == 0.93 and len(sig["last"]["t"]) == 500
    assert sig["last"]["t"][1] == pytest.approx(1 / 200.0)
    spec = st.part("spectra")
    assert spec["best"]["source"] == "kpi_scorer" and spec["best"]["f"] == [0.5, 1.0]  # the DC bin left out
    assert spec["last"]["source"] == "welch_psd" and len(spec["last"]["f"]) > 10  # no PSD sent: computed
    # a rejected run is the last run (with its reason), the best stays
    st.on_segment(segment_from_msg(segment_msg(4, valid=False)))
    sig = st.part("signals")
    assert sig["last"]["trial_id"] == 4 and not sig["last"]["valid"] and "too slow" in sig["last"]["reason"]
    assert sig["best"]["trial_id"] == 2
    assert st.part("speed")["last_mean_kmh"] == pytest.approx(8.2 * 3.6)


def test_decimation_keeps_the_peaks_and_bounds_the_points() -> None:
    x = np.sin(np.linspace(0, 40, 100_000))
    x[12345] = 7.0
    x[54321] = -9.0
    y, stride = decimate(x, 2000)
    assert y.size <= 2000 and stride > 1
    assert y.max() == 7.0 and y.min() == -9.0
    same, s1 = decimate(x[:100], 2000)
    assert s1 == 1 and np.array_equal(same, x[:100])


def test_diagnostics_fill_the_ecu_and_imu_cards() -> None:
    from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue

    arr = DiagnosticArray()
    ecu = DiagnosticStatus(
        name="ecu_bridge: CAN calibration link", level=DiagnosticStatus.WARN, message="last apply failed"
    )
    ecu.values = [KeyValue(key="applies_ok", value="4"), KeyValue(key="frames_sent", value="99")]
    imu = DiagnosticStatus(name="imu_ingest: imu/data_raw", level=DiagnosticStatus.OK, message="OK, 400.0 Hz")
    imu.values = [KeyValue(key="rate_hz", value="400.0"), KeyValue(key="gaps", value="0")]
    arr.status = [ecu, imu]
    st = CockpitState()
    assert set(st.on_diagnostics(diagnostics_from_msg(arr))) == {"ecu", "imu", "diagnostics"}
    st.on_calibration(calibration_from_msg(Calibration(trial_id=3, names=["a"], values=[0.5], crc32=0xABCD)))
    e = st.part("ecu")
    assert e["link"]["level"] == "WARN" and e["link"]["values"] == {"applies_ok": "4"}  # the card's keys only
    assert e["holds"] == {"trial_id": 3, "params": {"a": 0.5}, "crc32": "0x0000ABCD"}
    assert st.part("imu")["stream"]["values"] == {"rate_hz": "400.0", "gaps": "0"}
    assert len(st.part("diagnostics")) == 2


def test_the_journal_replaces_what_the_topics_said(tmp_path: Path) -> None:
    folder = tmp_path / "camp"
    make_campaign(folder, budget=6, reject={2: "alignment 0.31 below 0.5"})
    facts = read_folder(folder)
    assert facts is not None and facts.ended == "done"
    st = CockpitState()
    st.on_trial(trial_from_msg(trial_msg(Trial.STATE_SCORED, trial_id=1, j=123.0)))  # a stale topic view
    keys = st.set_rows(facts.rows, facts.recommendation, facts.last_apply)
    assert {"trials", "recommendation", "ecu"} <= set(keys)
    rows = st.part("trials")
    assert [r["trial_id"] for r in rows] == list(range(1, 8))  # 6 trials + the confirmation run
    assert rows[0]["j"] != 123.0
    assert rows[1]["rejected"] == [[1, "alignment 0.31 below 0.5"]] and rows[1]["attempts"] == 2
    assert rows[-1]["kind"] == "confirmation"
    assert st.part("recommendation")["final"] is True
    last = st.part("ecu")["last_apply"]
    assert last["success"] is True and last["trial_id"] == 7 and last["attempts"] == 2 and last["latency_s"] == 0.012
    assert st.set_rows(facts.rows, facts.recommendation, facts.last_apply) == []  # nothing new: no patch


def test_a_campaign_paused_for_a_lost_ecu_link_reads_as_paused_until_resumed(tmp_path: Path) -> None:
    """The agent stopped resumable (campaign_paused, exit 2): the folder view, the page and the report say so; they
    said 'a trial is in progress' (issue 18's pause and the cockpit met only on main)."""
    from bac_agent.journal import Journal
    from bac_campaign.report import campaign_status, load_campaign

    folder = tmp_path / "camp"
    make_campaign(folder, budget=6, stop_after=2)
    j = Journal(folder)
    j.append("link_lost", trial_id=3, message="cannot open CAN interface 'can0'", stamp=9.0)
    j.append("campaign_paused", trial_id=3, down_s=600.0, message="cannot open CAN interface 'can0'", stamp=9.5)
    j.close()
    facts = read_folder(folder)
    assert facts is not None and facts.ended == "paused"
    text = campaign_status(load_campaign(folder))
    assert "paused: the ECU link stayed down (cannot open CAN interface 'can0')" in text and "in progress" not in text
    j = Journal(folder)
    j.append("campaign_resumed", trials_done=2, in_flight=[3], torn_bytes=0, changed=[], stamp=0.0)
    j.close()
    facts = read_folder(folder)
    assert facts is not None and facts.ended == ""
    assert not load_campaign(folder).paused


def test_a_bag_without_the_cockpits_topics_gives_nothing(tmp_path: Path) -> None:
    """rosbags reads every message when given no connection: a bag of other topics gave all of them (2026-11-29)."""
    from rosbags.rosbag2 import StoragePlugin, Writer

    from bac_cockpit.folder import _messages
    from bac_measure.recording import bac_typestore

    store = bac_typestore()
    with Writer(tmp_path / "b", version=9, storage_plugin=StoragePlugin.MCAP) as w:
        conn = w.add_connection("/chatter", "std_msgs/msg/String", typestore=store)
        w.write(
            conn, 1, bytes(store.serialize_cdr(store.types["std_msgs/msg/String"](data="hi"), "std_msgs/msg/String"))
        )
    assert list(_messages(tmp_path / "b")) == []
