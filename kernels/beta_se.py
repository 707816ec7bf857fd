"""Physical parameters of the online β and their standard errors (delta method, method §2).

With ``b`` the force gain (``β1`` in force-input form, ``β1/K`` in velocity-loop form) and ``p`` the
pole: ``B = (1 − p)/b``, ``J = B Ts/(−ln p)``, ``d_p = β_sp/b``, ``c_n = −β_sn/b``, ``offset = −β_one/b``
and ``Var θ_k = g_kᵀ P g_k`` with the analytic gradient ``g_k = ∂θ_k/∂β`` and ``P = Λ⁻¹ΨΛ⁻ᵀ``. Without
the loop gain ``K`` (velocity-loop) ``K = 1`` is used: the values are then ``J/K, B/K, d/K``.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from .beta_layout import (
    FAST_FILL,
    L_FORM,
    L_IONE,
    L_ISN,
    L_ISP,
    N_PHYS,
    P_FASTLAM,
    P_GAIN,
    P_TS,
    S_FJD,
    S_FJN,
    S_FJV,
    S_FJW,
    V_TMP,
    V_X,
    beta_state_of,
    beta_state_views,
)
from .beta_prior import _check_physical, _layout, new_beta_buffers


@njit(cache=True, nogil=True)
def _cov_apply(bs, a, out, t1, t2):
    """``out = P a`` with ``P = Λ⁻¹ Ψ Λ⁻ᵀ`` (``bs.cov`` = Λ⁻¹)."""
    p = a.shape[0]
    C = bs.cov
    psi = bs.psi
    for i in range(p):
        acc = 0.0
        for j in range(p):
            acc += C[j, i] * a[j]
        t1[i] = acc                               # t1 = Λ⁻ᵀ a
    for i in range(p):
        acc = 0.0
        for j in range(p):
            acc += psi[i, j] * t1[j]
        t2[i] = acc                               # t2 = Ψ Λ⁻ᵀ a
    for i in range(p):
        acc = 0.0
        for j in range(p):
            acc += C[i, j] * t2[j]
        out[i] = acc                              # out = Λ⁻¹ Ψ Λ⁻ᵀ a


@njit(cache=True, nogil=True)
def physical_se_buffers(bfbuf, bibuf, theta, se, cov_work):
    """:func:`physical_se` on the base buffers of the β state."""
    return physical_se(beta_state_of(bfbuf, bibuf), theta, se, cov_work)


@njit(cache=True, nogil=True)
def fast_inertia(bs, J):
    """The fast inertia estimate (eq. 9) ``J + δ`` and its standard error, ``J`` the slow estimate
    (kg, or kg over K); NaN when the last ``FAST_MEMORY`` seconds of motion held no acceleration, and in
    the force-input form: there the command is the loop's reaction to the disturbance too, so no
    instrument free of it exists, and a disturbance step reads as an inertia step over a few samples."""
    sst = bs.sst
    d = sst[S_FJD]
    if bs.lay[L_FORM] == 1 or not (d != 0.0 and math.isfinite(J)):
        return np.nan, np.nan
    if sst[S_FJW] * (1.0 - bs.par[P_FASTLAM]) < FAST_FILL:   # not yet FAST_FILL of a full memory
        return np.nan, np.nan
    return J + sst[S_FJN] / d, math.sqrt(max(sst[S_FJV], 0.0)) / abs(d)


@njit(cache=True, nogil=True)
def physical_se(bs, theta, se, cov_work):
    """θ = (J, B, d_p, c_n, (d_p + c_n)/2, offset) of β̂ and their standard errors (delta method).

    ``cov_work`` (:data:`N_PHYS` + 2, p) scratch. Absent columns give NaN. Returns False when β̂ is not a
    physical drive (cannot happen after the projection; guards restored states).
    """
    beta = bs.beta
    p = beta.shape[0]
    form_force = bs.lay[L_FORM] == 1
    i_sp, i_sn, i_one = bs.lay[L_ISP], bs.lay[L_ISN], bs.lay[L_IONE]
    K = bs.par[P_GAIN]
    Ts = bs.par[P_TS]
    for k in range(N_PHYS):
        theta[k] = np.nan
        se[k] = np.nan
    if form_force:
        b = beta[0]
        pd = beta[1]
        db0 = 1.0
    else:
        b = beta[0] / K
        pd = beta[0] + beta[1]
        db0 = 1.0 / K
    if not (b > 0.0 and 0.0 < pd < 1.0):
        return False
    Lg = -math.log(pd)
    B = (1.0 - pd) / b
    J = B * Ts / Lg
    # gradients w.r.t. β (rows of G): ∂θ/∂β = ∂θ/∂b ∂b/∂β + ∂θ/∂p ∂p/∂β + direct terms
    G = cov_work[:N_PHYS]
    for k in range(N_PHYS):
        for j in range(p):
            G[k, j] = 0.0
    dp_d0 = 1.0 if not form_force else 0.0       # ∂p/∂β1 (velocity-loop p = β1 + β2)
    dp_d1 = 1.0                                   # ∂p/∂β2
    # rows: value, ∂/∂b, ∂/∂p
    theta[0] = J                                  # J = B Ts / (−ln p)
    G[0, 0] = (-J / b) * db0 + Ts * (-Lg / b + B / pd) / (Lg * Lg) * dp_d0
    G[0, 1] = Ts * (-Lg / b + B / pd) / (Lg * Lg) * dp_d1
    theta[1] = B                                  # B = (1 − p) / b
    G[1, 0] = (-B / b) * db0 + (-1.0 / b) * dp_d0
    G[1, 1] = (-1.0 / b) * dp_d1
    if i_sp >= 0:
        dpos = beta[i_sp] / b                     # d_p = β_sp / b
        cneg = -beta[i_sn] / b                    # c_n = −β_sn / b
        theta[2] = dpos
        G[2, 0] = (-dpos / b) * db0
        G[2, i_sp] = 1.0 / b
        theta[3] = cneg
        G[3, 0] = (-cneg / b) * db0
        G[3, i_sn] = -1.0 / b
        theta[4] = 0.5 * (dpos + cneg)
        for j in range(p):
            G[4, j] = 0.5 * (G[2, j] + G[3, j])
    if i_one >= 0:
        off = -beta[i_one] / b                    # offset = −β_one / b
        theta[5] = off
        G[5, 0] = (-off / b) * db0
        G[5, i_one] = -1.0 / b
    # Var θ_k = g_kᵀ P g_k,  P = Λ⁻¹ Ψ Λ⁻ᵀ
    x = cov_work[N_PHYS]
    gk = cov_work[N_PHYS + 1]                     # cov_work: (N_PHYS + 2, p)
    t1 = bs.vec[V_TMP]
    t2 = bs.vec[V_X]
    for k in range(N_PHYS):
        if not math.isfinite(theta[k]):
            continue
        for j in range(p):
            gk[j] = G[k, j]
        _cov_apply(bs, gk, x, t1, t2)
        v = 0.0
        vm = 0.0
        for j in range(p):
            v += gk[j] * x[j]                     # the sandwich gᵀΛ⁻¹ΨΛ⁻ᵀg
            vm += gk[j] * t1[j]                   # the model-based gᵀΛ⁻¹g (t1 = Λ⁻ᵀg)
        # the larger of the two: the sandwich of a few effective samples is too small
        v = max(v, vm)
        se[k] = math.sqrt(v) if v > 0.0 else 0.0
    return True


def physical_of(beta, names, Ts: float, P, *, gain: float | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Physical parameters (:data:`PHYSICAL`) of ``beta`` and their standard errors for the β
    covariance ``P`` (delta method, :func:`physical_se`), e.g. the model file's values and
    standard errors for the health reference. NaN for columns the model does not have."""
    form = _layout(names)[0]
    beta = np.asarray(beta, dtype=np.float64)
    _check_physical(form, beta)
    P = np.asarray(P, dtype=np.float64)
    p = beta.size
    if P.shape != (p, p) or not np.all(np.isfinite(P)):
        raise ValueError(f"P must be a finite ({p}, {p}) covariance")
    fbuf, ibuf = new_beta_buffers(beta, names, Ts, 1, gain=gain, P0=np.eye(p))
    probe = beta_state_views(fbuf, ibuf)
    Ps = 0.5 * (P + P.T)
    probe.cov[:] = Ps                             # P = Λ⁻¹ Ψ Λ⁻ᵀ with Λ⁻¹ = P, Ψ = P⁺
    probe.psi[:] = np.linalg.pinv(Ps, hermitian=True)
    theta, se = np.zeros(N_PHYS), np.zeros(N_PHYS)
    physical_se_buffers(fbuf, ibuf, theta, se, np.zeros((N_PHYS + 2, p)))
    return theta, se

