"""Allocation-free ``@njit`` core of the KRLS-T tracker (method §6, thesis eq. 2.14–2.22).

Reference: kafbox ``lib/krlst.m`` (S. Van Vaerenbergh), back-to-the-prior forgetting.
The public class is :class:`kernels.krlst.KRLST`; this module holds only the numerics.
Kernel values come from :mod:`kernels.covariance` (one formula per kernel).

Slots
-----
All matrices live in preallocated ``(M+1)×(M+1)`` buffers whose rows/columns are
*slots*. ``order[:n]`` lists the slots of the ``n`` dictionary elements in the
dictionary's logical order (kafbox's order, oldest first), ``order[n:]`` the free
slots. A free slot has an all-zero row and column in ``Q``, ``S`` (Σ) and ``K`` and
zero entries in ``mu`` and the pending vectors, so every matrix–vector product and
rank-one update runs over the contiguous range ``[0, hw)`` (``hw``: high-water mark
of used slots) without gathering: zeros contribute nothing. Adding a basis writes
one row/column into a free slot; removing one zeroes a row/column; nothing is
shifted, and no kernel value is recomputed. Only the pruning ``argmin`` walks the
logical order, so ties resolve to the first (oldest) element as Matlab's ``min``.

``Q``, ``S`` and ``K`` are stored full and kept *bitwise* symmetric: each element
update is an expression symmetric in ``(i, j)`` in floating point (for example
``Q[i,j] + c*(p[i]*p[j])``). Matrix–vector products use the symmetry to run
row-wise as contiguous axpys (``q += k[j] * Q[j, :]``), which LLVM vectorises
without reassociation, so the results do not depend on the vector width.

``K`` caches ``K_D = k(D, D) + ε_j I`` (the jitter on the diagonal, as ``Q ≈ K_D⁻¹``
is built from ``k_tt = k(x,x) + ε_j``), updated by one row/column per add/remove.

Deferred rank-one updates
-------------------------
The rank-one (rank-two with a removal) updates of ``Q`` and ``Σ`` at the end of
step ``t`` are stored as *pending* vectors and applied element by element inside
the first passes of step ``t+1`` (``q = Q k_t`` and ``Σ ← λΣ + (1−λ)K_D; h = Σq``),
so each matrix is swept once per step instead of twice. Every element gets exactly
the floating-point expression of the eager update, so the numbers are those of
the eager algorithm. :func:`predict` evaluates pending updates on the fly without
writing; ``KRLST`` materialises them for its ``Q``/``Sigma`` properties.

Uniform-grid lag table
----------------------
For a stationary kernel on a scalar time input sampled on a grid of step ``Ts``,
``k(t − t_i)`` depends on the integer lag ``L = (t − t_i)/Ts`` only. With a table
``tab[L] = kernel_value(L·Ts, 0)`` (built once by :func:`build_lag_table` from the
same ``kernel_value``) the ``k_t`` row costs ``n`` lookups instead of ``n``
``exp``/``sin`` evaluations. A lag further than ``1e-6·Ts`` from an integer falls
back to ``kernel_value``, and so does a lag beyond the table (which ends where the
kernel underflows to 0, or at ``nmax`` entries for a kernel that does not decay).

Split step (predict_next / update)
----------------------------------
:func:`learn` is :func:`arm` (steps 1–2: forget, then predict at ``x``) followed by
:func:`update` (steps 3–5, or 6 on the first sample). :func:`arm` writes the
forgetting into the state and keeps everything the update needs ("armed"):
``k_t, q, h`` in rows 3–5 of ``P``, ``k_tt, ŷ, γ², σ_f², σ_y²`` in ``fst`` and ``x``
itself in the free slot ``X[order[n]]`` (where step 3 puts it). The monitor arms
on ``x(k+1)`` as soon as it arrives and publishes the prediction, then calls
:func:`update` with the residual once ``v_m(k+2)`` is known. Arming again without an
update re-arms at the new ``x``; the forgetting is then applied once per :func:`arm`.
:func:`track` runs ``[update(y_j)] + arm(x_j)`` over a block of arriving samples.

Accuracy of Q: refinement and periodic re-inversion
---------------------------------------------------
kafbox's rank-one update multiplies the current error of ``Q`` by up to ~``|q|²/γ²``
(``γ² ≳ ε_j``) in a single step: with ``ε_j = 1e-6`` ``max|Q K_D − I|`` is ~3e-6
typically and exceeds 1e-5 on ~10 % of the steps (up to ~1e-3), and it is back at
that level ~100 steps after an exact re-inversion, so re-inverting alone cannot hold
it down. With ``ist[I_REFINE]`` the update uses ``q ← q + Q(k_t − K_D q)`` (one step
of iterative refinement; ``K_D q`` comes from the h pass) and the error stays
~1e-9. Every ``refresh_every`` steps (``ist``; 0 = never), at the end of
:func:`update`, :func:`refresh_inverse` recomputes ``Q`` from the cached ``K_D`` by a
Cholesky factorisation and triangular inverse in a dense scratch matrix that is
part of ``W`` (no allocation); the new ``Q`` supersedes a pending ``Q`` update.

Layout of the small arrays
--------------------------
``ist`` int64 ``[n, hw, M, steps, q_pending, s_pending, refresh_every, armed, refine]``
(``q_pending``: 0 none, 1 rank-one, 2 rank-one + removal downdate);
``fst`` float64 ``[λ, sn2, ε_j, num, den, s0², 1/γ², 1/[Q_new]_rr, 1/σ_y², 1/Ts,
k_tt, ŷ, γ², σ_f², σ_y²]`` (the last five: the armed prediction);
``P`` float64 ``(7, M+1)`` pending vectors ``p = [q; −1]``, ``a = [Q_new]_{:,r}``,
``g = [h; σ_f²]``, then the armed ``k_t, q, h, k_t − K_D q``; ``W`` float64
``(6 + M+1, M+1)`` scratch (not state): ``k_t, q, h`` of :func:`predict`, ``u, μ_new,
Q(k_t − K_D q)`` of :func:`update`, then the dense matrix of :func:`refresh_inverse`; ``out`` float64 ``(10,)`` ``ŷ, σ_y², σ_f², γ², removed,
reduced, filtered, filtered_var, s0², n``; the ``out`` of :func:`arm` and
:func:`predict` is ``ŷ, σ_f², σ_y², γ²``; a row of :func:`track` is described there.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from .covariance import kernel_row_at, kernel_value, kernel_value_at

N_OUT = 10
N_TRACK = 17
I_N, I_HW, I_M, I_STEPS, I_QPEND, I_SPEND, I_REFRESH, I_ARMED, I_REFINE = range(9)
(F_LAM, F_SN2, F_JIT, F_NUM, F_DEN, F_S02, F_QSC, F_QBINV, F_SC, F_INVTS,
 F_KTT, F_YM, F_G2, F_SF2, F_SY2) = range(15)
N_IST = 9
N_FST = 15
N_P = 7
N_W = 6
LAG_TOL = 1e-6


def new_state(budget: int, dim: int, forgetting: float, sn2: float, jitter: float, grid_step: float,
              refresh_every: int = 0, refine: bool = False):
    """Zeroed state buffers ``(X, Q, S, K, mu, order, ist, fst, P)`` for budget M and input dimension d."""
    cap = budget + 1
    X = np.zeros((cap, dim))
    Q = np.zeros((cap, cap))
    S = np.zeros((cap, cap))
    K = np.zeros((cap, cap))
    mu = np.zeros(cap)
    order = np.arange(cap, dtype=np.int64)
    ist = np.zeros(N_IST, dtype=np.int64)
    ist[I_M] = budget
    ist[I_REFRESH] = refresh_every
    ist[I_REFINE] = 1 if refine else 0
    fst = np.zeros(N_FST)
    fst[F_LAM] = forgetting
    fst[F_SN2] = sn2
    fst[F_JIT] = jitter
    fst[F_INVTS] = 0.0 if not grid_step else 1.0 / grid_step
    P = np.zeros((N_P, cap))
    return X, Q, S, K, mu, order, ist, fst, P


@njit(cache=True, nogil=True)
def build_lag_table(kinds, params, cols, step, nmax, tab):
    """``tab[L] = k(L·Ts)`` for ``L < nmax``, stopping where the kernel underflows to 0; returns the length."""
    x0 = np.zeros(1)
    x1 = np.zeros(1)
    for L in range(nmax):
        x1[0] = L * step
        v = kernel_value(kinds, params, cols, x1, x0)
        if v == 0.0:
            return L
        tab[L] = v
    return nmax


@njit(cache=True, nogil=True)
def _kernel_row(kinds, params, cols, X, order, n, hw, ist, fst, tab, x, kt):
    """``k_t = k(D, x)`` into the slots of ``kt`` (zeros elsewhere); returns ``k_tt = k(x,x) + ε_j``."""
    for i in range(hw):
        kt[i] = 0.0
    invts = fst[F_INVTS]
    ntab = tab.shape[0]
    if invts > 0.0 and ntab > 0:
        lim = ntab - 0.5
        for l in range(n):
            i = order[l]
            dl = abs(x[0] - X[i, 0]) * invts      # lag in grid steps
            if dl < lim:
                L = int(dl + 0.5)
                if abs(dl - L) <= LAG_TOL:
                    kt[i] = tab[L]                # k(L Ts), same kernel_value, computed once
                    continue
            kt[i] = kernel_value_at(kinds, params, cols, X, i, x)
        return tab[0] + fst[F_JIT]
    kernel_row_at(kinds, params, cols, X, order, n, x, kt)       # k_t = k(D, x)
    return kernel_value(kinds, params, cols, x, x) + fst[F_JIT]  # k_tt = k(x, x) + ε_j


@njit(cache=True, nogil=True)
def _q_pass(Q, P, ist, fst, hw, kt, q, write):
    """``q = Q k_t``, applying the pending update of ``Q`` on the way (written back when ``write``)."""
    for i in range(hw):
        q[i] = 0.0
    mode = ist[I_QPEND]
    p = P[0]
    a = P[1]
    sc = fst[F_QSC]
    binv = fst[F_QBINV]
    if mode == 0:
        for j in range(hw):
            kj = kt[j]
            for i in range(hw):
                q[i] += kj * Q[j, i]                            # q = Q k_t
    elif mode == 1:
        for j in range(hw):
            kj = kt[j]
            pj = p[j]
            for i in range(hw):
                v = Q[j, i] + sc * (pj * p[i])                  # Q ← [[Q,0],[0,0]] + p pᵀ/γ²  (2.15)
                if write:
                    Q[j, i] = v
                q[i] += kj * v
    else:
        for j in range(hw):
            kj = kt[j]
            pj = p[j]
            aj = a[j]
            for i in range(hw):
                # (2.15) then (2.22): Q ← Q_new[−r,−r] − Q_new[−r,r] Q_new[−r,r]ᵀ / Q_new[r,r]
                v = (Q[j, i] + sc * (pj * p[i])) - (aj * a[i]) * binv
                if write:
                    Q[j, i] = v
                q[i] += kj * v
    if write:
        ist[I_QPEND] = 0


@njit(cache=True, nogil=True)
def _h_pass(S, K, P, ist, fst, hw, lam, q, h, kq, want_kq, write):
    """``h = Σ q`` after ``Σ ← λΣ + (1−λ)K_D`` (2.19), applying the pending update of Σ on the way.

    With ``want_kq`` also ``kq = K_D q`` (for ``refine``): ``K_D`` is read anyway, but the
    extra accumulator costs ~10 %, so the loops exist in both forms.
    """
    for i in range(hw):
        h[i] = 0.0
    if want_kq:
        for i in range(hw):
            kq[i] = 0.0
    c1 = 1.0 - lam
    g = P[2]
    cs = fst[F_SC]
    if ist[I_SPEND] == 0:
        for j in range(hw):
            qj = q[j]
            if want_kq:
                for i in range(hw):
                    kji = K[j, i]
                    v = lam * S[j, i] + c1 * kji                # Σ ← λ Σ + (1 − λ) K_D
                    if write:
                        S[j, i] = v
                    h[i] += qj * v                              # h = Σ q
                    kq[i] += qj * kji                           # K_D q
            else:
                for i in range(hw):
                    v = lam * S[j, i] + c1 * K[j, i]            # Σ ← λ Σ + (1 − λ) K_D
                    if write:
                        S[j, i] = v
                    h[i] += qj * v                              # h = Σ q
    else:
        for j in range(hw):
            qj = q[j]
            gj = g[j]
            if want_kq:
                for i in range(hw):
                    kji = K[j, i]
                    v = S[j, i] - cs * (gj * g[i])              # Σ ← [[Σ,h],[hᵀ,σ_f²]] − g gᵀ/σ_y²  (2.14)
                    v = lam * v + c1 * kji                      # Σ ← λ Σ + (1 − λ) K_D  (2.19)
                    if write:
                        S[j, i] = v
                    h[i] += qj * v                              # h = Σ q
                    kq[i] += qj * kji                           # K_D q
            else:
                for i in range(hw):
                    v = S[j, i] - cs * (gj * g[i])              # Σ ← [[Σ,h],[hᵀ,σ_f²]] − g gᵀ/σ_y²  (2.14)
                    v = lam * v + c1 * K[j, i]                  # Σ ← λ Σ + (1 − λ) K_D  (2.19)
                    if write:
                        S[j, i] = v
                    h[i] += qj * v                              # h = Σ q
    if write:
        ist[I_SPEND] = 0


@njit(cache=True, nogil=True)
def arm(kinds, params, cols, X, Q, S, K, mu, order, ist, fst, P, W, tab, x, out):
    """Steps 1–2 at ``x``, in place ("predict_next"): forget, predict, keep what the update needs.

    ``out[:4] = ŷ, σ_f², σ_y², γ²`` (normalised). On an empty dictionary only ``x`` and
    ``k_tt`` are kept and the prior predictive ``0, k_tt, sn2 + k_tt, k_tt`` is reported.
    Arming again before :func:`update` forgets once more and predicts at the new ``x``.
    """
    n = ist[I_N]
    hw = ist[I_HW]
    lam = fst[F_LAM]
    sn2 = fst[F_SN2]
    s = order[n]                                  # free slot: where step 3 puts x
    for c in range(x.shape[0]):
        X[s, c] = x[c]
    ist[I_ARMED] = 1
    if n == 0:
        ktt = kernel_value(kinds, params, cols, x, x) + fst[F_JIT]   # k = k(x, x) + ε_j
        fst[F_KTT] = ktt
        fst[F_YM] = 0.0
        fst[F_G2] = ktt
        fst[F_SF2] = ktt
        fst[F_SY2] = sn2 + ktt
        out[0] = 0.0
        out[1] = ktt
        out[2] = sn2 + ktt
        out[3] = ktt
        return
    kt = P[3]
    q = P[4]
    h = P[5]

    # ---- 1. forget, μ part (2.19); the Σ part is fused into the h pass ---------------
    sl = math.sqrt(lam)
    for i in range(hw):
        mu[i] = sl * mu[i]                        # μ ← √λ μ

    # ---- 2. predict (2.17) ---------------------------------------------------------
    ktt = _kernel_row(kinds, params, cols, X, order, n, hw, ist, fst, tab, x, kt)
    _q_pass(Q, P, ist, fst, hw, kt, q, True)      # q = Q k_t
    y_mean = 0.0
    ktq = 0.0
    for i in range(hw):
        y_mean += q[i] * mu[i]                    # ŷ = qᵀ μ
        ktq += kt[i] * q[i]
    gamma2 = ktt - ktq                            # γ² = k_tt − k_tᵀ q
    if gamma2 < 0.0:
        gamma2 = 0.0
    res = P[6]
    refine = ist[I_REFINE] != 0
    _h_pass(S, K, P, ist, fst, hw, lam, q, h, res, refine, True)  # Σ ← λΣ + (1−λ)K_D;  h = Σ q
    qh = 0.0
    for i in range(hw):
        qh += q[i] * h[i]
    if refine:
        for i in range(hw):
            res[i] = kt[i] - res[i]               # k_t − K_D q, for the refinement of q
    sf2 = gamma2 + qh                             # σ_f² = γ² + qᵀ h
    if sf2 < 0.0:
        sf2 = 0.0
    sy2 = sn2 + sf2                               # σ_y² = sn2 + σ_f²
    fst[F_KTT] = ktt
    fst[F_YM] = y_mean
    fst[F_G2] = gamma2
    fst[F_SF2] = sf2
    fst[F_SY2] = sy2
    out[0] = y_mean
    out[1] = sf2
    out[2] = sy2
    out[3] = gamma2


@njit(cache=True, nogil=True)
def _init(X, Q, S, K, mu, order, ist, fst, y, out):
    """Step 6, eq. 2.16 (first sample, armed): ``Q = 1/k``, ``μ = y k/(k+sn2)``, ``Σ = k − k²/(k+sn2)``."""
    sn2 = fst[F_SN2]
    k = fst[F_KTT]                                # k = k(x, x) + ε_j  (x is in X[order[0]])
    s = order[0]
    K[s, s] = k                                   # K_D = k
    Q[s, s] = 1.0 / k                             # Q = 1 / k
    mu[s] = y * k / (k + sn2)                     # μ = y k / (k + sn2)
    S[s, s] = k - k * k / (k + sn2)               # Σ = k − k² / (k + sn2)
    fst[F_NUM] = y * y / (k + sn2)                # num = y² / (k + sn2)
    fst[F_DEN] = 1.0                              # den = 1
    fst[F_S02] = fst[F_NUM] / fst[F_DEN]          # s0² = num / den
    ist[I_N] = 1
    ist[I_HW] = s + 1
    ist[I_STEPS] += 1
    # report the prior predictive of this first sample (kafbox writes zeros on this row)
    _write_out(out, y, 0.0, sn2 + k, k, k, -1.0, 0.0, fst[F_S02], 1)


@njit(cache=True, nogil=True)
def _update(X, Q, S, K, mu, order, ist, fst, P, W, y, out):
    """Steps 3–5 for ``n ≥ 1`` from the armed prediction (eq. 2.14, 2.15, 2.20–2.22)."""
    n = ist[I_N]
    hw = ist[I_HW]
    M = ist[I_M]
    lam = fst[F_LAM]
    jit = fst[F_JIT]
    kt = P[3]
    q = P[4]
    h = P[5]
    u = W[3]
    m = W[4]
    p = P[0]
    a = P[1]
    g = P[2]
    ktt = fst[F_KTT]
    y_mean = fst[F_YM]
    gamma2 = fst[F_G2]
    sf2 = fst[F_SF2]
    sy2 = fst[F_SY2]
    dim = X.shape[1]
    err = y - y_mean
    e = err / sy2                                 # (y − ŷ) / σ_y²
    cs = 1.0 / sy2

    # ---- 4. signal power (2.20, with the square) ---------------------------------------
    fst[F_NUM] += lam * err * err / sy2           # num ← num + λ (y − ŷ)² / σ_y²
    fst[F_DEN] += lam                             # den ← den + λ
    fst[F_S02] = fst[F_NUM] / fst[F_DEN]          # s0² = num / den

    # ---- 3. posterior of f at [D; x] (2.14), μ part -------------------------------------
    s = order[n]                                  # free slot for the new basis (x is there)
    hwn = hw if s < hw else s + 1
    for i in range(hw):
        m[i] = mu[i] + e * h[i]                   # μ_new = [μ; ŷ] + (y − ŷ)/σ_y² [h; σ_f²]
    m[s] = y_mean + e * sf2

    # ---- 5. which basis to prune (2.21–2.22) ---------------------------------------------
    r = -1                                        # logical index to remove, -1: none
    g2q = gamma2                                  # γ² of the Q update (refined below)
    prune = n + 1 > M
    if gamma2 < jit:
        r = n                                     # roundoff guard: drop the new sample
    elif ist[I_REFINE] != 0:
        # One step of iterative refinement for the Q update: q ← q + Q (k_t − K_D q),
        # γ² ← k_tt − k_tᵀ q. Without it the update multiplies the error of Q by up to
        # ~|q|²/γ² ≲ 1/ε_j (kafbox's recursion); with it the error is not amplified.
        # (ŷ, γ², σ² reported and the μ, Σ updates keep the unrefined q, as kafbox.)
        res = P[6]                                # k_t − K_D q (from the h pass)
        w = W[5]
        for i in range(hwn):
            w[i] = 0.0
        if prune:
            for i in range(hwn):
                u[i] = 0.0
            for j in range(hwn):                  # u = Q μ_new, w = Q res (row/column s of Q is zero)
                mj = m[j]
                rj = res[j]
                for i in range(hwn):
                    v = Q[j, i]
                    u[i] += mj * v
                    w[i] += rj * v
        else:
            for j in range(hw):                   # w = Q res
                rj = res[j]
                for i in range(hw):
                    w[i] += rj * Q[j, i]
        g2r = ktt
        for i in range(hw):
            w[i] = q[i] + w[i]                    # refined q
            g2r -= kt[i] * w[i]
        if g2r > 0.0:
            g2q = g2r
            for i in range(hw):
                q[i] = w[i]
    elif prune:
        for i in range(hwn):
            u[i] = 0.0
        for j in range(hwn):                      # u = Q μ_new   (row/column s of Q is zero)
            mj = m[j]
            for i in range(hwn):
                u[i] += mj * Q[j, i]
    if r < 0 and prune:
        # criterion on Q_new = [[Q,0],[0,0]] + p pᵀ/γ², p = [q; −1], without forming Q_new:
        #   [Q_new μ_new]_i = [Q μ_new]_i + p_i (pᵀ μ_new)/γ²,  [Q_new]_ii = Q_ii + p_i²/γ²
        sc = 1.0 / g2q
        q[s] = -1.0
        pm = 0.0
        for i in range(hwn):
            pm += q[i] * m[i]                     # pᵀ μ_new
        best = np.inf
        for l in range(n + 1):
            i = order[l]                          # order[n] == s: the new sample is last
            qii = Q[i, i] + sc * (q[i] * q[i])    # [Q_new]_ii
            qmu = u[i] + sc * (q[i] * pm)         # [Q_new μ_new]_i
            crit = abs(qmu / qii)                 # |[Q μ]_i / Q_ii|, MSE pruning criterion
            if crit < best:                       # first minimum, as Matlab's min
                best = crit
                r = l
        q[s] = 0.0

    if r == n:
        # ---- reduced update: Q stays as before step 3, x is not added --------------------
        for i in range(hw):
            mu[i] = m[i]                          # μ ← μ + (y − ŷ)/σ_y² h
            g[i] = h[i]                           # Σ ← Σ − h hᵀ/σ_y²   (pending)
        m[s] = 0.0
        for c in range(dim):
            X[s, c] = 0.0                         # the slot stays free
        fst[F_SC] = cs
        ist[I_SPEND] = 1
        ist[I_STEPS] += 1
        _write_out(out, y, y_mean, sy2, sf2, gamma2, float(n), 1.0, fst[F_S02], n)
        return

    # ---- 3. update (2.14, 2.15): append x (already in slot s) to D ---------------------------
    for i in range(hw):
        K[s, i] = kt[i]
        K[i, s] = kt[i]
    K[s, s] = ktt                                 # K_D ← [[K_D, k_t], [k_tᵀ, k_tt]]
    for i in range(hw):
        S[s, i] = h[i]
        S[i, s] = h[i]
    S[s, s] = sf2                                 # Σ ← [[Σ, h], [hᵀ, σ_f²]] ...
    for i in range(hwn):
        mu[i] = m[i]                              # μ ← μ_new
        g[i] = h[i]
        p[i] = q[i]
    m[s] = 0.0
    g[s] = sf2                                    # ... − g gᵀ/σ_y²,  g = [h; σ_f²]  (pending)
    p[s] = -1.0                                   # Q ← [[Q,0],[0,0]] + p pᵀ/γ²,  p = [q; −1]  (pending)
    fst[F_SC] = cs
    ist[I_SPEND] = 1
    sc = 1.0 / g2q
    fst[F_QSC] = sc
    if r < 0:
        ist[I_QPEND] = 1
        n_new = n + 1
        removed = -1.0
    else:
        sr = order[r]
        for i in range(hwn):
            a[i] = Q[i, sr] + sc * (p[i] * p[sr])  # a = [Q_new]_{:, r}
        fst[F_QBINV] = 1.0 / a[sr]                # 1 / [Q_new]_rr
        ist[I_QPEND] = 2
        for i in range(hwn):                       # drop r: zero its row/column (2.21)
            Q[sr, i] = 0.0
            Q[i, sr] = 0.0
            S[sr, i] = 0.0
            S[i, sr] = 0.0
            K[sr, i] = 0.0
            K[i, sr] = 0.0
        mu[sr] = 0.0
        p[sr] = 0.0
        a[sr] = 0.0
        g[sr] = 0.0
        for c in range(dim):
            X[sr, c] = 0.0
        for l in range(r, n):                      # and from the logical order
            order[l] = order[l + 1]
        order[n] = sr
        n_new = n
        removed = float(r)
    ist[I_N] = n_new
    ist[I_HW] = hwn
    ist[I_STEPS] += 1
    _write_out(out, y, y_mean, sy2, sf2, gamma2, removed, 0.0, fst[F_S02], n_new)


@njit(cache=True, nogil=True)
def _write_out(out, y, y_mean, sy2, sf2, gamma2, removed, reduced, s02, n):
    out[0] = y_mean
    out[1] = sy2
    out[2] = sf2
    out[3] = gamma2
    out[4] = removed
    out[5] = reduced
    out[6] = y_mean + sf2 * (y - y_mean) / sy2    # E[f(x) | y] = ŷ + σ_f² (y − ŷ)/σ_y²
    out[7] = sf2 - sf2 * sf2 / sy2                # Var[f(x) | y] = σ_f² − σ_f⁴/σ_y²
    out[8] = s02
    out[9] = n


@njit(cache=True, nogil=True)
def refresh_inverse(Q, K, order, ist, W):
    """``Q ← K_D⁻¹`` from the cached ``K_D`` by Cholesky; False (``Q`` untouched) if not PD.

    Works in the dense scratch ``A = W[N_W:]`` (``(M+1)×(M+1)``, allocated with ``W``),
    in the dictionary's logical order, with row-wise axpys only (contiguous, so LLVM
    vectorises them without reassociation; about ``n³/2`` multiply-adds):

    1. ``K_D = Uᵀ U`` (upper ``U`` in ``A``'s upper triangle), diagonal copied to ``W[4]``;
    2. ``Z = U⁻ᵀ = L⁻¹`` row by row into ``A``'s strict lower triangle, diagonal in ``W[3]``;
    3. ``K_D⁻¹ = Zᵀ Z`` accumulated into ``A``'s upper triangle (``U`` is no longer needed);
    4. scattered into both halves of ``Q``'s slots (bitwise symmetric). The pending
       update of ``Q`` is dropped. A pivot ``≤ 0`` (``K_D`` numerically singular, e.g.
       ``ε_j = 0`` and a repeated input) leaves ``Q`` and its pending update as they were.
    """
    n = ist[I_N]
    A = W[N_W:]
    ud = W[4]
    zd = W[3]
    # ---- 1. Cholesky K_D = Uᵀ U (right-looking, row axpys) ------------------------------
    for i in range(n):
        si = order[i]
        for j in range(i, n):
            A[i, j] = K[si, order[j]]
    for k in range(n):
        d = A[k, k]
        if not d > 0.0:
            return False
        ukk = math.sqrt(d)
        A[k, k] = ukk
        ud[k] = ukk
        for j in range(k + 1, n):
            A[k, j] = A[k, j] / ukk
        for i in range(k + 1, n):
            c = A[k, i]
            for j in range(i, n):
                A[i, j] -= c * A[k, j]
    # ---- 2. Z = L⁻¹ (L = Uᵀ): row i solves Σ_k L[i,k] Z[k,:] = e_i -------------------------
    for i in range(n):
        for j in range(i):
            A[i, j] = 0.0                         # row i of Z accumulates here (strict lower)
        zi = 1.0
        for k in range(i):
            c = A[k, i]                           # L[i, k]
            for j in range(k):
                A[i, j] -= c * A[k, j]            # − L[i, k] Z[k, j]
            A[i, k] -= c * zd[k]
        uii = ud[i]
        for j in range(i):
            A[i, j] = A[i, j] / uii
        zd[i] = zi / uii
    # ---- 3. K_D⁻¹ = Zᵀ Z = Σ_k Z[k,:]ᵀ Z[k,:] into the upper triangle ----------------------------
    for a in range(n):
        for b in range(a, n):
            A[a, b] = 0.0
    for k in range(n):
        for a in range(k):
            c = A[k, a]                           # Z[k, a]
            for b in range(a, k):
                A[a, b] += c * A[k, b]            # row a of K_D⁻¹, columns a..k−1
            A[a, k] += c * zd[k]
        A[k, k] += zd[k] * zd[k]
    # ---- 4. scatter -------------------------------------------------------------------------
    for a in range(n):
        sa = order[a]
        for b in range(a, n):
            v = A[a, b]
            sb = order[b]
            Q[sa, sb] = v
            Q[sb, sa] = v
    ist[I_QPEND] = 0
    return True


@njit(cache=True, nogil=True)
def update(X, Q, S, K, mu, order, ist, fst, P, W, y, out):
    """Steps 3–5 (or 6 on the first sample) with the armed prediction; False if nothing is armed.

    After the step, every ``refresh_every`` steps, ``Q`` is recomputed from ``K_D``.
    """
    if ist[I_ARMED] == 0:
        return False
    ist[I_ARMED] = 0
    if ist[I_N] == 0:
        _init(X, Q, S, K, mu, order, ist, fst, y, out)
    else:
        _update(X, Q, S, K, mu, order, ist, fst, P, W, y, out)
    every = ist[I_REFRESH]
    if every > 0 and ist[I_STEPS] % every == 0:
        refresh_inverse(Q, K, order, ist, W)
    return True


@njit(cache=True, nogil=True)
def learn(kinds, params, cols, X, Q, S, K, mu, order, ist, fst, P, W, tab, x, y, out):
    """One sample: :func:`arm` at ``x`` then :func:`update` with ``y`` (steps 1–5, or 6 first)."""
    arm(kinds, params, cols, X, Q, S, K, mu, order, ist, fst, P, W, tab, x, out)
    update(X, Q, S, K, mu, order, ist, fst, P, W, y, out)


@njit(cache=True, nogil=True)
def learn_many(kinds, params, cols, X, Q, S, K, mu, order, ist, fst, P, W, tab, xs, ys, outs):
    """:func:`learn` over a stream; ``outs[t]`` receives the ``out`` row of sample ``t``."""
    for t in range(ys.shape[0]):
        learn(kinds, params, cols, X, Q, S, K, mu, order, ist, fst, P, W, tab, xs[t], ys[t], outs[t])


@njit(cache=True, nogil=True)
def track(kinds, params, cols, X, Q, S, K, mu, order, ist, fst, P, W, tab, xs, ys, learn_mask, outs):
    """Monitor block: for each arriving sample ``j`` in order, ``update(ys[j])`` if
    ``learn_mask[j]`` (``ys[j]``: the residual of the previously armed ``x``), then
    ``arm(xs[j])``.

    ``outs[j]`` (width :data:`N_TRACK`): ``[0:10]`` the ``out`` of the update (NaN when
    not learned), ``[10:14]`` the new prediction ``ŷ, σ_f², σ_y², γ²``, ``[14]`` s0²,
    ``[15]`` n after sample ``j``, ``[16]`` 1.0 if an update ran (mask set and armed).
    """
    for j in range(xs.shape[0]):
        o = outs[j]
        learned = False
        if learn_mask[j]:
            learned = update(X, Q, S, K, mu, order, ist, fst, P, W, ys[j], o)
        if not learned:
            for c in range(N_OUT):
                o[c] = np.nan
        arm(kinds, params, cols, X, Q, S, K, mu, order, ist, fst, P, W, tab, xs[j], o[N_OUT:])
        o[14] = fst[F_S02]
        o[15] = ist[I_N]
        o[16] = 1.0 if learned else 0.0


@njit(cache=True, nogil=True)
def predict(kinds, params, cols, X, Q, S, K, mu, order, ist, fst, P, W, tab, x, forget, out):
    """``ŷ, σ_f², σ_y², γ²`` at ``x`` from the current state (2.17) into ``out[:4]``; state untouched.

    With ``forget`` the forgetting (2.19) of the next step is applied virtually, so
    the numbers are bit-identical to what the next :func:`learn` reports for ``x``.
    """
    n = ist[I_N]
    hw = ist[I_HW]
    lam = fst[F_LAM] if forget else 1.0
    kt = W[0]
    q = W[1]
    h = W[2]
    ktt = _kernel_row(kinds, params, cols, X, order, n, hw, ist, fst, tab, x, kt)
    _q_pass(Q, P, ist, fst, hw, kt, q, False)
    sl = math.sqrt(lam)
    y_mean = 0.0
    ktq = 0.0
    for i in range(hw):
        y_mean += q[i] * (sl * mu[i])
        ktq += kt[i] * q[i]
    gamma2 = ktt - ktq
    if gamma2 < 0.0:
        gamma2 = 0.0
    _h_pass(S, K, P, ist, fst, hw, lam, q, h, W[3], False, False)
    qh = 0.0
    for i in range(hw):
        qh += q[i] * h[i]
    sf2 = gamma2 + qh
    if sf2 < 0.0:
        sf2 = 0.0
    out[0] = y_mean
    out[1] = sf2
    out[2] = fst[F_SN2] + sf2
    out[3] = gamma2


@njit(cache=True, nogil=True)
def materialize(Q, S, P, ist, fst, hw, Qout, Sout):
    """``Q`` and ``Σ`` with the pending updates applied (no forgetting), into ``Qout``, ``Sout``."""
    p = P[0]
    a = P[1]
    g = P[2]
    sc = fst[F_QSC]
    binv = fst[F_QBINV]
    cs = fst[F_SC]
    mode = ist[I_QPEND]
    for j in range(hw):
        for i in range(hw):
            v = Q[j, i]
            if mode == 1:
                v = v + sc * (p[j] * p[i])
            elif mode == 2:
                v = (v + sc * (p[j] * p[i])) - (a[j] * a[i]) * binv
            Qout[j, i] = v
            w = S[j, i]
            if ist[I_SPEND] != 0:
                w = w - cs * (g[j] * g[i])
            Sout[j, i] = w
