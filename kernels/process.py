"""Where a process acts: the samples whose residual carries more than the measurement noise.

A process force (cutting, a shaker, a pump) is seen in the one-step residual ``r(k)`` of the drive
model as content beyond the noise floor; where it does not act the residual is the measurement
part ε plus the model's own error, which varies only with the motion. The first difference removes
what a biased β leaves at constant speed (``Δβᵀz`` is constant there), so the test is the local
mean square of ``Δr`` against its noise floor:

    Δε(k) = n(k+2) − (1 + p) n(k+1) + p n(k),     E[Δε²] = (1 + (1 + p)² + p²) σ_n²            (P1)

(ε of :mod:`kernels.noise`, eq. N1). A sample is *active* when the mean of ``Δr²`` over the
``window`` samples centred on it exceeds ``factor`` times (P1) in a stretch at least ``min_run`` long
(a shorter one is the model's own error at a reversal or an acceleration); the active stretches are widened by
``dilate`` samples on both sides (the tails of a cut's entry and exit, where the process is weaker
than the test's threshold) and gaps shorter than ``2·dilate`` between them are filled (hysteresis:
one quiet moment is no end of the process). ``idle`` marks samples known to be free of the process
whatever their residual (a spindle at rest: no cut).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.ndimage import binary_closing, binary_dilation, uniform_filter1d

from .blocks import gate_runs
from .errors import ParameterError

__all__ = ["ProcessMask", "process_mask", "FACTOR", "WINDOW_SECONDS", "DILATE_SECONDS", "MIN_RUN_SECONDS"]

#: local mean square of Δr above this many times its noise floor (P1) is a process
FACTOR = 4.0
#: the local mean is taken over this long (s), at least 16 samples
WINDOW_SECONDS = 0.05
#: active stretches are widened by this long (s) on each side, at least 4 samples
DILATE_SECONDS = 0.1
#: a process acts at least this long at a time (s): shorter excursions are the model's own error at a
#: transient (a reversal, an acceleration), not a process
MIN_RUN_SECONDS = 0.25


@dataclass(frozen=True)
class ProcessMask:
    """``active`` (N,) bool: a process acts; ``level`` (N,): the local mean square of Δr over its floor (P1)."""

    active: np.ndarray
    level: np.ndarray

    def counts(self, moving: np.ndarray) -> tuple[int, int]:
        """``(free, acting)``: moving samples without and with the process."""
        moving = np.asarray(moving, dtype=bool)
        return int(np.sum(moving & ~self.active)), int(np.sum(moving & self.active))


def process_mask(residual, sigma_n: float, pole: float, Ts: float, *, idle=None, factor: float = FACTOR,
                 window_s: float = WINDOW_SECONDS, dilate_s: float = DILATE_SECONDS,
                 min_run_s: float = MIN_RUN_SECONDS) -> ProcessMask:
    """The samples where a process acts (module docstring): ``residual`` (N,) the one-step residual (m/s),
    ``sigma_n`` the measurement noise (m/s) and ``pole`` the drive's discrete pole (:func:`kernels.noise.white_noise`),
    ``Ts`` the sample period (s), ``idle`` (N,) bool or None: samples free of the process whatever their
    residual."""
    r = np.asarray(residual, dtype=np.float64)
    n = r.size
    if r.ndim != 1 or n < 3 or not np.all(np.isfinite(r)):
        raise ParameterError("residual must be a finite series of at least 3 samples", "residual")
    if not (math.isfinite(sigma_n) and sigma_n > 0.0):
        raise ParameterError(f"sigma_n must be a positive noise level (m/s), got {sigma_n!r}", "sigma_n")
    if not (math.isfinite(Ts) and Ts > 0.0):
        raise ParameterError(f"Ts must be a positive sample period (s), got {Ts!r}", "Ts")
    floor = (1.0 + (1.0 + pole) ** 2 + pole * pole) * sigma_n * sigma_n          # (P1)
    d2 = np.empty(n)
    d2[:-1] = np.diff(r) ** 2
    d2[-1] = d2[-2]
    window = max(16, int(round(window_s / Ts)))
    level = uniform_filter1d(d2, size=min(window, n), mode="nearest") / floor
    active = level > factor
    shortest = max(1, int(round(min_run_s / Ts)))
    for a, b, open_ in gate_runs(active):
        if open_ and b - a < shortest:
            active[a:b] = False
    dilate = max(4, int(round(dilate_s / Ts)))
    if active.any():
        active = binary_dilation(active, iterations=dilate)
        active = binary_closing(active, structure=np.ones(2 * dilate + 1, dtype=bool))
    if idle is not None:
        idle = np.asarray(idle, dtype=bool)
        if idle.shape != (n,):
            raise ParameterError(f"idle must have one flag per residual ({n}), got shape {idle.shape}", "idle")
        active &= ~idle
    return ProcessMask(active=active, level=level)
