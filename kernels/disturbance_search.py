"""The tracker's disturbance model, chosen online from the process the monitor sees.

The drive model β comes from identification; the *disturbance* model (the KRLS-T kernel and
its hyperparameters σ1, σ2, γ, λ) follows the samples being monitored. Candidates are
weighed by the prequential principle (Dawid 1984): a model is as good as its one-step-ahead
predictions of data it had not seen. Every candidate is replayed from nothing over the last
samples the primary tracker learned (a ring the compiled loop keeps) and scored by the sum of its
predictive log-densities

    ℓ_c = Σ_k log N(y_k; ŷ_c(k), s0²_c σ²_y,c(k))                                          (P1)

over the samples after its warm-up, against a control: the primary's own model replayed the same
way (a tracker fed only the recent samples predicts better after a change of the process than one
that remembers the time before it, whatever its kernel — the comparison must not reward that). A
candidate whose ℓ exceeds the control's by :attr:`SearchSettings.margin` is adopted (its replayed
tracker becomes the primary).

Where candidates come from (:meth:`DisturbanceSearch.tick`):

* **the process signals**: with spindle data in the samples, the spindle-phase kernel (per
  revolution, and per tooth for the tooth count the residual's spindle orders show) whatever the
  identification trial was;
* **the residual's spectrum**: without spindle data, the periods the harmonic-sum periodogram
  (:func:`kernels.period.detect_periods`, motion-locked periods left out) finds on the recent
  residual at several window lengths, each refined by an exact harmonic-power search (P2) and
  given data-driven starting hyperparameters: σ2 from the harmonics that carry the energy
  (P3), γ from the residual's power over the noise (P4);
* **tracking in time**: squared-exponential kernels of short length scale when the primary
  predicts poorly and nothing periodic is found (a step, a drift);
* **local search**: one hyperparameter of the primary at a time, ×/÷ a factor (σ1, σ2 ×2, γ ×4,
  the memory 1/(1 − λ) ×2) — an online coordinate search of the predictive likelihood.

A search runs every few seconds (sooner after an adoption, rarer while nothing improves) and at
once when the primary predicts poorly (a short EWMA of its normalised innovations ν² or of its
innovations over the noise floor); the replay work is bounded by a budget of replayed samples per
learned sample (a token bucket), so the per-sample cost stays within a fixed factor of the
tracker's. Everything depends on sample counts only, never on wall-clock time: the live monitor
and ``feedmon run --from`` choose the same models.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from typing import Literal

import numpy as np

from .covariance import Kernel, LocallyPeriodic, SquaredExponential, ZeroMeanLocallyPeriodic
from .period import detect_periods, harmonically_related, sampled_harmonic
from .spindle_phase import spindle_phase_kernel

__all__ = ["TrackerChoice", "SearchSettings", "DisturbanceSearch", "Ring", "Verdict", "prequential", "SPINDLE_START", "refine_period",
           "harmonic_amplitudes", "sigma2_of_harmonics", "spindle_orders", "tooth_count", "signal_to_noise",
           "LOG_2PI", "for_beta"]

LOG_2PI = math.log(2.0 * math.pi)
#: bounds of the hyperparameters a search may reach (beyond them a perturbation is not tried)
SIGMA1_RANGE = (0.005, 600.0)      # s
SIGMA2_RANGE = (0.02, 5.0)
GAMMA_RANGE = (1.0, 1e7)
MEMORY_RANGE = (50.0, 1e5)         # 1/(1 − λ), samples
#: σ1 (s) and σ2 of the spindle-phase kernel when the stream brings spindle data and the model file's
#: tracker was not periodic (thesis Table 4.5's σ1; σ2 for the few harmonics of a cutting force)
SPINDLE_START = {"sigma1": 1.2, "sigma2": 0.5}
#: a searched disturbance model whose γ is this many times the model file tracker's shows a disturbance the
#: file's tracker takes for noise: online β learns with it (:func:`for_beta`)
STRONG_GAMMA = 10.0


@dataclass(frozen=True)
class TrackerChoice:
    """One disturbance model of the tracker (method §5, §6).

    ``kind``: ``"time"`` — squared exponential in time, length scale ``sigma1`` (s);
    ``"periodic"`` — locally periodic in time, ``sigma1`` (s), ``sigma2``, period ``period`` (s), its
    zero-mean form with ``zero_mean`` (no slow mean to compete with the friction and damping columns;
    identification chooses it, and the search keeps that choice);
    ``"spindle"`` — the spindle-phase kernel on ``(t, θ)``: ``sigma1`` (s), ``sigma2``, period
    ``2π/teeth`` in θ (``teeth = 1``: per revolution). ``gamma`` the signal-to-noise ratio γ
    (``sn2 = 1/γ``), ``forgetting`` λ.
    """

    kind: Literal["time", "periodic", "spindle"]
    sigma1: float
    gamma: float
    forgetting: float
    sigma2: float = 0.5
    period: float = 0.0
    teeth: int = 1
    zero_mean: bool = False

    @property
    def spindle(self) -> bool:
        """The tracker input is ``x = (t, θ)``."""
        return self.kind == "spindle"

    @property
    def memory(self) -> float:
        """``1/(1 − λ)``, samples."""
        return 1.0 / (1.0 - self.forgetting) if self.forgetting < 1.0 else math.inf

    def kernel(self) -> Kernel:
        """The covariance function (one definition per kernel: :mod:`kernels.covariance`)."""
        if self.kind == "spindle":
            return spindle_phase_kernel(self.sigma1, self.sigma2, 2.0 * math.pi / self.teeth)
        if self.kind == "periodic":
            lp = ZeroMeanLocallyPeriodic if self.zero_mean else LocallyPeriodic
            return lp(self.sigma1, self.sigma2, self.period)
        return SquaredExponential(self.sigma1)

    def describe(self) -> str:
        """One line for logs and the status."""
        hyper = f"σ1 {self.sigma1:.3g} s, γ {self.gamma:.3g}, λ {self.forgetting:.5g}"
        if self.kind == "spindle":
            per = "revolution" if self.teeth == 1 else f"tooth ({self.teeth} teeth)"
            return f"spindle phase per {per}, σ2 {self.sigma2:.3g}, {hyper}"
        if self.kind == "periodic":
            zm = " (zero mean)" if self.zero_mean else ""
            return f"periodic in time{zm}, ψ {self.period:.6g} s, σ2 {self.sigma2:.3g}, {hyper}"
        return f"time (squared exponential), {hyper}"

    def same_structure(self, other: TrackerChoice) -> bool:
        """Same kernel family and period (within 0.3 %) or tooth count."""
        if self.kind != other.kind:
            return False
        if self.kind == "periodic":
            return abs(math.log(self.period / other.period)) < 3e-3
        return self.kind != "spindle" or self.teeth == other.teeth


def for_beta(choice: TrackerChoice, base: TrackerChoice) -> TrackerChoice:
    """The tracker online β learns with while ``choice`` publishes the disturbance.

    ``base``, the model file's tracker, whose hyperparameters identification weighed against the drive's
    regressors (a flexible kernel tuned for prediction can take up the friction and damping β should see),
    except where the process brings what ``base`` cannot follow:

    * a spindle in the samples: its phase kernel, at ``base``'s σ1, γ and λ (σ2 too when ``base`` has one);
    * a disturbance ``base`` takes for noise — ``choice`` of another structure whose signal-to-noise ratio
      γ is :data:`STRONG_GAMMA` times ``base``'s or more: ``choice`` itself. In closed loop the command
      answers the disturbance, so a disturbance left in β's noise is correlated with the command and
      biases β (docs/method.md, "Online β keeps the model file's tracker"); the slow columns a flexible
      kernel explains are then reported as not determined rather than learned wrong.
    """
    if choice.kind == "spindle":
        if base.kind == "spindle" and choice.same_structure(base):
            return base
        sigma2 = base.sigma2 if base.kind != "time" else choice.sigma2
        return replace(choice, sigma1=base.sigma1, sigma2=sigma2, gamma=base.gamma, forgetting=base.forgetting)
    if choice.gamma < STRONG_GAMMA * base.gamma or choice.kind == "periodic" and choice.same_structure(base):
        return base
    return choice


def _clip(x: float, lo_hi: tuple[float, float]) -> float:
    return float(min(max(x, lo_hi[0]), lo_hi[1]))


# ---------------------------------------------------------------------------------------------
# spectra of the recent residual
# ---------------------------------------------------------------------------------------------
def harmonic_amplitudes(y: np.ndarray, t: np.ndarray, period: float, *, most: int = 64) -> np.ndarray:
    """Amplitude of each harmonic ``h/period`` (h = 1 … below Nyquist, at most ``most``) of ``y``
    sampled at times ``t`` (s): the Hann-windowed exact DFT at those frequencies."""
    y = np.asarray(y, dtype=np.float64)
    n = y.size
    Ts = float(np.median(np.diff(t))) if n > 1 else 1.0
    h_max = int(min(most, max(1.0, 0.5 * period / Ts)))
    w = np.hanning(n)
    yw = (y - y.mean()) * w
    return np.sqrt(_harmonic_powers(yw, np.asarray(t, dtype=np.float64) - t[0], 1.0 / period, h_max)) \
        * 2.0 / max(w.sum(), 1e-300)


def _harmonic_powers(yw: np.ndarray, tt: np.ndarray, f: float, h_max: int, e1: np.ndarray | None = None) -> np.ndarray:
    """``|Σ_k yw_k e^(−2πi h f tt_k)|²`` for h = 1 … ``h_max``: the phasor of harmonic h is the h-th power
    of the fundamental's ``e1 = e^(−2πi f tt)`` (given, or computed), one complex exponential per sample
    instead of one per sample and harmonic (the exponentials were most of an online search's time)."""
    if e1 is None:
        e1 = np.exp(-2j * np.pi * f * tt)
    z = yw.astype(np.complex128)
    out = np.empty(h_max)
    for h in range(h_max):
        z *= e1
        out[h] = abs(z.sum()) ** 2
    return out


def refine_period(y: np.ndarray, t: np.ndarray, period: float, *, rel: float = 0.01, harmonics: int = 8) -> float:
    """The period near ``period`` that maximises the power at its first ``harmonics`` harmonics

        S(f) = Σ_h |Σ_k w_k y_k e^(−2πi h f t_k)|²                                          (P2)

    (a 41-point grid over ``period·(1 ± rel)``, then a parabola through the best three): a
    periodogram peak is only as precise as its bin, and a locally periodic kernel whose period is
    off by 1 % loses the pattern within ~100 periods."""
    y = np.asarray(y, dtype=np.float64)
    t = np.asarray(t, dtype=np.float64)
    Ts = float(np.median(np.diff(t)))
    w = np.hanning(y.size)
    yw = (y - y.mean()) * w
    tt = t - t[0]
    f0 = 1.0 / period
    fs = np.linspace(f0 * (1.0 - rel), f0 * (1.0 + rel), 41)
    S = np.empty(fs.size)
    e1 = np.exp(-2j * np.pi * fs[0] * tt)
    step = np.exp(-2j * np.pi * (fs[1] - fs[0]) * tt)  # the grid is uniform: e1 of the next f is e1·step
    for i, f in enumerate(fs):
        S[i] = float(_harmonic_powers(yw, tt, f, int(np.sum(np.arange(1, harmonics + 1) * f < 0.5 / Ts)), e1).sum())
        e1 *= step
    i = int(np.argmax(S))
    f = fs[i]
    if 0 < i < fs.size - 1:
        a, b, c = S[i - 1], S[i], S[i + 1]
        den = a - 2.0 * b + c
        if den < 0.0:
            f += 0.5 * (a - c) / den * (fs[1] - fs[0])
    return 1.0 / f


def sigma2_of_harmonics(amp: np.ndarray) -> float:
    """σ2 for a periodic factor whose harmonics carry the energy of ``amp``: the periodic kernel's
    Fourier weights fall like ``exp(−2h²σ2²)``, so it holds harmonics up to ``h ≈ 1/σ2``;

        σ2 = 1/h₉₅,   h₉₅ the harmonic below which 95 % of the energy lies                  (P3)
    """
    e = np.asarray(amp, dtype=np.float64) ** 2
    if e.size == 0 or not e.sum() > 0.0:
        return 0.5
    h95 = int(np.searchsorted(np.cumsum(e) / e.sum(), 0.95)) + 1
    return _clip(1.0 / h95, SIGMA2_RANGE)


def signal_to_noise(y: np.ndarray, noise2: float, fallback: float) -> float:
    """γ from moments: ``(var y − σ_ε²)/σ_ε²`` (P4), the disturbance's power over the noise's;
    ``fallback`` without a noise level."""
    if not noise2 > 0.0:
        return fallback
    return _clip((float(np.var(y)) - noise2) / noise2, GAMMA_RANGE)


def spindle_orders(y: np.ndarray, theta: np.ndarray, *, most: int = 24) -> np.ndarray:
    """Amplitude of the residual at spindle orders 1 … ``most`` (per revolution), from the
    samples' spindle angles θ (rad): ``|Σ_k y_k e^(−i h θ_k)|·2/n``. Any sampling rate, any speed
    profile: the angle is known at every sample."""
    y = np.asarray(y, dtype=np.float64)
    h = np.arange(1, most + 1)
    return np.abs(np.exp(-1j * np.outer(h, theta)) @ (y - y.mean())) * 2.0 / max(y.size, 1)


def tooth_count(orders: np.ndarray, *, share: float = 0.8, largest: int = 8) -> int:
    """The largest tooth count Z ≤ ``largest`` such that the orders that are multiples of Z carry
    ``share`` of the energy of orders 1 … (a tool whose teeth cut alike repeats every 2π/Z);
    1 when none does."""
    e = np.asarray(orders, dtype=np.float64) ** 2
    total = float(e.sum())
    if not total > 0.0:
        return 1
    for z in range(min(largest, e.size), 1, -1):
        if float(e[z - 1::z].sum()) >= share * total:
            return z
    return 1


# ---------------------------------------------------------------------------------------------
# prequential evaluation (P1)
# ---------------------------------------------------------------------------------------------
def _tracker(choice: TrackerChoice, budget: int, jitter: float, Ts: float):
    from .krlst import KRLST

    kernel = choice.kernel()
    return KRLST(kernel, gamma=choice.gamma, forgetting=choice.forgetting, budget=budget, jitter=jitter,
                 grid_step=Ts if kernel.is_stationary_1d else None, refine=True)


def prequential(choice: TrackerChoice, X: np.ndarray, y: np.ndarray, *, budget: int, jitter: float, Ts: float):
    """A fresh tracker of ``choice`` fed ``(X[k], y[k])`` in the monitor's order: the predictive
    log-density of each ``y[k]`` before it was learned (P1; NaN for the first, the prior) and the
    tracker, armed at ``X[-1]`` after learning ``y[:-1]``. ``X``: (n, 2) times (s) and spindle
    angles (rad); a time kernel reads the first column."""
    trk = _tracker(choice, budget, jitter, Ts)
    xs = X if choice.spindle else X[:, 0]
    n = y.size
    mask = np.ones(n, dtype=bool)
    mask[0] = False
    res = trk.track_many(xs, np.concatenate(([np.nan], y[:-1])), mask)
    R = res["next_sigma_y2"] * res["s02"]               # s0² when x[k] was armed (after learning y[k − 1])
    with np.errstate(divide="ignore", invalid="ignore"):
        ll = -0.5 * (LOG_2PI + np.log(R) + (y - res["next_mean"]) ** 2 / R)
    ll[~np.isfinite(ll)] = np.nan
    return ll, trk


def _horizon(choice: TrackerChoice, budget: int, Ts: float) -> tuple[int, int]:
    """Samples of warm-up and of scoring a candidate needs: the dictionary filled and one period seen
    before scoring (a periodic kernel predicts a cycle from the one before), one period (at least 256
    samples) scored."""
    one = int(choice.period / Ts) if choice.kind == "periodic" else 0
    return max(budget, one, 256), max(256, one)


def _far(a: TrackerChoice, b: TrackerChoice) -> bool:
    """γ or σ2 differ by more than a factor 2: worth weighing as another start."""
    return abs(math.log(a.gamma / b.gamma)) > math.log(2.0) or abs(math.log(a.sigma2 / b.sigma2)) > math.log(2.0)


def _revolution(ring: Ring) -> float | None:
    """The spindle's period (s) over the recent ring when its speed is constant within 2 %, else None:
    from the speed the samples carried, else from the angle (unwrapped: below half a turn per sample)."""
    k = min(len(ring), 2048)
    if k < 16:
        return None
    rpm = None if ring.rpm is None else np.abs(ring.rpm[-k:])
    if rpm is not None and np.all(np.isfinite(rpm)):
        w = rpm * (2.0 * math.pi / 60.0)                                  # rad/s
    else:
        w = np.diff(np.unwrap(ring.theta[-k:])) / np.diff(ring.t[-k:])
    if not np.all(np.isfinite(w)):
        return None
    med = float(np.median(w))
    if not med > 0.0 or float(np.max(np.abs(w - med))) > 0.02 * med:
        return None
    return 2.0 * math.pi / med


def perturbations(c: TrackerChoice) -> list[TrackerChoice]:
    """The local search's neighbours of ``c``: one hyperparameter ×/÷ its factor, inside the ranges."""
    out = []
    steps = [("sigma2", 0.5), ("sigma2", 2.0)] if c.kind != "time" else []
    steps += [("gamma", 4.0), ("gamma", 0.25), ("sigma1", 2.0), ("sigma1", 0.5), ("memory", 2.0), ("memory", 0.5)]
    for name, f in steps:
        if name == "memory":
            m = c.memory * f
            if not MEMORY_RANGE[0] <= m <= MEMORY_RANGE[1]:
                continue
            out.append(replace(c, forgetting=1.0 - 1.0 / m))
            continue
        v = getattr(c, name) * f
        lo, hi = {"sigma1": SIGMA1_RANGE, "sigma2": SIGMA2_RANGE, "gamma": GAMMA_RANGE}[name]
        if lo <= v <= hi:
            out.append(replace(c, **{name: v}))
    return out


# ---------------------------------------------------------------------------------------------
# the policy
# ---------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class SearchSettings:
    """How the search trades reaction, cost and stability (sample counts at the stream's Ts)."""

    margin: float = 10.0          #: log-likelihood a candidate must gain over the primary (nats)
    first: float = 1.0            #: s of learned samples before the first search
    every: float = 4.0            #: s between two searches while the primary improves
    every_max: float = 16.0       #: s between two searches at most, after searches that found nothing
    retry: float = 0.25           #: s between two searches while the primary predicts poorly
    lag: float = 0.1              #: s of samples after its start at which a search's verdict applies
    retry_max: float = 2.0        #: s at most between them after searches that found nothing
    cooldown: float = 20.0        #: s before a structure that lost is tried again
    settle: float = 0.5           #: s after an adoption before the validity test uses the innovations
    grace: float = 1.0            #: s a poor prediction is left to the search before the validity test sees it
    replay_rate: float = 1.0      #: replayed samples allowed per learned sample (cost bound)
    replay_burst: float = 16.0    #: s of replayed samples the budget may save up
    short_tau: float = 0.1        #: s, EWMA of the innovations for the "predicts poorly" test
    poor: float = 9.0             #: that EWMA of ν² (or of e² over the noise variance) means "poorly"


@dataclass
class Ring:
    """The recent learned samples (oldest first): times ``t`` (s), spindle angles ``theta`` (rad; 0
    without spindle data), the residual ``y`` the primary learned, the commanded velocity ``ref`` (m/s;
    NaN where the samples carry none) for the motion-period test, and the count
    ``count`` of learned samples at the newest one."""

    t: np.ndarray
    theta: np.ndarray
    y: np.ndarray
    ref: np.ndarray
    count: int
    rpm: np.ndarray | None = None    #: the spindle speed θ was integrated with (rpm; NaN: none)
    spindle: bool = False        #: every sample of the ring carries a spindle angle

    def __len__(self) -> int:
        return int(self.y.size)

    @property
    def X(self) -> np.ndarray:
        return np.column_stack((self.t, self.theta))


@dataclass
class Verdict:
    """What one search decided: the choice to adopt (None: keep the primary), its replayed tracker
    (it learned the window but its newest sample, at which it is armed), its gain over the control
    (nats), the ring entries it was replayed on (the newest ``window``), and what was weighed (for
    the log)."""

    adopt: TrackerChoice | None = None
    tracker: object | None = None
    gain: float = 0.0
    window: int = 0
    weighed: list[tuple[TrackerChoice, float]] = field(default_factory=list)


class DisturbanceSearch:
    """The online search of the tracker's disturbance model (module docstring).

    Parameters are the primary's ``choice``, the stream's ``Ts`` (s), the tracker ``budget`` M and
    ``jitter``, the residual noise variance ``noise2`` ((m/s)², 0 when unknown), ``teeth`` (the
    model's tooth count, when it knows one) and the :class:`SearchSettings`. State after a tick:
    ``choice`` (the primary's), the counts ``next_tick``/``next_retry`` at which the compiled loop
    pauses for the next search, ``freeze_until`` (the model-validity test ignores the innovations before that count).
    """

    def __init__(self, choice: TrackerChoice, *, Ts: float, budget: int, jitter: float, noise2: float = 0.0,
                 teeth: int | None = None, settings: SearchSettings | None = None):
        self.choice = choice
        self.Ts = float(Ts)
        self.budget = int(budget)
        self.jitter = float(jitter)
        self.noise2 = float(noise2)
        self.teeth = int(teeth) if teeth else None
        self.s = settings or SearchSettings()
        n = self._n
        self.next_tick = n(self.s.first)
        self.next_retry = 0
        self.freeze_until = 0
        self._gap = n(self.s.every)
        self._retry_gap = n(self.s.retry)
        self._credit = float(n(self.s.replay_burst))
        self._counted = 0
        self._tried: dict[tuple, int] = {}
        self._queue: list[TrackerChoice] = []
        self._poor_since: int | None = None
        self.searches = 0
        self.adoptions = 0

    def _n(self, seconds: float) -> int:
        return max(1, int(round(seconds / self.Ts)))

    # ------------------------------------------------------------------ candidates
    def _fresh(self, key: tuple, count: int) -> bool:
        """The structure ``key`` was not weighed within the cooldown."""
        last = self._tried.get(key)
        return last is None or count - last >= self._n(self.s.cooldown)

    @staticmethod
    def _key(c: TrackerChoice) -> tuple:
        """What the cooldown remembers of a structural candidate."""
        if c.kind == "periodic":
            return ("period", round(math.log(c.period) / 3e-3))
        return (c.kind, c.teeth if c.kind == "spindle" else round(math.log(c.sigma1), 1))

    def _structural(self, ring: Ring, poor: bool) -> list[TrackerChoice]:
        c = self.choice
        out: list[TrackerChoice] = []
        count = ring.count
        if ring.spindle:
            out += self._spindle(ring, count)
        if not ring.spindle or poor:
            out += self._periods(ring, count)
        if c.kind == "periodic":
            k = min(len(ring), max(self._n(20.0 * c.period), 2048))
            psi = refine_period(ring.y[-k:], ring.t[-k:], c.period, rel=0.005)
            if abs(psi / c.period - 1.0) > 3e-4:
                out.append(replace(c, period=psi))
        if poor and c.kind != "time":
            for ell in (0.02, 0.1):
                if self._fresh(("time", round(math.log(ell), 1)), count):
                    out.append(TrackerChoice("time", sigma1=ell, gamma=signal_to_noise(ring.y[-512:], self.noise2,
                                                                                       c.gamma),
                                             forgetting=c.forgetting))
        return out

    def _spindle(self, ring: Ring, count: int) -> list[TrackerChoice]:
        """Spindle-phase candidates: per revolution, per tooth for the tooth count the residual's spindle
        orders show (and the model's), with σ2 from the orders that carry the energy (P3) and γ from the
        residual's power (P4) — and the primary's hyperparameters where it is one already."""
        c = self.choice
        k = min(len(ring), 2048)
        orders = spindle_orders(ring.y[-k:], ring.theta[-k:])
        teeth = {1, tooth_count(orders)} | ({self.teeth} if self.teeth else set())
        out = []
        gamma = signal_to_noise(ring.y[-k:], self.noise2, c.gamma)
        sigma1 = c.sigma1 if c.kind in ("periodic", "spindle") else SPINDLE_START["sigma1"]
        for z in sorted(teeth):
            start = TrackerChoice("spindle", sigma1=sigma1, sigma2=sigma2_of_harmonics(orders[z - 1::z]), gamma=gamma,
                                  forgetting=c.forgetting, teeth=z)
            if c.kind != "spindle":               # with spindle data, a primary of another kind always faces one
                out.append(start)
                continue
            if self._fresh(("spindle", z), count):
                if z != c.teeth:
                    out.append(replace(c, teeth=z))
                if _far(start, c):                # the data's own starting values, when far from the primary's
                    out.append(start)
        return out

    def _periods(self, ring: Ring, count: int) -> list[TrackerChoice]:
        """Periodic candidates from the periodogram of the recent residual: the best two of each window
        length (0.5 … 16 s; a window holds a period only when it holds five of its cycles, so each
        length finds other periods), each refined on its window (P2) and new or out of its cooldown."""
        found: list[tuple[float, int]] = []
        n = len(ring)
        for seconds in (16.0, 8.0, 4.0, 2.0, 1.0, 0.5):    # the longest windows first: the surest periods
            k = self._n(seconds)
            if k > n or k < 128:
                continue
            ref = ring.ref[-k:]
            try:
                cands, _ = detect_periods(ring.y[-k:], self.Ts, reference=ref if np.isfinite(ref).all() else None)
            except ValueError:
                continue
            for pc in cands[:2]:
                if not any(abs(math.log(pc.period / p)) < 0.01 for p, _ in found):
                    found.append((pc.period, k))
        out = []
        c = self.choice
        rev = _revolution(ring) if ring.spindle else None
        for psi, k in found:
            psi = refine_period(ring.y[-k:], ring.t[-k:], psi)
            if c.kind == "periodic" and abs(math.log(psi / c.period)) < 3e-3:
                continue
            if rev is not None and (sampled_harmonic(psi, rev, self.Ts) or harmonically_related(psi, rev, max_ratio=8)):
                continue                          # the spindle's own period: its phase kernel is the model
            if not self._fresh(("period", round(math.log(psi) / 3e-3)), count):
                continue
            amp = harmonic_amplitudes(ring.y[-k:], ring.t[-k:], psi)
            out.append(TrackerChoice("periodic", sigma1=_clip(max(1.2, 4.0 * psi), SIGMA1_RANGE),
                                     sigma2=sigma2_of_harmonics(amp), period=psi,
                                     gamma=signal_to_noise(ring.y[-k:], self.noise2, c.gamma),
                                     forgetting=c.forgetting, zero_mean=c.zero_mean))
        return out

    # ------------------------------------------------------------------ one search
    def tick(self, ring: Ring, poor: bool) -> Verdict:
        """Weigh candidates on ``ring`` and say what to adopt; schedules the next search."""
        count = ring.count
        self._credit = min(self._credit + self.s.replay_rate * (count - self._counted), float(self._n(self.s.replay_burst)))
        self._counted = count
        verdict = Verdict()
        short = self._n(self.s.first) - len(ring)
        if short > 0:                             # too little seen yet: come back when there is enough
            self.next_tick = self.next_retry = count + short
            return verdict
        self.searches += 1
        cands = [(c, True) for c in self._structural(ring, poor)]
        if not poor:
            if not self._queue:
                self._queue = perturbations(self.choice)
            if self._queue:
                cands.append((self._queue.pop(0), False))
        X = ring.X
        plan = []                                 # (candidate, warm-up, replay length), within the budget
        for cand, structural in cands:
            warm, score = _horizon(cand, self.budget, self.Ts)
            L = min(len(ring), warm + score)
            if L - warm < 64:
                continue
            plan.append((cand, structural, warm, L))
        # the control: the primary's own choice replayed fresh over the longest window, so that every
        # candidate is weighed against the same start (a tracker fed only recent samples predicts better
        # after a change of the process than one that remembers the time before it, whatever its kernel)
        L_ctl = max((L for *_, L in plan), default=0)
        if plan and L_ctl <= self._credit:
            self._credit -= L_ctl
            own, _ = prequential(self.choice, X[-L_ctl:], ring.y[-L_ctl:], budget=self.budget, jitter=self.jitter,
                                 Ts=self.Ts)
            for cand, structural, warm, L in plan:
                if L > self._credit:              # saved up for this one: nothing cheaper goes first
                    break
                self._credit -= L
                if structural:
                    self._tried[self._key(cand)] = count
                ll, trk = prequential(cand, X[-L:], ring.y[-L:], budget=self.budget, jitter=self.jitter, Ts=self.Ts)
                gain = float(np.nansum(ll[warm:] - own[-L:][warm:]))
                verdict.weighed.append((cand, gain))
                if gain > max(self.s.margin, verdict.gain):
                    verdict.adopt, verdict.tracker, verdict.gain, verdict.window = cand, trk, gain, L
        self._schedule(count, poor, verdict.adopt is not None, bool(verdict.weighed))
        if verdict.adopt is not None:
            self.adoptions += 1
            self.choice = verdict.adopt
            self._queue = []                      # the neighbours of the new choice
        return verdict

    def _schedule(self, count: int, poor: bool, adopted: bool, weighed: bool) -> None:
        """The next searches: sooner after an adoption, rarer after searches that weighed candidates
        and found nothing better (exponential back-off, up to ``every_max`` / ``retry_max``)."""
        n = self._n
        if adopted:
            self._gap = n(self.s.first)
            self._retry_gap = n(self.s.retry)
            self.freeze_until = count + n(self.s.settle)
            self._poor_since = None
        elif poor:
            self._retry_gap = min(2 * self._retry_gap, n(self.s.retry_max))
            if self._poor_since is None:
                self._poor_since = count
            # the validity test waits for the search while it may still find a model, for at most `grace`
            self.freeze_until = max(self.freeze_until, min(count + self._retry_gap, self._poor_since + n(self.s.grace)))
        else:
            if weighed:
                self._gap = min(2 * self._gap, n(self.s.every_max))
            self._poor_since = None
        if adopted or not poor:
            self.next_tick = count + self._gap
        self.next_retry = count + self._retry_gap
