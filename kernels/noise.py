"""The white measurement noise in a window of one-step residuals, not inflated by a disturbance.

The one-step residual of the drive model (method §6) is ``v(k) = v_m(k+1) − βᵀz(k) = f(k) + ε(k)``:
a disturbance ``f`` (slow, or periodic with lines at the harmonics of its period, or a process that
acts part of the time) and the measurement part ``ε``. With white measurement noise ``n`` (std
``σ_n``) on the velocity, which the regressor ``v_m(k)`` carries too, the exact discrete drive gives

    ε(k) = n(k+1) − p n(k),      S_ε(ω) = σ_n² |1 − p e^{−iω}|²,      σ_ε² = (1 + p²) σ_n²       (N1)

with ``p`` the drive's discrete pole (``β2`` in the force-input form, ``β1 + β2`` in the velocity-loop
form, where the velocity controller feeds the noise back through ``v_r − v_m``). A disturbance has
its power in few frequency bins (lines, or the lowest frequencies); the noise in all of them. So the
estimate is a robust location of the periodogram after dividing out the noise's own shape:

    I_j = |Σ_k w_k x_k e^{−iω_j k}|² / Σ_k w_k²   (Hann taper w, mean removed)
    r_j = I_j / |1 − p e^{−iω_j}|²  over the bins with ω_j/π in [band]    → r_j ~ σ_n² · Exp(1)
    σ_n² = median_j(r_j) / ln 2                                                                  (N2)

(the median of an exponential variate is ln 2 times its mean). The low band edge leaves out the
slow disturbance and the frequencies where the shape of (N1) vanishes (p ≈ 1). Lines that occupy a
share ``s`` of the bins raise the median by a factor ``ln(1/(1 − 0.5/(1 − s)))/ln 2`` (+6 % at
s = 5 %). The standard error of σ_n² from the bins' count (two tapered bins are one independent
value): ``σ_n² / (ln 2 · √(n_bins/2))``. In time the estimate is robust as well: the median over windows
(:func:`white_noise`). Measured bias and spread on simulated trials and EMPS:
docs/identification.md.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import scipy.fft as sfft

from .errors import ParameterError

__all__ = ["NoiseEstimate", "white_noise", "BAND", "MIN_SAMPLES"]

#: normalised frequencies (ω/π, Nyquist = 1) whose periodogram bins carry the estimate (N2)
BAND = (0.25, 1.0)
#: the fewest residuals an estimate is made from
MIN_SAMPLES = 64
#: the estimate is the median over about this many windows …
WINDOWS = 8
#: … of this many samples at least and at most (a power of two; a shorter record is one window)
MIN_WINDOW, MAX_WINDOW = 512, 8192
#: a periodogram bin this many times the noise level is a line, left out
LINE_FACTOR = 10.0


@dataclass(frozen=True)
class NoiseEstimate:
    """``sigma_n``: std of the measurement noise on the velocity (m/s); ``sigma_eps``: std of the residual's
    measurement part ε (N1, m/s); ``se_eps``: the standard error of ``sigma_eps``; ``bins``: periodogram
    bins used; ``pole``: the p of (N1)."""

    sigma_n: float
    sigma_eps: float
    se_eps: float
    bins: int
    pole: float
    windows: int = 1

    def to_json(self) -> dict:
        return {"sigma_n": self.sigma_n, "sigma_eps": self.sigma_eps, "se_eps": self.se_eps, "bins": self.bins,
                "windows": self.windows, "pole": self.pole}


def _window(n: int, window: int | None) -> int:
    if window is not None:
        if not (isinstance(window, (int, np.integer)) and MIN_SAMPLES <= window):
            raise ParameterError(f"window must be an integer number of residuals ≥ {MIN_SAMPLES}, got {window!r}", "window")
        return min(int(window), n)
    w = 1 << max(int(math.log2(max(n // WINDOWS, 1))), 0)
    return min(n, max(MIN_WINDOW, min(MAX_WINDOW, w)))


def _window_variance(x: np.ndarray, pole: float, lo: float, hi: float) -> tuple[float, int]:
    """σ_n² of one window (N2), its lines left out (bins above :data:`LINE_FACTOR` times the estimate)."""
    n = x.size
    w = np.hanning(n + 2)[1:-1]
    spec = sfft.rfft((x - x.mean()) * w)
    periodogram = (spec.real ** 2 + spec.imag ** 2) / float(w @ w)
    omega = np.pi * np.arange(periodogram.size) / max(periodogram.size - 1, 1)
    use = (omega >= lo * np.pi) & (omega <= hi * np.pi)
    use[0] = False
    ratio = periodogram[use] / (1.0 + pole * pole - 2.0 * pole * np.cos(omega[use]))
    if ratio.size == 0:
        return math.nan, 0
    keep = ratio
    for _ in range(3):  # a line is a bin far above the noise: left out, the median taken again
        var = float(np.median(keep)) / math.log(2.0)
        keep = ratio[ratio <= LINE_FACTOR * var]
        if keep.size < max(ratio.size // 4, 1):
            return math.nan, 0
    return float(np.median(keep)) / math.log(2.0), int(keep.size)


def white_noise(residual, *, pole: float = 0.0, band: tuple[float, float] = BAND,
                window: int | None = None) -> NoiseEstimate:
    """The measurement noise in ``residual`` (a window of one-step residuals ``v(k)``, m/s, consecutive
    samples) by eq. N2; ``pole``: the drive's discrete pole p of eq. N1 (0: the residual's own white
    noise). Pure: the monitor can run it online on a few seconds of residuals.

    The record is cut into windows of ``window`` samples (default: about :data:`WINDOWS` of them, a power of
    two from :data:`MIN_WINDOW` to :data:`MAX_WINDOW`); each window's estimate (N2, its lines — bins above
    :data:`LINE_FACTOR` times the estimate — left out) and the median over the windows: a step, a glitch or
    a transient raises only the windows it falls in.

    Raises :class:`~kernels.errors.ParameterError` naming ``residual``, ``pole``, ``band`` or ``window``
    when the window is shorter than :data:`MIN_SAMPLES`, holds a non-finite value, or an argument is out of
    range."""
    x = np.asarray(residual, dtype=np.float64)
    if x.ndim != 1 or x.size < MIN_SAMPLES:
        raise ParameterError(f"residual must be a window of at least {MIN_SAMPLES} consecutive residuals, got shape "
                             f"{x.shape}", "residual")
    if not np.all(np.isfinite(x)):
        raise ParameterError("residual holds a non-finite value; estimate the noise on a window without it", "residual")
    if not (math.isfinite(pole) and -1.0 < pole < 1.0 + 1e-9):
        raise ParameterError(f"pole must be the drive's discrete pole in (−1, 1], got {pole!r}", "pole")
    lo, hi = (float(b) for b in band)
    if not 0.0 <= lo < hi <= 1.0:
        raise ParameterError(f"band must be (lo, hi) with 0 ≤ lo < hi ≤ 1 (fractions of the Nyquist frequency), got "
                             f"{band!r}", "band")
    size = _window(x.size, window)
    count = max(x.size // size, 1)
    per = [_window_variance(x[i * size:(i + 1) * size] if count > 1 else x, float(pole), lo, hi) for i in range(count)]
    good = [(v, b) for v, b in per if math.isfinite(v)]
    if not good:
        raise ParameterError("residual has no band without lines in which to see the noise (every window is lines)",
                             "residual")
    var_n = float(np.median([v for v, _ in good]))
    bins = int(sum(b for _, b in good))
    sigma_n = math.sqrt(var_n)
    sigma_eps = sigma_n * math.sqrt(1.0 + pole * pole)
    rel_var = 1.0 / (math.log(2.0) * math.sqrt(max(bins / 2.0, 1.0)))  # of σ_n², from the bins used
    return NoiseEstimate(sigma_n=sigma_n, sigma_eps=sigma_eps, se_eps=0.5 * sigma_eps * rel_var, bins=bins,
                         pole=float(pole), windows=len(good))
