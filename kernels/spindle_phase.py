"""The spindle-phase kernel in batch identification (method §5, "Spindle phase").

The online tracker's spindle-phase kernel (:func:`spindle_phase_kernel`; ``[tracker] kernel =
"spindle"``) works on ``x = (t, θ)``, θ the spindle angle (rad):

    k((t, θ), (t', θ')) = exp(−(t − t')²/(2σ1²)) · exp(−sin²(π(θ − θ')/P)/(2σ2²))            (S1)

with ``P = 2π`` per revolution. When the speed changes, ``A = Ω + γ⁻¹I`` of the PL-LSSVM is not a
function of the time lag, so the Toeplitz algebra of :mod:`kernels.likelihood` does not apply.
Within a stretch where the spindle turns at a constant rate ω (``θ = θ₀ + ω t``) it does:

    k = exp(−d²/(2σ1²)) · exp(−sin²(π ω d/P)/(2σ2²)),   d = t − t'                          (S2)

is the time kernel ``LocallyPeriodic(σ1, σ2, ψ = P/|ω|)`` (``SquaredExponential(σ1)`` at rest).
Identification therefore splits the record into such stretches (:func:`phase_segments`: θ linear
in t within ± ``tol`` rad) and treats them as independent realisations of the disturbance with a
shared β — ``A ≈ diag(A₁, …, A_S)``, one Levinson pass per stretch (:mod:`kernels.blocks`). The approximation leaves
out only the correlation across a change of speed (the pattern is learned afresh after each one),
which can only make this candidate look *worse* than the exact kernel: its evidence is conservative
against the exact time-kernel candidates it competes with.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from .covariance import Kernel, Periodic, Product, SquaredExponential

__all__ = ["spindle_phase_kernel", "spindle_phase", "PhaseSegments", "phase_segments", "segment_tolerance",
           "TOL_FRACTION", "MAX_SEGMENTS", "MAX_HOLE"]

#: θ may leave the straight line of its stretch by this fraction of the periodic factor's length
#: scale ``ℓ_θ = P σ2/π`` (S1 near zero lag): the kernel value then errs by ≲ 2·TOL_FRACTION
#: relative at one length scale of lag
TOL_FRACTION = 0.02
#: most stretches a record may split into (beyond it the speed varies continuously: the
#: block-diagonal approximation would forget the pattern every few samples)
MAX_SEGMENTS = 2000
#: longest hole in the spindle speed (s) bridged by linear interpolation
MAX_HOLE = 0.1


def spindle_phase_kernel(sigma1: float, sigma2: float, period: float = 2.0 * math.pi) -> Kernel:
    """(S1): ``SquaredExponential(σ1)`` on time (column 0) × ``Periodic(σ2, P)`` on the spindle angle
    (column 1, rad). The one definition, used by the online tracker
    (:class:`monitor.online_settings.SpindleKernel`) and by identification."""
    return Product(SquaredExponential(sigma1, dims=0), Periodic(sigma2, period, dims=1))


def spindle_phase(t, angle=None, rpm=None) -> np.ndarray | None:
    """Continuous spindle angle θ(t_k) (rad) of every sample, or None without usable spindle data.

    * ``angle`` (rad) when every sample has a finite one: unwrapped — guided by ``rpm`` when every
      sample has a finite speed (each step is the one nearest to the speed's trapezoid step, so a
      wrapped angle at any speed is followed), else by :func:`numpy.unwrap` (steps below π per
      sample: a cumulative angle, or a spindle slower than 30 revolutions per sample period);
    * else ``rpm`` integrated with the trapezoid rule of the online tracker
      (:func:`kernels.online._theta`): ``θ_k = θ_{k−1} + (2π/60)·(n_{k−1} + n_k)/2·(t_k − t_{k−1})``;
      holes in ``rpm`` (non-finite values) of at most :data:`MAX_HOLE` s are interpolated linearly
      (held at the ends); a longer hole leaves no usable speed.
    """
    t = np.asarray(t, dtype=np.float64)
    rate = None
    if rpm is not None:
        r = _fill_holes(t, np.asarray(rpm, dtype=np.float64))
        if r is not None:
            rate = (2.0 * math.pi / 60.0) * 0.5 * (r[1:] + r[:-1]) * np.diff(t)
    if angle is not None:
        a = np.asarray(angle, dtype=np.float64)
        if a.shape == t.shape and np.all(np.isfinite(a)):
            if rate is None:
                return np.unwrap(a)
            step = np.diff(a)
            step = rate + (np.mod(step - rate + math.pi, 2.0 * math.pi) - math.pi)
            return np.concatenate([a[:1], a[0] + np.cumsum(step)])
    if rate is None:
        return None
    return np.concatenate([[0.0], np.cumsum(rate)])


def _fill_holes(t: np.ndarray, x: np.ndarray) -> np.ndarray | None:
    """``x`` with holes (non-finite runs) of at most :data:`MAX_HOLE` s interpolated linearly in t (held
    at the ends); None when ``x`` does not match ``t`` or a hole is longer."""
    if x.shape != t.shape:
        return None
    ok = np.isfinite(x)
    if ok.all():
        return x
    good = np.flatnonzero(ok)
    if good.size == 0:
        return None
    edges = np.concatenate([[t[good[0]] - t[0]], np.diff(t[good]), [t[-1] - t[good[-1]]]])
    if float(np.max(edges)) > MAX_HOLE + 1e-12:
        return None
    return np.interp(t, t[good], x[good])


@dataclass(frozen=True)
class PhaseSegments:
    """Stretches of constant spindle speed: samples ``edges[s]:edges[s+1]`` turn at ``rate[s]``
    rad/s (θ within ± ``tol`` rad of a straight line in t)."""

    edges: np.ndarray  # (S + 1,) int64, 0 … N
    rate: np.ndarray  # (S,) rad/s
    tol: float  # rad

    @property
    def count(self) -> int:
        return int(self.rate.size)

    @property
    def lengths(self) -> np.ndarray:
        return np.diff(self.edges)

    def window(self, a: int, b: int) -> PhaseSegments:
        """The stretches of samples ``a … b − 1``, numbered from ``a`` (the speed of each unchanged)."""
        edges = np.clip(self.edges, a, b) - a
        keep = np.flatnonzero(np.diff(edges) > 0)
        return PhaseSegments(edges=np.concatenate([edges[keep], [b - a]]).astype(np.int64), rate=self.rate[keep],
                             tol=self.tol)

    def periods(self, P: float = 2.0 * math.pi) -> np.ndarray:
        """``ψ_s = P/|ω_s|`` (s) of each stretch (S2); ``inf`` at rest."""
        with np.errstate(divide="ignore"):
            return np.where(self.rate != 0.0, P / np.abs(self.rate), np.inf)

    def columns(self, kernel: Kernel, Ts: float, shift: float = 0.0, max_order: int | None = None) -> list[np.ndarray]:
        """First column of each stretch's Toeplitz block of ``Ω + shift·I``: the kernel itself (S1)
        evaluated at the lags ``(d, ω_s d)``, ``d = 0, Ts, 2Ts, …`` (S2) — at most ``max_order + 1`` lags."""
        out = []
        origin = np.zeros((1, 2))
        for n_s, w in zip(self.lengths.tolist(), self.rate.tolist()):
            d = np.arange(n_s if max_order is None else min(n_s, int(max_order) + 1)) * Ts
            col = kernel(origin, np.column_stack([d, w * d]))[0]
            col[0] += shift
            out.append(col)
        return out


def segment_tolerance(sigma2: float, P: float = 2.0 * math.pi) -> float:
    """``tol = TOL_FRACTION · P σ2/π`` (rad), the allowed departure of θ from its stretch's line."""
    return TOL_FRACTION * P * float(sigma2) / math.pi


def phase_segments(t, theta, tol: float) -> PhaseSegments:
    """Split the record into the longest stretches (greedy, from the start) in which θ stays within
    ``tol`` rad of the chord between the stretch's first and last sample; ``rate`` is the chord's
    slope. Each stretch's end is found by doubling then bisection (``O(N log N)``).

    Raises ``ValueError`` when θ or t are not finite, t does not increase, or the record needs more
    than :data:`MAX_SEGMENTS` stretches (the speed varies continuously at this tolerance).
    """
    t = np.asarray(t, dtype=np.float64)
    th = np.asarray(theta, dtype=np.float64)
    n = t.size
    if th.shape != t.shape or n < 2:
        raise ValueError(f"spindle angle and time must be two series of equal length ≥ 2, got {th.shape} and {t.shape}")
    if not (np.all(np.isfinite(t)) and np.all(np.isfinite(th))):
        raise ValueError("spindle angle or time has non-finite values")
    if np.any(np.diff(t) <= 0):
        raise ValueError("time must increase from sample to sample")
    if not (math.isfinite(tol) and tol > 0):
        raise ValueError(f"tolerance must be a positive angle in rad, got {tol!r}")

    def fits(i: int, j: int) -> bool:  # samples i … j−1 on one line
        if j - i <= 2:
            return True
        slope = (th[j - 1] - th[i]) / (t[j - 1] - t[i])
        return bool(np.max(np.abs(th[i:j] - th[i] - slope * (t[i:j] - t[i]))) <= tol)

    edges, rates = [0], []
    i = 0
    while i < n:
        good, step = min(i + 2, n), 2
        bad = None
        while good < n:
            j = min(i + 2 * step, n)
            if fits(i, j):
                good, step = j, 2 * step
            else:
                bad = j
                break
        if bad is not None:
            while bad - good > 1:
                mid = (good + bad) // 2
                if fits(i, mid):
                    good = mid
                else:
                    bad = mid
        rates.append((th[good - 1] - th[i]) / (t[good - 1] - t[i]) if good - i >= 2 else 0.0)
        edges.append(good)
        i = good
        if len(rates) > MAX_SEGMENTS:
            raise ValueError(f"the spindle speed varies continuously: θ needs more than {MAX_SEGMENTS} stretches of "
                             f"constant speed (±{tol:.3g} rad)")
    return PhaseSegments(edges=np.asarray(edges, dtype=np.int64), rate=np.asarray(rates, dtype=np.float64),
                         tol=float(tol))
