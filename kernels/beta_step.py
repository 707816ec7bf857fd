"""The compiled step of the online β: :func:`joint_arm` and :func:`joint_update` beside the KRLS-T core.

Equation numbers (1)–(9) refer to :mod:`kernels.beta_tracker`; the tracker-side contract is
listed in :func:`joint_arm`.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from . import _krlst_core as core
from .beta_layout import (
    B_FILTERED,
    B_INNOV,
    B_LEARNED,
    B_NU,
    B_RESID,
    B_VAR,
    B_WEIGHT,
    B_ZTN,
    C_ARMS,
    C_DIR,
    C_DOWNWEIGHTED,
    C_GATED,
    C_PROJECTED,
    C_QUIET,
    C_REJECTED,
    C_SEEN,
    C_SINCE_FORGET,
    C_SINCE_REBASE,
    C_UPDATES,
    C_VHAT_ARM,
    C_VSIM_ARM,
    FORGET_EVERY,
    J_FILTERED,
    J_FNEXT,
    J_FNEXTVAR,
    J_LEARNED,
    J_NU,
    J_RESID,
    J_WEIGHT,
    L_FORM,
    L_IONE,
    L_ISN,
    L_ISP,
    L_REBASE,
    P_ENABLED,
    P_FASTLAM,
    P_HOLD,
    P_HUBER,
    P_IV,
    P_MINSPEED,
    P_OMEGA,
    P_REJECT,
    P_WARMUP,
    S_FJD,
    S_FJN,
    S_FJV,
    S_FJW,
    S_SCALE,
    S_VHAT,
    S_VSIM,
    SCALE_FLOOR,
    V_BEFORE,
    V_G,
    V_SIM,
    V_TMP,
    V_X,
    V_ZETA,
    V_ZETAR,
    V_ZT,
    V_ZTR,
    beta_state_of,
)
from .beta_se import _cov_apply
from .linalg_small import congruence, invert


@njit(cache=True, nogil=True)
def _forget(bs):
    """(2) for the last :data:`FORGET_EVERY` learning samples, per physical parameter, with the
    operators ``T``, ``S`` of :func:`forgetting_operators` (:attr:`BetaState.forget`):

        Λ ← TᵀΛT + SᵀΛ₀S,   Ψ ← TᵀΨT + SᵀΛ₀S,   β̂ ← β̂ + Λ_new⁻¹ SᵀΛ₀S (β₀ − β̂),

    i.e. in the coordinates of the physical parameters θ each one is flattened towards the prior
    N(β₀, P₀) at its own rate (``Λ_θ ← DΛ_θD + EΛ₀θE``, ``D = diag(√λ_i^m)``, ``E = √(I − D²)``);
    with λ_J = λ_β it is ``Λ ← λ_β^m Λ + (1 − λ_β^m) Λ₀``."""
    beta = bs.beta
    p = beta.shape[0]
    vec = bs.vec
    info = bs.info
    if not invert(bs.cov, info, bs.lu, bs.piv, vec[V_TMP], vec[V_X]):   # Λ = (Λ⁻¹)⁻¹
        return
    T = bs.forget[0]
    prior = bs.work
    congruence(info, T, info, bs.lu)             # Λ ← TᵀΛT
    congruence(bs.psi, T, bs.psi, bs.lu)         # Ψ ← TᵀΨT
    congruence(bs.info0, bs.forget[1], prior, bs.lu)   # SᵀΛ₀S
    beta0 = bs.beta0
    d = vec[V_BEFORE]
    for i in range(p):
        acc = 0.0
        for j in range(p):
            acc += prior[i, j] * (beta0[j] - beta[j])
            info[i, j] += prior[i, j]
            bs.psi[i, j] += prior[i, j]
        d[i] = acc                                # SᵀΛ₀S (β₀ − β̂)
    if not invert(info, bs.cov, bs.lu, bs.piv, vec[V_TMP], vec[V_X]):
        return
    C = bs.cov
    for i in range(p):
        acc = 0.0
        for j in range(p):
            acc += C[i, j] * d[j]
        beta[i] += acc


@njit(cache=True, nogil=True)
def _project(bs, a, pa, t1, t2):
    """Estimate projection (7) onto ``aᵀβ ≤ b`` in the metric of ``P``; returns the number of projections."""
    beta = bs.beta
    cons = bs.cons
    p = beta.shape[0]
    count = 0
    for _sweep in range(3):
        moved = False
        for c in range(cons.shape[0]):
            viol = -cons[c, p]
            for j in range(p):
                viol += cons[c, j] * beta[j]      # aᵀβ − b
            if viol <= 0.0:
                continue
            for j in range(p):
                a[j] = cons[c, j]
            _cov_apply(bs, a, pa, t1, t2)         # P a
            den = 0.0
            for j in range(p):
                den += a[j] * pa[j]               # aᵀ P a
            if not den > 0.0:
                continue
            for j in range(p):
                beta[j] -= pa[j] * viol / den     # β ← β − P a (aᵀβ − b)/(aᵀ P a)
            moved = True
            count += 1
        if not moved:
            break
    return count


@njit(cache=True, nogil=True)
def _rows_dot(MZ, q, hw, out):
    """``out = Σ_i q[i] MZ[i, :]`` over the slots ``[0, hw)``; register accumulators for ≤ 6 columns
    (the regressors: e, v_m, −σ_p, −σ_n, 1), so the sweep is not a chain of stores."""
    p = MZ.shape[1]
    if p > 6:
        for j in range(p):
            out[j] = 0.0
        for i in range(hw):
            for j in range(p):
                out[j] += q[i] * MZ[i, j]
        return
    a0 = a1 = a2 = a3 = a4 = a5 = 0.0
    for i in range(hw):
        qi = q[i]
        a0 += qi * MZ[i, 0]
        a1 += qi * MZ[i, 1]
        if p > 2:
            a2 += qi * MZ[i, 2]
            if p > 3:
                a3 += qi * MZ[i, 3]
                if p > 4:
                    a4 += qi * MZ[i, 4]
                    if p > 5:
                        a5 += qi * MZ[i, 5]
    out[0] = a0
    out[1] = a1
    if p > 2:
        out[2] = a2
    if p > 3:
        out[3] = a3
    if p > 4:
        out[4] = a4
    if p > 5:
        out[5] = a5


@njit(cache=True, nogil=True)
def _rows_axpy(MZ, h, c, zt, hw):
    """``MZ[i, :] += c h[i] z̃`` for the slots ``[0, hw)`` (z̃ held in registers for ≤ 6 columns)."""
    p = MZ.shape[1]
    if p > 6:
        for i in range(hw):
            hi = c * h[i]
            for j in range(p):
                MZ[i, j] += zt[j] * hi
        return
    z0 = zt[0]
    z1 = zt[1]
    z2 = zt[2] if p > 2 else 0.0
    z3 = zt[3] if p > 3 else 0.0
    z4 = zt[4] if p > 4 else 0.0
    z5 = zt[5] if p > 5 else 0.0
    for i in range(hw):
        hi = c * h[i]
        MZ[i, 0] += z0 * hi
        MZ[i, 1] += z1 * hi
        if p > 2:
            MZ[i, 2] += z2 * hi
            if p > 3:
                MZ[i, 3] += z3 * hi
                if p > 4:
                    MZ[i, 4] += z4 * hi
                    if p > 5:
                        MZ[i, 5] += z5 * hi



@njit(cache=True, nogil=True)
def joint_arm(st, bs, x, out):
    """Tracker steps 1–2 at ``x`` (``_krlst_core.arm``) and the same on the shadow means.

    ``M_Z ← √λ M_Z`` (the forgetting of μ, eq. 2.19, applied to the scale of the stored
    means) and ``ẑ = M_Zᵀ q`` (the GP's prediction of z at x, eq. 2.17 applied to the
    regressors), armed in ``bs.zhat``. ``out[A_MEAN]`` becomes the prediction of f at x given
    β̂: the tracker's ``ŷ`` (for ``β_trk``, still in ``st.fst[F_YM]``) minus ``ẑᵀ(β̂ − β_trk)``.

    Tracker-side contract (what this relies on in :mod:`kernels._krlst_core`): after ``arm``,
    ``P[P_Q]`` holds ``q = Q k_t`` and ``P[P_H]`` holds ``h = Σ q`` over the slots ``[0, hw)``
    (zero on free slots), ``fst[F_YM], fst[F_SF2], fst[F_SY2]`` the armed ``ŷ, σ_f², σ_y²``
    and ``fst[F_S02]`` the signal power; the new basis goes to the free slot ``order[n]``;
    after ``update`` a reduced step (``O_REDUCED``) leaves that slot free, and a pruning step
    (``O_REMOVED ≥ 0``) moves the new basis into the pruned one's slot ``order[n − 1]`` and
    frees ``order[n]``; μ is stored unscaled in the slots and ``P[P_H]`` is not touched by
    ``update``.
    """
    st = core.unowned(st)
    n = st.ist[core.I_N]
    core.arm(st, x, out)
    bs.cnt[C_ARMS] += 1
    MZ = bs.MZ
    zhat = bs.zhat
    w = zhat.shape[0]                             # the p regressors and the instrument
    for j in range(w):
        zhat[j] = 0.0
    if n == 0:
        return
    hw = st.ist[core.I_HW]
    c = bs.sst[S_SCALE] * math.sqrt(st.fst[core.F_LAM])  # M_Z ← √λ M_Z (on the scale)
    if c < SCALE_FLOOR:
        for i in range(hw):
            for j in range(w):
                MZ[i, j] *= c
        c = 1.0
    bs.sst[S_SCALE] = c
    _rows_dot(MZ, st.P[core.P_Q], hw, zhat)     # Σ q_i M_Z[i, :]
    corr = 0.0
    beta = bs.beta
    btrk = bs.beta_trk
    for j in range(w):
        zhat[j] *= c                              # ẑ = M_Zᵀ q
    for j in range(beta.shape[0]):
        corr += zhat[j] * (beta[j] - btrk[j])
    out[core.A_MEAN] -= corr                      # f̂(x | β̂) = ŷ(β_trk) − ẑᵀ(β̂ − β_trk)


@njit(cache=True, nogil=True)
def rebase(st, bs):
    """Re-express the tracker's mean with β̂: ``μ ← μ − M_Z (β̂ − β_trk)``, ``β_trk ← β̂`` (eq. 6)."""
    beta = bs.beta
    btrk = bs.beta_trk
    MZ = bs.MZ
    p = beta.shape[0]
    d = bs.vec[V_X]
    c = bs.sst[S_SCALE]
    moved = False
    for j in range(p):
        d[j] = c * (beta[j] - btrk[j])
        if d[j] != 0.0:
            moved = True
        btrk[j] = beta[j]
    bs.cnt[C_SINCE_REBASE] = 0
    if not moved:
        return
    mu = st.mu
    for i in range(st.ist[core.I_HW]):
        acc = 0.0
        for j in range(p):
            acc += MZ[i, j] * d[j]
        mu[i] -= acc


@njit(cache=True, nogil=True)
def joint_update(st, bs, z, y, gate, out, bout):
    """Tracker steps 3–5 with the residual of ``β_trk``, the shadow update, then β (2)–(7).

    ``z``: the regressor ``z(k)`` of the armed sample; ``y = v_m(k+1)``; ``gate``: the
    caller allows learning β from this sample (chain intact, not stale); the warm-up
    (no learning during the first ``warmup`` trained samples, default the budget M) and
    the motion gate ``|v_m(k)| > Ω`` are applied here. ``out`` receives the
    tracker's step (``_krlst_core`` ``O_*`` layout: its filtered value goes with ``β_trk``),
    ``bout`` the named outputs :data:`BOUT` (``filtered`` re-expressed with the new β̂).
    Returns False (nothing done) when no prediction is armed.
    """
    st = core.unowned(st)
    ist = st.ist
    fst = st.fst
    if ist[core.I_ARMED] == 0:
        return False
    beta = bs.beta
    MZ = bs.MZ
    zhat = bs.zhat
    par = bs.par
    cnt = bs.cnt
    vec = bs.vec
    p = beta.shape[0]
    zt = vec[V_ZT]
    zeta = vec[V_ZETA]
    n = ist[core.I_N]
    hw = ist[core.I_HW]
    s = st.order[n]                               # the slot the new basis goes to
    sy2 = fst[core.F_SY2]
    sf2 = fst[core.F_SF2]
    s02 = fst[core.F_S02]
    h = st.P[core.P_H]
    btrk = bs.beta_trk
    base = 0.0
    base_trk = 0.0
    shift = 0.0
    for j in range(p):
        base += beta[j] * z[j]
        base_trk += btrk[j] * z[j]
        zt[j] = z[j] - zhat[j]                    # z̃ = z − ẑ
        zeta[j] = zt[j]
        shift += zt[j] * (beta[j] - btrk[j])
    # instrument for the measured velocity (eq. 8). Velocity loop: the velocity the model simulates from
    # the command alone, v_sim(k+1) = β₀ᵀz(v_ref(k), v_sim(k)) — free of the noise and of the disturbance
    # (a cutting force excites v_m at the tooth frequency; its prediction errors must not teach the
    # inertia), with its own shadow mean (column p of M_Z); restarted from v_m after a break of the chain.
    # Force input (u is the loop's reaction to the disturbance too): the model's one-step prediction
    # v̂(k), free of the noise; valid only right after the arm that followed it
    zx = bs.zx
    form_force = bs.lay[L_FORM] == 1
    vsim = z[1]
    if not form_force:
        if cnt[C_VSIM_ARM] == cnt[C_ARMS]:
            vsim = bs.sst[S_VSIM]
        zx[p] = vsim - zhat[p]
        if par[P_IV] != 0.0:
            zeta[1] = zx[p]                       # ζ̃ = ζ − ẑ_ζ with ζ = z, v_m(k) → v_sim(k)
    else:
        zx[p] = 0.0
        if par[P_IV] != 0.0 and cnt[C_VHAT_ARM] == cnt[C_ARMS]:
            zeta[1] = bs.sst[S_VHAT] - zhat[1]    # ζ̃ = ζ − ẑ with ζ = z, v_m(k) → v̂(k)
    for j in range(p):
        zx[j] = zt[j]
    resid_trk = y - base_trk                      # what the tracker trains on (its mean goes with β_trk)
    resid = y - base                              # r = y − β̂ᵀz (eq. 2.13)
    e = resid_trk - fst[core.F_YM] - shift        # e = y − β̂ᵀz − f̂(β̂) = ỹ − β̂ᵀz̃
    bs.sst[S_VHAT] = y - e                        # v̂(k+1) = β̂ᵀz(k) + f̂(k), before seeing y
    cnt[C_VHAT_ARM] = cnt[C_ARMS] + 1
    # shadow means (stored / scale c), the mean part of eq. 2.14 for every regressor column
    inv_sy2 = 1.0 / sy2
    inv_c = 1.0 / bs.sst[S_SCALE]
    w = p + 1
    _rows_axpy(MZ, h, inv_sy2 * inv_c, zx, hw)    # M_Z ← [M_Z; ẑ] + z̃/σ_y² [h; σ_f²]
    for j in range(w):
        MZ[s, j] = (zhat[j] + zx[j] * inv_sy2 * sf2) * inv_c
    core.update(st, resid_trk, out)
    if out[core.O_REDUCED] != 0.0:                # reduced update: the new basis was dropped
        for j in range(w):
            MZ[s, j] = 0.0
    elif out[core.O_REMOVED] >= 0.0:              # pruned: the new basis took the pruned one's slot
        t = st.order[ist[core.I_N] - 1]
        for j in range(w):
            MZ[t, j] = MZ[s, j]
            MZ[s, j] = 0.0
    R = s02 * sy2                                 # R = s0² σ_y²
    bout[B_RESID] = resid
    bout[B_INNOV] = e
    bout[B_VAR] = R
    bout[B_NU] = e / math.sqrt(R) if n > 0 and R > 0.0 else np.nan
    bout[B_WEIGHT] = 1.0
    bout[B_LEARNED] = 0.0
    ztn = 0.0
    for j in range(p):
        ztn += zt[j] * zt[j]
    bout[B_ZTN] = math.sqrt(ztn)
    if par[P_ENABLED] != 0.0 and n > 0 and R > 0.0:
        _beta_step(bs, z, e, R, gate, bout)
    if not form_force:                            # (8) the simulation's next step, with the model file's β₀
        zs = vec[V_SIM]                           # (stable by the validity rules; β̂ would feed back on itself)
        # np.bool_, not a literal False: one compiled regressor
        regressor(np.bool_(False), bs.lay[L_ISP], bs.lay[L_ISN], bs.lay[L_IONE], par[P_OMEGA], z[0], vsim, zs)
        acc = 0.0
        b0 = bs.beta0
        for j in range(p):
            acc += b0[j] * zs[j]
        bs.sst[S_VSIM] = acc
        cnt[C_VSIM_ARM] = cnt[C_ARMS] + 1
    # the filtered f at x(k) given β̂: f_filt(β_trk) − z_filtᵀ(β̂ − β_trk), z_filt = ẑ + σ_f² z̃/σ_y²
    filtered = out[core.O_FILT]
    for j in range(p):
        filtered -= (zhat[j] + sf2 * zt[j] * inv_sy2) * (beta[j] - btrk[j])
    bout[B_FILTERED] = filtered
    every = bs.lay[L_REBASE]
    if every > 0:
        cnt[C_SINCE_REBASE] += 1
        if cnt[C_SINCE_REBASE] >= every:
            rebase(st, bs)                        # (6), amortised: μ ← μ − M_Z (β̂ − β_trk)
    return True


@njit(cache=True, nogil=True)
def _beta_step(bs, z, e, R, gate, bout):
    """Steps (2)–(5) and (7) for one trained sample (``e``: innovation given β̂, ``R = s0²σ_y²``)."""
    beta = bs.beta
    par = bs.par
    cnt = bs.cnt
    vec = bs.vec
    C = bs.cov
    p = beta.shape[0]
    zt = vec[V_ZT]
    zeta = vec[V_ZETA]
    g = vec[V_G]
    row = vec[V_TMP]
    cnt[C_SEEN] += 1
    omega = par[P_OMEGA]
    vk = z[1]
    d = 1 if vk > omega else (-1 if vk < -omega else 0)   # direction of motion (0: dead band)
    # learn only in motion, and not from the first sample of a run of motion (:mod:`kernels.beta_tracker`)
    learn = gate and cnt[C_SEEN] > par[P_WARMUP] and d != 0 and d == cnt[C_DIR] and abs(vk) > par[P_MINSPEED]
    cnt[C_DIR] = d
    # ---- (3) gain direction and the normalised innovation ---------------------------------------
    ztg = _gain_direction(C, zt, zeta, g, row)
    Sfull = R + ztg                               # S = R + z̃ᵀ P z̃
    nu = e / math.sqrt(Sfull)
    bout[B_VAR] = Sfull
    bout[B_NU] = nu
    # redescending cut: |ν| ≥ reject — an abrupt disturbance the tracker could not foresee;
    # learn nothing from it (nor, with hold > 0, from the ``hold`` samples after it)
    if abs(nu) >= par[P_REJECT]:
        cnt[C_QUIET] = 0
    else:
        cnt[C_QUIET] += 1
    if learn and (abs(nu) >= par[P_REJECT] or cnt[C_QUIET] <= par[P_HOLD]):
        learn = False
        cnt[C_REJECTED] += 1
    if not learn:
        cnt[C_GATED] += 1
        return
    if bs.lay[L_ISP] >= 0 and bs.lay[L_IONE] >= 0:
        # (3') a moving sample says nothing about the rest direction d = e_sp + e_sn + e_one (zᵀd = 0 for
        # every z in motion); z̃ = z − ẑ has a component along d only through the tracker's memory of
        # samples at rest, which β does not learn from: learn with z̃, ζ̃ off d (:mod:`kernels.beta_tracker`)
        zt = _off_rest(zt, vec[V_ZTR], bs.lay)
        zeta = _off_rest(zeta, vec[V_ZETAR], bs.lay)
        ztg = _gain_direction(C, zt, zeta, g, row)
    # ---- (4) Huber weight, (5) update ------------------------------------------------------------
    c = par[P_HUBER]
    w = 1.0
    if abs(nu) > c:
        w = c / abs(nu)
        cnt[C_DOWNWEIGHTED] += 1
    # (9) the fast inertia estimate: δ = Σ ζ_J e/R ÷ Σ ζ_J s_J/R over a memory of FAST_MEMORY, with
    # s_J = z̃ᵀ∂β/∂J and ζ_J = ζ̃ᵀ∂β/∂J — an instrumental-variable estimate of the inertia's change since β̂,
    # unweighted: the samples that carry an abrupt change are the ones Huber's weight would discount
    sj = 0.0
    cj = 0.0
    dirj = bs.dirj
    for i in range(p):
        sj += zt[i] * dirj[i]
        cj += zeta[i] * dirj[i]
    sst = bs.sst
    lf = par[P_FASTLAM]
    sst[S_FJN] = lf * sst[S_FJN] + cj * e / R
    sst[S_FJD] = lf * sst[S_FJD] + cj * sj / R
    sst[S_FJV] = lf * sst[S_FJV] + cj * cj / R
    sst[S_FJW] = lf * sst[S_FJW] + 1.0
    Rw = R / w
    den = 1.0 / (Rw + ztg)
    coef = e * den
    meat = (w * e / R) ** 2                       # empirical score² (Huber–White sandwich); model-based: R/R_w²
    psi = bs.psi
    for i in range(p):
        beta[i] += g[i] * coef                    # β̂ ← β̂ + Λ⁻¹ζ̃ e / (R_w + z̃ᵀΛ⁻¹ζ̃)
        gi = g[i] * den
        for j in range(p):
            C[i, j] -= gi * row[j]                # Λ⁻¹ ← Λ⁻¹ − Λ⁻¹ζ̃ z̃ᵀΛ⁻¹ / (R_w + z̃ᵀΛ⁻¹ζ̃)   (Λ += ζ̃z̃ᵀ/R_w)
            psi[i, j] += zeta[i] * zeta[j] * meat  # Ψ ← Ψ + ζ̃ ζ̃ᵀ R / R_w²
    cnt[C_SINCE_FORGET] += 1
    if cnt[C_SINCE_FORGET] >= FORGET_EVERY:
        _forget(bs)                               # (2) for the last FORGET_EVERY learning samples
        cnt[C_SINCE_FORGET] = 0
    # ---- (7) physical constraints -------------------------------------------------------------
    viol = False
    cons = bs.cons
    for r in range(cons.shape[0]):
        a = -cons[r, p]
        for j in range(p):
            a += cons[r, j] * beta[j]
        if a > 0.0:
            viol = True
    if viol:
        cnt[C_PROJECTED] += _project(bs, zeta, g, row, vec[V_X])
    bout[B_WEIGHT] = w
    bout[B_LEARNED] = 1.0
    cnt[C_UPDATES] += 1


@njit(cache=True, nogil=True, inline="always")
def _gain_direction(C, zt, zeta, g, row):
    """Eq. (3): ``g = Λ⁻¹ζ̃``, ``row = z̃ᵀΛ⁻¹`` (into ``g``, ``row``; ``C`` holds Λ⁻¹); returns
    ``s = z̃ᵀΛ⁻¹ζ̃`` clipped at 0 (``= z̃ᵀPz̃`` without instrument)."""
    p = g.shape[0]
    s = 0.0
    for i in range(p):
        gi = 0.0
        ri = 0.0
        for j in range(p):
            gi += C[i, j] * zeta[j]               # g = Λ⁻¹ ζ̃
            ri += zt[j] * C[j, i]                 # rowᵀ = z̃ᵀ Λ⁻¹
        g[i] = gi
        row[i] = ri
        s += zt[i] * gi                           # z̃ᵀ Λ⁻¹ ζ̃
    return s if s > 0.0 else 0.0


@njit(cache=True, nogil=True, inline="always")
def _off_rest(x, out, lay):
    """``out = x − (xᵀd/3) d`` with ``d = e_sp + e_sn + e_one`` (the rest direction); returns ``out``."""
    isp, isn, ione = lay[L_ISP], lay[L_ISN], lay[L_IONE]
    for j in range(x.shape[0]):
        out[j] = x[j]
    m = (x[isp] + x[isn] + x[ione]) / 3.0
    out[isp] -= m
    out[isn] -= m
    out[ione] -= m
    return out


@njit(cache=True, nogil=True)
def regressor(form_force, i_sp, i_sn, i_one, omega, e, v, z):
    """``z(k)`` of method §2 into ``z``: ``[e, v, −σ_p(v), −σ_n(v), 1]`` with the columns present."""
    z[0] = e
    z[1] = v
    if i_sp >= 0:
        z[i_sp] = -1.0 if v > omega else 0.0
        z[i_sn] = -1.0 if v < -omega else 0.0
    if i_one >= 0:
        z[i_one] = 1.0



@njit(cache=True, nogil=True)
def track_joint(fbuf, ibuf, bfbuf, bibuf, X, e, v, gate, resume, out, bout, zbuf, rows):
    """Offline loop over one uninterrupted stream (benchmarks, tests): at sample ``j ≥ 1`` update
    with ``(z(j−1), v(j))`` (β learns where ``gate[j]``), then arm at ``X[j]`` (the tracker input,
    ``(n, d)``).

    ``resume``: sample 0 is the last sample of the previous call, already armed (its row
    is left NaN). ``rows[j]``: the columns :data:`~kernels.beta_layout.JOINT_ROWS` (signal units).
    """
    st = core.unowned(core.state_of(fbuf, ibuf))
    bs = beta_state_of(bfbuf, bibuf)
    form_force = bs.lay[L_FORM] == 1
    i_sp, i_sn, i_one = bs.lay[L_ISP], bs.lay[L_ISN], bs.lay[L_IONE]
    omega = bs.par[P_OMEGA]
    for j in range(X.shape[0]):
        r = rows[j]
        for c in range(r.shape[0]):
            r[c] = np.nan
        if j > 0:
            regressor(form_force, i_sp, i_sn, i_one, omega, e[j - 1], v[j - 1], zbuf)
            if joint_update(st, bs, zbuf, v[j], gate[j], out, bout):
                r[J_LEARNED] = bout[B_LEARNED]
                r[J_NU] = bout[B_NU]
                r[J_RESID] = bout[B_RESID]
                r[J_FILTERED] = bout[B_FILTERED]
                r[J_WEIGHT] = bout[B_WEIGHT]
        if j == 0 and resume:
            continue
        was_empty = st.ist[core.I_N] == 0
        joint_arm(st, bs, X[j], out)
        r[J_FNEXT] = out[core.A_MEAN]
        r[J_FNEXTVAR] = np.nan if was_empty else out[core.A_SF2] * st.fst[core.F_S02]


@njit(cache=True, nogil=True)
def replay_joint(fbuf, ibuf, bfbuf, bibuf, X, exo, v, target, x_now, out, bout, zbuf):
    """Rebuild a fresh tracker and its shadow means from recorded samples (:func:`replay_joint_rows`),
    then arm at ``x_now``."""
    replay_joint_rows(fbuf, ibuf, bfbuf, bibuf, X, exo, v, target, out, bout, zbuf)
    joint_arm(core.unowned(core.state_of(fbuf, ibuf)), beta_state_of(bfbuf, bibuf), x_now, out)


@njit(cache=True, nogil=True)
def replay_joint_rows(fbuf, ibuf, bfbuf, bibuf, X, exo, v, target, out, bout, zbuf):
    """For each recorded sample ``k``, arm at ``X[k]`` and learn ``(z(exo[k], v[k]), target[k])``
    without learning β (the caller has switched β's learning off). The samples need not be
    consecutive: each carries its own regressor and target (``target[k] = v_m`` of the sample after
    ``k``). Two calls on consecutive parts of a record do what one call on all of it does."""
    st = core.unowned(core.state_of(fbuf, ibuf))
    bs = beta_state_of(bfbuf, bibuf)
    form_force = bs.lay[L_FORM] == 1
    i_sp, i_sn, i_one = bs.lay[L_ISP], bs.lay[L_ISN], bs.lay[L_IONE]
    omega = bs.par[P_OMEGA]
    for k in range(X.shape[0]):
        joint_arm(st, bs, X[k], out)
        regressor(form_force, i_sp, i_sn, i_one, omega, exo[k], v[k], zbuf)
        joint_update(st, bs, zbuf, target[k], np.bool_(False), out, bout)   # not a literal: one joint_update


@njit(cache=True, nogil=True)
def joint_arm_buffers(fbuf, ibuf, bfbuf, bibuf, x, out):
    """:func:`joint_arm` on the base buffers of the tracker and of the β state."""
    joint_arm(core.state_of(fbuf, ibuf), beta_state_of(bfbuf, bibuf), x, out)


@njit(cache=True, nogil=True)
def joint_update_buffers(fbuf, ibuf, bfbuf, bibuf, z, y, gate, out, bout):
    """:func:`joint_update` on the base buffers of the tracker and of the β state."""
    return joint_update(core.state_of(fbuf, ibuf), beta_state_of(bfbuf, bibuf), z, y, gate, out, bout)


@njit(cache=True, nogil=True)
def rebase_buffers(fbuf, ibuf, bfbuf, bibuf):
    """:func:`rebase` on the base buffers."""
    rebase(core.state_of(fbuf, ibuf), beta_state_of(bfbuf, bibuf))
