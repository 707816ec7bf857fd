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
variance and ``Δℓ ≥`` :data:`ADEQUACY_MIN_GAIN`. Measured on 5 s windows: the adequate trials (simulated shaker
and milling with their disturbance models, the real EMPS drive) explain ≤ 0.35 (EMPS, whose velocity
is a filtered position difference), the drives beyond the model ≥ 0.6 (docs/identification.md).

What it is, in words an engineer acts on:

* **delay** — the command's effect put back, ``r(k) = e(k) + g·c(k)`` (``g``: the model's gain from
  command to velocity per sample), regressed on ``c(k − j)``, ``v(k − j)`` (j = 0…2) and a constant gives
  the timing of the command's effect, ``a_j/g``; when it is one-signed (``Σ|a_j| ≤`` :data:`SPREAD` ``Σa_j``)
  its centroid ``φ = Σ j a_j / Σ a_j`` (≥ :data:`MIN_LATE`) is how late the command acts: ``φ ≈ 1`` (within
  0.3) a force one sample late,
  ``φ ≈ ½`` a velocity half a sample late (the backward difference of an encoder's position);
* **resonance** — otherwise, the model's own prediction put back, ``w(k) = e(k) + g·c(k) + p·v(k)``
  (``p`` the model's pole: ``w`` is the next velocity less the disturbance), fitted by an ARX(4, 4) on
  ``v`` and ``c`` (and a constant, ``sign v``): its least damped complex pole pair is the mode the rigid
  model leaves (the rigid drive has one real pole); its frequency is reported;
* else **dynamics** the first-order model does not have.

The command ``c`` is the force command ``u`` (force-input form) or the velocity controller's error
``v_r − v_m`` (velocity-loop form), with ``g`` the model's β1 (``b`` resp. ``K_d``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from .errors import ParameterError

__all__ = ["Adequacy", "adequacy", "LAGS", "EXPLAINED", "ADEQUACY_MIN_GAIN", "SPREAD", "ADEQUACY_MIN_SAMPLES"]

#: lags of the command and the velocity in (A1)
LAGS = 3
#: share of the residual variance the lags must explain for the model to be inadequate …
EXPLAINED = 0.5
#: … with at least this log-likelihood gain (a likelihood ratio of e²⁵)
ADEQUACY_MIN_GAIN = 25.0
#: the command's effect is one-signed (a delay, not a resonance) when Σ|a_j| is at most this times Σa_j …
SPREAD = 1.5
#: … and late when its centroid is at least this many samples
MIN_LATE = 0.2
#: the fewest samples a window needs
ADEQUACY_MIN_SAMPLES = 64


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


def adequacy(residual, command, v_meas, Ts: float, *, gain: float, pole: float) -> Adequacy:
    """Test (A1) on one window: ``residual`` e(k) (m/s) after the disturbance model, ``command`` c(k) and
    ``v_meas`` v(k) of the same samples, sample period ``Ts`` (s), ``gain`` g: the model's β1 (the command's
    effect on the next velocity), ``pole`` p: its discrete pole (β2 force-input, β1 + β2 velocity-loop).
    Pure; online it runs on a few seconds of the monitor's innovations."""
    e = np.asarray(residual, dtype=np.float64)
    c = np.asarray(command, dtype=np.float64)
    v = np.asarray(v_meas, dtype=np.float64)
    if e.ndim != 1 or e.size < ADEQUACY_MIN_SAMPLES:
        raise ParameterError(f"residual must be a window of at least {ADEQUACY_MIN_SAMPLES} samples, got shape {e.shape}",
                             "residual")
    if c.shape != e.shape or v.shape != e.shape:
        raise ParameterError(f"command {c.shape} and v_meas {v.shape} must have the residual's shape {e.shape}",
                             "command", "v_meas")
    if not (np.all(np.isfinite(e)) and np.all(np.isfinite(c)) and np.all(np.isfinite(v))):
        raise ParameterError("residual, command and v_meas must be finite (a window without gaps)", "residual")
    if not (math.isfinite(gain) and gain != 0.0):
        raise ParameterError(f"gain must be the model's β1 (non-zero), got {gain!r}", "gain")
    if not math.isfinite(pole):
        raise ParameterError(f"pole must be the model's discrete pole, got {pole!r}", "pole")
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
    if explained < EXPLAINED or gain_ll < ADEQUACY_MIN_GAIN:
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
        if late >= 0.6 and abs(late - round(late)) <= 0.3:
            what = (f"the velocity lags the command by {round(late)} sample(s) (the force acts {late:.2f} samples after "
                    "it is asked for): identify with the delay modelled, or remove it from the drive's signal path")
            return Adequacy(adequate=False, explained=explained, gain=gain_ll, kind="delay", delay=late,
                            message=what, detail=detail)
        if late >= MIN_LATE:
            what = (f"the velocity lags the command by {late:.2f} samples: a velocity that is the backward difference "
                    "of positions (an average over the last sample interval) — record the drive's own velocity "
                    "estimate, or a centred difference")
            return Adequacy(adequate=False, explained=explained, gain=gain_ll, kind="delay", delay=late,
                            message=what, detail=detail)
    freq = _mode(y + gain * _lagged(c, 0) + pole * _lagged(v, 0), _lagged(c, 0), _lagged(v, 0), Ts)
    if freq is not None:
        what = (f"a resonance near {freq:.0f} Hz that the rigid model leaves ({100 * explained:.0f} % of the residual "
                "follows the drive's own past): identify at a lower bandwidth (a slower velocity loop or a "
                "low-pass below it), or model the second mass")
        return Adequacy(adequate=False, explained=explained, gain=gain_ll, kind="resonance", frequency=freq,
                        message=what, detail=detail)
    return Adequacy(adequate=False, explained=explained, gain=gain_ll, kind="dynamics", detail=detail,
                    message=f"{100 * explained:.0f} % of the residual follows the drive's own past: dynamics the rigid "
                            "first-order model does not have (a flexible mode, a filter or a delay in the loop)")


#: the least damped complex pole of the ARX is a mode when its radius is at least this
MODE_RADIUS = 0.3
#: AR order of the mode fit
MODE_ORDER = 4


def _mode(w: np.ndarray, c: np.ndarray, v: np.ndarray, Ts: float) -> float | None:
    """The frequency (Hz) of the least damped complex pole pair of an ARX(MODE_ORDER, MODE_ORDER) fit of ``w``
    on ``v`` and ``c`` (with a constant and ``sign v``); None when it has none of radius ≥ MODE_RADIUS."""
    L = MODE_ORDER
    n = w.size
    X = np.column_stack([v[L - j: n - j] for j in range(L + 1)] + [c[L - j: n - j] for j in range(L + 1)]
                        + [np.ones(n - L), np.sign(v[L:])])
    coef, _ = _fit(w[L:], X)
    roots = np.roots(np.r_[1.0, -coef[: L + 1]])
    pairs = [r for r in roots if r.imag > 1e-9 and abs(r) >= MODE_RADIUS]
    if not pairs:
        return None
    best = max(pairs, key=abs)
    return float(abs(np.angle(best)) / (2.0 * math.pi * Ts))
