"""Process monitors on the estimated feed force (N): pure numerics, no I/O.

The monitor service (:mod:`monitor.process_monitor`) hands each axis' estimate rows — force ``F(k)`` (N),
its calibrated standard deviation ``σ(k)`` (N), the spindle angle ``θ(k)`` (rad, unwrapped) — to
these steps and turns what they return into alarm messages. Every threshold is the larger of a
floor in newtons (or in a fraction of the cutting force) and ``k`` times a standard deviation that
is either the calibrated σ of the estimate or a spread learned from good data; ``k`` is the
monitor's sensitivity setting (larger: fewer alarms).

Steps (equation numbers used in the code):

* collision / overload (:func:`impulse_step`, per sample): with ``B(k) = max |F|`` over the previous
  ``W`` samples (the running peak, so the tooth-passing ripple and a feed step up to ``ratio`` × are
  nominal),

      alarm  ⇔  |F(k)| > L(k) = max(L_abs, ratio·B(k) + k·σ(k))                                   (M1)

  decided on the sample itself (detection latency 1 sample of the row); ``|F| > L_over`` on
  ``persist`` consecutive samples is an overload (M2);
* per tooth (:class:`ToothAccumulator`, :func:`tooth_fit`): over each spindle revolution the least-squares
  fit ``F(θ) ≈ a0 + Σ_{m ∈ {1, N_t}} (a_m cos mθ + b_m sin mθ)`` (M3) from its normal equations,
  summed over the last two revolutions (5 parameters from ≥ 2·N_t samples, any sampling phase). A
  tool with ``N_t`` equal teeth makes only orders ``N_t, 2N_t, …``; a once-per-revolution amplitude
  ``A1 = √(a1² + b1²)`` (N) is runout (chip thickness differs by ``2ρ`` between teeth, independent of
  the feed) or a tooth that cuts less than the next. Against ``Ā1, s1`` learned over the first cutting
  revolutions:

      broken tooth  ⇔  A1 − Ā1 > L_b  and  A1 − Ã1 > L_b   on 2 revolutions in a row,
                       L_b = max(q_b·a0, k·s1)                                                        (M4)
      runout        ⇔  mean of the last 4 revolutions' A1 − Ā1 > max(q_r·a0, k·s1/2)                 (M5)

  with ``Ã1`` the median ``A1`` of the ``STEP_WINDOW`` cutting revolutions before the first one over the
  limit: a breakage is a step within a revolution or two, a runout grows over hundreds. Without the step
  test a runout that had grown slowly past ``L_b`` (or met a smaller ``a0`` after a feed change, which
  lowers ``L_b``) was called a broken tooth;

  with ``a0`` the mean cutting force; a tooth force that drops to zero makes ``A1 ≈ 2a0/N_t·…`` far above
  ``q_b a0`` (``q_b`` = 0.5), a runout growing by 30 % of the tooth force makes ``ΔA1 ≈ 0.3 a0``
  (``q_r`` = 0.15);
* envelope (:func:`envelope_step`, per sample): the reference over program progress ``p`` (s since the
  section began), bin ``i = ⌊p/Δp⌋``, band ``μ_i ± max(b_min, k·√(s_i² + σ²))`` (M6); below the band where
  ``μ_i`` is a cut (``μ_i`` above ``cut_min``) for ``persist`` samples: missing cut; above it likewise: over band;
* wear (:func:`wear_trend`, per part): least-squares slope of a section's mean force over the last parts,
  ``t = slope/se(slope)`` and the rise over the window relative to the fit's start (M7).
"""

from __future__ import annotations

import math
from collections import deque

import numpy as np
from numba import njit

from .errors import ParameterError

__all__ = ["IMPULSE_STATE", "new_impulse_state", "impulse_step", "impulse_band", "ToothAccumulator", "tooth_fit",
           "ToothDetector", "envelope_step", "envelope_band", "new_envelope_state", "wear_trend"]

# ---- collision / overload (M1, M2) ------------------------------------------------------------------------
#: layout of the impulse monitor's float state: these slots, then a ring of |F| (``window`` values), then the
#: angle profile (``bins`` values and ``bins`` hit counts), then the slow profile (``bins`` values)
IMPULSE_STATE = ("window", "bins", "filled", "pos", "over_run", "holdoff", "sd_ew")
_I_W, _I_BINS, _I_FILLED, _I_POS, _I_OVER, _I_HOLD, _I_SD = range(len(IMPULSE_STATE))
#: weight of a new row's σ in the σ the limit uses: the tracker's σ grows on the very rows of an impulse
#: (a surprise), so the limit takes the σ of the rows before it
SD_WEIGHT = 0.05
SLOW_WEIGHT = 0.005
#: weight of a new sample in the slow angle profile (per hit of its bin: a time constant of seconds), which
#: remembers the cut through an air cut — the return of the cut is not an impulse
_I_SLOTS = len(IMPULSE_STATE)


def new_impulse_state(window: int, bins: int = 12) -> np.ndarray:
    """The impulse monitor's state (:data:`IMPULSE_STATE`): ``window`` samples of running peak, ``bins`` angle bins."""
    if not 2 <= int(window) <= 100_000:
        raise ParameterError(f"window {window!r} samples out of range: 2 … 100000", "window")
    if not 4 <= int(bins) <= 720:
        raise ParameterError(f"bins {bins!r} out of range: 4 … 720", "bins")
    st = np.zeros(_I_SLOTS + int(window) + 3 * int(bins))
    st[_I_W], st[_I_BINS] = window, bins
    return st


@njit(cache=True, nogil=True)
def _angle_limit(state, ratio_angle, k_sigma, limit_abs):
    """The collision limit on ``|F − P(θ)|`` (M1, with the angle): ``max(L_abs, ratio_angle·max|P| + k·σ̄)``."""
    w, bins = int(state[_I_W]), int(state[_I_BINS])
    prof, hits, slow = _I_SLOTS + w, _I_SLOTS + w + bins, _I_SLOTS + w + 2 * bins
    pmax = 0.0
    for j in range(bins):
        if state[hits + j] > 0.0:
            pmax = max(pmax, abs(state[prof + j]), abs(state[slow + j]))
    return max(limit_abs, ratio_angle * pmax + k_sigma * state[_I_SD])


@njit(cache=True, nogil=True)
def _peak_limit(state, ratio, k_sigma, limit_abs):
    """The collision limit on ``|F|`` (M1, without the angle): ``max(L_abs, ratio·B + k·σ̄)``."""
    w = int(state[_I_W])
    peak = 0.0
    for j in range(w):
        if state[_I_SLOTS + j] > peak:
            peak = state[_I_SLOTS + j]
    return max(limit_abs, ratio * peak + k_sigma * state[_I_SD])


@njit(cache=True, nogil=True)
def impulse_band(state, ratio, ratio_angle, k_sigma, limit_abs):
    """The force range the collision test (M1) passes as it stands (for the dashboard), ``(low, high)`` N:
    with an angle profile ``[min P − L, max P + L]`` over the bins seen (a force outside is a collision at
    any angle), without it ``±L``; NaN before the running peak is filled."""
    w, bins = int(state[_I_W]), int(state[_I_BINS])
    if state[_I_FILLED] < w:
        return math.nan, math.nan
    prof, hits, slow = _I_SLOTS + w, _I_SLOTS + w + bins, _I_SLOTS + w + 2 * bins
    lo, hi = math.inf, -math.inf
    for j in range(bins):
        if state[hits + j] >= 3.0:
            lo = min(lo, state[prof + j], state[slow + j])
            hi = max(hi, state[prof + j], state[slow + j])
    if hi >= lo:
        lim = _angle_limit(state, ratio_angle, k_sigma, limit_abs)
        return lo - lim, hi + lim
    lim = _peak_limit(state, ratio, k_sigma, limit_abs)
    return -lim, lim


@njit(cache=True, nogil=True)
def impulse_step(state, theta, force, sd, ratio, ratio_angle, k_sigma, limit_abs, limit_over, persist, alpha,
                 out_kind, out_value, out_limit):
    """Collision (M1) and overload (M2) over a block of rows; returns the number of alarms written.

    With the spindle angle ``θ`` (rad, NaN: unknown) the expected force ``P(θ)`` is an exponentially weighted
    profile over angle bins (weight ``alpha`` per hit) and the test is on ``|F − P(θ)|`` against
    ``max(L_abs, ratio_angle·max|P| + k·σ)`` (the tooth-passing ripple is expected, not an impulse);
    without it on ``|F|`` against ``max(L_abs, ratio·B + k·σ)``, ``B`` the running peak of the last ``window``
    rows (M1). A second, slow profile (:data:`SLOW_WEIGHT`) remembers the cut: the deviation is the smaller of
    the two and the limit uses the larger profile, so the return of the cut after an air cut is expected.
    ``force``, ``sd`` (N), NaN = no estimate (skipped). ``out_kind`` 0 collision, 1 overload,
    −1 none; ``out_value`` the tested magnitude, ``out_limit`` its limit (N). After a collision ``window``
    rows pass before the next (the impulse is in the peak and the profile)."""
    w, bins = int(state[_I_W]), int(state[_I_BINS])
    ring, prof, hits, slow = _I_SLOTS, _I_SLOTS + w, _I_SLOTS + w + bins, _I_SLOTS + w + 2 * bins
    two_pi = 2.0 * math.pi
    n_alarm = 0
    for i in range(force.size):
        out_kind[i] = -1
        f = force[i]
        if not math.isfinite(f):
            continue
        a = abs(f)
        th = theta[i]
        b = -1
        if math.isfinite(th):
            b = int(((th % two_pi) / two_pi) * bins) % bins
        filled = int(state[_I_FILLED])
        if state[_I_HOLD] > 0.0:
            state[_I_HOLD] -= 1.0
        elif filled >= w:
            if b >= 0 and state[hits + b] >= 3.0:
                lim = _angle_limit(state, ratio_angle, k_sigma, limit_abs)  # (M1), with the angle
                d = min(abs(f - state[prof + b]), abs(f - state[slow + b]))
            else:
                lim = _peak_limit(state, ratio, k_sigma, limit_abs)  # (M1), without
                d = a
            if d > lim:
                out_kind[i], out_value[i], out_limit[i] = 0, d, lim
                n_alarm += 1
                state[_I_HOLD] = w
        if a > limit_over:  # (M2)
            state[_I_OVER] += 1.0
            if state[_I_OVER] == persist and out_kind[i] < 0:
                out_kind[i], out_value[i], out_limit[i] = 1, a, limit_over
                n_alarm += 1
        else:
            state[_I_OVER] = 0.0
        pos = int(state[_I_POS])
        state[ring + pos] = a
        state[_I_POS] = (pos + 1) % w
        if filled < w:
            state[_I_FILLED] = filled + 1
        if math.isfinite(sd[i]) and out_kind[i] != 0 and state[_I_HOLD] <= 0.0:
            state[_I_SD] = sd[i] if state[_I_SD] == 0.0 else state[_I_SD] + SD_WEIGHT * (sd[i] - state[_I_SD])
        if b >= 0 and out_kind[i] != 0:  # the profile follows the cut (not the impulse itself)
            if state[hits + b] == 0.0:
                state[prof + b] = f
                state[slow + b] = f
            else:
                state[prof + b] += alpha * (f - state[prof + b])
                state[slow + b] += SLOW_WEIGHT * (f - state[slow + b])
            state[hits + b] += 1.0
    return n_alarm


# ---- per tooth (M3) ----------------------------------------------------------------------------------------
#: the fitted terms of (M3): a0, a1, b1, a_N, b_N
FIT_TERMS = 5


@njit(cache=True, nogil=True)
def _accumulate(normal, rhs, theta, f, teeth):
    """Add one sample to the normal equations of (M3)."""
    z0, z1, z2 = 1.0, math.cos(theta), math.sin(theta)
    z3, z4 = math.cos(teeth * theta), math.sin(teeth * theta)
    z = (z0, z1, z2, z3, z4)
    for r in range(5):
        rhs[r] += z[r] * f
        for c in range(5):
            normal[r, c] += z[r] * z[c]


@njit(cache=True, nogil=True)
def tooth_fit(normal, rhs, out):
    """Solve the 5×5 normal equations of (M3) (Cholesky, ridge 1e-9·trace); writes a0, a1, b1, aN, bN into
    ``out``; returns False when the samples do not determine the fit (too few, or all at one angle)."""
    n = 5
    L = np.zeros((n, n))
    ridge = 1e-9 * (normal[0, 0] + 1.0)
    for j in range(n):
        s = normal[j, j] + ridge
        for k in range(j):
            s -= L[j, k] * L[j, k]
        if s <= 1e-6 * (normal[0, 0] + 1.0):
            return False
        L[j, j] = math.sqrt(s)
        for i in range(j + 1, n):
            s2 = normal[i, j]
            for k in range(j):
                s2 -= L[i, k] * L[j, k]
            L[i, j] = s2 / L[j, j]
    y = np.zeros(n)
    for i in range(n):
        s = rhs[i]
        for k in range(i):
            s -= L[i, k] * y[k]
        y[i] = s / L[i, i]
    for i in range(n - 1, -1, -1):
        s = y[i]
        for k in range(i + 1, n):
            s -= L[k, i] * out[k]
        out[i] = s / L[i, i]
    return True


#: layout of :class:`ToothAccumulator`'s state: normal equations and right-hand side of the current and
#: the previous revolution, the current revolution number and sample count, then the angle profile's
#: sums and counts (``bins`` each)
_N_CUR, _R_CUR, _N_PREV, _R_PREV, _REV, _CNT, _PROF = 0, 25, 30, 55, 60, 61, 62


@njit(cache=True, nogil=True)
def _finish_revolution(acc, teeth, bins, row, prof):
    """Fit (M3) over this and the previous revolution; the per-tooth peaks and the angle profile of this one.
    Returns False when the fit is not determined."""
    normal = acc[_N_CUR:_N_CUR + 25].reshape((5, 5)) + acc[_N_PREV:_N_PREV + 25].reshape((5, 5))
    rhs = acc[_R_CUR:_R_CUR + 5] + acc[_R_PREV:_R_PREV + 5]
    coef = np.zeros(5)
    if not tooth_fit(normal, rhs, coef):
        return False
    row[1] = coef[0]
    row[2] = math.sqrt(coef[1] ** 2 + coef[2] ** 2)
    row[3] = math.sqrt(coef[3] ** 2 + coef[4] ** 2)
    row[4] = acc[_CNT]
    phase = math.atan2(coef[4], coef[3]) / teeth  # spindle angle of a tooth's peak (order N_t)
    for j in range(teeth):
        row[5 + j] = np.nan
    for b in range(bins):
        cnt = acc[_PROF + bins + b]
        if cnt > 0:
            mean = acc[_PROF + b] / cnt
            prof[b] = mean
            ang = (b + 0.5) * 2.0 * math.pi / bins
            rel = (ang - phase + math.pi / teeth) % (2.0 * math.pi)
            j = int(rel * teeth / (2.0 * math.pi)) % teeth
            if not (row[5 + j] >= mean):
                row[5 + j] = mean
        else:
            prof[b] = np.nan
    return True


@njit(cache=True, nogil=True)
def tooth_block(theta, force, teeth, bins, acc, rev_out, prof_out):
    """Per-revolution records of a block of rows (the state ``acc`` is carried from block to block).

    For each revolution that ends in the block (the next sample is in the next revolution) one row of
    ``rev_out`` gets: the index of the row that ended it, a0, A1, A_N (N), the revolution's sample count,
    then the ``teeth`` per-tooth peaks of the angle profile (N; sector ``2π/N_t`` around each peak of the
    fitted order N_t); ``prof_out`` its mean force per angle bin (NaN: no sample). A revolution needs
    ``2·N_t`` samples; a jump of the angle (backwards, or more than a revolution) starts afresh.
    Returns the number of rows written."""
    nrev = 0
    two_pi = 2.0 * math.pi
    for i in range(theta.size):
        th, f = theta[i], force[i]
        if not (math.isfinite(th) and math.isfinite(f)):
            continue
        rev = math.floor(th / two_pi)
        if acc[_CNT] == 0.0 and acc[_N_CUR] == 0.0:
            acc[_REV] = rev
        cur = acc[_REV]
        if rev != cur:
            next_one = rev == cur + 1.0
            if next_one and acc[_CNT] >= 2 * teeth and nrev < rev_out.shape[0]:
                if _finish_revolution(acc, teeth, bins, rev_out[nrev], prof_out[nrev]):
                    rev_out[nrev, 0] = i
                    nrev += 1
            if next_one:  # this revolution's sums become the previous ones
                acc[_N_PREV:_R_PREV + 5] = acc[_N_CUR:_R_CUR + 5]
            else:
                acc[_N_PREV:_R_PREV + 5] = 0.0
            acc[_N_CUR:_R_CUR + 5] = 0.0
            acc[_PROF:_PROF + 2 * bins] = 0.0
            acc[_REV] = rev
            acc[_CNT] = 0.0
        _accumulate(acc[_N_CUR:_N_CUR + 25].reshape((5, 5)), acc[_R_CUR:_R_CUR + 5], th, f, teeth)
        acc[_CNT] += 1.0
        b = int(((th % two_pi) / two_pi) * bins) % bins
        acc[_PROF + b] += f
        acc[_PROF + bins + b] += 1.0
    return nrev


class ToothAccumulator:
    """Per-revolution fit (M3) and angle profile of one axis' force; ``update(theta, force)`` returns the
    revolutions that ended: ``rows`` (row index, a0, A1, A_N, samples, per-tooth peaks …) and ``profiles``
    (mean force per angle bin, N)."""

    def __init__(self, teeth: int = 2, bins: int = 36, max_revolutions: int = 4096) -> None:
        if not 1 <= int(teeth) <= 32:
            raise ParameterError(f"teeth {teeth!r} out of range: 1 … 32", "teeth")
        if not 4 <= int(bins) <= 720:
            raise ParameterError(f"bins {bins!r} out of range: 4 … 720", "bins")
        self.teeth, self.bins, self.max_revolutions = int(teeth), int(bins), int(max_revolutions)
        self.acc = np.zeros(_PROF + 2 * self.bins)

    def update(self, theta: np.ndarray, force: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        n = max(1, min(self.max_revolutions, theta.size))
        rows = np.full((n, 5 + self.teeth), np.nan)
        prof = np.full((n, self.bins), np.nan)
        k = tooth_block(np.ascontiguousarray(theta, dtype=np.float64), np.ascontiguousarray(force, dtype=np.float64),
                        self.teeth, self.bins, self.acc, rows, prof)
        return rows[:k], prof[:k]


#: cutting revolutions whose median A1 is the step test's baseline Ã1 (M4)
STEP_WINDOW = 10
#: cutting revolutions in a row whose mean A1 the runout test judges (M5)
RUNOUT_WINDOW = 4


class ToothDetector:
    """Broken tooth (M4) and runout (M5) from the per-revolution records of :class:`ToothAccumulator`.

    ``learn`` cutting revolutions (``a0 > cut_min`` N) set ``Ā1`` and its spread ``s1``, after ``settle``
    cutting revolutions in a row (the tool's entry into the cut, where ``A1`` grows with the engagement);
    after that the reference is fixed for the run (a slow growth is what the runout test is for). ``sensitivity`` is ``k``;
    ``widen`` (≥ 1) multiplies every threshold (an operator's false-alarm acknowledgement)."""

    def __init__(self, *, learn: int = 30, cut_min: float = 5.0, sensitivity: float = 6.0,
                 broken_fraction: float = 0.5, runout_fraction: float = 0.1, settle: int = 25) -> None:
        if not 5 <= int(learn) <= 100_000:
            raise ParameterError(f"learn {learn!r} revolutions out of range: 5 … 100000", "learn")
        self.learn, self.cut_min, self.k = int(learn), float(cut_min), float(sensitivity)
        self.qb, self.qr = float(broken_fraction), float(runout_fraction)
        self.widen = 1.0
        self.settle = int(settle)
        self._cutting = 0  # cutting revolutions in a row
        self._a1: list[float] = []
        self.mean1 = math.nan
        self.sd1 = math.nan
        self._run = 0  # judged (learned) cutting revolutions in a row: the runout window needs RUNOUT_WINDOW
        self._over = 0
        #: A1 of the last cutting revolutions (not cleared by a pause: the same tool), the step baseline (M4)
        self._history: deque[float] = deque(maxlen=STEP_WINDOW + RUNOUT_WINDOW)
        self._step_base = math.nan  # Ã1, frozen at the first revolution over the limit
        self.latched: set[str] = set()

    @property
    def learned(self) -> bool:
        return math.isfinite(self.mean1)

    def limits(self, a0: float) -> tuple[float, float]:
        """The limits on ``A1 − Ā1`` (N) at mean force ``a0``: broken tooth (M4) and runout (M5); NaN while
        learning."""
        lim_b = self.widen * max(self.qb * a0, self.k * self.sd1)  # (M4)
        lim_r = self.widen * max(self.qr * a0, self.k * self.sd1 / 2.0)  # (M5)
        return lim_b, lim_r

    def update(self, a0: float, a1: float) -> list[tuple[str, float, float]]:
        """One revolution; returns the alarms ``(kind, measured excess ΔA1 (N), limit (N))`` it raised."""
        if not (math.isfinite(a0) and math.isfinite(a1)) or a0 <= self.cut_min:
            self._run = 0
            self._over = 0
            self._cutting = 0
            return []
        self._cutting += 1
        if not self.learned:
            if self._cutting <= self.settle:
                return []
            self._a1.append(a1)
            self._history.append(a1)
            if len(self._a1) >= self.learn:
                x = np.array(self._a1)
                self.mean1, self.sd1 = float(x.mean()), float(x.std(ddof=1))
            return []
        out = []
        d = a1 - self.mean1
        lim_b, lim_r = self.limits(a0)
        if d > lim_b and self._over == 0:
            self._step_base = self._baseline(skip=0)
        step = a1 - self._step_base if self._over or d > lim_b else 0.0
        self._over = self._over + 1 if d > lim_b and step > lim_b else 0
        if self._over >= 2 and "broken_tooth" not in self.latched:
            self.latched.add("broken_tooth")
            out.append(("broken_tooth", step, lim_b))
        self._run += 1
        if self._run >= RUNOUT_WINDOW:            # the window: this revolution and the last ones of the history
            recent = [*list(self._history)[len(self._history) - (RUNOUT_WINDOW - 1):], a1]
            dm = sum(recent) / RUNOUT_WINDOW - self.mean1
            # a step above the broken-tooth limit within the window is a breakage on its way, not runout
            steady = max(recent) - self._baseline(skip=RUNOUT_WINDOW - 1) <= lim_b
            if dm > lim_r and steady and "runout" not in self.latched and "broken_tooth" not in self.latched:
                self.latched.add("runout")
                out.append(("runout", dm, lim_r))
        self._history.append(a1)
        return out

    def _baseline(self, skip: int) -> float:
        """Ã1: the median A1 of up to ``STEP_WINDOW`` cutting revolutions, leaving out the last ``skip``
        (the learned Ā1 while there are none)."""
        h = list(self._history)
        h = h[:len(h) - skip][-STEP_WINDOW:]
        return float(np.median(h)) if h else self.mean1


# ---- envelope (M6) ------------------------------------------------------------------------------------------
def new_envelope_state() -> np.ndarray:
    """``[below_run, above_run, latched_below, latched_above]``."""
    return np.zeros(4)


@njit(cache=True, nogil=True)
def _envelope_band(mean, spread, sd, k_sigma, band_min):
    """The band (M6) of one reference bin, ``μ ± max(b_min, k·√(s² + σ²))`` (σ NaN: 0)."""
    s = sd if math.isfinite(sd) else 0.0
    half = max(band_min, k_sigma * math.sqrt(spread ** 2 + s * s))
    return mean - half, mean + half


def envelope_band(progress: float, sd: float, mean: np.ndarray, spread: np.ndarray, bin_s: float, k_sigma: float,
                  band_min: float) -> tuple[float, float]:
    """The band (M6) at ``progress`` s into the section (for the dashboard); NaN outside the reference."""
    if not (math.isfinite(progress) and progress >= 0.0):
        return math.nan, math.nan
    b = int(progress / bin_s)
    if b >= mean.size:
        return math.nan, math.nan
    return _envelope_band(float(mean[b]), float(spread[b]), float(sd), float(k_sigma), float(band_min))


@njit(cache=True, nogil=True)
def envelope_step(state, progress, force, sd, mean, spread, bin_s, k_sigma, band_min, cut_min, persist,
                  out_kind, out_value, out_limit):
    """Compare rows with a reference (M6); returns the number of alarms. ``progress`` (s into the section),
    ``mean``, ``spread`` (N) per bin of ``bin_s`` s; out_kind 0 missing cut, 1 over band, −1 none. An alarm
    latches until the section ends (the caller resets ``state``)."""
    n_alarm = 0
    for i in range(force.size):
        out_kind[i] = -1
        f, p = force[i], progress[i]
        if not (math.isfinite(f) and math.isfinite(p)) or p < 0.0:
            continue
        b = int(p / bin_s)
        if b >= mean.size:
            state[0] = 0.0
            state[1] = 0.0
            continue
        lo, hi = _envelope_band(mean[b], spread[b], sd[i], k_sigma, band_min)
        if f < lo and mean[b] > cut_min:
            state[0] += 1.0
            if state[0] >= persist and state[2] == 0.0:
                state[2] = 1.0
                out_kind[i], out_value[i], out_limit[i] = 0, f, lo
                n_alarm += 1
        else:
            state[0] = 0.0
        if f > hi:
            state[1] += 1.0
            if state[1] >= persist and state[3] == 0.0 and out_kind[i] < 0:
                state[3] = 1.0
                out_kind[i], out_value[i], out_limit[i] = 1, f, hi
                n_alarm += 1
        else:
            state[1] = 0.0
    return n_alarm


# ---- wear (M7) ----------------------------------------------------------------------------------------------
def wear_trend(values: np.ndarray) -> tuple[float, float, float]:
    """Least-squares line through one section's per-part values (mean force, N, or cut energy, J), oldest
    first: returns ``(t, rise, sd)``: the slope's t statistic, the fitted rise over the window relative to
    the fitted first value, and the residual standard deviation (NaN with fewer than 3 parts) (M7)."""
    y = np.asarray(values, dtype=np.float64)
    y = y[np.isfinite(y)]
    n = y.size
    if n < 3:
        return math.nan, math.nan, math.nan
    x = np.arange(n, dtype=np.float64)
    xm, ym = x.mean(), y.mean()
    sxx = float(((x - xm) ** 2).sum())
    slope = float(((x - xm) * (y - ym)).sum() / sxx)
    first = ym - slope * xm
    res = y - (first + slope * x)
    sd = math.sqrt(float((res ** 2).sum()) / (n - 2)) if n > 2 else math.nan
    se = sd / math.sqrt(sxx) if sd > 0 else 1e-300
    rise = slope * (n - 1) / first if first > 0 else math.nan
    return slope / se, rise, sd
