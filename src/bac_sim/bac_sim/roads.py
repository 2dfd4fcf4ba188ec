"""Road profiles: two wheel tracks (left, right) on a uniform distance grid.

Built-in roads (deterministic for a given seed):

* :func:`speed_bump_road`: smooth asphalt with one full-width speed bump at distance 0 (the paper's
  *speed bump*, driven at 30 km/h).
* :func:`test_road`: the paper's 1.5 km *test road* (driven at 60 km/h), sections of rough asphalt
  (ISO 8608 roughness, seeded, left and right tracks partially coherent), asymmetric waves (left !=
  right) and symmetric waves sweeping the ~1 Hz heave and pitch range, with smooth asphalt before
  and after for run-in and run-out.

Roads load from and save to ``.csv`` (columns ``distance_m,left_m,right_m``; ``# key: value`` header
lines for the metadata) or ``.npz``. Every profile is smoothed over the tyre's contact patch
(enveloping): a tyre cannot follow features much shorter than its footprint.
"""

from __future__ import annotations

import json
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from bac_sim.errors import RoadError

FloatArray = np.ndarray[Any, Any]

ISO8608_N0 = 0.1  # reference spatial frequency, cycles/m
# geometric mean of the displacement PSD at n0 (m^3) of the ISO 8608 classes A..E
ISO8608_CLASSES = {"A": 16e-6, "B": 64e-6, "C": 256e-6, "D": 1024e-6, "E": 4096e-6}
CONTACT_PATCH_M = 0.20  # length the tyre envelopes the road over


@dataclass(frozen=True)
class Road:
    """Left and right track heights (m, up) on a uniform grid ``s0 + i * ds``.

    ``meta`` carries what scenarios need: ``kpi_start_m`` / ``kpi_end_m`` (the section scored in
    distance mode), ``event_m`` (a single event such as the bump's leading edge), ``sections`` (a
    list of ``[name, start_m, end_m]``), ``seed``.
    """

    name: str
    s0: float
    ds: float
    left: FloatArray
    right: FloatArray
    meta: Mapping[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        left = np.ascontiguousarray(self.left, dtype=float)
        right = np.ascontiguousarray(self.right, dtype=float)
        if left.ndim != 1 or left.shape != right.shape:
            raise RoadError(f"road '{self.name}': left and right tracks must be 1-D of equal length")
        if left.size < 16:
            raise RoadError(f"road '{self.name}': at least 16 samples needed, got {left.size}")
        if not (np.all(np.isfinite(left)) and np.all(np.isfinite(right))):
            raise RoadError(f"road '{self.name}': heights contain NaN or infinite values")
        if not (np.isfinite(self.ds) and self.ds > 0 and np.isfinite(self.s0)):
            raise RoadError(f"road '{self.name}': grid spacing must be > 0")
        object.__setattr__(self, "left", left)
        object.__setattr__(self, "right", right)
        object.__setattr__(self, "meta", dict(self.meta))

    @property
    def n(self) -> int:
        return int(self.left.size)

    @property
    def s_end(self) -> float:
        return self.s0 + (self.n - 1) * self.ds

    @property
    def distance(self) -> FloatArray:
        return self.s0 + self.ds * np.arange(self.n)

    def heights(self, s: FloatArray) -> tuple[FloatArray, FloatArray]:
        """Left and right heights at distances ``s`` (any shape; linear interpolation, clamped)."""
        z = self.heights_stacked(np.clip(np.asarray(s, dtype=float), self.s0, self.s_end))
        return z[..., 0], z[..., 1]

    def heights_stacked(self, s: FloatArray) -> FloatArray:
        """Heights ``(..., 2)`` (left, right) at distances ``s`` inside the road (not clamped: fast path)."""
        left, right, dleft, dright = self._tables()
        u = np.asarray(s, dtype=float) - self.s0
        u *= 1.0 / self.ds
        i = u.astype(np.intp)
        np.minimum(i, self.n - 2, out=i)
        u -= i
        z = np.empty((*u.shape, 2))
        zl = np.take(left, i)
        zl += u * np.take(dleft, i)
        zr = np.take(right, i)
        zr += u * np.take(dright, i)
        z[..., 0] = zl
        z[..., 1] = zr
        return z

    def _tables(self) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray]:
        cached = self.__dict__.get("_table_cache")
        if cached is None:
            dleft = np.append(np.diff(self.left), 0.0)
            dright = np.append(np.diff(self.right), 0.0)
            cached = (self.left, self.right, dleft, dright)
            object.__setattr__(self, "_table_cache", cached)
        return cached

    def check_covers(self, s_from: float, s_to: float, what: str) -> None:
        if s_from < self.s0 - 1e-9 or s_to > self.s_end + 1e-9:
            raise RoadError(
                f"road '{self.name}' covers [{self.s0:.1f}, {self.s_end:.1f}] m but {what} needs "
                f"[{s_from:.1f}, {s_to:.1f}] m; extend the road or shorten the run-in/run-out"
            )

    # --- files ----------------------------------------------------------------------------
    def save(self, path: str | Path) -> None:
        p = Path(path)
        if p.suffix == ".npz":
            np.savez_compressed(
                p,
                distance=self.distance,
                left=self.left,
                right=self.right,
                meta=np.array(json.dumps({"name": self.name, **self.meta})),
            )
            return
        header = [f"# name: {self.name}"] + [f"# {k}: {json.dumps(v)}" for k, v in self.meta.items()]
        data = np.column_stack([self.distance, self.left, self.right])
        with p.open("w") as fh:
            fh.write("\n".join(header) + "\n")
            fh.write("distance_m,left_m,right_m\n")
            np.savetxt(fh, data, delimiter=",", fmt="%.6f")


def load_road(path: str | Path, envelope: bool = True) -> Road:
    """Load a road from ``.csv`` or ``.npz`` (see the module doc); resampled to a uniform grid."""
    p = Path(path)
    if not p.is_file():
        raise RoadError(f"road file not found: {p}")
    meta: dict[str, Any] = {}
    try:
        if p.suffix == ".npz":
            with np.load(p, allow_pickle=False) as z:
                s = np.asarray(z["distance"], dtype=float)
                left = np.asarray(z["left"], dtype=float)
                right = np.asarray(z["right"], dtype=float)
                if "meta" in z:
                    meta = dict(json.loads(str(z["meta"])))
        else:
            lines = p.read_text().splitlines()
            for line in lines:
                if line.startswith("#") and ":" in line:
                    key, _, value = line[1:].partition(":")
                    try:
                        meta[key.strip()] = json.loads(value.strip())
                    except json.JSONDecodeError:
                        meta[key.strip()] = value.strip()
            rows = [ln for ln in lines if ln.strip() and not ln.startswith("#")]
            if rows and not rows[0][0].isdigit() and rows[0][0] not in "-+.":
                rows = rows[1:]  # column header
            data = np.loadtxt(rows, delimiter=",", ndmin=2)
            if data.shape[1] < 3:
                raise RoadError(f"{p}: expected three columns distance_m,left_m,right_m")
            s, left, right = data[:, 0], data[:, 1], data[:, 2]
    except (KeyError, ValueError) as exc:
        if isinstance(exc, RoadError):
            raise
        raise RoadError(f"{p}: not a road file ({exc})") from exc
    if s.size < 16:
        raise RoadError(f"{p}: at least 16 samples needed, got {s.size}")
    if np.any(np.diff(s) <= 0):
        raise RoadError(f"{p}: distances must be strictly increasing")
    name = str(meta.pop("name", p.stem))
    ds = float(np.median(np.diff(s)))
    grid = np.arange(s[0], s[-1] + ds / 2, ds)
    left_u = np.interp(grid, s, left)
    right_u = np.interp(grid, s, right)
    if envelope:
        left_u, right_u = envelope_tyre(left_u, ds), envelope_tyre(right_u, ds)
    return Road(name, float(grid[0]), ds, left_u, right_u, meta)


# --- generators -----------------------------------------------------------------------------
def envelope_tyre(z: FloatArray, ds: float, patch: float = CONTACT_PATCH_M) -> FloatArray:
    """Moving average over the contact patch (a simple model of the tyre's enveloping)."""
    n = max(1, round(patch / ds))
    if n <= 1:
        return np.asarray(z, dtype=float)
    if n % 2 == 0:
        n += 1
    kernel = np.ones(n) / n
    padded = np.pad(np.asarray(z, dtype=float), n // 2, mode="edge")
    return np.convolve(padded, kernel, mode="valid")


def iso8608_tracks(
    length: float,
    ds: float,
    gd_n0: float,
    rng: np.random.Generator,
    track: float = 1.6,
    waviness: float = 2.0,
    n_min: float = 0.011,
    n_max: float = 20.0,
) -> tuple[FloatArray, FloatArray]:
    """Two random tracks with the ISO 8608 displacement PSD ``Gd(n) = gd_n0 (n / 0.1)^-w``.

    Left and right tracks share their long waves: their coherence is ``1 / (1 + (n track / 0.24)^2)``
    (1 for long waves, ~0.5 at 1/(0.15 m^-1) = 6.7 m with a 1.6 m track, small for short ones).
    Synthesized by inverse FFT with random phases; the mean is removed.
    """
    n = int(np.ceil(length / ds)) + 1
    n_fft = int(2 ** np.ceil(np.log2(n)))
    freqs = np.fft.rfftfreq(n_fft, d=ds)
    dn = freqs[1] - freqs[0]
    band = (freqs >= n_min) & (freqs <= n_max)
    psd = np.zeros_like(freqs)
    psd[band] = gd_n0 * (freqs[band] / ISO8608_N0) ** (-waviness)
    coherence = 1.0 / (1.0 + (freqs * track / 0.24) ** 2)
    amp_c = np.sqrt(2 * psd * dn * (1 + coherence) / 2)
    amp_d = np.sqrt(2 * psd * dn * (1 - coherence) / 2)

    def synth(amp: FloatArray) -> FloatArray:
        phase = rng.uniform(0, 2 * np.pi, size=amp.size)
        spec = amp * np.exp(1j * phase) * n_fft / 2
        return np.fft.irfft(spec, n=n_fft)[:n]

    common = synth(amp_c)
    diff = synth(amp_d)
    left = common + diff
    right = common - diff
    return left - left.mean(), right - right.mean()


def _taper(s: FloatArray, start: float, end: float, ramp: float) -> FloatArray:
    """1 inside [start, end], raised-cosine ramps of length ``ramp`` outside, 0 elsewhere."""
    w = np.zeros_like(s)
    inside = (s >= start) & (s <= end)
    w[inside] = 1.0
    up = (s > start - ramp) & (s < start)
    w[up] = 0.5 - 0.5 * np.cos(np.pi * (s[up] - (start - ramp)) / ramp)
    down = (s > end) & (s < end + ramp)
    w[down] = 0.5 + 0.5 * np.cos(np.pi * (s[down] - end) / ramp)
    return w


TEST_ROAD_SEED = 2021
TEST_ROAD_LENGTH_M = 1500.0


def build_test_road(
    seed: int = TEST_ROAD_SEED, ds: float = 0.05, run_in: float = 250.0, run_out: float = 250.0
) -> Road:
    """The 1.5 km test road of the paper's experiments (sec. IV-B, fig. 11), synthesized.

    Sections (distance from the start of the scored section):

    ===========  ===========  ===============================================================
    0-550 m      rough        ISO 8608 class B asphalt (Gd(n0) = 100e-6 m^3), partially coherent
    550-900 m    asymmetric   waves of 9-15 m on the left, shifted and shorter (6-10 m) on the
                              right, 11-14 mm (roll and pitch), on class A asphalt
    900-1300 m   symmetric    the same waves on both tracks: a sweep of 22 to 9 m (0.75-1.85 Hz
                              at 60 km/h), 16 mm, plus 3.3 m ripples (5 Hz) of 2.5 mm
    1300-1500 m  rough        class B asphalt again
    ===========  ===========  ===============================================================

    Before and after: class A asphalt (run-in, run-out).
    """
    rng = np.random.default_rng(seed)
    s = np.arange(-run_in, TEST_ROAD_LENGTH_M + run_out + ds / 2, ds)
    total = s[-1] - s[0]
    base_l, base_r = iso8608_tracks(total, ds, ISO8608_CLASSES["A"] / 2, rng)
    rough_l, rough_r = iso8608_tracks(total, ds, 100e-6, rng)
    base_l, base_r, rough_l, rough_r = (a[: s.size] for a in (base_l, base_r, rough_l, rough_r))
    w_rough = _taper(s, 0.0, 550.0, 10.0) + _taper(s, 1300.0, 1500.0, 10.0)
    left = base_l + w_rough * rough_l
    right = base_r + w_rough * rough_r
    # asymmetric waves: wavelength drifting 15 -> 9 m on the left, 10 -> 6 m on the right
    w_asym = _taper(s, 560.0, 890.0, 8.0)
    u = np.clip((s - 550.0) / 350.0, 0.0, 1.0)
    lam_l = 15.0 - 6.0 * u
    lam_r = 10.0 - 4.0 * u
    phase_l = 2 * np.pi * np.cumsum(ds / lam_l)
    phase_r = 2 * np.pi * np.cumsum(ds / lam_r) + 1.3
    left += w_asym * 0.014 * np.sin(phase_l)
    right += w_asym * 0.011 * np.sin(phase_r)
    # symmetric waves: sweep 22 -> 9 m plus 5 Hz ripple
    w_sym = _taper(s, 910.0, 1290.0, 8.0)
    v = np.clip((s - 900.0) / 400.0, 0.0, 1.0)
    lam = 22.0 - 13.0 * v
    phase = 2 * np.pi * np.cumsum(ds / lam)
    ripple = 0.0025 * np.sin(2 * np.pi * s / 3.3)
    sym = w_sym * (0.016 * np.sin(phase) + ripple)
    left += sym
    right += sym
    left = envelope_tyre(left, ds)
    right = envelope_tyre(right, ds)
    meta = {
        "kpi_start_m": 0.0,
        "kpi_end_m": TEST_ROAD_LENGTH_M,
        "sections": [
            ["rough", 0.0, 550.0],
            ["asymmetric", 550.0, 900.0],
            ["symmetric", 900.0, 1300.0],
            ["rough", 1300.0, 1500.0],
        ],
        "seed": seed,
    }
    return Road("test_road", float(s[0]), ds, left, right, meta)


BUMP_HEIGHT_M = 0.07
BUMP_LENGTH_M = 2.0


def speed_bump_road(
    seed: int = TEST_ROAD_SEED,
    ds: float = 0.01,
    height: float = BUMP_HEIGHT_M,
    length: float = BUMP_LENGTH_M,
    run_in: float = 60.0,
    run_out: float = 60.0,
) -> Road:
    """Smooth asphalt (ISO 8608 class A, lower half) with one full-width round-top bump at 0 m.

    The bump is a raised cosine, ``height`` high and ``length`` long, the same on both tracks: a
    round-top bump of 70 mm over 2 m, between a short speed bump (50-100 mm over 0.3-0.9 m) and a
    road hump (75 mm over 3.7 m); at 30 km/h it both jolts the car and sets its body oscillating.
    """
    rng = np.random.default_rng(seed + 1)
    s = np.arange(-run_in, run_out + length + ds / 2, ds)
    base_l, base_r = iso8608_tracks(s[-1] - s[0], ds, ISO8608_CLASSES["A"] / 4, rng)
    base_l, base_r = base_l[: s.size], base_r[: s.size]
    on = (s >= 0.0) & (s <= length)
    bump = np.zeros_like(s)
    bump[on] = height * 0.5 * (1 - np.cos(2 * np.pi * s[on] / length))
    left = envelope_tyre(base_l + bump, ds)
    right = envelope_tyre(base_r + bump, ds)
    meta = {"event_m": 0.0, "bump_height_m": height, "bump_length_m": length, "seed": seed}
    return Road("speed_bump", float(s[0]), ds, left, right, meta)
