"""Spectra for the dashboard: Welch PSD in dB above the noise floor, and the frequencies to mark.

The thesis checks a disturbance estimate by its spectrum (Figure 4.8d): the estimate and the
measured cutting force must show the same peaks at the tooth-passing frequency and its
harmonics, and the residual of the linear model shows where the model leaves periodic power.
Absolute levels differ between a residual in m/s and a force in N, so each spectrum is shown
relative to its own floor:

    P_dB(f) = 10·log10( P(f) / median_f P(f) ),   clipped at 0,

i.e. how far each frequency rises above the typical (median) level of the same signal, the DC
bin left out. A flat, noise-like spectrum sits near 0 dB; a tooth-passing line stands 20–40 dB
above it.

Markers (Hz): ``1/ψ`` from the tracker kernel's period ψ (model file), the spindle rotation
``rpm/60`` and the tooth-passing frequency ``teeth·rpm/60`` with its harmonics below Nyquist
(rpm from the samples' ``spindle_rpm``, teeth from the trial or the caller).
"""

from __future__ import annotations

import math

import numpy as np
from scipy.signal import welch

__all__ = ["psd_above_floor", "marker_frequencies"]

SPECTRUM_MIN_SAMPLES = 32  # fewer finite samples than this: no spectrum


def psd_above_floor(x: np.ndarray, fs: float, nperseg: int = 512) -> tuple[np.ndarray, np.ndarray] | None:
    """Frequencies (Hz, DC left out) and Welch PSD of ``x`` in dB above its median, clipped at 0.

    Non-finite samples are left out. ``None`` when fewer than :data:`SPECTRUM_MIN_SAMPLES` remain, ``fs``
    is not a positive finite rate, or the signal is constant (no floor to refer to).
    """
    x = np.asarray(x, dtype=np.float64)
    x = x[np.isfinite(x)]
    if x.size < SPECTRUM_MIN_SAMPLES or not (math.isfinite(fs) and fs > 0):
        return None
    freq, pxx = welch(x - x.mean(), fs=fs, nperseg=min(int(nperseg), x.size), detrend="constant")
    freq, pxx = freq[1:], pxx[1:]
    floor = float(np.median(pxx))
    if not (floor > 0 and math.isfinite(floor)):
        return None
    return freq, np.maximum(10.0 * np.log10(np.maximum(pxx, 1e-300) / floor), 0.0)


def marker_frequencies(fs: float, period: float | None = None, spindle_rpm: float | None = None,
                       teeth: int | None = None) -> dict[str, np.ndarray]:
    """Marker frequencies (Hz) below Nyquist ``fs/2``, by label.

    ``"1_over_psi"``: 1/ψ (``period`` in s); ``"tooth_passing"``: k·teeth·rpm/60, k = 1 … 8;
    ``"spindle"``: rpm/60 when the number of teeth is unknown. Unknown or absurd inputs
    (non-finite, ≤ 0) give no marker.
    """
    nyq = 0.5 * fs if math.isfinite(fs) and fs > 0 else 0.0
    out: dict[str, np.ndarray] = {}

    def ok(v) -> bool:
        return v is not None and math.isfinite(v) and v > 0

    if ok(period) and 1.0 / period < nyq:
        out["1_over_psi"] = np.array([1.0 / period])
    if ok(spindle_rpm):
        rev = spindle_rpm / 60.0
        if teeth is not None and teeth >= 1:
            tp = teeth * rev
            k = np.arange(1, 9)
            k = k[k * tp < nyq]
            if k.size:
                out["tooth_passing"] = k * tp
        elif rev < nyq:
            out["spindle"] = np.array([rev])
    return out
