"""Synthetic runs for the measurement-chain tests and the benchmark (no simulator needed).

A run is what the segmenter buffers: the ``imu/vehicle`` stream (vertical
acceleration, pitch rate, fixed rate) and ``vehicle/odom`` (distance since the
run started, speed). The vehicle is two decoupled damped modes driven by the
road under the front and rear axles:

* heave: a_z = s^2 (2 zeta w s + w^2) / (s^2 + 2 zeta w s + w^2) applied to the mean axle input;
* pitch: q = s (2 zeta w s + w^2) / (s^2 + 2 zeta w s + w^2) applied to (u_rear - u_front) / wheelbase

(a seat-rail IMU sees something like it). The road is a speed bump (a half-cosine) or a
random ISO 8608-like profile that is the same for every run of a ``road_seed``. Each run
starts at a road position ``offset_m`` (the driver never stops at the same point) and drives
at ``speed_mps`` (cruise control with its error): runs must be cut and aligned.
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from scipy import signal

from bac_measure.bagio import ImuArrays
from bac_measure.segmentation import ImuSeries, OdomSeries

NS = 1_000_000_000
T_START = 1_700_000_000 * NS  # the trial became ready to drive here
WHEELBASE = 2.8
FINE_HZ = 2000.0  # the vehicle is simulated at this rate, then sampled by the IMU


@dataclass
class SynthRun:
    imu: ImuSeries
    odom: OdomSeries
    start_ns: int  # the trial became ready to drive
    offset_m: float  # road position where the odometry reads 0
    speed_mps: float
    event_ns: int  # bump runs: when the front axle reached the bump start


def _mode(x: np.ndarray, f_hz: float, zeta: float, derivatives: int) -> np.ndarray:
    """Displacement transmissibility of a damped mode, differentiated ``derivatives`` times.

    The transmissibility is proper (bilinear, at the fine rate); the derivatives are taken numerically after it:
    the bilinear transform of the improper s^2 H(s) put a pole at Nyquist, whose ringing aliased into a constant
    offset of tens of m/s^2 once sampled at the IMU's rate."""
    w = 2 * np.pi * f_hz
    b, a = signal.bilinear([2 * zeta * w, w * w], [1.0, 2 * zeta * w, w * w], fs=FINE_HZ)
    y = np.asarray(signal.lfilter(b, a, x), dtype=np.float64)
    for _ in range(derivatives):
        y = np.gradient(y, 1.0 / FINE_HZ)
    return y


def bump_profile(x: np.ndarray, at_m: float, height: float = 0.06, length: float = 2.0) -> np.ndarray:
    u = np.clip((x - at_m) / length, 0.0, 1.0)
    return height * 0.5 * (1 - np.cos(2 * np.pi * u))


def random_road(x: np.ndarray, seed: int, roughness: float = 3e-5) -> np.ndarray:
    """ISO 8608-like profile: G(n) = roughness * (n / 0.1)^-2, n in 0.02..8 cycles/m (sum of sinusoids)."""
    grid = _road_table(seed, roughness, float(np.floor(x.min())) - 1.0, float(np.ceil(x.max())) + 1.0)
    return np.asarray(np.interp(x, grid[0], grid[1]), dtype=np.float64)


@functools.lru_cache(maxsize=16)
def _road_table(seed: int, roughness: float, lo: float, hi: float) -> tuple[np.ndarray, np.ndarray]:
    x = np.arange(lo, hi, 0.01)  # 1 cm: far finer than the shortest wavelength (12.5 cm)
    rng = np.random.default_rng(seed)
    n = np.geomspace(0.02, 8.0, 300)
    dn = np.gradient(n)
    amp = np.sqrt(2 * roughness * (n / 0.1) ** -2 * dn)
    phase = rng.uniform(0, 2 * np.pi, n.size)
    out = np.zeros_like(x)
    for k in range(0, n.size, 50):  # blocks: bounded memory
        b = slice(k, k + 50)
        out += np.sum(amp[b, None] * np.cos(2 * np.pi * n[b, None] * x[None, :] + phase[b, None]), axis=0)
    return x, out


def _run(
    road: Callable[[np.ndarray], np.ndarray],
    duration_s: float,
    speed_mps: float,
    offset_m: float,
    zeta: float,
    noise: float,
    fs: float,
    seed: int,
    lead_s: float,
    imu_phase_s: float,
    odom_hz: float,
    t0_ns: int,
) -> tuple[ImuSeries, OdomSeries]:
    rng = np.random.default_rng(seed)
    t_fine = np.arange(-lead_s, duration_s, 1 / FINE_HZ)
    x_front = offset_m + speed_mps * np.maximum(t_fine, 0.0)  # standing until the start, then cruising
    u_f = road(x_front)
    u_r = road(x_front - WHEELBASE)
    az = _mode((u_f + u_r) / 2, 1.2, zeta, 2) + 0.02 * _mode((u_f + u_r) / 2, 9.0, 0.15, 2)
    q = _mode((u_r - u_f) / WHEELBASE, 1.6, zeta, 1)
    t_imu = np.arange(-lead_s + imu_phase_s, duration_s - 0.01, 1 / fs)
    az_i = np.interp(t_imu, t_fine, az) + noise * rng.standard_normal(t_imu.size)
    q_i = np.interp(t_imu, t_fine, q) + 0.1 * noise * rng.standard_normal(t_imu.size)
    imu = ImuSeries(t0_ns + np.round(t_imu * NS).astype(np.int64), az_i, q_i)
    t_odom = np.arange(0.0, duration_s, 1 / odom_hz)
    dist = speed_mps * t_odom
    odom = OdomSeries(t0_ns + np.round(t_odom * NS).astype(np.int64), dist, np.full(t_odom.size, speed_mps))
    return imu, odom


def bump_run(
    speed_mps: float = 30 / 3.6,
    offset_m: float = 0.0,
    zeta: float = 0.3,
    noise: float = 0.02,
    fs: float = 200.0,
    seed: int = 0,
    bump_at_m: float = 25.0,
    duration_s: float = 7.0,
    imu_phase_s: float = 0.0,
    lead_s: float = 0.5,
    t0_ns: int = T_START,
) -> SynthRun:
    """A run over a speed bump at road position ``bump_at_m``; the trial became ready at ``t0_ns``."""
    imu, odom = _run(
        lambda x: bump_profile(x, bump_at_m),
        duration_s,
        speed_mps,
        offset_m,
        zeta,
        noise,
        fs,
        seed,
        lead_s,
        imu_phase_s,
        50.0,
        t0_ns,
    )
    event_ns = t0_ns + round((bump_at_m - offset_m) / speed_mps * NS)
    return SynthRun(imu, odom, t0_ns, offset_m, speed_mps, event_ns)


def road_run(
    speed_mps: float = 60 / 3.6,
    offset_m: float = 0.0,
    zeta: float = 0.3,
    noise: float = 0.05,
    fs: float = 200.0,
    seed: int = 0,
    road_seed: int = 42,
    length_m: float = 260.0,
    imu_phase_s: float = 0.0,
    lead_s: float = 0.5,
    roughness: float = 3e-5,
    t0_ns: int = T_START,
) -> SynthRun:
    """A run over ``length_m`` of a random road (the same road for the same ``road_seed``)."""
    imu, odom = _run(
        lambda x: random_road(x, road_seed, roughness),
        length_m / speed_mps,
        speed_mps,
        offset_m,
        zeta,
        noise,
        fs,
        seed,
        lead_s,
        imu_phase_s,
        50.0,
        t0_ns,
    )
    return SynthRun(imu, odom, t0_ns, offset_m, speed_mps, 0)


# --- raw IMU recordings shaped like real ones (issue 21) -------------------------------------------------------


@dataclass
class ImuRecording:
    """A raw IMU recording (sensor frame, gravity in, the sensor's offsets and noise) and its truth."""

    raw: ImuArrays
    accel_z: np.ndarray  # truth at the raw stamps: vehicle-frame vertical acceleration without gravity, m/s^2
    pitch_rate: np.ndarray  # truth: vehicle-frame pitch rate, rad/s
    mount_rpy_deg: tuple[float, float, float]
    lost: int  # samples dropped inside the stream (single losses and gaps)

    @property
    def j_true(self) -> float:
        """J (paper eq. 1) of the truth over the recording: RMS(a_z) + RMS(pitch rate)."""
        return float(np.sqrt(np.mean(self.accel_z**2)) + np.sqrt(np.mean(self.pitch_rate**2)))


def imu_recording(
    duration_s: float = 60.0,
    fs: float = 250.0,
    mount_rpy_deg: tuple[float, float, float] = (0.0, 0.0, 0.0),
    standstill_s: float = 0.0,
    accel_bias: tuple[float, float, float] = (0.05, -0.08, 0.3),
    gyro_bias: tuple[float, float, float] = (0.004, -0.006, 0.002),
    noise: float = 0.02,
    seed: int = 0,
    gaps: tuple[tuple[float, float], ...] = (),
    single_losses: int = 0,
    bumps_mps2: float = 0.0,
    clip_mps2: float = 0.0,
    jitter_s: float = 0.0,
    t0_ns: int = T_START,
) -> ImuRecording:
    """A raw IMU recording of a car on a rough road: heave at 1.3 and 9 Hz, pitch at 1.6 Hz, longitudinal and
    lateral accelerations that average out over the drive, after ``standstill_s`` at rest.

    ``mount_rpy_deg``: the sensor's mount (sensor = R.T @ vehicle, R = rotation_matrix(roll, pitch, yaw)):
    (90, 0, 0) has the sensor's y axis up, (180, 0, 0) is upside down. ``gaps``: (start_s, length_s) without
    samples; ``single_losses``: isolated samples dropped at random; ``bumps_mps2``: the peak of a few impacts
    (every 10 s); ``clip_mps2``: the accelerometer's full scale (values clipped there, e.g. 2 g = 19.6133).
    """
    from bac_imu.ingest import GRAVITY, rotation_matrix

    rng = np.random.default_rng(seed)
    n = round(duration_s * fs)
    t = np.arange(n) / fs
    moving = np.clip((t - standstill_s) / 2.0, 0.0, 1.0)  # rolls off smoothly after the standstill
    az = moving * (0.6 * np.sin(2 * np.pi * 1.3 * t + 0.4) + 0.15 * np.sin(2 * np.pi * 9.0 * t + 1.1))
    if bumps_mps2:
        for c in np.arange(standstill_s + 5.0, duration_s - 1.0, 10.0):
            az += bumps_mps2 * np.exp(-(((t - c) / 0.04) ** 2)) * np.cos(2 * np.pi * 7.0 * (t - c))
    q = moving * 0.06 * np.sin(2 * np.pi * 1.6 * t + 0.9)
    ax = moving * 0.8 * np.sin(2 * np.pi * t / 20.0)  # accelerate, brake: no net speed over 20 s
    ay = moving * 0.5 * np.sin(2 * np.pi * t / 14.0 + 0.3)  # curves left and right
    wz = moving * 0.1 * np.sin(2 * np.pi * t / 14.0 + 0.3)
    vehicle_acc = np.column_stack([ax, ay, az + GRAVITY])
    vehicle_gyr = np.column_stack([0.02 * moving * np.sin(2 * np.pi * 0.9 * t), q, wz])
    R = rotation_matrix(*mount_rpy_deg)
    acc = vehicle_acc @ R + np.asarray(accel_bias) + noise * rng.standard_normal((n, 3))
    gyr = vehicle_gyr @ R + np.asarray(gyro_bias) + 0.1 * noise * rng.standard_normal((n, 3))
    if clip_mps2:
        acc = np.clip(acc, -clip_mps2, clip_mps2)
    stamps = t0_ns + np.round(t * NS).astype(np.int64)
    if jitter_s:
        stamps += np.round(rng.normal(0.0, jitter_s, n) * NS).astype(np.int64)
        stamps = np.maximum.accumulate(stamps)
    keep = np.ones(n, bool)
    for start, length in gaps:
        keep &= ~((t >= start) & (t < start + length))
    if single_losses:
        inner = np.flatnonzero(keep[1:-1]) + 1
        drop = rng.choice(inner, size=single_losses, replace=False)
        drop = drop[keep[drop - 1] & keep[drop + 1]]  # isolated: both neighbours kept
        keep[drop] = False
    recv = stamps + 200_000 + rng.integers(0, 2_000_000, n)  # the bag's receive times: 0.2-2.2 ms later
    raw = ImuArrays("imu/data_raw", "imu_link", stamps[keep], recv[keep], acc[keep], gyr[keep])
    return ImuRecording(raw, az[keep], q[keep], mount_rpy_deg, int(n - np.count_nonzero(keep)))
