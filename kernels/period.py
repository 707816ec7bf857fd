"""Finding the period of a disturbance in a residual: a harmonic-sum periodogram.

A periodic disturbance of period ψ — whatever its shape (a sine, square pulses, cutting-force
impulses) — puts spectral lines at the harmonics ``h/ψ``. The score of a candidate fundamental
``f0`` sums the normalised line strength over all of its harmonics below Nyquist:

1. periodogram ``P(f)`` of the mean-removed series with a Hann window, zero-padded ``PAD``×;
2. ``R(f) = P(f) / bg(f)`` with ``bg`` a running median of ``log P`` over ``BACKGROUND_FRACTION``
   of the band (the coloured background of a real residual), then the maximum of ``R`` within
   ±1 native bin (a line's peak), standardised by the median and MAD of that maximum over all
   frequencies: ``z_h(f)``;
3. ``Z(f0) = Σ_{h=1..H} z_h(h f0) / √H`` over all ``H`` harmonics below Nyquist, on a log-spaced grid of ``f0`` fine enough that the highest harmonic stays
   within half a bin. Dividing by ``√H`` makes a sub-harmonic ``f0/2`` (twice the harmonics,
   half of them noise) score about ``1/√2`` of ``f0``, and a super-harmonic ``2 f0`` keeps only
   the even lines.

Candidates are the local maxima of ``Z`` above ``Z_MIN``, at least ``MIN_CYCLES`` periods in the
record, best first. A candidate whose period divides the period of the commanded motion
(``reference``, e.g. ``v_ref``: ``ψ_m/ψ`` or ``ψ/ψ_m`` an integer ``k ≤ LOCK_RATIO`` within 2 %)
is *locked to the motion* (``ψ_m`` from :func:`motion_period`: the autocorrelation of the reference peaks at
``MOTION_ACF`` or more): such a disturbance cannot be told from the drive's own response to that motion (every
regressor repeats with it), so it is reported separately, not proposed.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import scipy.fft as sfft
from numba import njit
from scipy.ndimage import maximum_filter1d, median_filter

__all__ = ["PeriodCandidate", "harmonic_score", "detect_periods", "motion_period", "harmonically_related",
           "sampled_harmonic", "PAD", "Z_MIN", "MIN_CYCLES", "BACKGROUND_FRACTION", "LOCK_RATIO", "MOTION_ACF"]

#: zero padding of the periodogram
PAD = 4
#: smallest harmonic-sum score of a detected period
Z_MIN = 30.0
#: periods the record must hold
MIN_CYCLES = 5.0
#: width of the running-median background (fraction of the frequency bins)
BACKGROUND_FRACTION = 0.02
#: autocorrelation the commanded motion must reach at its period to count as repeating
MOTION_ACF = 0.8
#: a period is locked to the motion when it is 1…LOCK_RATIO times, or 1/LOCK_RATIO…1 of, the motion period
LOCK_RATIO = 4


@dataclass(frozen=True)
class PeriodCandidate:
    """One detected period ψ (s) with its harmonic-sum score ``Z`` and harmonics counted."""

    period: float
    score: float
    harmonics: int


@njit(cache=True, nogil=True)
def _harmonic_sum(zh, df, f0s, out, nh):
    m = zh.shape[0]
    for i in range(f0s.shape[0]):
        s = 0.0
        count = 0
        h = 1
        while True:
            k = int(h * f0s[i] / df + 0.5)
            if k >= m:
                break
            s += zh[k]
            count += 1
            h += 1
        nh[i] = count
        out[i] = s / math.sqrt(count) if count else 0.0


def harmonic_score(x, Ts: float, *, f_min: float | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(f0, Z, H)``: the harmonic-sum score (module docstring, steps 1–3) on a log grid of ``f0``
    from ``f_min`` (default ``MIN_CYCLES`` periods in the record) to Nyquist."""
    x = np.asarray(x, dtype=np.float64)
    n = x.size
    if n < 16 or not np.all(np.isfinite(x)):
        raise ValueError("period detection needs at least 16 finite samples")
    Ts = float(Ts)
    x = x - x.mean()
    nfft = sfft.next_fast_len(PAD * n, real=True)
    P = np.abs(sfft.rfft(x * np.hanning(n), nfft)) ** 2
    df = 1.0 / (nfft * Ts)
    width = max(64, int(BACKGROUND_FRACTION * P.size)) | 1
    floor = max(float(P.max()) * 1e-300, 1e-300)
    bg = np.exp(median_filter(np.log(P + floor), size=width, mode="nearest"))
    peak = maximum_filter1d(P / bg, size=2 * PAD + 1)
    med = float(np.median(peak))
    mad = 1.4826 * float(np.median(np.abs(peak - med))) or 1.0
    zh = (peak - med) / mad
    f_nyq = 0.5 / Ts
    if f_min is None:
        f_min = MIN_CYCLES / (n * Ts)
    f_min = max(float(f_min), df)
    if not f_min < f_nyq:
        return np.zeros(0), np.zeros(0), np.zeros(0, dtype=np.int64)
    step = 0.5 / (n * Ts) / f_nyq  # relative spacing: the top harmonic moves < half a native bin
    f0 = np.exp(np.arange(math.log(f_min), math.log(f_nyq), step))
    z = np.zeros(f0.size)
    nh = np.zeros(f0.size, dtype=np.int64)
    _harmonic_sum(zh, df, f0, z, nh)
    return f0, z, nh


def _peaks(f0, z, nh, z_min, top, exclude=()) -> list[PeriodCandidate]:
    order = np.argsort(z)[::-1]
    out: list[PeriodCandidate] = []
    taken: list[float] = []
    for i in order:
        if z[i] < z_min or len(out) >= top:
            break
        f = float(f0[i])
        if any(abs(f - g) <= 0.03 * g for g in taken):
            continue
        taken.append(f)
        if any(harmonically_related(1.0 / f, p, max_ratio=LOCK_RATIO) for p in exclude):
            continue
        out.append(PeriodCandidate(period=1.0 / f, score=float(z[i]), harmonics=int(nh[i])))
    return out


def motion_period(reference, Ts: float) -> float | None:
    """The period (s) with which the commanded motion repeats: the first lag (beyond the first zero
    crossing, up to half the record) at which the normalised autocorrelation of ``reference`` (mean
    removed) comes within 0.02 of its highest value, when that reaches ``MOTION_ACF``; None otherwise
    (or without a usable reference)."""
    ref = np.asarray(reference, dtype=np.float64)
    n = ref.size
    if n < 16 or not np.all(np.isfinite(ref)) or np.ptp(ref) == 0.0:
        return None
    x = ref - ref.mean()
    nfft = sfft.next_fast_len(2 * n, real=True)
    acf = sfft.irfft(np.abs(sfft.rfft(x, nfft)) ** 2, nfft)[:n]
    acf = acf / acf[0] * n / (n - np.arange(n))  # unbiased: each lag over its overlap
    half = n // 2
    below = np.flatnonzero(acf[:half] < 0.0)
    if below.size == 0:
        return None
    lo = int(below[0])
    if half <= lo + 1:
        return None
    seg = acf[lo:half]
    best = float(seg.max())
    if best < MOTION_ACF:
        return None
    # the first lag reaching the best level: a motion repeating every ψ_m also repeats every 2ψ_m
    k = lo + int(np.flatnonzero(seg >= best - 0.02)[0])
    while k + 1 < half and acf[k + 1] > acf[k]:
        k += 1
    return float(k * Ts)


def harmonically_related(a: float, b: float, *, rel: float = 0.02, max_ratio: int | None = None) -> bool:
    """True when one period is an integer multiple ``k`` of the other (``k ≤ max_ratio`` when given),
    within ``rel`` relative to the longer one: then one kernel's periodic functions include the
    other's."""
    short, long_ = min(a, b), max(a, b)
    m = long_ / short
    k = round(m)
    if max_ratio is not None and k > max_ratio:
        return False
    return k >= 1 and abs(m - k) * short <= rel * long_


def sampled_harmonic(period: float, base: float, Ts: float, *, max_harmonic: int = 8, rel: float = 0.005) -> bool:
    """True when the line at ``1/period`` is, as sampled every ``Ts``, a harmonic ``h/base`` (h ≤
    ``max_harmonic``) folded into ``[0, 1/(2 Ts)]``, within ``rel`` of its frequency: e.g. the
    200 Hz tooth-passing line of a 4-tooth cutter at 3000 rpm (period base 20 ms) seen at 133.3 Hz
    at 333.3 Hz sampling. A periodic kernel at ``base`` then explains it too."""
    fs = 1.0 / Ts
    f = 1.0 / period
    for h in range(1, max_harmonic + 1):
        g = (h / base) % fs
        g = min(g, fs - g)
        if abs(g - f) <= rel * f:
            return True
    return False


def detect_periods(residual, Ts: float, *, reference=None, top: int = 3,
                   z_min: float = Z_MIN) -> tuple[list[PeriodCandidate], float | None]:
    """Periods of the disturbance in ``residual`` (best first, at most ``top``) and the motion
    period (s) of ``reference`` (:func:`motion_period`; None without one). Periods locked to the
    motion are left out."""
    f0, z, nh = harmonic_score(residual, Ts)
    motion = motion_period(reference, Ts) if reference is not None else None
    exclude = (motion,) if motion is not None else ()
    return _peaks(f0, z, nh, z_min, top, exclude), motion
