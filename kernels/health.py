"""Health statistics of one axis: parameter drift and model validity (method §9).

Pure numerics: a per-sample ``@njit`` step on the normalised innovation and a per-tick (about once a
second) verdict on the online physical parameters, allocation-free over a :class:`HealthState` of plain
arrays, plus the thin Python class :class:`HealthMonitor`. Levels: 0 ``ok``, 1 ``warn``, 2 ``alarm``.

Model validity (per sample)
---------------------------
Input: the normalised innovation ``ν(k) = e(k)/√S(k)`` of the joint tracker (:mod:`kernels.beta_tracker`:
``e = v_m(k+1) − β̂ᵀz(k) − f̂(k)``, ``S = s0²σ_y² + z̃ᵀPz̃``). When the model explains the data ``ν`` has
unit variance (KRLS-T's ``s0²`` is the running mean of ``e²/σ_y²``, eq. 2.20); a disturbance the model
cannot explain makes ``ν²`` large for as long as it lasts.

    c(k) = min(ν(k)², c_max)                                 clipped square (one outlier ≤ c_max)
    m(k) = m(k−1) + a (c(k) − m(k−1)),  a = 1 − exp(−Ts/τ)   EWMA of ν², time constant τ
    warn  while m ≥ θ_warn  for ≥ t_persist (and until m < θ_clear for ≥ t_hold)
    alarm while m ≥ θ_alarm for ≥ t_persist (and until m < θ_warn for ≥ t_hold)

Defaults ``τ = 0.5 s``, ``θ_warn = 5``, ``θ_alarm = 8``, ``θ_clear = 3``, ``c_max = 16``, ``t_persist =
0.25 s``, ``t_hold = 2 s``. For white ``ν`` the EWMA has mean 1 and standard deviation ``√(2a/(2−a))``
(≈ 0.078 at 333 Hz), so the threshold is set by the *nominal* non-white behaviour of real streams, with a
margin; the clipping bounds one sample's share and the persistence rejects bursts. ``s0²`` is a cumulative
mean: after a persistent change the verdict returns to ok once the tracker has adapted. A whiteness test
is not used: its nominal value depends on the noise structure and the tracker.

Parameter drift (per tick)
--------------------------
For each physical parameter j (inertia, damping, Coulomb ±, offset) with model-file value ``θ_j⁰ ± s_j⁰``
and online value ``θ̂_j ± ŝ_j``:

    z_j = (θ̂_j − θ_j⁰) / √(ŝ_j² + s_j⁰²)            drift in combined standard errors
    r_j = |θ̂_j − θ_j⁰| / scale_j                       relative drift (scale: |θ_j⁰|, or the
                                                       friction scale for Coulomb and offset)
    determined_j:  ŝ_j ≤ κ · ŝ_j^prior                 the data at least halved the prior s.e.
    warn  when determined, |z| ≥ z_warn  and r ≥ r_warn;  cleared when |z| < z_clear or r < r_warn/2
    alarm when determined, |z| ≥ z_alarm and r ≥ r_alarm; back to warn when |z| < z_warn or r < r_alarm/2

Defaults ``z_warn = 6``, ``z_alarm = 8``, ``z_clear = 4``, ``r_warn = 0.03``, ``r_alarm = 0.15``, ``κ = 0.5``.
With β memories of 5–10 s a year holds ~3·10⁷ independent looks for five parameters, so the largest |z|
of honest standard errors is ≈ 6: ``z_warn = 6`` with ``P(|z| > 6) = 2·10⁻⁹``. The relative threshold makes
a report practically as well as statistically significant (a high-SNR drive would otherwise alarm on
irrelevant deviations); 3 % because a parameter moves only while it is excited, so the first acceleration
after a step shows a fraction of it. The gap between ``z_warn`` and ``z_clear`` (hysteresis) keeps a
parameter at the threshold from flapping. A parameter the data do not determine is reported with its
uncertainty and never raises a drift warning. The measurements behind the defaults:
``docs/design-decisions.md``, "Kernels".
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields

import numpy as np
from numba import njit

from ._snapshot import fill_views
from .layout import Field, Layout

__all__ = ["HealthConfig", "HEALTH_RANGES", "HealthState", "HealthMonitor", "Verdict", "new_health_buffers",
           "health_state_views", "health_state_of", "validate_health_state", "health_sample", "health_tick",
           "LEVELS", "REASONS", "PARAMS", "STATE_FIELDS", "describe"]

LEVELS = ("ok", "warn", "alarm")
#: the drift-tested physical parameters (indices into :data:`kernels.beta_tracker.PHYSICAL`; the symmetric
#: Coulomb friction too — the one a trial without rest determines), then the fast inertia estimate
#: (:func:`kernels.beta_tracker.fast_inertia`, against the model file's inertia), tested for an abrupt
#: change (a payload): alarm only, at the alarm thresholds
PARAMS = ("inertia", "damping", "coulomb_pos", "coulomb_neg", "coulomb", "offset", "inertia_step")
PHYS_INDEX = (0, 1, 2, 3, 4, 5, 0)
STEP = len(PARAMS) - 1
#: reasons, in the order of ``HealthState.level``
REASONS = ("innovation",) + PARAMS
N_REASON = len(REASONS)

# par slots
(Q_A, Q_CLIP, Q_THW, Q_THA, Q_THC, Q_NPERS, Q_NHOLD, Q_ZW, Q_ZA, Q_ZC, Q_RW, Q_RA, Q_KAPPA,
 Q_WARMUP) = range(14)
N_QPAR = 14
# acc slots
(A_EWMA, A_SEEN, A_RUN_W, A_RUN_A, A_RUN_CLR, A_RUN_DOWN, A_WSUM, A_WN, A_WMAX) = range(9)
N_ACC = 9
# per-parameter statistics rows of ``stat``
S_Z, S_REL, S_DET = range(3)


#: each setting's range ``(lo, hi, open_low, what it is and trades)``, the one definition:
#: :meth:`HealthConfig.validate` checks it and ``monitor.online_settings.Health`` (the model file's
#: ``[health]``) declares its fields with it. Cross-field rules come on top (:meth:`HealthConfig.validate`).
HEALTH_RANGES: dict[str, tuple[float, float, bool, str]] = {
    "tau": (0.05, 10.0, False, "s, EWMA time constant of ν² (detection delay vs noise)"),
    "clip": (2.0, 20.0, False, "|ν| clip, standard deviations (one outlier's weight)"),
    "warn": (1.0, 400.0, False, "EWMA level of ν² for warn (false alarms vs detection)"),
    "alarm": (1.0, 400.0, False, "EWMA level of ν² for alarm"),
    "clear": (1.0, 400.0, False, "EWMA level below which warn clears (hysteresis)"),
    "persist": (0.0, 10.0, False, "s above a level before it counts (bursts vs delay)"),
    "hold": (0.0, 60.0, False, "s below before a level clears (flapping vs staying up)"),
    "z_warn": (0.1, 1000.0, False, "drift: standard errors for warn"),
    "z_alarm": (0.1, 1000.0, False, "drift: standard errors for alarm"),
    "z_clear": (0.1, 1000.0, False, "drift: standard errors below which warn clears"),
    "rel_warn": (0.0, 10.0, False, "drift: relative change for warn"),
    "rel_alarm": (0.0, 10.0, False, "drift: relative change for alarm"),
    "kappa": (0.0, 1.0, True, "determined: online s.e. ≤ kappa × prior s.e."),
    "warmup": (0.0, 3600.0, False, "s of innovations ignored after the start"),
}


@dataclass(frozen=True)
class HealthConfig:
    """Health thresholds (see the module docstring for what each trades; ranges :data:`HEALTH_RANGES`);
    SI units, seconds."""

    tau: float = 0.5            # s, EWMA time constant of ν²
    clip: float = 4.0           # |ν| clip (standard deviations)
    warn: float = 5.0           # EWMA level for warn                     (> clear)
    alarm: float = 8.0          # EWMA level for alarm                    (> warn, < clip²)
    clear: float = 3.0          # EWMA level below which warn clears      (> 1)
    persist: float = 0.25       # s above a level before it counts
    hold: float = 2.0           # s below before a level clears
    z_warn: float = 6.0         # drift: standard errors for warn         (> z_clear)
    z_alarm: float = 8.0        # drift: standard errors for alarm        (≥ z_warn)
    z_clear: float = 4.0        # drift: warn clears below this
    rel_warn: float = 0.03      # drift: relative change for warn
    rel_alarm: float = 0.15     # drift: relative change for alarm        (≥ rel_warn)
    kappa: float = 0.5          # determined: online s.e. ≤ κ · prior s.e.
    warmup: float = 2.0         # s of innovations ignored at the start

    def validate(self) -> HealthConfig:
        """Raise ``ValueError`` naming the first setting outside its range (:data:`HEALTH_RANGES`) or
        breaking a cross-field rule."""
        def need(ok, name, rule):
            if not ok:
                raise ValueError(f"health setting {name} = {getattr(self, name)!r} is out of range: {rule}")
        for f in fields(self):
            v = getattr(self, f.name)
            need(isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v), f.name,
                 "must be a finite number")
            lo, hi, open_low, _ = HEALTH_RANGES[f.name]
            need((lo < v if open_low else lo <= v) and v <= hi, f.name,
                 f"{lo:g} < {f.name} ≤ {hi:g}" if open_low else f"{lo:g} … {hi:g}")
        need(1.0 < self.clear < self.warn < self.alarm < self.clip ** 2, "clear", "1 < clear < warn < alarm < clip²")
        need(self.z_clear < self.z_warn <= self.z_alarm, "z_clear", "z_clear < z_warn ≤ z_alarm")
        need(self.rel_warn <= self.rel_alarm, "rel_warn", "rel_warn ≤ rel_alarm")
        return self


#: every field of :class:`HealthState` (``k`` = len(:data:`PARAMS`)): ``par`` settings (Q_*), ``ref`` rows
#: ``[θ⁰, s⁰, ŝ^prior, scale]`` per parameter (settings), ``acc`` the EWMA, run lengths and window sums
#: (state, A_*), ``stat`` rows ``[z, r, determined]`` of the last tick (output), ``level`` one level per
#: :data:`REASONS` (state)
FIELDS = (
    Field("par", "f8", (N_QPAR,), "setting", "thresholds and rates (Q_*)"),
    Field("ref", "f8", (4, "k"), "setting", "θ⁰, s⁰, ŝ^prior, scale per PARAMS"),
    Field("acc", "f8", (N_ACC,), "state", "EWMA, run lengths, window sums (A_*)"),
    Field("stat", "f8", (3, "k"), "output", "z, r, determined of the last tick (S_*)"),
    Field("level", "i8", (N_REASON,), "state", "level per REASONS"),
)
LAYOUT = Layout("HealthState", __name__, FIELDS, consts={"k": len(PARAMS)},
                doc="Named views of the two base buffers of the health state (:data:`FIELDS`).")
HealthState = LAYOUT.tuple

#: the fields that are state (snapshots): the others are settings or the last tick's output
STATE_FIELDS = LAYOUT.names("state")


def health_state_views(fbuf: np.ndarray, ibuf: np.ndarray) -> HealthState:
    """The :class:`HealthState` of the two base buffers, as NumPy views."""
    return LAYOUT.views(fbuf, ibuf)


#: ``health_state_of(fbuf, ibuf)``: the :class:`HealthState` of the two base buffers inside compiled code
#: (reference-free views, valid while the buffers are)
health_state_of = LAYOUT.accessor("health_state_of", __file__)


def new_health_buffers(Ts: float, theta_file, se_file, se_prior, scale,
                       config: HealthConfig | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Base buffers ``(float64, int64)`` of the state of an axis sampled every ``Ts`` s; the reference
    arrays are per :data:`PARAMS` (NaN for a parameter the model does not have: never tested)."""
    cfg = (config or HealthConfig()).validate()
    if not (math.isfinite(Ts) and Ts > 0):
        raise ValueError(f"Ts must be a positive number of seconds, got {Ts!r}")
    fbuf, ibuf = LAYOUT.new_buffers()
    hs = health_state_views(fbuf, ibuf)
    par = hs.par
    par[Q_A] = 1.0 - math.exp(-Ts / cfg.tau)
    par[Q_CLIP] = cfg.clip * cfg.clip
    par[Q_THW], par[Q_THA], par[Q_THC] = cfg.warn, cfg.alarm, cfg.clear
    par[Q_NPERS] = max(1.0, round(cfg.persist / Ts))
    par[Q_NHOLD] = max(1.0, round(cfg.hold / Ts))
    par[Q_ZW], par[Q_ZA], par[Q_ZC] = cfg.z_warn, cfg.z_alarm, cfg.z_clear
    par[Q_RW], par[Q_RA] = cfg.rel_warn, cfg.rel_alarm
    par[Q_KAPPA] = cfg.kappa
    par[Q_WARMUP] = round(cfg.warmup / Ts)
    for row, values in enumerate((theta_file, se_file, se_prior, scale)):
        a = np.asarray(values, dtype=np.float64)
        if a.shape != (len(PARAMS),):
            raise ValueError(f"health reference arrays must have {len(PARAMS)} entries ({', '.join(PARAMS)}), got {a.shape}")
        hs.ref[row] = a
    hs.acc[A_EWMA] = 1.0
    hs.stat[:] = np.nan
    return fbuf, ibuf


def validate_health_state(hs: HealthState) -> None:
    """Raise ``ValueError`` naming the entry unless the state part of ``hs`` (read from a file) is possible:
    levels in 0…2, the EWMA in [0, clip²], run lengths, counts and window sums finite and ≥ 0."""
    if not np.all(np.isfinite(hs.acc)):
        raise ValueError("health 'acc' holds non-finite values")
    if np.any((hs.level < 0) | (hs.level > 2)):
        raise ValueError("health 'level' must hold levels 0 (ok), 1 (warn) or 2 (alarm)")
    if not 0.0 <= hs.acc[A_EWMA] <= hs.par[Q_CLIP] or np.any(hs.acc < 0.0):
        raise ValueError("health 'acc': the EWMA of ν² must lie in [0, clip²] and the counts be ≥ 0")
    if hs.acc[A_WMAX] > hs.par[Q_CLIP] or hs.acc[A_WSUM] > hs.par[Q_CLIP] * hs.acc[A_WN]:
        raise ValueError("health 'acc': window statistics beyond the clip level")


@njit(cache=True, nogil=True)
def health_sample(hs, nu):
    """Per-sample model-validity step on the normalised innovation ``ν`` (NaN: skipped).

    Returns the validity level after the sample (0 ok, 1 warn, 2 alarm); it may change
    at any sample, so a publisher can report a change at once.
    """
    par = hs.par
    acc = hs.acc
    level = hs.level
    if not math.isfinite(nu):
        return level[0]
    acc[A_SEEN] += 1.0
    if acc[A_SEEN] <= par[Q_WARMUP]:
        return level[0]
    c = nu * nu
    if c > par[Q_CLIP]:
        c = par[Q_CLIP]                            # c = min(ν², c_max)
    m = acc[A_EWMA] + par[Q_A] * (c - acc[A_EWMA])  # m ← m + a (c − m)
    acc[A_EWMA] = m
    acc[A_WSUM] += c
    acc[A_WN] += 1.0
    if m > acc[A_WMAX]:
        acc[A_WMAX] = m
    # run lengths above / below the levels
    acc[A_RUN_W] = acc[A_RUN_W] + 1.0 if m >= par[Q_THW] else 0.0
    acc[A_RUN_A] = acc[A_RUN_A] + 1.0 if m >= par[Q_THA] else 0.0
    acc[A_RUN_CLR] = acc[A_RUN_CLR] + 1.0 if m < par[Q_THC] else 0.0
    acc[A_RUN_DOWN] = acc[A_RUN_DOWN] + 1.0 if m < par[Q_THW] else 0.0
    lv = level[0]
    if acc[A_RUN_A] >= par[Q_NPERS]:
        lv = 2
    elif lv == 2 and acc[A_RUN_DOWN] >= par[Q_NHOLD]:
        lv = 1                                     # alarm → warn after t_hold below θ_warn
    if lv < 2 and acc[A_RUN_W] >= par[Q_NPERS]:
        lv = 1
    if lv == 1 and acc[A_RUN_CLR] >= par[Q_NHOLD]:
        lv = 0                                     # warn → ok after t_hold below θ_clear
    level[0] = lv
    return lv


@njit(cache=True, nogil=True)
def health_tick(hs, theta, se):
    """Per-tick verdict: drift of each parameter (``theta``, ``se`` per :data:`PARAMS`, NaN =
    unknown) with hysteresis; returns the overall level (max over :data:`REASONS`).

    Also resets the window statistics of :func:`health_sample` (read them before)."""
    par = hs.par
    ref = hs.ref
    stat = hs.stat
    level = hs.level
    for j in range(ref.shape[1]):
        lv = level[1 + j]
        t0 = ref[0, j]
        s0 = ref[1, j]
        sp = ref[2, j]
        sc = ref[3, j]
        th = theta[j]
        s = se[j]
        stat[S_Z, j] = np.nan
        stat[S_REL, j] = np.nan
        stat[S_DET, j] = 0.0
        if not (math.isfinite(t0) and math.isfinite(th) and math.isfinite(s) and sc > 0.0):
            level[1 + j] = 0
            continue
        s0v = s0 if math.isfinite(s0) else 0.0
        comb = math.sqrt(s * s + s0v * s0v)
        d = th - t0
        z = d / comb if comb > 0.0 else (np.inf if d != 0.0 else 0.0)
        r = abs(d) / sc
        det = (not math.isfinite(sp)) or s <= par[Q_KAPPA] * sp
        stat[S_Z, j] = z
        stat[S_REL, j] = r
        stat[S_DET, j] = 1.0 if det else 0.0
        az = abs(z)
        if not det:
            lv = 0
        elif az >= par[Q_ZA] and r >= par[Q_RA]:
            lv = 2
        elif lv == 2:
            if az < par[Q_ZW] or r < 0.5 * par[Q_RA]:
                lv = 1 if j != STEP else 0        # alarm → warn (the step test has no warn level)
        if lv < 2 and det and j != STEP:
            if az >= par[Q_ZW] and r >= par[Q_RW]:
                lv = 1
            elif lv == 1 and (az < par[Q_ZC] or r < 0.5 * par[Q_RW]):
                lv = 0                             # warn → ok (hysteresis)
        level[1 + j] = lv
    acc = hs.acc
    acc[A_WSUM] = 0.0
    acc[A_WN] = 0.0
    acc[A_WMAX] = 0.0
    top = 0
    for i in range(level.shape[0]):
        if level[i] > top:
            top = level[i]
    return top


@dataclass(frozen=True)
class Verdict:
    """One health verdict: ``state`` (``ok | warn | alarm``), human-readable ``reasons``,
    ``levels`` per :data:`REASONS`, the innovation statistics of the window (``nu2_mean``,
    ``ewma_max``) and per parameter ``z``, ``rel``, ``determined``."""

    state: str
    reasons: list
    levels: dict
    nu2_mean: float
    ewma_max: float
    z: dict
    rel: dict
    determined: dict


class HealthMonitor:
    """River-style API over :func:`health_sample` / :func:`health_tick`.

    Parameters
    ----------
    Ts : float
        Sampling period (s).
    theta_file, se_file : mapping or sequence
        Model-file physical parameters and their standard errors per :data:`PARAMS`
        (missing → NaN: not tested).
    se_prior : sequence
        Prior standard errors of the online estimator (:class:`kernels.beta_tracker.OnlineBeta`
        ``.prior_se``), for the "determined" rule.
    scale : sequence, optional
        Scale of the relative drift per parameter (default ``|θ⁰|``, and the friction scale
        ``max(|d_p|, |c_n|, |offset|, 1 N)`` for Coulomb and offset).
    config : HealthConfig
    """

    def __init__(self, Ts: float, theta_file, se_file=None, se_prior=None, scale=None,
                 config: HealthConfig | None = None):
        t0 = self._vec(theta_file)
        s0 = self._vec(se_file)
        sp = self._vec(se_prior)
        if scale is None:
            fr = [abs(v) for v in (t0[2], t0[3], t0[5]) if math.isfinite(v)]
            fscale = max(fr + [1.0])
            scale = [abs(t0[0]), abs(t0[1]), fscale, fscale, fscale, fscale, abs(t0[0])]
        self.config = (config or HealthConfig()).validate()
        self._buf = new_health_buffers(Ts, t0, s0, sp, self._vec(scale), self.config)
        self.state = health_state_views(*self._buf)

    @staticmethod
    def _vec(values) -> np.ndarray:
        if values is None:
            return np.full(len(PARAMS), np.nan)
        if isinstance(values, dict):
            unknown = set(values) - set(PARAMS)
            if unknown:
                raise ValueError(f"unknown health parameter(s) {sorted(unknown)}; known: {', '.join(PARAMS)}")
            return np.array([float(values.get(k if k != "inertia_step" else "inertia", np.nan)) for k in PARAMS])
        a = np.asarray(values, dtype=np.float64)
        if a.shape != (len(PARAMS),):
            raise ValueError(f"health reference arrays must have {len(PARAMS)} entries ({', '.join(PARAMS)}), "
                             f"got shape {a.shape}")
        return a

    @property
    def buffers(self) -> tuple[np.ndarray, np.ndarray]:
        """The two base buffers of :attr:`state`, for compiled loops (:func:`kernels.online.track_block`)."""
        return self._buf

    def learn_one(self, nu: float) -> str:
        """Feed one normalised innovation; returns the innovation level (``ok | warn | alarm``)."""
        return LEVELS[int(health_sample(self.state, float(nu)))]

    def learn_many(self, nu) -> np.ndarray:
        """Feed a block; returns the innovation level after each sample (0/1/2)."""
        out = np.empty(len(nu), dtype=np.int64)
        _sample_many(self.state, np.ascontiguousarray(nu, dtype=np.float64), out)
        return out

    def verdict(self, theta=None, se=None) -> Verdict:
        """The tick verdict with the online parameters (mapping or sequence per :data:`PARAMS`)."""
        hs = self.state
        acc = hs.acc
        nu2 = acc[A_WSUM] / acc[A_WN] if acc[A_WN] > 0 else math.nan
        ewma_max = acc[A_WMAX] if acc[A_WN] > 0 else math.nan
        top = int(health_tick(hs, self._vec(theta), self._vec(se)))
        levels = {name: LEVELS[int(lv)] for name, lv in zip(REASONS, hs.level)}
        reasons = describe(hs.level, hs.stat[S_Z], hs.stat[S_REL], nu2, ewma_max)
        z = {p: float(hs.stat[S_Z, j]) for j, p in enumerate(PARAMS)}
        rel = {p: float(hs.stat[S_REL, j]) for j, p in enumerate(PARAMS)}
        det = {p: bool(hs.stat[S_DET, j]) for j, p in enumerate(PARAMS)}
        return Verdict(state=LEVELS[top], reasons=reasons, levels=levels, nu2_mean=float(nu2),
                       ewma_max=float(ewma_max), z=z, rel=rel, determined=det)

    def snapshot(self) -> dict[str, np.ndarray]:
        """The state (:data:`STATE_FIELDS`) as plain arrays (copies)."""
        return {f"health.{k}": np.array(getattr(self.state, k), copy=True) for k in STATE_FIELDS}

    def restore(self, snap: dict) -> None:
        """Continue from :meth:`snapshot` (same shapes required; checked by :func:`validate_health_state`,
        nothing changed when it fails)."""
        fbuf, ibuf = self._buf[0].copy(), self._buf[1].copy()
        hs = health_state_views(fbuf, ibuf)
        fill_views(hs, snap, STATE_FIELDS, prefix="health.", what="health snapshot")
        validate_health_state(hs)
        self._buf = (fbuf, ibuf)
        self.state = hs


def describe(level, z, rel, nu2_mean: float, ewma_max: float) -> list[str]:
    """The human-readable reasons of a verdict: ``level`` per :data:`REASONS`, ``z`` and ``rel`` per
    :data:`PARAMS` (the tick's statistics), the innovation window's mean ν² and EWMA peak."""
    reasons = []
    if level[0]:
        reasons.append(f"innovation: the model does not explain the data (mean ν² {nu2_mean:.1f} over the last "
                       f"window, EWMA peak {ewma_max:.1f}; expected 1)")
    for j, p in enumerate(PARAMS):
        if level[1 + j]:
            sign = "+" if z[j] > 0 else "−"
            if j == STEP:
                reasons.append(f"inertia step {sign}{100 * rel[j]:.1f} % of the model file value over the last "
                               f"accelerations ({abs(z[j]):.1f} standard errors): a payload or a changed drive")
            else:
                reasons.append(f"{p} drift {sign}{100 * rel[j]:.1f} % of the model file value "
                               f"({abs(z[j]):.1f} standard errors)")
    return reasons


@njit(cache=True, nogil=True)
def _sample_many(hs, nu, out):
    for i in range(nu.shape[0]):
        out[i] = health_sample(hs, nu[i])


def physical_vector(theta6) -> np.ndarray:
    """The :data:`PARAMS` entries of a :data:`kernels.beta_tracker.PHYSICAL` vector (the inertia stands for the
    reference of the inertia step)."""
    return np.asarray(theta6, dtype=np.float64)[list(PHYS_INDEX)]
