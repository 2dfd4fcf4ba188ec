"""A campaign as one ASAM MDF4 file (``bac export CAMPAIGN --mf4``): open it in asammdf's GUI, CANape or INCA.

Everything a calibration engineer wants beside their own measurements of the same drives, on the same absolute
time base (the file's start time is the campaign's first recorded stamp, UTC; every channel's time is seconds
from it, so a CANape recording of the same day lines up):

* ``trial_NNNN.raw.*``: the IMU as the driver sent it (``imu/data_raw``: accel_x/y/z in m/s^2, gyro_x/y/z in
  rad/s, sensor frame, gravity in), one channel group per trial at the IMU's rate;
* ``trial_NNNN.vehicle.*``: what the ingestion made of it (``imu/vehicle``: vertical acceleration without
  gravity, pitch rate, in the vehicle frame, at the output rate), when recorded;
* ``trial_NNNN.odom.*``: distance (m) and speed (m/s, km/h) of the odometry;
* ``trial_NNNN.aN.*``: each attempt's aligned window as the KPI scored it (``bac/run_segment``): accel_z
  (m/s^2), pitch_rate (rad/s) and, in distance mode, the road distance (m) of each sample; the time of a
  sample is the window's start plus k / sample rate (distance mode: at the target speed); the group comment
  holds J, validity and reason, lag, alignment score, mean speed and the trial's calibration;
* ``campaign.*`` (group "runs"): one sample per run at its window's start: trial, attempt, J and its parts,
  validity, and each calibration parameter of the trial (with its unit from the definition): the campaign's
  calibration history as signals;
* the file comment (HD block): campaign id, definition, strategy, recommendation and confirmation;
* what rescoring needs (:mod:`bac_campaign.exportio`): ``trial_NNNN.trial.*`` (the agent's ``bac/trial``
  announcements: where each run starts), the raw IMU's receive times, and the campaign's files as embedded
  attachments (journal, launch index, config/, the alignment reference): ``bac rescore CAMPAIGN.mf4`` scores
  the file as it scores the folder, without it.

Units and comments are on every channel. asammdf is imported only when exporting.

    bac export CAMPAIGN_DIR [--mf4] [--out FILE.mf4] [--no-raw]
"""

from __future__ import annotations

import argparse
import math
import sys
from collections.abc import Sequence
from dataclasses import dataclass, field
from datetime import UTC, datetime
from pathlib import Path
from typing import Any
from xml.sax.saxutils import escape

import numpy as np

from bac_campaign.exportio import attach_campaign_files, trial_signals
from bac_common.console import say
from bac_common.errors import BacError
from bac_measure.bagio import BagError, ImuArrays, bag_topics, read_imu, read_messages, read_odom, read_trials

NS = 1_000_000_000
ACCEL = "m/s^2"
RATE = "rad/s"


MDF_SUFFIX = ".mf4"  # asammdf names every MDF 4 file it writes so (out.mdf became out.mf4)


class ExportError(BacError, ValueError):
    """The campaign folder cannot be exported."""


@dataclass
class _Run:
    trial_id: int
    attempt: int
    window_start_ns: int
    segment: Any | None = None  # bac_msgs/RunSegment (rosbags)
    score: Any | None = None  # bac_msgs/RunScore


@dataclass
class ExportResult:
    path: Path
    channels: int
    groups: int
    runs: int
    notes: list[str] = field(default_factory=list)
    files: int = 0  # the campaign's files attached (journal, config, ...)


def _num(x: Any) -> float:
    try:
        v = float(x)
    except (TypeError, ValueError):
        return math.nan
    return v


def _hd_comment(lines: Sequence[str]) -> str:
    return "<HDcomment><TX>" + escape("\n".join(lines)) + "</TX></HDcomment>"


def export_mf4(campaign_dir: str | Path, out: str | Path | None = None, raw: bool = True) -> ExportResult:
    """Write the campaign's MDF4 file (default: ``<campaign>/export/<campaign id>.mf4``)."""
    from bac_campaign.report import load_campaign
    from bac_measure.mdfio import asammdf

    mod = asammdf()
    MDF, Signal = mod.MDF, mod.Signal

    camp = Path(campaign_dir)
    if out is not None and Path(out).suffix != MDF_SUFFIX:
        raise ExportError(
            f"--out {out}: bac export writes ASAM MDF 4 only; name the file .mf4 (CSV, MATLAB and more: open the "
            "MDF4 in asammdf's GUI or with asammdf's MDF.export)"
        )
    if not (camp / "bags").is_dir():
        raise ExportError(f"{camp} is not a campaign folder (no bags/): give the folder bac launch / bac demo made")
    bags = sorted(d for d in (camp / "bags").iterdir() if d.is_dir())
    if not bags:
        raise ExportError(f"{camp} holds no trial bags (bags/trial_*)")
    try:
        campaign = load_campaign(camp)
    except BacError as exc:
        raise ExportError(f"{camp}: {exc}") from exc
    units = {p.name: p.unit for p in campaign.definition.parameters}
    params = {t.trial_id: t.params for t in campaign.trials}
    notes: list[str] = []

    # read everything first: the file's start time is the earliest stamp
    per_bag: list[tuple[Path, dict[str, Any]]] = []
    t_min: int | None = None
    for bag in bags:
        try:
            topics = {"/" + t.lstrip("/") for t in bag_topics(bag)}
        except BagError as exc:
            notes.append(f"{bag.name}: skipped ({exc})")
            continue
        got: dict[str, Any] = {}
        if raw and "/imu/data_raw" in topics:
            got["raw"] = read_imu(bag, "imu/data_raw")
        if "/imu/vehicle" in topics:
            got["vehicle"] = read_imu(bag, "imu/vehicle")
        if "/vehicle/odom" in topics:
            got["odom"] = read_odom(bag, "vehicle/odom")
        if "/bac/trial" in topics:
            got["trials"] = read_trials(bag)
        runs: dict[tuple[int, int], _Run] = {}
        for topic, key in (("bac/run_segment", "segment"), ("bac/run_score", "score")):
            if "/" + topic not in topics:
                continue
            for _, m in read_messages(bag, topic):
                stamp = int(m.header.stamp.sec) * NS + int(m.header.stamp.nanosec)
                r = runs.setdefault((int(m.trial_id), int(m.attempt)), _Run(int(m.trial_id), int(m.attempt), stamp))
                setattr(r, key, m)
        got["runs"] = runs
        for v in (got.get("raw"), got.get("vehicle"), got.get("odom")):
            if v is not None and len(v):
                t_min = int(v.stamp_ns[0]) if t_min is None else min(t_min, int(v.stamp_ns[0]))
        for r in runs.values():
            t_min = r.window_start_ns if t_min is None else min(t_min, r.window_start_ns)
        for e in got.get("trials", []):
            t_min = e.stamp_ns if t_min is None else min(t_min, e.stamp_ns)
        per_bag.append((bag, got))
    if t_min is None:
        raise ExportError(f"{camp}: the trial bags hold no IMU, odometry or run to export")
    t0 = t_min - t_min % 1000  # MDF start time: microseconds

    def rel(ns: Any) -> Any:
        return (np.asarray(ns, dtype=np.int64) - t0) / 1e9

    mdf = MDF(version="4.10")
    mdf.header.start_time = datetime.fromtimestamp(t0 // NS, UTC).replace(microsecond=(t0 % NS) // 1000)
    rec = campaign.recommendation or {}
    confirmation = [t for t in campaign.trials if t.kind == 2 and t.status == "scored"]
    mdf.header.comment = _hd_comment(
        [
            f"bac campaign {campaign.campaign_id} ({camp.name}), exported {datetime.now(UTC):%Y-%m-%d %H:%M:%S} UTC",
            f"calibration definition: {campaign.definition.name}; tuned: {', '.join(campaign.names)}",
            f"strategy: {campaign.strategy}; trials: {len(campaign.trials)}; scored: {len(campaign.scored())}",
            "recommendation: "
            + (
                ", ".join(f"{k}={v:.6g}" for k, v in rec.get("params", {}).items())
                + f"; predicted J {_num(rec.get('predicted_j')):.6g} +- {_num(rec.get('predicted_std')):.3g}"
                if rec
                else "none"
            ),
            "confirmation run: " + (f"J {confirmation[-1].j:.6g}" if confirmation else "none"),
            "time: seconds from the start time (ROS time of the campaign's first recorded sample, UTC)",
            "J = weight_accel_z * A + weight_pitch_rate * RMS(pitch rate) (paper eq. 1: A = RMS(a_z))",
        ]
    )

    summary: list[tuple[float, int, int, Any, Any]] = []
    groups = 0
    for bag, got in per_bag:
        tid_name = bag.name  # trial_0003
        im: ImuArrays | None = got.get("raw")
        if im is not None and len(im):
            t = rel(im.stamp_ns)
            sigs = [
                Signal(
                    im.accel[:, i],
                    t,
                    name=f"{tid_name}.raw.accel_{a}",
                    unit=ACCEL,
                    comment=f"imu/data_raw linear_acceleration.{a}: IMU frame '{im.frame_id}', gravity included",
                )
                for i, a in enumerate("xyz")
            ] + [
                Signal(
                    im.gyro[:, i],
                    t,
                    name=f"{tid_name}.raw.gyro_{a}",
                    unit=RATE,
                    comment=f"imu/data_raw angular_velocity.{a}: IMU frame '{im.frame_id}'",
                )
                for i, a in enumerate("xyz")
            ]
            if im.has_recv:
                sigs.append(
                    Signal(
                        im.recv_ns.astype(np.int64),
                        t,
                        name=f"{tid_name}.raw.recv_ns",
                        unit="ns",
                        comment="imu/data_raw: bag (receive) time of each sample, ns since the epoch",
                    )
                )
            mdf.append(sigs, comment=f"{tid_name}: raw IMU (imu/data_raw)")
            groups += 1
        veh: ImuArrays | None = got.get("vehicle")
        if veh is not None and len(veh):
            t = rel(veh.stamp_ns)
            mdf.append(
                [
                    Signal(
                        veh.accel[:, 2],
                        t,
                        name=f"{tid_name}.vehicle.accel_z",
                        unit=ACCEL,
                        comment="imu/vehicle: vertical acceleration of the body, gravity removed, vehicle frame z up",
                    ),
                    Signal(
                        veh.gyro[:, 1],
                        t,
                        name=f"{tid_name}.vehicle.pitch_rate",
                        unit=RATE,
                        comment="imu/vehicle: pitch rate, vehicle frame y left, positive nose down",
                    ),
                ],
                comment=f"{tid_name}: ingested IMU (imu/vehicle, vehicle frame)",
            )
            groups += 1
        od = got.get("odom")
        if od is not None and len(od):
            t = rel(od.stamp_ns)
            mdf.append(
                [
                    Signal(od.distance_m, t, name=f"{tid_name}.odom.distance", unit="m", comment="vehicle/odom pose.x"),
                    Signal(od.speed_mps, t, name=f"{tid_name}.odom.speed", unit="m/s", comment="vehicle/odom twist.x"),
                    Signal(od.speed_mps * 3.6, t, name=f"{tid_name}.odom.speed_kmh", unit="km/h", comment="speed"),
                    Signal(od.series().position_y_m, t, name=f"{tid_name}.odom.position_y", unit="m", comment="pose.y"),
                    Signal(od.series().position_z_m, t, name=f"{tid_name}.odom.position_z", unit="m", comment="pose.z"),
                ],
                comment=f"{tid_name}: odometry (vehicle/odom)",
            )
            groups += 1
        if got.get("trials"):
            mdf.append(
                trial_signals(tid_name, got["trials"], t0),
                comment=f"{tid_name}: the agent's announcements (bac/trial): where each run starts",
            )
            groups += 1
        for (tid, att), r in sorted(got["runs"].items()):
            cal = params.get(tid, {})
            cal_text = ", ".join(f"{k}={v:.6g}{(' ' + units[k]) if units.get(k) else ''}" for k, v in cal.items())
            sc, seg = r.score, r.segment
            summary.append((float(rel(r.window_start_ns)), tid, att, sc, seg))
            if seg is None or len(seg.accel_z) < 2:
                continue
            fs = float(seg.sample_rate_hz)
            n = len(seg.accel_z)
            t = rel(r.window_start_ns) + np.arange(n) / fs
            pre = f"trial_{tid:04d}.a{att}"
            sigs = [
                Signal(
                    np.asarray(seg.accel_z, dtype=np.float64),
                    t,
                    name=f"{pre}.accel_z_aligned",
                    unit=ACCEL,
                    comment="bac/run_segment: a_z cut and aligned with the reference run (what J is computed on)",
                ),
                Signal(
                    np.asarray(seg.pitch_rate, dtype=np.float64),
                    t,
                    name=f"{pre}.pitch_rate_aligned",
                    unit=RATE,
                    comment="bac/run_segment: pitch rate cut and aligned with the reference run",
                ),
            ]
            if int(seg.mode) == 1:  # distance mode: the road position of each sample
                sigs.append(
                    Signal(
                        float(seg.distance_start_m) + np.arange(n) * float(seg.distance_step_m),
                        t,
                        name=f"{pre}.distance_aligned",
                        unit="m",
                        comment="road distance of each aligned sample (time at the target speed)",
                    )
                )
            j = _num(sc.j) if sc is not None else math.nan
            mdf.append(
                sigs,
                comment=(
                    f"trial {tid} attempt {att}: aligned window, {'event' if int(seg.mode) == 0 else 'distance'} mode,"
                    f" {n} samples at {fs:.6g} Hz; J {j:.6g} ({'valid' if seg.valid else 'invalid: ' + seg.reason}); "
                    f"lag {float(seg.lag_s):+.4f} s, alignment {float(seg.alignment_score):.3f}, mean speed "
                    f"{float(seg.mean_speed_mps) * 3.6:.2f} km/h; calibration {cal_text or '-'}"
                ),
            )
            groups += 1

    if summary:
        summary.sort(key=lambda x: x[0])
        t = np.array([s[0] for s in summary])
        # stamps of a group must increase: two runs at one stamp are 1 us apart
        for i in range(1, t.size):
            if t[i] <= t[i - 1]:
                t[i] = t[i - 1] + 1e-6

        def col(f: Any) -> Any:
            return np.array([f(s) for s in summary], dtype=np.float64)

        sigs = [
            Signal(col(lambda s: s[1]).astype(np.uint32), t, name="campaign.trial_id", unit="", comment="trial"),
            Signal(col(lambda s: s[2]).astype(np.uint32), t, name="campaign.attempt", unit="", comment="attempt"),
            Signal(
                col(lambda s: _num(s[3].j) if s[3] is not None else math.nan),
                t,
                name="campaign.J",
                unit="",
                comment="the KPI of the run (paper eq. 1: RMS(a_z) in m/s^2 + RMS(pitch rate) in rad/s); NaN: no J",
            ),
            Signal(
                col(lambda s: _num(s[3].rms_accel_z) if s[3] is not None else math.nan),
                t,
                name="campaign.rms_accel_z",
                unit=ACCEL,
                comment="RMS of the aligned vertical acceleration",
            ),
            Signal(
                col(lambda s: _num(s[3].rms_pitch_rate) if s[3] is not None else math.nan),
                t,
                name="campaign.rms_pitch_rate",
                unit=RATE,
                comment="RMS of the aligned pitch rate",
            ),
            Signal(
                col(lambda s: _num(s[3].weighted_rms_accel_z) if s[3] is not None else math.nan),
                t,
                name="campaign.wk_rms_accel_z",
                unit=ACCEL,
                comment="ISO 2631-1 Wk-weighted RMS of a_z",
            ),
            Signal(
                col(lambda s: float(bool(s[3].valid)) if s[3] is not None else 0.0).astype(np.uint8),
                t,
                name="campaign.valid",
                unit="",
                comment="1: the run was scored; 0: rejected (see the attempt's group comment for the reason)",
            ),
            Signal(
                col(lambda s: float(bool(s[4].valid)) if s[4] is not None else 0.0).astype(np.uint8),
                t,
                name="campaign.segment_valid",
                unit="",
                comment="1: the run's window was cut (bac/run_segment valid); the report shows the last such attempt",
            ),
            Signal(
                col(lambda s: _num(s[4].sample_rate_hz) if s[4] is not None else math.nan),
                t,
                name="campaign.sample_rate_hz",
                unit="Hz",
                comment="sample rate of the run's aligned window (trial_NNNN.aN.*)",
            ),
        ]
        for name in campaign.names:
            sigs.append(
                Signal(
                    col(lambda s, n=name: params.get(s[1], {}).get(n, math.nan)),
                    t,
                    name=f"campaign.{name}",
                    unit=units.get(name, ""),
                    comment=f"calibration value of {name} driven in the run (from the journal)",
                )
            )
        mdf.append(sigs, comment="runs: J and the calibration of every run, at its window's start")
        groups += 1

    skipped = [{"bag": n.split(":", 1)[0], "reason": n} for n in notes if ": skipped (" in n]
    attached = attach_campaign_files(mdf, camp, {"raw": raw, "skipped": skipped})
    path = Path(out) if out is not None else camp / "export" / f"{camp.name}.mf4"
    path.parent.mkdir(parents=True, exist_ok=True)
    mdf.save(path, overwrite=True)
    channels = sum(len(g.channels) - 1 for g in mdf.groups)
    mdf.close()
    return ExportResult(path, channels, groups, len(summary), notes, attached)


def main(argv: Sequence[str] | None = None) -> int:
    ap = argparse.ArgumentParser(
        prog="bac export", description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument("campaign", type=Path, help="campaign folder")
    ap.add_argument("--mf4", action="store_true", help="ASAM MDF 4.10 (the only format, and the default)")
    ap.add_argument("--out", type=Path, help="file to write (default: CAMPAIGN/export/<name>.mf4)")
    ap.add_argument("--no-raw", action="store_true", help="leave out imu/data_raw (a smaller file)")
    args = ap.parse_args(list(sys.argv[1:] if argv is None else argv))
    try:
        res = export_mf4(args.campaign, args.out, raw=not args.no_raw)
    except BacError as exc:
        say(f"bac export: {exc}", err=True)
        return 2
    for n in res.notes:
        say(f"note: {n}")
    how = (
        "bac rescore and bac report read it as the folder" if not res.notes else "bac rescore notes the bags left out"
    ) + ("" if not args.no_raw else "; without the raw IMU, bac rescore --reingest cannot run on it")
    say(
        f"{res.path}: {res.groups} channel groups, {res.channels} channels, {res.runs} runs, {res.files} campaign "
        f"files attached ({how})"
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
