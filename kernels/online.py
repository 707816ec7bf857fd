"""Online feed-drive disturbance tracking: residual → KRLS-T, one ``@njit`` loop per block.

The numerics of the monitor's per-sample path (method §6, "Timing in the monitor"):
for each arriving sample ``j`` of a block,

1. place it in the stream from its sequence number and time (below): drop it (duplicate,
   late re-send), or take it as the next sample, the first after a gap, or the first of a
   new bridge session;
2. classify its values: non-finite or absurd values are *rejected*; a repeated measured
   velocity while the axis moves is *stale* (the thesis' recording glitch);
3. residual of the previous step, eq. 2.13: ``v(j−1) = v_m(j) − βᵀ z(j−1)``, with
   ``z`` of method §2 (the model's prediction stands in for a stale ``v_m``);
4. KRLS-T update with that residual (:func:`kernels._krlst_core.update`, steps 3–5)
   unless the chain restarts at this sample or it is stale;
5. forgetting and one-step-ahead prediction at ``x(j)`` (:func:`kernels._krlst_core.arm`,
   steps 1–2), reused by the next update;
6. about once a second of data time (:attr:`OnlineConfig.tick_period`), and at once when the
   model-validity level changes, a health report (``ticks``, :data:`TICK`).

Online β and health (method §9). With adaptation on
(:attr:`OnlineConfig.mode` *track* or *apply*) steps 3–5 are the joint recursion of
:mod:`kernels.beta_tracker` (:func:`~kernels.beta_tracker.joint_update`,
:func:`~kernels.beta_tracker.joint_arm`): β̂ and its covariance learn from every sample the
tracker learns from; *apply* publishes the disturbance, the residual and ``v_pred`` with β̂
(row ``beta1``: the β1 they go with, for the newton scale), *track* with the model file's β.
Every learned sample feeds its normalised innovation ``ν`` to the health EWMA
(:func:`kernels.health.health_sample`; *off*: ``ν`` of the plain tracker); a report runs
:func:`kernels.health.health_tick` on the physical parameters of β̂ (:func:`~kernels.beta_tracker.physical_se`).

Tracker input. ``x = t`` for a time kernel; ``x = (t, θ)`` for the spindle-phase kernel
(:attr:`OnlineConfig.spindle`), θ (rad, kept in ``[0, P)``: the kernel is P-periodic in θ) from
the sample's ``spindle_angle``, else integrated from ``spindle_rpm`` with the trapezoid rule
``θ_k = θ_{k−1} + (2π/60)·(n_{k−1} + n_k)/2·(t_k − t_{k−1})`` — exact for a speed that changes
linearly between samples, also across a gap of up to :data:`THETA_GAP_MAX` s; after a longer gap,
time going backwards or a new session it restarts at ``θ = 2π n t/60``. A sample without a
usable angle or speed (absent, non-finite, or faster than ``rpm_max``) uses the model's nominal speed
(counted ``spindle_fallback``): without spindle data the kernel is then exactly the time kernel
with ψ = 60/n_nominal.

:func:`track_block` runs that loop without allocation; ``monitor.estimator`` is the thin
Python API around it (stumpy-style split). The model is :class:`OnlineConfig` (read only) and
what links consecutive blocks is :class:`OnlineState` (``int64`` sequence numbers and counters,
``float64`` for the rest): NamedTuples the loop builds from a few plain typed buffers
(:class:`ConfigBuffers`, :class:`StateBuffers`: numba types each array of a tuple argument on every
call), generated from one field list each (:data:`CONFIG_SPEC`, :data:`STATE_SPEC`). The output of a
block is ``rows``/``irows``, one named row per quantity (:data:`ROWS`, :data:`IROWS`), and ``counts``
(:data:`COUNTERS`). To extend the loop, add fields to these lists.

Sequence numbers and time
-------------------------
Sequence numbers are ``int64`` throughout (never floats: ``2**53 + 1`` has no float64). Let
``L`` be the last sequence number seen (rejected samples included), ``(s_r, t_r)`` the last
sample seen with a usable time (finite, ``|t| ≤ t_max``), ``W`` the reorder window
(:attr:`OnlineConfig.reorder_window`, samples) and ``Ts`` the sampling period. A sample
``(s, t)``, after the first one, is

* the **next** sample when ``s = L + 1`` (time going backwards still restarts the chain: GAP);
* after a **gap** of ``s − L − 1`` samples when ``s > L + 1`` and either the jump is small
  (``s − L − 1 ≤ W``) or the clock advanced with it — ``2 (t − t_r)/Ts + W ≥ s − s_r``, i.e.
  at least half the time the missing samples take (rate tolerance ×2). Counted in
  ``gaps`` and ``missing_samples``, flag GAP;
* the start of a **new session** (``seq_resets``, flag GAP, the chain restarts; nothing counted
  as missing) when the sequence number jumped ahead of the clock (``s > L + 1`` beyond the
  rule above, e.g. a bridge that restarts with another base, or one absurd ``seq``), or went
  back while the clock moved on (``s ≤ L`` and ``t > t_r``: a bridge that counts from 0 again);
* otherwise (``s ≤ L``, time not newer) a **duplicate** (``s = L``) or a **late re-send**
  (``s < L``): dropped, no row — unless ``W`` such samples in a row continue each other
  (``s`` = previous + 1): then the bridge restarted both its count and its clock, and the
  ``W``-th of them starts a new session (``W − 1`` samples are lost).

A sample without a usable time is judged by its sequence number alone. So a genuine gap
(``seq`` and ``t`` jump together) stays a gap, duplicates and re-sends are dropped, and a far
jump of ``seq`` either way costs one chain restart instead of silencing the axis.

Defence in depth: every input value the loop reads is checked where it is used (non-finite
angles and speeds fall back as above, never reach the kernel), and the health report buffer is
bounded (:func:`new_ticks`): a block never writes beyond it.

Every index the compiled code uses is checked: a block whose sequence numbers do not fit
in ``int64`` (``seq0 < 0`` or ``seq0 + n − 1 > 2**63 − 1``) is refused whole (counted
``rejected_seq_range``); the differences of two sequence numbers are formed only between
non-negative ``int64`` values (no overflow). The KRLS-T buffers are indexed by the core
with its own indices, which :func:`kernels._krlst_core.validate_state` checks before a
saved state is restored.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np
from numba import njit
from numba.extending import register_jitable

from . import _krlst_core as core
from . import beta_tracker as bt
from . import health as hl
from ._krlst_simd import view
from .flags import ADAPTATION_MODES, GAP_BIT, REDUCED_BIT, REJECTED_BIT, STALE_BIT, WARMUP_BIT
from .layout import Field, Layout, Record

__all__ = ["COUNTERS", "ROWS", "EXTRA_ROWS", "IROWS", "TICK", "SEQ_LIMIT", "REORDER_WINDOW", "OnlineConfig",
           "ConfigBuffers", "config_of", "new_config", "set_tracker_input", "new_search", "OnlineState", "StateBuffers", "state_of", "new_state", "new_rows",
           "new_scratch", "new_ticks", "track_block"]

#: counters of the ``counts`` output, in slot order (each a number of samples unless said)
COUNTERS = ("duplicate", "out_of_order", "rejected_non_finite", "rejected_out_of_range", "rejected_seq_range",
            "gaps", "missing_samples", "seq_resets", "time_backwards", "restarts", "stale", "trained",
            "spindle_fallback", "health_reports", "beta_updates", "interval_mismatch")
(C_DUP, C_OOO, C_NONFINITE, C_RANGE, C_SEQ_RANGE, C_GAPS, C_MISSING, C_RESET, C_BACK, C_RESTART, C_STALE,
 C_TRAINED, C_SPINDLE_FALLBACK, C_TICKS, C_BETA_UPDATES, C_INTERVAL) = range(len(COUNTERS))
#: a sample that follows the previous one (next ``seq``) more than this fraction of Ts early or late
#: is counted ``interval_mismatch``: β is of one sampling time (a stream at another rate than the
#: model's, or a controller that skipped cycles without skipping sequence numbers)
INTERVAL_TOLERANCE = 0.25

#: :attr:`OnlineConfig.mode`: the index in :data:`kernels.flags.ADAPTATION_MODES`
MODE_OFF, MODE_TRACK, MODE_APPLY = range(len(ADAPTATION_MODES))
#: longest gap (s of controller time) across which θ is integrated from the spindle speed
THETA_GAP_MAX = 60.0

#: largest sequence number the compiled loop can form (``int64``); the schema's bound is far lower
SEQ_LIMIT = 2**63 - 1

#: default reorder window W (samples): how far back a sample may be and still be a duplicate / re-send
REORDER_WINDOW = 256

# where a sample stands in the stream (see the module docstring)
_FIRST, _NEXT, _GAP, _RESET, _DUPLICATE, _LATE = range(6)


#: what the loop reads of the axis model (SI units), after β (float64 (p,), in the order of the model's
#: ``beta_names``): booleans and integers live in :attr:`ConfigBuffers.ints`, floats in ``floats``
CONFIG_SPEC = (
    Field("coulomb", "bool", (), "setting", "β has the Coulomb columns −σ_p, −σ_n (β[2], β[3])"),
    Field("intercept", "bool", (), "setting", "β ends with the constant column 'one'"),
    Field("omega", "f8", (), "setting", "Coulomb dead band Ω (m/s)"),
    Field("inv_ts", "f8", (), "setting", "1/Ts (1/s)"),
    Field("v_max", "f8", (), "setting", "|v_m| beyond which a sample is absurd (m/s)"),
    Field("e_max", "f8", (), "setting", "|v_ref| (m/s) or |u| (N) beyond which a sample is absurd"),
    Field("t_max", "f8", (), "setting", "|t| beyond which a controller time is absurd (s)"),
    Field("stale_detection", "bool", (), "setting", "detect repeated measured velocities"),
    Field("warmup", "i8", (), "setting", "rows flagged WARMUP while the tracker has learned ≤ this many samples"),
    Field("reorder_window", "i8", (), "setting", "W ≥ 1 (samples), see the module docstring"),
    Field("mode", "i8", (), "setting", "adaptation: MODE_OFF, MODE_TRACK, MODE_APPLY (ADAPTATION_MODES)"),
    Field("spindle", "bool", (), "setting", "tracker input x = (t, θ) (spindle-phase kernel), else x = t"),
    Field("tick_min", "i8", (), "setting", "samples at least between two health reports"),
    Field("theta_period", "f8", (), "setting", "P (rad): period of the kernel in θ (2π or 2π/teeth)"),
    Field("rpm_nominal", "f8", (), "setting", "the model's nominal spindle speed (rpm), used without spindle data"),
    Field("rpm_max", "f8", (), "setting", "|spindle_rpm| beyond which a speed is unusable (rpm)"),
    Field("tick_period", "f8", (), "setting", "s of data time between two health reports"),
)
CONFIG = Record("OnlineConfig", __name__, CONFIG_SPEC, head=("beta",),
                doc="What the loop reads of the axis model: named values of :class:`ConfigBuffers` (:data:`CONFIG_SPEC`).")
OnlineConfig = CONFIG.tuple


class ConfigBuffers(NamedTuple):
    """The storage of an :class:`OnlineConfig`, as the compiled loop takes it: β, then the integer and
    float values (:data:`CONFIG_SPEC`, slots ``CONFIG.int_slot`` / ``CONFIG.float_slot``)."""

    beta: np.ndarray
    ints: np.ndarray
    floats: np.ndarray


def new_config(*, beta, coulomb: bool, intercept: bool, omega: float, inv_ts: float, v_max: float, e_max: float,
               t_max: float, stale_detection: bool, warmup: int, reorder_window: int, mode: str = "off",
               spindle: bool = False, theta_period: float = 2.0 * math.pi, rpm_nominal: float = 0.0,
               rpm_max: float = 1e5, tick_period: float = 1.0) -> ConfigBuffers:
    """:class:`ConfigBuffers` from named values (see :class:`OnlineConfig`; ``mode`` one of :data:`ADAPTATION_MODES`)."""
    if mode not in ADAPTATION_MODES:
        raise ValueError(f"mode must be one of {', '.join(ADAPTATION_MODES)}, got {mode!r}")
    if spindle and not (math.isfinite(rpm_nominal) and 0.0 < rpm_nominal <= rpm_max):
        raise ValueError(f"the spindle-phase kernel needs a nominal speed in (0, {rpm_max:g}] rpm, got {rpm_nominal!r}")
    if not (math.isfinite(theta_period) and theta_period > 0.0):
        raise ValueError(f"theta_period must be a positive angle (rad), got {theta_period!r}")
    if not (math.isfinite(tick_period) and tick_period > 0.0):
        raise ValueError(f"tick_period must be a positive number of seconds, got {tick_period!r}")
    tick_min = max(1, int(round(0.5 * tick_period * inv_ts)))
    ints, floats = CONFIG.pack(coulomb=coulomb, intercept=intercept, omega=omega, inv_ts=inv_ts, v_max=v_max,
                               e_max=e_max, t_max=t_max, stale_detection=stale_detection, warmup=warmup,
                               reorder_window=reorder_window, mode=ADAPTATION_MODES.index(mode), spindle=spindle,
                               tick_min=tick_min, theta_period=theta_period, rpm_nominal=rpm_nominal,
                               rpm_max=rpm_max, tick_period=tick_period)
    return ConfigBuffers(np.ascontiguousarray(beta, dtype=np.float64), ints, floats)


def set_tracker_input(cfg: ConfigBuffers, spindle: bool, theta_period: float, rpm_nominal: float | None = None) -> None:
    """Change what the tracker reads in place (a new disturbance model): ``x = (t, θ)`` with a kernel
    ``theta_period``-periodic in θ (rad), or ``x = t``; ``rpm_nominal`` the speed θ is integrated at
    without spindle data (rpm; None: keep)."""
    if not (math.isfinite(theta_period) and theta_period > 0.0):
        raise ValueError(f"theta_period must be a positive angle (rad), got {theta_period!r}")
    ints, floats = CONFIG.int_slot, CONFIG.float_slot
    cfg.ints[ints["spindle"]] = int(bool(spindle))
    cfg.floats[floats["theta_period"]] = float(theta_period)
    if rpm_nominal is not None:
        rpm_max = cfg.floats[floats["rpm_max"]]
        if not (math.isfinite(rpm_nominal) and 0.0 <= rpm_nominal <= rpm_max):
            raise ValueError(f"rpm_nominal must be in [0, {rpm_max:g}] rpm, got {rpm_nominal!r}")
        cfg.floats[floats["rpm_nominal"]] = float(rpm_nominal)


#: ``config_of(beta, ints, floats)``: the :class:`OnlineConfig` stored in ``(beta, ints, floats)``; works in
#: Python and inside ``@njit``
config_of = CONFIG.accessor("config_of", __file__)

#: what links consecutive blocks of one axis (one value each): the integers, then the floats
STATE_SPEC = (
    Field("seen", "i8", (1,), "state", "1 once a sample was seen (last_seq is valid)"),
    Field("last_seq", "i8", (1,), "state", "L, sequence number of the last sample seen (rejected ones included)"),
    Field("ref_seq", "i8", (1,), "state", "s_r, sequence number of the last sample seen with a usable time"),
    Field("run_seq", "i8", (1,), "state", "last sample of the current run of dropped samples that continue each other"),
    Field("run_len", "i8", (1,), "state", "length of that run (0: none)"),
    Field("chain", "i8", (1,), "state", "1 when the last sample was accepted: the next one can form a residual"),
    Field("trained", "i8", (1,), "state", "samples the tracker learned from"),
    Field("tick_n", "i8", (1,), "state", "accepted samples since the last health report"),
    Field("ref_t", "f8", (1,), "state", "t_r, time of sample s_r (s); NaN: none"),
    Field("last_t", "f8", (1,), "state", "time of the last accepted sample (s); NaN: none"),
    Field("last_e", "f8", (1,), "state", "its exogenous input v_ref (m/s) or u (N)"),
    Field("last_v_raw", "f8", (1,), "state", "its measured velocity as received (m/s)"),
    Field("last_v_used", "f8", (1,), "state", "the velocity that entered its regressor (the model's for a stale one)"),
    Field("f_next", "f8", (1,), "state", "the prediction of f made at the last accepted sample (m/s)"),
    Field("f_next_var", "f8", (1,), "state", "its variance ((m/s)²)"),
    Field("theta", "f8", (1,), "state", "θ of the last accepted sample (rad, in [0, P)); NaN: none"),
    Field("theta_t", "f8", (1,), "state", "its time (s)"),
    Field("theta_rpm", "f8", (1,), "state", "the spindle speed used there (rpm); NaN: none"),
    Field("tick_t", "f8", (1,), "state", "data time of the last health report (s); NaN: none yet"),
)
STATE = Layout("OnlineState", __name__, STATE_SPEC,
               doc="What links consecutive blocks of one axis: named 1-element views of :class:`StateBuffers`.")
OnlineState = STATE.tuple


class StateBuffers(NamedTuple):
    """The storage of an :class:`OnlineState`: ``int64`` and ``float64`` slots in field order."""

    ints: np.ndarray
    floats: np.ndarray


#: ``state_of(ints, floats)``: the named views of the buffers of :class:`StateBuffers`; works in Python and
#: inside ``@njit``
state_of = STATE.sliced("state_of", __file__, ints_first=True)


def new_state(trained: int = 0) -> StateBuffers:
    """State of an axis that has seen no sample (its tracker may have learned ``trained`` samples before)."""
    _, n_float, n_int = STATE.offsets()
    buf = StateBuffers(np.zeros(n_int, dtype=np.int64), np.full(n_float, np.nan))
    state_of(*buf).trained[0] = trained
    return buf


#: rows of the float output of :func:`track_block` (``rows``, shape ``(len(ROWS) + len(EXTRA_ROWS), n)``),
#: one column per sample; :data:`ROWS` are the estimate block's columns
ROWS = ("v_pred", "residual", "f", "f_var", "f_next", "f_next_var")
R_VPRED, R_RESID, R_F, R_FVAR, R_FNEXT, R_FNEXTVAR = range(len(ROWS))
#: further float rows: ``beta1`` the β1 of the β the row's disturbance goes with (the model file's,
#: or β̂ in *apply* mode), for the newton scale ``b`` (method §7)
EXTRA_ROWS = ("beta1",)
R_BETA1 = len(ROWS)
#: rows of the integer output (``irows``, shape ``(len(IROWS), n)``)
IROWS = ("dict_size", "removed", "flags")
R_SIZE, R_REMOVED, R_FLAGS = range(len(IROWS))
# What each row holds, for sample j (emitted when it arrives; m/s and (m/s)²):
#   v_pred      βᵀz(j−1) + f̂(j−1): the velocity the model predicted for sample j
#   residual    v(j−1) = v_m(j) − βᵀz(j−1), eq. 2.13 (NaN when the chain (re)starts or j is stale)
#   f, f_var    the filtered disturbance of the step that ended at j (its prediction for a stale j)
#   f_next, f_next_var   the one-step-ahead prediction of f(j) from x(j)
#   dict_size   dictionary size after sample j;  removed  pruned dictionary index (−1: none)
#   flags       kernels.flags.EstimateFlag bits

#: columns of a health report (``ticks``, one row per report): the sample it was made at, the
#: physical parameters of β̂ and their standard errors (:data:`kernels.beta_tracker.PHYSICAL`, NaN
#: when not estimated), the level per :data:`kernels.health.REASONS`, the drift statistics per
#: :data:`kernels.health.PARAMS`, the innovation window (mean ν², EWMA peak) and the
#: overall level
TICK = (("seq", 1), ("t", 1), ("theta", bt.N_PHYS), ("se", bt.N_PHYS), ("level", hl.N_REASON),
        ("z", len(hl.PARAMS)), ("rel", len(hl.PARAMS)), ("determined", len(hl.PARAMS)), ("nu2_mean", 1),
        ("ewma_max", 1), ("state", 1))
_TICK_AT = {}
_at = 0
for _name, _width in TICK:
    _TICK_AT[_name] = _at
    _at += _width
N_TICK = _at
K_SEQ, K_T, K_THETA, K_SE, K_LEVEL, K_Z, K_REL, K_DET, K_NU2, K_EWMAX, K_STATE = (_TICK_AT[n] for n, _ in TICK)


#: columns of the ring of recent learned samples the disturbance-model search replays
#: (:mod:`kernels.disturbance_search`): the sample's time (s), spindle angle (rad; NaN without spindle
#: data), command (v_ref m/s or u N), the velocity in its regressor (m/s), the measured velocity of
#: the next sample (the target, m/s), the residual the tracker learned (m/s), and the commanded velocity
#: v_ref (m/s; NaN when the samples carry none) against which periods locked to the motion are told apart,
#: and the spindle speed θ was integrated with (rpm; NaN without spindle data)
RING = ("t", "theta", "exo", "v", "target", "resid", "ref", "rpm")
G_T, G_THETA, G_EXO, G_V, G_TARGET, G_RESID, G_REF, G_RPM = range(len(RING))
#: integer slots of the search state (``sint``): the ring's next write position and fill, the learned
#: samples counted for the search, the counts at which the loop pauses for the next search (routine,
#: and while the tracker predicts poorly), the count before which health and β do not learn, why
#: the loop paused (:data:`PAUSE_NONE` …) and the sample index it paused after, whether a second
#: tracker publishes the disturbance (``dual``: a time kernel short enough to follow the drive's own
#: regressors is kept away from online β, which keeps a tracker of its own) and whether that one reads θ
SEARCH_INTS = ("head", "fill", "count", "next_tick", "next_retry", "freeze_until", "pause", "stop", "dual", "pub_spindle")
(S_HEAD, S_FILL, S_COUNT, S_NEXT_TICK, S_NEXT_RETRY, S_FREEZE, S_PAUSE, S_STOP, S_DUAL,
 S_PUB_SPINDLE) = range(len(SEARCH_INTS))
PAUSE_NONE, PAUSE_ROUTINE, PAUSE_POOR = range(3)
#: float slots (``sflt``): the calibration's EWMAs of the squared innovation e² and of the
#: predictive variance P of f, the variance scale c² they give, the short EWMAs of ν² and e², then
#: settings: the residual noise variance σ_ε² ((m/s)², 0: the tracker's own s0²/γ), the EWMA
#: weights of the calibration and of the short test, the "predicts poorly" level, the θ of the last
#: accepted sample (NaN without spindle data) and its commanded velocity
SEARCH_FLOATS = ("cal_e2", "cal_p", "c2", "nu2", "e2", "noise2", "a_cal", "a_short", "poor", "theta_data", "ref")
(Q_CAL_E2, Q_CAL_P, Q_C2, Q_NU2, Q_E2, Q_NOISE2, Q_A_CAL, Q_A_SHORT, Q_POOR, Q_THETA,
 Q_REF) = range(len(SEARCH_FLOATS))
#: the calibration never lets the disturbance's share of the innovation fall below this fraction
CAL_FLOOR = 0.05


def new_search(Ts: float, *, noise2: float = 0.0, cal_tau: float = 2.0, short_tau: float = 0.1, poor: float = 9.0,
               ring: int = 4096, enabled: bool = True) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(ring, sint, sflt)``: the ring of ``ring`` learned samples (:data:`RING`) and the search and
    calibration state (:data:`SEARCH_INTS`, :data:`SEARCH_FLOATS`) of a stream sampled every ``Ts`` s.
    ``noise2``: the residual's white-noise variance ((m/s)²; 0: unknown, the tracker's own s0²/γ
    stands in). ``enabled=False``: the loop never pauses for a search (the calibration still runs)."""
    sint = np.zeros(len(SEARCH_INTS), dtype=np.int64)
    sint[S_NEXT_TICK] = sint[S_NEXT_RETRY] = 0 if enabled else np.iinfo(np.int64).max
    sflt = np.zeros(len(SEARCH_FLOATS))
    sflt[Q_C2] = 1.0
    sflt[Q_NU2] = 1.0
    sflt[Q_NOISE2] = max(0.0, float(noise2))
    sflt[Q_A_CAL] = 1.0 - math.exp(-Ts / cal_tau)
    sflt[Q_A_SHORT] = 1.0 - math.exp(-Ts / short_tau)
    sflt[Q_POOR] = poor
    sflt[Q_THETA] = np.nan
    sflt[Q_REF] = np.nan
    return np.full((max(16, int(ring)), len(RING)), np.nan), sint, sflt


def new_scratch(p: int) -> np.ndarray:
    """The scratch buffer of :func:`track_block` for a model with ``p`` β entries."""
    return np.zeros(_SCR_FIXED + _scr_p(p))


_SCR_X = 0                                    # x (≤ 2)
_SCR_OUT = 2                                  # the core's out (N_OUT ≥ N_ARM)
_SCR_BOUT = _SCR_OUT + core.N_OUT             # joint_update's bout
_SCR_THETA = _SCR_BOUT + bt.N_BOUT            # physical values
_SCR_SE = _SCR_THETA + bt.N_PHYS
_SCR_TH5 = _SCR_SE + bt.N_PHYS                # health PARAMS values
_SCR_SE5 = _SCR_TH5 + len(hl.PARAMS)
_SCR_FIXED = _SCR_SE5 + len(hl.PARAMS)        # then z (p) and the physical_se work (N_PHYS + 2, p)


@register_jitable
def _scr_p(p):
    return p + (bt.N_PHYS + 2) * p


def new_rows(n: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Output buffers ``rows`` (:data:`ROWS` then :data:`EXTRA_ROWS`), ``irows`` (:data:`IROWS`) and
    ``counts`` (:data:`COUNTERS`) for a block of ``n`` samples."""
    return (np.empty((len(ROWS) + len(EXTRA_ROWS), n)), np.empty((len(IROWS), n), dtype=np.int64),
            np.zeros(len(COUNTERS), np.int64))


def new_ticks(n: int, tick_min: int, change_min: int = 1) -> np.ndarray:
    """Output buffer of the health reports of a block of ``n`` samples: the periodic ones (at most one
    per ``tick_min`` samples) and those at a change of the model-validity level (at most one per
    ``change_min`` samples: the health statistics' persistence or hold, whichever is shorter)."""
    return np.empty((n // max(1, int(tick_min)) + n // max(1, int(change_min)) + 2, N_TICK))


@njit(cache=True, nogil=True)
def _linear(cfg, b, e, v):
    """``bᵀ z(k)`` of method §2 for one sample, ``z = [e, v, −σ_p, −σ_n, 1]`` with the Coulomb
    columns and the constant only when the model has them (either input form)."""
    acc = b[0] * e + b[1] * v
    if cfg.coulomb:
        if v > cfg.omega:
            acc -= b[2]                           # −σ_p column
        elif v < -cfg.omega:
            acc -= b[3]                           # −σ_n column
    if cfg.intercept:
        acc += b[b.shape[0] - 1]                  # constant column "one" (offset)
    return acc


@njit(cache=True, nogil=True)
def _theta(cfg, st, sp, j, tj, restart, counts):
    """θ of sample ``j`` (rad, in ``[0, P)``) for the spindle-phase kernel (module docstring)."""
    a = np.nan
    r = np.nan
    if sp.shape[1] > j:
        a = sp[0, j]
        r = sp[1, j]
    rate = r if (math.isfinite(r) and abs(r) <= cfg.rpm_max) else np.nan
    P = 2.0 * math.pi                            # the kernels are 2π/teeth-periodic in θ: one turn keeps θ small
    if math.isfinite(a):
        th = a
    else:
        if not math.isfinite(rate):
            rate = cfg.rpm_nominal                # no usable spindle data: the nominal speed
            counts[C_SPINDLE_FALLBACK] += 1
        dt = tj - st.theta_t[0]                   # NaN when there is no previous θ
        if not restart and math.isfinite(st.theta[0]) and 0.0 < dt <= THETA_GAP_MAX:
            r0 = st.theta_rpm[0] if math.isfinite(st.theta_rpm[0]) else rate
            th = st.theta[0] + (2.0 * math.pi / 60.0) * 0.5 * (r0 + rate) * dt   # trapezoid
        else:
            th = (2.0 * math.pi / 60.0) * rate * tj   # restart: as if at this speed since t = 0
    th = th - P * math.floor(th / P)
    if not (0.0 <= th < P):
        th = 0.0                                  # (rounding at the boundary)
    st.theta[0] = th
    st.theta_t[0] = tj
    st.theta_rpm[0] = rate
    return th


@njit(cache=True, nogil=True)
def _place(cfg, st, s, t, t_ok):
    """Where sample ``(s, t)`` stands in the stream (module docstring); updates the run of dropped samples."""
    if not st.seen[0]:
        return _FIRST
    last = st.last_seq[0]
    window = cfg.reorder_window
    clock = t_ok and math.isfinite(st.ref_t[0])   # both times usable
    if s > last:                                  # s − last ≥ 1, no overflow: both in [0, 2**63)
        if s - last == 1:
            return _NEXT
        if s - last - 1 <= window:
            return _GAP
        if clock and 2.0 * (t - st.ref_t[0]) * cfg.inv_ts + window >= float(s - st.ref_seq[0]):
            return _GAP                           # seq and time jumped together: samples lost
        return _RESET                             # seq ran ahead of the clock: a new session
    if clock and t > st.ref_t[0]:
        return _RESET                             # seq went back while time moved on: a new session
    if st.run_len[0] > 0 and s - 1 == st.run_seq[0]:      # s ≥ 0: no overflow
        st.run_len[0] += 1
    else:
        st.run_len[0] = 1
    st.run_seq[0] = s
    if st.run_len[0] >= window:
        return _RESET                             # W old-looking samples in a row: count and clock restarted
    return _DUPLICATE if s == last else _LATE


@njit(cache=True, nogil=True)
def _clear(rows, irows, j, ist):
    for r in range(rows.shape[0]):
        rows[r, j] = np.nan
    irows[R_REMOVED, j] = -1
    irows[R_SIZE, j] = ist[core.I_N]


@njit(cache=True, nogil=True)
def _tick(cfg, bs, hs, s, tj, ticks, k, scr, p):
    """Health report ``k`` at sample ``(s, tj)`` into ``ticks[k]`` (:data:`TICK`)."""
    row = ticks[k]
    theta = view(scr, _SCR_THETA, (bt.N_PHYS,))
    se = view(scr, _SCR_SE, (bt.N_PHYS,))
    th5 = view(scr, _SCR_TH5, (len(hl.PARAMS),))
    se5 = view(scr, _SCR_SE5, (len(hl.PARAMS),))
    cw = view(scr, _SCR_FIXED + p, (bt.N_PHYS + 2, p))
    for i in range(bt.N_PHYS):
        theta[i] = np.nan
        se[i] = np.nan
    if cfg.mode != MODE_OFF:
        bt.physical_se(bs, theta, se, cw)
    for i in range(len(hl.PARAMS)):
        th5[i] = theta[hl.PHYS_INDEX[i]]
        se5[i] = se[hl.PHYS_INDEX[i]]
    th5[hl.STEP], se5[hl.STEP] = bt.fast_inertia(bs, theta[0]) if cfg.mode != MODE_OFF else (np.nan, np.nan)
    acc = hs.acc
    wn = acc[hl.A_WN]
    row[K_NU2] = acc[hl.A_WSUM] / wn if wn > 0.0 else np.nan
    row[K_EWMAX] = acc[hl.A_WMAX] if wn > 0.0 else np.nan
    top = hl.health_tick(hs, th5, se5)            # resets the window statistics
    row[K_SEQ] = float(s)
    row[K_T] = tj
    for i in range(bt.N_PHYS):
        row[K_THETA + i] = theta[i]
        row[K_SE + i] = se[i]
    for i in range(hl.N_REASON):
        row[K_LEVEL + i] = float(hs.level[i])
    for i in range(len(hl.PARAMS)):
        row[K_Z + i] = hs.stat[hl.S_Z, i]
        row[K_REL + i] = hs.stat[hl.S_REL, i]
        row[K_DET + i] = hs.stat[hl.S_DET, i]
    row[K_STATE] = float(top)


@njit(cache=True, nogil=True)
def _learned(st, ring, sint, sflt, tr_fst_before, resid_trk, v_next, ref):
    """After a learned sample: the ring entry, the calibration's EWMAs and the short "predicts poorly"
    statistics. ``tr_fst_before``: the publishing tracker's armed ``ŷ, σ_f², σ_y², s0², sn2`` before the
    update. Returns ``(e, R, c2, noise2)``."""
    ym, sf2, sy2, s02, sn2 = tr_fst_before
    R = s02 * sy2                                 # predictive variance of the residual (eq. 2.17, 2.20)
    e_in = resid_trk - ym
    W = ring.shape[0]
    h = sint[S_HEAD]
    ring[h, G_T] = st.last_t[0]
    ring[h, G_THETA] = sflt[Q_THETA]
    ring[h, G_EXO] = st.last_e[0]
    ring[h, G_V] = st.last_v_used[0]
    ring[h, G_TARGET] = v_next
    ring[h, G_RESID] = resid_trk
    ring[h, G_REF] = ref
    ring[h, G_RPM] = st.theta_rpm[0] if math.isfinite(sflt[Q_THETA]) else np.nan
    sint[S_HEAD] = (h + 1) % W
    if sint[S_FILL] < W:
        sint[S_FILL] += 1
    sint[S_COUNT] += 1
    noise2 = sflt[Q_NOISE2] if sflt[Q_NOISE2] > 0.0 else s02 * sn2
    P = s02 * sf2                                 # predictive variance of f, as the tracker sees it
    if sflt[Q_CAL_P] == 0.0:                      # first learned sample: start the EWMAs here
        sflt[Q_CAL_E2] = e_in * e_in
        sflt[Q_CAL_P] = P
    a = sflt[Q_A_CAL]
    sflt[Q_CAL_E2] += a * (e_in * e_in - sflt[Q_CAL_E2])
    sflt[Q_CAL_P] += a * (P - sflt[Q_CAL_P])
    e2 = sflt[Q_CAL_E2]
    # E e² = E (f − f̂)² + σ_ε²: the prediction error of f over what the tracker expected   (C1)
    if sflt[Q_CAL_P] > 0.0:
        sflt[Q_C2] = max(e2 - noise2, CAL_FLOOR * e2) / sflt[Q_CAL_P]
    b = sflt[Q_A_SHORT]
    if R > 0.0:
        sflt[Q_NU2] += b * (min(e_in * e_in / R, 100.0) - sflt[Q_NU2])
    sflt[Q_E2] += b * (e_in * e_in - sflt[Q_E2])
    return e_in, R, sflt[Q_C2], noise2


@njit(cache=True, nogil=True)
def track_block(fbuf, ibuf, bfbuf, bibuf, hfbuf, hibuf, beta, cfg_ints, cfg_floats, st_ints, st_floats, seq0, t, e,
                v, sp, rows, irows, counts, ticks, scr, start, ring, sint, sflt, vref, pfbuf, pibuf):
    """Process samples ``start …`` of one block (method §6); returns the number of leading samples
    dropped.

    ``fbuf, ibuf``: the tracker's two base buffers (:meth:`kernels.krlst.KRLST.core_buffers`, named
    inside by :func:`kernels._krlst_core.state_of`); ``bfbuf, bibuf`` the online β state's
    (:func:`kernels.beta_tracker.new_beta_buffers`), ``hfbuf, hibuf`` the health state's
    (:func:`kernels.health.new_health_buffers`); ``beta … cfg_floats`` a :class:`ConfigBuffers`;
    ``st_ints, st_floats`` a :class:`StateBuffers` (updated); ``seq0`` the sequence number of
    sample 0 (int64); ``t`` (s), ``e`` (``v_ref`` m/s or ``u`` N), ``v`` (``v_m``, m/s): float64
    (n,), NaN = missing; ``sp`` (2, n) the spindle angle (rad) and speed (rpm), NaN = missing, or
    (2, 0) when the block has neither. ``rows`` (:data:`ROWS` + :data:`EXTRA_ROWS`, ≥ n) and
    ``irows`` (:data:`IROWS`, ≥ n) receive one column per sample from index ``first`` on (the
    return value: dropped samples — duplicates and late re-sends — always form a prefix, since the
    sample after an accepted one is its successor); ``counts`` accumulates :data:`COUNTERS`
    (``health_reports``: the rows written to ``ticks``, :func:`new_ticks`); ``scr`` scratch
    (:func:`new_scratch`). ``ring, sint, sflt`` (:func:`new_search`): the recent learned samples, the
    search and calibration state. The loop stops after the sample at which a search of the
    disturbance model is due (``sint[S_PAUSE]`` says why, ``sint[S_STOP]`` where to resume; it is
    ``n`` when the block is done): the caller runs the search and calls again from there. ``vref``
    (n,) the commanded velocity (m/s, NaN = missing) or (0,): what the ring keeps as the motion.
    ``pfbuf, pibuf``: with ``sint[S_DUAL]``, the buffers of the tracker that publishes the disturbance
    (then the first tracker serves online β and health only); unused otherwise.
    """
    tr = core.unowned(core.state_of(fbuf, ibuf))  # the tracker (no reference counting in the calls below)
    bs = bt.beta_state_of(bfbuf, bibuf)
    hs = hl.health_state_of(hfbuf, hibuf)
    n = t.shape[0]
    p = beta.shape[0]
    sint[S_PAUSE] = PAUSE_NONE
    sint[S_STOP] = n
    if (e.shape[0] != n or v.shape[0] != n or rows.shape[0] != len(ROWS) + len(EXTRA_ROWS) or rows.shape[1] < n
            or irows.shape[0] != len(IROWS) or irows.shape[1] < n or counts.shape[0] != len(COUNTERS)
            or sp.shape[0] != 2 or (sp.shape[1] != 0 and sp.shape[1] != n) or ticks.shape[1] != N_TICK
            or scr.shape[0] < _SCR_FIXED + _scr_p(p) or bs.beta.shape[0] != p or ring.shape[1] != len(RING)
            or sint.shape[0] != len(SEARCH_INTS) or sflt.shape[0] != len(SEARCH_FLOATS) or not 0 <= start <= n
            or (vref.shape[0] != 0 and vref.shape[0] != n)):
        raise ValueError("track_block: inconsistent array shapes")
    if n == 0 or start == n:
        return 0
    if seq0 < 0 or seq0 > SEQ_LIMIT - (n - 1):
        counts[C_SEQ_RANGE] += n                  # sequence numbers beyond int64: refused whole
        return n
    cfg = config_of(beta, cfg_ints, cfg_floats)
    st = state_of(st_ints, st_floats)
    mode = cfg.mode
    joint = mode != MODE_OFF
    apply = mode == MODE_APPLY
    bpub = bs.beta if apply else cfg.beta         # the β the published values go with
    x_t = view(scr, _SCR_X, (1,))                # x = t
    x_s = view(scr, _SCR_X, (2,))                # x = (t, θ)
    xbuf = x_s if cfg.spindle else x_t
    dual = sint[S_DUAL] != 0
    tp = core.unowned(core.state_of(pfbuf, pibuf)) if dual else tr   # the tracker that publishes
    xpub = x_s if (sint[S_PUB_SPINDLE] != 0 if dual else cfg.spindle) else x_t
    pst = tp.fst
    obuf = view(scr, _SCR_OUT, (core.N_OUT,))
    bout = view(scr, _SCR_BOUT, (bt.N_BOUT,))
    z = view(scr, _SCR_FIXED, (p,))
    form_force = bs.lay[bt.L_FORM] == 1
    i_sp, i_sn, i_one = bs.lay[bt.L_ISP], bs.lay[bt.L_ISN], bs.lay[bt.L_IONE]
    fst = tr.fst
    st_ref_prev = sflt[Q_REF]
    nticks = np.int64(0)                      # not a literal 0: one compiled _tick
    updates0 = bs.cnt[bt.C_UPDATES]
    first = 0
    for j in range(start, n):
        s = seq0 + j
        tj, ej, vj = t[j], e[j], v[j]
        report_now = False
        t_ok = math.isfinite(tj) and abs(tj) <= cfg.t_max
        # ---- 1. place it in the stream ---------------------------------------------------------
        where = _place(cfg, st, s, tj, t_ok)
        if where == _DUPLICATE or where == _LATE:
            counts[C_DUP if where == _DUPLICATE else C_OOO] += 1
            first = j + 1                         # a prefix (see the docstring)
            continue
        fl = 0
        if where == _GAP:
            counts[C_GAPS] += 1
            counts[C_MISSING] += s - st.last_seq[0] - 1
            fl |= GAP_BIT
        elif where == _RESET:
            counts[C_RESET] += 1
            fl |= GAP_BIT
        st.seen[0] = 1
        st.last_seq[0] = s
        st.run_len[0] = 0
        if t_ok:
            st.ref_seq[0] = s
            st.ref_t[0] = tj
        elif where == _RESET:
            st.ref_t[0] = np.nan                  # no clock reference in the new session yet
        _clear(rows, irows, j, tp.ist)
        # ---- 2. classify its values --------------------------------------------------------------
        if not (math.isfinite(tj) and math.isfinite(ej) and math.isfinite(vj)):
            counts[C_NONFINITE] += 1
            fl |= REJECTED_BIT
        elif abs(vj) > cfg.v_max or abs(ej) > cfg.e_max or not t_ok:
            counts[C_RANGE] += 1
            fl |= REJECTED_BIT
        if fl & REJECTED_BIT:
            irows[R_FLAGS, j] = fl
            st.chain[0] = 0                       # the next good sample restarts the chain
            if where == _RESET:
                st.last_t[0] = np.nan             # time order is judged within a session
            continue
        cont = st.chain[0] != 0 and where == _NEXT
        backwards = where == _NEXT and tj <= st.last_t[0]   # False while no sample was accepted (NaN)
        if backwards:
            counts[C_BACK] += 1
            fl |= GAP_BIT
            cont = False
        elif where == _NEXT and abs((tj - st.last_t[0]) * cfg.inv_ts - 1.0) > INTERVAL_TOLERANCE:
            counts[C_INTERVAL] += 1               # (False while no sample was accepted: NaN)
        stale = False
        if cont and cfg.stale_detection and vj == st.last_v_raw[0]:
            stale = abs(vj) > cfg.omega or ej != st.last_e[0]   # repeated while moving
        v_used = vj
        pause = PAUSE_NONE
        if cont:
            # ---- 3. residual of the previous step, eq. 2.13 ----------------------------------------
            base = _linear(cfg, bpub, st.last_e[0], st.last_v_used[0])
            f_pred = st.f_next[0]
            v_pred = base + (f_pred if math.isfinite(f_pred) else 0.0)
            rows[R_VPRED, j] = v_pred
            if stale:
                counts[C_STALE] += 1
                fl |= STALE_BIT
                rows[R_F, j] = f_pred             # predict only
                rows[R_FVAR, j] = st.f_next_var[0]
                v_used = v_pred                   # the model's velocity stands in for the repeat
            else:
                resid = vj - base
                rows[R_RESID, j] = resid
                # the publishing tracker's armed prediction, before the update changes it
                before = (pst[core.F_YM], pst[core.F_SF2], pst[core.F_SY2], pst[core.F_S02], pst[core.F_SN2])
                beta_before = (fst[core.F_YM], fst[core.F_SY2], fst[core.F_S02])
                resid_trk = vj - _linear(cfg, bs.beta_trk, st.last_e[0], st.last_v_used[0]) if joint and not dual \
                    else resid
                # the disturbance model had its chance (search): the model-validity test judges the drive only
                # then (online β learns throughout: its instrument does not see a disturbance's onset)
                settled = sint[S_COUNT] >= sint[S_FREEZE]
                # ---- 4. KRLS-T update (steps 3–5) with v(j−1) at the armed x(j−1), β and ν -----------
                nu = np.nan
                if joint:
                    bt.regressor(form_force, i_sp, i_sn, i_one, cfg.omega, st.last_e[0], st.last_v_used[0], z)
                    # gate np.bool_(True), not the literal True: one compiled joint_update for every caller
                    learned = bt.joint_update(tr, bs, z, vj, np.bool_(True), obuf, bout)
                    if learned:
                        nu = bout[bt.B_NU]
                        rows[R_F, j] = bout[bt.B_FILTERED] if apply else obuf[core.O_FILT]
                else:
                    learned = core.update(tr, resid, obuf)
                    if learned:
                        R0 = beta_before[2] * beta_before[1]  # the prediction's variance, eq. 2.17/2.20
                        nu = (resid - beta_before[0]) / math.sqrt(R0) if R0 > 0.0 else np.nan
                        rows[R_F, j] = obuf[core.O_FILT]                      # ŷ + σ_f²(y − ŷ)/σ_y²
                if dual and learned:                  # the disturbance published by its own tracker, whose
                    learned = core.update(tp, resid, obuf)   # innovations are what the validity test judges
                    if learned:
                        rows[R_F, j] = obuf[core.O_FILT]
                        Rp = before[3] * before[2]
                        nu = (resid - before[0]) / math.sqrt(Rp) if Rp > 0.0 else np.nan
                if learned:
                    _, R, c2, noise2 = _learned(st, ring, sint, sflt, before, resid_trk, vj,
                                                st_ref_prev if vref.shape[0] else np.nan)
                    # calibrated variance of the filtered f: the gain g = σ_f²/σ_y² on a prediction that
                    # errs by c²·P and a noise σ_ε²                                                (C2)
                    g = before[1] / before[2] if before[2] > 0.0 else 0.0
                    rows[R_FVAR, j] = (1.0 - g) ** 2 * c2 * before[3] * before[1] + g * g * noise2
                    irows[R_REMOVED, j] = int(obuf[core.O_REMOVED])
                    if obuf[core.O_REDUCED] != 0.0:
                        fl |= REDUCED_BIT
                    st.trained[0] += 1
                    counts[C_TRAINED] += 1
                    if st.trained[0] <= cfg.warmup:
                        fl |= WARMUP_BIT
                    if math.isfinite(nu) and settled:
                        lv0 = hs.level[0]
                        if hl.health_sample(hs, nu) != lv0:   # model validity: EWMA of ν²
                            report_now = True     # a change of the validity level is reported at once
                    count = sint[S_COUNT]
                    poor = sflt[Q_NU2] > sflt[Q_POOR] or sflt[Q_E2] > sflt[Q_POOR] * noise2
                    if poor and count >= sint[S_NEXT_RETRY]:
                        pause = PAUSE_POOR
                    elif count >= sint[S_NEXT_TICK]:
                        pause = PAUSE_ROUTINE
                else:                              # nothing armed (e.g. right after a restore)
                    counts[C_RESTART] += 1
                    fl |= WARMUP_BIT
        else:
            counts[C_RESTART] += 1
            fl |= WARMUP_BIT
        # ---- 5. forget + predict f(j) at x(j) (steps 1–2), armed for the next update ----------------
        was_empty = tr.ist[core.I_N] == 0
        x_s[0] = tj
        theta_data = np.nan
        if sp.shape[1] > j and (math.isfinite(sp[0, j]) or math.isfinite(sp[1, j])):
            theta_data = _theta(cfg, st, sp, j, tj, where == _RESET or backwards, counts)
        if xbuf.shape[0] == 2 or xpub.shape[0] == 2:
            x_s[1] = theta_data if math.isfinite(theta_data) else \
                _theta(cfg, st, sp, j, tj, where == _RESET or backwards, counts)
        sflt[Q_THETA] = theta_data
        if joint:
            bt.joint_arm(tr, bs, xbuf, obuf)
            f_next = obuf[core.A_MEAN] if apply else fst[core.F_YM]
        else:
            core.arm(tr, xbuf, obuf)
            f_next = obuf[core.A_MEAN]
        if dual:
            was_empty = tp.ist[core.I_N] == 0
            core.arm(tp, xpub, obuf)
            f_next = obuf[core.A_MEAN]
        # the calibrated variance of the prediction: c² × what the tracker expects (C1)
        f_next_var = np.nan if was_empty else sflt[Q_C2] * pst[core.F_SF2] * pst[core.F_S02]
        rows[R_FNEXT, j] = f_next
        rows[R_FNEXTVAR, j] = f_next_var
        rows[R_BETA1, j] = bpub[0]
        irows[R_FLAGS, j] = fl
        irows[R_SIZE, j] = tp.ist[core.I_N]
        st.chain[0] = 1
        st.last_t[0] = tj
        st.last_e[0] = ej
        st.last_v_raw[0] = vj
        st.last_v_used[0] = v_used
        st.f_next[0] = f_next
        st.f_next_var[0] = f_next_var
        st_ref_prev = vref[j] if vref.shape[0] else np.nan
        sflt[Q_REF] = st_ref_prev
        # ---- 6. health report about once per tick_period of data time -------------------------------
        if not (st.tick_t[0] <= tj) and st.tick_t[0] != -np.inf:   # first sample, or time went back
            st.tick_t[0] = tj
            st.tick_n[0] = 0
        st.tick_n[0] += 1
        if report_now or (tj - st.tick_t[0] >= cfg.tick_period and st.tick_n[0] >= cfg.tick_min):
            if nticks < ticks.shape[0]:
                _tick(cfg, bs, hs, s, tj, ticks, nticks, scr, p)
                nticks += 1
                st.tick_t[0] = tj
                st.tick_n[0] = 0
            else:                                 # (cannot happen with new_ticks' bound) report at the next sample
                st.tick_t[0] = -np.inf
        if pause != PAUSE_NONE:                   # a search of the disturbance model is due: hand over
            sint[S_PAUSE] = pause
            sint[S_STOP] = j + 1
            break
    counts[C_TICKS] += nticks
    counts[C_BETA_UPDATES] += bs.cnt[bt.C_UPDATES] - updates0
    return first
