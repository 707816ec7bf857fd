"""Online feed-drive disturbance tracking: residual → KRLS-T, one ``@njit`` loop per block.

The numerics of the monitor's per-sample path (method §6, "Timing in the monitor"):
for each arriving sample ``j`` of a block,

1. classify it: non-finite or absurd values are *rejected*; the first sample, one
   after a gap, a rejected sample or time going backwards *restarts* the regressor
   chain; a repeated measured velocity while the axis moves is *stale* (the
   thesis' recording glitch);
2. residual of the previous step, eq. 2.13: ``v(j−1) = v_m(j) − βᵀ z(j−1)``, with
   ``z`` of method §2 (the model's prediction stands in for a stale ``v_m``);
3. KRLS-T update with that residual (:func:`kernels._krlst_core.update`, steps 3–5)
   unless the sample restarts the chain or is stale;
4. forgetting and one-step-ahead prediction at ``x(j)`` (:func:`kernels._krlst_core.arm`,
   steps 1–2), reused by the next update.

:func:`track_block` runs that loop without allocation; ``monitor.estimator`` is
the thin Python API around it (stumpy-style split).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from . import _krlst_core as core

__all__ = ["COUNTERS", "CARRY", "N_ROW", "new_carry", "track_block",
           "FLAG_STALE", "FLAG_GAP", "FLAG_REJECTED", "FLAG_WARMUP", "FLAG_REDUCED"]

# flags (the same bits as monitor.schema)
FLAG_STALE, FLAG_GAP, FLAG_REJECTED, FLAG_WARMUP, FLAG_REDUCED = 1, 2, 4, 8, 16

#: counter slots of the ``counts`` array
COUNTERS = ("duplicate", "out_of_order", "rejected_non_finite", "rejected_out_of_range", "gaps",
            "missing_samples", "time_backwards", "restarts", "stale", "trained")
(C_DUP, C_OOO, C_NONFINITE, C_RANGE, C_GAPS, C_MISSING, C_BACK, C_RESTART, C_STALE, C_TRAINED) = range(10)

#: slots of the ``carry`` array (state between blocks)
CARRY = ("has_prev", "seq", "t", "e", "v_raw", "v_used", "chain", "f_next", "f_next_var", "trained")
(K_HAS, K_SEQ, K_T, K_E, K_VRAW, K_VUSED, K_CHAIN, K_FNEXT, K_FNEXTVAR, K_TRAINED) = range(10)

#: columns of the float output rows
N_ROW = 6  # v_pred, residual, f, f_var, f_next, f_next_var
R_VPRED, R_RESID, R_F, R_FVAR, R_FNEXT, R_FNEXTVAR = range(N_ROW)


def new_carry() -> np.ndarray:
    """Carry for a fresh axis: no previous sample."""
    c = np.full(len(CARRY), np.nan)
    c[K_HAS] = 0.0
    c[K_CHAIN] = 0.0
    c[K_TRAINED] = 0.0
    return c


@njit(cache=True, nogil=True)
def _linear(beta, coulomb, omega, force_input, e, v):
    """``βᵀ z(k)`` of method §2 for one sample (velocity-loop or force-input form)."""
    acc = beta[0] * e + beta[1] * v
    if coulomb:
        if v > omega:
            acc -= beta[2]                        # −σ_p column
        elif v < -omega:
            acc -= beta[3]                        # −σ_n column
    if force_input:
        acc += beta[beta.shape[0] - 1]            # constant column (force offset)
    return acc


@njit(cache=True, nogil=True)
def track_block(state, beta, coulomb, omega, force_input, limits, stale_detection, warmup,
                carry, seq0, t, e, v, rows, dict_size, removed, flags, counts, xbuf, obuf):
    """Process one block of samples (method §6); returns the number of leading samples dropped.

    ``state``: the tracker's :class:`kernels._krlst_core.State` (``KRLST.core_state``).
    ``limits = [v_max, e_max, t_max]``; ``rows`` (n, :data:`N_ROW`), ``dict_size``,
    ``removed``, ``flags`` (n,) receive one row per sample from index ``first`` on
    (the return value: samples whose sequence number is not newer than the last one
    seen are dropped — duplicates and out-of-order). ``counts`` accumulates the
    :data:`COUNTERS`; ``carry`` (:data:`CARRY`) links consecutive blocks.
    ``xbuf`` (1,) and ``obuf`` (≥ ``core.N_OUT``,) are scratch.
    """
    st = core.unowned(state)                      # (no reference counting in the calls below)
    n = t.shape[0]
    first = 0
    if carry[K_HAS] != 0.0 and seq0 <= carry[K_SEQ]:
        last_seen = int(carry[K_SEQ])
        first = min(n, last_seen + 1 - seq0)
        if seq0 + first - 1 == last_seen:
            counts[C_DUP] += 1
            counts[C_OOO] += first - 1
        else:
            counts[C_OOO] += first
    for j in range(first, n):
        seq = seq0 + j
        tj, ej, vj = t[j], e[j], v[j]
        r = rows[j]
        for c in range(N_ROW):
            r[c] = np.nan
        removed[j] = -1
        fl = 0
        # ---- 1. classify ------------------------------------------------------------------
        if not (math.isfinite(tj) and math.isfinite(ej) and math.isfinite(vj)):
            counts[C_NONFINITE] += 1
            fl = FLAG_REJECTED
        elif abs(vj) > limits[0] or abs(ej) > limits[1] or abs(tj) > limits[2]:
            counts[C_RANGE] += 1
            fl = FLAG_REJECTED
        if fl == FLAG_REJECTED:
            flags[j] = fl
            dict_size[j] = st.ist[core.I_N]
            carry[K_HAS] = 1.0
            carry[K_SEQ] = seq
            carry[K_CHAIN] = 0.0                   # the next good sample restarts the chain
            continue
        # ordering is checked against the last sample seen (rejected ones included for seq,
        # the last accepted one for time), whether or not the chain is intact
        has = carry[K_HAS] != 0.0
        cont = has and carry[K_CHAIN] != 0.0
        if has and seq > carry[K_SEQ] + 1:
            counts[C_GAPS] += 1
            counts[C_MISSING] += seq - int(carry[K_SEQ]) - 1
            fl |= FLAG_GAP
            cont = False
        elif has and tj <= carry[K_T]:            # False while no sample was accepted (NaN)
            counts[C_BACK] += 1
            fl |= FLAG_GAP
            cont = False
        stale = False
        if cont and stale_detection and vj == carry[K_VRAW]:
            stale = abs(vj) > omega or ej != carry[K_E]   # repeated while moving
        v_used = vj
        if cont:
            # ---- 2. residual of the previous step, eq. 2.13 -------------------------------------
            base = _linear(beta, coulomb, omega, force_input, carry[K_E], carry[K_VUSED])
            f_pred = carry[K_FNEXT]
            r[R_VPRED] = base + (f_pred if math.isfinite(f_pred) else 0.0)
            if stale:
                counts[C_STALE] += 1
                fl |= FLAG_STALE
                r[R_F] = f_pred                    # predict only
                r[R_FVAR] = carry[K_FNEXTVAR]
                v_used = r[R_VPRED]                # the model's velocity stands in for the repeat
            else:
                resid = vj - base
                r[R_RESID] = resid
                # ---- 3. KRLS-T update (steps 3–5) with v(j−1) at the armed x(j−1) -------------
                if core.update(st, resid, obuf):
                    s02 = obuf[core.O_S02]
                    r[R_F] = obuf[core.O_FILT]     # filtered f: ŷ + σ_f²(y − ŷ)/σ_y²
                    r[R_FVAR] = obuf[core.O_FILTVAR] * s02   # (σ_f² − σ_f⁴/σ_y²)·s0²
                    removed[j] = int(obuf[core.O_REMOVED])
                    if obuf[core.O_REDUCED] != 0.0:
                        fl |= FLAG_REDUCED
                    carry[K_TRAINED] += 1.0
                    counts[C_TRAINED] += 1
                    if carry[K_TRAINED] <= warmup:
                        fl |= FLAG_WARMUP
                else:                              # nothing armed (e.g. right after a restore)
                    counts[C_RESTART] += 1
                    fl |= FLAG_WARMUP
        else:
            counts[C_RESTART] += 1
            fl |= FLAG_WARMUP
        # ---- 4. forget + predict f(j) at x(j) (steps 1–2), armed for the next update ----------
        was_empty = st.ist[core.I_N] == 0
        xbuf[0] = tj
        core.arm(st, xbuf, obuf)
        r[R_FNEXT] = obuf[core.A_MEAN]
        r[R_FNEXTVAR] = np.nan if was_empty else obuf[core.A_SF2] * st.fst[core.F_S02]
        flags[j] = fl
        dict_size[j] = st.ist[core.I_N]
        carry[K_HAS] = 1.0
        carry[K_SEQ] = seq
        carry[K_T] = tj
        carry[K_E] = ej
        carry[K_VRAW] = vj
        carry[K_VUSED] = v_used
        carry[K_CHAIN] = 1.0
        carry[K_FNEXT] = r[R_FNEXT]
        carry[K_FNEXTVAR] = r[R_FNEXTVAR]
    return first
