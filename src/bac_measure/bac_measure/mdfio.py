"""ASAM MDF recordings (MDF4 ``.mf4``, MDF 3 ``.mdf`` / ``.dat``: INCA, CANape, data loggers) into the arrays of a bag.

An MDF file holds named channels in channel groups, each group on its own time base (an IMU at 400 Hz beside
a CAN speed at 100 Hz), each channel with its unit and the conversion from raw to physical values. bac needs
six IMU channels (the accelerometer and gyro axes of the sensor frame) and, to cut runs, a speed and/or a
distance channel. A **channel map** names them::

    # imu_channels.yaml: bac role -> channel name (its unit and conversion come from the file)
    accel_x: IMU_AccX
    accel_y: IMU_AccY
    accel_z: IMU_AccZ
    gyro_x: IMU_GyrX
    gyro_y: IMU_GyrY
    gyro_z: {name: IMU_GyrZ, group: 2}       # several channels of that name: the group index
    speed: VehSpd                            # optional; km/h, m/s, mph
    distance: {name: Odo, unit: km}          # optional; a unit for a channel whose file has none

or ``ROLE=NAME`` pairs on the command line (``--channel accel_x=IMU_AccX``). Without a map the channels are
guessed from their units and names (an acceleration unit and a name ending in x/y/z, ...) and the guess is
said; when it is ambiguous the error lists the file's channels with their units and a map to fill in.

Values are the file's physical values (asammdf applies each channel's conversion), then converted to SI
from the channel's unit (g, mg, m/s^2; deg/s, rad/s; km/h, m/s, mph; km, m). Stamps are the file's start
time plus each sample's time, in integer nanoseconds. IMU axes on other time bases than ``accel_z`` are
interpolated onto its time base (said in the notes). Without a distance channel the distance is the
integral of the speed (trapezoid). Invalid samples (MDF invalidation bits) become NaN: the ingestion counts
them as bad samples.

asammdf is imported only here and only when an MDF file is read (it takes ~0.4 s to import).
"""

from __future__ import annotations

import gc
import math
import re
import sys
import threading
import traceback
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

from bac_common.errors import BacError
from bac_measure.bagio import ImuArrays, OdomArrays

FloatArray = npt.NDArray[np.float64]
IntArray = npt.NDArray[np.int64]

MDF_MAGIC = (b"MDF     ", b"UnFinMF ")  # the first 8 bytes of an MDF file (finalized / not finalized)
MDF_SUFFIXES = (".mf4", ".mdf", ".dat", ".mf3")
IMU_ROLES = ("accel_x", "accel_y", "accel_z", "gyro_x", "gyro_y", "gyro_z")
ODOM_ROLES = ("speed", "distance")
ROLES = IMU_ROLES + ODOM_ROLES
ROLE_KEYS = ("name", "group", "unit", "gain")


class MdfError(BacError, OSError):
    """An MDF file that cannot be read, or that lacks the channels the map names."""


def _unit_key(unit: str) -> str:
    u = unit.strip().lower().replace(" ", "").replace("²", "^2").replace("**", "^").replace("sec", "s")
    return u.replace("°", "deg").replace("grad", "deg")


# unit (normalized by _unit_key) -> factor to SI, per quantity
UNITS: dict[str, dict[str, float]] = {
    "acceleration": {
        "m/s^2": 1.0,
        "m/s2": 1.0,
        "ms^-2": 1.0,
        "m*s^-2": 1.0,
        "mps2": 1.0,
        "g": 9.80665,
        "mg": 9.80665e-3,
    },
    "angular rate": {
        "rad/s": 1.0,
        "mrad/s": 1e-3,
        "deg/s": math.pi / 180.0,
        "dps": math.pi / 180.0,
        "degps": math.pi / 180.0,
        "rpm": 2 * math.pi / 60.0,
    },
    "speed": {"m/s": 1.0, "mps": 1.0, "km/h": 1 / 3.6, "kph": 1 / 3.6, "kmh": 1 / 3.6, "mph": 0.44704},
    "distance": {"m": 1.0, "km": 1000.0, "mm": 1e-3, "mi": 1609.344},
}
QUANTITY = {
    **dict.fromkeys(("accel_x", "accel_y", "accel_z"), "acceleration"),
    **dict.fromkeys(("gyro_x", "gyro_y", "gyro_z"), "angular rate"),
    "speed": "speed",
    "distance": "distance",
}


def si_factor(role: str, unit: str) -> float:
    """The factor taking values in ``unit`` to SI for ``role``; raises MdfError for a unit that is not one."""
    q = QUANTITY[role]
    f = UNITS[q].get(_unit_key(unit))
    if f is None:
        known = ", ".join(sorted(UNITS[q]))
        raise MdfError(
            f"{role}: unit {unit!r} is not a unit of {q} bac knows ({known}); "
            f"give the unit in the channel map ({role}: {{name: ..., unit: ...}})"
            if unit
            else f"{role}: the channel has no unit in the file; give it in the channel map "
            f"({role}: {{name: ..., unit: ...}}; one of {known})"
        )
    return f


@dataclass(frozen=True)
class ChannelRef:
    """Where a role's values come from: a channel (and its group when the name is not unique), a unit that
    replaces the file's, a gain (e.g. -1 for an axis the logger records with the other sign)."""

    name: str
    group: int | None = None
    unit: str | None = None
    gain: float = 1.0


@dataclass(frozen=True)
class ChannelMap:
    roles: Mapping[str, ChannelRef]

    @classmethod
    def parse(cls, spec: Mapping[str, Any], where: str = "channel map") -> ChannelMap:
        roles: dict[str, ChannelRef] = {}
        for role, v in spec.items():
            if role not in ROLES:
                raise MdfError(f"{where}: unknown role {role!r}; the roles are {', '.join(ROLES)}")
            if v is None or v == "":
                continue
            if isinstance(v, str):
                roles[role] = ChannelRef(v)
            elif isinstance(v, Mapping):
                bad = set(v) - set(ROLE_KEYS)
                if bad or "name" not in v:
                    raise MdfError(
                        f"{where}: {role}: give {{name: CHANNEL[, group: N][, unit: U][, gain: G]}}"
                        + (f" (unknown key(s) {', '.join(sorted(map(str, bad)))})" if bad else "")
                    )
                group = v.get("group")
                try:
                    gain = float(v.get("gain", 1.0))
                except (TypeError, ValueError):
                    gain = math.nan
                if not (math.isfinite(gain) and gain != 0.0):
                    raise MdfError(
                        f"{where}: {role}: gain {v.get('gain')!r} must be a finite, non-zero number (e.g. -1 for an "
                        "axis recorded with the other sign)"
                    )
                roles[role] = ChannelRef(
                    str(v["name"]),
                    None if group is None else int(group),
                    None if v.get("unit") is None else str(v["unit"]),
                    gain,
                )
            else:
                raise MdfError(f"{where}: {role}: expected a channel name or a mapping, got {v!r}")
        return cls(roles)

    @classmethod
    def load(cls, path: str | Path | None = None, pairs: Sequence[str] = ()) -> ChannelMap | None:
        """A map from a YAML file and/or ``ROLE=NAME`` pairs (the pairs win); None when neither is given."""
        spec: dict[str, Any] = {}
        if path is not None:
            import yaml

            p = Path(path)
            try:
                data = yaml.safe_load(p.read_text())
            except FileNotFoundError as exc:
                raise MdfError(f"channel map not found: {p}") from exc
            except yaml.YAMLError as exc:
                raise MdfError(f"{p}: not valid YAML: {exc}") from exc
            if not isinstance(data, Mapping):
                raise MdfError(f"{p}: expected a mapping ROLE: CHANNEL (roles: {', '.join(ROLES)})")
            spec.update(data)
        for item in pairs:
            if "=" not in item:
                raise MdfError(f"--channel takes ROLE=CHANNEL, got {item!r}")
            k, v = item.split("=", 1)
            spec[k.strip()] = v.strip()
        if path is None and not pairs:
            return None
        return cls.parse(spec, str(path) if path is not None else "--channel")


@dataclass(frozen=True)
class ChannelInfo:
    name: str
    group: int
    unit: str
    samples: int
    rate_hz: float
    comment: str = ""


@dataclass
class MdfRecording:
    """What was read: the IMU (and odometry when mapped) as bag arrays, the map used, notes."""

    path: Path
    imu: ImuArrays
    odom: OdomArrays | None
    mapping: dict[str, ChannelRef]
    notes: list[str] = field(default_factory=list)


def is_mdf(path: str | Path) -> bool:
    """True for an MDF file (by its first bytes, whatever its name)."""
    p = Path(path)
    if not p.is_file():
        return False
    with p.open("rb") as f:
        return f.read(8) in MDF_MAGIC


def asammdf() -> Any:
    """The asammdf module, imported on first use (~0.4 s), its helpers' start-up chatter (numexpr's thread
    count on the root logger) kept out of the tools' output."""
    import logging

    logging.getLogger("numexpr").setLevel(logging.WARNING)
    logging.getLogger("numexpr.utils").setLevel(logging.WARNING)
    import asammdf as module

    return module


def open_mdf(path: Path) -> Any:
    MDF = asammdf().MDF

    if not path.exists():
        raise MdfError(f"no such MDF file: {path}")
    if path.stat().st_size == 0:
        raise MdfError(f"{path} is empty (0 bytes): the recording was never written; record it again")
    if not is_mdf(path):
        raise MdfError(f"{path} is not an MDF file (it does not start with 'MDF     '): give an .mf4 / .mdf / .dat")
    try:
        return MDF(path)
    except Exception as exc:
        _drop_half_built(exc)
        raise MdfError(
            f"cannot read MDF file {path}: {exc or type(exc).__name__}; the file is truncated or corrupt (a logger "
            "that lost power?): open it in the logger's tool (CANape, INCA, asammdf GUI) to repair it"
        ) from exc


_HOOK_LOCK = threading.Lock()


def _drop_half_built(exc: BaseException) -> None:
    """Free the reader asammdf left half-built when it refused a file, now and quietly.

    Its ``MDF4.__del__`` calls ``close()``, which fails on an object whose ``__init__`` did not finish
    (``AttributeError: ... '_file'``); Python prints that as "Exception ignored in MDF4.__del__" with a traceback,
    after bac's own message, whenever the object is freed. The object lives in the frames of the exception's
    traceback: dropping the traceback frees it here, where that one report is left out (any other goes to the
    previous hook). Where asammdf failed is kept as text, a note on the exception, shown with bac's error wherever
    a traceback is printed (a caller's ``logger.exception``, a test's report): a bug report on a file asammdf
    refuses can still say where."""
    if exc.__traceback__ is not None:  # the whole chain, as Python would print it: asammdf may fail in a cause
        exc.add_note(
            "where asammdf refused it (its frames were freed):\n" + "".join(traceback.format_exception(exc)).rstrip()
        )
    with _HOOK_LOCK:  # two threads refusing files at once: each restores what it found, in order
        previous = sys.unraisablehook

        def hook(unraisable: Any) -> None:
            obj = getattr(unraisable, "object", None)
            if not (isinstance(unraisable.exc_value, AttributeError) and "MDF4.__del__" in repr(obj)):
                previous(unraisable)

        sys.unraisablehook = hook
        try:
            cause: BaseException | None = exc
            seen: set[int] = set()
            while cause is not None and id(cause) not in seen:  # the whole chain: any frame may hold the reader
                seen.add(id(cause))
                cause.__traceback__ = None
                cause = cause.__context__
            gc.collect()
        finally:
            sys.unraisablehook = previous


def mdf_start_ns(mdf: Any) -> int:
    """An open MDF file's start time (its header's, UTC when it names no zone) in ns since the epoch."""
    st: datetime = mdf.header.start_time
    if st.tzinfo is None:
        st = st.replace(tzinfo=UTC)
    td = st - datetime(1970, 1, 1, tzinfo=UTC)
    return int(td.days * 86_400 + td.seconds) * 1_000_000_000 + td.microseconds * 1_000


def list_channels(mdf: Any) -> list[ChannelInfo]:
    """Every data channel (not the time channels) with its group, unit, sample count and rate."""
    out: list[ChannelInfo] = []
    for gi, grp in enumerate(mdf.groups):
        n = int(getattr(grp.channel_group, "cycles_nr", 0) or 0)
        rate = math.nan
        master = None
        for ci, ch in enumerate(grp.channels):
            if getattr(ch, "channel_type", None) == 2 or (ch.name in ("time", "t") and ci == 0):  # the master
                master = ci
        if n > 1 and master is not None:
            try:
                t = mdf.get_master(gi)
                if t.size > 1 and t[-1] > t[0]:
                    rate = (t.size - 1) / float(t[-1] - t[0])
            except Exception:
                pass
        for ci, ch in enumerate(grp.channels):
            if ci == master:
                continue
            out.append(ChannelInfo(ch.name, gi, str(getattr(ch, "unit", "") or ""), n, rate, str(ch.comment or "")))
    return out


def _channel_table(channels: Sequence[ChannelInfo]) -> str:
    lines = [
        f"  {c.name!r:<28} group {c.group:<3} unit {c.unit or '-':<8} {c.samples} samples"
        + (f" at {c.rate_hz:.1f} Hz" if math.isfinite(c.rate_hz) else "")
        for c in channels
    ]
    return "\n".join(lines[:60]) + ("\n  ..." if len(lines) > 60 else "")


def _axis(name: str) -> str | None:
    m = re.search(r"([xyzXYZ])(?:[_\s.\-]?(?:raw|imu|sensor|axis))?$", name)
    if m is None:
        return None
    return m.group(1).lower()


def guess_map(channels: Sequence[ChannelInfo]) -> tuple[ChannelMap | None, str]:
    """A map from the channels' units and names: three acceleration and three angular-rate channels whose names
    end in x/y/z, one speed channel, one distance channel named like a distance. (None, why) when not unique."""
    by_q: dict[str, list[ChannelInfo]] = {q: [] for q in UNITS}
    for c in channels:
        for q, table in UNITS.items():
            if c.unit and _unit_key(c.unit) in table:
                by_q[q].append(c)
    roles: dict[str, ChannelRef] = {}
    why = []
    for prefix, q in (("accel", "acceleration"), ("gyro", "angular rate")):
        axes: dict[str, list[ChannelInfo]] = {}
        for c in by_q[q]:
            a = _axis(c.name)
            if a:
                axes.setdefault(a, []).append(c)
        for a in "xyz":
            cands = axes.get(a, [])
            if len(cands) != 1:
                why.append(f"{len(cands)} {q} channels for axis {a}")
                continue
            roles[f"{prefix}_{a}"] = ChannelRef(cands[0].name, cands[0].group)
    if why:
        return None, "; ".join(why)
    speeds = by_q["speed"]
    if len(speeds) == 1:
        roles["speed"] = ChannelRef(speeds[0].name, speeds[0].group)
    dists = [c for c in by_q["distance"] if re.search(r"dist|odo|weg|strecke", c.name, re.I)]
    if len(dists) == 1:
        roles["distance"] = ChannelRef(dists[0].name, dists[0].group)
    return ChannelMap(roles), ""


def _template() -> str:
    return "\n".join(f"  {r}: <channel>" for r in ROLES) + "\n"


def _get(mdf: Any, role: str, ref: ChannelRef, channels: Sequence[ChannelInfo], path: Path) -> tuple[Any, float]:
    """(asammdf Signal, factor to SI) of a role."""
    matches = [c for c in channels if c.name == ref.name and (ref.group is None or c.group == ref.group)]
    if not matches:
        similar = [c.name for c in channels if ref.name.lower() in c.name.lower() or c.name.lower() in ref.name.lower()]
        hint = f" (similar: {', '.join(repr(s) for s in similar[:5])})" if similar else ""
        raise MdfError(
            f"{path} has no channel {ref.name!r}{'' if ref.group is None else f' in group {ref.group}'} "
            f"(mapped to {role}){hint}; its channels:\n{_channel_table(channels)}\n"
            "fix the channel map (--channel-map FILE or --channel ROLE=NAME)"
        )
    if len(matches) > 1:
        groups = ", ".join(str(c.group) for c in matches)
        raise MdfError(
            f"{path}: channel {ref.name!r} (mapped to {role}) is in several groups ({groups}): "
            f"give the group in the channel map ({role}: {{name: {ref.name}, group: N}})"
        )
    c = matches[0]
    try:
        sig = mdf.get(c.name, group=c.group)
    except Exception as exc:
        raise MdfError(f"{path}: channel {c.name!r} (group {c.group}) cannot be read: {exc}") from exc
    if sig.samples.dtype.kind not in "fiub":
        raise MdfError(
            f"{path}: channel {c.name!r} (mapped to {role}) holds {sig.samples.dtype} values (text, a structure), "
            "not numbers"
        )
    unit = ref.unit if ref.unit is not None else str(sig.unit or c.unit or "")
    try:
        factor = si_factor(role, unit)
    except MdfError as exc:
        raise MdfError(f"{path}: channel {c.name!r}: {exc}") from exc
    return sig, factor * ref.gain


def _values(sig: Any, factor: float) -> FloatArray:
    v = np.asarray(sig.samples, dtype=np.float64) * factor
    inv = getattr(sig, "invalidation_bits", None)
    if inv is not None:
        mask = np.asarray(inv, dtype=bool)
        if mask.shape == v.shape and mask.any():
            v = v.copy()
            v[mask] = np.nan
    return np.asarray(v, dtype=np.float64)


def _stamps(start_ns: int, t: Any) -> IntArray:
    return start_ns + np.round(np.asarray(t, dtype=np.float64) * 1e9).astype(np.int64)


def read_mdf(
    path: str | Path,
    mapping: ChannelMap | None = None,
    need_odom: bool = False,
) -> MdfRecording:
    """The IMU (and the odometry, when a speed or distance channel is mapped or found) of an MDF file."""
    p = Path(path)
    mdf = open_mdf(p)
    try:
        channels = list_channels(mdf)
        notes: list[str] = []
        if not channels:
            raise MdfError(f"{p} holds no data channels: nothing was recorded")
        if mapping is None:
            mapping, why = guess_map(channels)
            if mapping is None:
                raise MdfError(
                    f"{p}: which channels are the IMU's cannot be told from their units and names ({why}); "
                    f"its channels:\n{_channel_table(channels)}\n"
                    f"give a channel map (--channel-map FILE with\n{_template()}or --channel ROLE=NAME)"
                )
            used = ", ".join(f"{r}={ref.name}" for r, ref in mapping.roles.items())
            notes.append(f"channels found by unit and name: {used}")
        missing = [r for r in IMU_ROLES if r not in mapping.roles]
        if missing:  # a partial map: the other roles by unit and name
            guessed, _ = guess_map(channels)
            if guessed is not None:
                extra = {r: ref for r, ref in guessed.roles.items() if r not in mapping.roles}
                if extra:
                    mapping = ChannelMap({**extra, **mapping.roles})
                    used = ", ".join(f"{r}={ref.name}" for r, ref in extra.items())
                    notes.append(f"the roles the map does not give found by unit and name: {used}")
            missing = [r for r in IMU_ROLES if r not in mapping.roles]
        if missing:
            raise MdfError(
                f"the channel map lacks {', '.join(missing)}: bac needs the three accelerometer and the three gyro "
                f"axes; {p} has:\n{_channel_table(channels)}"
            )
        start = mdf_start_ns(mdf)
        sigs = {r: _get(mdf, r, ref, channels, p) for r, ref in mapping.roles.items()}
        base_sig = sigs["accel_z"][0]
        t_base = np.asarray(base_sig.timestamps, dtype=np.float64)
        if t_base.size == 0:
            raise MdfError(f"{p}: channel {mapping.roles['accel_z'].name!r} holds no samples")
        cols = []
        resampled = []
        for r in IMU_ROLES:
            sig, f = sigs[r]
            v = _values(sig, f)
            t = np.asarray(sig.timestamps, dtype=np.float64)
            if t.shape != t_base.shape or not np.array_equal(t, t_base):
                if t.size < 2:
                    raise MdfError(f"{p}: channel {mapping.roles[r].name!r} ({r}) holds {t.size} samples")
                v = np.interp(t_base, t, v, left=np.nan, right=np.nan)
                resampled.append(f"{r} ({t.size} samples)")
            cols.append(v)
        if resampled:
            notes.append(
                f"IMU axes on another time base than accel_z, interpolated onto its {t_base.size} samples: "
                + ", ".join(resampled)
            )
        stamps = _stamps(start, t_base)
        data = np.column_stack(cols)
        frame = mapping.roles["accel_z"].name
        imu = ImuArrays(
            topic=f"mdf:{frame}",
            frame_id="",
            stamp_ns=stamps,
            recv_ns=stamps.copy(),
            accel=np.ascontiguousarray(data[:, :3]),
            gyro=np.ascontiguousarray(data[:, 3:]),
            has_recv=False,
        )
        odom = _odom(sigs, start, p, notes)
        if odom is None and need_odom:
            raise MdfError(
                f"{p}: no speed or distance channel is mapped or could be found: cutting runs needs one "
                "(--channel speed=NAME), or score the whole recording (--window whole)"
            )
        return MdfRecording(p, imu, odom, dict(mapping.roles), notes)
    finally:
        mdf.close()


def _odom(sigs: Mapping[str, tuple[Any, float]], start: int, p: Path, notes: list[str]) -> OdomArrays | None:
    if "distance" in sigs:
        dsig, df = sigs["distance"]
        t = np.asarray(dsig.timestamps, dtype=np.float64)
        dist = _values(dsig, df)
        if "speed" in sigs:
            ssig, sf = sigs["speed"]
            ts = np.asarray(ssig.timestamps, dtype=np.float64)
            speed = _values(ssig, sf)
            if not np.array_equal(ts, t):
                speed = np.interp(t, ts, speed)
        else:
            speed = np.gradient(dist, t) if t.size > 1 else np.zeros_like(dist)
            notes.append("speed: the derivative of the distance channel")
    elif "speed" in sigs:
        ssig, sf = sigs["speed"]
        t = np.asarray(ssig.timestamps, dtype=np.float64)
        speed = _values(ssig, sf)
        from scipy.integrate import cumulative_trapezoid

        dist = cumulative_trapezoid(np.nan_to_num(speed), t, initial=0.0) if t.size else np.zeros(0)
        notes.append("distance: the integral of the speed channel (trapezoid), 0 at its first sample")
    else:
        return None
    if t.size == 0:
        raise MdfError(f"{p}: the speed / distance channel holds no samples")
    stamps = _stamps(start, t)
    return OdomArrays(
        topic="mdf:odometry",
        frame_id="",
        stamp_ns=stamps,
        recv_ns=stamps.copy(),
        distance_m=np.asarray(dist, dtype=np.float64),
        speed_mps=np.asarray(speed, dtype=np.float64),
    )


def write_mdf(
    path: str | Path,
    imu: ImuArrays,
    odom: OdomArrays | None = None,
    names: Mapping[str, str] | None = None,
    version: str = "4.10",
) -> Path:
    """Write IMU (and odometry speed) arrays as an MDF file (tests, the benchmark, conversions): the IMU in one
    channel group (m/s^2, rad/s), the speed in another (m/s); ``names`` renames the roles' channels."""
    mod = asammdf()
    MDF, Signal = mod.MDF, mod.Signal
    nm = {r: r for r in ROLES} | dict(names or {})
    t0 = int(imu.stamp_ns[0])
    if odom is not None and len(odom):
        t0 = min(t0, int(odom.stamp_ns[0]))
    t0 -= t0 % 1000  # MDF start times have microsecond resolution
    mdf = MDF(version=version)
    mdf.header.start_time = datetime.fromtimestamp(t0 // 1_000_000_000, UTC).replace(
        microsecond=(t0 % 1_000_000_000) // 1000
    )
    t = (imu.stamp_ns - t0) / 1e9
    sigs = [Signal(imu.accel[:, i], t, name=nm[f"accel_{a}"], unit="m/s^2") for i, a in enumerate("xyz")] + [
        Signal(imu.gyro[:, i], t, name=nm[f"gyro_{a}"], unit="rad/s") for i, a in enumerate("xyz")
    ]
    mdf.append(sigs, comment="IMU")
    if odom is not None and len(odom):
        to = (odom.stamp_ns - t0) / 1e9
        mdf.append(
            [
                Signal(odom.speed_mps, to, name=nm["speed"], unit="m/s"),
                Signal(odom.distance_m, to, name=nm["distance"], unit="m"),
            ],
            comment="odometry",
        )
    p = Path(path)
    mdf.save(p, overwrite=True)
    mdf.close()
    return p
