"""IMU health report of a recording: what the stream looks like and what J it scores.

    python -m bac_measure.imu_health RECORDING [--topic /imu/data] [--channel-map MAP.yaml] [--channel ROLE=NAME]
                                       [--params ros_ws/params/car.yaml] [-p output_rate_hz=50]
                                       [--start S --end S] [--plot out.png] [--json]

Reads an IMU from any bag (rosbag2 mcap/sqlite3, ROS 1; ``--topic``) or MDF file (MDF4 / MDF 3 from INCA,
CANape, a data logger; channels by ``--channel-map`` / ``--channel``, else guessed from units and names), runs
it through the same ingestion core as the ``imu_ingest`` node (configuration from the node's parameter YAML
plus ``-p`` overrides, values parsed as YAML and checked against the parameters of imu_ingest, run_segmenter
and kpi_scorer) and reports the health over the **whole** recording (expected, received and lost samples,
rate, jitter, arrival jitter, gaps, NaN/inf, duplicated or out-of-order stamps, saturation and clipping,
clock jumps, the mount and where it came from, the mean a_z left after gravity removal), then scores the
whole ingested stream (or ``--start``/``--end`` seconds from its first sample) with the ``kpi_scorer``
configuration, ``min_coverage`` from run_segmenter's. Mount and bias come from a standstill unless
configured (``bac_measure.offline``); without one the mount's roll and pitch come from the mean
accelerometer and the report says so. When gravity is left in a_z (a mount that is wrong) there is no J:
the report names the likely cause. Exit code 0 when the report could be made, 2 on a bad recording or
configuration.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from collections.abc import Mapping
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np

from bac_common.console import say
from bac_common.errors import BacError
from bac_imu.ingest import NS, Clipping, IngestConfig, IngestOutput, StreamHealth, diagnose, ingest_all
from bac_measure.bagio import ImuArrays
from bac_measure.kpi import Score, score
from bac_measure.measure_config import (
    NODE_IMU_INGEST,
    NODE_KPI_SCORER,
    NODE_RUN_SEGMENTER,
    ParamsFileError,
    check_overrides,
    config_params,
    ingest_config,
    known_params,
    kpi_config,
    load_node_params,
    parse_value,
    segment_config,
)
from bac_measure.offline import OFFLINE_DEFAULTS, fit_rates, whole_recording
from bac_measure.segmentation import ImuSeries, window_segment

LEVELS = {0: "OK", 1: "WARN", 2: "ERROR", 3: "STALE"}
NODES = (NODE_IMU_INGEST, NODE_RUN_SEGMENTER, NODE_KPI_SCORER)


@dataclass
class Report:
    """Everything the health report says about one recording."""

    raw: ImuArrays
    out: IngestOutput
    health: StreamHealth
    score: Score
    config: IngestConfig
    clipping: list[Clipping] = field(default_factory=list)
    notes: list[str] = field(default_factory=list)
    what: str = ""  # where the IMU came from (topic, MDF channels)


def split_overrides(overrides: Mapping[str, Any]) -> dict[str, dict[str, Any]]:
    """Flat ``-p`` overrides to the node each belongs to; a name no node has is an error naming close ones."""
    out: dict[str, dict[str, Any]] = {n: {} for n in NODES}
    for k, v in overrides.items():
        owners = [n for n in NODES if k in config_params(n)] or [n for n in NODES if k in known_params(n)]
        if not owners:
            import difflib

            every = sorted({p for n in NODES for p in config_params(n)})
            close = difflib.get_close_matches(k, every, n=3)
            hint = f"; did you mean {' or '.join(close)}?" if close else ""
            raise ParamsFileError(
                f"unknown parameter {k!r}{hint} (-p takes parameters of imu_ingest, run_segmenter and kpi_scorer: "
                f"{', '.join(every)})"
            )
        out[owners[0]][k] = v
    return out


def analyse_report(
    raw: ImuArrays,
    params_files: list[str],
    overrides: Mapping[str, Any],
    start_s: float | None = None,
    end_s: float | None = None,
) -> Report:
    """Ingest a recorded IMU stream and score it (whole stream or a window in seconds from its start)."""
    by_node = split_overrides(overrides)
    notes: list[str] = []
    for node in NODES:
        notes += check_overrides(node, by_node[node])
    files_ingest = load_node_params(params_files, NODE_IMU_INGEST)
    user_ingest = by_node[NODE_IMU_INGEST]
    defaults = {k: v for k, v in OFFLINE_DEFAULTS.items() if k not in files_ingest}
    icfg = ingest_config(params_files, {**defaults, **user_ingest})
    scfg = segment_config(params_files, by_node[NODE_RUN_SEGMENTER])
    kcfg = kpi_config(params_files, by_node[NODE_KPI_SCORER])
    icfg, _ = fit_rates(raw, icfg, None, user_ingest, {}, notes)
    icfg, clips = whole_recording(raw, icfg, user_ingest, notes)
    out, health = ingest_all(raw.stamp_ns, raw.accel, raw.gyro, icfg, raw.recv_or_none)
    if len(out) < 2:
        raise BacError(
            f"the ingested stream holds {len(out)} sample(s): nothing to score ({len(raw)} raw samples; "
            "a recording of a second or more is needed)"
        )
    series = ImuSeries(out.stamp_ns, out.accel_z, out.pitch_rate)
    t0 = int(out.stamp_ns[0])
    seg = window_segment(
        series,
        None if start_s is None else t0 + round(start_s * NS),
        None if end_s is None else t0 + round(end_s * NS),
        imu_rate_hz=icfg.output_rate_hz,
        min_coverage=scfg.min_coverage,
    )
    if seg.valid and seg.coverage < 1.0:
        notes.append(
            f"{(1.0 - seg.coverage) * seg.window_length_s:.2f} s of holes in the window bridged by linear "
            f"interpolation (coverage {seg.coverage:.3f}, min_coverage {scfg.min_coverage:g})"
        )
    sc = score(seg, kcfg)
    problem = health.gravity_problem()
    if problem and sc.valid:
        sc = replace(sc, j=math.nan, valid=False, reason=problem)
    return Report(raw, out, health, sc, icfg, clips, notes)


def analyse(
    raw: ImuArrays,
    params_files: list[str],
    overrides: Mapping[str, Any],
    start_s: float | None = None,
    end_s: float | None = None,
) -> tuple[IngestOutput, StreamHealth, Score]:
    """:func:`analyse_report`'s output, health and score."""
    r = analyse_report(raw, params_files, overrides, start_s, end_s)
    return r.out, r.health, r.score


def report_text(raw: ImuArrays, health: StreamHealth, sc: Score, notes: list[str] | None = None, what: str = "") -> str:
    d = diagnose(health)
    lines = [
        f"{what or f'IMU topic {raw.topic}'} (frame {raw.frame_id or '-'}): {len(raw)} messages",
        f"health: {LEVELS[d.level]} - {d.message}",
        "  " + health.summary().replace("; ", "\n  "),
    ]
    if health.bias_source.startswith("long-run mean"):
        lines.append(
            "  no standstill in the recording: gravity and the gyro bias from the long-run mean (the drive's own "
            "mean accelerations are in them; record a standstill of a few seconds to measure them at rest)"
        )
    elif health.bias_source != "standstill":
        lines.append(
            "  no standstill bias: "
            + (
                "no standstill found in the recording; "
                if "no standstill" in health.bias_source
                else "bias_source is none; "
            )
            + "nominal gravity removed and no gyro bias: an accelerometer offset stays in a_z and in RMS(a_z)"
        )
    if health.events:
        lines.append(f"faults ({len(health.events)} most recent):")
        for e in health.events[-20:]:
            lines.append(f"  {e.kind:<13} at {e.start_ns / NS:.3f} s, {e.duration_s:.3f} s: {e.detail}")
    lines += [f"note: {n}" for n in notes or []]
    if sc.valid:
        lines.append(
            f"J ({sc.kpi}) = {sc.j:.6f}: RMS a_z {sc.rms_accel_z:.5f} m/s^2, RMS pitch rate {sc.rms_pitch_rate:.5f} "
            f"rad/s, Wk RMS a_z {sc.weighted_rms_accel_z:.5f} m/s^2, VDV {sc.vdv_accel_z:.4f} m/s^1.75"
        )
    else:
        lines.append(f"no J: {sc.reason}")
    return "\n".join(lines)


def jsonable(x: Any) -> Any:
    """``x`` with every NaN/inf float as None and tuples as lists: what :func:`json.dumps` writes as valid JSON."""
    if isinstance(x, float):
        return x if math.isfinite(x) else None
    if isinstance(x, np.floating):
        return jsonable(float(x))
    if isinstance(x, np.integer):
        return int(x)
    if isinstance(x, np.ndarray):
        return [jsonable(v) for v in x.tolist()]
    if isinstance(x, Mapping):
        return {str(k): jsonable(v) for k, v in x.items()}
    if isinstance(x, list | tuple):
        return [jsonable(v) for v in x]
    if isinstance(x, str | int | bool) or x is None:
        return x
    return str(x)


def report_json(r: Report) -> dict[str, Any]:
    h = asdict(r.health)
    h.update(
        samples_expected=r.health.samples_expected,
        loss_pct=r.health.loss_pct,
        gravity_problem=r.health.gravity_problem() or None,
        level=LEVELS[diagnose(r.health).level],
        message=diagnose(r.health).message,
    )
    s = {k: v for k, v in asdict(r.score).items() if not k.startswith("psd_")}
    out: dict[str, Any] = jsonable(
        {
            "source": r.what or r.raw.topic,
            "health": h,
            "clipping": [asdict(c) for c in r.clipping],
            "notes": r.notes,
            "config": asdict(r.config),
            "score": s,
        }
    )
    return out


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
    ap.add_argument("bag", help="rosbag2 folder, .mcap/.db3 file, ROS 1 .bag, or MDF file (.mf4, .mdf, .dat)")
    ap.add_argument("--topic", default=None, help="sensor_msgs/Imu topic of a bag (default: the bag's only one)")
    ap.add_argument("--channel-map", type=Path, default=None, help="MDF: YAML mapping roles to channels")
    ap.add_argument(
        "--channel", action="append", default=[], metavar="ROLE=NAME", help="MDF: map one role (repeatable)"
    )
    ap.add_argument("--params", action="append", default=[], help="parameter YAML (repeatable), as the nodes read")
    ap.add_argument("-p", dest="overrides", action="append", default=[], metavar="NAME=VALUE", help="override")
    ap.add_argument("--start", type=float, default=None, help="score from this many s after the first sample")
    ap.add_argument("--end", type=float, default=None, help="score up to this many s after the first sample")
    ap.add_argument("--plot", type=Path, default=None, help="save a PNG of the stream, step histogram and spectra")
    ap.add_argument("--json", action="store_true", help="print the health and the score as JSON")
    args = ap.parse_args(argv)
    try:
        overrides = {}
        for item in args.overrides:
            if "=" not in item:
                raise ParamsFileError(f"-p takes NAME=VALUE, got {item!r}")
            k, v = item.split("=", 1)
            overrides[k.strip()] = parse_value(v.strip())
        from bac_measure.mdfio import ChannelMap
        from bac_measure.sources import read_source

        bag = Path(args.bag)
        if bag.is_dir() and (bag / "journal.jsonl").is_file():
            trials = sorted(p.name for p in (bag / "bags").glob("trial_*")) if (bag / "bags").is_dir() else []
            raise ParamsFileError(
                f"{bag} is a campaign folder: give one of its bags, e.g. {bag / 'bags' / trials[0]}"
                if trials
                else f"{bag} is a campaign folder without bags/: no IMU recording in it"
            )
        src = read_source(args.bag, args.topic, channels=ChannelMap.load(args.channel_map, args.channel))
        r = analyse_report(src.imu, args.params, overrides, args.start, args.end)
        r.notes[:0] = src.notes
        r.what = src.what
    except BacError as exc:
        say(f"error: {exc}", err=True)
        return 2
    if args.json:
        say(json.dumps(report_json(r), indent=1, allow_nan=False))
    else:
        say(report_text(r.raw, r.health, r.score, r.notes, r.what))
    if args.plot is not None:
        plot(r.raw, r.out, r.health, r.score, args.plot)
        if not args.json:
            say(f"plot: {args.plot}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
