"""Dense operations on the KRLS-T core's state, off the per-sample sweeps: the periodic re-inversion
of ``Q`` from ``K_D`` by Cholesky (:func:`refresh_inverse`, the core's ``refresh_every``) and the full
``Q``, ``Σ`` with the pending updates applied (:func:`materialize`, for ``KRLST``'s properties).
"""

from __future__ import annotations

import math

from numba import njit

from ._krlst_simd import fmuladd
from ._krlst_state import F_DSC, F_QBINV, F_QSC, F_SC, I_HW, I_N, I_QPEND, I_SPEND, P_A, P_G, P_P, W_U, W_W, unowned


@njit(cache=True, nogil=True, inline="always")
def _k_at(st, i, j):
    """``K_D`` entry of slots ``i, j`` from the (strict upper, diagonal) storage."""
    if i == j:
        return st.Kd[i]
    return st.K[i, j] if i < j else st.K[j, i]


@njit(cache=True, nogil=True)
def refresh_inverse(st):
    """:func:`_refresh_inverse` (see there) on ``st``."""
    return _refresh_inverse(unowned(st))


@njit(cache=True, nogil=True)
def _refresh_inverse(st):
    """``Q ← K_D⁻¹`` from the cached ``K_D`` by Cholesky; False (``Q`` untouched) if not PD.

    Works in the dense scratch ``A`` in the dictionary's logical order, with row-wise axpys
    only (contiguous, so LLVM vectorises them without reassociation; ~``n³/2`` multiply-adds):

    1. ``K_D = Uᵀ U`` (upper ``U`` in ``A``'s upper triangle), diagonal copied to ``W[W_U]``;
    2. ``Z = U⁻ᵀ = L⁻¹`` row by row into ``A``'s strict lower triangle, diagonal in ``W[W_W]``;
    3. ``K_D⁻¹ = Zᵀ Z`` accumulated into ``A``'s upper triangle (``U`` is no longer needed);
    4. scattered into ``Q``'s (strict upper, diagonal) storage. The pending update of ``Q``
       is dropped. A pivot ``≤ 0`` (``K_D`` numerically singular, e.g. ``ε_j = 0`` and a
       repeated input) leaves ``Q`` and its pending update as they were.
    """
    n = st.ist[I_N]
    order = st.order
    A = st.A
    ud = st.W[W_U]
    zd = st.W[W_W]
    # ---- 1. Cholesky K_D = Uᵀ U (right-looking, row axpys) ----------------------------------------
    for i in range(n):
        si = order[i]
        for j in range(i, n):
            A[i, j] = _k_at(st, si, order[j])
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
    # ---- 2. Z = L⁻¹ (L = Uᵀ): row i solves Σ_k L[i,k] Z[k,:] = e_i -----------------------------------
    for i in range(n):
        for j in range(i):
            A[i, j] = 0.0                         # row i of Z accumulates here (strict lower)
        for k in range(i):
            c = A[k, i]                           # L[i, k]
            for j in range(k):
                A[i, j] -= c * A[k, j]            # − L[i, k] Z[k, j]
            A[i, k] -= c * zd[k]
        uii = ud[i]
        for j in range(i):
            A[i, j] = A[i, j] / uii
        zd[i] = 1.0 / uii
    # ---- 3. K_D⁻¹ = Zᵀ Z = Σ_k Z[k,:]ᵀ Z[k,:] into the upper triangle --------------------------------
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
    # ---- 4. scatter --------------------------------------------------------------------------------
    Q = st.Q
    for a in range(n):
        sa = order[a]
        st.Qd[sa] = A[a, a]
        for b in range(a + 1, n):
            sb = order[b]
            if sa < sb:
                Q[sa, sb] = A[a, b]
            else:
                Q[sb, sa] = A[a, b]
    st.ist[I_QPEND] = 0
    return True


@njit(cache=True, nogil=True)
def materialize(st, Qout, Sout):
    """Full ``Q`` and ``Σ = K_D + c D`` over the slots ``[0, hw)`` with the pending updates applied (no forgetting)."""
    st = unowned(st)
    ist = st.ist
    fst = st.fst
    hw = ist[I_HW]
    p = st.P[P_P]
    a = st.P[P_A]
    g = st.P[P_G]
    sc = fst[F_QSC]
    nb = -fst[F_QBINV]
    ncs = -fst[F_SC]
    mode = ist[I_QPEND]
    spend = ist[I_SPEND]
    for j in range(hw):
        for i in range(j, hw):
            if i == j:
                v = st.Qd[j]
                w = st.Dd[j]
                k = st.Kd[j]
            else:
                v = st.Q[j, i]
                w = st.D[j, i]
                k = st.K[j, i]
            if mode >= 1:
                v = fmuladd(sc * p[j], p[i], v)
            if mode == 2:
                v = fmuladd(nb * a[j], a[i], v)
            if spend:
                w = fmuladd(ncs * g[j], g[i], w)
            w = k + fst[F_DSC] * w
            Qout[j, i] = v
            Qout[i, j] = v
            Sout[j, i] = w
            Sout[i, j] = w
