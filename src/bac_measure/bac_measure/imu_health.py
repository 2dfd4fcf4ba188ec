"""IMU health report of a recording: what the stream looks like and what J it scores.

    python -m bac_measure.imu_health BAG [--topic /imu/data] [--params ros_ws/params/car.yaml]
                                       [-p output_rate_hz=50] [--start S --end S] [--plot out.png] [--json]

Reads an IMU topic from any bag (rosbag2 mcap/sqlite3, ROS 1), runs it through
the same ingestion core as the ``imu_ingest`` node (configuration from the
node's parameter YAML plus ``-p`` overrides), prints the stream's health
(rate, jitter, gaps, NaN/inf, duplicated or out-of-order stamps, saturation,
clock jumps, the mount found), and scores the whole ingested stream (or
``--start``/``--end`` seconds from its first sample) with the ``kpi_scorer``
configuration. Exit code 0 when the report could be made, 2 on a bad bag or
configuration.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from dataclasses import asdict
from pathlib import Path
from typing import Any

import numpy as np

from bac_common.console import say
from bac_common.errors import BacError
from bac_imu.ingest import NS, IngestOutput, StreamHealth, diagnose, ingest_all
from bac_measure.bagio import ImuArrays, read_imu
from bac_measure.kpi import Score, score
from bac_measure.measure_config import ingest_config, kpi_config
from bac_measure.segmentation import ImuSeries, window_segment

LEVELS = {0: "OK", 1: "WARN", 2: "ERROR", 3: "STALE"}


def _value(text: str) -> Any:
    for cast in (int, float):
        try:
            return cast(text)
        except ValueError:
            pass
    return text


def analyse(
    raw: ImuArrays,
    params_files: list[str],
    overrides: dict[str, Any],
    start_s: float | None = None,
    end_s: float | None = None,
) -> tuple[IngestOutput, StreamHealth, Score]:
    """Ingest a recorded IMU stream and score it (whole stream or a window in seconds from its start)."""
    icfg = ingest_config(params_files, overrides)
    out, health = ingest_all(raw.stamp_ns, raw.accel, raw.gyro, icfg, raw.recv_ns)
    if len(out) < 2:
        raise BacError("the ingested stream holds fewer than two samples: nothing to score")
    series = ImuSeries(out.stamp_ns, out.accel_z, out.pitch_rate)
    t0 = int(out.stamp_ns[0])
    seg = window_segment(
        series,
        None if start_s is None else t0 + round(start_s * NS),
        None if end_s is None else t0 + round(end_s * NS),
        imu_rate_hz=icfg.output_rate_hz,
    )
    return out, health, score(seg, kpi_config(params_files, overrides))


def report_text(raw: ImuArrays, health: StreamHealth, sc: Score) -> str:
    d = diagnose(health)
    lines = [
        f"IMU topic {raw.topic} (frame {raw.frame_id or '-'}): {len(raw)} messages",
        f"health: {LEVELS[d.level]} - {d.message}",
        "  " + health.summary().replace("; ", "\n  "),
    ]
    if health.events:
        lines.append(f"faults ({len(health.events)} most recent):")
        for e in health.events[-20:]:
            lines.append(f"  {e.kind:<13} at {e.start_ns / NS:.3f} s, {e.duration_s:.3f} s: {e.detail}")
    if sc.valid:
        lines.append(
            f"J ({sc.kpi}) = {sc.j:.6f}: RMS a_z {sc.rms_accel_z:.5f} m/s^2, RMS pitch rate {sc.rms_pitch_rate:.5f} "
            f"rad/s, Wk RMS a_z {sc.weighted_rms_accel_z:.5f} m/s^2, VDV {sc.vdv_accel_z:.4f} m/s^1.75"
        )
    else:
        lines.append(f"no J: {sc.reason}")
    return "\n".join(lines)


def plot(raw: ImuArrays, out: IngestOutput, health: StreamHealth, sc: Score, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(2, 2, figsize=(12, 7))
    t_raw = (raw.stamp_ns - raw.stamp_ns[0]) / NS
    t_out = (out.stamp_ns - raw.stamp_ns[0]) / NS
    ax[0, 0].plot(t_raw, raw.accel[:, 2], lw=0.6, color="0.6", label="raw z (sensor frame, gravity in)")
    ax[0, 0].plot(t_out, out.accel_z + health.gravity_mps2, lw=0.8, label="vehicle z + g (ingested)")
    ax[0, 0].set(xlabel="time, s", ylabel="m/s^2", title="vertical acceleration")
    ax[0, 0].legend(fontsize=8)
    ax[1, 0].plot(t_raw, raw.gyro[:, 1], lw=0.6, color="0.6", label="raw y")
    ax[1, 0].plot(t_out, out.pitch_rate, lw=0.8, label="pitch rate (ingested)")
    ax[1, 0].set(xlabel="time, s", ylabel="rad/s", title="pitch rate")
    ax[1, 0].legend(fontsize=8)
    steps = np.diff(raw.stamp_ns) / 1e6
    ax[0, 1].hist(steps[np.isfinite(steps)], bins=60, color="tab:gray")
    ax[0, 1].set(
        xlabel="stamp step, ms",
        ylabel="count",
        title=f"rate {health.rate_hz:.2f} Hz, jitter {health.jitter_ms:.3f} ms, {health.gaps} gap(s)",
    )
    ax[0, 1].set_yscale("log")
    if sc.psd_frequency_hz.size:
        ax[1, 1].semilogy(sc.psd_frequency_hz, sc.psd_accel_z, label="a_z, (m/s^2)^2/Hz")
        ax[1, 1].semilogy(sc.psd_frequency_hz, sc.psd_pitch_rate, label="pitch rate, (rad/s)^2/Hz")
        ax[1, 1].legend(fontsize=8)
    ax[1, 1].set(xlabel="frequency, Hz", title=f"Welch spectra, J = {sc.j:.4f}" if sc.valid else "no J")
    fig.suptitle(f"{raw.topic}: {health.samples_in} samples over {health.span_s:.1f} s")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m bac_measure.imu_health", description=__doc__.split("\n\n")[0])
    ap.add_argument("bag", help="rosbag2 folder, .mcap/.db3 file or ROS 1 .bag")
    ap.add_argument("--topic", default=None, help="sensor_msgs/Imu topic (default: the bag's only one)")
    ap.add_argument("--params", action="append", default=[], help="parameter YAML (repeatable), as the nodes read")
    ap.add_argument("-p", dest="overrides", action="append", default=[], metavar="NAME=VALUE", help="override")
    ap.add_argument("--start", type=float, default=None, help="score from this many s after the first sample")
    ap.add_argument("--end", type=float, default=None, help="score up to this many s after the first sample")
    ap.add_argument("--plot", type=Path, default=None, help="save a PNG of the stream, step histogram and spectra")
    ap.add_argument("--json", action="store_true", help="print the health and the score as JSON")
    args = ap.parse_args(argv)
    overrides = {}
    for item in args.overrides:
        if "=" not in item:
            ap.error(f"-p takes NAME=VALUE, got {item!r}")
        k, v = item.split("=", 1)
        overrides[k.strip()] = _value(v.strip())
    try:
        raw = read_imu(args.bag, args.topic)
        out, health, sc = analyse(raw, args.params, overrides, args.start, args.end)
    except BacError as exc:
        say(f"error: {exc}", err=True)
        return 2
    if args.json:
        h = asdict(health)
        s = {k: v for k, v in asdict(sc).items() if not k.startswith("psd_")}
        say(
            json.dumps(
                {"health": h, "score": s},
                default=lambda o: None if isinstance(o, float) and math.isnan(o) else str(o),
                indent=1,
            )
        )
    else:
        say(report_text(raw, health, sc))
    if args.plot is not None:
        plot(raw, out, health, sc, args.plot)
        if not args.json:
            say(f"plot: {args.plot}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
