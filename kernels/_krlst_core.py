"""Allocation-free ``@njit`` core of the KRLS-T tracker (method §6, thesis eq. 2.14–2.22).

Reference: kafbox ``lib/krlst.m`` (S. Van Vaerenbergh), back-to-the-prior forgetting. The public class
is :class:`kernels.krlst.KRLST`; this module holds only the numerics, on the :class:`State` of
:mod:`kernels._krlst_state` (its slots, storage and named slots are described there). Kernel values
come from :mod:`kernels.covariance` (one formula per kernel).

Deferred rank-one updates
-------------------------
The rank-one (rank-two with a removal) updates of ``Q`` and ``Δ`` at the end of step ``t`` are stored
as *pending* vectors and applied inside the passes of step ``t+1`` (``q = Q k_t`` and ``h = Σq``), so
each matrix is swept once per step. :func:`predict` applies pending updates on the fly without
writing; ``KRLST`` materialises them for its ``Q``/``Sigma`` properties. The ``h`` pass also yields
``K_D q`` (for ``refine``): ``h = Σ q = c·Dq + K_D q``.

Uniform-grid lag table
----------------------
For a stationary kernel on a scalar time input sampled on a grid of step ``Ts``, ``k(t − t_i)``
depends on the integer lag ``L = (t − t_i)/Ts`` only: ``tab[L] = k(L·Ts)`` (:func:`build_lag_table`)
makes the ``k_t`` row ``n`` lookups instead of ``n`` ``exp``. A lag further than ``1e-6·Ts`` from an
integer falls back to the direct evaluation. A kernel with a squared-exponential envelope is 0 beyond
the lag where the envelope falls below :data:`~kernels.covariance.KERNEL_FLOOR`: the table ends there
with a ``0.0`` and every older dictionary entry gets 0 without evaluation (no subnormal arithmetic, no
``exp`` of old entries). Other kernels end at their first 0 or at ``nmax`` entries. Without a table
the row is :func:`kernels.covariance.kernel_row_phased` (the sines of periodic factors from each
slot's cached phases ``Ph``).

Split step (predict_next / update)
----------------------------------
:func:`learn` is :func:`arm` (steps 1–2: forget, then predict at ``x``) followed by :func:`update`
(steps 3–5, or 6 on the first sample). :func:`arm` writes the forgetting into the state and keeps
everything the update needs ("armed"): ``k_t, q, h`` and ``k_t − K_D q`` in rows of ``P``,
``k_tt, ŷ, γ², σ_f², σ_y²`` in ``fst`` and ``x`` in the free slot ``X[order[n]]``. The monitor arms on
``x(k+1)`` as soon as it arrives and publishes the prediction, then calls :func:`update` with the
residual once ``v_m(k+2)`` is known. Arming again without an update re-arms at the new ``x``.
:func:`track` runs ``[update(y_j)] + arm(x_j)`` over a block of arriving samples.

Accuracy of Q
-------------
kafbox's rank-one update can multiply the error of ``Q`` by up to ``|q|²/γ²`` (``γ² ≳ ε_j``) in one
step, and re-inverting alone does not hold it down. With ``ist[I_REFINE]`` the update uses
``q ← q + Q(k_t − K_D q)`` (one step of iterative refinement, sharing the ``Q μ_new`` sweep of the
pruning criterion). Every ``refresh_every`` steps (0 = never) :func:`refresh_inverse` recomputes ``Q``
from ``K_D`` by a Cholesky factorisation in the dense scratch ``A``; the new ``Q`` supersedes a
pending update.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from ._krlst_dense import _refresh_inverse, materialize, refresh_inverse  # noqa: F401 (re-exported)
from ._krlst_simd import LANES, SWEEP_ROWS, Stream, fmuladd, sweep
from ._krlst_state import (  # noqa: F401 (the state's names are the core's: core.I_N, core.state_of, …)
    A_G2,
    A_MEAN,
    A_SF2,
    A_SY2,
    F_DEN,
    F_DSC,
    F_G2,
    F_INVTS,
    F_JIT,
    F_KTT,
    F_LAM,
    F_NUM,
    F_QBINV,
    F_QSC,
    F_S02,
    F_SC,
    F_SF2,
    F_SN2,
    F_SY2,
    F_YM,
    FIELDS,
    I_ARMED,
    I_HW,
    I_M,
    I_N,
    I_QPEND,
    I_REFINE,
    I_REFRESH,
    I_SPEND,
    I_STEPS,
    LAG_TOL,
    LAYOUT,
    N_ARM,
    N_FST,
    N_IST,
    N_OUT,
    N_P,
    N_TRACK,
    N_W,
    O_FILT,
    O_FILTVAR,
    O_G2,
    O_MEAN,
    O_REDUCED,
    O_REMOVED,
    O_S02,
    O_SF2,
    O_SIZE,
    O_SY2,
    P_A,
    P_G,
    P_H,
    P_KT,
    P_P,
    P_Q,
    P_RES,
    STATE_FIELDS,
    T_LEARNED,
    T_NEXT,
    T_S02,
    T_SIZE,
    W_H,
    W_KQ,
    W_KT,
    W_M,
    W_Q,
    W_U,
    W_W,
    State,
    new_buffers,
    new_state,
    state_of,
    state_views,
    unowned,
    validate_state,
)
from .covariance import KERNEL_FLOOR, envelope_bound, kernel_phases, kernel_row_phased, kernel_value


@njit(cache=True, nogil=True)
def build_lag_table(kinds, params, cols, step, nmax, tab):
    """``tab[L] = k(L·Ts)`` for ``L < nmax`` (0 below :data:`~kernels.covariance.KERNEL_FLOOR`, as the
    direct evaluation); returns the length.

    A kernel with a squared-exponential envelope stays below the floor at every lag from the one where
    its bound ``B·exp(−d²/(2σ²))`` (:func:`~kernels.covariance.envelope_bound`) falls below it: the
    table ends there with one ``0.0``, the *zero tail* sentinel —
    :func:`_kernel_row` then takes every lag beyond the table as 0 instead of evaluating it. Any other
    kernel stops at its first 0 (lags beyond are evaluated directly) or at ``nmax`` entries; such a
    table never ends with ``0.0``."""
    env, bound = envelope_bound(kinds, params)     # |k(d)| ≤ bound · exp(−d²/(2 env²))
    x0 = np.zeros(1)
    x1 = np.zeros(1)
    for L in range(nmax):
        d = L * step
        if env < math.inf and bound * math.exp(-(d * d) / (2.0 * env * env)) < KERNEL_FLOOR:
            tab[L] = 0.0                           # the zero tail
            return L + 1
        x1[0] = d
        v = kernel_value(kinds, params, cols, x1, x0)
        if abs(v) < KERNEL_FLOOR:
            v = 0.0
        if v == 0.0 and env == math.inf:
            return L
        tab[L] = v
    L = nmax
    while L > 0 and tab[L - 1] == 0.0:             # only the sentinel may end a table with 0.0
        L -= 1
    return L


# ---- k_t ----------------------------------------------------------------------------------------

@njit(cache=True, nogil=True, inline="always")
def _off_table(dl, top, zero_tail):
    """The table cannot give ``k`` at the lag ``dl`` (grid steps): off the grid within the table, or beyond
    a table without zero tail (NaN: True). Branch-free, so that the row loop vectorises."""
    inside = dl <= top
    return (inside & (abs(dl - np.floor(dl + 0.5)) > LAG_TOL)) | ((not inside) & (not (zero_tail & (dl > top))))


@njit(cache=True, nogil=True, inline="always")
def _kernel_row(st, x, xph, hw, kt):
    """``k_t = k(D, x)`` into the slots of ``kt`` (zeros elsewhere, up to ``hw8``); returns ``k_tt = k(x,x) + ε_j``."""
    hw8 = (hw + LANES - 1) // LANES * LANES
    tab = st.tab
    ntab = tab.shape[0]
    invts = st.fst[F_INVTS]
    if invts > 0.0 and ntab > 0:
        X = st.X
        occ = st.occ
        x0 = x[0]
        top = ntab - 1.0
        zero_tail = tab[ntab - 1] == 0.0               # k = 0 beyond the table (build_lag_table)
        nbad = 0
        # nearest table entry; beyond the table tab[top], 0 in a zero tail (NaN: a valid index, and
        # evaluated directly below)
        for i in range(hw):
            dl = abs(x0 - X[i, 0]) * invts             # lag in grid steps
            nbad += _off_table(dl, top, zero_tail) & (occ[i] != 0.0)
            kt[i] = np.floor((dl if dl <= top else top) + 0.5)
        for i in range(hw):
            kt[i] = occ[i] * tab[np.int64(kt[i])]      # k(L Ts), computed once
        if nbad:                                       # off the grid, or beyond a table without zero tail: direct
            for i in range(hw):
                dl = abs(x0 - X[i, 0]) * invts
                if occ[i] != 0.0 and _off_table(dl, top, zero_tail):
                    kernel_row_phased(st.kinds, st.params, st.cols, X, st.Ph, occ, i, i + 1, x, xph, kt)
        ktt = tab[0]
    else:
        # lo = np.int64(0), not a literal 0: one compiled kernel_row_phased for both calls
        kernel_row_phased(st.kinds, st.params, st.cols, st.X, st.Ph, st.occ, np.int64(0), hw, x, xph, kt)
        ktt = 1.0                                      # k(x, x): every kernel is normalised (Kernel.diag)
    for i in range(hw, hw8):
        kt[i] = 0.0
    return ktt + st.fst[F_JIT]                         # k_tt = k(x, x) + ε_j


# ---- sweeps (kernels._krlst_simd) ----------------------------------------------------------------

_Q2_W = sweep(Stream(terms=2, store=True))            # Q ← Q + (sc p) pᵀ − (binv a) aᵀ;  Q k
_Q1_W = sweep(Stream(terms=1, store=True))            # Q ← Q + (sc p) pᵀ;  Q k
_Q2_R = sweep(Stream(terms=2))
_Q1_R = sweep(Stream(terms=1))
_Q0_R = sweep(Stream())                                # Q k
_QQ_R = sweep(Stream(vecs=2))                          # Q m, Q r
_S1_W = sweep(Stream(terms=1, store=True), Stream())   # D ← D − (cs g) gᵀ;  D q, K q
_S1_R = sweep(Stream(terms=1), Stream())
_S0_R = sweep(Stream(), Stream())


@njit(cache=True, nogil=True, inline="always")
def _sweep_q(st, hw, kt, q, write):
    """``q = Q k_t`` (2.17), applying the pending update of ``Q`` on the way (written back when ``write``):
    ``Q ← [[Q,0],[0,0]] + p pᵀ/γ²`` (2.15), then ``− a aᵀ/[Q_new]_rr`` for a removal (2.22)."""
    hw8 = (hw + LANES - 1) // LANES * LANES
    for i in range(hw8):
        q[i] = 0.0
    mode = st.ist[I_QPEND]
    sc = st.fst[F_QSC]
    nb = -st.fst[F_QBINV]
    p = st.P[P_P]
    a = st.P[P_A]
    Q = st.Q
    Qd = st.Qd
    for j in range(0, hw, SWEEP_ROWS):
        if mode == 2:
            if write:
                _Q2_W(j, hw8, Q, Qd, sc, p, nb, a, q, kt)
            else:
                _Q2_R(j, hw8, Q, Qd, sc, p, nb, a, q, kt)
        elif mode == 1:
            if write:
                _Q1_W(j, hw8, Q, Qd, sc, p, q, kt)
            else:
                _Q1_R(j, hw8, Q, Qd, sc, p, q, kt)
        else:
            _Q0_R(j, hw8, Q, Qd, q, kt)
    if write:
        st.ist[I_QPEND] = 0


@njit(cache=True, nogil=True, inline="always")
def _sweep_sigma(st, hw, c, q, h, kq, write):
    """``h = Σ q`` after the forgetting ``Σ ← λΣ + (1−λ)K_D`` (2.19) and ``kq = K_D q``.

    With ``Δ = Σ − K_D = c·D`` the forgetting is ``c ← λc`` (the caller passes the new ``c``), so the
    sweep only applies the pending part of 2.14, ``D ← D − g gᵀ/(c σ_y²)`` (written back when
    ``write``), and ``h = c·(D q) + K_D q``. When ``c`` falls below 1e-100 it is folded into ``D``.
    """
    hw8 = (hw + LANES - 1) // LANES * LANES
    D = st.D
    Dd = st.Dd
    if write and c < 1e-100:                      # keep D finite: D ← c D, c ← 1
        for j in range(hw):
            for i in range(j, hw8):
                D[j, i] *= c
            Dd[j] *= c
        st.fst[F_SC] *= c
        c = 1.0
    if write:
        st.fst[F_DSC] = c
    for i in range(hw8):
        h[i] = 0.0
        kq[i] = 0.0
    spend = st.ist[I_SPEND]
    ncs = -st.fst[F_SC]
    g = st.P[P_G]
    K = st.K
    Kd = st.Kd
    for j in range(0, hw, SWEEP_ROWS):
        if spend:
            if write:
                _S1_W(j, hw8, D, Dd, ncs, g, h, q, K, Kd, kq, q)
            else:
                _S1_R(j, hw8, D, Dd, ncs, g, h, q, K, Kd, kq, q)
        else:
            _S0_R(j, hw8, D, Dd, h, q, K, Kd, kq, q)
    for i in range(hw8):
        h[i] = c * h[i] + kq[i]                   # h = Σ q = c D q + K_D q
    if write:
        st.ist[I_SPEND] = 0


@njit(cache=True, nogil=True, inline="always")
def _sweep_qq(st, hw, m, r_, u, w):
    """``u = Q m`` and ``w = Q r`` in one read-only sweep (``Q`` has no pending update)."""
    hw8 = (hw + LANES - 1) // LANES * LANES
    for i in range(hw8):
        u[i] = 0.0
        w[i] = 0.0
    for j in range(0, hw, SWEEP_ROWS):
        _QQ_R(j, hw8, st.Q, st.Qd, u, m, w, r_)


@njit(cache=True, nogil=True, inline="always")
def _dot(a, b, n):
    """``Σ_{i<n} a_i b_i`` in a fixed order (8 lanes, as the sweeps; ``n`` a multiple of 8)."""
    s0 = s1 = s2 = s3 = s4 = s5 = s6 = s7 = 0.0
    for i in range(0, n, LANES):
        s0 = fmuladd(a[i], b[i], s0)
        s1 = fmuladd(a[i + 1], b[i + 1], s1)
        s2 = fmuladd(a[i + 2], b[i + 2], s2)
        s3 = fmuladd(a[i + 3], b[i + 3], s3)
        s4 = fmuladd(a[i + 4], b[i + 4], s4)
        s5 = fmuladd(a[i + 5], b[i + 5], s5)
        s6 = fmuladd(a[i + 6], b[i + 6], s6)
        s7 = fmuladd(a[i + 7], b[i + 7], s7)
    return ((s0 + s1) + (s2 + s3)) + ((s4 + s5) + (s6 + s7))


# ---- steps 1–2: arm ------------------------------------------------------------------------------

@njit(cache=True, nogil=True)
def arm(st, x, out):
    """Steps 1–2 at ``x``, in place ("predict_next"): forget, predict, keep what the update needs.

    ``out[A_*] = ŷ, σ_f², σ_y², γ²`` (normalised). On an empty dictionary only ``x`` and
    ``k_tt`` are kept and the prior predictive ``0, k_tt, sn2 + k_tt, k_tt`` is reported.
    Arming again before :func:`update` forgets once more and predicts at the new ``x``.
    """
    _arm(unowned(st), x, out)


@njit(cache=True, nogil=True, inline="always")
def _arm(st, x, out):
    """:func:`arm` on an unowned state. (The helpers are inlined: numba increments and decrements
    the reference count of each of a ``State``'s arrays at every call boundary.)"""
    ist = st.ist
    fst = st.fst
    n = ist[I_N]
    hw = ist[I_HW]
    lam = fst[F_LAM]
    sn2 = fst[F_SN2]
    s = st.order[n]                               # free slot: where step 3 puts x
    for c in range(x.shape[0]):
        st.X[s, c] = x[c]
    xph = st.Ph[s]
    kernel_phases(st.kinds, st.params, st.cols, x, xph)
    ist[I_ARMED] = 1
    if n == 0:
        ktt = kernel_value(st.kinds, st.params, st.cols, x, x) + fst[F_JIT]   # k = k(x, x) + ε_j
        _armed(fst, out, ktt, 0.0, ktt, ktt, sn2 + ktt)
        return
    hw8 = (hw + LANES - 1) // LANES * LANES
    kt = st.P[P_KT]
    q = st.P[P_Q]
    h = st.P[P_H]
    mu = st.mu

    # ---- 1. forget, μ part (2.19); the Σ part is the λ of the Δ sweep --------------------------
    sl = math.sqrt(lam)
    for i in range(hw8):
        mu[i] = sl * mu[i]                        # μ ← √λ μ

    # ---- 2. predict (2.17) -----------------------------------------------------------------------
    ktt = _kernel_row(st, x, xph, hw, kt)         # k_t = k(D, x),  k_tt = k(x, x) + ε_j
    _sweep_q(st, hw, kt, q, True)                 # q = Q k_t
    y_mean = _dot(q, mu, hw8)                     # ŷ = qᵀ μ
    gamma2 = ktt - _dot(kt, q, hw8)               # γ² = k_tt − k_tᵀ q
    gamma2 = max(gamma2, 0.0)
    kq = st.W[W_KQ]
    _sweep_sigma(st, hw, lam * fst[F_DSC], q, h, kq, True)   # Σ ← λΣ + (1−λ)K_D;  h = Σ q, K_D q
    if ist[I_REFINE] != 0:
        res = st.P[P_RES]
        for i in range(hw8):
            res[i] = kt[i] - kq[i]                # k_t − K_D q, for the refinement of q
    sf2 = gamma2 + _dot(q, h, hw8)                # σ_f² = γ² + qᵀ h
    sf2 = max(sf2, 0.0)
    _armed(fst, out, ktt, y_mean, gamma2, sf2, sn2 + sf2)   # σ_y² = sn2 + σ_f²


@njit(cache=True, nogil=True, inline="always")
def _armed(fst, out, ktt, y_mean, gamma2, sf2, sy2):
    fst[F_KTT] = ktt
    fst[F_YM] = y_mean
    fst[F_G2] = gamma2
    fst[F_SF2] = sf2
    fst[F_SY2] = sy2
    out[A_MEAN] = y_mean
    out[A_SF2] = sf2
    out[A_SY2] = sy2
    out[A_G2] = gamma2


# ---- steps 3–6: update -------------------------------------------------------------------------

@njit(cache=True, nogil=True, inline="always")
def _init(st, y, out):
    """Step 6, eq. 2.16 (first sample, armed): ``Q = 1/k``, ``μ = y k/(k+sn2)``, ``Σ = k − k²/(k+sn2)``."""
    fst = st.fst
    ist = st.ist
    sn2 = fst[F_SN2]
    k = fst[F_KTT]                                # k = k(x, x) + ε_j  (x is in X[order[0]])
    s = st.order[0]
    st.Kd[s] = k                                  # K_D = k
    st.Qd[s] = 1.0 / k                            # Q = 1 / k
    st.mu[s] = y * k / (k + sn2)                  # μ = y k / (k + sn2)
    st.Dd[s] = -(k * k / (k + sn2)) / fst[F_DSC]  # Σ = k − k² / (k + sn2),  Δ = Σ − K_D = c D
    st.occ[s] = 1.0
    fst[F_NUM] = y * y / (k + sn2)                # num = y² / (k + sn2)
    fst[F_DEN] = 1.0                              # den = 1
    fst[F_S02] = fst[F_NUM] / fst[F_DEN]          # s0² = num / den
    ist[I_N] = 1
    ist[I_HW] = s + 1
    ist[I_STEPS] += 1
    # report the prior predictive of this first sample (kafbox writes zeros on this row)
    _write_out(out, y, 0.0, sn2 + k, k, k, -1.0, 0.0, fst[F_S02], 1)


@njit(cache=True, nogil=True, error_model="numpy")
def _criterion(u, q, Qd, sc, pm, hw8, crit):
    """``crit_i = |[Q_new μ_new]_i / [Q_new]_ii|`` for all slots at once (so that it vectorises; a
    free slot gives 0/0 = NaN, which no comparison picks); returns the smallest."""
    for i in range(hw8):
        qii = Qd[i] + sc * (q[i] * q[i])          # [Q_new]_ii
        qmu = u[i] + sc * (q[i] * pm)             # [Q_new μ_new]_i
        crit[i] = abs(qmu / qii)                  # |[Q μ]_i / Q_ii|, MSE pruning criterion
    m0 = m1 = m2 = m3 = m4 = m5 = m6 = m7 = np.inf
    for i in range(0, hw8, LANES):                # min is exact in any order: 8 independent chains
        m0 = min(m0, crit[i])
        m1 = min(m1, crit[i + 1])
        m2 = min(m2, crit[i + 2])
        m3 = min(m3, crit[i + 3])
        m4 = min(m4, crit[i + 4])
        m5 = min(m5, crit[i + 5])
        m6 = min(m6, crit[i + 6])
        m7 = min(m7, crit[i + 7])
    return min(min(min(m0, m1), min(m2, m3)), min(min(m4, m5), min(m6, m7)))


@njit(cache=True, nogil=True, inline="always")
def _update(st, y, out):
    """Steps 3–5 for ``n ≥ 1`` from the armed prediction (eq. 2.14, 2.15, 2.20–2.22)."""
    ist = st.ist
    fst = st.fst
    order = st.order
    n = ist[I_N]
    hw = ist[I_HW]
    M = ist[I_M]
    lam = fst[F_LAM]
    jit = fst[F_JIT]
    P = st.P
    kt = P[P_KT]
    q = P[P_Q]
    h = P[P_H]
    p = P[P_P]
    a = P[P_A]
    g = P[P_G]
    m = st.W[W_M]
    u = st.W[W_U]
    mu = st.mu
    ktt = fst[F_KTT]
    y_mean = fst[F_YM]
    gamma2 = fst[F_G2]
    sf2 = fst[F_SF2]
    sy2 = fst[F_SY2]
    err = y - y_mean
    e = err / sy2                                 # (y − ŷ) / σ_y²
    cs = 1.0 / sy2

    # ---- 4. signal power (2.20, with the square) ---------------------------------------------------
    fst[F_NUM] += lam * err * err / sy2           # num ← num + λ (y − ŷ)² / σ_y²
    fst[F_DEN] += lam                             # den ← den + λ
    fst[F_S02] = fst[F_NUM] / fst[F_DEN]          # s0² = num / den

    # ---- 3. posterior of f at [D; x] (2.14), μ part -----------------------------------------------
    s = order[n]                                  # free slot for the new basis (x is there)
    hwn = hw if s < hw else s + 1
    hw8 = (hwn + LANES - 1) // LANES * LANES
    for i in range(hw8):
        m[i] = mu[i] + e * h[i]                   # μ_new = [μ; ŷ] + (y − ŷ)/σ_y² [h; σ_f²]
    m[s] = y_mean + e * sf2

    # ---- 5. which basis to prune (2.21–2.22) ---------------------------------------------------------
    r = -1                                        # logical index to remove, -1: none
    g2q = gamma2                                  # γ² of the Q update (refined below)
    prune = n + 1 > M
    refine = ist[I_REFINE] != 0
    if not (gamma2 >= jit and gamma2 > 0.0):
        r = n                                     # roundoff guard: drop the new sample (also γ² = 0 with
                                                  # ε_j = 0, and a NaN γ² of a damaged state)
    elif prune or refine:
        # u = Q μ_new (row/column s of Q is zero); with refine also w = Q (k_t − K_D q), one
        # step of iterative refinement for the Q update: q ← q + w, γ² ← k_tt − k_tᵀ q. Without
        # it the update multiplies the error of Q by up to ~|q|²/γ² ≲ 1/ε_j (kafbox's recursion).
        # (ŷ, γ², σ² reported and the μ, Σ updates keep the unrefined q, as kafbox.)
        w = st.W[W_W]
        if prune and refine:
            _sweep_qq(st, hwn, m, P[P_RES], u, w)
        elif prune:
            _sweep_q(st, hwn, m, u, False)        # (no pending Q update: arm applied it)
        else:
            _sweep_q(st, hwn, P[P_RES], w, False)
        if refine:
            for i in range(hw8):
                w[i] = q[i] + w[i]                # refined q
            g2r = ktt - _dot(kt, w, hw8)
            if g2r > 0.0:
                g2q = g2r
                for i in range(hw8):
                    q[i] = w[i]
    if r < 0 and prune:
        # criterion on Q_new = [[Q,0],[0,0]] + p pᵀ/γ², p = [q; −1], without forming Q_new:
        #   [Q_new μ_new]_i = [Q μ_new]_i + p_i (pᵀ μ_new)/γ²,  [Q_new]_ii = Q_ii + p_i²/γ²
        sc = 1.0 / g2q
        q[s] = -1.0
        pm = _dot(q, m, hw8)                      # pᵀ μ_new
        crit = st.W[W_KT]
        best = _criterion(u, q, st.Qd, sc, pm, hw8, crit)
        for l in range(n + 1):                    # order[n] == s: the new sample is last
            if crit[order[l]] == best:            # first minimum, as Matlab's min
                r = l
                break
        if r < 0:
            r = n                                 # no finite criterion (a damaged state): drop the new
                                                  # sample rather than grow beyond the budget's slots
        q[s] = 0.0

    if r == n:
        # ---- reduced update: Q stays as before step 3, x is not added ---------------------------
        for i in range(hw8):
            mu[i] = m[i]                          # μ ← μ + (y − ŷ)/σ_y² h
            g[i] = h[i]                           # Σ ← Σ − h hᵀ/σ_y²   (pending)
        mu[s] = 0.0
        g[s] = 0.0
        _free_slot(st, s)                         # the slot stays free
        fst[F_SC] = cs / fst[F_DSC]
        ist[I_SPEND] = 1
        ist[I_STEPS] += 1
        _write_out(out, y, y_mean, sy2, sf2, gamma2, float(n), 1.0, fst[F_S02], n)
        return

    # ---- 3. update (2.14, 2.15): append x to D ------------------------------------------------------
    for i in range(hw8):
        mu[i] = mu[i] + e * h[i]                  # μ ← μ_new
        g[i] = h[i]
        p[i] = q[i]
    sc = 1.0 / g2q
    if r < 0:
        t = s                                     # the new basis stays in slot s
        ist[I_QPEND] = 1                          # Q ← [[Q,0],[0,0]] + p pᵀ/γ²  (pending)
        n_new = n + 1
        removed = -1.0
    else:
        # ---- 5. prune r (2.21–2.22); the new basis takes its slot ---------------------------------------
        t = order[r]
        Q = st.Q
        p[s] = -1.0
        for i in range(t):                        # a = [Q_new]_{:, r},  Q_new = [[Q,0],[0,0]] + p pᵀ/γ²
            a[i] = Q[i, t] + sc * (p[i] * p[t])
            Q[i, t] = 0.0                         # (row and column t of Q become those of the new basis: 0)
        a[t] = st.Qd[t] + sc * (p[t] * p[t])
        for i in range(t + 1, hw8):
            a[i] = Q[t, i] + sc * (p[i] * p[t])
            Q[t, i] = 0.0
        st.Qd[t] = 0.0
        fst[F_QBINV] = 1.0 / a[t]                 # Q ← Q_new[−r,−r] − a aᵀ/[Q_new]_rr  (pending)
        a[t] = a[s]                               # the new basis moves from slot s to t
        a[s] = 0.0
        p[s] = 0.0
        mu[s] = 0.0
        g[s] = 0.0
        for c in range(st.X.shape[1]):
            st.X[t, c] = st.X[s, c]
        for c in range(st.Ph.shape[1]):
            st.Ph[t, c] = st.Ph[s, c]
        _free_slot(st, s)
        for l in range(r, n - 1):                 # drop r from the logical order, the new basis last
            order[l] = order[l + 1]
        order[n - 1] = t
        order[n] = s
        ist[I_QPEND] = 2
        n_new = n
        removed = float(r)
    K, D = st.K, st.D
    ic = 1.0 / fst[F_DSC]
    for i in range(t):                            # K_D ← [[K_D, k_t], [k_tᵀ, k_tt]]  (row/column t)
        K[i, t] = kt[i]                           # Δ ← [[Δ, h − k_t], [·, σ_f² − k_tt]] ...
        D[i, t] = (h[i] - kt[i]) * ic
    for i in range(t + 1, hw8):
        K[t, i] = kt[i]
        D[t, i] = (h[i] - kt[i]) * ic
    st.Kd[t] = ktt
    st.Dd[t] = (sf2 - ktt) * ic
    mu[t] = y_mean + e * sf2
    g[t] = sf2                                    # ... − g gᵀ/σ_y²,  g = [h; σ_f²]  (pending)
    p[t] = -1.0                                   # p = [q; −1]
    st.occ[t] = 1.0
    fst[F_SC] = cs * ic
    ist[I_SPEND] = 1
    fst[F_QSC] = sc
    ist[I_N] = n_new
    ist[I_HW] = hwn
    ist[I_STEPS] += 1
    _write_out(out, y, y_mean, sy2, sf2, gamma2, removed, 0.0, fst[F_S02], n_new)


@njit(cache=True, nogil=True, inline="always")
def _free_slot(st, s):
    """Zero the input, phases and occupancy of slot ``s``."""
    for c in range(st.X.shape[1]):
        st.X[s, c] = 0.0
    for c in range(st.Ph.shape[1]):
        st.Ph[s, c] = 0.0
    st.occ[s] = 0.0


@njit(cache=True, nogil=True, inline="always")
def _write_out(out, y, y_mean, sy2, sf2, gamma2, removed, reduced, s02, n):
    out[O_MEAN] = y_mean
    out[O_SY2] = sy2
    out[O_SF2] = sf2
    out[O_G2] = gamma2
    out[O_REMOVED] = removed
    out[O_REDUCED] = reduced
    out[O_FILT] = y_mean + sf2 * (y - y_mean) / sy2    # E[f(x) | y] = ŷ + σ_f² (y − ŷ)/σ_y²
    out[O_FILTVAR] = sf2 - sf2 * sf2 / sy2             # Var[f(x) | y] = σ_f² − σ_f⁴/σ_y²
    out[O_S02] = s02
    out[O_SIZE] = n


@njit(cache=True, nogil=True)
def update(st, y, out):
    """Steps 3–5 (or 6 on the first sample) with the armed prediction; False if nothing is armed.

    ``out[O_*]``. After the step, every ``refresh_every`` steps, ``Q`` is recomputed from ``K_D``.
    """
    return _update_step(unowned(st), y, out)


@njit(cache=True, nogil=True, inline="always")
def _update_step(st, y, out):
    """:func:`update` on an unowned state."""
    ist = st.ist
    if ist[I_ARMED] == 0:
        return False
    ist[I_ARMED] = 0
    if ist[I_N] == 0:
        _init(st, y, out)
    else:
        _update(st, y, out)
    every = ist[I_REFRESH]
    if every > 0 and ist[I_STEPS] % every == 0:
        _refresh_inverse(st)
    return True


@njit(cache=True, nogil=True)
def learn(st, x, y, out):
    """One sample: :func:`arm` at ``x`` then :func:`update` with ``y`` (steps 1–5, or 6 first)."""
    st = unowned(st)
    arm(st, x, out)
    update(st, y, out)


@njit(cache=True, nogil=True)
def learn_many(st, xs, ys, outs):
    """:func:`learn` over a stream; ``outs[t]`` receives the ``out`` row of sample ``t``."""
    st = unowned(st)
    for t in range(ys.shape[0]):
        learn(st, xs[t], ys[t], outs[t])


@njit(cache=True, nogil=True)
def track(st, xs, ys, learn_mask, outs):
    """Monitor block: for each arriving sample ``j`` in order, ``update(ys[j])`` if
    ``learn_mask[j]`` (``ys[j]``: the residual of the previously armed ``x``), then
    ``arm(xs[j])``.

    ``outs[j]`` (width :data:`N_TRACK`): ``[0, N_OUT)`` the ``out`` of the update (NaN when
    not learned), ``[T_NEXT, T_NEXT + N_ARM)`` the new prediction (``A_*``), ``T_S02`` s0²,
    ``T_SIZE`` n after sample ``j``, ``T_LEARNED`` 1.0 if an update ran (mask set and armed).
    """
    st = unowned(st)
    for j in range(xs.shape[0]):
        o = outs[j]
        learned = False
        if learn_mask[j]:
            learned = update(st, ys[j], o)
        if not learned:
            for c in range(N_OUT):
                o[c] = np.nan
        arm(st, xs[j], o[T_NEXT:T_NEXT + N_ARM])
        o[T_S02] = st.fst[F_S02]
        o[T_SIZE] = st.ist[I_N]
        o[T_LEARNED] = 1.0 if learned else 0.0


@njit(cache=True, nogil=True)
def predict(st, x, forget, out):
    """:func:`_predict` (see there) on ``st``."""
    _predict(unowned(st), x, forget, out)


@njit(cache=True, nogil=True, inline="always")
def _predict(st, x, forget, out):
    """``ŷ, σ_f², σ_y², γ²`` at ``x`` from the current state (2.17) into ``out[A_*]``; state untouched.

    With ``forget`` the forgetting (2.19) of the next step is applied virtually, so the
    numbers are bit-identical to what the next :func:`learn` reports for ``x``.
    """
    ist = st.ist
    fst = st.fst
    hw = ist[I_HW]
    hw8 = (hw + LANES - 1) // LANES * LANES
    lam = fst[F_LAM] if forget else 1.0
    W = st.W
    kt = W[W_KT]
    q = W[W_Q]
    h = W[W_H]
    xph = st.xph
    kernel_phases(st.kinds, st.params, st.cols, x, xph)
    ktt = _kernel_row(st, x, xph, hw, kt)
    _sweep_q(st, hw, kt, q, False)
    sl = math.sqrt(lam)
    mu = W[W_M]
    for i in range(hw8):
        mu[i] = sl * st.mu[i]
    y_mean = _dot(q, mu, hw8)
    gamma2 = ktt - _dot(kt, q, hw8)
    gamma2 = max(gamma2, 0.0)
    kq = W[W_KQ]
    _sweep_sigma(st, hw, lam * fst[F_DSC], q, h, kq, False)
    sf2 = gamma2 + _dot(q, h, hw8)
    sf2 = max(sf2, 0.0)
    out[A_MEAN] = y_mean
    out[A_SF2] = sf2
    out[A_SY2] = fst[F_SN2] + sf2
    out[A_G2] = gamma2


# ---- Python entry points: the two base buffers instead of a State (kernels._krlst_state) ---------

@njit(cache=True, nogil=True)
def arm_buffers(fbuf, ibuf, x, out):
    """:func:`arm` on ``state_of(fbuf, ibuf)``."""
    _arm(state_of(fbuf, ibuf), x, out)


@njit(cache=True, nogil=True)
def update_buffers(fbuf, ibuf, y, out):
    """:func:`update` on ``state_of(fbuf, ibuf)``."""
    return _update_step(state_of(fbuf, ibuf), y, out)


@njit(cache=True, nogil=True)
def learn_buffers(fbuf, ibuf, x, y, out):
    """:func:`learn` on ``state_of(fbuf, ibuf)``."""
    learn(state_of(fbuf, ibuf), x, y, out)


@njit(cache=True, nogil=True)
def predict_buffers(fbuf, ibuf, x, forget, out):
    """:func:`predict` on ``state_of(fbuf, ibuf)``."""
    _predict(state_of(fbuf, ibuf), x, forget, out)
