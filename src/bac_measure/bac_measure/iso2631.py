"""ISO 2631-1:1997 frequency weighting Wk (vertical, seated) and the vibration dose value.

The weighting is the standard's analog filter (Annex A), band limiting
included:

* band limiting: 2nd-order Butterworth high-pass at f1 = 0.4 Hz and low-pass
  at f2 = 100 Hz (Q = 1/sqrt(2));
* acceleration-velocity transition: f3 = f4 = 12.5 Hz, Q4 = 0.63;
* upward step: f5 = 2.37 Hz, Q5 = 0.91, f6 = 3.35 Hz, Q6 = 0.91.

It is applied in the frequency domain with the analog response itself
(:func:`wk_response`), so the gain is exact at every sampling rate: a
bilinear IIR at 200 Hz misses the standard's table by 0.65 % at 12.5 Hz
because of frequency warping. The signal is zero-padded by
``PAD_S`` seconds so that the circular convolution equals the linear one
(the filter starts from rest at the first sample, like a causal filter); a
``pre_roll`` of the signal before the window (the segmenter keeps ``pre_roll_s``
of it) lets the window be weighted as part of the recording, not from rest.
"""

from __future__ import annotations

import math

import numpy as np
import numpy.typing as npt

FloatArray = npt.NDArray[np.float64]

# (f, Q) of ISO 2631-1:1997 table A.2, weighting Wk
WK_F1, WK_F2 = 0.4, 100.0
WK_F3, WK_F4, WK_Q4 = 12.5, 12.5, 0.63
WK_F5, WK_Q5, WK_F6, WK_Q6 = 2.37, 0.91, 3.35, 0.91
PAD_S = 20.0  # zero padding for the FFT filter: >> the impulse response of the 0.4 Hz high-pass

# ISO 2631-1 table 3: Wk factors (x 1000) at one-third-octave centre frequencies, Hz -> factor
WK_TABLE = {
    0.5: 0.418,
    1.0: 0.482,
    2.0: 0.531,
    4.0: 0.967,
    6.3: 1.054,
    8.0: 1.036,
    10.0: 0.988,
    12.5: 0.902,
    16.0: 0.768,
    31.5: 0.405,
    80.0: 0.132,
}


def wk_response(frequency_hz: npt.ArrayLike) -> npt.NDArray[np.complex128]:
    """Complex frequency response of Wk (band limiting included) at ``frequency_hz``."""
    f = np.asarray(frequency_hz, dtype=np.float64)
    s = 2j * np.pi * f
    w1, w2, w3, w4, w5, w6 = (2 * math.pi * x for x in (WK_F1, WK_F2, WK_F3, WK_F4, WK_F5, WK_F6))
    q12 = 1 / math.sqrt(2)
    high = s**2 / (s**2 + w1 * s / q12 + w1**2)
    low = w2**2 / (s**2 + w2 * s / q12 + w2**2)
    transition = (1 + s / w3) / (1 + s / (WK_Q4 * w4) + s**2 / w4**2)
    step = (1 + s / (WK_Q5 * w5) + s**2 / w5**2) / (1 + s / (WK_Q6 * w6) + s**2 / w6**2) * (w5 / w6) ** 2
    return np.asarray(high * low * transition * step, dtype=np.complex128)


def wk_filter(x: npt.ArrayLike, fs: float, pre_roll: npt.ArrayLike | None = None) -> FloatArray:
    """The Wk-weighted signal of ``x`` sampled at ``fs`` Hz.

    ``pre_roll``: the signal just before ``x`` (same rate): the filter runs through it first and the part over
    ``x`` is returned, so ``x`` is weighted as the middle of a recording, not from rest (the 0.4 Hz band limit
    rings for ~4 s). Without it the filter starts from rest at the first sample of ``x``.
    """
    a = np.asarray(x, dtype=np.float64)
    n = a.shape[0]
    if n == 0:
        return a.copy()
    pre = np.zeros(0) if pre_roll is None else np.asarray(pre_roll, dtype=np.float64).reshape(-1)
    if pre.size:
        a = np.concatenate([pre, a])
    m = a.shape[0]
    nfft = 1 << math.ceil(math.log2(m + PAD_S * fs))
    spectrum = np.fft.rfft(a, nfft)
    h = wk_response(np.fft.rfftfreq(nfft, 1.0 / fs))
    return np.asarray(np.fft.irfft(spectrum * h, nfft)[pre.size : m], dtype=np.float64)


def weighted_rms(x: npt.ArrayLike, fs: float) -> float:
    """ISO 2631-1 Wk frequency-weighted RMS acceleration, m/s^2."""
    aw = wk_filter(x, fs)
    return float(np.sqrt(np.mean(aw * aw))) if aw.size else math.nan


def vibration_dose_value(weighted: npt.ArrayLike, fs: float) -> float:
    """VDV = (integral of a_w^4 dt)^(1/4), m/s^1.75, of an already weighted signal."""
    aw = np.asarray(weighted, dtype=np.float64)
    return float(np.sum(aw**4) / fs) ** 0.25 if aw.size else math.nan
