"""Rescoring a resumed campaign: each run is cut from the bags of the launch that drove it.

Sim time starts again with each launch, so two launches of one campaign record the same stamps. The bags here
are built by hand: launch 1 drove trial 1 (attempt 1), launch 2 drove trial 1 again (attempt 2) and trial 2,
with exactly the stamps of launch 1, and opened a bag for trial 3 that holds no sample (killed at once).
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from bac_agent.journal import Journal
from bac_campaign.launches import LaunchIndex, launch_of_bags
from bac_campaign.rescore import RescoreResult, rescore
from bac_imu.ingest import ingest_all
from bac_measure.measure_config import ingest_config, segment_config
from bac_measure.recording import TrialBagWriter
from bac_measure.segmentation import Reference
from bac_sim.run import simulate_run

T0 = 10_000_000_000  # every launch's run starts at sim time 10 s
CID = "camp"
CALS = {"A": {"damping_front": 0.8, "damping_rear": 0.5}, "B": {"damping_front": 0.2, "damping_rear": 0.9},
        "C": {"damping_front": 0.5, "damping_rear": 0.3}}  # fmt: skip


def _trial(trial_id: int, attempt: int, state: int, stamp_ns: int) -> bytes:
    from rclpy.serialization import serialize_message

    from bac_msgs.msg import Calibration, Trial

    # (a calibration with values: rosbags and Fast-CDR align an empty float64[] differently)
    cal = Calibration(trial_id=trial_id, names=["damping_front"], values=[0.5])
    m = Trial(campaign_id=CID, trial_id=trial_id, attempt=attempt, state=state, calibration=cal)
    m.stamp.sec, m.stamp.nanosec = stamp_ns // 10**9, stamp_ns % 10**9
    return bytes(serialize_message(m))


def _run_messages(cal: str, seed: int, t0: int) -> list[tuple[str, int, bytes]]:
    """A simulated bump run as the recorder stores it: imu/vehicle (ingested) and vehicle/odom, stamped from t0."""
    from nav_msgs.msg import Odometry
    from rclpy.serialization import serialize_message
    from sensor_msgs.msg import Imu

    rec = simulate_run(CALS[cal], "bump", seed=seed)
    out, _ = ingest_all((t0 + np.round(rec.t * 1e9)).astype(np.int64), rec.accel, rec.gyro, ingest_config([]))
    msgs: list[tuple[str, int, bytes]] = []
    for t, az, q in zip(out.stamp_ns.tolist(), out.accel_z.tolist(), out.pitch_rate.tolist(), strict=True):
        m = Imu()
        m.header.stamp.sec, m.header.stamp.nanosec = t // 10**9, t % 10**9
        m.linear_acceleration.z = az
        m.angular_velocity.y = q
        msgs.append(("imu/vehicle", t, bytes(serialize_message(m))))
    odom_ns = (t0 + np.round(rec.odom_t * 1e9)).astype(np.int64)
    for t, d, v in zip(odom_ns.tolist(), rec.distance.tolist(), rec.speed.tolist(), strict=True):
        o = Odometry()
        o.header.stamp.sec, o.header.stamp.nanosec = t // 10**9, t % 10**9
        o.pose.pose.position.x = d
        o.twist.twist.linear.x = v
        msgs.append(("vehicle/odom", t, bytes(serialize_message(o))))
    return sorted(msgs, key=lambda x: x[1])


# (calibration, seed, start): launch 2 drives (1, 2) at the same sim time as launch 1 drove (1, 1), then (2, 1)
RUNS = {(1, 1): ("A", 3, T0), (1, 2): ("B", 4, T0), (2, 1): ("C", 5, T0 + 30 * 10**9)}
_MESSAGES: dict[tuple[int, int], list[tuple[str, int, bytes]]] = {}


def messages(key: tuple[int, int]) -> list[tuple[str, int, bytes]]:
    if key not in _MESSAGES:
        _MESSAGES[key] = _run_messages(*RUNS[key])
    return _MESSAGES[key]


def write_bag(path: Path, trial_id: int, runs: list[tuple[int, int]]) -> None:
    t0 = RUNS[runs[0]][2] if runs else T0
    with TrialBagWriter(path) as w:
        w.write("bac/trial", t0 - 10**8, _trial(trial_id, 1, 2, t0 - 10**8))  # APPLYING
        for tid, att in runs:
            w.write("bac/trial", t0, _trial(tid, att, 3, t0))  # READY_TO_DRIVE: the run starts
            w.write_many(messages((tid, att)))


def make_campaign(camp: Path, index: bool = True) -> None:
    bags = camp / "bags"
    plan = [
        (1, "trial_0001", 1, [(1, 1)]),
        (2, "trial_0001.r1", 1, [(1, 2)]),
        (2, "trial_0002", 2, [(2, 1)]),
        (2, "trial_0003", 3, []),  # opened, then the launch was killed: bac/trial only
    ]
    launches = {1: LaunchIndex(camp), 2: LaunchIndex(camp)} if index else {}
    for launch, name, tid, runs in plan:
        if index:
            launches[launch].bag_opened(bags / name, tid, T0)
        write_bag(bags / name, tid, runs)
    for li in launches.values():
        li.close()
    with Journal(camp) as j:
        j.append("campaign_started", campaign_id=CID, schema=2)
        j.append("trial_proposed", campaign_id=CID, trial_id=1)
        j.append("run_ready", campaign_id=CID, trial_id=1, attempt=1)
        j.append("campaign_resumed", campaign_id=CID)
        j.append("apply_requested", campaign_id=CID, trial_id=1, apply_try=2)
        j.append("run_ready", campaign_id=CID, trial_id=1, attempt=2)
        j.append("trial_scored", campaign_id=CID, trial_id=1, attempt=2, j=1.5)
        j.append("trial_proposed", campaign_id=CID, trial_id=2)
        j.append("run_ready", campaign_id=CID, trial_id=2, attempt=1)
        j.append("trial_scored", campaign_id=CID, trial_id=2, attempt=1, j=1.25)
        j.append("trial_proposed", campaign_id=CID, trial_id=3)


def by_key(result: RescoreResult) -> dict[tuple[int, int], Any]:
    out = {(r.run.trial_id, r.run.attempt): r for r in result.runs}
    assert len(out) == len(result.runs), "a run rescored twice"
    return out


@pytest.fixture(scope="module")
def alone(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, dict[tuple[int, int], float]]:
    """Each run rescored from a bag of its own, aligned with one template (the reference run (1, 2) cut alone):
    what the campaign's rescoring must give for it, whatever else the campaign holds."""
    d = tmp_path_factory.mktemp("alone")
    for tid, att in RUNS:
        write_bag(d / f"run_{tid}_{att}", tid, [(tid, att)])
    ref_seg = by_key(rescore([d / "run_1_2"]))[(1, 2)].segment
    template = d / "reference.npz"
    Reference.from_segment(ref_seg, segment_config([])).save(template)
    ov = {"run_segmenter": {"template_file": str(template)}}
    js = {key: by_key(rescore([d / f"run_{key[0]}_{key[1]}"], overrides=ov))[key] for key in RUNS}
    assert all(r.score.valid for r in js.values())
    assert len({round(r.j, 6) for r in js.values()}) == 3  # three different calibrations, three J
    return template, {k: r.j for k, r in js.items()}


@pytest.mark.slow
@pytest.mark.parametrize("index", [True, False], ids=["recorder index", "journal (older campaigns)"])
def test_each_run_is_cut_from_its_own_launch(
    alone: tuple[Path, dict[tuple[int, int], float]], tmp_path: Path, index: bool
) -> None:
    template, expected = alone
    camp = tmp_path / CID
    make_campaign(camp, index=index)
    assert bool(launch_of_bags(camp)) == index
    result = rescore([camp], overrides={"run_segmenter": {"template_file": str(template)}})
    got = by_key(result)
    assert set(got) == set(RUNS)  # trial 3's bag holds no IMU: no run, no abort
    for key, j in expected.items():
        assert got[key].score.valid, (key, got[key].score.reason)
        assert got[key].j == pytest.approx(j, abs=1e-9), key
    assert got[(1, 2)].live_j == 1.5 and got[(1, 1)].live_j is None  # the agent's verdict, from the journal
    assert [(r.run.trial_id, r.run.attempt) for r in result.runs] == [(1, 1), (1, 2), (2, 1)]  # the live order
    assert any("2 launches" in n for n in result.notes)
    assert any("not in launches.jsonl" in n for n in result.notes) != index


@pytest.mark.slow
def test_the_live_reference_run_is_the_reference(
    alone: tuple[Path, dict[tuple[int, int], float]], tmp_path: Path
) -> None:
    """The live segmenter made run (1, 2) the reference (its reference file says so; (1, 1) was cut off by the
    kill live, though its bag holds enough of it to be cut now): the rescoring aligns with (1, 2), as live."""
    template, expected = alone
    camp = tmp_path / CID
    make_campaign(camp)
    ref = Reference.load(template)
    assert (ref.run.trial_id, ref.run.attempt) == (1, 2)
    ref.save(camp / "reference.npz")
    got = by_key(rescore([camp]))
    assert got[(2, 1)].j == pytest.approx(expected[(2, 1)], abs=1e-9)  # aligned with (1, 2), as with the template
    # without the file, the first valid run in the live order, (1, 1), would be the reference
    (camp / "reference.npz").unlink()
    other = by_key(rescore([camp]))
    assert other[(2, 1)].j != pytest.approx(expected[(2, 1)], abs=1e-9)
    lines = [json.loads(x) for x in (camp / "launches.jsonl").read_text().splitlines()]
    assert [x["bag"] for x in lines] == ["trial_0001", "trial_0001.r1", "trial_0002", "trial_0003"]
