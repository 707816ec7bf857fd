"""Low-speed friction check: does the model's friction law hold near standstill?

The PL-ARX model (method §1) has Coulomb and viscous friction, ``d·sign(v) + B·v``. Real drives
depart from it near standstill, between the dead band and a few centimetres per second: the
friction rises towards its static value (a *Stribeck* hump), or it builds up gradually instead of
stepping to ``d`` (a smooth Coulomb onset: presliding, lubricant film). Fitted over a whole record
the law is right at speed; near standstill its error is a force the model cannot have. Offline it is a
small share of the samples. Online it weighs far more: the samples around a reversal or a start
are where the tracker's innovations are large, so an estimator that learns β from innovations
(:mod:`kernels.beta_tracker`) reads the Stribeck hump as viscous and Coulomb friction. On the real
EMPS drive (whose friction near standstill is ~6 N *below* the law: a gradual onset) the online
damping came out +25 % (Coulomb −10 %) against least squares and the published values, with the
model that was identified on the same record.

Test (a one-parameter family of extra columns, scanned)::

    h_i(v_s) = −sign(v_i) · exp(−(v_i / v_s)²)        (0 inside the dead band |v_i| ≤ Ω)     (LS1)

appended to the regressors ``Z`` of the written model: with ``e`` the model's one-step prediction
error and ``P`` the projection off the columns of ``Z``,

    a(v_s) = (P h)ᵀ e / ‖P h‖²,   RSS₁ = RSS₀ − a² ‖P h‖²,   Δℓ(v_s) = ½ N log(RSS₀ / RSS₁)   (LS2)

(the Gaussian log-likelihood gain of the column, β refitted). ``v_s`` runs over a log grid from
``2Ω`` to a third of the largest speed; the best is kept. The effect is *significant* when
``Δℓ ≥ min_gain`` (default 25: a likelihood ratio of e²⁵, far beyond the ½·2·log N of a BIC
penalty for the two parameters ``a, v_s`` at any record length here) and *local* when the samples
below ``2 v_s`` are at most ``max_share`` of the moving ones. Then the law does not hold below
``min_speed = 2 v_s`` (there the hump is ``e⁻⁴`` ≈ 2 % of its height) and the monitor learns β
only above it. A significant effect that is not local (most of the record is "low speed", e.g. a
milling feed of a few mm/s whose cutting force the column happens to follow) is reported, not
used: gating it would stop the learning.

Where the law holds (:func:`law_holds_above`): the lowest speed ``c`` such that least squares on the
samples outside ``Ω < |v| < c`` leaves no significant departure (LS2) among them — bisection on a log
grid of ``c`` from ``2Ω`` to a third of the largest speed, as far as the samples left out stay at most
``max_share`` of the motion. The mean departure of the samples below ``c`` from that fit,
``δ = mean(sign(v)·e)`` (velocity per sample; ``−δ/b`` in N), says which way the friction departs:
``δ < 0`` (``e`` holds ``−b·ΔF``) is *more* friction than the law, a Stribeck rise; ``δ > 0`` less.

    c* = min { c : Δℓ_max(samples outside Ω < |v| < c) < min_gain }                              (LS3)
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

__all__ = ["LowSpeedFriction", "LowSpeedCut", "low_speed_friction", "law_holds_above", "stribeck_column", "MIN_GAIN",
           "MAX_SHARE", "GRID", "SPAN"]

#: log-likelihood gain Δℓ (LS2) from which the effect counts
MIN_GAIN = 25.0
#: largest share of the moving samples below 2 v_s for the effect to be gated online
MAX_SHARE = 0.25
#: points of the v_s grid
GRID = 40
#: the law departs below SPAN · v_s (there the hump (LS1) is e^(−SPAN²) = e⁻⁴ ≈ 2 % of its height)
SPAN = 2.0


@dataclass(frozen=True)
class LowSpeedFriction:
    """Result of :func:`low_speed_friction` (speeds in m/s; ``amplitude``, ``se`` in the units of ``e``)."""

    v_s: float            #: speed scale of the hump (LS1)
    amplitude: float      #: a; ``a/b`` (b: the input gain) is the extra friction near standstill in N
                          #: (+: more than the law, a Stribeck rise; −: less, a gradual onset)
    se: float             #: its standard error
    gain: float           #: Δℓ (LS2)
    share: float          #: share of the moving samples slower than :attr:`speed`
    significant: bool     #: gain ≥ min_gain
    local: bool           #: share ≤ max_share

    def to_json(self) -> dict:
        return {"v_s": self.v_s, "amplitude": self.amplitude, "se": self.se, "gain": self.gain, "share": self.share,
                "significant": self.significant, "local": self.local, "min_speed": self.min_speed}

    @property
    def speed(self) -> float:
        """``SPAN · v_s`` = 2 v_s (m/s): below it the friction departs from the law."""
        return SPAN * self.v_s

    @property
    def min_speed(self) -> float:
        """The speed (m/s) below which the monitor does not learn β: :attr:`speed` when the effect is
        significant and local, else 0 (the law holds down to the dead band)."""
        return self.speed if (self.significant and self.local) else 0.0


def stribeck_column(v, omega: float, v_s: float) -> np.ndarray:
    """The column (LS1) ``−sign(v)·exp(−(v/v_s)²)``, 0 inside the dead band ``|v| ≤ Ω``: a friction that departs
    from the Coulomb level near standstill (its coefficient ``a``: the departure in velocity per sample)."""
    v = np.asarray(v, dtype=np.float64)
    sign = np.where(v > omega, 1.0, np.where(v < -omega, -1.0, 0.0))
    return -sign * np.exp(-((v / v_s) ** 2))


def low_speed_friction(Z, e, v, omega: float, *, min_gain: float = MIN_GAIN, max_share: float = MAX_SHARE,
                       grid: int = GRID, rise_only: bool = False) -> LowSpeedFriction | None:
    """Scan the Stribeck column (LS1) against the prediction error ``e`` (eq. LS2).

    ``Z`` (N, p): the model's regressors; ``e`` (N,): its one-step prediction error; ``v`` (N,): the
    measured velocity the regressors were built from (m/s), ``omega`` the dead band Ω (m/s). None when
    there is nothing to test (fewer than 50 moving samples, no speed range above ``2Ω``, or no
    residual). ``rise_only``: the best ``v_s`` among those where the friction is *above* the law
    (``a > 0``: a Stribeck rise, the shape of the column), None when there is none."""
    Z = np.asarray(Z, dtype=np.float64)
    e = np.asarray(e, dtype=np.float64)
    v = np.asarray(v, dtype=np.float64)
    n = e.size
    if Z.ndim != 2 or Z.shape[0] != n or v.shape != (n,):
        raise ValueError(f"Z {Z.shape}, e {e.shape} and v {v.shape} must have the same number of rows")
    if not (np.all(np.isfinite(Z)) and np.all(np.isfinite(e)) and np.all(np.isfinite(v))):
        raise ValueError("Z, e and v must be finite")
    moving = np.abs(v) > omega
    v_hi = float(np.max(np.abs(v))) / 3.0 if n else 0.0
    v_lo = max(2.0 * float(omega), 1e-9)
    if moving.sum() < 50 or v_hi <= v_lo or n <= Z.shape[1] + 2:
        return None
    q, _ = np.linalg.qr(Z)
    e0 = e - q @ (q.T @ e)                      # P e
    rss0 = float(e0 @ e0)
    if not rss0 > 0:
        return None
    best = None
    for vs in np.geomspace(v_lo, v_hi, grid):
        h = stribeck_column(v, omega, vs)        # LS1
        hp = h - q @ (q.T @ h)                   # P h
        hh = float(hp @ hp)
        if not hh > 1e-12 * float(h @ h):
            continue
        a = float(hp @ e0) / hh
        if rise_only and not a > 0.0:
            continue
        rss1 = max(rss0 - a * a * hh, 1e-300 * rss0)
        gain = 0.5 * n * math.log(rss0 / rss1)    # LS2
        if best is None or gain > best[1]:
            se = math.sqrt(rss1 / max(n - Z.shape[1] - 1, 1) / hh)
            best = (float(vs), gain, a, se)
    if best is None:
        return None
    vs, gain, a, se = best
    share = float(np.sum(moving & (np.abs(v) < SPAN * vs)) / moving.sum())
    return LowSpeedFriction(v_s=vs, amplitude=a, se=se, gain=gain, share=share, significant=gain >= min_gain,
                            local=share <= max_share)


@dataclass(frozen=True)
class LowSpeedCut:
    """Result of :func:`law_holds_above` (LS3): ``speed`` c* (m/s), ``departure`` δ (in the units of the
    regression's residual: ``−δ/b`` is the friction above the law in N), ``share`` of the moving samples
    below c*."""

    speed: float
    departure: float
    share: float

    @property
    def rise(self) -> bool:
        """More friction than the law below :attr:`speed` (a Stribeck rise)."""
        return self.departure < 0.0

    def to_json(self) -> dict:
        return {"speed": self.speed, "departure": self.departure, "share": self.share, "rise": self.rise}


def _departs(Z, y, v, omega, keep, min_gain) -> tuple[bool, np.ndarray]:
    theta = np.linalg.lstsq(Z[keep], y[keep], rcond=None)[0]
    e = y - Z @ theta
    check = low_speed_friction(Z[keep], e[keep], v[keep], omega, min_gain=min_gain, max_share=1.0)
    return check is not None and check.significant, e


def law_holds_above(Z, y, v, omega: float, *, min_gain: float = MIN_GAIN, max_share: float = MAX_SHARE,
                    grid: int = GRID) -> LowSpeedCut | None:
    """The speed above which the friction law holds (LS3) for the regression ``y ≈ Zθ`` with velocity ``v``
    (m/s) and dead band ``omega``; None when the law holds down to the dead band, or when no cut within
    ``max_share`` of the motion makes it hold."""
    Z = np.asarray(Z, dtype=np.float64)
    y = np.asarray(y, dtype=np.float64)
    v = np.asarray(v, dtype=np.float64)
    speed = np.abs(v)
    moving = speed > omega
    if moving.sum() < 50:
        return None
    cuts = np.geomspace(max(2.0 * omega, 1e-9), max(float(speed.max()) / 3.0, 4.0 * omega + 1e-9), grid)
    cuts = cuts[[np.mean(speed[moving] < c) <= max_share for c in cuts]]
    everything = np.ones(v.size, dtype=bool)
    if cuts.size == 0 or not _departs(Z, y, v, omega, everything, min_gain)[0]:
        return None

    def keep_of(c: float) -> np.ndarray:
        return ~(moving & (speed < c))

    if _departs(Z, y, v, omega, keep_of(cuts[-1]), min_gain)[0]:
        return None  # no cut within max_share makes the law hold
    lo, hi = -1, cuts.size - 1  # departs at lo (the whole record), holds at hi
    while hi - lo > 1:
        mid = (lo + hi) // 2
        if _departs(Z, y, v, omega, keep_of(cuts[mid]), min_gain)[0]:
            lo = mid
        else:
            hi = mid
    c = float(cuts[hi])
    keep = keep_of(c)
    _, e = _departs(Z, y, v, omega, keep, min_gain)
    below = ~keep
    departure = float(np.mean(np.sign(v[below]) * e[below]))
    return LowSpeedCut(speed=c, departure=departure, share=float(below.sum() / moving.sum()))
