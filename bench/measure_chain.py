"""How long the measurement chain takes for one 90 s run at 500 Hz (issue 4).

A run of the 1.5 km test road at 60 km/h (90 s between the section's ends)
from the simulated vehicle (``bac_sim.run``; a synthetic random road when
bac_sim is not installed), its IMU at 500 Hz, is written to an mcap bag.
Measured in the same process, median of ``--repeat`` repetitions:

* ``read_bag``: reading the IMU and odometry back from the bag into arrays
  (``bac_measure.bagio``, vectorized CDR), beside the baseline of deserializing
  each message with rosbags;
* ``read_mdf``: reading the same run from an MDF4 file (IMU channels in one group,
  speed and distance in another: ``bac_measure.mdfio`` through asammdf; its import,
  ~0.4 s once per process, is timed apart);
* ``ingest``: the raw stream to the vehicle-frame stream at 500 Hz (``bac_imu.ingest``);
* ``segment``: cut and align the run against a reference run (distance grid, +-20 m
  cross-correlation search, cubic re-sampling; ``bac_measure.segmentation.cut_run``);
* ``score``: J, Wk-weighted RMS, VDV and Welch spectra (``bac_measure.kpi.score``).

Ratios are against the bag read measured in the same run and against the run's
own 90 s. LAST line: ``segment_and_score_s <x>`` (goal: x <= 0.3).

    .venv/bin/python bench/measure_chain.py [--repeat 7] [--keep-bag DIR]
"""

from __future__ import annotations

import argparse
import statistics
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from bac_imu.ingest import GRAVITY, IngestConfig, ingest_all
from bac_measure.bagio import ImuArrays, OdomArrays, read_run, write_bag
from bac_measure.kpi import KpiConfig, score
from bac_measure.mdfio import ROLES, ChannelMap, read_mdf, write_mdf
from bac_measure.segmentation import ImuSeries, OdomSeries, Reference, SegmentConfig, cut_run

NS = 1_000_000_000
T0 = 1_700_000_000 * NS
RATE = 500.0
SEGMENT = SegmentConfig(
    mode="distance", target_speed_mps=60 / 3.6, distance_start_m=100.0, distance_end_m=1600.0, max_shift_m=20.0
)


def simulated_run(seed: int) -> tuple[ImuArrays, OdomArrays, str]:
    """A raw road run: bac_sim's when available, else a synthetic one."""
    try:
        from bac_sim.run import ImuSpec, simulate_run
    except ImportError:
        return (*synthetic_run(seed), "synthetic random road")
    rec = simulate_run(
        {"damping_front": 0.5, "damping_rear": 0.5},
        "road",
        seed=seed,
        imu=ImuSpec(rate_hz=RATE, mount_rpy_deg=(0, 0, 0)),
    )
    t = T0 + np.round(rec.t * NS).astype(np.int64)
    to = T0 + np.round(rec.odom_t * NS).astype(np.int64)
    return (
        ImuArrays("imu/data_raw", "imu_link", t, t, rec.accel, rec.gyro),
        OdomArrays("vehicle/odom", "odom", to, to, rec.distance, rec.speed),
        "bac_sim test road",
    )


def synthetic_run(seed: int) -> tuple[ImuArrays, OdomArrays]:
    from scipy import signal

    rng = np.random.default_rng(seed)
    v = 60 / 3.6
    offset = rng.normal(0, 5)
    n = round(100 * RATE)
    t_s = np.arange(n) / RATE
    x = offset + v * t_s
    road_rng = np.random.default_rng(42)
    k = np.geomspace(0.02, 8, 200)
    amp = np.sqrt(2 * 3e-5 * (k / 0.1) ** -2 * np.gradient(k))
    ph = road_rng.uniform(0, 2 * np.pi, k.size)
    z = np.zeros(n)
    for i in range(0, k.size, 25):
        z += np.sum(amp[i : i + 25, None] * np.cos(2 * np.pi * k[i : i + 25, None] * x + ph[i : i + 25, None]), axis=0)
    b, a = signal.bilinear([2 * 0.3 * 7.5, 7.5**2, 0, 0], [1, 2 * 0.3 * 7.5, 7.5**2], fs=RATE)
    az = signal.lfilter(b, a, z) + 0.05 * rng.standard_normal(n)
    acc = np.column_stack([0.05 * rng.standard_normal(n), 0.05 * rng.standard_normal(n), GRAVITY + az])
    gyr = np.column_stack(
        [0.01 * rng.standard_normal(n), np.gradient(signal.lfilter(b, a, z), t_s) * 0.01, np.zeros(n)]
    )
    t = T0 + np.round(t_s * NS).astype(np.int64)
    to = t[:: round(RATE / 100)]
    return (
        ImuArrays("imu/data_raw", "imu_link", t, t, acc, gyr),
        OdomArrays("vehicle/odom", "odom", to, to, v * (to - T0) / NS, np.full(to.size, v)),
    )


def timed(fn: Callable[[], Any], repeat: int) -> tuple[float, Any]:
    times, out = [], None
    for _ in range(repeat):
        t = time.perf_counter()
        out = fn()
        times.append(time.perf_counter() - t)
    return statistics.median(times), out


def chain_input(imu: ImuArrays, odom: OdomArrays) -> tuple[ImuSeries, OdomSeries]:
    out, _ = ingest_all(imu.stamp_ns, imu.accel, imu.gyro, IngestConfig(output_rate_hz=RATE))
    return ImuSeries(out.stamp_ns, out.accel_z, out.pitch_rate), OdomSeries(
        odom.stamp_ns, odom.distance_m, odom.speed_mps
    )


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--repeat", type=int, default=7)
    ap.add_argument("--keep-bag", type=Path, default=None, help="write the bag here and keep it")
    args = ap.parse_args(argv)

    t = time.perf_counter()
    raw, odom, source = simulated_run(seed=1)
    ref_raw, ref_odom, _ = simulated_run(seed=2)
    print(
        f"run: {source}, {len(raw)} IMU samples at {RATE:g} Hz over {(raw.stamp_ns[-1] - raw.stamp_ns[0]) / NS:.1f} s, "
        f"{len(odom)} odometry samples (made in {time.perf_counter() - t:.1f} s)"
    )

    with tempfile.TemporaryDirectory() as tmp:
        bag = write_bag((args.keep_bag or Path(tmp)) / "run", raw, odom)
        read_s, (imu_b, odom_b) = timed(lambda: read_run(bag), args.repeat)
        base_s, _ = timed(lambda: _deserialize_all(bag), max(1, args.repeat // 3))
        t = time.perf_counter()
        import asammdf  # noqa: F401  (what the first MDF read of a process pays)

        import_s = time.perf_counter() - t
        mf4 = write_mdf((args.keep_bag or Path(tmp)) / "run.mf4", raw, odom)
        roles = ChannelMap.parse({r: r for r in ROLES})  # write_mdf names each channel by its role
        mdf_s, rec = timed(lambda: read_mdf(mf4, roles), args.repeat)
    assert np.array_equal(imu_b.accel, raw.accel) and np.array_equal(odom_b.distance_m, odom.distance_m)
    assert np.array_equal(rec.imu.accel, raw.accel) and np.array_equal(rec.imu.stamp_ns, raw.stamp_ns)

    ingest_s, (imu, od) = timed(lambda: chain_input(imu_b, odom_b), args.repeat)
    ref_imu, ref_od = chain_input(ref_raw, ref_odom)
    ref_seg = cut_run(ref_imu, ref_od, SEGMENT, T0)
    assert ref_seg.valid, ref_seg.reason
    ref = Reference.from_segment(ref_seg, SEGMENT)
    kcfg = KpiConfig()
    seg_s, seg = timed(lambda: cut_run(imu, od, SEGMENT, T0, ref), args.repeat)
    score_s, sc = timed(lambda: score(seg, kcfg), args.repeat)
    both_s, sc2 = timed(lambda: score(cut_run(imu, od, SEGMENT, T0, ref), kcfg), args.repeat)
    assert seg.valid and sc.valid and sc2.j == sc.j, seg.reason

    shift = seg.lag_s * SEGMENT.target_speed_mps
    print(
        f"segment: {len(seg)} samples on a {seg.distance_step_m * 100:.2f} cm grid, shift {shift:+.2f} m, "
        f"alignment {seg.alignment_score:.3f}; J = {sc.j:.5f}"
    )
    rows = [
        ("read bag, per-message deserialize (baseline)", base_s),
        ("read bag, vectorized (bagio)", read_s),
        ("read MDF4, same run (mdfio, asammdf)", mdf_s),
        ("ingest 500 Hz", ingest_s),
        ("segment (cut + align)", seg_s),
        ("score (J, Wk, VDV, Welch)", score_s),
        ("segment + score", both_s),
    ]
    for name, s in rows:
        print(f"  {name:<46} {s * 1e3:9.1f} ms   x{s / read_s:6.2f} of the bag read   {90.0 / s:8.0f}x real time")
    print(f"vectorized bag read vs per-message: x{base_s / read_s:.1f} faster")
    print(f"MDF4 read vs bag read: x{read_s / mdf_s:.1f} faster (import asammdf once per process: {import_s:.2f} s)")
    print(f"segment_and_score_s {both_s:.4f}")
    return 0


def _deserialize_all(bag: Path) -> int:
    from rosbags.highlevel import AnyReader

    from bac_measure.recording import bac_typestore

    n = 0
    with AnyReader([bag], default_typestore=bac_typestore()) as r:
        for c, _, raw in r.messages():
            r.deserialize(raw, c.msgtype)
            n += 1
    return n


if __name__ == "__main__":
    sys.exit(main())
