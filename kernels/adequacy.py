"""Does the rigid first-order model explain the data? A test on a window of the residual left after the
disturbance model, with the command and the measured velocity of the same samples.

An adequate model leaves a residual ``e(k)`` that the drive's own past does not predict: what is left
is measurement noise and whatever the disturbance model missed, neither of which follows the command
a sample or two back. A drive the model does not describe leaves exactly that: a delay (the force acts
a sample late), a velocity that is a difference of positions (half a sample late), a resonance (the
velocity at the motor rings against the load). The test regresses the residual on the lagged command
``c`` and velocity ``v`` (ARX(3, 3) beyond the model's own first-order terms)::

    e(k) ≈ Σ_{j=0..L} a_j c(k−j) + Σ_{j=0..L} d_j v(k−j) + e₀,      L = LAGS                        (A1)
    R² = 1 − RSS₁/RSS₀,   Δℓ = ½ n log(RSS₀/RSS₁)

and calls the model inadequate when the lags explain at least :data:`EXPLAINED` of the residual's
variance and ``Δℓ ≥`` :data:`MIN_GAIN`. Measured on 5 s windows: the adequate trials (simulated shaker
and milling with their disturbance models, the real EMPS drive) explain ≤ 0.35 (EMPS, whose velocity
is a filtered position difference), the drives beyond the model ≥ 0.6 (docs/identification.md).

What it is, in words an engineer acts on:

* **delay** — the command's effect put back, ``r(k) = e(k) + g·c(k)`` (``g``: the model's gain from
  command to velocity per sample), regressed on ``c(k − j)``, ``v(k − j)`` (j = 0…2) and a constant gives
  the timing of the command's effect, ``a_j/g``; when it is one-signed (``Σ|a_j| ≤`` :data:`SPREAD` ``Σa_j``)
  its centroid ``φ = Σ j a_j / Σ a_j`` is how late the command acts: ``φ ≈ 1`` a force one sample late,
  ``φ ≈ ½`` a velocity half a sample late (the backward difference of an encoder's position);
* **resonance** — otherwise, the frequency where the residual's spectrum (Welch) stands highest above
  its median level: a lightly damped mode the rigid model leaves;
* else **dynamics** the first-order model does not have.

The command ``c`` is the force command ``u`` (force-input form) or the velocity controller's error
``v_r − v_m`` (velocity-loop form), with ``g`` the model's β1 (``b`` resp. ``K_d``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
import scipy.signal as ss

from .errors import ParameterError

__all__ = ["Adequacy", "adequacy", "LAGS", "EXPLAINED", "MIN_GAIN", "SPREAD", "MIN_SAMPLES"]

#: lags of the command and the velocity in (A1)
LAGS = 3
#: share of the residual variance the lags must explain for the model to be inadequate …
EXPLAINED = 0.5
#: … with at least this log-likelihood gain (a likelihood ratio of e²⁵)
MIN_GAIN = 25.0
#: the command's effect is one-signed (a delay, not a resonance) when Σ|a_j| is at most this times Σa_j
SPREAD = 1.5
#: the fewest samples a window needs
MIN_SAMPLES = 64


@dataclass(frozen=True)
class Adequacy:
    """Result of :func:`adequacy`. ``explained``: R² of (A1); ``gain``: Δℓ; ``adequate``; ``kind``: None
    (adequate) | "delay" | "resonance" | "dynamics"; ``delay``: φ in samples (the command's effect late by
    φ samples, when the kind is "delay"); ``frequency``: Hz of a resonance; ``message``: what it is and what
    to do."""

    adequate: bool
    explained: float
    gain: float
    kind: str | None = None
    delay: float | None = None
    frequency: float | None = None
    message: str = ""
    detail: dict = field(default_factory=dict)

    def to_json(self) -> dict:
        return {"adequate": self.adequate, "explained": self.explained, "gain": self.gain, "kind": self.kind,
                "delay": self.delay, "frequency": self.frequency, "message": self.message}


def _lagged(x: np.ndarray, j: int) -> np.ndarray:
    return x[LAGS - j: x.size - j]


def _fit(e: np.ndarray, X: np.ndarray) -> tuple[np.ndarray, float]:
    coef = np.linalg.lstsq(X, e, rcond=None)[0]
    r = e - X @ coef
    return coef, float(r @ r)


def adequacy(residual, command, v_meas, Ts: float, *, gain: float) -> Adequacy:
    """Test (A1) on one window: ``residual`` e(k) (m/s) after the disturbance model, ``command`` c(k) and
    ``v_meas`` v(k) of the same samples, sample period ``Ts`` (s), ``gain`` g: the model's β1 (the command's
    effect on the next velocity). Pure; online it runs on a few seconds of the monitor's innovations."""
    e = np.asarray(residual, dtype=np.float64)
    c = np.asarray(command, dtype=np.float64)
    v = np.asarray(v_meas, dtype=np.float64)
    if e.ndim != 1 or e.size < MIN_SAMPLES:
        raise ParameterError(f"residual must be a window of at least {MIN_SAMPLES} samples, got shape {e.shape}",
                             "residual")
    if c.shape != e.shape or v.shape != e.shape:
        raise ParameterError(f"command {c.shape} and v_meas {v.shape} must have the residual's shape {e.shape}",
                             "command", "v_meas")
    if not (np.all(np.isfinite(e)) and np.all(np.isfinite(c)) and np.all(np.isfinite(v))):
        raise ParameterError("residual, command and v_meas must be finite (a window without gaps)", "residual")
    if not (math.isfinite(gain) and gain != 0.0):
        raise ParameterError(f"gain must be the model's β1 (non-zero), got {gain!r}", "gain")
    if not (math.isfinite(Ts) and Ts > 0.0):
        raise ParameterError(f"Ts must be a positive sample period in s, got {Ts!r}", "Ts")
    y = e[LAGS:] - e[LAGS:].mean()
    rss0 = float(y @ y)
    n = y.size
    if not rss0 > 0.0:
        return Adequacy(adequate=True, explained=0.0, gain=0.0, message="the residual is zero")
    base = [_lagged(c, 0), _lagged(v, 0), np.ones(n)]
    X = np.column_stack(base + [_lagged(c, j) for j in range(1, LAGS + 1)] + [_lagged(v, j) for j in range(1, LAGS + 1)])
    _, rss1 = _fit(y, X)
    explained = max(0.0, 1.0 - rss1 / rss0)
    gain_ll = 0.5 * n * math.log(rss0 / max(rss1, 1e-300 * rss0))
    if explained < EXPLAINED or gain_ll < MIN_GAIN:
        return Adequacy(adequate=True, explained=explained, gain=gain_ll)
    # what it is: the timing of the command's effect, else a resonance in the residual
    r = y + gain * _lagged(c, 0)
    timing, _ = _fit(r, np.column_stack([_lagged(c, j) for j in range(3)] + [_lagged(v, j) for j in range(3)]
                                        + [np.ones(n)]))
    a = timing[:3] / gain
    detail = {"timing": a.tolist()}
    total = float(a.sum())
    if total > 0.0 and float(np.abs(a).sum()) <= SPREAD * total:
        late = float(np.arange(3) @ a) / total
        detail["centroid"] = late
        if late >= 0.3 and abs(late - round(late)) <= 0.3:
            what = (f"the velocity lags the command by {round(late)} sample(s) (the force acts {late:.2f} samples after "
                    "it is asked for): identify with the delay modelled, or remove it from the drive's signal path")
            return Adequacy(adequate=False, explained=explained, gain=gain_ll, kind="delay", delay=late,
                            message=what, detail=detail)
        if late >= 0.3:
            what = (f"the velocity lags the command by {late:.2f} samples: a velocity that is the backward difference "
                    "of positions (an average over the last sample interval) — record the drive's own velocity "
                    "estimate, or a centred difference")
            return Adequacy(adequate=False, explained=explained, gain=gain_ll, kind="delay", delay=late,
                            message=what, detail=detail)
    freq = _peak(e, Ts)
    if freq is not None:
        what = (f"a resonance near {freq:.0f} Hz that the rigid model leaves ({100 * explained:.0f} % of the residual "
                "follows the drive's own past): identify at a lower bandwidth (a slower velocity loop or a "
                "low-pass below it), or model the second mass")
        return Adequacy(adequate=False, explained=explained, gain=gain_ll, kind="resonance", frequency=freq,
                        message=what, detail=detail)
    return Adequacy(adequate=False, explained=explained, gain=gain_ll, kind="dynamics", detail=detail,
                    message=f"{100 * explained:.0f} % of the residual follows the drive's own past: dynamics the rigid "
                            "first-order model does not have (a flexible mode, a filter or a delay in the loop)")


#: a resonance stands this many times above the residual spectrum's median level
PEAK_FACTOR = 5.0


def _peak(e: np.ndarray, Ts: float) -> float | None:
    """The frequency (Hz) where the residual's Welch spectrum stands highest above its median (above a tenth of
    the band), when it stands at least :data:`PEAK_FACTOR` times higher; None otherwise."""
    nper = int(min(e.size, max(64, 2 ** int(math.log2(max(e.size // 8, 64))))))
    f, P = ss.welch(e - e.mean(), fs=1.0 / Ts, nperseg=nper)
    band = f > 0.1 * f[-1]
    if band.sum() < 4:
        return None
    level = float(np.median(P[band]))
    k = int(np.argmax(np.where(band, P, -np.inf)))
    return float(f[k]) if level > 0 and P[k] >= PEAK_FACTOR * level else None
