"""Simulate runs and write them as rosbag2 (mcap), the way a car's recording would look.

::

    python -m bac_campaign.record_run out/bump_run --scenario bump --set damping_front=0.8 --seed 3
    python -m bac_campaign.record_run out/road_c2 --scenario road --definition controller_ii --runs 3

Each run becomes a bag folder (``imu/data_raw`` as sensor_msgs/Imu in the IMU frame, raw;
``vehicle/odom`` as nav_msgs/Odometry) openable by ``ros2 bag`` and Foxglove, with a ``truth.json``
beside the bag's files: the calibration, the seed, the true J of the run and its KPI window (sim
time), for tests of the measurement chain. Unset parameters take the definition's baseline.
"""

from __future__ import annotations

import argparse
import json
import sys
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from bac_common.console import say
from bac_common.errors import BacError
from bac_common.paramspace import CalibrationDefinition
from bac_sim.driver import DriverModel
from bac_sim.run import ImuSpec, RunRecording, simulate_run


def write_run(rec: RunRecording, path: Path, start_time_s: float, storage: str = "mcap") -> Path:
    """Write one recording as a rosbag2 folder at ``path`` (stamps = ``start_time_s`` + run time)."""
    from bac_measure.bagio import ImuArrays, OdomArrays, write_bag

    t0_ns = round(start_time_s * 1e9)
    imu_ns = (t0_ns + np.round(rec.t * 1e9)).astype(np.int64)
    odom_ns = (t0_ns + np.round(rec.odom_t * 1e9)).astype(np.int64)
    imu = ImuArrays("imu/data_raw", "imu_link", imu_ns, imu_ns, rec.accel, rec.gyro)
    odom = OdomArrays("vehicle/odom", "odom", odom_ns, odom_ns, rec.distance, rec.speed)
    write_bag(path, imu, odom, storage=storage)
    truth = {
        "scenario": rec.scenario,
        "calibration": rec.calibration,
        "seed": rec.seed,
        "j_true": rec.j_true,
        "rms_accel_z": rec.rms_accel_z,
        "rms_pitch_rate": rec.rms_pitch_rate,
        "window_start_s": start_time_s + rec.window_start_s,
        "window_end_s": start_time_s + rec.window_end_s,
        "target_speed_mps": rec.target_speed,
        "bad_run": rec.bad_run,
        "imu_rate_hz": rec.imu.rate_hz,
        "imu_lever_arm_m": list(rec.imu.lever_arm),
        "imu_mount_rpy_deg": list(rec.imu.mount_rpy_deg),
    }
    (path / "truth.json").write_text(json.dumps(truth, indent=1) + "\n")
    return path


def main(argv: Sequence[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m bac_campaign.record_run", description=__doc__.splitlines()[0])
    ap.add_argument("output", help="bag folder to create (with --runs N: a folder of N bags run_001 ...)")
    ap.add_argument("--scenario", default="road", help="bump, road or a road file")
    ap.add_argument("--definition", default="controller_i", help="calibration definition (name or YAML path)")
    ap.add_argument("--set", nargs="*", default=[], metavar="NAME=VALUE", help="raw parameter values")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--runs", type=int, default=1, help="runs to record (seeds seed, seed+1, ...)")
    ap.add_argument("--imu-rate", type=float, default=400.0, help="IMU rate, Hz")
    ap.add_argument("--bad-run-probability", type=float, default=0.0)
    ap.add_argument("--start-time", type=float, default=100.0, help="sim time of the first run's start, s")
    ap.add_argument("--storage", default="mcap", choices=["mcap", "sqlite3"])
    args = ap.parse_args(argv)
    try:
        from bac_common.paths import resolve_definition

        definition = CalibrationDefinition.load(resolve_definition(args.definition))
        calibration = definition.baseline_values()
        for item in args.set:
            name, sep, value = item.partition("=")
            if not sep:
                raise BacError(f"--set {item!r}: expected NAME=VALUE")
            definition.parameter(name.strip()).check(float(value))
            calibration[name.strip()] = float(value)
        out = Path(args.output)
        if out.exists():
            raise BacError(f"{out} exists; choose a new folder")
        t = args.start_time
        for i in range(args.runs):
            rec = simulate_run(
                calibration,
                args.scenario,
                seed=args.seed + i,
                definition=definition,
                imu=ImuSpec(rate_hz=args.imu_rate),
                driver=DriverModel(bad_run_probability=args.bad_run_probability),
            )
            path = out if args.runs == 1 else out / f"run_{i + 1:03d}"
            path.parent.mkdir(parents=True, exist_ok=True)
            write_run(rec, path, t, args.storage)
            say(
                f"{path}: {rec.duration:.1f} s, {rec.t.size} IMU samples, true J {rec.j_true:.4f}"
                f"{' (bad run)' if rec.bad_run else ''}"
            )
            t += rec.duration + 30.0
    except (BacError, ValueError) as exc:
        say(f"record_run: {exc}", err=True)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
