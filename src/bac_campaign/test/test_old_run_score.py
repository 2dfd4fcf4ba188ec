"""A RunScore recorded before outcome_names / outcome_values existed (2026-11-24, issue 23) still reads: in
bac rescore (rosbags) and in bac replay (rclpy with the current definition, which alone refuses it)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import pytest
from rosbags.rosbag2 import StoragePlugin, Writer
from rosbags.typesys import Stores, get_types_from_msg, get_typestore

from bac_measure.bagio import read_messages
from bac_measure.recording import OLD_MESSAGE_PAD, bac_msgs_dir


def old_store() -> Any:
    """A type store with RunScore as it was before the outcomes (the current definition up to them)."""
    text = (bac_msgs_dir() / "RunScore.msg").read_text()
    store = get_typestore(Stores.ROS2_JAZZY)
    store.register(get_types_from_msg(text[: text.index("# Outcomes measured besides J")], "bac_msgs/msg/RunScore"))
    return store


def old_run_score(store: Any, reason: str, valid: bool, j: float) -> bytes:
    types = store.types
    m = types["bac_msgs/msg/RunScore"](
        header=types["std_msgs/msg/Header"](stamp=types["builtin_interfaces/msg/Time"](sec=5, nanosec=7), frame_id="x"),
        campaign_id="c1",
        trial_id=3,
        attempt=2,
        j=j,
        rms_accel_z=0.5,
        rms_pitch_rate=0.1,
        weighted_rms_accel_z=0.4,
        vdv_accel_z=0.9,
        kpi="rms",
        weight_accel_z=1.0,
        weight_pitch_rate=1.0,
        psd_frequency_hz=np.array([1.0, 2.0]),
        psd_accel_z=np.array([0.1, 0.2]),
        psd_pitch_rate=np.array([0.3, 0.4]),
        valid=valid,
        reason=reason,
    )
    return bytes(store.serialize_cdr(m, "bac_msgs/msg/RunScore"))


# reasons of every length modulo 4: the pad must cover the alignment before the sequences in each case
CASES = [("", True, 0.61), ("a", False, float("nan")), ("ab", True, 1.25), ("too slow", False, float("nan"))]


@pytest.mark.parametrize("storage", ["mcap", "sqlite3"])
def test_rescore_reads_an_old_bags_run_scores(tmp_path: Path, storage: str) -> None:
    """rosbags decodes with the definition the bag recorded (rosbag2 8+, mcap and sqlite3): bac rescore's J, valid
    and reason of an older bag are what was recorded."""
    store = old_store()
    path = tmp_path / "old_bag"
    with Writer(path, version=9, storage_plugin=getattr(StoragePlugin, storage.upper())) as w:
        conn = w.add_connection("/bac/run_score", "bac_msgs/msg/RunScore", typestore=store)
        for k, (reason, valid, j) in enumerate(CASES):
            w.write(conn, 1000 + k, old_run_score(store, reason, valid, j))
    msgs = [m for _, m in read_messages(path, "bac/run_score")]
    assert [(m.reason, bool(m.valid), m.trial_id, m.attempt) for m in msgs] == [(r, v, 3, 2) for r, v, _ in CASES]
    assert msgs[0].j == 0.61 and msgs[2].j == 1.25 and list(msgs[2].psd_pitch_rate) == [0.3, 0.4]
    assert all(len(getattr(m, "outcome_names", [])) == 0 for m in msgs)


def test_replay_decodes_an_old_run_score_with_empty_outcomes() -> None:
    from rclpy.serialization import deserialize_message

    from bac_campaign.replay import _run_score
    from bac_msgs.msg import RunScore

    store = old_store()
    for reason, valid, j in CASES:
        raw = old_run_score(store, reason, valid, j)
        with pytest.raises(Exception):  # noqa: B017  the current type alone refuses the shorter message
            deserialize_message(raw, RunScore)
        s = _run_score(raw)
        assert (s.campaign_id, s.trial_id, s.attempt, s.valid, s.reason) == ("c1", 3, 2, valid, reason)
        assert (s.j == j) or (np.isnan(j) and np.isnan(s.j))
        assert list(s.outcome_names) == [] and list(s.outcome_values) == []
    assert len(OLD_MESSAGE_PAD) >= 3 + 4 + 4  # alignment, two sequence lengths
